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

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use rstar::{PointDistance, RTree, RTreeNode, RTreeObject, AABB};

use crate::expr::{Enclosure, ImplicitFunction};
use crate::interval::Interval;
use crate::FitError;
use ism_format::io::Limits;

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

fn mesh_error(path: &Path, message: impl Into<String>) -> FitError {
    FitError::Mesh {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

impl TriangleMesh {
    /// Reads `path` by its extension: `.obj` (tobj), `.glb` or `.gltf` (gltf), with the default
    /// [`Limits`] (which refuse nothing a mesh with `u32` vertex ids can hold).
    ///
    /// # Errors
    /// [`FitError::Mesh`] with the path when the file is unreadable, malformed, has another
    /// extension, or holds no triangle.
    pub fn load(path: &Path) -> Result<TriangleMesh, FitError> {
        TriangleMesh::load_with_limits(path, &Limits::default())
    }

    /// [`TriangleMesh::load`] within `limits`: the file's size against `max_payload_bytes` before
    /// it is read, then the vertices and triangles against `max_vertices` and `max_simplices`
    /// before the mesh is built (a service fitting meshes from anyone lowers them, as for
    /// `ism_export::import`).
    ///
    /// # Errors
    /// As [`TriangleMesh::load`], and [`FitError::Mesh`] naming the limit passed.
    pub fn load_with_limits(path: &Path, limits: &Limits) -> Result<TriangleMesh, FitError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .unwrap_or_default();
        let size = std::fs::metadata(path)
            .map_err(|e| mesh_error(path, e.to_string()))?
            .len();
        if size > limits.max_payload_bytes {
            return Err(mesh_error(
                path,
                format!(
                    "the file has {size} bytes, above the limit of {} (max_payload_bytes)",
                    limits.max_payload_bytes
                ),
            ));
        }
        let bytes = std::fs::read(path).map_err(|e| mesh_error(path, e.to_string()))?;
        match ext.as_str() {
            "obj" => TriangleMesh::from_obj_with_limits(&bytes, path, limits),
            "glb" | "gltf" => TriangleMesh::from_gltf_with_limits(&bytes, path, limits),
            _ => Err(mesh_error(
                path,
                "unknown mesh format (expected .obj, .glb or .gltf)",
            )),
        }
    }

    /// Parses Wavefront OBJ text (polygons are triangulated, materials ignored); `path` names the
    /// source in errors.
    ///
    /// # Errors
    /// [`FitError::Mesh`] on a parse error, an index out of range or no triangle.
    pub fn from_obj(bytes: &[u8], path: &Path) -> Result<TriangleMesh, FitError> {
        TriangleMesh::from_obj_with_limits(bytes, path, &Limits::default())
    }

    /// [`TriangleMesh::from_obj`] within `limits` (`max_vertices`, `max_simplices`; the text's
    /// size is the caller's to bound).
    ///
    /// # Errors
    /// As [`TriangleMesh::from_obj`], and [`FitError::Mesh`] naming the limit passed.
    pub fn from_obj_with_limits(
        bytes: &[u8],
        path: &Path,
        limits: &Limits,
    ) -> Result<TriangleMesh, FitError> {
        let options = tobj::LoadOptions {
            triangulate: true,
            ..Default::default()
        };
        // Materials are irrelevant to the shape: the loader is told none exist.
        let (models, _) = tobj::load_obj_buf(&mut std::io::Cursor::new(bytes), &options, |_| {
            Err(tobj::LoadError::OpenFileFailed)
        })
        .map_err(|e| mesh_error(path, format!("OBJ: {e}")))?;
        let vertices: usize = models.iter().map(|m| m.mesh.positions.len() / 3).sum();
        let triangles: usize = models.iter().map(|m| m.mesh.indices.len() / 3).sum();
        within_limits(vertices, triangles, limits, path)?;
        let mut positions = Vec::new();
        let mut triangles = Vec::new();
        for model in &models {
            let m = &model.mesh;
            let base = positions.len();
            let count = m.positions.len() / 3;
            positions.extend(
                m.positions
                    .chunks_exact(3)
                    .map(|c| [f64::from(c[0]), f64::from(c[1]), f64::from(c[2])]),
            );
            for (t, tri) in m.indices.chunks_exact(3).enumerate() {
                if tri.iter().any(|&i| i as usize >= count) {
                    return Err(mesh_error(
                        path,
                        format!(
                            "OBJ object `{}`, triangle {t}: vertex index out of range (has {count} vertices)",
                            model.name
                        ),
                    ));
                }
                triangles.push([0, 1, 2].map(|k| (base + tri[k] as usize) as u32));
            }
        }
        TriangleMesh::welded(positions, triangles, path)
    }

    /// Parses glTF JSON or binary GLB: every triangle primitive (triangles, strips, fans) of every
    /// mesh instanced by the nodes of the default scene (all scenes if none is marked default;
    /// every mesh untransformed if there is no scene), with the nodes' transforms applied. Buffers
    /// referenced by relative URIs are read next to `path`.
    ///
    /// # Errors
    /// [`FitError::Mesh`] on a parse or validation error, a missing buffer, an index out of range
    /// or no triangle.
    pub fn from_gltf(bytes: &[u8], path: &Path) -> Result<TriangleMesh, FitError> {
        TriangleMesh::from_gltf_with_limits(bytes, path, &Limits::default())
    }

    /// [`TriangleMesh::from_gltf`] within `limits`: the buffers' declared lengths together
    /// against `max_payload_bytes` before any is read, the vertices and triangles gathered so far
    /// against `max_vertices` and `max_simplices` before each primitive is added.
    ///
    /// # Errors
    /// As [`TriangleMesh::from_gltf`], and [`FitError::Mesh`] naming the limit passed.
    pub fn from_gltf_with_limits(
        bytes: &[u8],
        path: &Path,
        limits: &Limits,
    ) -> Result<TriangleMesh, FitError> {
        let raw = gltf::Gltf::from_slice_without_validation(bytes)
            .map_err(|e| mesh_error(path, format!("glTF: {e}")))?;
        // gltf-json 1.4.1's validation indexes `accessors[POSITION]` without a bounds check
        // (src/mesh.rs:151) and panics on a bad index; check those indices before validating.
        let json = raw.document.as_json();
        for (mi, mesh) in json.meshes.iter().enumerate() {
            for (pi, p) in mesh.primitives.iter().enumerate() {
                let bad = p
                    .attributes
                    .values()
                    .chain(p.indices.as_ref())
                    .find(|a| a.value() >= json.accessors.len());
                if let Some(a) = bad {
                    return Err(mesh_error(
                        path,
                        format!(
                            "glTF mesh {mi}, primitive {pi}: accessor {} does not exist",
                            a.value()
                        ),
                    ));
                }
            }
        }
        let document = gltf::Document::from_json(raw.document.into_json())
            .map_err(|e| mesh_error(path, format!("glTF: {e}")))?;
        // gltf 1.4.1's `import_buffers` unwraps the percent-decoding of a relative buffer URI
        // (src/import.rs:50) and panics when the result is not UTF-8: refuse such a URI first, with
        // the same decoder (found by the `fit_mesh` fuzz target).
        for buffer in document.buffers() {
            if let gltf::buffer::Source::Uri(uri) = buffer.source() {
                if !uri.contains(':') && urlencoding::decode(uri).is_err() {
                    return Err(mesh_error(
                        path,
                        format!(
                            "glTF buffer {}: URI is not UTF-8 after percent-decoding",
                            buffer.index()
                        ),
                    ));
                }
            }
        }
        // Saturating: hostile lengths near u64::MAX must not overflow the sum (a panic in debug
        // builds, a wrapped sum that passes the check in release).
        let declared = document
            .buffers()
            .fold(0u64, |sum, b| sum.saturating_add(b.length() as u64));
        if declared > limits.max_payload_bytes {
            return Err(mesh_error(
                path,
                format!(
                    "the glTF buffers declare {declared} bytes, above the limit of {} \
                     (max_payload_bytes)",
                    limits.max_payload_bytes
                ),
            ));
        }
        let buffers = gltf::import_buffers(&document, path.parent(), raw.blob)
            .map_err(|e| mesh_error(path, format!("glTF buffers: {e}")))?;
        let mut out = (Vec::new(), Vec::new());
        let doc = &document;
        let scenes: Vec<gltf::Scene> = match doc.default_scene() {
            Some(s) => vec![s],
            None => doc.scenes().collect(),
        };
        if scenes.is_empty() {
            for mesh in doc.meshes() {
                add_gltf_mesh(&mesh, &IDENTITY, &buffers, path, limits, &mut out)?;
            }
        }
        // glTF 2.0: the node hierarchy is a set of disjoint strict trees, so a node is reached
        // once per scene. A file that reaches one twice (two parents, or the same child listed
        // twice) would instance its subtree 2^depth times from a few bytes: refused. Scenes may
        // share nodes; a node already loaded by an earlier scene is not loaded again (the shape
        // would hold the same triangles twice).
        let mut loaded_by: Vec<Option<usize>> = vec![None; doc.nodes().len()];
        for (si, scene) in scenes.into_iter().enumerate() {
            // Explicit stack instead of recursion: a deep node chain in a hostile file cannot
            // overflow it. glTF validation forbids cycles, and the depth cap is a second guard.
            let mut stack: Vec<(gltf::Node, [[f64; 4]; 4], usize)> =
                scene.nodes().map(|n| (n, IDENTITY, 0)).collect();
            while let Some((node, parent, depth)) = stack.pop() {
                if depth > MAX_NODE_DEPTH {
                    return Err(mesh_error(
                        path,
                        format!("glTF node hierarchy deeper than {MAX_NODE_DEPTH}"),
                    ));
                }
                match loaded_by[node.index()] {
                    Some(s) if s == si => {
                        return Err(mesh_error(
                            path,
                            format!(
                                "glTF node {} is reached twice in scene {si}; nodes form \
                                 disjoint trees (glTF 2.0), each with at most one parent",
                                node.index()
                            ),
                        ));
                    }
                    Some(_) => continue,
                    None => loaded_by[node.index()] = Some(si),
                }
                let local = node.transform().matrix().map(|c| c.map(f64::from));
                let world = mat_mul(&parent, &local);
                if let Some(mesh) = node.mesh() {
                    add_gltf_mesh(&mesh, &world, &buffers, path, limits, &mut out)?;
                }
                stack.extend(node.children().map(|c| (c, world, depth + 1)));
            }
        }
        TriangleMesh::welded(out.0, out.1, path)
    }

    /// Merges vertices with bit-identical positions (exporters split vertices per normal or
    /// texture coordinate; the shape's edges only connect after welding), drops unused vertices,
    /// and rejects non-finite coordinates and empty meshes.
    fn welded(
        positions: Vec<P3>,
        triangles: Vec<[u32; 3]>,
        path: &Path,
    ) -> Result<TriangleMesh, FitError> {
        if triangles.is_empty() {
            return Err(mesh_error(path, "no triangles"));
        }
        let mut ids: HashMap<[u64; 3], u32> = HashMap::new();
        let mut remap: Vec<Option<u32>> = vec![None; positions.len()];
        let mut welded = Vec::new();
        let mut tris = Vec::with_capacity(triangles.len());
        for tri in &triangles {
            let mut t = [0u32; 3];
            for (k, &v) in tri.iter().enumerate() {
                let id = match remap[v as usize] {
                    Some(id) => id,
                    None => {
                        let p = positions[v as usize];
                        if p.iter().any(|x| !x.is_finite()) {
                            return Err(mesh_error(
                                path,
                                format!("vertex {v} has a non-finite coordinate {p:?}"),
                            ));
                        }
                        // +0.0 for -0.0, so both weld.
                        let key = p.map(|x| (x + 0.0).to_bits());
                        let id = *ids.entry(key).or_insert_with(|| {
                            welded.push(p);
                            (welded.len() - 1) as u32
                        });
                        remap[v as usize] = Some(id);
                        id
                    }
                };
                t[k] = id;
            }
            tris.push(t);
        }
        Ok(TriangleMesh {
            positions: welded,
            triangles: tris,
        })
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

/// Deeper node chains are rejected rather than walked (no real asset comes near this).
const MAX_NODE_DEPTH: usize = 1024;

const IDENTITY: [[f64; 4]; 4] = [
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
];

/// Column-major 4×4 product `a · b` (glTF's layout: `m[column][row]`).
fn mat_mul(a: &[[f64; 4]; 4], b: &[[f64; 4]; 4]) -> [[f64; 4]; 4] {
    let mut out = [[0.0; 4]; 4];
    for (c, col) in out.iter_mut().enumerate() {
        for (r, x) in col.iter_mut().enumerate() {
            *x = (0..4).map(|k| a[k][r] * b[c][k]).sum();
        }
    }
    out
}

fn transform(m: &[[f64; 4]; 4], p: [f32; 3]) -> P3 {
    let p = p.map(f64::from);
    [0, 1, 2].map(|r| m[0][r] * p[0] + m[1][r] * p[1] + m[2][r] * p[2] + m[3][r])
}

/// [`FitError::Mesh`] when `vertices` or `triangles` pass `limits` — or pass what `u32` vertex
/// ids can address, whatever the limits say (a larger id would wrap).
fn within_limits(
    vertices: usize,
    triangles: usize,
    limits: &Limits,
    path: &Path,
) -> Result<(), FitError> {
    let max_vertices = limits.max_vertices.min(u64::from(u32::MAX));
    for (count, max, what, name) in [
        (vertices, max_vertices, "vertices", "max_vertices"),
        (
            triangles,
            limits.max_simplices,
            "triangles",
            "max_simplices",
        ),
    ] {
        if count as u64 > max {
            return Err(mesh_error(
                path,
                format!("the mesh has more than {max} {what} (limit {name})"),
            ));
        }
    }
    Ok(())
}

fn add_gltf_mesh(
    mesh: &gltf::Mesh,
    world: &[[f64; 4]; 4],
    buffers: &[gltf::buffer::Data],
    path: &Path,
    limits: &Limits,
    out: &mut (Vec<P3>, Vec<[u32; 3]>),
) -> Result<(), FitError> {
    use gltf::mesh::Mode;
    // A mirroring transform turns counter-clockwise triangles clockwise (glTF spec §3.7.4).
    let linear = [
        [world[0][0], world[0][1], world[0][2]],
        [world[1][0], world[1][1], world[1][2]],
        [world[2][0], world[2][1], world[2][2]],
    ];
    let mirrored = dot(linear[0], cross(linear[1], linear[2])) < 0.0;
    for (pi, primitive) in mesh.primitives().enumerate() {
        let mode = primitive.mode();
        if !matches!(
            mode,
            Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
        ) {
            continue;
        }
        let reader = primitive.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
        let Some(positions) = reader.read_positions() else {
            return Err(mesh_error(
                path,
                format!("mesh {}, primitive {pi}: no POSITION data", mesh.index()),
            ));
        };
        // glTF 2.0 §3.7.2.1: an indices accessor MUST hold unsigned byte, short or int scalars. The
        // `gltf` crate's index reader assumes it (`unreachable!` otherwise), so check first.
        if let Some(acc) = primitive.indices() {
            use gltf::accessor::{DataType, Dimensions};
            if !matches!(
                acc.data_type(),
                DataType::U8 | DataType::U16 | DataType::U32
            ) || acc.dimensions() != Dimensions::Scalar
            {
                return Err(mesh_error(
                    path,
                    format!(
                        "mesh {}, primitive {pi}: indices accessor {} holds {:?} {:?}; expected \
                         unsigned byte, short or int scalars",
                        mesh.index(),
                        acc.index(),
                        acc.data_type(),
                        acc.dimensions()
                    ),
                ));
            }
        }
        let base = out.0.len();
        // Checked before anything is added: the positions' length is their accessor's count.
        within_limits(base + positions.len(), out.1.len(), limits, path)?;
        out.0.extend(positions.map(|p| transform(world, p)));
        let count = out.0.len() - base;
        let indices: Vec<u32> = match reader.read_indices() {
            Some(i) => i.into_u32().collect(),
            None => (0..count as u32).collect(),
        };
        if let Some(bad) = indices.iter().find(|&&i| i as usize >= count) {
            return Err(mesh_error(
                path,
                format!(
                    "mesh {}, primitive {pi}: index {bad} out of range ({count} vertices)",
                    mesh.index()
                ),
            ));
        }
        let tris: Vec<[u32; 3]> = match mode {
            Mode::Triangles => indices
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect(),
            Mode::TriangleStrip => (2..indices.len())
                .map(|i| {
                    if i % 2 == 0 {
                        [indices[i - 2], indices[i - 1], indices[i]]
                    } else {
                        [indices[i - 1], indices[i - 2], indices[i]]
                    }
                })
                .collect(),
            _ => (2..indices.len())
                .map(|i| [indices[0], indices[i - 1], indices[i]])
                .collect(),
        };
        within_limits(out.0.len(), out.1.len() + tris.len(), limits, path)?;
        for t in tris {
            let mut t = t.map(|i| (base + i as usize) as u32);
            if mirrored {
                t.swap(1, 2);
            }
            out.1.push(t);
        }
    }
    Ok(())
}

/// One non-degenerate triangle in the R-tree.
#[derive(Clone, Debug)]
struct Tri {
    id: u32,
    v: [P3; 3],
}

impl RTreeObject for Tri {
    type Envelope = AABB<P3>;
    fn envelope(&self) -> Self::Envelope {
        let lo = [0, 1, 2].map(|k| self.v[0][k].min(self.v[1][k]).min(self.v[2][k]));
        let hi = [0, 1, 2].map(|k| self.v[0][k].max(self.v[1][k]).max(self.v[2][k]));
        AABB::from_corners(lo, hi)
    }
}

impl PointDistance for Tri {
    fn distance_2(&self, point: &P3) -> f64 {
        let q = closest_point_on_triangle(*point, self.v);
        let d = sub(*point, q);
        dot(d, d)
    }
}

/// The closest point of triangle `[a, b, c]` to `p`, by the Voronoi regions of its vertices,
/// edges and face (Ericson, *Real-Time Collision Detection* §5.1.5). Hand-written: it is twenty
/// lines, and the geometry crates that have it (`parry3d`) would pull in a second linear-algebra
/// stack for one function. Needs a triangle of nonzero area.
fn closest_point_on_triangle(p: P3, v: [P3; 3]) -> P3 {
    closest_feature(p, v).0
}

/// Where on a triangle its closest point to a query lies (the Voronoi region Ericson's test ends
/// in): a corner `k`, the edge from corner `k` to corner `k + 1 (mod 3)`, or the face.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Feature {
    Corner(usize),
    Edge(usize),
    Face,
}

/// [`closest_point_on_triangle`] and the [`Feature`] it lies on (the same arithmetic).
fn closest_feature(p: P3, [a, b, c]: [P3; 3]) -> (P3, Feature) {
    let ab = sub(b, a);
    let ac = sub(c, a);
    let ap = sub(p, a);
    let d1 = dot(ab, ap);
    let d2 = dot(ac, ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return (a, Feature::Corner(0));
    }
    let bp = sub(p, b);
    let d3 = dot(ab, bp);
    let d4 = dot(ac, bp);
    if d3 >= 0.0 && d4 <= d3 {
        return (b, Feature::Corner(1));
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return (axpy(a, d1 / (d1 - d3), ab), Feature::Edge(0));
    }
    let cp = sub(p, c);
    let d5 = dot(ab, cp);
    let d6 = dot(ac, cp);
    if d6 >= 0.0 && d5 <= d6 {
        return (c, Feature::Corner(2));
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return (axpy(a, d2 / (d2 - d6), ac), Feature::Edge(2));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return (
            axpy(b, (d4 - d3) / ((d4 - d3) + (d5 - d6)), sub(c, b)),
            Feature::Edge(1),
        );
    }
    let denom = 1.0 / (va + vb + vc);
    (axpy(axpy(a, vb * denom, ab), vc * denom, ac), Feature::Face)
}

/// Angle-weighted pseudonormals of a closed, consistently oriented manifold mesh with no
/// degenerate triangle (Bærentzen and Aanæs 2005): at a corner the sum of the incident faces'
/// unit normals weighted by their angles there, on an edge the sum of its two faces' normals. For
/// `p` off the surface with closest point `q`, `⟨p − q, n(q)⟩ > 0` exactly when `p` is outside
/// (their Theorem 1), `n(q)` being the face normal, the edge's or the corner's pseudonormal.
#[derive(Debug)]
struct Pseudonormals {
    /// Per vertex.
    corner: Vec<P3>,
    /// Per triangle, its edge `k → k + 1 (mod 3)`.
    edge: Vec<[P3; 3]>,
}

impl Pseudonormals {
    /// `None` unless the mesh is a closed, consistently oriented manifold without degenerate
    /// triangles (the theorem's setting).
    fn new(mesh: &TriangleMesh, check: &MeshCheck, normals: &[P3]) -> Option<Pseudonormals> {
        if !check.is_closed_manifold() || normals.contains(&[0.0; 3]) {
            return None;
        }
        let mut corner = vec![[0.0; 3]; mesh.positions.len()];
        let mut by_edge: HashMap<(u32, u32), P3> = HashMap::with_capacity(3 * normals.len());
        for (t, n) in mesh.triangles.iter().zip(normals) {
            let v = t.map(|i| mesh.positions[i as usize]);
            for k in 0..3 {
                let (e1, e2) = (sub(v[(k + 1) % 3], v[k]), sub(v[(k + 2) % 3], v[k]));
                let angle = norm(cross(e1, e2)).atan2(dot(e1, e2));
                corner[t[k] as usize] = axpy(corner[t[k] as usize], angle, *n);
                let (a, b) = (t[k], t[(k + 1) % 3]);
                let e = by_edge.entry((a.min(b), a.max(b))).or_insert([0.0; 3]);
                *e = axpy(*e, 1.0, *n);
            }
        }
        let edge = mesh
            .triangles
            .iter()
            .map(|t| {
                [0, 1, 2].map(|k| {
                    let (a, b) = (t[k], t[(k + 1) % 3]);
                    by_edge[&(a.min(b), a.max(b))]
                })
            })
            .collect();
        Some(Pseudonormals { corner, edge })
    }
}

/// The pseudonormal sign is used only when `p − q` makes an angle with the pseudonormal farther
/// than this cosine from 90°: rounding in the closest point (a few ulps of the coordinates) then
/// cannot move the sign; nearer to 90° (or at the surface) the winding number decides.
const PSEUDONORMAL_MIN_COS: f64 = 1e-3;

/// ... and only when `|⟨p − q, n⟩|` is above this fraction of the coordinates' size times `|n|`:
/// `q` and `p − q` are ~20 operations on coordinates of that size, so their rounding moves the
/// product by ≲ 10⁻¹⁴ of it; 10⁻¹² keeps a factor of 100. Points nearer the surface than that
/// (the fitter's root bisections end there) take the winding number.
const PSEUDONORMAL_MIN_DOT_REL: f64 = 1e-12;

/// Signed solid angle of triangle `[a, b, c]` seen from `p` (Van Oosterom and Strackee 1983):
/// positive when `p` is on the side the counter-clockwise normal points away from.
fn solid_angle(p: P3, [a, b, c]: [P3; 3]) -> f64 {
    let (a, b, c) = (sub(a, p), sub(b, p), sub(c, p));
    let (la, lb, lc) = (norm(a), norm(b), norm(c));
    let num = dot(a, cross(b, c));
    let den = la * lb * lc + dot(a, b) * lc + dot(a, c) * lb + dot(b, c) * la;
    2.0 * num.atan2(den)
}

/// A node of the winding-number hierarchy (mirrors one R-tree node).
#[derive(Debug)]
struct WindingNode {
    lo: P3,
    hi: P3,
    /// Triangles below this node.
    triangles: usize,
    /// Fan apex and the boundary chain of the node's patch (directed edges).
    apex: P3,
    boundary: Vec<[P3; 2]>,
    children: Vec<WindingChild>,
}

#[derive(Debug)]
enum WindingChild {
    Node(WindingNode),
    Triangle([P3; 3]),
}

impl WindingNode {
    /// Builds the node for an R-tree parent; `ids` collects the node's triangle ids.
    fn build(
        node: &rstar::ParentNode<Tri>,
        mesh: &TriangleMesh,
        ids: &mut Vec<u32>,
    ) -> WindingNode {
        let start = ids.len();
        let children = node
            .children()
            .iter()
            .map(|child| match child {
                RTreeNode::Leaf(t) => {
                    ids.push(t.id);
                    WindingChild::Triangle(t.v)
                }
                RTreeNode::Parent(p) => WindingChild::Node(WindingNode::build(p, mesh, ids)),
            })
            .collect();
        let mine = &ids[start..];
        // The boundary chain: directed edges of the patch minus those cancelled by their reverse.
        let mut chain: HashMap<(u32, u32), i32> = HashMap::new();
        for &t in mine {
            let t = mesh.triangles[t as usize];
            for k in 0..3 {
                let (u, v) = (t[k], t[(k + 1) % 3]);
                let (key, s) = if u < v { ((u, v), 1) } else { ((v, u), -1) };
                *chain.entry(key).or_default() += s;
            }
        }
        let mut edges: Vec<(u32, u32)> = Vec::new();
        for (&(u, v), &m) in &chain {
            // |m| > 1 only on non-manifold patches: repeat the edge, the chain stays exact.
            let e = if m > 0 { (u, v) } else { (v, u) };
            edges.extend(std::iter::repeat_n(e, m.unsigned_abs() as usize));
        }
        edges.sort_unstable();
        let apex_id = edges.first().map_or(0, |e| e.0);
        let apex = mesh.positions[apex_id as usize];
        let boundary = edges
            .iter()
            .filter(|e| e.0 != apex_id && e.1 != apex_id)
            .map(|&(u, v)| [mesh.positions[u as usize], mesh.positions[v as usize]])
            .collect();
        let env = node.envelope();
        WindingNode {
            lo: env.lower(),
            hi: env.upper(),
            triangles: mine.len(),
            apex,
            boundary,
            children,
        }
    }

    /// `Σ Ω / 4π`·4π (the solid-angle sum) of this node's patch at `p`.
    fn solid_angle_sum(&self, p: P3) -> f64 {
        let outside = (0..3).any(|k| p[k] < self.lo[k] || p[k] > self.hi[k]);
        if outside && self.boundary.len() < self.triangles {
            return self
                .boundary
                .iter()
                .map(|&[a, b]| solid_angle(p, [self.apex, a, b]))
                .sum();
        }
        self.children
            .iter()
            .map(|c| match c {
                WindingChild::Node(n) => n.solid_angle_sum(p),
                WindingChild::Triangle(t) => solid_angle(p, *t),
            })
            .sum()
    }
}

/// Rounding margin of the value bound, relative to the size of the coordinates: the distance is
/// ~30 operations on coordinates of that size (≲ 10⁻¹⁴ relative); 10⁻⁹ covers it many times
/// over, also for the cancellation in thin triangles.
const VALUE_MARGIN_REL: f64 = 1e-9;

/// Absolute widening of the computed unit normals' components (each is a cross product of
/// differences divided by its length: a few ulps); generous, like [`VALUE_MARGIN_REL`].
const NORMAL_MARGIN: f64 = crate::expr::GENERATOR_ERROR;

/// Normal turn (radians, 60°) across an edge beyond which the Plantinga–Vegter phase is skipped.
/// From 90° on the test can never pass near the edge (every cell on it sees both normals, whose
/// dot product is then ≤ 0). Between 60° and 90° it passes only on cells small enough to see
/// little more than the edge's two sides ([`ImplicitFunction::gradient_generators`]: the nearby
/// normals pairwise; a component-wise box of them already failed from ±35° around an axis on).
/// Kept at 60° because that refinement is costly: the Stanford bunny (82°) at 1e-2 with the phase
/// on ran over 12 CPU-minutes without finishing, against 3.5 with it skipped (session 14).
pub const PV_SHARPEST_EDGE: f64 = std::f64::consts::FRAC_PI_3;

/// [`MeshDistance::enclose`] gathers candidate triangles per sub-box of the box split this many
/// times along each axis (4³ sub-boxes): each level halves the over-reach of the candidate set, which
/// decides how small cells must get before the Plantinga–Vegter test can pass; 64 nearest-point
/// queries per enclosure cost less than the refinement they save (measured on an icosphere).
const GRADIENT_SPLIT_LEVELS: u32 = 2;

/// The signed distance to a mesh, with the winding-number sign (see the module doc).
///
/// Continuous only for a closed, consistently oriented manifold mesh ([`MeshCheck::is_closed_manifold`]):
/// across a hole the winding number passes ½ away from the triangles and `g` jumps from `+d` to
/// `−d` there, which no fit can meet (`ism fit --mesh` refuses such meshes).
#[derive(Debug)]
pub struct MeshDistance {
    mesh: TriangleMesh,
    check: MeshCheck,
    flipped: bool,
    /// Unit normal of each triangle (zero for a degenerate one).
    normals: Vec<P3>,
    tree: RTree<Tri>,
    winding: WindingNode,
    /// The fast sign, for a closed manifold mesh (`None` otherwise: the winding number decides).
    pseudonormals: Option<Pseudonormals>,
    /// Size of the coordinates, for the rounding margins.
    scale: f64,
    /// Key of this instance in the per-thread query caches.
    instance: u64,
    /// Cell size of the cache's grid.
    cache_cell: f64,
}

/// What one evaluation learned, reusable exactly by later queries near it.
#[derive(Clone, Copy, Debug)]
struct Known {
    p: P3,
    /// Distance from `p` to the mesh: the open ball of this radius meets no triangle, so the
    /// winding number, and with it the sign, is constant in it.
    dist: f64,
    inside: bool,
    /// The closest triangle: a nearby query's distance to it bounds its search radius.
    triangle: u32,
}

/// Entries per thread before the cache is cleared: ~12 MB per thread. The fitter revisits a
/// point within one face's Levenberg–Marquardt loop (a few thousand samples), so a small cache
/// keeps nearly all of its hits.
const CACHE_CAPACITY: usize = 1 << 17;

/// A cached sign is reused only within this fraction of the cached distance, so rounding in the
/// distance cannot put the query across the surface.
const CACHE_BALL_FRACTION: f64 = 0.5;

/// Cache grid cell relative to the mesh diagonal: the fitter's finite differences move its sample
/// points by ~10⁻⁷ of a cell, so they land in the cell of the unperturbed point.
const CACHE_CELL_REL: f64 = 1e-6;

static NEXT_INSTANCE: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

thread_local! {
    /// Per-thread cache of recent queries (no locking under rayon): grid cell → what was learned.
    static QUERY_CACHE: std::cell::RefCell<HashMap<(u64, [i64; 3]), Known>> =
        std::cell::RefCell::new(HashMap::new());
    /// This thread's previous (instance, closest triangle): consecutive queries are usually near
    /// each other, so it bounds the next search radius tightly.
    static LAST_TRIANGLE: std::cell::Cell<(u64, u32)> = const { std::cell::Cell::new((u64::MAX, 0)) };
}

impl MeshDistance {
    /// Orients the mesh outward ([`TriangleMesh::orient_outward`]) and builds the R-tree and the
    /// winding hierarchy.
    ///
    /// # Errors
    /// [`FitError::Mesh`] (with an empty path) when every triangle is degenerate.
    pub fn new(mut mesh: TriangleMesh) -> Result<MeshDistance, FitError> {
        let flipped = mesh.orient_outward();
        let check = mesh.check();
        let normals: Vec<P3> = mesh
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|v| mesh.positions[v as usize]);
                let n = cross(sub(b, a), sub(c, a));
                let l = norm(n);
                if l > 0.0 {
                    n.map(|x| x / l)
                } else {
                    [0.0; 3]
                }
            })
            .collect();
        let tris: Vec<Tri> = mesh
            .triangles
            .iter()
            .enumerate()
            .filter(|(i, _)| normals[*i] != [0.0; 3])
            .map(|(i, t)| Tri {
                id: i as u32,
                v: t.map(|v| mesh.positions[v as usize]),
            })
            .collect();
        if tris.is_empty() {
            return Err(FitError::Mesh {
                path: PathBuf::new(),
                message: "every triangle has zero area".into(),
            });
        }
        let tree = RTree::bulk_load(tris);
        let mesh_diagonal = mesh.diagonal().max(f64::MIN_POSITIVE);
        let winding = WindingNode::build(tree.root(), &mesh, &mut Vec::new());
        let pseudonormals = Pseudonormals::new(&mesh, &check, &normals);
        let scale = mesh
            .positions
            .iter()
            .flat_map(|p| p.iter().map(|x| x.abs()))
            .fold(0.0, f64::max)
            + mesh.diagonal();
        Ok(MeshDistance {
            mesh,
            check,
            flipped,
            normals,
            tree,
            winding,
            pseudonormals,
            scale,
            instance: NEXT_INSTANCE.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
            cache_cell: CACHE_CELL_REL * mesh_diagonal,
        })
    }

    /// The (outward-oriented) mesh.
    pub fn mesh(&self) -> &TriangleMesh {
        &self.mesh
    }

    /// Its combinatorial check.
    pub fn check(&self) -> MeshCheck {
        self.check
    }

    /// Why a fit of this mesh is refused, when it is (`ism fit --mesh` exits 2 with it; the
    /// caller prefixes the mesh's name): not a closed manifold. Across a hole the winding number
    /// passes ½ away from the triangles, where the signed distance jumps from +d to −d; the
    /// fitter would refine that jump to the simplex budget without ever meeting the tolerance.
    pub fn refusal(&self) -> Option<String> {
        let c = &self.check;
        (!c.is_closed_manifold()).then(|| {
            format!(
                "is not a closed manifold ({} boundary, {} non-manifold, {} misoriented edges): \
                 the signed distance would jump where the winding number crosses 1/2 off the \
                 surface; close and orient the mesh first",
                c.boundary_edges, c.nonmanifold_edges, c.misoriented_edges
            )
        })
    }

    /// Sets the options `ism fit --mesh` uses for this mesh: with `topology` asked for, the
    /// Plantinga–Vegter phase runs only when no edge is sharper than [`PV_SHARPEST_EDGE`] (at a
    /// crease the test fails at every cell size) and stops at cells shorter than half the median
    /// mesh edge or the tolerance (below that it can only find the creases, not features the
    /// mesh has; the topology is checked against the mesh's afterwards). Returns whether the
    /// phase was skipped because of a sharp edge.
    pub fn adapt_options(&self, options: &mut crate::FitOptions, topology: bool) -> bool {
        let sharp = self.sharpest_edge() > PV_SHARPEST_EDGE;
        options.topology = topology && !sharp;
        options.pv_min_edge = (0.5 * self.mesh.median_edge_length()).max(options.tolerance);
        topology && sharp
    }

    /// The largest angle (radians) between the normals of two triangles sharing an edge: above
    /// [`PV_SHARPEST_EDGE`], cells on that edge can fail the Plantinga–Vegter test at every size.
    pub fn sharpest_edge(&self) -> f64 {
        let mut by_edge: HashMap<(u32, u32), Vec<u32>> = HashMap::new();
        for (i, t) in self.mesh.triangles.iter().enumerate() {
            for k in 0..3 {
                let (u, v) = (t[k], t[(k + 1) % 3]);
                by_edge
                    .entry((u.min(v), u.max(v)))
                    .or_default()
                    .push(i as u32);
            }
        }
        let mut worst = 0.0f64;
        for tris in by_edge.values() {
            for (a, &i) in tris.iter().enumerate() {
                for &j in &tris[a + 1..] {
                    let (ni, nj) = (self.normals[i as usize], self.normals[j as usize]);
                    if ni != [0.0; 3] && nj != [0.0; 3] {
                        worst = worst.max(dot(ni, nj).clamp(-1.0, 1.0).acos());
                    }
                }
            }
        }
        worst
    }

    /// Whether [`MeshDistance::new`] turned the mesh inside out to make its volume positive.
    pub fn flipped(&self) -> bool {
        self.flipped
    }

    /// The generalized winding number at `p`, hierarchically (exact up to rounding).
    pub fn winding_number(&self, p: P3) -> f64 {
        self.winding.solid_angle_sum(p) / (4.0 * std::f64::consts::PI)
    }

    /// The generalized winding number at `p` as the plain sum over all triangles (reference).
    pub fn winding_number_brute_force(&self, p: P3) -> f64 {
        self.mesh
            .triangles
            .iter()
            .map(|t| solid_angle(p, t.map(|v| self.mesh.positions[v as usize])))
            .sum::<f64>()
            / (4.0 * std::f64::consts::PI)
    }

    /// The closest point of the mesh to `p` and the triangle it lies on.
    pub fn closest_point(&self, p: P3) -> (P3, u32) {
        // The tree is non-empty (checked in `new`).
        let t = self
            .tree
            .nearest_neighbor(p)
            .expect("the R-tree has at least one triangle");
        (closest_point_on_triangle(p, t.v), t.id)
    }

    /// Whether `p` is inside (`w > ½`).
    pub fn is_inside(&self, p: P3) -> bool {
        self.winding_number(p) > 0.5
    }

    /// Whether `p` is inside, given its closest triangle `t`: the pseudonormal sign when the mesh
    /// is a closed manifold and `p` is clearly off the surface and off the pseudonormal's
    /// perpendicular ([`PSEUDONORMAL_MIN_COS`]), else the winding number. Same answer as
    /// [`MeshDistance::is_inside`] (tested against it) for a dot product instead of a
    /// hierarchical sum of solid angles (the winding number was 70 % of a bunny fit's CPU).
    fn side(&self, p: P3, t: u32) -> bool {
        self.pseudonormal_side(p, t)
            .unwrap_or_else(|| self.is_inside(p))
    }

    /// The pseudonormal half of [`MeshDistance::side`]: `None` when it cannot decide.
    fn pseudonormal_side(&self, p: P3, t: u32) -> Option<bool> {
        let pn = self.pseudonormals.as_ref()?;
        let tri = self.mesh.triangles[t as usize];
        let (q, feature) = closest_feature(p, tri.map(|i| self.mesh.positions[i as usize]));
        let n = match feature {
            Feature::Face => self.normals[t as usize],
            Feature::Edge(k) => pn.edge[t as usize][k],
            Feature::Corner(k) => pn.corner[tri[k] as usize],
        };
        let d = sub(p, q);
        let (ld, ln) = (norm(d), norm(n));
        let s = dot(d, n);
        let clear = ln > 0.0
            && s.abs() > PSEUDONORMAL_MIN_COS * ld * ln
            && s.abs() > PSEUDONORMAL_MIN_DOT_REL * self.scale * ln;
        clear.then_some(s < 0.0)
    }

    /// The closest point and triangle, searching only within the distance to `hint`'s
    /// triangle (exact: the closest triangle is no farther than any other). `hint` is a triangle
    /// the R-tree returned, so it is not degenerate.
    fn closest_point_near(&self, p: P3, hint: u32) -> (P3, u32) {
        if hint as usize >= self.mesh.triangles.len() {
            return self.closest_point(p);
        }
        let h = hint;
        let v = self.mesh.triangles[hint as usize].map(|i| self.mesh.positions[i as usize]);
        let dh = sub(p, closest_point_on_triangle(p, v));
        // Widened so rounding cannot drop the hint itself from the ball.
        let r2 = dot(dh, dh) * (1.0 + 1e-9) + f64::MIN_POSITIVE;
        let mut best = (f64::INFINITY, h);
        for t in self.tree.locate_within_distance(p, r2) {
            let d = t.distance_2(&p);
            if d < best.0 || (d == best.0 && t.id < best.1) {
                best = (d, t.id);
            }
        }
        if best.0.is_finite() {
            let v = self.mesh.triangles[best.1 as usize].map(|i| self.mesh.positions[i as usize]);
            (closest_point_on_triangle(p, v), best.1)
        } else {
            self.closest_point(p)
        }
    }

    /// Distance to the closest point, its triangle, and the side: reuses a cached query in the
    /// same grid cell when `p` lies in its surface-free ball (same sign, exactly) and as the
    /// search hint; otherwise the R-tree and the winding number.
    fn locate(&self, p: P3) -> (P3, u32, bool) {
        let key = (
            self.instance,
            p.map(|x| (x / self.cache_cell).floor() as i64),
        );
        let known = QUERY_CACHE.with(|c| c.borrow().get(&key).copied());
        let last = LAST_TRIANGLE.with(|c| c.get());
        let (q, t) = match known {
            Some(k) => self.closest_point_near(p, k.triangle),
            None if last.0 == self.instance => self.closest_point_near(p, last.1),
            None => self.closest_point(p),
        };
        LAST_TRIANGLE.with(|c| c.set((self.instance, t)));
        let inside = match known {
            Some(k) if norm(sub(p, k.p)) < CACHE_BALL_FRACTION * k.dist => k.inside,
            // On the surface the side is not asked: the value is 0 and the gradient the face
            // normal either way (the fitter's measure queries points of the triangles).
            _ if p == q => false,
            _ => self.side(p, t),
        };
        let dist = norm(sub(p, q));
        if dist > 0.0 {
            QUERY_CACHE.with(|c| {
                let mut c = c.borrow_mut();
                if c.len() >= CACHE_CAPACITY {
                    c.clear();
                }
                c.insert(
                    key,
                    Known {
                        p,
                        dist,
                        inside,
                        triangle: t,
                    },
                );
            });
        }
        (q, t, inside)
    }

    /// Signed distance, its gradient, and the closest point.
    fn evaluate(&self, p: P3) -> (f64, P3) {
        let (q, t, inside) = self.locate(p);
        let d = sub(p, q);
        let dist = norm(d);
        let sign = if inside { -1.0 } else { 1.0 };
        let grad = if dist > 0.0 {
            d.map(|x| sign * x / dist)
        } else {
            self.normals[t as usize]
        };
        (sign * dist, grad)
    }

    /// The 1-Lipschitz bound of `g` over the box `[lo, hi]`: `g(centre) ± half-diagonal`,
    /// widened by the rounding margin.
    pub fn value_bounds(&self, lo: &[f64], hi: &[f64]) -> Interval {
        let (centre, half) = centre_and_half_diagonal(lo, hi);
        let v = self.value(&centre);
        let r = half + VALUE_MARGIN_REL * self.scale;
        Interval::new(v - r, v + r)
    }

    /// Unit-vector bounds containing `∇g` at every point of the box where it exists, or `None`
    /// when the normals there do not avoid the origin (see [`ImplicitFunction::enclose`]).
    fn gradient_bounds(&self, lo: &[f64], hi: &[f64]) -> Option<Vec<Interval>> {
        let ids = self.candidates(lo, hi);
        let mut nlo = [f64::INFINITY; 3];
        let mut nhi = [f64::NEG_INFINITY; 3];
        let mut sum = [0.0; 3];
        let mut normals = Vec::with_capacity(ids.len());
        for t in ids {
            let n = self.normals[t as usize];
            for k in 0..3 {
                nlo[k] = nlo[k].min(n[k] - NORMAL_MARGIN);
                nhi[k] = nhi[k].max(n[k] + NORMAL_MARGIN);
                sum[k] += n[k];
            }
            normals.push(n);
        }
        if normals.is_empty() {
            return None;
        }
        // A lower bound r on |u| for u in the convex hull of the normals: the larger of the
        // distance from 0 to their bounding box and the least projection on their mean direction.
        let to_box = (0..3)
            .map(|k| nlo[k].max(0.0).max(-nhi[k]).powi(2))
            .sum::<f64>()
            .sqrt();
        let l = norm(sum);
        let along = if l > 0.0 {
            let m = sum.map(|x| x / l);
            normals
                .iter()
                .map(|&n| dot(n, m) - 3.0 * NORMAL_MARGIN)
                .fold(f64::INFINITY, f64::min)
        } else {
            0.0
        };
        let r = to_box.max(along);
        if r <= 0.0 {
            return None;
        }
        // u_k / |u| with u_k ∈ [lo, hi] and |u| ∈ [r, 1].
        Some(
            (0..3)
                .map(|k| {
                    let a = if nlo[k] >= 0.0 { nlo[k] } else { nlo[k] / r };
                    let b = if nhi[k] >= 0.0 { nhi[k] / r } else { nhi[k] };
                    Interval::new(a.max(-1.0), b.min(1.0))
                })
                .collect(),
        )
    }

    /// The triangles that can hold the closest point of some point of the box `[lo, hi]`,
    /// sorted, without repeats. Gathered per sub-box: a sub-box of half-diagonal h around c needs
    /// the triangles within dist(c) + 2h of c, so splitting shrinks the 2h part, which dominates
    /// near the surface.
    fn candidates(&self, lo: &[f64], hi: &[f64]) -> Vec<u32> {
        let mut ids: Vec<u32> = Vec::new();
        let parts = 1usize << GRADIENT_SPLIT_LEVELS;
        let edge = |k: usize, j: usize| {
            if j == parts {
                hi[k]
            } else {
                lo[k] + (hi[k] - lo[k]) * (j as f64 / parts as f64)
            }
        };
        for i in 0..parts * parts * parts {
            let j = [i % parts, (i / parts) % parts, i / (parts * parts)];
            let sub_lo = [0, 1, 2].map(|k| edge(k, j[k]));
            let sub_hi = [0, 1, 2].map(|k| edge(k, j[k] + 1));
            let (c, half) = centre_and_half_diagonal(&sub_lo, &sub_hi);
            let (q, _) = self.closest_point(c);
            let radius = norm(sub(c, q)) + 2.0 * half + 2.0 * VALUE_MARGIN_REL * self.scale;
            ids.extend(
                self.tree
                    .locate_within_distance(c, radius * radius)
                    .map(|t| t.id),
            );
        }
        ids.sort_unstable();
        ids.dedup();
        ids
    }
}

