//! Rational C¹ smoothing: fit the weights of a rational stage with fixed control points so that the
//! shape is C¹ across the interior facets it crosses (Mello & Velho 2009, §8, Thm. 8.1 and eq. (6)).
//!
//! With `X|_σ = Σ q_I b_I B_I / Σ q_I B_I`, fixed control points `b_I = I/d` and `F = f̂ ∘ X`,
//! `F − c = u/v` with `u = Σ q_I (f̂(b_I) − c) B_I` and `v = Σ q_I B_I`; on `O` (`u = 0`) the gradient
//! is `∇u / v`, and `v` is continuous across a facet `δ` (weights on `δ` are stored once). So the
//! normal of `O` is continuous on `δ` when `u` is C¹ there, which are the linear conditions of
//! eq. (6): for each `|J| = d − 1` on `δ`,
//! `r_J = q_{J+e₀} â_{J+e₀} − Σᵢ wᵢ q′_{J+eᵢ} â′_{J+eᵢ} = 0`, with `â_I = Σₖ (f(vₖ) − c) Iₖ/d` and `w`
//! the barycentric coordinates of `σ`'s vertex `p₀` opposite `δ` in `σ′`. This is the residual of
//! `ism validate --quality` rule ISM-402 (spec/validation.md §5), computed here independently.
//!
//! [`smooth_rational`] minimizes, over the log-weights `β` (`q = exp β`, so weights stay positive)
//! of every multi-index that a crossed facet's conditions touch,
//!
//! `E(β) = Σ_δ Σ_J (r_J(q̃) / max|f − c|_δ)² + α Σ_k (β_k − β̄)²`, `q̃ = exp(β − β̄)`,
//!
//! where `β̄` is the mean log-weight of the connected group of unknowns `k` belongs to (unknowns are
//! connected when a facet condition couples them). Why this form: `r` is homogeneous of degree 1
//! in `q`, so a plain `Σ r²` is minimized by `q → 0`; dividing by the geometric mean `exp(β̄)` makes
//! the C¹ term scale-free like ISM-402's relative residual (which divides by the weights), so a
//! global shrink gains nothing, and the penalty on `β − β̄` picks, among the (usually many) exact
//! or near solutions, the one with the least spread of weights — near the input's map, and far
//! from the numerically delicate corners of the weight range. `α = 0` gives a pure least-squares
//! C¹ fit (the spread is then only limited by [`MAX_LOG_WEIGHT`]).
//!
//! The minimizer is a global sparse Levenberg–Marquardt on `β` with steps kept in the gauge
//! subspace (zero mean per group) and clamped to `|β| ≤` [`MAX_LOG_WEIGHT`]; a step is accepted
//! only if it lowers `E`, so the objective never increases. Every positive weight with fixed
//! control points gives a diffeomorphism (Mello & Velho 2009, Thm. 6.4), so the output is valid by construction
//! and the validator certifies it by that theorem.
//!
//! Input: a model without stages (a linear isocomplex), or whose only stage is an implicit rational
//! stage with every control point fixed — the setting where eq. (6) is exact. Anything else is a
//! [`C1Error`] saying why.
//!
//! ```
//! use ism_fit::c1::{smooth_rational, C1Options};
//!
//! let text = include_str!("../../../spec/examples/circle-linear.ism.json");
//! let model = ism_format::io::from_slice(text.as_bytes()).unwrap().model;
//! let smoothed = smooth_rational(&model, &C1Options::default())?;
//! let r = &smoothed.report;
//! assert!(r.residual_after.max < r.residual_before.max);
//! assert!(r.objective_after <= r.objective_before);
//! assert_eq!(smoothed.model.stages.len(), 1);
//! # Ok::<(), ism_fit::c1::C1Error>(())
//! ```

use ism_format::progress::{Cancelled, Progress};
use std::collections::HashMap;
use std::time::Instant;

use ism_format::indexed::shared_facets;
use ism_format::model::{Direction, FaceRecord, Model, Stage, StageKind};
use ism_format::multi_index;
use ism_geom::{linalg, Mat, MAX_VARS};
use rayon::prelude::*;

use crate::smooth::{normal_jumps, JumpStats};

/// Bound on `|ln q|` of every fitted weight: `q ∈ [e⁻⁴, e⁴] ≈ [0.018, 55]`. Theorem 6.4 holds for
/// any positive weights, so the bound is numerical: a weight ratio up to `e⁸ ≈ 3000` keeps the
/// denominator `Σ q_I B_I` of every simplex within a factor 3000 of its numerator's scale, so the
/// validator's sampled `det DX` (ISM-403) and the Newton inversion of `X` (ISM-401 samples, the
/// sampler) stay well conditioned, and a C¹ fit that would need more spread is a sign that the
/// positive solution does not exist (the paper's open question), not one to chase. An input
/// weight outside the range that the fit touches starts (and, if not moved, ends) at the bound.
pub const MAX_LOG_WEIGHT: f64 = 4.0;

/// A stored control point counts as fixed when it is within this of `J/d` in every face-local
/// coordinate: writers store `J/d` as the nearest double, and a text round trip is exact, so
/// anything above a few ulps is a moved point.
pub const FIXED_POINT_TOLERANCE: f64 = 1e-12;

/// Largest stage degree accepted (the format's limit, spec §5).
pub const MAX_DEGREE: u32 = 16;

/// Conjugate-gradient iterations per Levenberg–Marquardt step; the damped normal matrix is well
/// conditioned after the Jacobi preconditioner, and an inexact step is still checked by the
/// acceptance test.
const CG_MAX_ITERATIONS: usize = 100;

/// Relative residual at which conjugate gradients stop: well below the step's own accuracy need
/// (the acceptance test decides), well above rounding.
const CG_TOLERANCE: f64 = 1e-4;

/// Levenberg–Marquardt stops when an accepted step lowers `E` by less than this fraction of it: on
/// the circle and sphere runs the ISM-402 and ISM-401 figures then differ from those at `1e-10`
/// only in their fourth digit, in a third of the steps.
const STALL_FRACTION: f64 = 1e-6;

