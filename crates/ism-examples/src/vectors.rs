//! Broken files for `spec/vectors/reader/`: each is a valid model (or its bytes) with one defect,
//! and the rule a conforming reader must report for it.

use std::path::{Path, PathBuf};

use ism_format::builder::StageBuilder;
use ism_format::io::{self, WriteOptions, HEADER_LEN};
use ism_format::{Encoding, JsonValue, Model, Rule, Stage, StageKind, VertexMap};

use crate::{kuhn_grid_2d, Aabb};

/// One broken file.
#[derive(Clone, Debug)]
pub struct ReaderVector {
    /// File stem, e.g. `truncated`.
    pub name: &'static str,
    /// Encoding the bytes claim (its conventional extension names the file).
    pub encoding: Encoding,
    /// The file's bytes.
    pub bytes: Vec<u8>,
    /// The rule the reader must report first.
    pub rule: Rule,
}

impl ReaderVector {
    /// The file name, `NAME.<ext>`.
    pub fn file_name(&self) -> String {
        format!("{}.{}", self.name, self.encoding.extension())
    }
}

/// A single positive triangle with one vertex inside.
fn triangle() -> Model {
    let mut m = Model::new(2);
    m.vertices = vec![0.0, 0.0, 1.0, 0.0, 0.0, 1.0];
    m.simplices = vec![0, 1, 2];
    m.values = vec![-1.0, 1.0, 1.0];
    m
}

/// The 2 × 2 Kuhn grid of `[−1, 1]²` (vertex ids 0..9, vertex 4 at the centre and inside).
fn grid() -> Model {
    kuhn_grid_2d(2, 2, Aabb::cube(-1.0, 1.0), |p| {
        p[0] * p[0] + p[1] * p[1] - 0.25
    })
    .expect("fixed, valid grid")
}

fn with_stage(stage: Stage) -> Model {
    let mut m = grid();
    m.stages.push(stage);
    m
}

fn encode(model: &Model, encoding: Encoding) -> Vec<u8> {
    io::to_vec(
        model,
        encoding,
        WriteOptions {
            pretty: encoding == Encoding::Json,
            json_in_container: false,
        },
    )
    .expect("vector models encode")
}

/// Rewrites the header's CRC-32 after a deliberate header change, so only that change is wrong.
fn reseal_header(bytes: &mut [u8]) {
    let crc = crc32fast::hash(&bytes[..28]);
    bytes[28..32].copy_from_slice(&crc.to_le_bytes());
}

/// Rewrites payload length and both CRCs after a deliberate payload change.
fn reseal_payload(bytes: &mut [u8]) {
    let len = (bytes.len() - HEADER_LEN) as u64;
    bytes[16..24].copy_from_slice(&len.to_le_bytes());
    let crc = crc32fast::hash(&bytes[HEADER_LEN..]);
    bytes[24..28].copy_from_slice(&crc.to_le_bytes());
    reseal_header(bytes);
}

fn json_text(value: serde_json::Value) -> Vec<u8> {
    let mut out = serde_json::to_vec_pretty(&value).expect("plain JSON");
    out.push(b'\n');
    out
}

fn json_of(model: &Model) -> serde_json::Value {
    serde_json::to_value(model).expect("models are plain JSON")
}

