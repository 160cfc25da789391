//! Points on the shape `O`, uniform by true curved area (length in 2D).
//!
//! 1. Per top simplex σ crossed by the level, the linear patch `θ_σ` (segment, triangle or quad),
//!    cut into regions `r` (16 equal sub-triangles per triangle, 4 sub-segments per segment, and
//!    for many samples their parts where the bounds localise: see `split_regions`; the adaptive
//!    leaves of all-parametric maps), each with its point-space area `A_r` and a certified bound
//!    `B_r ≥ J` of the area element of the parametric map `θ_σ → O ∩ σ` over it
//!    ([`crate::chain`]; [`crate::bound`] for chains mixing implicit and parametric stages, and
//!    per bisection cell for a fused projective pair: [`crate::bound::CellBounds`]).
//! 2. Choose a region with probability `A_r B_r / Σ A B`, `u` uniform on it, solve `w = X⁻¹(u)`
//!    (Newton from a lattice of precomputed preimages, or directly for parametric maps),
//!    `p = W(w)`, and accept with probability `J(u) / B_r`. The accepted points have density
//!    `∝ J`, i.e. uniform with respect to the curved area; `J > B_r` is reported as an error, never
//!    clipped.
//! 3. Every accepted point is checked against `|F(p) − c| ≤ SURFACE_TOLERANCE · |∇F(p)| · L`
//!    (`L` the diagonal of the model's bounding box) and polished by Newton steps along `∇F`
//!    inside its simplex if needed.

use std::cell::OnceCell;
use std::sync::OnceLock;

use ism_format::Model;
use ism_geom::{linalg, Bary, Mat, ModelEval, Solved, MAX_VARS};
use rand::Rng;
use rayon::prelude::*;

use crate::bound::{
    fused_surface_area_element_bound, surface_area_element_bound, CellBounds, MAX_SURFACE_SPLITS,
};
use crate::chain::{
    chain_bound, parametric_leaves, tightening_pays, Budget, ChainBound, TIGHTNESS,
};
use crate::error::{Result, SampleError};

/// Required closeness of a surface sample to `O`, relative to the model size: `|F − c| / |∇F|`
/// (the first-order distance to the level set) at most this times the bounding-box diagonal. The
/// inverse map converges to `1e-12` in barycentric coordinates, which keeps samples two orders
/// inside this; the Newton polish handles the rare point where `|∇F|` is small.
pub const SURFACE_TOLERANCE: f64 = 1e-10;

/// Largest accepted residual `|X(w) − u|∞` of the inverse map. The kernel aims at `1e-12` and may
/// stall just above it on strongly weighted rational stages; a residual of `1e-9` moves the point
/// by `1e-9` of the simplex size in parameter space, which changes the sampled density by a
/// relative `O(1e-9)` (far below what any statistical test resolves), and the surface tolerance
/// below is checked (and polished) on the final point anyway.
pub const INVERSE_RESIDUAL: f64 = 1e-9;

/// Newton steps along `∇F` tried when a sample misses [`SURFACE_TOLERANCE`].
const POLISH_STEPS: usize = 4;

/// How patches are weighted and points accepted.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Weighting {
    /// Uniform by true curved area (the default and the only correct choice).
    #[default]
    CurvedArea,
    /// Uniform by the area of the linear patches, then mapped: NOT uniform on the curved shape.
    /// Kept so that the uniformity tests can show they reject it; do not use it for data.
    LinearArea,
}

/// One patch of the surface table.
#[derive(Clone, Debug)]
pub struct PatchEntry {
    /// Top simplex id.
    pub simplex: u32,
    /// Number of triangles (0 for a segment, 1 or 2).
    triangles: u8,
    /// Point-space area (length in 2D) of the linear patch.
    pub linear_area: f64,
    /// Certified bound of the area element on this simplex (the largest region bound).
    pub bound: f64,
    /// The regions a sample is drawn from, each with its certified bound of the area element:
    /// for implicit chains the `GUESS_LEVEL²` sub-triangles of each triangle (the
    /// `GUESS_LEVEL` sub-segments of a segment) or their parts ([`split_regions`]); for
    /// all-parametric ones the leaves of the adaptive refinement
    /// ([`crate::chain::parametric_leaves`]).
    regions: Vec<RegionEntry>,
    /// `|∇F_lin|` on this simplex.
    linear_gradient: f64,
    /// Whether the regions carry Newton starts (no: no stage, or all-parametric maps).
    guessed: bool,
    /// The patch's triangles (`triangles` of them; the segment's ends in the first for a
    /// segment), which the lattice subdivides.
    tris: [[Bary; 3]; 2],
    /// The lattice points `u` with their preimages `X⁻¹(u)` (`u` itself unless `guessed`),
    /// computed on first use ([`PatchEntry::lattice`]): 15 or 30 solves through every stage per
    /// patch, which the regions' bounds do not need and a table for few samples mostly never
    /// reads (16–33 % of the spec examples' first pass for `--surface 1` when built for every
    /// patch).
    lattice: OnceLock<Vec<(Bary, Bary)>>,
    /// The lattice's preimages one point at a time, for the draws' Newton starts while the whole
    /// lattice is not computed ([`PatchEntry::start`]): a candidate needs the three of its
    /// region's corners, and a table for few samples draws a few candidates from many patches
    /// (filling whole lattices was 19 % of stratified-3d's `--surface 1`). Each point is the
    /// same pure function of `u` as in the whole lattice, so the starts, hence the draws, are
    /// the same bits whichever holds them.
    starts: OnceLock<Box<[OnceLock<Bary>]>>,
    /// Mean exact `J` at the lattice points: an estimate of the curved area per linear area
    /// (implicit and mixed chains only: only their second pass reads it), computed on first use
    /// ([`PatchEntry::sample_mean`]).
    sample_mean: OnceLock<f64>,
    /// The stages of an all-parametric Bézier map as identity plus their moved control points, in
    /// processing order (last stored first); empty when the kernel's dense evaluation is used.
    sparse: Vec<SparseStage>,
}

/// A region of a patch: a triangle (a segment in 2D: the first two corners) of the linear patch.
#[derive(Clone, Debug)]
struct RegionEntry {
    /// Corners, barycentric `u`.
    u: [Bary; 3],
    /// Indices in the patch's lattice of the corners, whose preimages `X⁻¹(u)` start Newton
    /// close to the solution by linear interpolation. Unused unless the patch is `guessed`.
    g: [u16; 3],
    /// Share of the patch's area.
    fraction: f64,
    /// Certified bound of the area element on the region.
    bound: f64,
    /// For a part of a fixed region ([`split_regions`]): the barycentric weights of its corners
    /// in that region, whose lattice corners `g` start its Newton solves.
    part: Option<[[f64; 3]; 3]>,
}

/// Deepest halving of a fixed region of an implicit chain's patch ([`split_regions`]): up to
/// `4^3 = 64` parts.
const REGION_DEPTH: u32 = 3;

/// A region is replaced by its parts only when their bounded area is at most this fraction of
/// its own: where the chain's leaves and the per-stage cells are coarser than the parts, the
/// parts take the same bound, and more slots would only cost memory.
const PARTS_PAY: f64 = 0.9;

/// Subdivision level of the per-patch lattice of precomputed preimages. Linear interpolation on a
/// lattice of spacing `h = 1/4` is off by `O(h²)` times the map's second derivative, so Newton from
/// there needs two or three iterations instead of the five to fifteen a per-stage solve from the
/// identity takes; the table costs `15` inversions per triangle.
pub const GUESS_LEVEL: usize = 4;

/// Position of lattice point `(i, j)` (`i + j ≤ L`, barycentric `((L − i − j)/L, i/L, j/L)`) in
/// a triangle's part of the guess list (a segment stores point `i` at `i`).
fn lattice_index(i: usize, j: usize) -> usize {
    i * (2 * GUESS_LEVEL + 3 - i) / 2 + j
}

/// Number of lattice points per triangle.
const LATTICE_POINTS: usize = (GUESS_LEVEL + 1) * (GUESS_LEVEL + 2) / 2;

/// Everything the surface sampler precomputes: one entry per crossed simplex and the selection
/// table (Walker's alias method over the regions' weights `A_r B_r`).
#[derive(Clone, Debug)]
pub struct SurfaceTable {
    /// The patches, in simplex order.
    pub patches: Vec<PatchEntry>,
    /// The selection entries (one per region of positive weight), each with its alias pair and
    /// what a draw from it reads ([`Slot`]).
    slots: Vec<Slot>,
    /// What a draw reads of an all-parametric patch of sparse Bézier stages, in one record per
    /// patch ([`FastPatch`]); the other patches are drawn through [`PatchEntry`] and the kernel.
    fast: Vec<FastPatch>,
    /// The moved control points of the [`FastPatch`]es' stages, back to back.
    terms: Vec<Term>,
    /// `Σ A_σ B_σ`: an upper bound of the curved area of `O`.
    pub bounded_area: f64,
    /// `Σ A_σ`: the area of the linear isocomplex.
    pub linear_area: f64,
    scale: f64,
    weighting: Weighting,
    /// Whether [`SurfaceTable::draw_each`] picks [`PICK_AHEAD`] candidates at a time: set when
    /// every patch has a [`FastPatch`] record (fitted models), where a candidate is cheap enough
    /// that its cache misses dominate. Other tables (implicit chains: Newton per candidate) keep
    /// one pick per candidate, hence their output for a seed.
    pick_ahead: bool,
}

/// Candidates picked at a time by [`SurfaceTable::draw_each`] on tables with
/// `pick_ahead`. The slots, patch records and terms are read at random from tables of
/// megabytes; one candidate at a time, each of its first reads stalls on memory in turn. Picking
/// several first issues their reads back to back, so the misses overlap.
const PICK_AHEAD: usize = 8;

/// Slots picked ahead by [`SurfaceTable::pick_ahead`], used in order.
#[derive(Default)]
struct Ahead {
    slots: [u32; PICK_AHEAD],
    next: usize,
}

/// One selection entry of the alias table with what a draw from it reads, in one record (two
/// cache lines): the table is read at random, so the slot's alias pair, the region's corners and
/// bound, and where its patch is are read together instead of from four arrays. Laid out in
/// declaration order: the corners fill the first line and half the second.
#[derive(Clone, Debug)]
#[repr(C, align(64))]
struct Slot {
    /// Corners of the region (barycentric `u`; a segment uses the first two).
    u: [Bary; 3],
    /// A uniform slot `i` keeps `i` with probability `threshold`, else takes `alias`
    /// ([`alias_table`]).
    threshold: f64,
    /// Certified bound of the area element on the region.
    bound: f64,
    alias: u32,
    /// Index of the patch in [`SurfaceTable::patches`] and of the region in it.
    patch: u32,
    region: u32,
    /// Index in [`SurfaceTable::fast`], or `u32::MAX` when the patch has no fast record.
    fast: u32,
}

/// A moved control point of a [`SparseStage`]: exponents `I` and `c_I`.
type Term = ([u8; MAX_VARS], Bary);

/// Most stages a [`FastPatch`] holds (fitted models have three).
const FAST_STAGES: usize = 4;

/// What drawing from an all-parametric patch of sparse Bézier stages reads, copied out of the
/// model and the evaluator so that a candidate reads one record (and its stages' terms, back to
/// back) instead of chasing the simplex's vertex ids, values, inverse edge matrix and local map.
/// The arithmetic is the evaluator's, in the same order, so the results are the same bits.
/// Four cache lines exactly (laid out in declaration order, aligned to a line), so that
/// [`SurfaceTable::pick_ahead`] can touch each of them.
#[derive(Clone, Debug)]
#[repr(C, align(64))]
struct FastPatch {
    simplex: u32,
    /// Number of triangles (0 for a segment).
    triangles: u8,
    stages: u8,
    /// Where the first stage's terms start in [`SurfaceTable::terms`]; the stages' terms follow
    /// each other, in processing order.
    first: u32,
    /// End of each stage's terms, counted from `first` (what fits a `u16`: see
    /// [`FastPatch::new`]).
    ends: [u16; FAST_STAGES],
    degrees: [u8; FAST_STAGES],
    linear_gradient: f64,
    /// `f_{k+1} − f_0` (vertex values in the simplex's order), as
    /// [`ModelEval::gradient_from_jacobian`] computes them.
    df: [f64; 3],
    /// The simplex's inverse edge matrix, as the evaluator stores it.
    inv: [f64; 9],
    /// Vertex values and positions of the simplex (an accepted sample's `F` and point).
    values: [f64; MAX_VARS],
    vertices: [[f64; 3]; MAX_VARS],
}

const _: () = assert!(std::mem::size_of::<FastPatch>() == 4 * 64);

