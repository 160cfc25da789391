//! ISM fitting: adaptive polygonization of implicit functions, after Mello & Velho, *Simplicial
//! Diffeomorphisms* (IMPA technical report TR-2009-05, 2009, §9.2; Computer Aided Geometric Design
//! 27, 2010, §6), cited below as "Mello & Velho 2009" and "2010"; `spec/mathematics.md` restates
//! what this crate uses.
//!
//! - [`expr`]: `g` from text (`exmex`), exact symbolic gradient, interval enclosures;
//!   [`presets`]: circle, Taubin's curve, sphere, torus, genus-2 surface.
//! - [`complex`]: Kuhn/Freudenthal triangulation of a box, conforming longest-edge bisection.
//! - [`strata`]: the stratified Bézier map the fitter optimizes (valid by construction).
//! - [`fit`](mod@fit): the adaptive loop (Plantinga–Vegter topology refinement, edge roots, face-wise
//!   Levenberg–Marquardt, refinement of cells above the tolerance) and its report.
//! - [`measure`]: the two-sided distance between a fitted shape and its target (certified
//!   bounds, not first-order estimates); [`roundtrip`]: the encoding/export/sampling check a fit
//!   passes before it is written; [`verdict`]: the outcome every front end reports.
//! - [`shell`]: the written complex — the simplices that hold the solid, the records that move
//!   the shape.
//! - [`isocontour`]: the linear isocomplex, its topology and samples; [`svg`]: 2D pictures.
//! - [`mesh`]: closed triangle meshes as targets (loading, winding numbers, signed distance).
//! - Editing models: [`hermite`] (free-form modeling from Hermite data), [`smooth`] (normal jumps
//!   across facets), [`c1`] (rational C¹ weights); the first two optimize the layered map of
//!   [`layered`] (`X = S ∘ Y⁻¹`, the block's exact Jacobian) face by face with [`lm`].
//!
//! ```
//! use ism_fit::{fit, FitOptions, Preset};
//!
//! let circle = Preset::find("circle")?;
//! let g = circle.expression()?;
//! let mut options = FitOptions::new(circle.domain);
//! options.resolution = 4;
//! options.tolerance = 1e-3;
//! let fitted = fit(&g, &options, &ism_format::Progress::none())?;
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
pub mod layered;
pub mod lm;
pub mod measure;
pub mod mesh;
pub mod presets;
pub mod rational;
pub mod roundtrip;
pub mod shell;
pub mod smooth;
pub mod strata;
pub mod svg;
pub mod verdict;

#[cfg(test)]
mod test_rng;

pub use expr::{Expression, ImplicitFunction};
pub use fit::{fit, FitOptions, FitReport, Fitted};
pub use ism_format::progress::{Cancelled, Progress, Step};
pub use presets::{Preset, PRESETS};

/// The first five structural errors of `model` (the reader's checks; warnings left out).
fn structural_errors(model: &ism_format::Model) -> Vec<ism_format::Diagnostic> {
    ism_format::structure::check(model, 5)
        .into_iter()
        .filter(|d| d.severity == ism_format::Severity::Error)
        .collect()
}

/// Diagnostics as one message, `; `-separated.
fn join_diagnostics(list: &[ism_format::Diagnostic]) -> String {
    let parts: Vec<String> = list.iter().map(|d| d.to_string()).collect();
    parts.join("; ")
}

/// `(x, y[, z])` for messages.
fn show_point(p: &[f64]) -> String {
    let parts: Vec<String> = p.iter().map(|x| format!("{x}")).collect();
    format!("({})", parts.join(", "))
}

/// Errors of this crate.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    /// The caller cancelled the fit through its [`Progress`].
    #[error(transparent)]
    Cancelled(#[from] Cancelled),
    /// An expression did not parse, or uses a variable the dimension does not have.
    #[error("expression `{text}`: {message}")]
    Expression {
        /// The expression text.
        text: String,
        /// What went wrong.
        message: String,
    },
    /// Inconsistent or out-of-range options.
    #[error("{0}")]
    Options(String),
    /// The kernel cannot evaluate the fitted (or given) model: its error, kept as the source.
    #[error("the model does not evaluate")]
    Eval(#[source] ism_geom::GeomError),
    /// `g` is not a finite number at a point of the domain.
    #[error(
        "g is {value} at {}: it is not defined there (e.g. sqrt or ln of a negative number, or a \
         division by zero); choose a domain where g is finite",
        show_point(.point)
    )]
    Undefined {
        /// Where.
        point: Vec<f64>,
        /// The value `g` returned there (NaN or ±∞).
        value: f64,
    },
    /// `g` changes sign along an edge without passing through zero: a pole or a jump.
    #[error(
        "g changes sign between {} and {} without a zero: |g| grows to {value:.3e} near {} (a pole \
         or a jump, as 1/x has at x = 0); the shape g = 0 must lie where g is continuous",
        show_point(.from),
        show_point(.to),
        show_point(.near)
    )]
    NoRoot {
        /// One end of the edge.
        from: Vec<f64>,
        /// The other end.
        to: Vec<f64>,
        /// Where the sign changes.
        near: Vec<f64>,
        /// `|g|` there.
        value: f64,
    },
    /// `g` has one sign at every vertex after the topology phase: no shape to fit.
    #[error(
        "g has no zero set in the domain: it is {} at all {vertices} vertices sampled (smallest \
         |g| = {smallest:.3e}, at {}); check the expression and the domain",
        if *.positive { "positive" } else { "negative" },
        show_point(.at)
    )]
    NoZeroSet {
        /// Whether `g` is positive (else negative) everywhere sampled.
        positive: bool,
        /// Number of vertices sampled.
        vertices: usize,
        /// The smallest `|g|` among them.
        smallest: f64,
        /// Where.
        at: Vec<f64>,
    },
    /// A mesh file that cannot be read, or a mesh that cannot define a distance.
    #[error("mesh {}", path.display())]
    Mesh {
        /// The file (empty for an in-memory mesh).
        path: std::path::PathBuf,
        /// What went wrong, typed (the reader's error says where in the file).
        #[source]
        source: mesh::MeshError,
    },
}
