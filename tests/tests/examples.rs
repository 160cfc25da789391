//! Conformance: every example in `spec/examples/` reads in each of its six encodings, passes the
//! reader's structural checks, and the six encodings carry bit-identical models. One test per
//! example.

use std::collections::BTreeMap;
use std::path::PathBuf;

use ism_conformance::spec_dir;
use ism_format::{io, Encoding};
use libtest_mimic::{Arguments, Failed, Trial};

fn check(name: &str, files: &[PathBuf]) -> Result<(), Failed> {
    let mut encodings = Vec::new();
    let mut reference: Option<Vec<u8>> = None;
    for file in files {
        let doc = io::read_path(file).map_err(|e| format!("{}: {e}", file.display()))?;
        let bits = io::encode_payload(&doc.model, Encoding::Binary, false)?;
        match &reference {
            None => reference = Some(bits),
            Some(r) if *r != bits => {
                return Err(format!(
                    "{} differs from the other encodings of {name}",
                    file.display()
                )
                .into())
            }
            _ => {}
        }
        encodings.push(doc.encoding);
    }
    encodings.sort_by_key(|e| e.tag());
    if encodings != Encoding::ALL {
        return Err(format!("{name}: expected all six encodings, found {encodings:?}").into());
    }
    Ok(())
}

fn main() {
    let args = Arguments::from_args();
    let dir = spec_dir().join("examples");
    let mut groups: BTreeMap<String, Vec<PathBuf>> = BTreeMap::new();
    for entry in std::fs::read_dir(&dir).into_iter().flatten().flatten() {
        let path = entry.path();
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("")
            .to_string();
        let stem = [
            ".ism.json",
            ".ism.msgpack",
            ".ismb",
            ".ismc",
            ".ismz",
            ".isms",
        ]
        .iter()
        .find_map(|ext| name.strip_suffix(ext));
        if let Some(stem) = stem {
            groups.entry(stem.to_string()).or_default().push(path);
        }
    }
    let mut trials: Vec<Trial> = groups
        .into_iter()
        .map(|(name, files)| Trial::test(format!("example::{name}"), move || check(&name, &files)))
        .collect();
    if trials.is_empty() {
        trials.push(Trial::test("example::present", move || {
            Err(format!("no examples in {}", dir.display()).into())
        }));
    }
    libtest_mimic::run(&args, trials).exit();
}
