"""The Laplacian-flow skeletonizer: a binary vessel mask in, a centreline graph out."""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from vesselflow import _core
from vesselflow.graph import VesselGraph

logger = logging.getLogger(__name__)
"""Messages go to the ``vesselflow`` logger hierarchy (no prints)."""

ProgressCallback = Callable[[str, int, int, float], object]
"""``progress(stage, iteration, nodes, measure)``, called after every stage and iteration
(``measure``: the contraction's convergence measure, NaN outside the contraction)."""


class Skeletonizer:
    """Turns 3-D binary vessel masks into centreline graphs by Laplacian flow.

    Implements Damseh et al., "Laplacian Flow Dynamics on Geometric Graphs for
    Anatomical Modeling of Cerebrovascular Networks", with the changes listed in
    ``docs/method.md``; ``docs/parameters.md`` says which parameter to change for what.
    Every argument is keyword-only; an invalid value raises ``ValueError`` naming it.

    Parameters
    ----------
    connectivity : {6, 18, 26}
        Edges of the initial grid graph of foreground voxels.
    reconnect_thin : bool
        Also join every node of degree <= 2 to all foreground voxels within sqrt(2)
        voxels, so that one-voxel-thin vessels are not lost.
    radius_correction : float in [0, 1]
        Subtracted from every radius, in units of the smallest spacing. Radii are
        measured by cross-section area, unbiased on drawn tubes, so the default is 0; a
        positive value removes a known margin by which the mask is wider than its vessels.
    coarse_cell : float in [0, 4]
        Start the contraction from cells of voxels this many vessel radii wide instead
        of one node per voxel (never across two touching vessels; vessels of radius under
        ``2 / coarse_cell`` voxels or over 8 voxels keep a node per voxel); afterwards
        edges longer than the larger of a cell side and 2 voxels are split. 0 turns it
        off (one node per voxel everywhere, the paper's start).
    medial_weight : {"radius", "difference"}
        Medial Laplacian weights: ``r_j / sum r_k`` (the authors' code) or
        ``|r_i - r_j| / sum |r_i - r_k|`` (the paper's eq. 3).
    skeletal_angle : float in [0, 90]
        Degrees within which all neighbour directions of a node must be collinear
        for it to count as already skeletal (adaptive anchoring).
    anchor_ends : bool
        Also count nodes of degree 1 (free vessel ends) as skeletal, so the flow does not
        pull ends inward along their vessels (not in the paper; ``False`` follows it).
    sprouts : bool
        At output, grow back side branches the contraction swallowed into their parent:
        lobes of the mask that reach further from the graph than their own radius plus 8
        voxels become branches from the nearest edge, if at least 3.5 parent radii long
        (not in the paper). ``vesselflow.distributed`` grows them in every block and
        attaches them in the merge.
    medial : bool
        After refinement, move every node onto the ridge of the distance transform:
        within its cross-section to the nearest local maximum (never across a saddle
        into a touching vessel), and every junction to where its branches' centrelines
        meet, each at most 0.6 radii away (not in the paper; ``False`` leaves nodes at
        the local centre of mass of the mask).
    prune_spurs : float in [0, 100]
        Last, remove the terminal spurs (junction-to-end branches) shorter than this many
        radii of their junction, until none is left, as :meth:`VesselGraph.prune` does
        (not in the paper), and those whose nodes all lie within this many radii of
        another branch of their junction. At the default 1 only spurs inside their
        parent's lumen go: knots and second rails beside the centreline, not vessels;
        0 keeps every spur.
        ``vesselflow.distributed`` prunes the merged graph.
    merge_junctions : float in [0, 10]
        Then join two junctions linked by a branch shorter than this many times the
        larger of their radii into one node at their mean position (not in the paper):
        at the default 0.5, a meeting of four or more vessels (a capillary bed's
        crossing) that the contraction resolved as junctions of degree 3 a fraction of a
        radius apart. Loops and components are kept. 0 keeps every junction.
    radius_smoothing : float in [0, 100]
        Last of all, each node's radius becomes the median of the radii within this many
        base cells of it along its branch (not in the paper): junctions keep theirs and do
        not enter the median; nor do vessel ends (an end sits where the mask rounds the
        vessel off and reads the cap there), which take their branch's. It takes out the
        voxel grid's noise of the per-node measurement; narrowings and bulges shorter than
        about this length go with it. 0 keeps every node's own measurement.
        ``vesselflow.distributed`` smooths the merged graph.
    eps_gamma : float >= 1
        Anchoring factor of skeletal nodes.
    alpha, beta : float >= 0
        Weights of the l2-norm and medial Laplacians (not both 0).
    gamma : float > 0
        Anchoring weight: lower contracts faster and coarser.
    cg_tol : float in (0, 0.5]
        Relative residual at which conjugate gradients stop, measured in the
        preconditioner's norm (``sqrt(r . B r)`` against its starting value), in the
        contraction iterations near the stop level; earlier ones, far from it, solve
        more loosely (``cg_tol`` times the convergence measure, at most ``5e-4``).
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
        ends. 0 turns the test off (as in the paper).
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
    >>> skeletonizer = vesselflow.Skeletonizer(gamma=0.05)
    >>> graph = skeletonizer.run(mask, spacing=(1.0, 0.5, 0.5))
    >>> graph.positions.shape[1]
    3
    >>> vesselflow.Skeletonizer(gamma=-1)
    Traceback (most recent call last):
    ...
    ValueError: invalid parameter `gamma`: must be finite and in (0, 1000], got -1
    """

    __slots__ = ("_core",)

    def __init__(
        self,
        *,
        connectivity: Literal[6, 18, 26] = 6,
        reconnect_thin: bool = True,
        radius_correction: float = 0.0,
        coarse_cell: float = 0.67,
        medial_weight: Literal["radius", "difference"] = "radius",
        skeletal_angle: float = 10.0,
        anchor_ends: bool = True,
        sprouts: bool = True,
        medial: bool = True,
        prune_spurs: float = 1.0,
        merge_junctions: float = 0.5,
        radius_smoothing: float = 4.0,
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
        """Every parameter and its value, in documentation order.

        Returns
        -------
        dict
            ``{name: value}`` for every parameter of the constructor, defaults included
            (``max_memory``: ``"auto"``, or the limit in bytes, 0 for none).

        Examples
        --------
        >>> import vesselflow
        >>> vesselflow.Skeletonizer(gamma=0.1).params["gamma"]
        0.1
        """
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
            rule that :func:`load_volume` and the command line apply too: bool, and
            bytes that are all 0 or 1 (both read without a copy), integers with zero
            and at most one other value, or floats
            that are all 0 or 1 are binary (non-zero = vessel); anything else (a label
            image, a probability map, NaN) is a ``ValueError`` naming the values found,
            unless ``threshold`` or ``label`` says how to binarise it.
        spacing : sequence of 3 floats, or a float
            Voxel size along axes 0, 1, 2 in physical units (one number: the same on
            every axis); positions and radii of the result are in the same units.
        progress : callable or bool, optional
            ``True`` shows a tqdm bar on stderr: the nodes merged so far out of the
            initial graph's (a count that grows at a nearly steady pace, so the bar's
            time estimate holds), with the stage, iteration, nodes left and the
            convergence measure. A callable is called as
            ``progress(stage, iteration, nodes, measure)`` after every stage and
            iteration: ``stage`` is ``"edt"``, ``"grid"``, ``"contract"``,
            ``"refine"`` or ``"output"``, ``nodes`` the nodes of the graph now, and
            ``measure`` the contraction's convergence measure (short-cycle area over
            the stop level; the contraction stops when it reaches 1), NaN in the
            other stages. An exception it raises stops the run and propagates.
        threshold : float, optional
            Vessel where ``mask > threshold`` (e.g. a probability map).
        label : float, optional
            Vessel where ``mask == label`` (one label of a label image); not with
            ``threshold``.
        prune_min_length_over_radius : float, optional
            If given, finish with :meth:`VesselGraph.prune` at this ratio: terminal
            spurs shorter than this many radii of the vessel they join are removed.
            Default ``None``: no pruning.

        Returns
        -------
        VesselGraph
            Node positions and radii in the units of ``spacing``, the edges, the run
            record ``info`` (iterations, ``converged``, ``stalled``, nodes and
            short-cycle area per iteration, seconds per stage) and ``params``.

        Raises
        ------
        ValueError
            A mask that is not 3-D or not binary by the input rule, a bad ``spacing``,
            ``threshold`` with ``label``.
        MemoryError
            The run's estimated peak memory exceeds ``max_memory``.
        KeyboardInterrupt
            Ctrl-C during the run.

        Notes
        -----
        An empty mask gives an empty graph and a ``UserWarning``; a mask that is
        vessel everywhere is a solid block (background lies outside the array). The
        spacing must lie in [1e-12, 1e12] on every axis (``ValueError`` otherwise).

        The GIL is released while the core runs; Ctrl-C raises ``KeyboardInterrupt``
        within a fraction of a second, at any stage. An internal error (a bug) is a
        ``RuntimeError`` starting "internal error, please report".
        A run that stops at ``max_iterations`` before converging (or stalling) logs a
        warning on the ``vesselflow`` logger.

        Examples
        --------
        >>> import numpy as np, vesselflow
        >>> probability = np.zeros((40, 21, 21))
        >>> probability[:, 6:15, 6:15] = 0.9
        >>> graph = vesselflow.Skeletonizer().run(probability, spacing=0.5, threshold=0.5)
        >>> graph.info["converged"], graph.n_nodes == graph.n_edges + 1
        (True, True)
        """
        with _progress_callback(progress) as callback:
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
            "skeletonized %d voxels into %d nodes and %d edges in %d iterations (%s)",
            info["foreground_voxels"],
            graph.n_nodes,
            graph.n_edges,
            info["iterations"],
            _ending(info),
        )
        return graph


def _ending(info: dict[str, Any]) -> str:
    """How the contraction ended, in the command line's words."""
    if info["foreground_voxels"] == 0:
        return "empty mask"
    if info["converged"]:
        return "converged"
    return "stalled near convergence" if info["stalled"] else "stopped at max_iterations"


