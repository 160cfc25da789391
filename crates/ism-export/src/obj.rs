//! Wavefront OBJ writer: `v`, `vn`, and `f` (triangles) or `l` (segments).
//!
//! Our own writer: the format is a few lines of text, and the crate that reads it (`tobj`) does not
//! write. Numbers are printed in Rust's shortest round-trip form, so a reader gets the exact `f64`.

use std::io::Write;

use crate::mesh::{Mesh, Primitive};
use crate::Result;

/// Writes `mesh` as OBJ text. Vertex `i` of the mesh is OBJ vertex `i + 1`, with normal `i + 1`.
///
/// # Errors
/// [`crate::Error::Io`] when the writer fails.
pub fn write_obj<W: Write>(mesh: &Mesh, name: Option<&str>, mut out: W) -> Result<()> {
    writeln!(
        out,
        "# ISM export: {} vertices, {} cells",
        mesh.num_vertices(),
        mesh.num_cells()
    )?;
    if let Some(name) = name {
        // Object names end at the line; keep them on one.
        let clean: String = name
            .chars()
            .map(|c| if c.is_control() { ' ' } else { c })
            .collect();
        writeln!(out, "o {clean}")?;
    }
    for p in &mesh.positions {
        writeln!(out, "v {} {} {}", p[0], p[1], p[2])?;
    }
    let has_normals = mesh.normals.len() == mesh.positions.len();
    if has_normals {
        for n in &mesh.normals {
            writeln!(out, "vn {} {} {}", n[0], n[1], n[2])?;
        }
    }
    match mesh.primitive {
        Primitive::Triangles => {
            for t in mesh.cell_iter() {
                let [a, b, c] = [t[0] + 1, t[1] + 1, t[2] + 1];
                if has_normals {
                    writeln!(out, "f {a}//{a} {b}//{b} {c}//{c}")?;
                } else {
                    writeln!(out, "f {a} {b} {c}")?;
                }
            }
        }
        Primitive::Segments => {
            for s in mesh.cell_iter() {
                writeln!(out, "l {} {}", s[0] + 1, s[1] + 1)?;
            }
        }
    }
    out.flush()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::tests::tetrahedron_surface;

    #[test]
    fn tobj_reads_back_positions_normals_and_faces() {
        let mesh = tetrahedron_surface();
        let mut bytes = Vec::new();
        write_obj(&mesh, Some("tet"), &mut bytes).unwrap();
        let mut reader = std::io::BufReader::new(&bytes[..]);
        let (models, _) = tobj::load_obj_buf(&mut reader, &tobj::LoadOptions::default(), |_| {
            Err(tobj::LoadError::OpenFileFailed)
        })
        .unwrap();
        assert_eq!(models.len(), 1);
        let m = &models[0].mesh;
        assert_eq!(models[0].name, "tet");
        assert_eq!(m.positions.len(), 12);
        assert_eq!(m.normals.len(), 12);
        // tobj renumbers vertices in order of first use: compare the triangles' corner positions.
        let corners = |i: u32| {
            m.positions[3 * i as usize..3 * i as usize + 3]
                .iter()
                .map(|&x| f64::from(x))
                .collect::<Vec<_>>()
        };
        assert_eq!(m.indices.len(), mesh.cells.len());
        for (&theirs, &ours) in m.indices.iter().zip(&mesh.cells) {
            assert_eq!(corners(theirs), mesh.positions[ours as usize].to_vec());
        }
    }
}
