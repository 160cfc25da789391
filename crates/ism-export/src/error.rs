//! Errors of extraction, writing and import.

use std::path::PathBuf;

/// What went wrong, and where.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Writing or reading bytes failed.
    #[error("{}I/O error", path.as_ref().map(|p| format!("{}: ", p.display())).unwrap_or_default())]
    Io {
        /// The file, when known.
        path: Option<PathBuf>,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// The model cannot be extracted (e.g. a dimension other than 2 or 3).
    #[error("model not supported: {0}")]
    Unsupported(String),
    /// The math kernel cannot evaluate the model (a degenerate simplex, a malformed stage
    /// record): its error, kept as the source.
    #[error("cannot evaluate the model")]
    Geom(#[from] ism_geom::GeomError),
    /// A stage could not be inverted at a point of the linear patch of a simplex.
    #[error(
        "simplex {simplex}: stage inversion did not converge at u = {u:?} (residual {residual:e})"
    )]
    Inversion {
        /// Top simplex id.
        simplex: usize,
        /// The point of the linear patch, barycentric in the simplex's stored vertex order.
        u: Vec<f64>,
        /// Final residual `|X(w) − u|`.
        residual: f64,
    },
    /// The mesh has more vertices or cells than the target format can index.
    #[error("mesh too large for {format}: {what}")]
    TooLarge {
        /// Target format.
        format: &'static str,
        /// What overflowed.
        what: String,
    },
    /// The glTF document could not be serialized.
    #[error("glTF serialization: {0}")]
    Gltf(String),
    /// The caller cancelled the call through its [`ism_format::Progress`].
    #[error(transparent)]
    Cancelled(#[from] ism_format::Cancelled),
    /// An imported mesh file is malformed.
    #[error("{format} import{}: {message}", location.as_ref().map(|l| format!(" at {l}")).unwrap_or_default())]
    Import {
        /// Source format (`vtu`, `vtk`, `msh`).
        format: &'static str,
        /// Where: line number, XML element or byte offset.
        location: Option<String>,
        /// What was expected.
        message: String,
    },
}

impl Error {
    pub(crate) fn io(source: std::io::Error) -> Error {
        Error::Io { path: None, source }
    }

    pub(crate) fn import(
        format: &'static str,
        location: impl Into<Option<String>>,
        message: impl Into<String>,
    ) -> Error {
        Error::Import {
            format,
            location: location.into(),
            message: message.into(),
        }
    }
}

impl From<std::io::Error> for Error {
    fn from(source: std::io::Error) -> Error {
        Error::io(source)
    }
}

/// `Result` with this crate's [`Error`].
pub type Result<T> = std::result::Result<T, Error>;
