//! The structured encoding (spec §7.4.3): the compact grammar of §7.4.1 with a `complexForm` byte
//! before `vertices` and, per stage, a `Records` section that gives the face records either as in
//! the compact encoding (`recordForm` 0) or by the complex (`recordForm` 1): one bitmask per face
//! dimension over the complex's sorted `k`-faces, then the control points (as `f64`, or on the
//! `2^(−8w)` lattice as `w`-byte integers), then the weights.
//!
//! The decoder is the compact one (`crate::binary`), which calls [`BinaryDecoder::complex`]
//! and [`BinaryDecoder::records`] at the two members that differ; the encoder writes the shared
//! members with bincode's compact configuration, exactly as the compact writer does, and the
//! `Records` sections by hand.

use bincode::Encode;

use crate::binary::BinaryDecoder;
use crate::decode::Seg;
use crate::error::{Error, Result};
use crate::faces::FaceTable;
use crate::model::{Model, Stage, StageKind};
use crate::multi_index::binomial;
use crate::refine::{self, KuhnRefinement, RefineError, Refinement};
use crate::rules::{Location, Rule};

/// `complexForm` 0: `vertices` and `simplices` follow as in §7.4.1.
const COMPLEX_LISTED: u8 = 0;
/// `complexForm` 1: the complex by a Kuhn grid and edge bisections.
const COMPLEX_REFINED: u8 = 1;
/// `recordForm` 0: `faces` as in the compact encoding.
const RECORDS_LISTED: u8 = 0;
/// `recordForm` 1: records by masks over the complex's faces.
const RECORDS_BY_COMPLEX: u8 = 1;
/// The largest lattice `width` (bytes per integer).
const MAX_WIDTH: u8 = 4;
/// Face dimensions of a complex whose records can be given by it (`dimension` 2 or 3): 0 to 3.
const FACE_DIMS: usize = 4;

/// The sorted `k`-faces of a complex for one `k` (spec §7.4.3): `F_k` tuples of `k + 1` ids, flat,
/// in increasing lexicographic order, each once.
struct KFaces {
    /// `k + 1`.
    len: usize,
    ids: Vec<u32>,
}

impl KFaces {
    /// `F_k`.
    fn count(&self) -> usize {
        self.ids.len() / self.len
    }

    /// The `i`-th face.
    fn face(&self, i: usize) -> &[u32] {
        &self.ids[i * self.len..(i + 1) * self.len]
    }

    /// The position of `face` in the list, if it is a face of the complex.
    fn index_of(&self, face: &[u32]) -> Option<usize> {
        if face.len() != self.len {
            return None;
        }
        let (mut lo, mut hi) = (0, self.count());
        while lo < hi {
            let mid = lo + (hi - lo) / 2;
            match self.face(mid).cmp(face) {
                std::cmp::Ordering::Less => lo = mid + 1,
                std::cmp::Ordering::Greater => hi = mid,
                std::cmp::Ordering::Equal => return Some(mid),
            }
        }
        None
    }
}

/// The faces of a complex as the structured encoding numbers them, listed for a `k` when first
/// asked for. The complex is `simplices` as decoded, `dimension + 1` ids per simplex (a last,
/// incomplete group is no simplex), before any structural check: repeated ids in a simplex count
/// once, ids out of range are ids like any other. Only a `dimension` of 2 or 3 has them
/// (`recordForm` 1 is refused in the others, spec §7.4.3), so a simplex has at most 4 ids and 6
/// faces of one dimension: listing them costs memory proportional to the input.
pub(crate) struct ComplexFaces<'s> {
    dimension: u8,
    simplices: &'s [u32],
    lists: [Option<KFaces>; FACE_DIMS],
}

