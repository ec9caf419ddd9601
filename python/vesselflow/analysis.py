"""Branch analysis of a centreline graph: the branch table, junction angles, spur pruning.

A *branch* is a maximal path whose end nodes have degree != 2 and whose inner nodes
all have degree 2; a connected component made only of degree-2 nodes (an isolated
cycle) is one branch that starts and ends at its smallest node id. Nodes without
edges belong to no branch. Column names follow skan's ``summarize`` where the
quantities overlap, so code written for skan tables reads these too.

All lengths, radii, areas and volumes are in the graph's physical units (positions
are already scaled by the voxel spacing), so results do not depend on anisotropy.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.cluster.hierarchy import DisjointSet

from vesselflow import _core
from vesselflow.graph import VesselGraph

if TYPE_CHECKING:
    import pandas as pd

ENDPOINT_ENDPOINT, JUNCTION_ENDPOINT, JUNCTION_JUNCTION, ISOLATED_CYCLE = 0, 1, 2, 3
"""skan's ``branch-type`` codes."""


@dataclass(frozen=True)
class Branch:
    """One branch of a graph, as :func:`trace_branches` finds it.

    Attributes
    ----------
    nodes : list of int
        Node ids from one end to the other; the first repeats at the end for an
        isolated cycle.
    edges : list of int
        Rows of ``graph.edges``: ``edges[i]`` joins ``nodes[i]`` and ``nodes[i + 1]``.
    branch_type : int
        skan's code: 0 endpoint-endpoint, 1 junction-endpoint, 2 junction-junction,
        3 isolated cycle.

    Examples
    --------
    >>> from vesselflow import VesselGraph
    >>> from vesselflow.analysis import trace_branches
    >>> ring = VesselGraph([[0, 0, 0], [0, 0, 1], [0, 1, 1]], [1, 1, 1], [[0, 1], [1, 2], [2, 0]])
    >>> trace_branches(ring)
    [Branch(nodes=[0, 1, 2, 0], edges=[0, 1, 2], branch_type=3)]
    """

    nodes: list[int]
    edges: list[int]
    branch_type: int


def trace_branches(graph: VesselGraph) -> list[Branch]:
    """Split a graph into its branches (see the module docstring), without the table.

    The node paths behind :func:`branches` and :func:`junctions`, for code that needs
    only the topology (e.g. :mod:`vesselflow.metrics`).

    Parameters
    ----------
    graph : VesselGraph
        Any graph; nodes without edges belong to no branch.

    Returns
    -------
    list of Branch
        In the row order of :func:`branches`: first the branches that start at a node
        of degree != 2 (by node id, then edge order), then the isolated cycles.

    Examples
    --------
    >>> from vesselflow import VesselGraph
    >>> from vesselflow.analysis import trace_branches
    >>> star = VesselGraph([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [2, 0, 0]],
    ...                    [1, 1, 1, 1, 1], [[0, 1], [0, 2], [0, 3], [1, 4]])
    >>> [(b.nodes, b.branch_type) for b in trace_branches(star)]
    [([0, 1, 4], 1), ([0, 2], 1), ([0, 3], 1)]
    """
    return _trace(graph.n_nodes, graph.edges)


def _trace(n_nodes: int, edges: NDArray[np.int64]) -> list[Branch]:
    """Split the graph into branches, walking from every node of degree != 2 along each
    unused edge until the next such node, then around what is left (isolated cycles)."""
    degree = np.bincount(edges.ravel(), minlength=n_nodes).tolist()
    adjacency: list[list[tuple[int, int]]] = [[] for _ in range(n_nodes)]
    for e, (a, b) in enumerate(edges.tolist()):
        adjacency[a].append((b, e))
        adjacency[b].append((a, e))
    used = bytearray(len(edges))

    def walk(
        start: int, first: tuple[int, int], stop_at_start: bool
    ) -> tuple[list[int], list[int]]:
        nodes, path_edges = [start], [first[1]]
        node, edge = first
        used[edge] = 1
        while degree[node] == 2 and not (stop_at_start and node == start):
            nodes.append(node)
            (a, ea), (b, eb) = adjacency[node]
            node, edge = (b, eb) if ea == edge else (a, ea)
            used[edge] = 1
            path_edges.append(edge)
        nodes.append(node)
        return nodes, path_edges

    branches = []
    for start in range(n_nodes):
        if degree[start] == 2:
            continue
        for step in adjacency[start]:
            if not used[step[1]]:
                nodes, path_edges = walk(start, step, stop_at_start=False)
                kind = int(degree[nodes[0]] > 2) + int(degree[nodes[-1]] > 2)
                branches.append(Branch(nodes, path_edges, kind))
    for start in range(n_nodes):
        if degree[start] == 2 and not used[adjacency[start][0][1]]:
            nodes, path_edges = walk(start, adjacency[start][0], stop_at_start=True)
            branches.append(Branch(nodes, path_edges, ISOLATED_CYCLE))
    return branches


