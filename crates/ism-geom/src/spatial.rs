//! Spatial index of the top simplices' bounding boxes for point location.
//!
//! A uniform grid (cells ≈ 2 × simplices, compressed-row storage) is the first choice: one cell
//! lookup and a handful of candidates, several times faster than a tree on the quasi-uniform
//! meshes the project generates (Kuhn grids, refined complexes). When the mesh is so graded or
//! elongated that boxes would be replicated into too many cells, it falls back to an R*-tree
//! (`rstar`, maintained, bulk-loaded in `O(N log N)`), whose cost does not depend on grading.

use rstar::{RTree, RTreeObject, AABB};

/// Replication bound: if the grid would store more than this many (cell, simplex) entries per
/// simplex on average, the mesh is too graded or elongated for a uniform grid and the R*-tree is
/// used. Cells are as large as the mean box, so a box overlaps ≤ 2 cells per axis (≤ 8 entries in
/// 3-D) unless it is much larger than the mean.
const MAX_ENTRIES_PER_SIMPLEX: usize = 16;

/// Occupancy bound: a cell listing more boxes than this means small simplices crowd into one
/// cell (strong grading); scanning them would cost more than an R*-tree descent.
const MAX_CELL_OCCUPANCY: u32 = 256;

/// One bounding box with its simplex id (first `n` coordinates used).
#[derive(Clone, Copy, Debug)]
pub(crate) struct SimplexBox {
    pub lo: [f64; 3],
    pub hi: [f64; 3],
    pub id: u32,
}

impl RTreeObject for SimplexBox {
    type Envelope = AABB<[f64; 3]>;
    fn envelope(&self) -> Self::Envelope {
        AABB::from_corners(self.lo, self.hi)
    }
}

#[derive(Debug)]
pub(crate) struct Grid {
    n: usize,
    lo: [f64; 3],
    /// Cells per unit length along each axis.
    scale: [f64; 3],
    dims: [usize; 3],
    /// `items[start[c]..start[c + 1]]` are the simplices whose box overlaps cell `c`.
    start: Vec<u32>,
    items: Vec<u32>,
}

impl Grid {
    #[inline]
    fn cell_coord(&self, x: usize, v: f64) -> usize {
        let c = ((v - self.lo[x]) * self.scale[x]).floor();
        if c.is_nan() || c < 0.0 {
            0
        } else {
            (c as usize).min(self.dims[x] - 1)
        }
    }

    /// Cells a box is listed in: half-open in the upper bound, `[floor(lo), ceil(hi) − 1]`, so that
    /// a box ending exactly on a cell plane is not listed in the next cell (on grid-aligned meshes
    /// that would multiply the candidates by 2ⁿ); queries exactly on a plane also look at the
    /// cell below (see [`SpatialIndex::candidates`]).
    fn cell_range(&self, b: &SimplexBox) -> ([usize; 3], [usize; 3]) {
        let mut a = [0; 3];
        let mut z = [0; 3];
        for x in 0..self.n {
            a[x] = self.cell_coord(x, b.lo[x]);
            let t = ((b.hi[x] - self.lo[x]) * self.scale[x]).ceil() - 1.0;
            z[x] = if t.is_nan() || t < 0.0 {
                0
            } else {
                (t as usize).min(self.dims[x] - 1)
            }
            .max(a[x]);
        }
        (a, z)
    }

    fn linear(&self, c: [usize; 3]) -> usize {
        (c[2] * self.dims[1] + c[1]) * self.dims[0] + c[0]
    }

