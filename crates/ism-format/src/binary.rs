//! The decoder of the binary encoding (spec §7.4) and of the compact binary encoding (§7.4.1), written
//! from the grammar rather than with bincode so that every error names the member (JSON pointer) and
//! the byte offset, and so that a declared length is checked against the bytes left before anything
//! is allocated for it.
//!
//! The two encodings share one grammar and differ only in how integers wider than a byte (lengths,
//! `u32` ids, enumeration indices) are written: fixed width, or as bincode's variable-length
//! integer. One decoder does both, parameterised by `VARINT` (a const generic, so the fixed-width
//! decoder compiles to the same code it was before the compact encoding existed).

use std::collections::BTreeMap;
use std::io::Read;

use crate::decode::{pointer_of, Decoder, JsonTokens, Seg};
use crate::error::{Error, Result};
use crate::faces::FaceTable;
use crate::model::{Direction, JsonValue, Metadata, Model, Stage, StageKind, VertexMap};
use crate::rules::{Location, Rule};
use crate::structured::ComplexFaces;

/// Smallest encoded size of one element, per sequence type (spec §7.4, §7.4.1): what a declared
/// length is checked against.
#[derive(Clone, Copy)]
struct MinSize {
    f64: usize,
    u32: usize,
    string: usize,
    /// kind, degree, direction, name tag, three lengths (faces, vertexMaps, extras text).
    stage: usize,
    /// Three lengths.
    face_record: usize,
    /// vertex, the coefficients' length.
    vertex_map: usize,
    /// The name's length, the value's text length.
    extension: usize,
}

/// The binary encoding: `u32` 4 bytes, lengths 8.
const FIXED_MIN: MinSize = MinSize {
    f64: 8,
    u32: 4,
    string: 8,
    stage: 4 + 4 + 4 + 1 + 8 + 8 + 8,
    face_record: 8 * 3,
    vertex_map: 4 + 8,
    extension: 8 + 8,
};

/// The compact encoding: every integer and length at least one byte.
const VARINT_MIN: MinSize = MinSize {
    f64: 8,
    u32: 1,
    string: 1,
    stage: 1 + 1 + 1 + 1 + 1 + 1 + 1,
    face_record: 3,
    vertex_map: 1 + 1,
    extension: 1 + 1,
};

/// First bytes of bincode's variable-length integer (spec §7.4.1): below 251 the byte is the value;
/// 251, 252, 253 announce a little-endian `u16`, `u32`, `u64`.
const VARINT_U16: u8 = 251;
const VARINT_U32: u8 = 252;
const VARINT_U64: u8 = 253;

/// A variable-length integer at the start of some bytes.
#[derive(Debug, PartialEq, Eq)]
enum Varint {
    /// Its value and encoded length.
    Value(u64, usize),
    /// Its first byte announces this many bytes in all, more than are there.
    Short(usize),
    /// Not a minimal varint of the member's type (the reason).
    Bad(&'static str),
}

/// Reads a canonical varint of a `u32` (`wide` false) or `u64` (`wide` true) member from the start
/// of `bytes` (spec §7.4.1): the minimal form only, so each value has one encoding.
#[inline]
fn varint(bytes: &[u8], wide: bool) -> Varint {
    let Some(&first) = bytes.first() else {
        return Varint::Short(1);
    };
    let (len, least) = match first {
        0..=250 => return Varint::Value(u64::from(first), 1),
        VARINT_U16 => (3, 251),
        VARINT_U32 => (5, 1 << 16),
        VARINT_U64 if wide => (9, 1 << 32),
        VARINT_U64 => return Varint::Bad("first byte 253 (a u64) in a u32 member"),
        _ => return Varint::Bad("first byte 254 or 255 is not a varint of a u32 or u64"),
    };
    let Some(rest) = bytes.get(1..len) else {
        return Varint::Short(len);
    };
    let mut le = [0u8; 8];
    le[..len - 1].copy_from_slice(rest);
    let value = u64::from_le_bytes(le);
    if value < least {
        return Varint::Bad("not the minimal varint of its value");
    }
    Varint::Value(value, len)
}

/// Decodes up to `most` complete, canonical `u32` varints from the start of `bytes` into `out`;
/// how many, and the bytes they took. Stops before the first one that is not wholly there or not
/// canonical (the checked path reads that one, with its error).
#[inline]
fn varint_u32_run(bytes: &[u8], most: usize, out: &mut Vec<u32>) -> (usize, usize) {
    let mut at = 0;
    let mut k = 0;
    while k < most {
        match bytes.get(at) {
            Some(&b) if b <= 250 => {
                out.push(u32::from(b));
                at += 1;
            }
            Some(_) => match varint(&bytes[at..], false) {
                Varint::Value(v, len) => {
                    out.push(v as u32);
                    at += len;
                }
                _ => break,
            },
            None => break,
        }
        k += 1;
    }
    (k, at)
}

/// Window of a streamed payload: large enough that refills are rare, small enough to stay in cache.
const WINDOW: usize = 1 << 18;

/// In a streamed payload, sequences of records (stages, vertex maps, extension names) reserve at
/// most this many elements before their data has arrived (a declared length is only a claim until
/// the bytes are read); arrays of numbers and face tables reserve their declared length, see
/// `BinaryDecoder::reserve_exact`.
const STREAM_RESERVE: usize = 1 << 16;

/// A payload streamed from a reader through a fixed window, its CRC-32 computed on the way; never
/// reads past the declared payload length.
pub(crate) struct Stream<'r> {
    reader: &'r mut dyn Read,
    buf: Vec<u8>,
    /// Unread bytes are `buf[lo..hi]`.
    lo: usize,
    hi: usize,
    /// Payload bytes read from the reader so far.
    pulled: u64,
    /// The declared payload length.
    len: u64,
    crc: crc32fast::Hasher,
    /// The reader ended before `len` bytes.
    short: bool,
    /// The first read error.
    error: Option<std::io::Error>,
}

