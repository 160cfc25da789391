//! Wavefront OBJ: the writer (`v`, `vn`, and `f` (triangles) or `l` (segments)) and the triangle
//! reader `ism fit --mesh` uses ([`read_obj`], through `tobj`).
//!
//! Our own writer: the format is a few lines of text, and the crate that reads it (`tobj`) does not
//! write. Numbers are printed in their shortest round-trip form (`zmij`, as `serde_json` prints
//! them: `0.5`, `1.0`, `1e-7`), so a reader gets the exact `f64`; indices by `itoa`. Both format
//! into a buffer without `fmt`'s machinery (with `write!` the text was ~11 % of a whole export's
//! CPU).

use std::io::Write;

use crate::error::MeshReadError;
use crate::import::RawMesh;
use crate::mesh::{Mesh, Primitive};
use crate::Result;

/// Reads Wavefront OBJ text as triangles (polygons are triangulated by `tobj`, materials ignored,
/// the objects concatenated), within `limits` (`max_vertices`, `max_simplices`; the text's size is
/// the caller's to bound). The vertices are as written: not welded, possibly unused; the fields and
/// tetrahedra of the [`RawMesh`] are empty.
///
/// # Errors
/// [`MeshReadError::Obj`] on a parse error, [`MeshReadError::ObjIndex`] on a vertex index out of
/// range, [`MeshReadError::TooLarge`] past a limit.
pub fn read_obj(
    bytes: &[u8],
    limits: &ism_format::io::Limits,
) -> std::result::Result<RawMesh, MeshReadError> {
    let options = tobj::LoadOptions {
        triangulate: true,
        ..Default::default()
    };
    // Materials are irrelevant to the shape: the loader is told none exist.
    let (models, _) = tobj::load_obj_buf(&mut std::io::Cursor::new(bytes), &options, |_| {
        Err(tobj::LoadError::OpenFileFailed)
    })
    .map_err(MeshReadError::Obj)?;
    let vertices: usize = models.iter().map(|m| m.mesh.positions.len() / 3).sum();
    let triangles: usize = models.iter().map(|m| m.mesh.indices.len() / 3).sum();
    MeshReadError::check_counts(vertices, triangles, limits)?;
    let mut raw = RawMesh::default();
    for model in &models {
        let m = &model.mesh;
        let base = raw.points.len();
        let count = m.positions.len() / 3;
        raw.points.extend(
            m.positions
                .chunks_exact(3)
                .map(|c| [f64::from(c[0]), f64::from(c[1]), f64::from(c[2])]),
        );
        for (t, tri) in m.indices.chunks_exact(3).enumerate() {
            if tri.iter().any(|&i| i as usize >= count) {
                return Err(MeshReadError::ObjIndex {
                    object: model.name.clone(),
                    triangle: t,
                    vertices: count,
                });
            }
            raw.triangles
                .push([0, 1, 2].map(|k| (base + tri[k] as usize) as u32));
        }
    }
    Ok(raw)
}

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
    let mut text = Text::default();
    // A block's room up front: grown push by push, the buffer was copied a dozen times.
    text.line.reserve(Text::BLOCK + Text::LINE);
    for p in &mesh.positions {
        text.vector(&mut out, b"v", p)?;
    }
    let has_normals = mesh.normals.len() == mesh.positions.len();
    if has_normals {
        for n in &mesh.normals {
            text.vector(&mut out, b"vn", n)?;
        }
    }
    match mesh.primitive {
        Primitive::Triangles => {
            for t in mesh.cell_iter() {
                text.line.push(b'f');
                for &v in t {
                    text.line.push(b' ');
                    if has_normals {
                        // `i//i`: the index formatted once, copied twice.
                        let i = text.int.format(v + 1).as_bytes();
                        text.line.extend_from_slice(i);
                        text.line.extend_from_slice(b"//");
                        text.line.extend_from_slice(i);
                    } else {
                        text.index(v + 1);
                    }
                }
                text.end(&mut out)?;
            }
        }
        Primitive::Segments => {
            for s in mesh.cell_iter() {
                text.line.push(b'l');
                for &v in s {
                    text.line.push(b' ');
                    text.index(v + 1);
                }
                text.end(&mut out)?;
            }
        }
    }
    out.write_all(&text.line)?;
    out.flush()?;
    Ok(())
}

/// Lines being formatted, written out in blocks of about 64 KiB.
#[derive(Default)]
struct Text {
    line: Vec<u8>,
    float: zmij::Buffer,
    int: itoa::Buffer,
}

impl Text {
    const BLOCK: usize = 1 << 16;
    /// Room for one more line past [`Text::BLOCK`]: the longest line the writer makes is a `vn`
    /// line (2 + 3 × (1 + 24) bytes for three shortest round-trip `f64`s) or an `f` line of three
    /// `i//i` (2 + 3 × (1 + 22) bytes for ten-digit `u32`s), plus the newline.
    const LINE: usize = 128;

    fn index(&mut self, i: u32) {
        self.line.extend_from_slice(self.int.format(i).as_bytes());
    }

    /// `tag x y z`: the shortest round-trip form of each coordinate (`NaN`, `inf` and `-inf` as
    /// Rust prints them, which no valid mesh holds).
    fn vector<W: Write>(&mut self, out: &mut W, tag: &[u8], v: &[f64; 3]) -> Result<()> {
        self.line.extend_from_slice(tag);
        for &x in v {
            self.line.push(b' ');
            if x.is_finite() {
                self.line
                    .extend_from_slice(self.float.format_finite(x).as_bytes());
            } else {
                self.line.extend_from_slice(x.to_string().as_bytes());
            }
        }
        self.end(out)
    }

    fn end<W: Write>(&mut self, out: &mut W) -> Result<()> {
        self.line.push(b'\n');
        if self.line.len() >= Self::BLOCK {
            out.write_all(&self.line)?;
            self.line.clear();
        }
        Ok(())
    }
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

    /// The reader reads what the writer wrote (the same triangles, exact positions: the writer
    /// prints shortest round-trip numbers), and names the object and triangle of a bad index.
    #[test]
    fn read_obj_reads_the_writer_and_locates_bad_indices() {
        let mesh = tetrahedron_surface();
        let mut bytes = Vec::new();
        write_obj(&mesh, Some("tet"), &mut bytes).unwrap();
        let limits = ism_format::io::Limits::default();
        let raw = read_obj(&bytes, &limits).unwrap();
        let ours: Vec<[u32; 3]> = mesh.cells.chunks(3).map(|c| [c[0], c[1], c[2]]).collect();
        assert_eq!(raw.triangles.len(), ours.len());
        for (theirs, ours) in raw.triangles.iter().zip(&ours) {
            let p = |t: &[u32; 3], k: usize| t[k] as usize;
            for k in 0..3 {
                assert_eq!(raw.points[p(theirs, k)], mesh.positions[p(ours, k)]);
            }
        }
        let bad = b"o box\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 9\n";
        match read_obj(bad, &limits) {
            Err(MeshReadError::ObjIndex { .. }) | Err(MeshReadError::Obj(_)) => {}
            other => panic!("{other:?}"),
        }
        let small = ism_format::io::Limits {
            max_simplices: 3,
            ..limits
        };
        let err = read_obj(&bytes, &small).unwrap_err();
        assert_eq!(
            err.to_string(),
            "the mesh has more than 3 triangles (limit max_simplices)"
        );
    }
}
