//! The checked, indexed model: the topology of the complex and every stage's control net in flat,
//! struct-of-arrays tables, built once by the structural check and shared by every crate.
//!
//! [`Model`] is the file's serde image; [`IndexedModel`] wraps it the way gltf-rs's `Document`
//! wraps `gltf_json::Root`: immutable, with typed ids and O(1) addressing, so nobody above this
//! crate enumerates faces or hashes face keys.
//!
//! - **Faces.** Dimension 0 faces are the vertices (a [`FaceId`] of dimension 0 has the vertex id
//!   as index) and dimension `n` faces are the top simplices (index = simplex id); the faces of
//!   dimensions `1 … n−1` are numbered in increasing lexicographic order of their sorted vertex ids
//!   ([`Topology::face_vertices`]).
//! - **Simplex → faces.** [`Topology::simplex_face`] gives, for simplex `s` and the `j`-th subset of
//!   its local positions ([`local_faces`]), the face's index in O(1).
//! - **Neighbours.** [`Topology::neighbour`] gives the simplex across the facet opposite a local
//!   vertex, or `None` on the boundary.
//! - **Stage tables.** [`StageTable`] gives, per face dimension `k`, the record (if any) of every
//!   face of that dimension, and through it the face's owned control points (`(k + 1) · C(d − 1, k)`
//!   numbers, the identity's where the file has no record) and weights (`C(d − 1, k)`, rational
//!   stages) in O(1). The numbers are not copied: they stay in the stage's flat
//!   [`crate::FaceTable`] (one contiguous array each, the layout a numpy view wants). A monotonic
//!   stage gives `d + 1` coefficients per vertex. A stage's table is built on its first use.
//!
//! Built in parallel (rayon), one pass over each vertex's star for all face dimensions: every face
//! is found from its smallest vertex, so the only sorting is of a star's few dozen entries (linear
//! in the complex overall), and no face or simplex allocates.

use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, OnceLock};

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::faces::FaceTable;
use crate::model::{Model, Stage, StageKind};
use crate::multi_index::owned_count;
use crate::rules::Severity;

/// "No such entity": the value of an absent neighbour, record or face in the flat tables.
pub const NONE: u32 = u32::MAX;

/// A vertex of the complex.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct VertexId(pub u32);

/// A top simplex of the complex.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct SimplexId(pub u32);

/// A face of the complex: its dimension `k` (`k + 1` vertices) and its index among the faces of
/// that dimension.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct FaceId {
    /// Dimension `k` of the face, `0 ≤ k ≤ n`.
    pub dim: u8,
    /// Index among the faces of dimension `k`.
    pub index: u32,
}

/// The subsets of `size` local positions of a simplex with `m` vertices, in lexicographic order of
/// the position lists (`m ≤ 4`); `[0, 1], [0, 2], [0, 3], [1, 2], …` for edges of a tetrahedron.
/// Entries past `size` are unused.
pub fn local_faces(m: usize, size: usize) -> &'static [[u8; 4]] {
    static TABLES: OnceLock<Vec<Vec<Vec<[u8; 4]>>>> = OnceLock::new();
    let tables = TABLES.get_or_init(|| {
        (0..=4usize)
            .map(|m| {
                (0..=m)
                    .map(|size| {
                        let mut out: Vec<[u8; 4]> = (0u32..1 << m)
                            .filter(|mask| mask.count_ones() as usize == size)
                            .map(|mask| {
                                let mut f = [0u8; 4];
                                let mut len = 0;
                                for i in 0..m {
                                    if mask & (1 << i) != 0 {
                                        f[len] = i as u8;
                                        len += 1;
                                    }
                                }
                                f
                            })
                            .collect();
                        out.sort_unstable_by(|a, b| a[..size].cmp(&b[..size]));
                        out
                    })
                    .collect()
            })
            .collect()
    });
    if m > 4 || size > m {
        return &[];
    }
    &tables[m][size]
}

/// One face of a simplex given by its vertex list, named by the bit mask of its local positions:
/// what code that works on a simplex outside an [`IndexedModel`] needs of a face — a stage's
/// records looked up by sorted ids (`ism-geom`'s free-standing stages), the fitter's working
/// complex (it changes every round, so it is never indexed), a control net filled in local order.
/// [`simplex_faces`] enumerates them; an indexed model's faces come from [`Topology`] instead.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LocalFace {
    /// Bit `i` is set when local position `i` is a vertex of the face.
    pub mask: u8,
    len: u8,
    positions: [u8; 4],
    ids: [u32; 4],
}

impl LocalFace {
    /// The face of the simplex with vertex ids `simplex` (at most 4) at the local positions whose
    /// bits are set in `mask` (positions past the simplex are ignored).
    #[inline]
    pub fn of_mask(simplex: &[u32], mask: u8) -> LocalFace {
        let mut face = LocalFace {
            mask,
            len: 0,
            positions: [0; 4],
            ids: [0; 4],
        };
        for (p, &id) in simplex.iter().enumerate().take(4) {
            if mask >> p & 1 == 1 {
                // Insertion by (id, position): the positions end up ordered by vertex id (ties,
                // a simplex repeating a vertex, by position).
                let mut at = face.len as usize;
                while at > 0 && face.ids[at - 1] > id {
                    face.ids[at] = face.ids[at - 1];
                    face.positions[at] = face.positions[at - 1];
                    at -= 1;
                }
                face.ids[at] = id;
                face.positions[at] = p as u8;
                face.len += 1;
            }
        }
        face
    }

    /// Number of vertices (`k + 1` for a `k`-face).
    #[inline]
    pub fn len(&self) -> usize {
        usize::from(self.len)
    }

    /// Whether the face has no vertex (mask 0).
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The face's vertex ids, ascending: the key the file's face records use.
    #[inline]
    pub fn ids(&self) -> &[u32] {
        &self.ids[..self.len()]
    }

    /// The face's local positions in the simplex, ordered by vertex id (`positions()[j]` holds
    /// `ids()[j]`): the face's own vertex order `t_0 < … < t_k`.
    #[inline]
    pub fn positions(&self) -> &[u8] {
        &self.positions[..self.len()]
    }
}

/// The faces with at least `min_len` vertices of the simplex with vertex ids `simplex` (at most 4
/// ids), in increasing order of their position masks (`{0}, {1}, {0, 1}, {2}, {0, 2}, …`): the one
/// enumeration of a simplex's faces for code that has a vertex list rather than an
/// [`IndexedModel`].
///
/// ```
/// use ism_format::indexed::simplex_faces;
/// let edges: Vec<Vec<u32>> = simplex_faces(&[7, 2, 5], 2)
///     .filter(|f| f.len() == 2)
///     .map(|f| f.ids().to_vec())
///     .collect();
/// assert_eq!(edges, [vec![2, 7], vec![5, 7], vec![2, 5]]);
/// ```
pub fn simplex_faces(simplex: &[u32], min_len: usize) -> impl Iterator<Item = LocalFace> + '_ {
    let m = simplex.len().min(4);
    (1u8..(1 << m))
        .filter(move |&mask| usize::from(BITS[usize::from(mask)]) >= min_len)
        .map(move |mask| LocalFace::of_mask(simplex, mask))
}

/// A facet shared by two simplices: its sorted vertex ids and, per side, the simplex and the local
/// position opposite the facet ([`shared_facets`]).
pub type SharedFacet = (Vec<u32>, [(usize, usize); 2]);

/// The facets shared by exactly two simplices of a complex given as vertex lists (`m` ids per
/// simplex, `2 ≤ m ≤ 4`): `(sorted facet ids, [(simplex, local position opposite the facet); 2])`,
/// the lower simplex first, in increasing order of the ids; a facet held by one simplex (the
/// boundary) or by more than two is left out. The pairing [`Topology::neighbour`] gives an
/// indexed model, for complexes that are not one (the fitters' working complexes, a model
/// being edited).
///
/// ```
/// use ism_format::indexed::shared_facets;
/// // Two triangles of a square share the diagonal 0–2.
/// let pairs = shared_facets(3, &[0, 1, 2, 0, 2, 3]);
/// assert_eq!(pairs, [(vec![0, 2], [(0, 1), (1, 2)])]);
/// ```
pub fn shared_facets(m: usize, simplices: &[u32]) -> Vec<SharedFacet> {
    if !(2..=4).contains(&m) {
        return Vec::new();
    }
    // (facet ids padded with u32::MAX, simplex, opposite position): sorted, a facet's sides are
    // adjacent and in (simplex, position) order.
    let mut sides: Vec<([u32; 3], usize, usize)> = Vec::with_capacity(simplices.len());
    for (s, ids) in simplices.chunks_exact(m).enumerate() {
        for skip in 0..m {
            let mut key = [u32::MAX; 3];
            let facet = LocalFace::of_mask(ids, ((1u8 << m) - 1) & !(1 << skip));
            key[..m - 1].copy_from_slice(facet.ids());
            sides.push((key, s, skip));
        }
    }
    sides.sort_unstable();
    let mut out = Vec::new();
    let mut i = 0;
    while i < sides.len() {
        let mut j = i + 1;
        while j < sides.len() && sides[j].0 == sides[i].0 {
            j += 1;
        }
        if j - i == 2 {
            let (a, b) = (&sides[i], &sides[i + 1]);
            out.push((a.0[..m - 1].to_vec(), [(a.1, a.2), (b.1, b.2)]));
        }
        i = j;
    }
    out
}

/// Vertices per task of the topology build: a task numbers the faces whose smallest vertex lies in
/// its range. Small enough to balance the cores, large enough to amortise a task (a few hundred
/// stars of tens of simplices each).
const STAR_CHUNK: usize = 512;

/// Tasks run together before their faces are appended to the tables: the temporary memory is a
/// batch's faces (~32 k vertices' worth), not the whole complex's.
const CHUNK_BATCH: usize = 64;

/// A defect of the facet pairing found while indexing (reported by the structural check).
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) enum FacetDefect {
    /// More than two simplices share the facet; members in (side, simplex) order.
    Overshared { face: Vec<u32>, simplices: Vec<u32> },
    /// Two simplices lie on the same side of their shared facet.
    Overlap {
        face: Vec<u32>,
        first: u32,
        second: u32,
    },
}

/// The topology of the complex: faces of every dimension, simplex → face ids, facet neighbours and
/// vertex → simplex incidence.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Topology {
    n: usize,
    num_vertices: usize,
    num_simplices: usize,
    /// Per dimension `k` (`1 ≤ k < n`): sorted vertex ids of each face, `k + 1` per face, faces in
    /// increasing lexicographic order. Empty for `k = 0` and `k = n` (implicit).
    faces: Vec<Vec<u32>>,
    /// Per dimension `k` (`1 ≤ k < n`): `C(n + 1, k + 1)` face indices per simplex, in the order of
    /// [`local_faces`]. Empty for `k = 0` and `k = n` (implicit), and when only checking.
    simplex_faces: Vec<Vec<u32>>,
    /// `n + 1` per simplex: the simplex across the facet opposite each local vertex, or [`NONE`].
    /// Empty when only checking.
    neighbours: Vec<u32>,
    /// Per dimension `k` (`1 ≤ k ≤ n`): `nv + 1` offsets; the faces whose smallest vertex is `v`
    /// are `first_face[k][v] .. first_face[k][v + 1]` (for `k = n`, positions in `top_order`).
    first_face: Vec<Vec<u32>>,
    /// The simplices in increasing order of their sorted vertex ids (then orientation, then id):
    /// with `first_face[n]`, a top face is found by a binary search among a vertex's few.
    top_order: Vec<u32>,
    /// Vertex → incident simplices, compressed rows (`incidence_start` has `nv + 1` entries).
    incidence_start: Vec<usize>,
    incidence: Vec<u32>,
    /// Per dimension `k` (`1 ≤ k ≤ n`): the number of faces (index 0 unused).
    face_counts: Vec<usize>,
}

/// Number of set bits of each 4-bit mask.
const BITS: [u8; 16] = [0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4];

/// Bit `x` is the parity of the number of set bits of `x < 64` (the baseline x86-64 target has no
/// popcnt instruction).
const PARITY: u64 = {
    let mut table = 0u64;
    let mut x = 0;
    while x < 64 {
        table |= ((x as u64).count_ones() as u64 & 1) << x;
        x += 1;
    }
    table
};

/// Bit of the local position pair `(p, q)` in a simplex with at most 4 vertices.
const PAIR: [[u8; 4]; 4] = [[0, 0, 1, 2], [0, 0, 3, 4], [1, 3, 0, 5], [2, 4, 5, 0]];

/// Tables over bit masks of local positions of a simplex with `m ≤ 4` vertices.
struct Masks {
    /// Index of the subset among [`local_faces`]`(m, popcount)`.
    local: [u8; 16],
    /// The [`PAIR`] bits of the position pairs inside the subset.
    pairs: [u8; 16],
}

impl Masks {
    fn new(m: usize) -> Masks {
        let mut masks = Masks {
            local: [0; 16],
            pairs: [0; 16],
        };
        for size in 1..=m {
            for (j, pos) in local_faces(m, size).iter().enumerate() {
                let mask = pos[..size].iter().fold(0usize, |a, &p| a | 1 << p);
                masks.local[mask] = j as u8;
            }
        }
        for (mask, pairs) in masks.pairs.iter_mut().enumerate().take(1 << m) {
            for (p, row) in PAIR.iter().enumerate().take(m) {
                for (q, &bit) in row.iter().enumerate().take(m).skip(p + 1) {
                    if mask >> p & 1 == 1 && mask >> q & 1 == 1 {
                        *pairs |= 1 << bit;
                    }
                }
            }
        }
        masks
    }
}

