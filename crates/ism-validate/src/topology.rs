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

/// ISM-150 warnings. The model must have passed the structural checks that index vertices.
pub fn non_manifold(model: &Model) -> Vec<Message> {
    let n = model.dim();
    let m = n + 1;
    let mut out = Vec::new();
    // Facets with their simplices; only properly shared ones (exactly two) connect stars.
    let facets = faces_of_size(model, n);
    let facet_groups = groups(&facets);
    // Star of a face: the simplices of its group in the face list. Connectivity through facets that
    // contain the face: for each facet shared by two simplices, union them in the star of every
    // sub-face of the facet.
    let check = |k: usize, out: &mut Vec<Message>| {
        let list = faces_of_size(model, k);
        let star = groups(&list);
        let lookup = |key: &[u32; 4]| star.binary_search_by(|(k2, _)| k2.cmp(key)).ok();
        let mut dsu = Dsu::new(list.len());
        for (_, range) in &facet_groups {
            if range.len() != 2 {
                continue;
            }
            let (key, s1) = facets[range.start];
            let s2 = facets[range.start + 1].1;
            let len = key.iter().take_while(|&&x| x != u32::MAX).count();
            for mask in 0u32..(1 << len) {
                if mask.count_ones() as usize != k {
                    continue;
                }
                let sub: Vec<u32> = (0..len)
                    .filter(|i| mask & (1 << i) != 0)
                    .map(|i| key[i])
                    .collect();
                let mut sk = [u32::MAX; 4];
                sk[..k].copy_from_slice(&sub);
                let Some(g) = lookup(&sk) else { continue };
                let range = star[g].1.clone();
                let pos = |s: u32| {
                    range.start
                        + list[range.clone()]
                            .iter()
                            .position(|x| x.1 == s)
                            .expect("in star")
                };
                dsu.union(pos(s1) as u32, pos(s2) as u32);
            }
        }
        // Flatten the union–find once; then every star is checked on its own, on every core.
        let root: Vec<u32> = (0..list.len() as u32).map(|i| dsu.find(i)).collect();
        let found: Vec<Message> = star
            .par_iter()
            .filter_map(|(key, range)| {
                let roots: std::collections::BTreeSet<u32> =
                    range.clone().map(|i| root[i]).collect();
                let face: Vec<u32> = key[..k].to_vec();
                let first = list[range.start].1 as usize;
                let mut bad = None;
                if roots.len() > 1 {
                    bad = Some(format!(
                        "its star falls into {} parts joined only at this {}",
                        roots.len(),
                        if k == 1 { "vertex" } else { "edge" }
                    ));
                } else if k == 1 && n == 3 {
                    // Euler characteristic of the link: edges − triangles + tetrahedra around the
                    // vertex.
                    let v = key[0];
                    let tets = range.len();
                    let mut edges = std::collections::BTreeSet::new();
                    let mut tris = std::collections::BTreeMap::<[u32; 2], usize>::new();
                    for i in range.clone() {
                        let ids = model.simplex(list[i].1 as usize);
                        let others: Vec<u32> = ids.iter().copied().filter(|&x| x != v).collect();
                        for &a in &others {
                            edges.insert(a);
                        }
                        for a in 0..others.len() {
                            for b in (a + 1)..others.len() {
                                let t = [others[a].min(others[b]), others[a].max(others[b])];
                                *tris.entry(t).or_default() += 1;
                            }
                        }
                    }
                    let boundary = tris.values().any(|&c| c == 1);
                    let chi = edges.len() as i64 - tris.len() as i64 + tets as i64;
                    let expect = if boundary { 1 } else { 2 };
                    if chi != expect {
                        bad = Some(format!(
                            "its link has Euler characteristic {chi}; a manifold vertex has a disk (1) or sphere (2) link"
                        ));
                    }
                }
                let why = bad?;
                let mut loc = Location {
                    simplex: Some(first),
                    ..Location::pointer(format!("/simplices/{}", first * m))
                };
                if k == 1 {
                    loc = Location {
                        vertex: Some(key[0] as usize),
                        ..Location::pointer(format!("/vertices/{}", key[0] as usize * n))
                    };
                } else {
                    loc.face = Some(face);
                }
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
