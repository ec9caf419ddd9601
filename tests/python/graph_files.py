"""Graph files written without the checks of VesselGraph.save, as another tool (or a
damaged file) might hold them: the inputs of the loaders' tests."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from vesselflow import VesselGraph
from vesselflow.io import csv_edges_path

GRAPH_FORMATS = [".npz", ".json", ".graphml", ".swc", ".csv", ".vtp"]
"""The formats :func:`vesselflow.load_graph` reads (``.precomputed`` is written only)."""

_GRAPHML_HEAD = """<?xml version="1.0" encoding="UTF-8"?>
<graphml xmlns="http://graphml.graphdrawing.org/xmlns">
  <key id="spacing0" for="graph" attr.name="spacing0" attr.type="double"/>
  <key id="spacing1" for="graph" attr.name="spacing1" attr.type="double"/>
  <key id="spacing2" for="graph" attr.name="spacing2" attr.type="double"/>
  <key id="x" for="node" attr.name="x" attr.type="double"/>
  <key id="y" for="node" attr.name="y" attr.type="double"/>
  <key id="z" for="node" attr.name="z" attr.type="double"/>
  <key id="r" for="node" attr.name="r" attr.type="double"/>
  <graph id="G" edgedefault="undirected">
"""


def write_raw(
    path: Path,
    positions: Any,
    radii: Any,
    edges: Any,
    spacing: Any = (1.0, 1.0, 1.0),
) -> None:
    """Write the arrays as they are in the format of ``path``'s extension."""
    ext = path.suffix
    header = {"format": "vesselflow-graph", "version": 1}
    if ext == ".json":
        doc = {
            **header,
            "spacing": list(spacing),
            "positions": np.asarray(positions).tolist(),
            "radii": np.asarray(radii).tolist(),
            "edges": np.asarray(edges).tolist(),
            "info": {},
            "params": {},
        }
        path.write_text(json.dumps(doc))
    elif ext == ".npz":
        meta = json.dumps({**header, "info": {}, "params": {}}).encode()
        np.savez(
            path,
            positions=np.asarray(positions),
            radii=np.asarray(radii),
            edges=np.asarray(edges),
            spacing=np.asarray(spacing, dtype=np.float64),
            metadata=np.frombuffer(meta, dtype=np.uint8),
        )
    elif ext == ".graphml":
        lines = [_GRAPHML_HEAD]
        lines += [f'    <data key="spacing{a}">{s!r}</data>\n' for a, s in enumerate(spacing)]
        for i, ((x, y, z), r) in enumerate(zip(np.asarray(positions).tolist(), radii)):
            values = "".join(
                f'<data key="{k}">{float(v)!r}</data>' for k, v in zip("xyzr", (x, y, z, r))
            )
            lines.append(f'    <node id="{i}">{values}</node>\n')
        lines += [f'    <edge source="{a}" target="{b}"/>\n' for a, b in edges]
        lines.append("  </graph>\n</graphml>\n")
        path.write_text("".join(lines))
    else:
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        edges = np.asarray(edges).reshape(-1, 2)
        _RAW_WRITERS[ext](path, positions, np.asarray(radii, dtype=np.float64), edges, spacing)


def _raw_swc(path: Path, positions: Any, radii: Any, edges: Any, spacing: Any) -> None:
    """Every node a root, every edge a ``# loop-edge`` line (ids 1-based)."""
    lines = [f"# spacing {' '.join(repr(float(s)) for s in spacing)}"]
    lines += [f"# loop-edge {int(a) + 1} {int(b) + 1}" for a, b in edges.tolist()]
    for i, ((x, y, z), r) in enumerate(zip(positions.tolist(), radii.tolist()), start=1):
        lines.append(f"{i} 0 {x!r} {y!r} {z!r} {r!r} -1")
    path.write_text("\n".join(lines) + "\n")


def _raw_csv(path: Path, positions: Any, radii: Any, edges: Any, spacing: Any) -> None:
    rows = [
        f"{i},{x!r},{y!r},{z!r},{r!r}"
        for i, ((x, y, z), r) in enumerate(zip(positions.tolist(), radii.tolist()))
    ]
    path.write_text("\n".join(["id,x,y,z,r", *rows]) + "\n")
    pairs = [f"{a},{b}" for a, b in edges.tolist()]
    csv_edges_path(path).write_text("\n".join(["source,target", *pairs]) + "\n")


def _raw_vtp(path: Path, positions: Any, radii: Any, edges: Any, spacing: Any) -> None:
    from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
    from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter

    points = vtkPoints()
    points.SetData(numpy_to_vtk(np.ascontiguousarray(positions), deep=True))
    lines = vtkCellArray()
    lines.SetData(
        numpy_to_vtkIdTypeArray(np.arange(0, 2 * len(edges) + 1, 2, dtype=np.int64), deep=True),
        numpy_to_vtkIdTypeArray(np.asarray(edges, dtype=np.int64).reshape(-1).copy(), deep=True),
    )
    poly = vtkPolyData()
    poly.SetPoints(points)
    poly.SetLines(lines)
    radius = numpy_to_vtk(np.ascontiguousarray(radii), deep=True)
    radius.SetName("radius")
    poly.GetPointData().AddArray(radius)
    writer = vtkXMLPolyDataWriter()
    writer.SetFileName(str(path))
    writer.SetInputData(poly)
    assert writer.Write() == 1


_RAW_WRITERS = {".swc": _raw_swc, ".csv": _raw_csv, ".vtp": _raw_vtp}


def canonical(graph: VesselGraph) -> tuple[np.ndarray, np.ndarray, Counter[tuple[int, int]]]:
    """Positions and radii sorted by position, and the multiset of edges in that order:
    equal for two graphs that differ only in node numbering, edge order and direction."""
    order = np.lexsort(graph.positions.T[::-1])
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    edges = Counter(tuple(sorted(pair)) for pair in rank[graph.edges].tolist())
    return graph.positions[order], graph.radii[order], edges


def assert_same_graph(a: VesselGraph, b: VesselGraph) -> None:
    pa, ra, ea = canonical(a)
    pb, rb, eb = canonical(b)
    np.testing.assert_array_equal(pa, pb)
    np.testing.assert_array_equal(ra, rb)
    assert ea == eb
