//! Whole-model evaluation: point location, `F(p)`, `∇F(p)`, inside/outside, the linear patches
//! `θ_σ` and the parametric map `θ_σ ∋ u ↦ p ∈ O` with its derivative.
//!
//! Point location uses a uniform grid of the simplices' bounding boxes, falling back to an R*-tree
//! (`rstar`) on strongly graded meshes (see `spatial.rs` for why).
//!
//! Local maps are built lazily, once per simplex, and cached ([`ModelEval::local_map`]): a
//! million-simplex model with a few curved cells costs memory only for the cells actually
//! evaluated. A pass that visits every simplex once takes them uncached instead
//! ([`ModelEval::local_map_transient`]), so its memory does not grow with the model. Point
//! evaluations ([`ModelEval::value_at`], [`ModelEval::gradient_at`] and what calls them: `query`,
//! volume sampling) cache maps only while the cache holds less than its budget
//! ([`MAP_CACHE_BUDGET`], [`ModelEval::with_map_cache_budget`]); past it they build the map, use
//! it and drop it — the same map, so the same bits.

use std::borrow::Cow;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::OnceLock;

use ism_format::{IndexedModel, Model};
use rayon::prelude::*;

use crate::error::{GeomError, Result};
use crate::linalg;
use crate::spatial::{SimplexBox, SpatialIndex};
use crate::stage::{InverseResult, LocalMap};
use crate::{Bary, Mat, MAX_VARS};

/// Barycentric slack accepted by point location: a point whose smallest barycentric coordinate is
/// above `−LOCATE_TOLERANCE` counts as inside. Coordinates are computed from an inverted edge matrix,
/// so points exactly on a shared face come out as `±` a few ulps; this admits them on both sides
/// and is far below any meaningful distance in a unit-scaled model.
pub const LOCATE_TOLERANCE: f64 = 1e-10;

/// Default bytes of local maps an evaluator's point evaluations keep cached
/// ([`ModelEval::with_map_cache_budget`]): 1 GiB. `ism sample --volume 2000000` on the 1 M-tet
/// model of BENCHMARKS.md (three Bézier stages) meets ~0.9 M of its simplices and, caching every
/// map, grew by 2.3 GB (~2.6 KB a map) to a 2.9 GB peak; with the budget it peaks at 1.6 GB for the
/// same CPU and output (a map build costs about what the page faults of caching it did;
/// BENCHMARKS.md, issue 19, session 45). At ~2.6 KB a map, 1 GiB holds ~400 k of them (arithmetic, not
/// measured: the budget counts [`LocalMap::heap_bytes`], which leaves out the allocator's overhead).
pub const MAP_CACHE_BUDGET: usize = 1 << 30;

/// A located point: the top simplex and the barycentric coordinates there (clamped to `≥ 0`,
/// summing to 1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Located {
    /// Top simplex index.
    pub simplex: usize,
    /// Barycentric coordinates in that simplex's local vertex order.
    pub w: Bary,
}

/// One corner of a linear patch `θ_σ`: where the zero set of `Σ f_i u_i − c` crosses an edge of σ.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PatchCorner {
    /// Barycentric coordinates (two nonzero entries).
    pub u: Bary,
    /// Local positions of the edge's ends: `[inside vertex (f < c), outside vertex (f ≥ c)]`.
    pub edge: [usize; 2],
}

/// The linear patch `θ_σ = {u ∈ Δⁿ : Σ f_i u_i = c}` of one simplex: 2 corners in 2D (a segment),
/// 3 or 4 in 3D (triangle or quad, in cyclic order), 1 in 1D. Ordered so that the patch's
/// orientation normal points towards `F > c` (outside): in 2D the normal is the tangent
/// `p_1 − p_0` turned clockwise; in 3D `(p_1 − p_0) × (p_2 − p_0)`.
#[derive(Clone, Debug, PartialEq)]
pub struct Patch {
    /// The corners.
    pub corners: Vec<PatchCorner>,
}