/// A face met in the star of its smallest vertex `v`: the ids after `v` packed big-endian into
/// `key` (so `u128` order is lexicographic), then (side, simplex) in `tail` — the order in which
/// defects are reported — and the face's local index and (facets) the opposite local position.
#[derive(Clone, Copy)]
struct Entry {
    key: u128,
    tail: u64,
    local: u8,
    opposite: u8,
}

impl Entry {
    /// For faces of at most three vertices (`key`'s top and bottom 32 bits zero): one `u128` whose
    /// integer order is the (key, tail) order — ids after `v`, then tail, then local and opposite
    /// (a face meets each simplex once, so (key, tail) is already unique).
    #[inline]
    fn pack(&self) -> u128 {
        debug_assert_eq!(
            self.key & (u128::from(u32::MAX) | u128::from(u32::MAX) << 96),
            0
        );
        // `local` < 16, `opposite` ≤ 8 (8 for a top face: no position is omitted).
        self.key << 32
            | u128::from(self.tail) << 8
            | u128::from(self.local & 15) << 4
            | u128::from(self.opposite & 15)
    }
    #[inline]
    fn unpack(p: u128) -> Entry {
        Entry {
            key: (p >> 64) << 32,
            tail: (p >> 8) as u64 & ((1 << 33) - 1),
            local: (p >> 4) as u8 & 15,
            opposite: p as u8 & 15,
        }
    }
    fn simplex(&self) -> u32 {
        self.tail as u32
    }
    fn side(&self) -> bool {
        self.tail >> 32 != 0
    }
    /// The face's vertex ids after the smallest (`k` of them).
    fn rest(&self, k: usize) -> impl Iterator<Item = u32> + '_ {
        (0..k).map(move |i| (self.key >> (64 - 32 * i)) as u32)
    }
}

/// What one task found for its vertex range, appended in vertex order to the tables.
struct ChunkOut {
    /// Per dimension `k` (`1 ≤ k < n`): vertex ids of the faces, `k + 1` each.
    faces: Vec<Vec<u32>>,
    /// Per dimension `k` (`1 ≤ k ≤ n`): how many faces have each vertex of the range as smallest.
    counts: Vec<Vec<u32>>,
    /// Top simplices with their smallest vertex in the range, in `top_order`.
    top: Vec<u32>,
    duplicates: Vec<(u32, u32)>,
    defects: Vec<FacetDefect>,
    /// Check-only scan: per scanned stage, the records of the range's vertices.
    lookups: Vec<RecordLookup>,
}

/// What the check-only scan found of one stage's face records (see [`Topology::build`]).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub(crate) struct RecordLookup {
    /// The records naming no face of the complex, ascending.
    pub missing: Vec<u32>,
    /// `(record, first)`: a record naming the same face as the earlier record `first` (the first
    /// one naming it), ascending by record.
    pub repeats: Vec<(u32, u32)>,
}

/// A topology with the duplicate simplices, the facet defects and (check-only scan) the record
/// lookups of each table scanned.
type Scanned = (
    Topology,
    Vec<(u32, u32)>,
    Vec<FacetDefect>,
    Vec<RecordLookup>,
);

/// Shared state of a topology build.
struct Build<'a> {
    model: &'a Model,
    n: usize,
    incidence_start: &'a [usize],
    incidence: &'a [u32],
    masks: Masks,
    /// Per dimension `k`: the task-local face ids of each simplex's faces (rebased afterwards);
    /// empty when only checking. Every slot is written by the one task owning the face's smallest
    /// vertex, so relaxed atomic stores (plain moves) suffice.
    simplex_faces: Vec<Vec<AtomicU32>>,
    neighbours: Vec<AtomicU32>,
    /// Check-only scan (`Some`): no face tables are kept; the records of these face tables (their
    /// first ids non-decreasing, all below the vertex count) are looked up in the star of their
    /// first vertex instead, and in 3D the edges are only collected per vertex (a vertex's higher
    /// neighbours), not sorted as entries.
    scan: Option<&'a [&'a FaceTable]>,
}

impl Build<'_> {
    /// Numbers the faces whose smallest vertex is in `range`: one pass over each vertex's star
    /// finds them in every dimension; a face is only ever sorted among its vertex's few.
    fn chunk(&self, range: std::ops::Range<usize>) -> ChunkOut {
        // The simplex size as a constant: the per-simplex loops unroll.
        match self.n {
            0 => self.chunk_of::<1>(range),
            1 => self.chunk_of::<2>(range),
            2 => self.chunk_of::<3>(range),
            _ => self.chunk_of::<4>(range),
        }
    }

    /// [`Build::chunk`] for simplices of `M = n + 1 ≤ 4` vertices.
    fn chunk_of<const M: usize>(&self, range: std::ops::Range<usize>) -> ChunkOut {
        debug_assert_eq!(self.n + 1, M);
        let model = self.model;
        let (n, m) = (M - 1, M);
        let full = !self.neighbours.is_empty();
        let scan = self.scan.unwrap_or(&[]);
        let scanning = self.scan.is_some();
        // Scanning in 3D: edges are a vertex's higher neighbours, collected, not entries.
        let near_edges = scanning && n == 3;
        let mut out = ChunkOut {
            faces: vec![Vec::new(); n],
            counts: vec![Vec::with_capacity(range.len()); n + 1],
            top: Vec::new(),
            duplicates: Vec::new(),
            defects: Vec::new(),
            lookups: vec![RecordLookup::default(); scan.len()],
        };
        let mut buf: Vec<Vec<Entry>> = vec![Vec::new(); n + 1];
        // Faces of at most three vertices, packed one `u128` each (`Entry::pack`) for sorting.
        let mut packed: Vec<Vec<u128>> = vec![Vec::new(); n + 1];
        // Scanning: per dimension, the keys of the vertex's faces, ascending (top faces: with
        // repeats); in 3D the edges' keys are the higher neighbours in `near`.
        let mut keys: Vec<Vec<u128>> = vec![Vec::new(); n + 1];
        let mut near: Vec<u32> = Vec::new();
        // Scanning: each stage's next record (records of a vertex are consecutive).
        let mut cursor: Vec<usize> = scan
            .iter()
            .map(|t| {
                // The first record whose first id is at least the range's first vertex.
                let (mut lo, mut hi) = (0, t.len());
                while lo < hi {
                    let mid = lo + (hi - lo) / 2;
                    if (t.face(mid)[0] as usize) < range.start {
                        lo = mid + 1;
                    } else {
                        hi = mid;
                    }
                }
                lo
            })
            .collect();
        // Scanning: per dimension and face of the vertex, the first record naming it, as
        // `(visit, record)`: an entry of an earlier (vertex, stage) visit counts as none.
        let mut first: Vec<Vec<(u32, u32)>> = vec![Vec::new(); n + 1];
        let mut visit = 0u32;
        let all = (1u8 << m) - 1;
        for v in range {
            let v32 = v as u32;
            for b in &mut buf {
                b.clear();
            }
            for b in &mut packed {
                b.clear();
            }
            near.clear();
            let star = &self.incidence[self.incidence_start[v]..self.incidence_start[v + 1]];
            for &s in star {
                let ids: &[u32; M] = model.simplex(s as usize).try_into().expect("n + 1 ids");
                let (mut pv, mut higher, mut inv) = (0u8, 0u8, 0u8);
                for (p, &id) in ids.iter().enumerate() {
                    if id == v32 {
                        pv = p as u8;
                    } else if id > v32 {
                        higher |= 1 << p;
                        if near_edges {
                            near.push(id);
                        }
                    }
                }
                if higher == 0 {
                    // v is the simplex's largest vertex: no face has it as smallest.
                    continue;
                }
                if near_edges && BITS[higher as usize] == 1 {
                    // v is the second largest: its one face here is an edge, already collected.
                    continue;
                }
                for p in 0..M {
                    for q in p + 1..M {
                        if ids[p] > ids[q] {
                            inv |= 1 << PAIR[p][q];
                        }
                    }
                }
                // Every face with smallest vertex v: v and a nonempty subset of the higher ones.
                let mut t = higher;
                while t != 0 {
                    let face = t | 1 << pv;
                    // Masks have at most 4 bits: a table instead of a software popcount (the
                    // baseline x86-64 target has no popcnt instruction).
                    let k = BITS[t as usize] as usize;
                    if near_edges && k == 1 {
                        t = (t - 1) & higher;
                        continue;
                    }
                    let mut rest = [0u32; 3];
                    let mut bits = t;
                    for slot in rest.iter_mut().take(k) {
                        *slot = ids[bits.trailing_zeros() as usize];
                        bits &= bits - 1;
                    }
                    // At most three ids: a sorting network, no call into the general sort.
                    let swap = |r: &mut [u32; 3], a: usize, b: usize| {
                        if r[a] > r[b] {
                            r.swap(a, b);
                        }
                    };
                    if k >= 2 {
                        swap(&mut rest, 0, 1);
                    }
                    if k == 3 {
                        swap(&mut rest, 1, 2);
                        swap(&mut rest, 0, 1);
                    }
                    let key =
                        u128::from(rest[0]) << 64 | u128::from(rest[1]) << 32 | u128::from(rest[2]);
                    // Orientation parity of the face's ids in local order; a facet carries the
                    // sign (-1)^i of the local vertex i it omits.
                    let odd = PARITY >> (self.masks.pairs[face as usize] & inv) & 1 == 1;
                    let opposite = (!face & all).trailing_zeros() as u8;
                    let side = if k == n {
                        odd ^ (m % 2 == 1)
                    } else {
                        k == n - 1 && odd ^ (opposite % 2 == 1)
                    };
                    let entry = Entry {
                        key,
                        tail: u64::from(side) << 32 | u64::from(s),
                        local: self.masks.local[face as usize],
                        opposite,
                    };
                    if k <= 2 {
                        packed[k].push(entry.pack());
                    } else {
                        buf[k].push(entry);
                    }
                    t = (t - 1) & higher;
                }
            }
            for (k, entries) in buf.iter_mut().enumerate().skip(1) {
                if near_edges && k == 1 {
                    near.sort_unstable();
                    near.dedup();
                    keys[k].clear();
                    keys[k].extend(near.iter().map(|&w| u128::from(w) << 64));
                    out.counts[k].push(near.len() as u32);
                    continue;
                }
                if scanning && k <= 2 && k < n {
                    // Only the groups matter (their keys and, for facets, their defects): read
                    // straight from the packed integers, unpacking only a defective group.
                    let ps = &mut packed[k];
                    ps.sort_unstable();
                    keys[k].clear();
                    let mut i = 0;
                    while i < ps.len() {
                        let key = ps[i] >> 64;
                        let mut j = i + 1;
                        while j < ps.len() && ps[j] >> 64 == key {
                            j += 1;
                        }
                        keys[k].push(Entry::unpack(ps[i]).key);
                        // Two members on opposite sides (bit 40: the side in `tail`), or one.
                        let paired =
                            j - i == 1 || (j - i == 2 && (ps[i] ^ ps[i + 1]) >> 40 & 1 == 1);
                        if k == n - 1 && !paired {
                            let group: Vec<Entry> =
                                ps[i..j].iter().map(|&p| Entry::unpack(p)).collect();
                            out.defects.extend(facet_defect(v32, k, &group));
                        }
                        i = j;
                    }
                    out.counts[k].push(keys[k].len() as u32);
                    continue;
                }
                if k <= 2 {
                    // Sorted as plain integers (half the bytes moved, one comparison each).
                    let keys = &mut packed[k];
                    keys.sort_unstable();
                    entries.extend(keys.iter().map(|&p| Entry::unpack(p)));
                } else {
                    entries.sort_unstable_by_key(|e| (e.key, e.tail));
                }
                if scanning {
                    keys[k].clear();
                }
                if k == n {
                    for w in entries.windows(2) {
                        if w[0].key == w[1].key {
                            out.duplicates.push((w[1].simplex(), w[0].simplex()));
                        }
                    }
                    if scanning {
                        keys[k].extend(entries.iter().map(|e| e.key));
                    } else {
                        out.top.extend(entries.iter().map(Entry::simplex));
                    }
                    out.counts[k].push(entries.len() as u32);
                    continue;
                }
                let per = local_faces(m, k + 1).len();
                let mut count = 0u32;
                let mut i = 0;
                while i < entries.len() {
                    let mut j = i + 1;
                    while j < entries.len() && entries[j].key == entries[i].key {
                        j += 1;
                    }
                    let group = &entries[i..j];
                    let id = if scanning {
                        keys[k].push(group[0].key);
                        0
                    } else {
                        let id = (out.faces[k].len() / (k + 1)) as u32;
                        out.faces[k].push(v32);
                        out.faces[k].extend(group[0].rest(k));
                        id
                    };
                    if full {
                        let table = &self.simplex_faces[k];
                        for e in group {
                            table[e.simplex() as usize * per + e.local as usize]
                                .store(id, Ordering::Relaxed);
                        }
                    }
                    if k == n - 1 {
                        out.defects.extend(facet_defect(v32, k, group));
                        if let [a, b] = group {
                            if a.side() != b.side() && full {
                                self.neighbours[a.simplex() as usize * m + a.opposite as usize]
                                    .store(b.simplex(), Ordering::Relaxed);
                                self.neighbours[b.simplex() as usize * m + b.opposite as usize]
                                    .store(a.simplex(), Ordering::Relaxed);
                            }
                        }
                    }
                    count += 1;
                    i = j;
                }
                out.counts[k].push(count);
            }
            // Scanning: the records whose first id is v, looked up among v's faces (records
            // mostly come in the faces' order: each search starts where the last one ended).
            for (i, table) in scan.iter().enumerate() {
                let lookup = &mut out.lookups[i];
                if cursor[i] >= table.len() || table.face(cursor[i])[0] != v32 {
                    continue;
                }
                visit = visit.wrapping_add(1);
                for (k, f) in first.iter_mut().enumerate() {
                    f.resize(
                        f.len().max(keys[k].len().max(1)),
                        (visit.wrapping_sub(1), 0),
                    );
                }
                let mut pos = [0usize; 4];
                while cursor[i] < table.len() {
                    let r = cursor[i];
                    let face = table.face(r);
                    if face[0] != v32 {
                        break;
                    }
                    cursor[i] += 1;
                    let size = face.len();
                    let found = if size > m || face.windows(2).any(|w| w[0] >= w[1]) {
                        None
                    } else if size == 1 {
                        (!star.is_empty()).then_some(0)
                    } else {
                        let mut rest = [0u32; 3];
                        rest[..size - 1].copy_from_slice(&face[1..]);
                        let key = u128::from(rest[0]) << 64
                            | u128::from(rest[1]) << 32
                            | u128::from(rest[2]);
                        let group = &keys[size - 1];
                        let mut at = pos[size - 1];
                        if at > 0 && group[at - 1] >= key {
                            at = group.partition_point(|&x| x < key);
                        } else {
                            while at < group.len() && group[at] < key {
                                at += 1;
                            }
                        }
                        pos[size - 1] = at;
                        (group.get(at) == Some(&key)).then_some(at)
                    };
                    match found {
                        Some(at) => {
                            let slot = &mut first[size - 1][at];
                            if slot.0 == visit {
                                lookup.repeats.push((r as u32, slot.1));
                            } else {
                                *slot = (visit, r as u32);
                            }
                        }
                        None => lookup.missing.push(r as u32),
                    }
                }
            }
        }
        out
    }
}

