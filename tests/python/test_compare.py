"""vesselflow.compare: every available method on a tube and a Y with known centrelines."""

from __future__ import annotations

import sys
from types import ModuleType, SimpleNamespace

import networkx as nx
import numpy as np
import pytest
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from vesselflow import compare

AVAILABLE = compare.available()

# A capsule of radius 4 voxels around the segment (6, 11, 13) -> (33, 11, 13) (voxel
# indices), clear of the array border, at spacing (2, 1, 1): its axis runs along the
# anisotropic axis, from 12 to 66 in physical units.
TUBE_SPACING = (2.0, 1.0, 1.0)
TUBE_RADIUS = 4.0
TUBE_AXIS = ((6.0, 11.0, 13.0), (33.0, 11.0, 13.0))
# A Y of radius 3 voxels, spacing 1: trunk from (5, 21, 10) to the junction (20, 21, 10),
# arms to (36, 8, 10) and (36, 34, 10).
Y_RADIUS = 3.0
Y_JUNCTION = (20.0, 21.0, 10.0)
Y_ENDS = ((5.0, 21.0, 10.0), (36.0, 8.0, 10.0), (36.0, 34.0, 10.0))
Y_SEGMENTS = tuple((end, Y_JUNCTION) for end in Y_ENDS)


def segment_distance(points: np.ndarray, a: tuple[float, ...], b: tuple[float, ...]) -> np.ndarray:
    """Distance of every row of ``points`` to the segment ``a``-``b``."""
    start, direction = np.asarray(a), np.asarray(b) - np.asarray(a)
    t = np.clip((points - start) @ direction / (direction @ direction), 0.0, 1.0)
    return np.linalg.norm(points - (start + t[:, None] * direction), axis=1)


def tubes(shape: tuple[int, int, int], segments: tuple, radius: float) -> np.ndarray:
    """Voxels whose centre lies within ``radius`` of any segment (voxel units)."""
    centres = np.indices(shape).reshape(3, -1).T.astype(float)
    distance = np.min([segment_distance(centres, a, b) for a, b in segments], axis=0)
    return (distance <= radius).reshape(shape)


@pytest.fixture(scope="module")
def tube() -> np.ndarray:
    return tubes((40, 24, 26), (TUBE_AXIS,), TUBE_RADIUS)


@pytest.fixture(scope="module")
def y_shape() -> np.ndarray:
    return tubes((42, 43, 21), Y_SEGMENTS, Y_RADIUS)


def needs(method: str) -> None:
    if AVAILABLE[method] is not None:
        pytest.skip(f"{method}: {AVAILABLE[method]}")


def reference_edt_radii(mask: np.ndarray, positions: np.ndarray, spacing: tuple) -> np.ndarray:
    """The radius rule written out again: EDT at the voxel nearest each node."""
    distance = ndimage.distance_transform_edt(mask, sampling=spacing)
    index = np.clip(
        np.rint(positions / np.asarray(spacing)).astype(int), 0, np.array(mask.shape) - 1
    )
    return distance[tuple(index.T)]


@pytest.mark.parametrize("method", compare.METHODS)
def test_tube_centreline_radii_and_units(method: str, tube: np.ndarray) -> None:
    needs(method)
    graph = compare.run(method, tube, spacing=TUBE_SPACING)
    assert graph.info["method"] == method
    assert 0.0 < graph.info["seconds"] < 60.0
    np.testing.assert_array_equal(graph.spacing, TUBE_SPACING)
    p = graph.positions
    assert graph.n_nodes >= 5
    assert graph.n_edges >= graph.n_nodes - 1
    # Physical units along the anisotropic axis: the axis spans 12..66, a graph left in
    # voxel units would end near 33 and one scaled twice would reach beyond 100.
    assert p[:, 0].min() < 20.0
    assert 58.0 < p[:, 0].max() < 2.0 * (TUBE_AXIS[1][0] + TUBE_RADIUS) + 1.0
    # Away from the rounded ends every node is within 1.5 voxels (spacing 1 across the
    # axis) of the true axis, which sits off-centre so that swapped axes would show.
    inner = (p[:, 0] >= 2.0 * (TUBE_AXIS[0][0] + TUBE_RADIUS)) & (
        p[:, 0] <= 2.0 * (TUBE_AXIS[1][0] - TUBE_RADIUS)
    )
    assert inner.sum() >= 3
    off_axis = np.hypot(p[:, 1] - TUBE_AXIS[0][1], p[:, 2] - TUBE_AXIS[0][2])
    assert off_axis[inner].max() <= 1.5
    # Radii within a voxel of the true radius there.
    np.testing.assert_allclose(graph.radii[inner], TUBE_RADIUS, atol=1.0)
    if method == "vesselflow":
        assert graph.info["radii"] == "vesselflow"
    else:
        assert graph.info["radii"] == "edt"
        np.testing.assert_allclose(graph.radii, reference_edt_radii(tube, p, TUBE_SPACING))


