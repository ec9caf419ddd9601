"""The Skeletonizer's parameters: signature, defaults, repr, validation."""

from __future__ import annotations

import inspect
import pydoc
import re

import numpy as np
import pytest

import vesselflow
from vesselflow import _core, metrics, synth

DEFAULTS = dict(_core.param_defaults())


def test_core_lists_every_method_parameter_with_its_default():
    assert DEFAULTS == {
        "connectivity": 6,
        "reconnect_thin": True,
        "radius_correction": 0.0,
        "coarse_cell": 0.67,
        "medial_weight": "radius",
        "skeletal_angle": 10.0,
        "anchor_ends": True,
        "sprouts": True,
        "medial": True,
        "prune_spurs": 1.0,
        "merge_junctions": 0.5,
        "radius_smoothing": 4.0,
        "eps_gamma": 10.0,
        "alpha": 0.25,
        "beta": 0.5,
        "gamma": 0.05,
        "cg_tol": 1e-4,
        "cg_max_iterations": 2000,
        "max_cycle_nodes": 10,
        "stop_ratio": 1e-3,
        "stall_ratio": 0.01,
        "area_reference": "volume",
        "max_iterations": 100,
        "refine_area": 50.0,
        "max_refine_iterations": 100,
        "threads": 0,
        "max_memory": "auto",
    }


def test_python_signature_matches_core_defaults_in_order():
    sig = inspect.signature(vesselflow.Skeletonizer)
    assert all(p.kind is inspect.Parameter.KEYWORD_ONLY for p in sig.parameters.values())
    assert [(p.name, p.default) for p in sig.parameters.values()] == list(DEFAULTS.items())
    # Types too: an int default where the core has a float would change the repr.
    for p in sig.parameters.values():
        assert type(p.default) is type(DEFAULTS[p.name]), p.name


def test_help_shows_every_parameter_and_default():
    text = pydoc.render_doc(vesselflow.Skeletonizer, renderer=pydoc.plaintext)
    for name, default in DEFAULTS.items():
        assert re.search(rf"\b{name}: .*? = {re.escape(repr(default))}[,)]", text), name
        assert re.search(rf"\b{name}\b[^\n]* :", text), f"{name} undocumented"


def test_repr_lists_every_parameter_with_its_value():
    text = repr(vesselflow.Skeletonizer(gamma=0.1, medial_weight="difference"))
    expected = {**DEFAULTS, "gamma": 0.1, "medial_weight": "difference"}
    assert text == "Skeletonizer(" + ", ".join(f"{k}={v!r}" for k, v in expected.items()) + ")"


def test_params_dict_and_equality():
    a = vesselflow.Skeletonizer(connectivity=26, threads=1)
    assert a.params == {**DEFAULTS, "connectivity": 26, "threads": 1}
    assert a == vesselflow.Skeletonizer(threads=1, connectivity=26)
    assert a != vesselflow.Skeletonizer()
    assert a != "Skeletonizer"


def test_int_accepted_for_float_parameters_and_numpy_scalars():
    s = vesselflow.Skeletonizer(
        gamma=1,
        refine_area=np.float32(20.0),
        connectivity=np.int64(18),
        reconnect_thin=np.False_,
    )
    assert s.params["reconnect_thin"] is False
    assert s.params["gamma"] == 1.0
    assert isinstance(s.params["gamma"], float)
    assert s.params["refine_area"] == 20.0
    assert s.params["connectivity"] == 18


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("connectivity", 7),
        ("connectivity", 6.0),
        ("reconnect_thin", 1),
        ("radius_correction", 1.5),
        ("radius_correction", -0.1),
        ("coarse_cell", -0.1),
        ("coarse_cell", 4.5),
        ("medial_weight", "median"),
        ("medial_weight", 1),
        ("skeletal_angle", 91.0),
        ("anchor_ends", 1),
        ("sprouts", 1),
        ("medial", 1),
        ("merge_junctions", -0.5),
        ("merge_junctions", 11.0),
        ("eps_gamma", 0.5),
        ("alpha", -1.0),
        ("beta", float("inf")),
        ("gamma", 0.0),
        ("gamma", float("nan")),
        ("gamma", "fast"),
        ("cg_tol", 0.0),
        ("cg_max_iterations", 0),
        ("cg_max_iterations", -5),
        ("max_cycle_nodes", 3),
        ("stop_ratio", 2.0),
        ("stall_ratio", -0.1),
        ("stall_ratio", 0.75),
        ("area_reference", "initial"),
        ("max_iterations", -1),
        ("max_iterations", 2**70),
        ("refine_area", -1.0),
        ("max_refine_iterations", 1.5),
        ("threads", -1),
        ("threads", 100_000),
    ],
)
def test_invalid_value_is_a_value_error_naming_the_parameter(name, value):
    with pytest.raises(ValueError, match=f"`{name}`"):
        vesselflow.Skeletonizer(**{name: value})
    with pytest.raises(ValueError, match=f"`{name}`"):
        _core.Skeletonizer(**{name: value})


