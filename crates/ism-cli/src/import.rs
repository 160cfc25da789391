//! `ism import`: a simplicial mesh with a point scalar field → a linear ISM; glue over
//! `ism_export::import`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use ism_export::import::{import_path, ImportOptions};
use ism_format::{io, Encoding};

const AFTER_HELP: &str = "\
Reads .vtu (VTK XML: ASCII, inline binary or appended arrays, uncompressed or compressed with zlib,
LZ4 or LZMA, as meshio and VTK write them), .vtk (legacy ASCII) or .msh (Gmsh 4.1 ASCII).
Tetrahedra give a 3D model, otherwise triangles give a 2D one (planar in z). Quadratic cells keep
their corner nodes. Cells are re-oriented positively. The values come from --field (default: the
active or first scalar point array); a value equal to --level is refused. The model has no stage.

Examples:
  ism import ball.vtu ball.ism.json --field distance
  ism import part.msh part.ismb --field phi --level 0.5

Exit status: 0 on success, 2 when the mesh cannot be read or converted or the output cannot be
written.";

/// Arguments of `ism import`.
#[derive(clap::Args)]
#[command(after_help = AFTER_HELP)]
pub struct Args {
    /// Input mesh: .vtu, .vtk or .msh.
    input: PathBuf,
    /// Output model (.ism.json, .ism.msgpack, .ismb, .ismc, .ismz or .isms).
    output: PathBuf,
    /// Name of the point field giving the vertex values.
    #[arg(long)]
    field: Option<String>,
    /// The level c of the shape F = c.
    #[arg(long, default_value_t = 0.0)]
    level: f64,
    /// No progress display.
    #[arg(long, short)]
    quiet: bool,
    // The mesh file's bytes, its points and cells are checked against these before anything is
    // built (the stage and record limits do not apply to a mesh).
    #[command(flatten)]
    limits: crate::args::MeshLimits,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let options = ImportOptions {
        field: args.field.clone(),
        level: args.level,
        limits: args.limits.limits(),
    };
    let progress = crate::progress::Progress::new(args.quiet);
    progress.phase(format!(
        "reading {} and orienting its simplices",
        args.input.display()
    ));
    let (mut model, report) = import_path(&args.input, &options)
        .with_context(|| format!("cannot import {}", args.input.display()))?;
    model.metadata.name = args
        .input
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned());
    let encoding = Encoding::from_path(&args.output).with_context(|| {
        format!(
            "cannot tell the encoding of {}: use .ism.json, .ism.msgpack, .ismb, .ismc, .ismz or .isms",
            args.output.display()
        )
    })?;
    progress.phase(format!("writing {}", args.output.display()));
    io::write_path(
        &model,
        &args.output,
        Some(encoding),
        io::WriteOptions::default(),
    )
    .map_err(|e| crate::args::cannot_write_model(&args.output, e))?;
    progress.finish();
    eprintln!(
        "{} -> {}: dimension {}, {} vertices, {} simplices ({} re-oriented), values from {:?}, {} unused nodes dropped",
        args.input.display(),
        args.output.display(),
        model.dimension,
        model.num_vertices(),
        model.num_simplices(),
        report.reoriented,
        report.field,
        report.dropped_nodes
    );
    Ok(ExitCode::SUCCESS)
}
