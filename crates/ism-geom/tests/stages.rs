//! Property tests of local stages and maps: round trips, exact face invariance, Jacobians by finite
//! differences, the two Jacobian routes, and independent evaluation through `Bernstein`.

// Index loops over barycentric coordinates mirror the formulas under test.
#![allow(clippy::needless_range_loop)]

mod common;

use common::{make, Kind, Rng, KINDS};
use ism_format::{Model, StageKind};
use ism_geom::{linalg, Bary, Bernstein, LocalMap, LocalStage, INVERSE_TOLERANCE};
use proptest::prelude::*;

/// Round-trip tolerance on `w`: the residual target is 1e-12 in `u`; the inverse Jacobian of these
/// stages is bounded by a few hundred (weights up to e³ and monotonic slopes up to 20), so `w` is
/// accurate to ~1e-10.
const ROUNDTRIP_W: f64 = 1e-9;

/// Finite-difference step and tolerance: central differences have error `O(h²·|X'''|)`; with
/// `h = 1e-5` and third derivatives below ~1e3 that is 1e-7, plus rounding `1e-16/h`.
const FD_STEP: f64 = 1e-5;
const FD_TOL: f64 = 2e-6;

fn local_on_touched_simplex(
    model: &Model,
    stage_index: usize,
    rng: &mut Rng,
) -> (usize, LocalStage) {
    let stage = &model.stages[stage_index];
    let ns = model.num_simplices();
    let start = rng.below(ns);
    for k in 0..ns {
        let s = (start + k) % ns;
        let local = LocalStage::from_stage(stage, stage_index, model.simplex(s))
            .expect("generated stages are well-formed");
        if !local.is_identity() {
            return (s, local);
        }
    }
    (
        start,
        LocalStage::from_stage(stage, stage_index, model.simplex(start)).unwrap(),
    )
}

fn model_with(n: usize, kind: Kind, parametric: bool, seed: u64) -> (Model, Rng) {
    let mut rng = Rng(seed);
    let mut model = common::kuhn(n, if n == 2 { 2 } else { 1 }, &mut rng);
    let st = make(kind, &model, &mut rng, parametric);
    model.stages.push(st);
    (model, rng)
}

/// A Kuhn model of `n` dimensions with one stage of each of `kinds` in order (`make`), the
/// `i`-th parametric when `parametric(i)`: the stage chains the `inverse_near` and Jacobian
/// properties run on.
fn chain_model(
    n: usize,
    rng: &mut Rng,
    kinds: &[Kind],
    parametric: impl Fn(usize) -> bool,
) -> Model {
    let mut model = common::kuhn(n, 1, rng);
    for (i, kind) in kinds.iter().enumerate() {
        let st = make(*kind, &model, rng, parametric(i));
        model.stages.push(st);
    }
    model
}

fn max_diff(m: usize, a: &Bary, b: &Bary) -> f64 {
    (0..m).map(|i| (a[i] - b[i]).abs()).fold(0.0, f64::max)
}

fn check_roundtrip(local: &LocalStage, rng: &mut Rng, what: &str) -> Result<(), TestCaseError> {
    let m = local.vars();
    for _ in 0..40 {
        let w = rng.bary(m);
        let u = local.eval(&w);
        // Exact invariance: zero coordinates stay exactly zero, vertices map to themselves.
        for i in 0..m {
            if w[i] == 0.0 {
                prop_assert_eq!(u[i], 0.0, "{}: w={:?} u={:?}", what, w, u);
            }
            if w[i] == 1.0 {
                prop_assert_eq!(u[i], 1.0, "{}: vertex moved: {:?}", what, u);
            }
            prop_assert!(u[i] >= 0.0, "{}: u={:?}", what, u);
        }
        let back = local.inverse(&u);
        prop_assert!(
            back.converged,
            "{}: X⁻¹(X(w)) did not converge: w={:?} {:?}",
            what,
            w,
            back
        );
        prop_assert!(
            max_diff(m, &back.w, &w) < ROUNDTRIP_W,
            "{}: w={:?} back={:?}",
            what,
            w,
            back.w
        );
        for i in 0..m {
            if w[i] == 0.0 {
                prop_assert_eq!(back.w[i], 0.0, "{}: inverse left the face", what);
            }
        }
        // X(X⁻¹(u)) = u for an arbitrary u.
        let u2 = rng.bary(m);
        let pre = local.inverse(&u2);
        prop_assert!(
            pre.converged && pre.residual <= INVERSE_TOLERANCE,
            "{}: {:?}",
            what,
            pre
        );
        let again = local.eval(&pre.w);
        // Implicit: the residual is |X(w) − u| itself. Parametric: evaluating X means inverting the
        // stored map, so the 1e-12 residual is in w-space and u inherits the conditioning.
        let tol = if local.direction() == ism_format::Direction::Implicit {
            1e-11
        } else {
            ROUNDTRIP_W
        };
        prop_assert!(
            max_diff(m, &again, &u2) < tol,
            "{}: u={:?} X(X⁻¹(u))={:?}",
            what,
            u2,
            again
        );
        for i in 0..m {
            if u2[i] == 0.0 {
                prop_assert_eq!(pre.w[i], 0.0, "{}: inverse left the face", what);
            }
        }
    }
    Ok(())
}