/// Diagonal of the model's bounding box (1 for an empty model).
pub(crate) fn model_scale(model: &Model) -> f64 {
    let n = model.dim();
    if model.vertices.is_empty() || n == 0 {
        return 1.0;
    }
    let mut d2 = 0.0;
    for x in 0..n {
        let coords = model.vertices.iter().skip(x).step_by(n);
        let (lo, hi) = coords.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
        d2 += (hi - lo).powi(2);
    }
    if d2 > 0.0 {
        d2.sqrt()
    } else {
        1.0
    }
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

fn sub3(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross_norm(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    norm(&[
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ])
}

/// Refinement budget per patch in the first pass (see [`crate::chain`]).
const FIRST_SPLITS: usize = 48;
/// Most of [`FIRST_SPLITS`] an implicit chain spends while some leaf's determinant is not yet
/// certified: none. A root that neither the stored chain, its floors nor the fused map certifies
/// ([`chain_bound`]) is left to the per-stage bound in the first pass, and to the second pass's
/// whole budget if it then wastes the most. On the torus example every such root was still not
/// certified after all 48 splits (16 patches, 1 to 12 uncertified leaves each), and the wide
/// `u`-boxes of those leaves meet every region, which therefore took the per-stage bound anyway:
/// the splits were a quarter of the patches' work in a one-sample run and changed no region's
/// bound. Measured (whole `ism sample --surface N -j 1`, CPU, session 38): 12 splits against 48
/// gave torus example N = 1 / 10² / 10³ / 10⁴ 0.90 / 0.97 / 0.96 / 0.98× (best of 9); none against
/// 12 gave 0.97× at N = 1 and the same bytes at N = 1 to 10⁴ on the torus, sphere, stratified-3d,
/// two-stage and rational-degree5 examples and the 1 M-tet model (its N = 10⁵ 0.88×; best of 3
/// under load).
const FIRST_UNCERTIFIED: usize = 0;
/// Refinement budget of the second pass.
const SECOND_SPLITS: usize = 2048;
/// Most bisections of one all-parametric patch (the leaves are the regions drawn from): a cap
/// only; refinement stops at [`LEAF_EXCESS`] first.
const LEAF_SPLITS: usize = 1024;
/// An all-parametric patch's leaf is bisected while the sampling mass its bound wastes,
/// `A_leaf (B_leaf − J's size there)`, exceeds this fraction of the mean crossed patch's linear
/// area (worst leaf first): one threshold for the whole table, so refinement goes where the bounds
/// are loose instead of a fixed budget per patch plus a second pass for the worst ones. Measured
/// (session 11, `--surface 1 -j 1`, CPU, best of 3 alternating): 24 splits per patch plus the
/// second pass gave fitted sphere 0.56 s and `Σ A·B` 4.24× the curved area, fitted torus 1.95 s
/// and 5.31×; this threshold gives 0.38 s and 3.99×, 1.80 s and 4.27×.
const LEAF_EXCESS: f64 = 1.0 / 3.0;
/// With an expected number of samples `N`, a leaf is bisected while the sampling mass its bound
/// wastes exceeds this times the total linear area over `N`. A bisection saves about half its
/// leaf's waste, i.e. that share of `N` candidates, so this is about twice the cost of a
/// bisection in candidates. Scanned (session 12, whole runs, `-j 1`, CPU, load 8): 5 / 20 / 80
/// against the fixed threshold gave, at `N = 10⁶`, fitted sphere 4.72 / 3.25 / 2.58 vs 2.51 s and
/// fitted torus 6.61 / 4.17 / 4.78 vs 5.70 s; at `N = 2·10⁵` 1.30 / 0.94 / 0.72 vs 0.82 and
/// 2.59 / 1.95 / 2.11 vs 2.19.
const SPLIT_PAYS: f64 = 40.0;
/// An implicit chain's refinement ([`crate::chain::chain_bound`]: up to [`FIRST_SPLITS`]
/// bisections, each restricting every polynomial of the first stage and bounding the whole chain)
/// goes past the splits that make its bound finite only when the patch's bound then wastes more
/// than this times the all-parametric leaves' threshold (`A_patch (B − J_max)` against
/// `leaf_excess`); likewise the per-stage bound, and the second pass ([`SECOND_SPLITS`]) only
/// for a patch whose excess exceeds it times the budgets' ratio. Without it every patch spent
/// its budget whatever the samples asked: on the 1 M-tet model `ism sample --surface 1` cost
/// 29.3 CPU-s (8.1 with the chain split only until its bound is finite, 3.6 once an uncertified
/// root retries with the later stages' determinant floors), the sphere example 0.74 (now
/// 0.025). Scanned (whole `ism
/// sample --surface N -j 1`, CPU, session 34): 0.05 / 0.2 / 1 / 5 / 20 — 1 was never the
/// slowest beyond noise, from N = 10⁴ (sphere example 0.88 s at 0.2, 0.29 s at 1) to 10⁶
/// (within 6 % of the best on the sphere, stratified-3d and 1 M-tet models; 20 lost 4–15 %
/// there: too few splits). BENCHMARKS.md (issue 19, session 34).
const CHAIN_EXCESS_SHARE: f64 = 1.0;
/// A patch gets the second pass when its excess is above this share of the whole bounded area.
const REFINE_SHARE: f64 = 0.005;
/// At most this many patches get the second pass per round (bounds the table's cost).
const REFINE_COUNT: usize = 24;
/// Rounds of the second pass at most: each picks the worst of what the last left. One round was
/// all before session 36: on the torus example (bounded areas of its three-stage chains up to
/// 10⁵ × the curved area's estimate on some patches) the first round's threshold, relative to
/// the whole bounded area, left the next-worst patches unrefined, and they then held most of the
/// table. Scanned (whole `ism sample torus.ismb --surface N -j 1`, CPU, best of 2): 4 rounds
/// against 1, N = 10² / 10³ / 3·10³ / 10⁴ / 3·10⁴: 0.99 / 0.99 / 0.83 / 0.58 / 0.42×; 8 rounds
/// gave the same. Since the projective pair is bounded fused ([`fused_surface_area_element_bound`],
/// session 48) the first round leaves far less there: the rounds' table bounds the same area as one
/// round's up to N = 10⁴ and 0.84× at 10⁵ and 10⁶ (sphere example: the same up to 10⁵, 0.93× at
/// 10⁶).
const REFINE_ROUNDS: usize = 4;
/// The later rounds' threshold over the first's: a patch chosen later wastes less, and its
/// refinement (the same budget) saves fewer candidates. Scanned with 4 rounds on the torus example
/// (as above, CPU over one round's): factor 1 / 4 / 16 at N = 10² 1.12 / 1.00 / 0.99, at 3·10³
/// 1.08 / 0.90 / 0.83, at 10⁴ 0.63 / 0.58 / 0.58; 16 / 64 at 10³ 0.99 / 1.02, at 3·10⁴ 0.42 /
/// 0.49. The sphere and stratified-3d examples at 3·10³: the same CPU with each.
const LATER_ROUNDS_FACTOR: f64 = 16.0;

/// Point-space area (length in 2D) of a linear patch, as [`build_patch`] computes it.
fn patch_area(eval: &ModelEval, s: usize, patch: &ism_geom::Patch) -> f64 {
    let pts: Vec<[f64; 3]> = patch.corners.iter().map(|c| eval.point(s, &c.u)).collect();
    if eval.dim() == 2 {
        return norm(&sub3(&pts[1], &pts[0]));
    }
    let a0 = 0.5 * cross_norm(&sub3(&pts[1], &pts[0]), &sub3(&pts[2], &pts[0]));
    if pts.len() == 4 {
        a0 + 0.5 * cross_norm(&sub3(&pts[2], &pts[0]), &sub3(&pts[3], &pts[0]))
    } else {
        a0
    }
}

/// One patch of the table: linear patch, lattice of preimages, certified region bounds.
fn build_patch(
    eval: &ModelEval,
    s: usize,
    patch: &ism_geom::Patch,
    max_splits: usize,
    (leaf_excess, depth): (f64, u32),
) -> Result<PatchEntry> {
    let model = eval.model();
    let n = model.dim();

    let ids = model.simplex(s);
    let e = ism_geom::model::edge_matrix(model, ids);
    let inv = eval.inv_edges(s);
    let f0 = model.values[ids[0] as usize];
    let mut g = [0.0; 3];
    for (x, gx) in g.iter_mut().enumerate().take(n) {
        *gx = (0..n)
            .map(|l| (model.values[ids[l + 1] as usize] - f0) * inv[l][x])
            .sum();
    }
    let corners: Vec<Bary> = patch.corners.iter().map(|c| c.u).collect();
    let pts: Vec<[f64; 3]> = corners.iter().map(|u| eval.point(s, u)).collect();
    let (tris, count, first_fraction, area) = if n == 2 {
        let len = norm(&sub3(&pts[1], &pts[0]));
        ([[corners[0], corners[1], corners[1]]; 2], 0u8, 1.0, len)
    } else {
        let a0 = 0.5 * cross_norm(&sub3(&pts[1], &pts[0]), &sub3(&pts[2], &pts[0]));
        if corners.len() == 4 {
            let a1 = 0.5 * cross_norm(&sub3(&pts[2], &pts[0]), &sub3(&pts[3], &pts[0]));
            let t = [
                [corners[0], corners[1], corners[2]],
                [corners[0], corners[2], corners[3]],
            ];
            (t, 2u8, a0 / (a0 + a1), a0 + a1)
        } else {
            let t = [corners[0], corners[1], corners[2]];
            ([t, t], 1u8, 1.0, a0)
        }
    };
    let map = eval.local_map(s);
    if map.stages().is_empty() {
        return Ok(stage_free_patch(s, &tris, count, first_fraction, area, &g));
    }
    let values: Vec<f64> = ids.iter().map(|&v| model.values[v as usize]).collect();
    let parametric = map
        .stages()
        .iter()
        .all(|st| st.direction() == ism_format::Direction::Parametric);
    // All-parametric maps are evaluated directly ([`ism_geom::LocalMap::param_solve`]): their
    // lattice needs no preimages (an all-parametric `inverse` also pays a Newton solve per stage
    // for its residual). Computed only when read: by the samples below, or by the first draw.
    let lattice = OnceLock::new();
    let uncertified = |(stage, reason)| SampleError::Uncertified {
        simplex: s,
        stage,
        reason,
    };
    // Exact J at the lattice preimages (points of the shape): where the certified
    // refinement should come close. Computed only if a decision needs them.
    let lin = norm(&g[..n]);
    let compute_samples = || -> Vec<([f64; 4], f64)> {
        lattice_samples(
            eval,
            s,
            lattice.get_or_init(|| lattice_guesses(map, &tris, count, !parametric)),
            lin,
        )
    };
    // Shares of the patch's area per root: the triangles, or the segment.
    let root_shares: Vec<f64> = match count {
        0 | 1 => vec![1.0],
        _ => vec![first_fraction, 1.0 - first_fraction],
    };
    let roots: Vec<(Vec<Bary>, f64)> = root_shares
        .iter()
        .enumerate()
        .map(|(t, &share)| (tris[t][..if count == 0 { 2 } else { 3 }].to_vec(), share))
        .collect();
    let leaves = parametric_leaves(
        map,
        &inv,
        &values,
        model.level,
        &roots,
        // Computed only if a leaf is worth splitting (the refinement's threshold).
        &compute_samples,
        // Relative to this patch: leaf masses are shares of its area.
        (LEAF_SPLITS, leaf_excess / area),
    );
    // Mean exact J at the lattice: only the second pass of implicit chains reads it.
    let sample_mean = OnceLock::new();
    let regions: Vec<RegionEntry> = match leaves {
        // All-parametric maps: the leaves of the adaptive refinement, bounded directly (exact
        // restriction), are the regions.
        Some(leaves) => leaves
            .map_err(|reason| uncertified((map.stages().len().saturating_sub(1), reason)))?
            .into_iter()
            .map(|leaf| {
                let mut u = [[0.0; MAX_VARS]; 3];
                for (k, c) in leaf.corners.iter().enumerate() {
                    u[k] = *c;
                }
                RegionEntry {
                    u,
                    g: [0; 3],
                    fraction: root_shares[leaf.root] * leaf.fraction,
                    bound: leaf.bound,
                    part: None,
                }
            })
            .collect(),
        None => {
            let taken = OnceCell::new();
            let samples = || -> &[([f64; 4], f64)] { taken.get_or_init(compute_samples) };
            let bounder = implicit_region_bounds(ImplicitInputs {
                map,
                edges: &e,
                inv: &inv,
                values: &values,
                level: model.level,
                samples: &samples,
                max_splits,
                min_excess: if area > 0.0 {
                    CHAIN_EXCESS_SHARE * leaf_excess / area
                } else {
                    f64::INFINITY
                },
            })
            .map_err(uncertified)?;
            if let Some(samples) = taken.get() {
                let _ = sample_mean.set(mean_j(samples));
            }
            let bounds: Vec<f64> = regions(&tris, count)
                .iter()
                .map(|(lo, hi)| bounder.over(lo, hi))
                .collect();
            split_regions(
                lattice_regions(&tris, count, first_fraction, &bounds),
                &bounder,
                (count, depth),
                // A part's share of the table's candidates pays for the few look-ups it costs
                // once its bounded area is above the table-wide `total_area / expected`
                // (`leaf_excess / SPLIT_PAYS`), in shares of this patch.
                if area > 0.0 {
                    leaf_excess / SPLIT_PAYS / area
                } else {
                    f64::INFINITY
                },
            )
        }
    };
    let bound = regions.iter().map(|r| r.bound).fold(0.0, f64::max);
    if !bound.is_finite() {
        return Err(uncertified((
            map.stages().len().saturating_sub(1),
            "area element not bounded on the shape".into(),
        )));
    }
    Ok(PatchEntry {
        simplex: s as u32,
        triangles: count,
        linear_area: area,
        bound,
        regions,
        linear_gradient: norm(&g),
        // Newton starts: not needed without stages or with all-parametric maps (direct
        // evaluation).
        guessed: !parametric && !map.stages().is_empty(),
        tris,
        lattice,
        starts: OnceLock::new(),
        sample_mean,
        sparse: if parametric {
            map.stages()
                .iter()
                .rev()
                .map(SparseStage::new)
                .collect::<Option<Vec<_>>>()
                .unwrap_or_default()
        } else {
            Vec::new()
        },
    })
}

/// The patch of a simplex whose local map has no stage (fitted models leave the simplices no
/// control point moves without one): the shape there is the linear patch itself, `DX = I` and
/// `F = F_lin`, so `J = |∇F| / (|∇F_lin| det DX) = 1` exactly and `1` is its certified bound
/// on the whole patch. The regions are the patch's triangles (its segment in 2D): every
/// candidate is accepted, so splitting them further would only lengthen the selection table.
fn stage_free_patch(
    s: usize,
    tris: &[[Bary; 3]; 2],
    count: u8,
    first_fraction: f64,
    area: f64,
    gradient: &[f64; 3],
) -> PatchEntry {
    let regions = (0..usize::from(count.max(1)))
        .map(|t| RegionEntry {
            u: tris[t],
            g: [0; 3],
            fraction: if t == 0 {
                first_fraction
            } else {
                1.0 - first_fraction
            },
            bound: 1.0,
            part: None,
        })
        .collect();
    PatchEntry {
        simplex: s as u32,
        triangles: count,
        linear_area: area,
        bound: 1.0,
        regions,
        linear_gradient: norm(gradient),
        guessed: false,
        tris: *tris,
        lattice: OnceLock::new(),
        starts: OnceLock::new(),
        sample_mean: OnceLock::from(1.0),
        sparse: Vec::new(),
    }
}

/// Inputs of [`implicit_region_bounds`].
struct ImplicitInputs<'a> {
    map: &'a ism_geom::LocalMap,
    edges: &'a Mat,
    inv: &'a Mat,
    values: &'a [f64],
    level: f64,
    /// Points of the shape as `(u, exact J)`, taken on first call: only a decision they can
    /// change asks for them.
    samples: &'a dyn Fn() -> &'a [([f64; 4], f64)],
    max_splits: usize,
    /// The chain bound's excess over the samples (units of `J`), once finite, below which
    /// neither the chain nor the per-stage bound is tightened ([`CHAIN_EXCESS_SHARE`]).
    min_excess: f64,
}

/// The bounds an implicit chain's patch takes its regions' from ([`RegionBounder`]): the chain
/// bound's leaves, with the per-stage bound where the chain has none or is not tight within its
/// budget (both are certified, so their minimum is).
fn implicit_region_bounds(
    input: ImplicitInputs<'_>,
) -> std::result::Result<RegionBounder, (usize, String)> {
    let ImplicitInputs {
        map,
        edges,
        inv,
        values,
        level,
        samples,
        max_splits,
        min_excess,
    } = input;
    let n = map.vars() - 1;
    let best_sample = || samples().iter().map(|s| s.1).fold(0.0, f64::max);
    // The first pass gives certification none of its budget (see `FIRST_UNCERTIFIED`); the
    // second pass, for the patches that waste the most, all of it.
    let uncertified = if max_splits <= FIRST_SPLITS {
        FIRST_UNCERTIFIED
    } else {
        max_splits
    };
    let budget = Budget {
        splits: max_splits,
        uncertified,
        min_excess,
    };
    let chain_with = |budget| match chain_bound(map, inv, values, level, samples, budget) {
        Some(Ok(c)) => Some(c),
        _ => None,
    };
    let mut chain = chain_with(budget);
    // The per-stage bound is certified too; it is needed where the chain's is
    // missing, infinite, or not tight within its budget.
    let per_stage = match &chain {
        // A finite chain bound whose refinement would not pay: the per-stage bound (its own
        // bisection, as costly) would not either. The samples' `J` is not negative, so a bound
        // whose excess over 0 does not pay needs no samples to say so.
        Some(c) if c.top().is_finite() && !tightening_pays(c.top(), 0.0, min_excess) => Ok(None),
        Some(c) if c.top() * TIGHTNESS <= best_sample() => Ok(None),
        Some(c) if c.top().is_finite() && !tightening_pays(c.top(), best_sample(), min_excess) => {
            Ok(None)
        }
        // A projective stage fused into the next is bounded as one map near the shape (far
        // tighter than the pair's factors apart, and cheaper), refined only while that pays, as
        // the chain is; the stored map's bound otherwise. Measured (whole `ism sample
        // torus.ismb --surface N -j 1`, CPU, session 48): refined to its cap of
        // `MAX_SURFACE_SPLITS` whatever `N`, this bound gave a mean over seeds 0–39 of 16.9 µs
        // per simplex at N = 1 (32 splits: 13.8, but N = 30 / 100 1.13 / 1.12× the CPU); with
        // the test 13.2 µs, and 0.89 / 0.91 / 0.95 / 0.96 / 0.97× the CPU at N = 10 / 30 / 100
        // / 300 / 10⁴ (sphere example 10⁴ 0.92×; torus 10⁵ 1.00×).
        _ => match fused_surface_area_element_bound(
            map,
            edges,
            values,
            level,
            MAX_SURFACE_SPLITS,
            min_excess,
        ) {
            Some(b) => Ok(Some(b)),
            None => surface_area_element_bound(map, edges, values, level)
                .map(|b| Some(CellBounds::whole(b, n + 1))),
        },
    };
    let per_stage = match per_stage {
        Ok(b) => b,
        Err(err) => {
            // The cap on certification saves splits; it never makes a patch unsampleable: with
            // the per-stage bound failed, the chain gets its whole budget, as without the cap.
            if budget.uncertified < budget.splits
                && chain.as_ref().is_some_and(|c| !c.top().is_finite())
            {
                chain = chain_with(Budget::new(max_splits, min_excess));
            }
            if chain.is_none() {
                return Err(err);
            }
            None
        }
    };
    Ok(RegionBounder {
        chain,
        per_stage,
        vars: n + 1,
    })
}

/// The certified bounds an implicit chain's patch has (the chain bound's leaves, the per-stage
/// bound's cells), asked for any box of `u`: the fixed regions' and their parts'
/// ([`split_regions`]).
struct RegionBounder {
    chain: Option<ChainBound>,
    /// `None`: no per-stage bound (infinite).
    per_stage: Option<CellBounds>,
    vars: usize,
}

impl RegionBounder {
    /// The least of the two bounds over the points whose `u` lies in `[lo, hi]`.
    fn over(&self, lo: &[f64], hi: &[f64]) -> f64 {
        let (lo, hi) = (&lo[..self.vars], &hi[..self.vars]);
        let stage = self
            .per_stage
            .as_ref()
            .map_or(f64::INFINITY, |b| b.over(lo, hi));
        match &self.chain {
            // Every region holds points of the shape, so some leaf meets it; a
            // zero would mean a rounding gap between boxes: use the whole bound.
            Some(c) => match c.over(lo, hi) {
                b if b > 0.0 => b.min(stage),
                _ => c.top().min(stage),
            },
            None => stage,
        }
    }
}

impl SurfaceTable {
    /// Builds the table (in parallel over simplices).
    ///
    /// # Errors
    /// [`SampleError::EmptySurface`] when no simplex is crossed; [`SampleError::Uncertified`] when a
    /// stage's area-element bound cannot be certified on a crossed simplex.
    pub fn new(eval: &ModelEval, weighting: Weighting) -> Result<SurfaceTable> {
        Self::with_expected_samples(eval, weighting, None)
    }

    /// [`SurfaceTable::new`] for about `expected` samples in all: an all-parametric patch's
    /// leaf is bisected only while the sampling mass its bound wastes exceeds
    /// `SPLIT_PAYS` times the total linear area over `expected`, i.e. while the candidates the
    /// split saves on `expected` samples cost more than the split; an implicit chain is
    /// tightened past its first finite bound only on the same test (`CHAIN_EXCESS_SHARE`). Few
    /// samples get the root bounds alone (the cheapest certified table); many get tighter bounds
    /// than the fixed threshold gives. `None`: the fixed threshold of [`SurfaceTable::new`]. The
    /// table, hence the output for a seed, depends on `expected` but never on the thread count.
    ///
    /// # Errors
    /// As [`SurfaceTable::new`].
    pub fn with_expected_samples(
        eval: &ModelEval,
        weighting: Weighting,
        expected: Option<u64>,
    ) -> Result<SurfaceTable> {
        Self::build(eval, weighting, expected, REFINE_ROUNDS, REGION_DEPTH)
    }

    /// [`SurfaceTable::with_expected_samples`] with at most `rounds` rounds of the second pass and
    /// the fixed regions of implicit chains split at most `depth` times ([`split_regions`]).
    fn build(
        eval: &ModelEval,
        weighting: Weighting,
        expected: Option<u64>,
        rounds: usize,
        depth: u32,
    ) -> Result<SurfaceTable> {
        let model = eval.model();
        let crossed: Vec<(usize, ism_geom::Patch)> = (0..eval.num_simplices())
            .into_par_iter()
            .filter_map(|s| eval.patch(s).map(|p| (s, p)))
            .collect();
        // A serial sum in a fixed order: the threshold, hence the table, is the same whatever
        // the thread count.
        let total_area: f64 = crossed.iter().map(|(s, p)| patch_area(eval, *s, p)).sum();
        let leaf_excess = match expected {
            Some(count) => SPLIT_PAYS * total_area / count.max(1) as f64,
            None => LEAF_EXCESS * total_area / crossed.len().max(1) as f64,
        };
        let mut patches: Vec<PatchEntry> = crossed
            .par_iter()
            .map(|(s, patch)| build_patch(eval, *s, patch, FIRST_SPLITS, (leaf_excess, depth)))
            .collect::<Result<Vec<_>>>()?;
        // Second pass (implicit and mixed chains; all-parametric patches are refined by the
        // table-wide threshold already): the patches whose bounds waste the most (bounded minus
        // sampled curved area) get a larger refinement budget. Chosen from the figures so far in
        // a fixed order, so the table is the same whatever the thread count. In rounds:
        // once the worst are refined the whole bounded area shrinks, and the patches that waste
        // the most of what is left are chosen the same way (each patch at most once).
        let threshold =
            CHAIN_EXCESS_SHARE * leaf_excess * SECOND_SPLITS as f64 / FIRST_SPLITS as f64;
        let mut refined_once = vec![false; patches.len()];
        for round in 0..rounds {
            let total: f64 = patches.iter().map(PatchEntry::bounded_area).sum();
            let threshold = if round > 0 {
                threshold * LATER_ROUNDS_FACTOR
            } else {
                threshold
            };
            let worth = |excess: f64| excess > REFINE_SHARE * total && excess > threshold;
            // The excess needs the lattice's samples; it is never above the bounded area, so a
            // patch whose bounded area is not worth it is out without them.
            let excess: Vec<Option<f64>> = patches
                .par_iter()
                .zip(&refined_once)
                .map(|(p, &once)| {
                    (p.guessed && !once && worth(p.bounded_area())).then(|| p.excess(eval))
                })
                .collect();
            let mut worst: Vec<usize> = (0..patches.len())
                .filter(|&i| excess[i].is_some_and(worth))
                .collect();
            if worst.is_empty() {
                break;
            }
            let excess = |i: usize| excess[i].unwrap_or(0.0);
            worst.sort_by(|&a, &b| excess(b).total_cmp(&excess(a)).then(a.cmp(&b)));
            worst.truncate(REFINE_COUNT);
            let refined: Vec<(usize, PatchEntry)> = worst
                .par_iter()
                .map(|&i| {
                    let (s, patch) = &crossed[i];
                    build_patch(eval, *s, patch, SECOND_SPLITS, (leaf_excess, depth))
                        .map(|p| (i, p))
                })
                .collect::<Result<Vec<_>>>()?;
            for (i, p) in refined {
                refined_once[i] = true;
                if p.bounded_area() < patches[i].bounded_area() {
                    patches[i] = p;
                }
            }
        }

        let patches: Vec<PatchEntry> = patches
            .into_iter()
            .filter(|p| p.linear_area > 0.0)
            .collect();
        if patches.is_empty() {
            return Err(SampleError::EmptySurface { level: model.level });
        }
        // Sequential sums and a sequential alias construction: the same table, bit for bit,
        // whatever the thread count.
        let mut terms = Vec::new();
        let fast: Vec<Option<FastPatch>> = patches
            .iter()
            .map(|p| FastPatch::new(eval, p, &mut terms))
            .collect();
        let mut fast_index = vec![u32::MAX; patches.len()];
        let mut fast_records = Vec::new();
        for (i, f) in fast.into_iter().enumerate() {
            if let Some(f) = f {
                fast_index[i] = fast_records.len() as u32;
                fast_records.push(f);
            }
        }
        let mut slots = Vec::new();
        let mut weights = Vec::new();
        let mut acc = 0.0;
        let mut linear = 0.0;
        for (pi, p) in patches.iter().enumerate() {
            for (r, region) in p.regions.iter().enumerate() {
                let area = p.linear_area * region.fraction;
                let weight = match weighting {
                    Weighting::CurvedArea => area * region.bound,
                    Weighting::LinearArea => area,
                };
                if weight > 0.0 {
                    acc += weight;
                    slots.push(Slot {
                        u: region.u,
                        threshold: 1.0,
                        bound: region.bound,
                        alias: 0,
                        patch: pi as u32,
                        region: r as u32,
                        fast: fast_index[pi],
                    });
                    weights.push(weight);
                }
            }
            linear += p.linear_area;
        }
        for (slot, (threshold, alias)) in slots.iter_mut().zip(alias_table(&weights, acc)) {
            slot.threshold = threshold;
            slot.alias = alias;
        }
        Ok(SurfaceTable {
            patches,
            slots,
            fast: fast_records,
            terms,
            bounded_area: acc,
            linear_area: linear,
            scale: model_scale(model),
            weighting,
            pick_ahead: fast_index.iter().all(|&f| f != u32::MAX),
        })
    }

    /// Number of patches (crossed simplices).
    pub fn len(&self) -> usize {
        self.patches.len()
    }

    /// Whether there are no patches (never true for a built table).
    pub fn is_empty(&self) -> bool {
        self.patches.is_empty()
    }

    /// A selection entry with probability `A_r B_r / Σ A B`: one uniform picks a slot (its integer
    /// part) and decides between the slot and its alias (its fraction), O(1) with two memory
    /// reads where a binary search over the cumulative weights took `log₂` of the table's size.
    fn pick(&self, rng: &mut impl Rng) -> &Slot {
        let len = self.slots.len();
        let x = rng.random::<f64>() * len as f64;
        let slot = (x as usize).min(len - 1);
        let here = &self.slots[slot];
        if x - (slot as f64) < here.threshold {
            here
        } else {
            &self.slots[here.alias as usize]
        }
    }

    /// Draws one accepted surface sample.
    ///
    /// # Errors
    /// [`SampleError::Numerical`] when the inverse map does not converge, the area element exceeds
    /// its certified bound, or the point cannot be brought within [`SURFACE_TOLERANCE`].
    pub fn draw(&self, eval: &ModelEval, rng: &mut impl Rng) -> Result<SurfacePoint> {
        self.draw_with(eval, rng, None)
    }

    /// `count` accepted samples, each handed to `each` with the generator (which it may use
    /// between samples). Equal in distribution to `count` calls of [`SurfaceTable::draw`]: on
    /// tables with `pick_ahead` the candidates' slots are drawn `PICK_AHEAD` at a time (the
    /// same alias pick, its uniforms taken from the stream in a different order), so the bits
    /// for a seed differ from `draw`'s there; they never depend on the thread count. Picks left
    /// over after the last sample are dropped: they are independent of every candidate's
    /// acceptance, so dropping them biases nothing.
    ///
    /// # Errors
    /// As [`SurfaceTable::draw`], and `each`'s errors.
    pub fn draw_each<R: Rng>(
        &self,
        eval: &ModelEval,
        rng: &mut R,
        count: usize,
        mut each: impl FnMut(SurfacePoint, &mut R) -> Result<()>,
    ) -> Result<()> {
        let mut ahead = Ahead {
            next: PICK_AHEAD,
            ..Ahead::default()
        };
        for _ in 0..count {
            let point = self.draw_with(eval, rng, self.pick_ahead.then_some(&mut ahead))?;
            each(point, rng)?;
        }
        Ok(())
    }

    /// The next slot of `ahead`, refilled [`PICK_AHEAD`] at a time when used up: the pick
    /// uniforms are drawn first, then every slot is read (the reads are independent, so their
    /// misses overlap), then the chosen slots' patch records and first stage terms are touched
    /// for the same reason. Each pick is [`SurfaceTable::pick`]'s arithmetic.
    fn pick_ahead(&self, rng: &mut impl Rng, ahead: &mut Ahead) -> &Slot {
        if ahead.next == PICK_AHEAD {
            let len = self.slots.len();
            let mut x = [0.0; PICK_AHEAD];
            for xk in &mut x {
                *xk = rng.random::<f64>() * len as f64;
            }
            for (k, xk) in x.iter().enumerate() {
                let slot = (*xk as usize).min(len - 1);
                let here = &self.slots[slot];
                ahead.slots[k] = if xk - (slot as f64) < here.threshold {
                    slot as u32
                } else {
                    here.alias
                };
            }
            // Touch what each candidate reads: both lines of its slot, the four lines of its
            // patch record, its stages' first terms; the sum only keeps the reads.
            let mut touched = 0u64;
            for &k in &ahead.slots {
                let slot = &self.slots[k as usize];
                touched ^= slot.u[0][0].to_bits() ^ slot.bound.to_bits();
                if let Some(fast) = self.fast.get(slot.fast as usize) {
                    touched ^= fast.inv[1].to_bits()
                        ^ fast.values[0].to_bits()
                        ^ fast.vertices[MAX_VARS - 1][0].to_bits();
                    for k in 0..usize::from(fast.stages) {
                        touched ^= self.terms[fast.stage(k).0].1[0].to_bits();
                    }
                }
            }
            std::hint::black_box(touched);
            ahead.next = 0;
        }
        let slot = &self.slots[ahead.slots[ahead.next] as usize];
        ahead.next += 1;
        slot
    }

    /// [`SurfaceTable::draw`], its slots from `ahead` when given.
    fn draw_with(
        &self,
        eval: &ModelEval,
        rng: &mut impl Rng,
        mut ahead: Option<&mut Ahead>,
    ) -> Result<SurfacePoint> {
        let n = eval.dim();
        loop {
            let slot = match ahead.as_deref_mut() {
                Some(ahead) => self.pick_ahead(rng, ahead),
                None => self.pick(rng),
            };
            if let Some(fast) = self.fast.get(slot.fast as usize) {
                match self.draw_fast(eval, slot, fast, rng)? {
                    Some(point) => return Ok(point),
                    None => continue,
                }
            }
            let (patch, region) = (&self.patches[slot.patch as usize], slot.region as usize);
            let s = patch.simplex as usize;
            let map = eval.local_map(s);
            let (u, guess) = patch.propose(region, map, rng);
            if !patch.guessed && !map.stages().is_empty() {
                // All-parametric: no Newton and no inverse (see `param_adjugate`).
                let (w, adj, det_dy) = param_adjugate(map, &u, &patch.sparse);
                let scaled = eval.gradient_from_jacobian(s, &adj);
                let accept = match self.weighting {
                    Weighting::LinearArea => true,
                    Weighting::CurvedArea => {
                        let bound = patch.regions[region].bound;
                        let j = area_element_parametric(
                            s,
                            &w,
                            &scaled,
                            det_dy,
                            (patch_dim(patch), patch.linear_gradient),
                            bound,
                        )?;
                        rng.random::<f64>() * bound < j
                    }
                };
                if accept {
                    let mut grad = [0.0; 3];
                    for x in 0..n {
                        grad[x] = scaled[x] / det_dy;
                    }
                    let solved = Solved {
                        w,
                        x: u,
                        jacobian: adj,
                        residual: 0.0,
                        iterations: 0,
                    };
                    return self.finish_solved(eval, s, &solved, &grad);
                }
                continue;
            }
            let solved = if map.stages().is_empty() {
                Solved {
                    w: u,
                    x: u,
                    jacobian: ism_geom::stage::identity_mat(n),
                    residual: 0.0,
                    iterations: 0,
                }
            } else {
                match map.inverse_near(&u, &guess) {
                    Some(solved) => solved,
                    None => solve_from_scratch(map, s, &u)?,
                }
            };
            let grad = eval.gradient_from_jacobian(s, &solved.jacobian);
            let accept = match self.weighting {
                // No stage: the shape is the linear patch, J ≡ 1 (no rounding should decide).
                Weighting::LinearArea => true,
                Weighting::CurvedArea if map.stages().is_empty() => true,
                Weighting::CurvedArea => {
                    let bound = patch.regions[region].bound;
                    let j = self.area_element(s, &solved, &grad, patch, bound)?;
                    rng.random::<f64>() * bound < j
                }
            };
            if accept {
                return self.finish_solved(eval, s, &solved, &grad);
            }
        }
    }

    /// One candidate from a [`FastPatch`]: what the all-parametric branch of
    /// [`SurfaceTable::draw`] does through the patch entry, the evaluator and the local map, on
    /// the copied records instead: the same random numbers and the same arithmetic in the same
    /// order, hence the same bits. `None`: rejected.
    fn draw_fast(
        &self,
        eval: &ModelEval,
        slot: &Slot,
        fast: &FastPatch,
        rng: &mut impl Rng,
    ) -> Result<Option<SurfacePoint>> {
        let n = eval.dim();
        let s = fast.simplex as usize;
        let u = region_point(
            &slot.u,
            &region_weights(fast.triangles, rng),
            fast.triangles,
        );
        // A stage-free patch draws as `draw_with`'s stage-free branch: `w = u`, `J ≡ 1`.
        let mut w = if fast.stages == 0 {
            u
        } else {
            ism_geom::stage::project(n + 1, &u)
        };
        let mut dy = identity(n);
        for k in 0..usize::from(fast.stages) {
            let (start, end, degree) = fast.stage(k);
            let terms = &self.terms[start..end];
            let (next, j) = sparse_jacobian(terms, degree, n + 1, &w);
            dy = linalg::mul(n, &j, &dy);
            w = next;
        }
        let (adj, det_dy) = adjugate(n, &dy);
        // ModelEval::gradient_from_jacobian with the simplex's values and inverse edges copied.
        let mut dw = [0.0; 3];
        for (l, d) in dw.iter_mut().enumerate().take(n) {
            *d = (0..n).map(|k| fast.df[k] * adj[k][l]).sum();
        }
        let mut scaled = [0.0; 3];
        for (x, g) in scaled.iter_mut().enumerate().take(n) {
            *g = (0..n).map(|l| dw[l] * fast.inv[l * 3 + x]).sum();
        }
        // No stage: the shape is the linear patch, `J ≡ 1` (no rounding should decide).
        if self.weighting == Weighting::CurvedArea && fast.stages > 0 {
            let dim = if fast.triangles == 0 { 2 } else { 3 };
            let j = area_element_parametric(
                s,
                &w,
                &scaled,
                det_dy,
                (dim, fast.linear_gradient),
                slot.bound,
            )?;
            if rng.random::<f64>() * slot.bound >= j {
                return Ok(None);
            }
        }
        let mut grad = [0.0; 3];
        for x in 0..n {
            grad[x] = scaled[x] / det_dy;
        }
        // SurfaceTable::finish_solved with the simplex's values and vertices copied.
        let c = eval.model().level;
        let f: f64 = (0..=n).map(|i| fast.values[i] * u[i]).sum();
        let gn = norm(&grad[..n]);
        if (f - c).abs() <= SURFACE_TOLERANCE * gn * self.scale && gn > 0.0 {
            let mut normal = [0.0; 3];
            for x in 0..n {
                normal[x] = grad[x] / gn;
            }
            let mut p = [0.0; 3];
            for (i, q) in fast.vertices.iter().enumerate().take(n + 1) {
                for x in 0..n {
                    p[x] += w[i] * q[x];
                }
            }
            return Ok(Some(SurfacePoint {
                p,
                normal,
                value: f,
                simplex: s,
            }));
        }
        self.finish(eval, s, w).map(Some)
    }

    /// `J = |∇F| / (|∇F_lin| det DX)` (module doc of [`crate::bound`]), from the Jacobian the
    /// inverse returned.
    fn area_element(
        &self,
        s: usize,
        solved: &Solved,
        grad: &[f64; 3],
        patch: &PatchEntry,
        bound: f64,
    ) -> Result<f64> {
        let n = grad.len().min(patch_dim(patch));
        let det = linalg::det(n, &solved.jacobian);
        if det.is_nan() || det <= 0.0 {
            return Err(SampleError::Numerical {
                simplex: s,
                reason: format!("det DX = {det} ≤ 0 at w = {:?}", &solved.w[..=n]),
            });
        }
        let j = norm(&grad[..n]) / (patch.linear_gradient * det);
        if j > bound {
            return Err(SampleError::Numerical {
                simplex: s,
                reason: format!("area element {j} exceeds its certified bound {bound}"),
            });
        }
        Ok(j)
    }

    /// The accepted point, from the values the inverse already computed when they meet the
    /// surface tolerance (the usual case), else polished by [`SurfaceTable::finish`].
    fn finish_solved(
        &self,
        eval: &ModelEval,
        s: usize,
        solved: &Solved,
        grad: &[f64; 3],
    ) -> Result<SurfacePoint> {
        let n = eval.dim();
        let c = eval.model().level;
        let f = eval.value_from_coordinates(s, &solved.x);
        let gn = norm(&grad[..n]);
        if (f - c).abs() <= SURFACE_TOLERANCE * gn * self.scale && gn > 0.0 {
            let mut normal = [0.0; 3];
            for x in 0..n {
                normal[x] = grad[x] / gn;
            }
            return Ok(SurfacePoint {
                p: eval.point(s, &solved.w),
                normal,
                value: f,
                simplex: s,
            });
        }
        self.finish(eval, s, solved.w)
    }

    fn finish(&self, eval: &ModelEval, s: usize, mut w: Bary) -> Result<SurfacePoint> {
        let n = eval.dim();
        let c = eval.model().level;
        for step in 0..=POLISH_STEPS {
            let f = eval.value_at(s, &w);
            let grad = eval
                .gradient_at(s, &w)
                .ok_or_else(|| SampleError::Numerical {
                    simplex: s,
                    reason: "singular stage Jacobian".into(),
                })?;
            let gn = norm(&grad[..n]);
            let p = eval.point(s, &w);
            if (f - c).abs() <= SURFACE_TOLERANCE * gn * self.scale {
                let mut normal = [0.0; 3];
                for x in 0..n {
                    normal[x] = grad[x] / gn;
                }
                return Ok(SurfacePoint {
                    p,
                    normal,
                    value: f,
                    simplex: s,
                });
            }
            if step == POLISH_STEPS || gn == 0.0 {
                break;
            }
            // Newton along ∇F, kept in the simplex (the shape crosses σ, so the step is short).
            let mut q = p;
            for x in 0..n {
                q[x] -= (f - c) * grad[x] / (gn * gn);
            }
            w = ism_geom::stage::project(n + 1, &eval.barycentric(s, &q));
        }
        Err(SampleError::Numerical {
            simplex: s,
            reason: format!("sample at w = {:?} misses |F − c| ≤ {SURFACE_TOLERANCE}·|∇F|·L after {POLISH_STEPS} Newton steps", &w[..=n]),
        })
    }
}

/// `J = |E⁻ᵀ adj(DY)ᵀ Δf| / |∇F_lin|` for an all-parametric map, from `scaled` =
/// `det(DY) ∇F` ([`param_adjugate`]); `(n, |∇F_lin|)` of the patch.
fn area_element_parametric(
    s: usize,
    w: &Bary,
    scaled: &[f64; 3],
    det_dy: f64,
    (n, linear_gradient): (usize, f64),
    bound: f64,
) -> Result<f64> {
    if det_dy.is_nan() || det_dy <= 0.0 {
        return Err(SampleError::Numerical {
            simplex: s,
            reason: format!("det DY = {det_dy} ≤ 0 at w = {:?}", &w[..=n]),
        });
    }
    let j = norm(&scaled[..n]) / linear_gradient;
    if j > bound {
        return Err(SampleError::Numerical {
            simplex: s,
            reason: format!("area element {j} exceeds its certified bound {bound}"),
        });
    }
    Ok(j)
}

/// Walker's alias table (Vose's construction) of `weights` (positive, summing to `total`): entry
/// `i` gets `(threshold_i, alias_i)` such that picking a slot uniformly, keeping it with
/// probability `threshold_i` and taking `alias_i` otherwise selects `i` with probability
/// `weights[i] / total`. Slots are processed in a fixed order, so the table does not depend on
/// the thread count.
fn alias_table(weights: &[f64], total: f64) -> Vec<(f64, u32)> {
    let len = weights.len();
    let mut scaled: Vec<f64> = weights.iter().map(|w| w * len as f64 / total).collect();
    let mut table = vec![(1.0, 0u32); len];
    for (i, t) in table.iter_mut().enumerate() {
        t.1 = i as u32;
    }
    let (mut small, mut large): (Vec<usize>, Vec<usize>) = (0..len).partition(|&i| scaled[i] < 1.0);
    while let (Some(&s), Some(&l)) = (small.last(), large.last()) {
        small.pop();
        table[s] = (scaled[s], l as u32);
        scaled[l] = (scaled[l] + scaled[s]) - 1.0;
        if scaled[l] < 1.0 {
            large.pop();
            small.push(l);
        }
    }
    // What is left is 1 up to rounding: those slots keep themselves.
    for i in small.into_iter().chain(large) {
        table[i] = (1.0, i as u32);
    }
    table
}

/// A point of `O` with its unit normal and source simplex.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    /// Position (first `n` entries).
    pub p: [f64; 3],
    /// `∇F/|∇F|` (first `n` entries): points outside.
    pub normal: [f64; 3],
    /// `F(p)` (equal to the level within tolerance).
    pub value: f64,
    /// Source top simplex.
    pub simplex: usize,
}

