//! Tests of the fitter: fits against analytic truth, the schedule, the topology test's boxes.

use super::optimise::*;
use super::topology::*;
use super::*;
use crate::measure::measure;
use crate::presets::Preset;

#[test]
fn circle_fits_to_tolerance_with_the_right_topology() {
    let preset = Preset::find("circle").unwrap();
    let g = preset.expression().unwrap();
    let mut options = FitOptions::new(preset.domain);
    options.resolution = 6;
    options.tolerance = 1e-4;
    let fitted = fit(&g, &options, &ism_format::Progress::none()).unwrap();
    let r = &fitted.report;
    assert!(r.tolerance_met, "{r:?}");
    assert_eq!(
        r.topology,
        Topology {
            components: preset.components,
            euler: preset.euler
        }
    );
    let model = fitted.to_model("circle");
    let errors: Vec<_> = ism_format::structure::check(&model, 100)
        .into_iter()
        .filter(|d| d.severity == ism_format::Severity::Error)
        .collect();
    assert!(errors.is_empty(), "{errors:?}");
    // Compactness: the linear isocomplex on the same grid is far worse.
    let (_, _, linear) = linear_error(&g, &fitted.complex);
    assert!(
        linear > 10.0 * r.max_distance,
        "linear {linear} vs {}",
        r.max_distance
    );
}

/// The optimizer's stop ([`LM_DONE_FRACTION`]): a block whose residuals are all within
/// `lm_done` is left where it is; with no stop, a block that moves lowers its residuals'
/// sum of squares. Residuals from the closed form: for `g = x² + y² − r²`,
/// `g/|∇g| = (ρ² − r²)/(2ρ)` at radius `ρ`.
#[test]
fn conflict_levels_keep_the_serial_order_of_every_shared_cell() {
    let mut rng: u64 = 0x2545_f491_4f6c_dd1d;
    let mut next = |m: u64| {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        rng % m
    };
    let steps: Vec<(Vec<u32>, bool)> = (0..400)
        .map(|_| {
            let k = next(5) as usize;
            let cells = (0..k).map(|_| next(60) as u32).collect();
            (cells, next(40) == 0)
        })
        .collect();
    let levels = conflict_levels(steps.iter().map(|(c, a)| (&c[..], *a)));
    let mut level_of = vec![usize::MAX; steps.len()];
    for (l, run) in levels.iter().enumerate() {
        assert!(!run.is_empty() && run.windows(2).all(|w| w[0] < w[1]));
        let mut seen = HashSet::new();
        for &i in run {
            assert_eq!(level_of[i], usize::MAX, "step {i} twice");
            level_of[i] = l;
            // Steps that share a level share no cell (a step may repeat its own).
            let own: HashSet<u32> = steps[i].0.iter().copied().collect();
            assert!(
                own.iter().all(|c| seen.insert(*c)),
                "level {l} shares a cell"
            );
        }
    }
    assert!(level_of.iter().all(|&l| l != usize::MAX));
    let mut alone = 0;
    for i in 0..steps.len() {
        for j in i + 1..steps.len() {
            if steps[i].1 || steps[j].1 || steps[i].0.iter().any(|c| steps[j].0.contains(c)) {
                assert!(level_of[i] < level_of[j], "steps {i} and {j}");
            }
        }
        if steps[i].1 {
            alone += 1;
            assert_eq!(levels[level_of[i]], [i]);
        }
    }
    assert!(
        alone >= 3 && levels.len() < steps.len() / 2,
        "{alone}, {}",
        levels.len()
    );
}

#[test]
fn fits_are_the_same_bits_for_any_number_of_threads() {
    let preset = Preset::find("torus").unwrap();
    let g = preset.expression().unwrap();
    let mut options = FitOptions::new(preset.domain);
    options.tolerance = 4e-3;
    let fit_on = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| fit(&g, &options, &ism_format::Progress::none()).unwrap())
    };
    let one = fit_on(1);
    assert!(
        one.report.tolerance_met && one.report.simplices > 3_000,
        "{} simplices, met {}",
        one.report.simplices,
        one.report.tolerance_met
    );
    let bits = |f: &Fitted| {
        let mut entries: Vec<(Vec<u32>, Vec<u64>)> = f
            .map
            .entries()
            .map(|(k, l)| (k.to_vec(), l.iter().map(|x| x.to_bits()).collect()))
            .collect();
        entries.sort();
        (f.to_model("t"), entries)
    };
    for threads in [2, 3] {
        let other = fit_on(threads);
        assert!(bits(&one) == bits(&other), "{threads} threads");
        // The same report but for the time it took.
        let mut report = other.report.clone();
        report.seconds = one.report.seconds;
        assert_eq!(one.report, report, "{threads} threads");
    }
}

