//! Structurally valid models built from arbitrary bytes (target `validate_generated`), and an exact
//! check of `det DY > 0` at dyadic points that shares no code with `ism-validate` or `ism-geom`: the
//! dense control net is built from the spec's rules (§4.3–§5.4) here, and the Jacobian is evaluated
//! in exact rational arithmetic (`num-rational`).
//!
//! A model is a Kuhn (Freudenthal) triangulation of a small grid (2D: up to 2×2 squares, 8
//! triangles; 3D: up to 2×1×1 cubes, 12 tetrahedra) with dyadic vertex perturbations, vertex orders
//! permuted and re-oriented, arbitrary nonzero values, and one or two stages of any kind, degree
//! 1–3 (monotonic 1–4) and direction. Bézier and rational stages get records on arbitrary faces:
//! dyadic control points whose coordinates sum to exactly 1 (a coordinate may be zero or negative,
//! so invalid stages are generated too) and dyadic weights (zero allowed); monotonic stages get
//! vertex maps with dyadic nondecreasing coefficients. Every number is a dyadic rational, so the
//! model's `f64`s are its exact values.

use std::collections::{BTreeMap, BTreeSet};

use arbitrary::{Result, Unstructured};
use num_bigint::BigInt;
use num_rational::BigRational;
use num_traits::{One, Signed, Zero};

use ism_format::indexed::simplex_faces;
use ism_format::{Direction, FaceRecord, Model, Stage, StageKind, VertexMap};

type Q = BigRational;

/// A generated stage in the generator's own terms (the exact check reads these, not the model).
#[derive(Clone, Debug)]
struct GenStage {
    kind: StageKind,
    degree: u32,
    /// Face (sorted global ids) → (points, weights), as stored.
    records: BTreeMap<Vec<u32>, (Vec<f64>, Vec<f64>)>,
    /// Vertex → coefficients `a_0..a_d`.
    maps: BTreeMap<u32, Vec<f64>>,
}

/// A generated model and what the exact check needs.
#[derive(Clone, Debug)]
pub struct Generated {
    /// The model (structurally valid unless a perturbation made a simplex degenerate; callers
    /// check structure first).
    pub model: Model,
    /// Vertex positions (exact).
    positions: Vec<Vec<f64>>,
    /// Top simplices in stored order.
    simplices: Vec<Vec<u32>>,
    stages: Vec<GenStage>,
    /// Sample points (barycentric, exact dyadic, summing to 1, in the closed simplex).
    points: Vec<Vec<Q>>,
}

fn q(x: f64) -> Q {
    Q::from_float(x).expect("generated numbers are finite")
}

fn dyadic(numerator: i64, log2_denominator: u32) -> f64 {
    numerator as f64 / f64::from(1u32 << log2_denominator)
}

/// Multi-indices of degree `d` in `m` variables in canonical (lexicographically decreasing)
/// order, spec §4.3.
fn multi_indices(m: usize, d: u32) -> Vec<Vec<u32>> {
    if m == 1 {
        return vec![vec![d]];
    }
    let mut out = Vec::new();
    for first in (0..=d).rev() {
        for rest in multi_indices(m - 1, d - first) {
            let mut i = vec![first];
            i.extend(rest);
            out.push(i);
        }
    }
    out
}

fn factorial(k: u32) -> BigInt {
    (1..=k).fold(BigInt::one(), |a, b| a * BigInt::from(b))
}

fn pow(x: &Q, e: u32) -> Q {
    (0..e).fold(Q::one(), |a, _| a * x)
}

fn binomial(n: u32, k: u32) -> u32 {
    if k > n {
        return 0;
    }
    (0..k).fold(1u64, |a, i| a * u64::from(n - i) / u64::from(i + 1)) as u32
}

impl Generated {
    /// Builds a model from the fuzzer's bytes (`None` when they run out early).
    pub fn from_bytes(data: &[u8]) -> Option<Generated> {
        Generated::build(&mut Unstructured::new(data)).ok()
    }

