//! Dense Bernstein polynomials on a simplex with `m` variables (barycentric coordinates).
//!
//! `p(w) = Σ_{|I| = d} c_I B_I(w)`, `B_I(w) = d!/(I_0!…I_{m−1}!) Π w_i^{I_i}`, coefficients in the
//! canonical order of [`ism_format::multi_index`]. Vector-valued polynomials are arrays of these,
//! one per component.
//!
//! Evaluation is de Casteljau: at a vertex every step multiplies by an exact 1 or 0, so the value
//! there is exactly the vertex coefficient; on a face the coefficients off the face never enter.

use std::sync::OnceLock;

use ism_format::multi_index;

use crate::interval::Interval;

use crate::error::{GeomError, Result};
use crate::tables::multinomial;

/// A Bernstein polynomial of degree `d` in `m` barycentric variables.
#[derive(Debug, PartialEq)]
pub struct Bernstein {
    m: usize,
    degree: u32,
    coeffs: Vec<f64>,
}

/// Highest degree whose coefficient buffers a thread recycles ([`recycled`]).
const POOL_DEGREE: usize = 16;
/// Most buffers one thread keeps per shape: a bisection's children hold a few dozen
/// polynomials of one shape at a time, a chain's refinement some hundreds (64 left 2 % more of
/// the torus example's table instructions to the allocator than 256). At most ~12 MB per
/// thread (`Σ_{m ≤ 4, d ≤ 16} count(m, d) · 8 B · 256`), far less in practice: only shapes in
/// use fill up.
const POOL_DEPTH: usize = 256;

thread_local! {
    /// Coefficient buffers of this thread's dropped polynomials, per shape `(m, d)` at
    /// `m · (POOL_DEGREE + 1) + d`. The certified bounds build and drop ~160 k small polynomials
    /// for the torus example's sampler table alone; the system allocator served those in ~290
    /// instructions a pair (callgrind, session 46: a quarter of the table's instructions), most of
    /// its blocks being past its own per-thread cache (7 blocks per size, none above 1 KB).
    static POOL: std::cell::RefCell<Vec<Vec<Vec<f64>>>> =
        const { std::cell::RefCell::new(Vec::new()) };
}

/// The pool slot of shape `(m, d)`, when recycled.
#[inline]
fn pool_slot(m: usize, d: u32) -> Option<usize> {
    (m <= 4 && d as usize <= POOL_DEGREE).then_some(m * (POOL_DEGREE + 1) + d as usize)
}

/// A buffer of a dropped polynomial of shape `(m, d)` from this thread's pool, stale
/// coefficients and all (`count(m, d)` of them: every polynomial has exactly as many); `None`
/// when there is none (or the shape is not pooled).
#[inline]
fn recycled(m: usize, d: u32) -> Option<Vec<f64>> {
    let slot = pool_slot(m, d)?;
    POOL.try_with(|p| p.try_borrow_mut().ok()?.get_mut(slot)?.pop())
        .ok()?
}

/// `count(m, d)` zeros, in a recycled buffer when there is one.
#[inline]
fn zeros(m: usize, d: u32) -> Vec<f64> {
    match recycled(m, d) {
        Some(mut v) => {
            v.fill(0.0);
            v
        }
        None => vec![0.0; multi_index::count(m, d)],
    }
}

/// The coefficients `values` yields, in a recycled buffer when there is one.
#[inline]
fn collected(m: usize, d: u32, values: impl Iterator<Item = f64>) -> Vec<f64> {
    let mut v = recycled(m, d).unwrap_or_default();
    v.clear();
    v.extend(values);
    v
}

impl Clone for Bernstein {
    fn clone(&self) -> Bernstein {
        let coeffs = match recycled(self.m, self.degree) {
            Some(mut v) => {
                v.clear();
                v.extend_from_slice(&self.coeffs);
                v
            }
            None => self.coeffs.clone(),
        };
        Bernstein {
            m: self.m,
            degree: self.degree,
            coeffs,
        }
    }
}

impl Drop for Bernstein {
    /// The coefficient buffer goes back to this thread's pool (a bounded number per shape of
    /// degree ≤ 16 in at most 4 variables), else to the allocator.
    fn drop(&mut self) {
        let Some(slot) = pool_slot(self.m, self.degree) else {
            return;
        };
        if self.coeffs.capacity() == 0 {
            return;
        }
        let v = std::mem::take(&mut self.coeffs);
        let _ = POOL.try_with(|p| {
            if let Ok(mut p) = p.try_borrow_mut() {
                if p.is_empty() {
                    p.resize_with(5 * (POOL_DEGREE + 1), Vec::new);
                }
                let shelf = &mut p[slot];
                if shelf.len() < POOL_DEPTH {
                    shelf.push(v);
                }
            }
        });
    }
}

/// Highest degree whose index tables are cached for the life of the process. Products in the
/// certified bounds reach `2n · 2(d − 1) + …` for rational stages of degree `d ≤ 16`, i.e. below
/// 128 in 3D; higher degrees still work, with tables rebuilt per call.
const CACHED_DEGREE: usize = 128;

/// Index tables of one shape `(m, d)`: the canonical list, multinomials, ranks of `K + e_i` for the
/// degree-`d` indices `K` among degree `d + 1`, and a dense rank lookup. Building them costs more
/// than most operations that use them (ranks need binomials), hence the cache.
#[derive(Debug)]
struct Shape {
    /// All degree-`d` indices, canonical order, flat (`m` per index).
    all: Vec<u32>,
    /// `d! / Π I_i!` per index.
    multinom: Vec<f64>,
    /// `up[r * m + i]` = rank, among degree-`d + 1` indices, of `K_r + e_i`.
    up: Vec<usize>,
    /// Rank of every degree-`d` index, addressed by its first `m − 1` entries in radix `d + 1`.
    dense: Vec<u32>,
    /// Rank of `d · e_i`.
    vertex: [usize; 4],
}

impl Shape {
    fn build(m: usize, d: u32) -> Shape {
        let all = multi_index::all(m, d);
        let multinom = all.chunks_exact(m.max(1)).map(multinomial).collect();
        let mut up = Vec::with_capacity(all.len());
        let mut idx = vec![0u32; m];
        for k in all.chunks_exact(m.max(1)) {
            for i in 0..m {
                idx.copy_from_slice(k);
                idx[i] += 1;
                up.push(multi_index::rank(&idx));
            }
        }
        let radix = d as usize + 1;
        let mut dense = vec![0u32; radix.pow(m.saturating_sub(1) as u32)];
        for (r, k) in all.chunks_exact(m.max(1)).enumerate() {
            dense[dense_key(&k[..m.saturating_sub(1)], radix)] = r as u32;
        }
        let mut vertex = [0usize; 4];
        for (i, v) in vertex.iter_mut().enumerate().take(m) {
            idx.fill(0);
            idx[i] = d;
            *v = multi_index::rank(&idx);
        }
        Shape {
            all,
            multinom,
            up,
            dense,
            vertex,
        }
    }

    /// Rank of a degree-`d` index.
    #[inline]
    fn rank(&self, index: &[u32], d: u32) -> usize {
        let m = index.len();
        self.dense[dense_key(&index[..m.saturating_sub(1)], d as usize + 1)] as usize
    }
}

#[inline]
fn dense_key(head: &[u32], radix: usize) -> usize {
    head.iter().fold(0usize, |acc, &e| acc * radix + e as usize)
}

static SHAPES: [[OnceLock<Shape>; CACHED_DEGREE + 1]; 5] =
    [const { [const { OnceLock::new() }; CACHED_DEGREE + 1] }; 5];

