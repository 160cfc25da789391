//! `ism smooth` end to end: a fitted circle and the sphere example get smaller normal jumps
//! (ISM-401, the measure of `ism validate --quality`), and the output validates.

use std::path::{Path, PathBuf};
use std::process::Command;

fn ism() -> Command {
    Command::new(env!("CARGO_BIN_EXE_ism"))
}

fn json(stdout: &[u8]) -> serde_json::Value {
    serde_json::from_slice(stdout).expect("--json prints one JSON object")
}

fn smooth(input: &Path, output: &Path, extra: &[&str]) -> serde_json::Value {
    let out = ism()
        .arg("smooth")
        .arg(input)
        .arg("-o")
        .arg(output)
        .arg("--json")
        .args(extra)
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let check = ism().arg("validate").arg(output).output().unwrap();
    assert_eq!(
        check.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&check.stdout)
    );
    json(&out.stdout)
}

#[test]
fn fitted_circle_gets_smaller_jumps() {
    let dir = tempfile::tempdir().unwrap();
    let fitted = dir.path().join("circle.ism.json");
    let out = ism()
        .args(["fit", "--preset", "circle", "--resolution", "6", "-q", "-o"])
        .arg(&fitted)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(0));
    let r = smooth(&fitted, &dir.path().join("smooth.ism.json"), &[]);
    let (b, a) = (&r["before"], &r["after"]);
    assert!(
        a["max"].as_f64().unwrap() < 0.5 * b["max"].as_f64().unwrap(),
        "{r}"
    );
    assert!(
        a["mean"].as_f64().unwrap() < b["mean"].as_f64().unwrap(),
        "{r}"
    );
    assert_eq!(r["blockAdded"], false);

    // The reported measure is the validator's: `validate --quality --json` says the same.
    let q = ism()
        .args(["validate", "--quality", "--json"])
        .arg(dir.path().join("smooth.ism.json"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&q.stdout);
    assert!(text.contains("ISM-401"), "{text}");
}

#[test]
fn sphere_example_gets_smaller_jumps() {
    let dir = tempfile::tempdir().unwrap();
    let input =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../spec/examples/sphere.ism.json");
    let r = smooth(
        &input,
        &dir.path().join("sphere.ismb"),
        &["--iterations", "2"],
    );
    let (b, a) = (&r["before"], &r["after"]);
    assert!(
        a["mean"].as_f64().unwrap() < b["mean"].as_f64().unwrap(),
        "{r}"
    );
    assert!(
        a["max"].as_f64().unwrap() <= b["max"].as_f64().unwrap(),
        "{r}"
    );
    assert_eq!(r["blockAdded"], true);
}

#[test]
fn unreadable_input_exits_2() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing.ism.json");
    let out = ism()
        .arg("smooth")
        .arg(&missing)
        .arg("-o")
        .arg(dir.path().join("o.ism.json"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
}
