//! `ism export` end to end: formats by extension, JSON summary, exit statuses.

use std::path::{Path, PathBuf};
use std::process::Command;

fn example(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../spec/examples")
        .join(name)
}

fn ism(args: &[&std::ffi::OsStr]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_ism"))
        .args(args)
        .output()
        .expect("run ism")
}

fn export(input: &Path, output: &Path, extra: &[&str]) -> std::process::Output {
    let mut args: Vec<&std::ffi::OsStr> =
        vec!["export".as_ref(), input.as_os_str(), output.as_os_str()];
    args.extend(extra.iter().map(|s| std::ffi::OsStr::new(*s)));
    ism(&args)
}

#[test]
fn curve_export_writes_obj_lines_and_reports_a_closed_curve() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("circle.obj");
    let o = export(
        &example("circle-curved.ism.json"),
        &out,
        &["--tolerance", "1e-4", "--json"],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(summary["components"], 1);
    assert_eq!(summary["euler_characteristic"], 0);
    assert_eq!(summary["boundary_edges"], 0);
    let text = std::fs::read_to_string(&out).unwrap();
    let segments = text.lines().filter(|l| l.starts_with("l ")).count();
    assert_eq!(segments as u64, summary["cells"].as_u64().unwrap());
    assert!(text.lines().filter(|l| l.starts_with("v ")).count() > 8);
}

#[test]
fn every_extension_writes_a_file() {
    let dir = tempfile::tempdir().unwrap();
    for ext in ["obj", "gltf", "glb", "vtk", "vtu"] {
        let out = dir.path().join(format!("sphere.{ext}"));
        let o = export(&example("sphere.ism.json"), &out, &["--linear"]);
        assert!(
            o.status.success(),
            "{ext}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        assert!(std::fs::metadata(&out).unwrap().len() > 1000, "{ext}");
    }
    let glb = std::fs::read(dir.path().join("sphere.glb")).unwrap();
    assert_eq!(&glb[..4], b"glTF");
    assert_eq!(glb.len() % 4, 0);
}

#[test]
fn volume_export_names_exactness() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("q.vtu");
    let o = export(&example("quadratic-edges.ism.json"), &out, &["--volume"]);
    assert!(o.status.success());
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(stderr.contains("F is exact"), "{stderr}");
    let text = std::fs::read_to_string(&out).unwrap();
    assert!(text.contains(r#"<PointData Scalars="F">"#));
}

#[test]
fn bad_arguments_and_unreadable_input_exit_with_2_and_leave_no_file() {
    let dir = tempfile::tempdir().unwrap();
    let cases: [(PathBuf, PathBuf, &[&str]); 3] = [
        (example("sphere.ism.json"), dir.path().join("x.stl"), &[]),
        (
            example("sphere.ism.json"),
            dir.path().join("x.obj"),
            &["--volume"],
        ),
        (
            dir.path().join("missing.ism.json"),
            dir.path().join("y.obj"),
            &[],
        ),
    ];
    for (input, output, extra) in cases {
        let o = export(&input, &output, extra);
        assert_eq!(
            o.status.code(),
            Some(2),
            "{}",
            String::from_utf8_lossy(&o.stderr)
        );
        assert!(!output.exists());
    }
}
