"""Synthetic vessel volumes with ground truth: masks and the centreline graphs they came from.

Every generator returns ``(mask, truth)``: ``mask`` a C-order boolean array of the requested
shape, ``truth`` a :class:`~vesselflow.VesselGraph` whose positions and radii are in physical
units (voxel ``(i, j, k)`` has its centre at ``(i * s0, j * s1, k * s2)``), in the same frame as
the graphs :func:`vesselflow.skeletonize` returns for that mask and spacing.

- :func:`vascular_tree`: a VascuSynth-like arterial tree grown by constrained constructive
  optimisation, the kind of volume of the paper's synthetic set (its section IV-A, Table I);
- :func:`add_bubble_noise`: the paper authors' boundary noise for the ``D0``/``D1``/``D2`` sets;
- :func:`capillary_network`: a loopy mesh of thin tubes with a known cycle rank, like the
  two-photon microscopy stacks of section IV-E;
- :func:`cylinder`, :func:`torus`, :func:`y_bifurcation`, :func:`helix`: analytic shapes;
- :func:`vascular_bed`: the benchmark beds of ``benches/performance.py`` (mask only).
- :func:`vascular_forest`: a second, independently written family for honest benchmarks:
  trees grown from the faces inward by space colonisation, with anastomoses, touching and
  crossing vessels and a rippled radius, rasterised at voxel centres (see its docstring for
  how the truth radius relates to the mask under each convention).

All tubes are drawn by one rasteriser: a union of *round cones* (capsules whose radius may
vary linearly from one end to the other: the union of the balls centred on a segment with
linearly interpolated radii), sampled ``supersample**3`` times per voxel; a voxel is foreground
when at least half of its sub-samples are inside. Only voxels near a surface are supersampled
(the inside function is 1-Lipschitz, so a voxel whose centre is deeper than half its diagonal
is wholly inside or outside), so the cost is about that of sampling voxel centres.
Two conventions come out of it: *partial volume* (``supersample >= 2``, the default of every
generator but one: a voxel is foreground when at least half of it is inside) and *voxel centre*
(``supersample=1``: a voxel is foreground when its centre is inside; :func:`vascular_forest`,
and any generator called with ``supersample=1``). Both put a flat wall at the truth radius;
on the convex wall of a thin tube the partial-volume mask is slightly thinner.
Everything is deterministic given ``seed`` (a :class:`numpy.random.Generator` per call).
"""

from vesselflow.synth.analytic import cylinder, helix, torus, y_bifurcation
from vesselflow.synth.bed import vascular_bed
from vesselflow.synth.capillary import capillary_network
from vesselflow.synth.forest import vascular_forest
from vesselflow.synth.noise import BUBBLE_LEVELS, add_bubble_noise
from vesselflow.synth.tree import vascular_tree

__all__ = [
    "BUBBLE_LEVELS",
    "add_bubble_noise",
    "capillary_network",
    "cylinder",
    "helix",
    "torus",
    "vascular_bed",
    "vascular_forest",
    "vascular_tree",
    "y_bifurcation",
]
