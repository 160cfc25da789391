//! Strict decoding of the JSON and MessagePack encodings (spec §7.2, §7.3, §7.8).
//!
//! Both encodings are read by one typed decoder driven by a small pull tokenizer per encoding, so the
//! rules of §7.8 — nesting depth, unique keys, string keys, number ranges, what a location names —
//! are enforced once and identically. Serde's derive is not used for reading: it accepts integer
//! keys and arrays for structs in MessagePack, keeps the last of two equal keys in maps, and reports
//! positions only as lines and columns.
//!
//! Errors are reported in the order of the bytes: the first byte that breaks a rule decides. Each
//! carries the JSON pointer of the value being read (the enclosing array or object between values)
//! and the file offset of the offending byte.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashSet};

use crate::error::{Error, Result};
use crate::faces::FaceTable;
use crate::model::{Direction, JsonValue, Metadata, Model, Stage, StageKind, VertexMap};
use crate::rules::{Location, Rule};
use crate::structure::escape_pointer;

/// The deepest nesting of arrays and objects a file may hold, counting the model object as level 1
/// (spec §7.8). Readers refuse deeper payloads and writers refuse to write them.
pub const MAX_DEPTH: usize = 64;

/// The most decimal digits of an integer read without a general parse: 10^19 - 1 < 2^64.
const MAX_FAST_DIGITS: usize = 19;

/// A tokenizer failure: what went wrong and the file offset of the offending byte.
pub(crate) struct Fail {
    pub offset: u64,
    pub message: String,
}

type Step<T> = std::result::Result<T, Fail>;

/// A number as the encoding spelled it.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Num {
    /// The integer value, when the number was written as an integer (JSON: no fraction and no
    /// exponent; MessagePack: an int format) and fits in an `i128`.
    pub int: Option<i128>,
    /// The nearest `f64`.
    pub value: f64,
    /// Written as an integer.
    pub integer: bool,
}

impl std::fmt::Display for Num {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.int {
            Some(i) => write!(f, "{i}"),
            None => write!(f, "{}", self.value),
        }
    }
}

/// The start of a value.
pub(crate) enum Head {
    Null,
    Bool(bool),
    Num(Num),
    Str(String),
    /// An array; MessagePack knows the element count.
    Array(Option<usize>),
    /// An object (map); MessagePack knows the entry count.
    Object(Option<usize>),
}

impl Head {
    fn describe(&self) -> String {
        match self {
            Head::Null => "null".into(),
            Head::Bool(b) => b.to_string(),
            Head::Num(n) => format!("the number {n}"),
            Head::Str(s) if s.len() <= 40 => format!("the string {s:?}"),
            Head::Str(_) => "a string".into(),
            Head::Array(_) => "an array".into(),
            Head::Object(_) => "an object".into(),
        }
    }
}

/// Where a tokenizer is inside an array or object.
pub(crate) struct Seq {
    remaining: Option<usize>,
    first: bool,
}

impl Seq {
    fn new(count: Option<usize>) -> Seq {
        Seq {
            remaining: count,
            first: true,
        }
    }
}

/// A pull tokenizer over one encoding, borrowing the payload for `'a`.
pub(crate) trait Tokens<'a> {
    /// Reads the head of the next value and returns it with the file offset of its first byte.
    fn head(&mut self) -> Step<(Head, u64)>;
    /// Reads the next value when it is a number, as [`Tokens::head`] would; `None` (nothing consumed
    /// but whitespace) when it is anything else, for the caller to read its head and report it.
    /// The fast path of the arrays of numbers that make up most of a model.
    fn number(&mut self) -> Step<Option<(Num, u64)>>;
    /// The next value's `f64` when it is a valid, finite number the tokenizer reads in one pass;
    /// `None` (nothing consumed but whitespace) for [`Tokens::number`] to read it and say what is
    /// wrong. Returns in registers: the hot loop of the arrays of coordinates and control points.
    fn quick_f64(&mut self) -> Option<f64> {
        None
    }
    /// The next value when it is an integer from 0 to `max` written plainly, as
    /// [`Tokens::number`] would read it; `None` (nothing consumed but whitespace) otherwise. The
    /// hot loop of vertex ids.
    fn quick_uint(&mut self, _max: u32) -> Option<u32> {
        None
    }
    /// Reads a run of the array's next elements while each is a number [`Tokens::quick_f64`]
    /// reads, appending their values to `out`, and returns how many: the
    /// [`Tokens::next_element`] and `quick_f64` pairs of the general walk in one loop, without a
    /// call per element. Stops before the first element (with its separator) it does not take —
    /// the array's end, a number for the general reading, anything wrong — leaving the position
    /// and `seq` as they were there, so the general walk reads the rest exactly as it read the
    /// whole array before. The default takes none.
    fn quick_f64_run(&mut self, _seq: &mut Seq, _out: &mut Vec<f64>) -> usize {
        0
    }
    /// [`Tokens::quick_f64_run`] for the integers from 0 to `max` [`Tokens::quick_uint`] reads.
    fn quick_uint_run(&mut self, _seq: &mut Seq, _max: u32, _out: &mut Vec<u32>) -> usize {
        0
    }
    /// Whether the array has another element (JSON: consumes `,` or `]`).
    fn next_element(&mut self, seq: &mut Seq) -> Step<bool>;
    /// The next key of the object and its offset, or `None` at its end. Borrowed from the payload
    /// when it needs no unescaping: a million face records' keys allocate nothing.
    fn next_key(&mut self, seq: &mut Seq) -> Step<Option<(Cow<'a, str>, u64)>>;
    /// Checks that nothing but what the encoding allows follows the top-level value.
    fn end(&mut self) -> Step<()>;
}

fn show_byte(b: u8) -> String {
    if b.is_ascii_graphic() {
        format!("'{}'", b as char)
    } else {
        format!("byte 0x{b:02x}")
    }
}

/// The position of the first byte at or after `at` that is not JSON whitespace.
#[inline(always)]
fn skip_ws(b: &[u8], mut at: usize) -> usize {
    // A local index: kept in a register, not stored per byte.
    loop {
        match b.get(at) {
            Some(b' ' | b'\t' | b'\r') => at += 1,
            Some(b'\n') => {
                at += 1;
                // The indentation after a line break (a pretty-printed model puts each number
                // on its own line), eight spaces per step: the spaces are the bytes before the
                // first one that differs from b' ' (little-endian: the lowest set byte).
                while let Some(chunk) = b.get(at..at + 8) {
                    let word = u64::from_le_bytes(chunk.try_into().expect("eight bytes"));
                    let differ = word ^ u64::from_le_bytes([b' '; 8]);
                    if differ != 0 {
                        at += differ.trailing_zeros() as usize / 8;
                        break;
                    }
                    at += 8;
                }
            }
            _ => break,
        }
    }
    at
}

/// The integer from 0 to `max` written plainly at `start` and the position after it; `None`
/// for anything else ([`Tokens::quick_uint`]).
#[inline(always)]
fn plain_uint(b: &[u8], start: usize, max: u32) -> Option<(u32, usize)> {
    // At most 10 digits (u32::MAX has 10), no leading zero (JSON's `0` is the integer zero
    // alone), and a plain integer: no point, exponent or further digit after them.
    let mut at = start;
    let mut value = 0u64;
    while let Some(&c @ b'0'..=b'9') = b.get(at) {
        if at - start == 10 || (at == start + 1 && value == 0) {
            return None;
        }
        value = value * 10 + u64::from(c - b'0');
        at += 1;
    }
    if at == start || matches!(b.get(at), Some(b'.' | b'e' | b'E')) || value > u64::from(max) {
        return None;
    }
    Some((value as u32, at))
}

/// RFC 8259 JSON, strictly: whitespace is space, tab, LF and CR; no byte-order mark.
pub(crate) struct JsonTokens<'a> {
    b: &'a [u8],
    at: usize,
    base: u64,
}

