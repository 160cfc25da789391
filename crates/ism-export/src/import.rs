//! Import of simplicial meshes with a point scalar field into a linear ISM (no stage): VTK XML
//! `.vtu` (ASCII, inline base64 `binary` or `appended` base64/raw arrays, uncompressed or
//! compressed with zlib, LZ4 or LZMA — what meshio and `vtkXMLUnstructuredGridWriter` write by
//! default; the layout is described in `vtu_data.rs`), legacy `.vtk` (ASCII), Gmsh `.msh` 4.1 (ASCII).
//!
//! Tetrahedra make a 3D model (triangles in the same file are taken as boundary faces and
//! dropped); otherwise triangles make a 2D model (the file must be planar in `z`). Quadratic cells
//! (VTK 22/24, Gmsh 9/11) contribute their corner nodes, which both conventions list first, so the
//! differing edge-node orders do not matter; nodes no kept cell uses are dropped. Cells are
//! re-oriented positively (last two vertices swapped where the orientation determinant is
//! negative); a cell with zero volume is an error. The values are the chosen point field; a value
//! equal to the level is refused (choose another `level`).

use std::path::Path;

use ism_format::Model;

use crate::vtu_data::{Compressor, Layout};
use crate::{Error, Result};

/// Input mesh formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImportFormat {
    /// VTK XML unstructured grid.
    Vtu,
    /// Legacy VTK, ASCII, `DATASET UNSTRUCTURED_GRID`.
    VtkLegacy,
    /// Gmsh MSH 4.1, ASCII.
    Msh,
}

impl ImportFormat {
    /// The format of a file name's extension, if known.
    pub fn from_path(path: &Path) -> Option<ImportFormat> {
        match path.extension()?.to_str()?.to_ascii_lowercase().as_str() {
            "vtu" => Some(ImportFormat::Vtu),
            "vtk" => Some(ImportFormat::VtkLegacy),
            "msh" => Some(ImportFormat::Msh),
            _ => None,
        }
    }

    fn name(self) -> &'static str {
        match self {
            ImportFormat::Vtu => "vtu",
            ImportFormat::VtkLegacy => "vtk",
            ImportFormat::Msh => "msh",
        }
    }
}

/// A mesh as read: points, linear simplices (corner nodes), and 1-component point fields.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RawMesh {
    /// Point coordinates.
    pub points: Vec<[f64; 3]>,
    /// Tetrahedra (corner point indices).
    pub tetrahedra: Vec<[u32; 4]>,
    /// Triangles (corner point indices).
    pub triangles: Vec<[u32; 3]>,
    /// Scalar point fields by name, in file order; the first is the file's active scalars when
    /// the format says which.
    pub fields: Vec<(String, Vec<f64>)>,
}

/// Options of [`to_model`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ImportOptions {
    /// The point field giving the values; default: the first scalar field.
    pub field: Option<String>,
    /// The level `c` of the model.
    pub level: f64,
    /// The reader's bounds (the same [`ism_format::io::Limits`] as for ISM files): the file's
    /// size against `max_payload_bytes` before it is read, its points and cells against
    /// `max_vertices` and `max_simplices` before anything is built from them.
    pub limits: ism_format::io::Limits,
}

/// What [`to_model`] did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ImportReport {
    /// The field used for the values.
    pub field: String,
    /// Cells whose orientation was reversed.
    pub reoriented: usize,
    /// Nodes dropped because no kept cell uses them.
    pub dropped_nodes: usize,
    /// Triangles ignored because the mesh has tetrahedra.
    pub dropped_triangles: usize,
}

/// Reads a file by its extension and converts it.
///
/// # Errors
/// [`Error::Io`] if the file cannot be read, [`Error::Import`] for malformed content or an
/// unsupported variant (the message says what was expected, and where).
pub fn import_path(path: &Path, options: &ImportOptions) -> Result<(Model, ImportReport)> {
    let format = ImportFormat::from_path(path).ok_or_else(|| {
        Error::import(
            "mesh",
            None,
            format!(
                "unknown extension of {}: use .vtu, .vtk or .msh",
                path.display()
            ),
        )
    })?;
    let io_error = |source| Error::Io {
        path: Some(path.to_path_buf()),
        source,
    };
    let size = std::fs::metadata(path).map_err(io_error)?.len();
    let limit = options.limits.max_payload_bytes;
    if size > limit {
        return Err(Error::import(
            format.name(),
            None,
            format!(
                "{size} bytes; this reader accepts at most {limit} (Limits::max_payload_bytes)"
            ),
        ));
    }
    let bytes = std::fs::read(path).map_err(io_error)?;
    let raw = read_mesh(&bytes, format)?;
    to_model(&raw, options)
}

/// Parses a mesh file's bytes.
///
/// # Errors
/// [`Error::Import`] for malformed content or an unsupported variant.
pub fn read_mesh(bytes: &[u8], format: ImportFormat) -> Result<RawMesh> {
    // Raw appended data is binary inside XML: cut it out before the text is parsed.
    let (bytes, raw) = match format {
        ImportFormat::Vtu => split_raw_appended(bytes)?,
        _ => (std::borrow::Cow::Borrowed(bytes), None),
    };
    let bytes: &[u8] = &bytes;
    let text = std::str::from_utf8(bytes).map_err(|e| {
        Error::import(
            format.name(),
            format!("byte {}", e.valid_up_to()),
            "the file is not UTF-8 text (binary variants are not supported)",
        )
    })?;
    match format {
        ImportFormat::Vtu => read_vtu(text, raw),
        ImportFormat::VtkLegacy => read_legacy(text),
        ImportFormat::Msh => read_msh(text),
    }
}