#[test]
fn the_optimizer_stops_once_a_block_is_within_its_done_residual() {
    let preset = Preset::find("circle").unwrap();
    let g = preset.expression().unwrap();
    let radius: f64 = 0.28;
    let mut options = FitOptions::new(preset.domain);
    options.resolution = 6;
    options.tolerance = 1e-2;
    let mut fitter = Fitter::new(&g, &options);
    fitter.set_values_for_new_vertices();
    let crossing = fitter.crossing_cells();
    // Crossing edges placed, no point optimized yet.
    fitter.fit_region(&crossing, false);
    let residuals = |fitter: &Fitter, cells: &[u32], samples: &[Vec<Bary>]| -> Vec<f64> {
        let mut out = Vec::new();
        for (&c, us) in cells.iter().zip(samples) {
            let ids = fitter.complex.cell(c);
            let local = local_of(&fitter.map, &fitter.weights, ids);
            for u in us {
                let p = fitter.point_of(ids, &local.eval(u));
                let rho = p[0].hypot(p[1]);
                out.push((rho * rho - radius * radius) / (2.0 * rho));
            }
        }
        out
    };
    let mut faces: Vec<Vec<u32>> = crossing
        .iter()
        .flat_map(|&c| fitter.faces_of(c))
        .filter(|f| f.len() == 2 && !fitter.is_crossing_edge((f[0], f[1])))
        .collect();
    faces.sort();
    faces.dedup();
    assert!(faces.len() >= 8, "{} faces", faces.len());
    let mut moved = 0;
    for f in &faces {
        let cells = fitter.crossing_cells_with_face(f);
        let samples = fitter.cell_samples(&cells);
        let before = residuals(&fitter, &cells, &samples);
        let worst = before.iter().fold(0.0f64, |m, r| m.max(r.abs()));
        let logits = fitter.map.logits(f);
        // Just above the worst residual (the tape's rounding differs from the closed form's).
        fitter.lm_done = worst * (1.0 + 1e-9);
        assert!(!fitter.optimize(Param::Point(f), &cells, &samples), "{f:?}");
        assert_eq!(
            fitter
                .map
                .logits(f)
                .iter()
                .map(|x| x.to_bits())
                .collect::<Vec<_>>(),
            logits.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
            "{f:?}"
        );
        fitter.lm_done = 0.0;
        if fitter.optimize(Param::Point(f), &cells, &samples) {
            moved += 1;
            let after = residuals(&fitter, &cells, &samples);
            let cost = |r: &[f64]| r.iter().map(|x| x * x).sum::<f64>();
            assert!(cost(&after) < cost(&before), "{f:?}");
            assert_ne!(fitter.map.logits(f), logits, "{f:?}");
        } else {
            assert_eq!(fitter.map.logits(f), logits, "{f:?}");
        }
    }
    assert!(2 * moved >= faces.len(), "{moved} of {} moved", faces.len());
}

#[test]
fn fitter_map_agrees_with_the_kernel() {
    fitter_map_agrees_with_the_kernel_on(false);
}

#[test]
fn fitter_map_on_the_lattice_agrees_with_the_kernel() {
    // The written points are the rounded ones the fitter measured: the kernel evaluates the
    // file, the closed form the fitter's own map, and they agree as they do without rounding
    // (a map that measured the smooth points and wrote rounded ones would differ by ~1e-8).
    fitter_map_agrees_with_the_kernel_on(true);
}

fn fitter_map_agrees_with_the_kernel_on(lattice: bool) {
    // Two independent evaluations of the same parametric map: the closed-form strata here and
    // ism-geom's general Bézier stages on the written model.
    let preset = Preset::find("sphere").unwrap();
    let g = preset.expression().unwrap();
    let mut options = FitOptions::new(preset.domain);
    options.resolution = 3;
    options.tolerance = 1e-2;
    options.rational = true;
    options.lattice = lattice;
    let fitted = fit(&g, &options, &ism_format::Progress::none()).unwrap();
    // Every written point on the lattice (exact integer arithmetic on its numerators), or, off
    // it, at least one that is not (so the two runs test different files).
    let model = fitted.to_model("sphere");
    let mut off = 0;
    for stage in model
        .stages
        .iter()
        .filter(|s| s.kind == ism_format::model::StageKind::Bezier)
    {
        for r in stage.faces.iter() {
            for point in r.points.chunks(r.face.len()) {
                let n: Vec<f64> = point
                    .iter()
                    .map(|x| x * crate::strata::POINT_LATTICE)
                    .collect();
                let on = n.iter().all(|x| x.fract() == 0.0 && *x >= 1.0)
                    && n.iter().map(|&x| x as i64).sum::<i64>() == 1 << 24;
                off += usize::from(!on);
            }
        }
    }
    if lattice {
        assert_eq!(off, 0);
    } else {
        assert!(off > 0);
    }
    assert!(fitted.map.num_faces() > 0);
    assert!(fitted.weights.num_faces() > 0);
    // The whole complex: simplex `s` of this model is live cell `s`.
    let model = fitted.full_model("sphere");
    assert_eq!(
        model.stages.last().map(|s| s.kind),
        Some(ism_format::model::StageKind::Rational)
    );
    let eval = ism_geom::ModelEval::new(&model).unwrap();
    let live = fitted.complex.live_cells();
    let mut checked = 0;
    for (s, &c) in live.iter().enumerate() {
        let local = local_of(&fitted.map, &fitted.weights, fitted.complex.cell(c));
        for u in [
            [0.1, 0.2, 0.3, 0.4],
            [0.7, 0.1, 0.1, 0.1],
            [0.25, 0.25, 0.5, 0.0],
        ] {
            let w = local.eval(&u);
            let kernel = eval.param_point(s, &u);
            for k in 0..4 {
                assert!(
                    (w[k] - kernel.w[k]).abs() < 1e-9,
                    "cell {s}: {w:?} vs {:?}",
                    kernel.w
                );
            }
            checked += 1;
        }
    }
    assert!(checked > 100);
}

/// Largest `|g|/|∇g|` at the patch corners of a written model (the crossings of the edges),
/// evaluated by the kernel.
fn corner_error(g: &dyn ImplicitFunction, model: &Model) -> (f64, usize, usize) {
    let eval = ism_geom::ModelEval::new(model).unwrap();
    let mut worst = 0.0f64;
    let mut count = 0;
    let mut exact = 0;
    for s in 0..model.num_simplices() {
        if let Some(patch) = eval.patch(s) {
            for c in &patch.corners {
                let p = eval.param_point(s, &c.u).p;
                let d = g.distance_estimate(&p[..model.dim()]);
                worst = worst.max(d);
                count += 1;
                exact += usize::from(d < 1e-12);
            }
        }
    }
    (worst, count, exact)
}