/// Every reader vector, in a fixed order.
pub fn reader_vectors() -> Vec<ReaderVector> {
    use Encoding::{Binary as B, Json as J, MessagePack as M};
    let mut v = Vec::new();
    let mut push = |name, encoding, bytes, rule| {
        v.push(ReaderVector {
            name,
            encoding,
            bytes,
            rule,
        })
    };

    // Container (spec §7).
    let good_b = encode(&grid(), B);
    let good_m = encode(&grid(), M);
    push(
        "truncated-binary",
        B,
        good_b[..good_b.len() - 10].to_vec(),
        Rule::Truncated,
    );
    push(
        "truncated-header",
        M,
        good_m[..20].to_vec(),
        Rule::Truncated,
    );
    let mut flipped = good_m.clone();
    let mid = HEADER_LEN + (flipped.len() - HEADER_LEN) / 2;
    flipped[mid] ^= 0x10;
    push(
        "bit-flipped-payload-msgpack",
        M,
        flipped,
        Rule::ChecksumMismatch,
    );
    let mut flipped = good_b.clone();
    let mid = HEADER_LEN + (flipped.len() - HEADER_LEN) / 2;
    flipped[mid] ^= 0x01;
    push(
        "bit-flipped-payload-binary",
        B,
        flipped,
        Rule::ChecksumMismatch,
    );
    let mut bad = good_b.clone();
    bad[29] ^= 0xFF;
    push("bad-header-crc", B, bad, Rule::ChecksumMismatch);
    let mut bad = good_b.clone();
    bad[17] ^= 0x01;
    push("bit-flipped-header", B, bad, Rule::ChecksumMismatch);
    let mut bad = good_b.clone();
    bad[1] = b'J';
    push("wrong-magic", B, bad, Rule::BadMagic);
    push(
        "not-ism",
        J,
        b"solid cube\nendsolid cube\n".to_vec(),
        Rule::BadMagic,
    );
    let mut bad = good_b.clone();
    bad[8..10].copy_from_slice(&2u16.to_le_bytes());
    reseal_header(&mut bad);
    push("newer-major-container", B, bad, Rule::UnsupportedVersion);
    let mut newer = grid();
    newer.version = "2.0".into();
    push(
        "newer-major-json",
        J,
        encode(&newer, J),
        Rule::UnsupportedVersion,
    );
    push(
        "newer-major-new-shape",
        J,
        json_text(
            serde_json::json!({"version": "2.0", "dimension": 2, "mesh": {"points": [0, 0, 1, 0, 0, 1]}}),
        ),
        Rule::UnsupportedVersion,
    );
    let mut bad = good_b.clone();
    bad[12] = 9;
    reseal_header(&mut bad);
    push("unknown-encoding", B, bad, Rule::UnknownEncoding);
    let mut bad = good_b.clone();
    bad[13] = 1;
    reseal_header(&mut bad);
    push("reserved-header-byte", B, bad, Rule::Malformed);
    let mut bad = good_b.clone();
    bad[16..24].copy_from_slice(&(1u64 << 62).to_le_bytes());
    reseal_header(&mut bad);
    push("huge-payload-length", B, bad, Rule::LimitExceeded);
    push(
        "huge-sequence-length",
        B,
        huge_binary_length(),
        Rule::LimitExceeded,
    );
    push(
        "huge-array-length",
        M,
        huge_msgpack_length(),
        Rule::Malformed,
    );
    let mut minor = grid();
    minor.version = "1.1".into();
    let mut bad = encode(&minor, M);
    bad[10..12].copy_from_slice(&0u16.to_le_bytes());
    reseal_header(&mut bad);
    push("version-mismatch", M, bad, Rule::VersionMismatch);
    let mut bad = good_b.clone();
    bad.extend_from_slice(b"\0\0\0\0");
    push("trailing-data", B, bad, Rule::TrailingData);
    let text = encode(&grid(), J);
    push(
        "truncated-json",
        J,
        text[..text.len() / 2].to_vec(),
        Rule::Malformed,
    );
    let mut missing = json_of(&grid());
    missing.as_object_mut().expect("object").remove("values");
    push("missing-member", J, json_text(missing), Rule::Malformed);
    let mut wrong_type = json_of(&grid());
    wrong_type["simplices"][3] = serde_json::json!(-1);
    push("negative-index", J, json_text(wrong_type), Rule::Malformed);

    // Non-finite numbers: JSON cannot hold them, so these use MessagePack and binary.
    let mut m = grid();
    m.vertices[3] = f64::NAN;
    push("nan-vertex", B, encode(&m, B), Rule::VertexArray);
    let mut m = grid();
    m.values[0] = f64::INFINITY;
    push("inf-value", M, encode(&m, M), Rule::ValueArray);
    let mut m = grid();
    m.level = f64::NAN;
    push("nan-level", B, encode(&m, B), Rule::Level);
    let m = with_stage(
        StageBuilder::bezier(2)
            .face(&[0, 1], &[f64::NAN, 0.5], &[])
            .build(),
    );
    push("nan-point", M, encode(&m, M), Rule::NonFinite);
    let m = with_stage(
        StageBuilder::rational(2)
            .face(&[0, 1], &[0.5, 0.5], &[f64::INFINITY])
            .build(),
    );
    push("inf-weight", B, encode(&m, B), Rule::NonFinite);

    // Complex and values (spec §2–3).
    let mut m = triangle();
    m.dimension = 4;
    push("dimension-4", J, encode(&m, J), Rule::Dimension);
    let mut m = triangle();
    m.vertices.push(0.5);
    push("vertex-count", J, encode(&m, J), Rule::VertexArray);
    let mut m = triangle();
    m.simplices.clear();
    push("no-simplices", J, encode(&m, J), Rule::SimplexArray);
    let mut m = grid();
    m.simplices[4] = 9;
    push("index-out-of-range", J, encode(&m, J), Rule::IndexRange);
    let mut m = triangle();
    m.simplices = vec![0, 1, 1];
    push("repeated-index", J, encode(&m, J), Rule::RepeatedIndex);
    let mut m = triangle();
    m.simplices = vec![0, 2, 1];
    push("inverted-simplex", J, encode(&m, J), Rule::Inverted);
    let mut m = triangle();
    m.vertices = vec![0.0, 0.0, 1.0, 0.0, 2.0, 0.0];
    push("degenerate-simplex", J, encode(&m, J), Rule::Degenerate);
    let mut m = triangle();
    m.simplices = vec![0, 1, 2, 1, 2, 0];
    push(
        "duplicate-simplex",
        J,
        encode(&m, J),
        Rule::DuplicateSimplex,
    );
    let mut m = Model::new(2);
    m.vertices = vec![0.0, 0.0, 1.0, 0.0, 0.5, 1.0, 0.5, -1.0, 0.5, 2.0];
    m.simplices = vec![0, 1, 2, 1, 0, 3, 0, 1, 4];
    m.values = vec![-1.0, 1.0, 1.0, 1.0, 1.0];
    push("facet-shared-by-3", J, encode(&m, J), Rule::FacetOvershared);
    let mut m = Model::new(2);
    m.vertices = vec![0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.3, 0.5];
    m.simplices = vec![0, 1, 2, 0, 1, 3];
    m.values = vec![-1.0, 1.0, 1.0, 1.0];
    push("overlapping-neighbours", J, encode(&m, J), Rule::Overlap);
    let mut m = triangle();
    m.values.pop();
    push("value-count", J, encode(&m, J), Rule::ValueArray);
    let mut m = triangle();
    m.values[1] = 0.0;
    push("zero-value", J, encode(&m, J), Rule::ValueZero);
    let mut m = triangle();
    m.level = 1.0;
    m.values = vec![-1.0, 1.0, 2.0];
    push("value-at-level", J, encode(&m, J), Rule::ValueAtLevel);
    let mut m = grid();
    m.extensions_used = vec!["EXT_example".into()];
    m.extensions_required = vec!["EXT_example".into()];
    m.extensions.insert(
        "EXT_example".into(),
        JsonValue(serde_json::json!({"note": "a reader must refuse this file"})),
    );
    push(
        "extension-required",
        J,
        encode(&m, J),
        Rule::ExtensionRequired,
    );
    let mut m = grid();
    m.extensions
        .insert("EXT_unlisted".into(), JsonValue(serde_json::json!({})));
    push(
        "extension-not-listed",
        J,
        encode(&m, J),
        Rule::ExtensionsListed,
    );

    // Stages (spec §5).
    push(
        "stage-degree-0",
        J,
        encode(&with_stage(Stage::identity(StageKind::Bezier, 0)), J),
        Rule::StageDegree,
    );
    push(
        "stage-degree-17",
        J,
        encode(&with_stage(Stage::identity(StageKind::Bezier, 17)), J),
        Rule::StageDegree,
    );
    let mut s = Stage::identity(StageKind::Bezier, 2);
    s.faces.push(ism_format::FaceRecord {
        face: vec![4, 0],
        points: vec![0.4, 0.6],
        weights: vec![],
    });
    push(
        "unsorted-face",
        J,
        encode(&with_stage(s), J),
        Rule::FaceSorted,
    );
    let s = StageBuilder::bezier(2)
        .face(&[0, 8], &[0.4, 0.6], &[])
        .build();
    push("not-a-face", J, encode(&with_stage(s), J), Rule::NotAFace);
    let s = StageBuilder::bezier(2)
        .face(&[0, 1], &[0.4, 0.6], &[])
        .face(&[0, 1], &[0.3, 0.7], &[])
        .build();
    push(
        "duplicate-face",
        J,
        encode(&with_stage(s), J),
        Rule::DuplicateFace,
    );
    let s = StageBuilder::bezier(3)
        .face(&[0, 1], &[0.4, 0.6, 0.5], &[])
        .build();
    push(
        "wrong-point-count",
        J,
        encode(&with_stage(s), J),
        Rule::PointCount,
    );
    let s = StageBuilder::bezier(2)
        .face(&[0, 1, 4], &[0.3, 0.3, 0.4], &[])
        .build();
    push(
        "face-owns-nothing",
        J,
        encode(&with_stage(s), J),
        Rule::PointCount,
    );
    let s = StageBuilder::rational(3)
        .face(&[0, 1], &[0.6, 0.4, 0.3, 0.7], &[2.0])
        .build();
    push(
        "wrong-weight-count",
        J,
        encode(&with_stage(s), J),
        Rule::WeightCount,
    );
    let s = StageBuilder::bezier(2)
        .face(&[0, 1], &[0.4, 0.6], &[1.5])
        .build();
    push(
        "weights-on-bezier",
        J,
        encode(&with_stage(s), J),
        Rule::WeightCount,
    );
    let mut s = StageBuilder::monotonic(2)
        .vertex_map(0, &[0.0, 0.5, 1.0])
        .build();
    s.faces.push(ism_format::FaceRecord {
        face: vec![0, 1],
        points: vec![0.4, 0.6],
        weights: vec![],
    });
    push(
        "kind-mismatch",
        J,
        encode(&with_stage(s), J),
        Rule::KindMismatch,
    );
    let s = StageBuilder::monotonic(2)
        .vertex_map(9, &[0.0, 0.5, 1.0])
        .build();
    push(
        "vertex-map-out-of-range",
        J,
        encode(&with_stage(s), J),
        Rule::VertexMapIndex,
    );
    let mut s = Stage::identity(StageKind::Monotonic, 2);
    s.vertex_maps = vec![
        VertexMap {
            vertex: 3,
            coefficients: vec![0.0, 0.5, 1.0],
        },
        VertexMap {
            vertex: 3,
            coefficients: vec![0.0, 0.4, 1.0],
        },
    ];
    push(
        "vertex-map-twice",
        J,
        encode(&with_stage(s), J),
        Rule::VertexMapIndex,
    );
    let s = StageBuilder::monotonic(2)
        .vertex_map(0, &[0.0, 1.0])
        .build();
    push(
        "coefficient-count",
        J,
        encode(&with_stage(s), J),
        Rule::CoefficientCount,
    );
    v
}

