//! VTK writers: legacy `.vtk` (ASCII, version 4.2) and XML `.vtu` (binary, raw appended arrays),
//! for the extracted surface and for the complex itself as Bézier cells.
//!
//! Our own writer rather than `vtkio`: vtkio's current line is 0.7 release candidates on a forked
//! XML crate, and what we need (one unstructured grid, a handful of arrays, active-attribute
//! declarations such as `RationalWeights`) is a few hundred lines we can test directly against
//! the Python `vtk` reader.

use std::io::Write;

use crate::mesh::{Mesh, Primitive};
use crate::Result;

/// VTK cell type ids (`vtkCellType.h`).
pub mod cell_type {
    /// `VTK_LINE`
    pub const LINE: u8 = 3;
    /// `VTK_TRIANGLE`
    pub const TRIANGLE: u8 = 5;
    /// `VTK_TETRA`
    pub const TETRA: u8 = 10;
    /// `VTK_BEZIER_TRIANGLE`
    pub const BEZIER_TRIANGLE: u8 = 76;
    /// `VTK_BEZIER_TETRAHEDRON`
    pub const BEZIER_TETRAHEDRON: u8 = 78;
}

/// How [`UnstructuredGrid::write_vtu_with`] stores the arrays of a `.vtu`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum VtuCompression {
    /// Raw bytes (the default: the fastest to write and to read).
    #[default]
    None,
    /// zlib (`vtkZLibDataCompressor`) at [`VTU_ZLIB_LEVEL`], block by block as VTK writes it
    /// (VTK's XML writers compress with zlib by default).
    Zlib,
}

/// Uncompressed size of a compressed `.vtu` array's blocks: `vtkXMLWriter`'s default, 32 KiB.
pub const VTU_BLOCK: usize = 1 << 15;

/// zlib level of [`VtuCompression::Zlib`]: VTK's default (`vtkXMLWriter`'s `CompressionLevel`, 5
/// in VTK 9.7, whose writers also default to zlib and 32 KiB blocks). On the fitted torus's volume file (10.5 MB raw, zlib of 32 KiB blocks,
/// 2026-12-07): level 1 3.25×, level 5 3.52×, level 6 (zlib's default) 3.57× smaller, for 0.09 /
/// 0.17 / 0.32 CPU-s (BENCHMARKS.md, issue 19, session 49).
pub const VTU_ZLIB_LEVEL: u32 = 5;

/// Values of a data array: floating point or integer.
#[derive(Clone, Debug, PartialEq)]
pub enum ArrayValues {
    /// `Float64` / `double`.
    Float(Vec<f64>),
    /// `Int64` / `vtkIdType`-sized integers.
    Int(Vec<i64>),
}

impl ArrayValues {
    fn len(&self) -> usize {
        match self {
            ArrayValues::Float(v) => v.len(),
            ArrayValues::Int(v) => v.len(),
        }
    }
}

/// The role a point-data array plays (VTK's active attributes).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Attribute {
    /// A plain named array.
    None,
    /// The active scalars (what filters contour by default).
    Scalars,
    /// The active normals.
    Normals,
    /// Rational Bézier weights; VTK honours them only when declared as this attribute.
    RationalWeights,
}

/// A named data array with `components` values per tuple.
#[derive(Clone, Debug, PartialEq)]
pub struct DataArray {
    /// Array name.
    pub name: String,
    /// Values per tuple.
    pub components: usize,
    /// The values, tuple-major.
    pub values: ArrayValues,
    /// Active-attribute role.
    pub attribute: Attribute,
}

/// An unstructured grid, the one dataset both writers produce.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct UnstructuredGrid {
    /// Point coordinates.
    pub points: Vec<[f64; 3]>,
    /// Cell connectivity, flat.
    pub connectivity: Vec<u64>,
    /// End offset of each cell in `connectivity`.
    pub offsets: Vec<u64>,
    /// VTK cell type of each cell.
    pub types: Vec<u8>,
    /// Per-point arrays.
    pub point_data: Vec<DataArray>,
    /// Per-cell arrays.
    pub cell_data: Vec<DataArray>,
}

impl UnstructuredGrid {
    /// Appends a cell.
    pub fn push_cell(&mut self, cell_type: u8, ids: impl IntoIterator<Item = u64>) {
        self.connectivity.extend(ids);
        self.offsets.push(self.connectivity.len() as u64);
        self.types.push(cell_type);
    }

    /// Number of cells.
    pub fn num_cells(&self) -> usize {
        self.types.len()
    }

