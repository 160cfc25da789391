//! Certified upper bounds of the area element of the parametric map, per top simplex.
//!
//! In simplex σ with edge matrix `E` (columns `v_l − v_0`), let `K = W ∘ X ∘ W⁻¹` be the deformation
//! in point space, so `F = F_lin ∘ K` and the shape is `O ∩ σ = K⁻¹(θ)` with `θ` the linear patch.
//! The area element of `K⁻¹` restricted to `θ` (length element in 2D) is
//!
//! `J = |∇F(p)| / (|∇F_lin| · det DK(p))`,
//!
//! because `∇F = DKᵀ ∇F_lin` and a map `H` scales the area of a hypersurface with unit normal `ν` by
//! `|det DH| · |DH⁻ᵀ ν|` (here `H = K⁻¹`). With the stages `X = X_{m−1} ∘ … ∘ X_0` and
//! `M_k = E · DX_k · E⁻¹` (stage `k` in point space, evaluated on the way), `DK = M_{m−1} ⋯ M_0`, so
//!
//! `J ≤ Π_k sup‖M_k‖₂ / inf det M_k`,
//!
//! each sup and inf over the whole simplex (every stage maps the simplex onto itself, so wherever the
//! intermediate point lies, it is covered). Each factor comes from Bernstein coefficients:
//! the Jacobian entries of a polynomial stage are Bernstein polynomials, so `‖M(w)‖₂ ≤ max_K
//! ‖E D_K E⁻¹‖_F` by convexity of the norm; `det DX` is a Bernstein polynomial whose smallest
//! coefficient bounds it from below (refined by edge bisection while the bound is loose). Rational
//! and monotonic stages are quotients `P/Q` (monotonic: `P_i(w) = g_i(w_i)` written in the simplex's
//! Bernstein basis of degree `d`, `Q = Σ P_i`), bounded through the numerator `N = DP·Q − P ∇Qᵀ` and
//! the range of `Q`. A stage stored in the parametric direction (`S = X_k⁻¹`) uses
//! `‖S⁻¹‖ ≤ ‖S‖^{n−1}/det S` and `det X_k = 1/det S`.

use std::borrow::Borrow;

use ism_format::{Direction, StageKind};
use ism_geom::{linalg, Bary, Bernstein, LocalMap, LocalStage, Mat, MAX_VARS};

/// Relative margin added to a bound for floating-point rounding in the Bernstein products, norms and
/// determinants that produce it: these are sums of at most a few thousand products of numbers of
/// order one, whose relative rounding error is below `1e-12`; `1e-9` leaves three orders to spare
/// and costs nothing measurable in acceptance rate.
pub const BOUND_ROUNDING_MARGIN: f64 = 1e-9;

/// Most bisections spent tightening one stage's bound on one simplex: bounds the cost per simplex
/// (each split restricts `n² + 3` polynomials). Only the worst cell is split, and refinement stops
/// as soon as it is within `DET_TIGHTNESS` of the exact vertex values, so near-identity stages
/// (stratified models) stop after few or no splits.
const MAX_SPLITS: usize = 32;

/// Deepest bisection of one cell (cells at this depth are at most `2^(-depth/C(m,2))` of the
/// simplex in every direction).
const MAX_DEPTH: u32 = 24;

/// A cell's certified factor is accepted once the factor at the cell's vertices (exact values, so a
/// lower estimate of the supremum) is at least this fraction of it; otherwise the cell is bisected.
/// 0.85 keeps the sampler's acceptance rate within 15 % of what the exact supremum would give.
const DET_TIGHTNESS: f64 = 0.85;

/// The bound of one stage on one simplex.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StageBound {
    /// A certified upper bound of `‖M(w)‖₂ / det M(w)` over the simplex (`M = E DX E⁻¹` of the
    /// implicit-direction map `X`): the stage's factor in the bound of the area element. Computed
    /// per bisection cell as `sup_cell ‖M‖ / inf_cell det M`, maximized over the cells.
    pub factor: f64,
}

/// Bound of the area element `J` over a whole simplex: the product of its stages' factors, with the
/// rounding margin. `Err` says which stage could not be bounded and why.
pub fn area_element_bound(map: &LocalMap, edges: &Mat) -> Result<f64, (usize, String)> {
    let n = map.vars() - 1;
    let inv = linalg::inverse(n, edges).ok_or((0, "degenerate simplex".to_string()))?;
    let mut bound = 1.0;
    for (k, stage) in map.stages().iter().enumerate() {
        let b = stage_bound(stage, edges, &inv).map_err(|e| (k, e))?;
        bound *= b.factor;
    }
    if !bound.is_finite() {
        return Err((0, format!("area-element bound is {bound}")));
    }
    Ok(bound * (1.0 + BOUND_ROUNDING_MARGIN))
}

/// Most bisections spent on the last stage's surface-restricted bound: the level set is a
/// hypersurface, so halving the cell size roughly doubles (2D) or quadruples (3D) the cells that
/// cross it; 96 reaches cells of about 1/8 of the simplex around a typical patch.
pub(crate) const MAX_SURFACE_SPLITS: usize = 96;

/// Most bisections of the second round of the surface-restricted bound, for its cells
/// ([`CellBounds`]): that round splits a cell only while the area its bound wastes pays for the
/// split (the caller's `min_excess`), so this cap binds only for tables of very many samples.
/// Measured on the torus example (its 488 patches fuse; one thread, table alone, under load):
/// 96 / 384 / 1,536 bisections bound 97.4 / 65.2 / 48.3 of area (true area 5.9) for 10⁵
/// samples in 1.0 / 0.9 / 1.3 s, and 88.6 / 53.4 / 28.3 for 10⁷ in 1.6 / 2.5 / 6.2 s; whole
/// `ism sample --surface 10⁵` 0.44 / 0.33 / 0.31× the CPU of the fixed regions' single bound.
pub(crate) const MAX_CELL_SPLITS: usize = 1536;

/// Bound of the area element `J` on the part of a simplex where the shape lies: like
/// [`area_element_bound`], except that the last stage (when stored in the implicit direction)
/// contributes `sup |Mᵀν| / det M` (the exact factor of `J` for a single stage, `ν` the unit normal
/// of the linear patch) over only the bisection cells its level set `f·X(v) = c` can cross, instead
/// of `sup ‖M‖ / inf det M` over the whole simplex. `values` are `f` at the simplex's vertices
/// (stored order) and `level` is `c`.
pub fn surface_area_element_bound(
    map: &LocalMap,
    edges: &Mat,
    values: &[f64],
    level: f64,
) -> Result<f64, (usize, String)> {
    surface_bound(map, edges, values, level, None).map(|b| b.top)
}

/// [`surface_area_element_bound`] of `map` with each implicit projective stage fused into the
/// implicit net after it ([`LocalMap::fused`]: the spec examples' "vertex weights, then level
/// crossings" pair as one rational stage), its last stage restricted to the surface alone (no
/// whole-simplex factor) in at most `max_splits` bisections, and only while the bound's excess
/// over the largest value seen (in units of `J`) is above `min_excess` (the chain bound's test,
/// `tightening_pays`; 0: refined until tight or out of splits); `None` when
/// nothing fuses or that bound is not finite, and the caller keeps the stored map's.
///
/// The stored pair's factors are bounded apart — the projective stage's over the whole simplex,
/// where its determinant (a power of `Σ a_j w_j`) spans the ratio of the extreme scales — so
/// their product is loose by that ratio; the fused stage is bounded as one map near the shape.
/// Measured on the torus example (its 21 patches that take a per-stage bound in a one-sample
/// table): 9–24× tighter on the worst eight (e.g. 7.7·10³ against 1.9·10⁵, exact `J` there
/// at most 3.2), the whole table's bounded area 7.1·10³ against 3.8·10⁴. The whole-simplex
/// factor of the fused stage (a rational stage of degree `d` whose numerators have degree `2d`)
/// cost five times its restricted factor there and never was the smaller, so it is not formed.
/// The fused weights `q_I a^I` are the stored ones times products of at most `d` stored scales,
/// rounded: the fused `J` differs from the stored map's by rounding, which
/// [`BOUND_ROUNDING_MARGIN`] covers as it covers the evaluation's own (as for the chain bound's
/// fused roots).
pub fn fused_surface_area_element_bound(
    map: &LocalMap,
    edges: &Mat,
    values: &[f64],
    level: f64,
    max_splits: usize,
    min_excess: f64,
) -> Option<CellBounds> {
    let fused = fused_projective(map)?;
    surface_bound(&fused, edges, values, level, Some((max_splits, min_excess)))
        .ok()
        .filter(|b| b.top.is_finite())
}

