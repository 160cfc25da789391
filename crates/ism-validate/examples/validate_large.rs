//! Validates `ism_examples::large_stratified_model` (a Kuhn grid with a stratified stage on every
//! face) and prints the time per layer: the scale check of the validator.
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
    let options = ism_validate::Options {
        threads,
        ..Default::default()
    };
    let start = std::time::Instant::now();
    let report = ism_validate::validate(&model, &options);
    let total = start.elapsed().as_secs_f64();
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
        "{} simplices, {} stages (built in {built:.2} s): {} in {total:.2} s — structure {:.2} s, invariance {:.2} s, positivity {:.2} s\n  {}",
        report.model.simplices,
        report.model.stages,
        report.verdict.as_str(),
        report.timing.structure,
        report.timing.invariance,
        report.timing.positivity,
        certificates.join("\n  ")
    );
}
