//! `ism export`: extract the curved shape and write it as OBJ, glTF or VTK; glue over `ism-export`.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::Context;
use ism_export::export::{self, ExportOptions, Exported};
use ism_export::format::ExportFormat;
use ism_export::vtk::VtuCompression;

const AFTER_HELP: &str = "\
The output format follows the extension: .obj, .gltf, .glb, .vtk (legacy ASCII), .vtu (XML; its
arrays binary: appended raw, uncompressed, or zlib-compressed with --compress).
3D models give triangle meshes, 2D models polylines (OBJ `l`, glTF LINES, VTK lines). Each
patch of the linear isocomplex is refined until the chordal error is below --tolerance (model
units) or an edge is halved --max-depth times and its chord is within twice the tolerance or
twice its patch's size halved --max-depth times (30 halvings at most; edges left failing the
test are counted on the summary line and in --json), then mapped through the stage inverses,
and then coarsened: each vertex inside a patch is merged into a neighbour wherever the coarser
mesh still passes the same tests (0.6–0.8× the triangles at the same error; --no-coarsen keeps
the refined mesh, for less CPU). The error is
measured at test points (edge midpoints and quarters, triangle centroids, points aimed at the
middle where those land off it, points in stretches of an edge that the parameter crosses
fast, and points near the ends of patch edges on facets where the ends' tangents predict a
bend), not bounded: a stage that bends the shape between them (seen on --rational fits whose
weights reach the fitter's limits) can leave the mesh farther away. --volume
(.vtk/.vtu) writes the complex itself with F as a Bézier field instead of the surface: F itself
wherever the stages allow it (parametric stages, if any, before implicit ones, composed degree at
most 12: every example but two, every fitted model), as curved (rational) cells on the model's own
parametrisation (field_exact: true in --json, a rounding-level bound); otherwise degree and red
refinement of an interpolant are raised until max |F_vtk − F| is below --field-tolerance
(default: the surface tolerance times the median |∇F| of the linear interpolant on the crossed
simplices, so contouring F moves the surface by about --tolerance), the bound certified
(Bernstein bound of the exact rational form) when every stage is implicit and the composed degree
is at most 24 (above 12 only on models small enough for their exact forms), otherwise marked as
an estimate. The bound is printed and in --json.

Examples:
  ism export spec/examples/sphere.ism.json sphere.glb --tolerance 1e-3
  ism export spec/examples/torus.ismb torus.obj --tolerance 5e-4 --max-depth 10
  ism export spec/examples/torus.ismb torus-fast.glb --tolerance 1e-4 --no-coarsen
  ism export spec/examples/circle-curved.ism.json circle.vtu
  ism export spec/examples/sphere.ism.json sphere-linear.obj --linear
  ism export spec/examples/sphere.ism.json sphere-volume.vtu --volume

Exit status: 0 on success; 2 for an unreadable model, bad arguments, a failed write, a
numerical failure (a stage inversion that does not converge: the point and residual are printed;
`ism validate` tells whether the model itself is valid), or stages that fold at a point the export
places (their Jacobian determinant clearly negative: the point and the determinant are printed;
such a model is not valid, and its refinement would not end). Export never exits 1: it does not
certify validity.";

/// Arguments of `ism export`.
#[derive(clap::Args)]
#[command(after_help = AFTER_HELP)]
pub struct Args {
    /// The model (any encoding).
    input: PathBuf,
    /// Output file: .obj, .gltf, .glb, .vtk or .vtu.
    output: PathBuf,
    /// Chordal tolerance in model units.
    #[arg(long, default_value_t = 1e-3, value_parser = crate::args::positive, allow_hyphen_values = true)]
    tolerance: f64,
    /// Halvings of a patch edge after which it is halved further only while its chord is longer
    /// than twice the tolerance and than twice its patch's size halved as often (30 at most; 0:
    /// the linear patches' corners only).
    #[arg(long, default_value_t = 8)]
    max_depth: u32,
    /// Write the linear isocomplex (marching triangles/tetrahedra), ignoring the stages.
    #[arg(long, conflicts_with = "volume")]
    linear: bool,
    /// Write the complex with F as a higher-order field (VTK outputs only).
    #[arg(long)]
    volume: bool,
    /// With --volume: largest accepted |F_vtk − F| over the complex, in units of F [default: see
    /// below].
    #[arg(long, requires = "volume", value_parser = crate::args::positive, allow_hyphen_values = true)]
    field_tolerance: Option<f64>,
    /// Coarsen the curved surface after refinement (the default): vertices inside patches are
    /// merged wherever the coarser mesh still passes the refinement's tests, 0.6–0.8× the
    /// triangles at the same error.
    #[arg(long, conflicts_with_all = ["volume", "linear", "no_coarsen"])]
    coarsen: bool,
    /// Keep the refinement's mesh, not coarsened: 1.3–1.7× the triangles at the same error, for
    /// 0.65–0.9× the CPU.
    #[arg(long)]
    no_coarsen: bool,
    /// Compress the .vtu's arrays with zlib, block by block as VTK's XML writers do by default
    /// (vtkZLibDataCompressor): a smaller file, more CPU to write and read.
    #[arg(long)]
    compress: bool,
    #[command(flatten)]
    threads: crate::args::Threads,
    /// No progress display.
    #[arg(long, short)]
    quiet: bool,
    /// Print a JSON summary on stdout.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    limits: crate::args::ReadLimits,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    args.threads.install_on_calling_thread()?;
    let format = ExportFormat::from_path(&args.output).with_context(|| {
        format!(
            "cannot tell the output format of {}: use .obj, .gltf, .glb, .vtk or .vtu",
            args.output.display()
        )
    })?;
    if args.compress && format != ExportFormat::Vtu {
        anyhow::bail!(
            "--compress needs a .vtu output, not .{}",
            format.extension()
        );
    }
    if args.volume && !format.supports_volume() {
        anyhow::bail!(
            "--volume needs a VTK output (.vtk or .vtu), not .{}",
            format.extension()
        );
    }
    let progress = crate::progress::Progress::new(args.quiet);
    progress.phase(format!("reading {}", args.input.display()));
    // The same check as every reader's, but the index keeps only what the check needs: the
    // linear isocomplex looks no face record up, and the local maps look up only the records of
    // the simplices the level set crosses (`IndexedModel::simplex_records`), not the complex's
    // face tables (on the sphere example at 1e-3 those were 6 % of the export's instructions).
    let doc = args.limits.read_indexed_lazily(&args.input)?;
    let model = doc.model;
    let name = model.metadata.name.clone();
    let start = Instant::now();
    let options = ExportOptions {
        tolerance: args.tolerance,
        max_depth: args.max_depth,
        linear: args.linear,
        volume: args.volume,
        field_tolerance: args.field_tolerance,
        coarsen: if args.no_coarsen {
            Some(false)
        } else {
            args.coarsen.then_some(true)
        },
    };
    // The library reports its phases; counted ones get a labelled bar.
    let unit = |phase: &str| match phase {
        ism_export::extract::phase::FACETS => "facets",
        ism_export::extract::phase::PATCHES => "patches",
        _ => "simplices",
    };
    let built = match export::build(&model, &options, &progress.hook(unit)) {
        Ok(b) => b,
        Err(e @ ism_export::Error::Inversion { .. }) => {
            progress.finish();
            eprintln!(
                "error: numerical failure: {e}; run `ism validate` on the model to tell a \
                 numerical problem from an invalid model"
            );
            return Ok(ExitCode::from(2));
        }
        Err(e) if args.volume => return Err(e).context("cannot build the volume field"),
        Err(e) if args.linear => return Err(e).context("cannot extract the linear isocomplex"),
        Err(e) => return Err(e).context("cannot extract the shape"),
    };
    let extract_seconds = start.elapsed().as_secs_f64();
    progress.phase(format!("writing {}", args.output.display()));
    ism_format::io::write_atomic(&args.output, |w| {
        let compression = if args.compress {
            VtuCompression::Zlib
        } else {
            VtuCompression::None
        };
        built
            .write_with(format, name.as_deref(), compression, w)
            .map_err(std::io::Error::other)
    })
    .map_err(|e| crate::args::cannot_write(&args.output, &e))?;
    progress.phase("checking the mesh's topology");
    let mut summary = built.summary(&args.output, format);
    progress.finish();
    match &built {
        Exported::Volume { grid, report } => {
            // Formatted first, printed with one write (stderr is unbuffered: `eprintln!` with the
            // pieces made ~20 write calls).
            let line = format!(
                "{} -> {}: {} cells, {} control points; {}; field tolerance {:.3e} {}\n",
                args.input.display(),
                args.output.display(),
                grid.num_cells(),
                grid.points.len(),
                report.note,
                report.tolerance,
                if report.met {
                    "met"
                } else {
                    "NOT met (best bound found is written)"
                },
            );
            eprint!("{line}");
            summary["seconds"] = start.elapsed().as_secs_f64().into();
        }
        Exported::Surface { mesh, .. } => {
            let what = if mesh.dimension == 3 {
                "triangles"
            } else {
                "segments"
            };
            // Edges the refinement had to leave while their chordal test failed (`--max-depth`):
            // the export may be farther from the shape than asked there, so say so — and that the
            // test holds edges to a fraction of the tolerance (failing it is not yet exceeding it).
            // With how far they were measured from the shape (a sample of each such edge, not a
            // bound: `ExtractReport::depth_limited_error`).
            let limited = match summary["depth_limited_edges"].as_u64() {
                Some(n) if n > 0 => format!(
                    ", {n} edge{} at the depth limit (--max-depth) still failing the chordal test \
                     (which holds edges to {} of --tolerance; measured up to {:.3e} from the shape \
                     there)",
                    if n == 1 { "" } else { "s" },
                    ism_export::extract::EDGE_FRACTION,
                    summary["depth_limited_error"].as_f64().unwrap_or(f64::NAN)
                ),
                _ => String::new(),
            };
            let line = format!(
                "{} -> {}: {} vertices, {} {what}, {} components, Euler characteristic {}, {}{limited} ({:.3} s extraction)\n",
                args.input.display(),
                args.output.display(),
                mesh.num_vertices(),
                mesh.num_cells(),
                summary["components"],
                summary["euler_characteristic"],
                if summary["boundary_edges"] == 0 { "closed" } else { "with boundary" },
                extract_seconds
            );
            eprint!("{line}");
            summary["extract_seconds"] = extract_seconds.into();
        }
    }
    if args.json {
        // With its line end: stdout's line buffer then passes it on in one write, not two.
        let mut text = serde_json::to_string_pretty(&summary)?;
        text.push('\n');
        print!("{text}");
    }
    Ok(ExitCode::SUCCESS)
}