/// A Bézier stage as the identity plus its moved control points: `S(w) = w + Σ_I c_I w^I` on the
/// simplex, `c_I = C(d; I) (b_I − I/d)`, since the net `b_I = I/d` is the identity map
/// (`Σ_I (I/d) B_I(w) = w` where `Σ w = 1`, and its reduced Jacobian is the identity). A stratified
/// stage moves few of its points on a given simplex (the fitted torus: 59 / 20 / 2.7 % of the
/// degree-2 / 3 / 4 points), so this does a fraction of the kernel's dense evaluation; the values
/// agree to rounding (tested against [`ism_geom::LocalStage::jacobian_stored`]).
/// Powers `w_k^0 ..= w_k^d` a [`SparseStage`] tabulates: every degree the format allows.
const POWERS: usize = ism_format::structure::MAX_DEGREE as usize + 1;

#[derive(Clone, Debug)]
struct SparseStage {
    /// `(exponents I, c_I)` per moved control point.
    terms: Vec<Term>,
    degree: usize,
}

impl SparseStage {
    /// `None` unless the stage is Bézier.
    fn new(stage: &ism_geom::LocalStage) -> Option<SparseStage> {
        if stage.kind() != ism_format::StageKind::Bezier {
            return None;
        }
        let m = stage.vars();
        let d = stage.degree();
        // Beyond the format's maximum (a model built without the structural check) the power
        // table would not hold the exponents: the kernel's dense evaluation is used instead.
        if d as usize >= POWERS {
            return None;
        }
        // The kernel's identity net of this shape, built once per shape (it was built per
        // patch and stage: a dense stage and its allocations, 2 % of a small model's setup).
        type Nets = [[std::sync::OnceLock<Option<Vec<Bary>>>; POWERS]; MAX_VARS + 1];
        static IDENTITY: Nets =
            [const { [const { std::sync::OnceLock::new() }; POWERS] }; MAX_VARS + 1];
        if m > MAX_VARS {
            return None;
        }
        let identity = IDENTITY[m][d as usize]
            .get_or_init(|| {
                ism_geom::LocalStage::identity(ism_format::StageKind::Bezier, d, m)
                    .ok()
                    .map(|id| id.control_points().to_vec())
            })
            .as_deref()?;
        let fact = |k: u32| (1..=k).map(f64::from).product::<f64>();
        let mut terms = Vec::new();
        for (b, id) in stage.control_points().iter().zip(identity) {
            let mut c = [0.0; MAX_VARS];
            for k in 0..m {
                c[k] = b[k] - id[k];
            }
            if c.iter().all(|&x| x == 0.0) {
                continue;
            }
            let mut e = [0u8; MAX_VARS];
            for k in 0..m {
                e[k] = (id[k] * f64::from(d)).round() as u8;
            }
            let mult = fact(d) / e[..m].iter().map(|&x| fact(u32::from(x))).product::<f64>();
            for x in c.iter_mut().take(m) {
                *x *= mult;
            }
            terms.push((e, c));
        }
        Some(SparseStage {
            terms,
            degree: d as usize,
        })
    }