/// A binary file whose `vertices` length prefix claims 2⁶¹ numbers, with both CRCs valid.
fn huge_binary_length() -> Vec<u8> {
    let model = grid();
    let mut bytes = encode(&model, Encoding::Binary);
    // `version` (u64 length + 3 bytes), `dimension` (1 byte), four absent metadata members
    // (one tag byte each): the vertices' length prefix follows at payload offset 16.
    let at = HEADER_LEN + 8 + model.version.len() + 1 + 4;
    let stored = u64::from_le_bytes(bytes[at..at + 8].try_into().expect("8 bytes"));
    assert_eq!(
        stored as usize,
        model.vertices.len(),
        "binary layout changed: update the offset"
    );
    bytes[at..at + 8].copy_from_slice(&(1u64 << 61).to_le_bytes());
    reseal_payload(&mut bytes);
    bytes
}

/// A MessagePack file whose `vertices` array header claims 2³² − 1 elements, with both CRCs valid.
fn huge_msgpack_length() -> Vec<u8> {
    let model = grid();
    let bytes = encode(&model, Encoding::MessagePack);
    let key = b"\xa8vertices";
    let at = bytes
        .windows(key.len())
        .position(|w| w == key)
        .expect("vertices key")
        + key.len();
    // 18 numbers: an array16 header (0xdc + u16 length).
    assert_eq!(
        bytes[at], 0xdc,
        "msgpack layout changed: update the array header"
    );
    let mut out = bytes[..at].to_vec();
    out.extend_from_slice(&[0xdd, 0xff, 0xff, 0xff, 0xff]);
    out.extend_from_slice(&bytes[at + 3..]);
    reseal_payload(&mut out);
    out
}

