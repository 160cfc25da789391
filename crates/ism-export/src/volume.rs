//! The complex itself with `F` as a higher-order field: VTK Bézier triangles (type 76) or
//! tetrahedra (type 78), for ParaView or the Python `vtk` package to contour — `F` itself where the
//! stages allow it, else with a stated bound on how far the written field is from `F`.
//!
//! **Exact cells first.** When on every simplex the model's parametric stages (if any) come before
//! its implicit ones and the composed degree is at most [`MAX_EXACT_DEGREE`] — every example but
//! `stratified-3d` (degree 24) and `two-stage` (an implicit stage before a parametric one), and
//! every model `ism fit` writes — `F` itself is written (`volume/exact.rs`): one isoparametric
//! (rational) Bézier cell per simplex whose geometry is the model's parametrisation and whose field
//! is `F` on it; `exact: true`, and the certified bound covers rounding only (~1e-12). Should that
//! bound miss the tolerance (weights spanning ~37 orders of magnitude), the interpolant below is
//! tried too and the smaller bound is written.
//!
//! **Otherwise, interpolated cells.** Every top simplex is cut into `4^k` (2D) or `8^k` (3D)
//! sub-simplices by `k` levels of red refinement (edge midpoints; the refinement of a face does not
//! depend on the cell, so neighbouring cells stay conforming), and on each sub-simplex `F` is
//! replaced by its degree-`p` polynomial interpolant `G` at the lattice points (linear geometry,
//! control point `J/p`). Control points on shared faces are shared (identified by the face of the
//! parent that carries them and their exact dyadic barycentric numerators there, `PointIds`), so
//! the field is continuous. `(p, k)` is the cheapest pair (fewest control points) whose certified
//! bound meets the field tolerance; if none of the pairs tried meets it, the one with the
//! smallest bound is written and the bound says so.
//! Pairs that would write more than [`MAX_CONTROL_POINTS`] are not tried. When the shape crosses
//! few simplices ([`SCREENED`]), a pair is first fitted on those alone: their cells are among the
//! ones the tolerance applies to, so a bound over the tolerance there refuses the pair without
//! fitting every simplex (the result is the same).
//!
//! **The certificate (all-implicit models).** With every stage implicit, `F` on a simplex is a
//! ratio of polynomials: writing a stage projectively, `x ↦ (P(x), Q(x))` with `P` homogeneous of
//! degree `d` (Bézier: `Σ b_I B_I(x)`, rational: `Σ q_I b_I B_I(x)`, monotonic:
//! `g_i(x_i, Σx − x_i)` homogenised), the composition of all stages maps `w` to homogeneous
//! polynomials `N_i(w)` of degree `E = Π d` with `X(w) = N(w) / D(w)`, `D = Σ N_i` (each stage's
//! outputs sum to its denominator). These are computed exactly in the Bernstein basis by products
//! of Bernstein polynomials ([`ism_geom::Bernstein::mul`]), so `F − c`'s numerator
//! `N_F = Σ f_i N_i` and `D` are known as Bernstein polynomials on every sub-simplex (restriction
//! by blossoming). Then on a sub-simplex `T`
//!
//! `G − F = (G·D − N_F) / D`, and `|G − F| ≤ max_J |coef_J(G·D − N_F)| / min_J coef_J(D)`
//!
//! because a Bernstein polynomial lies between its smallest and largest coefficient (the basis is
//! non-negative and sums to 1) — provided `min coef(D) > 0`, which holds for the format's stages
//! (positive weights, increasing monotonic maps) once the cell is small enough; otherwise the bound
//! is infinite and a finer `k` is tried. A control point shared with an earlier cell takes that
//! cell's value; the largest such change `δ` is added to the bound (changing Bernstein coefficients
//! by at most `δ` changes the polynomial by at most `δ`). Floating-point rounding in forming the
//! coefficients is covered by an allowance of [`ROUNDING_ALLOWANCE_ULPS`] ulps of the magnitudes
//! involved (all products and sums are of the terms that magnitude bounds). The bound is therefore
//! conservative: the true `max |G − F|` over the cell is at most the printed value.
//!
//! **Where the tolerance applies.** A cell on which `N_F − c·D` (hence `F − c`) and `G − c` both
//! have Bernstein coefficients of one strict sign contains no point of either level set, so its
//! error cannot move the contour; the tolerance is compared with the bound over the other cells
//! (the ones the level may cross), and the bound over all cells is reported beside it.
//!
//! **Models with a parametric stage** (`X⁻¹` stored) that the exact cells do not take: `F` is not a
//! ratio of polynomials of `w`, so the bound is an *estimate*: the largest `|G − F|` at a dense
//! lattice of sample points ([`estimate_lattice_degree`]) of every sub-simplex, reported with
//! `certified: false` — never presented as a certificate. The same is done when an all-implicit
//! model's composed degree `E` exceeds [`MAX_COMPOSED_DEGREE`] (exact products would cost more
//! than they are worth). An estimate can be low between its lattice points (measured there, and
//! on `stratified-3d` before its degree 24 was certified: the degree-4 interpolant's estimate
//! 1.878e-3 "met" the field tolerance 1.886e-3, and 3.2 M random points found 1.921e-3).

use ism_format::progress::Progress;
use ism_format::{multi_index, Direction, Model, StageKind, Topology};
use ism_geom::{Bernstein, LocalMap, LocalStage, ModelEval, Restriction, MAX_VARS};
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};

use crate::vtk::{
    cell_type, vtk_local_multi_indices, ArrayValues, Attribute, DataArray, UnstructuredGrid,
};
use crate::{Error, Result};

mod exact;
pub use exact::MAX_EXACT_DEGREE;

/// Highest interpolation degree tried (84 control points per tetrahedron at 6).
pub const MAX_DEGREE: u32 = 6;

/// Most levels of red refinement tried (`8^3 = 512` sub-tetrahedra per cell).
pub const MAX_LEVEL: u32 = 3;

/// Largest composed degree `E` for which the exact rational form is built (and the bound is
/// certified); above it the bound falls back to an estimate. 24 takes the stratified chains of
/// edge, face and interior strata (degrees 4 · 3 · 2, `stratified-3d`), whose estimate had
/// claimed a tolerance the field did not meet (module doc). The cost grows fast with `E` (2 925
/// coefficients per polynomial at 24 in 3D, products `O(count(E)²)`, each bisection of the
/// certificate `O(E · count(E))`): `stratified-3d`'s certified search takes 0.59 CPU-s where its
/// estimate took 0.04 (BENCHMARKS.md, issue 19, session 51).
pub const MAX_COMPOSED_DEGREE: u32 = 24;

/// Most control points a candidate `(p, k)` of the search may write (a point shared by cells
/// counted once: `Σ_d f_d · C(p·2^k − 1, d)` over the complex's `f_d` faces of dimension `d`), so
/// a tight tolerance on a big model ends in "not met, best bound" instead of an unbounded file:
/// 16 M points. The 1 M-tet model of BENCHMARKS.md (`ism-make-examples --large 1000000`) meets its
/// default tolerance at degree 4 with 11.4 M points (a 1.15 GB `.vtu` with ASCII arrays, 0.68 GB
/// binary as written since session 45).
/// The cap was 4 M points counted per cell, 3–7× the points written: it stopped that model at
/// degree 2, 8× over its tolerance.
pub const MAX_CONTROL_POINTS: usize = 16_000_000;

/// Rounding allowance of the certificate, in ulps of the magnitudes involved: the coefficients
/// come from `O(E + p)` levels of products and sums of non-negative combinations, each rounding by
/// half an ulp; 1 024 ulps covers every degree this module builds with a wide margin, and is still
/// 1e-13 relative — far below any useful field tolerance.
pub const ROUNDING_ALLOWANCE_ULPS: f64 = 1024.0;

/// Degree of the sample lattice of an estimated bound (module doc) for interpolation degree `p`:
/// `2p + 2`, about two sample points per interval between interpolation nodes, where `G − F` is
/// zero, so each peak between them is sampled near its top. Measured on random models (test
/// `random_models_are_within_the_reported_bound`, two seeded runs of 150 models, 97 and 67
/// estimates; the first also with 3D parametric models of 3 cells a side): with `p + 4`, the
/// lattice before, the sampled `|G − F|` exceeded 5 and 1 of them, by up to 1.43× and 1.002× (an
/// unseeded run: 6 of 84, up to 1.61×); with `2p + 2`, none, at most 0.97× and 0.90×. It costs up
/// to 2.4× the samples (degree 6 in 3D: 680 for 286; the same lattice at `p = 2`). Still an
/// estimate, not a bound, and still low on smooth fitted models: on the fitted sphere preset (`ism
/// fit --preset sphere`) it reads 9.13e-4 on the unrefined degree-6 cells (`p + 4`: 5.80e-4) and
/// accepts them at the default field tolerance 9.86e-4, where a lattice of degree `4p + 1` finds
/// more than that tolerance there (and took 123 CPU-s instead of 3).
pub const fn estimate_lattice_degree(p: u32) -> u32 {
    2 * p + 2
}

/// Default field tolerance as a multiple of the surface tolerance: `ε_F = tolerance · g`, with `g`
/// the median `|∇F|` of the linear interpolant over the simplices the shape crosses, so contouring
/// the written field moves the surface by about `tolerance` (first order: `|δp| ≈ |δF| / |∇F|`).
///
/// Takes the evaluator [`volume_grid`] is given too: its inverses and spatial index are built once
/// per export (`ism export --volume` built them twice before).
pub fn default_field_tolerance(eval: &ModelEval, surface_tolerance: f64) -> f64 {
    let model = eval.model();
    let n = model.dim();
    let mut g: Vec<f64> = (0..model.num_simplices())
        .filter(|&s| eval.patch(s).is_some())
        .map(|s| {
            let ids = model.simplex(s);
            let f0 = model.values[ids[0] as usize];
            let a = eval.inv_edges(s);
            let mut grad = [0.0; 3];
            for (x, gx) in grad.iter_mut().enumerate().take(n) {
                *gx = (0..n)
                    .map(|l| (model.values[ids[l + 1] as usize] - f0) * a[l][x])
                    .sum();
            }
            grad.iter().map(|v| v * v).sum::<f64>().sqrt()
        })
        .filter(|v| v.is_finite() && *v > 0.0)
        .collect();
    if g.is_empty() {
        return surface_tolerance;
    }
    g.sort_unstable_by(f64::total_cmp);
    surface_tolerance * g[g.len() / 2]
}

/// Options of [`volume_grid`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VolumeOptions {
    /// Largest accepted `max |G − F|` over every cell, in units of `F`.
    pub field_tolerance: f64,
    /// Interpolated cells on straight (linear) geometry even where exact cells could be written:
    /// polynomial Bézier cells without weights, for a consumer that evaluates only those, with
    /// the certified (all-implicit) or estimated bound. `false` (what `ism export` does): exact
    /// cells wherever the stages allow them.
    pub interpolate: bool,
}

