//! ISM fitting: adaptive polygonization of implicit functions (papers `000` §9.2, `001` §6).
#![deny(missing_docs)]

pub mod complex;
pub mod expr;
pub mod fit;
pub mod interval;
pub mod isocontour;
pub mod presets;
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
}
