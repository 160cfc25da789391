//! The compressed encoding (spec §7.4.2): the compact payload of §7.4.1 compressed as one xz
//! stream, after its uncompressed length.
//!
//! Payload layout: `u64` little-endian uncompressed length `U`, then one xz stream (the `.xz`
//! file format: LZMA2) whose content is exactly `U` bytes of compact payload. The length comes
//! first so that a reader refuses a payload past its limit before decompressing anything, and so
//! that the compact decoder checks every declared sequence length against the bytes the payload
//! holds, exactly as in a `.ismc` file, before allocating for it.
//!
//! Reading streams: the xz decoder feeds the compact decoder through the same window as a streamed
//! `.ismc` file, so the uncompressed payload is never held whole, and no more than `U + 1` bytes
//! are ever decompressed (a decompression bomb is ISM-006 at the length, or ISM-007 when `U`
//! itself is past the limit).

use std::io::{Read, Write};

use crate::binary::{BinaryDecoder, Stream};
use crate::error::{Error, Result};
use crate::model::Model;
use crate::rules::{Location, Rule};

/// Bytes of the uncompressed length that opens the payload.
pub const LENGTH_PREFIX: usize = 8;

/// The xz preset the reference writer uses: `6`, xz's own default (8 MiB dictionary). On the
/// issue-17 fits presets 6 and 9e gave the same size within 0.6 % (BENCHMARKS.md), and 6
/// compresses several times faster.
pub const WRITE_PRESET: u32 = 6;

/// The memory the reference reader lets the xz decoder use (spec §7.4.2): 128 MiB, above what
/// every xz preset's decoder needs (preset 9: 64 MiB dictionary, 65 MiB in all) so that any file
/// an xz tool writes with a preset is read, and bounded so that a stream declaring a 1.5 GiB
/// dictionary cannot make the reader allocate it.
pub const DECODER_MEMORY_LIMIT: u64 = 128 << 20;

/// Reads the xz stream of a payload, recording the first decompression error (with the rule and
/// location of spec §7.4.2) instead of passing it to the compact decoder, which then sees the end
/// of its input: the caller reports the recorded error first.
struct XzSource<'a> {
    stream: liblzma::stream::Stream,
    input: &'a [u8],
    /// Input bytes consumed.
    pos: usize,
    /// File offset of the stream's first byte.
    base: u64,
    /// The stream ended (its index, footer and check verified).
    done: bool,
    error: Option<Error>,
}

impl<'a> XzSource<'a> {
    fn new(input: &'a [u8], base: u64) -> Result<XzSource<'a>> {
        // No flags: one stream, no concatenation, so bytes after it are the caller's to report.
        let stream =
            liblzma::stream::Stream::new_stream_decoder(DECODER_MEMORY_LIMIT, 0).map_err(|e| {
                Error::io(
                    None,
                    std::io::Error::other(format!("xz decoder could not start: {e}")),
                )
            })?;
        Ok(XzSource {
            stream,
            input,
            pos: 0,
            base,
            done: false,
            error: None,
        })
    }

    fn fail(&mut self, rule: Rule, offset: u64, message: String) {
        if self.error.is_none() {
            self.error = Some(Error::format(rule, Location::offset(offset), message));
        }
    }
}

impl Read for XzSource<'_> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        use liblzma::stream::{Action, Error as XzError, Status};
        if self.done || self.error.is_some() || buf.is_empty() {
            return Ok(0);
        }
        loop {
            let (in_before, out_before) = (self.stream.total_in(), self.stream.total_out());
            // All input is present: Finish lets the decoder tell a cut stream from one waiting
            // for more.
            let result = self
                .stream
                .process(&self.input[self.pos..], buf, Action::Finish);
            self.pos += (self.stream.total_in() - in_before) as usize;
            let produced = (self.stream.total_out() - out_before) as usize;
            match result {
                Ok(Status::StreamEnd) => {
                    self.done = true;
                    return Ok(produced);
                }
                Ok(_) if produced > 0 => return Ok(produced),
                Ok(Status::MemNeeded) => {
                    // No progress with every input byte offered: the stream is cut short.
                    let end = self.base + self.input.len() as u64;
                    self.fail(
                        Rule::Malformed,
                        end,
                        "the xz stream ends before its end marker (truncated compressed payload)"
                            .into(),
                    );
                    return Ok(0);
                }
                Ok(_) => {}
                Err(XzError::MemLimit) => {
                    self.fail(
                        Rule::LimitExceeded,
                        self.base,
                        format!(
                            "the xz stream needs more than the decoder's memory limit of {} MiB \
                             (a dictionary above 64 MiB)",
                            DECODER_MEMORY_LIMIT >> 20
                        ),
                    );
                    return Ok(0);
                }
                Err(e) => {
                    self.fail(
                        Rule::Malformed,
                        self.base,
                        format!("the payload is not a valid xz stream: {e}"),
                    );
                    return Ok(0);
                }
            }
        }
    }
}

