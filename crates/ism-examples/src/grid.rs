//! Kuhn (Freudenthal) triangulations of boxes and vertex values from an implicit function.

use ism_format::builder::kuhn_simplices;
use ism_format::Model;

use crate::Error;

/// An axis-aligned box `[min, max]` in `N` dimensions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb<const N: usize> {
    /// Lower corner.
    pub min: [f64; N],
    /// Upper corner.
    pub max: [f64; N],
}

impl<const N: usize> Aabb<N> {
    /// The box with corners `min` and `max`.
    pub fn new(min: [f64; N], max: [f64; N]) -> Self {
        Aabb { min, max }
    }

    /// The cube `[lo, hi]ᴺ`.
    pub fn cube(lo: f64, hi: f64) -> Self {
        Aabb {
            min: [lo; N],
            max: [hi; N],
        }
    }

    /// Grid point `i` along axis `a` of a grid with `cells` cells on that axis. The last point is
    /// exactly `max` (not `min + cells · step`), so grids of neighbouring boxes meet exactly.
    fn coordinate(&self, a: usize, i: usize, cells: usize) -> f64 {
        if i == cells {
            self.max[a]
        } else {
            self.min[a] + (self.max[a] - self.min[a]) * (i as f64 / cells as f64)
        }
    }

    fn check(&self, cells: &[usize]) -> Result<(), Error> {
        for a in 0..N {
            if !(self.min[a].is_finite() && self.max[a].is_finite() && self.min[a] < self.max[a]) {
                return Err(Error::BadBox {
                    axis: a,
                    min: self.min[a],
                    max: self.max[a],
                });
            }
        }
        if let Some(axis) = cells.iter().position(|&c| c == 0) {
            return Err(Error::NoCells { axis });
        }
        Ok(())
    }
}

/// Relative size of the nudge that moves a vertex value off the level (see [`set_values`]).
///
/// A value equal to the level puts the shape through a vertex, which the format forbids (ISM-113).
/// Moving it by 1e-6 of the largest `|g − c|` on the grid keeps the shape within a millionth of the
/// function's range of the exact one, while `value − c` stays ten orders of magnitude above the
/// rounding error of `f64`, so later computations see a definite sign.
pub const VALUE_NUDGE: f64 = 1e-6;

/// Sets `values` from `g` at every vertex, keeping `model.level`.
///
/// Deterministic nudge: a value exactly equal to the level `c` becomes `c + ε` (the vertex counts
/// as outside), with `ε = VALUE_NUDGE · max_v |g(v) − c|` (or `VALUE_NUDGE` when `g ≡ c`). A value
/// exactly zero (forbidden, ISM-112) becomes `−ε` when `c > 0` and `+ε` otherwise, which keeps its
/// side of the level.
///
/// # Errors
/// [`Error::NonFiniteValue`] when `g` returns NaN or ±∞ at some vertex.
pub fn set_values(model: &mut Model, g: impl Fn(&[f64]) -> f64) -> Result<(), Error> {
    let n = model.dim();
    let c = model.level;
    let mut values = Vec::with_capacity(model.num_vertices());
    for (v, p) in model.vertices.chunks_exact(n).enumerate() {
        let x = g(p);
        if !x.is_finite() {
            return Err(Error::NonFiniteValue {
                vertex: v,
                value: x,
            });
        }
        values.push(x);
    }
    let spread = values.iter().fold(0.0f64, |m, &x| m.max((x - c).abs()));
    let eps = if spread > 0.0 {
        VALUE_NUDGE * spread
    } else {
        VALUE_NUDGE
    };
    for x in &mut values {
        if *x == c {
            *x = c + eps;
        }
        if *x == 0.0 {
            *x = if c > 0.0 { -eps } else { eps };
        }
    }
    model.values = values;
    Ok(())
}

fn check_vertex_count(count: usize) -> Result<(), Error> {
    if count > u32::MAX as usize {
        return Err(Error::TooLarge { vertices: count });
    }
    Ok(())
}

