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
    # The box volume: 40 x 0.5 = 20 units down, 20 x 1 = 20 across, 40 voxels of the finer
    # spacing: 4 px per voxel is less than the least picture, 600 px, plus room for labels.
    assert 600 < pixels.shape[0] < 800
    assert 600 < pixels.shape[1] < 1000
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


def figure_px(figure: Figure) -> np.ndarray:
    return figure.get_size_inches() * figure.dpi


def test_figure_size_line_width_and_text_grow_with_the_volume(graph):
    small = graph.plot(mask=np.ones((4, 50, 50), np.uint8))
    large = graph.plot(mask=np.ones((4, 1000, 250), np.uint8))
    wide = graph.plot(mask=np.ones((4, 100, 400), np.uint8))
    # Spacing 0.5 down, 1 across: large is 500 units down, 250 across; wide 50 and 400.
    assert figure_px(large)[1] > 2 * figure_px(small)[1]
    assert figure_px(large)[1] > figure_px(large)[0]  # taller than wide, as the volume
    assert figure_px(wide)[0] > figure_px(wide)[1]
    lines = [next(c for c in f.axes[0].collections) for f in (small, large)]
    assert lines[1].get_linewidth()[0] > 2 * lines[0].get_linewidth()[0]
    sizes = [f.axes[1].yaxis.label.get_fontsize() for f in (small, large)]
    assert sizes[1] > 2 * sizes[0]


def test_colour_bar_has_a_label_and_ticks_within_the_radius_range(graph, box):
    figure = graph.plot(mask=box)
    figure.canvas.draw()
    bar = figure.axes[1]
    assert bar.get_ylabel() == "radius (physical units)"
    ticks = [t for t in bar.get_yticks() if 1.5 <= t <= 3.0]
    assert len(ticks) >= 3
    labels = [t.get_text() for t in bar.get_yticklabels() if t.get_text()]
    assert len(labels) >= 3


@pytest.fixture
def two_tubes() -> VesselGraph:
    """A thin vessel (radius 1) on the left, a thick one (radius 3) on the right, along y."""
    positions = [[0.0, 0.0, 0.0], [0.0, 30.0, 0.0], [30.0, 0.0, 0.0], [30.0, 30.0, 0.0]]
    return VesselGraph(positions, [1.0, 1.0, 3.0, 3.0], [[0, 1], [2, 3]])


def coloured(picture: np.ndarray) -> np.ndarray:
    """Pixels that are not background white nor grey."""
    rgb = picture.astype(int)
    return (rgb.max(axis=-1) - rgb.min(axis=-1)) > 40


def test_plot3d_draws_tubes_coloured_and_sized_by_radius(two_tubes, tmp_path):
    pytest.importorskip("pyvista")
    path = tmp_path / "tubes.png"
    picture = two_tubes.plot3d(path, view="xy", window_size=(400, 300))
    assert picture.shape == (300, 400, 3)
    np.testing.assert_allclose(imread(path)[..., :3], picture / 255.0, atol=1e-6)
    assert [p.name for p in tmp_path.iterdir()] == ["tubes.png"]
    # Looking down z: x across. The colour bar sits at the right: keep the left 80 %.
    mask = coloured(picture)
    mask[:, int(0.8 * picture.shape[1]) :] = False
    columns = np.flatnonzero(mask.any(axis=0))
    assert len(columns) > 10
    middle = (columns.min() + columns.max()) / 2
    left, right = mask.copy(), mask.copy()
    left[:, int(middle) :] = False
    right[:, : int(middle)] = False
    thin, thick = picture[left].astype(float), picture[right].astype(float)
    # viridis: purple (blue over green) at the low end, yellow (red and green over blue)
    # at the high end.
    assert thin[:, 2].mean() > thin[:, 1].mean()
    assert thick[:, 1].mean() > thick[:, 2].mean()
    assert thick[:, 0].mean() > thick[:, 2].mean()
    # The thick tube is three times as wide: about three times the pixels.
    assert 2.0 < right.sum() / left.sum() < 4.5


def test_plot3d_of_an_empty_graph_is_blank_and_bad_views_are_refused(tmp_path):
    pytest.importorskip("pyvista")
    empty = VesselGraph(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 2), np.int64))
    picture = empty.plot3d(window_size=(64, 48))
    assert (picture == 255).all()
    with pytest.raises(ValueError, match="view"):
        empty.plot3d(view="top")


def test_missing_pyvista_names_the_extra(graph, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyvista", None)
    with pytest.raises(ModuleNotFoundError, match=r"vesselflow\[viz\]"):
        graph.plot3d()