/// A point of the parametric form of `O`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ParamPoint {
    /// The point `p = Σ w_i v_i` (first `n` entries).
    pub p: [f64; 3],
    /// Its barycentric coordinates `w = X⁻¹(u)`.
    pub w: Bary,
    /// How the inversion went.
    pub inverse: InverseResult,
}

/// Evaluator of a whole model, built once.
pub struct ModelEval {
    /// Shared, not copied: an `Arc` inside.
    model: IndexedModel,
    n: usize,
    /// Per simplex, the inverse edge matrix `A` (row-major `n × n` in a `3 × 3`): reduced
    /// barycentric `w_{1..n} = A (p − v_0)`.
    inv_edges: Vec<[f64; 9]>,
    maps: Vec<OnceLock<LocalMap>>,
    /// Built with the tables, or on first use ([`ModelEval::for_extraction`]).
    index: OnceLock<SpatialIndex>,
    /// Whether the local maps are built [`LocalMap::fused`] ([`ModelEval::for_extraction`]).
    fused: bool,
    /// Heap bytes of the maps cached in `maps` so far ([`LocalMap::heap_bytes`]).
    cached_bytes: AtomicUsize,
    /// Above `cached_bytes` of this, point evaluations stop caching ([`MAP_CACHE_BUDGET`]).
    cache_budget: usize,
}

impl std::fmt::Debug for ModelEval {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ModelEval")
            .field("n", &self.n)
            .field("simplices", &self.inv_edges.len())
            .finish_non_exhaustive()
    }
}

/// What an evaluator computes from the model: per simplex the inverse edge matrix, the spatial
/// index, the slots of the local maps.
struct Tables {
    n: usize,
    inv_edges: Vec<[f64; 9]>,
    maps: Vec<OnceLock<LocalMap>>,
    index: OnceLock<SpatialIndex>,
}

/// The spatial index of `model`'s top simplices (their bounding boxes), the boxes computed in
/// parallel or not (not: inside a `OnceLock` initialiser, where a rayon worker waiting for its
/// jobs could steal one that waits on the same lock).
fn spatial_index(model: &Model, n: usize, parallel: bool) -> SpatialIndex {
    let bbox = |s: usize| {
        let mut lo = [0.0; 3];
        let mut hi = [0.0; 3];
        for (k, &v) in model.simplex(s).iter().enumerate() {
            let p = model.vertex(v as usize);
            for x in 0..n {
                if k == 0 || p[x] < lo[x] {
                    lo[x] = p[x];
                }
                if k == 0 || p[x] > hi[x] {
                    hi[x] = p[x];
                }
            }
        }
        SimplexBox {
            lo,
            hi,
            id: s as u32,
        }
    };
    let ns = model.num_simplices();
    let boxes: Vec<SimplexBox> = if parallel {
        (0..ns).into_par_iter().map(bbox).collect()
    } else {
        (0..ns).map(bbox).collect()
    };
    SpatialIndex::build(n, boxes)
}

impl Tables {
    /// The tables of `model`; the spatial index too when `index`, else left for first use.
    fn build(model: &Model, index: bool) -> Result<Tables> {
        let n = model.dim();
        if !(1..=3).contains(&n) {
            return Err(GeomError::Dimension(n));
        }
        let nv = model.num_vertices();
        let ns = model.num_simplices();
        // Each inverse written in place into one vector of the final size: collected as a
        // `Result`, the matrices went through pieces copied into a growing vector (0.1 M of this
        // function's 0.96 M instructions on the sphere example). Which error is reported when
        // several simplices are bad is as before: the first met (the lowest with one thread).
        let mut inv_edges = vec![[0.0; 9]; ns];
        inv_edges
            .par_iter_mut()
            .enumerate()
            .try_for_each(|(s, slot)| {
                let ids = model.simplex(s);
                if let Some(&bad) = ids.iter().find(|&&v| v as usize >= nv) {
                    return Err(GeomError::NoVertex {
                        simplex: s,
                        vertex: bad,
                        count: nv,
                    });
                }
                let e = edge_matrix(model, ids);
                let det = linalg::det(n, &e);
                let inv = linalg::inverse(n, &e).filter(|_| det != 0.0 && det.is_finite());
                let inv = inv.ok_or(GeomError::Degenerate { simplex: s, det })?;
                let mut out = [0.0; 9];
                for r in 0..n {
                    for c in 0..n {
                        out[r * 3 + c] = inv[r][c];
                    }
                }
                *slot = out;
                Ok(())
            })?;
        let index = if index {
            OnceLock::from(spatial_index(model, n, true))
        } else {
            OnceLock::new()
        };
        let maps = if model.stages.is_empty() {
            Vec::new()
        } else {
            (0..ns).map(|_| OnceLock::new()).collect()
        };
        Ok(Tables {
            n,
            inv_edges,
            maps,
            index,
        })
    }

