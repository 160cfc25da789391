//! Coefficient ranges of a polynomial, and of its reduced partial derivatives, restricted to the
//! simplex `{w ≥ lo, Σ w = 1}`: what [`crate::chain`] needs per cell for every stage after the
//! first, without building the restricted polynomials.
//!
//! The simplex has vertices `v_j = lo + r e_j` (`r = 1 − Σ lo`), so by multilinearity of the
//! (homogeneous) blossom `β` of a degree-`d` polynomial `P` the restricted Bernstein coefficient
//! of index `J` is
//!
//! `c_J = β(v_{j_1}, …, v_{j_d}) = Σ_{K ≤ J} C(J; K) r^{|K|} β(lo^{d−|K|}, e^K)`,
//!
//! with `C(J; K) = Π_i C(J_i, K_i)` (the ways to pick `K_i` of the `J_i` copies of `e_i`). The
//! blossoms `β(lo^{d−k}, e^K)` are the levels of one de Casteljau run at the (unnormalised) point
//! `lo`. The directional derivative `D = ∂_l − ∂_0` (degree `d − 1`, Bernstein coefficients
//! `d (b_{K+e_l} − b_{K+e_0})`, [`ism_geom::Bernstein::derivative`]) has the blossom
//! `β_D(x_1, …, x_{d−1}) = d (β(x_1, …, x_{d−1}, e_l) − β(x_1, …, x_{d−1}, e_0))`, so the same
//! levels give its restricted coefficients too. One de Casteljau run per component replaces the
//! `m` vertex replacements of each of the `m + n²` polynomials that exact restriction costs, and
//! nothing is allocated per polynomial. Only the coefficients' extremes are kept: they are the
//! enclosures the chain bound uses (convex hull property), widened like
//! [`crate::bound::quotient_range`] for rounding.

use std::sync::OnceLock;

use ism_format::multi_index;
use ism_geom::interval::Interval;
use ism_geom::{Bernstein, MAX_VARS};

use crate::bound::BOUND_ROUNDING_MARGIN;

/// Highest degree with a cached plan; higher degrees use exact restriction.
pub(crate) const MAX_DEGREE: usize = 8;

/// Blossoms of every degree `0..=MAX_DEGREE` in `MAX_VARS` variables: `C(MAX_DEGREE + 4, 4)`.
pub(crate) const LEVEL_CAP: usize = 495;

/// Index tables of one shape `(m, d)`.
struct Plan {
    /// `offsets[k]`: start of degree-`k` blossoms in a level buffer (`k = 0..=d`, plus the end).
    offsets: Vec<usize>,
    /// `up[offsets[k] * m + r * m + i]` (`k < d`): position (in the level buffer) of `K_r + e_i`,
    /// `K_r` the `r`-th index of degree `k`.
    up: Vec<u32>,
    /// Terms of the degree-`d` outputs: `terms[start[J]..start[J + 1]]` are `(k, position of K in
    /// the level buffer, C(J; K))` over `K ≤ J`.
    start: Vec<u32>,
    terms: Vec<(u8, u32, f64)>,
}

impl Plan {
    fn build(m: usize, d: u32) -> Plan {
        let mut offsets = vec![0usize];
        for k in 0..=d {
            offsets.push(offsets[k as usize] + multi_index::count(m, k));
        }
        let all: Vec<Vec<u32>> = (0..=d).map(|k| multi_index::all(m, k)).collect();
        let mut up = vec![0u32; offsets[d as usize] * m];
        for k in 0..d as usize {
            for (r, idx) in all[k].chunks_exact(m).enumerate() {
                for i in 0..m {
                    let mut next = idx.to_vec();
                    next[i] += 1;
                    up[(offsets[k] + r) * m + i] =
                        (offsets[k + 1] + multi_index::rank(&next)) as u32;
                }
            }
        }
        let mut start = vec![0u32];
        let mut terms = Vec::new();
        for j in all[d as usize].chunks_exact(m) {
            for k in 0..=d as usize {
                for (r, idx) in all[k].chunks_exact(m).enumerate() {
                    if idx.iter().zip(j).all(|(a, b)| a <= b) {
                        let weight: u64 = idx
                            .iter()
                            .zip(j)
                            .map(|(&a, &b)| multi_index::binomial(u64::from(b), u64::from(a)))
                            .product();
                        terms.push((k as u8, (offsets[k] + r) as u32, weight as f64));
                    }
                }
            }
            start.push(terms.len() as u32);
        }
        Plan {
            offsets,
            up,
            start,
            terms,
        }
    }
}

