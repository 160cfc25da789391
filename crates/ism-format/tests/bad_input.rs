//! Hostile and broken input: every case gets a typed error naming the rule and the place; nothing
//! panics; nothing allocates more than a small multiple of the input.

use ism_format::builder::{ModelBuilder, StageBuilder};
use ism_format::io::{self, WriteOptions, HEADER_LEN};
use ism_format::{Encoding, Error, Model, Rule};

/// Two triangles of a square with a quadratic stage and a rational stage: exercises every array.
fn sample_model() -> Model {
    ModelBuilder::new(2)
        .name("square")
        .vertex(&[0.0, 0.0], -1.0)
        .vertex(&[1.0, 0.0], 1.0)
        .vertex(&[1.0, 1.0], 2.0)
        .vertex(&[0.0, 1.0], 0.5)
        .simplex(&[0, 1, 2])
        .simplex(&[0, 2, 3])
        .stage(
            StageBuilder::bezier(2)
                .face(&[0, 2], &[0.6, 0.4], &[])
                .build(),
        )
        .stage(
            StageBuilder::rational(3)
                .face(&[0, 1, 2], &[0.2, 0.3, 0.5], &[2.0])
                .build(),
        )
        .build()
        .unwrap()
}

fn rule_of(result: Result<ism_format::Document, Error>) -> Rule {
    match result {
        Ok(_) => panic!("expected an error"),
        Err(e) => e
            .rule()
            .unwrap_or_else(|| panic!("error without a rule: {e}")),
    }
}

#[test]
fn every_truncation_is_an_error() {
    let model = sample_model();
    for enc in Encoding::ALL {
        let bytes = io::to_vec(&model, enc, WriteOptions::default()).unwrap();
        for len in 0..bytes.len() {
            assert!(
                io::from_slice(&bytes[..len]).is_err(),
                "{enc:?} truncated to {len} bytes was accepted"
            );
        }
    }
}

#[test]
fn truncated_container_reports_truncation_with_offset() {
    let bytes = io::to_vec(&sample_model(), Encoding::Binary, WriteOptions::default()).unwrap();
    let err = io::from_slice(&bytes[..bytes.len() - 5]).unwrap_err();
    assert_eq!(err.rule(), Some(Rule::Truncated));
    assert_eq!(
        err.diagnostics()[0].location.offset,
        Some(bytes.len() as u64 - 5)
    );
    assert_eq!(rule_of(io::from_slice(&bytes[..20])), Rule::Truncated);
}

#[test]
fn every_bit_flip_in_a_container_is_detected() {
    let model = sample_model();
    for enc in [Encoding::MessagePack, Encoding::Binary] {
        let bytes = io::to_vec(&model, enc, WriteOptions::default()).unwrap();
        for i in 0..bytes.len() {
            for bit in [0u8, 3, 7] {
                let mut b = bytes.clone();
                b[i] ^= 1 << bit;
                let rule = rule_of(io::from_slice(&b));
                assert!(
                    matches!(
                        rule,
                        Rule::ChecksumMismatch
                            | Rule::BadMagic
                            | Rule::Truncated
                            | Rule::TrailingData
                    ),
                    "{enc:?} byte {i} bit {bit}: {rule:?}"
                );
            }
        }
    }
}

/// Corrupt the payload but fix the checksums, so the decoders themselves see garbage.
#[test]
fn decoders_survive_corrupt_payloads_with_valid_checksums() {
    let model = sample_model();
    for enc in Encoding::ALL {
        let payload = io::encode_payload(&model, enc, false).unwrap();
        for i in 0..payload.len() {
            for x in [0x01u8, 0x80, 0xFF] {
                let mut p = payload.clone();
                p[i] ^= x;
                let mut bytes = io::header(enc, ism_format::FORMAT_VERSION, &p).to_vec();
                bytes.extend_from_slice(&p);
                let _ = io::from_slice(&bytes); // must return, not panic
            }
        }
    }
}

#[test]
fn wrong_magic_and_unknown_encoding() {
    assert_eq!(
        rule_of(io::from_slice(b"PK\x03\x04 not an ism")),
        Rule::BadMagic
    );
    assert_eq!(rule_of(io::from_slice(b"")), Rule::BadMagic);
    let payload = io::encode_payload(&sample_model(), Encoding::Binary, false).unwrap();
    let mut bytes = io::header(Encoding::Binary, ism_format::FORMAT_VERSION, &payload).to_vec();
    bytes[12] = 9;
    let crc = crc32fast::hash(&bytes[..28]);
    bytes[28..32].copy_from_slice(&crc.to_le_bytes());
    bytes.extend_from_slice(&payload);
    let err = io::from_slice(&bytes).unwrap_err();
    assert_eq!(err.rule(), Some(Rule::UnknownEncoding));
    assert_eq!(err.diagnostics()[0].location.offset, Some(12));
}

