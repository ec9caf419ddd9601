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
import errno
import importlib
import json
import os
import secrets
import shutil
import zipfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType
from typing import Any, Callable, NamedTuple

import numpy as np

from vesselflow.graph import VesselGraph, check_graph_arrays

FORMAT = "vesselflow-graph"
VERSION = 1


def load_graph(path: str | os.PathLike[str]) -> VesselGraph:
    """Read a graph file; the extension (``.npz``, ``.json``, ``.graphml``, ``.swc``,
    ``.vtp``, ``.csv``) picks the format.

    Raises ``OSError`` if the file cannot be read, ``ValueError`` if it is not a valid
    vesselflow graph or has an unsupported extension, and ``MemoryError`` if it does not
    fit in memory; every message names the file. What a file holds is checked by
    :func:`vesselflow.graph.check_graph_arrays`, whatever the format: finite positions,
    finite radii ``>= 0``, integer edge ids in range, no self-loops (repeated edges are
    kept). Only ``.npz`` and ``.json`` keep the run record; from the other formats
    ``info`` and ``params`` are empty. ``.csv`` does not keep the spacing (loaded as 1,
    1, 1). A ``.swc`` file's nodes come back in the file's (breadth-first) order, with
    the loops listed in its ``# loop-edge`` lines restored; SWC files of other tools
    load too (their ids need not be contiguous). A ``.vtp`` file may hold polylines:
    each segment is an edge.
    """
    path = Path(path)
    reader = _READERS[graph_extension(path)]
    try:
        parts = reader(path)
    except ModuleNotFoundError:
        raise
    except OSError as e:
        if e.filename is not None:  # opening a file failed: the message names it
            raise
        # A parser's own OSError (a seek before the start of a damaged archive, ...).
        raise ValueError(f"{path}: not a readable vesselflow graph: {_reason(e)}") from e
    except MemoryError as e:
        raise MemoryError(_memory_message(path, e)) from e
    except KeyError as e:
        raise ValueError(f"{path}: not a vesselflow graph: missing field {e}") from e
    except Exception as e:  # each parser raises its own types for a corrupt file
        raise ValueError(f"{path}: not a readable vesselflow graph: {_reason(e)}") from e
    try:
        positions, radii, edges, spacing = check_graph_arrays(
            parts.positions, parts.radii, parts.edges, parts.spacing
        )
        for name, value in (("info", parts.info), ("params", parts.params)):
            if not isinstance(value, dict):
                raise ValueError(f"{name} is not a JSON object")
    except MemoryError as e:
        raise MemoryError(_memory_message(path, e)) from e
    except ValueError as e:
        raise ValueError(f"{path}: invalid graph: {e}") from None
    return VesselGraph(positions, radii, edges, spacing, info=parts.info, params=parts.params)


def _reason(e: BaseException) -> str:
    """An exception as a message that is never empty."""
    if isinstance(e, RecursionError):
        return "nested too deeply"
    text = str(e) or type(e).__name__
    return text if isinstance(e, ValueError) else f"{type(e).__name__}: {text}"


def _memory_message(path: Path, e: MemoryError) -> str:
    try:
        size = f" ({path.stat().st_size / 2**20:.1f} MiB on disk)"
    except OSError:
        size = ""
    detail = f": {e}" if str(e) else ""
    return (
        f"{path}{size}: not enough memory to read this graph{detail}; free memory, or "
        "convert the graph to .npz (the most compact format) on a machine with more memory"
    )


def graph_extension(path: str | os.PathLike[str]) -> str:
    """The lower-case extension of a graph file name; ``ValueError`` naming the file
    and listing the supported ones if it is not a graph format."""
    suffix = Path(path).suffix
    if suffix.lower() not in _READERS:
        supported = ", ".join(sorted(_READERS))
        raise ValueError(f"{path}: unsupported extension {suffix!r} (supported: {supported})")
    return suffix.lower()


