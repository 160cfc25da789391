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
//! - **Stage tables.** [`StageTable`] stores, per face dimension `k`, the owned control points of
//!   every face of that dimension densely (`(k + 1) · C(d − 1, k)` numbers per face, the identity's
//!   where the file has no record) and the weights (`C(d − 1, k)` per face, rational stages), plus
//!   which record, if any, each face came from. A monotonic stage stores `d + 1` coefficients per
//!   vertex. The layout is the one a numpy view wants: one contiguous array per table, fixed stride.
//!
//! Built in parallel (rayon), one vertex star at a time: every face is found from its smallest
//! vertex, so the only sorting is of a star's few dozen entries (linear in the complex overall).

use std::sync::{Arc, OnceLock};

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::model::{Model, StageKind};
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

/// Vertices whose stars are sorted together (in parallel) before their faces are numbered: large
/// enough to keep every core busy, small enough that the block's entries (~100 per vertex) stay a
/// few megabytes.
const STAR_BLOCK: usize = 8192;

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
    /// [`local_faces`]. Empty for `k = 0` and `k = n` (implicit).
    simplex_faces: Vec<Vec<u32>>,
    /// `n + 1` per simplex: the simplex across the facet opposite each local vertex, or [`NONE`].
    neighbours: Vec<u32>,
    /// Per dimension `k` (`1 ≤ k < n`): `nv + 1` offsets; the faces whose smallest vertex is `v`
    /// are `first_face[k][v] .. first_face[k][v + 1]`.
    first_face: Vec<Vec<u32>>,
    /// Vertex → incident simplices, compressed rows (`incidence_start` has `nv + 1` entries).
    incidence_start: Vec<usize>,
    incidence: Vec<u32>,
}

/// Sorted vertex ids of the face of simplex `ids` at local positions `pos[..size]`, padded with
/// `u32::MAX`, and the parity of the permutation that sorted them.
fn sorted_key(ids: &[u32], pos: &[u8], size: usize) -> ([u32; 4], bool) {
    let mut k = [u32::MAX; 4];
    for (slot, &p) in k.iter_mut().zip(&pos[..size]) {
        *slot = ids[p as usize];
    }
    let mut odd = false;
    // Insertion sort counting swaps gives the permutation parity.
    for a in 1..size {
        let mut b = a;
        while b > 0 && k[b - 1] > k[b] {
            k.swap(b - 1, b);
            odd = !odd;
            b -= 1;
        }
    }
    (k, odd)
}

impl Topology {
    /// Indexes the complex of `model`, skipping the simplices flagged in `skip` (those that repeat a
    /// vertex id). The arrays must be well-formed (lengths, index ranges): the structural check
    /// calls this only then. Returns the topology, the duplicate simplices (each with the first
    /// simplex of the same vertex set, in sorted-key order) and the facet defects.
    pub(crate) fn build(
        model: &Model,
        skip: &[bool],
    ) -> (Topology, Vec<(u32, u32)>, Vec<FacetDefect>) {
        Topology::build_in_blocks(model, skip, STAR_BLOCK)
    }