impl<'s> ComplexFaces<'s> {
    pub(crate) fn new(dimension: u8, simplices: &'s [u32]) -> ComplexFaces<'s> {
        ComplexFaces {
            dimension,
            simplices,
            lists: Default::default(),
        }
    }

    /// Whether records can be given by this complex (`dimension` 2 or 3).
    fn has_records(&self) -> bool {
        (2..=3).contains(&self.dimension)
    }

    /// The sorted `k`-faces (`k ≤ dimension ≤ 3`), listed on the first call.
    fn faces(&mut self, k: usize) -> &KFaces {
        let (dimension, simplices) = (self.dimension, self.simplices);
        self.lists[k].get_or_insert_with(|| list_faces(dimension, simplices, k))
    }
}

/// The `k`-faces of the simplices (`dimension` at most 3), as tuples of 4 ids (the unused tail
/// zero in all, so it does not change their order), sorted and each once.
fn list_faces(dimension: u8, simplices: &[u32], k: usize) -> KFaces {
    let len = k + 1;
    let arity = usize::from(dimension) + 1;
    debug_assert!(arity <= FACE_DIMS && len <= arity);
    let mut tuples: Vec<[u32; FACE_DIMS]> = Vec::new();
    let mut ids = Vec::with_capacity(arity);
    for simplex in simplices.chunks_exact(arity) {
        ids.clear();
        ids.extend_from_slice(simplex);
        ids.sort_unstable();
        ids.dedup();
        let m = ids.len();
        if m < len {
            continue;
        }
        // The combinations of `len` of the `m` positions, in lexicographic order.
        let mut at: Vec<usize> = (0..len).collect();
        loop {
            let mut tuple = [0u32; FACE_DIMS];
            for (slot, &p) in tuple.iter_mut().zip(&at) {
                *slot = ids[p];
            }
            tuples.push(tuple);
            let Some(j) = (0..len).rev().find(|&j| at[j] < m - len + j) else {
                break;
            };
            at[j] += 1;
            for i in j + 1..len {
                at[i] = at[i - 1] + 1;
            }
        }
    }
    tuples.sort_unstable();
    tuples.dedup();
    KFaces {
        len,
        ids: tuples
            .iter()
            .flat_map(|t| t[..len].iter().copied())
            .collect(),
    }
}

/// The number of multi-indices a `k`-face owns at degree `d`, `C(d − 1, k)` (0 when `d ≤ k`),
/// saturating: a record's count of points and weights (spec §2.5).
fn owned(degree: u32, k: usize) -> u64 {
    if u64::from(degree) <= k as u64 {
        0
    } else {
        binomial(u64::from(degree) - 1, k as u64)
    }
}

/// The lattice step `2^(−8w)`.
fn step(width: u8) -> f64 {
    f64::powi(2.0, -8 * i32::from(width))
}

/// The first coordinate of a lattice point whose other integers sum to `sum`:
/// `(2^(8w) − sum) · 2^(−8w)`, exact (both factors are exact `f64` values and the second a power
/// of two).
fn lattice_first(sum: u64, width: u8) -> f64 {
    ((1i64 << (8 * width)) - sum as i64) as f64 * step(width)
}

/// Whether `point` (`k + 1` coordinates) is a point of the `2^(−8w)` lattice as the encoding
/// stores it, bit for bit (so `−0.0` is not: its integer 0 reads back as `+0.0`).
fn on_lattice(point: &[f64], width: u8) -> bool {
    let scale = (1u64 << (8 * width)) as f64;
    let mut sum = 0u64;
    for &c in &point[1..] {
        // Scaling by a power of two is exact in the range that matters.
        let x = c * scale;
        if !(x >= 0.0 && x < scale && x.fract() == 0.0) {
            return false;
        }
        let n = x as u64;
        if (n as f64 * step(width)).to_bits() != c.to_bits() {
            return false;
        }
        sum += n;
    }
    lattice_first(sum, width).to_bits() == point[0].to_bits()
}

/// A stage's `recordForm` 1 section, as the canonical writer chooses it.
struct ByComplex {
    dims: u8,
    /// `(k, mask)`, `k` ascending.
    masks: Vec<(usize, Vec<u8>)>,
    width: u8,
}

/// Whether a stage's records can be written by the complex, and how (spec §7.4.3, canonical form):
/// they must be exactly, in order, the records of some masks, each with the counts of its face,
/// and the model's `dimension` 2 or 3 (`recordForm` 1 is allowed only there).
fn by_complex(stage: &Stage, complex: &mut ComplexFaces) -> Option<ByComplex> {
    if !complex.has_records() || stage.kind == StageKind::Monotonic && !stage.faces.is_empty() {
        return None;
    }
    let mut masks: Vec<(usize, Vec<u8>)> = Vec::new();
    let mut last: Option<(usize, usize)> = None;
    for record in stage.faces.iter() {
        let len = record.face.len();
        if len == 0 || len - 1 > usize::from(complex.dimension) {
            return None;
        }
        let k = len - 1;
        if last.is_some_and(|(lk, _)| k < lk) {
            return None;
        }
        let list = complex.faces(k);
        let i = list.index_of(record.face)?;
        if last.is_some_and(|l| (k, i) <= l) {
            return None;
        }
        let n = owned(stage.degree, k);
        let weights = if stage.kind == StageKind::Rational {
            n
        } else {
            0
        };
        if record.points.len() as u64 != n.saturating_mul(len as u64)
            || record.weights.len() as u64 != weights
        {
            return None;
        }
        if masks.last().is_none_or(|(mk, _)| *mk != k) {
            masks.push((k, vec![0; list.count().div_ceil(8)]));
        }
        let mask = &mut masks.last_mut().expect("pushed above").1;
        mask[i / 8] |= 1 << (i % 8);
        last = Some((k, i));
    }
    let dims = masks.iter().fold(0u8, |d, (k, _)| d | 1 << k);
    // The smallest width at which every point is on the lattice (1 when there are none); each
    // point on one lattice is on the finer ones too.
    let mut width = 1;
    for record in stage.faces.iter() {
        for point in record.points.chunks_exact(record.face.len()) {
            match (width..=MAX_WIDTH).find(|&w| on_lattice(point, w)) {
                Some(w) => width = w,
                None => {
                    width = 0;
                    break;
                }
            }
        }
        if width == 0 {
            break;
        }
    }
    Some(ByComplex { dims, masks, width })
}

/// Appends `value` in the compact encoding (bincode's standard configuration, little-endian).
fn put<T: Encode>(out: &mut Vec<u8>, value: &T) -> Result<()> {
    bincode::encode_into_std_write(value, out, crate::io::compact_config())
        .map(drop)
        .map_err(|e| {
            Error::format(
                Rule::Malformed,
                Location::default(),
                format!("structured: {e}"),
            )
        })
}

/// A stage's `Records` section in its canonical form.
fn encode_records(out: &mut Vec<u8>, stage: &Stage, complex: &mut ComplexFaces) -> Result<()> {
    let Some(plan) = by_complex(stage, complex) else {
        out.push(RECORDS_LISTED);
        return put(out, &stage.faces);
    };
    out.push(RECORDS_BY_COMPLEX);
    out.push(plan.dims);
    for (_, mask) in &plan.masks {
        out.extend_from_slice(mask);
    }
    out.push(plan.width);
    let w = plan.width;
    for record in stage.faces.iter() {
        for point in record.points.chunks_exact(record.face.len()) {
            if w == 0 {
                point.iter().for_each(|c| out.extend(c.to_le_bytes()));
                continue;
            }
            let scale = (1u64 << (8 * w)) as f64;
            for &c in &point[1..] {
                out.extend(&((c * scale) as u64).to_le_bytes()[..usize::from(w)]);
            }
        }
    }
    for record in stage.faces.iter() {
        record
            .weights
            .iter()
            .for_each(|x| out.extend(x.to_le_bytes()));
    }
    Ok(())
}

/// The structured payload of `model` (spec §7.4.3), canonical (§7.7). The caller has checked that
/// the model can be written (finite numbers, depth) and that its records keep their numbers.
///
/// # Errors
/// None but an encoder's own (the shared members are written by bincode).
pub(crate) fn encode(model: &Model) -> Result<Vec<u8>> {
    encode_refined(model, None).map(|(payload, _)| payload)
}

/// [`encode`], with the complex as `complexForm` 1 when `refinement` gives exactly the model's
/// `vertices` and `simplices` (every bit, in order: [`KuhnRefinement::describes`] rebuilds them),
/// else as `complexForm` 0. Also returns whether `complexForm` 1 was written.
///
/// # Errors
/// As [`encode`].
pub(crate) fn encode_refined(
    model: &Model,
    refinement: Option<&KuhnRefinement>,
) -> Result<(Vec<u8>, bool)> {
    let refinement = refinement.filter(|r| {
        (2..=3).contains(&model.dimension)
            && r.domain.len() == 2 * usize::from(model.dimension)
            && r.describes(&model.vertices, &model.simplices)
    });
    let mut out = Vec::new();
    put(&mut out, &model.version)?;
    put(&mut out, &model.dimension)?;
    put(&mut out, &model.metadata)?;
    match refinement {
        Some(r) => {
            out.push(COMPLEX_REFINED);
            put(&mut out, &r.domain)?;
            put(&mut out, &r.cells)?;
            let splits: Vec<u32> = r.splits.iter().flatten().copied().collect();
            put(&mut out, &splits)?;
            let mut kept = vec![0u8; r.kept.len().div_ceil(8)];
            for (i, _) in r.kept.iter().enumerate().filter(|(_, &k)| k) {
                kept[i / 8] |= 1 << (i % 8);
            }
            out.extend(kept);
        }
        None => {
            out.push(COMPLEX_LISTED);
            put(&mut out, &model.vertices)?;
            put(&mut out, &model.simplices)?;
        }
    }
    put(&mut out, &model.values)?;
    put(&mut out, &model.level)?;
    let mut complex = ComplexFaces::new(model.dimension, &model.simplices);
    put(&mut out, &(model.stages.len() as u64))?;
    for stage in &model.stages {
        put(&mut out, &stage.kind)?;
        put(&mut out, &stage.degree)?;
        put(&mut out, &stage.direction)?;
        put(&mut out, &stage.name)?;
        encode_records(&mut out, stage, &mut complex)?;
        put(&mut out, &stage.vertex_maps)?;
        put(&mut out, &stage.extras)?;
    }
    put(&mut out, &model.extensions_used)?;
    put(&mut out, &model.extensions_required)?;
    put(&mut out, &model.extensions)?;
    put(&mut out, &model.extras)?;
    Ok((out, refinement.is_some()))
}

/// Decodes a structured payload whose first byte is at file offset `base`. Bytes after the model
/// are an error unless `allow_trailing` (a newer minor version's fields, spec §8.1).
///
/// # Errors
/// ISM-006 at the pointer and offset of spec §7.4.3 for bytes that are not such a payload.
pub(crate) fn decode(payload: &[u8], base: u64, allow_trailing: bool) -> Result<Model> {
    BinaryDecoder::structured(payload, base).model(allow_trailing)
}

impl<const VARINT: bool> BinaryDecoder<'_, '_, VARINT> {
    /// The `Complex` of spec §7.4.3: `complexForm` (at `/vertices`), then `vertices` and
    /// `simplices` as listed (form 0) or the refinement that gives them (form 1, in dimension 2
    /// or 3 only).
    pub(crate) fn complex(&mut self, dimension: u8) -> Result<(Vec<f64>, Vec<u32>)> {
        let at = self.at;
        let form = self.member("vertices", |d| d.u8("complexForm"))?;
        match form {
            COMPLEX_LISTED => Ok((
                self.member("vertices", |d| d.f64s("vertices"))?,
                self.member("simplices", |d| d.u32s("simplices"))?,
            )),
            COMPLEX_REFINED if (2..=3).contains(&dimension) => {
                self.refined_complex(usize::from(dimension))
            }
            _ => {
                self.path.push(Seg::Key("vertices".into()));
                Err(self.fail(
                    at,
                    if form == COMPLEX_REFINED {
                        format!("complexForm 1 in dimension {dimension}; a refinement gives the complex only in dimension 2 or 3")
                    } else {
                        format!("complexForm {form}; expected 0 (vertices and simplices listed) or 1 (a refined Kuhn grid)")
                    },
                ))
            }
        }
    }