/// Where [`Bernstein::replace_vertex`] finds each output coefficient among its de Casteljau
/// levels, for one cached shape `(m, d)`: level `t` (the blossom values `b(r^t, e^J)`,
/// `|J| = d − t`) starts at `offsets[t]` of the flat level buffer, and output `r` with vertex
/// `a` replaced is entry `gather[r · m + a]` (`t = I_a`, `J = I − I_a e_a`). A pure function of
/// the shape, so computed once instead of a rank lookup per coefficient and call.
#[derive(Debug)]
struct ReplacePlan {
    offsets: Vec<usize>,
    gather: Vec<u32>,
}

impl ReplacePlan {
    fn build(m: usize, d: u32) -> ReplacePlan {
        let mut offsets = Vec::with_capacity(d as usize + 2);
        let mut acc = 0usize;
        for t in 0..=d {
            offsets.push(acc);
            acc += multi_index::count(m, d - t);
        }
        offsets.push(acc);
        let top = shape(m, d);
        let mut gather = Vec::with_capacity(top.multinom.len() * m);
        let mut j = vec![0u32; m];
        for i in top.all.chunks_exact(m.max(1)) {
            for a in 0..m {
                j.copy_from_slice(i);
                let t = j[a];
                j[a] = 0;
                let lower = d - t;
                gather.push((offsets[t as usize] + shape(m, lower).rank(&j, lower)) as u32);
            }
        }
        ReplacePlan { offsets, gather }
    }
}

static REPLACE_PLANS: [[OnceLock<ReplacePlan>; CACHED_DEGREE + 1]; 5] =
    [const { [const { OnceLock::new() }; CACHED_DEGREE + 1] }; 5];

/// A cached shape, or one built for a single use (beyond the cache).
enum ShapeRef {
    Cached(&'static Shape),
    Owned(Box<Shape>),
}

impl std::ops::Deref for ShapeRef {
    type Target = Shape;
    #[inline]
    fn deref(&self) -> &Shape {
        match self {
            ShapeRef::Cached(s) => s,
            ShapeRef::Owned(s) => s,
        }
    }
}

/// Highest factor degree whose product plans ([`product_ranks`]) are cached: the determinants of
/// stage Jacobians in the certified bounds multiply factors of degree `d − 1` and `2 (d − 1)` for
/// a polynomial stage of degree `d` (6 for the examples' quartics), a rational stage's numerators
/// `d − 1` and `d`, and its denominator's powers `2d` by `2d`; higher products take the summing
/// path.
const PRODUCT_DEGREE: usize = 12;

static PRODUCTS: [[[OnceLock<Vec<u32>>; PRODUCT_DEGREE + 1]; PRODUCT_DEGREE + 1]; 5] =
    [const { [const { [const { OnceLock::new() }; PRODUCT_DEGREE + 1] }; PRODUCT_DEGREE + 1] }; 5];

/// For a product of degrees `da` and `db` in `m` variables: the rank of `a + b` among the indices
/// of degree `da + db`, at `i · count(m, db) + j` for the `i`-th index `a` of degree `da` and the
/// `j`-th `b` of degree `db` (canonical order). [`Bernstein::mul`] sums the index and looks its rank
/// up per term otherwise (a fifth of the sampler's setup on a model of quartic stages, session
/// 36). `None` past the cached shapes.
fn product_ranks(m: usize, da: u32, db: u32) -> Option<&'static [u32]> {
    let (ia, ib) = (da as usize, db as usize);
    if m > 4 || ia > PRODUCT_DEGREE || ib > PRODUCT_DEGREE {
        return None;
    }
    let plan = PRODUCTS[m][ia][ib].get_or_init(|| {
        let (sa, sb, sd) = (shape(m, da), shape(m, db), shape(m, da + db));
        let mut sum = vec![0u32; m];
        let mut ranks = Vec::with_capacity(sa.multinom.len() * sb.multinom.len());
        for a in sa.all.chunks_exact(m.max(1)) {
            for b in sb.all.chunks_exact(m.max(1)) {
                for k in 0..m {
                    sum[k] = a[k] + b[k];
                }
                ranks.push(sd.rank(&sum, da + db) as u32);
            }
        }
        ranks
    });
    Some(plan)
}

/// Highest degree whose elevation and edge-split plans are cached ([`elevation_plan`],
/// [`split_plan`]): the sampler's polynomials reach degree `(n + 1) d` (a rational stage's
/// determinant denominator, 16 for a quartic in 3D); higher degrees compute their ranks per call.
const PLAN_DEGREE: usize = 32;

/// The terms of one elevation step from degree `d` in `m` variables: for the `r`-th index `J` of
/// degree `d + 1` and each `k`, entry `r · m + k` holds `(J_k / (d + 1), rank of J − e_k)`, the
/// factor `0.0` where `J_k = 0` (no term). The factor is the same single division
/// [`Bernstein::elevate_general`] makes, so both give the same bits.
fn elevation_plan(m: usize, d: u32) -> Option<&'static [(f64, u32)]> {
    type Plan = OnceLock<Vec<(f64, u32)>>;
    static PLANS: [[Plan; PLAN_DEGREE + 1]; 5] =
        [const { [const { OnceLock::new() }; PLAN_DEGREE + 1] }; 5];
    if m == 0 || m > 4 || d as usize >= PLAN_DEGREE {
        return None;
    }
    let plan = PLANS[m][d as usize].get_or_init(|| {
        let (lower, upper) = (shape(m, d), shape(m, d + 1));
        let mut plan = vec![(0.0, 0u32); upper.multinom.len() * m];
        // `up` lists `K + e_k` for every degree-`d` index `K`: inverted, it gives `J − e_k`.
        for (r, ups) in lower.up.chunks_exact(m).enumerate() {
            for (k, &j) in ups.iter().enumerate() {
                let jk = upper.all[j * m + k];
                plan[j * m + k] = (f64::from(jk) / f64::from(d + 1), r as u32);
            }
        }
        plan
    });
    Some(plan)
}

/// The lines of [`Bernstein::split_edge`] for degree `d`, `m` variables and the edge `(a, b)`:
/// for each index `I` with `I_b = 0`, in canonical order, the ranks of `I − k e_a + k e_b`,
/// `k = 0..=I_a` (the line's length is `I_a + 1`), one after the other. Each index lies on
/// exactly one line, so the plan has as many entries as coefficients.
fn split_plan(m: usize, d: u32, a: usize, b: usize) -> Option<&'static [u32]> {
    /// Per edge `(a, b)`.
    type Plans = [[OnceLock<Vec<u32>>; 4]; 4];
    static PLANS: [[Plans; PLAN_DEGREE + 1]; 5] =
        [const { [const { [const { [const { OnceLock::new() }; 4] }; 4] }; PLAN_DEGREE + 1] }; 5];
    if m > 4 || a >= m || b >= m || a == b || d as usize > PLAN_DEGREE {
        return None;
    }
    let plan = PLANS[m][d as usize][a][b].get_or_init(|| {
        let sh = shape(m, d);
        let mut plan = Vec::with_capacity(sh.multinom.len());
        let mut idx = [0u32; 4];
        for i in sh.all.chunks_exact(m) {
            if i[b] != 0 {
                continue;
            }
            let l = i[a];
            idx[..m].copy_from_slice(i);
            for k in 0..=l {
                idx[a] = l - k;
                idx[b] = k;
                plan.push(sh.rank(&idx[..m], d) as u32);
            }
        }
        plan
    });
    Some(plan)
}

/// The tables of `(m, d)`: cached for `m ≤ 4`, `d ≤ CACHED_DEGREE`, built on the spot otherwise.
/// Inlined: the cached path is a bounds test and a load, and every operation asks for one to
/// three shapes (a call each was 3 % of the sampler's setup).
#[inline]
fn shape(m: usize, d: u32) -> ShapeRef {
    if m <= 4 && (d as usize) <= CACHED_DEGREE {
        ShapeRef::Cached(SHAPES[m][d as usize].get_or_init(|| Shape::build(m, d)))
    } else {
        ShapeRef::Owned(Box::new(Shape::build(m, d)))
    }
}