#[test]
fn rational_weights_lower_the_error_and_keep_the_crossings_exact() {
    // On a fixed complex (tolerance never binding), the weights are extra freedom: the fit
    // with them must be clearly better. Measured: circle 6.7e-4 → 4.7e-4, Taubin 1.7e-2 →
    // 1.2e-3. (The circle's optimum moves with the last bits of the vertex values: with
    // `x^2 + y^2 - c` summed as `x^2 + (y^2 - c)`, as before expressions were read left to
    // right, it was 3.3e-4.)
    for (name, resolution, gain) in [("circle", 6, 1.3), ("taubin", 10, 4.0)] {
        let preset = Preset::find(name).unwrap();
        let g = preset.expression().unwrap();
        let mut options = FitOptions::new(preset.domain);
        options.resolution = resolution;
        options.tolerance = 10.0;
        // A tolerance of 10 would let pruning drop every optimized point, and stop the
        // optimizer before its first step.
        options.prune = false;
        options.lm_done_fraction = 0.0;
        let plain = fit(&g, &options, &ism_format::Progress::none()).unwrap();
        options.rational = true;
        let weighted = fit(&g, &options, &ism_format::Progress::none()).unwrap();
        assert_eq!(plain.report.simplices, weighted.report.simplices);
        assert!(weighted.weights.num_faces() > 0);
        // The fit → target direction: the weights act on the fit's own error, and with a
        // tolerance of 10 the target → fit cover is too coarse to compare them.
        let (with, without) = (
            weighted.report.measure.shape_to_target,
            plain.report.measure.shape_to_target,
        );
        assert!(
            with * gain < without,
            "{name}: {with} with weights vs {without} without"
        );
        // Every weight change re-solves the edge points, so the shape still crosses each
        // edge at the root of g (bisection to 2⁻⁶⁰ of the edge) wherever the edge point can
        // reach it; where it cannot (α clamped: a root far from the linear crossing; 6 of
        // 414 Taubin corners on the complex of the bounding-box Plantinga–Vegter test, 8 of
        // 238 on the coarser one of the simplex-restricted test, PV_SPLIT) the weights can
        // only bring it closer.
        let model = weighted.to_model(name);
        let (worst, corners, exact) = corner_error(&g, &model);
        let (plain_worst, _, plain_exact) = corner_error(&g, &plain.to_model(name));
        assert!(corners > 20);
        assert!(
            exact >= plain_exact && exact * 20 >= corners * 19,
            "{name}: {exact}/{corners} exact"
        );
        assert!(
            worst <= plain_worst.max(1e-12),
            "{name}: {worst} vs {plain_worst}"
        );
        if name == "circle" {
            assert_eq!(exact, corners, "{name}: worst crossing off by {worst}");
        }
        let errors: Vec<_> = ism_format::structure::check(&model, 100)
            .into_iter()
            .filter(|d| d.severity == ism_format::Severity::Error)
            .collect();
        assert!(errors.is_empty(), "{errors:?}");
    }
}

#[test]
fn a_heart_with_cusps_and_flat_points_fits_and_names_them() {
    // (x² + y² − 1)³ − x²y³: singular at (0, ±1) and (±1, 0) (∇g = 0 there). Before issue 17
    // the topology phase bisected these until a simplex degenerated (exit 2 after 13–56 s).
    let g = crate::Expression::parse("(x^2+y^2-1)^3-x^2*y^3", 2).unwrap();
    let mut options = FitOptions::new(&[-1.5, 1.5, -1.5, 1.5]);
    options.tolerance = 0.03;
    let fitted = fit(&g, &options, &ism_format::Progress::none()).unwrap();
    let r = &fitted.report;
    assert!(r.tolerance_met, "{r:?}");
    assert!(!r.topology_certified);
    assert_eq!(r.pv_unfinished, 0);
    assert!(r.simplices < 5000, "{}", r.simplices);
    for singular in [[0.0, 1.0], [0.0, -1.0], [1.0, 0.0], [-1.0, 0.0]] {
        let hit = r.uncertain.iter().find(|u| {
            let d = (u.centre[0] - singular[0]).hypot(u.centre[1] - singular[1]);
            d <= u.radius
        });
        let hit = hit.unwrap_or_else(|| panic!("{singular:?} not named: {:?}", r.uncertain));
        assert!(hit.gradient_may_vanish);
        assert!(hit.shape_to_target <= options.tolerance);
        assert!(hit.target_to_shape <= options.tolerance);
    }
    assert!(r.uncertain.len() <= 6, "{:?}", r.uncertain);
}

#[test]
fn the_target_to_fit_direction_sees_what_the_fit_misses() {
    // A fit of the circle r = 0.5 measured against the circle plus a small circle of radius
    // 0.1 around (0.7, 0): every point of the fit is on the target (fit → target is the fit's
    // own error), but the target's point (0.8, 0) is 0.3 from the fit: exactly 0.3 up to
    // the fit's error.
    let circle = crate::Expression::parse("x^2 + y^2 - 0.25", 2).unwrap();
    let domain = [-1.0, 1.0, -1.0, 1.0];
    let mut options = FitOptions::new(&domain);
    options.tolerance = 1e-3;
    let fitted = fit(&circle, &options, &ism_format::Progress::none()).unwrap();
    let own = fitted.report.max_distance;
    assert!(own <= 1e-3);
    let both = crate::Expression::parse("(x^2 + y^2 - 0.25)*((x-0.7)^2 + y^2 - 0.01)", 2).unwrap();
    let c = ism_format::IndexedModel::for_evaluation(fitted.to_model("c")).unwrap();
    let m = measure(&both, &c, &domain, 1e-3, &[]).unwrap();
    // Fit → target: every fit point is within `own` of the circle, so of the union; the
    // measure's figure is a certified bound through the product `g` (a bracket along its
    // gradient line, looser than through the circle's own `g`), so it is checked against
    // the tolerance, and against the exact distance to the two circles at its worst point,
    // which it must not undercut.
    assert!(m.shape_to_target <= options.tolerance, "{m:?}");
    let p = &m.shape_to_target_at;
    let exact = (p[0].hypot(p[1]) - 0.5)
        .abs()
        .min(((p[0] - 0.7).hypot(p[1]) - 0.1).abs());
    assert!(exact <= own + 1e-12, "{exact} {own}");
    assert!(m.shape_to_target >= exact - 1e-12, "{m:?}");
    assert!(
        (m.target_to_shape - 0.3).abs() <= own + 1e-6,
        "{}",
        m.target_to_shape
    );
    assert!(m.target_to_shape_bound >= m.target_to_shape);
    assert!(m.target_to_shape_bound <= 0.3 + own + 0.5e-3, "{m:?}");
}