fn plan(m: usize, d: u32) -> &'static Plan {
    static PLANS: [[OnceLock<Plan>; MAX_DEGREE + 1]; MAX_VARS + 1] =
        [const { [const { OnceLock::new() }; MAX_DEGREE + 1] }; MAX_VARS + 1];
    PLANS[m][d as usize].get_or_init(|| Plan::build(m, d))
}

/// `[min, max]` of `Σ_terms w r^k level[pos]` over the outputs of `plan`, and the largest
/// magnitude.
fn output_range(plan: &Plan, level: &[f64], rpow: &[f64]) -> (f64, f64, f64) {
    let (mut lo, mut hi, mut top) = (f64::INFINITY, f64::NEG_INFINITY, 0.0f64);
    for w in plan.start.windows(2) {
        let mut c = 0.0;
        for &(k, pos, weight) in &plan.terms[w[0] as usize..w[1] as usize] {
            c += weight * rpow[k as usize] * level[pos as usize];
        }
        lo = lo.min(c);
        hi = hi.max(c);
        top = top.max(c.abs());
    }
    (lo, hi, top)
}

/// A range widened by [`BOUND_ROUNDING_MARGIN`] of its largest magnitude, like
/// [`crate::bound::quotient_range`].
fn widened((lo, hi, top): (f64, f64, f64)) -> Interval {
    let slack = BOUND_ROUNDING_MARGIN * top + f64::MIN_POSITIVE;
    Interval::new(lo - slack, hi + slack)
}

/// The restriction of polynomials of one degree to `{w ≥ lo}`: a de Casteljau run per polynomial
/// into a reused buffer.
pub(crate) struct Homothety {
    m: usize,
    d: u32,
    plan: &'static Plan,
    /// The derivative outputs' plan (degree `d − 1`); `None` for `d = 0`.
    lower: Option<&'static Plan>,
    /// `r^k`, `k = 0..=d`.
    rpow: [f64; MAX_DEGREE + 1],
    lo: [f64; MAX_VARS],
    level: [f64; LEVEL_CAP],
    dlevel: [f64; LEVEL_CAP],
}

impl Homothety {
    /// `None` when the degree has no plan (use exact restriction).
    #[cfg(test)]
    pub(crate) fn new(m: usize, d: u32, lo: &[f64]) -> Option<Homothety> {
        let mut h = Homothety::empty();
        h.set(m, d, lo).then_some(h)
    }

    /// A buffer for [`Homothety::set`] (the degree-0 plan in one variable until then).
    pub(crate) fn empty() -> Homothety {
        Homothety {
            m: 1,
            d: 0,
            plan: plan(1, 0),
            lower: None,
            rpow: [1.0; MAX_DEGREE + 1],
            lo: [0.0; MAX_VARS],
            level: [0.0; LEVEL_CAP],
            dlevel: [0.0; LEVEL_CAP],
        }
    }