/// The defect of a facet (`k = n − 1`) with smallest vertex `v` met by the simplices of `group`
/// (sorted entries of one key), if any: more than two simplices, or two distinct ones on the same
/// side.
fn facet_defect(v: u32, k: usize, group: &[Entry]) -> Option<FacetDefect> {
    let face = || std::iter::once(v).chain(group[0].rest(k)).collect();
    if group.len() > 2 {
        Some(FacetDefect::Overshared {
            face: face(),
            simplices: group.iter().map(Entry::simplex).collect(),
        })
    } else if let [a, b] = group {
        (a.side() == b.side() && a.simplex() != b.simplex()).then(|| FacetDefect::Overlap {
            face: face(),
            first: a.simplex(),
            second: b.simplex(),
        })
    } else {
        None
    }
}

/// A vector of `len` copies of `x`, or empty when `len` is 0: written on every core, so the fresh
/// pages are faulted in in parallel.
fn atomics(len: usize, x: u32) -> Vec<AtomicU32> {
    (0..len)
        .into_par_iter()
        .map(|_| AtomicU32::new(x))
        .collect()
}

/// Appends `parts` to `table`, in order, on every core: the new elements are first written in
/// parallel (faulting in the fresh pages), then each part is copied to its place in parallel.
fn append_parallel<T: Copy + Default + Send + Sync>(table: &mut Vec<T>, parts: &[&[T]]) {
    let old = table.len();
    let add: usize = parts.iter().map(|p| p.len()).sum();
    table.par_extend(rayon::iter::repeat_n(T::default(), add));
    let mut rest = &mut table[old..];
    let mut pairs = Vec::with_capacity(parts.len());
    for &part in parts {
        let (head, tail) = std::mem::take(&mut rest).split_at_mut(part.len());
        pairs.push((head, part));
        rest = tail;
    }
    pairs
        .into_par_iter()
        .for_each(|(dst, src)| dst.copy_from_slice(src));
}

/// Vertex → incident simplices (ascending), compressed rows, without the simplices flagged in
/// `skip`: a counting sort over blocks of simplices on every core — each block counts its
/// simplices per vertex, and fills its own slots of each row in order — so the rows are ascending
/// whatever the number of blocks or threads.
fn incidence(model: &Model, skip: &[bool]) -> (Vec<usize>, Vec<u32>) {
    let nv = model.num_vertices();
    let ns = model.num_simplices();
    let ok = |s: usize| !skip.get(s).copied().unwrap_or(false);
    // One block per thread (at most 8: each holds a counter per vertex).
    let blocks = rayon::current_num_threads().clamp(1, 8);
    let per = ns.div_ceil(blocks).max(1);
    let range = |b: usize| b * per..ns.min((b + 1) * per);
    let mut cursors: Vec<Vec<u32>> = (0..blocks)
        .into_par_iter()
        .map(|b| {
            let mut count = vec![0u32; nv];
            for s in range(b).filter(|&s| ok(s)) {
                for &v in model.simplex(s) {
                    count[v as usize] += 1;
                }
            }
            count
        })
        .collect();
    // Row starts, and each block's first slot within each row (the counts before it).
    let mut start = Vec::with_capacity(nv + 1);
    let mut total = 0usize;
    start.push(0);
    for v in 0..nv {
        let mut within = 0u32;
        for cursor in &mut cursors {
            let c = cursor[v];
            cursor[v] = within;
            within += c;
        }
        total += within as usize;
        start.push(total);
    }
    let slots = atomics(total, 0);
    // Every slot is written by exactly one block: relaxed stores are plain moves.
    cursors.par_iter_mut().enumerate().for_each(|(b, cursor)| {
        for s in range(b).filter(|&s| ok(s)) {
            for &v in model.simplex(s) {
                let v = v as usize;
                slots[start[v] + cursor[v] as usize].store(s as u32, Ordering::Relaxed);
                cursor[v] += 1;
            }
        }
    });
    drop(cursors);
    let incidence = slots.into_iter().map(AtomicU32::into_inner).collect();
    (start, incidence)
}

impl Topology {
    /// Indexes the complex of `model`, skipping the simplices flagged in `skip` (those that repeat a
    /// vertex id). The arrays must be well-formed (lengths, index ranges): the structural check
    /// calls this only then. Returns the topology, the duplicate simplices (each with the first
    /// simplex of the same vertex set, in sorted-key order) and the facet defects. `full = false`
    /// (a check that keeps nothing) leaves out the simplex → face tables and the neighbours.
    pub(crate) fn build(
        model: &Model,
        skip: &[bool],
        full: bool,
    ) -> (Topology, Vec<(u32, u32)>, Vec<FacetDefect>) {
        let (topology, duplicates, defects, _) =
            Topology::build_in_blocks(model, skip, STAR_CHUNK, full, None);
        (topology, duplicates, defects)
    }

    /// The check-only scan: [`Topology::build`] without `full`, keeping no face tables (the
    /// topology only counts faces: [`Topology::num_faces`]; [`Topology::find`] finds nothing of
    /// dimensions `1 … n`), and looking up instead the records of `tables` in the star of their
    /// first vertex. Every record of every table must name at least one id, the first ids
    /// non-decreasing and below the vertex count ([`Topology::scannable`]). Also returns, per
    /// table, the records naming no face and the repeated faces, as [`Topology::find`] and a pass
    /// over the records in order would find them.
    pub(crate) fn scan(model: &Model, skip: &[bool], tables: &[&FaceTable]) -> Scanned {
        Topology::build_in_blocks(model, skip, STAR_CHUNK, false, Some(tables))
    }

    /// Whether [`Topology::scan`] can look up the records of `table`: every record names at least
    /// one id, the first ids are non-decreasing and below `num_vertices`.
    pub(crate) fn scannable(table: &FaceTable, num_vertices: usize) -> bool {
        let ids = table.all_face_ids();
        if let Some([size, ..]) = table.uniform_lengths() {
            // Records of `size` ids each: their first ids are every `size`-th.
            return size > 0
                && ids.par_chunks(size).enumerate().all(|(r, face)| {
                    (face[0] as usize) < num_vertices && (r == 0 || ids[(r - 1) * size] <= face[0])
                });
        }
        let offsets = table.face_offsets();
        offsets.par_windows(2).enumerate().all(|(r, w)| {
            let a = ids.get(w[0] as usize).copied().unwrap_or(u32::MAX);
            w[1] > w[0]
                && (a as usize) < num_vertices
                && (r == 0 || ids[offsets[r - 1] as usize] <= a)
        })
    }

    /// [`Topology::build`] with `block` vertices per task (any `block ≥ 1` gives the same result;
    /// tests use small blocks).
    fn build_in_blocks(
        model: &Model,
        skip: &[bool],
        block: usize,
        full: bool,
        scan: Option<&[&FaceTable]>,
    ) -> Scanned {
        let keep = scan.is_none();
        let n = model.dim();
        let m = n + 1;
        let nv = model.num_vertices();
        let ns = model.num_simplices();

        // Vertex → incident simplices first: every face is then found from its smallest vertex,
        // so all the sorting below is of a vertex's star (tens of entries), in parallel, instead
        // of one global sort of millions of keys.
        let (incidence_start, incidence) = incidence(model, skip);

        let per = |k: usize| local_faces(m, k + 1).len();
        let build = Build {
            model,
            n,
            incidence_start: &incidence_start,
            incidence: &incidence,
            masks: Masks::new(m),
            simplex_faces: (0..n)
                .map(|k| {
                    let len = if full && k >= 1 { ns * per(k) } else { 0 };
                    atomics(len, NONE)
                })
                .collect(),
            neighbours: atomics(if full { ns * m } else { 0 }, NONE),
            scan,
        };
        let chunk = block.max(1);
        let starts: Vec<usize> = (0..nv).step_by(chunk).collect();
        // The face tables are reserved at their bound (untouched pages cost no memory) so they
        // never move while growing; shrunk at the end.
        let mut faces: Vec<Vec<u32>> = (0..n)
            .map(|k| {
                let mut t = Vec::new();
                if k >= 1 && keep {
                    let _ = t.try_reserve_exact(ns.saturating_mul(per(k) * (k + 1)));
                }
                t
            })
            .collect();
        let mut first_face: Vec<Vec<u32>> = (0..=n)
            .map(|k| Vec::with_capacity(if k >= 1 && keep { nv + 1 } else { 0 }))
            .collect();
        let mut top_order = Vec::with_capacity(if keep { ns } else { 0 });
        let mut lookups = vec![RecordLookup::default(); scan.map_or(0, <[_]>::len)];
        let mut bases: Vec<Vec<u32>> = vec![Vec::with_capacity(starts.len()); n];
        let mut next = vec![0u32; n + 1];
        let mut duplicates = Vec::new();
        let mut defects = Vec::new();
        for batch in starts.chunks(CHUNK_BATCH) {
            let outs: Vec<ChunkOut> = batch
                .par_iter()
                .map(|&start| build.chunk(start..nv.min(start.saturating_add(chunk))))
                .collect();
            // The batch's faces and top simplices land in the tables on every core.
            if keep {
                for (k, table) in faces.iter_mut().enumerate().skip(1) {
                    let parts: Vec<&[u32]> = outs.iter().map(|o| o.faces[k].as_slice()).collect();
                    append_parallel(table, &parts);
                }
                let parts: Vec<&[u32]> = outs.iter().map(|o| o.top.as_slice()).collect();
                append_parallel(&mut top_order, &parts);
            }
            for out in outs {
                for k in 1..=n {
                    if k < n {
                        bases[k].push(next[k]);
                    }
                    for &c in &out.counts[k] {
                        if keep {
                            first_face[k].push(next[k]);
                        }
                        next[k] += c;
                    }
                }
                duplicates.extend(out.duplicates);
                defects.extend(out.defects);
                for (all, part) in lookups.iter_mut().zip(out.lookups) {
                    all.missing.extend(part.missing);
                    all.repeats.extend(part.repeats);
                }
            }
        }
        if keep {
            for k in 1..=n {
                first_face[k].push(next[k]);
            }
        }
        for table in &mut faces {
            table.shrink_to_fit();
        }
        let Build {
            simplex_faces,
            neighbours,
            ..
        } = build;
        // Task-local face ids → global: add the base of the task owning the face's smallest vertex.
        let simplex_faces: Vec<Vec<u32>> = simplex_faces
            .into_iter()
            .enumerate()
            .map(|(k, table)| {
                let mut table: Vec<u32> = table.into_iter().map(AtomicU32::into_inner).collect();
                if !table.is_empty() {
                    let locals = local_faces(m, k + 1);
                    let base = &bases[k];
                    table
                        .par_chunks_mut(per(k))
                        .enumerate()
                        .for_each(|(s, row)| {
                            let ids = model.simplex(s);
                            for (slot, pos) in row.iter_mut().zip(locals) {
                                if *slot != NONE {
                                    let low = pos[..=k].iter().map(|&p| ids[p as usize]).min();
                                    *slot += base[low.unwrap_or(0) as usize / chunk];
                                }
                            }
                        });
                }
                table
            })
            .collect();
        let mut neighbours: Vec<u32> = neighbours.into_iter().map(AtomicU32::into_inner).collect();
        if n == 1 && full {
            // Facets are vertices: pair the (at most two) segments at each vertex.
            for v in 0..nv {
                if let [a, b] = incidence[incidence_start[v]..incidence_start[v + 1]] {
                    let (a, b) = (a as usize, b as usize);
                    let ia = model.simplex(a).iter().position(|&x| x as usize == v);
                    let ib = model.simplex(b).iter().position(|&x| x as usize == v);
                    if let (Some(ia), Some(ib)) = (ia, ib) {
                        neighbours[a * m + (1 - ia)] = b as u32;
                        neighbours[b * m + (1 - ib)] = a as u32;
                    }
                }
            }
        }
        let topology = Topology {
            n,
            num_vertices: nv,
            num_simplices: ns,
            faces,
            simplex_faces,
            first_face,
            top_order,
            neighbours,
            incidence_start,
            incidence,
            face_counts: next.iter().map(|&c| c as usize).collect(),
        };
        (topology, duplicates, defects, lookups)
    }

