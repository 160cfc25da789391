//! ISM example and benchmark models: Kuhn-triangulated grids, vertex values from implicit
//! functions, stage generators whose output the theorems of `mathematics.md` §3 certify as simplicial
//! diffeomorphisms, the named examples of `spec/examples/`, and the broken files of
//! `spec/vectors/reader/` and the expected bytes of `spec/vectors/writer/`.
//!
//! Everything is deterministic: the same arguments (and seed) give the same bytes.
//!
//! ```
//! use ism_examples::{kuhn_grid_3d, stratified_stages, Aabb};
//!
//! // A sphere of radius 0.6 on a 3×3×3 cube grid with a stratified stage on every face.
//! let mut model = kuhn_grid_3d(3, 3, 3, Aabb::cube(-1.0, 1.0), |p| {
//!     p.iter().map(|x| x * x).sum::<f64>() - 0.36
//! })?;
//! model.stages = stratified_stages(&model, 42, 0.5);
//! assert_eq!(model.num_simplices(), 6 * 27);
//! assert_eq!(model.stages.iter().map(|s| s.degree).collect::<Vec<_>>(), [4, 3, 2]);
//! // It reads back from every encoding.
//! for encoding in ism_format::Encoding::ALL {
//!     let bytes = ism_format::io::to_vec(&model, encoding, Default::default()).unwrap();
//!     assert_eq!(ism_format::io::from_slice(&bytes).unwrap().model, model);
//! }
//! # Ok::<(), ism_examples::Error>(())
//! ```
#![deny(missing_docs)]

mod faces;
mod grid;
pub mod named;
mod shapes;
mod stages;
pub mod vectors;
pub mod writer_vectors;

pub use faces::{faces_of_dimension, FaceRng};
pub use grid::{kuhn_grid_2d, kuhn_grid_3d, set_values, Aabb, VALUE_NUDGE};
pub use shapes::{ellipsoid_model, ELLIPSOID_CHAINS};
pub use stages::{
    cubic_face_point_stage, level_crossing_stage, level_crossing_stages, monotonic_stage,
    quadratic_edge_stage, rational_fixed_points_stage, seeded_weights, solitary_point,
    stratified_stages, stratum_stage, MAX_AMPLITUDE,
};

/// Why a generator could not build a model.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// A grid needs at least one cell per axis.
    #[error("grid has 0 cells along axis {axis}; expected at least 1")]
    NoCells {
        /// The axis (0 = x).
        axis: usize,
    },
    /// The box is empty or not finite along an axis.
    #[error("box axis {axis} is [{min}, {max}]; expected finite min < max")]
    BadBox {
        /// The axis.
        axis: usize,
        /// Lower bound given.
        min: f64,
        /// Upper bound given.
        max: f64,
    },
    /// Vertex ids are `u32` in the format.
    #[error("grid would have {vertices} vertices; the format's u32 ids allow at most 4294967295")]
    TooLarge {
        /// Vertex count requested (saturated).
        vertices: usize,
    },
    /// A model could not be encoded.
    #[error("encoding {}: {message}", path.display())]
    Encode {
        /// The file being written.
        path: std::path::PathBuf,
        /// The encoder's message.
        message: String,
    },
    /// A file could not be written.
    #[error("writing {}: {error}", path.display())]
    Write {
        /// The file.
        path: std::path::PathBuf,
        /// The operating system's error.
        error: std::io::Error,
    },
    /// [`ellipsoid_model`]'s centre and radii do not give one dimension of 2 or 3.
    #[error(
        "ellipsoid with {centre} centre coordinates and {radii} radii; expected 2 or 3 of each"
    )]
    ShapeDimension {
        /// Coordinates of the centre given.
        centre: usize,
        /// Radii given.
        radii: usize,
    },
    /// The implicit function returned NaN or ±∞.
    #[error("implicit function is {value} at vertex {vertex}; expected a finite number")]
    NonFiniteValue {
        /// The vertex id.
        vertex: usize,
        /// What the function returned.
        value: f64,
    },
}

/// Seed of the stages of [`large_stratified_model`].
pub const LARGE_MODEL_SEED: u64 = 20_260_101;

/// Amplitude of the solitary-point moves of [`large_stratified_model`]: moderate, so every stage
/// is far from degenerate.
pub const LARGE_MODEL_AMPLITUDE: f64 = 0.5;

/// A benchmark model with at least `target_tets` tetrahedra: the Kuhn triangulation of an `N³`
/// grid of `[−1, 1]³` with `N = ⌈(target_tets / 6)^⅓⌉`, values of the sphere `|p|² − 0.6²`, and
/// the three [`stratified_stages`] (solitary points on every edge, triangle and tetrahedron).
///
/// `large_stratified_model(1_000_000)` has `N = 56`: 1,053,696 tetrahedra, 185,193 vertices and
/// about 4.5 million face records.
pub fn large_stratified_model(target_tets: usize) -> ism_format::Model {
    let mut n = 1usize;
    while 6 * n * n * n < target_tets {
        n += 1;
    }
    let mut model = kuhn_grid_3d(n, n, n, Aabb::cube(-1.0, 1.0), |p| {
        p.iter().map(|x| x * x).sum::<f64>() - 0.36
    })
    .expect("a cube grid with N ≥ 1 and finite values is always valid");
    model.metadata.name = Some(format!(
        "stratified sphere, {} tetrahedra",
        model.num_simplices()
    ));
    model.metadata.generator = Some(concat!("ism-examples ", env!("CARGO_PKG_VERSION")).into());
    model.stages = stratified_stages(&model, LARGE_MODEL_SEED, LARGE_MODEL_AMPLITUDE);
    model
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn large_model_meets_its_target_with_the_smallest_grid() {
        let m = large_stratified_model(5000);
        // 6 · 9³ = 4374 < 5000 ≤ 6 · 10³.
        assert_eq!(m.num_simplices(), 6000);
        assert_eq!(m.stages.len(), 3);
        assert!(ism_format::structure::check(&m, 10).is_empty());
        assert_eq!(large_stratified_model(6).num_simplices(), 6);
    }
}
