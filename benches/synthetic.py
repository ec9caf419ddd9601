"""Synthetic vascular beds for the benchmarks.

``vascular_bed(size, seed)`` returns a cubic boolean mask of about 5 % foreground: a
connected tree of random, gently curving tubes of radii 1.5 to 6 voxels, each new vessel
sprouting from a point of an existing one at least as thick, plus a few anastomoses (tubes
that join two different vessels and so close loops; crossing vessels close more). Vessels
bounce off walls kept a voxel beyond their surface, so no tube is cut by the border and the
bed is one 26-connected component. The same seed always gives the same volume.

Each tube is rasterised as a chain of balls along its centreline, computing distances only
inside each ball's small bounding cube, in vectorised batches: with numpy alone a 256^3 bed
takes about 1 s and a 512^3 one about 12 s (800 MB peak).

Run it to see a volume's figures::

    python benches/synthetic.py 256 --seed 0 [--out bed.npy]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from typing import BinaryIO, Callable

import numpy as np

#: Radius range of the tubes, in voxels.
MIN_RADIUS = 1.5
MAX_RADIUS = 6.0
#: Spacing of centreline samples, voxels: balls this close make a smooth tube (the
#: scallops between balls of radius 1.5 are 0.09 voxel deep, less for thicker ones).
STEP = 1.0
#: Upper bound on the elements of one ball-stencil batch (memory of the painter).
BATCH_ELEMENTS = 1 << 23


def _paint_balls(mask: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> None:
    """Set every voxel whose centre lies within ``radii[i]`` of ``centres[i]`` for some i.

    Balls are grouped by their stencil size ``ceil(r)`` and tested in batches, so only a
    small cube around each ball is ever looked at; the squared distance is a sum of three
    broadcast per-axis terms. Every ball must lie inside ``mask``.
    """
    flat = mask.reshape(-1)
    half = np.ceil(radii).astype(int)
    for h in np.unique(half):
        ax = np.arange(-h, h + 2, dtype=np.float32)
        pick = np.flatnonzero(half == h)
        per_batch = max(1, BATCH_ELEMENTS // len(ax) ** 3)
        for b in range(0, len(pick), per_batch):
            idx = pick[b : b + per_batch]
            base = np.floor(centres[idx]).astype(np.int64)
            # Per axis: (ball, offset) squared distances from the ball's centre.
            sq = [(ax[None, :] - (centres[idx, k] - base[:, k])[:, None]) ** 2 for k in range(3)]
            d2 = sq[0][:, :, None, None] + sq[1][:, None, :, None] + sq[2][:, None, None, :]
            r2 = (radii[idx] ** 2).astype(np.float32)[:, None, None, None]
            ball, i, j, k = np.nonzero(d2 <= r2)
            v = base[ball] + np.stack([i, j, k], axis=1) - h
            flat[np.ravel_multi_index(v.T, mask.shape)] = True


def _fold(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Reflect coordinates into ``[lo, hi]`` as a path bouncing off two walls would be.

    The triangle wave is continuous and keeps step lengths, so a folded path stays a
    smooth tube of the same length.
    """
    width = hi - lo
    return lo + width - np.abs(np.mod(x - lo, 2 * width) - width)


