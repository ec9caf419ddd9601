//! `vesselflow._core.contract_block` and `merge_blocks`: the two phases of a chunked
//! run ([`vesselflow::blocks`]), a block part as a dict of NumPy arrays.

use ndarray::Array2;
use numpy::prelude::*;
use numpy::{PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple};
use vesselflow::blocks::{BlockPart, NodeRecord};
use vesselflow::blocks_route::{owner_voxel, RoutedPart};
use vesselflow::blocks_sprouts::SproutRecord;
use vesselflow::graph::{RunInfo, Skeleton};
use vesselflow::resample::Chain;
use vesselflow::Stop;

use crate::errors;
use crate::skeletonizer::{skeleton_to_py, PySkeletonizer};

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(contract_block, m)?)?;
    m.add_function(wrap_pyfunction!(merge_blocks, m)?)?;
    m.add_function(wrap_pyfunction!(largest_radius, m)?)?;
    m.add_function(wrap_pyfunction!(owner_voxels, m)?)?;
    m.add_function(wrap_pyfunction!(route_block, m)?)?;
    m.add_function(wrap_pyfunction!(splice_routes, m)?)?;
    Ok(())
}

/// The block phase on `mask` (uint8, block plus halo) whose voxel `(0, 0, 0)` is voxel
/// `origin` of a volume of shape `volume`; `core` the core's `[start, stop)` per axis.
/// Returns the part as a dict of arrays (see `merge_blocks`).
#[pyfunction]
pub fn contract_block<'py>(
    py: Python<'py>,
    skeletonizer: PyRef<'py, PySkeletonizer>,
    mask: PyReadonlyArray3<'py, u8>,
    origin: [i64; 3],
    core: [[usize; 2]; 3],
    volume: [usize; 3],
    spacing: [f64; 3],
) -> PyResult<Bound<'py, PyDict>> {
    let view = mask.as_array();
    let sk = &skeletonizer.inner;
    let context = || format!("block at {origin:?}, shape {:?}, core {core:?}", view.shape());
    let part = py
        .detach(|| errors::no_panic(context, || sk.contract_block(view, origin, core, volume, spacing, &Stop::new())))?
        .map_err(errors::core)?;
    part_to_py(py, part)
}

/// The largest vessel radius of `mask` (uint8) in physical units, or `None` if it holds
/// no foreground: the per-chunk pass of a chunked run.
#[pyfunction]
pub fn largest_radius<'py>(
    py: Python<'py>,
    skeletonizer: PyRef<'py, PySkeletonizer>,
    mask: PyReadonlyArray3<'py, u8>,
    spacing: [f64; 3],
) -> PyResult<Option<f64>> {
    let view = mask.as_array();
    let sk = &skeletonizer.inner;
    let context = || format!("chunk of shape {:?}", view.shape());
    py.detach(|| errors::no_panic(context, || sk.largest_radius(view, spacing)))?.map_err(errors::core)
}

/// The merge phase: the graph of the `parts` (dicts from `contract_block`, in a fixed
/// block order) as `(positions, radii, edges, info)`.
#[pyfunction]
pub fn merge_blocks<'py>(
    py: Python<'py>,
    skeletonizer: PyRef<'py, PySkeletonizer>,
    parts: Vec<Bound<'py, PyDict>>,
    volume: [usize; 3],
    spacing: [f64; 3],
) -> PyResult<Bound<'py, PyTuple>> {
    let parts = parts.iter().map(part_from_py).collect::<PyResult<Vec<_>>>()?;
    let sk = &skeletonizer.inner;
    let skeleton = py
        .detach(|| errors::no_panic(|| format!("{} blocks", parts.len()), || sk.merge_blocks(&parts, volume, spacing)))?
        .map_err(errors::core)?;
    skeleton_to_py(py, skeleton)
}

pub(crate) fn points(a: &PyReadonlyArray2<'_, f64>, name: &str) -> PyResult<Vec<[f64; 3]>> {
    let a = a.as_array();
    if a.ncols() != 3 {
        return Err(PyValueError::new_err(format!("`{name}` must have 3 columns")));
    }
    Ok(a.rows().into_iter().map(|r| [r[0], r[1], r[2]]).collect())
}

