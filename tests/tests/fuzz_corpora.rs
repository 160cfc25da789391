//! The seeds, corpora and fixed crashes of the fuzz targets
//! (`fuzz/seeds/<target>`, `fuzz/corpus/<target>`, `fuzz/artifacts/<target>`) replayed through the
//! targets' own properties (`ism_conformance::fuzz`):
//! one test per target, so every input a fuzzer kept stays a regression test. (The model readers'
//! round trips run in `crates/ism-format/tests/fuzz_regressions.rs`; here, that the readers agree.)

use std::path::{Path, PathBuf};

use ism_conformance::{fuzz, repo_root};
use ism_format::Encoding;
use libtest_mimic::{Arguments, Failed, Trial};

/// A target's property: panics when it fails.
type Property = fn(&[u8]);

/// Each target and its property.
const TARGETS: &[(&str, Property)] = &[
    ("read_any", fuzz::readers_agree),
    ("read_binary", |b| {
        fuzz::readers_agree_on_payload(Encoding::Binary, b)
    }),
    ("read_compact", |b| {
        fuzz::readers_agree_on_payload(Encoding::Compact, b)
    }),
    ("read_compressed", fuzz::read_compressed),
    ("read_structured", fuzz::read_structured),
    ("read_msgpack", |b| {
        fuzz::readers_agree_on_payload(Encoding::MessagePack, b)
    }),
    ("read_json", |b| {
        fuzz::readers_agree_on_payload(Encoding::Json, b)
    }),
    ("import_mesh", fuzz::import_mesh),
    ("fit_mesh", fuzz::fit_mesh),
    ("read_hermite", fuzz::read_hermite),
    ("validate_generated", fuzz::validate_generated),
];

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

fn replay(target: &str, check: Property) -> Result<(), Failed> {
    let root = repo_root().join("fuzz");
    let inputs: Vec<PathBuf> = ["seeds", "corpus", "artifacts"]
        .iter()
        .flat_map(|kind| files(&root.join(kind).join(target)))
        .collect();
    if inputs.is_empty() {
        return Err(format!("fuzz/seeds/{target} and fuzz/corpus/{target} are missing").into());
    }
    for file in &inputs {
        let bytes = std::fs::read(file).map_err(|e| format!("{}: {e}", file.display()))?;
        std::panic::catch_unwind(|| check(&bytes)).map_err(|_| {
            format!(
                "{} fails the property (see the panic above)",
                file.display()
            )
        })?;
    }
    Ok(())
}

fn main() {
    let args = Arguments::from_args();
    let trials = TARGETS
        .iter()
        .map(|&(target, check)| Trial::test(target, move || replay(target, check)))
        .collect();
    libtest_mimic::run(&args, trials).exit();
}
