"""vesselflow: vessel centreline graphs from 3-D binary masks by Laplacian flow.

>>> import vesselflow
>>> graph = vesselflow.skeletonize(mask, spacing=(0.5, 0.3, 0.3))  # doctest: +SKIP
>>> graph.save("vessels.graphml")  # doctest: +SKIP

The method is Damseh et al., "Laplacian Flow Dynamics on Geometric Graphs for
Anatomical Modeling of Cerebrovascular Networks"; the work is done by a Rust core
(``vesselflow._core``) with the GIL released. The documentation (``docs/`` in the source
repository) has a tutorial, the method with its departures from the paper and a guide
to the parameters.

A file that cannot be used as a mask raises :class:`VolumeError`, a ``ValueError``.
"""

from vesselflow._core import __version__
from vesselflow.graph import VesselGraph
from vesselflow.io import load_graph
from vesselflow.skeletonizer import Skeletonizer, skeletonize
from vesselflow.volumes import VolumeError, load_volume

__all__ = [
    "Skeletonizer",
    "VesselGraph",
    "VolumeError",
    "__version__",
    "load_graph",
    "load_volume",
    "skeletonize",
]