pub(crate) fn pairs_of<T: Copy + numpy::Element>(a: &PyReadonlyArray2<'_, T>, name: &str) -> PyResult<Vec<[T; 2]>> {
    let a = a.as_array();
    if a.ncols() != 2 {
        return Err(PyValueError::new_err(format!("`{name}` must have 2 columns")));
    }
    Ok(a.rows().into_iter().map(|r| [r[0], r[1]]).collect())
}

/// The rows of `edges` as pairs of node ids below `n`.
pub(crate) fn node_pairs(edges: &PyReadonlyArray2<'_, i64>, n: usize) -> PyResult<Vec<[usize; 2]>> {
    pairs_of(edges, "edges")?
        .into_iter()
        .map(|e| {
            let id = |i: i64| usize::try_from(i).ok().filter(|&i| i < n);
            match (id(e[0]), id(e[1])) {
                (Some(a), Some(b)) => Ok([a, b]),
                _ => Err(PyValueError::new_err(format!("edge {e:?} refers to a node outside 0..{n}"))),
            }
        })
        .collect()
}

/// The owner voxel of every edge (rows of global node ids into `positions`), for the
/// routing phase: an `(m, 3)` array.
#[pyfunction]
pub fn owner_voxels<'py>(
    py: Python<'py>,
    positions: PyReadonlyArray2<'py, f64>,
    edges: PyReadonlyArray2<'py, i64>,
    spacing: [f64; 3],
    volume: [usize; 3],
) -> PyResult<Bound<'py, PyArray2<i64>>> {
    let p = points(&positions, "positions")?;
    let e = pairs_of(&edges, "edges")?;
    let mut out = Vec::with_capacity(3 * e.len());
    for [a, b] in e {
        let (Some(&pa), Some(&pb)) =
            (usize::try_from(a).ok().and_then(|a| p.get(a)), usize::try_from(b).ok().and_then(|b| p.get(b)))
        else {
            return Err(PyValueError::new_err(format!("edge {a}-{b} joins a node not in positions")));
        };
        out.extend(owner_voxel(pa, pb, spacing, volume).map(|x| x as i64));
    }
    let n = out.len() / 3;
    Ok(Array2::from_shape_vec((n, 3), out).map_err(shape_err)?.into_pyarray(py))
}

/// The routing phase on one block (`mask` uint8, block plus halo; see `contract_block`
/// for `origin`, `core`, `volume`): `nodes` ascending global ids, `positions` theirs,
/// `edges` the owned sorted pairs of global ids. Returns the routed part as a dict of
/// arrays, or with `halo` (a list per axis) when the read was too small.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
pub fn route_block<'py>(
    py: Python<'py>,
    skeletonizer: PyRef<'py, PySkeletonizer>,
    mask: PyReadonlyArray3<'py, u8>,
    origin: [i64; 3],
    core: [[usize; 2]; 3],
    volume: [usize; 3],
    spacing: [f64; 3],
    nodes: PyReadonlyArray1<'py, u32>,
    positions: PyReadonlyArray2<'py, f64>,
    edges: PyReadonlyArray2<'py, u32>,
) -> PyResult<Bound<'py, PyDict>> {
    let view = mask.as_array();
    let sk = &skeletonizer.inner;
    let nodes = nodes.as_array().to_vec();
    let p = points(&positions, "positions")?;
    let e = pairs_of(&edges, "edges")?;
    let context = || format!("routing block at {origin:?}, shape {:?}, core {core:?}", view.shape());
    let part = py
        .detach(|| errors::no_panic(context, || sk.route_block(view, origin, core, volume, spacing, &nodes, &p, &e)))?
        .map_err(errors::core)?;
    let d = PyDict::new(py);
    let replaced =
        Array2::from_shape_vec((part.replaced.len(), 2), part.replaced.as_flattened().to_vec()).map_err(shape_err)?;
    d.set_item("replaced", replaced.into_pyarray(py))?;
    let n = part.positions.len();
    d.set_item(
        "positions",
        Array2::from_shape_vec((n, 3), part.positions.as_flattened().to_vec()).map_err(shape_err)?.into_pyarray(py),
    )?;
    d.set_item("radii", PyArray1::from_vec(py, part.radii))?;
    d.set_item(
        "edges",
        Array2::from_shape_vec((part.edges.len(), 2), part.edges.as_flattened().to_vec())
            .map_err(shape_err)?
            .into_pyarray(py),
    )?;
    d.set_item("halo", part.halo.map(|h| h.to_vec()))?;
    Ok(d)
}

