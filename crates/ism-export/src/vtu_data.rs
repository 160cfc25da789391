//! The binary payloads of VTK XML (`.vtu`) data arrays: inline `binary` (base64) and `appended`
//! (base64 or raw) data, uncompressed or compressed block by block with zlib, LZ4 or LZMA, as
//! `vtkXMLWriter` and meshio write them.
//!
//! Layout (VTK's "XML file formats" document): an uncompressed array is one header word (the byte
//! count) and the bytes; a compressed one is a header `[nblocks, block size, last block size (0:
//! full), compressed size of each block]` and the compressed blocks, each of which inflates to the
//! block size. Header words are `UInt32` or `UInt64` (`header_type`). In base64, VTK and meshio
//! encode the header and the data separately, each padded: decoding quantum by quantum (four
//! characters at a time) reads both that and a single joint encoding.

use base64::Engine;

use crate::{Error, Result};

const FMT: &str = "vtu";

/// A file's `compressor` attribute.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Compressor {
    /// No `compressor` attribute.
    None,
    /// `vtkZLibDataCompressor`.
    Zlib,
    /// `vtkLZ4DataCompressor`.
    Lz4,
    /// `vtkLZMADataCompressor`.
    Lzma,
}

impl Compressor {
    /// From the `compressor` attribute of `VTKFile`.
    pub(crate) fn from_attribute(value: Option<&str>) -> Result<Compressor> {
        match value {
            None => Ok(Compressor::None),
            Some("vtkZLibDataCompressor") => Ok(Compressor::Zlib),
            Some("vtkLZ4DataCompressor") => Ok(Compressor::Lz4),
            Some("vtkLZMADataCompressor") => Ok(Compressor::Lzma),
            Some(other) => Err(Error::import(
                FMT,
                "VTKFile".to_string(),
                format!(
                    "compressor {other:?} is not supported (vtkZLibDataCompressor, \
                     vtkLZ4DataCompressor or vtkLZMADataCompressor)"
                ),
            )),
        }
    }
}

/// How the arrays of one file are stored.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Layout {
    /// Header words are 8 bytes (`header_type="UInt64"`), else 4.
    pub(crate) header64: bool,
    /// The file's compressor.
    pub(crate) compressor: Compressor,
}

impl Layout {
    fn word(self) -> usize {
        if self.header64 {
            8
        } else {
            4
        }
    }

    fn read_word(self, bytes: &[u8], index: usize, at: &str) -> Result<usize> {
        let w = self.word();
        let chunk = bytes
            .get(index * w..(index + 1) * w)
            .ok_or_else(|| Error::import(FMT, at.to_string(), "data shorter than its header"))?;
        let value = if self.header64 {
            u64::from_le_bytes(chunk.try_into().expect("8 bytes"))
        } else {
            u64::from(u32::from_le_bytes(chunk.try_into().expect("4 bytes")))
        };
        usize::try_from(value)
            .map_err(|_| Error::import(FMT, at.to_string(), "header size out of range"))
    }

    /// Bytes of header before the data, once the first header word is known.
    fn header_len(self, first_word: usize, at: &str) -> Result<usize> {
        match self.compressor {
            Compressor::None => Ok(self.word()),
            _ => first_word
                .checked_add(3)
                .and_then(|words| words.checked_mul(self.word()))
                .ok_or_else(|| Error::import(FMT, at.to_string(), "block count out of range")),
        }
    }

    /// Total bytes (header and data) of an array whose header is `header`.
    fn total_len(self, header: &[u8], at: &str) -> Result<usize> {
        let first = self.read_word(header, 0, at)?;
        let hlen = self.header_len(first, at)?;
        let data = match self.compressor {
            Compressor::None => first,
            _ => (0..first).try_fold(0usize, |sum, b| {
                let size = self.read_word(header, 3 + b, at)?;
                sum.checked_add(size)
                    .ok_or_else(|| Error::import(FMT, at.to_string(), "block sizes overflow"))
            })?,
        };
        hlen.checked_add(data)
            .ok_or_else(|| Error::import(FMT, at.to_string(), "array size overflows"))
    }

