"""Graph files: reading every format :meth:`VesselGraph.save` writes, and writing the
formats other tools read (SWC, VTK PolyData, CSV tables).

``.npz``, ``.json`` and ``.graphml`` are defined in the project's format contract and
written by the Rust writer the ``vesselflow`` binary shares; ``.swc``, ``.vtp`` and
``.csv`` are written here. In every format positions are physical units in array axis
order (``x``, ``y``, ``z`` = axes 0, 1, 2) and radii are in the same units. Every writer
is atomic: it writes a temporary file beside the target and renames it over the target
once complete, so a failure never leaves a partial file.
"""

from __future__ import annotations

import csv
import importlib
import json
import os
import secrets
import zipfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType
from typing import Any, Callable
from xml.etree.ElementTree import ParseError

import numpy as np

from vesselflow.graph import VesselGraph

FORMAT = "vesselflow-graph"
VERSION = 1


def load_graph(path: str | os.PathLike[str]) -> VesselGraph:
    """Read a graph file; the extension (``.npz``, ``.json``, ``.graphml``, ``.swc``,
    ``.vtp``, ``.csv``) picks the format.

    Raises ``OSError`` if the file cannot be read and ``ValueError`` if it is not a
    vesselflow graph or has an unsupported extension; both messages name the file.
    Only ``.npz`` and ``.json`` keep the run record; from the other formats ``info`` and
    ``params`` are empty. ``.csv`` does not keep the spacing (loaded as 1, 1, 1). A
    ``.swc`` file's nodes come back in the file's (breadth-first) order, with the loops
    listed in its ``# loop-edge`` lines restored; SWC files of other tools load too
    (their ids need not be contiguous). A ``.vtp`` file may hold polylines: each
    segment is an edge.
    """
    path = Path(path)
    reader = _READERS[graph_extension(path)]
    try:
        return reader(path)
    except OSError:
        raise
    except KeyError as e:
        raise ValueError(f"{path}: not a vesselflow graph: missing field {e}") from e
    except (
        ValueError,
        TypeError,
        IndexError,
        ParseError,
        zipfile.BadZipFile,
        EOFError,
        csv.Error,
    ) as e:
        raise ValueError(f"{path}: not a readable vesselflow graph: {e}") from e


def graph_extension(path: str | os.PathLike[str]) -> str:
    """The lower-case extension of a graph file name; ``ValueError`` naming the file
    and listing the supported ones if it is not a graph format."""
    suffix = Path(path).suffix
    if suffix.lower() not in _READERS:
        supported = ", ".join(sorted(_READERS))
        raise ValueError(f"{path}: unsupported extension {suffix!r} (supported: {supported})")
    return suffix.lower()


def _check_header(meta: Mapping[str, Any]) -> None:
    if meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise ValueError(
            f"expected format {FORMAT!r} version {VERSION}, "
            f"got {meta.get('format')!r} version {meta.get('version')!r}"
        )


def _from_columns(arrays: Mapping[str, Any], meta: Mapping[str, Any]) -> VesselGraph:
    """A graph from its array columns and its checked metadata (info, params)."""
    _check_header(meta)
    return VesselGraph(
        positions=arrays["positions"],
        radii=arrays["radii"],
        edges=arrays["edges"],
        spacing=arrays["spacing"],
        info=meta["info"],
        params=meta["params"],
    )


def _read_npz(path: Path) -> VesselGraph:
    with np.load(path, allow_pickle=False) as z:
        return _from_columns(z, json.loads(z["metadata"].tobytes().decode("utf-8")))


def _read_json(path: Path) -> VesselGraph:
    with open(path, encoding="utf-8") as f:
        doc = json.load(f)
    if not isinstance(doc, dict):
        raise ValueError("top level is not a JSON object")
    return _from_columns(doc, doc)


def _read_graphml(path: Path) -> VesselGraph:
    import networkx as nx

    try:
        graph = nx.read_graphml(path)
    except nx.NetworkXError as e:
        raise ValueError(str(e)) from e
    n = graph.number_of_nodes()
    if sorted(int(node) for node in graph.nodes) != list(range(n)):
        raise ValueError(f"node ids are not 0..{n - 1}")
    positions = np.empty((n, 3))
    radii = np.empty(n)
    for node, data in graph.nodes(data=True):
        i = int(node)
        positions[i] = (data["x"], data["y"], data["z"])
        radii[i] = data["r"]
    edges = np.array(
        sorted(sorted((int(a), int(b))) for a, b in graph.edges), dtype=np.int64
    ).reshape(-1, 2)
    spacing = [graph.graph[f"spacing{axis}"] for axis in range(3)]
    return VesselGraph(positions=positions, radii=radii, edges=edges, spacing=spacing)