/// Errors of [`smooth_rational`], saying where and what was expected.
#[derive(Debug, thiserror::Error)]
pub enum C1Error {
    /// The caller cancelled the call through its [`Progress`].
    #[error(transparent)]
    Cancelled(#[from] Cancelled),
    /// The model has structural errors (the reader's diagnostics, each with its rule and place).
    #[error("model: {}", crate::join_diagnostics(.0))]
    Structure(Vec<ism_format::Diagnostic>),
    /// The dimension is not 2 or 3.
    #[error("dimension {0}: rational C¹ smoothing needs 2 or 3")]
    Dimension(u8),
    /// The stages are not the setting of Thm. 8.1.
    #[error("stage {stage}: {message}")]
    Stage {
        /// Stage index.
        stage: usize,
        /// What is wrong and what was expected.
        message: String,
    },
    /// More than one stage: Thm. 8.1 concerns a single rational map.
    #[error(
        "the model has {0} stages; rational C¹ smoothing needs no stage or a single implicit \
         rational stage with fixed control points (eq. (6) of Mello & Velho 2009, Thm. 8.1, is \
         exact only there)"
    )]
    StageCount(usize),
    /// A control point of the input's rational stage is moved.
    #[error(
        "stage 0, face {face:?}, owned index {index}: control point {found:?} is moved (expected the \
         fixed point {expected:?}; eq. (6) is exact only with fixed control points)"
    )]
    MovedPoint {
        /// The face record's vertex ids.
        face: Vec<u32>,
        /// Position of the multi-index among the face's owned ones.
        index: usize,
        /// The stored face-local coordinates.
        found: Vec<f64>,
        /// `J/d`.
        expected: Vec<f64>,
    },
    /// Inconsistent options.
    #[error("options: {0}")]
    Options(String),
}

/// Options of [`smooth_rational`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct C1Options {
    /// Degree of the rational stage; `None`: the input stage's, or `n` (the paper's) for a linear
    /// model. At least `n`.
    pub degree: Option<u32>,
    /// Weight of the spread penalty `Σ (β − β̄)²`.
    pub alpha: f64,
    /// Levenberg–Marquardt iterations (each one sparse solve).
    pub iterations: usize,
}

impl Default for C1Options {
    fn default() -> Self {
        C1Options {
            degree: None,
            alpha: 1e-4,
            iterations: 100,
        }
    }
}

impl C1Report {
    /// The report of `ism smooth --rational --json`, with the output's validation `verdict`.
    pub fn to_json(&self, verdict: &str) -> serde_json::Value {
        let res = |s: ResidualStats| serde_json::json!({"facets": s.facets, "max": s.max, "mean": s.mean});
        serde_json::json!({
            "mode": "rational",
            "degree": self.degree,
            "alpha": self.alpha,
            "residualBefore": res(self.residual_before),
            "residualAfter": res(self.residual_after),
            "before": crate::smooth::jump_json(self.jumps_before),
            "after": crate::smooth::jump_json(self.jumps_after),
            "objectiveBefore": self.objective_before,
            "objectiveAfter": self.objective_after,
            "steps": self.steps,
            "weights": self.weights,
            "groups": self.groups,
            "conditions": self.conditions,
            "weightRange": self.weight_range,
            "records": self.records,
            "verdict": verdict,
            "seconds": self.seconds,
            "fitSeconds": self.fit_seconds,
        })
    }
}

/// ISM-402 relative residual over the interior facets the shape crosses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ResidualStats {
    /// Crossed interior facets.
    pub facets: usize,
    /// Largest relative residual.
    pub max: f64,
    /// Mean relative residual.
    pub mean: f64,
}

/// One crossed interior facet's ISM-402 residual.
#[derive(Clone, Debug, PartialEq)]
pub struct FacetResidual {
    /// The facet's sorted vertex ids.
    pub face: Vec<u32>,
    /// The two simplices, lower index first (the validator's `σ`, `σ′`).
    pub simplices: [usize; 2],
    /// `sqrt(Σ_J r_J²)`.
    pub absolute: f64,
    /// `sqrt(Σ_J r_J²) / (max|f − c| · max_J q_{J+e₀})`, ISM-402's `value`.
    pub relative: f64,
}

/// Summary of [`smooth_rational`].
#[derive(Clone, Debug, PartialEq)]
pub struct C1Report {
    /// Degree of the output stage.
    pub degree: u32,
    /// The `alpha` used.
    pub alpha: f64,
    /// ISM-402 of the input (all weights 1 for a linear model).
    pub residual_before: ResidualStats,
    /// ISM-402 of the output.
    pub residual_after: ResidualStats,
    /// ISM-401 of the input (`None` when the validator does not compute it).
    pub jumps_before: Option<JumpStats>,
    /// ISM-401 of the output.
    pub jumps_after: Option<JumpStats>,
    /// `E` of the input.
    pub objective_before: f64,
    /// `E` of the output.
    pub objective_after: f64,
    /// `E` after each accepted step.
    pub steps: Vec<f64>,
    /// Weights optimized.
    pub weights: usize,
    /// Connected groups of them (one gauge each).
    pub groups: usize,
    /// Conditions `r_J` (rows of the least-squares system).
    pub conditions: usize,
    /// Smallest and largest output weight.
    pub weight_range: [f64; 2],
    /// Face records written.
    pub records: usize,
    /// Wall time in seconds, all of it.
    pub seconds: f64,
    /// Wall time of the fit alone (setting up and solving), without the ISM-401 measurements by
    /// the validator.
    pub fit_seconds: f64,
}

/// The result of [`smooth_rational`].
#[derive(Clone, Debug)]
pub struct C1Smoothed {
    /// The model with its one rational stage.
    pub model: Model,
    /// The summary.
    pub report: C1Report,
}

/// A weight: the face (sorted ids) that owns its multi-index and the rank among the owned ones.
type WeightKey = (Vec<u32>, usize);

/// The input stage's weights by face record.
type InputWeights = HashMap<Vec<u32>, Vec<f64>>;

/// An interior facet: sorted ids and `[(simplex, opposite local position); 2]`.
type FacetSides = ism_format::indexed::SharedFacet;

/// The owner of local multi-index `index` of a simplex with vertex ids `ids`.
fn owner(ids: &[u32], index: &[u32]) -> WeightKey {
    let mut face: Vec<(u32, u32)> = ids
        .iter()
        .zip(index)
        .filter(|(_, &e)| e > 0)
        .map(|(&v, &e)| (v, e - 1))
        .collect();
    face.sort_unstable();
    let reduced: Vec<u32> = face.iter().map(|x| x.1).collect();
    (
        face.iter().map(|x| x.0).collect(),
        multi_index::rank(&reduced),
    )
}

/// One condition `r_J`, already divided by `max|f − c|` of its facet: `Σ coef · q[var]`.
struct Row {
    terms: Vec<(usize, f64)>,
}