class _Parts(NamedTuple):
    """What a reader found, before :func:`check_graph_arrays` has seen it."""

    positions: Any
    radii: Any
    edges: Any
    spacing: Any = (1.0, 1.0, 1.0)
    info: Any = {}  # noqa: RUF012 (never mutated: load_graph copies it)
    params: Any = {}  # noqa: RUF012


def _check_header(meta: Mapping[str, Any]) -> None:
    if meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise ValueError(
            f"expected format {FORMAT!r} version {VERSION}, "
            f"got {meta.get('format')!r} version {meta.get('version')!r}"
        )


def _from_columns(arrays: Mapping[str, Any], meta: Any) -> _Parts:
    """A graph from its array columns and its metadata (header, info, params)."""
    if not isinstance(meta, dict):
        raise ValueError("the metadata is not a JSON object")
    _check_header(meta)
    return _Parts(
        arrays["positions"],
        arrays["radii"],
        arrays["edges"],
        arrays["spacing"],
        meta["info"],
        meta["params"],
    )


def _read_npz(path: Path) -> _Parts:
    with open(path, "rb") as f:  # np.load would also take a single .npy or a pickle
        if not zipfile.is_zipfile(f):
            raise ValueError("not an .npz (zip) archive")
    with np.load(path, allow_pickle=False) as z:
        names = ["positions", "radii", "edges", "spacing", "metadata"]
        missing = [name for name in names if name not in z.files]
        if missing:
            raise KeyError(missing[0])
        arrays = {name: z[name] for name in names[:4]}
        metadata = z["metadata"]
        if metadata.dtype != np.uint8:
            raise ValueError(f"metadata must be uint8 (UTF-8 JSON), got {metadata.dtype}")
        return _from_columns(arrays, json.loads(metadata.tobytes().decode("utf-8")))


def _read_json(path: Path) -> _Parts:
    with open(path, encoding="utf-8") as f:
        doc = json.load(f)
    if not isinstance(doc, dict):
        raise ValueError("top level is not a JSON object")
    return _from_columns(doc, doc)


def _read_graphml(path: Path) -> _Parts:
    import networkx as nx

    # A repeated edge makes networkx return a MultiGraph; its edges view lists each copy.
    graph = nx.read_graphml(path)
    if graph.is_directed():
        raise ValueError("a directed graph (vesselflow graphs are undirected)")
    nodes = graph.nodes
    for node, data in nodes.items():
        missing = [key for key in "xyzr" if key not in data]
        if missing:  # an edge to an undeclared node makes one without data
            raise ValueError(f"node {node!r} has no {missing[0]!r} (x, y, z and r are needed)")
    n = graph.number_of_nodes()
    ids = {node: _node_id(node) for node in nodes}
    if sorted(ids.values()) != list(range(n)):
        raise ValueError(f"node ids are not 0..{n - 1}")
    order = sorted(nodes, key=ids.__getitem__)
    positions = [[nodes[node][axis] for axis in "xyz"] for node in order]
    radii = [nodes[node]["r"] for node in order]
    edges = sorted(sorted((ids[a], ids[b])) for a, b in graph.edges())
    spacing = [graph.graph[f"spacing{axis}"] for axis in range(3)]
    return _Parts(positions, radii, edges, spacing)


def _node_id(text: str) -> int:
    """A GraphML node id that is a plain decimal integer (no sign, spaces or ``_``)."""
    if not (text.isascii() and text.isdigit()) or (len(text) > 1 and text[0] == "0"):
        raise ValueError(f"node id {text!r} is not a number 0..N-1")
    return int(text)