    fn with(self, model: IndexedModel) -> ModelEval {
        ModelEval {
            model,
            n: self.n,
            inv_edges: self.inv_edges,
            maps: self.maps,
            index: self.index,
            fused: false,
            cached_bytes: AtomicUsize::new(0),
            cache_budget: MAP_CACHE_BUDGET,
        }
    }
}

impl ModelEval {
    /// Indexes `model` for evaluation ([`IndexedModel::for_evaluation`]: shapes, index ranges and
    /// stage records are checked), inverts every edge matrix and builds the spatial index (in
    /// parallel). Copies the model; [`ModelEval::from_indexed`] shares an indexed one instead.
    ///
    /// # Errors
    /// [`GeomError::Structure`] for a model that cannot be indexed (the structural rule and where),
    /// [`GeomError::Degenerate`] for a simplex without an inverse edge matrix.
    pub fn new(model: &Model) -> Result<ModelEval> {
        let n = model.dim();
        if !(1..=3).contains(&n) {
            return Err(GeomError::Dimension(n));
        }
        // The tables first, the copy after: the copy does not add to the tables' peak memory.
        // The structural error, if any, is still the one reported (an indexing error comes
        // before a degenerate simplex, as when the copy was indexed first).
        let tables = Tables::build(model, true);
        let indexed = IndexedModel::for_evaluation(model.clone()).map_err(GeomError::from)?;
        Ok(tables?.with(indexed))
    }

    /// An evaluator sharing `model`'s topology and stage tables (no copy): inverts every edge
    /// matrix and builds the spatial index (in parallel).
    ///
    /// # Errors
    /// [`GeomError::Degenerate`] for a simplex without an inverse edge matrix.
    pub fn from_indexed(indexed: &IndexedModel) -> Result<ModelEval> {
        Ok(Tables::build(indexed, true)?.with(indexed.clone()))
    }

    /// [`ModelEval::from_indexed`] for a caller that inverts many points and need not reproduce
    /// the unfused bits (the exporter): its local maps are [`LocalMap::fused`] (a projective
    /// monotonic stage and the Bézier or rational stage after it evaluated as one rational stage:
    /// the same maps up to rounding, cheaper to evaluate and differentiate), and the spatial index
    /// is only built if [`ModelEval::locate`] is called (an export never locates a point; the
    /// index was ~2 % of a small model's export).
    ///
    /// # Errors
    /// As [`ModelEval::from_indexed`].
    pub fn for_extraction(indexed: &IndexedModel) -> Result<ModelEval> {
        let mut eval = Tables::build(indexed, false)?.with(indexed.clone());
        eval.fused = true;
        Ok(eval)
    }

    /// The spatial index, built now if it was left for first use.
    fn index(&self) -> &SpatialIndex {
        self.index
            .get_or_init(|| spatial_index(&self.model, self.n, false))
    }

    /// The model evaluated.
    pub fn model(&self) -> &Model {
        &self.model
    }

    /// The model evaluated, with its topology and stage tables.
    pub fn indexed(&self) -> &IndexedModel {
        &self.model
    }

    /// Dimension `n`.
    pub fn dim(&self) -> usize {
        self.n
    }

