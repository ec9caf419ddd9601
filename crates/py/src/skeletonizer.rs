//! `vesselflow._core.Skeletonizer`: keyword parameters in, NumPy mask borrowed without a
//! copy, the core run with the GIL released, arrays and a run-record dict out.

use ndarray::Array2;
use numpy::prelude::*;
use numpy::{Element, PyArray1, PyArray3, PyUntypedArray};
use pyo3::exceptions::{PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple};
use vesselflow::{Params, Progress, RunInfo, Skeleton, Voxel};

use crate::params::{value_from_py, value_to_py};
use crate::{binarise, errors, watch};
use vesselflow_io::MaskRule;

/// The method with a fixed set of parameters (see `vesselflow.Skeletonizer`).
#[pyclass(module = "vesselflow._core", name = "Skeletonizer", frozen)]
pub struct PySkeletonizer {
    pub(crate) inner: vesselflow::Skeletonizer,
}

#[pymethods]
impl PySkeletonizer {
    /// Check and keep the parameters; unknown names are a `TypeError`, bad values a
    /// `ValueError` naming the parameter.
    #[new]
    #[pyo3(signature = (**params))]
    fn new(params: Option<&Bound<'_, PyDict>>) -> PyResult<Self> {
        let mut p = Params::default();
        for (key, value) in params.into_iter().flatten() {
            let name: String = key.extract()?;
            p.set(&name, &value_from_py(&name, &value)?).map_err(errors::core)?;
        }
        let inner = errors::no_panic(|| format!("parameters {p:?}"), || vesselflow::Skeletonizer::new(p.clone()))?
            .map_err(errors::core)?;
        Ok(Self { inner })
    }

    /// Every parameter and its value, in documentation order.
    #[getter]
    fn params<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let dict = PyDict::new(py);
        for (name, v) in self.inner.params().values() {
            dict.set_item(name, value_to_py(py, &v)?)?;
        }
        Ok(dict)
    }

    /// `Skeletonizer(name=value, ...)` with every parameter, values as Python literals.
    fn __repr__(&self, py: Python<'_>) -> PyResult<String> {
        let args = self
            .inner
            .params()
            .values()
            .iter()
            .map(|(name, v)| Ok(format!("{name}={}", value_to_py(py, v)?.repr()?)))
            .collect::<PyResult<Vec<String>>>()?;
        Ok(format!("Skeletonizer({})", args.join(", ")))
    }

    fn __eq__(&self, other: &Self) -> bool {
        self.inner.params() == other.inner.params()
    }

    /// Skeletonize `mask` (3-D array made a mask by the input rule, see `binarise`,
    /// with `threshold` or `label`) with voxel `spacing` (3 numbers, or one for all
    /// axes). Returns `(positions, radii, edges, info)`.
    #[pyo3(
        signature = (mask, spacing = Spacing::Axes(vec![1.0, 1.0, 1.0]), progress = None, threshold = None, label = None),
        text_signature = "(self, mask, spacing=(1.0, 1.0, 1.0), progress=None, threshold=None, label=None)"
    )]
    fn run<'py>(
        &self,
        py: Python<'py>,
        mask: &Bound<'py, PyAny>,
        spacing: Spacing,
        progress: Option<Bound<'py, PyAny>>,
        threshold: Option<f64>,
        label: Option<f64>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let spacing = spacing.axes()?;
        let rule = MaskRule::new(threshold, label).map_err(PyValueError::new_err)?;
        if let Some(cb) = &progress {
            if !cb.is_callable() {
                return Err(PyTypeError::new_err(format!(
                    "progress must be callable or None, got {}",
                    cb.get_type().name()?
                )));
            }
        }
        let progress = progress.map(Bound::unbind);
        // The run goes on a helper thread while this one watches for Ctrl-C (see
        // `watch`). The observer runs there without the GIL; it re-attaches only to
        // call the callback, and parks its exception for `errors::to_py`.
        let mut pending: Option<PyErr> = None;
        let mut signal: Option<PyErr> = None;
        let mut observer = |p: &Progress| -> bool {
            match &progress {
                Some(cb) => Python::attach(|py| {
                    let step = cb.call1(py, (p.stage, p.iteration, p.nodes, p.measure)).map(drop);
                    step.map_err(|e| pending = Some(e)).is_ok()
                }),
                None => true,
            }
        };
        // `max_memory` left at "auto": what this process may still use, read now.
        let limited;
        let skeletonizer = match self.inner.params().max_memory {
            Some(_) => &self.inner,
            None => {
                let mut params = self.inner.params().clone();
                params.max_memory = Some(vesselflow_io::budget::usable_memory().unwrap_or(0));
                limited = vesselflow::Skeletonizer::new(params).map_err(errors::core)?;
                &limited
            }
        };
        let skeleton = run_any(py, skeletonizer, mask, rule, spacing, &mut observer, &mut signal);
        let skeleton = skeleton?.map_err(|e| errors::to_py(e, pending.take().or(signal.take())))?;
        skeleton_to_py(py, skeleton)
    }
}