    fn build(u: &mut Unstructured) -> Result<Generated> {
        let n: usize = if u.arbitrary()? { 3 } else { 2 };
        let cells: Vec<usize> = if n == 2 {
            vec![u.int_in_range(1..=2)?, u.int_in_range(1..=2)?]
        } else {
            vec![u.int_in_range(1..=2)?, 1, 1]
        };
        // Grid vertices, x fastest, each coordinate perturbed by a multiple of 1/64 in [-6, 6]/64.
        let mut positions = Vec::new();
        let ranges: Vec<usize> = cells.iter().map(|c| c + 1).collect();
        let total: usize = ranges.iter().product();
        for flat in 0..total {
            let mut g = Vec::with_capacity(n);
            let mut r = flat;
            for &len in &ranges {
                g.push(r % len);
                r /= len;
            }
            let mut p = Vec::with_capacity(n);
            for &c in &g {
                p.push(c as f64 + dyadic(i64::from(u.int_in_range(-6i8..=6)?), 6));
            }
            positions.push(p);
        }
        // Kuhn triangulation: per cell, one simplex per permutation of the axes (grid points are
        // numbered in the builder's flat order, so a corner's index is its vertex id).
        let mut simplices = Vec::new();
        for kuhn in ism_format::builder::kuhn_simplices(&cells) {
            let mut s: Vec<u32> = kuhn.corners.iter().map(|&c| c as u32).collect();
            // Any stored order: rotate by an arbitrary amount, then orient positively.
            let shift = u.int_in_range(0..=n)?;
            s.rotate_left(shift);
            if orientation(&positions, &s) < 0.0 {
                s.swap(n - 1, n);
            }
            simplices.push(s);
        }
        let mut values = Vec::with_capacity(positions.len());
        for _ in 0..positions.len() {
            let a: i8 = u.int_in_range(-8..=7)?;
            values.push(dyadic(
                if a >= 0 {
                    i64::from(a) + 1
                } else {
                    i64::from(a)
                },
                2,
            ));
        }
        // Every face, by its sorted ids.
        let mut faces: BTreeSet<Vec<u32>> = BTreeSet::new();
        for s in &simplices {
            faces.extend(simplex_faces(s, 1).map(|f| f.ids().to_vec()));
        }
        let stage_count = u.int_in_range(1..=2)?;
        let mut stages = Vec::new();
        for _ in 0..stage_count {
            let kind =
                *u.choose(&[StageKind::Bezier, StageKind::Rational, StageKind::Monotonic])?;
            let degree: u32 = if kind == StageKind::Monotonic {
                u.int_in_range(1..=4)?
            } else {
                u.int_in_range(1..=3)?
            };
            let mut stage = GenStage {
                kind,
                degree,
                records: BTreeMap::new(),
                maps: BTreeMap::new(),
            };
            if kind == StageKind::Monotonic {
                for v in 0..positions.len() as u32 {
                    if u.arbitrary()? {
                        let mut a = vec![0.0];
                        let mut sum = 0i64;
                        for _ in 0..degree {
                            sum += i64::from(u.int_in_range(0u8..=16)?);
                            a.push(dyadic(sum, 4));
                        }
                        stage.maps.insert(v, a);
                    }
                }
            } else {
                for f in &faces {
                    let k = f.len() as u32 - 1;
                    let owned = binomial(degree - 1, k);
                    if owned == 0 || !u.arbitrary()? {
                        continue;
                    }
                    let mut points = Vec::new();
                    let mut weights = Vec::new();
                    for _ in 0..owned {
                        // k free coordinates in [0, 64]/64; the last makes the sum exactly 1.
                        let mut rest = 64i64;
                        for _ in 0..k {
                            let c = i64::from(u.int_in_range(0u8..=64)?);
                            rest -= c;
                            points.push(dyadic(c, 6));
                        }
                        points.push(dyadic(rest, 6));
                        if kind == StageKind::Rational {
                            weights.push(dyadic(i64::from(u.int_in_range(0u8..=32)?), 3));
                        }
                    }
                    stage.records.insert(f.clone(), (points, weights));
                }
            }
            stages.push((stage, u.arbitrary::<bool>()?));
        }
        // Sample points: the vertices, edge midpoints (and in 3D triangle points) with coordinates
        // in {0, 1/2, 1}, the centre-like points with coordinates in {0, 1/4, …, 1} that have no
        // zero coordinate, and a few from the bytes.
        let mut points: Vec<Vec<Q>> = multi_indices(n + 1, 2)
            .into_iter()
            .chain(
                multi_indices(n + 1, 4)
                    .into_iter()
                    .filter(|i| i.iter().all(|&a| a > 0)),
            )
            .map(|i| {
                let d: u32 = i.iter().sum();
                i.iter()
                    .map(|&a| Q::new(BigInt::from(a), BigInt::from(d)))
                    .collect()
            })
            .collect();
        for _ in 0..4 {
            let mut w = Vec::new();
            let mut rest = 1024i64;
            for _ in 0..n {
                let a = i64::from(u.arbitrary::<u8>()?);
                rest -= a;
                w.push(Q::new(BigInt::from(a), BigInt::from(1024)));
            }
            if rest >= 0 {
                w.insert(0, Q::new(BigInt::from(rest), BigInt::from(1024)));
                points.push(w);
            }
        }

        let mut model = Model::new(n as u8);
        model.vertices = positions.iter().flatten().copied().collect();
        model.simplices = simplices.iter().flatten().copied().collect();
        model.values = values;
        for (s, parametric) in &stages {
            model.stages.push(Stage {
                kind: s.kind,
                degree: s.degree,
                direction: if *parametric {
                    Direction::Parametric
                } else {
                    Direction::Implicit
                },
                name: None,
                faces: s
                    .records
                    .iter()
                    .map(|(face, (points, weights))| FaceRecord {
                        face: face.clone(),
                        points: points.clone(),
                        weights: weights.clone(),
                    })
                    .collect(),
                vertex_maps: s
                    .maps
                    .iter()
                    .map(|(&vertex, coefficients)| VertexMap {
                        vertex,
                        coefficients: coefficients.clone(),
                    })
                    .collect(),
                extras: Default::default(),
            });
        }
        Ok(Generated {
            model,
            positions,
            simplices,
            stages: stages.into_iter().map(|(s, _)| s).collect(),
            points,
        })
    }