/// Slack of the box comparisons in [`CellBounds::over`]: above the residual the sampler accepts
/// of its inverse (`1e-9` in `u`), so the cell holding the preimage `J` is evaluated at is counted
/// for the region its `u` was drawn from, even where that preimage maps just outside it.
pub const CELL_BOX_SLACK: f64 = 1e-8;

/// A leaf cell of the surface-restricted bound: the box of `u` it maps into and its bound.
type LeafCell = (Bary, Bary, f64);

/// A certified bound of the area element `J` on the shape in one simplex, with the bisection
/// cells it came from: per cell, a box of the parameter points `u = X(w)` of the cell (the last
/// stage's components' ranges) and the cell's own bound. A part of the patch (a sampler region)
/// takes the largest bound of the cells whose box meets its own ([`CellBounds::over`]): every
/// point of the shape over that part lies in such a cell, so that is certified too, and far below
/// the whole simplex's where `J` peaks in one corner (a projective stage with weights far apart).
#[derive(Clone, Debug)]
pub struct CellBounds {
    top: f64,
    /// `(lo, hi, bound)` per leaf cell (the first `vars` coordinates of the boxes used); empty
    /// when the boxes could not be formed (a denominator with a coefficient ≤ 0).
    cells: Vec<LeafCell>,
    vars: usize,
}

impl CellBounds {
    /// A bound `top` over the whole simplex, without cells.
    pub(crate) fn whole(top: f64, vars: usize) -> CellBounds {
        CellBounds {
            top,
            cells: Vec::new(),
            vars,
        }
    }

    /// The bound over the whole simplex (the largest cell's).
    pub fn top(&self) -> f64 {
        self.top
    }

    /// The bound over the shape's points whose parameter `u` lies in the box `[lo, hi]`
    /// (barycentric coordinates): the largest bound of the cells whose box meets it, and
    /// [`CellBounds::top`] when none does (a box that holds points of the shape always meets
    /// one; rounding at a box's edge must not give it less than the whole bound).
    pub fn over(&self, lo: &[f64], hi: &[f64]) -> f64 {
        let mut best: Option<f64> = None;
        for (clo, chi, b) in &self.cells {
            if (0..self.vars)
                .all(|k| clo[k] <= hi[k] + CELL_BOX_SLACK && chi[k] >= lo[k] - CELL_BOX_SLACK)
            {
                // NaN is never a pass: such a cell bounds nothing.
                let b = if b.is_nan() { f64::INFINITY } else { *b };
                best = Some(best.map_or(b, |x: f64| x.max(b)));
            }
        }
        best.unwrap_or(self.top)
    }
}

/// `map` with each implicit projective stage fused into the next ([`LocalMap::fused`]), when
/// that leaves fewer stages; `None` when nothing fuses.
pub(crate) fn fused_projective(map: &LocalMap) -> Option<LocalMap> {
    let fused = map.clone().fused();
    (fused.stages().len() < map.stages().len()).then_some(fused)
}

/// [`surface_area_element_bound`] (`restricted_only: None`), or with the last stage's factor
/// restricted to the surface alone: `Some((max_splits, min_excess))` as
/// [`fused_surface_area_element_bound`] takes them.
fn surface_bound(
    map: &LocalMap,
    edges: &Mat,
    values: &[f64],
    level: f64,
    restricted_only: Option<(usize, f64)>,
) -> Result<CellBounds, (usize, String)> {
    let n = map.vars() - 1;
    let whole = |top: f64| CellBounds::whole(top, n + 1);
    let stages = map.stages();
    let Some(last) = stages.last() else {
        return Ok(whole(1.0));
    };
    if last.direction() == Direction::Parametric {
        return area_element_bound(map, edges).map(whole);
    }
    let inv = linalg::inverse(n, edges).ok_or((0, "degenerate simplex".to_string()))?;
    let mut bound = 1.0;
    for (k, stage) in stages[..stages.len() - 1].iter().enumerate() {
        bound *= stage_bound(stage, edges, &inv).map_err(|e| (k, e))?.factor;
    }
    let k = stages.len() - 1;
    let (splits, enough) = match restricted_only {
        // The last factor's excess counts `bound` times in `J`'s.
        Some((splits, min_excess)) => (splits, min_excess / bound),
        None => (MAX_SURFACE_SPLITS, 0.0),
    };
    let (restricted, leaves) = surface_stage_factor(
        last,
        &inv,
        values,
        level,
        splits,
        enough,
        restricted_only.is_some(),
    )
    .map_err(|e| (k, e))?;
    // Both factors are certified; the restricted one is usually far smaller, but its vector-norm
    // bound (componentwise maxima) can lose to the whole-simplex one on nearly affine stages.
    let top = bound
        * match restricted_only {
            None => restricted.min(stage_bound(last, edges, &inv).map_err(|e| (k, e))?.factor),
            Some(_) => restricted,
        };
    if !top.is_finite() {
        return Err((0, format!("area-element bound is {top}")));
    }
    let scale = bound * (1.0 + BOUND_ROUNDING_MARGIN);
    Ok(CellBounds {
        top: top * (1.0 + BOUND_ROUNDING_MARGIN),
        cells: leaves
            .into_iter()
            .map(|(lo, hi, b)| (lo, hi, b * scale))
            .collect(),
        vars: n + 1,
    })
}

/// A cell of the surface-restricted bound: `F − c` (times `Q`), the components of
/// `E⁻ᵀ ∇_w F` (times `Q²`), `Q²`, `det DX` (times its denominator `Q^{n+1}`,
/// [`det_over_denominator`]) and that denominator, restricted to the cell.
struct SurfaceCell {
    cross: Bernstein,
    grad: Vec<Bernstein>,
    q2: Option<Bernstein>,
    det: Bernstein,
    q2n: Option<Bernstein>,
    /// The stage's components `P_i` and denominator `Q` restricted to the cell, for the box of
    /// `u` the cell maps into (empty when not asked for: [`CellBounds`]).
    comps: Vec<Bernstein>,
    q: Option<Bernstein>,
    depth: u32,
}

impl SurfaceCell {
    fn split(&self, m: usize) -> (SurfaceCell, SurfaceCell) {
        let pairs: Vec<(usize, usize)> = (0..m)
            .flat_map(|i| (i + 1..m).map(move |j| (i, j)))
            .collect();
        let (e0, e1) = pairs[self.depth as usize % pairs.len()];
        let halve = |p: &Bernstein| p.split_edge(e0, e1);
        let halve_opt = |p: &Option<Bernstein>| match p {
            None => (None, None),
            Some(p) => {
                let (x, y) = halve(p);
                (Some(x), Some(y))
            }
        };
        let (c0, c1) = halve(&self.cross);
        let (g0, g1): (Vec<_>, Vec<_>) = self.grad.iter().map(halve).unzip();
        let (q0, q1) = halve_opt(&self.q2);
        let (d0, d1) = halve(&self.det);
        let (n0, n1) = halve_opt(&self.q2n);
        let (p0, p1): (Vec<_>, Vec<_>) = self.comps.iter().map(halve).unzip();
        let (qa, qb) = if self.comps.is_empty() {
            (None, None)
        } else {
            halve_opt(&self.q)
        };
        let depth = self.depth + 1;
        (
            SurfaceCell {
                cross: c0,
                grad: g0,
                q2: q0,
                det: d0,
                q2n: n0,
                comps: p0,
                q: qa,
                depth,
            },
            SurfaceCell {
                cross: c1,
                grad: g1,
                q2: q1,
                det: d1,
                q2n: n1,
                comps: p1,
                q: qb,
                depth,
            },
        )
    }

