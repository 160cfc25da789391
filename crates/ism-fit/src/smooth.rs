//! Smoothing: reduce the normal jumps of the shape across interior facets (Mello & Velho 2009, §8).
//!
//! A curved isocomplex is in general not smooth across a facet `δ`: the normals computed in the
//! two simplices `σ, σ′` at a point of `O ∩ δ` differ. [`smooth`] minimizes
//! `Σ_δ err(δ, β) + α Σ |β − β₀|²` with the paper's `err(δ, β) = Σ_i |n_σ(p_i) − n_σ′(p_i)|²`
//! over sample points `p_i` of `O` on `δ` (the same points `ism validate --quality` uses for
//! ISM-401: the crossing of the facet in 2D, five points along `θ ∩ δ` in 3D), over the solitary
//! points `β` (logits) of the stratified block of [`Layered`]. The proximity term (weight
//! [`SmoothOptions::alpha`]) keeps the map near the input where the jumps do not care.
//!
//! - A model whose first stages are a stratified block (what `ism fit` and `ism fit --hermite`
//!   write) has that block optimized. Any other model (monotonic, general Bézier, rational stages)
//!   keeps its stages and gets a new identity block in front of them, which is then optimized:
//!   `X = S ∘ Y⁻¹`, valid because each factor is. Rational weights are not optimized.
//! - The points of sign-changing edges stay fixed, so the shape keeps crossing every edge where it
//!   did; everything else in the cells around crossing facets moves.
//! - Validity by construction: softmax logits keep every solitary point in its open face. Each
//!   accepted Levenberg–Marquardt step lowers its face's part of the objective, which is the
//!   whole objective's change, so the objective never increases.
//!
//! ```
//! use ism_fit::smooth::{normal_jumps, smooth, SmoothOptions};
//! use ism_fit::{fit, FitOptions, Preset};
//!
//! let circle = Preset::find("circle")?;
//! let mut options = FitOptions::new(circle.domain);
//! options.resolution = 4;
//! let model = fit(&circle.expression()?, &options, &ism_format::Progress::none())?.to_model("circle");
//! let smoothed = smooth(&model, &SmoothOptions::default()).unwrap();
//! let (before, after) = (smoothed.report.before.unwrap(), smoothed.report.after.unwrap());
//! assert!(after.max < before.max);
//! # Ok::<(), ism_fit::FitError>(())
//! ```

use std::collections::HashMap;
use std::time::Instant;

use ism_format::indexed::shared_facets;
use ism_format::model::Model;
use ism_format::progress::Progress;
use ism_geom::{Bary, MAX_VARS};

use crate::layered::{check_structure, EditError, Jet, Layered, Sample};
use crate::lm::lm_face;
use crate::strata::StratifiedMap;

/// Points of `O` sampled per 3D facet along `θ ∩ δ` — the value ISM-401 uses, so the objective
/// and the reported measure look at the same points.
const FACET_SAMPLES_3D: usize = 5;

/// Options of [`smooth`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SmoothOptions {
    /// Gauss–Seidel sweeps over the free faces.
    pub iterations: usize,
    /// Weight of the proximity term `Σ |β − β₀|²` (logits).
    pub alpha: f64,
}

impl Default for SmoothOptions {
    fn default() -> Self {
        SmoothOptions {
            iterations: 4,
            alpha: 1e-3,
        }
    }
}

/// The two modes of `ism smooth` (and of the Python package's `Model.smooth`), with their
/// options: one place for the defaults of the options not given.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Mode {
    /// Normal jumps reduced by moving the solitary points ([`smooth`]).
    Jumps(SmoothOptions),
    /// The rational weights fitted to the C¹ condition ([`crate::c1::smooth_rational`]).
    Rational(crate::c1::C1Options),
}

