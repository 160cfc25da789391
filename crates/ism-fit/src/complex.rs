//! A mutable simplicial complex: the Kuhn/Freudenthal triangulation of a box and conforming
//! longest-edge bisection.
//!
//! Bisecting an edge splits *every* simplex around it, so the complex stays conforming; Rivara's
//! propagation (split a neighbour's longer edge first) keeps the cells from degenerating.

use std::collections::HashMap;

/// An edge as its two vertex ids, smaller first.
pub type EdgeKey = (u32, u32);

fn edge_key(a: u32, b: u32) -> EdgeKey {
    if a < b {
        (a, b)
    } else {
        (b, a)
    }
}

/// Top simplices of dimension `n` over points of `Rⁿ`, with removal.
#[derive(Clone, Debug)]
pub struct Complex {
    dim: usize,
    /// Flat coordinates, `dim` per vertex.
    points: Vec<f64>,
    /// `dim + 1` vertex ids per slot; dead slots keep their old ids.
    cells: Vec<u32>,
    alive: Vec<bool>,
    /// Live cells around each edge.
    edges: HashMap<EdgeKey, Vec<u32>>,
    /// How the complex was built, when it was built from a Kuhn grid by [`Complex::split_edge`]
    /// alone: the grid and every split, in order — what the structured encoding stores instead
    /// of the coordinates and ids ([`Complex::refinement`]).
    history: Option<History>,
}

/// A Kuhn grid and the edges split since, in order (see [`Complex::refinement`]).
#[derive(Clone, Debug)]
struct History {
    domain: Vec<f64>,
    cells: Vec<u32>,
    splits: Vec<[u32; 2]>,
}

impl Complex {
    /// The Kuhn/Freudenthal triangulation of the box `domain` (`lo, hi` per axis) with `cells[k]`
    /// cubes along axis `k`: each cube is split into `n!` simplices along its main diagonal, every
    /// simplex positively oriented.
    pub fn kuhn(domain: &[f64], cells: &[usize]) -> Complex {
        let dim = cells.len();
        // The grid points of the structured encoding's construction (spec §7.4.3), bit for bit.
        let points = ism_format::refine::grid_points(domain, cells);
        let mut complex = Complex {
            dim,
            points,
            cells: Vec::new(),
            alive: Vec::new(),
            edges: HashMap::new(),
            // A grid too large for u32 counts has no description (no fit gets near it).
            history: cells
                .iter()
                .map(|&c| u32::try_from(c).ok())
                .collect::<Option<Vec<u32>>>()
                .map(|cells| History {
                    domain: domain.to_vec(),
                    cells,
                    splits: Vec::new(),
                }),
        };
        // Grid points are numbered axis 0 fastest, as the builder numbers its corners.
        for s in ism_format::builder::kuhn_simplices(cells) {
            complex.add_cell(&s.oriented());
        }
        complex
    }

    /// Builds a complex from flat points and cells (cells must be positively oriented).
    pub fn from_parts(dim: usize, points: Vec<f64>, cells: &[u32]) -> Complex {
        let mut complex = Complex {
            dim,
            points,
            cells: Vec::new(),
            alive: Vec::new(),
            edges: HashMap::new(),
            history: None,
        };
        for c in cells.chunks_exact(dim + 1) {
            complex.add_cell(c);
        }
        complex
    }

    /// Space dimension `n`.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Number of vertices.
    pub fn num_vertices(&self) -> usize {
        self.points.len() / self.dim
    }

    /// Coordinates of vertex `v`.
    pub fn point(&self, v: u32) -> &[f64] {
        let n = self.dim;
        &self.points[v as usize * n..(v as usize + 1) * n]
    }

    /// All coordinates, flat.
    pub fn points(&self) -> &[f64] {
        &self.points
    }

    /// Number of cell slots (live and dead); ids of live cells are below this.
    pub fn slots(&self) -> usize {
        self.alive.len()
    }

    /// Whether cell slot `c` holds a live cell.
    pub fn is_alive(&self, c: u32) -> bool {
        self.alive[c as usize]
    }

    /// Vertex ids of cell `c` (positively oriented).
    pub fn cell(&self, c: u32) -> &[u32] {
        let m = self.dim + 1;
        &self.cells[c as usize * m..(c as usize + 1) * m]
    }

    /// Ids of the live cells, ascending.
    pub fn live_cells(&self) -> Vec<u32> {
        (0..self.alive.len() as u32)
            .filter(|&c| self.alive[c as usize])
            .collect()
    }

    /// Number of live cells.
    pub fn num_cells(&self) -> usize {
        self.alive.iter().filter(|&&a| a).count()
    }

    /// Live cells around edge `(a, b)`.
    pub fn cells_around(&self, a: u32, b: u32) -> &[u32] {
        self.edges
            .get(&edge_key(a, b))
            .map_or(&[], |v| v.as_slice())
    }

    /// Live cells and their vertices, flat, renumbered densely (for writing a model).
    pub fn compact_cells(&self) -> Vec<u32> {
        self.live_cells()
            .iter()
            .flat_map(|&c| self.cell(c).to_vec())
            .collect()
    }