/// VTK cell types whose first 3 (triangles) or 4 (tetrahedra) nodes are the corners.
fn vtk_corners(cell_type: i64) -> Option<usize> {
    match cell_type {
        5 | 22 | 69 | 76 => Some(3), // triangle, quadratic, Lagrange, Bézier triangle
        10 | 24 | 71 | 78 => Some(4), // tetra, quadratic, Lagrange, Bézier tetra
        _ => None,
    }
}

fn push_cell(
    raw: &mut RawMesh,
    corners: usize,
    ids: &[i64],
    npts: usize,
    fmt: &'static str,
    at: impl Fn() -> String,
) -> Result<()> {
    if ids.len() < corners {
        return Err(Error::import(
            fmt,
            at(),
            "cell has fewer nodes than its type needs",
        ));
    }
    let mut c = [0u32; 4];
    for (slot, &id) in c.iter_mut().zip(&ids[..corners]) {
        if id < 0 || id as usize >= npts {
            return Err(Error::import(
                fmt,
                at(),
                format!("node {id} out of range (0..{npts})"),
            ));
        }
        *slot = id as u32;
    }
    if corners == 4 {
        raw.tetrahedra.push(c);
    } else {
        raw.triangles.push([c[0], c[1], c[2]]);
    }
    Ok(())
}

fn parse_numbers(text: &str, fmt: &'static str, at: &str) -> Result<Vec<f64>> {
    text.split_ascii_whitespace()
        .map(|t| {
            t.parse::<f64>()
                .map_err(|_| Error::import(fmt, at.to_string(), format!("not a number: {t:?}")))
        })
        .collect()
}

/// A `.vtu` file's XML text (as bytes) and its raw appended data, if any.
type SplitVtu<'a> = (std::borrow::Cow<'a, [u8]>, Option<&'a [u8]>);

/// The file without the bytes of a raw `AppendedData` section (after its `_` up to
/// `</AppendedData>`), and those bytes; the file itself when it has none.
fn split_raw_appended(bytes: &[u8]) -> Result<SplitVtu<'_>> {
    fn find(hay: &[u8], needle: &[u8], from: usize) -> Option<usize> {
        hay.get(from..)?
            .windows(needle.len())
            .position(|w| w == needle)
            .map(|i| i + from)
    }
    let Some(tag) = find(bytes, b"<AppendedData", 0) else {
        return Ok((std::borrow::Cow::Borrowed(bytes), None));
    };
    let err = |m: &str| Error::import("vtu", "AppendedData".to_string(), m.to_string());
    let open_end = find(bytes, b">", tag).ok_or_else(|| err("unterminated tag"))?;
    let attributes = String::from_utf8_lossy(&bytes[tag..open_end]);
    if !attributes.contains("encoding=\"raw\"") && !attributes.contains("encoding='raw'") {
        return Ok((std::borrow::Cow::Borrowed(bytes), None));
    }
    let underscore = find(bytes, b"_", open_end).ok_or_else(|| err("no '_' before the data"))?;
    let close = bytes
        .windows(b"</AppendedData>".len())
        .rposition(|w| w == b"</AppendedData>")
        .filter(|&c| c > underscore)
        .ok_or_else(|| err("no </AppendedData>"))?;
    let mut text = bytes[..=underscore].to_vec();
    text.extend_from_slice(&bytes[close..]);
    Ok((
        std::borrow::Cow::Owned(text),
        Some(&bytes[underscore + 1..close]),
    ))
}