impl<'a> JsonTokens<'a> {
    /// Tokens of `bytes`, whose first byte is at file offset `base`.
    pub(crate) fn new(bytes: &'a [u8], base: u64) -> JsonTokens<'a> {
        JsonTokens {
            b: bytes,
            at: 0,
            base,
        }
    }

    fn fail(&self, at: usize, message: impl Into<String>) -> Fail {
        Fail {
            offset: self.base + at as u64,
            message: message.into(),
        }
    }

    fn found(&self, expected: &str) -> Fail {
        match self.b.get(self.at) {
            None => self.fail(
                self.at,
                format!("unexpected end of the JSON text; expected {expected}"),
            ),
            Some(&c) => self.fail(
                self.at,
                format!("unexpected {}; expected {expected}", show_byte(c)),
            ),
        }
    }

    #[inline]
    fn ws(&mut self) {
        self.at = skip_ws(self.b, self.at);
    }

    /// A string, borrowed from the text when it holds no escape (keys, most values).
    fn string(&mut self) -> Step<Cow<'a, str>> {
        let start = self.at;
        self.at += 1; // the opening quote
        let mut out = String::new();
        let b = self.b;
        loop {
            let run_start = self.at;
            while let Some(&c) = b.get(self.at) {
                if c == b'"' || c == b'\\' || c < 0x20 {
                    break;
                }
                self.at += 1;
            }
            let run = match std::str::from_utf8(&b[run_start..self.at]) {
                Ok(s) => s,
                Err(e) => {
                    return Err(self.fail(run_start + e.valid_up_to(), "invalid UTF-8 in a string"))
                }
            };
            if b.get(self.at) == Some(&b'"') && run_start == start + 1 {
                self.at += 1;
                return Ok(Cow::Borrowed(run));
            }
            out.push_str(run);
            match self.b.get(self.at) {
                None => {
                    return Err(self.fail(
                        self.at,
                        format!(
                            "unexpected end of the JSON text in the string starting at byte {}",
                            self.base + start as u64
                        ),
                    ))
                }
                Some(b'"') => {
                    self.at += 1;
                    return Ok(Cow::Owned(out));
                }
                Some(b'\\') => {
                    let esc = self.at;
                    self.at += 1;
                    let c = match self.b.get(self.at) {
                        Some(b'"') => '"',
                        Some(b'\\') => '\\',
                        Some(b'/') => '/',
                        Some(b'b') => '\u{8}',
                        Some(b'f') => '\u{c}',
                        Some(b'n') => '\n',
                        Some(b'r') => '\r',
                        Some(b't') => '\t',
                        Some(b'u') => {
                            self.at += 1;
                            let hi = self.hex4(esc)?;
                            let code = if (0xD800..0xDC00).contains(&hi) {
                                if self.b.get(self.at..self.at + 2) != Some(b"\\u") {
                                    return Err(self.fail(esc, "unpaired UTF-16 surrogate escape"));
                                }
                                self.at += 2;
                                let lo = self.hex4(esc)?;
                                if !(0xDC00..0xE000).contains(&lo) {
                                    return Err(self.fail(esc, "unpaired UTF-16 surrogate escape"));
                                }
                                0x10000 + ((hi - 0xD800) << 10) + (lo - 0xDC00)
                            } else if (0xDC00..0xE000).contains(&hi) {
                                return Err(self.fail(esc, "unpaired UTF-16 surrogate escape"));
                            } else {
                                hi
                            };
                            out.push(char::from_u32(code).expect("surrogates excluded"));
                            continue;
                        }
                        _ => return Err(self.fail(esc, "invalid escape in a string")),
                    };
                    self.at += 1;
                    out.push(c);
                }
                Some(_) => {
                    return Err(self.fail(
                        self.at,
                        "control character in a string (U+0000 to U+001F must be escaped)",
                    ))
                }
            }
        }
    }

    fn hex4(&mut self, esc: usize) -> Step<u32> {
        let digits = self
            .b
            .get(self.at..self.at + 4)
            .and_then(|d| std::str::from_utf8(d).ok())
            .filter(|d| d.bytes().all(|c| c.is_ascii_hexdigit()))
            .ok_or_else(|| {
                self.fail(esc, "invalid \\u escape: expected four hexadecimal digits")
            })?;
        self.at += 4;
        Ok(u32::from_str_radix(digits, 16).expect("hex digits"))
    }

    fn digits(&mut self) -> usize {
        // A local index: the loop keeps it in a register instead of storing `self.at` per digit.
        let (b, start) = (self.b, self.at);
        let mut at = start;
        while b.get(at).is_some_and(u8::is_ascii_digit) {
            at += 1;
        }
        self.at = at;
        at - start
    }

    /// A number (RFC 8259 grammar); its value correctly rounded to the nearest `f64`.
    #[inline]
    fn scan_number(&mut self) -> Step<Num> {
        let start = self.at;
        match self.quick_number() {
            Some(n) => Ok(n),
            None => {
                self.at = start;
                self.strict_number()
            }
        }
    }

    /// The number at the current position when it is valid and finite, in one pass: the
    /// integer part here, the fraction and exponent by fast-float2 (`parse_partial`: Eisel-Lemire
    /// with a correct fallback, the algorithm of Rust's own `str::parse::<f64>`, from the bytes and
    /// 1.6x std's speed on the benchmark model's numbers). `None` leaves the position anywhere, for
    /// [`JsonTokens::strict_number`] to read the number again and report what is wrong.
    ///
    /// fast-float2's grammar is JSON's widened (a `+` sign, leading zeros, `inf` and `nan`, a point
    /// without digits after it); what is checked here makes the text it took a JSON number and the
    /// one [`JsonTokens::strict_number`] takes: the integer part by JSON's rule (read here, so
    /// fast-float2 reads the same digits), a digit after a point, and no `e` or `E` left after the
    /// text (fast-float2 leaves an exponent without digits, which JSON refuses).
    #[inline]
    fn quick_number(&mut self) -> Option<Num> {
        let (b, start) = (self.b, self.at);
        let mut at = start;
        let negative = b.get(at) == Some(&b'-');
        if negative {
            at += 1;
        }
        let int_start = at;
        match b.get(at) {
            Some(b'0') => at += 1,
            Some(b'1'..=b'9') => {
                while b.get(at).is_some_and(u8::is_ascii_digit) {
                    at += 1;
                }
            }
            _ => return None,
        }
        match b.get(at) {
            Some(b'.' | b'e' | b'E') => {
                if b[at] == b'.' && !b.get(at + 1).is_some_and(u8::is_ascii_digit) {
                    return None;
                }
                let (value, len) = fast_float2::parse_partial::<f64, _>(&b[start..]).ok()?;
                let end = start + len;
                if end <= at || matches!(b.get(end), Some(b'e' | b'E')) || !value.is_finite() {
                    return None;
                }
                self.at = end;
                Some(Num {
                    int: None,
                    value,
                    integer: false,
                })
            }
            _ => {
                let digits = &b[int_start..at];
                if digits.len() > MAX_FAST_DIGITS {
                    return None;
                }
                let m = digits
                    .iter()
                    .fold(0u64, |m, &d| m * 10 + u64::from(d - b'0'));
                // `as` rounds to the nearest f64, ties to even: what a correctly rounded parse of
                // the same text gives (and `-0` keeps its sign).
                let (int, value) = if negative {
                    (-i128::from(m), -(m as f64))
                } else {
                    (i128::from(m), m as f64)
                };
                self.at = at;
                Some(Num {
                    int: Some(int),
                    value,
                    integer: true,
                })
            }
        }
    }

    /// A number, its grammar checked byte by byte to name what is wrong; the reference
    /// [`JsonTokens::quick_number`] agrees with (tests).
    #[cold]
    #[inline(never)]
    fn strict_number(&mut self) -> Step<Num> {
        let start = self.at;
        if self.b.get(self.at) == Some(&b'-') {
            self.at += 1;
        }
        match self.b.get(self.at) {
            Some(b'0') => self.at += 1,
            Some(b'1'..=b'9') => {
                self.digits();
            }
            _ => return Err(self.found("a digit")),
        }
        let mut integer = true;
        if self.b.get(self.at) == Some(&b'.') {
            integer = false;
            self.at += 1;
            if self.digits() == 0 {
                return Err(self.found("a digit after the decimal point"));
            }
        }
        if let Some(b'e' | b'E') = self.b.get(self.at) {
            integer = false;
            self.at += 1;
            if let Some(b'+' | b'-') = self.b.get(self.at) {
                self.at += 1;
            }
            if self.digits() == 0 {
                return Err(self.found("a digit in the exponent"));
            }
        }
        let text = std::str::from_utf8(&self.b[start..self.at]).expect("ASCII");
        let value: f64 = text
            .parse()
            .expect("JSON number grammar is Rust float grammar");
        if !value.is_finite() {
            let shown = if text.len() > 30 { &text[..30] } else { text };
            return Err(self.fail(
                start,
                format!("the number {shown} does not round to a finite f64 (JSON holds finite numbers only)"),
            ));
        }
        let int = if integer {
            text.parse::<i128>().ok()
        } else {
            None
        };
        Ok(Num {
            int,
            value,
            integer,
        })
    }

