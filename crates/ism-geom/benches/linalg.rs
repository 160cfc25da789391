//! The hand-written `linalg` (run-time `k ≤ 4` on `[[f64; 4]; 4]`) against `glam`'s `DMat2` /
//! `DMat3`, which the design names for small fixed-size math (issue 13): determinant, inverse and
//! solve of the 2 × 2 and 3 × 3 matrices the kernel's Newton steps, Jacobians and the sampler's
//! area elements use. Both sides get the same well-conditioned random matrices, converted to glam's
//! column-major types outside the timed loop. glam has no `solve`; its usual form is
//! `inverse() * b`, which is what a caller would write.
//!
//! `cargo bench -p ism-geom --bench linalg -- --warm-up-time 1 --measurement-time 3`

#[path = "../tests/common/mod.rs"]
mod common;

use std::hint::black_box;

use common::Rng;
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use glam::{DMat2, DMat3, DVec2, DVec3};
use ism_geom::{linalg, Mat, MAX_VARS};

const BATCH: usize = 4096;

/// Random `k × k` blocks, entries in [-1, 1] plus 2·I (well conditioned: the kernel's Jacobians
/// near the identity look like this).
fn matrices(rng: &mut Rng, k: usize) -> Vec<(Mat, [f64; MAX_VARS])> {
    (0..BATCH)
        .map(|_| {
            let mut a = [[0.0; MAX_VARS]; MAX_VARS];
            let mut b = [0.0; MAX_VARS];
            for (r, (row, v)) in a.iter_mut().zip(b.iter_mut()).enumerate().take(k) {
                for (c, x) in row.iter_mut().enumerate().take(k) {
                    *x = rng.uniform(-1.0, 1.0) + if r == c { 2.0 } else { 0.0 };
                }
                *v = rng.uniform(-1.0, 1.0);
            }
            (a, b)
        })
        .collect()
}

fn to_dmat2(a: &Mat) -> DMat2 {
    DMat2::from_cols(DVec2::new(a[0][0], a[1][0]), DVec2::new(a[0][1], a[1][1]))
}

fn to_dmat3(a: &Mat) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(a[0][0], a[1][0], a[2][0]),
        DVec3::new(a[0][1], a[1][1], a[2][1]),
        DVec3::new(a[0][2], a[1][2], a[2][2]),
    )
}

/// glam's three operations on `(matrix, right-hand side)` pairs; a macro because `DMat2` and
/// `DMat3` share these methods but no trait.
macro_rules! bench_glam {
    ($group:expr, $theirs:expr) => {
        $group.bench_function(BenchmarkId::new("det", "glam"), |b| {
            b.iter(|| {
                $theirs
                    .iter()
                    .map(|(a, _)| black_box(a).determinant())
                    .sum::<f64>()
            })
        });
        $group.bench_function(BenchmarkId::new("inverse", "glam"), |b| {
            b.iter(|| {
                $theirs
                    .iter()
                    .map(|(a, _)| black_box(a).inverse().x_axis.x)
                    .sum::<f64>()
            })
        });
        $group.bench_function(BenchmarkId::new("solve", "glam"), |b| {
            b.iter(|| {
                $theirs
                    .iter()
                    .map(|(a, v)| (black_box(a).inverse() * *v).x)
                    .sum::<f64>()
            })
        });
    };
}

fn compare(c: &mut Criterion) {
    let mut rng = Rng(7);
    for k in [2usize, 3] {
        let ours = matrices(&mut rng, k);
        let mut group = c.benchmark_group(format!("linalg/{k}x{k}"));
        group.throughput(Throughput::Elements(BATCH as u64));
        group.bench_function(BenchmarkId::new("det", "ism"), |b| {
            b.iter(|| {
                ours.iter()
                    .map(|(a, _)| linalg::det(black_box(k), black_box(a)))
                    .sum::<f64>()
            })
        });
        group.bench_function(BenchmarkId::new("inverse", "ism"), |b| {
            b.iter(|| {
                ours.iter()
                    .map(|(a, _)| {
                        linalg::inverse(black_box(k), black_box(a)).map_or(0.0, |m| m[0][0])
                    })
                    .sum::<f64>()
            })
        });
        group.bench_function(BenchmarkId::new("solve", "ism"), |b| {
            b.iter(|| {
                ours.iter()
                    .map(|(a, v)| {
                        linalg::solve(black_box(k), black_box(a), v).map_or(0.0, |x| x[0])
                    })
                    .sum::<f64>()
            })
        });
        if k == 2 {
            let theirs: Vec<(DMat2, DVec2)> = ours
                .iter()
                .map(|(a, v)| (to_dmat2(a), DVec2::new(v[0], v[1])))
                .collect();
            bench_glam!(group, theirs);
        } else {
            let theirs: Vec<(DMat3, DVec3)> = ours
                .iter()
                .map(|(a, v)| (to_dmat3(a), DVec3::new(v[0], v[1], v[2])))
                .collect();
            bench_glam!(group, theirs);
        }
        group.finish();
    }
}

criterion_group!(benches, compare);
criterion_main!(benches);