    /// The box of `u = X(w)` over the cell: each component's quotient range.
    fn u_box(&self) -> (Bary, Bary) {
        let mut lo = [0.0; MAX_VARS];
        let mut hi = [0.0; MAX_VARS];
        for (k, p) in self.comps.iter().enumerate() {
            (lo[k], hi[k]) = quotient_range(p, self.q.as_ref());
        }
        (lo, hi)
    }

    /// Whether the level set can meet the cell: `F − c` (times `Q > 0`) has coefficients of both
    /// signs, allowing for rounding in their computation.
    fn crosses(&self) -> bool {
        let c = self.cross.coeffs();
        let scale = c.iter().fold(0.0f64, |a, x| a.max(x.abs()));
        let slack = BOUND_ROUNDING_MARGIN * scale;
        self.cross.min_coeff() <= slack && self.cross.max_coeff() >= -slack
    }

    /// `(certified bound, estimate at the cell's vertices)` of `|E⁻ᵀ∇_w F| / (|∇F_lin| det DX)`.
    fn factor(&self, m: usize, linear: f64) -> (f64, f64) {
        let count = self.grad[0].coeffs().len();
        let mut g2 = 0.0;
        for g in &self.grad {
            let mut top: f64 = 0.0;
            for k in 0..count {
                let denom = self.q2.as_ref().map_or(1.0, |q| q.coeffs()[k]);
                top = top.max(g.coeffs()[k].abs() / denom);
            }
            g2 += top * top;
        }
        let (det_lo, _) = quotient_range(&self.det, self.q2n.as_ref());
        let mut estimate: f64 = 0.0;
        for i in 0..m {
            let qv = self.q2.as_ref().map_or(1.0, |q| q.vertex_value(i));
            let gv: f64 = self
                .grad
                .iter()
                .map(|g| (g.vertex_value(i) / qv).powi(2))
                .sum::<f64>()
                .sqrt();
            let dv =
                self.det.vertex_value(i) / self.q2n.as_ref().map_or(1.0, |q| q.vertex_value(i));
            if dv > 0.0 {
                estimate = estimate.max(gv / (linear * dv));
            }
        }
        let bound = if det_lo.is_nan() || det_lo <= 0.0 {
            f64::INFINITY
        } else {
            g2.sqrt() * (1.0 + BOUND_ROUNDING_MARGIN) / (linear * det_lo)
        };
        (bound, estimate)
    }
}

/// The last stage's factor `sup |E⁻ᵀ DXᵀ Δf| / (|∇F_lin| det DX)` over the cells its level set
/// crosses (see [`surface_area_element_bound`]), the worst cell bisected until the bound is within
/// `DET_TIGHTNESS` of the largest value seen or above it by at most `enough` (0: below
/// `DET_TIGHTNESS` already stops it), or `max_splits` are spent.
fn surface_stage_factor(
    stage: &LocalStage,
    inv_edges: &Mat,
    values: &[f64],
    level: f64,
    max_splits: usize,
    enough: f64,
    with_cells: bool,
) -> Result<(f64, Vec<LeafCell>), String> {
    let m = stage.vars();
    let n = m - 1;
    let JacobianPolys {
        p, q, q2, det, q2n, ..
    } = jacobian_polys(stage)?;
    // F = Σ f_i X_i = N/Q with N = Σ f_i P_i (Q ≡ 1 for a polynomial stage, whose components sum
    // to one).
    let mut nf = p[0].scale(values[0]);
    for (pi, &fi) in p.iter().zip(values).skip(1) {
        nf.add_scaled(pi, fi);
    }
    let cross = match &q {
        None => nf.add(&Bernstein::constant(m, nf.degree(), -level)),
        Some(q) => {
            let mut cross = nf.clone();
            cross.add_scaled(q, -level);
            cross
        }
    };
    // ∂F/∂w_l = (∂N Q − N ∂Q)/Q², numerators elevated to the degree of Q².
    let dw: Vec<Bernstein> = (1..m)
        .map(|l| match (&q, &q2) {
            (Some(q), Some(q2)) => {
                let mut d = nf.derivative(l).mul(q);
                d.add_scaled(&nf.mul(&q.derivative(l)), -1.0);
                d.elevate_to(q2.degree())
            }
            _ => nf.derivative(l),
        })
        .collect();
    // (E⁻ᵀ g)_x = Σ_l (E⁻¹)_{l x} g_l.
    let grad: Vec<Bernstein> = (0..n)
        .map(|x| {
            let mut acc = dw[0].scale(inv_edges[0][x]);
            for (l, g) in dw.iter().enumerate().skip(1) {
                acc.add_scaled(g, inv_edges[l][x]);
            }
            acc
        })
        .collect();
    let linear = linear_gradient_norm(inv_edges, &values[..m])?;
    // The boxes need `Q > 0` coefficientwise (`quotient_range`); a rational stage's weights are
    // positive, so this only fails on input the validator refuses.
    let boxes = with_cells
        && q.as_ref()
            .is_none_or(|q| q.min_coeff().is_finite() && q.min_coeff() > 0.0);
    let root = SurfaceCell {
        cross,
        grad,
        q2,
        det,
        q2n,
        comps: if boxes { p } else { Vec::new() },
        q: if boxes { q } else { None },
        depth: 0,
    };
    if !root.crosses() {
        // No surface in this simplex: nothing is ever sampled here.
        return Ok((0.0, Vec::new()));
    }
    let (bound, mut estimate) = root.factor(m, linear);
    // Per cell: its bound, the value at its vertices, the cell.
    let mut cells: Vec<(f64, f64, SurfaceCell)> = vec![(bound, estimate, root)];
    let mut splits = 0;
    let factor = loop {
        let Some(worst) = (0..cells.len()).max_by(|&i, &j| cells[i].0.total_cmp(&cells[j].0))
        else {
            break 0.0;
        };
        let top = cells[worst].0;
        if top * DET_TIGHTNESS <= estimate
            || (top.is_finite() && top - estimate <= enough)
            || splits >= max_splits
            || cells[worst].2.depth >= MAX_DEPTH
        {
            break top;
        }
        let (_, _, cell) = cells.swap_remove(worst);
        let (a, b) = cell.split(m);
        for child in [a, b] {
            if child.crosses() {
                let (bound, est) = child.factor(m, linear);
                estimate = estimate.max(est);
                cells.push((bound, est, child));
            }
        }
        splits += 1;
    };
    if !(factor.is_finite() && factor >= 0.0) {
        return Err(format!(
            "Jacobian determinant not certified positive near the surface after {splits} bisections"
        ));
    }
    if !boxes {
        return Ok((factor, Vec::new()));
    }
    // The whole bound is settled; the cells' own bounds go on to their parts of the patch
    // ([`CellBounds`]): the rest of the budget on the cells loosest in bounded area.
    refine_cells(&mut cells, m, linear, MAX_CELL_SPLITS, enough);
    let leaves = cells
        .iter()
        .map(|(b, _, cell)| {
            let (lo, hi) = cell.u_box();
            (lo, hi, *b)
        })
        .collect();
    Ok((factor, leaves))
}

