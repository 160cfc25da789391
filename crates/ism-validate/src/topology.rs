//! Non-manifold vertices and edges (ISM-150, a warning; spec/validation.md §2).
//!
//! A vertex is manifold when its link is a disk or a sphere (a path or a cycle in 2D); an edge of a
//! 3D complex when its link is a path or a cycle. Facets are shared by at most two simplices (the
//! reader enforces ISM-109), so a link is always a pseudo-manifold and it suffices to check that the
//! star is connected through facets containing the vertex (or edge) and, for 3D vertices, the
//! Euler characteristic of the link: 1 (disk) when it has boundary, 2 (sphere) when closed.

use ism_format::indexed::simplex_faces;
use ism_format::{IndexedModel, Location, Model, Rule};
use rayon::prelude::*;

use crate::report::Message;

/// Union–find over small local index sets.
#[derive(Default)]
struct Dsu(Vec<u32>);

impl Dsu {
    /// Resets to `n` singletons, reusing the allocation.
    fn reset(&mut self, n: usize) {
        self.0.clear();
        self.0.extend(0..n as u32);
    }
    fn find(&mut self, mut x: u32) -> u32 {
        while self.0[x as usize] != x {
            let p = self.0[x as usize];
            self.0[x as usize] = self.0[p as usize];
            x = p;
        }
        x
    }
    fn union(&mut self, a: u32, b: u32) {
        let (a, b) = (self.find(a), self.find(b));
        if a != b {
            self.0[a.max(b) as usize] = a.min(b);
        }
    }
}

/// The message for a star of `r` simplices around a `k`-vertex face whose facet-adjacency
/// components (`dsu`, over the star's local indices) are more than one: the star is then joined
/// only at the face. `roots` is scratch space, reused across stars.
fn split_star(dsu: &mut Dsu, roots: &mut Vec<u32>, r: usize, k: usize) -> Option<String> {
    roots.clear();
    roots.extend((0..r as u32).map(|i| dsu.find(i)));
    roots.sort_unstable();
    roots.dedup();
    (roots.len() > 1).then(|| {
        format!(
            "its star falls into {} parts joined only at this {}",
            roots.len(),
            if k == 1 { "vertex" } else { "edge" }
        )
    })
}

/// Sorted `(key, simplex)` pairs of the `k`-vertex faces of every simplex (built and sorted on every
/// core: on a million tetrahedra these lists hold millions of entries).
fn faces_of_size(model: &Model, k: usize) -> Vec<([u32; 4], u32)> {
    let mut out: Vec<([u32; 4], u32)> = (0..model.num_simplices())
        .into_par_iter()
        .flat_map_iter(|s| {
            let faces = simplex_faces(model.simplex(s), k).filter(move |f| f.len() == k);
            faces.map(move |f| {
                let mut key = [u32::MAX; 4];
                key[..k].copy_from_slice(f.ids());
                (key, s as u32)
            })
        })
        .collect();
    out.par_sort_unstable();
    out
}

/// Groups of equal keys in a sorted list: `(key, range)`.
fn groups(list: &[([u32; 4], u32)]) -> Vec<([u32; 4], std::ops::Range<usize>)> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < list.len() {
        let mut j = i + 1;
        while j < list.len() && list[j].0 == list[i].0 {
            j += 1;
        }
        out.push((list[i].0, i..j));
        i = j;
    }
    out
}

/// The ids of `simplex` other than those of the face `key` (first `k` entries), in stored order.
fn others(ids: &[u32], key: &[u32; 4], k: usize) -> ([u32; 4], usize) {
    let mut out = [u32::MAX; 4];
    let mut len = 0;
    for &id in ids {
        if !key[..k].contains(&id) {
            out[len] = id;
            len += 1;
        }
    }
    (out, len)
}

