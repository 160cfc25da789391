//! Issue 16, items 8–10: every bad input is refused with exit 2 and a message that names the
//! argument; options that do not apply are refused, not ignored; misleading wording is gone.

mod common;

use common::{assert_refused_with, assert_status, example, ism};

fn run(args: &[&str]) -> std::process::Output {
    ism().args(args).output().unwrap()
}

#[test]
fn unknown_preset_names_the_option_and_the_known_ones() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("x.ismb");
    let err = assert_refused_with(
        &run(&["fit", "--preset", "nosuch", "-o", out.to_str().unwrap()]),
        &["--preset", "unknown preset `nosuch`", "circle"],
    );
    assert!(!err.contains("options:"), "{err}");
}

#[test]
fn out_of_range_numbers_name_the_argument() {
    let sphere = example("sphere.ism.json");
    let sphere = sphere.to_str().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("x.ismb");
    let out = out.to_str().unwrap();
    let obj = dir.path().join("x.obj");
    let obj = obj.to_str().unwrap();
    for (args, arg) in [
        (
            vec!["fit", "--preset", "circle", "--tolerance", "0", "-o", out],
            "--tolerance",
        ),
        (
            vec!["fit", "--preset", "circle", "--tolerance", "-1", "-o", out],
            "--tolerance",
        ),
        (
            vec!["fit", "--preset", "circle", "--resolution", "0", "-o", out],
            "--resolution",
        ),
        (
            vec![
                "fit",
                "--preset",
                "circle",
                "--mesh-margin",
                "-0.5",
                "-o",
                out,
            ],
            "--mesh-margin",
        ),
        (
            vec!["export", sphere, obj, "--tolerance", "0"],
            "--tolerance",
        ),
        (
            vec!["export", sphere, obj, "--tolerance", "-1"],
            "--tolerance",
        ),
        (
            vec!["sample", sphere, "--near-surface", "10", "--sigma", "-1"],
            "--sigma",
        ),
        (
            vec!["smooth", sphere, "-o", out, "--alpha", "-1"],
            "--alpha",
        ),
    ] {
        let err = assert_refused_with(&run(&args), &[arg]);
        // Not "model not supported", and not clap's tip to write `-- -1`.
        assert!(
            !err.contains("not supported") && !err.contains("'-- "),
            "{args:?}: {err}"
        );
    }
}

#[test]
fn failed_write_names_the_path_once_and_no_temporary_file() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("no-such-dir");
    let sphere = example("circle-curved.ism.json");
    for (sub, name) in [("convert", "x.ismb"), ("export", "x.obj")] {
        let target = missing.join(name);
        let out = ism().arg(sub).arg(&sphere).arg(&target).output().unwrap();
        let err = assert_refused_with(&out, &["cannot write", "does not exist"]);
        assert_eq!(
            err.matches(target.to_str().unwrap()).count(),
            1,
            "{sub}: {err}"
        );
        // The temporary file beside the target is named `.ism-*.tmp`.
        assert!(
            !err.contains(".ism-") && !err.contains("at path"),
            "{sub}: {err}"
        );
    }
}

#[test]
fn doubled_operator_says_what_was_expected_where() {
    assert_refused_with(
        &run(&[
            "fit", "--expr", "x^^2", "--domain", "0,1,0,1", "-o", "x.ismb",
        ]),
        &["--expr", "after `^`", "character 3"],
    );
}

#[test]
fn fit_without_a_source_lists_every_source() {
    assert_refused_with(
        &run(&["fit"]),
        &["--expr", "--preset", "--mesh", "--hermite"],
    );
}

#[test]
fn options_that_do_not_apply_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let circle = example("circle-curved.ism.json");
    let circle = circle.to_str().unwrap();
    assert_refused_with(
        &run(&["sample", circle, "--surface", "10", "--sigma", "0.1"]),
        &["--sigma applies to --near-surface only"],
    );
    for (name, flag) in [("x.ismb", "--pretty"), ("x.ism.msgpack", "--container")] {
        let target = dir.path().join(name);
        let out = run(&["convert", circle, target.to_str().unwrap(), flag]);
        assert_refused_with(&out, &[flag, "JSON output only"]);
        assert!(!target.exists());
    }
    // --pretty with JSON output still works.
    let json = dir.path().join("x.ism.json");
    assert_status(
        &run(&["convert", circle, json.to_str().unwrap(), "--pretty"]),
        0,
    );
}

#[test]
fn query_lines_must_hold_the_model_dimension() {
    let sphere = example("sphere.ism.json");
    let mut child = ism()
        .args(["query", sphere.to_str().unwrap(), "-"])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    std::io::Write::write_all(child.stdin.as_mut().unwrap(), b"0 0 0\n0.1 0.2 0.3 0.4\n").unwrap();
    drop(child.stdin.take());
    let out = child.wait_with_output().unwrap();
    assert_refused_with(&out, &["line 2", "4 numbers, expected 3"]);
}