/// One de Casteljau step with point `x`: degree-`t + 1` coefficients `c` → degree-`t` into `out`
/// (`count(m, t)` entries). Zero weights are skipped, so a vertex or edge point mixes only the
/// coefficients it touches (exact values at vertices).
fn casteljau_into(m: usize, up: &[usize], c: &[f64], x: &[f64], out: &mut [f64]) {
    for (r, o) in out.iter_mut().enumerate() {
        let mut s = 0.0;
        for i in 0..m {
            if x[i] != 0.0 {
                s += x[i] * c[up[r * m + i]];
            }
        }
        *o = s;
    }
}

/// [`casteljau_into`] into a new vector.
fn casteljau_step(m: usize, t: u32, up: &[usize], c: &[f64], x: &[f64]) -> Vec<f64> {
    let mut out = vec![0.0; multi_index::count(m, t)];
    casteljau_into(m, up, c, x, &mut out);
    out
}

/// De Casteljau from degree `d` down to 0 at `x` in one scratch buffer, whose two halves hold
/// alternate levels (no allocation per level).
fn casteljau_to_value(m: usize, d: u32, coeffs: &[f64], x: &[f64], scratch: &mut Vec<f64>) -> f64 {
    let count = coeffs.len();
    scratch.clear();
    scratch.resize(2 * count, 0.0);
    let (mut cur, mut next) = scratch.split_at_mut(count);
    cur.copy_from_slice(coeffs);
    for t in (0..d).rev() {
        let sh = shape(m, t);
        casteljau_into(m, &sh.up, cur, x, &mut next[..sh.multinom.len()]);
        std::mem::swap(&mut cur, &mut next);
    }
    cur[0]
}

