//! `vesselflow._core.prune_spurs`: the core's spur pruning ([`vesselflow::prune`]) on a
//! graph's arrays, for `VesselGraph.prune`.

use numpy::{PyArray1, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::blocks::{node_pairs, points};

/// Which nodes and edges of the graph `(positions, radii, edges)` pruning its spurs
/// shorter than `k` junction radii keeps, and how many spurs it removes:
/// `(node_kept, edge_kept, count)`.
#[pyfunction]
#[allow(clippy::type_complexity)]
pub fn prune_spurs<'py>(
    py: Python<'py>,
    positions: PyReadonlyArray2<'py, f64>,
    radii: PyReadonlyArray1<'py, f64>,
    edges: PyReadonlyArray2<'py, i64>,
    k: f64,
) -> PyResult<(Bound<'py, PyArray1<bool>>, Bound<'py, PyArray1<bool>>, usize)> {
    let positions = points(&positions, "positions")?;
    let radii = radii.as_array().to_vec();
    let n = positions.len();
    if radii.len() != n {
        return Err(PyValueError::new_err(format!("{} radii for {n} nodes", radii.len())));
    }
    let edges = node_pairs(&edges, n)?;
    let kept = py.detach(|| vesselflow::prune::prune_spurs(n, &edges, &positions, &radii, k));
    Ok((PyArray1::from_vec(py, kept.nodes), PyArray1::from_vec(py, kept.edges), kept.spurs))
}
