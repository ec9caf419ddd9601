"""Volumes in: read a 3-D vessel mask and its voxel spacing from the field's file formats.

Every reader goes through the format's own library (nibabel, tifffile, zarr, h5py,
SimpleITK), imported only when a file of that format is read; those libraries are the
``io`` extra (``pip install vesselflow[io]``). The mask comes back in the array axis
order of the file as its library returns it, with the spacing per array axis, so a
graph made from it has positions ``(i * s0, j * s1, k * s2)`` in the file's physical
units (millimetres for NIfTI and MetaImage/NRRD as a rule, micrometres for ImageJ and
OME files as a rule; vesselflow keeps whatever unit the file uses).
"""

from __future__ import annotations

import logging
import os
import xml.etree.ElementTree as ElementTree
from pathlib import Path
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from vesselflow.io import import_extra

logger = logging.getLogger(__name__)

Spacing = tuple[float, float, float]
"""Voxel size along array axes 0, 1, 2, in the file's physical units."""


class _VolumeError(ValueError):
    """A refusal whose message already names the file (not wrapped again)."""


def load_volume(
    path: str | os.PathLike[str],
    key: str | None = None,
    threshold: float | None = None,
    label: float | None = None,
) -> tuple[NDArray[np.bool_], Spacing]:
    """Read a 3-D mask and its voxel spacing (physical units per voxel, axes 0, 1, 2).

    The extension picks the reader:

    ``.npy``
        NumPy array; spacing ``(1, 1, 1)``.
    ``.npz``
        The array named ``key``; by default the only array, or the one named ``mask``.
        An array named ``spacing`` (3 numbers), if present, gives the spacing.
    ``.nii``, ``.nii.gz``
        NIfTI through nibabel, with ``scl_slope``/``scl_inter`` applied. The array is
        returned in the axis order in which it is stored (voxel axes i, j, k) and the
        spacing is the header's zooms for those axes (``pixdim[1:4]``, usually mm). No
        reorientation is applied: the affine (qform/sform) is ignored, so a graph's
        positions are voxel index times spacing, not scanner coordinates.
    ``.tif``, ``.tiff``
        A (multi-page) TIFF stack through tifffile, axes ``(z, y, x)``. Spacing from
        ImageJ metadata (``spacing`` for z, the X/YResolution tags for x and y) or from
        OME-XML physical sizes, when present; otherwise 1.
    ``.zarr``
        A Zarr array, or an OME-Zarr image (the array ``key``, by default the first,
        full-resolution, dataset of the first multiscale); spacing from its OME
        ``coordinateTransformations`` ``scale``, otherwise 1.
    ``.h5``, ``.hdf5``
        The HDF5 dataset ``key`` through h5py (by default the only dataset in the file);
        spacing from an ``element_size_um`` or ``spacing`` attribute of the dataset,
        otherwise 1.
    ``.mha``, ``.mhd``, ``.nrrd``
        MetaImage or NRRD through SimpleITK, axes ``(z, y, x)``; SimpleITK's spacing
        (given in x, y, z order) is reversed to match.

    Axes of length 1 beyond three (a NIfTI time axis, OME-Zarr ``t`` and ``c``) are
    dropped. A boolean array is the mask as is. Other data count as binary when
    integer data hold zero and at most one other value, or float data hold only 0 and 1;
    the mask is then the non-zero voxels. Anything else (a probability map, a label
    image) needs ``threshold`` (mask = data > threshold) or ``label`` (mask = data ==
    label), in the data's own values.

    Raises ``FileNotFoundError`` if ``path`` does not exist, ``ModuleNotFoundError``
    naming the ``io`` extra if the format's library is not installed, and ``ValueError``
    naming the file if it cannot be read as a 3-D volume of its format or is not binary.
    """
    path = Path(path)
    if threshold is not None and label is not None:
        raise ValueError("pass threshold= or label=, not both")
    reader = _READERS.get(_extension(path))
    if reader is None:
        supported = ", ".join(sorted(_READERS))
        raise ValueError(f"{path}: unsupported volume extension (supported: {supported})")
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or directory")
    try:
        data, spacing = reader(path, key)
    except (FileNotFoundError, ModuleNotFoundError, MemoryError, _VolumeError):
        raise
    except Exception as e:  # each library raises its own types for a corrupt file
        raise ValueError(f"{path}: not a readable {_extension(path)} volume: {e}") from e
    data = np.asarray(data)
    if data.ndim != 3:
        raise ValueError(f"{path}: expected a 3-D volume, got shape {data.shape}")
    return _binarise(data, path, threshold, label), _check_spacing(spacing, path)


