"""What the distribution carries: one stable-ABI extension, the licence, the metadata a
package index shows, the console script, and an sdist with everything a wheel is built
from (README "Set up")."""

from __future__ import annotations

import email
import importlib.machinery
import importlib.metadata
import importlib.util
import re
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

import vesselflow
from vesselflow import _core

ROOT = Path(__file__).resolve().parents[2]
needs_source = pytest.mark.skipif(
    not (ROOT / "pyproject.toml").is_file(), reason="needs the source tree (pyproject.toml)"
)


def abi3_floor() -> tuple[int, int]:
    """The oldest CPython the extension is built for: pyo3's `abi3-pyXY` feature."""
    manifest = (ROOT / "crates" / "py" / "Cargo.toml").read_text()
    found = re.findall(r'"abi3-py(\d)(\d+)"', manifest)
    assert len(found) == 1, "crates/py/Cargo.toml names no single abi3-pyXY feature"
    return int(found[0][0]), int(found[0][1])


def python_versions(classifiers: list[str]) -> list[tuple[int, int]]:
    prefix = "Programming Language :: Python :: "
    versions = [c[len(prefix) :] for c in classifiers if c.startswith(prefix)]
    return sorted(
        (int(v.split(".")[0]), int(v.split(".")[1])) for v in versions if v.count(".") == 1
    )


def check_metadata(meta: email.message.Message) -> None:
    """The fields a package index shows, from core metadata (installed or PKG-INFO)."""
    assert meta.get("License-Expression") == "MIT"
    assert "LICENSE" in meta.get_all("License-File", [])
    assert meta.get("Author") == "the vesselflow developers"
    urls = dict(u.split(", ", 1) for u in meta.get_all("Project-URL", []))
    assert {"Homepage", "Repository", "Issues"} <= set(urls)
    assert all(u.startswith("https://") for u in urls.values())
    assert "skeletonization" in meta.get("Keywords", "").split(",")
    classifiers = meta.get_all("Classifier", [])
    assert "Operating System :: POSIX :: Linux" in classifiers
    assert "Typing :: Typed" in classifiers
    # PEP 639: a licence classifier beside License-Expression is refused by PyPI.
    assert not [c for c in classifiers if c.startswith("License ::")]
    # Every version from requires-python's floor to the newest classified one, no gaps.
    versions = python_versions(classifiers)
    floor = re.fullmatch(r">=\s*(\d+)\.(\d+)", meta.get("Requires-Python", ""))
    assert floor is not None
    assert versions[0] == (int(floor[1]), int(floor[2]))
    assert versions == [(3, minor) for minor in range(versions[0][1], versions[-1][1] + 1)]


@pytest.mark.skipif(sys.implementation.name != "cpython", reason="abi3 is CPython's")
@pytest.mark.skipif(sys.platform == "win32", reason="Windows names no ABI in the file name")
def test_the_extension_is_the_one_stable_abi_build() -> None:
    path = Path(_core.__file__)
    assert path.name == "_core.abi3.so"
    # A version-specific build left beside it would be imported first (it precedes
    # .abi3.so in EXTENSION_SUFFIXES) and shadow a fresh build.
    others = [
        p.name
        for p in path.parent.iterdir()
        if p.name.startswith("_core.")
        and p.name.endswith(tuple(importlib.machinery.EXTENSION_SUFFIXES))
    ]
    assert others == [path.name]


def installed_metadata() -> email.message.Message:
    meta = importlib.metadata.metadata("vesselflow")
    assert isinstance(meta, email.message.Message)
    return meta


def test_installed_metadata() -> None:
    meta = installed_metadata()
    check_metadata(meta)
    assert meta["Version"] == vesselflow.__version__
    versions = python_versions(meta.get_all("Classifier", []))
    assert sys.version_info[:2] in versions, "the running Python is not among the classifiers"


def test_installed_licence_file() -> None:
    dist = importlib.metadata.distribution("vesselflow")
    text = dist.read_text("licenses/LICENSE")
    assert text is not None
    assert text.startswith("MIT License")
    assert "Copyright (c) 2026 the vesselflow developers" in text


def test_console_script_is_the_cli() -> None:
    dist = importlib.metadata.distribution("vesselflow")
    (script,) = [
        ep for ep in dist.entry_points if (ep.group, ep.name) == ("console_scripts", "vesselflow")
    ]
    from vesselflow.__main__ import main

    assert script.load() is main


@needs_source
def test_classifiers_start_at_the_abi3_floor() -> None:
    assert python_versions(installed_metadata().get_all("Classifier", []))[0] == abi3_floor()


@needs_source
def test_repository_address_is_the_same_everywhere() -> None:
    cargo = re.search(r'^repository = "([^"]+)"', (ROOT / "Cargo.toml").read_text(), re.M)
    assert cargo is not None
    urls = installed_metadata().get_all("Project-URL", [])
    assert f"Repository, {cargo[1]}" in urls


@needs_source
@pytest.mark.skipif(importlib.util.find_spec("maturin") is None, reason="maturin not installed")
def test_sdist_has_what_a_wheel_is_built_from(tmp_path: Path) -> None:
    subprocess.run(
        [sys.executable, "-m", "maturin", "sdist", "--out", str(tmp_path)],
        cwd=ROOT,
        check=True,
        capture_output=True,
        timeout=300,
    )
    (sdist,) = tmp_path.glob("vesselflow-*.tar.gz")
    with tarfile.open(sdist) as tar:
        top = tar.getnames()[0].split("/")[0]
        names = {n.removeprefix(top + "/") for n in tar.getnames()}
        pkg_info = tar.extractfile(f"{top}/PKG-INFO")
        assert pkg_info is not None
        meta = email.message_from_bytes(pkg_info.read())
        licence = tar.extractfile(f"{top}/LICENSE")
        assert licence is not None
        assert licence.read().startswith(b"MIT License")
    for needed in [
        "LICENSE",
        "README.md",
        "Cargo.lock",
        "python/vesselflow/__init__.py",
        "python/vesselflow/__main__.py",
        "python/vesselflow/_core.pyi",
        "python/vesselflow/py.typed",
    ]:
        assert needed in names
    check_metadata(meta)
