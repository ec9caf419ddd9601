"""The package surface: exports, the stub of the extension, documented examples."""

from __future__ import annotations

import doctest
import importlib.util

import pytest

import vesselflow
import vesselflow.skeletonizer


def test_public_names():
    assert set(vesselflow.__all__) == {
        "Skeletonizer",
        "VesselGraph",
        "VolumeError",
        "__version__",
        "load_graph",
        "load_volume",
        "skeletonize",
    }
    assert vesselflow.__version__.count(".") == 2


def test_docstring_examples_run():
    result = doctest.testmod(vesselflow.skeletonizer)
    assert result.attempted > 0
    assert result.failed == 0


@pytest.mark.skipif(importlib.util.find_spec("mypy") is None, reason="mypy not installed")
def test_core_stub_matches_the_extension():
    from mypy import stubtest

    assert stubtest.test_stubs(stubtest.parse_options(["vesselflow._core"])) == 0
