//! Layer 3: positivity of `det DX` per stage and top simplex (ISM-301, ISM-302; spec/validation.md
//! §4). Theorems first; otherwise the certified Bernstein coefficients of [`crate::certify`].

use std::collections::BTreeMap;

use ism_format::progress::{Cancelled, Progress};
use ism_format::{multi_index, IndexedModel, Location, Model, Rule, StageKind};
use rayon::prelude::*;

use crate::certify::{Budget, Certificate, DetKernel};
use crate::net::{SimplexRecords, StageIndex};
use crate::report::{Bounds, Message, StageReport, Witness};
use crate::theorem;

/// Largest convolution table (products of pairs of coefficients) the numeric certificate builds:
/// 8 M entries is 48 MB and a few seconds of table building; beyond it (rational stages of degree
/// ≥ 13 in 3D) elements that need numbers are reported undetermined.
pub const MAX_CONVOLUTION_ENTRIES: usize = 8 << 20;

/// How one element was decided.
#[derive(Clone, Debug, PartialEq)]
pub enum Outcome {
    /// Certified: the method's name and, for subdivision, depth and lower bound.
    Valid {
        /// A theorem's name, [`theorem::IDENTITY`] or [`theorem::SUBDIVISION`].
        method: &'static str,
        /// Subdivision depth (0 for theorems).
        depth: u32,
        /// Certified lower bound of the certificate polynomial (subdivision only).
        lower_bound: Option<f64>,
    },
    /// A point where `det ≤ 0`.
    Invalid(Witness),
    /// Undecided within the piece budget.
    Undetermined(Bounds),
}

/// Settings of the positivity layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PositivityOptions {
    /// Work allowed per element.
    pub budget: Budget,
    /// Use the theorems (turn off to force numeric certification, e.g. for benchmarks and tests).
    pub theorems: bool,
}

/// What the stage as a whole is, before looking at simplices.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum StageClass {
    /// Every simplex touched by a record is covered by this theorem.
    Theorem(&'static str),
    /// Decide per simplex.
    PerSimplex,
}

fn classify_stage(model: &Model, index: &StageIndex<'_>, theorems: bool) -> StageClass {
    let stage = index.stage();
    let n = model.dim();
    let d = stage.degree;
    if !theorems {
        return StageClass::PerSimplex;
    }
    // The theorems assume adjusted nets; a record that is adjusted only within rounding (an edge
    // point at its vertex in reduced coordinates) sends its simplices to the numeric certificate.
    // Per record, on every core.
    let records = || (0..stage.faces.len()).into_par_iter();
    if stage.kind != StageKind::Monotonic && !records().all(|r| index.is_adjusted(r)) {
        return StageClass::PerSimplex;
    }
    match stage.kind {
        StageKind::Monotonic => StageClass::Theorem(theorem::MONOTONIC),
        StageKind::Bezier if d == 2 => StageClass::Theorem(theorem::PROP_5_6),
        StageKind::Rational if d == 2 => StageClass::Theorem(theorem::THM_6_5),
        StageKind::Bezier => {
            // A stratum G_j: degree j + 1 and every moving record on a j-face (its single centre
            // point). G_2 in 3D is Prop. 5.9; G_n is solitary in every simplex (decided per simplex).
            let j = d as usize - 1;
            let stratum =
                records().all(|r| index.is_trivial(r) || stage.faces.face(r).len() == j + 1);
            if stratum && j == 2 && n == 3 {
                StageClass::Theorem(theorem::PROP_5_9)
            } else if stratum && j == n {
                // The stratum G_n: every moving record is a top simplex's own centre point, so a
                // simplex carries at most one and Prop. 5.7 covers each — decided once for the
                // stage, with no face lookup per simplex (simplices without a record are the
                // identity, which the theorem covers too).
                StageClass::Theorem(theorem::PROP_5_7)
            } else {
                StageClass::PerSimplex
            }
        }
        StageKind::Rational => {
            if records().all(|r| index.is_fixed(r)) {
                StageClass::Theorem(theorem::THM_6_4)
            } else {
                StageClass::PerSimplex
            }
        }
    }
}

