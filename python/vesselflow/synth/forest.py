"""A second, independent family of vascular volumes: :func:`vascular_forest`.

Written apart from :func:`~vesselflow.synth.vascular_tree` so that a method tuned on one
family can be checked on the other: a different growth model (space colonisation instead of
constrained constructive optimisation), different geometry (vessels may touch and cross,
leaves join nearby vessels, the radius ripples along the vessel) and a different
rasterisation convention (voxel centres instead of supersampled partial volume).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from vesselflow.graph import VesselGraph
from vesselflow.synth._common import (
    BoolArray,
    FloatArray,
    IntArray,
    _check_int,
    _check_positive,
    _check_shape,
    _check_spacing,
    _extent,
    _rasterise,
)

#: Upper bound on space-colonisation rounds (growth stops earlier when no node can grow).
_MAX_ROUNDS = 600


def vascular_forest(
    shape: Sequence[int] = (128, 128, 128),
    seed: int = 0,
    spacing: ArrayLike = (1.0, 1.0, 1.0),
    *,
    n_trees: int | None = None,
    attractors: int = 500,
    root_radius: float = 6.5,
    min_radius: float = 1.5,
    ripple: float = 0.06,
    anastomoses: float = 0.35,
) -> tuple[BoolArray, VesselGraph]:
    """A forest of 1-4 vascular trees grown from the faces inward by space colonisation,
    with Murray radii, a rippled surface and anastomoses, rasterised at voxel centres.

    Lengths below are in units of the finest spacing ``s`` (all geometry is physical).

    1. **Roots.** ``n_trees`` (default: 1 to 4, drawn) roots on distinct faces of the box, at
       a uniform point of the middle 60 % of the face, ``root_radius + 1`` inside it, each
       first heading along the inward normal.
    2. **Growth** (space colonisation, Runions et al. 2007): ``attractors`` points drawn
       uniformly in the box shrunk by ``root_radius / 2 + 2``. Each round, every attractor
       is assigned to its nearest tree node; every node with attractors grows a child
       ``1.5 s`` away along the unit mean of the directions to them plus 0.6 times the node's
       own heading (persistence: smooth vessels), and attractors within ``5 s`` of a node are
       removed. Growth stops when no attractor is left or no node can grow (a child would
       leave the attractors' box grown by ``root_radius + 1``, or land within ``0.75 s`` of
       an existing node), or after 600 rounds.
    3. **Pruning.** Leaf branches that would be buried in their parent (shorter than the
       parent's radius plus two terminal radii plus ``2 s``) are removed, repeatedly.
    4. **Radii.** A power law of Murray's kind: a node feeding ``n`` leaves has radius
       ``min_radius * n**(1/k)``, so ``r_parent**k = r_a**k + r_b**k`` at every bifurcation,
       with the exponent ``k`` chosen per forest in [2, 3] (Murray's 3 and the lower values
       measured in arterial trees) so that the root of the largest tree has ``root_radius``
       when it can. Then a **ripple**: every radius is multiplied by
       ``1 + ripple * sin(2 pi a / w + phase)`` with ``a`` the arc length from the root and a
       wavelength ``w`` drawn in [10, 20] s per tree. The ripple is part of the truth radius.
    5. **Anastomoses.** Each leaf, with probability ``anastomoses``, is joined by a straight
       vessel (the leaf's radius, samples every ``s``) to the nearest node of another branch
       (not within ``6 * root_radius`` of path length upstream) whose centre lies within
       ``12 s`` plus both radii and whose wall is at least ``s`` away. These close loops in
       the truth graph; most that run beside their parent close no tunnel of the mask.
    6. **Volume (voxel-centre convention).** Every edge is a round cone (radii linear between
       its nodes' radii); a voxel is foreground exactly when its **centre** lies within the
       union (the shared rasteriser with one sample per voxel: the exact distance to the
       segment against the interpolated radius). The voxels holding truth nodes are set, and
       one-voxel background gaps in the creases where vessels meet are filled. Trees may touch
       and cross: nothing is checked or redrawn, so the mask's own topology (components,
       Betti numbers) is the target, not the truth graph's.

    Convention, for radius estimators: every voxel centre within ``r`` of the axis is
    foreground and none beyond (away from other vessels), so ``scipy.ndimage
    .distance_transform_edt`` (distance from a foreground voxel centre to the nearest
    background voxel centre) at a voxel centre ``delta`` from the axis lies in
    ``(r - delta, r + delta + sqrt(3)/2]``. :func:`vascular_tree` (supersampled partial volume
    thresholded at 0.5) puts the boundary at the same place on flat walls but shaves convex
    ones: thin vessels come out slightly thinner there.

    Parameters
    ----------
    shape : 3 ints
        Mask shape, voxels.
    seed : int
        Seed of the :func:`numpy.random.default_rng` that draws everything.
    spacing : 3 floats
        Voxel size along axes 0, 1, 2.
    n_trees : int, optional
        Number of trees (1 to 6); drawn in 1..4 by default.
    attractors : int
        Attraction points of space colonisation: more gives more, shorter branches.
    root_radius, min_radius : float
        Radius of the largest root and the floor of the radii, in units of the finest spacing.
    ripple : float
        Relative amplitude of the radius ripple, in [0, 0.3].
    anastomoses : float
        Probability that a leaf is joined to a nearby vessel, in [0, 1].

    Returns
    -------
    mask : (shape) bool
    truth : VesselGraph
        Nodes every about ``1.5 s`` along the vessels (``s`` on anastomoses), radii from 4.
        ``info`` holds ``generator``, ``seed``, ``roots``, ``junctions`` (nodes of degree at
        least 3), ``anastomoses`` (how many were made), ``n_trees``, ``terminal_radius``,
        ``murray_exponent`` and ``convention`` (``"voxel-centre"``).

    Raises
    ------
    ValueError, TypeError
        Bad arguments, or a box too small for the root radius.

    Examples
    --------
    >>> from vesselflow import synth
    >>> mask, truth = synth.vascular_forest((64, 64, 64), seed=1, attractors=60)
    >>> bool(mask.any()), truth.info["convention"]
    (True, 'voxel-centre')
    """
    dims = _check_shape(shape, minimum=16)
    sp = _check_spacing(spacing)
    n_attr = _check_int("attractors", attractors, 1)
    s = float(sp.min())
    r_root = _check_positive("root_radius", root_radius) * s
    r_min = _check_positive("min_radius", min_radius) * s
    if r_min > r_root:
        raise ValueError(f"min_radius {min_radius} must not exceed root_radius {root_radius}")
    if not 0.0 <= float(ripple) <= 0.3:
        raise ValueError(f"ripple must be in [0, 0.3], got {ripple!r}")
    if not 0.0 <= float(anastomoses) <= 1.0:
        raise ValueError(f"anastomoses must be in [0, 1], got {anastomoses!r}")
    rng = np.random.default_rng(seed)
    trees = int(rng.integers(1, 5)) if n_trees is None else _check_int("n_trees", n_trees, 1)
    if trees > 6:
        raise ValueError(f"n_trees must be at most 6 (one per face), got {trees}")
    extent = _extent(dims, sp)
    inset = r_root + s
    lo = np.full(3, 0.5 * r_root + 2.0 * s)
    hi = extent - lo
    if np.any(hi - lo <= 4.0 * inset):
        raise ValueError(f"shape {dims} is too small for a root radius of {root_radius}")

    pos, parent, root_of = _colonise(rng, trees, n_attr, extent, lo, hi, inset, s)
    pos, parent, root_of = _prune(pos, parent, root_of, r_root, r_min, s)
    leaves = _leaf_counts(parent)
    n_max = float(leaves[parent < 0].max())
    exponent = (
        float(np.clip(math.log(n_max) / math.log(r_root / r_min), 2.0, 3.0))
        if n_max > 1 and r_root > r_min
        else 3.0
    )
    radii = r_min * leaves ** (1.0 / exponent)
    arc = _arc_length(pos, parent)
    wave = rng.uniform(10.0, 20.0, trees) * s
    phase = rng.uniform(0.0, 2 * math.pi, trees)
    radii = radii * (
        1.0 + float(ripple) * np.sin(2 * math.pi * arc / wave[root_of] + phase[root_of])
    )
    edges = np.stack([np.flatnonzero(parent >= 0), parent[parent >= 0]], axis=1)
    pos, radii, edges, made = _anastomose(
        rng, pos, radii, edges, parent, arc, anastomoses, r_root, s
    )
    mask = _rasterise(
        dims,
        sp,
        pos[edges[:, 0]],
        pos[edges[:, 1]],
        radii[edges[:, 0]],
        radii[edges[:, 1]],
        1,
        pos,
        True,
    )
    degree = np.bincount(edges.ravel(), minlength=len(pos))
    info = {
        "generator": "vascular_forest",
        "seed": seed,
        "roots": np.flatnonzero(parent < 0).tolist(),
        "junctions": np.flatnonzero(degree >= 3).tolist(),
        "anastomoses": made,
        "n_trees": trees,
        "terminal_radius": r_min,
        "murray_exponent": exponent,
        "convention": "voxel-centre",
    }
    return mask, VesselGraph(pos, radii, edges, sp, info=info)


def _colonise(
    rng: np.random.Generator,
    trees: int,
    n_attr: int,
    extent: FloatArray,
    lo: FloatArray,
    hi: FloatArray,
    inset: float,
    s: float,
) -> tuple[FloatArray, IntArray, IntArray]:
    """Steps 1-2 of :func:`vascular_forest`: node positions, parents (-1 at roots) and the
    root each node grows from."""
    faces = rng.permutation(6)[:trees]
    pos: list[FloatArray] = []
    heading: list[FloatArray] = []
    for face in faces.tolist():
        axis, high = face // 2, face % 2 == 1
        p = extent * (0.2 + 0.6 * rng.random(3))
        p[axis] = extent[axis] - inset if high else inset
        h = np.zeros(3)
        h[axis] = -1.0 if high else 1.0
        pos.append(p)
        heading.append(h)
    parent = [-1] * trees
    root_of = list(range(trees))
    attr = lo + rng.random((n_attr, 3)) * (hi - lo)
    step, kill, too_close = 1.5 * s, 5.0 * s, 0.75 * s
    for _ in range(_MAX_ROUNDS):
        if len(attr) == 0:
            break
        nodes = np.asarray(pos)
        _, nearest = cKDTree(nodes).query(attr)
        grew = False
        for node in np.unique(nearest).tolist():
            to = attr[nearest == node] - nodes[node]
            pull = np.sum(to / np.linalg.norm(to, axis=1, keepdims=True), axis=0)
            norm = float(np.linalg.norm(pull))
            direction = (pull / norm if norm > 1e-9 else 0.0) + 0.6 * heading[node]
            direction /= max(float(np.linalg.norm(direction)), 1e-12)
            child = nodes[node] + step * direction
            if np.any(child < lo - inset) or np.any(child > hi + inset):
                continue
            if np.min(np.linalg.norm(np.asarray(pos) - child, axis=1)) < too_close:
                continue
            pos.append(child)
            heading.append(direction)
            parent.append(node)
            root_of.append(root_of[node])
            grew = True
        if not grew:
            break
        near = cKDTree(np.asarray(pos)).query(attr, distance_upper_bound=kill)[0]
        attr = attr[~np.isfinite(near)]
    return np.asarray(pos), np.asarray(parent, np.int64), np.asarray(root_of, np.int64)


def _leaf_counts(parent: IntArray) -> FloatArray:
    """Leaves downstream of every node (a leaf counts itself); parents precede children."""
    n = len(parent)
    children = np.bincount(parent[parent >= 0], minlength=n)
    count: FloatArray = (children == 0).astype(np.float64)
    for node in range(n - 1, -1, -1):
        if parent[node] >= 0:
            count[parent[node]] += count[node]
    return count


def _arc_length(pos: FloatArray, parent: IntArray) -> FloatArray:
    """Path length from each node's root (parents precede children)."""
    arc = np.zeros(len(pos))
    for node in range(len(pos)):
        if parent[node] >= 0:
            arc[node] = arc[parent[node]] + float(np.linalg.norm(pos[node] - pos[parent[node]]))
    return arc


def _prune(
    pos: FloatArray, parent: IntArray, root_of: IntArray, r_root: float, r_min: float, s: float
) -> tuple[FloatArray, IntArray, IntArray]:
    """Step 3 of :func:`vascular_forest`: drop leaf branches buried in their parent."""
    while True:
        n = len(pos)
        children = np.bincount(parent[parent >= 0], minlength=n)
        leaves = _leaf_counts(parent)
        keep = np.ones(n, dtype=bool)
        for leaf in np.flatnonzero(children == 0).tolist():
            chain, length, node = [leaf], 0.0, leaf
            while parent[node] >= 0 and children[parent[node]] == 1:
                length += float(np.linalg.norm(pos[node] - pos[parent[node]]))
                node = int(parent[node])
                chain.append(node)
            if parent[node] < 0:
                continue  # a whole unbranched tree: keep it
            fork = int(parent[node])
            length += float(np.linalg.norm(pos[node] - pos[fork]))
            r_fork = min(r_root, r_min * float(leaves[fork]) ** 0.5)
            if length < r_fork + 2.0 * r_min + 2.0 * s:
                keep[chain] = False
        if keep.all():
            return pos, parent, root_of
        index = np.cumsum(keep) - 1
        parent = np.where(parent[keep] >= 0, index[np.maximum(parent[keep], 0)], -1)
        pos, root_of = pos[keep], root_of[keep]


def _anastomose(
    rng: np.random.Generator,
    pos: FloatArray,
    radii: FloatArray,
    edges: IntArray,
    parent: IntArray,
    arc: FloatArray,
    probability: float,
    r_root: float,
    s: float,
) -> tuple[FloatArray, FloatArray, IntArray, int]:
    """Step 5 of :func:`vascular_forest`: join leaves to nearby vessels by straight tubes."""
    n = len(pos)
    children = np.bincount(parent[parent >= 0], minlength=n)
    leaves = np.flatnonzero((children == 0) & (parent >= 0))
    join = leaves[rng.random(len(leaves)) < probability]
    index = cKDTree(pos)
    new_pos, new_r, new_edges = [pos], [radii], [edges]
    next_id, made = n, 0
    for leaf in join.tolist():
        upstream = set()
        node = leaf
        while node >= 0 and arc[leaf] - arc[node] <= 6.0 * r_root:
            upstream.add(node)
            node = int(parent[node])
        reach = 12.0 * s + radii[leaf] + r_root
        near = [j for j in index.query_ball_point(pos[leaf], reach) if j not in upstream]
        if not near:
            continue
        cand = np.asarray(sorted(near))
        d = np.linalg.norm(pos[cand] - pos[leaf], axis=1)
        ok = (d - radii[cand] - radii[leaf] >= s) & (d <= 12.0 * s + radii[cand] + radii[leaf])
        if not np.any(ok):
            continue
        target = int(cand[ok][np.argmin(d[ok])])
        k = max(1, math.ceil(float(d[ok].min()) / s)) - 1
        t = (np.arange(1, k + 1) / (k + 1))[:, None]
        interior = pos[leaf] + t * (pos[target] - pos[leaf])
        ids = np.concatenate([[leaf], np.arange(next_id, next_id + k), [target]]).astype(np.int64)
        new_pos.append(interior)
        new_r.append(np.full(k, radii[leaf]))
        new_edges.append(np.stack([ids[:-1], ids[1:]], axis=1))
        next_id += k
        made += 1
    return np.concatenate(new_pos), np.concatenate(new_r), np.concatenate(new_edges), made