    /// An ISM-007 at payload offset `at` and the current pointer.
    fn limit(&self, at: usize, message: impl Into<String>) -> Error {
        Error::format(
            Rule::LimitExceeded,
            Location {
                pointer: Some(crate::decode::pointer_of(&self.path)),
                offset: Some(self.base + at as u64),
                ..Location::default()
            },
            message,
        )
    }

    /// `complexForm` 1 after its byte (spec §7.4.3), checked front to back: `box` decoded then
    /// checked, `cells` decoded then checked, the `⌈C₀ / 8⌉` bytes of the grid's `kept` bits
    /// after `cells`, the grid's vertex count below `2³²` (ISM-007) — all at `/vertices` — then
    /// `splits` decoded whole and its length even, each pair applied (an edge of a live slot,
    /// the midpoint's id below `2³² − 1` (ISM-007), `⌈C / 8⌉` within the bytes after `splits`),
    /// and `kept` — at `/simplices`. The work is bounded by the input: fewer than 8 live slots per
    /// byte left, 16 slots in all.
    fn refined_complex(&mut self, n: usize) -> Result<(Vec<f64>, Vec<u32>)> {
        let mut grid = self.member("vertices", |d| {
            let box_at = d.at;
            let domain = d.f64s("box")?;
            refine::check_domain(&domain, n).map_err(|e| d.fail(box_at, e.to_string()))?;
            let cells_at = d.at;
            let cells = d.u32s("cells")?;
            refine::check_cells(&cells, n).map_err(|e| d.fail(cells_at, e.to_string()))?;
            let slots = Refinement::grid_slots(&cells);
            let kept_bytes = slots.map(|c| c.div_ceil(8));
            if kept_bytes.is_none_or(|b| b > d.remaining() as u64) {
                return Err(d.fail(
                    cells_at,
                    format!(
                        "the grid's {} simplices need {} bytes of kept bits; only {} bytes remain",
                        slots.map_or("more than 2^64".into(), |c| c.to_string()),
                        kept_bytes.map_or("more than 2^61".into(), |b| b.to_string()),
                        d.remaining()
                    ),
                ));
            }
            let vertices = refine::grid_vertices(&cells);
            if vertices >= 1u128 << 32 {
                return Err(d.limit(
                    cells_at,
                    format!("the grid has {vertices} vertices; ids are below 2^32"),
                ));
            }
            Refinement::kuhn(&domain, &cells).map_err(|e| d.fail(box_at, e.to_string()))
        })?;
        self.member("simplices", |d| {
            let splits_at = d.at;
            let len = d.length(1, "splits")?;
            let mut ids = Vec::with_capacity(len);
            let mut pairs_at = Vec::with_capacity(len.div_ceil(2));
            for i in 0..len {
                if i % 2 == 0 {
                    pairs_at.push(d.at);
                }
                ids.push(d.u32("splits")?);
            }
            if len % 2 != 0 {
                return Err(d.fail(
                    splits_at,
                    format!("splits holds {len} ids; expected pairs (an even number)"),
                ));
            }
            // `kept` needs ⌈C / 8⌉ of the bytes after `splits`, and C never falls.
            let room = d.remaining() as u64;
            for (i, (pair, &at)) in ids.chunks_exact(2).zip(&pairs_at).enumerate() {
                grid.split(i, pair[0], pair[1]).map_err(|e| match e {
                    RefineError::IdsExhausted { .. } => d.limit(at, e.to_string()),
                    e => d.fail(at, e.to_string()),
                })?;
                if (grid.live() as u64).div_ceil(8) > room {
                    return Err(d.fail(
                        at,
                        format!(
                            "after split {i} the {} live simplices need {} bytes of kept bits; only {room} bytes follow splits",
                            grid.live(),
                            grid.live().div_ceil(8)
                        ),
                    ));
                }
            }
            let kept_at = d.at;
            let live = grid.live();
            let bytes = d.take(live.div_ceil(8), "kept")?;
            if live % 8 != 0 && bytes[bytes.len() - 1] >> (live % 8) != 0 {
                let last = bytes.len() - 1;
                return Err(d.fail(
                    kept_at + last,
                    format!("kept bits past the {live} live simplices are set"),
                ));
            }
            let kept: Vec<bool> = (0..live).map(|i| bytes[i / 8] >> (i % 8) & 1 == 1).collect();
            grid.model_arrays(&kept)
                .map_err(|e| d.fail(kept_at, e.to_string()))
        })
    }

