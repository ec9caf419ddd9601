"""Other skeletonizers behind one interface, for comparisons like the paper's section IV.

>>> from vesselflow import compare
>>> compare.available()  # doctest: +SKIP
{'vesselflow': None, 'voxel': None, 'teasar': None, 'mesh': None, 'pointcloud': "needs ..."}
>>> graph = compare.run("teasar", mask, spacing=(0.5, 0.3, 0.3))  # doctest: +SKIP
>>> graph.info["seconds"]  # doctest: +SKIP

Every method takes a 3-D binary mask (non-zero = vessel) and its voxel spacing and returns a
:class:`~vesselflow.VesselGraph` with positions in physical units, in the mask's array axis
order (the centre of voxel ``(i, j, k)`` is at ``(i*s0, j*s1, k*s2)``).

Methods (:data:`METHODS`), named after the paper's Table I where they stand for its peers:

``"vesselflow"``
    Our method, :func:`vesselflow.skeletonize`; options are its parameters.
``"voxel"`` (the paper's "Voxel-based", 3-D thinning)
    ``skimage.morphology.skeletonize`` (Lee et al. 1994 thinning, which works in voxel
    units whatever the spacing), then the pixel graph of ``skan.Skeleton`` (Nunez-Iglesias
    et al. 2018): one node per skeleton voxel, edges between 26-neighbours as skan keeps
    them. The paper used ITK's thinning; this is the same algorithm family.
``"teasar"``
    ``kimimaro.skeletonize`` (TEASAR, Sato et al. 2000, as changed by kimimaro): the mask is
    label 1, ``anisotropy=spacing``, ``fix_branching=True``, ``fill_holes=False``,
    ``dust_threshold=0``, ``parallel=1``, the soma heuristics off, and
    ``teasar_params`` from :data:`TEASAR_PARAMS` (the kimimaro README's ``scale`` and PDRF
    values; ``const``, the invalidation radius added to ``scale * DBF``, is in voxels of the
    largest spacing here, as vessels are a few voxels wide, not hundreds of nanometres).
    Options override these keys. kimimaro's vertices are already physical and in array
    axis order; the skeletons of all labels are merged into one graph.
``"mesh"`` (the paper's "Mesh-based", its reference [12]: mean curvature flow skeletons,
    Tagliasacchi et al. 2012, as implemented in CGAL)
    The surface is ``skimage.measure.marching_cubes`` at level 0.5 of the mask padded by one
    background voxel (so it is closed), in physical units; CGAL's
    ``Mean_curvature_flow_skeletonization``, through
    ``compas_cgal.skeletonization.mesh_skeleton`` (which exposes none of its parameters),
    turns it into polylines whose shared end points become the nodes.
``"pointcloud"`` (the paper's "PC-based", its reference [13]: Laplacian-based contraction of
    a point cloud, Cao et al. 2010)
    ``pc_skeletor.LBC`` on the marching-cubes vertices (as the paper fed mesh vertices to
    it); the nodes and edges of its ``skeleton_graph`` (a minimum spanning tree over
    farthest-point samples of the contracted cloud). pc-skeletor 1.0 does not install with
    pip on Python 3.11 with NumPy 2 (its pinned ``mistree==1.2.0`` is a source package that
    needs NumPy at build time and a Fortran compiler), so it is not in the ``bench`` extra
    and :func:`available` says why when it is missing.

Not wrapped: SOAX (Xu et al. 2015) and VTrails (Moriconi et al. 2018), the paper's other
peers, are C++/MATLAB applications with no package on PyPI.

Radii. Every comparator gets its radii from the same function, :func:`edt_radii`: the
Euclidean distance transform of the mask (``scipy.ndimage.distance_transform_edt(mask,
sampling=spacing)``, the distance from a vessel voxel centre to the nearest background voxel
centre, in physical units) read at the voxel nearest to each node, as the paper does for
all its peers ("the intensity of the Euclidean distance transform at the coordinate of that
node"). A node off the mask therefore gets radius 0. ``"vesselflow"`` keeps its own radii
(see ``docs/method.md``), so radius errors of our method are those of the method, not of
this helper.

Timing. ``graph.info["seconds"]`` is the wall time from the mask to the graph's nodes and
edges (surface extraction included for ``"mesh"`` and ``"pointcloud"``), without the shared
radius step. The first ``"voxel"`` run in a process also pays for skan's numba compilation
(about 5 to 8 s here). ``info["method"]`` names the method, ``info["radii"]`` says where the
radii come from (``"edt"`` or ``"vesselflow"``); ``graph.params`` holds the options used.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vesselflow.graph import VesselGraph
from vesselflow.skeletonizer import skeletonize

METHODS: tuple[str, ...] = ("vesselflow", "voxel", "teasar", "mesh", "pointcloud")
"""Names accepted by :func:`run`, ours first."""

TEASAR_PARAMS: Mapping[str, float] = {
    "scale": 1.5,
    "const": 4.0,
    "pdrf_scale": 100000.0,
    "pdrf_exponent": 4,
}
"""Default ``teasar_params`` of ``"teasar"``; ``const`` in voxels of the largest spacing."""

_BENCH_HINT = "pip install 'vesselflow[bench]'"
_PC_SKELETOR_HINT = (
    "pip install pc-skeletor (not in the bench extra: its pinned dependency mistree==1.2.0 "
    "builds from source with numpy.distutils and a Fortran compiler, which fails with pip on "
    "Python 3.11 with NumPy 2 and without gfortran)"
)

#: Per method: (module to import, package that provides it, how to install it).
_REQUIREMENTS: dict[str, tuple[tuple[str, str, str], ...]] = {
    "vesselflow": (),
    "voxel": (("skimage", "scikit-image", _BENCH_HINT), ("skan", "skan", _BENCH_HINT)),
    "teasar": (("kimimaro", "kimimaro", _BENCH_HINT),),
    "mesh": (
        ("skimage", "scikit-image", _BENCH_HINT),
        ("compas_cgal.skeletonization", "compas_cgal", _BENCH_HINT),
    ),
    "pointcloud": (
        ("skimage", "scikit-image", _BENCH_HINT),
        ("open3d", "open3d", _PC_SKELETOR_HINT),
        ("pc_skeletor", "pc-skeletor", _PC_SKELETOR_HINT),
    ),
}


def available() -> dict[str, str | None]:
    """Which methods can run here.

    Returns
    -------
    dict
        ``{method: None}`` for every method whose packages import, else ``{method: reason}``
        naming the missing package, the import error and how to install it; in
        :data:`METHODS` order.

    Examples
    --------
    >>> from vesselflow import compare
    >>> compare.available()["vesselflow"] is None  # ours needs nothing more
    True
    """
    return {method: _missing(method) for method in METHODS}


def run(
    method: str,
    mask: ArrayLike,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
    **options: Any,
) -> VesselGraph:
    """Skeletonize ``mask`` with one of :data:`METHODS`.

    Parameters
    ----------
    method : str
        One of :data:`METHODS` (see the module docstring for what each runs).
    mask : array_like
        3-D array, bool or numeric, non-zero = vessel.
    spacing : sequence of 3 floats
        Voxel size along axes 0, 1, 2, positive; positions and radii come out in these units.
    **options
        Method options: :func:`vesselflow.skeletonize` parameters for ``"vesselflow"``,
        ``teasar_params`` keys (``scale``, ``const`` in voxels of the largest spacing,
        ``pdrf_scale``, ``pdrf_exponent``, ``max_paths``) for ``"teasar"``,
        ``pc_skeletor.LBC`` arguments for ``"pointcloud"``; ``"voxel"`` and ``"mesh"`` take
        none. An unknown option raises ``TypeError``.

    Returns
    -------
    VesselGraph
        Positions in physical units in array axis order; radii from :func:`edt_radii`
        (``"vesselflow"``: its own); ``info["seconds"]`` the wall time of the method,
        ``info["method"]``, ``info["radii"]``. An all-background mask gives an empty graph.

    Raises
    ------
    ValueError
        Unknown method, a mask that is not 3-D, or a bad spacing.
    TypeError
        A mask that is not bool or numeric, or an option the method does not take.
    ImportError
        The method's packages are missing; the message says which and how to install them.

    Examples
    --------
    >>> import numpy as np
    >>> from vesselflow import compare
    >>> mask = np.zeros((40, 21, 21), bool)
    >>> mask[:, 6:15, 6:15] = True
    >>> graph = compare.run("vesselflow", mask, spacing=(1.0, 0.5, 0.5))
    >>> graph.info["method"], graph.info["seconds"] > 0
    ('vesselflow', True)
    >>> compare.run("teasar", mask)  # doctest: +SKIP
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}: choose one of {', '.join(METHODS)}")
    volume = _as_mask(mask)
    sampling = _as_spacing(spacing)
    reason = _missing(method)
    if reason is not None:
        raise ImportError(f"method {method!r} {reason}")
    if method == "vesselflow":
        return _run_vesselflow(volume, sampling, options)
    runner = _RUNNERS[method]
    _check_options(method, runner, options)
    start = time.perf_counter()
    if volume.any():
        positions, edges, extra = runner(volume, sampling, **options)
    else:
        positions, edges, extra = np.zeros((0, 3)), np.zeros((0, 2), np.int64), {}
    seconds = time.perf_counter() - start
    positions, edges = _clean(positions, edges)
    info: dict[str, Any] = {"method": method, "seconds": seconds, "radii": "edt", **extra}
    return VesselGraph(
        positions,
        edt_radii(volume, positions, tuple(sampling.tolist())),
        edges,
        spacing=sampling,
        info=info,
        params=dict(options),
    )


