//! The stratified map the fitter optimizes (`spec/mathematics.md` §3.2, Mello & Velho 2009, §5.4), stored parametric.
//!
//! Stratum `G_j` moves the solitary centre control point of every `j`-face; on a simplex it is the
//! degree-`(j+1)` Bézier map whose only non-fixed points are those centres:
//! `G_j(w) = w + Σ_τ (b_τ − 𝟙_τ/|τ|) · (j+1)! · Π_{i∈τ} w_i`. Every stratum is a simplicial
//! diffeomorphism for every position of its points in their open faces (2D and 3D, Props. 5.6,
//! 5.7, 5.9), so the composition is valid by construction.
//!
//! The fitter works in the parametric direction (Mello & Velho 2009, §9.2): the map `Y` carries the linear
//! patch `θ_σ` onto the curve. The model stores stratum `j` as stage `j − 1` with
//! `direction: parametric`, so `X⁻¹ = Y_0 ∘ Y_1 ∘ … ∘ Y_{n−1}`: the interior stratum acts first
//! on `u` and the edge stratum last. Positions are kept as logits through a softmax, so every
//! stored coordinate is positive and the coordinates of a point sum to 1.
//!
//! This module evaluates only the closed form above, for speed inside the optimizer; the general
//! kernel (`ism-geom`) evaluates the written model, and the tests check the two agree.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hash, Hasher};

use ism_format::indexed::simplex_faces;
use ism_format::model::{Direction, FaceRecord, Stage, StageKind};

use crate::rational::LocalRational;

/// Bound on each logit. Softmax coordinates then stay above `e^{−2·6}/(k+1) ≈ 1.5·10⁻⁶`, so no
/// control point approaches its face's boundary, where the Jacobian determinant would approach 0
/// and certification would need deep subdivision.
pub const LOGIT_BOUND: f64 = 6.0;

/// Largest number of barycentric coordinates (`n ≤ 3`).
const M: usize = 4;

/// The lattice the fitter's control points lie on: every coordinate a multiple of
/// `1 / POINT_LATTICE` = 2⁻²⁴, the coordinates of a point summing to 1 exactly. The structured
/// encoding (spec `ism-format.md` §7.4.3) then stores a point in 3 bytes per free coordinate
/// instead of 8 per coordinate (issue 17: files smaller than a mesh). Rounding moves a coordinate
/// by at most 2⁻²⁵ ≈ 3·10⁻⁸ of its face — far below any tolerance the fitter is asked for — and
/// the optimizer, the measurement and the written model all use the rounded point, so what is
/// measured is what is written. `LOGIT_BOUND` keeps every softmax coordinate above
/// `1.5·10⁻⁶ ≈ 25 · 2⁻²⁴`, so a rounded coordinate is never 0.
pub const POINT_LATTICE: f64 = 16_777_216.0;

/// Rounds the point `sigma` (positive coordinates summing to 1 within rounding) onto the
/// [`POINT_LATTICE`]: coordinates 1… to the nearest multiple (at least one step), coordinate 0
/// takes the rest, so the sum is 1 exactly (the spec's lattice form keeps `c₀ = 1 − Σ c_j`).
fn onto_lattice(sigma: &mut [f64]) {
    let Some((first, rest)) = sigma.split_first_mut() else {
        return;
    };
    let steps = POINT_LATTICE as i64;
    let mut taken = 0i64;
    for x in rest.iter_mut() {
        let n = (*x * POINT_LATTICE).round().clamp(1.0, POINT_LATTICE - 1.0) as i64;
        taken += n;
        *x = n as f64 / POINT_LATTICE;
    }
    // Never reached with bounded logits (coordinate 0 is ≥ 25 steps); kept so a point is
    // always inside its face: the excess comes off the largest other coordinate.
    while taken > steps - 1 {
        let largest = rest
            .iter_mut()
            .max_by(|a, b| a.total_cmp(b))
            .expect("taken > 0 needs a coordinate");
        let excess = (taken - (steps - 1)).min((*largest * POINT_LATTICE) as i64 - 1);
        *largest -= excess as f64 / POINT_LATTICE;
        taken -= excess;
    }
    *first = (steps - taken) as f64 / POINT_LATTICE;
}

/// Softmax of `logits` (clamped to `±LOGIT_BOUND`).
pub fn softmax(logits: &[f64]) -> Vec<f64> {
    let e: Vec<f64> = logits
        .iter()
        .map(|l| l.clamp(-LOGIT_BOUND, LOGIT_BOUND).exp())
        .collect();
    let s: f64 = e.iter().sum();
    e.iter().map(|x| x / s).collect()
}

/// [`softmax`] rounded onto the [`POINT_LATTICE`] (the point a map with
/// [`StratifiedMap::set_lattice`] stores).
pub fn softmax_on_lattice(logits: &[f64]) -> Vec<f64> {
    let mut sigma = softmax(logits);
    onto_lattice(&mut sigma);
    sigma
}

/// The derivative of a face term's displacement `δ_i = (σ_i − 1/k)·k!` (`σ` the softmax of the
/// `k` logits `θ`, clamped as [`softmax`] clamps them) in the logits: `out[j][i] = ∂δ_i/∂θ_j =
/// k!·σ_i(𝟙_{ij} − σ_j)`, and 0 for a logit at or beyond `+LOGIT_BOUND` or below
/// `−LOGIT_BOUND` (where the clamp holds it: the forward difference the optimizer used there
/// saw no change).
pub fn displacement_derivative(logits: &[f64]) -> [[f64; M]; M] {
    let k = logits.len().min(M);
    let mut e = [0.0; M];
    for (x, l) in e.iter_mut().zip(&logits[..k]) {
        *x = l.clamp(-LOGIT_BOUND, LOGIT_BOUND).exp();
    }
    let s: f64 = e[..k].iter().sum();
    let sigma = e.map(|x| x / s);
    let factorial: f64 = (1..=k).map(|x| x as f64).product();
    let mut out = [[0.0; M]; M];
    for (j, row) in out.iter_mut().enumerate().take(k) {
        if !(-LOGIT_BOUND..LOGIT_BOUND).contains(&logits[j]) {
            continue;
        }
        for (i, x) in row.iter_mut().enumerate().take(k) {
            let kronecker = if i == j { 1.0 } else { 0.0 };
            *x = factorial * sigma[i] * (kronecker - sigma[j]);
        }
    }
    out
}

