//! `vesselflow._core.binarise`: the input rule of `vesselflow_io::binarise` on a NumPy
//! array, so that `skeletonize`, `load_volume` and the command line accept the same
//! masks and refuse the same images.

use numpy::prelude::*;
use numpy::{Element, PyArrayDyn, PyUntypedArray};
use pyo3::exceptions::{PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use vesselflow_io::{Binariser, MaskRule, Sample};

use crate::errors;

/// The mask of `data` (any shape) by the input rule: `data` itself if it is bool and
/// neither `threshold` nor `label` is given, a bool view of it if it is a binary image
/// of bytes whose values are 0 and 1 (the usual segmentation file: no copy of the
/// volume), else a new bool array (`data > threshold`, `data == label`, or the binary
/// image's non-zero voxels). An image that is not a
/// mask, or both `threshold` and `label`, is a `ValueError`; a dtype that cannot hold
/// a mask a `TypeError`.
#[pyfunction]
#[pyo3(signature = (data, threshold = None, label = None))]
pub fn binarise<'py>(
    py: Python<'py>,
    data: &Bound<'py, PyAny>,
    threshold: Option<f64>,
    label: Option<f64>,
) -> PyResult<Bound<'py, PyAny>> {
    let rule = MaskRule::new(threshold, label).map_err(PyValueError::new_err)?;
    mask_of(py, data, rule)
}

/// [`binarise`] with the rule already made.
pub fn mask_of<'py>(py: Python<'py>, data: &Bound<'py, PyAny>, rule: MaskRule) -> PyResult<Bound<'py, PyAny>> {
    let array = data.cast::<PyUntypedArray>().map_err(|_| {
        PyTypeError::new_err(format!(
            "mask must be a numpy.ndarray, got {}",
            data.get_type().name().map_or_else(|_| "?".into(), |n| n.to_string())
        ))
    })?;
    let dtype = array.dtype();
    // Byte-swapped data (read from big-endian files) and half floats are copied to a
    // native type first.
    if dtype.is_native_byteorder() == Some(false) {
        let native = dtype.call_method1("newbyteorder", ("=",))?;
        return mask_of(py, &array.call_method1("astype", (native,))?, rule);
    }
    match (dtype.kind(), dtype.itemsize()) {
        (b'b', 1) if rule == MaskRule::Binary => Ok(data.clone()),
        // A NumPy bool byte may hold any value (`uint8_array.view(bool)`), which a Rust
        // `bool` must not: read bools as bytes, non-zero = true.
        (b'b', 1) => typed::<u8, bool>(py, &array.call_method1("view", ("u1",))?, rule, |x| x != 0),
        (b'i', 1) if rule == MaskRule::Binary && zeros_and_ones::<i8>(py, data)? => data.call_method1("view", ("?",)),
        (b'u', 1) if rule == MaskRule::Binary && zeros_and_ones::<u8>(py, data)? => data.call_method1("view", ("?",)),
        (b'i', 1) => typed::<i8, i8>(py, data, rule, |x| x),
        (b'i', 2) => typed::<i16, i16>(py, data, rule, |x| x),
        (b'i', 4) => typed::<i32, i32>(py, data, rule, |x| x),
        (b'i', 8) => typed::<i64, i64>(py, data, rule, |x| x),
        (b'u', 1) => typed::<u8, u8>(py, data, rule, |x| x),
        (b'u', 2) => typed::<u16, u16>(py, data, rule, |x| x),
        (b'u', 4) => typed::<u32, u32>(py, data, rule, |x| x),
        (b'u', 8) => typed::<u64, u64>(py, data, rule, |x| x),
        (b'f', 2) => mask_of(py, &array.call_method1("astype", ("f4",))?, rule),
        (b'f', 4) => typed::<f32, f32>(py, data, rule, |x| x),
        (b'f', 8) => typed::<f64, f64>(py, data, rule, |x| x),
        _ => {
            Err(PyTypeError::new_err(format!("mask dtype {dtype} is not bool, integer or float: it cannot be a mask")))
        }
    }
}

/// Whether every value of the byte image `data` is 0 or 1 (one pass, the GIL
/// released, nothing allocated): such an image is its own mask, read as bool.
fn zeros_and_ones<T: Element + Sample + Sync>(py: Python<'_>, data: &Bound<'_, PyAny>) -> PyResult<bool> {
    let array = data.cast::<PyArrayDyn<T>>().map_err(|_| PyRuntimeError::new_err("mask dtype dispatch failed"))?;
    let readonly = array.try_readonly().map_err(|e| PyValueError::new_err(format!("mask cannot be read: {e}")))?;
    let view = readonly.as_array();
    Ok(py.detach(|| {
        let mut binariser = Binariser::<T>::new(MaskRule::Binary);
        for &x in view.iter() {
            binariser.vessel(x);
            if binariser.refused() {
                return false;
            }
        }
        binariser.vessel_value().is_none_or(|v| v.to_f64() == 1.0)
    }))
}

/// Apply the rule to `data` of element type `T`, each value seen as `convert(value)`,
/// with the GIL released.
fn typed<'py, T: Element + Copy + Sync, S: Sample>(
    py: Python<'py>,
    data: &Bound<'py, PyAny>,
    rule: MaskRule,
    convert: impl Fn(T) -> S + Send + Sync,
) -> PyResult<Bound<'py, PyAny>> {
    let array = data.cast::<PyArrayDyn<T>>().map_err(|_| PyRuntimeError::new_err("mask dtype dispatch failed"))?;
    let readonly = array.try_readonly().map_err(|e| PyValueError::new_err(format!("mask cannot be read: {e}")))?;
    let view = readonly.as_array();
    let shape = format!("{:?}", view.shape());
    let mask = errors::no_panic(
        || format!("binarise, shape {shape}, dtype {}", S::NAME),
        || {
            py.detach(|| {
                let mut binariser = Binariser::<S>::new(rule);
                let mask = view.map(|&x| binariser.vessel(convert(x)) != 0);
                binariser.finish().map(|()| mask)
            })
        },
    )?
    .map_err(PyValueError::new_err)?;
    Ok(mask.into_pyarray(py).into_any())
}
