//! `ism sample`: point sets on, near or around the shape (glue over `ism_sample`).

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{bail, Context};
use ism_format::io;
use ism_sample::{FormatWriter, OutputFormat, Region, Sampler, Sink};

const AFTER_HELP: &str = "\
Exactly one of --surface, --volume, --near-surface per run.

Columns:
  --surface        x y [z] nx ny [nz] f simplex   (uniform by true curved area/length; normal = ∇F/|∇F|)
  --volume, --near-surface
                   x y [z] f label simplex        (label 1 inside F < c, 0 outside, -1 outside |K|)
  PLY files always carry z (and nz), 0 for 2D models. NPY files hold a structured array with these
  field names (numpy: a = np.load(path); a['x']).

Examples:
  ism sample sphere.ism.json --surface 100000 -o sphere.ply
  ism sample sphere.ism.json --surface 1000 --format csv > points.csv
  ism sample sphere.ism.json --volume 50000 --seed 7 -o volume.npy
  ism sample sphere.ism.json --volume 50000 --box -1,-1,-1,1,1,1 -o box.ply --format ply-ascii
  ism sample sphere.ism.json --near-surface 50000 --sigma 0.01 -o near.csv

Exit status: 0 success; 2 unreadable model, bad arguments, a model that cannot be sampled
(empty shape, uncertified stage) or a failed write.";

/// Arguments of `ism sample`.
#[derive(clap::Args)]
#[command(after_help = AFTER_HELP)]
pub struct Args {
    /// The model file (any encoding).
    model: PathBuf,
    /// Number of points on the shape, uniform by curved area.
    #[arg(long, value_name = "N")]
    surface: Option<u64>,
    /// Number of points uniform in the complex |K| (or in --box).
    #[arg(long, value_name = "N")]
    volume: Option<u64>,
    /// Number of surface points displaced along random directions by N(0, sigma²).
    #[arg(long = "near-surface", value_name = "N", requires = "sigma")]
    near_surface: Option<u64>,
    /// Standard deviation of the --near-surface displacement (model units).
    #[arg(long, value_name = "S", value_parser = crate::args::positive, allow_hyphen_values = true)]
    sigma: Option<f64>,
    /// With --volume: sample this box instead of |K|: lo_x,lo_y,hi_x,hi_y (2D) or
    /// lo_x,lo_y,lo_z,hi_x,hi_y,hi_z (3D).
    #[arg(
        long = "box",
        value_name = "LO,HI",
        value_delimiter = ',',
        allow_hyphen_values = true
    )]
    bbox: Option<Vec<f64>>,
    /// Seed: equal seeds give bit-identical output for any thread count.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[command(flatten)]
    out: OutputArgs,
    #[command(flatten)]
    limits: crate::args::ReadLimits,
}

/// Output options shared by `ism sample` and `ism query`.
#[derive(clap::Args)]
pub(crate) struct OutputArgs {
    /// Output file (format from the extension: .ply, .csv, .npy); standard output when absent or "-".
    #[arg(short, long)]
    pub(crate) output: Option<PathBuf>,
    /// Output format: ply (binary little-endian), ply-ascii, csv, npy. Default: from the extension,
    /// csv on standard output.
    #[arg(long, value_parser = parse_format)]
    pub(crate) format: Option<OutputFormat>,
    #[command(flatten)]
    pub(crate) threads: crate::args::Threads,
    /// No progress bar.
    #[arg(long, short)]
    pub(crate) quiet: bool,
}

fn parse_format(s: &str) -> Result<OutputFormat, String> {
    OutputFormat::from_name(s)
        .ok_or_else(|| format!("unknown format {s:?}; expected ply, ply-ascii, csv or npy"))
}

/// Which set to produce.
enum Job {
    Surface(u64),
    Volume(u64, Region),
    NearSurface(u64, f64),
}

/// The output format: `--format`, else the extension, else CSV for standard output.
pub(crate) fn choose_format(
    explicit: Option<OutputFormat>,
    output: Option<&Path>,
) -> anyhow::Result<OutputFormat> {
    if let Some(f) = explicit {
        return Ok(f);
    }
    match output {
        None => Ok(OutputFormat::Csv),
        Some(p) if p.as_os_str() == "-" => Ok(OutputFormat::Csv),
        Some(p) => OutputFormat::from_path(p).with_context(|| {
            format!("cannot tell the format of {} from its extension; use --format ply|ply-ascii|csv|npy", p.display())
        }),
    }
}

/// Binary formats (NPY, binary PLY) are refused on standard output when it is a terminal.
pub(crate) fn refuse_binary_on_terminal(
    format: OutputFormat,
    output: Option<&Path>,
) -> anyhow::Result<()> {
    let to_stdout = output.is_none_or(|p| p.as_os_str() == "-");
    let binary = matches!(format, OutputFormat::Npy | OutputFormat::PlyBinary);
    if to_stdout && binary && std::io::stdout().is_terminal() {
        bail!(
            "--format {} is binary and standard output is a terminal; give -o FILE or redirect \
             standard output (csv and ply-ascii are text)",
            format.name()
        );
    }
    Ok(())
}

