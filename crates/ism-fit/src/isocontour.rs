//! The linear isocomplex `f̂⁻¹(c)` (marching triangles / tetrahedra): its patches, its topology
//! (components and Euler characteristic), and samples on it.

use std::collections::HashMap;

use crate::complex::Complex;

/// Barycentric coordinates, first `n + 1` entries used.
pub type Bary = [f64; 4];

/// Corners of the linear patch `θ_σ = {u : Σ sᵢ uᵢ = 0}` for the signed values `s` of one cell
/// (`s = f − c`, never 0), in cyclic order, each with the local positions of its edge; empty when
/// all signs agree.
pub fn patch_corners(s: &[f64]) -> Vec<(Bary, [usize; 2])> {
    let m = s.len();
    let neg: Vec<usize> = (0..m).filter(|&i| s[i] < 0.0).collect();
    let pos: Vec<usize> = (0..m).filter(|&i| s[i] > 0.0).collect();
    if neg.is_empty() || pos.is_empty() {
        return Vec::new();
    }
    let corner = |a: usize, b: usize| {
        let t = s[a] / (s[a] - s[b]);
        let mut u = [0.0; 4];
        u[a] = 1.0 - t;
        u[b] = t;
        (u, [a, b])
    };
    if neg.len() == 2 && pos.len() == 2 {
        // Quad: consecutive corners share a vertex.
        let (a, b, c, d) = (neg[0], neg[1], pos[0], pos[1]);
        return vec![corner(a, c), corner(a, d), corner(b, d), corner(b, c)];
    }
    neg.iter()
        .flat_map(|&a| pos.iter().map(move |&b| (a, b)))
        .map(|(a, b)| corner(a, b))
        .collect()
}

/// Sample points of a patch in barycentric coordinates: a segment's `level + 1` evenly spaced
/// points (2D), or the barycentric grid of level `level` on each fan triangle (3D).
pub fn patch_samples(corners: &[Bary], level: usize) -> Vec<Bary> {
    let lerp3 = |a: &Bary, b: &Bary, c: &Bary, x: f64, y: f64, z: f64| {
        let mut u = [0.0; 4];
        for k in 0..4 {
            u[k] = x * a[k] + y * b[k] + z * c[k];
        }
        u
    };
    let l = level.max(1);
    let mut out = Vec::new();
    match corners.len() {
        0 => {}
        1 => out.push(corners[0]),
        2 => {
            for i in 0..=l {
                let t = i as f64 / l as f64;
                out.push(lerp3(
                    &corners[0],
                    &corners[1],
                    &corners[1],
                    1.0 - t,
                    t,
                    0.0,
                ));
            }
        }
        _ => {
            for k in 1..corners.len() - 1 {
                let (a, b, c) = (&corners[0], &corners[k], &corners[k + 1]);
                for i in 0..=l {
                    for j in 0..=l - i {
                        // Skip the shared edge a–b of later fan triangles (already sampled).
                        if k > 1 && j == 0 {
                            continue;
                        }
                        let x = (l - i - j) as f64 / l as f64;
                        let y = i as f64 / l as f64;
                        let z = j as f64 / l as f64;
                        out.push(lerp3(a, b, c, x, y, z));
                    }
                }
            }
        }
    }
    out
}

/// Topology of a linear isocomplex.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Topology {
    /// Connected components.
    pub components: usize,
    /// Euler characteristic `V − E (+ F)` of the cell decomposition the patches form.
    pub euler: i64,
}

