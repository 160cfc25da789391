//! Meshes in: a closed triangle mesh (OBJ or glTF/GLB) as an [`ImplicitFunction`].
//!
//! `g(p)` is the signed distance from `p` to the triangle soup: the distance comes from the
//! closest triangle (an `rstar` R-tree over triangle boxes, exact point–triangle distance in the
//! leaves), and the sign from the **generalized winding number** `w(p)` (Jacobson, Kavan and
//! Sorkine-Hornung 2013): `w = Σ Ω_t(p) / 4π` over the triangles' signed solid angles, inside
//! (`g < 0`) where `w > ½`. On a closed, consistently oriented manifold mesh the side of most
//! queries is read off the closest point instead, by the angle-weighted pseudonormal there
//! (Bærentzen and Aanæs 2005; same answer, a dot product instead of a sum of solid angles); the
//! winding number decides the rest (points within rounding of the surface or of the
//! pseudonormal's perpendicular) and every open or non-manifold mesh.
//!
//! `w` is evaluated hierarchically and exactly (the paper's §3.3, not the approximate dipole
//! expansion): for every node of the R-tree we store the boundary chain `∂P` of its patch `P`
//! (the directed edges whose reverse is not in the patch) and close it with a fan from one of its
//! vertices `o`. `P` and the reversed fan form a closed surface inside the node's box, whose winding
//! number is 0 at every point outside that box, so there `w_P(p) = Σ_{(a,b) ∈ ∂P} Ω(o, a, b)/4π`:
//! a sum over the boundary (about √|P| edges for a compact patch) instead of over `P`. Nodes whose
//! box contains `p` are opened. Queries are independent and run in parallel in the fitter.
//!
//! Why not the O(n) sum per query that is parallel over queries: the fitter asks for `g` millions of
//! times (Levenberg–Marquardt samples per face), and a mesh of 10⁴–10⁵ triangles would make each
//! call cost 10⁴–10⁵ solid angles. The hierarchical sum touches the boundaries of the O(log n) nodes
//! around the query. The brute-force sum stays as [`MeshDistance::winding_number_brute_force`] for
//! the tests.
//!
//! The gradient is `sign · (p − q)/|p − q|` with `q` the closest point (the outward face normal on
//! the surface itself). [`MeshDistance::enclose`] gives the Lipschitz value bound and a conservative
//! gradient enclosure from the normals of the triangles that can hold a closest point (see there).
//!
//! ```
//! use ism_fit::mesh::{MeshDistance, TriangleMesh};
//! use ism_fit::ImplicitFunction;
//!
//! let tet = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n";
//! let mesh = TriangleMesh::from_obj(tet.as_bytes(), std::path::Path::new("tet.obj"))?;
//! let g = MeshDistance::new(mesh)?;
//! let check = g.check();
//! assert!(check.is_closed_manifold() && check.euler == 2);
//! assert!((g.winding_number([0.1, 0.1, 0.1]) - 1.0).abs() < 1e-12);
//! assert!(g.winding_number([1.0, 1.0, 1.0]).abs() < 1e-12);
//! assert!((g.value(&[0.1, 0.1, 0.1]) + 0.1).abs() < 1e-12); // 0.1 below the face z = 0
//! assert!(g.value(&[0.0, 0.0, -0.5]) == 0.5);
//! # Ok::<(), ism_fit::FitError>(())
//! ```
//!
//! The module along its seams: this file holds the mesh itself ([`TriangleMesh`]: geometry,
//! orientation, the combinatorial [`MeshCheck`]); [`load`] reads files (the OBJ and glTF parsers
//! are `ism_export::obj::read_obj` and `ism_export::gltf::read_gltf`, beside their writers; here
//! the file's size is bounded and identical positions are welded); [`winding`] is the hierarchical
//! generalized winding number; [`distance`] the signed distance [`MeshDistance`] (R-tree, closest
//! points, pseudonormals, enclosures for the fitter); [`plan`] the fitting policy for a mesh
//! ([`MeshDistance::plan`]: refusal, domain, topology phase, expected topology), which `ism fit
//! --mesh` and the Python package render.