    /// Re-targets the buffers to degree `d` in `m` variables and the simplex `{w ≥ lo}`, as
    /// `Homothety::new` (a test constructor) would build them (without clearing the levels: every
    /// entry read is written first). `false` when the degree has no plan; the buffer is then unchanged.
    pub(crate) fn set(&mut self, m: usize, d: u32, lo: &[f64]) -> bool {
        if d as usize > MAX_DEGREE || m == 0 || m > MAX_VARS {
            return false;
        }
        let plan = plan(m, d);
        debug_assert!(plan.offsets[d as usize + 1] <= LEVEL_CAP);
        self.m = m;
        self.d = d;
        self.plan = plan;
        self.lower = (d > 0).then(|| self::plan(m, d - 1));
        self.lo = [0.0; MAX_VARS];
        self.lo[..m].copy_from_slice(&lo[..m]);
        let r = (1.0 - self.lo[..m].iter().sum::<f64>()).max(0.0);
        self.rpow = [1.0; MAX_DEGREE + 1];
        for k in 1..=d as usize {
            self.rpow[k] = self.rpow[k - 1] * r;
        }
        true
    }

    /// Loads a polynomial's coefficients (canonical order, degree `d`) and runs de Casteljau at
    /// `lo`: afterwards `level[offsets[k] + r]` is `β(lo^{d−k}, e^{K_r})`.
    pub(crate) fn load(&mut self, coeffs: &[f64]) {
        let (m, d) = (self.m, self.d as usize);
        let off = &self.plan.offsets;
        self.level[off[d]..off[d + 1]].copy_from_slice(coeffs);
        for k in (0..d).rev() {
            for pos in off[k]..off[k + 1] {
                let ups = &self.plan.up[pos * m..pos * m + m];
                let mut s = 0.0;
                for (i, &u) in ups.iter().enumerate() {
                    s += self.lo[i] * self.level[u as usize];
                }
                self.level[pos] = s;
            }
        }
    }

    /// Range of the loaded polynomial restricted to `{w ≥ lo}` (its restricted coefficients'
    /// extremes, widened for rounding), and the largest coefficient magnitude.
    pub(crate) fn range(&self) -> (Interval, f64) {
        let raw = output_range(self.plan, &self.level, &self.rpow);
        (widened(raw), raw.2)
    }

    /// Range of the loaded polynomial's reduced partial `∂/∂w_l = ∂_l − ∂_0` (`l = 1..m`)
    /// restricted to `{w ≥ lo}`, widened for rounding.
    pub(crate) fn derivative_range(&mut self, l: usize) -> Interval {
        let (m, d) = (self.m, self.d as usize);
        let Some(lower) = self.lower else {
            return Interval::point(0.0);
        };
        let off = &self.plan.offsets;
        let df = d as f64;
        // β_D(lo^{d−1−k}, e^K) = d (β(lo^{d−1−k}, e^{K+e_l}) − β(…, e^{K+e_0})), K of degree k.
        for pos in 0..off[d] {
            let ups = &self.plan.up[pos * m..pos * m + m];
            self.dlevel[pos] = df * (self.level[ups[l] as usize] - self.level[ups[0] as usize]);
        }
        widened(output_range(lower, &self.dlevel, &self.rpow))
    }
}

/// The restriction of `p` (degree ≤ [`MAX_DEGREE`], `m` variables) to the face spanned by
/// `vertices` (`k ≤ m` of them, barycentric, first `m` entries each): a polynomial in `k`
/// variables whose coefficient `I` is the blossom at `vertices[i]` repeated `I_i` times. The same
/// de Casteljau steps in the same order as the kernel's [`Bernstein::restrict_to_face`] (vertex 0
/// applied first, zero weights skipped), hence the same bits, but walked depth first in one
/// stack buffer (one allocation, the result) where the kernel allocates per step. `None` for a
/// degree without a plan (use the kernel).
pub(crate) fn restrict_to_face(p: &Bernstein, vertices: &[[f64; 4]]) -> Option<Bernstein> {
    let (m, d, k) = (p.vars(), p.degree(), vertices.len());
    if d as usize > MAX_DEGREE || m == 0 || m > MAX_VARS || k == 0 || k > MAX_VARS {
        return None;
    }
    // The de Casteljau buffer is the thread's: zeroing 4 KB on the stack per call was a tenth
    // of a small model's setup in instruction counts (session 19). What a previous call left in
    // it is never read: the walk writes every block below the top before reading it.
    thread_local! {
        static LEVEL: std::cell::RefCell<[f64; LEVEL_CAP]> =
            const { std::cell::RefCell::new([0.0; LEVEL_CAP]) };
    }
    let mut out = vec![0.0; multi_index::count(k, d)];
    LEVEL.with_borrow_mut(|level| {
        restrict_to_face_into(p.coeffs(), m, d, vertices, level, &mut out)
    });
    Bernstein::new(k, d, out).ok()
}

