//! Test-model generators: Kuhn grids and random valid stages of every kind.
//!
//! Every generator documents why its stages are valid (a theorem of Mello & Velho 2009, or a bound), so the
//! property tests that use them test the kernel, not luck.
#![allow(dead_code, clippy::needless_range_loop)]

use ism_format::{
    multi_index, Direction, FaceRecord, Model, Stage, StageKind, Topology, VertexMap,
};

/// SplitMix64: small, seedable, good enough for test data; proptest supplies the seeds.
pub struct Rng(pub u64);

impl Rng {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    pub fn uniform(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * self.unit()
    }
    pub fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }
    /// A point of the open simplex with `k` coordinates, each ≥ `lo` (needs `k·lo < 1`).
    pub fn open_simplex(&mut self, k: usize, lo: f64) -> Vec<f64> {
        let raw: Vec<f64> = (0..k).map(|_| -self.unit().max(1e-300).ln()).collect();
        let s: f64 = raw.iter().sum();
        raw.iter()
            .map(|r| lo + (1.0 - k as f64 * lo) * r / s)
            .collect()
    }
    /// Random barycentric point (`m` entries) of the closed simplex; with probability ~1/2 some
    /// coordinates are set to exactly 0 (a point on a face, an edge or a vertex).
    pub fn bary(&mut self, m: usize) -> [f64; 4] {
        let mut w = [0.0; 4];
        let raw = self.open_simplex(m, 0.0);
        w[..m].copy_from_slice(&raw);
        if self.unit() < 0.5 {
            let keep = 1 + self.below(m);
            let mut ids: Vec<usize> = (0..m).collect();
            for i in 0..m {
                let j = i + self.below(m - i);
                ids.swap(i, j);
            }
            let sub = self.open_simplex(keep, 0.0);
            w = [0.0; 4];
            for (k, &i) in ids[..keep].iter().enumerate() {
                w[i] = sub[k];
            }
        }
        w
    }
}

fn orient(model: &Model, ids: &mut [u32]) {
    let n = model.dim();
    let v0 = model.vertex(ids[0] as usize).to_vec();
    let mut e = [[0.0; 4]; 4];
    for l in 0..n {
        let v = model.vertex(ids[l + 1] as usize);
        for x in 0..n {
            e[x][l] = v[x] - v0[x];
        }
    }
    if ism_geom::linalg::det(n, &e) < 0.0 {
        ids.swap(0, 1);
    }
}

/// Kuhn (Freudenthal) triangulation of `[0,k]ⁿ` (n = 2: 2 triangles per square, n = 3: 6 tetrahedra
/// per cube), values from `rng` in `±[0.2, 1]`, positively oriented. Vertex ids are shuffled so
/// that local vertex order and global id order disagree.
pub fn kuhn(n: usize, k: usize, rng: &mut Rng) -> Model {
    let side = k + 1;
    let nv = side.pow(n as u32);
    let mut perm: Vec<u32> = (0..nv as u32).collect();
    for i in 0..nv {
        let j = i + rng.below(nv - i);
        perm.swap(i, j);
    }
    let mut model = Model::new(n as u8);
    model.vertices = vec![0.0; nv * n];
    model.values = vec![0.0; nv];
    for g in 0..nv {
        let mut c = g;
        let id = perm[g] as usize;
        for x in 0..n {
            model.vertices[id * n + x] = (c % side) as f64;
            c /= side;
        }
        let mag = rng.uniform(0.2, 1.0);
        model.values[id] = if rng.unit() < 0.5 { -mag } else { mag };
    }
    for s in ism_format::builder::kuhn_simplices(&vec![k; n]) {
        let mut ids: Vec<u32> = s.corners.iter().map(|&g| perm[g]).collect();
        orient(&model, &mut ids);
        model.simplices.extend_from_slice(&ids);
    }
    model
}

/// All faces with `k1` vertices (sorted ids), deduplicated, in lexicographic order: the indexed
/// complex's face table.
pub fn faces(model: &Model, k1: usize) -> Vec<Vec<u32>> {
    if k1 == 0 {
        return Vec::new();
    }
    let topology = Topology::of_complex(model).expect("a generated grid indexes");
    let flat = topology.sorted_faces(model, k1 - 1);
    flat.chunks_exact(k1).map(<[u32]>::to_vec).collect()
}

fn stage(kind: StageKind, degree: u32) -> Stage {
    Stage::identity(kind, degree)
}

/// Adjusted quadratic: one random point per edge, coordinates in `[0.02, 0.98]`. A diffeo by
/// Mello & Velho 2009, Prop. 5.6 (any `n`).
pub fn adjusted_quadratic(model: &Model, rng: &mut Rng) -> Stage {
    let mut st = stage(StageKind::Bezier, 2);
    for f in faces(model, 2) {
        let a = rng.uniform(0.02, 0.98);
        st.faces.push_record(&FaceRecord {
            face: f,
            points: vec![a, 1.0 - a],
            weights: vec![],
        });
    }
    st
}

/// Stratum `G_j`: the solitary centre point of every `j`-face, degree `j + 1`, each in the open face
/// with coordinates ≥ 0.01. A diffeo for n ≤ 3 (Mello & Velho 2009, Prop. 5.7–5.9).
pub fn stratum(model: &Model, rng: &mut Rng, j: usize) -> Stage {
    let mut st = stage(StageKind::Bezier, j as u32 + 1);
    for f in faces(model, j + 1) {
        let p = rng.open_simplex(j + 1, 0.01);
        st.faces.push_record(&FaceRecord {
            face: f,
            points: p,
            weights: vec![],
        });
    }
    st
}

