//! Point sets as columns, the [`Sink`] they stream into, and the file writers (PLY, CSV, NPY).
//!
//! A sampler produces [`SampleBlock`]s in a fixed order and hands each to a [`Sink`]: a writer of
//! one of the [`OutputFormat`]s, a [`Collect`] that keeps everything in memory, or any caller type.
//! Every format states its row count up front (PLY and NPY headers need it), so the writers stream
//! without buffering the whole set.

use std::io::Write;
use std::path::Path;

use crate::error::{Result, SampleError};

/// One kind of per-point data, in the order the writers emit them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Column {
    /// Coordinates `x y [z]` (f64).
    Position,
    /// Unit normal `nx ny [nz]`: `∇F/|∇F|`, pointing to the outside (`F > c`) (f64).
    Normal,
    /// `f = F(p) − c`, the signed deviation from the level (f64; NaN outside `|K|`).
    Value,
    /// `gx gy [gz]` = `∇F(p)` (f64; NaN outside `|K|`).
    Gradient,
    /// `label`: 1 inside the shape (`F < c`), 0 outside it, −1 outside `|K|` (i8).
    Label,
    /// `sign`: the sign of `F − c` (−1, 0, 1), 0 outside `|K|` (i8).
    Sign,
    /// `simplex`: id of the containing (or source) top simplex, −1 outside `|K|` (i32).
    Simplex,
}

/// Scalar type of one output field.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FieldType {
    /// IEEE double, little-endian in binary formats.
    F64,
    /// Signed byte.
    I8,
    /// Signed 32-bit integer, little-endian in binary formats.
    I32,
}

impl Column {
    /// The scalar fields this column contributes in a `dim`-dimensional set, with their names.
    pub fn fields(self, dim: usize) -> Vec<(&'static str, FieldType)> {
        let axes = |names: [&'static str; 3]| {
            names[..dim.min(3)]
                .iter()
                .map(|&s| (s, FieldType::F64))
                .collect()
        };
        match self {
            Column::Position => axes(["x", "y", "z"]),
            Column::Normal => axes(["nx", "ny", "nz"]),
            Column::Gradient => axes(["gx", "gy", "gz"]),
            Column::Value => vec![("f", FieldType::F64)],
            Column::Label => vec![("label", FieldType::I8)],
            Column::Sign => vec![("sign", FieldType::I8)],
            Column::Simplex => vec![("simplex", FieldType::I32)],
        }
    }
}

/// What a point set holds: its dimension, columns and total row count.
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    /// Space dimension (2 or 3).
    pub dim: usize,
    /// The columns, in output order.
    pub columns: Vec<Column>,
    /// Number of rows the sink will receive in total.
    pub count: u64,
}

impl Header {
    /// All scalar fields of a row, with names and types, in output order.
    pub fn fields(&self) -> Vec<(&'static str, FieldType)> {
        self.columns
            .iter()
            .flat_map(|c| c.fields(self.dim))
            .collect()
    }

    /// Whether the set has `column`.
    pub fn has(&self, column: Column) -> bool {
        self.columns.contains(&column)
    }
}

/// A block of rows stored column-wise. Vectors of columns the header lacks stay empty.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SampleBlock {
    /// `dim` coordinates per row.
    pub positions: Vec<f64>,
    /// `dim` numbers per row.
    pub normals: Vec<f64>,
    /// One per row.
    pub values: Vec<f64>,
    /// `dim` numbers per row.
    pub gradients: Vec<f64>,
    /// One per row.
    pub labels: Vec<i8>,
    /// One per row.
    pub signs: Vec<i8>,
    /// One per row; −1 for none.
    pub simplices: Vec<i32>,
}

impl SampleBlock {
    /// Number of rows, given the dimension.
    pub fn len(&self, dim: usize) -> usize {
        self.positions.len() / dim.max(1)
    }