    /// The array's uncompressed bytes from `bytes` (header first; trailing bytes ignored).
    fn payload(self, bytes: &[u8], at: &str) -> Result<Vec<u8>> {
        let first = self.read_word(bytes, 0, at)?;
        let hlen = self.header_len(first, at)?;
        if self.compressor == Compressor::None {
            return hlen
                .checked_add(first)
                .and_then(|end| bytes.get(hlen..end))
                .map(<[u8]>::to_vec)
                .ok_or_else(|| {
                    Error::import(
                        FMT,
                        at.to_string(),
                        format!(
                            "header declares {first} bytes, {} present",
                            bytes.len().saturating_sub(hlen)
                        ),
                    )
                });
        }
        let blocks = first;
        let block_size = self.read_word(bytes, 1, at)?;
        let last_size = match self.read_word(bytes, 2, at)? {
            0 => block_size,
            s => s,
        };
        // Every compressor has a bounded ratio (zlib 1032:1, LZ4 255:1; LZMA more on constant
        // data): a header that claims more than that of its blocks is refused before inflating.
        // The compressed bytes actually present, not the header's claim: the bound on the output
        // is then a multiple of the input.
        let compressed = self
            .total_len(bytes, at)?
            .min(bytes.len())
            .saturating_sub(hlen);
        let ratio = if self.compressor == Compressor::Lzma {
            1 << 16
        } else {
            2048
        };
        // No blocks, no bytes: the size words after the count then mean nothing. (Found by the
        // `import_mesh` fuzz target: zero blocks with a last-block size of 4 GB reserved 4 GB.)
        let claimed = match blocks {
            0 => 0,
            _ => (blocks - 1)
                .saturating_mul(block_size)
                .saturating_add(last_size),
        };
        if claimed > compressed.saturating_mul(ratio).saturating_add(1 << 16) {
            return Err(Error::import(
                FMT,
                at.to_string(),
                format!("header claims {claimed} bytes from {compressed} compressed bytes"),
            ));
        }
        let mut out = Vec::with_capacity(claimed);
        let mut start = hlen;
        for b in 0..blocks {
            let size = self.read_word(bytes, 3 + b, at)?;
            let block = start
                .checked_add(size)
                .and_then(|end| bytes.get(start..end))
                .ok_or_else(|| {
                    Error::import(
                        FMT,
                        format!("{at}, block {b}"),
                        "compressed block truncated",
                    )
                })?;
            let expected = if b + 1 == blocks {
                last_size
            } else {
                block_size
            };
            let inflated = inflate(self.compressor, block, expected)
                .map_err(|e| Error::import(FMT, format!("{at}, block {b}"), e))?;
            if inflated.len() != expected {
                return Err(Error::import(
                    FMT,
                    format!("{at}, block {b}"),
                    format!(
                        "block inflates to {} bytes, header says {expected}",
                        inflated.len()
                    ),
                ));
            }
            out.extend_from_slice(&inflated);
            start += size;
        }
        Ok(out)
    }

    /// An inline `format="binary"` array's text.
    pub(crate) fn inline(self, text: &str, at: &str) -> Result<Vec<u8>> {
        let bytes = Base64Stream::new(text).take_all(at)?;
        self.payload(&bytes, at)
    }

    /// An `appended` array at character `offset` of base64 `AppendedData` text (after the `_`).
    pub(crate) fn appended_base64(self, text: &str, offset: usize, at: &str) -> Result<Vec<u8>> {
        let tail = text
            .get(offset..)
            .ok_or_else(|| Error::import(FMT, at.to_string(), "offset beyond the AppendedData"))?;
        let mut stream = Base64Stream::new(tail);
        let mut bytes = stream.take(self.word(), at)?;
        let first = self.read_word(&bytes, 0, at)?;
        let hlen = self.header_len(first, at)?;
        bytes.extend(stream.take(hlen - bytes.len().min(hlen), at)?);
        let total = self.total_len(&bytes, at)?;
        let more = total.saturating_sub(bytes.len());
        bytes.extend(stream.take(more, at)?);
        self.payload(&bytes, at)
    }

