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
    /// The stages fold at a vertex the export placed: their Jacobian determinant there is clearly
    /// negative ([`crate::extract::FOLD_DETERMINANT`]), so the model is not valid (a valid
    /// model's is positive everywhere) and its shape has no mesh to export.
    #[error(
        "simplex {simplex}: the stages fold at u = {u:?} (Jacobian determinant {determinant:.3} \
         relative to its entries; a valid model's is positive everywhere): the model is not \
         valid there, run `ism validate` on it"
    )]
    Fold {
        /// Top simplex id.
        simplex: usize,
        /// The point of the linear patch, barycentric in the simplex's stored vertex order.
        u: Vec<f64>,
        /// `det J / Π_k Σ_l |J_kl|` at the point (in `[−1, 0)`).
        determinant: f64,
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

/// Why an OBJ or glTF/GLB triangle mesh could not be read ([`crate::obj::read_obj`],
/// [`crate::gltf::read_gltf`]). Each variant says where: the OBJ object and triangle, the glTF mesh,
/// primitive, accessor, buffer, node or scene. The messages are those `ism fit --mesh` prints after
/// the file's name.
#[derive(Debug, thiserror::Error)]
pub enum MeshReadError {
    /// `tobj` could not parse the text.
    #[error("OBJ: {0}")]
    Obj(tobj::LoadError),
    /// A face names a vertex its object does not have.
    #[error(
        "OBJ object `{object}`, triangle {triangle}: vertex index out of range (has {vertices} \
         vertices)"
    )]
    ObjIndex {
        /// The object's name.
        object: String,
        /// The triangle, counted within the object after triangulation.
        triangle: usize,
        /// The object's vertices.
        vertices: usize,
    },
    /// The `gltf` crate could not parse or validate the document.
    #[error("glTF: {0}")]
    Gltf(::gltf::Error),
    /// A primitive names an accessor the document does not have.
    #[error("glTF mesh {mesh}, primitive {primitive}: accessor {accessor} does not exist")]
    GltfAccessor {
        /// Mesh index.
        mesh: usize,
        /// Primitive index within the mesh.
        primitive: usize,
        /// The missing accessor.
        accessor: usize,
    },
    /// A relative buffer URI whose percent-decoding is not UTF-8.
    #[error("glTF buffer {buffer}: URI is not UTF-8 after percent-decoding")]
    GltfBufferUri {
        /// Buffer index.
        buffer: usize,
    },
    /// The buffers' declared lengths together pass `Limits::max_payload_bytes`.
    #[error(
        "the glTF buffers declare {declared} bytes, above the limit of {limit} (max_payload_bytes)"
    )]
    GltfBufferBytes {
        /// Sum of the declared lengths (saturating).
        declared: u64,
        /// The limit.
        limit: u64,
    },
    /// A GLB header whose total length is below the header's own 12 bytes.
    #[error("GLB header (byte 8): total length {length} is below the 12-byte header")]
    GlbLength {
        /// The declared total length.
        length: u32,
    },
    /// A buffer could not be loaded (a missing file, a bad `data:` URI, a short blob).
    #[error("glTF buffers: {0}")]
    GltfBuffers(::gltf::Error),
    /// A node chain deeper than the reader walks.
    #[error("glTF node hierarchy deeper than {max}")]
    GltfNodeDepth {
        /// The deepest level walked.
        max: usize,
    },
    /// A node reached twice within one scene (two parents, or a child listed twice).
    #[error(
        "glTF node {node} is reached twice in scene {scene}; nodes form disjoint trees (glTF \
         2.0), each with at most one parent"
    )]
    GltfNodeTwice {
        /// Node index.
        node: usize,
        /// Scene index, in the order the scenes are read.
        scene: usize,
    },
    /// A triangle primitive without positions.
    #[error("mesh {mesh}, primitive {primitive}: no POSITION data")]
    GltfNoPositions {
        /// Mesh index.
        mesh: usize,
        /// Primitive index within the mesh.
        primitive: usize,
    },
    /// An indices accessor of a type glTF 2.0 §3.7.2.1 forbids.
    #[error(
        "mesh {mesh}, primitive {primitive}: indices accessor {accessor} holds {data_type:?} \
         {dimensions:?}; expected unsigned byte, short or int scalars"
    )]
    GltfIndexType {
        /// Mesh index.
        mesh: usize,
        /// Primitive index within the mesh.
        primitive: usize,
        /// The accessor.
        accessor: usize,
        /// Its component type.
        data_type: ::gltf::accessor::DataType,
        /// Its element type.
        dimensions: ::gltf::accessor::Dimensions,
    },
    /// A `POSITION` accessor that does not hold float `VEC3`s (glTF 2.0 §3.7.2.1).
    #[error(
        "mesh {mesh}, primitive {primitive}: POSITION accessor {accessor} holds {data_type:?} \
         {dimensions:?}; expected float VEC3"
    )]
    GltfPositionType {
        /// Mesh index.
        mesh: usize,
        /// Primitive index within the mesh.
        primitive: usize,
        /// The accessor.
        accessor: usize,
        /// Its component type.
        data_type: ::gltf::accessor::DataType,
        /// Its element type.
        dimensions: ::gltf::accessor::Dimensions,
    },
    /// An index past the primitive's vertices.
    #[error(
        "mesh {mesh}, primitive {primitive}: index {index} out of range ({vertices} vertices)"
    )]
    GltfIndexRange {
        /// Mesh index.
        mesh: usize,
        /// Primitive index within the mesh.
        primitive: usize,
        /// The index.
        index: u32,
        /// The primitive's vertices.
        vertices: usize,
    },
    /// More vertices or triangles than the limits allow (or than `u32` ids can address).
    #[error("the mesh has more than {max} {what} (limit {limit})")]
    TooLarge {
        /// The bound passed.
        max: u64,
        /// `vertices` or `triangles`.
        what: &'static str,
        /// The `Limits` field: `max_vertices` or `max_simplices`.
        limit: &'static str,
    },
}

impl MeshReadError {
    /// [`MeshReadError::TooLarge`] when `vertices` or `triangles` pass `limits` — or pass what
    /// `u32` vertex ids can address, whatever the limits say (a larger id would wrap).
    pub(crate) fn check_counts(
        vertices: usize,
        triangles: usize,
        limits: &ism_format::io::Limits,
    ) -> std::result::Result<(), MeshReadError> {
        let max_vertices = limits.max_vertices.min(u64::from(u32::MAX));
        for (count, max, what, limit) in [
            (vertices, max_vertices, "vertices", "max_vertices"),
            (
                triangles,
                limits.max_simplices,
                "triangles",
                "max_simplices",
            ),
        ] {
            if count as u64 > max {
                return Err(MeshReadError::TooLarge { max, what, limit });
            }
        }
        Ok(())
    }
}
