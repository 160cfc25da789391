//! The files under `spec/` are exactly what the generators produce, and read back as intended.

use std::path::PathBuf;

use ism_examples::named::{all_examples, example_bytes};
use ism_examples::vectors::{expectation, reader_vectors};
use ism_format::{io, Encoding};

fn spec_dir(sub: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../spec")
        .join(sub)
}

const REGENERATE: &str =
    "run `cargo run -p ism-examples --bin ism-make-examples -- --vectors` and commit spec/";

#[test]
fn examples_on_disk_match_the_generators_and_agree_across_encodings() {
    for (name, model) in all_examples() {
        for encoding in Encoding::ALL {
            let path = spec_dir("examples").join(format!("{name}.{}", encoding.extension()));
            let on_disk = std::fs::read(&path)
                .unwrap_or_else(|e| panic!("{}: {e}; {REGENERATE}", path.display()));
            assert!(
                on_disk == example_bytes(&model, encoding).unwrap(),
                "{} is stale; {REGENERATE}",
                path.display()
            );
            let doc =
                io::from_slice(&on_disk).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            assert_eq!(doc.encoding, encoding);
            assert_eq!(doc.model, model, "{} does not round-trip", path.display());
            assert!(on_disk.len() < 1 << 20, "{} is over 1 MB", path.display());
        }
    }
}

#[test]
fn reader_vectors_on_disk_match_the_generators() {
    let vectors = reader_vectors();
    for vector in &vectors {
        let path = spec_dir("vectors/reader").join(vector.file_name());
        let on_disk = std::fs::read(&path)
            .unwrap_or_else(|e| panic!("{}: {e}; {REGENERATE}", path.display()));
        assert!(
            on_disk == vector.bytes,
            "{} is stale; {REGENERATE}",
            path.display()
        );
        let expect_path = spec_dir("vectors/reader").join(format!("{}.expect.json", vector.name));
        let expect: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&expect_path).unwrap()).unwrap();
        assert_eq!(
            expect,
            expectation(vector).unwrap(),
            "{}",
            expect_path.display()
        );
    }
    // No stray files: every file in the folder belongs to a vector (or is the README).
    let count = std::fs::read_dir(spec_dir("vectors/reader"))
        .unwrap()
        .filter(|e| e.as_ref().unwrap().file_name() != "README.md")
        .count();
    assert_eq!(
        count,
        2 * vectors.len(),
        "stray files in spec/vectors/reader; {REGENERATE}"
    );
}

#[test]
fn writer_vectors_on_disk_match_the_generators() {
    use ism_examples::writer_vectors::{writer_output, writer_vectors, OUTPUTS};
    let dir = spec_dir("vectors/writer");
    let vectors = writer_vectors();
    for vector in &vectors {
        let input = std::fs::read(dir.join(format!("{}.input.json", vector.name)))
            .unwrap_or_else(|e| panic!("{}: {e}; {REGENERATE}", vector.name));
        assert!(
            input == vector.input.as_bytes(),
            "{} input is stale; {REGENERATE}",
            vector.name
        );
        for (suffix, encoding, pretty) in OUTPUTS {
            let path = dir.join(format!("{}.{suffix}", vector.name));
            let on_disk = std::fs::read(&path)
                .unwrap_or_else(|e| panic!("{}: {e}; {REGENERATE}", path.display()));
            assert!(
                on_disk == writer_output(vector, encoding, pretty).unwrap(),
                "{} is stale; {REGENERATE}",
                path.display()
            );
        }
    }
    let count = std::fs::read_dir(&dir).unwrap().count();
    assert_eq!(
        count,
        vectors.len() * (1 + OUTPUTS.len()),
        "stray files in spec/vectors/writer; {REGENERATE}"
    );
}