def _components(branches: list[Branch]) -> list[int]:
    """Connected component of every branch, numbered in order of first appearance."""
    joined = DisjointSet(n for b in branches for n in (b.nodes[0], b.nodes[-1]))
    for b in branches:
        joined.merge(b.nodes[0], b.nodes[-1])
    labels: dict[int, int] = {}
    return [labels.setdefault(joined[b.nodes[0]], len(labels)) for b in branches]


def _segments(
    graph: VesselGraph, branches: list[Branch]
) -> tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Every edge of every branch: (branch index, length, radius at start, radius at end)."""
    counts = [len(b.edges) for b in branches]
    owner = np.repeat(np.arange(len(branches)), counts)
    start = np.array([n for b in branches for n in b.nodes[:-1]], dtype=np.intp)
    end = np.array([n for b in branches for n in b.nodes[1:]], dtype=np.intp)
    length = np.linalg.norm(graph.positions[end] - graph.positions[start], axis=1)
    return owner, length, graph.radii[start], graph.radii[end]


def branches(graph: VesselGraph) -> pd.DataFrame:
    """One row per branch (see the module docstring), in physical units.

    Columns (skan-compatible names first):

    - ``skeleton-id``: connected component, numbered 0, 1, ... in order of first row.
    - ``node-id-src``, ``node-id-dst``: end node ids (equal for cycles).
    - ``branch-distance``: length of the polyline through the branch's nodes.
    - ``branch-type``: 0 endpoint-endpoint, 1 junction-endpoint, 2 junction-junction,
      3 isolated cycle (a junction is a node of degree >= 3, an endpoint degree 1).
    - ``mean-radius``: plain mean of the radii of the branch's distinct nodes.
    - ``euclidean-distance``: straight distance between the end nodes (0 for cycles).
    - ``coord-src-{0,1,2}``, ``coord-dst-{0,1,2}``: end positions, array axis order.
    - ``tortuosity``: ``branch-distance / euclidean-distance`` (1 for a straight
      branch; NaN when the ends coincide, e.g. cycles, where a chord ratio is
      undefined, so that summaries such as ``describe()`` skip them without warnings).
    - ``radius-mean``, ``radius-sd``: mean and standard deviation of the radius along
      the branch, weighted by length: the radius is taken as linear along each edge
      and integrated exactly (plain node values if the branch has zero length).
    - ``radius-min``, ``radius-max``: extremes over the branch's nodes.
    - ``volume``: sum over edges of the frustum volume ``pi L (r1^2 + r1 r2 + r2^2) / 3``.
    - ``surface-area``: sum of lateral frustum areas ``pi (r1 + r2) sqrt(L^2 + (r1 - r2)^2)``
      (no end caps).
    - ``n-nodes``: distinct nodes on the branch, ends included.
    - ``nodes``: the node ids from src to dst (a list; cycles repeat src at the end).

    Parameters
    ----------
    graph : VesselGraph
        Positions and radii in physical units.

    Returns
    -------
    pandas.DataFrame
        One row per branch, in :func:`trace_branches` order, with the columns above.

    Examples
    --------
    >>> from vesselflow import VesselGraph
    >>> from vesselflow.analysis import branches
    >>> y = VesselGraph([[0, 0, 0], [0, 0, 4], [0, 3, 8], [0, -3, 8], [9, 9, 9], [9, 9, 9.5]],
    ...                 [2, 2, 1, 1, 1, 1], [[0, 1], [1, 2], [1, 3], [4, 5]])
    >>> table = branches(y)
    >>> table[["skeleton-id", "branch-type", "branch-distance", "euclidean-distance"]]
       skeleton-id  branch-type  branch-distance  euclidean-distance
    0            0            1              4.0                 4.0
    1            0            1              5.0                 5.0
    2            0            1              5.0                 5.0
    3            1            0              0.5                 0.5
    >>> table.groupby("skeleton-id")["branch-distance"].sum().tolist()  # length per tree
    [14.0, 0.5]
    """
    import pandas as pd

    traced = trace_branches(graph)
    n = len(traced)
    owner, length, r1, r2 = _segments(graph, traced)
    src = np.array([b.nodes[0] for b in traced], dtype=np.intp)
    dst = np.array([b.nodes[-1] for b in traced], dtype=np.intp)
    distinct = [b.nodes[:-1] if b.nodes[0] == b.nodes[-1] else b.nodes for b in traced]
    node_radii = [graph.radii[d] for d in distinct]

    total = np.bincount(owner, weights=length, minlength=n)
    chord = np.linalg.norm(graph.positions[dst] - graph.positions[src], axis=1)
    node_mean = np.array([r.mean() for r in node_radii])
    node_sd = np.array([r.std() for r in node_radii])
    weighted = np.bincount(owner, weights=length * (r1 + r2) / 2, minlength=n)
    has_length = total > 0
    mean = np.divide(weighted, total, out=node_mean.copy(), where=has_length)
    # Exact integral of (r - mean)^2 along each edge with r linear from r1 to r2.
    a, b = r1 - mean[owner], r2 - mean[owner]
    spread = np.bincount(owner, weights=length * (a * a + a * b + b * b) / 3, minlength=n)
    sd = np.sqrt(np.divide(spread, total, out=node_sd**2, where=has_length))
    with np.errstate(divide="ignore", invalid="ignore"):
        tortuosity = np.where(chord > 0, total / chord, np.nan)

    columns: dict[str, object] = {
        "skeleton-id": np.array(_components(traced), dtype=np.int64),
        "node-id-src": src.astype(np.int64),
        "node-id-dst": dst.astype(np.int64),
        "branch-distance": total,
        "branch-type": np.array([b.branch_type for b in traced], dtype=np.int64),
        "mean-radius": node_mean,
        "euclidean-distance": chord,
    }
    for end, ids in (("src", src), ("dst", dst)):
        for axis in range(3):
            columns[f"coord-{end}-{axis}"] = graph.positions[ids, axis]
    columns.update(
        {
            "tortuosity": tortuosity,
            "radius-mean": mean,
            "radius-min": np.array([r.min() for r in node_radii]),
            "radius-max": np.array([r.max() for r in node_radii]),
            "radius-sd": sd,
            "volume": np.bincount(
                owner, weights=math.pi * length * (r1 * r1 + r1 * r2 + r2 * r2) / 3, minlength=n
            ),
            "surface-area": np.bincount(
                owner, weights=math.pi * (r1 + r2) * np.hypot(length, r1 - r2), minlength=n
            ),
            "n-nodes": np.array([len(d) for d in distinct], dtype=np.int64),
            "nodes": [b.nodes for b in traced],
        }
    )
    return pd.DataFrame(columns)


def _direction(graph: VesselGraph, path: list[int]) -> NDArray[np.float64]:
    """From ``path[0]`` to the first node of ``path`` at least one radius (of
    ``path[0]``) away from it, or to the path's last node if none is that far."""
    origin = graph.positions[path[0]]
    steps = graph.positions[path[1:]] - origin
    far = np.flatnonzero(np.linalg.norm(steps, axis=1) >= graph.radii[path[0]])
    direction: NDArray[np.float64] = steps[far[0] if far.size else -1]
    return direction


