//! The named examples of `spec/examples/`, each a genuine simplicial diffeomorphism by one of the
//! constructions of `spec/mathematics.md` §3 (adjusted quadratic, solitary points, strata, fixed-point rational,
//! monotonic, and compositions of those).

use std::path::Path;

use ism_format::io::{self, WriteOptions};
use ism_format::{Direction, Encoding, Model, StageKind};

use crate::{
    cubic_face_point_stage, kuhn_grid_2d, kuhn_grid_3d, level_crossing_stages, monotonic_stage,
    quadratic_edge_stage, rational_fixed_points_stage, seeded_weights, stratified_stages, Aabb,
};

/// The generator string written into every example's metadata.
pub const GENERATOR: &str = concat!("ism-make-examples ", env!("CARGO_PKG_VERSION"));

/// Radius of the papers' circle (Mello & Velho 2010, Fig. 4): `x² + y² − 0.28²`.
pub const CIRCLE_RADIUS: f64 = 0.28;

/// The circle's implicit function.
pub fn circle(p: &[f64]) -> f64 {
    p[0] * p[0] + p[1] * p[1] - CIRCLE_RADIUS * CIRCLE_RADIUS
}

/// Radius of the `sphere` example.
pub const SPHERE_RADIUS: f64 = 0.7;

/// The sphere's implicit function `|p|² − 0.7²`.
pub fn sphere(p: &[f64]) -> f64 {
    p.iter().map(|x| x * x).sum::<f64>() - SPHERE_RADIUS * SPHERE_RADIUS
}

/// The torus `(√(x² + y²) − 0.6)² + z² − 0.25²`.
pub fn torus(p: &[f64]) -> f64 {
    let ring = (p[0] * p[0] + p[1] * p[1]).sqrt() - 0.6;
    ring * ring + p[2] * p[2] - 0.25 * 0.25
}

fn named(mut model: Model, name: &str, description: &str) -> Model {
    model.metadata.name = Some(name.into());
    model.metadata.generator = Some(GENERATOR.into());
    model.metadata.description = Some(description.into());
    model
}

/// The 4 × 4 Kuhn triangulation of `[−0.5, 0.5]²` with the circle's values: the linear isocomplex
/// of Mello & Velho 2010, Fig. 4, far from the circle.
fn circle_grid() -> Model {
    kuhn_grid_2d(4, 4, Aabb::cube(-0.5, 0.5), circle).expect("fixed, valid grid")
}