    /// Whether the block has no rows.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Appends every row of `other`.
    pub fn append(&mut self, other: &SampleBlock) {
        self.positions.extend_from_slice(&other.positions);
        self.normals.extend_from_slice(&other.normals);
        self.values.extend_from_slice(&other.values);
        self.gradients.extend_from_slice(&other.gradients);
        self.labels.extend_from_slice(&other.labels);
        self.signs.extend_from_slice(&other.signs);
        self.simplices.extend_from_slice(&other.simplices);
    }

    /// Checks that every column of `header` has one entry (or `dim`) per row and the others none.
    fn check(&self, header: &Header) -> Result<usize> {
        let dim = header.dim;
        let rows = self.len(dim);
        let expect = |col: Column, got: usize, per: usize| -> Result<()> {
            let want = if header.has(col) { rows * per } else { 0 };
            if got != want {
                return Err(SampleError::InvalidArgument(format!(
                    "sample block column {col:?} has {got} numbers, expected {want} for {rows} rows"
                )));
            }
            Ok(())
        };
        expect(Column::Position, self.positions.len(), dim)?;
        expect(Column::Normal, self.normals.len(), dim)?;
        expect(Column::Value, self.values.len(), 1)?;
        expect(Column::Gradient, self.gradients.len(), dim)?;
        expect(Column::Label, self.labels.len(), 1)?;
        expect(Column::Sign, self.signs.len(), 1)?;
        expect(Column::Simplex, self.simplices.len(), 1)?;
        Ok(rows)
    }
}

/// A scalar of one row, for the row-wise writers.
#[derive(Clone, Copy, Debug)]
enum Scalar {
    F64(f64),
    I8(i8),
    I32(i32),
}

/// Visits row `r`'s scalars in field order; `pad3` adds zero `z`/`nz`/`gz` fields to 2D vectors.
fn row_scalars(block: &SampleBlock, header: &Header, r: usize, pad3: bool, out: &mut Vec<Scalar>) {
    let dim = header.dim;
    out.clear();
    let vector = |v: &[f64], out: &mut Vec<Scalar>| {
        out.extend(v[r * dim..(r + 1) * dim].iter().map(|&x| Scalar::F64(x)));
        if pad3 && dim == 2 {
            out.push(Scalar::F64(0.0));
        }
    };
    for col in &header.columns {
        match col {
            Column::Position => vector(&block.positions, out),
            Column::Normal => vector(&block.normals, out),
            Column::Gradient => vector(&block.gradients, out),
            Column::Value => out.push(Scalar::F64(block.values[r])),
            Column::Label => out.push(Scalar::I8(block.labels[r])),
            Column::Sign => out.push(Scalar::I8(block.signs[r])),
            Column::Simplex => out.push(Scalar::I32(block.simplices[r])),
        }
    }
}

/// The little-endian rows of a binary PLY or NPY block: the bytes of [`row_scalars`]' scalars
/// row after row, written column by column into place (a row-wise list of tagged scalars cost
/// a fifth of the write, session 19). `pad3`'s zero components are `0.0`, whose bytes are the
/// zero fill.
fn encode_binary(
    block: &SampleBlock,
    header: &Header,
    rows: usize,
    pad3: bool,
    bytes: &mut Vec<u8>,
) {
    let dim = header.dim;
    let slots = if pad3 { dim.max(3) } else { dim };
    let width = |col: &Column| match col {
        Column::Position | Column::Normal | Column::Gradient => 8 * slots,
        Column::Value => 8,
        Column::Label | Column::Sign => 1,
        Column::Simplex => 4,
    };
    let stride: usize = header.columns.iter().map(width).sum();
    bytes.clear();
    bytes.resize(rows * stride, 0);
    let mut offset = 0;
    for col in &header.columns {
        let rows_out = bytes.chunks_exact_mut(stride);
        let at = offset;
        match col {
            Column::Position | Column::Normal | Column::Gradient => {
                let v = match col {
                    Column::Position => &block.positions,
                    Column::Normal => &block.normals,
                    _ => &block.gradients,
                };
                for (out, x) in rows_out.zip(v.chunks_exact(dim)) {
                    for (k, &c) in x.iter().enumerate() {
                        out[at + 8 * k..at + 8 * k + 8].copy_from_slice(&c.to_le_bytes());
                    }
                }
            }
            Column::Value => {
                for (out, &x) in rows_out.zip(&block.values) {
                    out[at..at + 8].copy_from_slice(&x.to_le_bytes());
                }
            }
            Column::Label | Column::Sign => {
                let v = if *col == Column::Label {
                    &block.labels
                } else {
                    &block.signs
                };
                for (out, &x) in rows_out.zip(v) {
                    out[at] = x.to_le_bytes()[0];
                }
            }
            Column::Simplex => {
                for (out, &x) in rows_out.zip(&block.simplices) {
                    out[at..at + 4].copy_from_slice(&x.to_le_bytes());
                }
            }
        }
        offset += width(col);
    }
}

