"""Ground-truth generators: vesselflow.synth."""

from __future__ import annotations

import math

import networkx as nx
import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from vesselflow import VesselGraph, synth
from vesselflow.synth import _common

CUBE = np.ones((3, 3, 3), dtype=bool)
SIX = ndimage.generate_binary_structure(3, 1)


def n_components(mask: np.ndarray) -> int:
    return int(ndimage.label(mask, structure=CUBE)[1])


def loops(mask: np.ndarray) -> int:
    """b1 of the 26-connected foreground from scikit-image's Euler number (independent of
    the generators' own check): b1 = b0 + b2 - chi, b2 = enclosed background 6-components."""
    measure = pytest.importorskip("skimage.measure")
    chi = int(measure.euler_number(mask, connectivity=3))
    cavities = int(ndimage.label(~np.pad(mask, 1), structure=SIX)[1]) - 1
    return n_components(mask) + cavities - chi


def node_voxels(graph: VesselGraph) -> tuple[np.ndarray, ...]:
    vox = np.rint(graph.positions / graph.spacing).astype(int)
    return vox[:, 0], vox[:, 1], vox[:, 2]


def same(a: tuple[np.ndarray, VesselGraph], b: tuple[np.ndarray, VesselGraph]) -> bool:
    return (
        np.array_equal(a[0], b[0])
        and np.array_equal(a[1].positions, b[1].positions)
        and np.array_equal(a[1].radii, b[1].radii)
        and np.array_equal(a[1].edges, b[1].edges)
    )


# --------------------------------------------------------------------------- rasteriser


def brute_force_round_cone(shape, spacing, p0, p1, r0, r1, ss):
    """Slow reference: every sub-sample of every voxel against the union of 1001 balls."""
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    grid = np.stack(np.meshgrid(*(np.arange(n) for n in shape), indexing="ij"), -1)
    offs = np.stack(np.meshgrid(sub, sub, sub, indexing="ij"), -1).reshape(-1, 3)
    pts = ((grid[..., None, :] + offs) * spacing).reshape(-1, 3)
    t = np.linspace(0.0, 1.0, 1001)[:, None]
    centres = p0 + t * (p1 - p0)
    radii = r0 + t[:, 0] * (r1 - r0)
    inside = np.zeros(len(pts), dtype=bool)
    for c, r in zip(centres, radii):
        inside |= np.sum((pts - c) ** 2, axis=1) <= r * r
    count = inside.reshape(*shape, ss**3).sum(axis=-1)
    return 2 * count >= ss**3


@pytest.mark.parametrize(
    ("spacing", "r0", "r1"), [((1.0, 1.0, 1.0), 1.2, 3.0), ((1.5, 0.8, 1.0), 2.5, 1.0)]
)
def test_rasteriser_matches_brute_force_supersampling(spacing, r0, r1):
    sp = np.asarray(spacing)
    shape = (11, 13, 12)
    p0, p1 = np.array([3.3, 4.1, 4.2]), np.array([11.6, 8.7, 7.9])
    mask = np.zeros(shape, dtype=bool)
    _common._paint_round_cones(mask, sp, p0[None], p1[None], np.array([r0]), np.array([r1]), 3)
    reference = brute_force_round_cone(shape, sp, p0, p1, r0, r1, 3)
    assert reference.sum() > 100
    # Only sub-samples within ~1e-4 of the surface can differ (the reference's 1001 balls).
    assert np.count_nonzero(mask != reference) <= 2


@pytest.mark.parametrize(("radius", "tolerance"), [(1.5, 0.06), (3.0, 0.03)])
def test_cylinder_volume_is_capsule_volume(radius, tolerance):
    start, end = np.array([8.3, 10.1, 12.7]), np.array([39.2, 33.6, 30.1])
    mask, truth = synth.cylinder((48, 48, 48), radius, start=start, end=end)
    length = float(np.linalg.norm(end - start))
    expected = math.pi * radius**2 * length + 4 / 3 * math.pi * radius**3
    assert abs(np.count_nonzero(mask) / expected - 1) < tolerance
    # Truth: the centreline every half voxel, with the radius.
    steps = np.linalg.norm(np.diff(truth.positions, axis=0), axis=1)
    assert steps.max() <= 0.5 + 1e-9
    assert np.allclose(truth.positions[[0, -1]], [start, end])
    assert np.allclose(truth.radii, radius)
    assert truth.n_edges == truth.n_nodes - 1


