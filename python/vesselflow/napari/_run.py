"""The widget's work, without Qt: run vesselflow on a layer's data, report progress,
stop when asked."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from vesselflow.napari._layers import LayerData, graph_layers
from vesselflow.skeletonizer import Skeletonizer


class Cancelled(Exception):
    """The user cancelled the run."""


def skeletonize_layer(
    data: Any,
    scale: Sequence[float],
    translate: Sequence[float] = (0.0, 0.0, 0.0),
    *,
    name: str = "vessels",
    params: Mapping[str, Any] | None = None,
    threshold: float | None = None,
    label: float | None = None,
    prune_min_length_over_radius: float | None = None,
    progress: Callable[[str, int, int], object] | None = None,
    cancelled: Callable[[], bool] = lambda: False,
) -> list[LayerData]:
    """Skeletonize a napari Image or Labels layer's data and return the graph's layers.

    Parameters
    ----------
    data : array-like
        The layer's data (NumPy, or a lazy array that ``numpy.asarray`` reads); 3-D.
    scale, translate : sequence of 3 floats
        The layer's ``scale`` (the voxel spacing) and ``translate``.
    name : str
        Base name of the new layers.
    params : mapping, optional
        :class:`vesselflow.Skeletonizer` parameters.
    threshold, label, prune_min_length_over_radius : float, optional
        How to binarise a non-binary layer, and whether to prune spurs (see
        :meth:`vesselflow.Skeletonizer.run`).
    progress : callable, optional
        Called as ``progress(stage, iteration, max_iterations)`` after every stage and
        iteration, from the thread that runs.
    cancelled : callable
        Asked after every stage and iteration; when it returns True the run stops and
        :class:`Cancelled` is raised.

    Returns
    -------
    list of (data, kwargs, layer type)
        The graph's layers (:func:`vesselflow.napari.graph_layers`), placed on the layer.

    Examples
    --------
    >>> import numpy as np
    >>> from vesselflow.napari._run import skeletonize_layer
    >>> mask = np.zeros((30, 15, 15), np.uint8)
    >>> mask[:, 5:10, 5:10] = 1
    >>> [kind for _, _, kind in skeletonize_layer(mask, scale=(1, 1, 1))]
    ['vectors', 'points']
    """
    volume = np.asarray(data)
    if volume.ndim != 3:
        raise ValueError(f"the layer must be 3-D, got shape {volume.shape}")
    spacing = [float(s) for s in scale][-3:]
    skeletonizer = Skeletonizer(**dict(params or {}))
    max_iterations = int(skeletonizer.params["max_iterations"])

    def callback(stage: str, iteration: int, nodes: int, measure: float) -> None:
        if cancelled():
            raise Cancelled("cancelled")
        if progress is not None:
            progress(stage, iteration, max_iterations)

    graph = skeletonizer.run(
        volume,
        spacing,
        callback,
        threshold=threshold,
        label=label,
        prune_min_length_over_radius=prune_min_length_over_radius,
    )
    return graph_layers(graph, name=name, translate=[float(t) for t in translate][-3:])
