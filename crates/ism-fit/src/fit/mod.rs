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
//! 5. The model is measured both ways ([`crate::measure`]); where that misses, the cells there are
//!    bisected and their one-sided goal lowered by the ratio the measure was off by
//!    (`Fitter::tighten_goals`: a rounded crease of a mesh, a peak between samples), and step 4
//!    runs again, for at most [`TWO_SIDED_ROUNDS`] rounds.
//!
//! Modules: `topology` (step 2's Plantinga–Vegter test and its cache), `optimise` (step 3's
//! Levenberg–Marquardt blocks, their parallel schedule, the pruning of records); the loop, the
//! refinement, the report and the model written live here, the two-sided measure in
//! [`crate::measure`].

use std::collections::{HashMap, HashSet};
use std::time::Instant;

use ism_format::indexed::simplex_faces;
use ism_format::model::Model;
use ism_format::progress::{Progress, Step};
use rayon::prelude::*;

use crate::complex::{Complex, EdgeKey};
use crate::expr::ImplicitFunction;
use crate::isocontour::{patch_corners, patch_samples, topology, Bary, Topology};
use crate::measure::{measure_cached_keeping_points, Measure, MeasureCache, Miss};
use crate::rational::{RationalWeights, LOG_WEIGHT_BOUND};
use crate::strata::{
    displacement, displacement_derivative, edge_logits, LocalStrata, Slot, StratifiedMap,
    LOGIT_BOUND,
};
use crate::FitError;

mod optimise;
#[cfg(test)]
mod tests;
pub(crate) mod topology;

pub use optimise::LM_DONE_FRACTION;
use optimise::*;

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
    /// Store every control point on the 2⁻²⁴ lattice ([`StratifiedMap::set_lattice`]), so that
    /// the structured encoding (spec §7.4.3, `.isms`) writes it in 3 bytes per free coordinate
    /// instead of 8 per coordinate. The fit measures the rounded points it writes. Off by
    /// default: rounding moves a point by up to 2⁻²⁵ of its face, so edge crossings are no
    /// longer exactly at the roots of `g` (within ~10⁻⁹ of the edge).
    pub lattice: bool,
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
            lattice: false,
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

/// Below this fraction of `max |g|` on the initial grid a value of `g` found by bisection counts as
/// a zero whatever the edge's ends say (`Fitter::root_is_a_zero`): a zero of high order, where
/// the ends' values are tiny too and rounding orders them arbitrarily.
pub const ROOT_ZERO_FRACTION: f64 = 1e-12;

/// Barycentric slack of [`Fitter::contains`] and of the box test of the Plantinga–Vegter split
/// (`simplex_test`): a point on a shared facet belongs to both cells (refining both is harmless),
/// and rounding must not put it in neither, nor drop a box that meets the cell.
const CONTAINS_SLACK: f64 = 1e-9;

/// Rounds of the two-sided accuracy loop: measure both directions on the model, refine where it
/// misses, re-fit. Each round costs a full measurement (most of a fit's time at fine
/// tolerances); misses that refinement cannot fix (a singular point at the minimum cell size)
/// end the loop earlier, as does [`FitOptions::max_simplices`]. Ten since session 24: with the
/// misses of a mesh's cover only where a point of the mesh is far from the fit, the bunny at
/// 7.24e-4 fell from 233 k missing points to 144 over the six rounds there were, ending at
/// 1.03× the tolerance; the bone at 1.06e-3 from 97 k to 2.3 k (issue 17).
pub const TWO_SIDED_ROUNDS: usize = 10;

/// The lowest a two-sided round sets a place's one-sided goal, as a fraction of the tolerance
/// (`Fitter::tighten_goals`). Where the fit is farther from the target than
/// `1 / GOAL_FLOOR` times its own one-sided error, a tighter one-sided goal is not what is
/// missing (a feature of the target no patch comes near): the miss's cells are bisected
/// (`Fitter::refine_misses`) instead of aiming ever lower.
pub const GOAL_FLOOR: f64 = 0.25;

/// Distance, as a fraction of the tolerance (or of a thousandth of the domain's diagonal where that
/// is smaller: a tolerance beyond it binds nothing, and the clearance must stay far below the
/// cells' size), that the fit keeps between its shape and every vertex of the complex
/// ([`vertex_clearance`], used by [`vertex_value`] and `Fitter::edge_crossing`). Where the target
/// passes through a grid vertex (the thin ellipsoid `x²/0.81 + y²/0.09 + z²/0.0036 = 1` at its
/// pole `(0, 0.3, 0)`, where `g` rounds to 1.1e-16) the crossings of every edge at that vertex sat
/// within 1e-17 of it and of each other, and the export had 48 triangles of no area there (the
/// round trip failed). Kept this far apart (2e-7 at that fit's tolerance 2e-4, on coordinates
/// of 0.3) they stay distinct even in a glTF export's f32; the shape moves by at most this, which
/// the fit's own measure sees like any other error.
pub const VERTEX_CLEARANCE: f64 = 1e-3;

