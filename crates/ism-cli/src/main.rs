//! `ism`: the command-line front end of the ISM libraries. Each subcommand is one module of glue.

use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod args;
mod convert;
mod export;
mod fit;
mod hermite;
mod import;
mod info;
mod progress;
mod query;
mod sample;
mod smooth;
mod validate;

const AFTER_HELP: &str = "\
Exit status:
  0  success (for `validate`: every stage certified)
  1  `validate` found an invalid or undetermined element; `info` read a structurally invalid
     model; `fit`, `smooth`, `export`: the result falls short (see each command's help)
  2  unreadable input, bad arguments, or a failed write

Examples:
  ism info spec/examples/circle-curved.ism.json
  ism convert spec/examples/sphere.ism.json sphere.ismb
  ism validate spec/examples/*.ism.json
  ism export spec/examples/sphere.ism.json sphere.glb --tolerance 1e-3";

/// Iso-Simplicial Models: read, validate, convert, export, sample and fit curved simplicial shapes.
#[derive(Parser)]
#[command(name = "ism", version, about, after_help = AFTER_HELP, propagate_version = true)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Summarize a model: dimension, counts, stages, bounding box, encoding, checksum.
    Info(info::Args),
    /// Re-encode a model (JSON, MessagePack, binary), bit-exact.
    Convert(convert::Args),
    /// Check structure, invariance and certified positivity of every stage.
    Validate(validate::Args),
    /// Extract the curved shape and write OBJ, glTF (.gltf/.glb) or VTK (.vtk/.vtu).
    Export(export::Args),
    /// Turn a simplicial mesh with a point scalar field (.vtu/.vtk/.msh) into a linear ISM.
    Import(import::Args),
    /// Sample points on, near or around the shape (PLY, CSV, NPY).
    Sample(sample::Args),
    /// Evaluate F, its sign and gradient at given points.
    Query(query::Args),
    /// Build an ISM by adaptive fitting: an expression or preset, a closed triangle mesh, or Hermite
    /// data.
    Fit(fit::Args),
    /// Reduce the normal jumps of the shape across facets (Mello & Velho 2009, §8).
    Smooth(smooth::Args),
}

/// `ism info … | head` closes stdout early; `println!` then panics. Treat that like the conventional
/// SIGPIPE exit (quiet, status 141) instead of a crash report; every other panic keeps the default hook.
fn quiet_broken_pipe() {
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let text = info
            .payload()
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| info.payload().downcast_ref::<&str>().copied())
            .unwrap_or("");
        if text.contains("failed printing to stdout") && text.contains("Broken pipe") {
            std::process::exit(141);
        }
        default(info);
    }));
}

fn main() -> ExitCode {
    quiet_broken_pipe();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Info(args) => info::run(args),
        Command::Convert(args) => convert::run(args),
        Command::Validate(args) => validate::run(args),
        Command::Export(args) => export::run(args),
        Command::Import(args) => import::run(args),
        Command::Sample(args) => sample::run(args),
        Command::Query(args) => query::run(args),
        Command::Fit(args) => fit::run(args),
        Command::Smooth(args) => smooth::run(args),
    };
    match result {
        Ok(code) => code,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::from(2)
        }
    }
}
