//! The tools as methods of `ism.Model`: validate, extract, export, sample, query, smooth.
//!
//! Each is the library call the CLI makes, run through [`crate::worker::run`] (GIL released,
//! Ctrl-C honoured). Point sets are written by `ism_sample`'s own NPY writer into memory and
//! handed to numpy without a copy, so their fields, order and bits are those of
//! `ism sample -o x.npy`.

use ism_export::extract::{extract, ExtractOptions};
use ism_export::format::{write_mesh, ExportFormat};
use ism_format::io;
use ism_geom::ModelEval;
use ism_sample::{FormatWriter, Header, OutputFormat, Region, SampleBlock, Sampler, Sink};
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::errors::{export_error, raise, sample_error};
use crate::model::Model;
use crate::worker::{run, Control, Stop};

/// A sink that writes NPY into memory, reports rows and stops when the caller cancels.
struct NpySink<'a> {
    writer: FormatWriter<Vec<u8>>,
    control: &'a Control,
    dim: usize,
    rows: u64,
}

impl Sink for NpySink<'_> {
    fn begin(&mut self, header: &Header) -> ism_sample::Result<()> {
        self.dim = header.dim;
        self.writer.begin(header)
    }

    fn block(&mut self, block: &SampleBlock) -> ism_sample::Result<()> {
        if self.control.cancelled() {
            return Err(ism_sample::SampleError::InvalidArgument(
                "interrupted".to_string(),
            ));
        }
        self.writer.block(block)?;
        self.rows += block.len(self.dim) as u64;
        self.control.report(self.rows);
        Ok(())
    }

    fn finish(&mut self) -> ism_sample::Result<()> {
        self.writer.finish()
    }
}

/// What to sample.
enum Job {
    Surface(u64),
    Volume(u64, Region),
    NearSurface(u64, f64),
    Query(Vec<f64>),
}

impl Model {
    /// Runs a sampling or query job on the cached sampler and returns the NPY bytes as a numpy
    /// structured array.
    fn sample_job<'py>(
        slf: &Bound<'py, Self>,
        job: Job,
        seed: u64,
        threads: usize,
        progress: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let py = slf.py();
        let me = slf.get();
        let total = match &job {
            Job::Surface(c) | Job::Volume(c, _) | Job::NearSurface(c, _) => *c,
            Job::Query(p) => (p.len() / me.inner.dim().max(1)) as u64,
        };
        // The evaluator and its surface table are kept between calls; a concurrent call builds
        // its own.
        let cached = me.sampler.lock().map(|mut s| s.take()).unwrap_or(None);
        let model = me.inner.clone();
        let (sampler, result) = run(
            py,
            threads,
            Stop::Polls,
            progress.map(|p| (p, total)),
            move |control| {
                let sampler = match cached {
                    Some(s) => s,
                    None => match Sampler::new(&model) {
                        Ok(s) => s,
                        Err(e) => return (None, Err(e)),
                    },
                };
                let sampler = sampler.seed(seed);
                let mut sink = NpySink {
                    writer: FormatWriter::new(Vec::new(), OutputFormat::Npy),
                    control,
                    dim: model.dim(),
                    rows: 0,
                };
                let r = match job {
                    Job::Surface(c) => sampler.surface(c, &mut sink),
                    Job::Volume(c, region) => sampler.volume(c, region, &mut sink),
                    Job::NearSurface(c, sigma) => sampler.near_surface(c, sigma, &mut sink),
                    Job::Query(points) => sampler.query(&points, &mut sink),
                };
                (Some(sampler), r.map(|()| sink.writer.into_inner()))
            },
        )?;
        if let Some(s) = sampler {
            if let Ok(mut slot) = me.sampler.lock() {
                *slot = Some(s);
            }
        }
        let bytes = result.map_err(|e| sample_error(py, &e))?;
        let buffer = PyArray1::from_vec(py, bytes);
        crate::convert(py)?.getattr("npy_view")?.call1((buffer,))
    }
}

/// An object of the pure-Python class `ism._results.<class>` built from JSON text.
fn wrap<'py>(py: Python<'py>, class: &str, json: String) -> PyResult<Bound<'py, PyAny>> {
    py.import("ism._results")?
        .getattr(class)?
        .getattr("from_json")?
        .call1((json,))
}