/// The second round of [`surface_stage_factor`] for [`CellBounds`], once the whole bound is
/// settled: every cell (not only the worst) is bisected while its bound is loose against its own
/// vertex values — above them by more than `DET_TIGHTNESS` and, times the share of the patch the
/// cell holds, by more than `enough` — the loosest in that bounded area first, for at most
/// `max_splits` bisections ([`MAX_CELL_SPLITS`]). Bisecting never raises a bound (a part's
/// Bernstein coefficients are convex combinations of the whole's), so no part of the patch gets
/// a larger one than before.
fn refine_cells(
    cells: &mut Vec<(f64, f64, SurfaceCell)>,
    m: usize,
    linear: f64,
    max_splits: usize,
    enough: f64,
) {
    // The share of the patch a cell `depth` bisections deep holds: its volume is `2^-depth` of
    // the simplex's, and the shape in it a hypersurface, so about `2^(-depth (n-1)/n)`.
    let n = (m - 1) as f64;
    let share = |depth: u32| (-(f64::from(depth)) * (n - 1.0) / n).exp2();
    let excess = |b: f64, e: f64, depth: u32| (b - e) * share(depth);
    let loose = |&(b, e, ref cell): &(f64, f64, SurfaceCell)| {
        b * DET_TIGHTNESS > e && excess(b, e, cell.depth) > enough && cell.depth < MAX_DEPTH
    };
    for _ in 0..max_splits {
        let Some(worst) = (0..cells.len())
            .filter(|&i| loose(&cells[i]))
            .max_by(|&i, &j| {
                let x = |k: usize| excess(cells[k].0, cells[k].1, cells[k].2.depth);
                x(i).total_cmp(&x(j))
            })
        else {
            break;
        };
        let (_, _, cell) = cells.swap_remove(worst);
        let (a, b) = cell.split(m);
        for child in [a, b] {
            if child.crosses() {
                let (bound, est) = child.factor(m, linear);
                cells.push((bound, est, child));
            }
        }
    }
}

/// `|∇F_lin|` on a simplex from the inverse edge matrix and the vertex values (stored order):
/// `(E⁻ᵀ Δf)_x = Σ_l (f_{l+1} − f_0) (E⁻¹)_{l x}`. `Err` when it is zero (no level set crosses).
pub(crate) fn linear_gradient_norm(inv_edges: &Mat, values: &[f64]) -> Result<f64, String> {
    let n = values.len() - 1;
    let linear = (0..n)
        .map(|x| {
            (0..n)
                .map(|l| (values[l + 1] - values[0]) * inv_edges[l][x])
                .sum::<f64>()
                .powi(2)
        })
        .sum::<f64>()
        .sqrt();
    if linear.is_nan() || linear <= 0.0 {
        return Err("the linear function is constant on the simplex".into());
    }
    Ok(linear)
}

/// `[lo, hi]` enclosing `num/den` on the (sub)simplex of their coefficients (`den > 0`
/// coefficientwise, or absent for 1): `num − r·den` has coefficients `num_I − r·den_I`, so the
/// extreme coefficient ratios bound the quotient. Widened by [`BOUND_ROUNDING_MARGIN`] of the
/// largest ratio for the rounding of the coefficients.
pub(crate) fn quotient_range(num: &Bernstein, den: Option<&Bernstein>) -> (f64, f64) {
    let (mut lo, mut hi, mut top) = (f64::INFINITY, f64::NEG_INFINITY, 0.0f64);
    for (k, &x) in num.coeffs().iter().enumerate() {
        let r = den.map_or(x, |d| x / d.coeffs()[k]);
        lo = lo.min(r);
        hi = hi.max(r);
        top = top.max(r.abs());
    }
    let slack = BOUND_ROUNDING_MARGIN * top + f64::MIN_POSITIVE;
    (lo - slack, hi + slack)
}

/// Bounds of one local stage (see the module doc).
///
/// # Errors
/// A message when the stored map's determinant cannot be shown positive by its Bernstein
/// coefficients after `MAX_SPLITS` bisections, or a denominator is not positive.
pub fn stage_bound(stage: &LocalStage, edges: &Mat, inv_edges: &Mat) -> Result<StageBound, String> {
    let m = stage.vars();
    let n = m - 1;
    let JacobianPolys {
        num, q2, det, q2n, ..
    } = jacobian_polys(stage)?;
    let ctx = CellContext {
        n,
        edges,
        inv_edges,
        parametric: stage.direction() == Direction::Parametric,
    };
    // Refine the cell with the largest bound until it is within DET_TIGHTNESS of the largest exact
    // vertex value seen (a lower estimate of the true supremum), or the budget is spent. The bound
    // is the largest cell bound, so only the worst cell ever needs splitting.
    let root = Cell {
        num,
        q2,
        det,
        q2n,
        depth: 0,
    };
    let (bound, mut estimate) = ctx.factor(&root)?;
    let mut cells: Vec<(f64, Cell)> = vec![(bound, root)];
    let mut splits = 0;
    let factor = loop {
        let worst = (0..cells.len())
            .max_by(|&i, &j| cells[i].0.total_cmp(&cells[j].0))
            .expect("never empty");
        let top = cells[worst].0;
        if top * DET_TIGHTNESS <= estimate
            || splits >= MAX_SPLITS
            || cells[worst].1.depth >= MAX_DEPTH
        {
            break top;
        }
        let (_, cell) = cells.swap_remove(worst);
        let (a, b) = cell.split(m);
        for child in [a, b] {
            let (bound, est) = ctx.factor(&child)?;
            estimate = estimate.max(est);
            cells.push((bound, child));
        }
        splits += 1;
    };
    if factor == f64::INFINITY {
        return Err(format!(
            "Jacobian determinant not certified positive after {splits} bisections"
        ));
    }
    if !(factor.is_finite() && factor > 0.0) {
        return Err(format!(
            "non-finite or non-positive area-element factor {factor}"
        ));
    }
    Ok(StageBound { factor })
}

/// A stage as Bernstein polynomials: components `P_i` and denominator `Q` (none for a polynomial
/// stage), reduced Jacobian numerators, their denominator `Q²`, and `det DX` as a numerator over
/// a denominator ([`det_over_denominator`]: `Q^{n+1}`).
struct JacobianPolys {
    /// Components `P_i`.
    p: Vec<Bernstein>,
    q: Option<Bernstein>,
    num: Vec<Vec<Bernstein>>,
    q2: Option<Bernstein>,
    det: Bernstein,
    q2n: Option<Bernstein>,
}

/// A stored stage as Bernstein polynomials on its simplex: components `P_i` and the denominator
/// `Q` (`None` for a polynomial stage, whose components sum to one). Rational: `P_i = Σ q_I b_{I,i}
/// B_I`, `Q = Σ q_I B_I`; monotonic: `P_i = g_i(w_i)` in the degree-`d` basis, `Q = Σ P_i`.
pub(crate) fn stage_components(stage: &LocalStage) -> (Vec<Bernstein>, Option<Bernstein>) {
    let m = stage.vars();
    let d = stage.degree();
    match stage.kind() {
        StageKind::Bezier => {
            let comps = (0..m)
                .map(|i| component(m, d, stage.control_points().iter().map(|b| b[i])))
                .collect();
            (comps, None)
        }
        StageKind::Rational => {
            let q = stage.weights();
            let comps = (0..m)
                .map(|i| {
                    component(
                        m,
                        d,
                        stage.control_points().iter().zip(q).map(|(b, w)| b[i] * w),
                    )
                })
                .collect();
            (comps, Some(component(m, d, q.iter().copied())))
        }
        StageKind::Monotonic => {
            // g_i(w_i) = Σ_j a_j C(d,j) w_i^j (1 − w_i)^{d−j}, and on the simplex 1 − w_i is the sum
            // of the other coordinates, so C(d,j) w_i^j (1−w_i)^{d−j} = Σ_{|I|=d, I_i=j} B_I(w):
            // the Bernstein coefficient of index I is a_{I_i}.
            let comps: Vec<Bernstein> = (0..m)
                .map(|i| {
                    let a = stage.monotonic_coefficients(i).to_vec();
                    Bernstein::from_fn(m, d, |idx| a[idx[i] as usize])
                })
                .collect();
            let mut total = comps[0].clone();
            for c in &comps[1..] {
                total = total.add(c);
            }
            (comps, Some(total))
        }
    }
}

