//! The exporter's fused local maps, built directly (`LocalMap::from_indexed_fused`: a projective
//! stage is read from its table and folded into the next net as it is built; a net is made sparse
//! from the points its records gave), against the reference route: every stage built
//! (`LocalMap::from_indexed`), then fused and made sparse over whole nets (`LocalMap::fused`).

mod common;

use common::{make, Kind, Rng};
use ism_format::{IndexedModel, Model, Stage, StageKind};
use ism_geom::LocalMap;

/// A projective stage (monotonic of degree 1, `g_i(t) = a_i t`) on every vertex.
fn projective(model: &Model, rng: &mut Rng) -> Stage {
    make(Kind::Monotonic(1), model, rng, false)
}

/// Stage sequences that fuse, skip identity stages between the pair, chain two projective
/// stages, end on one, refuse to fuse (a vertex map that is not projective, a parametric net, a
/// weight that overflows), and have no projective stage (nets, some sparse); each with what the
/// check below asserts of it.
fn sequences(model: &Model, rng: &mut Rng) -> Vec<(&'static str, Vec<Stage>)> {
    let net = |kind, rng: &mut Rng| make(kind, model, rng, false);
    let mut shifted = projective(model, rng);
    // Vertex 0's map no longer vanishes at 0: not projective on the simplices at vertex 0.
    shifted.vertex_maps[0].coefficients[0] = 0.05;
    let mut huge = projective(model, rng);
    // Fused weights a^I of this vertex overflow: no fusion on the simplices at vertex 0.
    huge.vertex_maps[0].coefficients[1] = 1e200;
    let mut partial = projective(model, rng);
    // Vertices without a map keep the identity's, `g(t) = t`: still projective.
    partial.vertex_maps.retain(|r| r.vertex % 3 != 1);
    vec![
        (
            "pair",
            vec![projective(model, rng), net(Kind::AdjustedQuadratic, rng)],
        ),
        (
            "identity between",
            vec![
                projective(model, rng),
                net(Kind::Solitary, rng),
                net(Kind::Rational(2), rng),
            ],
        ),
        (
            "two projective",
            vec![
                projective(model, rng),
                projective(model, rng),
                net(Kind::NearIdentity(2), rng),
            ],
        ),
        (
            "monotonic between",
            vec![
                projective(model, rng),
                net(Kind::Monotonic(2), rng),
                net(Kind::Rational(3), rng),
            ],
        ),
        (
            "projective last",
            vec![net(Kind::Rational(2), rng), projective(model, rng)],
        ),
        (
            "parametric net",
            vec![
                projective(model, rng),
                make(Kind::NearIdentity(3), model, rng, true),
            ],
        ),
        (
            "not projective",
            vec![shifted, net(Kind::AdjustedQuadratic, rng)],
        ),
        ("overflow", vec![huge, net(Kind::Rational(2), rng)]),
        ("partial", vec![partial, net(Kind::NearIdentity(2), rng)]),
        // Nets left unfused: a net whose few records deviate is evaluated sparsely.
        ("stratified", common::stratified(model, rng)),
        (
            "nets",
            vec![
                net(Kind::Solitary, rng),
                net(Kind::NearIdentity(3), rng),
                net(Kind::AdjustedQuadratic, rng),
            ],
        ),
    ]
}

/// Stage for stage and bit for bit (the `Debug` text prints each `f64` in its shortest round-trip
/// form), the direct build equals the reference on every simplex, with an eager and a lazy index;
/// and the cases do what they are named for (fusions happen, and are refused where they must be).
#[test]
fn fused_local_maps_equal_the_unfused_maps_fused() {
    for n in 2..=3usize {
        for seed in 0..4u64 {
            let mut rng = Rng(0xf05e_d000 + seed);
            let base = common::kuhn(n, 2, &mut rng);
            for (what, stages) in sequences(&base, &mut rng) {
                let mut model = base.clone();
                model.stages = stages;
                let eager = IndexedModel::new(model.clone()).expect("a valid model");
                let lazy = IndexedModel::new_lazy_or_model(model.clone())
                    .map_err(|(_, e)| e)
                    .expect("a valid model");
                let (mut fused, mut kept, mut sparse) = (0, 0, 0);
                for s in 0..model.num_simplices() {
                    let reference = LocalMap::from_indexed(&eager, s).unwrap();
                    let unfused = reference.stages().len();
                    let reference = reference.fused();
                    sparse += usize::from(format!("{reference:?}").contains("sparse: Some"));
                    for index in [&eager, &lazy] {
                        let direct = LocalMap::from_indexed_fused(index, s).unwrap();
                        assert_eq!(
                            format!("{direct:?}"),
                            format!("{reference:?}"),
                            "{what}, n = {n}, seed {seed}, simplex {s}"
                        );
                    }
                    let rational = |m: &LocalMap| {
                        m.stages()
                            .iter()
                            .filter(|st| st.kind() == StageKind::Rational)
                            .count()
                    };
                    if reference.stages().len() < unfused {
                        fused += 1;
                        assert!(rational(&reference) > 0, "{what}");
                    } else if unfused >= 2 {
                        kept += 1;
                    }
                }
                let at_vertex_0 = model.simplices.chunks(n + 1).any(|s| s.contains(&0));
                match what {
                    // Nothing to fuse with: the projective stage is placed as it is.
                    "parametric net" | "projective last" | "monotonic between" => {
                        assert!(fused == 0 && kept > 0, "{what}: {kept} {fused}")
                    }
                    "stratified" | "nets" => {
                        assert!(fused == 0 && sparse > 0, "{what}: {fused} {sparse}")
                    }
                    "not projective" | "overflow" => {
                        assert!(
                            at_vertex_0 && kept > 0 && fused > 0,
                            "{what}: {kept} {fused}"
                        )
                    }
                    _ => assert!(fused > 0, "{what}"),
                }
            }
        }
    }
}

/// `ModelEval::local_map_transient` builds the very map `local_map` caches (fused for the
/// exporter's evaluator, unfused otherwise) without caching it, and lends the cached one once
/// there is one.
#[test]
fn transient_local_maps_are_the_cached_maps_uncached() {
    use ism_geom::ModelEval;
    use std::borrow::Cow;
    for n in 2..=3usize {
        let mut rng = Rng(0x7a5e_0000 + n as u64);
        let base = common::kuhn(n, 2, &mut rng);
        for (what, stages) in sequences(&base, &mut rng) {
            let mut model = base.clone();
            model.stages = stages;
            let indexed = IndexedModel::new(model.clone()).expect("a valid model");
            for (route, eval) in [
                ("plain", ModelEval::from_indexed(&indexed).unwrap()),
                ("extraction", ModelEval::for_extraction(&indexed).unwrap()),
            ] {
                for s in 0..model.num_simplices() {
                    let first = eval.local_map_transient(s);
                    let again = eval.local_map_transient(s);
                    assert!(
                        matches!((&first, &again), (Cow::Owned(_), Cow::Owned(_))),
                        "{what}, {route}, simplex {s}: a transient map was cached"
                    );
                    let cached = eval.local_map(s);
                    assert_eq!(
                        format!("{first:?}"),
                        format!("{cached:?}"),
                        "{what}, {route}"
                    );
                    assert!(
                        matches!(eval.local_map_transient(s), Cow::Borrowed(m) if std::ptr::eq(m, cached)),
                        "{what}, {route}, simplex {s}: the cached map is not lent"
                    );
                }
            }
        }
    }
}