/// Receives a point set block by block: `begin` once, `block` in order, `finish` once.
pub trait Sink {
    /// Called once before any block.
    ///
    /// # Errors
    /// Whatever the sink's output reports.
    fn begin(&mut self, header: &Header) -> Result<()>;
    /// Called for each block, in order.
    ///
    /// # Errors
    /// Whatever the sink's output reports.
    fn block(&mut self, block: &SampleBlock) -> Result<()>;
    /// Called once after the last block.
    ///
    /// # Errors
    /// Whatever the sink's output reports, or a row count that differs from the header's.
    fn finish(&mut self) -> Result<()>;
}

/// A sink that keeps every row in memory.
#[derive(Clone, Debug, Default)]
pub struct Collect {
    /// The header received, once `begin` ran.
    pub header: Option<Header>,
    /// All rows received.
    pub rows: SampleBlock,
}

impl Sink for Collect {
    fn begin(&mut self, header: &Header) -> Result<()> {
        self.header = Some(header.clone());
        Ok(())
    }
    fn block(&mut self, block: &SampleBlock) -> Result<()> {
        self.rows.append(block);
        Ok(())
    }
    fn finish(&mut self) -> Result<()> {
        Ok(())
    }
}

/// The file formats of point sets.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum OutputFormat {
    /// PLY, `binary_little_endian 1.0`; 2D sets are written with `z = 0` (and `nz = 0`), since
    /// point-cloud tools expect three coordinates.
    PlyBinary,
    /// PLY, `ascii 1.0`; as [`OutputFormat::PlyBinary`] otherwise.
    PlyAscii,
    /// Comma-separated values with a header line of field names.
    Csv,
    /// A NumPy `.npy` file (format 1.0) holding a one-dimensional structured array whose field
    /// names are those of the CSV header (`a["x"]`, `a["label"]`, …).
    Npy,
}

impl OutputFormat {
    /// Every format.
    pub const ALL: [OutputFormat; 4] = [
        OutputFormat::PlyBinary,
        OutputFormat::PlyAscii,
        OutputFormat::Csv,
        OutputFormat::Npy,
    ];

    /// The format a file name implies: `.ply` (binary), `.csv`, `.npy`.
    pub fn from_path(path: &Path) -> Option<OutputFormat> {
        match path.extension()?.to_str()?.to_ascii_lowercase().as_str() {
            "ply" => Some(OutputFormat::PlyBinary),
            "csv" => Some(OutputFormat::Csv),
            "npy" => Some(OutputFormat::Npy),
            _ => None,
        }
    }