    /// Every (stage, simplex, sample point) where `det DY_σ ≤ 0` exactly (or where a rational or
    /// monotonic stage's denominator is not positive), as `(stage, simplex, point)`; at most `max`.
    pub fn nonpositive_jacobians(&self, max: usize) -> Vec<(usize, usize, Vec<Q>)> {
        let mut out = Vec::new();
        for (si, stage) in self.stages.iter().enumerate() {
            for (ti, s) in self.simplices.iter().enumerate() {
                let net = stage.dense_net(s);
                for w in &self.points {
                    if !stage.det_positive(s, net.as_deref(), w) {
                        out.push((si, ti, w.clone()));
                        if out.len() >= max {
                            return out;
                        }
                    }
                }
            }
        }
        out
    }

    /// The number of vertices (for messages).
    pub fn num_vertices(&self) -> usize {
        self.positions.len()
    }
}

/// `det[p1 − p0, …, pn − p0]` in `f64` (the generated coordinates are small dyadics, so the sign is
/// exact except for degenerate simplices, which the structural check then refuses).
fn orientation(positions: &[Vec<f64>], s: &[u32]) -> f64 {
    let p = |k: usize| &positions[s[k] as usize];
    let e = |k: usize| -> Vec<f64> { p(k).iter().zip(p(0)).map(|(a, b)| a - b).collect() };
    if s.len() == 3 {
        let (a, b) = (e(1), e(2));
        a[0] * b[1] - a[1] * b[0]
    } else {
        let (a, b, c) = (e(1), e(2), e(3));
        a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
            + a[2] * (b[0] * c[1] - b[1] * c[0])
    }
}

/// One control point of a dense net: local multi-index, barycentric point, weight.
type NetEntry = (Vec<u32>, Vec<Q>, Q);

impl GenStage {
    /// The dense control net of simplex `s` (spec §5.2 steps 1–3, §5.3), or `None` for a
    /// monotonic stage.
    fn dense_net(&self, s: &[u32]) -> Option<Vec<NetEntry>> {
        if self.kind == StageKind::Monotonic {
            return None;
        }
        let m = s.len();
        let d = self.degree;
        let mut net = Vec::new();
        for i in multi_indices(m, d) {
            let mut tau: Vec<u32> = (0..m).filter(|&p| i[p] > 0).map(|p| s[p]).collect();
            tau.sort_unstable();
            let pos = |t: u32| s.iter().position(|&x| x == t).unwrap();
            let mut b = vec![Q::zero(); m];
            let mut weight = Q::one();
            match self.records.get(&tau) {
                Some((points, weights)) => {
                    let k1 = tau.len();
                    let j_minus_1: Vec<u32> = tau.iter().map(|&t| i[pos(t)] - 1).collect();
                    let r = multi_indices(k1, d - k1 as u32)
                        .iter()
                        .position(|x| *x == j_minus_1)
                        .expect("an owned multi-index");
                    for (j, &t) in tau.iter().enumerate() {
                        b[pos(t)] = q(points[r * k1 + j]);
                    }
                    if !weights.is_empty() {
                        weight = q(weights[r]);
                    }
                }
                None => {
                    for p in 0..m {
                        b[p] = Q::new(BigInt::from(i[p]), BigInt::from(d));
                    }
                }
            }
            net.push((i, b, weight));
        }
        Some(net)
    }