/// One solitary free point: a random face of dimension `j`, degree `j + 1` (Mello & Velho 2009, Prop. 5.7).
pub fn solitary(model: &Model, rng: &mut Rng, j: usize) -> Stage {
    let all = faces(model, j + 1);
    let f = all[rng.below(all.len())].clone();
    let mut st = stage(StageKind::Bezier, j as u32 + 1);
    st.faces.push_record(&FaceRecord {
        face: f,
        points: rng.open_simplex(j + 1, 0.005),
        weights: vec![],
    });
    st
}

/// Stratified composition `G_1 ∘ … ∘ G_n` (`G_n` applied first).
pub fn stratified(model: &Model, rng: &mut Rng) -> Vec<Stage> {
    (1..=model.dim())
        .rev()
        .map(|j| stratum(model, rng, j))
        .collect()
}

/// Every control point fixed, random positive weights in `[0.05, 20]` on every face (vertices
/// included). A diffeo for any degree (Mello & Velho 2009, Thm. 6.4).
pub fn rational_fixed(model: &Model, rng: &mut Rng, d: u32) -> Stage {
    let mut st = stage(StageKind::Rational, d);
    for k1 in 1..=model.dim() + 1 {
        let owned = multi_index::owned(k1, d);
        if owned.is_empty() {
            continue;
        }
        for f in faces(model, k1) {
            let points: Vec<f64> = owned.iter().map(|&e| f64::from(e) / f64::from(d)).collect();
            let weights = (0..owned.len() / k1)
                .map(|_| (rng.uniform(-3.0, 3.0)).exp())
                .collect();
            st.faces.push_record(&FaceRecord {
                face: f,
                points,
                weights,
            });
        }
    }
    st
}

/// Bézier of degree `d`: every owned control point moved from `I/d` by at most `eps/d` inside its
/// face (a zero-sum perturbation). Every reduced-Jacobian coefficient `d(b_{I+e_k} − b_{I+e_0})` moves
/// by at most `2·eps` per entry, so for `eps ≤ 0.05` the Jacobian is `Id + E` with `|E_ij| ≤ 0.1`:
/// Gershgorin puts every eigenvalue within 0.3 of 1, so `det > 0` — valid for n ≤ 3.
pub fn near_identity_bezier(model: &Model, rng: &mut Rng, d: u32, eps: f64) -> Stage {
    let mut st = stage(StageKind::Bezier, d);
    for k1 in 2..=model.dim() + 1 {
        let owned = multi_index::owned(k1, d);
        if owned.is_empty() {
            continue;
        }
        for f in faces(model, k1) {
            let mut points = Vec::with_capacity(owned.len());
            for j in owned.chunks_exact(k1) {
                let raw: Vec<f64> = (0..k1).map(|_| rng.uniform(-1.0, 1.0)).collect();
                let mean = raw.iter().sum::<f64>() / k1 as f64;
                let dev: Vec<f64> = raw.iter().map(|r| r - mean).collect();
                let scale = dev.iter().fold(0.0f64, |a, b| a.max(b.abs())).max(1e-12);
                for (e, v) in j.iter().zip(&dev) {
                    points.push(f64::from(*e) / f64::from(d) + v / scale * eps / f64::from(d));
                }
            }
            st.faces.push_record(&FaceRecord {
                face: f,
                points,
                weights: vec![],
            });
        }
    }
    st
}

/// Monotonic: per vertex, strictly increasing coefficients `0 < a_1 < … < a_d` (increments in
/// `[0.05, 1]`). A diffeo (Mello & Velho 2009, §4).
pub fn monotonic(model: &Model, rng: &mut Rng, d: u32) -> Stage {
    let mut st = stage(StageKind::Monotonic, d);
    for v in 0..model.num_vertices() as u32 {
        let mut a = vec![0.0];
        for _ in 0..d {
            let last = *a.last().unwrap_or(&0.0);
            a.push(last + rng.uniform(0.05, 1.0));
        }
        st.vertex_maps.push(VertexMap {
            vertex: v,
            coefficients: a,
        });
    }
    st
}

/// The kinds exercised by the round-trip tests.
#[derive(Clone, Copy, Debug)]
pub enum Kind {
    AdjustedQuadratic,
    NearIdentity(u32),
    Solitary,
    Rational(u32),
    Monotonic(u32),
}

pub const KINDS: [Kind; 11] = [
    Kind::AdjustedQuadratic,
    Kind::NearIdentity(2),
    Kind::NearIdentity(3),
    Kind::NearIdentity(5),
    Kind::Solitary,
    Kind::Rational(2),
    Kind::Rational(3),
    Kind::Rational(5),
    Kind::Monotonic(2),
    Kind::Monotonic(3),
    Kind::Monotonic(5),
];

pub fn make(kind: Kind, model: &Model, rng: &mut Rng, parametric: bool) -> Stage {
    let mut st = match kind {
        Kind::AdjustedQuadratic => adjusted_quadratic(model, rng),
        Kind::NearIdentity(d) => near_identity_bezier(model, rng, d, 0.05),
        Kind::Solitary => {
            let j = 1 + rng.below(model.dim());
            solitary(model, rng, j)
        }
        Kind::Rational(d) => rational_fixed(model, rng, d),
        Kind::Monotonic(d) => monotonic(model, rng, d),
    };
    if parametric {
        st.direction = Direction::Parametric;
    }
    st
}