/// The distance a fit with `options` keeps between its shape and the vertices: [`VERTEX_CLEARANCE`]
/// of the tolerance or of a thousandth of the domain's diagonal, whichever is smaller.
pub fn vertex_clearance(options: &FitOptions) -> f64 {
    VERTEX_CLEARANCE * options.tolerance.min(1e-3 * diagonal(&options.domain))
}

/// The length of the diagonal of `domain` (`[lo, hi]` per axis).
fn diagonal(domain: &[f64]) -> f64 {
    domain
        .chunks(2)
        .map(|c| (c[1] - c[0]).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// `f(v)` for a vertex at `p`: the first-order signed distance `g(p)/|∇g(p)|` (just `g(p)` where
/// the gradient vanishes or is not finite), at least `clearance` in magnitude (`+clearance` where
/// `g` is 0: such a vertex is treated as outside; deterministic and documented in the CLI help).
/// Only the signs fix the complex's crossings, but the values also place the linear patch's
/// corner on each crossing edge (`t* = f_a/(f_a − f_b)`): on a first-order distance it lies next
/// to `g`'s root where the shape is smooth, so many crossing edges need no record of their own
/// (see `Fitter::prune`). With `g` itself (a quartic for the torus) the corner is off by about
/// the tolerance on almost every edge. Sphere preset at 2e-3: 113,000 → 95,524 bytes, torus
/// 420,255 → 292,311 (BENCHMARKS.md, issue 17). The floor keeps the corners apart where the shape
/// passes through a vertex ([`VERTEX_CLEARANCE`]).
pub fn vertex_value(g: &dyn ImplicitFunction, p: &[f64], clearance: f64) -> f64 {
    let mut grad = [0.0; 3];
    let n = g.dim();
    let v = g.gradient(p, &mut grad[..n]);
    let norm = grad[..n].iter().map(|x| x * x).sum::<f64>().sqrt();
    let v = if norm > 0.0 && norm.is_finite() {
        v / norm
    } else {
        v
    };
    let clearance = clearance.max(f64::MIN_POSITIVE);
    if !v.is_finite() || v.abs() < clearance {
        // 0 (either sign) counts as outside; so does NaN, which the caller reports.
        if v < 0.0 {
            -clearance
        } else {
            clearance
        }
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
    /// [`vertex_clearance`] of the options: the least distance kept between the shape and a
    /// vertex.
    clearance: f64,
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
    /// Boxes of the domain where the two-sided measure found the fit farther from the target
    /// than the tolerance although the cells there met their one-sided goal, each with the
    /// fraction of the tolerance the cells meeting it must aim at ([`Fitter::goal`],
    /// [`Fitter::tighten_goals`]). Geometric, so the cells a refinement makes there inherit it.
    goals: rstar::RTree<GoalBox>,
}

/// A box of [`Fitter::goals`] and its fraction of the tolerance.
type GoalBox = rstar::primitives::GeomWithData<rstar::primitives::Rectangle<[f64; 3]>, f64>;

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
            map: {
                let mut map = StratifiedMap::new(n);
                map.set_lattice(options.lattice);
                map
            },
            weights: RationalWeights::new(n),
            roots: HashMap::new(),
            rational: options.rational,
            scale,
            clearance: vertex_clearance(options),
            reach: diagonal(&options.domain),
            bisections: 0,
            trouble: None,
            errors: [HashMap::new(), HashMap::new()],
            pv: HashMap::new(),
            lm_done: options.lm_done_fraction * options.tolerance,
            goals: rstar::RTree::new(),
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
        self.edge_length(self.complex.longest_edge(c))
    }

    /// The length of the edge from vertex `a` to vertex `b`.
    fn edge_length(&self, (a, b): EdgeKey) -> f64 {
        let (pa, pb) = (self.complex.point(a), self.complex.point(b));
        pa.iter()
            .zip(pb)
            .map(|(x, y)| (x - y) * (x - y))
            .sum::<f64>()
            .sqrt()
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
            let x = vertex_value(self.g, &p, self.clearance);
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
            let (found, zero) = self.edge_crossing(e);
            if let Err(trouble) = zero {
                self.trouble.get_or_insert(trouble);
            }
            self.roots.insert(e, found);
        }
        place_crossing(&self.roots, &self.weights, &mut self.map, e);
    }

    /// `(t*, root)` of a sign-changing edge, both as the weight of its second vertex, with the root
    /// at least the clearance ([`vertex_clearance`]) from either end (where the target passes
    /// through a vertex, the roots of all its edges would otherwise meet there), and whether the
    /// sign change bisection found is a zero of `g` ([`Fitter::root_is_a_zero`], judged where it
    /// was found).
    pub(super) fn edge_crossing(&self, e: EdgeKey) -> ((f64, f64), Result<(), FitError>) {
        let (t, root) = self.edge_root(e);
        let zero = self.root_is_a_zero(e, root);
        let margin = (self.clearance / self.edge_length(e)).min(0.5);
        ((t, root.clamp(margin, 1.0 - margin)), zero)
    }

    /// `(t*, root)` of a sign-changing edge, both as the weight of its second vertex: the root by
    /// bisection of `g` along the edge.
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
        if v.abs() > ends && v.abs() > ROOT_ZERO_FRACTION * self.scale {
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
                .filter(|e| e.1 > TOLERANCE_MARGIN * options.tolerance * self.goal(e.0))
                .collect();
            if bad.is_empty() {
                // Before stopping, the report's own (denser) samples: a patch can peak between
                // the ranking samples, most with rational weights.
                bad = self.cell_errors(min_cell, true, options.tolerance);
                bad.retain(|e| e.1 > options.tolerance * self.goal(e.0));
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

    /// The fraction of the tolerance that cell `c`'s one-sided error must meet: 1, or the
    /// smallest of the [`Fitter::goals`] boxes that meet the cell's bounding box.
    fn goal(&self, c: u32) -> f64 {
        if self.goals.size() == 0 {
            return 1.0;
        }
        let (lo, hi) = self.complex.bounding_box(c);
        self.goal_in(&lo, &hi)
    }

    /// The smallest goal of the boxes meeting the box `lo`–`hi` (1 where none does).
    fn goal_in(&self, lo: &[f64], hi: &[f64]) -> f64 {
        let (mut a, mut b) = ([0.0; 3], [0.0; 3]);
        a[..self.n].copy_from_slice(&lo[..self.n]);
        b[..self.n].copy_from_slice(&hi[..self.n]);
        self.goals
            .locate_in_envelope_intersecting(rstar::AABB::from_corners(a, b))
            .map(|g| g.data)
            .fold(1.0, f64::min)
    }

    /// Lowers the one-sided goal where the two-sided measure missed (issue 17, session 25). The
    /// accuracy loop (its refinement and [`Fitter::prune`]) aims every cell's own samples at
    /// [`TOLERANCE_MARGIN`] of the tolerance; where the target has creases and corners (a
    /// triangle mesh) or the fit's error peaks between those samples, that leaves the true
    /// two-sided distance up to ~1.3× the tolerance (a patch that rounds a crease of angle `θ`
    /// within `e` of both faces is `e / cos(θ/2)` from its edge). Refining those cells did not
    /// settle it while the next round's pruning aimed them at the same margin again: the bone
    /// mesh's misses moved to other cells every round. So each miss of `distance` `d` lowers
    /// the goal of the cells around it to `min(goal there, e/t) · t/d` (`e`: the largest
    /// one-sided error of the crossing cells there, `t` the tolerance), the ratio it was off by,
    /// never below [`GOAL_FLOOR`]; the region is the miss's cell (a sample of the fit) or the
    /// box within `d` of the point (a point of the target). Returns whether a goal was lowered.
    fn tighten_goals(&mut self, misses: &[Miss], tolerance: f64) -> bool {
        let live = self.complex.live_cells();
        let n = self.n;
        let tree = self.cell_tree(&live);
        // The report-level error of every crossing cell near a miss, once.
        let mut error: HashMap<u32, f64> = HashMap::new();
        let mut boxes: Vec<GoalBox> = Vec::new();
        for m in misses {
            if !(m.distance.is_finite() && m.distance > tolerance) {
                continue;
            }
            let (lo, hi, cells): (Vec<f64>, Vec<f64>, Vec<u32>) = match m.simplex {
                Some(s) => match live.get(s) {
                    Some(&c) => {
                        let (lo, hi) = self.complex.bounding_box(c);
                        (lo, hi, vec![c])
                    }
                    None => continue,
                },
                None => {
                    let lo: Vec<f64> = (0..n).map(|k| m.at[k] - m.distance).collect();
                    let hi: Vec<f64> = (0..n).map(|k| m.at[k] + m.distance).collect();
                    let (mut a, mut b) = ([0.0; 3], [0.0; 3]);
                    a[..n].copy_from_slice(&lo);
                    b[..n].copy_from_slice(&hi);
                    let cells = tree
                        .locate_in_envelope_intersecting(rstar::AABB::from_corners(a, b))
                        .map(|b| b.data)
                        .collect();
                    (lo, hi, cells)
                }
            };
            let mut e = 0.0f64;
            for c in cells {
                if self.is_crossing(c) {
                    let x = match error.get(&c) {
                        Some(&x) => x,
                        None => {
                            let x = match self.errors[1].get(&c) {
                                Some(&x) => x,
                                None => self.cell_error(c, report_level(n), tolerance),
                            };
                            error.insert(c, x);
                            x
                        }
                    };
                    e = e.max(x);
                }
            }
            let now = self.goal_in(&lo, &hi);
            let goal = (now.min(e / tolerance) * tolerance / m.distance).max(GOAL_FLOOR);
            if goal < now {
                let (mut a, mut b) = ([0.0; 3], [0.0; 3]);
                a[..n].copy_from_slice(&lo);
                b[..n].copy_from_slice(&hi);
                boxes.push(GoalBox::new(
                    rstar::primitives::Rectangle::from_corners(a, b),
                    goal,
                ));
            }
        }
        let lowered = !boxes.is_empty();
        for b in boxes {
            self.goals.insert(b);
        }
        lowered
    }

    /// An R-tree of the bounding boxes of the cells `live`, each with its id.
    fn cell_tree(
        &self,
        live: &[u32],
    ) -> rstar::RTree<rstar::primitives::GeomWithData<rstar::primitives::Rectangle<[f64; 3]>, u32>>
    {
        let n = self.n;
        let boxes = live
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
        rstar::RTree::bulk_load(boxes)
    }

    /// Bisects the cells where a two-sided measurement found the fit farther than the
    /// tolerance from the target: the simplex of a sample of `S`, the cell holding a point of
    /// `Z` (its vertices may all have one sign, so no patch is there yet) and the cells whose
    /// bounding boxes come within the miss's distance of it — those with a longest
    /// edge of at least `min_cell`, within `max_simplices`. Returns the new vertices.
    fn refine_misses(&mut self, misses: &[Miss], min_cell: f64, max_simplices: usize) -> Vec<u32> {
        let live = self.complex.live_cells();
        let n = self.n;
        let tree = self.cell_tree(&live);
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
        let (mut m, points) = measure_cached_keeping_points(
            g,
            &model,
            &options.domain,
            options.tolerance,
            &mut measure_cache,
        )
        .map_err(FitError::Eval)?;
        let done = m.meets(options.tolerance)
            || rounds == TWO_SIDED_ROUNDS
            || fitter.complex.num_cells() >= options.max_simplices;
        let (lowered, new_vertices) = if done {
            (false, Vec::new())
        } else {
            (
                fitter.tighten_goals(&m.misses, options.tolerance),
                fitter.refine_misses(&m.misses, min_cell, options.max_simplices),
            )
        };
        if new_vertices.is_empty() && !lowered {
            // The final complex's Plantinga–Vegter status, whether or not the topology phase
            // ran, and the errors near the cells that fail it. Only the final complex's: the
            // rounds before do not read it (it was tested after every round until session 23:
            // 17,053 cell tests for the bunny at 1e-2, 13,308 for its final complex alone).
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
            let regions: Vec<(Vec<f64>, f64)> = clusters
                .iter()
                .map(|c| (c.centre.clone(), c.radius + options.tolerance))
                .collect();
            m.regions = points.regions(&regions);
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

    /// [`Fitted::to_model`]'s complex as the Kuhn grid the fit started from and the edges it split
    /// (spec `ism-format.md` §7.4.3, `complexForm` 1): what `ism fit` writes into a `.isms`
    /// instead of the coordinates and ids. `None` for a complex not refined from a grid.
    pub fn refinement(&self) -> Option<ism_format::refine::KuhnRefinement> {
        // The written model's level is 0 (`model_of`) and its simplices the live cells in order.
        let cells = self.complex.compact_cells();
        let m = self.complex.dim() + 1;
        let kept = crate::shell::kept_simplices(&cells, m, &self.values, 0.0);
        self.complex.refinement(kept)
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
    // The linear isocomplex as it is: no clearance but the least that makes an exact zero
    // positive.
    let values: Vec<f64> = (0..complex.num_vertices() as u32)
        .map(|v| vertex_value(g, complex.point(v), f64::MIN_POSITIVE))
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