/// What [`volume_grid`] wrote and how far it is from `F`.
#[derive(Clone, Debug, PartialEq)]
pub struct VolumeReport {
    /// Degree `p` of the Bézier cells.
    pub degree: u32,
    /// Levels `k` of red refinement of each simplex.
    pub level: u32,
    /// Cells written.
    pub cells: usize,
    /// Control points written.
    pub control_points: usize,
    /// Bound on `max |G − F|` over every cell the level may cross (a cell is left out only when
    /// `F − c` and `G − c` are both certified to keep one sign on it, so neither has a contour
    /// there): the number the tolerance is compared with.
    pub bound: f64,
    /// Bound on `max |G − F|` over the whole complex (away from the level it is the one-piece
    /// Bernstein bound, looser than `bound`'s refined one).
    pub global_bound: f64,
    /// The field tolerance asked for.
    pub tolerance: f64,
    /// Whether `bound` is a certified (conservative) bound; `false`: estimated from samples.
    pub certified: bool,
    /// Whether the cells are `F` itself (isoparametric cells on the model's parametrisation,
    /// `bound` then covers rounding only) rather than an interpolant on linear cells.
    pub exact: bool,
    /// `bound ≤ tolerance`.
    pub met: bool,
    /// One line on the method, for the user.
    pub note: String,
}

/// Control points written for degree `p` after `k` levels of red refinement: every point of the
/// `q = p·2^k` lattice of every top simplex, a shared one once — `Σ_d f_d · C(q − 1, d)` over
/// the complex's `f_d` faces of dimension `d` (`C(q − 1, d)` lattice points lie inside a
/// `d`-face). Red refinement's children are unimodular in the `2^k` lattice, so their degree-`p`
/// lattices cover the parent's `q` lattice exactly (test
/// `written_points_count_the_assembled_grid`). Saturates instead of wrapping.
fn written_points(topology: &Topology, n: usize, p: u32, k: u32) -> usize {
    let q = u64::from(p) << k;
    (0..=n)
        .map(|d| inside_points(q, d).saturating_mul(topology.num_faces(d) as u128))
        .fold(0u128, u128::saturating_add)
        .try_into()
        .unwrap_or(usize::MAX)
}

/// `C(q − 1, d)`: the points of the degree-`q` lattice inside a `d`-face (0 for `q ≤ d`);
/// exact while it fits (each partial product is a binomial times a factorial), else `u128::MAX`.
fn inside_points(q: u64, d: usize) -> u128 {
    (0..d as u64)
        .try_fold(1u128, |c, i| {
            Some(c.checked_mul(u128::from(q.saturating_sub(1 + i)))? / u128::from(i + 1))
        })
        .unwrap_or(u128::MAX)
}

/// The ids of the control points an assembly writes, by their place in the lattice of the face
/// that carries them: a point of a cell's degree-`q` lattice (numerators over `q` of the parent
/// simplex's barycentric coordinates) lies inside the face spanned by its nonzero numerators, and
/// is one of that face's `C(q − 1, d)` interior points — ranked by its numerators less one, in the
/// face's vertices by ascending global id, so every cell sharing the face finds the same slot.
/// One `u64` per slot, assigned in the order the points are first met (the order a map keyed by
/// the sorted (global vertex, numerator) pairs gave, so the same ids): the map held a key vector
/// per point, ~100 bytes each on the 1 M-tet model's 11.4 M points.
pub(crate) struct PointIds<'a> {
    model: &'a Model,
    topology: &'a Topology,
    q: u32,
    /// Per face dimension: the first slot and the slots per face.
    base: [usize; MAX_VARS],
    inside: [usize; MAX_VARS],
    ids: Vec<u64>,
    /// The face ids of `parent`'s faces by local mask ([`Topology::faces_by_mask`]).
    parent: Option<usize>,
    faces: [ism_format::FaceId; 16],
}

impl<'a> PointIds<'a> {
    /// No point yet, for the degree-`q` lattices of `model`'s simplices (`topology` its faces).
    pub(crate) fn new(model: &'a Model, topology: &'a Topology, q: u32) -> PointIds<'a> {
        let n = model.dim();
        let (mut base, mut inside) = ([0usize; MAX_VARS], [0usize; MAX_VARS]);
        let mut total = 0usize;
        for d in 0..=n {
            // Small: q is at most MAX_DEGREE · 2^MAX_LEVEL or MAX_EXACT_DEGREE.
            inside[d] = usize::try_from(inside_points(u64::from(q), d)).unwrap_or(usize::MAX);
            base[d] = total;
            total = total.saturating_add(topology.face_slots(d).saturating_mul(inside[d]));
        }
        PointIds {
            model,
            topology,
            q,
            base,
            inside,
            ids: vec![u64::MAX; total],
            parent: None,
            faces: [ism_format::FaceId { dim: 0, index: 0 }; 16],
        }
    }

    /// The slot of the point with numerators `num` (over `q`, summing to `q`) of simplex
    /// `parent`: its id is `self.ids[slot]` (`u64::MAX` until one is given).
    pub(crate) fn slot(&mut self, parent: usize, num: &[u32]) -> usize {
        if self.parent != Some(parent) {
            self.faces = self.topology.faces_by_mask(self.model, parent);
            self.parent = Some(parent);
        }
        let ids = self.model.simplex(parent);
        let mut support = [(0u32, 0u32); MAX_VARS];
        let (mut len, mut mask) = (0, 0usize);
        for (i, &a) in num.iter().enumerate().take(ids.len()) {
            if a > 0 {
                support[len] = (ids[i], a - 1);
                len += 1;
                mask |= 1 << i;
            }
        }
        support[..len].sort_unstable();
        let mut shifted = [0u32; MAX_VARS];
        for (x, &(_, a)) in shifted.iter_mut().zip(&support[..len]) {
            *x = a;
        }
        debug_assert_eq!(
            shifted[..len].iter().sum::<u32>() + len as u32,
            self.q,
            "numerators over q"
        );
        let face = self.faces[mask];
        let d = usize::from(face.dim);
        self.base[d] + face.index as usize * self.inside[d] + multi_index::rank(&shifted[..len])
    }

    /// The id stored for `slot`, if any.
    pub(crate) fn get(&self, slot: usize) -> Option<u64> {
        Some(self.ids[slot]).filter(|&id| id != u64::MAX)
    }

    /// Gives `slot` the id `id`.
    pub(crate) fn set(&mut self, slot: usize, id: u64) {
        self.ids[slot] = id;
    }
}

/// `F` on one simplex, in the form the certificate needs.
enum CellField {
    /// No stage touches the simplex: `F = Σ f_i w_i`.
    Linear([f64; MAX_VARS]),
    /// `F = N_F / D` (shifted by nothing: `N_F = Σ f_i N_i`), degree `E`.
    Rational { nf: Bernstein, d: Bernstein },
    /// Only evaluation is available (parametric stage, or `E` too high).
    Sampled,
}

/// A sub-simplex of refinement level `k`: corners as barycentric numerators over `2^k`.
type SubSimplex = Vec<[u32; MAX_VARS]>;

/// The `2^n`-way red refinement of a simplex given by corner numerators (2D: 4 triangles; 3D: 8
/// tetrahedra, the octahedron cut along the midpoint diagonal `m02–m13`). Children keep the
/// parent's orientation (a negatively oriented child gets two corners swapped).
fn red_refine(n: usize, c: &[[u32; MAX_VARS]]) -> Vec<SubSimplex> {
    // Corners doubled (to level + 1) and midpoints.
    let d: Vec<[u32; MAX_VARS]> = c
        .iter()
        .map(|v| {
            let mut o = [0; MAX_VARS];
            for i in 0..MAX_VARS {
                o[i] = 2 * v[i];
            }
            o
        })
        .collect();
    let mid = |a: usize, b: usize| {
        let mut o = [0; MAX_VARS];
        for i in 0..MAX_VARS {
            o[i] = c[a][i] + c[b][i];
        }
        o
    };
    let mut kids: Vec<SubSimplex> = if n == 2 {
        let (m01, m12, m02) = (mid(0, 1), mid(1, 2), mid(0, 2));
        vec![
            vec![d[0], m01, m02],
            vec![m01, d[1], m12],
            vec![m02, m12, d[2]],
            vec![m12, m02, m01],
        ]
    } else {
        let (m01, m02, m03, m12, m13, m23) = (
            mid(0, 1),
            mid(0, 2),
            mid(0, 3),
            mid(1, 2),
            mid(1, 3),
            mid(2, 3),
        );
        vec![
            vec![d[0], m01, m02, m03],
            vec![m01, d[1], m12, m13],
            vec![m02, m12, d[2], m23],
            vec![m03, m13, m23, d[3]],
            vec![m02, m13, m01, m12],
            vec![m02, m13, m12, m23],
            vec![m02, m13, m23, m03],
            vec![m02, m13, m03, m01],
        ]
    };
    let parent = orientation(n, &d);
    for k in &mut kids {
        if orientation(n, k) * parent < 0 {
            k.swap(0, 1);
        }
    }
    kids
}

/// Sign of the determinant of the corners' barycentric edge vectors (coordinates 1..=n).
fn orientation(n: usize, c: &[[u32; MAX_VARS]]) -> i64 {
    let e = |k: usize, i: usize| i64::from(c[k][i]) - i64::from(c[0][i]);
    let det = if n == 2 {
        e(1, 1) * e(2, 2) - e(1, 2) * e(2, 1)
    } else {
        e(1, 1) * (e(2, 2) * e(3, 3) - e(2, 3) * e(3, 2))
            - e(1, 2) * (e(2, 1) * e(3, 3) - e(2, 3) * e(3, 1))
            + e(1, 3) * (e(2, 1) * e(3, 2) - e(2, 2) * e(3, 1))
    };
    det.signum()
}

/// All sub-simplices of level `k` (corner numerators over `2^k`).
fn sub_simplices(n: usize, k: u32) -> Vec<SubSimplex> {
    let m = n + 1;
    let mut root = vec![[0u32; MAX_VARS]; m];
    for (i, c) in root.iter_mut().enumerate() {
        c[i] = 1;
    }
    let mut level = vec![root];
    for _ in 0..k {
        level = level.iter().flat_map(|s| red_refine(n, s)).collect();
    }
    level
}

/// `x_i = w_i` as degree-1 polynomials.
fn coordinates(m: usize) -> Vec<Bernstein> {
    (0..m)
        .map(|i| Bernstein::from_fn(m, 1, |idx| if idx[i] == 1 { 1.0 } else { 0.0 }))
        .collect()
}