fn json_dict<'py>(py: Python<'py>, value: &serde_json::Value) -> PyResult<Bound<'py, PyAny>> {
    crate::value_to_py(py, value)
}

/// Validates a file's bytes as `ism validate --json` does (the report's `file` member included).
#[pyfunction]
#[pyo3(signature = (path, *, max_issues = ism_validate::DEFAULT_MAX_ISSUES, threads = 0, max_pieces = ism_validate::DEFAULT_MAX_PIECES, quality = false, theorems = true))]
pub fn validate_path(
    py: Python<'_>,
    path: std::path::PathBuf,
    max_issues: usize,
    threads: usize,
    max_pieces: usize,
    quality: bool,
    theorems: bool,
) -> PyResult<Bound<'_, PyAny>> {
    let options = validate_options(max_issues, threads, max_pieces, quality, theorems)?;
    let report = run(py, 0, Stop::Detach, None, move |_| {
        ism_validate::validate_path(&path, &options)
    })?
    .map_err(|e| crate::errors::validate_error(py, &e))?;
    wrap(py, "ValidationReport", report_json(&report)?)
}

/// Validates bytes (any encoding), as [`validate_path`].
#[pyfunction]
#[pyo3(signature = (data, *, max_issues = ism_validate::DEFAULT_MAX_ISSUES, threads = 0, max_pieces = ism_validate::DEFAULT_MAX_PIECES, quality = false, theorems = true))]
pub fn validate_bytes(
    py: Python<'_>,
    data: Vec<u8>,
    max_issues: usize,
    threads: usize,
    max_pieces: usize,
    quality: bool,
    theorems: bool,
) -> PyResult<Bound<'_, PyAny>> {
    let options = validate_options(max_issues, threads, max_pieces, quality, theorems)?;
    let report = run(py, 0, Stop::Detach, None, move |_| {
        ism_validate::validate_bytes(&data, &options)
    })?
    .map_err(|e| crate::errors::validate_error(py, &e))?;
    wrap(py, "ValidationReport", report_json(&report)?)
}

fn validate_options(
    max_issues: usize,
    threads: usize,
    max_pieces: usize,
    quality: bool,
    theorems: bool,
) -> PyResult<ism_validate::Options> {
    if !(1..=1usize << 32).contains(&max_pieces) {
        return Err(PyValueError::new_err(format!(
            "max_pieces: expected a whole number of pieces from 1 to {}",
            1u64 << 32
        )));
    }
    Ok(ism_validate::Options {
        max_issues,
        threads,
        max_pieces,
        quality,
        theorems,
    })
}

fn report_json(report: &ism_validate::Report) -> PyResult<String> {
    serde_json::to_string(report)
        .map_err(|e| pyo3::exceptions::PyRuntimeError::new_err(format!("report as JSON: {e}")))
}

fn mesh_dict<'py>(py: Python<'py>, mesh: &ism_export::Mesh) -> PyResult<Bound<'py, PyDict>> {
    let n = mesh.dimension;
    let nv = mesh.num_vertices();
    let flat = |rows: &[[f64; 3]]| -> Vec<f64> {
        rows.iter().flat_map(|r| r[..n].iter().copied()).collect()
    };
    let d = PyDict::new(py);
    d.set_item("dimension", n)?;
    d.set_item(
        "positions",
        PyArray1::from_vec(py, flat(&mesh.positions)).reshape([nv, n])?,
    )?;
    d.set_item(
        "normals",
        PyArray1::from_vec(py, flat(&mesh.normals)).reshape([nv, n])?,
    )?;
    let arity = mesh.primitive.arity();
    d.set_item(
        "cells",
        PyArray1::from_slice(py, &mesh.cells).reshape([mesh.num_cells(), arity])?,
    )?;
    d.set_item("cell_simplex", PyArray1::from_slice(py, &mesh.cell_simplex))?;
    d.set_item(
        "vertex_simplex",
        PyArray1::from_slice(py, &mesh.vertex_simplex),
    )?;
    d.set_item(
        "gradient_norm",
        PyArray1::from_slice(py, &mesh.gradient_norm),
    )?;
    Ok(d)
}

fn topology_json(mesh: &ism_export::Mesh) -> serde_json::Value {
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
    })
}

