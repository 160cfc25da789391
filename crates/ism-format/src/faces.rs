//! A stage's face records as one flat table (compressed sparse rows): every record's face vertex
//! ids, control points and weights concatenated into three arrays, with one row of end offsets per
//! record.
//!
//! The file's grammar is a list of records, each with three variable-length arrays (spec §5.2), and
//! a [`Model`](crate::Model) must hold any list a file spells — also a wrong one, for the structural
//! check to report — so the rows keep their lengths rather than a fixed stride per face dimension
//! (the checked [`StageTable`](crate::StageTable) has the fixed strides). Four allocations per
//! stage instead of three per record: decoding a million-tetrahedron model no longer makes 13 M heap
//! vectors, and the binary encoding reads and writes each array as one run of bytes.
//!
//! Reading yields borrowed views ([`FaceRef`]: `face`, `points`, `weights` slices); builders push the
//! parts, or collect owned [`FaceRecord`]s. Serialization is the list of records, byte for byte.

use std::borrow::Cow;

use bincode::Encode;
use serde::{Deserialize, Serialize};

use crate::model::FaceRecord;

/// One record of a [`FaceTable`], borrowed.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct FaceRef<'a> {
    /// The face: its global vertex ids (strictly increasing in a valid file).
    pub face: &'a [u32],
    /// Control points, flat: `k + 1` barycentric coordinates per owned multi-index.
    pub points: &'a [f64],
    /// Rational stages: one weight per owned multi-index; empty otherwise.
    #[serde(skip_serializing_if = "<[f64]>::is_empty")]
    pub weights: &'a [f64],
}

impl FaceRef<'_> {
    /// An owned copy.
    pub fn to_record(&self) -> FaceRecord {
        FaceRecord {
            face: self.face.to_vec(),
            points: self.points.to_vec(),
            weights: self.weights.to_vec(),
        }
    }
}

/// One record of a [`FaceTable`], with its numbers writable in place (lengths are fixed; use
/// [`FaceTable::edit`] to change them).
#[derive(Debug, PartialEq)]
pub struct FaceMut<'a> {
    /// The face's vertex ids.
    pub face: &'a mut [u32],
    /// Control points.
    pub points: &'a mut [f64],
    /// Weights (empty unless rational).
    pub weights: &'a mut [f64],
}

/// The table would hold more than `u32::MAX` ids, coordinates or weights (a stage larger than the
/// largest payload a default reader accepts: 2³² coordinates are 32 GiB).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TableFull;

impl std::fmt::Display for TableFull {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(
            "a stage's face table holds at most 4294967295 ids, coordinates and weights each",
        )
    }
}

impl std::error::Error for TableFull {}

/// A stage's face records, flat (see the module docs).
///
/// The layout is the one numpy and the Python binding use: per part, the concatenated values and
/// `len() + 1` offsets starting at 0 (record `r`'s ids are `ids[offsets[r]..offsets[r + 1]]`).
/// Offsets are `u32` (12 bytes per record rather than 24): a stage holds at most `u32::MAX` face
/// ids, coordinates and weights each; the decoders report a larger one as a limit (ISM-007) and
/// [`FaceTable::push`] panics.
///
/// A table whose records all have the same lengths (a stage of one face dimension, as written by
/// every builder of strata) keeps no offsets at all: record `r`'s parts are at `r` times those
/// lengths ([`FaceTable::uniform_lengths`]); the offsets are then computed on request. Which of
/// the two forms a table has follows from its records alone, so equal records make equal tables.
#[derive(Clone, PartialEq)]
pub struct FaceTable {
    ids: Vec<u32>,
    points: Vec<f64>,
    weights: Vec<f64>,
    /// Number of records.
    len: usize,
    rows: Rows,
    /// `Some` for a table read without its numbers ([`crate::io::ReadOptions::keep_record_numbers`]):
    /// `points` and `weights` are then empty, and this counts what the records hold.
    elided: Option<Elided>,
}

/// What a table read without its numbers keeps of them: how many there were, and whether every
/// one was finite (the structural check's only question about their values).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Elided {
    points: usize,
    weights: usize,
    finite: bool,
}

