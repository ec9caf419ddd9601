"""The Laplacian-flow skeletonizer: a binary vessel mask in, a centreline graph out."""

from __future__ import annotations

import logging
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, Literal

import numpy as np

from vesselflow import _core
from vesselflow.graph import VesselGraph

logger = logging.getLogger(__name__)
"""Messages go to the ``vesselflow`` logger hierarchy (no prints)."""

ProgressCallback = Callable[[str, int, int, float], object]
"""``progress(stage, iteration, nodes, measure)``, called after every stage and iteration."""


class Skeletonizer:
    """Turns 3-D binary vessel masks into centreline graphs by Laplacian flow.

    Implements Damseh et al., "Laplacian Flow Dynamics on Geometric Graphs for
    Anatomical Modeling of Cerebrovascular Networks", as specified in METHOD.md.
    Every argument is keyword-only; an invalid value raises ``ValueError`` naming it.

    Parameters
    ----------
    connectivity : {6, 18, 26}
        Edges of the initial grid graph of foreground voxels.
    reconnect_thin : bool
        Also join every node of degree <= 2 to all foreground voxels within sqrt(2)
        voxels, so that one-voxel-thin vessels are not lost.
    radius_correction : float in [0, 1]
        Subtracted from every radius, in units of the smallest spacing: the distance
        transform measures to background voxel centres, half a voxel beyond the surface.
    medial_weight : {"radius", "difference"}
        Medial Laplacian weights: ``r_j / sum r_k`` (the authors' code) or
        ``|r_i - r_j| / sum |r_i - r_k|`` (the paper's eq. 3).
    skeletal_angle : float in [0, 90]
        Degrees within which all neighbour directions of a node must be collinear
        for it to count as already skeletal (adaptive anchoring).
    anchor_ends : bool
        Also count nodes of degree 1 (free vessel ends) as skeletal, so the flow does not
        pull ends inward along their vessels (not in METHOD.md; ``False`` follows it).
    eps_gamma : float >= 1
        Anchoring factor of skeletal nodes.
    alpha, beta : float >= 0
        Weights of the l2-norm and medial Laplacians (not both 0).
    gamma : float > 0
        Anchoring weight: lower contracts faster and coarser.
    cg_tol : float in (0, 0.5]
        Relative residual at which conjugate gradients stop, measured in the
        preconditioner's norm (``sqrt(r . B r)`` against its starting value).
    cg_max_iterations : int >= 1
        Cap on conjugate-gradient iterations per solve.
    max_cycle_nodes : int in [4, 64]
        Cycles with fewer nodes count in the convergence measure.
    stop_ratio : float in (0, 1]
        Contraction stops when the short-cycle area falls to this fraction of the
        reference area.
    stall_ratio : float in [0, 0.5]
        Contraction also stops (``info["stalled"]``) when an iteration merges fewer than
        this fraction of the nodes while the short-cycle area is within 10 times the stop
        level: the graph has stopped simplifying and further flow only shortens vessel
        ends. 0 turns the test off (METHOD.md).
    area_reference : {"volume", "initial_area"}
        Reference area: the foreground voxel count (the authors' code) or the initial
        short-cycle area (the paper).
    max_iterations : int >= 0
        Cap on contraction iterations (``info["converged"]`` and ``info["stalled"]``
        are False if reached).
    refine_area : float >= 0
        Refinement collapses cycles with an area below this many squared voxels.
    max_refine_iterations : int >= 0
        Cap on refinement iterations.
    threads : int >= 0
        Worker threads, 0 for one per core. The output does not depend on it.
    max_memory : int, str or None
        Refuse (``MemoryError``, naming what the run needs and what is allowed) a run
        whose estimated peak memory exceeds this many bytes, before its heavy stages.
        Bytes or a string with a unit (``"8GB"``, ``"512MiB"``). ``"auto"`` (default):
        what this process may still use (the smallest of the cgroup limit, the
        address-space limit and ``MemAvailable``), read when the run starts. ``0`` or
        ``None``: no limit. The output does not depend on it.

    Examples
    --------
    >>> import numpy as np, vesselflow
    >>> mask = np.zeros((40, 21, 21), bool)
    >>> mask[:, 6:15, 6:15] = True
    >>> graph = vesselflow.Skeletonizer(gamma=0.05).run(mask, spacing=(1.0, 0.5, 0.5))
    >>> graph.positions.shape[1]
    3
    """

    __slots__ = ("_core",)

    def __init__(
        self,
        *,
        connectivity: Literal[6, 18, 26] = 6,
        reconnect_thin: bool = True,
        radius_correction: float = 0.5,
        medial_weight: Literal["radius", "difference"] = "radius",
        skeletal_angle: float = 10.0,
        anchor_ends: bool = True,
        eps_gamma: float = 10.0,
        alpha: float = 0.25,
        beta: float = 0.5,
        gamma: float = 0.05,
        cg_tol: float = 1e-4,
        cg_max_iterations: int = 2000,
        max_cycle_nodes: int = 10,
        stop_ratio: float = 1e-3,
        stall_ratio: float = 0.01,
        area_reference: Literal["volume", "initial_area"] = "volume",
        max_iterations: int = 100,
        refine_area: float = 50.0,
        max_refine_iterations: int = 100,
        threads: int = 0,
        max_memory: int | str | None = "auto",
    ) -> None:
        # The signature above spells every parameter out for help() and type checkers;
        # the Rust core validates them (tests check these defaults against the core's).
        params = {name: value for name, value in locals().items() if name != "self"}
        if max_memory is None:
            params["max_memory"] = 0
        self._core = _core.Skeletonizer(**params)

    @property
    def params(self) -> dict[str, bool | int | float | str]:
        """Every parameter and its value, in documentation order."""
        return self._core.params

    def __repr__(self) -> str:
        return repr(self._core)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Skeletonizer):
            return NotImplemented
        return self._core == other._core

    __hash__ = None  # type: ignore[assignment]

    def run(
        self,
        mask: np.ndarray,
        spacing: Sequence[float] | float = (1.0, 1.0, 1.0),
        progress: ProgressCallback | bool | None = None,
        *,
        threshold: float | None = None,
        label: float | None = None,
        prune_min_length_over_radius: float | None = None,
    ) -> VesselGraph:
        """Skeletonize one mask.

        Parameters
        ----------
        mask : numpy.ndarray
            3-D array, any memory order and strides. It is made a mask by the input
            rule that :func:`load_volume` and the command line apply too: bool (read
            without a copy), integers with zero and at most one other value, or floats
            that are all 0 or 1 are binary (non-zero = vessel); anything else (a label
            image, a probability map, NaN) is a ``ValueError`` naming the values found,
            unless ``threshold`` or ``label`` says how to binarise it.
        spacing : sequence of 3 floats, or a float
            Voxel size along axes 0, 1, 2 in physical units (one number: the same on
            every axis); positions and radii of the result are in the same units.
        progress : callable or bool, optional
            ``True`` shows a tqdm bar on stderr (contraction iterations out of
            ``max_iterations``, with the stage, nodes left and the convergence
            measure, which reaches 1 when the run stops). A callable is called as
            ``progress(stage, iteration, nodes, measure)`` after every stage and
            iteration; an exception it raises stops the run and propagates.
        threshold : float, optional
            Vessel where ``mask > threshold`` (e.g. a probability map).
        label : float, optional
            Vessel where ``mask == label`` (one label of a label image); not with
            ``threshold``.
        prune_min_length_over_radius : float, optional
            If given, finish with :meth:`VesselGraph.prune` at this ratio: terminal
            spurs shorter than this many radii of the vessel they join are removed.
            Default ``None``: no pruning.

        An empty mask gives an empty graph and a ``UserWarning``; a mask that is
        vessel everywhere is a solid block (background lies outside the array). The
        spacing must lie in [1e-12, 1e12] on every axis (``ValueError`` otherwise).

        The GIL is released while the core runs; Ctrl-C raises ``KeyboardInterrupt``
        within a fraction of a second, at any stage. An internal error (a bug) is a
        ``RuntimeError`` starting "internal error, please report".
        A run that stops at ``max_iterations`` before converging (or stalling) logs a
        warning on the ``vesselflow`` logger.
        """
        with _progress_callback(progress, int(self.params["max_iterations"])) as callback:
            positions, radii, edges, info = self._core.run(
                mask, spacing, callback, threshold=threshold, label=label
            )
        if info["foreground_voxels"] == 0:
            warnings.warn("the mask is empty: the graph has no nodes", UserWarning, stacklevel=2)
        if not (info["converged"] or info["stalled"]):
            logger.warning(
                "contraction stopped at max_iterations=%d before converging "
                "(info['converged'] is False; see info['area_per_iteration']): "
                "raise max_iterations or lower gamma",
                info["iterations"],
            )
        graph = VesselGraph(
            positions=positions,
            radii=radii,
            edges=edges,
            spacing=np.broadcast_to(np.asarray(spacing, dtype=np.float64), 3),
            info=info,
            params=self.params,
        )
        if prune_min_length_over_radius is not None:
            graph = graph.prune(prune_min_length_over_radius)
        logger.info(
            "skeletonized %d voxels into %d nodes and %d edges in %d iterations",
            info["foreground_voxels"],
            graph.n_nodes,
            graph.n_edges,
            info["iterations"],
        )
        return graph


