//! Fits one preset and prints the report: `cargo run --release -p ism-fit --example fit_preset -- NAME RES TOL`.
use ism_fit::{fit, FitOptions, Preset};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let preset = Preset::find(args.get(1).map_or("circle", |s| s.as_str()))?;
    let mut options = FitOptions::new(preset.domain);
    if let Some(r) = args.get(2) {
        options.resolution = r.parse()?;
    }
    if let Some(t) = args.get(3) {
        options.tolerance = t.parse()?;
    }
    options.optimize = std::env::var("NO_OPT").is_err();
    options.topology = std::env::var("NO_PV").is_err();
    if let Ok(m) = std::env::var("MAX_SIMPLICES") {
        options.max_simplices = m.parse()?;
    }
    let g = preset.expression()?;
    let progress = ism_fit::Progress::new(|p| eprintln!("{} {} {:.3e}", p.phase, p.done, p.worst));
    let fitted = fit(&g, &options, &progress)?;
    println!("{:#?}", fitted.report);
    if let Some(svg) = args.get(4) {
        let model = ism_format::IndexedModel::for_evaluation(fitted.to_model(preset.name))?;
        std::fs::write(svg, ism_fit::svg::picture(&model, preset.name)?)?;
    }
    Ok(())
}
