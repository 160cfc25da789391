//! Adaptive polygonization of an implicit function (Mello & Velho 2009, §9.2, `spec/mathematics.md` §6).
//!
//! 1. The Kuhn triangulation of the domain box, `f = g/|∇g|` at the vertices ([`vertex_value`]), identity map.
//! 2. Topology: every cell whose bounding box fails the Plantinga–Vegter test
//!    (`0 ∉ □g` or `⟨□∇g, □∇g⟩ > 0`) is bisected until all pass, so no small component or
//!    handle hides inside a cell.
//! 3. Each sign-changing edge gets the edge-stratum point that moves the patch's corner onto the
//!    root of `g` on that edge; the other solitary points (edges without a crossing, triangles,
//!    tetrahedra) are optimized face by face, minimizing `Σ (g/|∇g|)²` over samples of the curved
//!    patches of the cells around the face.
//! 4. While the worst cell's error `max |g|/|∇g|` exceeds the tolerance, the worst cells are
//!    bisected (longest edge, with propagation), values set at the new vertices, and the points in
//!    the star of the new vertices re-optimized.

use std::collections::{HashMap, HashSet};
use std::time::Instant;

use ism_format::indexed::simplex_faces;
use ism_format::model::Model;
use ism_format::progress::{Progress, Step};
use rayon::prelude::*;

use crate::complex::{Complex, EdgeKey};
use crate::expr::ImplicitFunction;
use crate::isocontour::{patch_corners, patch_samples, topology, Bary, Topology};
use crate::measure::{measure_cached, Measure, MeasureCache, Miss};
use crate::rational::{RationalWeights, LOG_WEIGHT_BOUND};
use crate::strata::{
    displacement_derivative, edge_logits, LocalStrata, Slot, StratifiedMap, LOGIT_BOUND,
};
use crate::FitError;

/// Options of [`fit`].
#[derive(Clone, Debug)]
pub struct FitOptions {
    /// Domain box, `lo, hi` per axis.
    pub domain: Vec<f64>,
    /// Cells of the initial grid along the longest axis (others proportionally).
    pub resolution: usize,
    /// Target for the largest `|g|/|∇g|` on the shape.
    pub tolerance: f64,
    /// Stop refining at this many simplices even if the tolerance is not met.
    pub max_simplices: usize,
    /// Optimize the map (otherwise only the edge crossings are placed).
    pub optimize: bool,
    /// Also optimize the weights of a degree-2 rational stage ([`crate::rational`]) on the
    /// vertices and edges of crossing cells (with `optimize`). Off by default: on a fixed
    /// complex the weights cut the max error 1.3–13×, but each weight costs a face record, and the
    /// adaptive loop mostly reaches a tolerance with as few simplices without them (BENCHMARKS.md).
    pub rational: bool,
    /// Refine until every cell passes the Plantinga–Vegter test.
    pub topology: bool,
    /// The topology phase leaves cells whose longest edge is at most this long (0: no limit).
    /// For a mesh with creases the test fails near a crease at every cell size, so without a
    /// limit the phase would spend the whole simplex budget there; the mesh fit then checks the
    /// topology against the mesh's instead.
    pub pv_min_edge: f64,
    /// Before the two-sided measure, put every optimized point back at its face's centre (no
    /// record) where the crossed cells around it still meet the tolerance without it
    /// (`Fitter::prune`), crossing edges included. On by default: the sphere preset at 2e-3
    /// kept 1,442 of 4,424 records, 279 kB → 113 kB, on the same simplices (crossing edges
    /// kept, `f = g`); with the crossing edges prunable and `f = g/|∇g|`, 86 kB.
    pub prune: bool,
    /// The optimizer stops a parameter block once every residual at its samples is within this
    /// fraction of the tolerance ([`LM_DONE_FRACTION`] by default); 0: every block runs its
    /// iterations to the end (a fixed complex optimized as far as it goes, whatever the tolerance).
    pub lm_done_fraction: f64,
}

impl FitOptions {
    /// Defaults for a domain: resolution 8, tolerance 10⁻³ of the domain's largest side.
    pub fn new(domain: &[f64]) -> FitOptions {
        let size = domain.chunks(2).map(|c| c[1] - c[0]).fold(0.0, f64::max);
        FitOptions {
            domain: domain.to_vec(),
            resolution: 8,
            tolerance: 1e-3 * size,
            max_simplices: 200_000,
            optimize: true,
            rational: false,
            topology: true,
            pv_min_edge: 0.0,
            prune: true,
            lm_done_fraction: LM_DONE_FRACTION,
        }
    }
}

/// Reports a fit's step to `progress` (`done` = live simplices, `total` = the simplex budget,
/// `worst` = the largest cell error so far or NaN) and stops the fit when it was cancelled.
fn step(
    progress: &Progress,
    phase: &'static str,
    simplices: usize,
    options: &FitOptions,
    worst: f64,
) -> Result<(), FitError> {
    progress.report(&Step {
        phase,
        done: simplices as u64,
        total: options.max_simplices as u64,
        worst,
    });
    Ok(progress.check()?)
}

/// Summary of a fit.
#[derive(Clone, Debug, PartialEq)]
pub struct FitReport {
    /// Top simplices.
    pub simplices: usize,
    /// Vertices.
    pub vertices: usize,
    /// Simplices the shape passes through.
    pub crossing_simplices: usize,
    /// Stored real parameters of the stages (control point coordinates).
    pub parameters: usize,
    /// All numbers the model stores: coordinates, vertex ids, values, face ids and parameters.
    pub stored_numbers: usize,
    /// The two-sided distance between the fitted shape and the target as estimated, `max` of
    /// [`FitReport::measure`]'s two directions at their own points ([`Measure::max`]: a bound
    /// at those points, an estimate of the whole; [`Measure::max_bound`] bounds the whole).
    pub max_distance: f64,
    /// Mean of the `S → Z` bounds over the dense samples of the fitted shape.
    pub mean_distance: f64,
    /// Number of dense samples of the fitted shape.
    pub samples: usize,
    /// Both directions of the distance, how they were measured, and the error near
    /// [`FitReport::uncertain`].
    pub measure: Measure,
    /// Regions where the topology phase stopped at its smallest cell with the Plantinga–Vegter
    /// test still failing: singular points of `g` (crossings, cusps, isolated points, where
    /// `∇g` vanishes) or features below the tolerance. The topology is not certified there.
    pub uncertain: Vec<Uncertain>,
    /// Crossing cells at the smallest size the accuracy phase refines to
    /// ([`MIN_CELL_FRACTION`]) still above the tolerance.
    pub unresolved_cells: usize,
    /// Cells above the topology phase's smallest size still failing the Plantinga–Vegter test
    /// with the phase on: the simplex budget ran out before the topology was certified.
    pub pv_unfinished: usize,
    /// Two-sided measurements that found misses and refined there before the last one (0: the
    /// first measurement met the tolerance, or nothing could be refined).
    pub two_sided_rounds: usize,
    /// Refinement steps (edge bisections).
    pub bisections: usize,
    /// Cells of the final complex failing the Plantinga–Vegter test (0 = all pass; with the
    /// topology phase on, nonzero only when the simplex budget ran out).
    pub pv_failures: usize,
    /// Topology of `O` (= that of the linear isocomplex of the final complex).
    pub topology: Topology,
    /// Whether both directions of the two-sided distance are within the tolerance, as
    /// estimated ([`Measure::meets`]: `S → Z` at its samples plus its estimated error between
    /// them, `Z → S` at the points of its cover).
    pub tolerance_met: bool,
    /// Whether the Plantinga–Vegter test certified the topology (every cell passes).
    pub topology_certified: bool,
    /// Wall time in seconds.
    pub seconds: f64,
}

/// A cluster of cells where the topology could not be certified.
#[derive(Clone, Debug, PartialEq)]
pub struct Uncertain {
    /// Centre of the cells' bounding boxes.
    pub centre: Vec<f64>,
    /// Radius that holds the cells.
    pub radius: f64,
    /// Cells in the cluster.
    pub cells: usize,
    /// Whether the interval enclosure of `∇g` contains 0 on some of its cells: a singular point
    /// of `g` may be there (a crossing, a cusp, an isolated point).
    pub gradient_may_vanish: bool,
    /// Largest `S → Z` bound at samples in the region.
    pub shape_to_target: f64,
    /// Largest `Z → S` bound of the cover in the region.
    pub target_to_shape: f64,
}

/// The result of [`fit`].
#[derive(Clone, Debug)]
pub struct Fitted {
    /// The final complex.
    pub complex: Complex,
    /// `f` per vertex (`g/|∇g|`, with exact zeros nudged; see [`vertex_value`]).
    pub values: Vec<f64>,
    /// The fitted strata.
    pub map: StratifiedMap,
    /// The fitted rational weights (applied to `u` before the strata).
    pub weights: RationalWeights,
    /// The summary.
    pub report: FitReport,
}

/// Sample level of a patch while optimizing and ranking cells (segment points − 1 in 2D, grid
/// level per fan triangle in 3D): enough to see a cubic-like deviation, cheap enough for LM.
fn opt_level(n: usize) -> usize {
    if n == 2 {
        8
    } else {
        3
    }
}

/// Sample level for ranking cells against the tolerance: denser than the optimizer's, so a cell
/// that passes here rarely fails the dense report.
fn rank_level(n: usize) -> usize {
    if n == 2 {
        24
    } else {
        6
    }
}

/// The refinement and the pruning aim at this fraction of the tolerance: maxima between ranking
/// samples are up to ~10% higher in our runs (sphere, torus at level 6 vs 8), and the loop checks
/// the report's denser samples against the whole tolerance before it stops. 0.8, then 0.9
/// (session 11), now 0.95 with [`FIT_SWEEPS`] 4: sphere preset at 2e-3 86,076 -> 82,232 bytes
/// (estimate 1.84e-3 -> 1.91e-3), torus 271,275 -> 250,963 (1.88e-3 -> 1.92e-3); each alone:
/// margin 0.95 83,188 / 256,115, four sweeps 85,196 (sphere). The pruning must not aim higher
/// than the refinement: pruned cells that then fail the report samples are refined with every
/// point re-optimized (sphere at 0.9 / 0.8: 256 kB).
const TOLERANCE_MARGIN: f64 = 0.95;

/// Gauss–Seidel sweeps over a region's face points in [`Fitter::fit_region`]: 2 before; 4 reach
/// a better optimum on the same complex, so fewer cells fail and more records prune (see
/// [`TOLERANCE_MARGIN`]), for ~15 % more fit time on the torus.
const FIT_SWEEPS: usize = 4;

/// The optimizer stops a block's Levenberg–Marquardt iterations once every residual `|g|/|∇g|`
/// at its samples is within this fraction of the tolerance. Below it a step cannot change which
/// cells the accuracy loop refines (it refines above [`TOLERANCE_MARGIN`] of the tolerance, at
/// the denser ranking samples), and without a stop most blocks took all six iterations for ever
/// smaller gains: 92 % of the blocks changed in every sweep, 4.7 iterations each (torus preset at
/// 1e-4, issue 17 session 19). Measured at 1e-4 (session 19 notes): 0.25 fits the torus on 57,996
/// simplices (3,128,159 bytes) instead of 59,443 (3,160,979) and the sphere on 10,521 (843,360)
/// instead of 10,686 (843,768), both meeting the tolerance; 0.5 fits the sphere on 12,999
/// simplices (956,364 bytes), and a relative-decrease stop (1 %) on 13,686 (1,019,992): blocks
/// still above the tolerance stopped early.
pub const LM_DONE_FRACTION: f64 = 0.25;

/// Whether the fitter moves the interior control point of each crossed top simplex (the last
/// stratum, `G_n`). Off: the faces' points alone reach the tolerance on fewer simplices and the
/// file carries no record per crossed top simplex (see [`Fitter::fit_region`]).
const OPTIMIZE_TOP_INTERIOR: bool = false;

/// Sample level of the final dense report (shared with [`crate::measure`]).
fn report_level(n: usize) -> usize {
    crate::measure::report_level(n)
}

/// The topology phase does not split cells whose longest edge is at most this multiple of the
/// tolerance: at a singular point of `g` (a crossing, a cusp) the Plantinga–Vegter test fails at
/// every size, and bisecting it further only runs into degenerate simplices (issue 17: edge
/// determinant 0 after ~50 halvings). A feature smaller than this is within reach of the
/// two-sided measure, which reports it if it is missed.
pub const PV_MIN_CELL_FRACTION: f64 = 1.0;

/// ... or at most this fraction of the domain's longest side, whichever is smaller: a loose
/// tolerance still gets its topology certified down to features of this size.
pub const PV_MIN_CELL_OF_DOMAIN: f64 = 1.0 / 64.0;

/// The accuracy phase does not split crossing cells whose longest edge is below this multiple of
/// the tolerance: a cell that small which is still above the tolerance sits at a singular point
/// (where a linear patch cannot follow a crossing or a cusp) and is reported, not refined to
/// degeneracy.
pub const MIN_CELL_FRACTION: f64 = 0.01;

/// ... and not below this fraction of the domain's longest side (2⁻³⁰: some 20 halvings above
/// where coordinates of a Kuhn grid stop being distinct in double precision).
pub const MIN_CELL_OF_DOMAIN: f64 = 1.0 / (1u64 << 30) as f64;

/// Tolerances below this fraction of the domain's longest side are refused: cells would then be
/// split towards the resolution of double precision.
pub const MIN_TOLERANCE_FRACTION: f64 = 1e-12;

/// A cell's samples whose first-order estimate `|g|/|∇g|` is above this fraction of the
/// tolerance get the certified [`crate::measure::bracket_distance`] instead (too low where
/// `∇g` vanishes to higher order, as at the heart curve's (±1, 0)).
const BRACKET_ABOVE: f64 = 0.25;

/// Relative size of the value given to a vertex where `g` is exactly 0: the format needs
/// `f ≠ c`, and a tiny positive value keeps the crossing (numerically) at that vertex. Such a
/// vertex is treated as outside; this is deterministic and documented in the CLI help.
pub const ZERO_NUDGE: f64 = 1e-12;

/// Barycentric slack of [`Fitter::contains`] and of the box test of the Plantinga–Vegter split
/// (`simplex_test`): a point on a shared facet belongs to both cells (refining both is harmless),
/// and rounding must not put it in neither, nor drop a box that meets the cell.
const CONTAINS_SLACK: f64 = 1e-9;

/// Rounds of the two-sided accuracy loop: measure both directions on the model, refine where it
/// misses, re-fit. Each round costs a full measurement (most of a fit's time at fine
/// tolerances); misses that refinement cannot fix (a singular point at the minimum cell size)
/// end the loop earlier, as does [`FitOptions::max_simplices`].
pub const TWO_SIDED_ROUNDS: usize = 6;

/// `f(v)` for a vertex at `p`: the first-order signed distance `g(p)/|∇g(p)|` (just `g(p)` where
/// the gradient vanishes or is not finite), or `+ZERO_NUDGE · scale` where that is 0. Only the
/// signs fix the complex's crossings, but the values also place the linear patch's corner on
/// each crossing edge (`t* = f_a/(f_a − f_b)`): on a first-order distance it lies next to `g`'s
/// root where the shape is smooth, so many crossing edges need no record of their own (see
/// [`Fitter::prune`]). With `g` itself (a quartic for the torus) the corner is off by about the
/// tolerance on almost every edge. Sphere preset at 2e-3: 113,000 → 95,524 bytes, torus
/// 420,255 → 292,311 (BENCHMARKS.md, issue 17).
pub fn vertex_value(g: &dyn ImplicitFunction, p: &[f64], scale: f64) -> f64 {
    let mut grad = [0.0; 3];
    let n = g.dim();
    let v = g.gradient(p, &mut grad[..n]);
    let norm = grad[..n].iter().map(|x| x * x).sum::<f64>().sqrt();
    let v = if norm > 0.0 && norm.is_finite() {
        v / norm
    } else {
        v
    };
    if v == 0.0 || !v.is_finite() {
        ZERO_NUDGE * scale.max(f64::MIN_POSITIVE)
    } else {
        v
    }
}