/// A crossed interior facet.
struct Facet {
    face: Vec<u32>,
    simplices: [usize; 2],
    fmax: f64,
    rows: std::ops::Range<usize>,
    /// The unknowns `q_{J+e₀}` (ISM-402's normalisation).
    scale: Vec<usize>,
}

/// The least-squares problem: unknowns, conditions, groups.
struct Problem {
    keys: Vec<WeightKey>,
    rows: Vec<Row>,
    /// The rows by unknown (`Sᵀ`), so that both products run in parallel without scatter.
    columns: Vec<Vec<(usize, f64)>>,
    facets: Vec<Facet>,
    group: Vec<usize>,
    group_size: Vec<usize>,
}

/// Checks the input (see the module doc) and returns the degree and the input's weights by face.
fn check_input(model: &Model, options: &C1Options) -> Result<(u32, InputWeights), C1Error> {
    if !(options.alpha >= 0.0 && options.alpha.is_finite()) {
        return Err(C1Error::Options(format!(
            "alpha {} must be a finite number ≥ 0",
            options.alpha
        )));
    }
    if model.dimension != 2 && model.dimension != 3 {
        return Err(C1Error::Dimension(model.dimension));
    }
    let errors = crate::structural_errors(model);
    if !errors.is_empty() {
        return Err(C1Error::Structure(errors));
    }
    let n = model.dim() as u32;
    let mut weights = HashMap::new();
    let degree = match model.stages.as_slice() {
        [] => options.degree.unwrap_or(n),
        [stage] => {
            if stage.kind != StageKind::Rational {
                return Err(C1Error::Stage {
                    stage: 0,
                    message: format!(
                        "a {} stage; expected an implicit rational stage with fixed control \
                         points (or no stage): eq. (6) is exact only there",
                        stage.kind.as_str()
                    ),
                });
            }
            if stage.direction != Direction::Implicit {
                return Err(C1Error::Stage {
                    stage: 0,
                    message: "a parametric rational stage; expected the implicit direction \
                              (eq. (6) is a condition on X, not on X⁻¹)"
                        .to_string(),
                });
            }
            if let Some(d) = options.degree {
                if d != stage.degree {
                    return Err(C1Error::Options(format!(
                        "degree {d} asked, but the input's rational stage has degree {}",
                        stage.degree
                    )));
                }
            }
            let d = stage.degree;
            for record in &stage.faces {
                let k1 = record.face.len();
                let owned = multi_index::owned(k1, d);
                for (index, (j, point)) in
                    owned.chunks(k1).zip(record.points.chunks(k1)).enumerate()
                {
                    let expected: Vec<f64> =
                        j.iter().map(|&e| f64::from(e) / f64::from(d)).collect();
                    if point
                        .iter()
                        .zip(&expected)
                        .any(|(a, b)| (a - b).abs() > FIXED_POINT_TOLERANCE)
                    {
                        return Err(C1Error::MovedPoint {
                            face: record.face.to_vec(),
                            index,
                            found: point.to_vec(),
                            expected,
                        });
                    }
                }
                if let Some(j) = record.weights.iter().position(|&q| q <= 0.0) {
                    return Err(C1Error::Stage {
                        stage: 0,
                        message: format!(
                            "face {:?}: weight {j} is {}; expected a positive weight",
                            record.face, record.weights[j]
                        ),
                    });
                }
                weights.insert(record.face.to_vec(), record.weights.to_vec());
            }
            d
        }
        stages => return Err(C1Error::StageCount(stages.len())),
    };
    if degree < n || degree > MAX_DEGREE {
        return Err(C1Error::Options(format!(
            "degree {degree} must be between the dimension {n} and {MAX_DEGREE}"
        )));
    }
    Ok((degree, weights))
}

/// Barycentric coordinates of `p` in the simplex with the given vertices (solved directly, not
/// through the kernel's cached inverse, so that the check against ISM-402 is independent).
fn barycentric(model: &Model, ids: &[u32], p: &[f64]) -> Option<[f64; MAX_VARS]> {
    let n = model.dim();
    let mut a: Mat = [[0.0; MAX_VARS]; MAX_VARS];
    let mut b = [0.0; MAX_VARS];
    for (c, &v) in ids.iter().enumerate() {
        let x = model.vertex(v as usize);
        for r in 0..n {
            a[r][c] = x[r];
        }
        a[n][c] = 1.0;
    }
    b[..n].copy_from_slice(&p[..n]);
    b[n] = 1.0;
    linalg::solve(n + 1, &a, &b)
}

/// Interior facets crossed by the shape: `(sorted ids, [(simplex, opposite position); 2])` with
/// the lower simplex index first, in sorted order of the ids.
fn crossed_facets(model: &Model) -> Vec<FacetSides> {
    let m = model.dim() + 1;
    let mut out = shared_facets(m, &model.simplices);
    out.retain(|(key, _)| {
        let f = |v: &u32| model.values[*v as usize] - model.level;
        key.iter().any(|v| f(v) < 0.0) && key.iter().any(|v| f(v) > 0.0)
    });
    out
}

