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

    The constructor takes anything array-like, converts it to these dtypes and checks
    it with :func:`check_graph_arrays` (``ValueError`` naming the problem). Repeated
    edges are kept (every format keeps them); self-loops are refused.
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
        try:
            self.positions, self.radii, self.edges, self.spacing = check_graph_arrays(
                positions, radii, edges, spacing
            )
        except ValueError as e:
            raise ValueError(f"invalid graph: {e}{_RUN_HINT}") from None
        self.info = dict(info or {})
        self.params = dict(params or {})

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
        (a temporary file in the same folder, then renamed; the two CSV tables are
        replaced together or not at all). The arrays are checked first
        (:func:`check_graph_arrays`, ``ValueError``)."""
        from vesselflow.io import WRITERS, graph_extension

        extension = graph_extension(path)
        try:  # the arrays are public attributes: check what is written, not what was built
            check_graph_arrays(self.positions, self.radii, self.edges, self.spacing)
        except ValueError as e:
            raise ValueError(f"cannot save {path}: invalid graph: {e}{_RUN_HINT}") from None
        write = WRITERS.get(extension)
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


_RUN_HINT = (
    " (a graph returned by a vesselflow run never has this: if a run returned it, "
    "it is an internal error, please report it)"
)
"""Said with every refusal of a graph that is not read from a file."""


def check_graph_arrays(
    positions: ArrayLike,
    radii: ArrayLike,
    edges: ArrayLike,
    spacing: ArrayLike = (1.0, 1.0, 1.0),
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
    """The one rule for a valid graph, applied by the :class:`VesselGraph` constructor,
    by :func:`vesselflow.load_graph` to every format it reads, and before every save.

    ``positions`` is ``(N, 3)`` finite; ``radii`` is ``(N,)`` finite and ``>= 0``;
    ``edges`` is ``(E, 2)`` of integer node ids in ``0..N-1`` (integer-valued floats
    are accepted, other floats refused, never truncated) with no edge from a node to
    itself; repeated edges are allowed. ``spacing`` is 3 finite numbers ``> 0``. Empty
    arrays of any 1-D or 2-D shape with the right width stand for no nodes or no edges.

    Returns the arrays as float64 and int64; raises ``ValueError`` naming the first
    problem (array, index and value).
    """
    positions_ = _numbers("positions", positions, width=3)
    n = len(positions_)
    radii_ = _numbers("radii", radii, width=None)
    spacing_ = _numbers("spacing", spacing, width=None)
    if len(radii_) != n:
        raise ValueError(f"{n} positions but {len(radii_)} radii")
    if spacing_.shape != (3,) or not np.all(np.isfinite(spacing_) & (spacing_ > 0)):
        raise ValueError(f"spacing {spacing_.tolist()} must be 3 finite numbers > 0")
    bad = ~np.isfinite(positions_).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"positions[{i}] = {tuple(positions_[i].tolist())} is not finite")
    bad = ~(np.isfinite(radii_) & (radii_ >= 0))
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"radii[{i}] = {float(radii_[i])!r} is not a finite number >= 0")
    return positions_, radii_, _edge_ids(edges, n), spacing_


def _as_array(name: str, values: ArrayLike) -> NDArray[Any]:
    try:
        return np.asarray(values)
    except (ValueError, TypeError, OverflowError, RecursionError) as e:
        raise ValueError(f"{name} is not an array of numbers: {e}") from None


def _numbers(name: str, values: ArrayLike, width: int | None) -> NDArray[np.float64]:
    """``values`` as float64, ``(M, width)`` or ``(M,)`` when ``width`` is None."""
    array = _as_array(name, values)
    if array.size == 0 and array.ndim == 1:
        return np.empty((0,) if width is None else (0, width))
    if array.dtype.kind not in "iuf":
        raise ValueError(f"{name} must be numbers, got {array.dtype} values")
    shape_ok = array.ndim == 1 if width is None else array.ndim == 2 and array.shape[1] == width
    if not shape_ok:
        expected = "(N,)" if width is None else f"(N, {width})"
        raise ValueError(f"{name} must have shape {expected}, got {array.shape}")
    return array.astype(np.float64, copy=False)


def _edge_ids(edges: ArrayLike, n: int) -> NDArray[np.int64]:
    array = _as_array("edges", edges)
    if array.size == 0 and (array.ndim == 1 or array.shape[1:] == (2,)):
        return np.empty((0, 2), dtype=np.int64)
    if array.ndim != 2 or array.shape[1] != 2:
        raise ValueError(f"edges must have shape (E, 2), got {array.shape}")
    if array.dtype.kind == "f":
        bad = ~(np.isfinite(array) & (array == np.round(array)))
        if bad.any():
            e = int(np.argmax(bad.any(axis=1)))
            raise ValueError(f"edges[{e}] = {tuple(array[e].tolist())} are not integer node ids")
    elif array.dtype.kind not in "iu":
        raise ValueError(f"edges must be integer node ids, got {array.dtype} values")
    bad = ((array < 0) | (array >= n)).any(axis=1)
    if bad.any():
        e = int(np.argmax(bad))
        pair = tuple(array[e].tolist())
        raise ValueError(f"edges[{e}] = {pair} refers to a node outside 0..{n - 1}")
    ids = array.astype(np.int64)
    loops = ids[:, 0] == ids[:, 1]
    if loops.any():
        e = int(np.argmax(loops))
        raise ValueError(f"edges[{e}] joins node {ids[e, 0]} to itself (self-loops are refused)")
    return ids