def edt_radii(
    mask: ArrayLike, positions: ArrayLike, spacing: Sequence[float] = (1.0, 1.0, 1.0)
) -> NDArray[np.float64]:
    """Radii of nodes read from the mask's Euclidean distance transform.

    Parameters
    ----------
    mask : array_like
        3-D, non-zero = vessel.
    positions : (N, 3) array_like
        Node positions in physical units, array axis order.
    spacing : sequence of 3 floats
        Voxel size along axes 0, 1, 2.

    Returns
    -------
    (N,) float64
        ``scipy.ndimage.distance_transform_edt(mask, sampling=spacing)`` (the physical
        distance from a voxel centre to the nearest background voxel centre; 0 on
        background; voxels beyond the array border do not count as background) at the voxel
        nearest each node: index ``rint(position / spacing)`` clipped into the array. This
        is the paper's radius mapping for its peers (section IV-A).

    Examples
    --------
    >>> import numpy as np
    >>> from vesselflow import compare
    >>> mask = np.zeros((7, 7, 7), bool)
    >>> mask[3, 3, 1:6] = True  # a one-voxel line
    >>> compare.edt_radii(mask, [[3, 3, 3], [0, 0, 0]]).tolist()  # on it, and off the mask
    [1.0, 0.0]
    """
    from scipy import ndimage

    volume = _as_mask(mask)
    sampling = _as_spacing(spacing)
    points = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(points).all():
        raise ValueError("positions must be finite")
    if len(points) == 0:
        return np.zeros(0)
    distance = np.asarray(ndimage.distance_transform_edt(volume, sampling=sampling))
    index = np.rint(points / sampling).astype(np.int64)
    index = np.clip(index, 0, np.asarray(volume.shape) - 1)
    return np.asarray(distance[index[:, 0], index[:, 1], index[:, 2]], dtype=np.float64)


