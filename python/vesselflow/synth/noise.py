"""The paper authors' boundary "bubble" noise: :func:`add_bubble_noise`."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage

from vesselflow.synth._common import BoolArray, _check_spacing

#: Fraction of the (dilated, with ``dilate=True``) mask's boundary voxels that seed a bubble,
#: per noise level.
BUBBLE_LEVELS = {"D0": 0.005, "D1": 0.025, "D2": 0.075}


def add_bubble_noise(
    mask: ArrayLike,
    level: str | float,
    seed: int = 0,
    spacing: ArrayLike = (1.0, 1.0, 1.0),
    *,
    dilate: bool = False,
) -> BoolArray:
    """Boundary "bubble" noise, the recipe of the paper's ``D0``/``D1``/``D2`` sets.

    1. With ``dilate=True`` (the paper authors' code), dilate ``mask`` once with the
       6-connected structuring element first. That thickens every vessel by about one
       voxel, so a radius read faithfully off the noisy mask is about one voxel above the
       truth radius of the clean mask; the default (``False``, the paper's text: "bubbles
       on vessel boundaries") leaves the vessels as they are, so the truth radii still
       describe the noisy mask away from its bubbles.
    2. Seeds: ``round(fraction * B)`` of the ``B`` boundary voxels of the (dilated) mask
       (foreground voxels with a 6-neighbour in the background), drawn without replacement;
       ``fraction`` is :data:`BUBBLE_LEVELS` ``[level]`` (0.005, 0.025, 0.075 for D0, D1, D2)
       or ``level`` itself when it is a number in [0, 1].
    3. Stamp a ball of radius 2 voxels (physical radius ``2 * min(spacing)``, so an ellipsoid
       of voxels at anisotropic spacing) at every seed and take the union with the dilated mask.
    4. Fill holes: background 6-components that do not reach the border and have fewer than
       125 voxels become foreground.

    The result contains the (dilated) mask, hence ``mask``. The seeds are a prefix of one random
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
    dilated = ndimage.binary_dilation(m, structure=six) if dilate else m.copy()
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