@contextmanager
def _progress_callback(
    progress: ProgressCallback | bool | None, max_iterations: int
) -> Iterator[ProgressCallback | None]:
    """The core's callback for ``progress``: ``True`` drives a tqdm bar, closed on exit."""
    if progress is not True:
        yield progress or None
        return
    from tqdm.auto import tqdm

    with tqdm(total=max_iterations, unit="it", desc="vesselflow") as bar:

        def update(stage: str, iteration: int, nodes: int, measure: float) -> None:
            if stage == "contract":
                bar.update(iteration - bar.n)
            elif stage == "output":  # converged or stalled early: show the bar as complete
                bar.total = bar.n
            bar.set_postfix(stage=stage, nodes=nodes, measure=f"{measure:.3g}")

        yield update


def skeletonize(
    mask: np.ndarray,
    spacing: Sequence[float] | float = (1.0, 1.0, 1.0),
    *,
    progress: ProgressCallback | bool | None = None,
    threshold: float | None = None,
    label: float | None = None,
    prune_min_length_over_radius: float | None = None,
    **params: Any,
) -> VesselGraph:
    """Skeletonize ``mask`` in one call: ``Skeletonizer(**params).run(mask, spacing)``.

    See :class:`Skeletonizer` for the parameters and :meth:`Skeletonizer.run` for
    ``mask``, ``spacing``, ``progress``, ``threshold``, ``label`` and
    ``prune_min_length_over_radius``.
    """
    return Skeletonizer(**params).run(
        mask,
        spacing,
        progress,
        threshold=threshold,
        label=label,
        prune_min_length_over_radius=prune_min_length_over_radius,
    )
