//! The extracted shape: a welded triangle mesh (3D models) or polyline (2D models) with per-vertex
//! normals and attributes, and its topology summary.

/// What the cells of a [`Mesh`] are.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Primitive {
    /// Line segments, two vertex ids each (curves of 2D models).
    Segments,
    /// Triangles, three vertex ids each, counter-clockwise seen from outside (surfaces of 3D models).
    Triangles,
}

impl Primitive {
    /// Vertex ids per cell.
    pub fn arity(self) -> usize {
        match self {
            Primitive::Segments => 2,
            Primitive::Triangles => 3,
        }
    }
}

/// A mesh of the shape `O`: welded vertices with outward unit normals, and cells.
///
/// Positions are always 3-vectors; 2D models have `z = 0`. Every per-vertex array has one entry per
/// vertex, every per-cell array one per cell.
#[derive(Clone, Debug, PartialEq)]
pub struct Mesh {
    /// Dimension of the source model (2 or 3).
    pub dimension: usize,
    /// Segments (2D) or triangles (3D).
    pub primitive: Primitive,
    /// Vertex positions.
    pub positions: Vec<[f64; 3]>,
    /// Outward unit normals (`∇F/|∇F|`, pointing to `F > c`).
    pub normals: Vec<[f64; 3]>,
    /// `|∇F|` at each vertex (0 where it was not computed).
    pub gradient_norm: Vec<f64>,
    /// The lowest id of a top simplex the vertex lies in.
    pub vertex_simplex: Vec<u32>,
    /// Cells, flat: [`Primitive::arity`] vertex ids each.
    pub cells: Vec<u32>,
    /// The top simplex each cell comes from.
    pub cell_simplex: Vec<u32>,
}

impl Mesh {
    /// An empty mesh.
    pub fn new(dimension: usize, primitive: Primitive) -> Mesh {
        Mesh {
            dimension,
            primitive,
            positions: Vec::new(),
            normals: Vec::new(),
            gradient_norm: Vec::new(),
            vertex_simplex: Vec::new(),
            cells: Vec::new(),
            cell_simplex: Vec::new(),
        }
    }

    /// Number of vertices.
    pub fn num_vertices(&self) -> usize {
        self.positions.len()
    }

    /// Number of cells (segments or triangles).
    pub fn num_cells(&self) -> usize {
        self.cells.len() / self.primitive.arity()
    }

