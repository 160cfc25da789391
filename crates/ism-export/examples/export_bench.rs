//! Extraction benchmark on the ≥ 1,000,000-tetrahedron stratified sphere of `ism-examples`:
//! curved extraction (at a tolerance) or marching tetrahedra, on a given number of threads.
//! Prints one JSON line: triangles, seconds (with the part spent building the `ModelEval`:
//! spatial index, stage lookups), triangles per second with and without that part, and peak
//! resident memory (`VmHWM`, Linux) before and after the extraction. Run through `tools/bench_export.sh`.
//!
//! `cargo run --release -p ism-export --example export_bench -- TETS curved|marching TOL THREADS`

use std::time::Instant;

use ism_export::extract::{extract, ExtractOptions};
use ism_export::marching::marching;
use ism_geom::ModelEval;

/// Peak resident set size in KiB from `/proc/self/status` (0 where unavailable).
fn peak_rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
        })
        .unwrap_or(0)
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage = "usage: export_bench TETS curved|marching TOLERANCE THREADS";
    let [tets, mode, tol, threads] = &args[..] else {
        panic!("{usage}")
    };
    let tets: usize = tets.parse().expect(usage);
    let tolerance: f64 = tol.parse().expect(usage);
    let threads: usize = threads.parse().expect(usage);
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build_global()
        .expect("thread pool");
    let model = ism_examples::large_stratified_model(tets);
    let before = peak_rss_kib();
    let start = Instant::now();
    let mut setup = 0.0;
    let (triangles, extra) = match mode.as_str() {
        "curved" => {
            let eval = ModelEval::new(&model).expect("valid model");
            setup = start.elapsed().as_secs_f64();
            let (mesh, report) = extract(
                &eval,
                &ExtractOptions {
                    tolerance,
                    max_depth: 12,
                },
            )
            .expect("extraction");
            let t = mesh.topology();
            assert!(
                t.is_closed_oriented_manifold() && t.euler_characteristic == 2,
                "{t:?}"
            );
            (
                mesh.num_cells(),
                format!(
                    r#","crossed":{},"inversions":{},"max_residual":{:e}"#,
                    report.crossed_simplices, report.inversions, report.max_residual
                ),
            )
        }
        "marching" => {
            let mesh = marching(&model).expect("marching");
            (mesh.num_cells(), String::new())
        }
        _ => panic!("{usage}"),
    };
    let seconds = start.elapsed().as_secs_f64();
    println!(
        r#"{{"mode":"{mode}","tets":{},"tolerance":{tolerance},"threads":{threads},"triangles":{triangles},"seconds":{seconds:.4},"evaluator_seconds":{setup:.4},"triangles_per_second":{:.0},"triangles_per_second_after_evaluator":{:.0},"peak_rss_mib_before":{:.0},"peak_rss_mib":{:.0}{extra}}}"#,
        model.num_simplices(),
        triangles as f64 / seconds,
        triangles as f64 / (seconds - setup),
        before as f64 / 1024.0,
        peak_rss_kib() as f64 / 1024.0
    );
}
