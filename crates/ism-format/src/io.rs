//! Reading and writing the three encodings and the container (spec §7).

use std::io::{Read, Write};
use std::path::Path;

use crate::error::{Error, Result};
use crate::model::{Model, Version, FORMAT_VERSION};
use crate::rules::{Location, Rule, Severity};

/// The eight magic bytes that open a container: `\x89 I S M \r \n \x1a \n` (spec §7.1).
pub const MAGIC: [u8; 8] = [0x89, b'I', b'S', b'M', 0x0D, 0x0A, 0x1A, 0x0A];

/// Container header length in bytes.
pub const HEADER_LEN: usize = 32;

/// How the model is encoded (spec §7.2–7.4).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Encoding {
    /// JSON text (`.ism.json`), usually without a container.
    Json,
    /// MessagePack with named fields (`.ism.msgpack`), in a container.
    MessagePack,
    /// bincode 2 fixed-width little-endian (`.ismb`), in a container.
    Binary,
}

impl Encoding {
    /// Every encoding.
    pub const ALL: [Encoding; 3] = [Encoding::Json, Encoding::MessagePack, Encoding::Binary];

    /// The container's encoding tag.
    pub fn tag(self) -> u8 {
        match self {
            Encoding::Json => 1,
            Encoding::MessagePack => 2,
            Encoding::Binary => 3,
        }
    }

    /// The encoding with this container tag.
    pub fn from_tag(tag: u8) -> Option<Encoding> {
        Encoding::ALL.into_iter().find(|e| e.tag() == tag)
    }

    /// The conventional file extension, without the leading dot.
    pub fn extension(self) -> &'static str {
        match self {
            Encoding::Json => "ism.json",
            Encoding::MessagePack => "ism.msgpack",
            Encoding::Binary => "ismb",
        }
    }

    /// The encoding a file name suggests (only for writing: readers sniff content).
    pub fn from_path(path: &Path) -> Option<Encoding> {
        let name = path.file_name()?.to_str()?.to_ascii_lowercase();
        if name.ends_with(".json") {
            Some(Encoding::Json)
        } else if name.ends_with(".msgpack") || name.ends_with(".mpk") {
            Some(Encoding::MessagePack)
        } else if name.ends_with(".ismb") {
            Some(Encoding::Binary)
        } else {
            None
        }
    }

    /// A display name.
    pub fn name(self) -> &'static str {
        match self {
            Encoding::Json => "json",
            Encoding::MessagePack => "msgpack",
            Encoding::Binary => "binary",
        }
    }
}

impl std::str::FromStr for Encoding {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "json" => Ok(Encoding::Json),
            "msgpack" | "messagepack" => Ok(Encoding::MessagePack),
            "binary" | "bincode" | "ismb" => Ok(Encoding::Binary),
            other => Err(format!(
                "unknown encoding {other:?}; expected json, msgpack or binary"
            )),
        }
    }
}

/// Bounds a reader enforces against hostile input (spec §7.6).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Limits {
    /// Largest payload accepted, in bytes.
    pub max_payload_bytes: u64,
}

impl Default for Limits {
    fn default() -> Self {
        // 8 GiB: several times the largest models in use, well below what one machine can map.
        Limits {
            max_payload_bytes: 8 << 30,
        }
    }
}

/// Options for [`read_with`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ReadOptions {
    /// Resource bounds.
    pub limits: Limits,
    /// Run the structural checks of spec §2–5 after decoding (readers MUST; tools that only copy
    /// bytes may skip it).
    pub check_structure: bool,
    /// Extensions this reader understands (spec §8): a required one not listed is refused.
    pub supported_extensions: &'static [&'static str],
}

impl Default for ReadOptions {
    fn default() -> Self {
        ReadOptions {
            limits: Limits::default(),
            check_structure: true,
            supported_extensions: &[],
        }
    }
}

/// What the container said, for files that have one.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct ContainerInfo {
    /// Version in the header.
    pub major: u16,
    /// Minor version in the header.
    pub minor: u16,
    /// Payload length in bytes.
    pub payload_len: u64,
    /// The payload CRC-32, verified.
    pub crc32: u32,
}

/// A model as read, with how it was stored.
#[derive(Clone, Debug, PartialEq)]
pub struct Document {
    /// The model.
    pub model: Model,
    /// The encoding found by sniffing.
    pub encoding: Encoding,
    /// The container header, when the file had one (JSON usually has none).
    pub container: Option<ContainerInfo>,
    /// Total bytes read.
    pub byte_len: u64,
}