use std::collections::HashMap;

pub mod distance;
pub mod load;
pub mod plan;
mod winding;

pub use distance::{MeshDistance, PV_SHARPEST_EDGE};
pub use plan::{MeshPlan, MeshPlanError};

/// Why a mesh cannot be a target: the cause of [`FitError::Mesh`](crate::FitError::Mesh), which
/// adds the file.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum MeshError {
    /// The file could not be opened or read.
    #[error("cannot read the file")]
    Io(#[source] std::io::Error),
    /// The file is larger than `Limits::max_payload_bytes` (checked before it is read).
    #[error("the file has {bytes} bytes, above the limit of {limit} (max_payload_bytes)")]
    FileTooLarge {
        /// The file's size.
        bytes: u64,
        /// The limit it passes.
        limit: u64,
    },
    /// The extension names no mesh format this crate reads.
    #[error("unknown mesh format `{extension}` (expected .obj, .glb or .gltf)")]
    UnknownFormat {
        /// The file's extension, lowercased (empty when it has none).
        extension: String,
    },
    /// The OBJ or glTF reader refused the content; its error says where in the file.
    #[error(transparent)]
    Read(#[from] ism_export::error::MeshReadError),
    /// The file parsed but holds no triangle.
    #[error("no triangles")]
    NoTriangles,
    /// A vertex a triangle uses has a NaN or infinite coordinate.
    #[error("vertex {vertex} has a non-finite coordinate {point:?}")]
    NonFinite {
        /// The vertex, as numbered by the reader (before welding).
        vertex: u32,
        /// Its coordinates.
        point: P3,
    },
    /// Every triangle has zero area, so no distance or orientation can be defined.
    #[error("every triangle has zero area")]
    AllDegenerate,
}

type P3 = [f64; 3];

fn sub(a: P3, b: P3) -> P3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: P3, b: P3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: P3, b: P3) -> P3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn norm(a: P3) -> f64 {
    dot(a, a).sqrt()
}
fn axpy(a: P3, s: f64, d: P3) -> P3 {
    [a[0] + s * d[0], a[1] + s * d[1], a[2] + s * d[2]]
}

/// A triangle mesh: positions and vertex-id triples (counter-clockwise seen from outside).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriangleMesh {
    /// Vertex positions.
    pub positions: Vec<P3>,
    /// Triangles as vertex ids.
    pub triangles: Vec<[u32; 3]>,
}

/// Combinatorial checks of a mesh (after welding identical positions).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MeshCheck {
    /// Vertices used by some triangle.
    pub vertices: usize,
    /// Triangles.
    pub triangles: usize,
    /// Undirected edges.
    pub edges: usize,
    /// Edges with one triangle (the mesh is open there).
    pub boundary_edges: usize,
    /// Edges with more than two triangles.
    pub nonmanifold_edges: usize,
    /// Edges whose two triangles run through them in the same direction (inconsistent orientation).
    pub misoriented_edges: usize,
    /// Triangles of zero area (they have no normal and no solid angle).
    pub degenerate_triangles: usize,
    /// Connected components (triangles sharing a vertex).
    pub components: usize,
    /// Euler characteristic `V − E + F`.
    pub euler: i64,
}

impl MeshCheck {
    /// Closed, edge-manifold and consistently oriented: the mesh bounds a solid, and its
    /// components and Euler characteristic are the topology a fit must reproduce.
    pub fn is_closed_manifold(&self) -> bool {
        self.boundary_edges == 0 && self.nonmanifold_edges == 0 && self.misoriented_edges == 0
    }
}