/// Why the star of one face (`k` vertices; its simplices `members`) is not a manifold star, if it
/// is not. Everything is local to the star, so stars are checked independently, on every core.
///
/// Two simplices of the star are joined when they share a facet held by exactly these two (a facet
/// held by more is an ISM-109 error and joins nothing). Such a facet contains the face, so every
/// simplex holding it is in the star: sorting the star's facets through the face finds them all.
fn star_defect(
    model: &Model,
    key: &[u32; 4],
    k: usize,
    members: &[u32],
    scratch: &mut Scratch,
) -> Option<String> {
    let n = model.dim();
    let r = members.len();
    // (facet key, local index) for each facet of each member that contains the face: the face's
    // ids plus all but one of the member's other ids.
    let Scratch {
        facets,
        dsu,
        roots,
        verts,
        tris,
    } = scratch;
    facets.clear();
    for (local, &s) in members.iter().enumerate() {
        let (rest, len) = others(model.simplex(s as usize), key, k);
        for skip in 0..len {
            let mut f = [u32::MAX; 4];
            f[..k].copy_from_slice(&key[..k]);
            let mut at = k;
            for (j, &id) in rest[..len].iter().enumerate() {
                if j != skip {
                    f[at] = id;
                    at += 1;
                }
            }
            f[..at].sort_unstable();
            facets.push((f, local as u32));
        }
    }
    facets.sort_unstable();
    dsu.reset(r);
    let mut i = 0;
    while i < facets.len() {
        let mut j = i + 1;
        while j < facets.len() && facets[j].0 == facets[i].0 {
            j += 1;
        }
        if j - i == 2 {
            dsu.union(facets[i].1, facets[i + 1].1);
        }
        i = j;
    }
    if let Some(message) = split_star(dsu, roots, r, k) {
        return Some(message);
    }
    if k == 1 && n == 3 {
        // Euler characteristic of the link: vertices − edges + triangles of the link, i.e. the
        // star's edges, triangles and tetrahedra through the vertex.
        verts.clear();
        tris.clear();
        for &s in members {
            let (o, len) = others(model.simplex(s as usize), key, 1);
            verts.extend_from_slice(&o[..len]);
            for a in 0..len {
                for b in (a + 1)..len {
                    tris.push([o[a].min(o[b]), o[a].max(o[b])]);
                }
            }
        }
        verts.sort_unstable();
        verts.dedup();
        tris.sort_unstable();
        // A link edge held once is on the boundary of the link.
        let mut boundary = false;
        let mut distinct = 0usize;
        let mut i = 0;
        while i < tris.len() {
            let mut j = i + 1;
            while j < tris.len() && tris[j] == tris[i] {
                j += 1;
            }
            boundary |= j - i == 1;
            distinct += 1;
            i = j;
        }
        let chi = verts.len() as i64 - distinct as i64 + r as i64;
        let expect = if boundary { 1 } else { 2 };
        if chi != expect {
            return Some(format!(
                "its link has Euler characteristic {chi}; a manifold vertex has a disk (1) or sphere (2) link"
            ));
        }
    }
    None
}

/// Buffers of [`star_defect`], reused from star to star (no allocation per star).
#[derive(Default)]
struct Scratch {
    facets: Vec<([u32; 4], u32)>,
    dsu: Dsu,
    roots: Vec<u32>,
    verts: Vec<u32>,
    tris: Vec<[u32; 2]>,
}

/// The ISM-150 message of a star `members` of the face `key` (`k` vertices), if it is not a
/// manifold star; `why` decides.
fn star_message(
    model: &Model,
    key: &[u32; 4],
    k: usize,
    members: &[u32],
    why: Option<String>,
) -> Option<Message> {
    let n = model.dim();
    let m = n + 1;
    let why = why?;
    let first = members[0] as usize;
    let loc = if k == 1 {
        Location {
            vertex: Some(key[0] as usize),
            ..Location::pointer(format!("/vertices/{}", key[0] as usize * n))
        }
    } else {
        Location {
            simplex: Some(first),
            face: Some(key[..k].to_vec()),
            ..Location::pointer(format!("/simplices/{}", first * m))
        }
    };
    let what = if k == 1 { "vertex" } else { "edge" };
    Some(Message::new(
        Rule::NonManifold,
        loc,
        format!("non-manifold {what}: {why}"),
    ))
}

