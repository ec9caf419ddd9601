"""Synthetic vessel volumes with ground truth: masks and the centreline graphs they came from.

Every generator returns ``(mask, truth)``: ``mask`` a C-order boolean array of the requested
shape, ``truth`` a :class:`~vesselflow.VesselGraph` whose positions and radii are in physical
units (voxel ``(i, j, k)`` has its centre at ``(i * s0, j * s1, k * s2)``), in the same frame as
the graphs :func:`vesselflow.skeletonize` returns for that mask and spacing.

- :func:`vascular_tree`: a VascuSynth-like arterial tree grown by constrained constructive
  optimisation, the kind of volume of the paper's synthetic set (its section IV-A, Table I);
- :func:`add_bubble_noise`: the paper authors' boundary noise for the ``D0``/``D1``/``D2`` sets;
- :func:`capillary_network`: a loopy mesh of thin tubes with a known cycle rank, like the
  two-photon microscopy stacks of section IV-E;
- :func:`cylinder`, :func:`torus`, :func:`y_bifurcation`, :func:`helix`: analytic shapes;
- :func:`vascular_bed`: the benchmark beds of ``benches/performance.py`` (mask only).

All tubes are drawn by one rasteriser: a union of *round cones* (capsules whose radius may
vary linearly from one end to the other: the union of the balls centred on a segment with
linearly interpolated radii), sampled ``supersample**3`` times per voxel; a voxel is foreground
when at least half of its sub-samples are inside. Only voxels near a surface are supersampled
(the inside function is 1-Lipschitz, so a voxel whose centre is deeper than half its diagonal
is wholly inside or outside), so the cost is about that of sampling voxel centres.
Everything is deterministic given ``seed`` (a :class:`numpy.random.Generator` per call).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree

from vesselflow.graph import VesselGraph

__all__ = [
    "BUBBLE_LEVELS",
    "add_bubble_noise",
    "capillary_network",
    "cylinder",
    "helix",
    "torus",
    "vascular_bed",
    "vascular_tree",
    "y_bifurcation",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

#: Fraction of the dilated mask's boundary voxels that seed a bubble, per noise level.
BUBBLE_LEVELS = {"D0": 0.005, "D1": 0.025, "D2": 0.075}
#: Upper bound on the voxels (times sub-samples) evaluated in one vectorised batch.
_BATCH_ELEMENTS = 1 << 20

#: How many of the cheapest bifurcations CCO tries for a terminal before redrawing it.
_CCO_TRIES = 12
#: How many times a generator redraws before giving up on a topologically valid volume.
_MAX_ATTEMPTS = 8


# --------------------------------------------------------------------------- validation


def _check_shape(shape: Sequence[int], minimum: int = 4) -> tuple[int, int, int]:
    try:
        dims = tuple(int(n) for n in shape)
        exact = all(int(n) == n for n in shape)
    except TypeError:
        raise TypeError(f"shape must be 3 integers, got {shape!r}") from None
    if len(dims) != 3 or not exact:
        raise ValueError(f"shape must be 3 integers, got {shape!r}")
    if min(dims) < minimum:
        raise ValueError(f"shape must be at least {minimum} voxels along each axis, got {dims}")
    return dims[0], dims[1], dims[2]


def _check_spacing(spacing: ArrayLike) -> FloatArray:
    sp = np.asarray(spacing, dtype=np.float64).reshape(-1)
    if sp.shape != (3,):
        raise ValueError(f"spacing must hold 3 numbers, got {sp.size}")
    if not np.all(np.isfinite(sp)) or np.any(sp <= 0):
        raise ValueError(f"spacing must be 3 positive numbers, got {sp.tolist()}")
    return sp


def _check_int(name: str, value: object, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {type(value).__name__}")
    if value < minimum:
        raise ValueError(f"{name} must be at least {minimum}, got {value}")
    return int(value)


def _check_positive(name: str, value: float) -> float:
    v = float(value)
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return v


def _clearance(spacing: FloatArray) -> float:
    """Gap kept between the walls of vessels that must not touch: one voxel diagonal, the
    largest distance between the centres of two 26-neighbour voxels."""
    return float(np.linalg.norm(spacing))


def _extent(shape: tuple[int, int, int], spacing: FloatArray) -> FloatArray:
    """Physical coordinates of the last voxel centre (the first is at the origin)."""
    return (np.asarray(shape, dtype=np.float64) - 1.0) * spacing


# --------------------------------------------------------------------------- rasteriser


def _round_cone_depth(
    v: tuple[FloatArray, FloatArray, FloatArray],
    axis: FloatArray,
    length: FloatArray,
    r0: FloatArray,
    r1: FloatArray,
) -> FloatArray:
    """``max_t r(t) - |x - p(t)|`` over the round cone's axis, broadcast over points.

    ``v`` is ``x - p0`` per axis, ``axis`` the unit axis (components on its last dimension
    after broadcasting: passed as three arrays), ``p(t) = p0 + t * length * axis`` and
    ``r(t) = r0 + t * (r1 - r0)`` for ``t`` in [0, 1]. The function of ``t`` is concave, so
    its maximum is its stationary point clamped to [0, 1]: with ``s`` the axial and ``a`` the
    radial coordinate of ``x`` and ``k = (r1 - r0) / length``,
    ``t* = (s + k a / sqrt(1 - k^2)) / length``. When ``|k| >= 1`` one end ball contains the
    other and ``t*`` is that end. Positive inside, 0 on the surface, and 1-Lipschitz in ``x``.
    """
    d0, d1, d2 = axis[..., 0], axis[..., 1], axis[..., 2]
    s = v[0] * d0 + v[1] * d1 + v[2] * d2
    q = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    a = np.sqrt(np.maximum(q - s * s, 0.0))
    k = (r1 - r0) / length
    kc = np.clip(k, -0.999999, 0.999999)
    t = np.clip((s + kc * a / np.sqrt(1.0 - kc * kc)) / length, 0.0, 1.0)
    t = np.where(np.abs(k) >= 0.999999, (k > 0).astype(np.float64), t)
    u = s - t * length
    depth: FloatArray = r0 + t * (r1 - r0) - np.sqrt(a * a + u * u)
    return depth


def _depth_test(
    v: tuple[FloatArray, FloatArray, FloatArray],
    axis: FloatArray,
    length: FloatArray,
    r0: FloatArray,
    r1: FloatArray,
    tapered: bool,
) -> Callable[[float], BoolArray]:
    """``lambda h: depth >= h`` for the depth of :func:`_round_cone_depth`, computed once.

    For cones of constant radius (capsules) the depth is ``r - dist`` with ``dist`` the distance
    to the axis segment, so the test compares squared distances and needs no square root.
    """
    if tapered:
        depth = _round_cone_depth(v, axis, length, r0, r1)
        return lambda h: np.asarray(depth >= h)
    s = v[0] * axis[..., 0] + v[1] * axis[..., 1] + v[2] * axis[..., 2]
    q = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    sc = np.clip(s, 0.0, length)
    dist2 = q - sc * (2.0 * s - sc)

    def test(h: float) -> BoolArray:
        reach = np.maximum(r0 - h, 0.0)
        return np.asarray((dist2 <= reach * reach) & (r0 >= h))

    return test


def _ladder(n: IntArray) -> IntArray:
    """Round stencil sizes up to a few values (at most ~19 % waste), to batch stencils."""
    steps = np.unique(np.ceil(2.0 ** (np.arange(0, 48) / 4.0)).astype(np.int64))
    return steps[np.searchsorted(steps, n)]


def _paint_round_cones(
    mask: BoolArray,
    spacing: FloatArray,
    p0: FloatArray,
    p1: FloatArray,
    r0: FloatArray,
    r1: FloatArray,
    supersample: int,
) -> None:
    """Set the voxels of ``mask`` at least half covered by the union of round cones.

    Cone ``i`` runs from ``p0[i]`` (radius ``r0[i]``) to ``p1[i]`` (radius ``r1[i]``), all in
    physical units. A voxel's coverage is the fraction of its ``supersample**3`` sub-samples
    (a regular grid at the centres of equal sub-cells) inside the union; with
    ``supersample == 1`` a voxel is set when its centre is inside. Cones may stick out of the
    volume (they are clipped). Vectorised: cones are cut into pieces a few radii long, grouped
    by stencil size and evaluated in batches; only voxels within half a voxel diagonal of a
    surface are supersampled.
    """
    shape = np.asarray(mask.shape, dtype=np.int64)
    p0 = np.asarray(p0, dtype=np.float64).reshape(-1, 3)
    p1 = np.asarray(p1, dtype=np.float64).reshape(-1, 3)
    r0 = np.broadcast_to(np.asarray(r0, dtype=np.float64), (len(p0),)).copy()
    r1 = np.broadcast_to(np.asarray(r1, dtype=np.float64), (len(p0),)).copy()
    if len(p0) == 0:
        return
    # Cut long cones into pieces no longer than twice their radius (or 4 voxels), so that
    # their bounding boxes are tight. The union of the pieces is the same solid.
    seg = p1 - p0
    length = np.linalg.norm(seg, axis=1)
    piece = np.maximum(2.0 * np.maximum(r0, r1), 4.0 * float(spacing.max()))
    n_pieces = np.maximum(1, np.ceil(length / piece).astype(np.int64))
    cone = np.repeat(np.arange(len(p0)), n_pieces)
    first = np.repeat(np.cumsum(n_pieces) - n_pieces, n_pieces)
    j = np.arange(len(cone)) - first
    t0 = (j / n_pieces[cone])[:, None]
    t1 = ((j + 1) / n_pieces[cone])[:, None]
    a = p0[cone] + t0 * seg[cone]
    b = p0[cone] + t1 * seg[cone]
    ra = r0[cone] + t0[:, 0] * (r1 - r0)[cone]
    rb = r0[cone] + t1[:, 0] * (r1 - r0)[cone]
    seg = b - a
    length = np.linalg.norm(seg, axis=1)
    short = length < 1e-9
    axis = np.where(
        short[:, None], np.array([1.0, 0.0, 0.0]), seg / np.where(short, 1, length)[:, None]
    )
    length = np.where(short, 1e-9, length)

    half_diag = 0.5 * float(np.linalg.norm(spacing))
    reach = np.maximum(ra, rb)[:, None] + (half_diag if supersample > 1 else 0.0)
    lo = np.ceil((np.minimum(a, b) - reach) / spacing).astype(np.int64)
    hi = np.floor((np.maximum(a, b) + reach) / spacing).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, shape - 1)
    keep = np.all(hi >= lo, axis=1)
    a, axis, length, ra, rb, lo, hi = (x[keep] for x in (a, axis, length, ra, rb, lo, hi))
    if len(a) == 0:
        return
    size = _ladder(hi - lo + 1)

    ss = supersample
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    offsets = np.stack(np.meshgrid(sub, sub, sub, indexing="ij"), axis=-1).reshape(-1, 3) * spacing
    flat = mask.reshape(-1)
    edge_idx: list[IntArray] = []
    edge_in: list[BoolArray] = []

    tapered = ra != rb
    key = np.concatenate([size, tapered[:, None]], axis=1)
    groups, group_of = np.unique(key, axis=0, return_inverse=True)
    for g, group in enumerate(groups):
        dims, taper = group[:3], bool(group[3])
        members = np.flatnonzero(group_of.reshape(-1) == g)
        per_batch = max(1, _BATCH_ELEMENTS // int(np.prod(dims)))
        for start in range(0, len(members), per_batch):
            m = members[start : start + per_batch]
            idx = [lo[m, k, None] + np.arange(dims[k]) for k in range(3)]
            valid_k = [idx[k] <= hi[m, k, None] for k in range(3)]
            v = [idx[k] * spacing[k] - a[m, k, None] for k in range(3)]
            vb = (
                v[0][:, :, None, None],
                v[1][:, None, :, None],
                v[2][:, None, None, :],
            )
            at_depth = _depth_test(
                vb,
                axis[m][:, None, None, None, :],
                length[m][:, None, None, None],
                ra[m][:, None, None, None],
                rb[m][:, None, None, None],
                taper,
            )
            valid = (
                valid_k[0][:, :, None, None]
                & valid_k[1][:, None, :, None]
                & valid_k[2][:, None, None, :]
            )
            lin = (
                (idx[0] * shape[1] * shape[2])[:, :, None, None]
                + (idx[1] * shape[2])[:, None, :, None]
                + idx[2][:, None, None, :]
            )
            if ss == 1:
                flat[lin[valid & at_depth(0.0)]] = True
                continue
            sure = at_depth(half_diag)
            flat[lin[valid & sure]] = True
            which, i0, i1, i2 = np.nonzero(valid & at_depth(-half_diag) & ~sure)
            if len(which) == 0:
                continue
            vox = lin[which, i0, i1, i2]
            cm = m[which]
            centre = np.stack([i0, i1, i2], axis=1) + lo[cm]
            x = centre[:, None, :] * spacing + offsets[None, :, :] - a[cm][:, None, :]
            inside = _depth_test(
                (x[..., 0], x[..., 1], x[..., 2]),
                axis[cm][:, None, :],
                length[cm][:, None],
                ra[cm][:, None],
                rb[cm][:, None],
                taper,
            )(0.0)
            edge_idx.append(vox)
            edge_in.append(inside)
    if not edge_idx:
        return
    vox = np.concatenate(edge_idx)
    inside = np.concatenate(edge_in)
    order = np.argsort(vox, kind="stable")
    vox, inside = vox[order], inside[order]
    starts = np.flatnonzero(np.r_[True, vox[1:] != vox[:-1]])
    covered = np.logical_or.reduceat(inside, starts, axis=0)
    count = np.count_nonzero(covered, axis=1)
    flat[vox[starts[2 * count >= ss**3]]] = True


def _fill_creases(mask: BoolArray) -> None:
    """Set every background voxel whose two neighbours along some axis are both foreground.

    Where two tubes meet, their surfaces make a concave crease, and rasterising it can leave a
    background voxel pinched between them that the 26-connected foreground closes a ring
    around: a spurious tunnel. Filling one-voxel gaps removes them (it touches only concave
    places: a convex surface has no such voxel).
    """
    gaps = np.zeros_like(mask)
    for k in range(3):
        lo = tuple(slice(0, -2) if i == k else slice(None) for i in range(3))
        mid = tuple(slice(1, -1) if i == k else slice(None) for i in range(3))
        hi = tuple(slice(2, None) if i == k else slice(None) for i in range(3))
        gaps[mid] |= mask[lo] & mask[hi]
    mask |= gaps


def _rasterise(
    shape: tuple[int, int, int],
    spacing: FloatArray,
    p0: FloatArray,
    p1: FloatArray,
    r0: FloatArray,
    r1: FloatArray,
    supersample: int,
    centreline: FloatArray | None = None,
    creases: bool = False,
) -> BoolArray:
    """A new mask holding the round cones. The voxels holding ``centreline`` points are set
    too (this only matters where a radius is below about half a voxel), and with ``creases``
    one-voxel gaps are filled (:func:`_fill_creases`), for volumes where vessels meet."""
    mask = np.zeros(shape, dtype=bool)
    _paint_round_cones(mask, spacing, p0, p1, r0, r1, supersample)
    if centreline is not None and len(centreline):
        vox = np.rint(centreline / spacing).astype(np.int64)
        vox = np.clip(vox, 0, np.asarray(shape) - 1)
        mask[vox[:, 0], vox[:, 1], vox[:, 2]] = True
    if creases:
        _fill_creases(mask)
    return mask


# --------------------------------------------------------------------------- topology


def _betti_numbers(mask: BoolArray) -> tuple[int, int, int]:
    """Betti numbers ``(b0, b1, b2)`` of the foreground, 26-connected (background 6-connected).

    ``b0`` counts components, ``b2`` cavities (background 6-components not reaching the
    border) and ``b1`` tunnels (independent loops), from the Euler characteristic
    ``chi = b0 - b1 + b2`` of the cubical complex made of the closed voxel cubes:
    ``chi = V - E + F - C`` counting its distinct vertices, edges, faces and cubes.
    """
    m = np.pad(np.asarray(mask, dtype=bool), 1)
    n = np.asarray(m.shape) - 1

    def closed(axes: tuple[int, ...]) -> int:
        """Cells spanning a voxel along the other axes and at a voxel corner along ``axes``:
        present when any voxel around them is."""
        out = np.zeros(tuple(int(n[k]) if k in axes else int(m.shape[k]) for k in range(3)), bool)
        for shift in np.ndindex(*(2 if k in axes else 1 for k in range(3))):
            sl = tuple(
                slice(shift[k], shift[k] + int(n[k])) if k in axes else slice(None)
                for k in range(3)
            )
            out |= m[sl]
        return int(np.count_nonzero(out))

    vertices = closed((0, 1, 2))
    edges = closed((1, 2)) + closed((0, 2)) + closed((0, 1))
    faces = closed((0,)) + closed((1,)) + closed((2,))
    cubes = int(np.count_nonzero(m))
    chi = vertices - edges + faces - cubes
    b0 = int(ndimage.label(m, structure=np.ones((3, 3, 3), dtype=bool))[1])
    b2 = int(ndimage.label(~m)[1]) - 1
    return b0, b0 + b2 - chi, b2


def _cycle_rank(n_nodes: int, edges: IntArray) -> int:
    """``E - N + C`` of an undirected graph."""
    adj = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n_nodes, n_nodes))
    c = int(connected_components(adj, directed=False)[0])
    return len(edges) - n_nodes + c


# --------------------------------------------------------------------------- polylines


def _polyline_graph(
    nodes: FloatArray,
    node_radii: FloatArray,
    paths: Sequence[tuple[int, int, FloatArray, float]],
) -> tuple[FloatArray, FloatArray, IntArray]:
    """Truth arrays for curves between given nodes.

    ``paths`` holds ``(u, v, interior, r)``: a curve from node ``u`` to node ``v`` through the
    ``interior`` points (in order), of radius ``r``. The interior points become nodes after
    the given ones, chained by edges.
    """
    positions = [nodes]
    radii = [node_radii]
    edges: list[IntArray] = []
    next_id = len(nodes)
    for u, v, interior, r in paths:
        k = len(interior)
        ids = np.concatenate([[u], np.arange(next_id, next_id + k), [v]]).astype(np.int64)
        edges.append(np.stack([ids[:-1], ids[1:]], axis=1))
        positions.append(interior.reshape(-1, 3))
        radii.append(np.full(k, r))
        next_id += k
    return (
        np.concatenate(positions),
        np.concatenate(radii),
        np.concatenate(edges) if edges else np.empty((0, 2), dtype=np.int64),
    )


def _samples_between(p: FloatArray, q: FloatArray, step: float, minimum: int = 1) -> FloatArray:
    """Interior points splitting segment ``p``-``q`` into pieces of at most ``step``."""
    n = max(minimum + 1, math.ceil(float(np.linalg.norm(q - p)) / step))
    t = (np.arange(1, n) / n)[:, None]
    out: FloatArray = p + t * (q - p)
    return out


def _distance_to_segment(x: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Distance from points ``x`` to segments ``a``-``b``, broadcast over leading axes."""
    ab = b - a
    ax = x - a
    t = np.clip(np.sum(ax * ab, axis=-1) / np.maximum(np.sum(ab * ab, axis=-1), 1e-300), 0, 1)
    out: FloatArray = np.linalg.norm(ax - t[..., None] * ab, axis=-1)
    return out


