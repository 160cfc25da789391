//! `ism export` as library calls, shared by the CLI and the Python package: the options, what they
//! build (the curved surface, the linear isocomplex, or the complex with F as a Bézier field), the
//! writing, and the summary `ism export --json` prints.
//!
//! ```
//! use ism_export::export::{build, ExportOptions};
//! use ism_export::format::ExportFormat;
//! use ism_format::builder::{ModelBuilder, StageBuilder};
//! use ism_format::{IndexedModel, Progress};
//!
//! // A square of two triangles, one corner inside, with a quadratic stage bending the curve.
//! let model = ModelBuilder::new(2)
//!     .vertex(&[0.0, 0.0], -1.0)
//!     .vertex(&[1.0, 0.0], 1.0)
//!     .vertex(&[1.0, 1.0], 1.0)
//!     .vertex(&[0.0, 1.0], 1.0)
//!     .simplex(&[0, 1, 2])
//!     .simplex(&[0, 2, 3])
//!     .stage(StageBuilder::bezier(2).face(&[0, 2], &[0.7, 0.3], &[]).build())
//!     .build()?;
//! // Checked and indexed once (a file: `ism_format::io::read_path_indexed`).
//! let model = IndexedModel::new(model)?;
//! let options = ExportOptions::default();
//! let built = build(&model, &options, &Progress::none())?;
//! let mut obj = Vec::new();
//! built.write(ExportFormat::Obj, None, &mut obj)?;
//! let summary = built.summary(std::path::Path::new("x.obj"), ExportFormat::Obj);
//! assert_eq!(summary["format"], "obj");
//! let segments = summary["cells"].as_u64().unwrap();
//! // The curve was refined (more segments than its two linear ones), and the OBJ has one `l`
//! // line per segment.
//! assert!(segments > 2);
//! let text = String::from_utf8(obj)?;
//! assert_eq!(text.lines().filter(|l| l.starts_with("l ")).count() as u64, segments);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use std::io::Write;
use std::path::Path;

use ism_format::progress::Progress;
use ism_format::IndexedModel;
use ism_geom::ModelEval;

use crate::extract::{
    extract_coarsened_with_progress, extract_with_progress, ExtractOptions, ExtractReport,
    MAX_DEPTH_LIMIT,
};
use crate::format::{write_mesh_with, ExportFormat};
use crate::marching::marching;
use crate::mesh::Mesh;
use crate::volume::{
    check_dimension, default_field_tolerance, volume_grid_with_progress, VolumeOptions,
    VolumeReport,
};
use crate::vtk::{UnstructuredGrid, VtuCompression};
use crate::{Error, Result};

/// The options of `ism export`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExportOptions {
    /// Chordal tolerance of the curved surface, in model units ([`ExtractOptions::tolerance`]).
    pub tolerance: f64,
    /// Halvings of a patch edge past which only long edges are halved
    /// ([`ExtractOptions::max_depth`]).
    pub max_depth: u32,
    /// The linear isocomplex (marching simplices, stages ignored) instead of the curved shape.
    pub linear: bool,
    /// The complex itself with F as a Bézier field (VTK formats only).
    pub volume: bool,
    /// The volume field's tolerance; `None`: [`default_field_tolerance`] of `tolerance`.
    pub field_tolerance: Option<f64>,
    /// Whether the curved surface is coarsened after refinement: vertices inside patches
    /// collapsed where the coarser mesh still passes the refinement's own tests
    /// ([`crate::extract::extract_coarsened`]), 0.6–0.8× the triangles at the same true error
    /// for 1.1–1.5× the CPU (BENCHMARKS.md, issue 19). `None` (the default): yes — at equal true
    /// error the refined mesh alone has more triangles than marching cubes on a smooth closed
    /// shape (1.35× on the fitted sphere), the coarsened one fewer. `Some(false)`: the
    /// refinement's mesh (the cheaper export). Linear and volume exports have no refinement to
    /// coarsen: `Some(true)` with them is refused.
    pub coarsen: Option<bool>,
}

impl Default for ExportOptions {
    fn default() -> Self {
        let e = ExtractOptions::default();
        ExportOptions {
            tolerance: e.tolerance,
            max_depth: e.max_depth,
            linear: false,
            volume: false,
            field_tolerance: None,
            coarsen: None,
        }
    }
}

