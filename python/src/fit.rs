//! `ism.fit`, `ism.fit_mesh`, `ism.fit_hermite` and smoothing: glue over `ism-fit`, with the
//! option handling of `ism fit`, `ism fit --hermite` and `ism smooth` and the reports of their
//! `--json` output (same member names).

use ism_fit::c1::smooth_rational_with_progress;
use ism_fit::hermite::{fit_hermite_with_progress, HermiteData};
use ism_fit::mesh::{MeshDistance, MeshPlanError};
use ism_fit::smooth::{smooth_with_progress, Mode};
use ism_fit::verdict::{ExpectedTopology, Verdict};
use ism_fit::{Expression, FitOptions, ImplicitFunction, Preset, PRESETS};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::errors::raise;
use crate::model::Model;
use crate::worker::run;

fn verdict(model: &ism_format::Model) -> &'static str {
    ism_validate::validate(model, &ism_validate::Options::default())
        .verdict
        .as_str()
}

/// `ism smooth` without writing: the smoothed model and the `--json` report (options, reports
/// and their JSON are the library's, as the CLI's).
pub(crate) fn smooth(
    model: &ism_format::Model,
    mode: &Mode,
    progress: &ism_format::Progress,
) -> Result<(ism_format::Model, serde_json::Value), String> {
    match mode {
        Mode::Rational(options) => {
            let s = smooth_rational_with_progress(model, options, progress)
                .map_err(|e| crate::errors::chain(&e))?;
            let report = s.report.to_json(verdict(&s.model));
            Ok((s.model, report))
        }
        Mode::Jumps(options) => {
            let s = smooth_with_progress(model, options, progress)
                .map_err(|e| crate::errors::chain(&e))?;
            let report = s.report.to_json(verdict(&s.model));
            Ok((s.model, report))
        }
    }
}

/// Options shared by the three `fit` entry points.
struct FitArgs {
    resolution: usize,
    tolerance: Option<f64>,
    max_simplices: usize,
    optimize: bool,
    rational: bool,
    topology: bool,
    /// Control points on the 2⁻²⁴ lattice (`FitOptions::lattice`): small `.isms` files.
    lattice: bool,
}

impl FitArgs {
    fn options(&self, domain: &[f64]) -> PyResult<FitOptions> {
        if self.resolution == 0 {
            return Err(PyValueError::new_err("resolution: expected at least 1"));
        }
        if let Some(t) = self.tolerance {
            if !(t.is_finite() && t > 0.0) {
                return Err(PyValueError::new_err(format!(
                    "tolerance: expected a positive number, got {t}"
                )));
            }
        }
        let mut o = FitOptions::new(domain);
        o.resolution = self.resolution;
        if let Some(t) = self.tolerance {
            o.tolerance = t;
        }
        o.max_simplices = self.max_simplices;
        o.optimize = self.optimize;
        o.rational = self.rational;
        o.topology = self.topology;
        o.lattice = self.lattice;
        Ok(o)
    }
}

fn run_fit<'py>(
    py: Python<'py>,
    g: Box<dyn ImplicitFunction + Send>,
    options: FitOptions,
    name: String,
    expected: Option<ExpectedTopology>,
    mesh: Option<serde_json::Value>,
    progress: Option<&Bound<'py, PyAny>>,
) -> PyResult<(Model, Bound<'py, PyAny>)> {
    let result = run(py, 0, progress.map(|p| (p, 0)), move |control| {
        let fitted = ism_fit::fit(&*g, &options, &control.fit_hook())
            .map_err(|e| crate::errors::chain(&e))?;
        let model = fitted.to_model(&name);
        // The library's verdict (the same as `ism fit`'s), plus what this call adds from its input.
        let verdict = Verdict::judge(&fitted, &model, options.tolerance, expected, |_| {});
        let mut report = fitted.report.to_json();
        verdict.add_to_json(&mut report);
        report.insert("mesh".to_string(), mesh.into());
        let report = serde_json::Value::Object(report);
        Ok::<_, String>((model, report, fitted.refinement()))
    })?;
    let (model, report, refinement) = result.map_err(|m| raise(py, "FitError", &m, &[]))?;
    // Written as `.isms`, the model's complex is its grid and splits, as `ism fit -o X.isms` writes.
    let model = Model::new(model, None).with_refinement(refinement);
    Ok((model, crate::value_to_py(py, &report)?))
}

