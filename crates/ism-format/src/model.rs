//! The ISM data model: one serde type per object of `spec/ism-format.md`.
//!
//! Field order matters: the binary encoding (§7.4 of the spec) writes fields in declaration order.

use std::collections::BTreeMap;

// Encode only: the binary writer uses bincode; the reader is hand-written (binary.rs) so that
// every error names its member and byte offset.
use bincode::Encode;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

pub use crate::faces::FaceTable;

/// The format version this crate writes, and the newest it reads.
pub const FORMAT_VERSION: Version = Version { major: 1, minor: 0 };

/// `major.minor` format version (spec §2.1, §8.1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Version {
    /// Incompatible revisions.
    pub major: u16,
    /// Backward-compatible additions.
    pub minor: u16,
}

impl Version {
    /// Parses `"1.0"`; `None` unless the text is two decimal integers of at most 65535, without
    /// leading zeros, separated by a dot (spec §2.1: `"01.0"` is not a version).
    pub fn parse(text: &str) -> Option<Version> {
        let (a, b) = text.split_once('.')?;
        let digits = |s: &str| {
            !s.is_empty()
                && s.len() <= 5
                && s.bytes().all(|c| c.is_ascii_digit())
                && (s.len() == 1 || !s.starts_with('0'))
        };
        if !digits(a) || !digits(b) {
            return None;
        }
        Some(Version {
            major: a.parse().ok()?,
            minor: b.parse().ok()?,
        })
    }
}

impl std::fmt::Display for Version {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}.{}", self.major, self.minor)
    }
}

/// Any JSON value, carried verbatim by every encoding (spec §2.7: `extras`, `extensions`).
///
/// The binary encoding stores it as its canonical compact JSON text (spec §7.7), so all four
/// encodings keep it exactly.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema, Default)]
#[serde(transparent)]
pub struct JsonValue(pub serde_json::Value);

impl Encode for JsonValue {
    fn encode<E: bincode::enc::Encoder>(
        &self,
        encoder: &mut E,
    ) -> Result<(), bincode::error::EncodeError> {
        crate::canonical::json_text(&self.0).encode(encoder)
    }
}

impl JsonValue {
    /// Whether this is JSON `null` (how an absent `extras` reads).
    pub fn is_null(&self) -> bool {
        self.0.is_null()
    }
}

/// A complete Iso-Simplicial Model (spec §2).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema, Encode)]
#[serde(rename_all = "camelCase")]
#[schemars(
    title = "ISM model",
    description = "An Iso-Simplicial Model, JSON encoding of spec/ism-format.md version 1.0"
)]
pub struct Model {
    /// Format version `"major.minor"`; this specification is `"1.0"`.
    #[schemars(regex(
        pattern = r"^(0|[1-9][0-9]{0,3}|[1-5][0-9]{4}|6[0-4][0-9]{3}|65[0-4][0-9]{2}|655[0-2][0-9]|6553[0-5])\.(0|[1-9][0-9]{0,3}|[1-5][0-9]{4}|6[0-4][0-9]{3}|65[0-4][0-9]{2}|655[0-2][0-9]|6553[0-5])$"
    ))]
    pub version: String,
    /// Space dimension `n`: 2 (curves in the plane) or 3 (surfaces in space).
    #[schemars(range(min = 2, max = 3))]
    pub dimension: u8,
    /// Descriptive metadata.
    #[serde(default)]
    pub metadata: Metadata,
    /// Vertex coordinates, flat: `n` numbers per vertex.
    pub vertices: Vec<f64>,
    /// Top simplices, flat: `n + 1` vertex indices each, positively oriented.
    #[schemars(extend(
        "minItems" = 3,
        "items" = {"type": "integer", "format": "uint32", "minimum": 0, "maximum": 4294967295u64}
    ))]
    pub simplices: Vec<u32>,
    /// The vertex function `f`: one nonzero number per vertex.
    #[schemars(extend("items" = {"type": "number", "format": "double", "not": {"const": 0}}))]
    pub values: Vec<f64>,
    /// The level `c` of the shape `F = c`.
    #[serde(default)]
    pub level: f64,
    /// Diffeomorphism stages; `stages[0]` is applied first (spec §5).
    #[serde(default)]
    pub stages: Vec<Stage>,
    /// Names of the extensions this file uses.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub extensions_used: Vec<String>,
    /// Names of the extensions a reader must understand to read this file.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub extensions_required: Vec<String>,
    /// Extension payloads keyed by extension name.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub extensions: BTreeMap<String, JsonValue>,
    /// Application-specific data; readers carry it through untouched. `null` means none.
    #[serde(default, skip_serializing_if = "JsonValue::is_null")]
    pub extras: JsonValue,
}

/// Descriptive metadata (spec §2.6). Every member is optional.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, JsonSchema, Encode)]
#[serde(rename_all = "camelCase")]
pub struct Metadata {
    /// A short human-readable name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(with = "String")]
    pub name: Option<String>,
    /// The program that wrote the file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(with = "String")]
    pub generator: Option<String>,
    /// Length unit of the vertex coordinates, e.g. `"m"` or `"mm"`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(with = "String")]
    pub units: Option<String>,
    /// Free text.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(with = "String")]
    pub description: Option<String>,
}

/// Kind of a stage's map (spec §5.2–5.4).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema, Encode)]
#[serde(rename_all = "lowercase")]
pub enum StageKind {
    /// Polynomial Bernstein–Bézier map of degree `d`.
    Bezier,
    /// Rational Bernstein–Bézier map of degree `d` with positive weights.
    Rational,
    /// Monotonic map: one increasing 1-D Bernstein polynomial of degree `d` per vertex.
    Monotonic,
}