/// Where a [`FaceTable`]'s records lie in its three arrays.
#[derive(Clone, Debug, PartialEq)]
enum Rows {
    /// Every record has these lengths (ids, coordinates, weights); `[0, 0, 0]` when the table is
    /// empty.
    Uniform([u32; 3]),
    /// `len + 1` end offsets per part, from 0 (records of different lengths).
    Ragged {
        face_offsets: Vec<u32>,
        point_offsets: Vec<u32>,
        weight_offsets: Vec<u32>,
    },
}

impl Default for FaceTable {
    fn default() -> FaceTable {
        FaceTable {
            ids: Vec::new(),
            points: Vec::new(),
            weights: Vec::new(),
            len: 0,
            rows: Rows::Uniform([0; 3]),
            elided: None,
        }
    }
}

impl FaceTable {
    /// An empty table.
    pub fn new() -> FaceTable {
        FaceTable::default()
    }

    /// An empty table. (`records` is not needed: a table of records of one length keeps no
    /// offsets, and its parts can be reserved once the first record shows their lengths, by
    /// [`FaceTable::reserve_records`].)
    pub fn with_capacity(_records: usize) -> FaceTable {
        FaceTable::default()
    }

    /// Reserves room for `more` records of the lengths of the records so far (nothing for an empty
    /// or a ragged table, whose next lengths are unknown). Like `Vec::reserve`, but a reservation
    /// the allocator refuses is skipped (the parts then grow as records arrive).
    pub fn reserve_records(&mut self, more: usize) {
        if let (Rows::Uniform(lens), true) = (&self.rows, self.len > 0) {
            let [a, b, c] = lens.map(|x| (x as usize).saturating_mul(more));
            let _ = self.ids.try_reserve_exact(a);
            if self.elided.is_none() {
                let _ = self.points.try_reserve_exact(b);
                let _ = self.weights.try_reserve_exact(c);
            }
        }
    }

    /// Whether the table holds its control points and weights: false only for a table read with
    /// [`crate::io::ReadOptions::keep_record_numbers`] off. Such a table keeps every record's face
    /// ids and lengths ([`FaceTable::lengths`], [`FaceTable::uniform_lengths`], the offsets,
    /// [`FaceTable::num_points`]) but its records' `points` and `weights` are empty slices; it
    /// cannot be written or indexed ([`crate::Error::NumbersNotKept`]).
    pub fn numbers_kept(&self) -> bool {
        self.elided.is_none()
    }

    /// Control point coordinates over all records (also for a table read without its numbers).
    pub fn num_points(&self) -> usize {
        self.part_lens()[1]
    }

    /// Weights over all records (also for a table read without its numbers).
    pub fn num_weights(&self) -> usize {
        self.part_lens()[2]
    }

    /// Record `r`'s lengths (face ids, coordinates, weights), or `None` past the end; also for a
    /// table read without its numbers.
    pub fn lengths(&self, r: usize) -> Option<[usize; 3]> {
        self.ranges(r).map(|parts| parts.map(|p| p.len()))
    }

    /// Makes an empty table one that counts its records' numbers instead of keeping them (the
    /// binary decoder, for a read with `keep_record_numbers` off).
    pub(crate) fn elide_numbers(&mut self) {
        debug_assert!(self.len == 0 && self.points.is_empty() && self.weights.is_empty());
        self.elided = Some(Elided {
            points: 0,
            weights: 0,
            finite: true,
        });
    }

    /// For a table that does not keep its numbers: counts `points` coordinates and `weights`
    /// weights of the record being built, `finite` when every one of them is.
    pub(crate) fn count_numbers(&mut self, points: usize, weights: usize, finite: bool) {
        let e = self
            .elided
            .as_mut()
            .expect("count_numbers on a table that keeps its numbers");
        e.points += points;
        e.weights += weights;
        e.finite &= finite;
    }

    /// `Some(all finite)` for a table read without its numbers; `None` for one that keeps them.
    pub(crate) fn elided_finite(&self) -> Option<bool> {
        self.elided.map(|e| e.finite)
    }

    /// The lengths of the three parts: the arrays', or what a table without its numbers counted.
    #[inline]
    fn part_lens(&self) -> [usize; 3] {
        match self.elided {
            None => [self.ids.len(), self.points.len(), self.weights.len()],
            Some(e) => [self.ids.len(), e.points, e.weights],
        }
    }