/// Fits an ISM to the zero set of ``expr`` (variables x, y[, z]) over ``domain``
/// (x0, x1, y0, y1[, z0, z1]), or of a named ``preset``, as ``ism fit`` does.
/// ``progress(phase, simplices, worst)`` is called as the fit goes (worst = largest |g|/|∇g| so
/// far, NaN before the first evaluation). ``lattice`` stores the control points on the 2⁻²⁴
/// lattice (as ``ism fit --lattice``): the structured encoding (``.isms``) then writes each in 3
/// bytes per free coordinate; each point moves by at most 2⁻²⁵ of its face and the fit measures
/// the rounded points.
#[pyfunction]
#[pyo3(signature = (expr = None, domain = None, *, preset = None, resolution = 8, tolerance = None, max_simplices = 200_000, optimize = true, rational = false, topology = true, lattice = false, progress = None))]
#[allow(clippy::too_many_arguments)]
pub fn fit<'py>(
    py: Python<'py>,
    expr: Option<String>,
    domain: Option<Vec<f64>>,
    preset: Option<String>,
    resolution: usize,
    tolerance: Option<f64>,
    max_simplices: usize,
    optimize: bool,
    rational: bool,
    topology: bool,
    lattice: bool,
    progress: Option<&Bound<'py, PyAny>>,
) -> PyResult<(Model, Bound<'py, PyAny>)> {
    let args = FitArgs {
        resolution,
        tolerance,
        max_simplices,
        optimize,
        rational,
        topology,
        lattice,
    };
    let fail = |e: &dyn std::fmt::Display| raise(py, "FitError", &e.to_string(), &[]);
    let (g, domain, name, expected): (
        Box<dyn ImplicitFunction + Send>,
        Vec<f64>,
        String,
        Option<ExpectedTopology>,
    ) = match (preset, expr) {
        (Some(_), Some(_)) => return Err(PyValueError::new_err("give expr or preset, not both")),
        (Some(name), None) => {
            if domain.is_some() {
                return Err(PyValueError::new_err("a preset has its own domain"));
            }
            let p: &Preset = Preset::find(&name).map_err(|e| fail(&e))?;
            (
                Box::new(p.expression().map_err(|e| fail(&e))?),
                p.domain.to_vec(),
                p.name.to_string(),
                Some(ExpectedTopology::of_preset(p)),
            )
        }
        (None, Some(text)) => {
            let domain = domain.ok_or_else(|| {
                PyValueError::new_err("expr needs domain = (x0, x1, y0, y1[, z0, z1])")
            })?;
            if domain.len() != 4 && domain.len() != 6 {
                return Err(PyValueError::new_err(format!(
                    "domain needs 4 numbers (2D) or 6 (3D), got {}",
                    domain.len()
                )));
            }
            let e = Expression::parse(&text, domain.len() / 2).map_err(|e| fail(&e))?;
            (Box::new(e), domain, "fit".to_string(), None)
        }
        (None, None) => return Err(PyValueError::new_err("give expr with domain, or preset")),
    };
    let options = args.options(&domain)?;
    run_fit(py, g, options, name, expected, None, progress)
}

/// Fits an ISM to a closed triangle mesh (vertices (N, 3), faces (M, 3)): the shape is the zero
/// set of the signed distance, as ``ism fit --mesh``. ``progress`` and ``lattice`` as :func:`fit`.
#[pyfunction]
#[pyo3(signature = (vertices, faces, *, domain = None, margin = 0.05, resolution = 8, tolerance = None, max_simplices = 200_000, optimize = true, rational = false, topology = true, lattice = false, name = "mesh", progress = None))]
#[allow(clippy::too_many_arguments)]
pub fn fit_mesh<'py>(
    py: Python<'py>,
    vertices: &Bound<'py, PyAny>,
    faces: &Bound<'py, PyAny>,
    domain: Option<Vec<f64>>,
    margin: f64,
    resolution: usize,
    tolerance: Option<f64>,
    max_simplices: usize,
    optimize: bool,
    rational: bool,
    topology: bool,
    lattice: bool,
    name: &str,
    progress: Option<&Bound<'py, PyAny>>,
) -> PyResult<(Model, Bound<'py, PyAny>)> {
    let mesh = crate::tools::triangle_mesh(vertices, faces)?;
    if !(margin.is_finite() && margin >= 0.0) {
        return Err(PyValueError::new_err("margin: expected a number >= 0"));
    }
    let g = MeshDistance::new(mesh)
        .map_err(|e| raise(py, "FitError", &crate::errors::chain(&e), &[]))?;
    let plan = g
        .plan(domain.as_deref(), margin, topology)
        .map_err(|e| match e {
            MeshPlanError::NotClosedManifold(why) => {
                raise(py, "FitError", &format!("the mesh {why}"), &[])
            }
            MeshPlanError::DomainLength(n) => {
                PyValueError::new_err(format!("domain with a mesh needs 6 numbers, got {n}"))
            }
        })?;
    let args = FitArgs {
        resolution,
        tolerance,
        max_simplices,
        optimize,
        rational,
        topology,
        lattice,
    };
    let mut options = args.options(&plan.domain)?;
    plan.apply(&mut options);
    let check = plan.check;
    let diagonal = plan.diagonal;
    let info = serde_json::json!({
        "vertices": check.vertices,
        "triangles": check.triangles,
        "closedManifold": check.is_closed_manifold(),
        "components": check.components,
        "euler": check.euler,
        "flipped": plan.flipped,
        "diagonal": diagonal,
    });
    run_fit(
        py,
        Box::new(g),
        options,
        name.to_string(),
        Some(ExpectedTopology::of_mesh(&plan)),
        Some(info),
        progress,
    )
}

