//! Graph writers: the `vesselflow-graph` format (version 1) as `.graphml`, `.json`
//! or `.npz`, written atomically (a temporary file beside the target, renamed
//! over it once complete), so a failed or interrupted write leaves no partial file.
//!
//! Positions are physical units in array axis order (axis 0, 1, 2); node ids are
//! `0..N-1`. The `.json` and `.npz` files also carry the run record (`info`) and
//! the parameters (`params`); `.graphml` carries the spacing only.

use crate::IoError;
use ndarray::{Array1, Array2, ArrayView1, ArrayView2};
use serde::ser::{Serialize, Serializer};
use serde_json::{json, Map, Value};
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::Path;
use tempfile::NamedTempFile;
use vesselflow::{Params, RunInfo, Skeleton};

/// The `format` field of every graph file.
pub const FORMAT_NAME: &str = "vesselflow-graph";
/// The `version` field of every graph file.
pub const FORMAT_VERSION: u32 = 1;

/// The graph file formats [`write_graph`] can write, chosen by extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GraphFormat {
    /// `.graphml`: undirected GraphML, node data `x`, `y`, `z` (axes 0, 1, 2) and `r`.
    GraphMl,
    /// `.json`: one object with every array and the metadata.
    Json,
    /// `.npz`: NumPy arrays `positions`, `radii`, `edges`, `spacing`, `metadata`.
    Npz,
}

impl GraphFormat {
    /// The format a file name asks for (case-insensitive extension), if any.
    pub fn from_path(path: &Path) -> Option<GraphFormat> {
        let ext = path.extension()?.to_string_lossy().to_ascii_lowercase();
        match ext.as_str() {
            "graphml" => Some(GraphFormat::GraphMl),
            "json" => Some(GraphFormat::Json),
            "npz" => Some(GraphFormat::Npz),
            _ => None,
        }
    }
}

/// A graph held as arrays, as the Python bindings have it.
#[derive(Debug, Clone, Copy)]
pub struct GraphArrays<'a> {
    /// `(N, 3)` node positions, physical units, array axis order.
    pub positions: ArrayView2<'a, f64>,
    /// `(N,)` node radii, physical units.
    pub radii: ArrayView1<'a, f64>,
    /// `(E, 2)` node ids of each undirected edge.
    pub edges: ArrayView2<'a, i64>,
    /// Voxel spacing of the mask the graph came from.
    pub spacing: [f64; 3],
    /// The run record, a JSON object (see [`run_info_json`]).
    pub info: &'a Value,
    /// The parameters, a JSON object (see [`params_json`]).
    pub params: &'a Value,
}

/// The run record as the JSON object of the format contract: every [`RunInfo`]
/// field, with `stage_seconds` as an object `{stage: seconds}` in pipeline order.
pub fn run_info_json(info: &RunInfo) -> Value {
    let stage_seconds: Map<String, Value> =
        info.stage_seconds.iter().map(|t| (t.stage.to_string(), json!(t.seconds))).collect();
    json!({
        "foreground_voxels": info.foreground_voxels,
        "mask_components": info.mask_components,
        "iterations": info.iterations,
        "converged": info.converged,
        "stalled": info.stalled,
        "refine_iterations": info.refine_iterations,
        "refine_converged": info.refine_converged,
        "nodes_per_iteration": info.nodes_per_iteration,
        "area_per_iteration": info.area_per_iteration,
        "area_reference": info.area_reference,
        "cg_iterations": info.cg_iterations,
        "cg_unconverged": info.cg_unconverged,
        "stage_seconds": stage_seconds,
    })
}

/// The parameters as a JSON object `{name: value}`, in [`Params::NAMES`] order.
pub fn params_json(params: &Params) -> Value {
    let map: Map<String, Value> = params
        .values()
        .into_iter()
        .map(|(name, value)| {
            let value = match value {
                vesselflow::Value::Bool(b) => json!(b),
                vesselflow::Value::Int(i) => json!(i),
                vesselflow::Value::Float(x) => json!(x),
                vesselflow::Value::Str(s) => json!(s),
            };
            (name.to_string(), value)
        })
        .collect();
    Value::Object(map)
}

/// Write `skel` (with the `params` that made it) to `path`, in the format its
/// extension names (`.graphml`, `.json`, `.npz`). Atomic: on any error no file is
/// left at `path` (an existing file there is replaced only on success).
pub fn write_graph(path: &Path, skel: &Skeleton, params: &Params) -> Result<(), IoError> {
    let invalid = |reason: String| IoError::InvalidGraph { path: path.to_path_buf(), reason };
    let positions =
        ArrayView2::from_shape((skel.len(), 3), skel.positions.as_flattened()).map_err(|e| invalid(e.to_string()))?;
    let edges = Array2::from_shape_fn((skel.edges.len(), 2), |(e, end)| skel.edges[e][end] as i64);
    let (info, params) = (run_info_json(&skel.info), params_json(params));
    write_graph_arrays(
        path,
        &GraphArrays {
            positions,
            radii: ArrayView1::from(&skel.radii[..]),
            edges: edges.view(),
            spacing: skel.spacing,
            info: &info,
            params: &params,
        },
    )
}