    /// Value and reduced Jacobian (`R[i−1][l−1] = ∂_l S_i − ∂_0 S_i`, as the kernel's) at `w`
    /// (on the simplex).
    fn jacobian_stored(&self, m: usize, w: &Bary) -> (Bary, Mat) {
        sparse_jacobian(&self.terms, self.degree, m, w)
    }
}

/// [`ism_geom::stage::identity_mat`] (the same matrix), inlined: the draw builds one per stage
/// per candidate, and the kernel's is an out-of-line call (3 % of a fitted torus's 1e6 run).
#[inline]
fn identity(n: usize) -> Mat {
    let mut a = [[0.0; MAX_VARS]; MAX_VARS];
    for (i, row) in a.iter_mut().enumerate().take(n) {
        row[i] = 1.0;
    }
    a
}

/// [`SparseStage::jacobian_stored`] of the stage of degree `degree` with these terms.
fn sparse_jacobian(terms: &[Term], degree: usize, m: usize, w: &Bary) -> (Bary, Mat) {
    let mut pw = [[1.0f64; POWERS]; MAX_VARS];
    for k in 0..m {
        for p in 1..=degree {
            pw[k][p] = pw[k][p - 1] * w[k];
        }
    }
    let mut value = *w;
    let mut jac = identity(m - 1);
    for (e, c) in terms {
        let mut mono = 1.0;
        for k in 0..m {
            mono *= pw[k][e[k] as usize];
        }
        // ∂_j w^I = I_j w_j^{I_j − 1} Π_{k≠j} w_k^{I_k}.
        let mut grad = [0.0; MAX_VARS];
        for j in 0..m {
            if e[j] == 0 {
                continue;
            }
            let mut g = f64::from(e[j]) * pw[j][e[j] as usize - 1];
            for k in 0..m {
                if k != j {
                    g *= pw[k][e[k] as usize];
                }
            }
            grad[j] = g;
        }
        for i in 0..m {
            value[i] += c[i] * mono;
        }
        for i in 1..m {
            for l in 1..m {
                jac[i - 1][l - 1] += c[i] * (grad[l] - grad[0]);
            }
        }
    }
    (value, jac)
}

