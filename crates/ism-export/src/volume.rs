//! The complex itself with `F` as a higher-order field: VTK Bézier triangles (type 76) or
//! tetrahedra (type 78), for ParaView or the Python `vtk` package to contour.
//!
//! What is exact and what is approximated:
//! - **no stage**: `F` is the linear interpolant; written as linear cells (exact);
//! - **one polynomial Bézier stage of degree `d`, implicit direction**: `F = Σ f_i X_i` is a
//!   polynomial of degree `d` whose Bernstein coefficients are `c_I = Σ_i f_i b_I[i]`; written as
//!   degree-`d` Bézier cells with linear geometry (control point `I/d`): **exact**;
//! - **anything else** (rational, monotonic, parametric, compositions): `F` is not a polynomial
//!   of the simplex (or VTK's rational cells would also warp the geometry), so it is replaced by
//!   its degree-`p` polynomial interpolant at the lattice points `I/p` (`p` = the product of the
//!   stage degrees, at least 2, at most [`MAX_APPROXIMATION_DEGREE`]): exact at the vertices and the
//!   lattice points, approximate in between. The returned note says which case applied.
//!
//! Control points on a shared face are shared between the cells (keyed by the face's global
//! vertex ids and exponents), so the grid is conforming.

use std::collections::HashMap;

use ism_format::{multi_index, Direction, Model, StageKind};
use ism_geom::{LocalMap, ModelEval, StageLookup, MAX_VARS};

use crate::vtk::{
    cell_type, vtk_local_multi_indices, ArrayValues, Attribute, DataArray, UnstructuredGrid,
};
use crate::{Error, Result};

/// Highest degree of the interpolating approximation (35 control points per tetrahedron at 4).
pub const MAX_APPROXIMATION_DEGREE: u32 = 4;

