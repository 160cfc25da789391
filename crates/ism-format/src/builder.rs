//! Builders for models and stages, for programs that make ISMs.

use crate::error::{Error, Result};
use crate::model::{Direction, Model, Stage, StageKind, VertexMap};
use crate::rules::Severity;

/// Builds a [`Model`] vertex by vertex; [`ModelBuilder::build`] runs the structural checks.
#[derive(Clone, Debug)]
pub struct ModelBuilder {
    model: Model,
}

impl ModelBuilder {
    /// Starts a model of dimension `n` (2 or 3).
    pub fn new(dimension: u8) -> ModelBuilder {
        ModelBuilder {
            model: Model::new(dimension),
        }
    }

    /// Sets the name in the metadata.
    pub fn name(mut self, name: impl Into<String>) -> Self {
        self.model.metadata.name = Some(name.into());
        self
    }

    /// Sets the generator in the metadata.
    pub fn generator(mut self, generator: impl Into<String>) -> Self {
        self.model.metadata.generator = Some(generator.into());
        self
    }

    /// Sets the description in the metadata.
    pub fn description(mut self, text: impl Into<String>) -> Self {
        self.model.metadata.description = Some(text.into());
        self
    }

    /// Sets the level `c`.
    pub fn level(mut self, level: f64) -> Self {
        self.model.level = level;
        self
    }

    /// Adds a vertex with its value; returns the builder. Ids are assigned in order from 0.
    pub fn vertex(mut self, position: &[f64], value: f64) -> Self {
        self.model.vertices.extend_from_slice(position);
        self.model.values.push(value);
        self
    }

    /// Adds a top simplex (vertex ids, positively oriented).
    pub fn simplex(mut self, ids: &[u32]) -> Self {
        self.model.simplices.extend_from_slice(ids);
        self
    }

    /// Appends a stage (applied after those already added).
    pub fn stage(mut self, stage: Stage) -> Self {
        self.model.stages.push(stage);
        self
    }

    /// Finishes, returning the model if it is structurally valid.
    ///
    /// # Errors
    /// [`Error::Structure`] listing every structural error.
    pub fn build(self) -> Result<Model> {
        let errors: Vec<_> =
            crate::structure::check(&self.model, crate::structure::DEFAULT_MAX_DIAGNOSTICS)
                .into_iter()
                .filter(|d| d.severity == Severity::Error)
                .collect();
        if errors.is_empty() {
            Ok(self.model)
        } else {
            Err(Error::Structure(errors))
        }
    }

    /// Finishes without checking.
    pub fn build_unchecked(self) -> Model {
        self.model
    }
}

/// Builds a [`Stage`].
#[derive(Clone, Debug)]
pub struct StageBuilder {
    stage: Stage,
}

impl StageBuilder {
    /// A Bézier stage of degree `d` (all points fixed until set).
    pub fn bezier(degree: u32) -> StageBuilder {
        StageBuilder {
            stage: Stage::identity(StageKind::Bezier, degree),
        }
    }

    /// A rational stage of degree `d` (points fixed, weights 1 until set).
    pub fn rational(degree: u32) -> StageBuilder {
        StageBuilder {
            stage: Stage::identity(StageKind::Rational, degree),
        }
    }

    /// A monotonic stage of degree `d` (`g_v(t) = t` until set).
    pub fn monotonic(degree: u32) -> StageBuilder {
        StageBuilder {
            stage: Stage::identity(StageKind::Monotonic, degree),
        }
    }

    /// Stores the stage inverted (parametric direction).
    pub fn parametric(mut self) -> Self {
        self.stage.direction = Direction::Parametric;
        self
    }

    /// Sets the label.
    pub fn name(mut self, name: impl Into<String>) -> Self {
        self.stage.name = Some(name.into());
        self
    }

