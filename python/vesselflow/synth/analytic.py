"""Analytic shapes: :func:`cylinder`, :func:`torus`, :func:`y_bifurcation`, :func:`helix`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from vesselflow.graph import VesselGraph
from vesselflow.synth._common import (
    BoolArray,
    FloatArray,
    _check_int,
    _check_positive,
    _check_shape,
    _check_spacing,
    _extent,
    _polyline_graph,
    _rasterise,
    _samples_between,
)


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
