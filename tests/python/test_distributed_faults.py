"""A chunked run that loses a worker process mid-run completes with the same graph.

Its own LocalCluster (2 worker processes under nannies), so the killed worker does not
disturb the other distributed tests' cluster."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest

from vesselflow import distributed as vd

dask_distributed = pytest.importorskip("distributed", reason="needs the dask extra")
pytest.importorskip("zarr", reason="needs the dask extra")


def _torus(shape: tuple[int, int, int] = (24, 72, 72)) -> np.ndarray:
    i, j, k = np.indices(shape).astype(float)
    i, j, k = i - 11.5, j - 35.5, k - 35.5
    return (np.hypot(j, k) - 24) ** 2 + i**2 <= 16


@pytest.mark.parametrize("workdir", [False, True], ids=["in-memory", "workdir"])
def test_a_worker_killed_mid_run_does_not_change_the_graph(workdir: bool, tmp_path: Path) -> None:
    mask = _torus()
    with (
        dask_distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        dask_distributed.Client(cluster) as client,
    ):
        reference = vd.skeletonize(mask, chunks=24, client=client)
        pids: dict[str, int] = client.run(os.getpid)
        victim = pids[sorted(pids)[0]]
        killed: list[int] = []

        def kill_after_first_block(done: int, total: int) -> None:
            if done == 1 and not killed:
                os.kill(victim, signal.SIGKILL)
                killed.append(total)

        g = vd.skeletonize(
            mask,
            chunks=24,
            client=client,
            workdir=tmp_path / "w" if workdir else None,
            progress=kill_after_first_block,
        )
        # The nanny started a new worker process in place of the killed one.
        assert victim not in client.run(os.getpid).values()
    assert killed
    assert killed[0] == reference.info["blocks"] - reference.info["blocks_empty"] > 2
    for x, y in [
        (reference.positions, g.positions),
        (reference.radii, g.radii),
        (reference.edges, g.edges),
    ]:
        assert np.array_equal(x, y)
    assert g.info["blocks_computed"] + g.info["blocks_reused"] == killed[0]