/// [`restrict_to_face`] of the coefficients `coeffs` (degree `d`, `m` variables) into `out`
/// (`count(k, d)` entries, `k = vertices.len()`), with `level` as the de Casteljau buffer: the
/// same bits, nothing allocated. `false` for a shape without a plan.
pub(crate) fn restrict_to_face_into(
    coeffs: &[f64],
    m: usize,
    d: u32,
    vertices: &[[f64; 4]],
    level: &mut [f64; LEVEL_CAP],
    out: &mut [f64],
) -> bool {
    let k = vertices.len();
    if d as usize > MAX_DEGREE || m == 0 || m > MAX_VARS || k == 0 || k > MAX_VARS {
        return false;
    }
    let plan = plan(m, d);
    let top = plan.offsets[d as usize];
    level[top..top + coeffs.len()].copy_from_slice(coeffs);
    // The ranks are one per output coefficient: their count is `count(k, d)` without the
    // binomial's 128-bit division (3 % of a small model's setup, session 20).
    let ranks = face_ranks(k, d);
    face_walk(
        &FaceWalk {
            plan,
            m,
            vertices,
            ranks,
        },
        level,
        d as usize,
        0,
        &mut 0,
        &mut out[..ranks.len()],
    );
    true
}

/// Most polynomials [`restrict_batch_into`] restricts in one walk (the `n² ≤ 9` Jacobian entries
/// of a 3D stage).
pub(crate) const BATCH: usize = 9;

/// The de Casteljau buffer of [`restrict_batch_into`]: `BATCH` lanes per blossom.
pub(crate) type BatchLevels = [[f64; BATCH]; LEVEL_CAP];

/// [`restrict_to_face_into`] of up to [`BATCH`] polynomials of one shape `(m, d)` at once:
/// polynomial `b`'s coefficients are `srcs[b]` (canonical order) and its restriction goes to
/// `out[b * stride_out..]` (`count(k, d)` entries each). One walk of the prefix tree serves every
/// polynomial: each lane performs [`restrict_to_face_into`]'s operations in its order (the same
/// zero weights skipped), hence its bits, while the walk's index work is shared. `false` (nothing
/// written) for a shape without a plan or more than [`BATCH`] polynomials.
pub(crate) fn restrict_batch_into(
    srcs: &[&[f64]],
    (m, d): (usize, u32),
    vertices: &[[f64; 4]],
    level: &mut BatchLevels,
    out: &mut [f64],
    stride_out: usize,
) -> bool {
    let (k, count) = (vertices.len(), srcs.len());
    if d as usize > MAX_DEGREE
        || m == 0
        || m > MAX_VARS
        || k == 0
        || k > MAX_VARS
        || count > BATCH
        || count == 0
    {
        return false;
    }
    let plan = plan(m, d);
    let top = plan.offsets[d as usize];
    let len = plan.offsets[d as usize + 1] - top;
    if srcs.iter().any(|c| c.len() != len) {
        return false;
    }
    for (r, lanes) in level[top..top + len].iter_mut().enumerate() {
        for (b, x) in lanes.iter_mut().enumerate() {
            // Unused lanes hold zeros: never a subnormal or NaN left from an earlier call.
            *x = if b < count { srcs[b][r] } else { 0.0 };
        }
    }
    let ranks = face_ranks(k, d);
    let mut leaf = 0;
    batch_walk(
        &FaceWalk {
            plan,
            m,
            vertices,
            ranks,
        },
        level,
        d as usize,
        0,
        &mut leaf,
        (out, stride_out, count),
    );
    true
}

