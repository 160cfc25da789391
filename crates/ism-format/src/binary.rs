//! The binary encoding's decoder (spec §7.4), written from the grammar rather than with bincode so
//! that every error names the member (JSON pointer) and the byte offset, and so that a declared
//! length is checked against the bytes left before anything is allocated for it.

use std::collections::BTreeMap;

use crate::decode::{pointer_of, Decoder, JsonTokens, Seg};
use crate::error::{Error, Result};
use crate::model::{
    Direction, FaceRecord, JsonValue, Metadata, Model, Stage, StageKind, VertexMap,
};
use crate::rules::{Location, Rule};

/// Smallest encoded size of one element, per sequence type (spec §7.4): what a declared length is
/// checked against.
mod min_size {
    pub const F64: usize = 8;
    pub const U32: usize = 4;
    pub const STRING: usize = 8;
    /// kind, degree, direction (u32 each), name tag, three lengths (faces, vertexMaps, extras text).
    pub const STAGE: usize = 4 + 4 + 4 + 1 + 8 + 8 + 8;
    pub const FACE_RECORD: usize = 8 * 3;
    pub const VERTEX_MAP: usize = 4 + 8;
    pub const EXTENSION: usize = 8 + 8;
}

pub(crate) struct BinaryDecoder<'a> {
    b: &'a [u8],
    at: usize,
    base: u64,
    path: Vec<Seg>,
}

impl<'a> BinaryDecoder<'a> {
    /// A decoder of `payload`, whose first byte is at file offset `base`.
    pub(crate) fn new(payload: &'a [u8], base: u64) -> BinaryDecoder<'a> {
        BinaryDecoder {
            b: payload,
            at: 0,
            base,
            path: Vec::new(),
        }
    }

    fn fail(&self, at: usize, message: impl Into<String>) -> Error {
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

    fn remaining(&self) -> usize {
        self.b.len() - self.at
    }

    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8]> {
        self.take_with(n, || what.to_string())
    }

    /// [`Self::take`] with the description built only on failure (no allocation per record).
    fn take_with(&mut self, n: usize, what: impl FnOnce() -> String) -> Result<&'a [u8]> {
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
        let out = &self.b[self.at..self.at + n];
        self.at += n;
        Ok(out)
    }

    fn u8(&mut self, what: &str) -> Result<u8> {
        Ok(self.take(1, what)?[0])
    }

    fn u32(&mut self, what: &str) -> Result<u32> {
        let bytes = self.take(4, what)?;
        Ok(u32::from_le_bytes(bytes.try_into().expect("4 bytes")))
    }

    fn f64(&mut self, what: &str) -> Result<f64> {
        let bytes = self.take(8, what)?;
        Ok(f64::from_le_bytes(bytes.try_into().expect("8 bytes")))
    }

    /// A `u64` length prefix, checked against the bytes left: `min` is the smallest size of one
    /// element, so nothing is allocated for elements the payload cannot hold.
    fn length(&mut self, min: usize, what: &str) -> Result<usize> {
        let start = self.at;
        let bytes = self.take_with(8, || format!("the length of {what}"))?;
        let n = u64::from_le_bytes(bytes.try_into().expect("8 bytes"));
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
        let n = self.length(1, what)?;
        let at = self.at;
        let bytes = self.take(n, what)?;
        match std::str::from_utf8(bytes) {
            Ok(s) => Ok(s.to_string()),
            Err(e) => Err(self.fail(at + e.valid_up_to(), format!("invalid UTF-8 in {what}"))),
        }
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

    fn member<T>(
        &mut self,
        name: &'static str,
        read: impl FnOnce(&mut Self) -> Result<T>,
    ) -> Result<T> {
        self.path.push(Seg::Key(name.into()));
        let out = read(self)?;
        self.path.pop();
        Ok(out)
    }

    fn f64s(&mut self, what: &str) -> Result<Vec<f64>> {
        let n = self.length(min_size::F64, what)?;
        let bytes = self.take(n * 8, what)?;
        Ok(bytes
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
            .collect())
    }

    fn u32s(&mut self, what: &str) -> Result<Vec<u32>> {
        let n = self.length(min_size::U32, what)?;
        let bytes = self.take(n * 4, what)?;
        Ok(bytes
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes(c.try_into().expect("4 bytes")))
            .collect())
    }

    fn seq<T>(
        &mut self,
        min: usize,
        what: &str,
        mut read: impl FnMut(&mut Self) -> Result<T>,
    ) -> Result<Vec<T>> {
        let n = self.length(min, what)?;
        let mut out = Vec::with_capacity(n);
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
        let text = self.string("JSON text")?;
        let tokens = JsonTokens::new(text.as_bytes(), self.base + start as u64 + 8);
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

    fn stage(&mut self) -> Result<Stage> {
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
        let faces = self.member("faces", |d| {
            d.seq(min_size::FACE_RECORD, "faces", |d| {
                Ok(FaceRecord {
                    face: d.member("face", |d| d.u32s("face"))?,
                    points: d.member("points", |d| d.f64s("points"))?,
                    weights: d.member("weights", |d| d.f64s("weights"))?,
                })
            })
        })?;
        let vertex_maps = self.member("vertexMaps", |d| {
            d.seq(min_size::VERTEX_MAP, "vertexMaps", |d| {
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
        let n = self.length(min_size::EXTENSION, "extensions")?;
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
        let vertices = self.member("vertices", |d| d.f64s("vertices"))?;
        let simplices = self.member("simplices", |d| d.u32s("simplices"))?;
        let values = self.member("values", |d| d.f64s("values"))?;
        let level = self.member("level", |d| d.f64("level"))?;
        let stages = self.member("stages", |d| {
            d.seq(min_size::STAGE, "stages", |d| d.stage())
        })?;
        let extensions_used = self.member("extensionsUsed", |d| {
            d.seq(min_size::STRING, "extensionsUsed", |d| {
                d.string("an extension name")
            })
        })?;
        let extensions_required = self.member("extensionsRequired", |d| {
            d.seq(min_size::STRING, "extensionsRequired", |d| {
                d.string("an extension name")
            })
        })?;
        let extensions = self.member("extensions", |d| d.extensions())?;
        // Model (1).
        let extras = self.member("extras", |d| d.json(1))?;
        if self.at < self.b.len() && !allow_trailing {
            return Err(self.fail(
                self.at,
                format!("{} bytes follow the model", self.b.len() - self.at),
            ));
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