@pytest.mark.parametrize("method", compare.METHODS)
def test_y_is_one_branching_graph_on_the_centrelines(method: str, y_shape: np.ndarray) -> None:
    needs(method)
    graph = compare.run(method, y_shape)
    p = graph.positions
    n = graph.n_nodes
    adjacency = coo_matrix((np.ones(graph.n_edges), tuple(graph.edges.T)), shape=(n, n))
    assert connected_components(adjacency, directed=False)[0] == 1
    degrees = graph.degrees()
    junctions = p[degrees >= 3]
    assert len(junctions) >= 1
    # A junction node near the true junction, and the graph reaching every free end.
    assert np.linalg.norm(junctions - Y_JUNCTION, axis=1).min() <= 2.0 * Y_RADIUS
    for end in Y_ENDS:
        assert np.linalg.norm(p - end, axis=1).min() <= Y_RADIUS + 1.0
    # Within 1.5 voxels of the centrelines except near the free ends (rounded caps) and
    # the junction (where the medial axis of two tubes leaves both axes).
    off_axis = np.min([segment_distance(p, a, b) for a, b in Y_SEGMENTS], axis=0)
    near_end = np.min([np.linalg.norm(p - end, axis=1) for end in Y_ENDS], axis=0)
    near_junction = np.linalg.norm(p - Y_JUNCTION, axis=1)
    keep = (near_end > Y_RADIUS + 1.5) & (near_junction > 2.0 * Y_RADIUS)
    assert keep.sum() >= 6
    assert off_axis[keep].max() <= 1.5


@pytest.mark.parametrize("method", [m for m in compare.METHODS if m != "vesselflow"])
def test_empty_mask_gives_an_empty_graph(method: str) -> None:
    needs(method)
    graph = compare.run(method, np.zeros((5, 6, 7), np.uint8), spacing=(1.0, 2.0, 3.0))
    assert (graph.n_nodes, graph.n_edges) == (0, 0)
    assert graph.info["method"] == method


def test_edt_radii_reads_the_nearest_voxel() -> None:
    mask = np.zeros((9, 9, 9), bool)
    mask[1:8, 2:7, 2:7] = True  # a 7 x 5 x 5 box
    spacing = (1.0, 2.0, 0.5)
    positions = np.array(
        [
            [4.2, 8.0, 2.1],  # nearest voxel (4, 4, 4), the centre: 3 voxels to the side
            [1.3, 8.9, 1.8],  # nearest voxel (1, 4, 4), on the face across axis 0
            [0.0, 8.0, 2.0],  # background voxel (0, 4, 4)
            [-3.0, 100.0, 2.0],  # clipped to (0, 8, 4), background
        ]
    )
    radii = compare.edt_radii(mask, positions, spacing)
    # At the centre the nearest background voxel centres are 3 voxels away along axes 0, 1
    # and 2, that is 3, 6 and 1.5; at (1, 4, 4) the one at (0, 4, 4) is 1 away.
    np.testing.assert_allclose(radii, [1.5, 1.0, 0.0, 0.0])
    np.testing.assert_allclose(radii, reference_edt_radii(mask, positions, spacing))
    assert compare.edt_radii(mask, np.zeros((0, 3)), spacing).shape == (0,)


def test_unknown_method_and_bad_input_are_named() -> None:
    mask = np.ones((3, 3, 3), bool)
    with pytest.raises(ValueError, match="unknown method 'soax'"):
        compare.run("soax", mask)
    with pytest.raises(ValueError, match="3-D"):
        compare.run("voxel", np.ones((3, 3), bool))
    with pytest.raises(ValueError, match="spacing"):
        compare.run("voxel", mask, spacing=(1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="spacing"):
        compare.run("voxel", mask, spacing=(1.0, 1.0))
    with pytest.raises(TypeError, match="dtype"):
        compare.run("voxel", np.full((3, 3, 3), "a"))
    with pytest.raises(ValueError, match="finite"):
        compare.edt_radii(mask, [[np.nan, 0.0, 0.0]])


def test_unknown_option_is_a_type_error() -> None:
    needs("teasar")
    mask = np.zeros((4, 4, 4), bool)  # rejected before any work, even on an empty mask
    with pytest.raises(TypeError, match=r"'teasar': sigma \(accepted: const, max_paths"):
        compare.run("teasar", mask, sigma=1.0)
    with pytest.raises(TypeError, match="'mesh': smooth"):
        compare.run("mesh", mask, smooth=True)


def test_teasar_options_reach_kimimaro(tube: np.ndarray) -> None:
    needs("teasar")
    default = compare.run("teasar", tube, spacing=TUBE_SPACING)
    assert default.info["teasar_params"]["const"] == compare.TEASAR_PARAMS["const"] * 2.0
    # A huge invalidation radius leaves TEASAR one path only: a chain, no branches.
    chain = compare.run("teasar", tube, spacing=TUBE_SPACING, const=50.0)
    assert chain.params == {"const": 50.0}
    assert chain.info["teasar_params"]["const"] == 100.0
    assert chain.n_edges == chain.n_nodes - 1
    assert chain.degrees().max() <= 2
    assert (chain.degrees() == 1).sum() == 2


def test_missing_package_is_reported_and_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "kimimaro", None)  # makes `import kimimaro` fail
    reason = compare.available()["teasar"]
    assert reason is not None
    assert "kimimaro" in reason
    assert "vesselflow[bench]" in reason
    with pytest.raises(ImportError, match=r"method 'teasar' needs the package 'kimimaro'"):
        compare.run("teasar", np.ones((3, 3, 3), bool))


