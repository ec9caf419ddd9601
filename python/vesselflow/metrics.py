"""Scores of a centreline graph against a ground truth: NetMets, DIADEM, radius error, topology.

These are the measures of the paper's section IV (Damseh et al., "Laplacian Flow Dynamics on
Geometric Graphs for Anatomical Modeling of Cerebrovascular Networks", Tables I and II):

- :func:`netmets`: geometric and connectivity false-negative / false-positive rates of
  Mayerich et al., "NetMets: software for quantifying and visualizing errors in biological
  network segmentation", BMC Bioinformatics 13 (Suppl 8): S7, 2012; and the variant the
  paper's authors computed in their VascGraph code (``mode="vascgraph"``).
- :func:`diadem`: the DIADEM metric of Gillette, Brown and Ascoli, "The DIADEM metric: comparing
  multiple reconstructions of the same neuron", Neuroinformatics 9: 233-245, 2011.
- :func:`radius_error`: mean absolute percentage error of radii at matched points.
- :func:`topology`: components and loops of the graph against those of the mask.
- :func:`radius_bands`, :func:`junction_recall`, :func:`mask_fidelity`: radius bias per band
  of radius, true junctions found, and where the graph leaves the mask.
- :func:`join_close_junctions`: a graph with its junctions closer than a tolerance joined,
  to score connectivity at the resolution that tolerance gives.

All positions, ``sigma``, ``max_dist`` and thresholds are in the graphs' physical units.
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage
from scipy.cluster.hierarchy import DisjointSet
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree

from vesselflow.analysis import trace_branches
from vesselflow.graph import VesselGraph

__all__ = [
    "RADIUS_BANDS",
    "diadem",
    "join_close_junctions",
    "junction_recall",
    "mask_fidelity",
    "netmets",
    "radius_bands",
    "radius_error",
    "topology",
]

_SATURATION = 9.0
"""Beyond ``_SATURATION * sigma`` the NetMets score ``1 - exp(-d^2 / 2 sigma^2)`` is 1 to double
precision (exp(-40.5) < 3e-18), so distances known to exceed it are not refined further."""


# ----------------------------------------------------------------------------------------------
# input checks


def _check_graph(graph: object, name: str) -> VesselGraph:
    if not isinstance(graph, VesselGraph):
        raise TypeError(f"{name} must be a vesselflow.VesselGraph, got {type(graph).__name__}")
    if not np.all(np.isfinite(graph.positions)):
        raise ValueError(f"{name} has non-finite node positions")
    return graph


def _check_positive(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a number, got {type(value).__name__}")
    out = float(value)
    if not (math.isfinite(out) and out > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return out


def _check_nonnegative(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a number, got {type(value).__name__}")
    out = float(value)
    if not (math.isfinite(out) and out >= 0):
        raise ValueError(f"{name} must be a non-negative finite number, got {value!r}")
    return out


# ----------------------------------------------------------------------------------------------
# exact nearest point on a set of segments


class _SegmentIndex:
    """Exact point-to-segment nearest queries over segments ``a[s] -> b[s]``.

    Every segment is sampled at the midpoints of ``ceil(length / h)`` equal pieces, so each point
    of a segment lies within ``h / 2`` of one of its samples, and a KD-tree holds the samples. For
    a query ``q`` whose nearest segment is at distance ``d``, that segment has a sample within
    ``d + h / 2``; so once some segment at distance ``d_best`` is known, every segment with a
    sample within ``d_best + h / 2`` is a candidate and no other segment can be nearer. The
    ``k`` nearest samples are tried first (vectorised); queries whose ``k``-th sample lies inside
    that radius are redone with a ball query. The answer is exact, not an approximation.
    """

    def __init__(
        self, a: NDArray[np.float64], b: NDArray[np.float64], spacing: float = math.inf
    ) -> None:
        self.a = a
        self.ab = b - a
        self.len2 = np.einsum("ij,ij->i", self.ab, self.ab)
        lengths = np.sqrt(self.len2)
        positive = lengths[lengths > 0]
        # sample spacing: the median segment length, at most ``spacing`` (a finer spacing makes
        # the candidate radius tighter), but no more than ~4 samples per segment on average
        h = min(float(np.median(positive)), spacing) if positive.size else 1.0
        self.h = max(h, float(positive.sum()) / (4 * len(a))) if positive.size else 1.0
        pieces = np.maximum(1, np.ceil(lengths / self.h)).astype(np.int64)
        self.sample_segment = np.repeat(np.arange(len(a)), pieces)
        first = np.cumsum(pieces) - pieces
        within = np.arange(int(pieces.sum())) - np.repeat(first, pieces)
        t = (within + 0.5) / np.repeat(pieces, pieces)
        samples = a[self.sample_segment] + t[:, None] * self.ab[self.sample_segment]
        self.tree = cKDTree(samples)

    def _exact(
        self, q: NDArray[np.float64], seg: NDArray[np.int64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Distance from ``q[..., :]`` to segments ``seg[...]`` and the segment parameter."""
        a = self.a[seg]
        ab = self.ab[seg]
        len2 = self.len2[seg]
        rel = q - a
        dot = (rel * ab).sum(axis=-1)
        t = np.divide(dot, len2, out=np.zeros_like(dot), where=len2 > 0)
        np.clip(t, 0.0, 1.0, out=t)
        rel -= t[..., None] * ab
        return np.sqrt((rel * rel).sum(axis=-1)), t

    def nearest(
        self, q: NDArray[np.float64], cutoff: float = math.inf
    ) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
        """Distance, segment index and parameter ``t`` of the nearest segment point to each
        query. Queries provably farther than ``cutoff`` get an upper bound of their distance
        (still greater than ``cutoff``) instead of the exact value."""
        n = len(q)
        out_d = np.full(n, np.inf)
        out_s = np.zeros(n, dtype=np.int64)
        out_t = np.zeros(n)
        todo = np.arange(n)
        n_samples = int(self.tree.n)
        for k in (8, 32, 128):
            if todo.size == 0:
                break
            k = min(k, n_samples)
            sample_dist, sample_idx = self.tree.query(q[todo], k=k, workers=-1)
            sample_dist = np.asarray(sample_dist, dtype=np.float64).reshape(len(todo), k)
            seg = self.sample_segment[np.asarray(sample_idx, dtype=np.int64).reshape(len(todo), k)]
            dist, t = self._exact(q[todo][:, None, :], seg)
            best = np.argmin(dist, axis=1)
            rows = np.arange(len(todo))
            out_d[todo] = dist[rows, best]
            out_s[todo] = seg[rows, best]
            out_t[todo] = t[rows, best]
            # sure: every sample within d_best + h/2 was seen, or provably beyond the cutoff
            unsure = (sample_dist[:, -1] <= out_d[todo] + self.h / 2) & (k < n_samples)
            unsure &= sample_dist[:, 0] - self.h / 2 <= cutoff
            todo = todo[unsure]
        for i in todo.tolist():
            near = self.tree.query_ball_point(q[i], out_d[i] + self.h / 2)
            cand = np.unique(self.sample_segment[np.asarray(near, dtype=np.int64)])
            d, tt = self._exact(q[i][None, :], cand)
            j = int(np.argmin(d))
            out_d[i], out_s[i], out_t[i] = d[j], cand[j], tt[j]
        return out_d, out_s, out_t


