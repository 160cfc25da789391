//! Writes the validator's test vectors: `spec/vectors/validate/NAME.ism.json` and
//! `NAME.expect.json` (`{"verdict", "issues": [{"code", "location"}]}`).
//!
//! The expected `(code, location)` pairs are written here by hand from the construction of each
//! vector, not copied from the validator's output; every vector that must fold is also checked to
//! have `det DX < 0` at some point by `ism-geom`'s pointwise Jacobian before it is written.
//!
//! ```text
//! cargo run -p ism-validate --example make_vectors -- spec/vectors/validate
//! ```

use std::path::{Path, PathBuf};

use ism_format::builder::{ModelBuilder, StageBuilder};
use ism_format::{io, multi_index, Location, Model};
use serde_json::json;

struct Vector {
    name: &'static str,
    description: &'static str,
    model: Model,
    verdict: &'static str,
    issues: Vec<(&'static str, Location)>,
    /// Stage and simplex that must fold somewhere (checked with ism-geom).
    folds: Vec<(usize, usize)>,
}

fn square() -> ModelBuilder {
    ModelBuilder::new(2)
        .vertex(&[0.0, 0.0], -1.0)
        .vertex(&[1.0, 0.0], 1.0)
        .vertex(&[1.0, 1.0], 1.0)
        .vertex(&[0.0, 1.0], 1.0)
        .simplex(&[0, 1, 2])
        .simplex(&[0, 2, 3])
}

fn tet() -> ModelBuilder {
    ModelBuilder::new(3)
        .vertex(&[0.0, 0.0, 0.0], -1.0)
        .vertex(&[1.0, 0.0, 0.0], 1.0)
        .vertex(&[0.0, 1.0, 0.0], 1.0)
        .vertex(&[0.0, 0.0, 1.0], 1.0)
        .simplex(&[0, 1, 2, 3])
}

fn at(pointer: &str) -> Location {
    Location::pointer(pointer)
}

fn face_loc(stage: usize, face: &[u32], pointer: &str) -> Location {
    Location {
        stage: Some(stage),
        face: Some(face.to_vec()),
        ..at(pointer)
    }
}

fn element(stage: usize, simplex: usize, m: usize) -> Location {
    Location {
        stage: Some(stage),
        simplex: Some(simplex),
        ..at(&format!("/simplices/{}", simplex * m))
    }
}

fn vectors() -> Vec<Vector> {
    let fig2 = [0.1, 0.9, 0.5, 0.5, 0.9, 0.1];
    vec![
        Vector {
            name: "coordinate-negative",
            description: "A quadratic edge point outside its open edge (coordinate -0.2): not K-invariant.",
            model: square().stage(StageBuilder::bezier(2).face(&[0, 2], &[1.2, -0.2], &[]).build()).build_unchecked(),
            verdict: "invalid",
            issues: vec![("ISM-201", face_loc(0, &[0, 2], "/stages/0/faces/0/points/1"))],
            folds: vec![],
        },
        Vector {
            name: "coordinate-zero",
            description: "A cubic face point on the boundary of its face (coordinate 0).",
            model: square().stage(StageBuilder::bezier(3).face(&[0, 1, 2], &[0.5, 0.0, 0.5], &[]).build()).build_unchecked(),
            verdict: "invalid",
            issues: vec![("ISM-201", face_loc(0, &[0, 1, 2], "/stages/0/faces/0/points/1"))],
            folds: vec![],
        },
        Vector {
            name: "coordinate-sum",
            description: "Point coordinates summing to 1.1.",
            model: square().stage(StageBuilder::bezier(2).face(&[0, 2], &[0.7, 0.4], &[]).build()).build_unchecked(),
            verdict: "invalid",
            issues: vec![("ISM-202", face_loc(0, &[0, 2], "/stages/0/faces/0/points/0"))],
            folds: vec![],
        },
        Vector {
            name: "weight-zero",
            description: "A rational weight of 0.",
            model: square().stage(StageBuilder::rational(2).face(&[0, 2], &[0.5, 0.5], &[0.0]).build()).build_unchecked(),
            verdict: "invalid",
            issues: vec![("ISM-203", face_loc(0, &[0, 2], "/stages/0/faces/0/weights/0"))],
            folds: vec![],
        },
        Vector {
            name: "monotonic-decreasing",
            description: "A monotonic vertex map whose coefficients decrease (0, 0.6, 0.5, 1).",
            model: square()
                .stage(StageBuilder::monotonic(3).vertex_map(2, &[0.0, 0.6, 0.5, 1.0]).build())
                .build_unchecked(),
            verdict: "invalid",
            issues: vec![(
                "ISM-204",
                Location { stage: Some(0), vertex: Some(2), ..at("/stages/0/vertexMaps/0/coefficients/2") },
            )],
            folds: vec![],
        },
        Vector {
            name: "monotonic-offset",
            description: "A monotonic vertex map that does not start at 0.",
            model: square().stage(StageBuilder::monotonic(2).vertex_map(1, &[0.1, 0.5, 1.0]).build()).build_unchecked(),
            verdict: "invalid",
            issues: vec![(
                "ISM-204",
                Location { stage: Some(0), vertex: Some(1), ..at("/stages/0/vertexMaps/0/coefficients/0") },
            )],
            folds: vec![],
        },
        Vector {
            name: "fig2-quartic-fold-2d",
            description: "Mello & Velho 2009 Fig. 2 on the shared diagonal: quartic edge points b31 and b13 exchanged past the midpoint; \
                          both triangles fold.",
            model: square().stage(StageBuilder::bezier(4).face(&[0, 2], &fig2, &[]).build()).build_unchecked(),
            verdict: "invalid",
            issues: vec![("ISM-301", element(0, 0, 3)), ("ISM-301", element(0, 1, 3))],
            folds: vec![(0, 0), (0, 1)],
        },
        Vector {
            name: "fig2-exact-swap",
            description: "Mello & Velho 2009 Fig. 2 exactly: b31 = (1/4, 3/4) and b13 = (3/4, 1/4); det DX = 0 at the edge midpoint.",
            model: tet().stage(StageBuilder::bezier(4).face(&[0, 1], &[0.25, 0.75, 0.5, 0.5, 0.75, 0.25], &[]).build()).build_unchecked(),
            verdict: "invalid",
            issues: vec![("ISM-301", element(0, 0, 4))],
            folds: vec![],
        },
        Vector {
            name: "edge-point-on-vertex",
            description: "A quadratic edge point stored as (1e-17, 1.0): positive and summing to 1 in f64, but in reduced \
                          coordinates (b0 = 1 - b2 = 0) it sits on vertex 2, where det DX = 0 exactly. No theorem applies \
                          (spec/validation.md §4.2); the witness is the exact zero at the vertex.",
            model: square().stage(StageBuilder::bezier(2).face(&[0, 2], &[1e-17, 1.0], &[]).build()).build_unchecked(),
            verdict: "invalid",
            issues: vec![("ISM-301", element(0, 0, 3)), ("ISM-301", element(0, 1, 3))],
            folds: vec![],
        },
        Vector {
            name: "quartic-fold-3d",
            description: "A tetrahedron whose quartic edge (0, 1) folds (Mello & Velho 2009 Fig. 2 inside a 3D model).",
            model: tet().stage(StageBuilder::bezier(4).face(&[0, 1], &fig2, &[]).build()).build_unchecked(),
            verdict: "invalid",
            issues: vec![("ISM-301", element(0, 0, 4))],
            folds: vec![(0, 0)],
        },
        Vector {
            name: "rational-fold-2d",
            description: "A rational cubic whose edge points cross over; heavy weights on them make the fold visible.",
            model: square()
                .stage(StageBuilder::rational(3).face(&[0, 2], &[0.05, 0.95, 0.95, 0.05], &[4.0, 4.0]).build())
                .build_unchecked(),
            verdict: "invalid",
            issues: vec![("ISM-301", element(0, 0, 3)), ("ISM-301", element(0, 1, 3))],
            folds: vec![(0, 0), (0, 1)],
        },
        Vector {
            name: "second-stage-folds",
            description: "Stage 0 breaks invariance (not certified further); stage 1 folds: both reported.",
            model: square()
                .stage(StageBuilder::bezier(2).face(&[0, 1], &[-0.1, 1.1], &[]).build())
                .stage(StageBuilder::bezier(4).face(&[0, 2], &fig2, &[]).build())
                .build_unchecked(),
            verdict: "invalid",
            issues: vec![
                ("ISM-201", face_loc(0, &[0, 1], "/stages/0/faces/0/points/0")),
                ("ISM-301", element(1, 0, 3)),
                ("ISM-301", element(1, 1, 3)),
            ],
            folds: vec![(1, 0), (1, 1)],
        },
        Vector {
            name: "undetermined-degree",
            description: "A rational degree-16 stage in 3D with a moved edge: beyond the numeric certificate's table \
                          limit, so ISM-302 (never valid).",
            model: {
                let d = 16;
                let owned = multi_index::owned(2, d);
                let points: Vec<f64> = owned
                    .chunks(2)
                    .flat_map(|j| {
                        let t = f64::from(j[1]) / f64::from(d);
                        let t = t * t * (3.0 - 2.0 * t);
                        [1.0 - t, t]
                    })
                    .collect();
                let weights = vec![1.5; owned.len() / 2];
                tet().stage(StageBuilder::rational(d).face(&[0, 1], &points, &weights).build()).build_unchecked()
            },
            verdict: "undetermined",
            issues: vec![("ISM-302", element(0, 0, 4))],
            folds: vec![],
        },
        Vector {
            name: "non-manifold-vertex",
            description: "Two triangles meeting only at vertex 0 (a bow tie): ISM-150 warning, still valid.",
            model: ModelBuilder::new(2)
                .vertex(&[0.0, 0.0], -1.0)
                .vertex(&[1.0, 0.0], 1.0)
                .vertex(&[1.0, 1.0], 1.0)
                .vertex(&[-1.0, 0.0], 1.0)
                .vertex(&[-1.0, -1.0], 1.0)
                .simplex(&[0, 1, 2])
                .simplex(&[0, 3, 4])
                .build_unchecked(),
            verdict: "valid",
            issues: vec![("ISM-150", Location { vertex: Some(0), ..at("/vertices/0") })],
            folds: vec![],
        },
        Vector {
            name: "non-manifold-edge",
            description: "Two tetrahedra sharing only the edge (0, 1): the edge and both its vertices are non-manifold.",
            model: ModelBuilder::new(3)
                .vertex(&[0.0, 0.0, 0.0], -1.0)
                .vertex(&[1.0, 0.0, 0.0], 1.0)
                .vertex(&[0.0, 1.0, 0.0], 1.0)
                .vertex(&[0.0, 0.0, 1.0], 1.0)
                .vertex(&[0.0, -1.0, 0.0], 1.0)
                .vertex(&[0.0, 0.0, -1.0], 1.0)
                .simplex(&[0, 1, 2, 3])
                .simplex(&[0, 1, 4, 5])
                .build_unchecked(),
            verdict: "valid",
            issues: vec![
                ("ISM-150", Location { simplex: Some(0), face: Some(vec![0, 1]), ..at("/simplices/0") }),
                ("ISM-150", Location { vertex: Some(0), ..at("/vertices/0") }),
                ("ISM-150", Location { vertex: Some(1), ..at("/vertices/3") }),
            ],
            folds: vec![],
        },
        Vector {
            name: "value-at-level",
            description: "A vertex value equal to the level (structural, reported by layer 1; later layers skipped).",
            model: square().level(1.0).stage(StageBuilder::bezier(4).face(&[0, 2], &fig2, &[]).build()).build_unchecked(),
            verdict: "invalid",
            issues: vec![
                ("ISM-113", Location { vertex: Some(1), ..at("/values/1") }),
                ("ISM-113", Location { vertex: Some(2), ..at("/values/2") }),
                ("ISM-113", Location { vertex: Some(3), ..at("/values/3") }),
            ],
            folds: vec![],
        },
        Vector {
            name: "inverted-simplex",
            description: "A negatively oriented triangle (structural).",
            model: ModelBuilder::new(2)
                .vertex(&[0.0, 0.0], -1.0)
                .vertex(&[1.0, 0.0], 1.0)
                .vertex(&[0.0, 1.0], 1.0)
                .simplex(&[0, 2, 1])
                .build_unchecked(),
            verdict: "invalid",
            issues: vec![("ISM-106", Location { simplex: Some(0), ..at("/simplices/0") })],
            folds: vec![],
        },
    ]
}

/// Some sampled point of the simplex where ism-geom's det of the stored map is negative.
fn folds(model: &Model, stage: usize, simplex: usize) -> bool {
    let local =
        ism_geom::LocalStage::from_model(model, stage, simplex).expect("geom builds the stage");
    let n = model.dim();
    multi_index::all(n + 1, 24).chunks(n + 1).any(|i| {
        let mut w = [0.0; 4];
        for (c, &e) in i.iter().enumerate() {
            w[c] = f64::from(e) / 24.0;
        }
        let (_, j) = local.jacobian_stored(&w);
        ism_geom::linalg::det(n, &j) < 0.0
    })
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let dir = PathBuf::from(
        std::env::args()
            .nth(1)
            .unwrap_or_else(|| "spec/vectors/validate".into()),
    );
    std::fs::create_dir_all(&dir)?;
    for v in vectors() {
        for &(stage, simplex) in &v.folds {
            assert!(
                folds(&v.model, stage, simplex),
                "{}: stage {stage} simplex {simplex} does not fold",
                v.name
            );
        }
        let model_path = dir.join(format!("{}.ism.json", v.name));
        io::write_path(
            &v.model,
            &model_path,
            None,
            io::WriteOptions {
                pretty: true,
                ..Default::default()
            },
        )?;
        let expect = json!({
            "description": v.description,
            "verdict": v.verdict,
            "issues": v.issues.iter().map(|(code, loc)| json!({ "code": code, "location": loc })).collect::<Vec<_>>(),
        });
        write_text(
            &dir.join(format!("{}.expect.json", v.name)),
            &(serde_json::to_string_pretty(&expect)? + "\n"),
        )?;
        println!("wrote {}", model_path.display());
    }
    Ok(())
}

fn write_text(path: &Path, text: &str) -> std::io::Result<()> {
    use std::io::Write;
    io::write_atomic(path, |w| w.write_all(text.as_bytes()))
}
