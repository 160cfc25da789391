//! The decisions of spec §7.7–§7.8 (issue 18), each checked in every encoding it concerns: nesting
//! depth enforced identically by readers and writers, writers write their own version, versions
//! compare as numbers, optional strings are not `null`.

use ism_format::io::{self, ReadOptions, WriteOptions};
use ism_format::{Encoding, JsonValue, Model, Rule, MAX_DEPTH};

fn triangle() -> Model {
    let mut m = Model::new(2);
    m.vertices = vec![0.0, 0.0, 1.0, 0.0, 0.0, 1.0];
    m.simplices = vec![0, 1, 2];
    m.values = vec![-1.0, 1.0, 1.0];
    m
}

/// `levels` nested arrays around `0`.
fn nested(levels: usize) -> serde_json::Value {
    let mut v = serde_json::json!(0);
    for _ in 0..levels {
        v = serde_json::json!([v]);
    }
    v
}

#[test]
fn depth_limit_is_the_same_for_readers_and_writers_in_every_encoding() {
    // The model is level 1, so its extras may nest MAX_DEPTH - 1 levels; a stage's extras (below
    // the model, `stages` and the stage) MAX_DEPTH - 3.
    for (levels, stage_levels, fits) in [
        (MAX_DEPTH - 1, 0, true),
        (MAX_DEPTH, 0, false),
        (0, MAX_DEPTH - 3, true),
        (0, MAX_DEPTH - 2, false),
    ] {
        let mut m = triangle();
        m.extras = JsonValue(nested(levels));
        let mut stage = ism_format::Stage::identity(ism_format::StageKind::Bezier, 1);
        stage.extras = JsonValue(nested(stage_levels));
        m.stages.push(stage);
        for enc in Encoding::ALL {
            let written = io::to_vec(&m, enc, WriteOptions::default());
            let raw = io::to_vec_unchecked(&m, enc, WriteOptions::default()).unwrap();
            let read = io::from_slice(&raw);
            if fits {
                assert_eq!(io::from_slice(&written.unwrap()).unwrap().model, m);
                assert_eq!(read.unwrap().model, m, "{enc:?}");
            } else {
                let w = written.unwrap_err();
                let r = read.unwrap_err();
                assert_eq!(w.rule(), Some(Rule::Malformed), "{enc:?}: {w}");
                assert_eq!(r.rule(), Some(Rule::Malformed), "{enc:?}: {r}");
                // Both name the same array: the first one too deep.
                assert_eq!(
                    w.diagnostics()[0].location.pointer,
                    r.diagnostics()[0].location.pointer,
                    "{enc:?}"
                );
            }
        }
    }
}

#[test]
fn a_newer_minor_file_is_written_as_the_writers_own_version() {
    let mut json: serde_json::Value = serde_json::to_value(triangle()).unwrap();
    json["version"] = "1.1".into();
    json["addedIn11"] = serde_json::json!({"meaning": "unknown to a 1.0 reader"});
    let doc = io::from_slice(json.to_string().as_bytes()).unwrap();
    assert_eq!(doc.model.version, "1.1");
    for enc in Encoding::ALL {
        let bytes = io::to_vec(&doc.model, enc, WriteOptions::default()).unwrap();
        let again = io::from_slice(&bytes).unwrap();
        assert_eq!(again.model.version, "1.0", "{enc:?}");
        if let Some(c) = again.container {
            assert_eq!((c.major, c.minor), (1, 0));
        }
        assert_eq!(
            Model {
                version: "1.1".into(),
                ..again.model
            },
            doc.model
        );
    }
}

#[test]
fn versions_compare_as_numbers_and_have_no_leading_zeros() {
    for (text, ok) in [
        ("1.0", true),
        ("1.10", true),
        ("1.65535", true),
        ("01.0", false),
        ("1.00", false),
        ("1.65536", false),
        ("1", false),
        ("1.0.0", false),
        (" 1.0", false),
    ] {
        let mut m = triangle();
        m.version = text.into();
        let bytes = io::to_vec_unchecked(&m, Encoding::Json, WriteOptions::default()).unwrap();
        let result = io::from_slice(&bytes);
        assert_eq!(result.is_ok(), ok, "{text}: {result:?}");
        if !ok {
            let e = result.unwrap_err();
            assert_eq!(e.rule(), Some(Rule::Malformed));
            assert_eq!(
                e.diagnostics()[0].location.pointer.as_deref(),
                Some("/version")
            );
        }
    }
    // Header 1.10 and payload "1.10" agree; a 1.0 reader reads the newer minor.
    let mut m = triangle();
    m.version = "1.10".into();
    let bytes = io::to_vec_unchecked(&m, Encoding::MessagePack, WriteOptions::default()).unwrap();
    assert_eq!(u16::from_le_bytes([bytes[10], bytes[11]]), 10);
    assert_eq!(io::from_slice(&bytes).unwrap().model.version, "1.10");
}