    /// An `appended` array at byte `offset` of raw `AppendedData` bytes (after the `_`).
    pub(crate) fn appended_raw(self, raw: &[u8], offset: usize, at: &str) -> Result<Vec<u8>> {
        let tail = raw
            .get(offset..)
            .ok_or_else(|| Error::import(FMT, at.to_string(), "offset beyond the AppendedData"))?;
        self.payload(tail, at)
    }
}

fn inflate(
    compressor: Compressor,
    block: &[u8],
    expected: usize,
) -> std::result::Result<Vec<u8>, String> {
    use std::io::Read;
    let mut out = Vec::new();
    match compressor {
        Compressor::None => out.extend_from_slice(block),
        Compressor::Zlib => {
            flate2::read::ZlibDecoder::new(block)
                .take(expected as u64 + 1)
                .read_to_end(&mut out)
                .map_err(|e| format!("zlib: {e}"))?;
        }
        Compressor::Lz4 => {
            out = lz4_flex::block::decompress(block, expected).map_err(|e| format!("LZ4: {e}"))?;
        }
        Compressor::Lzma => {
            // VTK writes each block as an .xz stream (`lzma_easy_buffer_encode`).
            let mut reader = std::io::BufReader::new(block);
            let mut limited = Limited {
                out: &mut out,
                room: expected,
            };
            lzma_rs::xz_decompress(&mut reader, &mut limited).map_err(|e| format!("LZMA: {e}"))?;
        }
    }
    Ok(out)
}

/// A writer that refuses to grow past `room` bytes (a block never inflates beyond its header's
/// size).
struct Limited<'a> {
    out: &'a mut Vec<u8>,
    room: usize,
}

impl std::io::Write for Limited<'_> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        if buf.len() > self.room {
            return Err(std::io::Error::other(
                "the block inflates beyond its header's size",
            ));
        }
        self.room -= buf.len();
        self.out.extend_from_slice(buf);
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// Base64 text decoded four characters at a time, so that separately padded encodings laid end
/// to end decode to their concatenation. Whitespace is skipped.
struct Base64Stream<'a> {
    chars: std::str::Chars<'a>,
}

impl<'a> Base64Stream<'a> {
    fn new(text: &'a str) -> Self {
        Base64Stream {
            chars: text.chars(),
        }
    }

    /// The next quantum's bytes (1 to 3), or `None` at the end.
    fn quantum(&mut self, at: &str) -> Result<Option<Vec<u8>>> {
        let mut q = String::with_capacity(4);
        for c in self.chars.by_ref() {
            if c.is_ascii_whitespace() {
                continue;
            }
            q.push(c);
            if q.len() == 4 {
                break;
            }
        }
        match q.len() {
            0 => Ok(None),
            4 => base64::engine::general_purpose::STANDARD
                .decode(q.as_bytes())
                .map(Some)
                .map_err(|e| Error::import(FMT, at.to_string(), format!("base64: {e}"))),
            _ => Err(Error::import(
                FMT,
                at.to_string(),
                "base64 text ends inside a four-character group",
            )),
        }
    }

    /// At least `n` more bytes (whole quanta).
    fn take(&mut self, n: usize, at: &str) -> Result<Vec<u8>> {
        let mut out = Vec::new();
        while out.len() < n {
            match self.quantum(at)? {
                Some(bytes) => out.extend(bytes),
                None => {
                    return Err(Error::import(
                        FMT,
                        at.to_string(),
                        format!("base64 data ends after {} of {n} bytes", out.len()),
                    ))
                }
            }
        }
        Ok(out)
    }