    /// A stage's `Records` section, read inside `faces` (its pointer), as the stage's face table.
    pub(crate) fn records(
        &mut self,
        complex: &mut ComplexFaces,
        kind: StageKind,
        degree: u32,
    ) -> Result<FaceTable> {
        let at = self.at;
        match self.u8("recordForm")? {
            RECORDS_LISTED => self.face_table(),
            RECORDS_BY_COMPLEX if !complex.has_records() => Err(self.fail(
                at,
                format!(
                    "recordForm 1 in dimension {}; records are given by the complex only in dimension 2 or 3",
                    complex.dimension
                ),
            )),
            RECORDS_BY_COMPLEX => self.records_by_complex(complex, kind, degree),
            form => Err(self.fail(
                at,
                format!("recordForm {form}; expected 0 (records listed) or 1 (by the complex)"),
            )),
        }
    }

    /// The `recordForm` 1 section after its first byte: `dims`, the masks, `width`, the points and
    /// the weights. Every byte the points and weights take is checked to be there before the
    /// records are built.
    fn records_by_complex(
        &mut self,
        complex: &mut ComplexFaces,
        kind: StageKind,
        degree: u32,
    ) -> Result<FaceTable> {
        let dims_at = self.at;
        let dims = self.u8("dims")?;
        let n = usize::from(complex.dimension);
        if dims >> (n + 1) != 0 {
            return Err(self.fail(
                dims_at,
                format!("dims {dims:#010b} has bits above the dimension {n}"),
            ));
        }
        if kind == StageKind::Monotonic && dims != 0 {
            return Err(self.fail(
                dims_at,
                format!("dims {dims:#010b} in a monotonic stage, which has no face records"),
            ));
        }
        // (k, mask bytes, records): the masks are copied (they are bytes present) so that the
        // records can be built from them after the bytes they need were checked.
        let mut masks: Vec<(usize, Vec<u8>, u64)> = Vec::new();
        for k in (0..=n).filter(|k| dims >> k & 1 == 1) {
            let mask_at = self.at;
            // Listing the faces costs memory proportional to the simplices (at most 4 ids each);
            // a mask that runs past the payload fails at its first byte.
            let faces = complex.faces(k);
            let count = faces.count();
            let bytes = self.take(count.div_ceil(8), "a mask")?.to_vec();
            if count % 8 != 0 {
                let last = bytes.len() - 1;
                if bytes[last] >> (count % 8) != 0 {
                    return Err(self.fail(
                        mask_at + last,
                        format!("mask bits past the complex's {count} {k}-faces are set"),
                    ));
                }
            }
            let records = bytes.iter().map(|b| u64::from(b.count_ones())).sum();
            masks.push((k, bytes, records));
        }
        let width_at = self.at;
        let width = self.u8("width")?;
        if width > MAX_WIDTH {
            return Err(self.fail(
                width_at,
                format!(
                    "width {width}; expected 0 (f64) to {MAX_WIDTH} (bytes per lattice integer)"
                ),
            ));
        }
        let point_bytes = |k: usize| -> u64 {
            match width {
                0 => (k as u64 + 1) * 8,
                w => k as u64 * u64::from(w),
            }
        };
        let weight_of = |k: usize| match kind {
            StageKind::Rational => owned(degree, k),
            _ => 0,
        };
        let (mut points_len, mut needed) = (0u64, 0u64);
        for &(k, _, records) in &masks {
            let per = owned(degree, k);
            let p = records.saturating_mul(per.saturating_mul(point_bytes(k)));
            let w = records.saturating_mul(weight_of(k).saturating_mul(8));
            points_len = points_len.saturating_add(p);
            needed = needed.saturating_add(p).saturating_add(w);
        }
        if needed > self.remaining() as u64 {
            return Err(self.fail(
                width_at,
                format!(
                    "the records' points and weights need {needed} bytes; only {} remain",
                    self.remaining()
                ),
            ));
        }
        // Within the payload, so within usize.
        let (points_len, needed) = (points_len as usize, needed as usize);
        let section_at = self.at;
        let section = self.take(needed, "points and weights")?;
        let layout = Layout {
            degree,
            kind,
            width,
        };
        layout
            .records(complex, &masks, section.split_at(points_len))
            .map_err(|(r, full)| {
                Error::format(
                    Rule::LimitExceeded,
                    Location {
                        pointer: Some(format!("{}/{r}", crate::decode::pointer_of(&self.path))),
                        offset: Some(self.base + section_at as u64),
                        ..Location::default()
                    },
                    full.to_string(),
                )
            })
    }
}

/// What a `recordForm` 1 section's records hold, besides their faces.
struct Layout {
    degree: u32,
    kind: StageKind,
    width: u8,
}

impl Layout {
    /// The records of the set bits of `masks` (`(k, mask, _)`, `k` ascending), their points read
    /// from `points` and weights from `weights`, which hold exactly what they need (checked by the
    /// caller). Past the table's capacity: the record's position and why.
    fn records(
        &self,
        complex: &ComplexFaces,
        masks: &[(usize, Vec<u8>, u64)],
        (mut points, mut weights): (&[u8], &[u8]),
    ) -> std::result::Result<FaceTable, (usize, crate::faces::TableFull)> {
        let mut table = FaceTable::new();
        for (k, mask, _) in masks {
            let k = *k;
            let faces = complex.lists[k].as_ref().expect("listed with its mask");
            // Bounded by the bytes checked, or unused when no bit of this `k` is set.
            let per = owned(self.degree, k) as usize;
            let per_weights = match self.kind {
                StageKind::Rational => per,
                _ => 0,
            };
            let set = mask.iter().enumerate().flat_map(|(b, &byte)| {
                (0..8)
                    .filter(move |j| byte >> j & 1 == 1)
                    .map(move |j| b * 8 + j)
            });
            for i in set {
                let (ids, ps, ws) = table.parts_mut();
                ids.extend_from_slice(faces.face(i));
                for _ in 0..per {
                    points = self.point(k, points, ps);
                }
                let (record_weights, rest) = weights.split_at(per_weights * 8);
                ws.extend(record_weights.chunks_exact(8).map(f64_le));
                weights = rest;
                table.close_record().map_err(|full| (table.len(), full))?;
            }
        }
        Ok(table)
    }

    /// Appends the `k + 1` coordinates of the point at the start of `bytes` to `out`; the bytes
    /// after it.
    fn point<'b>(&self, k: usize, bytes: &'b [u8], out: &mut Vec<f64>) -> &'b [u8] {
        if self.width == 0 {
            let (point, rest) = bytes.split_at((k + 1) * 8);
            out.extend(point.chunks_exact(8).map(f64_le));
            return rest;
        }
        let w = usize::from(self.width);
        let (point, rest) = bytes.split_at(k * w);
        let first = out.len();
        out.push(0.0);
        let mut sum = 0u64;
        for c in point.chunks_exact(w) {
            let mut le = [0u8; 8];
            le[..w].copy_from_slice(c);
            let n = u64::from_le_bytes(le);
            sum += n;
            out.push(n as f64 * step(self.width));
        }
        out[first] = lattice_first(sum, self.width);
        rest
    }
}

/// A little-endian `f64` of 8 bytes.
fn f64_le(bytes: &[u8]) -> f64 {
    f64::from_le_bytes(bytes.try_into().expect("8 bytes"))
}
