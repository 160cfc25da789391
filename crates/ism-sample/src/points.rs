//! Reading query points: CSV / whitespace-separated text, or NPY arrays.
//!
//! Text: one point per line, exactly `n` numbers separated by commas, spaces or tabs; a first line
//! that does not parse as numbers is taken as a header, and when its field names include `x y [z]`
//! those columns are picked and other columns may follow (e.g. `ism query`'s own output); blank
//! lines and lines starting with `#` are skipped. NPY: a C-order array of shape `(N, n)` of
//! `<f8` or `<f4`, or a structured array with fields `x`, `y` (and `z`) of `<f8`/`<f4`. The format is
//! detected from the NPY magic bytes.

use crate::error::{Result, SampleError};

fn points_err(location: Option<String>, message: impl Into<String>) -> SampleError {
    SampleError::Points {
        location,
        message: message.into(),
    }
}

/// Parses points of dimension `dim` from bytes (text or NPY, detected), flat `dim` per point.
///
/// # Errors
/// [`SampleError::Points`] with the line and column (text) or byte offset (NPY) of the problem.
pub fn parse_points(bytes: &[u8], dim: usize) -> Result<Vec<f64>> {
    if bytes.starts_with(b"\x93NUMPY") {
        parse_npy(bytes, dim)
    } else {
        let text = std::str::from_utf8(bytes).map_err(|e| {
            points_err(
                Some(format!("byte {}", e.valid_up_to())),
                "text input is not UTF-8 (and not an NPY file)",
            )
        })?;
        parse_text(text, dim)
    }
}

fn split_fields(line: &str) -> impl Iterator<Item = &str> {
    line.split([',', ' ', '\t', ';']).filter(|s| !s.is_empty())
}

/// Parses text points (see the module doc).
///
/// # Errors
/// [`SampleError::Points`] naming the line and column.
pub fn parse_text(text: &str, dim: usize) -> Result<Vec<f64>> {
    let mut out = Vec::new();
    let mut columns: Option<Vec<usize>> = None;
    // Whether a header named the coordinate columns; without one a line holds exactly `dim`.
    let mut named = false;
    let mut seen_data = false;
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let fields: Vec<&str> = split_fields(line).collect();
        let numbers: Vec<Option<f64>> = fields.iter().map(|f| f.parse::<f64>().ok()).collect();
        if !seen_data && numbers.iter().any(Option::is_none) {
            // A header line: pick x, y, z by name if present, else the first n columns.
            if columns.is_some() {
                return Err(points_err(
                    Some(format!("line {}", i + 1)),
                    "a second header line",
                ));
            }
            let names = ["x", "y", "z"];
            let picked: Option<Vec<usize>> = names[..dim]
                .iter()
                .map(|name| {
                    fields
                        .iter()
                        .position(|f| f.trim_matches('"').eq_ignore_ascii_case(name))
                })
                .collect();
            named = picked.is_some();
            columns = Some(picked.unwrap_or_else(|| (0..dim).collect()));
            continue;
        }
        seen_data = true;
        if !named && fields.len() > dim {
            return Err(points_err(
                Some(format!("line {}", i + 1)),
                format!(
                    "{} numbers, expected {dim} (the model is {dim}-D); a header line naming \
                     the columns x, y{} lets other columns follow",
                    fields.len(),
                    if dim == 3 { ", z" } else { "" }
                ),
            ));
        }
        let cols = columns.get_or_insert_with(|| (0..dim).collect());
        for &c in cols.iter() {
            match numbers.get(c) {
                Some(Some(x)) => out.push(*x),
                Some(None) => {
                    return Err(points_err(
                        Some(format!("line {}, column {}", i + 1, c + 1)),
                        format!("expected a number, found {:?}", fields[c]),
                    ))
                }
                None => {
                    return Err(points_err(
                        Some(format!("line {}", i + 1)),
                        format!(
                            "expected at least {} numbers, found {}",
                            c + 1,
                            fields.len()
                        ),
                    ))
                }
            }
        }
    }
    Ok(out)
}