fn read_vtu(text: &str, raw_appended: Option<&[u8]>) -> Result<RawMesh> {
    const FMT: &str = "vtu";
    let doc = roxmltree::Document::parse(text)
        .map_err(|e| Error::import(FMT, None, format!("XML: {e}")))?;
    let root = doc.root_element();
    if root.attribute("type") != Some("UnstructuredGrid") {
        return Err(Error::import(
            FMT,
            "VTKFile".to_string(),
            "expected type=\"UnstructuredGrid\"",
        ));
    }
    let layout = Layout {
        header64: root.attribute("header_type") == Some("UInt64"),
        compressor: Compressor::from_attribute(root.attribute("compressor"))?,
    };
    let appended_node = root.children().find(|n| n.has_tag_name("AppendedData"));
    // Base64 appended text after its `_` marker.
    let appended_text = appended_node.and_then(|n| {
        let t = n.text().unwrap_or("");
        t.trim_start().strip_prefix('_')
    });
    if root
        .attribute("byte_order")
        .is_some_and(|b| b != "LittleEndian")
    {
        return Err(Error::import(
            FMT,
            "VTKFile".to_string(),
            "only LittleEndian binary data is supported",
        ));
    }
    let pieces: Vec<_> = root
        .descendants()
        .filter(|n| n.has_tag_name("Piece"))
        .collect();
    if pieces.len() != 1 {
        return Err(Error::import(
            FMT,
            "UnstructuredGrid".to_string(),
            format!("expected one Piece, found {}", pieces.len()),
        ));
    }
    let piece = pieces[0];
    let count = |name: &str| -> Result<usize> {
        piece
            .attribute(name)
            .and_then(|v| v.parse().ok())
            .ok_or_else(|| {
                Error::import(FMT, "Piece".to_string(), format!("missing or bad {name}"))
            })
    };
    let (npts, ncells) = (count("NumberOfPoints")?, count("NumberOfCells")?);
    let array = |node: roxmltree::Node| -> Result<(Vec<f64>, usize)> {
        let name = node.attribute("Name").unwrap_or("(unnamed)");
        let at = format!("DataArray {name}");
        let comps = node
            .attribute("NumberOfComponents")
            .and_then(|c| c.parse().ok())
            .unwrap_or(1usize);
        let body = node.text().unwrap_or("");
        let ty = node.attribute("type").unwrap_or("");
        let values = match node.attribute("format").unwrap_or("ascii") {
            "ascii" => parse_numbers(body, FMT, &at)?,
            "binary" => numbers_from_le(&layout.inline(body, &at)?, ty, &at)?,
            "appended" => {
                let offset: usize = node
                    .attribute("offset")
                    .and_then(|o| o.trim().parse().ok())
                    .ok_or_else(|| Error::import(FMT, at.clone(), "missing or bad offset"))?;
                let bytes = match (raw_appended, appended_text) {
                    (Some(raw), _) => layout.appended_raw(raw, offset, &at)?,
                    (None, Some(text)) => layout.appended_base64(text, offset, &at)?,
                    (None, None) => {
                        return Err(Error::import(
                            FMT,
                            at,
                            "format \"appended\" but no AppendedData section with a '_' marker",
                        ))
                    }
                };
                numbers_from_le(&bytes, ty, &at)?
            }
            other => {
                return Err(Error::import(
                    FMT,
                    at,
                    format!("format {other:?} is not supported (ascii, binary or appended)"),
                ))
            }
        };
        Ok((values, comps))
    };
    fn child<'a, 'i>(
        parent: roxmltree::Node<'a, 'i>,
        tag: &str,
    ) -> Option<roxmltree::Node<'a, 'i>> {
        parent.children().find(|n| n.has_tag_name(tag))
    }
    let mut raw = RawMesh::default();
    let points_node = child(piece, "Points")
        .and_then(|p| child(p, "DataArray"))
        .ok_or_else(|| Error::import(FMT, "Piece".to_string(), "no Points"))?;
    let (coords, comps) = array(points_node)?;
    if comps != 3 || coords.len() != 3 * npts {
        return Err(Error::import(
            FMT,
            "Points".to_string(),
            format!("expected {npts} points of 3 components"),
        ));
    }
    raw.points = coords.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    let cells =
        child(piece, "Cells").ok_or_else(|| Error::import(FMT, "Piece".to_string(), "no Cells"))?;
    let named = |name: &str| -> Result<Vec<f64>> {
        let node = cells
            .children()
            .find(|n| n.has_tag_name("DataArray") && n.attribute("Name") == Some(name))
            .ok_or_else(|| Error::import(FMT, "Cells".to_string(), format!("no {name} array")))?;
        Ok(array(node)?.0)
    };
    let (conn, offsets, types) = (named("connectivity")?, named("offsets")?, named("types")?);
    if offsets.len() != ncells || types.len() != ncells {
        return Err(Error::import(
            FMT,
            "Cells".to_string(),
            format!("expected {ncells} offsets and types"),
        ));
    }
    let mut start = 0usize;
    for (i, (&end, &t)) in offsets.iter().zip(&types).enumerate() {
        let end = end as usize;
        if end < start || end > conn.len() {
            return Err(Error::import(
                FMT,
                format!("cell {i}"),
                "offsets must increase within the connectivity",
            ));
        }
        if let Some(k) = vtk_corners(t as i64) {
            let ids: Vec<i64> = conn[start..end].iter().map(|&x| x as i64).collect();
            push_cell(&mut raw, k, &ids, npts, FMT, || format!("cell {i}"))?;
        }
        start = end;
    }
    if let Some(pd) = child(piece, "PointData") {
        let active = pd.attribute("Scalars");
        for node in pd.children().filter(|n| n.has_tag_name("DataArray")) {
            let (values, comps) = array(node)?;
            let name = node.attribute("Name").unwrap_or("").to_string();
            if comps == 1 && values.len() == npts {
                if active == Some(name.as_str()) {
                    raw.fields.insert(0, (name, values));
                } else {
                    raw.fields.push((name, values));
                }
            }
        }
    }
    Ok(raw)
}

/// Little-endian values of VTK type `ty`, as `f64`.
fn numbers_from_le(data: &[u8], ty: &str, at: &str) -> Result<Vec<f64>> {
    const FMT: &str = "vtu";
    macro_rules! conv {
        ($t:ty) => {
            data.chunks_exact(std::mem::size_of::<$t>())
                .map(|c| <$t>::from_le_bytes(c.try_into().expect("chunk size")) as f64)
                .collect()
        };
    }
    Ok(match ty {
        "Float32" => conv!(f32),
        "Float64" => conv!(f64),
        "Int8" => conv!(i8),
        "UInt8" => conv!(u8),
        "Int16" => conv!(i16),
        "UInt16" => conv!(u16),
        "Int32" => conv!(i32),
        "UInt32" => conv!(u32),
        "Int64" => conv!(i64),
        "UInt64" => conv!(u64),
        other => {
            return Err(Error::import(
                FMT,
                at.to_string(),
                format!("unsupported type {other:?}"),
            ))
        }
    })
}

/// A whitespace tokenizer that knows its line, for error locations.
struct Tokens<'a> {
    lines: std::iter::Peekable<std::iter::Enumerate<std::str::Lines<'a>>>,
    current: std::str::SplitAsciiWhitespace<'a>,
    line: usize,
    fmt: &'static str,
}