@contextmanager
def _progress_callback(
    progress: ProgressCallback | bool | None,
) -> Iterator[ProgressCallback | None]:
    """The core's callback for ``progress``: ``True`` drives a tqdm bar, closed on exit.

    The bar counts the nodes merged since the grid graph, out of the grid graph's nodes.
    A contraction iteration takes time in proportion to the nodes it starts with and
    merges a similar fraction of them, so merged nodes accrue at a nearly steady rate
    and tqdm's remaining-time estimate holds: on five real volumes, 0.5 to 1.6 times
    the true remaining time from 10 % to 90 % of a run, where a bar of iterations out
    of ``max_iterations`` said 11 to 160 times too much, as most runs stop far earlier.
    """
    if progress is not True:
        yield progress or None
        return
    from tqdm.auto import tqdm

    layout = "{desc}: {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}{postfix}]"
    with tqdm(total=1, desc="vesselflow", bar_format=layout) as bar:
        grid_nodes = 0

        def update(stage: str, iteration: int, nodes: int, measure: float) -> None:
            nonlocal grid_nodes
            if stage == "grid":
                grid_nodes = nodes
                bar.total = max(nodes, 1)
            merged = max(grid_nodes, 1) if stage == "output" else max(grid_nodes - nodes, 0)
            bar.set_description_str(f"vesselflow {stage}", refresh=False)
            postfix: dict[str, object] = {"iteration": iteration, "nodes": nodes}
            if math.isfinite(measure):
                postfix["measure"] = f"{measure:.3g}"
            bar.set_postfix(postfix, refresh=False)
            bar.update(merged - bar.n)
            bar.refresh()

        yield update


