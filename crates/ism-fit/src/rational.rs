//! The rational stage the fitter optimizes beside the strata (`spec/mathematics.md` §3.3, Mello & Velho 2009, §6).
//!
//! A degree-2 rational map whose control points are all fixed at `I/2` and whose weights are free:
//! `R(u)ᵢ = (qᵢ uᵢ² + Σ_{j≠i} q_{ij} uᵢ uⱼ) / (Σᵢ qᵢ uᵢ² + 2 Σ_{i<j} q_{ij} uᵢ uⱼ)`, with `qᵢ` the
//! weight of vertex `i` (index `2eᵢ`) and `q_{ij}` that of edge `ij` (index `eᵢ + eⱼ`). With every
//! control point fixed, every choice of positive weights is a simplicial diffeomorphism (Thm. 6.4),
//! so the stage is valid by construction; weights are kept as logarithms, `q = exp(β)`.
//!
//! Weights are keyed by face (sorted global vertex ids), so the simplices around a face read the
//! same numbers and the map is continuous across faces. The model stores the stage as the **last**
//! stage, `direction: parametric`, so it is the first map applied to `u` on the linear patch:
//! `X⁻¹ = G₁ ∘ … ∘ G_n ∘ R`. On an edge `ab` only `q_a, q_b, q_ab` act ([`RationalWeights::edge`]),
//! which lets the fitter keep each crossing exact by re-solving the edge stratum's point.
//!
//! ```
//! use ism_fit::rational::RationalWeights;
//!
//! let mut r = RationalWeights::new(2);
//! r.set_log_weight(&[3], 0.5);
//! r.set_log_weight(&[3, 8], -0.4);
//! let local = r.local(&[8, 3, 5]);
//! let w = local.eval(&[0.2, 0.3, 0.5, 0.0]);
//! assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-15);
//! // The edge map agrees with the simplex map on that edge (t = weight of vertex 8, the second id).
//! let on_edge = local.eval(&[0.4, 0.6, 0.0, 0.0]);
//! assert!((on_edge[0] - r.edge(3, 8, 0.4)).abs() < 1e-15);
//! ```

use std::collections::HashMap;

use ism_format::model::{Direction, FaceRecord, Stage, StageKind};

/// Bound on each log-weight: weights stay within `[e⁻³, e³] ≈ [0.05, 20]`. Any positive weights
/// give a diffeomorphism, but a ratio of 400 between neighbouring weights already pulls a patch
/// almost onto a vertex; beyond it the fitter gains nothing and the sampler's bounds loosen.
pub const LOG_WEIGHT_BOUND: f64 = 3.0;

/// Largest number of barycentric coordinates (`n ≤ 3`).
const M: usize = 4;

/// Log-weights of vertices and edges, keyed by sorted global ids; unset faces have weight 1.
#[derive(Clone, Debug, Default)]
pub struct RationalWeights {
    dim: usize,
    log: HashMap<Vec<u32>, f64>,
}

/// The rational map on one top simplex, in its local vertex order.
#[derive(Clone, Copy, Debug)]
pub struct LocalRational {
    m: usize,
    /// `q[i][i]` vertex weights, `q[i][j] = q[j][i]` edge weights.
    q: [[f64; M]; M],
    identity: bool,
}

impl LocalRational {
    /// The identity on `m` coordinates.
    pub fn identity(m: usize) -> LocalRational {
        LocalRational {
            m,
            q: [[1.0; M]; M],
            identity: true,
        }
    }

    /// Whether every weight is 1 (the map is the identity).
    pub fn is_identity(&self) -> bool {
        self.identity
    }

    /// `R(u)`. A zero coordinate stays exactly zero, so faces stay in place.
    pub fn eval(&self, u: &[f64; M]) -> [f64; M] {
        if self.identity {
            return *u;
        }
        let m = self.m;
        let mut num = [0.0; M];
        for i in 0..m {
            if u[i] == 0.0 {
                continue;
            }
            let s: f64 = self.q[i][..m].iter().zip(&u[..m]).map(|(q, x)| q * x).sum();
            num[i] = u[i] * s;
        }
        // Σᵢ numᵢ = Σᵢ qᵢuᵢ² + 2Σ_{i<j} q_{ij}uᵢuⱼ: the denominator, positive inside the simplex.
        let den: f64 = num[..m].iter().sum();
        let mut out = [0.0; M];
        for i in 0..m {
            out[i] = num[i] / den;
        }
        out
    }
}

impl RationalWeights {
    /// All weights 1 (the identity) in dimension `n`.
    pub fn new(dim: usize) -> RationalWeights {
        RationalWeights {
            dim,
            log: HashMap::new(),
        }
    }

    /// The log-weight of `face` (a sorted vertex or edge), 0 if unset.
    pub fn log_weight(&self, face: &[u32]) -> f64 {
        self.log.get(face).copied().unwrap_or(0.0)
    }

    /// Sets the log-weight of `face` (sorted ids, 1 or 2 of them), clamped to
    /// `±LOG_WEIGHT_BOUND`.
    pub fn set_log_weight(&mut self, face: &[u32], beta: f64) {
        debug_assert!(face.len() == 1 || face.len() == 2);
        self.log.insert(
            face.to_vec(),
            beta.clamp(-LOG_WEIGHT_BOUND, LOG_WEIGHT_BOUND),
        );
    }

    /// Keeps only the faces for which `keep` is true.
    pub fn retain(&mut self, mut keep: impl FnMut(&[u32]) -> bool) {
        self.log.retain(|f, _| keep(f));
    }

    /// Number of faces with a weight other than 1.
    pub fn num_faces(&self) -> usize {
        self.log.values().filter(|&&b| b != 0.0).count()
    }