fn centre_and_half_diagonal(lo: &[f64], hi: &[f64]) -> ([f64; 3], f64) {
    let mut c = [0.0; 3];
    let mut h2 = 0.0;
    for k in 0..3 {
        c[k] = 0.5 * (lo[k] + hi[k]);
        // The centre is rounded; half the width plus an ulp of the ends bounds |p − c|.
        let w = 0.5 * (hi[k] - lo[k]) + f64::EPSILON * (lo[k].abs() + hi[k].abs());
        h2 += w * w;
    }
    (c, h2.sqrt() * (1.0 + 4.0 * f64::EPSILON))
}

impl ImplicitFunction for MeshDistance {
    fn dim(&self) -> usize {
        3
    }

    fn value(&self, p: &[f64]) -> f64 {
        let p = [p[0], p[1], p[2]];
        let (q, _, inside) = self.locate(p);
        let dist = norm(sub(p, q));
        if inside {
            -dist
        } else {
            dist
        }
    }

    fn gradient(&self, p: &[f64], gradient: &mut [f64]) -> f64 {
        let (v, g) = self.evaluate([p[0], p[1], p[2]]);
        gradient[..3].copy_from_slice(&g);
        v
    }

    /// Value: [`MeshDistance::value_bounds`]. Gradient: at a point `p` off the surface with
    /// closest point `q`, `∇g(p)` is a unit vector in the cone of the outward normals of the
    /// triangles containing `q` (`p − q` is a proximal normal of the solid, or of its complement
    /// inside; proximal normals lie in the Clarke normal cone, the convex cone of the limiting
    /// normals, which at a mesh point are its faces' normals). Every such triangle lies within
    /// `|g(centre)| + 2·half-diagonal` of the centre, so the R-tree gathers a superset; the unit
    /// vectors of their cone are enclosed by dividing the normals' bounding box by a lower bound
    /// `r` on the length of their convex combinations. On a closed, consistently oriented mesh
    /// only; otherwise (or when the normals surround the origin, as at a sharp corner) there is no
    /// useful enclosure and the gradient is `[-1, 1]` per component, which fails the
    /// Plantinga–Vegter test: cells at sharp features are then refined until the simplex budget.
    /// Returns `None` (no test at all) for an open or non-manifold mesh, where the sign is not a
    /// solid's and the test would not mean what it says.
    fn is_explicit(&self) -> bool {
        true
    }