/// Write a graph given as arrays (see [`GraphArrays`]) to `path`, like
/// [`write_graph`]. The arrays are checked first (shapes, edge ids in `0..N`,
/// finite values, positive spacing, `info` and `params` JSON objects).
pub fn write_graph_arrays(path: &Path, graph: &GraphArrays<'_>) -> Result<(), IoError> {
    let format = check_graph_output(path)?;
    check_arrays(graph).map_err(|reason| IoError::InvalidGraph { path: path.to_path_buf(), reason })?;
    write_atomically(path, |w| match format {
        GraphFormat::GraphMl => write_graphml(w, graph),
        GraphFormat::Json => write_json(w, graph),
        GraphFormat::Npz => write_npz(w, graph),
    })
}

/// Check, before a long run, that a graph can be written to `path`: a known
/// extension, not a directory, and a directory that exists and accepts a new file
/// (checked by creating and removing a temporary file there).
pub fn check_graph_output(path: &Path) -> Result<GraphFormat, IoError> {
    let format = GraphFormat::from_path(path).ok_or_else(|| IoError::UnsupportedGraph { path: path.to_path_buf() })?;
    check_writable(path)?;
    Ok(format)
}

/// Check, before any work, that a file can be written at `path`: it is not a
/// directory, and its directory exists and accepts a new file (a probe file is
/// created and removed).
pub fn check_writable(path: &Path) -> Result<(), IoError> {
    let error = |source| IoError::Write { path: path.to_path_buf(), source };
    if path.is_dir() {
        return Err(error(io::Error::new(io::ErrorKind::IsADirectory, "it is a directory")));
    }
    temp_file_beside(path).map(drop).map_err(error)
}

fn check_arrays(g: &GraphArrays<'_>) -> Result<(), String> {
    let n = g.positions.nrows();
    if g.positions.ncols() != 3 {
        return Err(format!("positions must have shape (N, 3), got {:?}", g.positions.shape()));
    }
    if g.radii.len() != n {
        return Err(format!("radii has {} entries for {n} nodes", g.radii.len()));
    }
    if g.edges.ncols() != 2 {
        return Err(format!("edges must have shape (E, 2), got {:?}", g.edges.shape()));
    }
    if let Some(id) = g.edges.iter().find(|&&id| id < 0 || id as u64 >= n as u64) {
        return Err(format!("edge endpoint {id} is not a node id in 0..{n}"));
    }
    if g.positions.iter().chain(g.radii.iter()).any(|x| !x.is_finite()) {
        return Err("positions and radii must be finite".to_string());
    }
    if g.spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(format!("spacing {:?} must be three finite numbers > 0", g.spacing));
    }
    for (name, value) in [("info", g.info), ("params", g.params)] {
        if !value.is_object() {
            return Err(format!("{name} must be a JSON object, got {value}"));
        }
    }
    Ok(())
}

/// A new temporary file in the directory of `path`, readable like any file the
/// user creates (tempfile's default is owner-only; the umask still applies).
fn temp_file_beside(path: &Path) -> io::Result<NamedTempFile> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    if !dir.is_dir() {
        let (kind, what) = if dir.exists() {
            (io::ErrorKind::NotADirectory, "is not a directory")
        } else {
            (io::ErrorKind::NotFound, "does not exist")
        };
        return Err(io::Error::new(kind, format!("{} {what}", dir.display())));
    }
    let mut builder = tempfile::Builder::new();
    builder.prefix(".vesselflow-").suffix(".tmp");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        builder.permissions(std::fs::Permissions::from_mode(0o666));
    }
    builder
        .tempfile_in(dir)
        .map_err(|e| io::Error::new(e.kind(), format!("cannot create a file in {}: {}", dir.display(), e.kind())))
}

/// Write `path` all or nothing: `write` fills a temporary file beside it, which is
/// synced and renamed over `path` only if everything succeeded.
pub fn write_atomically(
    path: &Path,
    write: impl FnOnce(&mut BufWriter<&File>) -> io::Result<()>,
) -> Result<(), IoError> {
    let error = |source| IoError::Write { path: path.to_path_buf(), source };
    let temp = temp_file_beside(path).map_err(error)?;
    let mut writer = BufWriter::new(temp.as_file());
    write(&mut writer).map_err(error)?;
    writer.into_inner().map_err(|e| error(e.into_error()))?;
    temp.as_file().sync_all().map_err(error)?;
    temp.persist(path).map_err(|e| error(e.error))?;
    Ok(())
}