    /// The lengths (face ids, coordinates, weights) every record has, when they are all the same;
    /// `None` when records differ (or the table is empty). Record `r`'s parts then start at `r`
    /// times these lengths in [`FaceTable::all_face_ids`], [`FaceTable::all_points`] and
    /// [`FaceTable::all_weights`].
    #[inline]
    pub fn uniform_lengths(&self) -> Option<[usize; 3]> {
        match &self.rows {
            Rows::Uniform(lens) if self.len > 0 => Some(lens.map(|x| x as usize)),
            _ => None,
        }
    }

    /// Number of records.
    #[inline]
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether there is no record.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Record `r`'s ranges in the three arrays, or `None` past the end.
    #[inline]
    fn ranges(&self, r: usize) -> Option<[std::ops::Range<usize>; 3]> {
        if r >= self.len {
            return None;
        }
        Some(match &self.rows {
            Rows::Uniform(lens) => lens.map(|x| {
                let x = x as usize;
                r * x..(r + 1) * x
            }),
            Rows::Ragged {
                face_offsets,
                point_offsets,
                weight_offsets,
            } => {
                let range = |o: &[u32]| o[r] as usize..o[r + 1] as usize;
                [
                    range(face_offsets),
                    range(point_offsets),
                    range(weight_offsets),
                ]
            }
        })
    }