def test_anisotropic_spacing_gives_same_physical_cylinder():
    start, end = (10.0, 20.3, 23.7), (50.0, 31.1, 18.2)
    volumes = []
    for spacing in [(1.0, 1.0, 1.0), (2.0, 1.0, 1.0), (1.5, 0.8, 1.2)]:
        shape = tuple(round(60 / s) + 1 for s in spacing)
        mask, truth = synth.cylinder(shape, 3.0, spacing, start=start, end=end)
        volumes.append(np.count_nonzero(mask) * np.prod(spacing))
        assert np.allclose(truth.positions[[0, -1]], [start, end])
        assert mask[node_voxels(truth)].all()
    assert max(volumes) / min(volumes) < 1.04


def test_torus_has_one_loop_and_true_centreline():
    mask, truth = synth.torus((56, 56, 56), 18.0, 3.0)
    assert n_components(mask) == 1
    assert loops(mask) == 1
    assert truth.n_edges == truth.n_nodes
    assert np.all(truth.degrees() == 2)
    centre = (np.asarray(mask.shape) - 1) / 2
    d = truth.positions - centre
    assert np.allclose(d[:, 0], 0.0)
    assert np.allclose(np.hypot(d[:, 1], d[:, 2]), 18.0)
    # A ring tube of radius 3 about a circle of radius 18: 2 pi^2 R r^2 (the ring lies
    # between two voxel planes, so its cross-section is quantised along axis 0).
    assert abs(np.count_nonzero(mask) / (2 * math.pi**2 * 18 * 9) - 1) < 0.05


def test_helix_centreline_and_volume():
    mask, truth = synth.helix((64, 48, 48), radius=2.0, helix_radius=10.0, pitch=20.0)
    centre = (np.asarray(mask.shape) - 1) / 2
    d = truth.positions - centre
    assert np.allclose(np.hypot(d[:, 1], d[:, 2]), 10.0)
    assert mask[node_voxels(truth)].all()
    assert n_components(mask) == 1
    assert loops(mask) == 0
    arc = np.sum(np.linalg.norm(np.diff(truth.positions, axis=0), axis=1))
    expected = math.pi * 4 * arc + 4 / 3 * math.pi * 8
    assert abs(np.count_nonzero(mask) / expected - 1) < 0.05


def test_y_bifurcation_obeys_murray_and_is_a_tree():
    mask, truth = synth.y_bifurcation((64, 64, 48), radius=4.0, angle=70.0)
    deg = truth.degrees()
    assert deg[0] == 3
    assert np.count_nonzero(deg == 1) == 3
    assert np.count_nonzero(deg == 3) == 1
    child = truth.info["child_radius"]
    assert math.isclose(4.0**3, 2 * child**3)
    assert sorted(np.unique(truth.radii).round(9)) == sorted({round(child, 9), 4.0})
    assert n_components(mask) == 1
    assert loops(mask) == 0
    assert mask[node_voxels(truth)].all()


def test_betti_numbers_agree_with_scikit_image():
    measure = pytest.importorskip("skimage.measure")
    rng = np.random.default_rng(5)
    for density in (0.2, 0.4, 0.6):
        mask = rng.random((12, 13, 11)) < density
        b0, b1, b2 = _common._betti_numbers(mask)
        assert b0 == n_components(mask)
        assert b0 - b1 + b2 == measure.euler_number(mask, connectivity=3)
    shell = np.zeros((7, 7, 7), dtype=bool)
    shell[1:-1, 1:-1, 1:-1] = True
    shell[2:-2, 2:-2, 2:-2] = False
    assert _common._betti_numbers(shell) == (1, 0, 1)


# --------------------------------------------------------------------------- vascular tree


@pytest.fixture(scope="module")
def tree32() -> tuple[np.ndarray, VesselGraph]:
    return synth.vascular_tree((96, 96, 96), 32, seed=3)


def test_tree_truth_is_a_binary_tree_with_the_terminals(tree32):
    _mask, truth = tree32
    assert truth.n_nodes == truth.n_edges + 1
    graph = truth.to_networkx()
    assert nx.is_tree(graph)
    deg = truth.degrees()
    leaves = set(np.flatnonzero(deg == 1).tolist())
    assert leaves == {truth.info["root"], *truth.info["terminals"]}
    assert len(truth.info["terminals"]) == 32
    assert np.count_nonzero(deg == 3) == 31
    assert deg.max() == 3
    assert sorted(np.flatnonzero(deg == 3).tolist()) == truth.info["bifurcations"]
    # Samples along segments: no edge longer than a voxel.
    lengths = np.linalg.norm(np.diff(truth.positions[truth.edges], axis=1)[:, 0], axis=1)
    assert lengths.max() <= 1.0 + 1e-9