def test_alpha_and_beta_cannot_both_be_zero():
    vesselflow.Skeletonizer(alpha=0.0)
    with pytest.raises(ValueError, match="alpha and beta"):
        vesselflow.Skeletonizer(alpha=0.0, beta=0.0)


@pytest.mark.parametrize("value", [None, [1], {"a": 1}, 1j])
def test_value_of_unsupported_type_is_a_type_error_naming_the_parameter(value):
    with pytest.raises(TypeError, match="`gamma`"):
        _core.Skeletonizer(gamma=value)


def test_unknown_keyword_is_a_type_error():
    with pytest.raises(TypeError, match="unexpected keyword argument 'gama'"):
        vesselflow.Skeletonizer(gama=0.1)
    with pytest.raises(TypeError, match="unexpected keyword argument 'gama'"):
        _core.Skeletonizer(gama=0.1)
    with pytest.raises(TypeError, match="unexpected keyword argument 'gama'"):
        vesselflow.skeletonize(np.zeros((2, 2, 2), bool), gama=0.1)


def test_positional_parameters_are_refused():
    with pytest.raises(TypeError):
        vesselflow.Skeletonizer(6)  # type: ignore[misc]


def test_skeletonize_passes_parameters(tube):
    fast = vesselflow.skeletonize(tube, max_iterations=1)
    assert fast.info["iterations"] == 1
    assert fast.params["max_iterations"] == 1
    full = vesselflow.skeletonize(tube)
    assert full.info["iterations"] > 1
    assert full.params == DEFAULTS


def test_merge_junctions_joins_split_crossings_and_keeps_the_loops():
    # A jittered, bent capillary lattice: the contraction splits most of its crossings
    # into junctions of degree 3 a fraction of a radius apart.
    mask, _ = synth.capillary_network(
        (56, 56, 56), seed=3, radius=(1.4, 2.4), jitter=0.2, bend=0.2, supersample=1
    )
    joined = vesselflow.skeletonize(mask)
    split = vesselflow.skeletonize(mask, merge_junctions=0)
    assert split.params["merge_junctions"] == 0
    degree = {g: np.bincount(g.edges.ravel(), minlength=g.n_nodes) for g in (joined, split)}
    assert (degree[joined] >= 3).sum() < (degree[split] >= 3).sum()
    assert (degree[joined] >= 4).sum() > (degree[split] >= 4).sum()
    one, other = (metrics.topology(mask, g) for g in (joined, split))
    assert one["graph_cycles"] == other["graph_cycles"] > 0
    assert one["graph_components"] == other["graph_components"] == one["mask_components"]


def test_a_run_over_max_memory_is_a_memory_error_naming_both_numbers(tube):
    with pytest.raises(MemoryError, match=r"needs about .* but max_memory allows 1000 B") as err:
        vesselflow.skeletonize(tube, max_memory="1KB")
    assert "crop the volume" in str(err.value)
    assert vesselflow.Skeletonizer(max_memory="512MiB").params["max_memory"] == 512 * 2**20
    with pytest.raises(ValueError, match="max_memory"):
        vesselflow.Skeletonizer(max_memory="lots")


def test_a_generous_max_memory_gives_the_same_graph(tube):
    free = vesselflow.skeletonize(tube, max_memory=None)
    assert free.params["max_memory"] == 0
    for limit in ("64GiB", "auto", 2**40):
        graph = vesselflow.skeletonize(tube, max_memory=limit)
        np.testing.assert_array_equal(graph.positions, free.positions)
        np.testing.assert_array_equal(graph.radii, free.radii)
        np.testing.assert_array_equal(graph.edges, free.edges)
