"""Graph files in: reading every format :meth:`VesselGraph.save` writes.

Every format is written by the Rust writers of ``vesselflow-io`` (the one registry of
graph formats, shared with the ``vesselflow`` binary, reached through
:func:`vesselflow._core.write_graph`); they are read back here, in Python, because the
readers use the field's Python libraries (networkx for GraphML, VTK for ``.vtp``). In
every format positions are physical units in the graph's coordinate frame (array axis
order, ``x``, ``y``, ``z`` = axes 0, 1, 2, unless the run asked for ``coordinates=``)
and radii are in the same units. ``.precomputed`` (Neuroglancer) folders are written,
not read: Neuroglancer, cloud-volume and osteoid read them.
"""

from __future__ import annotations

import csv
import errno
import json
import os
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Callable, NamedTuple

import numpy as np

from vesselflow._util import import_extra
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
    each segment is an edge. ``.precomputed`` folders are written, not read.

    Parameters
    ----------
    path : str or os.PathLike
        The graph file.

    Returns
    -------
    VesselGraph
        The graph, with the spacing, run record and parameters its format keeps.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from vesselflow import VesselGraph
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "g.swc"
    >>> VesselGraph([[0, 0, 0], [0, 0, 2]], [1.0, 0.5], [[0, 1]]).save(path)
    >>> load_graph(path).edges.tolist()
    [[0, 1]]
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
    """The edges table beside a nodes table, as the Rust writer names it.

    Parameters
    ----------
    path : str or os.PathLike
        The nodes table, ``name.csv``.

    Returns
    -------
    pathlib.Path
        ``name.edges.csv`` in the same folder.

    Examples
    --------
    >>> csv_edges_path("out/graph.csv").as_posix()
    'out/graph.edges.csv'
    """
    path = Path(path)
    return path.with_name(f"{path.stem}.edges{path.suffix}")


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
