"""The CCO arterial tree: :func:`vascular_tree`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Callable

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage

from vesselflow.graph import VesselGraph
from vesselflow.synth._common import (
    _MAX_ATTEMPTS,
    BoolArray,
    FloatArray,
    _betti_numbers,
    _check_int,
    _check_positive,
    _check_shape,
    _check_spacing,
    _clearance,
    _distance_to_segment,
    _extent,
    _points_to_segments,
    _polyline_graph,
    _rasterise,
    _samples_between,
)

#: How many of the cheapest bifurcations CCO tries for a terminal before redrawing it.
_CCO_TRIES = 12


def vascular_tree(
    shape: Sequence[int] = (128, 128, 128),
    n_terminals: int = 32,
    seed: int = 0,
    spacing: ArrayLike = (1.0, 1.0, 1.0),
    *,
    root_radius: float | None = None,
    min_radius: float | None = None,
    supersample: int = 3,
    margin: float | None = None,
) -> tuple[BoolArray, VesselGraph]:
    """A VascuSynth-style arterial tree grown by constrained constructive optimisation (CCO).

    The construction (Schreiner and Buxbaum 1993; Karch et al. 1999; Hamarneh and Jassi's
    VascuSynth 2010, which made the paper's synthetic set):

    1. **Demand map.** A smooth random density over the box (a 4x4x4 grid of uniform random
       values, trilinearly interpolated, plus 0.2). Terminals are drawn from it by rejection
       sampling inside the box shrunk by ``margin``, at least ``d_min`` from every earlier
       terminal and the root and clear of every existing vessel, where
       ``d_min = 0.5 * (inner volume / n_terminals)**(1/3)``; ``d_min`` shrinks by 10 % after
       every 200 rejected terminals (here or in step 3); after ``400 + 40 * n_terminals``
       the box counts as full and the tree is regrown from scratch.
    2. **Inlet.** The root node lies on the axis-0 low face (the root radius plus one voxel
       of the coarsest spacing inside it, so the vessel is not cut by the border), at a random
       point of the middle half of that face. The first terminal is joined to it directly.
    3. **Growth.** Each new terminal ``t`` is joined to one of the 6 existing segments nearest
       to it, say ``p -> c``, by a new bifurcation ``b`` replacing it with ``p -> b``,
       ``b -> c`` and ``b -> t``. ``b`` is tried on a barycentric grid of step 1/8 over the
       triangle ``(p, c, t)`` (new segments at least 2 voxels long) and the pair (segment,
       ``b``) kept is the one minimising the total tree volume ``sum(length * r**2)`` with the
       radii the new tree would have, among those whose new segments keep a clearance of one
       voxel diagonal plus both radii from every non-adjacent vessel and whose terminals
       (``t``, and ``c`` if it is one) keep that clearance from the other two new segments,
       so that no terminal is buried in the vessel it branches from; if none does, the
       terminal is redrawn.
    4. **Radii.** Every terminal draws the same flow ``Q``. Murray's law with exponent 3 is the
       minimum-work condition for Poiseuille flow; it makes ``Q`` proportional to ``r**3`` in
       every segment, so a segment feeding ``n`` terminals has ``r = r_term * n**(1/3)`` and at
       every bifurcation ``r_parent**3 = r_a**3 + r_b**3`` holds exactly. The absolute scale,
       which a pressure drop and a viscosity would set through the Poiseuille resistance
       ``8 mu L / (pi r**4)``, is set instead by the radii asked for: terminal radius
       ``min_radius`` and root radius ``min_radius * n_terminals**(1/3)`` (6 voxels for 64
       terminals at the default 1.5), or ``root_radius`` and terminal radius
       ``root_radius / n_terminals**(1/3)``.
    5. **Volume.** Every segment is rasterised as a capsule of its radius (the shared
       supersampled rasteriser: a voxel is foreground when at least half of its
       ``supersample**3`` sub-samples are inside), the voxels holding centreline samples
       are set, and one-voxel background gaps in the creases where vessels meet are filled
       (a background voxel whose two neighbours along an axis are foreground: otherwise
       rasterised creases can hold spurious tunnels). The mask's Betti numbers are checked
       (one 26-connected component, no loop, no cavity); a tree whose vessels touch is
       redrawn (same generator, so still deterministic).

    Parameters
    ----------
    shape : 3 ints
        Mask shape, voxels.
    n_terminals : int
        Number of terminals (leaves other than the root); the paper uses 16, 32 and 64.
    seed : int
        Seed of the :func:`numpy.random.default_rng` that draws everything.
    spacing : 3 floats
        Voxel size along axes 0, 1, 2; all lengths are physical.
    root_radius, min_radius : float, optional
        Root and terminal radii (physical, see 4). By default ``min_radius`` is 1.5 times the
        finest spacing. Giving both requires ``root_radius >= min_radius * n**(1/3)``: then the
        terminal radius is ``root_radius / n**(1/3)``.
    supersample : int
        Sub-samples per voxel along each axis.
    margin : float, optional
        Distance (physical) kept between terminals and the faces; by default the root radius
        plus two finest voxels, so no vessel reaches the border.

    Returns
    -------
    mask : (shape) bool
    truth : VesselGraph
        A tree (``n_nodes == n_edges + 1``): the root, bifurcations and terminals, and points
        every finest voxel (at least one) along each segment; each node's radius is that of the
        segment entering it (the root's is the root radius). ``info`` holds ``root`` (node id),
        ``terminals`` and ``bifurcations`` (node ids), ``terminal_radius``, ``root_radius``,
        ``murray_exponent`` (3), ``seed`` and ``attempts`` (trees grown, see 1 and 5).

    Raises
    ------
    ValueError, TypeError
        Bad arguments, or a box too small for the root radius and margin.
    RuntimeError
        The box filled up twice before all terminals were placed, or no tree without
        touching vessels came out of 8 attempts.
    """
    dims = _check_shape(shape, minimum=8)
    sp = _check_spacing(spacing)
    n = _check_int("n_terminals", n_terminals, 1)
    ss = _check_int("supersample", supersample, 1)
    s_min = float(sp.min())
    r_term = _check_positive("min_radius", 1.5 * s_min if min_radius is None else min_radius)
    if root_radius is not None:
        r_root = _check_positive("root_radius", root_radius)
        if r_root / n ** (1 / 3) < r_term * (1 - 1e-12):
            raise ValueError(
                f"root_radius {r_root:g} is too small for {n} terminals of radius at least "
                f"{r_term:g}: Murray's law needs root_radius >= {r_term * n ** (1 / 3):g}"
            )
        r_term = r_root / n ** (1 / 3)
    else:
        r_root = r_term * n ** (1 / 3)
    extent = _extent(dims, sp)
    gap = r_root + 2.0 * s_min if margin is None else float(margin)
    if not math.isfinite(gap) or gap < 0:
        raise ValueError(f"margin must be a non-negative number, got {margin!r}")
    inlet_depth = r_root + float(sp.max())
    lo = np.full(3, gap)
    hi = extent - gap
    if np.any(hi - lo <= 2.0 * s_min) or extent[0] <= 2 * inlet_depth:
        raise ValueError(
            f"shape {dims} at spacing {sp.tolist()} is too small for a root radius of "
            f"{r_root:g} and a margin of {gap:g}"
        )
    rng = np.random.default_rng(seed)
    full = 0
    for attempt in range(1, _MAX_ATTEMPTS + 1):
        grown = _grow_cco(rng, n, r_term, lo, hi, extent, inlet_depth, sp)
        if grown is None:
            full += 1
            if full == 2:
                raise RuntimeError(
                    f"could not fit {n} terminals into shape {dims} (twice); use a larger "
                    "shape, fewer terminals or thinner vessels"
                )
            continue
        mask, truth = _tree_volume(dims, sp, ss, grown, r_term)
        b0, b1, b2 = _betti_numbers(mask)
        if (b0, b1, b2) == (1, 0, 0):
            truth.info.update(
                generator="vascular_tree",
                seed=seed,
                terminal_radius=r_term,
                root_radius=r_root,
                murray_exponent=3,
                attempts=attempt,
            )
            return mask, truth
    raise RuntimeError(
        f"no tree of {n} terminals without touching vessels in {_MAX_ATTEMPTS} attempts; use "
        "a larger shape, fewer terminals or thinner vessels"
    )


class _Tree:
    """A growing CCO tree: node positions and segments ``start -> end`` with parents."""

    def __init__(self, root: FloatArray, first: FloatArray) -> None:
        self.pos: list[FloatArray] = [root, first]
        self.start: list[int] = [0]
        self.end: list[int] = [1]
        self.parent: list[int] = [-1]
        self.n_down: list[int] = [1]
        self.terminals: list[int] = [1]

    def arrays(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        pos = np.asarray(self.pos)
        return pos[self.start], pos[self.end], np.asarray(self.n_down, dtype=np.float64)


def _grow_cco(
    rng: np.random.Generator,
    n: int,
    r_term: float,
    lo: FloatArray,
    hi: FloatArray,
    extent: FloatArray,
    inlet_depth: float,
    spacing: FloatArray,
) -> _Tree | None:
    """Steps 1-3 of :func:`vascular_tree`: the tree's nodes and segments, or None when
    ``400 + 40 * n`` terminals were rejected (the tree has filled the box)."""
    s_min = float(spacing.min())
    clearance = _clearance(spacing)
    field = rng.random((4, 4, 4))
    d_min = 0.5 * (float(np.prod(hi - lo)) / n) ** (1 / 3)

    def radius(count: FloatArray | float) -> FloatArray:
        return np.asarray(r_term * np.cbrt(count), dtype=np.float64)

    def draw() -> FloatArray:
        while True:
            x = lo + rng.random((64, 3)) * (hi - lo)
            grid = (x / extent * 3.0).T
            density = 0.2 + ndimage.map_coordinates(field, grid, order=1, mode="nearest")
            ok = rng.random(64) * 1.2 < density
            if np.any(ok):
                out: FloatArray = x[np.argmax(ok)]
                return out

    root = np.array([inlet_depth, 0.0, 0.0])
    root[1:] = extent[1:] * (0.25 + 0.5 * rng.random(2))
    first = draw()
    while np.linalg.norm(first - root) < d_min:
        first = draw()
    tree = _Tree(root, first)
    # Barycentric grid over the triangle (p, c, t), vertices excluded.
    g = 8
    bary = np.array(
        [(i, j, g - i - j) for i in range(g + 1) for j in range(g + 1 - i)], dtype=np.float64
    )
    bary = bary[np.max(bary, axis=1) < g] / g
    failures = 0
    while len(tree.terminals) < n:
        t = draw()
        a, b, count = tree.arrays()
        pos = np.asarray(tree.pos)
        seg_r = radius(count)
        far = np.min(np.linalg.norm(pos[[0, *tree.terminals]] - t, axis=1)) >= d_min
        clear = far and bool(
            np.all(_points_to_segments(t[None], a, b)[0] >= seg_r + r_term + clearance)
        )
        if not clear or not _connect(tree, t, bary, radius, clearance, 2.0 * s_min):
            failures += 1
            if failures % 200 == 0:
                d_min *= 0.9
            if failures > 400 + 40 * n:
                return None
    return tree


def _connect(
    tree: _Tree,
    t: FloatArray,
    bary: FloatArray,
    radius: Callable[[FloatArray | float], FloatArray],
    clearance: float,
    min_length: float,
) -> bool:
    """Step 3 of :func:`vascular_tree` for terminal ``t``; False when no connection is clear."""
    a, b, count = tree.arrays()
    pos = np.asarray(tree.pos)
    n_seg = len(a)
    dist = _points_to_segments(t[None], a, b)[0]
    candidates = np.argsort(dist, kind="stable")[:6]
    seg_len = np.linalg.norm(b - a, axis=1)
    # Volume added along the path to the root: every ancestor feeds one terminal more.
    growth = seg_len * (np.cbrt(count + 1) ** 2 - np.cbrt(count) ** 2)
    path = np.zeros(len(candidates))
    for k, s in enumerate(candidates):
        up = tree.parent[s]
        while up >= 0:
            path[k] += growth[up]
            up = tree.parent[up]
    # Every candidate segment p -> c against every grid point b: arrays (candidate, point).
    p, c = a[candidates][:, None, :], b[candidates][:, None, :]
    bif = bary[None, :, 0, None] * p + bary[None, :, 1, None] * c + bary[None, :, 2, None] * t
    m = count[candidates][:, None]
    l_pb = np.linalg.norm(bif - p, axis=2)
    l_bc = np.linalg.norm(bif - c, axis=2)
    l_bt = np.linalg.norm(bif - t, axis=2)
    ok = (l_pb >= min_length) & (l_bc >= min_length) & (l_bt >= min_length)
    # Terminals must stick out of the vessels they branch from, or the mask hides them.
    r_pb, r_bc, r_bt = radius(m + 1), radius(m), float(radius(1.0))
    ok &= _distance_to_segment(t, p, bif) >= r_pb + r_bt + clearance
    ok &= _distance_to_segment(t, bif, c) >= r_bc + r_bt + clearance
    leaf = (np.asarray(tree.n_down)[candidates] == 1)[:, None]
    ok &= ~leaf | (_distance_to_segment(c, p, bif) >= r_pb + r_bc + clearance)
    ok &= ~leaf | (_distance_to_segment(c, bif, t) >= r_bt + r_bc + clearance)
    cost = (
        l_pb * np.cbrt(m + 1) ** 2
        + l_bc * np.cbrt(m) ** 2
        + l_bt
        - seg_len[candidates][:, None] * np.cbrt(m) ** 2
        + path[:, None]
    )
    cost = np.where(ok, cost, np.inf)
    order = np.argsort(cost, axis=None, kind="stable")[: min(_CCO_TRIES, int(ok.sum()))]
    width = bif.shape[1]
    options = [(int(candidates[i // width]), bif[i // width, i % width]) for i in order.tolist()]
    if not options:
        return False
    # Clearance of the new segments from every segment that shares no node with them, for all
    # options at once; the cheapest option that passes is applied.
    seg_r = radius(count)
    starts, ends = np.asarray(tree.start), np.asarray(tree.end)
    pts, pt_r, pt_option = [], [], []
    shared = np.empty((len(options), n_seg), dtype=bool)
    for i, (s, bif) in enumerate(options):
        p_node, c_node = tree.start[s], tree.end[s]
        shared[i] = np.isin(starts, (p_node, c_node)) | np.isin(ends, (p_node, c_node))
        new_r = radius(np.array([count[s] + 1, count[s], 1.0]))
        for (u, v), r in zip(((pos[p_node], bif), (bif, pos[c_node]), (bif, t)), new_r):
            # Interior samples: the end points sit on nodes the new segments share.
            inner = _samples_between(u, v, 0.5 * min_length)
            pts.append(inner)
            pt_r.append(np.full(len(inner), r))
            pt_option.append(np.full(len(inner), i))
    option_of = np.concatenate(pt_option)
    points = np.concatenate(pts)
    point_r = np.concatenate(pt_r)
    # Only segments whose bounding boxes come within reach of the samples' can be hit.
    reach = float(point_r.max()) + seg_r + clearance
    near = np.flatnonzero(
        np.all(np.minimum(a, b) - reach[:, None] <= points.max(axis=0), axis=1)
        & np.all(np.maximum(a, b) + reach[:, None] >= points.min(axis=0), axis=1)
    )
    d = _points_to_segments(points, a[near], b[near])
    hit = (d < point_r[:, None] + seg_r[near][None, :] + clearance) & ~shared[option_of][:, near]
    blocked = np.zeros(len(options), dtype=bool)
    blocked[option_of[np.any(hit, axis=1)]] = True
    if blocked.all():
        return False
    s, bif = options[int(np.argmin(blocked))]
    p_node, c_node = tree.start[s], tree.end[s]
    # Apply: s becomes p -> b; new segments b -> c (children of c re-parented) and b -> t.
    b_node = len(tree.pos)
    tree.pos.append(bif)
    t_node = len(tree.pos)
    tree.pos.append(t)
    tree.end[s] = b_node
    bc = len(tree.start)
    for i in range(n_seg):
        if tree.parent[i] == s:
            tree.parent[i] = bc
    tree.start += [b_node, b_node]
    tree.end += [c_node, t_node]
    tree.parent += [s, s]
    tree.n_down += [tree.n_down[s], 1]
    up = s
    while up >= 0:
        tree.n_down[up] += 1
        up = tree.parent[up]
    tree.terminals.append(t_node)
    return True


def _tree_volume(
    shape: tuple[int, int, int],
    spacing: FloatArray,
    supersample: int,
    tree: _Tree,
    r_term: float,
) -> tuple[BoolArray, VesselGraph]:
    """Step 5 of :func:`vascular_tree`: truth graph and mask of a grown tree."""
    nodes = np.asarray(tree.pos)
    seg_r = r_term * np.cbrt(np.asarray(tree.n_down, dtype=np.float64))
    node_r = np.empty(len(nodes))
    node_r[0] = seg_r[0]
    node_r[tree.end] = seg_r
    step = float(spacing.min())
    paths = [
        (u, v, _samples_between(nodes[u], nodes[v], step), float(r))
        for u, v, r in zip(tree.start, tree.end, seg_r)
    ]
    positions, radii, edges = _polyline_graph(nodes, node_r, paths)
    a, b = nodes[tree.start], nodes[tree.end]
    mask = _rasterise(shape, spacing, a, b, seg_r, seg_r, supersample, positions, True)
    is_bif = np.zeros(len(nodes), dtype=bool)
    is_bif[tree.start] = True
    is_bif[0] = False
    info = {
        "root": 0,
        "terminals": sorted(tree.terminals),
        "bifurcations": np.flatnonzero(is_bif).tolist(),
    }
    return mask, VesselGraph(positions, radii, edges, spacing, info=info)