    /// Whether `det DY_σ(w) > 0` (and the denominator is positive), exactly.
    fn det_positive(&self, s: &[u32], net: Option<&[NetEntry]>, w: &[Q]) -> bool {
        let m = s.len();
        // Y = N / D with N_i, D and their partial derivatives in the m barycentric variables
        // taken as independent.
        let mut num = vec![Q::zero(); m];
        let mut dnum = vec![vec![Q::zero(); m]; m];
        let mut den = Q::zero();
        let mut dden = vec![Q::zero(); m];
        match net {
            Some(net) => {
                let d = self.degree;
                for (i, b, weight) in net {
                    let coef = Q::from_integer(
                        factorial(d) / i.iter().map(|&x| factorial(x)).product::<BigInt>(),
                    ) * weight;
                    let basis = i
                        .iter()
                        .zip(w)
                        .fold(coef.clone(), |a, (&e, x)| a * pow(x, e));
                    let grad: Vec<Q> = (0..m)
                        .map(|k| {
                            if i[k] == 0 {
                                return Q::zero();
                            }
                            (0..m).fold(coef.clone() * Q::from_integer(i[k].into()), |a, p| {
                                a * pow(&w[p], if p == k { i[p] - 1 } else { i[p] })
                            })
                        })
                        .collect();
                    for r in 0..m {
                        num[r] += &b[r] * &basis;
                        for k in 0..m {
                            dnum[r][k] += &b[r] * &grad[k];
                        }
                    }
                    den += &basis;
                    for k in 0..m {
                        dden[k] += &grad[k];
                    }
                }
            }
            None => {
                let d = self.degree;
                // A vertex without a map has g(t) = t: coefficients j/d (exact here, not f64).
                let identity: Vec<Q> = (0..=d)
                    .map(|j| Q::new(BigInt::from(j), BigInt::from(d)))
                    .collect();
                for r in 0..m {
                    let stored: Option<Vec<Q>> = self
                        .maps
                        .get(&s[r])
                        .map(|a| a.iter().map(|&x| q(x)).collect());
                    let a = stored.as_ref().unwrap_or(&identity);
                    let (g, dg) = bernstein_1d(a, d, &w[r]);
                    num[r] = g.clone();
                    dnum[r][r] = dg.clone();
                    den += g;
                    dden[r] = dg;
                }
            }
        }
        if !den.is_positive() {
            return false;
        }
        // Local coordinates t_j = w_j (j ≥ 1), w_0 = 1 − Σ t: ∂/∂t_j = ∂_j − ∂_0. Rows 1..m of
        // D·∂N − N·∂D (the Jacobian of N/D times D², D² > 0).
        let n = m - 1;
        let mut jac = vec![vec![Q::zero(); n]; n];
        for r in 1..m {
            for j in 1..m {
                let dn = &dnum[r][j] - &dnum[r][0];
                let dd = &dden[j] - &dden[0];
                jac[r - 1][j - 1] = &den * dn - &num[r] * dd;
            }
        }
        determinant(jac).is_positive()
    }
}

/// `g(t) = Σ a_j C(d, j) t^j (1 − t)^(d − j)` and `g'(t)`.
fn bernstein_1d(a: &[Q], d: u32, t: &Q) -> (Q, Q) {
    let one_minus = Q::one() - t;
    let mut g = Q::zero();
    let mut dg = Q::zero();
    for (j, aj) in a.iter().enumerate() {
        let j = j as u32;
        let c = aj * Q::from_integer(binomial(d, j).into());
        g += &c * pow(t, j) * pow(&one_minus, d - j);
        if j > 0 {
            dg += &c * Q::from_integer(j.into()) * pow(t, j - 1) * pow(&one_minus, d - j);
        }
        if j < d {
            dg -= &c * Q::from_integer((d - j).into()) * pow(t, j) * pow(&one_minus, d - j - 1);
        }
    }
    (g, dg)
}

