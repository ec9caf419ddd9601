"""Helpers shared by the generators: argument checks, the round-cone rasteriser, the Betti
numbers of a mask and polyline truth graphs."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

#: Upper bound on the voxels (times sub-samples) evaluated in one vectorised batch.
_BATCH_ELEMENTS = 1 << 20
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