    fn literal(&mut self, word: &[u8], head: Head) -> Step<Head> {
        if self.b.get(self.at..self.at + word.len()) == Some(word) {
            self.at += word.len();
            Ok(head)
        } else {
            Err(self.found("a value"))
        }
    }
}

impl<'a> Tokens<'a> for JsonTokens<'a> {
    #[inline]
    fn head(&mut self) -> Step<(Head, u64)> {
        self.ws();
        let start = self.at;
        let offset = self.base + start as u64;
        let head = match self.b.get(self.at) {
            Some(b'{') => {
                self.at += 1;
                Head::Object(None)
            }
            Some(b'[') => {
                self.at += 1;
                Head::Array(None)
            }
            Some(b'"') => Head::Str(self.string()?.into_owned()),
            Some(b't') => self.literal(b"true", Head::Bool(true))?,
            Some(b'f') => self.literal(b"false", Head::Bool(false))?,
            Some(b'n') => self.literal(b"null", Head::Null)?,
            Some(b'-' | b'0'..=b'9') => Head::Num(self.scan_number()?),
            _ => return Err(self.found("a value")),
        };
        Ok((head, offset))
    }

    #[inline]
    fn quick_f64(&mut self) -> Option<f64> {
        self.ws();
        let start = self.at;
        match self.quick_number() {
            Some(n) => Some(n.value),
            None => {
                self.at = start;
                None
            }
        }
    }

    #[inline]
    fn quick_uint(&mut self, max: u32) -> Option<u32> {
        self.ws();
        let (value, end) = plain_uint(self.b, self.at, max)?;
        self.at = end;
        Some(value)
    }

    fn quick_f64_run(&mut self, seq: &mut Seq, out: &mut Vec<f64>) -> usize {
        let b = self.b;
        let mut taken = 0;
        loop {
            let save = self.at;
            // The separator as `next_element` reads it when it answers `true`.
            let mut p = skip_ws(b, save);
            match b.get(p) {
                Some(b',') if !seq.first => p = skip_ws(b, p + 1),
                Some(b']') | None => break,
                Some(_) if seq.first => {}
                Some(_) => break,
            }
            self.at = p;
            let Some(n) = self.quick_number() else {
                // Not this element: the general walk reads it, separator and all.
                self.at = save;
                break;
            };
            out.push(n.value);
            seq.first = false;
            taken += 1;
        }
        taken
    }

    fn quick_uint_run(&mut self, seq: &mut Seq, max: u32, out: &mut Vec<u32>) -> usize {
        // The separator as `next_element` reads it when it answers `true`, then `quick_uint`, on
        // a local position (in a register): the simplices' ids are most of a model's numbers.
        let b = self.b;
        let (mut at, mut first) = (self.at, seq.first);
        let mut taken = 0;
        loop {
            let mut p = skip_ws(b, at);
            match b.get(p) {
                Some(b',') if !first => p = skip_ws(b, p + 1),
                Some(b']') | None => break,
                Some(_) if first => {}
                Some(_) => break,
            }
            let Some((v, end)) = plain_uint(b, p, max) else {
                break;
            };
            out.push(v);
            at = end;
            first = false;
            taken += 1;
        }
        // Not this element: the general walk reads it, separator and all.
        self.at = at;
        seq.first = first;
        taken
    }

    #[inline]
    fn number(&mut self) -> Step<Option<(Num, u64)>> {
        self.ws();
        match self.b.get(self.at) {
            Some(b'-' | b'0'..=b'9') => {
                let offset = self.base + self.at as u64;
                Ok(Some((self.scan_number()?, offset)))
            }
            _ => Ok(None),
        }
    }

    fn next_element(&mut self, seq: &mut Seq) -> Step<bool> {
        self.ws();
        if seq.first {
            seq.first = false;
            if self.b.get(self.at) == Some(&b']') {
                self.at += 1;
                return Ok(false);
            }
            return Ok(true);
        }
        match self.b.get(self.at) {
            Some(b',') => {
                self.at += 1;
                Ok(true)
            }
            Some(b']') => {
                self.at += 1;
                Ok(false)
            }
            _ => Err(self.found("',' or ']'")),
        }
    }

    fn next_key(&mut self, seq: &mut Seq) -> Step<Option<(Cow<'a, str>, u64)>> {
        self.ws();
        if seq.first {
            seq.first = false;
            if self.b.get(self.at) == Some(&b'}') {
                self.at += 1;
                return Ok(None);
            }
        } else {
            match self.b.get(self.at) {
                Some(b',') => {
                    self.at += 1;
                    self.ws();
                }
                Some(b'}') => {
                    self.at += 1;
                    return Ok(None);
                }
                _ => return Err(self.found("',' or '}'")),
            }
        }
        if self.b.get(self.at) != Some(&b'"') {
            return Err(self.found("a string key"));
        }
        let offset = self.base + self.at as u64;
        let key = self.string()?;
        self.ws();
        if self.b.get(self.at) != Some(&b':') {
            return Err(self.found("':'"));
        }
        self.at += 1;
        Ok(Some((key, offset)))
    }

    fn end(&mut self) -> Step<()> {
        self.ws();
        match self.b.get(self.at) {
            None => Ok(()),
            Some(&c) => Err(self.fail(
                self.at,
                format!(
                    "unexpected {} after the top-level object; only whitespace may follow",
                    show_byte(c)
                ),
            )),
        }
    }
}

/// MessagePack, strictly: maps with `str` keys, `str` strings, no `bin` or `ext`.
pub(crate) struct MsgpackTokens<'a> {
    b: &'a [u8],
    at: usize,
    base: u64,
}

impl<'a> MsgpackTokens<'a> {
    /// Tokens of `bytes`, whose first byte is at file offset `base`.
    pub(crate) fn new(bytes: &'a [u8], base: u64) -> MsgpackTokens<'a> {
        MsgpackTokens {
            b: bytes,
            at: 0,
            base,
        }
    }

    fn fail(&self, at: usize, message: impl Into<String>) -> Fail {
        Fail {
            offset: self.base + at as u64,
            message: message.into(),
        }
    }

    /// The next `n` bytes of the value starting at `start`.
    fn take(&mut self, n: usize, start: usize) -> Step<&'a [u8]> {
        if self.b.len() - self.at < n {
            return Err(self.fail(
                start,
                format!(
                    "the value needs {n} more bytes at byte {}; the payload ends after {}",
                    self.base + self.at as u64,
                    self.b.len() - self.at
                ),
            ));
        }
        let out = &self.b[self.at..self.at + n];
        self.at += n;
        Ok(out)
    }

    fn uint(&mut self, n: usize, start: usize) -> Step<u64> {
        let bytes = self.take(n, start)?;
        Ok(bytes.iter().fold(0u64, |acc, &b| (acc << 8) | u64::from(b)))
    }

    fn count(&mut self, n: usize, per: usize, start: usize, what: &str) -> Step<usize> {
        let count = self.uint(n, start)? as usize;
        let remaining = self.b.len() - self.at;
        if count > remaining / per {
            return Err(self.fail(
                start,
                format!(
                    "{what} declares {count} entries; only {remaining} bytes remain in the payload"
                ),
            ));
        }
        Ok(count)
    }

    fn str_of(&mut self, len: usize, start: usize) -> Step<String> {
        let remaining = self.b.len() - self.at;
        if len > remaining {
            return Err(self.fail(
                start,
                format!("str declares {len} bytes; only {remaining} remain in the payload"),
            ));
        }
        let data_at = self.at;
        let bytes = self.take(len, start)?;
        match std::str::from_utf8(bytes) {
            Ok(s) => Ok(s.to_string()),
            Err(e) => Err(self.fail(data_at + e.valid_up_to(), "invalid UTF-8 in a str")),
        }
    }
}

fn int_num(i: i128) -> Num {
    Num {
        int: Some(i),
        value: i as f64,
        integer: true,
    }
}