/// Logits of the edge point that puts a fraction `alpha` of its weight on the second vertex.
pub fn edge_logits(alpha: f64) -> [f64; 2] {
    let a = alpha.clamp(1e-9, 1.0 - 1e-9);
    [0.0, (a / (1.0 - a)).ln().clamp(-LOGIT_BOUND, LOGIT_BOUND)]
}

/// A face's sorted vertex ids as a fixed array (the rest `u32::MAX`) with their number: a key
/// compared and hashed without a heap pointer. Issue 17: with `Vec<u32>` keys and the default
/// SipHash, [`StratifiedMap::local_with`]'s eleven lookups per tetrahedron and their `memcmp`
/// were ~12 % of a torus fit at 3e-4.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct FaceKey {
    ids: [u32; M],
    len: u8,
}

impl FaceKey {
    fn of(face: &[u32]) -> FaceKey {
        assert!(
            (1..=M).contains(&face.len()),
            "a face has 1 to {M} vertices, not {}",
            face.len()
        );
        let mut ids = [u32::MAX; M];
        ids[..face.len()].copy_from_slice(face);
        FaceKey {
            ids,
            len: face.len() as u8,
        }
    }

    fn ids(&self) -> &[u32] {
        &self.ids[..usize::from(self.len)]
    }
}

impl Hash for FaceKey {
    fn hash<H: Hasher>(&self, state: &mut H) {
        // The unused ids are u32::MAX, so the length need not be hashed (equality checks it).
        state.write_u64(u64::from(self.ids[0]) | u64::from(self.ids[1]) << 32);
        state.write_u64(u64::from(self.ids[2]) | u64::from(self.ids[3]) << 32);
    }
}

/// A multiply–rotate hash of [`FaceKey`]'s two words (the Fx hash of rustc, with a final
/// rotation so that the table's bucket index, taken from the low bits, depends on every id).
/// Keys are vertex ids of the fitter's own complex, not untrusted input, so no protection
/// against chosen collisions is needed.
#[derive(Clone, Copy, Debug, Default)]
struct FaceHasher(u64);

impl Hasher for FaceHasher {
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(u64::from(b));
        }
    }

    fn write_u64(&mut self, x: u64) {
        const K: u64 = 0xf135_7aea_2e62_a9c5;
        self.0 = (self.0 ^ x).wrapping_mul(K);
    }

    fn finish(&self) -> u64 {
        self.0.rotate_left(26)
    }
}

/// A stored point: its (clamped) logits and the displacement [`Term::set`] computes from them,
/// computed once when the point is set instead of at every [`StratifiedMap::local_with`].
#[derive(Clone, Copy, Debug)]
struct Stored {
    logits: [f64; M],
    delta: [f64; M],
}

/// Solitary points of every stratum, as logits keyed by the sorted global vertex ids of the face.
/// A face without an entry has its fixed centre (all logits 0).
#[derive(Clone, Debug, Default)]
pub struct StratifiedMap {
    dim: usize,
    logits: HashMap<FaceKey, Stored, BuildHasherDefault<FaceHasher>>,
    /// Whether the stored points are rounded onto the [`POINT_LATTICE`]
    /// ([`StratifiedMap::set_lattice`]).
    lattice: bool,
}

#[derive(Clone, Copy, Debug)]
struct Term {
    positions: [u8; M],
    len: u8,
    /// `(b_τ − 𝟙_τ/|τ|) · |τ|!`, per position in `positions`.
    delta: [f64; M],
}

/// A term that moves nothing (the padding of [`LocalStrata::terms`]).
const NO_TERM: Term = Term {
    positions: [0; M],
    len: 0,
    delta: [0.0; M],
};

/// `(σ − 1/len)·len!` for `σ` the softmax of the `len` logits (clamped), as [`softmax`] computes it:
/// a face term's displacement, what [`LocalStrata::set_displacement`] takes.
pub fn displacement(logits: &[f64]) -> [f64; M] {
    displacement_of(logits, false)
}

/// [`displacement`] of the point rounded onto the [`POINT_LATTICE`] (`lattice` true) or of the
/// smooth softmax, whose derivative [`displacement_derivative`] is (a difference quotient of the
/// rounded one would see its 2⁻²⁴ steps, so the optimizer's trials use the smooth one).
pub fn displacement_of(logits: &[f64], lattice: bool) -> [f64; M] {
    let len = logits.len();
    let mut e = [0.0; M];
    for (x, l) in e.iter_mut().zip(logits) {
        *x = l.clamp(-LOGIT_BOUND, LOGIT_BOUND).exp();
    }
    let s: f64 = e[..len].iter().sum();
    let mut sigma = e.map(|x| x / s);
    if lattice {
        onto_lattice(&mut sigma[..len]);
    }
    let factorial: f64 = (1..=len).map(|x| x as f64).product();
    let mut delta = [0.0; M];
    for (d, x) in delta.iter_mut().zip(&sigma[..len]) {
        *d = (x - 1.0 / len as f64) * factorial;
    }
    delta
}

impl Term {
    /// Sets the displacement from the face's logits (sorted ids, the order of `positions`):
    /// the same numbers as [`softmax`] then `(b − 1/len)·len!`.
    fn set(&mut self, logits: &[f64]) {
        self.delta = displacement(&logits[..usize::from(self.len)]);
    }

    fn positions(&self) -> &[u8] {
        &self.positions[..usize::from(self.len)]
    }
}

/// A term's position as an index of a point's coordinates: below [`M`] by construction, and
/// taken modulo [`M`] so that the compiler drops the bounds checks of the optimizer's innermost
/// loops ([`LocalStrata::apply`] and its derivative).
fn at(p: u8) -> usize {
    usize::from(p) % M
}

/// Where stratum `j`'s terms start in [`LocalStrata::terms`] (index `j − 1`): a tetrahedron has
/// six edges, four triangles and one interior.
const STRATUM_START: [usize; M - 1] = [0, 6, 10];

/// Room for the terms of all strata of a tetrahedron.
const MAX_TERMS: usize = 11;

/// Where a face's term is in a [`LocalStrata`] ([`StratifiedMap::local_with`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Slot {
    stratum: usize,
    term: usize,
}

/// The stratified map on one top simplex, in its local vertex order, optionally after the
/// fitter's rational stage ([`crate::rational`]).
#[derive(Clone, Debug)]
pub struct LocalStrata {
    m: usize,
    /// The terms of stratum `j` are `terms[STRATUM_START[j − 1]..][..count[j − 1]]`, in the
    /// order of [`simplex_faces`] (fixed arrays: the optimizer builds a map per cell and block
    /// run, and three growing vectors each were a good part of its allocations).
    terms: [Term; MAX_TERMS],
    count: [u8; M - 1],
    /// Applied to `u` before the strata.
    pre: Option<LocalRational>,
}