/// [`face_walk`] on [`BATCH`] lanes.
fn batch_walk(
    walk: &FaceWalk<'_>,
    level: &mut BatchLevels,
    t: usize,
    first: usize,
    leaf: &mut usize,
    (out, stride, count): (&mut [f64], usize, usize),
) {
    let k = walk.vertices.len();
    if t == 0 {
        let at = walk.ranks[*leaf] as usize;
        for (b, &x) in level[walk.plan.offsets[0]].iter().enumerate().take(count) {
            out[b * stride + at] = x;
        }
        *leaf += 1;
        return;
    }
    let m = walk.m;
    let off = &walk.plan.offsets;
    for v in first..k {
        let x = &walk.vertices[v];
        for pos in off[t - 1]..off[t] {
            let ups = &walk.plan.up[pos * m..pos * m + m];
            let mut s = [0.0; BATCH];
            for i in 0..m {
                if x[i] != 0.0 {
                    let (xi, src) = (x[i], &level[ups[i] as usize]);
                    for (acc, &c) in s.iter_mut().zip(src) {
                        *acc += xi * c;
                    }
                }
            }
            level[pos] = s;
        }
        batch_walk(walk, level, t - 1, v, leaf, (&mut *out, stride, count));
    }
}

/// `multi_index::count(k, d)` (coefficients of a degree-`d` polynomial in `k` variables) from
/// the cached walk tables where they exist: the binomial's 128-bit division was 3 % of a small
/// model's setup (session 20).
pub(crate) fn coeff_count(k: usize, d: u32) -> usize {
    if k == 0 || k > MAX_VARS || d as usize > MAX_DEGREE {
        return multi_index::count(k, d);
    }
    face_ranks(k, d).len()
}

/// The largest magnitude of the coefficients of `p.derivative(l)` (the reduced partial
/// `∂_l − ∂_0`, degree `d − 1`, coefficients `d (b_{K+e_l} − b_{K+e_0})` computed as the kernel
/// does), without building it. `None` for degree 0 or a shape without a plan.
pub(crate) fn derivative_max_abs(p: &Bernstein, l: usize) -> Option<f64> {
    let (m, d) = (p.vars(), p.degree());
    if d == 0 || d as usize > MAX_DEGREE || m == 0 || m > MAX_VARS || l >= m {
        return None;
    }
    let plan = plan(m, d);
    let (lo, hi) = (plan.offsets[d as usize - 1], plan.offsets[d as usize]);
    let c = p.coeffs();
    let df = f64::from(d);
    let mut top = 0.0f64;
    for pos in lo..hi {
        // Positions of K + e_l and K + e_0 among the degree-d blossoms: coefficient ranks.
        let ups = &plan.up[pos * m..pos * m + m];
        let x = df * (c[ups[l] as usize - hi] - c[ups[0] as usize - hi]);
        top = top.max(x.abs());
    }
    Some(top)
}

/// A de Casteljau buffer for [`restrict_to_face_into`].
#[cfg(test)]
pub(crate) fn level_buffer() -> [f64; LEVEL_CAP] {
    [0.0; LEVEL_CAP]
}

/// What every node of [`face_walk`] shares.
struct FaceWalk<'a> {
    plan: &'a Plan,
    m: usize,
    vertices: &'a [[f64; 4]],
    /// [`face_ranks`] of the face's vertex count and the degree.
    ranks: &'static [u32],
}