/// Powers `x^0 … x^d` (degree-0 constant 1 first).
fn powers(x: &Bernstein, d: u32) -> Vec<Bernstein> {
    let mut out = vec![Bernstein::constant(x.vars(), 0, 1.0)];
    for _ in 0..d {
        let next = out.last().expect("non-empty").mul(x);
        out.push(next);
    }
    out
}

/// Sum of polynomials of one shape.
fn sum(polys: impl Iterator<Item = Bernstein>) -> Option<Bernstein> {
    polys.reduce(|a, b| a.add(&b))
}

/// One implicit stage applied projectively to `x` (homogeneous polynomials of one degree `e`):
/// the stage's homogeneous numerators, degree `d·e`.
fn apply_stage(stage: &LocalStage, x: &[Bernstein]) -> Vec<Bernstein> {
    let m = x.len();
    let d = stage.degree();
    match stage.kind() {
        StageKind::Bezier | StageKind::Rational => {
            let pw: Vec<Vec<Bernstein>> = x.iter().map(|xi| powers(xi, d)).collect();
            let idx = multi_index::all(m, d);
            let points = stage.control_points();
            let weights = stage.weights();
            let mut out: Vec<Option<Bernstein>> = vec![None; m];
            for (r, i) in idx.chunks_exact(m).enumerate() {
                let mut mono = pw[0][i[0] as usize].clone();
                for k in 1..m {
                    mono = mono.mul(&pw[k][i[k] as usize]);
                }
                let q = weights.get(r).copied().unwrap_or(1.0);
                let c = multinomial(i) * q;
                for k in 0..m {
                    let b = points[r][k];
                    if b != 0.0 {
                        let term = mono.scale(c * b);
                        out[k] = Some(match out[k].take() {
                            Some(acc) => acc.add(&term),
                            None => term,
                        });
                    }
                }
            }
            let zero = Bernstein::constant(m, x[0].degree() * d, 0.0);
            out.into_iter()
                .map(|o| o.unwrap_or_else(|| zero.clone()))
                .collect()
        }
        StageKind::Monotonic => {
            let total = sum(x.iter().cloned()).expect("m ≥ 2");
            (0..m)
                .map(|i| {
                    let rest = total.add(&x[i].scale(-1.0));
                    let a = stage.monotonic_coefficients(i);
                    let pa = powers(&x[i], d);
                    let pb = powers(&rest, d);
                    sum((0..=d).map(|j| {
                        let c = a[j as usize] * binomial(d, j);
                        pa[j as usize].mul(&pb[(d - j) as usize]).scale(c)
                    }))
                    .expect("d ≥ 1")
                })
                .collect()
        }
    }
}

fn binomial(n: u32, k: u32) -> f64 {
    multi_index::binomial(u64::from(n), u64::from(k)) as f64
}

fn multinomial(i: &[u32]) -> f64 {
    let mut c = 1.0;
    let mut k = 0u32;
    for &e in i {
        for j in 1..=e {
            k += 1;
            c *= f64::from(k) / f64::from(j);
        }
    }
    c
}

/// The degree of stages of these degrees composed, saturating: a file may hold any number of
/// stages of degree up to 16, and sixteen of degree 16 wrap a `u64` product to 0 (which would pass
/// every degree limit).
fn composed_degree(degrees: impl Iterator<Item = u32>) -> u64 {
    degrees.fold(1, |e, d| e.saturating_mul(u64::from(d)))
}

/// `F` on simplex `s` as `N_F / D` when every stage is implicit and `E ≤ cap` (at most
/// [`MAX_COMPOSED_DEGREE`], [`certified_degree_cap`]).
fn cell_field(model: &Model, map: &LocalMap, ids: &[u32], cap: u32) -> CellField {
    let m = map.vars();
    let mut f = [0.0; MAX_VARS];
    for i in 0..m {
        f[i] = model.values[ids[i] as usize];
    }
    if map.stages().is_empty() {
        return CellField::Linear(f);
    }
    let degree = composed_degree(map.stages().iter().map(LocalStage::degree));
    if degree > u64::from(cap.min(MAX_COMPOSED_DEGREE))
        || map
            .stages()
            .iter()
            .any(|s| s.direction() != Direction::Implicit)
    {
        return CellField::Sampled;
    }
    let mut x = coordinates(m);
    for stage in map.stages() {
        x = apply_stage(stage, &x);
    }
    let d = sum(x.iter().cloned()).expect("m ≥ 2");
    let nf = sum(x.iter().enumerate().map(|(i, xi)| xi.scale(f[i]))).expect("m ≥ 2");
    CellField::Rational { nf, d }
}

/// Composed degree up to which the exact rational form is always built (and the bound
/// certified), whatever the model's size: the cap before session 51, which no model has been
/// seen to pay for.
pub const ALWAYS_CERTIFIED_DEGREE: u32 = 12;

/// Most coefficients per polynomial, over all simplices (`simplices · C(E + n, n)`), that the
/// exact rational forms of a chain of composed degree `E` above [`ALWAYS_CERTIFIED_DEGREE`] may
/// hold: the search keeps every simplex's `N_F` and `D` (two polynomials of 2 925 coefficients at
/// degree 24 in 3D), and certifying one costs ~3.5 ms (`stratified-3d`, 162 tetrahedra: 0.56 s
/// on one thread). 8 M coefficients are 128 MB and, at that rate (not measured), ~10 CPU-s (2,700 tetrahedra at degree
/// 24); the 1 M-tet model of BENCHMARKS.md (degree 24, 1,053,696 tetrahedra) would need 49 GB, so
/// a larger model keeps the estimate, and says so.
pub const CERTIFIED_COEFFICIENTS: u64 = 8_000_000;

/// The composed-degree cap of [`cell_field`] for `model`: [`MAX_COMPOSED_DEGREE`] when its whole
/// chain's degree is at most [`ALWAYS_CERTIFIED_DEGREE`] or its exact forms fit
/// [`CERTIFIED_COEFFICIENTS`], else [`ALWAYS_CERTIFIED_DEGREE`].
fn certified_degree_cap(model: &Model) -> u32 {
    let top = composed_degree(model.stages.iter().map(|s| s.degree));
    let m = model.dim() + 1;
    let fits = top <= u64::from(MAX_COMPOSED_DEGREE)
        && (model.num_simplices() as u64).saturating_mul(multi_index::count(m, top as u32) as u64)
            <= CERTIFIED_COEFFICIENTS;
    if top <= u64::from(ALWAYS_CERTIFIED_DEGREE) || fits {
        MAX_COMPOSED_DEGREE
    } else {
        ALWAYS_CERTIFIED_DEGREE
    }
}

/// Inverse of the Bernstein collocation matrix at the degree-`p` lattice (row-major, `count²`):
/// coefficients = `A⁻¹ ·` values at `J/p`. Gauss–Jordan with partial pivoting, hand-written for a
/// matrix of at most 84 × 84 built once per degree.
fn inverse_collocation(m: usize, p: u32) -> Result<Vec<f64>> {
    let canonical = multi_index::all(m, p);
    let count = canonical.len() / m;
    let mut a = vec![0.0; count * count];
    for r in 0..count {
        let w: Vec<f64> = (0..m)
            .map(|i| f64::from(canonical[r * m + i]) / f64::from(p))
            .collect();
        for c in 0..count {
            let idx = &canonical[c * m..(c + 1) * m];
            a[r * count + c] = multinomial(idx)
                * idx
                    .iter()
                    .zip(&w)
                    .map(|(&e, &x)| x.powi(e as i32))
                    .product::<f64>();
        }
    }
    let mut inv = vec![0.0; count * count];
    for i in 0..count {
        inv[i * count + i] = 1.0;
    }
    for col in 0..count {
        let pivot = (col..count)
            .max_by(|&x, &y| {
                a[x * count + col]
                    .abs()
                    .total_cmp(&a[y * count + col].abs())
            })
            .expect("non-empty range");
        if a[pivot * count + col].abs() < 1e-14 {
            return Err(Error::Unsupported(format!(
                "collocation matrix of degree {p} is singular"
            )));
        }
        for k in 0..count {
            a.swap(col * count + k, pivot * count + k);
            inv.swap(col * count + k, pivot * count + k);
        }
        let piv = a[col * count + col];
        for k in 0..count {
            a[col * count + k] /= piv;
            inv[col * count + k] /= piv;
        }
        for r in 0..count {
            if r != col {
                let f = a[r * count + col];
                if f != 0.0 {
                    for k in 0..count {
                        a[r * count + k] -= f * a[col * count + k];
                        inv[r * count + k] -= f * inv[col * count + k];
                    }
                }
            }
        }
    }
    Ok(inv)
}

/// `poly` restricted to the sub-simplex with barycentric `vertices` (of the cell), and a bound on
/// how far the computed coefficients are from the exact restriction's. Each de Casteljau step
/// forms `Σ λ_i c_i` (at most `m` terms), rounded by at most `γ_m Σ |λ_i c_i|` with
/// `γ_m = m·ε / (1 − m·ε)`; a step scales magnitudes and earlier errors by at most `Σ |λ_i|`, so
/// `m` replacements of `d` steps each are off by at most `m · d · γ_m · A · max |coef|`, where `A`
/// is the plan's [`Restriction::amplification`] (1 without a plan: the blossom at the vertices'
/// own coordinates, convex combinations). The interior children of a red refinement replace with
/// weights outside the simplex (`A = 3ᵈ` at one level), which the certificate's allowance did not
/// cover before (BENCHMARKS.md, issue 19, session 51: at degree 24 two levels gave bounds of 6e7).
fn restricted(poly: &Bernstein, vertices: &[Vec<f64>]) -> (Bernstein, f64) {
    let m = poly.vars();
    let d = poly.degree();
    let eps = f64::EPSILON;
    let gamma = (m as f64 * eps) / (1.0 - m as f64 * eps);
    let magnitude = poly.coeffs().iter().map(|c| c.abs()).fold(0.0, f64::max);
    let (out, amplification) = match Restriction::new(vertices) {
        Some(plan) => (poly.restrict_with(&plan), plan.amplification(d)),
        None => (poly.restrict(vertices), 1.0),
    };
    let err = m as f64 * f64::from(d) * gamma * amplification * magnitude;
    // NaN (an infinite amplification times a zero magnitude) bounds nothing.
    (out, if err.is_nan() { f64::INFINITY } else { err })
}

/// Shared per-degree tables.
struct DegreeTables {
    p: u32,
    /// Canonical degree-`p` indices, flat.
    canonical: Vec<u32>,
    inv: Vec<f64>,
    /// Dense sample lattice ([`estimate_lattice_degree`]) for estimates, flat canonical indices.
    dense: Vec<u32>,
}

/// One written sub-cell: its local Bernstein coefficients of `G` (canonical order), the keys of its
/// control points, and its own bound (before sharing).
struct SubCell {
    parent: usize,
    corners: SubSimplex,
    coeffs: Vec<f64>,
    bound: f64,
    /// Certified sign of `F − c` on the whole sub-cell (`±1`), or 0 when the level may cross it.
    side: i8,
}

