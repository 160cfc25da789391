//! Stage generators, each one a construction that the theorems of `spec/mathematics.md` §3 certify as a
//! simplicial diffeomorphism for every parameter they accept.

use ism_format::multi_index::{owned, owned_count};
use ism_format::{FaceRecord, FaceTable, Model, Stage, StageKind, Topology, VertexMap};
use rayon::prelude::*;

use crate::faces::{faces_of_dimension, FaceRng};

/// Largest accepted move amplitude. Solitary points stay strictly inside their open face for any
/// amplitude below 1 (see [`solitary_point`]); 0.9 keeps every coordinate at least a tenth of the
/// centre's, so generated models stay well conditioned for the numerical tools downstream.
pub const MAX_AMPLITUDE: f64 = 0.9;

fn clamp_amplitude(amplitude: f64) -> f64 {
    if amplitude.is_finite() {
        amplitude.clamp(0.0, MAX_AMPLITUDE)
    } else {
        0.0
    }
}

/// The centre `(1/(k+1), …)` of a face with `k + 1` vertices, moved: coordinate `i` is
/// `(1 + a·rᵢ)/(k+1)` with `rᵢ ∈ [−1, 1)` drawn from the face's stream, then renormalized to sum 1.
/// With `a < 1` every coordinate stays positive, so the point lies in the open face.
pub fn solitary_point(seed: u64, face: &[u32], amplitude: f64) -> Vec<f64> {
    let a = clamp_amplitude(amplitude);
    let mut rng = FaceRng::new(seed, face);
    let raw: Vec<f64> = face.iter().map(|_| 1.0 + a * rng.symmetric()).collect();
    let total: f64 = raw.iter().sum();
    raw.iter().map(|x| x / total).collect()
}

/// A Bézier stage of degree `j + 1` whose only records are the solitary centre points of every
/// `j`-face, each moved by [`solitary_point`]: the stratum `G_j` of the stratified scheme
/// (`spec/mathematics.md` §3.2), a diffeomorphism for every position in 2D and 3D.
pub fn stratum_stage(model: &Model, j: usize, seed: u64, amplitude: f64) -> Stage {
    stratum_of_faces(&faces_of_dimension(model, j), j, seed, amplitude)
}

/// [`stratum_stage`] on the given `j`-faces (flat, sorted ids).
fn stratum_of_faces(faces: &[u32], j: usize, seed: u64, amplitude: f64) -> Stage {
    // Points in parallel into one flat array, then the table in one pass (no record vectors).
    let points: Vec<f64> = faces
        .par_chunks_exact(j + 1)
        .flat_map_iter(|face| solitary_point(seed, face, amplitude))
        .collect();
    let mut stage = Stage::identity(StageKind::Bezier, j as u32 + 1);
    stage.name = Some(format!("stratum G{j}"));
    stage.faces = FaceTable::with_capacity(faces.len() / (j + 1));
    for (face, point) in faces.chunks_exact(j + 1).zip(points.chunks_exact(j + 1)) {
        stage.faces.push(face, point, &[]);
    }
    stage
}

/// The stratified scheme `G = G_1 ∘ G_2 ∘ … ∘ G_n` (`spec/mathematics.md` §3.2) as `n` Bézier stages: one
/// [`stratum_stage`] per face dimension `j = 1..n`, with a solitary point on EVERY `j`-face.
///
/// Returned in application order (`stages[0]` first), which for `G_1 ∘ … ∘ G_n` is
/// `[G_n, G_{n−1}, …, G_1]`: degrees `n + 1, n, …, 2`. Strata use seeds `seed + j`, so the same
/// face gets independent moves in different models only if their seeds differ.
pub fn stratified_stages(model: &Model, seed: u64, amplitude: f64) -> Vec<Stage> {
    let n = model.dim();
    // The complex indexed once for all the strata.
    let topology = Topology::of_complex(model);
    (1..=n)
        .rev()
        .map(|j| {
            let faces = topology
                .as_ref()
                .map_or_else(Vec::new, |t| t.sorted_faces(model, j));
            stratum_of_faces(&faces, j, seed.wrapping_add(j as u64), amplitude)
        })
        .collect()
}