impl Problem {
    fn new(model: &Model, d: u32) -> Problem {
        let m = model.dim() + 1;
        let level = model.level;
        let mut index: HashMap<WeightKey, usize> = HashMap::new();
        let mut keys: Vec<WeightKey> = Vec::new();
        let mut var = |key: WeightKey| -> usize {
            *index.entry(key.clone()).or_insert_with(|| {
                keys.push(key);
                keys.len() - 1
            })
        };
        let mut rows = Vec::new();
        let mut facets = Vec::new();
        let lattice = multi_index::all(m, d - 1);
        for (face, [(s1, a1), (s2, _)]) in crossed_facets(model) {
            let ids1 = model.simplex(s1);
            let ids2 = model.simplex(s2);
            let f1: Vec<f64> = ids1
                .iter()
                .map(|&v| model.values[v as usize] - level)
                .collect();
            let f2: Vec<f64> = ids2
                .iter()
                .map(|&v| model.values[v as usize] - level)
                .collect();
            let fmax = f1.iter().chain(&f2).fold(0.0f64, |a, &x| a.max(x.abs()));
            let Some(w) = barycentric(model, ids2, model.vertex(ids1[a1] as usize)) else {
                continue;
            };
            // â_I = f̂(I/d) − c for fixed control points.
            let ahat = |f: &[f64], i: &[u32]| {
                (0..m).map(|k| f[k] * f64::from(i[k])).sum::<f64>() / f64::from(d)
            };
            let start = rows.len();
            let mut scale = Vec::new();
            for j in lattice.chunks(m) {
                if j[a1] != 0 {
                    continue;
                }
                let mut i1 = j.to_vec();
                i1[a1] += 1;
                let v1 = var(owner(ids1, &i1));
                scale.push(v1);
                let mut terms = vec![(v1, ahat(&f1, &i1) / fmax)];
                let mut j2 = vec![0u32; m];
                for (pos, &e) in j.iter().enumerate() {
                    if e > 0 {
                        let p2 = ids2
                            .iter()
                            .position(|&v| v == ids1[pos])
                            .expect("facet vertex in both simplices");
                        j2[p2] = e;
                    }
                }
                for (i, wi) in w.iter().enumerate().take(m) {
                    let mut i2 = j2.clone();
                    i2[i] += 1;
                    terms.push((var(owner(ids2, &i2)), -wi * ahat(&f2, &i2) / fmax));
                }
                rows.push(Row { terms });
            }
            facets.push(Facet {
                face,
                simplices: [s1, s2],
                fmax,
                rows: start..rows.len(),
                scale,
            });
        }
        // Groups: unknowns coupled by a condition (union–find).
        let mut parent: Vec<usize> = (0..keys.len()).collect();
        fn find(parent: &mut [usize], mut x: usize) -> usize {
            while parent[x] != x {
                parent[x] = parent[parent[x]];
                x = parent[x];
            }
            x
        }
        for row in &rows {
            let a = find(&mut parent, row.terms[0].0);
            for &(v, _) in &row.terms[1..] {
                let b = find(&mut parent, v);
                parent[b] = a;
            }
        }
        let mut group_of_root: HashMap<usize, usize> = HashMap::new();
        let mut group = vec![0; keys.len()];
        let mut group_size = Vec::new();
        for (k, g) in group.iter_mut().enumerate() {
            let root = find(&mut parent, k);
            let next = group_of_root.len();
            *g = *group_of_root.entry(root).or_insert(next);
            if *g == group_size.len() {
                group_size.push(0);
            }
            group_size[*g] += 1;
        }
        let mut columns: Vec<Vec<(usize, f64)>> = vec![Vec::new(); keys.len()];
        for (i, row) in rows.iter().enumerate() {
            for &(v, c) in &row.terms {
                columns[v].push((i, c));
            }
        }
        Problem {
            keys,
            rows,
            columns,
            facets,
            group,
            group_size,
        }
    }

    /// `v − mean of its group`.
    fn center(&self, v: &[f64]) -> Vec<f64> {
        let mut mean = vec![0.0; self.group_size.len()];
        for (k, &x) in v.iter().enumerate() {
            mean[self.group[k]] += x;
        }
        for (g, s) in mean.iter_mut().zip(&self.group_size) {
            *g /= *s as f64;
        }
        v.iter()
            .enumerate()
            .map(|(k, &x)| x - mean[self.group[k]])
            .collect()
    }

    /// The conditions at weights `q`.
    fn residuals(&self, q: &[f64]) -> Vec<f64> {
        self.rows
            .par_iter()
            .map(|r| r.terms.iter().map(|&(v, c)| c * q[v]).sum())
            .collect()
    }

    /// `E(β)` and its parts: the centred log-weights `u`, `q̃ = exp u`, the conditions at `q̃`.
    fn objective(&self, beta: &[f64], alpha: f64) -> (f64, Vec<f64>, Vec<f64>, Vec<f64>) {
        let u = self.center(beta);
        let q: Vec<f64> = u.iter().map(|x| x.exp()).collect();
        let r = self.residuals(&q);
        let e = r.iter().map(|x| x * x).sum::<f64>() + alpha * u.iter().map(|x| x * x).sum::<f64>();
        (e, u, q, r)
    }

    /// `Sᵀ y` scaled by `q`: `(D Sᵀ y)_k`.
    fn transpose_times(&self, q: &[f64], y: &[f64]) -> Vec<f64> {
        self.columns
            .par_iter()
            .zip(q)
            .map(|(col, qk)| qk * col.iter().map(|&(i, c)| c * y[i]).sum::<f64>())
            .collect()
    }

    /// ISM-402 per crossed facet at the stored weights `q` (unnormalised, not centred).
    fn facet_residuals(&self, q: &[f64]) -> Vec<FacetResidual> {
        let r = self.residuals(q);
        self.facets
            .iter()
            .map(|f| {
                let sum: f64 = r[f.rows.clone()].iter().map(|x| x * x).sum();
                let qmax = f.scale.iter().fold(0.0f64, |a, &v| a.max(q[v]));
                FacetResidual {
                    face: f.face.clone(),
                    simplices: f.simplices,
                    absolute: sum.sqrt() * f.fmax,
                    relative: sum.sqrt() / qmax.max(f64::MIN_POSITIVE),
                }
            })
            .collect()
    }
}

fn stats(list: &[FacetResidual]) -> ResidualStats {
    let max = list.iter().map(|f| f.relative).fold(0.0f64, f64::max);
    let mean = if list.is_empty() {
        0.0
    } else {
        list.iter().map(|f| f.relative).sum::<f64>() / list.len() as f64
    };
    ResidualStats {
        facets: list.len(),
        max,
        mean,
    }
}

/// Solves `(P (D SᵀS D + α) P + λ) x = b` by Jacobi-preconditioned conjugate gradients,
/// matrix-free. Hand-written: the operator has a per-group rank-one part (the centring `P`) that a
/// sparse-matrix crate would have to store densely, and the workspace has no sparse solver.
fn solve_step(p: &Problem, q: &[f64], alpha: f64, lambda: f64, b: &[f64]) -> Vec<f64> {
    let apply = |x: &[f64]| -> Vec<f64> {
        let px = p.center(x);
        let dx: Vec<f64> = px.iter().zip(q).map(|(a, b)| a * b).collect();
        let sdx = p.residuals(&dx);
        let mut y = p.transpose_times(q, &sdx);
        y.iter_mut().zip(&px).for_each(|(a, b)| *a += alpha * b);
        let mut y = p.center(&y);
        y.iter_mut().zip(x).for_each(|(a, b)| *a += lambda * b);
        y
    };
    let mut diag = vec![alpha + lambda; p.keys.len()];
    for row in &p.rows {
        for &(v, c) in &row.terms {
            diag[v] += (c * q[v]).powi(2);
        }
    }
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let mut x = vec![0.0; b.len()];
    let mut r = b.to_vec();
    let mut z: Vec<f64> = r.iter().zip(&diag).map(|(a, d)| a / d).collect();
    let mut dir = z.clone();
    let mut rz = dot(&r, &z);
    let norm_b = dot(b, b).sqrt();
    for _ in 0..CG_MAX_ITERATIONS {
        if dot(&r, &r).sqrt() <= CG_TOLERANCE * norm_b {
            break;
        }
        let ad = apply(&dir);
        let den = dot(&dir, &ad);
        if den <= 0.0 || !den.is_finite() {
            break;
        }
        let step = rz / den;
        x.iter_mut().zip(&dir).for_each(|(a, b)| *a += step * b);
        r.iter_mut().zip(&ad).for_each(|(a, b)| *a -= step * b);
        z = r.iter().zip(&diag).map(|(a, d)| a / d).collect();
        let rz_new = dot(&r, &z);
        let beta = rz_new / rz;
        rz = rz_new;
        dir.iter_mut().zip(&z).for_each(|(a, b)| *a = b + beta * *a);
    }
    x
}