/// What a streamed payload turned out to be once read to its end.
pub(crate) struct StreamEnd {
    /// Payload bytes present (less than declared when the file is truncated).
    pub available: u64,
    /// Bytes after the declared payload (counted up to `trailing_cap`).
    pub trailing: u64,
    /// CRC-32 of the payload bytes present.
    pub crc: u32,
    /// A read error, which decides over everything else.
    pub error: Option<std::io::Error>,
}

impl<'r> Stream<'r> {
    pub(crate) fn new(reader: &'r mut dyn Read, len: u64) -> Stream<'r> {
        Stream {
            reader,
            buf: vec![0; WINDOW],
            lo: 0,
            hi: 0,
            pulled: 0,
            len,
            crc: crc32fast::Hasher::new(),
            short: false,
            error: None,
        }
    }

    /// Makes `n` unread bytes available in the window; false when the reader ends (or fails)
    /// first. The window grows past [`WINDOW`] only as bytes actually arrive.
    fn fill(&mut self, n: usize) -> bool {
        if self.hi - self.lo >= n {
            return true;
        }
        if self.short || self.error.is_some() {
            return false;
        }
        self.buf.copy_within(self.lo..self.hi, 0);
        self.hi -= self.lo;
        self.lo = 0;
        while self.hi < n {
            if self.hi == self.buf.len() {
                let grown = (self.buf.len() * 2).min(n.max(WINDOW));
                self.buf.resize(grown.max(self.hi + 1), 0);
            }
            let want = (self.buf.len() - self.hi) as u64;
            let want = want.min(self.len - self.pulled) as usize;
            if want == 0 {
                self.short = true;
                return false;
            }
            match self.reader.read(&mut self.buf[self.hi..self.hi + want]) {
                Ok(0) => {
                    self.short = true;
                    return false;
                }
                Ok(k) => {
                    self.crc.update(&self.buf[self.hi..self.hi + k]);
                    self.hi += k;
                    self.pulled += k as u64;
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => {
                    self.error = Some(e);
                    return false;
                }
            }
        }
        true
    }

    /// Reads the rest of the payload (checksumming it) and counts what follows, up to
    /// `trailing_cap` bytes.
    pub(crate) fn finish(mut self, trailing_cap: u64) -> StreamEnd {
        let mut scratch = vec![0u8; WINDOW];
        while self.error.is_none() && !self.short && self.pulled < self.len {
            let want = (self.len - self.pulled).min(WINDOW as u64) as usize;
            match self.reader.read(&mut scratch[..want]) {
                Ok(0) => self.short = true,
                Ok(k) => {
                    self.crc.update(&scratch[..k]);
                    self.pulled += k as u64;
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => self.error = Some(e),
            }
        }
        let mut trailing = 0;
        if self.error.is_none() && !self.short {
            match std::io::copy(
                &mut (&mut self.reader).take(trailing_cap),
                &mut std::io::sink(),
            ) {
                Ok(k) => trailing = k,
                Err(e) => self.error = Some(e),
            }
        }
        StreamEnd {
            available: self.pulled,
            trailing,
            crc: self.crc.finalize(),
            error: self.error,
        }
    }
}

/// The decoder's bytes: the whole payload in memory, or a stream.
enum Source<'a, 'r> {
    Slice(&'a [u8]),
    Stream(&'a mut Stream<'r>),
}

/// The decoder of a binary payload: fixed-width integers (`VARINT` false, spec §7.4) or bincode
/// varints (`VARINT` true, the compact encoding, §7.4.1).
pub(crate) struct BinaryDecoder<'a, 'r, const VARINT: bool> {
    src: Source<'a, 'r>,
    /// Payload bytes consumed.
    pub(crate) at: usize,
    /// Declared payload length.
    end: usize,
    pub(crate) base: u64,
    pub(crate) path: Vec<Seg>,
    /// Keep face records' control points and weights (false: count them and test them finite,
    /// [`crate::io::ReadOptions::keep_record_numbers`]).
    keep_numbers: bool,
    /// The structured encoding (spec §7.4.3): the compact grammar with the complex as `Complex`
    /// (`complexForm` then the listed arrays or a refinement) and a stage's records as `Records`
    /// (both read by `crate::structured`).
    structured: bool,
}

impl<'a> BinaryDecoder<'a, '_, true> {
    /// A decoder of a structured payload (spec §7.4.3: the compact grammar, so varints) held whole
    /// in memory, whose first byte is at file offset `base`.
    pub(crate) fn structured(payload: &'a [u8], base: u64) -> Self {
        let mut d = Self::new(payload, base);
        d.structured = true;
        d
    }
}

/// Whether every little-endian `f64` in `bytes` is finite, without stopping early (so the loop
/// vectorizes: a file's numbers are finite almost always).
#[inline]
fn all_finite(bytes: &[u8]) -> bool {
    bytes.chunks_exact(8).fold(true, |ok, c| {
        ok & f64::from_le_bytes(c.try_into().expect("8 bytes")).is_finite()
    })
}

impl<'a, 'r, const VARINT: bool> BinaryDecoder<'a, 'r, VARINT> {
    /// The smallest element sizes of this encoding.
    const MIN: MinSize = if VARINT { VARINT_MIN } else { FIXED_MIN };

    /// A decoder of `payload`, whose first byte is at file offset `base`.
    pub(crate) fn new(payload: &'a [u8], base: u64) -> Self {
        BinaryDecoder {
            src: Source::Slice(payload),
            at: 0,
            end: payload.len(),
            base,
            path: Vec::new(),
            keep_numbers: true,
            structured: false,
        }
    }

    /// A decoder of a streamed payload whose first byte is at file offset `base`.
    pub(crate) fn stream(stream: &'a mut Stream<'r>, base: u64) -> Self {
        let end = usize::try_from(stream.len).unwrap_or(usize::MAX);
        BinaryDecoder {
            src: Source::Stream(stream),
            at: 0,
            end,
            base,
            path: Vec::new(),
            keep_numbers: true,
            structured: false,
        }
    }

    /// Whether face records keep their control points and weights (the default) or only count
    /// them and test them finite: same bytes accepted, same errors, same face ids and lengths.
    pub(crate) fn keep_numbers(mut self, keep: bool) -> Self {
        self.keep_numbers = keep;
        self
    }

    pub(crate) fn fail(&self, at: usize, message: impl Into<String>) -> Error {
        Error::format(
            Rule::Malformed,
            Location {
                pointer: Some(pointer_of(&self.path)),
                offset: Some(self.base + at as u64),
                ..Location::default()
            },
            message,
        )
    }

    pub(crate) fn remaining(&self) -> usize {
        self.end - self.at
    }

    /// How many of `n` declared elements to reserve room for: all of them when the payload is in
    /// memory (its length was checked against the file), a bounded number when streaming.
    fn reserve_hint(&self, n: usize) -> usize {
        match self.src {
            Source::Slice(_) => n,
            Source::Stream(_) => n.min(STREAM_RESERVE),
        }
    }

    pub(crate) fn take(&mut self, n: usize, what: &str) -> Result<&[u8]> {
        self.take_with(n, || what.to_string())
    }

    /// [`Self::take`] with the description built only on failure (no allocation per record).
    fn take_with(&mut self, n: usize, what: impl FnOnce() -> String) -> Result<&[u8]> {
        if self.remaining() < n {
            return Err(self.fail(
                self.at,
                format!(
                    "{} needs {n} bytes; the payload ends after {}",
                    what(),
                    self.remaining()
                ),
            ));
        }
        let at = self.at;
        self.at += n;
        match &mut self.src {
            Source::Slice(b) => Ok(&b[at..at + n]),
            Source::Stream(s) => {
                if !s.fill(n) {
                    // The file ended early or could not be read: the caller reports that
                    // (truncation, I/O error), not this placeholder.
                    return Err(Error::format(
                        Rule::Truncated,
                        Location::offset(self.base + at as u64),
                        "the payload ended early",
                    ));
                }
                let out = &s.buf[s.lo..s.lo + n];
                s.lo += n;
                Ok(out)
            }
        }
    }

    /// Appends `n` little-endian numbers of `size` bytes to `out`, converted by `read`, a window
    /// at a time.
    fn numbers_into<T>(
        &mut self,
        n: usize,
        size: usize,
        what: &str,
        out: &mut Vec<T>,
        read: impl Fn(&[u8]) -> T,
    ) -> Result<()> {
        let per = (WINDOW / size).max(1);
        let mut left = n;
        while left > 0 {
            let k = left.min(per);
            let bytes = self.take(k * size, what)?;
            out.extend(bytes.chunks_exact(size).map(&read));
            left -= k;
        }
        Ok(())
    }

    pub(crate) fn u8(&mut self, what: &str) -> Result<u8> {
        Ok(self.take(1, what)?[0])
    }

    pub(crate) fn u32(&mut self, what: &str) -> Result<u32> {
        if VARINT {
            // `wide` false: a value above u32::MAX cannot be read.
            return Ok(self.varint_checked(false, || what.to_string())? as u32);
        }
        let bytes = self.take(4, what)?;
        Ok(u32::from_le_bytes(bytes.try_into().expect("4 bytes")))
    }

    /// A canonical varint of a `u32` or (`wide`) `u64` member, every error at its first byte: a
    /// first byte that is no such varint, a varint that runs past the payload, one that is not
    /// minimal (spec §7.4.1). `what` names the member and is called only on failure: a length
    /// prefix's "the length of …" is not formatted per sequence read.
    fn varint_checked(&mut self, wide: bool, what: impl Fn() -> String) -> Result<u64> {
        let start = self.at;
        let first = self.take_with(1, &what)?[0];
        let len = match first {
            0..=250 => return Ok(u64::from(first)),
            VARINT_U16 => 3,
            VARINT_U32 => 5,
            VARINT_U64 if wide => 9,
            _ => 1,
        };
        if len > 1 && self.remaining() < len - 1 {
            return Err(self.fail(
                start,
                format!(
                    "{}: a varint of {len} bytes; the payload ends after {}",
                    what(),
                    self.remaining() + 1
                ),
            ));
        }
        let mut bytes = [0u8; 9];
        bytes[0] = first;
        if len > 1 {
            let rest = self.take_with(len - 1, &what)?;
            bytes[1..len].copy_from_slice(rest);
        }
        match varint(&bytes[..len], wide) {
            Varint::Value(v, _) => Ok(v),
            Varint::Bad(why) => Err(self.fail(start, format!("{}: {why} (spec §7.4.1)", what()))),
            Varint::Short(_) => unreachable!("all {len} bytes are there"),
        }
    }

    fn f64(&mut self, what: &str) -> Result<f64> {
        let bytes = self.take(8, what)?;
        Ok(f64::from_le_bytes(bytes.try_into().expect("8 bytes")))
    }

    /// A length prefix (`u64`, or a varint), checked against the bytes left: `min` is the smallest size of one
    /// element, so nothing is allocated for elements the payload cannot hold.
    pub(crate) fn length(&mut self, min: usize, what: &str) -> Result<usize> {
        let start = self.at;
        let n = if VARINT {
            self.varint_checked(true, || format!("the length of {what}"))?
        } else {
            let bytes = self.take_with(8, || format!("the length of {what}"))?;
            u64::from_le_bytes(bytes.try_into().expect("8 bytes"))
        };
        let left = self.remaining();
        if n > (left / min) as u64 {
            return Err(self.fail(
                start,
                format!(
                    "{what} declares {n} elements of at least {min} bytes; only {left} bytes remain"
                ),
            ));
        }
        Ok(n as usize)
    }

    fn string(&mut self, what: &str) -> Result<String> {
        Ok(self.string_at(what)?.0)
    }

    /// A string and the payload offset of its first byte (after the length prefix).
    fn string_at(&mut self, what: &str) -> Result<(String, usize)> {
        let n = self.length(1, what)?;
        let at = self.at;
        let bytes = self.take(n, what)?;
        let text = std::str::from_utf8(bytes)
            .map(str::to_string)
            .map_err(|e| e.valid_up_to());
        text.map(|t| (t, at))
            .map_err(|valid| self.fail(at + valid, format!("invalid UTF-8 in {what}")))
    }

    fn optional_string(&mut self, what: &str) -> Result<Option<String>> {
        let start = self.at;
        match self.u8(&format!("the presence tag of {what}"))? {
            0 => Ok(None),
            1 => Ok(Some(self.string(what)?)),
            t => Err(self.fail(
                start,
                format!("presence tag {t} of {what}; expected 0 (absent) or 1 (present)"),
            )),
        }
    }

    pub(crate) fn member<T>(
        &mut self,
        name: &'static str,
        read: impl FnOnce(&mut Self) -> Result<T>,
    ) -> Result<T> {
        self.path.push(Seg::Key(name.into()));
        let out = read(self)?;
        self.path.pop();
        Ok(out)
    }

    /// A length-prefixed array of `f64` in a vector of exactly its length (reserved once: see
    /// [`Self::reserve_exact`]).
    pub(crate) fn f64s(&mut self, what: &str) -> Result<Vec<f64>> {
        let n = self.length(Self::MIN.f64, what)?;
        let mut out = Vec::new();
        Self::reserve_exact(&mut out, n);
        self.numbers_into(n, 8, what, &mut out, |c| {
            f64::from_le_bytes(c.try_into().expect("8 bytes"))
        })?;
        Ok(out)
    }

    /// A length-prefixed array of `u32`, as [`Self::f64s`].
    pub(crate) fn u32s(&mut self, what: &str) -> Result<Vec<u32>> {
        let n = self.length(Self::MIN.u32, what)?;
        let mut out = Vec::new();
        Self::reserve_exact(&mut out, n);
        self.u32_elements(n, what, &mut out)?;
        Ok(out)
    }

    /// Reserves room for `n` more elements the payload declares (and has room for: the caller
    /// checked `n` against the bytes left), so a large array is allocated once instead of grown by
    /// doubling (each growth copies it and touches its pages again). Reserving is not touching: a
    /// streamed payload's pages are written only as its bytes arrive, so a file that declares more
    /// than it holds costs address space, not memory, until it is found short; a reservation the
    /// allocator refuses is skipped (the vector then grows as bytes arrive).
    fn reserve_exact<T>(out: &mut Vec<T>, n: usize) {
        let _ = out.try_reserve_exact(n);
    }

    /// Appends a length-prefixed array of `f64` to `out` (no allocation but `out`'s growth).
    fn f64s_into(&mut self, out: &mut Vec<f64>, what: &str) -> Result<()> {
        let n = self.length(Self::MIN.f64, what)?;
        self.numbers_into(n, 8, what, out, |c| {
            f64::from_le_bytes(c.try_into().expect("8 bytes"))
        })
    }

    /// Appends a length-prefixed array of `u32` to `out`.
    fn u32s_into(&mut self, out: &mut Vec<u32>, what: &str) -> Result<()> {
        let n = self.length(Self::MIN.u32, what)?;
        self.u32_elements(n, what, out)
    }

    /// Appends `n` `u32` elements to `out`: fixed width a window at a time, or varints, as many at
    /// a time as are wholly at hand (the checked path reads the one that is not, with its error).
    fn u32_elements(&mut self, n: usize, what: &str, out: &mut Vec<u32>) -> Result<()> {
        if !VARINT {
            return self.numbers_into(n, 4, what, out, |c| {
                u32::from_le_bytes(c.try_into().expect("4 bytes"))
            });
        }
        let mut left = n;
        while left > 0 {
            let (k, used) = varint_u32_run(self.at_hand(), left, out);
            self.advance(used);
            left -= k;
            if left > 0 {
                out.push(self.u32(what)?);
                left -= 1;
            }
        }
        Ok(())
    }

    /// The payload bytes already at hand (in memory, or in the stream's window), unconsumed.
    #[inline]
    fn at_hand(&self) -> &[u8] {
        match &self.src {
            Source::Slice(b) => &b[self.at..],
            Source::Stream(s) => &s.buf[s.lo..s.hi],
        }
    }

    /// Consumes `n` bytes of [`Self::at_hand`].
    #[inline]
    fn advance(&mut self, n: usize) {
        self.at += n;
        if let Source::Stream(s) = &mut self.src {
            s.lo += n;
        }
    }

    /// One face record read straight from the bytes at hand, when all of it is there: the three
    /// length-prefixed arrays appended to the table's parts. `false` (nothing consumed, nothing
    /// appended) when the record is not wholly at hand; then the checked path reads it, with its
    /// errors. Whole records at hand lie inside the declared payload, so every length check of the
    /// checked path would pass: the two paths accept the same bytes and decode them alike.
    #[inline]
    fn face_record_at_hand(&mut self, table: &mut FaceTable) -> bool {
        if VARINT {
            return self.varint_record_at_hand(table);
        }
        let bytes = self.at_hand();
        let length = |at: usize| -> Option<usize> {
            let b = bytes.get(at..at + 8)?;
            usize::try_from(u64::from_le_bytes(b.try_into().ok()?)).ok()
        };
        let Some(nf) = length(0) else { return false };
        let f_end = match nf.checked_mul(4).and_then(|x| x.checked_add(8)) {
            Some(e) => e,
            None => return false,
        };
        let Some(np) = length(f_end) else {
            return false;
        };
        let p_end = match np.checked_mul(8).and_then(|x| x.checked_add(f_end + 8)) {
            Some(e) => e,
            None => return false,
        };
        let Some(nw) = length(p_end) else {
            return false;
        };
        let w_end = match nw.checked_mul(8).and_then(|x| x.checked_add(p_end + 8)) {
            Some(e) if e <= bytes.len() => e,
            _ => return false,
        };
        let (ids, points, weights) = table.parts_mut();
        ids.extend(
            bytes[8..f_end]
                .chunks_exact(4)
                .map(|c| u32::from_le_bytes(c.try_into().expect("4 bytes"))),
        );
        if !self.keep_numbers {
            let finite =
                all_finite(&bytes[f_end + 8..p_end]) && all_finite(&bytes[p_end + 8..w_end]);
            table.count_numbers(np, nw, finite);
            self.advance(w_end);
            return true;
        }
        points.extend(
            bytes[f_end + 8..p_end]
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes"))),
        );
        weights.extend(
            bytes[p_end + 8..w_end]
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes"))),
        );
        self.advance(w_end);
        true
    }

    /// [`Self::face_record_at_hand`] for the compact encoding: lengths and ids are varints, so the
    /// record's layout is found as it is read; `false` (nothing consumed, nothing appended) when
    /// a part is not wholly at hand or not canonical.
    fn varint_record_at_hand(&mut self, table: &mut FaceTable) -> bool {
        let bytes = self.at_hand();
        let length = |at: usize| -> Option<(usize, usize)> {
            match varint(bytes.get(at..)?, true) {
                Varint::Value(v, len) => Some((usize::try_from(v).ok()?, len)),
                _ => None,
            }
        };
        let (ids, points, weights) = table.parts_mut();
        let ids_before = ids.len();
        let layout = (|| {
            let (nf, l) = length(0)?;
            let (k, used) = varint_u32_run(&bytes[l..], nf, ids);
            (k == nf).then_some(())?;
            let (np, l2) = length(l + used)?;
            let p_start = l + used + l2;
            let p_end = np.checked_mul(8)?.checked_add(p_start)?;
            let (nw, l3) = length(p_end)?;
            let w_start = p_end + l3;
            let w_end = nw.checked_mul(8)?.checked_add(w_start)?;
            (w_end <= bytes.len()).then_some((np, p_start, p_end, nw, w_start, w_end))
        })();
        let Some((np, p_start, p_end, nw, w_start, w_end)) = layout else {
            ids.truncate(ids_before);
            return false;
        };
        if !self.keep_numbers {
            let finite = all_finite(&bytes[p_start..p_end]) && all_finite(&bytes[w_start..w_end]);
            table.count_numbers(np, nw, finite);
            self.advance(w_end);
            return true;
        }
        points.extend(
            bytes[p_start..p_end]
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes"))),
        );
        weights.extend(
            bytes[w_start..w_end]
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes"))),
        );
        self.advance(w_end);
        true
    }

    /// Of the next `left` face records, those wholly at hand that have the lengths every record of
    /// `table` has so far (a uniform table, not empty): appended in one loop, without a record's
    /// bookkeeping; how many. Stops before the first record of other lengths, the first one not
    /// wholly at hand and the first one the table has no room for: the general path reads those.
    /// What is appended is what [`Self::face_record_at_hand`] would append, record by record.
    fn uniform_records_at_hand(&mut self, table: &mut FaceTable, left: usize) -> usize {
        if VARINT {
            // Records of one shape still differ in size (varint ids): record by record.
            return 0;
        }
        let Some([a, b, c]) = table.uniform_lengths() else {
            return 0;
        };
        let room = table.uniform_room();
        let bytes = match &self.src {
            Source::Slice(p) => &p[self.at..],
            Source::Stream(s) => &s.buf[s.lo..s.hi],
        };
        // A record: length a, the ids (to `fe`), length b, the points (from `ps` to `pe`),
        // length c, the weights (from `ws` to the end).
        let fe = 8 + 4 * a;
        let (ps, pe) = (fe + 8, fe + 8 + 8 * b);
        let ws = pe + 8;
        let size = ws + 8 * c;
        let most = (bytes.len() / size).min(left).min(room);
        let prefix = |n: usize| (n as u64).to_le_bytes();
        let (la, lb, lc) = (prefix(a), prefix(b), prefix(c));
        let keep = self.keep_numbers;
        let mut finite = true;
        let (ids, points, weights) = table.parts_mut();
        let mut k = 0;
        for rec in bytes.chunks_exact(size).take(most) {
            if rec[..8] != la || rec[fe..ps] != lb || rec[pe..ws] != lc {
                break;
            }
            ids.extend(
                rec[8..fe]
                    .chunks_exact(4)
                    .map(|x| u32::from_le_bytes(x.try_into().expect("4 bytes"))),
            );
            k += 1;
            if !keep {
                finite &= all_finite(&rec[ps..pe]) & all_finite(&rec[ws..]);
                continue;
            }
            points.extend(
                rec[ps..pe]
                    .chunks_exact(8)
                    .map(|x| f64::from_le_bytes(x.try_into().expect("8 bytes"))),
            );
            weights.extend(
                rec[ws..]
                    .chunks_exact(8)
                    .map(|x| f64::from_le_bytes(x.try_into().expect("8 bytes"))),
            );
        }
        if !keep {
            table.count_numbers(k * b, k * c, finite);
        }
        table.close_uniform(k);
        self.advance(k * size);
        k
    }

    /// A stage's `faces`: straight into the flat table, one pass, nothing allocated per record.
    pub(crate) fn face_table(&mut self) -> Result<FaceTable> {
        let n = self.length(Self::MIN.face_record, "faces")?;
        let mut table = FaceTable::new();
        if !self.keep_numbers {
            table.elide_numbers();
        }
        // A record's numbers on the checked path, when the table does not keep them.
        let mut scratch: Vec<f64> = Vec::new();
        let mut i = 0;
        while i < n {
            if i > 0 {
                i += self.uniform_records_at_hand(&mut table, n - i);
                if i == n {
                    break;
                }
            }
            let before = self.at;
            if self.face_record_at_hand(&mut table) {
                if table.close_record().is_ok() {
                    if i == 0 {
                        // Room for the rest, when the payload can hold that many records of the
                        // first one's size (records of one face dimension, as usual): the parts
                        // are allocated once (see `reserve_exact`).
                        let size = self.at - before;
                        let rest = n - 1;
                        if rest
                            .checked_mul(size)
                            .is_some_and(|b| b <= self.remaining())
                        {
                            table.reserve_records(rest);
                        }
                    }
                    i += 1;
                    continue;
                }
                // Past the table's capacity: the error the checked path gives at this record.
                return Err(Error::format(
                    Rule::LimitExceeded,
                    Location {
                        pointer: Some(format!("{}/{i}", pointer_of(&self.path))),
                        offset: Some(self.base + self.at as u64),
                        ..Location::default()
                    },
                    crate::faces::TableFull.to_string(),
                ));
            }
            self.path.push(Seg::Index(i));
            let (ids, points, weights) = table.parts_mut();
            self.member("face", |d| d.u32s_into(ids, "face"))?;
            if self.keep_numbers {
                self.member("points", |d| d.f64s_into(points, "points"))?;
                self.member("weights", |d| d.f64s_into(weights, "weights"))?;
            } else {
                scratch.clear();
                self.member("points", |d| d.f64s_into(&mut scratch, "points"))?;
                let np = scratch.len();
                self.member("weights", |d| d.f64s_into(&mut scratch, "weights"))?;
                let finite = scratch.iter().all(|x| x.is_finite());
                table.count_numbers(np, scratch.len() - np, finite);
            }
            if let Err(full) = table.close_record() {
                return Err(Error::format(
                    Rule::LimitExceeded,
                    Location {
                        pointer: Some(pointer_of(&self.path)),
                        offset: Some(self.base + self.at as u64),
                        ..Location::default()
                    },
                    full.to_string(),
                ));
            }
            self.path.pop();
            i += 1;
        }
        Ok(table)
    }

    fn seq<T>(
        &mut self,
        min: usize,
        what: &str,
        mut read: impl FnMut(&mut Self) -> Result<T>,
    ) -> Result<Vec<T>> {
        let n = self.length(min, what)?;
        let mut out = Vec::with_capacity(self.reserve_hint(n));
        for i in 0..n {
            self.path.push(Seg::Index(i));
            out.push(read(self)?);
            self.path.pop();
        }
        Ok(out)
    }

    /// A `json` member: the canonical compact JSON text of the value (spec §7.4, §7.7), nested below
    /// `depth` arrays and objects.
    fn json(&mut self, depth: usize) -> Result<JsonValue> {
        let start = self.at;
        let (text, text_at) = self.string_at("JSON text")?;
        let tokens = JsonTokens::new(text.as_bytes(), self.base + text_at as u64);
        let mut d = Decoder::nested(tokens, self.path.clone(), depth);
        let value = d.json()?;
        d.end()?;
        let canonical = crate::canonical::json_text(&value);
        if canonical != text {
            let shown: String = canonical.chars().take(60).collect();
            return Err(self.fail(
                start,
                format!("JSON text is not in the canonical compact form (spec §7.7), which begins {shown:?}"),
            ));
        }
        Ok(JsonValue(value))
    }

    /// A stage; `complex` is the complex's faces in the structured encoding (`None` in the
    /// others), whose records are then given by it (spec §7.4.3).
    fn stage(&mut self, complex: Option<&mut ComplexFaces>) -> Result<Stage> {
        let kind_at = self.at;
        let kind = match self.member("kind", |d| d.u32("kind"))? {
            0 => StageKind::Bezier,
            1 => StageKind::Rational,
            2 => StageKind::Monotonic,
            k => {
                self.path.push(Seg::Key("kind".into()));
                return Err(self.fail(
                    kind_at,
                    format!("kind {k}; expected 0 (bezier), 1 (rational) or 2 (monotonic)"),
                ));
            }
        };
        let degree = self.member("degree", |d| d.u32("degree"))?;
        let direction_at = self.at;
        let direction = match self.member("direction", |d| d.u32("direction"))? {
            0 => Direction::Implicit,
            1 => Direction::Parametric,
            k => {
                self.path.push(Seg::Key("direction".into()));
                return Err(self.fail(
                    direction_at,
                    format!("direction {k}; expected 0 (implicit) or 1 (parametric)"),
                ));
            }
        };
        let name = self.member("name", |d| d.optional_string("name"))?;
        let faces = self.member("faces", |d| match complex {
            Some(complex) => d.records(complex, kind, degree),
            None => d.face_table(),
        })?;
        let vertex_maps = self.member("vertexMaps", |d| {
            d.seq(Self::MIN.vertex_map, "vertexMaps", |d| {
                Ok(VertexMap {
                    vertex: d.member("vertex", |d| d.u32("vertex"))?,
                    coefficients: d.member("coefficients", |d| d.f64s("coefficients"))?,
                })
            })
        })?;
        // Model (1), stages (2), this stage (3).
        let extras = self.member("extras", |d| d.json(3))?;
        Ok(Stage {
            kind,
            degree,
            direction,
            name,
            faces,
            vertex_maps,
            extras,
        })
    }

    fn extensions(&mut self) -> Result<BTreeMap<String, JsonValue>> {
        let n = self.length(Self::MIN.extension, "extensions")?;
        let mut out = BTreeMap::new();
        let mut previous: Option<String> = None;
        for _ in 0..n {
            let key_at = self.at;
            let key = self.string("an extension name")?;
            self.path.push(Seg::Key(key.clone().into()));
            if let Some(prev) = &previous {
                if key.as_bytes() <= prev.as_bytes() {
                    return Err(self.fail(
                        key_at,
                        if key == *prev {
                            format!("extension {key:?} given twice")
                        } else {
                            format!("extension names must be in increasing byte order: {key:?} follows {prev:?}")
                        },
                    ));
                }
            }
            // Model (1), extensions (2).
            let value = self.json(2)?;
            self.path.pop();
            previous = Some(key.clone());
            out.insert(key, value);
        }
        Ok(out)
    }

    /// Decodes the whole payload. Bytes after the model are an error unless `allow_trailing` (a
    /// newer minor version's added fields, spec §8.1).
    pub(crate) fn model(&mut self, allow_trailing: bool) -> Result<Model> {
        let version = self.member("version", |d| d.string("version"))?;
        let dimension = self.member("dimension", |d| d.u8("dimension"))?;
        let metadata = self.member("metadata", |d| {
            Ok(Metadata {
                name: d.member("name", |d| d.optional_string("name"))?,
                generator: d.member("generator", |d| d.optional_string("generator"))?,
                units: d.member("units", |d| d.optional_string("units"))?,
                description: d.member("description", |d| d.optional_string("description"))?,
            })
        })?;
        let (vertices, simplices) = if self.structured {
            // `complexForm`, then `vertices` and `simplices` as listed or by a refinement.
            self.complex(dimension)?
        } else {
            (
                self.member("vertices", |d| d.f64s("vertices"))?,
                self.member("simplices", |d| d.u32s("simplices"))?,
            )
        };
        let values = self.member("values", |d| d.f64s("values"))?;
        let level = self.member("level", |d| d.f64("level"))?;
        // The structured encoding's records refer to the complex's faces, computed when a stage
        // first needs them.
        let mut complex = self
            .structured
            .then(|| ComplexFaces::new(dimension, &simplices));
        let stages = self.member("stages", |d| {
            d.seq(Self::MIN.stage, "stages", |d| d.stage(complex.as_mut()))
        })?;
        let extensions_used = self.member("extensionsUsed", |d| {
            d.seq(Self::MIN.string, "extensionsUsed", |d| {
                d.string("an extension name")
            })
        })?;
        let extensions_required = self.member("extensionsRequired", |d| {
            d.seq(Self::MIN.string, "extensionsRequired", |d| {
                d.string("an extension name")
            })
        })?;
        let extensions = self.member("extensions", |d| d.extensions())?;
        // Model (1).
        let extras = self.member("extras", |d| d.json(1))?;
        if self.at < self.end && !allow_trailing {
            return Err(self.fail(
                self.at,
                format!("{} bytes follow the model", self.end - self.at),
            ));
        }
        if allow_trailing && self.at < self.end {
            // A newer minor version's added fields: consumed unread (a stream is drained by its
            // owner, which also checksums them).
            self.at = self.end;
        }
        Ok(Model {
            version,
            dimension,
            metadata,
            vertices,
            simplices,
            values,
            level,
            stages,
            extensions_used,
            extensions_required,
            extensions,
            extras,
        })
    }
}
