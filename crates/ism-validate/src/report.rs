//! The validation report (spec/validation.md §6, schema `spec/schema/report.schema.json`).
//!
//! Modelled on the Khronos glTF validator's report: a versioned document with counts per severity
//! and a list of messages, each with a stable `code` (the rule id), a `severity`, a `message` and a
//! `location` whose `pointer` is a JSON pointer into the model's JSON encoding.

use std::collections::BTreeMap;

use ism_format::{Location, Rule, Severity};
use serde::{Deserialize, Serialize};

/// Version of the report format this crate writes.
pub const REPORT_VERSION: &str = "2.0";

/// The verdict of a whole file.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, PartialOrd, Ord)]
#[serde(rename_all = "lowercase")]
pub enum Verdict {
    /// No error: every stage certified.
    Valid,
    /// Some positivity questions were left undecided and nothing else is wrong.
    Undetermined,
    /// At least one error other than ISM-302.
    Invalid,
}

impl Verdict {
    /// The spelling used in the report.
    pub fn as_str(self) -> &'static str {
        match self {
            Verdict::Valid => "valid",
            Verdict::Undetermined => "undetermined",
            Verdict::Invalid => "invalid",
        }
    }
}

/// A point where `det DX ≤ 0`, proven by exact rational evaluation of the stored map's Jacobian at
/// exactly this point (spec/validation.md §4.4).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct Witness {
    /// Barycentric coordinates in the top simplex, in its stored vertex order; the point is
    /// `(w₁ … wₙ)` with `w₀ = 1 − (w₁ + … + wₙ)` exactly.
    pub point: Vec<f64>,
    /// `det DX` of the stored map there (reduced barycentric coordinates), rounded to a double of
    /// the proven sign: never above 0, and 0 exactly when the value is 0.
    pub det: f64,
    /// The certificate polynomial there (`det DX` for polynomial stages; `N = Q^{n+1} det DX` for
    /// rational ones), rounded the same way.
    pub polynomial_value: f64,
}

/// Bounds left when subdivision stopped (ISM-302).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct Bounds {
    /// Depth reached.
    pub depth: u32,
    /// Pieces examined.
    pub pieces: usize,
    /// Certified lower bound of the floating-point certificate polynomial over the pieces left
    /// undecided; absent when the floating-point path could not run (numbers beyond its range).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lower: Option<f64>,
    /// Smallest value found at a piece corner (an upper bound of the minimum); absent likewise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub upper: Option<f64>,
}

/// One diagnostic of the report.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct Message {
    /// The rule id, e.g. `ISM-301`.
    pub code: String,
    /// Severity.
    pub severity: Severity,
    /// What was found and what was expected.
    pub message: String,
    /// Where.
    pub location: Location,
    /// For ISM-301: where `det DX ≤ 0`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub witness: Option<Witness>,
    /// For ISM-302: how far subdivision went.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bounds: Option<Bounds>,
    /// For ISM-401..403: the measured quantity (angle in degrees, residual, det).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub value: Option<f64>,
}

impl Message {
    /// A message for `rule` at the rule's severity.
    pub fn new(rule: Rule, location: Location, message: impl Into<String>) -> Message {
        Message {
            code: rule.id().to_string(),
            severity: rule.severity(),
            message: message.into(),
            location,
            witness: None,
            bounds: None,
            value: None,
        }
    }

    /// The rule, when the code is one of the spec's.
    pub fn rule(&self) -> Option<Rule> {
        Rule::from_id(&self.code)
    }
}

impl From<ism_format::Diagnostic> for Message {
    fn from(d: ism_format::Diagnostic) -> Message {
        Message {
            code: d.rule.id().to_string(),
            severity: d.severity,
            message: d.message,
            location: d.location,
            witness: None,
            bounds: None,
            value: None,
        }
    }
}

/// The messages with their counts.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct Issues {
    /// Errors found (all of them, also those cut from `messages`).
    pub num_errors: usize,
    /// Warnings found.
    pub num_warnings: usize,
    /// Infos found.
    pub num_infos: usize,
    /// Whether `messages` was cut at the maximum number of messages.
    pub truncated: bool,
    /// Findings: errors first, then warnings and infos, each in file order.
    pub messages: Vec<Message>,
    /// Number of findings per rule id (all of them).
    pub counts: BTreeMap<String, usize>,
}