/// [`star_defect`] on an indexed model (no structural error, so a facet has a neighbour across it
/// exactly when two simplices hold it on opposite sides): the star's simplices are joined through
/// the topology's facet neighbours, with no sorting of facets. `members` ascending.
fn star_defect_indexed(
    model: &Model,
    topology: &ism_format::Topology,
    key: &[u32; 4],
    k: usize,
    members: &[u32],
    scratch: &mut Scratch,
) -> Option<String> {
    let n = model.dim();
    let r = members.len();
    let Scratch {
        dsu, roots, verts, ..
    } = scratch;
    dsu.reset(r);
    // Facets of the star through the face held by one simplex only (boundary of the link).
    let mut held_once = 0usize;
    for (local, &s) in members.iter().enumerate() {
        let ids = model.simplex(s as usize);
        for (i, id) in ids.iter().enumerate() {
            // The facet opposite local vertex i contains the face unless i is one of its vertices.
            if key[..k].contains(id) {
                continue;
            }
            match topology.neighbour(s as usize, i) {
                Some(t) => {
                    if let Ok(j) = members.binary_search(&t.0) {
                        dsu.union(local as u32, j as u32);
                    }
                }
                None => held_once += 1,
            }
        }
    }
    if let Some(message) = split_star(dsu, roots, r, k) {
        return Some(message);
    }
    if k == 1 && n == 3 {
        // Euler characteristic of the link: its vertices (the star's edges through the vertex),
        // edges (triangles: 3 per tetrahedron, interior ones counted twice) and triangles.
        verts.clear();
        for &s in members {
            let (o, len) = others(model.simplex(s as usize), key, 1);
            verts.extend_from_slice(&o[..len]);
        }
        verts.sort_unstable();
        verts.dedup();
        let triangles = (3 * r + held_once) / 2;
        let chi = verts.len() as i64 - triangles as i64 + r as i64;
        let expect = if held_once > 0 { 1 } else { 2 };
        if chi != expect {
            return Some(format!(
                "its link has Euler characteristic {chi}; a manifold vertex has a disk (1) or sphere (2) link"
            ));
        }
    }
    None
}

/// [`non_manifold`] on an indexed model: the stars come from its topology (vertex incidence) and
/// are joined through its facet neighbours, so nothing is sorted globally and no facet is sorted
/// per star. One parallel pass over the vertices: the star of each edge is found in the star of
/// its smaller vertex (the edges of `v` in increasing order of their other vertex, i.e. in edge
/// order). Same messages, same order (edges first, then vertices).
pub fn non_manifold_indexed(indexed: &IndexedModel) -> Vec<Message> {
    let model: &Model = indexed;
    let topology = indexed.topology();
    let n = model.dim();
    #[derive(Default)]
    struct Buffers {
        scratch: Scratch,
        /// (other vertex, simplex) of the edges from a vertex to a larger one, packed.
        pairs: Vec<u64>,
        members: Vec<u32>,
    }
    let found: Vec<(Vec<Message>, Option<Message>)> = (0..model.num_vertices())
        .into_par_iter()
        .map_init(Buffers::default, |buf, v| {
            let star = topology.vertex_simplices(v);
            if star.is_empty() {
                return None;
            }
            let v32 = v as u32;
            let mut edges = Vec::new();
            if n == 3 {
                let Buffers {
                    scratch,
                    pairs,
                    members,
                } = buf;
                pairs.clear();
                for &s in star {
                    for &b in model.simplex(s as usize) {
                        if b > v32 {
                            pairs.push(u64::from(b) << 32 | u64::from(s));
                        }
                    }
                }
                // By other vertex, then simplex: each edge's star ascending.
                pairs.sort_unstable();
                let mut i = 0;
                while i < pairs.len() {
                    let b = (pairs[i] >> 32) as u32;
                    members.clear();
                    while i < pairs.len() && (pairs[i] >> 32) as u32 == b {
                        members.push(pairs[i] as u32);
                        i += 1;
                    }
                    let key = [v32, b, u32::MAX, u32::MAX];
                    let why = star_defect_indexed(model, topology, &key, 2, members, scratch);
                    edges.extend(star_message(model, &key, 2, members, why));
                }
            }
            let key = [v32, u32::MAX, u32::MAX, u32::MAX];
            let why = star_defect_indexed(model, topology, &key, 1, star, &mut buf.scratch);
            let vertex = star_message(model, &key, 1, star, why);
            (!edges.is_empty() || vertex.is_some()).then_some((edges, vertex))
        })
        .flatten()
        .collect();
    let (mut out, mut vertices) = (Vec::new(), Vec::new());
    for (edges, vertex) in found {
        out.extend(edges);
        vertices.extend(vertex);
    }
    out.extend(vertices);
    out
}

