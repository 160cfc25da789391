//! `ism fit` end to end: presets and expressions, the written model validates, report, exit codes.

mod common;

use common::{assert_status, assert_validates, example, ism, json};

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
    assert_status(&out, 0);
    let r = json(&out.stdout);
    assert_eq!(r["toleranceMet"], true);
    assert!(r["maxDistance"].as_f64().unwrap() <= 1e-4);
    assert_eq!(r["components"], 1);
    assert_eq!(r["euler"], 0);
    assert_eq!(r["pvFailures"], 0);
    assert!(r["parameters"].as_u64().unwrap() > 0);
    let picture = std::fs::read_to_string(&svg).unwrap();
    assert!(picture.starts_with("<svg") && picture.contains("<circle"));

    assert_validates(&model);
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
    assert_status(&out, 0);
    assert_eq!(json(&out.stdout)["components"], 1);
    assert_validates(&model);
}

/// Issue 16: `--expr -x^2-y^2+0.25` (no `=`, leading minus) is the disc of radius 0.5, i.e. a circle:
/// one component, Euler characteristic 0, not the two branches of a hyperbola.
#[test]
fn leading_minus_expression_is_a_circle() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("disc.ismb");
    let out = ism()
        .args([
            "fit",
            "--expr",
            "-x^2-y^2+0.25",
            "--domain",
            "-1,1,-1,1",
            "--json",
            "-q",
            "-o",
        ])
        .arg(&model)
        .output()
        .unwrap();
    assert_status(&out, 0);
    let r = json(&out.stdout);
    assert_eq!(r["components"], 1);
    assert_eq!(r["euler"], 0);
    assert_validates(&model);
}

#[test]
fn help_documents_the_expression_grammar() {
    let out = ism().args(["fit", "--help"]).output().unwrap();
    assert_status(&out, 0);
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.contains("-x^2 = -(x^2)"), "{text}");
    assert!(text.contains("right to left"), "{text}");
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
    assert_status(&out, 1);
    assert!(String::from_utf8_lossy(&out.stderr).contains("not met"));
    assert!(model.exists());
}

/// `ism ARGS -o MODEL` exits 2 and writes nothing.
#[track_caller]
fn assert_refused(args: &[&str], model: &std::path::Path) {
    let out = ism().args(args).arg("-o").arg(model).output().unwrap();
    assert_eq!(
        out.status.code(),
        Some(2),
        "{args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(!model.exists(), "{args:?} wrote a file");
}

#[test]
fn bad_arguments_exit_2() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("x.ism.json");
    let handles = example("hermite/ellipse.hermite.json");
    for args in [
        vec!["fit", "--preset", "nope"],
        vec!["fit", "--expr", "x^2 + w", "--domain", "0,1,0,1"],
        vec!["fit", "--expr", "x^2 + (y", "--domain", "0,1,0,1"],
        vec!["fit", "--expr", "x + y", "--domain", "0,1,0,1,0"],
        vec!["fit", "--expr", "x + y", "--domain", "1,0,0,1"],
        vec!["fit", "--preset", "circle", "--tolerance", "-1"],
        vec!["fit", "--hermite", handles.to_str().unwrap(), "--rational"],
    ] {
        assert_refused(&args, &model);
    }
}

#[test]
fn list_presets_names_all_five() {
    let out = ism().args(["fit", "--list-presets"]).output().unwrap();
    assert_status(&out, 0);
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
    assert_status(&out, 0);
    let r = json(&out.stdout);
    assert_eq!(
        (r["components"].as_u64(), r["euler"].as_i64()),
        (Some(1), Some(2))
    );
    assert_eq!(r["topologyMatchesPreset"], true);
    assert_validates(&model);
}

/// An icosphere of radius `r` around `centre` (`level` subdivisions), outward triangles.
fn icosphere(level: usize, r: f64, centre: [f64; 3]) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
    let mesh = ism_fit::mesh::TriangleMesh::icosphere(level, r, centre);
    (mesh.positions, mesh.triangles)
}