    /// The complex as a Kuhn grid and its edge splits (spec `ism-format.md` §7.4.3,
    /// `complexForm` 1), with `kept[i]` for its `i`-th live cell; `None` when it was not built
    /// from a grid by splits alone ([`Complex::from_parts`]). Its live cells in order are
    /// [`Complex::compact_cells`]'s: the construction the spec fixes is this type's own —
    /// children of a split appended in the order of the cells around the edge, each list kept in
    /// increasing slot order — which the writer checks by rebuilding before it uses it.
    pub fn refinement(&self, kept: Vec<bool>) -> Option<ism_format::refine::KuhnRefinement> {
        let h = self.history.as_ref()?;
        Some(ism_format::refine::KuhnRefinement {
            domain: h.domain.clone(),
            cells: h.cells.clone(),
            splits: h.splits.clone(),
            kept,
        })
    }

    /// The axis-aligned bounding box of cell `c`: `(lo, hi)`.
    pub fn bounding_box(&self, c: u32) -> (Vec<f64>, Vec<f64>) {
        let n = self.dim;
        let mut lo = vec![f64::INFINITY; n];
        let mut hi = vec![f64::NEG_INFINITY; n];
        for &v in self.cell(c) {
            for (k, &x) in self.point(v).iter().enumerate() {
                lo[k] = lo[k].min(x);
                hi[k] = hi[k].max(x);
            }
        }
        (lo, hi)
    }

    /// Signed volume times `n!` (the determinant of the edge vectors from the first vertex).
    pub fn orientation(&self, c: u32) -> f64 {
        let ids = self.cell(c);
        let n = self.dim;
        let p0 = self.point(ids[0]);
        let mut m = vec![0.0; n * n];
        for (j, &v) in ids[1..].iter().enumerate() {
            for k in 0..n {
                m[k * n + j] = self.point(v)[k] - p0[k];
            }
        }
        determinant(&mut m, n)
    }

    fn add_cell(&mut self, ids: &[u32]) -> u32 {
        let c = self.alive.len() as u32;
        self.cells.extend_from_slice(ids);
        self.alive.push(true);
        for i in 0..ids.len() {
            for j in i + 1..ids.len() {
                self.edges
                    .entry(edge_key(ids[i], ids[j]))
                    .or_default()
                    .push(c);
            }
        }
        c
    }

    fn remove_cell(&mut self, c: u32) {
        self.alive[c as usize] = false;
        let ids = self.cell(c).to_vec();
        for i in 0..ids.len() {
            for j in i + 1..ids.len() {
                let key = edge_key(ids[i], ids[j]);
                if let Some(list) = self.edges.get_mut(&key) {
                    list.retain(|&x| x != c);
                    if list.is_empty() {
                        self.edges.remove(&key);
                    }
                }
            }
        }
    }

    fn length2(&self, e: EdgeKey) -> f64 {
        self.point(e.0)
            .iter()
            .zip(self.point(e.1))
            .map(|(a, b)| (a - b) * (a - b))
            .sum()
    }

    /// The longest edge of cell `c`, ties broken by vertex ids so the order is total (which is
    /// what makes the propagation terminate).
    pub fn longest_edge(&self, c: u32) -> EdgeKey {
        let ids = self.cell(c);
        let mut best: Option<(f64, EdgeKey)> = None;
        for i in 0..ids.len() {
            for j in i + 1..ids.len() {
                let e = edge_key(ids[i], ids[j]);
                let l = self.length2(e);
                let better = match best {
                    None => true,
                    Some((bl, be)) => l > bl || (l == bl && e < be),
                };
                if better {
                    best = Some((l, e));
                }
            }
        }
        best.map(|b| b.1).unwrap_or((0, 0))
    }

    /// Splits edge `e` at its midpoint in every cell around it. Returns the new vertex id and the
    /// new cells. Each child keeps the parent's orientation: replacing one vertex by the midpoint
    /// of an edge from it halves the signed volume.
    pub fn split_edge(&mut self, e: EdgeKey) -> (u32, Vec<u32>) {
        let mid: Vec<f64> = self
            .point(e.0)
            .iter()
            .zip(self.point(e.1))
            .map(|(a, b)| 0.5 * (a + b))
            .collect();
        let m = self.num_vertices() as u32;
        self.points.extend_from_slice(&mid);
        if let Some(h) = &mut self.history {
            h.splits.push([e.0, e.1]);
        }
        let around = self.cells_around(e.0, e.1).to_vec();
        let mut new_cells = Vec::with_capacity(2 * around.len());
        for c in around {
            let ids = self.cell(c).to_vec();
            self.remove_cell(c);
            let a: Vec<u32> = ids.iter().map(|&v| if v == e.1 { m } else { v }).collect();
            let b: Vec<u32> = ids.iter().map(|&v| if v == e.0 { m } else { v }).collect();
            new_cells.push(self.add_cell(&a));
            new_cells.push(self.add_cell(&b));
        }
        (m, new_cells)
    }

