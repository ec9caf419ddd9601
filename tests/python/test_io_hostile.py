"""The Rust NIfTI reader (``crates/io``) against files written by nibabel: data at
``vox_offset`` 1024, big-endian headers, ``scl_slope``/``scl_inter`` scaling, ``.nii``
and ``.nii.gz`` (issue 19). Each file is run through the ``vesselflow`` program and must
give exactly the graph of the same mask saved as ``.npy`` with nibabel's voxel sizes,
so the mask, its axis order and its spacing all agree with nibabel's reading.

Also: the reader's default memory budget follows ``RLIMIT_AS`` (a header declaring
more than the limit is refused up front, with a message naming the budget).

The program is ``$VESSELFLOW_BIN``, else ``target/release/vesselflow`` or
``target/debug/vesselflow`` (build it first: ``cargo build -p vesselflow-cli``).
"""

from __future__ import annotations

import gzip
import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import make_tube

nib = pytest.importorskip("nibabel")

ROOT = Path(__file__).resolve().parents[2]


def program() -> str:
    candidates = [os.environ.get("VESSELFLOW_BIN", "")]
    candidates += [
        str(ROOT / "target" / profile / "vesselflow") for profile in ("release", "debug")
    ]
    for candidate in candidates:
        if candidate and os.access(candidate, os.X_OK):
            return candidate
    pytest.skip(
        "no vesselflow program built (cargo build -p vesselflow-cli, or set VESSELFLOW_BIN)"
    )


def run(*args: str, preexec_fn=None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [program(), *args],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
        preexec_fn=preexec_fn,
    )


def graph_of(path: Path, out: Path, spacing: tuple[float, ...] | None = None) -> dict:
    args = ["skeletonize", str(path), "-o", str(out), "-q"]
    if spacing is not None:
        args += ["--spacing", *(repr(float(s)) for s in spacing)]
    result = run(*args)
    assert result.returncode == 0, result.stderr
    graph = json.loads(out.read_text())
    return {key: graph[key] for key in ("spacing", "positions", "radii", "edges")} | {
        "foreground": graph["info"]["foreground_voxels"]
    }


MASK = make_tube((24, 13, 11), 3.5)
ZOOMS = (0.5, 0.75, 2.0)


def write_variant(path: Path, variant: str) -> None:
    """Write MASK with nibabel in one of the layouts the old reader got wrong."""
    affine = np.diag([*ZOOMS, 1.0])
    if variant == "offset_1024":
        img = nib.Nifti1Image(MASK.astype(np.int16), affine)
        img.header.set_data_offset(1024)
    elif variant == "big_endian_offset_1024":
        # Vessel voxels hold 256: read in the wrong byte order they are still non-zero,
        # so the scaled variant below is what catches a byte-order bug.
        img = nib.Nifti1Image(
            MASK.astype(">i2") * 256, affine, header=nib.Nifti1Header(endianness=">")
        )
        img.set_data_dtype(">i2")
        img.header.set_data_offset(1024)
    elif variant == "big_endian_scaled":
        # Raw 256 / 512 with slope 1/256 and intercept -1: 0 / 1 only if decoded big-endian.
        raw = (MASK.astype(">i2") + 1) * 256
        img = nib.Nifti1Image(raw, affine, header=nib.Nifti1Header(endianness=">"))
        img.set_data_dtype(">i2")
        img.header.set_slope_inter(1 / 256, -1.0)
    elif variant == "float_slope":
        # Raw float32 0 / 2 with slope 0.5.
        img = nib.Nifti1Image(MASK.astype(np.float32) * 2, affine)
        img.set_data_dtype(np.float32)
        img.header.set_slope_inter(0.5, 0.0)
    else:
        raise ValueError(variant)
    nib.save(img, path)


VARIANTS = ["offset_1024", "big_endian_offset_1024", "big_endian_scaled", "float_slope"]


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz"])
@pytest.mark.parametrize("variant", VARIANTS)
def test_nibabel_files_give_the_graph_of_the_same_mask(tmp_path, variant, suffix):
    path = tmp_path / f"{variant}{suffix}"
    write_variant(path, variant)
    # What nibabel reads is the mask (so the file really is the layout claimed).
    img = nib.load(path)
    values = img.get_fdata()
    assert np.array_equal(values != 0, MASK)
    if "scaled" in variant or "slope" in variant:
        assert set(np.unique(values)) == {0.0, 1.0}
        assert img.dataobj.slope != 1.0
    assert tuple(float(z) for z in img.header.get_zooms()[:3]) == ZOOMS
    raw = gzip.decompress(path.read_bytes()) if suffix == ".nii.gz" else path.read_bytes()
    endian = ">" if "big_endian" in variant else "<"
    assert struct.unpack(endian + "i", raw[:4])[0] == 348
    if "offset" in variant:
        assert struct.unpack(endian + "f", raw[108:112])[0] == 1024.0

    reference = tmp_path / "mask.npy"
    np.save(reference, MASK.astype(np.uint8))
    expected = graph_of(reference, tmp_path / "ref.json", ZOOMS)
    assert graph_of(path, tmp_path / "got.json") == expected


def test_nibabel_scaled_to_non_binary_values_is_refused(tmp_path):
    # Raw 0 / 1 with slope 0.5: nibabel reads 0 / 0.5, an image, not a mask.
    path = tmp_path / "half.nii.gz"
    img = nib.Nifti1Image(MASK.astype(np.float32), np.eye(4))
    img.header.set_slope_inter(0.5, 0.0)
    nib.save(img, path)
    assert set(np.unique(nib.load(path).get_fdata())) == {0.0, 0.5}
    result = run("skeletonize", str(path), "-o", str(tmp_path / "g.json"))
    assert result.returncode != 0
    assert "half.nii.gz" in result.stderr, result.stderr
    assert "0.5" in result.stderr, result.stderr


def _gz_declaring(path: Path, dims: tuple[int, int, int]) -> None:
    """A tiny .nii.gz whose nibabel header declares `dims` uint8 voxels but whose
    stream holds only 1 KiB of them."""
    hdr = nib.Nifti1Header()
    hdr.set_data_shape(dims)
    hdr.set_data_dtype(np.uint8)
    hdr.set_data_offset(352)
    body = hdr.binaryblock + b"\0" * 4 + b"\0" * 1024
    path.write_bytes(gzip.compress(body))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_AS budget is Linux only")
def test_default_budget_follows_rlimit_as(tmp_path):
    import resource

    path = tmp_path / "bomb.nii.gz"
    _gz_declaring(path, (2048, 2048, 1024))  # 4 GiB declared, 1 KiB present

    def limit_address_space() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))

    limited = run(
        "skeletonize", str(path), "-o", str(tmp_path / "g.json"), preexec_fn=limit_address_space
    )
    assert limited.returncode != 0
    assert "bomb.nii.gz" in limited.stderr, limited.stderr
    assert "2048\N{MULTIPLICATION SIGN}2048\N{MULTIPLICATION SIGN}1024" in limited.stderr
    assert "may be used" in limited.stderr, limited.stderr

    # Without the limit the budget is larger (unless this machine has under 4 GiB
    # free): the read starts, and the short stream is reported as truncated.
    unlimited = run("skeletonize", str(path), "-o", str(tmp_path / "g.json"))
    assert unlimited.returncode != 0
    if "may be used" not in unlimited.stderr:
        assert "truncated" in unlimited.stderr, unlimited.stderr