/// A quadratic Bézier stage moving the middle control point of every edge along the edge:
/// `(½ + a·r/2, ½ − a·r/2)` with `r ∈ [−1, 1)`. Adjusted and of degree 2, hence a diffeomorphism
/// (`spec/mathematics.md` §3.2, Mello & Velho 2009, Prop. 5.6).
pub fn quadratic_edge_stage(model: &Model, seed: u64, amplitude: f64) -> Stage {
    let mut stage = stratum_stage(model, 1, seed, amplitude);
    stage.name = Some("quadratic edges".into());
    stage
}

/// A cubic Bézier stage moving the centre point (index `111`) of every triangle of the complex
/// (in 2D: of every top simplex, a solitary point per simplex, Mello & Velho 2009, Prop. 5.7; in 3D: the stratum
/// `G_2`, Mello & Velho 2009, Prop. 5.9). A diffeomorphism in both cases.
pub fn cubic_face_point_stage(model: &Model, seed: u64, amplitude: f64) -> Stage {
    let mut stage = stratum_stage(model, 2, seed, amplitude);
    stage.name = Some("cubic face points".into());
    stage
}

/// A rational stage of degree `degree` with every control point fixed (`b_I = I/d`) and the weights
/// `weight(face, J)` for the multi-index `J` owned by `face` (sorted global ids). Fixed points with
/// positive weights make a diffeomorphism for every `n` (Mello & Velho 2009, Thm. 6.4). Faces whose weights are
/// all 1 are left out (they equal the default). Non-positive or non-finite weights are replaced
/// by 1, so the result is always a valid stage.
pub fn rational_fixed_points_stage(
    model: &Model,
    degree: u32,
    weight: impl Fn(&[u32], &[u32]) -> f64 + Sync,
) -> Stage {
    let n = model.dim();
    let mut stage = Stage::identity(StageKind::Rational, degree);
    stage.name = Some(format!("rational degree {degree}, fixed points"));
    for k in 1..=n {
        let m = k + 1;
        if owned_count(m, degree) == 0 {
            continue;
        }
        let indices = owned(m, degree);
        let faces = faces_of_dimension(model, k);
        let records: Vec<FaceRecord> = faces
            .par_chunks_exact(m)
            .filter_map(|face| {
                let weights: Vec<f64> = indices
                    .chunks_exact(m)
                    .map(|j| {
                        let q = weight(face, j);
                        if q.is_finite() && q > 0.0 {
                            q
                        } else {
                            1.0
                        }
                    })
                    .collect();
                if weights.iter().all(|&q| q == 1.0) {
                    return None;
                }
                let points = indices
                    .iter()
                    .map(|&e| f64::from(e) / f64::from(degree))
                    .collect();
                Some(FaceRecord {
                    face: face.to_vec(),
                    points,
                    weights,
                })
            })
            .collect();
        stage.faces.extend(records);
    }
    stage
}

/// Seeded weights for [`rational_fixed_points_stage`]: `exp(spread · r)`, `r ∈ [−1, 1)` drawn from
/// the stream of the face and multi-index, so every weight lies in `[e^−spread, e^spread)`.
pub fn seeded_weights(seed: u64, spread: f64) -> impl Fn(&[u32], &[u32]) -> f64 + Sync {
    move |face, index| {
        let key: Vec<u32> = face.iter().chain(index).copied().collect();
        (spread * FaceRng::new(seed, &key).symmetric()).exp()
    }
}