impl Mode {
    /// The mode from the front ends' optional arguments; the defaults fill the rest.
    ///
    /// # Errors
    /// [`EditError::Model`] for a `degree` without `rational`, or an `alpha` that is not a finite
    /// number ≥ 0.
    pub fn new(
        iterations: Option<usize>,
        alpha: Option<f64>,
        rational: bool,
        degree: Option<u32>,
    ) -> Result<Mode, EditError> {
        if let Some(a) = alpha {
            if !(a.is_finite() && a >= 0.0) {
                return Err(EditError::Model(format!(
                    "alpha {a} must be a finite number ≥ 0"
                )));
            }
        }
        if rational {
            let d = crate::c1::C1Options::default();
            return Ok(Mode::Rational(crate::c1::C1Options {
                degree,
                alpha: alpha.unwrap_or(d.alpha),
                iterations: iterations.unwrap_or(d.iterations),
            }));
        }
        if degree.is_some() {
            return Err(EditError::Model(
                "a degree applies to rational smoothing only".into(),
            ));
        }
        let d = SmoothOptions::default();
        Ok(Mode::Jumps(SmoothOptions {
            iterations: iterations.unwrap_or(d.iterations),
            alpha: alpha.unwrap_or(d.alpha),
        }))
    }
}

/// ISM-401 statistics as JSON (`null` when not measured): `{facets, max, mean}`.
pub fn jump_json(s: Option<JumpStats>) -> serde_json::Value {
    match s {
        Some(s) => serde_json::json!({"facets": s.facets, "max": s.max, "mean": s.mean}),
        None => serde_json::Value::Null,
    }
}

impl SmoothReport {
    /// The report of `ism smooth --json`, with the output's validation `verdict`.
    pub fn to_json(&self, verdict: &str) -> serde_json::Value {
        serde_json::json!({
            "before": jump_json(self.before),
            "after": jump_json(self.after),
            "objectiveBefore": self.objective_before,
            "objectiveAfter": self.objective_after,
            "sweeps": self.sweeps,
            "facets": self.facets,
            "samples": self.samples,
            "freeFaces": self.free_faces,
            "blockAdded": self.block_added,
            "verdict": verdict,
            "seconds": self.seconds,
        })
    }
}

/// The ISM-401 measure of `ism validate --quality`: per interior facet crossing the shape, the
/// largest angle between the two simplices' normals; max and mean over facets.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JumpStats {
    /// Facets measured.
    pub facets: usize,
    /// Largest jump, degrees.
    pub max: f64,
    /// Mean jump, degrees (as printed by the validator: 3 decimals).
    pub mean: f64,
}

/// Summary of [`smooth`].
#[derive(Clone, Debug, PartialEq)]
pub struct SmoothReport {
    /// ISM-401 of the input (`None` when the validator does not certify every stage).
    pub before: Option<JumpStats>,
    /// ISM-401 of the output.
    pub after: Option<JumpStats>,
    /// `Σ_δ err(δ)` of the input.
    pub objective_before: f64,
    /// `Σ_δ err(δ)` of the output.
    pub objective_after: f64,
    /// The full objective (with the proximity term) after each sweep.
    pub sweeps: Vec<f64>,
    /// Interior facets crossing the shape.
    pub facets: usize,
    /// Sample points on them.
    pub samples: usize,
    /// Solitary points optimized.
    pub free_faces: usize,
    /// Whether a new stratified block was put in front of the input's stages.
    pub block_added: bool,
    /// Wall time in seconds.
    pub seconds: f64,
}

/// The result of [`smooth`].
#[derive(Clone, Debug)]
pub struct Smoothed {
    /// The smoothed model.
    pub model: Model,
    /// The summary.
    pub report: SmoothReport,
}

/// ISM-401 of `model` from the validator (quality layer); `None` when it is not computed (some
/// stage not certified).
pub fn normal_jumps(model: &Model) -> Option<JumpStats> {
    let options = ism_validate::Options {
        quality: true,
        ..ism_validate::Options::default()
    };
    let report = ism_validate::validate(model, &options);
    // The validator's statistics as data, never its wording.
    let jumps = report.quality.normal_jumps?;
    Some(JumpStats {
        facets: jumps.facets,
        max: jumps.max_degrees,
        mean: jumps.mean_degrees,
    })
}