/// Central differences of `f` along `e_l − e_0` at interior `w`, Richardson-extrapolated from steps
/// `h` and `h/2` so the truncation error is O(h⁴): plain central differences (O(h²)) are too coarse
/// for strongly weighted rational stages, whose third derivatives reach 1e5.
fn fd_reduced(m: usize, w: &Bary, f: impl Fn(&Bary) -> Bary) -> ism_geom::Mat {
    let central = |h: f64| {
        let mut j = [[0.0; 4]; 4];
        for l in 1..m {
            let mut wp = *w;
            let mut wm = *w;
            wp[l] += h;
            wp[0] -= h;
            wm[l] -= h;
            wm[0] += h;
            let (a, b) = (f(&wp), f(&wm));
            for k in 1..m {
                j[k - 1][l - 1] = (a[k] - b[k]) / (2.0 * h);
            }
        }
        j
    };
    let (coarse, fine) = (central(FD_STEP), central(FD_STEP / 2.0));
    let mut j = [[0.0; 4]; 4];
    for r in 0..4 {
        for c in 0..4 {
            j[r][c] = (4.0 * fine[r][c] - coarse[r][c]) / 3.0;
        }
    }
    j
}

/// Richardson-extrapolated central difference of a scalar function of one step.
fn richardson(g: impl Fn(f64) -> f64) -> f64 {
    let central = |h: f64| (g(h) - g(-h)) / (2.0 * h);
    (4.0 * central(FD_STEP / 2.0) - central(FD_STEP)) / 3.0
}