    /// The surface or curve of `mesh` as a grid of triangles or lines, with point arrays `Normals`
    /// (active normals), `GradientNorm` (`|∇F|`, active scalars) and `SourceSimplex`, and the
    /// cell array `SourceSimplex`.
    pub fn from_mesh(mesh: &Mesh) -> UnstructuredGrid {
        let mut g = UnstructuredGrid {
            points: mesh.positions.clone(),
            ..Default::default()
        };
        let t = match mesh.primitive {
            Primitive::Triangles => cell_type::TRIANGLE,
            Primitive::Segments => cell_type::LINE,
        };
        for c in mesh.cell_iter() {
            g.push_cell(t, c.iter().map(|&i| u64::from(i)));
        }
        if mesh.normals.len() == mesh.positions.len() {
            g.point_data.push(DataArray {
                name: "Normals".into(),
                components: 3,
                values: ArrayValues::Float(mesh.normals.iter().flatten().copied().collect()),
                attribute: Attribute::Normals,
            });
        }
        if mesh.gradient_norm.len() == mesh.positions.len() {
            g.point_data.push(DataArray {
                name: "GradientNorm".into(),
                components: 1,
                values: ArrayValues::Float(mesh.gradient_norm.clone()),
                attribute: Attribute::Scalars,
            });
        }
        if mesh.vertex_simplex.len() == mesh.positions.len() {
            g.point_data.push(DataArray {
                name: "SourceSimplex".into(),
                components: 1,
                values: ArrayValues::Int(
                    mesh.vertex_simplex.iter().map(|&s| i64::from(s)).collect(),
                ),
                attribute: Attribute::None,
            });
        }
        if mesh.cell_simplex.len() == mesh.num_cells() {
            g.cell_data.push(DataArray {
                name: "SourceSimplex".into(),
                components: 1,
                values: ArrayValues::Int(mesh.cell_simplex.iter().map(|&s| i64::from(s)).collect()),
                attribute: Attribute::None,
            });
        }
        g
    }

    /// Writes the XML `.vtu` form: every data array binary, in one raw `AppendedData` section
    /// (`format="appended"`, `encoding="raw"`, little-endian, `UInt64` size headers, uncompressed)
    /// — what `vtkXMLUnstructuredGridWriter` writes in its default appended mode with
    /// `EncodeAppendedDataOff()` and no compressor (its default base64-encodes and zlib-compresses
    /// them: smaller, slower to write and read); read by VTK, ParaView, meshio and
    /// [`crate::import`]. Binary values are the stored bits, written without formatting a number:
    /// 0.57–0.76× the bytes of the decimal text, and VTK reads the 1 M-tet model's volume file with
    /// 58× less CPU (BENCHMARKS.md, issue 19, session 45); the legacy `.vtk` form stays ASCII for
    /// readers who want text. [`Self::write_vtu_with`] compresses the arrays.
    ///
    /// # Errors
    /// [`crate::Error::Io`] when the writer fails.
    pub fn write_vtu<W: Write>(&self, out: W) -> Result<()> {
        self.write_vtu_with(out, VtuCompression::None)
    }