/// The merged graph `(positions, radii, edges)` with the routed parts (dicts from
/// `route_block`, in block order) spliced in and its short spurs pruned, as
/// `(positions, radii, edges, info)`.
#[pyfunction]
pub fn splice_routes<'py>(
    py: Python<'py>,
    skeletonizer: PyRef<'py, PySkeletonizer>,
    positions: PyReadonlyArray2<'py, f64>,
    radii: PyReadonlyArray1<'py, f64>,
    edges: PyReadonlyArray2<'py, i64>,
    parts: Vec<Bound<'py, PyDict>>,
    spacing: [f64; 3],
) -> PyResult<Bound<'py, PyTuple>> {
    let get = |d: &Bound<'py, PyDict>, name: &str| {
        d.get_item(name)?.ok_or_else(|| PyValueError::new_err(format!("routed part has no `{name}`")))
    };
    let mut routed = Vec::with_capacity(parts.len());
    for d in &parts {
        let replaced: PyReadonlyArray2<u32> = get(d, "replaced")?.extract()?;
        let pos: PyReadonlyArray2<f64> = get(d, "positions")?.extract()?;
        let r: PyReadonlyArray1<f64> = get(d, "radii")?.extract()?;
        let e: PyReadonlyArray2<i64> = get(d, "edges")?.extract()?;
        let halo: Option<Vec<usize>> = get(d, "halo")?.extract()?;
        let halo = halo
            .map(|h| <[usize; 3]>::try_from(h).map_err(|_| PyValueError::new_err("`halo` needs 3 values")))
            .transpose()?;
        routed.push(RoutedPart {
            replaced: pairs_of(&replaced, "replaced")?,
            positions: points(&pos, "positions")?,
            radii: r.as_array().to_vec(),
            edges: pairs_of(&e, "edges")?,
            halo,
        });
    }
    let positions = points(&positions, "positions")?;
    let edges = node_pairs(&edges, positions.len())?;
    let merged = Skeleton { positions, radii: radii.as_array().to_vec(), edges, spacing, info: RunInfo::default() };
    let sk = &skeletonizer.inner;
    let out = py
        .detach(|| {
            errors::no_panic(|| format!("{} routed blocks", routed.len()), || sk.splice_routes(merged, &routed))
        })?
        .map_err(errors::core)?;
    skeleton_to_py(py, out)
}

/// An array of the wrong shape for its rows: the one error of building the arrays a
/// block part or a routed part travels in.
fn shape_err(e: ndarray::ShapeError) -> PyErr {
    PyValueError::new_err(e.to_string())
}