def _extension(path: Path) -> str:
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def _binarise(
    data: NDArray[Any], path: Path, threshold: float | None, label: float | None
) -> NDArray[np.bool_]:
    if threshold is not None:
        return np.asarray(data > threshold)
    if label is not None:
        return np.asarray(data == label)
    if data.dtype == np.bool_:
        return data
    advice = (
        "pass threshold= (mask = data > threshold) or label= (mask = data == label) "
        "to say how to binarise it"
    )
    if data.dtype.kind in "iu":
        lo, hi = data.min(initial=0), data.max(initial=0)
        # Binary: one value throughout, or zero and one other value (lo or hi).
        if lo == hi or (
            (lo == 0 or hi == 0) and np.count_nonzero(data == (hi or lo)) == np.count_nonzero(data)
        ):
            return np.asarray(data != 0)
        raise _VolumeError(
            f"{path}: not a binary mask: {data.dtype} values from {lo} to {hi} "
            f"with more than one non-zero value; {advice}"
        )
    if data.dtype.kind == "f":
        if np.all((data == 0) | (data == 1)):
            return np.asarray(data == 1)
        raise _VolumeError(
            f"{path}: not a binary mask: {data.dtype} values other than 0 and 1 "
            f"(from {np.nanmin(data)} to {np.nanmax(data)}); {advice}"
        )
    raise _VolumeError(f"{path}: data of dtype {data.dtype} cannot be a mask")


def _check_spacing(spacing: Any, path: Path) -> Spacing:
    values = [abs(float(s)) for s in np.asarray(spacing, dtype=np.float64).reshape(-1)]
    if len(values) != 3:
        raise _VolumeError(f"{path}: spacing {values} does not hold 3 numbers")
    for axis, s in enumerate(values):
        if not (np.isfinite(s) and s > 0):
            logger.warning("%s: spacing of axis %d is %s; using 1", path, axis, s)
            values[axis] = 1.0
    return values[0], values[1], values[2]


def _drop_unit_axes(data: Any, spatial_first: bool) -> Any:
    """Drop length-1 axes beyond three: trailing ones (NIfTI) or leading ones (OME, TIFF)."""
    order = range(data.ndim - 1, 2, -1) if spatial_first else range(data.ndim - 4, -1, -1)
    for axis in order:
        if data.ndim > 3 and data.shape[axis] == 1:
            data = data[(slice(None),) * axis + (0,)]
    return data


def _read_npy(path: Path, key: str | None) -> tuple[Any, Any]:
    return np.load(path, allow_pickle=False), (1.0, 1.0, 1.0)


def _read_npz(path: Path, key: str | None) -> tuple[Any, Any]:
    with np.load(path, allow_pickle=False) as npz:
        names = [name for name in npz.files if name != "spacing"]
        if key is None:
            key = "mask" if "mask" in names else names[0] if len(names) == 1 else None
        if key not in names:
            raise _VolumeError(
                f"{path}: choose the array with key= (arrays: {', '.join(npz.files)})"
            )
        spacing = npz["spacing"] if "spacing" in npz.files else (1.0, 1.0, 1.0)
        return npz[key], spacing


def _read_nifti(path: Path, key: str | None) -> tuple[Any, Any]:
    nib = import_extra("nibabel", "io")
    image = nib.load(path)
    data = _drop_unit_axes(np.asanyarray(image.dataobj), spatial_first=True)
    # Zooms are float32: read 0.3 back as the decimal that was meant, as the binary does.
    return data, [float(str(zoom)) for zoom in image.header.get_zooms()[:3]]


