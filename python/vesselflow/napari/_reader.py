"""The napari reader of vesselflow graph files (through :func:`vesselflow.load_graph`)."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Union

from vesselflow.io import load_graph
from vesselflow.napari._layers import LayerData, graph_layers

PathOrPaths = Union[str, os.PathLike[str], list[str]]


def get_reader(path: PathOrPaths) -> Callable[[PathOrPaths], list[LayerData]] | None:
    """The reader for ``path`` if it is a vesselflow graph file, else ``None`` (so that
    napari tries its other readers: an ``.npz`` or ``.json`` may hold anything).

    The file is read here, once; the function returned hands its layers to napari
    (see :func:`vesselflow.napari.graph_layers`).
    """
    paths = [path] if isinstance(path, (str, os.PathLike)) else list(path)
    layers: list[LayerData] = []
    for p in paths:
        try:
            graph = load_graph(p)
        except (ValueError, OSError, KeyError):
            return None
        layers.extend(graph_layers(graph, name=Path(p).stem))

    def read(_: PathOrPaths) -> list[LayerData]:
        return layers

    return read
