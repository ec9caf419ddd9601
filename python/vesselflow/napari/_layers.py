"""A graph as napari layer data: no napari import, so it is tested without Qt."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from vesselflow.graph import VesselGraph

LayerData = tuple[Any, dict[str, Any], str]
"""napari's ``LayerDataTuple``: ``(data, keyword arguments, layer type)``."""


def graph_layers(
    graph: VesselGraph, name: str = "vessels", translate: Sequence[float] = (0.0, 0.0, 0.0)
) -> list[LayerData]:
    """The layers that show ``graph`` in napari, over an image whose scale is the
    graph's spacing.

    Parameters
    ----------
    graph : VesselGraph
        Positions in physical units, array axis order: napari's world coordinates of an
        image layer whose ``scale`` is the voxel spacing.
    name : str
        Layer names are ``"<name> edges"`` and ``"<name> nodes"``.
    translate : sequence of 3 floats
        The image layer's ``translate``, so that the graph lies on it.

    Returns
    -------
    list of (data, kwargs, layer type)
        A ``"vectors"`` layer, one ``(start, direction)`` row per edge, with the feature
        ``radius`` (mean of its two nodes) as ``edge_color`` through ``viridis``; and a
        ``"points"`` layer, one point per node, with the features ``radius`` and
        ``degree``, face colour by radius, and size the node's diameter (world units).
        Vectors rather than one Shapes path per edge: napari draws a Vectors layer as one
        mesh, fast with the tens of thousands of edges of a real volume, where a Shapes
        layer of that many shapes is slow to draw and select.

    Examples
    --------
    >>> from vesselflow import VesselGraph
    >>> from vesselflow.napari import graph_layers
    >>> graph = VesselGraph([[0, 0, 0], [0, 0, 4.0]], [1.0, 2.0], [[0, 1]])
    >>> [kind for _, _, kind in graph_layers(graph)]
    ['vectors', 'points']
    """
    start = graph.positions[graph.edges[:, 0]]
    direction = graph.positions[graph.edges[:, 1]] - start
    edge_radius = graph.radii[graph.edges].mean(axis=1) if graph.n_edges else np.zeros(0)
    translate = tuple(float(t) for t in translate)
    line_width = max(
        float(graph.spacing.min()), 0.5 * float(np.median(graph.radii)) if graph.n_nodes else 0.0
    )
    edges: LayerData = (
        np.stack([start, direction], axis=1),
        {
            "name": f"{name} edges",
            "features": {"radius": edge_radius},
            "edge_color": "radius",
            "edge_colormap": "viridis",
            "edge_width": line_width,
            "translate": translate,
        },
        "vectors",
    )
    nodes: LayerData = (
        graph.positions.copy(),
        {
            "name": f"{name} nodes",
            "features": {"radius": graph.radii.copy(), "degree": graph.degrees()},
            "face_color": "radius",
            "face_colormap": "viridis",
            "size": 2.0 * graph.radii,
            "border_width": 0.0,
            "opacity": 0.5,
            "translate": translate,
            "visible": False,
        },
        "points",
    )
    return [edges, nodes]