impl<'a> Tokens<'a> {
    fn new(text: &'a str, fmt: &'static str) -> Tokens<'a> {
        Tokens {
            lines: text.lines().enumerate().peekable(),
            current: "".split_ascii_whitespace(),
            line: 0,
            fmt,
        }
    }

    fn next(&mut self) -> Option<&'a str> {
        loop {
            if let Some(t) = self.current.next() {
                return Some(t);
            }
            let (i, l) = self.lines.next()?;
            self.line = i + 1;
            self.current = l.split_ascii_whitespace();
        }
    }

    fn rest_of_line(&mut self) -> Vec<&'a str> {
        self.current.by_ref().collect()
    }

    fn expect(&mut self) -> Result<&'a str> {
        let line = self.line;
        self.next().ok_or_else(|| {
            Error::import(self.fmt, format!("line {line}"), "unexpected end of file")
        })
    }

    fn parse<T: std::str::FromStr>(&mut self) -> Result<T> {
        let t = self.expect()?;
        t.parse().map_err(|_| {
            Error::import(
                self.fmt,
                format!("line {}", self.line),
                format!("bad number {t:?}"),
            )
        })
    }

    fn err(&self, message: impl Into<String>) -> Error {
        Error::import(self.fmt, format!("line {}", self.line), message)
    }
}

/// Counts read from a file are trusted only this far before allocation: a corrupt count must not
/// make us reserve gigabytes; vectors still grow as values actually arrive.
const RESERVE_LIMIT: usize = 1 << 20;

fn read_legacy(text: &str) -> Result<RawMesh> {
    const FMT: &str = "vtk";
    let mut lines = text.lines();
    if !lines.next().unwrap_or("").starts_with("# vtk DataFile") {
        return Err(Error::import(
            FMT,
            "line 1".to_string(),
            "expected \"# vtk DataFile Version …\"",
        ));
    }
    let _title = lines.next();
    if lines.next().map(str::trim) != Some("ASCII") {
        return Err(Error::import(
            FMT,
            "line 3".to_string(),
            "only ASCII legacy files are supported",
        ));
    }
    let body_start: usize = text
        .lines()
        .take(3)
        .map(|l| l.len() + 1)
        .sum::<usize>()
        .min(text.len());
    let mut t = Tokens::new(&text[body_start..], FMT);
    let mut raw = RawMesh::default();
    let (mut cells, mut types): (Vec<Vec<i64>>, Vec<i64>) = (Vec::new(), Vec::new());
    let mut section_count = 0usize;
    let mut in_point_data = false;
    while let Some(word) = t.next() {
        match word.to_ascii_uppercase().as_str() {
            "DATASET" => {
                let kind = t.expect()?;
                if !kind.eq_ignore_ascii_case("UNSTRUCTURED_GRID") {
                    return Err(t.err(format!(
                        "DATASET {kind} is not supported (expected UNSTRUCTURED_GRID)"
                    )));
                }
            }
            "POINTS" => {
                let n: usize = t.parse()?;
                let _ty = t.expect()?;
                raw.points.reserve(n.min(RESERVE_LIMIT));
                for _ in 0..n {
                    raw.points.push([t.parse()?, t.parse()?, t.parse()?]);
                }
            }
            "CELLS" => {
                let n: usize = t.parse()?;
                let size: usize = t.parse()?;
                let next = t.expect()?;
                if next.eq_ignore_ascii_case("OFFSETS") {
                    // File version 5.x: OFFSETS vtktypeint64 <n> values, CONNECTIVITY <ty> <size>.
                    let _ty = t.expect()?;
                    let offsets: Vec<usize> = (0..n).map(|_| t.parse()).collect::<Result<_>>()?;
                    if !t.expect()?.eq_ignore_ascii_case("CONNECTIVITY") {
                        return Err(t.err("expected CONNECTIVITY"));
                    }
                    let _ty = t.expect()?;
                    let conn: Vec<i64> = (0..size).map(|_| t.parse()).collect::<Result<_>>()?;
                    for w in offsets.windows(2) {
                        if w[0] > w[1] || w[1] > conn.len() {
                            return Err(t.err("offsets must increase within the connectivity"));
                        }
                        cells.push(conn[w[0]..w[1]].to_vec());
                    }
                } else {
                    let mut first = Some(next);
                    for _ in 0..n {
                        let k: usize = match first.take() {
                            Some(s) => s.parse().map_err(|_| t.err(format!("bad count {s:?}")))?,
                            None => t.parse()?,
                        };
                        if k > 64 {
                            return Err(t.err(format!("cell with {k} nodes")));
                        }
                        cells.push((0..k).map(|_| t.parse()).collect::<Result<_>>()?);
                    }
                }
            }
            "CELL_TYPES" => {
                let n: usize = t.parse()?;
                types = (0..n).map(|_| t.parse()).collect::<Result<_>>()?;
            }
            "POINT_DATA" => {
                section_count = t.parse()?;
                in_point_data = true;
            }
            "CELL_DATA" => {
                section_count = t.parse()?;
                in_point_data = false;
            }
            "SCALARS" => {
                let name = t.expect()?.to_string();
                let _ty = t.expect()?;
                let rest = t.rest_of_line();
                let comps: usize = rest.first().and_then(|c| c.parse().ok()).unwrap_or(1);
                if t.next().map(|w| w.eq_ignore_ascii_case("LOOKUP_TABLE")) != Some(true) {
                    return Err(t.err("expected LOOKUP_TABLE after SCALARS"));
                }
                let _table = t.expect()?;
                let values: Vec<f64> = (0..section_count * comps)
                    .map(|_| t.parse())
                    .collect::<Result<_>>()?;
                if in_point_data && comps == 1 {
                    raw.fields.push((name, values));
                }
            }
            "NORMALS" | "VECTORS" => {
                let _name = t.expect()?;
                let _ty = t.expect()?;
                for _ in 0..3 * section_count {
                    t.parse::<f64>()?;
                }
            }
            "FIELD" => {
                let _name = t.expect()?;
                let k: usize = t.parse()?;
                for _ in 0..k {
                    let name = t.expect()?.to_string();
                    let comps: usize = t.parse()?;
                    let tuples: usize = t.parse()?;
                    let _ty = t.expect()?;
                    let values: Vec<f64> = (0..comps.saturating_mul(tuples))
                        .map(|_| t.parse())
                        .collect::<Result<_>>()?;
                    if in_point_data && comps == 1 && tuples == raw.points.len() {
                        raw.fields.push((name, values));
                    }
                }
            }
            "METADATA" => {
                // Informational block ending at a blank line; skip its tokens until a keyword.
                while let Some(w) = t.next() {
                    if w == "INFORMATION"
                        || w == "COMPONENT_NAMES"
                        || w.starts_with("NAME")
                        || w.starts_with("DATA")
                    {
                        continue;
                    }
                    if w.chars().all(|c| c.is_ascii_uppercase() || c == '_') && w.len() > 3 {
                        break;
                    }
                }
            }
            other => return Err(t.err(format!("unexpected keyword {other:?}"))),
        }
    }
    if types.len() != cells.len() {
        return Err(Error::import(
            FMT,
            None,
            format!("{} cells but {} cell types", cells.len(), types.len()),
        ));
    }
    let npts = raw.points.len();
    for (i, (ids, &ty)) in cells.iter().zip(&types).enumerate() {
        if let Some(k) = vtk_corners(ty) {
            push_cell(&mut raw, k, ids, npts, FMT, || format!("cell {i}"))?;
        }
    }
    Ok(raw)
}