impl<'a> Tokens<'a> for MsgpackTokens<'a> {
    fn head(&mut self) -> Step<(Head, u64)> {
        let start = self.at;
        let offset = self.base + start as u64;
        let Some(&m) = self.b.get(self.at) else {
            return Err(self.fail(start, "unexpected end of the payload; expected a value"));
        };
        self.at += 1;
        let head = match m {
            0x00..=0x7f => Head::Num(int_num(i128::from(m))),
            0x80..=0x8f => Head::Object(Some(usize::from(m & 0x0f))),
            0x90..=0x9f => Head::Array(Some(usize::from(m & 0x0f))),
            0xa0..=0xbf => Head::Str(self.str_of(usize::from(m & 0x1f), start)?),
            0xc0 => Head::Null,
            0xc2 => Head::Bool(false),
            0xc3 => Head::Bool(true),
            0xca => {
                let bits = self.uint(4, start)? as u32;
                let value = f64::from(f32::from_bits(bits));
                Head::Num(Num {
                    int: None,
                    value,
                    integer: false,
                })
            }
            0xcb => {
                let value = f64::from_bits(self.uint(8, start)?);
                Head::Num(Num {
                    int: None,
                    value,
                    integer: false,
                })
            }
            0xcc..=0xcf => {
                let n = 1 << (m - 0xcc);
                Head::Num(int_num(i128::from(self.uint(n, start)?)))
            }
            0xd0..=0xd3 => {
                let n = 1usize << (m - 0xd0);
                let raw = self.uint(n, start)?;
                let shift = 64 - 8 * n as u32;
                Head::Num(int_num(i128::from(((raw << shift) as i64) >> shift)))
            }
            0xd9..=0xdb => {
                let n = 1 << (m - 0xd9);
                let len = self.uint(n, start)? as usize;
                Head::Str(self.str_of(len, start)?)
            }
            0xdc | 0xdd => {
                let n = if m == 0xdc { 2 } else { 4 };
                Head::Array(Some(self.count(n, 1, start, "array")?))
            }
            0xde | 0xdf => {
                let n = if m == 0xde { 2 } else { 4 };
                Head::Object(Some(self.count(n, 2, start, "map")?))
            }
            0xe0..=0xff => Head::Num(int_num(i128::from(m as i8))),
            0xc4..=0xc6 => {
                return Err(self.fail(
                    start,
                    format!("bin (0x{m:02x}) is not allowed; strings are str"),
                ))
            }
            0xc7..=0xc9 | 0xd4..=0xd8 => {
                return Err(self.fail(start, format!("ext (0x{m:02x}) is not allowed")))
            }
            0xc1 => return Err(self.fail(start, "0xc1 is not a MessagePack format")),
        };
        Ok((head, offset))
    }

    fn number(&mut self) -> Step<Option<(Num, u64)>> {
        match self.b.get(self.at) {
            Some(0x00..=0x7f | 0xca..=0xd3 | 0xe0..=0xff) => match self.head()? {
                (Head::Num(n), offset) => Ok(Some((n, offset))),
                _ => unreachable!("the formats above are numbers"),
            },
            _ => Ok(None),
        }
    }

    fn next_element(&mut self, seq: &mut Seq) -> Step<bool> {
        let left = seq
            .remaining
            .as_mut()
            .expect("MessagePack arrays are counted");
        if *left == 0 {
            return Ok(false);
        }
        *left -= 1;
        Ok(true)
    }

    fn next_key(&mut self, seq: &mut Seq) -> Step<Option<(Cow<'a, str>, u64)>> {
        if !self.next_element(seq)? {
            return Ok(None);
        }
        match self.head()? {
            (Head::Str(key), offset) => Ok(Some((Cow::Owned(key), offset))),
            (other, offset) => Err(Fail {
                offset,
                message: format!("map keys must be str; found {}", other.describe()),
            }),
        }
    }

    fn end(&mut self) -> Step<()> {
        if self.at < self.b.len() {
            return Err(self.fail(
                self.at,
                format!(
                    "{} bytes follow the MessagePack object",
                    self.b.len() - self.at
                ),
            ));
        }
        Ok(())
    }
}

/// How many keys an object's duplicate check compares one by one before it takes a hash set
/// (hostile files may hold millions of unknown keys in one object).
const FEW_KEYS: usize = 16;

/// One step of a JSON pointer.
#[derive(Clone, Debug)]
pub(crate) enum Seg {
    /// A member name: borrowed for the names of the format (no allocation per record), owned for
    /// keys read from the file.
    Key(std::borrow::Cow<'static, str>),
    Index(usize),
}

/// The member names of the format as static strings, so that tracking the path of a million
/// face records allocates nothing; other keys (extras, extensions) stay owned.
fn intern(key: &str) -> Cow<'static, str> {
    const NAMES: &[&str] = &[
        "face",
        "points",
        "weights",
        "vertex",
        "coefficients",
        "kind",
        "degree",
        "direction",
        "name",
        "faces",
        "vertexMaps",
        "extras",
        "version",
        "dimension",
        "metadata",
        "vertices",
        "simplices",
        "values",
        "level",
        "stages",
        "extensionsUsed",
        "extensionsRequired",
        "extensions",
        "generator",
        "units",
        "description",
    ];
    match NAMES.iter().find(|&&n| n == key) {
        Some(&n) => Cow::Borrowed(n),
        None => Cow::Owned(key.to_string()),
    }
}

/// The RFC 6901 pointer of a path.
pub(crate) fn pointer_of(path: &[Seg]) -> String {
    let mut out = String::new();
    for seg in path {
        out.push('/');
        match seg {
            Seg::Key(k) => out.push_str(&escape_pointer(k)),
            Seg::Index(i) => out.push_str(&i.to_string()),
        }
    }
    out
}

/// The typed decoder: reads a [`Model`] from tokens, tracking the pointer and the nesting depth.
pub(crate) struct Decoder<'a, T> {
    tok: T,
    path: Vec<Seg>,
    /// The first [`FEW_KEYS`] keys of each object being read, outermost first, borrowed from the
    /// payload where they can be: the duplicate check of a million face records allocates nothing.
    keys: Vec<Cow<'a, str>>,
    /// The index of the element being read by [`Decoder::flat_array`]: the last step of the
    /// pointer, after `path`.
    element: Option<usize>,
    depth: usize,
}

