"""Radii of whole pipeline runs against analytic tubes (issue 15, item 3).

The estimator itself is tested band by band in ``tests/radius.rs``; here the graph that
``skeletonize`` returns must carry it: straight tubes drawn by both rasterisation
conventions (``supersample=1``: a voxel is set when its centre is inside; ``3``: when half
of its sub-samples are), along an axis and oblique, at unit and anisotropic spacing.
"""

from __future__ import annotations

import numpy as np
import pytest

import vesselflow
from vesselflow import synth


@pytest.mark.parametrize("supersample", [1, 3])
@pytest.mark.parametrize(
    ("spacing", "oblique"),
    [((1.0, 1.0, 1.0), False), ((1.0, 1.0, 1.0), True), ((1.5, 1.0, 1.0), False)],
)
def test_a_straight_tube_of_radius_5_has_its_radius_within_3_percent(
    supersample: int, spacing: tuple[float, float, float], oblique: bool
) -> None:
    shape = (48, 32, 32) if spacing[0] == 1.0 else (32, 32, 32)
    start = end = None
    if oblique:
        start, end = (7.0, 9.0, 11.5), (40.0, 22.3, 19.0)
    mask, truth = synth.cylinder(
        shape, radius=5.0, spacing=spacing, start=start, end=end, supersample=supersample
    )
    graph = vesselflow.skeletonize(mask, spacing)
    # The path's inner nodes, one radius and more from the caps.
    a, b = truth.positions[0], truth.positions[-1]
    axis = (b - a) / np.linalg.norm(b - a)
    along = (graph.positions - a) @ axis
    inner = (along > 5.0) & (along < np.linalg.norm(b - a) - 5.0)
    assert inner.sum() >= 5
    median = float(np.median(graph.radii[inner]))
    assert median == pytest.approx(5.0, rel=0.03)
