"""``python -m vesselflow`` and the ``vesselflow`` console script: the command-line
program of the Rust binary, run from the extension module."""

from __future__ import annotations

import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

from vesselflow import _core

EXIT_TERMINATED = 128 + signal.SIGTERM
"""Exit status after SIGTERM, as a shell reports a process that SIGTERM killed."""


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived. Raised by the handler :func:`sigterm_raises` installs, so that
    it unwinds like Ctrl-C: a run stops at its next progress report and every atomic
    write in progress removes its temporary files."""


@contextmanager
def sigterm_raises() -> Iterator[list[bool]]:
    """Within the block, the first SIGTERM raises :class:`Terminated` (a second one
    gets the default action: the process ends at once). Yields a one-item list that
    is ``[True]`` once SIGTERM has arrived. The previous handler is restored on exit;
    outside the main thread this does nothing (Python only handles signals there)."""
    received = [False]

    def handler(signum: int, frame: FrameType | None) -> None:
        received[0] = True
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        raise Terminated(f"terminated by signal {signum}")

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread
        yield received
        return
    try:
        yield received
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def main() -> None:
    """Run the command line with ``sys.argv`` and exit with its status: 143 after
    SIGTERM (the run stops, and no output file or temporary file is left).
    ``vesselflow distributed ...`` is the chunked run on Dask (Python only)."""
    if sys.argv[1:2] == ["distributed"]:
        from vesselflow.distributed import main as distributed_main

        sys.exit(distributed_main(sys.argv[2:]))
    try:
        with sigterm_raises() as terminated:
            # SIGTERM while the run polls for signals stops the run (the program says
            # "interrupted"); at any other time Terminated propagates to here.
            code = _core.cli_main(["vesselflow", *sys.argv[1:]])
            if terminated[0]:
                code = EXIT_TERMINATED
    except Terminated:
        code = EXIT_TERMINATED
    sys.exit(code)


if __name__ == "__main__":
    main()