def junctions(graph: VesselGraph) -> pd.DataFrame:
    """One row per junction (node of degree >= 3), ordered by node id.

    Columns: ``node-id``; ``coord-{0,1,2}`` (position, array axis order) and
    ``radius``, physical units; ``degree``; ``branches``, the row index in
    :func:`branches` of the branch leaving along each incident edge (a branch
    that returns to the same junction appears twice); ``angles``, the angle in
    degrees between every pair of those branches, pairs ``(0, 1), (0, 2), ...,
    (1, 2), ...`` in ``itertools.combinations`` order (``nan`` for a zero-length
    direction).

    A branch's direction at the junction points from the junction to the first
    node along the branch that is at least one junction radius away (the vessel's
    course outside the junction's own sphere), or to the branch's far end if no
    node is that far.

    Parameters
    ----------
    graph : VesselGraph
        Positions and radii in physical units.

    Returns
    -------
    pandas.DataFrame
        One row per junction with the columns above.

    Examples
    --------
    >>> from vesselflow import VesselGraph
    >>> from vesselflow.analysis import junctions
    >>> y = VesselGraph([[0, 0, 0], [0, 0, 4], [0, 3, 8], [0, -3, 8]], [2, 1, 1, 1],
    ...                 [[0, 1], [1, 2], [1, 3]])
    >>> row = junctions(y).iloc[0]
    >>> int(row["node-id"]), int(row["degree"]), row["branches"]
    (1, 3, [0, 1, 2])
    >>> [round(a, 1) for a in row["angles"]]  # trunk-left, trunk-right, left-right
    [143.1, 143.1, 73.7]
    """
    import pandas as pd

    traced = trace_branches(graph)
    degree = graph.degrees()
    ends: dict[int, list[tuple[int, NDArray[np.float64]]]] = {}
    for row, b in enumerate(traced):
        for path in (b.nodes, b.nodes[::-1]):
            if degree[path[0]] >= 3:
                ends.setdefault(path[0], []).append((row, _direction(graph, path)))

    ids = sorted(ends)
    angles = []
    for j in ids:
        unit = [d / np.linalg.norm(d) if np.any(d) else d * np.nan for _, d in ends[j]]
        angles.append(
            [
                math.degrees(math.acos(float(np.clip(u @ v, -1.0, 1.0))))
                if np.isfinite(u @ v)
                else math.nan
                for u, v in itertools.combinations(unit, 2)
            ]
        )
    rows = np.array(ids, dtype=np.int64)
    return pd.DataFrame(
        {
            "node-id": rows,
            **{f"coord-{axis}": graph.positions[rows, axis] for axis in range(3)},
            "radius": graph.radii[rows],
            "degree": degree[rows],
            "branches": [[row for row, _ in ends[j]] for j in ids],
            "angles": angles,
        }
    )