impl LocalStrata {
    /// This map after `r`: `u ↦ Y(R(u))` (the rational stage is stored last, so it acts first).
    pub fn after(mut self, r: LocalRational) -> LocalStrata {
        self.pre = (!r.is_identity()).then_some(r);
        self
    }

    /// Moves the point of the face at `slot` to the one with these logits (clamped, as
    /// [`StratifiedMap::set_logits`] stores them).
    pub fn set_point(&mut self, slot: Slot, logits: &[f64]) {
        self.terms[STRATUM_START[slot.stratum] + slot.term].set(logits);
    }

    /// [`LocalStrata::set_point`] with the point's [`displacement`] computed by the caller: the
    /// same for every cell with the face, so the optimizer computes it once per trial, not once
    /// per cell (its exponentials).
    pub fn set_displacement(&mut self, slot: Slot, delta: &[f64; M]) {
        self.terms[STRATUM_START[slot.stratum] + slot.term].delta = *delta;
    }

    /// Number of strata (`m − 1`, stratum `j` at index `j − 1`).
    fn strata(&self) -> usize {
        self.m.saturating_sub(1)
    }

    /// The terms of the stratum at index `j` (stratum `j + 1`).
    fn stratum(&self, j: usize) -> &[Term] {
        &self.terms[STRATUM_START[j]..][..usize::from(self.count[j])]
    }

    /// `w = Y(u)`: the rational stage if any, then strata `n, n−1, …, 1` in turn.
    pub fn eval(&self, u: &[f64; M]) -> [f64; M] {
        self.eval_after(&self.eval_before(u, None), None)
    }

    /// The part of [`LocalStrata::eval`] that acts before the stratum of `slot` (the rational
    /// stage and the higher strata; all of it for `None`): it does not depend on the slot's
    /// point, so the optimizer computes it once per sample.
    pub fn eval_before(&self, u: &[f64; M], slot: Option<Slot>) -> [f64; M] {
        let v = match &self.pre {
            Some(r) => r.eval(u),
            None => *u,
        };
        let from = slot.map_or(0, |s| s.stratum + 1);
        (from.min(self.strata())..self.strata())
            .rev()
            .fold(v, |v, j| self.apply(self.stratum(j), v))
    }

    /// The rest of [`LocalStrata::eval`] after [`LocalStrata::eval_before`] with the same
    /// `slot`: `eval(u) = eval_after(eval_before(u, slot), slot)`, bit for bit.
    pub fn eval_after(&self, v: &[f64; M], slot: Option<Slot>) -> [f64; M] {
        let to = slot.map_or(0, |s| s.stratum + 1).min(self.strata());
        (0..to)
            .rev()
            .fold(*v, |v, j| self.apply(self.stratum(j), v))
    }

    /// [`LocalStrata::eval_after`] at `v` for the slot's point set to logits `θ` (call
    /// [`LocalStrata::set_point`] with them first), with its exact derivative: `dw[j]` is
    /// `∂w/∂θ_j`, for `j` below `k` (the face's size). `w` is bit for bit `eval_after(v, Some(slot))`.
    /// `delta_derivative` is [`displacement_derivative`]`(θ)` (the same for every sample: the
    /// optimizer computes it once per iteration).
    ///
    /// The slot's term adds `δ_i(θ)·b(v)` to coordinate `p_i`, with `b` the product of the
    /// stratum's input over the face — which does not depend on `θ`; the strata below are then
    /// carried forward with the tangents (product rule on each term). Issue 17: the optimizer's
    /// forward-difference columns were `k` more map passes per Levenberg–Marquardt iteration.
    pub fn eval_after_jacobian(
        &self,
        v: &[f64; M],
        slot: Slot,
        delta_derivative: &[[f64; M]; M],
        dw: &mut [[f64; M]; M],
    ) -> [f64; M] {
        let t = &self.terms[STRATUM_START[slot.stratum] + slot.term];
        let len = usize::from(t.len);
        let mut b = 1.0;
        for &p in t.positions() {
            b *= v[at(p)];
        }
        let mut w = self.apply(self.stratum(slot.stratum), *v);
        let mut tangents = [[0.0; M]; M];
        for (tangent, dd) in tangents.iter_mut().zip(delta_derivative).take(len) {
            for (i, &p) in t.positions().iter().enumerate() {
                let p = at(p);
                // A coordinate that `apply` clamped at 0 stays there.
                if w[p] > 0.0 {
                    tangent[p] = b * dd[i];
                }
            }
        }
        for j in (0..slot.stratum).rev() {
            w = self.apply_tangents(self.stratum(j), w, &mut tangents[..len]);
        }
        dw[..len].copy_from_slice(&tangents[..len]);
        w
    }

    /// [`LocalStrata::apply`] (bit for bit) and its derivative applied to each of `tangents`.
    fn apply_tangents(&self, terms: &[Term], v: [f64; M], tangents: &mut [[f64; M]]) -> [f64; M] {
        let mut out = v;
        let mut inputs = [[0.0; M]; M];
        inputs[..tangents.len()].copy_from_slice(tangents);
        for t in terms {
            let positions = t.positions();
            let mut b = 1.0;
            for &p in positions {
                b *= v[at(p)];
            }
            for (tangent, dv) in tangents.iter_mut().zip(&inputs) {
                // d(Π v_p) = Σ_i dv_{p_i} Π_{l≠i} v_{p_l}.
                let mut db = 0.0;
                for (i, &p) in positions.iter().enumerate() {
                    let mut rest = dv[at(p)];
                    for (l, &q) in positions.iter().enumerate() {
                        if l != i {
                            rest *= v[at(q)];
                        }
                    }
                    db += rest;
                }
                for (d, &p) in t.delta.iter().zip(positions) {
                    tangent[at(p)] += d * db;
                }
            }
            for (k, &p) in positions.iter().enumerate() {
                out[at(p)] += t.delta[k] * b;
            }
        }
        for (x, p) in out.iter_mut().take(self.m).zip(0..) {
            if *x < 0.0 {
                *x = 0.0;
                for tangent in tangents.iter_mut() {
                    tangent[p] = 0.0;
                }
            }
        }
        out
    }