/// Phase names [`build`] reports besides those of [`crate::extract::phase`] and
/// [`crate::volume::PHASE`] (uncounted: `total` is 0).
pub mod phase {
    /// Marching simplices (`linear`).
    pub const LINEAR: &str = "extracting the linear isocomplex (marching simplices)";
    /// Building the evaluator (stage tables, inverses).
    pub const PREPARING: &str = "preparing the model's stages for evaluation and inversion";
    /// Extracting the curved shape (then counted: [`crate::extract::phase`]).
    pub const EXTRACTING: &str =
        "extracting the curved shape: refining the patches to the tolerance, inverting the stages";
    /// Choosing the volume field's default tolerance.
    pub const FIELD_TOLERANCE: &str = "choosing the field tolerance of the volume";
}

/// What [`build`] made.
#[derive(Clone, Debug)]
pub enum Exported {
    /// The curved surface (or, with `linear`, the linear isocomplex: no extraction report).
    Surface {
        /// The mesh (triangles, or segments in 2D).
        mesh: Mesh,
        /// What the curved extraction did; `None` for the linear isocomplex.
        extract: Option<ExtractReport>,
    },
    /// The complex with F as a Bézier field.
    Volume {
        /// The cells.
        grid: UnstructuredGrid,
        /// Degree, refinement and the field error bound.
        report: VolumeReport,
    },
}

/// Checks `options` against each other and against `format` (when given).
///
/// # Errors
/// [`Error::Unsupported`] naming the option: `linear` with `volume`, `volume` with a format that
/// cannot carry cells, a tolerance that is not a positive number, `max_depth` over
/// [`MAX_DEPTH_LIMIT`].
pub fn check(options: &ExportOptions, format: Option<ExportFormat>) -> Result<()> {
    let bad = |m: String| Err(Error::Unsupported(m));
    if !(options.tolerance.is_finite() && options.tolerance > 0.0) {
        return bad(format!(
            "tolerance: expected a positive number, got {}",
            options.tolerance
        ));
    }
    if options.max_depth > MAX_DEPTH_LIMIT {
        return bad(format!("max depth: at most {MAX_DEPTH_LIMIT}"));
    }
    if let Some(t) = options.field_tolerance {
        if !(t.is_finite() && t > 0.0) {
            return bad(format!(
                "field tolerance: expected a positive number, got {t}"
            ));
        }
        if !options.volume {
            return bad("a field tolerance applies to a volume export only".into());
        }
    }
    if options.volume && options.linear {
        return bad("linear and volume exclude each other".into());
    }
    if options.coarsen == Some(true) && (options.volume || options.linear) {
        return bad(
            "coarsening applies to the curved surface only, not to linear or volume".into(),
        );
    }
    if let Some(f) = format {
        if options.volume && !f.supports_volume() {
            return bad(format!(
                "volume needs a VTK output (.vtk or .vtu), not .{}",
                f.extension()
            ));
        }
    }
    Ok(())
}

/// Builds what `options` ask for (see [`Exported`]) from a checked, indexed model (its index is
/// shared by the evaluator: no copy, no second structural check), reporting to `progress` and
/// stopping when it is cancelled.
///
/// # Errors
/// As [`check`]; [`Error::Geom`] for a model the kernel cannot evaluate (its error as the
/// source); [`Error::Unsupported`] for one that cannot be extracted;
/// [`Error::Inversion`] (a numerical failure of the extraction); [`Error::Cancelled`].
pub fn build(
    model: &IndexedModel,
    options: &ExportOptions,
    progress: &Progress,
) -> Result<Exported> {
    check(options, None)?;
    progress.check()?;
    if options.volume {
        // One evaluator (inverses, spatial index) for the default tolerance and the grid.
        check_dimension(model.dim())?;
        let eval = ModelEval::from_indexed(model)?;
        let field_tolerance = match options.field_tolerance {
            Some(t) => t,
            None => {
                progress.report_count(phase::FIELD_TOLERANCE, 0, 0);
                default_field_tolerance(&eval, options.tolerance)
            }
        };
        let (grid, report) = volume_grid_with_progress(
            &eval,
            &VolumeOptions {
                field_tolerance,
                interpolate: false,
            },
            progress,
        )?;
        return Ok(Exported::Volume { grid, report });
    }
    if options.linear {
        progress.report_count(phase::LINEAR, 0, 0);
        return Ok(Exported::Surface {
            mesh: marching(model)?,
            extract: None,
        });
    }
    progress.report_count(phase::PREPARING, 0, 0);
    // Fused maps (the extraction inverts every point it places; a projective monotonic stage
    // merged into the next one halves the stages it evaluates, same map up to rounding) and no
    // spatial index (nothing is located).
    let eval = ModelEval::for_extraction(model)?;
    progress.check()?;
    progress.report_count(phase::EXTRACTING, 0, 0);
    let extract_options = ExtractOptions {
        tolerance: options.tolerance,
        max_depth: options.max_depth,
    };
    let (mesh, report) = if options.coarsen.unwrap_or(true) {
        extract_coarsened_with_progress(&eval, &extract_options, progress)?
    } else {
        extract_with_progress(&eval, &extract_options, progress)?
    };
    Ok(Exported::Surface {
        mesh,
        extract: Some(report),
    })
}