    /// The exact distance to the triangles (the R-tree's closest point, no cache).
    fn distance_bound(&self, p: &[f64], _reach: f64) -> f64 {
        let p = [p[0], p[1], p[2]];
        norm(sub(p, self.closest_point(p).0))
    }

    /// A barycentric grid on every triangle, fine enough that its sub-triangles' edges are at
    /// most `spacing` (coarser if that would exceed `budget` points): every point of a triangle
    /// is within its longest edge of each of its corners, so within that of a grid point.
    fn surface_points(&self, spacing: f64, budget: usize) -> Option<(Vec<[f64; 3]>, f64)> {
        let mesh = self.mesh();
        let longest: Vec<f64> = mesh
            .triangles
            .iter()
            .map(|t| {
                let v = t.map(|i| mesh.positions[i as usize]);
                norm(sub(v[0], v[1]))
                    .max(norm(sub(v[1], v[2])))
                    .max(norm(sub(v[2], v[0])))
            })
            .collect();
        let levels = |spacing: f64| -> Vec<usize> {
            longest
                .iter()
                .map(|l| ((l / spacing).ceil() as usize).clamp(1, 1 << 12))
                .collect()
        };
        let mut spacing = spacing;
        let mut ls = levels(spacing);
        // Coarser while over the budget, down to one cell per triangle (the mesh's own vertices).
        while ls.iter().any(|&l| l > 1)
            && ls.iter().map(|l| (l + 1) * (l + 2) / 2).sum::<usize>() > budget
        {
            spacing *= 1.5;
            ls = levels(spacing);
        }
        let radius = longest
            .iter()
            .zip(&ls)
            .map(|(l, &k)| l / k as f64)
            .fold(0.0, f64::max);
        let mut points = Vec::new();
        for (t, &l) in mesh.triangles.iter().zip(&ls) {
            let v = t.map(|i| mesh.positions[i as usize]);
            for i in 0..=l {
                for j in 0..=l - i {
                    let (a, b) = (i as f64 / l as f64, j as f64 / l as f64);
                    let c = 1.0 - a - b;
                    points.push([0, 1, 2].map(|k| c * v[0][k] + a * v[1][k] + b * v[2][k]));
                }
            }
        }
        Some((points, radius))
    }

