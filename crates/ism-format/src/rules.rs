//! Numbered requirements of `spec/ism-format.md` and the diagnostics that cite them.
//!
//! A [`Rule`]'s id (`ISM-104`) is stable: it is the heading of its requirement in the spec, and
//! validators, reports and tests quote it.

use serde::{Deserialize, Serialize};

/// How serious a diagnostic is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Severity {
    /// Informative only.
    Info,
    /// Legal but suspicious; does not make a file invalid.
    Warning,
    /// The file violates a MUST of the spec.
    Error,
}

macro_rules! rules {
    ($( $variant:ident = $id:literal, $sev:ident, $title:literal; )*) => {
        /// A numbered requirement of the spec.
        #[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
        pub enum Rule { $( #[doc = $title] $variant, )* }

        impl Rule {
            /// Every rule, in id order.
            pub const ALL: &'static [Rule] = &[$(Rule::$variant,)*];
            /// The stable id, e.g. `"ISM-104"`.
            pub fn id(self) -> &'static str { match self { $(Rule::$variant => $id,)* } }
            /// The severity of a violation.
            pub fn severity(self) -> Severity { match self { $(Rule::$variant => Severity::$sev,)* } }
            /// One-line statement of the requirement.
            pub fn title(self) -> &'static str { match self { $(Rule::$variant => $title,)* } }
            /// Looks a rule up by id.
            pub fn from_id(id: &str) -> Option<Rule> { match id { $($id => Some(Rule::$variant),)* _ => None } }
        }
    };
}

rules! {
    // Container and encoding (spec §7).
    BadMagic = "ISM-001", Error, "The file starts with the ISM container magic or is a JSON document";
    UnsupportedVersion = "ISM-002", Error, "The major version is one this reader implements";
    ChecksumMismatch = "ISM-003", Error, "The payload CRC-32 and header CRC-32 match the stored values";
    Truncated = "ISM-004", Error, "The file holds the whole header and the declared payload";
    UnknownEncoding = "ISM-005", Error, "The encoding tag is 1 (JSON), 2 (MessagePack), 3 (binary), 4 (compact) or 5 (compressed)";
    Malformed = "ISM-006", Error, "The payload decodes as the declared encoding and matches the data model";
    LimitExceeded = "ISM-007", Error, "The declared payload length and the model's entity counts fit the reader's limits";
    ExtensionRequired = "ISM-008", Error, "Every extension in extensionsRequired is supported by the reader";
    VersionMismatch = "ISM-009", Error, "The container version equals the payload's version member";
    TrailingData = "ISM-010", Error, "No bytes follow the declared payload";
    // Complex and vertex function (spec §2–3).
    Dimension = "ISM-101", Error, "dimension is 2 or 3";
    VertexArray = "ISM-102", Error, "vertices holds n finite numbers per vertex";
    SimplexArray = "ISM-103", Error, "simplices holds n + 1 indices per simplex and at least one simplex";
    IndexRange = "ISM-104", Error, "Every simplex index is less than the number of vertices";
    RepeatedIndex = "ISM-105", Error, "A simplex names n + 1 distinct vertices";
    Inverted = "ISM-106", Error, "Every simplex is positively oriented";
    Degenerate = "ISM-107", Error, "No simplex is degenerate (relative volume above the degeneracy tolerance)";
    DuplicateSimplex = "ISM-108", Error, "No two simplices have the same vertex set";
    FacetOvershared = "ISM-109", Error, "Every facet belongs to at most two simplices";
    Overlap = "ISM-110", Error, "Two simplices sharing a facet lie on opposite sides of it";
    ValueArray = "ISM-111", Error, "values holds one finite number per vertex";
    ValueZero = "ISM-112", Error, "No vertex value is zero";
    ValueAtLevel = "ISM-113", Error, "No vertex value equals the level";
    Level = "ISM-114", Error, "level is finite";
    NonManifold = "ISM-150", Warning, "Every vertex and edge has a manifold neighbourhood";
    UnusedVertex = "ISM-151", Warning, "Every vertex belongs to a simplex";
    ExtensionsListed = "ISM-152", Error, "extensionsRequired and the keys of extensions are listed in extensionsUsed, each name once";
    // Stages (spec §5).
    StageDegree = "ISM-120", Error, "A stage's degree is between 1 and the maximum degree";
    FaceSorted = "ISM-121", Error, "A face record's vertex ids are strictly increasing";
    NotAFace = "ISM-122", Error, "A face record names a face of the complex";
    DuplicateFace = "ISM-123", Error, "A stage has at most one record per face";
    PointCount = "ISM-124", Error, "A face record stores (k + 1) · C(d − 1, k) coordinates, and the face owns control points";
    WeightCount = "ISM-125", Error, "A rational face record stores C(d − 1, k) weights; other kinds store none";
    NonFinite = "ISM-126", Error, "Coordinates, weights and coefficients are finite";
    KindMismatch = "ISM-127", Error, "Face records belong to Bézier and rational stages, vertex maps to monotonic ones";
    VertexMapIndex = "ISM-128", Error, "A vertex map names an existing vertex, at most once per stage";
    CoefficientCount = "ISM-129", Error, "A vertex map stores d + 1 coefficients";
    // Invariance (spec §6.2): the validator certifies these.
    CoordinatePositive = "ISM-201", Error, "Every stored barycentric coordinate is positive";
    CoordinateSum = "ISM-202", Error, "Every stored control point's coordinates sum to 1 within the sum tolerance";
    WeightPositive = "ISM-203", Error, "Every rational weight is positive";
    MonotonicIncreasing = "ISM-204", Error, "A vertex map starts at 0 and is strictly increasing";
    // Positivity (spec §6.3).
    JacobianPositive = "ISM-301", Error, "det DX > 0 on every closed top simplex, for every stage";
    Undetermined = "ISM-302", Error, "The positivity of det DX is decided within the piece budget";
    // Quality (spec §6.4), reported with --quality.
    NormalJump = "ISM-401", Warning, "The normal of the shape jumps across an interior facet";
    RationalC1 = "ISM-402", Warning, "A rational stage's weights meet the C¹ condition at an interior facet";
    JacobianRange = "ISM-403", Info, "Range of det DX per stage";
}

/// Where a diagnostic applies. Every member is optional; set the ones that name the place.
#[derive(Clone, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize, PartialOrd, Ord)]
#[serde(rename_all = "camelCase")]
pub struct Location {
    /// JSON pointer (RFC 6901) into the JSON encoding, e.g. `/stages/0/faces/3/points/2`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pointer: Option<String>,
    /// Byte offset in the file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub offset: Option<u64>,
    /// Stage index.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stage: Option<usize>,
    /// Top simplex index.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub simplex: Option<usize>,
    /// Face, as its sorted vertex ids.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub face: Option<Vec<u32>>,
    /// Vertex id.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vertex: Option<usize>,
}

impl Location {
    /// A location with only a JSON pointer.
    pub fn pointer(p: impl Into<String>) -> Location {
        Location {
            pointer: Some(p.into()),
            ..Location::default()
        }
    }
    /// A location with only a byte offset.
    pub fn offset(offset: u64) -> Location {
        Location {
            offset: Some(offset),
            ..Location::default()
        }
    }
}

impl std::fmt::Display for Location {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let mut parts = Vec::new();
        if let Some(s) = self.stage {
            parts.push(format!("stage {s}"));
        }
        if let Some(s) = self.simplex {
            parts.push(format!("simplex {s}"));
        }
        if let Some(face) = &self.face {
            parts.push(format!("face {face:?}"));
        }
        if let Some(v) = self.vertex {
            parts.push(format!("vertex {v}"));
        }
        if let Some(p) = &self.pointer {
            parts.push(format!("at {p}"));
        }
        if let Some(o) = self.offset {
            parts.push(format!("byte {o}"));
        }
        if parts.is_empty() {
            f.write_str("file")
        } else {
            f.write_str(&parts.join(", "))
        }
    }
}

/// One finding: which rule, where, and what was expected.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Diagnostic {
    /// The rule violated.
    #[serde(with = "rule_serde")]
    pub rule: Rule,
    /// Severity (the rule's own, unless a tool downgrades it).
    pub severity: Severity,
    /// Where.
    pub location: Location,
    /// What was found and what was expected.
    pub message: String,
}

impl Diagnostic {
    /// A diagnostic at the rule's own severity.
    pub fn new(rule: Rule, location: Location, message: impl Into<String>) -> Diagnostic {
        Diagnostic {
            rule,
            severity: rule.severity(),
            location,
            message: message.into(),
        }
    }
}

impl std::fmt::Display for Diagnostic {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} ({}): {}",
            self.rule.id(),
            self.location,
            self.message
        )
    }
}

mod rule_serde {
    use super::Rule;
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(rule: &Rule, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(rule.id())
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Rule, D::Error> {
        let id = String::deserialize(d)?;
        Rule::from_id(&id).ok_or_else(|| serde::de::Error::custom(format!("unknown rule id {id}")))
    }
}
