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

import math
import os
import xml.etree.ElementTree as ElementTree
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import IO, Any, Callable, Literal, overload

import numpy as np
from numpy.typing import DTypeLike, NDArray

from vesselflow import _core
from vesselflow._util import import_extra, spacing_argument

Spacing = tuple[float, float, float]
"""Voxel size along array axes 0, 1, 2, in the file's physical units."""


class VolumeError(ValueError):
    """A volume file that cannot be used as a mask; the message names the file and the
    problem (unreadable, not 3-D, not binary, ambiguous key, ...)."""


GIB = 2**30

_MEMORY_ADVICE = (
    "free memory, crop or downsample the volume, or split it into blocks and run each "
    "(a chunked run); if more memory is free than detected, pass max_memory= (bytes)"
)


class _Budget:
    """The memory a volume may take: what a file declares is checked against it before
    the data are read, and an allocation that fails anyway is reported with it."""

    def __init__(self, path: Path, available: int | None) -> None:
        self.path = path
        self.available = available
        self.declared = ""
        self.refused = False

    def check(self, shape: Any, dtype: DTypeLike, converted_itemsize: int = 0) -> None:
        """Refuse (``MemoryError``) a ``shape`` x ``dtype`` array, plus a converted copy
        of ``converted_itemsize`` bytes per voxel, if it does not fit: with the mask and
        one boolean temporary, reading needs ``itemsize + converted + 2`` bytes a voxel."""
        shape = tuple(int(d) for d in shape)
        try:
            dtype = np.dtype(dtype)
        except TypeError:  # a library's own dtype object: count 8 bytes a voxel
            dtype = np.dtype(np.float64)
        voxels = math.prod(shape)
        data = voxels * dtype.itemsize
        needed = data + voxels * (converted_itemsize + 2)
        self.declared = (
            f"declares a {'x'.join(map(str, shape))} {dtype} volume ({_size(data)}); "
            f"reading it as a mask needs about {_size(needed)}"
        )
        if self.available is not None and needed > self.available:
            self.refused = True
            raise MemoryError(
                f"{self.path}: {self.declared}, {_size(max(self.available, 0))} available; "
                f"{_MEMORY_ADVICE}"
            )

    def check_npy(self, f: IO[bytes]) -> None:
        """:meth:`check` with the header of the ``.npy`` data in ``f``."""
        version = np.lib.format.read_magic(f)
        read_header = (
            np.lib.format.read_array_header_1_0
            if version == (1, 0)
            else np.lib.format.read_array_header_2_0
        )
        shape, _, dtype = read_header(f)
        self.check(shape, dtype)

    def out_of_memory(self, e: MemoryError) -> str:
        """The message for a ``MemoryError`` raised while reading: never empty."""
        if self.declared:
            what = f"it {self.declared}"
        else:
            try:
                what = f"the file holds {_size(self.path.stat().st_size)}"
            except OSError:
                what = "its size is unknown"
        available = "" if self.available is None else f", {_size(self.available)} available"
        detail = f" ({e})" if str(e) else ""
        return (
            f"{self.path}: ran out of memory reading the volume{detail}: {what}{available}; "
            f"{_MEMORY_ADVICE}"
        )


def _size(n: int) -> str:
    if n >= GIB // 10:
        return f"{n / GIB:.1f} GiB"
    return f"{n / 2**20:.1f} MiB" if n >= 2**20 // 10 else f"{n} bytes"


def _available_memory() -> int | None:
    """Bytes this process may still allocate (the core's rule, shared with
    ``max_memory="auto"``); None where the system does not tell."""
    return _core.usable_memory()


@overload
def load_volume(
    path: str | os.PathLike[str],
    key: str | None = ...,
    threshold: float | None = ...,
    label: float | None = ...,
    max_memory: int | None = ...,
    spacing: Sequence[float] | float | None = ...,
    return_affine: Literal[False] = ...,
) -> tuple[NDArray[np.bool_], Spacing]: ...


@overload
def load_volume(
    path: str | os.PathLike[str],
    key: str | None = ...,
    threshold: float | None = ...,
    label: float | None = ...,
    max_memory: int | None = ...,
    spacing: Sequence[float] | float | None = ...,
    *,
    return_affine: Literal[True],
) -> tuple[NDArray[np.bool_], Spacing, NDArray[np.float64]]: ...