/// Parses an NPY file's points (see the module doc).
///
/// # Errors
/// [`SampleError::Points`] naming the byte offset.
pub fn parse_npy(bytes: &[u8], dim: usize) -> Result<Vec<f64>> {
    let at = |offset: usize| Some(format!("byte {offset}"));
    if bytes.len() < 10 || !bytes.starts_with(b"\x93NUMPY") {
        return Err(points_err(at(0), "not an NPY file (magic \\x93NUMPY)"));
    }
    let (header_len, start): (usize, usize) = match bytes[6] {
        1 => (usize::from(u16::from_le_bytes([bytes[8], bytes[9]])), 10),
        2 | 3 if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        v => {
            return Err(points_err(
                at(6),
                format!("NPY version {v} is not supported (1, 2 or 3)"),
            ))
        }
    };
    let data_start = start
        .checked_add(header_len)
        .filter(|&e| e <= bytes.len())
        .ok_or_else(|| {
            points_err(
                at(8),
                format!("header length {header_len} runs past the end of the file"),
            )
        })?;
    let dict = std::str::from_utf8(&bytes[start..data_start])
        .map_err(|_| points_err(at(start), "NPY header is not text"))?;
    if dict.contains("'fortran_order': True") {
        return Err(points_err(
            at(start),
            "Fortran-order arrays are not supported; save with C order",
        ));
    }
    let shape = dict_value(dict, "shape")
        .ok_or_else(|| points_err(at(start), "NPY header has no 'shape'"))?;
    let shape: Vec<usize> = shape
        .trim_matches(|c| c == '(' || c == ')')
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| points_err(at(start), format!("cannot read shape {shape}")))?;
    let descr = dict_value(dict, "descr")
        .ok_or_else(|| points_err(at(start), "NPY header has no 'descr'"))?;
    let data = &bytes[data_start..];
    // Field byte offsets and sizes of x, y, z within a record, and the record size.
    let (record, fields): (usize, Vec<(usize, bool)>) = if descr.starts_with('[') {
        let mut offset = 0usize;
        let mut found: Vec<Option<(usize, bool)>> = vec![None; dim];
        let items: Vec<&str> = descr
            .trim_matches(|c| c == '[' || c == ']')
            .split(')')
            .collect();
        for item in items {
            let parts: Vec<&str> = item
                .split(['(', ',', '\'', '"', ' '])
                .filter(|s| !s.is_empty())
                .collect();
            if parts.len() < 2 {
                continue;
            }
            let size = type_size(parts[1]).ok_or_else(|| {
                points_err(
                    at(start),
                    format!("field {:?} has unsupported type {:?}", parts[0], parts[1]),
                )
            })?;
            if let Some(axis) = ["x", "y", "z"][..dim].iter().position(|&a| a == parts[0]) {
                match parts[1] {
                    "<f8" => found[axis] = Some((offset, true)),
                    "<f4" => found[axis] = Some((offset, false)),
                    t => {
                        return Err(points_err(
                            at(start),
                            format!("field {} must be <f8 or <f4, not {t}", parts[0]),
                        ))
                    }
                }
            }
            offset += size;
        }
        let fields: Option<Vec<_>> = found.into_iter().collect();
        let fields = fields
            .ok_or_else(|| points_err(at(start), "structured array lacks a field x, y or z"))?;
        if shape.len() != 1 {
            return Err(points_err(
                at(start),
                format!("structured array must be 1-D, shape is {shape:?}"),
            ));
        }
        (offset, fields)
    } else {
        let wide = match descr.trim_matches(|c| c == '\'' || c == '"') {
            "<f8" => true,
            "<f4" => false,
            t => {
                return Err(points_err(
                    at(start),
                    format!("array type {t} is not supported (<f8 or <f4)"),
                ))
            }
        };
        if shape.len() != 2 || shape[1] != dim {
            return Err(points_err(
                at(start),
                format!("array shape {shape:?}; expected (N, {dim})"),
            ));
        }
        let size = if wide { 8 } else { 4 };
        (size * dim, (0..dim).map(|k| (k * size, wide)).collect())
    };
    let rows = shape[0];
    let need = rows
        .checked_mul(record)
        .ok_or_else(|| points_err(at(start), "shape overflows"))?;
    if data.len() != need {
        return Err(points_err(
            at(data_start),
            format!("{} data bytes; the shape and type need {need}", data.len()),
        ));
    }
    let mut out = Vec::with_capacity(rows * dim);
    for r in data.chunks_exact(record.max(1)).take(rows) {
        for &(off, wide) in &fields {
            out.push(if wide {
                f64::from_le_bytes(r[off..off + 8].try_into().expect("8 bytes"))
            } else {
                f64::from(f32::from_le_bytes(
                    r[off..off + 4].try_into().expect("4 bytes"),
                ))
            });
        }
    }
    Ok(out)
}

fn type_size(code: &str) -> Option<usize> {
    let digits = code.trim_start_matches(['<', '>', '|', '=']);
    let (_, n) = digits.split_at(1.min(digits.len()));
    n.parse().ok()
}

