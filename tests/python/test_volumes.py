"""Volumes in: load_volume reads each format's mask and spacing through its own library."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest

from vesselflow import VolumeError, load_volume


@pytest.fixture
def mask() -> np.ndarray:
    """A random bool mask with three different side lengths: any axis swap shows."""
    return np.random.default_rng(3).random((4, 5, 6)) < 0.4


def check(path: Path, mask: np.ndarray, spacing: tuple[float, float, float], **kw: object) -> None:
    loaded, loaded_spacing = load_volume(path, **kw)  # type: ignore[arg-type]
    assert loaded.dtype == np.bool_
    np.testing.assert_array_equal(loaded, mask)
    np.testing.assert_allclose(loaded_spacing, spacing, rtol=1e-6)


def test_npy_bool_and_integer(tmp_path: Path, mask: np.ndarray) -> None:
    np.save(tmp_path / "b.npy", mask)
    check(tmp_path / "b.npy", mask, (1, 1, 1))
    np.save(tmp_path / "u.npy", mask.astype(np.uint8) * 255)
    check(tmp_path / "u.npy", mask, (1, 1, 1))
    np.save(tmp_path / "neg.npy", -mask.astype(np.int16))
    check(tmp_path / "neg.npy", mask, (1, 1, 1))
    np.save(tmp_path / "empty.npy", np.zeros((2, 3, 4), np.int32))
    check(tmp_path / "empty.npy", np.zeros((2, 3, 4), bool), (1, 1, 1))


def test_npz_key_default_and_spacing(tmp_path: Path, mask: np.ndarray) -> None:
    np.savez(tmp_path / "one.npz", seg=mask, spacing=[0.5, 1, 2])
    check(tmp_path / "one.npz", mask, (0.5, 1, 2))
    np.savez(tmp_path / "two.npz", mask=mask, other=~mask)
    check(tmp_path / "two.npz", mask, (1, 1, 1))
    check(tmp_path / "two.npz", ~mask, (1, 1, 1), key="other")
    np.savez(tmp_path / "many.npz", a=mask, b=mask)
    with pytest.raises(ValueError, match=r"many\.npz.*key="):
        load_volume(tmp_path / "many.npz")


@pytest.mark.parametrize("name", ["m.nii", "m.nii.gz"])
def test_nifti_spacing_from_zooms_in_stored_axis_order(
    tmp_path: Path, mask: np.ndarray, name: str
) -> None:
    nib = pytest.importorskip("nibabel")
    # An oblique affine: it must not reorder or flip the array.
    affine = np.array([[0, 0, -2.0, 10], [0.3, 0, 0, 0], [0, 0.5, 0, 0], [0, 0, 0, 1]])
    image = nib.Nifti1Image(mask.astype(np.uint8), affine)
    image.header.set_zooms((0.3, 0.5, 2.0))
    nib.save(image, tmp_path / name)
    loaded, spacing = load_volume(tmp_path / name)
    np.testing.assert_array_equal(loaded, mask)
    assert spacing == (0.3, 0.5, 2.0)  # the decimals meant, not their float32 values


def test_nifti_trailing_unit_axis_is_dropped_and_scaling_applied(
    tmp_path: Path, mask: np.ndarray
) -> None:
    nib = pytest.importorskip("nibabel")
    image = nib.Nifti1Image(mask[..., None].astype(np.int16) * 2, np.diag([1.0, 2, 3, 1]))
    image.header.set_slope_inter(0.5, 0)
    nib.save(image, tmp_path / "t.nii")
    check(tmp_path / "t.nii", mask, (1, 2, 3))


def test_tiff_imagej_spacing_from_spacing_and_resolution(tmp_path: Path, mask: np.ndarray) -> None:
    tifffile = pytest.importorskip("tifffile")
    path = tmp_path / "stack.tif"
    tifffile.imwrite(
        path,
        mask.astype(np.uint8) * 255,
        imagej=True,
        resolution=(1 / 0.25, 1 / 0.5),  # pixels per unit along x, y
        metadata={"spacing": 2.0, "unit": "um", "axes": "ZYX"},
    )
    check(path, mask, (2.0, 0.5, 0.25))


def test_tiff_ome_physical_sizes(tmp_path: Path, mask: np.ndarray) -> None:
    tifffile = pytest.importorskip("tifffile")
    path = tmp_path / "stack.ome.tiff"
    tifffile.imwrite(
        path,
        mask.astype(np.uint16),
        ome=True,
        metadata={"axes": "ZYX", "PhysicalSizeZ": 3.0, "PhysicalSizeY": 0.7, "PhysicalSizeX": 0.2},
    )
    check(path, mask, (3.0, 0.7, 0.2))


def test_tiff_without_metadata_has_unit_spacing(tmp_path: Path, mask: np.ndarray) -> None:
    tifffile = pytest.importorskip("tifffile")
    tifffile.imwrite(tmp_path / "plain.tif", mask.astype(np.uint8), photometric="minisblack")
    check(tmp_path / "plain.tif", mask, (1, 1, 1))


def test_zarr_array(tmp_path: Path, mask: np.ndarray) -> None:
    zarr = pytest.importorskip("zarr", minversion="3")
    zarr.save_array(str(tmp_path / "m.zarr"), mask.astype(np.uint8))
    check(tmp_path / "m.zarr", mask, (1, 1, 1))


@pytest.mark.parametrize("version", ["0.4", "0.5"])
def test_ome_zarr_scale_and_unit_axes(tmp_path: Path, mask: np.ndarray, version: str) -> None:
    zarr = pytest.importorskip("zarr", minversion="3")
    path = tmp_path / "image.ome.zarr"
    group = zarr.open_group(str(path), mode="w", zarr_format=2 if version == "0.4" else 3)
    group.create_array("0", data=mask[None, None].astype(np.uint8))
    group.create_array("1", data=mask[None, None, ::2, ::2, ::2].astype(np.uint8))
    axes = [{"name": n} for n in "tczyx"]
    multiscales = [
        {
            "version": version,
            "axes": axes,
            "datasets": [
                {
                    "path": "0",
                    "coordinateTransformations": [{"type": "scale", "scale": [1, 1, 4, 0.5, 0.25]}],
                },
                {
                    "path": "1",
                    "coordinateTransformations": [{"type": "scale", "scale": [1, 1, 8, 1, 0.5]}],
                },
            ],
        }
    ]
    if version == "0.4":
        group.attrs["multiscales"] = multiscales
    else:
        group.attrs["ome"] = {"version": version, "multiscales": multiscales}
    check(path, mask, (4, 0.5, 0.25))
    check(path, mask[::2, ::2, ::2], (8, 1, 0.5), key="1")


def test_ome_zarr_affine_has_scale_then_translation_then_the_multiscale_transform(
    tmp_path: Path, mask: np.ndarray
) -> None:
    # OME-NGFF: a dataset's scale and translation apply first, then the multiscale's own.
    zarr = pytest.importorskip("zarr", minversion="3")
    path = tmp_path / "image.ome.zarr"
    group = zarr.open_group(str(path), mode="w", zarr_format=2)
    group.create_array("0", data=mask[None].astype(np.uint8))
    group.attrs["multiscales"] = [
        {
            "version": "0.4",
            "axes": [{"name": n} for n in "czyx"],
            "datasets": [
                {
                    "path": "0",
                    "coordinateTransformations": [
                        {"type": "scale", "scale": [1, 4, 0.5, 0.25]},
                        {"type": "translation", "translation": [0, 10, -2, 3]},
                    ],
                }
            ],
            "coordinateTransformations": [{"type": "scale", "scale": [1, 2, 2, 2]}],
        }
    ]
    loaded, spacing, affine = load_volume(path, return_affine=True)
    assert np.array_equal(loaded, mask)
    assert spacing == (8.0, 1.0, 0.5)
    index = np.array([3.0, 5.0, 7.0, 1.0])
    expected = 2 * (index[:3] * [4, 0.5, 0.25] + [10, -2, 3])
    assert np.allclose(affine @ index, [*expected, 1.0])
    group.attrs["multiscales"] = [
        {
            **group.attrs["multiscales"][0],
            "coordinateTransformations": [{"type": "scale", "scale": [1, 2]}],
        }
    ]
    with pytest.raises(VolumeError, match="OME scale"):
        load_volume(path)


def test_hdf5_dataset_key_and_spacing_attribute(tmp_path: Path, mask: np.ndarray) -> None:
    h5py = pytest.importorskip("h5py")
    path = tmp_path / "m.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("seg/vessels", data=mask)
        f["seg/vessels"].attrs["element_size_um"] = [2.0, 0.4, 0.4]
    check(path, mask, (2.0, 0.4, 0.4))
    with h5py.File(path, "a") as f:
        f.create_dataset("raw", data=mask.astype(np.uint8))
        f["raw"].attrs["spacing"] = [1.0, 3.0, 5.0]
    check(path, mask, (1, 3, 5), key="raw")
    with pytest.raises(ValueError, match=r"m\.h5.*key=.*raw.*seg/vessels"):
        load_volume(path)
    with pytest.raises(ValueError, match="'nope'"):
        load_volume(path, key="nope")


@pytest.mark.parametrize("ext", [".mha", ".mhd", ".nrrd"])
def test_simpleitk_spacing_is_reversed_to_array_axis_order(
    tmp_path: Path, mask: np.ndarray, ext: str
) -> None:
    sitk = pytest.importorskip("SimpleITK")
    image = sitk.GetImageFromArray(mask.astype(np.uint8))  # array axes (z, y, x)
    image.SetSpacing((0.25, 0.5, 3.0))  # x, y, z
    sitk.WriteImage(image, str(tmp_path / f"m{ext}"))
    check(tmp_path / f"m{ext}", mask, (3.0, 0.5, 0.25))


def test_non_binary_data_needs_threshold_or_label(tmp_path: Path, mask: np.ndarray) -> None:
    probability = np.where(mask, 0.9, 0.1)
    np.save(tmp_path / "p.npy", probability)
    with pytest.raises(ValueError, match=r"p\.npy.*not a binary mask.*threshold=.*label=") as e:
        load_volume(tmp_path / "p.npy")
    assert re.search(r"float64 values other than 0 and 1 \(e\.g\. 0\.[19]\)", str(e.value))
    check(tmp_path / "p.npy", mask, (1, 1, 1), threshold=0.5)

    labels = mask.astype(np.uint8) * 3
    labels[0] = 7
    np.save(tmp_path / "l.npy", labels)
    with pytest.raises(ValueError, match=r"uint8 values 0, 7 and 3 \(at least two non-zero"):
        load_volume(tmp_path / "l.npy")
    expected = mask.copy()
    expected[0] = False
    check(tmp_path / "l.npy", expected, (1, 1, 1), label=3)
    check(tmp_path / "l.npy", labels > 0, (1, 1, 1), threshold=0)
    with pytest.raises(ValueError, match="not both"):
        load_volume(tmp_path / "l.npy", threshold=1, label=3)

    np.save(tmp_path / "f.npy", mask.astype(np.float32))
    check(tmp_path / "f.npy", mask, (1, 1, 1))
    np.save(tmp_path / "f2.npy", mask * 2.0)
    with pytest.raises(ValueError, match="other than 0 and 1"):
        load_volume(tmp_path / "f2.npy")


def test_missing_file_unsupported_extension_and_wrong_shape(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"absent\.nii\.gz"):
        load_volume(tmp_path / "absent.nii.gz")
    (tmp_path / "m.png").write_bytes(b"")
    with pytest.raises(ValueError, match=r"m\.png.*unsupported.*\.zarr"):
        load_volume(tmp_path / "m.png")
    np.save(tmp_path / "flat.npy", np.zeros((3, 4), bool))
    with pytest.raises(ValueError, match=r"flat\.npy.*3-D.*\(3, 4\)"):
        load_volume(tmp_path / "flat.npy")


@pytest.mark.parametrize(
    ("name", "module"),
    [
        ("c.npy", "numpy"),
        ("c.npz", "numpy"),
        ("c.nii", "nibabel"),
        ("c.nii.gz", "nibabel"),
        ("c.tif", "tifffile"),
        ("c.h5", "h5py"),
        ("c.mha", "SimpleITK"),
        ("c.nrrd", "SimpleITK"),
    ],
)
def test_corrupt_file_is_refused_naming_it(tmp_path: Path, name: str, module: str) -> None:
    pytest.importorskip(module)
    path = tmp_path / name
    path.write_bytes(b"this is not a volume file, just some bytes" * 10)
    with pytest.raises(ValueError, match=name.replace(".", r"\.")):
        load_volume(path)


@pytest.mark.parametrize(
    ("name", "module"),
    [
        ("m.nii", "nibabel"),
        ("m.tif", "tifffile"),
        ("m.zarr", "zarr"),
        ("m.h5", "h5py"),
        ("m.nrrd", "SimpleITK"),
    ],
)
def test_missing_library_names_the_extra(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str, module: str
) -> None:
    (tmp_path / name).write_bytes(b"")
    monkeypatch.setitem(sys.modules, module, None)
    with pytest.raises(ModuleNotFoundError, match=rf"{module}.*pip install vesselflow\[io\]"):
        load_volume(tmp_path / name)
