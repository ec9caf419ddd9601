"""The command line reads ``.npz`` masks (our data's format) as ``load_volume`` does:
the array ``mask`` (or ``--key``), the archive's ``spacing``, the one input rule."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import vesselflow
from graph_files import assert_same_graph
from vesselflow import _core, load_graph


def tube() -> np.ndarray:
    mask = np.zeros((30, 16, 16), dtype=np.float32)  # float 0/1: a mask by the input rule
    mask[3:27, 5:11, 4:12] = 1.0
    return mask


def run(*args: str) -> int:
    return _core.cli_main(["vesselflow", "skeletonize", *args, "-q"])


def test_cli_graph_of_an_npz_equals_the_python_graph(tmp_path: Path) -> None:
    path = tmp_path / "vessels.npz"
    np.savez_compressed(path, mask=tube(), spacing=np.array([2.0, 0.5, 0.75]), other=np.arange(3))
    assert run(str(path), "-o", str(tmp_path / "cli.json")) == 0
    cli = load_graph(tmp_path / "cli.json")
    mask, spacing = vesselflow.load_volume(path)
    python = vesselflow.skeletonize(mask, spacing)
    np.testing.assert_array_equal(cli.spacing, [2.0, 0.5, 0.75])
    assert cli.n_nodes > 5
    assert_same_graph(cli, python)


def test_cli_npz_key_chooses_among_arrays(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "two.npz"
    np.savez(path, first=tube(), second=tube()[:, :, ::-1].copy())
    assert run(str(path), "-o", str(tmp_path / "g.json")) == 1
    err = capfd.readouterr().err
    assert "two.npz" in err
    assert "--key" in err
    assert "first, second" in err
    assert not (tmp_path / "g.json").exists()
    assert run(str(path), "-o", str(tmp_path / "g.json"), "--key", "second") == 0
    second = load_graph(tmp_path / "g.json")
    expected = vesselflow.skeletonize(tube()[:, :, ::-1].copy())
    assert_same_graph(second, expected)
