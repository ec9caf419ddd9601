"""Graphs out: SWC, VTK PolyData, CSV and Neuroglancer skeletons written by
VesselGraph.save (the Rust writers of the one format registry, which the binary uses
too), read back by load_graph or by an independent reader."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from graph_files import assert_same_graph
from vesselflow import VesselGraph, _core, load_graph
from vesselflow.io import csv_edges_path


@pytest.fixture
def looped() -> VesselGraph:
    """Three components: a square loop with a tail (a chord makes a second loop), a
    path of two edges, an isolated node; plus one repeated edge. Values with full
    float precision, so any rounding in a text format shows."""
    rng = np.random.default_rng(7)
    positions = rng.uniform(0, 100, size=(9, 3)) / 3
    radii = rng.uniform(0.5, 3, size=9) / 7
    radii[2] = 5.0  # root of the first component
    edges = [[0, 1], [1, 2], [2, 3], [3, 0], [0, 2], [3, 4], [5, 6], [6, 7], [6, 7]]
    return VesselGraph(positions, radii, edges, spacing=(2.5, 0.5, 0.75))


@pytest.mark.parametrize("ext", [".swc", ".csv", ".vtp"])
def test_round_trip_keeps_positions_radii_and_every_edge(
    tmp_path: Path, looped: VesselGraph, ext: str
) -> None:
    if ext == ".vtp":
        pytest.importorskip("vtkmodules")
    path = tmp_path / f"graph{ext}"
    looped.save(path)
    back = load_graph(path)
    assert_same_graph(looped, back)
    expected_spacing = (1.0, 1.0, 1.0) if ext == ".csv" else (2.5, 0.5, 0.75)
    np.testing.assert_array_equal(back.spacing, expected_spacing)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["graph.csv", "graph.edges.csv"] if ext == ".csv" else [path.name]
    )


def swc_table(path: Path) -> np.ndarray:
    return np.loadtxt(path, comments="#", ndmin=2)


def test_swc_is_a_breadth_first_forest_rooted_at_the_widest_node(
    tmp_path: Path, looped: VesselGraph
) -> None:
    path = tmp_path / "g.swc"
    looped.save(path)
    table = swc_table(path)
    ids, parents = table[:, 0].astype(int), table[:, 6].astype(int)
    np.testing.assert_array_equal(ids, np.arange(1, 10))
    assert set(table[:, 1]) == {0}
    # Parents precede children (readers that build trees in one pass need this).
    assert np.all((parents == -1) | (parents < ids))
    # One root per component; the first component is rooted at its widest node, node 2.
    roots = table[parents == -1]
    assert len(roots) == 3
    np.testing.assert_array_equal(roots[0, 2:6], [*looped.positions[2], 5.0])
    # x y z are array axes 0 1 2: each row is one node's position, radius next.
    rows = {tuple(row[2:6]) for row in table}
    assert rows == {(*p, r) for p, r in zip(looped.positions.tolist(), looped.radii.tolist())}
    # Breadth-first: node 2's neighbours 1, 3, 0 hang from the root.
    root_id = ids[0]
    children = {tuple(row[2:5]) for row in table[parents == root_id]}
    assert children == {tuple(looped.positions[i]) for i in (0, 1, 3)}


def test_swc_lists_every_edge_left_out_of_the_trees(tmp_path: Path, looped: VesselGraph) -> None:
    path = tmp_path / "g.swc"
    looped.save(path)
    text = path.read_text()
    loop_lines = [line.split() for line in text.splitlines() if line.startswith("# loop-edge")]
    # 9 edges, 9 nodes in 3 components: 9 - (9 - 3) = 3 edges close loops or repeat one.
    assert len(loop_lines) == 3
    tree_edges = int(np.sum(swc_table(path)[:, 6] != -1))
    assert tree_edges + len(loop_lines) == looped.n_edges
    # The repeated edge 6-7 appears once as a tree edge and once as a loop edge.
    table = swc_table(path)
    id_of = {tuple(row[2:5]): int(row[0]) for row in table}
    six, seven = id_of[tuple(looped.positions[6])], id_of[tuple(looped.positions[7])]
    assert sorted([six, seven]) in [sorted(map(int, words[2:4])) for words in loop_lines]
    assert text.splitlines()[1] == "# spacing 2.5 0.5 0.75"


def test_swc_of_another_tool_loads(tmp_path: Path) -> None:
    path = tmp_path / "neuron.swc"
    path.write_text(
        "# made elsewhere\n"
        "10 1 0 0 0 2.0 -1\n"
        "20 3 1.5 0 0 1.0 10\n"
        "\n"
        "35 3 1.5 2 0 0.5 20\n"
        "40 3 3 0 0.5 0.5 20\n"
    )
    graph = load_graph(path)
    np.testing.assert_array_equal(graph.radii, [2.0, 1.0, 0.5, 0.5])
    np.testing.assert_array_equal(graph.positions[3], [3, 0, 0.5])
    assert graph.edges.tolist() == [[0, 1], [1, 2], [1, 3]]
    np.testing.assert_array_equal(graph.spacing, [1, 1, 1])


def test_csv_tables(tmp_path: Path, looped: VesselGraph) -> None:
    path = tmp_path / "g.csv"
    looped.save(path)
    nodes = path.read_text().splitlines()
    assert nodes[0] == "id,x,y,z,r"
    assert nodes[3].split(",")[0] == "2"
    np.testing.assert_array_equal(
        [float(v) for v in nodes[3].split(",")[1:]], [*looped.positions[2], looped.radii[2]]
    )
    edges = csv_edges_path(path).read_text().splitlines()
    assert edges[0] == "source,target"
    assert [line.split(",") for line in edges[1:]] == [
        [str(a), str(b)] for a, b in looped.edges.tolist()
    ]


def test_vtp_holds_points_one_line_per_edge_and_a_radius_array(
    tmp_path: Path, looped: VesselGraph
) -> None:
    pytest.importorskip("vtkmodules")
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

    path = tmp_path / "g.vtp"
    looped.save(path)
    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    poly = reader.GetOutput()
    np.testing.assert_array_equal(vtk_to_numpy(poly.GetPoints().GetData()), looped.positions)
    np.testing.assert_array_equal(
        vtk_to_numpy(poly.GetPointData().GetArray("radius")), looped.radii
    )
    assert poly.GetNumberOfLines() == looped.n_edges
    connectivity = vtk_to_numpy(poly.GetLines().GetConnectivityArray())
    np.testing.assert_array_equal(connectivity.reshape(-1, 2), looped.edges)


def test_vtp_polylines_become_chains_of_edges(tmp_path: Path) -> None:
    pytest.importorskip("vtkmodules")
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData, vtkPolyLine
    from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter

    points = vtkPoints()
    for p in ([0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [0, 2, 0]):
        points.InsertNextPoint(p)
    lines = vtkCellArray()
    for chain in ([0, 1, 2], [0, 3, 4]):
        line = vtkPolyLine()
        line.GetPointIds().SetNumberOfIds(len(chain))
        for slot, point in enumerate(chain):
            line.GetPointIds().SetId(slot, point)
        lines.InsertNextCell(line)
    poly = vtkPolyData()
    poly.SetPoints(points)
    poly.SetLines(lines)
    radius = numpy_to_vtk(np.array([1.0, 0.5, 0.5, 0.25, 0.25]), deep=True)
    radius.SetName("radius")
    poly.GetPointData().AddArray(radius)
    writer = vtkXMLPolyDataWriter()
    writer.SetFileName(str(tmp_path / "chains.vtp"))
    writer.SetInputData(poly)
    writer.Write()

    graph = load_graph(tmp_path / "chains.vtp")
    assert graph.edges.tolist() == [[0, 1], [1, 2], [0, 3], [3, 4]]
    np.testing.assert_array_equal(graph.radii, [1.0, 0.5, 0.5, 0.25, 0.25])


@pytest.mark.parametrize("ext", [".swc", ".csv", ".vtp", ".precomputed"])
def test_refused_write_leaves_no_file_and_keeps_the_old_one(
    tmp_path: Path, looped: VesselGraph, ext: str
) -> None:
    path = tmp_path / f"g{ext}"
    path.write_text("old")
    if ext == ".csv":  # the second table cannot be written: the first is kept too
        (tmp_path / "g.edges.csv").mkdir()
        (tmp_path / "g.edges.csv" / "x").write_text("")
    if ext in (".csv", ".precomputed"):
        with pytest.raises(OSError, match=r"g\.(edges\.csv|precomputed)"):
            looped.save(path)
        assert path.read_text() == "old"
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
            [path.name, "g.edges.csv"] if ext == ".csv" else [path.name]
        )
    with pytest.raises(OSError, match="absent"):
        looped.save(tmp_path / "absent" / f"g{ext}")
    assert not (tmp_path / "absent").exists()


def test_vtp_is_written_without_vtk_and_read_with_it(
    tmp_path: Path, looped: VesselGraph, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "vtkmodules.vtkIOXML", None)
    looped.save(tmp_path / "g.vtp")  # the Rust writer needs no VTK
    with pytest.raises(ModuleNotFoundError, match=r"pip install vesselflow\[io\]"):
        load_graph(tmp_path / "g.vtp")


@pytest.mark.parametrize(
    ("name", "text"),
    [
        ("bad.swc", "1 0 0 0 0 1 -1\n2 0 1 0 0 1 7\n"),
        ("short.swc", "1 0 0 0\n"),
        ("bad.vtp", "<VTKFile type='PolyData'> garbage"),
        ("bad.csv", "id,x,y\n0,1,2\n"),
    ],
)
def test_unreadable_files_are_refused_naming_them(tmp_path: Path, name: str, text: str) -> None:
    if name.endswith(".vtp"):
        pytest.importorskip("vtkmodules")
    path = tmp_path / name
    path.write_text(text)
    if path.suffix == ".csv":
        csv_edges_path(path).write_text("source,target\n")
    with pytest.raises(ValueError, match=name):
        load_graph(path)


WRITTEN = [".graphml", ".json", ".npz", ".swc", ".vtp", ".csv", ".precomputed"]


def outputs(path: Path) -> dict[str, bytes]:
    """Every file a write made, by name (inside a ``.precomputed`` folder too)."""
    files = [path, csv_edges_path(path)] if path.suffix == ".csv" else [path]
    found: dict[str, bytes] = {}
    for file in files:
        inner = sorted(file.iterdir()) if file.is_dir() else [file]
        found.update({p.relative_to(path.parent).as_posix(): p.read_bytes() for p in inner})
    return found


@pytest.mark.parametrize("ext", WRITTEN)
def test_python_and_the_binary_write_the_same_bytes(tmp_path: Path, ext: str) -> None:
    """One registry: the CLI's file equals VesselGraph.save's of the same graph."""
    (tmp_path / "cli").mkdir()
    (tmp_path / "py").mkdir()
    assert _core.cli_main(["vesselflow", "demo", "-o", str(tmp_path / "cli" / "d.json"), "-q"]) == 0
    assert (
        _core.cli_main(["vesselflow", "demo", "-o", str(tmp_path / "cli" / f"d{ext}"), "-q"]) == 0
    )
    graph = load_graph(tmp_path / "cli" / "d.json")
    if ext in (".json", ".npz"):  # the run record holds timings: compare the graph
        assert_same_graph(load_graph(tmp_path / "cli" / f"d{ext}"), graph)
        return
    graph.save(tmp_path / "py" / f"d{ext}")
    cli, py = outputs(tmp_path / "cli" / f"d{ext}"), outputs(tmp_path / "py" / f"d{ext}")
    assert cli.keys() == py.keys()
    assert len(cli) >= 1
    assert cli == py


def test_precomputed_skeleton_reads_back_with_osteoid(tmp_path: Path, looped: VesselGraph) -> None:
    osteoid = pytest.importorskip("osteoid")
    path = tmp_path / "g.precomputed"
    looped.save(path)
    assert sorted(p.name for p in path.iterdir()) == ["1", "info"]
    info = json.loads((path / "info").read_text())
    assert info["@type"] == "neuroglancer_skeletons"
    assert info["vertex_attributes"] == [
        {"id": "radius", "data_type": "float32", "num_components": 1}
    ]
    skeleton = osteoid.Skeleton.from_precomputed(
        (path / "1").read_bytes(), segid=1, vertex_attributes=info["vertex_attributes"]
    )
    np.testing.assert_array_equal(skeleton.vertices, looped.positions.astype(np.float32))
    np.testing.assert_array_equal(skeleton.edges, looped.edges.astype(np.uint32))
    np.testing.assert_array_equal(skeleton.radius, looped.radii.astype(np.float32))
    # The transform maps the stored (array-order) vertices to x, y, z: x = axis 2.
    transform = np.reshape(info["transform"], (3, 4))
    xyz = skeleton.vertices.astype(np.float64) @ transform[:, :3].T + transform[:, 3]
    np.testing.assert_allclose(xyz, looped.positions[:, ::-1], rtol=1e-6)
    # In xyz (or world) coordinates the vertices are x, y, z already.
    looped.to_coordinates("xyz").save(path)  # replaces the earlier folder
    again = json.loads((path / "info").read_text())
    assert again["transform"] == [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.precomputed"]


def test_precomputed_never_replaces_a_folder_of_other_data(
    tmp_path: Path, looped: VesselGraph
) -> None:
    path = tmp_path / "data.precomputed"
    path.mkdir()
    (path / "info").write_text('{"@type": "neuroglancer_multiscale_volume"}')
    with pytest.raises(FileExistsError, match=r"data\.precomputed.*not a Neuroglancer skeleton"):
        looped.save(path)
    assert (path / "info").read_text() == '{"@type": "neuroglancer_multiscale_volume"}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data.precomputed"]
