//! Single-threaded throughput probe for a shared machine: runs one operation many times so that
//! its cost can be read from the process's USER CPU time (`/usr/bin/time -f %U`), which other
//! processes' load does not inflate the way wall-clock time is.
//!
//! `cargo run --release -p ism-geom --example throughput -- <bezier|rational|monotonic> <degree> <eval|jacobian|inverse> <millions>`
//! `cargo run --release -p ism-geom --example throughput -- locate <cubes per side> - <millions>`

#[path = "../tests/common/mod.rs"]
mod common;

use std::hint::black_box;

use common::Rng;
use ism_geom::{Bary, LocalStage};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() != 5 {
        eprintln!("usage: throughput <bezier|rational|monotonic> <degree> <eval|jacobian|inverse> <millions>");
        std::process::exit(2);
    }
    let degree: u32 = args[2].parse().unwrap_or(3);
    let millions: f64 = args[4].parse().unwrap_or(1.0);
    if args[1] == "locate" {
        locate(args[2].parse().unwrap_or(55), millions);
        return;
    }
    let mut rng = Rng(1);
    let model = common::kuhn(3, 1, &mut rng);
    let stage = match args[1].as_str() {
        "bezier" => common::near_identity_bezier(&model, &mut rng, degree, 0.05),
        "rational" => common::rational_fixed(&model, &mut rng, degree),
        _ => common::monotonic(&model, &mut rng, degree),
    };
    let local = LocalStage::from_stage(&stage, 0, model.simplex(0)).expect("valid stage");
    let ws: Vec<Bary> = (0..4096)
        .map(|_| {
            let mut w = [0.0; 4];
            w.copy_from_slice(&rng.open_simplex(4, 0.0));
            w
        })
        .collect();
    let us: Vec<Bary> = ws.iter().map(|w| local.eval(w)).collect();
    let total = (millions * 1e6) as usize;
    let start = std::time::Instant::now();
    let mut acc = 0.0;
    let mut iterations = 0u64;
    for k in 0..total {
        let i = k % ws.len();
        acc += match args[3].as_str() {
            "eval" => local.eval(black_box(&ws[i]))[1],
            "jacobian" => local.jacobian(black_box(&ws[i])).1.map_or(0.0, |j| j[0][0]),
            _ => {
                let r = local.inverse(black_box(&us[i]));
                iterations += u64::from(r.iterations);
                r.w[1]
            }
        };
    }
    let wall = start.elapsed().as_secs_f64();
    println!(
        "{} d={} {}: {} ops, wall {:.3}s ({:.2} M/s wall), mean Newton iterations {:.2} (checksum {acc:.3})",
        args[1],
        degree,
        args[3],
        total,
        wall,
        total as f64 / wall / 1e6,
        iterations as f64 / total as f64
    );
}

/// Builds a Kuhn grid of `k³` cubes × 6 tetrahedra and locates random points in it.
fn locate(k: usize, millions: f64) {
    let mut rng = Rng(2);
    let model = common::kuhn(3, k, &mut rng);
    let start = std::time::Instant::now();
    let eval = ism_geom::ModelEval::new(&model).expect("valid model");
    let build = start.elapsed().as_secs_f64();
    let pts: Vec<f64> = (0..3 * 65536).map(|_| rng.uniform(0.0, k as f64)).collect();
    let total = (millions * 1e6) as usize;
    let start = std::time::Instant::now();
    let mut acc = 0usize;
    for i in 0..total {
        let p = &pts[3 * (i % 65536)..3 * (i % 65536) + 3];
        acc += eval.locate(black_box(p)).map_or(0, |l| l.simplex);
    }
    let wall = start.elapsed().as_secs_f64();
    println!(
        "locate in {} tets: build {:.2}s wall, {} locations in {:.3}s wall ({:.2} M/s wall) (checksum {acc})",
        eval.num_simplices(),
        build,
        total,
        wall,
        total as f64 / wall / 1e6
    );
}