/// Reads a model from bytes, sniffing the encoding, with default options.
///
/// # Errors
/// [`Error::Format`] for container or encoding problems (with byte offset or JSON pointer),
/// [`Error::Structure`] for structural ones.
pub fn from_slice(bytes: &[u8]) -> Result<Document> {
    from_slice_with(bytes, &ReadOptions::default())
}

/// Reads a model from a reader with default options; see [`from_slice`].
///
/// # Errors
/// As [`from_slice`], plus [`Error::Io`].
pub fn read<R: Read>(reader: R) -> Result<Document> {
    read_with(reader, &ReadOptions::default())
}

/// Reads a model from a file; see [`from_slice`].
///
/// # Errors
/// As [`from_slice`], plus [`Error::Io`] naming the path.
pub fn read_path(path: impl AsRef<Path>) -> Result<Document> {
    let path = path.as_ref();
    let file = std::fs::File::open(path).map_err(|e| Error::io(Some(path.to_path_buf()), e))?;
    read_with(std::io::BufReader::new(file), &ReadOptions::default()).map_err(|e| match e {
        Error::Io { path: None, error } => Error::io(Some(path.to_path_buf()), error),
        other => other,
    })
}

/// Reads a model from a reader. Allocates no more than the bytes that actually arrive (bounded by
/// `options.limits`) plus the decoded model.
///
/// # Errors
/// As [`from_slice`], plus [`Error::Io`].
pub fn read_with<R: Read>(reader: R, options: &ReadOptions) -> Result<Document> {
    let mut bytes = Vec::new();
    // `take` bounds the read even for an endless stream; one extra byte detects "too long".
    reader
        .take(
            options
                .limits
                .max_payload_bytes
                .saturating_add(HEADER_LEN as u64 + 1),
        )
        .read_to_end(&mut bytes)
        .map_err(|e| Error::io(None, e))?;
    from_slice_with(&bytes, options)
}

/// Reads a model from bytes with explicit options; see [`from_slice`].
///
/// # Errors
/// As [`from_slice`].
pub fn from_slice_with(bytes: &[u8], options: &ReadOptions) -> Result<Document> {
    let doc = decode(bytes, options)?;
    check_extensions(&doc.model, options)?;
    if options.check_structure {
        let errors: Vec<_> =
            crate::structure::check(&doc.model, crate::structure::DEFAULT_MAX_DIAGNOSTICS)
                .into_iter()
                .filter(|d| d.severity == Severity::Error)
                .collect();
        if !errors.is_empty() {
            return Err(Error::Structure(errors));
        }
    }
    Ok(doc)
}

fn check_extensions(model: &Model, options: &ReadOptions) -> Result<()> {
    for (i, name) in model.extensions_required.iter().enumerate() {
        if !options.supported_extensions.contains(&name.as_str()) {
            return Err(Error::format(
                Rule::ExtensionRequired,
                Location::pointer(format!("/extensionsRequired/{i}")),
                format!("required extension {name:?} is not supported by this reader"),
            ));
        }
    }
    Ok(())
}

