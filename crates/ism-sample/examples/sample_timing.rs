//! Times the surface table, surface sampling and volume sampling of a model file.
//!
//! `cargo run --release -p ism-sample --example sample_timing -- MODEL [SURFACE_COUNT] [VOLUME_COUNT] [EXPECTED]`

use std::time::Instant;

use ism_sample::{Region, Sampler, Sink};

/// Counts rows without storing them.
struct Count(u64);

impl Sink for Count {
    fn begin(&mut self, _: &ism_sample::Header) -> ism_sample::Result<()> {
        Ok(())
    }
    fn block(&mut self, b: &ism_sample::SampleBlock) -> ism_sample::Result<()> {
        self.0 += b.simplices.len() as u64;
        Ok(())
    }
    fn finish(&mut self) -> ism_sample::Result<()> {
        Ok(())
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let model = ism_format::io::read_path(&args[1])?.model;
    let surface: u64 = args.get(2).map_or(Ok(100_000), |s| s.parse())?;
    let volume: u64 = args.get(3).map_or(Ok(100_000), |s| s.parse())?;
    let t = Instant::now();
    // As `ism sample --surface N` does: the table's refinement is sized for N samples (or for
    // the fourth argument's count, to time a table apart from its samples).
    let expected: u64 = args.get(4).map_or(Ok(surface), |s| s.parse())?;
    let sampler = Sampler::new(&model)?
        .seed(1)
        .expected_surface_samples(expected);
    let table = sampler.surface_table()?;
    let build = t.elapsed().as_secs_f64();
    println!(
        "model: {} simplices, {} patches; table {build:.3}s; linear area {:.4}, bounded area {:.4}",
        model.num_simplices(),
        table.len(),
        table.linear_area,
        table.bounded_area
    );
    let t = Instant::now();
    let mut c = Count(0);
    sampler.surface(surface, &mut c)?;
    let s = t.elapsed().as_secs_f64();
    println!(
        "surface: {} samples in {s:.3}s = {:.0}/s",
        c.0,
        c.0 as f64 / s
    );
    let t = Instant::now();
    let mut c = Count(0);
    sampler.volume(volume, Region::Complex, &mut c)?;
    let s = t.elapsed().as_secs_f64();
    println!(
        "volume: {} samples in {s:.3}s = {:.0}/s",
        c.0,
        c.0 as f64 / s
    );
    Ok(())
}
