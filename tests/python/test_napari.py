"""The napari plugin: its manifest (npe2's own validator), the reader's layers, and the
widget's work (runs, reports progress, cancels) without Qt; the widget itself in a
viewer when napari and a display are there."""

from __future__ import annotations

import os
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import pytest

import vesselflow
from vesselflow import VesselGraph
from vesselflow.napari import graph_layers
from vesselflow.napari._reader import get_reader
from vesselflow.napari._run import Cancelled, skeletonize_layer

MANIFEST = Path(vesselflow.__file__).parent / "napari" / "napari.yaml"


@pytest.fixture
def graph() -> VesselGraph:
    positions = [[0.0, 0.0, 0.0], [0.0, 0.0, 4.0], [0.0, 3.0, 4.0], [2.0, 0.0, 4.0]]
    return VesselGraph(positions, [1.0, 2.0, 3.0, 0.5], [[0, 1], [1, 2], [1, 3]], spacing=(2, 1, 1))


@pytest.fixture
def tube() -> np.ndarray:
    mask = np.zeros((40, 15, 15), np.uint8)
    mask[:, 5:10, 5:10] = 1
    return mask


def test_manifest_is_valid_and_names_importable_commands():
    npe2 = pytest.importorskip("npe2")
    manifest = npe2.PluginManifest.from_file(MANIFEST)
    assert manifest.name == "vesselflow"
    commands = {c.id: c.python_name for c in manifest.contributions.commands}
    assert commands["vesselflow.get_reader"] == "vesselflow.napari._reader:get_reader"
    (reader,) = manifest.contributions.readers
    assert "*.swc" in reader.filename_patterns
    (widget,) = manifest.contributions.widgets
    assert commands[widget.command].endswith(":SkeletonizeWidget")
    # The reader's command resolves without napari.
    module, _, name = commands["vesselflow.get_reader"].partition(":")
    assert getattr(__import__(module, fromlist=[name]), name) is get_reader


def test_manifest_entry_point_is_declared():
    pyproject = (Path(__file__).parents[2] / "pyproject.toml").read_text()
    assert '[project.entry-points."napari.manifest"]' in pyproject
    assert 'vesselflow = "vesselflow.napari:napari.yaml"' in pyproject
    installed = [e for e in entry_points(group="napari.manifest") if e.name == "vesselflow"]
    if installed:  # an install made after the entry point was added
        assert installed[0].value == "vesselflow.napari:napari.yaml"


def test_graph_layers_hold_edges_nodes_and_radius(graph):
    (vectors, vkw, vkind), (points, pkw, pkind) = graph_layers(graph, name="g", translate=(1, 2, 3))
    assert (vkind, pkind) == ("vectors", "points")
    assert vectors.shape == (3, 2, 3)
    np.testing.assert_array_equal(vectors[:, 0], graph.positions[graph.edges[:, 0]])
    np.testing.assert_array_equal(vectors[:, 0] + vectors[:, 1], graph.positions[graph.edges[:, 1]])
    np.testing.assert_array_equal(vkw["features"]["radius"], [1.5, 2.5, 1.25])
    assert (vkw["edge_color"], vkw["edge_colormap"]) == ("radius", "viridis")
    np.testing.assert_array_equal(points, graph.positions)
    np.testing.assert_array_equal(pkw["features"]["radius"], graph.radii)
    np.testing.assert_array_equal(pkw["features"]["degree"], [1, 3, 1, 1])
    np.testing.assert_array_equal(pkw["size"], 2 * graph.radii)
    assert vkw["translate"] == pkw["translate"] == (1.0, 2.0, 3.0)
    assert (vkw["name"], pkw["name"]) == ("g edges", "g nodes")


@pytest.mark.parametrize("suffix", [".swc", ".json", ".graphml"])
def test_reader_returns_the_graphs_layers(graph, tmp_path, suffix):
    path = tmp_path / f"vessels{suffix}"
    graph.save(path)
    reader = get_reader(str(path))
    assert reader is not None
    layers = reader(str(path))
    assert [kind for _, _, kind in layers] == ["vectors", "points"]
    loaded = vesselflow.load_graph(path)
    np.testing.assert_allclose(layers[1][0], loaded.positions)
    np.testing.assert_allclose(layers[1][1]["features"]["radius"], loaded.radii)
    assert layers[0][1]["name"] == "vessels edges"


def test_reader_declines_files_that_are_not_graphs(tmp_path):
    mask = tmp_path / "mask.npz"
    np.savez(mask, mask=np.zeros((3, 3, 3)))
    notes = tmp_path / "notes.json"
    notes.write_text('{"hello": 1}')
    assert get_reader(str(mask)) is None
    assert get_reader(str(notes)) is None
    assert get_reader(str(tmp_path / "missing.swc")) is None


def test_worker_runs_on_layer_data_with_its_scale_and_reports_progress(tube):
    seen = []
    layers = skeletonize_layer(
        tube,
        scale=(2.0, 0.5, 0.5),
        translate=(10.0, 0.0, 0.0),
        name="tube",
        params={"gamma": 0.05},
        progress=lambda stage, iteration, total: seen.append((stage, iteration, total)),
    )
    points, kwargs, _ = layers[1]
    expected = vesselflow.skeletonize(tube, (2.0, 0.5, 0.5), gamma=0.05)
    np.testing.assert_array_equal(points, expected.positions)  # physical units: the scale
    assert kwargs["translate"] == (10.0, 0.0, 0.0)
    assert kwargs["name"] == "tube nodes"
    assert seen
    assert {total for _, _, total in seen} == {100}
    assert "contract" in {stage for stage, _, _ in seen}


def test_worker_cancels_and_refuses_bad_layers(tube):
    calls = []

    def cancelled() -> bool:
        calls.append(1)
        return len(calls) > 2

    with pytest.raises(Cancelled):
        skeletonize_layer(tube, scale=(1, 1, 1), cancelled=cancelled)
    assert len(calls) == 3  # stopped at the first callback after the request
    with pytest.raises(ValueError, match="3-D"):
        skeletonize_layer(tube[0], scale=(1, 1))
    labels = tube * 3
    labels[:, 0, 0] = 5
    with pytest.raises(ValueError, match="label="):
        skeletonize_layer(labels, scale=(1, 1, 1))
    layers = skeletonize_layer(labels, scale=(1, 1, 1), label=3)
    assert len(layers[1][0]) > 0


needs_display = pytest.mark.skipif(
    not os.environ.get("DISPLAY"), reason="the napari widget needs a display (run under xvfb-run)"
)


@needs_display
def test_widget_in_a_viewer_adds_the_graph_layers(tube, request):
    napari = pytest.importorskip("napari")
    pytest.importorskip("pytestqt")
    qtbot = request.getfixturevalue("qtbot")
    from vesselflow.napari._widget import SkeletonizeWidget

    viewer = napari.Viewer(show=False)
    try:
        viewer.add_labels(tube, scale=(2.0, 0.5, 0.5), name="tube")
        widget = SkeletonizeWidget(viewer)
        widget.reset_choices()
        worker = widget.start()
        with qtbot.waitSignal(worker.finished, timeout=60_000):
            pass
        names = [layer.name for layer in viewer.layers]
        assert names == ["tube", "tube edges", "tube nodes"]
        assert "radius" in viewer.layers["tube nodes"].features
    finally:
        viewer.close()