/// Builds the volume grid and a one-line note on exactness.
///
/// # Errors
/// [`Error::Unsupported`] for a dimension other than 2 or 3 or a model the evaluator rejects.
pub fn volume_grid(model: &Model) -> Result<(UnstructuredGrid, String)> {
    let n = model.dim();
    if n != 2 && n != 3 {
        return Err(Error::Unsupported(format!(
            "volume export needs a 2D or 3D model, got dimension {n}"
        )));
    }
    let m = n + 1;
    let single_bezier = model.stages.len() == 1
        && model.stages[0].kind == StageKind::Bezier
        && model.stages[0].direction == Direction::Implicit;
    let (degree, mode) = if model.stages.is_empty() {
        (1, Mode::Linear)
    } else if single_bezier {
        (model.stages[0].degree, Mode::ExactBezier)
    } else {
        let p = model
            .stages
            .iter()
            .map(|s| s.degree)
            .product::<u32>()
            .clamp(2, MAX_APPROXIMATION_DEGREE);
        (p, Mode::Interpolated)
    };
    let local_order = vtk_local_multi_indices(n, degree);
    let canonical = multi_index::all(m, degree);
    let rank_of: Vec<usize> = local_order.chunks(m).map(multi_index::rank).collect();
    let lookups: Vec<StageLookup> = model
        .stages
        .iter()
        .enumerate()
        .map(|(i, s)| StageLookup::new(s, i))
        .collect();
    let eval = match mode {
        Mode::Interpolated => {
            Some(ModelEval::new(model).map_err(|e| Error::Unsupported(e.to_string()))?)
        }
        _ => None,
    };
    let collocation = match mode {
        Mode::Interpolated => Some(inverse_collocation(m, degree, &canonical)?),
        _ => None,
    };
    let ctype = match (n, mode) {
        (2, Mode::Linear) => cell_type::TRIANGLE,
        (3, Mode::Linear) => cell_type::TETRA,
        (2, _) => cell_type::BEZIER_TRIANGLE,
        _ => cell_type::BEZIER_TETRAHEDRON,
    };
    let mut grid = UnstructuredGrid::default();
    let mut values: Vec<f64> = Vec::new();
    let mut index: HashMap<Vec<(u32, u32)>, u64> = HashMap::new();
    let count = canonical.len() / m;
    for s in 0..model.num_simplices() {
        let ids = model.simplex(s);
        // Bernstein coefficients of F on this simplex, canonical order.
        let coeffs: Vec<f64> = match mode {
            Mode::Linear => (0..m).map(|i| model.values[ids[i] as usize]).collect(),
            Mode::ExactBezier => {
                let map = LocalMap::new(&model.stages, &lookups, ids)
                    .map_err(|e| Error::Unsupported(e.to_string()))?;
                let points = map.stages()[0].control_points();
                (0..count)
                    .map(|r| {
                        let b: [f64; MAX_VARS] = points.get(r).copied().unwrap_or_else(|| {
                            let mut b = [0.0; MAX_VARS];
                            for i in 0..m {
                                b[i] = f64::from(canonical[r * m + i]) / f64::from(degree);
                            }
                            b
                        });
                        (0..m).map(|i| model.values[ids[i] as usize] * b[i]).sum()
                    })
                    .collect()
            }
            Mode::Interpolated => {
                let eval = eval.as_ref().expect("built for this mode");
                let inv = collocation.as_ref().expect("built for this mode");
                let samples: Vec<f64> = (0..count)
                    .map(|r| {
                        let mut w = [0.0; MAX_VARS];
                        for i in 0..m {
                            w[i] = f64::from(canonical[r * m + i]) / f64::from(degree);
                        }
                        eval.value_at(s, &w)
                    })
                    .collect();
                (0..count)
                    .map(|r| (0..count).map(|c| inv[r * count + c] * samples[c]).sum())
                    .collect()
            }
        };
        let order: Vec<&[u32]> = if mode == Mode::Linear {
            Vec::new()
        } else {
            local_order.chunks(m).collect()
        };
        let mut cell = Vec::with_capacity(count);
        let npts = if mode == Mode::Linear { m } else { count };
        for k in 0..npts {
            let (exps, rank): (Vec<u32>, usize) = if mode == Mode::Linear {
                let mut e = vec![0u32; m];
                e[k] = 1;
                (e, k)
            } else {
                (order[k].to_vec(), rank_of[k])
            };
            let mut key: Vec<(u32, u32)> = (0..m)
                .filter(|&i| exps[i] > 0)
                .map(|i| (ids[i], exps[i]))
                .collect();
            key.sort_unstable();
            let id = *index.entry(key).or_insert_with(|| {
                let mut p = [0.0; 3];
                for i in 0..m {
                    let v = model.vertex(ids[i] as usize);
                    for x in 0..n {
                        p[x] += f64::from(exps[i]) / f64::from(degree) * v[x];
                    }
                }
                grid.points.push(p);
                values.push(coeffs[rank]);
                (grid.points.len() - 1) as u64
            });
            cell.push(id);
        }
        grid.push_cell(ctype, cell);
    }
    grid.point_data.push(DataArray {
        name: "F".into(),
        components: 1,
        values: ArrayValues::Float(values),
        attribute: Attribute::Scalars,
    });
    grid.cell_data.push(DataArray {
        name: "SourceSimplex".into(),
        components: 1,
        values: ArrayValues::Int((0..model.num_simplices() as i64).collect()),
        attribute: Attribute::None,
    });
    let note = match mode {
        Mode::Linear => "exact (no stage: linear cells)".to_string(),
        Mode::ExactBezier => format!("exact (one Bézier stage: degree-{degree} Bézier cells with F's Bernstein coefficients)"),
        Mode::Interpolated => format!(
            "approximated (stages {}: degree-{degree} polynomial interpolant of F at the lattice points, exact there and at vertices)",
            model.stages.iter().map(|s| format!("{} d={}", s.kind.as_str(), s.degree)).collect::<Vec<_>>().join(" → ")
        ),
    };
    Ok((grid, note))
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Mode {
    Linear,
    ExactBezier,
    Interpolated,
}

/// Inverse of the Bernstein collocation matrix `A[r][c] = B_c(I_r / d)` at the degree-`d` lattice:
/// Bernstein coefficients = `A⁻¹ ·` values at the lattice points. The lattice is unisolvent, so `A`
/// is invertible; Gauss–Jordan with partial pivoting, hand-written for a matrix of at most 35 × 35
/// built once per export.
fn inverse_collocation(m: usize, d: u32, canonical: &[u32]) -> Result<Vec<f64>> {
    let count = canonical.len() / m;
    let mut a = vec![0.0; count * count];
    for r in 0..count {
        let w: Vec<f64> = (0..m)
            .map(|i| f64::from(canonical[r * m + i]) / f64::from(d))
            .collect();
        for c in 0..count {
            let idx = &canonical[c * m..(c + 1) * m];
            a[r * count + c] = bernstein_basis(d, idx, &w);
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
                "collocation matrix of degree {d} is singular"
            )));
        }
        for k in 0..count {
            a.swap(col * count + k, pivot * count + k);
            inv.swap(col * count + k, pivot * count + k);
        }
        let p = a[col * count + col];
        for k in 0..count {
            a[col * count + k] /= p;
            inv[col * count + k] /= p;
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

/// `B_I(w) = d!/∏ I_i! · ∏ w_i^{I_i}`.
fn bernstein_basis(d: u32, index: &[u32], w: &[f64]) -> f64 {
    let mut coef = 1.0;
    let mut k = 0u32;
    let mut value = 1.0;
    for (&e, &x) in index.iter().zip(w) {
        for j in 1..=e {
            k += 1;
            coef *= f64::from(k) / f64::from(j);
        }
        value *= x.powi(e as i32);
    }
    debug_assert_eq!(k, d);
    coef * value
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Evaluates a Bézier cell's field from its VTK-ordered coefficients at barycentric `w`.
    fn eval_cell(n: usize, d: u32, coeffs: &[f64], w: &[f64]) -> f64 {
        let order = vtk_local_multi_indices(n, d);
        order
            .chunks(n + 1)
            .zip(coeffs)
            .map(|(i, c)| c * bernstein_basis(d, i, w))
            .sum()
    }

    fn cell_coeffs(grid: &UnstructuredGrid, cell: usize) -> Vec<f64> {
        let start = if cell == 0 {
            0
        } else {
            grid.offsets[cell - 1] as usize
        };
        let end = grid.offsets[cell] as usize;
        let ArrayValues::Float(f) = &grid.point_data[0].values else {
            panic!("F is float")
        };
        grid.connectivity[start..end]
            .iter()
            .map(|&p| f[p as usize])
            .collect()
    }

    #[test]
    fn single_bezier_stage_is_exact_against_the_evaluator() {
        for (name, model) in ism_examples::named::all_examples() {
            let (grid, note) = volume_grid(&model).unwrap();
            let eval = ModelEval::new(&model).unwrap();
            let n = model.dim();
            let exact = note.starts_with("exact");
            let degree = if model.stages.is_empty() {
                1
            } else if exact {
                model.stages[0].degree
            } else {
                0
            };
            // Sample points: lattice-free interior points of a few cells.
            for s in (0..model.num_simplices()).step_by(7) {
                let coeffs = cell_coeffs(&grid, s);
                let w: Vec<f64> = if n == 2 {
                    vec![0.2, 0.3, 0.5]
                } else {
                    vec![0.1, 0.2, 0.3, 0.4]
                };
                let mut wb = [0.0; MAX_VARS];
                wb[..n + 1].copy_from_slice(&w);
                let f = eval.value_at(s, &wb);
                if exact {
                    let ours = eval_cell(n, degree, &coeffs, &w);
                    assert!(
                        (ours - f).abs() < 1e-12,
                        "{name} simplex {s}: {ours} vs {f}"
                    );
                } else {
                    // Interpolant: exact at the lattice points, so at vertex 0 (first in VTK order).
                    let v0 = model.values[model.simplex(s)[0] as usize];
                    assert!(
                        (coeffs[0] - v0).abs() < 1e-9,
                        "{name}: vertex coefficient {} vs {v0}",
                        coeffs[0]
                    );
                }
            }
        }
    }
}