    /// One stratum.
    fn apply(&self, terms: &[Term], v: [f64; M]) -> [f64; M] {
        let mut out = v;
        for t in terms {
            let mut b = 1.0;
            for &p in t.positions() {
                b *= v[at(p)];
            }
            for (k, &p) in t.positions().iter().enumerate() {
                out[at(p)] += t.delta[k] * b;
            }
        }
        // Keep exact zeros exact (a point on a face stays on it) and the sum at 1.
        for x in out.iter_mut().take(self.m) {
            if *x < 0.0 {
                *x = 0.0;
            }
        }
        out
    }
}

/// The terms of every face of ≥ 2 vertices of one cell, stored point or not, in the order of
/// [`simplex_faces`]: [`StratifiedMap::local_with`] without its hash lookups. The optimizer
/// builds a cell's map once per block run, about 28 times per cell and region fit (7 blocks
/// per tetrahedron, 4 sweeps); each build looked up all eleven faces in the whole fit's map,
/// a cache miss each (issue 17, session 26: `local_with` ~10 % of the torus at 1e-4). Kept
/// equal to the map by [`CellTerms::set_logits`] for every face set while it is used.
#[derive(Clone, Debug)]
pub struct CellTerms {
    m: usize,
    terms: [Term; MAX_TERMS],
    keys: [FaceKey; MAX_TERMS],
    /// The stored (clamped) logits of each face, zeros where none is stored.
    logits: [[f64; M]; MAX_TERMS],
    count: u8,
    /// Bit `i` set: face `i` has a stored point (else its term is the centre's zero).
    stored: u16,
    /// The map's [`StratifiedMap::set_lattice`], which points set later follow too.
    lattice: bool,
}

impl CellTerms {
    /// The index of `face` (sorted ids) among the cell's faces, if it is one of them.
    pub fn face_index(&self, face: &[u32]) -> Option<usize> {
        self.keys[..usize::from(self.count)]
            .iter()
            .position(|k| k.ids() == face)
    }

    /// Stores the point of face `i` as [`StratifiedMap::set_logits`] stores it (clamped).
    pub fn set_logits(&mut self, i: usize, logits: &[f64]) {
        let mut l = [0.0; M];
        for (s, x) in l.iter_mut().zip(logits) {
            *s = x.clamp(-LOGIT_BOUND, LOGIT_BOUND);
        }
        let t = &mut self.terms[i];
        t.delta = displacement_of(&l[..usize::from(t.len)], self.lattice);
        self.logits[i] = l;
        self.stored |= 1 << i;
    }

    /// The logits of face `i`: [`StratifiedMap::logits`] of that face.
    pub fn logits(&self, i: usize) -> &[f64] {
        &self.logits[i][..usize::from(self.terms[i].len)]
    }

    /// [`StratifiedMap::local_with`] on this cell with the face at index `wanted`: the same
    /// terms in the same order, so the same numbers bit for bit.
    pub fn local_with(&self, wanted: Option<usize>) -> (LocalStrata, Option<Slot>) {
        let mut terms = [NO_TERM; MAX_TERMS];
        let mut count = [0u8; M - 1];
        let mut slot = None;
        for (i, term) in self.terms[..usize::from(self.count)].iter().enumerate() {
            let is_wanted = wanted == Some(i);
            if self.stored >> i & 1 == 0 && !is_wanted {
                continue;
            }
            let j = usize::from(term.len) - 2;
            if is_wanted {
                slot = Some(Slot {
                    stratum: j,
                    term: usize::from(count[j]),
                });
            }
            terms[STRATUM_START[j] + usize::from(count[j])] = *term;
            count[j] += 1;
        }
        (
            LocalStrata {
                m: self.m,
                terms,
                count,
                pre: None,
            },
            slot,
        )
    }
}

impl StratifiedMap {
    /// The identity map in dimension `n`.
    pub fn new(dim: usize) -> StratifiedMap {
        StratifiedMap {
            dim,
            logits: HashMap::default(),
            lattice: false,
        }
    }

    /// Rounds every point the map stores — now and when set later — onto the
    /// [`POINT_LATTICE`] (`on`), or keeps the softmax as it is. The local maps, [`Self::point`]
    /// and [`Self::to_stages`] all read the rounded point, so what a fit measures is what it
    /// writes; the optimizer's trials ([`displacement`]) stay smooth. Off by default: rounding
    /// moves a point by up to 2⁻²⁵ of its face, which the exact edge crossings of `ism smooth`'s
    /// handles and of rational fits would lose.
    pub fn set_lattice(&mut self, on: bool) {
        self.lattice = on;
        for (key, stored) in self.logits.iter_mut() {
            let len = key.ids().len();
            stored.delta = displacement_of(&stored.logits[..len], on);
        }
    }

    /// Whether the map rounds its points onto the lattice ([`Self::set_lattice`]).
    pub fn on_lattice(&self) -> bool {
        self.lattice
    }

    /// Space dimension.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// The logits of `face` (sorted ids), zeros if unset.
    pub fn logits(&self, face: &[u32]) -> Vec<f64> {
        match self.logits.get(&FaceKey::of(face)) {
            Some(stored) => stored.logits[..face.len()].to_vec(),
            None => vec![0.0; face.len()],
        }
    }

    /// Sets the logits of `face` (sorted ids, 1 to 4 of them, as many logits), clamped to
    /// `±LOGIT_BOUND`.
    pub fn set_logits(&mut self, face: &[u32], logits: &[f64]) {
        assert_eq!(face.len(), logits.len(), "one logit per vertex of the face");
        let key = FaceKey::of(face);
        let mut l = [0.0; M];
        for (s, x) in l.iter_mut().zip(logits) {
            *s = x.clamp(-LOGIT_BOUND, LOGIT_BOUND);
        }
        let delta = displacement_of(&l[..face.len()], self.lattice);
        self.logits.insert(key, Stored { logits: l, delta });
    }

    /// Forgets the point of `face` (back to the fixed centre).
    pub fn remove(&mut self, face: &[u32]) {
        self.logits.remove(&FaceKey::of(face));
    }

    /// Keeps only the faces for which `keep` is true.
    pub fn retain(&mut self, mut keep: impl FnMut(&[u32]) -> bool) {
        self.logits.retain(|f, _| keep(f.ids()));
    }

    /// The control point of `face` (coordinates w.r.t. the sorted ids).
    pub fn point(&self, face: &[u32]) -> Vec<f64> {
        self.softmax(&self.logits(face))
    }

    /// The stored point of `logits`: on the lattice when the map is.
    fn softmax(&self, logits: &[f64]) -> Vec<f64> {
        if self.lattice {
            softmax_on_lattice(logits)
        } else {
            softmax(logits)
        }
    }