    /// Record `r`, or `None` past the end.
    #[inline]
    pub fn get(&self, r: usize) -> Option<FaceRef<'_>> {
        let [f, p, w] = self.ranges(r)?;
        // A table read without its numbers has none to lend.
        let (p, w) = if self.elided.is_some() {
            (0..0, 0..0)
        } else {
            (p, w)
        };
        Some(FaceRef {
            face: &self.ids[f],
            points: &self.points[p],
            weights: &self.weights[w],
        })
    }

    /// Record `r`.
    ///
    /// # Panics
    /// If `r ≥ len()`, like slice indexing.
    #[inline]
    pub fn record(&self, r: usize) -> FaceRef<'_> {
        self.get(r)
            .unwrap_or_else(|| panic!("face record {r} out of range: the table has {}", self.len()))
    }

    /// Record `r`'s face ids alone (what face lookups need: no point or weight ranges).
    ///
    /// # Panics
    /// If `r ≥ len()`.
    #[inline]
    pub fn face(&self, r: usize) -> &[u32] {
        match &self.rows {
            Rows::Uniform(lens) => {
                assert!(
                    r < self.len,
                    "face record {r} out of range: the table has {}",
                    self.len
                );
                let a = lens[0] as usize;
                &self.ids[r * a..(r + 1) * a]
            }
            Rows::Ragged { face_offsets, .. } => {
                &self.ids[face_offsets[r] as usize..face_offsets[r + 1] as usize]
            }
        }
    }

    /// Record `r` with its numbers writable, or `None` past the end.
    pub fn get_mut(&mut self, r: usize) -> Option<FaceMut<'_>> {
        let [f, p, w] = self.ranges(r)?;
        let (p, w) = if self.elided.is_some() {
            (0..0, 0..0)
        } else {
            (p, w)
        };
        Some(FaceMut {
            face: &mut self.ids[f],
            points: &mut self.points[p],
            weights: &mut self.weights[w],
        })
    }

    /// Record `r` with its numbers writable.
    ///
    /// # Panics
    /// If `r ≥ len()`.
    pub fn record_mut(&mut self, r: usize) -> FaceMut<'_> {
        let len = self.len();
        self.get_mut(r)
            .unwrap_or_else(|| panic!("face record {r} out of range: the table has {len}"))
    }

    /// The records in order.
    pub fn iter(&self) -> Iter<'_> {
        Iter {
            table: self,
            front: 0,
            back: self.len(),
        }
    }

    /// Appends a record.
    ///
    /// # Panics
    /// If the table would hold more than `u32::MAX` ids, coordinates or weights.
    pub fn push(&mut self, face: &[u32], points: &[f64], weights: &[f64]) {
        self.ids.extend_from_slice(face);
        if self.elided.is_some() {
            let finite = points.iter().chain(weights).all(|x| x.is_finite());
            self.count_numbers(points.len(), weights.len(), finite);
        } else {
            self.points.extend_from_slice(points);
            self.weights.extend_from_slice(weights);
        }
        self.close_record().expect("face table overflow");
    }

    /// Appends an owned record.
    ///
    /// # Panics
    /// As [`FaceTable::push`].
    pub fn push_record(&mut self, record: &FaceRecord) {
        self.push(&record.face, &record.points, &record.weights);
    }

    /// Ends a record whose parts were appended to [`FaceTable::parts_mut`]'s arrays.
    pub(crate) fn close_record(&mut self) -> Result<(), TableFull> {
        let end = |n: usize| u32::try_from(n).map_err(|_| TableFull);
        let [ids, points, weights] = self.part_lens();
        let row = [end(ids)?, end(points)?, end(weights)?];
        match &mut self.rows {
            Rows::Uniform(lens) => {
                // The previous records end at `len` times their lengths, within u32 (checked when
                // they were closed).
                let end_of =
                    |records: usize, i: usize| (records as u64 * u64::from(lens[i])) as u32;
                let this = [0, 1, 2].map(|i| row[i] - end_of(self.len, i));
                if self.len == 0 {
                    *lens = this;
                } else if this != *lens {
                    // The first record of other lengths: the offsets of those before it, then on.
                    let offsets = |i: usize| -> Vec<u32> {
                        let mut o = Vec::with_capacity(self.len + 2);
                        o.extend((0..=self.len).map(|r| end_of(r, i)));
                        o.push(row[i]);
                        o
                    };
                    self.rows = Rows::Ragged {
                        face_offsets: offsets(0),
                        point_offsets: offsets(1),
                        weight_offsets: offsets(2),
                    };
                }
            }
            Rows::Ragged {
                face_offsets,
                point_offsets,
                weight_offsets,
            } => {
                face_offsets.push(row[0]);
                point_offsets.push(row[1]);
                weight_offsets.push(row[2]);
            }
        }
        self.len += 1;
        Ok(())
    }

    /// How many more records of the lengths of a uniform, nonempty table it has room for (the
    /// `u32` offsets' bound); 0 for other tables.
    pub(crate) fn uniform_room(&self) -> usize {
        let used = self.part_lens();
        match (&self.rows, self.len > 0) {
            (Rows::Uniform(lens), true) => {
                [(lens[0], used[0]), (lens[1], used[1]), (lens[2], used[2])]
                    .iter()
                    .map(|&(per, used)| match per {
                        0 => usize::MAX,
                        per => (u32::MAX as usize).saturating_sub(used) / per as usize,
                    })
                    .min()
                    .unwrap_or(0)
            }
            _ => 0,
        }
    }

    /// Ends `k` records of a uniform, nonempty table's lengths whose parts were appended to
    /// [`FaceTable::parts_mut`]'s arrays (at most [`FaceTable::uniform_room`] of them).
    pub(crate) fn close_uniform(&mut self, k: usize) {
        if k == 0 {
            return;
        }
        let Rows::Uniform(lens) = self.rows else {
            unreachable!("close_uniform on a ragged table");
        };
        self.len += k;
        debug_assert_eq!(self.part_lens(), lens.map(|x| x as usize * self.len));
    }

    /// The arrays a decoder appends a record's parts to before [`FaceTable::close_record`].
    pub(crate) fn parts_mut(&mut self) -> (&mut Vec<u32>, &mut Vec<f64>, &mut Vec<f64>) {
        (&mut self.ids, &mut self.points, &mut self.weights)
    }

    /// `len() + 1` offsets into [`FaceTable::all_face_ids`], from 0 (computed when the records
    /// all have the same lengths: [`FaceTable::uniform_lengths`]).
    pub fn face_offsets(&self) -> Cow<'_, [u32]> {
        self.offsets(0)
    }

    /// `len() + 1` offsets into [`FaceTable::all_points`], from 0 (computed as
    /// [`FaceTable::face_offsets`]).
    pub fn point_offsets(&self) -> Cow<'_, [u32]> {
        self.offsets(1)
    }

    /// `len() + 1` offsets into [`FaceTable::all_weights`], from 0 (computed as
    /// [`FaceTable::face_offsets`]).
    pub fn weight_offsets(&self) -> Cow<'_, [u32]> {
        self.offsets(2)
    }

    /// Part `i`'s offsets.
    fn offsets(&self, i: usize) -> Cow<'_, [u32]> {
        match &self.rows {
            // Within u32, as the part's length is.
            Rows::Uniform(lens) => (0..=self.len)
                .map(|r| (r as u64 * u64::from(lens[i])) as u32)
                .collect(),
            Rows::Ragged {
                face_offsets,
                point_offsets,
                weight_offsets,
            } => Cow::Borrowed([face_offsets, point_offsets, weight_offsets][i]),
        }
    }

    /// Every record's face ids, concatenated.
    pub fn all_face_ids(&self) -> &[u32] {
        &self.ids
    }

    /// Every record's control point coordinates, concatenated (empty for a table read without its
    /// numbers: [`FaceTable::numbers_kept`]).
    pub fn all_points(&self) -> &[f64] {
        &self.points
    }

    /// Every record's weights, concatenated (empty for a table read without its numbers).
    pub fn all_weights(&self) -> &[f64] {
        &self.weights
    }

    /// Every record's control point coordinates, concatenated and writable.
    pub fn all_points_mut(&mut self) -> &mut [f64] {
        &mut self.points
    }

    /// Every record's weights, concatenated and writable.
    pub fn all_weights_mut(&mut self) -> &mut [f64] {
        &mut self.weights
    }

    /// Owned copies of the records.
    pub fn to_records(&self) -> Vec<FaceRecord> {
        self.iter().map(|r| r.to_record()).collect()
    }

    /// Rewrites the table through an owned list of records: for the rare edit that changes lengths
    /// or order (tests that build wrong files, builders that sort).
    /// (A table read without its numbers has records with empty `points` and `weights`: the
    /// rewritten table keeps those empty numbers, not the lengths it was read with.)
    ///
    /// # Panics
    /// As [`FaceTable::push`].
    pub fn edit<T>(&mut self, f: impl FnOnce(&mut Vec<FaceRecord>) -> T) -> T {
        let mut records = self.to_records();
        let out = f(&mut records);
        *self = FaceTable::from(records);
        out
    }

    /// Removes every record.
    pub fn clear(&mut self) {
        *self = FaceTable::default();
    }
}

