//! `ism smooth` end to end: a fitted circle and the sphere example get smaller normal jumps
//! (ISM-401, the measure of `ism validate --quality`), and the output validates; with `--rational`,
//! linear models get a rational stage with a smaller C¹ residual (ISM-402).

mod common;

use std::path::Path;

use common::{assert_status, assert_validates, example, ism, json};

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
    assert_status(&out, 0);
    assert_validates(output);
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
    assert_status(&out, 0);
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
    let input = example("sphere.ism.json");
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
    assert_status(&out, 2);
}

/// `--rational` (JSON report): exit 0, the output validates, ISM-402 and ISM-401 drop.
fn rational(input: &Path, output: &Path, extra: &[&str]) -> serde_json::Value {
    let r = smooth(input, output, &[&["--rational"], extra].concat());
    assert_eq!(r["mode"], "rational", "{r}");
    assert_eq!(r["verdict"], "valid", "{r}");
    let f = |v: &serde_json::Value| v.as_f64().unwrap();
    let (rb, ra) = (&r["residualBefore"], &r["residualAfter"]);
    assert!(f(&ra["max"]) < 0.1 * f(&rb["max"]), "{r}");
    assert!(f(&ra["mean"]) < 0.1 * f(&rb["mean"]), "{r}");
    let (b, a) = (&r["before"], &r["after"]);
    assert!(f(&a["max"]) < f(&b["max"]), "{r}");
    assert!(f(&a["mean"]) < 0.5 * f(&b["mean"]), "{r}");
    assert!(f(&r["objectiveAfter"]) < f(&r["objectiveBefore"]), "{r}");
    r
}

#[test]
fn rational_on_the_linear_circle() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("c1.ism.json");
    let r = rational(&example("circle-linear.ism.json"), &out, &[]);
    assert_eq!(r["degree"], 2);
    assert_eq!(r["residualAfter"]["facets"], 18);

    // The written stage: one rational stage, every control point fixed, weights positive.
    let model: serde_json::Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
    let stages = model["stages"].as_array().unwrap();
    assert_eq!(stages.len(), 1);
    assert_eq!(stages[0]["kind"], "rational");
    let records = stages[0]["faces"].as_array().unwrap();
    assert!(!records.is_empty());
    assert!(records
        .iter()
        .flat_map(|f| f["weights"].as_array().unwrap())
        .all(|w| w.as_f64().unwrap() > 0.0));

    // Its output is a valid input again (a rational stage with fixed points), with --degree 2.
    let again = dir.path().join("again.ism.json");
    let out2 = ism()
        .arg("smooth")
        .arg(&out)
        .arg("-o")
        .arg(&again)
        .args(["--rational", "--degree", "2", "--json"])
        .output()
        .unwrap();
    assert_status(&out2, 0);
    let r2 = json(&out2.stdout);
    assert!(
        r2["objectiveAfter"].as_f64() <= r["objectiveAfter"].as_f64(),
        "{r2}"
    );

    // The text report names both measures.
    let text = ism()
        .arg("smooth")
        .arg(example("circle-linear.ism.json"))
        .arg("-o")
        .arg(dir.path().join("c1-text.ismb"))
        .args(["--rational", "--degree", "3", "--alpha", "1e-3"])
        .output()
        .unwrap();
    assert_status(&text, 0);
    let stdout = String::from_utf8_lossy(&text.stdout);
    for needle in [
        "ISM-402",
        "ISM-401",
        "rational degree 3",
        "validate         valid",
    ] {
        assert!(stdout.contains(needle), "{needle}: {stdout}");
    }
}

#[test]
fn rational_on_a_linear_sphere() {
    let dir = tempfile::tempdir().unwrap();
    let fitted = dir.path().join("sphere.ism.json");
    let out = ism()
        .args([
            "fit",
            "--preset",
            "sphere",
            "--resolution",
            "4",
            "--tolerance",
            "1",
        ])
        .args(["--no-topology", "--no-optimize", "-q", "-o"])
        .arg(&fitted)
        .output()
        .unwrap();
    assert_status(&out, 0);
    // Keep the complex and values only: the linear isocomplex.
    let mut model: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&fitted).unwrap()).unwrap();
    model["stages"] = serde_json::json!([]);
    let linear = dir.path().join("linear.ism.json");
    std::fs::write(&linear, serde_json::to_vec(&model).unwrap()).unwrap();
    let r = rational(&linear, &dir.path().join("c1.ismb"), &[]);
    assert_eq!(r["degree"], 3);
}

#[test]
fn rational_refuses_other_stages_with_exit_2() {
    let dir = tempfile::tempdir().unwrap();
    let out = ism()
        .arg("smooth")
        .arg(example("quadratic-edges.ism.json"))
        .arg("-o")
        .arg(dir.path().join("o.ism.json"))
        .arg("--rational")
        .output()
        .unwrap();
    assert_status(&out, 2);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("stage 0") && err.contains("bezier"), "{err}");
    assert!(!dir.path().join("o.ism.json").exists());
    // --degree needs --rational.
    let out = ism()
        .arg("smooth")
        .arg(example("circle-linear.ism.json"))
        .arg("-o")
        .arg(dir.path().join("o.ism.json"))
        .args(["--degree", "3"])
        .output()
        .unwrap();
    assert_status(&out, 2);
}