    fn enclose(&self, lo: &[f64], hi: &[f64]) -> Option<Enclosure> {
        if !self.check.is_closed_manifold() {
            return None;
        }
        let value = self.value_bounds(lo, hi);
        let unit = Interval::new(-1.0, 1.0);
        let gradient = if value.contains(0.0) {
            self.gradient_bounds(lo, hi)
                .unwrap_or_else(|| vec![unit; 3])
        } else {
            // 0 ∉ □g already passes the test.
            vec![unit; 3]
        };
        Some(Enclosure { value, gradient })
    }

    /// The normals of the triangles that can hold the closest point of a point of the box: the
    /// gradient there is one of them, or lies between those of the triangles meeting at the
    /// closest edge or vertex — the same hull [`MeshDistance::gradient_bounds`] bounds.
    fn gradient_generators(&self, lo: &[f64], hi: &[f64], out: &mut Vec<f64>) -> bool {
        if !self.check.is_closed_manifold() {
            return false;
        }
        for t in self.candidates(lo, hi) {
            out.extend_from_slice(&self.normals[t as usize]);
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A cube `[-s, s]³` as 12 outward triangles, with the 8 corners shifted by `offset`.
    fn cube(s: f64, offset: P3) -> TriangleMesh {
        let mut positions = Vec::new();
        for i in 0..8 {
            let c = [i & 1, (i >> 1) & 1, (i >> 2) & 1].map(|b| if b == 1 { s } else { -s });
            positions.push([c[0] + offset[0], c[1] + offset[1], c[2] + offset[2]]);
        }
        let quads = [
            [0, 2, 3, 1], // z = -s
            [4, 5, 7, 6], // z = +s
            [0, 1, 5, 4], // y = -s
            [2, 6, 7, 3], // y = +s
            [0, 4, 6, 2], // x = -s
            [1, 3, 7, 5], // x = +s
        ];
        let triangles = quads
            .iter()
            .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
            .collect();
        TriangleMesh {
            positions,
            triangles,
        }
    }

    fn icosphere(level: usize) -> TriangleMesh {
        TriangleMesh::icosphere(level, 1.0, [0.0; 3])
    }

    /// A closed torus (radii `big`, `small`) of `n × m` quads split in two, outward: saddle
    /// vertices and concave edges on its inner side.
    fn torus_mesh(n: u32, m: u32, big: f64, small: f64) -> TriangleMesh {
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

    /// The pseudonormal sign agrees with the brute-force winding number (an independent sum of
    /// all solid angles) on nonconvex closed meshes — a torus (saddle corners, concave edges) and
    /// an icosphere with radial bumps — at random points in the box and at points just off the
    /// surface near corners, edges and faces; and it is the fast path for most of them.
    #[test]
    fn pseudonormal_sign_agrees_with_the_winding_number() {
        let mut bumpy = TriangleMesh::icosphere(3, 1.0, [0.0; 3]);
        for (k, p) in bumpy.positions.iter_mut().enumerate() {
            let f = 1.0 + 0.25 * ((k * 7919) % 13) as f64 / 13.0;
            *p = p.map(|x| x * f);
        }
        for (name, mesh) in [("torus", torus_mesh(24, 12, 1.0, 0.35)), ("bumpy", bumpy)] {
            let g = MeshDistance::new(mesh).unwrap();
            assert!(g.check().is_closed_manifold(), "{name}");
            assert!(g.pseudonormals.is_some(), "{name}");
            let mut queries = points(3000, -1.6, 1.6, 11);
            // Just off the surface: from each vertex and from edge midpoints and face centres,
            // along a deterministic direction, at distances from 1e-12 to 1e-1.
            let dirs = points(4 * g.mesh.triangles.len(), -1.0, 1.0, 29);
            for (k, t) in g.mesh.triangles.iter().enumerate() {
                let v = t.map(|i| g.mesh.positions[i as usize]);
                let sites = [
                    v[0],
                    [0, 1, 2].map(|x| 0.5 * (v[0][x] + v[1][x])),
                    [0, 1, 2].map(|x| (v[0][x] + v[1][x] + v[2][x]) / 3.0),
                    v[1],
                ];
                for (j, site) in sites.into_iter().enumerate() {
                    let h = 10f64.powi(-1 - ((k + j) % 12) as i32);
                    queries.push(axpy(site, h, dirs[4 * k + j]));
                }
            }
            let mut fast = 0;
            for p in &queries {
                let (_, t) = g.closest_point(*p);
                let truth = g.winding_number_brute_force(*p) > 0.5;
                assert_eq!(g.side(*p, t), truth, "{name} at {p:?}");
                if let Some(side) = g.pseudonormal_side(*p, t) {
                    assert_eq!(side, truth, "{name} at {p:?}");
                    fast += 1;
                }
            }
            // Every point but those within ~1e-12 of the surface (1 in 12 of the near ones).
            assert!(
                fast * 10 > queries.len() * 9,
                "{name}: {fast} of {}",
                queries.len()
            );
        }
    }

    /// Deterministic points in a box (a fixed LCG: the tests need no RNG crate for this).
    fn points(n: usize, lo: f64, hi: f64, seed: u64) -> Vec<P3> {
        let mut s = seed;
        let mut next = move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            lo + (hi - lo) * ((s >> 11) as f64 / (1u64 << 53) as f64)
        };
        (0..n).map(|_| [next(), next(), next()]).collect()
    }

    /// Independent point–triangle distance: projection onto the plane when it falls inside
    /// (barycentric test), otherwise the nearest of the three edges as segments.
    fn brute_distance(p: P3, [a, b, c]: [P3; 3]) -> f64 {
        let n = cross(sub(b, a), sub(c, a));
        let nn = dot(n, n);
        let h = dot(sub(p, a), n) / nn;
        let q = axpy(p, -h, n);
        let inside = [(a, b), (b, c), (c, a)]
            .iter()
            .all(|&(u, v)| dot(cross(sub(v, u), sub(q, u)), n) >= 0.0);
        if inside {
            return norm(sub(p, q));
        }
        [(a, b), (b, c), (c, a)]
            .iter()
            .map(|&(u, v)| {
                let d = sub(v, u);
                let t = (dot(sub(p, u), d) / dot(d, d)).clamp(0.0, 1.0);
                norm(sub(p, axpy(u, t, d)))
            })
            .fold(f64::INFINITY, f64::min)
    }

    #[test]
    fn winding_number_is_one_inside_and_zero_outside() {
        for mesh in [cube(0.5, [0.1, -0.2, 0.05]), icosphere(2)] {
            let d = MeshDistance::new(mesh).unwrap();
            assert!(!d.flipped());
            for p in points(400, -1.5, 1.5, 7) {
                let w = d.winding_number(p);
                let brute = d.winding_number_brute_force(p);
                assert!((w - brute).abs() < 1e-9, "{p:?}: {w} vs {brute}");
                let (q, _) = d.closest_point(p);
                if norm(sub(p, q)) < 1e-9 {
                    continue;
                }
                assert!(
                    w.abs() < 1e-9 || (w - 1.0).abs() < 1e-9,
                    "{p:?}: w = {w} is not 0 or 1"
                );
            }
        }
        // Against ground truth that does not use solid angles: the cube's own inequalities.
        let d = MeshDistance::new(cube(0.5, [0.0; 3])).unwrap();
        for p in points(300, -1.0, 1.0, 3) {
            let inside = p.iter().all(|x| x.abs() < 0.5);
            assert_eq!(d.is_inside(p), inside, "{p:?}");
            assert_eq!(d.value(&p) < 0.0, inside, "{p:?}");
        }
    }

    #[test]
    fn hierarchy_matches_ground_truth_on_a_larger_mesh() {
        let d = MeshDistance::new(icosphere(4)).unwrap();
        assert_eq!(d.check().triangles, 5120);
        for p in points(200, -1.3, 1.3, 11) {
            let w = d.winding_number(p);
            let expect = if norm(p) < 0.99 {
                1.0
            } else if norm(p) > 1.0 {
                0.0
            } else {
                continue;
            };
            assert!((w - expect).abs() < 1e-9, "{p:?}: {w}");
        }
    }

    #[test]
    fn signed_distance_matches_brute_force() {
        for mesh in [cube(0.5, [0.0; 3]), icosphere(2)] {
            let d = MeshDistance::new(mesh.clone()).unwrap();
            for p in points(500, -1.4, 1.4, 5) {
                let brute = mesh
                    .triangles
                    .iter()
                    .map(|t| brute_distance(p, t.map(|v| mesh.positions[v as usize])))
                    .fold(f64::INFINITY, f64::min);
                let mut grad = [0.0; 3];
                let g = d.gradient(&p, &mut grad);
                assert!((g.abs() - brute).abs() < 1e-12, "{p:?}: {g} vs {brute}");
                assert!((norm(grad) - 1.0).abs() < 1e-12);
                // The per-thread cache (sign reuse, search hint) answers like a cold query: a
                // tiny and a larger step from p, against the brute-force sign and distance.
                for step in [1e-9, 1e-3, 0.05] {
                    let r = axpy(p, step, [0.6, -0.48, 0.64]);
                    let brute_r = mesh
                        .triangles
                        .iter()
                        .map(|t| brute_distance(r, t.map(|v| mesh.positions[v as usize])))
                        .fold(f64::INFINITY, f64::min);
                    let inside = d.winding_number_brute_force(r) > 0.5;
                    let v = d.value(&r);
                    assert!((v.abs() - brute_r).abs() < 1e-12, "{r:?}: {v} vs {brute_r}");
                    assert!(brute_r < 1e-12 || (v < 0.0) == inside, "{r:?}: {v}");
                }
                // The gradient is that of a distance: stepping along it changes g by the step.
                let h = 1e-7 * brute;
                let ahead = d.value(&axpy(p, h, grad));
                assert!((ahead - g - h).abs() < 1e-3 * h, "{p:?}");
            }
        }
    }

    #[test]
    fn sharp_edges_are_measured() {
        let cube = MeshDistance::new(cube(0.5, [0.0; 3])).unwrap();
        assert!((cube.sharpest_edge() - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert!(cube.sharpest_edge() > PV_SHARPEST_EDGE);
        // Icosphere level 2: neighbouring normals turn by about 10°.
        let ico = MeshDistance::new(icosphere(2)).unwrap();
        assert!(
            ico.sharpest_edge() < 15f64.to_radians(),
            "{}",
            ico.sharpest_edge()
        );
    }

    #[test]
    fn inverted_mesh_is_flipped_and_topology_is_counted() {
        let mut m = icosphere(1);
        for t in &mut m.triangles {
            t.swap(0, 1);
        }
        let d = MeshDistance::new(m).unwrap();
        assert!(d.flipped());
        assert!(d.value(&[0.0, 0.0, 0.0]) < 0.0);
        let c = d.check();
        assert!(c.is_closed_manifold(), "{c:?}");
        assert_eq!((c.components, c.euler), (1, 2));
        // Two disjoint cubes: 2 components, χ = 4; dropping a triangle opens the mesh.
        let a = cube(0.3, [-0.5, 0.0, 0.0]);
        let b = cube(0.3, [0.5, 0.0, 0.0]);
        let mut two = a.clone();
        two.positions.extend(&b.positions);
        two.triangles
            .extend(b.triangles.iter().map(|t| t.map(|v| v + 8)));
        let c = two.check();
        assert_eq!((c.components, c.euler), (2, 4));
        two.triangles.pop();
        let c = two.check();
        assert_eq!(c.boundary_edges, 3);
        assert!(!c.is_closed_manifold());
    }

    fn obj_text(mesh: &TriangleMesh) -> String {
        let mut s = String::from("# test\no shape\n");
        for p in &mesh.positions {
            s += &format!("v {} {} {}\n", p[0], p[1], p[2]);
        }
        for t in &mesh.triangles {
            s += &format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1);
        }
        s
    }

    /// A GLB holding `mesh` in two halves: node 0 with the first half as-is, node 1 with the
    /// second half translated by −`shift` in the buffer and +`shift` by a node translation under
    /// a parent with a uniform scale 2 whose child scales by ½ (the transforms must compose).
    fn glb_bytes(mesh: &TriangleMesh, shift: [f32; 3]) -> Vec<u8> {
        let half = mesh.triangles.len() / 2;
        let mut bin: Vec<u8> = Vec::new();
        let mut views = Vec::new();
        let mut accessors = Vec::new();
        for (part, range) in [(0usize, 0..half), (1, half..mesh.triangles.len())] {
            let tris = &mesh.triangles[range];
            let pos: Vec<[f32; 3]> = tris
                .iter()
                .flat_map(|t| t.iter())
                .map(|&v| {
                    let p = mesh.positions[v as usize];
                    let s = if part == 1 { shift } else { [0.0; 3] };
                    [0, 1, 2].map(|k| p[k] as f32 - s[k])
                })
                .collect();
            let offset = bin.len();
            for p in &pos {
                for x in p {
                    bin.extend(x.to_le_bytes());
                }
            }
            let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
            for p in &pos {
                for k in 0..3 {
                    lo[k] = lo[k].min(p[k]);
                    hi[k] = hi[k].max(p[k]);
                }
            }
            views.push(format!(
                r#"{{"buffer":0,"byteOffset":{offset},"byteLength":{}}}"#,
                pos.len() * 12
            ));
            accessors.push(format!(
                r#"{{"bufferView":{part},"componentType":5126,"count":{},"type":"VEC3","min":{lo:?},"max":{hi:?}}}"#,
                pos.len()
            ));
        }
        let json = format!(
            r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0,2]}}],
            "nodes":[{{"mesh":0}},{{"mesh":1,"translation":[{},{},{}],"scale":[0.5,0.5,0.5]}},{{"children":[1],"scale":[2,2,2]}}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}},{{"primitives":[{{"attributes":{{"POSITION":1}}}}]}}],
            "buffers":[{{"byteLength":{}}}],"bufferViews":[{}],"accessors":[{}]}}"#,
            shift[0] / 2.0,
            shift[1] / 2.0,
            shift[2] / 2.0,
            bin.len(),
            views.join(","),
            accessors.join(",")
        );
        glb_container(json, bin)
    }

    /// A GLB file (glTF 2.0 binary container): the JSON chunk and the BIN chunk, each padded to 4.
    fn glb_container(json: String, mut bin: Vec<u8>) -> Vec<u8> {
        let mut json = json.into_bytes();
        while json.len() % 4 != 0 {
            json.push(b' ');
        }
        while bin.len() % 4 != 0 {
            bin.push(0);
        }
        let total = 12 + 8 + json.len() + 8 + bin.len();
        let mut out = Vec::new();
        out.extend(b"glTF");
        out.extend(2u32.to_le_bytes());
        out.extend((total as u32).to_le_bytes());
        out.extend((json.len() as u32).to_le_bytes());
        out.extend(b"JSON");
        out.extend(&json);
        out.extend((bin.len() as u32).to_le_bytes());
        out.extend(b"BIN\0");
        out.extend(&bin);
        out
    }

    /// A tetrahedron as a GLB whose indices accessor has the given component type and type.
    fn indexed_glb(component: u32, kind: &str) -> Vec<u8> {
        let pos: [[f32; 3]; 4] = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ];
        let idx: [u32; 12] = [0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3];
        let mut bin: Vec<u8> = pos.iter().flatten().flat_map(|x| x.to_le_bytes()).collect();
        let ioff = bin.len();
        // Four bytes per index whatever the declared type: enough bytes for every case.
        bin.extend(idx.iter().flat_map(|i| i.to_le_bytes()));
        let json = format!(
            r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0]}}],"nodes":[{{"mesh":0}}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1}}]}}],
            "buffers":[{{"byteLength":{}}}],
            "bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":48}},{{"buffer":0,"byteOffset":{ioff},"byteLength":48}}],
            "accessors":[{{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[0,0,0],"max":[1,1,1]}},
            {{"bufferView":1,"componentType":{component},"count":12,"type":"{kind}"}}]}}"#,
            bin.len()
        );
        glb_container(json, bin)
    }

    /// glTF 2.0 allows only unsigned byte/short/int scalar indices; anything else is an error
    /// naming the accessor, not a panic (the `gltf` crate's reader has `unreachable!` there; found
    /// by the `fit_mesh` fuzz target).
    #[test]
    fn gltf_indices_of_a_type_the_spec_forbids_are_an_error() {
        let ok = TriangleMesh::from_gltf(&indexed_glb(5125, "SCALAR"), Path::new("t.glb")).unwrap();
        assert_eq!(ok.triangles.len(), 4);
        for (component, kind) in [
            (5120, "SCALAR"),
            (5122, "SCALAR"),
            (5126, "SCALAR"),
            (5125, "VEC2"),
        ] {
            let err = TriangleMesh::from_gltf(&indexed_glb(component, kind), Path::new("t.glb"))
                .map(|m| m.triangles.len());
            let message = format!("{}", err.expect_err("forbidden index type accepted"));
            assert!(
                message.contains("indices accessor 1"),
                "{component} {kind}: {message}"
            );
        }
    }

    /// The tetrahedron of [`indexed_glb`] (u32 indices) under the given `"scene"`/`"scenes"`/
    /// `"nodes"` members.
    fn tetra_glb(scenes_and_nodes: &str) -> Vec<u8> {
        let glb = indexed_glb(5125, "SCALAR");
        let json_len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
        let json = std::str::from_utf8(&glb[20..20 + json_len]).unwrap();
        let bin = glb[20 + json_len + 8..].to_vec();
        let json = json.replacen(
            r#""scene":0,"scenes":[{"nodes":[0]}],"nodes":[{"mesh":0}],"#,
            scenes_and_nodes,
            1,
        );
        assert!(json.contains(scenes_and_nodes), "the template changed");
        glb_container(json, bin)
    }

    /// A node reached twice in one scene (two parents, or one child listed twice) is refused: 40
    /// levels of `children: [next, next]` would instance the mesh 2⁴⁰ times from a few hundred
    /// bytes (before, `ism fit --mesh` on such a file was still running when a 20 s timeout stopped it). Scenes may share nodes: a
    /// node loaded by an earlier scene is not loaded again. Truth: the triangle counts the files
    /// were built with.
    #[test]
    fn gltf_nodes_are_instanced_once() {
        let chain: Vec<String> = (0..40)
            .map(|i| format!(r#"{{"children":[{},{}]}}"#, i + 1, i + 1))
            .chain([r#"{"mesh":0}"#.to_string()])
            .collect();
        let dag = tetra_glb(&format!(
            r#""scene":0,"scenes":[{{"nodes":[0]}}],"nodes":[{}],"#,
            chain.join(",")
        ));
        let err = TriangleMesh::from_gltf(&dag, Path::new("dag.glb"))
            .map(|m| m.triangles.len())
            .expect_err("a node with two parents accepted");
        assert!(
            format!("{err}").contains("reached twice in scene 0"),
            "{err}"
        );
        // Two parents of one mesh node, no repetition within a children list.
        let two_parents = tetra_glb(
            r#""scene":0,"scenes":[{"nodes":[0,1]}],"nodes":[{"children":[2]},{"children":[2]},{"mesh":0}],"#,
        );
        let err = TriangleMesh::from_gltf(&two_parents, Path::new("t.glb"))
            .map(|m| m.triangles.len())
            .expect_err("a node with two parents accepted");
        assert!(
            format!("{err}").contains("node 2 is reached twice"),
            "{err}"
        );
        // Two scenes sharing the mesh node, none the default: every scene is read, the node once.
        let shared = tetra_glb(r#""scenes":[{"nodes":[0]},{"nodes":[0]}],"nodes":[{"mesh":0}],"#);
        let mesh = TriangleMesh::from_gltf(&shared, Path::new("t.glb")).unwrap();
        assert_eq!(mesh.triangles.len(), 4);
        // Two nodes instancing one mesh is legal and gives both copies.
        let two = tetra_glb(
            r#""scene":0,"scenes":[{"nodes":[0,1]}],"nodes":[{"mesh":0},{"mesh":0,"translation":[5,0,0]}],"#,
        );
        let mesh = TriangleMesh::from_gltf(&two, Path::new("t.glb")).unwrap();
        assert_eq!(mesh.triangles.len(), 8);
    }

    /// `Limits` bound a mesh read: vertices and triangles (OBJ after parsing, glTF per primitive
    /// before it is added) and the file's or buffers' bytes before reading. At the limit the
    /// tetrahedron (4 vertices, 4 triangles) reads; one below, it is refused naming the limit.
    #[test]
    fn limits_refuse_larger_meshes() {
        let obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n";
        let glb = indexed_glb(5125, "SCALAR");
        let at = Limits {
            max_vertices: 4,
            max_simplices: 4,
            ..Limits::default()
        };
        let read = |bytes: &[u8], glb: bool, limits: &Limits| {
            if glb {
                TriangleMesh::from_gltf_with_limits(bytes, Path::new("t.glb"), limits)
            } else {
                TriangleMesh::from_obj_with_limits(bytes, Path::new("t.obj"), limits)
            }
            .map(|m| m.triangles.len())
        };
        for (bytes, is_glb) in [(&obj[..], false), (&glb[..], true)] {
            assert_eq!(read(bytes, is_glb, &at).unwrap(), 4);
            for (limits, name) in [
                (
                    Limits {
                        max_vertices: 3,
                        ..at
                    },
                    "max_vertices",
                ),
                (
                    Limits {
                        max_simplices: 3,
                        ..at
                    },
                    "max_simplices",
                ),
            ] {
                let err = read(bytes, is_glb, &limits).expect_err("over the limit");
                assert!(format!("{err}").contains(name), "{name}: {err}");
            }
        }
        // The GLB's one buffer declares 96 bytes.
        let err = read(
            &glb,
            true,
            &Limits {
                max_payload_bytes: 95,
                ..at
            },
        )
        .expect_err("buffers over the limit");
        assert!(format!("{err}").contains("max_payload_bytes"), "{err}");
        // Declared lengths whose sum overflows u64 are over the limit, not a panic.
        let huge = format!(
            r#"{{"asset":{{"version":"2.0"}},"buffers":[{{"byteLength":{m},"uri":"a.bin"}},{{"byteLength":{m},"uri":"b.bin"}}]}}"#,
            m = u64::MAX - 1
        );
        let err = read(huge.as_bytes(), true, &at).expect_err("overflowing buffers accepted");
        assert!(format!("{err}").contains("max_payload_bytes"), "{err}");
        // A file: its size is checked before it is read.
        let dir = std::env::temp_dir().join(format!("ism-fit-limits-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("t.obj");
        std::fs::write(&path, obj).unwrap();
        let size = obj.len() as u64;
        let load = |max_payload_bytes| {
            TriangleMesh::load_with_limits(
                &path,
                &Limits {
                    max_payload_bytes,
                    ..Limits::default()
                },
            )
            .map(|m| m.triangles.len())
        };
        assert_eq!(load(size).unwrap(), 4);
        let err = load(size - 1).expect_err("file over the limit");
        assert!(format!("{err}").contains("max_payload_bytes"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A relative buffer URI whose percent-decoding is not UTF-8 is an error, not a panic in the
    /// `gltf` crate's importer (found by the `fit_mesh` fuzz target); a valid one still reaches
    /// the file system.
    #[test]
    fn gltf_buffer_uris_that_do_not_decode_are_an_error() {
        let gltf = |uri: &str| {
            format!(
                r#"{{"asset":{{"version":"2.0"}},"buffers":[{{"byteLength":4,"uri":"{uri}"}}]}}"#
            )
        };
        let err = TriangleMesh::from_gltf(
            gltf("a%ACb.bin").as_bytes(),
            Path::new("/nonexistent/t.gltf"),
        )
        .map(|m| m.triangles.len())
        .expect_err("undecodable URI accepted");
        assert!(format!("{err}").contains("not UTF-8"), "{err}");
        let err = TriangleMesh::from_gltf(
            gltf("missing%20file.bin").as_bytes(),
            Path::new("/nonexistent/t.gltf"),
        )
        .map(|m| m.triangles.len())
        .expect_err("a missing buffer file accepted");
        assert!(format!("{err}").contains("buffers"), "{err}");
    }

    #[test]
    fn obj_and_glb_of_the_same_shape_give_the_same_function() {
        // Coordinates on a 2⁻¹² grid: exact in f32 and under the test's shifts and scalings, so
        // both formats carry the same numbers and the GLB's halves weld at their seam.
        let mut mesh = icosphere(1);
        for p in &mut mesh.positions {
            *p = p.map(|x| (x * 4096.0).round() / 4096.0);
        }
        let obj = TriangleMesh::from_obj(obj_text(&mesh).as_bytes(), Path::new("s.obj")).unwrap();
        let glb = TriangleMesh::from_gltf(&glb_bytes(&mesh, [0.25, -0.5, 1.0]), Path::new("s.glb"))
            .unwrap();
        assert_eq!(obj.check(), glb.check());
        assert_eq!(obj.check().euler, 2);
        let (a, b) = (
            MeshDistance::new(obj).unwrap(),
            MeshDistance::new(glb).unwrap(),
        );
        for p in points(300, -1.5, 1.5, 9) {
            let (va, vb) = (a.value(&p), b.value(&p));
            assert!((va - vb).abs() < 1e-6, "{p:?}: {va} vs {vb}");
        }
    }

    #[test]
    fn bad_input_is_an_error_not_a_panic() {
        let path = Path::new("bad.obj");
        for text in [
            "",
            "v 0 0 0\nv 1 0 0\nf 1 2 3\n",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n",
            "v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
            "f 1 2 3\n",
            "v a b c\nf 1 2 3\n",
        ] {
            let r = TriangleMesh::from_obj(text.as_bytes(), path);
            assert!(matches!(r, Err(FitError::Mesh { .. })), "{text:?}: {r:?}");
        }
        for bytes in [
            &b""[..],
            b"glTF\x02\x00\x00\x00",
            b"{\"asset\":{\"version\":\"2.0\"}}",
            b"{not json",
        ] {
            let r = TriangleMesh::from_gltf(bytes, Path::new("bad.glb"));
            assert!(matches!(r, Err(FitError::Mesh { .. })), "{bytes:?}: {r:?}");
        }
        // A GLB cut short.
        let glb = glb_bytes(&icosphere(0), [0.0; 3]);
        for cut in [20, glb.len() / 2, glb.len() - 4] {
            assert!(TriangleMesh::from_gltf(&glb[..cut], Path::new("cut.glb")).is_err());
        }
        // Only degenerate triangles.
        let flat = TriangleMesh {
            positions: vec![[0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]],
            triangles: vec![[0, 1, 2]],
        };
        assert!(MeshDistance::new(flat).is_err());
        assert!(TriangleMesh::load(Path::new("/nonexistent/x.obj")).is_err());
        assert!(TriangleMesh::load(Path::new("x.stl")).is_err());
    }

    #[test]
    fn mutated_files_are_errors_or_meshes_never_panics() {
        // Random byte edits of a valid GLB and OBJ (deterministic LCG). This found gltf-json's
        // unchecked accessor index, now checked before its validation runs.
        let glb = glb_bytes(&icosphere(1), [0.25, -0.5, 1.0]);
        let obj = obj_text(&cube(0.5, [0.0; 3])).into_bytes();
        let mut s: u64 = 1;
        let mut next = move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 33) as usize
        };
        for i in 0..4000 {
            let mut b = if i % 2 == 0 { glb.clone() } else { obj.clone() };
            for _ in 0..1 + next() % 4 {
                let k = next() % b.len();
                b[k] = (next() % 256) as u8;
            }
            let r = std::panic::catch_unwind(|| {
                if i % 2 == 0 {
                    TriangleMesh::from_gltf(&b, Path::new("f.glb")).map(|m| m.triangles.len())
                } else {
                    TriangleMesh::from_obj(&b, Path::new("f.obj")).map(|m| m.triangles.len())
                }
            });
            assert!(r.is_ok(), "panic on {}", String::from_utf8_lossy(&b));
        }
    }

    /// A closed prism (length 2) whose roof turns by `turn` radians at its ridge (on y = h,
    /// along z): triangles oriented outward from the centroid.
    fn roof_prism(turn: f64) -> TriangleMesh {
        // Roof faces at ±(90° − turn/2) from the base: apex angle π − turn.
        let h = 1.0 / (0.5 * (std::f64::consts::PI - turn)).tan();
        let mut positions = Vec::new();
        for z in [-1.0, 1.0] {
            positions.extend([[-1.0, 0.0, z], [1.0, 0.0, z], [0.0, h, z]]);
        }
        let quads = [[0, 1, 4, 3], [1, 2, 5, 4], [2, 0, 3, 5]];
        let mut triangles: Vec<[u32; 3]> = quads
            .iter()
            .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
            .collect();
        triangles.extend([[0, 2, 1], [3, 4, 5]]);
        let centre = [0.0, h / 3.0, 0.0];
        for t in &mut triangles {
            let [a, b, c] = t.map(|i| positions[i as usize]);
            if dot(cross(sub(b, a), sub(c, a)), sub(a, centre)) < 0.0 {
                t.swap(1, 2);
            }
        }
        TriangleMesh {
            positions,
            triangles,
        }
    }

    /// The gradient generators hold the Plantinga–Vegter consequence they are used for: in every
    /// box where they agree pairwise, the true gradients (the closest-point directions, sampled)
    /// agree pairwise too — on an 82° ridge, a torus (saddles, concave edges) and a bumpy sphere.
    /// And they are useful where the box of normals is not: small boxes on the 82° ridge pass.
    #[test]
    fn gradient_generators_agree_only_where_the_gradients_do() {
        let turn = 82f64.to_radians();
        let mut bumpy = TriangleMesh::icosphere(2, 1.0, [0.0; 3]);
        for (k, p) in bumpy.positions.iter_mut().enumerate() {
            let f = 1.0 + 0.25 * ((k * 7919) % 13) as f64 / 13.0;
            *p = p.map(|x| x * f);
        }
        let h = 1.0 / (0.5 * (std::f64::consts::PI - turn)).tan();
        for (name, mesh) in [
            ("roof", roof_prism(turn)),
            ("torus", torus_mesh(16, 8, 1.0, 0.35)),
            ("bumpy", bumpy),
        ] {
            let d = MeshDistance::new(mesh).unwrap();
            assert!(d.check().is_closed_manifold(), "{name}");
            let mut boxes: Vec<(P3, f64)> = points(300, -1.4, 1.4, 5)
                .into_iter()
                .enumerate()
                .map(|(i, lo)| (lo, [0.02, 0.08, 0.2, 0.5][i % 4]))
                .collect();
            // Boxes centred on the ridge's middle part, from 0.4 down to 0.003 wide.
            let ridge: Vec<(P3, f64)> = (0..40)
                .map(|i| {
                    let w = 0.4 * 0.85f64.powi(i);
                    let z = -0.5 + (i as f64 * 0.37) % 1.0;
                    ([-0.5 * w, h - 0.5 * w, z - 0.5 * w], w)
                })
                .collect();
            if name == "roof" {
                boxes.extend(&ridge);
            }
            let (mut agreed, mut ridge_passed) = (0, 0);
            for (i, (lo, w)) in boxes.iter().enumerate() {
                let hi = lo.map(|x| x + w);
                let mut gens = Vec::new();
                assert!(d.gradient_generators(lo, &hi, &mut gens), "{name}");
                if !crate::fit::unit_vectors_agree(3, &gens) {
                    continue;
                }
                agreed += 1;
                ridge_passed += usize::from(i >= 300);
                let grads: Vec<P3> = points(60, 0.0, 1.0, i as u64 + 1)
                    .into_iter()
                    .map(|s| {
                        let p = [0, 1, 2].map(|k| lo[k] + w * s[k]);
                        let mut g = [0.0; 3];
                        d.gradient(&p, &mut g);
                        g
                    })
                    .collect();
                for a in &grads {
                    for b in &grads {
                        assert!(dot(*a, *b) > 0.0, "{name} box {lo:?} +{w}: {a:?} {b:?}");
                    }
                }
            }
            assert!(agreed > 10, "{name}: {agreed} boxes agreed");
            if name == "roof" {
                assert!(ridge_passed > 10, "{ridge_passed} ridge boxes passed");
                // The component-wise box of the two roof normals cannot pass there.
                let (lo, w) = ridge[ridge.len() - 1];
                let hi = lo.map(|x| x + w);
                let enc = d.enclose(&lo, &hi).unwrap();
                let mut dotb = Interval::point(0.0);
                for gk in &enc.gradient {
                    dotb = dotb + *gk * *gk;
                }
                assert!(enc.value.contains(0.0) && dotb.lo <= 0.0, "{enc:?}");
            }
        }
    }

    #[test]
    fn enclosures_contain_point_values_and_gradients() {
        let d = MeshDistance::new(icosphere(2)).unwrap();
        let corners = points(60, -1.3, 1.1, 13);
        let mut passed_near_surface = 0;
        for (i, lo) in corners.iter().enumerate() {
            let w = [0.02, 0.08, 0.2][i % 3];
            let hi = lo.map(|x| x + w);
            let enc = d.enclose(lo, &hi).unwrap();
            for s in points(40, 0.0, 1.0, i as u64) {
                let p = [0, 1, 2].map(|k| lo[k] + w * s[k]);
                let mut g = [0.0; 3];
                let v = d.gradient(&p, &mut g);
                assert!(enc.value.contains(v), "{p:?}");
                if enc.value.contains(0.0) {
                    for (bound, gk) in enc.gradient.iter().zip(g) {
                        assert!(bound.contains(gk), "{p:?} {gk}: {enc:?}");
                    }
                }
            }
            if enc.value.contains(0.0) {
                let mut dot = Interval::point(0.0);
                for gk in &enc.gradient {
                    dot = dot + *gk * *gk;
                }
                passed_near_surface += usize::from(dot.lo > 0.0);
            }
        }
        // Small boxes on a smooth mesh pass the test (the enclosure is useful, not just safe).
        assert!(passed_near_surface > 0);
    }
}