    /// Records a face's owned control points (flat, canonical order). The face ids are sorted here,
    /// with each point's coordinates permuted to match.
    pub fn face(mut self, face: &[u32], points: &[f64], weights: &[f64]) -> Self {
        let m = face.len();
        let mut order: Vec<usize> = (0..m).collect();
        order.sort_by_key(|&i| face[i]);
        let sorted_face: Vec<u32> = order.iter().map(|&i| face[i]).collect();
        let identity = order.iter().enumerate().all(|(a, &b)| a == b);
        let points = if identity || m == 0 {
            points.to_vec()
        } else {
            // Reorder each point's coordinates; the canonical order of owned indices is defined on
            // the sorted face, so a caller with an unsorted face must already list points in the
            // order of the sorted face's multi-indices.
            points
                .chunks(m)
                .flat_map(|p| order.iter().map(move |&i| p[i]))
                .collect()
        };
        self.stage.faces.push(&sorted_face, &points, weights);
        self
    }

    /// Records a monotonic vertex map.
    pub fn vertex_map(mut self, vertex: u32, coefficients: &[f64]) -> Self {
        self.stage.vertex_maps.push(VertexMap {
            vertex,
            coefficients: coefficients.to_vec(),
        });
        self
    }

    /// Finishes.
    pub fn build(self) -> Stage {
        self.stage
    }
}

/// One simplex of a Kuhn triangulation ([`kuhn_simplices`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct KuhnSimplex {
    /// The `n + 1` grid points of the monotone path from the cell's lowest corner to its highest,
    /// as flat grid indices (axis 0 fastest, `cells[a] + 1` points along axis `a`).
    pub corners: Vec<usize>,
    /// Whether the path's axis permutation is odd: on a grid whose axes keep their orientation the
    /// simplex as listed is then negatively oriented (swap two corners to fix it).
    pub odd: bool,
}

impl KuhnSimplex {
    /// The corners as vertex ids of a grid numbered in the builder's flat order, positively
    /// oriented when the grid's axes keep their orientation (an odd path's last two corners
    /// swapped: `det[e_π(0) … e_π(n−1)] = sign(π)`).
    pub fn oriented(&self) -> Vec<u32> {
        let mut ids: Vec<u32> = self.corners.iter().map(|&c| c as u32).collect();
        let n = ids.len();
        if self.odd && n >= 2 {
            ids.swap(n - 2, n - 1);
        }
        ids
    }
}