/// The text of a key's value in an NPY header dict (up to the matching close bracket).
fn dict_value<'a>(dict: &'a str, key: &str) -> Option<&'a str> {
    let k = dict.find(&format!("'{key}'"))?;
    let rest = dict[k + key.len() + 2..]
        .trim_start()
        .strip_prefix(':')?
        .trim_start();
    let mut depth = 0i32;
    for (i, c) in rest.char_indices() {
        match c {
            '(' | '[' => depth += 1,
            ')' | ']' => {
                depth -= 1;
                if depth == 0 {
                    return Some(&rest[..=i]);
                }
            }
            ',' | '}' if depth == 0 => return Some(rest[..i].trim()),
            _ => {}
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::{Column, FormatWriter, Header, OutputFormat, SampleBlock, Sink};

    #[test]
    fn text_with_and_without_header() {
        assert_eq!(
            parse_text("1,2\n3 4\n", 2).unwrap(),
            vec![1.0, 2.0, 3.0, 4.0]
        );
        assert_eq!(parse_text("id,y,x\n7,2,1\n", 2).unwrap(), vec![1.0, 2.0]);
        let err = parse_text("1,2\n3,zz\n", 2).unwrap_err().to_string();
        assert!(err.contains("line 2, column 2"), "{err}");
        assert!(parse_text("1\n", 2)
            .unwrap_err()
            .to_string()
            .contains("line 1"));
        // Issue 16: four numbers on a line of a 3-D query are refused, naming the line.
        let err = parse_text("0 0 0\n1 2 3 4\n", 3).unwrap_err().to_string();
        assert!(
            err.contains("line 2") && err.contains("4 numbers, expected 3"),
            "{err}"
        );
        // A header naming the columns lets others follow; one that does not name them does not.
        assert_eq!(parse_text("x,y,f\n1,2,9\n", 2).unwrap(), vec![1.0, 2.0]);
        assert!(parse_text("a,b\n1,2,9\n", 2).is_err());
    }

    #[test]
    fn our_own_npy_reads_back_as_points() {
        let header = Header {
            dim: 3,
            columns: vec![Column::Position, Column::Value],
            count: 2,
        };
        let rows = SampleBlock {
            positions: vec![1.0, 2.0, 3.0, -4.0, 5.5, 6.25],
            values: vec![0.1, 0.2],
            ..SampleBlock::default()
        };
        let mut w = FormatWriter::new(Vec::new(), OutputFormat::Npy);
        w.begin(&header).unwrap();
        w.block(&rows).unwrap();
        w.finish().unwrap();
        let bytes = w.into_inner();
        assert_eq!(parse_points(&bytes, 3).unwrap(), rows.positions);
        // Truncation anywhere never panics and is an error.
        for cut in 0..bytes.len() {
            assert!(parse_points(&bytes[..cut], 3).is_err() || cut == 0);
        }
    }

    proptest::proptest! {
        /// Any finite points written as NPY or CSV by our writers read back exactly.
        #[test]
        fn written_points_read_back_exactly(
            coords in proptest::collection::vec(-1e300f64..1e300, 0..90),
            dim in 2usize..=3,
        ) {
            let rows = coords.len() / dim;
            let positions = coords[..rows * dim].to_vec();
            let header = Header { dim, columns: vec![Column::Position, Column::Value], count: rows as u64 };
            let block = SampleBlock { values: vec![0.5; rows], positions: positions.clone(), ..SampleBlock::default() };
            for format in [OutputFormat::Npy, OutputFormat::Csv] {
                let mut w = FormatWriter::new(Vec::new(), format);
                w.begin(&header).unwrap();
                w.block(&block).unwrap();
                w.finish().unwrap();
                proptest::prop_assert_eq!(&parse_points(&w.into_inner(), dim).unwrap(), &positions);
            }
        }
    }

    #[test]
    fn plain_npy_array() {
        let dict = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 2), }";
        let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
        let pad = 64 - (10 + dict.len() + 1) % 64;
        let hlen = (dict.len() + pad + 1) as u16;
        bytes.extend_from_slice(&hlen.to_le_bytes());
        bytes.extend_from_slice(dict.as_bytes());
        bytes.extend(std::iter::repeat_n(b' ', pad));
        bytes.push(b'\n');
        for x in [1.0f32, 2.0, 3.0, 4.5] {
            bytes.extend_from_slice(&x.to_le_bytes());
        }
        assert_eq!(parse_points(&bytes, 2).unwrap(), vec![1.0, 2.0, 3.0, 4.5]);
        assert!(parse_points(&bytes, 3).is_err());
    }
}