    /// The map restricted to edge `a < b`: `t` (the weight of `b`) ↦ the weight of `b` after `R`.
    pub fn edge(&self, a: u32, b: u32, t: f64) -> f64 {
        let qa = self.log_weight(&[a]).exp();
        let qb = self.log_weight(&[b]).exp();
        let qab = self.log_weight(&[a, b]).exp();
        let s = 1.0 - t;
        let nb = t * (qb * t + qab * s);
        let na = s * (qa * s + qab * t);
        nb / (na + nb)
    }

    /// The map on the simplex with vertex ids `cell` (local order).
    pub fn local(&self, cell: &[u32]) -> LocalRational {
        let m = cell.len();
        let mut local = LocalRational::identity(m);
        for i in 0..m {
            for j in i..m {
                let beta = if i == j {
                    self.log_weight(&[cell[i]])
                } else {
                    let (a, b) = (cell[i].min(cell[j]), cell[i].max(cell[j]));
                    self.log_weight(&[a, b])
                };
                if beta != 0.0 {
                    local.identity = false;
                    let q = beta.exp();
                    local.q[i][j] = q;
                    local.q[j][i] = q;
                }
            }
        }
        local
    }

    /// The stage: `kind: rational`, degree 2, parametric, one record per vertex or edge whose
    /// weight is not 1 and for which `exists` is true (records sorted by face); `None` when no
    /// record is left (the identity needs no stage).
    pub fn to_stage(&self, exists: impl Fn(&[u32]) -> bool) -> Option<Stage> {
        let mut faces: Vec<FaceRecord> = self
            .log
            .iter()
            .filter(|(f, &b)| b != 0.0 && exists(f))
            .map(|(f, &b)| FaceRecord {
                face: f.clone(),
                points: if f.len() == 1 {
                    vec![1.0]
                } else {
                    vec![0.5, 0.5]
                },
                weights: vec![b.exp()],
            })
            .collect();
        if faces.is_empty() {
            return None;
        }
        faces.sort_by(|a, b| a.face.cmp(&b.face));
        let mut stage = Stage::identity(StageKind::Rational, 2);
        stage.direction = Direction::Parametric;
        stage.name = Some(format!("rational weights (degree 2, {}D)", self.dim));
        stage.faces = faces.into();
        Some(stage)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identity_until_set() {
        let r = RationalWeights::new(3);
        let u = [0.1, 0.2, 0.3, 0.4];
        assert!(r.local(&[4, 1, 7, 2]).is_identity());
        assert_eq!(r.local(&[4, 1, 7, 2]).eval(&u), u);
    }

    #[test]
    fn matches_the_bernstein_definition() {
        // R(u) = Σ q_I (I/2) B_I(u) / Σ q_I B_I(u), written out term by term.
        let mut r = RationalWeights::new(3);
        r.set_log_weight(&[1], 0.7);
        r.set_log_weight(&[7], -1.1);
        r.set_log_weight(&[1, 4], 0.4);
        r.set_log_weight(&[2, 7], -2.0);
        r.set_log_weight(&[1, 2], 1.9);
        let cell = [4u32, 1, 7, 2];
        let local = r.local(&cell);
        let u = [0.15, 0.25, 0.35, 0.25];
        let q = |i: usize, j: usize| -> f64 {
            if i == j {
                r.log_weight(&[cell[i]]).exp()
            } else {
                let (a, b) = (cell[i].min(cell[j]), cell[i].max(cell[j]));
                r.log_weight(&[a, b]).exp()
            }
        };
        let mut num = [0.0; 4];
        let mut den = 0.0;
        for i in 0..4 {
            for j in i..4 {
                // B_{eᵢ+eⱼ} = 2uᵢuⱼ (i ≠ j) or uᵢ² (i = j); control point (eᵢ + eⱼ)/2.
                let b = if i == j {
                    u[i] * u[i]
                } else {
                    2.0 * u[i] * u[j]
                };
                den += q(i, j) * b;
                num[i] += q(i, j) * b * 0.5;
                num[j] += q(i, j) * b * 0.5;
            }
        }
        let w = local.eval(&u);
        for i in 0..4 {
            assert!((w[i] - num[i] / den).abs() < 1e-15, "{w:?}");
        }
        // Vertices and faces stay in place.
        assert_eq!(local.eval(&[0.0, 1.0, 0.0, 0.0]), [0.0, 1.0, 0.0, 0.0]);
        assert_eq!(local.eval(&[0.0, 0.5, 0.5, 0.0])[0], 0.0);
    }

    #[test]
    fn larger_weights_attract() {
        let mut r = RationalWeights::new(2);
        r.set_log_weight(&[5], 1.0);
        // The weight of vertex 5 after the map exceeds its weight before: points move toward 5.
        assert!(r.edge(2, 5, 0.3) > 0.3);
        assert!(r.edge(5, 9, 0.3) < 0.3);
        // Clamped to the bound.
        r.set_log_weight(&[5], 50.0);
        assert_eq!(r.log_weight(&[5]), LOG_WEIGHT_BOUND);
    }

    #[test]
    fn stage_records_hold_one_weight_each() {
        let mut r = RationalWeights::new(2);
        r.set_log_weight(&[3], 0.5);
        r.set_log_weight(&[1, 3], -0.5);
        r.set_log_weight(&[1, 2], 0.0);
        let stage = r.to_stage(|_| true).unwrap();
        assert_eq!(stage.kind, StageKind::Rational);
        assert_eq!(stage.faces.len(), 2);
        assert_eq!(stage.faces.record(0).face, [1, 3]);
        assert_eq!(stage.faces.record(0).points, [0.5, 0.5]);
        assert_eq!(stage.faces.record(1).points, [1.0]);
        assert!(r.to_stage(|f| f.len() > 2).is_none());
    }
}