def _points_to_segments(points: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """(P, M) distances from each point to each segment ``a[m]``-``b[m]``."""
    ab = b - a
    denom = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
    ap = points[:, None, :] - a[None, :, :]
    t = np.clip(np.einsum("pmk,mk->pm", ap, ab) / denom, 0.0, 1.0)
    d = ap - t[..., None] * ab[None, :, :]
    out: FloatArray = np.sqrt(np.einsum("pmk,pmk->pm", d, d))
    return out


# --------------------------------------------------------------------------- vascular tree


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


# --------------------------------------------------------------------------- bubble noise


def add_bubble_noise(
    mask: ArrayLike,
    level: str | float,
    seed: int = 0,
    spacing: ArrayLike = (1.0, 1.0, 1.0),
) -> BoolArray:
    """Boundary "bubble" noise, the paper authors' recipe for their ``D0``/``D1``/``D2`` sets.

    1. Dilate ``mask`` once with the 6-connected structuring element.
    2. Seeds: ``round(fraction * B)`` of the ``B`` boundary voxels of the dilated mask
       (foreground voxels with a 6-neighbour in the background), drawn without replacement;
       ``fraction`` is :data:`BUBBLE_LEVELS` ``[level]`` (0.005, 0.025, 0.075 for D0, D1, D2)
       or ``level`` itself when it is a number in [0, 1].
    3. Stamp a ball of radius 2 voxels (physical radius ``2 * min(spacing)``, so an ellipsoid
       of voxels at anisotropic spacing) at every seed and take the union with the dilated mask.
    4. Fill holes: background 6-components that do not reach the border and have fewer than
       125 voxels become foreground.

    The result contains the dilated mask, hence ``mask``. The seeds are a prefix of one random
    order of the boundary voxels, so with one ``seed`` a higher level adds a superset of the
    bubbles of a lower one (``D0 <= D1 <= D2`` voxelwise).
    """
    m = np.asarray(mask)
    if m.ndim != 3:
        raise ValueError(f"mask must be 3-D, got {m.ndim}-D")
    if m.dtype != np.bool_:
        raise TypeError(f"mask must be a bool array, got {m.dtype}")
    if isinstance(level, str):
        if level not in BUBBLE_LEVELS:
            raise ValueError(
                f"level must be one of {sorted(BUBBLE_LEVELS)} or a fraction, got {level!r}"
            )
        fraction = BUBBLE_LEVELS[level]
    elif isinstance(level, (int, float, np.floating, np.integer)) and not isinstance(level, bool):
        fraction = float(level)
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"level as a fraction must be in [0, 1], got {level}")
    else:
        raise TypeError(f"level must be a str or a float, got {type(level).__name__}")
    sp = _check_spacing(spacing)
    rng = np.random.default_rng(seed)
    six = ndimage.generate_binary_structure(3, 1)
    dilated = ndimage.binary_dilation(m, structure=six)
    boundary = dilated & ~ndimage.binary_erosion(dilated, structure=six, border_value=1)
    candidates = np.flatnonzero(boundary)
    order = rng.permutation(len(candidates))
    seeds = candidates[order[: round(fraction * len(candidates))]]
    noisy = dilated.copy()
    if len(seeds):
        r = 2.0 * float(sp.min())
        half = np.floor(r / sp).astype(np.int64)
        grid = np.stack(
            np.meshgrid(*(np.arange(-h, h + 1) for h in half), indexing="ij"), axis=-1
        ).reshape(-1, 3)
        ball = grid[np.sum((grid * sp) ** 2, axis=1) <= r * r]
        centres = np.stack(np.unravel_index(seeds, m.shape), axis=1)
        vox = (centres[:, None, :] + ball[None, :, :]).reshape(-1, 3)
        inside = np.all((vox >= 0) & (vox < np.asarray(m.shape)), axis=1)
        vox = vox[inside]
        noisy[vox[:, 0], vox[:, 1], vox[:, 2]] = True
    holes, n_holes = ndimage.label(~noisy, structure=six)
    if n_holes:
        sizes = np.bincount(holes.ravel(), minlength=n_holes + 1)
        border = np.unique(
            np.concatenate(
                [
                    holes[0].ravel(),
                    holes[-1].ravel(),
                    holes[:, 0].ravel(),
                    holes[:, -1].ravel(),
                    holes[:, :, 0].ravel(),
                    holes[:, :, -1].ravel(),
                ]
            )
        )
        fill = sizes < 125
        fill[0] = False
        fill[border] = False
        noisy |= fill[holes]
    out: BoolArray = np.asarray(noisy, dtype=bool)
    return out