fn interior(rng: &mut Rng, m: usize) -> Bary {
    let mut w = [0.0; 4];
    w[..m].copy_from_slice(&rng.open_simplex(m, 0.02));
    w
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn round_trips_are_exact_on_faces(seed in any::<u64>(), n in 2usize..=3, parametric in any::<bool>()) {
        for kind in KINDS {
            let (model, mut rng) = model_with(n, kind, parametric, seed);
            let (s, local) = local_on_touched_simplex(&model, 0, &mut rng);
            check_roundtrip(&local, &mut rng, &format!("{kind:?} n={n} parametric={parametric} simplex {s}"))?;
        }
    }

    #[test]
    fn jacobians_match_finite_differences(seed in any::<u64>(), n in 2usize..=3, parametric in any::<bool>()) {
        for kind in KINDS {
            let (model, mut rng) = model_with(n, kind, parametric, seed);
            let (_, local) = local_on_touched_simplex(&model, 0, &mut rng);
            let m = n + 1;
            for _ in 0..5 {
                let w = interior(&mut rng, m);
                let (u, j) = local.jacobian(&w);
                let j = j.expect("valid stage: nonsingular");
                prop_assert!(max_diff(m, &u, &local.eval(&w)) < 1e-12);
                let fd = fd_reduced(m, &w, |x| local.eval(x));
                for r in 0..n {
                    for c in 0..n {
                        prop_assert!((j[r][c] - fd[r][c]).abs() < FD_TOL * (1.0 + fd[r][c].abs()),
                            "{:?}: J[{}][{}] = {} vs FD {}", kind, r, c, j[r][c], fd[r][c]);
                    }
                }
                // Homogeneous Jacobian of the stored map against FD in each variable separately
                // (the stored formula extended off the plane Σw = 1).
                let (_, h) = local.homogeneous_jacobian_stored(&w);
                for c in 0..m {
                    for r in 0..m {
                        let fd = richardson(|h| {
                            let mut wh = w;
                            wh[c] += h;
                            local.eval_stored(&wh)[r]
                        });
                        prop_assert!((h[r][c] - fd).abs() < FD_TOL * (1.0 + fd.abs()), "{:?} H[{}][{}]", kind, r, c);
                    }
                }
            }
        }
    }

    #[test]
    fn composed_maps_round_trip_and_chain_rule_holds(seed in any::<u64>(), n in 2usize..=3) {
        let mut rng = Rng(seed);
        let model = chain_model(n, &mut rng, &[Kind::Monotonic(3), Kind::NearIdentity(3), Kind::Rational(2), Kind::AdjustedQuadratic], |i| i % 2 == 1);
        for s in 0..model.num_simplices() {
            let map = LocalMap::from_model(&model, s).unwrap();
            prop_assert_eq!(map.stages().len(), 4);
            let m = n + 1;
            for _ in 0..10 {
                let w = rng.bary(m);
                let u = map.eval(&w);
                let back = map.inverse(&u);
                prop_assert!(back.converged, "{:?}", back);
                prop_assert!(max_diff(m, &back.w, &w) < ROUNDTRIP_W);
                for i in 0..m {
                    if w[i] == 0.0 {
                        prop_assert_eq!(u[i], 0.0);
                        prop_assert_eq!(back.w[i], 0.0);
                    }
                }
            }
            let w = interior(&mut rng, m);
            let j = map.jacobian(&w).1.unwrap();
            let fd = fd_reduced(m, &w, |x| map.eval(x));
            for r in 0..n {
                for c in 0..n {
                    prop_assert!((j[r][c] - fd[r][c]).abs() < FD_TOL * (1.0 + fd[r][c].abs()));
                }
            }
        }
    }

    /// `inverse_near` from a perturbed guess lands on the same preimage as `inverse`, and the
    /// value and Jacobian it returns are those of the map at that preimage.
    #[test]
    fn inverse_near_agrees_with_inverse_and_returns_the_jacobian(seed in any::<u64>(), n in 2usize..=3) {
        let mut rng = Rng(seed);
        let model = chain_model(n, &mut rng, &[Kind::Monotonic(3), Kind::NearIdentity(3), Kind::Rational(2)], |i| i == 1);
        let m = n + 1;
        for s in 0..model.num_simplices() {
            let map = LocalMap::from_model(&model, s).unwrap();
            for _ in 0..10 {
                let w = interior(&mut rng, m);
                let u = map.eval(&w);
                let mut guess = w;
                for g in guess.iter_mut().take(m) {
                    *g *= 1.0 + 0.02 * (rng.bary(2)[0] - 0.5);
                }
                let Some(near) = map.inverse_near(&u, &guess) else {
                    // Allowed (callers fall back), but not from a guess this close.
                    return Err(TestCaseError::fail(format!("no convergence from {guess:?}")));
                };
                prop_assert!(near.residual <= INVERSE_TOLERANCE);
                prop_assert!(max_diff(m, &near.w, &w) < ROUNDTRIP_W);
                let (x, j) = map.jacobian(&near.w);
                prop_assert_eq!(x, near.x);
                prop_assert_eq!(j.unwrap(), near.jacobian);
            }
        }
    }

    /// On an edge of the simplex `inverse_near` solves the one-dimensional problem along it
    /// (bracketed secant, `LocalMap::inverse_on_edge`): from the crossing itself as the start
    /// (what the exporter gives a patch corner), it lands on the known preimage of a point built
    /// as `X(w)` with `w` on the edge, with the same acceptance and the map's value and Jacobian
    /// there; it agrees with the robust `inverse`.
    #[test]
    fn inverse_near_on_an_edge_finds_the_known_preimage(seed in any::<u64>(), n in 2usize..=3) {
        let mut rng = Rng(seed);
        let model = chain_model(n, &mut rng, &[Kind::Monotonic(3), Kind::NearIdentity(3), Kind::Rational(2)], |i| i == 1);
        let m = n + 1;
        for s in 0..model.num_simplices() {
            let map = LocalMap::from_model(&model, s).unwrap();
            for (a, b) in [(0, 1), (0, m - 1), (1, m - 1)] {
                // Inside the edge, where the crossing itself is a poor start for Newton.
                let t = 0.02 + 0.96 * rng.bary(2)[0];
                let mut w: Bary = Default::default();
                w[a] = 1.0 - t;
                w[b] = t;
                let u = map.eval(&w);
                for i in (0..m).filter(|&i| i != a && i != b) {
                    prop_assert_eq!(u[i], 0.0, "faces map to themselves");
                }
                let Some(near) = map.inverse_near(&u, &u) else {
                    return Err(TestCaseError::fail(format!("no convergence on edge {a}-{b} at {u:?}")));
                };
                prop_assert!(near.residual <= INVERSE_TOLERANCE);
                prop_assert!(max_diff(m, &near.w, &w) < ROUNDTRIP_W);
                prop_assert!(max_diff(m, &near.w, &map.inverse(&u).w) < ROUNDTRIP_W);
                let (x, j) = map.jacobian(&near.w);
                prop_assert_eq!(x, near.x);
                prop_assert_eq!(j.unwrap(), near.jacobian);
            }
        }
    }

    /// For all-parametric maps `param_solve` is `inverse` without Newton, with `DX = DY⁻¹`.
    #[test]
    fn param_solve_agrees_with_inverse_and_jacobian(seed in any::<u64>(), n in 2usize..=3) {
        let mut rng = Rng(seed);
        let mut model = chain_model(n, &mut rng, &[Kind::NearIdentity(3), Kind::Rational(2), Kind::Monotonic(2)], |_| true);
        let m = n + 1;
        for s in 0..model.num_simplices() {
            let map = LocalMap::from_model(&model, s).unwrap();
            for _ in 0..10 {
                let u = interior(&mut rng, m);
                let solved = map.param_solve(&u).unwrap();
                let reference = map.inverse(&u);
                prop_assert!(max_diff(m, &solved.w, &reference.w) < ROUNDTRIP_W);
                prop_assert!(max_diff(m, &map.eval(&solved.w), &u) < ROUNDTRIP_W);
                let j = map.jacobian(&solved.w).1.unwrap();
                for r in 0..n {
                    for c in 0..n {
                        prop_assert!((j[r][c] - solved.jacobian[r][c]).abs() < 1e-8 * (1.0 + j[r][c].abs()));
                    }
                }
            }
        }
        // An implicit stage anywhere: no direct solve.
        let st = make(Kind::NearIdentity(2), &model, &mut rng, false);
        model.stages.push(st);
        let map = LocalMap::from_model(&model, 0).unwrap();
        prop_assert!(map.param_solve(&interior(&mut rng, m)).is_none());
    }

    /// Mello & Velho 2009, §3 Prop. 3.1: for a polynomial stage `det(reduced) = det(H) / d`.
    #[test]
    fn reduced_and_homogeneous_jacobian_routes_agree(seed in any::<u64>(), n in 2usize..=3, d in 1u32..=6) {
        let mut rng = Rng(seed);
        let model = common::kuhn(n, 1, &mut rng);
        let st = common::near_identity_bezier(&model, &mut rng, d, 0.3);
        let local = LocalStage::from_stage(&st, 0, model.simplex(rng.below(model.num_simplices()))).unwrap();
        for _ in 0..20 {
            let w = rng.bary(n + 1);
            let (_, h) = local.homogeneous_jacobian_stored(&w);
            let hom = linalg::det(n + 1, &h) / f64::from(d);
            let red = local.det(&w);
            prop_assert!((hom - red).abs() < 1e-12 * (1.0 + red.abs()), "d={} hom={} red={}", d, hom, red);
        }
    }

    /// Evaluation through `Bernstein` (de Casteljau, one polynomial per coordinate) against the
    /// stage's power-basis evaluation, and Bernstein derivatives against the reduced Jacobian.
    #[test]
    fn bernstein_route_agrees_with_stage_evaluation(seed in any::<u64>(), n in 2usize..=3, d in 1u32..=7) {
        let mut rng = Rng(seed);
        let model = common::kuhn(n, 1, &mut rng);
        let st = common::near_identity_bezier(&model, &mut rng, d, 0.4);
        let local = LocalStage::from_stage(&st, 0, model.simplex(0)).unwrap();
        let m = n + 1;
        let comps: Vec<Bernstein> = (0..m)
            .map(|i| Bernstein::new(m, d, local.control_points().iter().map(|b| b[i]).collect()).unwrap())
            .collect();
        for _ in 0..10 {
            let w = rng.bary(m);
            let u = local.eval_stored(&w);
            let (_, j) = local.jacobian_stored(&w);
            for i in 0..m {
                prop_assert!((comps[i].eval(&w[..m]) - u[i]).abs() < 1e-13);
            }
            for k in 1..m {
                for l in 1..m {
                    prop_assert!((comps[k].derivative(l).eval(&w[..m]) - j[k - 1][l - 1]).abs() < 1e-11);
                }
            }
        }
    }
}

#[test]
fn identity_stages_are_the_identity_exactly() {
    for kind in [StageKind::Bezier, StageKind::Rational, StageKind::Monotonic] {
        for m in 2..=4 {
            let local = LocalStage::identity(kind, 3, m).unwrap();
            let w = [0.1, 0.2, 0.3, 0.4];
            let mut w = w;
            let s: f64 = w[..m].iter().sum();
            for x in w.iter_mut().take(m) {
                *x /= s;
            }
            for x in w.iter_mut().skip(m) {
                *x = 0.0;
            }
            assert_eq!(local.eval(&w), w);
            assert_eq!(local.inverse(&w).w, w);
        }
    }
}
