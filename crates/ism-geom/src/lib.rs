//! ISM math kernel: Bernstein–Bézier polynomials on simplices, simplicial diffeomorphism stages,
//! and whole-model evaluation. The mathematics (Mello & Velho, *Simplicial Diffeomorphisms*, 2009
//! report and 2010 CAGD paper) is restated in `spec/mathematics.md`.
//!
//! - [`bernstein`]: dense Bernstein polynomials in the canonical multi-index order — de Casteljau
//!   evaluation (exact at vertices), derivatives, products, degree elevation, edge subdivision and
//!   restriction to sub-simplices.
//! - [`stage`]: [`LocalStage`] (one stage on one top simplex, dense control net in local vertex
//!   order) and [`LocalMap`] (all stages of a simplex): `X(w)`, reduced and homogeneous Jacobians,
//!   `det`, and the inverse `X⁻¹(u)` by damped Newton with a continuation fallback. Points on a face
//!   stay on that face exactly.
//! - [`model`]: [`ModelEval`] — point location (uniform grid, R*-tree for graded meshes), `F(p)`, `∇F(p)`, inside/outside, the
//!   linear patches `θ_σ`, the parametric map `u ↦ p` and its derivative, batch APIs over rayon.
//!
//! Directions: [`LocalStage::eval`] is always `X` (point coordinates → function coordinates) and
//! [`LocalStage::inverse`] always `X⁻¹`; [`LocalStage::eval_stored`] / [`LocalStage::invert_stored`]
//! address the stored formula, which for a `parametric` stage is `X⁻¹` (so its `eval` solves by
//! Newton and its `inverse` is a direct evaluation).
//!
//! Barycentric points are [`Bary`] = `[f64; 4]` (first `n + 1` entries used; `n ≤ 3`), matrices
//! [`Mat`] = `[[f64; 4]; 4]` (upper-left block used), so evaluation never allocates.
//!
//! ```
//! use ism_format::builder::{ModelBuilder, StageBuilder};
//! use ism_geom::{LocalMap, ModelEval};
//!
//! // Two triangles; a quadratic stage moves the control point of the diagonal edge (0, 2).
//! let model = ModelBuilder::new(2)
//!     .vertex(&[0.0, 0.0], -1.0)
//!     .vertex(&[1.0, 0.0], 1.0)
//!     .vertex(&[1.0, 1.0], 1.0)
//!     .vertex(&[0.0, 1.0], 1.0)
//!     .simplex(&[0, 1, 2])
//!     .simplex(&[0, 2, 3])
//!     .stage(StageBuilder::bezier(2).face(&[0, 2], &[0.7, 0.3], &[]).build())
//!     .build_unchecked();
//! let map = LocalMap::from_model(&model, 0)?;
//! let w = [0.2, 0.3, 0.5, 0.0];
//! let u = map.eval(&w);
//! let back = map.inverse(&u);
//! assert!(back.converged && (back.w[1] - w[1]).abs() < 1e-10);
//! assert_eq!(map.eval(&[0.0, 0.4, 0.6, 0.0])[0], 0.0); // on edge (1, 2): stays there exactly
//! assert!(map.det(&w) > 0.0);
//!
//! let eval = ModelEval::new(&model)?;
//! let f = eval.value(&[0.5, 0.25]).unwrap();
//! let at_vertex = eval.value(&[1.0, 0.0]).unwrap();
//! assert_eq!(at_vertex, 1.0);
//! assert!(f.is_finite() && eval.patch(0).is_some());
//! # Ok::<(), ism_geom::GeomError>(())
//! ```
#![deny(missing_docs)]

pub mod bernstein;
pub mod error;
pub mod interval;
pub mod linalg;
pub mod model;
mod spatial;
pub mod stage;
mod tables;

pub use bernstein::{Bernstein, Restriction};
pub use error::{GeomError, Result};
pub use model::{Located, ModelEval, ParamPoint, Patch, PatchCorner, LOCATE_TOLERANCE};
pub use stage::{InverseResult, LocalMap, LocalStage, Solved, INVERSE_TOLERANCE};

/// Largest number of barycentric coordinates supported (`n ≤ 3`).
pub const MAX_VARS: usize = 4;

/// Largest stage degree (the format's limit, `ism_format::structure::MAX_DEGREE`).
pub const MAX_DEGREE: u32 = ism_format::structure::MAX_DEGREE;

/// Barycentric coordinates: the first `n + 1` entries are used, the rest are zero.
pub type Bary = [f64; MAX_VARS];

/// A small matrix: only the upper-left block (`n × n` or `(n + 1) × (n + 1)`) is meaningful.
pub type Mat = [[f64; MAX_VARS]; MAX_VARS];