# --- the methods: each takes a non-empty bool mask and the spacing, returns
# --- (positions (N, 3) physical, edges (E, 2), extra info)

_Result = tuple[NDArray[np.float64], NDArray[np.int64], dict[str, Any]]


def _run_vesselflow(
    volume: NDArray[np.bool_], sampling: NDArray[np.float64], options: Mapping[str, Any]
) -> VesselGraph:
    start = time.perf_counter()
    graph = skeletonize(volume, tuple(sampling.tolist()), **options)
    graph.info["seconds"] = time.perf_counter() - start
    graph.info["method"] = "vesselflow"
    graph.info["radii"] = "vesselflow"
    return graph


def _voxel(volume: NDArray[np.bool_], sampling: NDArray[np.float64]) -> _Result:
    skeletonize = _module("skimage.morphology").skeletonize
    skan = _module("skan")
    thin = np.asarray(skeletonize(volume), dtype=bool)
    if not thin.any():
        return np.zeros((0, 3)), np.zeros((0, 2), np.int64), {"skeleton_voxels": 0}
    skeleton = skan.Skeleton(thin, spacing=sampling)
    graph = skeleton.graph.tocoo()
    upper = graph.row < graph.col
    edges = np.stack([graph.row[upper], graph.col[upper]], axis=1).astype(np.int64)
    positions = np.asarray(skeleton.coordinates, dtype=np.float64) * sampling
    return positions, edges, {"skeleton_voxels": int(thin.sum())}