/// The Kuhn triangulation of an `nx × ny` grid of `bbox`: two triangles per square, all sharing
/// the diagonal direction `(+1, +1)`, so the complex is conforming.
///
/// Vertex `(i, j)` has id `i + (nx + 1)·j`. Square `(i, j)` (squares in order `i` fastest) gives
/// triangles `(v00, v10, v11)` and `(v00, v11, v01)`, both positively oriented. Values come from
/// `g` as in [`set_values`]; the level is 0.
///
/// # Errors
/// [`Error::NoCells`], [`Error::BadBox`], [`Error::TooLarge`], [`Error::NonFiniteValue`].
///
/// ```
/// use ism_examples::{kuhn_grid_2d, Aabb};
/// let m = kuhn_grid_2d(3, 2, Aabb::cube(-1.0, 1.0), |p| p[0] * p[0] + p[1] * p[1] - 0.25)?;
/// assert_eq!((m.num_vertices(), m.num_simplices()), (12, 12));
/// # Ok::<(), ism_examples::Error>(())
/// ```
pub fn kuhn_grid_2d(
    nx: usize,
    ny: usize,
    bbox: Aabb<2>,
    g: impl Fn(&[f64]) -> f64,
) -> Result<Model, Error> {
    bbox.check(&[nx, ny])?;
    let count = (nx + 1).checked_mul(ny + 1).ok_or(Error::TooLarge {
        vertices: usize::MAX,
    })?;
    check_vertex_count(count)?;
    let mut model = Model::new(2);
    model.vertices.reserve(2 * count);
    for j in 0..=ny {
        let y = bbox.coordinate(1, j, ny);
        for i in 0..=nx {
            model
                .vertices
                .extend_from_slice(&[bbox.coordinate(0, i, nx), y]);
        }
    }
    kuhn_into(&mut model, &[nx, ny]);
    set_values(&mut model, g)?;
    Ok(model)
}

/// Appends the simplices of the Kuhn triangulation of the grid ([`kuhn_simplices`]: cells axis 0
/// fastest, grid point ids in the same flat order), each positively oriented
/// ([`ism_format::builder::KuhnSimplex::oriented`]: an odd path's last two vertices swapped).
fn kuhn_into(model: &mut Model, cells: &[usize]) {
    let simplices = kuhn_simplices(cells);
    model.simplices.reserve(simplices.len() * (cells.len() + 1));
    for s in simplices {
        model.simplices.extend(s.oriented());
    }
}