impl<'a, T: Tokens<'a>> Decoder<'a, T> {
    pub(crate) fn new(tok: T) -> Decoder<'a, T> {
        Decoder {
            tok,
            path: Vec::new(),
            keys: Vec::new(),
            element: None,
            depth: 0,
        }
    }

    /// A decoder for a value nested at `path`, below `depth` arrays and objects.
    pub(crate) fn nested(tok: T, path: Vec<Seg>, depth: usize) -> Decoder<'a, T> {
        Decoder {
            tok,
            path,
            keys: Vec::new(),
            element: None,
            depth,
        }
    }

    fn at(&self, offset: u64, message: impl Into<String>) -> Error {
        Error::format(
            Rule::Malformed,
            Location {
                pointer: Some(self.pointer()),
                offset: Some(offset),
                ..Location::default()
            },
            message,
        )
    }

    /// The JSON pointer of the value being read.
    fn pointer(&self) -> String {
        let mut out = pointer_of(&self.path);
        if let Some(i) = self.element {
            out.push('/');
            out.push_str(&i.to_string());
        }
        out
    }

    fn err(&self, fail: Fail) -> Error {
        self.at(fail.offset, fail.message)
    }

    fn head(&mut self) -> Result<(Head, u64)> {
        self.tok.head().map_err(|f| self.err(f))
    }

    fn wrong(&self, offset: u64, expected: &str, found: &Head) -> Error {
        self.at(
            offset,
            format!("expected {expected}; found {}", found.describe()),
        )
    }

    fn enter(&mut self, offset: u64) -> Result<()> {
        self.depth += 1;
        if self.depth > MAX_DEPTH {
            return Err(self.at(
                offset,
                format!("arrays and objects nested deeper than {MAX_DEPTH} levels"),
            ));
        }
        Ok(())
    }

    /// Checks that nothing follows the top-level value.
    pub(crate) fn end(&mut self) -> Result<()> {
        self.tok.end().map_err(|f| self.err(f))
    }

    /// Reads an object, calling `member` for each key with the key pushed on the path; returns the
    /// object's offset.
    fn object(
        &mut self,
        what: &str,
        mut member: impl FnMut(&mut Self, &str, u64) -> Result<()>,
    ) -> Result<u64> {
        let (head, offset) = self.head()?;
        let Head::Object(count) = head else {
            return Err(self.wrong(offset, what, &head));
        };
        self.enter(offset)?;
        let mut seq = Seq::new(count);
        // This object's keys: `self.keys[first..]` (nested objects stack theirs above and take
        // them off again), then a hash set once there are more than FEW_KEYS.
        let first = self.keys.len();
        let mut many: Option<HashSet<Cow<'a, str>>> = None;
        loop {
            let next = self.tok.next_key(&mut seq).map_err(|f| self.err(f))?;
            let Some((key, key_offset)) = next else { break };
            let repeated = match &mut many {
                Some(set) => !set.insert(key.clone()),
                None if self.keys[first..].contains(&key) => true,
                None if self.keys.len() - first < FEW_KEYS => {
                    self.keys.push(key.clone());
                    false
                }
                None => {
                    let mut set: HashSet<_> = self.keys.drain(first..).collect();
                    set.insert(key.clone());
                    many = Some(set);
                    false
                }
            };
            self.path.push(Seg::Key(intern(&key)));
            if repeated {
                return Err(self.at(key_offset, format!("member {key:?} given twice")));
            }
            member(self, &key, key_offset)?;
            self.path.pop();
        }
        self.keys.truncate(first);
        self.depth -= 1;
        Ok(offset)
    }

    fn array(&mut self, what: &str, element: impl FnMut(&mut Self) -> Result<()>) -> Result<()> {
        self.array_of::<false>(what, element)
    }

    /// [`Decoder::array`] for elements that are neither arrays nor objects (numbers): the index is
    /// noted in [`Decoder::element`] instead of pushed on the path, which is the same pointer for
    /// an error without a push and a pop per number on the way to success. The arrays of numbers
    /// are read by [`Decoder::number_array`]; this element-by-element walk, what they were read
    /// by before, is kept as the tests' reference.
    #[cfg(test)]
    fn flat_array(
        &mut self,
        what: &str,
        element: impl FnMut(&mut Self) -> Result<()>,
    ) -> Result<()> {
        self.array_of::<true>(what, element)
    }

    /// Opens an array for [`Decoder::array_of`] and [`Decoder::number_array`]: reads its head (an
    /// error naming `what` if it is not an array) and goes one level deeper; the caller walks the
    /// elements with the returned [`Seq`] and then leaves the level (`self.depth -= 1`).
    fn open_array(&mut self, what: &str) -> Result<Seq> {
        let (head, offset) = self.head()?;
        let Head::Array(count) = head else {
            return Err(self.wrong(offset, what, &head));
        };
        self.enter(offset)?;
        Ok(Seq::new(count))
    }

    /// The array walk of [`Decoder::array`] (`FLAT = false`: each index pushed on the path) and
    /// [`Decoder::flat_array`] (`FLAT = true`: noted in [`Decoder::element`]); a const parameter so
    /// each keeps its own loop with no branch per element.
    fn array_of<const FLAT: bool>(
        &mut self,
        what: &str,
        mut element: impl FnMut(&mut Self) -> Result<()>,
    ) -> Result<()> {
        let mut seq = self.open_array(what)?;
        let mut i = 0;
        while self.tok.next_element(&mut seq).map_err(|f| self.err(f))? {
            if FLAT {
                self.element = Some(i);
                element(self)?;
                self.element = None;
            } else {
                self.path.push(Seg::Index(i));
                element(self)?;
                self.path.pop();
            }
            i += 1;
        }
        self.depth -= 1;
        Ok(())
    }

    fn string_at(&mut self) -> Result<(String, u64)> {
        match self.head()? {
            (Head::Str(s), offset) => Ok((s, offset)),
            (other, offset) => Err(self.wrong(offset, "a string", &other)),
        }
    }

    fn string(&mut self) -> Result<String> {
        Ok(self.string_at()?.0)
    }

    fn uint(&mut self, max: u32) -> Result<u32> {
        if let Some(v) = self.tok.quick_uint(max) {
            return Ok(v);
        }
        match self.tok.number().map_err(|f| self.err(f))? {
            Some((n, offset)) => match n.int {
                // `-0` is a sign: refused like any other (spec §7.2).
                Some(i)
                    if n.integer
                        && (0..=i128::from(max)).contains(&i)
                        && !n.value.is_sign_negative() =>
                {
                    Ok(i as u32)
                }
                _ => Err(self.at(
                    offset,
                    format!("expected an integer from 0 to {max}; found the number {n}"),
                )),
            },
            None => {
                let (other, offset) = self.head()?;
                Err(self.wrong(offset, &format!("an integer from 0 to {max}"), &other))
            }
        }
    }

    fn f64(&mut self) -> Result<f64> {
        if let Some(v) = self.tok.quick_f64() {
            return Ok(v);
        }
        match self.tok.number().map_err(|f| self.err(f))? {
            Some((n, _)) => Ok(n.value),
            None => {
                let (other, offset) = self.head()?;
                Err(self.wrong(offset, "a number", &other))
            }
        }
    }

    fn f64s(&mut self) -> Result<Vec<f64>> {
        let mut out = Vec::new();
        self.f64s_into(&mut out)?;
        Ok(out)
    }

    fn u32s(&mut self) -> Result<Vec<u32>> {
        let mut out = Vec::new();
        self.u32s_into(&mut out)?;
        Ok(out)
    }

    /// Appends an array of numbers to `out`.
    fn f64s_into(&mut self, out: &mut Vec<f64>) -> Result<()> {
        self.number_array(
            "an array of numbers",
            out,
            |tok, seq, out| tok.quick_f64_run(seq, out),
            Self::f64,
        )
    }

    /// Appends an array of integers to `out`.
    fn u32s_into(&mut self, out: &mut Vec<u32>) -> Result<()> {
        self.number_array(
            "an array of integers",
            out,
            |tok, seq, out| tok.quick_uint_run(seq, u32::MAX, out),
            |d| d.uint(u32::MAX),
        )
    }

    /// [`Decoder::flat_array`] of numbers appended to `out`: runs of elements taken by `run` (a
    /// tokenizer loop: [`Tokens::quick_f64_run`], [`Tokens::quick_uint_run`]; a call per element
    /// was most of the time of reading a model's arrays), and between them the element `run` does
    /// not take read one by one by `element`, the general reading, with its error. `run` takes
    /// only what `element` would read to the same value and leaves the rest untouched, so the
    /// values, errors and pointers are those of `flat_array` with `element` alone.
    fn number_array<X>(
        &mut self,
        what: &str,
        out: &mut Vec<X>,
        mut run: impl FnMut(&mut T, &mut Seq, &mut Vec<X>) -> usize,
        mut element: impl FnMut(&mut Self) -> Result<X>,
    ) -> Result<()> {
        let mut seq = self.open_array(what)?;
        let mut i = 0;
        loop {
            i += run(&mut self.tok, &mut seq, out);
            if !self.tok.next_element(&mut seq).map_err(|f| self.err(f))? {
                break;
            }
            self.element = Some(i);
            out.push(element(self)?);
            self.element = None;
            i += 1;
        }
        self.depth -= 1;
        Ok(())
    }

    fn strings(&mut self) -> Result<Vec<String>> {
        let mut out = Vec::new();
        self.array("an array of strings", |d| {
            out.push(d.string()?);
            Ok(())
        })?;
        Ok(out)
    }

    /// Reads any value as JSON data (`extras`, extension payloads, unknown members).
    pub(crate) fn json(&mut self) -> Result<serde_json::Value> {
        use serde_json::Value;
        let (head, offset) = self.head()?;
        Ok(match head {
            Head::Null => Value::Null,
            Head::Bool(b) => Value::Bool(b),
            Head::Str(s) => Value::String(s),
            Head::Num(n) if n.integer => match n.int {
                Some(i) if (0..=i128::from(u64::MAX)).contains(&i) => Value::from(i as u64),
                Some(i) if (i128::from(i64::MIN)..0).contains(&i) => Value::from(i as i64),
                _ => {
                    return Err(self.at(
                        offset,
                        format!("the integer {n} is outside -2^63 .. 2^64 - 1, the range of integers in json data"),
                    ))
                }
            },
            Head::Num(n) => match serde_json::Number::from_f64(n.value) {
                Some(x) => Value::Number(x),
                None => {
                    return Err(self.at(
                        offset,
                        format!("{} in json data: JSON holds finite numbers only", n.value),
                    ))
                }
            },
            Head::Array(count) => {
                self.enter(offset)?;
                let mut seq = Seq::new(count);
                let mut out = Vec::new();
                while self.tok.next_element(&mut seq).map_err(|f| self.err(f))? {
                    self.path.push(Seg::Index(out.len()));
                    out.push(self.json()?);
                    self.path.pop();
                }
                self.depth -= 1;
                Value::Array(out)
            }
            Head::Object(count) => {
                self.enter(offset)?;
                let mut seq = Seq::new(count);
                let mut out = serde_json::Map::new();
                loop {
                    let next = self.tok.next_key(&mut seq).map_err(|f| self.err(f))?;
                    let Some((key, key_offset)) = next else { break };
                    self.path.push(Seg::Key(Cow::Owned(key.to_string())));
                    if out.contains_key(&*key) {
                        return Err(self.at(key_offset, format!("member {key:?} given twice")));
                    }
                    let value = self.json()?;
                    out.insert(key.into_owned(), value);
                    self.path.pop();
                }
                self.depth -= 1;
                Value::Object(out)
            }
        })
    }

    fn metadata(&mut self) -> Result<Metadata> {
        let mut m = Metadata::default();
        self.object("an object", |d, key, _| {
            match key {
                "name" => m.name = Some(d.string()?),
                "generator" => m.generator = Some(d.string()?),
                "units" => m.units = Some(d.string()?),
                "description" => m.description = Some(d.string()?),
                _ => {
                    d.json()?;
                }
            }
            Ok(())
        })?;
        Ok(m)
    }

    fn missing(&mut self, offset: u64, members: &[(&str, bool)]) -> Result<()> {
        match members.iter().find(|(_, present)| !present) {
            Some((name, _)) => Err(self.at(offset, format!("missing required member {name:?}"))),
            None => Ok(()),
        }
    }

    /// One face record, appended straight to `table`'s flat arrays (members in any order; the
    /// object's own checks refuse a repeated member).
    fn face_record(&mut self, table: &mut FaceTable) -> Result<()> {
        let mut face = false;
        let (ids, points, weights) = table.parts_mut();
        let offset = self.object("an object (a face record)", |d, key, _| {
            match key {
                "face" => {
                    d.u32s_into(ids)?;
                    face = true;
                }
                "points" => d.f64s_into(points)?,
                "weights" => d.f64s_into(weights)?,
                _ => {
                    d.json()?;
                }
            }
            Ok(())
        })?;
        self.missing(offset, &[("face", face)])?;
        table.close_record().map_err(|full| {
            Error::format(
                Rule::LimitExceeded,
                Location {
                    pointer: Some(self.pointer()),
                    offset: Some(offset),
                    ..Location::default()
                },
                full.to_string(),
            )
        })
    }

    fn vertex_map(&mut self) -> Result<VertexMap> {
        let (mut vertex, mut coefficients) = (None, None);
        let offset = self.object("an object (a vertex map)", |d, key, _| {
            match key {
                "vertex" => vertex = Some(d.uint(u32::MAX)?),
                "coefficients" => coefficients = Some(d.f64s()?),
                _ => {
                    d.json()?;
                }
            }
            Ok(())
        })?;
        self.missing(
            offset,
            &[
                ("vertex", vertex.is_some()),
                ("coefficients", coefficients.is_some()),
            ],
        )?;
        Ok(VertexMap {
            vertex: vertex.unwrap_or_default(),
            coefficients: coefficients.unwrap_or_default(),
        })
    }

    fn stage(&mut self) -> Result<Stage> {
        let mut stage = Stage::identity(StageKind::Bezier, 0);
        let (mut kind, mut degree) = (false, false);
        let offset = self.object("an object (a stage)", |d, key, _| {
            match key {
                "kind" => {
                    let (s, at) = d.string_at()?;
                    stage.kind = match s.as_str() {
                        "bezier" => StageKind::Bezier,
                        "rational" => StageKind::Rational,
                        "monotonic" => StageKind::Monotonic,
                        _ => {
                            return Err(d.at(
                                at,
                                format!(
                                "kind {s:?}; expected \"bezier\", \"rational\" or \"monotonic\""
                            ),
                            ))
                        }
                    };
                    kind = true;
                }
                "degree" => {
                    stage.degree = d.uint(u32::MAX)?;
                    degree = true;
                }
                "direction" => {
                    let (s, at) = d.string_at()?;
                    stage.direction = match s.as_str() {
                        "implicit" => Direction::Implicit,
                        "parametric" => Direction::Parametric,
                        _ => {
                            return Err(d.at(
                                at,
                                format!("direction {s:?}; expected \"implicit\" or \"parametric\""),
                            ))
                        }
                    };
                }
                "name" => stage.name = Some(d.string()?),
                "faces" => {
                    let mut table = FaceTable::new();
                    d.array("an array of face records", |d| d.face_record(&mut table))?;
                    stage.faces = table;
                }
                "vertexMaps" => d.array("an array of vertex maps", |d| {
                    let m = d.vertex_map()?;
                    stage.vertex_maps.push(m);
                    Ok(())
                })?,
                "extras" => stage.extras = JsonValue(d.json()?),
                _ => {
                    d.json()?;
                }
            }
            Ok(())
        })?;
        self.missing(offset, &[("kind", kind), ("degree", degree)])?;
        Ok(stage)
    }

    /// Reads the whole payload: one model object and nothing after it.
    pub(crate) fn model(&mut self) -> Result<Model> {
        let mut m = Model::new(0);
        let (mut version, mut dimension, mut vertices, mut simplices, mut values) =
            (false, false, false, false, false);
        let offset = self.object("an object (the model)", |d, key, _| {
            match key {
                "version" => {
                    m.version = d.string()?;
                    version = true;
                }
                "dimension" => {
                    m.dimension = d.uint(u32::from(u8::MAX))? as u8;
                    dimension = true;
                }
                "metadata" => m.metadata = d.metadata()?,
                "vertices" => {
                    m.vertices = d.f64s()?;
                    vertices = true;
                }
                "simplices" => {
                    m.simplices = d.u32s()?;
                    simplices = true;
                }
                "values" => {
                    m.values = d.f64s()?;
                    values = true;
                }
                "level" => m.level = d.f64()?,
                "stages" => d.array("an array of stages", |d| {
                    let s = d.stage()?;
                    m.stages.push(s);
                    Ok(())
                })?,
                "extensionsUsed" => m.extensions_used = d.strings()?,
                "extensionsRequired" => m.extensions_required = d.strings()?,
                "extensions" => {
                    let mut ext = BTreeMap::new();
                    d.object("an object", |d, key, _| {
                        ext.insert(key.to_string(), JsonValue(d.json()?));
                        Ok(())
                    })?;
                    m.extensions = ext;
                }
                "extras" => m.extras = JsonValue(d.json()?),
                _ => {
                    d.json()?;
                }
            }
            Ok(())
        })?;
        self.missing(
            offset,
            &[
                ("version", version),
                ("dimension", dimension),
                ("vertices", vertices),
                ("simplices", simplices),
                ("values", values),
            ],
        )?;
        self.end()?;
        Ok(m)
    }
}

