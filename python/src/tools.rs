//! The tools as methods of `ism.Model`: validate, extract, export, sample, query, smooth.
//!
//! Each is the library call the CLI makes, run through [`crate::worker::run`] (GIL released,
//! Ctrl-C honoured). Point sets are written by `ism_sample`'s own NPY writer into memory and
//! handed to numpy without a copy, so their fields, order and bits are those of
//! `ism sample -o x.npy`.

use ism_export::export::{ExportOptions, Exported};
use ism_export::format::ExportFormat;
use ism_geom::ModelEval;
use ism_sample::{FormatWriter, Header, OutputFormat, Region, SampleBlock, Sampler, Sink};
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::errors::{export_error, raise, sample_error};
use crate::model::{Model, Shared};
use crate::worker::{run, Control};

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
        let (sampler, result) = run(py, threads, progress.map(|p| (p, total)), move |control| {
            // A checked read's index is reused: the evaluator only inverts the edge matrices
            // and builds its spatial index (no copy, no second structural check).
            let sampler = match cached {
                Some(s) => s,
                None => {
                    let eval = match &model {
                        Shared::Indexed(indexed) => ModelEval::from_indexed(indexed),
                        Shared::Plain(plain) => ModelEval::new(plain),
                    };
                    match eval {
                        Ok(e) => Sampler::from_eval(e),
                        Err(e) => {
                            let e = ism_sample::SampleError::Geometry(e);
                            return (None, Err(e));
                        }
                    }
                }
            };
            let mut sampler = sampler.seed(seed);
            if let Job::Surface(c) | Job::NearSurface(c, _) = &job {
                // As `ism sample` does: the surface table refines its bounds as far as `c`
                // samples pay for it, so the rows for a seed are the CLI's, bit for bit (a cached
                // table built for another count is rebuilt).
                sampler = sampler.expected_surface_samples(*c);
            }
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
        })?;
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
#[pyo3(signature = (path, *, max_issues = ism_validate::DEFAULT_MAX_ISSUES, threads = 0, max_pieces = ism_validate::DEFAULT_MAX_PIECES, quality = false, theorems = true, progress = None, limits = None))]
#[allow(clippy::too_many_arguments)]
pub fn validate_path<'py>(
    py: Python<'py>,
    path: std::path::PathBuf,
    max_issues: usize,
    threads: usize,
    max_pieces: usize,
    quality: bool,
    theorems: bool,
    progress: Option<&Bound<'py, PyAny>>,
    limits: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyAny>> {
    let mut options = validate_options(max_issues, threads, max_pieces, quality, theorems)?;
    options.limits = crate::model::limits_from(limits)?;
    let report = run(py, 0, progress.map(|p| (p, 0)), move |control| {
        ism_validate::validate_path_with_progress(&path, &options, &control.hook())
    })?
    .map_err(|e| crate::errors::validate_error(py, &e))?;
    wrap(py, "ValidationReport", report_json(&report)?)
}

