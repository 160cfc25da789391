//! The layered map `X = S ∘ Y⁻¹` that Hermite fitting ([`crate::hermite`]) and smoothing
//! ([`crate::smooth`]) optimize: a model split into a stratified Bézier block `Y` (applied first,
//! stored parametric, its solitary points kept as softmax logits) and the kept stages `S` after it
//! ([`Layered`]); per simplex, the block with its exact Jacobian ([`Jet`]) and the normal of the
//! shape under it ([`Layered::normal`]). The per-face optimizer both use is [`crate::lm`]; the
//! error both report is [`EditError`].

use std::collections::{HashMap, HashSet};

use ism_format::indexed::simplex_faces;
use ism_format::model::{Direction, Model, Stage, StageKind};
use ism_format::progress::Cancelled;
use ism_format::IndexedModel;
use ism_geom::linalg;
use ism_geom::stage::{reduce, LocalMap};
use ism_geom::{Bary, Mat, MAX_VARS};

use crate::strata::{softmax, StratifiedMap, LOGIT_BOUND};

/// Errors of Hermite fitting and smoothing, saying where.
#[derive(Debug, thiserror::Error)]
pub enum EditError {
    /// The handles file is not valid JSON of the documented shape.
    #[error("handles file: {0}")]
    Json(String),
    /// A handle is inconsistent with the complex.
    #[error("handle {index} (edge {edge:?}): {message}")]
    Handle {
        /// Position in `handles`.
        index: usize,
        /// The edge as given.
        edge: [u32; 2],
        /// What is wrong.
        message: String,
    },
    /// The complex or model is unusable (missing or inconsistent arrays, a degenerate simplex).
    #[error("model: {0}")]
    Model(String),
    /// The model breaks structural rules (spec §2–5): the reader's diagnostics, each with its
    /// rule and place.
    #[error("model: {}", crate::join_diagnostics(.0))]
    Structure(Vec<ism_format::Diagnostic>),
    /// The kept stages cannot be indexed for evaluation.
    #[error("the kept stages do not index")]
    Index(#[source] ism_format::Error),
    /// The math kernel refused the model.
    #[error("model does not evaluate")]
    Geom(#[from] ism_geom::GeomError),
    /// The caller cancelled the call through its [`ism_format::Progress`].
    #[error(transparent)]
    Cancelled(#[from] Cancelled),
}

/// Structural errors of a model (up to five) as one [`EditError::Structure`].
pub(crate) fn check_structure(model: &Model) -> Result<(), EditError> {
    let errors = crate::structural_errors(model);
    if errors.is_empty() {
        Ok(())
    } else {
        Err(EditError::Structure(errors))
    }
}

/// A model split into an optimizable stratified block `Y` (applied first, stored parametric) and
/// the kept stages `S` after it.
#[derive(Clone, Debug)]
pub struct Layered {
    /// The model with only the kept stages `S` in `stages`.
    pub base: Model,
    /// The block.
    pub map: StratifiedMap,
    /// Whether the block is new (the input's first stages were not a stratified block).
    pub block_added: bool,
    pub(crate) frames: Vec<Frame>,
}

/// Per top simplex: ids, signed values, inverse edge matrix, kept stages.
#[derive(Clone, Debug)]
pub(crate) struct Frame {
    pub(crate) ids: Vec<u32>,
    /// `f − c` per local vertex.
    pub(crate) f: Bary,
    /// `∂w_l/∂p_x` (reduced barycentric by Cartesian).
    ainv: Mat,
    pub(crate) outer: LocalMap,
}

/// Whether stage `k` (0-based, stratum `k + 1`) of `stages` has the stratified form [`crate::fit`]
/// writes: parametric Bézier of degree `k + 2` whose records are solitary points of `(k + 1)`-faces.
fn is_stratum(stage: &Stage, k: usize) -> bool {
    let j = k + 1;
    stage.kind == StageKind::Bezier
        && stage.direction == Direction::Parametric
        && stage.degree as usize == j + 1
        && stage.vertex_maps.is_empty()
        && stage
            .faces
            .iter()
            .all(|r| r.face.len() == j + 1 && r.points.len() == j + 1 && r.weights.is_empty())
}

/// Logits of a stored point (`ln`, shifted to centre their range), if the softmax can represent
/// it within `±LOGIT_BOUND` (else the block is not taken over). Points written from bounded logits
/// come back within rounding of the bound, hence the slack.
fn logits_of(point: &[f64]) -> Option<Vec<f64>> {
    const SLACK: f64 = 1e-9;
    if point.iter().any(|&x| !(x > 0.0 && x.is_finite())) {
        return None;
    }
    let l: Vec<f64> = point.iter().map(|x| x.ln()).collect();
    let hi = l.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let lo = l.iter().copied().fold(f64::INFINITY, f64::min);
    let mid = 0.5 * (hi + lo);
    (hi - lo <= 2.0 * LOGIT_BOUND * (1.0 + SLACK)).then(|| {
        l.iter()
            .map(|x| (x - mid).clamp(-LOGIT_BOUND, LOGIT_BOUND))
            .collect()
    })
}

impl Layered {
    /// Splits `model`: if its first `n` stages are a stratified block (the form `ism fit` writes)
    /// they become the optimizable block; otherwise an identity block is put in front of all its
    /// stages.
    ///
    /// # Errors
    /// [`EditError::Structure`] for structural errors; [`EditError::Model`] for a dimension other
    /// than 2 and 3; [`EditError::Index`] or [`EditError::Geom`] if a stage does not evaluate.
    pub fn new(model: &Model) -> Result<Layered, EditError> {
        check_structure(model)?;
        let n = model.dim();
        if !(2..=3).contains(&n) {
            return Err(EditError::Model(format!(
                "dimension {n}: only 2 and 3 are supported"
            )));
        }
        let mut map = StratifiedMap::new(n);
        let mut taken = model.stages.len() >= n
            && model.stages[..n]
                .iter()
                .enumerate()
                .all(|(k, s)| is_stratum(s, k));
        if taken {
            'outer: for stage in &model.stages[..n] {
                for r in &stage.faces {
                    match logits_of(r.points) {
                        Some(l) => map.set_logits(r.face, &l),
                        None => {
                            taken = false;
                            break 'outer;
                        }
                    }
                }
            }
        }
        if !taken {
            map = StratifiedMap::new(n);
        }
        let mut base = model.clone();
        if taken {
            base.stages.drain(..n);
        }
        // The kept stages are read through the indexed model: the topology names each simplex's
        // faces, so no face key is hashed per simplex. `model` passed the structural check above,
        // and dropping whole stages keeps it passing.
        let indexed = IndexedModel::for_evaluation(base).map_err(EditError::Index)?;
        let mut frames = Vec::with_capacity(indexed.num_simplices());
        for s in 0..indexed.num_simplices() {
            let ids = indexed.simplex(s).to_vec();
            let outer = LocalMap::from_indexed(&indexed, s)?;
            let mut f = [0.0; MAX_VARS];
            for (i, &v) in ids.iter().enumerate() {
                f[i] = indexed.values[v as usize] - indexed.level;
            }
            let v0 = indexed.vertex(ids[0] as usize);
            let mut a = [[0.0; MAX_VARS]; MAX_VARS];
            for c in 0..n {
                let vc = indexed.vertex(ids[c + 1] as usize);
                for r in 0..n {
                    a[r][c] = vc[r] - v0[r];
                }
            }
            let ainv = linalg::inverse(n, &a).ok_or_else(|| {
                EditError::Model(format!("simplex {s} is degenerate (zero volume)"))
            })?;
            frames.push(Frame {
                ids,
                f,
                ainv,
                outer,
            });
        }
        Ok(Layered {
            base: indexed.into_model(),
            map,
            block_added: !taken,
            frames,
        })
    }

    /// Space dimension.
    pub fn dim(&self) -> usize {
        self.base.dim()
    }

    pub(crate) fn frames(&self) -> &[Frame] {
        &self.frames
    }

    /// The model: the block's strata (faces of the complex only), then the kept stages.
    pub fn to_model(&self) -> Model {
        let mut faces = HashSet::new();
        for fr in &self.frames {
            for f in faces_of(&fr.ids) {
                faces.insert(f);
            }
        }
        let mut model = self.base.clone();
        let mut stages = self.map.to_stages(|f| faces.contains(f));
        stages.append(&mut model.stages);
        model.stages = stages;
        model
    }

    /// A sample of `O` in simplex `s` at function-side coordinates `u` (on `θ_σ`): its preimage
    /// `z = S⁻¹(u)` and the row `(∂F/∂z)` (reduced), both independent of the block.
    pub(crate) fn sample(&self, s: usize, u: &Bary) -> Option<Sample> {
        let fr = &self.frames[s];
        let m = fr.ids.len();
        let n = m - 1;
        let (z, js) = if fr.outer.stages().is_empty() {
            (*u, ism_geom::stage::identity_mat(n))
        } else {
            let inv = fr.outer.inverse(u);
            if !inv.converged {
                return None;
            }
            let (_, j) = fr.outer.jacobian(&inv.w);
            (inv.w, j?)
        };
        let mut a = [0.0; 3];
        for (l, al) in a.iter_mut().enumerate().take(n) {
            *al = (0..n).map(|k| (fr.f[k + 1] - fr.f[0]) * js[k][l]).sum();
        }
        Some(Sample { cell: s, z, a })
    }

    /// Point `p` and unit normal of `O` at a sample under the block `jet` of its cell.
    pub(crate) fn normal(&self, jet: &Jet, smp: &Sample) -> Option<([f64; 3], [f64; 3])> {
        let fr = &self.frames[smp.cell];
        let m = fr.ids.len();
        let n = m - 1;
        let (w, h) = jet.eval_jacobian(&smp.z);
        let r = reduce(m, &h);
        // ∇_w F = a · J_Y⁻¹, i.e. J_Yᵀ x = aᵀ.
        let mut rt = [[0.0; MAX_VARS]; MAX_VARS];
        for i in 0..n {
            for j in 0..n {
                rt[i][j] = r[j][i];
            }
        }
        let mut b = [0.0; MAX_VARS];
        b[..n].copy_from_slice(&smp.a[..n]);
        let dw = linalg::solve(n, &rt, &b)?;
        let mut g = [0.0; 3];
        for (x, gx) in g.iter_mut().enumerate().take(n) {
            *gx = (0..n).map(|l| dw[l] * fr.ainv[l][x]).sum();
        }
        let norm = g.iter().map(|x| x * x).sum::<f64>().sqrt();
        if !(norm > 0.0 && norm.is_finite()) {
            return None;
        }
        let mut p = [0.0; 3];
        for (i, &v) in fr.ids.iter().enumerate() {
            for (x, px) in p.iter_mut().enumerate().take(n) {
                *px += w[i] * self.base.vertex(v as usize)[x];
            }
        }
        Some((p, [g[0] / norm, g[1] / norm, g[2] / norm]))
    }

    /// The simplices containing all of `face` (any order).
    /// The faces whose solitary points may move around the cells in `by_cell` (every face of those
    /// cells except the sign-changing edges, whose points hold the crossings), sorted, and for
    /// each the indices (sorted, distinct) of the terms in `by_cell` of the cells around it.
    pub(crate) fn free_blocks(
        &self,
        by_cell: &HashMap<usize, Vec<usize>>,
    ) -> (Vec<Vec<u32>>, Vec<Vec<usize>>) {
        let mut free: Vec<Vec<u32>> = {
            let mut set = HashSet::new();
            for &s in by_cell.keys() {
                for f in faces_of(&self.frames[s].ids) {
                    if !(f.len() == 2 && self.is_crossing_edge(f[0], f[1])) {
                        set.insert(f);
                    }
                }
            }
            set.into_iter().collect()
        };
        free.sort();
        let blocks = free
            .iter()
            .map(|f| {
                let mut ks: Vec<usize> = self
                    .cells_with(f)
                    .into_iter()
                    .filter_map(|s| by_cell.get(&s))
                    .flatten()
                    .copied()
                    .collect();
                ks.sort_unstable();
                ks.dedup();
                ks
            })
            .collect();
        (free, blocks)
    }

    pub(crate) fn cells_with(&self, face: &[u32]) -> Vec<usize> {
        (0..self.frames.len())
            .filter(|&s| face.iter().all(|v| self.frames[s].ids.contains(v)))
            .collect()
    }

    pub(crate) fn is_crossing_edge(&self, a: u32, b: u32) -> bool {
        let c = self.base.level;
        (self.base.values[a as usize] - c) * (self.base.values[b as usize] - c) < 0.0
    }
}

/// A sample of `O` for the optimizers (see [`Layered::sample`]).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Sample {
    pub(crate) cell: usize,
    pub(crate) z: Bary,
    pub(crate) a: [f64; 3],
}

/// Every face of dimension ≥ 1 of a simplex, as sorted ids, in the order of
/// [`simplex_faces`] (the fitters' complexes change as they run, so they are not indexed models).
pub(crate) fn faces_of(ids: &[u32]) -> Vec<Vec<u32>> {
    simplex_faces(ids, 2).map(|f| f.ids().to_vec()).collect()
}

#[derive(Clone, Copy, Debug)]
struct Term {
    positions: [usize; MAX_VARS],
    len: usize,
    delta: [f64; MAX_VARS],
}

/// The block on one simplex with its exact Jacobian. Hand-written beside
/// [`crate::strata::LocalStrata`] (which evaluates only): the normals need `DY`, and finite
/// differences of it inside the optimizer's own finite differences would be too noisy. The tests
/// check both evaluations agree and the Jacobian against differences.
#[derive(Clone, Debug)]
pub(crate) struct Jet {
    m: usize,
    strata: Vec<Vec<Term>>,
}

impl Jet {
    pub(crate) fn new(map: &StratifiedMap, cell: &[u32]) -> Jet {
        let m = cell.len();
        let mut strata = vec![Vec::new(); m.saturating_sub(1)];
        for face in simplex_faces(cell, 2) {
            let len = face.len();
            let logits = map.logits(face.ids());
            if logits.iter().all(|&l| l == logits[0]) {
                continue; // the fixed centre: no term
            }
            let point = softmax(&logits);
            let factorial: f64 = (1..=len).map(|x| x as f64).product();
            let mut term = Term {
                positions: [0; MAX_VARS],
                len,
                delta: [0.0; MAX_VARS],
            };
            for (slot, &p) in face.positions().iter().enumerate() {
                term.positions[slot] = usize::from(p);
                term.delta[slot] = (point[slot] - 1.0 / len as f64) * factorial;
            }
            strata[len - 2].push(term);
        }
        Jet { m, strata }
    }

