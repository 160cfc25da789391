//! `ism sample` end to end: formats, reproducibility across thread counts, labels, exit codes.

use std::path::PathBuf;
use std::process::{Command, Output};

fn ism() -> Command {
    Command::new(env!("CARGO_BIN_EXE_ism"))
}

fn example(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../spec/examples")
        .join(name)
}

fn run(args: &[&str]) -> Output {
    ism().arg("sample").args(args).output().unwrap()
}

fn ok(out: &Output) {
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn csv_rows(text: &str) -> (Vec<String>, Vec<Vec<f64>>) {
    let mut lines = text.lines();
    let header = lines
        .next()
        .unwrap()
        .split(',')
        .map(str::to_string)
        .collect();
    let rows = lines
        .map(|l| l.split(',').map(|x| x.parse::<f64>().unwrap()).collect())
        .collect();
    (header, rows)
}

#[test]
fn surface_csv_on_stdout_lies_on_the_curve() {
    let model = example("circle-curved.ism.json");
    let out = run(&[model.to_str().unwrap(), "--surface", "500", "--seed", "3"]);
    ok(&out);
    let (header, rows) = csv_rows(&String::from_utf8(out.stdout).unwrap());
    assert_eq!(header, ["x", "y", "nx", "ny", "f", "simplex"]);
    assert_eq!(rows.len(), 500);
    let level = ism_format::io::read_path(&model).unwrap().model.level;
    for r in &rows {
        assert!(
            (r[4] - level).abs() < 1e-8,
            "F = {} off the level {level}",
            r[4]
        );
        assert!((r[2].hypot(r[3]) - 1.0).abs() < 1e-12, "normal not unit");
        assert!(r[5] >= 0.0);
    }
}

#[test]
fn same_seed_is_bit_identical_for_one_and_two_threads() {
    let dir = tempfile::tempdir().unwrap();
    let model = example("cubic-face-point.ism.json");
    let mut files = Vec::new();
    for (threads, seed) in [("1", "5"), ("2", "5"), ("2", "6")] {
        let path = dir.path().join(format!("s{threads}-{seed}.npy"));
        let out = run(&[
            model.to_str().unwrap(),
            "--surface",
            "9000",
            "--seed",
            seed,
            "-j",
            threads,
            "-o",
            path.to_str().unwrap(),
        ]);
        ok(&out);
        files.push(std::fs::read(&path).unwrap());
    }
    assert!(files[0].starts_with(b"\x93NUMPY"));
    assert_eq!(files[0], files[1], "thread count changed the output");
    assert_ne!(files[1], files[2], "seed did not change the output");
}

#[test]
fn volume_in_a_box_labels_points_outside_the_complex() {
    let model = example("circle-curved.ism.json");
    let doc = ism_format::io::read_path(&model).unwrap().model;
    let out = run(&[
        model.to_str().unwrap(),
        "--volume",
        "2000",
        "--box",
        "-3,-3,3,3",
        "--format",
        "csv",
    ]);
    ok(&out);
    let (header, rows) = csv_rows(&String::from_utf8(out.stdout).unwrap());
    assert_eq!(header, ["x", "y", "f", "label", "simplex"]);
    let outside = rows.iter().filter(|r| r[4] < 0.0).count();
    assert!(outside > 0 && outside < rows.len());
    for r in &rows {
        if r[4] < 0.0 {
            assert!(r[2].is_nan() && r[3] == -1.0);
        } else {
            assert_eq!(r[3], f64::from(u8::from(r[2] < doc.level)));
        }
    }
}

#[test]
fn ply_binary_and_ascii_headers() {
    let dir = tempfile::tempdir().unwrap();
    let model = example("circle-curved.ism.json");
    let bin = dir.path().join("a.ply");
    ok(&run(&[
        model.to_str().unwrap(),
        "--near-surface",
        "100",
        "--sigma",
        "0.01",
        "-o",
        bin.to_str().unwrap(),
    ]));
    let bytes = std::fs::read(&bin).unwrap();
    let text = String::from_utf8_lossy(&bytes[..200]);
    assert!(
        text.starts_with("ply\nformat binary_little_endian 1.0\n"),
        "{text}"
    );
    assert!(text
        .contains("element vertex 100\nproperty double x\nproperty double y\nproperty double z\n"));
    let asc = dir.path().join("b.ply");
    ok(&run(&[
        model.to_str().unwrap(),
        "--surface",
        "10",
        "--format",
        "ply-ascii",
        "-o",
        asc.to_str().unwrap(),
    ]));
    let text = std::fs::read_to_string(&asc).unwrap();
    assert!(text.contains("format ascii 1.0\n") && text.contains("property double nz\n"));
    let body = text.split("end_header\n").nth(1).unwrap();
    assert_eq!(body.lines().count(), 10);
}

#[test]
fn bad_arguments_exit_2() {
    let model = example("circle-curved.ism.json");
    let m = model.to_str().unwrap();
    for args in [
        vec![m],
        vec![m, "--surface", "10", "--volume", "10"],
        vec![m, "--near-surface", "10"],
        vec![m, "--near-surface", "10", "--sigma", "-1"],
        vec![m, "--volume", "10", "--box", "0,0,1"],
        vec![m, "--surface", "10", "-o", "/tmp/x.unknown-extension"],
        vec!["/nonexistent/model.ism.json", "--surface", "10"],
    ] {
        let out = run(&args);
        assert_eq!(
            out.status.code(),
            Some(2),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
}