    /// Every remaining byte.
    fn take_all(&mut self, at: &str) -> Result<Vec<u8>> {
        let mut out = Vec::new();
        while let Some(bytes) = self.quantum(at)? {
            out.extend(bytes);
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn b64(bytes: &[u8]) -> String {
        base64::engine::general_purpose::STANDARD.encode(bytes)
    }

    fn zlib(bytes: &[u8]) -> Vec<u8> {
        use std::io::Write;
        let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
        e.write_all(bytes).unwrap();
        e.finish().unwrap()
    }

    const UNCOMPRESSED: Layout = Layout {
        header64: false,
        compressor: Compressor::None,
    };

    #[test]
    fn separately_padded_base64_decodes_to_the_concatenation() {
        // Header [5] as UInt32 (4 bytes: "BQAAAA==") and five data bytes ("AQIDBAU="), each padded.
        let text = format!("{}{}", b64(&5u32.to_le_bytes()), b64(&[1, 2, 3, 4, 5]));
        assert_eq!(text, "BQAAAA==AQIDBAU=");
        assert_eq!(
            UNCOMPRESSED.inline(&text, "a").unwrap(),
            vec![1, 2, 3, 4, 5]
        );
        // The same bytes encoded jointly.
        let joint = b64(&[5, 0, 0, 0, 1, 2, 3, 4, 5]);
        assert_eq!(
            UNCOMPRESSED.inline(&joint, "a").unwrap(),
            vec![1, 2, 3, 4, 5]
        );
    }

    #[test]
    fn zlib_blocks_inflate_in_order() {
        // 10 bytes in blocks of 4: sizes 4, 4, 2 (last block size 2).
        let data: Vec<u8> = (0..10).collect();
        let blocks: Vec<Vec<u8>> = data.chunks(4).map(zlib).collect();
        let mut header = Vec::new();
        for w in [3u64, 4, 2]
            .into_iter()
            .chain(blocks.iter().map(|b| b.len() as u64))
        {
            header.extend_from_slice(&w.to_le_bytes());
        }
        let layout = Layout {
            header64: true,
            compressor: Compressor::Zlib,
        };
        let text = format!("{}{}", b64(&header), b64(&blocks.concat()));
        assert_eq!(layout.inline(&text, "a").unwrap(), data);
        // Appended, after another array's text, at its character offset.
        let before = b64(&[9, 9, 9, 9, 9]);
        let appended = format!("{before}{text}");
        assert_eq!(
            layout
                .appended_base64(&appended, before.len(), "a")
                .unwrap(),
            data
        );
        let raw = [header.clone(), blocks.concat()].concat();
        assert_eq!(layout.appended_raw(&raw, 0, "a").unwrap(), data);
        // A block that inflates to a size other than the header's is an error.
        let mut wrong = header.clone();
        wrong[16..24].copy_from_slice(&3u64.to_le_bytes());
        let text = format!("{}{}", b64(&wrong), b64(&blocks.concat()));
        let err = layout.inline(&text, "a").unwrap_err().to_string();
        assert!(
            err.contains("block 2") && err.contains("header says 3"),
            "{err}"
        );
    }

    #[test]
    fn truncated_and_unknown_inputs_are_errors_not_panics() {
        let layout = Layout {
            header64: false,
            compressor: Compressor::Zlib,
        };
        for text in ["", "AAAA", "AQAAAA==", "AQAAAAQAAAAEAAAA/////w=="] {
            assert!(layout.inline(text, "a").is_err(), "{text:?}");
        }
        assert!(Compressor::from_attribute(Some("vtkZstdDataCompressor")).is_err());
    }

    /// A compressed header's claims are bounded by the bytes present, before anything is reserved
    /// (fuzz finding `fuzz/artifacts/import_mesh/oom-1d3f22…`: zero blocks, last block 4 GB).
    #[test]
    fn header_claims_do_not_reserve_memory() {
        for compressor in [Compressor::Zlib, Compressor::Lzma, Compressor::Lz4] {
            let layout = Layout {
                header64: false,
                compressor,
            };
            // Zero blocks: nothing, whatever the size words say.
            let zero = [0u32, 1 << 20, u32::MAX].map(u32::to_le_bytes).concat();
            assert_eq!(
                layout.appended_raw(&zero, 0, "a").unwrap(),
                Vec::<u8>::new()
            );
            // One block claimed to hold 4 GB, declared 1 GB compressed, 8 bytes present.
            let one = [1u32, u32::MAX, u32::MAX, 1 << 30, 0, 0]
                .map(u32::to_le_bytes)
                .concat();
            let err = layout.appended_raw(&one, 0, "a").unwrap_err().to_string();
            assert!(err.contains("header claims"), "{err}");
        }
    }
}