    /// Iterator over the cells' vertex ids.
    pub fn cell_iter(&self) -> std::slice::ChunksExact<'_, u32> {
        self.cells.chunks_exact(self.primitive.arity())
    }

    /// Axis-aligned bounding box `(min, max)`; `None` for an empty mesh.
    pub fn bounds(&self) -> Option<([f64; 3], [f64; 3])> {
        let first = *self.positions.first()?;
        Some(
            self.positions
                .iter()
                .fold((first, first), |(mut lo, mut hi), p| {
                    for k in 0..3 {
                        lo[k] = lo[k].min(p[k]);
                        hi[k] = hi[k].max(p[k]);
                    }
                    (lo, hi)
                }),
        )
    }

    /// Enclosed volume (3D, by the divergence theorem) or signed area (2D); positive when the
    /// cells are oriented with the outside to the left of `normals`' opposite, i.e. outward.
    ///
    /// Only meaningful for a closed mesh.
    pub fn enclosed_measure(&self) -> f64 {
        match self.primitive {
            Primitive::Triangles => {
                self.cell_iter()
                    .map(|t| {
                        let [a, b, c] = [0, 1, 2].map(|k| self.positions[t[k] as usize]);
                        dot(a, cross(b, c))
                    })
                    .sum::<f64>()
                    / 6.0
            }
            Primitive::Segments => {
                self.cell_iter()
                    .map(|s| {
                        let a = self.positions[s[0] as usize];
                        let b = self.positions[s[1] as usize];
                        a[0] * b[1] - a[1] * b[0]
                    })
                    .sum::<f64>()
                    / 2.0
            }
        }
    }

    /// Counts components, boundary and non-manifold elements, orientation conflicts and
    /// degenerate cells: what the topology guarantee promises.
    pub fn topology(&self) -> Topology {
        let nv = self.num_vertices();
        let mut dsu = DisjointSets::new(nv);
        let mut used = vec![false; nv];
        let mut degenerate = 0usize;
        for c in self.cell_iter() {
            for &v in c {
                used[v as usize] = true;
            }
            for w in c.windows(2) {
                dsu.union(w[0] as usize, w[1] as usize);
            }
            if self.is_degenerate(c) {
                degenerate += 1;
            }
        }
        let vertices = used.iter().filter(|&&u| u).count();
        // Only the vertices of one cell are ever joined, so a set holding a used vertex holds
        // only used ones, its root among them: the components are the used vertices that are
        // their own root. Counted in place of sorting every used vertex's root and removing the
        // repeats: the same count, 3 % of this function's instructions on the sphere example.
        let components = (0..nv).filter(|&v| used[v] && dsu.is_root(v)).count();
        match self.primitive {
            Primitive::Segments => {
                // A closed curve has every vertex in exactly one outgoing and one incoming segment.
                let mut out_deg = vec![0u32; nv];
                let mut in_deg = vec![0u32; nv];
                for s in self.cell_iter() {
                    out_deg[s[0] as usize] += 1;
                    in_deg[s[1] as usize] += 1;
                }
                let boundary = (0..nv)
                    .filter(|&v| used[v] && out_deg[v] + in_deg[v] == 1)
                    .count();
                let non_manifold = (0..nv).filter(|&v| out_deg[v] + in_deg[v] > 2).count();
                let orientation_conflicts = (0..nv)
                    .filter(|&v| used[v] && out_deg[v] + in_deg[v] == 2 && out_deg[v] != 1)
                    .count();
                Topology {
                    components,
                    euler_characteristic: vertices as i64 - self.num_cells() as i64,
                    vertices,
                    edges: self.num_cells(),
                    faces: 0,
                    boundary_edges: boundary,
                    non_manifold_edges: non_manifold,
                    orientation_conflicts,
                    degenerate_cells: degenerate,
                }
            }
            Primitive::Triangles => {
                // Every directed edge grouped by its undirected key: an undirected edge of a closed
                // oriented manifold appears once in each direction. The groups come from a
                // counting sort on the smaller vertex id (linear; each vertex's bucket holds its
                // few edges to larger ids, sorted in place) — hash maps cost as much as a fifth of
                // a whole export, a full sort of the 3 · faces keys still ~5 %.
                let mut start = vec![0usize; nv + 1];
                for t in self.cell_iter() {
                    for k in 0..3 {
                        start[t[k].min(t[(k + 1) % 3]) as usize + 1] += 1;
                    }
                }
                for v in 0..nv {
                    start[v + 1] += start[v];
                }
                // Per directed edge: the larger id and the direction (`a < b`) in one word.
                let mut next = start.clone();
                let mut other = vec![0u64; 3 * self.num_cells()];
                for t in self.cell_iter() {
                    for k in 0..3 {
                        let (a, b) = (t[k], t[(k + 1) % 3]);
                        let slot = &mut next[a.min(b) as usize];
                        other[*slot] = (u64::from(a.max(b)) << 1) | u64::from(a < b);
                        *slot += 1;
                    }
                }
                let mut boundary = 0;
                let mut non_manifold = 0;
                let mut conflicts = 0;
                let mut edges = 0;
                for v in 0..nv {
                    let bucket = &mut other[start[v]..start[v + 1]];
                    bucket.sort_unstable();
                    for run in bucket.chunk_by(|x, y| x >> 1 == y >> 1) {
                        edges += 1;
                        let fwd = run.iter().filter(|&&e| e & 1 == 1).count();
                        let bwd = run.len() - fwd;
                        match fwd + bwd {
                            1 => boundary += 1,
                            2 if fwd != 1 => conflicts += 1,
                            2 => {}
                            _ => non_manifold += 1,
                        }
                    }
                }
                let faces = self.num_cells();
                Topology {
                    components,
                    euler_characteristic: vertices as i64 - edges as i64 + faces as i64,
                    vertices,
                    edges,
                    faces,
                    boundary_edges: boundary,
                    non_manifold_edges: non_manifold,
                    orientation_conflicts: conflicts,
                    degenerate_cells: degenerate,
                }
            }
        }
    }

    /// A cell is degenerate when two of its vertex ids coincide or its positions span no area
    /// (triangles) or length (segments), relative to its size.
    fn is_degenerate(&self, cell: &[u32]) -> bool {
        let p = |k: usize| self.positions[cell[k] as usize];
        match self.primitive {
            Primitive::Segments => cell[0] == cell[1] || p(0) == p(1),
            Primitive::Triangles => {
                if cell[0] == cell[1] || cell[1] == cell[2] || cell[0] == cell[2] {
                    return true;
                }
                let (a, b, c) = (p(0), p(1), p(2));
                let e1 = sub(b, a);
                let e2 = sub(c, a);
                let area2 = norm(cross(e1, e2));
                let scale = dot(e1, e1).max(dot(e2, e2)).max(dot(sub(c, b), sub(c, b)));
                // Twice the area against the longest edge squared: below this the triangle's
                // normal is dominated by f64 rounding of its coordinates.
                area2 <= DEGENERATE_RELATIVE_AREA * scale
            }
        }
    }
}

