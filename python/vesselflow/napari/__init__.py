"""The napari plugin (``napari`` extra): open vesselflow graph files as layers, and run
vesselflow on an Image or Labels layer from a dock widget.

The manifest is ``napari.yaml`` beside this file, found through the ``napari.manifest``
entry point. A graph becomes two layers: a Vectors layer with one segment per edge and a
Points layer with one point per node, both coloured by radius (``viridis``) and carrying
it as the feature ``radius``; the points' size is the vessel's diameter.
"""

from vesselflow.napari._layers import graph_layers

__all__ = ["graph_layers"]