/// The Kuhn (Freudenthal) triangulation of an `nx × ny × nz` grid of `bbox`: six tetrahedra per
/// cube, one per monotone path from the cube's lowest to its highest corner, conforming because every
/// cube is split the same way.
///
/// Vertex `(i, j, k)` has id `i + (nx + 1)·(j + (ny + 1)·k)`. The tetrahedron of path `π` is
/// `(c, c + e_π0, c + e_π0 + e_π1, c + 1)`; its orientation is the sign of `π`, so for odd `π` the
/// last two vertices are swapped. Cubes in order `i` fastest, then `j`, then `k`; paths in the
/// order `012, 021, 102, 120, 201, 210`. Values come from `g` as in [`set_values`]; the level is 0.
///
/// # Errors
/// [`Error::NoCells`], [`Error::BadBox`], [`Error::TooLarge`], [`Error::NonFiniteValue`].
///
/// ```
/// use ism_examples::{kuhn_grid_3d, Aabb};
/// let m = kuhn_grid_3d(2, 2, 2, Aabb::cube(-1.0, 1.0), |p| p.iter().map(|x| x * x).sum::<f64>() - 0.5)?;
/// assert_eq!((m.num_vertices(), m.num_simplices()), (27, 48));
/// # Ok::<(), ism_examples::Error>(())
/// ```
pub fn kuhn_grid_3d(
    nx: usize,
    ny: usize,
    nz: usize,
    bbox: Aabb<3>,
    g: impl Fn(&[f64]) -> f64,
) -> Result<Model, Error> {
    bbox.check(&[nx, ny, nz])?;
    let count = (nx + 1)
        .checked_mul(ny + 1)
        .and_then(|c| c.checked_mul(nz + 1))
        .ok_or(Error::TooLarge {
            vertices: usize::MAX,
        })?;
    check_vertex_count(count)?;
    let mut model = Model::new(3);
    model.vertices.reserve(3 * count);
    for k in 0..=nz {
        let z = bbox.coordinate(2, k, nz);
        for j in 0..=ny {
            let y = bbox.coordinate(1, j, ny);
            for i in 0..=nx {
                model
                    .vertices
                    .extend_from_slice(&[bbox.coordinate(0, i, nx), y, z]);
            }
        }
    }
    kuhn_into(&mut model, &[nx, ny, nz]);
    set_values(&mut model, g)?;
    Ok(model)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ism_format::structure::{check, orientation};

    #[test]
    fn grids_are_structurally_valid_and_positive() {
        let m2 = kuhn_grid_2d(4, 3, Aabb::new([0.0, -1.0], [2.0, 1.0]), |p| p[0] - 0.7).unwrap();
        let m3 = kuhn_grid_3d(3, 2, 2, Aabb::cube(0.0, 1.0), |p| p[2] - 0.31).unwrap();
        for m in [&m2, &m3] {
            assert!(check(m, 100).is_empty(), "{:?}", check(m, 100));
            for s in 0..m.num_simplices() {
                assert!(orientation(m, s).0 > 0.0);
            }
        }
        assert_eq!(m2.num_simplices(), 24);
        assert_eq!(m3.num_simplices(), 6 * 12);
        // Volumes add up to the box: the tetrahedra tile the cube without overlap.
        let vol: f64 = (0..m3.num_simplices())
            .map(|s| orientation(&m3, s).0 / 6.0)
            .sum();
        assert!((vol - 1.0).abs() < 1e-12, "{vol}");
        let area: f64 = (0..m2.num_simplices())
            .map(|s| orientation(&m2, s).0 / 2.0)
            .sum();
        assert!((area - 4.0).abs() < 1e-12, "{area}");
    }

    #[test]
    fn values_at_level_or_zero_are_nudged_outward_or_keep_their_side() {
        let mut m = kuhn_grid_2d(2, 2, Aabb::cube(-1.0, 1.0), |p| p[0]).unwrap();
        // p[0] = 0 on the middle column: nudged to +1e-6 (outside).
        assert!(m.values.iter().all(|&v| v != 0.0));
        assert_eq!(m.values[1], VALUE_NUDGE);
        m.level = 0.5;
        set_values(&mut m, |p| p[0] + 0.5).unwrap();
        // p[0] + 0.5 = 0.5 = c at x = 0 → c + ε; = 0 at x = −0.5 never (grid has x ∈ {−1, 0, 1}).
        assert_eq!(m.values[1], 0.5 + VALUE_NUDGE * 1.0);
        set_values(&mut m, |p| p[0] + 1.0).unwrap();
        // Zero at x = −1 with c = 0.5 > 0: inside, so −ε with ε = 1e-6 · max|g − c| = 1.5e-6.
        assert_eq!(m.values[0], -VALUE_NUDGE * 1.5);
        assert!(check(&m, 100).is_empty());
    }

    #[test]
    fn bad_arguments_are_typed_errors() {
        assert!(matches!(
            kuhn_grid_2d(0, 1, Aabb::cube(0.0, 1.0), |_| 1.0),
            Err(Error::NoCells { axis: 0 })
        ));
        assert!(matches!(
            kuhn_grid_2d(1, 1, Aabb::cube(1.0, 1.0), |_| 1.0),
            Err(Error::BadBox { axis: 0, .. })
        ));
        assert!(matches!(
            kuhn_grid_3d(1, 1, 1, Aabb::cube(0.0, 1.0), |_| f64::NAN),
            Err(Error::NonFiniteValue { vertex: 0, .. })
        ));
        assert!(matches!(
            kuhn_grid_3d(5000, 5000, 5000, Aabb::cube(0.0, 1.0), |_| 1.0),
            Err(Error::TooLarge { .. })
        ));
    }
}