/// Buffers of [`vertex_defect`], reused from star to star.
#[derive(Default)]
struct StarScratch {
    dsu: Dsu,
    roots: Vec<u32>,
    /// Open-addressing table of the star's facets through the vertex, keyed by their other ids
    /// (packed): `(key, first member's local index, stamp)`; a slot of an older stamp is empty.
    facets: Vec<(u64, u32, u32)>,
    /// The same for the link's vertices (the star's other ids).
    verts: Vec<(u32, u32)>,
    stamp: u32,
}

/// Slot of `key` in a table of `2^bits` slots (Fibonacci hashing).
#[inline]
fn slot(key: u64, bits: u32) -> usize {
    (key.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> (64 - bits)) as usize
}

/// [`star_defect`] for a vertex `v` (`k = 1`) of a complex without structural errors (a facet is
/// held by at most two simplices): the same test, with the star's facets through `v` and the
/// link's vertices counted in small hash tables instead of sorted.
fn vertex_defect(model: &Model, v: u32, members: &[u32], buf: &mut StarScratch) -> Option<String> {
    let n = model.dim();
    let r = members.len();
    let StarScratch {
        dsu,
        roots,
        facets,
        verts,
        stamp,
    } = buf;
    // At most n facets through v and n link vertices per member: tables at most half full.
    let bits = (2 * n * r).next_power_of_two().trailing_zeros().max(4);
    let size = 1usize << bits;
    if facets.len() < size {
        facets.resize(size, (0, 0, 0));
        verts.resize(size, (0, 0));
    }
    *stamp = stamp.wrapping_add(1);
    if *stamp == 0 {
        // Wrapped: forget every older stamp.
        facets.iter_mut().for_each(|e| e.2 = 0);
        verts.iter_mut().for_each(|e| e.1 = 0);
        *stamp = 1;
    }
    let stamp = *stamp;
    dsu.reset(r);
    let (mut entries, mut distinct, mut link_vertices) = (0usize, 0usize, 0usize);
    let mut facet = |key: u64, local: u32, dsu: &mut Dsu| {
        entries += 1;
        let mut at = slot(key, bits);
        loop {
            let e = &mut facets[at];
            if e.2 != stamp {
                *e = (key, local, stamp);
                distinct += 1;
                return;
            }
            if e.0 == key {
                // The second member holding this facet (no facet has a third).
                dsu.union(e.1, local);
                return;
            }
            at = (at + 1) & (size - 1);
        }
    };
    for (local, &s) in members.iter().enumerate() {
        let mut o = [0u32; 3];
        let mut len = 0;
        for &id in model.simplex(s as usize) {
            if id != v && len < 3 {
                o[len] = id;
                len += 1;
            }
        }
        let local = local as u32;
        if n == 3 {
            // The facets through v: v and two of the three others.
            for (a, b) in [(0, 1), (0, 2), (1, 2)] {
                let (x, y) = (o[a].min(o[b]), o[a].max(o[b]));
                facet(u64::from(x) << 32 | u64::from(y), local, dsu);
            }
            for &x in &o[..3] {
                let mut at = slot(u64::from(x), bits);
                loop {
                    let e = &mut verts[at];
                    if e.1 != stamp {
                        *e = (x, stamp);
                        link_vertices += 1;
                        break;
                    }
                    if e.0 == x {
                        break;
                    }
                    at = (at + 1) & (size - 1);
                }
            }
        } else {
            for &x in &o[..len] {
                facet(u64::from(x), local, dsu);
            }
        }
    }
    if let Some(message) = split_star(dsu, roots, r, 1) {
        return Some(message);
    }
    if n == 3 {
        // Euler characteristic of the link: its vertices, edges (the facets through v) and
        // triangles (the members). A facet held once is on the link's boundary: each facet is
        // held once or twice, so `entries = once + 2 · twice` and `distinct = once + twice`.
        let boundary = 2 * distinct > entries;
        let chi = link_vertices as i64 - distinct as i64 + r as i64;
        let expect = if boundary { 1 } else { 2 };
        if chi != expect {
            return Some(format!(
                "its link has Euler characteristic {chi}; a manifold vertex has a disk (1) or sphere (2) link"
            ));
        }
    }
    None
}