def _teasar(
    volume: NDArray[np.bool_],
    sampling: NDArray[np.float64],
    *,
    scale: float = TEASAR_PARAMS["scale"],
    const: float = TEASAR_PARAMS["const"],
    pdrf_scale: float = TEASAR_PARAMS["pdrf_scale"],
    pdrf_exponent: int = int(TEASAR_PARAMS["pdrf_exponent"]),
    max_paths: int | None = None,
) -> _Result:
    kimimaro = _module("kimimaro")
    params: dict[str, Any] = {
        "scale": scale,
        "const": const * float(sampling.max()),
        "pdrf_scale": pdrf_scale,
        "pdrf_exponent": int(pdrf_exponent),
    }
    if max_paths is not None:
        params["max_paths"] = max_paths
    # Vessels have no somata: thresholds beyond any radius switch that heuristic off.
    no_soma = float(np.sum(np.asarray(volume.shape) * sampling)) * 10.0
    params.update(
        soma_detection_threshold=no_soma,
        soma_acceptance_threshold=no_soma,
        soma_invalidation_scale=1.0,
        soma_invalidation_const=0.0,
    )
    skeletons = kimimaro.skeletonize(
        volume.astype(np.uint8),
        teasar_params=params,
        anisotropy=tuple(sampling.tolist()),
        dust_threshold=0,
        fix_branching=True,
        fix_borders=True,
        fill_holes=False,
        progress=False,
        parallel=1,
    )
    positions, edges = [], []
    offset = 0
    for label in sorted(skeletons):
        skeleton = skeletons[label]
        positions.append(np.asarray(skeleton.vertices, dtype=np.float64).reshape(-1, 3))
        edges.append(np.asarray(skeleton.edges, dtype=np.int64).reshape(-1, 2) + offset)
        offset += len(positions[-1])
    if not positions:
        return np.zeros((0, 3)), np.zeros((0, 2), np.int64), {"teasar_params": params}
    return np.concatenate(positions), np.concatenate(edges), {"teasar_params": params}


