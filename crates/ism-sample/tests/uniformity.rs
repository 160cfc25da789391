//! Statistical tests of the surface sampler.
//!
//! The surface of each model is cut into cells: every linear patch `θ_σ` is split in parameter
//! space (2D: segment halves; 3D: the patch's triangles, each cut into its 4 midpoint
//! sub-triangles). Each cell's TRUE curved area is computed independently of the sampler, by fine
//! quadrature of the parametric map `u ↦ W(X⁻¹(u))` (polyline length in 2D, sum of flat
//! micro-triangle areas in 3D; neither uses the area-element formula nor its bound). Samples are
//! binned by cell and compared with Pearson's chi-square test.
//!
//! Significance: α = 0.001. The seeds are fixed, so each test is deterministic; the statement is
//! that a correct sampler passes at α (it does for these seeds) and that sampling by linear-patch
//! area is rejected with p < 1e-9 on the same models.

mod common;

use ism_format::Model;
use ism_geom::{Bary, ModelEval};
use ism_sample::{Collect, Sampler, Weighting};
use statrs::distribution::{ChiSquared, ContinuousCDF};

/// The test's significance level.
const ALPHA: f64 = 1e-3;

/// One cell: the simplex, the barycentric corners of its parameter region, its curved area.
struct Cell {
    simplex: usize,
    corners: Vec<Bary>,
    area: f64,
}

fn lerp(a: &Bary, b: &Bary, t: f64) -> Bary {
    let mut out = [0.0; 4];
    for i in 0..4 {
        out[i] = (1.0 - t) * a[i] + t * b[i];
    }
    out
}

fn point(eval: &ModelEval, s: usize, u: &Bary) -> [f64; 3] {
    let r = eval.param_point(s, u);
    assert!(r.inverse.converged, "inverse did not converge");
    r.p
}

fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn tri_area(a: &[f64; 3], b: &[f64; 3], c: &[f64; 3]) -> f64 {
    let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
    let x = [
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    ];
    0.5 * (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt()
}

/// Curved length of the image of segment `[a, b]` by a 400-segment polyline.
fn curved_length(eval: &ModelEval, s: usize, a: &Bary, b: &Bary) -> f64 {
    let k = 400;
    let pts: Vec<[f64; 3]> = (0..=k)
        .map(|i| point(eval, s, &lerp(a, b, i as f64 / k as f64)))
        .collect();
    pts.windows(2).map(|w| dist(&w[0], &w[1])).sum()
}

/// Curved area of the image of triangle `[a, b, c]` by `k²` flat micro-triangles.
fn curved_area(eval: &ModelEval, s: usize, a: &Bary, b: &Bary, c: &Bary) -> f64 {
    let k = 16;
    let at = |i: usize, j: usize| {
        let (x, y) = (i as f64 / k as f64, j as f64 / k as f64);
        let mut u = [0.0; 4];
        for t in 0..4 {
            u[t] = (1.0 - x - y) * a[t] + x * b[t] + y * c[t];
        }
        point(eval, s, &u)
    };
    let mut grid = vec![vec![[0.0; 3]; k + 1]; k + 1];
    for (i, row) in grid.iter_mut().enumerate() {
        for (j, p) in row.iter_mut().enumerate().take(k + 1 - i) {
            *p = at(i, j);
        }
    }
    let mut area = 0.0;
    for i in 0..k {
        for j in 0..(k - i) {
            area += tri_area(&grid[i][j], &grid[i + 1][j], &grid[i][j + 1]);
            if i + j + 1 < k {
                area += tri_area(&grid[i + 1][j], &grid[i + 1][j + 1], &grid[i][j + 1]);
            }
        }
    }
    area
}

fn cells(eval: &ModelEval) -> Vec<Cell> {
    let n = eval.dim();
    let mut out = Vec::new();
    for s in 0..eval.num_simplices() {
        let Some(patch) = eval.patch(s) else { continue };
        let c: Vec<Bary> = patch.corners.iter().map(|k| k.u).collect();
        if n == 2 {
            let mid = lerp(&c[0], &c[1], 0.5);
            for (a, b) in [(c[0], mid), (mid, c[1])] {
                out.push(Cell {
                    simplex: s,
                    corners: vec![a, b],
                    area: curved_length(eval, s, &a, &b),
                });
            }
        } else {
            let tris: Vec<[Bary; 3]> = if c.len() == 4 {
                vec![[c[0], c[1], c[2]], [c[0], c[2], c[3]]]
            } else {
                vec![[c[0], c[1], c[2]]]
            };
            for [a, b, cc] in tris {
                let (ab, bc, ca) = (lerp(&a, &b, 0.5), lerp(&b, &cc, 0.5), lerp(&cc, &a, 0.5));
                for t in [[a, ab, ca], [ab, b, bc], [ca, bc, cc], [ab, bc, ca]] {
                    out.push(Cell {
                        simplex: s,
                        area: curved_area(eval, s, &t[0], &t[1], &t[2]),
                        corners: t.to_vec(),
                    });
                }
            }
        }
    }
    out
}

/// Barycentric coordinates of `u` w.r.t. the cell's corners (least squares; exact when `u` lies
/// in the cell's affine hull).
fn local_coords(corners: &[Bary], u: &Bary) -> Vec<f64> {
    let k = corners.len();
    // Normal equations (Gᵀ G) λ = Gᵀ u with the constraint carried by the barycentric sums.
    let mut a = vec![vec![0.0; k]; k];
    let mut b = vec![0.0; k];
    for i in 0..k {
        for j in 0..k {
            a[i][j] = (0..4).map(|t| corners[i][t] * corners[j][t]).sum();
        }
        b[i] = (0..4).map(|t| corners[i][t] * u[t]).sum();
    }
    // Gaussian elimination with partial pivoting (k ≤ 3).
    for col in 0..k {
        let piv = (col..k)
            .max_by(|&x, &y| a[x][col].abs().total_cmp(&a[y][col].abs()))
            .unwrap();
        a.swap(col, piv);
        b.swap(col, piv);
        for r in (col + 1)..k {
            let f = a[r][col] / a[col][col];
            let pivot_row = a[col].clone();
            for (x, p) in a[r].iter_mut().zip(&pivot_row).skip(col) {
                *x -= f * p;
            }
            b[r] -= f * b[col];
        }
    }
    let mut x = vec![0.0; k];
    for r in (0..k).rev() {
        x[r] = (b[r] - ((r + 1)..k).map(|c| a[r][c] * x[c]).sum::<f64>()) / a[r][r];
    }
    x
}

/// Pearson chi-square p-value of the samples' cell counts against the curved areas.
/// `expected`: the table sized for that many samples ([`Sampler::expected_surface_samples`]).
fn p_value(
    model: &Model,
    weighting: Weighting,
    count: u64,
    seed: u64,
    expected: Option<u64>,
) -> (f64, f64, usize) {
    let mut sampler = Sampler::new(model).unwrap().seed(seed);
    if let Some(e) = expected {
        sampler = sampler.expected_surface_samples(e);
    }
    let sampler = sampler.weighting(weighting);
    let eval = sampler.eval();
    let cells = cells(eval);
    let mut by_simplex: std::collections::HashMap<usize, Vec<usize>> = Default::default();
    for (i, c) in cells.iter().enumerate() {
        by_simplex.entry(c.simplex).or_default().push(i);
    }
    let mut rows = Collect::default();
    sampler.surface(count, &mut rows).unwrap();
    let n = eval.dim();
    let mut observed = vec![0u64; cells.len()];
    for (r, p) in rows.rows.positions.chunks_exact(n).enumerate() {
        let s = rows.rows.simplices[r] as usize;
        let w = eval.barycentric(s, p);
        let u = eval.local_map(s).eval(&w);
        let best = by_simplex[&s]
            .iter()
            .map(|&i| {
                (
                    i,
                    local_coords(&cells[i].corners, &u)
                        .iter()
                        .copied()
                        .fold(f64::INFINITY, f64::min),
                )
            })
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap();
        assert!(
            best.1 > -1e-6,
            "sample {r} lies in no cell of simplex {s} ({})",
            best.1
        );
        observed[best.0] += 1;
    }
    let total_area: f64 = cells.iter().map(|c| c.area).sum();
    // Pool cells whose expected count is below 5 into one bin, as the test requires.
    let (mut chi2, mut bins) = (0.0, 0usize);
    let (mut pool_o, mut pool_e) = (0.0, 0.0);
    for (c, &o) in cells.iter().zip(&observed) {
        let e = count as f64 * c.area / total_area;
        if e < 5.0 {
            pool_o += o as f64;
            pool_e += e;
        } else {
            chi2 += (o as f64 - e).powi(2) / e;
            bins += 1;
        }
    }
    if pool_e > 0.0 {
        chi2 += (pool_o - pool_e).powi(2) / pool_e;
        bins += 1;
    }
    let dist = ChiSquared::new((bins - 1) as f64).unwrap();
    (dist.sf(chi2), chi2, bins)
}

#[test]
fn curved_area_sampling_passes_and_linear_area_sampling_fails() {
    for (name, model) in common::curved_models() {
        let count = if model.dim() == 2 { 40_000 } else { 60_000 };
        // The fixed refinement threshold, the root bounds alone (a table sized for one sample:
        // all-parametric patches are not refined at all) and a table sized for `count`.
        for expected in [None, Some(1), Some(count)] {
            let (p, chi2, bins) = p_value(&model, Weighting::CurvedArea, count, 11, expected);
            eprintln!(
                "{name} ({expected:?} expected): curved-area sampler chi2 = {chi2:.1} on {bins} bins, p = {p:.4}"
            );
            assert!(
                p > ALPHA,
                "{name} ({expected:?} expected): uniform-by-curved-area sampler rejected, p = {p}, chi2 = {chi2} ({bins} bins)"
            );
        }
        let (p_lin, chi2_lin, _) = p_value(&model, Weighting::LinearArea, count, 11, None);
        eprintln!("{name}: linear-area sampler chi2 = {chi2_lin:.1}, p = {p_lin:.3e}");
        assert!(
            p_lin < 1e-9,
            "{name}: the test failed to reject linear-patch-area sampling (p = {p_lin})"
        );
    }
}

/// Every surface sample lies in its source simplex and on the level set within the tolerance,
/// checked here by re-evaluating `F` and `∇F` at the written position.
#[test]
fn every_sample_is_in_its_simplex_and_on_the_level_set() {
    for (name, model) in common::curved_models() {
        assert_exact(name, &model, 4000, 5);
    }
}

/// Draws `count` surface samples of `model` with `seed` and checks each one: inside its source
/// simplex and `|F − c| ≤ SURFACE_TOLERANCE · |∇F| · L` (`L` the diagonal of `[−1, 1]ⁿ`), with `F`
/// and `∇F` evaluated again at the written position (point location and the kernel's inverse,
/// not the sampler's construction of the point).
fn assert_exact(name: &str, model: &Model, count: u64, seed: u64) {
    let sampler = Sampler::new(model).unwrap().seed(seed);
    let mut rows = Collect::default();
    sampler.surface(count, &mut rows).unwrap();
    let eval = sampler.eval();
    let n = eval.dim();
    let scale = 2.0 * (n as f64).sqrt(); // bounding-box diagonal of [−1, 1]ⁿ
    for (r, p) in rows.rows.positions.chunks_exact(n).enumerate() {
        let s = rows.rows.simplices[r] as usize;
        let w = eval.barycentric(s, p);
        assert!(
            w[..=n].iter().all(|&x| x >= -1e-12),
            "{name}: sample {r} outside simplex {s}: {w:?}"
        );
        let f = eval.value_at(s, &w);
        let g = eval.gradient_at(s, &w).unwrap();
        let gn = g[..n].iter().map(|x| x * x).sum::<f64>().sqrt();
        assert!(
            (f - model.level).abs() <= ism_sample::SURFACE_TOLERANCE * gn * scale,
            "{name}: sample {r}: |F − c| = {:e} > 1e-10·|∇F|·L = {:e}",
            (f - model.level).abs(),
            ism_sample::SURFACE_TOLERANCE * gn * scale
        );
    }
}

/// The same seed gives the same rows on one and on two threads: an implicit model with the
/// fixed refinement threshold, and all-parametric ones (one partly stage-free) with a table sized
/// for the samples (as `ism sample` builds it).
#[test]
fn output_does_not_depend_on_the_thread_count() {
    let models = common::curved_models();
    for (name, model, expected) in [
        (models[2].0, &models[2].1, None),
        (
            models[6].0,
            &models[6].1,
            Some(3 * ism_sample::seed::CHUNK as u64 + 17),
        ),
        (
            models[7].0,
            &models[7].1,
            Some(3 * ism_sample::seed::CHUNK as u64 + 17),
        ),
    ] {
        thread_count_check(name, model, expected);
    }
}

fn thread_count_check(name: &str, model: &Model, expected: Option<u64>) {
    assert!(name.contains("stratified"));
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut sampler = Sampler::new(model).unwrap().seed(99);
            if let Some(e) = expected {
                sampler = sampler.expected_surface_samples(e);
            }
            let mut rows = Collect::default();
            sampler
                .surface(3 * ism_sample::seed::CHUNK as u64 + 17, &mut rows)
                .unwrap();
            let mut vol = Collect::default();
            sampler.near_surface(10_000, 0.05, &mut vol).unwrap();
            (rows.rows, vol.rows)
        })
    };
    let one = run(1);
    let two = run(2);
    assert_eq!(
        one.0
            .positions
            .iter()
            .map(|x| x.to_bits())
            .collect::<Vec<_>>(),
        two.0
            .positions
            .iter()
            .map(|x| x.to_bits())
            .collect::<Vec<_>>()
    );
    assert_eq!(one.1.simplices, two.1.simplices);
    assert_eq!(one.1.labels, two.1.labels);
}