struct Fitter<'a> {
    g: &'a dyn ImplicitFunction,
    n: usize,
    complex: Complex,
    values: Vec<f64>,
    map: StratifiedMap,
    weights: RationalWeights,
    /// Per sign-changing edge `(a, b)`: the linear crossing `t*` and the root of `g`, both as the
    /// weight of `b` (values never change, so neither does this).
    roots: HashMap<EdgeKey, (f64, f64)>,
    rational: bool,
    scale: f64,
    /// The domain's diagonal: how far a distance bound searches.
    reach: f64,
    bisections: usize,
    /// The first point where `g` was not finite, or the first sign change without a root: the
    /// fit stops with this error at the next check.
    trouble: Option<FitError>,
    /// [`Fitter::cell_error`] of crossing cells at [`rank_level`] and at [`report_level`], kept
    /// until a face of the cell (or, with rational weights, a vertex's weight) changes: the
    /// accuracy loop ranks every crossing cell after each refinement, and most of them were not
    /// touched by it (issue 17, session 16: re-checking them was ~15 % of a torus fit). A cell's
    /// error depends only on its vertices, their values, and its faces' points and weights, and
    /// cells are never renumbered (a refined cell dies, its children are new ids).
    errors: [HashMap<u32, f64>; 2],
    /// [`Fitter::pv_passes`] of every cell tested so far. The test reads only `g` and the cell's
    /// vertex coordinates, which never change for a cell id (a refined cell dies, its children are
    /// new ids), so each cell is tested once per fit: the topology phase re-tested every live cell
    /// after each refinement, and the status check every cell after each two-sided round (the
    /// Stanford bunny's 3,000 failing cells, 64 sub-boxes each, four times: issue 17, session 20).
    pv: HashMap<u32, bool>,
    /// [`FitOptions::lm_done_fraction`] of the tolerance: [`Fitter::optimize`] stops when every
    /// residual of a block is at most this.
    lm_done: f64,
}

/// One optimizable parameter block of the fitter.
#[derive(Clone, Copy, Debug)]
enum Param<'f> {
    /// The solitary point of a face of ≥ 2 vertices (logits).
    Point(&'f [u32]),
    /// The rational weight of a vertex or an edge (one log-weight).
    Weight(&'f [u32]),
}

/// A parameter block's mapped sample points as a function of its parameter: what
/// [`Fitter::levenberg_marquardt`] moves.
trait BlockMap {
    /// The mapped sample points with the parameter at `x`.
    fn points(&mut self, x: &[f64]) -> Vec<[f64; 3]>;
    /// `jac[j][i] = n̂ᵢ · ∂pᵢ/∂xⱼ` at `x`, where the points are `pts` and their unit normals
    /// `normals`.
    fn jacobian(&mut self, x: &[f64], pts: &[[f64; 3]], normals: &[[f64; 3]], jac: &mut [Vec<f64>]);
}

/// A face's point over its crossing cells, each cell's map built once with a slot for the face
/// ([`StratifiedMap::local_with`]) and the map before the face's stratum applied to the samples
/// (`before`): a trial moves only the slot. Writes nothing shared, so blocks run in parallel.
struct FacePoint<'f, 'a> {
    fitter: &'f Fitter<'a>,
    cells: &'f [u32],
    locals: Vec<(LocalStrata, Slot, Vec<Bary>)>,
}

impl BlockMap for FacePoint<'_, '_> {
    fn points(&mut self, x: &[f64]) -> Vec<[f64; 3]> {
        let mut out = Vec::new();
        for (&c, (local, slot, before)) in self.cells.iter().zip(&mut self.locals) {
            local.set_point(*slot, x);
            let ids = self.fitter.complex.cell(c);
            out.extend(
                before
                    .iter()
                    .map(|v| self.fitter.point_of(ids, &local.eval_after(v, Some(*slot)))),
            );
        }
        out
    }

    /// The exact derivative of the map in the face's logits.
    fn jacobian(
        &mut self,
        x: &[f64],
        _pts: &[[f64; 3]],
        normals: &[[f64; 3]],
        jac: &mut [Vec<f64>],
    ) {
        let mut i = 0;
        let mut dw = [[0.0; 4]; 4];
        let dd = displacement_derivative(x);
        for (&c, (local, slot, before)) in self.cells.iter().zip(self.locals.iter_mut()) {
            local.set_point(*slot, x);
            let ids = self.fitter.complex.cell(c);
            for v in before.iter() {
                local.eval_after_jacobian(v, *slot, &dd, &mut dw);
                for (col, d) in jac.iter_mut().zip(&dw) {
                    let dp = self.fitter.point_of(ids, d);
                    col[i] = (0..3).map(|e| normals[i][e] * dp[e]).sum::<f64>();
                }
                i += 1;
            }
        }
    }
}

/// Any parameter (a weight moves the crossings too) through the whole map, set in place per trial.
struct WholeMap<'f, 'a> {
    fitter: &'f Fitter<'a>,
    param: Param<'f>,
    /// The sign-changing edges a weight acts on (their crossings are re-placed).
    edges: &'f [EdgeKey],
    cells: &'f [u32],
    samples: &'f [Vec<Bary>],
    map: &'f mut StratifiedMap,
    weights: &'f mut RationalWeights,
}

impl BlockMap for WholeMap<'_, '_> {
    fn points(&mut self, x: &[f64]) -> Vec<[f64; 3]> {
        self.fitter.block_points(
            self.param,
            x,
            self.edges,
            self.cells,
            self.samples,
            self.map,
            self.weights,
        )
    }

    /// Forward differences of the whole map.
    fn jacobian(
        &mut self,
        x: &[f64],
        pts: &[[f64; 3]],
        normals: &[[f64; 3]],
        jac: &mut [Vec<f64>],
    ) {
        const H: f64 = 1e-7;
        for (j, col) in jac.iter_mut().enumerate() {
            let mut xh = x.to_vec();
            xh[j] += H;
            let ph = self.points(&xh);
            for (i, v) in col.iter_mut().enumerate() {
                *v = (0..3)
                    .map(|d| normals[i][d] * (ph[i][d] - pts[i][d]))
                    .sum::<f64>()
                    / H;
            }
        }
    }
}

/// A block's run in a parallel level of [`Fitter::fit_region`]'s sweeps, applied in serial order.
enum Run {
    /// Skipped: idle since its last run (checked again when applied, on the same stamps).
    Skipped,
    /// A face point's new logits and whether they moved.
    Done((Vec<f64>, bool)),
}

/// A parameter block of [`Fitter::fit_region`]: the parameter, its crossing cells, their samples.
type Block<'f> = (Param<'f>, Vec<u32>, Vec<Vec<Bary>>);

/// The schedule of [`Fitter::fit_region`]'s `sweeps` passes over `blocks` ([`conflict_levels`]
/// of the nodes `sweep × blocks.len() + block`): a weight re-places crossings on its star, so it
/// runs alone.
fn sweep_levels(blocks: &[Block], sweeps: usize) -> Vec<Vec<usize>> {
    let nb = blocks.len();
    conflict_levels((0..sweeps * nb).map(|node| {
        let (param, cells, _) = &blocks[node % nb];
        (&cells[..], matches!(param, Param::Weight(_)))
    }))
}

/// A parallel schedule of steps that must seem to run in the given order, where a step reads
/// and writes only what belongs to its cells (`(cells, alone)` per step): the step indices by
/// level, each level in increasing order. A step's level is one more than the highest level of
/// an earlier step sharing a cell with it, so the steps of a level share no cell and every
/// earlier step that does is in an earlier level: running the levels in order, the steps of a
/// level in any order (or at once), reads and writes what the serial order does. A step marked
/// `alone` is a level of its own after everything before it, and everything after comes later.
fn conflict_levels<'c>(steps: impl Iterator<Item = (&'c [u32], bool)>) -> Vec<Vec<usize>> {
    let mut last: HashMap<u32, usize> = HashMap::new();
    // The last lone step's level (levels count from 1 here).
    let mut floor = 0;
    let mut levels: Vec<Vec<usize>> = Vec::new();
    for (i, (cells, alone)) in steps.enumerate() {
        let level = if alone {
            floor = levels.len() + 1;
            floor
        } else {
            1 + cells
                .iter()
                .filter_map(|c| last.get(c).copied())
                .fold(floor, usize::max)
        };
        for &c in cells {
            last.insert(c, level);
        }
        if levels.len() < level {
            levels.resize(level, Vec::new());
        }
        levels[level - 1].push(i);
    }
    levels
}

/// The fitter's whole map on one cell: the rational stage, then the strata.
fn local_of(map: &StratifiedMap, weights: &RationalWeights, ids: &[u32]) -> LocalStrata {
    map.local(ids).after(weights.local(ids))
}

/// Sets the edge-stratum point of the sign-changing edge `e` so that the whole map sends the
/// linear crossing onto the root of `g`. On the edge the strata above the first are the identity
/// and the map is `t ↦ y(R_e(t))` with `y(s) = s + (2α − 1)·s(1 − s)`, so
/// `α = ½ + (root − s)/(2s(1 − s))` at `s = R_e(t*)`.
fn place_crossing(
    roots: &HashMap<EdgeKey, (f64, f64)>,
    weights: &RationalWeights,
    map: &mut StratifiedMap,
    e: EdgeKey,
) {
    let Some(&(t, root)) = roots.get(&e) else {
        return;
    };
    let s = weights.edge(e.0, e.1, t);
    let alpha = 0.5 + (root - s) / (2.0 * s * (1.0 - s)).max(f64::MIN_POSITIVE);
    map.set_logits(&[e.0, e.1], &edge_logits(alpha));
}

impl<'a> Fitter<'a> {
    /// The fitter on the options' initial grid, before any vertex value.
    fn new(g: &'a dyn ImplicitFunction, options: &FitOptions) -> Fitter<'a> {
        let n = g.dim();
        let complex = Complex::kuhn(
            &options.domain,
            &grid_cells(&options.domain, options.resolution),
        );
        let scale = (0..complex.num_vertices() as u32)
            .map(|v| g.value(complex.point(v)).abs())
            .filter(|x| x.is_finite())
            .fold(0.0, f64::max);
        Fitter {
            g,
            n,
            complex,
            values: Vec::new(),
            map: StratifiedMap::new(n),
            weights: RationalWeights::new(n),
            roots: HashMap::new(),
            rational: options.rational,
            scale,
            reach: options
                .domain
                .chunks(2)
                .map(|c| (c[1] - c[0]).powi(2))
                .sum::<f64>()
                .sqrt(),
            bisections: 0,
            trouble: None,
            errors: [HashMap::new(), HashMap::new()],
            pv: HashMap::new(),
            lm_done: options.lm_done_fraction * options.tolerance,
        }
    }
}

impl Fitter<'_> {
    fn is_crossing(&self, c: u32) -> bool {
        let ids = self.complex.cell(c);
        let neg = ids.iter().any(|&v| self.values[v as usize] < 0.0);
        let pos = ids.iter().any(|&v| self.values[v as usize] > 0.0);
        neg && pos
    }

    fn crossing_cells(&self) -> Vec<u32> {
        self.complex
            .live_cells()
            .into_iter()
            .filter(|&c| self.is_crossing(c))
            .collect()
    }

    fn point_of(&self, cell: &[u32], w: &Bary) -> [f64; 3] {
        let mut p = [0.0; 3];
        for (i, &v) in cell.iter().enumerate() {
            for (k, x) in self.complex.point(v).iter().enumerate() {
                p[k] += w[i] * x;
            }
        }
        p
    }

    /// The cell's error: `|g|/|∇g|` at its samples, replaced by the certified
    /// [`crate::measure::bracket_distance`] where that estimate is not small.
    fn cell_error(&self, c: u32, level: usize, tolerance: f64) -> f64 {
        let local = local_of(&self.map, &self.weights, self.complex.cell(c));
        self.cell_error_of(c, &local, level, tolerance)
    }

    /// [`Fitter::cell_error`] with the cell's map `local`.
    fn cell_error_of(&self, c: u32, local: &LocalStrata, level: usize, tolerance: f64) -> f64 {
        let ids = self.complex.cell(c);
        let s: Vec<f64> = ids.iter().map(|&v| self.values[v as usize]).collect();
        let corners: Vec<Bary> = patch_corners(&s).into_iter().map(|x| x.0).collect();
        let mut worst = 0.0f64;
        for u in patch_samples(&corners, level) {
            let p = self.point_of(ids, &local.eval(&u));
            let estimate = self.g.distance_estimate(&p[..self.n]);
            let d = if estimate > BRACKET_ABOVE * tolerance {
                self.g.distance_bound(&p[..self.n], self.reach)
            } else {
                estimate
            };
            worst = worst.max(if d.is_nan() { f64::INFINITY } else { d });
        }
        worst
    }

    /// [`Fitter::cell_error`] of every crossing cell with a longest edge of at least `min_cell`,
    /// at the ranking (`report = false`) or the report level, from the cache where the cell is
    /// unchanged since it was last computed (the same number: the inputs are the same).
    fn cell_errors(&mut self, min_cell: f64, report: bool, tolerance: f64) -> Vec<(u32, f64)> {
        let slot = usize::from(report);
        let out: Vec<(u32, f64)> = {
            let f = &*self;
            let level = if report {
                report_level(f.n)
            } else {
                rank_level(f.n)
            };
            f.crossing_cells()
                .into_par_iter()
                .filter(|&c| f.longest_edge_length(c) >= min_cell)
                .map(|c| match f.errors[slot].get(&c) {
                    Some(&e) => {
                        // The unit tests' fits check every cached value against a fresh one.
                        #[cfg(test)]
                        assert_eq!(
                            e.to_bits(),
                            f.cell_error(c, level, tolerance).to_bits(),
                            "stale cached error of cell {c}"
                        );
                        (c, e)
                    }
                    None => (c, f.cell_error(c, level, tolerance)),
                })
                .collect()
        };
        self.errors[slot].extend(out.iter().copied());
        out
    }

    /// Forgets the cached errors of the cells with the face `face` (sorted ids).
    fn forget_face(&mut self, face: &[u32]) {
        let cells: Vec<u32> = self
            .complex
            .cells_around(face[0], face[1])
            .iter()
            .copied()
            .filter(|&c| face.iter().all(|v| self.complex.cell(c).contains(v)))
            .collect();
        for c in cells {
            for cache in &mut self.errors {
                cache.remove(&c);
            }
        }
    }

    fn longest_edge_length(&self, c: u32) -> f64 {
        let (a, b) = self.complex.longest_edge(c);
        let (pa, pb) = (self.complex.point(a), self.complex.point(b));
        pa.iter()
            .zip(pb)
            .map(|(x, y)| (x - y) * (x - y))
            .sum::<f64>()
            .sqrt()
    }

