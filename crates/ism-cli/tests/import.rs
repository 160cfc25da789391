//! `ism import` end to end: a legacy VTK mesh becomes a linear model; bad values exit with 2.

use std::process::Command;

const LEGACY: &str =
    "# vtk DataFile Version 4.2\ntwo tets\nASCII\nDATASET UNSTRUCTURED_GRID\nPOINTS 5 double\n\
0 0 0  1 0 0  0 1 0  0 0 1  1 1 1\nCELLS 2 10\n4 0 1 2 3\n4 1 3 2 4\nCELL_TYPES 2\n10 10\n\
POINT_DATA 5\nSCALARS phi double 1\nLOOKUP_TABLE default\n-1 1 1 1 2\n";

fn ism(args: &[&std::ffi::OsStr]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_ism"))
        .args(args)
        .output()
        .expect("run ism")
}

#[test]
fn legacy_vtk_becomes_a_positively_oriented_linear_model() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("two.vtk");
    std::fs::write(&src, LEGACY).unwrap();
    let out = dir.path().join("two.ism.json");
    let o = ism(&[
        "import".as_ref(),
        src.as_os_str(),
        out.as_os_str(),
        "--field".as_ref(),
        "phi".as_ref(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stderr).contains("1 re-oriented"));
    let info = ism(&["info".as_ref(), "--json".as_ref(), out.as_os_str()]);
    let s: serde_json::Value = serde_json::from_slice(&info.stdout).unwrap();
    assert_eq!(
        (
            s["dimension"].as_u64(),
            s["vertices"].as_u64(),
            s["simplices"].as_u64()
        ),
        (Some(3), Some(5), Some(2))
    );
    // The model reads back through the validator's structural checks (ism info would refuse it
    // otherwise) and exports: one corner inside, so a single small closed-off patch.
    let obj = dir.path().join("two.obj");
    let e = ism(&["export".as_ref(), out.as_os_str(), obj.as_os_str()]);
    assert!(e.status.success(), "{}", String::from_utf8_lossy(&e.stderr));
}

#[test]
fn value_on_the_level_is_refused_with_status_2() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("two.vtk");
    std::fs::write(&src, LEGACY).unwrap();
    let out = dir.path().join("two.ism.json");
    let o = ism(&[
        "import".as_ref(),
        src.as_os_str(),
        out.as_os_str(),
        "--level".as_ref(),
        "2".as_ref(),
    ]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("equals the level"));
    assert!(!out.exists());
}
