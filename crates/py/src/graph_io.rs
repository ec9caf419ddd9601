//! `write_graph`: graph arrays from Python to the io crate's atomic writers, so that
//! `VesselGraph.save` and the `vesselflow` binary write the same files.

use std::path::PathBuf;

use numpy::{PyReadonlyArray1, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use serde_json::Value;
use vesselflow_io::GraphArrays;

use crate::errors;

/// Write a graph to `path` in the format its extension names (`.graphml`, `.json`,
/// `.npz`). `info_json` and `params_json` are JSON objects (text). The file appears
/// complete or not at all; the GIL is released while writing.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
pub fn write_graph(
    py: Python<'_>,
    path: PathBuf,
    positions: PyReadonlyArray2<'_, f64>,
    radii: PyReadonlyArray1<'_, f64>,
    edges: PyReadonlyArray2<'_, i64>,
    spacing: Vec<f64>,
    info_json: &str,
    params_json: &str,
) -> PyResult<()> {
    let spacing: [f64; 3] = spacing
        .try_into()
        .map_err(|s: Vec<f64>| PyValueError::new_err(format!("spacing must hold 3 numbers, got {}", s.len())))?;
    let parse = |name: &str, text: &str| {
        serde_json::from_str::<Value>(text).map_err(|e| PyValueError::new_err(format!("{name} is not valid JSON: {e}")))
    };
    let (info, params) = (parse("info", info_json)?, parse("params", params_json)?);
    let graph = GraphArrays {
        positions: positions.as_array(),
        radii: radii.as_array(),
        edges: edges.as_array(),
        spacing,
        info: &info,
        params: &params,
    };
    let context = || format!("writing {} nodes to {}", graph.positions.nrows(), path.display());
    py.detach(|| errors::no_panic(context, || vesselflow_io::write_graph_arrays(&path, &graph)))?
        .map_err(errors::io_to_py)
}
