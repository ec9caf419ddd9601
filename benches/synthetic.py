"""Synthetic vascular beds for the benchmarks: a command line around
:func:`vesselflow.synth.vascular_bed`.

``vascular_bed(size, seed)`` returns a cubic boolean mask of about 5 % foreground: a
connected tree of random, gently curving tubes of radii 1.5 to 6 voxels plus a few
anastomoses, one 26-connected component, the same volume for the same seed (see its
docstring). With numpy alone a 256^3 bed takes about 2 s.

Run it to see a volume's figures::

    python benches/synthetic.py 256 --seed 0 [--out bed.npy]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from typing import BinaryIO, Callable

import numpy as np

from vesselflow.synth import vascular_bed

__all__ = ["describe", "vascular_bed", "write_atomic"]


def describe(mask: np.ndarray) -> tuple[float, int]:
    """Foreground fraction and number of 26-connected components of ``mask``."""
    try:
        import cc3d

        components = int(cc3d.connected_components(mask, connectivity=26, return_N=True)[1])
    except ImportError:
        from scipy import ndimage

        components = int(ndimage.label(mask, structure=np.ones((3, 3, 3)))[1])
    return float(np.count_nonzero(mask)) / mask.size, components


def write_atomic(path: str | os.PathLike[str], write: Callable[[BinaryIO], object]) -> None:
    """Create or replace ``path`` with what ``write`` puts in a binary file: first a temp
    file in the same folder, then a rename, so no reader ever sees a partial file."""
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # the mode open() would give, not mkstemp's 0600
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("size", type=int, help="edge of the cube, voxels")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fraction", type=float, default=0.05, help="target foreground")
    parser.add_argument("--loops", type=int, default=4, help="anastomoses to add")
    parser.add_argument("--out", help="write the mask here (.npy, bool)")
    args = parser.parse_args()
    t0 = time.perf_counter()
    try:
        mask = vascular_bed(args.size, args.seed, args.fraction, args.loops)
    except ValueError as e:
        parser.error(str(e))
    seconds = time.perf_counter() - t0
    frac, components = describe(mask)
    print(
        f"{args.size}^3 seed {args.seed}: {np.count_nonzero(mask)} foreground voxels "
        f"({100 * frac:.2f} %), {components} 26-connected component(s), "
        f"generated in {seconds:.1f} s"
    )
    if args.out:
        write_atomic(args.out, lambda f: np.save(f, mask))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
