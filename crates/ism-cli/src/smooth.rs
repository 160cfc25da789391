//! `ism smooth`: reduce the normal jumps of the shape across interior facets (glue over
//! `ism_fit::smooth`, and `ism_fit::c1` with `--rational`).

use std::path::PathBuf;
use std::process::ExitCode;

use ism_fit::c1::{smooth_rational_with_progress, C1Error, C1Report};
use ism_fit::smooth::{smooth_with_progress, Mode};
use ism_format::io;

const AFTER_HELP: &str = "\
Minimizes Mello & Velho's (2009, §8) sum over interior facets of |n_σ − n_σ'|² at the points of the
shape on the facet, plus alpha·|β − β₀|² (β the logits of the solitary control points), by
per-face Levenberg–Marquardt sweeps. A model whose first stages are a stratified block (as `ism
fit` writes) has that block optimized; any other model keeps its stages and gets a new stratified
block in front of them (rational weights are not optimized here: see --rational). Control points
of edges the shape crosses stay fixed, so the shape still crosses every edge where it did. The
output is valid by construction and checked by the validator.

Smoothing trades position for smoothness; --alpha sets the balance (fitted circle, resolution 6:
input jump max 16.3°, |g|/|∇g| max 6.7e-4; alpha 1e-3: 2.7°, 1.3e-3; alpha 0.1: 4.3°, 7.3e-4).