thread_local! {
    /// Scratch space of the de Casteljau loops (one per thread: evaluation and restriction are
    /// called from rayon workers, millions of times, on small polynomials).
    static SCRATCH: std::cell::RefCell<Vec<f64>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// How to restrict polynomials to one sub-simplex by replacing the vertices one at a time: vertex
/// `k` of the current simplex is replaced by the target's vertex `k`, written in the current
/// simplex's barycentric coordinates.
#[derive(Clone, Debug)]
pub struct Restriction {
    points: Vec<[f64; crate::MAX_VARS]>,
    vertices: Vec<Vec<f64>>,
}

impl Restriction {
    /// How much restricting a degree-`d` polynomial with this plan can grow its coefficients'
    /// magnitude, and the rounding of each de Casteljau step before it: each replacement is `d`
    /// steps with the weights `λ` (the new vertex in the current simplex's coordinates), and a
    /// step scales by at most `Σ |λ_i|` — 1 when the new vertex is inside the current simplex (a
    /// convex combination), more when it is outside (the interior children of a red refinement,
    /// where `λ` holds a `−1` after the first replacements: 3ᵈ). The product over the
    /// replacements.
    pub fn amplification(&self, d: u32) -> f64 {
        let exponent = i32::try_from(d).unwrap_or(i32::MAX);
        self.points
            .iter()
            .map(|lam| lam.iter().map(|x| x.abs()).sum::<f64>().powi(exponent))
            .product()
    }

    /// The plan for the sub-simplex with barycentric `vertices`; `None` when a replacement would be
    /// degenerate (a new vertex's coordinate on the vertex it replaces is not clearly positive) or
    /// there are more than `MAX_VARS` variables.
    pub fn new(vertices: &[Vec<f64>]) -> Option<Restriction> {
        let m = vertices.len();
        if m == 0 || m > crate::MAX_VARS || vertices.iter().any(|v| v.len() < m) {
            return None;
        }
        // Columns: the current simplex's vertices in the original coordinates.
        let mut cur = [[0.0; crate::MAX_VARS]; crate::MAX_VARS];
        for (i, row) in cur.iter_mut().enumerate().take(m) {
            row[i] = 1.0;
        }
        let mut points = Vec::with_capacity(m);
        for k in 0..m {
            let mut target = [0.0; crate::MAX_VARS];
            target[..m].copy_from_slice(&vertices[k][..m]);
            let lam = crate::linalg::solve(m, &cur, &target)?;
            // Far from zero, so the solve's rounding stays at the level of the coefficients'.
            if lam[k].is_nan() || lam[k] <= 1e-6 {
                return None;
            }
            points.push(lam);
            for (i, row) in cur.iter_mut().enumerate().take(m) {
                row[k] = vertices[k][i];
            }
        }
        Some(Restriction {
            points,
            vertices: vertices.to_vec(),
        })
    }
}

impl Bernstein {
    /// A polynomial from its coefficients in canonical order.
    ///
    /// # Errors
    /// [`GeomError::Coefficients`] when `coeffs.len() != C(d + m − 1, m − 1)` or `m == 0`.
    pub fn new(m: usize, degree: u32, coeffs: Vec<f64>) -> Result<Bernstein> {
        let expected = multi_index::count(m, degree);
        if m == 0 || coeffs.len() != expected {
            return Err(GeomError::Coefficients {
                vars: m,
                degree,
                expected,
                found: coeffs.len(),
            });
        }
        Ok(Bernstein { m, degree, coeffs })
    }

    /// The constant `c` as a degree-`d` polynomial (all coefficients `c`).
    pub fn constant(m: usize, degree: u32, c: f64) -> Bernstein {
        Bernstein {
            m,
            degree,
            coeffs: vec![c; multi_index::count(m, degree)],
        }
    }

    /// Coefficients from a function of the multi-index (e.g. `|i| i[0] as f64 / d as f64`).
    pub fn from_fn(m: usize, degree: u32, mut f: impl FnMut(&[u32]) -> f64) -> Bernstein {
        let coeffs = shape(m, degree)
            .all
            .chunks_exact(m.max(1))
            .map(&mut f)
            .collect();
        Bernstein { m, degree, coeffs }
    }

    /// Number of variables `m`.
    pub fn vars(&self) -> usize {
        self.m
    }

    /// Degree `d`.
    pub fn degree(&self) -> u32 {
        self.degree
    }

    /// Coefficients in canonical order.
    pub fn coeffs(&self) -> &[f64] {
        &self.coeffs
    }

    /// Consumes into the coefficient vector.
    pub fn into_coeffs(mut self) -> Vec<f64> {
        std::mem::take(&mut self.coeffs)
    }

    /// The exact value at vertex `i`: the coefficient of `d·e_i`.
    pub fn vertex_value(&self, i: usize) -> f64 {
        if self.m <= 4 {
            return self.coeffs[shape(self.m, self.degree).vertex[i]];
        }
        let mut idx = vec![0u32; self.m];
        idx[i] = self.degree;
        self.coeffs[multi_index::rank(&idx)]
    }

    /// Smallest coefficient (a lower bound of the polynomial on the simplex).
    pub fn min_coeff(&self) -> f64 {
        self.coeffs.iter().copied().fold(f64::INFINITY, f64::min)
    }

    /// Largest coefficient (an upper bound on the simplex).
    pub fn max_coeff(&self) -> f64 {
        self.coeffs
            .iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max)
    }

    /// `p(w)` by de Casteljau (`w` has `m` entries; need not sum to 1: the homogeneous form is
    /// evaluated).
    pub fn eval(&self, w: &[f64]) -> f64 {
        SCRATCH.with(|scratch| match scratch.try_borrow_mut() {
            Ok(mut buf) => casteljau_to_value(self.m, self.degree, &self.coeffs, w, &mut buf),
            Err(_) => casteljau_to_value(self.m, self.degree, &self.coeffs, w, &mut Vec::new()),
        })
    }

    /// An enclosure of `p` over the box `w ∈ [w_i]` of barycentric coordinates, by de Casteljau in
    /// interval arithmetic. The homogeneous form is evaluated, so points of the box off the plane
    /// `Σ w = 1` only widen the result: it contains every value of `p` on the box's part of the
    /// simplex.
    pub fn eval_interval(&self, w: &[Interval]) -> Interval {
        let m = self.m;
        let mut c: Vec<Interval> = self.coeffs.iter().map(|&x| Interval::point(x)).collect();
        for t in (0..self.degree).rev() {
            let shape = shape(m, t);
            let count = multi_index::count(m, t);
            let mut next = Vec::with_capacity(count);
            for r in 0..count {
                let mut s = Interval::point(0.0);
                for (i, wi) in w.iter().enumerate().take(m) {
                    s = s + *wi * c[shape.up[r * m + i]];
                }
                next.push(s);
            }
            c = next;
        }
        c[0]
    }

    /// `[min coefficient, max coefficient]`: an enclosure of `p` on the simplex.
    pub fn range(&self) -> Interval {
        Interval::new(self.min_coeff(), self.max_coeff())
    }

    /// The homogeneous partial derivative `∂p/∂w_j`, degree `d − 1`: coefficients `d c_{K + e_j}`.
    /// Degree 0 gives the zero polynomial of degree 0.
    pub fn partial(&self, j: usize) -> Bernstein {
        let m = self.m;
        if self.degree == 0 {
            return Bernstein::constant(m, 0, 0.0);
        }
        let t = self.degree - 1;
        let up = &shape(m, t).up;
        let d = f64::from(self.degree);
        let coeffs = (0..multi_index::count(m, t))
            .map(|r| d * self.coeffs[up[r * m + j]])
            .collect();
        Bernstein {
            m,
            degree: t,
            coeffs,
        }
    }

    /// Directional derivative along `e_k − e_0` (the reduced-coordinate partial `∂/∂w_k` with
    /// `w_0 = 1 − Σ`): coefficients `d (c_{K + e_k} − c_{K + e_0})`, degree `d − 1`.
    pub fn derivative(&self, k: usize) -> Bernstein {
        self.directional(k, 0)
    }

    /// Directional derivative along `e_a − e_b`, degree `d − 1`.
    pub fn directional(&self, a: usize, b: usize) -> Bernstein {
        let m = self.m;
        if self.degree == 0 {
            return Bernstein::constant(m, 0, 0.0);
        }
        let t = self.degree - 1;
        let up = &shape(m, t).up;
        let d = f64::from(self.degree);
        let coeffs = collected(
            m,
            t,
            (0..multi_index::count(m, t))
                .map(|r| d * (self.coeffs[up[r * m + a]] - self.coeffs[up[r * m + b]])),
        );
        Bernstein {
            m,
            degree: t,
            coeffs,
        }
    }

    /// The product (degree `a + b`): `B^a_I B^b_J = C(a;I) C(b;J) / C(a+b;I+J) · B^{a+b}_{I+J}`.
    ///
    /// # Panics
    /// If the variable counts differ.
    pub fn mul(&self, other: &Bernstein) -> Bernstein {
        assert_eq!(self.m, other.m, "Bernstein::mul: variable counts differ");
        let m = self.m;
        let d = self.degree + other.degree;
        let mut out = zeros(m, d);
        let (sa, sb, sd) = (shape(m, self.degree), shape(m, other.degree), shape(m, d));
        let term = |out: &mut [f64], ca: f64, j: usize, r: usize| {
            out[r] += ca * sb.multinom[j] / sd.multinom[r] * other.coeffs[j];
        };
        if let Some(ranks) = product_ranks(m, self.degree, other.degree) {
            // The same terms in the same order as below, the ranks looked up instead of summed.
            let nb = sb.multinom.len();
            for (i, row) in ranks.chunks_exact(nb).enumerate() {
                if self.coeffs[i] == 0.0 {
                    continue;
                }
                let ca = sa.multinom[i] * self.coeffs[i];
                // `term`'s arithmetic with `b`'s entries walked alongside the ranks.
                for ((&r, &mb), &cb) in row.iter().zip(&sb.multinom).zip(&other.coeffs) {
                    let r = r as usize;
                    out[r] += ca * mb / sd.multinom[r] * cb;
                }
            }
        } else {
            let mut sum = vec![0u32; m];
            for (i, a) in sa.all.chunks_exact(m).enumerate() {
                if self.coeffs[i] == 0.0 {
                    continue;
                }
                let ca = sa.multinom[i] * self.coeffs[i];
                for (j, b) in sb.all.chunks_exact(m).enumerate() {
                    for k in 0..m {
                        sum[k] = a[k] + b[k];
                    }
                    term(&mut out, ca, j, sd.rank(&sum, d));
                }
            }
        }
        Bernstein {
            m,
            degree: d,
            coeffs: out,
        }
    }

    /// Sum of two polynomials of the same shape (elevate first if the degrees differ).
    ///
    /// # Panics
    /// If the shapes differ.
    pub fn add(&self, other: &Bernstein) -> Bernstein {
        // `1 · b` is exact: the same sums as `a + b`.
        let mut sum = self.clone();
        sum.add_scaled(other, 1.0);
        sum
    }

    /// `self += s · other` in place: bit-identical to `self.add(&other.scale(s))` (each
    /// coefficient `a + s·b`, the product rounded first) without its two allocations.
    ///
    /// # Panics
    /// If the shapes differ.
    pub fn add_scaled(&mut self, other: &Bernstein, s: f64) {
        assert!(
            self.m == other.m && self.degree == other.degree,
            "Bernstein::add_scaled (or add): shapes differ"
        );
        for (a, b) in self.coeffs.iter_mut().zip(&other.coeffs) {
            *a += s * b;
        }
    }

    /// `s · p`.
    pub fn scale(&self, s: f64) -> Bernstein {
        Bernstein {
            m: self.m,
            degree: self.degree,
            coeffs: collected(self.m, self.degree, self.coeffs.iter().map(|c| s * c)),
        }
    }

    /// Degree elevation by one: `c'_I = Σ_i I_i/(d+1) · c_{I − e_i}`.
    pub fn elevate(&self) -> Bernstein {
        let m = self.m;
        let d1 = self.degree + 1;
        let Some(plan) = elevation_plan(m, self.degree) else {
            return self.elevate_general();
        };
        // The same terms in the same order as `elevate_general`, with `J − e_k`'s rank and the
        // factor `J_k / (d + 1)` looked up (a rank per term was most of the elevation's cost).
        let coeffs = collected(
            m,
            d1,
            plan.chunks_exact(m).map(|terms| {
                let mut s = 0.0;
                for &(factor, r) in terms {
                    if factor != 0.0 {
                        s += factor * self.coeffs[r as usize];
                    }
                }
                s
            }),
        );
        Bernstein {
            m,
            degree: d1,
            coeffs,
        }
    }

    /// [`Bernstein::elevate`] with every rank computed (shapes beyond the cached plans).
    fn elevate_general(&self) -> Bernstein {
        let m = self.m;
        let d1 = self.degree + 1;
        let mut idx = vec![0u32; m];
        let lower = shape(m, self.degree);
        let coeffs = shape(m, d1)
            .all
            .chunks_exact(m)
            .map(|i| {
                let mut s = 0.0;
                for k in 0..m {
                    if i[k] > 0 {
                        idx.copy_from_slice(i);
                        idx[k] -= 1;
                        s += f64::from(i[k]) / f64::from(d1)
                            * self.coeffs[lower.rank(&idx, self.degree)];
                    }
                }
                s
            })
            .collect();
        Bernstein {
            m,
            degree: d1,
            coeffs,
        }
    }

    /// Elevated to degree `target ≥ d` (unchanged when equal).
    pub fn elevate_to(&self, target: u32) -> Bernstein {
        if self.degree >= target {
            return self.clone();
        }
        let mut p = self.elevate();
        while p.degree < target {
            p = p.elevate();
        }
        p
    }

    /// The same polynomial on the simplex whose vertex `a` is replaced by the point `r`
    /// (barycentric, `m` entries): coefficient `I` is the blossom at `r` repeated `I_a` times and
    /// `e_i` repeated `I_i` times (`i ≠ a`), computed level by level (`O(d · count · m)`).
    pub fn replace_vertex(&self, a: usize, r: &[f64]) -> Bernstein {
        let m = self.m;
        let d = self.degree;
        if m == 0 || m > crate::MAX_VARS || d as usize > CACHED_DEGREE {
            return Bernstein {
                m,
                degree: d,
                coeffs: self.replace_vertex_general(a, r),
            };
        }
        let plan = REPLACE_PLANS[m][d as usize].get_or_init(|| ReplacePlan::build(m, d));
        let fill = |levels: &mut Vec<f64>| -> Vec<f64> {
            let offsets = &plan.offsets;
            levels.clear();
            levels.resize(offsets[d as usize + 1], 0.0);
            levels[..self.coeffs.len()].copy_from_slice(&self.coeffs);
            for t in 0..d as usize {
                let (done, rest) = levels.split_at_mut(offsets[t + 1]);
                let len = offsets[t + 2] - offsets[t + 1];
                let up = &shape(m, d - t as u32 - 1).up;
                casteljau_into(m, up, &done[offsets[t]..], r, &mut rest[..len]);
            }
            collected(
                m,
                d,
                plan.gather
                    .iter()
                    .skip(a)
                    .step_by(m)
                    .map(|&g| levels[g as usize]),
            )
        };
        let coeffs = SCRATCH.with(|scratch| match scratch.try_borrow_mut() {
            Ok(mut buf) => fill(&mut buf),
            Err(_) => fill(&mut Vec::new()),
        });
        Bernstein {
            m,
            degree: d,
            coeffs,
        }
    }

    /// [`Bernstein::replace_vertex`] for any shape, with per-level vectors and the index tables
    /// fetched once per call (for shapes beyond the cache, where fetching builds them).
    fn replace_vertex_general(&self, a: usize, r: &[f64]) -> Vec<f64> {
        let m = self.m;
        let d = self.degree;
        let mut levels = vec![self.coeffs.clone()];
        for t in 0..d {
            let next = casteljau_step(
                m,
                d - t - 1,
                &shape(m, d - t - 1).up,
                &levels[t as usize],
                r,
            );
            levels.push(next);
        }
        let mut j = vec![0u32; m];
        let shapes: Vec<ShapeRef> = (0..=d).map(|t| shape(m, t)).collect();
        shapes[d as usize]
            .all
            .chunks_exact(m)
            .map(|i| {
                j.copy_from_slice(i);
                let t = j[a];
                j[a] = 0;
                let lower = d - t;
                levels[t as usize][shapes[lower as usize].rank(&j, lower)]
            })
            .collect()
    }

    /// Splits edge `(a, b)` at its midpoint: the first child has vertex `b` replaced by the midpoint
    /// (the half where `w_a ≥ w_b`), the second has vertex `a` replaced. Both keep the parent's
    /// orientation and vertex order.
    ///
    /// Only the coefficients along the edge's direction mix: for each multi-index `J` of the other
    /// variables, the line `c_{J + (L−k) e_a + k e_b}` (`k = 0..L`, `L = d − |J|`) is a univariate
    /// Bernstein polynomial, and one de Casteljau triangle at `1/2` gives both halves (its first
    /// and last diagonals). `O(d · count)` with no per-level allocation, and every sum is the one
    /// [`Bernstein::replace_vertex`] forms (`0 + ½x + ½y`), so the result is bit-identical to it.
    pub fn split_edge(&self, a: usize, b: usize) -> (Bernstein, Bernstein) {
        let m = self.m;
        if a == b || a >= m || b >= m || m > 4 {
            let mut mid = vec![0.0; m];
            mid[a] = 0.5;
            mid[b] = 0.5;
            return (self.replace_vertex(b, &mid), self.replace_vertex(a, &mid));
        }
        let d = self.degree;
        let sh = shape(m, d);
        let mut left = zeros(m, d);
        let mut right = zeros(m, d);
        let len = d as usize + 1;
        // The line and its ranks on the stack up to degree 63 (every polynomial the kernel and
        // the sampler's area elements form): the sampler splits ~26 polynomials per leaf, and two
        // heap buffers per split were a large part of its setup's allocations.
        const STACK: usize = 64;
        let (mut line_stack, mut ranks_stack) = ([0.0; STACK], [0usize; STACK]);
        let (mut line_heap, mut ranks_heap) = (Vec::new(), Vec::new());
        let (line, ranks): (&mut [f64], &mut [usize]) = if len <= STACK {
            (&mut line_stack[..len], &mut ranks_stack[..len])
        } else {
            line_heap.resize(len, 0.0);
            ranks_heap.resize(len, 0);
            (&mut line_heap, &mut ranks_heap)
        };
        // The lower-indexed variable's term comes first in `replace_vertex`'s sums.
        let a_first = a < b;
        if let Some(plan) = split_plan(m, d, a, b) {
            // The same lines in the same order as below, their ranks looked up (a rank per
            // coefficient was a third of the split's cost).
            let mut rest = plan;
            while let Some(&first) = rest.first() {
                let l = sh.all[first as usize * m + a] as usize;
                let (ranks, tail) = rest.split_at(l + 1);
                for (x, &r) in line.iter_mut().zip(ranks) {
                    *x = self.coeffs[r as usize];
                }
                halve_line(&mut line[..=l], a_first, |level, lo, hi| {
                    left[ranks[level] as usize] = lo;
                    right[ranks[l - level] as usize] = hi;
                });
                rest = tail;
            }
            let child = |coeffs| Bernstein {
                m,
                degree: d,
                coeffs,
            };
            return (child(left), child(right));
        }
        let mut idx = [0u32; 4];
        for i in sh.all.chunks_exact(m) {
            if i[b] != 0 {
                continue;
            }
            let l = i[a] as usize;
            idx[..m].copy_from_slice(i);
            for k in 0..=l {
                idx[a] = (l - k) as u32;
                idx[b] = k as u32;
                ranks[k] = sh.rank(&idx[..m], d);
                line[k] = self.coeffs[ranks[k]];
            }
            halve_line(&mut line[..=l], a_first, |level, lo, hi| {
                left[ranks[level]] = lo;
                right[ranks[l - level]] = hi;
            });
        }
        let child = |coeffs| Bernstein {
            m,
            degree: d,
            coeffs,
        };
        (child(left), child(right))
    }

    /// Restriction to the sub-simplex with barycentric vertices `vertices[0..m]` (each `m` entries):
    /// coefficient `I` is the blossom at `vertices[i]` repeated `I_i` times. Computed by replacing
    /// the vertices one at a time (`O(m² · d · count)`), or directly from the blossom
    /// (`O(count² · m)`) when a replacement would be degenerate; for bisection prefer
    /// [`Bernstein::split_edge`].
    pub fn restrict(&self, vertices: &[Vec<f64>]) -> Bernstein {
        match Restriction::new(vertices) {
            Some(plan) => self.restrict_with(&plan),
            None => self.restrict_by_blossom(vertices),
        }
    }

    /// [`Bernstein::restrict`] with a precomputed plan (shared by every polynomial restricted to
    /// the same sub-simplex).
    pub fn restrict_with(&self, plan: &Restriction) -> Bernstein {
        if plan.points.len() != self.m {
            return self.restrict_by_blossom(&plan.vertices);
        }
        let mut p = self.clone();
        for (k, lam) in plan.points.iter().enumerate() {
            p = p.replace_vertex(k, &lam[..self.m]);
        }
        p
    }

    #[cfg(test)]
    fn restrict_by_replacement(&self, vertices: &[Vec<f64>]) -> Option<Bernstein> {
        Restriction::new(vertices).map(|plan| self.restrict_with(&plan))
    }

    fn restrict_by_blossom(&self, vertices: &[Vec<f64>]) -> Bernstein {
        self.restrict_to_face(&vertices[..self.m])
    }

    /// Restriction to the sub-simplex (of any dimension) spanned by `vertices` (barycentric, `m`
    /// entries each): a polynomial in `vertices.len()` variables whose coefficient `I` is the
    /// blossom at `vertices[i]` repeated `I_i` times. `O(count_out · count · m)`.
    pub fn restrict_to_face(&self, vertices: &[Vec<f64>]) -> Bernstein {
        let k1 = vertices.len();
        let d = self.degree;
        let out_shape = shape(k1, d);
        let mut coeffs = vec![0.0; out_shape.multinom.len()];
        if k1 == 0 {
            return Bernstein {
                m: 0,
                degree: d,
                coeffs,
            };
        }
        // Coefficient I applies vertex 0 I_0 times, then vertex 1 I_1 times, …: indices sharing a
        // prefix share those de Casteljau steps, so walk the prefix tree depth first (the same
        // steps in the same order per coefficient as one chain each, hence the same bits).
        let mut idx = vec![0u32; k1];
        let ups: Vec<ShapeRef> = (0..d).map(|t| shape(self.m, t)).collect();
        let walk = FaceWalk {
            vertices,
            ups: &ups,
            out_shape: &out_shape,
            degree: d,
        };
        self.face_prefix(&walk, 0, d, &self.coeffs, &mut idx, &mut coeffs);
        Bernstein {
            m: k1,
            degree: d,
            coeffs,
        }
    }

    /// One node of [`Bernstein::restrict_to_face`]'s prefix tree: `cur` holds the blossom values
    /// with `vertices[..k]` applied `idx[..k]` times (degree `t` left); fills every coefficient
    /// with that prefix.
    fn face_prefix(
        &self,
        walk: &FaceWalk<'_>,
        k: usize,
        t: u32,
        cur: &[f64],
        idx: &mut [u32],
        out: &mut [f64],
    ) {
        let m = self.m;
        let last = k + 1 == walk.vertices.len();
        let mut c = cur.to_vec();
        for e in 0..=t {
            if e > 0 {
                let lower = t - e;
                c = casteljau_step(
                    m,
                    lower,
                    &walk.ups[lower as usize].up,
                    &c,
                    &walk.vertices[k],
                );
            }
            if last && e < t {
                continue;
            }
            idx[k] = e;
            if last {
                out[walk.out_shape.rank(idx, walk.degree)] = c[0];
            } else {
                self.face_prefix(walk, k + 1, t - e, &c, idx, out);
            }
        }
        idx[k] = 0;
    }
}