#[test]
fn newer_major_version_is_refused_clearly() {
    let mut model = sample_model();
    model.version = "2.0".into();
    for enc in Encoding::ALL {
        // The writer writes only its own version; the raw encoder writes what the model says.
        let bytes = io::to_vec_unchecked(&model, enc, WriteOptions::default()).unwrap();
        let err = io::from_slice(&bytes).unwrap_err();
        assert_eq!(err.rule(), Some(Rule::UnsupportedVersion), "{enc:?}: {err}");
        assert!(err.to_string().contains("2.0"), "{err}");
    }
    // A newer major whose shape changed entirely still reports the version, not the shape.
    let err = io::from_slice(br#"{"version": "3.1", "everything": "different"}"#).unwrap_err();
    assert_eq!(err.rule(), Some(Rule::UnsupportedVersion));
    // A newer minor of the same major reads (unknown members ignored).
    let mut newer = sample_model();
    newer.version = "1.7".into();
    let mut json: serde_json::Value = serde_json::to_value(&newer).unwrap();
    json["futureMember"] = serde_json::json!([1, 2, 3]);
    assert!(io::from_slice(json.to_string().as_bytes()).is_ok());
}

#[test]
fn huge_declared_lengths_fail_without_allocating() {
    // The binary payload starts with the version string (u64 length + bytes), then dimension (u8),
    // then metadata: four Option<String> tags, then `vertices` (u64 length).
    let model = sample_model();
    let payload = io::encode_payload(&model, Encoding::Binary, false).unwrap();
    let version_end = 8 + 3;
    let mut offset = version_end + 1;
    // Skip the metadata: name is Some("square"), generator/units/description None.
    assert_eq!(payload[offset], 1);
    offset += 1 + 8 + 6 + 3;
    assert_eq!(
        u64::from_le_bytes(payload[offset..offset + 8].try_into().unwrap()),
        8,
        "vertices length"
    );
    for huge in [u64::MAX, 1 << 60, 1 << 40, 1 << 32] {
        let mut p = payload.clone();
        p[offset..offset + 8].copy_from_slice(&huge.to_le_bytes());
        let mut bytes = io::header(Encoding::Binary, ism_format::FORMAT_VERSION, &p).to_vec();
        bytes.extend_from_slice(&p);
        let rule = rule_of(io::from_slice(&bytes));
        assert!(
            matches!(rule, Rule::LimitExceeded | Rule::Malformed),
            "{rule:?}"
        );
    }
    // MessagePack: an array header claiming 2^32 − 1 elements, then nothing.
    let mut p = rmp_header_map_with_huge_array();
    let mut bytes = io::header(Encoding::MessagePack, ism_format::FORMAT_VERSION, &p).to_vec();
    bytes.append(&mut p);
    assert_eq!(rule_of(io::from_slice(&bytes)), Rule::Malformed);
    // A container that declares a payload longer than the limit.
    let mut bytes = io::header(Encoding::Binary, ism_format::FORMAT_VERSION, &payload).to_vec();
    bytes[16..24].copy_from_slice(&(1u64 << 62).to_le_bytes());
    let crc = crc32fast::hash(&bytes[..28]);
    bytes[28..32].copy_from_slice(&crc.to_le_bytes());
    assert_eq!(rule_of(io::from_slice(&bytes)), Rule::LimitExceeded);
}

fn rmp_header_map_with_huge_array() -> Vec<u8> {
    // {"version": "1.0", "dimension": 2, "vertices": array32(0xFFFFFFFF) ...truncated}
    let mut v = vec![0x83];
    v.extend_from_slice(&[0xA7]);
    v.extend_from_slice(b"version");
    v.extend_from_slice(&[0xA3]);
    v.extend_from_slice(b"1.0");
    v.extend_from_slice(&[0xA9]);
    v.extend_from_slice(b"dimension");
    v.push(2);
    v.extend_from_slice(&[0xA8]);
    v.extend_from_slice(b"vertices");
    v.extend_from_slice(&[0xDD, 0xFF, 0xFF, 0xFF, 0xFF]);
    v
}

#[test]
fn structural_errors_name_the_place() {
    type Mutation = Box<dyn Fn(&mut Model)>;
    let cases: Vec<(&str, Mutation, Rule, &str)> = vec![
        (
            "nan vertex",
            Box::new(|m| m.vertices[3] = f64::NAN),
            Rule::VertexArray,
            "/vertices/3",
        ),
        (
            "inf value",
            Box::new(|m| m.values[1] = f64::INFINITY),
            Rule::ValueArray,
            "/values/1",
        ),
        (
            "zero value",
            Box::new(|m| m.values[2] = 0.0),
            Rule::ValueZero,
            "/values/2",
        ),
        (
            "value at level",
            Box::new(|m| m.level = 0.5),
            Rule::ValueAtLevel,
            "/values/3",
        ),
        (
            "index out of range",
            Box::new(|m| m.simplices[4] = 9),
            Rule::IndexRange,
            "/simplices/4",
        ),
        (
            "repeated index",
            Box::new(|m| m.simplices[5] = 0),
            Rule::RepeatedIndex,
            "/simplices/3",
        ),
        (
            "inverted",
            Box::new(|m| m.simplices.swap(4, 5)),
            Rule::Inverted,
            "/simplices/3",
        ),
        (
            "degenerate",
            Box::new(|m| m.vertices[7] = m.vertices[7] * 0.0 + 0.0),
            Rule::Degenerate,
            "/simplices/3",
        ),
        (
            "non-face",
            Box::new(|m| m.stages[0].faces.edit(|r| r[0].face = vec![1, 3])),
            Rule::NotAFace,
            "/stages/0/faces/0/face",
        ),
        (
            "unsorted face",
            Box::new(|m| m.stages[0].faces.edit(|r| r[0].face = vec![2, 0])),
            Rule::FaceSorted,
            "/stages/0/faces/0/face",
        ),
        (
            "coordinates",
            Box::new(|m| m.stages[0].faces.edit(|r| r[0].points.push(0.1))),
            Rule::PointCount,
            "/stages/0/faces/0/points",
        ),
        (
            "weights",
            Box::new(|m| m.stages[1].faces.edit(|r| r[0].weights.clear())),
            Rule::WeightCount,
            "/stages/1/faces/0/weights",
        ),
        (
            "degree",
            Box::new(|m| m.stages[1].degree = 99),
            Rule::StageDegree,
            "/stages/1/degree",
        ),
    ];
    for (what, mutate, rule, pointer) in cases {
        let mut m = sample_model();
        mutate(&mut m);
        for enc in [Encoding::MessagePack, Encoding::Binary] {
            // Writers refuse non-finite numbers; the raw encoder makes the broken file.
            let bytes = io::to_vec_unchecked(&m, enc, WriteOptions::default()).unwrap();
            let err = io::from_slice(&bytes).unwrap_err();
            let d = &err.diagnostics()[0];
            assert_eq!(
                (d.rule, d.location.pointer.as_deref()),
                (rule, Some(pointer)),
                "{what}: {err}"
            );
        }
    }
}

#[test]
fn failed_writes_leave_no_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("out.ism.json");
    let mut m = sample_model();
    m.vertices[0] = f64::NAN; // readers refuse NaN (ISM-102), so the writer does too
    let before: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert!(before.is_empty());
    let err = io::write_path(&m, &path, Some(Encoding::Json), WriteOptions::default()).unwrap_err();
    assert_eq!(err.rule(), Some(Rule::VertexArray));
    assert_eq!(
        std::fs::read_dir(dir.path()).unwrap().count(),
        0,
        "no partial or temporary file"
    );
    m.vertices[0] = 0.0;
    // Nested deeper than readers accept (spec §7.8): ISM-006 before anything is written.
    let mut deep = serde_json::json!(1);
    for _ in 0..ism_format::MAX_DEPTH {
        deep = serde_json::json!([deep]);
    }
    m.extras = ism_format::JsonValue(deep);
    let err =
        io::write_path(&m, &path, Some(Encoding::Binary), WriteOptions::default()).unwrap_err();
    assert_eq!(err.rule(), Some(Rule::Malformed));
    assert_eq!(
        std::fs::read_dir(dir.path()).unwrap().count(),
        0,
        "no partial or temporary file"
    );
    // An existing file is left untouched by a failed write.
    std::fs::write(&path, b"previous").unwrap();
    assert!(io::write_path(
        &m,
        &path,
        Some(Encoding::MessagePack),
        WriteOptions::default()
    )
    .is_err());
    assert_eq!(std::fs::read(&path).unwrap(), b"previous");
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    // A directory that does not exist: an error naming the path.
    let err = io::write_path(
        &sample_model(),
        dir.path().join("missing/x.ismb"),
        None,
        WriteOptions::default(),
    )
    .unwrap_err();
    assert!(err.to_string().contains("missing"), "{err}");
}

