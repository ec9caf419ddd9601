"""The centreline graph a run returns: arrays, run record, conversions, saving."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vesselflow import _core

if TYPE_CHECKING:
    import networkx as nx
    import pandas as pd
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure


class VesselGraph:
    """A vessel centreline graph with radii.

    Attributes
    ----------
    positions : (N, 3) float64
        Node positions in physical units, in the mask's array axis order (axis 0, 1, 2).
    radii : (N,) float64
        Vessel radius at each node, physical units.
    edges : (E, 2) int64
        Undirected edges as node-index pairs.
    spacing : (3,) float64
        Voxel spacing of the mask the graph came from.
    info : dict
        Record of the run (iterations, convergence, nodes per iteration, seconds
        per stage, ...); empty for graphs loaded from formats that do not keep it.
    params : dict
        Parameters of the run; empty when unknown.

    The constructor takes anything array-like, converts it to these dtypes and
    checks the shapes and edge ids (``ValueError``).
    """

    positions: NDArray[np.float64]
    radii: NDArray[np.float64]
    edges: NDArray[np.int64]
    spacing: NDArray[np.float64]
    info: dict[str, Any]
    params: dict[str, Any]

    def __init__(
        self,
        positions: ArrayLike,
        radii: ArrayLike,
        edges: ArrayLike,
        spacing: ArrayLike = (1.0, 1.0, 1.0),
        info: Mapping[str, Any] | None = None,
        params: Mapping[str, Any] | None = None,
    ) -> None:
        self.positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        self.radii = np.asarray(radii, dtype=np.float64).reshape(-1)
        self.edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        self.spacing = np.asarray(spacing, dtype=np.float64).reshape(-1)
        self.info = dict(info or {})
        self.params = dict(params or {})
        n = len(self.positions)
        if len(self.radii) != n:
            raise ValueError(f"{n} positions but {len(self.radii)} radii")
        if self.spacing.shape != (3,):
            raise ValueError(f"spacing must hold 3 numbers, got {self.spacing.shape[0]}")
        if self.edges.size and (self.edges.min() < 0 or self.edges.max() >= n):
            raise ValueError(f"edges refer to nodes outside 0..{n - 1}")

    @property
    def n_nodes(self) -> int:
        """Number of nodes."""
        return len(self.positions)

    @property
    def n_edges(self) -> int:
        """Number of edges."""
        return len(self.edges)

    def degrees(self) -> NDArray[np.int64]:
        """Degree of every node, (N,) int64."""
        return np.bincount(self.edges.ravel(), minlength=self.n_nodes).astype(np.int64)

    def to_networkx(self) -> nx.Graph:
        """An undirected ``networkx.Graph``: nodes ``0..N-1`` with attributes ``pos``
        (length-3 array, physical units) and ``r`` (radius); graph attribute ``spacing``."""
        import networkx as nx

        graph = nx.Graph(spacing=tuple(self.spacing.tolist()))
        graph.add_nodes_from(
            (i, {"pos": self.positions[i].copy(), "r": float(r)}) for i, r in enumerate(self.radii)
        )
        graph.add_edges_from(self.edges.tolist())
        return graph

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the graph to ``path``; the extension picks the format.

        ``.npz``, ``.json`` and ``.graphml`` are written by the same code as the
        ``vesselflow`` binary; ``.swc`` (a forest, loops listed in ``# loop-edge`` header
        lines), ``.vtp`` (VTK PolyData with a ``radius`` point array; needs the ``io``
        extra) and ``.csv`` (nodes table ``graph.csv`` plus edges table
        ``graph.edges.csv``) by :mod:`vesselflow.io`. Every file is written atomically
        (a temporary file in the same folder, then renamed)."""
        from vesselflow.io import WRITERS, graph_extension

        write = WRITERS.get(graph_extension(path))
        if write is not None:
            write(self, Path(path))
            return
        _core.write_graph(
            os.fspath(path),
            np.ascontiguousarray(self.positions, dtype=np.float64),
            np.ascontiguousarray(self.radii, dtype=np.float64),
            np.ascontiguousarray(self.edges, dtype=np.int64),
            np.ascontiguousarray(self.spacing, dtype=np.float64),
            json.dumps(self.info, default=_json_default),
            json.dumps(self.params, default=_json_default),
        )

    def __repr__(self) -> str:
        spacing = ", ".join(f"{s:g}" for s in self.spacing)
        converged = self.info.get("converged")
        tail = "" if converged is None else f", converged={converged}"
        return (
            f"VesselGraph(n_nodes={self.n_nodes}, n_edges={self.n_edges}, "
            f"spacing=({spacing}){tail})"
        )

    def branches(self) -> pd.DataFrame:
        """The branch table, one row per branch between junctions and endpoints, with
        lengths, tortuosity, radius statistics, volume and surface area in physical units
        (skan-compatible column names): see :func:`vesselflow.analysis.branches`."""
        from vesselflow.analysis import branches

        return branches(self)

    def junctions(self) -> pd.DataFrame:
        """One row per node of degree >= 3: position, radius, degree and the angles (degrees)
        between its branches: see :func:`vesselflow.analysis.junctions`."""
        from vesselflow.analysis import junctions

        return junctions(self)

    def prune(self, min_length_over_radius: float = 2.0) -> VesselGraph:
        """A new graph without terminal spurs shorter than ``min_length_over_radius`` times
        the radius where they join, removed iteratively; components and loops are kept:
        see :func:`vesselflow.analysis.prune`."""
        from vesselflow.analysis import prune

        return prune(self, min_length_over_radius)

    def plot(
        self,
        mask: ArrayLike | None = None,
        path: str | os.PathLike[str] | None = None,
        axis: int = 0,
        ax: Axes | None = None,
    ) -> Figure:
        """Maximum-intensity projection of ``mask`` along ``axis`` with the edges drawn on
        top, coloured by radius; saved as PNG (atomically) when ``path`` is given. Needs
        matplotlib (``pip install 'vesselflow[viz]'``): see :func:`vesselflow.plot.plot`."""
        from vesselflow.plot import plot

        return plot(self, mask=mask, path=path, axis=axis, ax=ax)


def _json_default(obj: object) -> Any:
    """JSON for the NumPy values a user may put in ``info`` or ``params``."""
    if isinstance(obj, (np.generic, np.ndarray)):
        return obj.tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serializable")
