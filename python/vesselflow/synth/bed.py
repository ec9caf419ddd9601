"""The benchmark beds of ``benches/performance.py``: :func:`vascular_bed` (mask only)."""

from __future__ import annotations

import numpy as np

from vesselflow.synth._common import BoolArray, FloatArray, IntArray, _paint_round_cones

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
