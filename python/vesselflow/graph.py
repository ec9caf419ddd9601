"""The centreline graph a run returns: arrays, run record, conversions, saving."""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Literal

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

    Examples
    --------
    >>> from vesselflow import VesselGraph
    >>> graph = VesselGraph(positions=[[0, 0, 0], [0, 0, 2], [0, 2, 2]], radii=[1, 1, 0.5],
    ...                     edges=[[0, 1], [1, 2]], spacing=(2.0, 1.0, 1.0))
    >>> graph
    VesselGraph(n_nodes=3, n_edges=2, spacing=(2, 1, 1))
    >>> graph.positions.dtype, graph.edges.dtype
    (dtype('float64'), dtype('int64'))
    >>> VesselGraph([[0, 0, 0]], [1.0], [[0, 0]])  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: invalid graph: edges[0] joins node 0 to itself (self-loops are refused) ...
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
        """Number of nodes, ``len(positions)``."""
        return len(self.positions)

    @property
    def n_edges(self) -> int:
        """Number of edges, ``len(edges)`` (a repeated edge counts each time)."""
        return len(self.edges)

    def degrees(self) -> NDArray[np.int64]:
        """The degree of every node.

        Returns
        -------
        (N,) int64
            Edges at each node (1: a vessel end, 2: along a vessel, >= 3: a junction).

        Examples
        --------
        >>> from vesselflow import VesselGraph
        >>> VesselGraph([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [1, 1, 1], [[0, 1], [1, 2]]).degrees()
        array([1, 2, 1])
        """
        return np.bincount(self.edges.ravel(), minlength=self.n_nodes).astype(np.int64)

    def to_networkx(self) -> nx.Graph:
        """The graph as a ``networkx.Graph``.

        Returns
        -------
        networkx.Graph
            Undirected; nodes ``0..N-1`` with attributes ``pos`` (length-3 array, physical
            units) and ``r`` (radius); graph attribute ``spacing``. A repeated edge
            becomes one networkx edge.

        Examples
        --------
        >>> import networkx as nx
        >>> from vesselflow import VesselGraph
        >>> graph = VesselGraph([[0, 0, 0], [3, 4, 0]], [1.0, 0.5], [[0, 1]])
        >>> G = graph.to_networkx()
        >>> G.nodes[1]["r"], nx.number_connected_components(G)
        (0.5, 1)
        """
        import networkx as nx

        graph = nx.Graph(spacing=tuple(self.spacing.tolist()))
        graph.add_nodes_from(
            (i, {"pos": self.positions[i].copy(), "r": float(r)}) for i, r in enumerate(self.radii)
        )
        graph.add_edges_from(self.edges.tolist())
        return graph

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the graph to ``path``; the extension picks the format.

        Every format is written by the Rust writers that the ``vesselflow`` binary uses
        too (one registry, :func:`vesselflow._core.write_graph`): ``.npz``, ``.json``
        and ``.graphml`` (the vesselflow-graph format), ``.swc`` (a forest, loops listed
        in ``# loop-edge`` header lines), ``.vtp`` (VTK XML PolyData with a ``radius``
        point array), ``.csv`` (nodes table ``graph.csv`` plus edges table
        ``graph.edges.csv``) and ``.precomputed`` (a Neuroglancer skeleton folder:
        ``info`` and the skeleton of segment 1, with a ``radius`` vertex attribute).
        Every file is written atomically (a temporary file in the same folder, then
        renamed; the two CSV tables are replaced together or not at all; a
        ``.precomputed`` folder replaces only an earlier skeleton folder).

        Parameters
        ----------
        path : str or os.PathLike
            The file (or ``.precomputed`` folder) to write.

        Returns
        -------
        None

        Raises
        ------
        ValueError
            An unsupported extension, or arrays that break :func:`check_graph_arrays`.
        OSError
            The file cannot be written; nothing is left behind.

        Examples
        --------
        >>> import tempfile, pathlib
        >>> graph = VesselGraph([[0, 0, 0], [0, 0, 2]], [1.0, 1.0], [[0, 1]])
        >>> folder = pathlib.Path(tempfile.mkdtemp())
        >>> graph.save(folder / "g.swc")
        >>> (folder / "g.swc").read_text().splitlines()[-1]
        '2 0 0.0 0.0 2.0 1.0 1'
        """
        try:  # the arrays are public attributes: check what is written, not what was built
            check_graph_arrays(self.positions, self.radii, self.edges, self.spacing)
        except ValueError as e:
            raise ValueError(f"cannot save {path}: invalid graph: {e}{_RUN_HINT}") from None
        _core.write_graph(
            os.fspath(path),
            np.ascontiguousarray(self.positions, dtype=np.float64),
            np.ascontiguousarray(self.radii, dtype=np.float64),
            np.ascontiguousarray(self.edges, dtype=np.int64),
            np.ascontiguousarray(self.spacing, dtype=np.float64),
            json.dumps(self.info, default=_json_default),
            json.dumps(self.params, default=_json_default),
        )

    def to_coordinates(
        self, coordinates: Literal["array", "xyz", "world"], affine: ArrayLike | None = None
    ) -> VesselGraph:
        """The graph with its positions in another coordinate frame.

        A run gives positions in physical units along the array axes (``"array"``:
        voxel ``(i, j, k)`` is at ``(i*s0, j*s1, k*s2)``). ``"xyz"`` reverses the
        columns, so that x is the last array axis (the order of SWC, VTK, Neuroglancer
        and ImageJ for a ``(z, y, x)`` stack), and reverses ``spacing`` with them.
        ``"world"`` maps every position through ``affine``, the image's 4 x 4
        voxel-to-world matrix: ``affine @ (p / spacing, 1)``; ``spacing`` stays in
        array axis order. Radii are not changed: they stay in the units of
        ``spacing``, which are the world's when the affine's column lengths equal the
        spacing (NIfTI's qform; every spacing-only format); otherwise a warning says
        so. The frame is recorded in ``info["coordinates"]`` (and ``info["affine"]``),
        which the writers read (the SWC header, the Neuroglancer transform).

        Parameters
        ----------
        coordinates : {"array", "xyz", "world"}
            The frame.
        affine : array_like (4, 4), optional
            The voxel-to-world affine; needed for ``"world"``.

        Returns
        -------
        VesselGraph
            A new graph (this one is not changed); this graph itself for ``"array"``.

        Raises
        ------
        ValueError
            An unknown frame, a missing or invalid affine (not finite, last row not
            ``0 0 0 1``, singular), or a graph that is not in array coordinates.

        Examples
        --------
        >>> graph = VesselGraph([[1.0, 2.0, 3.0]], [0.5], [], spacing=(1.0, 2.0, 3.0))
        >>> graph.to_coordinates("xyz").positions.tolist()
        [[3.0, 2.0, 1.0]]
        >>> shift = [[1, 0, 0, 10], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
        >>> graph.to_coordinates("world", shift).positions.tolist()  # voxel (1, 1, 1)
        [[11.0, 1.0, 1.0]]
        """
        if coordinates == "array":
            return self
        current = self.info.get("coordinates", "array")
        if current != "array":
            raise ValueError(f"the graph is in {current!r} coordinates, not 'array'")
        matrix = None if affine is None else np.asarray(affine, dtype=np.float64)
        positions, spacing, warning = _core.to_frame(
            np.ascontiguousarray(self.positions), self.spacing.tolist(), coordinates, matrix
        )
        if warning is not None:
            logging.getLogger("vesselflow").warning("coordinates=%r: %s", coordinates, warning)
        info: dict[str, Any] = {**self.info, "coordinates": coordinates}
        if coordinates == "world" and matrix is not None:
            info["affine"] = matrix.tolist()
        return VesselGraph(
            positions, self.radii, self.edges, spacing, info=info, params=self.params
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
        """The branch table: see :func:`vesselflow.analysis.branches`.

        Returns
        -------
        pandas.DataFrame
            One row per branch between junctions and endpoints, with lengths,
            tortuosity, radius statistics, volume and surface area in physical units
            (skan-compatible column names).

        Examples
        --------
        >>> from vesselflow import VesselGraph
        >>> graph = VesselGraph([[0, 0, 0], [0, 3, 4], [0, 6, 8]], [1, 1, 1], [[0, 1], [1, 2]])
        >>> graph.branches()[["branch-distance", "tortuosity"]].to_dict("records")
        [{'branch-distance': 10.0, 'tortuosity': 1.0}]
        """
        from vesselflow.analysis import branches

        return branches(self)

    def junctions(self) -> pd.DataFrame:
        """The junction table: see :func:`vesselflow.analysis.junctions`.

        Returns
        -------
        pandas.DataFrame
            One row per node of degree >= 3: position, radius, degree and the angles
            (degrees) between its branches.

        Examples
        --------
        >>> from vesselflow import VesselGraph
        >>> t = VesselGraph([[0, 0, 0], [0, 0, 5], [0, 0, -5], [0, 5, 0]], [1, 1, 1, 1],
        ...                 [[0, 1], [0, 2], [0, 3]])
        >>> t.junctions()["angles"].tolist()
        [[180.0, 90.0, 90.0]]
        """
        from vesselflow.analysis import junctions

        return junctions(self)

    def prune(self, min_length_over_radius: float = 2.0) -> VesselGraph:
        """Remove short terminal spurs: see :func:`vesselflow.analysis.prune`.

        Parameters
        ----------
        min_length_over_radius : float
            A spur shorter than this many radii of the junction it joins goes, and
            so does one whose nodes all lie within this many radii of another branch
            of its junction.

        Returns
        -------
        VesselGraph
            A new graph (this one is left alone); components and loops are kept.

        Examples
        --------
        >>> from vesselflow import VesselGraph
        >>> spur = VesselGraph([[0, 0, 0], [0, 0, 10], [0, 0, -10], [0, 1, 0]], [1, 1, 1, 0.5],
        ...                    [[0, 1], [0, 2], [0, 3]])
        >>> spur.prune(2.0).n_nodes, spur.prune(0.5).n_nodes
        (3, 4)
        """
        from vesselflow.analysis import prune

        return prune(self, min_length_over_radius)

    def plot(
        self,
        mask: ArrayLike | None = None,
        path: str | os.PathLike[str] | None = None,
        axis: int = 0,
        ax: Axes | None = None,
    ) -> Figure:
        """Draw the graph over the mask: see :func:`vesselflow.plot.plot`.

        A maximum-intensity projection of ``mask`` along ``axis`` with the edges drawn on
        top, coloured by radius; saved as PNG (atomically) when ``path`` is given. Needs
        matplotlib (``pip install 'vesselflow[viz]'``).

        Returns
        -------
        matplotlib.figure.Figure
            The figure (made without pyplot: nothing opens a window).

        Examples
        --------
        >>> fig = graph.plot(mask=mask, path="vessels.png", axis=0)  # doctest: +SKIP
        """
        from vesselflow.plot import plot

        return plot(self, mask=mask, path=path, axis=axis, ax=ax)

    def plot3d(
        self,
        path: str | os.PathLike[str] | None = None,
        *,
        view: str = "iso",
        window_size: tuple[int, int] = (1024, 768),
    ) -> NDArray[np.uint8]:
        """The vessels as tubes coloured by radius, rendered off-screen.

        Needs pyvista (``pip install 'vesselflow[viz]'``); see
        :func:`vesselflow.plot.plot3d` for the details.

        Parameters
        ----------
        path : str or os.PathLike, optional
            Where to save the picture as PNG (written atomically).
        view : {"iso", "xy", "xz", "yz"}
            The camera direction.
        window_size : tuple of 2 ints
            The picture's width and height in pixels.

        Returns
        -------
        numpy.ndarray
            The picture, RGB, ``uint8``, shape ``(height, width, 3)``.

        Examples
        --------
        >>> rgb = graph.plot3d("vessels3d.png", view="iso")  # doctest: +SKIP
        """
        from vesselflow.plot import plot3d

        return plot3d(self, path, view=view, window_size=window_size)


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

    Returns
    -------
    tuple of 4 arrays
        ``positions``, ``radii``, ``edges``, ``spacing`` as float64, float64, int64 and
        float64.

    Raises
    ------
    ValueError
        Naming the first problem (array, index and value).

    Examples
    --------
    >>> from vesselflow.graph import check_graph_arrays
    >>> arrays = check_graph_arrays([[0, 0, 0], [1, 0, 0]], [1, 1], [[0, 1.0]])
    >>> arrays[2].dtype  # the edges
    dtype('int64')
    >>> check_graph_arrays([[0, 0, 0], [1, 0, 0]], [1, -1], [[0, 1]])
    Traceback (most recent call last):
    ...
    ValueError: radii[1] = -1.0 is not a finite number >= 0
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
