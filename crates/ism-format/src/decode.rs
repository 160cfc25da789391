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

use std::collections::{BTreeMap, HashSet};

use crate::error::{Error, Result};
use crate::faces::FaceTable;
use crate::model::{Direction, JsonValue, Metadata, Model, Stage, StageKind, VertexMap};
use crate::rules::{Location, Rule};
use crate::structure::escape_pointer;

/// The deepest nesting of arrays and objects a file may hold, counting the model object as level 1
/// (spec §7.8). Readers refuse deeper payloads and writers refuse to write them.
pub const MAX_DEPTH: usize = 64;

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

/// A pull tokenizer over one encoding.
pub(crate) trait Tokens {
    /// Reads the head of the next value and returns it with the file offset of its first byte.
    fn head(&mut self) -> Step<(Head, u64)>;
    /// Whether the array has another element (JSON: consumes `,` or `]`).
    fn next_element(&mut self, seq: &mut Seq) -> Step<bool>;
    /// The next key of the object and its offset, or `None` at its end.
    fn next_key(&mut self, seq: &mut Seq) -> Step<Option<(String, u64)>>;
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

    fn ws(&mut self) {
        while let Some(b' ' | b'\t' | b'\n' | b'\r') = self.b.get(self.at) {
            self.at += 1;
        }
    }

    fn string(&mut self) -> Step<String> {
        let start = self.at;
        self.at += 1; // the opening quote
        let mut out = String::new();
        loop {
            let run_start = self.at;
            while let Some(&c) = self.b.get(self.at) {
                if c == b'"' || c == b'\\' || c < 0x20 {
                    break;
                }
                self.at += 1;
            }
            match std::str::from_utf8(&self.b[run_start..self.at]) {
                Ok(s) => out.push_str(s),
                Err(e) => {
                    return Err(self.fail(run_start + e.valid_up_to(), "invalid UTF-8 in a string"))
                }
            }
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
                    return Ok(out);
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
        let start = self.at;
        while self.b.get(self.at).is_some_and(u8::is_ascii_digit) {
            self.at += 1;
        }
        self.at - start
    }

    fn number(&mut self) -> Step<Num> {
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

impl Tokens for JsonTokens<'_> {
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
            Some(b'"') => Head::Str(self.string()?),
            Some(b't') => self.literal(b"true", Head::Bool(true))?,
            Some(b'f') => self.literal(b"false", Head::Bool(false))?,
            Some(b'n') => self.literal(b"null", Head::Null)?,
            Some(b'-' | b'0'..=b'9') => Head::Num(self.number()?),
            _ => return Err(self.found("a value")),
        };
        Ok((head, offset))
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

    fn next_key(&mut self, seq: &mut Seq) -> Step<Option<(String, u64)>> {
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

impl Tokens for MsgpackTokens<'_> {
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

    fn next_key(&mut self, seq: &mut Seq) -> Step<Option<(String, u64)>> {
        if !self.next_element(seq)? {
            return Ok(None);
        }
        match self.head()? {
            (Head::Str(key), offset) => Ok(Some((key, offset))),
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

/// The keys of one object so far: a short list for the few members of the model's objects, a hash
/// set once an object grows (hostile files may hold millions of unknown keys).
#[derive(Default)]
struct SeenKeys {
    few: Vec<String>,
    many: HashSet<String>,
}

impl SeenKeys {
    /// Adds `key`; false when it was there already.
    fn insert(&mut self, key: &str) -> bool {
        if self.many.is_empty() {
            if self.few.iter().any(|k| k == key) {
                return false;
            }
            if self.few.len() < 16 {
                self.few.push(key.to_string());
                return true;
            }
            self.many.extend(self.few.drain(..));
        }
        self.many.insert(key.to_string())
    }
}

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
fn intern(key: String) -> std::borrow::Cow<'static, str> {
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
        Some(&n) => std::borrow::Cow::Borrowed(n),
        None => std::borrow::Cow::Owned(key),
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
pub(crate) struct Decoder<T> {
    tok: T,
    path: Vec<Seg>,
    depth: usize,
}

impl<T: Tokens> Decoder<T> {
    pub(crate) fn new(tok: T) -> Decoder<T> {
        Decoder {
            tok,
            path: Vec::new(),
            depth: 0,
        }
    }

    /// A decoder for a value nested at `path`, below `depth` arrays and objects.
    pub(crate) fn nested(tok: T, path: Vec<Seg>, depth: usize) -> Decoder<T> {
        Decoder { tok, path, depth }
    }

    fn at(&self, offset: u64, message: impl Into<String>) -> Error {
        Error::format(
            Rule::Malformed,
            Location {
                pointer: Some(pointer_of(&self.path)),
                offset: Some(offset),
                ..Location::default()
            },
            message,
        )
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
        let mut seen = SeenKeys::default();
        loop {
            let next = self.tok.next_key(&mut seq).map_err(|f| self.err(f))?;
            let Some((key, key_offset)) = next else { break };
            let repeated = !seen.insert(&key);
            let key = intern(key);
            self.path.push(Seg::Key(key.clone()));
            if repeated {
                return Err(self.at(key_offset, format!("member {key:?} given twice")));
            }
            member(self, &key, key_offset)?;
            self.path.pop();
        }
        self.depth -= 1;
        Ok(offset)
    }

    fn array(
        &mut self,
        what: &str,
        mut element: impl FnMut(&mut Self) -> Result<()>,
    ) -> Result<()> {
        let (head, offset) = self.head()?;
        let Head::Array(count) = head else {
            return Err(self.wrong(offset, what, &head));
        };
        self.enter(offset)?;
        let mut seq = Seq::new(count);
        let mut i = 0;
        while self.tok.next_element(&mut seq).map_err(|f| self.err(f))? {
            self.path.push(Seg::Index(i));
            element(self)?;
            self.path.pop();
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
        match self.head()? {
            (Head::Num(n), offset) => match n.int {
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
            (other, offset) => {
                Err(self.wrong(offset, &format!("an integer from 0 to {max}"), &other))
            }
        }
    }

    fn f64(&mut self) -> Result<f64> {
        match self.head()? {
            (Head::Num(n), _) => Ok(n.value),
            (other, offset) => Err(self.wrong(offset, "a number", &other)),
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
        self.array("an array of numbers", |d| {
            out.push(d.f64()?);
            Ok(())
        })
    }

    /// Appends an array of integers to `out`.
    fn u32s_into(&mut self, out: &mut Vec<u32>) -> Result<()> {
        self.array("an array of integers", |d| {
            out.push(d.uint(u32::MAX)?);
            Ok(())
        })
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
                    self.path.push(Seg::Key(key.clone().into()));
                    if out.contains_key(&key) {
                        return Err(self.at(key_offset, format!("member {key:?} given twice")));
                    }
                    let value = self.json()?;
                    out.insert(key, value);
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
                    pointer: Some(pointer_of(&self.path)),
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
pub(crate) fn probe_version<T: Tokens>(tok: T) -> Option<String> {
    let mut d = Decoder::new(tok);
    let value = d.json().ok()?;
    d.end().ok()?;
    value.get("version")?.as_str().map(str::to_string)
}