/// The output positions of [`face_walk`]'s leaves in the order it reaches them, for `k`
/// vertices and degree `d`: leaf `i` has applied vertex `v` `counts[v]` times, and its
/// coefficient's place is `multi_index::rank(counts)` (ranking at every leaf was a fifth of the
/// walk, session 19). The walk's order depends on `(k, d)` only.
fn face_ranks(k: usize, d: u32) -> &'static [u32] {
    static RANKS: [[OnceLock<Vec<u32>>; MAX_DEGREE + 1]; MAX_VARS + 1] =
        [const { [const { OnceLock::new() }; MAX_DEGREE + 1] }; MAX_VARS + 1];
    /// The same recursion as [`face_walk`]'s, ranking each leaf.
    fn walk(k: usize, t: u32, first: usize, counts: &mut [u32; MAX_VARS], out: &mut Vec<u32>) {
        if t == 0 {
            out.push(multi_index::rank(&counts[..k]) as u32);
            return;
        }
        for v in first..k {
            counts[v] += 1;
            walk(k, t - 1, v, counts, out);
            counts[v] -= 1;
        }
    }
    RANKS[k][d as usize].get_or_init(|| {
        let mut out = Vec::with_capacity(multi_index::count(k, d));
        walk(k, d, 0, &mut [0; MAX_VARS], &mut out);
        out
    })
}

