"""Whole-organ volumes on Dask: the volume cut into blocks with a halo, each block run
on a worker that reads it straight from the store, and the blocks' parts merged into
one graph on the calling process (``vesselflow._core.contract_block`` and
``merge_blocks``; the design is in the Rust module ``vesselflow::blocks``); then the
merged edges that cross background are routed inside the mask, each by the block that
owns it (``route_block`` and ``splice_routes``; ``vesselflow::blocks_route``).

Needs the ``dask`` extra: ``pip install vesselflow[dask]``.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from vesselflow import _core
from vesselflow._util import atomic_files, import_extra, spacing_argument
from vesselflow.graph import VesselGraph
from vesselflow.skeletonizer import Skeletonizer
from vesselflow.volumes import open_zarr

REACH = 16
"""Base cells a cut disturbs the contraction. Measured on the shapes of
``tests/python/test_distributed.py`` (a diagonal tube of radius 3 and a torus cut by
blocks of 32 at faces, edges and corners), NetMets at sigma = 1 against the single run:
halo 4 leaves a spur on the tube (CFPR 0.86), halos 4 and 8 split the torus's loop at a
seam (CFNR = CFPR = 1), halo 16 gives all four rates <= 0.003. The default halo is the
larger of this and three times the largest vessel radius found by the per-chunk pass."""

BLOCK_RADII = 6
"""Fewest radii of the thickest vessel a block should span along every axis it cuts; under
it the run warns. Measured on straight tubes whose ends lie within 4 voxels of a seam, 16
per set-up (``benches/results/chunked.md``, "Vessel ends near seams"): in blocks of 3.6
and 5.3 radii, 1 of 16 tubes had an end more than 2 voxels off (6.9 and 4.4; the single
run: none; NetMets' CFNR 0.062 against 0); in blocks of 6.4, 7.1 and 12.8 radii none, as
in the single run."""

Block = tuple[int, int, int]
Slices = tuple[slice, slice, slice]


class _Source:
    """A 3-D array that every worker can read: a Zarr array (pickled with its store)
    and the leading indices that drop its unit axes."""

    def __init__(self, array: Any, lead: tuple[int, ...]) -> None:
        self.array = array
        self.lead = lead
        self.shape: tuple[int, int, int] = tuple(int(n) for n in array.shape[len(lead) :])  # type: ignore[assignment]
        if len(self.shape) != 3:
            raise ValueError(f"source must be 3-D (after unit axes), got shape {array.shape}")

    def read(self, where: Slices) -> NDArray[Any]:
        return np.asarray(self.array[(*self.lead, *where)])


def _source(source: Any, key: str | None, workdir: Path) -> tuple[_Source, Any]:
    """The source as a worker-readable Zarr array, and its spacing if known."""
    zarr = import_extra("zarr", "dask")
    if isinstance(source, (str, os.PathLike)):
        array, spacing, _ = open_zarr(Path(source), key)
        return _Source(array, _lead(array.shape)), spacing
    if isinstance(source, zarr.Array):
        return _Source(source, _lead(source.shape)), None
    if hasattr(source, "dask"):  # a dask array: stored once, then read by blocks
        path = workdir / "input.zarr"
        source.to_zarr(str(path), overwrite=True)
        array = zarr.open_array(str(path), mode="r")
        return _Source(array, _lead(array.shape)), None
    data = np.asarray(source)
    path = workdir / "input.zarr"
    array = zarr.open_array(
        str(path), mode="w", shape=data.shape, dtype=data.dtype, chunks=(64,) * data.ndim
    )
    array[...] = data
    return _Source(zarr.open_array(str(path), mode="r"), _lead(data.shape)), None


def _lead(shape: Sequence[int]) -> tuple[int, ...]:
    """Index 0 on the leading unit axes beyond three (OME ``t`` and ``c``)."""
    lead = len(shape) - 3
    if lead < 0 or any(shape[i] != 1 for i in range(max(lead, 0))):
        raise ValueError(f"source must be 3-D (unit axes aside), got shape {tuple(shape)}")
    return (0,) * lead


def _mask(source: _Source, where: Slices, threshold: float | None, label: float | None) -> Any:
    return _core.binarise(source.read(where), threshold, label).view(np.uint8)


def _chunk_pass(
    source: _Source,
    where: Slices,
    spacing: Sequence[float],
    params: dict[str, Any],
    threshold: float | None,
    label: float | None,
) -> float:
    """The largest vessel radius (physical units) in a chunk, or -1 if it holds no
    foreground: the cheap pass that skips empty blocks and sizes the halo (the run's own
    EDT, 4-8x faster than SciPy's on a 128³ chunk). Voxels outside the window measured
    are background, so a chunk inside a vessel thicker than itself reads at most half
    its side (a 16³ chunk in a radius-12 vessel: 8, and a halo of 24 where the vessel
    needs 36); such a chunk is measured again on windows grown by the chunk's size on
    every side, then twice that, and so on (clipped to the volume), until the radius
    stays a voxel under half the window or the window is the whole volume."""
    sk = _core.Skeletonizer(**params)
    window, margin, r = where, [w.stop - w.start for w in where], -1.0
    # Each round at least doubles the margin: capped by the volume's size in bits.
    for _ in range(64):
        mask = np.ascontiguousarray(_mask(source, window, threshold, label))
        got = _core.largest_radius(sk, mask, list(spacing))
        if got is None:
            return -1.0  # the chunk itself is empty (a grown window holds it)
        r = float(got)
        full = all(w.start == 0 and w.stop == n for w, n in zip(window, source.shape))
        cap = min(math.ceil(n / 2) * d for n, d in zip(mask.shape, spacing))
        if full or r < cap - max(spacing):
            return r
        grown = [
            slice(max(w.start - m, 0), min(w.stop + m, n))
            for w, m, n in zip(where, margin, source.shape)
        ]
        window = grown[0], grown[1], grown[2]
        margin = [2 * m for m in margin]
    return r


def _block_task(
    source: _Source,
    block: Block,
    outer: Slices,
    core: list[list[int]],
    spacing: list[float],
    params: dict[str, Any],
    rule: tuple[float | None, float | None],
    out: str | None,
) -> tuple[str, Any]:
    """Run the block phase of one block; with ``out``, keep its part there (an npz
    written atomically) and return its path, reusing a part already there."""
    if out is not None and Path(out).exists():
        return "reused", out
    mask = np.ascontiguousarray(_mask(source, outer, *rule))
    origin = [s.start for s in outer]
    sk = _core.Skeletonizer(**params)
    part = _core.contract_block(sk, mask, origin, core, list(source.shape), spacing)
    if out is None:
        return "computed", part
    with atomic_files(Path(out)) as (temp,), open(temp, "wb") as f:
        np.savez(f, **part)  # type: ignore[arg-type]  # numpy stubs: allow_pickle
    return "computed", out


PART_FORMAT = 5
"""Version of the block parts kept in a ``workdir`` (2: one record per node of a block,
with its position; 3: with the block's sprouts; 4: with the radius each node split long
edges by, for the coarse start; 5: with the nodes the split put on the block's edges);
a workdir of another version is refused like one of another set-up."""

ROUTE_READS = 4
"""Reads a routing task may make: the first with the block phase's halo, each next one
with the halo the block reported it needs (``vesselflow::blocks_route``)."""


def _owned_edges(
    positions: NDArray[Any],
    edges: NDArray[Any],
    spacing: Sequence[float],
    shape: Sequence[int],
    size: Sequence[int],
) -> dict[Block, tuple[NDArray[Any], NDArray[Any]]]:
    """The merged edges of every block that owns one (the owner voxel's block), in
    block order: the nodes they join (ascending global ids) and the edges (sorted)."""
    if len(edges) == 0:
        return {}
    owner = _core.owner_voxels(positions, edges, list(spacing), list(shape)) // np.asarray(size)
    order = np.lexsort((np.arange(len(edges)), owner[:, 2], owner[:, 1], owner[:, 0]))
    keys, starts = np.unique(owner[order], axis=0, return_index=True)
    out = {}
    for key, lo, hi in zip(keys, starts, [*starts[1:], len(order)]):
        mine = edges[np.sort(order[lo:hi])]
        nodes = np.unique(mine).astype(np.uint32)
        out[(int(key[0]), int(key[1]), int(key[2]))] = (nodes, mine.astype(np.uint32))
    return out


def _route_task(
    source: _Source,
    block: Block,
    size: Sequence[int],
    widths: Sequence[int],
    spacing: list[float],
    params: dict[str, Any],
    rule: tuple[float | None, float | None],
    nodes: NDArray[Any],
    positions: NDArray[Any],
    edges: NDArray[Any],
    out: str | None,
) -> tuple[str, dict[str, Any]]:
    """Run the routing phase of one block on its owned edges, reading the block again
    with a larger halo when it reports one; with ``out``, keep the part there."""
    if out is not None and Path(out).exists():
        with np.load(out) as f:
            return "reused", {**{name: f[name] for name in f.files}, "halo": None}
    sk = _core.Skeletonizer(**params)
    halo = list(widths)
    for _ in range(ROUTE_READS):
        outer, core = _block_args(block, size, halo, source.shape)
        mask = np.ascontiguousarray(_mask(source, outer, *rule))
        origin = [s.start for s in outer]
        part = _core.route_block(
            sk, mask, origin, core, list(source.shape), spacing, nodes, positions, edges
        )
        if part["halo"] is None:
            break
        halo = [max(h, n) for h, n in zip(halo, part["halo"])]
    else:
        raise RuntimeError(f"block {block}: routing still needs a larger halo than {halo}")
    if out is not None:
        arrays = {k: v for k, v in part.items() if k != "halo"}
        with atomic_files(Path(out)) as (temp,), open(temp, "wb") as f:
            np.savez(f, **arrays)
    return "computed", part


def skeletonize(
    source: Any,
    spacing: Sequence[float] | float | None = None,
    *,
    chunks: Sequence[int] | int = (256, 256, 256),
    client: Any = None,
    workdir: str | os.PathLike[str] | None = None,
    progress: Callable[[int, int], object] | None = None,
    halo: int | None = None,
    key: str | None = None,
    threshold: float | None = None,
    label: float | None = None,
    **params: Any,
) -> VesselGraph:
    """Skeletonize a volume in blocks on a Dask cluster: one graph, as from
    :func:`vesselflow.skeletonize` on the whole volume (see the README section "Whole
    organs on Dask" for how close).

    Parameters
    ----------
    source
        A Zarr or OME-Zarr path (``key`` as for :func:`vesselflow.load_volume`), a zarr
        array, a dask array or a NumPy array. Workers read their blocks from the store;
        a dask or NumPy array is first stored as Zarr in ``workdir``.
    spacing
        Voxel spacing (3 numbers, or one); by default the OME metadata's, else 1.
    chunks
        Core block shape in voxels (one number for all axes). Wider blocks give a graph
        closer to the single run's in less time (fewer seams, less halo per voxel), for
        more memory per worker (README, "Whole organs on Dask"). A block should span at
        least :data:`BLOCK_RADII` radii of the thickest vessel along every axis it cuts:
        the run warns when it does not.
    client
        A ``dask.distributed.Client``; ``None`` runs on a local cluster of one
        single-threaded worker process per core.
    workdir
        Directory for the blocks' parts (and the routing phase's): a run interrupted, or
        one that lost a worker, resumes there and computes only the missing blocks.
        ``None``: a temporary directory, parts kept in memory.
    progress
        Called as ``progress(done, total)`` after every block.
    halo
        Halo width in base cells (the smallest spacing); by default the larger of
        :data:`REACH` and three times the largest vessel radius. A wider one costs time
        and does not bring the graph closer to the single run's: each block still runs its
        own flow (its own stop and solve).
    key, threshold, label
        As for :func:`vesselflow.load_volume`: the dataset and the input rule.
    **params
        Method parameters, as for :class:`vesselflow.Skeletonizer`; checked before any
        work is sent. With ``sprouts`` (default), every block grows the sprouts of its
        read and reports those whose lobe ends in its core; the merge attaches them
        (``info["sprouts"]`` counts them).

    Returns
    -------
    VesselGraph
        The merged graph; ``info`` holds ``blocks`` (total), ``blocks_empty`` (skipped),
        ``blocks_computed`` and ``blocks_reused`` (found in ``workdir``), ``blocks_routed``
        (blocks that own a merged edge) and ``routes_reused`` (their routing parts found in
        ``workdir``), ``halo``, and ``seconds``: wall time of the per-chunk pass, the block
        phase (reading, binarising and the blocks, with the time their parts take to come
        back), the merge and the routing phase.
    """
    import tempfile

    distributed = import_extra("distributed", "dask")
    sk = Skeletonizer(**params)
    core_params = dict(sk.params)
    core_params["threads"] = 1
    size = _chunk_shape(chunks)
    if halo is not None and (isinstance(halo, bool) or int(halo) != halo or halo < 0):
        raise ValueError(f"halo={halo!r} must be a whole number of base cells >= 0")
    temp = tempfile.TemporaryDirectory(prefix="vesselflow-") if workdir is None else None
    root = Path(temp.name if temp is not None else workdir)  # type: ignore[arg-type]
    root.mkdir(parents=True, exist_ok=True)
    own = None
    try:
        src, file_spacing = _source(source, key, root)
        spacing3 = spacing_argument(spacing if spacing is not None else (file_spacing or 1.0))
        _core.Skeletonizer(**core_params)  # spacing and parameters checked before work
        if client is None:
            own = distributed.Client(
                distributed.LocalCluster(
                    n_workers=os.cpu_count() or 1, threads_per_worker=1, processes=True
                )
            )
        run = own or client
        blocks = _blocks(src.shape, size)
        rule = (threshold, label)
        clock = time.perf_counter()
        radii = run.gather(
            run.map(
                _chunk_pass,
                [src] * len(blocks),
                [_core_slices(b, size, src.shape) for b in blocks],
                [spacing3] * len(blocks),
                [core_params] * len(blocks),
                [threshold] * len(blocks),
                [label] * len(blocks),
                pure=False,
            )
        )
        seconds = {"chunk_pass": time.perf_counter() - clock}
        occupied = [b for b, r in zip(blocks, radii) if r >= 0]
        c = min(spacing3)
        r_max = max((r for r in radii if r >= 0), default=0.0)
        cells = halo if halo is not None else max(REACH, math.ceil(3 * r_max / c))
        cut = [size[d] * spacing3[d] for d in range(3) if src.shape[d] > size[d]]
        if cut and min(cut) < BLOCK_RADII * r_max:
            wide = [math.ceil(BLOCK_RADII * r_max / s) for s in spacing3]
            warnings.warn(
                f"blocks of {list(size)} voxels span {min(cut) / r_max:.1f} radii of the "
                f"thickest vessel (radius {r_max:.3g}), under {BLOCK_RADII}: vessel ends near "
                f"seams can come out several voxels off; chunks of at least {wide} voxels "
                "avoid it",
                UserWarning,
                stacklevel=2,
            )
        widths = [math.ceil(cells * c / s) for s in spacing3]
        parts_dir = None
        if workdir is not None:
            parts_dir = root / "blocks"
            _claim(root, PART_FORMAT, src.shape, size, widths, spacing3, core_params, rule)
            parts_dir.mkdir(exist_ok=True)
        args = [_block_args(b, size, widths, src.shape) for b in occupied]
        clock = time.perf_counter()
        futures = [
            run.submit(
                _block_task,
                src,
                b,
                outer,
                core,
                list(spacing3),
                core_params,
                rule,
                None if parts_dir is None else str(parts_dir / f"{b[0]}_{b[1]}_{b[2]}.npz"),
                pure=False,
            )
            for b, (outer, core) in zip(occupied, args)
        ]
        for done, _ in enumerate(distributed.as_completed(futures), start=1):
            if progress is not None:
                progress(done, len(futures))
        results = run.gather(futures)
        seconds["blocks"] = time.perf_counter() - clock
        clock = time.perf_counter()
        counts = {"computed": 0, "reused": 0}
        parts = []
        for status, value in results:
            counts[status] += 1
            if isinstance(value, str):
                with np.load(value) as f:
                    value = {name: f[name] for name in f.files}
            parts.append(value)
        positions, radii_out, edges, info = _core.merge_blocks(
            _core.Skeletonizer(**core_params), parts, list(src.shape), list(spacing3)
        )
        seconds["merge"] = time.perf_counter() - clock
        clock = time.perf_counter()
        routes_dir = None
        if parts_dir is not None:
            routes_dir = root / "routes"
            routes_dir.mkdir(exist_ok=True)
        owned = _owned_edges(positions, edges, spacing3, src.shape, size)
        futures = [
            run.submit(
                _route_task,
                src,
                b,
                size,
                widths,
                list(spacing3),
                core_params,
                rule,
                nodes,
                positions[nodes],
                own_edges,
                None if routes_dir is None else str(routes_dir / f"{b[0]}_{b[1]}_{b[2]}.npz"),
                pure=False,
            )
            for b, (nodes, own_edges) in owned.items()
        ]
        routed = run.gather(futures)
        for status, _ in routed:
            counts["routes_" + status] = counts.get("routes_" + status, 0) + 1
        positions, radii_out, edges, spliced = _core.splice_routes(
            _core.Skeletonizer(**core_params),
            positions,
            radii_out,
            edges,
            [part for _, part in routed],
            list(spacing3),
        )
        info["pruned_spurs"] = spliced["pruned_spurs"]
        seconds["route"] = time.perf_counter() - clock
    finally:
        if own is not None:
            own.close()
        if temp is not None:
            temp.cleanup()
    info.update(
        blocks=len(blocks),
        blocks_empty=len(blocks) - len(occupied),
        blocks_computed=counts["computed"],
        blocks_reused=counts["reused"],
        blocks_routed=len(owned),
        routes_reused=counts.get("routes_reused", 0),
        halo=cells,
        seconds=seconds,
    )
    return VesselGraph(positions, radii_out, edges, spacing3, info, dict(sk.params))


def _chunk_shape(chunks: Sequence[int] | int) -> tuple[int, int, int]:
    values = [chunks] * 3 if isinstance(chunks, int) else list(chunks)
    if len(values) != 3 or not all(isinstance(v, int) and v >= 1 for v in values):
        raise ValueError(f"chunks={chunks!r} must be one or three whole numbers >= 1")
    return values[0], values[1], values[2]


def _blocks(shape: Sequence[int], size: Sequence[int]) -> list[Block]:
    counts = [math.ceil(n / s) for n, s in zip(shape, size)]
    return [(i, j, k) for i in range(counts[0]) for j in range(counts[1]) for k in range(counts[2])]


def _core_slices(b: Block, size: Sequence[int], shape: Sequence[int]) -> Slices:
    s = [slice(b[d] * size[d], min((b[d] + 1) * size[d], shape[d])) for d in range(3)]
    return s[0], s[1], s[2]


def _block_args(
    b: Block, size: Sequence[int], widths: Sequence[int], shape: Sequence[int]
) -> tuple[Slices, list[list[int]]]:
    """The block with its halo, and its core in the block's indices."""
    core = _core_slices(b, size, shape)
    lo = [max(core[d].start - widths[d], 0) for d in range(3)]
    hi = [min(core[d].stop + widths[d], shape[d]) for d in range(3)]
    outer = (slice(lo[0], hi[0]), slice(lo[1], hi[1]), slice(lo[2], hi[2]))
    return outer, [[core[d].start - lo[d], core[d].stop - lo[d]] for d in range(3)]


def _claim(root: Path, *setup: Any) -> None:
    """Tie ``root`` to this run's set-up, so that parts of another run are never
    merged into this one."""
    text = json.dumps(setup, sort_keys=True, default=str)
    digest = hashlib.sha256(text.encode()).hexdigest()
    stamp = root / "run.json"
    if stamp.exists():
        old = json.loads(stamp.read_text()).get("digest")
        if old != digest:
            raise ValueError(
                f"workdir {root} holds blocks of another run (other volume shape, chunks, "
                "halo, spacing, parameters, input rule or vesselflow part format); "
                "use a new workdir"
            )
        return
    with atomic_files(stamp) as (temp,):
        temp.write_text(json.dumps({"digest": digest, "setup": text}))


def main(argv: Sequence[str] | None = None) -> int:
    """``vesselflow distributed SOURCE -o GRAPH [...]``: :func:`skeletonize` from the
    command line, on the Dask scheduler ``--scheduler`` (else a local cluster). Returns
    the exit status."""
    import argparse

    parser = argparse.ArgumentParser(
        prog="vesselflow distributed",
        description="Skeletonize a Zarr/OME-Zarr volume in blocks on a Dask cluster.",
    )
    parser.add_argument("source", help="Zarr or OME-Zarr path")
    parser.add_argument("-o", "--output", required=True, help="graph file (any graph format)")
    parser.add_argument("--chunks", type=int, nargs="+", default=[256], help="block shape")
    parser.add_argument("--scheduler", help="Dask scheduler address, e.g. tcp://host:8786")
    parser.add_argument("--workdir", help="directory for block results (resumable)")
    parser.add_argument("--halo", type=int, help="halo in base cells (default: automatic)")
    parser.add_argument("--spacing", type=float, nargs="+", help="voxel spacing (1 or 3)")
    parser.add_argument("--key", help="dataset inside the Zarr group")
    parser.add_argument("--threshold", type=float, help="mask = data > threshold")
    parser.add_argument("--label", type=float, help="mask = data == label")
    parser.add_argument(
        "--param", action="append", default=[], metavar="NAME=VALUE", help="method parameter"
    )
    args = parser.parse_args(argv)
    params: dict[str, Any] = {}
    for item in args.param:
        name, sep, value = item.partition("=")
        if not sep:
            parser.error(f"--param {item!r} must be NAME=VALUE")
        params[name] = json.loads(value) if value[:1] in "-0123456789tf[" else value
    chunks = args.chunks[0] if len(args.chunks) == 1 else tuple(args.chunks)
    client = None
    if args.scheduler:
        client = import_extra("distributed", "dask").Client(args.scheduler)
    try:
        graph = skeletonize(
            args.source,
            args.spacing,
            chunks=chunks,
            client=client,
            workdir=args.workdir,
            halo=args.halo,
            key=args.key,
            threshold=args.threshold,
            label=args.label,
            progress=lambda done, total: print(f"\rblocks {done}/{total}", end="", flush=True),
            **params,
        )
    except (ValueError, TypeError, FileNotFoundError, ModuleNotFoundError) as e:
        print(f"\nvesselflow distributed: error: {e}", file=sys.stderr)
        return 2
    finally:
        if client is not None:
            client.close()
    graph.save(args.output)
    print(f"\n{graph.n_nodes} nodes, {graph.n_edges} edges -> {args.output}")
    return 0