# --------------------------------------------------------------------------- capillaries


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


# --------------------------------------------------------------------------- analytic shapes


def _centre(shape: tuple[int, int, int], spacing: FloatArray) -> FloatArray:
    return _extent(shape, spacing) / 2.0


def _tube(
    shape: tuple[int, int, int],
    spacing: FloatArray,
    supersample: int,
    points: FloatArray,
    radii: FloatArray,
    closed: bool,
    info: dict[str, Any],
) -> tuple[BoolArray, VesselGraph]:
    """Mask and truth of one tube through ``points`` (a loop when ``closed``)."""
    n = len(points)
    ids = np.arange(n)
    edges = (
        np.stack([ids, np.roll(ids, -1)], axis=1)
        if closed
        else np.stack([ids[:-1], ids[1:]], axis=1)
    )
    a, b = points[edges[:, 0]], points[edges[:, 1]]
    mask = _rasterise(
        shape, spacing, a, b, radii[edges[:, 0]], radii[edges[:, 1]], supersample, points
    )
    return mask, VesselGraph(points, radii, edges, spacing, info=info)


def _arc_step(spacing: FloatArray) -> float:
    """Spacing of analytic centreline samples: half the finest voxel."""
    return 0.5 * float(spacing.min())


def cylinder(
    shape: Sequence[int] = (48, 48, 48),
    radius: float = 3.0,
    spacing: ArrayLike = (1.0, 1.0, 1.0),
    *,
    start: ArrayLike | None = None,
    end: ArrayLike | None = None,
    supersample: int = 3,
) -> tuple[BoolArray, VesselGraph]:
    """A straight tube of constant ``radius`` from ``start`` to ``end`` with hemispherical caps
    (a capsule), all physical.

    By default it runs along axis 0 through the centre of the box, its caps one voxel plus the
    radius inside the faces. The volume is ``pi r^2 L + 4/3 pi r^3``. Truth: the centreline
    from ``start`` to ``end`` every half finest voxel, radius ``radius``.
    """
    dims = _check_shape(shape)
    sp = _check_spacing(spacing)
    ss = _check_int("supersample", supersample, 1)
    r = _check_positive("radius", radius)
    c = _centre(dims, sp)
    inset = r + float(sp[0])
    p = c.copy() if start is None else np.asarray(start, dtype=np.float64).reshape(-1)
    q = c.copy() if end is None else np.asarray(end, dtype=np.float64).reshape(-1)
    if start is None:
        p[0] = inset
    if end is None:
        q[0] = _extent(dims, sp)[0] - inset
    if p.shape != (3,) or q.shape != (3,):
        raise ValueError("start and end must hold 3 numbers each")
    length = float(np.linalg.norm(q - p))
    if length <= 0:
        raise ValueError("start and end must differ (is the shape long enough for the radius?)")
    m = max(2, math.ceil(length / _arc_step(sp)))
    points = p + (np.arange(m + 1) / m)[:, None] * (q - p)
    info = {"generator": "cylinder", "length": length, "radius": r}
    return _tube(dims, sp, ss, points, np.full(m + 1, r), False, info)


