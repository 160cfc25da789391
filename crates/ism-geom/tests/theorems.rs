//! The injectivity theorems of Mello & Velho 2009 as property tests: `det DX > 0` at sampled points (lattice
//! points of every simplex, boundary included) for every construction the theorems cover, and the
//! degree-4 1-D counterexample (Mello & Velho 2009, Fig. 2) has `det < 0` somewhere.

// Index loops over barycentric coordinates mirror the formulas under test.
#![allow(clippy::needless_range_loop)]

mod common;

use common::Rng;
use ism_format::{FaceRecord, Model, Stage, StageKind};
use ism_geom::{Bernstein, LocalMap, LocalStage};
use proptest::prelude::*;

/// Barycentric lattice of resolution `r` (all `w = I/r`, `|I| = r`): vertices, edges and faces
/// included, where positivity is hardest.
fn lattice(m: usize, r: u32) -> Vec<[f64; 4]> {
    ism_format::multi_index::all(m, r)
        .chunks_exact(m)
        .map(|i| {
            let mut w = [0.0; 4];
            for k in 0..m {
                w[k] = f64::from(i[k]) / f64::from(r);
            }
            w
        })
        .collect()
}

fn min_det(model: &Model, rng: &mut Rng) -> f64 {
    let m = model.dim() + 1;
    let mut pts = lattice(m, 9);
    pts.extend((0..30).map(|_| rng.bary(m)));
    let mut min = f64::INFINITY;
    for s in 0..model.num_simplices() {
        let map = LocalMap::from_model(model, s).unwrap();
        for w in &pts {
            min = min.min(map.det(w));
        }
    }
    min
}

fn grid(n: usize, rng: &mut Rng) -> Model {
    common::kuhn(n, if n == 2 { 2 } else { 1 }, rng)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 40, ..ProptestConfig::default() })]

    /// Mello & Velho 2009, Prop. 5.6: adjusted quadratic ⇒ diffeo (any n).
    #[test]
    fn adjusted_quadratic_stages_have_positive_jacobian(seed in any::<u64>(), n in 2usize..=3) {
        let mut rng = Rng(seed);
        let mut model = grid(n, &mut rng);
        let st = common::adjusted_quadratic(&model, &mut rng);
        model.stages.push(st);
        let d = min_det(&model, &mut rng);
        prop_assert!(d > 0.0, "min det {}", d);
    }

    /// Mello & Velho 2009, Prop. 5.7: one solitary free point anywhere in its open face ⇒ diffeo.
    #[test]
    fn solitary_stages_have_positive_jacobian(seed in any::<u64>(), n in 2usize..=3) {
        let mut rng = Rng(seed);
        let mut model = grid(n, &mut rng);
        for j in 1..=n {
            model.stages = vec![common::solitary(&model, &mut rng, j)];
            let d = min_det(&model, &mut rng);
            prop_assert!(d > 0.0, "j={} min det {}", j, d);
        }
    }

    /// Mello & Velho 2009, §5.4: every stratum `G_j` is a diffeo for n ≤ 3, hence so is the composition.
    #[test]
    fn stratified_compositions_have_positive_jacobian(seed in any::<u64>(), n in 2usize..=3) {
        let mut rng = Rng(seed);
        let mut model = grid(n, &mut rng);
        model.stages = common::stratified(&model, &mut rng);
        let d = min_det(&model, &mut rng);
        prop_assert!(d > 0.0, "min det {}", d);
    }

    /// Mello & Velho 2009, Thm. 6.4: fixed control points with any positive weights ⇒ diffeo, any degree.
    #[test]
    fn fixed_point_rational_stages_have_positive_jacobian(seed in any::<u64>(), n in 2usize..=3, d in 1u32..=5) {
        let mut rng = Rng(seed);
        let mut model = grid(n, &mut rng);
        let st = common::rational_fixed(&model, &mut rng, d);
        model.stages.push(st);
        let m = min_det(&model, &mut rng);
        prop_assert!(m > 0.0, "min det {}", m);
    }

    /// Mello & Velho 2009, §4: monotonic stages with strictly increasing coefficients are diffeos.
    #[test]
    fn monotonic_stages_have_positive_jacobian(seed in any::<u64>(), n in 2usize..=3, d in 1u32..=5) {
        let mut rng = Rng(seed);
        let mut model = grid(n, &mut rng);
        let st = common::monotonic(&model, &mut rng, d);
        model.stages.push(st);
        let m = min_det(&model, &mut rng);
        prop_assert!(m > 0.0, "min det {}", m);
    }
}

/// Control points on edge (0, 1) of degree 4 at positions `x` (second coordinate) for the owned
/// indices (3,1), (2,2), (1,3).
fn edge_stage(x: [f64; 3]) -> Stage {
    let mut st = Stage::identity(StageKind::Bezier, 4);
    let points = x.iter().flat_map(|&t| [1.0 - t, t]).collect();
    st.faces.push_record(&FaceRecord {
        face: vec![0, 1],
        points,
        weights: vec![],
    });
    st
}

/// Mello & Velho 2009, Fig. 2: an adjusted degree-4 map with `b13` and `b31` exchanged is not injective. The
/// text does not give the figure's positions; ordered positions 0.1, 0.5, 0.9 with the two ends
/// exchanged reproduce it. Checked three ways: the 1-D stage (an edge as a 1-simplex), the 2-D
/// stage on a triangle containing that edge, and the 1-D Bernstein derivative.
#[test]
fn degree_four_counterexample_has_negative_jacobian() {
    let ordered = edge_stage([0.1, 0.5, 0.9]);
    let swapped = edge_stage([0.9, 0.5, 0.1]);
    let mid = [0.5, 0.5, 0.0, 0.0];
    let one_d = |st: &Stage| LocalStage::from_stage(st, 0, &[0, 1]).unwrap();
    let two_d = |st: &Stage| LocalStage::from_stage(st, 0, &[0, 1, 2]).unwrap();

    assert!(one_d(&swapped).det(&mid) < 0.0);
    assert!(two_d(&swapped).det(&mid) < 0.0);
    // The ordered configuration is a diffeo (Prop. 5.4): positive everywhere sampled.
    for w in lattice(2, 40) {
        assert!(one_d(&ordered).det(&w) > 0.0);
    }
    for w in lattice(3, 12) {
        assert!(two_d(&ordered).det(&w) > 0.0);
    }
    // The edge coordinate x(t) as a Bernstein polynomial: x' < 0 at t = 1/2, and not monotone:
    // x(0.3) > x(0.7).
    let x = Bernstein::new(2, 4, vec![0.0, 0.9, 0.5, 0.1, 1.0]).unwrap();
    assert!(x.derivative(1).eval(&[0.5, 0.5]) < 0.0);
    assert!(x.eval(&[0.7, 0.3]) > x.eval(&[0.3, 0.7]));
    // Same non-monotonicity seen through the stage's own evaluation.
    let st = one_d(&swapped);
    assert!(st.eval(&[0.7, 0.3, 0.0, 0.0])[1] > st.eval(&[0.3, 0.7, 0.0, 0.0])[1]);
    // Exchanging the fixed positions instead gives x' = 3(1 − 2t)² ≥ 0: zero at the midpoint, so
    // still not a diffeomorphism.
    let fixed_swapped = one_d(&edge_stage([0.75, 0.5, 0.25]));
    assert!(fixed_swapped.det(&mid).abs() < 1e-14);
}