/// A monotonic stage of degree `degree` with a map on every used vertex: coefficients
/// `a_0 = 0`, `a_j = a_{j−1} + (1 + a·r_j)/d` with `r_j ∈ [−1, 1)` and `a = min(amplitude, 0.9)`,
/// strictly increasing, so each `g_v` is increasing and the stage a diffeomorphism (Mello & Velho 2009, §4).
pub fn monotonic_stage(model: &Model, degree: u32, seed: u64, amplitude: f64) -> Stage {
    let a = clamp_amplitude(amplitude);
    let vertices = faces_of_dimension(model, 0);
    let d = f64::from(degree.max(1));
    let mut stage = Stage::identity(StageKind::Monotonic, degree);
    stage.name = Some(format!("monotonic degree {degree}"));
    stage.vertex_maps = vertices
        .iter()
        .map(|&v| {
            let mut rng = FaceRng::new(seed, &[v]);
            let mut acc = 0.0;
            let mut coefficients = vec![0.0];
            for _ in 0..degree {
                acc += (1.0 + a * rng.symmetric()) / d;
                coefficients.push(acc);
            }
            VertexMap {
                vertex: v,
                coefficients,
            }
        })
        .collect();
    stage
}

/// Bisection steps for edge crossings: 60 halvings take the bracket below 1e-18 of the edge, under
/// f64 resolution.
const BISECTION_STEPS: usize = 60;

/// Bounds keeping a quadratic middle point well inside the open edge (a 5 % margin): adjusted, and
/// far enough from the vertices that the Jacobian stays above a tenth of the identity's.
const BETA_RANGE: (f64, f64) = (0.05, 0.95);