    /// Builds the grid, or `None` when it would replicate boxes too much.
    fn build(n: usize, boxes: &[SimplexBox]) -> Option<Grid> {
        if boxes.is_empty() || boxes.len() >= u32::MAX as usize {
            return None;
        }
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for b in boxes {
            for x in 0..n {
                lo[x] = lo[x].min(b.lo[x]);
                hi[x] = hi[x].max(b.hi[x]);
            }
        }
        if (0..n).any(|x| !lo[x].is_finite() || !hi[x].is_finite()) {
            return None;
        }
        let extent: Vec<f64> = (0..n)
            .map(|x| (hi[x] - lo[x]).max(f64::MIN_POSITIVE))
            .collect();
        // Cell size: the mean box extent, grown if that would make too many cells.
        let mean: f64 = boxes
            .iter()
            .map(|b| (0..n).map(|x| b.hi[x] - b.lo[x]).sum::<f64>())
            .sum::<f64>()
            / (n * boxes.len()) as f64;
        let volume: f64 = extent.iter().product();
        let max_cells = 4 * boxes.len() + 16;
        let mut h = mean.max((volume / max_cells as f64).powf(1.0 / n as f64));
        if !(h.is_finite() && h > 0.0) {
            return None;
        }
        let mut dims = [1usize; 3];
        let mut scale = [0.0; 3];
        loop {
            for x in 0..n {
                dims[x] = ((extent[x] / h).ceil() as usize).clamp(1, max_cells);
                scale[x] = dims[x] as f64 / extent[x];
            }
            if dims[0].saturating_mul(dims[1]).saturating_mul(dims[2]) <= max_cells {
                break;
            }
            h *= 1.25;
        }
        let cells = dims[0] * dims[1] * dims[2];
        let mut grid = Grid {
            n,
            lo,
            scale,
            dims,
            start: vec![0; cells + 1],
            items: Vec::new(),
        };
        let mut total = 0usize;
        for b in boxes {
            let (a, z) = grid.cell_range(b);
            let count = (z[0] - a[0] + 1) * (z[1] - a[1] + 1) * (z[2] - a[2] + 1);
            total += count;
            if total > MAX_ENTRIES_PER_SIMPLEX * boxes.len() {
                return None;
            }
            for k in a[2]..=z[2] {
                for j in a[1]..=z[1] {
                    for i in a[0]..=z[0] {
                        let c = grid.linear([i, j, k]);
                        grid.start[c + 1] += 1;
                    }
                }
            }
        }
        if grid.start.iter().any(|&k| k > MAX_CELL_OCCUPANCY) {
            return None;
        }
        for c in 0..cells {
            grid.start[c + 1] += grid.start[c];
        }
        let mut fill: Vec<u32> = grid.start[..cells].to_vec();
        grid.items = vec![0; total];
        for b in boxes {
            let (a, z) = grid.cell_range(b);
            for k in a[2]..=z[2] {
                for j in a[1]..=z[1] {
                    for i in a[0]..=z[0] {
                        let c = grid.linear([i, j, k]);
                        grid.items[fill[c] as usize] = b.id;
                        fill[c] += 1;
                    }
                }
            }
        }
        Some(grid)
    }
}

/// Grid or tree, chosen at build time.
#[derive(Debug)]
pub(crate) enum SpatialIndex {
    Grid(Grid),
    Tree(RTree<SimplexBox>),
}

impl SpatialIndex {
    pub(crate) fn build(n: usize, boxes: Vec<SimplexBox>) -> SpatialIndex {
        match Grid::build(n, &boxes) {
            Some(g) => SpatialIndex::Grid(g),
            None => SpatialIndex::Tree(RTree::bulk_load(boxes)),
        }
    }

    /// Calls `f` with every simplex whose box may contain `q`; stops when `f` returns `false`.
    #[inline]
    pub(crate) fn candidates(&self, q: &[f64; 3], mut f: impl FnMut(usize) -> bool) {
        match self {
            SpatialIndex::Grid(g) => {
                let mut c = [0; 3];
                let mut on_plane = [false; 3];
                for x in 0..g.n {
                    let t = (q[x] - g.lo[x]) * g.scale[x];
                    // Outside the grid's box (or NaN): no simplex can contain q.
                    if !(t >= 0.0 && t <= g.dims[x] as f64) {
                        return;
                    }
                    c[x] = (t.floor() as usize).min(g.dims[x] - 1);
                    on_plane[x] = t == t.floor() && c[x] > 0 && t < g.dims[x] as f64;
                }
                // Exactly on cell planes, a simplex ending there is listed only in the cell below:
                // visit those cells too (at most 2ⁿ, and only for such exact points).
                let mut planes = [0usize; 3];
                let mut count = 0;
                for (x, _) in on_plane.iter().enumerate().take(g.n).filter(|(_, &p)| p) {
                    planes[count] = x;
                    count += 1;
                }
                for combo in 0u32..(1 << count) {
                    let mut cc = c;
                    for (k, &x) in planes[..count].iter().enumerate() {
                        if combo & (1 << k) != 0 {
                            cc[x] -= 1;
                        }
                    }
                    let cell = g.linear(cc);
                    for &s in &g.items[g.start[cell] as usize..g.start[cell + 1] as usize] {
                        if !f(s as usize) {
                            return;
                        }
                    }
                }
            }
            SpatialIndex::Tree(t) => {
                for b in t.locate_in_envelope_intersecting(AABB::from_point(*q)) {
                    if !f(b.id as usize) {
                        return;
                    }
                }
            }
        }
    }

    /// `"grid"` or `"rtree"` (for diagnostics and benchmarks).
    pub(crate) fn kind(&self) -> &'static str {
        match self {
            SpatialIndex::Grid(_) => "grid",
            SpatialIndex::Tree(_) => "rtree",
        }
    }
}