/// The model with `model`'s complex and values and one rational stage of degree `d` whose weights
/// are the input's, overridden by `fitted`.
fn build(model: &Model, d: u32, input: &InputWeights, fitted: &HashMap<WeightKey, f64>) -> Model {
    let mut faces: HashMap<Vec<u32>, Vec<f64>> = input.clone();
    for ((face, rank), &q) in fitted {
        faces
            .entry(face.clone())
            .or_insert_with(|| vec![1.0; multi_index::owned_count(face.len(), d)])[*rank] = q;
    }
    let mut records: Vec<FaceRecord> = faces
        .into_iter()
        .filter(|(_, w)| w.iter().any(|&q| q != 1.0))
        .map(|(face, weights)| {
            let k1 = face.len();
            let points = multi_index::owned(k1, d)
                .iter()
                .map(|&e| f64::from(e) / f64::from(d))
                .collect();
            FaceRecord {
                face,
                points,
                weights,
            }
        })
        .collect();
    records.sort_by(|a, b| (a.face.len(), &a.face).cmp(&(b.face.len(), &b.face)));
    let mut out = model.clone();
    let mut stage = Stage::identity(StageKind::Rational, d);
    stage.name = Some("rational C1".to_string());
    stage.faces = records.into();
    out.stages = vec![stage];
    out.metadata.generator = Some(format!(
        "ism-fit {} (smooth --rational)",
        env!("CARGO_PKG_VERSION")
    ));
    out
}

/// ISM-402 relative residuals of `model` at every interior facet the shape crosses, computed from
/// eq. (6) directly (see the module doc): with `f − c` in place of `f` — the same as the
/// validator's for `c = 0`. A linear model is read as the identity rational stage of degree `n`.
///
/// # Errors
/// As [`smooth_rational`] for inputs outside Thm. 8.1's setting.
pub fn residuals(model: &Model) -> Result<Vec<FacetResidual>, C1Error> {
    let (d, input) = check_input(model, &C1Options::default())?;
    let problem = Problem::new(model, d);
    let q: Vec<f64> = problem
        .keys
        .iter()
        .map(|(face, rank)| input.get(face).map_or(1.0, |w| w[*rank]))
        .collect();
    Ok(problem.facet_residuals(&q))
}

/// Fits the weights of a rational stage with fixed control points so that the shape is as close
/// to C¹ across the crossed facets as the weights allow (see the module doc).
///
/// # Errors
/// [`C1Error`] when the model is not a linear isocomplex or a single implicit rational stage with
/// fixed control points, has structural errors or an unsupported dimension, or the options are
/// inconsistent.
pub fn smooth_rational(model: &Model, options: &C1Options) -> Result<C1Smoothed, C1Error> {
    smooth_rational_with_progress(model, options, &Progress::none())
}

/// The phase [`smooth_rational_with_progress`] reports, counted in Levenberg–Marquardt steps
/// (of at most [`C1Options::iterations`]).
pub const PHASE: &str = "rational smoothing: fitting the weights";

/// [`smooth_rational`] with a progress and cancel hook ([`PHASE`]); a cancelled hook stops the
/// fit at its next step.
///
/// # Errors
/// As [`smooth_rational`]; [`C1Error::Cancelled`].
pub fn smooth_rational_with_progress(
    model: &Model,
    options: &C1Options,
    progress: &Progress,
) -> Result<C1Smoothed, C1Error> {
    let start = Instant::now();
    let (d, input) = check_input(model, options)?;
    let problem = Problem::new(model, d);
    let alpha = options.alpha;
    let mut beta: Vec<f64> = problem
        .keys
        .iter()
        .map(|(face, rank)| {
            input
                .get(face)
                .map_or(0.0, |w| w[*rank].ln())
                .clamp(-MAX_LOG_WEIGHT, MAX_LOG_WEIGHT)
        })
        .collect();
    let initial_q: Vec<f64> = problem
        .keys
        .iter()
        .map(|(face, rank)| input.get(face).map_or(1.0, |w| w[*rank]))
        .collect();
    let residual_before = stats(&problem.facet_residuals(&initial_q));
    let (objective_before, ..) = problem.objective(&beta, alpha);
    let mut cost = objective_before;
    let mut steps = Vec::new();
    let mut lambda = 1e-3;
    for iteration in 0..options.iterations {
        progress.report_count(PHASE, iteration as u64, options.iterations as u64);
        progress.check()?;
        if problem.keys.is_empty() {
            break;
        }
        let (_, u, q, r) = problem.objective(&beta, alpha);
        let mut g = problem.transpose_times(&q, &r);
        g.iter_mut().zip(&u).for_each(|(a, b)| *a += alpha * b);
        let g = problem.center(&g);
        if g.iter().all(|&x| x == 0.0) {
            break;
        }
        let minus_g: Vec<f64> = g.iter().map(|x| -x).collect();
        let mut accepted = None;
        for _ in 0..8 {
            let step = solve_step(&problem, &q, alpha, lambda, &minus_g);
            let trial: Vec<f64> = beta
                .iter()
                .zip(&step)
                .map(|(b, s)| (b + s).clamp(-MAX_LOG_WEIGHT, MAX_LOG_WEIGHT))
                .collect();
            let (e, ..) = problem.objective(&trial, alpha);
            if e < cost {
                accepted = Some((trial, e));
                lambda = (lambda / 3.0).max(1e-12);
                break;
            }
            lambda *= 8.0;
        }
        let Some((trial, e)) = accepted else {
            break;
        };
        let gain = cost - e;
        beta = trial;
        cost = e;
        steps.push(e);
        if gain <= STALL_FRACTION * cost {
            break;
        }
    }
    let fit_seconds = start.elapsed().as_secs_f64();
    let q: Vec<f64> = beta.iter().map(|x| x.exp()).collect();
    let residual_after = stats(&problem.facet_residuals(&q));
    let fitted: HashMap<WeightKey, f64> = problem
        .keys
        .iter()
        .cloned()
        .zip(q.iter().copied())
        .collect();
    let out = build(model, d, &input, &fitted);
    let weight_range = out.stages[0]
        .faces
        .all_weights()
        .iter()
        .fold([1.0f64, 1.0f64], |[lo, hi], &w| [lo.min(w), hi.max(w)]);
    let report = C1Report {
        degree: d,
        alpha,
        residual_before,
        residual_after,
        jumps_before: normal_jumps(model),
        jumps_after: normal_jumps(&out),
        objective_before,
        objective_after: cost,
        steps,
        weights: problem.keys.len(),
        groups: problem.group_size.len(),
        conditions: problem.rows.len(),
        weight_range,
        records: out.stages[0].faces.len(),
        seconds: start.elapsed().as_secs_f64(),
        fit_seconds,
    };
    Ok(C1Smoothed { model: out, report })
}

