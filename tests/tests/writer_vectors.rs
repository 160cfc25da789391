//! Conformance: every model in `spec/vectors/writer/` encodes to exactly the bytes beside it, in every
//! encoding (spec §7.7), and each of those files reads back and re-encodes to itself. One test per
//! vector.

use std::path::{Path, PathBuf};

use ism_conformance::spec_dir;
use ism_format::io::{self, WriteOptions};
use ism_format::Encoding;
use libtest_mimic::{Arguments, Failed, Trial};

/// Output file suffix, encoding, pretty JSON.
const OUTPUTS: [(&str, Encoding, bool); 6] = [
    ("ism.json", Encoding::Json, false),
    ("pretty.ism.json", Encoding::Json, true),
    ("ism.msgpack", Encoding::MessagePack, false),
    ("ismb", Encoding::Binary, false),
    ("ismc", Encoding::Compact, false),
    ("isms", Encoding::Structured, false),
];

fn check(dir: &Path, stem: &str) -> Result<(), Failed> {
    let input = std::fs::read(dir.join(format!("{stem}.input.json")))?;
    let model = io::from_slice(&input)
        .map_err(|e| format!("input does not read: {e}"))?
        .model;
    for (suffix, encoding, pretty) in OUTPUTS {
        let expected = std::fs::read(dir.join(format!("{stem}.{suffix}")))?;
        let options = WriteOptions {
            pretty,
            json_in_container: false,
        };
        let written = io::to_vec(&model, encoding, options)?;
        if written != expected {
            let at = written
                .iter()
                .zip(&expected)
                .position(|(a, b)| a != b)
                .unwrap_or(written.len().min(expected.len()));
            return Err(format!("{stem}.{suffix}: bytes differ from byte {at} on").into());
        }
        // Canonical: what was written reads back and re-encodes to the same bytes.
        let again =
            io::from_slice(&expected).map_err(|e| format!("{stem}.{suffix} does not read: {e}"))?;
        if io::to_vec(&again.model, encoding, options)? != expected {
            return Err(format!("{stem}.{suffix} is not a fixed point of read + write").into());
        }
    }
    Ok(())
}

fn main() {
    let args = Arguments::from_args();
    let dir = spec_dir().join("vectors/writer");
    let mut stems: Vec<String> = std::fs::read_dir(&dir)
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .filter_map(|e| {
                    e.file_name()
                        .to_str()
                        .and_then(|n| n.strip_suffix(".input.json"))
                        .map(str::to_string)
                })
                .collect()
        })
        .unwrap_or_default();
    stems.sort();
    let mut trials: Vec<Trial> = stems
        .into_iter()
        .map(|stem| {
            let dir: PathBuf = dir.clone();
            Trial::test(format!("writer::{stem}"), move || check(&dir, &stem))
        })
        .collect();
    if trials.is_empty() {
        trials.push(Trial::test("writer::vectors_present", move || {
            Err(format!("no vectors in {}", dir.display()).into())
        }));
    }
    libtest_mimic::run(&args, trials).exit();
}