def import_extra(module: str, extra: str) -> ModuleType:
    """Import an optional dependency; if it is missing, say which extra installs it."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        raise ModuleNotFoundError(
            f"{module} is not installed; install it with: pip install vesselflow[{extra}]",
            name=module,
        ) from e


@contextmanager
def _atomic(path: Path) -> Iterator[Path]:
    """A temporary path beside ``path``, renamed over it when the block succeeds and
    removed when it fails."""
    temp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    try:
        yield temp
        os.replace(temp, path)
    except BaseException:
        temp.unlink(missing_ok=True)
        raise


def _bfs_forest(graph: VesselGraph) -> tuple[list[int], list[int], list[int]]:
    """Breadth-first spanning forest: nodes in visiting order, each node's parent (-1 for
    a root) and the indices of the edges left out of the trees (loops, repeated edges).

    Each connected component is rooted at its node of largest radius (lowest id on ties);
    components come in the order of their roots' radii, largest first.
    """
    n = graph.n_nodes
    ends = np.concatenate([graph.edges, graph.edges[:, ::-1]])
    edge_ids = np.tile(np.arange(graph.n_edges), 2)
    by_node = np.argsort(ends[:, 0], kind="stable")
    starts = np.searchsorted(ends[by_node, 0], np.arange(n + 1)).tolist()
    neighbours, via = ends[by_node, 1].tolist(), edge_ids[by_node].tolist()
    parent = [-1] * n
    visited = [False] * n
    in_tree = [False] * graph.n_edges
    order: list[int] = []
    for root in np.lexsort((np.arange(n), -graph.radii)).tolist():
        if visited[root]:
            continue
        visited[root] = True
        head = len(order)
        order.append(root)
        while head < len(order):
            node = order[head]
            head += 1
            for slot in range(starts[node], starts[node + 1]):
                other = neighbours[slot]
                if not visited[other]:
                    visited[other] = True
                    parent[other] = node
                    in_tree[via[slot]] = True
                    order.append(other)
    loops = [e for e, tree in enumerate(in_tree) if not tree]
    return order, parent, loops


def _write_swc(graph: VesselGraph, path: Path) -> None:
    order, parent, loops = _bfs_forest(graph)
    swc_id = np.empty(graph.n_nodes, dtype=np.int64)
    swc_id[order] = np.arange(1, graph.n_nodes + 1)
    spacing = " ".join(repr(s) for s in graph.spacing.tolist())
    lines = [
        f"# {FORMAT} version {VERSION} (SWC)",
        f"# spacing {spacing}",
        "# columns: id type x y z radius parent; x y z = array axes 0 1 2, physical units",
        "# one tree per connected component, rooted at its node of largest radius "
        "(lowest id on ties), parents from a breadth-first search",
        "# edges not in the trees (loops) are listed below as 'loop-edge id id'",
    ]
    lines += [f"# loop-edge {swc_id[a]} {swc_id[b]}" for a, b in graph.edges[loops].tolist()]
    positions, radii = graph.positions.tolist(), graph.radii.tolist()
    for i, node in enumerate(order, start=1):
        x, y, z = positions[node]
        up = -1 if parent[node] < 0 else swc_id[parent[node]]
        lines.append(f"{i} 0 {x!r} {y!r} {z!r} {radii[node]!r} {up}")
    with _atomic(path) as temp:
        temp.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _read_swc(path: Path) -> VesselGraph:
    spacing = [1.0, 1.0, 1.0]
    loop_ids: list[tuple[int, int]] = []
    rows: list[list[float]] = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            words = line.split()
            if not words:
                continue
            if words[0].startswith("#"):
                tag = words[1:2] if words[0] == "#" else [words[0][1:]]
                values = words[2:] if words[0] == "#" else words[1:]
                if tag == ["spacing"]:
                    spacing = [float(v) for v in values]
                elif tag == ["loop-edge"]:
                    loop_ids.append((int(values[0]), int(values[1])))
                continue
            if len(words) < 7:
                raise ValueError(f"an SWC line needs 7 columns: {line.strip()!r}")
            rows.append([float(w) for w in words[:7]])
    table = np.array(rows, dtype=np.float64).reshape(-1, 7)
    index = {int(swc): i for i, swc in enumerate(table[:, 0])}
    if len(index) != len(table):
        raise ValueError("repeated SWC ids")

    def node(swc: int) -> int:
        if swc not in index:
            raise ValueError(f"SWC id {swc} is not a sample")
        return index[swc]

    edges = [(node(int(up)), i) for i, up in enumerate(table[:, 6]) if up >= 0]
    edges += [(node(a), node(b)) for a, b in loop_ids]
    return VesselGraph(positions=table[:, 2:5], radii=table[:, 5], edges=edges, spacing=spacing)


def _vtk() -> tuple[Any, Any, Any, Any]:
    """The VTK modules used: common core, data model, XML I/O, NumPy support."""
    return (
        import_extra("vtkmodules.vtkCommonCore", "io"),
        import_extra("vtkmodules.vtkCommonDataModel", "io"),
        import_extra("vtkmodules.vtkIOXML", "io"),
        import_extra("vtkmodules.util.numpy_support", "io"),
    )


def _write_vtp(graph: VesselGraph, path: Path) -> None:
    core, model, xml, numpy_vtk = _vtk()
    points = core.vtkPoints()
    points.SetData(numpy_vtk.numpy_to_vtk(np.ascontiguousarray(graph.positions), deep=True))
    offsets = np.arange(0, 2 * graph.n_edges + 1, 2, dtype=np.int64)
    lines = model.vtkCellArray()
    lines.SetData(
        numpy_vtk.numpy_to_vtkIdTypeArray(offsets, deep=True),
        numpy_vtk.numpy_to_vtkIdTypeArray(graph.edges.reshape(-1).copy(), deep=True),
    )
    poly = model.vtkPolyData()
    poly.SetPoints(points)
    poly.SetLines(lines)
    for data, name, values in (
        (poly.GetPointData(), "radius", graph.radii),
        (poly.GetFieldData(), "spacing", graph.spacing),
    ):
        array = numpy_vtk.numpy_to_vtk(np.ascontiguousarray(values), deep=True)
        array.SetName(name)
        data.AddArray(array)
    poly.GetPointData().SetActiveScalars("radius")
    with _atomic(path) as temp:
        writer = xml.vtkXMLPolyDataWriter()
        writer.SetFileName(str(temp))
        writer.SetInputData(poly)
        if writer.Write() != 1:
            raise OSError(f"{path}: VTK could not write the file")


def _read_vtp(path: Path) -> VesselGraph:
    _, _, xml, numpy_vtk = _vtk()
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    reader = xml.vtkXMLPolyDataReader()
    if not reader.CanReadFile(str(path)):
        raise ValueError("not a VTK XML PolyData file")
    errors: list[str] = []
    reader.AddObserver("ErrorEvent", lambda _obj, event: errors.append(event))
    reader.SetFileName(str(path))
    reader.Update()
    if errors:
        raise ValueError("VTK could not read it (see its messages on stderr)")
    poly = reader.GetOutput()
    radius = poly.GetPointData().GetArray("radius")
    if radius is None:
        raise ValueError("no 'radius' point array")
    n = poly.GetNumberOfPoints()
    positions = numpy_vtk.vtk_to_numpy(poly.GetPoints().GetData()) if n else np.empty((0, 3))
    cells = poly.GetLines()
    offsets = numpy_vtk.vtk_to_numpy(cells.GetOffsetsArray())
    connectivity = numpy_vtk.vtk_to_numpy(cells.GetConnectivityArray())
    # Consecutive points of one polyline are joined; no segment crosses polylines.
    within = np.ones(len(connectivity), dtype=bool)
    within[offsets[:-1]] = False
    edges = np.stack([connectivity[:-1], connectivity[1:]], axis=1)[within[1:]]
    spacing_array = poly.GetFieldData().GetArray("spacing")
    spacing = (1.0, 1.0, 1.0) if spacing_array is None else numpy_vtk.vtk_to_numpy(spacing_array)
    return VesselGraph(
        positions=positions,
        radii=numpy_vtk.vtk_to_numpy(radius),
        edges=edges,
        spacing=spacing,
    )


def csv_edges_path(path: str | os.PathLike[str]) -> Path:
    """The edges table written beside a nodes table: ``graph.csv`` -> ``graph.edges.csv``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.edges{path.suffix}")