/// Shapes and stages no test was written for ([`ism_examples::ellipsoid_model`]: a random ellipse
/// or ellipsoid — centre, radii, grid resolution — under one of four random stage chains, stored
/// parametric or implicit): the samples are uniform by curved area (the chi-square test above,
/// against the independent quadrature of the cells, with the table sized for the samples as `ism
/// sample` builds it or with the fixed threshold) and each one lies on the level set.
mod unseen {
    use super::*;
    use ism_examples::{ellipsoid_model, ELLIPSOID_CHAINS};
    use ism_format::Direction;
    use proptest::prelude::*;

    /// Significance on random models. Each run draws new cases, so a correct sampler must pass
    /// all of them at once: at 1e-6 per case a 12-case run fails by chance about once in 80,000
    /// runs. What a bias scores at these counts (20,000 / 40,000 samples, against the fixed
    /// models' 40,000 / 60,000, where sampling by linear patch area gives p < 1e-9) has not been
    /// measured on the random models.
    const ALPHA_UNSEEN: f64 = 1e-6;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(12))]
        #[test]
        fn random_shapes_and_stages_are_sampled_uniformly_and_exactly(
            three in any::<bool>(),
            centre in prop::array::uniform3(-0.2f64..0.2),
            radii in prop::array::uniform3(0.35f64..0.75),
            cells in 2usize..4,
            chain in 0..ELLIPSOID_CHAINS,
            implicit in any::<bool>(),
            seed in 0u64..1_000_000,
            amplitude in 0.1f64..0.8,
            sized in any::<bool>(),
        ) {
            let n = if three { 3 } else { 2 };
            let direction = if implicit { Direction::Implicit } else { Direction::Parametric };
            // 2D grids twice as fine: as many crossed cells as a 3D grid gives patches.
            let cells = if three { cells } else { 2 * cells };
            let model = ellipsoid_model(
                &centre[..n],
                &radii[..n],
                cells,
                (chain, seed, amplitude),
                direction,
            )
            .unwrap();
            // A small ellipse between the grid's vertices separates none of them: no shape.
            let inside = model.values.iter().filter(|&&f| f < model.level).count();
            prop_assume!(inside > 0 && inside < model.values.len());
            let name = format!(
                "{n}D ellipsoid {:?} {:?}, {cells} cells a side, chain {chain}, implicit \
                 {implicit}, seed {seed}, amplitude {amplitude}, sized {sized}",
                &centre[..n],
                &radii[..n]
            );
            let count = if three { 40_000 } else { 20_000 };
            let (p, chi2, bins) =
                p_value(&model, Weighting::CurvedArea, count, seed, sized.then_some(count));
            prop_assert!(
                p > ALPHA_UNSEEN,
                "{name}: rejected, p = {p}, chi2 = {chi2} ({bins} bins)"
            );
            assert_exact(&name, &model, 2000, seed);
        }
    }
}