    /// The faces with a stored point and their logits, in no particular order.
    pub fn entries(&self) -> impl Iterator<Item = (&[u32], &[f64])> {
        self.logits
            .iter()
            .map(|(f, s)| (f.ids(), &s.logits[..usize::from(f.len)]))
    }

    /// Number of faces with a stored point.
    pub fn num_faces(&self) -> usize {
        self.logits.len()
    }

    /// The map on the simplex with vertex ids `cell` (local order).
    pub fn local(&self, cell: &[u32]) -> LocalStrata {
        self.local_with(cell, None).0
    }

    /// [`StratifiedMap::local`], with a term for `face` (sorted ids, a face of `cell`) even when
    /// it has no stored point (a zero displacement adds exactly nothing), and where that term
    /// is: [`LocalStrata::set_point`] then moves the point without rebuilding the rest. The
    /// optimizer moves one face at a time over the same cells (issue 17: rebuilding each cell's
    /// map per trial, with its hash lookups, was ~20 % of a torus fit).
    pub fn local_with(&self, cell: &[u32], face: Option<&[u32]>) -> (LocalStrata, Option<Slot>) {
        let m = cell.len();
        assert!(m <= M, "a cell has at most {M} vertices, not {m}");
        let mut terms = [NO_TERM; MAX_TERMS];
        let mut count = [0u8; M - 1];
        let mut slot = None;
        // Every face of ≥ 2 vertices (the cells of the fitter's working complex: not an indexed
        // model, so the faces come from the vertex list).
        for local in simplex_faces(cell, 2) {
            let len = local.len();
            let key = local.ids();
            let wanted = face == Some(key);
            let stored = self.logits.get(&FaceKey::of(key));
            if stored.is_none() && !wanted {
                continue;
            }
            let mut term = Term {
                positions: [0; M],
                len: len as u8,
                delta: [0.0; M],
            };
            term.positions[..len].copy_from_slice(local.positions());
            match stored {
                Some(s) => term.delta = s.delta,
                None => term.set(&[0.0; M][..len]),
            }
            let j = len - 2;
            if wanted {
                slot = Some(Slot {
                    stratum: j,
                    term: usize::from(count[j]),
                });
            }
            terms[STRATUM_START[j] + usize::from(count[j])] = term;
            count[j] += 1;
        }
        (
            LocalStrata {
                m,
                terms,
                count,
                pre: None,
            },
            slot,
        )
    }

    /// Every face term of `cell` (see [`CellTerms`]): the lookups of
    /// [`StratifiedMap::local_with`] done once.
    pub fn cell_terms(&self, cell: &[u32]) -> CellTerms {
        let m = cell.len();
        assert!(m <= M, "a cell has at most {M} vertices, not {m}");
        let mut out = CellTerms {
            m,
            terms: [NO_TERM; MAX_TERMS],
            keys: [FaceKey {
                ids: [u32::MAX; M],
                len: 0,
            }; MAX_TERMS],
            logits: [[0.0; M]; MAX_TERMS],
            count: 0,
            stored: 0,
            lattice: self.lattice,
        };
        for (i, local) in simplex_faces(cell, 2).enumerate() {
            let len = local.len();
            let key = FaceKey::of(local.ids());
            let mut term = Term {
                positions: [0; M],
                len: len as u8,
                delta: [0.0; M],
            };
            term.positions[..len].copy_from_slice(local.positions());
            match self.logits.get(&key) {
                Some(s) => {
                    term.delta = s.delta;
                    out.logits[i] = s.logits;
                    out.stored |= 1 << i;
                }
                None => term.set(&[0.0; M][..len]),
            }
            out.terms[i] = term;
            out.keys[i] = key;
            out.count += 1;
        }
        out
    }