/// How a stage was certified (layer 3).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct StageReport {
    /// Stage index.
    pub index: usize,
    /// `bezier`, `rational` or `monotonic`.
    pub kind: String,
    /// Degree.
    pub degree: u32,
    /// `implicit` or `parametric` (a parametric stage is valid iff its stored map is).
    pub direction: String,
    /// `certified`, `invalid`, `undetermined`, or `skipped` (earlier layers failed).
    pub status: String,
    /// Why the positivity layer did not run, when skipped.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub skipped_because: Option<String>,
    /// Top simplices certified valid.
    pub valid: usize,
    /// Top simplices with a witness of `det ≤ 0`.
    pub invalid: usize,
    /// Top simplices left undecided.
    pub undetermined: usize,
    /// Certified simplices per method: a theorem's name, `identity`, or `subdivision`.
    pub certificates: BTreeMap<String, usize>,
    /// Deepest subdivision used by a certificate.
    pub max_depth: u32,
    /// Smallest certified lower bound of the certificate polynomial over subdivision certificates.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub min_lower_bound: Option<f64>,
    /// Range of the Jacobian-polynomial values at the simplex vertices (exact coefficients), over
    /// the simplices examined numerically, when `--quality` asked for it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub det_range: Option<[f64; 2]>,
}

/// Size of the model validated.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct ModelInfo {
    /// Dimension.
    pub dimension: u8,
    /// Vertices.
    pub vertices: usize,
    /// Top simplices.
    pub simplices: usize,
    /// Stages.
    pub stages: usize,
}

/// The file, when the report comes from one.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct FileInfo {
    /// Path as given.
    pub path: String,
    /// Encoding found by sniffing.
    pub encoding: String,
    /// Size in bytes.
    pub bytes: u64,
}

/// Wall-clock time per layer, in seconds.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct Timing {
    /// Layer 1.
    pub structure: f64,
    /// Layer 2.
    pub invariance: f64,
    /// Layer 3.
    pub positivity: f64,
    /// Layer 4 (`--quality`).
    pub quality: f64,
}

/// The whole report.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct Report {
    /// [`REPORT_VERSION`].
    pub report_version: String,
    /// `ism-validate <crate version>`.
    pub validator: String,
    /// The file, when validated from one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file: Option<FileInfo>,
    /// The model's size.
    pub model: ModelInfo,
    /// The verdict.
    pub verdict: Verdict,
    /// Findings.
    pub issues: Issues,
    /// Layer 3 per stage.
    pub stages: Vec<StageReport>,
    /// Floating-point pieces allowed per element (the exact path gets a sixteenth as many).
    pub piece_budget: usize,
    /// Time per layer.
    pub timing: Timing,
    /// The quality layer's statistics as data, for programs (the messages are rendered from them;
    /// not part of the JSON report, whose schema is fixed).
    #[serde(skip)]
    pub quality: QualityStats,
}

/// Statistics of the quality layer (layer 4), as numbers.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct QualityStats {
    /// ISM-401 over the interior facets the shape crosses; `None` when not computed (quality off,
    /// or some stage not certified so that `X⁻¹` may not exist).
    pub normal_jumps: Option<NormalJumps>,
}

/// The jump of the shape's normal across the interior facets it crosses (ISM-401).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NormalJumps {
    /// Interior facets crossed by the shape (where the jump was measured).
    pub facets: usize,
    /// Largest jump, degrees.
    pub max_degrees: f64,
    /// Mean jump, degrees.
    pub mean_degrees: f64,
}

impl Report {
    /// `(code, location)` of every message, for tests and scripts.
    pub fn pairs(&self) -> Vec<(String, Location)> {
        self.issues
            .messages
            .iter()
            .map(|m| (m.code.clone(), m.location.clone()))
            .collect()
    }

    /// Whether the model is valid (no error).
    pub fn is_valid(&self) -> bool {
        self.verdict == Verdict::Valid
    }
}

/// Collects messages up to a maximum while counting them all.
#[derive(Debug)]
pub(crate) struct Collector {
    pub messages: Vec<Message>,
    pub counts: BTreeMap<String, usize>,
    pub total: [usize; 3],
    pub max: usize,
    pub truncated: bool,
}

impl Collector {
    pub fn new(max: usize) -> Collector {
        Collector {
            messages: Vec::new(),
            counts: BTreeMap::new(),
            total: [0; 3],
            max,
            truncated: false,
        }
    }

    pub fn push(&mut self, m: Message) {
        *self.counts.entry(m.code.clone()).or_default() += 1;
        self.total[m.severity as usize] += 1;
        if self.messages.len() < self.max {
            self.messages.push(m);
        } else {
            self.truncated = true;
        }
    }

    pub fn finish(mut self) -> Issues {
        // Errors first, then warnings, then infos; stable so file order is kept within each.
        self.messages.sort_by_key(|m| std::cmp::Reverse(m.severity));
        Issues {
            num_errors: self.total[Severity::Error as usize],
            num_warnings: self.total[Severity::Warning as usize],
            num_infos: self.total[Severity::Info as usize],
            truncated: self.truncated,
            messages: self.messages,
            counts: self.counts,
        }
    }
}
