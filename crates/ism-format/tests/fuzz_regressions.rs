//! Every input the fuzzers kept (`fuzz/corpus/*`) and every crash they found (`fuzz/artifacts/*`,
//! fixed since) runs through the same checks as the fuzz targets: a typed error or a model that
//! re-encodes and reads back equal. Never a panic.

use std::path::{Path, PathBuf};

use ism_format::{io, Encoding, FORMAT_VERSION};

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

fn check_any(bytes: &[u8]) {
    if let Ok(doc) = io::from_slice(bytes) {
        let again = io::to_vec(&doc.model, doc.encoding, Default::default()).expect("re-encode");
        assert_eq!(io::from_slice(&again).expect("re-read").model, doc.model);
    }
}

fn check_payload(encoding: Encoding, payload: &[u8]) {
    let mut bytes = io::header(encoding, FORMAT_VERSION, payload).to_vec();
    bytes.extend_from_slice(payload);
    check_any(&bytes);
}

#[test]
fn fuzz_corpus_and_crashes_are_handled() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fuzz");
    let mut count = 0;
    for kind in ["corpus", "artifacts"] {
        for (target, encoding) in [
            ("read_any", None),
            ("read_binary", Some(Encoding::Binary)),
            ("read_msgpack", Some(Encoding::MessagePack)),
            ("read_json", Some(Encoding::Json)),
        ] {
            for file in files(&root.join(kind).join(target)) {
                let bytes = std::fs::read(&file).unwrap();
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