def test_tree_terminals_stick_out_of_other_vessels(tree32):
    _, truth = tree32
    graph = truth.to_networkx()
    bifurcations = set(truth.info["bifurcations"])
    for t in truth.info["terminals"]:
        branch, prev = [t], None
        while branch[-1] not in bifurcations:
            step = next(n for n in graph.neighbors(branch[-1]) if n != prev)
            prev = branch[-1]
            branch.append(step)
        others = np.setdiff1d(np.arange(truth.n_nodes), branch[:-1])
        gap = np.linalg.norm(truth.positions[others] - truth.positions[t], axis=1)
        # The terminal's cap (radius r_t) lies wholly outside every other vessel.
        assert np.min(gap - truth.radii[others]) > truth.radii[t]


def test_tree_radii_follow_murray_at_every_bifurcation(tree32):
    _, truth = tree32
    graph = truth.to_networkx()
    for b in truth.info["bifurcations"]:
        r = np.sort([truth.radii[n] for n in graph.neighbors(b)])
        assert math.isclose(r[2] ** 3, r[0] ** 3 + r[1] ** 3, rel_tol=1e-9)
    # Equal flows: terminal radius r_t, root radius r_t * 32**(1/3).
    r_t = truth.info["terminal_radius"]
    assert np.allclose(truth.radii[truth.info["terminals"]], r_t)
    assert math.isclose(truth.radii[truth.info["root"]], r_t * 32 ** (1 / 3))
    assert math.isclose(r_t, 1.5)


def test_tree_mask_is_one_loop_free_component_holding_the_truth(tree32):
    mask, truth = tree32
    assert mask.dtype == np.bool_
    assert mask.flags.c_contiguous
    assert n_components(mask) == 1
    assert loops(mask) == 0
    assert mask[node_voxels(truth)].all()
    # Nothing touches the border.
    for axis in range(3):
        assert not np.take(mask, [0, -1], axis=axis).any()
    # The radii are the mask's: distance to the background at samples of thick vessels.
    edt = ndimage.distance_transform_edt(mask)
    thick = truth.radii >= 2.5
    depth = edt[node_voxels(truth)][thick]
    assert np.median(np.abs(depth - truth.radii[thick])) < 0.75


def test_tree_is_shorter_than_a_star(tree32):
    _, truth = tree32
    tree_length = np.sum(np.linalg.norm(np.diff(truth.positions[truth.edges], axis=1), axis=2))
    root = truth.positions[truth.info["root"]]
    star = np.sum(np.linalg.norm(truth.positions[truth.info["terminals"]] - root, axis=1))
    assert tree_length < 0.7 * star


def test_tree_is_deterministic_and_seeded(tree32):
    again = synth.vascular_tree((96, 96, 96), 32, seed=3)
    assert same(tree32, again)
    other = synth.vascular_tree((96, 96, 96), 32, seed=4)
    assert not np.array_equal(tree32[0], other[0])


def test_tree_with_64_terminals_has_root_of_six_voxels():
    mask, truth = synth.vascular_tree((128, 128, 128), 64, seed=0)
    assert len(truth.info["terminals"]) == 64
    assert math.isclose(truth.info["root_radius"], 6.0)
    assert n_components(mask) == 1
    root = truth.positions[truth.info["root"]]
    assert root[0] == pytest.approx(7.0)  # inlet on the axis-0 face, radius + 1 voxel in