/// `w = Y(u)`, the adjugate `adj(DY) = det(DY) · DX` (reduced Jacobians) and `det DY` of an
/// all-parametric map (`Y = X⁻¹` stored, `Y = Y_0 ∘ … ∘ Y_last`). With `DX = DY⁻¹`,
/// `∇F = E⁻ᵀ DXᵀ Δf = E⁻ᵀ adj(DY)ᵀ Δf / det DY` and `det DX = 1 / det DY`, so the area element
/// `J = |∇F| / (|∇F_lin| det DX) = |E⁻ᵀ adj(DY)ᵀ Δf| / |∇F_lin|` and the normal's direction
/// need no inverse: a rejected candidate costs the stage Jacobians and nothing else.
/// `sparse`: the stages as [`SparseStage`]s in processing order (used when there is one per
/// stage), else the kernel's dense evaluation.
fn param_adjugate(map: &ism_geom::LocalMap, u: &Bary, sparse: &[SparseStage]) -> (Bary, Mat, f64) {
    let n = map.vars() - 1;
    let mut w = ism_geom::stage::project(n + 1, u);
    let mut dy = ism_geom::stage::identity_mat(n);
    if !sparse.is_empty() && sparse.len() == map.stages().len() {
        for st in sparse {
            let (next, j) = st.jacobian_stored(n + 1, &w);
            dy = linalg::mul(n, &j, &dy);
            w = next;
        }
    } else {
        // The last stored stage acts on u first (as in `LocalMap::param_solve`).
        for st in map.stages().iter().rev() {
            let (next, j) = st.jacobian_stored(&w);
            dy = linalg::mul(n, &j, &dy);
            w = next;
        }
    }
    let (adj, det) = adjugate(n, &dy);
    (w, adj, det)
}

/// `adj(DY)` and `det DY` (reduced Jacobians, `n × n`).
fn adjugate(n: usize, dy: &Mat) -> (Mat, f64) {
    let mut adj = [[0.0; MAX_VARS]; MAX_VARS];
    match n {
        1 => adj[0][0] = 1.0,
        2 => {
            adj[0][0] = dy[1][1];
            adj[0][1] = -dy[0][1];
            adj[1][0] = -dy[1][0];
            adj[1][1] = dy[0][0];
        }
        _ => {
            // adj(A)[i][j] = cofactor of A[j][i]; cyclic indices give the signs for 3×3.
            for (i, row) in adj.iter_mut().enumerate().take(3) {
                for (j, entry) in row.iter_mut().enumerate().take(3) {
                    let (r0, r1) = ((j + 1) % 3, (j + 2) % 3);
                    let (c0, c1) = ((i + 1) % 3, (i + 2) % 3);
                    *entry = dy[r0][c0] * dy[r1][c1] - dy[r0][c1] * dy[r1][c0];
                }
            }
        }
    }
    (adj, linalg::det(n, dy))
}

/// `X⁻¹(u)` with the robust per-stage solver (when Newton from the lattice guess fails), and the
/// Jacobian there.
fn solve_from_scratch(map: &ism_geom::LocalMap, s: usize, u: &Bary) -> Result<Solved> {
    let n = map.vars() - 1;
    let inv = map.inverse(u);
    if inv.residual.is_nan() || inv.residual > INVERSE_RESIDUAL {
        return Err(SampleError::Numerical {
            simplex: s,
            reason: format!(
                "inverse map did not converge at u = {:?} (residual {:e})",
                &u[..=n],
                inv.residual
            ),
        });
    }
    let (x, j) = map.jacobian(&inv.w);
    let jacobian = j.ok_or_else(|| SampleError::Numerical {
        simplex: s,
        reason: "singular stage Jacobian".into(),
    })?;
    Ok(Solved {
        w: inv.w,
        x,
        jacobian,
        residual: inv.residual,
        iterations: inv.iterations,
    })
}

/// Dimension of the patch's simplex (2 for a segment patch, 3 otherwise).
fn patch_dim(patch: &PatchEntry) -> usize {
    if patch.triangles == 0 {
        2
    } else {
        3
    }
}

/// The lattice points of each patch triangle (segment in 2D) with their preimages `X⁻¹(u)`, or
/// with `u` itself when `preimages` is false.
fn lattice_guesses(
    map: &ism_geom::LocalMap,
    tris: &[[Bary; 3]; 2],
    count: u8,
    preimages: bool,
) -> Vec<(Bary, Bary)> {
    (0..lattice_len(count))
        .map(|k| {
            let u = lattice_point(tris, count, k);
            (
                u,
                if preimages {
                    lattice_preimage(map, &u)
                } else {
                    u
                },
            )
        })
        .collect()
}

/// The preimage kept for lattice point `u`, in the whole lattice ([`lattice_guesses`]) and
/// point by point ([`PatchEntry::start`]) alike, so both give the draws the same bits. Only a
/// starting guess: an unconverged preimage costs iterations, not accuracy.
fn lattice_preimage(map: &ism_geom::LocalMap, u: &Bary) -> Bary {
    map.inverse(u).w
}

/// Number of lattice points of a patch of `count` triangles (0: a segment).
fn lattice_len(count: u8) -> usize {
    if count == 0 {
        GUESS_LEVEL + 1
    } else {
        LATTICE_POINTS * usize::from(count)
    }
}

/// Lattice point `k` of a patch of `count` triangles `tris` (0: the segment `tris[0][0..2]`), in
/// the order of [`lattice_guesses`] (triangle by triangle, [`lattice_index`] within each).
fn lattice_point(tris: &[[Bary; 3]; 2], count: u8, k: usize) -> Bary {
    if count == 0 {
        return segment_point(&tris[0], k);
    }
    let (t, r) = (k / LATTICE_POINTS, k % LATTICE_POINTS);
    let i = (0..=GUESS_LEVEL)
        .rev()
        .find(|&i| lattice_index(i, 0) <= r)
        .expect("lattice_index(0, 0) = 0");
    lattice_u(&tris[t], (i, r - lattice_index(i, 0)))
}

/// Lattice point `i` (`0..=GUESS_LEVEL`) of a segment patch, whose ends are `tri[0]`, `tri[1]`.
fn segment_point(tri: &[Bary; 3], i: usize) -> Bary {
    let t = i as f64 / GUESS_LEVEL as f64;
    let mut u = [0.0; MAX_VARS];
    for k in 0..MAX_VARS {
        u[k] = (1.0 - t) * tri[0][k] + t * tri[1][k];
    }
    u
}

/// `(u, exact J)` at the lattice points whose preimage converged (points of the shape): J from
/// the stage Jacobians there, `lin` being `|∇F_lin|`.
fn lattice_samples(
    eval: &ModelEval,
    s: usize,
    lattice: &[(Bary, Bary)],
    lin: f64,
) -> Vec<([f64; 4], f64)> {
    let map = eval.local_map(s);
    let n = map.vars() - 1;
    lattice
        .iter()
        .filter_map(|(u, w)| {
            let (x, j) = match map.param_solve(u) {
                Some(solved) => (solved.x, solved.jacobian),
                None => {
                    let (x, j) = map.jacobian(w);
                    (x, j?)
                }
            };
            // Only converged preimages are points of the shape.
            let off = (0..=n).map(|i| (x[i] - u[i]).abs()).fold(0.0, f64::max);
            let grad = eval.gradient_from_jacobian(s, &j);
            let det = linalg::det(n, &j);
            (det > 0.0 && off <= INVERSE_RESIDUAL).then(|| (*u, norm(&grad[..n]) / (lin * det)))
        })
        .collect()
}

