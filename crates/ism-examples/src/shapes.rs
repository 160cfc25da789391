//! Shapes of random size and position under random stage chains, for property tests: models no
//! example was written for, built from this crate's grids and stages.

use ism_format::{Direction, Model};

use crate::{
    kuhn_grid_2d, kuhn_grid_3d, monotonic_stage, quadratic_edge_stage, rational_fixed_points_stage,
    seeded_weights, stratified_stages, Aabb, Error,
};

/// The stage chains [`ellipsoid_model`] builds: `chain` is taken modulo this.
pub const ELLIPSOID_CHAINS: usize = 4;

/// An ellipse (2D, `centre.len() == 2`) or ellipsoid (3D) `Σ_k ((x_k − centre_k) / radii_k)² = 1`
/// in a Kuhn grid of `cells` cells per side of `[−1, 1]ⁿ` (so `centre` and `radii` decide which
/// grid vertices lie inside), under one stage chain with random control points from `seed` and
/// `amplitude`, every stage in `direction`. Chains (`chain % ELLIPSOID_CHAINS`):
///
/// 0. the stratified scheme ([`stratified_stages`]: solitary points on every face dimension);
/// 1. a quadratic edge stage ([`quadratic_edge_stage`]);
/// 2. a cubic monotonic stage ([`monotonic_stage`]);
/// 3. a cubic rational stage with fixed control points and weights in `[e^(−2a), e^(2a))`
///    ([`rational_fixed_points_stage`], [`seeded_weights`], `a = amplitude`).
///
/// Every chain is a diffeomorphism for any seed and amplitude the generators accept, so the model
/// is valid. A dimension other than 2 or 3, or `radii` of another length than `centre`, is
/// [`Error::ShapeDimension`].
///
/// ```
/// use ism_examples::ellipsoid_model;
/// use ism_format::Direction;
/// let m = ellipsoid_model(&[0.1, 0.0, -0.1], &[0.6, 0.5, 0.4], 2, (3, 7, 0.5), Direction::Implicit)?;
/// assert_eq!((m.dim(), m.num_simplices(), m.stages.len()), (3, 48, 1));
/// let flat = ellipsoid_model(&[0.0; 3], &[0.5; 2], 2, (0, 1, 0.5), Direction::Implicit);
/// assert!(matches!(flat, Err(ism_examples::Error::ShapeDimension { centre: 3, radii: 2 })));
/// # Ok::<(), ism_examples::Error>(())
/// ```
pub fn ellipsoid_model(
    centre: &[f64],
    radii: &[f64],
    cells: usize,
    (chain, seed, amplitude): (usize, u64, f64),
    direction: Direction,
) -> Result<Model, Error> {
    let n = centre.len();
    if radii.len() != n || !(2..=3).contains(&n) {
        return Err(Error::ShapeDimension {
            centre: n,
            radii: radii.len(),
        });
    }
    let (centre, radii) = (centre.to_vec(), radii.to_vec());
    let g = move |p: &[f64]| {
        (0..centre.len())
            .map(|k| ((p[k] - centre[k]) / radii[k]).powi(2))
            .sum::<f64>()
            - 1.0
    };
    let mut model = match n {
        2 => kuhn_grid_2d(cells, cells, Aabb::cube(-1.0, 1.0), g)?,
        3 => kuhn_grid_3d(cells, cells, cells, Aabb::cube(-1.0, 1.0), g)?,
        _ => unreachable!("the dimension was checked above"),
    };
    let mut stages = match chain % ELLIPSOID_CHAINS {
        0 => stratified_stages(&model, seed, amplitude),
        1 => vec![quadratic_edge_stage(&model, seed, amplitude)],
        2 => vec![monotonic_stage(&model, 3, seed, amplitude)],
        _ => vec![rational_fixed_points_stage(
            &model,
            3,
            seeded_weights(seed, 2.0 * amplitude),
        )],
    };
    for stage in &mut stages {
        stage.direction = direction;
    }
    model.stages = stages;
    Ok(model)
}