def test_tree_has_same_physical_geometry_at_anisotropic_spacing():
    # The same 64^3 physical box at two anisotropic spacings (same finest voxel and voxel
    # diagonal, hence same defaults): the same tree, and masks of the same physical volume.
    a = synth.vascular_tree((33, 65, 65), 16, seed=2, spacing=(2.0, 1.0, 1.0))
    b = synth.vascular_tree((65, 33, 65), 16, seed=2, spacing=(1.0, 2.0, 1.0))
    assert np.allclose(a[1].positions, b[1].positions)
    assert np.array_equal(a[1].edges, b[1].edges)
    assert np.allclose(a[1].radii, b[1].radii)
    for mask, truth in (a, b):
        assert mask[node_voxels(truth)].all()
        assert n_components(mask) == 1
    v_a, v_b = np.count_nonzero(a[0]), np.count_nonzero(b[0])
    assert abs(v_a / v_b - 1) < 0.05
    # And about the isotropic volume of the same tree's vessels: sum of pi r^2 L.
    seg = np.linalg.norm(np.diff(a[1].positions[a[1].edges], axis=1)[:, 0], axis=1)
    r = a[1].radii[a[1].edges].min(axis=1)
    assert 2 * v_a == pytest.approx(np.sum(math.pi * r**2 * seg), rel=0.15)


def test_tree_root_radius_sets_the_terminal_radius():
    _, truth = synth.vascular_tree((80, 80, 80), 8, seed=1, root_radius=4.0)
    assert math.isclose(truth.info["terminal_radius"], 2.0)
    assert math.isclose(truth.radii[truth.info["root"]], 4.0)


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"n_terminals": 0}, ValueError, "n_terminals"),
        ({"n_terminals": 2.5}, TypeError, "n_terminals"),
        ({"spacing": (1.0, -1.0, 1.0)}, ValueError, "spacing"),
        ({"shape": (64, 64)}, ValueError, "shape"),
        ({"shape": (12, 12, 12)}, ValueError, "too small"),
        ({"root_radius": 2.0, "min_radius": 1.5}, ValueError, "root_radius"),
        ({"supersample": 0}, ValueError, "supersample"),
        ({"min_radius": -1.0}, ValueError, "min_radius"),
    ],
)
def test_tree_rejects_bad_input(kwargs, error, match):
    args = {"shape": (64, 64, 64), "n_terminals": 8, **kwargs}
    with pytest.raises(error, match=match):
        synth.vascular_tree(**args)


# --------------------------------------------------------------------------- bubble noise


@pytest.fixture(scope="module")
def small_tree() -> np.ndarray:
    return synth.vascular_tree((64, 64, 64), 16, seed=1)[0]


@pytest.mark.parametrize("dilate", [False, True])
def test_bubble_noise_levels_nest_and_contain_the_base_mask(small_tree, dilate):
    # The base is the mask itself (the paper's text) or, with dilate=True, the mask
    # dilated once (the paper authors' code).
    base = ndimage.binary_dilation(small_tree, structure=SIX) if dilate else small_tree
    noisy = [
        synth.add_bubble_noise(small_tree, level, seed=7, dilate=dilate)
        for level in ("D0", "D1", "D2")
    ]
    added = [np.count_nonzero(n & ~base) for n in noisy]
    assert 0 < added[0] < added[1] < added[2]
    for n in noisy:
        assert np.all(n >= base)
    assert np.all(noisy[0] <= noisy[1])
    assert np.all(noisy[1] <= noisy[2])
    # Bubbles are radius-2 balls on the boundary: every added voxel is within 2 voxels of
    # the base mask.
    dist = ndimage.distance_transform_edt(~base)
    assert dist[noisy[2] & ~base].max() <= 2.0 + 1e-9


def test_bubble_noise_is_deterministic_and_levels_are_fractions(small_tree):
    a = synth.add_bubble_noise(small_tree, "D1", seed=3)
    assert np.array_equal(a, synth.add_bubble_noise(small_tree, "D1", seed=3))
    assert np.array_equal(a, synth.add_bubble_noise(small_tree, 0.025, seed=3))
    assert not np.array_equal(a, synth.add_bubble_noise(small_tree, "D1", seed=4))
    # Level 0 leaves the mask as it is, or only dilates it with dilate=True.
    assert np.array_equal(synth.add_bubble_noise(small_tree, 0.0, seed=3), small_tree)
    plain = synth.add_bubble_noise(small_tree, 0.0, seed=3, dilate=True)
    assert np.array_equal(plain, ndimage.binary_dilation(small_tree, structure=SIX))


def test_bubble_noise_fills_holes_under_125_voxels():
    mask = np.zeros((40, 20, 20), dtype=bool)
    # Two closed boxes: interiors 6^3 and 7^3, which the dilation shrinks to 4^3 and 5^3.
    mask[2:10, 2:10, 2:10] = True
    mask[3:9, 3:9, 3:9] = False
    mask[20:29, 2:11, 2:11] = True
    mask[21:28, 3:10, 3:10] = False
    noisy = synth.add_bubble_noise(mask, 0.0, dilate=True)
    assert noisy[5, 5, 5]  # 64-voxel hole filled
    assert not noisy[24, 6, 6]  # 125-voxel hole kept
    assert np.count_nonzero(~noisy[21:28, 3:10, 3:10]) == 125