/// The mean of the samples' `J` (0 without samples).
fn mean_j(samples: &[([f64; 4], f64)]) -> f64 {
    samples.iter().map(|s| s.1).sum::<f64>() / samples.len().max(1) as f64
}

/// The `GUESS_LEVEL²` sub-triangles of the lattice of a triangle, as lattice coordinates
/// `(i, j)` of their vertices: "lower" `(i, j), (i+1, j), (i, j+1)` for `i + j < L`, then "upper"
/// `(i+1, j+1), (i, j+1), (i+1, j)` for `i + j < L − 1`. All have the same area.
fn sub_triangles() -> &'static [[(usize, usize); 3]] {
    static SUBS: std::sync::OnceLock<Vec<[(usize, usize); 3]>> = std::sync::OnceLock::new();
    SUBS.get_or_init(|| {
        let l = GUESS_LEVEL;
        let mut out = Vec::with_capacity(l * l);
        for i in 0..l {
            for j in 0..l - i {
                out.push([(i, j), (i + 1, j), (i, j + 1)]);
            }
        }
        for i in 0..l {
            for j in 0..l - i {
                if i + j + 1 < l {
                    out.push([(i + 1, j + 1), (i, j + 1), (i + 1, j)]);
                }
            }
        }
        out
    })
}

/// `u` of lattice point `(i, j)` of triangle `tri`.
fn lattice_u(tri: &[Bary; 3], (i, j): (usize, usize)) -> Bary {
    let l = GUESS_LEVEL as f64;
    let (lb, lc) = (i as f64 / l, j as f64 / l);
    let la = 1.0 - lb - lc;
    let mut u = [0.0; MAX_VARS];
    for k in 0..MAX_VARS {
        u[k] = la * tri[0][k] + lb * tri[1][k] + lc * tri[2][k];
    }
    u
}

/// Bounding boxes (in `u`) of the regions of a patch: sub-triangles of each triangle, or
/// sub-segments of a segment.
fn regions(tris: &[[Bary; 3]; 2], count: u8) -> Vec<(Bary, Bary)> {
    if count == 0 {
        let [a, b, _] = tris[0];
        let l = GUESS_LEVEL as f64;
        return (0..GUESS_LEVEL)
            .map(|k| {
                let at = |t: f64| {
                    let mut u = [0.0; MAX_VARS];
                    for x in 0..MAX_VARS {
                        u[x] = (1.0 - t) * a[x] + t * b[x];
                    }
                    u
                };
                bary_box(&[at(k as f64 / l), at((k + 1) as f64 / l)])
            })
            .collect();
    }
    tris.iter()
        .take(usize::from(count))
        .flat_map(|tri| {
            sub_triangles().iter().map(|v| {
                bary_box(&[
                    lattice_u(tri, v[0]),
                    lattice_u(tri, v[1]),
                    lattice_u(tri, v[2]),
                ])
            })
        })
        .collect()
}