impl SubCell {
    /// The cell is certified free of the level: `F − c` has sign `side` everywhere (certified by
    /// its Bernstein coefficients) and so do all of `G − c`'s coefficients (so `G − c` too).
    fn away(&self, coeffs: impl Iterator<Item = f64>, level: f64) -> bool {
        self.side != 0
            && coeffs
                .into_iter()
                .all(|v| (v - level) * f64::from(self.side) > 0.0)
    }
}

/// Barycentric point of the parent from sub-simplex corners (numerators over `2^k`) and a lattice
/// index `J` of degree `p`: numerators over `p · 2^k`.
fn lattice_numerators(corners: &[[u32; MAX_VARS]], j: &[u32]) -> [u32; MAX_VARS] {
    let mut o = [0u32; MAX_VARS];
    for (c, &e) in corners.iter().zip(j) {
        for i in 0..MAX_VARS {
            o[i] += e * c[i];
        }
    }
    o
}

fn to_bary(num: &[u32; MAX_VARS], denom: f64, m: usize) -> [f64; MAX_VARS] {
    let mut w = [0.0; MAX_VARS];
    for i in 0..m {
        w[i] = f64::from(num[i]) / denom;
    }
    w
}

/// Bisections of the certificate's domain (not of the written cell) per cell: up to `2^8` pieces
/// where the one-piece bound is loose.
const CERTIFY_DEPTH: u32 = 8;

/// The denominator `D` of [`certify`]'s quotient on the current piece.
#[derive(Clone, Copy)]
enum Denominator<'a> {
    /// `D` itself, bisected with the numerator (rational stages: `D` varies over the cell), and
    /// how far its coefficients may be below the true ones (restriction rounding, [`restricted`]).
    Poly(&'a Bernstein, f64),
    /// A positive lower bound of `D` over the whole cell, hence over every piece (non-rational
    /// stages: `D` is a constant up to rounding, [`NEAR_CONSTANT_DENOMINATOR`]).
    Floor(f64),
}

/// Largest spread `max coef(D) − min coef(D)`, relative to `min coef(D)`, for which `D` is taken
/// as the constant `min coef(D)` plus a remainder counted in the allowance ([`fit_sub`]). Stages
/// without weights sum their outputs to 1, so `D` is constant but for the rounding of its
/// products (~1e-15 relative); 1e-12 leaves that a wide margin, and the remainder it admits
/// (`max |G| · spread`) is still far below any field tolerance. Splitting a constant `D` with the
/// numerator, and multiplying `G` by it, was most of the certificate's cost at composed degree 24.
const NEAR_CONSTANT_DENOMINATOR: f64 = 1e-12;

/// `max |num / D|` over the simplex, bounded by `(max |coef(num)| + allowance) / min coef(D)`
/// (`D > 0`), tightened by bisecting the domain (de Casteljau, [`Bernstein::split_edge`]) while the
/// bound exceeds `target` and depth remains: on a piece the coefficients converge to the values,
/// so the bound converges to the true maximum. The maximum over the pieces bounds the whole.
/// Infinite when `D`'s coefficients are not all positive on a piece at the depth limit.
fn certify(num: &Bernstein, d: Denominator, allowance: f64, target: f64, depth: u32) -> f64 {
    let dmin = match d {
        Denominator::Poly(d, slack) => d.min_coeff() - slack,
        Denominator::Floor(v) => v,
    };
    let worst = num.coeffs().iter().map(|c| c.abs()).fold(0.0, f64::max);
    let bound = if dmin > 0.0 {
        (worst + allowance) / dmin
    } else {
        f64::INFINITY
    };
    if bound <= target || depth == 0 || bound.is_nan() {
        return bound;
    }
    // Split the edge whose ends' values of num differ most (where the pieces gain most).
    let m = num.vars();
    let mut edge = (0, 1);
    let mut spread = -1.0;
    for a in 0..m {
        for b in a + 1..m {
            let mut diff = (num.vertex_value(a) - num.vertex_value(b)).abs();
            if let Denominator::Poly(d, _) = d {
                diff += (d.vertex_value(a) - d.vertex_value(b)).abs();
            }
            if diff > spread {
                spread = diff;
                edge = (a, b);
            }
        }
    }
    // Alternate with a round-robin edge so that no edge is never split.
    if depth % 2 == 0 {
        let k = (depth as usize / 2) % (m * (m - 1) / 2);
        let mut pairs = (0..m).flat_map(|a| (a + 1..m).map(move |b| (a, b)));
        edge = pairs.nth(k).unwrap_or(edge);
    }
    let (n1, n2) = num.split_edge(edge.0, edge.1);
    let halves = match d {
        Denominator::Poly(d, slack) => Some((d.split_edge(edge.0, edge.1), slack)),
        Denominator::Floor(_) => None,
    };
    let (d1, d2) = match &halves {
        Some(((d1, d2), slack)) => (Denominator::Poly(d1, *slack), Denominator::Poly(d2, *slack)),
        None => (d, d),
    };
    let b1 = certify(&n1, d1, allowance, target, depth - 1);
    if b1.is_nan() || b1 > bound {
        return bound;
    }
    let b2 = certify(&n2, d2, allowance, target, depth - 1);
    bound.min(b1.max(b2))
}

/// Fits `G` on one sub-simplex and bounds `|G − F|` there.
#[allow(clippy::too_many_arguments)]
fn fit_sub(
    eval: &ModelEval,
    map: &LocalMap,
    field: &CellField,
    s: usize,
    m: usize,
    k: u32,
    corners: &[[u32; MAX_VARS]],
    t: &DegreeTables,
    tol: f64,
    level: f64,
) -> (Vec<f64>, f64, i8) {
    let p = t.p;
    let count = t.canonical.len() / m;
    let scale = f64::from(p) * f64::from(1u32 << k);
    let bary = |j: &[u32]| to_bary(&lattice_numerators(corners, j), scale, m);
    let value = |w: &[f64; MAX_VARS]| match field {
        CellField::Linear(f) => (0..m).map(|i| f[i] * w[i]).sum::<f64>(),
        _ => eval.value_from_coordinates(s, &map.eval(w)),
    };
    let values: Vec<f64> = t
        .canonical
        .chunks_exact(m)
        .map(|j| value(&bary(j)))
        .collect();
    let coeffs: Vec<f64> = (0..count)
        .map(|r| (0..count).map(|c| t.inv[r * count + c] * values[c]).sum())
        .collect();
    let sign_of = |c: &mut dyn Iterator<Item = f64>| -> i8 {
        let (mut pos, mut neg, mut any) = (true, true, false);
        for v in c {
            any = true;
            pos &= v > 0.0;
            neg &= v < 0.0;
        }
        if any && pos {
            1
        } else if any && neg {
            -1
        } else {
            0
        }
    };
    let mut side = 0i8;
    let bound = match field {
        CellField::Linear(f) => {
            side = sign_of(&mut corners.iter().map(|c| {
                let w = to_bary(c, f64::from(1u32 << k), m);
                (0..m).map(|i| f[i] * w[i]).sum::<f64>() - level
            }));
            // G is F exactly (a linear function is its own interpolant): only rounding.
            let mag = f.iter().map(|v| v.abs()).fold(0.0, f64::max);
            ROUNDING_ALLOWANCE_ULPS * f64::EPSILON * mag * count as f64
        }
        CellField::Rational { nf, d } => {
            let verts: Vec<Vec<f64>> = corners
                .iter()
                .map(|c| to_bary(c, f64::from(1u32 << k), m)[..m].to_vec())
                .collect();
            let ((nf_t, nf_err), (d_t, d_err)) = if k == 0 {
                ((nf.clone(), 0.0), (d.clone(), 0.0))
            } else {
                (restricted(nf, &verts), restricted(d, &verts))
            };
            {
                let g = Bernstein::new(m, p, coeffs.clone()).expect("count matches the degree");
                let e = nf_t.degree();
                let gmax = coeffs.iter().map(|c| c.abs()).fold(0.0, f64::max);
                let dmax = d_t.coeffs().iter().map(|c| c.abs()).fold(0.0, f64::max);
                let nmax = nf_t.coeffs().iter().map(|c| c.abs()).fold(0.0, f64::max);
                let allowance = ROUNDING_ALLOWANCE_ULPS
                    * f64::EPSILON
                    * (gmax * dmax + nmax)
                    * f64::from(p + e + 1);
                // The restricted coefficients are within `nf_err` and `d_err` of the sub-cell's
                // own ([`restricted`]): `D` lies in `[dlo, dhi]` on it, and the numerator below
                // is off by at most `nf_err + max |G| · d_err`.
                let (dlo, dhi) = (d_t.min_coeff() - d_err, dmax + d_err);
                let allowance = allowance + nf_err + gmax * d_err;
                // `D` constant but for rounding (no weights): `G·D − N_F = (dlo·G − N_F) +
                // G·(D − dlo)`, and `|G·(D − dlo)| ≤ max |coef(G)| · (dhi − dlo)` (a Bernstein
                // polynomial lies within its coefficients' range), so the certificate bisects
                // `dlo·G − N_F` of degree `max(p, E)` alone against the floor `dlo` of `D`
                // ([`NEAR_CONSTANT_DENOMINATOR`]).
                let constant = dlo > 0.0 && dhi - dlo <= NEAR_CONSTANT_DENOMINATOR * dlo;
                let (num, allowance) = if constant {
                    let top = p.max(e);
                    let mut num = g.elevate_to(top).scale(dlo);
                    num.add_scaled(&nf_t.elevate_to(top), -1.0);
                    (num, allowance + gmax * (dhi - dlo))
                } else {
                    (
                        g.mul(&d_t).add(&nf_t.elevate_to(p + e).scale(-1.0)),
                        allowance,
                    )
                };
                let denominator = if constant {
                    Denominator::Floor(dlo)
                } else {
                    Denominator::Poly(&d_t, d_err)
                };
                // Sign of F − c = (N_F − c D) / D on the cell, certified by the coefficients
                // (each farther from 0 than its restriction's error).
                let margin = nf_err + level.abs() * d_err;
                side = sign_of(
                    &mut nf_t
                        .coeffs()
                        .iter()
                        .zip(d_t.coeffs())
                        .map(|(a, b)| a - level * b)
                        .map(|v| if v.abs() > margin { v } else { 0.0 }),
                );
                let away = side != 0 && coeffs.iter().all(|v| (v - level) * f64::from(side) > 0.0);
                // Away from the level only the one-piece bound is computed (it is reported, but
                // the tolerance applies where the level may pass).
                let target = if away { f64::INFINITY } else { tol };
                let b = certify(&num, denominator, allowance, target, CERTIFY_DEPTH);
                if b.is_nan() {
                    f64::INFINITY
                } else {
                    b
                }
            }
        }
        CellField::Sampled => {
            let g = Bernstein::new(m, p, coeffs.clone()).expect("count matches the degree");
            let q = estimate_lattice_degree(p);
            let denom = f64::from(q) * f64::from(1u32 << k);
            let mut worst = 0.0f64;
            for j in t.dense.chunks_exact(m) {
                let w = to_bary(&lattice_numerators(corners, j), denom, m);
                let mut local = [0.0; MAX_VARS];
                for i in 0..m {
                    local[i] = f64::from(j[i]) / f64::from(q);
                }
                let diff = (g.eval(&local[..m]) - value(&w)).abs();
                worst = if diff.is_nan() {
                    f64::INFINITY
                } else {
                    worst.max(diff)
                };
            }
            worst
        }
    };
    (coeffs, bound, side)
}

