//! Non-manifold vertices and edges (ISM-150, a warning; spec/validation.md §2).
//!
//! A vertex is manifold when its link is a disk or a sphere (a path or a cycle in 2D); an edge of a
//! 3D complex when its link is a path or a cycle. Facets are shared by at most two simplices (the
//! reader enforces ISM-109), so a link is always a pseudo-manifold and it suffices to check that the
//! star is connected through facets containing the vertex (or edge) and, for 3D vertices, the
//! Euler characteristic of the link: 1 (disk) when it has boundary, 2 (sphere) when closed.

use ism_format::{Location, Model, Rule};
use rayon::prelude::*;

use crate::report::Message;

/// Union–find over small local index sets.
struct Dsu(Vec<u32>);

impl Dsu {
    fn new(n: usize) -> Dsu {
        Dsu((0..n as u32).collect())
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

/// Sorted `(key, simplex)` pairs of the `k`-vertex faces of every simplex (built and sorted on every
/// core: on a million tetrahedra these lists hold millions of entries).
fn faces_of_size(model: &Model, k: usize) -> Vec<([u32; 4], u32)> {
    let m = model.dim() + 1;
    let masks: Vec<u32> = (0u32..(1 << m))
        .filter(|mask| mask.count_ones() as usize == k)
        .collect();
    let mut out: Vec<([u32; 4], u32)> = (0..model.num_simplices())
        .into_par_iter()
        .flat_map_iter(|s| {
            let ids = model.simplex(s);
            masks.iter().map(move |&mask| {
                let mut key = [u32::MAX; 4];
                let mut len = 0;
                for (i, &id) in ids.iter().enumerate() {
                    if mask & (1 << i) != 0 {
                        key[len] = id;
                        len += 1;
                    }
                }
                key[..len].sort_unstable();
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
fn star_defect(model: &Model, key: &[u32; 4], k: usize, members: &[u32]) -> Option<String> {
    let n = model.dim();
    let r = members.len();
    // (facet key, local index) for each facet of each member that contains the face: the face's
    // ids plus all but one of the member's other ids.
    let mut facets: Vec<([u32; 4], u32)> = Vec::with_capacity(r * (n + 1 - k));
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
    let mut dsu = Dsu::new(r);
    for (_, range) in groups(&facets) {
        if range.len() == 2 {
            dsu.union(facets[range.start].1, facets[range.start + 1].1);
        }
    }
    let mut roots: Vec<u32> = (0..r as u32).map(|i| dsu.find(i)).collect();
    roots.sort_unstable();
    roots.dedup();
    if roots.len() > 1 {
        return Some(format!(
            "its star falls into {} parts joined only at this {}",
            roots.len(),
            if k == 1 { "vertex" } else { "edge" }
        ));
    }
    if k == 1 && n == 3 {
        // Euler characteristic of the link: vertices − edges + triangles of the link, i.e. the
        // star's edges, triangles and tetrahedra through the vertex.
        let mut verts: Vec<u32> = Vec::with_capacity(3 * r);
        let mut tris: Vec<[u32; 2]> = Vec::with_capacity(3 * r);
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

/// ISM-150 warnings. The model must have passed the structural checks that index vertices.
pub fn non_manifold(model: &Model) -> Vec<Message> {
    let n = model.dim();
    let m = n + 1;
    let mut out = Vec::new();
    let check = |k: usize, out: &mut Vec<Message>| {
        let list = faces_of_size(model, k);
        let star = groups(&list);
        let found: Vec<Message> = star
            .par_iter()
            .filter_map(|(key, range)| {
                let members: Vec<u32> = list[range.clone()].iter().map(|x| x.1).collect();
                let why = star_defect(model, key, k, &members)?;
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
            })
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
        assert!(non_manifold(&b.build().unwrap()).is_empty());
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
    }
}