def torus(
    shape: Sequence[int] = (64, 64, 64),
    major_radius: float = 20.0,
    minor_radius: float = 3.0,
    spacing: ArrayLike = (1.0, 1.0, 1.0),
    *,
    supersample: int = 3,
) -> tuple[BoolArray, VesselGraph]:
    """A ring tube: centreline a circle of radius ``major_radius`` about the box centre in the
    plane of axes 1 and 2, tube radius ``minor_radius`` (physical).

    Truth: a closed loop of samples every about half finest voxel (as many edges as nodes).
    """
    dims = _check_shape(shape)
    sp = _check_spacing(spacing)
    ss = _check_int("supersample", supersample, 1)
    big = _check_positive("major_radius", major_radius)
    small = _check_positive("minor_radius", minor_radius)
    if small >= big:
        raise ValueError(f"minor_radius {small:g} must be below major_radius {big:g}")
    m = max(8, math.ceil(2 * math.pi * big / _arc_step(sp)))
    theta = 2 * math.pi * np.arange(m) / m
    points = np.stack([np.zeros(m), big * np.cos(theta), big * np.sin(theta)], axis=1)
    points += _centre(dims, sp)
    info = {"generator": "torus", "major_radius": big, "minor_radius": small}
    return _tube(dims, sp, ss, points, np.full(m, small), True, info)