impl Exported {
    /// Writes it in `format` to `out`; `name` labels the object where the format has a place for
    /// it (a volume's legacy VTK header: "ISM volume" without one).
    ///
    /// # Errors
    /// Whatever the writer reports; [`Error::Unsupported`] for a volume in a non-VTK format.
    pub fn write<W: Write>(&self, format: ExportFormat, name: Option<&str>, out: W) -> Result<()> {
        self.write_with(format, name, VtuCompression::None, out)
    }

    /// [`Self::write`], a `.vtu`'s arrays stored as `compression` says
    /// ([`crate::vtk::UnstructuredGrid::write_vtu_with`]; the other formats ignore it).
    ///
    /// # Errors
    /// As [`Self::write`].
    pub fn write_with<W: Write>(
        &self,
        format: ExportFormat,
        name: Option<&str>,
        compression: VtuCompression,
        out: W,
    ) -> Result<()> {
        match self {
            Exported::Surface { mesh, .. } => write_mesh_with(mesh, format, name, compression, out),
            Exported::Volume { grid, .. } => match format {
                ExportFormat::Vtu => grid.write_vtu_with(out, compression),
                ExportFormat::VtkLegacy => grid.write_legacy(name.unwrap_or("ISM volume"), out),
                f => Err(Error::Unsupported(format!(
                    "volume needs a VTK output (.vtk or .vtu), not .{}",
                    f.extension()
                ))),
            },
        }
    }

    /// The members of `ism export --json` (without its timings) for output `path` in `format`.
    pub fn summary(&self, path: &Path, format: ExportFormat) -> serde_json::Value {
        let mut out = serde_json::json!({
            "output": path.display().to_string(),
            "format": format.extension(),
        });
        let more = match self {
            Exported::Volume { report, .. } => serde_json::json!({
                "cells": report.cells,
                "control_points": report.control_points,
                "degree": report.degree,
                "refinement_levels": report.level,
                "field_error_bound": report.bound,
                "field_error_bound_everywhere": report.global_bound,
                "field_error_certified": report.certified,
                "field_exact": report.exact,
                "field_tolerance": report.tolerance,
                "field_tolerance_met": report.met,
                "field_note": report.note,
            }),
            Exported::Surface { mesh, extract } => surface_summary(mesh, extract.as_ref()),
        };
        if let (Some(o), serde_json::Value::Object(m)) = (out.as_object_mut(), more) {
            o.extend(m);
        }
        out
    }
}

/// `ism export` of a model to `path`: the format from the extension, [`build`], then an atomic
/// write (nothing half-written is left on failure).
///
/// # Errors
/// [`Error::Unsupported`] for an unknown extension; as [`build`]; [`Error::Io`] (with the path)
/// when writing fails.
pub fn export_path(
    model: &IndexedModel,
    path: &Path,
    options: &ExportOptions,
    progress: &Progress,
) -> Result<(Exported, ExportFormat)> {
    let format = ExportFormat::from_path(path).ok_or_else(|| {
        Error::Unsupported(format!(
            "cannot tell the output format of {}: use .obj, .gltf, .glb, .vtk or .vtu",
            path.display()
        ))
    })?;
    check(options, Some(format))?;
    let built = build(model, options, progress)?;
    write_path(&built, format, model.metadata.name.as_deref(), path)?;
    Ok((built, format))
}