/// What a reader reports for a vector: the first diagnostic's rule and location, as JSON
/// `{"rule": "ISM-0xx", "location": {…}}`.
///
/// # Errors
/// A message when the bytes read successfully or report a different rule than intended.
pub fn expectation(vector: &ReaderVector) -> Result<serde_json::Value, String> {
    match io::from_slice(&vector.bytes) {
        Ok(_) => Err(format!("{}: reads without error", vector.file_name())),
        Err(e) => {
            let first = e
                .diagnostics()
                .first()
                .ok_or_else(|| format!("{}: error without diagnostic: {e}", vector.file_name()))?;
            if first.rule != vector.rule {
                return Err(format!(
                    "{}: expected {}, reader reports {first}",
                    vector.file_name(),
                    vector.rule.id()
                ));
            }
            Ok(serde_json::json!({"rule": first.rule.id(), "location": first.location}))
        }
    }
}

/// Writes every vector and its `NAME.expect.json` into `dir`; returns the paths written.
///
/// # Errors
/// I/O errors, or a vector that does not fail as intended (a reader change or a generator bug).
pub fn write_reader_vectors(dir: &Path) -> Result<Vec<PathBuf>, String> {
    std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let mut written = Vec::new();
    for vector in reader_vectors() {
        let expect = expectation(&vector)?;
        let path = dir.join(vector.file_name());
        let expect_path = dir.join(format!("{}.expect.json", vector.name));
        let mut expect_text = serde_json::to_vec_pretty(&expect).map_err(|e| e.to_string())?;
        expect_text.push(b'\n');
        for (p, bytes) in [(&path, &vector.bytes), (&expect_path, &expect_text)] {
            io::write_atomic(p, |w| std::io::Write::write_all(w, bytes))
                .map_err(|e| format!("{}: {e}", p.display()))?;
            written.push(p.clone());
        }
    }
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_vector_fails_with_its_rule_and_names_are_unique() {
        let vectors = reader_vectors();
        // Stems are unique, so `NAME.expect.json` pairs with exactly one `NAME.<ext>`.
        let mut names: Vec<&str> = vectors.iter().map(|v| v.name).collect();
        names.sort();
        let before = names.len();
        names.dedup();
        assert_eq!(before, names.len(), "duplicate vector file names");
        for v in &vectors {
            let expect = expectation(v).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(expect["rule"], v.rule.id());
        }
        // Every reader-side error rule (ISM-0xx and ISM-1xx errors) has at least one vector.
        for rule in Rule::ALL {
            let id = rule.id();
            let reader_rule = id < "ISM-200" && rule.severity() == ism_format::Severity::Error;
            if reader_rule {
                assert!(
                    vectors.iter().any(|v| v.rule == *rule),
                    "no vector for {id}"
                );
            }
        }
    }

    #[test]
    fn every_truncation_of_a_valid_file_is_an_error_not_a_panic() {
        for encoding in Encoding::ALL {
            let bytes = encode(&grid(), encoding);
            for len in 0..bytes.len() {
                assert!(
                    io::from_slice(&bytes[..len]).is_err(),
                    "{encoding:?} truncated to {len} reads"
                );
            }
        }
    }
}