/// Points of a 2D model's shape, `per_patch` + 1 per patch, drawn by the kernel, and the
/// chords between neighbours.
fn shape_polyline(model: &Model, per_patch: usize) -> Vec<([f64; 2], [f64; 2])> {
    let eval = ism_geom::ModelEval::new(model).unwrap();
    let mut chords = Vec::new();
    for s in 0..model.num_simplices() {
        if let Some(patch) = eval.patch(s) {
            let corners: Vec<Bary> = patch.corners.iter().map(|c| c.u).collect();
            let ps: Vec<[f64; 2]> = patch_samples(&corners, per_patch)
                .iter()
                .map(|u| {
                    let p = eval.param_point(s, u).p;
                    [p[0], p[1]]
                })
                .collect();
            chords.extend(ps.windows(2).map(|w| (w[0], w[1])));
        }
    }
    chords
}

fn to_chords(chords: &[([f64; 2], [f64; 2])], q: [f64; 2]) -> f64 {
    chords
        .iter()
        .map(|(p, r)| {
            let (dx, dy) = (r[0] - p[0], r[1] - p[1]);
            let len2 = (dx * dx + dy * dy).max(f64::MIN_POSITIVE);
            let t = (((q[0] - p[0]) * dx + (q[1] - p[1]) * dy) / len2).clamp(0.0, 1.0);
            (p[0] + t * dx - q[0]).hypot(p[1] + t * dy - q[1])
        })
        .fold(f64::INFINITY, f64::min)
}

#[test]
fn the_accuracy_loop_refines_where_the_fit_misses_part_of_the_target() {
    // Two circles: r = 0.5 about the origin and r = 0.1 about (0.7, 0.03). On the 4×4 Kuhn
    // grid of [−1, 1]² without the topology phase no vertex lies inside the small circle
    // (it crosses the edge (0.5, 0)–(1, 0) twice), so no patch is there and the one-sided
    // error at the fit's samples is fine; only the target → fit direction sees the miss.
    // Ground truth from the circles themselves: exact distances of the fit's points to them,
    // and of dense points of both circles to the fit's chords.
    let g =
        crate::Expression::parse("(x^2 + y^2 - 0.25)*((x-0.7)^2 + (y-0.03)^2 - 0.01)", 2).unwrap();
    let mut options = FitOptions::new(&[-1.0, 1.0, -1.0, 1.0]);
    options.resolution = 4;
    options.topology = false;
    options.tolerance = 2e-3;
    let fitted = fit(&g, &options, &ism_format::Progress::none()).unwrap();
    let r = &fitted.report;
    assert!(r.tolerance_met, "{:?}", r.measure);
    assert_eq!(r.topology.components, 2, "{r:?}");
    let model = fitted.to_model("two");
    let chords = shape_polyline(&model, 64);
    let to_circles = |p: [f64; 2]| -> f64 {
        let big = (p[0].hypot(p[1]) - 0.5).abs();
        let small = ((p[0] - 0.7).hypot(p[1] - 0.03) - 0.1).abs();
        big.min(small)
    };
    let fit_to_target = chords.iter().map(|c| to_circles(c.0)).fold(0.0, f64::max);
    assert!(fit_to_target <= options.tolerance, "{fit_to_target}");
    let mut target_to_fit = 0.0f64;
    for i in 0..2000 {
        let t = i as f64 * std::f64::consts::TAU / 2000.0;
        for (c, rad) in [([0.0, 0.0], 0.5), ([0.7, 0.03], 0.1)] {
            let q = [c[0] + rad * t.cos(), c[1] + rad * t.sin()];
            target_to_fit = target_to_fit.max(to_chords(&chords, q));
        }
    }
    assert!(target_to_fit <= options.tolerance, "{target_to_fit}");
    // The measure agrees with the truth (an upper bound at its points, up to its cover).
    assert!(r.measure.target_to_shape_bound >= target_to_fit);
}

#[test]
fn the_box_test_of_the_plantinga_vegter_split_never_drops_a_box_that_meets_the_simplex() {
    // Points of a simplex drawn as convex combinations of its corners (ground truth: they
    // are in it by construction); every box around one must be kept, in 2D and 3D, for
    // thin and skewed simplices. And boxes far beyond a facet are dropped.
    let mut rng = crate::test_rng::Lcg::new(7);
    let mut rnd = move || rng.unit();
    for n in [2usize, 3] {
        for _ in 0..200 {
            let pts: Vec<f64> = (0..(n + 1) * n).map(|_| rnd() * 2.0 - 1.0).collect();
            let ids: Vec<u32> = (0..=n as u32).collect();
            let complex = Complex::from_parts(n, pts.clone(), &ids);
            let Some(meets) = simplex_test(&complex, 0) else {
                continue;
            };
            for _ in 0..50 {
                let w: Vec<f64> = (0..=n).map(|_| rnd().powi(3)).collect();
                let sum: f64 = w.iter().sum();
                let p: Vec<f64> = (0..n)
                    .map(|k| (0..=n).map(|i| w[i] / sum * pts[i * n + k]).sum())
                    .collect();
                let r = 1e-3 * rnd();
                let l: Vec<f64> = p.iter().map(|x| x - r).collect();
                let h: Vec<f64> = p.iter().map(|x| x + r).collect();
                assert!(meets(&l, &h), "{pts:?} {p:?}");
            }
            // A small box around a point beyond the facet opposite corner 0 (λ₀ = −1 there:
            // the facet's centroid moved away from corner 0 by their difference) is dropped.
            let p: Vec<f64> = (0..n)
                .map(|k| {
                    let fc = (1..=n).map(|i| pts[i * n + k]).sum::<f64>() / n as f64;
                    2.0 * fc - pts[k]
                })
                .collect();
            let l: Vec<f64> = p.iter().map(|x| x - 1e-9).collect();
            let h: Vec<f64> = p.iter().map(|x| x + 1e-9).collect();
            assert!(!meets(&l, &h), "{pts:?} {p:?}");
        }
    }
}

