"""The command line from Python: ``python -m vesselflow``, the console script, and
``_core.cli_main`` (the same program as the Rust binary)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import sysconfig

import numpy as np
import pytest

import vesselflow
from conftest import make_slow_tube, make_tube
from vesselflow import _core, load_graph


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, capture_output=True, text=True, timeout=300, check=False)


def test_python_m_vesselflow_demo_prints_a_summary():
    result = run(sys.executable, "-m", "vesselflow", "demo")
    assert result.returncode == 0, result.stderr
    assert "vesselflow demo" in result.stdout
    summary = dict(line.split(maxsplit=1) for line in result.stdout.splitlines()[1:3])
    assert int(summary["nodes"]) > 10


def test_console_script_help():
    script = os.path.join(sysconfig.get_path("scripts"), "vesselflow")
    if not os.path.exists(script):
        pytest.skip(f"console script not installed at {script}")
    result = run(script, "--help")
    assert result.returncode == 0, result.stderr
    assert "skeletonize" in result.stdout
    assert "demo" in result.stdout


def test_version_is_the_package_version():
    result = run(sys.executable, "-m", "vesselflow", "--version")
    assert result.returncode == 0
    assert result.stdout.split() == ["vesselflow", vesselflow.__version__]


def test_cli_and_python_api_give_the_same_graph(branching, tmp_path):
    np.save(tmp_path / "mask.npy", branching.astype(np.uint8))
    out = tmp_path / "graph.npz"
    argv = ["vesselflow", "skeletonize", str(tmp_path / "mask.npy"), "-o", str(out)]
    code = _core.cli_main([*argv, "--spacing", "1", "2", "0.5", "--gamma", "0.1", "-q"])
    assert code == 0
    from_cli = load_graph(out)
    from_python = vesselflow.skeletonize(branching, spacing=(1, 2, 0.5), gamma=0.1)
    np.testing.assert_array_equal(from_cli.positions, from_python.positions)
    np.testing.assert_array_equal(from_cli.radii, from_python.radii)
    np.testing.assert_array_equal(from_cli.edges, from_python.edges)
    assert from_cli.params == from_python.params


def test_bad_command_line_exits_2_with_a_one_line_error(tmp_path):
    np.save(tmp_path / "mask.npy", np.zeros((4, 4, 4), np.uint8))
    mask = str(tmp_path / "mask.npy")
    for args, problem in (
        (["skeletonize", mask, "-o", str(tmp_path / "g.xyz")], "g.xyz"),
        (["skeletonize", mask, "-o", str(tmp_path / "g.json"), "--gamma", "-1"], "gamma"),
    ):
        result = run(sys.executable, "-m", "vesselflow", *args)
        assert result.returncode == 2
        errors = [line for line in result.stderr.splitlines() if line.strip()]
        assert len(errors) == 1, result.stderr
        assert errors[0].startswith("vesselflow: error:")
        assert problem in errors[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mask.npy"]


@pytest.mark.skipif(sys.platform == "win32", reason="needs POSIX signals")
def test_ctrl_c_stops_the_console_program_without_output(tmp_path):
    np.save(tmp_path / "mask.npy", make_slow_tube())
    out = tmp_path / "graph.json"
    argv = [sys.executable, "-m", "vesselflow", "skeletonize", str(tmp_path / "mask.npy")]
    # The child gets SIGINT's default action, as in a terminal: a test runner started in
    # the background of a non-interactive shell has it ignored, and that is inherited.
    with subprocess.Popen(
        [*argv, "-o", str(out)],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    ) as proc:
        assert proc.stderr is not None
        first = proc.stderr.readline()  # the first progress report: the run has begun
        proc.send_signal(signal.SIGINT)
        rest = proc.stderr.read()
        code = proc.wait(timeout=120)
    assert first, rest
    assert code == 130, first + rest
    assert "interrupted" in rest
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mask.npy"]


def test_help_gives_every_method_parameter_a_sentence():
    result = run(sys.executable, "-m", "vesselflow", "skeletonize", "--help")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    for name in vesselflow.Skeletonizer().params:
        option = f"--{name.replace('_', '-')} <VALUE>"
        line = next((line for line in lines if option in line), None)
        assert line is not None, f"{option} missing"
        words = line.split(option, 1)[1].split("[default:")[0].split()
        assert len(words) >= 4, line
        assert words[-1].endswith("."), line
    assert "METHOD.md" not in result.stdout
    assert "docs/parameters.md" in result.stdout


def test_a_run_says_how_it_ended_and_what_the_graph_holds(tmp_path):
    np.save(tmp_path / "tube.npy", make_tube((40, 15, 15)).astype(np.uint8))
    base = [sys.executable, "-m", "vesselflow", "skeletonize", str(tmp_path / "tube.npy")]
    result = run(*base, "-o", str(tmp_path / "g.json"))
    assert result.returncode == 0, result.stderr
    graph = load_graph(tmp_path / "g.json")
    ending = [line for line in result.stderr.splitlines() if " after " in line]
    iterations = graph.info["iterations"]
    assert ending == [
        f"vesselflow: converged after {iterations} iteration{'s' * (iterations != 1)}: "
        f"{graph.n_nodes} nodes, {graph.n_edges} edges, 1 component, 0 independent cycles, "
        "0 junctions, 2 endpoints"
    ]
    # The contraction's parts are timed under one `contract` row, named as in the progress.
    timing = result.stderr.split("stage ", 1)[1].splitlines()
    assert [line.split()[0] for line in timing if not line.startswith(" ")][:4] == [
        "edt",
        "grid",
        "coarse",
        "contract",
    ]

    capped = run(*base, "-o", str(tmp_path / "c.json"), "--max-iterations", "1")
    assert capped.returncode == 0, capped.stderr
    assert "warning: the contraction stopped at --max-iterations 1" in capped.stderr
    assert "vesselflow: stopped at --max-iterations after 1 iteration: " in capped.stderr
    # Under --quiet the warning stays and the ending line goes.
    quiet = run(*base, "-o", str(tmp_path / "c.json"), "--max-iterations", "1", "-q")
    assert quiet.stderr.splitlines() == [capped.stderr.splitlines()[-3]]


def test_an_empty_mask_warns_on_the_command_line(tmp_path):
    np.save(tmp_path / "empty.npy", np.zeros((5, 6, 7), np.uint8))
    result = run(
        sys.executable, "-m", "vesselflow", "skeletonize", str(tmp_path / "empty.npy"),
        "-o", str(tmp_path / "g.json"), "-q",
    )  # fmt: skip
    assert result.returncode == 0
    assert result.stderr == "vesselflow: warning: the mask is empty: the graph has no nodes\n"
    assert load_graph(tmp_path / "g.json").n_nodes == 0