def _write_csv(graph: VesselGraph, path: Path) -> None:
    with _atomic(path) as nodes_temp, _atomic(csv_edges_path(path)) as edges_temp:
        with open(nodes_temp, "w", newline="", encoding="utf-8") as f:
            writer = csv.writer(f)
            writer.writerow(["id", "x", "y", "z", "r"])
            positions = graph.positions.tolist()
            writer.writerows([i, *positions[i], r] for i, r in enumerate(graph.radii.tolist()))
        with open(edges_temp, "w", newline="", encoding="utf-8") as f:
            writer = csv.writer(f)
            writer.writerow(["source", "target"])
            writer.writerows(graph.edges.tolist())


def _read_csv(path: Path) -> VesselGraph:
    with open(path, newline="", encoding="utf-8") as f:
        nodes = list(csv.DictReader(f))
    with open(csv_edges_path(path), newline="", encoding="utf-8") as f:
        edges = list(csv.DictReader(f))
    index = {row["id"]: i for i, row in enumerate(nodes)}
    if len(index) != len(nodes):
        raise ValueError("repeated node ids")
    return VesselGraph(
        positions=[[float(row[axis]) for axis in "xyz"] for row in nodes],
        radii=[float(row["r"]) for row in nodes],
        edges=[(index[row["source"]], index[row["target"]]) for row in edges],
    )


_READERS: dict[str, Callable[[Path], VesselGraph]] = {
    ".csv": _read_csv,
    ".graphml": _read_graphml,
    ".json": _read_json,
    ".npz": _read_npz,
    ".swc": _read_swc,
    ".vtp": _read_vtp,
}

WRITERS: dict[str, Callable[[VesselGraph, Path], None]] = {
    ".csv": _write_csv,
    ".swc": _write_swc,
    ".vtp": _write_vtp,
}
"""Writers of the formats :meth:`VesselGraph.save` does not hand to the Rust writer."""
