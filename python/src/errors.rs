//! The libraries' typed errors as the exceptions of `ism/errors.py`, keeping rule, place and text.

use ism_format::{Diagnostic, ErrorChain};
use pyo3::prelude::*;

/// An error's message with its causes, each once (see [`ErrorChain`]): the text of every exception.
pub(crate) fn chain(err: &(dyn std::error::Error + 'static)) -> String {
    ErrorChain(err).to_string()
}

/// An exception of class `kind` (a name in `ism.errors`) with `message` and the diagnostics the
/// library gave (rule id, location, message each).
pub(crate) fn raise(
    py: Python<'_>,
    kind: &str,
    message: &str,
    diagnostics: &[Diagnostic],
) -> PyErr {
    let build = || -> PyResult<PyErr> {
        let list = serde_json::to_string(diagnostics).map_err(|e| {
            pyo3::exceptions::PyRuntimeError::new_err(format!("diagnostics as JSON: {e}"))
        })?;
        let list = crate::json_to_py(py, &list)?;
        let err = py
            .import("ism.errors")?
            .getattr("_make")?
            .call1((kind, message, list))?;
        Ok(PyErr::from_value(err))
    };
    build().unwrap_or_else(|e| e)
}

/// `ism_format::Error`: I/O → `FileError`, container/encoding → `FormatError`, structure →
/// `StructureError`.
pub(crate) fn format_error(py: Python<'_>, err: &ism_format::Error) -> PyErr {
    let kind = match err {
        ism_format::Error::Io { .. } => "FileError",
        ism_format::Error::Format(_) => "FormatError",
        ism_format::Error::Structure(_) => "StructureError",
        _ => "ISMError",
    };
    raise(py, kind, &chain(err), err.diagnostics())
}

/// `ism_validate::Error`: unreadable input.
pub(crate) fn validate_error(py: Python<'_>, err: &ism_validate::Error) -> PyErr {
    match err {
        ism_validate::Error::Read(e) => format_error(py, e),
        ism_validate::Error::Io { .. } => raise(py, "FileError", &chain(err), &[]),
        _ => raise(py, "ISMError", &chain(err), &[]),
    }
}

/// `ism_sample::SampleError`.
pub(crate) fn sample_error(py: Python<'_>, err: &ism_sample::SampleError) -> PyErr {
    let kind = match err {
        ism_sample::SampleError::Io { .. } => "FileError",
        ism_sample::SampleError::InvalidArgument(_) => {
            return pyo3::exceptions::PyValueError::new_err(chain(err))
        }
        ism_sample::SampleError::Geometry(_) => "EvaluationError",
        _ => "SampleError",
    };
    raise(py, kind, &chain(err), &[])
}

/// `ism_export::Error`.
pub(crate) fn export_error(py: Python<'_>, err: &ism_export::Error) -> PyErr {
    let kind = match err {
        ism_export::Error::Inversion { .. } => "InversionError",
        _ => "ExportError",
    };
    raise(py, kind, &chain(err), &[])
}

/// A Rust panic caught at the boundary (never unwinds into the interpreter).
pub(crate) fn panic_error(py: Python<'_>, payload: &(dyn std::any::Any + Send)) -> PyErr {
    let text = payload
        .downcast_ref::<String>()
        .map(String::as_str)
        .or_else(|| payload.downcast_ref::<&str>().copied())
        .unwrap_or("(no message)");
    raise(
        py,
        "InternalError",
        &format!("internal error in the ISM library: {text}"),
        &[],
    )
}