    /// The spatial index chosen: `"grid"` (uniform grid) or `"rtree"` (graded meshes).
    pub fn index_kind(&self) -> &'static str {
        self.index().kind()
    }

    /// Number of top simplices.
    pub fn num_simplices(&self) -> usize {
        self.inv_edges.len()
    }

    /// The inverse of simplex `s`'s edge matrix ([`edge_matrix`]), computed once in
    /// [`ModelEval::new`] (which refuses degenerate simplices, so it always exists).
    pub fn inv_edges(&self, s: usize) -> Mat {
        let a = &self.inv_edges[s];
        let mut out = [[0.0; MAX_VARS]; MAX_VARS];
        for (r, row) in out.iter_mut().enumerate().take(self.n) {
            row[..self.n].copy_from_slice(&a[r * 3..r * 3 + self.n]);
        }
        out
    }

    /// The local map (all stages) of simplex `s`, built on first use.
    ///
    /// # Panics
    /// If `s` is out of range.
    pub fn local_map(&self, s: usize) -> &LocalMap {
        static IDENTITY: [OnceLock<LocalMap>; MAX_VARS + 1] = [
            OnceLock::new(),
            OnceLock::new(),
            OnceLock::new(),
            OnceLock::new(),
            OnceLock::new(),
        ];
        let m = self.n + 1;
        if self.maps.is_empty() {
            assert!(s < self.num_simplices(), "simplex {s} out of range");
            return IDENTITY[m].get_or_init(|| LocalMap::from_stages(m, Vec::new()));
        }
        self.maps[s].get_or_init(|| {
            let map = self.build_local_map(s);
            self.cached_bytes
                .fetch_add(map.heap_bytes(), Ordering::Relaxed);
            map
        })
    }

    /// `f` applied to simplex `s`'s local map: the cached one, or cached now while the cache holds
    /// less than its budget ([`ModelEval::with_map_cache_budget`]), else one built for this call
    /// and dropped after it — the same map ([`ModelEval::local_map_transient`]), so `f` sees the
    /// same bits either way. For point evaluations, which may visit any number of simplices.
    ///
    /// # Panics
    /// If `s` is out of range.
    pub fn with_local_map<R>(&self, s: usize, f: impl FnOnce(&LocalMap) -> R) -> R {
        if self.maps.is_empty() || self.cached_bytes.load(Ordering::Relaxed) < self.cache_budget {
            return f(self.local_map(s));
        }
        f(&self.local_map_transient(s))
    }

    /// This evaluator with at most about `bytes` of local maps cached by point evaluations
    /// ([`ModelEval::with_local_map`]; default [`MAP_CACHE_BUDGET`]): past it a point evaluation
    /// builds its simplex's map and drops it. The cache may exceed it by the maps being built
    /// when it is reached (one per thread), and by the maps [`ModelEval::local_map`] keeps for
    /// callers that hold them (the surface sampler's table, the exporter), which it counts.
    /// Values never depend on it.
    #[must_use]
    pub fn with_map_cache_budget(mut self, bytes: usize) -> ModelEval {
        self.cache_budget = bytes;
        self
    }

    /// Heap bytes of the local maps cached so far ([`LocalMap::heap_bytes`]).
    pub fn cached_map_bytes(&self) -> usize {
        self.cached_bytes.load(Ordering::Relaxed)
    }

    /// Simplex `s`'s local map as [`ModelEval::local_map`] caches it (fused or not).
    fn build_local_map(&self, s: usize) -> LocalMap {
        let map = if self.fused {
            LocalMap::from_indexed_fused(&self.model, s)
        } else {
            LocalMap::from_indexed(&self.model, s)
        };
        map.expect("an indexed model's stage tables are complete")
    }

    /// The local map of simplex `s` without keeping it: the cached one when
    /// [`ModelEval::local_map`] built it already, else the same map built afresh and dropped
    /// with the returned value. For a pass that visits every simplex of a large model once (the
    /// volume export): [`ModelEval::local_map`] keeps every map it builds, and on the 1 M-tet
    /// model (three stages) the volume export peaked at 3.8 GB with the cache and 1.0 GB without.
    pub fn local_map_transient(&self, s: usize) -> Cow<'_, LocalMap> {
        if self.maps.is_empty() {
            return Cow::Borrowed(self.local_map(s));
        }
        if let Some(map) = self.maps[s].get() {
            return Cow::Borrowed(map);
        }
        Cow::Owned(self.build_local_map(s))
    }

    /// Unclamped barycentric coordinates of `p` (first `n` entries used) w.r.t. simplex `s`.
    pub fn barycentric(&self, s: usize, p: &[f64]) -> Bary {
        let n = self.n;
        let a = &self.inv_edges[s];
        let v0 = self.model.vertex(self.model.simplex(s)[0] as usize);
        let mut w = [0.0; MAX_VARS];
        let mut sum = 0.0;
        for r in 0..n {
            let mut acc = 0.0;
            for c in 0..n {
                acc += a[r * 3 + c] * (p[c] - v0[c]);
            }
            w[r + 1] = acc;
            sum += acc;
        }
        w[0] = 1.0 - sum;
        w
    }

    /// The point `Σ w_i v_i` of simplex `s` (first `n` entries).
    #[inline]
    pub fn point(&self, s: usize, w: &Bary) -> [f64; 3] {
        // The dimension as a constant, so the loops unroll (the exporter maps every test point
        // through here); the sums are the same, in the same order, for every `n`.
        match self.n {
            3 => self.point_n::<3>(s, w),
            2 => self.point_n::<2>(s, w),
            _ => self.point_n::<1>(s, w),
        }
    }

    #[inline(always)]
    fn point_n<const N: usize>(&self, s: usize, w: &Bary) -> [f64; 3] {
        let ids = &self.model.simplices[s * (N + 1)..(s + 1) * (N + 1)];
        let vertices = &self.model.vertices;
        let mut p = [0.0; 3];
        for (i, &v) in ids.iter().enumerate() {
            let q = &vertices[v as usize * N..(v as usize + 1) * N];
            for x in 0..N {
                p[x] += w[i] * q[x];
            }
        }
        p
    }

    /// The top simplex containing `p` (first `n` entries used), or `None` outside the complex. On a
    /// shared face the simplex with the largest smallest coordinate wins (ties: lowest index), so
    /// the answer is deterministic.
    pub fn locate(&self, p: &[f64]) -> Option<Located> {
        let mut q = [0.0; 3];
        q[..self.n].copy_from_slice(&p[..self.n]);
        let mut best: Option<(f64, usize, Bary)> = None;
        self.index().candidates(&q, |s| {
            let w = self.barycentric(s, &q);
            let min = w[..=self.n].iter().copied().fold(f64::INFINITY, f64::min);
            if min < -LOCATE_TOLERANCE {
                return true;
            }
            let better = match best {
                None => true,
                Some((bm, bs, _)) => min > bm || (min == bm && s < bs),
            };
            if better {
                best = Some((min, s, w));
            }
            // Clearly interior: in a complex no other simplex contains the point.
            min <= LOCATE_TOLERANCE
        });
        best.map(|(_, s, w)| Located {
            simplex: s,
            w: crate::stage::project(self.n + 1, &w),
        })
    }

    /// `F` at barycentric `w` of simplex `s`: `Σ f(v_i) X(w)_i`.
    pub fn value_at(&self, s: usize, w: &Bary) -> f64 {
        self.with_local_map(s, |map| self.value_from_coordinates(s, &map.eval(w)))
    }

    /// `∇F` (first `n` entries) at barycentric `w` of simplex `s`, by the chain rule through the
    /// stages; `None` where a parametric stage's stored Jacobian is singular.
    pub fn gradient_at(&self, s: usize, w: &Bary) -> Option<[f64; 3]> {
        let (_, j) = self.with_local_map(s, |map| map.jacobian(w));
        Some(self.gradient_from_jacobian(s, &j?))
    }

    /// [`ModelEval::value_at`] and [`ModelEval::gradient_at`] together, the map taken once (built
    /// once when it is not cached).
    pub fn value_and_gradient_at(&self, s: usize, w: &Bary) -> (f64, Option<[f64; 3]>) {
        let (x, (_, j)) = self.with_local_map(s, |map| (map.eval(w), map.jacobian(w)));
        (
            self.value_from_coordinates(s, &x),
            j.map(|j| self.gradient_from_jacobian(s, &j)),
        )
    }

    /// `∇F` (first `n` entries) in simplex `s` from the reduced Jacobian `DX` of its map at the
    /// point (e.g. the one [`LocalMap::inverse_near`] returns).
    pub fn gradient_from_jacobian(&self, s: usize, j: &Mat) -> [f64; 3] {
        let n = self.n;
        let ids = self.model.simplex(s);
        let f0 = self.model.values[ids[0] as usize];
        // ∂F/∂w_l (reduced) = Σ_k (f_k − f_0) J[k][l].
        let mut dw = [0.0; 3];
        for l in 0..n {
            dw[l] = (0..n)
                .map(|k| (self.model.values[ids[k + 1] as usize] - f0) * j[k][l])
                .sum();
        }
        let a = &self.inv_edges[s];
        let mut g = [0.0; 3];
        for x in 0..n {
            g[x] = (0..n).map(|l| dw[l] * a[l * 3 + x]).sum();
        }
        g
    }

    /// `F` in simplex `s` from the function coordinates `x = X(w)` of a point.
    pub fn value_from_coordinates(&self, s: usize, x: &Bary) -> f64 {
        self.model
            .simplex(s)
            .iter()
            .enumerate()
            .map(|(i, &v)| self.model.values[v as usize] * x[i])
            .sum()
    }

    /// `F(p)`, or `None` outside the complex.
    pub fn value(&self, p: &[f64]) -> Option<f64> {
        self.locate(p).map(|l| self.value_at(l.simplex, &l.w))
    }

    /// `∇F(p)`, or `None` outside the complex (or at a singular parametric stage).
    pub fn gradient(&self, p: &[f64]) -> Option<[f64; 3]> {
        self.locate(p)
            .and_then(|l| self.gradient_at(l.simplex, &l.w))
    }

    /// Whether `p` is inside the shape (`F(p) < c`); `None` outside the complex.
    pub fn inside(&self, p: &[f64]) -> Option<bool> {
        self.value(p).map(|f| f < self.model.level)
    }

    /// The linear patch `θ_σ` of simplex `s`; `None` when all vertex values are on one side of `c`.
    pub fn patch(&self, s: usize) -> Option<Patch> {
        let n = self.n;
        let ids = self.model.simplex(s);
        let c = self.model.level;
        // Fixed arrays, no vectors: every simplex is asked and most are not crossed (three
        // allocations each were 3 % of the sphere example's export).
        let mut f = [0.0; MAX_VARS];
        let (mut inside, mut outside) = ([0usize; MAX_VARS], [0usize; MAX_VARS]);
        let (mut ni, mut no) = (0, 0);
        for (i, &v) in ids.iter().enumerate() {
            f[i] = self.model.values[v as usize] - c;
            if f[i] < 0.0 {
                inside[ni] = i;
                ni += 1;
            } else if f[i] >= 0.0 {
                outside[no] = i;
                no += 1;
            }
        }
        if ni == 0 || no == 0 {
            return None;
        }
        let (inside, outside) = (&inside[..ni], &outside[..no]);
        let corner = |a: usize, b: usize| {
            // Zero of f_a (1 − t) + f_b t on the edge; f_a < 0 ≤ f_b so the denominator is > 0.
            let t = f[a] / (f[a] - f[b]);
            let mut u = [0.0; MAX_VARS];
            u[a] = 1.0 - t;
            u[b] = t;
            PatchCorner { u, edge: [a, b] }
        };
        let mut corners: Vec<PatchCorner> = if inside.len() == 2 && outside.len() == 2 {
            let (a, b, c2, d) = (inside[0], inside[1], outside[0], outside[1]);
            vec![corner(a, c2), corner(a, d), corner(b, d), corner(b, c2)]
        } else {
            inside
                .iter()
                .flat_map(|&a| outside.iter().map(move |&b| (a, b)))
                .map(|(a, b)| corner(a, b))
                .collect()
        };
        if n >= 2 {
            // Orient by the gradient of the linear function (outward: towards F > c).
            let grad = {
                let a = &self.inv_edges[s];
                let mut g = [0.0; 3];
                for x in 0..n {
                    g[x] = (0..n).map(|l| (f[l + 1] - f[0]) * a[l * 3 + x]).sum();
                }
                g
            };
            // Only the first two or three corners' points orient the patch: mapped on demand,
            // not collected into a vector (an allocation per crossed simplex).
            let p = |i: usize| self.point(s, &corners[i].u);
            let p0 = p(0);
            let d1 = sub(&p(1), &p0);
            let normal = if n == 2 {
                [d1[1], -d1[0], 0.0]
            } else {
                let d2 = sub(&p(2), &p0);
                [
                    d1[1] * d2[2] - d1[2] * d2[1],
                    d1[2] * d2[0] - d1[0] * d2[2],
                    d1[0] * d2[1] - d1[1] * d2[0],
                ]
            };
            let dot: f64 = (0..3).map(|x| normal[x] * grad[x]).sum();
            if dot < 0.0 {
                corners.reverse();
            }
        }
        Some(Patch { corners })
    }

    /// The parametric map at `u ∈ θ_σ` (or any `u ∈ Δⁿ`): `w = X⁻¹(u)`, `p = Σ w_i v_i`.
    pub fn param_point(&self, s: usize, u: &Bary) -> ParamPoint {
        let inverse = self.local_map(s).inverse(u);
        ParamPoint {
            p: self.point(s, &inverse.w),
            w: inverse.w,
            inverse,
        }
    }

    /// Derivative `∂p/∂(u_1..u_n)` of the parametric map at barycentric `w = X⁻¹(u)` of simplex
    /// `s` (row `x` = coordinate, column `l` = `u_l`, `u_0 = 1 − Σ`): `E · DX(w)⁻¹` with `E` the edge
    /// matrix. Compose with the patch's own parameterisation for an area element. `None` when
    /// `DX(w)` is singular.
    pub fn param_jacobian(&self, s: usize, w: &Bary) -> Option<Mat> {
        let n = self.n;
        let (_, j) = self.local_map(s).jacobian(w);
        let jinv = linalg::inverse(n, &j?)?;
        let e = edge_matrix(&self.model, self.model.simplex(s));
        Some(linalg::mul(n, &e, &jinv))
    }

    /// Locates many points (flat, `n` per point), in parallel.
    pub fn locate_many(&self, points: &[f64]) -> Vec<Option<Located>> {
        points
            .par_chunks_exact(self.n)
            .map(|p| self.locate(p))
            .collect()
    }

    /// `F` at many points (flat, `n` per point), in parallel; `None` outside the complex.
    pub fn values(&self, points: &[f64]) -> Vec<Option<f64>> {
        points
            .par_chunks_exact(self.n)
            .map(|p| self.value(p))
            .collect()
    }

    /// `∇F` at many points (flat, `n` per point), in parallel.
    pub fn gradients(&self, points: &[f64]) -> Vec<Option<[f64; 3]>> {
        points
            .par_chunks_exact(self.n)
            .map(|p| self.gradient(p))
            .collect()
    }

    /// The parametric map at many `(simplex, u)` pairs, in parallel.
    pub fn param_points(&self, queries: &[(usize, Bary)]) -> Vec<ParamPoint> {
        queries
            .par_iter()
            .map(|(s, u)| self.param_point(*s, u))
            .collect()
    }
}

fn sub(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// `E[x][l] = (v_{l+1} − v_0)_x`: columns are the edges from vertex 0.
/// The edge matrix of the simplex with vertex ids `ids`: column `l` is `v_{l+1} − v_0`, so
/// `p = v_0 + E·(w_1, …, w_n)`.
pub fn edge_matrix(model: &Model, ids: &[u32]) -> Mat {
    let n = model.dim();
    let v0 = model.vertex(ids[0] as usize);
    let mut e = [[0.0; MAX_VARS]; MAX_VARS];
    for l in 0..n {
        let v = model.vertex(ids[l + 1] as usize);
        for x in 0..n {
            e[x][l] = v[x] - v0[x];
        }
    }
    e
}
