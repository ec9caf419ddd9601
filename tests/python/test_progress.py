"""progress=True (a tqdm bar on stderr) and messages on the ``vesselflow`` logger."""

from __future__ import annotations

import logging

import vesselflow
from conftest import make_tube


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