/// [`Error::Unsupported`] unless `n` is 2 or 3: the volume export writes VTK Bézier triangles or
/// tetrahedra only. [`crate::export::build`] asks before building the evaluator.
pub(crate) fn check_dimension(n: usize) -> Result<()> {
    if n != 2 && n != 3 {
        return Err(Error::Unsupported(format!(
            "volume export needs a 2D or 3D model, got dimension {n}"
        )));
    }
    Ok(())
}

/// Builds the volume grid of the model `eval` evaluates at the cheapest `(p, k)` meeting
/// `options.field_tolerance`.
///
/// # Errors
/// [`Error::Unsupported`] for a dimension other than 2 or 3 or a non-positive tolerance.
pub fn volume_grid(
    eval: &ModelEval,
    options: &VolumeOptions,
) -> Result<(UnstructuredGrid, VolumeReport)> {
    volume_grid_with_progress(eval, options, &Progress::none())
}

/// The phase [`volume_grid_with_progress`] reports, once per (degree, refinement) candidate it
/// fits on every simplex, counted in simplices.
pub const PHASE: &str = "fitting the Bézier field of F per simplex";

/// The phase of a candidate's screen (its fit on the crossed simplices only, [`SCREENED`]),
/// counted in simplices.
pub const SCREEN_PHASE: &str = "screening a Bézier field candidate on the crossed simplices";

/// Largest fraction of the simplices crossed by the shape for which a candidate is first fitted
/// on those alone (its screen). Their cells are among those the tolerance applies to, so a screen
/// over the tolerance refuses the candidate at a fraction of a whole fit (the 1 M-tet model:
/// degrees 2 and 3 refused on its crossed simplices before degree 4 met, BENCHMARKS.md); a
/// candidate that passes is then fitted whole, so its screen is spent for nothing. A quarter: a
/// passed screen wastes at most a quarter of a whole fit, a refused one saves at least three
/// quarters of one.
pub const SCREENED: f64 = 0.25;

/// [`volume_grid`] with a progress and cancel hook (phases [`PHASE`] and [`SCREEN_PHASE`]); a
/// cancelled hook stops the fit within one simplex per worker thread.
///
/// # Errors
/// As [`volume_grid`]; [`Error::Cancelled`] when `progress` was cancelled.
pub fn volume_grid_with_progress(
    eval: &ModelEval,
    options: &VolumeOptions,
    progress: &Progress,
) -> Result<(UnstructuredGrid, VolumeReport)> {
    let model = eval.model();
    let n = model.dim();
    check_dimension(n)?;
    let tol = options.field_tolerance;
    if tol.is_nan() || tol <= 0.0 {
        return Err(Error::Unsupported(format!(
            "field tolerance must be positive, got {tol}"
        )));
    }
    // `F` itself where the stages allow it: on the examples no larger than the interpolant that
    // meets the default tolerance (BENCHMARKS.md, session 42), and exact. Its bound is rounding
    // only, unless weights span many orders of magnitude (rational-degree5's weights raised to
    // the 60th power: 4.8e21): then the interpolant is tried too and the smaller bound written.
    let exact = if options.interpolate {
        None
    } else {
        exact::exact_grid(eval, tol, progress)?
    };
    match exact {
        Some(done) if done.1.met => Ok(done),
        Some(done) => {
            let interpolated = interpolated_grid(eval, tol, progress)?;
            Ok(if interpolated.1.bound < done.1.bound {
                interpolated
            } else {
                done
            })
        }
        None => interpolated_grid(eval, tol, progress),
    }
}

/// The interpolant of [`volume_grid_with_progress`] (module doc, "Otherwise, interpolated cells").
fn interpolated_grid(
    eval: &ModelEval,
    tol: f64,
    progress: &Progress,
) -> Result<(UnstructuredGrid, VolumeReport)> {
    let cap = certified_degree_cap(eval.model());
    let found = interpolated_search(eval, tol, progress, SCREENED, true, cap)?;
    // Only a chain above `ALWAYS_CERTIFIED_DEGREE` has an estimate's search that differs: below
    // it the second search would repeat the first.
    let top = composed_degree(eval.model().stages.iter().map(|s| s.degree));
    if found.1.met
        || !found.1.certified
        || cap <= ALWAYS_CERTIFIED_DEGREE
        || top <= u64::from(ALWAYS_CERTIFIED_DEGREE)
    {
        return Ok(found);
    }
    // A chain above `ALWAYS_CERTIFIED_DEGREE` whose certificate does not reach the tolerance
    // (restricting its degree-24 forms to refined cells amplifies rounding past use, so its
    // certified bounds come from unrefined cells): the estimate's search, as before these
    // chains were certified, and the estimate if it says it meets the tolerance (labelled an
    // estimate, with the certified bound beside it).
    let estimated =
        interpolated_search(eval, tol, progress, SCREENED, true, ALWAYS_CERTIFIED_DEGREE)?;
    if !estimated.1.met {
        return Ok(found);
    }
    let (grid, mut report) = estimated;
    report.note = format!(
        "{}; the best certified bound, {:.3e} (degree {}, {} level(s)), did not meet the tolerance",
        report.note, found.1.bound, found.1.degree, found.1.level
    );
    Ok((grid, report))
}

/// [`interpolated_grid`], its candidates screened on the crossed simplices when those are at most
/// `screened` of all ([`SCREENED`]; 0: never, 1: always), and with `stop` a fit stopped at its
/// first bound above the tolerance ([`fit_candidate`]). The same result whatever `screened` and
/// `stop` (test `screened_search_writes_what_the_whole_search_writes`).
fn interpolated_search(
    eval: &ModelEval,
    tol: f64,
    progress: &Progress,
    screened: f64,
    stop: bool,
    cap: u32,
) -> Result<(UnstructuredGrid, VolumeReport)> {
    let model = eval.model();
    let n = model.dim();
    let m = n + 1;
    let ns = model.num_simplices();
    let fields: Vec<CellField> = (0..ns)
        .into_par_iter()
        // Each map built, used and dropped ([`ModelEval::local_map_transient`]): the evaluator's
        // cache would hold every simplex's map at once.
        .map(|s| cell_field(model, &eval.local_map_transient(s), model.simplex(s), cap))
        .collect();
    let certified = !fields.iter().any(|f| matches!(f, CellField::Sampled));
    // Candidates by written size; the first whose bound meets the tolerance wins.
    let mut candidates: Vec<(usize, u32, u32)> = (0..=MAX_LEVEL)
        .flat_map(|k| {
            (2..=MAX_DEGREE).map(move |p| {
                let sub = if n == 2 { 4usize.pow(k) } else { 8usize.pow(k) };
                (sub * multi_index::count(m, p), p, k)
            })
        })
        .collect();
    candidates.sort_unstable();
    let topology = eval.indexed().topology();
    // The screen's simplices: the crossed ones, when they are few enough to pay ([`SCREENED`]).
    let crossed: Vec<usize> = (0..ns)
        .into_par_iter()
        .filter(|&s| eval.patch(s).is_some())
        .collect();
    let screen = (crossed.len() as f64) <= screened * ns as f64;
    let all: Vec<usize> = (0..ns).collect();
    let fit = |(p, k): (u32, u32), parents: &[usize], abort_above: f64, phase: &'static str| {
        fit_candidate(
            eval,
            &fields,
            p,
            k,
            parents,
            tol,
            abort_above,
            progress,
            phase,
        )
    };
    // Best so far: (bound, candidate index, p, k, cells); the smallest bound wins, then the
    // earliest candidate.
    let mut best: Option<(f64, usize, u32, u32, Vec<SubCell>)> = None;
    // Candidates refused by their screen or stopped above the tolerance, with the bound found (a
    // lower bound of their own).
    let mut refused: Vec<(f64, usize)> = Vec::new();
    let mut met = false;
    for (i, &(_, p, k)) in candidates.iter().enumerate() {
        // The written count is not monotonic in the candidates' order (by points per cell): a
        // later candidate may still fit. The first candidate is tried whatever its size.
        let first = best.is_none() && refused.is_empty();
        if written_points(topology, n, p, k) > MAX_CONTROL_POINTS && !first {
            continue;
        }
        if screen {
            let lower = fit((p, k), &crossed, tol, SCREEN_PHASE)?.bound;
            if lower > tol {
                refused.push((lower, i));
                continue;
            }
        }
        match fit((p, k), &all, if stop { tol } else { f64::INFINITY }, PHASE)? {
            Fit {
                bound,
                cells: Some(cells),
            } => {
                if best.as_ref().is_none_or(|b| bound < b.0) {
                    best = Some((bound, i, p, k, cells));
                }
                if bound <= tol {
                    met = true;
                    break;
                }
            }
            Fit { bound, cells: None } => refused.push((bound, i)),
        }
    }
    if !met {
        // None meets the tolerance: the smallest bound of every candidate tried is written, as
        // without the screen. A refused candidate's bound is at least its screen's, so they are
        // fitted whole in the order of their screens only while one could still win.
        refused.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        for (lower, i) in refused {
            if best
                .as_ref()
                .is_some_and(|b| lower > b.0 || (lower == b.0 && i > b.1))
            {
                break;
            }
            let (_, p, k) = candidates[i];
            let Fit { bound, cells } = fit((p, k), &all, f64::INFINITY, PHASE)?;
            let cells = cells.expect("a fit without a stop is whole");
            if best
                .as_ref()
                .is_none_or(|b| bound < b.0 || (bound == b.0 && i < b.1))
            {
                best = Some((bound, i, p, k, cells));
            }
        }
    }
    let (_, _, p, k, cells) = best.expect("at least one candidate");
    let (grid, bound, global) = assemble(model, topology, n, p, k, &cells);
    let sampled_note = if certified {
        "certified: Bernstein bound of (G·D − N_F)/D per cell (F = N_F/D exactly, all stages implicit)".to_string()
    } else {
        format!("ESTIMATED, not certified: largest |G − F| at a dense sample lattice (a parametric stage, a composed degree above {MAX_COMPOSED_DEGREE}, or above {ALWAYS_CERTIFIED_DEGREE} on a model whose exact forms would pass {CERTIFIED_COEFFICIENTS} coefficients, has no exact rational form here)")
    };
    let report = VolumeReport {
        degree: p,
        level: k,
        cells: grid.num_cells(),
        control_points: grid.points.len(),
        bound,
        global_bound: global,
        tolerance: tol,
        certified,
        exact: false,
        met: bound <= tol,
        note: format!(
            "degree-{p} Bézier cells, {k} level(s) of red refinement; max |F_vtk − F| ≤ {bound:.3e} on the cells the level may cross (≤ {global:.3e} everywhere; elsewhere F − c and F_vtk − c are certified to keep one sign) ({sampled_note})"
        ),
    };
    Ok((grid, report))
}