/// A triangle whose doubled area is below this fraction of its longest edge squared counts as
/// degenerate: at ~1e-12 its normal direction carries no correct digits after f32 export.
pub const DEGENERATE_RELATIVE_AREA: f64 = 1e-12;

/// Topological summary of a [`Mesh`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Topology {
    /// Connected components (of the used vertices).
    pub components: usize,
    /// `V − E + F` (triangles) or `V − E` (segments).
    pub euler_characteristic: i64,
    /// Vertices used by some cell.
    pub vertices: usize,
    /// Distinct undirected edges (triangles) or segments.
    pub edges: usize,
    /// Triangles (0 for segments).
    pub faces: usize,
    /// Edges in one triangle only (segments: vertices in one segment only).
    pub boundary_edges: usize,
    /// Edges in more than two triangles (segments: vertices in more than two segments).
    pub non_manifold_edges: usize,
    /// Manifold edges traversed in the same direction by both triangles (segments: vertices with
    /// two incoming or two outgoing segments).
    pub orientation_conflicts: usize,
    /// Cells with repeated vertices or no area.
    pub degenerate_cells: usize,
}

impl Topology {
    /// Closed, oriented, manifold and without degenerate cells.
    pub fn is_closed_oriented_manifold(&self) -> bool {
        self.boundary_edges == 0
            && self.non_manifold_edges == 0
            && self.orientation_conflicts == 0
            && self.degenerate_cells == 0
    }
}

/// Union–find over vertex ids, for counting components. Hand-written: twenty lines, not worth a
/// dependency.
struct DisjointSets {
    parent: Vec<usize>,
}

impl DisjointSets {
    fn new(n: usize) -> DisjointSets {
        DisjointSets {
            parent: (0..n).collect(),
        }
    }

    fn find(&mut self, mut v: usize) -> usize {
        while self.parent[v] != v {
            self.parent[v] = self.parent[self.parent[v]];
            v = self.parent[v];
        }
        v
    }

    /// Whether `v` is its set's representative.
    fn is_root(&self, v: usize) -> bool {
        self.parent[v] == v
    }

    fn union(&mut self, a: usize, b: usize) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            self.parent[ra.max(rb)] = ra.min(rb);
        }
    }
}

pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