def _vessel(
    rng: np.random.Generator,
    start: np.ndarray,
    heading: np.ndarray,
    length: float,
    r0: float,
    size: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Centreline samples and radii of one vessel leaving ``start`` along ``heading``.

    It runs for ``length`` voxels; its radius starts at ``r0`` and tapers by up to 20 %;
    its direction wanders as a random walk (thin vessels wander more), and it bounces off
    walls kept one voxel beyond its surface.
    """
    r1 = max(MIN_RADIUS, r0 * rng.uniform(0.8, 1.0))
    n = max(2, int(length / STEP))
    kick = rng.normal(scale=0.25 * np.sqrt(STEP / r0), size=(n, 3))
    kick[0] = heading / max(float(np.linalg.norm(heading)), 1e-12)
    d = np.cumsum(kick, axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    path = start + np.concatenate([np.zeros((1, 3)), np.cumsum(STEP * d[1:], axis=0)])
    return _fold(path, r0 + 1.0, size - 2.0 - r0), np.linspace(r0, r1, n)


def vascular_bed(size: int, seed: int = 0, fraction: float = 0.05, loops: int = 4) -> np.ndarray:
    """A ``(size, size, size)`` boolean vascular bed with about ``fraction`` foreground.

    The root vessel (radius 6) starts at the centre of the volume. Each later vessel draws
    a radius in [1.5, 6] skewed toward thin ones (``1.5 * 4**(u**2)``, u uniform) and a
    random aim point, and sprouts toward the aim, for 10 to 30 radii, from the sample
    nearest the aim among 4096 random centreline samples at least as thick as itself.
    Vessels are added in rounds until the foreground reaches ``fraction`` (small volumes
    overshoot by up to a vessel); then ``loops`` anastomoses join pairs of different
    vessels whose walls are 2 to 12 voxels apart.
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
    root_length = min(3.0 * size, 0.2 * target / (np.pi * MAX_RADIUS**2))
    points, radii = _vessel(rng, centre, rng.normal(size=3), root_length, MAX_RADIUS, size)
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
        new_p, new_r, new_v, added = [], [], [], 0.0
        while foreground + added < target and len(new_p) < max(16, vessels // 8):
            # Sprouting toward random aims from the nearest sample spreads the bed over
            # the volume instead of thickening it around the root.
            r0 = MIN_RADIUS * (MAX_RADIUS / MIN_RADIUS) ** (rng.uniform() ** 2)
            aim = rng.uniform(0, size - 1, size=3)
            near = rng.integers(len(points), size=min(len(points), 4096))
            near = near[radii[near] >= r0]
            if len(near) == 0:
                continue
            pick = near[np.argmin(np.sum((points[near] - aim) ** 2, axis=1))]
            heading = aim - points[pick]
            length = np.clip(np.linalg.norm(heading), 10 * r0, 30 * r0)
            p, r = _vessel(rng, points[pick], heading, length, r0, size)
            new_p.append(p)
            new_r.append(r)
            new_v.append(np.full(len(p), vessels))
            vessels += 1
            added += STEP * np.pi * float(np.sum(r * r))
        points = np.concatenate([points, *new_p])
        radii = np.concatenate([radii, *new_r])
        vessel_of = np.concatenate([vessel_of, *new_v])
    _paint_balls(mask, *_anastomoses(rng, points, radii, vessel_of, loops))
    return mask


def _anastomoses(
    rng: np.random.Generator,
    points: np.ndarray,
    radii: np.ndarray,
    vessel_of: np.ndarray,
    loops: int,
) -> tuple[np.ndarray, np.ndarray]:
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
        n = int(np.linalg.norm(points[j] - points[i]) / STEP) + 2
        t = np.linspace(0.0, 1.0, n)[:, None]
        centres.append(points[i] + t * (points[j] - points[i]))
        r = max(MIN_RADIUS, 0.8 * min(radii[i], radii[j]))
        tube_radii.append(np.full(n, r))
        made += 1
    return np.concatenate(centres), np.concatenate(tube_radii)


def describe(mask: np.ndarray) -> tuple[float, int]:
    """Foreground fraction and number of 26-connected components of ``mask``."""
    try:
        import cc3d

        components = int(cc3d.connected_components(mask, connectivity=26, return_N=True)[1])
    except ImportError:
        from scipy import ndimage

        components = int(ndimage.label(mask, structure=np.ones((3, 3, 3)))[1])
    return float(np.count_nonzero(mask)) / mask.size, components


def write_atomic(path: str | os.PathLike[str], write: Callable[[BinaryIO], object]) -> None:
    """Create or replace ``path`` with what ``write`` puts in a binary file: first a temp
    file in the same folder, then a rename, so no reader ever sees a partial file."""
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # the mode open() would give, not mkstemp's 0600
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("size", type=int, help="edge of the cube, voxels")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fraction", type=float, default=0.05, help="target foreground")
    parser.add_argument("--loops", type=int, default=4, help="anastomoses to add")
    parser.add_argument("--out", help="write the mask here (.npy, bool)")
    args = parser.parse_args()
    t0 = time.perf_counter()
    try:
        mask = vascular_bed(args.size, args.seed, args.fraction, args.loops)
    except ValueError as e:
        parser.error(str(e))
    seconds = time.perf_counter() - t0
    frac, components = describe(mask)
    print(
        f"{args.size}^3 seed {args.seed}: {np.count_nonzero(mask)} foreground voxels "
        f"({100 * frac:.2f} %), {components} 26-connected component(s), "
        f"generated in {seconds:.1f} s"
    )
    if args.out:
        write_atomic(args.out, lambda f: np.save(f, mask))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