/// Runs `produce` into a writer of `format` at `output` (atomically) or on standard output.
pub(crate) fn write_output(
    output: Option<&Path>,
    format: OutputFormat,
    produce: impl FnOnce(&mut dyn Sink) -> ism_sample::Result<()>,
) -> anyhow::Result<()> {
    match output {
        Some(path) if path.as_os_str() != "-" => {
            let mut failure: Option<ism_sample::SampleError> = None;
            let written = io::write_atomic(path, |w| {
                let mut sink = FormatWriter::new(w, format);
                produce(&mut sink).map_err(|e| {
                    let text = ism_format::ErrorChain(&e).to_string();
                    failure = Some(e);
                    std::io::Error::other(text)
                })
            });
            match (written, failure) {
                (Ok(()), _) => Ok(()),
                (Err(_), Some(e)) => Err(e.into()),
                (Err(e), None) => Err(crate::args::cannot_write(path, &e)),
            }
        }
        _ => {
            let stdout = std::io::stdout();
            let mut sink = FormatWriter::new(std::io::BufWriter::new(stdout.lock()), format);
            produce(&mut sink)?;
            sink.into_inner()
                .flush()
                .context("cannot write to standard output")?;
            Ok(())
        }
    }
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let progress = crate::progress::Progress::new(args.out.quiet);
    progress.phase(format!("reading {}", args.model.display()));
    let doc = args.limits.read_indexed(&args.model)?;
    let model = doc.model;
    let n = model.dim();
    let mut jobs = Vec::new();
    if let Some(c) = args.surface {
        jobs.push(Job::Surface(c));
    }
    if let Some(c) = args.volume {
        let region = match &args.bbox {
            None => Region::Complex,
            Some(v) if v.len() == 2 * n => {
                let mut lo = [0.0; 3];
                let mut hi = [0.0; 3];
                lo[..n].copy_from_slice(&v[..n]);
                hi[..n].copy_from_slice(&v[n..]);
                Region::Box { lo, hi }
            }
            Some(v) => bail!(
                "--box needs {} numbers (lo then hi) for a {n}D model, got {}",
                2 * n,
                v.len()
            ),
        };
        jobs.push(Job::Volume(c, region));
    } else if args.bbox.is_some() {
        bail!("--box applies to --volume only");
    }
    if args.sigma.is_some() && args.near_surface.is_none() {
        bail!("--sigma applies to --near-surface only");
    }
    if let Some(c) = args.near_surface {
        let sigma = args.sigma.context("--near-surface needs --sigma")?;
        jobs.push(Job::NearSurface(c, sigma));
    }
    let job = match jobs.len() {
        1 => jobs.pop().expect("one job"),
        0 => bail!("nothing to sample: give --surface N, --volume N or --near-surface N --sigma S"),
        _ => bail!("give only one of --surface, --volume, --near-surface per run"),
    };
    let format = choose_format(args.out.format, args.out.output.as_deref())?;
    refuse_binary_on_terminal(format, args.out.output.as_deref())?;
    let total = match job {
        Job::Surface(c) | Job::Volume(c, _) | Job::NearSurface(c, _) => c,
    };
    progress.phase("preparing the model's stages for evaluation and inversion");
    let mut sampler = Sampler::from_indexed(&model)?.seed(args.seed);
    if matches!(job, Job::Surface(_) | Job::NearSurface(..)) {
        // The table refines its bounds as far as `total` samples pay for it.
        sampler = sampler.expected_surface_samples(total);
    }
    // The calling thread is one of the pool's threads (`-j 1` starts none): the sampler's
    // writer runs queued chunks itself while it waits (`rayon::yield_now`), so it needs no
    // worker of its own, and handing the work to one and waiting cost 3-7 % of a small model's
    // `--surface 1` (issue 19, session 36).
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.out.threads.count())
        .use_current_thread()
        .build()?;
    if matches!(job, Job::Surface(_) | Job::NearSurface(..)) {
        progress.phase("measuring the curved area of every patch of the shape");
        pool.install(|| sampler.surface_table().map(|_| ()))?;
    }
    let counter = progress.counted("sampling", total, "points");
    sampler = sampler.progress(move |done| counter.set(done));
    pool.install(|| {
        write_output(args.out.output.as_deref(), format, |sink| match job {
            Job::Surface(c) => sampler.surface(c, sink),
            Job::Volume(c, region) => sampler.volume(c, region, sink),
            Job::NearSurface(c, sigma) => sampler.near_surface(c, sigma, sink),
        })
    })?;
    progress.finish();
    Ok(ExitCode::SUCCESS)
}
