//! Every input the fuzzers kept (`fuzz/corpus/*`) and every crash they found (`fuzz/artifacts/*`,
//! fixed since) runs through the same checks as the fuzz targets: a typed error or a model that
//! re-encodes and reads back equal. Never a panic.

use std::path::{Path, PathBuf};

use ism_format::io::{self, ReadOptions, WriteOptions};
use ism_format::{Encoding, Model, FORMAT_VERSION};

fn files(dir: &Path) -> Vec<PathBuf> {
    let mut out: Vec<PathBuf> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.is_file())
        .collect();
    out.sort();
    out
}

/// The model as a writer writes it back: its own version (spec §8.1).
fn as_written(model: &Model) -> Model {
    Model {
        version: FORMAT_VERSION.to_string(),
        ..model.clone()
    }
}

fn check_any(bytes: &[u8]) {
    if let Ok(doc) = io::from_slice(bytes) {
        let again = io::to_vec(&doc.model, doc.encoding, Default::default()).expect("re-encode");
        assert_eq!(
            io::from_slice(&again).expect("re-read").model,
            as_written(&doc.model)
        );
    }
}

/// The property of the `cross_encoding` fuzz target (spec §7.7): whatever reads, in any encoding,
/// is written in each encoding, reads back equal, and re-encodes to the same canonical bytes,
/// whichever encoding it came from.
fn check_cross(bytes: &[u8]) {
    let unchecked = ReadOptions {
        check_structure: false,
        ..ReadOptions::default()
    };
    let Ok(doc) = io::from_slice_with(bytes, &unchecked) else {
        return;
    };
    let binary = |m: &Model| io::encode_payload(m, Encoding::Binary, false).unwrap();
    let mut canonical = Vec::new();
    for encoding in Encoding::ALL {
        match io::to_vec(&doc.model, encoding, WriteOptions::default()) {
            Ok(written) => {
                let again =
                    io::from_slice_with(&written, &unchecked).expect("a written file reads");
                assert_eq!(binary(&again.model), binary(&as_written(&doc.model)));
                assert_eq!(
                    io::to_vec(&again.model, encoding, WriteOptions::default()).unwrap(),
                    written
                );
                canonical.push(written);
            }
            Err(e) => {
                assert!(io::check_writable(&doc.model).is_err(), "{encoding:?}: {e}");
                assert!(canonical.is_empty(), "{encoding:?}: {e}");
            }
        }
    }
    for written in &canonical {
        let model = io::from_slice_with(written, &unchecked).unwrap().model;
        for (encoding, expected) in Encoding::ALL.into_iter().zip(&canonical) {
            assert_eq!(
                &io::to_vec(&model, encoding, WriteOptions::default()).unwrap(),
                expected
            );
        }
    }
}

fn check_payload(encoding: Encoding, payload: &[u8]) {
    let mut bytes = io::header(encoding, FORMAT_VERSION, payload).to_vec();
    bytes.extend_from_slice(payload);
    check_any(&bytes);
    // The binary encodings leave a writer no choice (spec §7.7): a payload that reads is the one
    // the writer writes for its model.
    if matches!(encoding, Encoding::Binary | Encoding::Compact) {
        if let Ok(doc) = io::from_slice(&bytes) {
            let again = io::to_vec(&doc.model, encoding, Default::default()).unwrap();
            assert_eq!(
                &again[io::HEADER_LEN..],
                payload,
                "{encoding:?} not canonical"
            );
        }
    }
}

#[test]
fn fuzz_corpus_and_crashes_are_handled() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fuzz");
    let mut count = 0;
    for kind in ["corpus", "artifacts"] {
        for (target, encoding) in [
            ("read_any", None),
            ("read_binary", Some(Encoding::Binary)),
            ("read_compact", Some(Encoding::Compact)),
            ("read_structured", Some(Encoding::Structured)),
            ("read_msgpack", Some(Encoding::MessagePack)),
            ("read_json", Some(Encoding::Json)),
            ("cross_encoding", None),
        ] {
            for file in files(&root.join(kind).join(target)) {
                let bytes = std::fs::read(&file).unwrap();
                if target == "cross_encoding" {
                    check_cross(&bytes);
                }
                match encoding {
                    None => check_any(&bytes),
                    Some(e) => check_payload(e, &bytes),
                }
                count += 1;
            }
        }
    }
    assert!(count >= 4, "the fuzz corpus is missing ({count} files)");
}
