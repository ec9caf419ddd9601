"""Running on NumPy masks: dtypes, memory layouts, bad input, progress, interrupts."""

from __future__ import annotations

import os
import signal
import threading
import tracemalloc

import networkx as nx
import numpy as np
import pytest

import vesselflow
from conftest import make_slow_tube, make_tube
from vesselflow import _core


def assert_same_graph(a: vesselflow.VesselGraph, b: vesselflow.VesselGraph) -> None:
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.radii, b.radii)
    np.testing.assert_array_equal(a.edges, b.edges)


def test_result_arrays_have_the_contract_types(branching):
    g = vesselflow.skeletonize(branching, spacing=(1.0, 2.0, 0.5))
    assert g.positions.dtype == np.float64
    assert g.positions.shape == (g.n_nodes, 3)
    assert g.radii.dtype == np.float64
    assert g.radii.shape == (g.n_nodes,)
    assert g.edges.dtype == np.int64
    assert g.edges.shape == (g.n_edges, 2)
    assert g.spacing.tolist() == [1.0, 2.0, 0.5]
    assert np.all(g.edges[:, 0] < g.edges[:, 1])
    assert g.n_nodes > 10
    # The T has one junction and three ends.
    assert sorted(np.bincount(g.degrees()).tolist()[1::2]) == [1, 3]
    assert g.info["foreground_voxels"] == int(branching.sum())
    assert g.info["mask_components"] == 1
    assert isinstance(g.info["converged"], bool)
    assert isinstance(g.info["stage_seconds"], dict)
    assert "edt" in g.info["stage_seconds"]
    assert len(g.info["nodes_per_iteration"]) == g.info["iterations"] + 1


def test_positions_are_physical_in_array_axis_order(tube):
    g1 = vesselflow.skeletonize(tube)
    g2 = vesselflow.skeletonize(tube, spacing=(2.0, 1.0, 1.0))
    # Along axis 0 the tube spans voxels 0..29, i.e. 0..58 units at spacing 2: a
    # position beyond 29 can only be in physical units.
    assert g1.positions[:, 0].max() - g1.positions[:, 0].min() > 20
    assert 40 < g2.positions[:, 0].max() <= 58
    assert g2.positions[:, 0].min() >= 0
    np.testing.assert_allclose(g2.positions[:, 1:], 7.0, atol=0.5)


@pytest.mark.parametrize(
    "dtype", [np.uint8, np.int8, np.int16, np.uint16, np.int32, np.uint32, np.int64, np.uint64]
)
def test_integer_dtypes_give_the_bool_graph(branching, dtype):
    expected = vesselflow.skeletonize(branching)
    assert_same_graph(vesselflow.skeletonize(branching.astype(dtype)), expected)


def test_any_nonzero_value_is_vessel(branching):
    expected = vesselflow.skeletonize(branching)
    labels = branching.astype(np.int16) * np.int16(-300)
    assert_same_graph(vesselflow.skeletonize(labels), expected)
    # A bool view of bytes other than 0/1 must not be misread.
    bytes_ = branching.astype(np.uint8) * np.uint8(7)
    assert_same_graph(vesselflow.skeletonize(bytes_.view(bool)), expected)


def test_big_endian_mask(branching):
    expected = vesselflow.skeletonize(branching)
    assert_same_graph(vesselflow.skeletonize(branching.astype(">u2")), expected)


def test_memory_layouts_give_the_contiguous_graph(branching):
    expected = vesselflow.skeletonize(branching)
    fortran = np.asfortranarray(branching)
    assert fortran.flags.f_contiguous
    assert not fortran.flags.c_contiguous
    assert_same_graph(vesselflow.skeletonize(fortran), expected)

    padded = np.zeros((80, 24, 30), np.int32)
    padded[::2] = branching
    assert not padded[::2].flags.contiguous
    assert_same_graph(vesselflow.skeletonize(padded[::2]), expected)

    flipped = branching[::-1, :, ::-1].copy()[::-1, :, ::-1]
    assert flipped.strides[0] < 0
    assert flipped.strides[2] < 0
    assert_same_graph(vesselflow.skeletonize(flipped), expected)

    transposed = np.ascontiguousarray(branching.transpose(2, 0, 1)).transpose(1, 2, 0)
    assert_same_graph(vesselflow.skeletonize(transposed), expected)

    readonly = branching.copy()
    readonly.flags.writeable = False
    assert_same_graph(vesselflow.skeletonize(readonly), expected)