/// A candidate's fit ([`fit_candidate`]).
struct Fit {
    /// With `cells`: the largest bound of the sub-cells the level may cross by their own
    /// coefficients (the number the search compares with the tolerance; assembly can only raise
    /// it). Stopped early: the largest such bound above `abort_above` that was found, a lower
    /// bound of the candidate's own.
    bound: f64,
    /// Every sub-cell, or `None` when the fit stopped at a bound above `abort_above`.
    cells: Option<Vec<SubCell>>,
}

/// Fits candidate `(p, k)` on the sub-cells of `parents` (progress phase `phase`). Once a sub-cell
/// the level may cross has a bound above `abort_above`, the candidate cannot meet that number and
/// the remaining simplices are skipped (`cells: None`): a failed certificate bisects its cell to
/// [`CERTIFY_DEPTH`], so a candidate that fails was the search's most expensive kind of fit
/// (`stratified-3d`, composed degree 24: BENCHMARKS.md, issue 19, session 51). Which sub-cells ran
/// before the stop depends on the threads; the stop itself, and a complete fit, do not.
#[allow(clippy::too_many_arguments)]
fn fit_candidate(
    eval: &ModelEval,
    fields: &[CellField],
    p: u32,
    k: u32,
    parents: &[usize],
    tol: f64,
    abort_above: f64,
    progress: &Progress,
    phase: &'static str,
) -> Result<Fit> {
    let model = eval.model();
    let m = model.dim() + 1;
    let tables = DegreeTables {
        p,
        canonical: multi_index::all(m, p),
        inv: inverse_collocation(m, p)?,
        dense: multi_index::all(m, estimate_lattice_degree(p)),
    };
    let subs = sub_simplices(m - 1, k);
    let counter = progress.phase(phase, parents.len() as u64);
    // The largest bound above `abort_above` found so far, as bits (bounds are non-negative, whose
    // bit patterns order as the numbers do); 0 while none is.
    let failed = AtomicU64::new(0);
    let cells: Vec<SubCell> = parents
        .par_iter()
        .flat_map_iter(|&s| {
            let field = &fields[s];
            let tables = &tables;
            let failed = &failed;
            // Once cancelled or failed, the remaining simplices yield nothing (checked below).
            let live = !counter.is_cancelled() && failed.load(Ordering::Relaxed) == 0;
            if live {
                counter.add(1);
            }
            // Built per simplex and candidate and dropped after its sub-cells (see `fields`).
            let map = eval.local_map_transient(s);
            subs.iter()
                .take_while(move |_| live && failed.load(Ordering::Relaxed) == 0)
                .map(move |c| {
                    let (coeffs, bound, side) =
                        fit_sub(eval, &map, field, s, m, k, c, tables, tol, model.level);
                    let cell = SubCell {
                        parent: s,
                        corners: c.clone(),
                        coeffs,
                        bound,
                        side,
                    };
                    if bound > abort_above && !cell.away(cell.coeffs.iter().copied(), model.level) {
                        failed.fetch_max(bound.to_bits(), Ordering::Relaxed);
                    }
                    cell
                })
        })
        .collect();
    progress.check()?;
    let failed = failed.into_inner();
    if failed != 0 {
        return Ok(Fit {
            bound: f64::from_bits(failed),
            cells: None,
        });
    }
    let bound = cells
        .iter()
        .filter(|c| !c.away(c.coeffs.iter().copied(), model.level))
        .map(|c| c.bound)
        .fold(0.0, f64::max);
    Ok(Fit {
        bound,
        cells: Some(cells),
    })
}

/// Writes the cells with shared control points; returns the grid and the final bound (each
/// cell's own bound plus the largest change its shared coefficients received).
fn assemble(
    model: &Model,
    topology: &Topology,
    n: usize,
    p: u32,
    k: u32,
    cells: &[SubCell],
) -> (UnstructuredGrid, f64, f64) {
    let m = n + 1;
    let local_order = vtk_local_multi_indices(n, p);
    let rank_of: Vec<usize> = local_order.chunks(m).map(multi_index::rank).collect();
    let ctype = if n == 2 {
        cell_type::BEZIER_TRIANGLE
    } else {
        cell_type::BEZIER_TETRAHEDRON
    };
    let denom = f64::from(p) * f64::from(1u32 << k);
    let mut grid = UnstructuredGrid::default();
    let mut values: Vec<f64> = Vec::new();
    let mut index = PointIds::new(model, topology, p << k);
    let mut parents: Vec<i64> = Vec::with_capacity(cells.len());
    let mut bound = 0.0f64;
    let mut global = 0.0f64;
    for cell in cells {
        let ids = model.simplex(cell.parent);
        let mut conn = Vec::with_capacity(rank_of.len());
        let mut delta = 0.0f64;
        for (j, &rank) in local_order.chunks(m).zip(&rank_of) {
            let num = lattice_numerators(&cell.corners, j);
            let slot = index.slot(cell.parent, &num[..m]);
            let own = cell.coeffs[rank];
            let id = match index.get(slot) {
                Some(id) => {
                    delta = delta.max((values[id as usize] - own).abs());
                    id
                }
                None => {
                    let mut pt = [0.0; 3];
                    for i in 0..m {
                        let v = model.vertex(ids[i] as usize);
                        for x in 0..n {
                            pt[x] += f64::from(num[i]) / denom * v[x];
                        }
                    }
                    grid.points.push(pt);
                    values.push(own);
                    let id = (grid.points.len() - 1) as u64;
                    index.set(slot, id);
                    id
                }
            };
            conn.push(id);
        }
        let cell_bound = if delta.is_nan() {
            f64::INFINITY
        } else {
            cell.bound + delta
        };
        global = global.max(cell_bound);
        // The final (shared) coefficients decide whether the level stays out of the cell.
        if !cell.away(conn.iter().map(|&i| values[i as usize]), model.level) {
            bound = bound.max(cell_bound);
        }
        grid.push_cell(ctype, conn);
        parents.push(cell.parent as i64);
    }
    attach_arrays(&mut grid, values, None, parents);
    (grid, bound, global)
}

