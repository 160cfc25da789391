//! Exact volume cells: models whose parametric stages (if any) come before their implicit ones —
//! every model `ism fit` writes (all parametric), every all-implicit one — as isoparametric
//! (rational) Bézier cells whose geometry is the model's own parametrisation (the straight simplex
//! without parametric stages) and whose field is `F` on it.
//!
//! **Why it is exact.** With stages `0 … j−1` parametric (`X_k = Y_k⁻¹`) and `j …` implicit
//! (`X_k = Y_k`), put `v = X_{j−1} ∘ ⋯ ∘ X_0 (w)`. Then `w = Y_0(Y_1(⋯Y_{j−1}(v)⋯))` and
//! `F = f̂(Y_{m−1}(⋯Y_j(v)⋯))` are both ratios of polynomials of `v` (each stage applied
//! projectively in the Bernstein basis, as for the certificate in [`super`]): `w(v) = N_x / D_x`,
//! `F(v) = N_F / D_F`, of degrees `E_x` and `E_F` (products of the stages' degrees). A VTK Bézier
//! cell maps its parameter `v` to a point and a value with the same (rational) basis, so the cell
//! of degree `E = E_x + E_F` with weights `ω = D_x·D_F`, control points `(Σ pᵢ N_x,i)·D_F / ω` and
//! values `N_F·D_x / ω` (Bernstein coefficients) has point `x(v)` and value `F(x(v))` for every
//! `v` — `F` itself, with no interpolation error. When every stage is a Bézier map (no rational or
//! monotonic stage) both denominators are `(Σ v)^E ≡ 1` and the cell is polynomial of degree
//! `max(E_x, E_F)`. Every stage with data anywhere is composed on every simplex, identity there or
//! not (see [`chain`]), so all cells have one degree.
//!
//! **Continuity.** A control point is identified by the face that owns it and its exponents there
//! (`super::PointIds`: the face's id and the exponents' rank in the face's global vertex order),
//! so neighbours share it. The stages keep faces in place and are stored face-locally, and both
//! neighbours compose the same chain, so their coefficients on a shared face are the same numbers
//! up to rounding; the first cell's are written.
//!
//! **What is reported.** Per cell, the written weights, values and points differ from the cell's
//! own coefficients only by that sharing and by rounding: with `ω'`, `φ'` written and `ω`, `ωφ`
//! the cell's own, `|F' − F| ≤ (max |ω'φ' − ωφ| + max |φ| · max |ω' − ω|) / min ω'` at every
//! parameter (`F` is a convex combination of the `φ` when the weights are positive), plus the
//! rounding allowance of [`ROUNDING_ALLOWANCE_ULPS`]; the same for the points. A non-positive
//! weight, a chain with an implicit stage before a parametric one, or a degree above
//! [`MAX_EXACT_DEGREE`] makes [`exact_grid`] decline (`None`): the caller falls back to
//! interpolated cells.

use ism_format::progress::{Cancelled, Progress};
use ism_format::{multi_index, Direction, Model, StageKind};
use ism_geom::{Bernstein, LocalStage, ModelEval};
use rayon::prelude::*;

use super::{
    apply_stage, attach_arrays, composed_degree, coordinates, sum, PointIds, VolumeReport, PHASE,
    ROUNDING_ALLOWANCE_ULPS,
};
use crate::vtk::{cell_type, vtk_local_multi_indices, UnstructuredGrid};
use crate::Result;

/// Highest degree of an exact cell. A degree-`E` tetrahedron has `C(E + 3, 3)` control points
/// (455 at 12); the fitted presets need 6 (a quadratic edge stratum and a cubic face stratum);
/// a cell of degree 24 (the certificate's [`super::MAX_COMPOSED_DEGREE`]) would write 2 925 points
/// per tetrahedron, where a degree-5 interpolant meets `stratified-3d`'s default tolerance with 56.
pub const MAX_EXACT_DEGREE: u32 = 12;

/// One simplex's exact cell: Bernstein polynomials of the parameter `v` (canonical order).
struct ExactCell {
    /// `ω`; `None`: every weight 1 (a polynomial cell).
    weight: Option<Bernstein>,
    /// `ω · x_c` for each spatial coordinate `c`.
    position: Vec<Bernstein>,
    /// `ω · F`.
    field: Bernstein,
}

impl ExactCell {
    fn elevate_to(self, e: u32) -> ExactCell {
        ExactCell {
            weight: self.weight.map(|w| w.elevate_to(e)),
            position: self.position.iter().map(|p| p.elevate_to(e)).collect(),
            field: self.field.elevate_to(e),
        }
    }
}

