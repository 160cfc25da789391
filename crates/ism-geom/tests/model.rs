//! Whole-model evaluation on Kuhn grids with random valid stages: continuity of `F` across every
//! shared face, gradients by finite differences, point location, patches and the parametric map.

// Index loops over barycentric coordinates mirror the formulas under test.
#![allow(clippy::needless_range_loop)]

mod common;

use std::collections::HashMap;

use common::{make, Kind, Rng};
use ism_format::Model;
use ism_geom::{ModelEval, LOCATE_TOLERANCE};
use proptest::prelude::*;

fn random_model(n: usize, seed: u64) -> (Model, Rng) {
    let mut rng = Rng(seed);
    let mut model = common::kuhn(n, 2, &mut rng);
    let mut stages = common::stratified(&model, &mut rng);
    stages.push(make(Kind::Rational(3), &model, &mut rng, false));
    stages.push(make(Kind::Monotonic(2), &model, &mut rng, true));
    stages.push(make(Kind::AdjustedQuadratic, &model, &mut rng, false));
    model.stages = stages;
    (model, rng)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    /// Both sides of every interior facet give the same `F` (to 1e-12) at random points of the
    /// facet, each side evaluated with exact barycentric coordinates in its own local order.
    #[test]
    fn f_is_continuous_across_shared_faces(seed in any::<u64>(), n in 2usize..=3) {
        let (model, mut rng) = random_model(n, seed);
        let eval = ModelEval::new(&model).unwrap();
        let mut facets: HashMap<Vec<u32>, Vec<usize>> = HashMap::new();
        for s in 0..model.num_simplices() {
            let ids = model.simplex(s);
            for skip in 0..=n {
                let mut f: Vec<u32> = ids.iter().enumerate().filter(|&(i, _)| i != skip).map(|(_, &v)| v).collect();
                f.sort_unstable();
                facets.entry(f).or_default().push(s);
            }
        }
        let mut checked = 0;
        for (face, owners) in &facets {
            if owners.len() != 2 {
                continue;
            }
            for _ in 0..3 {
                let mut c = rng.bary(n);
                if c[..n].iter().all(|&x| x == 0.0) {
                    c[0] = 1.0;
                }
                let vals: Vec<f64> = owners
                    .iter()
                    .map(|&s| {
                        let ids = model.simplex(s);
                        let mut w = [0.0; 4];
                        for (k, v) in face.iter().enumerate() {
                            let pos = ids.iter().position(|x| x == v).unwrap();
                            w[pos] = c[k];
                        }
                        eval.value_at(s, &w)
                    })
                    .collect();
                prop_assert!((vals[0] - vals[1]).abs() < 1e-12, "face {:?}: {} vs {}", face, vals[0], vals[1]);
                checked += 1;
            }
        }
        prop_assert!(checked > 0);
    }

    /// `∇F` (chain rule through all stages) against central differences of `F`, at interior points.
    #[test]
    fn gradient_matches_finite_differences(seed in any::<u64>(), n in 2usize..=3) {
        let (model, mut rng) = random_model(n, seed);
        let eval = ModelEval::new(&model).unwrap();
        let h = 1e-6;
        for _ in 0..20 {
            let s = rng.below(model.num_simplices());
            let mut w = [0.0; 4];
            w[..=n].copy_from_slice(&rng.open_simplex(n + 1, 0.05));
            let p = eval.point(s, &w);
            let g = eval.gradient_at(s, &w).unwrap();
            for x in 0..n {
                let mut pp = p;
                let mut pm = p;
                pp[x] += h;
                pm[x] -= h;
                let fd = (eval.value_at(s, &eval.barycentric(s, &pp)) - eval.value_at(s, &eval.barycentric(s, &pm))) / (2.0 * h);
                prop_assert!((g[x] - fd).abs() < 1e-5 * (1.0 + fd.abs()), "∂{}: {} vs {}", x, g[x], fd);
            }
        }
    }

    /// Points of every patch `θ_σ` map through the parametric form onto `F = c`, evaluated back
    /// through point location (independent of the inverse's own residual); the patch normal agrees
    /// with `∇F` there; the parametric Jacobian matches finite differences.
    #[test]
    fn parametric_form_lands_on_the_level_set(seed in any::<u64>(), n in 2usize..=3) {
        let (model, mut rng) = random_model(n, seed);
        let eval = ModelEval::new(&model).unwrap();
        let mut bare = model.clone();
        bare.stages.clear();
        let linear = ModelEval::new(&bare).unwrap();
        let mut patches = 0;
        for s in 0..model.num_simplices() {
            let Some(patch) = eval.patch(s) else { continue };
            patches += 1;
            let k = patch.corners.len();
            let expected_corners = if n == 2 { k == 2 } else { k == 3 || k == 4 };
            prop_assert!(expected_corners);
            for c in &patch.corners {
                let f: f64 = model.simplex(s).iter().enumerate().map(|(i, &v)| model.values[v as usize] * c.u[i]).sum();
                prop_assert!((f - model.level).abs() < 1e-12);
            }
            // A random convex combination of the corners.
            let lam = rng.open_simplex(k, 0.0);
            let mut u = [0.0; 4];
            for (c, l) in patch.corners.iter().zip(&lam) {
                for i in 0..=n {
                    u[i] += l * c.u[i];
                }
            }
            let pp = eval.param_point(s, &u);
            prop_assert!(pp.inverse.converged, "{:?}", pp.inverse);
            let f = eval.value(&pp.p[..n]).unwrap();
            prop_assert!((f - model.level).abs() < 1e-9, "F = {} at a parametric point", f);
            // Orientation: the corner order's normal (of the linear patch) points along the
            // linear function's gradient, towards F > c.
            let lin: Vec<[f64; 3]> = patch.corners.iter().map(|c| linear.point(s, &c.u)).collect();
            let a = [lin[1][0] - lin[0][0], lin[1][1] - lin[0][1], lin[1][2] - lin[0][2]];
            let normal = if n == 2 {
                [a[1], -a[0], 0.0]
            } else {
                let b = [lin[2][0] - lin[0][0], lin[2][1] - lin[0][1], lin[2][2] - lin[0][2]];
                [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
            };
            let g = linear.gradient_at(s, &[0.25; 4]).unwrap();
            prop_assert!((0..3).map(|x| normal[x] * g[x]).sum::<f64>() > 0.0);
            // Parametric Jacobian vs finite differences along u_l − u_0 at an interior u.
            let mut ui = [0.0; 4];
            ui[..=n].copy_from_slice(&rng.open_simplex(n + 1, 0.1));
            let w = eval.param_point(s, &ui).w;
            let jac = eval.param_jacobian(s, &w).unwrap();
            let h = 1e-6;
            for l in 1..=n {
                let mut up = ui;
                let mut um = ui;
                up[l] += h;
                up[0] -= h;
                um[l] -= h;
                um[0] += h;
                let (a, b) = (eval.param_point(s, &up).p, eval.param_point(s, &um).p);
                for x in 0..n {
                    let fd = (a[x] - b[x]) / (2.0 * h);
                    prop_assert!((jac[x][l - 1] - fd).abs() < 1e-5 * (1.0 + fd.abs()));
                }
            }
        }
        prop_assert!(patches > 0 || model.values.iter().all(|&v| v > 0.0) || model.values.iter().all(|&v| v < 0.0));
    }
}

#[test]
fn location_finds_the_containing_simplex_and_rejects_outside_points() {
    for n in [2usize, 3] {
        let mut rng = Rng(42 + n as u64);
        let model = common::kuhn(n, 4, &mut rng);
        let eval = ModelEval::new(&model).unwrap();
        for _ in 0..500 {
            let p: Vec<f64> = (0..n).map(|_| rng.uniform(0.0, 4.0)).collect();
            let loc = eval.locate(&p).expect("inside the grid");
            let w = eval.barycentric(loc.simplex, &p);
            assert!(w[..=n].iter().all(|&x| x >= -LOCATE_TOLERANCE));
            let back = eval.point(loc.simplex, &loc.w);
            assert!((0..n).all(|x| (back[x] - p[x]).abs() < 1e-12));
            // Brute force: the located simplex is one of those containing p.
            let containing: Vec<usize> = (0..model.num_simplices())
                .filter(|&s| {
                    eval.barycentric(s, &p)[..=n]
                        .iter()
                        .all(|&x| x >= -LOCATE_TOLERANCE)
                })
                .collect();
            assert!(containing.contains(&loc.simplex));
        }
        // Vertices are located, with F exactly f(v) (identity model).
        for v in 0..model.num_vertices() {
            let f = eval.value(model.vertex(v)).unwrap();
            assert_eq!(f, model.values[v]);
        }
        for p in [[-0.5, 1.0, 1.0], [1.0, 4.5, 1.0], [1.0, 1.0, -1e-6]] {
            if n == 2 && p[2] != 1.0 {
                continue;
            }
            assert!(eval.locate(&p[..n]).is_none(), "{p:?}");
        }
    }
}

/// A strongly graded mesh (coordinates `x ↦ 8^x`, so cell sizes differ by 8⁷) takes the R*-tree
/// path; a Kuhn grid takes the uniform grid. Both agree with brute force.
#[test]
fn both_spatial_indices_agree_with_brute_force() {
    for graded in [false, true] {
        let mut rng = Rng(9);
        let mut model = common::kuhn(3, if graded { 8 } else { 4 }, &mut rng);
        if graded {
            for c in model.vertices.iter_mut() {
                *c = 8f64.powf(*c);
            }
        }
        let eval = ModelEval::new(&model).unwrap();
        assert_eq!(eval.index_kind(), if graded { "rtree" } else { "grid" });
        // The exporter's evaluator builds its index on first use (sequentially): the same index.
        let indexed = ism_format::IndexedModel::for_evaluation(model.clone()).unwrap();
        let lazy = ModelEval::for_extraction(&indexed).unwrap();
        let hi = if graded { 8f64.powi(8) } else { 4.0 };
        let lo = if graded { 1.0 } else { 0.0 };
        for _ in 0..400 {
            let p: Vec<f64> = (0..3).map(|_| rng.uniform(lo - 0.1, hi + 0.1)).collect();
            let brute: Vec<usize> = (0..model.num_simplices())
                .filter(|&s| {
                    eval.barycentric(s, &p)[..4]
                        .iter()
                        .all(|&x| x >= -LOCATE_TOLERANCE)
                })
                .collect();
            let located = eval.locate(&p);
            match located {
                Some(l) => assert!(brute.contains(&l.simplex)),
                None => assert!(brute.is_empty(), "{p:?} missed: {brute:?}"),
            }
            assert_eq!(
                lazy.locate(&p).map(|l| l.simplex),
                located.map(|l| l.simplex)
            );
        }
    }
}

/// A non-convex (L-shaped) grid: every vertex, including those on the re-entrant boundary that
/// lie exactly on grid planes, is located.
#[test]
fn boundary_points_of_a_non_convex_complex_are_located() {
    for n in [2usize, 3] {
        let mut rng = Rng(11);
        let full = common::kuhn(n, 4, &mut rng);
        let mut model = full.clone();
        model.simplices.clear();
        for s in full.simplex_iter() {
            let centre: Vec<f64> = (0..n)
                .map(|x| {
                    s.iter().map(|&v| full.vertex(v as usize)[x]).sum::<f64>() / (n + 1) as f64
                })
                .collect();
            if !(centre[0] > 2.0 && centre[1] > 2.0) {
                model.simplices.extend_from_slice(s);
            }
        }
        let eval = ModelEval::new(&model).unwrap();
        let used: std::collections::BTreeSet<u32> = model.simplices.iter().copied().collect();
        for &v in &used {
            let p = model.vertex(v as usize);
            let loc = eval
                .locate(p)
                .unwrap_or_else(|| panic!("vertex {v} at {p:?} not located"));
            assert!(model.simplex(loc.simplex).contains(&v));
        }
        assert!(eval.locate(&[3.5, 3.5, 1.0][..n]).is_none());
    }
}

#[test]
fn batch_apis_agree_with_single_point_calls() {
    let (model, mut rng) = random_model(3, 7);
    let eval = ModelEval::new(&model).unwrap();
    let pts: Vec<f64> = (0..300).map(|_| rng.uniform(-0.2, 2.2)).collect();
    let vals = eval.values(&pts);
    let grads = eval.gradients(&pts);
    for (i, p) in pts.chunks_exact(3).enumerate() {
        assert_eq!(vals[i], eval.value(p));
        assert_eq!(grads[i], eval.gradient(p));
    }
    assert!(vals.iter().any(Option::is_none) && vals.iter().any(Option::is_some));
}

#[test]
fn malformed_records_are_reported_with_their_location() {
    let mut rng = Rng(3);
    let mut model = common::kuhn(2, 1, &mut rng);
    let mut st = common::adjusted_quadratic(&model, &mut rng);
    st.faces.edit(|r| r[1].points.push(0.5));
    model.stages.push(st);
    let err = ModelEval::new(&model).unwrap_err();
    // The structural rule (ISM-124), the record's JSON pointer and the stage.
    let ism_geom::GeomError::Structure(d) = &err else {
        panic!("expected a structural error, got {err}");
    };
    assert_eq!(d.rule, ism_format::Rule::PointCount, "{err}");
    assert_eq!(
        d.location.pointer.as_deref(),
        Some("/stages/0/faces/1/points"),
        "{err}"
    );
    assert_eq!(d.location.stage, Some(0));
    let mut degenerate = common::kuhn(2, 1, &mut rng);
    degenerate.vertices[0] = f64::NAN;
    assert!(ModelEval::new(&degenerate).is_err());
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 16, ..ProptestConfig::default() })]

    /// The indexed route (flat stage tables addressed through the topology) builds exactly the
    /// local maps of the independent route that hashes each face key of each simplex
    /// (`LocalStage::from_stage`), on every simplex of random stratified, rational, monotonic and adjusted
    /// models.
    #[test]
    fn indexed_local_maps_equal_the_hashed_lookup_route(seed in any::<u64>(), n in 2usize..=3) {
        let (model, _) = random_model(n, seed);
        let indexed = ism_format::IndexedModel::new(model.clone()).unwrap();
        let mut curved = 0;
        for s in 0..model.num_simplices() {
            for (k, stage) in model.stages.iter().enumerate() {
                let a = ism_geom::LocalStage::from_indexed(&indexed, k, s).unwrap();
                let b = ism_geom::LocalStage::from_stage(stage, k, model.simplex(s)).unwrap();
                prop_assert_eq!(a.is_identity(), b.is_identity());
                prop_assert_eq!(a.control_points(), b.control_points());
                prop_assert_eq!(a.weights(), b.weights());
                for i in 0..=n {
                    if stage.kind == ism_format::StageKind::Monotonic {
                        prop_assert_eq!(a.monotonic_coefficients(i), b.monotonic_coefficients(i));
                    }
                }
                curved += usize::from(!a.is_identity());
            }
        }
        prop_assert!(curved > 0, "the random models have curved simplices");
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 12, ..ProptestConfig::default() })]

    /// The map cache's budget changes no value: evaluators caching everything, nothing, and a
    /// budget met part way give the same bits for `F`, `∇F` and the two together at random
    /// points of every simplex; with no budget point evaluations cache nothing, and a budget is
    /// exceeded by about the one map built when it was reached (one thread here; the bound below
    /// allows for maps larger than the first one).
    #[test]
    fn map_cache_budget_changes_no_value(seed in any::<u64>(), n in 2usize..=3) {
        let (model, mut rng) = random_model(n, seed);
        let all = ModelEval::new(&model).unwrap();
        let none = ModelEval::new(&model).unwrap().with_map_cache_budget(0);
        let one_map = all.local_map_transient(0).heap_bytes();
        prop_assert!(one_map > 0);
        let part_budget = 3 * one_map;
        let part = ModelEval::new(&model).unwrap().with_map_cache_budget(part_budget);
        let bits = |g: Option<[f64; 3]>| g.map(|g| g.map(f64::to_bits));
        for s in 0..model.num_simplices() {
            let mut w = [0.0; 4];
            w[..=n].copy_from_slice(&rng.open_simplex(n + 1, 0.0));
            let f = all.value_at(s, &w);
            let g = all.gradient_at(s, &w);
            for e in [&none, &part] {
                prop_assert_eq!(e.value_at(s, &w).to_bits(), f.to_bits());
                prop_assert_eq!(bits(e.gradient_at(s, &w)), bits(g));
                let (f2, g2) = e.value_and_gradient_at(s, &w);
                prop_assert_eq!((f2.to_bits(), bits(g2)), (f.to_bits(), bits(g)));
            }
        }
        prop_assert_eq!(none.cached_map_bytes(), 0);
        prop_assert!(part.cached_map_bytes() >= part_budget.min(all.cached_map_bytes()));
        // Every map of these models is about as large as the first one.
        prop_assert!(part.cached_map_bytes() < part_budget + 4 * one_map);
        prop_assert!(all.cached_map_bytes() > part.cached_map_bytes());
        // `local_map` keeps what it builds whatever the budget (its callers hold the map).
        let held = none.local_map(0).heap_bytes();
        prop_assert_eq!(none.cached_map_bytes(), held);
    }
}