    /// `Y(u)` and its homogeneous Jacobian `∂Y_i/∂u_j` (`m × m`).
    pub(crate) fn eval_jacobian(&self, u: &Bary) -> (Bary, Mat) {
        let m = self.m;
        let mut v = *u;
        let mut acc = ism_geom::stage::identity_mat(m);
        for terms in self.strata.iter().rev() {
            let mut out = v;
            let mut d = ism_geom::stage::identity_mat(m);
            for t in terms {
                let pos = &t.positions[..t.len];
                let mut b = 1.0;
                for &p in pos {
                    b *= v[p];
                }
                for (k, &p) in pos.iter().enumerate() {
                    out[p] += t.delta[k] * b;
                }
                for (qi, &q) in pos.iter().enumerate() {
                    let partial: f64 = pos
                        .iter()
                        .enumerate()
                        .filter(|&(ri, _)| ri != qi)
                        .map(|(_, &r)| v[r])
                        .product();
                    for (k, &p) in pos.iter().enumerate() {
                        d[p][q] += t.delta[k] * partial;
                    }
                }
            }
            // As the evaluator does: keep exact zeros on faces (rounding may give −1e−17).
            for x in out.iter_mut().take(m) {
                if *x < 0.0 {
                    *x = 0.0;
                }
            }
            acc = linalg::mul(m, &d, &acc);
            v = out;
        }
        (v, acc)
    }
}

/// Angle in degrees between unit vectors.
pub(crate) fn angle_deg(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    let dot: f64 = (0..3).map(|i| a[i] * b[i]).sum();
    dot.clamp(-1.0, 1.0).acos().to_degrees()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jet_agrees_with_the_strata_evaluator_and_its_differences() {
        let mut map = StratifiedMap::new(3);
        let cell = [7u32, 2, 9, 4];
        map.set_logits(&[2, 7], &[0.0, 1.0]);
        map.set_logits(&[4, 9], &[0.4, -0.3]);
        map.set_logits(&[2, 4, 9], &[0.3, -0.2, 0.5]);
        map.set_logits(&[2, 4, 7, 9], &[0.3, -0.2, 0.5, 1.0]);
        let jet = Jet::new(&map, &cell);
        let local = map.local(&cell);
        // Interior points only: the evaluator clamps negative coordinates, so differences across a
        // face would be one-sided.
        for u in [
            [0.1, 0.2, 0.3, 0.4],
            [0.6, 0.05, 0.1, 0.25],
            [0.25, 0.25, 0.25, 0.25],
        ] {
            let (w, h) = jet.eval_jacobian(&u);
            let expect = local.eval(&u);
            for k in 0..4 {
                assert!((w[k] - expect[k]).abs() < 1e-14);
            }
            // Central differences in each (homogeneous) variable.
            for q in 0..4 {
                let e = 1e-6;
                let (mut up, mut dn) = (u, u);
                up[q] += e;
                dn[q] -= e;
                let (a, _) = jet.eval_jacobian(&up);
                let (b, _) = jet.eval_jacobian(&dn);
                for p in 0..4 {
                    let fd = (a[p] - b[p]) / (2.0 * e);
                    assert!(
                        (fd - h[p][q]).abs() < 1e-7,
                        "∂{p}/∂{q}: {fd} vs {}",
                        h[p][q]
                    );
                }
            }
        }
    }
}