    /// The name used on the command line: `ply`, `ply-ascii`, `csv`, `npy`.
    pub fn name(self) -> &'static str {
        match self {
            OutputFormat::PlyBinary => "ply",
            OutputFormat::PlyAscii => "ply-ascii",
            OutputFormat::Csv => "csv",
            OutputFormat::Npy => "npy",
        }
    }

    /// Parses a name as printed by [`OutputFormat::name`].
    pub fn from_name(name: &str) -> Option<OutputFormat> {
        OutputFormat::ALL.into_iter().find(|f| f.name() == name)
    }
}

/// A [`Sink`] that writes one of the [`OutputFormat`]s to a byte stream as blocks arrive.
#[derive(Debug)]
pub struct FormatWriter<W: Write> {
    out: W,
    format: OutputFormat,
    header: Option<Header>,
    written: u64,
    row: Vec<Scalar>,
    text: String,
    /// The binary formats' bytes of one block, kept between blocks (a fresh quarter-megabyte
    /// buffer per block was mapped and unmapped by the allocator every time).
    bytes: Vec<u8>,
}

impl<W: Write> FormatWriter<W> {
    /// A writer of `format` into `out` (wrap files in a `BufWriter`).
    pub fn new(out: W, format: OutputFormat) -> FormatWriter<W> {
        FormatWriter {
            out,
            format,
            header: None,
            written: 0,
            row: Vec::new(),
            text: String::new(),
            bytes: Vec::new(),
        }
    }

    /// Gives the stream back.
    pub fn into_inner(self) -> W {
        self.out
    }

    fn ply_header(&mut self, header: &Header) -> std::io::Result<()> {
        let kind = if self.format == OutputFormat::PlyAscii {
            "ascii"
        } else {
            "binary_little_endian"
        };
        let mut text = format!("ply\nformat {kind} 1.0\ncomment ISM point set (ism-sample)\n");
        text += &format!("element vertex {}\n", header.count);
        for col in &header.columns {
            // PLY readers expect 3D points: pad a 2D set's vectors with a zero third component.
            for (name, ty) in col.fields(3.max(header.dim)) {
                let ty = match ty {
                    FieldType::F64 => "double",
                    FieldType::I8 => "char",
                    FieldType::I32 => "int",
                };
                text += &format!("property {ty} {name}\n");
            }
        }
        text += "end_header\n";
        self.out.write_all(text.as_bytes())
    }

    fn npy_header(&mut self, header: &Header) -> std::io::Result<()> {
        let descr: Vec<String> = header
            .fields()
            .iter()
            .map(|(name, ty)| {
                let code = match ty {
                    FieldType::F64 => "<f8",
                    FieldType::I8 => "|i1",
                    FieldType::I32 => "<i4",
                };
                format!("('{name}', '{code}')")
            })
            .collect();
        let dict = format!(
            "{{'descr': [{}], 'fortran_order': False, 'shape': ({},), }}",
            descr.join(", "),
            header.count
        );
        // NPY 1.0: magic (6) + version (2) + u16 header length, then the dict padded with spaces
        // and ending in '\n' so that the data starts on a multiple of 64 bytes.
        let unpadded = 10 + dict.len() + 1;
        let total = unpadded.div_ceil(64) * 64;
        let header_len = total - 10;
        let header_len_u16 = u16::try_from(header_len)
            .map_err(|_| std::io::Error::other("NPY header longer than 65535 bytes"))?;
        self.out.write_all(b"\x93NUMPY\x01\x00")?;
        self.out.write_all(&header_len_u16.to_le_bytes())?;
        self.out.write_all(dict.as_bytes())?;
        self.out
            .write_all(&vec![b' '; header_len - dict.len() - 1])?;
        self.out.write_all(b"\n")
    }
}

fn io_err(e: std::io::Error) -> SampleError {
    SampleError::Io {
        path: None,
        source: e,
    }
}

