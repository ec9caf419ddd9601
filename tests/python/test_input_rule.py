"""One input rule for every entry point: the command line (``.npy``, ``.nii.gz``),
``skeletonize`` and ``load_volume`` accept the same masks, refuse the same images and
binarise them the same way with ``threshold=`` / ``label=``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

import vesselflow
from vesselflow import VesselGraph, _core, load_graph, load_volume

nib = pytest.importorskip("nibabel")

GAMMA = 0.1  # a quick run; every entry point gets the same parameters


def assert_same_graph(a: VesselGraph, b: VesselGraph) -> None:
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.radii, b.radii)
    np.testing.assert_array_equal(a.edges, b.edges)


def save(data: np.ndarray, path: Path) -> Path:
    if path.name.endswith(".nii.gz"):
        nib.save(nib.Nifti1Image(data, np.eye(4)), path)  # spacing 1, 1, 1
    else:
        np.save(path, data)
    return path


def cli(capfd: pytest.CaptureFixture[str], path: Path, *options: str) -> VesselGraph:
    """The graph of the command line on ``path``, or ``ValueError`` with its stderr."""
    out = path.with_name(path.name.split(".")[0] + "_graph.npz")
    argv = ["vesselflow", "skeletonize", str(path), "-o", str(out), "--gamma", str(GAMMA), "-q"]
    capfd.readouterr()
    if _core.cli_main([*argv, *options]) != 0:
        raise ValueError(capfd.readouterr().err)
    return load_graph(out)


def python(data: np.ndarray, **kw: Any) -> VesselGraph:
    return vesselflow.skeletonize(data, gamma=GAMMA, **kw)


def through_load_volume(path: Path, **kw: Any) -> VesselGraph:
    mask, spacing = load_volume(path, **kw)
    return python(mask, spacing=spacing)


ENTRY_POINTS = ["cli .npy", "cli .nii.gz", "skeletonize", "load_volume .npy", "load_volume .nii.gz"]


def run_on(
    entry: str, data: np.ndarray, tmp_path: Path, capfd: pytest.CaptureFixture[str], **kw: Any
) -> VesselGraph:
    """Run on ``data`` through ``entry`` (files in ``tmp_path``), with ``threshold=`` or
    ``label=`` in ``kw``."""
    if entry == "skeletonize":
        return python(data, **kw)
    path = save(data, tmp_path / ("data.npy" if entry.endswith(".npy") else "data.nii.gz"))
    if entry.startswith("cli"):
        return cli(capfd, path, *(f"--{name}={value}" for name, value in kw.items()))
    return through_load_volume(path, **kw)


def label_image(branching: np.ndarray) -> np.ndarray:
    """Labels 0 to 6: the T as label 3 except its top (label 6), and single voxels of
    labels 1, 2, 4 and 5 away from it."""
    labels = np.where(branching, 3, 0).astype(np.uint8)
    labels[:8][branching[:8]] = 6
    for n, label in enumerate((1, 2, 4, 5)):
        labels[2 + 3 * n, 1, 28] = label
    return labels


@pytest.mark.parametrize("entry", ENTRY_POINTS)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_float_mask_gives_the_same_graph_everywhere(branching, tmp_path, capfd, entry, dtype):
    graph = run_on(entry, branching.astype(dtype), tmp_path, capfd)
    assert_same_graph(graph, python(branching))


@pytest.mark.parametrize("entry", ENTRY_POINTS)
def test_label_image_is_refused_everywhere_naming_threshold_and_label(
    branching, tmp_path, capfd, entry
):
    refusal = r"uint8 values 0, \d and \d \(at least two non-zero values\).*threshold=.*label="
    with pytest.raises(ValueError, match=refusal):
        run_on(entry, label_image(branching), tmp_path, capfd)


@pytest.mark.parametrize("entry", ENTRY_POINTS)
def test_label_gives_the_graph_of_that_label_everywhere(branching, tmp_path, capfd, entry):
    labels = label_image(branching)
    expected = python(labels == 3)
    assert expected.n_nodes > 10
    assert_same_graph(run_on(entry, labels, tmp_path, capfd, label=3), expected)


@pytest.mark.parametrize("entry", ENTRY_POINTS)
def test_threshold_binarises_a_probability_map_everywhere(branching, tmp_path, capfd, entry):
    noise = np.random.default_rng(0).uniform(0, 0.4, branching.shape)
    probability = np.where(branching, 1 - noise, noise).astype(np.float32)
    with pytest.raises(ValueError, match=r"float32 values other than 0 and 1.*threshold="):
        run_on(entry, probability, tmp_path, capfd)
    graph = run_on(entry, probability, tmp_path, capfd, threshold=0.5)
    assert_same_graph(graph, python(branching))


@pytest.mark.parametrize("values", [[0.0, np.nan], [0.0, 0.5], [0.0, 2.0]])
def test_floats_other_than_0_and_1_are_refused(values):
    data = np.full((4, 4, 4), values[0])
    data[1:3, 1:3, 1:3] = values[1]
    with pytest.raises(ValueError, match=r"float64 values other than 0 and 1 .*threshold="):
        python(data)


def test_threshold_and_label_together_are_an_error(branching, tmp_path, capfd):
    with pytest.raises(ValueError, match="not both"):
        python(branching, threshold=0.5, label=1)
    with pytest.raises(ValueError, match="not both"):
        load_volume(save(branching, tmp_path / "m.npy"), threshold=0.5, label=1)
    with pytest.raises(ValueError, match="'--threshold <T>' cannot be used with '--label <V>'"):
        cli(capfd, tmp_path / "m.npy", "--threshold", "0.5", "--label", "1")


def test_bool_mask_is_used_without_a_copy_and_binarise_copies_the_rest(branching):
    assert _core.binarise(branching) is branching
    labels = label_image(branching)
    mask = _core.binarise(labels, label=6)
    assert mask.dtype == np.bool_
    np.testing.assert_array_equal(mask, labels == 6)
    np.testing.assert_array_equal(_core.binarise(branching, threshold=0), branching)


def test_a_byte_mask_of_zeros_and_ones_is_viewed_not_copied(branching):
    for dtype in (np.uint8, np.int8):
        data = branching.astype(dtype)
        mask = _core.binarise(data)
        assert mask.dtype == np.bool_
        assert np.shares_memory(mask, data), dtype
        np.testing.assert_array_equal(mask, branching)
        # The same graph as from the bool mask.
        assert_same_graph(vesselflow.skeletonize(data), vesselflow.skeletonize(branching))
    # Other vessel values, or a rule, make a new bool array of the mask.
    byte = branching.astype(np.uint8)
    for data, rule in ((byte * 255, {}), (byte, {"label": 1})):
        mask = _core.binarise(data, **rule)
        assert mask.dtype == np.bool_
        assert not np.shares_memory(mask, data)
        assert mask.view(np.uint8).max() == 1
        np.testing.assert_array_equal(mask, branching)
    # A label image of bytes is still refused.
    with pytest.raises(ValueError, match="label="):
        _core.binarise(label_image(branching).astype(np.uint8))


def test_scalar_spacing_is_isotropic(tube):
    expected = vesselflow.skeletonize(tube, spacing=(0.5, 0.5, 0.5))
    graph = vesselflow.skeletonize(tube, 0.5)
    assert_same_graph(graph, expected)
    assert graph.spacing.tolist() == [0.5, 0.5, 0.5]
    assert_same_graph(vesselflow.Skeletonizer().run(tube, np.float32(0.5)), expected)
    for bad in (0.0, -1.0, np.nan, np.inf, 1e13):
        with pytest.raises(ValueError, match="spacing"):
            vesselflow.skeletonize(tube, bad)


def test_unusable_file_spacing_is_an_error_and_spacing_replaces_it(tube, tmp_path):
    path = tmp_path / "flat.npz"
    np.savez(path, mask=tube, spacing=[1.0, 0.0, 1.0])
    with pytest.raises(ValueError, match=r"flat\.npz: the file's spacing .*spacing="):
        load_volume(path)
    mask, spacing = load_volume(path, spacing=0.5)
    assert spacing == (0.5, 0.5, 0.5)
    np.testing.assert_array_equal(mask, tube)
    assert load_volume(path, spacing=[1, 2, 3])[1] == (1.0, 2.0, 3.0)
    with pytest.raises(ValueError, match="3 numbers or one"):
        load_volume(path, spacing=(1.0, 2.0))