/// Result of the positivity layer on one stage.
#[derive(Clone, Debug)]
pub struct StageOutcome {
    /// Per-stage summary.
    pub report: StageReport,
    /// ISM-301 / ISM-302 messages, in simplex order.
    pub messages: Vec<Message>,
}

#[derive(Default)]
struct Tally {
    valid: usize,
    invalid: usize,
    undetermined: usize,
    certificates: BTreeMap<&'static str, usize>,
    max_depth: u32,
    min_lower: Option<f64>,
    bad: Vec<(usize, Outcome)>,
}

impl Tally {
    fn add(&mut self, s: usize, outcome: Outcome) {
        match &outcome {
            Outcome::Valid {
                method,
                depth,
                lower_bound,
            } => {
                self.valid += 1;
                *self.certificates.entry(method).or_default() += 1;
                self.max_depth = self.max_depth.max(*depth);
                if let Some(l) = lower_bound {
                    self.min_lower = Some(self.min_lower.map_or(*l, |m: f64| m.min(*l)));
                }
            }
            Outcome::Invalid(_) => self.invalid += 1,
            Outcome::Undetermined(_) => self.undetermined += 1,
        }
        if !matches!(outcome, Outcome::Valid { .. }) {
            self.bad.push((s, outcome));
        }
    }

    fn merge(mut self, other: Tally) -> Tally {
        self.valid += other.valid;
        self.invalid += other.invalid;
        self.undetermined += other.undetermined;
        for (k, v) in other.certificates {
            *self.certificates.entry(k).or_default() += v;
        }
        self.max_depth = self.max_depth.max(other.max_depth);
        self.min_lower = match (self.min_lower, other.min_lower) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
        self.bad.extend(other.bad);
        self
    }
}

/// Checks stage `k` of a model that passed layers 1 and 2 for this stage.
pub fn check_stage(indexed: &IndexedModel, k: usize, options: PositivityOptions) -> StageOutcome {
    match check_stage_with_progress(indexed, k, options, &Progress::none()) {
        Ok(outcome) => outcome,
        Err(Cancelled) => unreachable!("Progress::none() is never cancelled"),
    }
}