impl<W: Write> Sink for FormatWriter<W> {
    fn begin(&mut self, header: &Header) -> Result<()> {
        if !(2..=3).contains(&header.dim) || !header.has(Column::Position) {
            return Err(SampleError::InvalidArgument(format!(
                "point sets need dimension 2 or 3 and positions (got dimension {})",
                header.dim
            )));
        }
        match self.format {
            OutputFormat::PlyBinary | OutputFormat::PlyAscii => {
                self.ply_header(header).map_err(io_err)?
            }
            OutputFormat::Npy => self.npy_header(header).map_err(io_err)?,
            OutputFormat::Csv => {
                let names: Vec<&str> = header.fields().iter().map(|f| f.0).collect();
                writeln!(self.out, "{}", names.join(",")).map_err(io_err)?;
            }
        }
        self.header = Some(header.clone());
        Ok(())
    }

    fn block(&mut self, block: &SampleBlock) -> Result<()> {
        let header = self
            .header
            .clone()
            .ok_or_else(|| SampleError::InvalidArgument("block before begin".into()))?;
        let rows = block.check(&header)?;
        if self.written + rows as u64 > header.count {
            return Err(SampleError::InvalidArgument(format!(
                "more rows than the {} the header announced",
                header.count
            )));
        }
        let pad3 = matches!(
            self.format,
            OutputFormat::PlyBinary | OutputFormat::PlyAscii
        );
        let binary = matches!(self.format, OutputFormat::PlyBinary | OutputFormat::Npy);
        let separator = if self.format == OutputFormat::Csv {
            ','
        } else {
            ' '
        };
        if binary {
            let mut bytes = std::mem::take(&mut self.bytes);
            encode_binary(block, &header, rows, pad3, &mut bytes);
            let written = self.out.write_all(&bytes).map_err(io_err);
            self.bytes = bytes;
            written?;
            self.written += rows as u64;
            return Ok(());
        }
        let mut row = std::mem::take(&mut self.row);
        let mut text = std::mem::take(&mut self.text);
        text.clear();
        for r in 0..rows {
            use std::fmt::Write as _;
            row_scalars(block, &header, r, pad3, &mut row);
            for (i, s) in row.iter().enumerate() {
                if i > 0 {
                    text.push(separator);
                }
                // `{:?}` on f64 prints the shortest text that reads back to the same double,
                // switching to exponent notation for very large and small magnitudes.
                let _ = match *s {
                    Scalar::F64(x) => write!(text, "{x:?}"),
                    Scalar::I8(x) => write!(text, "{x}"),
                    Scalar::I32(x) => write!(text, "{x}"),
                };
            }
            text.push('\n');
        }
        self.out.write_all(text.as_bytes()).map_err(io_err)?;
        self.row = row;
        self.text = text;
        self.written += rows as u64;
        Ok(())
    }

    fn finish(&mut self) -> Result<()> {
        let expected = self.header.as_ref().map_or(0, |h| h.count);
        if self.written != expected {
            return Err(SampleError::InvalidArgument(format!(
                "wrote {} rows but the header announced {expected}",
                self.written
            )));
        }
        self.out.flush().map_err(io_err)
    }
}