def _edge_segments(
    graph: VesselGraph, with_isolated: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Segment end points of every edge (and, if asked, a zero-length segment for every node
    without edges); the third array gives the node ids ``(S, 2)`` of each segment's ends."""
    ends = graph.edges
    if with_isolated:
        isolated = np.flatnonzero(graph.degrees() == 0)
        ends = np.concatenate([ends, np.stack([isolated, isolated], axis=1)])
    return graph.positions[ends[:, 0]], graph.positions[ends[:, 1]], ends


# ----------------------------------------------------------------------------------------------
# NetMets


def _length_samples(
    graph: VesselGraph, step: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Midpoint-rule quadrature of the graph's edges: points and their length weights."""
    a, b, _ = _edge_segments(graph)
    lengths = np.linalg.norm(b - a, axis=1)
    keep = lengths > 0
    a, b, lengths = a[keep], b[keep], lengths[keep]
    pieces = np.maximum(1, np.ceil(lengths / step)).astype(np.int64)
    owner = np.repeat(np.arange(len(a)), pieces)
    first = np.cumsum(pieces) - pieces
    within = np.arange(int(pieces.sum())) - np.repeat(first, pieces)
    t = (within + 0.5) / pieces[owner]
    points = a[owner] + t[:, None] * (b - a)[owner]
    return points, (lengths / pieces)[owner]


def _geometry_rate(source: VesselGraph, target: VesselGraph, sigma: float, step: float) -> float:
    """Length-weighted mean over ``source`` of ``1 - exp(-d^2 / 2 sigma^2)``, with ``d`` the
    exact distance to the nearest segment of ``target``."""
    points, weights = _length_samples(source, step)
    total = float(weights.sum())
    if total <= 0:
        raise ValueError("a network has no edges of positive length; its NetMets rate is undefined")
    a, b, _ = _edge_segments(target)
    if len(a) == 0:
        return 1.0
    cutoff = _SATURATION * sigma
    d, _, _ = _SegmentIndex(a, b, sigma / 2).nearest(points, cutoff=cutoff)
    score = -np.expm1(-(d**2) / (2 * sigma**2))
    return float(np.dot(weights, score) / total)


def _core_branches(graph: VesselGraph) -> list[tuple[int, int]]:
    """End nodes of every branch (the core graph's edges; loops appear as ``(u, u)``)."""
    return [(br.nodes[0], br.nodes[-1]) for br in trace_branches(graph)]


def _match_core_nodes(
    pos_t: NDArray[np.float64], pos_g: NDArray[np.float64], sigma: float
) -> tuple[dict[int, int], dict[int, int]]:
    """One-to-one greedy matching of two point sets: all pairs at distance <= sigma are taken
    in increasing distance (ties: truth index, then graph index), each point used once."""
    if len(pos_t) == 0 or len(pos_g) == 0:
        return {}, {}
    pairs = cKDTree(pos_t).sparse_distance_matrix(cKDTree(pos_g), sigma, output_type="ndarray")
    order = np.lexsort((pairs["j"], pairs["i"], pairs["v"]))
    label_t: dict[int, int] = {}
    label_g: dict[int, int] = {}
    for i, j in zip(pairs["i"][order].tolist(), pairs["j"][order].tolist()):
        if i not in label_t and j not in label_g:
            label_t[i] = label_g[j] = len(label_t)
    return label_t, label_g


def _reduced_core_edges(branches: list[tuple[int, int]], label: dict[int, int]) -> Counter[Any]:
    """Core edges between matched core nodes, unmatched core nodes made transparent.

    A branch between two matched nodes gives the edge of their labels. Unmatched core nodes
    joined by branches form clusters; a cluster reached by branches from matched nodes with
    labels ``s_0 <= s_1 <= ... <= s_k`` gives the ``k`` edges ``(s_0, s_i)`` (a star on the
    smallest label), so a path through unmatched junctions still connects its matched ends.
    """
    unmatched = DisjointSet(n for uv in branches for n in uv if n not in label)
    edges: Counter[Any] = Counter()
    attach: list[tuple[int, int]] = []
    for u, v in branches:
        lu, lv = label.get(u), label.get(v)
        if lu is not None and lv is not None:
            edges[(min(lu, lv), max(lu, lv))] += 1
        elif lu is not None:
            attach.append((v, lu))
        elif lv is not None:
            attach.append((u, lv))
        else:
            unmatched.merge(u, v)
    clusters: dict[int, list[int]] = {}
    for node, lab in attach:
        clusters.setdefault(unmatched[node], []).append(lab)
    for labs in clusters.values():
        labs.sort()
        for other in labs[1:]:
            edges[(labs[0], other)] += 1
    return edges


def _netmets_proper(
    truth: VesselGraph, graph: VesselGraph, sigma: float, step: float
) -> dict[str, float]:
    gfnr = _geometry_rate(truth, graph, sigma, step)
    gfpr = _geometry_rate(graph, truth, sigma, step)
    br_t, br_g = _core_branches(truth), _core_branches(graph)
    if not br_t or not br_g:
        raise ValueError("a network has no edges; its connectivity rates are undefined")
    core_t = sorted({n for br in br_t for n in br})
    core_g = sorted({n for br in br_g for n in br})
    lab_t, lab_g = _match_core_nodes(truth.positions[core_t], graph.positions[core_g], sigma)
    label_t = {core_t[i]: lab for i, lab in lab_t.items()}
    label_g = {core_g[j]: lab for j, lab in lab_g.items()}
    red_t = _reduced_core_edges(br_t, label_t)
    red_g = _reduced_core_edges(br_g, label_g)
    true_pos = sum(min(count, red_g[key]) for key, count in red_t.items())
    return {
        "gfnr": gfnr,
        "gfpr": gfpr,
        "cfnr": (len(br_t) - true_pos) / len(br_t),
        "cfpr": (len(br_g) - true_pos) / len(br_g),
    }


def _trim_largest(d: NDArray[np.float64], portion: float = 0.99) -> NDArray[np.float64]:
    """VascGraph's ``decideThresh``: 1000-bin histogram of ``d`` (numpy's default range); the
    threshold is the left edge of the first bin where the cumulative fraction exceeds
    ``portion``; distances at or above it are set to 0 (not dropped)."""
    counts, edges = np.histogram(d, bins=1000)
    idx = int(np.argmax(np.cumsum(counts) > portion * len(d)))
    return np.where(d < edges[idx], d, 0.0)


def _netmets_vascgraph(truth: VesselGraph, graph: VesselGraph, sigma: float) -> dict[str, float]:
    core_t = np.flatnonzero(truth.degrees() != 2)
    core_g = np.flatnonzero(graph.degrees() != 2)
    if core_t.size == 0 or core_g.size == 0:
        raise ValueError("a network has no nodes of degree != 2 (junctions or endpoints)")
    pos_t, pos_g = truth.positions[core_t], graph.positions[core_g]
    d1, nn1 = cKDTree(pos_g).query(pos_t)
    d2, nn2 = cKDTree(pos_t).query(pos_g)
    d1, d2 = np.asarray(d1, dtype=np.float64), np.asarray(d2, dtype=np.float64)
    gfnr = float(np.mean(-np.expm1(-(_trim_largest(d1) ** 2) / (2 * sigma**2))))
    gfpr = float(np.mean(-np.expm1(-(_trim_largest(d2) ** 2) / (2 * sigma**2))))
    # matched: mutual nearest core nodes closer than sigma
    mutual = (nn2[nn1] == np.arange(len(core_t))) & (d1 < sigma)
    partner_t = {int(core_t[i]): int(core_g[nn1[i]]) for i in np.flatnonzero(mutual)}
    pairs_t = {tuple(sorted(br)) for br in _core_branches(truth)}
    pairs_g = {tuple(sorted(br)) for br in _core_branches(graph)}
    if not pairs_t or not pairs_g:
        raise ValueError("a network has no edges; its connectivity rates are undefined")
    kept_t = sum(
        1
        for u, v in pairs_t
        if u in partner_t
        and v in partner_t
        and tuple(sorted((partner_t[u], partner_t[v]))) in pairs_g
    )
    partner_g = {g: t for t, g in partner_t.items()}
    true_pos = sum(
        1
        for u, v in pairs_g
        if u in partner_g
        and v in partner_g
        and tuple(sorted((partner_g[u], partner_g[v]))) in pairs_t
    )
    false_neg = len(pairs_t) - kept_t
    false_pos = len(pairs_g) - true_pos
    return {
        "gfnr": gfnr,
        "gfpr": gfpr,
        "cfnr": false_neg / (false_neg + true_pos) if false_neg + true_pos else 0.0,
        "cfpr": false_pos / (false_pos + true_pos) if false_pos + true_pos else 0.0,
    }


def netmets(
    truth: VesselGraph,
    graph: VesselGraph,
    sigma: float,
    *,
    mode: str = "netmets",
    step: float | None = None,
) -> dict[str, float]:
    """NetMets geometry and connectivity error rates of ``graph`` against ``truth``.

    Parameters
    ----------
    truth, graph : VesselGraph
        Ground-truth and extracted centreline networks (positions in physical units).
    sigma : float
        Tolerance (the paper's tau), physical units.
    mode : {"netmets", "vascgraph"}
        ``"netmets"``: NetMets proper (below). ``"vascgraph"``: the variant in the paper
        authors' VascGraph code (``VascGraph/GraphValidation/ValidateNetMets.py``).
    step : float, optional
        Quadrature step along the edges for the geometry integrals (``"netmets"`` only);
        default ``sigma / 4``.

    Returns
    -------
    dict
        ``gfnr``, ``gfpr``, ``cfnr``, ``cfpr``, each in [0, 1]; 0 is perfect.

    Notes
    -----
    **NetMets proper** (Mayerich et al. 2012; the ``rtsFiberNetwork`` code of NetMets):

    *Geometry.* ``GFNR = (1/L_t) * integral over the truth's edges of 1 - exp(-d(p)^2 /
    (2 sigma^2)) dl(p)`` where ``L_t`` is the truth's total edge length and ``d(p)`` the exact
    Euclidean distance from ``p`` to the nearest edge segment of ``graph``; ``GFPR`` is the same
    along ``graph`` against ``truth``. The integral is a midpoint rule: each edge is cut into
    ``ceil(length / step)`` equal pieces. Deviation: NetMets resamples both networks at spacing
    sigma and measures distances to the other network's sample points (ANN k-d tree) with a
    trapezoid rule; here distances are to segments, so they do not depend on how edges are
    subdivided.

    *Connectivity.* Each network is reduced to its core graph: core nodes are the nodes of
    degree != 2, core edges are the branches between them (a branch from a node back to itself
    is a loop; an isolated cycle is one loop at its smallest node id). Core nodes of the two
    networks are matched one to one: all pairs at distance <= sigma, taken greedily in
    increasing distance. As in NetMets (``BOOST_FindCoreGraph``), unmatched core nodes are
    transparent: a branch between matched nodes ``a, b`` is the core edge ``(a, b)``; unmatched
    core nodes connected by branches form a cluster, and a cluster reached from matched nodes
    ``s_0 <= ... <= s_k`` (ordered by match label) gives core edges ``(s_0, s_i)``. Core edges of
    the two networks are paired one to one by their (unordered) end labels; with ``TP`` pairs,
    ``CFNR = (B_t - TP) / B_t`` and ``CFPR = (B_g - TP) / B_g`` where ``B`` counts branches.
    Deviations: NetMets labels each truth node's nearest graph node within sigma (not one to
    one) and builds the transparent edges with a breadth-first search whose result depends on
    the search order; the star rule here is a canonical, order-free version. NetMets' released
    code also swaps the two denominators (``cFNR`` divided by the test network's fibre count);
    here each rate is divided by its own network's branch count, as the paper defines them.
    A false spur on a truth branch therefore raises only ``cfpr``, and a missing branch only
    ``cfnr``.

    **VascGraph variant** (``mode="vascgraph"``), as read in ``ValidateNetMets.py``:

    *Geometry.* Only nodes of degree != 2 are used. ``d1`` = distance from each such truth node
    to the nearest such graph node, ``d2`` the reverse. The largest distances are trimmed by
    ``decideThresh`` (1000-bin histogram, threshold = left edge of the first bin where the
    cumulative fraction exceeds 0.99) and, as in that code, trimmed distances are set to 0
    rather than dropped. ``GFNR = mean(1 - exp(-d1^2 / 2 sigma^2))``, ``GFPR`` likewise with
    ``d2``. No integration along the edges.

    *Connectivity.* Branches are the distinct node pairs joined by a branch of the reduced
    graph. Core nodes are matched when they are mutual nearest neighbours closer than sigma. A
    branch is kept when both its ends are matched and their partners are joined by a branch in
    the other network; ``TP`` = kept graph branches, ``FN`` = truth branches not kept, ``FP`` =
    graph branches not kept; ``CFNR = FN / (FN + TP)``, ``CFPR = FP / (FP + TP)``. Verified in
    the code: the distance sets, the trimming, the score, the mutual matching and the two rate
    formulas. Simplified: VascGraph deletes the interiors of rejected branches from a copy of
    the graph and re-counts the branches of what is left (which can split or merge branches);
    here the kept branches are counted directly. Unlike NetMets proper, this variant counts a
    graph branch that bridges a missed junction as a false positive.

    Examples
    --------
    >>> from vesselflow import VesselGraph, metrics
    >>> truth = VesselGraph([[0, 0, 0], [0, 0, 10], [0, 0, 20]], [2, 2, 2], [[0, 1], [1, 2]])
    >>> graph = VesselGraph([[0, 0.5, 0], [0, 0.5, 20]], [1.8, 2.2], [[0, 1]])  # 0.5 off
    >>> {k: round(v, 3) for k, v in metrics.netmets(truth, graph, sigma=3.0).items()}
    {'gfnr': 0.014, 'gfpr': 0.014, 'cfnr': 0.0, 'cfpr': 0.0}
    """
    truth = _check_graph(truth, "truth")
    graph = _check_graph(graph, "graph")
    sigma = _check_positive(sigma, "sigma")
    if mode == "netmets":
        step = sigma / 4 if step is None else _check_positive(step, "step")
        return _netmets_proper(truth, graph, sigma, step)
    if mode == "vascgraph":
        return _netmets_vascgraph(truth, graph, sigma)
    raise ValueError(f"mode must be 'netmets' or 'vascgraph', got {mode!r}")


# ----------------------------------------------------------------------------------------------
# DIADEM


class _KeyTree:
    """A graph's spanning tree from ``root`` reduced to its key nodes (root, bifurcations,
    terminations), with cumulative path lengths from the root (3-D, xy-plane, z) and an Euler
    tour for ancestor tests."""

    def __init__(self, graph: VesselGraph, root: int, z_axis: int | None) -> None:
        pos = graph.positions
        n = graph.n_nodes
        e = graph.edges[graph.edges[:, 0] != graph.edges[:, 1]]
        e = np.unique(np.sort(e, axis=1), axis=0)
        length = np.linalg.norm(pos[e[:, 0]] - pos[e[:, 1]], axis=1)
        # csgraph drops zero weights: lift them slightly so that coincident nodes stay linked
        tiny = 1e-12 * max(float(length.max(initial=0.0)), 1.0)
        weights = coo_matrix((length + tiny, (e[:, 0], e[:, 1])), shape=(n, n))
        mst = minimum_spanning_tree(weights)
        order, pred = breadth_first_order(mst, root, directed=False, return_predecessors=True)
        xy_axes = [a for a in range(3) if a != z_axis]
        children = np.zeros(n, dtype=np.int64)
        children_of_parent = pred[order[1:]]
        np.add.at(children, children_of_parent, 1)
        step = np.zeros((n, 3))
        delta = pos[order[1:]] - pos[children_of_parent]
        step[order[1:], 0] = np.linalg.norm(delta, axis=1)
        step[order[1:], 1] = np.linalg.norm(delta[:, xy_axes], axis=1)
        if z_axis is not None:
            step[order[1:], 2] = np.abs(delta[:, z_axis])
        cum = np.zeros((n, 3))
        is_key = np.zeros(n, dtype=bool)
        is_key[order] = children[order] != 1
        is_key[root] = True
        key_parent = np.full(n, -1, dtype=np.int64)
        for node in order[1:].tolist():
            p = int(pred[node])
            cum[node] = cum[p] + step[node]
            key_parent[node] = p if is_key[p] else key_parent[p]
        self.keys = [int(k) for k in order if is_key[k]]  # breadth-first, root first
        self.root = root
        self.pos = pos
        self.cum = cum
        self.parent = {k: int(key_parent[k]) for k in self.keys[1:]}
        self.kids: dict[int, list[int]] = {k: [] for k in self.keys}
        for k, p in self.parent.items():
            self.kids[p].append(k)
        self.tips = {k for k in self.keys[1:] if not self.kids[k]}
        # Euler tour on the key tree
        self.tin: dict[int, int] = {}
        self.tout: dict[int, int] = {}
        clock = 0
        stack: list[tuple[int, bool]] = [(root, False)]
        while stack:
            node, done = stack.pop()
            if done:
                self.tout[node] = clock
                continue
            self.tin[node] = clock
            clock += 1
            stack.append((node, True))
            stack.extend((c, False) for c in reversed(self.kids[node]))

    def is_ancestor(self, a: int, b: int) -> bool:
        """True when ``a`` is a proper ancestor of ``b`` in the key tree."""
        return a != b and self.tin[a] < self.tin[b] and self.tout[b] <= self.tout[a]

    def weights(self, scheme: int, spur: float) -> dict[int, float]:
        """Weight of every non-root key node; ``degree`` = number of terminations below."""
        degree: dict[int, int] = {}
        for k in reversed(self.keys):
            degree[k] = sum(degree[c] for c in self.kids[k]) if self.kids[k] else 1
        out: dict[int, float] = {}
        for k in self.keys[1:]:
            kids = self.kids[k]
            if scheme == 1:
                w = float(degree[k])
            elif scheme == 2:
                w = 1.0
            elif scheme == 3:
                w = math.sqrt(degree[k])
            else:
                w = len(kids) / sum(1.0 / degree[c] for c in kids) if kids else 1.0
            if k in self.tips and self.cum[k, 0] - self.cum[self.parent[k], 0] < spur:
                w = 0.0
            out[k] = w
        return out


def diadem(
    truth_tree: VesselGraph,
    graph_tree: VesselGraph,
    *,
    root: int | None = None,
    xy_threshold: float = 1.0,
    z_threshold: float = 1.0,
    xy_z_ratio: float = 1.0,
    xy_path_thresh: float = 0.08,
    z_path_thresh: float = 0.20,
    terminal_threshold: float = 0.0,
    terminal_path_threshold: float = 1.0,
    remove_spurs: float = 0.0,
    weight_scheme: int = 1,
    z_path: bool = True,
    excess_nodes: bool = True,
    z_axis: int | None = 0,
) -> float:
    """DIADEM score in [0, 1] of ``graph_tree`` against the gold standard ``truth_tree``.

    Gillette, Brown, Ascoli, "The DIADEM metric: comparing multiple reconstructions of the same
    neuron", Neuroinformatics 9 (2011) 233-245; keywords and defaults are those of the official
    ``DiademMetric.jar`` (its readme): ``-x 1``, ``-Z 1``, ``-R 1``, ``--xy-path-thresh 0.08``,
    ``--z-path-thresh 0.20``, ``-t 0``, ``-p 1.0``, ``-r 0``, ``-w 1``, ``--z-path true``,
    ``--excess-nodes true``. The jar's defaults are meant for pixel units; set the thresholds
    for your physical units.

    Definition. Both networks are made trees: the minimum spanning tree by edge length of the
    component holding the root (the paper notes DIADEM is for trees; its authors likewise scored
    minimum spanning trees of their graphs). The truth root is ``root`` or, by default, the
    degree-1 truth node of largest radius; the graph root is the graph node nearest to it. Each
    tree is reduced to key nodes: the root, bifurcations (>= 2 children) and terminations. A
    key node's weight is its degree, the number of terminations in its subtree
    (``weight_scheme`` 1; 2 = uniform, 3 = square root of degree, 4 = harmonic mean of its
    children's degrees); terminations on a branch shorter than ``remove_spurs`` weigh 0 but can
    still be matched. The roots are matched to each other and not scored.

    Gold key nodes are visited breadth first. For gold node ``g`` let ``a`` be its nearest
    matched gold ancestor and ``m(a)`` the test node matched to it. A test key node ``t`` is a
    candidate when it is unmatched, is a descendant of ``m(a)``, lies within the Euclidean
    thresholds of ``g`` (xy distance <= ``xy_threshold`` and ``|dz| <= z_threshold *
    xy_z_ratio``; z is array axis ``z_axis``), and its path from ``m(a)`` agrees with the gold
    path from ``a`` to ``g``: ``|P_xy(t) - P_xy(g)| <= xy_path_thresh * P(g)`` and ``|P_z(t) -
    P_z(g)| <= z_path_thresh * P(g)``, where ``P`` is the 3-D path length, ``P_xy`` its
    projection on the xy plane and ``P_z`` the summed ``|dz|``. The nearest candidate is the
    match. Because ancestors are the nearest *matched* ones, a gold bifurcation the test misses
    (a continuation) is scored as missed while the nodes beyond it can still match. With
    ``terminal_threshold > 0``, a gold termination with no candidate may also match a test
    termination within ``terminal_threshold`` times the Euclidean thresholds whose path is at
    least ``terminal_path_threshold`` times the gold one (a simplified form of the jar's
    terminal rule). With ``z_path=False`` z is ignored in distances and paths. With
    ``z_axis=None`` there is no z: distances and path lengths are 3-D and are held to the xy
    thresholds alone (for isotropic volumes, where no axis is the microscope's coarse one).

    ``score = sum of weights of matched gold nodes / (sum of gold weights + sum of weights of
    unmatched test key nodes)``, the last term only with ``excess_nodes``.

    Not implemented from the jar: the "distant match" report, micron conversion and the
    data-set presets (``-D``).

    Returns
    -------
    float
        The score in [0, 1]; 1 is perfect.

    Examples
    --------
    >>> from vesselflow import VesselGraph, metrics
    >>> truth = VesselGraph([[0, 0, 0], [0, 0, 10], [0, 0, 20]], [2, 2, 2], [[0, 1], [1, 2]])
    >>> graph = VesselGraph([[0, 0.5, 0], [0, 0.5, 20]], [1.8, 2.2], [[0, 1]])  # 0.5 off
    >>> metrics.diadem(truth, graph)
    1.0
    """
    truth = _check_graph(truth_tree, "truth_tree")
    graph = _check_graph(graph_tree, "graph_tree")
    xy_thr = _check_positive(xy_threshold, "xy_threshold")
    z_thr = _check_positive(z_threshold, "z_threshold") * _check_positive(xy_z_ratio, "xy_z_ratio")
    xy_path = _check_nonnegative(xy_path_thresh, "xy_path_thresh")
    z_path_t = _check_nonnegative(z_path_thresh, "z_path_thresh")
    term_thr = _check_nonnegative(terminal_threshold, "terminal_threshold")
    term_path = _check_nonnegative(terminal_path_threshold, "terminal_path_threshold")
    spur = _check_nonnegative(remove_spurs, "remove_spurs")
    if weight_scheme not in (1, 2, 3, 4):
        raise ValueError(f"weight_scheme must be 1, 2, 3 or 4, got {weight_scheme!r}")
    if z_axis not in (0, 1, 2, None):
        raise ValueError(f"z_axis must be 0, 1, 2 or None, got {z_axis!r}")
    if truth.n_nodes == 0 or graph.n_nodes == 0:
        raise ValueError("both trees need at least one node")
    if root is None:
        ends = np.flatnonzero(truth.degrees() == 1)
        if ends.size == 0:
            raise ValueError("truth_tree has no degree-1 node to root it; pass root=")
        root = int(ends[np.argmax(truth.radii[ends])])
    elif isinstance(root, bool) or not isinstance(root, (int, np.integer)):
        raise TypeError(f"root must be a node index, got {type(root).__name__}")
    elif not 0 <= int(root) < truth.n_nodes:
        raise ValueError(f"root {root} is not a node of truth_tree (0..{truth.n_nodes - 1})")
    root = int(root)
    groot = int(np.argmin(np.linalg.norm(graph.positions - truth.positions[root], axis=1)))
    gold = _KeyTree(truth, root, z_axis)
    test = _KeyTree(graph, groot, z_axis)
    w_gold = gold.weights(weight_scheme, spur)
    w_test = test.weights(weight_scheme, spur)
    total = sum(w_gold.values())
    if total <= 0:
        raise ValueError("truth_tree has no scored key nodes (bifurcations or terminations)")

    xy_axes = [a for a in range(3) if a != z_axis]
    test_keys = np.array(test.keys[1:], dtype=np.int64)
    test_pos = test.pos[test_keys] if test_keys.size else np.zeros((0, 3))
    use_z = bool(z_path) and z_axis is not None
    match: dict[int, int] = {root: groot}
    matched_test = {groot}
    nearest_matched: dict[int, int] = {root: root}  # gold key -> nearest matched ancestor-or-self

    for g in gold.keys[1:]:
        a = nearest_matched[gold.parent[g]]
        ma = match[a]
        path_g = gold.cum[g] - gold.cum[a]
        delta = test_pos - gold.pos[g]
        dxy = np.linalg.norm(delta[:, xy_axes], axis=1)
        dz = np.abs(delta[:, z_axis]) if use_z else np.zeros(len(delta))
        best: tuple[float, int] | None = None
        for scale, terminal in ((1.0, False), (term_thr, True)):
            if terminal and (best is not None or scale <= 0 or g not in gold.tips):
                break
            near = np.flatnonzero((dxy <= scale * xy_thr) & (dz <= scale * z_thr))
            for i in near.tolist():
                t = int(test_keys[i])
                if t in matched_test or not test.is_ancestor(ma, t):
                    continue
                path_t = test.cum[t] - test.cum[ma]
                if terminal:
                    ok = t in test.tips and path_t[0] >= term_path * path_g[0]
                else:
                    ok = abs(path_t[1] - path_g[1]) <= xy_path * path_g[0] and (
                        not use_z or abs(path_t[2] - path_g[2]) <= z_path_t * path_g[0]
                    )
                if ok:
                    dist = float(np.hypot(dxy[i], dz[i]))
                    if best is None or dist < best[0]:
                        best = (dist, t)
        if best is not None:
            match[g] = best[1]
            matched_test.add(best[1])
            nearest_matched[g] = g
        else:
            nearest_matched[g] = a

    score = sum(w for g, w in w_gold.items() if g in match)
    excess = sum(w for t, w in w_test.items() if t not in matched_test) if excess_nodes else 0.0
    return float(score / (total + excess))


# ----------------------------------------------------------------------------------------------
# radius error


def _matched_radii(
    truth: VesselGraph, graph: VesselGraph, max_dist: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Truth radius (interpolated on the nearest truth segment), graph radius and matching
    distance of every graph node within ``max_dist`` of the truth centreline."""
    a, b, ends = _edge_segments(truth, with_isolated=True)
    if len(a) == 0:
        raise ValueError("truth has no nodes")
    d, seg, t = _SegmentIndex(a, b, max_dist / 2).nearest(graph.positions, cutoff=max_dist)
    ok = d <= max_dist
    r_t = (1 - t[ok]) * truth.radii[ends[seg[ok], 0]] + t[ok] * truth.radii[ends[seg[ok], 1]]
    return r_t, graph.radii[ok], d[ok]


def radius_error(
    truth: VesselGraph, graph: VesselGraph, max_dist: float, *, normalised: bool = False
) -> dict[str, float]:
    """Mean absolute percentage error of the graph's radii at matched points of the truth.

    Each graph node is matched to the nearest point of the truth centreline (exact
    point-to-segment distance over the truth's edges; truth nodes without edges count as
    points) if that point is within ``max_dist``; the truth radius there is interpolated
    linearly between the segment's end radii. With ``r_g`` the graph radii and ``r_t`` the
    truth radii at the matches, ``mape = 100 * mean(|r_g - r_t| / r_t)``.

    ``normalised=True`` is the paper authors' variant (VascGraph ``ValidateRadius.GetScores``):
    both radius vectors are min-max normalised, ``n = (r - min r) / (max r - min r)``, then,
    because ``min n = 0 < 1``, both are shifted by +1 before the percentage error:
    ``mape = 100 * mean(|n_g - n_t| / (1 + n_t))``. It is blind to any global scale (and
    offset) of the radii: radii all 10 % too large score 0. VascGraph also matches node to
    node (not to segments) and by default first replaces each branch's radii by their mean;
    neither is reproduced here.

    Returns
    -------
    dict
        ``mape`` (percent; NaN when nothing matched), ``n_matched``, ``n_unmatched`` (graph
        nodes farther than ``max_dist``), ``mean_abs_error`` (mean ``|r_g - r_t|``, physical
        units, of the raw radii) and ``mean_dist`` (mean matching distance).

    Examples
    --------
    >>> from vesselflow import VesselGraph, metrics
    >>> truth = VesselGraph([[0, 0, 0], [0, 0, 10], [0, 0, 20]], [2, 2, 2], [[0, 1], [1, 2]])
    >>> graph = VesselGraph([[0, 0.5, 0], [0, 0.5, 20]], [1.8, 2.2], [[0, 1]])  # 0.5 off
    >>> error = metrics.radius_error(truth, graph, max_dist=3.0)
    >>> round(error["mape"], 6), error["n_matched"]  # radii 10 % off at both nodes
    (10.0, 2)
    """
    truth = _check_graph(truth, "truth")
    graph = _check_graph(graph, "graph")
    max_dist = _check_positive(max_dist, "max_dist")
    r_t, r_g, dist = _matched_radii(truth, graph, max_dist)
    n = len(r_t)
    out: dict[str, float] = {
        "mape": math.nan,
        "n_matched": n,
        "n_unmatched": int(graph.n_nodes - n),
        "mean_abs_error": float(np.mean(np.abs(r_g - r_t))) if n else math.nan,
        "mean_dist": float(np.mean(dist)) if n else math.nan,
    }
    if n == 0:
        return out
    if normalised:
        if np.ptp(r_t) == 0 or np.ptp(r_g) == 0:
            raise ValueError("normalised radius error needs non-constant radii in both graphs")
        n_t = (r_t - r_t.min()) / np.ptp(r_t)
        n_g = (r_g - r_g.min()) / np.ptp(r_g)
        out["mape"] = float(100 * np.mean(np.abs(n_g - n_t) / (1 + n_t)))
    else:
        if np.any(r_t <= 0):
            raise ValueError("truth radii at matched points must be positive for a MAPE")
        out["mape"] = float(100 * np.mean(np.abs(r_g - r_t) / r_t))
    return out


# ----------------------------------------------------------------------------------------------
# topology


def _euler_26(mask: NDArray[np.bool_]) -> int:
    """Euler characteristic of the union of the closed unit cubes of the foreground voxels
    (the cubical complex whose connectivity is 26-connectivity): ``V - E + F - C``, counting
    every lattice vertex, edge and face that belongs to at least one foreground cube."""
    p = np.pad(mask, 1)

    def any_window(arr: NDArray[np.bool_], axes: tuple[int, ...]) -> int:
        # cells present = any foreground voxel among the 2 neighbours along each listed axis
        out = arr
        for ax in axes:
            lo = [slice(None)] * 3
            hi = [slice(None)] * 3
            lo[ax] = slice(None, -1)
            hi[ax] = slice(1, None)
            out = out[tuple(lo)] | out[tuple(hi)]
        return int(out.sum())

    vertices = any_window(p, (0, 1, 2))
    edges = sum(any_window(p, tuple(a for a in range(3) if a != ax)) for ax in range(3))
    faces = sum(any_window(p, (ax,)) for ax in range(3))
    cubes = int(mask.sum())
    return vertices - edges + faces - cubes


def topology(
    mask: ArrayLike, graph: VesselGraph, spacing: ArrayLike | None = None
) -> dict[str, Any]:
    """Connected components and loops of ``graph`` against those of the binary ``mask``.

    - ``mask_components``: 26-connected foreground components (``scipy.ndimage.label`` with a
      3x3x3 structure).
    - ``graph_components``: connected components of the graph (a node without edges is one).
    - ``mask_loops``: first Betti number of the foreground,
      ``b1 = b0 - chi + b2``, with ``chi`` the Euler characteristic of the union of the closed
      foreground voxel cubes (the complex matching 26-connectivity; vertices - edges + faces -
      cubes) and ``b2`` the enclosed cavities: 6-connected background components that do not
      touch the array border.
    - ``graph_cycles``: cycle rank ``E - N + C`` (self-loops and repeated edges count).
    - also ``components_equal``, ``loops_equal``, ``mask_euler`` and ``mask_cavities``.

    ``spacing`` (default ``graph.spacing``) is used only to check that the graph's nodes lie
    within the mask's physical extent (voxel (i, j, k) centred at ``(i, j, k) * spacing``, one
    voxel of slack); counts do not depend on it.

    Returns
    -------
    dict
        The counts above; ``components_equal`` and ``loops_equal`` are bool, the rest int.

    Examples
    --------
    >>> import numpy as np
    >>> from vesselflow import VesselGraph, metrics
    >>> mask = np.zeros((5, 5, 30), bool)
    >>> mask[1:4, 1:4, 2:28] = True  # a bar: one component, no loop
    >>> graph = VesselGraph([[2, 2, 3], [2, 2, 26]], [1, 1], [[0, 1]])
    >>> t = metrics.topology(mask, graph)
    >>> t["mask_components"], t["graph_components"], t["loops_equal"]
    (1, 1, True)
    """
    graph = _check_graph(graph, "graph")
    arr = np.asarray(mask)
    if arr.ndim != 3:
        raise ValueError(f"mask must be 3-D, got {arr.ndim} dimensions")
    if arr.dtype != bool:
        if not np.issubdtype(arr.dtype, np.number):
            raise TypeError(f"mask must be boolean or numeric, got dtype {arr.dtype}")
        arr = arr != 0
    sp = graph.spacing if spacing is None else np.asarray(spacing, dtype=np.float64).reshape(-1)
    if sp.shape != (3,) or not np.all(np.isfinite(sp)) or np.any(sp <= 0):
        raise ValueError(f"spacing must be 3 positive numbers, got {spacing!r}")
    if graph.n_nodes:
        lo = graph.positions.min(axis=0) / sp
        hi = graph.positions.max(axis=0) / sp
        if np.any(lo < -1) or np.any(hi > np.asarray(arr.shape)):
            raise ValueError("graph nodes lie outside the mask at this spacing")

    _, mask_components = ndimage.label(arr, structure=np.ones((3, 3, 3), dtype=bool))
    background, n_bg = ndimage.label(~arr)  # 6-connected
    border = np.concatenate(
        [
            background[[0, -1], :, :].ravel(),
            background[:, [0, -1], :].ravel(),
            background[:, :, [0, -1]].ravel(),
        ]
    )
    cavities = int(n_bg - np.count_nonzero(np.unique(border)))
    chi = _euler_26(arr)
    mask_loops = int(mask_components - chi + cavities)

    n = graph.n_nodes
    adj = coo_matrix((np.ones(graph.n_edges), (graph.edges[:, 0], graph.edges[:, 1])), (n, n))
    graph_components = int(connected_components(adj, directed=False)[0]) if n else 0
    graph_cycles = int(graph.n_edges - n + graph_components)
    return {
        "mask_components": int(mask_components),
        "graph_components": graph_components,
        "components_equal": int(mask_components) == graph_components,
        "mask_loops": mask_loops,
        "graph_cycles": graph_cycles,
        "loops_equal": mask_loops == graph_cycles,
        "mask_euler": chi,
        "mask_cavities": cavities,
    }


# ----------------------------------------------------------------------------------------------
# fidelity to the mask, junctions and radius bands

#: Radius bands of :func:`radius_bands`, in units of the finest voxel spacing: [low, high).
RADIUS_BANDS: tuple[tuple[float, float], ...] = ((1.0, 2.0), (2.0, 3.0), (3.0, 5.0), (5.0, 10.0))


def radius_bands(
    truth: VesselGraph,
    graph: VesselGraph,
    max_dist: float,
    bands: tuple[tuple[float, float], ...] = RADIUS_BANDS,
) -> dict[str, dict[str, float]]:
    """Radius bias and MAPE of the graph per band of truth radius.

    Graph nodes are matched to the truth centreline as in :func:`radius_error`; each match
    falls in the band ``[low, high)`` holding its truth radius divided by the finest spacing
    of ``truth`` (so bands are in voxels).

    Parameters
    ----------
    truth, graph : VesselGraph
    max_dist : float
        Matching tolerance, physical.
    bands : tuple of (low, high)
        Bands in voxels; by default :data:`RADIUS_BANDS` (1-2, 2-3, 3-5, 5-10).

    Returns
    -------
    dict
        Keyed ``"low-high"`` (e.g. ``"1-2"``), each a dict with ``n`` (matched nodes),
        ``bias`` (percent, ``100 * mean((r_g - r_t) / r_t)``: negative when radii are too
        small) and ``mape`` (percent); NaN where the band holds no match.

    Examples
    --------
    >>> from vesselflow import synth
    >>> _, truth = synth.cylinder((40, 24, 24), radius=2.5)
    >>> radius_bands(truth, truth, 2.0)["2-3"]["mape"]
    0.0
    """
    truth = _check_graph(truth, "truth")
    graph = _check_graph(graph, "graph")
    max_dist = _check_positive(max_dist, "max_dist")
    r_t, r_g, _ = _matched_radii(truth, graph, max_dist)
    if np.any(r_t <= 0):
        raise ValueError("truth radii at matched points must be positive")
    rel = (r_g - r_t) / r_t
    vox = r_t / float(np.min(truth.spacing))
    out: dict[str, dict[str, float]] = {}
    for low, high in bands:
        sel = (vox >= low) & (vox < high)
        n = int(sel.sum())
        out[f"{low:g}-{high:g}"] = {
            "n": n,
            "bias": float(100 * np.mean(rel[sel])) if n else math.nan,
            "mape": float(100 * np.mean(np.abs(rel[sel]))) if n else math.nan,
        }
    return out


def junction_recall(truth: VesselGraph, graph: VesselGraph, sigma: float) -> dict[str, float]:
    """How many true junctions (truth nodes of degree 3 or more) have a graph node within
    ``sigma``.

    Returns
    -------
    dict
        ``n_junctions``, ``found`` and ``recall`` (``found / n_junctions``; NaN without
        junctions).

    Examples
    --------
    >>> from vesselflow import synth
    >>> _, truth = synth.y_bifurcation()
    >>> junction_recall(truth, truth, 1.0)["recall"]
    1.0
    """
    truth = _check_graph(truth, "truth")
    graph = _check_graph(graph, "graph")
    sigma = _check_positive(sigma, "sigma")
    degree = np.bincount(truth.edges.ravel(), minlength=truth.n_nodes)
    junctions = truth.positions[degree >= 3]
    found = 0
    if len(junctions) and graph.n_nodes:
        d, _ = cKDTree(graph.positions).query(junctions, distance_upper_bound=sigma)
        found = int(np.count_nonzero(d <= sigma))
    n = len(junctions)
    return {"n_junctions": n, "found": found, "recall": found / n if n else math.nan}


def join_close_junctions(graph: VesselGraph, distance: float) -> VesselGraph:
    """``graph`` with every edge shorter than ``distance`` between two junctions (nodes of
    degree 3 or more) contracted: each cluster of junctions such edges join becomes one node
    at their mean position, with their mean radius.

    NetMets matches core nodes one to one within ``sigma``, so two true junctions closer
    than ``sigma`` (a vessel giving off two branches a voxel or two apart) need two graph
    junctions, each within ``sigma`` of its own, to be matched; a graph with one junction
    there loses the branches of the other. ``netmets(join_close_junctions(truth, sigma),
    graph, sigma)`` scores connectivity at the resolution ``sigma`` stands for. Junctions
    close in space but not joined by a short edge (crossing vessels) stay apart.

    Parameters
    ----------
    graph : VesselGraph
    distance : float
        Junctions joined by an edge shorter than this (physical units, > 0) become one.

    Returns
    -------
    VesselGraph
        The contracted graph: nodes renumbered in order (a cluster where its first member
        was), edges the contraction makes twice kept once, ``spacing`` and ``info`` as
        ``graph``'s.

    Raises
    ------
    ValueError, TypeError
        ``distance`` not a positive finite number.

    Examples
    --------
    >>> import numpy as np
    >>> from vesselflow import VesselGraph
    >>> positions = [[0, 0, 0], [5, 0, 0], [6, 0, 0], [11, 0, 0], [5, 4, 0], [6, -4, 0]]
    >>> g = VesselGraph(positions, np.ones(6), [[0, 1], [1, 2], [2, 3], [1, 4], [2, 5]])
    >>> joined = join_close_junctions(g, 2.0)
    >>> joined.n_nodes, joined.n_edges, joined.positions[1].tolist()
    (5, 4, [5.5, 0.0, 0.0])
    """
    graph = _check_graph(graph, "graph")
    distance = _check_positive(distance, "distance")
    n = graph.n_nodes
    edges = graph.edges
    degree = graph.degrees()
    length = np.linalg.norm(graph.positions[edges[:, 0]] - graph.positions[edges[:, 1]], axis=1)
    short = (degree[edges[:, 0]] >= 3) & (degree[edges[:, 1]] >= 3) & (length < distance)
    pairs = coo_matrix((np.ones(int(short.sum())), (edges[short, 0], edges[short, 1])), (n, n))
    k, label = connected_components(pairs, directed=False)
    count = np.bincount(label, minlength=k).astype(float)
    positions = np.zeros((k, 3))
    np.add.at(positions, label, graph.positions)
    radii = np.zeros(k)
    np.add.at(radii, label, graph.radii)
    kept = label[edges[~short]]
    kept = np.unique(np.sort(kept[kept[:, 0] != kept[:, 1]], axis=1), axis=0)
    return VesselGraph(
        positions / count[:, None],
        radii / count,
        kept.reshape(-1, 2),
        graph.spacing,
        dict(graph.info),
    )


def mask_fidelity(mask: ArrayLike, graph: VesselGraph) -> dict[str, float]:
    """Where the graph leaves the mask it was built from.

    Parameters
    ----------
    mask : array_like
        3-D, non-zero = vessel; voxel ``(i, j, k)`` is centred at ``(i, j, k) * graph.spacing``.
    graph : VesselGraph

    Returns
    -------
    dict
        - ``nodes_outside_dilated``: graph nodes whose voxel (position / spacing, rounded) is
          outside the mask dilated by one voxel (a 3x3x3 cube; out of the array counts as
          outside): the invariant of ``tests/method.rs``.
        - ``edge_outside``: fraction of the graph's edge length whose points fall in
          background voxels (each edge sampled every quarter of the finest spacing, each
          sample in the voxel it rounds to); ``edge_outside_length`` the same as a length
          (physical).

    Examples
    --------
    >>> from vesselflow import synth
    >>> mask, truth = synth.torus()
    >>> mask_fidelity(mask, truth)["nodes_outside_dilated"]
    0
    """
    graph = _check_graph(graph, "graph")
    arr = np.asarray(mask)
    if arr.ndim != 3:
        raise ValueError(f"mask must be 3-D, got {arr.ndim} dimensions")
    arr = arr != 0
    shape = np.asarray(arr.shape)

    def inside(points: NDArray[np.float64], volume: NDArray[np.bool_]) -> NDArray[np.bool_]:
        vox = np.rint(points / graph.spacing).astype(np.int64)
        ok = np.all((vox >= 0) & (vox < shape), axis=1)
        hit = np.zeros(len(points), dtype=bool)
        hit[ok] = volume[tuple(vox[ok].T)]
        return hit

    dilated = ndimage.binary_dilation(arr, structure=np.ones((3, 3, 3), dtype=bool))
    nodes_out = int(graph.n_nodes - np.count_nonzero(inside(graph.positions, dilated)))
    a = graph.positions[graph.edges[:, 0]]
    b = graph.positions[graph.edges[:, 1]]
    length = np.linalg.norm(b - a, axis=1)
    total = float(length.sum())
    if total == 0.0:
        return {"nodes_outside_dilated": nodes_out, "edge_outside": 0.0, "edge_outside_length": 0.0}
    pieces = np.maximum(1, np.ceil(length / (0.25 * float(graph.spacing.min())))).astype(np.int64)
    edge = np.repeat(np.arange(len(a)), pieces)
    first = np.repeat(np.cumsum(pieces) - pieces, pieces)
    t = ((np.arange(len(edge)) - first + 0.5) / pieces[edge])[:, None]
    points = a[edge] + t * (b - a)[edge]
    outside = ~inside(points, arr)
    out_length = float(np.sum((length / pieces)[edge][outside]))
    return {
        "nodes_outside_dilated": nodes_out,
        "edge_outside": out_length / total,
        "edge_outside_length": out_length,
    }