    /// The stages of a model: stratum `j` as a parametric Bézier stage of degree `j + 1`, edges
    /// first (see the module doc for the order). Only faces for which `exists` is true are
    /// written; records are sorted by face.
    pub fn to_stages(&self, exists: impl Fn(&[u32]) -> bool) -> Vec<Stage> {
        (1..=self.dim)
            .map(|j| {
                let mut faces: Vec<FaceRecord> = self
                    .entries()
                    .filter(|(f, l)| f.len() == j + 1 && l.iter().any(|&x| x != 0.0) && exists(f))
                    .map(|(f, l)| FaceRecord {
                        face: f.to_vec(),
                        points: self.softmax(l),
                        weights: Vec::new(),
                    })
                    .collect();
                faces.sort_by(|a, b| a.face.cmp(&b.face));
                let mut stage = Stage::identity(StageKind::Bezier, j as u32 + 1);
                stage.direction = Direction::Parametric;
                stage.name = Some(format!("stratum G{j}"));
                stage.faces = faces.into();
                stage
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn softmax_points_lie_on_the_lattice_and_sum_to_one_exactly() {
        // Ground truth: exact integer arithmetic on the lattice numerators, and the unrounded
        // softmax within half a step per coordinate.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        for len in 1..=4 {
            for _ in 0..2000 {
                let logits: Vec<f64> = (0..len).map(|_| (next() - 0.5) * 16.0).collect();
                let p = softmax_on_lattice(&logits);
                let e: Vec<f64> = logits
                    .iter()
                    .map(|l| l.clamp(-LOGIT_BOUND, LOGIT_BOUND).exp())
                    .collect();
                let s: f64 = e.iter().sum();
                let mut numerators = 0i64;
                for (x, ex) in p.iter().zip(&e) {
                    let n = x * POINT_LATTICE;
                    assert_eq!(n, n.trunc(), "{p:?} off the lattice");
                    assert!(n >= 1.0, "{p:?} has a coordinate on the face's boundary");
                    numerators += n as i64;
                    // Coordinate 0 absorbs the others' rounding: up to 1.5 steps for 4 coordinates.
                    assert!(
                        (x - ex / s).abs() <= 2.0 / POINT_LATTICE,
                        "{p:?} vs {}",
                        ex / s
                    );
                }
                assert_eq!(numerators, POINT_LATTICE as i64, "{p:?}");
                assert_eq!(p.iter().sum::<f64>(), 1.0);
                // A map on the lattice reads the same rounded point as its displacement.
                let factorial: f64 = (1..=len).map(|x| x as f64).product();
                let d = displacement_of(&logits, true);
                for i in 0..len {
                    assert_eq!(d[i], (p[i] - 1.0 / len as f64) * factorial);
                }
            }
        }
    }

    #[test]
    fn a_map_on_the_lattice_writes_and_evaluates_the_rounded_points() {
        // A point set before the switch and one after are both rounded, in the written stages,
        // in the map's local maps and in a cell cache's; the kernel's agreement with the
        // written file on a whole fit is in fit/tests.rs.
        let cell = [7u32, 2, 9, 4];
        let u = [0.1, 0.2, 0.3, 0.4];
        let (edge, triangle) = ([2u32, 7], [2u32, 4, 9]);
        let mut map = StratifiedMap::new(3);
        map.set_logits(&edge, &[0.0, 1.0]);
        map.set_logits(&triangle, &[0.3, -0.2, 0.5]);
        let smooth = map.local(&cell).eval(&u);
        let mut cache = map.cell_terms(&cell);
        map.set_lattice(true);
        map.set_logits(&triangle, &[0.3, -0.2, 0.6]);
        let mut written = 0;
        for stage in map.to_stages(|_| true) {
            for r in stage.faces.iter() {
                assert_eq!(r.points, softmax_on_lattice(&map.logits(r.face)));
                assert_eq!(r.points.iter().sum::<f64>(), 1.0);
                written += 1;
            }
        }
        assert_eq!(written, 2);
        let rounded = map.local(&cell).eval(&u);
        assert_ne!(rounded, smooth);
        // A cache taken from the map on the lattice follows it for the points set later; one
        // taken before keeps the smooth points (the fitter sets the lattice before any cache).
        let mut on = map.cell_terms(&cell);
        for c in [&mut on, &mut cache] {
            let i = c.face_index(&triangle).unwrap();
            c.set_logits(i, &[0.3, -0.2, 0.6]);
        }
        assert_eq!(on.local_with(None).0.eval(&u), rounded);
        assert_ne!(cache.local_with(None).0.eval(&u), rounded);
        // Off again: the smooth softmax.
        map.set_lattice(false);
        assert_eq!(map.point(&edge), softmax(&map.logits(&edge)));
    }

    #[test]
    fn identity_until_set_and_faces_stay_put() {
        let mut map = StratifiedMap::new(3);
        let cell = [7u32, 2, 9, 4];
        let u = [0.1, 0.2, 0.3, 0.4];
        assert_eq!(map.local(&cell).eval(&u), u);
        map.set_logits(&[2, 7], &[0.0, 1.0]);
        map.set_logits(&[2, 4, 9], &[0.3, -0.2, 0.5]);
        map.set_logits(&[2, 4, 7, 9], &[0.3, -0.2, 0.5, 1.0]);
        let local = map.local(&cell);
        let w = local.eval(&u);
        assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-14);
        assert!(w.iter().all(|&x| x > 0.0));
        // A point on the face (2, 9, 4) (local 1, 2, 3) stays on it: coordinate 0 stays exactly 0.
        let on_face = local.eval(&[0.0, 0.2, 0.3, 0.5]);
        assert_eq!(on_face[0], 0.0);
        // Vertices are fixed.
        assert_eq!(local.eval(&[0.0, 0.0, 1.0, 0.0]), [0.0, 0.0, 1.0, 0.0]);
    }

    #[test]
    fn a_moved_slot_evaluates_as_the_rebuilt_map_bit_for_bit() {
        let mut map = StratifiedMap::new(3);
        let cell = [7u32, 2, 9, 4];
        map.set_logits(&[2, 7], &[0.0, 1.0]);
        map.set_logits(&[2, 4, 7, 9], &[0.3, -0.2, 0.5, 1.0]);
        let us = [
            [0.1, 0.2, 0.3, 0.4],
            [0.0, 0.5, 0.25, 0.25],
            [0.7, 0.0, 0.0, 0.3],
        ];
        // A face with a stored point and one without.
        for face in [vec![2u32, 7], vec![2, 4, 9]] {
            let (mut local, slot) = map.local_with(&cell, Some(&face));
            for logits in [[0.4, -7.0, 2.0], [0.0, 0.0, 0.0], [-1.0, 3.0, 0.5]] {
                let l = &logits[..face.len()];
                local.set_point(slot.unwrap(), l);
                let mut moved = map.clone();
                moved.set_logits(&face, l);
                let rebuilt = moved.local(&cell);
                for u in &us {
                    let (a, b) = (local.eval(u), rebuilt.eval(u));
                    assert_eq!(a.map(f64::to_bits), b.map(f64::to_bits), "{face:?} {l:?}");
                    // In two parts around the slot's stratum.
                    let split = local.eval_after(&local.eval_before(u, slot), slot);
                    assert_eq!(split.map(f64::to_bits), b.map(f64::to_bits));
                    // With the displacement computed once for all cells.
                    let mut shared = local.clone();
                    shared.set_point(slot.unwrap(), &[0.0; M][..face.len()]);
                    shared.set_displacement(slot.unwrap(), &displacement(l));
                    assert_eq!(shared.eval(u).map(f64::to_bits), b.map(f64::to_bits));
                }
            }
        }
    }

    /// The optimizer's per-cell cache against the whole map it mirrors: after each of a run of
    /// sets (logits beyond the clamp, back to the centre, faces of other cells too), the
    /// cache's map with a slot for every face, and without one, evaluates bit for bit as the
    /// map's own [`StratifiedMap::local_with`], and the logits are the map's.
    #[test]
    fn a_cell_s_cached_terms_evaluate_as_the_whole_map_bit_for_bit() {
        for cell in [vec![7u32, 2, 9, 4], vec![5u32, 1, 3]] {
            let mut map = StratifiedMap::new(cell.len() - 1);
            map.set_logits(&[2, 7], &[0.0, 1.0]);
            map.set_logits(&[1, 5], &[0.2, -0.4]);
            let mut cached = map.cell_terms(&cell);
            let faces: Vec<Vec<u32>> = simplex_faces(&cell, 2).map(|f| f.ids().to_vec()).collect();
            let us = [
                [0.1, 0.2, 0.3, 0.4],
                [0.0, 0.5, 0.25, 0.25],
                [0.7, 0.0, 0.0, 0.3],
                [0.2, 0.3, 0.5, 0.0],
            ];
            // A fixed pseudo-random sequence of faces and logits (a linear congruence).
            let mut rng = crate::test_rng::Lcg::new(12345);
            let mut next = || (rng.next_u64() >> 33) as f64 / (1u64 << 31) as f64;
            for step in 0..60 {
                let face = &faces[(next() * faces.len() as f64) as usize % faces.len()];
                let logits: Vec<f64> = face.iter().map(|_| 16.0 * next() - 8.0).collect();
                let logits = if step % 7 == 0 {
                    vec![0.0; face.len()]
                } else {
                    logits
                };
                map.set_logits(face, &logits);
                cached.set_logits(cached.face_index(face).unwrap(), &logits);
                // A face of another cell: nothing of this cell changes.
                map.set_logits(&[100, 101], &[0.5, -0.5]);
                for (i, f) in faces.iter().enumerate() {
                    assert_eq!(cached.face_index(f), Some(i));
                    assert_eq!(cached.logits(i), &map.logits(f)[..], "{f:?}");
                    let (a, slot_a) = cached.local_with(Some(i));
                    let (b, slot_b) = map.local_with(&cell, Some(f));
                    assert_eq!(slot_a, slot_b);
                    let (c, _) = cached.local_with(None);
                    let d = map.local(&cell);
                    for u in &us {
                        let u = if cell.len() == 3 {
                            let s = u[0] + u[1] + u[2];
                            [u[0] / s, u[1] / s, u[2] / s, 0.0]
                        } else {
                            *u
                        };
                        assert_eq!(a.eval(&u).map(f64::to_bits), b.eval(&u).map(f64::to_bits));
                        assert_eq!(c.eval(&u).map(f64::to_bits), d.eval(&u).map(f64::to_bits));
                    }
                }
            }
            assert_eq!(cached.face_index(&[100, 101]), None);
        }
    }

    /// A complex number, for the complex-step derivative `Im f(x + ih)/h` (exact to rounding,
    /// no cancellation): the peer of [`LocalStrata::eval_after_jacobian`].
    #[derive(Clone, Copy, Debug)]
    struct C(f64, f64);

    impl std::ops::Add for C {
        type Output = C;
        fn add(self, o: C) -> C {
            C(self.0 + o.0, self.1 + o.1)
        }
    }

    impl std::ops::Mul for C {
        type Output = C;
        fn mul(self, o: C) -> C {
            C(self.0 * o.0 - self.1 * o.1, self.0 * o.1 + self.1 * o.0)
        }
    }

    impl C {
        fn exp(self) -> C {
            let r = self.0.exp();
            C(r * self.1.cos(), r * self.1.sin())
        }
        fn recip(self) -> C {
            let d = self.0 * self.0 + self.1 * self.1;
            C(self.0 / d, -self.1 / d)
        }
    }

    /// The stratified map on `cell` straight from the module doc's closed form, in complex
    /// arithmetic: `G_j(w) = w + Σ_τ (b_τ − 𝟙_τ/|τ|)·|τ|!·Π_{i∈τ} w_i` over the `j`-faces `τ`,
    /// the interior stratum first and the edge stratum last; `b_τ` the softmax of the face's
    /// logits (w.r.t. its sorted ids). `moved` adds `i·h` to logit `j` of one face.
    fn closed_form(
        faces: &[(Vec<u32>, Vec<f64>)],
        cell: &[u32],
        u: &[f64; M],
        moved: Option<(&[u32], usize, f64)>,
    ) -> [C; M] {
        let mut w: Vec<C> = u.iter().map(|&x| C(x, 0.0)).collect();
        for len in (2..=cell.len()).rev() {
            let input = w.clone();
            for (face, logits) in faces.iter().filter(|f| f.0.len() == len) {
                let l: Vec<C> = logits
                    .iter()
                    .enumerate()
                    .map(|(j, &x)| match moved {
                        Some((f, mj, h)) if f == &face[..] && mj == j => C(x, h),
                        _ => C(x, 0.0),
                    })
                    .collect();
                let e: Vec<C> = l.iter().map(|x| x.exp()).collect();
                let sum = e.iter().fold(C(0.0, 0.0), |a, &b| a + b).recip();
                let factorial: f64 = (1..=len).map(|x| x as f64).product();
                let positions: Vec<usize> = face
                    .iter()
                    .map(|v| cell.iter().position(|c| c == v).unwrap())
                    .collect();
                let product = positions.iter().fold(C(1.0, 0.0), |a, &p| a * input[p]);
                for (i, &p) in positions.iter().enumerate() {
                    let b = e[i] * sum + C(-1.0 / len as f64, 0.0);
                    w[p] = w[p] + b * C(factorial, 0.0) * product;
                }
            }
        }
        [w[0], w[1], w[2], w[3]]
    }

    #[test]
    fn the_exact_jacobian_agrees_with_the_complex_step_and_with_differences() {
        let cell = [7u32, 2, 9, 4];
        let faces: Vec<(Vec<u32>, Vec<f64>)> = vec![
            (vec![2, 7], vec![0.0, 0.7]),
            (vec![4, 9], vec![-0.4, 0.3]),
            (vec![2, 9], vec![0.2, -0.5]),
            (vec![2, 4, 9], vec![0.3, -0.2, 0.5]),
            (vec![4, 7, 9], vec![-0.6, 0.1, 0.4]),
            (vec![2, 4, 7, 9], vec![0.3, -0.2, 0.5, 1.0]),
        ];
        let mut map = StratifiedMap::new(3);
        for (f, l) in &faces {
            map.set_logits(f, l);
        }
        let us = [
            [0.1, 0.2, 0.3, 0.4],
            [0.25, 0.25, 0.25, 0.25],
            [0.6, 0.05, 0.15, 0.2],
            [0.0, 0.5, 0.25, 0.25],
        ];
        // Faces with a stored point, one without (its term starts at the centre), one edge of
        // the stratum acting last and triangles of the one before it.
        for face in [
            vec![2u32, 7],
            vec![2, 4, 9],
            vec![4, 7, 9],
            vec![2, 4],
            vec![2, 4, 7],
        ] {
            let (mut local, slot) = map.local_with(&cell, Some(&face));
            let slot = slot.unwrap();
            let x = map.logits(&face);
            local.set_point(slot, &x);
            let mut faces = faces.clone();
            if !faces.iter().any(|f| f.0 == face) {
                faces.push((face.clone(), x.clone()));
            }
            for u in &us {
                let v = local.eval_before(u, Some(slot));
                let mut dw = [[f64::NAN; M]; M];
                let w = local.eval_after_jacobian(&v, slot, &displacement_derivative(&x), &mut dw);
                let plain = local.eval_after(&v, Some(slot));
                assert_eq!(w.map(f64::to_bits), plain.map(f64::to_bits));
                let peer = closed_form(&faces, &cell, u, None);
                for c in 0..M {
                    assert!((peer[c].0 - w[c]).abs() < 1e-14, "{face:?} {u:?}");
                }
                for j in 0..face.len() {
                    const H: f64 = 1e-30;
                    let cs = closed_form(&faces, &cell, u, Some((&face, j, H)));
                    // Central differences of the map itself, a second peer.
                    const D: f64 = 1e-6;
                    let mut xp = x.clone();
                    let mut xm = x.clone();
                    xp[j] += D;
                    xm[j] -= D;
                    local.set_point(slot, &xp);
                    let wp = local.eval_after(&v, Some(slot));
                    local.set_point(slot, &xm);
                    let wm = local.eval_after(&v, Some(slot));
                    local.set_point(slot, &x);
                    for c in 0..M {
                        let exact = cs[c].1 / H;
                        assert!(
                            (dw[j][c] - exact).abs() <= 1e-13 * (1.0 + exact.abs()),
                            "{face:?} {u:?} logit {j} coordinate {c}: {} vs {exact}",
                            dw[j][c]
                        );
                        let fd = (wp[c] - wm[c]) / (2.0 * D);
                        assert!((dw[j][c] - fd).abs() < 1e-8, "{} vs {fd}", dw[j][c]);
                    }
                }
            }
        }
    }

    #[test]
    fn a_logit_at_its_clamp_has_the_forward_differences_zero_column() {
        let cell = [3u32, 5, 8];
        let face = [3u32, 5, 8];
        let mut map = StratifiedMap::new(2);
        map.set_logits(&[3, 5], &[0.0, -1.0]);
        let (mut local, slot) = map.local_with(&cell, Some(&face));
        let slot = slot.unwrap();
        let x = [LOGIT_BOUND, 0.5, -LOGIT_BOUND];
        local.set_point(slot, &x);
        let u = [0.2, 0.3, 0.5, 0.0];
        let v = local.eval_before(&u, Some(slot));
        let mut dw = [[0.0; M]; M];
        let w = local.eval_after_jacobian(&v, slot, &displacement_derivative(&x), &mut dw);
        for j in 0..3 {
            const H: f64 = 1e-7;
            let mut xh = x;
            xh[j] += H;
            local.set_point(slot, &xh);
            let wh = local.eval_after(&v, Some(slot));
            for c in 0..M {
                let fd = (wh[c] - w[c]) / H;
                if j == 0 {
                    // Held at +LOGIT_BOUND: moving it up changes nothing.
                    assert_eq!(dw[j][c], 0.0);
                    assert_eq!(fd, 0.0);
                } else {
                    assert!(dw[j][c] != 0.0 || c == 3);
                    assert!(
                        (dw[j][c] - fd).abs() < 1e-6,
                        "{j} {c}: {} vs {fd}",
                        dw[j][c]
                    );
                }
            }
        }
    }

    #[test]
    fn faces_sharing_ids_are_kept_apart_as_a_sorted_map_keeps_them() {
        // Truth: a BTreeMap keyed by the ids as a vector, written alongside. The faces share
        // prefixes ([1, 2] in [1, 2, 3] in [1, 2, 3, 4]) and hold ids up to u32::MAX − 1, the
        // cases a fixed-array key with padding could confuse.
        let big = u32::MAX - 1;
        let faces: Vec<Vec<u32>> = vec![
            vec![1, 2],
            vec![1, 2, 3],
            vec![1, 2, 3, 4],
            vec![2, 3],
            vec![1, 3],
            vec![0, big],
            vec![0, 1, big],
            vec![0, 1, 2, big],
            vec![big - 1, big],
        ];
        let mut map = StratifiedMap::new(3);
        let mut truth: std::collections::BTreeMap<Vec<u32>, Vec<f64>> = Default::default();
        let mut rng = crate::test_rng::Lcg::new(12345);
        let mut next = || rng.unit();
        for round in 0..200 {
            let f = &faces[(next() * faces.len() as f64) as usize];
            if round % 7 == 3 {
                map.remove(f);
                truth.remove(f);
            } else {
                // Some beyond the bound: stored clamped.
                let l: Vec<f64> = f.iter().map(|_| 16.0 * next() - 8.0).collect();
                map.set_logits(f, &l);
                truth.insert(
                    f.clone(),
                    l.iter()
                        .map(|x| x.clamp(-LOGIT_BOUND, LOGIT_BOUND))
                        .collect(),
                );
            }
            for f in &faces {
                let expect = truth.get(f).cloned().unwrap_or(vec![0.0; f.len()]);
                assert_eq!(map.logits(f), expect, "{f:?} after {round} changes");
            }
            let mut entries: Vec<(Vec<u32>, Vec<f64>)> = map
                .entries()
                .map(|(f, l)| (f.to_vec(), l.to_vec()))
                .collect();
            entries.sort_by(|a, b| a.0.cmp(&b.0));
            let expect: Vec<(Vec<u32>, Vec<f64>)> = truth.clone().into_iter().collect();
            assert_eq!(entries, expect);
            assert_eq!(map.num_faces(), truth.len());
        }
        // The map on a cell is the closed form of the stored points.
        let cell = [3u32, 1, 4, 2];
        let stored: Vec<(Vec<u32>, Vec<f64>)> = truth
            .iter()
            .filter(|(f, _)| f.iter().all(|v| cell.contains(v)))
            .map(|(f, l)| (f.clone(), l.clone()))
            .collect();
        let u = [0.1, 0.2, 0.3, 0.4];
        let peer = closed_form(&stored, &cell, &u, None);
        let w = map.local(&cell).eval(&u);
        for c in 0..M {
            assert!((peer[c].0 - w[c]).abs() < 1e-14, "{stored:?}");
        }
        map.retain(|f| f.len() == 2);
        truth.retain(|f, _| f.len() == 2);
        let mut kept: Vec<Vec<u32>> = map.entries().map(|(f, _)| f.to_vec()).collect();
        kept.sort();
        assert_eq!(kept, truth.keys().cloned().collect::<Vec<_>>());
    }

    #[test]
    fn edge_point_moves_the_edge_as_a_quadratic() {
        let mut map = StratifiedMap::new(2);
        let alpha = 0.8;
        map.set_logits(&[3, 5], &edge_logits(alpha));
        // Local order (5, 3): position 0 is vertex 5, the second sorted vertex.
        let local = map.local(&[5, 3, 8]);
        let t = 0.3; // weight on vertex 5
        let w = local.eval(&[t, 1.0 - t, 0.0, 0.0]);
        // y(t) = t + (2α − 1)·t(1 − t) for the weight on the second sorted vertex.
        let expect = t + (2.0 * alpha - 1.0) * t * (1.0 - t);
        assert!((w[0] - expect).abs() < 1e-12, "{} vs {}", w[0], expect);
    }
}