def test_available_lists_every_method_and_ours_is_there() -> None:
    assert list(AVAILABLE) == list(compare.METHODS)
    assert AVAILABLE["vesselflow"] is None
    assert all(reason is None or isinstance(reason, str) for reason in AVAILABLE.values())


def test_pointcloud_adapter_with_a_stand_in_lbc(
    monkeypatch: pytest.MonkeyPatch, tube: np.ndarray
) -> None:
    """pc-skeletor does not install here; check our side of it against a stand-in with its
    interface (open3d point cloud in; ``skeleton_graph`` with ``pos`` out): the surface
    points it gets are physical, and its node labels, which need not be 0..N-1, map to
    rows in order."""
    needs("mesh")  # the surface comes from scikit-image like the mesh method's
    seen: dict[str, object] = {}

    class StandInLBC:
        def __init__(self, point_cloud: np.ndarray, **options: object) -> None:
            seen["points"], seen["options"] = point_cloud, options

        def extract_skeleton(self) -> None:
            pass

        def extract_topology(self) -> None:
            # Three nodes: the means of the surface points in three slabs along axis 0.
            points = np.asarray(seen["points"])
            slabs = np.array_split(points[np.argsort(points[:, 0])], 3)
            self.skeleton_graph = nx.Graph()
            for label, slab in zip((30, 10, 20), slabs):
                self.skeleton_graph.add_node(label, pos=slab.mean(axis=0))
            self.skeleton_graph.add_edges_from([(30, 10), (10, 20)])

    open3d = ModuleType("open3d")
    open3d.geometry = SimpleNamespace(PointCloud=np.asarray)  # type: ignore[attr-defined]
    open3d.utility = SimpleNamespace(Vector3dVector=np.asarray)  # type: ignore[attr-defined]
    pc_skeletor = ModuleType("pc_skeletor")
    pc_skeletor.LBC = StandInLBC  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "open3d", open3d)
    monkeypatch.setitem(sys.modules, "pc_skeletor", pc_skeletor)
    assert compare.available()["pointcloud"] is None

    graph = compare.run("pointcloud", tube, spacing=TUBE_SPACING, filter_nb_neighbors=5)
    points = np.asarray(seen["points"])
    assert seen["options"] == {"down_sample": -1, "filter_nb_neighbors": 5}
    # The surface of the capsule in physical units: axis 0 from 2*(6-4) to 2*(33+4), the
    # cross-section a circle of radius ~4.5 (level 0.5 between voxel centres) around the axis.
    assert 2.0 < points[:, 0].min() < 5.0
    assert 73.0 < points[:, 0].max() < 76.0
    across = np.hypot(points[:, 1] - TUBE_AXIS[0][1], points[:, 2] - TUBE_AXIS[0][2])
    assert across.max() <= TUBE_RADIUS + 1.0
    # Labels 30, 10, 20 become rows 2, 0, 1 (sorted labels), edges follow.
    assert graph.n_nodes == 3
    order = np.argsort(graph.positions[:, 0])
    np.testing.assert_array_equal(order, [2, 0, 1])
    assert {tuple(e) for e in graph.edges.tolist()} == {(0, 2), (0, 1)}
    np.testing.assert_allclose(graph.positions[:, 1:], [TUBE_AXIS[0][1:]] * 3, atol=0.5)
    np.testing.assert_allclose(
        graph.radii, reference_edt_radii(tube, graph.positions, TUBE_SPACING)
    )
    assert graph.info["method"] == "pointcloud"
    assert graph.info["surface_vertices"] == len(points)
