//! `ism convert`: re-encode a model; the numbers are carried bit for bit.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use ism_format::{io, Encoding};

const AFTER_HELP: &str = "\
The output encoding follows --to, else the output extension (.ism.json, .ism.msgpack, .ismb,
.ismc, .ismz, .isms). Compact binary (.ismc) is the binary encoding with variable-length integers;
compressed (.ismz) is the compact payload compressed by xz, the smallest (any xz decoder reads it,
e.g. Python's lzma module; writing is slower, several MB/s); structured (.isms) is the compact
encoding with face records given by the complex and control points on a lattice when they lie on
one, the smallest uncompressed.
The input encoding is detected from its content, whatever its name. The output is written to a
temporary file and renamed, so a failure leaves no partial file.

Examples:
  ism convert sphere.ism.json sphere.ismb
  ism convert sphere.ismb sphere.ism.json --pretty
  ism convert in.dat out.dat --to msgpack
  ism convert sphere.ismb sphere.ismc
  ism convert sphere.ismb sphere.ismz
  ism convert sphere.ismb sphere.isms

Exit status: 0 on success, 2 when the input is unreadable or the output cannot be written.";

/// Arguments of `ism convert`.
#[derive(clap::Args)]
#[command(after_help = AFTER_HELP)]
pub struct Args {
    /// Input model.
    input: PathBuf,
    /// Output file.
    output: PathBuf,
    /// Output encoding: json, msgpack, binary, compact, compressed or structured.
    #[arg(long)]
    to: Option<Encoding>,
    /// Indent JSON output.
    #[arg(long)]
    pretty: bool,
    /// Put JSON output inside the checksummed container.
    #[arg(long)]
    container: bool,
    /// No progress display.
    #[arg(long, short)]
    quiet: bool,
    #[command(flatten)]
    limits: crate::args::ReadLimits,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    if let Some(encoding) = args
        .to
        .or_else(|| Encoding::from_path(&args.output))
        .filter(|&e| e != Encoding::Json)
    {
        for (given, flag) in [(args.pretty, "--pretty"), (args.container, "--container")] {
            if given {
                anyhow::bail!(
                    "{flag} applies to JSON output only; {} is written as {} (always in the \
                     container, never indented)",
                    args.output.display(),
                    encoding.name()
                );
            }
        }
    }
    let progress = crate::progress::Progress::new(args.quiet);
    progress.phase(format!("reading {}", args.input.display()));
    let doc = args.limits.read(&args.input)?;
    let encoding = args
        .to
        .or_else(|| Encoding::from_path(&args.output))
        .with_context(|| {
            format!(
                "cannot tell the encoding of {}: use --to json|msgpack|binary|compact|compressed|structured",
                args.output.display()
            )
        })?;
    let options = io::WriteOptions {
        pretty: args.pretty,
        json_in_container: args.container,
    };
    progress.phase(format!("writing {}", args.output.display()));
    io::write_path(&doc.model, &args.output, Some(encoding), options)
        .map_err(|e| crate::args::cannot_write_model(&args.output, e))?;
    progress.finish();
    eprintln!(
        "{} ({}) -> {} ({})",
        args.input.display(),
        doc.encoding.name(),
        args.output.display(),
        encoding.name()
    );
    Ok(ExitCode::SUCCESS)
}