/// What every node of [`Bernstein::face_prefix`]'s walk shares.
struct FaceWalk<'a> {
    vertices: &'a [Vec<f64>],
    /// Index tables of degrees `0..d` in the parent's variables.
    ups: &'a [ShapeRef],
    out_shape: &'a Shape,
    degree: u32,
}

/// Halves one line of Bernstein coefficients (the terms along edge `(a, b)`, `e_a`-side first) at
/// the edge's midpoint by de Casteljau's algorithm, in place. `emit(level, lo, hi)` receives, for
/// each level `0..=l` (`l = line.len() - 1`), the `level`-th coefficient of the half keeping `a`
/// (`lo`) and the `(l - level)`-th of the half keeping `b` (`hi`).
///
/// `a_first` (`a < b`) fixes the summation order: the lower-indexed variable's term comes first,
/// as in `replace_vertex`'s sums, so [`Bernstein::split_edge`] and every caller that must match it
/// bit for bit (the sampler's flat stage tables) use this one routine.
pub fn halve_line(line: &mut [f64], a_first: bool, mut emit: impl FnMut(usize, f64, f64)) {
    let Some(l) = line.len().checked_sub(1) else {
        return;
    };
    emit(0, line[0], line[l]);
    for level in 1..=l {
        for j in 0..=(l - level) {
            // line[j] is the e_a-side term, line[j + 1] the e_b-side one.
            let (x, y) = (0.5 * line[j], 0.5 * line[j + 1]);
            line[j] = if a_first {
                (0.0 + x) + y
            } else {
                (0.0 + y) + x
            };
        }
        emit(level, line[0], line[l - level]);
    }
}

