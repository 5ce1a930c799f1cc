//! Python ⇄ serde conversions.
//!
//! Everything that crosses the boundary as a `dict` has exactly the JSON shape
//! of the core's serde types (`protocol::Request`, `Response`, `IterationRecord`,
//! `ControlCommand`, `RunStatus`, the configs): Python objects are converted
//! with `pythonize`, so floats keep every bit (also NaN), and errors name the
//! offending field.

use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict, PyFloat, PyInt, PyList, PyString, PyTuple};
use serde::de::DeserializeOwned;
use serde::Serialize;

/// A copy of `obj` made of plain Python objects (`dict`, `list`, `float`,
/// `int`, `str`, `bool`, `None`): numpy arrays and numpy scalars (anything
/// with `tolist()`) are converted, tuples become lists, any other mapping
/// with `items()` becomes a dict.
pub fn plain<'py>(obj: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
    let py = obj.py();
    if obj.is_none()
        || obj.is_instance_of::<PyBool>()
        || obj.is_instance_of::<PyInt>()
        || obj.is_instance_of::<PyFloat>()
        || obj.is_instance_of::<PyString>()
    {
        return Ok(obj.clone());
    }
    if let Ok(d) = obj.cast::<PyDict>() {
        let out = PyDict::new(py);
        for (k, v) in d.iter() {
            out.set_item(k, plain(&v)?)?;
        }
        return Ok(out.into_any());
    }
    if obj.is_instance_of::<PyList>() || obj.is_instance_of::<PyTuple>() {
        let out = PyList::empty(py);
        for item in obj.try_iter()? {
            out.append(plain(&item?)?)?;
        }
        return Ok(out.into_any());
    }
    if obj.hasattr("tolist")? {
        // numpy arrays and scalars
        return plain(&obj.call_method0("tolist")?);
    }
    if obj.hasattr("items")? {
        let out = PyDict::new(py);
        for kv in obj.call_method0("items")?.try_iter()? {
            let (k, v): (Bound<'py, PyAny>, Bound<'py, PyAny>) = kv?.extract()?;
            out.set_item(k, plain(&v)?)?;
        }
        return Ok(out.into_any());
    }
    Ok(obj.clone())
}

/// Deserialize a core type from a Python object; a `ValueError` names the
/// field (`invalid response at `outcome.scan.traces[0].x`: …`).
pub fn from_py<T: DeserializeOwned>(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<T> {
    let p = plain(obj)?;
    let mut de = pythonize::Depythonizer::from_object(&p);
    serde_path_to_error::deserialize(&mut de).map_err(|e| {
        let path = e.path().to_string();
        if path == "." {
            PyValueError::new_err(format!("invalid {what}: {}", e.inner()))
        } else {
            PyValueError::new_err(format!("invalid {what} at `{path}`: {}", e.inner()))
        }
    })
}

/// Serialize a core type into plain Python objects (its JSON shape).
pub fn to_py<'py, T: Serialize + ?Sized>(
    py: Python<'py>,
    value: &T,
) -> PyResult<Bound<'py, PyAny>> {
    pythonize::pythonize(py, value)
        .map_err(|e| PyRuntimeError::new_err(format!("internal: cannot convert to Python: {e}")))
}

/// Serialize to a JSON value (for the config merge).
pub fn to_value<T: Serialize + ?Sized>(value: &T) -> PyResult<serde_json::Value> {
    serde_json::to_value(value)
        .map_err(|e| PyRuntimeError::new_err(format!("internal: cannot serialize: {e}")))
}
