//! What the rational weights add on a fixed complex (BENCHMARKS.md, section fit): each preset is
//! fitted with the refinement switched off (the tolerance never binds), once with the stratified
//! points only and once with the rational weights as well, on the same complex.
//!
//! `cargo run --release -p ism-fit --example weights [-- NAME RES ...]`
use ism_fit::{fit, FitOptions, Preset};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let cases: Vec<(String, usize)> = if args.is_empty() {
        vec![
            ("circle".into(), 6),
            ("taubin".into(), 10),
            ("sphere".into(), 6),
            ("torus".into(), 8),
        ]
    } else {
        args.chunks(2)
            .map(|c| {
                (
                    c[0].clone(),
                    c.get(1).and_then(|r| r.parse().ok()).unwrap_or(8),
                )
            })
            .collect()
    };
    println!("| shape | complex | map | simplices | stage parameters | stored numbers | max abs(g)/grad | mean | fit time |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for (name, res) in cases {
        let preset = Preset::find(&name)?;
        let g = preset.expression()?;
        for rational in [false, true] {
            let mut options = FitOptions::new(preset.domain);
            options.resolution = res;
            options.tolerance = f64::MAX;
            options.rational = rational;
            let r = fit(&g, &options, &ism_format::Progress::none())?.report;
            println!(
                "| {name} | Kuhn {res} + PV | {} | {} | {} | {} | {:.2e} | {:.2e} | {:.1} s |",
                if rational {
                    "strata + rational weights"
                } else {
                    "strata"
                },
                r.simplices,
                r.parameters,
                r.stored_numbers,
                r.max_distance,
                r.mean_distance,
                r.seconds
            );
        }
    }
    Ok(())
}