#[cfg(test)]
mod tests {
    /// `halve_line` against the closed form of de Casteljau's halving: the half keeping `a` has
    /// coefficients `2^-k Σ_i C(k, i) c_i` (k = 0..=l), the half keeping `b` has
    /// `2^-(l-j) Σ_i C(l-j, i) c_(j+i)`. Integer coefficients and halving make both exact.
    #[test]
    fn halve_line_is_de_casteljau_closed_form() {
        let binom =
            |n: usize, k: usize| (0..k).fold(1.0, |acc, i| acc * (n - i) as f64 / (i + 1) as f64);
        for l in 0..=7usize {
            let coeffs: Vec<f64> = (0..=l).map(|i| ((i * 7 + 3) % 11) as f64 - 5.0).collect();
            for a_first in [true, false] {
                let mut line = coeffs.clone();
                let (mut lo, mut hi) = (vec![f64::NAN; l + 1], vec![f64::NAN; l + 1]);
                let mut levels = Vec::new();
                halve_line(&mut line, a_first, |level, x, y| {
                    levels.push(level);
                    lo[level] = x;
                    hi[l - level] = y;
                });
                assert_eq!(levels, (0..=l).collect::<Vec<_>>());
                for (k, &got) in lo.iter().enumerate() {
                    let want: f64 =
                        (0..=k).map(|i| binom(k, i) * coeffs[i]).sum::<f64>() / 2f64.powi(k as i32);
                    assert_eq!(got, want, "left {k} of degree {l}");
                    let j = l - k;
                    let want: f64 = (0..=k).map(|i| binom(k, i) * coeffs[j + i]).sum::<f64>()
                        / 2f64.powi(k as i32);
                    assert_eq!(hi[j], want, "right {j} of degree {l}");
                }
            }
        }
        halve_line(&mut [], true, |_, _, _| {
            panic!("an empty line has no coefficient")
        });
    }

    use super::*;

    fn power_eval(p: &Bernstein, w: &[f64]) -> f64 {
        let m = p.vars();
        multi_index::all(m, p.degree())
            .chunks_exact(m)
            .zip(p.coeffs())
            .map(|(i, c)| {
                c * multinomial(i)
                    * i.iter()
                        .zip(w)
                        .map(|(&e, &x)| x.powi(e as i32))
                        .product::<f64>()
            })
            .sum()
    }

