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

/// The model's bytes as they are: vectors are files readers refuse, which writers do not write.
fn encode(model: &Model, encoding: Encoding) -> Vec<u8> {
    io::to_vec_unchecked(
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
        Rule::Malformed,
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
    s.faces.push_record(&ism_format::FaceRecord {
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
    s.faces.push_record(&ism_format::FaceRecord {
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
    v.extend(strictness_vectors());
    v.extend(structured_vectors());
    v
}

/// The triangle with a quadratic stage whose one record, on the edge [1, 2] with the point
/// (0.5, 0.5), the structured encoding writes by the complex: `recordForm` 1, `dims` 0b10, the
/// mask 0b100 over the edges [0,1] [0,2] [1,2], `width` 1, the integer 128 (spec §7.4.3). Its
/// structured file and the file offset of `recordForm`; `name` names the stage.
fn structured_triangle(name: Option<&str>) -> (Vec<u8>, usize) {
    let mut m = triangle();
    let mut stage = StageBuilder::bezier(2)
        .face(&[1, 2], &[0.5, 0.5], &[])
        .build();
    stage.name = name.map(str::to_string);
    m.stages.push(stage);
    let bytes = encode(&m, Encoding::Structured);
    let records = [1, 0b10, 0b100, 1, 128];
    let at = bytes
        .windows(records.len())
        .position(|w| w == records)
        .expect("the records of the stage by the complex");
    (bytes, at)
}

/// The unit square, one cube split on its diagonal, three of the four halves kept, as a structured
/// file with `complexForm` 1 (spec §7.4.3; `crates/ism-format/tests/structured.rs` writes its
/// payload byte by byte): payload offsets 10 `box`, 43 `cells`, 46 `splits`, 49 `kept`.
fn refined_square() -> Vec<u8> {
    let mut m = Model::new(2);
    m.vertices = vec![0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.5, 0.5];
    m.simplices = vec![0, 1, 4, 0, 4, 2, 4, 3, 2];
    m.values = vec![-1.0, 1.0, 1.0, 1.0, -0.5];
    let refinement = ism_format::refine::KuhnRefinement {
        domain: vec![0.0, 1.0, 0.0, 1.0],
        cells: vec![1, 1],
        splits: vec![[0, 3]],
        kept: vec![true, false, true, true],
    };
    let (bytes, refined) = io::to_vec_refined(&m, &refinement).expect("the square encodes");
    assert!(refined, "the refinement gives the square");
    assert_eq!(bytes[HEADER_LEN + 9], 1, "complexForm 1");
    bytes
}

/// The structured encoding's own errors (spec §7.4.3), each at its pointer and offset.
fn structured_vectors() -> Vec<ReaderVector> {
    let s = Encoding::Structured;
    let mut v = Vec::new();
    let mut push = |name, bytes, rule| {
        v.push(ReaderVector {
            name,
            encoding: s,
            bytes,
            rule,
        })
    };
    // `at + i` of the records set to `byte`, the checksums made valid.
    let patched = |i: usize, byte: u8| {
        let (mut bytes, at) = structured_triangle(None);
        bytes[at + i] = byte;
        reseal_payload(&mut bytes);
        bytes
    };
    let (dims, mask, width) = (1, 2, 3);
    // complexForm: the byte before the vertices' length (version, dimension, four absent
    // metadata members before it).
    let (mut form, _) = structured_triangle(None);
    let at = HEADER_LEN + 1 + 3 + 1 + 4;
    assert_eq!(form[at], 0, "structured layout changed: update the offset");
    form[at] = 2;
    reseal_payload(&mut form);
    push("structured-complex-form", form, Rule::Malformed);
    // complexForm 1 (the complex by a refined Kuhn grid) in dimension 4: at the byte.
    let (mut form, _) = structured_triangle(None);
    form[HEADER_LEN + 4] = 4;
    form[at] = 1;
    reseal_payload(&mut form);
    push("structured-refined-dimension", form, Rule::Malformed);
    // The unit square split on its diagonal (`refined_square`), one error each: a box with
    // lo = hi on axis 0 (at the box), 1000 × 1000 cubes whose kept bits the payload cannot hold
    // (at cells, before the grid is built), a pair that is no edge of a live simplex (at the
    // pair), a kept padding bit (at its byte).
    let (payload, bx, cells, splits, kept) = (HEADER_LEN, 10, 43, 46, 49);
    let square = refined_square();
    let with = |at: usize, bytes: &[u8], removed: usize| {
        let mut out = square.clone();
        out.splice(payload + at..payload + at + removed, bytes.iter().copied());
        reseal_payload(&mut out);
        out
    };
    push(
        "structured-refined-box",
        with(bx + 9, &0.0f64.to_le_bytes()[..], 8),
        Rule::Malformed,
    );
    push(
        "structured-refined-kept-bytes",
        with(cells, &[2, 0xFB, 0xE8, 0x03, 0xFB, 0xE8, 0x03], 3),
        Rule::Malformed,
    );
    push(
        "structured-refined-split",
        with(splits + 1, &[1, 2], 2),
        Rule::Malformed,
    );
    push(
        "structured-refined-kept-padding",
        with(kept, &[0b1_1101], 1),
        Rule::Malformed,
    );
    push("structured-record-form", patched(0, 2), Rule::Malformed);
    push(
        "structured-dims-above-dimension",
        patched(dims, 0b1010),
        Rule::Malformed,
    );
    push(
        "structured-mask-padding",
        patched(mask, 0b1100),
        Rule::Malformed,
    );
    push("structured-width", patched(width, 5), Rule::Malformed);
    // Width 0: the point's two f64 need 16 bytes; 15 follow the width.
    push(
        "structured-short-points",
        patched(width, 0),
        Rule::Malformed,
    );
    // The kind (three bytes before `recordForm`: kind, degree, direction, name) made monotonic.
    push(
        "structured-monotonic-dims",
        {
            let (mut bytes, at) = structured_triangle(None);
            assert_eq!(bytes[at - 4..at], [0, 2, 0, 0], "stage header");
            bytes[at - 4] = 2;
            reseal_payload(&mut bytes);
            bytes
        },
        Rule::Malformed,
    );
    // Degree 2³² − 1: C(d − 1, 1) points per edge record, refused at `width` before allocating.
    let (mut huge, at) = structured_triangle(None);
    huge.splice(at - 3..at - 2, [0xFC, 0xFF, 0xFF, 0xFF, 0xFF]);
    reseal_payload(&mut huge);
    push("structured-huge-degree", huge, Rule::Malformed);
    // The payload ends inside the mask (the stage named so that the payload still holds the
    // smallest stage, 7 bytes, and the stage count passes).
    let (mut cut, at) = structured_triangle(Some("a stage."));
    cut.truncate(at + mask);
    reseal_payload(&mut cut);
    push("structured-truncated-mask", cut, Rule::Malformed);
    v
}

/// The compact JSON text of `model` with `members` (JSON text starting with `,`) inserted before
/// the closing brace.
fn json_with(model: &Model, members: &str) -> Vec<u8> {
    let mut text = String::from_utf8(
        io::to_vec_unchecked(model, Encoding::Json, WriteOptions::default()).expect("encodes"),
    )
    .expect("UTF-8");
    assert_eq!(text.pop(), Some('}'));
    text.push_str(members);
    text.push('}');
    text.into_bytes()
}

/// A MessagePack file of `model` whose top-level map gets `entries` more entries, `bytes` appended.
fn msgpack_with(model: &Model, entries: u8, bytes: &[u8]) -> Vec<u8> {
    let mut out = encode(model, Encoding::MessagePack);
    let map = out[HEADER_LEN];
    assert!((0x80..0x90).contains(&map), "the model is a fixmap");
    out[HEADER_LEN] = map + entries;
    assert!(out[HEADER_LEN] < 0x90, "still a fixmap");
    out.extend_from_slice(bytes);
    reseal_payload(&mut out);
    out
}

/// A binary file of `model` whose payload tail (the last `cut` bytes) is replaced by `tail`.
fn binary_with_tail(model: &Model, cut: usize, tail: &[u8]) -> Vec<u8> {
    let mut out = encode(model, Encoding::Binary);
    out.truncate(out.len() - cut);
    out.extend_from_slice(tail);
    reseal_payload(&mut out);
    out
}

/// The binary `string` (and `json`) encoding: u64 length, then the bytes.
fn binary_string(text: &str) -> Vec<u8> {
    let mut out = (text.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(text.as_bytes());
    out
}

/// Nested arrays `[[…[0]…]]`, `levels` deep, as JSON text.
fn nested_json(levels: usize) -> String {
    format!("{}0{}", "[".repeat(levels), "]".repeat(levels))
}

/// One vector per decision of issue 18 (spec §7.8 and the rules it settles): each file breaks
/// exactly one rule that the spec used to leave open.
fn strictness_vectors() -> Vec<ReaderVector> {
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
    let tri = triangle();
    // MessagePack: maps with str keys only, str not bin, the model is a map (spec §7.3).
    push(
        "msgpack-integer-key",
        M,
        msgpack_with(&tri, 1, &[0x01, 0x00]),
        Rule::Malformed,
    );
    let mut array_model = encode(&tri, M);
    array_model.truncate(HEADER_LEN);
    array_model.extend_from_slice(&[0x92, 0xa3, b'1', b'.', b'0', 0x02]);
    reseal_payload(&mut array_model);
    push("msgpack-model-as-array", M, array_model, Rule::Malformed);
    let mut bin = encode(&tri, M);
    let key = b"\xa7version\xa3";
    let at = bin
        .windows(key.len())
        .position(|w| w == key)
        .expect("version key")
        + key.len()
        - 1;
    bin.splice(at..at + 1, [0xc4, 0x03]);
    reseal_payload(&mut bin);
    push("msgpack-bin-string", M, bin, Rule::Malformed);
    let mut map32 = encode(&tri, M);
    map32.splice(HEADER_LEN..HEADER_LEN + 1, [0xdf, 0xff, 0xff, 0xff, 0xff]);
    reseal_payload(&mut map32);
    push("msgpack-map32-length", M, map32, Rule::Malformed);

    // Nesting depth: at most MAX_DEPTH arrays and objects, the model being level 1 (spec §7.8).
    let too_deep = ism_format::MAX_DEPTH; // extras at level 2 .. MAX_DEPTH + 1
    push(
        "json-extras-too-deep",
        J,
        json_with(&tri, &format!(",\"extras\":{}", nested_json(too_deep))),
        Rule::Malformed,
    );
    let mut deep = b"\xa6extras".to_vec();
    deep.extend(std::iter::repeat_n(0x91u8, too_deep));
    deep.push(0xc0);
    push(
        "msgpack-extras-too-deep",
        M,
        msgpack_with(&tri, 1, &deep),
        Rule::Malformed,
    );
    push(
        "binary-extras-too-deep",
        B,
        binary_with_tail(&tri, 12, &binary_string(&nested_json(too_deep))),
        Rule::Malformed,
    );
    let mut staged = tri.clone();
    staged.stages.push(Stage::identity(StageKind::Bezier, 1));
    push(
        "binary-stage-extras-too-deep",
        B,
        {
            // The stage's extras (4 + 8 bytes), then the model's three empty sequences and extras.
            let mut tail = binary_string(&nested_json(too_deep - 2));
            tail.extend_from_slice(&[0u8; 24]);
            tail.extend_from_slice(&binary_string("null"));
            binary_with_tail(&staged, 12 + 24 + 12, &tail)
        },
        Rule::Malformed,
    );

    // json data (extras, extensions) is carried unchanged, so it must be representable unchanged
    // in every encoding (spec §2.7, §7.8).
    push(
        "json-extras-big-integer",
        J,
        json_with(&tri, ",\"extras\":[18446744073709551616]"),
        Rule::Malformed,
    );
    push(
        "json-extras-number-overflow",
        J,
        json_with(&tri, ",\"extras\":{\"x\":1e400}"),
        Rule::Malformed,
    );
    push(
        "json-extras-duplicate-key",
        J,
        json_with(&tri, ",\"extras\":{\"a\":1,\"b\":2,\"a\":3}"),
        Rule::Malformed,
    );
    let mut nan = b"\xa6extras\x91\xcb".to_vec();
    nan.extend_from_slice(&f64::NAN.to_be_bytes());
    push(
        "msgpack-extras-nan",
        M,
        msgpack_with(&tri, 1, &nan),
        Rule::Malformed,
    );
    // Binary json text is canonical (spec §7.7): `1e+16` is spelled `1e16`.
    push(
        "binary-extras-not-canonical",
        B,
        binary_with_tail(&tri, 12, &binary_string("[1e+16]")),
        Rule::Malformed,
    );
    push(
        "binary-extras-whitespace",
        B,
        binary_with_tail(&tri, 12, &binary_string("{\"a\": 1}")),
        Rule::Malformed,
    );

    // Keys unique everywhere; binary extension names strictly increasing (spec §7.4, §7.8).
    push(
        "json-duplicate-member",
        J,
        json_with(&tri, ",\"dimension\":2"),
        Rule::Malformed,
    );
    push(
        "json-extensions-duplicate-key",
        J,
        json_with(
            &tri,
            ",\"extensionsUsed\":[\"EXT_a\"],\"extensions\":{\"EXT_a\":1,\"EXT_a\":2}",
        ),
        Rule::Malformed,
    );
    let mut with_ext = tri.clone();
    with_ext.extensions_used = vec!["EXT_a".into(), "EXT_b".into()];
    let ext_entry = |name: &str, value: &str| {
        let mut out = binary_string(name);
        out.extend(binary_string(value));
        out
    };
    let extensions_tail = |entries: &[(&str, &str)]| {
        let mut out = (entries.len() as u64).to_le_bytes().to_vec();
        for (name, value) in entries {
            out.extend(ext_entry(name, value));
        }
        out.extend(binary_string("null"));
        out
    };
    push(
        "binary-extensions-unsorted",
        B,
        binary_with_tail(
            &with_ext,
            20,
            &extensions_tail(&[("EXT_b", "1"), ("EXT_a", "2")]),
        ),
        Rule::Malformed,
    );
    push(
        "binary-extensions-duplicate-key",
        B,
        binary_with_tail(
            &with_ext,
            20,
            &extensions_tail(&[("EXT_a", "1"), ("EXT_a", "2")]),
        ),
        Rule::Malformed,
    );
    let mut listed_twice = tri.clone();
    listed_twice.extensions_used = vec!["EXT_a".into(), "EXT_b".into(), "EXT_a".into()];
    push(
        "extension-listed-twice",
        J,
        encode(&listed_twice, J),
        Rule::ExtensionsListed,
    );

    // Numbers: JSON text rounds to the nearest f64; one that rounds to infinity is ISM-006 (spec §7.2).
    let text = String::from_utf8(json_with(&tri, "")).expect("UTF-8");
    push(
        "json-number-overflow",
        J,
        text.replacen("[-1.0,", "[-1e400,", 1).into_bytes(),
        Rule::Malformed,
    );
    push(
        "json-index-too-large",
        J,
        text.replacen("[0,1,2]", "[0,1,4294967296]", 1).into_bytes(),
        Rule::Malformed,
    );
    push(
        "json-index-minus-zero",
        J,
        text.replacen("[0,1,2]", "[0,1,-0]", 1).into_bytes(),
        Rule::Malformed,
    );
    push(
        "json-index-with-exponent",
        J,
        text.replacen("[0,1,2]", "[0,1,2e0]", 1).into_bytes(),
        Rule::Malformed,
    );

    // Detection and whitespace: RFC 8259 only, no byte-order mark (spec §7.5).
    let mut ff = b"\x0c".to_vec();
    ff.extend_from_slice(text.as_bytes());
    push("json-form-feed", J, ff, Rule::BadMagic);
    let mut bom = b"\xEF\xBB\xBF".to_vec();
    bom.extend_from_slice(text.as_bytes());
    push("json-bom", J, bom, Rule::BadMagic);
    let mut bom = io::to_vec_unchecked(
        &tri,
        J,
        WriteOptions {
            pretty: false,
            json_in_container: true,
        },
    )
    .expect("encodes");
    bom.splice(HEADER_LEN..HEADER_LEN, *b"\xEF\xBB\xBF");
    reseal_payload(&mut bom);
    push("checksummed-json-bom", J, bom, Rule::Malformed);

    // Optional strings are strings: `null` is not absence (spec §2.6, §7.2).
    push(
        "metadata-name-null",
        J,
        text.replacen("\"metadata\":{}", "\"metadata\":{\"name\":null}", 1)
            .into_bytes(),
        Rule::Malformed,
    );
    push(
        "stage-name-null",
        J,
        text.replacen(
            "\"stages\":[]",
            "\"stages\":[{\"kind\":\"bezier\",\"degree\":1,\"name\":null}]",
            1,
        )
        .into_bytes(),
        Rule::Malformed,
    );
    push(
        "level-null",
        J,
        text.replacen("\"level\":0.0", "\"level\":null", 1)
            .into_bytes(),
        Rule::Malformed,
    );

    // Versions: canonical decimal, no leading zeros (spec §2.1).
    push(
        "version-leading-zero",
        J,
        text.replacen("\"1.0\"", "\"01.0\"", 1).into_bytes(),
        Rule::Malformed,
    );

    // Locations are real pointers (spec §9): a text that ends inside the model.
    push("json-open-brace", J, b"{".to_vec(), Rule::Malformed);

    // Binary errors name the member and the byte (spec §7.4).
    let mut kind = encode(&staged, B);
    let pattern: &[u8] = &[
        1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0,
    ];
    let at = kind
        .windows(pattern.len())
        .position(|w| w == pattern)
        .expect("stage header")
        + 8;
    kind[at] = 7;
    reseal_payload(&mut kind);
    push("binary-bad-kind", B, kind, Rule::Malformed);
    let mut tag = encode(&tri, B);
    // version (8 + 3 bytes), dimension (1 byte): metadata.name's presence tag.
    tag[HEADER_LEN + 12] = 2;
    reseal_payload(&mut tag);
    push("binary-bad-presence-tag", B, tag, Rule::Malformed);
    let mut short = encode(&tri, B);
    // Cut inside `vertices` (its length prefix at payload offset 16), checksums made valid.
    short.truncate(HEADER_LEN + 16 + 8 + 20);
    reseal_payload(&mut short);
    push("binary-short-payload", B, short, Rule::Malformed);

    // Compact binary: canonical varints only, every varint error at its first byte (spec §7.4.1).
    let c = Encoding::Compact;
    push(
        "compact-non-minimal-varint",
        c,
        compact_vertices_length(&tri, &[0xFB, 6, 0], false),
        Rule::Malformed,
    );
    push(
        "compact-non-minimal-u64-varint",
        c,
        compact_vertices_length(&tri, &[0xFD, 6, 0, 0, 0, 0, 0, 0, 0], false),
        Rule::Malformed,
    );
    push(
        "compact-truncated-varint",
        c,
        compact_vertices_length(&tri, &[0xFC, 6, 0], true),
        Rule::Malformed,
    );
    let mut huge = vec![0xFD];
    huge.extend((1u64 << 61).to_le_bytes());
    push(
        "compact-huge-length",
        c,
        compact_vertices_length(&tri, &huge, false),
        Rule::Malformed,
    );
    push(
        "compact-varint-byte-254",
        c,
        compact_vertices_length(&tri, &[0xFE], false),
        Rule::Malformed,
    );
    push(
        "compact-varint-byte-255",
        c,
        compact_vertices_length(&tri, &[0xFF], false),
        Rule::Malformed,
    );
    let mut kind = encode(&staged, c);
    // The stage follows `level` (8 zero bytes) and the stage count 1: kind 0, degree 1.
    let at = kind[HEADER_LEN..]
        .windows(11)
        .position(|w| w == [0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 1])
        .expect("stage header")
        + HEADER_LEN
        + 9;
    kind.splice(at..at + 1, [0xFD, 0, 0, 0, 0, 1, 0, 0, 0]);
    reseal_payload(&mut kind);
    push("compact-u64-varint-in-u32", c, kind, Rule::Malformed);

    // Compressed: the uncompressed length, the xz stream and the compact payload inside, each
    // error at its location of spec §7.4.2.
    let z = Encoding::Compressed;
    let compact = encode(&tri, c)[HEADER_LEN..].to_vec();
    push(
        "compressed-short-payload",
        z,
        compressed_file(&[1, 2, 3, 4, 5]),
        Rule::Malformed,
    );
    push(
        "compressed-huge-length",
        z,
        compressed_with(1 << 62, &xz(&compact)),
        Rule::LimitExceeded,
    );
    let mut magic = xz(&compact);
    magic[0] ^= 0x01;
    push(
        "compressed-not-xz",
        z,
        compressed_with(compact.len() as u64, &magic),
        Rule::Malformed,
    );
    // The stream's last 12 bytes are its footer; the CRC64 of the block's content is the 8 bytes
    // before the index, which a one-block stream of a short payload places right after the data.
    let good = xz(&compact);
    let mut check = good.clone();
    let at = xz_check_offset(&good);
    check[at] ^= 0x01;
    push(
        "compressed-bad-check",
        z,
        compressed_with(compact.len() as u64, &check),
        Rule::Malformed,
    );
    push(
        "compressed-truncated-stream",
        z,
        compressed_with(compact.len() as u64, &good[..good.len() - 12]),
        Rule::Malformed,
    );
    push(
        "compressed-length-short",
        z,
        compressed_with(compact.len() as u64 + 1, &good),
        Rule::Malformed,
    );
    // A bomb: 16 MiB of zeros (about 2.5 kB of xz) declared as 64 bytes; refused after 65.
    push(
        "compressed-bomb",
        z,
        compressed_with(64, &xz(&vec![0u8; 16 << 20])),
        Rule::Malformed,
    );
    push(
        "compressed-dictionary-too-large",
        z,
        compressed_with(compact.len() as u64, &xz_with_dictionary_4gib(&good)),
        Rule::LimitExceeded,
    );
    let mut padded = good.clone();
    padded.extend_from_slice(&[0, 0, 0, 0]);
    push(
        "compressed-trailing-data",
        z,
        compressed_with(compact.len() as u64, &padded),
        Rule::Malformed,
    );
    let mut inner = compact_vertices_length(&tri, &[0xFB, 6, 0], false);
    let inner = inner.split_off(HEADER_LEN);
    push(
        "compressed-bad-compact",
        z,
        compressed_with(inner.len() as u64, &xz(&inner)),
        Rule::Malformed,
    );
    v
}

/// `bytes` compressed as one xz stream by the reference writer's preset.
fn xz(bytes: &[u8]) -> Vec<u8> {
    use std::io::Write;
    let mut e = liblzma::write::XzEncoder::new(Vec::new(), ism_format::compressed::WRITE_PRESET);
    e.write_all(bytes).expect("in memory");
    e.finish().expect("in memory")
}

/// The first byte of a one-block xz stream's CRC64 check (xz file format 1.2, §2.1.3 and §4):
/// the index (which starts with a zero byte, then the record count 1 as a varint) and the
/// 12-byte footer follow it; the index of one record is `size` bytes, read from the footer.
fn xz_check_offset(stream: &[u8]) -> usize {
    let footer = stream.len() - 12;
    let backward = u32::from_le_bytes(stream[footer + 4..footer + 8].try_into().expect("4 bytes"));
    let index_len = (backward as usize + 1) * 4;
    footer - index_len - 8
}

/// `stream` (one block, LZMA2) with its block header declaring the largest LZMA2 dictionary,
/// 4 GiB − 1 (property byte 40, xz file format 1.2 §5.3.1), and the header's CRC32 rewritten: a
/// decoder would need 4 GiB, which readers refuse before allocating (spec §7.4.2).
fn xz_with_dictionary_4gib(stream: &[u8]) -> Vec<u8> {
    let mut out = stream.to_vec();
    // The block header follows the 12-byte stream header; its first byte is (size / 4) − 1.
    let start = 12;
    let size = (usize::from(out[start]) + 1) * 4;
    let header = &mut out[start..start + size];
    // Filter flags of LZMA2: id 0x21, property size 1, the dictionary byte.
    let at = header
        .windows(2)
        .position(|w| w == [0x21, 0x01])
        .expect("LZMA2 filter flags")
        + 2;
    header[at] = 40;
    let crc = crc32fast::hash(&header[..size - 4]);
    header[size - 4..].copy_from_slice(&crc.to_le_bytes());
    out
}

/// A compressed container: uncompressed length `declared`, then `stream`.
fn compressed_with(declared: u64, stream: &[u8]) -> Vec<u8> {
    let mut payload = declared.to_le_bytes().to_vec();
    payload.extend_from_slice(stream);
    compressed_file(&payload)
}

/// A compressed container around `payload` as it is, both CRCs valid.
fn compressed_file(payload: &[u8]) -> Vec<u8> {
    let mut bytes = io::header(Encoding::Compressed, ism_format::FORMAT_VERSION, payload).to_vec();
    bytes.extend_from_slice(payload);
    bytes
}

/// A compact file of `model` whose `vertices` length (one byte, at payload offset 9: version, dimension,
/// four absent metadata members before it) is replaced by `with`; the payload ends there when `cut`.
fn compact_vertices_length(model: &Model, with: &[u8], cut: bool) -> Vec<u8> {
    let mut bytes = encode(model, Encoding::Compact);
    let at = HEADER_LEN + 1 + model.version.len() + 1 + 4;
    assert_eq!(
        usize::from(bytes[at]),
        model.vertices.len(),
        "compact layout changed: update the offset"
    );
    bytes.splice(at..at + 1, with.iter().copied());
    if cut {
        bytes.truncate(at + with.len());
    }
    reseal_payload(&mut bytes);
    bytes
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