/// Every edge the linear shape crosses, with the linear crossing `t₀` and the crossing `t*` of `g`
/// (both as the parameter from `face[0]` to `face[1]`).
fn crossings(model: &Model, g: &(impl Fn(&[f64]) -> f64 + Sync)) -> Vec<([u32; 2], f64, f64)> {
    let n = model.dim();
    let c = model.level;
    let edges = faces_of_dimension(model, 1);
    edges
        .par_chunks_exact(2)
        .filter_map(|e| {
            let (fa, fb) = (
                model.values[e[0] as usize] - c,
                model.values[e[1] as usize] - c,
            );
            if (fa < 0.0) == (fb < 0.0) {
                return None;
            }
            let (pa, pb) = (model.vertex(e[0] as usize), model.vertex(e[1] as usize));
            let at = |t: f64| -> Vec<f64> { (0..n).map(|i| pa[i] + t * (pb[i] - pa[i])).collect() };
            let ga = g(&at(0.0)) - c;
            let gb = g(&at(1.0)) - c;
            if !(ga.is_finite() && gb.is_finite()) || (ga < 0.0) == (gb < 0.0) {
                return None;
            }
            let (mut lo, mut hi) = (0.0f64, 1.0f64);
            for _ in 0..BISECTION_STEPS {
                let mid = 0.5 * (lo + hi);
                if ((g(&at(mid)) - c) < 0.0) == (ga < 0.0) {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            let t_star = (0.5 * (lo + hi)).clamp(1e-6, 1.0 - 1e-6);
            Some(([e[0], e[1]], fa / (fa - fb), t_star))
        })
        .collect()
}

/// The quadratic stage whose middle point on each crossed edge solves `X(s) = t₀` for the edge's
/// map `X(t) = 2t(1 − t)β + t²`: `β = (t₀ − s²) / (2s(1 − s))`, clamped to [`BETA_RANGE`].
fn crossing_quadratic(
    found: &[([u32; 2], f64, f64)],
    s_of: impl Fn(&[u32; 2], f64) -> f64,
) -> Stage {
    let mut stage = Stage::identity(StageKind::Bezier, 2);
    stage.name = Some("level crossings".into());
    stage.faces = found
        .iter()
        .map(|(e, t0, t_star)| {
            let s = s_of(e, *t_star);
            let beta = ((t0 - s * s) / (2.0 * s * (1.0 - s))).clamp(BETA_RANGE.0, BETA_RANGE.1);
            // Point coordinates w.r.t. (e0, e1): (1 − β, β).
            FaceRecord {
                face: e.to_vec(),
                points: vec![1.0 - beta, beta],
                weights: Vec::new(),
            }
        })
        .collect();
    stage
}

/// A quadratic stage that moves the level set toward the exact zero set of `g` along every edge the
/// linear shape crosses: on an edge `[a, b]` with `f(a) − c`, `f(b) − c` of opposite signs, the linear
/// crossing is at `t₀ = (c − f(a)) / (f(b) − f(a))`; bisection on `g` finds the exact crossing `t*`;
/// the middle control point `β` (the coordinate of `b`) solves `X(t*) = t₀` for the edge's
/// quadratic map `X(t) = 2t(1 − t)β + t²`, i.e. `β = (t₀ − t*²) / (2t*(1 − t*))`, clamped to
/// `[0.05, 0.95]` so the stage stays adjusted (hence a diffeomorphism, degree 2). Then `F` vanishes
/// exactly where `g` does on every crossed edge whose `β` was not clamped; a quadratic reaches only
/// `t₀ ∈ (t*², 2t* − t*²)`, see [`level_crossing_stages`] for more reach.
pub fn level_crossing_stage(model: &Model, g: impl Fn(&[f64]) -> f64 + Sync) -> Stage {
    crossing_quadratic(&crossings(model, &g), |_, t| t)
}

/// Two stages that put the shape on the zero set of `g` along the crossed edges, with more reach
/// than [`level_crossing_stage`] alone:
///
/// 1. a monotonic stage of degree 1, `g_v(t) = λ_v t` (coefficients `[0, λ_v]`, `λ_v > 0`), which
///    on an edge `[a, b]` is `X₀(t) = λ_b t / (λ_a (1 − t) + λ_b t)`. The `log λ_v` are fitted by
///    least squares to `logit t₀ − logit t*` over the crossed edges (Gauss–Seidel, a small ridge
///    term pinning the free additive constant, clamped to `|log λ| ≤ 3`);
/// 2. the quadratic stage of [`level_crossing_stage`] solving `X₁(X₀(t*)) = t₀`.
///
/// Both are diffeomorphisms by construction (monotonic: Mello & Velho 2009, §4; adjusted quadratic), so their
/// composition is. Returned in application order.
pub fn level_crossing_stages(model: &Model, g: impl Fn(&[f64]) -> f64 + Sync) -> Vec<Stage> {
    /// Ridge weight: small against the edge equations (weight 1), enough to make the system
    /// definite and to keep vertices off crossed edges at λ = 1.
    const RIDGE: f64 = 1e-3;
    /// Sweeps of Gauss–Seidel; the example models have graph diameters below 20, and each sweep
    /// propagates information across the whole graph in one direction.
    const SWEEPS: usize = 400;
    /// Bound on |log λ|: weights within a factor e³ ≈ 20 keep the map moderate.
    const LOG_BOUND: f64 = 3.0;
    let found = crossings(model, &g);
    let logit = |t: f64| (t / (1.0 - t)).ln();
    let nv = model.num_vertices();
    let mut adjacent: Vec<Vec<(usize, f64)>> = vec![Vec::new(); nv];
    for (e, t0, t_star) in &found {
        let r = logit(*t0) - logit(*t_star);
        // Equation x_b − x_a = r.
        adjacent[e[1] as usize].push((e[0] as usize, r));
        adjacent[e[0] as usize].push((e[1] as usize, -r));
    }
    let mut x = vec![0.0f64; nv];
    for _ in 0..SWEEPS {
        for v in 0..nv {
            if adjacent[v].is_empty() {
                continue;
            }
            let sum: f64 = adjacent[v].iter().map(|&(u, r)| x[u] + r).sum();
            x[v] = (sum / (adjacent[v].len() as f64 + RIDGE)).clamp(-LOG_BOUND, LOG_BOUND);
        }
    }
    let lambda: Vec<f64> = x.iter().map(|l| l.exp()).collect();
    let mut monotonic = Stage::identity(StageKind::Monotonic, 1);
    monotonic.name = Some("level crossings, vertex weights".into());
    monotonic.vertex_maps = (0..nv)
        .filter(|&v| !adjacent[v].is_empty())
        .map(|v| VertexMap {
            vertex: v as u32,
            coefficients: vec![0.0, lambda[v]],
        })
        .collect();
    let quadratic = crossing_quadratic(&found, |e, t| {
        let (la, lb) = (lambda[e[0] as usize], lambda[e[1] as usize]);
        lb * t / (la * (1.0 - t) + lb * t)
    });
    vec![monotonic, quadratic]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{kuhn_grid_2d, kuhn_grid_3d, Aabb};
    use ism_format::structure::check;

    fn sphere(p: &[f64]) -> f64 {
        p.iter().map(|x| x * x).sum::<f64>() - 0.4
    }

    #[test]
    fn stratified_stages_cover_every_face_with_interior_points() {
        let mut m = kuhn_grid_3d(2, 2, 2, Aabb::cube(-1.0, 1.0), sphere).unwrap();
        m.stages = stratified_stages(&m, 3, 0.5);
        assert!(check(&m, 100).is_empty(), "{:?}", check(&m, 100));
        let degrees: Vec<u32> = m.stages.iter().map(|s| s.degree).collect();
        assert_eq!(degrees, vec![4, 3, 2]);
        for (stage, j) in m.stages.iter().zip([3usize, 2, 1]) {
            assert_eq!(stage.faces.len(), faces_of_dimension(&m, j).len() / (j + 1));
            for rec in &stage.faces {
                assert_eq!(rec.points.len(), j + 1);
                assert!(rec.points.iter().all(|&x| x > 0.0));
                assert!((rec.points.iter().sum::<f64>() - 1.0).abs() < 1e-15);
            }
        }
        // Parameters per tetrahedron neighbourhood: 1 per edge, 2 per triangle, 3 per tet (free).
        let again = stratified_stages(&m, 3, 0.5);
        assert_eq!(again, m.stages, "deterministic");
        assert_ne!(stratified_stages(&m, 4, 0.5), m.stages, "seeded");
    }

    #[test]
    fn generated_stages_pass_structural_checks() {
        let base = kuhn_grid_2d(4, 4, Aabb::cube(-0.5, 0.5), |p| {
            p[0] * p[0] + p[1] * p[1] - 0.28 * 0.28
        })
        .unwrap();
        let stages = [
            quadratic_edge_stage(&base, 1, 0.6),
            cubic_face_point_stage(&base, 2, 0.6),
            rational_fixed_points_stage(&base, 5, seeded_weights(3, 1.0)),
            monotonic_stage(&base, 3, 4, 0.5),
            level_crossing_stage(&base, |p| p[0] * p[0] + p[1] * p[1] - 0.28 * 0.28),
        ];
        for stage in stages {
            let mut m = base.clone();
            m.stages.push(stage);
            assert!(check(&m, 100).is_empty(), "{:?}", check(&m, 100));
        }
    }

    #[test]
    fn rational_weights_are_positive_and_points_fixed() {
        let m = kuhn_grid_2d(2, 2, Aabb::cube(0.0, 1.0), |p| p[0] - 0.4).unwrap();
        let s = rational_fixed_points_stage(&m, 5, seeded_weights(9, 1.0));
        let edges = faces_of_dimension(&m, 1).len() / 2;
        assert_eq!(s.faces.len(), edges + m.num_simplices());
        for rec in &s.faces {
            let k1 = rec.face.len();
            assert_eq!(rec.weights.len(), owned_count(k1, 5));
            assert!(rec
                .weights
                .iter()
                .all(|&q| q > 0.0 && (q - 1.0).abs() > 0.0));
            let expect: Vec<f64> = owned(k1, 5).iter().map(|&e| f64::from(e) / 5.0).collect();
            assert_eq!(rec.points, expect);
        }
        let unit = rational_fixed_points_stage(&m, 5, |_, _| 1.0);
        assert!(unit.faces.is_empty());
    }

    #[test]
    fn monotonic_coefficients_strictly_increase_from_zero() {
        let m = kuhn_grid_3d(1, 1, 1, Aabb::cube(0.0, 1.0), |p| p[1] - 0.5).unwrap();
        let s = monotonic_stage(&m, 4, 11, 5.0);
        assert_eq!(s.vertex_maps.len(), 8);
        for map in &s.vertex_maps {
            assert_eq!(map.coefficients[0], 0.0);
            assert!(map.coefficients.windows(2).all(|w| w[1] > w[0]));
        }
    }

    #[test]
    fn two_stage_level_crossing_lands_on_the_zero_set() {
        // Composition along an edge, evaluated independently of the fitting code: X0 from the
        // stored monotonic coefficients, X1 from the stored quadratic point; solve
        // X1(X0(t)) = t0 by bisection (both are increasing) and evaluate g there.
        let g = |p: &[f64]| p[0] * p[0] + p[1] * p[1] - 0.28 * 0.28;
        let m = kuhn_grid_2d(4, 4, Aabb::cube(-0.5, 0.5), g).unwrap();
        let stages = level_crossing_stages(&m, g);
        let mut with = m.clone();
        with.stages = stages.clone();
        assert!(check(&with, 100).is_empty());
        let lambda = |v: u32| {
            stages[0]
                .vertex_maps
                .iter()
                .find(|map| map.vertex == v)
                .map_or(1.0, |map| map.coefficients[1])
        };
        let mut exact = 0;
        for rec in &stages[1].faces {
            let (a, b) = (rec.face[0], rec.face[1]);
            let beta = rec.points[1];
            let (fa, fb) = (m.values[a as usize], m.values[b as usize]);
            let t0 = fa / (fa - fb);
            let x = |t: f64| {
                let s = lambda(b) * t / (lambda(a) * (1.0 - t) + lambda(b) * t);
                2.0 * s * (1.0 - s) * beta + s * s
            };
            let (mut lo, mut hi) = (0.0, 1.0);
            for _ in 0..80 {
                let mid = 0.5 * (lo + hi);
                if x(mid) < t0 {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            let t = 0.5 * (lo + hi);
            let (pa, pb) = (m.vertex(a as usize), m.vertex(b as usize));
            let p = [pa[0] + t * (pb[0] - pa[0]), pa[1] + t * (pb[1] - pa[1])];
            if beta > 0.05 && beta < 0.95 {
                assert!(g(&p).abs() < 1e-12, "g = {} on edge {:?}", g(&p), rec.face);
                exact += 1;
            }
        }
        assert_eq!(
            exact,
            stages[1].faces.len(),
            "every crossing reached on the circle grid"
        );
    }

    #[test]
    fn level_crossing_puts_the_zero_on_the_exact_crossing() {
        let g = |p: &[f64]| p[0] * p[0] + p[1] * p[1] - 0.28 * 0.28;
        let m = kuhn_grid_2d(4, 4, Aabb::cube(-0.5, 0.5), g).unwrap();
        let s = level_crossing_stage(&m, g);
        assert!(!s.faces.is_empty());
        for rec in &s.faces {
            let (a, b) = (rec.face[0] as usize, rec.face[1] as usize);
            let beta = rec.points[1];
            // Solve X(t) = t0 on the edge independently (bisection on the monotone quadratic map,
            // written in Bernstein form) and check g vanishes there.
            let (fa, fb) = (m.values[a], m.values[b]);
            let t0 = fa / (fa - fb);
            let x = |t: f64| 2.0 * t * (1.0 - t) * beta + t * t;
            let (mut lo, mut hi) = (0.0, 1.0);
            for _ in 0..80 {
                let mid = 0.5 * (lo + hi);
                if x(mid) < t0 {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            let t = 0.5 * (lo + hi);
            let p: Vec<f64> = (0..2)
                .map(|i| m.vertex(a)[i] + t * (m.vertex(b)[i] - m.vertex(a)[i]))
                .collect();
            if beta > 0.05 && beta < 0.95 {
                assert!(g(&p).abs() < 1e-12, "g = {} on edge {:?}", g(&p), rec.face);
            }
        }
    }
}