fn jacobian_polys(stage: &LocalStage) -> Result<JacobianPolys, String> {
    let m = stage.vars();
    let n = m - 1;
    let (p, q) = stage_components(stage);
    // Numerators of the reduced Jacobian entries (rows u_1..u_n, columns w_1..w_n).
    let mut num: Vec<Vec<Bernstein>> = Vec::with_capacity(n);
    for pi in &p[1..] {
        let row = (1..m)
            .map(|l| match &q {
                None => pi.derivative(l),
                Some(q) => {
                    let mut e = pi.derivative(l).mul(q);
                    e.add_scaled(&pi.mul(&q.derivative(l)), -1.0);
                    e
                }
            })
            .collect();
        num.push(row);
    }
    // Denominators: Q² for the entries, Q^{n+1} for the determinant (none for a polynomial stage).
    let q2 = q.as_ref().map(|q| q.mul(q));
    if let Some(q2) = &q2 {
        if q2.min_coeff().is_nan() || q2.min_coeff() <= 0.0 {
            return Err(format!(
                "denominator has a coefficient {} ≤ 0",
                q2.min_coeff()
            ));
        }
    }
    let num: Vec<Vec<Bernstein>> = match &q2 {
        None => num,
        Some(q2) => num
            .iter()
            .map(|row| row.iter().map(|e| e.elevate_to(q2.degree())).collect())
            .collect(),
    };
    let (det, q2n) = det_over_denominator(&p, q.as_ref(), &num);
    Ok(JacobianPolys {
        p,
        q,
        num,
        q2,
        det,
        q2n,
    })
}

/// A sub-simplex of one stage's bound computation: the Jacobian numerators, their denominator
/// `Q²`, the determinant numerator and its denominator `Q^{n+1}`, all restricted to the cell.
struct Cell {
    num: Vec<Vec<Bernstein>>,
    q2: Option<Bernstein>,
    det: Bernstein,
    q2n: Option<Bernstein>,
    depth: u32,
}

impl Cell {
    /// Bisects edge `(a, b)`, cycling with depth so every edge is split within `C(m, 2)` levels.
    fn split(&self, m: usize) -> (Cell, Cell) {
        let pairs: Vec<(usize, usize)> = (0..m)
            .flat_map(|i| (i + 1..m).map(move |j| (i, j)))
            .collect();
        let (e0, e1) = pairs[self.depth as usize % pairs.len()];
        let halve = |p: &Bernstein| p.split_edge(e0, e1);
        let halve_opt = |p: &Option<Bernstein>| match p {
            None => (None, None),
            Some(p) => {
                let (x, y) = halve(p);
                (Some(x), Some(y))
            }
        };
        let mut num0 = Vec::with_capacity(self.num.len());
        let mut num1 = Vec::with_capacity(self.num.len());
        for row in &self.num {
            let (r0, r1): (Vec<_>, Vec<_>) = row.iter().map(halve).unzip();
            num0.push(r0);
            num1.push(r1);
        }
        let (q0, q1) = halve_opt(&self.q2);
        let (d0, d1) = halve(&self.det);
        let (n0, n1) = halve_opt(&self.q2n);
        let depth = self.depth + 1;
        (
            Cell {
                num: num0,
                q2: q0,
                det: d0,
                q2n: n0,
                depth,
            },
            Cell {
                num: num1,
                q2: q1,
                det: d1,
                q2n: n1,
                depth,
            },
        )
    }
}

struct CellContext<'a> {
    n: usize,
    edges: &'a Mat,
    inv_edges: &'a Mat,
    parametric: bool,
}

impl CellContext<'_> {
    /// `‖E C E⁻¹‖₂` bound for the coefficient (or vertex value) matrix picked by `at`.
    fn norm(&self, num: &[Vec<Bernstein>], at: impl Fn(&Bernstein) -> f64) -> f64 {
        let mut c: Mat = [[0.0; MAX_VARS]; MAX_VARS];
        for (i, row) in num.iter().enumerate() {
            for (l, e) in row.iter().enumerate() {
                c[i][l] = at(e);
            }
        }
        spectral_norm_bound(
            self.n,
            &linalg::mul(self.n, &linalg::mul(self.n, self.edges, &c), self.inv_edges),
        )
    }

    /// The stage's factor from sup ‖M‖ and the range of det M (see the module doc).
    fn combine(&self, norm: f64, det_lo: f64, det_hi: f64) -> f64 {
        if self.parametric {
            // X_k = S⁻¹: σ_max(S⁻¹) = 1/σ_min(S) ≤ σ_max(S)^{n−1}/det S, and det X_k = 1/det S.
            norm.powi(self.n as i32 - 1) / det_lo * det_hi
        } else {
            norm / det_lo
        }
    }

    /// `(certified bound, estimate from exact vertex values)` of the factor on `cell`.
    fn factor(&self, cell: &Cell) -> Result<(f64, f64), String> {
        let m = self.n + 1;
        let count = cell.num[0][0].coeffs().len();
        let mut norm: f64 = 0.0;
        for k in 0..count {
            let denom = cell.q2.as_ref().map_or(1.0, |q| q.coeffs()[k]);
            norm = norm.max(self.norm(&cell.num, |e| e.coeffs()[k]) / denom);
        }
        // det/D ≥ min_I det_I/D_I (D = Q^{n+1}) since det − r D has coefficients det_I − r D_I.
        let (det_lo, det_hi) = quotient_range(&cell.det, cell.q2n.as_ref());
        let mut estimate: f64 = 0.0;
        for i in 0..m {
            let qv = cell.q2.as_ref().map_or(1.0, |q| q.vertex_value(i));
            let nv = self.norm(&cell.num, |e| e.vertex_value(i)) / qv;
            let dv =
                cell.det.vertex_value(i) / cell.q2n.as_ref().map_or(1.0, |q| q.vertex_value(i));
            if dv.is_nan() || dv <= 0.0 {
                return Err(format!(
                    "Jacobian determinant {dv} ≤ 0 at a vertex of a sub-simplex: the stage is not a diffeomorphism"
                ));
            }
            estimate = estimate.max(self.combine(nv, dv, dv));
        }
        if det_lo.is_nan() || det_lo <= 0.0 {
            // Not certified on this cell yet: an infinite bound makes it the first to be split.
            return Ok((f64::INFINITY, estimate));
        }
        Ok((self.combine(norm, det_lo, det_hi), estimate))
    }
}

fn component(m: usize, d: u32, coeffs: impl Iterator<Item = f64>) -> Bernstein {
    Bernstein::new(m, d, coeffs.collect()).expect("a dense net has C(d+n, n) points")
}

/// `det` of an `n × n` matrix of Bernstein polynomials of equal degree (`n ≤ 3`), as a polynomial.
pub(crate) fn det_poly<T: Borrow<Bernstein>>(a: &[Vec<T>]) -> Bernstein {
    // The products, then the signed sums in place (`add_scaled`: the same roundings as
    // `x.add(&y.scale(-1.0))`, without the two allocations per term).
    let e = |i: usize, j: usize| a[i][j].borrow();
    match a.len() {
        1 => e(0, 0).clone(),
        2 => {
            let mut d = e(0, 0).mul(e(1, 1));
            d.add_scaled(&e(0, 1).mul(e(1, 0)), -1.0);
            d
        }
        _ => {
            let minor = |c0: usize, c1: usize| {
                let mut m = e(1, c0).mul(e(2, c1));
                m.add_scaled(&e(1, c1).mul(e(2, c0)), -1.0);
                m
            };
            let mut d = e(0, 0).mul(&minor(1, 2));
            d.add_scaled(&e(0, 1).mul(&minor(0, 2)), -1.0);
            d.add_scaled(&e(0, 2).mul(&minor(0, 1)), 1.0);
            d
        }
    }
}