/// The Kuhn (Freudenthal) triangulation of a grid with `cells[a]` cells along axis `a`
/// (`n = cells.len()` axes): `n!` simplices per cell, one per monotone path from the
/// cell's lowest to its highest corner, conforming because every cell is split the same way.
/// Cells in flat order (axis 0 fastest), within a cell the paths in lexicographic order of their
/// axis permutations (`01, 10`; `012, 021, 102, 120, 201, 210`).
///
/// The one builder of the grids that tests and generators across the workspace start from; each
/// chooses its own coordinates, vertex numbering and orientation fix.
///
/// ```
/// use ism_format::builder::kuhn_simplices;
/// let square = kuhn_simplices(&[1, 1]);
/// assert_eq!(square[0].corners, [0, 1, 3]);
/// assert_eq!((square[1].corners.as_slice(), square[1].odd), ([0, 2, 3].as_slice(), true));
/// assert_eq!(kuhn_simplices(&[2, 1, 3]).len(), 6 * 6);
/// ```
pub fn kuhn_simplices(cells: &[usize]) -> Vec<KuhnSimplex> {
    let n = cells.len();
    // The permutations of the axes in lexicographic order.
    fn permutations(n: usize, current: &mut Vec<usize>, out: &mut Vec<Vec<usize>>) {
        if current.len() == n {
            out.push(current.clone());
            return;
        }
        for axis in 0..n {
            if !current.contains(&axis) {
                current.push(axis);
                permutations(n, current, out);
                current.pop();
            }
        }
    }
    let mut perms = Vec::new();
    permutations(n, &mut Vec::new(), &mut perms);
    // Stride of each axis in the flat numbering of the grid points.
    let mut strides = vec![1usize; n];
    for a in 1..n {
        strides[a] = strides[a - 1] * (cells[a - 1] + 1);
    }
    let count: usize = cells.iter().product();
    let mut out = Vec::with_capacity(count * perms.len());
    for cell in 0..count {
        let mut rest = cell;
        let mut base = 0;
        for a in 0..n {
            base += (rest % cells[a]) * strides[a];
            rest /= cells[a];
        }
        for p in &perms {
            let mut corners = Vec::with_capacity(n + 1);
            corners.push(base);
            for &axis in p.iter() {
                corners.push(corners[corners.len() - 1] + strides[axis]);
            }
            let inversions = (0..n)
                .flat_map(|a| (a + 1..n).map(move |b| (a, b)))
                .filter(|&(a, b)| p[a] > p[b])
                .count();
            out.push(KuhnSimplex {
                corners,
                odd: inversions % 2 == 1,
            });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Integer determinant of the edge vectors of `n + 1` grid points.
    fn det(points: &[Vec<i64>]) -> i64 {
        let e: Vec<Vec<i64>> = points[1..]
            .iter()
            .map(|p| p.iter().zip(&points[0]).map(|(a, b)| a - b).collect())
            .collect();
        match e.len() {
            1 => e[0][0],
            2 => e[0][0] * e[1][1] - e[0][1] * e[1][0],
            _ => {
                e[0][0] * (e[1][1] * e[2][2] - e[1][2] * e[2][1])
                    - e[0][1] * (e[1][0] * e[2][2] - e[1][2] * e[2][0])
                    + e[0][2] * (e[1][0] * e[2][1] - e[1][1] * e[2][0])
            }
        }
    }

    #[test]
    fn kuhn_simplices_tile_the_grid_with_unit_simplices_of_the_stated_orientation() {
        // Truth: grid coordinates decoded from the flat index, and integer determinants: each
        // simplex has volume 1/n! with sign −1 exactly when `odd`, the volumes add up to the
        // grid's, and no simplex repeats.
        for cells in [
            vec![3],
            vec![2, 3],
            vec![3, 1],
            vec![2, 1, 3],
            vec![1, 2, 2],
        ] {
            let n = cells.len();
            let coords = |mut flat: usize| -> Vec<i64> {
                cells
                    .iter()
                    .map(|&c| {
                        let x = flat % (c + 1);
                        flat /= c + 1;
                        x as i64
                    })
                    .collect()
            };
            let simplices = kuhn_simplices(&cells);
            let factorial: usize = (1..=n).product();
            let cubes: usize = cells.iter().product();
            assert_eq!(simplices.len(), factorial * cubes, "{cells:?}");
            let mut seen = std::collections::BTreeSet::new();
            for s in &simplices {
                assert_eq!(s.corners.len(), n + 1);
                let points: Vec<Vec<i64>> = s.corners.iter().map(|&c| coords(c)).collect();
                assert_eq!(det(&points), if s.odd { -1 } else { 1 }, "{cells:?} {s:?}");
                let oriented: Vec<Vec<i64>> =
                    s.oriented().iter().map(|&c| coords(c as usize)).collect();
                assert_eq!(det(&oriented), 1, "{cells:?} {s:?}");
                let grid_points: usize = cells.iter().map(|c| c + 1).product();
                assert!(s.corners.iter().all(|&c| c < grid_points), "{s:?}");
                let mut key = s.corners.clone();
                key.sort_unstable();
                assert!(seen.insert(key), "{cells:?}: {s:?} twice");
            }
        }
        // Any number of axes: 4! simplices per cell of a 4-dimensional grid, the first along the
        // axes in order.
        let four = kuhn_simplices(&[1, 2, 1, 1]);
        assert_eq!(four.len(), 24 * 2);
        assert_eq!(four[0].corners, [0, 1, 3, 9, 21]);
        assert!(kuhn_simplices(&[0, 3]).is_empty());
    }
}