@pytest.mark.parametrize(
    ("mask", "level", "error"),
    [
        (np.zeros((8, 8, 8), bool), "D3", ValueError),
        (np.zeros((8, 8, 8), bool), 1.5, ValueError),
        (np.zeros((8, 8, 8), bool), None, TypeError),
        (np.zeros((8, 8, 8), np.uint8), "D0", TypeError),
        (np.zeros((8, 8), bool), "D0", ValueError),
    ],
)
def test_bubble_noise_rejects_bad_input(mask, level, error):
    with pytest.raises(error):
        synth.add_bubble_noise(mask, level)


# --------------------------------------------------------------------------- capillaries


@pytest.fixture(scope="module")
def capillaries() -> tuple[np.ndarray, VesselGraph]:
    return synth.capillary_network((72, 72, 72), seed=0)


def test_capillary_mask_realises_the_truth_cycle_rank(capillaries):
    mask, truth = capillaries
    graph = truth.to_networkx()
    assert nx.is_connected(graph)
    rank = truth.n_edges - truth.n_nodes + 1
    assert truth.info["cycle_rank"] == rank > 20
    assert n_components(mask) == 1
    assert loops(mask) == rank


def test_capillary_truth_lies_in_mask_with_its_radii(capillaries):
    mask, truth = capillaries
    assert mask[node_voxels(truth)].all()
    assert truth.radii.min() >= 1.0
    assert truth.radii.max() <= 2.0
    lengths = np.linalg.norm(np.diff(truth.positions[truth.edges], axis=1)[:, 0], axis=1)
    assert lengths.max() <= 1.0 + 1e-9
    lattice = truth.info["lattice_nodes"]
    assert truth.degrees()[:lattice].min() >= 1
    assert np.all(truth.degrees()[lattice:] == 2)


def test_capillaries_are_deterministic_and_seeded(capillaries):
    assert same(capillaries, synth.capillary_network((72, 72, 72), seed=0))
    assert not np.array_equal(capillaries[0], synth.capillary_network((72, 72, 72), seed=1)[0])


def test_capillaries_at_anisotropic_spacing_keep_their_topology():
    mask, truth = synth.capillary_network((36, 64, 64), seed=2, spacing=(2.0, 1.0, 1.0))
    assert loops(mask) == truth.info["cycle_rank"] > 5
    assert n_components(mask) == 1
    assert mask[node_voxels(truth)].all()


@pytest.mark.parametrize(
    ("kwargs", "error"),
    [
        ({"radius": (2.0, 1.0)}, ValueError),
        ({"radius": 1.0}, TypeError),
        ({"node_spacing": 5.0}, ValueError),
        ({"shape": (20, 20, 20)}, ValueError),
        ({"extra_edges": 1.5}, ValueError),
    ],
)
def test_capillaries_reject_bad_input(kwargs, error):
    with pytest.raises(error):
        synth.capillary_network(**kwargs)


def test_analytic_shapes_reject_bad_input():
    with pytest.raises(ValueError, match="radius"):
        synth.cylinder(radius=0.0)
    with pytest.raises(ValueError, match="minor_radius"):
        synth.torus(major_radius=3.0, minor_radius=4.0)
    with pytest.raises(ValueError, match="angle"):
        synth.y_bifurcation(angle=200.0)
    with pytest.raises(ValueError, match="too small"):
        synth.helix((64, 20, 20))
    with pytest.raises(TypeError, match="supersample"):
        synth.cylinder(supersample=2.0)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- vascular bed


def test_vascular_bed_is_one_component_near_its_fraction():
    mask = synth.vascular_bed(48, seed=2, fraction=0.05)
    assert mask.shape == (48, 48, 48)
    assert mask.dtype == np.bool_
    assert 0.05 <= np.count_nonzero(mask) / mask.size < 0.1
    assert n_components(mask) == 1
    assert np.array_equal(mask, synth.vascular_bed(48, seed=2, fraction=0.05))
    assert not np.array_equal(mask, synth.vascular_bed(48, seed=3, fraction=0.05))
    with pytest.raises(ValueError, match="size"):
        synth.vascular_bed(8)
    with pytest.raises(ValueError, match="fraction"):
        synth.vascular_bed(32, fraction=0.7)