def import_extra(module: str, extra: str) -> ModuleType:
    """Import an optional dependency; if it is missing, say which extra installs it."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        raise ModuleNotFoundError(
            f"{module} is not installed; install it with: pip install vesselflow[{extra}]",
            name=module,
        ) from e


TEMP_PREFIX, TEMP_SUFFIX = ".vesselflow-", ".tmp"
"""Temporary files of an unfinished write are named ``.vesselflow-*.tmp``, as the Rust
writer names them."""


def _temp_beside(path: Path) -> Path:
    return path.with_name(f"{TEMP_PREFIX}{secrets.token_hex(6)}{TEMP_SUFFIX}")


@contextmanager
def atomic_files(*paths: Path) -> Iterator[list[Path]]:
    """One temporary path beside each of ``paths`` for the block to write; when the
    block succeeds they replace ``paths`` together.

    All or nothing: on any failure (an exception in the block, a failed rename,
    ``KeyboardInterrupt``, the ``Terminated`` that the console script raises on
    SIGTERM) the temporary files are removed, the files already replaced get their old
    contents back and files that did not exist are not created.
    """
    temps = [_temp_beside(path) for path in paths]
    try:
        yield temps
        _replace_all(temps, list(paths))
    finally:
        for temp in temps:
            temp.unlink(missing_ok=True)


@contextmanager
def _atomic(path: Path) -> Iterator[Path]:
    """:func:`atomic_files` for one file."""
    with atomic_files(path) as (temp,):
        yield temp


def _replace_all(temps: list[Path], paths: list[Path]) -> None:
    if len(paths) == 1:
        os.replace(temps[0], paths[0])
        return
    # Keep the old files (a hard link, or a copy where links are not supported) until
    # every new one is in place, so that a failure part-way can put them back. What is
    # undone is read from the disk, not from variables, so an exception between any two
    # steps (KeyboardInterrupt, SIGTERM) still undoes exactly what was done.
    backups = [_temp_beside(path) for path in paths]
    try:
        for path, backup in zip(paths, backups):
            _keep_old(path, backup)
        for temp, path in zip(temps, paths):
            os.replace(temp, path)
    except BaseException:
        for temp, path, backup in zip(temps, paths, backups):
            if temp.exists():  # not moved into place: nothing to undo
                continue
            if backup.exists():
                os.replace(backup, path)
            else:
                path.unlink(missing_ok=True)
        raise
    finally:
        for backup in backups:
            backup.unlink(missing_ok=True)


def _keep_old(path: Path, backup: Path) -> None:
    """Give the file at ``path``, if any, the second name ``backup``."""
    if not os.path.lexists(path):
        return
    try:
        os.link(path, backup, follow_symlinks=False)
    except OSError:
        shutil.copy2(path, backup, follow_symlinks=False)


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
    with atomic_files(path) as (temp,):
        temp.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _read_swc(path: Path) -> _Parts:
    spacing: list[str] = ["1", "1", "1"]
    loop_ids: list[tuple[int, int]] = []
    rows: list[list[str]] = []
    with open(path, encoding="utf-8") as f:
        for number, line in enumerate(f, start=1):
            words = line.split()
            if not words:
                continue
            if words[0].startswith("#"):
                tag = words[1:2] if words[0] == "#" else [words[0][1:]]
                values = words[2:] if words[0] == "#" else words[1:]
                if tag == ["spacing"]:
                    spacing = values
                elif tag == ["loop-edge"]:
                    if len(values) != 2:
                        raise ValueError(f"line {number}: a loop-edge line needs 2 SWC ids")
                    loop_ids.append((_swc_id(values[0], number), _swc_id(values[1], number)))
                continue
            if len(words) < 7:
                raise ValueError(f"line {number}: an SWC line needs 7 columns: {line.strip()!r}")
            rows.append(words[:7])
    ids = [_swc_id(row[0], 0) for row in rows]
    index = {swc: i for i, swc in enumerate(ids)}
    if len(index) != len(ids):
        raise ValueError("repeated SWC ids")

    def node(swc: int) -> int:
        if swc not in index:
            raise ValueError(f"SWC id {swc} is not a sample")
        return index[swc]

    parents = [_swc_id(row[6], 0) for row in rows]
    edges = [(node(up), i) for i, up in enumerate(parents) if up >= 0]
    edges += [(node(a), node(b)) for a, b in loop_ids]
    table = np.array([[float(w) for w in row[2:6]] for row in rows], dtype=np.float64)
    table = table.reshape(-1, 4)
    return _Parts(table[:, :3], table[:, 3], edges, [float(s) for s in spacing])


def _swc_id(word: str, line: int) -> int:
    """An SWC sample id or parent id: an integer, written as such or as ``n.0``."""
    value = float(word)
    if not (np.isfinite(value) and value == int(value)):
        where = f"line {line}: " if line else ""
        raise ValueError(f"{where}SWC id {word!r} is not an integer")
    return int(value)


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
    with atomic_files(path) as (temp,):
        writer = xml.vtkXMLPolyDataWriter()
        writer.SetFileName(str(temp))
        writer.SetInputData(poly)
        if writer.Write() != 1:
            raise OSError(f"{path}: VTK could not write the file")


def _read_vtp(path: Path) -> _Parts:
    _, _, xml, numpy_vtk = _vtk()
    if not path.is_file():
        raise FileNotFoundError(errno.ENOENT, "no such file", str(path))
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
    if poly.GetNumberOfPolys() or poly.GetNumberOfStrips():
        raise ValueError("it holds polygons or triangle strips, not only lines")
    cells = poly.GetLines()
    offsets = numpy_vtk.vtk_to_numpy(cells.GetOffsetsArray())
    connectivity = numpy_vtk.vtk_to_numpy(cells.GetConnectivityArray())
    # Consecutive points of one polyline are joined; no segment crosses polylines.
    within = np.ones(len(connectivity), dtype=bool)
    within[offsets[:-1]] = False
    edges = np.stack([connectivity[:-1], connectivity[1:]], axis=1)[within[1:]]
    spacing_array = poly.GetFieldData().GetArray("spacing")
    spacing = (1.0, 1.0, 1.0) if spacing_array is None else numpy_vtk.vtk_to_numpy(spacing_array)
    return _Parts(positions, numpy_vtk.vtk_to_numpy(radius), edges, spacing)


def csv_edges_path(path: str | os.PathLike[str]) -> Path:
    """The edges table written beside a nodes table: ``graph.csv`` -> ``graph.edges.csv``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.edges{path.suffix}")