#[test]
fn the_reported_bounds_hold_against_exact_closest_points_on_a_circle() {
    // A fit of the ellipse x²/0.36 + y²/0.16 = 1 measured against another curve, the circle
    // |p − c| = 0.45 with c = (0.05, 0.02), written as ((x−cx)² + (y−cy)² − r²)³ so that ∇g
    // vanishes on it (a first-order |g|/|∇g| is 6× too small there). Ground truth from the
    // circle's exact closest points: dist(p, Z) = ||p − c| − r| at dense points of the fit
    // drawn by the kernel, and dense exact points of the circle to the fit's dense chords
    // (256 per patch). Every reported bound must hold; every estimate must be within its
    // stated error.
    let ellipse = crate::Expression::parse("x^2/0.36 + y^2/0.16 - 1", 2).unwrap();
    let domain = [-1.0, 1.0, -1.0, 1.0];
    let mut options = FitOptions::new(&domain);
    options.tolerance = 1e-2;
    let model = fit(&ellipse, &options, &ism_format::Progress::none())
        .unwrap()
        .to_model("e");
    let (c, rad) = ([0.05f64, 0.02f64], 0.45f64);
    let circle = crate::Expression::parse("((x-0.05)^2 + (y-0.02)^2 - 0.2025)^3", 2).unwrap();
    let tolerance = 1e-2;
    let indexed = ism_format::IndexedModel::for_evaluation(model.clone()).unwrap();
    let m = measure(&circle, &indexed, &domain, tolerance, &[]).unwrap();
    let chords = shape_polyline(&model, 256);
    let to_circle = |p: [f64; 2]| ((p[0] - c[0]).hypot(p[1] - c[1]) - rad).abs();
    let fit_to_target = chords.iter().map(|ch| to_circle(ch.0)).fold(0.0, f64::max);
    let target_to_fit = (0..4000)
        .map(|i| {
            let t = i as f64 * std::f64::consts::TAU / 4000.0;
            to_chords(&chords, [c[0] + rad * t.cos(), c[1] + rad * t.sin()])
        })
        .fold(0.0, f64::max);
    // The truth is far above the fit's own error (≤ 1e-2): the circle is another curve.
    assert!(
        fit_to_target > 0.1 && target_to_fit > 0.1,
        "{fit_to_target} {target_to_fit}"
    );
    let radius = match m.cover {
        crate::measure::TargetCover::Boxes { largest, .. } => largest,
        _ => panic!("{:?}", m.cover),
    };
    // Bounds over the whole of S and Z.
    assert!(
        m.shape_to_target_bound() >= fit_to_target,
        "{m:?} {fit_to_target}"
    );
    assert!(
        m.target_to_shape_bound >= target_to_fit,
        "{m:?} {target_to_fit}"
    );
    assert!(m.max_bound() >= fit_to_target.max(target_to_fit));
    // Estimates: never above the truth by more than rounding (each is a distance to a point
    // actually found), never below it by more than the stated spacing or cover radius.
    assert!(m.shape_to_target <= fit_to_target * 1.001 + 1e-9, "{m:?}");
    assert!(m.shape_to_target >= fit_to_target - m.shape_cover, "{m:?}");
    assert!(m.target_to_shape <= target_to_fit * 1.001 + 1e-9, "{m:?}");
    assert!(m.target_to_shape >= target_to_fit - radius, "{m:?}");
    // And the bounds are not vacuous.
    assert!(m.max_bound() <= fit_to_target.max(target_to_fit) + radius + m.shape_cover);
}

#[test]
fn the_two_sided_distance_of_an_ellipse_fit_matches_the_analytic_one() {
    // x²/a² + y²/b² = 1 with a = 0.9, b = 0.3. Ground truth independent of the measure: the
    // exact distance from a point to the ellipse (closest parameter by a dense scan refined
    // by ternary search), at points of the fit drawn by the kernel; and the distance from
    // dense points of the ellipse to a dense polyline of the fit (an upper bound).
    let (a, b) = (0.9f64, 0.3f64);
    let g = crate::Expression::parse("x^2/0.81 + y^2/0.09 - 1", 2).unwrap();
    let domain = [-1.0, 1.0, -1.0, 1.0];
    let mut options = FitOptions::new(&domain);
    options.tolerance = 2e-3;
    let fitted = fit(&g, &options, &ism_format::Progress::none()).unwrap();
    let r = &fitted.report;
    assert!(r.tolerance_met, "{r:?}");
    let to_ellipse = |p: [f64; 2]| -> f64 {
        let d = |t: f64| (a * t.cos() - p[0]).hypot(b * t.sin() - p[1]);
        let n = 4000;
        let k = (0..n)
            .map(|i| i as f64 * std::f64::consts::TAU / n as f64)
            .min_by(|x, y| d(*x).total_cmp(&d(*y)))
            .unwrap();
        let (mut lo, mut hi) = (k - 2e-3, k + 2e-3);
        for _ in 0..80 {
            let (m1, m2) = (lo + (hi - lo) / 3.0, hi - (hi - lo) / 3.0);
            if d(m1) < d(m2) {
                hi = m2;
            } else {
                lo = m1;
            }
        }
        d(0.5 * (lo + hi))
    };
    let model = fitted.to_model("e");
    let eval = ism_geom::ModelEval::new(&model).unwrap();
    let mut fit_points = Vec::new();
    let mut chords = Vec::new();
    for s in 0..model.num_simplices() {
        if let Some(patch) = eval.patch(s) {
            let corners: Vec<Bary> = patch.corners.iter().map(|c| c.u).collect();
            let ps: Vec<[f64; 2]> = patch_samples(&corners, 200)
                .iter()
                .map(|u| {
                    let p = eval.param_point(s, u).p;
                    [p[0], p[1]]
                })
                .collect();
            chords.extend(ps.windows(2).map(|w| (w[0], w[1])));
            fit_points.extend(ps);
        }
    }
    let true_fit_to_target = fit_points
        .iter()
        .step_by(7)
        .map(|p| to_ellipse(*p))
        .fold(0.0, f64::max);
    let m = &r.measure;
    // A bound at its samples: never below the truth there by more than the truth can vary
    // between samples, and close to it.
    assert!(
        m.shape_to_target >= 0.9 * true_fit_to_target,
        "{} vs {true_fit_to_target}",
        m.shape_to_target
    );
    assert!(m.shape_to_target <= 1.05 * true_fit_to_target + 1e-6);
    // Distance to the fit's chords between samples 1/200 of a patch apart (they stray from
    // the curve by ~κh²/8, far below the figures compared).
    let to_fit = |q: [f64; 2]| -> f64 {
        chords
            .iter()
            .map(|(p, r)| {
                let (dx, dy) = (r[0] - p[0], r[1] - p[1]);
                let len2 = (dx * dx + dy * dy).max(f64::MIN_POSITIVE);
                let t = (((q[0] - p[0]) * dx + (q[1] - p[1]) * dy) / len2).clamp(0.0, 1.0);
                (p[0] + t * dx - q[0]).hypot(p[1] + t * dy - q[1])
            })
            .fold(f64::INFINITY, f64::min)
    };
    let true_target_to_fit = (0..2000)
        .map(|i| {
            let t = i as f64 * std::f64::consts::TAU / 2000.0;
            to_fit([a * t.cos(), b * t.sin()])
        })
        .fold(0.0, f64::max);
    let radius = match m.cover {
        crate::measure::TargetCover::Boxes { largest, .. } => largest,
        _ => panic!("{:?}", m.cover),
    };
    assert!(
        m.target_to_shape >= true_target_to_fit - radius
            && m.target_to_shape <= 1.02 * true_target_to_fit + 1e-6,
        "{} vs {true_target_to_fit} (radius {radius})",
        m.target_to_shape
    );
    assert!(m.target_to_shape_bound >= true_target_to_fit);
}