#[cfg(test)]
mod tests {
    use super::*;
    use ism_validate::{validate, Options, Verdict};

    fn example(name: &str) -> Model {
        let path = format!("{}/../../spec/examples/{name}", env!("CARGO_MANIFEST_DIR"));
        let bytes = std::fs::read(&path).unwrap();
        ism_format::io::from_slice(&bytes).unwrap().model
    }

    fn quality(model: &Model) -> ism_validate::Report {
        let options = Options {
            quality: true,
            max_issues: usize::MAX,
            ..Options::default()
        };
        validate(model, &options)
    }

    /// Checks `residuals(model)` against the validator's ISM-402 messages facet by facet.
    fn assert_matches_validator(model: &Model) {
        let ours = residuals(model).unwrap();
        assert!(!ours.is_empty());
        let report = quality(model);
        assert_eq!(report.verdict, Verdict::Valid);
        let found: HashMap<(usize, Vec<u32>), f64> = report
            .issues
            .messages
            .iter()
            .filter(|m| m.code == ism_format::Rule::RationalC1.id())
            .map(|m| {
                let loc = &m.location;
                (
                    (loc.simplex.unwrap(), loc.face.clone().unwrap()),
                    m.value.unwrap(),
                )
            })
            .collect();
        let mut compared = 0;
        for f in &ours {
            match found.get(&(f.simplices[0], f.face.clone())) {
                Some(&v) => {
                    assert!(
                        (v - f.relative).abs() <= 1e-9 * v.max(1e-6),
                        "facet {:?}: validator {v}, ours {}",
                        f.face,
                        f.relative
                    );
                    compared += 1;
                }
                None => assert!(
                    f.relative <= ism_validate::quality::C1_RELATIVE_TOLERANCE,
                    "facet {:?}: ours {} but no ISM-402",
                    f.face,
                    f.relative
                ),
            }
        }
        assert!(compared > 0);
    }

    #[test]
    fn residual_is_the_validators_ism402() {
        let model = example("circle-linear.ism.json");
        for degree in [2, 3] {
            let s = smooth_rational(
                &model,
                &C1Options {
                    degree: Some(degree),
                    ..C1Options::default()
                },
            )
            .unwrap();
            assert_matches_validator(&s.model);
        }
    }

    #[test]
    fn optimisation_lowers_the_objective_and_the_jumps() {
        let model = example("circle-linear.ism.json");
        let s = smooth_rational(&model, &C1Options::default()).unwrap();
        let r = &s.report;
        let mut last = r.objective_before;
        assert!(!r.steps.is_empty());
        for &e in &r.steps {
            assert!(e < last, "{r:?}");
            last = e;
        }
        assert_eq!(r.objective_after, last);
        assert!(r.objective_after < 0.01 * r.objective_before, "{r:?}");
        assert!(r.residual_after.max < 0.1 * r.residual_before.max, "{r:?}");
        let (b, a) = (r.jumps_before.unwrap(), r.jumps_after.unwrap());
        assert!(a.max < 0.2 * b.max && a.mean < 0.2 * b.mean, "{r:?}");
        assert_eq!(a.facets, r.residual_after.facets);
        // The weights stay in the documented range, and the validator certifies the stage by a
        // theorem (degree 2: Thm. 6.5, adjusted quadratic rational; else Thm. 6.4), no
        // subdivision.
        assert!(r.weight_range[0] >= (-MAX_LOG_WEIGHT).exp() * (1.0 - 1e-12));
        assert!(r.weight_range[1] <= MAX_LOG_WEIGHT.exp() * (1.0 + 1e-12));
        let report = quality(&s.model);
        assert_eq!(report.verdict, Verdict::Valid);
        let certs = &report.stages[0].certificates;
        assert!(
            certs.keys().all(|k| k == ism_validate::theorem::THM_6_4
                || k == ism_validate::theorem::THM_6_5),
            "{certs:?}"
        );
        // Its own output is accepted as input, at the same objective.
        let again = smooth_rational(&s.model, &C1Options::default()).unwrap();
        let e = again.report.objective_before;
        assert!(
            (e - r.objective_after).abs() <= 1e-12 * e.max(1e-300),
            "{e}"
        );
        assert!(again.report.objective_after <= e);
    }