/// `det DX` of a stage with components `P` and denominator `Q` (`n + 1 = P.len()` variables) as a
/// numerator over a denominator of the same degree, for [`quotient_range`]: `(det(num), None)`
/// for a polynomial stage (`num` its reduced Jacobian), and for a rational one `(R, Q^{n+1})`
/// with `R` elevated to `Q^{n+1}`'s degree `d (n + 1)`.
///
/// Why `R`: the entries of a rational stage's Jacobian are `(Q A − p qᵀ) / Q²` with `A = ∂P`,
/// `p = P` (rows `1..n`) and `q = ∂Q` (reduced derivatives), and by the matrix determinant lemma
/// `det(Q A − p qᵀ) = Q^{n−1} (Q det A − qᵀ adj(A) p) = Q^{n−1} R`, where `R` is the determinant
/// of the bordered matrix `[[Q, qᵀ], [p, A]]`, of degree `d + n (d − 1)`. So
/// `det DX = det(num) / Q^{2n} = R / Q^{n+1}`: the same function as the numerators' determinant
/// (degree `n (2d − 1)` over `Q^{2n}`, `2dn`) with far fewer coefficients to subdivide — for a
/// quadratic stage in 3D degree 8 instead of 12, 165 coefficients instead of 455 each.
pub(crate) fn det_over_denominator(
    p: &[Bernstein],
    q: Option<&Bernstein>,
    num: &[Vec<Bernstein>],
) -> (Bernstein, Option<Bernstein>) {
    let Some(q) = q else {
        return (det_poly(num), None);
    };
    let m = p.len();
    let n = m - 1;
    if let Some(product) = projective_product(p, q) {
        let den = q_power(q, n + 1);
        return (Bernstein::constant(m, den.degree(), product), Some(den));
    }
    expanded_over_denominator(p, q)
}

/// [`det_over_denominator`] of a rational stage by expanding the bordered determinant.
fn expanded_over_denominator(p: &[Bernstein], q: &Bernstein) -> (Bernstein, Option<Bernstein>) {
    let m = p.len();
    let n = m - 1;
    let row = |head: &Bernstein| -> Vec<Bernstein> {
        std::iter::once(head.clone())
            .chain((1..m).map(|l| head.derivative(l)))
            .collect()
    };
    let bordered: Vec<Vec<Bernstein>> = std::iter::once(row(q))
        .chain(p[1..].iter().map(row))
        .collect();
    let r = match n {
        0..=2 => det_poly(&bordered),
        // 4 × 4: along the first row, each minor a 3 × 3 determinant. Every term takes one entry
        // per column (degrees `d, d − 1, …`), so all terms share the degree `d + n (d − 1)`.
        _ => {
            let mut acc: Option<Bernstein> = None;
            for c in 0..=n {
                // The minor's entries borrowed, not copied.
                let minor: Vec<Vec<&Bernstein>> = bordered[1..]
                    .iter()
                    .map(|r| {
                        r.iter()
                            .enumerate()
                            .filter(|&(k, _)| k != c)
                            .map(|(_, e)| e)
                            .collect()
                    })
                    .collect();
                let term = bordered[0][c].mul(&det_poly(&minor));
                let sign = if c % 2 == 1 { -1.0 } else { 1.0 };
                match &mut acc {
                    // `scale(-1.0)` is exact: the first term (c = 0) is taken as it is.
                    None => acc = Some(term),
                    Some(a) => a.add_scaled(&term, sign),
                }
            }
            acc.expect("n + 1 ≥ 1 terms")
        }
    };
    let den = q_power(q, n + 1);
    (r.elevate_to(den.degree()), Some(den))
}

/// `q^k`, `k ≥ 1`, as repeated products (the order [`det_over_denominator`] has always used).
fn q_power(q: &Bernstein, k: usize) -> Bernstein {
    let mut den = q.clone();
    for _ in 1..k {
        den = den.mul(q);
    }
    den
}

/// `Π a_i` when the stage is projective — degree 1 with `P_i = a_i w_i` and `Q = Σ_i P_i`, as a
/// monotonic stage of degree 1 is (spec §5.4: `g_i(t) = a_i t`, `a_i > 0`). Its bordered
/// determinant `R` is then the constant `Π a_i`: `det DX = Π a_i / Q^{n+1}` (for `n = 1`,
/// `d/dw₁ (a₁w₁ / (a₀w₀ + a₁w₁)) = a₀a₁ / Q²` on `w₀ + w₁ = 1`), where the expansion of
/// [`det_over_denominator`] costs ~20 polynomial products and an elevation per stage (~11 % of
/// the torus example's sampler table, whose every patch restricts its projective first stage).
/// `None` otherwise.
fn projective_product(p: &[Bernstein], q: &Bernstein) -> Option<f64> {
    let m = p.len();
    if q.degree() != 1 || q.vars() != m {
        return None;
    }
    let mut product = 1.0;
    for (i, pi) in p.iter().enumerate() {
        if pi.degree() != 1 || pi.vars() != m {
            return None;
        }
        // A degree-1 polynomial's coefficients are its vertex values: `a_i` at vertex `i`, 0 at
        // the others, and `Q`'s the same `a_i`.
        if (0..m).any(|j| j != i && pi.vertex_value(j) != 0.0) {
            return None;
        }
        let a = pi.vertex_value(i);
        if !(a > 0.0 && a.is_finite()) || q.vertex_value(i) != a {
            return None;
        }
        product *= a;
    }
    (product > 0.0 && product.is_finite()).then_some(product)
}

