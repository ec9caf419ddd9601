"""progress=True (a tqdm bar on stderr) and messages on the ``vesselflow`` logger."""

from __future__ import annotations

import logging

import vesselflow
from conftest import make_tube
from vesselflow import synth


def test_progress_true_shows_a_bar_on_stderr(capsys):
    graph = vesselflow.skeletonize(make_tube(), progress=True)
    captured = capsys.readouterr()
    assert captured.out == ""
    bar = captured.err.replace("\r", "\n").splitlines()
    iterations = graph.info["iterations"]
    # The last refresh shows every contraction iteration done and the final stage.
    final = [line for line in bar if "stage=output" in line][-1]
    assert f"{iterations}/{iterations}" in final
    assert f"nodes={graph.n_nodes}" in final
    assert any("stage=contract" in line for line in bar)


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
    assert any(f"{graph.n_nodes} nodes" in r.getMessage() for r in caplog.records)


def test_converged_run_logs_no_warning(caplog):
    with caplog.at_level(logging.WARNING, logger="vesselflow"):
        graph = vesselflow.skeletonize(make_tube())
    assert graph.info["converged"] is True
    assert caplog.records == []


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