def skeletonize(
    mask: np.ndarray,
    spacing: Sequence[float] | float = (1.0, 1.0, 1.0),
    *,
    progress: ProgressCallback | bool | None = None,
    threshold: float | None = None,
    label: float | None = None,
    prune_min_length_over_radius: float | None = None,
    coordinates: Literal["array", "xyz", "world"] = "array",
    affine: ArrayLike | None = None,
    **params: Any,
) -> VesselGraph:
    """Skeletonize ``mask`` in one call: ``Skeletonizer(**params).run(mask, spacing)``.

    See :class:`Skeletonizer` for the parameters and :meth:`Skeletonizer.run` for
    ``mask``, ``spacing``, ``progress``, ``threshold``, ``label`` and
    ``prune_min_length_over_radius``. ``coordinates`` picks the frame of the
    positions (:meth:`VesselGraph.to_coordinates`): ``"array"`` (physical units along
    array axes 0, 1, 2, the default), ``"xyz"`` (x = the last axis, the order of SWC,
    VTK, Neuroglancer and ImageJ) or ``"world"`` (through ``affine``, the image's 4 x 4
    voxel-to-world matrix, as ``load_volume(path, return_affine=True)`` returns it).
    Radii stay in the units of ``spacing``.

    Returns
    -------
    VesselGraph
        The centreline graph, in the units of ``spacing``; ``graph.info`` records the run.

    Examples
    --------
    >>> import numpy as np, vesselflow
    >>> mask = np.zeros((40, 21, 21), bool)
    >>> mask[:, 6:15, 6:15] = True
    >>> graph = vesselflow.skeletonize(mask, spacing=(1.0, 0.5, 0.5), gamma=0.05)
    >>> int(graph.degrees().max())  # a straight tube gives a path
    2
    >>> length = graph.branches()["branch-distance"].sum()  # in the units of spacing
    >>> round(float(length), 3)  # through two faces of the array, and so is its centreline
    39.0
    >>> xyz = vesselflow.skeletonize(mask, spacing=(1.0, 0.5, 0.5), coordinates="xyz")
    >>> xyz.spacing.tolist()  # x, y, z: the columns of xyz.positions
    [0.5, 0.5, 1.0]
    """
    graph = Skeletonizer(**params).run(
        mask,
        spacing,
        progress,
        threshold=threshold,
        label=label,
        prune_min_length_over_radius=prune_min_length_over_radius,
    )
    return graph.to_coordinates(coordinates, affine)
