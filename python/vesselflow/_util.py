"""Helpers shared by the modules of the package: optional imports and atomic writes.

Nothing here imports another vesselflow module, so every module may import this one.
"""

from __future__ import annotations

import importlib
import os
import secrets
import shutil
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType

import numpy as np


def import_extra(module: str, extra: str) -> ModuleType:
    """Import an optional dependency; if it is missing, say which extra installs it.

    Parameters
    ----------
    module : str
        The module to import, e.g. ``"nibabel"``.
    extra : str
        The extra of vesselflow that installs it, e.g. ``"io"``.

    Returns
    -------
    types.ModuleType
        The imported module.

    Raises
    ------
    ModuleNotFoundError
        Naming the module and ``pip install vesselflow[extra]``.

    Examples
    --------
    >>> import_extra("json", "io").__name__
    'json'
    """
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        raise ModuleNotFoundError(
            f"{module} is not installed; install it with: pip install vesselflow[{extra}]",
            name=module,
        ) from e


TEMP_PREFIX, TEMP_SUFFIX = ".vesselflow-", ".tmp"
"""Temporary files of an unfinished write are named ``.vesselflow-*.tmp``, as the Rust
writers name them."""


def _temp_beside(path: Path) -> Path:
    return path.with_name(f"{TEMP_PREFIX}{secrets.token_hex(6)}{TEMP_SUFFIX}")


@contextmanager
def atomic_files(*paths: Path) -> Iterator[list[Path]]:
    """One temporary path beside each of ``paths`` for the block to write; when the
    block succeeds they replace ``paths`` together.

    All or nothing: on any failure (an exception in the block, a failed rename,
    ``KeyboardInterrupt``, the ``Terminated`` that the console script raises on
    SIGTERM) the temporary files are removed, the files already replaced get their old
    contents back and files that did not exist are not created.

    Parameters
    ----------
    *paths : pathlib.Path
        The files to write.

    Returns
    -------
    contextlib.AbstractContextManager
        Yields the list of temporary paths, one per target, in order.

    Examples
    --------
    >>> import tempfile
    >>> target = Path(tempfile.mkdtemp()) / "a.txt"
    >>> with atomic_files(target) as (temp,):
    ...     _ = temp.write_text("done")
    >>> target.read_text()
    'done'
    """
    temps = [_temp_beside(path) for path in paths]
    try:
        yield temps
        _replace_all(temps, list(paths))
    finally:
        for temp in temps:
            temp.unlink(missing_ok=True)


@contextmanager
def atomic_file(path: Path) -> Iterator[Path]:
    """:func:`atomic_files` for one file.

    Parameters
    ----------
    path : pathlib.Path
        The file to write.

    Returns
    -------
    contextlib.AbstractContextManager
        Yields the temporary path to write; it replaces ``path`` when the block ends
        without an exception.

    Examples
    --------
    >>> import tempfile
    >>> target = Path(tempfile.mkdtemp()) / "b.txt"
    >>> with atomic_file(target) as temp:
    ...     _ = temp.write_text("done")
    >>> target.read_text()
    'done'
    """
    with atomic_files(path) as (temp,):
        yield temp


def _replace_all(temps: list[Path], paths: list[Path]) -> None:
    if len(paths) == 1:
        os.replace(temps[0], paths[0])
        return
    # Keep the old files (a hard link, or a copy where links are not supported) until
    # every new one is in place, so that a failure part-way can put them back. What is
    # undone is read from the disk, not from variables, so an exception between any two
    # steps (KeyboardInterrupt, SIGTERM) still undoes exactly what was done.
    backups = [_temp_beside(path) for path in paths]
    try:
        for path, backup in zip(paths, backups):
            _keep_old(path, backup)
        for temp, path in zip(temps, paths):
            os.replace(temp, path)
    except BaseException:
        for temp, path, backup in zip(temps, paths, backups):
            if temp.exists():  # not moved into place: nothing to undo
                continue
            if backup.exists():
                os.replace(backup, path)
            else:
                path.unlink(missing_ok=True)
        raise
    finally:
        for backup in backups:
            backup.unlink(missing_ok=True)


def _keep_old(path: Path, backup: Path) -> None:
    """Give the file at ``path``, if any, the second name ``backup``."""
    if not os.path.lexists(path):
        return
    try:
        os.link(path, backup, follow_symlinks=False)
    except OSError:
        shutil.copy2(path, backup, follow_symlinks=False)


def spacing_argument(spacing: Sequence[float] | float) -> tuple[float, float, float]:
    """A ``spacing=`` argument as 3 floats; one number means the same on every axis.

    The values themselves are checked by the run, as for any spacing.

    Parameters
    ----------
    spacing : float or sequence of 3 floats
        Voxel size along the array axes.

    Returns
    -------
    tuple of 3 floats

    Raises
    ------
    ValueError
        If ``spacing`` is neither one number nor three.

    Examples
    --------
    >>> spacing_argument(0.5)
    (0.5, 0.5, 0.5)
    """
    values = np.asarray(spacing, dtype=np.float64).reshape(-1)
    if values.size not in (1, 3):
        raise ValueError(f"spacing={spacing!r} must be 3 numbers or one")
    values = np.broadcast_to(values, 3)
    return float(values[0]), float(values[1]), float(values[2])
