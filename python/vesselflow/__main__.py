"""``python -m vesselflow`` and the ``vesselflow`` console script: the command-line
program of the Rust binary, run from the extension module."""

from __future__ import annotations

import sys

from vesselflow import _core


def main() -> None:
    """Run the command line with ``sys.argv`` and exit with its status."""
    sys.exit(_core.cli_main(["vesselflow", *sys.argv[1:]]))


if __name__ == "__main__":
    main()