def prune(graph: VesselGraph, min_length_over_radius: float = 2.0) -> VesselGraph:
    """A copy of ``graph`` without short terminal spurs.

    A spur is a junction-endpoint branch (type 1); it is short when its length is
    below ``min_length_over_radius`` times the radius of the junction it joins, a
    scale-free criterion (a bump on a thick vessel is pruned, a real thin branch of
    the same length on a thin vessel is kept), and also, whatever its length, when
    every one of its nodes lies within ``min_length_over_radius`` radii of another
    branch of its junction (a second rail running beside the vessel). Passes repeat
    until nothing changes, so a spur that becomes short only after its own spurs go is
    pruned too. Each pass removes at most ``degree - 2`` spurs per junction, shortest
    first, so a junction never becomes an endpoint: connected components, loops and
    endpoint-endpoint branches are never removed, and a junction left with degree 2
    becomes an ordinary path node.

    Parameters
    ----------
    graph : VesselGraph
        The graph to prune; it is left alone.
    min_length_over_radius : float
        Finite and >= 0 (0 prunes nothing).

    Returns
    -------
    VesselGraph
        Dense node ids (the kept nodes in their old order), edges in their old order,
        the same ``spacing`` and ``params``, and ``info`` extended with
        ``pruned_branches`` (the count removed) and ``prune_min_length_over_radius``.

    Examples
    --------
    >>> from vesselflow import VesselGraph
    >>> from vesselflow.analysis import prune
    >>> # a vessel along axis 2 (radius 2) with a 1-long bump at node 1
    >>> bumpy = VesselGraph([[0, 0, 0], [0, 0, 5], [0, 0, 10], [0, 1, 5]], [2, 2, 2, 1],
    ...                     [[0, 1], [1, 2], [1, 3]])
    >>> clean = prune(bumpy, 2.0)
    >>> clean.n_nodes, clean.edges.tolist(), clean.info["pruned_branches"]
    (3, [[0, 1], [1, 2]], 1)
    """
    k = float(min_length_over_radius)
    if not (math.isfinite(k) and k >= 0):
        raise ValueError(f"`min_length_over_radius` must be finite and >= 0, got {k}")
    node_kept, edge_kept, pruned = _core.prune_spurs(
        graph.positions, graph.radii, graph.edges.astype(np.int64), k
    )
    new_id = np.cumsum(node_kept) - 1
    return VesselGraph(
        positions=graph.positions[node_kept],
        radii=graph.radii[node_kept],
        edges=new_id[graph.edges[edge_kept]],
        spacing=graph.spacing,
        info={
            **graph.info,
            "pruned_branches": pruned,
            "prune_min_length_over_radius": k,
        },
        params=graph.params,
    )
