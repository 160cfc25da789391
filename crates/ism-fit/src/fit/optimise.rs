//! The optimisation of a fit: face-wise Levenberg–Marquardt over blocks of parameters (a face's
//! solitary point, a rational weight), Gauss–Seidel sweeps scheduled in parallel levels, and the
//! pruning of records the tolerance does not need (Mello & Velho 2009, §9.2 step 3).

use super::*;
use crate::rational::LocalRational;
use crate::strata::CellTerms;

/// Sample level of a patch while optimizing and ranking cells (segment points − 1 in 2D, grid
/// level per fan triangle in 3D): enough to see a cubic-like deviation, cheap enough for LM.
pub(super) fn opt_level(n: usize) -> usize {
    if n == 2 {
        8
    } else {
        3
    }
}

/// Gauss–Seidel sweeps over a region's face points in [`Fitter::fit_region`]: 2 before; 4 reach
/// a better optimum on the same complex, so fewer cells fail and more records prune (see
/// [`TOLERANCE_MARGIN`]), for ~15 % more fit time on the torus.
pub(super) const FIT_SWEEPS: usize = 4;

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

/// The most unknowns of a parameter block: the logits of a tetrahedron's interior point.
const MAX_BLOCK: usize = 4;

/// Whether the fitter moves the interior control point of each crossed top simplex (the last
/// stratum, `G_n`). Off: the faces' points alone reach the tolerance on fewer simplices and the
/// file carries no record per crossed top simplex (see [`Fitter::fit_region`]).
pub(super) const OPTIMIZE_TOP_INTERIOR: bool = false;

