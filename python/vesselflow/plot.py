"""Pictures of a centreline graph: the mask's maximum-intensity projection with the graph
on top, coloured by radius (matplotlib), and a 3-D view of the vessels as tubes coloured
by radius (pyvista, rendered off-screen); both are the ``viz`` extra.

The projection follows the rules of the command line's ``--plot``: a few pixels per
voxel (within bounds), so the picture grows with the volume, and lines and text grow
with the picture."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vesselflow._util import atomic_file as _atomic
from vesselflow._util import import_extra
from vesselflow.graph import VesselGraph

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

PX_PER_VOXEL = 4.0
"""Pixels per voxel (of the finer spacing) along the projection's longer side..."""
MIN_LONG_SIDE_PX, MAX_LONG_SIDE_PX = 600.0, 2400.0
"""...bounded to these (the command line's ``--plot`` uses the same numbers)."""
DPI = 100.0
RADIUS_LABEL = "radius (physical units)"


def long_side_px(extent: ArrayLike, spacing: ArrayLike) -> float:
    """Pixels on the longer side of a picture of a region ``extent`` physical units wide
    and high, sampled at ``spacing``: :data:`PX_PER_VOXEL` per voxel of the finer
    spacing, within :data:`MIN_LONG_SIDE_PX` and :data:`MAX_LONG_SIDE_PX`."""
    voxels = float(np.max(extent)) / float(np.min(spacing))
    return float(np.clip(PX_PER_VOXEL * voxels, MIN_LONG_SIDE_PX, MAX_LONG_SIDE_PX))


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
        Draw into these axes. By default a new 100 dpi figure (made without pyplot, so no
        window opens) whose size follows the projected region: its longer side gets 4
        pixels per voxel, at least 600 and at most 2400 pixels, and the colour bar and
        labels are added beside it.

    Returns
    -------
    matplotlib.figure.Figure
        The figure holding the plot. Each edge is a segment coloured by the mean radius
        of its two nodes (physical units, ``viridis``), 1/300 of the picture's longer side
        wide, with a colour bar labelled "radius (physical units)" with ticks; the text
        grows with the picture too.

    Examples
    --------
    >>> import numpy as np, vesselflow
    >>> mask = np.zeros((20, 40, 30), bool)
    >>> mask[8:13, 5:35, 12:17] = True
    >>> graph = vesselflow.skeletonize(mask)
    >>> figure = graph.plot(mask=mask, path="tube.png")  # 600 px high: 40 voxels is small
    """
    import_extra("matplotlib", "viz")
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure

    if axis not in (0, 1, 2):
        raise ValueError(f"`axis` must be 0, 1 or 2, got {axis!r}")
    rows, cols = (a for a in range(3) if a != axis)

    volume = None
    if mask is not None:
        volume = np.asarray(mask)
        if volume.ndim != 3:
            raise ValueError(f"`mask` must be 3-D, got shape {volume.shape}")
    plane = graph.spacing[[rows, cols]]
    if volume is not None:
        extent_units = np.array([volume.shape[rows], volume.shape[cols]]) * plane
    elif graph.n_nodes:
        span = graph.positions[:, [rows, cols]].max(axis=0) - graph.positions[:, [rows, cols]].min(
            axis=0
        )
        extent_units = span + plane
    else:
        extent_units = plane
    long_px = long_side_px(extent_units, plane)
    font_pt = max(10.0, 10.0 * long_px / MIN_LONG_SIDE_PX)
    if ax is None:
        height_px, width_px = extent_units / extent_units.max() * long_px
        # Room for the axis labels (left, below) and the colour bar, its ticks and label.
        margin_px = 9.0 * font_pt * DPI / 72.0
        figure_px = (width_px + 1.6 * margin_px, height_px + 0.8 * margin_px)
        figure_in = np.maximum(figure_px, 3.0 * margin_px) / DPI
        ax = Figure(figsize=tuple(figure_in), dpi=DPI, layout="constrained").add_subplot()
    figure = ax.figure.figure  # the top-level figure, also when ``ax`` is in a subfigure
    if volume is not None:
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
    line_pt = max(2.0, long_px / 300.0) * 72.0 / DPI
    lines = LineCollection(list(segments), cmap="viridis", linewidths=line_pt, capstyle="round")
    lines.set_array(graph.radii[graph.edges].mean(axis=1))
    ax.add_collection(lines, autolim=mask is None)
    if mask is None:
        ax.autoscale_view()
    ax.set_aspect("equal")
    ax.set_xlabel(f"axis {cols} (physical units)", fontsize=font_pt)
    ax.set_ylabel(f"axis {rows} (physical units)", fontsize=font_pt)
    ax.tick_params(labelsize=font_pt)
    bar = figure.colorbar(lines, ax=ax)
    bar.set_label(RADIUS_LABEL, fontsize=font_pt)
    bar.ax.tick_params(labelsize=font_pt)
    if path is not None:
        with _atomic(Path(path)) as temp:
            figure.savefig(temp, format="png")
    return figure


def tubes(graph: VesselGraph, n_sides: int = 16) -> Any:
    """The graph's edges as tubes whose radius is the vessels' (pyvista, ``viz`` extra).

    Parameters
    ----------
    graph : VesselGraph
        The graph; positions are used as given (column 0 is VTK's x).
    n_sides : int
        Sides of each tube's cross-section.

    Returns
    -------
    pyvista.PolyData
        A surface with a ``radius`` point array (physical units), ready for
        ``pyvista.Plotter.add_mesh(..., scalars="radius")``. A node of radius 0 is drawn
        with a tenth of the smallest spacing, so that every edge shows.

    Examples
    --------
    >>> from vesselflow import VesselGraph
    >>> from vesselflow.plot import tubes
    >>> mesh = tubes(VesselGraph([[0, 0, 0], [0, 0, 9.0]], [1.0, 2.0], [[0, 1]]))
    >>> mesh.n_points > 0
    True
    """
    pv = import_extra("pyvista", "viz")
    lines = np.column_stack([np.full(graph.n_edges, 2), graph.edges]).ravel()
    skeleton = pv.PolyData(np.ascontiguousarray(graph.positions), lines=lines)
    skeleton.point_data["radius"] = np.maximum(graph.radii, 0.1 * float(graph.spacing.min()))
    return skeleton.tube(scalars="radius", absolute=True, n_sides=n_sides, capping=True)


def plot3d(
    graph: VesselGraph,
    path: str | os.PathLike[str] | None = None,
    *,
    view: str = "iso",
    window_size: tuple[int, int] = (1024, 768),
) -> NDArray[np.uint8]:
    """Render the vessels as tubes coloured by radius, off-screen (pyvista, ``viz`` extra).

    Parameters
    ----------
    graph : VesselGraph
        The graph; see :func:`tubes`.
    path : str or os.PathLike, optional
        Save the picture there as PNG (atomically: a temporary file, then renamed).
    view : {"iso", "xy", "xz", "yz"}
        The camera: isometric, or looking along the third, second or first coordinate
        (parallel projection). Coordinates are the graph's positions as given.
    window_size : (int, int)
        Width and height of the picture in pixels.

    Returns
    -------
    numpy.ndarray
        The picture, (height, width, 3) uint8: white background, tubes in the
        ``viridis`` colour of their radius, lit, and a colour bar titled
        "radius (physical units)".

    Nothing opens a window: the rendering is off-screen (through the display if there
    is one, else VTK's EGL or OSMesa fallback of its Linux wheels).

    Examples
    --------
    >>> import numpy as np, vesselflow
    >>> mask = np.zeros((20, 40, 30), bool)
    >>> mask[8:13, 5:35, 12:17] = True
    >>> picture = vesselflow.skeletonize(mask).plot3d("tube-3d.png")
    >>> picture.shape
    (768, 1024, 3)
    """
    pv = import_extra("pyvista", "viz")
    if view not in ("iso", "xy", "xz", "yz"):
        raise ValueError(f"`view` must be 'iso', 'xy', 'xz' or 'yz', got {view!r}")
    width, height = (int(v) for v in window_size)
    if width < 1 or height < 1:
        raise ValueError(f"`window_size` must be two positive integers, got {window_size!r}")
    plotter = pv.Plotter(off_screen=True, window_size=(width, height))
    try:
        plotter.set_background("white")
        if graph.n_edges:
            plotter.add_mesh(
                tubes(graph),
                scalars="radius",
                cmap="viridis",
                smooth_shading=True,
                scalar_bar_args={
                    "title": RADIUS_LABEL,
                    "color": "black",
                    "vertical": True,
                    "position_x": 0.8,
                    "title_font_size": 14,
                    "label_font_size": 14,
                },
            )
        if view == "iso":
            plotter.view_isometric()
        else:
            plotter.enable_parallel_projection()
            getattr(plotter, f"view_{view}")()
        picture = np.asarray(plotter.screenshot(return_img=True), dtype=np.uint8)[..., :3]
    finally:
        plotter.close()
    if path is not None:
        from matplotlib.image import imsave

        with _atomic(Path(path)) as temp:
            imsave(temp, picture, format="png")
    return picture
