"""VesselGraph.plot: the projection, the radius-coloured edges, the PNG file."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from vesselflow import VesselGraph

matplotlib = pytest.importorskip("matplotlib")
from matplotlib.collections import LineCollection  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.image import imread  # noqa: E402

SPACING = (2.0, 0.5, 1.0)


@pytest.fixture
def box() -> np.ndarray:
    """A bright block at voxels [4:8, 10:30, 2:6] of a (12, 40, 20) volume."""
    mask = np.zeros((12, 40, 20), np.uint8)
    mask[4:8, 10:30, 2:6] = 1
    return mask


@pytest.fixture
def graph() -> VesselGraph:
    """Three nodes on a line along axis 2 at the far end of axis 1 (away from the box)."""
    positions = [[10.0, 18.0, 8.0], [10.0, 18.0, 12.0], [12.0, 18.0, 16.0]]
    return VesselGraph(positions, [1.0, 2.0, 4.0], [[0, 1], [1, 2]], spacing=SPACING)


def test_png_is_written_with_the_expected_size_and_content(graph, box, tmp_path):
    path = tmp_path / "graph.png"
    figure = graph.plot(mask=box, path=path)
    assert isinstance(figure, Figure)
    pixels = imread(path)
    assert pixels.shape == (480, 640, 4)
    rgb = pixels[..., :3].reshape(-1, 3)
    assert rgb.std() > 0.1
    assert len(np.unique(rgb.round(2), axis=0)) > 50  # grey image, viridis lines and bar
    assert [p.name for p in tmp_path.iterdir()] == ["graph.png"]


def png_colour(figure: Figure, pixels: np.ndarray, x: float, y: float) -> np.ndarray:
    """Colour of the saved PNG at data point (x, y) of the figure's first axes."""
    px, py = figure.axes[0].transData.transform((x, y))
    return pixels[round(pixels.shape[0] - py), round(px), :3]


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_projection_of_a_known_mask_appears_at_physical_scale(graph, box, tmp_path, axis):
    figure = graph.plot(mask=box, path=tmp_path / "p.png", axis=axis)
    ax = figure.axes[0]
    np.testing.assert_array_equal(ax.images[0].get_array(), box.max(axis=axis))
    rows, cols = (a for a in range(3) if a != axis)
    # Extents in physical units: pixel centres at index * spacing.
    left, right, bottom, top = ax.images[0].get_extent()
    assert (left, right) == (-0.5 * SPACING[cols], (box.shape[cols] - 0.5) * SPACING[cols])
    assert (top, bottom) == (-0.5 * SPACING[rows], (box.shape[rows] - 0.5) * SPACING[rows])
    assert ax.get_aspect() == 1.0
    pixels = imread(tmp_path / "p.png")
    centre = [(4 + 7) / 2, (10 + 29) / 2, (2 + 5) / 2]  # voxel centre of the box
    outside = [0, 36, 18]
    inside_colour = png_colour(
        figure, pixels, centre[cols] * SPACING[cols], centre[rows] * SPACING[rows]
    )
    outside_colour = png_colour(
        figure, pixels, outside[cols] * SPACING[cols], outside[rows] * SPACING[rows]
    )
    np.testing.assert_allclose(inside_colour, 0.5, atol=0.02)  # mid grey: the mask
    np.testing.assert_allclose(outside_colour, 0.0, atol=0.02)  # black: background


def test_edges_are_segments_coloured_by_radius(graph):
    figure = graph.plot(axis=1)
    ax = figure.axes[0]
    (lines,) = [c for c in ax.collections if isinstance(c, LineCollection)]
    # axis 1 projected away: x = axis 2, y = axis 0.
    np.testing.assert_array_equal(
        np.array(lines.get_segments()), graph.positions[:, [2, 0]][graph.edges]
    )
    np.testing.assert_array_equal(lines.get_array(), [1.5, 3.0])
    assert len(figure.axes) == 2  # the plot and its colour bar
    assert "radius" in figure.axes[1].get_ylabel()
    # Without a mask the view fits the graph, rows growing downwards as in an image.
    x0, x1 = ax.get_xlim()
    assert x0 <= 8.0
    assert x1 >= 16.0
    assert ax.yaxis_inverted()


def test_draws_into_given_axes(graph, box):
    figure = Figure()
    left, right = figure.subplots(1, 2)
    assert graph.plot(mask=box, ax=right) is figure
    assert not left.images
    assert len(right.images) == 1


def test_bad_arguments(graph, box):
    with pytest.raises(ValueError, match="axis"):
        graph.plot(axis=3)
    with pytest.raises(ValueError, match="3-D"):
        graph.plot(mask=box[0])


def test_failed_save_leaves_no_file(graph, tmp_path, monkeypatch):
    def broken(self, fname, **kwargs):
        with open(fname, "wb") as f:
            f.write(b"\x89PNG half")
        raise RuntimeError("disk full")

    monkeypatch.setattr(Figure, "savefig", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        graph.plot(path=tmp_path / "g.png")
    assert list(tmp_path.iterdir()) == []


def test_save_replaces_an_existing_file_and_missing_folder_is_an_error(graph, tmp_path):
    path = tmp_path / "g.png"
    path.write_bytes(b"old")
    graph.plot(path=path)
    assert path.read_bytes().startswith(b"\x89PNG")
    with pytest.raises(FileNotFoundError):
        graph.plot(path=tmp_path / "missing" / "g.png")


def test_missing_matplotlib_names_the_extra(graph, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(ModuleNotFoundError, match=r"vesselflow\[viz\]"):
        graph.plot()
