"""A loopy capillary mesh with a known cycle rank: :func:`capillary_network`."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree

from vesselflow.graph import VesselGraph
from vesselflow.synth._common import (
    _MAX_ATTEMPTS,
    BoolArray,
    FloatArray,
    IntArray,
    _betti_numbers,
    _check_int,
    _check_positive,
    _check_shape,
    _check_spacing,
    _clearance,
    _cycle_rank,
    _extent,
    _polyline_graph,
    _rasterise,
)


def capillary_network(
    shape: Sequence[int] = (96, 96, 96),
    seed: int = 0,
    spacing: ArrayLike = (1.0, 1.0, 1.0),
    *,
    radius: tuple[float, float] = (1.0, 2.0),
    node_spacing: float = 14.0,
    extra_edges: float = 0.5,
    jitter: float = 0.15,
    bend: float = 0.1,
    supersample: int = 3,
) -> tuple[BoolArray, VesselGraph]:
    """A loopy mesh of thin, gently curved vessels, like a two-photon capillary bed.

    Nodes sit on a cubic lattice of step ``node_spacing`` (physical) centred in the box, each
    moved by up to ``jitter * node_spacing`` along each axis. The kept edges are a random
    spanning tree of the lattice's 6-neighbour edges (Kruskal on random weights) plus each other
    lattice edge with probability ``extra_edges``, so the graph is connected and has many
    cycles. Each edge is a quadratic Bezier curve whose control point is moved off the chord's
    midpoint by up to ``bend`` times the chord length in a random perpendicular direction,
    with a radius drawn uniformly from ``radius`` (physical), sampled every finest voxel and
    rasterised as a chain of capsules (shared supersampled rasteriser) through every fourth
    sample; one-voxel background gaps in the creases where vessels meet are filled (see
    :func:`vascular_tree`, step 5).

    The mask realises the graph's topology: where two vessels that share no node come closer
    than one voxel diagonal plus their radii, or two that share a node do so away
    from it, one of them is dropped if the graph stays connected, otherwise both are
    straightened; then the mask's Betti numbers are checked (one 26-component, no cavity, as
    many loops as the truth's cycle rank), and the network is redrawn if they differ.

    Returns
    -------
    mask : (shape) bool
    truth : VesselGraph
        Lattice nodes first (radius: the largest of their vessels'), then the curve samples.
        ``info["cycle_rank"]`` is ``E - N + C`` (C = 1), which equals the mask's number of
        independent loops; ``info["lattice_nodes"]`` the number of lattice nodes.
    """
    dims = _check_shape(shape, minimum=8)
    sp = _check_spacing(spacing)
    ss = _check_int("supersample", supersample, 1)
    try:
        r_lo, r_hi = (float(x) for x in radius)
    except (TypeError, ValueError):
        raise TypeError(f"radius must be a pair of numbers, got {radius!r}") from None
    if not (0 < r_lo <= r_hi and math.isfinite(r_hi)):
        raise ValueError(f"radius must be a pair 0 < low <= high, got {radius!r}")
    step = _check_positive("node_spacing", node_spacing)
    for name, value, top in (
        ("extra_edges", extra_edges, 1.0),
        ("jitter", jitter, 0.25),
        ("bend", bend, 0.25),
    ):
        if not 0.0 <= float(value) <= top:
            raise ValueError(f"{name} must be in [0, {top}], got {value!r}")
    clearance = _clearance(sp)
    if step * (1.0 - 2.0 * jitter) < 2.0 * r_hi + 2.0 * clearance:
        raise ValueError(
            f"node_spacing {step:g} leaves no room between vessels of radius up to {r_hi:g}"
        )
    extent = _extent(dims, sp)
    margin = r_hi + jitter * step + bend * step * (1 + 2 * jitter) + clearance
    counts = np.floor((extent - 2 * margin) / step).astype(np.int64) + 1
    if np.any(counts < 2):
        raise ValueError(
            f"shape {dims} at spacing {sp.tolist()} is too small for a lattice of step {step:g}"
        )
    rng = np.random.default_rng(seed)
    for _ in range(_MAX_ATTEMPTS):
        result = _draw_capillaries(
            rng,
            dims,
            sp,
            ss,
            counts,
            step,
            extent,
            (r_lo, r_hi),
            extra_edges,
            jitter,
            bend,
            clearance,
        )
        if result is not None:
            mask, truth = result
            truth.info.update(generator="capillary_network", seed=seed)
            return mask, truth
    raise RuntimeError(f"no valid capillary network in {_MAX_ATTEMPTS} attempts")


def _draw_capillaries(
    rng: np.random.Generator,
    shape: tuple[int, int, int],
    spacing: FloatArray,
    supersample: int,
    counts: IntArray,
    step: float,
    extent: FloatArray,
    radius: tuple[float, float],
    extra_edges: float,
    jitter: float,
    bend: float,
    clearance: float,
) -> tuple[BoolArray, VesselGraph] | None:
    index = np.arange(int(np.prod(counts))).reshape(tuple(int(c) for c in counts))
    lattice = np.stack(np.unravel_index(index.ravel(), index.shape), axis=1).astype(np.float64)
    origin = (extent - (counts - 1) * step) / 2.0
    nodes = origin + lattice * step + rng.uniform(-jitter, jitter, lattice.shape) * step
    pairs = []
    for k in range(3):
        lo_sl = tuple(slice(0, -1) if i == k else slice(None) for i in range(3))
        hi_sl = tuple(slice(1, None) if i == k else slice(None) for i in range(3))
        pairs.append(np.stack([index[lo_sl].ravel(), index[hi_sl].ravel()], axis=1))
    all_edges = np.concatenate(pairs)
    n_nodes = len(nodes)
    weights = rng.random(len(all_edges)) + 1.0
    span = minimum_spanning_tree(
        coo_matrix((weights, (all_edges[:, 0], all_edges[:, 1])), shape=(n_nodes, n_nodes))
    ).tocoo()
    in_tree = {(min(u, v), max(u, v)) for u, v in zip(span.row.tolist(), span.col.tolist())}
    extra = rng.random(len(all_edges)) < extra_edges
    keep = np.array([(int(u), int(v)) in in_tree for u, v in all_edges]) | extra
    edges = all_edges[keep]
    r_edge = rng.uniform(radius[0], radius[1], len(edges))
    # Perpendicular bend directions and amounts.
    chord = nodes[edges[:, 1]] - nodes[edges[:, 0]]
    rand = rng.normal(size=chord.shape)
    unit = chord / np.linalg.norm(chord, axis=1, keepdims=True)
    perp = rand - np.sum(rand * unit, axis=1, keepdims=True) * unit
    perp /= np.linalg.norm(perp, axis=1, keepdims=True)
    offset = (
        perp * (bend * rng.uniform(-1.0, 1.0, len(edges)) * np.linalg.norm(chord, axis=1))[:, None]
    )
    s_min = float(spacing.min())

    def curve(e: int) -> FloatArray:
        p, q = nodes[edges[e, 0]], nodes[edges[e, 1]]
        ctrl = (p + q) / 2.0 + offset[e]
        length = float(np.linalg.norm(q - p)) * (1.0 + 2.0 * bend)
        m = max(2, math.ceil(length / s_min))
        t = (np.arange(1, m) / m)[:, None]
        out: FloatArray = (1 - t) ** 2 * p + 2 * (1 - t) * t * ctrl + t**2 * q
        return out

    alive = np.ones(len(edges), dtype=bool)
    straight = np.zeros(len(edges), dtype=bool)
    for _ in range(50):
        live = np.flatnonzero(alive)
        interiors = {int(e): curve(int(e)) for e in live}
        pts = np.concatenate([interiors[int(e)] for e in live])
        owner = np.concatenate([np.full(len(interiors[int(e)]), e) for e in live])
        near = cKDTree(pts).query_pairs(2.0 * radius[1] + clearance, output_type="ndarray")
        ea, eb = owner[near[:, 0]], owner[near[:, 1]]
        d = np.linalg.norm(pts[near[:, 0]] - pts[near[:, 1]], axis=1)
        limit = r_edge[ea] + r_edge[eb] + clearance
        bad = (ea != eb) & (d < limit)
        # Vessels sharing a node overlap around it; only contacts away from it count.
        for side_a in (0, 1):
            for side_b in (0, 1):
                shared = bad & (edges[ea, side_a] == edges[eb, side_b])
                hub = nodes[edges[ea, side_a]]
                away = 1.5 * (2.0 * radius[1] + clearance)
                close_a = np.linalg.norm(pts[near[:, 0]] - hub, axis=1) < away
                close_b = np.linalg.norm(pts[near[:, 1]] - hub, axis=1) < away
                bad &= ~(shared & (close_a | close_b))
        if not np.any(bad):
            break
        conflicts = sorted({(int(min(x, y)), int(max(x, y))) for x, y in zip(ea[bad], eb[bad])})
        for x, y in conflicts:
            if not (alive[x] and alive[y]):
                continue
            dropped = False
            for e in (y, x):
                alive[e] = False
                kept = edges[alive]
                n_comp = connected_components(
                    coo_matrix(
                        (np.ones(len(kept)), (kept[:, 0], kept[:, 1])), shape=(n_nodes, n_nodes)
                    ),
                    directed=False,
                )[0]
                if n_comp == 1:
                    dropped = True
                    break
                alive[e] = True
            if not dropped:
                if straight[x] and straight[y]:
                    return None
                straight[[x, y]] = True
                offset[[x, y]] = 0.0
    else:
        return None
    live = np.flatnonzero(alive)
    node_r = np.zeros(n_nodes)
    np.maximum.at(node_r, edges[live, 0], r_edge[live])
    np.maximum.at(node_r, edges[live, 1], r_edge[live])
    paths = [(int(edges[e, 0]), int(edges[e, 1]), curve(int(e)), float(r_edge[e])) for e in live]
    positions, radii, truth_edges = _polyline_graph(nodes, node_r, paths)
    # Each vessel is drawn as chords over up to 4 samples, with the vessel's own radius: a
    # chord of length c strays from a curve of radius of curvature R by c^2 / (8 R), kept
    # under 0.05 voxel (R >= L^2 / (4 |offset|) for a quadratic Bezier of chord L).
    chords_a, chords_b, chords_r = [], [], []
    for vessel, (u, v, interior, r) in zip(live.tolist(), paths):
        line = np.vstack([nodes[u], interior, nodes[v]])
        bent = float(np.linalg.norm(offset[vessel]))
        chord_len = float(np.linalg.norm(nodes[v] - nodes[u]))
        every = 4
        if bent > 0:
            longest = math.sqrt(0.4 * chord_len**2 / (4.0 * bent))
            every = max(1, min(4, int(longest / s_min)))
        ids = np.unique(np.r_[np.arange(0, len(line), every), len(line) - 1])
        chords_a.append(line[ids[:-1]])
        chords_b.append(line[ids[1:]])
        chords_r.append(np.full(len(ids) - 1, r))
    piece_r = np.concatenate(chords_r)
    mask = _rasterise(
        shape,
        spacing,
        np.concatenate(chords_a),
        np.concatenate(chords_b),
        piece_r,
        piece_r,
        supersample,
        positions,
        True,
    )
    rank = _cycle_rank(len(positions), truth_edges)
    if _betti_numbers(mask) != (1, rank, 0):
        return None
    info = {"cycle_rank": rank, "lattice_nodes": n_nodes}
    return mask, VesselGraph(positions, radii, truth_edges, spacing, info=info)
