//! `ism fit` end to end: presets and expressions, the written model validates, report, exit codes.

use std::process::Command;

fn ism() -> Command {
    Command::new(env!("CARGO_BIN_EXE_ism"))
}

fn report(stdout: &[u8]) -> serde_json::Value {
    serde_json::from_slice(stdout).expect("--json prints one JSON object")
}

#[test]
fn circle_preset_fits_validates_and_draws() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("circle.ism.json");
    let svg = dir.path().join("circle.svg");
    let out = ism()
        .args([
            "fit",
            "--preset",
            "circle",
            "--resolution",
            "6",
            "--tolerance",
            "1e-4",
            "--json",
            "-q",
            "-o",
        ])
        .arg(&model)
        .arg("--svg")
        .arg(&svg)
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r = report(&out.stdout);
    assert_eq!(r["toleranceMet"], true);
    assert!(r["maxDistance"].as_f64().unwrap() <= 1e-4);
    assert_eq!(r["components"], 1);
    assert_eq!(r["euler"], 0);
    assert_eq!(r["pvFailures"], 0);
    assert!(r["parameters"].as_u64().unwrap() > 0);
    let picture = std::fs::read_to_string(&svg).unwrap();
    assert!(picture.starts_with("<svg") && picture.contains("<circle"));

    let check = ism().arg("validate").arg(&model).output().unwrap();
    assert_eq!(
        check.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&check.stdout)
    );
}

#[test]
fn expression_with_negative_domain_fits() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("ellipse.ismb");
    let out = ism()
        .args([
            "fit",
            "--expr",
            "x^2 + 2*y^2 - 0.5",
            "--domain",
            "-1,1,-1,1",
            "--tolerance",
            "1e-3",
            "--json",
            "-q",
            "-o",
        ])
        .arg(&model)
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(report(&out.stdout)["components"], 1);
    let check = ism().arg("validate").arg(&model).output().unwrap();
    assert_eq!(
        check.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&check.stdout)
    );
}

#[test]
fn tolerance_not_met_exits_1_but_writes_the_model() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("taubin.ism.json");
    let out = ism()
        .args([
            "fit",
            "--preset",
            "taubin",
            "--resolution",
            "4",
            "--tolerance",
            "1e-9",
            "--max-simplices",
            "300",
            "--no-topology",
            "-q",
            "-o",
        ])
        .arg(&model)
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(1),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stderr).contains("not met"));
    assert!(model.exists());
}

#[test]
fn bad_arguments_exit_2() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("x.ism.json");
    for args in [
        vec!["fit", "--preset", "nope"],
        vec!["fit", "--expr", "x^2 + w", "--domain", "0,1,0,1"],
        vec!["fit", "--expr", "x^2 + (y", "--domain", "0,1,0,1"],
        vec!["fit", "--expr", "x + y", "--domain", "0,1,0,1,0"],
        vec!["fit", "--expr", "x + y", "--domain", "1,0,0,1"],
        vec!["fit", "--preset", "circle", "--tolerance", "-1"],
    ] {
        let out = ism().args(&args).arg("-o").arg(&model).output().unwrap();
        assert_eq!(
            out.status.code(),
            Some(2),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(!model.exists(), "{args:?} wrote a file");
    }
}

#[test]
fn list_presets_names_all_five() {
    let out = ism().args(["fit", "--list-presets"]).output().unwrap();
    assert_eq!(out.status.code(), Some(0));
    let text = String::from_utf8(out.stdout).unwrap();
    for name in ["circle", "taubin", "sphere", "torus", "genus2"] {
        assert!(text.contains(name), "{text}");
    }
}

#[test]
fn sphere_preset_fits_in_3d_with_the_true_topology_and_validates() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("sphere.ismb");
    let out = ism()
        .args([
            "fit",
            "--preset",
            "sphere",
            "--resolution",
            "4",
            "--tolerance",
            "1e-2",
            "--json",
            "-q",
            "-o",
        ])
        .arg(&model)
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r = report(&out.stdout);
    assert_eq!(
        (r["components"].as_u64(), r["euler"].as_i64()),
        (Some(1), Some(2))
    );
    assert_eq!(r["topologyMatchesPreset"], true);
    let check = ism().arg("validate").arg(&model).output().unwrap();
    assert_eq!(
        check.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&check.stdout)
    );
}