#[test]
fn functions_without_a_zero_set_a_pole_or_nan_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("x.ismb");
    let out = out.to_str().unwrap();
    let cases: [(&[&str], &[&str]); 4] = [
        // x² + y² + 5 ≥ 5 everywhere.
        (
            &["--expr", "x^2+y^2+5", "--domain", "-1,1,-1,1"],
            &["no zero set", "positive"],
        ),
        // 1/x at the grid vertex x = 0 of [-1, 1]: not finite there.
        (
            &["--expr", "1/x", "--domain", "-1,1,-1,1"],
            &["g is inf", "not defined"],
        ),
        // 1/x changes sign between the grid lines x = -0.15 and x = 0.1 without a zero.
        (
            &[
                "--expr",
                "1/x",
                "--domain",
                "-0.9,1.1,-1,1",
                "--no-topology",
            ],
            &["without a zero", "pole"],
        ),
        // sqrt(x) is NaN for x < 0.
        (
            &["--expr", "sqrt(x)-0.5", "--domain", "-1,1,-1,1"],
            &["g is NaN", "not defined"],
        ),
    ];
    for (args, words) in cases {
        let mut all = vec!["fit", "-q", "-o", out];
        all.extend_from_slice(args);
        assert_refused_with(&run(&all), words);
        assert!(
            !std::path::Path::new(out).exists(),
            "{args:?} wrote a model"
        );
    }
}

#[cfg(unix)]
#[test]
fn binary_output_to_a_terminal_is_refused() {
    let circle = example("circle-curved.ism.json");
    for format in ["npy", "ply"] {
        let (_controller, terminal) = common::pseudo_terminal();
        let out = ism()
            .args([
                "sample",
                circle.to_str().unwrap(),
                "--surface",
                "10",
                "--format",
                format,
            ])
            .stdout(terminal)
            .output()
            .unwrap();
        assert_refused_with(&out, &[&format!("--format {format} is binary"), "-o FILE"]);
    }
    // CSV to a terminal is fine.
    let (_controller, terminal) = common::pseudo_terminal();
    let out = ism()
        .args([
            "sample",
            circle.to_str().unwrap(),
            "--surface",
            "10",
            "--format",
            "csv",
        ])
        .stdout(terminal)
        .output()
        .unwrap();
    assert_status(&out, 0);
}

#[test]
fn info_on_a_structurally_broken_file_exits_1_like_validate() {
    let broken = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../spec/vectors/reader/index-out-of-range.ism.json");
    let out = run(&["info", broken.to_str().unwrap()]);
    assert_status(&out, 1);
    assert!(String::from_utf8_lossy(&out.stderr).contains("ISM-104"));
    assert_status(&run(&["validate", broken.to_str().unwrap()]), 1);
    // Unreadable stays 2.
    let crc = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../spec/vectors/reader/bad-header-crc.ismb");
    assert_status(&run(&["info", crc.to_str().unwrap()]), 2);
}

#[test]
fn smooth_rational_on_two_stages_says_what_it_needs() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("x.ism.json");
    let model = example("two-stage.ism.json");
    assert_refused_with(
        &run(&[
            "smooth",
            model.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--rational",
        ]),
        &["--rational", "has 2 stages", "without --rational"],
    );
}

#[test]
fn every_parallel_command_takes_j_and_threads() {
    let dir = tempfile::tempdir().unwrap();
    let circle = example("circle-curved.ism.json");
    let circle = circle.to_str().unwrap();
    let obj = dir.path().join("c.obj");
    let model = dir.path().join("c.ism.json");
    let smoothed = dir.path().join("s.ism.json");
    let pts = dir.path().join("p.csv");
    std::fs::write(&pts, "0 0\n").unwrap();
    for flag in ["-j", "--threads"] {
        for args in [
            vec!["validate", circle, flag, "1"],
            vec!["export", circle, obj.to_str().unwrap(), flag, "1", "-q"],
            vec!["sample", circle, "--surface", "5", flag, "1", "-q"],
            vec!["query", circle, pts.to_str().unwrap(), flag, "1", "-q"],
            vec![
                "fit",
                "--preset",
                "circle",
                "--resolution",
                "4",
                "--tolerance",
                "1e-2",
                "-o",
                model.to_str().unwrap(),
                flag,
                "1",
                "-q",
            ],
            vec![
                "smooth",
                circle,
                "-o",
                smoothed.to_str().unwrap(),
                "--iterations",
                "1",
                flag,
                "1",
                "-q",
            ],
        ] {
            let out = run(&args);
            assert_status(&out, 0);
        }
    }
}
