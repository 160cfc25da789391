//! glTF 2.0 writer (`.gltf` with an embedded base64 buffer, and binary `.glb`), built with the
//! `gltf-json` data model so the document is the spec's own types.
//!
//! Layout: one buffer holding positions (`VEC3` f32, with the exact f32 `min`/`max` the spec
//! requires), unit normals (`VEC3` f32), then indices (`SCALAR` u32); one mesh with one primitive
//! (`TRIANGLES`, or `LINES` for 2D curves), one node, one scene. Every section is a multiple of 4
//! bytes, so every accessor is aligned.

use std::borrow::Cow;
use std::io::Write;

use base64::Engine;
use gltf_json as json;
use json::validation::{Checked, USize64};

use crate::mesh::{Mesh, Primitive};
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
}