/// Validates bytes (any encoding), as [`validate_path`].
#[pyfunction]
#[pyo3(signature = (data, *, max_issues = ism_validate::DEFAULT_MAX_ISSUES, threads = 0, max_pieces = ism_validate::DEFAULT_MAX_PIECES, quality = false, theorems = true, progress = None, limits = None))]
#[allow(clippy::too_many_arguments)]
pub fn validate_bytes<'py>(
    py: Python<'py>,
    data: Vec<u8>,
    max_issues: usize,
    threads: usize,
    max_pieces: usize,
    quality: bool,
    theorems: bool,
    progress: Option<&Bound<'py, PyAny>>,
    limits: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyAny>> {
    let mut options = validate_options(max_issues, threads, max_pieces, quality, theorems)?;
    options.limits = crate::model::limits_from(limits)?;
    let report = run(py, 0, progress.map(|p| (p, 0)), move |control| {
        ism_validate::validate_bytes_with_progress(&data, &options, &control.hook())
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
        ..ism_validate::Options::default()
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

/// The options of `ism export`, checked (as the CLI's argument parser and the library check them).
fn export_options(
    tolerance: f64,
    max_depth: u32,
    linear: bool,
    volume: bool,
    coarsen: Option<bool>,
    format: Option<ExportFormat>,
) -> PyResult<ExportOptions> {
    let options = ExportOptions {
        tolerance,
        max_depth,
        linear,
        volume,
        field_tolerance: None,
        coarsen,
    };
    ism_export::export::check(&options, format).map_err(|e| match e {
        ism_export::Error::Unsupported(m) => PyValueError::new_err(m),
        e => PyValueError::new_err(crate::errors::chain(&e)),
    })?;
    Ok(options)
}

#[pymethods]
impl Model {
    /// Validates the model (structure, invariance, certified positivity of every stage) as
    /// ``ism validate`` does and returns an :class:`ism.ValidationReport`.
    ///
    /// ``progress(phase, done, total)`` is called as the positivity layer goes (done/total in
    /// simplices); Ctrl-C or an exception from it stops the run.
    #[pyo3(signature = (*, max_issues = ism_validate::DEFAULT_MAX_ISSUES, threads = 0, max_pieces = ism_validate::DEFAULT_MAX_PIECES, quality = false, theorems = true, progress = None))]
    #[allow(clippy::too_many_arguments)]
    fn validate<'py>(
        &self,
        py: Python<'py>,
        max_issues: usize,
        threads: usize,
        max_pieces: usize,
        quality: bool,
        theorems: bool,
        progress: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let options = validate_options(max_issues, threads, max_pieces, quality, theorems)?;
        let model = self.inner.clone();
        let report = run(py, 0, progress.map(|p| (p, 0)), move |control| {
            ism_validate::validate_with_progress(&model, &options, &control.hook())
        })?
        .map_err(|e| crate::errors::validate_error(py, &ism_validate::Error::from(e)))?;
        wrap(py, "ValidationReport", report_json(&report)?)
    }

    /// The curved shape as an :class:`ism.Surface` (numpy arrays: positions (Nv, n), normals
    /// (Nv, n), cells (Nc, 3) triangles or, in 2D, (Nc, 2) segments, cell_simplex,
    /// vertex_simplex, gradient_norm; and a ``report`` dict), as ``ism export`` extracts it:
    /// patches refined until the chordal error is below ``tolerance`` or an edge is halved
    /// ``max_depth`` times and is short in space (``ism export --max-depth``; 30 halvings at most).
    /// ``linear`` gives the linear isocomplex (marching simplices, stages ignored). The curved
    /// surface is coarsened after refinement (vertices inside patches merged wherever the coarser
    /// mesh still passes the refinement's tests: 0.6–0.8× the triangles at the same error);
    /// ``coarsen=False`` keeps the refinement's mesh (``ism export --no-coarsen``: cheaper),
    /// ``coarsen=True`` with ``linear`` is refused.
    ///
    /// ``progress(phase, done, total)`` is called as the extraction goes (counted phases: facets,
    /// then patches); Ctrl-C or an exception from it stops the extraction.
    #[pyo3(signature = (tolerance = 1e-3, *, max_depth = 8, linear = false, coarsen = None, threads = 0, progress = None))]
    #[allow(clippy::too_many_arguments)]
    fn extract_surface<'py>(
        &self,
        py: Python<'py>,
        tolerance: f64,
        max_depth: u32,
        linear: bool,
        coarsen: Option<bool>,
        threads: usize,
        progress: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let options = export_options(tolerance, max_depth, linear, false, coarsen, None)?;
        let model = self.inner.clone();
        let built = run(py, threads, progress.map(|p| (p, 0)), move |control| {
            export_build(&model, &options, control)
        })?
        .map_err(|e| export_error(py, &e))?;
        let Exported::Surface { mesh, extract } = built else {
            return Err(pyo3::exceptions::PyRuntimeError::new_err(
                "a surface export built a volume",
            ));
        };
        let d = mesh_dict(py, &mesh)?;
        let summary = ism_export::export::surface_summary(&mesh, extract.as_ref());
        d.set_item("report", json_dict(py, &summary)?)?;
        py.import("ism._results")?
            .getattr("Surface")?
            .call((), Some(&d))
    }

    /// Writes the shape to ``path`` as ``ism export`` does: the format follows the extension
    /// (.obj, .gltf, .glb, .vtk, .vtu); ``linear`` writes the linear isocomplex, ``volume`` the
    /// complex with F as a Bézier field (VTK only), ``coarsen`` as :meth:`extract_surface`,
    /// ``compress`` zlib-compresses a .vtu's arrays (``ism export --compress``; .vtu only).
    /// Returns the summary of ``ism export --json`` (without its timings).
    /// ``progress(phase, done, total)`` as :meth:`extract_surface`.
    #[pyo3(signature = (path, *, tolerance = 1e-3, max_depth = 8, linear = false, volume = false, coarsen = None, compress = false, threads = 0, progress = None))]
    #[allow(clippy::too_many_arguments)]
    fn export<'py>(
        &self,
        py: Python<'py>,
        path: std::path::PathBuf,
        tolerance: f64,
        max_depth: u32,
        linear: bool,
        volume: bool,
        coarsen: Option<bool>,
        compress: bool,
        threads: usize,
        progress: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let format = ExportFormat::from_path(&path).ok_or_else(|| {
            PyValueError::new_err(format!(
                "cannot tell the output format of {}: use .obj, .gltf, .glb, .vtk or .vtu",
                path.display()
            ))
        })?;
        if compress && format != ExportFormat::Vtu {
            return Err(PyValueError::new_err(format!(
                "compress needs a .vtu output, not .{}",
                format.extension()
            )));
        }
        let compression = if compress {
            ism_export::vtk::VtuCompression::Zlib
        } else {
            ism_export::vtk::VtuCompression::None
        };
        let options = export_options(tolerance, max_depth, linear, volume, coarsen, Some(format))?;
        let model = self.inner.clone();
        let name = self.inner.metadata.name.clone();
        // Built on the worker, written here once `run` has returned: a progress callback that
        // raises (or Ctrl-C) while the worker finishes still means no file, which writing on
        // the worker could not promise (the worker may finish before the callback has run).
        let built = run(py, threads, progress.map(|p| (p, 0)), move |control| {
            export_build(&model, &options, control)
        })?
        .map_err(|e| export_error(py, &e))?;
        py.allow_threads(|| {
            ism_export::export::write_path_with(&built, format, name.as_deref(), compression, &path)
        })
        .map_err(|e| export_error(py, &e))?;
        json_dict(py, &built.summary(&path, format))
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
    /// ``progress(phase, done, total)`` is called per sweep/step; Ctrl-C or an exception from it
    /// stops the smoothing.
    #[pyo3(signature = (*, iterations = None, alpha = None, rational = false, degree = None, threads = 0, progress = None))]
    #[allow(clippy::too_many_arguments)]
    fn smooth<'py>(
        &self,
        py: Python<'py>,
        iterations: Option<usize>,
        alpha: Option<f64>,
        rational: bool,
        degree: Option<u32>,
        threads: usize,
        progress: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<(Model, Bound<'py, PyAny>)> {
        let mode = ism_fit::smooth::Mode::new(iterations, alpha, rational, degree)
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        let model = self.inner.clone();
        let result = run(py, threads, progress.map(|p| (p, 0)), move |control| {
            crate::fit::smooth(&model, &mode, &control.hook())
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

/// `ism export`'s build on a model's index: a checked read's is shared (no copy, no second
/// structural check); a model built or read unchecked is indexed for evaluation here, as the
/// evaluator did before (a copy).
fn export_build(
    model: &Shared,
    options: &ExportOptions,
    control: &Control,
) -> Result<Exported, ism_export::Error> {
    match model {
        Shared::Indexed(indexed) => ism_export::export::build(indexed, options, &control.hook()),
        Shared::Plain(plain) => {
            let indexed = ism_format::IndexedModel::for_evaluation((**plain).clone())
                .map_err(ism_geom::GeomError::from)?;
            ism_export::export::build(&indexed, options, &control.hook())
        }
    }
}
