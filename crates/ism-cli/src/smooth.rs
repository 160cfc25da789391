//! `ism smooth`: reduce the normal jumps of the shape across interior facets (glue over
//! `ism_fit::smooth`).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use ism_fit::smooth::{smooth, SmoothOptions};
use ism_format::io;

const AFTER_HELP: &str = "\
Minimizes the paper's (000 §8) sum over interior facets of |n_σ − n_σ'|² at the points of the
shape on the facet, plus alpha·|β − β₀|² (β the logits of the solitary control points), by
per-face Levenberg–Marquardt sweeps. A model whose first stages are a stratified block (as `ism
fit` writes) has that block optimized; any other model keeps its stages and gets a new stratified
block in front of them (rational weights are not optimized). Control points of edges the shape
crosses stay fixed, so the shape still crosses every edge where it did. The output is valid by
construction and checked by the validator.

Smoothing trades position for smoothness; --alpha sets the balance (fitted circle, resolution 6:
input jump max 16.3°, |g|/|∇g| max 6.7e-4; alpha 1e-3: 2.7°, 1.3e-3; alpha 0.1: 4.3°, 7.3e-4).

The normal jump is reported with the measure of `ism validate --quality` (ISM-401): per facet
the largest angle between the two sides' normals; max and mean over facets.

Examples:
  ism smooth circle.ism.json -o circle-smooth.ism.json
  ism smooth spec/examples/sphere.ism.json -o sphere-smooth.ismb --iterations 2 --json

Exit status: 0 when the output validates; 1 when it does not; 2 on unreadable input, bad
arguments or a failed write.";

/// Arguments of `ism smooth`.
#[derive(clap::Args)]
#[command(after_help = AFTER_HELP)]
pub struct Args {
    /// Input model (.ism.json, .ism.msgpack or .ismb).
    model: PathBuf,
    /// Output model.
    #[arg(short, long)]
    output: PathBuf,
    /// Gauss–Seidel sweeps over the free control points.
    #[arg(long, default_value_t = SmoothOptions::default().iterations)]
    iterations: usize,
    /// Weight of the proximity term alpha·|β − β₀|² (0: jumps only).
    #[arg(long, default_value_t = SmoothOptions::default().alpha)]
    alpha: f64,
    /// Print the report as JSON on stdout.
    #[arg(long)]
    json: bool,
}

fn stats(s: Option<ism_fit::smooth::JumpStats>) -> serde_json::Value {
    match s {
        Some(s) => serde_json::json!({"facets": s.facets, "max": s.max, "mean": s.mean}),
        None => serde_json::Value::Null,
    }
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let doc = io::read_path(&args.model)
        .with_context(|| format!("cannot read {}", args.model.display()))?;
    let options = SmoothOptions {
        iterations: args.iterations,
        alpha: args.alpha,
    };
    let smoothed = smooth(&doc.model, &options)?;
    io::write_path(
        &smoothed.model,
        &args.output,
        None,
        io::WriteOptions::default(),
    )
    .with_context(|| format!("cannot write {}", args.output.display()))?;
    let verdict =
        ism_validate::validate(&smoothed.model, &ism_validate::Options::default()).verdict;
    let r = &smoothed.report;
    if args.json {
        let value = serde_json::json!({
            "before": stats(r.before),
            "after": stats(r.after),
            "objectiveBefore": r.objective_before,
            "objectiveAfter": r.objective_after,
            "sweeps": r.sweeps,
            "facets": r.facets,
            "samples": r.samples,
            "freeFaces": r.free_faces,
            "blockAdded": r.block_added,
            "verdict": verdict.as_str(),
            "seconds": r.seconds,
        });
        println!("{value}");
    } else {
        let show = |s: Option<ism_fit::smooth::JumpStats>| match s {
            Some(s) => format!(
                "max {:.3}°, mean {:.3}° over {} facets",
                s.max, s.mean, s.facets
            ),
            None => "not measured (a stage is not certified)".to_string(),
        };
        println!("wrote {}", args.output.display());
        println!("  normal jump (ISM-401) before  {}", show(r.before));
        println!("  normal jump (ISM-401) after   {}", show(r.after));
        println!(
            "  objective        {:.4e} -> {:.4e} ({} samples, {} free control points{})",
            r.objective_before,
            r.objective_after,
            r.samples,
            r.free_faces,
            if r.block_added {
                ", new stratified block in front of the input's stages"
            } else {
                ""
            }
        );
        println!("  time             {:.2} s", r.seconds);
        println!("  validate         {}", verdict.as_str());
    }
    Ok(if verdict == ism_validate::Verdict::Valid {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}