    /// The topology of `model`'s complex alone, for a program that makes a model (its stages are
    /// not looked at, nothing is checked beyond what indexing needs): `None` when an array is
    /// unsound (shapes, index ranges, non-finite numbers) or a simplex repeats a vertex.
    pub fn of_complex(model: &Model) -> Option<Topology> {
        crate::structure::arrays_sound_and_no_repeated_vertex(model)
            .then(|| Topology::build(model, &[], true).0)
    }

    /// Every distinct `k`-face of the complex (`0 ≤ k ≤ n`), `k + 1` sorted vertex ids each, flat
    /// and in increasing lexicographic order: for `1 ≤ k < n` the face table
    /// ([`Topology::face_vertices`]), for `k = 0` the vertices that belong to a simplex, for
    /// `k = n` the top simplices' vertex sets (a repeated simplex once). `model` is the one
    /// indexed.
    pub fn sorted_faces(&self, model: &Model, k: usize) -> Vec<u32> {
        match k {
            0 => (0..self.num_vertices as u32)
                .filter(|&v| !self.vertex_simplices(v as usize).is_empty())
                .collect(),
            k if k < self.n => self.faces[k].clone(),
            k if k == self.n => {
                let m = k + 1;
                let mut out: Vec<u32> = Vec::with_capacity(self.top_order.len() * m);
                for &s in &self.top_order {
                    let mut key = [0u32; 4];
                    key[..m].copy_from_slice(model.simplex(s as usize));
                    key[..m].sort_unstable();
                    // `top_order` is sorted by these keys: a repeat is the previous one.
                    if out.len() < m || out[out.len() - m..] != key[..m] {
                        out.extend_from_slice(&key[..m]);
                    }
                }
                out
            }
            _ => Vec::new(),
        }
    }

    /// Space dimension `n`.
    pub fn dim(&self) -> usize {
        self.n
    }

    /// Number of vertices.
    pub fn num_vertices(&self) -> usize {
        self.num_vertices
    }

    /// Number of top simplices.
    pub fn num_simplices(&self) -> usize {
        self.num_simplices
    }

    /// Number of faces of dimension `k` (`0 ≤ k ≤ n`; dimension 0 counts the vertices that belong
    /// to a simplex).
    pub fn num_faces(&self, k: usize) -> usize {
        match k {
            0 => (0..self.num_vertices)
                .filter(|&v| self.incidence_start[v + 1] > self.incidence_start[v])
                .count(),
            k if k == self.n => self.num_simplices,
            k if k < self.n => self.face_counts[k],
            _ => 0,
        }
    }

    /// Size of the index range of dimension-`k` faces (the number of rows of a dimension-`k`
    /// table): every vertex id for `k = 0`, every simplex for `k = n`.
    pub fn face_slots(&self, k: usize) -> usize {
        match k {
            0 => self.num_vertices,
            k if k == self.n => self.num_simplices,
            k if k < self.n => self.faces[k].len() / (k + 1),
            _ => 0,
        }
    }

    /// Sorted vertex ids of the dimension-`k` faces, `k + 1` per face, for `1 ≤ k < n` (empty
    /// otherwise: vertices and top simplices are their own tables).
    pub fn face_vertices(&self, k: usize) -> &[u32] {
        self.faces.get(k).map_or(&[], Vec::as_slice)
    }

    /// The dimension-`k` face of simplex `s` at the `j`-th subset of [`local_faces`]`(n + 1, k + 1)`.
    ///
    /// # Panics
    /// If `s`, `k` or `j` is out of range.
    #[inline]
    pub fn simplex_face(&self, model: &Model, s: usize, k: usize, j: usize) -> u32 {
        let m = self.n + 1;
        if k == 0 {
            model.simplex(s)[local_faces(m, 1)[j][0] as usize]
        } else if k == self.n {
            assert_eq!(j, 0, "a simplex has one top face");
            s as u32
        } else {
            let per = local_faces(m, k + 1).len();
            self.simplex_faces[k][s * per + j]
        }
    }

    /// Every face of simplex `s` by the bit mask of its local positions (bit `i`: local vertex
    /// `i`; entry 0 and masks past `2^(n+1)` unused): what code filling a simplex's control net
    /// wants, since a control point's support is such a mask.
    ///
    /// # Panics
    /// If `s` is out of range.
    pub fn faces_by_mask(&self, model: &Model, s: usize) -> [FaceId; 16] {
        let m = self.n + 1;
        let mut out = [FaceId { dim: 0, index: 0 }; 16];
        for size in 1..=m {
            let k = size - 1;
            for (j, pos) in local_faces(m, size).iter().enumerate() {
                let mask = pos[..size].iter().fold(0usize, |acc, &p| acc | 1 << p);
                out[mask] = FaceId {
                    dim: k as u8,
                    index: self.simplex_face(model, s, k, j),
                };
            }
        }
        out
    }

    /// The face ids of dimension `k` of every simplex, `C(n + 1, k + 1)` per simplex, for
    /// `1 ≤ k < n` (empty otherwise).
    pub fn simplex_face_table(&self, k: usize) -> &[u32] {
        self.simplex_faces.get(k).map_or(&[], Vec::as_slice)
    }

    /// The simplex across the facet of `s` opposite its local vertex `i`, or `None` on the boundary.
    #[inline]
    pub fn neighbour(&self, s: usize, i: usize) -> Option<SimplexId> {
        let t = self.neighbours[s * (self.n + 1) + i];
        (t != NONE).then_some(SimplexId(t))
    }

    /// All facet neighbours, `n + 1` per simplex, [`NONE`] on the boundary.
    pub fn neighbours(&self) -> &[u32] {
        &self.neighbours
    }

    /// The simplices incident to vertex `v`.
    #[inline]
    pub fn vertex_simplices(&self, v: usize) -> &[u32] {
        &self.incidence[self.incidence_start[v]..self.incidence_start[v + 1]]
    }

    /// The face with these vertex ids (strictly increasing), if it is a face of the complex.
    pub fn find(&self, model: &Model, face: &[u32]) -> Option<FaceId> {
        let size = face.len();
        if size == 0 || size > self.n + 1 || face.windows(2).any(|w| w[0] >= w[1]) {
            return None;
        }
        let k = size - 1;
        if k == 0 {
            let v = face[0] as usize;
            return (v < self.num_vertices && !self.vertex_simplices(v).is_empty()).then_some(
                FaceId {
                    dim: 0,
                    index: face[0],
                },
            );
        }
        let v = face[0] as usize;
        if v >= self.num_vertices {
            return None;
        }
        if k == self.n {
            // Simplices whose smallest vertex is `v`, in order of their sorted ids: the first
            // match (of duplicates, the one the check reports as first).
            let sorted = |s: u32| {
                let mut key = [0u32; 4];
                key[..size].copy_from_slice(model.simplex(s as usize));
                key[..size].sort_unstable();
                key
            };
            let mut want = [0u32; 4];
            want[..size].copy_from_slice(face);
            let range =
                &self.top_order[self.first_face[k][v] as usize..self.first_face[k][v + 1] as usize];
            let at = range.partition_point(|&s| sorted(s) < want);
            return range
                .get(at)
                .filter(|&&s| sorted(s) == want)
                .map(|&s| FaceId {
                    dim: k as u8,
                    index: s,
                });
        }
        // Faces with smallest vertex `v` are contiguous and sorted: a search among a few dozen.
        let table = &self.faces[k];
        let (mut lo, mut hi) = (
            self.first_face[k][v] as usize,
            self.first_face[k][v + 1] as usize,
        );
        while lo < hi {
            let mid = (lo + hi) / 2;
            match table[mid * size..(mid + 1) * size].cmp(face) {
                std::cmp::Ordering::Less => lo = mid + 1,
                std::cmp::Ordering::Greater => hi = mid,
                std::cmp::Ordering::Equal => {
                    return Some(FaceId {
                        dim: k as u8,
                        index: mid as u32,
                    })
                }
            }
        }
        None
    }
}

/// Dense points and weights per face dimension (see [`StageTable::points`]).
type Dense = (Vec<Vec<f64>>, Vec<Vec<f64>>);

/// One stage's face → record index, built on first use of the stage (readers that only count or
/// copy never pay for it). Control points are not copied: they stay in the stage's
/// [`crate::FaceTable`], which a [`StageTable`] reads through.
#[derive(Clone, Debug, PartialEq)]
struct StageRows {
    /// Per dimension `k`: the record (index into the stage's `faces`) of each face, or [`NONE`].
    record: Vec<Vec<u32>>,
    /// Per dimension `k`: the identity's owned control points of a face (`J / d` for its owned
    /// multi-indices `J`).
    identity: Vec<Vec<f64>>,
    /// Unit weights, as many as the largest face owns (rational stages).
    ones: Vec<f64>,
    /// Monotonic: the vertex map record of each vertex, or [`NONE`].
    vertex_record: Vec<u32>,
    /// Monotonic: `d + 1` coefficients per vertex.
    coefficients: Vec<f64>,
    /// Dense copies of the points and weights per face dimension, only for callers that want
    /// one array per dimension ([`StageTable::points`]; the Python binding's numpy views).
    dense: OnceLock<Dense>,
}

impl StageRows {
    /// `faces`: the face index of each record, as the structural check found it (its dimension is
    /// the record's vertex count − 1).
    fn build(stage: &Stage, topology: &Topology, faces: &[u32]) -> StageRows {
        let d = stage.degree;
        let n = topology.dim();
        if stage.kind == StageKind::Monotonic {
            return StageRows::monotonic(stage, topology.num_vertices());
        }
        let mut rows = StageRows {
            record: Vec::new(),
            identity: Vec::new(),
            ones: Vec::new(),
            vertex_record: Vec::new(),
            coefficients: Vec::new(),
            dense: OnceLock::new(),
        };
        match stage.kind {
            StageKind::Monotonic => unreachable!("returned above"),
            StageKind::Bezier | StageKind::Rational => {
                for k in 0..=n {
                    rows.record.push(vec![NONE; topology.face_slots(k)]);
                    rows.identity.push(
                        crate::multi_index::owned(k + 1, d)
                            .iter()
                            .map(|&e| f64::from(e) / f64::from(d))
                            .collect(),
                    );
                }
                if stage.kind == StageKind::Rational {
                    rows.ones =
                        vec![1.0; (0..=n).map(|k| owned_count(k + 1, d)).max().unwrap_or(0)];
                }
                for (r, &id) in faces.iter().enumerate() {
                    if id != NONE {
                        let k = stage.faces.face(r).len() - 1;
                        rows.record[k][id as usize] = r as u32;
                    }
                }
            }
        }
        rows
    }

    /// A monotonic stage's rows: indexed by vertex, so no face table is needed (a lazy index
    /// stays lazy).
    fn monotonic(stage: &Stage, nv: usize) -> StageRows {
        let d = stage.degree;
        let per = d as usize + 1;
        let mut rows = StageRows {
            record: Vec::new(),
            identity: Vec::new(),
            ones: Vec::new(),
            vertex_record: vec![NONE; nv],
            coefficients: (0..nv * per)
                .map(|i| (i % per) as f64 / f64::from(d))
                .collect(),
            dense: OnceLock::new(),
        };
        for (r, map) in stage.vertex_maps.iter().enumerate() {
            let v = map.vertex as usize;
            rows.vertex_record[v] = r as u32;
            rows.coefficients[v * per..(v + 1) * per].copy_from_slice(&map.coefficients);
        }
        rows
    }
}