fn read_msh(text: &str) -> Result<RawMesh> {
    const FMT: &str = "msh";
    let mut t = Tokens::new(text, FMT);
    let mut raw = RawMesh::default();
    let mut tag_to_index: std::collections::HashMap<u64, u32> = std::collections::HashMap::new();
    let mut elements: Vec<(usize, Vec<u64>)> = Vec::new();
    let mut node_data: Vec<(String, Vec<(u64, f64)>)> = Vec::new();
    while let Some(section) = t.next() {
        match section {
            "$MeshFormat" => {
                let version = t.expect()?;
                if !version.starts_with('4') {
                    return Err(t.err(format!(
                        "MSH version {version} is not supported (expected 4.x)"
                    )));
                }
                let file_type: u32 = t.parse()?;
                if file_type != 0 {
                    return Err(t.err("binary MSH is not supported (expected ASCII)"));
                }
                let _size = t.expect()?;
                skip_to(&mut t, "$EndMeshFormat")?;
            }
            "$Nodes" => {
                let blocks: usize = t.parse()?;
                let total: usize = t.parse()?;
                let _min = t.expect()?;
                let _max = t.expect()?;
                raw.points.reserve(total.min(RESERVE_LIMIT));
                for _ in 0..blocks {
                    let _dim = t.expect()?;
                    let _tag = t.expect()?;
                    let parametric: u32 = t.parse()?;
                    let n: usize = t.parse()?;
                    let tags: Vec<u64> = (0..n).map(|_| t.parse()).collect::<Result<_>>()?;
                    for tag in tags {
                        let p = [t.parse()?, t.parse()?, t.parse()?];
                        if parametric != 0 {
                            return Err(t.err("parametric node coordinates are not supported"));
                        }
                        tag_to_index.insert(tag, raw.points.len() as u32);
                        raw.points.push(p);
                    }
                }
                skip_to(&mut t, "$EndNodes")?;
            }
            "$Elements" => {
                let blocks: usize = t.parse()?;
                let _total = t.expect()?;
                let _min = t.expect()?;
                let _max = t.expect()?;
                for _ in 0..blocks {
                    let _dim = t.expect()?;
                    let _tag = t.expect()?;
                    let ty: u32 = t.parse()?;
                    let n: usize = t.parse()?;
                    let nodes = match ty {
                        2 => 3,
                        4 => 4,
                        9 => 6,
                        11 => 10,
                        1 => 2,
                        15 => 1,
                        8 => 3,
                        3 => 4,
                        _ => return Err(t.err(format!("element type {ty} is not supported"))),
                    };
                    let corners = match ty {
                        2 | 9 => 3,
                        4 | 11 => 4,
                        _ => 0,
                    };
                    for _ in 0..n {
                        let _etag = t.expect()?;
                        let ids: Vec<u64> = (0..nodes).map(|_| t.parse()).collect::<Result<_>>()?;
                        if corners > 0 {
                            elements.push((corners, ids));
                        }
                    }
                }
                skip_to(&mut t, "$EndElements")?;
            }
            "$NodeData" => {
                let nstr: usize = t.parse()?;
                let mut strings = Vec::new();
                for _ in 0..nstr {
                    strings.push(t.expect()?.trim_matches('"').to_string());
                }
                let nreal: usize = t.parse()?;
                for _ in 0..nreal {
                    t.expect()?;
                }
                let nint: usize = t.parse()?;
                let ints: Vec<usize> = (0..nint).map(|_| t.parse()).collect::<Result<_>>()?;
                let comps = ints.get(1).copied().unwrap_or(1);
                let count = ints.get(2).copied().unwrap_or(0);
                let mut values = Vec::with_capacity(count.min(RESERVE_LIMIT));
                for _ in 0..count {
                    let tag: u64 = t.parse()?;
                    let v: f64 = t.parse()?;
                    for _ in 1..comps {
                        t.parse::<f64>()?;
                    }
                    values.push((tag, v));
                }
                if comps == 1 {
                    node_data.push((strings.first().cloned().unwrap_or_default(), values));
                }
                skip_to(&mut t, "$EndNodeData")?;
            }
            s if s.starts_with('$') && !s.starts_with("$End") => {
                let end = format!("$End{}", &s[1..]);
                skip_to(&mut t, &end)?;
            }
            other => return Err(t.err(format!("unexpected token {other:?} between sections"))),
        }
    }
    let npts = raw.points.len();
    for (i, (corners, tags)) in elements.iter().enumerate() {
        let ids: Vec<i64> = tags
            .iter()
            .map(|tag| {
                tag_to_index.get(tag).map(|&x| i64::from(x)).ok_or_else(|| {
                    Error::import(
                        FMT,
                        format!("element {i}"),
                        format!("unknown node tag {tag}"),
                    )
                })
            })
            .collect::<Result<_>>()?;
        push_cell(&mut raw, *corners, &ids, npts, FMT, || {
            format!("element {i}")
        })?;
    }
    for (name, pairs) in node_data {
        let mut values = vec![f64::NAN; npts];
        for (tag, v) in pairs {
            let &i = tag_to_index.get(&tag).ok_or_else(|| {
                Error::import(
                    FMT,
                    format!("NodeData {name}"),
                    format!("unknown node tag {tag}"),
                )
            })?;
            values[i as usize] = v;
        }
        raw.fields.push((name, values));
    }
    Ok(raw)
}

