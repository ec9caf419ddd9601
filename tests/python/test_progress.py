"""progress=True (a tqdm bar on stderr) and messages on the ``vesselflow`` logger."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

import vesselflow
from conftest import make_tube
from vesselflow import synth
from vesselflow.skeletonizer import _progress_callback


def bar_lines(err: str) -> list[str]:
    return [line for line in err.replace("\r", "\n").splitlines() if line.strip()]


def test_progress_true_shows_a_bar_on_stderr(capsys):
    graph = vesselflow.skeletonize(make_tube(), progress=True)
    captured = capsys.readouterr()
    assert captured.out == ""
    bar = bar_lines(captured.err)
    # The last refresh shows the bar complete, the final stage and the nodes left.
    final = [line for line in bar if line.startswith("vesselflow output")][-1]
    assert "100%" in final
    assert f"nodes={graph.n_nodes}" in final
    assert any(line.startswith("vesselflow contract") and "measure=" in line for line in bar)


def test_the_bar_counts_nodes_merged_out_of_the_grid_graph(capsys):
    # Not iterations out of max_iterations: most runs stop far before the cap, so that
    # bar's remaining time was many times too long. Merged nodes accrue steadily.
    nan = math.nan
    with _progress_callback(True) as update:
        assert update is not None
        reports = [
            ("edt", 0, 0, nan, "0%"),
            ("grid", 0, 1000, nan, "0%"),
            ("contract", 1, 600, 5.0, "40%"),
            ("contract", 2, 250, 0.5, "75%"),
            ("refine", 1, 200, nan, "80%"),
            ("output", 0, 200, nan, "100%"),
        ]
        for stage, iteration, nodes, measure, percent in reports:
            update(stage, iteration, nodes, measure)
            last = bar_lines(capsys.readouterr().err)[-1]
            assert last.startswith(f"vesselflow {stage}: {percent:>4}|"), last
            assert f"nodes={nodes}" in last
            assert ("measure=" in last) == (stage == "contract"), last
    assert "measure=0.5" not in last


def test_the_measure_is_the_convergence_measure_and_nan_outside_the_contraction(branching):
    calls = []
    graph = vesselflow.skeletonize(branching, progress=lambda *a: calls.append(a))
    info = graph.info
    contract = [measure for stage, _, _, measure in calls if stage == "contract"]
    expected = [a / info["area_reference"] for a in info["area_per_iteration"][1:]]
    assert len(contract) == info["iterations"] > 0
    assert contract == pytest.approx(expected, rel=1e-12)
    assert contract[-1] <= 1.0 or info["stalled"]
    others = [(stage, measure) for stage, _, _, measure in calls if stage != "contract"]
    assert {stage for stage, _ in others} >= {"edt", "grid", "refine", "output"}
    assert all(math.isnan(measure) for _, measure in others), others


def test_progress_bar_gives_the_same_graph_as_no_progress(branching):
    quiet = vesselflow.skeletonize(branching)
    shown = vesselflow.Skeletonizer().run(branching, progress=True)
    assert (shown.positions == quiet.positions).all()
    assert shown.info["converged"] == quiet.info["converged"]


def test_progress_false_is_silent(capsys):
    vesselflow.skeletonize(make_tube(), progress=False)
    assert capsys.readouterr().err == ""


def test_early_stop_logs_a_warning(caplog):
    with caplog.at_level(logging.INFO, logger="vesselflow"):
        graph = vesselflow.skeletonize(make_tube((60, 15, 15)), max_iterations=1)
    assert graph.info["converged"] is False
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert warnings[0].name.startswith("vesselflow")
    assert "max_iterations=1" in warnings[0].getMessage()
    summary = [r.getMessage() for r in caplog.records if f"{graph.n_nodes} nodes" in r.getMessage()]
    assert len(summary) == 1
    assert summary[0].endswith("in 1 iterations (stopped at max_iterations)")


def test_converged_run_logs_no_warning(caplog):
    with caplog.at_level(logging.INFO, logger="vesselflow"):
        graph = vesselflow.skeletonize(make_tube())
    assert graph.info["converged"] is True
    assert [r.levelno for r in caplog.records] == [logging.INFO]
    assert caplog.records[0].getMessage().endswith("(converged)")


def test_stalled_run_logs_no_warning(caplog):
    # Thin vessels (radius 0.5 to 2 voxels): the graph stops simplifying after a few
    # iterations, well before the cycle-area level; that is a normal end, not a cap.
    mask, _ = synth.vascular_tree(
        (64, 64, 64), n_terminals=32, seed=0, min_radius=0.5, root_radius=2.0
    )
    with caplog.at_level(logging.WARNING, logger="vesselflow"):
        graph = vesselflow.skeletonize(mask)
    assert graph.info["stalled"] is True
    assert graph.info["converged"] is False
    assert graph.info["iterations"] < graph.params["max_iterations"]
    assert not [r for r in caplog.records if r.levelno == logging.WARNING]


def test_an_empty_mask_warns_and_says_so_in_the_log(caplog):
    with (
        caplog.at_level(logging.INFO, logger="vesselflow"),
        pytest.warns(UserWarning, match="the mask is empty"),
    ):
        graph = vesselflow.skeletonize(np.zeros((6, 7, 8), bool))
    assert graph.n_nodes == 0
    assert [r.getMessage()[-12:] for r in caplog.records] == ["(empty mask)"]