/// Upper bound of the spectral norm `σ_max` of the upper-left `n × n` block (`n ≤ 3`): the largest
/// eigenvalue of `AᵀA` in closed form (trigonometric for `n = 3`), plus an allowance for rounding of
/// [`BOUND_ROUNDING_MARGIN`] times the Frobenius norm.
pub fn spectral_norm_bound(n: usize, a: &Mat) -> f64 {
    let mut s = [[0.0f64; 3]; 3];
    for i in 0..n {
        for j in 0..n {
            s[i][j] = (0..n).map(|k| a[k][i] * a[k][j]).sum();
        }
    }
    let frob2: f64 = (0..n).map(|i| s[i][i]).sum();
    let lambda = match n {
        1 => s[0][0],
        2 => {
            let tr = s[0][0] + s[1][1];
            let det = s[0][0] * s[1][1] - s[0][1] * s[1][0];
            (tr + (tr * tr - 4.0 * det).max(0.0).sqrt()) / 2.0
        }
        _ => {
            // Eigenvalues of a symmetric 3×3 matrix (Smith 1961).
            let p1 = s[0][1].powi(2) + s[0][2].powi(2) + s[1][2].powi(2);
            let q = (s[0][0] + s[1][1] + s[2][2]) / 3.0;
            let p2 =
                (s[0][0] - q).powi(2) + (s[1][1] - q).powi(2) + (s[2][2] - q).powi(2) + 2.0 * p1;
            let p = (p2 / 6.0).sqrt();
            if p == 0.0 {
                q
            } else {
                let mut b = s;
                for (i, row) in b.iter_mut().enumerate() {
                    for (j, x) in row.iter_mut().enumerate() {
                        *x = (*x - if i == j { q } else { 0.0 }) / p;
                    }
                }
                let det_b = b[0][0] * (b[1][1] * b[2][2] - b[1][2] * b[2][1])
                    - b[0][1] * (b[1][0] * b[2][2] - b[1][2] * b[2][0])
                    + b[0][2] * (b[1][0] * b[2][1] - b[1][1] * b[2][0]);
                let r = (det_b / 2.0).clamp(-1.0, 1.0);
                q + 2.0 * p * (r.acos() / 3.0).cos()
            }
        }
    };
    (lambda.max(0.0) + BOUND_ROUNDING_MARGIN * frob2).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use ism_format::builder::{ModelBuilder, StageBuilder};

    fn two_triangles(stage: ism_format::Stage) -> ism_format::Model {
        ModelBuilder::new(2)
            .vertex(&[0.0, 0.0], -1.0)
            .vertex(&[1.0, 0.0], 1.0)
            .vertex(&[1.0, 1.0], 1.0)
            .vertex(&[0.0, 1.0], 1.0)
            .simplex(&[0, 1, 2])
            .simplex(&[0, 2, 3])
            .stage(stage)
            .build()
            .unwrap()
    }

    /// A spec example (`spec/examples/NAME.ism.json`).
    fn example(name: &str) -> ism_format::Model {
        let path = format!(
            "{}/../../spec/examples/{name}.ism.json",
            env!("CARGO_MANIFEST_DIR")
        );
        ism_format::io::read_path(path).unwrap().model
    }

    fn edges(model: &ism_format::Model, s: usize) -> Mat {
        ism_geom::model::edge_matrix(model, model.simplex(s))
    }

    /// The fused bound ([`fused_surface_area_element_bound`]) dominates the exact `J` of the
    /// stored, unfused map (the kernel's Newton inverse and Jacobian: independent of the
    /// Bernstein enclosures) at a lattice of points of the shape on every crossed simplex of the
    /// examples whose projective stage fuses, and is tighter than the stored map's bound
    /// ([`surface_area_element_bound`]) in sum over the torus example's patches (measured: 0.11×);
    /// and the bound of the cells whose box holds each point's `u` ([`CellBounds::over`], what a
    /// sampler region takes) dominates `J` there too, below the whole bound (measured, summed over
    /// the points: 3.4·10⁵ against 9.4·10⁶ on the torus, 2.3·10⁴ against 5.0·10⁴ on the sphere).
    #[test]
    fn fused_bound_dominates_the_stored_maps_area_element() {
        const LEVEL: usize = 6;
        for (name, fused_patches) in [("torus", 400), ("sphere", 300), ("circle-curved", 10)] {
            let model = example(name);
            let eval = ism_geom::ModelEval::new(&model).unwrap();
            let n = model.dim();
            let (mut patches, mut points, mut fused_sum, mut stored_sum) = (0, 0, 0.0, 0.0);
            let (mut local_sum, mut whole_sum) = (0.0, 0.0);
            for s in 0..model.num_simplices() {
                let Some(patch) = eval.patch(s) else { continue };
                let map = eval.local_map(s);
                let e = edges(&model, s);
                let inv = linalg::inverse(n, &e).unwrap();
                let ids = model.simplex(s);
                let values: Vec<f64> = ids.iter().map(|&v| model.values[v as usize]).collect();
                let Some(cells) = fused_surface_area_element_bound(
                    map,
                    &e,
                    &values,
                    model.level,
                    MAX_SURFACE_SPLITS,
                    0.0,
                ) else {
                    continue;
                };
                let bound = cells.top();
                patches += 1;
                fused_sum += bound;
                stored_sum += surface_area_element_bound(map, &e, &values, model.level).unwrap();
                let lin = linear_gradient_norm(&inv, &values).unwrap();
                let corners: Vec<Bary> = patch.corners.iter().map(|c| c.u).collect();
                // The patch's triangles (its segment in 2D), each on a lattice of `LEVEL`.
                let tris: Vec<[Bary; 3]> = match corners.len() {
                    2 => vec![[corners[0], corners[1], corners[1]]],
                    3 => vec![[corners[0], corners[1], corners[2]]],
                    _ => vec![
                        [corners[0], corners[1], corners[2]],
                        [corners[0], corners[2], corners[3]],
                    ],
                };
                for t in &tris {
                    for i in 0..=LEVEL {
                        for j in 0..=LEVEL - i {
                            let (a, b) = (i as f64 / LEVEL as f64, j as f64 / LEVEL as f64);
                            let mut u = [0.0; MAX_VARS];
                            for (k, x) in u.iter_mut().enumerate().take(n + 1) {
                                *x = (1.0 - a - b) * t[0][k] + a * t[1][k] + b * t[2][k];
                            }
                            let solved = map.inverse(&u);
                            assert!(solved.converged, "{name}: simplex {s}: no preimage");
                            let jac = map.jacobian(&solved.w).1.unwrap();
                            let g = eval.gradient_from_jacobian(s, &jac);
                            let grad = g[..n].iter().map(|x| x * x).sum::<f64>().sqrt();
                            let j = grad / (lin * linalg::det(n, &jac));
                            assert!(
                                j <= bound,
                                "{name}: simplex {s}: J {j} above the fused bound {bound}"
                            );
                            // And below the bound of the cells whose box holds the point's `u`
                            // (what a region of the sampler takes, `CellBounds::over`).
                            let local = cells.over(&u[..=n], &u[..=n]);
                            assert!(
                                j <= local && local <= bound,
                                "{name}: simplex {s}: J {j} above its cells' bound {local} \
                                 (whole {bound})"
                            );
                            local_sum += local;
                            whole_sum += bound;
                            points += 1;
                        }
                    }
                }
            }
            eprintln!(
                "{name}: {patches} fused patches, {points} points; bounds summed: fused \
                 {fused_sum:.4e}, stored {stored_sum:.4e}; at the points: their cells' \
                 {local_sum:.4e}, the whole {whole_sum:.4e}"
            );
            assert!(patches >= fused_patches, "{name}: {patches} patches fuse");
            // The cells localise: at the points, their cells' bounds sum to less than the
            // whole simplices' (else `CellBounds` would add nothing).
            assert!(
                local_sum < 0.9 * whole_sum,
                "{name}: cells {local_sum} against whole {whole_sum}"
            );
            if name == "torus" {
                assert!(
                    fused_sum < 0.2 * stored_sum,
                    "fused {fused_sum} against stored {stored_sum}"
                );
            }
        }
    }

    /// The projective stages of the implicit examples (monotonic, degree 1) take the closed form
    /// `R = Π a_i` over `Q^{n+1}`; it equals the expanded bordered determinant (the general path)
    /// coefficient by coefficient to rounding, and `R / Q^{n+1}` equals the kernel's Jacobian
    /// determinant (`LocalStage::jacobian_stored`, an independent computation) at the vertices
    /// and centroid. Other stages (the quadratic Bézier ones, the fused rational ones) and a
    /// projective stage with a coefficient off its vertex are not taken for projective.
    #[test]
    fn projective_stages_take_the_closed_form_determinant() {
        let mut closed = 0;
        for name in ["torus", "sphere", "circle-curved"] {
            let model = example(name);
            let eval = ism_geom::ModelEval::new(&model).unwrap();
            let n = model.dim();
            let m = n + 1;
            for s in 0..model.num_simplices() {
                let map = eval.local_map(s);
                let fused = map.clone().fused();
                for stage in map.stages().iter().chain(fused.stages()) {
                    let (p, q) = stage_components(stage);
                    let Some(q) = q else { continue };
                    let projective =
                        stage.kind() == ism_format::StageKind::Monotonic && stage.degree() == 1;
                    assert_eq!(
                        projective_product(&p, &q).is_some(),
                        projective,
                        "{name} {s}"
                    );
                    if !projective {
                        continue;
                    }
                    closed += 1;
                    let (r, den) = det_over_denominator(&p, Some(&q), &[]);
                    let (want, want_den) = expanded_over_denominator(&p, &q);
                    let (den, want_den) = (den.unwrap(), want_den.unwrap());
                    assert_eq!(den, want_den);
                    assert_eq!(r.degree(), want.degree());
                    let scale = want.coeffs().iter().fold(0.0f64, |a, c| a.max(c.abs()));
                    for (a, b) in r.coeffs().iter().zip(want.coeffs()) {
                        assert!((a - b).abs() <= 1e-13 * scale, "{name} {s}: {a} vs {b}");
                    }
                    let mut points: Vec<[f64; MAX_VARS]> = (0..m)
                        .map(|i| {
                            let mut w = [0.0; MAX_VARS];
                            w[i] = 1.0;
                            w
                        })
                        .collect();
                    let mut centroid = [0.0; MAX_VARS];
                    centroid[..m].fill(1.0 / m as f64);
                    points.push(centroid);
                    for w in points {
                        let kernel = linalg::det(n, &stage.jacobian_stored(&w).1);
                        let got = r.eval(&w[..m]) / den.eval(&w[..m]);
                        assert!(
                            (got - kernel).abs() <= 1e-12 * kernel.abs(),
                            "{got} {kernel}"
                        );
                    }
                    // One coefficient off its vertex: no longer `a_i w_i`.
                    let mut off = p.clone();
                    let mut c = off[0].coeffs().to_vec();
                    let last = c.len() - 1;
                    c[last] += 0.5;
                    off[0] = Bernstein::new(m, 1, c).unwrap();
                    assert!(projective_product(&off, &q).is_none());
                }
            }
        }
        assert!(closed > 1000, "{closed} projective stages checked");
    }

    /// The bound must dominate sup ‖M‖/det M sampled densely (a necessary condition), and be
    /// reasonably tight (within a factor 4 here) so sampling stays efficient.
    fn check_dominates(model: &ism_format::Model) {
        for s in 0..model.num_simplices() {
            let map = LocalMap::from_model(model, s).unwrap();
            let e = edges(model, s);
            let inv = linalg::inverse(2, &e).unwrap();
            let bound = area_element_bound(&map, &e).unwrap();
            let mut worst: f64 = 0.0;
            let k = 60;
            for i in 0..=k {
                for j in 0..=(k - i) {
                    let w = [
                        1.0 - (i + j) as f64 / k as f64,
                        i as f64 / k as f64,
                        j as f64 / k as f64,
                        0.0,
                    ];
                    let (_, jac) = map.jacobian(&w);
                    let jac = jac.unwrap();
                    let mm = linalg::mul(2, &linalg::mul(2, &e, &jac), &inv);
                    // 2×2 spectral norm from the singular values.
                    let (a, b, c, d) = (mm[0][0], mm[0][1], mm[1][0], mm[1][1]);
                    let s1 = a * a + b * b + c * c + d * d;
                    let det = a * d - b * c;
                    let smax = ((s1 + (s1 * s1 - 4.0 * det * det).max(0.0).sqrt()) / 2.0).sqrt();
                    worst = worst.max(smax / det);
                }
            }
            eprintln!("simplex {s}: bound {bound} sampled {worst}");
            assert!(
                bound >= worst,
                "simplex {s}: bound {bound} < sampled {worst}"
            );
            assert!(
                bound <= 4.0 * worst,
                "simplex {s}: bound {bound} loose vs {worst}"
            );
        }
    }

    /// The surface-restricted bound must dominate `J` sampled densely on the shape (points
    /// `X⁻¹(u)` for `u` on the linear patch), and never exceed the whole-simplex bound by more
    /// than rounding.
    fn check_surface_dominates(model: &ism_format::Model) {
        let eval = ism_geom::ModelEval::new(model).unwrap();
        for s in 0..model.num_simplices() {
            let Some(patch) = eval.patch(s) else { continue };
            let map = eval.local_map(s);
            let e = edges(model, s);
            let inv = linalg::inverse(2, &e).unwrap();
            let ids = model.simplex(s);
            let values: Vec<f64> = ids.iter().map(|&v| model.values[v as usize]).collect();
            let bound = surface_area_element_bound(map, &e, &values, model.level).unwrap();
            let whole = area_element_bound(map, &e).unwrap();
            let linear = (0..2)
                .map(|x| {
                    (0..2)
                        .map(|l| (values[l + 1] - values[0]) * inv[l][x])
                        .sum::<f64>()
                        .powi(2)
                })
                .sum::<f64>()
                .sqrt();
            let (a, b) = (patch.corners[0].u, patch.corners[1].u);
            let mut worst: f64 = 0.0;
            for k in 0..=400 {
                let t = f64::from(k) / 400.0;
                let mut u = [0.0; MAX_VARS];
                for i in 0..3 {
                    u[i] = (1.0 - t) * a[i] + t * b[i];
                }
                let w = map.inverse(&u).w;
                let jac = map.jacobian(&w).1.unwrap();
                let g = eval.gradient_from_jacobian(s, &jac);
                let j = (g[0] * g[0] + g[1] * g[1]).sqrt() / (linear * linalg::det(2, &jac));
                worst = worst.max(j);
            }
            eprintln!("simplex {s}: surface bound {bound}, whole {whole}, sampled {worst}");
            assert!(
                bound >= worst,
                "simplex {s}: bound {bound} < sampled {worst}"
            );
            assert!(
                bound <= whole * (1.0 + 1e-9),
                "simplex {s}: {bound} > {whole}"
            );
        }
    }

    #[test]
    fn surface_bounds_dominate_the_area_element_on_the_shape() {
        for stage in [
            StageBuilder::bezier(2)
                .face(&[0, 2], &[0.7, 0.3], &[])
                .build(),
            StageBuilder::bezier(3)
                .face(&[0, 1, 2], &[0.5, 0.2, 0.3], &[])
                .face(&[0, 1], &[0.6, 0.4, 0.1, 0.9], &[])
                .build(),
            StageBuilder::rational(2)
                .face(&[0, 2], &[0.5, 0.5], &[3.0])
                .build(),
            StageBuilder::monotonic(3)
                .vertex_map(0, &[0.0, 1.0, 1.5, 2.0])
                .vertex_map(2, &[0.0, 0.2, 0.5, 1.0])
                .build(),
        ] {
            check_surface_dominates(&two_triangles(stage));
        }
    }

    #[test]
    fn bezier_rational_monotonic_and_parametric_bounds_dominate_samples() {
        check_dominates(&two_triangles(
            StageBuilder::bezier(2)
                .face(&[0, 2], &[0.7, 0.3], &[])
                .build(),
        ));
        check_dominates(&two_triangles(
            StageBuilder::bezier(3)
                .face(&[0, 1, 2], &[0.5, 0.2, 0.3], &[])
                .build(),
        ));
        check_dominates(&two_triangles(
            StageBuilder::bezier(2)
                .face(&[0, 2], &[0.7, 0.3], &[])
                .parametric()
                .build(),
        ));
        check_dominates(&two_triangles(
            StageBuilder::rational(2)
                .face(&[0, 2], &[0.5, 0.5], &[3.0])
                .build(),
        ));
        check_dominates(&two_triangles(
            StageBuilder::monotonic(3)
                .vertex_map(0, &[0.0, 1.0, 1.5, 2.0])
                .vertex_map(2, &[0.0, 0.2, 0.5, 1.0])
                .build(),
        ));
    }

    #[test]
    fn spectral_norm_matches_known_singular_values() {
        // Rotation (about z by 0.3) times diag(3, 2, 0.5): σ_max = 3.
        let (c, s) = (0.3f64.cos(), 0.3f64.sin());
        let mut a = [[0.0; MAX_VARS]; MAX_VARS];
        let diag = [3.0, 2.0, 0.5];
        let rot = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]];
        for i in 0..3 {
            for j in 0..3 {
                a[i][j] = rot[i][j] * diag[j];
            }
        }
        let b = spectral_norm_bound(3, &a);
        assert!((3.0..3.0 + 1e-6).contains(&b), "{b}");
        let b2 = spectral_norm_bound(
            2,
            &[
                [1.0, 2.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0.0; 4],
                [0.0; 4],
            ],
        );
        // Singular values of [[1,2],[0,1]]: 1 ± √2.
        assert!(
            b2 >= 1.0 + 2f64.sqrt() && b2 < 1.0 + 2f64.sqrt() + 1e-6,
            "{b2}"
        );
    }

    #[test]
    fn identity_stage_has_factor_one() {
        let model = two_triangles(
            StageBuilder::bezier(2)
                .face(&[0, 2], &[0.5, 0.5], &[])
                .build(),
        );
        let map = LocalMap::from_model(&model, 0).unwrap();
        let b = area_element_bound(&map, &edges(&model, 0)).unwrap();
        assert!((b - 1.0).abs() < 1e-8, "{b}");
    }

    #[test]
    fn a_folding_stage_is_refused() {
        // A cubic edge point far outside its edge's natural position does not make the stage fold
        // (adjusted), so fold a Bézier stage of degree 4 in 1-D style: swap b13 and b31 on edge 0-2.
        let model = two_triangles(
            StageBuilder::bezier(4)
                .face(&[0, 2], &[0.25, 0.75, 0.5, 0.5, 0.75, 0.25], &[])
                .build(),
        );
        let map = LocalMap::from_model(&model, 0).unwrap();
        assert!(area_element_bound(&map, &edges(&model, 0)).is_err());
    }
}