pub(crate) fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A regular tetrahedron's surface, outward: the smallest closed oriented mesh.
    pub(crate) fn tetrahedron_surface() -> Mesh {
        let mut m = Mesh::new(3, Primitive::Triangles);
        m.positions = vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ];
        m.normals = vec![[0.0, 0.0, 1.0]; 4];
        m.gradient_norm = vec![1.0; 4];
        m.vertex_simplex = vec![0; 4];
        m.cells = vec![0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3];
        m.cell_simplex = vec![0; 4];
        m
    }

    #[test]
    fn closed_tetrahedron_has_euler_two_and_positive_volume() {
        let m = tetrahedron_surface();
        let t = m.topology();
        assert_eq!(
            (
                t.components,
                t.euler_characteristic,
                t.vertices,
                t.edges,
                t.faces
            ),
            (1, 2, 4, 6, 4)
        );
        assert!(t.is_closed_oriented_manifold(), "{t:?}");
        assert!((m.enclosed_measure() - 1.0 / 6.0).abs() < 1e-15);
    }

    #[test]
    fn flipped_triangle_and_open_surface_are_detected() {
        let mut m = tetrahedron_surface();
        m.cells.swap(0, 1);
        assert_eq!(m.topology().orientation_conflicts, 3);
        m.cells.truncate(9);
        m.cell_simplex.truncate(3);
        let t = m.topology();
        assert_eq!(t.boundary_edges, 3);
        assert!(!t.is_closed_oriented_manifold());
    }

    /// Three triangles on one edge (a "book" of three pages), and an isolated triangle: counted by
    /// hand, one non-manifold edge, six boundary edges on the pages and three on the lone one,
    /// two components.
    #[test]
    fn book_of_three_pages_has_one_non_manifold_edge() {
        let mut m = Mesh::new(3, Primitive::Triangles);
        m.positions = vec![
            [0.0, 0.0, 0.0],
            [0.0, 0.0, 1.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [-1.0, -1.0, 0.0],
            [5.0, 0.0, 0.0],
            [6.0, 0.0, 0.0],
            [5.0, 1.0, 0.0],
        ];
        m.cells = vec![0, 1, 2, 1, 0, 3, 0, 1, 4, 5, 6, 7];
        let t = m.topology();
        assert_eq!(
            (
                t.components,
                t.edges,
                t.boundary_edges,
                t.non_manifold_edges,
                t.orientation_conflicts
            ),
            (2, 10, 9, 1, 0)
        );
        assert_eq!(t.euler_characteristic, 8 - 10 + 4);
    }

    /// Components are counted over the vertices the cells use: `k` disjoint tetrahedron
    /// surfaces, with unused vertices before, between and after them, are `k` components of
    /// `4k` vertices, Euler characteristic `2k` (each surface a sphere).
    #[test]
    fn disjoint_surfaces_with_unused_vertices_are_counted_once_each() {
        let tet = tetrahedron_surface();
        for k in 1..=5 {
            let mut m = Mesh::new(3, Primitive::Triangles);
            // One unused vertex first, then each surface's four followed by two unused ones.
            m.positions.push([9.0, 9.0, 9.0]);
            for copy in 0..k {
                let base = m.positions.len() as u32;
                let shift = 3.0 * copy as f64;
                m.positions
                    .extend(tet.positions.iter().map(|p| [p[0] + shift, p[1], p[2]]));
                m.positions.extend([[-1.0, -1.0, -1.0]; 2]);
                m.cells.extend(tet.cells.iter().map(|&v| base + v));
            }
            let t = m.topology();
            assert_eq!(
                (t.components, t.vertices, t.euler_characteristic),
                (k, 4 * k, 2 * k as i64),
                "{k} surfaces"
            );
            assert!(t.is_closed_oriented_manifold(), "{t:?}");
        }
    }

    #[test]
    fn square_polyline_is_closed_with_positive_area() {
        let mut m = Mesh::new(2, Primitive::Segments);
        m.positions = vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 1.0, 0.0],
            [0.0, 1.0, 0.0],
        ];
        m.cells = vec![0, 1, 1, 2, 2, 3, 3, 0];
        let t = m.topology();
        assert_eq!((t.components, t.euler_characteristic), (1, 0));
        assert!(t.is_closed_oriented_manifold());
        assert_eq!(m.enclosed_measure(), 1.0);
    }
}
