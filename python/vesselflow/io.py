"""Reading graph files written by :meth:`VesselGraph.save` or the ``vesselflow`` binary.

The formats (``.npz``, ``.json``, ``.graphml``) are defined in the project's format
contract: positions in physical units and array axis order, node ids ``0..N-1``.
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Any, Callable
from xml.etree.ElementTree import ParseError

import numpy as np

from vesselflow.graph import VesselGraph

FORMAT = "vesselflow-graph"
VERSION = 1


def load_graph(path: str | os.PathLike[str]) -> VesselGraph:
    """Read a graph file; the extension (``.npz``, ``.json``, ``.graphml``) picks the format.

    Raises ``OSError`` if the file cannot be read and ``ValueError`` if it is not a
    vesselflow graph or has an unsupported extension; both messages name the file.
    ``.graphml`` files carry no run record: ``info`` and ``params`` are empty.
    """
    path = Path(path)
    reader = _READERS.get(path.suffix.lower())
    if reader is None:
        supported = ", ".join(sorted(_READERS))
        raise ValueError(f"{path}: unsupported extension {path.suffix!r} (supported: {supported})")
    try:
        return reader(path)
    except OSError:
        raise
    except KeyError as e:
        raise ValueError(f"{path}: not a vesselflow graph: missing field {e}") from e
    except (ValueError, TypeError, IndexError, ParseError, zipfile.BadZipFile, EOFError) as e:
        raise ValueError(f"{path}: not a readable vesselflow graph: {e}") from e


def _check_header(meta: dict[str, Any]) -> None:
    if meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise ValueError(
            f"expected format {FORMAT!r} version {VERSION}, "
            f"got {meta.get('format')!r} version {meta.get('version')!r}"
        )


def _read_npz(path: Path) -> VesselGraph:
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(z["metadata"].tobytes().decode("utf-8"))
        _check_header(meta)
        return VesselGraph(
            positions=z["positions"],
            radii=z["radii"],
            edges=z["edges"],
            spacing=z["spacing"],
            info=meta["info"],
            params=meta["params"],
        )


def _read_json(path: Path) -> VesselGraph:
    with open(path, encoding="utf-8") as f:
        doc = json.load(f)
    if not isinstance(doc, dict):
        raise ValueError("top level is not a JSON object")
    _check_header(doc)
    return VesselGraph(
        positions=doc["positions"],
        radii=doc["radii"],
        edges=doc["edges"],
        spacing=doc["spacing"],
        info=doc["info"],
        params=doc["params"],
    )


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


_READERS: dict[str, Callable[[Path], VesselGraph]] = {
    ".graphml": _read_graphml,
    ".json": _read_json,
    ".npz": _read_npz,
}
