"""The Rust extension of vesselflow (private: use the ``vesselflow`` package)."""

import os
from collections.abc import Callable, Sequence
from typing import Any, final

import numpy as np
from numpy.typing import NDArray

_ParamValue = bool | int | float | str

__version__: str
__all__ = [
    "Skeletonizer",
    "__version__",
    "binarise",
    "cli_main",
    "contract_block",
    "largest_radius",
    "memory_estimate",
    "merge_blocks",
    "owner_voxels",
    "param_defaults",
    "prune_spurs",
    "route_block",
    "splice_routes",
    "to_frame",
    "usable_memory",
    "write_graph",
]

@final
class Skeletonizer:
    """The method with a fixed set of parameters (see ``vesselflow.Skeletonizer``)."""

    def __new__(cls, **params: _ParamValue) -> Skeletonizer: ...
    @property
    def params(self) -> dict[str, _ParamValue]: ...
    def __eq__(self, value: object, /) -> bool: ...
    def run(
        self,
        mask: NDArray[Any],
        spacing: Sequence[float] | float = (1.0, 1.0, 1.0),
        progress: Callable[[str, int, int, float], object] | None = None,
        threshold: float | None = None,
        label: float | None = None,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64], dict[str, Any]]:
        """Returns ``(positions (N, 3), radii (N,), edges (E, 2) int64, info)``."""

def binarise(
    data: NDArray[Any], threshold: float | None = None, label: float | None = None
) -> NDArray[np.bool_]:
    """The input rule: ``data`` if bool, else a new bool mask (``ValueError`` if not one)."""

def memory_estimate(
    shape: tuple[int, int, int] | list[int],
    foreground: int,
    connectivity: int = 6,
    threads: int = 0,
) -> int:
    """Estimated peak bytes beyond the mask of a run (the ``max_memory`` guard's figure)."""

def usable_memory() -> int | None:
    """Bytes this process may still allocate (available memory, cgroup and
    ``RLIMIT_AS`` room, the least); ``None`` where none is known."""

def param_defaults() -> list[tuple[str, _ParamValue]]:
    """Every parameter with its default, in documentation order."""

def write_graph(
    path: str | os.PathLike[str],
    positions: NDArray[np.float64],
    radii: NDArray[np.float64],
    edges: NDArray[np.int64],
    spacing: Sequence[float] | NDArray[np.float64],
    info_json: str,
    params_json: str,
) -> None:
    """Write a graph atomically; the extension of ``path`` picks the format."""

def to_frame(
    positions: NDArray[np.float64],
    spacing: Sequence[float],
    coordinates: str,
    affine: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], tuple[float, float, float], str | None]:
    """Positions in the frame ``coordinates``, the spacing to store, and a warning."""

def cli_main(argv: list[str]) -> int:
    """Run the ``vesselflow`` command line with ``argv`` (``argv[0]`` is the program name)."""

def contract_block(
    skeletonizer: Skeletonizer,
    mask: NDArray[np.uint8],
    origin: Sequence[int],
    core: Sequence[Sequence[int]],
    volume: Sequence[int],
    spacing: Sequence[float],
) -> dict[str, NDArray[Any]]:
    """The block phase of a chunked run: a block part as a dict of arrays."""

def largest_radius(
    skeletonizer: Skeletonizer, mask: NDArray[np.uint8], spacing: Sequence[float]
) -> float | None:
    """The largest vessel radius of a chunk (physical units), or None if it is empty."""

def owner_voxels(
    positions: NDArray[np.float64],
    edges: NDArray[np.int64],
    spacing: Sequence[float],
    volume: Sequence[int],
) -> NDArray[np.int64]:
    """The voxel that owns each edge (its midpoint's voxel, clamped to the volume)."""

def route_block(
    skeletonizer: Skeletonizer,
    mask: NDArray[np.uint8],
    origin: Sequence[int],
    core: Sequence[Sequence[int]],
    volume: Sequence[int],
    spacing: Sequence[float],
    nodes: NDArray[np.uint32],
    positions: NDArray[np.float64],
    edges: NDArray[np.uint32],
) -> dict[str, Any]:
    """The routing phase of one block: the routed part, or the halo it needs."""

def prune_spurs(
    positions: NDArray[np.float64],
    radii: NDArray[np.float64],
    edges: NDArray[np.int64],
    k: float,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], int]:
    """Which nodes and edges pruning the spurs shorter than ``k`` junction radii keeps, and
    how many spurs it removes."""

def splice_routes(
    skeletonizer: Skeletonizer,
    positions: NDArray[np.float64],
    radii: NDArray[np.float64],
    edges: NDArray[np.int64],
    parts: list[dict[str, Any]],
    spacing: Sequence[float],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64], dict[str, Any]]:
    """The merged graph with the routed parts spliced in and its short spurs pruned, and an
    info dict (``pruned_spurs``)."""

def merge_blocks(
    skeletonizer: Skeletonizer,
    parts: list[dict[str, NDArray[Any]]],
    volume: Sequence[int],
    spacing: Sequence[float],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64], dict[str, Any]]:
    """The merge phase of a chunked run: the graph of the block parts."""
