//! Reading and writing the six encodings and the container (spec §7).

use std::io::{Read, Write};
use std::path::Path;

use crate::decode::MAX_DEPTH;
use crate::error::{Error, Result};
use crate::model::{JsonValue, Model, Version, FORMAT_VERSION};
use crate::refine::KuhnRefinement;
use crate::rules::{Location, Rule, Severity};

/// The eight magic bytes that open a container: `\x89 I S M \r \n \x1a \n` (spec §7.1).
pub const MAGIC: [u8; 8] = [0x89, b'I', b'S', b'M', 0x0D, 0x0A, 0x1A, 0x0A];

/// Container header length in bytes.
pub const HEADER_LEN: usize = 32;

/// How the model is encoded (spec §7.2–7.4.3).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Encoding {
    /// JSON text (`.ism.json`), usually without a container.
    Json,
    /// MessagePack with named fields (`.ism.msgpack`), in a container.
    MessagePack,
    /// bincode 2 fixed-width little-endian (`.ismb`), in a container.
    Binary,
    /// Compact binary (`.ismc`): the binary encoding's grammar with every integer wider than a
    /// byte written as bincode 2's variable-length integer (spec §7.4.1), in a container. The
    /// smallest encoding: a length or an id below 251 takes one byte.
    Compact,
    /// Compressed (`.ismz`): the compact payload compressed as one xz stream after its
    /// uncompressed length (spec §7.4.2), in a container. The smallest file; a second
    /// implementation needs only an xz decoder (Python: the standard `lzma` module).
    Compressed,
    /// Structured (`.isms`): the compact grammar with a stage's face records given by masks over
    /// the complex's faces and control points on a `2^(−8w)` lattice when they lie on one (spec
    /// §7.4.3), in a container. The smallest uncompressed encoding.
    Structured,
}

impl Encoding {
    /// Every encoding.
    pub const ALL: [Encoding; 6] = [
        Encoding::Json,
        Encoding::MessagePack,
        Encoding::Binary,
        Encoding::Compact,
        Encoding::Compressed,
        Encoding::Structured,
    ];

    /// The container's encoding tag.
    pub fn tag(self) -> u8 {
        match self {
            Encoding::Json => 1,
            Encoding::MessagePack => 2,
            Encoding::Binary => 3,
            Encoding::Compact => 4,
            Encoding::Compressed => 5,
            Encoding::Structured => 6,
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
            Encoding::Compact => "ismc",
            Encoding::Compressed => "ismz",
            Encoding::Structured => "isms",
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
        } else if name.ends_with(".ismc") {
            Some(Encoding::Compact)
        } else if name.ends_with(".ismz") {
            Some(Encoding::Compressed)
        } else if name.ends_with(".isms") {
            Some(Encoding::Structured)
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
            Encoding::Compact => "compact",
            Encoding::Compressed => "compressed",
            Encoding::Structured => "structured",
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
            "compact" | "ismc" => Ok(Encoding::Compact),
            "compressed" | "ismz" | "xz" => Ok(Encoding::Compressed),
            "structured" | "isms" => Ok(Encoding::Structured),
            other => Err(format!(
                "unknown encoding {other:?}; expected json, msgpack, binary, compact, compressed or structured"
            )),
        }
    }
}

/// Bounds a reader enforces against hostile input (spec §7.6).
///
/// The payload limit bounds memory: it is checked before anything is read past the header, and
/// every decoder allocates only for elements the bytes at hand can hold (a streamed binary payload
/// may reserve address space for the large arrays its declared length can hold, see
/// [`read_with`]; pages are written only as bytes arrive). The entity limits bound
/// the *work* after decoding (structural check, indexing, validation, export): they are checked
/// right after decoding, before any of it, and a count above one is ISM-007 at the member's
/// pointer. The defaults of the entity limits refuse nothing a readable file can hold (ids are
/// `u32`; 8 GiB of payload holds fewer than 2³² vertices or simplices); a service that accepts
/// files from anyone lowers them. Nesting depth is fixed by the format (§7.8, [`MAX_DEPTH`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Limits {
    /// Largest payload accepted, in bytes.
    pub max_payload_bytes: u64,
    /// Most vertices accepted.
    pub max_vertices: u64,
    /// Most top simplices accepted.
    pub max_simplices: u64,
    /// Most stages accepted.
    pub max_stages: u64,
    /// Most records accepted over all stages: face records of Bézier and rational stages plus
    /// vertex maps of monotonic ones.
    pub max_records: u64,
}

impl Default for Limits {
    fn default() -> Self {
        // 8 GiB: several times the largest models in use, well below what one machine can map.
        Limits {
            max_payload_bytes: 8 << 30,
            max_vertices: u64::from(u32::MAX),
            max_simplices: u64::from(u32::MAX),
            max_stages: u64::MAX,
            max_records: u64::MAX,
        }
    }
}