/// Iterator over a [`FaceTable`]'s records.
#[derive(Clone, Debug)]
pub struct Iter<'a> {
    table: &'a FaceTable,
    front: usize,
    back: usize,
}

impl<'a> Iterator for Iter<'a> {
    type Item = FaceRef<'a>;

    fn next(&mut self) -> Option<FaceRef<'a>> {
        if self.front >= self.back {
            return None;
        }
        let r = self.front;
        self.front += 1;
        self.table.get(r)
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let n = self.back - self.front;
        (n, Some(n))
    }

    fn nth(&mut self, n: usize) -> Option<FaceRef<'a>> {
        self.front = self.front.saturating_add(n).min(self.back);
        self.next()
    }
}

impl DoubleEndedIterator for Iter<'_> {
    fn next_back(&mut self) -> Option<Self::Item> {
        if self.front >= self.back {
            return None;
        }
        self.back -= 1;
        self.table.get(self.back)
    }
}

impl ExactSizeIterator for Iter<'_> {}

impl std::iter::FusedIterator for Iter<'_> {}

impl<'a> IntoIterator for &'a FaceTable {
    type Item = FaceRef<'a>;
    type IntoIter = Iter<'a>;
    fn into_iter(self) -> Iter<'a> {
        self.iter()
    }
}

impl std::fmt::Debug for FaceTable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list().entries(self.iter()).finish()
    }
}

impl From<Vec<FaceRecord>> for FaceTable {
    fn from(records: Vec<FaceRecord>) -> FaceTable {
        records.into_iter().collect()
    }
}

impl FromIterator<FaceRecord> for FaceTable {
    fn from_iter<I: IntoIterator<Item = FaceRecord>>(iter: I) -> FaceTable {
        let mut table = FaceTable::new();
        table.extend(iter);
        table
    }
}