/// The spec examples whose projective stage fuses into the next (the torus in 3D, the curved
/// circle in 2D): their area element peaks in corners of the fixed regions, so a table for many
/// samples draws from parts of regions bounded by the per-stage bound's cells. Uniform by
/// curved area against the same independent quadrature of the cells, for a table sized for the
/// samples (parts) and, for the circle, for one sample (none).
#[test]
fn projective_examples_are_sampled_uniformly() {
    for (name, count) in [("torus", 60_000u64), ("circle-curved", 40_000)] {
        let path = format!(
            "{}/../../spec/examples/{name}.ism.json",
            env!("CARGO_MANIFEST_DIR")
        );
        let model = ism_format::io::read_path(path).unwrap().model;
        // The one-sample table of the torus draws ~10³ candidates per sample (over a minute here).
        let tables: &[Option<u64>] = if name == "torus" {
            &[Some(count)]
        } else {
            &[Some(count), Some(1)]
        };
        for &expected in tables {
            let (p, chi2, bins) = p_value(&model, Weighting::CurvedArea, count, 13, expected);
            eprintln!(
                "{name} ({expected:?} expected): chi2 = {chi2:.1} on {bins} bins, p = {p:.4}"
            );
            assert!(
                p > ALPHA,
                "{name} ({expected:?} expected): rejected, p = {p}, chi2 = {chi2} ({bins} bins)"
            );
        }
    }
}