    /// [`Self::write_vtu`], the arrays stored as `compression` says: with
    /// [`VtuCompression::Zlib`] each array is cut in [`VTU_BLOCK`]-byte blocks compressed
    /// separately (in parallel) behind VTK's compression header (`compressor=
    /// "vtkZLibDataCompressor"`, `UInt64` header words: block count, block size, last block's
    /// size (0 when full), each block's compressed size), as `vtkXMLWriter` writes them and
    /// [`crate::import`], VTK, ParaView and meshio read them.
    ///
    /// # Errors
    /// [`crate::Error::Io`] when the writer fails.
    pub fn write_vtu_with<W: Write>(&self, mut out: W, compression: VtuCompression) -> Result<()> {
        // Every array in file order: point data, cell data, points, connectivity, offsets, types.
        let payloads: Vec<Payload<'_>> = self
            .point_data
            .iter()
            .chain(&self.cell_data)
            .map(Payload::of)
            .chain([
                Payload::Points(&self.points),
                Payload::Unsigned(&self.connectivity),
                Payload::Unsigned(&self.offsets),
                Payload::Bytes(&self.types),
            ])
            .collect();
        let compressed: Option<Vec<Vec<u8>>> = match compression {
            VtuCompression::None => None,
            VtuCompression::Zlib => Some(
                payloads
                    .iter()
                    .map(Payload::zlib)
                    .collect::<std::io::Result<_>>()?,
            ),
        };
        // Each array's offset is the bytes before it in the section (size headers included).
        let mut offsets = Vec::with_capacity(payloads.len());
        let mut offset = 0u64;
        for (i, p) in payloads.iter().enumerate() {
            offsets.push(offset);
            offset += match &compressed {
                Some(c) => c[i].len() as u64,
                None => 8 + p.bytes(),
            };
        }
        let (np, nc) = (self.point_data.len(), self.cell_data.len());
        let [at_points, at_connectivity, at_offsets, at_types] =
            [0, 1, 2, 3].map(|k| offsets[np + nc + k]);
        let compressor = match compression {
            VtuCompression::None => "",
            VtuCompression::Zlib => r#" compressor="vtkZLibDataCompressor""#,
        };

        writeln!(out, r#"<?xml version="1.0"?>"#)?;
        writeln!(
            out,
            r#"<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" header_type="UInt64"{compressor}>"#
        )?;
        writeln!(out, "  <UnstructuredGrid>")?;
        writeln!(
            out,
            r#"    <Piece NumberOfPoints="{}" NumberOfCells="{}">"#,
            self.points.len(),
            self.num_cells()
        )?;
        write_vtu_data(&mut out, "PointData", &self.point_data, &offsets[..np])?;
        write_vtu_data(&mut out, "CellData", &self.cell_data, &offsets[np..np + nc])?;
        writeln!(out, "      <Points>")?;
        writeln!(
            out,
            r#"        <DataArray type="Float64" NumberOfComponents="3" format="appended" offset="{at_points}"/>"#
        )?;
        writeln!(out, "      </Points>")?;
        writeln!(out, "      <Cells>")?;
        writeln!(
            out,
            r#"        <DataArray type="Int64" Name="connectivity" format="appended" offset="{at_connectivity}"/>"#
        )?;
        writeln!(
            out,
            r#"        <DataArray type="Int64" Name="offsets" format="appended" offset="{at_offsets}"/>"#
        )?;
        writeln!(
            out,
            r#"        <DataArray type="UInt8" Name="types" format="appended" offset="{at_types}"/>"#
        )?;
        writeln!(out, "      </Cells>")?;
        writeln!(out, "    </Piece>")?;
        writeln!(out, "  </UnstructuredGrid>")?;
        write!(out, "  <AppendedData encoding=\"raw\">\n   _")?;
        for (i, p) in payloads.iter().enumerate() {
            match &compressed {
                Some(c) => out.write_all(&c[i])?,
                None => p.write(&mut out)?,
            }
        }
        writeln!(out, "\n  </AppendedData>")?;
        writeln!(out, "</VTKFile>")?;
        out.flush()?;
        Ok(())
    }

    /// Writes the legacy `.vtk` form (ASCII, file version 4.2). The normals become `VECTORS` (not
    /// the `NORMALS` attribute, which meshio's legacy reader refuses; VTK reads both, and keeps the
    /// array's name), the active scalars `SCALARS`, every other array a `FIELD` entry.
    ///
    /// # Errors
    /// [`crate::Error::Io`] when the writer fails.
    pub fn write_legacy<W: Write>(&self, title: &str, mut out: W) -> Result<()> {
        writeln!(out, "# vtk DataFile Version 4.2")?;
        // The title is one line of at most 256 characters.
        let title: String = title
            .chars()
            .filter(|c| !c.is_control())
            .take(255)
            .collect();
        writeln!(
            out,
            "{}",
            if title.is_empty() {
                "ISM export"
            } else {
                &title
            }
        )?;
        writeln!(out, "ASCII")?;
        writeln!(out, "DATASET UNSTRUCTURED_GRID")?;
        writeln!(out, "POINTS {} double", self.points.len())?;
        for p in &self.points {
            writeln!(out, "{} {} {}", p[0], p[1], p[2])?;
        }
        writeln!(
            out,
            "CELLS {} {}",
            self.num_cells(),
            self.num_cells() + self.connectivity.len()
        )?;
        let mut start = 0usize;
        for &end in &self.offsets {
            let ids = &self.connectivity[start..end as usize];
            write!(out, "{} ", ids.len())?;
            write_joined(&mut out, ids)?;
            start = end as usize;
        }
        writeln!(out, "CELL_TYPES {}", self.num_cells())?;
        write_wrapped(&mut out, &self.types)?;
        write_legacy_data(&mut out, "POINT_DATA", self.points.len(), &self.point_data)?;
        write_legacy_data(&mut out, "CELL_DATA", self.num_cells(), &self.cell_data)?;
        out.flush()?;
        Ok(())
    }
}

fn write_joined<W: Write, T: std::fmt::Display>(out: &mut W, values: &[T]) -> std::io::Result<()> {
    for (i, v) in values.iter().enumerate() {
        if i > 0 {
            out.write_all(b" ")?;
        }
        write!(out, "{v}")?;
    }
    out.write_all(b"\n")
}

/// Writes values a fixed number per line, so no line grows with the mesh.
fn write_wrapped<W: Write, T: std::fmt::Display>(out: &mut W, values: &[T]) -> std::io::Result<()> {
    for chunk in values.chunks(12) {
        write_joined(out, chunk)?;
    }
    Ok(())
}

fn write_array_values<W: Write>(out: &mut W, a: &DataArray) -> std::io::Result<()> {
    let per_line = a.components.max(1);
    match &a.values {
        ArrayValues::Float(v) => {
            for chunk in v.chunks(per_line) {
                write_joined(out, chunk)?;
            }
        }
        ArrayValues::Int(v) => {
            for chunk in v.chunks(per_line.max(12)) {
                write_joined(out, chunk)?;
            }
        }
    }
    Ok(())
}

/// The `section` element (`PointData`, `CellData`) declaring `arrays`, each at its offset in the
/// appended section (`at`, in the same order).
fn write_vtu_data<W: Write>(
    out: &mut W,
    section: &str,
    arrays: &[DataArray],
    at: &[u64],
) -> std::io::Result<()> {
    let mut decl = String::new();
    for a in arrays {
        let key = match a.attribute {
            Attribute::None => continue,
            Attribute::Scalars => "Scalars",
            Attribute::Normals => "Normals",
            Attribute::RationalWeights => "RationalWeights",
        };
        decl.push_str(&format!(r#" {key}="{}""#, xml_escape(&a.name)));
    }
    writeln!(out, "      <{section}{decl}>")?;
    for (a, offset) in arrays.iter().zip(at) {
        let ty = match a.values {
            ArrayValues::Float(_) => "Float64",
            ArrayValues::Int(_) => "Int64",
        };
        writeln!(
            out,
            r#"        <DataArray type="{ty}" Name="{}" NumberOfComponents="{}" format="appended" offset="{offset}"/>"#,
            xml_escape(&a.name),
            a.components
        )?;
    }
    writeln!(out, "      </{section}>")
}

/// The values of one appended array, as the little-endian bytes its declared type stores.
#[derive(Clone, Copy)]
enum Payload<'a> {
    /// `Float64`, three per point.
    Points(&'a [[f64; 3]]),
    /// `Float64`.
    Float(&'a [f64]),
    /// `Int64`.
    Int(&'a [i64]),
    /// `Int64` from unsigned ids and offsets (all below 2⁶³: they count entries of a `Vec`, so
    /// their bytes are the same).
    Unsigned(&'a [u64]),
    /// `UInt8`.
    Bytes(&'a [u8]),
}

impl<'a> Payload<'a> {
    fn of(a: &'a DataArray) -> Payload<'a> {
        match &a.values {
            ArrayValues::Float(v) => Payload::Float(v),
            ArrayValues::Int(v) => Payload::Int(v),
        }
    }

    /// The array as a compressed appended array: VTK's zlib header (`UInt64` words) and the
    /// [`VTU_BLOCK`]-byte blocks of its values, each compressed on its own (in parallel).
    fn zlib(&self) -> std::io::Result<Vec<u8>> {
        use rayon::prelude::*;
        let mut raw = Vec::with_capacity(8 + self.bytes() as usize);
        self.write(&mut raw)?;
        let raw = &raw[8..];
        let blocks: Vec<Vec<u8>> = raw
            .par_chunks(VTU_BLOCK)
            .map(|block| {
                let mut e = flate2::write::ZlibEncoder::new(
                    Vec::new(),
                    flate2::Compression::new(VTU_ZLIB_LEVEL),
                );
                e.write_all(block)?;
                e.finish()
            })
            .collect::<std::io::Result<_>>()?;
        let words = [
            blocks.len() as u64,
            VTU_BLOCK as u64,
            (raw.len() % VTU_BLOCK) as u64,
        ]
        .into_iter()
        .chain(blocks.iter().map(|b| b.len() as u64));
        let mut out =
            Vec::with_capacity(8 * (3 + blocks.len()) + blocks.iter().map(Vec::len).sum::<usize>());
        for w in words {
            out.extend_from_slice(&w.to_le_bytes());
        }
        for b in &blocks {
            out.extend_from_slice(b);
        }
        Ok(out)
    }

    /// The values' size in bytes (the array's header word).
    fn bytes(&self) -> u64 {
        let n = match self {
            Payload::Points(v) => 24 * v.len(),
            Payload::Float(v) => 8 * v.len(),
            Payload::Int(v) => 8 * v.len(),
            Payload::Unsigned(v) => 8 * v.len(),
            Payload::Bytes(v) => v.len(),
        };
        n as u64
    }

    /// Writes the header word and the values, through a fixed buffer (the writer may be
    /// unbuffered; a whole array is never copied).
    fn write<W: Write>(&self, out: &mut W) -> std::io::Result<()> {
        out.write_all(&self.bytes().to_le_bytes())?;
        match *self {
            Payload::Points(v) => write_le(out, v.iter().flatten(), |x| x.to_le_bytes()),
            Payload::Float(v) => write_le(out, v.iter(), |x| x.to_le_bytes()),
            Payload::Int(v) => write_le(out, v.iter(), |x| x.to_le_bytes()),
            Payload::Unsigned(v) => write_le(out, v.iter(), |x| x.to_le_bytes()),
            Payload::Bytes(v) => out.write_all(v),
        }
    }
}

/// Writes 8-byte values as `bytes` encodes them, 64 KiB at a time.
fn write_le<'v, W: Write, T: 'v + Copy>(
    out: &mut W,
    values: impl Iterator<Item = &'v T>,
    bytes: impl Fn(T) -> [u8; 8],
) -> std::io::Result<()> {
    let mut buf = [0u8; 1 << 16];
    let mut len = 0;
    for &v in values {
        buf[len..len + 8].copy_from_slice(&bytes(v));
        len += 8;
        if len == buf.len() {
            out.write_all(&buf)?;
            len = 0;
        }
    }
    out.write_all(&buf[..len])
}

fn write_legacy_data<W: Write>(
    out: &mut W,
    section: &str,
    count: usize,
    arrays: &[DataArray],
) -> std::io::Result<()> {
    if arrays.is_empty() {
        return Ok(());
    }
    writeln!(out, "{section} {count}")?;
    let legacy_name = |name: &str| name.replace(char::is_whitespace, "_");
    let mut fields = Vec::new();
    let mut scalars_done = false;
    let mut normals_done = false;
    for a in arrays {
        match (a.attribute, &a.values) {
            (Attribute::Normals, ArrayValues::Float(_)) if !normals_done && a.components == 3 => {
                normals_done = true;
                writeln!(out, "VECTORS {} double", legacy_name(&a.name))?;
                write_array_values(out, a)?;
            }
            (Attribute::Scalars, values) if !scalars_done => {
                scalars_done = true;
                let ty = if matches!(values, ArrayValues::Float(_)) {
                    "double"
                } else {
                    "long"
                };
                writeln!(
                    out,
                    "SCALARS {} {ty} {}",
                    legacy_name(&a.name),
                    a.components
                )?;
                writeln!(out, "LOOKUP_TABLE default")?;
                write_array_values(out, a)?;
            }
            _ => fields.push(a),
        }
    }
    if !fields.is_empty() {
        writeln!(out, "FIELD FieldData {}", fields.len())?;
        for a in fields {
            let ty = if matches!(a.values, ArrayValues::Float(_)) {
                "double"
            } else {
                "long"
            };
            writeln!(
                out,
                "{} {} {} {ty}",
                legacy_name(&a.name),
                a.components,
                a.values.len() / a.components.max(1)
            )?;
            write_array_values(out, a)?;
        }
    }
    Ok(())
}

fn xml_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// Point order of VTK's higher-order triangle of degree `d`, as VTK barycentric indices
/// `(b0, b1, b2)` where local vertex 0 is `(0, 0, d)`, vertex 1 `(d, 0, 0)`, vertex 2 `(0, d, 0)`:
/// the three vertices, the edges (0→1, 1→2, 2→0) each walked from its first vertex, then the
/// interior as a triangle of degree `d − 3` in the same order, recursively.
pub fn vtk_triangle_order(d: u32) -> Vec<[u32; 3]> {
    if d == 0 {
        return vec![[0, 0, 0]];
    }
    let lam = |l: [u32; 3]| [l[1], l[2], l[0]];
    let mut out = vec![lam([d, 0, 0]), lam([0, d, 0]), lam([0, 0, d])];
    for (a, b) in [(0usize, 1usize), (1, 2), (2, 0)] {
        for k in 1..d {
            let mut l = [0u32; 3];
            l[a] = d - k;
            l[b] = k;
            out.push(lam(l));
        }
    }
    if d >= 3 {
        out.extend(
            vtk_triangle_order(d - 3)
                .into_iter()
                .map(|b| [b[0] + 1, b[1] + 1, b[2] + 1]),
        );
    }
    out
}

/// Point order of VTK's higher-order tetrahedron of degree `d`, as VTK barycentric indices
/// `(b0, b1, b2, b3)` where local vertex 0 is `(0, 0, 0, d)` and vertex `k ≥ 1` has `b_{k−1} = d`:
/// vertices; edges 0→1, 1→2, 2→0, 0→3, 1→3, 2→3; the four faces' interiors, each a VTK triangle
/// of degree `d − 3` laid onto the face's coordinates; then the interior as a tetrahedron of degree
/// `d − 4`, recursively.
pub fn vtk_tetra_order(d: u32) -> Vec<[u32; 4]> {
    if d == 0 {
        return vec![[0, 0, 0, 0]];
    }
    // Local vertex weights λ → VTK's barycentric index.
    let lam = |l: [u32; 4]| [l[1], l[2], l[3], l[0]];
    let mut out: Vec<[u32; 4]> = (0..4)
        .map(|v| {
            let mut l = [0u32; 4];
            l[v] = d;
            lam(l)
        })
        .collect();
    for (a, b) in [(0usize, 1usize), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)] {
        for k in 1..d {
            let mut l = [0u32; 4];
            l[a] = d - k;
            l[b] = k;
            out.push(lam(l));
        }
    }
    if d >= 3 {
        // Which VTK barycentric slots a face's triangle coordinates occupy, and which slot is
        // zero on that face (faces 013, 123, 203, 021 in vertex terms).
        const FACE_SLOTS: [[usize; 3]; 4] = [[0, 2, 3], [2, 0, 1], [2, 1, 3], [1, 0, 3]];
        const FACE_ZERO: [usize; 4] = [1, 3, 0, 2];
        for f in 0..4 {
            for t in vtk_triangle_order(d - 3) {
                let mut b = [0u32; 4];
                for c in 0..3 {
                    b[FACE_SLOTS[f][c]] = t[c] + 1;
                }
                b[FACE_ZERO[f]] = 0;
                out.push(b);
            }
        }
    }
    if d >= 4 {
        out.extend(
            vtk_tetra_order(d - 4)
                .into_iter()
                .map(|b| [b[0] + 1, b[1] + 1, b[2] + 1, b[3] + 1]),
        );
    }
    out
}

/// The VTK point order of a degree-`d` Bézier cell on an `n`-simplex as local multi-indices
/// `I` (entry `i` = exponent of the simplex's stored vertex `i`), flat, `n + 1` per point.
pub fn vtk_local_multi_indices(n: usize, d: u32) -> Vec<u32> {
    match n {
        2 => vtk_triangle_order(d)
            .into_iter()
            .flat_map(|b| [b[2], b[0], b[1]])
            .collect(),
        3 => vtk_tetra_order(d)
            .into_iter()
            .flat_map(|b| [b[3], b[0], b[1], b[2]])
            .collect(),
        _ => Vec::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::tests::tetrahedron_surface;

    // Fixtures printed by Python vtk 9.7: vtkHigherOrderTriangle/Tetra.BarycentricIndex(i, b, d).
    const VTK_TRI_4: [[u32; 3]; 15] = [
        [0, 0, 4],
        [4, 0, 0],
        [0, 4, 0],
        [1, 0, 3],
        [2, 0, 2],
        [3, 0, 1],
        [3, 1, 0],
        [2, 2, 0],
        [1, 3, 0],
        [0, 3, 1],
        [0, 2, 2],
        [0, 1, 3],
        [1, 1, 2],
        [2, 1, 1],
        [1, 2, 1],
    ];
    const VTK_TET_3: [[u32; 4]; 20] = [
        [0, 0, 0, 3],
        [3, 0, 0, 0],
        [0, 3, 0, 0],
        [0, 0, 3, 0],
        [1, 0, 0, 2],
        [2, 0, 0, 1],
        [2, 1, 0, 0],
        [1, 2, 0, 0],
        [0, 2, 0, 1],
        [0, 1, 0, 2],
        [0, 0, 1, 2],
        [0, 0, 2, 1],
        [2, 0, 1, 0],
        [1, 0, 2, 0],
        [0, 2, 1, 0],
        [0, 1, 2, 0],
        [1, 0, 1, 1],
        [1, 1, 1, 0],
        [0, 1, 1, 1],
        [1, 1, 0, 1],
    ];
    const VTK_TET_5_TAIL: [[u32; 4]; 8] = [
        [1, 2, 0, 2],
        [2, 2, 0, 1],
        [2, 1, 0, 2],
        [1, 1, 1, 2],
        [2, 1, 1, 1],
        [1, 2, 1, 1],
        [1, 1, 2, 1],
        [0, 0, 0, 0],
    ];

    #[test]
    fn orders_match_vtk_fixtures() {
        assert_eq!(vtk_triangle_order(4), VTK_TRI_4.to_vec());
        assert_eq!(vtk_tetra_order(3), VTK_TET_3.to_vec());
        let t5 = vtk_tetra_order(5);
        assert_eq!(t5.len(), 56);
        assert_eq!(t5[49..56], VTK_TET_5_TAIL[..7]);
    }

    #[test]
    fn orders_are_permutations_of_all_multi_indices() {
        for d in 0..=8u32 {
            for n in [2usize, 3] {
                let mut ours: Vec<Vec<u32>> = vtk_local_multi_indices(n, d)
                    .chunks(n + 1)
                    .map(<[u32]>::to_vec)
                    .collect();
                assert!(ours.iter().all(|i| i.iter().sum::<u32>() == d));
                ours.sort();
                let mut all: Vec<Vec<u32>> = ism_format::multi_index::all(n + 1, d)
                    .chunks(n + 1)
                    .map(<[u32]>::to_vec)
                    .collect();
                all.sort();
                assert_eq!(ours, all, "n = {n}, d = {d}");
            }
        }
    }

    #[test]
    fn legacy_and_vtu_contain_every_array() {
        let g = UnstructuredGrid::from_mesh(&tetrahedron_surface());
        let mut legacy = Vec::new();
        g.write_legacy("tet", &mut legacy).unwrap();
        let text = String::from_utf8(legacy).unwrap();
        assert!(text.contains("CELLS 4 16\n3 0 2 1\n"));
        assert!(text.contains("VECTORS Normals double"));
        assert!(text.contains("SCALARS GradientNorm double 1"));
        assert!(text.contains("FIELD FieldData 1\nSourceSimplex 1 4 long"));
        assert!(text.contains("CELL_DATA 4"));
        let mut vtu = Vec::new();
        g.write_vtu(&mut vtu).unwrap();
        let (text, _) = split_vtu(&vtu);
        let doc = roxmltree::Document::parse(&text).expect("well-formed XML");
        let piece = doc.descendants().find(|n| n.has_tag_name("Piece")).unwrap();
        assert_eq!(piece.attribute("NumberOfPoints"), Some("4"));
        assert_eq!(piece.attribute("NumberOfCells"), Some("4"));
        let pd = doc
            .descendants()
            .find(|n| n.has_tag_name("PointData"))
            .unwrap();
        assert_eq!(pd.attribute("Normals"), Some("Normals"));
        assert_eq!(pd.attribute("Scalars"), Some("GradientNorm"));
    }

    /// A compressed `.vtu` holds the uncompressed one's arrays: every array's section, taken
    /// apart by the offsets in its XML and VTK's header words and inflated block by block here
    /// (flate2's decoder, not the writer), is the raw file's section for the same array, byte
    /// for byte — on arrays of several blocks with a partial last one (the points), of exactly
    /// eight blocks (the types: last block size 0). The importer reads
    /// both files to the same mesh.
    #[test]
    fn compressed_vtu_arrays_inflate_to_the_raw_ones() {
        use std::io::Read;
        let mut g = UnstructuredGrid::default();
        let n = 5000;
        g.points = (0..n)
            .map(|i| {
                let t = i as f64 * 0.01;
                [t.cos(), t.sin(), t * 1e-3]
            })
            .collect();
        let cells = 8 * VTU_BLOCK;
        for c in 0..cells {
            let a = (c % (n - 2)) as u64;
            g.push_cell(cell_type::TRIANGLE, [a, a + 1, a + 2]);
        }
        g.point_data.push(DataArray {
            name: "F".into(),
            components: 1,
            values: ArrayValues::Float(g.points.iter().map(|p| p[0] - 0.25).collect()),
            attribute: Attribute::Scalars,
        });
        g.cell_data.push(DataArray {
            name: "Few".into(),
            components: 1,
            values: ArrayValues::Int((0..cells as i64).map(|c| c % 3).collect()),
            attribute: Attribute::None,
        });
        let (mut raw_file, mut zlib_file) = (Vec::new(), Vec::new());
        g.write_vtu(&mut raw_file).unwrap();
        g.write_vtu_with(&mut zlib_file, VtuCompression::Zlib)
            .unwrap();
        let (raw_text, raw) = split_vtu(&raw_file);
        let (zlib_text, zlib) = split_vtu(&zlib_file);
        let offsets = |text: &str| -> Vec<usize> {
            let doc = roxmltree::Document::parse(text).unwrap();
            doc.descendants()
                .filter(|n| n.has_tag_name("DataArray"))
                .map(|n| n.attribute("offset").unwrap().parse().unwrap())
                .collect()
        };
        assert!(zlib_text.contains(r#"compressor="vtkZLibDataCompressor""#));
        assert!(!raw_text.contains("compressor"));
        let (raw_at, zlib_at) = (offsets(&raw_text), offsets(&zlib_text));
        assert_eq!(raw_at.len(), 6);
        let word = |b: &[u8], i: usize| {
            u64::from_le_bytes(b[8 * i..8 * i + 8].try_into().unwrap()) as usize
        };
        let mut last_sizes = Vec::new();
        for (k, (&r, &z)) in raw_at.iter().zip(&zlib_at).enumerate() {
            let size = word(&raw[r..], 0);
            let values = &raw[r + 8..r + 8 + size];
            let section = &zlib[z..];
            let (blocks, block, last) = (word(section, 0), word(section, 1), word(section, 2));
            assert_eq!(block, VTU_BLOCK);
            assert_eq!(blocks, size.div_ceil(VTU_BLOCK), "array {k}");
            assert_eq!(last, size % VTU_BLOCK, "array {k}");
            last_sizes.push((blocks, last));
            let mut inflated = Vec::new();
            let mut at = 8 * (3 + blocks);
            for b in 0..blocks {
                let c = word(section, 3 + b);
                flate2::read::ZlibDecoder::new(&section[at..at + c])
                    .read_to_end(&mut inflated)
                    .unwrap();
                at += c;
            }
            assert_eq!(inflated, values, "array {k}");
            // The next array starts where this one's blocks end.
            if let Some(&next) = zlib_at.get(k + 1) {
                assert_eq!(z + at, next);
            } else {
                assert_eq!(z + at, zlib.len());
            }
        }
        // Points: several blocks, a partial last; types: exactly eight full ones.
        assert!(last_sizes.contains(&(8, 0)));
        assert!(last_sizes.iter().any(|&(b, l)| b > 1 && l > 0));
        assert!(zlib_file.len() < raw_file.len() / 2);
        let read = |bytes: &[u8]| {
            crate::import::read_mesh(bytes, crate::import::ImportFormat::Vtu).unwrap()
        };
        let (a, b) = (read(&raw_file), read(&zlib_file));
        assert_eq!(a.points, b.points);
        assert_eq!(a.triangles, b.triangles);
        assert_eq!(a.fields, b.fields);
    }

    /// A `.vtu` as its XML (with an empty `AppendedData` element) and the raw bytes after `_`.
    fn split_vtu(vtu: &[u8]) -> (String, Vec<u8>) {
        let tag = b"<AppendedData encoding=\"raw\">\n   _";
        let start = vtu.windows(tag.len()).position(|w| w == tag).unwrap() + tag.len();
        let end = vtu.len() - b"\n  </AppendedData>\n</VTKFile>\n".len();
        assert_eq!(&vtu[end..], b"\n  </AppendedData>\n</VTKFile>\n");
        let mut text = String::from_utf8(vtu[..start - 1].to_vec()).unwrap();
        text.push_str("</AppendedData></VTKFile>");
        (text, vtu[start..end].to_vec())
    }

    /// Every array of a written `.vtu`, decoded from its declared type and offset, holds the
    /// grid's values bit for bit, and the arrays tile the appended section exactly; the
    /// importer reads the same points, triangles and scalar fields back.
    #[test]
    fn vtu_arrays_are_the_values_bit_for_bit() {
        let mut g = UnstructuredGrid::from_mesh(&tetrahedron_surface());
        // Values whose decimal text would need care: signed zero, subnormal, extremes.
        g.points[0] = [-0.0, 5e-324, f64::MAX];
        g.points[1] = [0.1 + 0.2, -f64::MIN_POSITIVE, 1.0 / 3.0];
        g.cell_data.push(DataArray {
            name: "Wide <ids> & \"more\"".into(),
            components: 2,
            values: ArrayValues::Int(vec![i64::MIN, i64::MAX, -1, 0, 1, 2, 3, 4]),
            attribute: Attribute::None,
        });
        let mut vtu = Vec::new();
        g.write_vtu(&mut vtu).unwrap();
        let (text, raw) = split_vtu(&vtu);
        let doc = roxmltree::Document::parse(&text).expect("well-formed XML");
        let mut expected: Vec<(Option<&str>, Vec<u8>)> = Vec::new();
        let le8 = |v: &mut Vec<u8>, bits: u64| v.extend_from_slice(&bits.to_le_bytes());
        for a in g.point_data.iter().chain(&g.cell_data) {
            let mut bytes = Vec::new();
            match &a.values {
                ArrayValues::Float(v) => v.iter().for_each(|x| le8(&mut bytes, x.to_bits())),
                ArrayValues::Int(v) => v.iter().for_each(|&x| le8(&mut bytes, x as u64)),
            }
            expected.push((Some(a.name.as_str()), bytes));
        }
        let mut points = Vec::new();
        g.points
            .iter()
            .flatten()
            .for_each(|x| le8(&mut points, x.to_bits()));
        expected.push((None, points));
        for v in [&g.connectivity, &g.offsets] {
            let mut bytes = Vec::new();
            v.iter().for_each(|&x| le8(&mut bytes, x));
            expected.push((None, bytes));
        }
        expected.push((None, g.types.clone()));
        let arrays: Vec<_> = doc
            .descendants()
            .filter(|n| n.has_tag_name("DataArray"))
            .collect();
        assert_eq!(arrays.len(), expected.len());
        let mut end = 0;
        for (node, (name, bytes)) in arrays.iter().zip(&expected) {
            assert_eq!(node.attribute("format"), Some("appended"));
            if let Some(name) = name {
                assert_eq!(node.attribute("Name"), Some(*name));
            }
            let at: usize = node.attribute("offset").unwrap().parse().unwrap();
            assert_eq!(at, end, "arrays are contiguous, in file order");
            let size = u64::from_le_bytes(raw[at..at + 8].try_into().unwrap()) as usize;
            assert_eq!(&raw[at + 8..at + 8 + size], &bytes[..]);
            end = at + 8 + size;
        }
        assert_eq!(end, raw.len(), "nothing after the last array");

        let back = crate::import::read_mesh(&vtu, crate::import::ImportFormat::Vtu).unwrap();
        let bits =
            |p: &[[f64; 3]]| -> Vec<u64> { p.iter().flatten().map(|x| x.to_bits()).collect() };
        assert_eq!(bits(&back.points), bits(&g.points));
        let triangles: Vec<u64> = back
            .triangles
            .iter()
            .flatten()
            .map(|&i| u64::from(i))
            .collect();
        assert_eq!(triangles, g.connectivity);
        let gradient = back.fields.iter().find(|f| f.0 == "GradientNorm").unwrap();
        let ArrayValues::Float(want) = &g.point_data[1].values else {
            panic!("GradientNorm is Float64")
        };
        assert_eq!(&gradient.1, want);
    }
}
