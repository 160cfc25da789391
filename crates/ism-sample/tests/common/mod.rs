//! Test models: small Kuhn grids of `[−1, 1]ⁿ` with strongly curved stages of every kind.

#![allow(dead_code)]

use ism_format::{FaceRecord, Model, Stage, StageKind, VertexMap};

/// A deterministic number in `[−1, 1)` from a face and a salt (splitmix64).
pub fn hash_unit(ids: &[u32], salt: u64) -> f64 {
    let mut x = salt.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    for &i in ids {
        x ^= u64::from(i)
            .wrapping_add(0x9E37_79B9_7F4A_7C15)
            .wrapping_add(x << 6)
            .wrapping_add(x >> 2);
        x = x.wrapping_mul(0xBF58_476D_1CE4_E5B9);
        x ^= x >> 31;
    }
    (x >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
}

fn nudge(v: f64) -> f64 {
    if v.abs() < 1e-6 {
        1e-3
    } else {
        v
    }
}

/// Kuhn triangulation of `[−1, 1]²` with `k × k` squares, values `g`.
pub fn kuhn2d(k: usize, g: impl Fn(f64, f64) -> f64) -> Model {
    let mut m = Model::new(2);
    let c = |i: usize| -1.0 + 2.0 * i as f64 / k as f64;
    for j in 0..=k {
        for i in 0..=k {
            m.vertices.extend_from_slice(&[c(i), c(j)]);
            m.values.push(nudge(g(c(i), c(j))));
        }
    }
    kuhn_simplices_into(&mut m, &[k, k]);
    m
}

/// The Kuhn simplices of the grid (ids in the grid's flat order, axis 0 fastest), each positively
/// oriented.
fn kuhn_simplices_into(m: &mut Model, cells: &[usize]) {
    for s in ism_format::builder::kuhn_simplices(cells) {
        m.simplices.extend(s.oriented());
    }
}

/// Kuhn triangulation of `[−1, 1]³` with `k³` cubes (6 tetrahedra each), values `g`.
pub fn kuhn3d(k: usize, g: impl Fn(f64, f64, f64) -> f64) -> Model {
    let mut m = Model::new(3);
    let c = |i: usize| -1.0 + 2.0 * i as f64 / k as f64;
    for kk in 0..=k {
        for j in 0..=k {
            for i in 0..=k {
                m.vertices.extend_from_slice(&[c(i), c(j), c(kk)]);
                m.values.push(nudge(g(c(i), c(j), c(kk))));
            }
        }
    }
    kuhn_simplices_into(&mut m, &[k, k, k]);
    m
}

/// All faces with `k + 1` vertices (sorted ids), each once.
pub fn faces(model: &Model, k: usize) -> Vec<Vec<u32>> {
    let m = model.dim() + 1;
    let mut out: Vec<Vec<u32>> = Vec::new();
    for s in model.simplex_iter() {
        let mut ids = s.to_vec();
        ids.sort_unstable();
        for mask in 0u32..(1 << m) {
            if mask.count_ones() as usize == k + 1 {
                out.push(
                    (0..m)
                        .filter(|i| mask & (1 << i) != 0)
                        .map(|i| ids[i])
                        .collect(),
                );
            }
        }
    }
    out.sort();
    out.dedup();
    out
}

/// The solitary centre point of a face, moved by up to `amplitude` (relative), positive coordinates.
fn moved_centre(face: &[u32], amplitude: f64, salt: u64) -> Vec<f64> {
    let raw: Vec<f64> = (0..face.len())
        .map(|i| 1.0 + amplitude * hash_unit(face, salt + i as u64))
        .collect();
    let t: f64 = raw.iter().sum();
    raw.iter().map(|x| x / t).collect()
}

/// Bézier stage of degree `k + 1` moving the centre point of every `k`-face (a stratum, a
/// diffeomorphism for every position in 2D and 3D).
pub fn stratum(model: &Model, k: usize, amplitude: f64, salt: u64) -> Stage {
    let mut st = Stage::identity(StageKind::Bezier, k as u32 + 1);
    st.faces = faces(model, k)
        .into_iter()
        .map(|f| FaceRecord {
            points: moved_centre(&f, amplitude, salt),
            face: f,
            weights: Vec::new(),
        })
        .collect();
    st
}

/// Rational stage of degree 2 with fixed points and weights `exp(spread · r)` on every edge.
pub fn rational_weights(model: &Model, spread: f64, salt: u64) -> Stage {
    let mut st = Stage::identity(StageKind::Rational, 2);
    st.faces = faces(model, 1)
        .into_iter()
        .map(|f| FaceRecord {
            points: vec![0.5, 0.5],
            weights: vec![(spread * hash_unit(&f, salt)).exp()],
            face: f,
        })
        .collect();
    st
}

/// Monotonic cubic stage: every vertex gets increasing coefficients with random increments.
pub fn monotonic(model: &Model, salt: u64) -> Stage {
    let mut st = Stage::identity(StageKind::Monotonic, 3);
    st.vertex_maps = (0..model.num_vertices() as u32)
        .map(|v| {
            let mut a = vec![0.0];
            for j in 1..=3 {
                let inc = 1.0 + 0.8 * hash_unit(&[v], salt + j);
                a.push(a[j as usize - 1] + inc);
            }
            VertexMap {
                vertex: v,
                coefficients: a,
            }
        })
        .collect();
    st
}

/// 2D circle of radius 0.55 on a 6×6 grid.
pub fn circle_grid() -> Model {
    kuhn2d(6, |x, y| x * x + y * y - 0.55 * 0.55)
}

/// 3D sphere of radius 0.6 on a 3×3×3 grid (162 tetrahedra).
pub fn sphere_grid() -> Model {
    kuhn3d(3, |x, y, z| x * x + y * y + z * z - 0.6 * 0.6)
}

/// The test models: `(name, model)`, each strongly curved.
pub fn curved_models() -> Vec<(&'static str, Model)> {
    let mut out = Vec::new();
    let base = circle_grid();
    let mut m = base.clone();
    m.stages = vec![stratum(&m, 1, 0.7, 1)];
    out.push(("2d quadratic edges", m.clone()));
    let mut p = m.clone();
    p.stages[0].direction = ism_format::Direction::Parametric;
    out.push(("2d quadratic edges, parametric", p));
    let mut s = base.clone();
    s.stages = vec![stratum(&s, 2, 0.8, 2), stratum(&s, 1, 0.6, 3)];
    out.push(("2d stratified", s));
    let mut r = base.clone();
    r.stages = vec![rational_weights(&r, 1.5, 4)];
    out.push(("2d rational weights", r));
    let mut mo = base.clone();
    mo.stages = vec![monotonic(&mo, 5)];
    out.push(("2d monotonic", mo));
    let sp = sphere_grid();
    let mut st = sp.clone();
    st.stages = vec![
        stratum(&st, 3, 0.6, 6),
        stratum(&st, 2, 0.6, 7),
        stratum(&st, 1, 0.6, 8),
    ];
    out.push(("3d stratified", st.clone()));
    // What `ism fit` writes: every stage stored in the parametric direction.
    let mut pst = st;
    for stage in &mut pst.stages {
        stage.direction = ism_format::Direction::Parametric;
    }
    out.push(("3d stratified, parametric", pst.clone()));
    // As fitted models are: stages that move nothing on part of the complex (here the faces
    // with a vertex at x < 0 keep their identity points), whose simplices have no stage at all.
    let mut half = pst;
    let x = |v: u32| half.vertices[3 * v as usize];
    let kept: Vec<Vec<FaceRecord>> = half
        .stages
        .iter()
        .map(|st| {
            st.faces
                .to_records()
                .into_iter()
                .filter(|f| f.face.iter().all(|&v| x(v) > 0.0))
                .collect()
        })
        .collect();
    for (st, faces) in half.stages.iter_mut().zip(kept) {
        st.faces = faces.into();
    }
    out.push(("3d stratified, parametric, half stage-free", half));
    out
}