/// Every example as `(name, model)`, in a fixed order.
pub fn all_examples() -> Vec<(&'static str, Model)> {
    let mut out = Vec::new();

    out.push((
        "circle-linear",
        named(
            circle_grid(),
            "circle-linear",
            "x² + y² − 0.28² on a 4×4 Kuhn-triangulated square [−0.5, 0.5]², no stage: the linear isocomplex of Mello & Velho (2010) Fig. 4.",
        ),
    ));

    let mut curved = circle_grid();
    curved.stages = level_crossing_stages(&curved, circle);
    out.push((
        "circle-curved",
        named(
            curved,
            "circle-curved",
            "circle-linear with two stages pulling the polygon onto the circle: a degree-1 monotonic stage (vertex weights) then an adjusted quadratic stage, fitted so the shape crosses each crossed edge where the circle does.",
        ),
    ));

    let mut sphere_model =
        kuhn_grid_3d(6, 6, 6, Aabb::cube(-1.0, 1.0), sphere).expect("fixed, valid grid");
    sphere_model.stages = level_crossing_stages(&sphere_model, sphere);
    out.push((
        "sphere",
        named(
            sphere_model,
            "sphere",
            "|p|² − 0.7² on a 6×6×6 Kuhn-triangulated cube [−1, 1]³ with a degree-1 monotonic and an adjusted quadratic stage putting the surface on the sphere along the crossed edges.",
        ),
    ));

    let mut quadratic = circle_grid();
    quadratic
        .stages
        .push(quadratic_edge_stage(&quadratic, 11, 0.6));
    out.push((
        "quadratic-edges",
        named(quadratic, "quadratic-edges", "The circle grid with a quadratic stage moving the middle control point of every edge (adjusted, degree 2)."),
    ));

    let mut cubic = circle_grid();
    cubic.stages.push(cubic_face_point_stage(&cubic, 12, 0.6));
    out.push((
        "cubic-face-point",
        named(cubic, "cubic-face-point", "The circle grid with a cubic stage moving the solitary centre point of every triangle."),
    ));

    let mut stratified = kuhn_grid_3d(3, 3, 3, Aabb::cube(-1.0, 1.0), |p| {
        p.iter().map(|x| x * x).sum::<f64>() - 0.36
    })
    .expect("fixed, valid grid");
    stratified.stages = stratified_stages(&stratified, 13, 0.5);
    out.push((
        "stratified-3d",
        named(
            stratified,
            "stratified-3d",
            "|p|² − 0.6² on a 3×3×3 Kuhn grid with the stratified scheme G1∘G2∘G3: solitary points on every tetrahedron (degree 4, applied first), triangle (degree 3) and edge (degree 2).",
        ),
    ));

    let mut rational = circle_grid();
    rational.stages.push(rational_fixed_points_stage(
        &rational,
        5,
        seeded_weights(14, 0.7),
    ));
    out.push((
        "rational-degree5",
        named(
            rational,
            "rational-degree5",
            "The circle grid with a rational degree-5 stage: every control point fixed, non-uniform weights in [e^−0.7, e^0.7] on every edge and triangle.",
        ),
    ));

    let mut monotonic = circle_grid();
    monotonic
        .stages
        .push(monotonic_stage(&monotonic, 3, 15, 0.6));
    out.push((
        "monotonic",
        named(monotonic, "monotonic", "The circle grid with a cubic monotonic stage: an increasing 1-D Bernstein polynomial per vertex."),
    ));

    let mut two = circle_grid();
    two.stages.push(monotonic_stage(&two, 2, 16, 0.5));
    let mut inverse = quadratic_edge_stage(&two, 17, 0.5);
    inverse.direction = Direction::Parametric;
    inverse.name = Some("quadratic edges, stored inverted".into());
    two.stages.push(inverse);
    out.push((
        "two-stage",
        named(
            two,
            "two-stage",
            "Composition X = X1 ∘ X0: a quadratic monotonic stage X0 applied first, then X1 whose inverse (a quadratic edge stage) is stored (direction parametric).",
        ),
    ));

    let mut torus_model = kuhn_grid_3d(
        8,
        8,
        4,
        Aabb::new([-1.0, -1.0, -0.5], [1.0, 1.0, 0.5]),
        torus,
    )
    .expect("fixed, valid grid");
    torus_model.stages = level_crossing_stages(&torus_model, torus);
    out.push((
        "torus",
        named(
            torus_model,
            "torus",
            "(√(x²+y²) − 0.6)² + z² − 0.25² on an 8×8×4 Kuhn grid of [−1, 1]²×[−0.5, 0.5] with a degree-1 monotonic and an adjusted quadratic stage fitted on the crossed edges: genus 1.",
        ),
    ));
    out
}

/// The bytes of one example in one encoding, as `spec/examples/` holds them (JSON pretty-printed,
/// without container; MessagePack and binary in the container).
///
/// # Errors
/// Only if encoding fails (it does not for the generated models).
pub fn example_bytes(model: &Model, encoding: Encoding) -> ism_format::Result<Vec<u8>> {
    io::to_vec(
        model,
        encoding,
        WriteOptions {
            pretty: encoding == Encoding::Json,
            json_in_container: false,
        },
    )
}

/// Writes every example in all five encodings into `dir` (atomically, file by file); returns the
/// paths written.
///
/// # Errors
/// [`crate::Error::Encode`] or [`crate::Error::Write`], naming the file.
pub fn write_examples(dir: &Path) -> Result<Vec<std::path::PathBuf>, crate::Error> {
    let mut written = Vec::new();
    for (name, model) in all_examples() {
        for encoding in Encoding::ALL {
            let path = dir.join(format!("{name}.{}", encoding.extension()));
            let bytes = example_bytes(&model, encoding).map_err(|error| crate::Error::Encode {
                path: path.clone(),
                message: error.to_string(),
            })?;
            io::write_atomic(&path, |w| std::io::Write::write_all(w, &bytes)).map_err(|error| {
                crate::Error::Write {
                    path: path.clone(),
                    error,
                }
            })?;
            written.push(path);
        }
    }
    Ok(written)
}

/// Whether a stage kind appears in some example (used by tests to show coverage).
pub fn kinds_covered() -> Vec<StageKind> {
    let mut kinds: Vec<StageKind> = all_examples()
        .iter()
        .flat_map(|(_, m)| m.stages.iter().map(|s| s.kind))
        .collect();
    kinds.sort_by_key(|k| k.as_str());
    kinds.dedup();
    kinds
}