fn extract_json(r: &ism_export::extract::ExtractReport) -> serde_json::Value {
    serde_json::json!({
        "crossed_simplices": r.crossed_simplices,
        "inversions": r.inversions,
        "max_inverse_residual": r.max_residual,
        "depth_limited_edges": r.depth_limited_edges,
    })
}

/// Extracts the curved (or, with `linear`, the linear) shape as `ism export` does.
fn extract_mesh(
    model: &ism_format::Model,
    tolerance: f64,
    max_depth: u32,
    linear: bool,
) -> Result<(ism_export::Mesh, Option<ism_export::extract::ExtractReport>), ism_export::Error> {
    if linear {
        return Ok((ism_export::marching::marching(model)?, None));
    }
    let eval = ModelEval::new(model)
        .map_err(|e| ism_export::Error::Unsupported(format!("cannot evaluate the model: {e}")))?;
    let (mesh, report) = extract(
        &eval,
        &ExtractOptions {
            tolerance,
            max_depth,
        },
    )?;
    Ok((mesh, Some(report)))
}

fn check_extract_args(tolerance: f64, max_depth: u32) -> PyResult<()> {
    if !(tolerance.is_finite() && tolerance > 0.0) {
        return Err(PyValueError::new_err(format!(
            "tolerance: expected a positive number, got {tolerance}"
        )));
    }
    if max_depth > ism_export::extract::MAX_DEPTH_LIMIT {
        return Err(PyValueError::new_err(format!(
            "max_depth: at most {}",
            ism_export::extract::MAX_DEPTH_LIMIT
        )));
    }
    Ok(())
}