def test_strided_view_is_the_subsampled_mask(branching):
    view = branching[::2]
    assert_same_graph(vesselflow.skeletonize(view), vesselflow.skeletonize(view.copy()))


def test_bool_mask_is_read_without_a_copy():
    mask = np.zeros((64, 256, 128), bool, order="F")[:, ::2, :]  # 2 MiB, strided
    mask[20:40, 30:34, 60:64] = 1
    tracemalloc.start()
    try:
        vesselflow.skeletonize(mask)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < mask.nbytes / 8


@pytest.mark.parametrize("dtype", [np.complex128, object, "U1"])
def test_dtype_that_cannot_hold_a_mask_is_a_type_error(dtype):
    mask = np.zeros((4, 4, 4), dtype=dtype)
    with pytest.raises(TypeError, match=r"not bool, integer or float: it cannot be a mask"):
        vesselflow.skeletonize(mask)


@pytest.mark.parametrize("dtype", [np.float16, np.float32, ">f8"])
def test_float_0_1_mask_gives_the_bool_graph(branching, dtype):
    expected = vesselflow.skeletonize(branching)
    assert_same_graph(vesselflow.skeletonize(branching.astype(dtype)), expected)


@pytest.mark.parametrize("shape", [(5, 5), (2, 3, 4, 5), (7,)])
def test_wrong_ndim_is_a_value_error_naming_the_shape(shape):
    with pytest.raises(ValueError, match=r"3-D.*" + str(list(shape)).replace("[", r"\[")):
        vesselflow.skeletonize(np.ones(shape, bool))


@pytest.mark.parametrize("mask", [[[[1]]], None, "mask", 3])
def test_non_array_mask_is_a_type_error(mask):
    with pytest.raises(TypeError, match=r"numpy\.ndarray"):
        vesselflow.skeletonize(mask)


@pytest.mark.parametrize(
    "spacing",
    [
        (1.0, 1.0),
        (1.0, 1.0, 1.0, 1.0),
        (1.0, float("nan"), 1.0),
        (1.0, 1.0, float("inf")),
        (0.0, 1.0, 1.0),
        (1.0, -1.0, 1.0),
    ],
)
def test_bad_spacing_is_a_value_error(tube, spacing):
    with pytest.raises(ValueError, match="spacing"):
        vesselflow.skeletonize(tube, spacing=spacing)


def test_spacing_of_wrong_type_is_a_type_error(tube):
    with pytest.raises(TypeError):
        vesselflow.skeletonize(tube, spacing="111")
    with pytest.raises(TypeError):
        vesselflow.skeletonize(tube, spacing=None)  # type: ignore[arg-type]


def test_spacing_may_be_an_array_or_list(tube):
    expected = vesselflow.skeletonize(tube, spacing=(1.0, 0.5, 0.5))
    assert_same_graph(vesselflow.skeletonize(tube, spacing=np.array([1, 0.5, 0.5])), expected)
    assert_same_graph(vesselflow.skeletonize(tube, spacing=[1, 0.5, 0.5]), expected)


def test_empty_mask_gives_an_empty_graph():
    with pytest.warns(UserWarning, match="the mask is empty: the graph has no nodes"):
        g = vesselflow.skeletonize(np.zeros((10, 11, 12), bool))
    assert g.positions.shape == (0, 3)
    assert g.positions.dtype == np.float64
    assert g.radii.shape == (0,)
    assert g.radii.dtype == np.float64
    assert g.edges.shape == (0, 2)
    assert g.edges.dtype == np.int64
    assert g.n_nodes == 0
    assert g.degrees().shape == (0,)
    assert g.to_networkx().number_of_nodes() == 0


def test_zero_size_mask_gives_an_empty_graph():
    g = vesselflow.skeletonize(np.zeros((0, 5, 5), np.uint8))
    assert g.n_nodes == 0
    assert g.n_edges == 0