# --------------------------------------------------------------------------- forest


@pytest.fixture(scope="module")
def forest() -> tuple[np.ndarray, VesselGraph]:
    return synth.vascular_forest((96, 96, 96), seed=3, attractors=300)


@pytest.fixture(scope="module")
def smooth_forest() -> tuple[np.ndarray, VesselGraph]:
    """Without ripple: radii constant between junctions, for the exact EDT bounds."""
    return synth.vascular_forest((96, 96, 96), seed=3, attractors=300, ripple=0.0)


def isolated_nodes(truth: VesselGraph, shape: tuple[int, ...], margin: float = 6.0) -> np.ndarray:
    """Every other degree-2 node with no junction, leaf or other vessel within ``2 r + margin`` (by
    path length along the truth, nodes closer than that in space but farther than twice
    that along the graph belong to another vessel), away from the box faces."""
    graph = truth.to_networkx()
    for u, v in graph.edges:
        graph[u][v]["w"] = float(np.linalg.norm(truth.positions[u] - truth.positions[v]))
    degree = truth.degrees()
    tree = cKDTree(truth.positions)
    out = []
    for node in np.flatnonzero(degree == 2)[::2]:
        reach = 2.0 * truth.radii[node] + margin
        p = truth.positions[node]
        if np.any(p < reach) or np.any(p > np.asarray(shape) - 1 - reach):
            continue
        along = nx.single_source_dijkstra_path_length(graph, int(node), 2 * reach, weight="w")
        near = tree.query_ball_point(p, reach)
        if all(j in along for j in near) and all(
            degree[j] == 2 for j in along if along[j] <= reach
        ):
            out.append(node)
    return np.asarray(out, dtype=np.int64)


def test_forest_truth_lies_on_the_medial_axis(forest):
    """In the cross-section through each isolated truth node, the top of the distance
    transform (the centre of the voxels within half a voxel of its maximum) lies within a
    fraction of a voxel of the node: the truth is the mask's medial axis."""
    mask, truth = forest
    edt = ndimage.distance_transform_edt(mask)
    nodes = isolated_nodes(truth, mask.shape)
    assert len(nodes) > 50
    off = []
    for node in nodes:
        p, r = truth.positions[node], truth.radii[node]
        a, b = (truth.positions[j] for j in truth.to_networkx().neighbors(int(node)))
        tangent = (b - a) / np.linalg.norm(b - a)
        lo = np.floor(p - r - 1).astype(int)
        idx = np.stack(
            np.meshgrid(
                *(np.arange(lo[k], lo[k] + int(2 * r + 4)) for k in range(3)), indexing="ij"
            ),
            -1,
        ).reshape(-1, 3)
        v = idx - p
        axial = v @ tangent
        radial = np.linalg.norm(v - axial[:, None] * tangent, axis=1)
        section = idx[(np.abs(axial) <= 0.5) & (radial <= r)]
        value = edt[tuple(section.T)]
        # The ridge of a thick tube is a plateau of near-equal values: take its centre.
        top = section[value >= value.max() - 0.5].mean(axis=0)
        d = top - p
        off.append(np.linalg.norm(d - (d @ tangent) * tangent))
    off = np.asarray(off)
    # A truth moved by one voxel gives a median of about 0.6 and a maximum of 1.2.
    assert off.max() <= 1.0
    assert np.quantile(off, 0.95) <= 0.6
    assert np.median(off) <= 0.3


def test_forest_radii_bound_the_distance_transform_on_straight_segments(smooth_forest):
    """The voxel-centre convention: at a voxel centre ``delta`` from the axis, the EDT
    (distance to the nearest background voxel centre) lies in (r - delta, r + delta +
    sqrt(3)/2]; a partial-volume or off-by-half-a-voxel mask breaks one of the bounds."""
    mask, truth = smooth_forest
    edt = ndimage.distance_transform_edt(mask)
    nodes = isolated_nodes(truth, mask.shape)
    assert len(nodes) > 50
    p = truth.positions[nodes]
    r = truth.radii[nodes]
    vox = np.rint(p).astype(int)
    delta = np.linalg.norm(vox - p, axis=1)
    value = edt[tuple(vox.T)]
    slack = 0.02 * r  # the axis bends a little between samples
    assert np.all(value > r - delta - slack)
    assert np.all(value <= r + delta + math.sqrt(3) / 2 + slack)
    # On average the EDT at the nearest voxel is close to r (within a quarter voxel).
    assert abs(np.mean(value - r)) < 0.25