def _read_tiff(path: Path, key: str | None) -> tuple[Any, Any]:
    tifffile = import_extra("tifffile", "io")
    with tifffile.TiffFile(path) as tif:
        data = _drop_unit_axes(tif.series[0].asarray(), spatial_first=False)
        spacing = [1.0, 1.0, 1.0]
        if tif.is_imagej and tif.imagej_metadata:
            page = tif.pages[0]
            spacing[0] = float(tif.imagej_metadata.get("spacing", 1.0))
            for axis, tag in ((1, "YResolution"), (2, "XResolution")):
                if tag in page.tags:
                    pixels, unit = page.tags[tag].value
                    spacing[axis] = unit / pixels
        elif tif.is_ome and tif.ome_metadata:
            spacing = _ome_tiff_spacing(tif.ome_metadata)
        return data, spacing


def _ome_tiff_spacing(ome_xml: str) -> list[float]:
    """PhysicalSizeZ/Y/X of the first OME ``Pixels`` element (1 where absent)."""
    for element in ElementTree.fromstring(ome_xml).iter():
        if element.tag.endswith("}Pixels") or element.tag == "Pixels":
            return [float(element.get(f"PhysicalSize{axis}", 1.0)) for axis in "ZYX"]
    return [1.0, 1.0, 1.0]


def _read_zarr(path: Path, key: str | None) -> tuple[Any, Any]:
    zarr = import_extra("zarr", "io")
    node = zarr.open(str(path), mode="r")
    if not hasattr(node, "shape"):  # a group: OME-Zarr (0.4 in attributes, 0.5 under "ome")
        attrs = dict(node.attrs)
        multiscales = attrs.get("multiscales") or attrs.get("ome", {}).get("multiscales")
        if not multiscales:
            if key is None:
                raise _VolumeError(f"{path}: a Zarr group without OME metadata: pass key=")
            return _zarr_array(node[key], path), (1.0, 1.0, 1.0)
        datasets = multiscales[0]["datasets"]
        paths = [d["path"] for d in datasets]
        if key is not None and key not in paths:
            raise _VolumeError(f"{path}: no dataset {key!r} (datasets: {', '.join(paths)})")
        dataset = datasets[0 if key is None else paths.index(key)]
        spacing = np.ones(len(multiscales[0].get("axes", [])) or 3)
        for transform in dataset.get("coordinateTransformations", []):
            if transform.get("type") == "scale":
                spacing = np.asarray(transform["scale"], dtype=np.float64)
        array = _zarr_array(node[dataset["path"]], path)
        return _drop_unit_axes(array, spatial_first=False), spacing[-3:]
    return _zarr_array(node, path), (1.0, 1.0, 1.0)


def _zarr_array(array: Any, path: Path) -> Any:
    return _drop_unit_axes(np.asarray(array[...]), spatial_first=False)


def _read_hdf5(path: Path, key: str | None) -> tuple[Any, Any]:
    h5py = import_extra("h5py", "io")
    with h5py.File(path, "r") as f:
        if key is None:
            names: list[str] = []
            f.visititems(lambda name, obj: names.append(name) if hasattr(obj, "shape") else None)
            if len(names) != 1:
                raise _VolumeError(
                    f"{path}: choose the dataset with key= (datasets: {', '.join(names)})"
                )
            key = names[0]
        if key not in f:
            raise _VolumeError(f"{path}: no dataset {key!r}")
        dataset = f[key]
        spacing: Any = (1.0, 1.0, 1.0)
        for attr in ("element_size_um", "spacing"):
            if attr in dataset.attrs:
                spacing = dataset.attrs[attr]
                break
        return dataset[...], spacing


def _read_sitk(path: Path, key: str | None) -> tuple[Any, Any]:
    sitk = import_extra("SimpleITK", "io")
    image = sitk.ReadImage(str(path))
    return sitk.GetArrayFromImage(image), tuple(reversed(image.GetSpacing()))


_READERS: dict[str, Callable[[Path, str | None], tuple[Any, Any]]] = {
    ".npy": _read_npy,
    ".npz": _read_npz,
    ".nii": _read_nifti,
    ".nii.gz": _read_nifti,
    ".tif": _read_tiff,
    ".tiff": _read_tiff,
    ".zarr": _read_zarr,
    ".h5": _read_hdf5,
    ".hdf5": _read_hdf5,
    ".mha": _read_sitk,
    ".mhd": _read_sitk,
    ".nrrd": _read_sitk,
}

__all__ = ["Spacing", "load_volume"]