    #[test]
    fn the_level_is_subtracted() {
        // F = c with values f is F − t = c − t with values f − t: the same shape, the same
        // conditions (eq. (6) is on f − c), the same weights.
        let model = example("circle-linear.ism.json");
        let mut shifted = model.clone();
        shifted.values.iter_mut().for_each(|f| *f += 0.3);
        shifted.level = 0.3;
        let a = smooth_rational(&model, &C1Options::default()).unwrap();
        let b = smooth_rational(&shifted, &C1Options::default()).unwrap();
        // The validator subtracts the level too (ISM-402 on f − c).
        assert_matches_validator(&b.model);
        let (ra, rb) = (&a.report, &b.report);
        assert_eq!(ra.weights, rb.weights);
        // The input's figures agree to rounding; the fits to the stopping rule's accuracy (the
        // rounding of f − c changes the path of the iteration, not its limit).
        let close = |x: f64, y: f64, rel: f64| (x - y).abs() <= rel * x.abs();
        assert!(close(ra.residual_before.max, rb.residual_before.max, 1e-12));
        assert!(close(
            ra.residual_before.mean,
            rb.residual_before.mean,
            1e-12
        ));
        assert!(close(ra.objective_before, rb.objective_before, 1e-12));
        assert!(
            close(ra.objective_after, rb.objective_after, 1e-6),
            "{ra:?} {rb:?}"
        );
        assert!(
            close(ra.residual_after.max, rb.residual_after.max, 1e-3),
            "{ra:?} {rb:?}"
        );
        let (ja, jb) = (ra.jumps_after.unwrap(), rb.jumps_after.unwrap());
        assert!((ja.max - jb.max).abs() < 1e-2, "{ja:?} {jb:?}");
    }

    #[test]
    fn a_larger_alpha_keeps_the_weights_closer_together() {
        let model = example("circle-linear.ism.json");
        let spread = |alpha: f64| {
            let r = smooth_rational(
                &model,
                &C1Options {
                    alpha,
                    ..C1Options::default()
                },
            )
            .unwrap()
            .report;
            (r.weight_range[1] / r.weight_range[0], r.residual_after.max)
        };
        let (wide, fine) = spread(1e-5);
        let (narrow, coarse) = spread(1e-2);
        assert!(
            narrow < wide && fine < coarse,
            "{wide} {fine} {narrow} {coarse}"
        );
    }

    /// Two triangles sharing the edge `{1, 2}` that the shape crosses; `σ = (0, 1, 2)`,
    /// `σ′ = (3, 2, 1)`.
    fn two_triangles() -> Model {
        let mut model = Model::new(2);
        model.vertices = vec![-1.0, 0.2, 0.0, -1.0, 0.0, 1.0, 1.1, -0.3];
        model.simplices = vec![0, 1, 2, 3, 2, 1];
        model.values = vec![0.5, -1.0, 1.0, -0.5];
        model
    }

    /// Thm. 8.1's exact solution on two triangles: all weights 1 except `q₀₁ = q_{e₀+e₁}` and
    /// `q₀₂` (edges `{0,1}`, `{0,2}`), where eq. (6) reads `q₀ⱼ (f₀ + fⱼ)/2 = (fⱼ + g′(p₀))/2` for
    /// `j = 1, 2`, with `g′` the linear function of `σ′` extended to `p₀` (the right side is the
    /// blossom of a linear function). `None` when that solution is not positive; else the model
    /// and `g′(p₀) − f₀` (zero iff the linear shape has no corner).
    fn exact_c1(linear: &Model) -> Option<(Model, f64)> {
        let eval = ism_geom::ModelEval::new(linear).unwrap();
        let w = eval.barycentric(1, linear.vertex(0));
        let g = (0..3)
            .map(|i| w[i] * linear.values[linear.simplex(1)[i] as usize])
            .sum::<f64>();
        let f = &linear.values;
        let q01 = (f[1] + g) / (f[0] + f[1]);
        let q02 = (f[2] + g) / (f[0] + f[2]);
        if !(q01 > 0.0 && q02 > 0.0) {
            return None;
        }
        let mut model = linear.clone();
        let mut stage = Stage::identity(StageKind::Rational, 2);
        for (face, q) in [(vec![0, 1], q01), (vec![0, 2], q02)] {
            stage.faces.push_record(&FaceRecord {
                face,
                points: vec![0.5, 0.5],
                weights: vec![q],
            });
        }
        model.stages = vec![stage];
        Some((model, g - f[0]))
    }

    #[test]
    fn exact_solution_of_eq6_makes_the_shape_c1() {
        let linear = two_triangles();
        let (model, corner) = exact_c1(&linear).unwrap();
        assert!(corner.abs() > 0.1, "the linear shape has a corner");
        let ours = residuals(&model).unwrap();
        assert_eq!(ours.len(), 1);
        assert!(ours[0].relative < 1e-14, "{ours:?}");
        let before = normal_jumps(&linear).unwrap();
        let after = normal_jumps(&model).unwrap();
        assert!(before.max > 1.0, "{before:?}");
        assert!(after.max < 1e-4, "{after:?}");
        // The optimizer finds an exact solution from the linear model too (α = 0: C¹ only).
        let s = smooth_rational(
            &linear,
            &C1Options {
                alpha: 0.0,
                ..C1Options::default()
            },
        )
        .unwrap();
        assert!(s.report.residual_after.max < 1e-8, "{:?}", s.report);
        assert!(s.report.jumps_after.unwrap().max < 1e-4, "{:?}", s.report);
    }

    #[test]
    fn sphere_on_a_grid_gets_smaller_jumps() {
        let complex = crate::complex::Complex::kuhn(&[-1.0, 1.0, -1.0, 1.0, -1.0, 1.0], &[3, 3, 3]);
        let mut model = Model::new(3);
        model.vertices = complex.points().to_vec();
        model.simplices = complex.compact_cells();
        model.values = model
            .vertices
            .chunks(3)
            .map(|p| p.iter().map(|x| x * x).sum::<f64>() - 0.55)
            .collect();
        let s = smooth_rational(&model, &C1Options::default()).unwrap();
        let r = &s.report;
        assert_eq!(r.degree, 3);
        assert!(r.residual_after.max < 0.1 * r.residual_before.max, "{r:?}");
        let (b, a) = (r.jumps_before.unwrap(), r.jumps_after.unwrap());
        assert!(a.mean < 0.5 * b.mean && a.max < b.max, "{r:?}");
        assert_matches_validator(&s.model);
    }

