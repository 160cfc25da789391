//! `ism fit --hermite` end to end: the example handles file, editing a model, bad handles.

mod common;

use std::path::PathBuf;

use common::{assert_status, assert_validates, example, ism, json};

fn handles() -> PathBuf {
    example("hermite/ellipse.hermite.json")
}

#[test]
fn example_handles_fit_validate_and_draw() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("ellipse.ism.json");
    let svg = dir.path().join("ellipse.svg");
    let out = ism()
        .args(["fit", "--json", "--hermite"])
        .arg(handles())
        .arg("-o")
        .arg(&model)
        .arg("--svg")
        .arg(&svg)
        .output()
        .unwrap();
    assert_status(&out, 0);
    let r = json(&out.stdout);
    assert_eq!(r["handles"].as_array().unwrap().len(), 18);
    assert!(r["maxPositionError"].as_f64().unwrap() < 1e-9);
    let (before, after) = (
        r["meanAngleBefore"].as_f64().unwrap(),
        r["meanAngleAfter"].as_f64().unwrap(),
    );
    assert!(after < 0.5 * before, "{r}");
    assert!(r["objectiveAfter"].as_f64().unwrap() < r["objectiveBefore"].as_f64().unwrap());
    assert_eq!(r["verdict"], "valid");
    assert!(std::fs::read_to_string(&svg).unwrap().starts_with("<svg"));
    assert_validates(&model);

    // Edit the result: the handles file names the model, turns one normal and moves a crossing.
    let mut data: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(handles()).unwrap()).unwrap();
    let obj = data.as_object_mut().unwrap();
    for key in ["dimension", "vertices", "simplices", "values"] {
        obj.remove(key);
    }
    obj.insert("model".into(), "ellipse.ism.json".into());
    let h0 = &mut obj.get_mut("handles").unwrap()[0];
    let t = h0["t"].as_f64().unwrap();
    h0["t"] = serde_json::json!(t + 0.02);
    let edit = dir.path().join("edit.hermite.json");
    std::fs::write(&edit, serde_json::to_string(&data).unwrap()).unwrap();
    let edited = dir.path().join("edited.ismb");
    let out = ism()
        .args(["fit", "--json", "--hermite"])
        .arg(&edit)
        .arg("-o")
        .arg(&edited)
        .output()
        .unwrap();
    assert_status(&out, 0);
    let r = json(&out.stdout);
    assert_eq!(r["blockAdded"], false);
    assert!(r["maxPositionError"].as_f64().unwrap() < 1e-9, "{r}");
    assert_validates(&edited);
}

#[test]
fn bad_handles_exit_2_with_the_handle_named() {
    let dir = tempfile::tempdir().unwrap();
    let mut data: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(handles()).unwrap()).unwrap();
    let n = &mut data["handles"][3]["normal"];
    *n = serde_json::json!([-n[0].as_f64().unwrap(), -n[1].as_f64().unwrap()]);
    let bad = dir.path().join("bad.hermite.json");
    std::fs::write(&bad, serde_json::to_string(&data).unwrap()).unwrap();
    let out = ism()
        .args(["fit", "--hermite"])
        .arg(&bad)
        .arg("-o")
        .arg(dir.path().join("x.ism.json"))
        .output()
        .unwrap();
    assert_status(&out, 2);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("handle 3") && err.contains("outside"), "{err}");
    assert!(!dir.path().join("x.ism.json").exists());
}
