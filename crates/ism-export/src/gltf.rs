//! glTF 2.0: the writer (`.gltf` with an embedded base64 buffer, and binary `.glb`), built with the
//! `gltf-json` data model so the document is the spec's own types, and the triangle reader
//! `ism fit --mesh` uses ([`read_gltf`], through the `gltf` crate, with the checks that keep its
//! panics on hostile input out of reach).
//!
//! Writer layout: //! one buffer holding positions (`VEC3` f32, with the exact f32 `min`/`max` the spec
//! requires), unit normals (`VEC3` f32), then indices (`SCALAR` u32); one mesh with one primitive
//! (`TRIANGLES`, or `LINES` for 2D curves), one node, one scene. Every section is a multiple of 4
//! bytes, so every accessor is aligned.

use std::borrow::Cow;
use std::io::Write;
use std::path::Path;

use base64::Engine;
use gltf_json as json;
use json::validation::{Checked, USize64};

use ism_format::io::Limits;

use crate::error::MeshReadError;
use crate::import::RawMesh;
use crate::mesh::{cross, dot, Mesh, Primitive};
use crate::{Error, Result};

/// Which glTF container to write.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GltfContainer {
    /// JSON `.gltf` with the buffer embedded as a `data:` URI.
    Text,
    /// Binary `.glb`: JSON chunk plus BIN chunk.
    Binary,
}

/// Writes `mesh` as glTF 2.0.
///
/// # Errors
/// [`Error::TooLarge`] past the 4 GiB limit of a GLB, [`Error::Gltf`] if serialization fails,
/// [`Error::Io`] when the writer fails.
pub fn write_gltf<W: Write>(
    mesh: &Mesh,
    name: Option<&str>,
    container: GltfContainer,
    mut out: W,
) -> Result<()> {
    let (root, bin) = document(mesh, name, container)?;
    match container {
        GltfContainer::Text => {
            root.to_writer_pretty(&mut out)
                .map_err(|e| Error::Gltf(e.to_string()))?;
            writeln!(out)?;
        }
        GltfContainer::Binary => {
            let json_bytes =
                json::serialize::to_vec(&root).map_err(|e| Error::Gltf(e.to_string()))?;
            let total = 12 + 8 + pad4(json_bytes.len()) + 8 + pad4(bin.len());
            let length = u32::try_from(total).map_err(|_| Error::TooLarge {
                format: "glb",
                what: format!("{total} bytes exceed the 4 GiB GLB limit"),
            })?;
            let glb = gltf::binary::Glb {
                header: gltf::binary::Header {
                    magic: *b"glTF",
                    version: 2,
                    length,
                },
                json: Cow::Owned(json_bytes),
                bin: Some(Cow::Owned(bin)),
            };
            glb.to_writer(&mut out).map_err(|e| match e {
                gltf::Error::Io(io) => Error::io(io),
                other => Error::Gltf(other.to_string()),
            })?;
        }
    }
    out.flush()?;
    Ok(())
}

fn pad4(n: usize) -> usize {
    n.div_ceil(4) * 4
}