    /// The Plantinga–Vegter test on cell `c`: `0 ∉ □g(C)`, or `⟨□∇g(C), □∇g(C)⟩ > 0` (no two
    /// gradients in `C` orthogonal or opposed). The enclosures are over boxes that cover `C`:
    /// first its bounding box; when that fails, the [`PV_SPLIT`]`ⁿ` parts of the box that meet
    /// the simplex (a part that lies beyond one of its facets is left out), with `□∇g` the hull
    /// over them. Both cover `C`, so both are sound; the parts hug the simplex, which fills only
    /// `1/n!` of its box (a Kuhn cell lies along the box's diagonal), so fewer cells fail that
    /// contain no zero, and the gradient's range is taken over less.
    fn pv_passes(&self, c: u32) -> bool {
        let (lo, hi) = self.complex.bounding_box(c);
        let Some(enc) = self.g.enclose(&lo, &hi) else {
            return true;
        };
        if !enc.value.contains(0.0) || gradients_agree(&enc.gradient) {
            return true;
        }
        let n = self.n;
        let Some(inside) = simplex_test(&self.complex, c) else {
            return false;
        };
        let m = PV_SPLIT;
        let mut hull: Vec<Option<(f64, f64)>> = vec![None; n];
        let mut zero = false;
        let (mut l, mut h) = (vec![0.0; n], vec![0.0; n]);
        for idx in 0..m.pow(n as u32) {
            sub_box(&lo, &hi, m, idx, &mut l, &mut h);
            if !inside(&l, &h) {
                continue;
            }
            let Some(e) = self.g.enclose(&l, &h) else {
                return false;
            };
            zero |= e.value.contains(0.0) || e.value.lo.is_nan();
            for (acc, gk) in hull.iter_mut().zip(&e.gradient) {
                let (a, b) = (gk.lo, gk.hi);
                if a.is_nan() || b.is_nan() {
                    return false;
                }
                *acc = Some(acc.map_or((a, b), |(x, y)| (x.min(a), y.max(b))));
            }
        }
        if !zero {
            return true;
        }
        let gradient: Vec<crate::interval::Interval> = hull
            .iter()
            .map(|x| {
                x.map_or(crate::interval::Interval::ENTIRE, |(a, b)| {
                    crate::interval::Interval::new(a, b)
                })
            })
            .collect();
        gradients_agree(&gradient) || self.generators_agree(&lo, &hi, &inside)
    }

    /// The cells of `cells` that fail [`Fitter::pv_passes`], in their order: cells not tested
    /// before in parallel, the others from [`Fitter::pv`] (under `cfg(test)` re-tested and checked
    /// to give the same answer).
    fn pv_failing(&mut self, cells: Vec<u32>) -> Vec<u32> {
        let fresh: Vec<(u32, bool)> = {
            let f = &*self;
            cells
                .par_iter()
                .filter(|c| !f.pv.contains_key(c))
                .map(|&c| (c, f.pv_passes(c)))
                .collect()
        };
        #[cfg(test)]
        {
            let f = &*self;
            cells.par_iter().for_each(|c| {
                if let Some(&known) = f.pv.get(c) {
                    assert_eq!(known, f.pv_passes(*c), "cached PV status of cell {c}");
                }
            });
        }
        self.pv.extend(fresh);
        cells.into_iter().filter(|c| !self.pv[c]).collect()
    }

    /// The Plantinga–Vegter test from the function's gradient generators over the sub-boxes of
    /// `[lo, hi]` that meet the cell (see [`ImplicitFunction::gradient_generators`]); `false`
    /// when it has none.
    fn generators_agree(
        &self,
        lo: &[f64],
        hi: &[f64],
        inside: &impl Fn(&[f64], &[f64]) -> bool,
    ) -> bool {
        let n = self.n;
        let m = PV_SPLIT;
        let mut generators = Vec::new();
        let (mut l, mut h) = (vec![0.0; n], vec![0.0; n]);
        for idx in 0..m.pow(n as u32) {
            sub_box(lo, hi, m, idx, &mut l, &mut h);
            if inside(&l, &h) && !self.g.gradient_generators(&l, &h, &mut generators) {
                return false;
            }
        }
        // Neighbouring sub-boxes give mostly the same vectors: each once (bit-equal copies).
        let mut unique: Vec<&[f64]> = generators.chunks_exact(n).collect();
        unique.sort_unstable_by(|a, b| {
            a.iter()
                .zip(*b)
                .map(|(x, y)| x.total_cmp(y))
                .find(|o| o.is_ne())
                .unwrap_or(std::cmp::Ordering::Equal)
        });
        unique.dedup();
        unit_vectors_agree(n, &unique.concat())
    }

    fn set_values_for_new_vertices(&mut self) {
        for v in self.values.len()..self.complex.num_vertices() {
            let p = self.complex.point(v as u32).to_vec();
            let raw = self.g.value(&p);
            if !raw.is_finite() && self.trouble.is_none() {
                self.trouble = Some(FitError::Undefined {
                    point: p.clone(),
                    value: raw,
                });
            }
            let x = vertex_value(self.g, &p, self.scale);
            self.values.push(x);
        }
    }

    /// The first problem with `g` met so far (see [`Fitter::trouble`]).
    fn check(&mut self) -> Result<(), FitError> {
        self.trouble.take().map_or(Ok(()), Err)
    }

    fn refine(&mut self, c: u32) -> Vec<u32> {
        let added = self.complex.refine(c);
        self.bisections += added.len();
        self.set_values_for_new_vertices();
        added
    }

    fn is_crossing_edge(&self, e: EdgeKey) -> bool {
        (self.values[e.0 as usize] < 0.0) != (self.values[e.1 as usize] < 0.0)
    }

    /// Finds the root of `g` on a sign-changing edge (once) and puts the edge-stratum point where
    /// it maps the patch corner onto it ([`place_crossing`]).
    fn init_crossing_edge(&mut self, e: EdgeKey) {
        if !self.roots.contains_key(&e) {
            let found = self.edge_root(e);
            if let Err(trouble) = self.root_is_a_zero(e, found.1) {
                self.trouble.get_or_insert(trouble);
            }
            self.roots.insert(e, found);
        }
        place_crossing(&self.roots, &self.weights, &mut self.map, e);
    }