/// Components and Euler characteristic of `f̂⁻¹(c)` for signed values `s` per vertex: its
/// vertices are the sign-changing edges, its edges the sign-changing triangles (each carries one
/// segment), and in 3D its faces the sign-changing tetrahedra.
pub fn topology(complex: &Complex, s: &[f64]) -> Topology {
    let n = complex.dim();
    let mut vertex_id: HashMap<(u32, u32), usize> = HashMap::new();
    let mut triangles: std::collections::HashSet<Vec<u32>> = std::collections::HashSet::new();
    let mut cells = 0i64;
    let mut parent: Vec<usize> = Vec::new();
    fn find(p: &mut [usize], x: usize) -> usize {
        let mut r = x;
        while p[r] != r {
            r = p[r];
        }
        let mut y = x;
        while p[y] != r {
            let next = p[y];
            p[y] = r;
            y = next;
        }
        r
    }
    for c in complex.live_cells() {
        let ids = complex.cell(c);
        let vals: Vec<f64> = ids.iter().map(|&v| s[v as usize]).collect();
        let corners = patch_corners(&vals);
        if corners.is_empty() {
            continue;
        }
        cells += 1;
        let mut members = Vec::new();
        for (_, [a, b]) in &corners {
            let key = if ids[*a] < ids[*b] {
                (ids[*a], ids[*b])
            } else {
                (ids[*b], ids[*a])
            };
            let next = vertex_id.len();
            let id = *vertex_id.entry(key).or_insert_with(|| {
                parent.push(next);
                next
            });
            members.push(id);
        }
        for w in members.windows(2) {
            let (ra, rb) = (find(&mut parent, w[0]), find(&mut parent, w[1]));
            parent[ra] = rb;
        }
        if n == 3 {
            for skip in 0..4 {
                let mut tri: Vec<u32> = ids
                    .iter()
                    .enumerate()
                    .filter(|(i, _)| *i != skip)
                    .map(|(_, &v)| v)
                    .collect();
                tri.sort_unstable();
                let sv: Vec<f64> = tri.iter().map(|&v| s[v as usize]).collect();
                if sv.iter().any(|&x| x < 0.0) && sv.iter().any(|&x| x > 0.0) {
                    triangles.insert(tri);
                }
            }
        }
    }
    let v = vertex_id.len() as i64;
    let components = (0..parent.len())
        .filter(|&x| find(&mut parent, x) == x)
        .count();
    let euler = match n {
        2 => v - cells,
        3 => v - triangles.len() as i64 + cells,
        _ => v,
    };
    Topology { components, euler }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn values(c: &Complex, g: impl Fn(&[f64]) -> f64) -> Vec<f64> {
        (0..c.num_vertices() as u32)
            .map(|v| {
                let x = g(c.point(v));
                if x == 0.0 {
                    1e-12
                } else {
                    x
                }
            })
            .collect()
    }

    #[test]
    fn topology_of_known_shapes() {
        let c = Complex::kuhn(&[-1.0, 1.0, -1.0, 1.0], &[16, 16]);
        let two_circles = values(&c, |p| {
            ((p[0] - 0.5).powi(2) + p[1] * p[1] - 0.1).min((p[0] + 0.5).powi(2) + p[1] * p[1] - 0.1)
        });
        assert_eq!(
            topology(&c, &two_circles),
            Topology {
                components: 2,
                euler: 0
            }
        );
        let c3 = Complex::kuhn(&[-1.0, 1.0, -1.0, 1.0, -1.0, 1.0], &[10, 10, 10]);
        let sphere = values(&c3, |p| p.iter().map(|x| x * x).sum::<f64>() - 0.5);
        assert_eq!(
            topology(&c3, &sphere),
            Topology {
                components: 1,
                euler: 2
            }
        );
        let torus = values(&c3, |p| {
            let r = (p[0] * p[0] + p[1] * p[1]).sqrt() - 0.6;
            r * r + p[2] * p[2] - 0.09
        });
        assert_eq!(
            topology(&c3, &torus),
            Topology {
                components: 1,
                euler: 0
            }
        );
    }

    #[test]
    fn samples_cover_the_patch_corners() {
        let corners = patch_corners(&[-1.0, -2.0, 1.0, 3.0]);
        assert_eq!(corners.len(), 4);
        let pts: Vec<Bary> = corners.iter().map(|c| c.0).collect();
        let s = patch_samples(&pts, 3);
        for c in &pts {
            assert!(s
                .iter()
                .any(|x| x.iter().zip(c).all(|(a, b)| (a - b).abs() < 1e-15)));
        }
        // Every sample lies on θ: Σ s_i u_i = 0.
        for u in &s {
            let v = -u[0] - 2.0 * u[1] + u[2] + 3.0 * u[3];
            assert!(v.abs() < 1e-14);
        }
    }
}
