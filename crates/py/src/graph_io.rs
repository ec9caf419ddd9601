//! `write_graph`: graph arrays from Python to the io crate's atomic writers, so that
//! `VesselGraph.save` and the `vesselflow` binary write the same files.

use std::path::PathBuf;

use ndarray::Array2;
use numpy::{IntoPyArray, PyArray2, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use serde_json::Value;
use vesselflow_io::GraphArrays;

use crate::errors;

/// Write a graph to `path` in the format its extension names (the io crate's
/// registry: `.graphml`, `.json`, `.npz`, `.swc`, `.vtp`, `.csv`, `.precomputed`). `info_json` and `params_json` are JSON objects (text). The file appears
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

/// Positions of a run (physical units, array axes) in the frame `coordinates`
/// (`"array"`, `"xyz"`, `"world"`; the io crate's rule, see `vesselflow_io::to_frame`),
/// with the voxel-to-world `affine` (4 × 4; needed for `"world"`). Returns the new
/// positions, the spacing to store and a warning for the user, if any.
#[pyfunction]
#[pyo3(signature = (positions, spacing, coordinates, affine=None))]
#[allow(clippy::type_complexity)]
pub fn to_frame<'py>(
    py: Python<'py>,
    positions: PyReadonlyArray2<'py, f64>,
    spacing: [f64; 3],
    coordinates: &str,
    affine: Option<PyReadonlyArray2<'py, f64>>,
) -> PyResult<(Bound<'py, PyArray2<f64>>, [f64; 3], Option<String>)> {
    let coordinates: vesselflow_io::Coordinates = coordinates.parse().map_err(PyValueError::new_err)?;
    let affine = match affine {
        Some(a) => {
            let a = a.as_array();
            if a.shape() != [4, 4] {
                return Err(PyValueError::new_err(format!("affine must have shape (4, 4), got {:?}", a.shape())));
            }
            std::array::from_fn(|r| std::array::from_fn(|c| a[[r, c]]))
        }
        None if coordinates == vesselflow_io::Coordinates::World => {
            return Err(PyValueError::new_err(
                "coordinates='world' needs the image's voxel-to-world affine: pass affine= \
                 (load_volume(path, return_affine=True) returns it)",
            ))
        }
        None => vesselflow_io::spacing_affine(spacing),
    };
    let view = positions.as_array();
    if view.ncols() != 3 {
        return Err(PyValueError::new_err(format!("positions must have shape (N, 3), got {:?}", view.shape())));
    }
    let mut rows: Vec<[f64; 3]> = view.rows().into_iter().map(|r| [r[0], r[1], r[2]]).collect();
    let frame = vesselflow_io::to_frame(&mut rows, spacing, coordinates, &affine).map_err(PyValueError::new_err)?;
    let out = Array2::from_shape_vec((rows.len(), 3), rows.into_flattened())
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    Ok((out.into_pyarray(py), frame.spacing, frame.warning))
}