def test_forest_has_what_the_benchmark_needs(forest):
    mask, truth = forest
    info = truth.info
    assert info["generator"] == "vascular_forest"
    assert info["convention"] == "voxel-centre"
    # Anastomoses: loops in the truth and tunnels in the mask.
    # Each anastomosis adds one edge more than nodes (a loop, or a bridge between trees).
    assert info["anastomoses"] > 5
    assert truth.n_edges - truth.n_nodes + info["n_trees"] == info["anastomoses"]
    assert loops(mask) >= 1
    # Thick vessels with thin side branches: radii in every band 1-2 ... 5-10 voxels.
    r = truth.radii
    assert r.min() >= 1.5 * 0.94 - 1e-9
    assert r.max() <= 6.5 * 1.06 + 1e-9
    for lo, hi in ((1, 2), (2, 3), (3, 5), (5, 10)):
        assert np.any((r >= lo) & (r < hi)), (lo, hi)
    # Vessels that touch or cross: nodes far apart along the graph whose tubes overlap.
    tree = cKDTree(truth.positions)
    graph = truth.to_networkx()
    pairs = tree.query_pairs(2 * r.max(), output_type="ndarray")
    gap = np.linalg.norm(truth.positions[pairs[:, 0]] - truth.positions[pairs[:, 1]], axis=1)
    overlapping = pairs[gap < r[pairs[:, 0]] + r[pairs[:, 1]]]
    assert any(
        not nx.has_path(graph, i, j) or nx.shortest_path_length(graph, i, j) > 2 * (r[i] + r[j])
        for i, j in overlapping.tolist()
    )
    # The ripple is part of the truth radius: radii vary along unbranched vessels.
    plain = synth.vascular_forest((96, 96, 96), seed=3, attractors=300, ripple=0.0)[1]
    # Same trees (nodes first); the anastomoses may differ, as they depend on the radii.
    m = min(plain.n_nodes, truth.n_nodes)
    same_rows = np.all(plain.positions[:m] == truth.positions[:m], axis=1)
    m = int(np.argmin(same_rows)) if not same_rows.all() else m
    assert m > 500
    ratio = truth.radii[:m] / plain.radii[:m]
    assert 0.94 - 1e-9 <= ratio.min() < 0.96
    assert 1.04 < ratio.max() <= 1.06 + 1e-9
    # Every truth node is in the mask.
    assert mask[node_voxels(truth)].all()


def test_forest_is_deterministic_and_seeded(forest):
    assert same(forest, synth.vascular_forest((96, 96, 96), seed=3, attractors=300))
    other = synth.vascular_forest((96, 96, 96), seed=4, attractors=300)
    assert not np.array_equal(forest[0], other[0])


@pytest.mark.parametrize(
    ("kwargs", "error"),
    [
        ({"shape": (8, 64, 64)}, ValueError),
        ({"shape": (20, 20, 20), "root_radius": 6.5}, ValueError),
        ({"ripple": 0.5}, ValueError),
        ({"anastomoses": 1.5}, ValueError),
        ({"n_trees": 7}, ValueError),
        ({"attractors": 0}, ValueError),
        ({"attractors": 2.5}, TypeError),
        ({"min_radius": 7.0}, ValueError),
        ({"spacing": (1.0, -1.0, 1.0)}, ValueError),
    ],
)
def test_forest_rejects_bad_input(kwargs, error):
    with pytest.raises(error):
        synth.vascular_forest(**{"shape": (64, 64, 64), **kwargs})


def test_voxel_centre_lattice_has_its_designed_loops():
    """The benchmark's lattice (voxel-centre rasterisation, jitter and bend 0.2): as many
    mask loops (scikit-image's Euler number, independent of the generator's own check) as
    the truth's cycle rank."""
    mask, truth = synth.capillary_network(
        (72, 72, 72), seed=1, radius=(1.4, 2.4), jitter=0.2, bend=0.2, supersample=1
    )
    assert loops(mask) == truth.info["cycle_rank"] > 20
    assert n_components(mask) == 1
    assert mask[node_voxels(truth)].all()