def y_bifurcation(
    shape: Sequence[int] = (64, 64, 64),
    radius: float = 4.0,
    spacing: ArrayLike = (1.0, 1.0, 1.0),
    *,
    angle: float = 60.0,
    supersample: int = 3,
) -> tuple[BoolArray, VesselGraph]:
    """A parent tube splitting into two symmetric children.

    The parent (radius ``radius``) runs along axis 0 from near the low face to the box centre;
    the children leave the centre ``angle`` degrees apart in the plane of axes 0 and 1, with
    Murray's radii ``radius / 2**(1/3)``, and end a radius plus one voxel inside the faces.
    One-voxel background gaps in the creases of the junction are filled (see
    :func:`vascular_tree`, step 5).
    Truth: a tree of 3 branches sampled every half finest voxel; node 0 is the junction.
    """
    dims = _check_shape(shape)
    sp = _check_spacing(spacing)
    ss = _check_int("supersample", supersample, 1)
    r = _check_positive("radius", radius)
    half = math.radians(_check_positive("angle", angle)) / 2
    if half >= math.pi / 2:
        raise ValueError(f"angle must be below 180 degrees, got {angle}")
    extent = _extent(dims, sp)
    c = extent / 2.0
    rc = r / 2 ** (1 / 3)
    inset = r + float(sp.max())
    # Children run until their caps are `inset` from a face along axis 0 or 1.
    reach = min(
        (extent[0] - c[0] - inset) / math.cos(half), (extent[1] - c[1] - inset) / math.sin(half)
    )
    if c[0] - inset <= 0 or reach <= 0:
        raise ValueError(f"shape {dims} is too small for a radius of {r:g}")
    step = _arc_step(sp)
    tips = [
        np.array([inset, c[1], c[2]]),
        c + reach * np.array([math.cos(half), math.sin(half), 0.0]),
        c + reach * np.array([math.cos(half), -math.sin(half), 0.0]),
    ]
    paths = [
        (0, i + 1, _samples_between(c, tip, step), float(rad))
        for i, (tip, rad) in enumerate(zip(tips, (r, rc, rc)))
    ]
    # Branches are listed junction-out; the parent's samples go from the junction down.
    nodes = np.vstack([c, *tips])
    positions, radii, edges = _polyline_graph(nodes, np.array([r, r, rc, rc]), paths)
    piece_r = np.repeat([p[3] for p in paths], [len(p[2]) + 1 for p in paths])
    a, b = positions[edges[:, 0]], positions[edges[:, 1]]
    mask = _rasterise(dims, sp, a, b, piece_r, piece_r, ss, positions, True)
    info = {"generator": "y_bifurcation", "radius": r, "child_radius": rc, "angle": angle}
    return mask, VesselGraph(positions, radii, edges, sp, info=info)