/// Parses the container header at the start of `bytes` (which must start with [`MAGIC`]).
///
/// # Errors
/// ISM-004 when shorter than the header, ISM-003 on a header checksum mismatch, ISM-002 for an
/// unsupported major version, ISM-005 for an unknown encoding tag.
pub fn parse_header(bytes: &[u8]) -> Result<(Encoding, ContainerInfo)> {
    if bytes.len() < HEADER_LEN {
        return Err(Error::format(
            Rule::Truncated,
            Location::offset(bytes.len() as u64),
            format!(
                "file ends after {} bytes, inside the {HEADER_LEN}-byte container header",
                bytes.len()
            ),
        ));
    }
    let u16_at = |o: usize| u16::from_le_bytes([bytes[o], bytes[o + 1]]);
    let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
    let stored_header_crc = u32_at(28);
    let header_crc = crc32fast::hash(&bytes[..28]);
    if header_crc != stored_header_crc {
        return Err(Error::format(
            Rule::ChecksumMismatch,
            Location::offset(28),
            format!("header CRC-32 is {header_crc:08x}; header stores {stored_header_crc:08x} (corrupt header)"),
        ));
    }
    let (major, minor) = (u16_at(8), u16_at(10));
    if major != FORMAT_VERSION.major {
        return Err(Error::format(
            Rule::UnsupportedVersion,
            Location::offset(8),
            format!(
                "format version {major}.{minor}; this reader implements major version {}",
                FORMAT_VERSION.major
            ),
        ));
    }
    let encoding = Encoding::from_tag(bytes[12]).ok_or_else(|| {
        Error::format(
            Rule::UnknownEncoding,
            Location::offset(12),
            format!(
                "encoding tag {}; expected 1 (JSON), 2 (MessagePack) or 3 (binary)",
                bytes[12]
            ),
        )
    })?;
    if bytes[13] != 0 || u16_at(14) != 0 {
        return Err(Error::format(
            Rule::Malformed,
            Location::offset(13),
            "reserved header bytes 13–15 must be zero",
        ));
    }
    let payload_len = u64::from_le_bytes(bytes[16..24].try_into().expect("8 bytes"));
    Ok((
        encoding,
        ContainerInfo {
            major,
            minor,
            payload_len,
            crc32: u32_at(24),
        },
    ))
}

fn decode(bytes: &[u8], options: &ReadOptions) -> Result<Document> {
    if bytes.starts_with(&MAGIC) {
        let (encoding, info) = parse_header(bytes)?;
        if info.payload_len > options.limits.max_payload_bytes {
            return Err(Error::format(
                Rule::LimitExceeded,
                Location::offset(16),
                format!(
                    "declared payload of {} bytes exceeds the limit of {}",
                    info.payload_len, options.limits.max_payload_bytes
                ),
            ));
        }
        let available = (bytes.len() - HEADER_LEN) as u64;
        if available < info.payload_len {
            return Err(Error::format(
                Rule::Truncated,
                Location::offset(bytes.len() as u64),
                format!(
                    "payload declares {} bytes; file holds only {available} after the header",
                    info.payload_len
                ),
            ));
        }
        let end = HEADER_LEN + info.payload_len as usize;
        if end < bytes.len() {
            return Err(Error::format(
                Rule::TrailingData,
                Location::offset(end as u64),
                format!("{} bytes follow the declared payload", bytes.len() - end),
            ));
        }
        let payload = &bytes[HEADER_LEN..end];
        let crc = crc32fast::hash(payload);
        if crc != info.crc32 {
            return Err(Error::format(
                Rule::ChecksumMismatch,
                Location::offset(24),
                format!(
                    "payload CRC-32 is {crc:08x}; header stores {:08x} (corrupt payload)",
                    info.crc32
                ),
            ));
        }
        let reader_minor_is_older = info.minor > FORMAT_VERSION.minor;
        let model = match encoding {
            Encoding::Json => decode_json(payload, HEADER_LEN as u64)?,
            Encoding::MessagePack => decode_msgpack(payload, HEADER_LEN as u64)?,
            Encoding::Binary => decode_binary(payload, HEADER_LEN as u64, reader_minor_is_older)?,
        };
        let version = check_version(&model)?;
        if version.major != info.major || version.minor != info.minor {
            return Err(Error::format(
                Rule::VersionMismatch,
                Location::pointer("/version"),
                format!(
                    "payload says version {version}; container header says {}.{}",
                    info.major, info.minor
                ),
            ));
        }
        return Ok(Document {
            model,
            encoding,
            container: Some(info),
            byte_len: bytes.len() as u64,
        });
    }
    let text_start = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    match text_start.iter().find(|b| !b.is_ascii_whitespace()) {
        Some(b'{') => {
            // A UTF-8 byte-order mark is skipped (spec §7.5); offsets still count from the file start.
            let bom = (bytes.len() - text_start.len()) as u64;
            let model = decode_json(text_start, bom)?;
            check_version(&model)?;
            Ok(Document {
                model,
                encoding: Encoding::Json,
                container: None,
                byte_len: bytes.len() as u64,
            })
        }
        _ => Err(Error::format(
            Rule::BadMagic,
            Location::offset(0),
            "neither the ISM container magic \\x89ISM\\r\\n\\x1a\\n nor a JSON object",
        )),
    }
}