impl<'a> FromIterator<FaceRef<'a>> for FaceTable {
    fn from_iter<I: IntoIterator<Item = FaceRef<'a>>>(iter: I) -> FaceTable {
        let mut table = FaceTable::new();
        for r in iter {
            table.push(r.face, r.points, r.weights);
        }
        table
    }
}

impl Extend<FaceRecord> for FaceTable {
    fn extend<I: IntoIterator<Item = FaceRecord>>(&mut self, iter: I) {
        let iter = iter.into_iter();
        let more = iter.size_hint().0;
        for (i, r) in iter.enumerate() {
            self.push_record(&r);
            if i == 0 {
                self.reserve_records(more.saturating_sub(1));
            }
        }
    }
}

impl Serialize for FaceTable {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        if !self.numbers_kept() {
            return Err(serde::ser::Error::custom(NOT_KEPT));
        }
        s.collect_seq(self.iter())
    }
}

impl<'de> Deserialize<'de> for FaceTable {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<FaceTable, D::Error> {
        Vec::<FaceRecord>::deserialize(d).map(FaceTable::from)
    }
}

/// Why a table read without its numbers is not serialized (writers refuse it earlier, with
/// [`crate::Error::NumbersNotKept`]; this guards the serde and bincode impls themselves).
const NOT_KEPT: &str = "a face table read without its control points and weights cannot be written";

/// The binary encoding of `Vec<FaceRecord>` (spec §7.4: a `u64` count, then per record three
/// `u64`-length-prefixed arrays of little-endian numbers), written a slice at a time; with a
/// varint configuration (the compact encoding, §7.4.1) lengths and ids go through bincode's own
/// integer encoder, the numbers still a slice at a time.
impl Encode for FaceTable {
    fn encode<E: bincode::enc::Encoder>(
        &self,
        encoder: &mut E,
    ) -> Result<(), bincode::error::EncodeError> {
        use bincode::enc::write::Writer;
        if !self.numbers_kept() {
            return Err(bincode::error::EncodeError::Other(NOT_KEPT));
        }
        (self.len() as u64).encode(encoder)?;
        use bincode::config::Config;
        if encoder.config().int_encoding() != bincode::config::IntEncoding::Fixed {
            for r in self.iter() {
                (r.face.len() as u64).encode(encoder)?;
                for id in r.face {
                    id.encode(encoder)?;
                }
                (r.points.len() as u64).encode(encoder)?;
                write_le(encoder.writer(), r.points)?;
                (r.weights.len() as u64).encode(encoder)?;
                write_le(encoder.writer(), r.weights)?;
            }
            return Ok(());
        }
        let w = encoder.writer();
        for r in self.iter() {
            w.write(&(r.face.len() as u64).to_le_bytes())?;
            write_le(w, r.face)?;
            w.write(&(r.points.len() as u64).to_le_bytes())?;
            write_le(w, r.points)?;
            w.write(&(r.weights.len() as u64).to_le_bytes())?;
            write_le(w, r.weights)?;
        }
        Ok(())
    }
}

/// Numbers that the binary encoding writes little-endian.
pub(crate) trait LeBytes: bytemuck::Pod {
    /// The little-endian bytes of one number.
    fn le(self) -> [u8; 8];
    /// Their length.
    const SIZE: usize;
}

impl LeBytes for u32 {
    fn le(self) -> [u8; 8] {
        let mut out = [0; 8];
        out[..4].copy_from_slice(&self.to_le_bytes());
        out
    }
    const SIZE: usize = 4;
}

impl LeBytes for f64 {
    fn le(self) -> [u8; 8] {
        self.to_le_bytes()
    }
    const SIZE: usize = 8;
}