    fn sample(m: usize, d: u32, seed: u64) -> Bernstein {
        let mut s = seed;
        Bernstein::from_fn(m, d, |_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        })
    }

    const W: [[f64; 4]; 3] = [
        [0.1, 0.2, 0.3, 0.4],
        [0.7, 0.1, 0.15, 0.05],
        [0.25, 0.25, 0.25, 0.25],
    ];

    /// `add_scaled` in place equals `add(&scale)` bit for bit (the callers rely on it: the
    /// sampler's tables must not change), for scales of ±1, a power of two and two inexact ones,
    /// and evaluates to `p + s·q` (ground truth: the power form at three points).
    #[test]
    fn add_scaled_equals_add_of_scale() {
        for (m, d) in [(2, 3), (3, 2), (4, 5)] {
            for (k, s) in [1.0, -1.0, 0.5, -0.3, 1.0 / 3.0].into_iter().enumerate() {
                let (p, q) = (sample(m, d, 11 + k as u64), sample(m, d, 97 + k as u64));
                let want = p.add(&q.scale(s));
                let mut got = p.clone();
                got.add_scaled(&q, s);
                let bits =
                    |b: &Bernstein| b.coeffs().iter().map(|c| c.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&got), bits(&want), "m {m} d {d} s {s}");
                for w in &W {
                    let w = &w[..m];
                    let exact = power_eval(&p, w) + s * power_eval(&q, w);
                    assert!(
                        (power_eval(&got, w) - exact).abs() < 1e-12,
                        "m {m} d {d} s {s}"
                    );
                }
            }
        }
    }

    /// The face restriction's prefix-tree walk against one de Casteljau chain per coefficient
    /// (the definition): equal bit for bit.
    #[test]
    fn face_restriction_walk_equals_one_chain_per_coefficient() {
        let pts = [
            vec![0.2, 0.3, 0.1, 0.4],
            vec![0.6, 0.1, 0.25, 0.05],
            vec![0.1, 0.1, 0.7, 0.1],
            vec![0.0, 0.5, 0.5, 0.0],
        ];
        for m in 2..=4 {
            for d in 0..=7 {
                let p = sample(m, d, 5 + u64::from(d));
                for k1 in 1..=m {
                    let verts: Vec<Vec<f64>> = pts[..k1].iter().map(|v| v[..m].to_vec()).collect();
                    let fast = p.restrict_to_face(&verts);
                    let slow: Vec<f64> = multi_index::all(k1, d)
                        .chunks_exact(k1)
                        .map(|i| {
                            let mut c = p.coeffs().to_vec();
                            let mut t = d;
                            for (k, &e) in i.iter().enumerate() {
                                for _ in 0..e {
                                    t -= 1;
                                    c = casteljau_step(m, t, &shape(m, t).up, &c, &verts[k]);
                                }
                            }
                            c[0]
                        })
                        .collect();
                    let bits = |c: &[f64]| c.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(fast.coeffs()), bits(&slow), "m={m} d={d} k1={k1}");
                }
            }
        }
    }

    /// `split_edge`'s univariate triangle against the general vertex replacement (an independent
    /// computation of the same blossom values): equal bit for bit, for every edge and shape.
    #[test]
    fn edge_split_equals_vertex_replacement_bit_for_bit() {
        for m in 2..=4 {
            // 63 and 64 on either side of split_edge's stack buffer (64 entries), 70 on the heap;
            // the last cached split plan's degree and the next (`PLAN_DEGREE`).
            let high: &[u32] = if m == 2 { &[63, 64, 70] } else { &[] };
            let plan = PLAN_DEGREE as u32;
            for d in (0..=9).chain([plan, plan + 1]).chain(high.iter().copied()) {
                let p = sample(m, d, 31 + u64::from(d) + 100 * m as u64);
                for a in 0..m {
                    for b in 0..m {
                        if a == b {
                            continue;
                        }
                        let mut mid = vec![0.0; m];
                        mid[a] = 0.5;
                        mid[b] = 0.5;
                        let (l, r) = p.split_edge(a, b);
                        let general = |v: usize| p.replace_vertex_general(v, &mid);
                        let bits = |c: &[f64]| c.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                        assert_eq!(bits(l.coeffs()), bits(&general(b)), "m={m} d={d} ({a},{b})");
                        assert_eq!(bits(r.coeffs()), bits(&general(a)), "m={m} d={d} ({a},{b})");
                        // And the fast vertex replacement agrees with the general one.
                        assert_eq!(bits(p.replace_vertex(b, &mid).coeffs()), bits(&general(b)));
                        let w = [0.3, 0.1, 0.4, 0.2];
                        assert_eq!(
                            bits(p.replace_vertex(a, &w[..m]).coeffs()),
                            bits(&p.replace_vertex_general(a, &w[..m]))
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn casteljau_matches_power_form_and_vertices_are_exact() {
        for m in 2..=4 {
            for d in 0..=8 {
                let p = sample(m, d, 7 + u64::from(d));
                for w in &W {
                    let w = &w[..m];
                    assert!((p.eval(w) - power_eval(&p, w)).abs() < 1e-12, "m={m} d={d}");
                }
                for i in 0..m {
                    let mut e = vec![0.0; m];
                    e[i] = 1.0;
                    assert_eq!(p.eval(&e), p.vertex_value(i));
                }
            }
        }
    }

    #[test]
    fn interval_evaluation_encloses_point_values_on_the_box() {
        for m in 2..=4 {
            for d in 0..=6 {
                let p = sample(m, d, 3 + u64::from(d));
                let lo = [0.1, 0.2, 0.05, 0.3];
                let hi = [0.3, 0.35, 0.2, 0.45];
                let boxed: Vec<Interval> = (0..m).map(|i| Interval::new(lo[i], hi[i])).collect();
                let enclosure = p.eval_interval(&boxed);
                let mut s = 11u64;
                for _ in 0..200 {
                    let mut w = [0.0; 4];
                    for i in 0..m {
                        s = s.wrapping_mul(6364136223846793005).wrapping_add(1);
                        let t = (s >> 11) as f64 / (1u64 << 53) as f64;
                        w[i] = lo[i] + t * (hi[i] - lo[i]);
                    }
                    assert!(enclosure.contains(p.eval(&w[..m])), "m={m} d={d}");
                }
                let centre = vec![1.0 / m as f64; m];
                assert!(p.range().contains(p.eval(&centre)));
            }
        }
    }

    /// Recycled coefficient buffers (the thread's pool) hold a dropped polynomial's stale
    /// values: none may reach a result. Every operation that takes a recycled buffer, run after
    /// the pool is filled with NaN buffers of every pooled shape, gives the bits it gives on a
    /// fresh thread (empty pool).
    #[test]
    fn recycled_buffers_never_leak_stale_values() {
        fn ops() -> Vec<Vec<u64>> {
            let bits = |c: &[f64]| c.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            let mut out = Vec::new();
            for m in 1..=4 {
                for d in 0..=6 {
                    let p = sample(m, d, 11 + u64::from(d) + 10 * m as u64);
                    let q = sample(m, 2, 3);
                    let mut res = vec![
                        p.mul(&q),
                        q.mul(&p),
                        p.elevate(),
                        p.elevate_to(d + 3),
                        p.scale(-1.5),
                        p.clone(),
                        p.add(&p),
                    ];
                    if d > 0 {
                        res.push(p.derivative(m - 1));
                    }
                    if m >= 2 {
                        let (l, r) = p.split_edge(0, m - 1);
                        res.extend([l, r]);
                        let mut w = vec![0.0; m];
                        w[0] = 0.3;
                        w[m - 1] = 0.7;
                        res.push(p.replace_vertex(0, &w));
                    }
                    out.extend(res.iter().map(|b| bits(b.coeffs())));
                }
            }
            out
        }
        let fresh = std::thread::spawn(ops).join().expect("fresh thread");
        let stale = std::thread::spawn(|| {
            let junk: Vec<Bernstein> = (1..=4)
                .flat_map(|m| {
                    (0..=POOL_DEGREE as u32).flat_map(move |d| {
                        (0..POOL_DEPTH).map(move |_| Bernstein::constant(m, d, f64::NAN))
                    })
                })
                .collect();
            drop(junk);
            // The pool is full: one more is freed, not kept.
            drop(Bernstein::constant(2, 1, f64::NAN));
            ops()
        })
        .join()
        .expect("stale thread");
        assert_eq!(fresh, stale);
    }

    /// One elevation step through the cached plan (`elevation_plan`) against the ranks computed
    /// per term (`elevate_general`, the reference): the same bits, for every shape up to one
    /// past the plans' limit, with zero, negative, infinite and NaN coefficients (a zero factor
    /// must skip its term, as the reference does, and never form `0 · ∞`).
    #[test]
    fn elevation_plan_equals_the_general_elevation_bit_for_bit() {
        let bits = |c: &[f64]| c.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for m in 1..=4 {
            for d in (0..=6).chain([PLAN_DEGREE as u32 - 1, PLAN_DEGREE as u32]) {
                let mut p = sample(m, d, 5 + u64::from(d) + 40 * m as u64);
                let specials = [0.0, -0.0, f64::INFINITY, f64::NAN, -3.5];
                for (c, &x) in p.coeffs.iter_mut().zip(specials.iter().cycle()).step_by(3) {
                    *c = x;
                }
                let want = p.elevate_general();
                let got = p.elevate();
                assert_eq!(got.degree(), d + 1);
                assert_eq!(bits(got.coeffs()), bits(want.coeffs()), "m={m} d={d}");
                let far = p.elevate_to(d + 3);
                let mut step = want;
                for _ in 0..2 {
                    step = step.elevate_general();
                }
                assert_eq!(bits(far.coeffs()), bits(step.coeffs()), "m={m} d={d} + 3");
                assert_eq!(bits(p.elevate_to(d).coeffs()), bits(p.coeffs()));
            }
        }
    }

    #[test]
    fn product_elevation_and_derivative_agree_with_evaluation() {
        for m in 2..=4 {
            let p = sample(m, 3, 1);
            let q = sample(m, 2, 2);
            let pq = p.mul(&q);
            let e = p.elevate_to(6);
            for w in &W {
                // Elevation multiplies the homogeneous form by Σw, so compare on the simplex.
                let total: f64 = w[..m].iter().sum();
                let w: Vec<f64> = w[..m].iter().map(|x| x / total).collect();
                let w = &w[..];
                assert!((pq.eval(w) - p.eval(w) * q.eval(w)).abs() < 1e-12);
                assert!((e.eval(w) - p.eval(w)).abs() < 1e-12);
                for k in 1..m {
                    let h = 1e-6;
                    let mut wp = w.to_vec();
                    let mut wm = w.to_vec();
                    wp[k] += h;
                    wp[0] -= h;
                    wm[k] -= h;
                    wm[0] += h;
                    let fd = (p.eval(&wp) - p.eval(&wm)) / (2.0 * h);
                    assert!((p.derivative(k).eval(w) - fd).abs() < 1e-7);
                }
            }
        }
    }

    /// Products on both sides of the cached plans' degree limit (`PRODUCT_DEGREE`: looked-up
    /// ranks below, summed indices above) equal the product of the factors' values (de
    /// Casteljau evaluation, independent of the product's index arithmetic), in 1 to 4 variables.
    #[test]
    fn products_inside_and_past_the_cached_plans_agree_with_evaluation() {
        let limit = PRODUCT_DEGREE as u32;
        let degrees = [
            (0, 5),
            (1, limit),
            (limit, 1),
            (4, 9),
            (limit + 1, 2),
            (2, limit + 1),
        ];
        for m in 1..=4 {
            for (k, &(da, db)) in degrees.iter().enumerate() {
                let p = sample(m, da, 7 + k as u64);
                let q = sample(m, db, 19 + k as u64);
                let pq = p.mul(&q);
                assert_eq!(pq.degree(), da + db);
                for w in &W {
                    let total: f64 = w[..m].iter().sum();
                    let w: Vec<f64> = w[..m].iter().map(|x| x / total).collect();
                    let (got, want) = (pq.eval(&w), p.eval(&w) * q.eval(&w));
                    assert!(
                        (got - want).abs() <= 1e-12 * (1.0 + want.abs()),
                        "m={m} degrees {da}+{db}: {got} against {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn restriction_by_replacement_matches_the_blossom() {
        for m in 2..=4 {
            for d in 0..=7 {
                let p = sample(m, d, 17 + u64::from(d));
                // A small simplex {w ≥ lo} and a general one.
                let lo = [0.21, 0.3, 0.12, 0.17];
                let rest = 1.0 - lo[..m].iter().sum::<f64>();
                let corner: Vec<Vec<f64>> = (0..m)
                    .map(|j| {
                        let mut v = lo[..m].to_vec();
                        v[j] += rest;
                        v
                    })
                    .collect();
                let general: Vec<Vec<f64>> = (0..m)
                    .map(|j| {
                        let mut v = vec![0.1; m];
                        v[j] += 1.0 - 0.1 * m as f64;
                        v[(j + 1) % m] += 0.05;
                        v[j] -= 0.05;
                        v
                    })
                    .collect();
                for verts in [&corner, &general] {
                    let fast = p.restrict_by_replacement(verts).expect("well ordered");
                    let slow = p.restrict_by_blossom(verts);
                    for (a, b) in fast.coeffs().iter().zip(slow.coeffs()) {
                        assert!((a - b).abs() < 1e-12, "m={m} d={d}: {a} vs {b}");
                    }
                }
            }
        }
    }

    #[test]
    fn restriction_to_a_face_evaluates_like_the_parent() {
        for m in 3..=4 {
            for d in 0..=5 {
                let p = sample(m, d, 5 + u64::from(d));
                let verts: Vec<Vec<f64>> = (0..m - 1)
                    .map(|j| {
                        let mut v = vec![0.15; m];
                        v[j] += 1.0 - 0.15 * m as f64;
                        v
                    })
                    .collect();
                let face = p.restrict_to_face(&verts);
                assert_eq!(face.vars(), m - 1);
                let lam = [0.2, 0.5, 0.3];
                let lam = &lam[..m - 1];
                let total: f64 = lam.iter().sum();
                let lam: Vec<f64> = lam.iter().map(|x| x / total).collect();
                let mut point = vec![0.0; m];
                for (l, v) in lam.iter().zip(&verts) {
                    for k in 0..m {
                        point[k] += l * v[k];
                    }
                }
                assert!(
                    (face.eval(&lam) - p.eval(&point)).abs() < 1e-12,
                    "m={m} d={d}"
                );
            }
        }
    }

    #[test]
    fn split_and_restrict_reproduce_the_parent() {
        for m in 2..=4 {
            let p = sample(m, 4, 3);
            let (a, b) = p.split_edge(0, m - 1);
            // A point of child a with local coordinates w maps to the parent point with vertex m−1
            // replaced by the midpoint of edge (0, m−1).
            for w in &W {
                let w = &w[..m];
                let mut parent = w.to_vec();
                parent[0] += 0.5 * w[m - 1];
                parent[m - 1] = 0.5 * w[m - 1];
                assert!((a.eval(w) - p.eval(&parent)).abs() < 1e-12);
                let mut parent_b = w.to_vec();
                parent_b[m - 1] += 0.5 * w[0];
                parent_b[0] = 0.5 * w[0];
                assert!((b.eval(w) - p.eval(&parent_b)).abs() < 1e-12);
            }
            let verts: Vec<Vec<f64>> = (0..m)
                .map(|i| {
                    (0..m)
                        .map(|j| if i == j { 0.6 } else { 0.4 / (m - 1) as f64 })
                        .collect()
                })
                .collect();
            let r = p.restrict(&verts);
            for w in &W {
                let w = &w[..m];
                let x: Vec<f64> = (0..m)
                    .map(|j| (0..m).map(|i| w[i] * verts[i][j]).sum())
                    .collect();
                assert!((r.eval(w) - p.eval(&x)).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn wrong_coefficient_count_is_an_error() {
        assert!(matches!(
            Bernstein::new(3, 2, vec![0.0; 5]),
            Err(GeomError::Coefficients { expected: 6, .. })
        ));
    }
}
