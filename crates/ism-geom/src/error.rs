//! Typed errors of the math kernel.

/// Why a local map or a model evaluator could not be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GeomError {
    /// The model's dimension is outside `1..=3`.
    #[error("dimension {0}; expected 1, 2 or 3")]
    Dimension(usize),
    /// A stage index past the end of `stages`.
    #[error("stage {index} does not exist (the model has {count} stages)")]
    NoStage {
        /// Requested stage.
        index: usize,
        /// Number of stages.
        count: usize,
    },
    /// A simplex index past the end of `simplices`.
    #[error("simplex {index} does not exist (the model has {count} simplices)")]
    NoSimplex {
        /// Requested simplex.
        index: usize,
        /// Number of simplices.
        count: usize,
    },
    /// A vertex id past the end of `vertices`.
    #[error(
        "simplex {simplex}: vertex id {vertex} does not exist (the model has {count} vertices)"
    )]
    NoVertex {
        /// Simplex referencing the vertex.
        simplex: usize,
        /// Offending id.
        vertex: u32,
        /// Number of vertices.
        count: usize,
    },
    /// The model breaks a structural rule evaluation depends on (spec §2–5): the rule, where, and
    /// what was expected.
    #[error("{0}")]
    Structure(Box<ism_format::Diagnostic>),
    /// Degree 0 or above [`crate::MAX_DEGREE`].
    #[error("stage {stage}: degree {degree}; expected 1 to {max}", max = crate::MAX_DEGREE)]
    Degree {
        /// Stage index.
        stage: usize,
        /// Declared degree.
        degree: u32,
    },
    /// A face record whose arrays do not have the lengths its face and the degree imply.
    #[error("stage {stage}, face record {record} (face {face:?}): {what}: {found} numbers, expected {expected}")]
    FaceRecord {
        /// Stage index.
        stage: usize,
        /// Record index in `faces`.
        record: usize,
        /// The record's face.
        face: Vec<u32>,
        /// Which array (`points`, `weights`, `face`).
        what: &'static str,
        /// Length found.
        found: usize,
        /// Length expected.
        expected: usize,
    },
    /// A monotonic vertex map with the wrong number of coefficients.
    #[error("stage {stage}, vertex map {record} (vertex {vertex}): {found} coefficients, expected {expected}")]
    VertexMap {
        /// Stage index.
        stage: usize,
        /// Record index in `vertexMaps`.
        record: usize,
        /// Its vertex id.
        vertex: u32,
        /// Length found.
        found: usize,
        /// Length expected (`degree + 1`).
        expected: usize,
    },
    /// A top simplex whose vertices are affinely dependent (zero volume).
    #[error("simplex {simplex} is degenerate (edge-matrix determinant {det:e})")]
    Degenerate {
        /// Simplex index.
        simplex: usize,
        /// The determinant found.
        det: f64,
    },
    /// Array lengths of the model disagree (`vertices`, `values`, `simplices`).
    #[error("model arrays disagree: {0}")]
    Shape(String),
    /// Bernstein coefficient arrays of the wrong length.
    #[error("Bernstein polynomial in {vars} variables of degree {degree} needs {expected} coefficients, got {found}")]
    Coefficients {
        /// Number of variables `m`.
        vars: usize,
        /// Degree.
        degree: u32,
        /// Needed.
        expected: usize,
        /// Given.
        found: usize,
    },
}

/// Result alias of this crate.
pub type Result<T> = std::result::Result<T, GeomError>;

impl From<ism_format::Error> for GeomError {
    /// The first diagnostic of a structural error (indexing reports nothing else).
    fn from(e: ism_format::Error) -> GeomError {
        match e.diagnostics().first() {
            Some(d) => GeomError::Structure(Box::new(d.clone())),
            None => GeomError::Shape(e.to_string()),
        }
    }
}
