//! Placeholder until this subcommand's library lands.

use std::process::ExitCode;

/// Arguments.
#[derive(clap::Args)]
pub struct Args {
    /// Input files.
    files: Vec<std::path::PathBuf>,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let _ = args.files;
    anyhow::bail!("this subcommand is not implemented yet")
}