/// Writes `built` to `path` as `format` (the glTF scene named `name`), atomically: a temporary
/// file renamed into place, so a failed write leaves no file. The second half of
/// [`export_path`], for callers that decide between building and writing whether to write at all
/// (the Python package writes only once no progress callback can cancel the call any more).
///
/// # Errors
/// [`Error::Io`] naming `path` when writing fails.
pub fn write_path(
    built: &Exported,
    format: ExportFormat,
    name: Option<&str>,
    path: &Path,
) -> Result<()> {
    write_path_with(built, format, name, VtuCompression::None, path)
}

/// [`write_path`], a `.vtu`'s arrays stored as `compression` says ([`Exported::write_with`]).
///
/// # Errors
/// As [`write_path`].
pub fn write_path_with(
    built: &Exported,
    format: ExportFormat,
    name: Option<&str>,
    compression: VtuCompression,
    path: &Path,
) -> Result<()> {
    ism_format::io::write_atomic(path, |w| {
        built
            .write_with(format, name, compression, w)
            .map_err(std::io::Error::other)
    })
    .map_err(|source| Error::Io {
        path: Some(path.to_path_buf()),
        source,
    })
}

/// The members of a surface export's summary (`ism export --json`, and the report of the Python
/// package's `extract_surface`): the mesh's counts and topology, and what the curved extraction did
/// (`null` for the linear isocomplex, which needs none).
pub fn surface_summary(mesh: &Mesh, extract: Option<&ExtractReport>) -> serde_json::Value {
    let t = mesh.topology();
    serde_json::json!({
        "vertices": mesh.num_vertices(),
        "cells": mesh.num_cells(),
        "components": t.components,
        "euler_characteristic": t.euler_characteristic,
        "boundary_edges": t.boundary_edges,
        "non_manifold_edges": t.non_manifold_edges,
        "orientation_conflicts": t.orientation_conflicts,
        "degenerate_cells": t.degenerate_cells,
        "enclosed_measure": mesh.enclosed_measure(),
        "crossed_simplices": extract.map(|r| r.crossed_simplices),
        "inversions": extract.map(|r| r.inversions),
        "max_inverse_residual": extract.map(|r| r.max_residual),
        "depth_limited_edges": extract.map(|r| r.depth_limited_edges),
        "depth_limited_error": extract.map(|r| r.depth_limited_error),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use ism_format::Model;

    /// Three collinear vertices make a degenerate triangle: the kernel's error reaches the caller
    /// as the source (its simplex and determinant), not as text.
    #[test]
    fn kernel_errors_are_kept_as_the_source() {
        let mut model = Model::new(2);
        model.vertices = vec![0.0, 0.0, 1.0, 0.0, 2.0, 0.0];
        model.values = vec![-1.0, 1.0, 1.0];
        model.simplices = vec![0, 1, 2];
        // Indexed for evaluation (the reader's check would refuse it before the kernel sees it).
        let model = IndexedModel::for_evaluation(model).unwrap();
        for volume in [false, true] {
            let options = ExportOptions {
                volume,
                field_tolerance: volume.then_some(1e-3),
                ..ExportOptions::default()
            };
            let Err(err) = build(&model, &options, &Progress::none()) else {
                panic!("a degenerate simplex must not export");
            };
            let source = std::error::Error::source(&err)
                .and_then(|e| e.downcast_ref::<ism_geom::GeomError>());
            assert!(
                matches!(
                    source,
                    Some(ism_geom::GeomError::Degenerate { simplex: 0, .. })
                ),
                "volume {volume}: {err:?}"
            );
            // The kernel's message is printed once: by the chain, not by the wrapper too.
            let kernel = "simplex 0 is degenerate (edge-matrix determinant";
            assert!(!err.to_string().contains(kernel), "{err}");
            let chain = ism_format::ErrorChain(&err).to_string();
            assert_eq!(chain.matches(kernel).count(), 1, "{chain}");
            assert!(chain.starts_with("cannot evaluate the model: simplex 0 is degenerate"));
        }
    }

    /// I/O errors keep the operating system's error as their source and name it once.
    #[test]
    fn io_errors_name_their_cause_once() {
        let err = Error::Io {
            path: Some("/out/shape.obj".into()),
            source: std::io::Error::other("disk full"),
        };
        assert_eq!(err.to_string(), "/out/shape.obj: I/O error");
        assert_eq!(
            ism_format::ErrorChain(&err).to_string(),
            "/out/shape.obj: I/O error: disk full"
        );
        let cancelled = Error::from(ism_format::Cancelled);
        assert_eq!(ism_format::ErrorChain(&cancelled).to_string(), "cancelled");
    }
}
