//! Linear isocomplex error of a preset on uniform grids: `cargo run --release -p ism-fit --example baseline -- NAME R...`.
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let preset = ism_fit::Preset::find(&args[1])?;
    let g = preset.expression()?;
    for r in &args[2..] {
        let (cells, stored, err) = ism_fit::fit::linear_baseline(&g, preset.domain, r.parse()?);
        println!("R={r} simplices={cells} stored={stored} max={err:.3e}");
    }
    Ok(())
}
