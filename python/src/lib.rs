//! The `ism` Python package's compiled half, `ism._ism`: thin glue over the ISM library crates.
//!
//! Every operation is a call into `ism-format`, `ism-validate`, `ism-sample`, `ism-export` or
//! `ism-fit`; this crate only converts between Python objects and the libraries' types, runs long
//! calls off the interpreter's thread ([`worker`]) and turns the libraries' typed errors into the
//! exceptions of `ism/errors.py` ([`errors`]). The Python half (`ism/`) holds the pure-Python
//! pieces: the exception classes, input checks, adapters to trimesh, PyVista and meshio.

use pyo3::prelude::*;

mod errors;
mod fit;
mod model;
mod tools;
mod worker;

/// Imports the pure-Python helper module `ism._convert`.
pub(crate) fn convert(py: Python<'_>) -> PyResult<Bound<'_, PyModule>> {
    py.import("ism._convert")
}

/// A Python object from JSON text (`json.loads`).
pub(crate) fn json_to_py<'py>(py: Python<'py>, text: &str) -> PyResult<Bound<'py, PyAny>> {
    convert(py)?.getattr("from_json")?.call1((text,))
}

/// A Python object from a JSON value.
pub(crate) fn value_to_py<'py>(
    py: Python<'py>,
    value: &serde_json::Value,
) -> PyResult<Bound<'py, PyAny>> {
    json_to_py(py, &value.to_string())
}

/// A JSON value from a Python object (`json.dumps`, NaN refused).
pub(crate) fn py_to_value(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<serde_json::Value> {
    let text: String = convert(obj.py())?
        .getattr("to_json")?
        .call1((obj, name))?
        .extract()?;
    serde_json::from_str(&text).map_err(|e| {
        pyo3::exceptions::PyValueError::new_err(format!("{name}: not representable as JSON: {e}"))
    })
}

/// The compiled module `ism._ism`.
#[pymodule]
fn _ism(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("FORMAT_VERSION", ism_format::FORMAT_VERSION.to_string())?;
    m.add_class::<model::Model>()?;
    m.add_class::<model::Stage>()?;
    m.add_function(wrap_pyfunction!(model::read_path, m)?)?;
    m.add_function(wrap_pyfunction!(model::read_bytes, m)?)?;
    m.add_function(wrap_pyfunction!(tools::validate_path, m)?)?;
    m.add_function(wrap_pyfunction!(tools::validate_bytes, m)?)?;
    m.add_function(wrap_pyfunction!(fit::fit, m)?)?;
    m.add_function(wrap_pyfunction!(fit::fit_mesh, m)?)?;
    m.add_function(wrap_pyfunction!(fit::fit_hermite, m)?)?;
    m.add_function(wrap_pyfunction!(fit::presets, m)?)?;
    Ok(())
}