def test_all_foreground_is_a_solid_block_with_its_graph():
    g = vesselflow.skeletonize(np.ones((24, 8, 8), np.uint8))
    assert g.n_nodes > 0
    assert g.info["mask_components"] == 1
    # The inscribed ball (half the 8-voxel side) plus the radius cap's half voxel diagonal.
    assert (g.radii <= 4.0 + 0.5 * np.sqrt(3)).all()


def test_progress_receives_every_stage_in_order(branching):
    calls = []
    g = vesselflow.skeletonize(branching, progress=lambda *a: calls.append(a))
    stages = [c[0] for c in calls]
    assert stages[0] == "edt"
    assert stages[-1] == "output"
    assert {"grid", "contract"} <= set(stages)
    contract = [c for c in calls if c[0] == "contract"]
    assert len(contract) == g.info["iterations"]
    for stage, iteration, nodes, measure in calls:
        assert isinstance(stage, str)
        assert isinstance(iteration, int)
        assert isinstance(nodes, int)
        assert isinstance(measure, float)
    assert calls[-1][2] == g.n_nodes


def test_exception_in_progress_propagates_and_stops_the_run(branching):
    class Stop(Exception):
        pass

    seen = []

    def progress(stage, iteration, nodes, measure):
        seen.append(stage)
        if stage == "grid":
            raise Stop("from the callback")

    with pytest.raises(Stop, match="from the callback"):
        vesselflow.skeletonize(branching, progress=progress)
    assert seen[-1] == "grid"
    assert "contract" not in seen


def test_progress_must_be_callable(tube):
    with pytest.raises(TypeError, match="progress"):
        vesselflow.skeletonize(tube, progress=3)


@pytest.mark.skipif(not hasattr(signal, "pthread_kill"), reason="needs POSIX signals")
def test_signal_interrupts_a_run_with_the_gil_released():
    """SIGINT from another thread stops a run: that thread gets the GIL while the run
    goes on (released), and the run checks for signals between iterations."""

    class Interrupted(Exception):
        pass

    def handler(signum, frame):
        raise Interrupted

    mask = make_slow_tube()
    started = threading.Event()
    stages = []

    def progress(stage, *_):
        stages.append(stage)
        started.set()

    def interrupt():
        started.wait()
        os.kill(os.getpid(), signal.SIGINT)

    previous = signal.signal(signal.SIGINT, handler)
    try:
        killer = threading.Thread(target=interrupt)
        killer.start()
        with pytest.raises(Interrupted):
            vesselflow.skeletonize(mask, progress=progress)
        killer.join()
    finally:
        signal.signal(signal.SIGINT, previous)
    assert "output" not in stages


def test_threads_do_not_change_the_output(branching, torus):
    for mask in (branching, torus):
        one = vesselflow.skeletonize(mask, threads=1)
        two = vesselflow.skeletonize(mask, threads=2)
        assert_same_graph(one, two)
        assert one.n_nodes > 0


def test_torus_gives_one_cycle_on_its_centre_circle(torus):
    g = vesselflow.skeletonize(torus)
    graph = g.to_networkx()
    assert nx.number_connected_components(graph) == 1
    assert len(nx.cycle_basis(graph)) == 1
    distance = np.hypot(g.positions[:, 1] - 17.5, g.positions[:, 2] - 17.5)
    np.testing.assert_allclose(distance, 12.0, atol=0.75)
    np.testing.assert_allclose(g.positions[:, 0], 5.5, atol=0.5)


def test_two_tubes_give_two_components():
    mask = np.zeros((30, 15, 40), bool)
    mask[:, :, :15] = make_tube()
    mask[:, :, 25:] = make_tube()
    g = vesselflow.skeletonize(mask)
    assert g.info["mask_components"] == 2
    assert nx.number_connected_components(g.to_networkx()) == 2


def test_core_run_returns_arrays_and_info(tube):
    positions, radii, edges, info = _core.Skeletonizer().run(tube)
    assert positions.shape == (len(radii), 3)
    assert edges.shape[1] == 2
    assert positions.flags.c_contiguous
    assert positions.flags.writeable
    assert info["foreground_voxels"] == int(tube.sum())