#[pymethods]
impl Model {
    /// Validates the model (structure, invariance, certified positivity of every stage) as
    /// ``ism validate`` does and returns an :class:`ism.ValidationReport`.
    #[pyo3(signature = (*, max_issues = ism_validate::DEFAULT_MAX_ISSUES, threads = 0, max_pieces = ism_validate::DEFAULT_MAX_PIECES, quality = false, theorems = true))]
    fn validate<'py>(
        &self,
        py: Python<'py>,
        max_issues: usize,
        threads: usize,
        max_pieces: usize,
        quality: bool,
        theorems: bool,
    ) -> PyResult<Bound<'py, PyAny>> {
        let options = validate_options(max_issues, threads, max_pieces, quality, theorems)?;
        let model = self.inner.clone();
        let report = run(py, 0, Stop::Detach, None, move |_| {
            ism_validate::validate(&model, &options)
        })?;
        wrap(py, "ValidationReport", report_json(&report)?)
    }

    /// The curved shape as an :class:`ism.Surface` (numpy arrays: positions (Nv, n), normals
    /// (Nv, n), cells (Nc, 3) triangles or, in 2D, (Nc, 2) segments, cell_simplex,
    /// vertex_simplex, gradient_norm; and a ``report`` dict), as ``ism export`` extracts it:
    /// patches refined until the chordal error is below ``tolerance`` or ``max_depth`` halvings.
    /// ``linear`` gives the linear isocomplex (marching simplices, stages ignored).
    #[pyo3(signature = (tolerance = 1e-3, *, max_depth = 8, linear = false, threads = 0))]
    fn extract_surface<'py>(
        &self,
        py: Python<'py>,
        tolerance: f64,
        max_depth: u32,
        linear: bool,
        threads: usize,
    ) -> PyResult<Bound<'py, PyAny>> {
        check_extract_args(tolerance, max_depth)?;
        let model = self.inner.clone();
        let (mesh, report) = run(py, threads, Stop::Detach, None, move |_| {
            extract_mesh(&model, tolerance, max_depth, linear)
        })?
        .map_err(|e| export_error(py, &e))?;
        let d = mesh_dict(py, &mesh)?;
        let mut summary = topology_json(&mesh);
        if let (Some(r), Some(obj)) = (report, summary.as_object_mut()) {
            if let Some(extra) = extract_json(&r).as_object() {
                obj.extend(extra.clone());
            }
        }
        d.set_item("report", json_dict(py, &summary)?)?;
        py.import("ism._results")?
            .getattr("Surface")?
            .call((), Some(&d))
    }

    /// Writes the shape to ``path`` as ``ism export`` does: the format follows the extension
    /// (.obj, .gltf, .glb, .vtk, .vtu); ``linear`` writes the linear isocomplex, ``volume`` the
    /// complex with F as a Bézier field (VTK only). Returns the summary of ``ism export --json``.
    #[pyo3(signature = (path, *, tolerance = 1e-3, max_depth = 8, linear = false, volume = false, threads = 0))]
    #[allow(clippy::too_many_arguments)]
    fn export<'py>(
        &self,
        py: Python<'py>,
        path: std::path::PathBuf,
        tolerance: f64,
        max_depth: u32,
        linear: bool,
        volume: bool,
        threads: usize,
    ) -> PyResult<Bound<'py, PyAny>> {
        check_extract_args(tolerance, max_depth)?;
        let format = ExportFormat::from_path(&path).ok_or_else(|| {
            PyValueError::new_err(format!(
                "cannot tell the output format of {}: use .obj, .gltf, .glb, .vtk or .vtu",
                path.display()
            ))
        })?;
        if volume && linear {
            return Err(PyValueError::new_err(
                "linear and volume exclude each other",
            ));
        }
        if volume && !format.supports_volume() {
            return Err(PyValueError::new_err(format!(
                "volume needs a VTK output (.vtk or .vtu), not .{}",
                format.extension()
            )));
        }
        let model = self.inner.clone();
        let out = path.clone();
        let result = run(
            py,
            threads,
            Stop::Detach,
            None,
            move |_| -> Result<serde_json::Value, String> {
                let name = model.metadata.name.clone();
                if volume {
                    // The CLI's default field tolerance (issue 19): the surface tolerance times
                    // the median |∇F| of the linear interpolant on the crossed simplices.
                    let options = ism_export::volume::VolumeOptions {
                        field_tolerance: ism_export::volume::default_field_tolerance(
                            &model, tolerance,
                        ),
                    };
                    let (grid, report) = ism_export::volume::volume_grid(&model, &options)
                        .map_err(|e| format!("cannot build the volume field: {e}"))?;
                    io::write_atomic(&out, |w| {
                        let r = match format {
                            ExportFormat::Vtu => grid.write_vtu(w),
                            _ => grid.write_legacy(name.as_deref().unwrap_or("ISM volume"), w),
                        };
                        r.map_err(std::io::Error::other)
                    })
                    .map_err(|e| format!("cannot write {}: {e}", out.display()))?;
                    return Ok(serde_json::json!({
                        "output": out.display().to_string(),
                        "format": format.extension(),
                        "cells": grid.num_cells(),
                        "control_points": grid.points.len(),
                        "field": report.note,
                        "degree": report.degree,
                        "refinement_levels": report.level,
                        "field_error_bound": report.bound,
                        "field_error_bound_everywhere": report.global_bound,
                        "field_error_certified": report.certified,
                        "field_tolerance": report.tolerance,
                        "field_tolerance_met": report.met,
                    }));
                }
                let (mesh, report) = extract_mesh(&model, tolerance, max_depth, linear)
                    .map_err(|e| e.to_string())?;
                io::write_atomic(&out, |w| {
                    write_mesh(&mesh, format, name.as_deref(), w).map_err(std::io::Error::other)
                })
                .map_err(|e| format!("cannot write {}: {e}", out.display()))?;
                let mut summary = topology_json(&mesh);
                if let Some(obj) = summary.as_object_mut() {
                    obj.insert("output".into(), out.display().to_string().into());
                    obj.insert("format".into(), format.extension().into());
                    if let Some(r) = report {
                        if let Some(extra) = extract_json(&r).as_object() {
                            obj.extend(extra.clone());
                        }
                    }
                }
                Ok(summary)
            },
        )?;
        match result {
            Ok(summary) => json_dict(py, &summary),
            Err(message) => Err(raise(py, "ExportError", &message, &[])),
        }
    }

    /// ``n`` points on the shape, uniform by curved area (length in 2D): a numpy structured array
    /// with the fields of ``ism sample --surface`` (x, y[, z], nx, ny[, nz], f, simplex),
    /// bit-identical to the CLI's for the same ``seed``. ``progress(done, total)`` is called
    /// between blocks of rows.
    ///
    /// >>> import ism
    /// >>> pts = ism.read("spec/examples/circle-curved.ismb").sample_surface(500, seed=3)
    /// >>> pts.dtype.names, len(pts)
    /// (('x', 'y', 'nx', 'ny', 'f', 'simplex'), 500)
    #[pyo3(signature = (n, seed = 0, *, threads = 0, progress = None))]
    fn sample_surface<'py>(
        slf: &Bound<'py, Self>,
        n: u64,
        seed: u64,
        threads: usize,
        progress: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        Model::sample_job(slf, Job::Surface(n), seed, threads, progress)
    }

    /// ``n`` points uniform in the complex (or in ``box = (lo, hi)``): fields x, y[, z], f, label,
    /// simplex as ``ism sample --volume``.
    #[pyo3(signature = (n, seed = 0, *, r#box = None, threads = 0, progress = None))]
    fn sample_volume<'py>(
        slf: &Bound<'py, Self>,
        n: u64,
        seed: u64,
        r#box: Option<(Vec<f64>, Vec<f64>)>,
        threads: usize,
        progress: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let dim = slf.get().inner.dim();
        let region = match r#box {
            None => Region::Complex,
            Some((lo_in, hi_in)) => {
                if lo_in.len() != dim || hi_in.len() != dim {
                    return Err(PyValueError::new_err(format!(
                        "box: expected (lo, hi) with {dim} numbers each"
                    )));
                }
                let mut lo = [0.0; 3];
                let mut hi = [0.0; 3];
                lo[..dim].copy_from_slice(&lo_in);
                hi[..dim].copy_from_slice(&hi_in);
                Region::Box { lo, hi }
            }
        };
        Model::sample_job(slf, Job::Volume(n, region), seed, threads, progress)
    }

    /// ``n`` surface points displaced along random directions by N(0, sigma²): fields as
    /// ``ism sample --near-surface``.
    #[pyo3(signature = (n, sigma, seed = 0, *, threads = 0, progress = None))]
    fn sample_near_surface<'py>(
        slf: &Bound<'py, Self>,
        n: u64,
        sigma: f64,
        seed: u64,
        threads: usize,
        progress: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        if !(sigma.is_finite() && sigma > 0.0) {
            return Err(PyValueError::new_err(format!(
                "sigma: expected a positive number, got {sigma}"
            )));
        }
        Model::sample_job(slf, Job::NearSurface(n, sigma), seed, threads, progress)
    }

    /// Evaluates points (array (N, n)): a structured array with the fields of ``ism query``
    /// (x, y[, z], simplex, f, sign, gx, gy[, gz]); simplex −1, f and ∇F NaN outside the complex.
    ///
    /// >>> import ism
    /// >>> q = ism.read("spec/examples/sphere.ismb").query([[0.0, 0.0, 0.0], [9.0, 9.0, 9.0]])
    /// >>> q["simplex"].tolist(), q["sign"].tolist()
    /// ([516, -1], [-1, 0])
    #[pyo3(signature = (points, *, threads = 0, progress = None))]
    fn query<'py>(
        slf: &Bound<'py, Self>,
        points: &Bound<'py, PyAny>,
        threads: usize,
        progress: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let py = slf.py();
        let dim = slf.get().inner.dim();
        let a = crate::convert(py)?
            .getattr("float_array")?
            .call1((points, "points", 2))?;
        let a: PyReadonlyArray2<f64> = a.extract()?;
        if a.shape()[1] != dim && a.shape()[0] != 0 {
            return Err(PyValueError::new_err(format!(
                "points: expected shape (N, {dim}), got {:?}",
                a.shape()
            )));
        }
        let flat = a.as_slice()?.to_vec();
        Model::sample_job(slf, Job::Query(flat), 0, threads, progress)
    }

    /// Smooths the shape (Mello & Velho 2009, §8) as ``ism smooth`` does; with ``rational`` the C¹
    /// rational-weight fit. Returns ``(model, report dict)``.
    #[pyo3(signature = (*, iterations = None, alpha = None, rational = false, degree = None, threads = 0))]
    fn smooth<'py>(
        &self,
        py: Python<'py>,
        iterations: Option<usize>,
        alpha: Option<f64>,
        rational: bool,
        degree: Option<u32>,
        threads: usize,
    ) -> PyResult<(Model, Bound<'py, PyAny>)> {
        if degree.is_some() && !rational {
            return Err(PyValueError::new_err(
                "degree applies to rational smoothing only",
            ));
        }
        if let Some(a) = alpha {
            if !(a.is_finite() && a >= 0.0) {
                return Err(PyValueError::new_err(format!(
                    "alpha: expected a number >= 0, got {a}"
                )));
            }
        }
        let model = self.inner.clone();
        let result = run(py, threads, Stop::Detach, None, move |_| {
            crate::fit::smooth(&model, iterations, alpha, rational, degree)
        })?;
        let (out, report) = result.map_err(|m| raise(py, "FitError", &m, &[]))?;
        Ok((Model::new(out, None), json_dict(py, &report)?))
    }
}