fn obj_text(points: &[[f64; 3]], tris: &[[u32; 3]]) -> String {
    let mut s = String::new();
    for p in points {
        s += &format!("v {} {} {}\n", p[0], p[1], p[2]);
    }
    for t in tris {
        s += &format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    s
}

/// A GLB with one indexed triangle primitive placed by a node translation.
fn glb_bytes(points: &[[f64; 3]], tris: &[[u32; 3]], translation: [f32; 3]) -> Vec<u8> {
    let mut bin = Vec::new();
    let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
    for p in points {
        for k in 0..3 {
            let x = p[k] as f32;
            lo[k] = lo[k].min(x);
            hi[k] = hi[k].max(x);
            bin.extend(x.to_le_bytes());
        }
    }
    let index_offset = bin.len();
    for t in tris {
        for i in t {
            bin.extend(i.to_le_bytes());
        }
    }
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0]}}],
        "nodes":[{{"mesh":0,"translation":{translation:?}}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1}}]}}],
        "buffers":[{{"byteLength":{}}}],
        "bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":{index_offset}}},
                       {{"buffer":0,"byteOffset":{index_offset},"byteLength":{}}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":{},"type":"VEC3","min":{lo:?},"max":{hi:?}}},
                     {{"bufferView":1,"componentType":5125,"count":{},"type":"SCALAR"}}]}}"#,
        bin.len(),
        bin.len() - index_offset,
        points.len(),
        tris.len() * 3
    );
    let mut json = json.into_bytes();
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = Vec::new();
    out.extend(b"glTF");
    out.extend(2u32.to_le_bytes());
    out.extend((total as u32).to_le_bytes());
    out.extend((json.len() as u32).to_le_bytes());
    out.extend(b"JSON");
    out.extend(&json);
    out.extend((bin.len() as u32).to_le_bytes());
    out.extend(b"BIN\0");
    out.extend(&bin);
    out
}

fn fit_mesh(mesh: &std::path::Path, model: &std::path::Path, extra: &[&str]) -> serde_json::Value {
    let out = ism()
        .arg("fit")
        .arg("--mesh")
        .arg(mesh)
        .args(extra)
        .args(["--json", "-q", "-o"])
        .arg(model)
        .output()
        .unwrap();
    assert_status(&out, 0);
    assert_validates(model);
    json(&out.stdout)
}

#[test]
fn obj_and_glb_meshes_fit_validate_and_keep_the_sphere_topology() {
    let dir = tempfile::tempdir().unwrap();
    let (points, tris) = icosphere(2, 0.5, [0.0; 3]);
    let obj = dir.path().join("ball.obj");
    std::fs::write(&obj, obj_text(&points, &tris)).unwrap();
    let glb = dir.path().join("ball.glb");
    std::fs::write(&glb, glb_bytes(&points, &tris, [0.25, 0.0, -0.5])).unwrap();
    // The Plantinga–Vegter phase is covered by the library tests; here it would dominate the time.
    let settings = ["--resolution", "3", "--tolerance", "3e-2", "--no-topology"];
    let a = fit_mesh(&obj, &dir.path().join("a.ismb"), &settings);
    let b = fit_mesh(&glb, &dir.path().join("b.ismb"), &settings);
    for r in [&a, &b] {
        assert_eq!(
            (r["components"].as_u64(), r["euler"].as_i64()),
            (Some(1), Some(2))
        );
        assert_eq!(r["topologyMatchesPreset"], true);
        let m = &r["mesh"];
        assert_eq!(m["triangles"], 320);
        assert_eq!(m["closedManifold"], true);
        assert_eq!(
            (m["components"].as_u64(), m["euler"].as_i64()),
            (Some(1), Some(2))
        );
        // True distance to the mesh, relative to its diagonal.
        let rel = m["maxDistanceRelative"].as_f64().unwrap();
        let diagonal = m["diagonal"].as_f64().unwrap();
        assert!(rel > 0.0 && rel * diagonal <= 3e-2, "{r}");
    }
    // The same shape moved by the node translation: about the same complex size and the same
    // error. Not the identical complex: translated coordinates round differently (~1e-16
    // relative), and the fitter's refine/prune decisions compare error estimates with a margin of
    // the tolerance, so a cell within rounding of that threshold may go either way and its split
    // spreads to its neighbours (366 vs 378 simplices since the margin became 0.95 in 6bec71cd;
    // 168 vs 152 since the Z → S projection slides along patch edges, issue 17 session 14: the
    // false misses it reported had forced refinements, and in a complex this small one split's
    // star is a larger share, so 12 %).
    let (sa, sb) = (
        a["simplices"].as_u64().unwrap() as f64,
        b["simplices"].as_u64().unwrap() as f64,
    );
    assert!(
        (sa - sb).abs() <= 0.12 * sa.max(sb),
        "{sa} vs {sb} simplices"
    );
    // The errors: both within the tolerance (above) and close. Since the two-sided rounds lower
    // the one-sided goal where they miss (issue 17, session 25), which cells miss — and so how
    // far below the tolerance the fit ends — follows those rounding-level decisions too: 2.77e-2
    // vs 2.91e-2 here (were within 1e-3 before). A tenth of the tolerance still catches a
    // translation that changed the fit itself.
    let (ea, eb) = (
        a["maxDistance"].as_f64().unwrap(),
        b["maxDistance"].as_f64().unwrap(),
    );
    assert!((ea - eb).abs() < 0.1 * 3e-2, "{ea} vs {eb}");
}

