"""Pictures of a centreline graph: the mask's maximum-intensity projection with the graph
on top, coloured by radius (matplotlib, the ``viz`` extra)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from vesselflow.graph import VesselGraph
from vesselflow.io import _atomic, import_extra

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure


def plot(
    graph: VesselGraph,
    mask: ArrayLike | None = None,
    path: str | os.PathLike[str] | None = None,
    axis: int = 0,
    ax: Axes | None = None,
) -> Figure:
    """Draw ``graph`` projected along array axis ``axis`` over the mask's maximum-intensity
    projection.

    Parameters
    ----------
    graph : VesselGraph
        The graph; its ``spacing`` scales the mask's voxels.
    mask : array-like, optional
        The 3-D volume the graph came from (any numeric dtype; its maximum shows as mid
        grey, its minimum black). Without it only the graph is drawn.
    path : str or os.PathLike, optional
        Save the figure there as PNG (written to a temporary file in the same folder,
        then renamed: a failure leaves no partial file).
    axis : {0, 1, 2}
        The array axis projected away. The image's rows are the lower remaining axis,
        its columns the higher one, both in physical units (voxel ``(i, j, k)`` is at
        ``(i*s0, j*s1, k*s2)``), so anisotropic voxels show at their true aspect.
    ax : matplotlib.axes.Axes, optional
        Draw into these axes; by default a new 6.4 x 4.8 inch, 100 dpi figure (a
        640 x 480 pixel PNG), made without pyplot so no window opens.

    Returns
    -------
    matplotlib.figure.Figure
        The figure holding the plot. Each edge is a segment coloured by the mean radius
        of its two nodes (physical units, ``viridis``), with a colour bar.
    """
    import_extra("matplotlib", "viz")
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure

    if axis not in (0, 1, 2):
        raise ValueError(f"`axis` must be 0, 1 or 2, got {axis!r}")
    rows, cols = (a for a in range(3) if a != axis)

    if ax is None:
        ax = Figure(figsize=(6.4, 4.8), dpi=100).add_subplot()
    figure = ax.figure.figure  # the top-level figure, also when ``ax`` is in a subfigure
    if mask is not None:
        volume = np.asarray(mask)
        if volume.ndim != 3:
            raise ValueError(f"`mask` must be 3-D, got shape {volume.shape}")
        projection = volume.max(axis=axis).astype(np.float64)
        s_rows, s_cols = graph.spacing[rows], graph.spacing[cols]
        n_rows, n_cols = projection.shape
        # Pixel centres at index * spacing, as for the graph's positions.
        extent = (-0.5 * s_cols, (n_cols - 0.5) * s_cols, (n_rows - 0.5) * s_rows, -0.5 * s_rows)
        low, high = projection.min(), projection.max()
        # The brightest voxel at mid grey, so that edges of every colour stand out.
        ax.imshow(
            projection,
            cmap="gray",
            vmin=low,
            vmax=2 * high - low,
            extent=extent,
            interpolation="nearest",
        )
    else:
        ax.invert_yaxis()  # rows grow downwards, as in the image
    segments = graph.positions[:, [cols, rows]][graph.edges]
    lines = LineCollection(list(segments), cmap="viridis", linewidths=1.5)
    lines.set_array(graph.radii[graph.edges].mean(axis=1))
    ax.add_collection(lines, autolim=mask is None)
    if mask is None:
        ax.autoscale_view()
    ax.set_aspect("equal")
    ax.set_xlabel(f"axis {cols} (physical units)")
    ax.set_ylabel(f"axis {rows} (physical units)")
    figure.colorbar(lines, ax=ax, label="radius (physical units)")
    if path is not None:
        with _atomic(Path(path)) as temp:
            figure.savefig(temp, format="png")
    return figure