/// Calls `ism._adapters.<name>(model, *args, **kwargs)`.
fn adapter<'py>(
    slf: &Bound<'py, Model>,
    name: &str,
    args: &Bound<'py, pyo3::types::PyTuple>,
    kwargs: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyAny>> {
    let f = slf.py().import("ism._adapters")?.getattr(name)?;
    let mut all = vec![slf.clone().into_any()];
    all.extend(args.iter());
    f.call(pyo3::types::PyTuple::new(slf.py(), all)?, kwargs)
}

#[pymethods]
impl Model {
    /// The curved surface as a ``trimesh.Trimesh`` (3D models; needs trimesh). Arguments as
    /// :meth:`extract_surface`.
    #[pyo3(signature = (*args, **kwargs))]
    fn to_trimesh<'py>(
        slf: &Bound<'py, Self>,
        args: &Bound<'py, pyo3::types::PyTuple>,
        kwargs: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        adapter(slf, "to_trimesh", args, kwargs)
    }

    /// The curved surface as a ``pyvista.PolyData`` (default), or with ``volume=True`` the complex
    /// with F as VTK Bézier cells (``pyvista.UnstructuredGrid``); needs pyvista.
    #[pyo3(signature = (*args, **kwargs))]
    fn to_pyvista<'py>(
        slf: &Bound<'py, Self>,
        args: &Bound<'py, pyo3::types::PyTuple>,
        kwargs: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        adapter(slf, "to_pyvista", args, kwargs)
    }

    /// The linear complex as a ``meshio.Mesh`` with the vertex values as point data ``"f"``;
    /// needs meshio.
    #[pyo3(signature = (*args, **kwargs))]
    fn to_meshio<'py>(
        slf: &Bound<'py, Self>,
        args: &Bound<'py, pyo3::types::PyTuple>,
        kwargs: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        adapter(slf, "to_meshio", args, kwargs)
    }
}