    /// [`Topology::build`] with `block` vertices' stars sorted at a time (any `block ≥ 1` gives
    /// the same result; tests use small blocks).
    fn build_in_blocks(
        model: &Model,
        skip: &[bool],
        block: usize,
    ) -> (Topology, Vec<(u32, u32)>, Vec<FacetDefect>) {
        let n = model.dim();
        let m = n + 1;
        let nv = model.num_vertices();
        let ns = model.num_simplices();
        let ok = |s: usize| !skip.get(s).copied().unwrap_or(false);

        // Vertex → incident simplices first: every face is then found from its smallest vertex,
        // so all the sorting below is of a vertex's star (tens of entries), in parallel, instead
        // of one global sort of millions of keys.
        let mut incidence_start = vec![0usize; nv + 1];
        for s in (0..ns).filter(|&s| ok(s)) {
            for &v in model.simplex(s) {
                incidence_start[v as usize + 1] += 1;
            }
        }
        for v in 0..nv {
            incidence_start[v + 1] += incidence_start[v];
        }
        let mut fill = incidence_start.clone();
        let mut incidence = vec![0u32; incidence_start[nv]];
        for s in (0..ns).filter(|&s| ok(s)) {
            for &v in model.simplex(s) {
                incidence[fill[v as usize]] = s as u32;
                fill[v as usize] += 1;
            }
        }
        drop(fill);
        let star = |v: usize| &incidence[incidence_start[v]..incidence_start[v + 1]];

        // Faces of each dimension `k` whose smallest vertex is `v`: (key, side, simplex, local
        // face index) sorted by key, side, simplex — the order in which defects are reported.
        type Entry = ([u32; 4], bool, u32, u8);
        let entries_of = |v: usize, size: usize| -> Vec<Entry> {
            let locals = local_faces(m, size);
            let mut out = Vec::new();
            for &s in star(v) {
                let ids = model.simplex(s as usize);
                for (j, pos) in locals.iter().enumerate() {
                    if !pos[..size].iter().any(|&p| ids[p as usize] == v as u32) {
                        continue;
                    }
                    let (key, odd) = sorted_key(ids, pos, size);
                    if key[0] != v as u32 {
                        continue;
                    }
                    // The facet opposite local vertex i carries sign (-1)^i: positions are sorted,
                    // so the missing one is the first i with pos[i] != i.
                    let missing = (0..m).find(|&i| i >= size || pos[i] as usize != i);
                    let side = odd ^ missing.is_some_and(|i| i % 2 == 1);
                    out.push((key, side, s, j as u8));
                }
            }
            out.sort_unstable();
            out
        };

        // Top faces: duplicates share their smallest vertex.
        let duplicates: Vec<(u32, u32)> = (0..nv)
            .into_par_iter()
            .flat_map_iter(|v| {
                let e = entries_of(v, m);
                let mut found = Vec::new();
                for w in e.windows(2) {
                    if w[0].0 == w[1].0 {
                        found.push((w[1].2, w[0].2));
                    }
                }
                found
            })
            .collect();

        let mut faces = vec![Vec::new(); m];
        let mut simplex_faces = vec![Vec::new(); m];
        let mut first_face = vec![Vec::new(); m];
        let mut neighbours = vec![NONE; ns * m];
        let mut defects = Vec::new();
        for k in 1..n {
            let size = k + 1;
            let locals = local_faces(m, size);
            let per = locals.len();
            let mut table = Vec::new();
            let mut of_simplex = vec![NONE; ns * per];
            let mut first = Vec::with_capacity(nv + 1);
            let mut id = 0u32;
            // Stars in parallel, a block of vertices at a time: the sorted entries of a block are
            // numbered in order and dropped, so the temporary memory stays a block's, not the
            // whole complex's.
            let groups = (0..nv).step_by(block.max(1)).flat_map(|start| {
                (start..nv.min(start.saturating_add(block.max(1))))
                    .into_par_iter()
                    .map(|v| entries_of(v, size))
                    .collect::<Vec<Vec<Entry>>>()
            });
            for entries in groups {
                first.push(id);
                let mut i = 0;
                while i < entries.len() {
                    let mut j = i + 1;
                    while j < entries.len() && entries[j].0 == entries[i].0 {
                        j += 1;
                    }
                    let group = &entries[i..j];
                    table.extend_from_slice(&group[0].0[..size]);
                    for &(_, _, s, local) in group {
                        of_simplex[s as usize * per + local as usize] = id;
                    }
                    if k == n - 1 {
                        let face = group[0].0[..size].to_vec();
                        if group.len() > 2 {
                            defects.push(FacetDefect::Overshared {
                                face,
                                simplices: group.iter().map(|g| g.2).collect(),
                            });
                        } else if group.len() == 2 {
                            let (a, b) = (group[0].2, group[1].2);
                            if group[0].1 == group[1].1 {
                                if a != b {
                                    defects.push(FacetDefect::Overlap {
                                        face,
                                        first: a,
                                        second: b,
                                    });
                                }
                            } else {
                                // A facet-sized subset omits exactly one local position.
                                let opposite = |g: &Entry| {
                                    let pos = &locals[g.3 as usize];
                                    (0..m).find(|&i| !pos[..size].contains(&(i as u8)))
                                };
                                if let (Some(oa), Some(ob)) =
                                    (opposite(&group[0]), opposite(&group[1]))
                                {
                                    neighbours[a as usize * m + oa] = b;
                                    neighbours[b as usize * m + ob] = a;
                                }
                            }
                        }
                    }
                    id += 1;
                    i = j;
                }
            }
            first.push(id);
            faces[k] = table;
            simplex_faces[k] = of_simplex;
            first_face[k] = first;
        }
        if n == 1 {
            // Facets are vertices: pair the (at most two) segments at each vertex.
            for v in 0..nv {
                if let [a, b] = star(v) {
                    let (a, b) = (*a as usize, *b as usize);
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
            neighbours,
            incidence_start,
            incidence,
        };
        (topology, duplicates, defects)
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
            k if k < self.n => self.faces[k].len() / (k + 1),
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

    /// The face ids of dimension `k` of every simplex, `C(n + 1, k + 1)` per simplex, for
    /// `1 ≤ k < n` (empty otherwise).
    pub fn simplex_face_table(&self, k: usize) -> &[u32] {
        self.simplex_faces.get(k).map_or(&[], Vec::as_slice)
    }

    /// The simplex across the facet of `s` opposite its local vertex `i`, or `None` on the boundary.
    pub fn neighbour(&self, s: usize, i: usize) -> Option<SimplexId> {
        let t = self.neighbours[s * (self.n + 1) + i];
        (t != NONE).then_some(SimplexId(t))
    }

    /// All facet neighbours, `n + 1` per simplex, [`NONE`] on the boundary.
    pub fn neighbours(&self) -> &[u32] {
        &self.neighbours
    }

    /// The simplices incident to vertex `v`.
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
            return self
                .vertex_simplices(v)
                .iter()
                .find(|&&s| {
                    let mut key = [0u32; 4];
                    key[..size].copy_from_slice(model.simplex(s as usize));
                    key[..size].sort_unstable();
                    key[..size] == *face
                })
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

/// One stage's control data in flat tables addressed by face index (see the module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct StageTable {
    kind: StageKind,
    degree: u32,
    /// Per dimension `k`: the record (index into the stage's `faces`) of each face, or [`NONE`].
    record: Vec<Vec<u32>>,
    /// Per dimension `k`: `(k + 1) · C(d − 1, k)` owned control point coordinates per face.
    points: Vec<Vec<f64>>,
    /// Per dimension `k` (rational stages): `C(d − 1, k)` weights per face.
    weights: Vec<Vec<f64>>,
    /// Monotonic: the vertex map record of each vertex, or [`NONE`].
    vertex_record: Vec<u32>,
    /// Monotonic: `d + 1` coefficients per vertex.
    coefficients: Vec<f64>,
}

impl StageTable {
    /// `faces`: the face of each record, as the structural check found it.
    fn build(
        model: &Model,
        topology: &Topology,
        stage_index: usize,
        faces: &[Option<FaceId>],
    ) -> StageTable {
        let stage = &model.stages[stage_index];
        let d = stage.degree;
        let n = topology.dim();
        let mut table = StageTable {
            kind: stage.kind,
            degree: d,
            record: Vec::new(),
            points: Vec::new(),
            weights: Vec::new(),
            vertex_record: Vec::new(),
            coefficients: Vec::new(),
        };
        match stage.kind {
            StageKind::Monotonic => {
                let nv = topology.num_vertices();
                let per = d as usize + 1;
                table.vertex_record = vec![NONE; nv];
                table.coefficients = (0..nv * per)
                    .map(|i| (i % per) as f64 / f64::from(d))
                    .collect();
                for (r, map) in stage.vertex_maps.iter().enumerate() {
                    let v = map.vertex as usize;
                    table.vertex_record[v] = r as u32;
                    table.coefficients[v * per..(v + 1) * per].copy_from_slice(&map.coefficients);
                }
            }
            StageKind::Bezier | StageKind::Rational => {
                let rational = stage.kind == StageKind::Rational;
                for k in 0..=n {
                    let size = k + 1;
                    let owned = owned_count(size, d);
                    let rows = topology.face_slots(k);
                    table.record.push(vec![NONE; rows]);
                    // The identity: owned multi-index J of the face has control point J / d.
                    let identity: Vec<f64> = crate::multi_index::owned(size, d)
                        .iter()
                        .map(|&e| f64::from(e) / f64::from(d))
                        .collect();
                    let mut points = Vec::with_capacity(rows * identity.len());
                    for _ in 0..rows {
                        points.extend_from_slice(&identity);
                    }
                    table.points.push(points);
                    table.weights.push(if rational {
                        vec![1.0; rows * owned]
                    } else {
                        Vec::new()
                    });
                }
                for (r, (rec, id)) in stage.faces.iter().zip(faces).enumerate() {
                    let Some(id) = *id else { continue };
                    let (k, i) = (id.dim as usize, id.index as usize);
                    let owned = owned_count(k + 1, d);
                    table.record[k][i] = r as u32;
                    let stride = owned * (k + 1);
                    table.points[k][i * stride..(i + 1) * stride].copy_from_slice(rec.points);
                    if rational && !rec.weights.is_empty() {
                        table.weights[k][i * owned..(i + 1) * owned].copy_from_slice(rec.weights);
                    }
                }
            }
        }
        table
    }

    /// The map kind.
    pub fn kind(&self) -> StageKind {
        self.kind
    }

    /// The degree `d`.
    pub fn degree(&self) -> u32 {
        self.degree
    }

    /// Owned control point coordinates of every dimension-`k` face, `(k + 1) · C(d − 1, k)` per
    /// face (barycentric w.r.t. the face's sorted vertices), the identity's where no record exists.
    /// Empty for monotonic stages.
    pub fn points(&self, k: usize) -> &[f64] {
        self.points.get(k).map_or(&[], Vec::as_slice)
    }

    /// Weights of every dimension-`k` face, `C(d − 1, k)` per face, 1 where no record exists.
    /// Empty unless the stage is rational.
    pub fn weights(&self, k: usize) -> &[f64] {
        self.weights.get(k).map_or(&[], Vec::as_slice)
    }

    /// The record of each dimension-`k` face ([`NONE`] where the file has none).
    pub fn records(&self, k: usize) -> &[u32] {
        self.record.get(k).map_or(&[], Vec::as_slice)
    }

    /// The record of face `face`, if the file has one.
    pub fn record_of(&self, face: FaceId) -> Option<usize> {
        let r = *self
            .record
            .get(face.dim as usize)?
            .get(face.index as usize)?;
        (r != NONE).then_some(r as usize)
    }

    /// Owned control point coordinates of one face.
    pub fn face_points(&self, face: FaceId) -> &[f64] {
        let k = face.dim as usize;
        let stride = owned_count(k + 1, self.degree) * (k + 1);
        &self.points[k][face.index as usize * stride..(face.index as usize + 1) * stride]
    }

    /// Weights of one face (rational stages; empty otherwise).
    pub fn face_weights(&self, face: FaceId) -> &[f64] {
        if self.weights.is_empty() || self.weights[face.dim as usize].is_empty() {
            return &[];
        }
        let owned = owned_count(face.dim as usize + 1, self.degree);
        let i = face.index as usize;
        &self.weights[face.dim as usize][i * owned..(i + 1) * owned]
    }

    /// Monotonic: the `d + 1` coefficients of every vertex (the identity's `j / d` where the file
    /// has no map). Empty for other kinds.
    pub fn coefficients(&self) -> &[f64] {
        &self.coefficients
    }

    /// Monotonic: the vertex map record of each vertex ([`NONE`] where the file has none).
    pub fn vertex_records(&self) -> &[u32] {
        &self.vertex_record
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
    topology: Topology,
    stages: Vec<StageTable>,
    diagnostics: Vec<crate::rules::Diagnostic>,
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
    /// # Errors
    /// [`Error::Structure`] with the errors that prevent indexing.
    pub fn for_evaluation(model: Model) -> Result<IndexedModel> {
        IndexedModel::build(model, usize::MAX, |rule| {
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
        })
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
        let (diagnostics, topology) = crate::structure::check_indexed(&model, max);
        let (errors, diagnostics): (Vec<_>, Vec<_>) = diagnostics
            .into_iter()
            .partition(|d| d.severity == Severity::Error && fatal(d.rule));
        let (topology, record_faces) = match topology {
            Some((t, faces)) if errors.is_empty() && faces.len() == model.stages.len() => {
                (t, faces)
            }
            _ => return Err((model, Error::Structure(errors))),
        };
        let stages = (0..model.stages.len())
            .into_par_iter()
            .map(|i| StageTable::build(&model, &topology, i, &record_faces[i]))
            .collect();
        Ok(IndexedModel {
            inner: Arc::new(Inner {
                model,
                topology,
                stages,
                diagnostics,
            }),
        })
    }

    /// The model as stored in the file.
    pub fn model(&self) -> &Model {
        &self.inner.model
    }

    /// The topology of the complex.
    pub fn topology(&self) -> &Topology {
        &self.inner.topology
    }

    /// The flat tables of stage `i`.
    ///
    /// # Panics
    /// If `i` is out of range.
    pub fn stage(&self, i: usize) -> &StageTable {
        &self.inner.stages[i]
    }

    /// The flat tables of every stage, in application order.
    pub fn stages(&self) -> &[StageTable] {
        &self.inner.stages
    }

    /// The structural diagnostics that did not prevent indexing: warnings (e.g. unused vertices)
    /// and, for [`IndexedModel::for_evaluation`], the errors it tolerates.
    pub fn diagnostics(&self) -> &[crate::rules::Diagnostic] {
        &self.inner.diagnostics
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

    /// A Kuhn triangulation of the grid `g^n` (positively oriented): the ground truth below is
    /// computed by brute force over vertex subsets, independently of the sort-based index.
    fn kuhn(n: usize, g: usize) -> Model {
        let mut model = Model::new(n as u8);
        let side = g + 1;
        let id = |c: &[usize]| c.iter().rev().fold(0, |acc, &x| acc * side + x) as u32;
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
        let perms: Vec<Vec<usize>> = if n == 2 {
            vec![vec![0, 1], vec![1, 0]]
        } else {
            vec![
                vec![0, 1, 2],
                vec![0, 2, 1],
                vec![1, 0, 2],
                vec![1, 2, 0],
                vec![2, 0, 1],
                vec![2, 1, 0],
            ]
        };
        for cell in 0..g.pow(n as u32) {
            let mut base = vec![0usize; n];
            let mut rest = cell;
            for b in base.iter_mut() {
                *b = rest % g;
                rest /= g;
            }
            for p in &perms {
                let mut c = base.clone();
                let mut ids = vec![id(&c)];
                for &axis in p {
                    c[axis] += 1;
                    ids.push(id(&c));
                }
                // A Kuhn simplex's orientation is the sign of its permutation.
                let inversions = (0..n)
                    .flat_map(|a| (a + 1..n).map(move |b| (a, b)))
                    .filter(|&(a, b)| p[a] > p[b])
                    .count();
                if inversions % 2 == 1 {
                    ids.swap(1, 2);
                }
                model.simplices.extend(ids);
            }
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
    fn faces_neighbours_and_euler_characteristic_match_brute_force() {
        for (n, g) in [(2, 4), (3, 3)] {
            let model = kuhn(n, g);
            let indexed = IndexedModel::new(model.clone()).expect("a Kuhn grid is valid");
            let t = indexed.topology();
            let m = n + 1;
            let mut euler = 0i64;
            for k in 0..=n {
                let brute = brute_faces(&model, k + 1);
                assert_eq!(t.num_faces(k), brute.len(), "n={n} k={k}");
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
            let whole = Topology::build_in_blocks(&model, &skip, usize::MAX);
            for block in [1, 3, 7] {
                assert_eq!(Topology::build_in_blocks(&model, &skip, block), whole);
            }
        }
    }

    #[test]
    fn an_invalid_model_is_refused_with_the_structural_errors() {
        let mut model = kuhn(2, 2);
        model.simplices.swap(1, 2); // invert simplex 0
        let err = IndexedModel::new(model).unwrap_err();
        assert_eq!(err.rule(), Some(crate::rules::Rule::Inverted));
    }
}