/// [`non_manifold`] on an indexed model without structural errors, from its vertex → simplex
/// incidence alone ([`IndexedModel::vertex_simplices`]: a lazily indexed model builds no face
/// tables for it). Same messages, same order (edges first, then vertices).
///
/// Every vertex star is tested on every core. Edges are tested only between two non-manifold
/// vertices: when a vertex `v` passes, its link is a disk or a sphere (the link is a
/// pseudo-surface — a facet is held by at most two simplices — connected through its edges; its
/// normalisation is then a connected surface of Euler characteristic at least the link's, and a
/// connected surface has at most 2, or 1 with boundary, so the link is its own normalisation, a
/// sphere or a disk). The star of an edge `{v, b}` is the star of `b` in the link of `v`, joined
/// through the link's edges at `b`: in a disk or a sphere, a fan — connected, so the edge is
/// manifold.
pub fn non_manifold_stars(indexed: &IndexedModel) -> Vec<Message> {
    let model: &Model = indexed;
    let n = model.dim();
    let bad: Vec<(u32, Message)> = (0..model.num_vertices())
        .into_par_iter()
        .map_init(StarScratch::default, |buf, v| {
            let star = indexed.vertex_simplices(v);
            if star.is_empty() {
                return None;
            }
            let why = vertex_defect(model, v as u32, star, buf);
            let key = [v as u32, u32::MAX, u32::MAX, u32::MAX];
            star_message(model, &key, 1, star, why).map(|m| (v as u32, m))
        })
        .flatten()
        .collect();
    let mut out = Vec::new();
    if n == 3 {
        let is_bad = |b: u32| bad.binary_search_by_key(&b, |x| x.0).is_ok();
        let edges: Vec<Vec<Message>> = bad
            .par_iter()
            .map_init(
                || (Scratch::default(), Vec::new(), Vec::new()),
                |(scratch, others, members), &(v, _)| {
                    let star = indexed.vertex_simplices(v as usize);
                    others.clear();
                    for &s in star {
                        others.extend(
                            model
                                .simplex(s as usize)
                                .iter()
                                .filter(|&&b| b > v && is_bad(b)),
                        );
                    }
                    others.sort_unstable();
                    others.dedup();
                    let mut found = Vec::new();
                    for &b in others.iter() {
                        members.clear();
                        members.extend(
                            star.iter()
                                .filter(|&&s| model.simplex(s as usize).contains(&b)),
                        );
                        let key = [v, b, u32::MAX, u32::MAX];
                        let why = star_defect(model, &key, 2, members, scratch);
                        found.extend(star_message(model, &key, 2, members, why));
                    }
                    found
                },
            )
            .collect();
        out.extend(edges.into_iter().flatten());
    }
    out.extend(bad.into_iter().map(|(_, m)| m));
    out
}