/// Builds the glTF root and the binary buffer (already padded to 4 bytes).
fn document(
    mesh: &Mesh,
    name: Option<&str>,
    container: GltfContainer,
) -> Result<(json::Root, Vec<u8>)> {
    let nv = mesh.num_vertices();
    let arity = mesh.primitive.arity();
    if u32::try_from(nv).is_err() {
        return Err(Error::TooLarge {
            format: "glTF",
            what: format!("{nv} vertices"),
        });
    }
    let mut root = json::Root {
        asset: json::Asset {
            generator: Some(format!("ism-export {}", env!("CARGO_PKG_VERSION"))),
            ..Default::default()
        },
        ..Default::default()
    };
    let mut bin: Vec<u8> = Vec::with_capacity(nv * 24 + mesh.cells.len() * 4);
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in &mesh.positions {
        for k in 0..3 {
            let x = p[k] as f32;
            lo[k] = lo[k].min(x);
            hi[k] = hi[k].max(x);
            bin.extend_from_slice(&x.to_le_bytes());
        }
    }
    let normals_offset = bin.len();
    for n in &mesh.normals {
        for x in unit_f32(*n) {
            bin.extend_from_slice(&x.to_le_bytes());
        }
    }
    let has_normals = mesh.normals.len() == nv && nv > 0;
    let indices_offset = bin.len();
    for &i in &mesh.cells {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    let byte_length = bin.len();
    bin.resize(pad4(byte_length), 0);

    let empty = mesh.num_cells() == 0;
    if !empty {
        let uri = match container {
            GltfContainer::Text => Some(format!(
                "data:application/octet-stream;base64,{}",
                base64::engine::general_purpose::STANDARD.encode(&bin[..byte_length])
            )),
            GltfContainer::Binary => None,
        };
        let buffer = root.push(json::Buffer {
            byte_length: USize64::from(byte_length),
            name: None,
            uri,
            extensions: None,
            extras: Default::default(),
        });
        let view =
            |root: &mut json::Root, offset: usize, length: usize, target: json::buffer::Target| {
                root.push(json::buffer::View {
                    buffer,
                    byte_length: USize64::from(length),
                    byte_offset: Some(USize64::from(offset)),
                    byte_stride: None,
                    name: None,
                    target: Some(Checked::Valid(target)),
                    extensions: None,
                    extras: Default::default(),
                })
            };
        let accessor =
            |root: &mut json::Root,
             view: json::Index<json::buffer::View>,
             count: usize,
             component: json::accessor::ComponentType,
             type_: json::accessor::Type,
             bounds: Option<(serde_json::Value, serde_json::Value)>| {
                let (min, max) = match bounds {
                    Some((a, b)) => (Some(a), Some(b)),
                    None => (None, None),
                };
                root.push(json::Accessor {
                    buffer_view: Some(view),
                    byte_offset: None,
                    count: USize64::from(count),
                    component_type: Checked::Valid(json::accessor::GenericComponentType(component)),
                    extensions: None,
                    extras: Default::default(),
                    type_: Checked::Valid(type_),
                    min,
                    max,
                    name: None,
                    normalized: false,
                    sparse: None,
                })
            };
        use json::accessor::{ComponentType, Type};
        use json::buffer::Target;
        let pos_view = view(&mut root, 0, nv * 12, Target::ArrayBuffer);
        let positions = accessor(
            &mut root,
            pos_view,
            nv,
            ComponentType::F32,
            Type::Vec3,
            Some((serde_json::json!(lo), serde_json::json!(hi))),
        );
        let mut attributes = std::collections::BTreeMap::new();
        attributes.insert(Checked::Valid(json::mesh::Semantic::Positions), positions);
        if has_normals {
            let nrm_view = view(&mut root, normals_offset, nv * 12, Target::ArrayBuffer);
            let normals = accessor(
                &mut root,
                nrm_view,
                nv,
                ComponentType::F32,
                Type::Vec3,
                None,
            );
            attributes.insert(Checked::Valid(json::mesh::Semantic::Normals), normals);
        }
        let idx_view = view(
            &mut root,
            indices_offset,
            mesh.cells.len() * 4,
            Target::ElementArrayBuffer,
        );
        let indices = accessor(
            &mut root,
            idx_view,
            mesh.cells.len(),
            ComponentType::U32,
            Type::Scalar,
            None,
        );
        let mode = match mesh.primitive {
            Primitive::Triangles => json::mesh::Mode::Triangles,
            Primitive::Segments => json::mesh::Mode::Lines,
        };
        debug_assert_eq!(mesh.cells.len() % arity, 0);
        let gmesh = root.push(json::Mesh {
            extensions: None,
            extras: Default::default(),
            name: name.map(str::to_string),
            primitives: vec![json::mesh::Primitive {
                attributes,
                extensions: None,
                extras: Default::default(),
                indices: Some(indices),
                material: None,
                mode: Checked::Valid(mode),
                targets: None,
            }],
            weights: None,
        });
        let node = root.push(json::Node {
            mesh: Some(gmesh),
            name: name.map(str::to_string),
            ..Default::default()
        });
        let scene = root.push(json::Scene {
            extensions: None,
            extras: Default::default(),
            name: None,
            nodes: vec![node],
        });
        root.scene = Some(scene);
    } else {
        // An empty shape is still a valid asset: no scene at all (a scene must list at least one
        // node).
        bin.clear();
    }
    Ok((root, bin))
}

/// The normal as f32 with unit length in f32 arithmetic (the validator checks `|n| = 1` on the
/// stored floats). A zero normal, which a valid model never produces on `O`, becomes +z so the
/// file stays valid.
fn unit_f32(n: [f64; 3]) -> [f32; 3] {
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if len.is_nan() || len <= 0.0 || !len.is_finite() {
        return [0.0, 0.0, 1.0];
    }
    [
        (n[0] / len) as f32,
        (n[1] / len) as f32,
        (n[2] / len) as f32,
    ]
}

/// Bytes of a GLB header: magic, version, total length (glTF 2.0 §4.4.3).
const GLB_HEADER_BYTES: u32 = 12;

/// Reads glTF JSON or binary GLB as triangles: every triangle primitive (triangles, strips, fans)
/// of every mesh instanced by the nodes of the default scene (all scenes if none is marked default;
/// every mesh untransformed if there is no scene), with the nodes' transforms applied (mirroring
/// ones flip the triangles back to counter-clockwise). Buffers referenced by relative URIs are read
/// from `base` (the file's directory). Within `limits`: the buffers' declared lengths together
/// against `max_payload_bytes` before any is read, the vertices and triangles gathered so far
/// against `max_vertices` and `max_simplices` before each primitive is added. The vertices are as
/// stored, not welded; the fields and tetrahedra of the [`RawMesh`] are empty.
///
/// # Errors
/// A [`MeshReadError`] naming the mesh, primitive, accessor, buffer, node or scene: a parse or
/// validation error, a missing buffer, an index out of range, a node reached twice, a limit passed.
pub fn read_gltf(
    bytes: &[u8],
    base: Option<&Path>,
    limits: &Limits,
) -> std::result::Result<RawMesh, MeshReadError> {
    // gltf 1.4.1's `Glb::from_slice` subtracts the 12-byte header from the declared total length
    // unchecked (src/binary.rs:252): a length below 12 panics with overflow checks on and wraps to
    // a huge length (then an error) without. Refuse it first (found by the `fit_mesh` fuzz target).
    if let Some(length) = bytes
        .strip_prefix(b"glTF")
        .and_then(|rest| rest.get(4..8))
        .map(|l| u32::from_le_bytes([l[0], l[1], l[2], l[3]]))
    {
        if length < GLB_HEADER_BYTES {
            return Err(MeshReadError::GlbLength { length });
        }
    }
    let raw = ::gltf::Gltf::from_slice_without_validation(bytes).map_err(MeshReadError::Gltf)?;
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
                return Err(MeshReadError::GltfAccessor {
                    mesh: mi,
                    primitive: pi,
                    accessor: a.value(),
                });
            }
        }
    }
    let document =
        ::gltf::Document::from_json(raw.document.into_json()).map_err(MeshReadError::Gltf)?;
    // gltf 1.4.1's `import_buffers` unwraps the percent-decoding of a relative buffer URI
    // (src/import.rs:50) and panics when the result is not UTF-8: refuse such a URI first, with
    // the same decoder (found by the `fit_mesh` fuzz target).
    for buffer in document.buffers() {
        if let ::gltf::buffer::Source::Uri(uri) = buffer.source() {
            if !uri.contains(':') && urlencoding::decode(uri).is_err() {
                return Err(MeshReadError::GltfBufferUri {
                    buffer: buffer.index(),
                });
            }
        }
    }
    // Saturating: hostile lengths near u64::MAX must not overflow the sum (a panic in debug
    // builds, a wrapped sum that passes the check in release).
    let declared = document
        .buffers()
        .fold(0u64, |sum, b| sum.saturating_add(b.length() as u64));
    if declared > limits.max_payload_bytes {
        return Err(MeshReadError::GltfBufferBytes {
            declared,
            limit: limits.max_payload_bytes,
        });
    }
    let buffers =
        ::gltf::import_buffers(&document, base, raw.blob).map_err(MeshReadError::GltfBuffers)?;
    let mut out = RawMesh::default();
    let doc = &document;
    let scenes: Vec<::gltf::Scene> = match doc.default_scene() {
        Some(s) => vec![s],
        None => doc.scenes().collect(),
    };
    if scenes.is_empty() {
        for mesh in doc.meshes() {
            add_mesh(&mesh, &IDENTITY, &buffers, limits, &mut out)?;
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
        let mut stack: Vec<(::gltf::Node, [[f64; 4]; 4], usize)> =
            scene.nodes().map(|n| (n, IDENTITY, 0)).collect();
        while let Some((node, parent, depth)) = stack.pop() {
            if depth > MAX_NODE_DEPTH {
                return Err(MeshReadError::GltfNodeDepth {
                    max: MAX_NODE_DEPTH,
                });
            }
            match loaded_by[node.index()] {
                Some(s) if s == si => {
                    return Err(MeshReadError::GltfNodeTwice {
                        node: node.index(),
                        scene: si,
                    });
                }
                Some(_) => continue,
                None => loaded_by[node.index()] = Some(si),
            }
            let local = node.transform().matrix().map(|c| c.map(f64::from));
            let world = mat_mul(&parent, &local);
            if let Some(mesh) = node.mesh() {
                add_mesh(&mesh, &world, &buffers, limits, &mut out)?;
            }
            stack.extend(node.children().map(|c| (c, world, depth + 1)));
        }
    }
    Ok(out)
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

/// `m · (p, 1)`, the affine part of a column-major transform applied to a point.
fn transform(m: &[[f64; 4]; 4], p: [f32; 3]) -> [f64; 3] {
    let p = p.map(f64::from);
    [0, 1, 2].map(|r| m[0][r] * p[0] + m[1][r] * p[1] + m[2][r] * p[2] + m[3][r])
}

/// Appends the triangle primitives of `mesh`, placed by `world`, to `out`.
fn add_mesh(
    mesh: &::gltf::Mesh,
    world: &[[f64; 4]; 4],
    buffers: &[::gltf::buffer::Data],
    limits: &Limits,
    out: &mut RawMesh,
) -> std::result::Result<(), MeshReadError> {
    use ::gltf::mesh::Mode;
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
        // glTF 2.0 §3.7.2.1: POSITION MUST be float VEC3. The `gltf` crate's position reader
        // assumes it (a debug assertion on the element size, else other bytes read as
        // positions), so check first (found by the `fit_mesh` fuzz target).
        if let Some(acc) = primitive.get(&::gltf::Semantic::Positions) {
            use ::gltf::accessor::{DataType, Dimensions};
            if acc.data_type() != DataType::F32 || acc.dimensions() != Dimensions::Vec3 {
                return Err(MeshReadError::GltfPositionType {
                    mesh: mesh.index(),
                    primitive: pi,
                    accessor: acc.index(),
                    data_type: acc.data_type(),
                    dimensions: acc.dimensions(),
                });
            }
        }
        let reader = primitive.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
        let Some(positions) = reader.read_positions() else {
            return Err(MeshReadError::GltfNoPositions {
                mesh: mesh.index(),
                primitive: pi,
            });
        };
        // glTF 2.0 §3.7.2.1: an indices accessor MUST hold unsigned byte, short or int scalars. The
        // `gltf` crate's index reader assumes it (`unreachable!` otherwise), so check first.
        if let Some(acc) = primitive.indices() {
            use ::gltf::accessor::{DataType, Dimensions};
            if !matches!(
                acc.data_type(),
                DataType::U8 | DataType::U16 | DataType::U32
            ) || acc.dimensions() != Dimensions::Scalar
            {
                return Err(MeshReadError::GltfIndexType {
                    mesh: mesh.index(),
                    primitive: pi,
                    accessor: acc.index(),
                    data_type: acc.data_type(),
                    dimensions: acc.dimensions(),
                });
            }
        }
        let base = out.points.len();
        // Checked before anything is added: the positions' length is their accessor's count.
        MeshReadError::check_counts(base + positions.len(), out.triangles.len(), limits)?;
        out.points.extend(positions.map(|p| transform(world, p)));
        let count = out.points.len() - base;
        let indices: Vec<u32> = match reader.read_indices() {
            Some(i) => i.into_u32().collect(),
            None => (0..count as u32).collect(),
        };
        if let Some(&bad) = indices.iter().find(|&&i| i as usize >= count) {
            return Err(MeshReadError::GltfIndexRange {
                mesh: mesh.index(),
                primitive: pi,
                index: bad,
                vertices: count,
            });
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
        MeshReadError::check_counts(out.points.len(), out.triangles.len() + tris.len(), limits)?;
        for t in tris {
            let mut t = t.map(|i| (base + i as usize) as u32);
            if mirrored {
                t.swap(1, 2);
            }
            out.triangles.push(t);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::tests::tetrahedron_surface;

    fn read_back(bytes: &[u8]) -> gltf::Gltf {
        gltf::Gltf::from_slice(bytes).expect("gltf crate parses and validates the document")
    }

    #[test]
    fn glb_and_gltf_read_back_with_positions_bounds_and_indices() {
        let mesh = tetrahedron_surface();
        for container in [GltfContainer::Binary, GltfContainer::Text] {
            let mut bytes = Vec::new();
            write_gltf(&mesh, Some("tet"), container, &mut bytes).unwrap();
            if container == GltfContainer::Binary {
                assert_eq!(bytes.len() % 4, 0, "GLB output is 4-byte aligned");
            }
            let doc = read_back(&bytes);
            let m = doc.meshes().next().unwrap();
            let prim = m.primitives().next().unwrap();
            assert_eq!(prim.mode(), gltf::mesh::Mode::Triangles);
            let pos = prim.get(&gltf::Semantic::Positions).unwrap();
            assert_eq!(pos.count(), 4);
            assert_eq!(pos.min().unwrap(), serde_json::json!([0.0, 0.0, 0.0]));
            assert_eq!(pos.max().unwrap(), serde_json::json!([1.0, 1.0, 1.0]));
            assert_eq!(prim.indices().unwrap().count(), 12);
            assert_eq!(doc.scenes().next().unwrap().nodes().count(), 1);
            let bin = match container {
                GltfContainer::Binary => doc.blob.clone().unwrap(),
                GltfContainer::Text => {
                    let uri = match doc.buffers().next().unwrap().source() {
                        gltf::buffer::Source::Uri(u) => u.to_string(),
                        gltf::buffer::Source::Bin => panic!("text glTF must embed its buffer"),
                    };
                    let b64 = uri
                        .strip_prefix("data:application/octet-stream;base64,")
                        .unwrap();
                    base64::engine::general_purpose::STANDARD
                        .decode(b64)
                        .unwrap()
                }
            };
            let view = prim.indices().unwrap().view().unwrap();
            let idx: Vec<u32> = bin[view.offset()..view.offset() + view.length()]
                .chunks_exact(4)
                .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            assert_eq!(idx, mesh.cells);
        }
    }

    #[test]
    fn empty_mesh_gives_an_asset_without_scene() {
        let mesh = Mesh::new(3, Primitive::Triangles);
        let mut bytes = Vec::new();
        write_gltf(&mesh, None, GltfContainer::Binary, &mut bytes).unwrap();
        let doc = read_back(&bytes);
        assert_eq!(doc.scenes().count(), 0);
        assert_eq!(doc.meshes().count(), 0);
    }

    /// The reader reads what the writer wrote, in both containers: the same triangles on the
    /// same (f32-rounded) positions.
    #[test]
    fn read_gltf_reads_the_writer() {
        let mesh = tetrahedron_surface();
        for container in [GltfContainer::Binary, GltfContainer::Text] {
            let mut bytes = Vec::new();
            write_gltf(&mesh, Some("tet"), container, &mut bytes).unwrap();
            let raw = read_gltf(&bytes, None, &Limits::default()).unwrap();
            assert_eq!(raw.triangles.len() * 3, mesh.cells.len(), "{container:?}");
            for (t, c) in raw.triangles.iter().zip(mesh.cells.chunks(3)) {
                for k in 0..3 {
                    let ours = mesh.positions[c[k] as usize].map(|x| f64::from(x as f32));
                    assert_eq!(raw.points[t[k] as usize], ours, "{container:?}");
                }
            }
        }
        let err = read_gltf(b"{", None, &Limits::default()).unwrap_err();
        assert!(matches!(err, MeshReadError::Gltf(_)), "{err:?}");
    }

    /// A POSITION accessor of another element or component type is refused with its mesh,
    /// primitive and accessor (the writer's `.gltf` with that accessor's `type` or
    /// `componentType` changed), not read as other bytes or stopped by a debug assertion.
    #[test]
    fn position_accessor_of_another_type_is_refused() {
        let mut bytes = Vec::new();
        write_gltf(
            &tetrahedron_surface(),
            Some("tet"),
            GltfContainer::Text,
            &mut bytes,
        )
        .unwrap();
        let json: serde_json::Value = serde_json::from_slice(&bytes).unwrap();
        let position = json["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
            .as_u64()
            .unwrap() as usize;
        for (key, value) in [
            ("type", serde_json::json!("VEC4")),
            ("type", serde_json::json!("VEC2")),
            ("componentType", serde_json::json!(5125)),
        ] {
            let mut j = json.clone();
            j["accessors"][position][key] = value.clone();
            let text = serde_json::to_vec(&j).unwrap();
            let err = read_gltf(&text, None, &Limits::default()).unwrap_err();
            assert!(
                matches!(err, MeshReadError::GltfPositionType { mesh: 0, primitive: 0, accessor, .. } if accessor == position),
                "{key} {value}: {err:?}"
            );
        }
        // Unchanged, it reads.
        assert!(read_gltf(&bytes, None, &Limits::default()).is_ok());
    }

    /// A GLB whose header declares a total length below its own 12 bytes is an error, not a
    /// panic (the `fit_mesh` fuzz target's input: magic, version 0x3a00ff, length 0); lengths
    /// from 12 on reach the `gltf` crate, which reports the short file.
    #[test]
    fn glb_length_below_the_header_is_refused() {
        let mut bytes = b"glTF\xff\x00\x3a\x00".to_vec();
        bytes.extend([0u8; 4]);
        bytes.extend([0u8; 30]);
        for length in [0u32, 1, 11, 12, 13, u32::MAX] {
            bytes[8..12].copy_from_slice(&length.to_le_bytes());
            let err = read_gltf(&bytes, None, &Limits::default()).unwrap_err();
            if length < 12 {
                assert!(
                    matches!(err, MeshReadError::GlbLength { length: l } if l == length),
                    "{length}: {err:?}"
                );
            } else {
                assert!(matches!(err, MeshReadError::Gltf(_)), "{length}: {err:?}");
            }
        }
    }
}