/// One stage's face records grouped by their face's first (smallest) vertex id: what finds the
/// records of one simplex's faces without the complex's face tables (the lazy index,
/// [`IndexedModel::simplex_records`]). The structural check has made sure that every record names
/// a face of the complex, none twice, with its ids ascending.
#[derive(Debug)]
struct RecordIndex {
    /// Per record, grouped by first id: the record and its face's ids after the first (`len`
    /// of them, the rest [`NONE`]): a simplex's faces among a vertex's records are found by
    /// comparing integers, without reading the face table's rows.
    entries: Vec<(u32, u8, [u32; 3])>,
    /// `nv + 1` offsets into `entries`: the records whose face starts with vertex `v` are
    /// `entries[start[v] .. start[v + 1]]`.
    start: Vec<u32>,
}

impl RecordIndex {
    fn build(table: &FaceTable, nv: usize) -> RecordIndex {
        let mut start = vec![0u32; nv + 1];
        for r in 0..table.len() {
            start[table.face(r)[0] as usize + 1] += 1;
        }
        for v in 0..nv {
            start[v + 1] += start[v];
        }
        let mut next = start.clone();
        let mut entries = vec![(NONE, 0u8, [NONE; 3]); table.len()];
        for r in 0..table.len() {
            let face = table.face(r);
            let slot = &mut next[face[0] as usize];
            let mut rest = [NONE; 3];
            // At most 4 ids (n ≤ 3): the check refused longer records.
            for (x, &id) in rest.iter_mut().zip(&face[1..]) {
                *x = id;
            }
            entries[*slot as usize] = (r as u32, (face.len() - 1) as u8, rest);
            *slot += 1;
        }
        RecordIndex { entries, start }
    }
}

/// One stage's control data addressed by face (see the module docs): the record of each face and,
/// through it, the control points and weights in the stage's [`crate::FaceTable`] — the identity's
/// where the file has no record.
#[derive(Clone, Copy, Debug)]
pub struct StageTable<'a> {
    stage: &'a Stage,
    rows: &'a StageRows,
}

impl<'a> StageTable<'a> {
    /// The map kind.
    pub fn kind(&self) -> StageKind {
        self.stage.kind
    }

    /// The degree `d`.
    pub fn degree(&self) -> u32 {
        self.stage.degree
    }

    /// The record of each dimension-`k` face ([`NONE`] where the file has none).
    #[inline]
    pub fn records(&self, k: usize) -> &'a [u32] {
        self.rows.record.get(k).map_or(&[], Vec::as_slice)
    }

    /// The record of face `face`, if the file has one.
    pub fn record_of(&self, face: FaceId) -> Option<usize> {
        let r = *self
            .rows
            .record
            .get(face.dim as usize)?
            .get(face.index as usize)?;
        (r != NONE).then_some(r as usize)
    }

    /// Owned control point coordinates of one face, `(k + 1) · C(d − 1, k)` numbers (barycentric
    /// w.r.t. the face's sorted vertices): the record's, or the identity's.
    ///
    /// # Panics
    /// If `face` is out of range or the stage is monotonic.
    pub fn face_points(&self, face: FaceId) -> &'a [f64] {
        match self.record_of(face) {
            Some(r) => self.stage.faces.record(r).points,
            None => &self.rows.identity[face.dim as usize],
        }
    }

    /// Weights of one face, `C(d − 1, k)` (rational stages; 1 where the file has no record; empty
    /// for other kinds).
    pub fn face_weights(&self, face: FaceId) -> &'a [f64] {
        if self.stage.kind != StageKind::Rational {
            return &[];
        }
        match self.record_of(face) {
            Some(r) if !self.stage.faces.record(r).weights.is_empty() => {
                self.stage.faces.record(r).weights
            }
            _ => &self.rows.ones[..owned_count(face.dim as usize + 1, self.stage.degree)],
        }
    }

    /// Owned control point coordinates of every dimension-`k` face, `(k + 1) · C(d − 1, k)` per
    /// face, the identity's where no record exists: a dense copy made on the first call (for one
    /// array per dimension, e.g. a numpy view); [`StageTable::face_points`] reads without copying.
    /// Empty for monotonic stages.
    pub fn points(&self, k: usize) -> &'a [f64] {
        self.dense().0.get(k).map_or(&[], Vec::as_slice)
    }

    /// Weights of every dimension-`k` face, `C(d − 1, k)` per face, 1 where no record exists (a
    /// dense copy, as [`StageTable::points`]). Empty unless the stage is rational.
    pub fn weights(&self, k: usize) -> &'a [f64] {
        self.dense().1.get(k).map_or(&[], Vec::as_slice)
    }

    fn dense(&self) -> &'a Dense {
        let (stage, rows) = (self.stage, self.rows);
        rows.dense.get_or_init(|| {
            let mut points = Vec::new();
            let mut weights = Vec::new();
            if stage.kind == StageKind::Monotonic {
                return (points, weights);
            }
            let rational = stage.kind == StageKind::Rational;
            for (k, records) in rows.record.iter().enumerate() {
                let mut p = Vec::with_capacity(records.len() * rows.identity[k].len());
                let mut w = Vec::new();
                for index in 0..records.len() {
                    let face = FaceId {
                        dim: k as u8,
                        index: index as u32,
                    };
                    p.extend_from_slice(self.face_points(face));
                    if rational {
                        w.extend_from_slice(self.face_weights(face));
                    }
                }
                points.push(p);
                weights.push(w);
            }
            (points, weights)
        })
    }

    /// Monotonic: the `d + 1` coefficients of every vertex (the identity's `j / d` where the file
    /// has no map). Empty for other kinds.
    pub fn coefficients(&self) -> &'a [f64] {
        &self.rows.coefficients
    }

    /// Monotonic: the vertex map record of each vertex ([`NONE`] where the file has none).
    pub fn vertex_records(&self) -> &'a [u32] {
        &self.rows.vertex_record
    }
}

/// A structurally checked model with its topology and flat stage tables; cheap to share
/// (`Arc`-backed clones).
#[derive(Clone, Debug)]
pub struct IndexedModel {
    inner: Arc<Inner>,
}

#[derive(Debug)]
struct Inner {
    model: Model,
    /// The topology with its face tables, simplex → face tables and neighbours, and per stage the
    /// face index of each record: built by the check ([`IndexedModel::new`]) or on first use
    /// ([`IndexedModel::new_lazy_or_model`]).
    full: OnceLock<(Topology, Vec<Vec<u32>>)>,
    /// What the check that keeps nothing built (vertex → simplex incidence and face counts, no
    /// face tables), while `full` is not built ([`IndexedModel::new_lazy_or_model`]).
    checked: Option<Topology>,
    /// Per stage, built on first use.
    stages: Vec<OnceLock<StageRows>>,
    /// Per stage, the records ordered by face, built on first use of
    /// [`IndexedModel::simplex_records`] while `full` is not built.
    record_index: Vec<OnceLock<RecordIndex>>,
    /// Found by the check, or on first use for an evaluator's index of a model without stages
    /// whose arrays are sound ([`IndexedModel::for_evaluation`]).
    diagnostics: OnceLock<Vec<crate::rules::Diagnostic>>,
}

/// The structural rules whose breach makes a model impossible to evaluate
/// ([`IndexedModel::for_evaluation`] refuses them; it keeps the others as diagnostics).
/// What both indexes start from: a model that kept its numbers, the structural check (`full`:
/// also building the face tables) with at most `max` errors, and its diagnostics split into the
/// errors `fatal` deems fatal and the rest.
#[allow(clippy::type_complexity)]
fn check_for_index(
    model: &Model,
    max: usize,
    full: bool,
    fatal: impl Fn(crate::rules::Rule) -> bool,
) -> Result<(
    Vec<crate::rules::Diagnostic>,
    Vec<crate::rules::Diagnostic>,
    Option<(Topology, crate::structure::RecordFaces)>,
)> {
    Error::unless_numbers_kept(model, "index")?;
    let (diagnostics, topology) = crate::structure::check_indexed(model, max, full);
    let (errors, diagnostics) = diagnostics
        .into_iter()
        .partition(|d| d.severity == Severity::Error && fatal(d.rule));
    Ok((errors, diagnostics, topology))
}

fn evaluation_fatal(rule: crate::rules::Rule) -> bool {
    use crate::rules::Rule::*;
    matches!(
        rule,
        Dimension
            | VertexArray
            | SimplexArray
            | IndexRange
            | RepeatedIndex
            | StageDegree
            | KindMismatch
            | NotAFace
            | FaceSorted
            | DuplicateFace
            | PointCount
            | WeightCount
            | CoefficientCount
            | VertexMapIndex
            | NonFinite
    )
}

impl Inner {
    fn full(&self) -> &(Topology, Vec<Vec<u32>>) {
        self.full.get_or_init(|| {
            // A model is indexed lazily only when no simplex repeats a vertex (ISM-105 is fatal
            // for every lazy index): nothing to skip, and the tables are the ones the full check
            // builds.
            let model = &self.model;
            let (topology, _, _) = Topology::build(model, &[], true);
            let record_faces = crate::structure::record_faces(model, &topology);
            (topology, record_faces)
        })
    }

    /// The vertex → simplex incidence, from whichever topology is at hand (both hold the same).
    fn incidence(&self) -> &Topology {
        match (&self.checked, self.full.get()) {
            (_, Some((t, _))) | (Some(t), None) => t,
            (None, None) => &self.full().0,
        }
    }
}

impl PartialEq for IndexedModel {
    fn eq(&self, other: &Self) -> bool {
        self.inner.model == other.inner.model
    }
}

impl IndexedModel {
    /// Checks `model` (spec §2–5) and indexes it: the structural check builds the topology, which
    /// is kept.
    ///
    /// # Errors
    /// [`Error::Structure`] with every structural error found (at most
    /// [`crate::structure::DEFAULT_MAX_DIAGNOSTICS`]).
    pub fn new(model: Model) -> Result<IndexedModel> {
        IndexedModel::build(model, crate::structure::DEFAULT_MAX_DIAGNOSTICS, |_| true)
    }

    /// [`IndexedModel::new`], giving the model back with the error when it is refused (a validator
    /// still reports on it).
    ///
    /// # Errors
    /// As [`IndexedModel::new`], with the model.
    #[allow(clippy::result_large_err)]
    pub fn new_or_model(model: Model) -> std::result::Result<IndexedModel, (Model, Error)> {
        IndexedModel::build_or_model(model, crate::structure::DEFAULT_MAX_DIAGNOSTICS, |_| true)
    }

    /// Indexes `model` for evaluation, refusing only what makes indexing or the stage tables
    /// impossible — array shapes and index ranges, a simplex repeating a vertex, stage records that
    /// name no face, name one twice, have the wrong lengths or non-finite numbers — and keeping every
    /// other structural error (orientation, overlaps, values at the level, …) in
    /// [`IndexedModel::diagnostics`]. Fitters evaluate intermediate models that are not yet valid
    /// files; readers use [`IndexedModel::new`].
    ///
    /// A model without stages is indexed lazily: nothing looks its face records up, so an
    /// evaluator that only locates points and reads vertices and simplices (a linear isocomplex:
    /// the fitter's first models, the kernel's point-location benchmark) does not pay for face
    /// tables it never reads; the first [`IndexedModel::topology`] call builds them (outside a
    /// parallel loop, as for [`IndexedModel::new_lazy_or_model`]). When its arrays are sound and
    /// no simplex repeats a vertex — all such a model can be refused for — not even the check
    /// runs now: the first [`IndexedModel::diagnostics`] call runs it (the same diagnostics).
    ///
    /// # Errors
    /// [`Error::Structure`] with the errors that prevent indexing.
    pub fn for_evaluation(model: Model) -> Result<IndexedModel> {
        if model.stages.is_empty() {
            if crate::structure::arrays_sound_and_no_repeated_vertex(&model) {
                // Nothing to refuse: the check (its tolerated diagnostics) and the tables wait
                // for their first use.
                return Ok(IndexedModel {
                    inner: Arc::new(Inner {
                        model,
                        full: OnceLock::new(),
                        checked: None,
                        stages: Vec::new(),
                        record_index: Vec::new(),
                        diagnostics: OnceLock::new(),
                    }),
                });
            }
            return IndexedModel::lazy_or_model(model, usize::MAX, evaluation_fatal)
                .map_err(|(_, e)| e);
        }
        IndexedModel::build(model, usize::MAX, evaluation_fatal)
    }

    /// Runs the check (at most `max` errors), refuses when an error `fatal` deems fatal is found,
    /// and otherwise builds the stage tables.
    fn build(
        model: Model,
        max: usize,
        fatal: impl Fn(crate::rules::Rule) -> bool,
    ) -> Result<IndexedModel> {
        IndexedModel::build_or_model(model, max, fatal).map_err(|(_, e)| e)
    }

    #[allow(clippy::result_large_err)]
    fn build_or_model(
        model: Model,
        max: usize,
        fatal: impl Fn(crate::rules::Rule) -> bool,
    ) -> std::result::Result<IndexedModel, (Model, Error)> {
        let (errors, diagnostics, topology) = match check_for_index(&model, max, true, fatal) {
            Ok(checked) => checked,
            Err(e) => return Err((model, e)),
        };
        let (topology, record_faces) = match topology {
            Some((t, faces)) if errors.is_empty() && faces.len() == model.stages.len() => {
                (t, faces)
            }
            _ => return Err((model, Error::Structure(errors))),
        };
        let stages: Vec<OnceLock<StageRows>> =
            (0..model.stages.len()).map(|_| OnceLock::new()).collect();
        Ok(IndexedModel {
            inner: Arc::new(Inner {
                model,
                full: OnceLock::from((topology, record_faces)),
                checked: None,
                record_index: stages.iter().map(|_| OnceLock::new()).collect(),
                stages,
                diagnostics: OnceLock::from(diagnostics),
            }),
        })
    }