/// `stages` composed projectively on the coordinates of `v`, applied in iteration order, and
/// whether any of them is rational or monotonic (a denominator other than 1).
fn compose<'a>(m: usize, stages: impl Iterator<Item = &'a LocalStage>) -> (Vec<Bernstein>, bool) {
    let mut x = coordinates(m);
    let mut rational = false;
    for s in stages {
        rational |= s.kind() != StageKind::Bezier;
        x = apply_stage(s, &x);
    }
    (x, rational)
}

/// The exact cell of simplex `ids` under its `stages` (every stage of the chain, identity or not,
/// in application order), whose first `j` are parametric and the rest implicit, of degree `e`.
fn exact_cell(model: &Model, stages: &[LocalStage], j: usize, e: u32, ids: &[u32]) -> ExactCell {
    let m = model.dim() + 1;
    let n = m - 1;
    // w(v) = Y_0(⋯Y_{j−1}(v)): the last parametric stage is applied first.
    let (x, rx) = compose(m, stages[..j].iter().rev());
    let (y, rf) = compose(m, stages[j..].iter());
    let position: Vec<Bernstein> = (0..n)
        .map(|c| sum((0..m).map(|i| x[i].scale(model.vertex(ids[i] as usize)[c]))).expect("m ≥ 2"))
        .collect();
    let nf = sum((0..m).map(|i| y[i].scale(model.values[ids[i] as usize]))).expect("m ≥ 2");
    if !(rx || rf) {
        return ExactCell {
            weight: None,
            position,
            field: nf,
        }
        .elevate_to(e);
    }
    // Multiplying by a denominator that is identically 1 (`(Σ v)^E` in the Bernstein basis)
    // is a degree elevation.
    let dx = rx.then(|| sum(x.iter().cloned()).expect("m ≥ 2"));
    let df = rf.then(|| sum(y.iter().cloned()).expect("m ≥ 2"));
    let times = |p: &Bernstein, d: &Option<Bernstein>| match d {
        Some(d) => p.mul(d).elevate_to(e),
        None => p.elevate_to(e),
    };
    let weight = match (&dx, &df) {
        (Some(a), Some(b)) => a.mul(b),
        (Some(a), None) | (None, Some(a)) => a.elevate_to(e),
        (None, None) => unreachable!("one of them is rational"),
    };
    ExactCell {
        weight: Some(weight),
        position: position.iter().map(|p| times(p, &df)).collect(),
        field: times(&nf, &dx),
    }
}

/// The stages an exact cell composes — every stage with a record or vertex map anywhere (a stage
/// without any is the identity everywhere) — with the number of leading parametric ones and the
/// cells' degree, or `None` when an implicit stage comes before a parametric one or the degree
/// exceeds [`MAX_EXACT_DEGREE`].
///
/// A stage that is the identity on some simplices only is still composed there: a rational
/// representation is unique only up to a common factor, and leaving out an identity Bézier stage
/// after a rational one drops the factor `D^(d−1)` on one side of a face and not on the other
/// (measured: the examples' neighbours then disagreed by 0.1–0.25 in their shared weights).
fn chain(model: &Model) -> Option<(Vec<usize>, usize, u32)> {
    let active: Vec<usize> = (0..model.stages.len())
        .filter(|&i| {
            let s = &model.stages[i];
            !s.faces.is_empty() || !s.vertex_maps.is_empty()
        })
        .collect();
    let parametric = |i: &usize| model.stages[*i].direction == Direction::Parametric;
    let j = active.iter().take_while(|i| parametric(i)).count();
    if active[j..].iter().any(parametric) {
        return None;
    }
    let degree_of = |s: &[usize]| composed_degree(s.iter().map(|&i| model.stages[i].degree));
    let (ex, ef) = (degree_of(&active[..j]), degree_of(&active[j..]));
    let any_rational = active
        .iter()
        .any(|&i| model.stages[i].kind != StageKind::Bezier);
    let e = if any_rational {
        ex.saturating_add(ef)
    } else {
        ex.max(ef)
    };
    (e <= u64::from(MAX_EXACT_DEGREE)).then_some((active, j, e as u32))
}