impl Limits {
    /// ISM-007 for the first entity count of `model` above its limit, at the member's pointer
    /// (`/vertices`, `/simplices`, `/stages`, or the stage whose records pass the limit).
    ///
    /// # Errors
    /// [`Error::Format`] with [`Rule::LimitExceeded`].
    pub fn check(&self, model: &Model) -> Result<()> {
        // `what` names the member, the count and the limit's field (`max_{what}`).
        let over = |pointer: String, what: &str, count: u64, limit: u64| {
            Err(Error::format(
                Rule::LimitExceeded,
                Location::pointer(pointer),
                format!("{count} {what}; this reader accepts at most {limit} (Limits::max_{what})"),
            ))
        };
        for (what, count, limit) in [
            ("vertices", model.num_vertices(), self.max_vertices),
            ("simplices", model.num_simplices(), self.max_simplices),
            ("stages", model.stages.len(), self.max_stages),
        ] {
            if count as u64 > limit {
                return over(format!("/{what}"), what, count as u64, limit);
            }
        }
        // Records over all stages: the stage where the running total passes the limit is named.
        let mut records = 0u64;
        for (k, stage) in model.stages.iter().enumerate() {
            records += (stage.faces.len() + stage.vertex_maps.len()) as u64;
            if records > self.max_records {
                return over(format!("/stages/{k}"), "records", records, self.max_records);
            }
        }
        Ok(())
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
    /// Keep the face records' control points and weights (the default). Off, a binary file read
    /// by [`read_path_with`] keeps every record's face ids and lengths but not its numbers (what a
    /// summary such as `ism info` needs, without the memory): every check still runs and reports
    /// what it would (the numbers are tested finite as they are decoded; a file with a non-finite
    /// one is read again keeping them, so its errors are exactly a full read's). Such a model's
    /// tables answer [`crate::FaceTable::numbers_kept`] false, and writing or indexing it is
    /// [`Error::NumbersNotKept`]. Other encodings, and [`read_with`] / [`from_slice_with`] (which
    /// cannot read their bytes twice), keep the numbers.
    pub keep_record_numbers: bool,
}

impl Default for ReadOptions {
    fn default() -> Self {
        ReadOptions {
            limits: Limits::default(),
            check_structure: true,
            supported_extensions: &[],
            keep_record_numbers: true,
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
    read_path_with(path, &ReadOptions::default())
}

/// Reads a model from a file with explicit options; see [`read_with`].
///
/// # Errors
/// As [`from_slice`], plus [`Error::Io`] naming the path.
pub fn read_path_with(path: impl AsRef<Path>, options: &ReadOptions) -> Result<Document> {
    let path = path.as_ref();
    let read = |keep: bool| {
        let file = std::fs::File::open(path).map_err(|e| Error::io(Some(path.to_path_buf()), e))?;
        // No BufReader: `read_with` streams binary payloads through its own window. The file's
        // length sizes the buffer of an encoding read whole (a hint only: the read still stops
        // at the limit, and a file that changed length is read as it is).
        let len = file.metadata().map(|m| m.len()).unwrap_or(0);
        read_sized(file, options, keep, len).map_err(|e| match e {
            Error::Io { path: None, error } => Error::io(Some(path.to_path_buf()), error),
            other => other,
        })
    };
    match read(options.keep_record_numbers)? {
        Some(doc) => Ok(doc),
        // A non-finite number in a table that did not keep its numbers: read again keeping them,
        // for the structural check to name it.
        None => read(true)?.ok_or_else(|| unreachable_reread(path)),
    }
}

/// A read keeping every number always returns a document or an error; this stands in for the
/// impossible third case instead of a panic.
fn unreachable_reread(path: &Path) -> Error {
    Error::io(
        Some(path.to_path_buf()),
        std::io::Error::other("a read keeping every number asked to be read again"),
    )
}

/// Reads a model from a reader. Uses no more memory than the bytes that actually arrive (bounded
/// by `options.limits`) plus the decoded model: a binary payload's large arrays (vertices,
/// simplices, values, a stage's face records) are reserved once at the length they declare, when
/// the declared payload can hold it, so they never grow by copying; reserved pages are touched
/// only as bytes arrive, and a reservation the allocator refuses is skipped.
///
/// A binary file is decoded as it streams in (its checksum computed on the way), so its bytes are
/// never held in memory all at once; the other encodings are read whole first. Either way the
/// errors are those of [`from_slice_with`] on the same bytes, in the same order.
///
/// # Errors
/// As [`from_slice`], plus [`Error::Io`].
pub fn read_with<R: Read>(reader: R, options: &ReadOptions) -> Result<Document> {
    read_keeping(reader, options, true)?.ok_or_else(|| {
        Error::io(
            None,
            std::io::Error::other("a read keeping every number asked to be read again"),
        )
    })
}

/// [`read_with`], a binary payload's face records keeping their numbers or not (`keep`); `None`
/// when they were not kept and one was not finite (the caller reads the bytes again keeping them,
/// so that the structural check can name it; nothing else was checked yet, so the errors a full
/// read reports first, container and encoding, were already reported).
fn read_keeping<R: Read>(reader: R, options: &ReadOptions, keep: bool) -> Result<Option<Document>> {
    read_sized(reader, options, keep, 0)
}

/// [`read_keeping`] of a source expected to hold `len` bytes (0: unknown): an encoding that is
/// read whole (JSON, MessagePack, compressed) gets a buffer of that size up front, bounded by the
/// limit, instead of one grown by doubling and copying (~2 % of a small JSON model's export, most
/// of it in fresh pages faulted in for each copy).
fn read_sized<R: Read>(
    reader: R,
    options: &ReadOptions,
    keep: bool,
    len: u64,
) -> Result<Option<Document>> {
    // `take` bounds the read even for an endless stream; one extra byte detects "too long".
    let cap = options
        .limits
        .max_payload_bytes
        .saturating_add(HEADER_LEN as u64 + 1);
    let mut reader = reader.take(cap);
    let mut head = Vec::with_capacity(HEADER_LEN);
    (&mut reader)
        .take(HEADER_LEN as u64)
        .read_to_end(&mut head)
        .map_err(|e| Error::io(None, e))?;
    if let Some((info, encoding)) = streamable(&head, options) {
        let doc = read_binary_stream(&mut reader, info, encoding, cap, keep)?;
        debug_assert_eq!(doc.encoding, encoding);
        let finite = doc
            .model
            .stages
            .iter()
            .all(|s| s.faces.elided_finite().unwrap_or(true));
        if !finite {
            return Ok(None);
        }
        return finish_read(doc, options).map(Some);
    }
    let mut bytes = head;
    // At most the limit plus the one byte that detects "too long" (`cap`); a refused reservation
    // only leaves the buffer to grow as it would have.
    let expected = usize::try_from(len.min(cap)).unwrap_or(0);
    let _ = bytes.try_reserve_exact(expected.saturating_sub(bytes.len()));
    reader
        .read_to_end(&mut bytes)
        .map_err(|e| Error::io(None, e))?;
    from_slice_with(&bytes, options).map(Some)
}

/// The container header of a binary file that can be streamed: one whose header is whole and valid
/// and whose payload is within the limit (every other case takes the in-memory path, which reports
/// the error).
fn streamable(head: &[u8], options: &ReadOptions) -> Option<(ContainerInfo, Encoding)> {
    if head.len() < HEADER_LEN || !head.starts_with(&MAGIC) {
        return None;
    }
    let (encoding, info) = parse_header(head).ok()?;
    (matches!(encoding, Encoding::Binary | Encoding::Compact)
        && info.payload_len <= options.limits.max_payload_bytes)
        .then_some((info, encoding))
}

/// Decodes a binary or compact payload as it streams from `reader` (positioned after the header), then reports
/// exactly what [`decode`] would for the same bytes: a short file, trailing bytes or a checksum
/// mismatch before any decoding error.
fn read_binary_stream(
    reader: &mut dyn Read,
    info: ContainerInfo,
    encoding: Encoding,
    cap: u64,
    keep_numbers: bool,
) -> Result<Document> {
    use crate::binary::BinaryDecoder;
    let mut stream = crate::binary::Stream::new(reader, info.payload_len);
    let reader_minor_is_older = info.minor > FORMAT_VERSION.minor;
    let decoded = if encoding == Encoding::Compact {
        BinaryDecoder::<true>::stream(&mut stream, HEADER_LEN as u64)
            .keep_numbers(keep_numbers)
            .model(reader_minor_is_older)
    } else {
        BinaryDecoder::<false>::stream(&mut stream, HEADER_LEN as u64)
            .keep_numbers(keep_numbers)
            .model(reader_minor_is_older)
    };
    // The bytes `read_with` would have held: at most `cap`, the header included.
    let trailing_cap = cap.saturating_sub(HEADER_LEN as u64 + info.payload_len);
    let end = stream.finish(trailing_cap);
    if let Some(e) = end.error {
        return Err(Error::io(None, e));
    }
    let file_len = HEADER_LEN as u64 + end.available + end.trailing;
    if end.available < info.payload_len {
        return Err(Error::format(
            Rule::Truncated,
            Location::offset(file_len),
            format!(
                "payload declares {} bytes; file holds only {} after the header",
                info.payload_len, end.available
            ),
        ));
    }
    if end.trailing > 0 {
        return Err(Error::format(
            Rule::TrailingData,
            Location::offset(HEADER_LEN as u64 + info.payload_len),
            format!("{} bytes follow the declared payload", end.trailing),
        ));
    }
    if end.crc != info.crc32 {
        return Err(Error::format(
            Rule::ChecksumMismatch,
            Location::offset(24),
            format!(
                "payload CRC-32 is {:08x}; header stores {:08x} (corrupt payload)",
                end.crc, info.crc32
            ),
        ));
    }
    container_document(decoded?, encoding, info, file_len)
}

/// Reads a model from bytes with explicit options; see [`from_slice`].
///
/// # Errors
/// As [`from_slice`].
pub fn from_slice_with(bytes: &[u8], options: &ReadOptions) -> Result<Document> {
    finish_read(decode(bytes, options)?, options)
}

/// The checks after decoding: the entity limits, required extensions, then (unless skipped) the
/// structural rules.
fn finish_read(doc: Document, options: &ReadOptions) -> Result<Document> {
    options.limits.check(&doc.model)?;
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

/// A checked, indexed model as read, with how it was stored.
#[derive(Clone, Debug)]
pub struct IndexedDocument {
    /// The model with its topology and flat stage tables.
    pub model: crate::IndexedModel,
    /// The encoding found by sniffing.
    pub encoding: Encoding,
    /// The container header, when the file had one.
    pub container: Option<ContainerInfo>,
    /// Total bytes read.
    pub byte_len: u64,
}

/// Reads bytes and indexes the model: the structural check runs once and its topology is kept
/// (`options.check_structure` is ignored: an indexed model is always checked).
///
/// # Errors
/// As [`from_slice`].
pub fn from_slice_indexed(bytes: &[u8], options: &ReadOptions) -> Result<IndexedDocument> {
    let unchecked = ReadOptions {
        check_structure: false,
        ..*options
    };
    let doc = from_slice_with(bytes, &unchecked)?;
    Ok(IndexedDocument {
        model: crate::IndexedModel::new(doc.model)?,
        encoding: doc.encoding,
        container: doc.container,
        byte_len: doc.byte_len,
    })
}

/// Reads a file and indexes the model; see [`from_slice_indexed`].
///
/// # Errors
/// As [`from_slice`], plus [`Error::Io`] naming the path.
pub fn read_path_indexed(path: impl AsRef<Path>) -> Result<IndexedDocument> {
    read_path_indexed_with(path, &ReadOptions::default())
}

/// Reads a file within `options` (its limits and extensions; `check_structure` is ignored: an
/// indexed model is always checked) and indexes the model; see [`from_slice_indexed`].
///
/// # Errors
/// As [`from_slice_with`], plus [`Error::Io`] naming the path.
pub fn read_path_indexed_with(
    path: impl AsRef<Path>,
    options: &ReadOptions,
) -> Result<IndexedDocument> {
    read_path_indexed_by(path, options, crate::IndexedModel::new)
}

/// [`read_path_indexed_with`] for a caller that looks up few face records or none (`ism export`:
/// the crossed simplices' records, through [`crate::IndexedModel::simplex_records`]): the same
/// structural check and errors, but only the vertex incidence is kept and the face tables are built
/// on first use ([`crate::IndexedModel::new_lazy_or_model`]).
///
/// # Errors
/// As [`read_path_indexed_with`].
pub fn read_path_indexed_lazily_with(
    path: impl AsRef<Path>,
    options: &ReadOptions,
) -> Result<IndexedDocument> {
    read_path_indexed_by(path, options, |model| {
        crate::IndexedModel::new_lazy_or_model(model).map_err(|(_, e)| e)
    })
}

/// Reads a file within `options` without the reader's own structural check (`index` makes it:
/// indexing checks the structure) and indexes the model with `index`: the one body of
/// [`read_path_indexed_with`] and [`read_path_indexed_lazily_with`].
fn read_path_indexed_by(
    path: impl AsRef<Path>,
    options: &ReadOptions,
    index: impl FnOnce(Model) -> Result<crate::IndexedModel>,
) -> Result<IndexedDocument> {
    let unchecked = ReadOptions {
        check_structure: false,
        ..*options
    };
    let doc = read_path_with(path, &unchecked)?;
    Ok(IndexedDocument {
        model: index(doc.model)?,
        encoding: doc.encoding,
        container: doc.container,
        byte_len: doc.byte_len,
    })
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
                "encoding tag {}; expected 1 (JSON), 2 (MessagePack), 3 (binary), 4 (compact), 5 (compressed) or 6 (structured)",
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
            Encoding::Binary => {
                decode_binary::<false>(payload, HEADER_LEN as u64, reader_minor_is_older)?
            }
            Encoding::Compact => {
                decode_binary::<true>(payload, HEADER_LEN as u64, reader_minor_is_older)?
            }
            Encoding::Compressed => crate::compressed::decode(
                payload,
                HEADER_LEN as u64,
                options.limits.max_payload_bytes,
                reader_minor_is_older,
            )?,
            Encoding::Structured => {
                crate::structured::decode(payload, HEADER_LEN as u64, reader_minor_is_older)?
            }
        };
        return container_document(model, encoding, info, bytes.len() as u64);
    }
    // Detection (spec §7.5): JSON whitespace only (RFC 8259: space, tab, LF, CR), no byte-order mark.
    match bytes
        .iter()
        .find(|b| !matches!(b, b' ' | b'\t' | b'\n' | b'\r'))
    {
        Some(b'{') => {
            // A JSON text without a container is all payload. `read_with` holds at most the limit
            // plus a header and one byte, so a longer text arrives cut short: refusing it here by
            // its length gives the stream and the slice the same error (not a parse error at the
            // cut).
            let limit = options.limits.max_payload_bytes;
            if bytes.len() as u64 > limit {
                return Err(Error::format(
                    Rule::LimitExceeded,
                    Location::offset(limit),
                    format!("the JSON text is longer than the payload limit of {limit} bytes"),
                ));
            }
            let model = decode_json(bytes, 0)?;
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

/// A decoded container payload: its version must be one this reader reads and the header's.
fn container_document(
    model: Model,
    encoding: Encoding,
    info: ContainerInfo,
    byte_len: u64,
) -> Result<Document> {
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
    Ok(Document {
        model,
        encoding,
        container: Some(info),
        byte_len,
    })
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

/// After a payload failed to decode: when it is nonetheless well-formed (spec §7.8) and names a
/// version of another major, that is the error to report (spec §8.1), not the shape change it brought.
fn version_first(error: Error, probed: Option<String>) -> Error {
    if let Some(version) = probed {
        let model_version = Model {
            version,
            ..Model::new(0)
        };
        if let Err(e @ Error::Format(_)) = check_version(&model_version) {
            if e.rule() == Some(Rule::UnsupportedVersion) {
                return e;
            }
        }
    }
    error
}

fn decode_json(bytes: &[u8], base: u64) -> Result<Model> {
    crate::decode::Decoder::new(crate::decode::JsonTokens::new(bytes, base))
        .model()
        .map_err(|e| {
            version_first(
                e,
                crate::decode::probe_version(crate::decode::JsonTokens::new(bytes, base)),
            )
        })
}

fn decode_msgpack(bytes: &[u8], base: u64) -> Result<Model> {
    crate::decode::Decoder::new(crate::decode::MsgpackTokens::new(bytes, base))
        .model()
        .map_err(|e| {
            version_first(
                e,
                crate::decode::probe_version(crate::decode::MsgpackTokens::new(bytes, base)),
            )
        })
}

/// The bincode configuration that writes the binary encoding (spec §7.4): little-endian,
/// fixed-width integers, lengths as u64.
pub fn binary_config(
) -> bincode::config::Configuration<bincode::config::LittleEndian, bincode::config::Fixint> {
    bincode::config::standard()
        .with_little_endian()
        .with_fixed_int_encoding()
}

/// The bincode configuration that writes the compact encoding (spec §7.4.1): little-endian, integers
/// as bincode's variable-length integers (its standard configuration, so a second implementation can
/// use bincode's defaults directly).
pub fn compact_config(
) -> bincode::config::Configuration<bincode::config::LittleEndian, bincode::config::Varint> {
    bincode::config::standard().with_little_endian()
}

/// Decodes a binary (`VARINT` false) or compact (`VARINT` true) payload.
fn decode_binary<const VARINT: bool>(
    bytes: &[u8],
    base: u64,
    allow_trailing: bool,
) -> Result<Model> {
    crate::binary::BinaryDecoder::<VARINT>::new(bytes, base).model(allow_trailing)
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

/// Encodes a model's payload (without container) in the canonical form of spec §7.7.
///
/// The writer refuses what a reader refuses (spec §7.7): a non-finite number (with the rule a reader
/// reports for it), `extras` or extension data nested deeper than [`MAX_DEPTH`] (ISM-006). It
/// always writes its own format version, [`FORMAT_VERSION`] (spec §8.1).
///
/// # Errors
/// The first such problem, with its JSON pointer.
pub fn encode_payload(model: &Model, encoding: Encoding, pretty: bool) -> Result<Vec<u8>> {
    check_writable(model)?;
    let mut out = Vec::new();
    encode_into(&own_version(model), encoding, pretty, &mut out)?;
    Ok(out)
}

/// The model as this writer writes it: with its own version.
fn own_version(model: &Model) -> std::borrow::Cow<'_, Model> {
    let own = FORMAT_VERSION.to_string();
    if model.version == own {
        std::borrow::Cow::Borrowed(model)
    } else {
        std::borrow::Cow::Owned(Model {
            version: own,
            ..model.clone()
        })
    }
}

/// A writer that remembers the first I/O error it passed on, so that an encoder's error can be
/// told apart from the writer's (the encoders wrap both in their own types).
struct Tracked<W> {
    inner: W,
    error: Option<std::io::Error>,
}

impl<W: Write> Write for Tracked<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.inner.write(buf).inspect_err(|e| self.remember(e))
    }
    fn write_all(&mut self, buf: &[u8]) -> std::io::Result<()> {
        self.inner.write_all(buf).inspect_err(|e| self.remember(e))
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush().inspect_err(|e| self.remember(e))
    }
}

impl<W> Tracked<W> {
    fn remember(&mut self, e: &std::io::Error) {
        if self.error.is_none() {
            self.error = Some(std::io::Error::new(e.kind(), e.to_string()));
        }
    }
}

/// Encodes the payload into `out` as the model stands (no checks but JSON's refusal of non-finite
/// numbers), streaming: nothing but the encoder's own small buffers is allocated.
fn encode_into<W: Write>(model: &Model, encoding: Encoding, pretty: bool, out: W) -> Result<()> {
    Error::unless_numbers_kept(model, "write")?;
    let fail = |what: &str, e: String| {
        Error::format(Rule::Malformed, Location::default(), format!("{what}: {e}"))
    };
    let mut w = Tracked {
        inner: out,
        error: None,
    };
    let result = match encoding {
        Encoding::Json => {
            // serde_json would write NaN and infinity as `null`.
            if let Some((_, location)) = first_non_finite(model) {
                return Err(Error::format(
                    Rule::NonFinite,
                    location,
                    "JSON cannot represent NaN or infinity; use the binary or MessagePack encoding",
                ));
            }
            crate::canonical::to_json_writer(model, pretty, &mut w)
                .map_err(|e| fail("JSON", e.to_string()))
        }
        Encoding::MessagePack => rmp_serde::encode::write_named(&mut w, model)
            .map_err(|e| fail("MessagePack", e.to_string())),
        Encoding::Binary => bincode::encode_into_std_write(model, &mut w, binary_config())
            .map(drop)
            .map_err(|e| fail("binary", e.to_string())),
        Encoding::Compact => bincode::encode_into_std_write(model, &mut w, compact_config())
            .map(drop)
            .map_err(|e| fail("compact", e.to_string())),
        Encoding::Compressed => {
            crate::compressed::encode(model, &mut w).map_err(|e| fail("compressed", e.to_string()))
        }
        Encoding::Structured => crate::structured::encode(model).and_then(|payload| {
            w.write_all(&payload)
                .map_err(|e| fail("structured", e.to_string()))
        }),
    };
    match (result, w.error) {
        (Ok(()), _) => Ok(()),
        (Err(_), Some(io)) => Err(Error::io(None, io)),
        (Err(e), None) => Err(e),
    }
}

/// Checks that a model can be written as a file readers accept at the encoding level: every
/// number finite, `json` data at most [`MAX_DEPTH`] deep (spec §7.7, §7.8).
///
/// # Errors
/// The first problem, with the rule and location a reader would report.
pub fn check_writable(model: &Model) -> Result<()> {
    Error::unless_numbers_kept(model, "write")?;
    if let Some((rule, location)) = first_non_finite(model) {
        return Err(Error::format(
            rule,
            location,
            "NaN or infinity: readers refuse non-finite numbers, so writers do too",
        ));
    }
    let deep = |value: &JsonValue, above: usize, pointer: String| {
        let mut pointer = pointer;
        too_deep(&value.0, above, &mut pointer).then(|| {
            Error::format(
                Rule::Malformed,
                Location::pointer(pointer),
                format!("arrays and objects nested deeper than {MAX_DEPTH} levels; readers refuse them, so writers do too"),
            )
        })
    };
    // Containers above each json member: the model (1), `extensions` (2), `stages` and a stage (3).
    for (k, stage) in model.stages.iter().enumerate() {
        if let Some(e) = deep(&stage.extras, 3, format!("/stages/{k}/extras")) {
            return Err(e);
        }
    }
    for (name, value) in &model.extensions {
        let pointer = format!("/extensions/{}", crate::structure::escape_pointer(name));
        if let Some(e) = deep(value, 2, pointer) {
            return Err(e);
        }
    }
    match deep(&model.extras, 1, "/extras".into()) {
        Some(e) => Err(e),
        None => Ok(()),
    }
}

/// Whether `value`, below `above` arrays and objects, nests deeper than [`MAX_DEPTH`]; `pointer`
/// is left at the first array or object too deep. Recursion stops at the limit.
fn too_deep(value: &serde_json::Value, above: usize, pointer: &mut String) -> bool {
    use serde_json::Value;
    let children: Box<dyn Iterator<Item = (String, &Value)>> = match value {
        Value::Array(items) => Box::new(items.iter().enumerate().map(|(i, v)| (i.to_string(), v))),
        Value::Object(map) => Box::new(
            map.iter()
                .map(|(k, v)| (crate::structure::escape_pointer(k), v)),
        ),
        _ => return false,
    };
    if above + 1 > MAX_DEPTH {
        return true;
    }
    for (token, child) in children {
        let len = pointer.len();
        pointer.push('/');
        pointer.push_str(&token);
        if too_deep(child, above + 1, pointer) {
            return true;
        }
        pointer.truncate(len);
    }
    false
}

/// The first NaN or infinity among the model's numbers, with the rule and location a reader
/// reports for it (spec §9: ISM-102, ISM-111, ISM-114, ISM-126).
fn first_non_finite(model: &Model) -> Option<(Rule, Location)> {
    let find = |xs: &[f64]| xs.iter().position(|x| !x.is_finite());
    if let Some(i) = find(&model.vertices) {
        return Some((
            Rule::VertexArray,
            Location {
                vertex: Some(i / model.dim().max(1)),
                ..Location::pointer(format!("/vertices/{i}"))
            },
        ));
    }
    if let Some(i) = find(&model.values) {
        return Some((
            Rule::ValueArray,
            Location {
                vertex: Some(i),
                ..Location::pointer(format!("/values/{i}"))
            },
        ));
    }
    if !model.level.is_finite() {
        return Some((Rule::Level, Location::pointer("/level")));
    }
    for (k, stage) in model.stages.iter().enumerate() {
        for (r, rec) in stage.faces.iter().enumerate() {
            let at = |what: &str, i: usize| {
                Some((
                    Rule::NonFinite,
                    Location {
                        stage: Some(k),
                        face: Some(rec.face.to_vec()),
                        ..Location::pointer(format!("/stages/{k}/faces/{r}/{what}/{i}"))
                    },
                ))
            };
            if let Some(i) = find(rec.points) {
                return at("points", i);
            }
            if let Some(i) = find(rec.weights) {
                return at("weights", i);
            }
        }
        for (r, map) in stage.vertex_maps.iter().enumerate() {
            if let Some(i) = find(&map.coefficients) {
                return Some((
                    Rule::NonFinite,
                    Location {
                        stage: Some(k),
                        vertex: Some(map.vertex as usize),
                        ..Location::pointer(format!("/stages/{k}/vertexMaps/{r}/coefficients/{i}"))
                    },
                ));
            }
        }
    }
    None
}

/// The container header for a payload.
pub fn header(encoding: Encoding, version: Version, payload: &[u8]) -> [u8; HEADER_LEN] {
    header_of(
        encoding,
        version,
        payload.len() as u64,
        crc32fast::hash(payload),
    )
}

/// The container header for a payload of `len` bytes with CRC-32 `crc`.
fn header_of(encoding: Encoding, version: Version, len: u64, crc: u32) -> [u8; HEADER_LEN] {
    let mut h = [0u8; HEADER_LEN];
    h[..8].copy_from_slice(&MAGIC);
    h[8..10].copy_from_slice(&version.major.to_le_bytes());
    h[10..12].copy_from_slice(&version.minor.to_le_bytes());
    h[12] = encoding.tag();
    h[16..24].copy_from_slice(&len.to_le_bytes());
    h[24..28].copy_from_slice(&crc.to_le_bytes());
    let hc = crc32fast::hash(&h[..28]);
    h[28..32].copy_from_slice(&hc.to_le_bytes());
    h
}

/// Whether a file of this encoding has the container (spec §7.1).
fn in_container(encoding: Encoding, options: WriteOptions) -> bool {
    encoding != Encoding::Json || options.json_in_container
}

/// Encodes a whole file in memory, in the canonical form of spec §7.7: a file this crate reads.
///
/// # Errors
/// As [`encode_payload`].
pub fn to_vec(model: &Model, encoding: Encoding, options: WriteOptions) -> Result<Vec<u8>> {
    check_writable(model)?;
    encode_file(&own_version(model), encoding, options, FORMAT_VERSION)
}

/// Encodes a model as it is, without the checks of [`to_vec`] and with its own `version` (also in
/// the container header, when it parses): for test vectors, which are files readers refuse.
///
/// # Errors
/// ISM-126 for a non-finite number in JSON, which cannot hold one.
#[doc(hidden)]
pub fn to_vec_unchecked(
    model: &Model,
    encoding: Encoding,
    options: WriteOptions,
) -> Result<Vec<u8>> {
    let version = model.parsed_version().unwrap_or(FORMAT_VERSION);
    encode_file(model, encoding, options, version)
}

/// The file in one buffer: the payload is encoded after room for the header, which is filled in
/// last (one copy of the payload in memory, not two).
fn encode_file(
    model: &Model,
    encoding: Encoding,
    options: WriteOptions,
    version: Version,
) -> Result<Vec<u8>> {
    if !in_container(encoding, options) {
        let mut out = Vec::new();
        encode_into(model, encoding, options.pretty, &mut out)?;
        return Ok(out);
    }
    let mut out = vec![0u8; HEADER_LEN];
    encode_into(model, encoding, options.pretty, &mut out)?;
    let h = header(encoding, version, &out[HEADER_LEN..]);
    out[..HEADER_LEN].copy_from_slice(&h);
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

/// Encodes a whole structured file (`.isms`, spec §7.4.3) whose complex is written as
/// `complexForm` 1 — the Kuhn grid and edge bisections of `refinement` — when
/// [`KuhnRefinement::describes`] the model's `vertices` and `simplices` exactly (every bit, in
/// order; it rebuilds them to check), and as the canonical `complexForm` 0 otherwise (a
/// refinement of another model, or a `dimension` other than 2 or 3). The rest of the file is the
/// canonical structured encoding. Returns the file and whether `complexForm` 1 was written.
///
/// Form 1 is a writer's option, not the canonical form: [`to_vec`], [`write_path`] and
/// `ism convert` always write `complexForm` 0. A reader gives the same model either way.
///
/// # Errors
/// As [`to_vec`].
pub fn to_vec_refined(model: &Model, refinement: &KuhnRefinement) -> Result<(Vec<u8>, bool)> {
    check_writable(model)?;
    let model = own_version(model);
    let (payload, refined) = crate::structured::encode_refined(&model, Some(refinement))?;
    let mut out = Vec::with_capacity(HEADER_LEN + payload.len());
    out.extend(header(Encoding::Structured, FORMAT_VERSION, &payload));
    out.extend(payload);
    Ok((out, refined))
}

/// Writes [`to_vec_refined`]'s file to `path` atomically, as [`write_path`] does (a temporary
/// file beside it, renamed over it: a failure never leaves a partial file), whatever the path's
/// extension. Returns whether `complexForm` 1 was written.
///
/// # Errors
/// As [`to_vec_refined`], plus [`Error::Io`] naming the path.
pub fn write_path_refined(
    model: &Model,
    path: impl AsRef<Path>,
    refinement: &KuhnRefinement,
) -> Result<bool> {
    let path = path.as_ref();
    let (bytes, refined) = to_vec_refined(model, refinement)?;
    write_atomic(path, |w| w.write_all(&bytes))
        .map_err(|e| Error::io(Some(path.to_path_buf()), e))?;
    Ok(refined)
}

/// A writer that counts the bytes it passes on and their CRC-32 (the container's payload checksum,
/// computed while the payload streams to the file).
struct CrcWriter<W> {
    inner: W,
    hasher: crc32fast::Hasher,
    len: u64,
}

impl<W: Write> Write for CrcWriter<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.hasher.update(&buf[..n]);
        self.len += n as u64;
        Ok(n)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

/// Buffer between the encoders' many small writes and the checksum and file: large enough that
/// the CRC runs over long stretches.
const STREAM_BUFFER: usize = 1 << 20;

/// Writes a file atomically: into a temporary file beside `path`, then renamed over it, so a
/// failure never leaves a partial file. The encoding defaults to the one the extension suggests.
///
/// The payload streams to the file (its checksum computed on the way, the header written last), so
/// no copy of the encoded payload is held in memory.
///
/// # Errors
/// As [`to_vec`], plus [`Error::Io`] naming the path.
pub fn write_path(
    model: &Model,
    path: impl AsRef<Path>,
    encoding: Option<Encoding>,
    options: WriteOptions,
) -> Result<()> {
    use std::io::{Seek, SeekFrom};
    let path = path.as_ref();
    let encoding = encoding
        .or_else(|| Encoding::from_path(path))
        .unwrap_or(Encoding::Binary);
    check_writable(model)?;
    let model = own_version(model);
    // The encoders' own errors, kept while the closure reports an I/O error to abandon the file.
    let mut failed: Option<Error> = None;
    let written = write_atomic(path, |w| {
        w.flush()?;
        let mut file: &std::fs::File = w.get_ref();
        let container = in_container(encoding, options);
        if container {
            file.write_all(&[0; HEADER_LEN])?;
        }
        let mut out = std::io::BufWriter::with_capacity(
            STREAM_BUFFER,
            CrcWriter {
                inner: file,
                hasher: crc32fast::Hasher::new(),
                len: 0,
            },
        );
        if let Err(e) = encode_into(&model, encoding, options.pretty, &mut out) {
            let io = match &e {
                Error::Io { error, .. } => std::io::Error::new(error.kind(), error.to_string()),
                _ => std::io::Error::other("encoding failed"),
            };
            failed = Some(e);
            return Err(io);
        }
        let crc = out.into_inner().map_err(|e| e.into_error())?;
        if container {
            let h = header_of(encoding, FORMAT_VERSION, crc.len, crc.hasher.finalize());
            file.seek(SeekFrom::Start(0))?;
            file.write_all(&h)?;
        }
        Ok(())
    });
    match (written, failed) {
        (Ok(()), _) => Ok(()),
        (Err(_), Some(Error::Io { error, .. })) => Err(Error::io(Some(path.to_path_buf()), error)),
        (Err(_), Some(e)) => Err(e),
        (Err(e), None) => Err(Error::io(Some(path.to_path_buf()), e)),
    }
}

/// Where [`write_atomic`] writes for `path`, and whether it must copy rather than rename there
/// (see there): a symbolic link resolved to its target, unless that is not a regular file or
/// lies in `/proc` or `/dev`. A path that does not exist yet is a new regular file.
fn destination(path: &Path) -> (std::path::PathBuf, bool) {
    let Ok(meta) = std::fs::symlink_metadata(path) else {
        return (path.to_path_buf(), false);
    };
    if meta.is_file() {
        return (path.to_path_buf(), false);
    }
    if meta.file_type().is_symlink() {
        if let Ok(target) = std::fs::canonicalize(path) {
            let descriptor = target.starts_with("/proc") || target.starts_with("/dev");
            if !descriptor && std::fs::metadata(&target).is_ok_and(|m| m.is_file()) {
                return (target, false);
            }
        } else {
            // A dangling link: created through it, as `open` would.
            return (path.to_path_buf(), true);
        }
    }
    (path.to_path_buf(), true)
}

/// Runs `fill` on a temporary file beside `path` and renames it over `path` only if `fill` and the
/// flush succeed. Shared by every writer of the workspace.
///
/// A rename replaces whatever is at `path`: as root, `ism convert m.ism /dev/null` turned the
/// machine's `/dev/null` into a regular file, and `-o /dev/stdout` its symbolic link. So a
/// symbolic link is followed, and the temporary file renamed over the regular file it names
/// (the link stays); a destination that is not a regular file (a device, a named pipe, or a
/// link into `/proc` or `/dev` such as `/dev/stdout`, whose target is an open descriptor) gets
/// the finished temporary file (made in the system's temporary directory) copied into it
/// instead: still nothing reaches it unless `fill` succeeded, but a failure of the copy itself
/// can leave part of the bytes there.
///
/// # Errors
/// Whatever `fill`, the temporary file, the rename or the copy report.
pub fn write_atomic(
    path: &Path,
    fill: impl FnOnce(&mut std::io::BufWriter<&std::fs::File>) -> std::io::Result<()>,
) -> std::io::Result<()> {
    let (path, special) = destination(path);
    let path = path.as_path();
    let dir = match path.parent() {
        _ if special => std::env::temp_dir(),
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => std::path::PathBuf::from("."),
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
    if special {
        use std::io::Seek;
        let mut from = tmp.as_file();
        from.seek(std::io::SeekFrom::Start(0))?;
        // A device or pipe is opened as it is (truncation means nothing to them; a regular file
        // behind `/proc/self/fd/1` starts afresh, as `cp x /dev/stdout` does); `create` only for
        // a dangling link's target; a directory fails here with the system's error.
        let mut to = std::fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(true)
            .open(path)?;
        std::io::copy(&mut from, &mut to)?;
        return to.flush();
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A named pipe `name` in `dir` (made by `mkfifo`) and a thread reading it to the end.
    #[cfg(unix)]
    fn fifo_with_reader(
        dir: &Path,
        name: &str,
    ) -> (std::path::PathBuf, std::thread::JoinHandle<Vec<u8>>) {
        let fifo = dir.join(name);
        let made = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap();
        assert!(made.success());
        let reader = {
            let fifo = fifo.clone();
            std::thread::spawn(move || std::fs::read(fifo).unwrap())
        };
        (fifo, reader)
    }

    /// A named pipe as the destination: the bytes arrive through it and it is still a pipe
    /// afterwards (a rename would have replaced it with a regular file, as it did `/dev/null`).
    #[cfg(unix)]
    #[test]
    fn write_atomic_into_a_named_pipe_keeps_the_pipe() {
        use std::os::unix::fs::FileTypeExt;
        let dir = tempfile::tempdir().unwrap();
        let (fifo, reader) = fifo_with_reader(dir.path(), "pipe");
        let payload: Vec<u8> = (0..200_000u32).map(|i| (i % 251) as u8).collect();
        write_atomic(&fifo, |w| w.write_all(&payload)).unwrap();
        // The type first: had the pipe been replaced, the reader would wait forever.
        assert!(std::fs::symlink_metadata(&fifo)
            .unwrap()
            .file_type()
            .is_fifo());
        assert_eq!(reader.join().unwrap(), payload);
        // Nothing was left beside it.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    /// Through a symbolic link to a regular file: the link stays a link, its target gets the
    /// bytes, and a second write replaces them atomically there.
    #[cfg(unix)]
    #[test]
    fn write_atomic_through_a_symlink_keeps_the_link() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("real.bin");
        std::fs::write(&target, b"old contents, longer than the new").unwrap();
        let link = dir.path().join("link.bin");
        std::os::unix::fs::symlink(&target, &link).unwrap();
        write_atomic(&link, |w| w.write_all(b"new")).unwrap();
        assert!(std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink());
        assert_eq!(std::fs::read(&target).unwrap(), b"new");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
    }

    /// `write_path` into a named pipe (it seeks back for the header, which a pipe cannot): the
    /// pipe delivers exactly the bytes of `to_vec`, and stays a pipe. (Not `/dev/null` itself: a
    /// regression would replace the test machine's `/dev/null`.)
    #[cfg(unix)]
    #[test]
    fn write_path_into_a_named_pipe_delivers_the_file() {
        use crate::builder::ModelBuilder;
        use std::os::unix::fs::FileTypeExt;
        let mut b = ModelBuilder::new(2);
        for (p, f) in [([0.0, 0.0], -1.0), ([1.0, 0.0], 1.0), ([0.0, 1.0], 1.0)] {
            b = b.vertex(&p, f);
        }
        let m = b.simplex(&[0, 1, 2]).build().unwrap();
        let dir = tempfile::tempdir().unwrap();
        let (fifo, reader) = fifo_with_reader(dir.path(), "model.ismb");
        write_path(&m, &fifo, None, WriteOptions::default()).unwrap();
        let want = to_vec(&m, Encoding::Binary, WriteOptions::default()).unwrap();
        assert!(std::fs::symlink_metadata(&fifo)
            .unwrap()
            .file_type()
            .is_fifo());
        assert_eq!(reader.join().unwrap(), want);
    }

    /// Hands out one byte per read: no face record is ever wholly in the stream's window, so every
    /// record takes the decoder's checked path.
    struct OneByte<'a>(&'a [u8]);

    impl Read for OneByte<'_> {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            let n = buf.len().min(1).min(self.0.len());
            buf[..n].copy_from_slice(&self.0[..n]);
            self.0 = &self.0[n..];
            Ok(n)
        }
    }

    /// The checked record path without the numbers keeps the ids and lengths the full read keeps
    /// (truth: the records written), and asks for a second read when a number is not finite.
    #[test]
    fn byte_by_byte_reads_without_numbers() {
        use crate::builder::{ModelBuilder, StageBuilder};
        // One triangle; records of two lengths (edges, the triangle), with weights.
        let mut b = ModelBuilder::new(2);
        for (p, f) in [([0.0, 0.0], -1.0), ([1.0, 0.0], 1.0), ([0.0, 1.0], 1.0)] {
            b = b.vertex(&p, f);
        }
        let stage = StageBuilder::rational(3)
            .face(&[0, 2], &[0.6, 0.4, 0.3, 0.7], &[1.5, 2.0])
            .face(&[0, 1, 2], &[0.2, 0.3, 0.5], &[0.5])
            .face(&[1, 2], &[0.5, 0.5, 0.25, 0.75], &[1.0, 3.0]);
        let m = b.simplex(&[0, 1, 2]).stage(stage.build()).build().unwrap();
        let options = ReadOptions::default();
        let bytes = to_vec(&m, Encoding::Binary, WriteOptions::default()).unwrap();
        let doc = read_keeping(OneByte(&bytes), &options, false)
            .unwrap()
            .unwrap();
        let (got, want) = (&doc.model.stages[0].faces, &m.stages[0].faces);
        assert!(!got.numbers_kept());
        assert_eq!(got.all_face_ids(), want.all_face_ids());
        assert_eq!(got.point_offsets(), want.point_offsets());
        assert_eq!(got.weight_offsets(), want.weight_offsets());
        assert_eq!((got.num_points(), got.num_weights()), (11, 5));
        let mut nan = m.clone();
        nan.stages[0].faces.record_mut(1).weights[0] = f64::NAN;
        let bytes = to_vec_unchecked(&nan, Encoding::Binary, WriteOptions::default()).unwrap();
        assert!(read_keeping(OneByte(&bytes), &options, false)
            .unwrap()
            .is_none());
        assert_eq!(
            read_keeping(OneByte(&bytes), &options, true)
                .unwrap_err()
                .rule(),
            Some(Rule::NonFinite)
        );
    }
}