fn skip_to(t: &mut Tokens, end: &str) -> Result<()> {
    while let Some(w) = t.next() {
        if w == end {
            return Ok(());
        }
    }
    Err(t.err(format!("missing {end}")))
}

/// Converts a read mesh into a linear ISM.
///
/// # Errors
/// [`Error::Import`] when the mesh has no simplices, the field is missing or has a value equal to
/// the level (or not finite) on a used node, a 2D mesh is not planar, or a cell is degenerate.
pub fn to_model(raw: &RawMesh, options: &ImportOptions) -> Result<(Model, ImportReport)> {
    const FMT: &str = "mesh";
    let limits = &options.limits;
    let cells = raw.tetrahedra.len().max(raw.triangles.len()) as u64;
    for (count, limit, what, field) in [
        (
            raw.points.len() as u64,
            limits.max_vertices,
            "points",
            "max_vertices",
        ),
        (cells, limits.max_simplices, "cells", "max_simplices"),
    ] {
        if count > limit {
            return Err(Error::import(
                FMT,
                None,
                format!("{count} {what}; this reader accepts at most {limit} (Limits::{field})"),
            ));
        }
    }
    let (n, cells): (usize, Vec<Vec<u32>>) = if !raw.tetrahedra.is_empty() {
        (3, raw.tetrahedra.iter().map(|c| c.to_vec()).collect())
    } else if !raw.triangles.is_empty() {
        (2, raw.triangles.iter().map(|c| c.to_vec()).collect())
    } else {
        return Err(Error::import(FMT, None, "no triangles or tetrahedra"));
    };
    let (field, values) = match &options.field {
        Some(name) => raw.fields.iter().find(|(f, _)| f == name).ok_or_else(|| {
            let names: Vec<&str> = raw.fields.iter().map(|(f, _)| f.as_str()).collect();
            Error::import(
                FMT,
                None,
                format!("no point field {name:?}; the file has {names:?}"),
            )
        })?,
        None => raw
            .fields
            .first()
            .ok_or_else(|| Error::import(FMT, None, "the mesh has no scalar point field"))?,
    };
    if n == 2 {
        let z0 = raw.points.first().map_or(0.0, |p| p[2]);
        if let Some(i) = raw.points.iter().position(|p| p[2] != z0) {
            return Err(Error::import(
                FMT,
                format!("point {i}"),
                "a triangle mesh must lie in a plane z = const to become a 2D model",
            ));
        }
    }
    // Keep only used nodes, in first-use order of the original numbering.
    let mut new_id = vec![u32::MAX; raw.points.len()];
    let mut used: Vec<u32> = Vec::new();
    for c in &cells {
        for &v in c {
            if new_id[v as usize] == u32::MAX {
                new_id[v as usize] = 0;
                used.push(v);
            }
        }
    }
    used.sort_unstable();
    for (k, &v) in used.iter().enumerate() {
        new_id[v as usize] = k as u32;
    }
    let mut model = Model::new(n as u8);
    model.level = options.level;
    model.metadata.generator = Some(format!("ism-export {} import", env!("CARGO_PKG_VERSION")));
    for &v in &used {
        let p = raw.points[v as usize];
        model.vertices.extend_from_slice(&p[..n]);
        let f = values[v as usize];
        if !f.is_finite() {
            return Err(Error::import(
                FMT,
                format!("node {v}"),
                format!("field {field:?} is not finite there ({f})"),
            ));
        }
        if f == options.level {
            return Err(Error::import(
                FMT,
                format!("node {v}"),
                format!(
                    "field {field:?} equals the level {} there; choose another level",
                    options.level
                ),
            ));
        }
        model.values.push(f);
    }
    let mut report = ImportReport {
        field: field.clone(),
        dropped_nodes: raw.points.len() - used.len(),
        dropped_triangles: if n == 3 { raw.triangles.len() } else { 0 },
        ..Default::default()
    };
    for (i, c) in cells.iter().enumerate() {
        let mut ids: Vec<u32> = c.iter().map(|&v| new_id[v as usize]).collect();
        let p = |k: usize| &raw.points[c[k] as usize];
        let det = if n == 2 {
            (p(1)[0] - p(0)[0]) * (p(2)[1] - p(0)[1]) - (p(1)[1] - p(0)[1]) * (p(2)[0] - p(0)[0])
        } else {
            let e = |k: usize| [p(k)[0] - p(0)[0], p(k)[1] - p(0)[1], p(k)[2] - p(0)[2]];
            let (a, b, d) = (e(1), e(2), e(3));
            a[0] * (b[1] * d[2] - b[2] * d[1]) - a[1] * (b[0] * d[2] - b[2] * d[0])
                + a[2] * (b[0] * d[1] - b[1] * d[0])
        };
        if det == 0.0 || !det.is_finite() {
            return Err(Error::import(
                FMT,
                format!("cell {i}"),
                "degenerate cell (zero volume)",
            ));
        }
        if det < 0.0 {
            ids.swap(n - 1, n);
            report.reoriented += 1;
        }
        model.simplices.extend_from_slice(&ids);
    }
    // A tool never writes a file it refuses to read: the reader's own structural checks (spec §3.1:
    // degeneracy relative to the longest edge, duplicate cells, facets shared by three cells, …)
    // decide, not a second copy of them here. Simplex `s` is kept cell `s`. (Found by the
    // `import_mesh` fuzz target: a cell of relative volume 1e-29 became an ISM-107 file.)
    if let Some(d) = ism_format::structure::check(&model, 1)
        .into_iter()
        .find(|d| d.severity == ism_format::Severity::Error)
    {
        return Err(Error::import(
            FMT,
            d.location.simplex.map(|s| format!("cell {s}")),
            format!("the cells do not make a valid model: {d}"),
        ));
    }
    Ok((model, report))
}

