"""Volumes too large for memory: refused from their header, before the data are read, with
a message that says what needs how much, how much there is and what to do."""

from __future__ import annotations

import gzip
import re
from pathlib import Path

import numpy as np
import pytest

import vesselflow
import vesselflow.volumes
from vesselflow import VolumeError, load_volume

GIB = 2**30


def test_a_nifti_declaring_4_gib_is_refused_from_its_header(tmp_path: Path) -> None:
    nib = pytest.importorskip("nibabel")
    header = nib.Nifti1Header()
    header.set_data_shape((2048, 2048, 1024))
    header.set_data_dtype(np.uint8)
    path = tmp_path / "big.nii.gz"
    # The header and a few bytes of data: the file inflates to far less than it declares.
    with gzip.open(path, "wb") as f:
        f.write(header.binaryblock + b"\0" * 4 + b"\1" * 1000)
    with pytest.raises(MemoryError) as caught:
        load_volume(path, max_memory=GIB)
    message = str(caught.value)
    assert message.startswith(f"{path}: declares a 2048x2048x1024 uint8 volume (4.0 GiB)")
    assert "needs about 12.0 GiB, 1.0 GiB available" in message
    assert "chunked run" in message
    assert "max_memory=" in message


def test_the_limit_defaults_to_the_memory_available(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    np.save(tmp_path / "m.npy", np.zeros((64, 64, 64), np.uint16))  # 0.5 MiB, 1 MiB as a mask
    monkeypatch.setattr(vesselflow.volumes, "_available_memory", lambda: 2**20 - 1)
    with pytest.raises(MemoryError, match=r"m\.npy: declares a 64x64x64 uint16 .* 1\.0 MiB avai"):
        load_volume(tmp_path / "m.npy")
    monkeypatch.setattr(vesselflow.volumes, "_available_memory", lambda: None)  # unknown
    mask, _ = load_volume(tmp_path / "m.npy")
    assert mask.shape == (64, 64, 64)


@pytest.mark.parametrize("name", ["m.npy", "m.npz", "m.tif", "m.h5", "m.zarr", "m.nrrd"])
def test_every_format_checks_the_declared_size(tmp_path: Path, name: str) -> None:
    data = np.zeros((40, 50, 60), np.uint8)
    path = tmp_path / name
    if name.endswith(".npy"):
        np.save(path, data)
    elif name.endswith(".npz"):
        np.savez(path, mask=data)
    elif name.endswith(".tif"):
        pytest.importorskip("tifffile").imwrite(path, data)
    elif name.endswith(".h5"):
        with pytest.importorskip("h5py").File(path, "w") as f:
            f["mask"] = data
    elif name.endswith(".zarr"):
        pytest.importorskip("zarr").save_array(str(path), data)
    else:
        sitk = pytest.importorskip("SimpleITK")
        sitk.WriteImage(sitk.GetImageFromArray(data), str(path))
    # 120 000 voxels of 1 byte, plus 2 bytes each for the mask and a temporary.
    needed = 40 * 50 * 60 * 3
    with pytest.raises(MemoryError, match=re.escape(f"{path}: declares a 40x50x60 uint8")):
        load_volume(path, max_memory=needed - 1)
    mask, _ = load_volume(path, max_memory=needed)
    assert mask.shape == (40, 50, 60)


def test_a_memory_error_without_a_message_gets_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    np.save(tmp_path / "m.npy", np.zeros((4, 5, 6), bool))

    def inflate(*args: object, **kwargs: object) -> None:
        raise MemoryError()

    monkeypatch.setattr(vesselflow.volumes.np, "load", inflate)
    with pytest.raises(MemoryError) as caught:
        load_volume(tmp_path / "m.npy", max_memory=10 * GIB)
    message = str(caught.value)
    assert message.startswith(f"{tmp_path / 'm.npy'}: ran out of memory reading the volume")
    assert "declares a 4x5x6 bool volume" in message
    assert "10.0 GiB available" in message
    assert "chunked run" in message


def test_volume_error_is_public_and_a_value_error(tmp_path: Path) -> None:
    np.save(tmp_path / "labels.npy", np.arange(60).reshape(3, 4, 5))
    with pytest.raises(vesselflow.VolumeError, match=r"labels\.npy: not a binary mask"):
        load_volume(tmp_path / "labels.npy")
    assert issubclass(VolumeError, ValueError)
    assert "VolumeError" in vesselflow.__all__
    (tmp_path / "bad.npy").write_bytes(b"garbage")
    with pytest.raises(VolumeError, match=r"bad\.npy: not a readable \.npy volume"):
        load_volume(tmp_path / "bad.npy")


def test_available_memory_is_positive_where_known() -> None:
    available = vesselflow.volumes._available_memory()
    assert available is None or available > 0