#[test]
fn null_is_not_an_optional_string_in_any_map_encoding() {
    let base = serde_json::to_value(triangle()).unwrap();
    for (pointer, value) in [
        ("/metadata/name", serde_json::Value::Null),
        ("/metadata", serde_json::Value::Null),
        ("/level", serde_json::Value::Null),
    ] {
        let mut json = base.clone();
        let (parent, key) = pointer.rsplit_once('/').unwrap();
        json.pointer_mut(if parent.is_empty() { "" } else { parent })
            .unwrap()
            .as_object_mut()
            .unwrap()
            .insert(key.to_string(), value.clone());
        let text = json.to_string();
        let msgpack = {
            let payload = rmp_serde::to_vec_named(&json).unwrap();
            let mut out =
                io::header(Encoding::MessagePack, ism_format::FORMAT_VERSION, &payload).to_vec();
            out.extend_from_slice(&payload);
            out
        };
        for bytes in [text.as_bytes(), &msgpack[..]] {
            let e = io::from_slice(bytes).unwrap_err();
            assert_eq!(e.rule(), Some(Rule::Malformed), "{pointer}: {e}");
            assert_eq!(
                e.diagnostics()[0].location.pointer.as_deref(),
                Some(pointer)
            );
        }
    }
}

#[test]
fn json_data_keeps_integers_floats_and_member_order_in_every_encoding() {
    let mut m = triangle();
    let text =
        r#"{"z":1,"a":1.0,"m":[18446744073709551615,-9223372036854775808,-0.0,5e-324,1e16]}"#;
    m.extras = JsonValue(serde_json::from_str(text).unwrap());
    for enc in Encoding::ALL {
        let bytes = io::to_vec(&m, enc, WriteOptions::default()).unwrap();
        let back = io::from_slice(&bytes).unwrap().model;
        assert_eq!(
            ism_format::canonical::json_text(&back.extras.0),
            r#"{"z":1,"a":1.0,"m":[18446744073709551615,-9223372036854775808,-0.0,5e-324,1e16]}"#,
            "{enc:?}"
        );
    }
}

#[test]
fn binary_errors_name_the_member_and_the_byte() {
    let bytes = io::to_vec(&triangle(), Encoding::Binary, WriteOptions::default()).unwrap();
    // Every truncation whose checksums are made valid again is ISM-006 with a pointer and an
    // offset inside the file, and a message free of Rust type names.
    for len in 32..bytes.len() {
        let payload = &bytes[32..len];
        let mut file = io::header(Encoding::Binary, ism_format::FORMAT_VERSION, payload).to_vec();
        file.extend_from_slice(payload);
        let e = io::from_slice_with(&file, &ReadOptions::default()).unwrap_err();
        let d = &e.diagnostics()[0];
        assert_eq!(d.rule, Rule::Malformed, "{len}: {e}");
        assert!(d.location.pointer.is_some(), "{len}: {e}");
        assert!(
            d.location.offset.is_some_and(|o| o <= len as u64),
            "{len}: {e}"
        );
        assert!(
            !d.message.contains("Unexpected") && !d.message.contains("::"),
            "{len}: {e}"
        );
    }
}

#[test]
fn a_member_given_twice_is_found_among_many_unknown_members() {
    let text = String::from_utf8(
        io::to_vec(&triangle(), Encoding::Json, WriteOptions::default()).unwrap(),
    )
    .unwrap();
    for count in [1usize, 15, 16, 17, 40] {
        let unknown: String = (0..count).map(|i| format!(",\"u{i}\":{i}")).collect();
        let ok = format!("{}{unknown}}}", &text[..text.len() - 1]);
        assert!(io::from_slice(ok.as_bytes()).is_ok(), "{count}");
        for repeated in ["u0", "version"] {
            let bad = format!("{}{unknown},\"{repeated}\":0}}", &text[..text.len() - 1]);
            let e = io::from_slice(bad.as_bytes()).unwrap_err();
            let d = &e.diagnostics()[0];
            assert_eq!(d.rule, Rule::Malformed, "{count} {repeated}");
            assert_eq!(
                d.location.pointer.as_deref(),
                Some(&*format!("/{repeated}"))
            );
            assert_eq!(
                d.location.offset,
                Some(bad.rfind(&format!("\"{repeated}\"")).unwrap() as u64)
            );
        }
    }
}
