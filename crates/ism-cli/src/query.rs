//! `ism query`: F, its sign and gradient at given points (glue over `ism_sample`).

use std::io::Read;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use ism_sample::{points, Sampler};

use crate::sample::{choose_format, write_output, OutputArgs};

const AFTER_HELP: &str = "\
Input points: CSV or whitespace-separated text, n numbers per line (a header line may name the
columns x,y[,z]), or an NPY array of shape (N, n) of float64/float32 (or a structured array with
fields x, y[, z]); the format is detected from the content. \"-\" reads standard input.

Output columns: x y [z] simplex f sign gx gy [gz]
  simplex  containing top simplex, -1 outside |K|
  f        F(p), NaN outside |K|
  sign     sign of F - c: -1 inside, 1 outside, 0 on the level or outside |K|
  g*       ∇F(p), NaN outside |K|

Examples:
  ism query sphere.ism.json points.csv
  printf '0 0 0\\n0.5 0.5 0.5\\n' | ism query sphere.ism.json -
  ism query sphere.ism.json points.npy -o values.npy

Exit status: 0 success; 2 unreadable model or points, bad arguments or a failed write.";

/// Arguments of `ism query`.
#[derive(clap::Args)]
#[command(after_help = AFTER_HELP)]
pub struct Args {
    /// The model file (any encoding).
    model: PathBuf,
    /// The points (CSV/text or NPY; "-" for standard input).
    points: PathBuf,
    #[command(flatten)]
    out: OutputArgs,
    #[command(flatten)]
    limits: crate::args::ReadLimits,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let progress = crate::progress::Progress::new(args.out.quiet);
    progress.phase(format!("reading {}", args.model.display()));
    let doc = args.limits.read_indexed(&args.model)?;
    let model = doc.model;
    progress.phase(format!("reading points from {}", args.points.display()));
    let bytes = if args.points.as_os_str() == "-" {
        let mut buf = Vec::new();
        std::io::stdin()
            .read_to_end(&mut buf)
            .context("cannot read standard input")?;
        buf
    } else {
        std::fs::read(&args.points)
            .with_context(|| format!("cannot read {}", args.points.display()))?
    };
    let pts = points::parse_points(&bytes, model.dim())
        .with_context(|| format!("cannot read points from {}", args.points.display()))?;
    let format = choose_format(args.out.format, args.out.output.as_deref())?;
    crate::sample::refuse_binary_on_terminal(format, args.out.output.as_deref())?;
    progress.phase("preparing the model's stages for evaluation");
    let mut sampler = Sampler::from_indexed(&model)?;
    let counter = progress.counted(
        "evaluating",
        (pts.len() / model.dim().max(1)) as u64,
        "points",
    );
    sampler = sampler.progress(move |done| counter.set(done));
    // The calling thread is one of the pool's threads (`-j 1` starts none), as in `ism sample`:
    // the parallel loop starts here instead of being handed to a worker and waited for.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.out.threads.count())
        .use_current_thread()
        .build()?;
    pool.install(|| {
        write_output(args.out.output.as_deref(), format, |sink| {
            sampler.query(&pts, sink)
        })
    })?;
    progress.finish();
    Ok(ExitCode::SUCCESS)
}