#[test]
fn a_low_poly_mesh_with_creases_fits_with_the_topology_phase_on() {
    // The icosahedron's normals turn by 41.8° at every edge: under the 60° skip, so the
    // Plantinga–Vegter phase runs, and it fails near the creases at every cell size. It must
    // stop at the mesh's scale instead of spending the simplex budget there (it did, for 5 min).
    let dir = tempfile::tempdir().unwrap();
    let (points, tris) = icosphere(0, 1.0, [0.0; 3]);
    assert_eq!(tris.len(), 20);
    let obj = dir.path().join("ico.obj");
    std::fs::write(&obj, obj_text(&points, &tris)).unwrap();
    let r = fit_mesh(
        &obj,
        &dir.path().join("ico.ismb"),
        &["--resolution", "4", "--tolerance", "5e-2"],
    );
    assert_eq!(r["toleranceMet"], true);
    assert!(r["simplices"].as_u64().unwrap() < 20_000, "{r}");
    assert_eq!(
        (r["components"].as_u64(), r["euler"].as_i64()),
        (Some(1), Some(2))
    );
    assert_eq!(r["topologyMatchesPreset"], true);
}

#[test]
fn two_balls_give_two_components() {
    let dir = tempfile::tempdir().unwrap();
    let (mut points, mut tris) = icosphere(1, 0.3, [-0.45, 0.0, 0.0]);
    let (p2, t2) = icosphere(1, 0.3, [0.45, 0.0, 0.0]);
    let n = points.len() as u32;
    points.extend(p2);
    tris.extend(t2.iter().map(|t| t.map(|v| v + n)));
    let obj = dir.path().join("two.obj");
    std::fs::write(&obj, obj_text(&points, &tris)).unwrap();
    let r = fit_mesh(
        &obj,
        &dir.path().join("two.ism.json"),
        &["--resolution", "5", "--tolerance", "5e-2", "--no-topology"],
    );
    assert_eq!(
        (r["components"].as_u64(), r["euler"].as_i64()),
        (Some(2), Some(4))
    );
    assert_eq!(r["mesh"]["components"], 2);
}

#[test]
fn bad_meshes_and_conflicting_arguments_exit_2() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("x.ismb");
    let garbage = dir.path().join("garbage.obj");
    std::fs::write(&garbage, "v 0 0 0\nv 1 0 0\nf 1 2 7\n").unwrap();
    let glb = dir.path().join("cut.glb");
    let (points, tris) = icosphere(0, 1.0, [0.0; 3]);
    let bytes = glb_bytes(&points, &tris, [0.0; 3]);
    std::fs::write(&glb, &bytes[..bytes.len() / 2]).unwrap();
    let obj = dir.path().join("ok.obj");
    std::fs::write(&obj, obj_text(&points, &tris)).unwrap();
    let missing = dir.path().join("missing.obj");
    let stl = dir.path().join("x.stl");
    std::fs::write(&stl, "solid x\nendsolid x\n").unwrap();
    for args in [
        vec!["fit", "--mesh", missing.to_str().unwrap()],
        vec!["fit", "--mesh", garbage.to_str().unwrap()],
        vec!["fit", "--mesh", glb.to_str().unwrap()],
        vec!["fit", "--mesh", stl.to_str().unwrap()],
        vec!["fit", "--mesh", obj.to_str().unwrap(), "--preset", "sphere"],
        vec!["fit", "--mesh", obj.to_str().unwrap(), "--expr", "x"],
        vec![
            "fit",
            "--mesh",
            obj.to_str().unwrap(),
            "--hermite",
            "h.json",
        ],
        vec!["fit", "--mesh", obj.to_str().unwrap(), "--mesh-margin=-1"],
        vec![
            "fit",
            "--mesh",
            obj.to_str().unwrap(),
            "--domain",
            "0,1,0,1",
        ],
    ] {
        assert_refused(&args, &model);
    }
}