/// Decodes a compressed payload whose first byte is at file offset `base` (spec §7.4.2): the
/// length, then the stream decompressed into the compact decoder. Errors, in the order of the
/// spec: a payload shorter than the length; a length past `max_payload_bytes` (ISM-007); a
/// stream that does not decompress (ISM-006 at its first byte; ISM-007 there for a dictionary
/// past the decoder's memory limit), is cut short (ISM-006 at the payload's end), or holds other
/// than the declared length (ISM-006 at the length); bytes after the stream (ISM-006 at the
/// first); then the compact decoder's own errors, at `base` plus their position in the
/// uncompressed payload (the offsets of a `.ismc` file holding it).
pub(crate) fn decode(
    payload: &[u8],
    base: u64,
    max_payload_bytes: u64,
    allow_trailing: bool,
) -> Result<Model> {
    let Some(prefix) = payload.get(..LENGTH_PREFIX) else {
        return Err(Error::format(
            Rule::Malformed,
            Location::offset(base + payload.len() as u64),
            format!(
                "a compressed payload starts with its {LENGTH_PREFIX}-byte uncompressed length; \
                 this one has {} bytes",
                payload.len()
            ),
        ));
    };
    let declared = u64::from_le_bytes(prefix.try_into().expect("8 bytes"));
    if declared > max_payload_bytes {
        return Err(Error::format(
            Rule::LimitExceeded,
            Location::offset(base),
            format!(
                "the compressed payload declares {declared} bytes uncompressed, above the limit \
                 of {max_payload_bytes}"
            ),
        ));
    }
    let stream_base = base + LENGTH_PREFIX as u64;
    let mut source = XzSource::new(&payload[LENGTH_PREFIX..], stream_base)?;
    let mut stream = Stream::new(&mut source, declared);
    let decoded = BinaryDecoder::<true>::stream(&mut stream, base).model(allow_trailing);
    // Decompress to the end (at most one byte past the declared length) before reporting
    // anything: decompression errors come before the payload's own.
    let end = stream.finish(1);
    if let Some(e) = source.error.take() {
        return Err(e);
    }
    if let Some(e) = end.error {
        return Err(Error::io(None, e));
    }
    if end.available != declared || end.trailing > 0 {
        let got = if end.trailing > 0 {
            "more".to_string()
        } else {
            end.available.to_string()
        };
        return Err(Error::format(
            Rule::Malformed,
            Location::offset(base),
            format!(
                "the compressed payload declares {declared} bytes uncompressed; its xz stream \
                 holds {got}"
            ),
        ));
    }
    if !source.done {
        // The declared bytes were all there but the stream did not end after them: read on to
        // its end marker (a stream holding more bytes was reported above).
        let mut one = [0u8; 1];
        let n = source.read(&mut one).map_err(|e| Error::io(None, e))?;
        if let Some(e) = source.error.take() {
            return Err(e);
        }
        if n > 0 || !source.done {
            return Err(Error::format(
                Rule::Malformed,
                Location::offset(base),
                format!(
                    "the compressed payload declares {declared} bytes uncompressed; its xz \
                     stream holds more"
                ),
            ));
        }
    }
    if source.pos < source.input.len() {
        return Err(Error::format(
            Rule::Malformed,
            Location::offset(stream_base + source.pos as u64),
            format!(
                "{} bytes follow the xz stream in the compressed payload",
                source.input.len() - source.pos
            ),
        ));
    }
    decoded
}

/// A writer that only counts: the compact payload's length, written before its compressed bytes.
struct Count(u64);

impl Write for Count {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0 += buf.len() as u64;
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// Writes a model's compressed payload to `out`: the compact payload is encoded twice, once to
/// count its bytes and once through the xz encoder, so it is never held uncompressed.
pub(crate) fn encode<W: Write>(
    model: &Model,
    mut out: W,
) -> std::result::Result<(), bincode::error::EncodeError> {
    let config = crate::io::compact_config();
    let mut count = Count(0);
    bincode::encode_into_std_write(model, &mut count, config)?;
    out.write_all(&count.0.to_le_bytes())
        .map_err(|inner| bincode::error::EncodeError::Io { inner, index: 0 })?;
    let mut xz = liblzma::write::XzEncoder::new(out, WRITE_PRESET);
    bincode::encode_into_std_write(model, &mut xz, config)?;
    xz.finish()
        .map_err(|inner| bincode::error::EncodeError::Io { inner, index: 0 })?;
    Ok(())
}