/// Writes `xs` as little-endian numbers: one copy of the slice's bytes on little-endian machines.
pub(crate) fn write_le<T: LeBytes, W: bincode::enc::write::Writer>(
    w: &mut W,
    xs: &[T],
) -> Result<(), bincode::error::EncodeError> {
    if cfg!(target_endian = "little") {
        w.write(bytemuck::cast_slice(xs))
    } else {
        for &x in xs {
            w.write(&x.le()[..T::SIZE])?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn records() -> Vec<FaceRecord> {
        vec![
            FaceRecord {
                face: vec![0, 2],
                points: vec![0.25, 0.75],
                weights: vec![],
            },
            FaceRecord {
                face: vec![],
                points: vec![],
                weights: vec![2.0],
            },
            FaceRecord {
                face: vec![1, 2, 3],
                points: vec![0.1, 0.2, 0.7, 0.3, 0.3, 0.4],
                weights: vec![1.5, 0.5],
            },
        ]
    }

    #[test]
    fn views_give_back_every_record() {
        let recs = records();
        let table = FaceTable::from(recs.clone());
        assert_eq!(table.len(), 3);
        assert_eq!(table.to_records(), recs);
        for (r, rec) in recs.iter().enumerate() {
            let view = table.record(r);
            assert_eq!(view.face, rec.face.as_slice());
            assert_eq!(table.face(r), rec.face.as_slice());
            assert_eq!(view.points, rec.points.as_slice());
            assert_eq!(view.weights, rec.weights.as_slice());
        }
        assert!(table.get(3).is_none());
        let back: Vec<_> = table.iter().rev().map(|r| r.to_record()).collect();
        assert_eq!(back, recs.iter().rev().cloned().collect::<Vec<_>>());
        assert_eq!(table.iter().nth(2).map(|r| r.face), Some(&[1u32, 2, 3][..]));
        assert_eq!(table.iter().len(), 3);
    }

    #[test]
    fn serializes_as_the_list_of_records() {
        let recs = records();
        let table = FaceTable::from(recs.clone());
        // Ground truth: serde's derive of the owned records.
        assert_eq!(
            serde_json::to_string(&table).unwrap(),
            serde_json::to_string(&recs).unwrap()
        );
        assert_eq!(
            rmp_serde::to_vec_named(&table).unwrap(),
            rmp_serde::to_vec_named(&recs).unwrap()
        );
        let config = crate::io::binary_config();
        assert_eq!(
            bincode::encode_to_vec(&table, config).unwrap(),
            bincode::encode_to_vec(&recs, config).unwrap()
        );
        let back: FaceTable = serde_json::from_str(&serde_json::to_string(&recs).unwrap()).unwrap();
        assert_eq!(back, table);
    }

    #[test]
    fn edits_in_place_and_by_record() {
        let mut table = FaceTable::from(records());
        table.record_mut(2).points[0] = 9.0;
        table.record_mut(0).face[1] = 5;
        assert_eq!(table.record(2).points[0], 9.0);
        assert_eq!(table.record(0).face, &[0, 5]);
        table.edit(|r| r[1].face.push(7));
        assert_eq!(table.record(1).face, &[7]);
        assert_eq!(table.record(2).weights, &[1.5, 0.5]);
        assert_eq!(table.all_weights(), &[2.0, 1.5, 0.5]);
        assert_eq!(&*table.weight_offsets(), &[0, 0, 1, 3]);
        assert_eq!(&*table.face_offsets(), &[0, 2, 3, 6]);
        assert_eq!(&*table.point_offsets(), &[0, 2, 2, 8]);
        table.clear();
        assert!(table.is_empty());
    }

    /// Offsets from the records' lengths by prefix sums (the test's own arithmetic).
    fn prefix_sums(records: &[FaceRecord], part: impl Fn(&FaceRecord) -> usize) -> Vec<u32> {
        let mut out = vec![0u32];
        for r in records {
            out.push(out.last().unwrap() + part(r) as u32);
        }
        out
    }

    fn record(face: &[u32], points: usize, weights: usize, seed: f64) -> FaceRecord {
        FaceRecord {
            face: face.to_vec(),
            points: (0..points).map(|i| seed + i as f64).collect(),
            weights: (0..weights).map(|i| -seed - i as f64).collect(),
        }
    }

    /// Tables of records of one length keep no offsets; tables of records of several lengths
    /// switch to offsets at the first record of other lengths. Either way every accessor gives the
    /// records pushed (truth: the list of owned records and its prefix sums).
    #[test]
    fn uniform_and_ragged_tables_give_back_the_records() {
        let uniform: Vec<FaceRecord> = (0..50)
            .map(|i| record(&[i, i + 1, i + 2], 3, 1, f64::from(i)))
            .collect();
        let mut late = uniform.clone();
        late.push(record(&[60, 61], 4, 2, 0.5));
        late.extend(uniform.iter().cloned());
        let mut early = vec![record(&[7], 0, 0, 0.0)];
        early.extend(uniform.iter().cloned());
        let empty_records: Vec<FaceRecord> = (0..5).map(|_| record(&[], 0, 0, 0.0)).collect();
        for (name, records, lens) in [
            ("uniform", &uniform, Some([3, 3, 1])),
            ("one other record late", &late, None),
            ("one other record first", &early, None),
            ("empty records", &empty_records, Some([0, 0, 0])),
            ("one record", &uniform[..1].to_vec(), Some([3, 3, 1])),
            ("no record", &Vec::new(), None),
        ] {
            // Three ways to build the same table.
            let pushed = {
                let mut t = FaceTable::new();
                for r in records {
                    t.push(&r.face, &r.points, &r.weights);
                }
                t
            };
            let collected = FaceTable::from(records.clone());
            let by_ref: FaceTable = pushed.iter().collect();
            assert_eq!(pushed, collected, "{name}");
            assert_eq!(by_ref, collected, "{name}");
            assert_eq!(pushed.uniform_lengths(), lens, "{name}");
            assert_eq!(pushed.len(), records.len(), "{name}");
            assert_eq!(&pushed.to_records(), records, "{name}");
            for (r, rec) in records.iter().enumerate() {
                assert_eq!(pushed.face(r), rec.face.as_slice(), "{name} {r}");
                assert_eq!(pushed.record(r).to_record(), *rec, "{name} {r}");
            }
            assert!(pushed.get(records.len()).is_none(), "{name}");
            assert_eq!(
                &*pushed.face_offsets(),
                prefix_sums(records, |r| r.face.len()),
                "{name}"
            );
            assert_eq!(
                &*pushed.point_offsets(),
                prefix_sums(records, |r| r.points.len()),
                "{name}"
            );
            assert_eq!(
                &*pushed.weight_offsets(),
                prefix_sums(records, |r| r.weights.len()),
                "{name}"
            );
            let concat = |f: fn(&FaceRecord) -> Vec<f64>| -> Vec<f64> {
                records.iter().flat_map(f).collect()
            };
            assert_eq!(pushed.all_points(), concat(|r| r.points.clone()), "{name}");
            assert_eq!(
                pushed.all_weights(),
                concat(|r| r.weights.clone()),
                "{name}"
            );
            // The binary encoding is the list of records'.
            let config = crate::io::binary_config();
            assert_eq!(
                bincode::encode_to_vec(&pushed, config).unwrap(),
                bincode::encode_to_vec(records, config).unwrap(),
                "{name}"
            );
        }
        // Equal records, equal tables; different records, different tables (also when only the
        // form would differ were it not decided by the records).
        assert_ne!(
            FaceTable::from(uniform.clone()),
            FaceTable::from(late.clone())
        );
        let mut reserved = FaceTable::from(uniform[..1].to_vec());
        reserved.reserve_records(1000);
        for r in &uniform[1..] {
            reserved.push_record(r);
        }
        assert_eq!(reserved, FaceTable::from(uniform.clone()));
    }

    #[test]
    #[should_panic(expected = "out of range")]
    fn a_record_past_the_end_of_a_table_of_empty_records_panics() {
        let t = FaceTable::from(vec![record(&[], 0, 0, 0.0); 3]);
        let _ = t.face(3);
    }

    #[test]
    fn uniform_room_counts_what_u32_offsets_can_address() {
        let t = FaceTable::from(vec![record(&[1, 2], 4, 0, 0.0); 3]);
        // ids: 6 used of u32::MAX, 2 per record; points: 12 used, 4 per record.
        assert_eq!(t.uniform_room(), (u32::MAX as usize - 12) / 4);
        assert_eq!(FaceTable::new().uniform_room(), 0);
        let ragged = FaceTable::from(vec![record(&[1], 1, 0, 0.0), record(&[1, 2], 1, 0, 0.0)]);
        assert_eq!(ragged.uniform_room(), 0);
        let empty = FaceTable::from(vec![record(&[], 0, 0, 0.0); 2]);
        assert_eq!(empty.uniform_room(), usize::MAX);
    }
}
