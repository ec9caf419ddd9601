//! Graph writers, the one registry of graph formats (the `vesselflow` binary and
//! Python's `VesselGraph.save` both write through [`write_graph_arrays`]): the
//! `vesselflow-graph` format (version 1) as `.graphml`, `.json` or `.npz`, and the
//! formats of other tools, `.swc`, `.vtp`, `.csv` (a pair of tables) and
//! `.precomputed` (a Neuroglancer skeleton folder). Everything is written
//! atomically (temporary files beside the target, renamed over it once complete;
//! several outputs are replaced together, see [`replace_all`]), so a failed or
//! interrupted write leaves no partial file.
//!
//! Positions are physical units in the graph's coordinate frame (array axis order
//! unless `info["coordinates"]` says `"xyz"` or `"world"`); node ids are `0..N-1`.
//! The `.json` and `.npz` files also carry the run record (`info`) and the
//! parameters (`params`); the other formats carry the spacing at most.

mod formats;

use crate::IoError;
use ndarray::{Array1, Array2, ArrayView1, ArrayView2};
use serde::ser::{Serialize, Serializer};
use serde_json::{json, Map, Value};
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use tempfile::NamedTempFile;
use vesselflow::{Params, RunInfo, Skeleton};

/// The `format` field of every graph file.
pub const FORMAT_NAME: &str = "vesselflow-graph";
/// The `version` field of every graph file.
pub const FORMAT_VERSION: u32 = 1;

/// The graph file formats [`write_graph`] can write, chosen by extension: the one
/// registry of graph formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GraphFormat {
    /// `.graphml`: undirected GraphML, node data `x`, `y`, `z` (positions' columns 0, 1, 2) and `r`.
    GraphMl,
    /// `.json`: one object with every array and the metadata.
    Json,
    /// `.npz`: NumPy arrays `positions`, `radii`, `edges`, `spacing`, `metadata`.
    Npz,
    /// `.swc`: one tree per component, breadth-first, loops in `# loop-edge` lines.
    Swc,
    /// `.vtp`: VTK XML PolyData, one line per edge, a `radius` point array.
    Vtp,
    /// `.csv`: a nodes table `name.csv` (`id,x,y,z,r`) and an edges table
    /// `name.edges.csv` (`source,target`), replaced together.
    Csv,
    /// `.precomputed`: a Neuroglancer precomputed skeleton folder (`info` and the
    /// skeleton of segment 1, with a `radius` vertex attribute).
    Precomputed,
}

