"""Small analytic masks shared by the Python tests."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np
import pytest


def make_tube(shape: tuple[int, int, int] = (30, 15, 15), radius: float = 4.0) -> np.ndarray:
    """A straight bool cylinder along axis 0 through the centre of axes 1 and 2."""
    _, j, k = np.indices(shape)
    return (j - (shape[1] - 1) / 2) ** 2 + (k - (shape[2] - 1) / 2) ** 2 <= radius**2


def make_slow_tube() -> np.ndarray:
    """A thick tube with about 4 s of work on 2 cores, so that a signal sent at the
    first progress report lands mid-run even on a loaded machine."""
    return make_tube((400, 41, 41), 14.0)


def noisy_forests(seeds: Iterable[int]) -> Iterator[tuple[np.ndarray, Any]]:
    """Noisy (D2) 96³ forests of the second synthetic family and their truth graphs, one
    per seed (use seeds outside the fidelity benchmark's tuning and held-out sets)."""
    from vesselflow import synth

    for seed in seeds:
        mask, truth = synth.vascular_forest((96, 96, 96), seed=seed)
        yield synth.add_bubble_noise(mask, "D2", seed=seed), truth


def mean_rate(rows: list[dict[str, float]], key: str) -> float:
    """The mean of ``key`` over NetMets result rows."""
    return float(np.mean([r[key] for r in rows]))


@pytest.fixture
def tube() -> np.ndarray:
    """A straight tube of radius 4 along axis 0, shape (30, 15, 15)."""
    return make_tube()


@pytest.fixture
def branching() -> np.ndarray:
    """A T-shaped bool mask (trunk along axis 0, one branch along axis 2) in a box with
    three different side lengths: any mix-up of axes or strides changes the graph."""
    i, j, k = np.indices((40, 24, 30))
    trunk = (j - 11.5) ** 2 + (k - 9) ** 2 <= 9
    branch = ((i - 25) ** 2 + (j - 11.5) ** 2 <= 6.25) & (k >= 9)
    return trunk | branch


@pytest.fixture
def torus() -> np.ndarray:
    """A solid bool torus, major radius 12, minor 3.5, centred at (5.5, 17.5, 17.5)."""
    i, j, k = np.indices((12, 36, 36)).astype(float)
    return (np.hypot(j - 17.5, k - 17.5) - 12) ** 2 + (i - 5.5) ** 2 <= 3.5**2