fn part_to_py(py: Python<'_>, part: BlockPart) -> PyResult<Bound<'_, PyDict>> {
    let rows = |v: Vec<f64>, n: usize| Array2::from_shape_vec((n, 3), v);
    let n = part.cells.len();
    let d = PyDict::new(py);
    d.set_item("component", PyArray1::from_iter(py, part.cells.iter().map(|s| s.component)))?;
    let cells = Array2::from_shape_vec((n, 3), part.cells.iter().flat_map(|s| s.cell).collect()).map_err(shape_err)?;
    d.set_item("cell", cells.into_pyarray(py))?;
    d.set_item("node", PyArray1::from_iter(py, part.cells.iter().map(|s| s.node)))?;
    let position = rows(part.cells.iter().flat_map(|s| s.position).collect(), n).map_err(shape_err)?;
    d.set_item("position", position.into_pyarray(py))?;
    d.set_item("count", PyArray1::from_iter(py, part.cells.iter().map(|s| s.count)))?;
    d.set_item("radius", PyArray1::from_iter(py, part.cells.iter().map(|s| s.radius)))?;
    d.set_item("split_radius", PyArray1::from_iter(py, part.cells.iter().map(|s| s.split_radius)))?;
    for (name, pairs) in [("edges", &part.edges), ("bridges", &part.bridges)] {
        let a = Array2::from_shape_vec((pairs.len(), 2), pairs.as_flattened().to_vec()).map_err(shape_err)?;
        d.set_item(name, a.into_pyarray(py))?;
    }
    d.set_item("face_voxel", PyArray1::from_iter(py, part.faces.iter().map(|f| f.0)))?;
    d.set_item("face_cell", PyArray1::from_iter(py, part.faces.iter().map(|f| f.1)))?;
    // Sprouts: one row each, their nodes concatenated (`sprout_length` each).
    let k = part.sprouts.len();
    d.set_item("sprout_round", PyArray1::from_iter(py, part.sprouts.iter().map(|s| s.round)))?;
    d.set_item("sprout_split", PyArray1::from_iter(py, part.sprouts.iter().map(|s| s.split)))?;
    let start = rows(part.sprouts.iter().flat_map(|s| s.start).collect(), k).map_err(shape_err)?;
    d.set_item("sprout_start", start.into_pyarray(py))?;
    d.set_item("sprout_start_radius", PyArray1::from_iter(py, part.sprouts.iter().map(|s| s.start_radius)))?;
    set_node_lists(&d, "sprout", part.sprouts.iter().map(|s| (&s.positions[..], &s.radii[..])))?;
    // Split chains: their ends one row each, their nodes concatenated (`chain_length` each).
    let ends = Array2::from_shape_vec((part.chains.len(), 2), part.chains.iter().flat_map(|c| c.ends).collect())
        .map_err(shape_err)?;
    d.set_item("chain_ends", ends.into_pyarray(py))?;
    set_node_lists(&d, "chain", part.chains.iter().map(|c| (&c.positions[..], &c.radii[..])))?;
    Ok(d)
}

/// Node lists of one kind (`{kind}_length` nodes each, their rows of `{kind}_position` and
/// `{kind}_radius` concatenated in order): how sprouts and split chains travel.
fn set_node_lists<'a>(
    d: &Bound<'_, PyDict>,
    kind: &str,
    lists: impl Iterator<Item = (&'a [[f64; 3]], &'a [f64])> + Clone,
) -> PyResult<()> {
    let py = d.py();
    d.set_item(format!("{kind}_length"), PyArray1::from_iter(py, lists.clone().map(|l| l.0.len() as u64)))?;
    let flat: Vec<f64> = lists.clone().flat_map(|l| l.0.as_flattened().iter().copied()).collect();
    let nodes = Array2::from_shape_vec((flat.len() / 3, 3), flat).map_err(shape_err)?;
    d.set_item(format!("{kind}_position"), nodes.into_pyarray(py))?;
    d.set_item(format!("{kind}_radius"), PyArray1::from_iter(py, lists.flat_map(|l| l.1.iter().copied())))?;
    Ok(())
}

/// One node list: positions and radii.
type NodeList = (Vec<[f64; 3]>, Vec<f64>);

/// The `count` node lists of one kind that [`set_node_lists`] wrote.
fn node_lists_from_py<'py>(
    get: &dyn Fn(&str) -> PyResult<Bound<'py, PyAny>>,
    kind: &str,
    count: usize,
) -> PyResult<Vec<NodeList>> {
    let length: PyReadonlyArray1<u64> = get(&format!("{kind}_length"))?.extract()?;
    let position: PyReadonlyArray2<f64> = get(&format!("{kind}_position"))?.extract()?;
    let radius: PyReadonlyArray1<f64> = get(&format!("{kind}_radius"))?.extract()?;
    let (length, radius) = (length.as_array(), radius.as_array());
    let position = points(&position, &format!("{kind}_position"))?;
    if length.len() != count {
        return Err(PyValueError::new_err(format!("block part {kind} arrays disagree in length")));
    }
    let total = length.iter().try_fold(0u64, |a, &n| a.checked_add(n));
    if total != Some(position.len() as u64) || total != Some(radius.len() as u64) {
        return Err(PyValueError::new_err(format!("block part {kind} nodes disagree with `{kind}_length`")));
    }
    let mut at = 0usize;
    Ok(length
        .iter()
        .map(|&n| {
            let n = n as usize;
            let list = (position[at..at + n].to_vec(), radius.slice(ndarray::s![at..at + n]).to_vec());
            at += n;
            list
        })
        .collect())
}