/// `--mesh-max-bytes/--mesh-max-vertices/--mesh-max-triangles`: a mesh one past a limit is
/// refused (exit 2, the limit named, nothing written); at the limit it is read and fitted.
#[test]
fn mesh_limits_refuse_one_past_and_accept_at_the_count() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("x.ismb");
    let (points, tris) = icosphere(0, 1.0, [0.0; 3]);
    let obj = dir.path().join("ico.obj");
    std::fs::write(&obj, obj_text(&points, &tris)).unwrap();
    // Truth: the counts of the mesh as generated and the file's size on disk.
    let size = std::fs::metadata(&obj).unwrap().len();
    let cases = [
        ("--mesh-max-bytes", size, "max_payload_bytes"),
        ("--mesh-max-vertices", points.len() as u64, "max_vertices"),
        ("--mesh-max-triangles", tris.len() as u64, "max_simplices"),
    ];
    for (flag, count, name) in cases {
        let below = (count - 1).to_string();
        let out = ism()
            .args(["fit", "--mesh", obj.to_str().unwrap(), flag, &below, "-q"])
            .arg("-o")
            .arg(&model)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{flag} {below}: {stderr}");
        assert!(stderr.contains(name), "{flag} {below}: {stderr}");
        assert!(!model.exists(), "{flag} {below} wrote a file");
        let at = count.to_string();
        let out = ism()
            .args(["fit", "--mesh", obj.to_str().unwrap(), flag, &at, "-q"])
            .args(["--resolution", "2", "--tolerance", "0.5", "--no-optimize"])
            .arg("-o")
            .arg(&model)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!stderr.contains(name), "{flag} {at}: {stderr}");
        assert!(model.exists(), "{flag} {at}: {stderr}");
        std::fs::remove_file(&model).unwrap();
    }
    // The flags are for --mesh only.
    assert_refused(
        &["fit", "--preset", "circle", "--mesh-max-vertices", "4"],
        &model,
    );
}

#[test]
fn open_mesh_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let (points, mut tris) = icosphere(1, 0.5, [0.0; 3]);
    tris.pop();
    let obj = dir.path().join("open.obj");
    std::fs::write(&obj, obj_text(&points, &tris)).unwrap();
    let model = dir.path().join("open.ismb");
    let out = ism()
        .arg("fit")
        .arg("--mesh")
        .arg(&obj)
        .arg("-o")
        .arg(&model)
        .output()
        .unwrap();
    assert_status(&out, 2);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("not a closed manifold (3 boundary"),
        "{stderr}"
    );
    assert!(!model.exists());
}

#[test]
fn rational_weights_are_fitted_written_and_validated() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("taubin.ism.json");
    let out = ism()
        .args([
            "fit",
            "--preset",
            "taubin",
            "--resolution",
            "8",
            "--no-topology",
            "--tolerance",
            "2e-3",
            "--rational",
            "--json",
            "-q",
            "-o",
        ])
        .arg(&model)
        .output()
        .unwrap();
    assert_status(&out, 0);
    let r = json(&out.stdout);
    assert!(r["maxDistance"].as_f64().unwrap() <= 2e-3);
    assert_eq!(
        (r["components"].clone(), r["euler"].clone()),
        (2.into(), 0.into())
    );
    let written: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&model).unwrap()).unwrap();
    let last = written["stages"]
        .as_array()
        .unwrap()
        .last()
        .unwrap()
        .clone();
    assert_eq!(last["kind"], "rational");
    assert_eq!(last["direction"], "parametric");
    let weights: Vec<f64> = last["faces"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|f| {
            f["weights"]
                .as_array()
                .unwrap()
                .iter()
                .map(|w| w.as_f64().unwrap())
        })
        .collect();
    assert!(weights.len() > 10);
    assert!(weights.iter().all(|&w| w > 0.0) && weights.iter().any(|&w| (w - 1.0).abs() > 1e-3));

    assert_validates(&model);
    let samples = dir.path().join("s.npy");
    let sampled = ism()
        .args(["sample", "--surface", "2000", "-o"])
        .arg(&samples)
        .arg(&model)
        .output()
        .unwrap();
    assert_status(&sampled, 0);
}

#[test]
fn a_singular_curve_fits_and_names_its_singular_points() {
    // The heart (x² + y² − 1)³ − x²y³ = 0 (issue 17): exit 2 with a degenerate simplex before.
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("heart.ismb");
    let out = ism()
        .args(["fit", "-q", "--json", "--expr", "(x^2+y^2-1)^3-x^2*y^3"])
        .args(["--domain=-1.5,1.5,-1.5,1.5", "--tolerance", "0.03", "-o"])
        .arg(&model)
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(r["topologyCertified"], false);
    assert_eq!(r["topologyChecked"], false);
    assert!(r["topologyMatchesPreset"].is_null());
    assert_eq!(r["toleranceMet"], true);
    let uncertain = r["uncertain"].as_array().unwrap();
    assert!((4..=6).contains(&uncertain.len()), "{uncertain:?}");
    assert!(r["maxDistance"].as_f64().unwrap() <= 0.03);
    assert!(r["targetToShape"].as_f64().unwrap() <= r["targetToShapeBound"].as_f64().unwrap());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("singular point"), "{stderr}");
    assert!(model.exists());
}
