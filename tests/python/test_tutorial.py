"""docs/tutorial.md says every command and output in it was run as shown: run it and
compare what it prints (timings aside) with what the page shows."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

TUTORIAL = Path(__file__).resolve().parents[2] / "docs" / "tutorial.md"

pytest.importorskip("nibabel")
pytest.importorskip("matplotlib")


def blocks(kind: str, text: str) -> list[str]:
    return re.findall(rf"```{kind}\n(.*?)```", text, re.S)


def in_order(printed: list[str], shown: list[str]) -> None:
    """Every printed line appears among the shown lines, in the same order."""
    at = 0
    for line in printed:
        assert line in shown[at:], (
            f"printed {line!r}, not shown (after line {at} of the page's output)"
        )
        at = shown.index(line, at) + 1


def test_the_tutorial_prints_what_it_shows(tmp_path):
    page = TUTORIAL.read_text(encoding="utf-8")
    code = blocks("python", page)
    texts = blocks("text", page)
    assert len(code) == 5
    assert code[0].startswith("# make_volume.py")

    def run(args: list[str]) -> list[str]:
        done = subprocess.run(args, cwd=tmp_path, capture_output=True, text=True, check=True)
        return [line.rstrip() for line in (done.stdout + done.stderr).splitlines()]

    (tmp_path / "make_volume.py").write_text(code[0])
    assert run([sys.executable, "make_volume.py"]) == texts[0].splitlines()[1:]

    # The command line: every line but the per-stage seconds.
    cli = run(
        [
            sys.executable,
            "-m",
            "vesselflow",
            "skeletonize",
            "vessels.nii.gz",
            "-o",
            "vessels.graphml",
            "--plot",
            "vessels.png",
        ]
    )
    timed = re.compile(r"^(stage +seconds|\s*\w+ +\d+\.\d+)$")
    shown = [line for line in texts[1].splitlines()[1:] if not timed.match(line)]
    assert [line for line in cli if not timed.match(line)] == shown

    # Python: what the script prints to stdout (the progress bar and the log go to stderr).
    (tmp_path / "tutorial.py").write_text("\n".join(code[1:]))
    done = subprocess.run(
        [sys.executable, "tutorial.py"], cwd=tmp_path, capture_output=True, text=True, check=True
    )
    shown = [line.rstrip() for t in texts[2:] for line in t.splitlines()]
    in_order([line.rstrip() for line in done.stdout.splitlines()], shown)
    assert (
        "INFO:vesselflow.skeletonizer:"
        + done.stderr.split("INFO:vesselflow.skeletonizer:")[1].splitlines()[0]
        in shown
    )