/// The arrays of every volume grid: point data `F` (the active scalars) and, for rational cells,
/// their weights (the active `RationalWeights`: VTK honours them only so declared); cell data
/// `SourceSimplex` (each cell's top simplex).
fn attach_arrays(
    grid: &mut UnstructuredGrid,
    f: Vec<f64>,
    weights: Option<Vec<f64>>,
    parents: Vec<i64>,
) {
    grid.point_data.push(DataArray {
        name: "F".into(),
        components: 1,
        values: ArrayValues::Float(f),
        attribute: Attribute::Scalars,
    });
    if let Some(w) = weights {
        grid.point_data.push(DataArray {
            name: "RationalWeights".into(),
            components: 1,
            values: ArrayValues::Float(w),
            attribute: Attribute::RationalWeights,
        });
    }
    grid.cell_data.push(DataArray {
        name: "SourceSimplex".into(),
        components: 1,
        values: ArrayValues::Int(parents),
        attribute: Attribute::None,
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use ism_format::IndexedModel;
    use std::collections::HashMap;

    /// The certified bound holds: at random points of every fifth written cell, `|G − F|` (F from
    /// the model evaluator, G the written cell's value at the same parameter, its point mapped
    /// back to `F`'s simplex) is at most the reported bound — for every example, as exact cells
    /// where it takes them and as interpolated ones (the Bernstein certificate), including
    /// rational and monotonic stages; and for every example with its stages made parametric
    /// (each stored map is a diffeomorphism either way), whose exact cells are checked by the
    /// evaluator's Newton inversion of those stages.
    #[test]
    fn written_field_is_within_the_reported_bound() {
        for (name, model) in ism_examples::named::all_examples() {
            let n = model.dim();
            if n != 2 && n != 3 {
                continue;
            }
            let mut parametric = model.clone();
            for stage in &mut parametric.stages {
                stage.direction = Direction::Parametric;
            }
            assert_within_bound(name, model.clone(), true, false);
            assert_within_bound(&format!("{name}, interpolated"), model, true, true);
            assert_within_bound(&format!("{name}, parametric"), parametric, true, false);
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(12))]
        /// The same on shapes and stages no example was written for
        /// ([`ism_examples::ellipsoid_model`]: a random ellipse or ellipsoid under one of four
        /// random stage chains, stored parametric or implicit), for every certified bound; a model
        /// with a parametric stage must not be reported certified. Estimates (a parametric stage,
        /// or a composed degree above [`MAX_COMPOSED_DEGREE`]) are not bounds, and are not
        /// asserted here; what their lattice has been measured to miss is at
        /// [`estimate_lattice_degree`].
        #[test]
        fn random_models_are_within_the_reported_bound(
            three in proptest::bool::ANY,
            centre in proptest::array::uniform3(-0.2f64..0.2),
            radii in proptest::array::uniform3(0.35f64..0.75),
            cells in 2usize..4,
            chain in 0..ism_examples::ELLIPSOID_CHAINS,
            implicit in proptest::bool::ANY,
            seed in 0u64..1_000_000,
            amplitude in 0.1f64..0.8,
        ) {
            let n = if three { 3 } else { 2 };
            // 3D grids of 2 cells a side: where no pair meets the tolerance the interpolant's
            // search fits every pair (the interpolated runs, and the 3D stratified chain, of
            // degree 24, which no exact cell takes). 2D grids twice as fine as drawn.
            let cells = if three { 2 } else { 2 * cells };
            let direction = if implicit {
                ism_format::Direction::Implicit
            } else {
                ism_format::Direction::Parametric
            };
            let model = ism_examples::ellipsoid_model(
                &centre[..n],
                &radii[..n],
                cells,
                (chain, seed, amplitude),
                direction,
            )
            .unwrap();
            let name = format!(
                "{n}D ellipsoid {:?} {:?}, {cells} cells a side, chain {chain}, implicit \
                 {implicit}, seed {seed}, amplitude {amplitude}",
                &centre[..n],
                &radii[..n]
            );
            // Interpolated too where that is certified: a parametric model's estimate search is
            // slow in 3D (20–62 s on 48–162 tetrahedra, session 41).
            if implicit {
                assert_within_bound(&format!("{name}, interpolated"), model.clone(), false, true);
            }
            assert_within_bound(&name, model, false, false);
        }
    }

    /// [`written_field_is_within_the_reported_bound`] for one model: the sampled `|G − F|` within
    /// the reported bound when it is certified (and, with `estimates`, when it is estimated);
    /// `interpolate` as [`VolumeOptions::interpolate`].
    fn assert_within_bound(
        name: &str,
        model: ism_format::Model,
        estimates: bool,
        interpolate: bool,
    ) {
        let parametric = model
            .stages
            .iter()
            .any(|s| s.direction == Direction::Parametric);
        // One direction throughout, of a composed degree an exact cell takes even with weights
        // (`E + 1`): the exact cells are written unless interpolation is asked for.
        let one_direction = model
            .stages
            .windows(2)
            .all(|w| w[0].direction == w[1].direction);
        let exact_expected = !interpolate
            && one_direction
            && model.stages.iter().map(|s| s.degree).product::<u32>() < MAX_EXACT_DEGREE;
        let model = IndexedModel::new(model).unwrap();
        let eval = ModelEval::from_indexed(&model).unwrap();
        let tol = default_field_tolerance(&eval, 1e-3);
        let (grid, report) = volume_grid(
            &eval,
            &VolumeOptions {
                field_tolerance: tol,
                interpolate,
            },
        )
        .unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(report.bound.is_finite(), "{name}: {report:?}");
        let worst = sampled_error(&eval, &grid, report.degree, 5, 4);
        assert!(
            !exact_expected || report.exact,
            "{name}: stages of one direction and a low degree, yet not written exactly: {report:?}"
        );
        assert!(
            !(interpolate && report.exact),
            "{name}: interpolation asked for"
        );
        assert!(
            !(parametric && report.certified && !report.exact),
            "{name}: a parametric stage has no exact rational form, yet certified: {report:?}"
        );
        assert!(report.bound <= report.global_bound, "{name}: {report:?}");
        assert_eq!(report.met, report.bound <= report.tolerance, "{name}");
        if !report.certified && !estimates {
            return;
        }
        // Points are recomputed through the physical coordinates: allow their rounding.
        assert!(
            worst <= report.global_bound * (1.0 + 1e-9) + 1e-12,
            "{name}: sampled {worst:e} above the bound {:e}",
            report.global_bound
        );
    }

    /// The largest `|G − F|` at `per_cell` random parameters of every `step`-th cell of `grid`
    /// (written at `degree`): `G` the cell's value by its own (rational) Bernstein basis, `F`
    /// the model evaluator's at the cell's point mapped back to `F`'s simplex.
    fn sampled_error(
        eval: &ModelEval,
        grid: &UnstructuredGrid,
        degree: u32,
        step: usize,
        per_cell: usize,
    ) -> f64 {
        let ArrayValues::Float(f) = &grid.point_data[0].values else {
            panic!("F is float")
        };
        let ArrayValues::Int(parent) = &grid.cell_data[0].values else {
            panic!("SourceSimplex is int")
        };
        let n = eval.dim();
        let m = n + 1;
        // Weights of rational cells (exact grids only; 1 otherwise).
        let weight = grid
            .point_data
            .iter()
            .find(|a| a.attribute == Attribute::RationalWeights)
            .map(|a| match &a.values {
                ArrayValues::Float(w) => w.clone(),
                ArrayValues::Int(_) => panic!("weights are float"),
            });
        let order = vtk_local_multi_indices(n, degree);
        let mut seed = 12345u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut worst = 0.0f64;
        for c in (0..grid.num_cells()).step_by(step) {
            let start = if c == 0 {
                0
            } else {
                grid.offsets[c - 1] as usize
            };
            let conn = &grid.connectivity[start..grid.offsets[c] as usize];
            let s = parent[c] as usize;
            for _ in 0..per_cell {
                let mut l: Vec<f64> = (0..m).map(|_| rnd() + 1e-3).collect();
                let t: f64 = l.iter().sum();
                l.iter_mut().for_each(|x| *x /= t);
                // The cell's point and value at parameter `l`, by its own (rational) Bernstein
                // basis in VTK's point order: linear geometry has its control points on the
                // lattice, so this is the interpolant's point too.
                let (mut den, mut g, mut p) = (0.0, 0.0, [0.0; 3]);
                for (i, &id) in order.chunks(m).zip(conn) {
                    let id = id as usize;
                    let b = multinomial(i)
                        * i.iter()
                            .zip(&l)
                            .map(|(&e, &x)| x.powi(e as i32))
                            .product::<f64>()
                        * weight.as_ref().map_or(1.0, |w| w[id]);
                    den += b;
                    g += b * f[id];
                    for (px, cx) in p.iter_mut().zip(&grid.points[id]).take(n) {
                        *px += b * cx;
                    }
                }
                g /= den;
                p.iter_mut().for_each(|x| *x /= den);
                let w = eval.barycentric(s, &p);
                let w = ism_geom::stage::project(m, &w);
                worst = worst.max((g - eval.value_at(s, &w)).abs());
            }
        }
        worst
    }

    /// A chain of composed degree 24, every stage implicit (`stratified-3d`: Bézier strata of
    /// degrees 4, 3 and 2) is certified ([`MAX_COMPOSED_DEGREE`]), its near-constant denominator
    /// taken as its floor ([`NEAR_CONSTANT_DENOMINATOR`]), and the bound holds at 500 random
    /// points of every written cell, `F` from the model evaluator (its stages evaluated, not the
    /// composed Bernstein form the certificate uses). Before, the search chose degree 4 by an
    /// estimate of 1.878e-3 against the tolerance 1.886e-3, and such sampling found 1.921e-3.
    /// A model of the chain past [`CERTIFIED_COEFFICIENTS`] keeps the estimate.
    #[test]
    fn degree_24_chain_is_certified_and_within_its_bound_at_dense_samples() {
        let (_, model) = ism_examples::named::all_examples()
            .into_iter()
            .find(|(name, _)| *name == "stratified-3d")
            .expect("the example");
        assert_eq!(
            model.stages.iter().map(|s| s.degree).product::<u32>(),
            MAX_COMPOSED_DEGREE
        );
        let model = IndexedModel::new(model).unwrap();
        let eval = ModelEval::from_indexed(&model).unwrap();
        let tol = default_field_tolerance(&eval, 1e-3);
        let (grid, report) = volume_grid(
            &eval,
            &VolumeOptions {
                field_tolerance: tol,
                interpolate: false,
            },
        )
        .unwrap();
        assert!(
            report.certified && !report.exact && report.met,
            "{report:?}"
        );
        assert_eq!(certified_degree_cap(eval.model()), MAX_COMPOSED_DEGREE);
        // A larger model of the chain (3,072 tetrahedra: 9.0 M coefficients per form) is over
        // the budget and keeps the estimate.
        let large = ism_examples::large_stratified_model(6 * 8 * 8 * 8);
        assert_eq!(certified_degree_cap(&large), ALWAYS_CERTIFIED_DEGREE);
        let worst = sampled_error(&eval, &grid, report.degree, 1, 500);
        assert!(
            worst > 0.0 && worst <= report.global_bound,
            "sampled {worst:e} against the bound {:e}",
            report.global_bound
        );
    }

    /// [`restricted`]'s error bound holds: `stratified-3d`'s degree-24 forms (and degree-12 ones,
    /// their products with the first stage dropped) restricted to every sub-cell of one and two
    /// levels of red refinement, by vertex replacement, are within the stated error of the
    /// restriction by the blossom at the sub-cell's own vertices (convex combinations only: off by
    /// at most `d · γ_m · max |coef|`, added to the stated error). The corner children amplify
    /// nothing; the interior ones do, and at degree 24 and two levels past any use.
    #[test]
    fn restriction_errors_bound_the_replacements_rounding() {
        let (_, model) = ism_examples::named::all_examples()
            .into_iter()
            .find(|(name, _)| *name == "stratified-3d")
            .expect("the example");
        let eval = ModelEval::new(&model).unwrap();
        let s = (0..model.num_simplices())
            .find(|&s| eval.patch(s).is_some())
            .expect("a crossed simplex");
        let m = model.dim() + 1;
        let map = eval.local_map(s);
        let mut x = coordinates(m);
        let mut forms = Vec::new();
        for (i, stage) in map.stages().iter().enumerate() {
            x = apply_stage(stage, &x);
            if i >= 1 {
                forms.push(sum(x.iter().cloned()).unwrap());
                forms.push(x[0].clone());
            }
        }
        assert_eq!(forms.last().unwrap().degree(), 24);
        let (mut amplified, mut useless) = (0, 0);
        for k in [1, 2] {
            for corners in sub_simplices(m - 1, k) {
                let verts: Vec<Vec<f64>> = corners
                    .iter()
                    .map(|c| to_bary(c, f64::from(1u32 << k), m)[..m].to_vec())
                    .collect();
                let plan = Restriction::new(&verts);
                for poly in &forms {
                    let d = poly.degree();
                    let (ours, err) = restricted(poly, &verts);
                    let reference = poly.restrict_to_face(&verts);
                    let magnitude = poly.coeffs().iter().map(|c| c.abs()).fold(0.0, f64::max);
                    let gamma = m as f64 * f64::EPSILON / (1.0 - m as f64 * f64::EPSILON);
                    let reference_err = f64::from(d) * gamma * magnitude;
                    let diff = ours
                        .coeffs()
                        .iter()
                        .zip(reference.coeffs())
                        .map(|(a, b)| (a - b).abs())
                        .fold(0.0, f64::max);
                    assert!(
                        diff <= err + reference_err,
                        "k {k}, degree {d}, {corners:?}: {diff:e} > {err:e}"
                    );
                    let a = plan.as_ref().map_or(1.0, |p| p.amplification(d));
                    amplified += usize::from(a > 1.0);
                    useless += usize::from(err > magnitude);
                }
            }
        }
        assert!(amplified > 0 && useless > 0, "{amplified} {useless}");
        // Corner children of one level replace by convex combinations.
        let corner = &sub_simplices(m - 1, 1)[0];
        let verts: Vec<Vec<f64>> = corner
            .iter()
            .map(|c| to_bary(c, 2.0, m)[..m].to_vec())
            .collect();
        assert_eq!(Restriction::new(&verts).unwrap().amplification(24), 1.0);
    }

    /// Weights over many orders of magnitude (rational-degree5's raised to the 60th power, from
    /// 6e-19 to 1e18 — still a diffeomorphism, Thm. 6.4) make the exact cells' rounding bound
    /// useless (it read 4.8e21): then the interpolant is tried too and the smaller bound is the
    /// one written and reported. With the weights squared the exact cells meet the tolerance
    /// and are kept.
    #[test]
    fn exact_cells_give_way_to_a_smaller_interpolant_bound() {
        let (_, base) = ism_examples::named::all_examples()
            .into_iter()
            .find(|(name, _)| *name == "rational-degree5")
            .expect("the example");
        for (power, exact_kept) in [(2, true), (60, false)] {
            let mut model = base.clone();
            for r in 0..model.stages[0].faces.len() {
                for w in model.stages[0].faces.record_mut(r).weights.iter_mut() {
                    *w = w.powi(power);
                }
            }
            let model = IndexedModel::new(model).unwrap();
            let eval = ModelEval::from_indexed(&model).unwrap();
            let field_tolerance = default_field_tolerance(&eval, 1e-3);
            let grid = |interpolate| {
                volume_grid(
                    &eval,
                    &VolumeOptions {
                        field_tolerance,
                        interpolate,
                    },
                )
                .unwrap()
                .1
            };
            let (chosen, interpolated) = (grid(false), grid(true));
            assert_eq!(chosen.exact, exact_kept, "power {power}: {chosen:?}");
            assert_eq!(chosen.met, exact_kept, "power {power}: {chosen:?}");
            assert!(chosen.bound <= interpolated.bound, "power {power}");
            if !exact_kept {
                assert_eq!(chosen, interpolated, "power {power}");
            }
        }
    }

    /// Every 2D and 3D example (the dimensions the volume export writes), indexed.
    fn indexed_examples() -> Vec<(&'static str, Model, IndexedModel)> {
        ism_examples::named::all_examples()
            .into_iter()
            .filter(|(_, model)| matches!(model.dim(), 2 | 3))
            .map(|(name, model)| (name, model.clone(), IndexedModel::new(model).unwrap()))
            .collect()
    }

    /// [`written_points`] (from the face counts) is the number of points [`assemble`] writes
    /// (deduplicated by their [`PointIds`] slots, which `point_slots_are_the_points_of_the_complex`
    /// checks against their exact keys) for every example, 2D and 3D, at every degree unrefined
    /// and the lower ones after one and two levels; and it saturates instead of wrapping.
    #[test]
    fn written_points_count_the_assembled_grid() {
        for (name, model, indexed) in indexed_examples() {
            let n = model.dim();
            let m = n + 1;
            // Every degree unrefined; fewer refined (debug-build time: the grids grow as 8^k).
            for (k, top) in [(0, MAX_DEGREE), (1, 4), (2, 2)] {
                let subs = sub_simplices(n, k);
                for p in 2..=top {
                    let count = multi_index::count(m, p);
                    let cells: Vec<SubCell> = (0..model.num_simplices())
                        .flat_map(|s| {
                            subs.iter().map(move |c| SubCell {
                                parent: s,
                                corners: c.clone(),
                                coeffs: vec![0.0; count],
                                bound: 0.0,
                                side: 0,
                            })
                        })
                        .collect();
                    let (grid, _, _) = assemble(&model, indexed.topology(), n, p, k, &cells);
                    assert_eq!(
                        written_points(indexed.topology(), n, p, k),
                        grid.points.len(),
                        "{name}: p = {p}, k = {k}"
                    );
                }
            }
        }
        let model = ism_examples::named::all_examples()
            .into_iter()
            .find(|(_, m)| m.dim() == 3)
            .unwrap()
            .1;
        let indexed = IndexedModel::new(model).unwrap();
        assert_eq!(
            written_points(indexed.topology(), 3, u32::MAX, 31),
            usize::MAX
        );
    }

    /// The screen and the stopped fits change no result: never screened and never stopped, always
    /// screened (whatever the crossed fraction) and screened by [`SCREENED`], each with fits
    /// stopped at their first bound above the tolerance and (by [`SCREENED`]) without, the
    /// search writes the same grid and report — on
    /// the examples whose interpolant is written (composed degree 24; an implicit stage before a
    /// parametric one), the sphere example's interpolant (all stages implicit: the certified
    /// bound, with cells certified away from the level) and a larger stratified model where
    /// [`SCREENED`] screens, at tolerances
    /// met by a later candidate, met by the first, and (the 2D one) met by none: the refused
    /// candidates are then fitted whole while one could still have the smallest bound.
    #[test]
    fn screened_search_writes_what_the_whole_search_writes() {
        let mut models: Vec<(String, Model, bool)> = ism_examples::named::all_examples()
            .into_iter()
            .filter(|(name, _)| ["stratified-3d", "two-stage", "sphere"].contains(name))
            // Met by none only on the 2D one: the 3D searches through every candidate take
            // minutes in a debug build.
            .map(|(name, m)| (name.to_string(), m, name == "two-stage"))
            .collect();
        models.push((
            "large, 8³ cubes".into(),
            ism_examples::large_stratified_model(6 * 8 * 8 * 8),
            false,
        ));
        assert_eq!(models.len(), 4);
        let mut screened = 0;
        for (name, model, unmet) in models {
            let indexed = IndexedModel::new(model).unwrap();
            let eval = ModelEval::from_indexed(&indexed).unwrap();
            let ns = eval.num_simplices() as f64;
            let crossed = (0..eval.num_simplices())
                .filter(|&s| eval.patch(s).is_some())
                .count() as f64;
            screened += usize::from(crossed <= SCREENED * ns);
            let cap = certified_degree_cap(eval.model());
            let base = default_field_tolerance(&eval, 1e-3);
            let mut tolerances = vec![base, base * 1e3];
            if unmet {
                tolerances.push(base * 1e-9);
            }
            for tol in tolerances {
                let search = |fraction, stop| {
                    let (grid, report) =
                        interpolated_search(&eval, tol, &Progress::none(), fraction, stop, cap)
                            .unwrap();
                    let mut bytes = Vec::new();
                    grid.write_vtu(&mut bytes).unwrap();
                    (bytes, report)
                };
                let whole = search(0.0, false);
                assert!(tol >= base || !whole.1.met, "{name}: met at {tol}");
                for (fraction, stop) in [
                    (0.0, true),
                    (1.0, true),
                    (SCREENED, true),
                    (SCREENED, false),
                ] {
                    let other = search(fraction, stop);
                    let case = format!("{name}, tolerance {tol}, screened {fraction}, stop {stop}");
                    assert_eq!(whole.1, other.1, "{case}");
                    assert!(whole.0 == other.0, "{case}: grids differ");
                }
            }
        }
        assert!(screened >= 1, "no model screened by SCREENED");
    }

    /// Two lattice points get the same [`PointIds`] slot exactly when they are the same point of
    /// the complex — the same global vertices with the same numerators (the key the assembly
    /// hashed before) — on every 2D and 3D example at several degrees, and every slot is within
    /// the table.
    #[test]
    fn point_slots_are_the_points_of_the_complex() {
        for (name, model, indexed) in indexed_examples() {
            let m = model.dim() + 1;
            for q in [1, 2, 3, 5] {
                let mut ids = PointIds::new(&model, indexed.topology(), q);
                let mut by_key: HashMap<Vec<(u32, u32)>, usize> = HashMap::new();
                let mut by_slot: HashMap<usize, Vec<(u32, u32)>> = HashMap::new();
                for s in 0..model.num_simplices() {
                    let vertices = model.simplex(s);
                    for j in multi_index::all(m, q).chunks_exact(m) {
                        let slot = ids.slot(s, j);
                        assert!(slot < ids.ids.len(), "{name}: slot out of range");
                        let mut key: Vec<(u32, u32)> = (0..m)
                            .filter(|&i| j[i] > 0)
                            .map(|i| (vertices[i], j[i]))
                            .collect();
                        key.sort_unstable();
                        assert_eq!(*by_key.entry(key.clone()).or_insert(slot), slot, "{name}");
                        assert_eq!(*by_slot.entry(slot).or_insert(key.clone()), key, "{name}");
                    }
                }
            }
        }
    }

    #[test]
    fn composed_degrees_saturate() {
        assert_eq!(composed_degree([2, 3, 4].into_iter()), 24);
        assert_eq!(composed_degree(std::iter::empty()), 1);
        // 16^16 = 2^64: a wrapping product would read 0 and pass every degree limit.
        assert_eq!(composed_degree(std::iter::repeat_n(16, 16)), u64::MAX);
        assert_eq!(composed_degree(std::iter::repeat_n(2, 70)), u64::MAX);
    }

    #[test]
    fn red_refinement_covers_the_simplex_with_positive_children() {
        for n in [2usize, 3] {
            let kids = sub_simplices(n, 2);
            assert_eq!(kids.len(), if n == 2 { 16 } else { 64 });
            // Volumes (in numerator units) sum to the parent's: |det| of each child = parent / 2^(n·k).
            for k in &kids {
                assert_eq!(orientation(n, k), 1);
            }
            let vol = |c: &SubSimplex| -> i64 {
                let e = |a: usize, i: usize| i64::from(c[a][i]) - i64::from(c[0][i]);
                if n == 2 {
                    (e(1, 1) * e(2, 2) - e(1, 2) * e(2, 1)).abs()
                } else {
                    (e(1, 1) * (e(2, 2) * e(3, 3) - e(2, 3) * e(3, 2))
                        - e(1, 2) * (e(2, 1) * e(3, 3) - e(2, 3) * e(3, 1))
                        + e(1, 3) * (e(2, 1) * e(3, 2) - e(2, 2) * e(3, 1)))
                    .abs()
                }
            };
            let total: i64 = kids.iter().map(vol).sum();
            let parent = 4i64.pow(n as u32); // (2^k)^n with k = 2, unit simplex det 1
            assert_eq!(total, parent);
        }
    }

    /// The rational form is `F`: `N_F / D` at random points equals the evaluator's `F`.
    #[test]
    fn composed_rational_form_matches_the_evaluator() {
        for (name, model) in ism_examples::named::all_examples() {
            let eval = ModelEval::new(&model).unwrap();
            let m = model.dim() + 1;
            for s in (0..model.num_simplices()).step_by(3) {
                if let CellField::Rational { nf, d } = cell_field(
                    &model,
                    eval.local_map(s),
                    model.simplex(s),
                    MAX_COMPOSED_DEGREE,
                ) {
                    let w = [0.1, 0.2, 0.3, 0.4];
                    let mut wb = [0.0; MAX_VARS];
                    let t: f64 = w[..m].iter().sum();
                    for i in 0..m {
                        wb[i] = w[i] / t;
                    }
                    let ours = nf.eval(&wb[..m]) / d.eval(&wb[..m]);
                    let f = eval.value_at(s, &wb);
                    assert!(
                        (ours - f).abs() < 1e-11,
                        "{name} simplex {s}: {ours} vs {f}"
                    );
                }
            }
        }
    }
}