/// The complex as exact (rational) Bézier cells (module doc), or `None` when some simplex's chain
/// has no such form or a weight is not positive. `tolerance` is only reported against.
///
/// # Errors
/// [`crate::Error::Cancelled`] when `progress` was cancelled.
pub(super) fn exact_grid(
    eval: &ModelEval,
    tolerance: f64,
    progress: &Progress,
) -> Result<Option<(UnstructuredGrid, VolumeReport)>> {
    let model = eval.model();
    let n = model.dim();
    let m = n + 1;
    let ns = model.num_simplices();
    let Some((active, j, degree)) = chain(model) else {
        return Ok(None);
    };
    let counter = progress.phase(PHASE, ns as u64);
    let cells: Vec<ExactCell> = (0..ns)
        .into_par_iter()
        .map(|s| {
            if counter.is_cancelled() {
                return Err(crate::Error::Cancelled(Cancelled));
            }
            counter.add(1);
            let stages = active
                .iter()
                .map(|&i| LocalStage::from_indexed(eval.indexed(), i, s))
                .collect::<std::result::Result<Vec<_>, _>>()?;
            Ok(exact_cell(model, &stages, j, degree, model.simplex(s)))
        })
        .collect::<Result<_>>()?;
    let rational = cells.iter().any(|c| c.weight.is_some());

    let local_order = vtk_local_multi_indices(n, degree);
    let rank_of: Vec<usize> = local_order.chunks(m).map(multi_index::rank).collect();
    let ctype = if n == 2 {
        cell_type::BEZIER_TRIANGLE
    } else {
        cell_type::BEZIER_TETRAHEDRON
    };
    let mut grid = UnstructuredGrid::default();
    let (mut values, mut weights) = (Vec::new(), Vec::new());
    let mut index = PointIds::new(model, eval.indexed().topology(), degree);
    let (mut field_bound, mut point_bound) = (0.0f64, 0.0f64);
    let allowance = ROUNDING_ALLOWANCE_ULPS * f64::EPSILON * f64::from(degree + 1);
    for (s, cell) in cells.iter().enumerate() {
        let mut conn = Vec::with_capacity(rank_of.len());
        // Largest differences of the written (ω', ω'φ', ω'P') from the cell's own, and the
        // magnitudes the bound and the allowance scale with.
        let (mut d_w, mut d_f, mut d_p) = (0.0f64, 0.0f64, 0.0f64);
        let (mut min_w, mut max_w) = (f64::INFINITY, 0.0f64);
        let (mut max_f, mut max_p, mut max_wf, mut max_wp) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        for (j, &rank) in local_order.chunks(m).zip(&rank_of) {
            let slot = index.slot(s, j);
            let w = cell.weight.as_ref().map_or(1.0, |w| w.coeffs()[rank]);
            let wf = cell.field.coeffs()[rank];
            let mut wp = [0.0; 3];
            for (c, p) in cell.position.iter().enumerate() {
                wp[c] = p.coeffs()[rank];
            }
            max_f = max_f.max((wf / w).abs());
            max_wf = max_wf.max(wf.abs());
            for &v in &wp[..n] {
                max_p = max_p.max((v / w).abs());
                max_wp = max_wp.max(v.abs());
            }
            let id = match index.get(slot) {
                Some(id) => id,
                None => {
                    let mut pt = [0.0; 3];
                    for c in 0..n {
                        pt[c] = wp[c] / w;
                    }
                    grid.points.push(pt);
                    values.push(wf / w);
                    weights.push(w);
                    let id = (grid.points.len() - 1) as u64;
                    index.set(slot, id);
                    id
                }
            };
            let (w2, f2, p2) = (
                weights[id as usize],
                values[id as usize],
                grid.points[id as usize],
            );
            min_w = min_w.min(w2);
            max_w = max_w.max(w.abs());
            d_w = d_w.max((w2 - w).abs());
            d_f = d_f.max((w2 * f2 - wf).abs());
            for c in 0..n {
                d_p = d_p.max((w2 * p2[c] - wp[c]).abs());
            }
            conn.push(id);
        }
        // A weight that is not positive (or NaN: `partial_cmp` is `None`) has no convex bound.
        if min_w.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return Ok(None);
        }
        let f = (d_f + max_f * d_w + allowance * (max_wf + max_f * max_w)) / min_w;
        let p = (d_p + max_p * d_w + allowance * (max_wp + max_p * max_w)) / min_w;
        if !(f.is_finite() && p.is_finite()) {
            return Ok(None);
        }
        field_bound = field_bound.max(f);
        point_bound = point_bound.max(p);
        grid.push_cell(ctype, conn);
    }
    attach_arrays(
        &mut grid,
        values,
        rational.then_some(weights),
        (0..ns as i64).collect(),
    );
    let kind = if rational { "rational " } else { "" };
    let report = VolumeReport {
        degree,
        level: 0,
        cells: grid.num_cells(),
        control_points: grid.points.len(),
        bound: field_bound,
        global_bound: field_bound,
        tolerance,
        certified: true,
        exact: true,
        met: field_bound <= tolerance,
        note: if j == 0 {
            format!(
                "EXACT: one {kind}Bézier cell of degree {degree} per simplex, F itself (the stages composed) on the straight simplex; max |F_vtk − F| ≤ {field_bound:.3e} (rounding and shared control points, certified)"
            )
        } else {
            format!(
                "EXACT: one {kind}Bézier cell of degree {degree} per simplex, its geometry the model's own parametrisation x(v) (the parametric stages) and its field F(x(v)) (the implicit stages on f̂); max |F_vtk − F| ≤ {field_bound:.3e} at every parameter and the points within {point_bound:.3e} of x(v) (rounding and shared control points, certified)"
            )
        },
    };
    Ok(Some((grid, report)))
}