/// [`check_stage`] reporting [`crate::POSITIVITY_PHASE`] in simplices; stops (within one simplex
/// per worker thread) when `progress` is cancelled.
///
/// # Errors
/// [`Cancelled`] when `progress` was cancelled.
pub fn check_stage_with_progress(
    indexed: &IndexedModel,
    k: usize,
    options: PositivityOptions,
    progress: &Progress,
) -> Result<StageOutcome, Cancelled> {
    let model: &Model = indexed;
    let stage = &model.stages[k];
    let n = model.dim();
    let index = StageIndex::new(indexed, k);
    let class = classify_stage(model, &index, options.theorems);
    let rational = stage.kind == StageKind::Rational;
    let kernel = if matches!(class, StageClass::PerSimplex) && stage.kind != StageKind::Monotonic {
        // The simplices look their records up: build the stage's tables (and a lazily indexed
        // model's face tables) here, not on first use inside the parallel loop below (a rayon
        // worker waiting for a cell's initialisation could run a job that waits for it again).
        let _ = indexed.stage(k);
        kernel_if_affordable(n, stage.degree, rational)
    } else {
        None
    };
    let decide = |s: usize| -> Outcome {
        // A stage-wide theorem covers every simplex, touched or not: no lookup needed.
        if let StageClass::Theorem(name) = class {
            return Outcome::Valid {
                method: name,
                depth: 0,
                lower_bound: None,
            };
        }
        if stage.kind == StageKind::Monotonic {
            // Only the §4 theorem certifies monotonic maps (there is no numeric kernel for them,
            // and they have no face records to look up): without it, undetermined. (Found by the
            // `validate_generated` fuzz target: `--no-theorems` on a monotonic stage indexed the
            // empty face-record table and panicked.)
            return Outcome::Undetermined(Bounds {
                depth: 0,
                pieces: 0,
                lower: None,
                upper: None,
            });
        }
        let records = index.records(s);
        let moving: Vec<(usize, usize)> = records
            .iter()
            .filter(|&(_, r)| !index.is_trivial(r))
            .collect();
        if stage.kind != StageKind::Monotonic && moving.is_empty() {
            return Outcome::Valid {
                method: theorem::IDENTITY,
                depth: 0,
                lower_bound: None,
            };
        }
        let adjusted = records.iter().all(|(_, r)| index.is_adjusted(r));
        if options.theorems && adjusted {
            if let Some(name) =
                simplex_theorem(&index, &records, &moving, stage.kind, stage.degree, n)
            {
                return Outcome::Valid {
                    method: name,
                    depth: 0,
                    lower_bound: None,
                };
            }
        }
        let net = index.dense_net(s, &records);
        if options.theorems
            && adjusted
            && rational
            && n == 2
            && theorem::sottile_zhu_compatible(&net)
        {
            return Outcome::Valid {
                method: theorem::SOTTILE_ZHU,
                depth: 0,
                lower_bound: None,
            };
        }
        let Some(kernel) = &kernel else {
            return Outcome::Undetermined(Bounds {
                depth: 0,
                pieces: 0,
                lower: None,
                upper: None,
            });
        };
        outcome_of(kernel.certify(&net, options.budget))
    };
    let counter = progress.phase(crate::POSITIVITY_PHASE, model.num_simplices() as u64);
    let tally = if let StageClass::Theorem(name) = class {
        // A stage-wide theorem covers every simplex: the stage costs its O(records)
        // classification above and nothing per simplex.
        let all = model.num_simplices();
        counter.add(all as u64);
        Tally {
            valid: all,
            certificates: BTreeMap::from([(name, all)]),
            ..Tally::default()
        }
    } else {
        (0..model.num_simplices())
            .into_par_iter()
            .fold(Tally::default, |mut t, s| {
                // Once cancelled, the remaining simplices are skipped (the tally is then dropped).
                if !counter.is_cancelled() {
                    t.add(s, decide(s));
                    counter.add(1);
                }
                t
            })
            .reduce(Tally::default, Tally::merge)
    };
    progress.check()?;
    let mut bad = tally.bad;
    bad.sort_by_key(|(s, _)| *s);
    let m = n + 1;
    let messages = bad
        .into_iter()
        .map(|(s, outcome)| {
            let loc = Location {
                stage: Some(k),
                simplex: Some(s),
                ..Location::pointer(format!("/simplices/{}", s * m))
            };
            match outcome {
                Outcome::Invalid(w) => {
                    let text = format!(
                        "det DX = {:.6e} ≤ 0 (exact) at barycentric point {:?} of simplex {s} (stage {k}); the stage folds there",
                        w.det, w.point
                    );
                    Message { witness: Some(w), ..Message::new(Rule::JacobianPositive, loc, text) }
                }
                Outcome::Undetermined(b) => {
                    let text = if stage.kind == StageKind::Monotonic {
                        // Not a question of degree or budget: a monotonic stage has no numeric
                        // certificate at all, only the theorem (which --no-theorems turns off).
                        format!(
                            "monotonic stage: only the theorem \"{}\" certifies it, and theorems are off (--no-theorems); positivity not decided",
                            theorem::MONOTONIC
                        )
                    } else if b.pieces == 0 {
                        format!("degree {} is beyond this validator's numeric certificate; positivity not decided", stage.degree)
                    } else {
                        format!(
                            "positivity of det DX not decided within the piece budget ({} pieces, depth {}){}",
                            b.pieces,
                            b.depth,
                            match (b.lower, b.upper) {
                                (Some(l), Some(u)) => format!(": lower bound {l:.3e}, smallest value {u:.3e}"),
                                _ => String::new(),
                            }
                        )
                    };
                    Message { bounds: Some(b), ..Message::new(Rule::Undetermined, loc, text) }
                }
                Outcome::Valid { .. } => unreachable!("only failures are kept"),
            }
        })
        .collect();
    let status = if tally.invalid > 0 {
        "invalid"
    } else if tally.undetermined > 0 {
        "undetermined"
    } else {
        "certified"
    };
    let report = StageReport {
        index: k,
        kind: stage.kind.as_str().to_string(),
        degree: stage.degree,
        direction: direction_name(stage.direction).to_string(),
        status: status.to_string(),
        skipped_because: None,
        valid: tally.valid,
        invalid: tally.invalid,
        undetermined: tally.undetermined,
        certificates: tally
            .certificates
            .into_iter()
            .map(|(k, v)| (k.to_string(), v))
            .collect(),
        max_depth: tally.max_depth,
        min_lower_bound: tally.min_lower,
        det_range: None,
    };
    Ok(StageOutcome { report, messages })
}