def load_volume(
    path: str | os.PathLike[str],
    key: str | None = None,
    threshold: float | None = None,
    label: float | None = None,
    max_memory: int | None = None,
    spacing: Sequence[float] | float | None = None,
    return_affine: bool = False,
) -> tuple[NDArray[np.bool_], Spacing] | tuple[NDArray[np.bool_], Spacing, NDArray[np.float64]]:
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
        reorientation is applied; the voxel-to-world affine (the sform, else the
        qform, else the zooms) is returned with ``return_affine=True``.
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
    dropped. The data become a mask by the input rule that ``skeletonize`` and the
    command line apply too: a boolean array is the mask as is; integer data holding zero
    and at most one other value, or float data holding only 0 and 1, are binary and the
    mask is their non-zero voxels. Anything else (a probability map, a label image, NaN)
    needs ``threshold`` (mask = data > threshold) or ``label`` (mask = data == label), in
    the data's own values; passing both is a ``ValueError``.

    ``return_affine=True`` also returns the 4 x 4 voxel-to-world affine (array index
    ``(i, j, k, 1)`` to world ``(x, y, z, 1)``), for ``skeletonize(...,
    coordinates="world", affine=...)``: NIfTI's sform (``sform_code > 0``), else its
    qform (``qform_code > 0``), else the zooms on the diagonal, as the ``vesselflow``
    binary reads it; SimpleITK's origin, direction and spacing (LPS, columns in the
    array's axis order); the diagonal of the spacing for the other formats (``.npy``,
    ``.npz``, TIFF and HDF5; OME-Zarr gives its ``scale`` and ``translation``).

    ``spacing`` (3 numbers, or one for every axis) replaces the file's spacing; it is
    needed for a file whose spacing is not finite numbers > 0, which is an error.

    Before reading the data, the size the file declares (array shape and data type,
    from its header) is checked against ``max_memory`` bytes, by default the memory
    this process can still use (Linux: available memory, cgroup and address-space
    limits; no check where these are unknown).

    Raises ``FileNotFoundError`` if ``path`` does not exist, ``ModuleNotFoundError``
    naming the ``io`` extra if the format's library is not installed,
    :class:`VolumeError` (a ``ValueError``) naming the file if it cannot be read as a
    3-D volume of its format or is not binary, and ``MemoryError`` saying how much memory
    the volume needs and how much there is.

    Returns
    -------
    mask : (I, J, K) bool ndarray
        The vessel mask, axes as stored in the file.
    spacing : tuple of 3 floats
        Voxel size along axes 0, 1, 2.
    affine : (4, 4) float64 ndarray
        Only with ``return_affine=True``: the voxel-to-world affine.

    Examples
    --------
    >>> import tempfile, pathlib, numpy as np
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "m.npz"
    >>> np.savez(path, mask=np.ones((2, 3, 4), bool), spacing=np.array([2.0, 1.0, 0.5]))
    >>> mask, spacing, affine = load_volume(path, return_affine=True)
    >>> mask.shape, spacing, np.diag(affine).tolist()
    ((2, 3, 4), (2.0, 1.0, 0.5), [2.0, 1.0, 0.5, 1.0])
    """
    path = Path(path)
    if threshold is not None and label is not None:  # before reading anything
        raise ValueError("pass threshold= or label=, not both")
    given = None if spacing is None else spacing_argument(spacing)
    reader = _READERS.get(_extension(path))
    if reader is None:
        supported = ", ".join(sorted(_READERS))
        raise ValueError(f"{path}: unsupported volume extension (supported: {supported})")
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or directory")
    budget = _Budget(path, _available_memory() if max_memory is None else max_memory)
    try:
        data, file_spacing, *file_affine = reader(path, key, budget)
        data = np.asarray(data)
        if data.ndim != 3:
            raise VolumeError(f"{path}: expected a 3-D volume, got shape {data.shape}")
        mask = _binarise(data, path, threshold, label)
        voxel = given or _check_spacing(file_spacing, path)
        if not return_affine:
            return mask, voxel
        affine = np.asarray(file_affine[0], float) if file_affine else np.diag([*voxel, 1.0])
        return mask, voxel, affine
    except (FileNotFoundError, ModuleNotFoundError, VolumeError):
        raise
    except MemoryError as e:
        if budget.refused:
            raise
        raise MemoryError(budget.out_of_memory(e)) from e
    except Exception as e:  # each library raises its own types for a corrupt file
        problem = str(e) if isinstance(e, ValueError) and str(e) else f"{type(e).__name__}: {e}"
        raise VolumeError(f"{path}: not a readable {_extension(path)} volume: {problem}") from e


def _extension(path: Path) -> str:
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def _binarise(
    data: NDArray[Any], path: Path, threshold: float | None, label: float | None
) -> NDArray[np.bool_]:
    """The input rule (``vesselflow._core.binarise``, shared with ``skeletonize`` and the
    command line), its refusal naming the file."""
    try:
        return _core.binarise(data, threshold, label)
    except (ValueError, TypeError) as e:
        raise VolumeError(f"{path}: {e}") from e


def _check_spacing(spacing: Any, path: Path) -> Spacing:
    """The file's spacing, sign ignored; its range is checked by the run, as for any
    spacing."""
    values = [abs(float(s)) for s in np.asarray(spacing, dtype=np.float64).reshape(-1)]
    if len(values) != 3:
        raise VolumeError(f"{path}: spacing {values} does not hold 3 numbers")
    if not all(np.isfinite(s) and s > 0 for s in values):
        raise VolumeError(
            f"{path}: the file's spacing {values} is not 3 finite numbers > 0; "
            "pass spacing= to give the voxel size"
        )
    return values[0], values[1], values[2]


def _drop_unit_axes(data: Any, spatial_first: bool) -> Any:
    """Drop length-1 axes beyond three: trailing ones (NIfTI) or leading ones (OME, TIFF)."""
    order = range(data.ndim - 1, 2, -1) if spatial_first else range(data.ndim - 4, -1, -1)
    for axis in order:
        if data.ndim > 3 and data.shape[axis] == 1:
            data = data[(slice(None),) * axis + (0,)]
    return data


def _read_npy(path: Path, key: str | None, budget: _Budget) -> tuple[Any, Any]:
    with open(path, "rb") as f:
        budget.check_npy(f)
    return np.load(path, allow_pickle=False), (1.0, 1.0, 1.0)


def _read_npz(path: Path, key: str | None, budget: _Budget) -> tuple[Any, Any]:
    with np.load(path, allow_pickle=False) as npz:
        names = [name for name in npz.files if name != "spacing"]
        if key is None:
            key = "mask" if "mask" in names else names[0] if len(names) == 1 else None
        if key is None or key not in names:
            raise VolumeError(
                f"{path}: choose the array with key= (arrays: {', '.join(npz.files)})"
            )
        spacing = npz["spacing"] if "spacing" in npz.files else (1.0, 1.0, 1.0)
        with zipfile.ZipFile(path) as archive:
            member = f"{key}.npy" if f"{key}.npy" in archive.namelist() else key
            with archive.open(member) as f:
                budget.check_npy(f)
        return npz[key], spacing


def _read_nifti(path: Path, key: str | None, budget: _Budget) -> tuple[Any, Any, Any]:
    nib = import_extra("nibabel", "io")
    image = nib.load(path)  # the header only: the data are read below
    scaled = getattr(image.dataobj, "slope", 1.0) != 1 or getattr(image.dataobj, "inter", 0) != 0
    budget.check(image.header.get_data_shape(), image.get_data_dtype(), 8 if scaled else 0)
    data = _drop_unit_axes(np.asanyarray(image.dataobj), spatial_first=True)
    # Zooms are float32: read 0.3 back as the decimal that was meant, as the binary does.
    zooms = [float(str(zoom)) for zoom in image.header.get_zooms()[:3]]
    affine = image.header.get_sform(coded=True)[0]
    if affine is None:
        affine = image.header.get_qform(coded=True)[0]
    if affine is None:  # neither code set: the NIfTI standard's method 1, as the binary
        affine = np.diag([abs(z) for z in zooms] + [1.0])
    return data, zooms, affine


def _read_tiff(path: Path, key: str | None, budget: _Budget) -> tuple[Any, Any]:
    tifffile = import_extra("tifffile", "io")
    with tifffile.TiffFile(path) as tif:
        if not tif.series:
            raise ValueError("no image series in the file")
        series = tif.series[0]
        budget.check(series.shape, series.dtype)
        data = _drop_unit_axes(series.asarray(), spatial_first=False)
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


def _read_zarr(path: Path, key: str | None, budget: _Budget) -> tuple[Any, Any, Any]:
    array, spacing, affine = open_zarr(path, key)
    return _zarr_array(array, budget), spacing, affine


def open_zarr(path: Path, key: str | None) -> tuple[Any, Any, NDArray[np.float64]]:
    """The Zarr array of ``path`` (not read; unit axes not dropped), its spacing and its
    voxel-to-world affine, by the rules of :func:`load_volume`.

    For OME-Zarr the dataset's ``coordinateTransformations`` (``scale``, then
    ``translation``) are applied first and then those of the multiscale itself, as the
    OME-NGFF specification orders them; the last three axes are the spatial ones. The
    spacing is the diagonal of that affine; a plain array has spacing 1 and the identity.
    """
    zarr = import_extra("zarr", "io")
    node = zarr.open(str(path), mode="r")
    if not hasattr(node, "shape"):  # a group: OME-Zarr (0.4 in attributes, 0.5 under "ome")
        attrs = dict(node.attrs)
        multiscales = attrs.get("multiscales") or attrs.get("ome", {}).get("multiscales")
        if not multiscales:
            if key is None:
                raise VolumeError(f"{path}: a Zarr group without OME metadata: pass key=")
            return node[key], (1.0, 1.0, 1.0), np.eye(4)
        datasets = multiscales[0]["datasets"]
        paths = [d["path"] for d in datasets]
        if key is not None and key not in paths:
            raise VolumeError(f"{path}: no dataset {key!r} (datasets: {', '.join(paths)})")
        dataset = datasets[0 if key is None else paths.index(key)]
        affine = np.eye(4)
        for transforms in (
            dataset.get("coordinateTransformations", []),
            multiscales[0].get("coordinateTransformations", []),
        ):
            for transform in transforms:
                kind = transform.get("type")
                if kind not in ("scale", "translation"):
                    continue
                values = np.asarray(transform[kind], dtype=np.float64).reshape(-1)
                if values.size < 3 or not np.all(np.isfinite(values)):
                    raise VolumeError(
                        f"{path}: OME {kind} {values.tolist()} is not 3 finite numbers"
                    )
                step = np.eye(4)
                if kind == "scale":
                    step[:3, :3] = np.diag(values[-3:])
                else:
                    step[:3, 3] = values[-3:]
                affine = step @ affine
        return node[dataset["path"]], np.diag(affine)[:3].copy(), affine
    return node, (1.0, 1.0, 1.0), np.eye(4)


def _zarr_array(array: Any, budget: _Budget) -> Any:
    budget.check(array.shape, array.dtype)
    return _drop_unit_axes(np.asarray(array[...]), spatial_first=False)


def _read_hdf5(path: Path, key: str | None, budget: _Budget) -> tuple[Any, Any]:
    h5py = import_extra("h5py", "io")
    with h5py.File(path, "r") as f:
        if key is None:
            names: list[str] = []
            f.visititems(lambda name, obj: names.append(name) if hasattr(obj, "shape") else None)
            if len(names) != 1:
                raise VolumeError(
                    f"{path}: choose the dataset with key= (datasets: {', '.join(names)})"
                )
            key = names[0]
        if key not in f:
            raise VolumeError(f"{path}: no dataset {key!r}")
        dataset = f[key]
        spacing: Any = (1.0, 1.0, 1.0)
        for attr in ("element_size_um", "spacing"):
            if attr in dataset.attrs:
                spacing = dataset.attrs[attr]
                break
        budget.check(dataset.shape, dataset.dtype)
        return dataset[...], spacing


def _read_sitk(path: Path, key: str | None, budget: _Budget) -> tuple[Any, Any, Any]:
    sitk = import_extra("SimpleITK", "io")
    info = sitk.ImageFileReader()
    info.SetFileName(str(path))
    info.ReadImageInformation()  # the header only
    components = info.GetNumberOfComponents()
    shape = (*reversed(info.GetSize()), *([components] if components > 1 else []))
    budget.check(shape, _SITK_DTYPES.get(info.GetPixelIDValue(), "float64"))
    image = sitk.ReadImage(str(path))
    # World = origin + direction @ diag(spacing) @ index (x, y, z); array axes are (z, y, x).
    linear = np.reshape(image.GetDirection(), (3, 3)) @ np.diag(image.GetSpacing())
    affine = np.eye(4)
    affine[:3, :3] = linear[:, ::-1]
    affine[:3, 3] = image.GetOrigin()
    return sitk.GetArrayFromImage(image), tuple(reversed(image.GetSpacing())), affine


_SITK_DTYPES = dict(enumerate(["int8", "uint8", "int16", "uint16", "int32", "uint32"]))
_SITK_DTYPES.update({6: "int64", 7: "uint64", 8: "float32", 9: "float64"})
"""SimpleITK's scalar pixel ids (sitkInt8 = 0 ... sitkFloat64 = 9); others count as 8 bytes."""

_READERS: dict[str, Callable[[Path, str | None, _Budget], tuple[Any, ...]]] = {
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

__all__ = ["Spacing", "VolumeError", "load_volume"]