#[cfg(test)]
mod tests {
    use super::*;
    use base64::Engine;

    const LEGACY: &str = "# vtk DataFile Version 4.2\ntwo tets\nASCII\nDATASET UNSTRUCTURED_GRID\nPOINTS 6 double\n\
0 0 0  1 0 0  0 1 0  0 0 1  1 1 1  9 9 9\nCELLS 3 14\n4 0 1 2 3\n4 1 3 2 4\n3 0 1 2\nCELL_TYPES 3\n10 10 5\n\
POINT_DATA 6\nSCALARS f double 1\nLOOKUP_TABLE default\n-1 1 1 1 2 5\n";

    #[test]
    fn legacy_tets_are_reoriented_and_unused_nodes_dropped() {
        let raw = read_mesh(LEGACY.as_bytes(), ImportFormat::VtkLegacy).unwrap();
        assert_eq!(
            (raw.points.len(), raw.tetrahedra.len(), raw.triangles.len()),
            (6, 2, 1)
        );
        let (model, report) = to_model(&raw, &ImportOptions::default()).unwrap();
        assert_eq!(model.dimension, 3);
        assert_eq!(model.num_vertices(), 5);
        assert_eq!(report.dropped_nodes, 1);
        assert_eq!(report.dropped_triangles, 1);
        // (1, 3, 2, 4) is negatively oriented as listed.
        assert_eq!(report.reoriented, 1);
        assert_eq!(model.simplex(1), &[1, 3, 4, 2]);
        assert!(ism_format::structure::check(&model, 10)
            .iter()
            .all(|d| d.severity != ism_format::Severity::Error));
    }

    #[test]
    fn value_at_the_level_and_missing_field_are_refused() {
        let raw = read_mesh(LEGACY.as_bytes(), ImportFormat::VtkLegacy).unwrap();
        let err = to_model(
            &raw,
            &ImportOptions {
                field: None,
                level: 1.0,
                ..ImportOptions::default()
            },
        )
        .unwrap_err();
        assert!(err.to_string().contains("equals the level"), "{err}");
        let err = to_model(
            &raw,
            &ImportOptions {
                field: Some("g".into()),
                level: 0.0,
                ..ImportOptions::default()
            },
        )
        .unwrap_err();
        assert!(err.to_string().contains("no point field \"g\""), "{err}");
    }

    /// The entity limits: points and cells above `Limits` are refused before anything is built
    /// (counts from the parsed mesh: 6 points, 2 tetrahedra); at exactly those counts the
    /// mesh converts; a file larger than `max_payload_bytes` is refused before it is read.
    #[test]
    fn import_limits_refuse_larger_meshes() {
        let raw = read_mesh(LEGACY.as_bytes(), ImportFormat::VtkLegacy).unwrap();
        let points = raw.points.len() as u64;
        let cells = raw.tetrahedra.len().max(raw.triangles.len()) as u64;
        let with = |max_vertices: u64, max_simplices: u64| ImportOptions {
            limits: ism_format::io::Limits {
                max_vertices,
                max_simplices,
                ..Default::default()
            },
            ..ImportOptions::default()
        };
        to_model(&raw, &with(points, cells)).expect("at the limits");
        let err = to_model(&raw, &with(points - 1, cells)).unwrap_err();
        assert!(err.to_string().contains("Limits::max_vertices"), "{err}");
        let err = to_model(&raw, &with(points, cells - 1)).unwrap_err();
        assert!(err.to_string().contains("Limits::max_simplices"), "{err}");
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.vtk");
        std::fs::write(&path, LEGACY).unwrap();
        let small = ImportOptions {
            limits: ism_format::io::Limits {
                max_payload_bytes: LEGACY.len() as u64 - 1,
                ..Default::default()
            },
            ..ImportOptions::default()
        };
        let err = import_path(&path, &small).unwrap_err();
        assert!(
            err.to_string().contains("Limits::max_payload_bytes"),
            "{err}"
        );
        import_path(&path, &ImportOptions::default()).expect("within the default limits");
    }