/// A facet sample seen from both sides.
struct Pair {
    a: Sample,
    b: Sample,
}

/// Samples of `O` on the interior facets crossing the shape (σ's and σ′'s coordinates).
fn facet_pairs(layer: &Layered) -> Result<(usize, Vec<Pair>), EditError> {
    let frames = layer.frames();
    let m = layer.dim() + 1;
    let ids: Vec<u32> = frames
        .iter()
        .flat_map(|fr| fr.ids.iter().copied())
        .collect();
    let mut pairs = Vec::new();
    let mut crossing = 0;
    for (_, [(s1, a1), (s2, _)]) in shared_facets(m, &ids) {
        let f = &frames[s1].f;
        let pos: Vec<usize> = (0..m).filter(|&i| i != a1).collect();
        let mut ends: Vec<Bary> = Vec::new();
        for x in 0..pos.len() {
            for y in (x + 1)..pos.len() {
                let (i, j) = (pos[x], pos[y]);
                if f[i] * f[j] < 0.0 {
                    let t = f[j] / (f[j] - f[i]);
                    let mut u = [0.0; MAX_VARS];
                    u[i] = t;
                    u[j] = 1.0 - t;
                    ends.push(u);
                }
            }
        }
        let us: Vec<Bary> = match ends.len() {
            1 => ends,
            2 => (0..FACET_SAMPLES_3D)
                .map(|k| {
                    let t = (k as f64 + 0.5) / FACET_SAMPLES_3D as f64;
                    let mut u = [0.0; MAX_VARS];
                    for c in 0..m {
                        u[c] = (1.0 - t) * ends[0][c] + t * ends[1][c];
                    }
                    u
                })
                .collect(),
            _ => continue,
        };
        crossing += 1;
        for u in us {
            let mut u2 = [0.0; MAX_VARS];
            for &i in &pos {
                let v = frames[s1].ids[i];
                let j = frames[s2]
                    .ids
                    .iter()
                    .position(|&w| w == v)
                    .expect("facet vertex in both simplices");
                u2[j] = u[i];
            }
            let (Some(a), Some(b)) = (layer.sample(s1, &u), layer.sample(s2, &u2)) else {
                return Err(EditError::Model(format!(
                    "the stages of simplex {s1} or {s2} do not invert at a point of the shape"
                )));
            };
            pairs.push(Pair { a, b });
        }
    }
    Ok((crossing, pairs))
}

/// Reduces the normal jumps of `model` (see the module doc).
///
/// # Errors
/// [`EditError::Structure`] for structural errors; [`EditError::Model`] for a dimension other than
/// 2 and 3, a negative `alpha`, or kept stages that do not invert at a point of the shape; [`EditError::Geom`] when a
/// stage does not evaluate.
pub fn smooth(model: &Model, options: &SmoothOptions) -> Result<Smoothed, EditError> {
    smooth_with_progress(model, options, &Progress::none())
}

/// The phase [`smooth_with_progress`] reports once per sweep, counted in free faces.
pub const PHASE: &str = "smoothing: fitting the faces around the crossed facets";

