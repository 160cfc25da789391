//! `ism validate` end to end: summary, JSON report, exit codes 0/1/2, options.

use std::path::PathBuf;
use std::process::Command;

fn ism() -> Command {
    Command::new(env!("CARGO_BIN_EXE_ism"))
}

fn spec(path: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../spec")
        .join(path)
}

#[test]
fn valid_example_exits_0_with_a_one_line_verdict() {
    let out = ism()
        .args(["validate"])
        .arg(spec("examples/stratified-3d.ism.json"))
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    let first = text.lines().next().unwrap();
    assert!(
        first.contains("VALID") && first.contains("0 error(s)"),
        "{text}"
    );
    assert!(text.contains("certified"), "{text}");
}

#[test]
fn folded_model_exits_1_and_names_the_rule_and_element() {
    let out = ism()
        .args(["validate"])
        .arg(spec("vectors/validate/quartic-fold-3d.ism.json"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.contains("INVALID"), "{text}");
    assert!(
        text.contains("ISM-301") && text.contains("simplex 0"),
        "{text}"
    );
}

#[test]
fn json_report_carries_witness_and_certificates() {
    let out = ism()
        .args(["validate", "--json", "--threads", "1"])
        .arg(spec("vectors/validate/second-stage-folds.ism.json"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["reportVersion"], "2.0");
    assert_eq!(report["verdict"], "invalid");
    assert_eq!(report["stages"][0]["status"], "skipped");
    assert_eq!(report["stages"][1]["status"], "invalid");
    let witness = &report["issues"]["messages"][1]["witness"];
    assert!(witness["det"].as_f64().unwrap() <= 0.0, "{report:#}");
}

#[test]
fn undetermined_exits_1() {
    let out = ism()
        .args(["validate", "--json"])
        .arg(spec("vectors/validate/undetermined-degree.ism.json"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["verdict"], "undetermined");
}

#[test]
fn unreadable_missing_and_bad_arguments_exit_2() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.ismb");
    std::fs::write(&bad, b"\x89ISM\r\n\x1a\ntruncated").unwrap();
    let out = ism().arg("validate").arg(&bad).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let out = ism()
        .arg("validate")
        .arg(dir.path().join("missing.ism.json"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    for budget in ["x", "0", "-3"] {
        let out = ism()
            .args(["validate", &format!("--max-pieces={budget}")])
            .arg(&bad)
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "--max-pieces={budget}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains("--max-pieces"), "{err}");
    }
}

#[test]
fn no_theorems_certifies_numerically_with_the_same_verdict() {
    let out = ism()
        .args(["validate", "--json", "--no-theorems"])
        .arg(spec("examples/cubic-face-point.ism.json"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(0));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let certs = report["stages"][0]["certificates"].as_object().unwrap();
    assert!(
        certs
            .keys()
            .all(|k| k == "Bernstein coefficients with subdivision" || k.starts_with("identity")),
        "{certs:?}"
    );
}