/// Writes a whole in-memory set to `path` atomically (temporary file, then rename).
///
/// # Errors
/// [`SampleError::Io`] naming the path.
pub fn write_path(
    path: &Path,
    format: OutputFormat,
    header: &Header,
    rows: &SampleBlock,
) -> Result<()> {
    let mut inner: Option<SampleError> = None;
    let result = ism_format::io::write_atomic(path, |w| {
        let mut sink = FormatWriter::new(w, format);
        let run = sink
            .begin(header)
            .and_then(|_| sink.block(rows))
            .and_then(|_| sink.finish());
        run.map_err(|e| {
            let msg = ism_format::ErrorChain(&e).to_string();
            inner = Some(e);
            std::io::Error::other(msg)
        })
    });
    match (result, inner) {
        (Ok(()), _) => Ok(()),
        (Err(_), Some(e)) => Err(e),
        (Err(e), None) => Err(SampleError::Io {
            path: Some(path.to_path_buf()),
            source: e,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> (Header, SampleBlock) {
        let header = Header {
            dim: 2,
            columns: vec![
                Column::Position,
                Column::Normal,
                Column::Value,
                Column::Label,
                Column::Simplex,
            ],
            count: 2,
        };
        let rows = SampleBlock {
            positions: vec![0.5, 0.25, 1.0, -2.0],
            normals: vec![1.0, 0.0, 0.0, 1.0],
            values: vec![0.0, -1.5e-300],
            labels: vec![1, 0],
            simplices: vec![3, -1],
            ..SampleBlock::default()
        };
        (header, rows)
    }

    fn write(format: OutputFormat) -> Vec<u8> {
        let (header, rows) = small();
        let mut w = FormatWriter::new(Vec::new(), format);
        w.begin(&header).unwrap();
        w.block(&rows).unwrap();
        w.finish().unwrap();
        w.into_inner()
    }

    #[test]
    fn csv_rows_read_back_exactly() {
        let text = String::from_utf8(write(OutputFormat::Csv)).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "x,y,nx,ny,f,label,simplex");
        assert_eq!(lines[2], "1.0,-2.0,0.0,1.0,-1.5e-300,0,-1");
        let f: f64 = lines[2].split(',').nth(4).unwrap().parse().unwrap();
        assert_eq!(f, -1.5e-300);
    }

    #[test]
    fn ply_binary_pads_2d_and_has_exact_length() {
        let bytes = write(OutputFormat::PlyBinary);
        let end = bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .unwrap()
            + 11;
        let header = std::str::from_utf8(&bytes[..end]).unwrap();
        assert!(header.contains("element vertex 2\n"));
        assert!(header.contains("property double z\n") && header.contains("property double nz\n"));
        assert!(
            header.contains("property char label\n") && header.contains("property int simplex\n")
        );
        // x y z nx ny nz f = 7 doubles, 1 char, 1 int per row.
        assert_eq!(bytes.len() - end, 2 * (7 * 8 + 1 + 4));
        let z = f64::from_le_bytes(bytes[end + 16..end + 24].try_into().unwrap());
        assert_eq!(z, 0.0);
        let simplex = i32::from_le_bytes(bytes[bytes.len() - 4..].try_into().unwrap());
        assert_eq!(simplex, -1);
    }

    #[test]
    fn npy_header_is_aligned_and_describes_fields() {
        let bytes = write(OutputFormat::Npy);
        assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
        let hlen = usize::from(u16::from_le_bytes([bytes[8], bytes[9]]));
        assert_eq!((10 + hlen) % 64, 0);
        let dict = std::str::from_utf8(&bytes[10..10 + hlen]).unwrap();
        assert!(dict.contains("('label', '|i1')") && dict.contains("'shape': (2,)"));
        assert!(dict.ends_with('\n'));
        assert_eq!(bytes.len() - 10 - hlen, 2 * (5 * 8 + 1 + 4));
    }

    /// Every column in 2D and 3D, over two blocks, PLY and NPY: each row's bytes decoded field by
    /// field (names and types from the header the file announces) give the block's numbers, the
    /// PLY's padded `z`-components of 2D vectors are `0.0`.
    #[test]
    fn binary_rows_decode_to_the_block() {
        for dim in [2usize, 3] {
            let rows = 5usize;
            let header = Header {
                dim,
                columns: vec![
                    Column::Position,
                    Column::Simplex,
                    Column::Normal,
                    Column::Label,
                    Column::Value,
                    Column::Sign,
                    Column::Gradient,
                ],
                count: 2 * rows as u64,
            };
            let num = |k: usize| (k as f64 - 7.5) * 0.3125e-3 + 1.0 / (k as f64 + 3.0);
            let block = |first: usize| SampleBlock {
                positions: (0..rows * dim).map(|k| num(first + k)).collect(),
                normals: (0..rows * dim).map(|k| -num(first + 2 * k)).collect(),
                gradients: (0..rows * dim)
                    .map(|k| num(first + 3 * k) * 1e300)
                    .collect(),
                values: (0..rows).map(|k| -num(first + 5 * k) * 1e-300).collect(),
                labels: (0..rows).map(|k| [1i8, 0, -1][(first + k) % 3]).collect(),
                signs: (0..rows)
                    .map(|k| [-1i8, 0, 1][(first + 2 * k) % 3])
                    .collect(),
                simplices: (0..rows)
                    .map(|k| [i32::MIN, -1, 7, i32::MAX, 0][(first + k) % 5])
                    .collect(),
            };
            let blocks = [block(0), block(100)];
            for format in [OutputFormat::PlyBinary, OutputFormat::Npy] {
                let mut w = FormatWriter::new(Vec::new(), format);
                w.begin(&header).unwrap();
                for b in &blocks {
                    w.block(b).unwrap();
                }
                w.finish().unwrap();
                let bytes = w.into_inner();
                let pad = format == OutputFormat::PlyBinary;
                let fields: Vec<(&str, FieldType)> = header
                    .columns
                    .iter()
                    .flat_map(|c| c.fields(if pad { 3 } else { dim }))
                    .collect();
                let row_len: usize = fields
                    .iter()
                    .map(|f| match f.1 {
                        FieldType::F64 => 8,
                        FieldType::I8 => 1,
                        FieldType::I32 => 4,
                    })
                    .sum();
                let data = &bytes[bytes.len() - 2 * rows * row_len..];
                for (r, row) in data.chunks_exact(row_len).enumerate() {
                    let (b, k) = (&blocks[r / rows], r % rows);
                    let mut at = 0;
                    for (name, ty) in &fields {
                        let axis = |v: &[f64], a: usize| if a < dim { v[k * dim + a] } else { 0.0 };
                        match ty {
                            FieldType::F64 => {
                                let got = f64::from_le_bytes(row[at..at + 8].try_into().unwrap());
                                let want = match *name {
                                    "x" => axis(&b.positions, 0),
                                    "y" => axis(&b.positions, 1),
                                    "z" => axis(&b.positions, 2),
                                    "nx" => axis(&b.normals, 0),
                                    "ny" => axis(&b.normals, 1),
                                    "nz" => axis(&b.normals, 2),
                                    "gx" => axis(&b.gradients, 0),
                                    "gy" => axis(&b.gradients, 1),
                                    "gz" => axis(&b.gradients, 2),
                                    "f" => b.values[k],
                                    other => panic!("unexpected double field {other}"),
                                };
                                assert_eq!(
                                    got.to_bits(),
                                    want.to_bits(),
                                    "{format:?} {dim}D row {r} {name}"
                                );
                                at += 8;
                            }
                            FieldType::I8 => {
                                let got = row[at] as i8;
                                let want = if *name == "label" {
                                    b.labels[k]
                                } else {
                                    b.signs[k]
                                };
                                assert_eq!(got, want, "{format:?} {dim}D row {r} {name}");
                                at += 1;
                            }
                            FieldType::I32 => {
                                let got = i32::from_le_bytes(row[at..at + 4].try_into().unwrap());
                                assert_eq!(got, b.simplices[k], "{format:?} {dim}D row {r}");
                                at += 4;
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn row_count_mismatch_is_an_error() {
        let (mut header, rows) = small();
        header.count = 3;
        let mut w = FormatWriter::new(Vec::new(), OutputFormat::Csv);
        w.begin(&header).unwrap();
        w.block(&rows).unwrap();
        assert!(w.finish().is_err());
        let mut bad = rows.clone();
        bad.labels.pop();
        let mut w = FormatWriter::new(Vec::new(), OutputFormat::Csv);
        w.begin(&header).unwrap();
        assert!(w.block(&bad).is_err());
    }
}