/// ISM-150 warnings. The model must have passed the structural checks that index vertices.
pub fn non_manifold(model: &Model) -> Vec<Message> {
    let n = model.dim();
    let mut out = Vec::new();
    let check = |k: usize, out: &mut Vec<Message>| {
        let list = faces_of_size(model, k);
        let star = groups(&list);
        let found: Vec<Message> = star
            .par_iter()
            .map_init(Scratch::default, |scratch, (key, range)| {
                let members: Vec<u32> = list[range.clone()].iter().map(|x| x.1).collect();
                let why = star_defect(model, key, k, &members, scratch);
                star_message(model, key, k, &members, why)
            })
            .flatten()
            .collect();
        out.extend(found);
    };
    if n == 3 {
        check(2, &mut out);
    }
    check(1, &mut out);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use ism_format::builder::ModelBuilder;

    #[test]
    fn bowtie_vertex_is_non_manifold() {
        // Two triangles touching at vertex 0 only.
        let model = ModelBuilder::new(2)
            .vertex(&[0.0, 0.0], -1.0)
            .vertex(&[1.0, 0.0], 1.0)
            .vertex(&[1.0, 1.0], 1.0)
            .vertex(&[-1.0, 0.0], 1.0)
            .vertex(&[-1.0, -1.0], 1.0)
            .simplex(&[0, 1, 2])
            .simplex(&[0, 3, 4])
            .build()
            .unwrap();
        let w = non_manifold(&model);
        assert_eq!(w.len(), 1, "{w:?}");
        assert_eq!(w[0].location.vertex, Some(0));
        same_from_the_index(&model);
    }

    #[test]
    fn fan_and_closed_star_are_manifold() {
        // A square of two triangles and a hexagon around an interior vertex.
        let mut b = ModelBuilder::new(2).vertex(&[0.0, 0.0], -1.0);
        for i in 0..6 {
            let a = std::f64::consts::PI / 3.0 * f64::from(i);
            b = b.vertex(&[a.cos(), a.sin()], 1.0);
        }
        for i in 0..6u32 {
            b = b.simplex(&[0, 1 + i, 1 + (i + 1) % 6]);
        }
        let model = b.build().unwrap();
        assert!(non_manifold(&model).is_empty());
        same_from_the_index(&model);
    }

    #[test]
    fn tetrahedra_sharing_an_edge_only() {
        let model = ModelBuilder::new(3)
            .vertex(&[0.0, 0.0, 0.0], -1.0)
            .vertex(&[1.0, 0.0, 0.0], 1.0)
            .vertex(&[0.0, 1.0, 0.0], 1.0)
            .vertex(&[0.0, 0.0, 1.0], 1.0)
            .vertex(&[0.0, -1.0, 0.0], 1.0)
            .vertex(&[0.0, 0.0, -1.0], 1.0)
            .simplex(&[0, 1, 2, 3])
            .simplex(&[0, 1, 4, 5])
            .build()
            .unwrap();
        let w = non_manifold(&model);
        // The edge {0,1} and both of its vertices.
        let edges: Vec<_> = w.iter().filter(|m| m.location.face.is_some()).collect();
        assert_eq!(edges.len(), 1, "{w:?}");
        assert_eq!(edges[0].location.face, Some(vec![0, 1]));
        let verts: Vec<_> = w.iter().filter_map(|m| m.location.vertex).collect();
        assert_eq!(verts, vec![0, 1]);
        same_from_the_index(&model);
    }

    /// The stars read from the index give exactly the messages of the sort-based enumeration
    /// (an independent way to find every vertex and edge star).
    /// With any thread count.
    fn same_from_the_index(model: &Model) {
        let text = |w: Vec<Message>| format!("{w:?}");
        let expected = text(non_manifold(model));
        for threads in [1, 2, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("a pool");
            let (found, stars, lazy) = pool.install(|| {
                let indexed = IndexedModel::new(model.clone()).expect("structurally valid");
                let lazy = IndexedModel::new_lazy_or_model(model.clone()).expect("valid");
                let stars = text(non_manifold_stars(&lazy));
                (
                    text(non_manifold_indexed(&indexed)),
                    text(non_manifold_stars(&indexed)),
                    stars,
                )
            });
            assert_eq!(found, expected, "{threads} threads");
            assert_eq!(stars, expected, "{threads} threads");
            assert_eq!(lazy, expected, "{threads} threads");
        }
    }

    /// A Kuhn triangulation of the grid `g^n` with the simplices `keep` accepts (by index),
    /// positively oriented.
    fn kuhn_part(n: usize, g: usize, keep: impl Fn(usize) -> bool) -> Model {
        let mut model = Model::new(n as u8);
        let side = g + 1;
        for i in 0..side.pow(n as u32) {
            let mut rest = i;
            for _ in 0..n {
                model.vertices.push((rest % side) as f64);
                rest /= side;
            }
            model.values.push(if i % 3 == 0 { -1.0 } else { 1.0 });
        }
        let simplices = ism_format::builder::kuhn_simplices(&vec![g; n]);
        for (index, s) in simplices.iter().enumerate() {
            if keep(index) {
                model.simplices.extend(s.oriented());
            }
        }
        model
    }

    #[test]
    fn stars_agree_with_the_sort_on_grids_with_simplices_removed() {
        // Truth: the sort-based enumeration of every vertex and edge star (`non_manifold`), which
        // tests every edge whatever its vertices. Random removals pinch vertices and edges of
        // every kind; the kinds met are counted so that each case is known to be exercised.
        let mut kinds = std::collections::BTreeMap::<String, usize>::new();
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        let mut random = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        for round in 0..120 {
            let (n, g) = if round % 3 == 0 { (2, 5) } else { (3, 3) };
            // Keep between a third and all but a few.
            let keep_per_mille = 350 + random() % 600;
            let draws: Vec<u64> = (0..6 * g * g * g).map(|_| random() % 1000).collect();
            let model = kuhn_part(n, g, |s| draws[s] < keep_per_mille);
            if model.simplices.is_empty() {
                continue;
            }
            let expected = non_manifold(&model);
            for m in &expected {
                let what = if m.location.face.is_some() {
                    "edge"
                } else {
                    "vertex"
                };
                let why = if m.message.contains("Euler") {
                    "euler"
                } else {
                    "split"
                };
                *kinds.entry(format!("{n}d {what} {why}")).or_default() += 1;
            }
            let text = |w: &[Message]| format!("{w:?}");
            let lazy = IndexedModel::new_lazy_or_model(model.clone()).expect("valid");
            assert_eq!(
                text(&non_manifold_stars(&lazy)),
                text(&expected),
                "round {round}"
            );
            let eager = IndexedModel::new(model).expect("valid");
            assert_eq!(
                text(&non_manifold_indexed(&eager)),
                text(&expected),
                "round {round}"
            );
        }
        for kind in [
            "2d vertex split",
            "3d vertex split",
            "3d vertex euler",
            "3d edge split",
        ] {
            assert!(
                kinds.get(kind).is_some_and(|&c| c >= 3),
                "{kind}: {kinds:?}"
            );
        }
    }

    #[test]
    fn index_and_sort_agree_on_a_pinched_grid() {
        // Two 2×2×2 cube grids of six tetrahedra per cube, the second shifted so that they share
        // one corner vertex and one edge: manifold everywhere except there.
        let mut b = ModelBuilder::new(3);
        let mut id = std::collections::HashMap::new();
        let mut vertex = |b: ModelBuilder, p: [i64; 3]| -> (ModelBuilder, u32) {
            let next = id.len() as u32;
            match id.get(&p) {
                Some(&i) => (b, i),
                None => {
                    id.insert(p, next);
                    let q = p.map(|x| x as f64);
                    (
                        b.vertex(
                            &q,
                            if (p[0] + p[1] + p[2]) % 2 == 0 {
                                -1.0
                            } else {
                                1.0
                            },
                        ),
                        next,
                    )
                }
            }
        };
        let kuhn = [
            [0, 1, 2],
            [0, 2, 1],
            [1, 0, 2],
            [1, 2, 0],
            [2, 0, 1],
            [2, 1, 0],
        ];
        for origin in [[0i64, 0, 0], [2, 2, 0]] {
            for cell in 0..8i64 {
                let base = [
                    origin[0] + cell % 2,
                    origin[1] + cell / 2 % 2,
                    origin[2] + cell / 4,
                ];
                for p in kuhn {
                    let mut c = base;
                    let mut ids = Vec::new();
                    let (nb, v) = vertex(b, c);
                    b = nb;
                    ids.push(v);
                    for axis in p {
                        c[axis] += 1;
                        let (nb, v) = vertex(b, c);
                        b = nb;
                        ids.push(v);
                    }
                    let odd = (p[0] > p[1]) as u32 + (p[0] > p[2]) as u32 + (p[1] > p[2]) as u32;
                    if odd % 2 == 1 {
                        ids.swap(1, 2);
                    }
                    b = b.simplex(&ids);
                }
            }
        }
        let model = b.build().unwrap();
        assert!(!non_manifold(&model).is_empty());
        same_from_the_index(&model);
    }
}