impl TriangleMesh {
    /// A torus around the z axis (radii `big` and `small`) of `n × m` quads split in two,
    /// triangles facing outward: a closed, consistently oriented test shape with saddle vertices
    /// and concave edges on its inner side (for fits, benchmarks and tests, as
    /// [`TriangleMesh::icosphere`]).
    pub fn torus(n: u32, m: u32, big: f64, small: f64) -> TriangleMesh {
        let tau = std::f64::consts::TAU;
        let mut positions = Vec::new();
        for i in 0..n {
            for j in 0..m {
                let (u, v) = (tau * i as f64 / n as f64, tau * j as f64 / m as f64);
                let r = big + small * v.cos();
                positions.push([r * u.cos(), r * u.sin(), small * v.sin()]);
            }
        }
        let id = |i: u32, j: u32| (i % n) * m + (j % m);
        let mut triangles = Vec::new();
        for i in 0..n {
            for j in 0..m {
                let q = [id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1)];
                triangles.push([q[0], q[1], q[2]]);
                triangles.push([q[0], q[2], q[3]]);
            }
        }
        TriangleMesh {
            positions,
            triangles,
        }
    }

    /// An icosphere: the icosahedron subdivided `level` times (`20·4^level` triangles), its
    /// vertices on the sphere of `radius` around `centre`, triangles facing outward. A closed,
    /// consistently oriented test shape for fits, benchmarks and the CLI's tests.
    pub fn icosphere(level: usize, radius: f64, centre: P3) -> TriangleMesh {
        let t = (1.0 + 5f64.sqrt()) / 2.0;
        let mut positions: Vec<P3> = [
            [-1.0, t, 0.0],
            [1.0, t, 0.0],
            [-1.0, -t, 0.0],
            [1.0, -t, 0.0],
            [0.0, -1.0, t],
            [0.0, 1.0, t],
            [0.0, -1.0, -t],
            [0.0, 1.0, -t],
            [t, 0.0, -1.0],
            [t, 0.0, 1.0],
            [-t, 0.0, -1.0],
            [-t, 0.0, 1.0],
        ]
        .iter()
        .map(|p| p.map(|x| x / norm(*p)))
        .collect();
        let mut triangles: Vec<[u32; 3]> = vec![
            [0, 11, 5],
            [0, 5, 1],
            [0, 1, 7],
            [0, 7, 10],
            [0, 10, 11],
            [1, 5, 9],
            [5, 11, 4],
            [11, 10, 2],
            [10, 7, 6],
            [7, 1, 8],
            [3, 9, 4],
            [3, 4, 2],
            [3, 2, 6],
            [3, 6, 8],
            [3, 8, 9],
            [4, 9, 5],
            [2, 4, 11],
            [6, 2, 10],
            [8, 6, 7],
            [9, 8, 1],
        ];
        for _ in 0..level {
            let mut mid: HashMap<(u32, u32), u32> = HashMap::new();
            let mut next = Vec::new();
            for t in &triangles {
                let m = [0, 1, 2].map(|k| {
                    let (a, b) = (t[k], t[(k + 1) % 3]);
                    *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                        let p = positions[a as usize];
                        let q = positions[b as usize];
                        let s = [p[0] + q[0], p[1] + q[1], p[2] + q[2]];
                        positions.push(s.map(|x| x / norm(s)));
                        (positions.len() - 1) as u32
                    })
                });
                next.extend([
                    [t[0], m[0], m[2]],
                    [t[1], m[1], m[0]],
                    [t[2], m[2], m[1]],
                    [m[0], m[1], m[2]],
                ]);
            }
            triangles = next;
        }
        for p in &mut positions {
            *p = [0, 1, 2].map(|k| centre[k] + radius * p[k]);
        }
        TriangleMesh {
            positions,
            triangles,
        }
    }

    /// Axis-aligned bounding box of the vertices.
    pub fn bounding_box(&self) -> (P3, P3) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in &self.positions {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        (lo, hi)
    }

    /// Length of the bounding box's diagonal.
    pub fn diagonal(&self) -> f64 {
        let (lo, hi) = self.bounding_box();
        norm(sub(hi, lo))
    }

    /// Median length of the triangles' edges (each edge counted once per triangle side); 0 for
    /// an empty mesh. The median, not the minimum, so a few slivers do not decide it.
    pub fn median_edge_length(&self) -> f64 {
        let mut lengths: Vec<f64> = self
            .triangles
            .iter()
            .flat_map(|t| (0..3).map(move |k| (t[k], t[(k + 1) % 3])))
            .filter_map(|(a, b)| {
                let (pa, pb) = (
                    self.positions.get(a as usize)?,
                    self.positions.get(b as usize)?,
                );
                Some(norm(sub(*pa, *pb)))
            })
            .filter(|l| l.is_finite())
            .collect();
        if lengths.is_empty() {
            return 0.0;
        }
        let mid = lengths.len() / 2;
        *lengths.select_nth_unstable_by(mid, f64::total_cmp).1
    }

    /// The fitting domain: the bounding box padded by `margin × diagonal` on every side
    /// (`x0,x1,y0,y1,z0,z1`).
    pub fn domain(&self, margin: f64) -> Vec<f64> {
        let (lo, hi) = self.bounding_box();
        let pad = margin * norm(sub(hi, lo));
        (0..3).flat_map(|k| [lo[k] - pad, hi[k] + pad]).collect()
    }

    /// Enclosed volume (signed: negative when the triangles face inward).
    pub fn signed_volume(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|v| self.positions[v as usize]);
                dot(a, cross(b, c)) / 6.0
            })
            .sum()
    }

    /// Flips every triangle if the signed volume is negative (a mesh exported inside out), so the
    /// winding number is +1 inside. Returns whether it flipped.
    pub fn orient_outward(&mut self) -> bool {
        let flip = self.signed_volume() < 0.0;
        if flip {
            for t in &mut self.triangles {
                t.swap(1, 2);
            }
        }
        flip
    }

    /// Edge counts, orientation, components and Euler characteristic.
    pub fn check(&self) -> MeshCheck {
        // Per undirected edge (lo, hi): triangles running lo→hi and hi→lo.
        let mut edges: HashMap<(u32, u32), (u32, u32)> = HashMap::new();
        let mut degenerate = 0;
        let mut parent: Vec<u32> = (0..self.positions.len() as u32).collect();
        fn find(p: &mut [u32], x: u32) -> u32 {
            let mut r = x;
            while p[r as usize] != r {
                r = p[r as usize];
            }
            let mut y = x;
            while p[y as usize] != r {
                let next = p[y as usize];
                p[y as usize] = r;
                y = next;
            }
            r
        }
        let mut used = vec![false; self.positions.len()];
        for t in &self.triangles {
            let [a, b, c] = t.map(|v| self.positions[v as usize]);
            if cross(sub(b, a), sub(c, a)) == [0.0; 3] {
                degenerate += 1;
            }
            for k in 0..3 {
                let (u, v) = (t[k], t[(k + 1) % 3]);
                used[u as usize] = true;
                let e = edges.entry((u.min(v), u.max(v))).or_default();
                if u < v {
                    e.0 += 1;
                } else {
                    e.1 += 1;
                }
                let (ru, rv) = (find(&mut parent, u), find(&mut parent, v));
                parent[ru as usize] = rv;
            }
        }
        let (mut boundary, mut nonmanifold, mut misoriented) = (0, 0, 0);
        for &(f, b) in edges.values() {
            match f + b {
                1 => boundary += 1,
                2 if f != 1 => misoriented += 1,
                2 => {}
                _ => nonmanifold += 1,
            }
        }
        let vertices = used.iter().filter(|&&u| u).count();
        let components = (0..self.positions.len() as u32)
            .filter(|&v| used[v as usize] && find(&mut parent, v) == v)
            .count();
        MeshCheck {
            vertices,
            triangles: self.triangles.len(),
            edges: edges.len(),
            boundary_edges: boundary,
            nonmanifold_edges: nonmanifold,
            misoriented_edges: misoriented,
            degenerate_triangles: degenerate,
            components,
            euler: vertices as i64 - edges.len() as i64 + self.triangles.len() as i64,
        }
    }
}