impl GraphFormat {
    /// Every format with its extension, in the order error messages list them.
    pub const ALL: [(GraphFormat, &'static str); 7] = [
        (GraphFormat::GraphMl, "graphml"),
        (GraphFormat::Json, "json"),
        (GraphFormat::Npz, "npz"),
        (GraphFormat::Swc, "swc"),
        (GraphFormat::Vtp, "vtp"),
        (GraphFormat::Csv, "csv"),
        (GraphFormat::Precomputed, "precomputed"),
    ];

    /// The format a file name asks for (case-insensitive extension), if any.
    pub fn from_path(path: &Path) -> Option<GraphFormat> {
        let ext = path.extension()?.to_string_lossy().to_ascii_lowercase();
        GraphFormat::ALL.iter().find(|(_, e)| *e == ext).map(|(f, _)| *f)
    }

    /// The supported extensions as a message lists them: `.graphml, .json, ... or .precomputed`.
    pub fn extensions_text() -> String {
        let names: Vec<String> = GraphFormat::ALL.iter().map(|(_, e)| format!(".{e}")).collect();
        format!("{} or {}", names[..names.len() - 1].join(", "), names[names.len() - 1])
    }

    /// Every path a write to `path` creates or replaces: `path` itself, and for
    /// `.csv` the edges table beside it (`g.csv` -> `g.edges.csv`).
    pub fn outputs(self, path: &Path) -> Vec<PathBuf> {
        match self {
            GraphFormat::Csv => {
                let stem = path.file_stem().unwrap_or_default().to_string_lossy();
                let ext = path.extension().unwrap_or_default().to_string_lossy();
                vec![path.to_path_buf(), path.with_file_name(format!("{stem}.edges.{ext}"))]
            }
            _ => vec![path.to_path_buf()],
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
        "sprouts": info.sprouts,
        "pruned_spurs": info.pruned_spurs,
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
/// extension names (see [`GraphFormat`]). Atomic: on any error no file is
/// left at `path` (an existing file there is replaced only on success).
pub fn write_graph(path: &Path, skel: &Skeleton, params: &Params) -> Result<(), IoError> {
    write_skeleton(path, skel, params, &run_info_json(&skel.info))
}

/// [`write_graph`] with the run record given as JSON (e.g. [`run_info_json`] with
/// the entries of [`frame_info`] added).
pub fn write_skeleton(path: &Path, skel: &Skeleton, params: &Params, info: &Value) -> Result<(), IoError> {
    let invalid = |reason: String| IoError::InvalidGraph { path: path.to_path_buf(), reason };
    let positions =
        ArrayView2::from_shape((skel.len(), 3), skel.positions.as_flattened()).map_err(|e| invalid(e.to_string()))?;
    let edges = Array2::from_shape_fn((skel.edges.len(), 2), |(e, end)| skel.edges[e][end] as i64);
    let params = params_json(params);
    write_graph_arrays(
        path,
        &GraphArrays {
            positions,
            radii: ArrayView1::from(&skel.radii[..]),
            edges: edges.view(),
            spacing: skel.spacing,
            info,
            params: &params,
        },
    )
}

/// Record in a run record (a JSON object) the frame of its graph's positions:
/// `"coordinates"` (`"array"`, `"xyz"` or `"world"`) and, for `"world"`, the
/// `"affine"` (4 × 4, row-major). The writers read it back: the SWC header says
/// what `x y z` are, the Neuroglancer `transform` maps array order to x, y, z.
pub fn frame_info(info: &mut Value, coordinates: crate::Coordinates, affine: &[[f64; 4]; 4]) {
    if let Some(map) = info.as_object_mut() {
        map.insert("coordinates".to_string(), json!(coordinates.name()));
        if coordinates == crate::Coordinates::World {
            map.insert("affine".to_string(), json!(affine));
        }
    }
}

/// Write a graph given as arrays (see [`GraphArrays`]) to `path`, like
/// [`write_graph`]. The arrays are checked first (shapes, edge ids in `0..N`,
/// finite values, positive spacing, `info` and `params` JSON objects).
pub fn write_graph_arrays(path: &Path, graph: &GraphArrays<'_>) -> Result<(), IoError> {
    let format = check_graph_output(path)?;
    check_arrays(graph).map_err(|reason| IoError::InvalidGraph { path: path.to_path_buf(), reason })?;
    match format {
        GraphFormat::GraphMl => write_atomically(path, |w| write_graphml(w, graph)),
        GraphFormat::Json => write_atomically(path, |w| write_json(w, graph)),
        GraphFormat::Npz => write_atomically(path, |w| write_npz(w, graph)),
        GraphFormat::Swc => write_atomically(path, |w| formats::write_swc(w, graph)),
        GraphFormat::Vtp => write_atomically(path, |w| formats::write_vtp(w, graph)),
        GraphFormat::Csv => formats::write_csv(path, &format.outputs(path), graph),
        GraphFormat::Precomputed => formats::write_precomputed(path, graph),
    }
}

/// Check, before a long run, that a graph can be written to `path`: a known
/// extension, not a directory (a `.precomputed` folder may replace an earlier
/// one, nothing else), and a directory that exists and accepts a new file
/// (checked by creating and removing a temporary file there).
pub fn check_graph_output(path: &Path) -> Result<GraphFormat, IoError> {
    let format = GraphFormat::from_path(path).ok_or_else(|| IoError::UnsupportedGraph { path: path.to_path_buf() })?;
    for output in format.outputs(path) {
        if format == GraphFormat::Precomputed {
            formats::check_precomputed_target(&output)?;
            temp_file_beside(&output).map(drop).map_err(|source| IoError::Write { path: output.clone(), source })?;
        } else {
            check_writable(&output)?;
        }
    }
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

/// A new temporary folder in the directory of `path` (mode 0755), for outputs
/// that are folders (`.precomputed`) or staged before [`replace_all`].
pub fn temp_dir_beside(path: &Path) -> io::Result<tempfile::TempDir> {
    let dir = temp_file_beside(path)?; // the same checks and messages as for a file
    let parent = dir.path().parent().map(Path::to_path_buf).unwrap_or_default();
    drop(dir);
    let temp = tempfile::Builder::new().prefix(".vesselflow-").suffix(".tmp").tempdir_in(parent)?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(temp.path(), std::fs::Permissions::from_mode(0o755))?;
    }
    Ok(temp)
}

/// Move each `staged` path (a file or a folder) to its `target`, all or nothing:
/// if any move fails, the targets already replaced get their old contents back,
/// targets that did not exist are removed, and the error is returned. An existing
/// target file keeps its name until it is replaced (it is kept aside through a hard
/// link, or a copy where links are not supported); an existing target folder is
/// moved aside, then removed once everything is in place.
pub fn replace_all(staged: &[PathBuf], targets: &[PathBuf]) -> Result<(), IoError> {
    debug_assert_eq!(staged.len(), targets.len());
    let mut backups: Vec<Option<tempfile::TempPath>> = Vec::new();
    let mut moved = 0;
    let result = (|| {
        for target in targets {
            backups.push(keep_aside(target).map_err(|source| IoError::Write { path: target.clone(), source })?);
        }
        for (from, to) in staged.iter().zip(targets) {
            std::fs::rename(from, to).map_err(|source| IoError::Write { path: to.clone(), source })?;
            moved += 1;
        }
        Ok(())
    })();
    if result.is_err() {
        for (i, (from, to)) in staged.iter().zip(targets).enumerate().take(moved) {
            let _ = std::fs::rename(to, from); // the staged copy goes back where its owner removes it
            if let Some(Some(backup)) = backups.get(i) {
                let _ = std::fs::rename(backup, to);
            }
        }
        // Folders moved aside but not replaced go back too.
        for (i, to) in targets.iter().enumerate().skip(moved) {
            if let Some(Some(backup)) = backups.get(i) {
                if backup.is_dir() {
                    let _ = std::fs::rename(backup, to);
                }
            }
        }
    }
    for backup in backups.into_iter().flatten() {
        if backup.is_dir() {
            let _ = std::fs::remove_dir_all(&backup);
        }
        drop(backup); // removes a backup file
    }
    result
}

/// Give an existing `target` a second, temporary name beside it (a file: a hard
/// link or copy; a folder: moved there), returned so it can be restored or removed.
fn keep_aside(target: &Path) -> io::Result<Option<tempfile::TempPath>> {
    let Ok(meta) = std::fs::symlink_metadata(target) else {
        return Ok(None);
    };
    let backup = temp_file_beside(target)?.into_temp_path();
    if meta.is_dir() {
        std::fs::remove_file(&backup)?;
        std::fs::rename(target, &backup)?;
    } else {
        std::fs::remove_file(&backup)?;
        if std::fs::hard_link(target, &backup).is_err() {
            std::fs::copy(target, &backup)?;
        }
    }
    Ok(Some(backup))
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