    /// [`IndexedModel::new_or_model`] that builds now only what the check needs anyway: the
    /// diagnostics (the same as [`IndexedModel::new`]'s) and the vertex → simplex incidence
    /// ([`IndexedModel::vertex_simplices`]). The face tables, simplex → face tables, neighbours
    /// and stage tables — the same ones [`IndexedModel::new`] builds — are built on the first call
    /// of [`IndexedModel::topology`] or [`IndexedModel::stage`]. For a validator whose stages may
    /// all be decided from their records alone (e.g. by a theorem).
    ///
    /// That first call builds on the current rayon pool: make it outside a parallel loop (a rayon
    /// worker waiting inside it may pick up a job of the loop that calls it again, and a
    /// [`OnceLock`] is not reentrant).
    ///
    /// # Errors
    /// As [`IndexedModel::new_or_model`], with the model.
    #[allow(clippy::result_large_err)]
    pub fn new_lazy_or_model(model: Model) -> std::result::Result<IndexedModel, (Model, Error)> {
        IndexedModel::lazy_or_model(model, crate::structure::DEFAULT_MAX_DIAGNOSTICS, |_| true)
    }

    /// The lazy index: the check that keeps nothing (at most `max` errors), refused when an error
    /// `fatal` deems fatal is found. Every caller counts ISM-105 (a simplex repeating a vertex)
    /// fatal, so the face tables built later skip no simplex and are the eager ones.
    #[allow(clippy::result_large_err)]
    fn lazy_or_model(
        model: Model,
        max: usize,
        fatal: impl Fn(crate::rules::Rule) -> bool,
    ) -> std::result::Result<IndexedModel, (Model, Error)> {
        let (errors, diagnostics, topology) = match check_for_index(&model, max, false, &fatal) {
            Ok(checked) => checked,
            Err(e) => return Err((model, e)),
        };
        debug_assert!(fatal(crate::rules::Rule::RepeatedIndex));
        // No fatal error: the check ran every stage rule (an error budget of `max` errors is
        // spent only by errors, which are all fatal for the reader's lazy index, and `max` is
        // unbounded for the evaluator's).
        let checked = match topology {
            Some((t, _)) if errors.is_empty() => t,
            _ => return Err((model, Error::Structure(errors))),
        };
        let stages: Vec<OnceLock<StageRows>> =
            (0..model.stages.len()).map(|_| OnceLock::new()).collect();
        Ok(IndexedModel {
            inner: Arc::new(Inner {
                model,
                full: OnceLock::new(),
                checked: Some(checked),
                record_index: stages.iter().map(|_| OnceLock::new()).collect(),
                stages,
                diagnostics: OnceLock::from(diagnostics),
            }),
        })
    }

    /// The simplices incident to vertex `v`, ascending (as [`Topology::vertex_simplices`], without
    /// building the face tables of a lazily indexed model).
    ///
    /// # Panics
    /// If `v` is out of range.
    pub fn vertex_simplices(&self, v: usize) -> &[u32] {
        self.inner.incidence().vertex_simplices(v)
    }

    /// The model as stored in the file.
    pub fn model(&self) -> &Model {
        &self.inner.model
    }

    /// The topology of the complex (built on the first call for a model indexed by
    /// [`IndexedModel::new_lazy_or_model`]).
    pub fn topology(&self) -> &Topology {
        &self.inner.full().0
    }

    /// The flat tables of stage `i`.
    ///
    /// # Panics
    /// If `i` is out of range.
    pub fn stage(&self, i: usize) -> StageTable<'_> {
        let inner = &*self.inner;
        let stage = &inner.model.stages[i];
        let rows = if stage.kind == StageKind::Monotonic {
            // Indexed by vertex: a lazy index does not build its face tables for it.
            inner.stages[i].get_or_init(|| StageRows::monotonic(stage, inner.model.num_vertices()))
        } else {
            let (topology, record_faces) = inner.full();
            inner.stages[i].get_or_init(|| StageRows::build(stage, topology, &record_faces[i]))
        };
        StageTable { stage, rows }
    }

    /// The record of stage `i` (a Bézier or rational stage) naming each face of simplex `s`, by
    /// the bit mask of the face's local positions (bit `j`: local vertex `j`; entry 0 and masks
    /// past `2^(n+1)` unused), [`NONE`] where the file has none: what a caller filling one
    /// simplex's control net wants ([`IndexedModel::stage`]'s
    /// [`StageTable::record_of`] of [`Topology::faces_by_mask`], the same records).
    ///
    /// A lazily indexed model ([`IndexedModel::new_lazy_or_model`]) whose face tables are not
    /// built yet finds the records by their faces' vertex ids instead (a per-stage order of the
    /// records, built on first use without a thread pool, so a parallel loop may call this
    /// first): a caller that only reads some simplices' records — an export reads the simplices
    /// the level set crosses — never pays for the complex's face tables. The check has refused a
    /// record that names no face of the complex or repeats one, so both routes agree.
    ///
    /// # Panics
    /// If `i` or `s` is out of range, or stage `i` is monotonic (indexed by vertex).
    pub fn simplex_records(&self, i: usize, s: usize) -> [u32; 16] {
        let inner = &*self.inner;
        let model = &inner.model;
        let stage = &model.stages[i];
        assert!(
            stage.kind != StageKind::Monotonic,
            "stage {i} is monotonic: its records are per vertex"
        );
        let simplex = model.simplex(s);
        let m = simplex.len().min(4);
        let mut out = [NONE; 16];
        if let Some((topology, _)) = inner.full.get() {
            let table = self.stage(i);
            let faces = topology.faces_by_mask(model, s);
            for (record, face) in out.iter_mut().zip(&faces).take(1 << m).skip(1) {
                *record = table.records(usize::from(face.dim))[face.index as usize];
            }
            return out;
        }
        let index = inner.record_index[i]
            .get_or_init(|| RecordIndex::build(&stage.faces, model.num_vertices()));
        // Each face's record is among its first vertex's: a pass over the simplex's vertices'
        // records keeps those whose other ids are all in the simplex, at the mask of their
        // positions (a simplex's ids are distinct: the check refused repeats).
        let position = |id: u32| simplex[..m].iter().position(|&x| x == id);
        for (p, &v) in simplex[..m].iter().enumerate() {
            let run = &index.entries
                [index.start[v as usize] as usize..index.start[v as usize + 1] as usize];
            'records: for &(r, len, rest) in run {
                let mut mask = 1usize << p;
                for &id in &rest[..usize::from(len)] {
                    match position(id) {
                        Some(q) => mask |= 1 << q,
                        None => continue 'records,
                    }
                }
                out[mask] = r;
            }
        }
        out
    }

    /// The flat tables of every stage, in application order.
    pub fn stages(&self) -> impl ExactSizeIterator<Item = StageTable<'_>> + '_ {
        (0..self.inner.stages.len()).map(|i| self.stage(i))
    }

    /// The structural diagnostics that did not prevent indexing: warnings (e.g. unused vertices)
    /// and, for [`IndexedModel::for_evaluation`], the errors it tolerates.
    pub fn diagnostics(&self) -> &[crate::rules::Diagnostic] {
        self.inner.diagnostics.get_or_init(|| {
            // Only an evaluator's index of a model without stages, whose arrays were sound,
            // defers them: the check finds no error it refuses (no stage rule applies), so every
            // diagnostic is kept, as the check at construction would have kept them.
            match check_for_index(&self.inner.model, usize::MAX, false, evaluation_fatal) {
                Ok((errors, diagnostics, _)) => {
                    debug_assert!(errors.is_empty(), "{errors:?}");
                    diagnostics
                }
                Err(_) => Vec::new(),
            }
        })
    }

    /// The model, without the index (a copy when the index is shared).
    pub fn into_model(self) -> Model {
        match Arc::try_unwrap(self.inner) {
            Ok(inner) => inner.model,
            Err(shared) => shared.model.clone(),
        }
    }
}

impl std::ops::Deref for IndexedModel {
    type Target = Model;
    fn deref(&self) -> &Model {
        &self.inner.model
    }
}

#[cfg(test)]
mod tests {
    use std::collections::{BTreeSet, HashMap};

    use super::*;
    use crate::model::{FaceRecord, Stage, VertexMap};

    #[test]
    fn packed_entries_keep_the_entry_and_its_order() {
        // Ground truth: the (key, tail) tuple order the star sort is defined by.
        let mut entries = Vec::new();
        let ids = [0u32, 1, 7, u32::MAX - 1, u32::MAX];
        for &a in &ids {
            for &b in &ids {
                for tail in [0u64, 1, 1 << 32, (1 << 32) | 5, (1 << 33) - 1] {
                    for (local, opposite) in [(0u8, 0u8), (5, 3), (3, 8), (15, 1)] {
                        entries.push(Entry {
                            key: u128::from(a) << 64 | u128::from(b) << 32,
                            tail,
                            local,
                            opposite,
                        });
                    }
                }
            }
        }
        for e in &entries {
            let back = Entry::unpack(e.pack());
            assert_eq!(
                (back.key, back.tail, back.local, back.opposite),
                (e.key, e.tail, e.local, e.opposite)
            );
        }
        for x in &entries {
            for y in &entries {
                if (x.key, x.tail) != (y.key, y.tail) {
                    assert_eq!(
                        x.pack().cmp(&y.pack()),
                        (x.key, x.tail).cmp(&(y.key, y.tail))
                    );
                }
            }
        }
    }

    /// A Kuhn triangulation of the grid `g^n` (positively oriented): the ground truth below is
    /// computed by brute force over vertex subsets, independently of the sort-based index.
    fn kuhn(n: usize, g: usize) -> Model {
        let mut model = Model::new(n as u8);
        let side = g + 1;
        let count = side.pow(n as u32);
        for i in 0..count {
            let mut rest = i;
            for _ in 0..n {
                model.vertices.push((rest % side) as f64);
                rest /= side;
            }
            // Alternate signs so the level set is not empty; never zero.
            model.values.push(if i % 3 == 0 { -1.0 } else { 1.0 });
        }
        for s in crate::builder::kuhn_simplices(&vec![g; n]) {
            model.simplices.extend(s.oriented());
        }
        model
    }

    fn brute_faces(model: &Model, size: usize) -> BTreeSet<Vec<u32>> {
        let m = model.dim() + 1;
        let mut out = BTreeSet::new();
        for ids in model.simplex_iter() {
            for pos in local_faces(m, size) {
                let mut f: Vec<u32> = pos[..size].iter().map(|&p| ids[p as usize]).collect();
                f.sort_unstable();
                out.insert(f);
            }
        }
        out
    }

