//! ISM fitting: adaptive polygonization of implicit functions (papers `000` §9.2, `001` §6).
//!
//! - [`expr`]: `g` from text (`exmex`), exact symbolic gradient, interval enclosures;
//!   [`presets`]: circle, Taubin's curve, sphere, torus, genus-2 surface.
//! - [`complex`]: Kuhn/Freudenthal triangulation of a box, conforming longest-edge bisection.
//! - [`strata`]: the stratified Bézier map the fitter optimizes (valid by construction).
//! - [`fit`](mod@fit): the adaptive loop (Plantinga–Vegter topology refinement, edge roots, face-wise
//!   Levenberg–Marquardt, refinement of cells above the tolerance) and its report.
//! - [`isocontour`]: the linear isocomplex, its topology and samples; [`svg`]: 2D pictures.
//!
//! ```
//! use ism_fit::{fit, FitOptions, Preset};
//!
//! let circle = Preset::find("circle")?;
//! let g = circle.expression()?;
//! let mut options = FitOptions::new(circle.domain);
//! options.resolution = 4;
//! options.tolerance = 1e-3;
//! let fitted = fit(&g, &options, &mut |_| {})?;
//! assert!(fitted.report.tolerance_met);
//! assert_eq!((fitted.report.topology.components, fitted.report.topology.euler), (1, 0));
//! let model = fitted.to_model("circle");
//! assert!(ism_format::structure::check(&model, 10)
//!     .iter()
//!     .all(|d| d.severity != ism_format::Severity::Error));
//! # Ok::<(), ism_fit::FitError>(())
//! ```
#![deny(missing_docs)]

pub mod c1;
pub mod complex;
pub mod expr;
pub mod fit;
pub mod hermite;
pub mod interval;
pub mod isocontour;
pub mod mesh;
pub mod presets;
pub mod rational;
pub mod smooth;
pub mod strata;
pub mod svg;

pub use expr::{Expression, ImplicitFunction};
pub use fit::{fit, FitOptions, FitReport, Fitted, Progress};
pub use presets::{Preset, PRESETS};

/// Errors of this crate.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    /// An expression did not parse, or uses a variable the dimension does not have.
    #[error("expression `{text}`: {message}")]
    Expression {
        /// The expression text.
        text: String,
        /// What went wrong.
        message: String,
    },
    /// Inconsistent or out-of-range options.
    #[error("options: {0}")]
    Options(String),
    /// A mesh file that cannot be read, or a mesh that cannot define a distance.
    #[error("mesh {}: {message}", path.display())]
    Mesh {
        /// The file (empty for an in-memory mesh).
        path: std::path::PathBuf,
        /// What went wrong.
        message: String,
    },
}
