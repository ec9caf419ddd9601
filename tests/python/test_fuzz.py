"""Property-based tests (hypothesis) of the file readers: random bytes, and valid files
truncated, extended or with bytes flipped, in every format of ``load_graph`` and of
``load_volume`` that the test can write. Each gives a result that passes the checks, or
a ``ValueError``, ``OSError`` or ``MemoryError`` whose message names the file: never
another exception, never a crash. Arrays with every kind of bad value follow the one
rule (:func:`vesselflow.graph.check_graph_arrays`) in every format, and valid graphs
with repeated edges round-trip through every format.

Two profiles: ``ci`` (the default: 60 examples per test, about 15 s in all) and
``long`` (``HYPOTHESIS_PROFILE=long``: 5 000 examples per test) for a long campaign,
for instance::

    HYPOTHESIS_PROFILE=long python3 -m pytest tests/python/test_fuzz.py
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from graph_files import GRAPH_FORMATS, assert_same_graph, write_raw
from vesselflow import VesselGraph, load_graph, load_volume
from vesselflow.graph import check_graph_arrays
from vesselflow.io import csv_edges_path

# No example database (no .hypothesis/ folder in the work tree): a failure prints the
# @reproduce_failure blob that replays it.
_COMMON: dict[str, Any] = {
    "deadline": None,
    "database": None,
    "print_blob": True,
    "suppress_health_check": [HealthCheck.too_slow],
}
settings.register_profile("ci", max_examples=60, **_COMMON)
settings.register_profile("long", max_examples=5_000, **_COMMON)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

MiB = 2**20
VOLUME_FORMATS = [".npy", ".npz", ".nii", ".nii.gz", ".tif"]
MAGICS = [b"PK\x03\x04", b"\x93NUMPY\x01\x00", b"II*\x00", b"MM\x00*", b"\x1f\x8b\x08\x00"]
MAGICS += [b"<?xml version='1.0'?><graphml", b"<VTKFile", b'{"format": "vesselflow-graph"']
TOKENS = [b"nan", b"-1", b"-0.5", b"1e999", b"9" * 25, b"1.5", b"[", b"]", b"{", b"\x00"]
TOKENS += [b",", b"\n", b" ", b'"', b"<", b">", b"inf", b"0", b"18446744073709551616"]


def needs(ext: str) -> None:
    if ext == ".vtp":
        pytest.importorskip("vtkmodules")
    elif ext.startswith(".nii"):
        pytest.importorskip("nibabel")
    elif ext == ".tif":
        pytest.importorskip("tifffile")


@pytest.fixture(scope="module")
def workdir() -> Iterator[Path]:
    with tempfile.TemporaryDirectory() as folder:
        yield Path(folder)


def sample_graph() -> VesselGraph:
    """Two components, a loop, a repeated edge; full-precision floats."""
    rng = np.random.default_rng(11)
    edges = [[0, 1], [1, 2], [2, 3], [3, 0], [3, 4], [5, 6], [5, 6]]
    graph = VesselGraph(rng.random((7, 3)) * 50, rng.random(7), edges, spacing=(0.5, 1, 2))
    graph.info = {"iterations": 3}
    return graph


def valid_graph_files(ext: str, folder: Path) -> dict[str, bytes]:
    """The file (and for .csv the edges table) of the sample graph, by name."""
    path = folder / f"valid{ext}"
    sample_graph().save(path)
    parts = [path, csv_edges_path(path)] if ext == ".csv" else [path]
    return {p.name.replace("valid", "g"): p.read_bytes() for p in parts}


def valid_volume_file(ext: str, folder: Path) -> bytes:
    mask = np.random.default_rng(2).random((4, 5, 6)) < 0.5
    path = folder / f"valid{ext}"
    if ext == ".npy":
        np.save(path, mask)
    elif ext == ".npz":
        np.savez(path, mask=mask.astype(np.uint8), spacing=[0.5, 1.0, 2.0])
    elif ext.startswith(".nii"):
        import nibabel as nib

        nib.save(nib.Nifti1Image(mask.astype(np.uint8), np.diag([0.5, 1, 2, 1])), path)
    else:
        import tifffile

        tifffile.imwrite(path, mask.astype(np.uint8) * 255, imagej=True, resolution=(2, 2))
    return path.read_bytes()


@st.composite
def mutations(draw: st.DrawFn, original: bytes) -> bytes:
    """``original`` after one to four edits: truncation, bytes flipped, inserted,
    deleted or overwritten (random bytes, or a token that parsers treat specially),
    random bytes appended."""
    data = bytearray(original)
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["truncate", "flip", "extend", "insert", "delete", "token"]))
        at = draw(st.integers(0, len(data)))
        if kind == "truncate":
            del data[at:]
        elif kind == "flip" and data:
            data[min(at, len(data) - 1)] ^= draw(st.integers(1, 255))
        elif kind == "extend":
            data += draw(st.binary(min_size=1, max_size=64))
        elif kind == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=16))
        elif kind == "delete":
            del data[at : at + draw(st.integers(1, 16))]
        elif kind == "token":
            token = draw(st.sampled_from(TOKENS))
            data[at : at + draw(st.integers(0, len(token)))] = token
    return bytes(data)


def random_bytes() -> st.SearchStrategy[bytes]:
    """Random bytes, bare or after the magic number of a format (to get past it)."""
    tail = st.binary(max_size=1024)
    return st.one_of(tail, st.tuples(st.sampled_from(MAGICS), tail).map(b"".join))


def assert_clean_error(path: Path, error: Exception) -> None:
    assert isinstance(error, (ValueError, OSError, MemoryError)), repr(error)
    assert path.name in str(error), repr(error)
    # What stopped the file, for --hypothesis-show-statistics: the words after the name.
    event(f"{type(error).__name__}: {str(error).split(path.name, 1)[1][2:50]}")


def assert_graph_outcome(path: Path) -> None:
    """Either a graph that passes the one rule, or a clean error naming the file."""
    try:
        graph = load_graph(path)
    except (ValueError, OSError, MemoryError) as e:
        error = e
    else:
        error = None
    if error is not None:
        assert_clean_error(path, error)
        return
    event("loaded")
    check_graph_arrays(graph.positions, graph.radii, graph.edges, graph.spacing)
    assert isinstance(graph.info, dict)
    assert isinstance(graph.params, dict)


def assert_volume_outcome(path: Path) -> None:
    try:
        mask, spacing = load_volume(path, max_memory=64 * MiB)
    except (ValueError, OSError, MemoryError) as e:
        error = e
    else:
        error = None
    if error is not None:
        assert_clean_error(path, error)
        return
    event("loaded")
    assert mask.dtype == np.bool_
    assert mask.ndim == 3
    assert len(spacing) == 3
    assert all(np.isfinite(s) and s > 0 for s in spacing)


@pytest.mark.parametrize("ext", GRAPH_FORMATS)
@given(data=st.data())
def test_graph_file_with_random_bytes(workdir: Path, ext: str, data: st.DataObject) -> None:
    needs(ext)
    path = workdir / f"random{ext}"
    path.write_bytes(data.draw(random_bytes(), label="file"))
    if ext == ".csv":
        csv_edges_path(path).write_bytes(data.draw(random_bytes(), label="edges table"))
    assert_graph_outcome(path)


@pytest.mark.parametrize("ext", GRAPH_FORMATS)
@given(data=st.data())
def test_damaged_graph_file(workdir: Path, ext: str, data: st.DataObject) -> None:
    needs(ext)
    originals = _cached(("graph", ext), lambda: valid_graph_files(ext, workdir))
    for name, original in originals.items():
        damaged = data.draw(st.one_of(st.just(original), mutations(original)), label=name)
        (workdir / name).write_bytes(damaged)
    assert_graph_outcome(workdir / f"g{ext}")


@pytest.mark.parametrize("ext", VOLUME_FORMATS)
@given(content=random_bytes())
def test_volume_file_with_random_bytes(workdir: Path, ext: str, content: bytes) -> None:
    needs(ext)
    path = workdir / f"random{ext}"
    path.write_bytes(content)
    assert_volume_outcome(path)


@pytest.mark.parametrize("ext", VOLUME_FORMATS)
@given(data=st.data())
def test_damaged_volume_file(workdir: Path, ext: str, data: st.DataObject) -> None:
    needs(ext)
    original = _cached(("volume", ext), lambda: valid_volume_file(ext, workdir))
    path = workdir / f"damaged{ext}"
    path.write_bytes(data.draw(mutations(original), label="file"))
    assert_volume_outcome(path)


_CACHE: dict[Any, Any] = {}


def _cached(key: Any, make: Any) -> Any:
    if key not in _CACHE:
        _CACHE[key] = make()
    return _CACHE[key]


# Values that a file can hold and the rule must judge: every special float, and ids
# that are negative, too large, non-integer or the same at both ends.
SPECIAL = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, -1.0, 0.5, 1.0, 2.0, 3.0, 1e300, -1e-300]),
)


@st.composite
def raw_graphs(draw: st.DrawFn) -> dict[str, Any]:
    n = draw(st.integers(0, 5))
    positions = draw(hnp.arrays(np.float64, (n, 3), elements=SPECIAL))
    radii = draw(hnp.arrays(np.float64, (n,), elements=SPECIAL))
    ids = st.one_of(st.integers(-2, n + 1), st.sampled_from([0.5, 1.0, 2**53, -0.0]))
    edges = draw(st.lists(st.tuples(ids, ids), max_size=6))
    spacing = draw(hnp.arrays(np.float64, (3,), elements=SPECIAL))
    return {"positions": positions, "radii": radii, "edges": edges, "spacing": spacing}


def rule_accepts(arrays: dict[str, Any]) -> bool:
    try:
        check_graph_arrays(**arrays)
    except ValueError:
        return False
    return True


@pytest.mark.parametrize("ext", [".json", ".npz"])
@given(arrays=raw_graphs())
def test_every_value_is_judged_by_the_one_rule(
    workdir: Path, ext: str, arrays: dict[str, Any]
) -> None:
    path = workdir / f"raw{ext}"
    edges = arrays["edges"]
    if ext == ".npz":  # a NumPy array of mixed ids is float: as NumPy would store it
        arrays = {**arrays, "edges": np.array(edges, dtype=float).reshape(-1, 2)}
    write_raw(path, **arrays)
    if not rule_accepts(arrays):
        with pytest.raises(ValueError, match=path.name):
            load_graph(path)
        with pytest.raises(ValueError, match="internal error, please report"):
            VesselGraph(**arrays)
        return
    graph = load_graph(path)
    np.testing.assert_array_equal(graph.positions, np.reshape(arrays["positions"], (-1, 3)))
    np.testing.assert_array_equal(graph.radii, arrays["radii"])
    np.testing.assert_array_equal(graph.edges, np.reshape(np.array(edges, dtype=float), (-1, 2)))


FINITE = st.floats(-1e6, 1e6, allow_nan=False, allow_subnormal=False)
POSITIVE = st.floats(1e-6, 1e6, allow_subnormal=False)


@st.composite
def valid_graphs(draw: st.DrawFn) -> VesselGraph:
    """Graphs with distinct positions (so node order can be recovered), any radii >= 0,
    and edges that may repeat, either way round."""
    points = draw(st.lists(st.tuples(FINITE, FINITE, FINITE), unique=True, max_size=8))
    n = len(points)
    radii = draw(st.lists(st.floats(0, 1e3, allow_subnormal=False), min_size=n, max_size=n))
    pairs = st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)).filter(lambda e: e[0] != e[1])
    edges = draw(st.lists(pairs, max_size=12)) if n >= 2 else []
    spacing = draw(st.tuples(POSITIVE, POSITIVE, POSITIVE))
    return VesselGraph(points, radii, edges, spacing=spacing)


@pytest.mark.parametrize("ext", GRAPH_FORMATS)
@given(graph=valid_graphs())
@settings(suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
def test_valid_graphs_round_trip_through_every_format(
    workdir: Path, ext: str, graph: VesselGraph
) -> None:
    needs(ext)
    path = workdir / f"round{ext}"
    graph.save(path)
    back = load_graph(path)
    assert_same_graph(back, graph)
    if ext != ".csv":
        np.testing.assert_array_equal(back.spacing, graph.spacing)