/// Fits a model to Hermite data (positions and normals on sign-changing edges; ``data`` is the
/// handles document of spec/hermite.md as a dict or JSON text); ``model`` is the base model when
/// the document has no complex of its own.
/// ``progress(phase, done, total)`` is called per sweep over the free faces; Ctrl-C or an
/// exception from it stops the fit.
#[pyfunction]
#[pyo3(signature = (data, model = None, *, progress = None))]
pub fn fit_hermite<'py>(
    py: Python<'py>,
    data: &Bound<'py, PyAny>,
    model: Option<&Bound<'py, Model>>,
    progress: Option<&Bound<'py, PyAny>>,
) -> PyResult<(Model, Bound<'py, PyAny>)> {
    let text: String = match data.extract::<String>() {
        Ok(t) => t,
        Err(_) => crate::py_to_value(data, "data")?.to_string(),
    };
    let base = model.map(|m| (*m.get().inner).clone());
    let result = run(py, 0, progress.map(|p| (p, 0)), move |control| {
        let data = HermiteData::from_json(&text).map_err(|e| crate::errors::chain(&e))?;
        if data.model.is_some() && base.is_none() {
            return Err(
                "the handles name a model file; read it with ism.read and pass it as model="
                    .to_string(),
            );
        }
        let model = data
            .base_model(base)
            .map_err(|e| crate::errors::chain(&e))?;
        let fitted =
            fit_hermite_with_progress(&model, &data.handles, &data.options(), &control.hook())
                .map_err(|e| crate::errors::chain(&e))?;
        let r = &fitted.report;
        let handles: Vec<_> = r
            .handles
            .iter()
            .map(|h| {
                serde_json::json!({
                    "edge": h.edge,
                    "target": h.target,
                    "achieved": h.achieved,
                    "positionError": h.position_error,
                    "angleBefore": h.angle_before,
                    "angleAfter": h.angle_after,
                })
            })
            .collect();
        let report = serde_json::json!({
            "handles": handles,
            "maxPositionError": r.max_position_error,
            "maxAngleBefore": r.max_angle_before,
            "maxAngleAfter": r.max_angle_after,
            "meanAngleBefore": r.mean_angle_before,
            "meanAngleAfter": r.mean_angle_after,
            "objectiveBefore": r.objective_before,
            "objectiveAfter": r.objective_after,
            "freeFaces": r.free_faces,
            "blockAdded": r.block_added,
            "valuesAdjusted": r.values_adjusted,
            "simplices": fitted.model.num_simplices(),
            "verdict": verdict(&fitted.model),
            "seconds": r.seconds,
        });
        Ok::<_, String>((fitted.model, report))
    })?;
    let (model, report) = result.map_err(|m| raise(py, "FitError", &m, &[]))?;
    Ok((Model::new(model, None), crate::value_to_py(py, &report)?))
}

/// The fit presets: list of dicts (name, dimension, description, domain, components, euler).
#[pyfunction]
pub fn presets(py: Python<'_>) -> PyResult<Bound<'_, PyAny>> {
    let list: Vec<_> = PRESETS
        .iter()
        .map(|p| {
            serde_json::json!({
                "name": p.name,
                "dimension": p.dim,
                "description": p.description,
                "domain": p.domain,
                "components": p.components,
                "euler": p.euler,
            })
        })
        .collect();
    crate::value_to_py(py, &serde_json::Value::Array(list))
}