def helix(
    shape: Sequence[int] = (64, 64, 64),
    radius: float = 2.0,
    spacing: ArrayLike = (1.0, 1.0, 1.0),
    *,
    helix_radius: float = 12.0,
    pitch: float = 16.0,
    supersample: int = 3,
) -> tuple[BoolArray, VesselGraph]:
    """A helical tube of radius ``radius`` around the box's axis-0 centre line: centreline
    ``(z, c1 + R cos(2 pi z / pitch), c2 + R sin(2 pi z / pitch))`` for ``z`` between a radius
    plus one voxel from each axis-0 face, ``R = helix_radius`` (all physical).

    Truth: the centreline sampled every about half finest voxel of arc length.
    """
    dims = _check_shape(shape)
    sp = _check_spacing(spacing)
    ss = _check_int("supersample", supersample, 1)
    r = _check_positive("radius", radius)
    big = _check_positive("helix_radius", helix_radius)
    h = _check_positive("pitch", pitch)
    extent = _extent(dims, sp)
    c = extent / 2.0
    z0, z1 = r + float(sp[0]), extent[0] - r - float(sp[0])
    if z1 <= z0 or np.any(big + r + sp[1:] > c[1:]):
        raise ValueError(f"shape {dims} is too small for this helix")
    arc = (z1 - z0) * math.hypot(1.0, 2 * math.pi * big / h)
    m = max(2, math.ceil(arc / _arc_step(sp)))
    z = np.linspace(z0, z1, m + 1)
    phase = 2 * math.pi * z / h
    points = np.stack([z, c[1] + big * np.cos(phase), c[2] + big * np.sin(phase)], axis=1)
    info = {"generator": "helix", "radius": r, "helix_radius": big, "pitch": h}
    return _tube(dims, sp, ss, points, np.full(m + 1, r), False, info)


