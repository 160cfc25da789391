//! Throughput of the kernel: evaluations, Jacobians and inversions per second for each stage kind
//! and degree (2, 3, 5) on a 3-D simplex, on 1 thread and on 2 (rayon batch); point locations per
//! second on a Kuhn grid of 55³ cubes × 6 = 998 250 tetrahedra.
//!
//! `cargo bench -p ism-geom -- --warm-up-time 1 --measurement-time 3`

#[path = "../tests/common/mod.rs"]
mod common;

use std::hint::black_box;

use common::Rng;
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use ism_format::{Model, Stage};
use ism_geom::{Bary, LocalStage, ModelEval};
use rayon::prelude::*;

const BATCH: usize = 4096;

fn stage_for(kind: &str, d: u32, model: &Model, rng: &mut Rng) -> Stage {
    match kind {
        "bezier" => common::near_identity_bezier(model, rng, d, 0.05),
        "rational" => common::rational_fixed(model, rng, d),
        _ => common::monotonic(model, rng, d),
    }
}

fn points(rng: &mut Rng, m: usize) -> Vec<Bary> {
    (0..BATCH)
        .map(|_| {
            let mut w = [0.0; 4];
            w[..m].copy_from_slice(&rng.open_simplex(m, 0.0));
            w
        })
        .collect()
}

fn two_threads() -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .expect("thread pool")
}

fn stages(c: &mut Criterion) {
    let pool = two_threads();
    let mut rng = Rng(1);
    let model = common::kuhn(3, 1, &mut rng);
    let ws = points(&mut rng, 4);
    for kind in ["bezier", "rational", "monotonic"] {
        let mut group = c.benchmark_group(format!("stage3d/{kind}"));
        group.throughput(Throughput::Elements(BATCH as u64));
        for d in [2u32, 3, 5] {
            let st = stage_for(kind, d, &model, &mut rng);
            let local = LocalStage::from_stage(&st, 0, model.simplex(0)).expect("valid stage");
            let us: Vec<Bary> = ws.iter().map(|w| local.eval(w)).collect();
            group.bench_with_input(BenchmarkId::new("eval/1t", d), &d, |b, _| {
                b.iter(|| ws.iter().map(|w| local.eval(black_box(w))[1]).sum::<f64>())
            });
            group.bench_with_input(BenchmarkId::new("eval/2t", d), &d, |b, _| {
                b.iter(|| {
                    pool.install(|| {
                        ws.par_iter()
                            .map(|w| local.eval(black_box(w))[1])
                            .sum::<f64>()
                    })
                })
            });
            group.bench_with_input(BenchmarkId::new("jacobian/1t", d), &d, |b, _| {
                b.iter(|| {
                    ws.iter()
                        .map(|w| local.jacobian(black_box(w)).1.map_or(0.0, |j| j[0][0]))
                        .sum::<f64>()
                })
            });
            group.bench_with_input(BenchmarkId::new("det/1t", d), &d, |b, _| {
                b.iter(|| ws.iter().map(|w| local.det(black_box(w))).sum::<f64>())
            });
            group.bench_with_input(BenchmarkId::new("inverse/1t", d), &d, |b, _| {
                b.iter(|| {
                    us.iter()
                        .map(|u| local.inverse(black_box(u)).w[1])
                        .sum::<f64>()
                })
            });
            group.bench_with_input(BenchmarkId::new("inverse/2t", d), &d, |b, _| {
                b.iter(|| {
                    pool.install(|| {
                        us.par_iter()
                            .map(|u| local.inverse(black_box(u)).w[1])
                            .sum::<f64>()
                    })
                })
            });
        }
        group.finish();
    }
}

fn location(c: &mut Criterion) {
    let pool = two_threads();
    let mut rng = Rng(2);
    let model = common::kuhn(3, 55, &mut rng);
    assert_eq!(model.num_simplices(), 55 * 55 * 55 * 6);
    let mut group = c.benchmark_group("model3d_998250_tets");
    group.sample_size(10);
    group.bench_function("build", |b| {
        b.iter(|| {
            ModelEval::new(black_box(&model))
                .expect("valid model")
                .num_simplices()
        })
    });
    let eval = ModelEval::new(&model).expect("valid model");
    let pts: Vec<f64> = (0..BATCH * 3).map(|_| rng.uniform(0.0, 55.0)).collect();
    group.throughput(Throughput::Elements(BATCH as u64));
    group.bench_function("locate/1t", |b| {
        b.iter(|| {
            pts.chunks_exact(3)
                .filter_map(|p| eval.locate(black_box(p)))
                .map(|l| l.simplex)
                .sum::<usize>()
        })
    });
    group.bench_function("locate/2t", |b| {
        b.iter(|| {
            pool.install(|| {
                eval.locate_many(black_box(&pts))
                    .iter()
                    .flatten()
                    .map(|l| l.simplex)
                    .sum::<usize>()
            })
        })
    });
    group.bench_function("value/1t", |b| {
        b.iter(|| {
            pts.chunks_exact(3)
                .filter_map(|p| eval.value(black_box(p)))
                .sum::<f64>()
        })
    });
    group.finish();
}

criterion_group!(benches, stages, location);
criterion_main!(benches);