fn check_version(model: &Model) -> Result<Version> {
    let version = model.parsed_version().ok_or_else(|| {
        Error::format(
            Rule::Malformed,
            Location::pointer("/version"),
            format!("version {:?} is not \"major.minor\"", model.version),
        )
    })?;
    if version.major != FORMAT_VERSION.major {
        return Err(Error::format(
            Rule::UnsupportedVersion,
            Location::pointer("/version"),
            format!(
                "format version {version}; this reader implements major version {}",
                FORMAT_VERSION.major
            ),
        ));
    }
    Ok(version)
}

/// Peeks at `version` when full decoding failed, so a newer major is reported as such rather than
/// as whatever shape change it brought.
fn probe_version_json(bytes: &[u8]) -> Option<Result<()>> {
    #[derive(serde::Deserialize)]
    struct Probe {
        version: String,
    }
    let probe: Probe = serde_json::from_slice(bytes).ok()?;
    let model_version = Model {
        version: probe.version,
        ..Model::new(0)
    };
    Some(check_version(&model_version).map(|_| ()))
}

fn decode_json(bytes: &[u8], base: u64) -> Result<Model> {
    let de = &mut serde_json::Deserializer::from_slice(bytes);
    match serde_path_to_error::deserialize::<_, Model>(&mut *de) {
        Ok(model) => {
            // Only white space may follow the object (spec §7.2).
            de.end().map_err(|e| {
                let offset = line_column_offset(bytes, e.line(), e.column()).map(|o| o + base);
                Error::format(
                    Rule::Malformed,
                    Location {
                        offset,
                        ..Location::default()
                    },
                    format!("JSON: {e}"),
                )
            })?;
            Ok(model)
        }
        Err(err) => {
            if let Some(Err(version_error)) = probe_version_json(bytes) {
                return Err(version_error);
            }
            let pointer = path_to_pointer(err.path());
            let inner = err.into_inner();
            let offset = line_column_offset(bytes, inner.line(), inner.column()).map(|o| o + base);
            Err(Error::format(
                Rule::Malformed,
                Location {
                    pointer: Some(pointer),
                    offset,
                    ..Location::default()
                },
                format!("JSON: {inner}"),
            ))
        }
    }
}

fn decode_msgpack(bytes: &[u8], base: u64) -> Result<Model> {
    let mut cursor = std::io::Cursor::new(bytes);
    let result = {
        let de = &mut rmp_serde::Deserializer::new(&mut cursor);
        serde_path_to_error::deserialize::<_, Model>(de)
    };
    match result {
        Ok(model) => {
            if (cursor.position() as usize) < bytes.len() {
                return Err(Error::format(
                    Rule::Malformed,
                    Location::offset(base + cursor.position()),
                    "bytes follow the MessagePack document",
                ));
            }
            Ok(model)
        }
        Err(err) => {
            let pointer = path_to_pointer(err.path());
            Err(Error::format(
                Rule::Malformed,
                Location {
                    pointer: Some(pointer),
                    offset: Some(base + cursor.position()),
                    ..Location::default()
                },
                format!("MessagePack: {}", err.into_inner()),
            ))
        }
    }
}

fn path_to_pointer(path: &serde_path_to_error::Path) -> String {
    use serde_path_to_error::Segment;
    let mut out = String::new();
    for seg in path.iter() {
        match seg {
            Segment::Seq { index } => out.push_str(&format!("/{index}")),
            Segment::Map { key } => {
                out.push_str(&format!("/{}", crate::structure::escape_pointer(key)))
            }
            Segment::Enum { variant } => {
                out.push_str(&format!("/{}", crate::structure::escape_pointer(variant)))
            }
            Segment::Unknown => out.push_str("/?"),
        }
    }
    out
}

fn line_column_offset(bytes: &[u8], line: usize, column: usize) -> Option<u64> {
    if line == 0 {
        return None;
    }
    let mut offset = 0usize;
    for _ in 1..line {
        offset += bytes[offset..].iter().position(|&b| b == b'\n')? + 1;
    }
    Some((offset + column.saturating_sub(1)) as u64)
}

/// The bincode configuration of the binary encoding (spec §7.4): little-endian, fixed-width
/// integers, lengths as u64.
pub fn binary_config(
) -> bincode::config::Configuration<bincode::config::LittleEndian, bincode::config::Fixint> {
    bincode::config::standard()
        .with_little_endian()
        .with_fixed_int_encoding()
}