def _surface(
    volume: NDArray[np.bool_], sampling: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Closed marching-cubes surface of ``volume`` (padded by a background voxel), physical."""
    marching_cubes = _module("skimage.measure").marching_cubes
    padded = np.pad(volume, 1).astype(np.float32)
    vertices, faces, _, _ = marching_cubes(padded, level=0.5, spacing=tuple(sampling.tolist()))
    vertices = np.asarray(vertices, dtype=np.float64) - sampling
    return vertices, np.asarray(faces, dtype=np.int64)


def _mesh(volume: NDArray[np.bool_], sampling: NDArray[np.float64]) -> _Result:
    mesh_skeleton = _module("compas_cgal.skeletonization").mesh_skeleton
    vertices, faces = _surface(volume, sampling)
    segments = np.asarray(mesh_skeleton((vertices, faces)), dtype=np.float64).reshape(-1, 2, 3)
    # Polylines share their end points exactly: equal coordinates are one node.
    positions, inverse = np.unique(segments.reshape(-1, 3), axis=0, return_inverse=True)
    edges = np.asarray(inverse, dtype=np.int64).reshape(-1, 2)
    extra = {"surface_vertices": len(vertices), "surface_faces": len(faces)}
    return positions, edges, extra


def _pointcloud(
    volume: NDArray[np.bool_], sampling: NDArray[np.float64], **lbc_options: Any
) -> _Result:
    open3d = _module("open3d")
    pc_skeletor = _module("pc_skeletor")
    vertices, _ = _surface(volume, sampling)
    cloud = open3d.geometry.PointCloud(open3d.utility.Vector3dVector(vertices))
    lbc = pc_skeletor.LBC(point_cloud=cloud, **{"down_sample": -1, **lbc_options})
    lbc.extract_skeleton()
    lbc.extract_topology()
    graph = lbc.skeleton_graph
    nodes = sorted(graph.nodes)
    index = {node: i for i, node in enumerate(nodes)}
    positions = np.asarray([graph.nodes[n]["pos"] for n in nodes], dtype=np.float64)
    edges = np.asarray([(index[a], index[b]) for a, b in graph.edges], dtype=np.int64)
    return positions.reshape(-1, 3), edges.reshape(-1, 2), {"surface_vertices": len(vertices)}


_RUNNERS: dict[str, Callable[..., _Result]] = {
    "voxel": _voxel,
    "teasar": _teasar,
    "mesh": _mesh,
    "pointcloud": _pointcloud,
}


# --- helpers


def _missing(method: str) -> str | None:
    """None if every package ``method`` needs imports, else why not and how to fix it."""
    for module, package, hint in _REQUIREMENTS[method]:
        try:
            importlib.import_module(module)
        except Exception as error:  # a broken install fails with more than ImportError
            return f"needs the package {package!r} ({type(error).__name__}: {error}): {hint}"
    return None


def _module(name: str) -> Any:
    """An optional dependency, imported when a method runs (typed ``Any``)."""
    return importlib.import_module(name)


def _check_options(method: str, runner: Callable[..., _Result], options: Mapping[str, Any]) -> None:
    """``TypeError`` for options ``runner`` does not take (checked before any work)."""
    import inspect

    parameters = inspect.signature(runner).parameters
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
        return
    keywords = {n for n, p in parameters.items() if p.kind is inspect.Parameter.KEYWORD_ONLY}
    unknown = set(options) - keywords
    if unknown:
        accepted = ", ".join(sorted(keywords)) or "none"
        raise TypeError(
            f"unknown option(s) for {method!r}: {', '.join(sorted(unknown))} (accepted: {accepted})"
        )


def _clean(
    positions: NDArray[np.float64], edges: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Edges as sorted unique pairs without self-loops."""
    points = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    pairs = np.sort(np.asarray(edges, dtype=np.int64).reshape(-1, 2), axis=1)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    if len(pairs):
        pairs = np.unique(pairs, axis=0)
    return points, pairs


def _as_mask(mask: ArrayLike) -> NDArray[np.bool_]:
    array = np.asarray(mask)
    if array.ndim != 3:
        raise ValueError(f"mask must be 3-D, got {array.ndim} dimension(s)")
    if array.dtype.kind not in "biuf":
        raise TypeError(f"mask must be bool or numeric, got dtype {array.dtype}")
    return np.asarray(array != 0, dtype=bool)


def _as_spacing(spacing: Sequence[float]) -> NDArray[np.float64]:
    values = np.asarray(spacing, dtype=np.float64).reshape(-1)
    if values.shape != (3,) or not np.isfinite(values).all() or (values <= 0).any():
        raise ValueError(f"spacing must be 3 positive finite numbers, got {list(spacing)}")
    return values