/// One optimizable parameter block of the fitter.
#[derive(Clone, Copy, Debug)]
pub(super) enum Param<'f> {
    /// The solitary point of a face of ≥ 2 vertices (logits).
    Point(&'f [u32]),
    /// The rational weight of a vertex or an edge (one log-weight).
    Weight(&'f [u32]),
}

/// A parameter block's mapped sample points as a function of its parameter: what
/// [`Fitter::levenberg_marquardt`] moves.
pub(super) trait BlockMap {
    /// The mapped sample points with the parameter at `x`, into `out` (cleared first).
    fn points(&mut self, x: &[f64], out: &mut Vec<[f64; 3]>);
    /// `jac[j·m + i] = n̂ᵢ · ∂pᵢ/∂xⱼ` at `x` (column `j` of `m = pts.len()` rows), where the
    /// points are `pts` and their unit normals `normals`.
    fn jacobian(&mut self, x: &[f64], pts: &[[f64; 3]], normals: &[[f64; 3]], jac: &mut [f64]);
}

/// A face's point over its crossing cells, each cell's map built once with a slot for the face
/// ([`StratifiedMap::local_with`]) and the map before the face's stratum applied to the samples
/// (`before`): a trial moves only the slot. Writes nothing shared, so blocks run in parallel.
pub(super) struct FacePoint<'f, 'a> {
    fitter: &'f Fitter<'a>,
    cells: &'f [u32],
    locals: Vec<(LocalStrata, Slot, Vec<Bary>)>,
    /// Each cell's vertex coordinates (`n` per vertex, the first `(n + 1)·n`), read once per
    /// block or taken from the [`CellCache`].
    corners: Vec<[f64; CORNERS]>,
    /// The number of samples over all cells (the points' vector is reserved at once).
    samples: usize,
}

impl FacePoint<'_, '_> {
    /// [`Fitter::point_of`] on the `k`-th cell from its stored coordinates (the same sums in the
    /// same order).
    fn point_of(&self, k: usize, w: &Bary) -> [f64; 3] {
        let n = self.fitter.n;
        let mut p = [0.0; 3];
        for (i, x) in self.corners[k][..(n + 1) * n].chunks_exact(n).enumerate() {
            for (pk, x) in p.iter_mut().zip(x) {
                *pk += w[i] * x;
            }
        }
        p
    }
}

impl BlockMap for FacePoint<'_, '_> {
    fn points(&mut self, x: &[f64], out: &mut Vec<[f64; 3]>) {
        out.clear();
        out.reserve(self.samples);
        let delta = displacement(x);
        for k in 0..self.cells.len() {
            let (local, slot, _) = &mut self.locals[k];
            local.set_displacement(*slot, &delta);
            let (local, slot, before) = &self.locals[k];
            out.extend(
                before
                    .iter()
                    .map(|v| self.point_of(k, &local.eval_after(v, Some(*slot)))),
            );
        }
    }

    /// The exact derivative of the map in the face's logits.
    fn jacobian(&mut self, x: &[f64], _pts: &[[f64; 3]], normals: &[[f64; 3]], jac: &mut [f64]) {
        let m = normals.len();
        let mut i = 0;
        let mut dw = [[0.0; 4]; 4];
        let dd = displacement_derivative(x);
        let delta = displacement(x);
        for k in 0..self.cells.len() {
            let (local, slot, _) = &mut self.locals[k];
            local.set_displacement(*slot, &delta);
            let (local, slot, before) = &self.locals[k];
            for v in before.iter() {
                local.eval_after_jacobian(v, *slot, &dd, &mut dw);
                for (col, d) in jac.chunks_exact_mut(m).zip(&dw) {
                    let dp = self.point_of(k, d);
                    col[i] = (0..3).map(|e| normals[i][e] * dp[e]).sum::<f64>();
                }
                i += 1;
            }
        }
    }
}

/// Any parameter (a weight moves the crossings too) through the whole map, set in place per trial.
pub(super) struct WholeMap<'f, 'a> {
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
    fn points(&mut self, x: &[f64], out: &mut Vec<[f64; 3]>) {
        *out = self.fitter.block_points(
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
    fn jacobian(&mut self, x: &[f64], pts: &[[f64; 3]], normals: &[[f64; 3]], jac: &mut [f64]) {
        const H: f64 = 1e-7;
        let mut ph = Vec::new();
        for (j, col) in jac.chunks_exact_mut(pts.len()).enumerate() {
            let mut xh = x.to_vec();
            xh[j] += H;
            self.points(&xh, &mut ph);
            for (i, v) in col.iter_mut().enumerate() {
                *v = (0..3)
                    .map(|d| normals[i][d] * (ph[i][d] - pts[i][d]))
                    .sum::<f64>()
                    / H;
            }
        }
    }
}

/// Room for a cell's vertex coordinates (4 vertices of 3 coordinates).
const CORNERS: usize = 12;

/// A cell's vertex coordinates, `n` per vertex, padded with zeros.
fn cell_corners(complex: &Complex, ids: &[u32]) -> [f64; CORNERS] {
    let mut out = [0.0; CORNERS];
    for (o, x) in out
        .iter_mut()
        .zip(ids.iter().flat_map(|&v| complex.point(v).iter()))
    {
        *o = *x;
    }
    out
}

/// What [`Fitter::optimize_point`] reads of each crossing cell of a region fit, kept for all
/// its sweeps: the face terms ([`CellTerms`], updated as the sweeps set points), the rational
/// stage and the vertex coordinates. Only for fits without rational weights: a weight block
/// re-places crossings and changes the rational stage of its star.
pub(super) struct CellCache {
    cells: Vec<(CellTerms, LocalRational, [f64; CORNERS])>,
    /// Per block (the order of the region's blocks): each cell's index in `cells` and the
    /// block's face's index among its faces; empty for a block not taken from the cache.
    places: Vec<Vec<(usize, usize)>>,
}

impl CellCache {
    /// The cache of the point blocks of `blocks` (weight blocks get no places).
    fn new(fitter: &Fitter, blocks: &[Block]) -> CellCache {
        let mut index: HashMap<u32, usize> = HashMap::new();
        let mut cells = Vec::new();
        let places = blocks
            .iter()
            .map(|(param, block_cells, _)| {
                let Param::Point(face) = param else {
                    return Vec::new();
                };
                let places: Option<Vec<(usize, usize)>> = block_cells
                    .iter()
                    .map(|&c| {
                        let at = *index.entry(c).or_insert_with(|| {
                            let ids = fitter.complex.cell(c);
                            cells.push((
                                fitter.map.cell_terms(ids),
                                fitter.weights.local(ids),
                                cell_corners(&fitter.complex, ids),
                            ));
                            cells.len() - 1
                        });
                        Some((at, cells[at].0.face_index(face)?))
                    })
                    .collect();
                places.unwrap_or_default()
            })
            .collect();
        CellCache { cells, places }
    }

    /// Whether block `block` is taken from the cache.
    fn has(&self, block: usize) -> bool {
        !self.places[block].is_empty()
    }

    /// The map of the `k`-th cell of block `block` with a slot for its face, as
    /// [`Fitter::optimize_point`] builds it from the whole map, and the cell's corners.
    fn local(&self, block: usize, k: usize) -> (LocalStrata, Option<Slot>, [f64; CORNERS]) {
        let (at, face) = self.places[block][k];
        let (terms, pre, corners) = &self.cells[at];
        let (local, slot) = terms.local_with(Some(face));
        (local.after(*pre), slot, *corners)
    }

    /// The logits of block `block`'s face: [`StratifiedMap::logits`].
    fn logits(&self, block: usize) -> Vec<f64> {
        let (at, face) = self.places[block][0];
        self.cells[at].0.logits(face).to_vec()
    }

    /// Records that block `block`'s face now has the point with `logits`.
    fn set(&mut self, block: usize, logits: &[f64]) {
        for &(at, face) in &self.places[block] {
            self.cells[at].0.set_logits(face, logits);
        }
    }
}

/// A block's run in a parallel level of [`Fitter::fit_region`]'s sweeps, applied in serial order.
pub(super) enum Run {
    /// Skipped: idle since its last run (checked again when applied, on the same stamps).
    Skipped,
    /// A face point's new logits and whether they moved.
    Done((Vec<f64>, bool)),
}

/// A parameter block of [`Fitter::fit_region`]: the parameter, its crossing cells, their samples.
pub(super) type Block<'f> = (Param<'f>, Vec<u32>, Vec<Vec<Bary>>);

/// The schedule of [`Fitter::fit_region`]'s `sweeps` passes over `blocks` ([`conflict_levels`]
/// of the nodes `sweep × blocks.len() + block`): a weight re-places crossings on its star, so it
/// runs alone.
pub(super) fn sweep_levels(blocks: &[Block], sweeps: usize) -> Vec<Vec<usize>> {
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
pub(super) fn conflict_levels<'c>(
    steps: impl Iterator<Item = (&'c [u32], bool)>,
) -> Vec<Vec<usize>> {
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
pub(super) fn local_of(map: &StratifiedMap, weights: &RationalWeights, ids: &[u32]) -> LocalStrata {
    map.local(ids).after(weights.local(ids))
}

/// Sets the edge-stratum point of the sign-changing edge `e` so that the whole map sends the
/// linear crossing onto the root of `g`. On the edge the strata above the first are the identity
/// and the map is `t ↦ y(R_e(t))` with `y(s) = s + (2α − 1)·s(1 − s)`, so
/// `α = ½ + (root − s)/(2s(1 − s))` at `s = R_e(t*)`.
pub(super) fn place_crossing(
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

impl Fitter<'_> {
    /// Initializes the crossing edges of `cells` and optimizes every other face point of them but
    /// the top simplices' interior points ([`OPTIMIZE_TOP_INTERIOR`]).
    pub(super) fn fit_region(&mut self, cells: &[u32], optimize: bool) {
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
        // The new crossing edges' roots in parallel (60 evaluations of `g` each: for a mesh target
        // these serial nearest-point queries were ~8 % of the bunny's CPU, issue 17, session 23),
        // then kept in the faces' order, as `init_crossing_edge` would one by one.
        type Root = (EdgeKey, (f64, f64), Result<(), FitError>);
        let fresh: Vec<Root> = {
            let fitter = &*self;
            faces
                .par_iter()
                .filter(|f| {
                    f.len() == 2
                        && fitter.is_crossing_edge((f[0], f[1]))
                        && !fitter.roots.contains_key(&(f[0], f[1]))
                })
                .map(|f| {
                    let e = (f[0], f[1]);
                    let (found, zero) = fitter.edge_crossing(e);
                    (e, found, zero)
                })
                .collect()
        };
        for (e, found, zero) in fresh {
            if let Err(trouble) = zero {
                self.trouble.get_or_insert(trouble);
            }
            self.roots.insert(e, found);
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
        let mut cache = (!self.rational).then(|| CellCache::new(self, &blocks));
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
                let cache = cache.as_ref();
                level
                    .par_iter()
                    .map(|&node| {
                        let (param, cells, samples) = &blocks[node % nb];
                        match param {
                            Param::Point(face) if !skipped(node, &idle, &moved) => this
                                .optimize_point(face, cells, samples, cache, node % nb)
                                .map(Run::Done),
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
                let run = match (run, param) {
                    (None, Param::Point(face)) => self
                        .optimize_point(face, cells, samples, cache.as_ref(), node % nb)
                        .map(Run::Done),
                    (run, _) => run,
                };
                let changed = match (run, param) {
                    (Some(Run::Done((x, changed))), Param::Point(face)) => {
                        self.map.set_logits(face, &x);
                        if let Some(cache) = &mut cache {
                            cache.set(node % nb, &x);
                        }
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
    pub(super) fn cell_samples(&self, cells: &[u32]) -> Vec<Vec<Bary>> {
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
    pub(super) fn set_param(
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
    pub(super) fn block_points(
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

    /// `g/|∇g|` and the unit normal `∇g/|∇g|` at each point into `r` and `normals` (cleared
    /// first; `grads` is work space).
    pub(super) fn residuals_at(
        &self,
        points: &[[f64; 3]],
        grads: &mut Vec<(f64, [f64; 3])>,
        r: &mut Vec<f64>,
        normals: &mut Vec<[f64; 3]>,
    ) {
        let n = self.n;
        self.g.gradient_each(points, grads);
        r.clear();
        normals.clear();
        r.reserve(points.len());
        normals.reserve(points.len());
        for (v, grad) in grads.iter() {
            let norm = grad[..n]
                .iter()
                .map(|x| x * x)
                .sum::<f64>()
                .sqrt()
                .max(f64::MIN_POSITIVE);
            r.push(v / norm);
            normals.push([grad[0] / norm, grad[1] / norm, grad[2] / norm]);
        }
    }

    /// Levenberg–Marquardt on one parameter block (≤ 4 unknowns) over the crossing `cells` it acts
    /// on ([`Fitter::levenberg_marquardt`]), on the map in place. Returns whether the parameter
    /// moved.
    pub(super) fn optimize(&mut self, param: Param, cells: &[u32], samples: &[Vec<Bary>]) -> bool {
        if cells.is_empty() {
            return false;
        }
        if let Param::Point(face) = param {
            if let Some((x, moved)) = self.optimize_point(face, cells, samples, None, 0) {
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
    /// With a `cache` that has places for block `block` (this face's), the maps come from it.
    pub(super) fn optimize_point(
        &self,
        face: &[u32],
        cells: &[u32],
        samples: &[Vec<Bary>],
        cache: Option<&CellCache>,
        block: usize,
    ) -> Option<(Vec<f64>, bool)> {
        if cells.is_empty() {
            return None;
        }
        let cache = cache.filter(|c| c.has(block));
        let mut locals = Vec::with_capacity(cells.len());
        let mut corners = Vec::with_capacity(cells.len());
        for (k, (&c, us)) in cells.iter().zip(samples).enumerate() {
            let (local, slot, at) = match cache {
                Some(cache) => cache.local(block, k),
                None => {
                    let ids = self.complex.cell(c);
                    let (local, slot) = self.map.local_with(ids, Some(face));
                    let local = local.after(self.weights.local(ids));
                    (local, slot, cell_corners(&self.complex, ids))
                }
            };
            let slot = slot?;
            let before = us
                .iter()
                .map(|u| local.eval_before(u, Some(slot)))
                .collect();
            locals.push((local, slot, before));
            corners.push(at);
        }
        let x = match cache {
            Some(cache) => cache.logits(block),
            None => self.map.logits(face),
        };
        let samples = samples.iter().map(Vec::len).sum();
        let mut points = FacePoint {
            fitter: self,
            cells,
            locals,
            corners,
            samples,
        };
        Some(self.levenberg_marquardt(&mut points, x, LOGIT_BOUND))
    }

    /// Levenberg–Marquardt from `x` (clamped to `±bound`) on the residuals `r = g/|∇g|` at the
    /// block's points. Hand-written: a dense 4×4 solve is all it needs, and a general solver crate
    /// would not know the softmax and weight clamps. The Jacobian of `r` is `n̂ · ∂p/∂θ` (exact on
    /// the zero set, Gauss–Newton's usual approximation off it), so `g` is evaluated once per
    /// trial. Only improving steps are taken, and none once every residual is within
    /// [`Fitter::lm_done`]. Returns the final parameter and whether it moved.
    pub(super) fn levenberg_marquardt(
        &self,
        block: &mut impl BlockMap,
        mut x: Vec<f64>,
        bound: f64,
    ) -> (Vec<f64>, bool) {
        let k = x.len();
        let mut moved = false;
        // The trial's buffers, swapped with the current ones when a step is taken (no
        // allocation per trial).
        let mut grads = Vec::new();
        let (mut pts, mut r, mut normals) = (Vec::new(), Vec::new(), Vec::new());
        let (mut pn, mut rn, mut nn) = (Vec::new(), Vec::new(), Vec::new());
        let mut xn = Vec::with_capacity(k);
        block.points(&x, &mut pts);
        self.residuals_at(&pts, &mut grads, &mut r, &mut normals);
        let mut cost: f64 = r.iter().map(|v| v * v).sum();
        let mut lambda = 1e-3;
        let mut jac = Vec::new();
        for _ in 0..6 {
            // NaN residuals are never done.
            if r.iter().all(|v| v.abs() <= self.lm_done) {
                break;
            }
            let m = r.len();
            jac.clear();
            jac.resize(k * m, 0.0);
            block.jacobian(&x, &pts, &normals, &mut jac);
            // The normal equations `JᵀJ` and `−Jᵀr`, the same for every trial of this iteration.
            let mut a0 = [0.0; MAX_BLOCK * MAX_BLOCK];
            let mut b0 = [0.0; MAX_BLOCK];
            for i in 0..k {
                let ji = &jac[i * m..(i + 1) * m];
                for j in 0..k {
                    let jj = &jac[j * m..(j + 1) * m];
                    a0[i * k + j] = ji.iter().zip(jj).map(|(p, q)| p * q).sum();
                }
                b0[i] = -ji.iter().zip(&r).map(|(p, q)| p * q).sum::<f64>();
            }
            let mut improved = false;
            for _ in 0..4 {
                let (mut a, mut b) = (a0, b0);
                for i in 0..k {
                    a[i * k + i] += lambda * a[i * k + i] + 1e-12;
                }
                let Some(step) = solve(&mut a[..k * k], &mut b[..k], k) else {
                    break;
                };
                xn.clear();
                xn.extend(
                    x.iter()
                        .zip(&step)
                        .map(|(a, s)| (a + s).clamp(-bound, bound)),
                );
                block.points(&xn, &mut pn);
                self.residuals_at(&pn, &mut grads, &mut rn, &mut nn);
                let cn: f64 = rn.iter().map(|v| v * v).sum();
                if cn < cost {
                    std::mem::swap(&mut x, &mut xn);
                    std::mem::swap(&mut pts, &mut pn);
                    std::mem::swap(&mut r, &mut rn);
                    std::mem::swap(&mut normals, &mut nn);
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

    /// Puts back at its face's centre (no record) every optimized point whose crossing cells
    /// still meet `TOLERANCE_MARGIN × tolerance` at the ranking samples without it: smallest
    /// displacement first. That includes the crossing edges' points, which move the patch corner
    /// from the linear crossing of the values onto `g`'s root: with distance-like values
    /// ([`vertex_value`]) the two are often close enough. A record costs
    /// 48–60 bytes (edge, triangle) against 16 for a tetrahedron's ids, and most of the
    /// optimizer's moves are not needed once the cells are small enough for their worst one.
    /// The accuracy loop checks again afterwards (denser samples), and the two-sided measure
    /// runs on the pruned model.
    pub(super) fn prune(&mut self, tolerance: f64) {
        let centre_gap = |l: &[f64]| {
            let p = crate::strata::softmax(l);
            let c = 1.0 / p.len() as f64;
            p.iter().map(|x| (x - c).abs()).fold(0.0, f64::max)
        };
        let mut faces: Vec<(f64, Vec<u32>)> = self
            .map
            .entries()
            .map(|(f, l)| (centre_gap(l), f.to_vec()))
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
            .map(|(f, l)| (f.to_vec(), l.to_vec()))
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
                            without.set_lattice(this.map.on_lattice());
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
                                <= TOLERANCE_MARGIN * tolerance * this.goal(c)
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
    pub(super) fn refit_star(&mut self, new_vertices: &[u32], optimize: bool) {
        let new_set: HashSet<u32> = new_vertices.iter().copied().collect();
        let region: Vec<u32> = self
            .complex
            .live_cells()
            .into_iter()
            .filter(|&c| self.complex.cell(c).iter().any(|v| new_set.contains(v)))
            .collect();
        self.fit_region(&region, optimize);
    }
}