/// Voxel spacing as Python gives it: three numbers, or one for every axis.
#[derive(FromPyObject)]
pub enum Spacing {
    Isotropic(f64),
    Axes(Vec<f64>),
}

impl Spacing {
    /// The spacing of axes 0, 1, 2; anything but 1 or 3 numbers is the core's
    /// `InvalidSpacing` (its range is checked by the run).
    fn axes(self) -> PyResult<[f64; 3]> {
        match self {
            Spacing::Isotropic(s) => Ok([s; 3]),
            Spacing::Axes(s) => s.try_into().map_err(|s| errors::core(vesselflow::volume::invalid_spacing(s))),
        }
    }
}

/// Check that `mask` is a 3-D array, make it a bool mask by `rule` (no copy if it is
/// one already, see [`binarise::mask_of`]) and run on it. The outer `PyResult` holds
/// mask errors (and caught panics), the inner one the core's; `signal` receives the
/// exception of a signal handler that stopped the run.
fn run_any(
    py: Python<'_>,
    sk: &vesselflow::Skeletonizer,
    mask: &Bound<'_, PyAny>,
    rule: MaskRule,
    spacing: [f64; 3],
    observer: &mut (dyn FnMut(&Progress) -> bool + Send),
    signal: &mut Option<PyErr>,
) -> PyResult<vesselflow::Result<Skeleton>> {
    if let Ok(array) = mask.cast::<PyUntypedArray>() {
        if array.ndim() != 3 {
            return Err(PyValueError::new_err(format!("mask must be 3-D, got shape {:?}", array.shape())));
        }
    }
    let mask = binarise::mask_of(py, mask, rule)?;
    // A NumPy bool byte may hold any value (`uint8_array.view(bool)`), which a Rust
    // `bool` must not: read bool masks through a uint8 view (no copy).
    let bytes = mask.call_method1("view", ("u1",))?;
    run_typed::<u8>(py, sk, &bytes, spacing, observer, signal)
}

/// Borrow the array read-only (any strides, no copy) and run with the GIL released,
/// watching for Ctrl-C ([`watch::watched`]); a panic becomes a `RuntimeError`.
fn run_typed<T: Voxel + Element>(
    py: Python<'_>,
    sk: &vesselflow::Skeletonizer,
    mask: &Bound<'_, PyAny>,
    spacing: [f64; 3],
    observer: &mut (dyn FnMut(&Progress) -> bool + Send),
    signal: &mut Option<PyErr>,
) -> PyResult<vesselflow::Result<Skeleton>> {
    let array = mask.cast::<PyArray3<T>>().map_err(|_| PyRuntimeError::new_err("mask dtype dispatch failed"))?;
    let readonly = array.try_readonly().map_err(|e| PyValueError::new_err(format!("mask cannot be read: {e}")))?;
    let view = readonly.as_array();
    let context =
        || format!("input shape {:?}, dtype {}, spacing {spacing:?}", view.shape(), std::any::type_name::<T>());
    let (result, pending) =
        watch::watched(py, |stop| errors::no_panic(context, || sk.run_with_stop(view, spacing, stop, observer)));
    *signal = pending;
    result
}

/// `(positions (N, 3) float64, radii (N,) float64, edges (E, 2) int64, info dict)`.
pub(crate) fn skeleton_to_py(py: Python<'_>, sk: Skeleton) -> PyResult<Bound<'_, PyTuple>> {
    let shape_err = |e: ndarray::ShapeError| PyRuntimeError::new_err(e.to_string());
    let n = sk.positions.len();
    let positions = Array2::from_shape_vec((n, 3), sk.positions.as_flattened().to_vec()).map_err(shape_err)?;
    let edge_ids = sk.edges.as_flattened().iter().map(|&i| i as i64).collect();
    let edges = Array2::from_shape_vec((sk.edges.len(), 2), edge_ids).map_err(shape_err)?;
    PyTuple::new(
        py,
        [
            positions.into_pyarray(py).into_any(),
            PyArray1::from_vec(py, sk.radii).into_any(),
            edges.into_pyarray(py).into_any(),
            info_to_py(py, &sk.info)?.into_any(),
        ],
    )
}

/// The run record as a dict, through the io crate's JSON form so that the dict and
/// the graph files agree field for field.
fn info_to_py<'py>(py: Python<'py>, info: &RunInfo) -> PyResult<Bound<'py, PyAny>> {
    let text = vesselflow_io::run_info_json(info).to_string();
    py.import("json")?.call_method1("loads", (text,))
}