def _write_csv(graph: VesselGraph, path: Path) -> None:
    with atomic_files(path, csv_edges_path(path)) as (nodes_temp, edges_temp):
        with open(nodes_temp, "w", newline="", encoding="utf-8") as f:
            writer = csv.writer(f)
            writer.writerow(["id", "x", "y", "z", "r"])
            positions = graph.positions.tolist()
            writer.writerows([i, *positions[i], r] for i, r in enumerate(graph.radii.tolist()))
        with open(edges_temp, "w", newline="", encoding="utf-8") as f:
            writer = csv.writer(f)
            writer.writerow(["source", "target"])
            writer.writerows(graph.edges.tolist())


def _read_csv(path: Path) -> _Parts:
    nodes = _csv_table(path, ["id", "x", "y", "z", "r"])
    edges_path = csv_edges_path(path)
    edges = _csv_table(edges_path, ["source", "target"])
    index = {row["id"]: i for i, row in enumerate(nodes)}
    if len(index) != len(nodes):
        raise ValueError("repeated node ids")

    def node(row: int, end: str) -> int:
        name = edges[row][end]
        if name not in index:
            raise ValueError(f"{edges_path.name} row {row + 1}: {end} {name!r} is not a node id")
        return index[name]

    return _Parts(
        [[float(row[axis]) for axis in "xyz"] for row in nodes],
        [float(row["r"]) for row in nodes],
        [(node(row, "source"), node(row, "target")) for row in range(len(edges))],
    )


def _csv_table(path: Path, columns: list[str]) -> list[dict[str, str]]:
    """The rows of a CSV table with (at least) ``columns``, each row complete."""
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        missing = [c for c in columns if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path.name}: no column {', '.join(map(repr, missing))}")
        rows = list(reader)
    for number, row in enumerate(rows, start=1):
        if None in row or any(row[c] is None for c in columns):
            raise ValueError(f"{path.name} row {number}: wrong number of fields")
    return rows


_READERS: dict[str, Callable[[Path], _Parts]] = {
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