/// `(R, C)` array serialised as a list of rows (JSON `[[..], ..]`).
struct Rows<'a, T>(ArrayView2<'a, T>);
/// 1-D array serialised as a list.
struct Items<'a, T>(ArrayView1<'a, T>);

impl<T: Serialize> Serialize for Rows<'_, T> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(self.0.rows().into_iter().map(Items))
    }
}

impl<T: Serialize> Serialize for Items<'_, T> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(self.0.iter())
    }
}

/// The `.json` file, fields in contract order.
#[derive(serde::Serialize)]
struct JsonGraph<'a> {
    format: &'static str,
    version: u32,
    spacing: [f64; 3],
    positions: Rows<'a, f64>,
    radii: Items<'a, f64>,
    edges: Rows<'a, i64>,
    info: &'a Value,
    params: &'a Value,
}

/// The `.npz` `metadata` array's JSON object.
#[derive(serde::Serialize)]
struct NpzMetadata<'a> {
    format: &'static str,
    version: u32,
    info: &'a Value,
    params: &'a Value,
}

fn write_json(w: &mut impl Write, g: &GraphArrays<'_>) -> io::Result<()> {
    let doc = JsonGraph {
        format: FORMAT_NAME,
        version: FORMAT_VERSION,
        spacing: g.spacing,
        positions: Rows(g.positions),
        radii: Items(g.radii),
        edges: Rows(g.edges),
        info: g.info,
        params: g.params,
    };
    serde_json::to_writer(&mut *w, &doc)?;
    w.write_all(b"\n")
}

fn write_npz(w: &mut BufWriter<&File>, g: &GraphArrays<'_>) -> io::Result<()> {
    let metadata = NpzMetadata { format: FORMAT_NAME, version: FORMAT_VERSION, info: g.info, params: g.params };
    let metadata = Array1::from(serde_json::to_vec(&metadata)?);
    let mut npz = ndarray_npy::NpzWriter::new(w);
    let result = (|| {
        npz.add_array("positions", &g.positions)?;
        npz.add_array("radii", &g.radii)?;
        npz.add_array("edges", &g.edges)?;
        npz.add_array("spacing", &Array1::from(g.spacing.to_vec()))?;
        npz.add_array("metadata", &metadata)?;
        npz.finish().map(drop)
    })();
    result.map_err(io::Error::other)
}

/// GraphML by hand: every value written is a number or a fixed name, so nothing
/// needs escaping, and a plain writer streams millions of nodes cheaply.
/// Floats use Rust's shortest round-trip form, which Python's `float()` parses.
fn write_graphml(w: &mut impl Write, g: &GraphArrays<'_>) -> io::Result<()> {
    w.write_all(
        br#"<?xml version="1.0" encoding="UTF-8"?>
<graphml xmlns="http://graphml.graphdrawing.org/xmlns" xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" xsi:schemaLocation="http://graphml.graphdrawing.org/xmlns http://graphml.graphdrawing.org/xmlns/1.0/graphml.xsd">
  <key id="spacing0" for="graph" attr.name="spacing0" attr.type="double"/>
  <key id="spacing1" for="graph" attr.name="spacing1" attr.type="double"/>
  <key id="spacing2" for="graph" attr.name="spacing2" attr.type="double"/>
  <key id="x" for="node" attr.name="x" attr.type="double"/>
  <key id="y" for="node" attr.name="y" attr.type="double"/>
  <key id="z" for="node" attr.name="z" attr.type="double"/>
  <key id="r" for="node" attr.name="r" attr.type="double"/>
  <graph id="G" edgedefault="undirected">
"#,
    )?;
    for (axis, s) in g.spacing.iter().enumerate() {
        writeln!(w, "    <data key=\"spacing{axis}\">{s:?}</data>")?;
    }
    for (id, (p, r)) in g.positions.rows().into_iter().zip(g.radii.iter()).enumerate() {
        writeln!(
            w,
            "    <node id=\"{id}\"><data key=\"x\">{:?}</data><data key=\"y\">{:?}</data>\
             <data key=\"z\">{:?}</data><data key=\"r\">{r:?}</data></node>",
            p[0], p[1], p[2]
        )?;
    }
    for e in g.edges.rows() {
        writeln!(w, "    <edge source=\"{}\" target=\"{}\"/>", e[0], e[1])?;
    }
    w.write_all(b"  </graph>\n</graphml>\n")
}