impl StageKind {
    /// The spelling used in JSON and in messages.
    pub fn as_str(self) -> &'static str {
        match self {
            StageKind::Bezier => "bezier",
            StageKind::Rational => "rational",
            StageKind::Monotonic => "monotonic",
        }
    }
}

/// Which way a stage's stored map points (spec §5.1).
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema, Encode,
)]
#[serde(rename_all = "lowercase")]
pub enum Direction {
    /// The stored map is the stage `X_k` itself: point coordinates → function coordinates.
    #[default]
    Implicit,
    /// The stored map is `X_k⁻¹`: function coordinates → point coordinates.
    Parametric,
}

/// One simplicial diffeomorphism stage (spec §5).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema, Encode)]
#[serde(rename_all = "camelCase")]
pub struct Stage {
    /// The map kind.
    pub kind: StageKind,
    /// Polynomial degree `d ≥ 1` (at most 16, spec §5).
    #[schemars(range(min = 1, max = 16))]
    pub degree: u32,
    /// Direction of the stored map.
    #[serde(default)]
    pub direction: Direction,
    /// Optional label.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(with = "String")]
    pub name: Option<String>,
    /// Moved control points (and weights) of Bézier and rational stages, one record per face.
    // Stored flat (`FaceTable`), encoded as the list of records; the schema is the list's.
    #[serde(default, skip_serializing_if = "FaceTable::is_empty")]
    #[schemars(with = "Vec<FaceRecord>")]
    pub faces: FaceTable,
    /// Per-vertex 1-D functions of a monotonic stage.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub vertex_maps: Vec<VertexMap>,
    /// Application-specific data. `null` means none.
    #[serde(default, skip_serializing_if = "JsonValue::is_null")]
    pub extras: JsonValue,
}

/// The control points (and weights) that a face owns (spec §5.2).
// Owned: what builders assemble and `FaceTable` stores flat.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema, Encode)]
#[serde(rename_all = "camelCase")]
pub struct FaceRecord {
    /// The face: its `k + 1` global vertex ids, strictly increasing.
    #[schemars(extend(
        "minItems" = 1,
        "maxItems" = 4,
        "items" = {"type": "integer", "format": "uint32", "minimum": 0, "maximum": 4294967295u64}
    ))]
    pub face: Vec<u32>,
    /// Control points, flat: `k + 1` barycentric coordinates (w.r.t. `face`) per owned multi-index,
    /// in canonical order.
    #[serde(default)]
    pub points: Vec<f64>,
    /// Rational stages only: one weight per owned multi-index, in canonical order.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub weights: Vec<f64>,
}

/// A monotonic stage's function `g_v` for one vertex (spec §5.4).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema, Encode)]
#[serde(rename_all = "camelCase")]
pub struct VertexMap {
    /// Global vertex id.
    #[schemars(extend("maximum" = 4294967295u64))]
    pub vertex: u32,
    /// The `d + 1` Bernstein coefficients `a_0 = 0 < a_1 < … < a_d`.
    pub coefficients: Vec<f64>,
}

impl Model {
    /// An empty model of the given dimension at the current format version.
    pub fn new(dimension: u8) -> Model {
        Model {
            version: FORMAT_VERSION.to_string(),
            dimension,
            metadata: Metadata::default(),
            vertices: Vec::new(),
            simplices: Vec::new(),
            values: Vec::new(),
            level: 0.0,
            stages: Vec::new(),
            extensions_used: Vec::new(),
            extensions_required: Vec::new(),
            extensions: BTreeMap::new(),
            extras: JsonValue::default(),
        }
    }

    /// `n`, as a `usize`.
    #[inline]
    pub fn dim(&self) -> usize {
        usize::from(self.dimension)
    }

    /// Number of vertices (`vertices.len() / n`).
    #[inline]
    pub fn num_vertices(&self) -> usize {
        self.vertices.len() / self.dim().max(1)
    }

    /// Number of top simplices.
    #[inline]
    pub fn num_simplices(&self) -> usize {
        self.simplices.len() / (self.dim() + 1)
    }

    /// Coordinates of vertex `v`.
    #[inline]
    pub fn vertex(&self, v: usize) -> &[f64] {
        let n = self.dim();
        &self.vertices[v * n..(v + 1) * n]
    }

    /// Vertex ids of top simplex `s`, in stored (positive) order.
    #[inline]
    pub fn simplex(&self, s: usize) -> &[u32] {
        let m = self.dim() + 1;
        &self.simplices[s * m..(s + 1) * m]
    }

    /// Iterator over the top simplices.
    pub fn simplex_iter(&self) -> std::slice::ChunksExact<'_, u32> {
        self.simplices.chunks_exact(self.dim() + 1)
    }

    /// The declared version, if it parses.
    pub fn parsed_version(&self) -> Option<Version> {
        Version::parse(&self.version)
    }
}

impl Stage {
    /// A stage of the given kind and degree with every control point fixed (the identity map).
    pub fn identity(kind: StageKind, degree: u32) -> Stage {
        Stage {
            kind,
            degree,
            direction: Direction::Implicit,
            name: None,
            faces: FaceTable::new(),
            vertex_maps: Vec::new(),
            extras: JsonValue::default(),
        }
    }

    /// Number of stored real parameters (coordinates, weights, coefficients).
    pub fn parameter_count(&self) -> usize {
        self.faces.num_points()
            + self.faces.num_weights()
            + self
                .vertex_maps
                .iter()
                .map(|m| m.coefficients.len())
                .sum::<usize>()
    }
}
