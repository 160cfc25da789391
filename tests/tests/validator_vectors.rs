//! Conformance of the validator (spec/validation.md §7): every vector in `spec/vectors/validate/`
//! gets exactly the `(code, location)` pairs and the verdict of its `NAME.expect.json`, and every
//! example in `spec/examples/` (all five encodings) is valid. One test per file.

use std::path::{Path, PathBuf};

use ism_conformance::spec_dir;
use ism_format::Location;
use ism_validate::{validate_path, Options};
use libtest_mimic::{Arguments, Failed, Trial};
use serde::Deserialize;

#[derive(Deserialize)]
struct Expected {
    code: String,
    location: Location,
}

#[derive(Deserialize)]
struct Expectation {
    verdict: String,
    issues: Vec<Expected>,
}

fn check_vector(expect_path: &Path) -> Result<(), Failed> {
    let expect: Expectation = serde_json::from_slice(&std::fs::read(expect_path)?)?;
    let name = expect_path
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or("");
    let stem = name
        .strip_suffix(".expect.json")
        .ok_or("not an expectation")?;
    let model = expect_path.with_file_name(format!("{stem}.ism.json"));
    let report = validate_path(&model, &Options::default())?;
    let mut got: Vec<(String, Location)> = report.pairs();
    let mut want: Vec<(String, Location)> = expect
        .issues
        .into_iter()
        .map(|e| (e.code, e.location))
        .collect();
    got.sort();
    want.sort();
    if got != want {
        return Err(format!("{}:\n  got  {got:?}\n  want {want:?}", model.display()).into());
    }
    if report.verdict.as_str() != expect.verdict {
        return Err(format!(
            "verdict {} ; expected {}",
            report.verdict.as_str(),
            expect.verdict
        )
        .into());
    }
    // Every rejection by ISM-301 carries a witness whose det is not positive.
    for m in &report.issues.messages {
        if m.code == "ISM-301" {
            let w = m.witness.as_ref().ok_or("ISM-301 without witness")?;
            if w.det > 0.0 {
                return Err(format!("witness det {} > 0", w.det).into());
            }
        }
    }
    Ok(())
}

fn check_example(path: &Path) -> Result<(), Failed> {
    let report = validate_path(path, &Options::default())?;
    if !report.is_valid() {
        return Err(format!(
            "{} is {}: {:?}",
            path.display(),
            report.verdict.as_str(),
            report.issues.messages
        )
        .into());
    }
    Ok(())
}

fn files(dir: &Path) -> Vec<PathBuf> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .map(|e| e.path())
                .filter(|p| p.is_file())
                .collect()
        })
        .unwrap_or_default();
    paths.sort();
    paths
}

fn main() {
    let args = Arguments::from_args();
    let mut trials = Vec::new();
    let vectors = spec_dir().join("vectors/validate");
    for path in files(&vectors) {
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("")
            .to_string();
        if let Some(stem) = name.strip_suffix(".expect.json") {
            trials.push(Trial::test(format!("validate::{stem}"), move || {
                check_vector(&path)
            }));
        }
    }
    let examples = spec_dir().join("examples");
    for path in files(&examples) {
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("")
            .to_string();
        if name.ends_with(".ism.json") || name.ends_with(".ismb") || name.ends_with(".ism.msgpack")
        {
            trials.push(Trial::test(format!("example_valid::{name}"), move || {
                check_example(&path)
            }));
        }
    }
    if trials.is_empty() {
        trials.push(Trial::test("validate::vectors_present", move || {
            Err(format!("no vectors in {}", vectors.display()).into())
        }));
    }
    libtest_mimic::run(&args, trials).exit();
}
