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

/// The default export is coarsened (the same as `--coarsen`): fewer triangles than
/// `--no-coarsen`, the refined export's topology, closed; `--coarsen` is refused with `--linear`
/// and with `--no-coarsen`.
#[test]
fn coarsened_export_has_fewer_triangles_and_the_same_topology() {
    let dir = tempfile::tempdir().unwrap();
    let run = |extra: &[&str]| {
        let out = dir.path().join("t.obj");
        let mut args = vec!["--tolerance", "1e-4", "--json", "-q"];
        args.extend_from_slice(extra);
        let o = export(&example("torus.ism.json"), &out, &args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        serde_json::from_slice::<serde_json::Value>(&o.stdout).unwrap()
    };
    let (fine, coarse) = (run(&["--no-coarsen"]), run(&[]));
    let mut explicit = run(&["--coarsen"]);
    // Everything but the timing.
    explicit["extract_seconds"] = coarse["extract_seconds"].clone();
    assert_eq!(explicit, coarse);
    assert!(coarse["cells"].as_u64().unwrap() < fine["cells"].as_u64().unwrap());
    for key in ["components", "euler_characteristic", "boundary_edges"] {
        assert_eq!(coarse[key], fine[key], "{key}");
    }
    assert_eq!(coarse["boundary_edges"], 0);
    let o = export(
        &example("torus.ism.json"),
        &dir.path().join("l.obj"),
        &["--coarsen", "--linear"],
    );
    assert_eq!(o.status.code(), Some(2));
    let o = export(
        &example("torus.ism.json"),
        &dir.path().join("c.obj"),
        &["--coarsen", "--no-coarsen"],
    );
    assert_eq!(o.status.code(), Some(2));
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

/// `--volume` states how far the written field is from F: exact cells (F itself, a certified
/// rounding-level bound) where the stages allow them, an estimate (`field_error_certified: false`)
/// for a model with an implicit stage before a parametric one; an explicit `--field-tolerance` is
/// honoured.
#[test]
fn volume_export_states_its_field_error() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("q.vtu");
    for (model, certified, exact) in [
        ("quadratic-edges.ism.json", true, true),
        ("sphere.ism.json", true, true),
        ("two-stage.ism.json", false, false),
    ] {
        let o = export(
            &example(model),
            &out,
            &["--volume", "--json", "--field-tolerance", "1e-4"],
        );
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(r["field_error_certified"], certified, "{model}: {r}");
        assert_eq!(r["field_exact"], exact, "{model}: {r}");
        assert_eq!(r["field_tolerance"], 1e-4, "{model}: {r}");
        let bound = r["field_error_bound"].as_f64().unwrap();
        assert!(bound <= 1e-4, "{model}: {r}");
        assert_eq!(r["field_tolerance_met"], true, "{model}: {r}");
        // The method line (certified or estimated, and why) is part of the summary too.
        assert!(
            r["field_note"].as_str().is_some_and(|s| !s.is_empty()),
            "{model}: {r}"
        );
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(stderr.contains("max |F_vtk − F| ≤"), "{stderr}");
        // The XML before the binary arrays (the raw `AppendedData` section).
        let bytes = std::fs::read(&out).unwrap();
        let header = bytes
            .windows(b"<AppendedData".len())
            .position(|w| w == b"<AppendedData")
            .expect("an AppendedData section");
        let text = std::str::from_utf8(&bytes[..header]).unwrap();
        // F is the active scalars (and the weights, when the cells are rational, the active
        // RationalWeights: `<PointData Scalars="F" RationalWeights="RationalWeights">`).
        assert!(text.contains(r#"<PointData Scalars="F""#), "{model}");
    }
    // --field-tolerance needs --volume.
    let o = export(
        &example("sphere.ism.json"),
        &dir.path().join("s.obj"),
        &["--field-tolerance", "1e-3"],
    );
    assert_eq!(o.status.code(), Some(2));
}

#[test]
fn bad_arguments_and_unreadable_input_exit_with_2_and_leave_no_file() {
    let dir = tempfile::tempdir().unwrap();
    let cases: [(PathBuf, PathBuf, &[&str]); 4] = [
        (example("sphere.ism.json"), dir.path().join("x.stl"), &[]),
        (
            example("sphere.ism.json"),
            dir.path().join("z.obj"),
            &["--compress"],
        ),
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

/// Models whose stages fold (the validator's fold vectors, `ism validate` exit 1) stop at the
/// first vertex placed on the far sheet: exit 2 at once, naming the simplex, the point and the
/// Jacobian determinant, no file left. `quartic-fold-3d` at 1e-4 ran over 300 CPU-s and 5 GB
/// before (the refinement never converges across a fold); the others wrote a mesh that is not the
/// model's shape (one with boundary) and exited 0.
#[test]
fn folded_models_exit_with_2_at_the_fold() {
    let dir = tempfile::tempdir().unwrap();
    let vectors = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../spec/vectors/validate");
    for name in [
        "quartic-fold-3d.ism.json",
        "fig2-quartic-fold-2d.ism.json",
        "second-stage-folds.ism.json",
    ] {
        let output = dir.path().join("fold.obj");
        let o = export(&vectors.join(name), &output, &["--tolerance", "1e-4"]);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{name}: {stderr}");
        assert!(
            stderr.contains("the stages fold at u = [")
                && stderr.contains("Jacobian determinant -"),
            "{name}: {stderr}"
        );
        assert!(!output.exists(), "{name}");
    }
}

/// Issue 19: models that validate must export. Two that did not, both failing with "stage
/// inversion did not converge … (residual 1.0000056e-12)" / "(residual 3.2e-12)" and exit 1:
/// the `ism smooth --rational` output of the sphere example's linear isocomplex (Newton stopped a
/// hair under 1e-12, and the re-evaluation without the Jacobian landed a hair over), and a
/// `--rational` fit of a thin ellipsoid at 1e-2 (a patch corner 1e-10 from a vertex, where the
/// composed parametric map cannot be evaluated to 1e-12). Both must now validate, export with
/// exit 0, and give a closed surface with the ellipsoid's/sphere's topology.
#[test]
fn certified_valid_rational_models_export() {
    let dir = tempfile::tempdir().unwrap();
    let mut model: serde_json::Value =
        serde_json::from_slice(&std::fs::read(example("sphere.ism.json")).unwrap()).unwrap();
    model["stages"] = serde_json::json!([]);
    let linear = dir.path().join("linear.ism.json");
    std::fs::write(&linear, serde_json::to_vec(&model).unwrap()).unwrap();
    let smoothed = dir.path().join("smoothed.ism.json");
    let o = ism(&[
        "smooth".as_ref(),
        linear.as_os_str(),
        "-o".as_ref(),
        smoothed.as_os_str(),
        "--rational".as_ref(),
        "-q".as_ref(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let fitted = dir.path().join("ellipsoid.ism.json");
    let o = ism(&[
        "fit".as_ref(),
        "--expr".as_ref(),
        "(x/0.9)^2+(y/0.5)^2+(z/0.2)^2-1".as_ref(),
        "--domain=-1,1,-1,1,-1,1".as_ref(),
        "--rational".as_ref(),
        "--tolerance".as_ref(),
        "1e-2".as_ref(),
        "-q".as_ref(),
        "-o".as_ref(),
        fitted.as_os_str(),
    ]);
    // Exit 1 is fine here: since issue 17 the fit measures target → fit too, and this thin
    // ellipsoid at 1e-2 is reported as not meeting the tolerance; the model is written anyway.
    assert!(
        matches!(o.status.code(), Some(0 | 1)) && fitted.exists(),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    for (model, tolerance) in [(&smoothed, "1e-4"), (&fitted, "1e-3")] {
        let o = ism(&["validate".as_ref(), model.as_os_str(), "-q".as_ref()]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stdout));
        let out = dir.path().join("out.obj");
        let o = export(model, &out, &["--tolerance", tolerance, "--json", "-q"]);
        assert!(
            o.status.success(),
            "{}: {}",
            model.display(),
            String::from_utf8_lossy(&o.stderr)
        );
        let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(summary["components"], 1, "{summary}");
        assert_eq!(summary["euler_characteristic"], 2, "{summary}");
        assert_eq!(summary["boundary_edges"], 0, "{summary}");
    }
}

/// Edges the refinement leaves at the depth limit while their chordal test fails are named on the
/// summary line, with the count `--json` gives; an export without any says nothing of it.
#[test]
fn edges_left_at_the_depth_limit_are_reported() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("e.obj");
    // Two halvings of each patch edge are far from what 1e-4 needs on the torus example: edges
    // still long stay at the limit. (The fitted rational ellipsoid of
    // tests/python/test_export_rational.py kept four at the default depth until session 33's
    // normals prediction and escape separation; it now keeps none.)
    let o = export(
        &example("torus.ism.json"),
        &out,
        &["--tolerance", "1e-4", "--max-depth", "2", "--json", "-q"],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let n = summary["depth_limited_edges"].as_u64().unwrap();
    assert!(n > 0, "{summary}");
    // Two halvings leave edges whose midpoints are far off at 1e-4: the measured distance is
    // above what the test allows (0.75 of the tolerance) and below the torus's size.
    let error = summary["depth_limited_error"].as_f64().unwrap();
    assert!(error > 0.75e-4 && error < 0.1, "{summary}");
    let line = String::from_utf8_lossy(&o.stderr);
    assert!(
        line.contains(&format!(
            ", {n} edge{} at the depth limit (--max-depth) still failing the chordal test \
             (which holds edges to 0.75 of --tolerance; measured up to {error:.3e} from the shape \
             there)",
            if n == 1 { "" } else { "s" }
        )),
        "{line}"
    );
    let o = export(&example("sphere.ism.json"), &out, &["--json", "-q"]);
    assert!(o.status.success());
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(summary["depth_limited_edges"], 0);
    assert_eq!(summary["depth_limited_error"], 0.0);
    assert!(!String::from_utf8_lossy(&o.stderr).contains("depth limit"));
}
