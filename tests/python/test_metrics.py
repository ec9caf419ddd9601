"""Tests of vesselflow.metrics on hand-built graphs and analytic masks."""

from __future__ import annotations

from math import erf

import numpy as np
import pytest

from vesselflow import VesselGraph
from vesselflow.metrics import _euler_26, _SegmentIndex, diadem, netmets, radius_error, topology


def y_graph(offset: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> VesselGraph:
    """A Y: trunk 0-1 along axis 0, two daughters 1-2 and 1-3."""
    pos = np.array([[0, 0, 0], [10, 0, 0], [20, 6, 0], [20, -6, 0]], float) + offset
    return VesselGraph(pos, [3.0, 2.5, 1.5, 1.0], [[0, 1], [1, 2], [1, 3]])


def tree_graph() -> VesselGraph:
    """A binary tree of depth 3 (7 branches) in the plane axis 1-2, with z = axis 0 = 0."""
    pos = [[0.0, 0.0, 0.0], [0.0, 10.0, 0.0]]
    radii = [4.0, 3.0]
    edges = []
    frontier = [(1, 0.0, 8.0)]
    for _ in range(2):
        nxt = []
        for node, y_off, half in frontier:
            for sign in (1, -1):
                pos.append([0.0, pos[node][1] + 10.0, pos[node][2] + sign * half])
                radii.append(radii[node] * 0.8)
                edges.append([node, len(pos) - 1])
                nxt.append((len(pos) - 1, y_off, half / 2))
        frontier = nxt
    edges.append([0, 1])
    return VesselGraph(pos, radii, edges)


def subdivide(graph: VesselGraph, pieces: int) -> VesselGraph:
    """Every edge cut into ``pieces`` equal edges; radii interpolated linearly."""
    pos, radii, edges = list(graph.positions), list(graph.radii), []
    for a, b in graph.edges.tolist():
        prev = a
        for i in range(1, pieces):
            f = i / pieces
            pos.append((1 - f) * graph.positions[a] + f * graph.positions[b])
            radii.append((1 - f) * graph.radii[a] + f * graph.radii[b])
            edges.append([prev, len(pos) - 1])
            prev = len(pos) - 1
        edges.append([prev, b])
    return VesselGraph(pos, radii, edges)


def drop_edge(graph: VesselGraph, edge: tuple[int, int]) -> VesselGraph:
    keep = [e for e in graph.edges.tolist() if sorted(e) != sorted(edge)]
    used = sorted({n for e in keep for n in e})
    remap = {old: new for new, old in enumerate(used)}
    return VesselGraph(
        graph.positions[used], graph.radii[used], [[remap[a], remap[b]] for a, b in keep]
    )


# ---------------------------------------------------------------------------------- NetMets


@pytest.mark.parametrize("mode", ["netmets", "vascgraph"])
@pytest.mark.parametrize("make", [y_graph, tree_graph])
def test_identical_graphs_score_zero(mode, make):
    g = make()
    rates = netmets(g, g, 1.0, mode=mode)
    assert set(rates) == {"gfnr", "gfpr", "cfnr", "cfpr"}
    for value in rates.values():
        assert value == pytest.approx(0.0, abs=1e-12)


def test_deleted_branch_raises_only_false_negatives():
    truth = y_graph()
    graph = drop_edge(truth, (1, 3))  # the junction becomes a degree-2 node
    rates = netmets(truth, graph, 1.0)
    # along the missing daughter (length L) the distance to the kept one is s * sin(angle):
    # the integral of 1 - exp(-d^2 / 2) is L - sqrt(pi / 2) / sin(angle), over 10 + 2 L
    length = np.hypot(10, 6)
    sin_angle = np.sin(2 * np.arctan(0.6))
    missing = (length - np.sqrt(np.pi / 2) / sin_angle) / (10 + 2 * length)
    assert rates["gfnr"] == pytest.approx(missing, rel=1e-4)
    assert rates["gfpr"] == pytest.approx(0.0, abs=1e-12)
    # truth branches (0,1) (1,2) (1,3): the junction is transparent; only 0-2 survives
    assert rates["cfnr"] == pytest.approx(2 / 3)
    assert rates["cfpr"] == 0.0


def test_false_spur_raises_only_false_positives():
    truth = VesselGraph([[0, 0, 0], [20, 0, 0]], [1, 1], [[0, 1]])
    graph = VesselGraph(
        [[0, 0, 0], [10, 0, 0], [20, 0, 0], [10, 8, 0]], [1, 1, 1, 1], [[0, 1], [1, 2], [1, 3]]
    )
    rates = netmets(truth, graph, 1.0)
    assert rates["gfnr"] == pytest.approx(0.0, abs=1e-12)
    assert rates["cfnr"] == 0.0
    # along the spur d = s: the integral over [0, 8] of 1 - exp(-s^2 / 2)
    # is 8 - sqrt(pi / 2) erf(8 / sqrt 2)
    assert rates["gfpr"] == pytest.approx((8 - np.sqrt(np.pi / 2) * erf(8 / np.sqrt(2))) / 28)
    assert rates["cfpr"] == pytest.approx(2 / 3)


def test_far_shift_gives_rates_near_one():
    truth = tree_graph()
    rates = netmets(truth, tree_graph_shifted(50.0), 1.0)
    for value in rates.values():
        assert value == pytest.approx(1.0, abs=1e-9)


def tree_graph_shifted(shift: float) -> VesselGraph:
    g = tree_graph()
    return VesselGraph(g.positions + np.array([shift, 0, 0]), g.radii, g.edges)


def test_vascgraph_far_shift_and_its_trimming():
    rng = np.random.default_rng(3)
    truth = subdivide(tree_graph(), 1)
    # every junction/endpoint far away, by distances that differ
    jitter = rng.uniform(40, 60, size=(truth.n_nodes, 1)) * np.array([[1.0, 0, 0]])
    graph = VesselGraph(truth.positions + jitter, truth.radii, truth.edges)
    rates = netmets(truth, graph, 1.0, mode="vascgraph")
    # VascGraph sets the largest 1 % of distances to zero: with 8 core nodes that is one node
    assert rates["gfnr"] == pytest.approx(7 / 8, abs=1e-9)
    assert rates["gfpr"] == pytest.approx(7 / 8, abs=1e-9)
    assert rates["cfnr"] == 1.0
    assert rates["cfpr"] == 1.0


def test_vascgraph_counts_a_bridging_branch_as_false_positive():
    truth = y_graph()
    rates = netmets(truth, drop_edge(truth, (1, 3)), 1.0, mode="vascgraph")
    assert rates["cfnr"] == 1.0
    assert rates["cfpr"] == 1.0
    assert rates["gfpr"] == pytest.approx(0.0, abs=1e-12)


def test_subdividing_edges_does_not_change_netmets():
    truth = tree_graph()
    shifted = VesselGraph(truth.positions + np.array([0.6, 0.3, 0]), truth.radii, truth.edges)
    coarse = netmets(truth, shifted, 1.0)
    fine = netmets(truth, subdivide(shifted, 7), 1.0)
    assert 0.05 < coarse["gfnr"] < 0.5  # a real, partial geometric error
    for key in coarse:
        assert fine[key] == pytest.approx(coarse[key], abs=1e-3)
    assert fine["cfnr"] == coarse["cfnr"]
    assert fine["cfpr"] == coarse["cfpr"]


def test_loops_are_branches():
    # a square cycle (isolated loop) and a junction carrying a loop
    square = VesselGraph(
        [[0, 0, 0], [0, 10, 0], [0, 10, 10], [0, 0, 10]],
        np.ones(4),
        [[0, 1], [1, 2], [2, 3], [3, 0]],
    )
    assert netmets(square, square, 1.0) == pytest.approx(
        {"gfnr": 0, "gfpr": 0, "cfnr": 0, "cfpr": 0}, abs=1e-12
    )
    lasso = VesselGraph(
        [[0, 0, 0], [10, 0, 0], [15, 5, 0], [15, -5, 0]],
        np.ones(4),
        [[0, 1], [1, 2], [2, 3], [3, 1]],
    )
    stick = VesselGraph([[0, 0, 0], [10, 0, 0]], np.ones(2), [[0, 1]])
    rates = netmets(lasso, stick, 1.0)
    assert rates["cfnr"] == pytest.approx(0.5)  # the loop branch (1, 1) is missed
    assert rates["cfpr"] == pytest.approx(0.0)
    assert netmets(lasso, lasso, 1.0)["cfnr"] == 0.0


def test_segment_index_is_exact_against_brute_force():
    rng = np.random.default_rng(7)
    a = rng.uniform(0, 20, size=(300, 3))
    b = a + rng.normal(scale=rng.uniform(0.1, 5, size=(300, 1)), size=(300, 3))
    b[:5] = a[:5]  # a few zero-length segments
    q = rng.uniform(-5, 25, size=(500, 3))
    d, seg, t = _SegmentIndex(a, b, 0.5).nearest(q)
    ab = b - a
    len2 = (ab**2).sum(1)
    tt = np.clip(
        np.divide(((q[:, None] - a) * ab).sum(2), len2, out=np.zeros((500, 300)), where=len2 > 0),
        0,
        1,
    )
    brute = np.linalg.norm(q[:, None] - (a + tt[..., None] * ab), axis=2)
    np.testing.assert_allclose(d, brute.min(axis=1), rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(q - (a[seg] + t[:, None] * ab[seg]), axis=1), d)


def test_netmets_rejects_bad_input():
    g = y_graph()
    with pytest.raises(ValueError, match="sigma"):
        netmets(g, g, 0.0)
    with pytest.raises(ValueError, match="mode"):
        netmets(g, g, 1.0, mode="bogus")
    with pytest.raises(TypeError, match="VesselGraph"):
        netmets(g.positions, g, 1.0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="step"):
        netmets(g, g, 1.0, step=-1)


# ---------------------------------------------------------------------------------- DIADEM


def test_diadem_identical_is_one_and_missing_branch_loses_its_weight():
    truth = tree_graph()
    assert diadem(truth, truth) == 1.0
    assert diadem(truth, subdivide(truth, 3)) == 1.0
    # drop one deepest termination (edge 2-4): the gold tip (weight 1) is missed, and its
    # parent bifurcation (degree 2) becomes a continuation in the test tree, so it is missed too
    graph = drop_edge(truth, (2, 4))
    # gold weights: 1 trunk bifurcation of degree 4, 2 of degree 2, 4 tips of 1: total 12
    assert diadem(truth, graph) == pytest.approx((12 - 3) / 12)


def test_diadem_path_length_rule_rejects_a_detour():
    truth = VesselGraph([[0, 0, 0], [0, 0, 20]], [2, 1], [[0, 1]])
    # same end points, but the test path wanders: 2 * hypot(10, 10) = 28.3 > 1.08 * 20
    detour = VesselGraph([[0, 0, 0], [0, 10, 10], [0, 0, 20]], [2, 1, 1], [[0, 1], [1, 2]])
    assert diadem(truth, detour) == 0.0
    # a straight but slightly displaced test tip still matches
    close = VesselGraph([[0, 0, 0], [0, 0.5, 20]], [2, 1], [[0, 1]])
    assert diadem(truth, close) == 1.0


def test_diadem_without_a_z_axis_compares_3d_path_lengths():
    # A straight gold path along axis 2; the test path zigzags +-0.5 along axis 0 (the
    # default z axis) every 2.5 units: its 3-D length is 7 % longer, its summed |dz| 7 of 20.
    truth = VesselGraph([[0, 0, 0], [0, 0, 20]], [2, 1], [[0, 1]])
    zig = [[0.5 * (-1.0) ** k if 0 < k < 8 else 0.0, 0, 2.5 * k] for k in range(9)]
    graph = VesselGraph(zig, np.ones(9), [[k, k + 1] for k in range(8)])
    assert diadem(truth, graph, z_axis=0) == 0.0  # the z path (7) exceeds 0.2 * 20
    assert diadem(truth, graph, z_axis=None) == 1.0  # 3-D path 21.4 is within 0.08 * 20
    assert diadem(truth, graph, z_axis=None, xy_path_thresh=0.05) == 0.0
    with pytest.raises(ValueError, match="z_axis"):
        diadem(truth, graph, z_axis=3)


def test_diadem_excess_nodes_count_against_score():
    truth = VesselGraph([[0, 0, 0], [0, 0, 20]], [2, 1], [[0, 1]])
    spur = VesselGraph(
        [[0, 0, 0], [0, 0, 10], [0, 0, 20], [0, 8, 10]], [2, 1, 1, 1], [[0, 1], [1, 2], [1, 3]]
    )
    # the extra bifurcation (degree 2) and tip (1) are excess: 1 / (1 + 3)
    assert diadem(truth, spur) == pytest.approx(1 / 4)
    assert diadem(truth, spur, excess_nodes=False) == 1.0


def test_diadem_takes_the_minimum_spanning_tree_of_a_loopy_graph():
    truth = VesselGraph([[0, 0, 0], [0, 0, 20]], [2, 1], [[0, 1]])
    # a detour loop whose long side the spanning tree drops
    loopy = VesselGraph([[0, 0, 0], [0, 0, 20], [0, 3, 10]], [2, 1, 1], [[0, 1], [0, 2], [2, 1]])
    assert diadem(truth, loopy) == pytest.approx(1.0)


def test_diadem_rejects_bad_input():
    g = y_graph()
    with pytest.raises(ValueError, match="root"):
        diadem(g, g, root=99)
    with pytest.raises(ValueError, match="xy_threshold"):
        diadem(g, g, xy_threshold=-1)
    with pytest.raises(ValueError, match="weight_scheme"):
        diadem(g, g, weight_scheme=7)
    ring = VesselGraph([[0, 0, 0], [0, 1, 0], [0, 1, 1]], np.ones(3), [[0, 1], [1, 2], [2, 0]])
    with pytest.raises(ValueError, match="degree-1"):
        diadem(ring, ring)


# ---------------------------------------------------------------------------------- radii


def test_radius_error_scaled_radii():
    truth = subdivide(tree_graph(), 4)
    graph = VesselGraph(truth.positions, truth.radii * 1.1, truth.edges)
    plain = radius_error(truth, graph, 1.0)
    assert plain["mape"] == pytest.approx(10.0, rel=1e-9)
    assert plain["n_matched"] == truth.n_nodes
    norm = radius_error(truth, graph, 1.0, normalised=True)
    assert norm["mape"] == pytest.approx(0.0, abs=1e-9)  # blind to a global scale


def test_radius_error_interpolates_along_segments_and_respects_max_dist():
    truth = VesselGraph([[0, 0, 0], [10, 0, 0]], [1.0, 3.0], [[0, 1]])
    graph = VesselGraph([[2.5, 0.2, 0], [5, 0, 0], [5, 9, 0]], [1.5, 2.0, 7.0], [])
    out = radius_error(truth, graph, 1.0)
    assert out["n_matched"] == 2
    assert out["n_unmatched"] == 1
    assert out["mape"] == pytest.approx(0.0, abs=1e-12)  # r = 1.5 at 2.5, 2.0 at 5
    with pytest.raises(ValueError, match="max_dist"):
        radius_error(truth, graph, 0)


# ---------------------------------------------------------------------------------- topology


def ball(shape, centre, radius):
    i, j, k = np.indices(shape)
    return (i - centre[0]) ** 2 + (j - centre[1]) ** 2 + (k - centre[2]) ** 2 <= radius**2


def ring_graph(n: int = 12) -> VesselGraph:
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    pos = np.stack([np.full(n, 5.5), 17.5 + 12 * np.cos(ang), 17.5 + 12 * np.sin(ang)], 1)
    return VesselGraph(pos, np.ones(n), [[i, (i + 1) % n] for i in range(n)])


def test_topology_torus_has_one_loop(torus):
    out = topology(torus, ring_graph())
    assert out["mask_components"] == 1
    assert out["mask_loops"] == 1
    assert out["mask_cavities"] == 0
    assert out["graph_cycles"] == 1
    assert out["components_equal"]
    assert out["loops_equal"]


def test_topology_two_tubes_two_components():
    mask = np.zeros((20, 20, 20), bool)
    mask[:, 4:7, 4:7] = True
    mask[:, 13:16, 13:16] = True
    line = VesselGraph([[0, 5, 5], [19, 5, 5]], [1, 1], [[0, 1]])
    out = topology(mask, line)
    assert out["mask_components"] == 2
    assert out["graph_components"] == 1
    assert not out["components_equal"]
    assert out["mask_loops"] == 0


def test_topology_hollow_sphere_has_a_cavity_not_a_loop():
    mask = ball((25, 25, 25), (12, 12, 12), 10) & ~ball((25, 25, 25), (12, 12, 12), 7)
    point = VesselGraph([[12, 12, 2]], [1], np.zeros((0, 2)))
    out = topology(mask, point)
    assert out["mask_cavities"] == 1
    assert out["mask_euler"] == 2
    assert out["mask_loops"] == 0
    assert out["graph_components"] == 1
    assert out["graph_cycles"] == 0


def test_topology_diagonal_voxels_are_connected():
    mask = np.zeros((4, 4, 4), bool)
    mask[1, 1, 1] = mask[2, 2, 2] = True  # touch at a corner only: 26-connected
    out = topology(mask, VesselGraph(np.zeros((0, 3)), [], np.zeros((0, 2))))
    assert out["mask_components"] == 1
    assert out["mask_euler"] == 1
    assert out["mask_loops"] == 0


def test_euler_characteristic_matches_skimage():
    measure = pytest.importorskip("skimage.measure")
    rng = np.random.default_rng(11)
    for density in (0.15, 0.4, 0.6, 0.85):
        mask = rng.random((9, 10, 11)) < density
        assert _euler_26(mask) == measure.euler_number(mask, connectivity=3)


def test_topology_rejects_bad_input(torus):
    with pytest.raises(ValueError, match="3-D"):
        topology(torus[0], ring_graph())
    with pytest.raises(ValueError, match="outside"):
        topology(torus, ring_graph(), spacing=(0.1, 0.1, 0.1))