/// Exact determinant by cofactor expansion (n ≤ 3).
fn determinant(m: Vec<Vec<Q>>) -> Q {
    match m.len() {
        1 => m[0][0].clone(),
        2 => &m[0][0] * &m[1][1] - &m[0][1] * &m[1][0],
        _ => {
            let minor =
                |a: usize, b: usize, c: usize, e: usize| &m[a][c] * &m[b][e] - &m[a][e] * &m[b][c];
            &m[0][0] * minor(1, 2, 1, 2) - &m[0][1] * minor(1, 2, 0, 2)
                + &m[0][2] * minor(1, 2, 0, 1)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The identity stage (no records) has det 1 everywhere; a stage whose edge point sits on a
    /// vertex folds there (spec/vectors/validate/edge-point-on-vertex: det 0 at the vertex).
    #[test]
    fn exact_check_sees_identity_positive_and_a_fold() {
        let mut net_stage = GenStage {
            kind: StageKind::Bezier,
            degree: 2,
            records: BTreeMap::new(),
            maps: BTreeMap::new(),
        };
        let s = [0u32, 1, 2];
        let corner = vec![Q::one(), Q::zero(), Q::zero()];
        let inside = vec![
            Q::new(1.into(), 2.into()),
            Q::new(1.into(), 4.into()),
            Q::new(1.into(), 4.into()),
        ];
        for w in [&corner, &inside] {
            let net = net_stage.dense_net(&s);
            assert!(net_stage.det_positive(&s, net.as_deref(), w));
        }
        // Edge [0, 1]'s control point moved onto vertex 1: Y(w) along the edge is
        // w0² e0 + (2 w0 w1 + w1²) e1, whose derivative vanishes at w1 = 1.
        net_stage
            .records
            .insert(vec![0, 1], (vec![0.0, 1.0], vec![]));
        let net = net_stage.dense_net(&s);
        let at_vertex_1 = vec![Q::zero(), Q::one(), Q::zero()];
        assert!(!net_stage.det_positive(&s, net.as_deref(), &at_vertex_1));
        assert!(net_stage.det_positive(&s, net.as_deref(), &inside));
    }

    /// A monotonic map with a flat start has det 0 at the vertex where `g'(0) = 0`.
    #[test]
    fn exact_check_of_monotonic_maps() {
        let mut stage = GenStage {
            kind: StageKind::Monotonic,
            degree: 2,
            records: BTreeMap::new(),
            maps: BTreeMap::new(),
        };
        let s = [0u32, 1, 2];
        let inside = vec![
            Q::new(1.into(), 2.into()),
            Q::new(1.into(), 4.into()),
            Q::new(1.into(), 4.into()),
        ];
        assert!(stage.det_positive(&s, None, &inside));
        // g_1(t) = t² (a = 0, 0, 1): g_1'(0) = 0, so det DY = 0 where w1 = 0.
        stage.maps.insert(1, vec![0.0, 0.0, 1.0]);
        let w1_zero = vec![
            Q::new(1.into(), 2.into()),
            Q::zero(),
            Q::new(1.into(), 2.into()),
        ];
        assert!(!stage.det_positive(&s, None, &w1_zero));
        assert!(stage.det_positive(&s, None, &inside));
    }

    /// Generated models are structurally valid, and all-zero bytes give one (the identity-like
    /// model the fuzzer starts from).
    #[test]
    fn generated_models_are_structurally_valid() {
        let mut checked = 0;
        for seed in 0u8..64 {
            let bytes: Vec<u8> = (0..512u32)
                .map(|i| (i as u8).wrapping_mul(seed).wrapping_add(seed))
                .collect();
            let Some(g) = Generated::from_bytes(&bytes) else {
                continue;
            };
            let errors: Vec<_> = ism_format::structure::check(&g.model, 10)
                .into_iter()
                .filter(|d| d.severity == ism_format::Severity::Error)
                .collect();
            assert!(errors.is_empty(), "seed {seed}: {errors:?}");
            checked += 1;
        }
        assert!(checked > 32, "only {checked} models generated");
    }
}