    #[test]
    fn vtu_ascii_and_binary_agree() {
        let grid_text = |binary: bool| {
            let enc = |v: &[f64]| {
                let mut b = (v.len() as u64 * 8).to_le_bytes().to_vec();
                for x in v {
                    b.extend_from_slice(&x.to_le_bytes());
                }
                base64::engine::general_purpose::STANDARD.encode(b)
            };
            let arr = |name: &str, comps: usize, v: &[f64]| {
                if binary {
                    format!(
                        r#"<DataArray type="Float64" Name="{name}" NumberOfComponents="{comps}" format="binary">{}</DataArray>"#,
                        enc(v)
                    )
                } else {
                    let s: Vec<String> = v.iter().map(|x| x.to_string()).collect();
                    format!(
                        r#"<DataArray type="Float64" Name="{name}" NumberOfComponents="{comps}" format="ascii">{}</DataArray>"#,
                        s.join(" ")
                    )
                }
            };
            format!(
                r#"<?xml version="1.0"?><VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" header_type="UInt64"><UnstructuredGrid><Piece NumberOfPoints="3" NumberOfCells="1"><PointData Scalars="f">{}</PointData><Points>{}</Points><Cells>{}{}{}</Cells></Piece></UnstructuredGrid></VTKFile>"#,
                arr("f", 1, &[-1.0, 2.0, 3.0]),
                arr("p", 3, &[0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0]),
                arr("connectivity", 1, &[0.0, 1.0, 2.0]),
                arr("offsets", 1, &[3.0]),
                arr("types", 1, &[5.0]),
            )
        };
        let a = read_mesh(grid_text(false).as_bytes(), ImportFormat::Vtu).unwrap();
        let b = read_mesh(grid_text(true).as_bytes(), ImportFormat::Vtu).unwrap();
        assert_eq!(a, b);
        let (model, report) = to_model(&a, &ImportOptions::default()).unwrap();
        assert_eq!(model.dimension, 2);
        assert_eq!(report.reoriented, 1);
        assert_eq!(model.simplex(0), &[0, 2, 1]);
    }

    #[test]
    fn msh4_quadratic_tet_keeps_its_corners() {
        let msh = "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n1 10 1 10\n3 1 0 10\n1\n2\n3\n4\n5\n6\n7\n8\n9\n10\n\
0 0 0\n1 0 0\n0 1 0\n0 0 1\n.5 0 0\n.5 .5 0\n0 .5 0\n0 0 .5\n0 .5 .5\n.5 0 .5\n$EndNodes\n\
$Elements\n1 1 1 1\n3 1 11 1\n1 1 2 3 4 5 6 7 8 10 9\n$EndElements\n\
$NodeData\n1\n\"f\"\n1\n0\n3\n0\n1\n4\n1 -1\n2 1\n3 1\n4 1\n$EndNodeData\n";
        let raw = read_mesh(msh.as_bytes(), ImportFormat::Msh).unwrap();
        assert_eq!(raw.tetrahedra, vec![[0, 1, 2, 3]]);
        // Nodes 5..10 have no value in the field, but only corners become vertices.
        let (model, report) = to_model(&raw, &ImportOptions::default()).unwrap();
        assert_eq!((model.num_vertices(), report.dropped_nodes), (4, 6));
        assert_eq!(model.values, vec![-1.0, 1.0, 1.0, 1.0]);
    }

    /// Cells the reader would refuse are refused at import, with the reader's rule (fuzz finding:
    /// `fuzz/artifacts/import_mesh/crash-092f37…`, a tetrahedron of relative volume 1e-29).
    #[test]
    fn cells_the_reader_refuses_are_not_imported() {
        let import = |cells: &str, points: &str| {
            let text = format!(
                "# vtk DataFile Version 4.2\nx\nASCII\nDATASET UNSTRUCTURED_GRID\nPOINTS 5 double\n\
                 {points}\nCELLS 2 10\n{cells}\nCELL_TYPES 2\n10 10\n\
                 POINT_DATA 5\nSCALARS f double 1\nLOOKUP_TABLE default\n-1 1 1 1 2\n"
            );
            let raw = read_mesh(text.as_bytes(), ImportFormat::VtkLegacy).unwrap();
            to_model(&raw, &ImportOptions::default())
                .unwrap_err()
                .to_string()
        };
        let cube = "0 0 0  1 0 0  0 1 0  0 0 1  1 1 1";
        let twice = import("4 0 1 2 3\n4 0 1 3 2", cube);
        assert!(
            twice.contains("at cell 1") && twice.contains("ISM-108"),
            "{twice}"
        );
        let flat = import(
            "4 0 1 2 3\n4 1 3 2 4",
            "0 0 0  1 0 0  0 1 0  1e-30 1e-30 1e-29  1 1 1",
        );
        assert!(
            flat.contains("at cell 0") && flat.contains("ISM-107"),
            "{flat}"
        );
    }

    #[test]
    fn truncated_inputs_fail_without_panicking() {
        for cut in 0..LEGACY.len() {
            let _ = read_mesh(&LEGACY.as_bytes()[..cut], ImportFormat::VtkLegacy);
        }
    }
}
