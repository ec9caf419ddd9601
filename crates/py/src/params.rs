//! Parameter values between Python objects and [`vesselflow::Value`].

use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyFloat, PyString};
use vesselflow::{Params, Value};

/// Read a keyword argument's value. `bool` is tested before `int` because Python's
/// `bool` is an `int`; NumPy scalars are accepted: `numpy.bool_` by type (it has
/// `__float__` but no `__index__`), the others through `__index__` / `__float__`.
pub fn value_from_py(name: &str, obj: &Bound<'_, PyAny>) -> PyResult<Value> {
    if obj.is_instance_of::<PyBool>() || is_numpy_bool(obj)? {
        return Ok(Value::Bool(obj.is_truthy()?));
    }
    if obj.is_instance_of::<PyString>() {
        return Ok(Value::Str(obj.extract()?));
    }
    if obj.is_instance_of::<PyFloat>() {
        return Ok(Value::Float(obj.extract()?));
    }
    if obj.hasattr("__index__")? {
        return obj.extract::<i64>().map(Value::Int).map_err(|e| {
            PyValueError::new_err(format!("invalid parameter `{name}`: {obj} is not a 64-bit integer ({e})"))
        });
    }
    if obj.hasattr("__float__")? {
        // Not `?`: Python 3.9's `complex` has a `__float__` that raises (the TypeError below).
        if let Ok(value) = obj.extract::<f64>() {
            return Ok(Value::Float(value));
        }
    }
    Err(PyTypeError::new_err(format!(
        "parameter `{name}` must be a bool, int, float or str, got {}",
        obj.get_type().name()?
    )))
}

fn is_numpy_bool(obj: &Bound<'_, PyAny>) -> PyResult<bool> {
    let ty = obj.get_type();
    // `to_cow`, not `to_str`: the stable ABI has no borrowed UTF-8 view before 3.10.
    Ok(ty.module()? == "numpy" && matches!(&*ty.name()?.to_cow()?, "bool" | "bool_"))
}

/// A parameter value as the Python object it came from.
pub fn value_to_py<'py>(py: Python<'py>, value: &Value) -> PyResult<Bound<'py, PyAny>> {
    Ok(match value {
        Value::Bool(b) => PyBool::new(py, *b).to_owned().into_any(),
        Value::Int(i) => i.into_pyobject(py)?.into_any(),
        Value::Float(x) => x.into_pyobject(py)?.into_any(),
        Value::Str(s) => PyString::new(py, s).into_any(),
    })
}

/// Every parameter with its default, in documentation order.
#[pyfunction]
pub fn param_defaults(py: Python<'_>) -> PyResult<Vec<(&'static str, Bound<'_, PyAny>)>> {
    Params::default().values().iter().map(|(name, v)| Ok((*name, value_to_py(py, v)?))).collect()
}