#[test]
fn header_is_32_bytes_and_crc_protected() {
    let bytes = io::to_vec(&sample_model(), Encoding::Binary, WriteOptions::default()).unwrap();
    assert_eq!(&bytes[..8], &io::MAGIC);
    assert_eq!(HEADER_LEN, 32);
    assert_eq!(
        u32::from_le_bytes(bytes[24..28].try_into().unwrap()),
        crc32fast::hash(&bytes[HEADER_LEN..])
    );
}

#[test]
fn json_with_bom_and_trailing_text_are_refused() {
    let json = io::to_vec(&sample_model(), Encoding::Json, WriteOptions::default()).unwrap();
    // spec §7.5: no byte-order mark, in plain JSON (ISM-001) as in checksummed JSON (ISM-006).
    let mut with_bom = b"\xEF\xBB\xBF".to_vec();
    with_bom.extend_from_slice(&json);
    let err = io::from_slice(&with_bom).unwrap_err();
    assert_eq!(err.rule(), Some(Rule::BadMagic));
    assert_eq!(err.diagnostics()[0].location.offset, Some(0));
    let mut trailing = json.clone();
    trailing.extend_from_slice(b"  \n garbage");
    let err = io::from_slice(&trailing).unwrap_err();
    assert_eq!(err.rule(), Some(Rule::Malformed));
    assert_eq!(
        err.diagnostics()[0].location.offset,
        Some(json.len() as u64 + 4)
    );
    let mut spaces = json;
    spaces.extend_from_slice(b" \n\t ");
    assert!(io::from_slice(&spaces).is_ok());
}