    /// `(t*, root)` of a sign-changing edge, both as the weight of its second vertex.
    fn edge_root(&self, e: EdgeKey) -> (f64, f64) {
        let (fa, fb) = (self.values[e.0 as usize], self.values[e.1 as usize]);
        let t = fa / (fa - fb);
        let pa = self.complex.point(e.0).to_vec();
        let pb = self.complex.point(e.1).to_vec();
        let at = |s: f64| -> f64 {
            let p: Vec<f64> = pa.iter().zip(&pb).map(|(a, b)| a + s * (b - a)).collect();
            self.g.value(&p)
        };
        // Bisection: the values at the ends have opposite signs by construction (the nudged zero
        // counts as positive, like its value).
        let (mut lo, mut hi) = (0.0f64, 1.0f64);
        let neg_at_lo = fa < 0.0;
        for _ in 0..60 {
            let mid = 0.5 * (lo + hi);
            let v = at(mid);
            if (v < 0.0) == neg_at_lo {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        (t, 0.5 * (lo + hi))
    }

    /// Whether the sign change that bisection found at weight `root` of edge `e` is a zero of `g`.
    /// A continuous `g` is tiny there (bisection stops at 2⁻⁶⁰ of the edge); at or near a pole or
    /// a jump `|g|` exceeds its values at the edge's ends; NaN means `g` is undefined there.
    fn root_is_a_zero(&self, e: EdgeKey, root: f64) -> Result<(), FitError> {
        let pa = self.complex.point(e.0).to_vec();
        let pb = self.complex.point(e.1).to_vec();
        let near: Vec<f64> = pa
            .iter()
            .zip(&pb)
            .map(|(a, b)| a + root * (b - a))
            .collect();
        let v = self.g.value(&near);
        if v.is_nan() {
            return Err(FitError::Undefined {
                point: near,
                value: v,
            });
        }
        // Bisection may land exactly on a pole (∞) or next to it (huge): neither is a zero.
        // Tiny values (a zero of high order) are a zero whatever the ends say: the ends' values
        // are then tiny too, and rounding orders them arbitrarily.
        let ends = self.g.value(&pa).abs().max(self.g.value(&pb).abs());
        if v.abs() > ends && v.abs() > ZERO_NUDGE * self.scale {
            return Err(FitError::NoRoot {
                from: pa,
                to: pb,
                near,
                value: v.abs(),
            });
        }
        Ok(())
    }

    fn faces_of(&self, c: u32) -> Vec<Vec<u32>> {
        crate::hermite::faces_of(self.complex.cell(c))
    }

    fn crossing_cells_with_face(&self, face: &[u32]) -> Vec<u32> {
        self.complex
            .cells_around(face[0], face[1])
            .iter()
            .copied()
            .filter(|&c| {
                self.is_crossing(c) && face.iter().all(|v| self.complex.cell(c).contains(v))
            })
            .collect()
    }

    /// Initializes the crossing edges of `cells` and optimizes every other face point of them but
    /// the top simplices' interior points ([`OPTIMIZE_TOP_INTERIOR`]).
    fn fit_region(&mut self, cells: &[u32], optimize: bool) {
        let mut faces: Vec<Vec<u32>> = Vec::new();
        let mut seen = HashSet::new();
        for &c in cells {
            if !self.complex.is_alive(c) || !self.is_crossing(c) {
                continue;
            }
            for f in self.faces_of(c) {
                if seen.insert(f.clone()) {
                    faces.push(f);
                }
            }
        }
        faces.sort();
        for f in &faces {
            self.forget_face(f);
        }
        for f in &faces {
            if f.len() == 2 && self.is_crossing_edge((f[0], f[1])) {
                self.init_crossing_edge((f[0], f[1]));
            }
        }
        if !optimize {
            return;
        }
        // Weights sit on the vertices and edges of the region's crossing cells; a vertex's
        // weight acts on every crossing cell around it, in the region or not.
        let mut weighted: Vec<Vec<u32>> = Vec::new();
        let mut star: HashMap<u32, Vec<u32>> = HashMap::new();
        if self.rational {
            let mut vertices: Vec<u32> = faces
                .iter()
                .filter(|f| f.len() == 2)
                .flat_map(|f| f.iter().copied())
                .collect();
            vertices.sort_unstable();
            vertices.dedup();
            let wanted: HashSet<u32> = vertices.iter().copied().collect();
            for c in self.crossing_cells() {
                for &v in self.complex.cell(c) {
                    if wanted.contains(&v) {
                        star.entry(v).or_default().push(c);
                    }
                }
            }
            // A vertex's weight bends every crossing cell around it.
            for cells in star.values() {
                for c in cells {
                    for cache in &mut self.errors {
                        cache.remove(c);
                    }
                }
            }
            weighted.extend(vertices.into_iter().map(|v| vec![v]));
            weighted.extend(faces.iter().filter(|f| f.len() == 2).cloned());
        }
        // The blocks and their cells and samples: the sweeps move points only, so these stay.
        let mut blocks: Vec<Block> = Vec::new();
        for f in &faces {
            if f.len() == 2 && self.is_crossing_edge((f[0], f[1])) {
                continue;
            }
            // The interior point of a top simplex stays at its centre (no record): it bends
            // one cell only, and measured with and without it (issue 17 notes, `ism fit
            // --preset sphere --tolerance 2e-3`) the fits without it meet the same
            // tolerance on fewer cells — 1,085 crossed tetrahedra instead of 1,481,
            // 279 kB instead of 471 kB — since each such record costs 72 bytes.
            if f.len() == self.n + 1 && !OPTIMIZE_TOP_INTERIOR {
                continue;
            }
            let cells = self.crossing_cells_with_face(f);
            let samples = self.cell_samples(&cells);
            blocks.push((Param::Point(f), cells, samples));
        }
        for f in &weighted {
            let cells = if f.len() == 1 {
                star.get(&f[0]).cloned().unwrap_or_default()
            } else {
                self.crossing_cells_with_face(f)
            };
            let samples = self.cell_samples(&cells);
            blocks.push((Param::Weight(f), cells, samples));
        }
        // Gauss–Seidel sweeps: faces couple only through shared cells, so later passes let each
        // parameter see its neighbours' updates. A block whose last run left its parameter where
        // it was is skipped while no parameter of its cells has moved since: `optimize` reads only
        // the map and the weights on those cells, so it would leave it there again (bit for bit).
        // A parameter acts on the crossing cells of its block only (a point on the cells with its
        // face, a weight on its star), so a change stamps exactly those.
        //
        // The sweeps run in the serial order above, but level by level (`sweep_levels`): blocks
        // of one level share no cell, so each reads the same map whichever runs first, and they
        // run in parallel; their results are applied in serial order before the next level. So
        // the fit is bit for bit the serial Gauss–Seidel one for any number of threads.
        let levels = sweep_levels(&blocks, FIT_SWEEPS);
        let nb = blocks.len();
        // The serial position (1-based: sweep × blocks + block + 1) of the last run of a block
        // that moved a cell's parameters, and of each block's last run that did not move.
        let mut moved: HashMap<u32, usize> = HashMap::new();
        let mut idle: Vec<Option<usize>> = vec![None; nb];
        for level in &levels {
            let skipped = |node: usize, idle: &[Option<usize>], moved: &HashMap<u32, usize>| {
                idle[node % nb].is_some_and(|since| {
                    blocks[node % nb]
                        .1
                        .iter()
                        .all(|c| moved.get(c).is_none_or(|&at| at < since))
                })
            };
            let runs: Vec<Option<Run>> = if level.len() == 1 {
                // One block (or a weight, alone by construction): run it on the map in place.
                vec![None]
            } else {
                let this = &*self;
                level
                    .par_iter()
                    .map(|&node| {
                        let (param, cells, samples) = &blocks[node % nb];
                        match param {
                            Param::Point(face) if !skipped(node, &idle, &moved) => {
                                this.optimize_point(face, cells, samples).map(Run::Done)
                            }
                            _ => Some(Run::Skipped),
                        }
                    })
                    .collect()
            };
            for (&node, run) in level.iter().zip(runs) {
                let (param, cells, samples) = &blocks[node % nb];
                let at = node + 1;
                if skipped(node, &idle, &moved) {
                    // The unit tests' fits check that every skipped block is a no-op.
                    #[cfg(test)]
                    assert!(
                        !self.optimize(*param, cells, samples),
                        "a skipped block moved: {param:?}"
                    );
                    continue;
                }
                let changed = match (run, param) {
                    (Some(Run::Done((x, changed))), Param::Point(face)) => {
                        self.map.set_logits(face, &x);
                        changed
                    }
                    _ => self.optimize(*param, cells, samples),
                };
                if changed {
                    for &c in cells {
                        moved.insert(c, at);
                    }
                    idle[node % nb] = None;
                } else {
                    idle[node % nb] = Some(at);
                }
            }
        }
    }

    /// Patch samples (`u`) of each cell, in the order of `cells`.
    fn cell_samples(&self, cells: &[u32]) -> Vec<Vec<Bary>> {
        cells
            .iter()
            .map(|&c| {
                let s: Vec<f64> = self
                    .complex
                    .cell(c)
                    .iter()
                    .map(|&v| self.values[v as usize])
                    .collect();
                let corners: Vec<Bary> = patch_corners(&s).into_iter().map(|x| x.0).collect();
                patch_samples(&corners, opt_level(self.n))
            })
            .collect()
    }

    /// Sets `param` to `x` in `map`/`weights`; a weight change re-places the crossings of
    /// `edges` (the sign-changing edges it acts on), so every crossing stays exact.
    fn set_param(
        &self,
        param: Param,
        x: &[f64],
        edges: &[EdgeKey],
        map: &mut StratifiedMap,
        weights: &mut RationalWeights,
    ) {
        match param {
            Param::Point(face) => map.set_logits(face, x),
            Param::Weight(face) => {
                weights.set_log_weight(face, x[0]);
                for &e in edges {
                    place_crossing(&self.roots, weights, map, e);
                }
            }
        }
    }

    /// The mapped sample points of `cells` with `param` set to `x`.
    #[allow(clippy::too_many_arguments)]
    fn block_points(
        &self,
        param: Param,
        x: &[f64],
        edges: &[EdgeKey],
        cells: &[u32],
        samples: &[Vec<Bary>],
        map: &mut StratifiedMap,
        weights: &mut RationalWeights,
    ) -> Vec<[f64; 3]> {
        self.set_param(param, x, edges, map, weights);
        let mut out = Vec::new();
        for (&c, us) in cells.iter().zip(samples) {
            let ids = self.complex.cell(c);
            let local = local_of(map, weights, ids);
            out.extend(us.iter().map(|u| self.point_of(ids, &local.eval(u))));
        }
        out
    }

    /// `g/|∇g|` and the unit normal `∇g/|∇g|` at each point.
    fn residuals_at(&self, points: &[[f64; 3]]) -> (Vec<f64>, Vec<[f64; 3]>) {
        let n = self.n;
        points
            .iter()
            .map(|p| {
                let mut grad = [0.0; 3];
                let v = self.g.gradient(&p[..n], &mut grad[..n]);
                let norm = grad[..n]
                    .iter()
                    .map(|x| x * x)
                    .sum::<f64>()
                    .sqrt()
                    .max(f64::MIN_POSITIVE);
                (v / norm, [grad[0] / norm, grad[1] / norm, grad[2] / norm])
            })
            .unzip()
    }

    /// Levenberg–Marquardt on one parameter block (≤ 4 unknowns) over the crossing `cells` it acts
    /// on ([`Fitter::levenberg_marquardt`]), on the map in place. Returns whether the parameter
    /// moved.
    fn optimize(&mut self, param: Param, cells: &[u32], samples: &[Vec<Bary>]) -> bool {
        if cells.is_empty() {
            return false;
        }
        if let Param::Point(face) = param {
            if let Some((x, moved)) = self.optimize_point(face, cells, samples) {
                self.map.set_logits(face, &x);
                return moved;
            }
        }
        let mut map = std::mem::take(&mut self.map);
        let mut weights = std::mem::take(&mut self.weights);
        let (x, bound, edges) = match param {
            Param::Point(face) => (map.logits(face), LOGIT_BOUND, Vec::new()),
            Param::Weight(face) => {
                let mut edges: Vec<EdgeKey> = Vec::new();
                for &c in cells {
                    let ids = self.complex.cell(c);
                    for (i, &a) in ids.iter().enumerate() {
                        for &b in &ids[i + 1..] {
                            let e = (a.min(b), a.max(b));
                            if self.is_crossing_edge(e)
                                && face.iter().all(|v| *v == e.0 || *v == e.1)
                            {
                                edges.push(e);
                            }
                        }
                    }
                }
                edges.sort_unstable();
                edges.dedup();
                (vec![weights.log_weight(face)], LOG_WEIGHT_BOUND, edges)
            }
        };
        let mut block = WholeMap {
            fitter: self,
            param,
            edges: &edges,
            cells,
            samples,
            map: &mut map,
            weights: &mut weights,
        };
        let (x, moved) = self.levenberg_marquardt(&mut block, x, bound);
        self.set_param(param, &x, &edges, &mut map, &mut weights);
        self.map = map;
        self.weights = weights;
        moved
    }

    /// [`Fitter::optimize`] of a face's point without changing anything: the new logits and
    /// whether they moved, or `None` where the face is not a face of every cell (then `optimize`
    /// takes the general path). A face's point moves only its own term of each cell's map, so the
    /// maps are built once and the part before that term's stratum is applied once per sample.
    fn optimize_point(
        &self,
        face: &[u32],
        cells: &[u32],
        samples: &[Vec<Bary>],
    ) -> Option<(Vec<f64>, bool)> {
        if cells.is_empty() {
            return None;
        }
        let locals = cells
            .iter()
            .zip(samples)
            .map(|(&c, us)| {
                let ids = self.complex.cell(c);
                let (local, slot) = self.map.local_with(ids, Some(face));
                let local = local.after(self.weights.local(ids));
                let slot = slot?;
                let before = us
                    .iter()
                    .map(|u| local.eval_before(u, Some(slot)))
                    .collect();
                Some((local, slot, before))
            })
            .collect::<Option<Vec<_>>>()?;
        let mut block = FacePoint {
            fitter: self,
            cells,
            locals,
        };
        Some(self.levenberg_marquardt(&mut block, self.map.logits(face), LOGIT_BOUND))
    }

    /// Levenberg–Marquardt from `x` (clamped to `±bound`) on the residuals `r = g/|∇g|` at the
    /// block's points. Hand-written: a dense 4×4 solve is all it needs, and a general solver crate
    /// would not know the softmax and weight clamps. The Jacobian of `r` is `n̂ · ∂p/∂θ` (exact on
    /// the zero set, Gauss–Newton's usual approximation off it), so `g` is evaluated once per
    /// trial. Only improving steps are taken, and none once every residual is within
    /// [`Fitter::lm_done`]. Returns the final parameter and whether it moved.
    fn levenberg_marquardt(
        &self,
        block: &mut impl BlockMap,
        mut x: Vec<f64>,
        bound: f64,
    ) -> (Vec<f64>, bool) {
        let k = x.len();
        let mut moved = false;
        let mut pts = block.points(&x);
        let (mut r, mut normals) = self.residuals_at(&pts);
        let mut cost: f64 = r.iter().map(|v| v * v).sum();
        let mut lambda = 1e-3;
        for _ in 0..6 {
            // NaN residuals are never done.
            if r.iter().all(|v| v.abs() <= self.lm_done) {
                break;
            }
            let mut jac = vec![vec![0.0; r.len()]; k];
            block.jacobian(&x, &pts, &normals, &mut jac);
            let mut improved = false;
            for _ in 0..4 {
                let mut a = vec![0.0; k * k];
                let mut b = vec![0.0; k];
                for i in 0..k {
                    for j in 0..k {
                        a[i * k + j] = jac[i].iter().zip(&jac[j]).map(|(p, q)| p * q).sum();
                    }
                    b[i] = -jac[i].iter().zip(&r).map(|(p, q)| p * q).sum::<f64>();
                }
                for i in 0..k {
                    a[i * k + i] += lambda * a[i * k + i] + 1e-12;
                }
                let Some(step) = solve(&mut a, &mut b, k) else {
                    break;
                };
                let xn: Vec<f64> = x
                    .iter()
                    .zip(&step)
                    .map(|(a, s)| (a + s).clamp(-bound, bound))
                    .collect();
                let pn = block.points(&xn);
                let (rn, nn) = self.residuals_at(&pn);
                let cn: f64 = rn.iter().map(|v| v * v).sum();
                if cn < cost {
                    x = xn;
                    pts = pn;
                    r = rn;
                    normals = nn;
                    cost = cn;
                    lambda = (lambda / 3.0).max(1e-9);
                    improved = true;
                    moved = true;
                    break;
                }
                lambda *= 5.0;
            }
            if !improved {
                break;
            }
        }
        (x, moved)
    }

    /// The one-sided accuracy loop: while cells' own samples are farther than the tolerance
    /// from `Z`, bisect the worst cells and re-fit the star of the new vertices.
    fn accuracy(
        &mut self,
        options: &FitOptions,
        min_cell: f64,
        progress: &Progress,
    ) -> Result<(), FitError> {
        let mut pruned = false;
        loop {
            let errors = self.cell_errors(min_cell, false, options.tolerance);
            let worst = errors.iter().map(|e| e.1).fold(0.0, f64::max);
            step(progress, "refine", self.complex.num_cells(), options, worst)?;
            let mut bad: Vec<(u32, f64)> = errors
                .into_iter()
                .filter(|e| e.1 > TOLERANCE_MARGIN * options.tolerance)
                .collect();
            if bad.is_empty() {
                // Before stopping, the report's own (denser) samples: a patch can peak between
                // the ranking samples, most with rational weights.
                bad = self.cell_errors(min_cell, true, options.tolerance);
                bad.retain(|e| e.1 > options.tolerance);
            }
            if bad.is_empty() && !pruned && options.prune && options.optimize {
                self.prune(options.tolerance);
                pruned = true;
                continue;
            }
            if bad.is_empty() || self.complex.num_cells() >= options.max_simplices {
                return Ok(());
            }
            bad.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
            // The paper refines one worst cell per step; we refine every cell above the target
            // in one step (worst first), which reaches the same kind of complex in far fewer
            // re-optimizations. A cell's longest edge is often not the one where the patch is
            // poor (a sliver near a vertex), so it may take a few steps for the bad edge itself
            // to be split.
            let mut new_vertices = Vec::new();
            for &(c, _) in &bad {
                if self.complex.is_alive(c) && self.complex.num_cells() < options.max_simplices {
                    new_vertices.extend(self.refine(c));
                }
            }
            if new_vertices.is_empty() {
                return Ok(());
            }
            self.refit_star(&new_vertices, options.optimize);
            self.check()?;
            progress.check()?;
        }
    }

    /// Puts back at its face's centre (no record) every optimized point whose crossing cells
    /// still meet `TOLERANCE_MARGIN × tolerance` at the ranking samples without it: smallest
    /// displacement first. That includes the crossing edges' points, which move the patch corner
    /// from the linear crossing of the values onto `g`'s root: with distance-like values
    /// ([`vertex_value`]) the two are often close enough. A record costs
    /// 48–60 bytes (edge, triangle) against 16 for a tetrahedron's ids, and most of the
    /// optimizer's moves are not needed once the cells are small enough for their worst one.
    /// The accuracy loop checks again afterwards (denser samples), and the two-sided measure
    /// runs on the pruned model.
    fn prune(&mut self, tolerance: f64) {
        let centre_gap = |l: &[f64]| {
            let p = crate::strata::softmax(l);
            let c = 1.0 / p.len() as f64;
            p.iter().map(|x| (x - c).abs()).fold(0.0, f64::max)
        };
        let mut faces: Vec<(f64, Vec<u32>)> = self
            .map
            .entries()
            .map(|(f, l)| (centre_gap(l), f.clone()))
            .collect();
        faces.sort_by(|a, b| a.0.total_cmp(&b.0).then_with(|| a.1.cmp(&b.1)));
        let level = rank_level(self.n);
        // In that order, but level by level ([`conflict_levels`]): a face's test reads the points
        // of its crossing cells' faces only, and a removal changes only the cells with the face,
        // so faces without a common crossing cell are tested in parallel on the same numbers as
        // one after another, and the result is the serial one for any number of threads.
        let cells: Vec<Vec<u32>> = faces
            .iter()
            .map(|(_, f)| self.crossing_cells_with_face(f))
            .collect();
        // The stored points, kept equal to the map's as faces are removed: a cell's map without
        // the tested face is built from them (the same lookups as the whole map's).
        let mut stored: HashMap<Vec<u32>, Vec<f64>> = self
            .map
            .entries()
            .map(|(f, l)| (f.clone(), l.clone()))
            .collect();
        for run in conflict_levels(cells.iter().map(|c| (&c[..], false))) {
            let removable: Vec<bool> = {
                let this = &*self;
                let stored = &stored;
                run.par_iter()
                    .map(|&i| {
                        let face = &faces[i].1;
                        cells[i].iter().all(|&c| {
                            let ids = this.complex.cell(c);
                            let mut without = StratifiedMap::new(this.n);
                            for f in simplex_faces(ids, 2) {
                                let key = f.ids();
                                if key != &face[..] {
                                    if let Some(l) = stored.get(key) {
                                        without.set_logits(key, l);
                                    }
                                }
                            }
                            let local = without.local(ids).after(this.weights.local(ids));
                            this.cell_error_of(c, &local, level, tolerance)
                                <= TOLERANCE_MARGIN * tolerance
                        })
                    })
                    .collect()
            };
            for (&i, removable) in run.iter().zip(removable) {
                if removable {
                    let face = &faces[i].1;
                    self.map.remove(face);
                    stored.remove(face);
                    self.forget_face(face);
                }
            }
        }
    }

    /// Re-fits the star of `new_vertices` and the cells sharing a vertex with it (their faces
    /// share points with the star).
    fn refit_star(&mut self, new_vertices: &[u32], optimize: bool) {
        let new_set: HashSet<u32> = new_vertices.iter().copied().collect();
        let region: Vec<u32> = self
            .complex
            .live_cells()
            .into_iter()
            .filter(|&c| self.complex.cell(c).iter().any(|v| new_set.contains(v)))
            .collect();
        self.fit_region(&region, optimize);
    }

    /// Bisects the cells where a two-sided measurement found the fit farther than the
    /// tolerance from the target: the simplex of a sample of `S`, the cell holding a point of
    /// `Z` (its vertices may all have one sign, so no patch is there yet) and the cells whose
    /// bounding boxes come within the miss's distance of it — those with a longest
    /// edge of at least `min_cell`, within `max_simplices`. Returns the new vertices.
    fn refine_misses(&mut self, misses: &[Miss], min_cell: f64, max_simplices: usize) -> Vec<u32> {
        let live = self.complex.live_cells();
        let n = self.n;
        let boxes: Vec<
            rstar::primitives::GeomWithData<rstar::primitives::Rectangle<[f64; 3]>, u32>,
        > = live
            .iter()
            .map(|&c| {
                let (lo, hi) = self.complex.bounding_box(c);
                let (mut a, mut b) = ([0.0; 3], [0.0; 3]);
                a[..n].copy_from_slice(&lo);
                b[..n].copy_from_slice(&hi);
                rstar::primitives::GeomWithData::new(
                    rstar::primitives::Rectangle::from_corners(a, b),
                    c,
                )
            })
            .collect();
        let tree = rstar::RTree::bulk_load(boxes);
        let mut cells: Vec<u32> = Vec::new();
        for m in misses {
            match m.simplex {
                Some(s) => cells.extend(live.get(s).copied()),
                // The cell holding the point, and the cells within the miss's distance of it:
                // the patches that must come nearer (one round then often suffices).
                None => {
                    let r = if m.distance.is_finite() {
                        m.distance
                    } else {
                        0.0
                    };
                    let (mut lo, mut hi) = (m.at, m.at);
                    for k in 0..n {
                        lo[k] -= r;
                        hi[k] += r;
                    }
                    let near = rstar::AABB::from_corners(lo, hi);
                    cells.extend(
                        tree.locate_in_envelope_intersecting(near)
                            .map(|b| b.data)
                            .filter(|&c| r > 0.0 || self.contains(c, &m.at[..n])),
                    )
                }
            }
        }
        cells.sort_unstable();
        cells.dedup();
        let mut new_vertices = Vec::new();
        for c in cells {
            if self.complex.is_alive(c)
                && self.longest_edge_length(c) >= min_cell
                && self.complex.num_cells() < max_simplices
            {
                new_vertices.extend(self.refine(c));
            }
        }
        new_vertices
    }

    /// Whether `p` lies in cell `c` (barycentric coordinates ≥ −[`CONTAINS_SLACK`]).
    fn contains(&self, c: u32, p: &[f64]) -> bool {
        let ids = self.complex.cell(c);
        let n = self.n;
        let o = self.complex.point(ids[0]);
        // Edge matrix (column k = vertex k+1 − vertex 0), row-major n×n.
        let mut a = vec![0.0; n * n];
        for (k, &v) in ids[1..].iter().enumerate() {
            for (i, x) in self.complex.point(v).iter().enumerate() {
                a[i * n + k] = x - o[i];
            }
        }
        let mut b: Vec<f64> = (0..n).map(|i| p[i] - o[i]).collect();
        match solve(&mut a, &mut b, n) {
            Some(w) => {
                let sum: f64 = w.iter().sum();
                w.iter().all(|&x| x >= -CONTAINS_SLACK) && sum <= 1.0 + CONTAINS_SLACK
            }
            None => false,
        }
    }

    /// Groups `cells` into clusters of cells within `2·size` of each other (a grid hash of cell
    /// centres, connected through neighbouring grid cells).
    fn clusters(&self, cells: &[u32], size: f64) -> Vec<Uncertain> {
        let n = self.n;
        let h = (2.0 * size).max(f64::MIN_POSITIVE);
        let centres: Vec<(Vec<f64>, f64)> = cells
            .iter()
            .map(|&c| {
                let (lo, hi) = self.complex.bounding_box(c);
                let centre: Vec<f64> = lo.iter().zip(&hi).map(|(a, b)| 0.5 * (a + b)).collect();
                let half = lo
                    .iter()
                    .zip(&hi)
                    .map(|(a, b)| (0.5 * (b - a)).powi(2))
                    .sum::<f64>()
                    .sqrt();
                (centre, half)
            })
            .collect();
        let key = |p: &[f64]| -> Vec<i64> { p.iter().map(|x| (x / h).floor() as i64).collect() };
        let mut grid: HashMap<Vec<i64>, Vec<usize>> = HashMap::new();
        for (i, (c, _)) in centres.iter().enumerate() {
            grid.entry(key(c)).or_default().push(i);
        }
        let mut label = vec![usize::MAX; cells.len()];
        let mut out = Vec::new();
        for start in 0..cells.len() {
            if label[start] != usize::MAX {
                continue;
            }
            let id = out.len();
            let mut stack = vec![start];
            label[start] = id;
            let mut members = Vec::new();
            while let Some(i) = stack.pop() {
                members.push(i);
                let k = key(&centres[i].0);
                for offset in 0..3usize.pow(n as u32) {
                    let mut nk = k.clone();
                    let mut o = offset;
                    for x in nk.iter_mut() {
                        *x += (o % 3) as i64 - 1;
                        o /= 3;
                    }
                    for &j in grid.get(&nk).map_or(&[][..], |v| &v[..]) {
                        if label[j] == usize::MAX {
                            label[j] = id;
                            stack.push(j);
                        }
                    }
                }
            }
            let mut centre = vec![0.0; n];
            for &i in &members {
                for (c, x) in centre.iter_mut().zip(&centres[i].0) {
                    *c += x / members.len() as f64;
                }
            }
            let radius = members
                .iter()
                .map(|&i| {
                    let d: f64 = (0..n)
                        .map(|k| (centres[i].0[k] - centre[k]).powi(2))
                        .sum::<f64>()
                        .sqrt();
                    d + centres[i].1
                })
                .fold(0.0, f64::max);
            let gradient_may_vanish = members.iter().any(|&i| {
                let (lo, hi) = self.complex.bounding_box(cells[i]);
                self.g
                    .enclose(&lo, &hi)
                    .is_some_and(|e| e.gradient.iter().all(|d| d.contains(0.0)))
            });
            out.push(Uncertain {
                centre,
                radius,
                cells: members.len(),
                gradient_may_vanish,
                shape_to_target: 0.0,
                target_to_shape: 0.0,
            });
        }
        out
    }

    fn faces_of_crossing_cells(&self) -> HashSet<Vec<u32>> {
        let mut set = HashSet::new();
        for c in self.crossing_cells() {
            for f in self.faces_of(c) {
                set.insert(f);
            }
        }
        set
    }
}

/// Solves `a x = b` (`k × k`, row-major) by Gaussian elimination with partial pivoting.
fn solve(a: &mut [f64], b: &mut [f64], k: usize) -> Option<Vec<f64>> {
    for col in 0..k {
        let p = (col..k).max_by(|&i, &j| a[i * k + col].abs().total_cmp(&a[j * k + col].abs()))?;
        if a[p * k + col].abs() < 1e-300 {
            return None;
        }
        for j in 0..k {
            a.swap(p * k + j, col * k + j);
        }
        b.swap(p, col);
        for row in col + 1..k {
            let f = a[row * k + col] / a[col * k + col];
            for j in col..k {
                a[row * k + j] -= f * a[col * k + j];
            }
            b[row] -= f * b[col];
        }
    }
    let mut x = vec![0.0; k];
    for row in (0..k).rev() {
        let s: f64 = (row + 1..k).map(|j| a[row * k + j] * x[j]).sum();
        x[row] = (b[row] - s) / a[row * k + row];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// Cells per axis for `resolution` cells along the longest side.
pub fn grid_cells(domain: &[f64], resolution: usize) -> Vec<usize> {
    let sides: Vec<f64> = domain.chunks(2).map(|c| c[1] - c[0]).collect();
    let longest = sides.iter().copied().fold(0.0, f64::max);
    sides
        .iter()
        .map(|s| ((resolution as f64 * s / longest).round() as usize).max(1))
        .collect()
}

fn check_options(g: &dyn ImplicitFunction, o: &FitOptions) -> Result<(), FitError> {
    let n = g.dim();
    if !(2..=3).contains(&n) {
        return Err(FitError::Options(format!(
            "dimension {n}: only 2 and 3 are supported"
        )));
    }
    if o.domain.len() != 2 * n {
        return Err(FitError::Options(format!(
            "domain has {} numbers; a {n}-D domain needs {}",
            o.domain.len(),
            2 * n
        )));
    }
    if o.domain
        .chunks(2)
        .any(|c| !(c[0].is_finite() && c[1].is_finite() && c[0] < c[1]))
    {
        return Err(FitError::Options(
            "domain: each axis needs finite lo < hi".into(),
        ));
    }
    if o.resolution == 0 || o.resolution > 512 {
        return Err(FitError::Options(format!(
            "resolution {} is outside 1..=512",
            o.resolution
        )));
    }
    if !(o.lm_done_fraction >= 0.0 && o.lm_done_fraction.is_finite()) {
        return Err(FitError::Options(format!(
            "lm_done_fraction {} must be a finite number >= 0",
            o.lm_done_fraction
        )));
    }
    if !(o.tolerance > 0.0 && o.tolerance.is_finite()) {
        return Err(FitError::Options(
            "tolerance must be a positive number".into(),
        ));
    }
    let size = o.domain.chunks(2).map(|c| c[1] - c[0]).fold(0.0, f64::max);
    if o.tolerance < MIN_TOLERANCE_FRACTION * size {
        return Err(FitError::Options(format!(
            "tolerance {:e} is below {MIN_TOLERANCE_FRACTION:e} of the domain's size {size}: \
             cells would be split towards the resolution of double precision",
            o.tolerance
        )));
    }
    if !(o.pv_min_edge >= 0.0 && o.pv_min_edge.is_finite()) {
        return Err(FitError::Options(
            "the topology phase's smallest cell edge must be a finite number ≥ 0".into(),
        ));
    }
    let cells: usize = grid_cells(&o.domain, o.resolution)
        .iter()
        .product::<usize>()
        * if n == 2 { 2 } else { 6 };
    if cells > o.max_simplices {
        return Err(FitError::Options(format!(
            "the initial grid has {cells} simplices, more than max-simplices {}",
            o.max_simplices
        )));
    }
    Ok(())
}

/// Fits an ISM to the zero set of `g` (see the module doc). `progress` gets a [`Step`] at each
/// step of each phase (`topology`, `optimize`, `refine`, `report`; `done` = live simplices,
/// `total` = [`FitOptions::max_simplices`], `worst` = largest cell error or NaN); a cancelled
/// `progress` stops the fit at its next step.
///
/// # Errors
/// [`FitError::Options`] for a bad domain, resolution or tolerance; [`FitError::Cancelled`].
pub fn fit(
    g: &dyn ImplicitFunction,
    options: &FitOptions,
    progress: &Progress,
) -> Result<Fitted, FitError> {
    check_options(g, options)?;
    let start = Instant::now();
    let mut fitter = Fitter::new(g, options);
    fitter.set_values_for_new_vertices();
    fitter.check()?;

    // Topology phase.
    let size = options
        .domain
        .chunks(2)
        .map(|c| c[1] - c[0])
        .fold(0.0, f64::max);
    let pv_min_edge = options
        .pv_min_edge
        .max((PV_MIN_CELL_FRACTION * options.tolerance).min(PV_MIN_CELL_OF_DOMAIN * size));
    if options.topology {
        loop {
            let large: Vec<u32> = {
                let f = &fitter;
                f.complex
                    .live_cells()
                    .into_iter()
                    .filter(|&c| f.longest_edge_length(c) > pv_min_edge)
                    .collect()
            };
            let failing = fitter.pv_failing(large);
            step(
                progress,
                "topology",
                fitter.complex.num_cells(),
                options,
                f64::NAN,
            )?;
            if failing.is_empty()
                || fitter.complex.num_cells() + 2 * failing.len() > options.max_simplices
            {
                break;
            }
            for c in failing {
                if fitter.complex.is_alive(c) {
                    fitter.refine(c);
                }
            }
            fitter.check()?;
        }
    }
    no_zero_set(&fitter)?;

    // Initial fit of every crossing cell.
    let crossing = fitter.crossing_cells();
    step(
        progress,
        "optimize",
        fitter.complex.num_cells(),
        options,
        f64::NAN,
    )?;
    fitter.fit_region(&crossing, options.optimize);
    fitter.check()?;
    progress.check()?;

    // Accuracy phase: refine on the fitter's own one-sided samples until they meet the
    // tolerance, then measure both directions on the model as written; where that measure still
    // misses (a piece of the target no patch comes near, a patch peaking between samples),
    // refine there and go again.
    let min_cell = (MIN_CELL_FRACTION * options.tolerance).max(MIN_CELL_OF_DOMAIN * size);
    let mut rounds = 0;
    // Each round's measure re-measures only the patches the round changed (same numbers).
    let mut measure_cache = MeasureCache::new();
    let (model, m, clusters, pv_failures, pv_unfinished) = loop {
        fitter.accuracy(options, min_cell, progress)?;
        // The complex's Plantinga–Vegter status, whether or not the topology phase ran.
        let failing = fitter.pv_failing(fitter.complex.live_cells());
        let pv_failures = failing.len();
        let pv_unfinished = if options.topology {
            failing
                .iter()
                .filter(|&&c| fitter.longest_edge_length(c) > pv_min_edge)
                .count()
        } else {
            0
        };
        let clusters = fitter.clusters(&failing, pv_min_edge);
        step(
            progress,
            "report",
            fitter.complex.num_cells(),
            options,
            f64::NAN,
        )?;
        // Indexed once for the kernel (no copy): the measure evaluates through the index.
        let model = ism_format::IndexedModel::for_evaluation(model_of(
            &fitter.complex,
            &fitter.values,
            &fitter.map,
            &fitter.weights,
            "fit",
        ))
        .map_err(|e| FitError::Eval(e.into()))?;
        let regions: Vec<(Vec<f64>, f64)> = clusters
            .iter()
            .map(|c| (c.centre.clone(), c.radius + options.tolerance))
            .collect();
        let m = measure_cached(
            g,
            &model,
            &options.domain,
            options.tolerance,
            &regions,
            &mut measure_cache,
        )
        .map_err(FitError::Eval)?;
        let done = m.meets(options.tolerance)
            || rounds == TWO_SIDED_ROUNDS
            || fitter.complex.num_cells() >= options.max_simplices;
        let new_vertices = if done {
            Vec::new()
        } else {
            fitter.refine_misses(&m.misses, min_cell, options.max_simplices)
        };
        if new_vertices.is_empty() {
            break (model, m, clusters, pv_failures, pv_unfinished);
        }
        fitter.refit_star(&new_vertices, options.optimize);
        fitter.check()?;
        progress.check()?;
        rounds += 1;
    };
    let unresolved_cells = {
        let f = &fitter;
        f.crossing_cells()
            .into_par_iter()
            .filter(|&c| f.longest_edge_length(c) < min_cell)
            .filter(|&c| f.cell_error(c, report_level(f.n), options.tolerance) > options.tolerance)
            .count()
    };
    let faces = fitter.faces_of_crossing_cells();
    fitter.map.retain(|f| faces.contains(f));
    let touched: HashSet<u32> = faces.iter().flatten().copied().collect();
    fitter
        .weights
        .retain(|f| faces.contains(f) || (f.len() == 1 && touched.contains(&f[0])));
    let pl_topology = topology(&fitter.complex, &fitter.values);
    let mut fitted = Fitted {
        complex: fitter.complex,
        values: fitter.values,
        map: fitter.map,
        weights: fitter.weights,
        report: FitReport {
            simplices: 0,
            vertices: 0,
            crossing_simplices: 0,
            parameters: 0,
            stored_numbers: 0,
            max_distance: 0.0,
            mean_distance: 0.0,
            samples: 0,
            bisections: fitter.bisections,
            pv_failures,
            topology: pl_topology,
            tolerance_met: false,
            topology_certified: pv_failures == 0,
            measure: Measure {
                shape_to_target: 0.0,
                shape_to_target_mean: 0.0,
                shape_to_target_at: Vec::new(),
                samples: 0,
                shape_spacing: 0.0,
                shape_cover: 0.0,
                dense_samples: 0,
                shape_to_target_error: 0.0,
                target_to_shape: 0.0,
                target_to_shape_bound: 0.0,
                target_to_shape_at: Vec::new(),
                cover: crate::measure::TargetCover::None,
                cells: 0,
                regions: Vec::new(),
                misses: Vec::new(),
            },
            uncertain: Vec::new(),
            unresolved_cells,
            pv_unfinished,
            two_sided_rounds: rounds,
            seconds: 0.0,
        },
    };
    // The model as written: the measured one without the face records that cannot change the
    // shape (same patches).
    drop(model);
    let model = fitted.to_model("fit");
    let r = &mut fitted.report;
    r.simplices = model.num_simplices();
    r.vertices = model.num_vertices();
    r.crossing_simplices = m.cells;
    r.parameters = model.stages.iter().map(|s| s.parameter_count()).sum();
    r.stored_numbers = stored_numbers(&model);
    r.max_distance = m.max();
    r.mean_distance = m.shape_to_target_mean;
    r.samples = m.samples;
    r.tolerance_met = m.meets(options.tolerance);
    r.uncertain = clusters
        .into_iter()
        .zip(&m.regions)
        .map(|(mut c, region)| {
            c.shape_to_target = region.shape_to_target;
            c.target_to_shape = region.target_to_shape;
            c
        })
        .collect();
    r.measure = m;
    r.seconds = start.elapsed().as_secs_f64();
    Ok(fitted)
}

impl FitReport {
    /// The members of `ism fit --json` that this report holds (the front ends add what depends
    /// on their input: the topology reference, the mesh, the structural check, the round trip).
    pub fn to_json(&self) -> serde_json::Map<String, serde_json::Value> {
        let m = &self.measure;
        let cover = match &m.cover {
            crate::measure::TargetCover::Boxes { count, largest } => serde_json::json!({
                "method": "interval boxes", "count": count, "largestHalfDiagonal": largest}),
            // `toleranceMet` judged `Z → S` on the certified bound ([`Measure::meets`]); on the
            // estimate for the boxes.
            crate::measure::TargetCover::MeshPoints { count, radius } => serde_json::json!({
                "method": "mesh points", "count": count, "coveringRadius": radius,
                "toleranceJudgedOn": "targetToShapeBound"}),
            crate::measure::TargetCover::None => serde_json::json!({"method": "none"}),
        };
        let uncertain: Vec<serde_json::Value> = self
            .uncertain
            .iter()
            .map(|u| {
                serde_json::json!({
                    "centre": u.centre,
                    "radius": u.radius,
                    "cells": u.cells,
                    "gradientMayVanish": u.gradient_may_vanish,
                    "shapeToTarget": u.shape_to_target,
                    "targetToShape": u.target_to_shape,
                })
            })
            .collect();
        let value = serde_json::json!({
            "simplices": self.simplices,
            "vertices": self.vertices,
            "crossingSimplices": self.crossing_simplices,
            "parameters": self.parameters,
            "storedNumbers": self.stored_numbers,
            "maxDistance": self.max_distance,
            "meanDistance": self.mean_distance,
            "samples": self.samples,
            "shapeToTarget": m.shape_to_target,
            "shapeToTargetAt": m.shape_to_target_at,
            "shapeToTargetError": m.shape_to_target_error,
            "denseSamples": m.dense_samples,
            "sampleSpacing": m.shape_spacing,
            "sampleCover": m.shape_cover,
            "shapeToTargetBound": m.shape_to_target_bound(),
            "maxDistanceBound": m.max_bound(),
            "targetToShape": m.target_to_shape,
            "targetToShapeBound": m.target_to_shape_bound,
            "targetToShapeAt": m.target_to_shape_at,
            "targetCover": cover,
            "uncertain": uncertain,
            "unresolvedCells": self.unresolved_cells,
            "pvUnfinished": self.pv_unfinished,
            "twoSidedRounds": self.two_sided_rounds,
            "topologyCertified": self.topology_certified,
            "bisections": self.bisections,
            "pvFailures": self.pv_failures,
            "components": self.topology.components,
            "euler": self.topology.euler,
            "toleranceMet": self.tolerance_met,
            "seconds": self.seconds,
        });
        match value {
            serde_json::Value::Object(map) => map,
            _ => unreachable!("json! of an object literal is an object"),
        }
    }
}

/// [`FitError::NoZeroSet`] when every vertex value has one sign.
fn no_zero_set(fitter: &Fitter) -> Result<(), FitError> {
    let negative = fitter.values.iter().filter(|&&v| v < 0.0).count();
    if negative != 0 && negative != fitter.values.len() {
        return Ok(());
    }
    let (at, smallest) = fitter
        .values
        .iter()
        .enumerate()
        .map(|(v, x)| (v, x.abs()))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap_or((0, f64::NAN));
    Err(FitError::NoZeroSet {
        positive: negative == 0,
        vertices: fitter.values.len(),
        smallest,
        at: if fitter.values.is_empty() {
            Vec::new()
        } else {
            fitter.complex.point(at as u32).to_vec()
        },
    })
}

/// Every number a model stores: coordinates, simplex ids, values, and per face record its ids,
/// points and weights.
pub fn stored_numbers(model: &Model) -> usize {
    model.vertices.len()
        + model.simplices.len()
        + model.values.len()
        + model
            .stages
            .iter()
            .flat_map(|s| &s.faces)
            .map(|f| f.face.len() + f.points.len() + f.weights.len())
            .sum::<usize>()
}

/// Distance estimates on dense samples of a model's shape.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DenseError {
    /// Largest `|g|/|∇g|`.
    pub max: f64,
    /// Mean `|g|/|∇g|`.
    pub mean: f64,
    /// Number of samples.
    pub samples: usize,
    /// Simplices the shape passes through.
    pub cells: usize,
}

/// `|g|/|∇g|` at dense samples of the parametric form of the model's shape, evaluated by the
/// kernel (`ism-geom`: `θ_σ` and `u ↦ p`, through the model's index), independently of the
/// fitter's own evaluation.
///
/// # Errors
/// The kernel's error when the model does not evaluate.
pub fn dense_error(
    g: &dyn ImplicitFunction,
    model: &ism_format::IndexedModel,
) -> Result<DenseError, ism_geom::GeomError> {
    let eval = ism_geom::ModelEval::from_indexed(model)?;
    let n = model.dim();
    let per_cell: Vec<(f64, f64, usize)> = (0..model.num_simplices())
        .into_par_iter()
        .filter_map(|s| {
            let patch = eval.patch(s)?;
            let corners: Vec<Bary> = patch.corners.iter().map(|c| c.u).collect();
            let mut max = 0.0f64;
            let mut sum = 0.0;
            let samples = patch_samples(&corners, report_level(n));
            for u in &samples {
                let p = crate::measure::shape_point(&eval, s, u);
                let d = g.distance_estimate(&p[..n]);
                max = max.max(d);
                sum += d;
            }
            Some((max, sum, samples.len()))
        })
        .collect();
    let samples: usize = per_cell.iter().map(|x| x.2).sum();
    Ok(DenseError {
        max: per_cell.iter().map(|x| x.0).fold(0.0, f64::max),
        // `+ 0.0`: an empty float sum is −0.0, and a shape-free model should report 0.
        mean: per_cell.iter().map(|x| x.1).sum::<f64>() / samples.max(1) as f64 + 0.0,
        samples,
        cells: per_cell.len(),
    })
}

impl Fitted {
    /// The ISM: the complex, `f`, level 0, and one parametric Bézier stage per stratum — as
    /// written, restricted to the simplices with an inside vertex and the records of crossed
    /// simplices ([`crate::shell`]; the same shape and solid).
    pub fn to_model(&self, name: &str) -> Model {
        crate::shell::shell(&self.full_model(name))
    }

    /// The model on the whole complex the fitter refined: simplex `i` is the `i`-th of
    /// `complex.live_cells()` (the same shape as [`Fitted::to_model`]).
    pub fn full_model(&self, name: &str) -> Model {
        model_of(&self.complex, &self.values, &self.map, &self.weights, name)
    }
}

/// The ISM of a fit's parts (see [`Fitted::to_model`]); simplex `i` of the model is the `i`-th
/// of `complex.live_cells()`.
fn model_of(
    complex: &Complex,
    values: &[f64],
    map: &StratifiedMap,
    weights: &RationalWeights,
    name: &str,
) -> Model {
    {
        let n = complex.dim();
        let mut model = Model::new(n as u8);
        model.metadata.name = Some(name.to_string());
        model.metadata.generator = Some(format!("ism-fit {}", env!("CARGO_PKG_VERSION")));
        model.vertices = complex.points().to_vec();
        model.simplices = complex.compact_cells();
        model.values = values.to_vec();
        let faces: HashSet<Vec<u32>> = {
            let mut set = HashSet::new();
            for c in complex.live_cells() {
                let faces = ism_format::indexed::simplex_faces(complex.cell(c), 1);
                set.extend(faces.map(|f| f.ids().to_vec()));
            }
            set
        };
        model.stages = map.to_stages(|f| faces.contains(f));
        model.stages.extend(weights.to_stage(|f| faces.contains(f)));
        model
    }
}

/// The linear isocomplex of `g` on the uniform Kuhn grid of `domain` with `resolution` cells along
/// the longest side: `(simplices, stored numbers of the complex with values, max |g|/|∇g|)` — the
/// comparison the compactness table makes.
pub fn linear_baseline(
    g: &dyn ImplicitFunction,
    domain: &[f64],
    resolution: usize,
) -> (usize, usize, f64) {
    let complex = Complex::kuhn(domain, &grid_cells(domain, resolution));
    linear_error(g, &complex)
}

/// `(simplices, stored numbers, max |g|/|∇g|)` of the linear isocomplex of `g` on `complex`.
pub fn linear_error(g: &dyn ImplicitFunction, complex: &Complex) -> (usize, usize, f64) {
    let n = complex.dim();
    let scale = 1.0;
    let values: Vec<f64> = (0..complex.num_vertices() as u32)
        .map(|v| vertex_value(g, complex.point(v), scale))
        .collect();
    let cells = complex.live_cells();
    let max = cells
        .par_iter()
        .map(|&c| {
            let ids = complex.cell(c);
            let s: Vec<f64> = ids.iter().map(|&v| values[v as usize]).collect();
            let corners: Vec<Bary> = patch_corners(&s).into_iter().map(|x| x.0).collect();
            let mut m = 0.0f64;
            for u in patch_samples(&corners, report_level(n)) {
                let mut p = [0.0; 3];
                for (i, &v) in ids.iter().enumerate() {
                    for (k, x) in complex.point(v).iter().enumerate() {
                        p[k] += u[i] * x;
                    }
                }
                m = m.max(g.distance_estimate(&p[..n]));
            }
            m
        })
        .reduce(|| 0.0, f64::max);
    let stored = complex.points().len() + cells.len() * (n + 1) + values.len();
    (cells.len(), stored, max)
}

/// Re-exported for tests and tools: the map of a fitted model per cell, keyed by live cell id.
pub fn local_maps(fitted: &Fitted) -> HashMap<u32, LocalStrata> {
    fitted
        .complex
        .live_cells()
        .into_iter()
        .map(|c| {
            let ids = fitted.complex.cell(c);
            (c, local_of(&fitted.map, &fitted.weights, ids))
        })
        .collect()
}

/// Parts per axis of a cell's bounding box in the Plantinga–Vegter test ([`Fitter::pv_passes`]).
/// Measured on the presets at their default tolerance (session 10): the topology phase's
/// complex, torus 10,680 → 7,010 simplices (504,283 → 420,255 .ismb bytes), genus-2 18,496 →
/// 11,910 (812,596 → 608,512); the sphere's is unchanged (its topology phase refines nothing
/// the accuracy loop would not). 3 parts: 7,068 / 12,915; 5: 6,946 / 11,454.
const PV_SPLIT: usize = 4;

/// `⟨□∇g, □∇g⟩ > 0` with the two factors as independent boxes (not squares): no two gradients
/// in the box are orthogonal or opposed.
fn gradients_agree(gradient: &[crate::interval::Interval]) -> bool {
    let mut dot = crate::interval::Interval::point(0.0);
    for gk in gradient {
        dot = dot + *gk * *gk;
    }
    dot.lo > 0.0
}

/// Sub-box `idx` (in 0..m^n, first axis fastest) of `[lo, hi]` split into `m` parts per axis,
/// written to `[l, h]`; the last part ends exactly at `hi`.
fn sub_box(lo: &[f64], hi: &[f64], m: usize, idx: usize, l: &mut [f64], h: &mut [f64]) {
    let mut rest = idx;
    for k in 0..lo.len() {
        let i = rest % m;
        rest /= m;
        let w = (hi[k] - lo[k]) / m as f64;
        l[k] = lo[k] + i as f64 * w;
        h[k] = if i + 1 == m {
            hi[k]
        } else {
            lo[k] + (i + 1) as f64 * w
        };
    }
}

/// Pairwise dot products of unit vectors each within
/// [`GENERATOR_ERROR`](crate::expr::GENERATOR_ERROR) per component of the true ones must exceed
/// this to count as positive: the rounding of a dot product of vectors of length ≲ 1 is ~10⁻¹⁶,
/// the generators' own error moves it by at most 2·√n·10⁻⁹ < 4·10⁻⁹.
const GENERATOR_DOT_MARGIN: f64 = 4.0 * crate::expr::GENERATOR_ERROR;

/// Whether every pair of the unit vectors in `flat` (`n` numbers each) has a dot product above
/// [`GENERATOR_DOT_MARGIN`] — then so has every pair of vectors in their conic hull
/// (bilinearity), which is the Plantinga–Vegter condition. `false` for none. First the cheap
/// sufficient test: all within 45° (less the margin) of their mean direction; then every pair.
pub(crate) fn unit_vectors_agree(n: usize, flat: &[f64]) -> bool {
    let count = flat.len() / n;
    if count == 0 || count > MAX_GENERATORS {
        return false;
    }
    let v = |i: usize| &flat[i * n..(i + 1) * n];
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let mut mean = vec![0.0; n];
    for i in 0..count {
        for (m, x) in mean.iter_mut().zip(v(i)) {
            *m += x;
        }
    }
    let len = dot(&mean, &mean).sqrt();
    if len > 0.0 {
        mean.iter_mut().for_each(|m| *m /= len);
        // Two vectors at angles a, b ≤ 45° − δ from one axis are at most 90° − 2δ apart. The
        // mean is rounded: its own error (≲ 10⁻¹⁵) is far inside the margin.
        let cos_limit = std::f64::consts::FRAC_1_SQRT_2 + GENERATOR_DOT_MARGIN;
        if (0..count).all(|i| dot(v(i), &mean) > cos_limit) {
            return true;
        }
    }
    (0..count).all(|i| (i + 1..count).all(|j| dot(v(i), v(j)) > GENERATOR_DOT_MARGIN))
}

/// More distinct generators than this for one cell fail the test rather than cost a quadratic
/// number of dot products (a cell that sees this many triangles is far from passing anyway).
const MAX_GENERATORS: usize = 4096;

/// A conservative test of whether a box `[l, h]` meets simplex `c`: `false` only when every
/// corner of the box has the same barycentric coordinate below `−CONTAINS_SLACK` (the box lies beyond
/// that facet's plane). `None` for a degenerate simplex.
fn simplex_test(complex: &Complex, c: u32) -> Option<impl Fn(&[f64], &[f64]) -> bool> {
    let n = complex.dim();
    let ids = complex.cell(c);
    let v0: Vec<f64> = complex.point(ids[0]).to_vec();
    // Edge matrix E (columns v_i − v_0) and its inverse: λ_{1..n} = E⁻¹ (p − v_0).
    let mut e: ism_geom::Mat = Default::default();
    for i in 0..n {
        let p = complex.point(ids[i + 1]);
        for k in 0..n {
            e[k][i] = p[k] - v0[k];
        }
    }
    let inv = ism_geom::linalg::inverse(n, &e)?;
    Some(move |l: &[f64], h: &[f64]| {
        let corners = 1usize << n;
        // Per coordinate λ_0..λ_n: is it below the margin at every corner?
        let mut beyond = [true; 4];
        for mask in 0..corners {
            let mut d = [0.0f64; 3];
            for k in 0..n {
                let x = if mask & (1 << k) == 0 { l[k] } else { h[k] };
                d[k] = x - v0[k];
            }
            let mut sum = 0.0;
            for i in 0..n {
                let li: f64 = (0..n).map(|k| inv[i][k] * d[k]).sum();
                sum += li;
                if li >= -CONTAINS_SLACK {
                    beyond[i + 1] = false;
                }
            }
            if 1.0 - sum >= -CONTAINS_SLACK {
                beyond[0] = false;
            }
        }
        !beyond[..=n].iter().any(|&b| b)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::measure::measure;
    use crate::presets::Preset;

    #[test]
    fn circle_fits_to_tolerance_with_the_right_topology() {
        let preset = Preset::find("circle").unwrap();
        let g = preset.expression().unwrap();
        let mut options = FitOptions::new(preset.domain);
        options.resolution = 6;
        options.tolerance = 1e-4;
        let fitted = fit(&g, &options, &ism_format::Progress::none()).unwrap();
        let r = &fitted.report;
        assert!(r.tolerance_met, "{r:?}");
        assert_eq!(
            r.topology,
            Topology {
                components: preset.components,
                euler: preset.euler
            }
        );
        let model = fitted.to_model("circle");
        let errors: Vec<_> = ism_format::structure::check(&model, 100)
            .into_iter()
            .filter(|d| d.severity == ism_format::Severity::Error)
            .collect();
        assert!(errors.is_empty(), "{errors:?}");
        // Compactness: the linear isocomplex on the same grid is far worse.
        let (_, _, linear) = linear_error(&g, &fitted.complex);
        assert!(
            linear > 10.0 * r.max_distance,
            "linear {linear} vs {}",
            r.max_distance
        );
    }

    /// The optimizer's stop ([`LM_DONE_FRACTION`]): a block whose residuals are all within
    /// `lm_done` is left where it is; with no stop, a block that moves lowers its residuals'
    /// sum of squares. Residuals from the closed form: for `g = x² + y² − r²`,
    /// `g/|∇g| = (ρ² − r²)/(2ρ)` at radius `ρ`.
    #[test]
    fn conflict_levels_keep_the_serial_order_of_every_shared_cell() {
        let mut rng: u64 = 0x2545_f491_4f6c_dd1d;
        let mut next = |m: u64| {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            rng % m
        };
        let steps: Vec<(Vec<u32>, bool)> = (0..400)
            .map(|_| {
                let k = next(5) as usize;
                let cells = (0..k).map(|_| next(60) as u32).collect();
                (cells, next(40) == 0)
            })
            .collect();
        let levels = conflict_levels(steps.iter().map(|(c, a)| (&c[..], *a)));
        let mut level_of = vec![usize::MAX; steps.len()];
        for (l, run) in levels.iter().enumerate() {
            assert!(!run.is_empty() && run.windows(2).all(|w| w[0] < w[1]));
            let mut seen = HashSet::new();
            for &i in run {
                assert_eq!(level_of[i], usize::MAX, "step {i} twice");
                level_of[i] = l;
                // Steps that share a level share no cell (a step may repeat its own).
                let own: HashSet<u32> = steps[i].0.iter().copied().collect();
                assert!(
                    own.iter().all(|c| seen.insert(*c)),
                    "level {l} shares a cell"
                );
            }
        }
        assert!(level_of.iter().all(|&l| l != usize::MAX));
        let mut alone = 0;
        for i in 0..steps.len() {
            for j in i + 1..steps.len() {
                if steps[i].1 || steps[j].1 || steps[i].0.iter().any(|c| steps[j].0.contains(c)) {
                    assert!(level_of[i] < level_of[j], "steps {i} and {j}");
                }
            }
            if steps[i].1 {
                alone += 1;
                assert_eq!(levels[level_of[i]], [i]);
            }
        }
        assert!(
            alone >= 3 && levels.len() < steps.len() / 2,
            "{alone}, {}",
            levels.len()
        );
    }

    #[test]
    fn fits_are_the_same_bits_for_any_number_of_threads() {
        let preset = Preset::find("torus").unwrap();
        let g = preset.expression().unwrap();
        let mut options = FitOptions::new(preset.domain);
        options.tolerance = 4e-3;
        let fit_on = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| fit(&g, &options, &ism_format::Progress::none()).unwrap())
        };
        let one = fit_on(1);
        assert!(
            one.report.tolerance_met && one.report.simplices > 3_000,
            "{} simplices, met {}",
            one.report.simplices,
            one.report.tolerance_met
        );
        let bits = |f: &Fitted| {
            let mut entries: Vec<(Vec<u32>, Vec<u64>)> = f
                .map
                .entries()
                .map(|(k, l)| (k.clone(), l.iter().map(|x| x.to_bits()).collect()))
                .collect();
            entries.sort();
            (f.to_model("t"), entries)
        };
        for threads in [2, 3] {
            let other = fit_on(threads);
            assert!(bits(&one) == bits(&other), "{threads} threads");
            // The same report but for the time it took.
            let mut report = other.report.clone();
            report.seconds = one.report.seconds;
            assert_eq!(one.report, report, "{threads} threads");
        }
    }

    #[test]
    fn the_optimizer_stops_once_a_block_is_within_its_done_residual() {
        let preset = Preset::find("circle").unwrap();
        let g = preset.expression().unwrap();
        let radius: f64 = 0.28;
        let mut options = FitOptions::new(preset.domain);
        options.resolution = 6;
        options.tolerance = 1e-2;
        let mut fitter = Fitter::new(&g, &options);
        fitter.set_values_for_new_vertices();
        let crossing = fitter.crossing_cells();
        // Crossing edges placed, no point optimized yet.
        fitter.fit_region(&crossing, false);
        let residuals = |fitter: &Fitter, cells: &[u32], samples: &[Vec<Bary>]| -> Vec<f64> {
            let mut out = Vec::new();
            for (&c, us) in cells.iter().zip(samples) {
                let ids = fitter.complex.cell(c);
                let local = local_of(&fitter.map, &fitter.weights, ids);
                for u in us {
                    let p = fitter.point_of(ids, &local.eval(u));
                    let rho = p[0].hypot(p[1]);
                    out.push((rho * rho - radius * radius) / (2.0 * rho));
                }
            }
            out
        };
        let mut faces: Vec<Vec<u32>> = crossing
            .iter()
            .flat_map(|&c| fitter.faces_of(c))
            .filter(|f| f.len() == 2 && !fitter.is_crossing_edge((f[0], f[1])))
            .collect();
        faces.sort();
        faces.dedup();
        assert!(faces.len() >= 8, "{} faces", faces.len());
        let mut moved = 0;
        for f in &faces {
            let cells = fitter.crossing_cells_with_face(f);
            let samples = fitter.cell_samples(&cells);
            let before = residuals(&fitter, &cells, &samples);
            let worst = before.iter().fold(0.0f64, |m, r| m.max(r.abs()));
            let logits = fitter.map.logits(f);
            // Just above the worst residual (the tape's rounding differs from the closed form's).
            fitter.lm_done = worst * (1.0 + 1e-9);
            assert!(!fitter.optimize(Param::Point(f), &cells, &samples), "{f:?}");
            assert_eq!(
                fitter
                    .map
                    .logits(f)
                    .iter()
                    .map(|x| x.to_bits())
                    .collect::<Vec<_>>(),
                logits.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
                "{f:?}"
            );
            fitter.lm_done = 0.0;
            if fitter.optimize(Param::Point(f), &cells, &samples) {
                moved += 1;
                let after = residuals(&fitter, &cells, &samples);
                let cost = |r: &[f64]| r.iter().map(|x| x * x).sum::<f64>();
                assert!(cost(&after) < cost(&before), "{f:?}");
                assert_ne!(fitter.map.logits(f), logits, "{f:?}");
            } else {
                assert_eq!(fitter.map.logits(f), logits, "{f:?}");
            }
        }
        assert!(2 * moved >= faces.len(), "{moved} of {} moved", faces.len());
    }

    #[test]
    fn fitter_map_agrees_with_the_kernel() {
        // Two independent evaluations of the same parametric map: the closed-form strata here and
        // ism-geom's general Bézier stages on the written model.
        let preset = Preset::find("sphere").unwrap();
        let g = preset.expression().unwrap();
        let mut options = FitOptions::new(preset.domain);
        options.resolution = 3;
        options.tolerance = 1e-2;
        options.rational = true;
        let fitted = fit(&g, &options, &ism_format::Progress::none()).unwrap();
        assert!(fitted.map.num_faces() > 0);
        assert!(fitted.weights.num_faces() > 0);
        // The whole complex: simplex `s` of this model is live cell `s`.
        let model = fitted.full_model("sphere");
        assert_eq!(
            model.stages.last().map(|s| s.kind),
            Some(ism_format::model::StageKind::Rational)
        );
        let eval = ism_geom::ModelEval::new(&model).unwrap();
        let live = fitted.complex.live_cells();
        let mut checked = 0;
        for (s, &c) in live.iter().enumerate() {
            let local = local_of(&fitted.map, &fitted.weights, fitted.complex.cell(c));
            for u in [
                [0.1, 0.2, 0.3, 0.4],
                [0.7, 0.1, 0.1, 0.1],
                [0.25, 0.25, 0.5, 0.0],
            ] {
                let w = local.eval(&u);
                let kernel = eval.param_point(s, &u);
                for k in 0..4 {
                    assert!(
                        (w[k] - kernel.w[k]).abs() < 1e-9,
                        "cell {s}: {w:?} vs {:?}",
                        kernel.w
                    );
                }
                checked += 1;
            }
        }
        assert!(checked > 100);
    }

    /// Largest `|g|/|∇g|` at the patch corners of a written model (the crossings of the edges),
    /// evaluated by the kernel.
    fn corner_error(g: &dyn ImplicitFunction, model: &Model) -> (f64, usize, usize) {
        let eval = ism_geom::ModelEval::new(model).unwrap();
        let mut worst = 0.0f64;
        let mut count = 0;
        let mut exact = 0;
        for s in 0..model.num_simplices() {
            if let Some(patch) = eval.patch(s) {
                for c in &patch.corners {
                    let p = eval.param_point(s, &c.u).p;
                    let d = g.distance_estimate(&p[..model.dim()]);
                    worst = worst.max(d);
                    count += 1;
                    exact += usize::from(d < 1e-12);
                }
            }
        }
        (worst, count, exact)
    }

    #[test]
    fn rational_weights_lower_the_error_and_keep_the_crossings_exact() {
        // On a fixed complex (tolerance never binding), the weights are extra freedom: the fit
        // with them must be clearly better. Measured: circle 6.7e-4 → 4.7e-4, Taubin 1.7e-2 →
        // 1.2e-3. (The circle's optimum moves with the last bits of the vertex values: with
        // `x^2 + y^2 - c` summed as `x^2 + (y^2 - c)`, as before expressions were read left to
        // right, it was 3.3e-4.)
        for (name, resolution, gain) in [("circle", 6, 1.3), ("taubin", 10, 4.0)] {
            let preset = Preset::find(name).unwrap();
            let g = preset.expression().unwrap();
            let mut options = FitOptions::new(preset.domain);
            options.resolution = resolution;
            options.tolerance = 10.0;
            // A tolerance of 10 would let pruning drop every optimized point, and stop the
            // optimizer before its first step.
            options.prune = false;
            options.lm_done_fraction = 0.0;
            let plain = fit(&g, &options, &ism_format::Progress::none()).unwrap();
            options.rational = true;
            let weighted = fit(&g, &options, &ism_format::Progress::none()).unwrap();
            assert_eq!(plain.report.simplices, weighted.report.simplices);
            assert!(weighted.weights.num_faces() > 0);
            // The fit → target direction: the weights act on the fit's own error, and with a
            // tolerance of 10 the target → fit cover is too coarse to compare them.
            let (with, without) = (
                weighted.report.measure.shape_to_target,
                plain.report.measure.shape_to_target,
            );
            assert!(
                with * gain < without,
                "{name}: {with} with weights vs {without} without"
            );
            // Every weight change re-solves the edge points, so the shape still crosses each
            // edge at the root of g (bisection to 2⁻⁶⁰ of the edge) wherever the edge point can
            // reach it; where it cannot (α clamped: a root far from the linear crossing; 6 of
            // 414 Taubin corners on the complex of the bounding-box Plantinga–Vegter test, 8 of
            // 238 on the coarser one of the simplex-restricted test, PV_SPLIT) the weights can
            // only bring it closer.
            let model = weighted.to_model(name);
            let (worst, corners, exact) = corner_error(&g, &model);
            let (plain_worst, _, plain_exact) = corner_error(&g, &plain.to_model(name));
            assert!(corners > 20);
            assert!(
                exact >= plain_exact && exact * 20 >= corners * 19,
                "{name}: {exact}/{corners} exact"
            );
            assert!(
                worst <= plain_worst.max(1e-12),
                "{name}: {worst} vs {plain_worst}"
            );
            if name == "circle" {
                assert_eq!(exact, corners, "{name}: worst crossing off by {worst}");
            }
            let errors: Vec<_> = ism_format::structure::check(&model, 100)
                .into_iter()
                .filter(|d| d.severity == ism_format::Severity::Error)
                .collect();
            assert!(errors.is_empty(), "{errors:?}");
        }
    }

    #[test]
    fn a_heart_with_cusps_and_flat_points_fits_and_names_them() {
        // (x² + y² − 1)³ − x²y³: singular at (0, ±1) and (±1, 0) (∇g = 0 there). Before issue 17
        // the topology phase bisected these until a simplex degenerated (exit 2 after 13–56 s).
        let g = crate::Expression::parse("(x^2+y^2-1)^3-x^2*y^3", 2).unwrap();
        let mut options = FitOptions::new(&[-1.5, 1.5, -1.5, 1.5]);
        options.tolerance = 0.03;
        let fitted = fit(&g, &options, &ism_format::Progress::none()).unwrap();
        let r = &fitted.report;
        assert!(r.tolerance_met, "{r:?}");
        assert!(!r.topology_certified);
        assert_eq!(r.pv_unfinished, 0);
        assert!(r.simplices < 5000, "{}", r.simplices);
        for singular in [[0.0, 1.0], [0.0, -1.0], [1.0, 0.0], [-1.0, 0.0]] {
            let hit = r.uncertain.iter().find(|u| {
                let d = (u.centre[0] - singular[0]).hypot(u.centre[1] - singular[1]);
                d <= u.radius
            });
            let hit = hit.unwrap_or_else(|| panic!("{singular:?} not named: {:?}", r.uncertain));
            assert!(hit.gradient_may_vanish);
            assert!(hit.shape_to_target <= options.tolerance);
            assert!(hit.target_to_shape <= options.tolerance);
        }
        assert!(r.uncertain.len() <= 6, "{:?}", r.uncertain);
    }

    #[test]
    fn the_target_to_fit_direction_sees_what_the_fit_misses() {
        // A fit of the circle r = 0.5 measured against the circle plus a small circle of radius
        // 0.1 around (0.7, 0): every point of the fit is on the target (fit → target is the fit's
        // own error), but the target's point (0.8, 0) is 0.3 from the fit: exactly 0.3 up to
        // the fit's error.
        let circle = crate::Expression::parse("x^2 + y^2 - 0.25", 2).unwrap();
        let domain = [-1.0, 1.0, -1.0, 1.0];
        let mut options = FitOptions::new(&domain);
        options.tolerance = 1e-3;
        let fitted = fit(&circle, &options, &ism_format::Progress::none()).unwrap();
        let own = fitted.report.max_distance;
        assert!(own <= 1e-3);
        let both =
            crate::Expression::parse("(x^2 + y^2 - 0.25)*((x-0.7)^2 + y^2 - 0.01)", 2).unwrap();
        let c = ism_format::IndexedModel::for_evaluation(fitted.to_model("c")).unwrap();
        let m = measure(&both, &c, &domain, 1e-3, &[]).unwrap();
        // Fit → target: every fit point is within `own` of the circle, so of the union; the
        // measure's figure is a certified bound through the product `g` (a bracket along its
        // gradient line, looser than through the circle's own `g`), so it is checked against
        // the tolerance, and against the exact distance to the two circles at its worst point,
        // which it must not undercut.
        assert!(m.shape_to_target <= options.tolerance, "{m:?}");
        let p = &m.shape_to_target_at;
        let exact = (p[0].hypot(p[1]) - 0.5)
            .abs()
            .min(((p[0] - 0.7).hypot(p[1]) - 0.1).abs());
        assert!(exact <= own + 1e-12, "{exact} {own}");
        assert!(m.shape_to_target >= exact - 1e-12, "{m:?}");
        assert!(
            (m.target_to_shape - 0.3).abs() <= own + 1e-6,
            "{}",
            m.target_to_shape
        );
        assert!(m.target_to_shape_bound >= m.target_to_shape);
        assert!(m.target_to_shape_bound <= 0.3 + own + 0.5e-3, "{m:?}");
    }

    /// Points of a 2D model's shape, `per_patch` + 1 per patch, drawn by the kernel, and the
    /// chords between neighbours.
    fn shape_polyline(model: &Model, per_patch: usize) -> Vec<([f64; 2], [f64; 2])> {
        let eval = ism_geom::ModelEval::new(model).unwrap();
        let mut chords = Vec::new();
        for s in 0..model.num_simplices() {
            if let Some(patch) = eval.patch(s) {
                let corners: Vec<Bary> = patch.corners.iter().map(|c| c.u).collect();
                let ps: Vec<[f64; 2]> = patch_samples(&corners, per_patch)
                    .iter()
                    .map(|u| {
                        let p = eval.param_point(s, u).p;
                        [p[0], p[1]]
                    })
                    .collect();
                chords.extend(ps.windows(2).map(|w| (w[0], w[1])));
            }
        }
        chords
    }

    fn to_chords(chords: &[([f64; 2], [f64; 2])], q: [f64; 2]) -> f64 {
        chords
            .iter()
            .map(|(p, r)| {
                let (dx, dy) = (r[0] - p[0], r[1] - p[1]);
                let len2 = (dx * dx + dy * dy).max(f64::MIN_POSITIVE);
                let t = (((q[0] - p[0]) * dx + (q[1] - p[1]) * dy) / len2).clamp(0.0, 1.0);
                (p[0] + t * dx - q[0]).hypot(p[1] + t * dy - q[1])
            })
            .fold(f64::INFINITY, f64::min)
    }

    #[test]
    fn the_accuracy_loop_refines_where_the_fit_misses_part_of_the_target() {
        // Two circles: r = 0.5 about the origin and r = 0.1 about (0.7, 0.03). On the 4×4 Kuhn
        // grid of [−1, 1]² without the topology phase no vertex lies inside the small circle
        // (it crosses the edge (0.5, 0)–(1, 0) twice), so no patch is there and the one-sided
        // error at the fit's samples is fine; only the target → fit direction sees the miss.
        // Ground truth from the circles themselves: exact distances of the fit's points to them,
        // and of dense points of both circles to the fit's chords.
        let g = crate::Expression::parse("(x^2 + y^2 - 0.25)*((x-0.7)^2 + (y-0.03)^2 - 0.01)", 2)
            .unwrap();
        let mut options = FitOptions::new(&[-1.0, 1.0, -1.0, 1.0]);
        options.resolution = 4;
        options.topology = false;
        options.tolerance = 2e-3;
        let fitted = fit(&g, &options, &ism_format::Progress::none()).unwrap();
        let r = &fitted.report;
        assert!(r.tolerance_met, "{:?}", r.measure);
        assert_eq!(r.topology.components, 2, "{r:?}");
        let model = fitted.to_model("two");
        let chords = shape_polyline(&model, 64);
        let to_circles = |p: [f64; 2]| -> f64 {
            let big = (p[0].hypot(p[1]) - 0.5).abs();
            let small = ((p[0] - 0.7).hypot(p[1] - 0.03) - 0.1).abs();
            big.min(small)
        };
        let fit_to_target = chords.iter().map(|c| to_circles(c.0)).fold(0.0, f64::max);
        assert!(fit_to_target <= options.tolerance, "{fit_to_target}");
        let mut target_to_fit = 0.0f64;
        for i in 0..2000 {
            let t = i as f64 * std::f64::consts::TAU / 2000.0;
            for (c, rad) in [([0.0, 0.0], 0.5), ([0.7, 0.03], 0.1)] {
                let q = [c[0] + rad * t.cos(), c[1] + rad * t.sin()];
                target_to_fit = target_to_fit.max(to_chords(&chords, q));
            }
        }
        assert!(target_to_fit <= options.tolerance, "{target_to_fit}");
        // The measure agrees with the truth (an upper bound at its points, up to its cover).
        assert!(r.measure.target_to_shape_bound >= target_to_fit);
    }

    #[test]
    fn the_box_test_of_the_plantinga_vegter_split_never_drops_a_box_that_meets_the_simplex() {
        // Points of a simplex drawn as convex combinations of its corners (ground truth: they
        // are in it by construction); every box around one must be kept, in 2D and 3D, for
        // thin and skewed simplices. And boxes far beyond a facet are dropped.
        let mut seed = 7u64;
        let mut rnd = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        for n in [2usize, 3] {
            for _ in 0..200 {
                let pts: Vec<f64> = (0..(n + 1) * n).map(|_| rnd() * 2.0 - 1.0).collect();
                let ids: Vec<u32> = (0..=n as u32).collect();
                let complex = Complex::from_parts(n, pts.clone(), &ids);
                let Some(meets) = simplex_test(&complex, 0) else {
                    continue;
                };
                for _ in 0..50 {
                    let w: Vec<f64> = (0..=n).map(|_| rnd().powi(3)).collect();
                    let sum: f64 = w.iter().sum();
                    let p: Vec<f64> = (0..n)
                        .map(|k| (0..=n).map(|i| w[i] / sum * pts[i * n + k]).sum())
                        .collect();
                    let r = 1e-3 * rnd();
                    let l: Vec<f64> = p.iter().map(|x| x - r).collect();
                    let h: Vec<f64> = p.iter().map(|x| x + r).collect();
                    assert!(meets(&l, &h), "{pts:?} {p:?}");
                }
                // A small box around a point beyond the facet opposite corner 0 (λ₀ = −1 there:
                // the facet's centroid moved away from corner 0 by their difference) is dropped.
                let p: Vec<f64> = (0..n)
                    .map(|k| {
                        let fc = (1..=n).map(|i| pts[i * n + k]).sum::<f64>() / n as f64;
                        2.0 * fc - pts[k]
                    })
                    .collect();
                let l: Vec<f64> = p.iter().map(|x| x - 1e-9).collect();
                let h: Vec<f64> = p.iter().map(|x| x + 1e-9).collect();
                assert!(!meets(&l, &h), "{pts:?} {p:?}");
            }
        }
    }

    #[test]
    fn the_reported_bounds_hold_against_exact_closest_points_on_a_circle() {
        // A fit of the ellipse x²/0.36 + y²/0.16 = 1 measured against another curve, the circle
        // |p − c| = 0.45 with c = (0.05, 0.02), written as ((x−cx)² + (y−cy)² − r²)³ so that ∇g
        // vanishes on it (a first-order |g|/|∇g| is 6× too small there). Ground truth from the
        // circle's exact closest points: dist(p, Z) = ||p − c| − r| at dense points of the fit
        // drawn by the kernel, and dense exact points of the circle to the fit's dense chords
        // (256 per patch). Every reported bound must hold; every estimate must be within its
        // stated error.
        let ellipse = crate::Expression::parse("x^2/0.36 + y^2/0.16 - 1", 2).unwrap();
        let domain = [-1.0, 1.0, -1.0, 1.0];
        let mut options = FitOptions::new(&domain);
        options.tolerance = 1e-2;
        let model = fit(&ellipse, &options, &ism_format::Progress::none())
            .unwrap()
            .to_model("e");
        let (c, rad) = ([0.05f64, 0.02f64], 0.45f64);
        let circle = crate::Expression::parse("((x-0.05)^2 + (y-0.02)^2 - 0.2025)^3", 2).unwrap();
        let tolerance = 1e-2;
        let indexed = ism_format::IndexedModel::for_evaluation(model.clone()).unwrap();
        let m = measure(&circle, &indexed, &domain, tolerance, &[]).unwrap();
        let chords = shape_polyline(&model, 256);
        let to_circle = |p: [f64; 2]| ((p[0] - c[0]).hypot(p[1] - c[1]) - rad).abs();
        let fit_to_target = chords.iter().map(|ch| to_circle(ch.0)).fold(0.0, f64::max);
        let target_to_fit = (0..4000)
            .map(|i| {
                let t = i as f64 * std::f64::consts::TAU / 4000.0;
                to_chords(&chords, [c[0] + rad * t.cos(), c[1] + rad * t.sin()])
            })
            .fold(0.0, f64::max);
        // The truth is far above the fit's own error (≤ 1e-2): the circle is another curve.
        assert!(
            fit_to_target > 0.1 && target_to_fit > 0.1,
            "{fit_to_target} {target_to_fit}"
        );
        let radius = match m.cover {
            crate::measure::TargetCover::Boxes { largest, .. } => largest,
            _ => panic!("{:?}", m.cover),
        };
        // Bounds over the whole of S and Z.
        assert!(
            m.shape_to_target_bound() >= fit_to_target,
            "{m:?} {fit_to_target}"
        );
        assert!(
            m.target_to_shape_bound >= target_to_fit,
            "{m:?} {target_to_fit}"
        );
        assert!(m.max_bound() >= fit_to_target.max(target_to_fit));
        // Estimates: never above the truth by more than rounding (each is a distance to a point
        // actually found), never below it by more than the stated spacing or cover radius.
        assert!(m.shape_to_target <= fit_to_target * 1.001 + 1e-9, "{m:?}");
        assert!(m.shape_to_target >= fit_to_target - m.shape_cover, "{m:?}");
        assert!(m.target_to_shape <= target_to_fit * 1.001 + 1e-9, "{m:?}");
        assert!(m.target_to_shape >= target_to_fit - radius, "{m:?}");
        // And the bounds are not vacuous.
        assert!(m.max_bound() <= fit_to_target.max(target_to_fit) + radius + m.shape_cover);
    }

    #[test]
    fn the_two_sided_distance_of_an_ellipse_fit_matches_the_analytic_one() {
        // x²/a² + y²/b² = 1 with a = 0.9, b = 0.3. Ground truth independent of the measure: the
        // exact distance from a point to the ellipse (closest parameter by a dense scan refined
        // by ternary search), at points of the fit drawn by the kernel; and the distance from
        // dense points of the ellipse to a dense polyline of the fit (an upper bound).
        let (a, b) = (0.9f64, 0.3f64);
        let g = crate::Expression::parse("x^2/0.81 + y^2/0.09 - 1", 2).unwrap();
        let domain = [-1.0, 1.0, -1.0, 1.0];
        let mut options = FitOptions::new(&domain);
        options.tolerance = 2e-3;
        let fitted = fit(&g, &options, &ism_format::Progress::none()).unwrap();
        let r = &fitted.report;
        assert!(r.tolerance_met, "{r:?}");
        let to_ellipse = |p: [f64; 2]| -> f64 {
            let d = |t: f64| (a * t.cos() - p[0]).hypot(b * t.sin() - p[1]);
            let n = 4000;
            let k = (0..n)
                .map(|i| i as f64 * std::f64::consts::TAU / n as f64)
                .min_by(|x, y| d(*x).total_cmp(&d(*y)))
                .unwrap();
            let (mut lo, mut hi) = (k - 2e-3, k + 2e-3);
            for _ in 0..80 {
                let (m1, m2) = (lo + (hi - lo) / 3.0, hi - (hi - lo) / 3.0);
                if d(m1) < d(m2) {
                    hi = m2;
                } else {
                    lo = m1;
                }
            }
            d(0.5 * (lo + hi))
        };
        let model = fitted.to_model("e");
        let eval = ism_geom::ModelEval::new(&model).unwrap();
        let mut fit_points = Vec::new();
        let mut chords = Vec::new();
        for s in 0..model.num_simplices() {
            if let Some(patch) = eval.patch(s) {
                let corners: Vec<Bary> = patch.corners.iter().map(|c| c.u).collect();
                let ps: Vec<[f64; 2]> = patch_samples(&corners, 200)
                    .iter()
                    .map(|u| {
                        let p = eval.param_point(s, u).p;
                        [p[0], p[1]]
                    })
                    .collect();
                chords.extend(ps.windows(2).map(|w| (w[0], w[1])));
                fit_points.extend(ps);
            }
        }
        let true_fit_to_target = fit_points
            .iter()
            .step_by(7)
            .map(|p| to_ellipse(*p))
            .fold(0.0, f64::max);
        let m = &r.measure;
        // A bound at its samples: never below the truth there by more than the truth can vary
        // between samples, and close to it.
        assert!(
            m.shape_to_target >= 0.9 * true_fit_to_target,
            "{} vs {true_fit_to_target}",
            m.shape_to_target
        );
        assert!(m.shape_to_target <= 1.05 * true_fit_to_target + 1e-6);
        // Distance to the fit's chords between samples 1/200 of a patch apart (they stray from
        // the curve by ~κh²/8, far below the figures compared).
        let to_fit = |q: [f64; 2]| -> f64 {
            chords
                .iter()
                .map(|(p, r)| {
                    let (dx, dy) = (r[0] - p[0], r[1] - p[1]);
                    let len2 = (dx * dx + dy * dy).max(f64::MIN_POSITIVE);
                    let t = (((q[0] - p[0]) * dx + (q[1] - p[1]) * dy) / len2).clamp(0.0, 1.0);
                    (p[0] + t * dx - q[0]).hypot(p[1] + t * dy - q[1])
                })
                .fold(f64::INFINITY, f64::min)
        };
        let true_target_to_fit = (0..2000)
            .map(|i| {
                let t = i as f64 * std::f64::consts::TAU / 2000.0;
                to_fit([a * t.cos(), b * t.sin()])
            })
            .fold(0.0, f64::max);
        let radius = match m.cover {
            crate::measure::TargetCover::Boxes { largest, .. } => largest,
            _ => panic!("{:?}", m.cover),
        };
        assert!(
            m.target_to_shape >= true_target_to_fit - radius
                && m.target_to_shape <= 1.02 * true_target_to_fit + 1e-6,
            "{} vs {true_target_to_fit} (radius {radius})",
            m.target_to_shape
        );
        assert!(m.target_to_shape_bound >= true_target_to_fit);
    }

    /// Pruning drops records and the written shape still meets the tolerance both ways — checked
    /// against the sphere's closed form with the sampler's points (fit → sphere) and sign changes
    /// of the kernel's `F` along radii (sphere → fit), not with the fitter's measure.
    #[test]
    fn pruned_records_keep_the_sphere_within_tolerance() {
        use rand::SeedableRng;
        let preset = Preset::find("sphere").unwrap();
        let g = preset.expression().unwrap();
        let mut options = FitOptions::new(preset.domain);
        options.resolution = 4;
        options.tolerance = 1e-2;
        let records = |m: &Model| m.stages.iter().map(|s| s.faces.len()).sum::<usize>();
        options.prune = false;
        let full = fit(&g, &options, &ism_format::Progress::none()).unwrap();
        options.prune = true;
        let pruned = fit(&g, &options, &ism_format::Progress::none()).unwrap();
        assert!(full.report.tolerance_met && pruned.report.tolerance_met);
        let (a, b) = (full.to_model("a"), pruned.to_model("b"));
        assert!(
            records(&b) < records(&a),
            "{} vs {}",
            records(&b),
            records(&a)
        );
        let tol = options.tolerance;
        let eval = ism_geom::ModelEval::new(&b).unwrap();
        let table =
            ism_sample::SurfaceTable::new(&eval, ism_sample::Weighting::CurvedArea).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let mut worst = 0.0f64;
        for _ in 0..4000 {
            let q = table.draw(&eval, &mut rng).unwrap().p;
            worst = worst.max((q[0].hypot(q[1]).hypot(q[2]) - 0.6).abs());
        }
        assert!(worst <= tol, "fit -> sphere {worst}");
        // Every radius crosses the fit within `tol` of the sphere: F changes sign there.
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        for i in 0..2000 {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / 2000.0;
            let r = (1.0 - z * z).sqrt();
            let d = [
                r * (golden * i as f64).cos(),
                r * (golden * i as f64).sin(),
                z,
            ];
            // Outside the written shell complex is outside the solid (crate::shell).
            let at = |t: f64| eval.value(&[d[0] * t, d[1] * t, d[2] * t]);
            let inside = at(0.6 - tol).is_some_and(|v| v < 0.0);
            let outside = at(0.6 + tol).is_none_or(|v| v > 0.0);
            assert!(inside && outside, "radius {d:?}");
        }
    }

    #[test]
    fn bad_options_are_errors() {
        let g = crate::Expression::parse("x^2 + y^2 - 1", 2).unwrap();
        let mut o = FitOptions::new(&[0.0, 1.0, 0.0, 1.0]);
        o.domain = vec![0.0, 1.0];
        assert!(matches!(
            fit(&g, &o, &ism_format::Progress::none()),
            Err(FitError::Options(_))
        ));
        let mut o = FitOptions::new(&[0.0, 1.0, 1.0, 0.0]);
        assert!(fit(&g, &o, &ism_format::Progress::none()).is_err());
        o.domain = vec![0.0, 1.0, 0.0, 1.0];
        o.tolerance = -1.0;
        assert!(fit(&g, &o, &ism_format::Progress::none()).is_err());
        o.tolerance = 1e-3;
        for bad in [-0.5, f64::NAN, f64::INFINITY] {
            o.lm_done_fraction = bad;
            assert!(matches!(
                fit(&g, &o, &ism_format::Progress::none()),
                Err(FitError::Options(_))
            ));
        }
    }
}