fn decode_binary(bytes: &[u8], base: u64, allow_trailing: bool) -> Result<Model> {
    // bincode trusts declared sequence lengths up to its configured limit; the limit is a type
    // parameter, so pick the smallest power of two ≥ 8 × payload. Decoded Vec<T> memory is at most
    // its encoded size times size_of::<T>() / 4 (u32 is the smallest element the model encodes),
    // so a hostile length cannot allocate more than a small multiple of the input.
    macro_rules! with_limit {
        ($($bits:literal)*) => {{
            let need = (bytes.len() as u64).saturating_mul(8).max(1 << 16);
            let bits = 64 - need.leading_zeros();
            match bits {
                $( b if b <= $bits => bincode::decode_from_slice::<Model, _>(bytes, binary_config().with_limit::<{ 1usize << $bits }>()), )*
                _ => bincode::decode_from_slice::<Model, _>(bytes, binary_config().with_limit::<{ 1usize << 40 }>()),
            }
        }};
    }
    let result = with_limit!(17 20 23 26 29 32 35 38);
    match result {
        Ok((model, used)) => {
            if used < bytes.len() && !allow_trailing {
                return Err(Error::format(
                    Rule::Malformed,
                    Location::offset(base + used as u64),
                    format!("{} bytes follow the binary model", bytes.len() - used),
                ));
            }
            Ok(model)
        }
        Err(e) => {
            let rule = if matches!(e, bincode::error::DecodeError::LimitExceeded) {
                Rule::LimitExceeded
            } else {
                Rule::Malformed
            };
            let at = match &e {
                bincode::error::DecodeError::UnexpectedEnd { .. } => {
                    Some(base + bytes.len() as u64)
                }
                _ => None,
            };
            Err(Error::format(
                rule,
                Location {
                    offset: at,
                    ..Location::default()
                },
                format!("binary: {e}"),
            ))
        }
    }
}

/// Options for writing.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WriteOptions {
    /// Indent JSON output (examples); compact otherwise.
    pub pretty: bool,
    /// Wrap JSON in the container too (checksummed JSON). Ignored for the other encodings, which
    /// are always in a container.
    pub json_in_container: bool,
}

/// Encodes a model's payload (without container).
///
/// # Errors
/// Only if serialization itself fails (e.g. non-finite numbers in JSON).
pub fn encode_payload(model: &Model, encoding: Encoding, pretty: bool) -> Result<Vec<u8>> {
    let fail = |what: &str, e: String| {
        Error::format(Rule::Malformed, Location::default(), format!("{what}: {e}"))
    };
    match encoding {
        Encoding::Json => {
            if let Some(pointer) = first_non_finite(model) {
                return Err(Error::format(
                    Rule::NonFinite,
                    Location::pointer(pointer),
                    "JSON cannot represent NaN or infinity; use the binary or MessagePack encoding",
                ));
            }
            if pretty {
                serde_json::to_vec_pretty(model).map_err(|e| fail("JSON", e.to_string()))
            } else {
                serde_json::to_vec(model).map_err(|e| fail("JSON", e.to_string()))
            }
        }
        Encoding::MessagePack => {
            rmp_serde::to_vec_named(model).map_err(|e| fail("MessagePack", e.to_string()))
        }
        Encoding::Binary => bincode::encode_to_vec(model, binary_config())
            .map_err(|e| fail("binary", e.to_string())),
    }
}

/// JSON pointer of the first NaN or infinity among the model's numbers (JSON would write `null`).
fn first_non_finite(model: &Model) -> Option<String> {
    let find = |xs: &[f64]| xs.iter().position(|x| !x.is_finite());
    if let Some(i) = find(&model.vertices) {
        return Some(format!("/vertices/{i}"));
    }
    if let Some(i) = find(&model.values) {
        return Some(format!("/values/{i}"));
    }
    if !model.level.is_finite() {
        return Some("/level".into());
    }
    for (k, stage) in model.stages.iter().enumerate() {
        for (r, rec) in stage.faces.iter().enumerate() {
            if let Some(i) = find(&rec.points) {
                return Some(format!("/stages/{k}/faces/{r}/points/{i}"));
            }
            if let Some(i) = find(&rec.weights) {
                return Some(format!("/stages/{k}/faces/{r}/weights/{i}"));
            }
        }
        for (r, map) in stage.vertex_maps.iter().enumerate() {
            if let Some(i) = find(&map.coefficients) {
                return Some(format!("/stages/{k}/vertexMaps/{r}/coefficients/{i}"));
            }
        }
    }
    None
}