/// The `version` string of a payload that is well-formed (every rule of spec §7.8 holds) but did
/// not decode as a model; `None` otherwise. Used to report a newer major version as such.
pub(crate) fn probe_version<'a, T: Tokens<'a>>(tok: T) -> Option<String> {
    let mut d = Decoder::new(tok);
    let value = d.json().ok()?;
    d.end().ok()?;
    value.get("version")?.as_str().map(str::to_string)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What reading a number from `text` gives: the value's bits, its integer reading and where
    /// the tokenizer stopped; or the error's offset and message.
    type Outcome = std::result::Result<(u64, Option<i128>, bool, usize), (u64, String)>;

    fn read(text: &[u8], strict: bool) -> Outcome {
        let mut t = JsonTokens::new(text, 0);
        let r = if strict {
            t.strict_number()
        } else {
            t.scan_number()
        };
        match r {
            Ok(n) => Ok((n.value.to_bits(), n.int, n.integer, t.at)),
            Err(f) => Err((f.offset, f.message)),
        }
    }

    /// The whitespace skip (eight spaces per step after a line break) stops where a byte-by-byte
    /// scan stops, from every start in short strings over whitespace and near-whitespace bytes,
    /// and after indentation runs of every length modulo 8.
    #[test]
    fn whitespace_is_skipped_as_a_byte_by_byte_scan_skips_it() {
        // Truth: the byte-by-byte loop over JSON's four whitespace bytes.
        let reference = |b: &[u8], mut at: usize| {
            while matches!(b.get(at), Some(b' ' | b'\t' | b'\n' | b'\r')) {
                at += 1;
            }
            at
        };
        // Every string of up to 6 bytes over whitespace, a value byte and a space-like
        // non-whitespace byte (`!` is 0x21: one bit from a space), then up to 5 spaces, from
        // every start.
        const ALPHABET: &[u8] = b" \n\t\r1!";
        let mut text = Vec::new();
        let mut checked = 0;
        for len in 0..=11u32 {
            let count = ALPHABET.len().pow(len.min(6));
            for mut code in 0..count {
                text.clear();
                for i in 0..len {
                    // Past 6 bytes, runs of spaces: the eight-byte steps and their ends.
                    if i < 6 {
                        text.push(ALPHABET[code % ALPHABET.len()]);
                        code /= ALPHABET.len();
                    } else {
                        text.push(b' ');
                    }
                }
                for start in 0..=text.len() {
                    let mut t = JsonTokens::new(&text, 0);
                    t.at = start;
                    t.ws();
                    assert_eq!(t.at, reference(&text, start), "{text:?} from {start}");
                    checked += 1;
                }
            }
        }
        // Long indentation runs with every following byte and length modulo 8.
        for run in 0..40 {
            for last in [b'1', b'!', b'\t', b'\0', 0xa0] {
                let mut text = b"\n".to_vec();
                text.extend(std::iter::repeat_n(b' ', run));
                text.push(last);
                let mut t = JsonTokens::new(&text, 0);
                t.ws();
                assert_eq!(t.at, reference(&text, 0), "{run} spaces then {last}");
            }
        }
        assert!(checked > 100_000);
    }

    /// The fast reading agrees with the byte-by-byte one (the reader before issue 13's session
    /// 17) on every string of up to 6 bytes over the characters of numbers and two that end them:
    /// same value bits, integer reading and end, or the same error at the same byte.
    #[test]
    fn quick_numbers_agree_with_the_strict_reading() {
        const ALPHABET: &[u8] = b"0159-+.eE]";
        for text in [
            "4294967295",
            "4294967296",
            "04",
            "10000000000",
            "007",
            " 12 ",
        ] {
            quick_reads_agree(text.as_bytes());
        }
        let mut text = Vec::new();
        let mut checked = 0;
        for len in 1..=6u32 {
            for mut code in 0..ALPHABET.len().pow(len) {
                text.clear();
                for _ in 0..len {
                    text.push(ALPHABET[code % ALPHABET.len()]);
                    code /= ALPHABET.len();
                }
                assert_eq!(
                    read(&text, false),
                    read(&text, true),
                    "{:?}",
                    String::from_utf8_lossy(&text)
                );
                quick_reads_agree(&text);
                checked += 1;
            }
        }
        assert_eq!(checked, (1..=6).map(|l| 10usize.pow(l)).sum::<usize>());
    }

    /// `quick_f64` and `quick_uint` read what `number` reads, to the same byte, or leave the
    /// position where it was.
    fn quick_reads_agree(text: &[u8]) {
        let shown = String::from_utf8_lossy(text);
        let after_ws = text
            .iter()
            .position(|c| !b" \t\n\r".contains(c))
            .unwrap_or(text.len());
        let mut general = JsonTokens::new(text, 0);
        let number = general.number().ok().flatten();
        let mut t = JsonTokens::new(text, 0);
        match t.quick_f64() {
            Some(v) => {
                let (n, _) = number.unwrap_or_else(|| panic!("{shown}"));
                assert_eq!(
                    (v.to_bits(), t.at),
                    (n.value.to_bits(), general.at),
                    "{shown}"
                );
            }
            None => assert_eq!(t.at, after_ws, "{shown}"),
        }
        for max in [0, 1, 5, 9, 10, 15, 99, 100, u32::MAX] {
            let mut t = JsonTokens::new(text, 0);
            match t.quick_uint(max) {
                Some(v) => {
                    let (n, _) = number.unwrap_or_else(|| panic!("{shown}"));
                    assert!(n.integer && !n.value.is_sign_negative(), "{shown}");
                    assert_eq!((Some(i128::from(v)), t.at), (n.int, general.at), "{shown}");
                    assert!(v <= max, "{shown}");
                }
                None => {
                    assert_eq!(t.at, after_ws, "{shown}");
                    // Refused only what is not an integer from 0 to max, or a `0` that a digit
                    // follows (which the next token refuses).
                    if let Some((n, _)) = number {
                        let fits = n.integer
                            && !n.value.is_sign_negative()
                            && n.int.is_some_and(|i| (0..=i128::from(max)).contains(&i));
                        let zero_then_digit = text.get(general.at).is_some_and(u8::is_ascii_digit);
                        assert!(!fits || zero_then_digit, "{shown}");
                    }
                }
            }
        }
    }

    /// Tokens that take no runs ([`Tokens::quick_f64_run`] and [`Tokens::quick_uint_run`] are the
    /// defaults): every element of every array read one by one, as before the runs.
    struct OneByOne<'a>(JsonTokens<'a>);

    impl<'a> Tokens<'a> for OneByOne<'a> {
        fn head(&mut self) -> Step<(Head, u64)> {
            self.0.head()
        }
        fn number(&mut self) -> Step<Option<(Num, u64)>> {
            self.0.number()
        }
        fn quick_f64(&mut self) -> Option<f64> {
            self.0.quick_f64()
        }
        fn quick_uint(&mut self, max: u32) -> Option<u32> {
            self.0.quick_uint(max)
        }
        fn next_element(&mut self, seq: &mut Seq) -> Step<bool> {
            self.0.next_element(seq)
        }
        fn next_key(&mut self, seq: &mut Seq) -> Step<Option<(Cow<'a, str>, u64)>> {
            self.0.next_key(seq)
        }
        fn end(&mut self) -> Step<()> {
            self.0.end()
        }
    }

    /// What reading `text` as an array of numbers and as one of integers gives, by the runs
    /// (`Decoder::f64s_into`, `u32s_into`) and element by element (`flat_array` with the general
    /// readings, the route before the runs): values (bits), or the error with its pointer and
    /// offset; and where the tokenizer stopped.
    fn arrays_both_ways(text: &[u8]) -> [(String, usize); 4] {
        let show = |r: Result<String>| r.unwrap_or_else(|e| format!("error {e:?}"));
        let mut d = Decoder::nested(JsonTokens::new(text, 7), vec![Seg::Key("k".into())], 1);
        let mut f = Vec::new();
        let runs_f64 = show(d.f64s_into(&mut f).map(|()| format!("{:?}", bits(&f))));
        let runs_f64_at = d.tok.at;
        let mut d = Decoder::nested(JsonTokens::new(text, 7), vec![Seg::Key("k".into())], 1);
        let mut u = Vec::new();
        let runs_u32 = show(d.u32s_into(&mut u).map(|()| format!("{u:?}")));
        let runs_u32_at = d.tok.at;
        let mut d = Decoder::nested(JsonTokens::new(text, 7), vec![Seg::Key("k".into())], 1);
        let mut f = Vec::new();
        let one_f64 = show(
            d.flat_array("an array of numbers", |d| {
                f.push(d.f64()?);
                Ok(())
            })
            .map(|()| format!("{:?}", bits(&f))),
        );
        let one_f64_at = d.tok.at;
        let mut d = Decoder::nested(JsonTokens::new(text, 7), vec![Seg::Key("k".into())], 1);
        let mut u = Vec::new();
        let one_u32 = show(
            d.flat_array("an array of integers", |d| {
                u.push(d.uint(u32::MAX)?);
                Ok(())
            })
            .map(|()| format!("{u:?}")),
        );
        let one_u32_at = d.tok.at;
        let shown = String::from_utf8_lossy(text);
        assert_eq!(
            (&runs_f64, runs_f64_at),
            (&one_f64, one_f64_at),
            "numbers: {shown}"
        );
        assert_eq!(
            (&runs_u32, runs_u32_at),
            (&one_u32, one_u32_at),
            "integers: {shown}"
        );
        [
            (runs_f64, runs_f64_at),
            (runs_u32, runs_u32_at),
            (one_f64, one_f64_at),
            (one_u32, one_u32_at),
        ]
    }

    fn bits(v: &[f64]) -> Vec<u64> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// The runs read arrays of numbers as the element-by-element walk reads them — the same
    /// values, or the same error at the same byte with the same pointer — on every array of up to
    /// five elements over numbers, integers out of range, other values and broken separators, cut
    /// at every byte; and on texts with a stray byte at every position.
    #[test]
    fn number_runs_read_what_the_element_walk_reads() {
        const ELEMENTS: &[&str] = &[
            "0",
            "7",
            "4294967295",
            "4294967296",
            "-1",
            "-0",
            "0.5",
            "-2.25e-3",
            "1e400",
            "01",
            "1.",
            "\"x\"",
            "[]",
            "null",
        ];
        const SEPARATORS: &[&str] = &[",", " , ", ",\n    ", "", ";"];
        let mut texts = vec![b"[]".to_vec(), b"[ ]".to_vec(), b"{}".to_vec()];
        let mut code = 0usize;
        for len in 1..=5 {
            for _ in 0..60 {
                // A deterministic walk over the combinations (a mixed radix of the code).
                code = code
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let mut c = code >> 11;
                let mut text = String::from("[");
                if c % 3 == 0 {
                    text.push_str("\n  ");
                }
                c /= 3;
                for i in 0..len {
                    if i > 0 {
                        // Mostly good separators, sometimes a broken one.
                        let k = if c % 4 == 0 {
                            c / 4 % SEPARATORS.len()
                        } else {
                            c % 3
                        };
                        text.push_str(SEPARATORS[k]);
                        c /= 16;
                    }
                    // Mostly plain numbers, so runs are long, sometimes anything.
                    let k = if c % 3 == 0 {
                        c / 3 % ELEMENTS.len()
                    } else {
                        c % 8
                    };
                    text.push_str(ELEMENTS[k]);
                    c /= 48;
                }
                text.push_str(if c % 5 == 0 { " ]" } else { "]" });
                texts.push(text.into_bytes());
            }
        }
        let mut checked = 0;
        let mut failed = 0;
        for text in &texts {
            // The whole text, every truncation, and a stray byte at every position.
            let mut variants = vec![text.clone()];
            for cut in 0..text.len() {
                variants.push(text[..cut].to_vec());
                for stray in [b'x', b',', b']', b' '] {
                    let mut t = text.clone();
                    t.insert(cut, stray);
                    variants.push(t);
                }
            }
            for v in &variants {
                let [(runs, _), ..] = arrays_both_ways(v);
                failed += usize::from(runs.starts_with("error"));
                checked += 1;
            }
        }
        // Both outcomes are well represented.
        assert!(checked > 20_000 && failed > checked / 4 && failed < checked * 9 / 10);
    }

    /// Whole models read by the runs are the models read element by element, on every example of
    /// the specification.
    #[test]
    fn example_models_read_as_element_by_element() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../spec/examples");
        let mut read = 0;
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if !path.to_string_lossy().ends_with(".ism.json") {
                continue;
            }
            let bytes = std::fs::read(&path).unwrap();
            let runs = Decoder::new(JsonTokens::new(&bytes, 0)).model().unwrap();
            let one = Decoder::new(OneByOne(JsonTokens::new(&bytes, 0)))
                .model()
                .unwrap();
            // Debug prints every f64 in its shortest round-trip form: equal text, equal bits.
            assert_eq!(
                format!("{runs:?}"),
                format!("{one:?}"),
                "{}",
                path.display()
            );
            assert!(!runs.simplices.is_empty());
            read += 1;
        }
        assert!(read >= 10, "{read} examples");
    }

    /// A small deterministic generator (SplitMix64) for the hostile numbers below.
    struct Mix(u64);

    impl Mix {
        fn next(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }
    }

    /// Checks one number against Rust's `str::parse` (correctly rounded, the peer): the value's
    /// bits when finite (an error otherwise, as JSON holds finite numbers only), the whole text
    /// read, the integer reading of an integer; and against the strict reading.
    fn against_std(text: &str) {
        let outcome = read(text.as_bytes(), false);
        assert_eq!(outcome, read(text.as_bytes(), true), "{text}");
        let peer: f64 = text.parse().expect("a JSON number");
        if !peer.is_finite() {
            assert!(outcome.is_err(), "{text}: {outcome:?}");
            return;
        }
        let (bits, int, integer, end) = outcome.unwrap_or_else(|e| panic!("{text}: {e:?}"));
        assert_eq!(
            bits,
            peer.to_bits(),
            "{text}: {} against {peer:e}",
            f64::from_bits(bits)
        );
        assert_eq!(end, text.len(), "{text}");
        let is_integer = !text.contains(['.', 'e', 'E']);
        assert_eq!(integer, is_integer, "{text}");
        if is_integer {
            assert_eq!(int, text.parse::<i128>().ok(), "{text}");
        }
    }

    /// Hostile numbers read to the same bits as `str::parse`: signed zeros, subnormals and the
    /// edges of the range, 17 significant digits, long mantissas, large exponents, exact halfway
    /// points between neighbouring doubles (ties to even) and the decimals just beside them, and
    /// integers at and beyond 19 digits.
    #[test]
    fn hostile_numbers_round_as_std_does() {
        for text in [
            "0",
            "-0",
            "0.0",
            "-0.0",
            "-0e0",
            "0e-999",
            "-0E+999",
            "1e-400",
            "-1e-400",
            "4.9406564584124654e-324",
            "2.4703282292062327e-324",
            "2.4703282292062328e-324",
            "2.2250738585072011e-308",
            "2.2250738585072014e-308",
            "1.7976931348623157e308",
            "1.7976931348623158e308",
            "1.7976931348623159e308",
            "1e309",
            "-1e309",
            "9007199254740993",
            "-9007199254740993",
            "9007199254740993.0",
            "9999999999999999999",
            "-9999999999999999999",
            "10000000000000000000",
            "18446744073709551615",
            "18446744073709551616",
            "170141183460469231731687303715884105727",
            "170141183460469231731687303715884105728",
            "1e23",
            "8.98846567431158e307",
            "0.1",
            "0.30000000000000004",
            "-0.9642857142857143",
            "0.21476153521305769",
            "123456789012345678901234567890e-30",
        ] {
            against_std(text);
        }
        // Long mantissas: 800 digits, the slow path of every parser.
        against_std(&format!("0.{}1", "0".repeat(800)));
        against_std(&format!("1{}e-800", "0".repeat(800)));
        against_std(&format!("{}.5", "9".repeat(400)));
        let mut mix = Mix(0x1513);
        for _ in 0..20_000 {
            let x = f64::from_bits(mix.next() >> 1);
            if !x.is_finite() {
                continue;
            }
            // The shortest digits, 17 digits, 25 digits, and the exact binary value.
            against_std(&format!("{x:?}"));
            against_std(&format!("-{x:e}"));
            against_std(&format!("{x:.16e}"));
            against_std(&format!("{x:.24e}"));
            against_std(&format!("{x:.800e}"));
            // Subnormals.
            let tiny = f64::from_bits(mix.next() % (1 << 52));
            against_std(&format!("{tiny:e}"));
            against_std(&format!("{tiny:.20e}"));
        }
        // Exactly halfway between the neighbours m·2^k and (m+1)·2^k, and just below and above:
        // (2m+1)·2^(k-1), written exactly as (2m+1)·5^j / 10^j for k - 1 = -j.
        for _ in 0..20_000 {
            let m = (1u128 << 52) | u128::from(mix.next() % (1 << 52));
            let j = (mix.next() % 28) as u32; // (2m+1)·5^j·10 < 2^128
            let digits = ((2 * m + 1) * 5u128.pow(j)).to_string();
            let (int, frac) = digits.split_at(digits.len().saturating_sub(j as usize));
            let frac = format!("{}{frac}", "0".repeat(j as usize - frac.len()));
            let int = if int.is_empty() { "0" } else { int };
            let point = if j == 0 { "" } else { "." };
            against_std(&format!("{int}{point}{frac}"));
            against_std(&format!("{int}.{frac}000000000000000000001"));
            let below = ((2 * m + 1) * 5u128.pow(j) * 10 - 1).to_string();
            let (bi, bf) = below.split_at(below.len() - j as usize - 1);
            against_std(&format!(
                "{}.{bf}9999",
                if bi.is_empty() { "0" } else { bi }
            ));
            // The same points at large and small scales.
            let e = (mix.next() % 600) as i32 - 300;
            against_std(&format!("{int}{point}{frac}e{e}"));
        }
    }
}
