//! Conformance: every broken file in `spec/vectors/reader/` is refused with exactly the rule and
//! location its `NAME.expect.json` states (spec §9). One test per vector.

use std::path::{Path, PathBuf};

use ism_conformance::spec_dir;
use ism_format::{io, Location};
use libtest_mimic::{Arguments, Failed, Trial};
use serde::Deserialize;

#[derive(Deserialize)]
struct Expectation {
    rule: String,
    #[serde(default)]
    location: Location,
}

fn vector_file(expect: &Path) -> Option<PathBuf> {
    let stem = expect
        .file_name()?
        .to_str()?
        .strip_suffix(".expect.json")?
        .to_string();
    let dir = expect.parent()?;
    std::fs::read_dir(dir)
        .ok()?
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .find(|p| {
            let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
            name != format!("{stem}.expect.json")
                && name
                    .strip_prefix(&stem)
                    .is_some_and(|rest| rest.starts_with('.'))
        })
}

fn check(expect_path: &Path) -> Result<(), Failed> {
    let expect: Expectation = serde_json::from_slice(&std::fs::read(expect_path)?)?;
    let file = vector_file(expect_path).ok_or("no vector file beside the expectation")?;
    let err = match io::read_path(&file) {
        Ok(_) => {
            return Err(format!("{} was accepted; expected {}", file.display(), expect.rule).into())
        }
        Err(e) => e,
    };
    let first = err
        .diagnostics()
        .first()
        .ok_or_else(|| format!("error without a rule: {err}"))?;
    if first.rule.id() != expect.rule || first.location != expect.location {
        return Err(format!(
            "got {} at {:?}; expected {} at {:?}\n  message: {}",
            first.rule.id(),
            first.location,
            expect.rule,
            expect.location,
            first.message
        )
        .into());
    }
    Ok(())
}

fn main() {
    let args = Arguments::from_args();
    let dir = spec_dir().join("vectors/reader");
    let mut trials = Vec::new();
    let mut paths: Vec<PathBuf> = std::fs::read_dir(&dir)
        .map(|rd| rd.filter_map(|e| e.ok()).map(|e| e.path()).collect())
        .unwrap_or_default();
    paths.sort();
    for path in paths {
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("")
            .to_string();
        if let Some(stem) = name.strip_suffix(".expect.json") {
            let p = path.clone();
            trials.push(Trial::test(format!("reader::{stem}"), move || check(&p)));
        }
    }
    if trials.is_empty() {
        // An empty directory must not pass silently.
        trials.push(Trial::test("reader::vectors_present", move || {
            Err(format!("no vectors in {}", dir.display()).into())
        }));
    }
    libtest_mimic::run(&args, trials).exit();
}