/// Replaces each region of an implicit chain's patch whose bounded area (its share of the patch
/// times its bound) is above `min_mass` (a share of the patch) by its parts — four triangles at
/// its edges' midpoints, or two halves of a segment — each bounded over its own box, when their
/// bounded area is at most [`PARTS_PAY`] of the region's; and the parts likewise, to
/// `max_depth` halvings ([`REGION_DEPTH`]). The bounds stay certified (each part's is the bound over a box
/// that holds it, and never above its region's), and a sample is drawn the same way from a part
/// as from a region; where `J` peaks in a corner of a region (a projective stage with weights
/// far apart) the rest of it stops taking the peak's bound. Asking the bounds is cheap (no new
/// bisection): they are the chain's leaves and the per-stage bound's cells, which may be finer
/// than the fixed regions.
fn split_regions(
    regions: Vec<RegionEntry>,
    bounder: &RegionBounder,
    (triangles, max_depth): (u8, u32),
    min_mass: f64,
) -> Vec<RegionEntry> {
    // Corners of the parts, as weights of the region's corners.
    const HALF: f64 = 0.5;
    let tri_parts: [[[f64; 3]; 3]; 4] = [
        [[1.0, 0.0, 0.0], [HALF, HALF, 0.0], [HALF, 0.0, HALF]],
        [[HALF, HALF, 0.0], [0.0, 1.0, 0.0], [0.0, HALF, HALF]],
        [[HALF, 0.0, HALF], [0.0, HALF, HALF], [0.0, 0.0, 1.0]],
        [[HALF, HALF, 0.0], [0.0, HALF, HALF], [HALF, 0.0, HALF]],
    ];
    let seg_parts: [[[f64; 3]; 3]; 2] = [
        [[1.0, 0.0, 0.0], [HALF, HALF, 0.0], [HALF, HALF, 0.0]],
        [[HALF, HALF, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]],
    ];
    let parts: &[[[f64; 3]; 3]] = if triangles == 0 {
        &seg_parts
    } else {
        &tri_parts
    };
    let mut out = Vec::with_capacity(regions.len());
    let mut stack: Vec<(RegionEntry, u32)> = regions.into_iter().rev().map(|r| (r, 0)).collect();
    while let Some((r, depth)) = stack.pop() {
        let mass = r.fraction * r.bound;
        // A NaN mass is not split (nor is an infinite one refused here: `build_patch` refuses a
        // patch whose bound is not finite).
        if depth >= max_depth || mass.is_nan() || mass <= min_mass {
            out.push(r);
            continue;
        }
        // The part's corners in the fixed region (composed with the region's own, for a part).
        let base = r
            .part
            .unwrap_or([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
        let children: Vec<RegionEntry> = parts
            .iter()
            .map(|w| {
                let mut u = [[0.0; MAX_VARS]; 3];
                let mut part = [[0.0; 3]; 3];
                for k in 0..3 {
                    u[k] = region_point(&r.u, &w[k], triangles);
                    for j in 0..3 {
                        part[k][j] = (0..3).map(|i| w[k][i] * base[i][j]).sum();
                    }
                }
                let (lo, hi) = corner_box(&u, triangles);
                RegionEntry {
                    u,
                    g: r.g,
                    fraction: r.fraction / parts.len() as f64,
                    bound: bounder.over(&lo, &hi).min(r.bound),
                    part: Some(part),
                }
            })
            .collect();
        let parts_mass: f64 = children.iter().map(|c| c.fraction * c.bound).sum();
        if parts_mass <= PARTS_PAY * mass {
            stack.extend(children.into_iter().rev().map(|c| (c, depth + 1)));
        } else {
            out.push(r);
        }
    }
    out
}

/// The box of a region's corners (two for a segment).
fn corner_box(u: &[Bary; 3], triangles: u8) -> (Bary, Bary) {
    bary_box(&u[..if triangles == 0 { 2 } else { 3 }])
}

/// The coordinatewise box of barycentric points.
fn bary_box(pts: &[Bary]) -> (Bary, Bary) {
    let mut lo = [f64::INFINITY; MAX_VARS];
    let mut hi = [f64::NEG_INFINITY; MAX_VARS];
    for p in pts {
        for k in 0..MAX_VARS {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    (lo, hi)
}

/// The fixed regions of an implicit chain's patch, in [`regions`] order, with the indices of
/// their corners in the lattice ([`lattice_guesses`]) and their bounds.
fn lattice_regions(
    tris: &[[Bary; 3]; 2],
    count: u8,
    first_fraction: f64,
    bounds: &[f64],
) -> Vec<RegionEntry> {
    if count == 0 {
        let share = 1.0 / GUESS_LEVEL as f64;
        return (0..GUESS_LEVEL)
            .map(|k| {
                let (a, b) = (segment_point(&tris[0], k), segment_point(&tris[0], k + 1));
                // The lattice's `u` is computed the same way: the same bits.
                RegionEntry {
                    u: [a, b, b],
                    g: [k as u16, k as u16 + 1, k as u16 + 1],
                    fraction: share,
                    bound: bounds[k],
                    part: None,
                }
            })
            .collect();
    }
    let per = (GUESS_LEVEL * GUESS_LEVEL) as f64;
    let mut out = Vec::with_capacity(bounds.len());
    for (t, tri) in tris.iter().take(usize::from(count)).enumerate() {
        let share = if t == 0 {
            first_fraction
        } else {
            1.0 - first_fraction
        };
        for v in sub_triangles() {
            let mut u = [[0.0; MAX_VARS]; 3];
            let mut g = [0u16; 3];
            for (k, &c) in v.iter().enumerate() {
                u[k] = lattice_u(tri, c);
                // At most `2 · LATTICE_POINTS` (30) entries.
                g[k] = (t * LATTICE_POINTS + lattice_index(c.0, c.1)) as u16;
            }
            out.push(RegionEntry {
                u,
                g,
                fraction: share / per,
                bound: bounds[out.len()],
                part: None,
            });
        }
    }
    out
}

impl PatchEntry {
    /// `Σ_r A_r B_r`: this patch's share of the table's bounded area.
    fn bounded_area(&self) -> f64 {
        self.regions
            .iter()
            .map(|r| self.linear_area * r.fraction * r.bound)
            .sum()
    }

    /// Bounded area minus the sampled estimate of the curved area: what loose bounds cost here.
    /// Never above [`PatchEntry::bounded_area`] (the estimate is not negative).
    fn excess(&self, eval: &ModelEval) -> f64 {
        (self.bounded_area() - self.linear_area * self.sample_mean(eval)).max(0.0)
    }

    /// Mean exact `J` at the lattice points (computed on first use).
    fn sample_mean(&self, eval: &ModelEval) -> f64 {
        *self.sample_mean.get_or_init(|| {
            let s = self.simplex as usize;
            let lattice = self.lattice(eval.local_map(s));
            mean_j(&lattice_samples(eval, s, lattice, self.linear_gradient))
        })
    }

    /// The lattice points with their preimages (computed on first use; `map` is the patch's
    /// local map).
    fn lattice(&self, map: &ism_geom::LocalMap) -> &[(Bary, Bary)] {
        self.lattice
            .get_or_init(|| lattice_guesses(map, &self.tris, self.triangles, self.guessed))
    }

    /// The preimage of lattice point `k` (a `guessed` patch's): from the whole lattice when it
    /// is computed, else computed alone and kept ([`PatchEntry::starts`]).
    fn start(&self, map: &ism_geom::LocalMap, k: usize) -> Bary {
        if let Some(lattice) = self.lattice.get() {
            return lattice[k].1;
        }
        let starts = self.starts.get_or_init(|| {
            (0..lattice_len(self.triangles))
                .map(|_| OnceLock::new())
                .collect()
        });
        *starts[k]
            .get_or_init(|| lattice_preimage(map, &lattice_point(&self.tris, self.triangles, k)))
    }

    /// Number of regions a sample is drawn from.
    pub fn regions(&self) -> usize {
        self.regions.len()
    }

    /// `u` uniform (by point-space area; `W` is affine so barycentric area is proportional) on
    /// region `region` of the patch, and the preimage guess interpolated linearly in the
    /// preimages at the region's corners (`map`: the patch's local map).
    fn propose(&self, region: usize, map: &ism_geom::LocalMap, rng: &mut impl Rng) -> (Bary, Bary) {
        let r = &self.regions[region];
        let weights = region_weights(self.triangles, rng);
        let u = region_point(&r.u, &weights, self.triangles);
        if !self.guessed {
            return (u, u);
        }
        // A part's weights in its fixed region, whose corners' preimages start Newton.
        let in_region = match &r.part {
            None => weights,
            Some(part) => {
                let mut w = [0.0; 3];
                for (wk, pk) in weights.iter().zip(part) {
                    for (x, p) in w.iter_mut().zip(pk) {
                        *x += wk * p;
                    }
                }
                w
            }
        };
        let g = region_point(
            &r.g.map(|k| self.start(map, usize::from(k))),
            &in_region,
            self.triangles,
        );
        (u, g)
    }
}

/// Weights of the corners of a uniform point of a region: a triangle (`triangles > 0`) or a
/// segment.
fn region_weights(triangles: u8, rng: &mut impl Rng) -> [f64; 3] {
    if triangles == 0 {
        let t: f64 = rng.random();
        [1.0 - t, t, 0.0]
    } else {
        let r1: f64 = rng.random();
        let r2: f64 = rng.random();
        let s = r1.sqrt();
        [1.0 - s, s * (1.0 - r2), s * r2]
    }
}

/// `Σ weights_k points_k` over the region's corners (two for a segment).
fn region_point(points: &[Bary; 3], weights: &[f64; 3], triangles: u8) -> Bary {
    let corners = if triangles == 0 { 2 } else { 3 };
    let mut out = [0.0; MAX_VARS];
    for (wt, p) in weights.iter().zip(points).take(corners) {
        for (o, x) in out.iter_mut().zip(p) {
            *o += wt * x;
        }
    }
    out
}

impl FastPatch {
    /// `(start, end, degree)` of stage `k`'s terms in [`SurfaceTable::terms`].
    fn stage(&self, k: usize) -> (usize, usize, usize) {
        let first = self.first as usize;
        let start = if k == 0 {
            0
        } else {
            usize::from(self.ends[k - 1])
        };
        (
            first + start,
            first + usize::from(self.ends[k]),
            usize::from(self.degrees[k]),
        )
    }

    /// The record of an all-parametric patch whose stages are all sparse Bézier stages (at most
    /// [`FAST_STAGES`] with at most `u16::MAX` terms in all; none: a stage-free patch), appending
    /// their terms to `terms`; `None` otherwise (the patch is then drawn through the kernel).
    fn new(eval: &ModelEval, patch: &PatchEntry, terms: &mut Vec<Term>) -> Option<FastPatch> {
        let s = patch.simplex as usize;
        let stages = eval.local_map(s).stages().len();
        if patch.guessed || patch.sparse.len() != stages || stages > FAST_STAGES {
            return None;
        }
        let model = eval.model();
        let n = model.dim();
        let ids = model.simplex(s);
        let f0 = model.values[ids[0] as usize];
        let mut df = [0.0; 3];
        for (k, d) in df.iter_mut().enumerate().take(n) {
            *d = model.values[ids[k + 1] as usize] - f0;
        }
        let edges = eval.inv_edges(s);
        let mut inv = [0.0; 9];
        for l in 0..n {
            for x in 0..n {
                inv[l * 3 + x] = edges[l][x];
            }
        }
        let mut values = [0.0; MAX_VARS];
        let mut vertices = [[0.0; 3]; MAX_VARS];
        for (i, &v) in ids.iter().enumerate() {
            values[i] = model.values[v as usize];
            vertices[i][..n].copy_from_slice(model.vertex(v as usize));
        }
        let first = u32::try_from(terms.len()).ok()?;
        let mut ends = [0; FAST_STAGES];
        let mut degrees = [0; FAST_STAGES];
        let mut end = 0usize;
        for (k, st) in patch.sparse.iter().enumerate() {
            end += st.terms.len();
            ends[k] = u16::try_from(end).ok()?;
            degrees[k] = u8::try_from(st.degree).ok()?;
        }
        for st in &patch.sparse {
            terms.extend_from_slice(&st.terms);
        }
        Some(FastPatch {
            simplex: patch.simplex,
            triangles: patch.triangles,
            stages: stages as u8,
            first,
            ends,
            degrees,
            linear_gradient: patch.linear_gradient,
            df,
            inv,
            values,
            vertices,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ism_format::Direction;

    /// 3,000 draws from `t` with a ChaCha8 stream of `seed`: one at a time through
    /// `SurfaceTable::draw`, or (`ahead`) through `draw_each`, which picks 8 slots ahead.
    fn draws(t: &SurfaceTable, eval: &ModelEval, seed: u64, ahead: bool) -> Vec<SurfacePoint> {
        use rand::SeedableRng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        if !ahead {
            return (0..3000).map(|_| t.draw(eval, &mut rng).unwrap()).collect();
        }
        let mut out = Vec::new();
        t.draw_each(eval, &mut rng, 3000, |p, _| {
            out.push(p);
            Ok(())
        })
        .unwrap();
        out
    }

    /// The spec example `name` (its JSON encoding).
    fn example(name: &str) -> ism_format::Model {
        let path = format!(
            "{}/../../spec/examples/{name}.ism.json",
            env!("CARGO_MANIFEST_DIR")
        );
        ism_format::io::read_path(path).unwrap().model
    }

    /// Every bit of a sample: position, normal, value and simplex.
    fn point_bits(p: &SurfacePoint) -> Vec<u64> {
        let mut v: Vec<u64> = p.p.iter().chain(&p.normal).map(|x| x.to_bits()).collect();
        v.push(p.value.to_bits());
        v.push(p.simplex as u64);
        v
    }

    /// A table sized for one sample keeps the root bounds of an all-parametric map (one region
    /// per triangle of each patch); sized for a million it refines them, so its bounded area is
    /// smaller; both bound the same curved area from above (the lattice's mean exact `J` per
    /// patch is below each patch's bounded area). Without a size, the fixed threshold.
    /// The fast records of all-parametric patches give the same draws, bit for bit, as the
    /// patch entries through the evaluator and the kernel's local maps (the truth: the same
    /// table with its fast records removed, so every draw takes the general branch), in 2D and
    /// 3D, weighted by curved and by linear area.
    #[test]
    fn fast_records_draw_the_same_bits_as_the_kernel_route() {
        for (name, sized) in [
            ("stratified-3d", Some(100_000)),
            ("stratified-3d", None),
            ("quadratic-edges", Some(10_000)),
            ("quadratic-edges", None),
        ] {
            let mut model = example(name);
            for stage in &mut model.stages {
                stage.direction = Direction::Parametric;
            }
            let eval = ModelEval::new(&model).unwrap();
            for weighting in [Weighting::CurvedArea, Weighting::LinearArea] {
                let table = SurfaceTable::with_expected_samples(&eval, weighting, sized).unwrap();
                assert!(!table.fast.is_empty(), "{name}: no fast record");
                let mut slow = table.clone();
                slow.fast.clear();
                // Picks drawn ahead: the slow table keeps `pick_ahead`, so both take the same
                // slots and must again give the same bits.
                assert!(table.pick_ahead, "{name}: a patch without a fast record");
                let (a, b) = (
                    draws(&table, &eval, 11, false),
                    draws(&slow, &eval, 11, false),
                );
                let (c, d) = (
                    draws(&table, &eval, 11, true),
                    draws(&slow, &eval, 11, true),
                );
                assert_eq!((a.len(), c.len()), (3000, 3000));
                for (x, y) in a.iter().zip(&b).chain(c.iter().zip(&d)) {
                    assert_eq!(point_bits(x), point_bits(y), "{name} {weighting:?}");
                }
            }
        }
    }

    /// The lattice of Newton starts is computed when first read: a table for one sample leaves
    /// most implicit patches without it (their bounds do not need it), and drawing computes the
    /// points its candidates start from ([`PatchEntry::start`]) in the patches it draws from. The
    /// draws are the same bits as from the same table with every lattice filled beforehand (the
    /// eager table of earlier versions), in 2D and 3D.
    #[test]
    fn lattices_are_computed_on_first_use_and_draw_the_same_bits() {
        use rand::SeedableRng;
        for (name, sized) in [("stratified-3d", 1), ("torus", 1), ("circle-curved", 1)] {
            let model = example(name);
            let eval = ModelEval::new(&model).unwrap();
            let lazy =
                SurfaceTable::with_expected_samples(&eval, Weighting::CurvedArea, Some(sized))
                    .unwrap();
            assert!(
                lazy.patches.iter().all(|p| p.guessed),
                "{name}: implicit chains"
            );
            // Patches with preimages computed: the whole lattice, or some of its points.
            let filled = |t: &SurfaceTable| {
                t.patches
                    .iter()
                    .filter(|p| {
                        p.lattice.get().is_some()
                            || p.starts
                                .get()
                                .is_some_and(|s| s.iter().any(|x| x.get().is_some()))
                    })
                    .count()
            };
            let before = filled(&lazy);
            assert!(
                2 * before < lazy.len(),
                "{name}: {before} of {} lattices computed for one sample",
                lazy.len()
            );
            let eager = lazy.clone();
            for p in &eager.patches {
                p.lattice(eval.local_map(p.simplex as usize));
            }
            let draw = |t: &SurfaceTable| {
                let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
                (0..200)
                    .map(|_| point_bits(&t.draw(&eval, &mut rng).unwrap()))
                    .collect::<Vec<_>>()
            };
            assert_eq!(draw(&lazy), draw(&eager), "{name}");
            let after = filled(&lazy);
            assert!(
                before < after,
                "{name}: {before} lattices before drawing, {after} after"
            );
        }
    }

    /// `stratified-3d` made parametric, its stages' moved points kept only on the faces that
    /// contain vertex `keep`: the simplices without that vertex have no stage at all (as fitted
    /// models leave the simplices no control point moves).
    fn partly_stage_free(keep: u32) -> ism_format::Model {
        let mut model = example("stratified-3d");
        for stage in &mut model.stages {
            stage.direction = Direction::Parametric;
            stage
                .faces
                .edit(|faces| faces.retain(|f| f.face.contains(&keep)));
        }
        model
    }

    /// A stage-free patch is drawn from its triangles with the bound 1 — the kernel's exact `J`
    /// there is 1 to rounding, checked on a lattice of each — while the staged patches of the
    /// same table keep their refined leaves; the fast records (stage-free ones included) draw the
    /// same bits as the general route, one pick at a time and eight ahead.
    #[test]
    fn stage_free_patches_are_their_triangles_with_bound_one() {
        let model = partly_stage_free(model_vertex_of_a_crossed_simplex());
        let eval = ModelEval::new(&model).unwrap();
        let table =
            SurfaceTable::with_expected_samples(&eval, Weighting::CurvedArea, Some(100_000))
                .unwrap();
        let (mut free, mut staged) = (0, 0);
        for p in &table.patches {
            let s = p.simplex as usize;
            let map = eval.local_map(s);
            if !map.stages().is_empty() {
                staged += 1;
                continue;
            }
            free += 1;
            assert_eq!(p.regions(), usize::from(p.triangles.max(1)));
            for r in &p.regions {
                assert_eq!(r.bound, 1.0);
                for k in 0..3 {
                    for l in 0..3 {
                        // Points of the region (corners and edge midpoints).
                        let u: Bary = std::array::from_fn(|x| 0.5 * (r.u[k][x] + r.u[l][x]));
                        let solved = map.param_solve(&u).unwrap();
                        let grad = eval.gradient_from_jacobian(s, &solved.jacobian);
                        let det = linalg::det(3, &solved.jacobian);
                        let j = norm(&grad[..3]) / (p.linear_gradient * det);
                        assert!((j - 1.0).abs() <= 1e-12, "simplex {s}: J = {j}");
                    }
                }
            }
            let fractions: f64 = p.regions.iter().map(|r| r.fraction).sum();
            assert!((fractions - 1.0).abs() <= 1e-15);
        }
        assert!(
            free > 0 && staged > 0,
            "{free} stage-free, {staged} staged patches"
        );
        assert!(table.pick_ahead, "a patch without a fast record");
        let mut slow = table.clone();
        slow.fast.clear();
        for ahead in [false, true] {
            let (a, b) = (
                draws(&table, &eval, 5, ahead),
                draws(&slow, &eval, 5, ahead),
            );
            let free_drawn = a
                .iter()
                .filter(|p| eval.local_map(p.simplex).stages().is_empty())
                .count();
            assert!(free_drawn > 0, "no sample on a stage-free patch");
            for (x, y) in a.iter().zip(&b) {
                assert_eq!(point_bits(x), point_bits(y), "ahead {ahead}");
            }
        }
    }

    /// The inlined identity is the kernel's, for every size the draw uses.
    #[test]
    fn inlined_identity_is_the_kernels() {
        for n in 0..=MAX_VARS {
            assert_eq!(identity(n), ism_geom::stage::identity_mat(n));
        }
    }

    /// A vertex of the first crossed simplex of `stratified-3d`.
    fn model_vertex_of_a_crossed_simplex() -> u32 {
        let model = example("stratified-3d");
        let eval = ModelEval::new(&model).unwrap();
        let s = (0..model.num_simplices())
            .find(|&s| eval.patch(s).is_some())
            .unwrap();
        model.simplex(s)[0]
    }

    #[test]
    fn a_table_sized_for_more_samples_is_tighter() {
        let mut model = example("stratified-3d");
        for stage in &mut model.stages {
            stage.direction = Direction::Parametric;
        }
        let eval = ModelEval::new(&model).unwrap();
        let table = |e| SurfaceTable::with_expected_samples(&eval, Weighting::CurvedArea, e);
        let one = table(Some(1)).unwrap();
        let many = table(Some(1_000_000)).unwrap();
        let fixed = table(None).unwrap();
        assert_eq!(one.len(), many.len());
        for p in &one.patches {
            assert_eq!(p.regions(), usize::from(p.triangles.max(1)));
        }
        let regions = |t: &SurfaceTable| t.patches.iter().map(PatchEntry::regions).sum::<usize>();
        assert!(regions(&many) > regions(&one) && regions(&fixed) > regions(&one));
        assert!(many.bounded_area < one.bounded_area);
        assert!(fixed.bounded_area < one.bounded_area);
        // The exact J on the lattice of each patch (the kernel's evaluation) stays below its
        // bound in either table.
        for t in [&one, &many] {
            for p in &t.patches {
                let s = p.simplex as usize;
                let map = eval.local_map(s);
                let lin = p.linear_gradient;
                for r in &p.regions {
                    for k in 0..3 {
                        let u = r.u[k];
                        let solved = map.param_solve(&u).unwrap();
                        let grad = eval.gradient_from_jacobian(s, &solved.jacobian);
                        let det = linalg::det(3, &solved.jacobian);
                        let j = norm(&grad[..3]) / (lin * det);
                        assert!(j <= r.bound * (1.0 + 1e-12), "J {j} > bound {}", r.bound);
                    }
                }
            }
        }
    }

    /// Implicit chains ([`CHAIN_EXCESS_SHARE`]): a table sized for one sample keeps each
    /// patch's chain bound as soon as it is finite (no tightening, no per-stage bound, no second
    /// pass), so it bounds more area than the table for a million samples; both stay certified —
    /// the exact `J` at the corners and centroid of every region (the kernel's own Newton inverse and Jacobian, not
    /// the table's enclosures) is below the region's bound — on the implicit examples, the
    /// torus' extreme weights included.
    #[test]
    fn implicit_chains_refine_only_for_enough_samples_and_stay_certified() {
        for name in ["stratified-3d", "sphere", "torus"] {
            let model = example(name);
            let eval = ModelEval::new(&model).unwrap();
            let table = |e| {
                SurfaceTable::with_expected_samples(&eval, Weighting::CurvedArea, Some(e)).unwrap()
            };
            let (one, many) = (table(1), table(1_000_000));
            assert!(
                one.patches.iter().all(|p| p.guessed),
                "{name}: implicit chains"
            );
            assert!(
                one.bounded_area > many.bounded_area,
                "{name}: the root bounds ({}) are looser than the refined ones ({})",
                one.bounded_area,
                many.bounded_area
            );
            let checked =
                assert_certified(name, &eval, &one) + assert_certified(name, &eval, &many);
            assert!(checked > 100, "{name}: {checked} points");
        }
    }

    /// Checks that every region's bound is at least the exact `J` (the kernel's Newton inverse
    /// and Jacobian, not the table's enclosures) at the region's corners and centroid, and
    /// returns the number of points checked.
    fn assert_certified(name: &str, eval: &ModelEval, table: &SurfaceTable) -> usize {
        let n = eval.dim();
        let mut checked = 0;
        for p in &table.patches {
            let s = p.simplex as usize;
            let map = eval.local_map(s);
            for r in &p.regions {
                let mut centroid = [0.0; MAX_VARS];
                for (k, c) in centroid.iter_mut().enumerate() {
                    *c = (r.u[0][k] + r.u[1][k] + r.u[2][k]) / 3.0;
                }
                for u in [r.u[0], r.u[1], r.u[2], centroid] {
                    let inv = map.inverse(&u);
                    assert!(inv.converged, "{name}: simplex {s}: no preimage of {u:?}");
                    let (_, jac) = map.jacobian(&inv.w);
                    let jac = jac.unwrap();
                    let grad = eval.gradient_from_jacobian(s, &jac);
                    let det = linalg::det(n, &jac);
                    let j = norm(&grad[..n]) / (p.linear_gradient * det);
                    assert!(
                        j <= r.bound * (1.0 + 1e-12),
                        "{name}: simplex {s}: J {j} > bound {}",
                        r.bound
                    );
                    checked += 1;
                }
            }
        }
        checked
    }

    /// The second pass in rounds: on the torus example the table for 10⁵ samples (fixed regions,
    /// no parts) bounds no more area with all rounds than with one, and stays certified. Measured
    /// before the per-cell bounds ([`CellBounds`]): 272.6 against 322.8; since, 103.5 both (the
    /// first round's cells leave nothing worth a later round on this model).
    #[test]
    fn later_rounds_of_the_second_pass_never_loosen_the_torus_table() {
        let model = example("torus");
        let eval = ModelEval::new(&model).unwrap();
        let build = |rounds| {
            SurfaceTable::build(&eval, Weighting::CurvedArea, Some(100_000), rounds, 0).unwrap()
        };
        let (one, all) = (build(1), build(REFINE_ROUNDS));
        eprintln!(
            "torus, 10^5 samples: bounded area {} with one round, {} with {REFINE_ROUNDS}",
            one.bounded_area, all.bounded_area
        );
        assert!(
            all.bounded_area <= one.bounded_area,
            "rounds: {} against one round's {}",
            all.bounded_area,
            one.bounded_area
        );
        assert!(assert_certified("torus", &eval, &all) > 100);
    }

    /// Parts of the fixed regions ([`split_regions`]) on the torus example, whose projective
    /// stage peaks in corners of its regions: the table for 10⁵ samples (first pass) has them; each part's
    /// corners are its fixed region's lattice corners weighted by `part` (what its Newton starts
    /// interpolate), its bound is at most the region's it came from — the same lattice triangle's
    /// unsplit bound in the table built without parts — and the shares still sum to one per
    /// patch; the table is certified at every part's corners and centroid (the kernel's exact
    /// `J`, [`assert_certified`]); and its bounded area is below the table's without parts.
    #[test]
    fn parts_of_regions_are_certified_and_start_from_their_regions_lattice() {
        let model = example("torus");
        let eval = ModelEval::new(&model).unwrap();
        let table =
            SurfaceTable::build(&eval, Weighting::CurvedArea, Some(100_000), 0, REGION_DEPTH)
                .unwrap();
        let mut parts = 0;
        for p in &table.patches {
            let map = eval.local_map(p.simplex as usize);
            let lattice = p.lattice(map);
            let shares: f64 = p.regions.iter().map(|r| r.fraction).sum();
            assert!((shares - 1.0).abs() < 1e-12, "shares sum to {shares}");
            for r in &p.regions {
                let Some(part) = r.part else { continue };
                parts += 1;
                let fixed = r.g.map(|k| lattice[usize::from(k)].0);
                for (weights, corner) in part.iter().zip(&r.u) {
                    let u = region_point(&fixed, weights, p.triangles);
                    for (x, y) in u.iter().zip(corner) {
                        assert!((x - y).abs() < 1e-15, "{u:?} vs {corner:?}");
                    }
                }
            }
        }
        assert!(parts > 1000, "{parts} parts");
        assert!(assert_certified("torus", &eval, &table) > 100_000);
        // The default table (with the second pass) too.
        let full = SurfaceTable::with_expected_samples(&eval, Weighting::CurvedArea, Some(100_000))
            .unwrap();
        assert!(full
            .patches
            .iter()
            .any(|p| p.regions.iter().any(|r| r.part.is_some())));
        assert!(assert_certified("torus", &eval, &full) > 100_000);
        // Parts never take more than their region: the same table without parts (the first pass
        // only in both, so the same chain and per-stage bounds; the fixed regions found by their
        // lattice corners `g`).
        let unsplit =
            SurfaceTable::build(&eval, Weighting::CurvedArea, Some(100_000), 0, 0).unwrap();
        for (a, b) in table.patches.iter().zip(&unsplit.patches) {
            assert_eq!(a.simplex, b.simplex);
            assert!(b.regions.iter().all(|r| r.part.is_none()));
            for r in &a.regions {
                let fixed = b.regions.iter().find(|f| f.g == r.g).unwrap();
                assert!(r.bound <= fixed.bound, "{} > {}", r.bound, fixed.bound);
                if r.part.is_none() {
                    assert_eq!(r.bound, fixed.bound);
                }
            }
        }
        eprintln!(
            "torus, 10^5 samples, first pass: {parts} parts; bounded area {} ({} without parts)",
            table.bounded_area, unsplit.bounded_area
        );
        assert!(table.bounded_area < 0.8 * unsplit.bounded_area);
    }

    /// The sparse form of a Bézier stage gives the kernel's value and reduced Jacobian (its
    /// dense evaluation, independent code) to rounding, on every stage of every simplex of
    /// 2D and 3D examples, at interior, face and vertex points.
    #[test]
    fn sparse_stage_equals_the_kernel_dense_stage() {
        let mut checked = 0;
        for name in [
            "stratified-3d",
            "quadratic-edges",
            "cubic-face-point",
            "two-stage",
        ] {
            let model = example(name);
            let eval = ModelEval::new(&model).unwrap();
            let m = model.dim() + 1;
            for s in 0..model.num_simplices() {
                for st in eval.local_map(s).stages() {
                    let Some(sparse) = SparseStage::new(st) else {
                        continue;
                    };
                    for w in [
                        [0.25, 0.25, 0.25, 0.25],
                        [0.1, 0.2, 0.3, 0.4],
                        [0.6, 0.3, 0.1, 0.0],
                        [0.0, 0.5, 0.5, 0.0],
                        [1.0, 0.0, 0.0, 0.0],
                        [0.05, 0.05, 0.1, 0.8],
                    ] {
                        let mut w = w;
                        if m == 3 {
                            let t = w[3];
                            w[3] = 0.0;
                            w[0] += t;
                        }
                        let (v0, j0) = st.jacobian_stored(&w);
                        let (v1, j1) = sparse.jacobian_stored(m, &w);
                        for i in 0..m {
                            assert!(
                                (v0[i] - v1[i]).abs() <= 1e-13,
                                "{name} {s}: value {v0:?} vs {v1:?}"
                            );
                        }
                        for i in 0..m - 1 {
                            for l in 0..m - 1 {
                                assert!(
                                    (j0[i][l] - j1[i][l]).abs() <= 1e-12 * (1.0 + j0[i][l].abs()),
                                    "{name} {s}: jacobian {j0:?} vs {j1:?}"
                                );
                            }
                        }
                        checked += 1;
                    }
                }
            }
        }
        assert!(checked > 100, "only {checked} points checked");
    }

    /// High degrees (the format allows up to `MAX_DEGREE` = 16): the sparse form of a
    /// parametric Bézier stage of degree 8 to 16 on a triangle, with every interior point moved,
    /// gives the kernel's dense value and reduced Jacobian to rounding (it indexed a fixed table
    /// of powers up to 7 and panicked from degree 8 on).
    #[test]
    fn sparse_stage_equals_the_kernel_dense_stage_up_to_the_maximum_degree() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for d in 8..=ism_format::structure::MAX_DEGREE {
            let owned = ism_format::multi_index::owned(3, d);
            // Identity positions K/d, moved along the first two coordinates by up to 1e-3 (the
            // coordinates keep summing to 1; small enough to stay a diffeomorphism).
            let points: Vec<f64> = owned
                .chunks(3)
                .flat_map(|k| {
                    let t = rng.random_range(-1e-3..1e-3);
                    let f = f64::from(d);
                    [
                        f64::from(k[0]) / f + t,
                        f64::from(k[1]) / f - t,
                        f64::from(k[2]) / f,
                    ]
                })
                .collect();
            let model = ism_format::builder::ModelBuilder::new(2)
                .vertex(&[0.0, 0.0], -1.0)
                .vertex(&[1.0, 0.0], 1.0)
                .vertex(&[0.0, 1.0], 1.0)
                .simplex(&[0, 1, 2])
                .stage(
                    ism_format::builder::StageBuilder::bezier(d)
                        .parametric()
                        .face(&[0, 1, 2], &points, &[])
                        .build(),
                )
                .build()
                .expect("a valid degree-{d} model");
            let eval = ModelEval::new(&model).unwrap();
            let st = &eval.local_map(0).stages()[0];
            let sparse = SparseStage::new(st).expect("a Bézier stage");
            assert!(!sparse.terms.is_empty());
            for w in [
                [1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0, 0.0],
                [0.1, 0.2, 0.7, 0.0],
                [0.0, 0.5, 0.5, 0.0],
                [1.0, 0.0, 0.0, 0.0],
            ] {
                let (v0, j0) = st.jacobian_stored(&w);
                let (v1, j1) = sparse.jacobian_stored(3, &w);
                for i in 0..3 {
                    assert!((v0[i] - v1[i]).abs() <= 1e-13, "d={d}: {v0:?} vs {v1:?}");
                }
                for i in 0..2 {
                    for l in 0..2 {
                        assert!(
                            (j0[i][l] - j1[i][l]).abs() <= 1e-12 * (1.0 + j0[i][l].abs()),
                            "d={d}: {j0:?} vs {j1:?}"
                        );
                    }
                }
            }
        }
    }

    /// The alias table selects entry `i` with probability `w_i / Σ w`: the probability each table
    /// implies (`(threshold_i + Σ_{j: alias_j = i} (1 − threshold_j)) / len`, summed exactly over
    /// the slots) matches the weights, for equal, skewed, tiny and single weights.
    #[test]
    fn alias_table_gives_each_entry_its_weight() {
        let cases: Vec<Vec<f64>> = vec![
            vec![1.0],
            vec![1.0; 7],
            vec![0.1, 5.0, 0.2, 3.0, 1e-9, 7.5],
            (1..200)
                .map(|i| f64::from(i).powi(3) % 17.0 + 1e-3)
                .collect(),
            vec![1e-300, 1.0, 1e300],
        ];
        for weights in cases {
            let total: f64 = weights.iter().sum();
            let table = alias_table(&weights, total);
            let len = weights.len() as f64;
            let mut implied = vec![0.0; weights.len()];
            for (slot, &(threshold, other)) in table.iter().enumerate() {
                assert!((0.0..=1.0).contains(&threshold), "threshold {threshold}");
                implied[slot] += threshold / len;
                implied[other as usize] += (1.0 - threshold) / len;
            }
            for (i, (&w, &p)) in weights.iter().zip(&implied).enumerate() {
                assert!(
                    (p - w / total).abs() <= 1e-12,
                    "entry {i}: probability {p}, weight share {}",
                    w / total
                );
            }
        }
    }

    /// The adjugate route (no inverse) gives the same `w`, `∇F` and area element as the inverse
    /// route of `LocalMap::param_solve` (LU inverse of `DY`), on every crossed simplex of 2D and
    /// 3D models with all stages turned parametric, at points of each patch.
    #[test]
    fn adjugate_route_equals_the_inverse_route() {
        let mut checked = 0;
        for name in ["stratified-3d", "quadratic-edges", "rational-degree5"] {
            let mut model = example(name);
            for stage in &mut model.stages {
                stage.direction = Direction::Parametric;
            }
            let eval = ModelEval::new(&model).unwrap();
            let n = model.dim();
            for s in 0..model.num_simplices() {
                let Some(patch) = eval.patch(s) else { continue };
                let map = eval.local_map(s);
                let c: Vec<Bary> = patch.corners.iter().map(|c| c.u).collect();
                for t in [0.0, 0.3, 0.5, 0.9] {
                    let mut u = [0.0; MAX_VARS];
                    for k in 0..=n {
                        u[k] = (1.0 - t) * c[0][k] + t * c[1][k];
                    }
                    let Some(solved) = map.param_solve(&u) else {
                        continue;
                    };
                    let (w, adj, det_dy) = param_adjugate(map, &u, &[]);
                    assert_eq!(w, solved.w);
                    let grad = eval.gradient_from_jacobian(s, &solved.jacobian);
                    let scaled = eval.gradient_from_jacobian(s, &adj);
                    let gn = norm(&grad[..n]);
                    for x in 0..n {
                        assert!((scaled[x] / det_dy - grad[x]).abs() <= 1e-10 * gn.max(1.0));
                    }
                    let j_inverse = gn / linalg::det(n, &solved.jacobian);
                    let j_adjugate = norm(&scaled[..n]);
                    assert!((j_inverse - j_adjugate).abs() <= 1e-10 * j_inverse);
                    checked += 1;
                }
            }
        }
        assert!(checked > 20, "only {checked} points checked");
    }
}
