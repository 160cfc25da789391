//! The generalized winding number, evaluated hierarchically and exactly over the R-tree's nodes
//! (the module doc of [`super`] says how and why).

use std::collections::HashMap;

use rstar::RTreeNode;

use super::distance::Tri;
use super::{cross, dot, norm, sub, TriangleMesh, P3};

/// Signed solid angle of triangle `[a, b, c]` seen from `p` (Van Oosterom and Strackee 1983):
/// positive when `p` is on the side the counter-clockwise normal points away from.
pub(super) fn solid_angle(p: P3, [a, b, c]: [P3; 3]) -> f64 {
    let (a, b, c) = (sub(a, p), sub(b, p), sub(c, p));
    let (la, lb, lc) = (norm(a), norm(b), norm(c));
    let num = dot(a, cross(b, c));
    let den = la * lb * lc + dot(a, b) * lc + dot(a, c) * lb + dot(b, c) * la;
    2.0 * num.atan2(den)
}

/// A node of the winding-number hierarchy (mirrors one R-tree node).
#[derive(Debug)]
pub(super) struct WindingNode {
    lo: P3,
    hi: P3,
    /// Triangles below this node.
    triangles: usize,
    /// Fan apex and the boundary chain of the node's patch (directed edges).
    apex: P3,
    boundary: Vec<[P3; 2]>,
    children: Vec<WindingChild>,
}

#[derive(Debug)]
enum WindingChild {
    Node(WindingNode),
    Triangle([P3; 3]),
}

impl WindingNode {
    /// Builds the node for an R-tree parent; `ids` collects the node's triangle ids.
    pub(super) fn build(
        node: &rstar::ParentNode<Tri>,
        mesh: &TriangleMesh,
        ids: &mut Vec<u32>,
    ) -> WindingNode {
        let start = ids.len();
        let children = node
            .children()
            .iter()
            .map(|child| match child {
                RTreeNode::Leaf(t) => {
                    ids.push(t.id);
                    WindingChild::Triangle(t.v)
                }
                RTreeNode::Parent(p) => WindingChild::Node(WindingNode::build(p, mesh, ids)),
            })
            .collect();
        let mine = &ids[start..];
        // The boundary chain: directed edges of the patch minus those cancelled by their reverse.
        let mut chain: HashMap<(u32, u32), i32> = HashMap::new();
        for &t in mine {
            let t = mesh.triangles[t as usize];
            for k in 0..3 {
                let (u, v) = (t[k], t[(k + 1) % 3]);
                let (key, s) = if u < v { ((u, v), 1) } else { ((v, u), -1) };
                *chain.entry(key).or_default() += s;
            }
        }
        let mut edges: Vec<(u32, u32)> = Vec::new();
        for (&(u, v), &m) in &chain {
            // |m| > 1 only on non-manifold patches: repeat the edge, the chain stays exact.
            let e = if m > 0 { (u, v) } else { (v, u) };
            edges.extend(std::iter::repeat_n(e, m.unsigned_abs() as usize));
        }
        edges.sort_unstable();
        let apex_id = edges.first().map_or(0, |e| e.0);
        let apex = mesh.positions[apex_id as usize];
        let boundary = edges
            .iter()
            .filter(|e| e.0 != apex_id && e.1 != apex_id)
            .map(|&(u, v)| [mesh.positions[u as usize], mesh.positions[v as usize]])
            .collect();
        let env = node.envelope();
        WindingNode {
            lo: env.lower(),
            hi: env.upper(),
            triangles: mine.len(),
            apex,
            boundary,
            children,
        }
    }

    /// `Σ Ω / 4π`·4π (the solid-angle sum) of this node's patch at `p`.
    pub(super) fn solid_angle_sum(&self, p: P3) -> f64 {
        let outside = (0..3).any(|k| p[k] < self.lo[k] || p[k] > self.hi[k]);
        if outside && self.boundary.len() < self.triangles {
            return self
                .boundary
                .iter()
                .map(|&[a, b]| solid_angle(p, [self.apex, a, b]))
                .sum();
        }
        self.children
            .iter()
            .map(|c| match c {
                WindingChild::Node(n) => n.solid_angle_sum(p),
                WindingChild::Triangle(t) => solid_angle(p, *t),
            })
            .sum()
    }
}
