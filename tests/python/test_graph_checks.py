"""One rule for a valid graph, everywhere: every loader refuses what the constructor and
save refuse, with a ValueError naming the file and the problem; multi-file saves are
all or nothing, also when SIGTERM arrives."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import vesselflow.io
from conftest import make_slow_tube
from graph_files import GRAPH_FORMATS, assert_same_graph, write_raw
from vesselflow import VesselGraph, load_graph
from vesselflow.__main__ import EXIT_TERMINATED, Terminated, sigterm_raises
from vesselflow.graph import check_graph_arrays
from vesselflow.io import csv_edges_path

POSITIONS = [[0.0, 0.0, 0.0], [1.0, 0.5, 0.25], [2.0, 1.0, 0.5]]
RADII = [1.0, 0.5, 0.25]
EDGES = [[0, 1], [1, 2]]


def needs(ext: str) -> None:
    if ext == ".vtp":
        pytest.importorskip("vtkmodules")


def with_nan_position() -> dict[str, Any]:
    positions = np.array(POSITIONS)
    positions[1, 2] = np.nan
    return {"positions": positions}


# case -> (what to change, message, formats that can hold it)
BAD = {
    "nan position": (with_nan_position(), r"positions\[\d\] = \(1\.0, 0\.5, nan\) is not finite"),
    "inf radius": ({"radii": [1.0, np.inf, 0.25]}, r"radii\[\d\] = inf is not a finite"),
    "negative radius": ({"radii": [1.0, -0.5, 0.25]}, r"radii\[\d\] = -0\.5 is not a finite"),
    "self-loop": ({"edges": [[0, 1], [2, 2]]}, r"joins node \d to itself"),
    "edge out of range": ({"edges": [[0, 1], [1, 7]]}, r"outside 0\.\.2|not a node id|'7'"),
}


@pytest.mark.parametrize("ext", GRAPH_FORMATS)
@pytest.mark.parametrize("case", sorted(BAD))
def test_every_format_refuses_an_invalid_graph_naming_file_and_problem(
    tmp_path: Path, ext: str, case: str
) -> None:
    needs(ext)
    if case == "edge out of range" and ext == ".swc":
        pytest.skip("SWC refers to nodes by id: covered by test_damaged_files_are_value_errors")
    change, message = BAD[case]
    arrays = {"positions": POSITIONS, "radii": RADII, "edges": EDGES, **change}
    path = tmp_path / f"bad{ext}"
    write_raw(path, **arrays)
    with pytest.raises(ValueError, match=rf"bad\{ext}: .*({message})"):
        load_graph(path)


@pytest.mark.parametrize(
    ("edges", "message"),
    [
        # Six ids: reshaped to three edges before; an (E, 2) array is required now.
        ([[0, 1, 2], [1, 2, 0]], r"edges must have shape \(E, 2\), got \(2, 3\)"),
        ([[0, 1.5], [1, 2]], r"edges\[0\] = \(0\.0, 1\.5\) are not integer node ids"),
        ([[0, 1], [1, 2.0000001]], r"edges\[1\] .* not integer"),
        ([[0, 1], [1, 10**30]], r"edges must be integer node ids, got object"),
        ([[0, 1], [1, 2**63]], r"edges\[1\] = \(1\.0, 9\.2\d*e\+18\) refers to a node outside"),
    ],
)
@pytest.mark.parametrize("ext", [".json", ".npz"])
def test_edge_ids_are_never_reshaped_or_truncated(
    tmp_path: Path, ext: str, edges: Any, message: str
) -> None:
    path = tmp_path / f"g{ext}"
    if ext == ".npz" and np.asarray(edges).dtype == object:
        pytest.skip("NumPy files cannot hold Python integers this large")
    write_raw(path, POSITIONS, RADII, edges)
    with pytest.raises(ValueError, match=rf"g\{ext}: .*{message}"):
        load_graph(path)


def test_integer_valued_float_edge_ids_are_accepted(tmp_path: Path) -> None:
    path = tmp_path / "g.npz"
    write_raw(path, POSITIONS, RADII, np.array(EDGES, dtype=np.float64))
    graph = load_graph(path)
    assert graph.edges.dtype == np.int64
    assert graph.edges.tolist() == EDGES


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('{"format": "vesselflow-graph", "version": 1, "positions": [[1e999, 0, 0]]', "not a"),
        ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
        ("\udcff", "codec can't decode|surrogates"),
        (
            '{"format": "vesselflow-graph", "version": 1, "spacing": [1, 1, 1], '
            '"positions": [[1e400, 0, 0]], "radii": [1], "edges": [], "info": {}, "params": {}}',
            r"positions\[0\] = \(inf, 0\.0, 0\.0\) is not finite",
        ),
        (
            '{"format": "vesselflow-graph", "version": 1, "spacing": [1, 1, 1], '
            f'"positions": [[{10**400}, 0, 0]], "radii": [1], "edges": [], "info": {{}}, '
            '"params": {}}',
            "positions must be numbers, got object",
        ),
        (
            '{"format": "vesselflow-graph", "version": 1, "spacing": [1, 1, 1], '
            '"positions": [], "radii": [], "edges": [], "info": [], "params": {}}',
            "info is not a JSON object",
        ),
    ],
)
def test_json_pathologies_are_value_errors(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "g.json"
    path.write_bytes(text.encode("utf-8", errors="surrogateescape"))
    with pytest.raises(ValueError, match=rf"g\.json: .*({message})"):
        load_graph(path)


@pytest.mark.parametrize(
    ("name", "data", "message"),
    [
        ("g.npz", b"PK\x03\x04 not really a zip", "not an .npz"),
        ("g.graphml", b"<graphml><graph><node id='0'>", "not a readable"),
        ("g.graphml", b"<graphml><graph edgedefault='directed'/></graphml>", "directed"),
        ("g.csv", b"id,x,y,z,r\n0,1,2,3\n", "row 1: wrong number of fields"),
        ("g.swc", b"1 0 0 0 0 1 -1\n2 0 1 0 0 1 1.5\n", r"SWC id '1\.5' is not an integer"),
        ("g.swc", b"1.5 0 0 0 0 1 -1\n", r"SWC id '1\.5' is not an integer"),
        ("g.swc", b"1 0 0 0 0 1 -1\n2 0 1 0 0 1 7\n", "SWC id 7 is not a sample"),
        ("g.swc", b"1 0 0 0 0 1 -1\n2 0 1 0 0 1 inf\n", r"SWC id 'inf' is not an integer"),
        ("g.swc", b"# loop-edge 1\n1 0 0 0 0 1 -1\n", "line 1: a loop-edge line needs 2"),
    ],
)
def test_damaged_files_are_value_errors(
    tmp_path: Path, name: str, data: bytes, message: str
) -> None:
    path = tmp_path / name
    path.write_bytes(data)
    csv_edges_path(path).write_text("source,target\n")
    with pytest.raises(ValueError, match=rf"{name.replace('.', '[.]')}: .*{message}"):
        load_graph(path)


def test_csv_edge_to_an_unknown_node_names_table_and_row(tmp_path: Path) -> None:
    path = tmp_path / "g.csv"
    path.write_text("id,x,y,z,r\na,0,0,0,1\nb,1,0,0,1\n")
    csv_edges_path(path).write_text("source,target\na,b\nb,c\n")
    with pytest.raises(ValueError, match=r"g\.edges\.csv row 2: target 'c' is not a node id"):
        load_graph(path)


@pytest.fixture
def repeated() -> VesselGraph:
    """A loop, a repeated edge and the same edge the other way round: a multigraph."""
    rng = np.random.default_rng(5)
    edges = [[0, 1], [1, 2], [2, 0], [2, 3], [2, 3], [3, 2], [4, 5]]
    return VesselGraph(rng.random((6, 3)) * 7, rng.random(6), edges, spacing=(1, 2, 3))


@pytest.mark.parametrize("ext", GRAPH_FORMATS)
def test_repeated_edges_round_trip_through_every_format(
    tmp_path: Path, repeated: VesselGraph, ext: str
) -> None:
    needs(ext)
    repeated.save(tmp_path / f"g{ext}")
    back = load_graph(tmp_path / f"g{ext}")
    assert back.n_edges == 7
    assert_same_graph(back, repeated)


def test_graphml_node_declared_only_by_an_edge_is_named(tmp_path: Path) -> None:
    path = tmp_path / "g.graphml"
    write_raw(path, POSITIONS[:2], RADII[:2], [[0, 1], [1, 2]])
    with pytest.raises(ValueError, match=r"g\.graphml: .*node '2' has no 'x'"):
        load_graph(path)


def test_constructor_refuses_with_the_rule_and_says_a_run_never_does_this() -> None:
    with pytest.raises(ValueError, match=r"radii\[1\] = -0\.5.*internal error, please report"):
        VesselGraph(POSITIONS, [1.0, -0.5, 0.25], EDGES)
    with pytest.raises(ValueError, match=r"positions must have shape \(N, 3\), got \(2, 2\)"):
        VesselGraph([[0, 0], [1, 1]], [1, 1], [])
    with pytest.raises(ValueError, match=r"spacing \[1\.0, 0\.0, 1\.0\] must be 3 finite"):
        VesselGraph(POSITIONS, RADII, EDGES, spacing=(1, 0, 1))
    # Empty arrays of either shape stand for no nodes and no edges.
    empty = VesselGraph([], [], [])
    assert empty.positions.shape == (0, 3)
    assert empty.edges.shape == (0, 2)


@pytest.mark.parametrize("ext", GRAPH_FORMATS)
@pytest.mark.parametrize(
    ("attribute", "index", "value", "message"),
    [
        ("positions", (2, 0), np.nan, r"positions\[2\]"),
        ("radii", 0, -1.0, r"radii\[0\] = -1\.0"),
        ("edges", (1, 1), 1, r"edges\[1\] joins node 1 to itself"),
        ("edges", (0, 0), 3, r"edges\[0\] = \(3, 1\) refers to a node outside 0\.\.2"),
    ],
)
def test_save_refuses_a_graph_changed_after_construction_and_writes_nothing(
    tmp_path: Path, ext: str, attribute: str, index: Any, value: float, message: str
) -> None:
    needs(ext)
    graph = VesselGraph(POSITIONS, RADII, EDGES)
    getattr(graph, attribute)[index] = value
    path = tmp_path / f"g{ext}"
    with pytest.raises(
        ValueError,
        match=rf"cannot save .*g\{ext}: invalid graph: {message}.*"
        "internal error, please report",
    ):
        graph.save(path)
    assert list(tmp_path.iterdir()) == []


def test_check_graph_arrays_converts_and_keeps_repeated_edges() -> None:
    positions, radii, edges, spacing = check_graph_arrays(
        np.arange(6, dtype=np.int32).reshape(2, 3), [1, 0], [[0, 1], [1, 0]], (1, 1, 1)
    )
    assert positions.dtype == radii.dtype == spacing.dtype == np.float64
    assert edges.dtype == np.int64
    assert edges.tolist() == [[0, 1], [1, 0]]


# Files are whole or absent.


@pytest.fixture
def small() -> VesselGraph:
    return VesselGraph(POSITIONS, RADII, EDGES)


def temps(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if p.name.startswith(".vesselflow-")]


def test_csv_save_failing_on_the_nodes_table_keeps_the_old_edges_table(
    tmp_path: Path, small: VesselGraph
) -> None:
    (tmp_path / "g.csv").mkdir()  # the nodes table cannot be replaced
    csv_edges_path(tmp_path / "g.csv").write_text("old")
    with pytest.raises(OSError, match=r"g\.csv"):
        small.save(tmp_path / "g.csv")
    assert (tmp_path / "g.edges.csv").read_text() == "old"
    assert temps(tmp_path) == []


def test_csv_save_that_cannot_write_the_second_table_keeps_both(
    tmp_path: Path, small: VesselGraph
) -> None:
    # The all-or-nothing replacement itself (a rename failing part-way) is tested in
    # Rust: crates/io/tests/formats.rs, replace_all_puts_everything_back_...
    path = tmp_path / "g.csv"
    path.write_text("old nodes")
    csv_edges_path(path).mkdir()
    (csv_edges_path(path) / "x").write_text("")
    with pytest.raises(IsADirectoryError, match=r"g\.edges\.csv"):
        small.save(path)
    assert path.read_text() == "old nodes"
    assert temps(tmp_path) == []


@pytest.mark.skipif(sys.platform == "win32", reason="needs POSIX signals")
@pytest.mark.parametrize("ext", [".csv", ".swc"])
def test_sigterm_during_a_write_leaves_complete_files_and_no_temporaries(
    tmp_path: Path, small: VesselGraph, monkeypatch: pytest.MonkeyPatch, ext: str
) -> None:
    path = tmp_path / f"g{ext}"
    path.write_text("old")
    real_write = vesselflow._core.write_graph

    def sigterm_then_write(*args: Any) -> None:
        # Pending during the Rust write, as a signal that arrives in it is: Python
        # handles it when the call returns.
        signal.pthread_sigmask(signal.SIG_BLOCK, [signal.SIGTERM])
        signal.pthread_kill(threading.get_ident(), signal.SIGTERM)  # to this thread
        try:
            real_write(*args)
        finally:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGTERM])

    monkeypatch.setattr(vesselflow._core, "write_graph", sigterm_then_write)
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated), sigterm_raises() as terminated:
        small.save(path)
    monkeypatch.undo()
    assert terminated == [True]
    assert_same_graph(load_graph(path), small)  # one Rust call: the new files, whole
    assert temps(tmp_path) == []
    assert signal.getsignal(signal.SIGTERM) == before


@pytest.mark.skipif(sys.platform == "win32", reason="needs POSIX signals")
def test_sigterm_stops_the_console_program_without_output_and_exit_143(tmp_path: Path) -> None:
    np.save(tmp_path / "mask.npy", make_slow_tube())
    argv = [sys.executable, "-m", "vesselflow", "skeletonize", str(tmp_path / "mask.npy")]
    with subprocess.Popen(
        [*argv, "-o", str(tmp_path / "graph.json")],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
    ) as proc:
        assert proc.stderr is not None
        first = proc.stderr.readline()  # the first progress report: the run has begun
        proc.send_signal(signal.SIGTERM)
        rest = proc.stderr.read()
        code = proc.wait(timeout=120)
    assert first, rest
    assert code == EXIT_TERMINATED == 143, first + rest
    assert "interrupted" in rest
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mask.npy"]


SAVE_IN_A_LOOP = """
import sys
import numpy as np
from vesselflow import VesselGraph
from vesselflow.__main__ import EXIT_TERMINATED, Terminated, sigterm_raises

rng = np.random.default_rng(0)
n = 200_000
graph = VesselGraph(rng.random((n, 3)), rng.random(n), np.c_[np.arange(n - 1), np.arange(1, n)])
try:
    with sigterm_raises():
        print("saving", flush=True)
        while True:
            graph.save(sys.argv[1])
except Terminated:
    sys.exit(EXIT_TERMINATED)
"""


@pytest.mark.skipif(sys.platform == "win32", reason="needs POSIX signals")
@pytest.mark.parametrize("ext", [".csv", ".json"])
def test_sigterm_at_any_moment_of_saving_leaves_whole_files_only(tmp_path: Path, ext: str) -> None:
    """The child saves over and over; SIGTERM lands at some moment of a save (Python
    writer or Rust writer). Whatever the moment, the files are whole or absent."""
    out = tmp_path / f"g{ext}"
    with subprocess.Popen(
        [sys.executable, "-c", SAVE_IN_A_LOOP, str(out)], stdout=subprocess.PIPE, text=True
    ) as proc:
        assert proc.stdout is not None
        assert proc.stdout.readline() == "saving\n"
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=120)
    assert code == EXIT_TERMINATED
    assert temps(tmp_path) == []
    if out.exists():
        assert load_graph(out).n_nodes == 200_000