/// Numpy (N, 3) positions and triangles as a fitter mesh.
pub(crate) fn triangle_mesh(
    vertices: &Bound<'_, PyAny>,
    faces: &Bound<'_, PyAny>,
) -> PyResult<ism_fit::mesh::TriangleMesh> {
    let conv = crate::convert(vertices.py())?;
    let v = conv
        .getattr("float_array")?
        .call1((vertices, "vertices", 2))?;
    let v: PyReadonlyArray2<f64> = v.extract()?;
    let f = conv.getattr("index_array")?.call1((faces, "faces", 2))?;
    let f: numpy::PyReadonlyArray2<u32> = f.extract()?;
    if v.shape()[1] != 3 || f.shape()[1] != 3 {
        return Err(PyValueError::new_err(format!(
            "expected vertices (N, 3) and faces (M, 3), got {:?} and {:?}",
            v.shape(),
            f.shape()
        )));
    }
    let nv = v.shape()[0];
    let positions = v
        .as_slice()?
        .chunks_exact(3)
        .map(|p| [p[0], p[1], p[2]])
        .collect();
    let mut triangles = Vec::new();
    for t in f.as_slice()?.chunks_exact(3) {
        if t.iter().any(|&i| i as usize >= nv) {
            return Err(PyValueError::new_err(format!(
                "faces: vertex id out of range in {t:?} ({nv} vertices)"
            )));
        }
        triangles.push([t[0], t[1], t[2]]);
    }
    Ok(ism_fit::mesh::TriangleMesh {
        positions,
        triangles,
    })
}
