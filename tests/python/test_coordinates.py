"""World and xyz coordinates, checked the way users check them: a graph written in world
coordinates lies on its mask read back through nibabel with the file's affine, in the
Python package and in the command line alike; ``xyz`` puts the last array axis in the
SWC ``x`` column."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import vesselflow
from vesselflow import _core, load_graph

nib = pytest.importorskip("nibabel")
ndimage = pytest.importorskip("scipy.ndimage")


def bent_tube() -> np.ndarray:
    """A tube along axis 0 that turns along axis 2: no symmetry hides a transposed axis."""
    mask = np.zeros((36, 22, 30), dtype=np.uint8)
    z, y, x = np.ogrid[:36, :22, :30]
    mask[((y - 11) ** 2 + (x - 8) ** 2 <= 9) & (z <= 24)] = 1
    mask[((z - 24) ** 2 + (y - 11) ** 2 <= 9) & (x >= 8) & (x <= 26)] = 1
    return mask


def oblique_affine() -> np.ndarray:
    """Rotation (30 degrees about one axis, then 20 about another), anisotropic voxels
    and a translation."""
    a, b = math.radians(30), math.radians(20)
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
    affine = np.eye(4)
    affine[:3, :3] = rz @ rx @ np.diag([0.8, 1.3, 2.0])
    affine[:3, 3] = [12.5, -40.0, 7.25]
    return affine


def on_mask(points: np.ndarray, nifti: Path) -> np.ndarray:
    """For each world point, whether it lies in the file's mask dilated by one voxel,
    read through nibabel with the file's own affine."""
    image = nib.load(nifti)
    dilated = ndimage.binary_dilation(np.asarray(image.dataobj) > 0, iterations=1)
    voxels = np.rint(nib.affines.apply_affine(np.linalg.inv(image.affine), points)).astype(int)
    inside = np.all((voxels >= 0) & (voxels < dilated.shape), axis=1)
    hits = np.zeros(len(points), dtype=bool)
    hits[inside] = dilated[tuple(voxels[inside].T)]
    return hits


def vtp_points(path: Path) -> np.ndarray:
    """The points of a ``.vtp`` file, read by VTK itself."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    return np.asarray(vtk_to_numpy(reader.GetOutput().GetPoints().GetData()), dtype=np.float64)


@pytest.fixture
def nifti(tmp_path: Path) -> Path:
    path = tmp_path / "tube.nii.gz"
    nib.save(nib.Nifti1Image(bent_tube(), oblique_affine()), path)
    return path


def test_load_volume_returns_the_file_affine(nifti: Path) -> None:
    mask, spacing, affine = vesselflow.load_volume(nifti, return_affine=True)
    np.testing.assert_allclose(affine, oblique_affine(), rtol=0, atol=1e-5)  # stored as float32
    np.testing.assert_allclose(spacing, [0.8, 1.3, 2.0], rtol=1e-6)
    assert mask.sum() == bent_tube().sum()
    plain = vesselflow.load_volume(nifti)
    assert len(plain) == 2


def test_spacing_only_formats_give_the_diagonal(tmp_path: Path) -> None:
    path = tmp_path / "m.npz"
    np.savez(path, mask=bent_tube(), spacing=np.array([2.0, 0.5, 0.25]))
    _, spacing, affine = vesselflow.load_volume(path, return_affine=True)
    assert spacing == (2.0, 0.5, 0.25)
    np.testing.assert_array_equal(affine, np.diag([2.0, 0.5, 0.25, 1.0]))


def test_world_graph_lies_on_its_mask_in_python_and_in_the_cli(nifti: Path, tmp_path: Path) -> None:
    pytest.importorskip("vtkmodules")
    mask, spacing, affine = vesselflow.load_volume(nifti, return_affine=True)
    graph = vesselflow.skeletonize(mask, spacing, coordinates="world", affine=affine)
    assert graph.n_nodes > 20
    assert graph.info["coordinates"] == "world"
    graph.save(tmp_path / "py.vtp")
    points = vtp_points(tmp_path / "py.vtp")
    assert on_mask(points, nifti).all()
    # The same graph in array coordinates is not on the world-space mask: the check
    # above tells the frames apart.
    array = vesselflow.skeletonize(mask, spacing)
    assert on_mask(array.positions, nifti).mean() < 0.5

    code = _core.cli_main(
        [
            "vesselflow",
            "skeletonize",
            str(nifti),
            "-o",
            str(tmp_path / "cli.vtp"),
            "-q",
            "--coordinates",
            "world",
        ]
    )
    assert code == 0
    cli_points = vtp_points(tmp_path / "cli.vtp")
    assert on_mask(cli_points, nifti).all()
    # Rust computes the qform/sform in float64, nibabel from the same float32 fields.
    np.testing.assert_allclose(cli_points, points, rtol=0, atol=1e-4)


def test_world_needs_an_affine_and_refuses_a_bad_one() -> None:
    mask = bent_tube()
    with pytest.raises(ValueError, match="affine="):
        vesselflow.skeletonize(mask, coordinates="world")
    flat = np.diag([1.0, 1.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="singular"):
        vesselflow.skeletonize(mask, coordinates="world", affine=flat)
    with pytest.raises(ValueError, match="'array', 'xyz', 'world'"):
        vesselflow.skeletonize(mask, coordinates="zyx")  # type: ignore[arg-type]


def test_world_with_an_affine_of_other_voxel_size_warns_about_radii(
    caplog: pytest.LogCaptureFixture,
) -> None:
    graph = vesselflow.skeletonize(bent_tube(), (1.0, 1.0, 1.0))
    moved = graph.to_coordinates("world", np.diag([2.0, 2.0, 2.0, 1.0]))
    np.testing.assert_allclose(moved.positions, 2 * graph.positions)
    np.testing.assert_array_equal(moved.radii, graph.radii)
    assert "radii stay in the spacing's units" in caplog.text


def swc_rows(path: Path) -> tuple[list[str], np.ndarray]:
    lines = path.read_text().splitlines()
    header = [line for line in lines if line.startswith("#")]
    rows = np.array([[float(w) for w in line.split()] for line in lines if line[:1] != "#"])
    return header, rows


@pytest.mark.parametrize("entry", ["python", "cli"])
def test_xyz_puts_the_last_axis_in_the_swc_x_column(
    tmp_path: Path, entry: str, monkeypatch: Any
) -> None:
    mask = np.zeros((12, 14, 60), dtype=bool)  # a tube along the last axis: x in ImageJ
    mask[3:9, 4:10, 2:58] = True
    spacing = (3.0, 1.0, 0.5)
    path = tmp_path / "tube.swc"
    if entry == "python":
        vesselflow.skeletonize(mask, spacing, coordinates="xyz").save(path)
    else:
        np.save(tmp_path / "tube.npy", mask)
        argv = ["vesselflow", "skeletonize", str(tmp_path / "tube.npy"), "-o", str(path)]
        argv += ["--spacing", "3", "1", "0.5", "--coordinates", "xyz", "-q"]
        assert _core.cli_main(argv) == 0
    header, rows = swc_rows(path)
    extent = rows[:, 2:5].max(axis=0) - rows[:, 2:5].min(axis=0)
    assert extent[0] > 20
    assert extent[1] < 2
    assert extent[2] < 4
    assert "# spacing 0.5 1.0 3.0" in header
    assert any("x y z = array axes 2 1 0" in line for line in header)
    back = load_graph(path)
    np.testing.assert_array_equal(back.spacing, [0.5, 1.0, 3.0])
