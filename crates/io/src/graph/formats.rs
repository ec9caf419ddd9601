//! The graph formats of other tools: SWC, VTK XML PolyData, a pair of CSV tables
//! and Neuroglancer precomputed skeletons. Each is written from [`GraphArrays`]
//! after [`super::check_arrays`], atomically (see [`super::write_graph_arrays`]).

use super::{replace_all, temp_dir_beside, temp_file_beside, GraphArrays, FORMAT_NAME, FORMAT_VERSION};
use crate::IoError;
use serde_json::{json, Value};
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};

/// The coordinate frame the positions are in, from `info["coordinates"]`
/// (written by a run with `coordinates=`; absent means array axes).
#[derive(Clone, Copy, PartialEq, Eq)]
enum Frame {
    Array,
    Xyz,
    World,
}

fn frame(g: &GraphArrays<'_>) -> Frame {
    match g.info.get("coordinates").and_then(Value::as_str) {
        Some("xyz") => Frame::Xyz,
        Some("world") => Frame::World,
        _ => Frame::Array,
    }
}

/// What the columns `x y z` hold, as the SWC header says it.
fn frame_text(g: &GraphArrays<'_>) -> &'static str {
    match frame(g) {
        Frame::Array => "array axes 0 1 2",
        Frame::Xyz => "array axes 2 1 0 (x = last axis)",
        Frame::World => "world coordinates (the image's voxel-to-world affine)",
    }
}

/// Breadth-first spanning forest: the nodes in visiting order, each node's parent
/// (`None` for a root) and the ids of the edges left out of the trees (loops,
/// repeated edges). Each component is rooted at its node of largest radius (lowest
/// id on ties); components come in the order of their roots' radii, largest first.
/// A node's neighbours are visited in the order of the edges where it is the first
/// end, then of those where it is the second.
fn bfs_forest(g: &GraphArrays<'_>) -> (Vec<usize>, Vec<Option<usize>>, Vec<usize>) {
    let n = g.radii.len();
    let mut adjacency: Vec<Vec<(usize, usize)>> = vec![Vec::new(); n];
    for end in 0..2 {
        for (e, edge) in g.edges.rows().into_iter().enumerate() {
            adjacency[edge[end] as usize].push((edge[1 - end] as usize, e));
        }
    }
    let mut roots: Vec<usize> = (0..n).collect();
    // Radii are finite (checked before writing): `partial_cmp` is total here and ±0 tie.
    roots.sort_by(|&a, &b| g.radii[b].partial_cmp(&g.radii[a]).unwrap_or(std::cmp::Ordering::Equal).then(a.cmp(&b)));
    let mut parent = vec![None; n];
    let mut visited = vec![false; n];
    let mut in_tree = vec![false; g.edges.nrows()];
    let mut order = Vec::with_capacity(n);
    for root in roots {
        if visited[root] {
            continue;
        }
        visited[root] = true;
        let mut head = order.len();
        order.push(root);
        while head < order.len() {
            let node = order[head];
            head += 1;
            for &(other, e) in &adjacency[node] {
                if !visited[other] {
                    visited[other] = true;
                    parent[other] = Some(node);
                    in_tree[e] = true;
                    order.push(other);
                }
            }
        }
    }
    let loops = (0..in_tree.len()).filter(|&e| !in_tree[e]).collect();
    (order, parent, loops)
}

/// SWC: ids 1-based in breadth-first order (a parent precedes its children), type 0,
/// columns `id type x y z radius parent`; the spacing and the edges left out of the
/// trees (`# loop-edge i j`) in header lines, which `vesselflow.load_graph` reads.
pub(super) fn write_swc(w: &mut impl Write, g: &GraphArrays<'_>) -> io::Result<()> {
    let (order, parent, loops) = bfs_forest(g);
    let mut swc_id = vec![0usize; order.len()];
    for (i, &node) in order.iter().enumerate() {
        swc_id[node] = i + 1;
    }
    let [s0, s1, s2] = g.spacing;
    writeln!(w, "# {FORMAT_NAME} version {FORMAT_VERSION} (SWC)")?;
    writeln!(w, "# spacing {s0:?} {s1:?} {s2:?}")?;
    writeln!(w, "# columns: id type x y z radius parent; x y z = {}, physical units", frame_text(g))?;
    writeln!(
        w,
        "# one tree per connected component, rooted at its node of largest radius \
         (lowest id on ties), parents from a breadth-first search"
    )?;
    writeln!(w, "# edges not in the trees (loops) are listed below as 'loop-edge id id'")?;
    for e in loops {
        writeln!(w, "# loop-edge {} {}", swc_id[g.edges[[e, 0]] as usize], swc_id[g.edges[[e, 1]] as usize])?;
    }
    for (i, &node) in order.iter().enumerate() {
        let p = g.positions.row(node);
        let up = parent[node].map_or(-1, |u| swc_id[u] as i64);
        writeln!(w, "{} 0 {:?} {:?} {:?} {:?} {up}", i + 1, p[0], p[1], p[2], g.radii[node])?;
    }
    Ok(())
}

/// VTK XML PolyData (ASCII, exact shortest round-trip decimals): the nodes as
/// points, one line cell per edge, the radii as the active point scalars `radius`
/// and the spacing as the field-data array `spacing`.
pub(super) fn write_vtp(w: &mut impl Write, g: &GraphArrays<'_>) -> io::Result<()> {
    let (n, e) = (g.radii.len(), g.edges.nrows());
    let values = |w: &mut dyn Write, values: &mut dyn Iterator<Item = String>| -> io::Result<()> {
        for (i, v) in values.enumerate() {
            w.write_all(if i % 12 == 0 { b"\n          " } else { b" " })?;
            w.write_all(v.as_bytes())?;
        }
        w.write_all(b"\n        ")
    };
    writeln!(w, "<?xml version=\"1.0\"?>")?;
    writeln!(w, "<VTKFile type=\"PolyData\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt64\">")?;
    writeln!(w, "  <PolyData>")?;
    writeln!(w, "    <FieldData>")?;
    write!(w, "        <DataArray type=\"Float64\" Name=\"spacing\" NumberOfTuples=\"3\" format=\"ascii\">")?;
    values(w, &mut g.spacing.iter().map(|s| format!("{s:?}")))?;
    writeln!(w, "</DataArray>\n    </FieldData>")?;
    writeln!(
        w,
        "    <Piece NumberOfPoints=\"{n}\" NumberOfVerts=\"0\" NumberOfLines=\"{e}\" NumberOfStrips=\"0\" NumberOfPolys=\"0\">"
    )?;
    writeln!(w, "      <PointData Scalars=\"radius\">")?;
    write!(w, "        <DataArray type=\"Float64\" Name=\"radius\" format=\"ascii\">")?;
    values(w, &mut g.radii.iter().map(|r| format!("{r:?}")))?;
    writeln!(w, "</DataArray>\n      </PointData>")?;
    writeln!(w, "      <Points>")?;
    write!(w, "        <DataArray type=\"Float64\" Name=\"Points\" NumberOfComponents=\"3\" format=\"ascii\">")?;
    values(w, &mut g.positions.iter().map(|x| format!("{x:?}")))?;
    writeln!(w, "</DataArray>\n      </Points>")?;
    writeln!(w, "      <Lines>")?;
    write!(w, "        <DataArray type=\"Int64\" Name=\"connectivity\" format=\"ascii\">")?;
    values(w, &mut g.edges.iter().map(i64::to_string))?;
    writeln!(w, "</DataArray>")?;
    // Offsets are where each cell ends (VTK XML has no leading 0).
    write!(w, "        <DataArray type=\"Int64\" Name=\"offsets\" format=\"ascii\">")?;
    values(w, &mut (1..=e).map(|i| (2 * i).to_string()))?;
    writeln!(w, "</DataArray>\n      </Lines>")?;
    writeln!(w, "    </Piece>\n  </PolyData>\n</VTKFile>")
}

/// The nodes table `id,x,y,z,r` at `outputs[0]` and the edges table `source,target`
/// at `outputs[1]` (CSV with CRLF line ends, as Python's `csv` module writes),
/// replaced together: both are written to temporary files first.
pub(super) fn write_csv(path: &Path, outputs: &[PathBuf], g: &GraphArrays<'_>) -> Result<(), IoError> {
    let error = |path: &Path| {
        let path = path.to_path_buf();
        move |source| IoError::Write { path, source }
    };
    type Fill<'f> = &'f dyn Fn(&mut dyn Write) -> io::Result<()>;
    let tables: [(&Path, Fill<'_>); 2] = [
        (&outputs[0], &|w| {
            w.write_all(b"id,x,y,z,r\r\n")?;
            for (i, (p, r)) in g.positions.rows().into_iter().zip(g.radii.iter()).enumerate() {
                write!(w, "{i},{:?},{:?},{:?},{r:?}\r\n", p[0], p[1], p[2])?;
            }
            Ok(())
        }),
        (&outputs[1], &|w| {
            w.write_all(b"source,target\r\n")?;
            for e in g.edges.rows() {
                write!(w, "{},{}\r\n", e[0], e[1])?;
            }
            Ok(())
        }),
    ];
    let mut temps = Vec::new();
    for (target, fill) in tables {
        let temp = temp_file_beside(target).map_err(error(target))?;
        let mut writer = BufWriter::new(temp.as_file());
        fill(&mut writer).map_err(error(target))?;
        writer.into_inner().map_err(|e| error(target)(e.into_error()))?;
        temp.as_file().sync_all().map_err(error(target))?;
        temps.push(temp.into_temp_path());
    }
    let staged: Vec<PathBuf> = temps.iter().map(|t| t.to_path_buf()).collect();
    replace_all(&staged, outputs).map_err(|e| match e {
        IoError::Write { source, .. } => IoError::Write { path: path.to_path_buf(), source },
        other => other,
    })
}

/// The `@type` of a Neuroglancer skeleton folder's `info`.
const SKELETONS: &str = "neuroglancer_skeletons";

/// The segment id of the one skeleton written (the file `1` in the folder).
const SEGMENT: &str = "1";

/// A `.precomputed` target may be new, or a skeleton folder written before (its
/// `info` says `neuroglancer_skeletons`), which is replaced; anything else is
/// refused, so that no folder of other data is ever removed.
pub(super) fn check_precomputed_target(path: &Path) -> Result<(), IoError> {
    let Ok(meta) = std::fs::symlink_metadata(path) else {
        return Ok(());
    };
    let ours = meta.is_dir()
        && std::fs::read(path.join("info"))
            .ok()
            .and_then(|text| serde_json::from_slice::<Value>(&text).ok())
            .is_some_and(|info| info["@type"] == SKELETONS);
    if ours {
        return Ok(());
    }
    Err(IoError::Write {
        path: path.to_path_buf(),
        source: io::Error::new(
            io::ErrorKind::AlreadyExists,
            "it exists and is not a Neuroglancer skeleton folder (only such a folder is replaced)",
        ),
    })
}

/// The `info` of the skeleton folder: the stored vertices are the positions as they
/// are, and `transform` (3 × 4, row-major) maps them to x, y, z: the identity for
/// positions already in (x, y, z) order or in world coordinates, the reversal of the
/// axes for positions in array axis order (x = axis 2). Units are the graph's.
fn precomputed_info(g: &GraphArrays<'_>) -> Value {
    let transform: [f64; 12] = match frame(g) {
        Frame::Array => [0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        Frame::Xyz | Frame::World => [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0],
    };
    json!({
        "@type": SKELETONS,
        "transform": transform,
        "vertex_attributes": [{"id": "radius", "data_type": "float32", "num_components": 1}],
    })
}

/// A Neuroglancer precomputed skeleton folder: `info` and the skeleton of segment 1
/// in the documented binary form (little-endian: `u32` vertex count, `u32` edge
/// count, `f32` positions, `u32` edge pairs, then the `f32` radius of each vertex).
/// Written into a temporary folder beside `path`, then moved into place.
pub(super) fn write_precomputed(path: &Path, g: &GraphArrays<'_>) -> Result<(), IoError> {
    let error = |source| IoError::Write { path: path.to_path_buf(), source };
    check_precomputed_target(path)?;
    let too_many = |what: &str, count: usize| {
        error(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("{count} {what} do not fit the format's 32-bit counts"),
        ))
    };
    let nodes = u32::try_from(g.radii.len()).map_err(|_| too_many("nodes", g.radii.len()))?;
    let edges = u32::try_from(g.edges.nrows()).map_err(|_| too_many("edges", g.edges.nrows()))?;
    let staging = temp_dir_beside(path).map_err(error)?;
    let write_file = |name: &str, fill: &dyn Fn(&mut BufWriter<&File>) -> io::Result<()>| -> io::Result<()> {
        let file = File::create(staging.path().join(name))?;
        let mut writer = BufWriter::new(&file);
        fill(&mut writer)?;
        writer.into_inner().map_err(io::IntoInnerError::into_error)?;
        file.sync_all()
    };
    write_file("info", &|w| {
        serde_json::to_writer_pretty(&mut *w, &precomputed_info(g))?;
        w.write_all(b"\n")
    })
    .map_err(error)?;
    write_file(SEGMENT, &|w| {
        w.write_all(&nodes.to_le_bytes())?;
        w.write_all(&edges.to_le_bytes())?;
        for &x in g.positions.iter() {
            w.write_all(&(x as f32).to_le_bytes())?;
        }
        for &id in g.edges.iter() {
            w.write_all(&(id as u32).to_le_bytes())?; // ids are checked to lie in 0..N
        }
        for &r in g.radii.iter() {
            w.write_all(&(r as f32).to_le_bytes())?;
        }
        Ok(())
    })
    .map_err(error)?;
    replace_all(&[staging.path().to_path_buf()], &[path.to_path_buf()])
}
