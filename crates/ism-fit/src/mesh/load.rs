//! Reading a triangle mesh from a file or bytes: the format by the extension, the file's size
//! against the limits, the parsing by `ism_export`'s OBJ and glTF readers (beside their writers),
//! then welding of identical positions (exporters split vertices per normal or texture
//! coordinate; the shape's edges only connect after welding).

use std::collections::HashMap;
use std::path::Path;

use ism_export::import::RawMesh;
use ism_format::io::Limits;

use super::{MeshError, TriangleMesh};
use crate::FitError;

/// [`FitError::Mesh`] for `path`.
fn mesh_error(path: &Path, source: impl Into<MeshError>) -> FitError {
    FitError::Mesh {
        path: path.to_path_buf(),
        source: source.into(),
    }
}

impl TriangleMesh {
    /// Reads `path` by its extension: `.obj` ([`ism_export::obj::read_obj`]), `.glb` or `.gltf`
    /// ([`ism_export::gltf::read_gltf`]), with the default
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
        // The format first: a file we could not parse is not worth reading.
        let gltf = match ext.as_str() {
            "obj" => false,
            "glb" | "gltf" => true,
            _ => {
                return Err(mesh_error(
                    path,
                    MeshError::UnknownFormat { extension: ext },
                ))
            }
        };
        let size = std::fs::metadata(path)
            .map_err(|e| mesh_error(path, MeshError::Io(e)))?
            .len();
        if size > limits.max_payload_bytes {
            return Err(mesh_error(
                path,
                MeshError::FileTooLarge {
                    bytes: size,
                    limit: limits.max_payload_bytes,
                },
            ));
        }
        let bytes = std::fs::read(path).map_err(|e| mesh_error(path, MeshError::Io(e)))?;
        if gltf {
            TriangleMesh::from_gltf_with_limits(&bytes, path, limits)
        } else {
            TriangleMesh::from_obj_with_limits(&bytes, path, limits)
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
        let raw = ism_export::obj::read_obj(bytes, limits).map_err(|e| mesh_error(path, e))?;
        TriangleMesh::welded(raw, path)
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
        let raw = ism_export::gltf::read_gltf(bytes, path.parent(), limits)
            .map_err(|e| mesh_error(path, e))?;
        TriangleMesh::welded(raw, path)
    }

    /// Merges vertices with bit-identical positions (exporters split vertices per normal or
    /// texture coordinate; the shape's edges only connect after welding), drops unused vertices,
    /// and rejects non-finite coordinates and empty meshes.
    fn welded(raw: RawMesh, path: &Path) -> Result<TriangleMesh, FitError> {
        let RawMesh {
            points: positions,
            triangles,
            ..
        } = raw;
        if triangles.is_empty() {
            return Err(mesh_error(path, MeshError::NoTriangles));
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
                                MeshError::NonFinite {
                                    vertex: v,
                                    point: p,
                                },
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
}