    /// Refines cell `c` by longest-edge bisection with propagation (Rivara): while a cell around
    /// `c`'s longest edge has a longer edge of its own, that cell is refined first, so only
    /// longest edges are ever split. Returns the new vertices in insertion order.
    pub fn refine(&mut self, c: u32) -> Vec<u32> {
        let mut new_vertices = Vec::new();
        self.refine_into(c, &mut new_vertices);
        new_vertices
    }

    fn refine_into(&mut self, c: u32, new_vertices: &mut Vec<u32>) {
        while self.alive[c as usize] {
            let e = self.longest_edge(c);
            let blocker = self
                .cells_around(e.0, e.1)
                .iter()
                .copied()
                .find(|&t| self.longest_edge(t) != e);
            match blocker {
                // The blocker's longest edge is strictly greater in the total order, so the chain
                // of recursive calls is finite.
                Some(t) => self.refine_into(t, new_vertices),
                None => {
                    let (m, _) = self.split_edge(e);
                    new_vertices.push(m);
                }
            }
        }
    }
}

/// Determinant by Gaussian elimination with partial pivoting (`m` is overwritten). Small fixed
/// sizes (n ≤ 3) only; a linear-algebra crate would be heavier than this loop.
pub(crate) fn determinant(m: &mut [f64], n: usize) -> f64 {
    let mut det = 1.0;
    for col in 0..n {
        let pivot = (col..n)
            .max_by(|&a, &b| m[a * n + col].abs().total_cmp(&m[b * n + col].abs()))
            .unwrap_or(col);
        if m[pivot * n + col] == 0.0 {
            return 0.0;
        }
        if pivot != col {
            for k in 0..n {
                m.swap(pivot * n + k, col * n + k);
            }
            det = -det;
        }
        det *= m[col * n + col];
        for row in col + 1..n {
            let factor = m[row * n + col] / m[col * n + col];
            for k in col..n {
                m[row * n + k] -= factor * m[col * n + k];
            }
        }
    }
    det
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    /// Conformity: every (n−1)-face is shared by at most two cells, and a face on one cell only
    /// lies on the box boundary.
    fn assert_conforming(c: &Complex, domain: &[f64]) {
        let n = c.dim();
        let mut faces: HashMap<Vec<u32>, usize> = HashMap::new();
        for cell in c.live_cells() {
            assert!(c.orientation(cell) > 0.0, "cell {cell} not positive");
            let ids = c.cell(cell);
            for skip in 0..=n {
                let mut f: Vec<u32> = ids
                    .iter()
                    .enumerate()
                    .filter(|(i, _)| *i != skip)
                    .map(|(_, &v)| v)
                    .collect();
                f.sort();
                *faces.entry(f).or_default() += 1;
            }
        }
        for (f, count) in faces {
            assert!(count <= 2, "face {f:?} on {count} cells");
            if count == 1 {
                let on_boundary = (0..n).any(|k| {
                    f.iter().all(|&v| c.point(v)[k] == domain[2 * k])
                        || f.iter().all(|&v| c.point(v)[k] == domain[2 * k + 1])
                });
                assert!(on_boundary, "hanging face {f:?}");
            }
        }
    }

    fn total_volume(c: &Complex) -> f64 {
        let fact: f64 = (1..=c.dim()).map(|k| k as f64).product();
        c.live_cells()
            .iter()
            .map(|&x| c.orientation(x) / fact)
            .sum()
    }

    #[test]
    fn kuhn_is_positive_conforming_and_fills_the_box() {
        let d2 = [0.0, 1.0, 0.0, 2.0];
        let k2 = Complex::kuhn(&d2, &[3, 4]);
        assert_eq!(k2.num_cells(), 2 * 12);
        assert_conforming(&k2, &d2);
        assert!((total_volume(&k2) - 2.0).abs() < 1e-12);
        let d3 = [-1.0, 1.0, 0.0, 1.0, 0.0, 0.5];
        let k3 = Complex::kuhn(&d3, &[2, 2, 3]);
        assert_eq!(k3.num_cells(), 6 * 12);
        assert_conforming(&k3, &d3);
        assert!((total_volume(&k3) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn refinement_keeps_conformity_orientation_and_volume() {
        for (domain, res) in [
            (vec![0.0, 1.0, 0.0, 1.0], vec![2, 2]),
            (vec![0.0, 1.0, 0.0, 1.0, 0.0, 1.0], vec![2, 2, 2]),
        ] {
            let mut c = Complex::kuhn(&domain, &res);
            // Deterministic pseudo-random choice of cells to refine.
            let mut rng = crate::test_rng::Lcg::new(12345);
            for _ in 0..60 {
                let live = c.live_cells();
                let pick = live[(rng.next_u64() >> 33) as usize % live.len()];
                let before = c.num_vertices();
                let added = c.refine(pick);
                assert!(!added.is_empty());
                assert_eq!(c.num_vertices(), before + added.len());
                assert!(!c.is_alive(pick));
            }
            assert_conforming(&c, &domain);
            assert!((total_volume(&c) - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn determinant_of_a_swap_is_minus_one() {
        let mut m = vec![0.0, 1.0, 1.0, 0.0];
        assert_eq!(determinant(&mut m, 2), -1.0);
    }
}