/// One node of the prefix tree: `level`'s degree-`t` block holds the blossom with the vertices
/// applied so far (vertex `i` as often as the path from the root chose it); children apply a
/// vertex `≥ first` once more. Leaves are numbered in visiting order (`leaf`) and placed by
/// [`face_ranks`].
fn face_walk(
    walk: &FaceWalk<'_>,
    level: &mut [f64; LEVEL_CAP],
    t: usize,
    first: usize,
    leaf: &mut usize,
    out: &mut [f64],
) {
    let k = walk.vertices.len();
    if t == 0 {
        out[walk.ranks[*leaf] as usize] = level[walk.plan.offsets[0]];
        *leaf += 1;
        return;
    }
    let m = walk.m;
    let off = &walk.plan.offsets;
    for v in first..k {
        let x = &walk.vertices[v];
        for pos in off[t - 1]..off[t] {
            let ups = &walk.plan.up[pos * m..pos * m + m];
            let mut s = 0.0;
            for i in 0..m {
                if x[i] != 0.0 {
                    s += x[i] * level[ups[i] as usize];
                }
            }
            level[pos] = s;
        }
        face_walk(walk, level, t - 1, v, leaf, out);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The kernel's exact restriction (`Bernstein::restrict`, vertex by vertex) is the reference:
    /// the ranges here must equal the extremes of its coefficients, and of its derivatives'.
    #[test]
    fn ranges_equal_the_kernel_restriction() {
        let mut rng = ChaCha8Rng::seed_from_u64(19);
        for m in 2..=4usize {
            for d in 0..=5u32 {
                for _ in 0..20 {
                    let p = Bernstein::from_fn(m, d, |_| rng.random_range(-2.0..2.0));
                    // A corner `lo` with Σ lo < 1, sometimes tiny cells.
                    let shrink: f64 = if rng.random_bool(0.5) { 1e-3 } else { 0.6 };
                    let mut lo: Vec<f64> = (0..m).map(|_| rng.random::<f64>()).collect();
                    let s: f64 = lo.iter().sum();
                    for x in lo.iter_mut() {
                        *x *= (1.0 - shrink) / s;
                    }
                    let r = 1.0 - lo.iter().sum::<f64>();
                    let vertices: Vec<Vec<f64>> = (0..m)
                        .map(|j| {
                            let mut v = lo.clone();
                            v[j] += r;
                            v
                        })
                        .collect();
                    let exact = p.restrict(&vertices);
                    let mut h = Homothety::new(m, d, &lo).unwrap();
                    h.load(p.coeffs());
                    let (range, _) = h.range();
                    // The ranges enclose the exact coefficients' and are wider by the rounding
                    // margin only.
                    let close = |r: Interval, e: &Bernstein| {
                        let top = e.coeffs().iter().fold(0.0f64, |a, x| a.max(x.abs()));
                        let (lo, hi) = (e.min_coeff(), e.max_coeff());
                        let margin = 2.0 * BOUND_ROUNDING_MARGIN * top + 1e-12;
                        r.lo <= lo + 1e-12
                            && r.hi >= hi - 1e-12
                            && r.lo >= lo - margin
                            && r.hi <= hi + margin
                    };
                    assert!(close(range, &exact), "m {m} d {d}");
                    // The reduced partials, restricted by the kernel after differentiating.
                    for l in 1..m {
                        let dr = h.derivative_range(l);
                        let reference = p.derivative(l).restrict(&vertices);
                        assert!(
                            close(dr, &reference),
                            "m {m} d {d} l {l}: {dr:?} vs [{}, {}]",
                            reference.min_coeff(),
                            reference.max_coeff()
                        );
                    }
                }
            }
        }
    }

    /// `k` random points of the simplex in `m` variables (barycentric, summing to 1), about a
    /// third of their coordinates zero (the restriction skips those terms).
    fn random_face(rng: &mut ChaCha8Rng, m: usize, k: usize) -> Vec<[f64; 4]> {
        (0..k)
            .map(|_| {
                let mut v = [0.0; 4];
                for x in v.iter_mut().take(m) {
                    if rng.random_bool(0.67) {
                        *x = rng.random::<f64>();
                    }
                }
                let s: f64 = v.iter().sum();
                if s == 0.0 {
                    v[0] = 1.0;
                } else {
                    for x in v.iter_mut() {
                        *x /= s;
                    }
                }
                v
            })
            .collect()
    }

    /// The kernel's `Bernstein::restrict_to_face` is the reference, bit for bit (the same steps in
    /// the same order), on faces of every dimension with vertices on edges, inside faces and in
    /// the interior, and with zero coordinates (skipped terms).
    #[test]
    fn face_restriction_equals_the_kernel_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(23);
        for m in 1..=4usize {
            for d in 0..=MAX_DEGREE as u32 {
                for k in 1..=m {
                    for _ in 0..6 {
                        let p = Bernstein::from_fn(m, d, |_| rng.random_range(-2.0..2.0));
                        let vertices = random_face(&mut rng, m, k);
                        let refs: Vec<Vec<f64>> =
                            vertices.iter().map(|v| v[..m].to_vec()).collect();
                        let kernel = p.restrict_to_face(&refs);
                        let ours = restrict_to_face(&p, &vertices).unwrap();
                        assert_eq!(
                            (ours.vars(), ours.degree()),
                            (kernel.vars(), kernel.degree())
                        );
                        let same = ours
                            .coeffs()
                            .iter()
                            .zip(kernel.coeffs())
                            .all(|(a, b)| a.to_bits() == b.to_bits());
                        assert!(same, "m {m} d {d} k {k}");
                        let mut level = level_buffer();
                        let mut out = vec![f64::NAN; multi_index::count(k, d)];
                        assert!(restrict_to_face_into(
                            p.coeffs(),
                            m,
                            d,
                            &vertices,
                            &mut level,
                            &mut out
                        ));
                        let same = out
                            .iter()
                            .zip(kernel.coeffs())
                            .all(|(a, b)| a.to_bits() == b.to_bits());
                        assert!(same, "into: m {m} d {d} k {k}");
                    }
                }
            }
        }
        let high = Bernstein::constant(3, MAX_DEGREE as u32 + 1, 1.0);
        assert!(restrict_to_face(&high, &[[1.0, 0.0, 0.0, 0.0]]).is_none());
    }

    /// `coeff_count` is the format's count and `derivative_max_abs` the largest coefficient
    /// magnitude of the kernel's derivative, for every shape with a plan.
    #[test]
    fn counts_and_derivative_magnitudes_equal_the_kernel() {
        let mut rng = ChaCha8Rng::seed_from_u64(37);
        for k in 0..=MAX_VARS + 1 {
            for d in 0..=MAX_DEGREE as u32 + 1 {
                assert_eq!(coeff_count(k, d), multi_index::count(k, d), "k {k} d {d}");
            }
        }
        for m in 1..=4usize {
            for d in 0..=MAX_DEGREE as u32 {
                let p = Bernstein::from_fn(m, d, |_| rng.random_range(-2.0..2.0));
                for l in 0..m {
                    let ours = derivative_max_abs(&p, l);
                    if d == 0 {
                        assert!(ours.is_none(), "degree 0 has no plan");
                        continue;
                    }
                    let ours = ours.expect("a plan for every degree 1..=MAX_DEGREE");
                    let kernel = p
                        .derivative(l)
                        .coeffs()
                        .iter()
                        .fold(0.0f64, |a, x| a.max(x.abs()));
                    assert_eq!(ours.to_bits(), kernel.to_bits(), "m {m} d {d} l {l}");
                }
            }
        }
    }

    /// The batched walk gives every polynomial the kernel's `Bernstein::restrict_to_face` bits,
    /// for every shape, batch size and face, with a buffer that earlier calls (and NaNs) left
    /// dirty; it refuses what it does not cover, writing nothing.
    #[test]
    fn batched_face_restriction_equals_the_kernel_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(31);
        let mut level = Box::new([[f64::NAN; BATCH]; LEVEL_CAP]);
        for m in 1..=4usize {
            for d in 0..=MAX_DEGREE as u32 {
                for k in 1..=m {
                    for count in 1..=BATCH {
                        let polys: Vec<Bernstein> = (0..count)
                            .map(|_| Bernstein::from_fn(m, d, |_| rng.random_range(-2.0..2.0)))
                            .collect();
                        let vertices = random_face(&mut rng, m, k);
                        let refs: Vec<Vec<f64>> =
                            vertices.iter().map(|v| v[..m].to_vec()).collect();
                        let len = multi_index::count(k, d);
                        // A stride above the length: the gaps must stay untouched.
                        let stride = len + 1;
                        let mut out = vec![f64::NAN; count * stride];
                        let srcs: Vec<&[f64]> = polys.iter().map(|p| p.coeffs()).collect();
                        assert!(restrict_batch_into(
                            &srcs,
                            (m, d),
                            &vertices,
                            &mut level,
                            &mut out,
                            stride
                        ));
                        for (b, p) in polys.iter().enumerate() {
                            let kernel = p.restrict_to_face(&refs);
                            let ours = &out[b * stride..b * stride + len];
                            let same = ours
                                .iter()
                                .zip(kernel.coeffs())
                                .all(|(a, c)| a.to_bits() == c.to_bits());
                            assert!(same, "m {m} d {d} k {k} count {count} poly {b}");
                            assert!(out[b * stride + len].is_nan(), "gap written");
                        }
                    }
                }
            }
        }
        let one = Bernstein::constant(3, 2, 1.0);
        let vertices = [[1.0, 0.0, 0.0, 0.0]];
        let mut out = vec![f64::NAN; 16];
        let too_many: Vec<&[f64]> = vec![one.coeffs(); BATCH + 1];
        assert!(!restrict_batch_into(
            &too_many,
            (3, 2),
            &vertices,
            &mut level,
            &mut out,
            1
        ));
        let high = Bernstein::constant(3, MAX_DEGREE as u32 + 1, 1.0);
        assert!(!restrict_batch_into(
            &[high.coeffs()],
            (3, MAX_DEGREE as u32 + 1),
            &vertices,
            &mut level,
            &mut out,
            1
        ));
        let short = [1.0, 2.0];
        assert!(!restrict_batch_into(
            &[&short[..]],
            (3, 2),
            &vertices,
            &mut level,
            &mut out,
            1
        ));
        assert!(out.iter().all(|x| x.is_nan()), "a refusal writes nothing");
    }
}