/// [`smooth`] with a progress and cancel hook ([`PHASE`]); a cancelled hook stops the sweeps at
/// their next face.
///
/// # Errors
/// As [`smooth`]; [`EditError::Cancelled`].
pub fn smooth_with_progress(
    model: &Model,
    options: &SmoothOptions,
    progress: &Progress,
) -> Result<Smoothed, EditError> {
    let start = Instant::now();
    if !(options.alpha >= 0.0 && options.alpha.is_finite()) {
        return Err(EditError::Model(format!(
            "alpha {} must be a finite number ≥ 0",
            options.alpha
        )));
    }
    check_structure(model)?;
    let before = normal_jumps(model);
    let mut layer = Layered::new(model)?;
    let n = layer.dim();
    let (facets, pairs) = facet_pairs(&layer)?;

    let residuals = |layer: &Layered, map: &StratifiedMap, which: &[usize]| -> Vec<f64> {
        let mut jets: HashMap<usize, Jet> = HashMap::new();
        let mut out = Vec::with_capacity(which.len() * n);
        for &k in which {
            let p = &pairs[k];
            let mut normal = |smp: &Sample| {
                let jet = jets
                    .entry(smp.cell)
                    .or_insert_with(|| Jet::new(map, &layer.frames()[smp.cell].ids));
                layer.normal(jet, smp).map(|x| x.1)
            };
            match (normal(&p.a), normal(&p.b)) {
                (Some(x), Some(y)) => out.extend((0..n).map(|c| x[c] - y[c])),
                // Degenerate gradient: the largest possible deviation, so steps avoid it.
                _ => out.extend((0..n).map(|_| 2.0)),
            }
        }
        out
    };
    let all: Vec<usize> = (0..pairs.len()).collect();
    let jump_cost = |layer: &Layered, map: &StratifiedMap| -> f64 {
        residuals(layer, map, &all).iter().map(|v| v * v).sum()
    };
    let objective_before = jump_cost(&layer, &layer.map);

    // Free faces: every solitary point of the cells around crossing facets, except the points of
    // sign-changing edges (they hold the crossings).
    let mut by_cell: HashMap<usize, Vec<usize>> = HashMap::new();
    for (k, p) in pairs.iter().enumerate() {
        by_cell.entry(p.a.cell).or_default().push(k);
        by_cell.entry(p.b.cell).or_default().push(k);
    }
    let (free, blocks) = layer.free_blocks(&by_cell);
    let start_logits: Vec<Vec<f64>> = free.iter().map(|f| layer.map.logits(f)).collect();
    let sqrt_alpha = options.alpha.sqrt();
    let mut map = std::mem::take(&mut layer.map);
    let proximity = |map: &StratifiedMap| -> f64 {
        free.iter()
            .zip(&start_logits)
            .map(|(f, x0)| {
                map.logits(f)
                    .iter()
                    .zip(x0)
                    .map(|(a, b)| (a - b).powi(2))
                    .sum::<f64>()
            })
            .sum::<f64>()
            * options.alpha
    };
    let mut sweeps = Vec::with_capacity(options.iterations);
    for _ in 0..options.iterations {
        let counter = progress.phase(PHASE, free.len() as u64);
        for ((f, which), x0) in free.iter().zip(&blocks).zip(&start_logits) {
            progress.check()?;
            counter.add(1);
            lm_face(&mut map, f, 3, &|m: &StratifiedMap| {
                let mut r = residuals(&layer, m, which);
                r.extend(
                    m.logits(f)
                        .iter()
                        .zip(x0)
                        .map(|(a, b)| sqrt_alpha * (a - b)),
                );
                r
            });
        }
        sweeps.push(jump_cost(&layer, &map) + proximity(&map));
    }
    let objective_after = jump_cost(&layer, &map);
    layer.map = map;
    let out = if layer.block_added && layer.map.num_faces() == 0 {
        model.clone()
    } else {
        let mut out = layer.to_model();
        out.metadata.generator = Some(format!("ism-fit {} (smooth)", env!("CARGO_PKG_VERSION")));
        out
    };
    let after = normal_jumps(&out);
    Ok(Smoothed {
        model: out,
        report: SmoothReport {
            before,
            after,
            objective_before,
            objective_after,
            sweeps,
            facets,
            samples: pairs.len(),
            free_faces: free.len(),
            block_added: layer.block_added,
            seconds: start.elapsed().as_secs_f64(),
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layered::faces_of;
    use crate::{fit, FitOptions, Preset};

    fn valid(model: &Model) -> bool {
        ism_validate::validate(model, &ism_validate::Options::default()).verdict
            == ism_validate::Verdict::Valid
    }

    fn check(model: &Model, options: &SmoothOptions) -> SmoothReport {
        let s = smooth(model, options).unwrap();
        let r = s.report;
        assert!(valid(&s.model));
        // Never increases the objective: each sweep's total is at most the previous one.
        let mut last = r.objective_before;
        for &x in &r.sweeps {
            assert!(x <= last * (1.0 + 1e-12) + 1e-15, "{r:?}");
            last = x;
        }
        assert!(r.objective_after <= r.objective_before);
        r
    }

    #[test]
    fn fitted_circle_gets_smoother() {
        let circle = Preset::find("circle").unwrap();
        let mut o = FitOptions::new(circle.domain);
        o.resolution = 6;
        o.tolerance = 1e-3;
        let model = fit(
            &circle.expression().unwrap(),
            &o,
            &ism_format::Progress::none(),
        )
        .unwrap()
        .to_model("circle");
        let r = check(&model, &SmoothOptions::default());
        assert!(!r.block_added);
        let (b, a) = (r.before.unwrap(), r.after.unwrap());
        assert!(a.max < 0.5 * b.max && a.mean < 0.5 * b.mean, "{r:?}");
        // Smoothing trades position for smoothness (|g|/|∇g| max 6.1e-4 → 2.3e-3 at α = 1e-3 in
        // our runs since the fit's vertex values are first-order distances and its crossing
        // edges can go unrecorded; 6.7e-4 → 1.3e-3 before); a larger α stays nearer the input
        // (1.1e-3 at α = 0.1).
        let g = circle.expression().unwrap();
        let distance = |alpha: f64| {
            let s = smooth(
                &model,
                &SmoothOptions {
                    alpha,
                    ..SmoothOptions::default()
                },
            )
            .unwrap();
            let indexed = ism_format::IndexedModel::for_evaluation(s.model).unwrap();
            let d = crate::fit::dense_error(&g, &indexed).unwrap().max;
            (d, s.report.after.unwrap().max)
        };
        let indexed = ism_format::IndexedModel::for_evaluation(model.clone()).unwrap();
        let input = crate::fit::dense_error(&g, &indexed).unwrap().max;
        let (d_small, _) = distance(1e-3);
        let (d_large, jump_large) = distance(0.1);
        assert!(
            d_large < d_small && d_small < 4.0 * input,
            "{input} {d_small} {d_large}"
        );
        assert!(jump_large < 0.5 * b.max);
    }

    #[test]
    fn sphere_example_gets_smoother() {
        let text = include_str!("../../../spec/examples/sphere.ism.json");
        let model = ism_format::io::from_slice(text.as_bytes()).unwrap().model;
        let r = check(
            &model,
            &SmoothOptions {
                iterations: 2,
                ..SmoothOptions::default()
            },
        );
        assert!(r.block_added);
        let (b, a) = (r.before.unwrap(), r.after.unwrap());
        assert!(a.mean < b.mean && a.max <= b.max, "{r:?}");
    }

    #[test]
    fn measure_matches_the_validator_on_both_sides() {
        // Our objective's samples are ISM-401's: with no change (0 sweeps) the per-sample angles
        // bound the validator's maximum from both sides.
        let circle = Preset::find("circle").unwrap();
        let mut o = FitOptions::new(circle.domain);
        o.resolution = 4;
        let model = fit(
            &circle.expression().unwrap(),
            &o,
            &ism_format::Progress::none(),
        )
        .unwrap()
        .to_model("circle");
        let s = smooth(
            &model,
            &SmoothOptions {
                iterations: 0,
                alpha: 0.0,
            },
        )
        .unwrap();
        let b = s.report.before.unwrap();
        // The same map, re-encoded (logits → points): equal up to rounding.
        let a = s.report.after.unwrap();
        assert_eq!(a.facets, b.facets);
        assert!((a.max - b.max).abs() <= 1e-9 * b.max, "{a:?} vs {b:?}");
        assert!((a.mean - b.mean).abs() <= 1e-9 * b.mean, "{a:?} vs {b:?}");
        assert_eq!(b.facets, s.report.facets);
        // |n − n′|² = 2 − 2 cos θ per sample; the largest sample term gives the max angle.
        let layer = Layered::new(&model).unwrap();
        let (_, pairs) = facet_pairs(&layer).unwrap();
        let mut worst = 0.0f64;
        for p in &pairs {
            let ja = Jet::new(&layer.map, &layer.frames()[p.a.cell].ids);
            let jb = Jet::new(&layer.map, &layer.frames()[p.b.cell].ids);
            let na = layer.normal(&ja, &p.a).unwrap().1;
            let nb = layer.normal(&jb, &p.b).unwrap().1;
            worst = worst.max(crate::layered::angle_deg(&na, &nb));
        }
        assert!((worst - b.max).abs() < 1e-6, "{worst} vs {}", b.max);
    }

    #[test]
    fn negative_alpha_is_an_error() {
        let text = include_str!("../../../spec/examples/circle-curved.ism.json");
        let model = ism_format::io::from_slice(text.as_bytes()).unwrap().model;
        let o = SmoothOptions {
            alpha: -1.0,
            ..SmoothOptions::default()
        };
        assert!(matches!(smooth(&model, &o), Err(EditError::Model(_))));
        let s = smooth(&model, &SmoothOptions::default()).unwrap();
        assert!(valid(&s.model));
    }

    mod properties {
        use super::*;
        use crate::complex::Complex;
        use proptest::prelude::*;

        /// A 3×3 Kuhn grid with the given values (pushed away from 0) and random solitary points.
        fn random_model(values: &[f64], logits: &[f64]) -> Model {
            let complex = Complex::kuhn(&[0.0, 1.0, 0.0, 1.0], &[3, 3]);
            let mut model = Model::new(2);
            model.vertices = complex.points().to_vec();
            model.simplices = complex.compact_cells();
            model.values = values
                .iter()
                .map(|&v| {
                    if v.abs() < 0.05 {
                        0.05f64.copysign(v)
                    } else {
                        v
                    }
                })
                .collect();
            let mut layer = Layered::new(&model).unwrap();
            let mut faces: Vec<Vec<u32>> = model.simplices.chunks(3).flat_map(faces_of).collect();
            faces.sort();
            faces.dedup();
            for (k, f) in faces.iter().enumerate() {
                let l: Vec<f64> = (0..f.len())
                    .map(|i| logits[(3 * k + i) % logits.len()])
                    .collect();
                layer.map.set_logits(f, &l);
            }
            layer.to_model()
        }

        proptest! {
            #![proptest_config(ProptestConfig::with_cases(24))]

            #[test]
            fn smoothing_never_increases_the_objective_nor_invalidates(
                values in prop::collection::vec(-1.0f64..1.0, 16),
                logits in prop::collection::vec(-3.0f64..3.0, 32),
                alpha in prop_oneof![Just(0.0), 1e-4f64..1.0],
            ) {
                let model = random_model(&values, &logits);
                prop_assume!(valid(&model));
                let s = smooth(&model, &SmoothOptions { iterations: 2, alpha }).unwrap();
                let r = &s.report;
                let mut last = r.objective_before;
                for &x in &r.sweeps {
                    prop_assert!(x <= last * (1.0 + 1e-12) + 1e-15, "{:?}", r);
                    last = x;
                }
                prop_assert!(r.objective_after <= r.objective_before * (1.0 + 1e-12) + 1e-15);
                prop_assert!(valid(&s.model));
            }
        }
    }
}