/// The container header for a payload.
pub fn header(encoding: Encoding, version: Version, payload: &[u8]) -> [u8; HEADER_LEN] {
    let mut h = [0u8; HEADER_LEN];
    h[..8].copy_from_slice(&MAGIC);
    h[8..10].copy_from_slice(&version.major.to_le_bytes());
    h[10..12].copy_from_slice(&version.minor.to_le_bytes());
    h[12] = encoding.tag();
    h[16..24].copy_from_slice(&(payload.len() as u64).to_le_bytes());
    h[24..28].copy_from_slice(&crc32fast::hash(payload).to_le_bytes());
    let hc = crc32fast::hash(&h[..28]);
    h[28..32].copy_from_slice(&hc.to_le_bytes());
    h
}

/// Encodes a whole file in memory.
///
/// # Errors
/// As [`encode_payload`]; also ISM-006 when the model's `version` does not parse.
pub fn to_vec(model: &Model, encoding: Encoding, options: WriteOptions) -> Result<Vec<u8>> {
    let payload = encode_payload(model, encoding, options.pretty)?;
    if encoding == Encoding::Json && !options.json_in_container {
        return Ok(payload);
    }
    let version = model.parsed_version().ok_or_else(|| {
        Error::format(
            Rule::Malformed,
            Location::pointer("/version"),
            format!("version {:?} is not \"major.minor\"", model.version),
        )
    })?;
    let mut out = Vec::with_capacity(HEADER_LEN + payload.len());
    out.extend_from_slice(&header(encoding, version, &payload));
    out.extend_from_slice(&payload);
    Ok(out)
}

/// Writes a whole file to a writer.
///
/// # Errors
/// As [`to_vec`], plus [`Error::Io`].
pub fn write<W: Write>(
    model: &Model,
    encoding: Encoding,
    options: WriteOptions,
    mut writer: W,
) -> Result<()> {
    let bytes = to_vec(model, encoding, options)?;
    writer.write_all(&bytes).map_err(|e| Error::io(None, e))?;
    writer.flush().map_err(|e| Error::io(None, e))
}

/// Writes a file atomically: into a temporary file beside `path`, then renamed over it, so a
/// failure never leaves a partial file. The encoding defaults to the one the extension suggests.
///
/// # Errors
/// As [`to_vec`], plus [`Error::Io`] naming the path.
pub fn write_path(
    model: &Model,
    path: impl AsRef<Path>,
    encoding: Option<Encoding>,
    options: WriteOptions,
) -> Result<()> {
    let path = path.as_ref();
    let encoding = encoding
        .or_else(|| Encoding::from_path(path))
        .unwrap_or(Encoding::Binary);
    let bytes = to_vec(model, encoding, options)?;
    write_atomic(path, |w| w.write_all(&bytes)).map_err(|e| Error::io(Some(path.to_path_buf()), e))
}

/// Runs `fill` on a temporary file beside `path` and renames it over `path` only if `fill` and the
/// flush succeed. Shared by every writer of the workspace.
///
/// # Errors
/// Whatever `fill`, the temporary file or the rename report.
pub fn write_atomic(
    path: &Path,
    fill: impl FnOnce(&mut std::io::BufWriter<&std::fs::File>) -> std::io::Result<()>,
) -> std::io::Result<()> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let tmp = tempfile::Builder::new()
        .prefix(".ism-")
        .suffix(".tmp")
        .tempfile_in(dir)?;
    {
        let mut w = std::io::BufWriter::new(tmp.as_file());
        fill(&mut w)?;
        w.flush()?;
    }
    // Temporary files are created owner-only; give the result the permissions of the file it
    // replaces, or the usual rw-r--r-- for a new file.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(path)
            .map(|m| m.permissions().mode())
            .unwrap_or(0o644);
        tmp.as_file()
            .set_permissions(std::fs::Permissions::from_mode(mode))?;
    }
    // No fsync: the rename already guarantees readers see either the old file or the whole new
    // one if this process dies; durability against power loss is the caller's choice (fsync the
    // result) and costs seconds on large models.
    tmp.persist(path).map_err(|e| e.error)?;
    Ok(())
}