# --------------------------------------------------------------------------- vascular bed

#: Radius range of the bed's tubes, in voxels.
BED_MIN_RADIUS = 1.5
BED_MAX_RADIUS = 6.0
#: Spacing of the bed's centreline samples, voxels.
BED_STEP = 1.0


def _fold(x: FloatArray, lo: FloatArray | float, hi: FloatArray | float) -> FloatArray:
    """Reflect coordinates into ``[lo, hi]`` as a path bouncing off two walls would be.

    The triangle wave is continuous and keeps step lengths, so a folded path stays a
    smooth tube of the same length.
    """
    width = np.asarray(hi) - np.asarray(lo)
    out: FloatArray = lo + width - np.abs(np.mod(x - lo, 2 * width) - width)
    return out


def _bed_vessel(
    rng: np.random.Generator,
    start: FloatArray,
    heading: FloatArray,
    length: float,
    r0: float,
    size: int,
) -> tuple[FloatArray, FloatArray]:
    """Centreline samples and radii of one bed vessel leaving ``start`` along ``heading``.

    It runs for ``length`` voxels; its radius starts at ``r0`` and tapers by up to 20 %;
    its direction wanders as a random walk (thin vessels wander more), and it bounces off
    walls kept one voxel beyond its surface.
    """
    r1 = max(BED_MIN_RADIUS, r0 * rng.uniform(0.8, 1.0))
    n = max(2, int(length / BED_STEP))
    kick = rng.normal(scale=0.25 * np.sqrt(BED_STEP / r0), size=(n, 3))
    kick[0] = heading / max(float(np.linalg.norm(heading)), 1e-12)
    d = np.cumsum(kick, axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    path = start + np.concatenate([np.zeros((1, 3)), np.cumsum(BED_STEP * d[1:], axis=0)])
    return _fold(path, r0 + 1.0, size - 2.0 - r0), np.linspace(r0, r1, n)


def _paint_balls(mask: BoolArray, centres: FloatArray, radii: FloatArray) -> None:
    """Set every voxel whose centre lies within ``radii[i]`` of ``centres[i]`` (voxel units):
    the shared rasteriser with zero-length cones and one sample per voxel."""
    _paint_round_cones(mask, np.ones(3), centres, centres, radii, radii, 1)


def vascular_bed(size: int, seed: int = 0, fraction: float = 0.05, loops: int = 4) -> BoolArray:
    """A ``(size, size, size)`` boolean vascular bed with about ``fraction`` foreground.

    The benchmark volume of ``benches/performance.py`` (mask only, unit spacing, no truth): a
    connected tree of random, gently curving tubes of radii 1.5 to 6 voxels plus ``loops``
    anastomoses, one 26-connected component, no tube cut by the border.

    The root vessel (radius 6) starts at the centre of the volume, heading in a random
    direction, and is up to a fifth of the target foreground long (at most 3 ``size``). Each
    later vessel draws a radius in [1.5, 6] skewed toward thin ones (``1.5 * 4**(u**2)``, u
    uniform) and a random aim point, and sprouts toward the aim, for 10 to 30 radii, from the
    sample nearest the aim among 4096 random centreline samples at least as thick as itself.
    A vessel's radius tapers linearly by up to 20 %; its direction is a random walk (kicks of
    ``0.25 * sqrt(1 / r0)`` per 1-voxel step) folded back into the box so that its wall stays a
    voxel from the faces. Vessels are added in rounds until the foreground reaches
    ``fraction`` (small volumes overshoot by up to a vessel); then ``loops`` anastomoses
    (straight tubes of 0.8 times the thinner radius, at least 1.5) join pairs of samples of
    different vessels whose walls are 2 to 12 voxels apart. Tubes are painted as balls every
    voxel along their centreline (a voxel is foreground when its centre is in a ball).
    The same seed always gives the same volume.
    """
    if size < 16:
        raise ValueError(f"size must be at least 16 voxels, got {size}")
    if not 0.0 < fraction < 0.5:
        raise ValueError(f"fraction must be in (0, 0.5), got {fraction}")
    if loops < 0:
        raise ValueError(f"loops must be non-negative, got {loops}")
    rng = np.random.default_rng(seed)
    mask = np.zeros((size, size, size), dtype=bool)
    target = fraction * mask.size
    centre = np.full(3, (size - 1) / 2.0)
    # The root: the thickest vessel, up to a fifth of the foreground, crossing the volume.
    root_length = min(3.0 * size, 0.2 * target / (np.pi * BED_MAX_RADIUS**2))
    points, radii = _bed_vessel(rng, centre, rng.normal(size=3), root_length, BED_MAX_RADIUS, size)
    vessel_of = np.zeros(len(points), dtype=np.int64)
    painted, vessels = 0, 1
    while True:
        _paint_balls(mask, points[painted:], radii[painted:])
        painted = len(points)
        foreground = np.count_nonzero(mask)
        if foreground >= target:
            break
        # Grow until the tubes' volumes (an overestimate: tubes overlap) cover the deficit,
        # or by an eighth, so that new vessels can also sprout from recent ones.
        new_p: list[FloatArray] = []
        new_r: list[FloatArray] = []
        new_v: list[IntArray] = []
        added = 0.0
        while foreground + added < target and len(new_p) < max(16, vessels // 8):
            # Sprouting toward random aims from the nearest sample spreads the bed over
            # the volume instead of thickening it around the root.
            r0 = BED_MIN_RADIUS * (BED_MAX_RADIUS / BED_MIN_RADIUS) ** (rng.uniform() ** 2)
            aim = rng.uniform(0, size - 1, size=3)
            near = rng.integers(len(points), size=min(len(points), 4096))
            near = near[radii[near] >= r0]
            if len(near) == 0:
                continue
            pick = near[np.argmin(np.sum((points[near] - aim) ** 2, axis=1))]
            heading = aim - points[pick]
            length = float(np.clip(np.linalg.norm(heading), 10 * r0, 30 * r0))
            p, r = _bed_vessel(rng, points[pick], heading, length, r0, size)
            new_p.append(p)
            new_r.append(r)
            new_v.append(np.full(len(p), vessels))
            vessels += 1
            added += BED_STEP * np.pi * float(np.sum(r * r))
        points = np.concatenate([points, *new_p])
        radii = np.concatenate([radii, *new_r])
        vessel_of = np.concatenate([vessel_of, *new_v])
    _paint_balls(mask, *_bed_anastomoses(rng, points, radii, vessel_of, loops))
    return mask


def _bed_anastomoses(
    rng: np.random.Generator,
    points: FloatArray,
    radii: FloatArray,
    vessel_of: IntArray,
    loops: int,
) -> tuple[FloatArray, FloatArray]:
    """Centreline samples of ``loops`` straight tubes joining pairs of distinct vessels."""
    centres, tube_radii = [np.empty((0, 3))], [np.empty(0)]
    made, tries = 0, 0
    while made < loops and tries < 100 * loops:
        tries += 1
        i = rng.integers(len(points))
        gap = np.linalg.norm(points - points[i], axis=1) - radii - radii[i]
        ok = np.flatnonzero((vessel_of != vessel_of[i]) & (gap > 2.0) & (gap < 12.0))
        if len(ok) == 0:
            continue
        j = rng.choice(ok)
        n = int(np.linalg.norm(points[j] - points[i]) / BED_STEP) + 2
        t = np.linspace(0.0, 1.0, n)[:, None]
        centres.append(points[i] + t * (points[j] - points[i]))
        r = max(BED_MIN_RADIUS, 0.8 * min(radii[i], radii[j]))
        tube_radii.append(np.full(n, r))
        made += 1
    return np.concatenate(centres), np.concatenate(tube_radii)
