//! Invariants of the generators over random sizes, boxes, seeds and amplitudes.

use ism_examples::{
    cubic_face_point_stage, faces_of_dimension, kuhn_grid_2d, kuhn_grid_3d, monotonic_stage,
    quadratic_edge_stage, rational_fixed_points_stage, seeded_weights, stratified_stages, Aabb,
};
use ism_format::structure::{check, orientation};
use proptest::prelude::*;

fn assert_clean(model: &ism_format::Model) {
    let diagnostics = check(model, 20);
    assert!(diagnostics.is_empty(), "{diagnostics:?}");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn grids_tile_their_box_with_positive_simplices(
        nx in 1usize..5, ny in 1usize..5, nz in 1usize..4,
        lo in -3.0f64..0.0, size in 0.1f64..4.0, offset in -1.0f64..1.0,
    ) {
        let m2 = kuhn_grid_2d(nx, ny, Aabb::new([lo, lo], [lo + size, lo + 2.0 * size]), |p| p[0] - offset).unwrap();
        let m3 = kuhn_grid_3d(nx, ny, nz, Aabb::cube(lo, lo + size), |p| p[1] + p[2] - offset).unwrap();
        assert_clean(&m2);
        assert_clean(&m3);
        let area: f64 = (0..m2.num_simplices()).map(|s| orientation(&m2, s).0 / 2.0).sum();
        prop_assert!((area - 2.0 * size * size).abs() <= 1e-9 * size * size);
        let volume: f64 = (0..m3.num_simplices()).map(|s| orientation(&m3, s).0 / 6.0).sum();
        prop_assert!((volume - size.powi(3)).abs() <= 1e-9 * size.powi(3));
        // Euler characteristic of a triangulated disk / ball is 1.
        let c2: Vec<i64> = (0..3).map(|k| (faces_of_dimension(&m2, k).len() / (k + 1)) as i64).collect();
        prop_assert_eq!(c2[0] - c2[1] + c2[2], 1);
        let c3: Vec<i64> = (0..4).map(|k| (faces_of_dimension(&m3, k).len() / (k + 1)) as i64).collect();
        prop_assert_eq!(c3[0] - c3[1] + c3[2] - c3[3], 1);
    }

    #[test]
    fn stages_are_structurally_valid_and_adjusted(
        seed in any::<u64>(), amplitude in -1.0f64..3.0, degree in 1u32..7, spread in 0.0f64..2.0,
    ) {
        let m2 = kuhn_grid_2d(3, 2, Aabb::cube(-1.0, 1.0), |p| p[0] * p[0] + p[1] * p[1] - 0.4).unwrap();
        let m3 = kuhn_grid_3d(2, 2, 1, Aabb::cube(-1.0, 1.0), |p| p[0] * p[0] + p[1] * p[1] + p[2] * p[2] - 0.4).unwrap();
        for base in [&m2, &m3] {
            let mut stages = stratified_stages(base, seed, amplitude);
            stages.push(quadratic_edge_stage(base, seed, amplitude));
            stages.push(cubic_face_point_stage(base, seed, amplitude));
            stages.push(rational_fixed_points_stage(base, degree, seeded_weights(seed, spread)));
            stages.push(monotonic_stage(base, degree, seed, amplitude));
            for stage in &stages {
                for record in &stage.faces {
                    let k1 = record.face.len();
                    for point in record.points.chunks(k1) {
                        prop_assert!(point.iter().all(|&c| c > 0.0));
                        prop_assert!((point.iter().sum::<f64>() - 1.0).abs() < 1e-14);
                    }
                    prop_assert!(record.weights.iter().all(|&q| q > 0.0 && q.is_finite()));
                }
                for map in &stage.vertex_maps {
                    prop_assert_eq!(map.coefficients[0], 0.0);
                    prop_assert!(map.coefficients.windows(2).all(|w| w[1] > w[0]));
                }
            }
            let mut model = base.clone();
            model.stages = stages;
            assert_clean(&model);
        }
    }
}