/// Pruning drops records and the written shape still meets the tolerance both ways — checked
/// against the sphere's closed form with the sampler's points (fit → sphere) and sign changes
/// of the kernel's `F` along radii (sphere → fit), not with the fitter's measure.
#[test]
fn pruned_records_keep_the_sphere_within_tolerance() {
    use rand::SeedableRng;
    let preset = Preset::find("sphere").unwrap();
    let g = preset.expression().unwrap();
    let mut options = FitOptions::new(preset.domain);
    options.resolution = 4;
    options.tolerance = 1e-2;
    let records = |m: &Model| m.stages.iter().map(|s| s.faces.len()).sum::<usize>();
    options.prune = false;
    let full = fit(&g, &options, &ism_format::Progress::none()).unwrap();
    options.prune = true;
    let pruned = fit(&g, &options, &ism_format::Progress::none()).unwrap();
    assert!(full.report.tolerance_met && pruned.report.tolerance_met);
    let (a, b) = (full.to_model("a"), pruned.to_model("b"));
    assert!(
        records(&b) < records(&a),
        "{} vs {}",
        records(&b),
        records(&a)
    );
    let tol = options.tolerance;
    let eval = ism_geom::ModelEval::new(&b).unwrap();
    let table = ism_sample::SurfaceTable::new(&eval, ism_sample::Weighting::CurvedArea).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let mut worst = 0.0f64;
    for _ in 0..4000 {
        let q = table.draw(&eval, &mut rng).unwrap().p;
        worst = worst.max((q[0].hypot(q[1]).hypot(q[2]) - 0.6).abs());
    }
    assert!(worst <= tol, "fit -> sphere {worst}");
    // Every radius crosses the fit within `tol` of the sphere: F changes sign there.
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    for i in 0..2000 {
        let z = 1.0 - 2.0 * (i as f64 + 0.5) / 2000.0;
        let r = (1.0 - z * z).sqrt();
        let d = [
            r * (golden * i as f64).cos(),
            r * (golden * i as f64).sin(),
            z,
        ];
        // Outside the written shell complex is outside the solid (crate::shell).
        let at = |t: f64| eval.value(&[d[0] * t, d[1] * t, d[2] * t]);
        let inside = at(0.6 - tol).is_some_and(|v| v < 0.0);
        let outside = at(0.6 + tol).is_none_or(|v| v > 0.0);
        assert!(inside && outside, "radius {d:?}");
    }
}

#[test]
fn bad_options_are_errors() {
    let g = crate::Expression::parse("x^2 + y^2 - 1", 2).unwrap();
    let mut o = FitOptions::new(&[0.0, 1.0, 0.0, 1.0]);
    o.domain = vec![0.0, 1.0];
    assert!(matches!(
        fit(&g, &o, &ism_format::Progress::none()),
        Err(FitError::Options(_))
    ));
    let mut o = FitOptions::new(&[0.0, 1.0, 1.0, 0.0]);
    assert!(fit(&g, &o, &ism_format::Progress::none()).is_err());
    o.domain = vec![0.0, 1.0, 0.0, 1.0];
    o.tolerance = -1.0;
    assert!(fit(&g, &o, &ism_format::Progress::none()).is_err());
    o.tolerance = 1e-3;
    for bad in [-0.5, f64::NAN, f64::INFINITY] {
        o.lm_done_fraction = bad;
        assert!(matches!(
            fit(&g, &o, &ism_format::Progress::none()),
            Err(FitError::Options(_))
        ));
    }
}

/// A closed prism along z (length 1.2) over the triangle `(−0.7, −0.2)`, `(0.7, −0.2)`,
/// `(0.7, 0.175)`: a 15° edge along its left side, where the two faces' outward normals are 165°
/// apart; triangles oriented outward from the centroid.
fn sharp_prism() -> crate::mesh::TriangleMesh {
    let section = [[-0.7, -0.2], [0.7, -0.2], [0.7, 0.175]];
    let mut positions = Vec::new();
    for z in [-0.6, 0.6] {
        positions.extend(section.iter().map(|p| [p[0], p[1], z]));
    }
    let mut triangles: Vec<[u32; 3]> = [[0, 1, 4, 3], [1, 2, 5, 4], [2, 0, 3, 5]]
        .iter()
        .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
        .collect();
    triangles.extend([[0, 2, 1], [3, 4, 5]]);
    let centre = [0.7 / 3.0, -0.075, 0.0];
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    for t in &mut triangles {
        let [a, b, c] = t.map(|i| positions[i as usize]);
        let (u, v, w) = (sub(b, a), sub(c, a), sub(a, centre));
        let n = [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ];
        if n[0] * w[0] + n[1] * w[1] + n[2] * w[2] < 0.0 {
            t.swap(1, 2);
        }
    }
    crate::mesh::TriangleMesh {
        positions,
        triangles,
    }
}

