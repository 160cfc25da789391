//! Validates `ism_examples::large_stratified_model` (a Kuhn grid with a stratified stage on every
//! face) and prints the wall and CPU time of the structural check, indexing and every layer, and
//! the time per layer: the scale check of the validator. THREADS 0 (default) uses every core.
//!
//! ```text
//! cargo run --release -p ism-validate --example validate_large -- 1000000 [threads]
//! ```

fn main() {
    let target: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(1_000_000);
    let threads: usize = std::env::args()
        .nth(2)
        .and_then(|a| a.parse().ok())
        .unwrap_or(0);
    let start = std::time::Instant::now();
    let model = ism_examples::large_stratified_model(target);
    let built = start.elapsed().as_secs_f64();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("a thread pool");
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    let (start, cpu0) = (std::time::Instant::now(), cpu());
    // The structural check indexes the model once (moved in, not copied); then every layer.
    let (indexed, report) = pool.install(|| {
        let indexed = ism_format::IndexedModel::new(model).expect("a valid model");
        let report = ism_validate::validate_indexed(&indexed, &ism_validate::Options::default());
        (indexed, report)
    });
    let (total, cpu_total) = (start.elapsed().as_secs_f64(), cpu() - cpu0);
    drop(indexed);
    let certificates: Vec<String> = report
        .stages
        .iter()
        .map(|s| {
            format!(
                "stage {} ({} d={}): {:?}",
                s.index, s.kind, s.degree, s.certificates
            )
        })
        .collect();
    println!(
        "{} simplices, {} stages (built in {built:.2} s), {} threads, load {}: {} in {total:.2} s wall, {cpu_total:.2} CPU-s (check + index {:.2} s; structure {:.2} s, invariance {:.2} s, positivity {:.2} s)\n  {}",
        report.model.simplices,
        report.model.stages,
        pool.current_num_threads(),
        load.split_whitespace().next().unwrap_or("?"),
        report.verdict.as_str(),
        total - report.timing.structure - report.timing.invariance - report.timing.positivity,
        report.timing.structure,
        report.timing.invariance,
        report.timing.positivity,
        certificates.join("\n  ")
    );
}

#[path = "support/cpu.rs"]
mod support;
use support::cpu;
