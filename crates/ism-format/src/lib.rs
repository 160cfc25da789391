//! The ISM file format: data model, encodings and structural checks.
//!
//! An *Iso-Simplicial Model* is a simplicial complex with a nonzero value per vertex and a sequence
//! of simplicial diffeomorphism stages; its shape is the level set `F = c` of the deformed
//! piecewise-linear function. This crate reads and writes the six encodings of
//! `spec/ism-format.md` (JSON, MessagePack, binary, compact binary, compressed, structured), detects them by content, and
//! enforces the structural requirements a reader must. It does no geometry beyond orientation signs.
//!
//! ```
//! use ism_format::{builder::{ModelBuilder, StageBuilder}, io, Encoding};
//!
//! // A unit square as two triangles, one corner inside, with a quadratic stage bending one edge.
//! let model = ModelBuilder::new(2)
//!     .name("square")
//!     .vertex(&[0.0, 0.0], -1.0)
//!     .vertex(&[1.0, 0.0], 1.0)
//!     .vertex(&[1.0, 1.0], 1.0)
//!     .vertex(&[0.0, 1.0], 1.0)
//!     .simplex(&[0, 1, 2])
//!     .simplex(&[0, 2, 3])
//!     .stage(StageBuilder::bezier(2).face(&[0, 2], &[0.6, 0.4], &[]).build())
//!     .build()?;
//! for encoding in Encoding::ALL {
//!     let bytes = io::to_vec(&model, encoding, io::WriteOptions::default())?;
//!     let doc = io::from_slice(&bytes)?;
//!     assert_eq!(doc.encoding, encoding);
//!     assert_eq!(doc.model, model);
//! }
//! # Ok::<(), ism_format::Error>(())
//! ```
#![deny(missing_docs)]

mod binary;
pub mod builder;
pub mod canonical;
pub mod compressed;
mod decode;
pub mod error;
pub mod faces;
pub mod indexed;
pub mod io;
pub mod model;
pub mod multi_index;
pub mod progress;
pub mod refine;
pub mod rules;
pub mod structure;
mod structured;

pub use decode::MAX_DEPTH;
pub use error::{Error, ErrorChain, Result};
pub use faces::{FaceMut, FaceRef, FaceTable};
pub use indexed::{FaceId, IndexedModel, SimplexId, StageTable, Topology, VertexId};
pub use io::{Document, Encoding};
pub use model::{
    Direction, FaceRecord, JsonValue, Metadata, Model, Stage, StageKind, Version, VertexMap,
    FORMAT_VERSION,
};
pub use progress::{Cancelled, Progress};
pub use rules::{Diagnostic, Location, Rule, Severity};

/// The JSON Schema of the JSON encoding, generated from the types (checked in as
/// `spec/schema/ism.schema.json`).
pub fn json_schema() -> serde_json::Value {
    serde_json::to_value(schemars::schema_for!(Model)).expect("a schema is plain JSON")
}