    #[test]
    fn local_faces_are_the_subsets_in_lexicographic_order() {
        assert_eq!(
            local_faces(4, 2)
                .iter()
                .map(|f| [f[0], f[1]])
                .collect::<Vec<_>>(),
            vec![[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]
        );
        assert_eq!(local_faces(3, 3).len(), 1);
        assert_eq!(local_faces(4, 1).len(), 4);
    }

    #[test]
    fn simplex_faces_are_the_subsets_by_mask_with_ids_sorted() {
        // Truth: each subset of positions written out, its (id, position) pairs sorted.
        let lists: [&[u32]; 6] = [
            &[5],
            &[9, 2],
            &[7, 2, 5],
            &[3, 8, 1, 6],
            &[4, 4, 1],
            &[0, 1, 2, 3],
        ];
        for ids in lists {
            let m = ids.len();
            for min_len in 0..=m + 1 {
                let mut expected = Vec::new();
                for mask in 1u8..1 << m {
                    let mut pairs: Vec<(u32, u8)> = (0..m)
                        .filter(|&p| mask >> p & 1 == 1)
                        .map(|p| (ids[p], p as u8))
                        .collect();
                    if pairs.len() < min_len {
                        continue;
                    }
                    pairs.sort_unstable();
                    let sorted: Vec<u32> = pairs.iter().map(|x| x.0).collect();
                    let positions: Vec<u8> = pairs.iter().map(|x| x.1).collect();
                    expected.push((mask, sorted, positions));
                }
                let found: Vec<(u8, Vec<u32>, Vec<u8>)> = simplex_faces(ids, min_len)
                    .map(|f| (f.mask, f.ids().to_vec(), f.positions().to_vec()))
                    .collect();
                assert_eq!(found, expected, "{ids:?} min {min_len}");
                assert!(
                    simplex_faces(ids, min_len).all(|f| f.len() == f.ids().len() && !f.is_empty())
                );
            }
        }
    }

    #[test]
    fn shared_facets_are_the_neighbour_pairs() {
        // Truth: the neighbour table (itself tested against brute force below) — each pair of
        // neighbours once, its facet the ids but the opposite vertex.
        for (n, g) in [(2, 3), (3, 2)] {
            let model = kuhn(n, g);
            let m = n + 1;
            let t = IndexedModel::new(model.clone()).expect("valid");
            let t = t.topology();
            let mut expected = Vec::new();
            for (s, ids) in model.simplex_iter().enumerate() {
                for i in 0..m {
                    let Some(SimplexId(other)) = t.neighbour(s, i) else {
                        continue;
                    };
                    let other = other as usize;
                    if other < s {
                        continue;
                    }
                    let mut facet: Vec<u32> = (0..m).filter(|&p| p != i).map(|p| ids[p]).collect();
                    facet.sort_unstable();
                    let j = (0..m)
                        .find(|&p| !facet.contains(&model.simplex(other)[p]))
                        .expect("an opposite vertex");
                    expected.push((facet, [(s, i), (other, j)]));
                }
            }
            expected.sort();
            assert_eq!(shared_facets(m, &model.simplices), expected, "n={n}");
        }
        // A facet held by three triangles, and the boundary: left out.
        assert!(shared_facets(3, &[0, 1, 2, 1, 0, 3, 0, 1, 4]).is_empty());
        assert!(shared_facets(5, &[0, 1, 2, 3, 4]).is_empty());
    }

    #[test]
    fn sorted_top_faces_list_a_repeated_simplex_once() {
        // Truth: the distinct sorted vertex sets of the simplices, in lexicographic order.
        let mut model = kuhn(2, 2);
        let first = model.simplex(0).to_vec();
        model.simplices.extend(first);
        let topology = Topology::of_complex(&model).expect("sound arrays");
        let expected: Vec<u32> = brute_faces(&model, 3).into_iter().flatten().collect();
        assert_eq!(topology.sorted_faces(&model, 2), expected);
        assert_eq!(expected.len(), 3 * 8);
        // Unsound arrays or a simplex repeating a vertex: no topology.
        model.simplices[1] = model.simplices[0];
        assert!(Topology::of_complex(&model).is_none());
        model.simplices[1] = 1000;
        assert!(Topology::of_complex(&model).is_none());
    }

    #[test]
    fn faces_neighbours_and_euler_characteristic_match_brute_force() {
        // Whatever the thread count: the incidence rows are filled in one block of simplices per
        // thread, the face tables appended part by part on every core.
        for threads in [1, 2, 3, 5] {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("a pool")
                .install(match_brute_force);
        }
    }

    fn match_brute_force() {
        for (n, g) in [(2, 4), (3, 3)] {
            let model = kuhn(n, g);
            let indexed = IndexedModel::new(model.clone()).expect("a Kuhn grid is valid");
            let t = indexed.topology();
            let m = n + 1;
            let mut euler = 0i64;
            for k in 0..=n {
                let brute = brute_faces(&model, k + 1);
                assert_eq!(t.num_faces(k), brute.len(), "n={n} k={k}");
                let flat: Vec<u32> = brute.iter().flatten().copied().collect();
                assert_eq!(t.sorted_faces(&model, k), flat, "n={n} k={k}");
                let alone = Topology::of_complex(&model).expect("sound arrays");
                assert_eq!(alone.sorted_faces(&model, k), flat, "n={n} k={k}");
                euler += if k % 2 == 0 { 1 } else { -1 } * brute.len() as i64;
                if (1..n).contains(&k) {
                    let listed: Vec<Vec<u32>> = t
                        .face_vertices(k)
                        .chunks(k + 1)
                        .map(<[u32]>::to_vec)
                        .collect();
                    assert_eq!(listed, brute.iter().cloned().collect::<Vec<_>>());
                }
                // Every face of every simplex is found, by lookup and by the simplex's table.
                for (s, ids) in model.simplex_iter().enumerate() {
                    for (j, pos) in local_faces(m, k + 1).iter().enumerate() {
                        let mut f: Vec<u32> = pos[..=k].iter().map(|&p| ids[p as usize]).collect();
                        f.sort_unstable();
                        let found = t.find(&model, &f).expect("a face of the complex");
                        assert_eq!(found.dim as usize, k);
                        assert_eq!(found.index, t.simplex_face(&model, s, k, j));
                    }
                }
            }
            // A triangulated square or cube is a disk or ball.
            assert_eq!(euler, 1, "n={n}");
            // Each simplex's faces by position mask: the face of those positions' ids.
            for (s, ids) in model.simplex_iter().enumerate() {
                let by_mask = t.faces_by_mask(&model, s);
                for (mask, &face) in by_mask.iter().enumerate().take(1 << m).skip(1) {
                    let mut f: Vec<u32> = (0..m)
                        .filter(|&p| mask >> p & 1 == 1)
                        .map(|p| ids[p])
                        .collect();
                    f.sort_unstable();
                    assert_eq!(Some(face), t.find(&model, &f), "s={s} mask={mask}");
                }
            }
            // Neighbours: brute force over all pairs sharing n vertices.
            let sets: Vec<BTreeSet<u32>> = model
                .simplex_iter()
                .map(|ids| ids.iter().copied().collect())
                .collect();
            for (s, ids) in model.simplex_iter().enumerate() {
                for i in 0..m {
                    let facet: BTreeSet<u32> = ids
                        .iter()
                        .enumerate()
                        .filter(|&(j, _)| j != i)
                        .map(|(_, &v)| v)
                        .collect();
                    let across: Vec<usize> = (0..sets.len())
                        .filter(|&o| o != s && facet.is_subset(&sets[o]))
                        .collect();
                    assert!(across.len() <= 1);
                    assert_eq!(
                        t.neighbour(s, i).map(|x| x.0 as usize),
                        across.first().copied()
                    );
                }
            }
            for v in 0..model.num_vertices() {
                let brute: Vec<u32> = (0..sets.len() as u32)
                    .filter(|&s| sets[s as usize].contains(&(v as u32)))
                    .collect();
                assert_eq!(t.vertex_simplices(v), brute.as_slice());
            }
            // Not faces: a non-edge, unsorted ids, out-of-range ids.
            assert!(t
                .find(&model, &[0, model.num_vertices() as u32 - 1])
                .is_none());
            assert!(t.find(&model, &[1, 0]).is_none());
            assert!(t.find(&model, &[u32::MAX]).is_none());
        }
    }

    #[test]
    fn stage_tables_hold_each_record_at_its_face_and_the_identity_elsewhere() {
        let mut model = kuhn(3, 2);
        let d = 3;
        let mut stage = Stage::identity(StageKind::Rational, d);
        let mut expected: HashMap<Vec<u32>, (Vec<f64>, Vec<f64>)> = HashMap::new();
        // Records on a few faces of each dimension, with distinct values.
        for (k, face) in [(1, vec![0u32, 1]), (2, vec![0, 1, 4]), (1, vec![1, 4])] {
            let owned = owned_count(k + 1, d);
            let points: Vec<f64> = (0..owned * (k + 1))
                .map(|i| 0.1 + 0.01 * (i + face.len()) as f64)
                .collect();
            let weights: Vec<f64> = (0..owned).map(|i| 1.5 + i as f64).collect();
            expected.insert(face.clone(), (points.clone(), weights.clone()));
            stage.faces.push_record(&FaceRecord {
                face,
                points,
                weights,
            });
        }
        model.stages.push(stage);
        let mut mono = Stage::identity(StageKind::Monotonic, 2);
        mono.vertex_maps.push(VertexMap {
            vertex: 5,
            coefficients: vec![0.0, 0.3, 1.0],
        });
        model.stages.push(mono);
        let indexed = IndexedModel::new(model.clone()).expect("valid");
        let t = indexed.topology();
        let table = indexed.stage(0);
        for k in 1..=2 {
            let owned = owned_count(k + 1, d);
            let identity: Vec<f64> = crate::multi_index::owned(k + 1, d)
                .iter()
                .map(|&e| f64::from(e) / f64::from(d))
                .collect();
            for (i, face) in t.face_vertices(k).chunks(k + 1).enumerate() {
                let id = FaceId {
                    dim: k as u8,
                    index: i as u32,
                };
                // The dense copy (numpy views) row by row equals the per-face reads.
                let stride = identity.len();
                assert_eq!(
                    &table.points(k)[i * stride..(i + 1) * stride],
                    table.face_points(id)
                );
                assert_eq!(
                    &table.weights(k)[i * owned..(i + 1) * owned],
                    table.face_weights(id)
                );
                match expected.get(face) {
                    Some((p, w)) => {
                        assert_eq!(table.face_points(id), p.as_slice());
                        assert_eq!(table.face_weights(id), w.as_slice());
                        let r = table.record_of(id).expect("recorded");
                        assert_eq!(model.stages[0].faces.record(r).face, face);
                    }
                    None => {
                        assert_eq!(table.face_points(id), identity.as_slice());
                        assert_eq!(table.face_weights(id), vec![1.0; owned].as_slice());
                        assert_eq!(table.record_of(id), None);
                    }
                }
            }
        }
        let mono = indexed.stage(1);
        assert_eq!(&mono.coefficients()[5 * 3..6 * 3], &[0.0, 0.3, 1.0]);
        assert_eq!(&mono.coefficients()[4 * 3..5 * 3], &[0.0, 0.5, 1.0]);
        assert_eq!(mono.vertex_records()[5], 0);
        assert_eq!(mono.vertex_records()[4], NONE);
    }

    #[test]
    fn any_block_size_gives_the_same_topology() {
        for (n, g) in [(2, 4), (3, 3)] {
            let model = kuhn(n, g);
            let skip = vec![false; model.num_simplices()];
            let whole = Topology::build_in_blocks(&model, &skip, usize::MAX, true, None);
            for block in [1, 3, 7] {
                assert_eq!(
                    Topology::build_in_blocks(&model, &skip, block, true, None),
                    whole
                );
            }
            // A check that keeps nothing builds the same faces, without the per-simplex tables.
            let (lean, duplicates, defects, _) =
                Topology::build_in_blocks(&model, &skip, 5, false, None);
            assert_eq!((duplicates, defects), (whole.1.clone(), whole.2.clone()));
            assert_eq!(lean.faces, whole.0.faces);
            assert_eq!(lean.first_face, whole.0.first_face);
            assert_eq!(lean.top_order, whole.0.top_order);
            assert!(lean.neighbours.is_empty());
        }
    }

    /// Face records of every kind the scan must tell apart, sorted by first id: every face of the
    /// complex (some named two or three times), non-faces, unsorted and repeated ids, too many
    /// ids.
    fn records_to_scan(model: &Model) -> Vec<Vec<u32>> {
        let n = model.dim();
        let nv = model.num_vertices() as u32;
        let mut out: Vec<Vec<u32>> = Vec::new();
        for size in 1..=n + 1 {
            for (i, f) in brute_faces(model, size).into_iter().enumerate() {
                for _ in 0..1 + usize::from(i % 3 == 0) + usize::from(i % 7 == 0) {
                    out.push(f.clone());
                }
            }
        }
        for v in 0..nv {
            for size in 2..=n + 2 {
                // Ids far apart are no face of a Kuhn grid (of at least 2 cells a side).
                let far: Vec<u32> = (0..size as u32).map(|i| v + i * nv / 3).collect();
                if far.iter().all(|&x| x < nv) {
                    out.push(far.clone());
                }
            }
            if v + 1 < nv {
                out.push(vec![v, v]);
                out.push(vec![v, v + 1, v]);
                let mut unsorted = vec![v];
                unsorted.extend((1..=n as u32).rev().map(|i| (v + i).min(nv - 1)));
                out.push(unsorted);
            }
        }
        // Some faces named again, in decreasing order (a search before the last one's end).
        for size in (1..=n + 1).rev() {
            let faces: Vec<Vec<u32>> = brute_faces(model, size).into_iter().collect();
            out.extend(faces.into_iter().rev().step_by(5));
        }
        // Stable: records of one first id keep the order above (repeats after their first).
        out.sort_by_key(|f| f[0]);
        out
    }

    fn lookup_by_brute_force(model: &Model, records: &[Vec<u32>]) -> RecordLookup {
        let n = model.dim();
        let faces: Vec<BTreeSet<Vec<u32>>> =
            (0..=n + 1).map(|size| brute_faces(model, size)).collect();
        let mut first: HashMap<&[u32], u32> = HashMap::new();
        let mut out = RecordLookup::default();
        for (r, f) in records.iter().enumerate() {
            if f.len() > n + 1 || !faces[f.len()].contains(f) {
                out.missing.push(r as u32);
            } else if let Some(&a) = first.get(f.as_slice()) {
                out.repeats.push((r as u32, a));
            } else {
                first.insert(f, r as u32);
            }
        }
        out
    }

    #[test]
    fn scanned_records_match_a_brute_force_lookup() {
        // Ground truth: membership in the set of all vertex subsets of the simplices, and the
        // first record naming each face in a pass over the records.
        for threads in [1, 2, 3, 5] {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("a pool")
                .install(scan_matches_brute_force);
        }
    }

    /// A cone of `r` tetrahedra around the axis from the apex 0 to the centre 1 of a ring of `r`
    /// vertices: the apex has `r + 1` higher neighbours, more than any vertex of a Kuhn grid.
    fn cone(r: usize) -> Model {
        let mut model = Model::new(3);
        model.vertices.extend([0.0, 0.0, 1.0, 0.0, 0.0, 0.0]);
        for i in 0..r {
            let a = std::f64::consts::TAU * i as f64 / r as f64;
            model.vertices.extend([a.cos(), a.sin(), 0.0]);
        }
        model.values = (0..r + 2)
            .map(|i| if i == 0 { -1.0 } else { 1.0 })
            .collect();
        for i in 0..r {
            let (a, b) = (2 + i as u32, 2 + ((i + 1) % r) as u32);
            model.simplices.extend([0, 1, a, b]);
        }
        model
    }

    fn scan_matches_brute_force() {
        for model in [kuhn(2, 4), kuhn(3, 3), cone(40)] {
            let n = model.dim();
            let skip = vec![false; model.num_simplices()];
            let records = records_to_scan(&model);
            // Two tables: all records, and every other one (another numbering of repeats).
            let mut tables = [FaceTable::new(), FaceTable::new()];
            for (r, f) in records.iter().enumerate() {
                tables[0].push(f, &[], &[]);
                if r % 2 == 0 {
                    tables[1].push(f, &[], &[]);
                }
            }
            let halves: Vec<Vec<u32>> = records.iter().step_by(2).cloned().collect();
            let expected = [
                lookup_by_brute_force(&model, &records),
                lookup_by_brute_force(&model, &halves),
            ];
            assert!(!expected[0].missing.is_empty() && !expected[0].repeats.is_empty());
            let nv = model.num_vertices();
            assert!(tables.iter().all(|t| Topology::scannable(t, nv)));
            let refs: Vec<&FaceTable> = tables.iter().collect();
            let whole = Topology::build_in_blocks(&model, &skip, usize::MAX, false, None);
            for block in [1, 3, 7, STAR_CHUNK] {
                let (t, duplicates, defects, lookups) =
                    Topology::build_in_blocks(&model, &skip, block, false, Some(&refs));
                assert_eq!(lookups, expected, "n={n} block={block}");
                assert_eq!((duplicates, defects), (whole.1.clone(), whole.2.clone()));
                for k in 0..=n {
                    let brute = brute_faces(&model, k + 1).len();
                    assert_eq!(t.num_faces(k), brute, "n={n} k={k}");
                }
            }
        }
    }

    #[test]
    fn the_scan_and_the_face_tables_report_alike() {
        // The check that keeps nothing scans; the one that keeps the index searches its face
        // tables: same diagnostics, in the same order, whatever the cap.
        for (n, g) in [(2, 4), (3, 3)] {
            let mut model = kuhn(n, g);
            let records = records_to_scan(&model);
            let d = 2u32;
            let mut bezier = Stage::identity(StageKind::Bezier, d);
            let mut rational = Stage::identity(StageKind::Rational, d + 1);
            for (r, f) in records.iter().enumerate() {
                let owned = owned_count(f.len(), d);
                // Some records with a point too few or a non-finite number.
                let mut points = vec![0.25; owned * f.len()];
                if r % 5 == 1 {
                    points.pop();
                }
                if r % 11 == 2 {
                    if let Some(x) = points.first_mut() {
                        *x = f64::NAN;
                    }
                }
                bezier.faces.push(f, &points, &[]);
                let owned = owned_count(f.len(), d + 1);
                rational
                    .faces
                    .push(f, &vec![0.25; owned * f.len()], &vec![1.0; owned]);
            }
            model.stages = vec![bezier, Stage::identity(StageKind::Monotonic, 1), rational];
            for max in [3, 40, 1_000_000] {
                let scanned = crate::structure::check_indexed(&model, max, false).0;
                let searched = crate::structure::check_indexed(&model, max, true).0;
                assert_eq!(scanned, searched, "n={n} max={max}");
                assert!(scanned.len() >= max.min(100), "n={n} max={max}");
            }
        }
    }

    /// An evaluator's index of a model without stages is lazy, and builds what the eager one
    /// builds (truth: the eager index of the same model, `IndexedModel::build` with the same
    /// rules): the same diagnostics, tolerated errors included, no face table before
    /// `topology()`, then the same topology; the same refusal of a fatal error.
    #[test]
    fn an_evaluator_index_without_stages_is_lazy_and_the_same() {
        for (n, g) in [(2, 4), (3, 3)] {
            let mut model = kuhn(n, g);
            // Tolerated: an unused vertex (warning), one simplex inverted (an orientation error),
            // a vertex value at the level.
            model.vertices.extend(std::iter::repeat_n(9.0, n));
            model.values.push(1.0);
            model.simplices.swap(0, 1);
            model.values[2] = model.level;
            let eager =
                IndexedModel::build(model.clone(), usize::MAX, evaluation_fatal).expect("valid");
            let lazy = IndexedModel::for_evaluation(model.clone()).expect("valid");
            // Sound arrays, no repeated vertex: not even the check ran yet.
            assert!(lazy.inner.diagnostics.get().is_none());
            assert!(lazy.inner.checked.is_none() && lazy.inner.full.get().is_none());
            assert!(eager.diagnostics().len() >= 2, "{:?}", eager.diagnostics());
            assert!(eager
                .diagnostics()
                .iter()
                .any(|d| d.severity == Severity::Error));
            assert_eq!(lazy.diagnostics(), eager.diagnostics(), "n={n}");
            assert!(lazy.inner.full.get().is_none());
            assert_eq!(lazy.topology(), eager.topology(), "n={n}");
            for v in 0..model.num_vertices() {
                assert_eq!(
                    lazy.vertex_simplices(v),
                    eager.topology().vertex_simplices(v)
                );
            }
            // Fatal for both, with the same errors: a simplex repeating a vertex, a vertex
            // index out of range, a coordinate that is not finite, a dimension the format has
            // not.
            let mut repeated = model.clone();
            repeated.simplices[1] = repeated.simplices[0];
            let mut range = model.clone();
            range.simplices[2] = model.num_vertices() as u32;
            let mut nan = model.clone();
            nan.vertices[1] = f64::NAN;
            let mut dim = model.clone();
            dim.dimension = 4;
            for (bad, rule) in [
                (repeated, crate::rules::Rule::RepeatedIndex),
                (range, crate::rules::Rule::IndexRange),
                (nan, crate::rules::Rule::VertexArray),
                (dim, crate::rules::Rule::Dimension),
            ] {
                let e = IndexedModel::build(bad.clone(), usize::MAX, evaluation_fatal).unwrap_err();
                let l = IndexedModel::for_evaluation(bad).unwrap_err();
                assert_eq!(l.diagnostics(), e.diagnostics());
                assert_eq!(l.rule(), Some(rule), "{l:?}");
            }
        }
    }

    #[test]
    fn a_lazy_index_builds_the_tables_of_an_eager_one() {
        // Truth: the eagerly built index (its tables are checked against brute force above).
        for (n, g) in [(2, 4), (3, 3)] {
            let mut model = kuhn(n, g);
            // An unused vertex: a warning, kept by both.
            model.vertices.extend(std::iter::repeat_n(9.0, n));
            model.values.push(1.0);
            let plain = IndexedModel::new(model.clone()).expect("valid");
            let d = 3;
            let mut bezier = Stage::identity(StageKind::Bezier, d);
            let mut rational = Stage::identity(StageKind::Rational, d);
            for k in 1..n {
                let faces = plain.topology().face_vertices(k);
                for (i, face) in faces.chunks(k + 1).enumerate() {
                    let owned = owned_count(k + 1, d);
                    let points = vec![1.0 / (k + 1) as f64; owned * (k + 1)];
                    if i % 3 == 0 {
                        bezier.faces.push(face, &points, &[]);
                    }
                    if i % 4 == 1 {
                        rational.faces.push(face, &points, &vec![2.0; owned]);
                    }
                }
            }
            // Records in decreasing face order: not scannable, the check keeps its face tables.
            let mut reversed = Stage::identity(StageKind::Bezier, d);
            for r in (0..bezier.faces.len()).rev() {
                let rec = bezier.faces.record(r);
                reversed.faces.push(rec.face, rec.points, rec.weights);
            }
            let mut mono = Stage::identity(StageKind::Monotonic, 2);
            mono.vertex_maps.push(VertexMap {
                vertex: 3,
                coefficients: vec![0.0, 0.4, 1.0],
            });
            for stages in [vec![bezier.clone(), mono, rational], vec![reversed, bezier]] {
                model.stages = stages;
                let eager = IndexedModel::new(model.clone()).expect("valid");
                let lazy = IndexedModel::new_lazy_or_model(model.clone()).expect("valid");
                assert_eq!(lazy.diagnostics(), eager.diagnostics(), "n={n}");
                assert_eq!(lazy.diagnostics().len(), 1);
                // The incidence is there before the tables are built.
                assert!(lazy.inner.full.get().is_none());
                for v in 0..model.num_vertices() {
                    assert_eq!(
                        lazy.vertex_simplices(v),
                        eager.topology().vertex_simplices(v)
                    );
                }
                assert!(lazy.inner.full.get().is_none());
                assert_eq!(lazy.topology(), eager.topology(), "n={n}");
                for i in 0..model.stages.len() {
                    let (a, b) = (lazy.stage(i), eager.stage(i));
                    for k in 0..=n {
                        assert_eq!(a.records(k), b.records(k), "n={n} stage {i} k={k}");
                    }
                    assert_eq!(a.coefficients(), b.coefficients());
                    assert_eq!(a.vertex_records(), b.vertex_records());
                }
            }
        }
    }

    #[test]
    fn a_lazy_index_finds_each_simplexs_records_as_a_search_of_the_records_does() {
        // Truth: a linear search of the stage's records for each face's ids (neither the face
        // tables nor the lazy index's grouping).
        for (n, g) in [(2, 4), (3, 3)] {
            let mut model = kuhn(n, g);
            let plain = IndexedModel::new(model.clone()).expect("valid");
            let d = 4;
            let mut bezier = Stage::identity(StageKind::Bezier, d);
            let mut rational = Stage::identity(StageKind::Rational, d);
            let mut faces_of: Vec<Vec<u32>> = Vec::new();
            for k in 1..n {
                faces_of.extend(
                    plain
                        .topology()
                        .face_vertices(k)
                        .chunks(k + 1)
                        .map(<[u32]>::to_vec),
                );
            }
            // Top faces too (degree 4 owns interior points of a triangle and a tetrahedron).
            faces_of.extend((0..model.num_simplices()).map(|s| {
                let mut ids = model.simplex(s).to_vec();
                ids.sort_unstable();
                ids
            }));
            for (i, face) in faces_of.iter().enumerate() {
                let owned = owned_count(face.len(), d);
                if owned == 0 {
                    continue;
                }
                let points = vec![1.0 / face.len() as f64; owned * face.len()];
                if i % 3 == 0 {
                    bezier.faces.push(face, &points, &[]);
                }
                if i % 4 == 1 {
                    rational.faces.push(face, &points, &vec![2.0; owned]);
                }
            }
            let mut mono = Stage::identity(StageKind::Monotonic, 2);
            mono.vertex_maps.push(VertexMap {
                vertex: 3,
                coefficients: vec![0.0, 0.4, 1.0],
            });
            model.stages = vec![bezier, mono, rational];
            let eager = IndexedModel::new(model.clone()).expect("valid");
            let lazy = IndexedModel::new_lazy_or_model(model.clone()).expect("valid");
            let m = n + 1;
            for i in [0, 2] {
                let table = &model.stages[i].faces;
                assert!(!table.is_empty(), "n={n} stage {i}");
                let mut found = 0;
                for s in 0..model.num_simplices() {
                    let mut truth = [NONE; 16];
                    for (mask, t) in truth.iter_mut().enumerate().take(1 << m).skip(1) {
                        let face = LocalFace::of_mask(model.simplex(s), mask as u8);
                        if let Some(r) = (0..table.len()).find(|&r| table.face(r) == face.ids()) {
                            *t = r as u32;
                            found += 1;
                        }
                    }
                    assert_eq!(lazy.simplex_records(i, s), truth, "n={n} stage {i} s={s}");
                    assert_eq!(eager.simplex_records(i, s), truth, "n={n} stage {i} s={s}");
                }
                assert!(found > 0, "n={n} stage {i}");
            }
            // Neither the lookups nor a monotonic stage's rows built the lazy index's tables.
            assert_eq!(
                lazy.stage(1).vertex_records(),
                eager.stage(1).vertex_records()
            );
            assert_eq!(lazy.stage(1).coefficients(), eager.stage(1).coefficients());
            assert!(lazy.inner.full.get().is_none());
        }
    }

    #[test]
    fn a_lazy_index_refuses_what_an_eager_one_refuses() {
        let mut model = kuhn(3, 2);
        model.simplices.swap(1, 2); // invert simplex 0
        let mut stage = Stage::identity(StageKind::Bezier, 2);
        stage.faces.push(&[0, 20], &[0.5, 0.5], &[]); // not a face
        model.stages.push(stage);
        let eager = IndexedModel::new(model.clone()).unwrap_err();
        let (back, lazy) = IndexedModel::new_lazy_or_model(model.clone()).unwrap_err();
        assert_eq!(format!("{lazy:?}"), format!("{eager:?}"));
        assert!(format!("{lazy:?}").contains("NotAFace"), "{lazy:?}");
        assert_eq!(back, model);
    }

    #[test]
    fn an_invalid_model_is_refused_with_the_structural_errors() {
        let mut model = kuhn(2, 2);
        model.simplices.swap(1, 2); // invert simplex 0
        let err = IndexedModel::new(model).unwrap_err();
        assert_eq!(err.rule(), Some(crate::rules::Rule::Inverted));
    }
}