fn part_from_py(d: &Bound<'_, PyDict>) -> PyResult<BlockPart> {
    let get = |name: &str| {
        d.get_item(name)?.ok_or_else(|| PyValueError::new_err(format!("block part has no `{name}` array")))
    };
    let component: PyReadonlyArray1<u32> = get("component")?.extract()?;
    let cell: PyReadonlyArray2<i64> = get("cell")?.extract()?;
    let position: PyReadonlyArray2<f64> = get("position")?.extract()?;
    let count: PyReadonlyArray1<u64> = get("count")?.extract()?;
    let radius: PyReadonlyArray1<f64> = get("radius")?.extract()?;
    let split_radius: PyReadonlyArray1<f64> = get("split_radius")?.extract()?;
    let node: PyReadonlyArray1<u32> = get("node")?.extract()?;
    let (component, cell, position, count, radius, split_radius, node) = (
        component.as_array(),
        cell.as_array(),
        position.as_array(),
        count.as_array(),
        radius.as_array(),
        split_radius.as_array(),
        node.as_array(),
    );
    let n = component.len();
    let lengths = [count.len(), radius.len(), split_radius.len(), node.len()];
    if cell.dim() != (n, 3) || position.dim() != (n, 3) || lengths.iter().any(|&l| l != n) {
        return Err(PyValueError::new_err("block part arrays disagree in length"));
    }
    let cells = (0..n)
        .map(|i| NodeRecord {
            component: component[i],
            cell: std::array::from_fn(|d| cell[[i, d]]),
            node: node[i],
            position: std::array::from_fn(|d| position[[i, d]]),
            count: count[i],
            radius: radius[i],
            split_radius: split_radius[i],
        })
        .collect();
    let pairs = |name: &str| -> PyResult<Vec<[u32; 2]>> { pairs_of(&get(name)?.extract()?, name) };
    let voxel: PyReadonlyArray1<u64> = get("face_voxel")?.extract()?;
    let face_cell: PyReadonlyArray1<u32> = get("face_cell")?.extract()?;
    if voxel.len() != face_cell.len() {
        return Err(PyValueError::new_err("block part face arrays disagree in length"));
    }
    let faces = voxel.as_array().iter().copied().zip(face_cell.as_array().iter().copied()).collect();
    Ok(BlockPart {
        cells,
        edges: pairs("edges")?,
        bridges: pairs("bridges")?,
        faces,
        sprouts: sprouts_from_py(&get)?,
        chains: chains_from_py(&get)?,
    })
}

fn chains_from_py<'py>(get: &dyn Fn(&str) -> PyResult<Bound<'py, PyAny>>) -> PyResult<Vec<Chain>> {
    let ends = pairs_of::<u32>(&get("chain_ends")?.extract()?, "chain_ends")?;
    let lists = node_lists_from_py(get, "chain", ends.len())?;
    Ok(ends.into_iter().zip(lists).map(|(ends, (positions, radii))| Chain { ends, positions, radii }).collect())
}

fn sprouts_from_py<'py>(get: &dyn Fn(&str) -> PyResult<Bound<'py, PyAny>>) -> PyResult<Vec<SproutRecord>> {
    let round: PyReadonlyArray1<u32> = get("sprout_round")?.extract()?;
    let split: PyReadonlyArray1<bool> = get("sprout_split")?.extract()?;
    let start: PyReadonlyArray2<f64> = get("sprout_start")?.extract()?;
    let start_radius: PyReadonlyArray1<f64> = get("sprout_start_radius")?.extract()?;
    let (round, split, start_radius) = (round.as_array(), split.as_array(), start_radius.as_array());
    let start = points(&start, "sprout_start")?;
    let k = round.len();
    if split.len() != k || start.len() != k || start_radius.len() != k {
        return Err(PyValueError::new_err("block part sprout arrays disagree in length"));
    }
    let lists = node_lists_from_py(get, "sprout", k)?;
    Ok(lists
        .into_iter()
        .enumerate()
        .map(|(i, (positions, radii))| SproutRecord {
            round: round[i],
            split: split[i],
            start: start[i],
            start_radius: start_radius[i],
            positions,
            radii,
        })
        .collect())
}
