"""VesselGraph: counts, networkx view, saving and loading every format."""

from __future__ import annotations

import json
import os
import sys

import networkx as nx
import numpy as np
import pytest

import vesselflow
from vesselflow import VesselGraph, load_graph

FORMATS = [".npz", ".json", ".graphml"]


@pytest.fixture
def graph(branching) -> VesselGraph:
    return vesselflow.skeletonize(branching, spacing=(0.5, 0.3, 0.7))


def test_counts_and_degrees(graph):
    assert graph.n_nodes == len(graph.positions) == len(graph.radii)
    assert graph.n_edges == len(graph.edges)
    degrees = graph.degrees()
    assert degrees.sum() == 2 * graph.n_edges
    expected = np.zeros(graph.n_nodes, np.int64)
    for a, b in graph.edges:
        expected[a] += 1
        expected[b] += 1
    np.testing.assert_array_equal(degrees, expected)


def test_repr_is_short(graph):
    text = repr(graph)
    assert text.startswith(f"VesselGraph(n_nodes={graph.n_nodes}, n_edges={graph.n_edges}, ")
    assert "spacing=(0.5, 0.3, 0.7)" in text
    assert "\n" not in text


def test_to_networkx(graph):
    g = graph.to_networkx()
    assert isinstance(g, nx.Graph)
    assert not g.is_directed()
    assert g.number_of_nodes() == graph.n_nodes
    assert g.number_of_edges() == graph.n_edges
    assert g.graph["spacing"] == (0.5, 0.3, 0.7)
    for i in (0, graph.n_nodes // 2, graph.n_nodes - 1):
        pos = g.nodes[i]["pos"]
        assert isinstance(pos, np.ndarray)
        assert pos.shape == (3,)
        np.testing.assert_array_equal(pos, graph.positions[i])
        assert g.nodes[i]["r"] == graph.radii[i]
        assert isinstance(g.nodes[i]["r"], float)
    assert sorted(d for _, d in g.degree()) == sorted(graph.degrees().tolist())
    assert all(g.has_edge(int(a), int(b)) for a, b in graph.edges)


def test_constructor_checks_arrays():
    with pytest.raises(ValueError, match="radii"):
        VesselGraph(positions=np.zeros((3, 3)), radii=np.zeros(2), edges=np.zeros((0, 2)))
    with pytest.raises(ValueError, match="edges"):
        VesselGraph(positions=np.zeros((3, 3)), radii=np.zeros(3), edges=[[0, 3]])
    with pytest.raises(ValueError, match="spacing"):
        VesselGraph(np.zeros((1, 3)), np.zeros(1), np.zeros((0, 2)), spacing=[1.0, 1.0])


@pytest.mark.parametrize("ext", FORMATS)
def test_save_load_round_trip(graph, tmp_path, ext):
    path = tmp_path / f"vessels{ext}"
    graph.save(path)
    loaded = load_graph(path)
    # Every format writes floats in shortest round-trip form: equality is exact.
    np.testing.assert_array_equal(loaded.positions, graph.positions)
    np.testing.assert_array_equal(loaded.radii, graph.radii)
    np.testing.assert_array_equal(loaded.edges, graph.edges)
    np.testing.assert_array_equal(loaded.spacing, graph.spacing)
    assert loaded.positions.dtype == np.float64
    assert loaded.edges.dtype == np.int64
    if ext == ".graphml":
        assert loaded.info == {}
        assert loaded.params == {}
    else:
        assert loaded.info == graph.info
        assert loaded.params == graph.params
    assert [p.name for p in tmp_path.iterdir()] == [path.name]


@pytest.mark.parametrize("ext", FORMATS)
def test_save_load_empty_graph(tmp_path, ext):
    empty = vesselflow.skeletonize(np.zeros((4, 4, 4), bool))
    empty.save(tmp_path / f"e{ext}")
    loaded = load_graph(str(tmp_path / f"e{ext}"))
    assert loaded.positions.shape == (0, 3)
    assert loaded.edges.shape == (0, 2)


def test_files_follow_the_format_contract(graph, tmp_path):
    graph.save(tmp_path / "g.json")
    doc = json.loads((tmp_path / "g.json").read_text())
    assert doc["format"] == "vesselflow-graph"
    assert doc["version"] == 1
    assert doc["spacing"] == [0.5, 0.3, 0.7]
    assert doc["info"]["stage_seconds"] == graph.info["stage_seconds"]

    graph.save(tmp_path / "g.npz")
    with np.load(tmp_path / "g.npz", allow_pickle=False) as z:
        assert sorted(z.files) == ["edges", "metadata", "positions", "radii", "spacing"]
        assert z["metadata"].dtype == np.uint8
        assert z["edges"].dtype == np.int64
        meta = json.loads(z["metadata"].tobytes())
        assert meta["format"] == "vesselflow-graph"
        assert meta["params"] == graph.params

    graph.save(tmp_path / "g.graphml")
    g = nx.read_graphml(tmp_path / "g.graphml")
    assert [g.graph[f"spacing{axis}"] for axis in range(3)] == [0.5, 0.3, 0.7]
    assert g.nodes["0"] == {
        "x": graph.positions[0, 0],
        "y": graph.positions[0, 1],
        "z": graph.positions[0, 2],
        "r": graph.radii[0],
    }


def test_save_replaces_an_existing_file(graph, tmp_path):
    path = tmp_path / "g.json"
    path.write_text("old")
    graph.save(path)
    assert load_graph(path).n_nodes == graph.n_nodes


def test_save_with_numpy_values_in_info(graph, tmp_path):
    graph.info["extra"] = np.float32(1.5)
    graph.info["arr"] = np.arange(3)
    graph.save(tmp_path / "g.json")
    info = load_graph(tmp_path / "g.json").info
    assert info["extra"] == 1.5
    assert info["arr"] == [0, 1, 2]


def test_save_unknown_extension_is_a_value_error_and_writes_nothing(graph, tmp_path):
    with pytest.raises(
        ValueError, match=r"vessels\.xyz.*\.graphml, \.json, \.npz, \.swc, \.vtp, \.csv or \.prec"
    ):
        graph.save(tmp_path / "vessels.xyz")
    assert list(tmp_path.iterdir()) == []


def test_save_to_missing_directory_is_an_os_error_and_writes_nothing(graph, tmp_path):
    with pytest.raises(FileNotFoundError, match="missing"):
        graph.save(tmp_path / "missing" / "g.json")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(
    sys.platform == "win32" or os.geteuid() == 0, reason="root ignores directory permissions"
)
def test_save_to_read_only_directory_is_an_os_error(graph, tmp_path):
    tmp_path.chmod(0o555)
    try:
        with pytest.raises(PermissionError):
            graph.save(tmp_path / "g.npz")
        assert list(tmp_path.iterdir()) == []
    finally:
        tmp_path.chmod(0o755)


def test_save_onto_a_directory_is_an_os_error(graph, tmp_path):
    (tmp_path / "d.json").mkdir()
    with pytest.raises(OSError, match="directory"):
        graph.save(tmp_path / "d.json")
    assert [p.name for p in tmp_path.iterdir()] == ["d.json"]


def test_save_invalid_graph_is_a_value_error(tmp_path):
    bad = VesselGraph(np.zeros((1, 3)), np.ones(1), np.zeros((0, 2)))
    bad.positions[0, 1] = np.nan  # the constructor refuses it: changed afterwards
    with pytest.raises(ValueError, match="finite"):
        bad.save(tmp_path / "g.npz")
    assert list(tmp_path.iterdir()) == []


def test_load_unknown_extension_lists_the_supported_ones(tmp_path):
    path = tmp_path / "g.xyz"
    path.write_text("1 2 3")
    with pytest.raises(ValueError, match=r"g\.xyz.*\.graphml, \.json, \.npz"):
        load_graph(path)


@pytest.mark.parametrize("ext", FORMATS)
def test_load_missing_file_is_an_os_error_naming_it(tmp_path, ext):
    with pytest.raises(OSError, match=f"nothere{ext}"):
        load_graph(tmp_path / f"nothere{ext}")


@pytest.mark.parametrize("ext", FORMATS)
def test_load_truncated_file_is_a_value_error_naming_it(graph, tmp_path, ext):
    path = tmp_path / f"g{ext}"
    graph.save(path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=f"g{ext}"):
        load_graph(path)


@pytest.mark.parametrize("ext", FORMATS)
def test_load_garbage_is_a_value_error(tmp_path, ext):
    path = tmp_path / f"g{ext}"
    path.write_bytes(b"\x00\x01 not a graph")
    with pytest.raises(ValueError, match=f"g{ext}"):
        load_graph(path)


def test_load_json_of_another_format_is_a_value_error(tmp_path):
    path = tmp_path / "g.json"
    path.write_text(json.dumps({"format": "other", "version": 1}))
    with pytest.raises(ValueError, match="vesselflow-graph"):
        load_graph(path)
    path.write_text(json.dumps({"format": "vesselflow-graph", "version": 1, "spacing": [1] * 3}))
    with pytest.raises(ValueError, match="missing field 'positions'"):
        load_graph(path)


def test_load_graphml_from_other_tools(tmp_path):
    """A GraphML file written by networkx with the contract's keys loads too."""
    g = nx.Graph(spacing0=1.0, spacing1=2.0, spacing2=3.0)
    g.add_node("1", x=1.0, y=2.0, z=3.0, r=0.5)
    g.add_node("0", x=0.0, y=0.0, z=0.0, r=1.5)
    g.add_edge("1", "0")
    nx.write_graphml(g, tmp_path / "g.graphml")
    loaded = load_graph(tmp_path / "g.graphml")
    np.testing.assert_array_equal(loaded.positions, [[0, 0, 0], [1, 2, 3]])
    np.testing.assert_array_equal(loaded.radii, [1.5, 0.5])
    np.testing.assert_array_equal(loaded.edges, [[0, 1]])
    np.testing.assert_array_equal(loaded.spacing, [1, 2, 3])