/// `implicit` or `parametric`.
pub fn direction_name(d: ism_format::Direction) -> &'static str {
    match d {
        ism_format::Direction::Implicit => "implicit",
        ism_format::Direction::Parametric => "parametric",
    }
}

/// The kernel for `(n, d, rational)` unless its tables would exceed [`MAX_CONVOLUTION_ENTRIES`].
pub fn kernel_if_affordable(n: usize, degree: u32, rational: bool) -> Option<DetKernel> {
    let m = n + 1;
    let size = if rational { n + 1 } else { n };
    let entry = degree - 1;
    let det_degree = if rational {
        (n as u32 + 1) * degree - n as u32
    } else {
        n as u32 * (degree - 1)
    };
    let first = if rational { degree } else { entry };
    // The largest table multiplies the first column by the minor of the others.
    let minor_degree = det_degree - first;
    let entries = multi_index::count(m, first) * multi_index::count(m, minor_degree);
    // u16 indices in the tables.
    if entries > MAX_CONVOLUTION_ENTRIES
        || multi_index::count(m, det_degree) > usize::from(u16::MAX)
        || size == 0
    {
        return None;
    }
    Some(DetKernel::new(n, degree, rational))
}

fn simplex_theorem(
    index: &StageIndex<'_>,
    records: &SimplexRecords,
    moving: &[(usize, usize)],
    kind: StageKind,
    d: u32,
    n: usize,
) -> Option<&'static str> {
    let _ = records;
    match kind {
        StageKind::Bezier => {
            // One moving record whose face has exactly d vertices owns one point, the centre index
            // J ∈ {0,1}^{n+1} of that face: the solitary case (this also covers the strata G_n).
            if moving.len() == 1 && (moving[0].0 as u32).count_ones() == d && d as usize <= n + 1 {
                Some(theorem::PROP_5_7)
            } else {
                None
            }
        }
        StageKind::Rational => {
            if moving.iter().all(|&(_, r)| index.is_fixed(r)) {
                Some(theorem::THM_6_4)
            } else {
                None
            }
        }
        StageKind::Monotonic => Some(theorem::MONOTONIC),
    }
}

/// Turns an element's certificate into an outcome.
pub fn outcome_of(certificate: Certificate) -> Outcome {
    match certificate {
        Certificate::Positive {
            exact,
            depth,
            lower_bound,
            ..
        } => Outcome::Valid {
            method: if exact {
                theorem::EXACT_SUBDIVISION
            } else {
                theorem::SUBDIVISION
            },
            depth,
            lower_bound,
        },
        Certificate::NonPositive(w) => Outcome::Invalid(Witness {
            point: w.point,
            det: w.det,
            polynomial_value: w.polynomial_value,
        }),
        Certificate::Undetermined {
            depth,
            pieces,
            lower_bound,
            upper_bound,
        } => Outcome::Undetermined(Bounds {
            depth,
            pieces,
            lower: lower_bound.is_finite().then_some(lower_bound),
            upper: upper_bound.is_finite().then_some(upper_bound),
        }),
    }
}
