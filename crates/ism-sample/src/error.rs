//! The crate's error type.

use std::path::PathBuf;

/// Why sampling, querying or writing a point set failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SampleError {
    /// The operating system refused a read or write.
    #[error("I/O error{}", path.as_ref().map(|p| format!(" on {}", p.display())).unwrap_or_default())]
    Io {
        /// The file, when known.
        path: Option<PathBuf>,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A request the sampler cannot honour (bad count, sigma, box, column layout …).
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
    /// The model has no surface to sample: no top simplex has vertices on both sides of the level.
    #[error("the shape F = c is empty: no top simplex has vertex values on both sides of the level {level}")]
    EmptySurface {
        /// The level `c`.
        level: f64,
    },
    /// No certified bound of the area element could be found for a simplex, so uniform sampling
    /// by curved area cannot be guaranteed there.
    #[error("simplex {simplex}, stage {stage}: {reason}")]
    Uncertified {
        /// Top simplex id.
        simplex: usize,
        /// Stage index (`stages[stage]`).
        stage: usize,
        /// What failed.
        reason: String,
    },
    /// A sample broke a certified bound or a tolerance: a bug or an invalid model, never ignored.
    #[error("simplex {simplex}: {reason}")]
    Numerical {
        /// Top simplex id.
        simplex: usize,
        /// What failed.
        reason: String,
    },
    /// The model could not be evaluated: the math kernel's error, kept as the source.
    #[error("model evaluation")]
    Geometry(#[from] ism_geom::GeomError),
    /// A points file could not be parsed.
    #[error("points input{}: {message}", location.as_ref().map(|l| format!(" at {l}")).unwrap_or_default())]
    Points {
        /// Where: `line 3, column 2` (text) or `byte 128` (NPY).
        location: Option<String>,
        /// What was expected.
        message: String,
    },
}

impl SampleError {
    /// A copy of a cached error (I/O errors keep their kind and text).
    pub fn duplicate(&self) -> SampleError {
        match self {
            SampleError::Io { path, source } => SampleError::Io {
                path: path.clone(),
                source: std::io::Error::new(source.kind(), source.to_string()),
            },
            SampleError::InvalidArgument(s) => SampleError::InvalidArgument(s.clone()),
            SampleError::EmptySurface { level } => SampleError::EmptySurface { level: *level },
            SampleError::Uncertified {
                simplex,
                stage,
                reason,
            } => SampleError::Uncertified {
                simplex: *simplex,
                stage: *stage,
                reason: reason.clone(),
            },
            SampleError::Numerical { simplex, reason } => SampleError::Numerical {
                simplex: *simplex,
                reason: reason.clone(),
            },
            SampleError::Geometry(e) => SampleError::Geometry(e.clone()),
            SampleError::Points { location, message } => SampleError::Points {
                location: location.clone(),
                message: message.clone(),
            },
        }
    }
}

/// Shorthand for this crate's results.
pub type Result<T, E = SampleError> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use super::*;

    /// Three collinear vertices make a degenerate triangle: the kernel's error is the source of
    /// [`SampleError::Geometry`] (its simplex and determinant), and survives `duplicate`.
    #[test]
    fn geometry_errors_keep_the_kernel_error_as_source() {
        let mut model = ism_format::Model::new(2);
        model.vertices = vec![0.0, 0.0, 1.0, 0.0, 2.0, 0.0];
        model.values = vec![-1.0, 1.0, 1.0];
        model.simplices = vec![0, 1, 2];
        let Err(err) = crate::sampler::Sampler::new(&model) else {
            panic!("a degenerate simplex must not evaluate");
        };
        let source =
            std::error::Error::source(&err).and_then(|e| e.downcast_ref::<ism_geom::GeomError>());
        assert!(
            matches!(
                source,
                Some(ism_geom::GeomError::Degenerate { simplex: 0, .. })
            ),
            "{err:?}"
        );
        assert!(matches!(
            err.duplicate(),
            SampleError::Geometry(ism_geom::GeomError::Degenerate { simplex: 0, .. })
        ));
        // The kernel's message is printed once: by the chain, not by the wrapper too.
        let kernel = "simplex 0 is degenerate (edge-matrix determinant";
        assert!(!err.to_string().contains(kernel), "{err}");
        let chain = ism_format::ErrorChain(&err).to_string();
        assert_eq!(chain.matches(kernel).count(), 1, "{chain}");
        assert!(chain.starts_with("model evaluation: simplex 0 is degenerate"));
    }

    /// I/O errors keep the operating system's error as their source and name it once.
    #[test]
    fn io_errors_name_their_cause_once() {
        let err = SampleError::Io {
            path: Some("/out/points.csv".into()),
            source: std::io::Error::other("disk full"),
        };
        assert_eq!(err.to_string(), "I/O error on /out/points.csv");
        assert_eq!(
            ism_format::ErrorChain(&err).to_string(),
            "I/O error on /out/points.csv: disk full"
        );
    }
}