With --rational (Mello & Velho 2009, §8, Thm. 8.1, eq. (6)): the input must be a linear isocomplex (no stage) or
have one implicit rational stage with every control point fixed. The output has one rational stage
of degree --degree (default: the input stage's, or the dimension n as in the paper) with fixed
control points and weights q = exp(β), |β| ≤ 4, fitted by sparse Levenberg–Marquardt to minimize
the C¹ residual of eq. (6) (ISM-402) over the interior facets the shape crosses, plus
alpha·Σ(β − β̄)² (β̄ the mean log-weight: the residual is scale-free, the penalty keeps the
weights' spread small). --iterations counts Levenberg–Marquardt steps there (default 100), and
--alpha defaults to 1e-4. Positive weights with fixed points are a diffeomorphism (Thm. 6.4), so
the output is valid by construction. Reported: ISM-402 relative residual and ISM-401 normal jump
(max, mean over crossed facets) before and after. Any positive weights move the shape's crossings
along the edges, so the shape moves too (spec/examples/circle-linear.ism.json: ISM-402 max 0.52 ->
0.017, normal jump max 36.9° -> 2.5°, mean 20.0° -> 1.1°).

The normal jump is reported with the measure of `ism validate --quality` (ISM-401): per facet
the largest angle between the two sides' normals; max and mean over facets.

Examples:
  ism smooth circle.ism.json -o circle-smooth.ism.json
  ism smooth spec/examples/sphere.ism.json -o sphere-smooth.ismb --iterations 2 --json
  ism smooth spec/examples/circle-linear.ism.json -o circle-c1.ism.json --rational
  ism smooth linear-sphere.ism.json -o sphere-c1.ismb --rational --degree 4 --alpha 1e-3 --json

Exit status: 0 when the output validates; 1 when it does not; 2 on unreadable input, bad
arguments, an input --rational refuses (other stages, moved control points) or a failed write.";

/// Arguments of `ism smooth`.
#[derive(clap::Args)]
#[command(after_help = AFTER_HELP)]
pub struct Args {
    /// Input model (.ism.json, .ism.msgpack, .ismb, .ismc, .ismz or .isms).
    model: PathBuf,
    /// Output model.
    #[arg(short, long)]
    output: PathBuf,
    /// Gauss–Seidel sweeps over the free control points [default: 4; with --rational:
    /// Levenberg–Marquardt steps, default 100].
    #[arg(long)]
    iterations: Option<usize>,
    /// Weight of the proximity term alpha·|β − β₀|² (0: jumps only) [default: 1e-3; with
    /// --rational: of the spread penalty alpha·Σ(β − β̄)², default 1e-4].
    #[arg(long, value_parser = crate::args::non_negative, allow_hyphen_values = true)]
    alpha: Option<f64>,
    /// Fit the weights of a rational stage with fixed control points to the C¹ condition of
    /// Mello & Velho 2009, Thm. 8.1 instead (input: no stage, or one such rational stage).
    #[arg(long)]
    rational: bool,
    /// Degree of the rational stage (with --rational) [default: the input stage's, or n].
    #[arg(long, requires = "rational")]
    degree: Option<u32>,
    /// Print the report as JSON on stdout.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    threads: crate::args::Threads,
    /// No progress display.
    #[arg(long, short)]
    quiet: bool,
    #[command(flatten)]
    limits: crate::args::ReadLimits,
}

fn show_jumps(s: Option<ism_fit::smooth::JumpStats>) -> String {
    match s {
        Some(s) => format!(
            "max {:.3}°, mean {:.3}° over {} facets",
            s.max, s.mean, s.facets
        ),
        None => "not measured (a stage is not certified)".to_string(),
    }
}

fn print_rational(r: &C1Report, output: &std::path::Path, verdict: &str, json: bool) {
    if json {
        let value = r.to_json(verdict);
        println!("{value}");
        return;
    }
    let res = |s: ism_fit::c1::ResidualStats| {
        format!(
            "max {:.3e}, mean {:.3e} over {} facets",
            s.max, s.mean, s.facets
        )
    };
    println!("wrote {}", output.display());
    println!("  C¹ residual (ISM-402) before  {}", res(r.residual_before));
    println!("  C¹ residual (ISM-402) after   {}", res(r.residual_after));
    println!(
        "  normal jump (ISM-401) before  {}",
        show_jumps(r.jumps_before)
    );
    println!(
        "  normal jump (ISM-401) after   {}",
        show_jumps(r.jumps_after)
    );
    println!(
        "  objective        {:.4e} -> {:.4e} ({} steps, {} weights in {} groups, {} conditions)",
        r.objective_before,
        r.objective_after,
        r.steps.len(),
        r.weights,
        r.groups,
        r.conditions
    );
    println!(
        "  stage            rational degree {}, {} records, weights in [{:.4}, {:.4}], alpha {:e}",
        r.degree, r.records, r.weight_range[0], r.weight_range[1], r.alpha
    );
    println!(
        "  time             {:.2} s ({:.2} s fitting, the rest measuring ISM-401)",
        r.seconds, r.fit_seconds
    );
    println!("  validate         {verdict}");
}

fn write_and_validate(
    model: &ism_format::Model,
    output: &std::path::Path,
    progress: &crate::progress::Progress,
) -> anyhow::Result<ism_validate::Verdict> {
    progress.phase(format!("writing {}", output.display()));
    io::write_path(model, output, None, io::WriteOptions::default())
        .map_err(|e| crate::args::cannot_write_model(output, e))?;
    progress.phase("validating the output");
    let verdict = ism_validate::validate(model, &ism_validate::Options::default()).verdict;
    progress.finish();
    Ok(verdict)
}

fn exit(verdict: ism_validate::Verdict) -> ExitCode {
    if verdict == ism_validate::Verdict::Valid {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    }
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    args.threads.install()?;
    let progress = crate::progress::Progress::new(args.quiet);
    progress.phase(format!("reading {}", args.model.display()));
    let doc = args.limits.read(&args.model)?;
    let options = match Mode::new(args.iterations, args.alpha, args.rational, args.degree)? {
        Mode::Rational(options) => options,
        Mode::Jumps(options) => {
            progress.phase(format!(
                "smoothing: {} sweeps over the free control points, measuring the normal jumps",
                options.iterations
            ));
            let smoothed = smooth_with_progress(&doc.model, &options, &progress.hook(|_| "faces"))?;
            return finish_jumps(&args, smoothed, &progress);
        }
    };
    progress.phase(
        "fitting the rational weights to the C¹ condition (Levenberg–Marquardt), measuring the \
         normal jumps",
    );
    let hook = progress.hook(|_| "steps");
    let smoothed =
        smooth_rational_with_progress(&doc.model, &options, &hook).map_err(|e| match e {
            C1Error::StageCount(k) => anyhow::anyhow!(
                "--rational: {} has {k} stages, but the C¹ condition (Mello & Velho 2009, \
                 Thm. 8.1) is for a model with no stage or a single implicit rational stage with \
                 fixed control points; smooth it without --rational, or give --rational the \
                 linear model (no stage)",
                args.model.display()
            ),
            e => anyhow::Error::new(e).context("--rational"),
        })?;
    let verdict = write_and_validate(&smoothed.model, &args.output, &progress)?;
    print_rational(&smoothed.report, &args.output, verdict.as_str(), args.json);
    Ok(exit(verdict))
}

/// Writes, validates and reports a plain (normal-jump) smoothing.
fn finish_jumps(
    args: &Args,
    smoothed: ism_fit::smooth::Smoothed,
    progress: &crate::progress::Progress,
) -> anyhow::Result<ExitCode> {
    let verdict = write_and_validate(&smoothed.model, &args.output, progress)?;
    let r = &smoothed.report;
    if args.json {
        let value = r.to_json(verdict.as_str());
        println!("{value}");
    } else {
        let show = show_jumps;
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
    Ok(exit(verdict))
}