/// A closed torus mesh (radii 1 and 0.4, 32 × 12 quads split in two): smooth, with saddles.
fn torus_mesh() -> crate::mesh::TriangleMesh {
    crate::mesh::TriangleMesh::torus(32, 12, 1.0, 0.4)
}

/// The Plantinga–Vegter test with its shortcuts for a mesh (witnesses, the generators'
/// superset, the generators' early exit, the hull skipped where a witness shows it fails) gives
/// the answer of the test without them ([`Fitter::pv_passes_reference`], session 22's code) on
/// every cell of complexes (6³ grid) refined three times around the surface of a prism with a 15° edge
/// (normals 165° apart) and of a smooth torus — and each shortcut decides some cells, so the
/// comparison covers them.
#[test]
fn the_plantinga_vegter_shortcuts_give_the_reference_answer_on_every_cell() {
    let (mut witnessed, mut hull_known, mut by_superset) = (0, 0, 0);
    let (mut passed, mut failed) = (0, 0);
    for (name, mesh, domain) in [
        ("prism", sharp_prism(), [-0.9, 0.9, -0.5, 0.5, -0.8, 0.8]),
        ("torus", torus_mesh(), [-1.6, 1.6, -1.6, 1.6, -0.6, 0.6]),
    ] {
        let g = crate::mesh::MeshDistance::new(mesh).unwrap();
        let mut options = FitOptions::new(&domain);
        options.resolution = 6;
        let mut fitter = Fitter::new(&g, &options);
        fitter.set_values_for_new_vertices();
        for _ in 0..3 {
            for c in fitter.crossing_cells() {
                if fitter.complex.is_alive(c) {
                    fitter.refine(c);
                }
            }
        }
        let cells = fitter.complex.live_cells();
        assert!(cells.len() > 1000, "{name}: {} cells", cells.len());
        for &c in &cells {
            let expected = fitter.pv_passes_reference(c);
            assert_eq!(fitter.pv_passes(c), expected, "{name}, cell {c}");
            let (lo, hi) = fitter.complex.bounding_box(c);
            match fitter.pv_witnessed(c, &lo, &hi) {
                Witnessed::Fails => witnessed += 1,
                Witnessed::HullFails => hull_known += 1,
                Witnessed::Undecided => {}
            }
            if let Some(inside) = simplex_test(&fitter.complex, c) {
                by_superset += usize::from(fitter.superset_agrees(&lo, &hi, &inside));
            }
            passed += usize::from(expected);
            failed += usize::from(!expected);
        }
    }
    assert!(
        witnessed > 200 && hull_known > 200 && by_superset > 200,
        "{witnessed} failed by witnesses, {hull_known} hull known, {by_superset} by the superset"
    );
    assert!(
        passed > 1000 && failed > 1000,
        "{passed} passed, {failed} failed"
    );
}

/// Exact distance from `p` to the triangle `t`: the crate's oracle (`measure::tests`, Ericson's
/// closest point by the Voronoi regions of the vertices, edges and face).
fn point_triangle_distance(p: [f64; 3], t: [[f64; 3]; 3]) -> f64 {
    crate::measure::tests::triangle_distance(&p, &t[0], &t[1], &t[2])
}

/// Issue 17, session 25: a mesh whose every edge is a crease (the icosahedron: faces 41.8° apart,
/// vertices where five meet) is fitted as `ism fit --mesh` does (its plan), and the two-sided
/// distance is checked against exact point–triangle distances, not the fitter's measure: the
/// fit's export at 1 % of the tolerance (within that of the fit) against the icosahedron's
/// triangles, both ways — lattice points of every face (its vertices and edges, where a fit that
/// rounds the creases is farthest) to the export's triangles, the export's vertices to the faces.
/// The fit must meet the tolerance by both the report and the truth, and its certified
/// target → fit bound must not undercut the truth. The rounds: the one-sided goal lowered where
/// the creases missed settles them in one round (the code before took two at this tolerance, 3,165
/// simplices against 2,886; at 2e-2 four rounds against two).
#[test]
fn a_fit_of_a_mesh_with_creases_meets_its_tolerance_by_exact_distances() {
    let mesh = crate::mesh::TriangleMesh::icosphere(0, 1.0, [0.0; 3]);
    let faces: Vec<[[f64; 3]; 3]> = mesh
        .triangles
        .iter()
        .map(|t| t.map(|v| mesh.positions[v as usize]))
        .collect();
    let g = crate::mesh::MeshDistance::new(mesh).unwrap();
    let plan = g.plan(None, 0.05, true).unwrap();
    let mut options = FitOptions::new(&plan.domain);
    options.tolerance = 3e-2;
    plan.apply(&mut options);
    let fitted = fit(&g, &options, &ism_format::Progress::none()).unwrap();
    let r = &fitted.report;
    let t = options.tolerance;
    assert!(r.tolerance_met, "{:?}", r.measure);
    assert!(r.two_sided_rounds <= 1, "{} rounds", r.two_sided_rounds);
    // The export: every point of it within `e` of the fit, and of the fit within `e` of it.
    let e = 0.01 * t;
    let model = fitted.to_model("ico");
    let eval = ism_geom::ModelEval::new(&model).unwrap();
    let extract = ism_export::extract::ExtractOptions {
        tolerance: e,
        ..Default::default()
    };
    let (export, _) = ism_export::extract::extract(&eval, &extract).unwrap();
    let triangles: Vec<[[f64; 3]; 3]> = export
        .cells
        .chunks_exact(3)
        .map(|c| [0, 1, 2].map(|k| export.positions[c[k] as usize]))
        .collect();
    assert!(triangles.len() > 1000, "{} triangles", triangles.len());
    // The largest distance from `points` to the nearest of `tris`, exactly (brute force).
    let farthest = |points: &[[f64; 3]], tris: &[[[f64; 3]; 3]]| {
        points
            .par_iter()
            .map(|&p| {
                tris.iter()
                    .map(|&f| point_triangle_distance(p, f))
                    .fold(f64::INFINITY, f64::min)
            })
            .reduce(|| 0.0, f64::max)
    };
    // Fit → target: every export vertex to the icosahedron.
    let fit_to_target = farthest(&export.positions, &faces);
    assert!(
        fit_to_target <= t + e,
        "fit → target {fit_to_target} > {t} + {e}"
    );
    // Target → fit: a level-12 lattice on every face (its corners and edges included).
    let level = 12;
    let points: Vec<[f64; 3]> = faces
        .iter()
        .flat_map(|&f| crate::measure::tests::triangle_lattice(f, level))
        .collect();
    let target_to_fit = farthest(&points, &triangles);
    assert!(
        target_to_fit <= t + e,
        "target → fit {target_to_fit} > {t} + {e}"
    );
    // The certificate is an upper bound of the truth (up to the export's own error).
    assert!(
        r.measure.target_to_shape_bound >= target_to_fit - e,
        "certified {} below the truth {target_to_fit}",
        r.measure.target_to_shape_bound
    );
    // Ground-truth check of the distance function itself: a point above a face's centre.
    let f = faces[0];
    let c = [0, 1, 2].map(|k| (f[0][k] + f[1][k] + f[2][k]) / 3.0);
    assert!(point_triangle_distance(c, f) < 1e-15);
    assert!((point_triangle_distance(f[0].map(|x| 2.0 * x), f) - 1.0).abs() < 1e-12);
}