    #[test]
    fn inputs_outside_the_theorem_are_typed_errors() {
        let o = C1Options::default();
        for name in ["quadratic-edges.ism.json", "monotonic.ism.json"] {
            let e = smooth_rational(&example(name), &o).err().unwrap();
            assert!(matches!(e, C1Error::Stage { stage: 0, .. }), "{name}: {e}");
        }
        let e = smooth_rational(&example("two-stage.ism.json"), &o)
            .err()
            .unwrap();
        assert!(matches!(e, C1Error::StageCount(2)), "{e}");
        // Fixed points and non-uniform weights: in the theorem's setting, accepted.
        let degree5 = smooth_rational(&example("rational-degree5.ism.json"), &o).unwrap();
        assert_eq!(degree5.report.degree, 5);
        assert!(degree5.report.objective_after < degree5.report.objective_before);

        let linear = two_triangles();
        let good = smooth_rational(&linear, &o).unwrap().model;
        let mut moved = good.clone();
        moved.stages[0].faces.record_mut(0).points[0] += 1e-6;
        let e = smooth_rational(&moved, &o).err().unwrap();
        assert!(matches!(e, C1Error::MovedPoint { index: 0, .. }), "{e}");
        let mut parametric = good.clone();
        parametric.stages[0].direction = Direction::Parametric;
        assert!(matches!(
            smooth_rational(&parametric, &o),
            Err(C1Error::Stage { .. })
        ));
        let with = |degree: Option<u32>, alpha: f64| C1Options { degree, alpha, ..o };
        assert!(matches!(
            smooth_rational(&linear, &with(Some(1), o.alpha)),
            Err(C1Error::Options(_))
        ));
        assert!(matches!(
            smooth_rational(&good, &with(Some(3), o.alpha)),
            Err(C1Error::Options(_))
        ));
        assert!(matches!(
            smooth_rational(&linear, &with(None, -1.0)),
            Err(C1Error::Options(_))
        ));
        assert!(matches!(
            smooth_rational(&linear, &with(None, f64::NAN)),
            Err(C1Error::Options(_))
        ));
        let mut broken = linear.clone();
        broken.values.pop();
        let e = smooth_rational(&broken, &o).err().unwrap();
        let C1Error::Structure(diagnostics) = &e else {
            panic!("expected C1Error::Structure, got {e:?}");
        };
        // Truth: the reader's own check of the same model, kept as data (rule and place).
        let expected: Vec<_> = ism_format::structure::check(&broken, 5)
            .into_iter()
            .filter(|d| d.severity == ism_format::Severity::Error)
            .collect();
        assert!(!expected.is_empty());
        assert_eq!(diagnostics, &expected);
        let listed: Vec<String> = expected.iter().map(|d| d.to_string()).collect();
        assert_eq!(e.to_string(), format!("model: {}", listed.join("; ")));
        let mut negative = good.clone();
        negative.stages[0].faces.record_mut(0).weights[0] = -1.0;
        let e = smooth_rational(&negative, &o).err().unwrap();
        assert!(e.to_string().contains("positive weight"), "{e}");
        let mut weights_off = good;
        weights_off.stages[0].faces.edit(|r| r[0].weights.push(1.0));
        assert!(matches!(
            smooth_rational(&weights_off, &o),
            Err(C1Error::Structure(_))
        ));
    }

    mod properties {
        use super::*;
        use proptest::prelude::*;

        proptest! {
            #![proptest_config(ProptestConfig::with_cases(16))]

            /// Random positive weights on every face record of circle-linear: our residual is the
            /// validator's, facet by facet.
            #[test]
            fn random_weights_match_the_validator(
                degree in 2u32..4,
                logs in prop::collection::vec(-2.0f64..2.0, 64),
            ) {
                let mut model = example("circle-linear.ism.json");
                let mut faces: Vec<Vec<u32>> = Vec::new();
                for ids in model.simplex_iter() {
                    let local = ism_format::indexed::simplex_faces(ids, 1);
                    faces.extend(local.map(|f| f.ids().to_vec()));
                }
                faces.sort();
                faces.dedup();
                let mut stage = Stage::identity(StageKind::Rational, degree);
                let mut k = 0;
                for face in faces {
                    let owned = multi_index::owned(face.len(), degree);
                    if owned.is_empty() {
                        continue;
                    }
                    let points = owned.iter().map(|&e| f64::from(e) / f64::from(degree)).collect();
                    let weights = (0..owned.len() / face.len())
                        .map(|_| {
                            k += 1;
                            logs[k % logs.len()].exp()
                        })
                        .collect();
                    stage.faces.push_record(&FaceRecord { face, points, weights });
                }
                model.stages = vec![stage];
                assert_matches_validator(&model);
            }

            /// Thm. 8.1 on random pairs of triangles: where eq. (6) has the positive solution of
            /// [`exact_c1`], the residual vanishes and so does the normal jump (ISM-401).
            #[test]
            fn exact_positive_solutions_remove_the_jump(
                p0 in (-1.5f64..-0.2, -0.8f64..0.8),
                p3 in (0.2f64..1.5, -0.8f64..0.8),
                f in (0.1f64..1.5, -1.5f64..-0.2, 0.2f64..1.5, 0.1f64..1.5),
                signs in (any::<bool>(), any::<bool>()),
            ) {
                let mut linear = two_triangles();
                linear.vertices = vec![p0.0, p0.1, 0.0, -1.0, 0.0, 1.0, p3.0, p3.1];
                let s = |neg: bool| if neg { -1.0 } else { 1.0 };
                linear.values = vec![s(signs.0) * f.0, f.1, f.2, s(signs.1) * f.3];
                let exact = exact_c1(&linear);
                prop_assume!(exact.is_some());
                let (model, _) = exact.unwrap();
                let ours = residuals(&model).unwrap();
                prop_assert_eq!(ours.len(), 1);
                prop_assert!(ours[0].relative < 1e-12, "{:?}", ours);
                let after = normal_jumps(&model).unwrap();
                prop_assert!(after.max < 1e-4, "{:?}", after);
            }

            /// Random values on a small grid: the objective never increases, the output is valid.
            #[test]
            fn never_increases_nor_invalidates(
                values in prop::collection::vec(-1.0f64..1.0, 16),
                alpha in prop_oneof![Just(0.0), 1e-5f64..1.0],
            ) {
                let complex = crate::complex::Complex::kuhn(&[0.0, 1.0, 0.0, 1.0], &[3, 3]);
                let mut model = Model::new(2);
                model.vertices = complex.points().to_vec();
                model.simplices = complex.compact_cells();
                model.values = values
                    .iter()
                    .map(|&v| if v.abs() < 0.05 { 0.05f64.copysign(v) } else { v })
                    .collect();
                let s = smooth_rational(&model, &C1Options { alpha, iterations: 20, ..C1Options::default() }).unwrap();
                let r = &s.report;
                let mut last = r.objective_before;
                for &e in &r.steps {
                    prop_assert!(e < last, "{:?}", r);
                    last = e;
                }
                prop_assert!(r.objective_after <= r.objective_before);
                prop_assert_eq!(
                    validate(&s.model, &Options::default()).verdict,
                    Verdict::Valid
                );
            }
        }
    }
}