#[test]
fn the_refinement_of_a_fit_rebuilds_its_written_complex_bit_for_bit() {
    // The structured encoding's complexForm 1 (spec §7.4.3) stores a fit's complex as its Kuhn
    // grid and splits. Its construction (ism_format::refine, written from the spec) must give
    // the written model's vertices and simplices exactly — the fitter's own complex is a second,
    // independent implementation of the same rule.
    for (name, tolerance) in [("circle", 2e-3), ("sphere", 1e-2), ("torus", 2e-2)] {
        let preset = Preset::find(name).unwrap();
        let g = preset.expression().unwrap();
        let mut options = FitOptions::new(preset.domain);
        options.resolution = 4;
        options.tolerance = tolerance;
        let fitted = fit(&g, &options, &ism_format::Progress::none()).unwrap();
        let model = fitted.to_model(name);
        let refinement = fitted.refinement().expect("a fit refines a Kuhn grid");
        assert!(
            !refinement.splits.is_empty(),
            "{name}: the fit split no edge"
        );
        assert!(
            refinement.kept.iter().any(|&k| !k),
            "{name}: the shell dropped nothing"
        );
        let (vertices, simplices) = refinement.model_arrays().unwrap();
        assert_eq!(simplices, model.simplices, "{name}");
        assert_eq!(
            vertices.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
            model
                .vertices
                .iter()
                .map(|x| x.to_bits())
                .collect::<Vec<_>>(),
            "{name}"
        );
        assert!(refinement.describes(&model.vertices, &model.simplices));
    }
}

/// Targets through vertices of the grid (a sphere and a circle of radius ½ on a grid of step ½;
/// `g` is exactly 0 at their axis points): the crossings of every edge at such a vertex would meet
/// there, and the export had triangles (segments) of no size. With [`VERTEX_CLEARANCE`] the
/// round trip — encoding, export without degenerate cells, sampling — passes, and the shape
/// keeps its clearance: `F` has the vertex's sign at the vertex and changes sign within the
/// tolerance of it along the axis (the sphere's closed form, not the fitter's measure).
#[test]
fn targets_through_grid_vertices_export_without_degenerate_cells() {
    for (text, n) in [("x^2 + y^2 + z^2 - 0.25", 3), ("x^2 + y^2 - 0.25", 2)] {
        let g = crate::Expression::parse(text, n).unwrap();
        let domain: Vec<f64> = [-1.0, 1.0].repeat(n);
        let mut options = FitOptions::new(&domain);
        options.resolution = 4;
        options.tolerance = 1e-2;
        let fitted = fit(&g, &options, &ism_format::Progress::none()).unwrap();
        assert!(fitted.report.tolerance_met, "{text}: {:?}", fitted.report);
        let model = fitted.to_model("through");
        let trip = crate::roundtrip::round_trip(&model, fitted.report.topology, options.tolerance);
        assert!(trip.is_ok(), "{text}: {:?}", trip.err());
        let eval = ism_geom::ModelEval::new(&model).unwrap();
        let clearance = vertex_clearance(&options);
        for axis in 0..n {
            for sign in [-1.0, 1.0] {
                let at = |r: f64| {
                    let mut p = vec![0.0; n];
                    p[axis] = sign * r;
                    eval.value(&p).unwrap()
                };
                // The vertex on the target counts as outside; the shape passes inside it.
                assert!(at(0.5) > 0.0, "{text}: axis {axis} {sign}");
                assert!(
                    at(0.5 - 0.5 * clearance) > 0.0,
                    "{text}: axis {axis} {sign}"
                );
                assert!(
                    at(0.5 - options.tolerance) < 0.0,
                    "{text}: axis {axis} {sign}"
                );
            }
        }
    }
}

/// [`vertex_value`] keeps `clearance` from 0 on the right side: checked against `g/|∇g|` written out
/// for the sphere `x² + y² + z² = ¼` (`(ρ² − ¼)/(2ρ)` at radius `ρ`).
#[test]
fn vertex_values_keep_their_sign_and_the_clearance() {
    let g = crate::Expression::parse("x^2 + y^2 + z^2 - 0.25", 3).unwrap();
    let exact = |rho: f64| (rho * rho - 0.25) / (2.0 * rho);
    for (rho, clearance) in [
        (0.7, 1e-5),
        (0.3, 1e-5),
        (0.5 + 1e-3, 1e-5),
        (0.5 - 1e-3, 1e-5),
    ] {
        let v = vertex_value(&g, &[rho, 0.0, 0.0], clearance);
        assert!((v - exact(rho)).abs() <= 1e-15, "{rho}: {v} {}", exact(rho));
    }
    for (rho, sign) in [(0.5, 1.0), (0.5 + 1e-9, 1.0), (0.5 - 1e-9, -1.0)] {
        assert_eq!(
            vertex_value(&g, &[rho, 0.0, 0.0], 1e-5),
            sign * 1e-5,
            "{rho}"
        );
    }
}
