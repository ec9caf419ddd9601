"""Chunked runs on Dask against the single run: ``benches/results/chunked.md``.

    python benches/chunked.py [--block 128] [--workers 2] [--out benches/results/chunked.md]

Volumes: the 256³ synthetic bed (``vesselflow.synth.vascular_bed``, seed 0; ``--size``)
and a 512x512x256 tiling of four beds (seeds 0-3), stored as Zarr (chunks of the block size).
For each: the single run in a fresh subprocess (wall time, peak RSS) and the chunked run
(``vesselflow.distributed.skeletonize``, blocks of ``--block``³) on a fresh LocalCluster
of ``--workers`` single-threaded worker processes (wall time, every worker's peak RSS);
then components and cycle rank of both graphs, NetMets at sigma = 1 voxel between them,
the radii of matched nodes (each chunked node and the nearest single-run node within
1 voxel), the same against the single run with its solver's tolerance halved and doubled,
on the mask with its axes reordered and on the mask one voxel further into a larger array
(the method's own spread), the chunked run's
time per phase, determinism (the run again on 1 worker: identical arrays), a worker
killed mid-run (same graph), and a resume after deleting parts from the workdir (blocks
recomputed). On the first volume, what the chunked run's distance from the single run is
made of: how much of it lies near the seams, a sweep of the halo, and both runs held to
one contraction schedule; where a volume holds several blocks twice as wide, the run in
those. Then the fidelity benchmark's held-out synthetic cases in blocks of 64³, scored
against their truth beside the single run and its own spread (``fidelity.score``); and
straight tubes with their ends near seams, in blocks of 3.6 to 12.8 of their radii (how far
the graph's ends lie from the true ones, single run against chunked run). Ends with the
scaling law and projections for 2048³ and 10000³.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import distributed
import networkx as nx
import numpy as np
import zarr
from scipy.spatial import cKDTree

import vesselflow
from vesselflow import distributed as vd
from vesselflow.metrics import _edge_segments, _length_samples, _SegmentIndex, netmets
from vesselflow.synth import cylinder, vascular_bed

if TYPE_CHECKING:
    import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))

SINGLE = """
import json, sys, time
import numpy as np, zarr, vesselflow
mask = np.asarray(zarr.open_array(sys.argv[1], mode="r")[...])
params = json.loads(sys.argv[3])
axes = params.pop("axes", [0, 1, 2])
shift = params.pop("shift", 0)
mask = np.ascontiguousarray(np.pad(mask, ((shift, 0),) * 3).transpose(axes))
t = time.perf_counter()
g = vesselflow.skeletonize(mask, **params)
wall = time.perf_counter() - t
positions = g.positions[:, np.argsort(axes)] - shift
np.savez(sys.argv[2], positions=positions, radii=g.radii, edges=g.edges)
hwm = [int(x.split()[1]) * 1024 for x in open("/proc/self/status") if x.startswith("VmHWM:")]
print(json.dumps({"wall": wall, "peak": hwm[0], "iterations": g.info["iterations"]}))
"""


def _topology(g: vesselflow.VesselGraph) -> tuple[int, int]:
    nxg = g.to_networkx()
    comps = nx.number_connected_components(nxg)
    return comps, nxg.number_of_edges() - nxg.number_of_nodes() + comps


def _peak() -> int:
    """This process's peak RSS: ``VmHWM``, not ``ru_maxrss``, which Linux carries over
    exec from the forked parent (a worker or the single run would report this script's
    own RSS, the volumes it holds, whenever that is larger)."""
    with open("/proc/self/status") as f:
        return next(int(x.split()[1]) * 1024 for x in f if x.startswith("VmHWM:"))


def _cluster(workers: int) -> tuple[Any, Any]:
    cluster = distributed.LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,
        silence_logs=50,
    )
    return cluster, distributed.Client(cluster)


def _chunked(path: str, block: int, workers: int, **kw: Any) -> tuple[Any, float, list[int]]:
    cluster, client = _cluster(workers)
    try:
        base = list(client.run(_peak).values())
        t = time.perf_counter()
        g = vd.skeletonize(path, chunks=block, client=client, **kw)
        wall = time.perf_counter() - t
        peaks = list(client.run(_peak).values())
    finally:
        client.close()
        cluster.close()
    return g, wall, [max(p, b) for p, b in zip(peaks, base)]


def _same(a: Any, b: Any) -> bool:
    return all(
        np.array_equal(x, y)
        for x, y in [(a.positions, b.positions), (a.radii, b.radii), (a.edges, b.edges)]
    )


def _killed_run(path: str, block: int, workers: int, workdir: Path) -> tuple[Any, bool]:
    """The run with one worker process killed after the second block."""
    cluster, client = _cluster(workers)
    killed = [False]
    pids = client.run(os.getpid)

    def progress(done: int, total: int) -> None:
        if done == 2 and not killed[0]:
            os.kill(pids[sorted(pids)[0]], signal.SIGKILL)
            killed[0] = True

    try:
        g = vd.skeletonize(path, chunks=block, client=client, workdir=workdir, progress=progress)
    finally:
        client.close()
        cluster.close()
    return g, killed[0]


def _single(path: str, npz: Path, params: dict[str, Any]) -> tuple[dict[str, float], Any]:
    """The single run of the Zarr at ``path`` in a fresh process: (wall, peak), graph.
    ``params`` may hold ``axes``: the run is then on the mask with its axes in that
    order, and the graph's positions are put back in the mask's own axis order; and
    ``shift``: the run is on the mask with that many background slabs before each axis,
    and the positions are shifted back."""
    out = subprocess.run(
        [sys.executable, "-c", SINGLE, path, str(npz), json.dumps(params)],
        check=True,
        capture_output=True,
        text=True,
    )
    with np.load(npz) as f:
        graph = vesselflow.VesselGraph(f["positions"], f["radii"], f["edges"])
    return json.loads(out.stdout.strip().splitlines()[-1]), graph


def _compare(one: Any, g: Any) -> dict[str, Any]:
    """``g`` against the single run ``one``: topology of both, NetMets at sigma = 1
    voxel (and at 2), and the radii of matched nodes (each node of ``g`` and the nearest
    node of ``one`` within 1 voxel)."""
    dist, idx = cKDTree(one.positions).query(g.positions)
    matched = dist <= 1.0
    rel = np.abs(g.radii[matched] - one.radii[idx[matched]]) / np.maximum(
        one.radii[idx[matched]], 1e-9
    )
    nan = float("nan")
    return {
        "topology": (_topology(one), _topology(g)),
        "rates": netmets(one, g, 1.0),
        "rates2": netmets(one, g, 2.0),
        "nodes": (one.n_nodes, g.n_nodes),
        "matched": float(matched.mean()),
        "radius_median": float(np.median(rel)) if rel.size else nan,
        "radius_mean": float(rel.mean()) if rel.size else nan,
        "radius_within_2pc": float((rel <= 0.02).mean()) if rel.size else nan,
    }


#: Halos of the sweep on the first volume, beside its automatic halo (the report's
#: main row); 127 is a block of 128 that reads all but one slab of a 256 volume.
SWEEP_HALOS = (32, 64, 100, 127)
#: Both runs held to one schedule: the contraction capped below the iterations any run
#: takes when free (the 256³ bed's single run stalls after 12; blocks of 128³ stopped
#: after 13-15 in an earlier sweep: chunked.md, "History of the README's ..."), every solve tight.
SCHEDULE = {"max_iterations": 9, "cg_tol": 1e-10}
#: Width (voxels) of the band about the seams in which the differences are counted apart.
SEAM_BAND = 10.0


def _seam_split(one: Any, g: Any, shape: tuple[int, ...], block: int) -> dict[str, float]:
    """Where ``g`` departs from the single run ``one``: of ``one``'s centreline length,
    the share within :data:`SEAM_BAND` voxels of a seam (a block face inside the
    volume), and the share farther than 1 voxel from ``g`` in that band and beyond it."""
    points, weights = _length_samples(one, 0.25)
    a, b, _ = _edge_segments(g)
    d, _, _ = _SegmentIndex(a, b, 0.5).nearest(points)
    seam = np.full(len(points), np.inf)
    for axis, n in enumerate(shape):
        for k in range(1, -(-n // block)):
            seam = np.minimum(seam, np.abs(points[:, axis] - (k * block - 0.5)))
    band, far = seam < SEAM_BAND, d > 1.0
    total = float(weights.sum())
    return {
        "band": float(weights[band].sum()) / total,
        "far_in_band": float(weights[band & far].sum() / max(weights[band].sum(), 1e-12)),
        "far_beyond": float(weights[~band & far].sum() / max(weights[~band].sum(), 1e-12)),
    }


def _gap(
    path: str, shape: tuple[int, ...], one: Any, g: Any, args: Any, npz: Path
) -> dict[str, Any]:
    """What the chunked run's distance from the single run is made of (first volume):
    where it lies (:func:`_seam_split`), how it moves with the halo, and with both runs
    held to one contraction schedule (:data:`SCHEDULE`)."""
    halos = []
    for halo in SWEEP_HALOS:
        x, wall, _ = _chunked(path, args.block, args.workers, halo=halo)
        halos.append((f"halo {halo}", netmets(one, x, 1.0), wall))
    stats, fixed_one = _single(path, npz, SCHEDULE)
    x, wall, _ = _chunked(path, args.block, args.workers, halo=100, **SCHEDULE)
    schedule = ", ".join(f"{k}={v:g}" for k, v in SCHEDULE.items())
    halos.append((f"halo 100, both runs at {schedule}", netmets(fixed_one, x, 1.0), wall))
    return {
        "seams": _seam_split(one, g, shape, args.block),
        "halos": halos,
        "iterations": int(stats["iterations"]),
    }


#: Blocks of the check against the truth: the fidelity benchmark's volumes are 96³ to
#: 192³, so blocks of 64³ put seams through every one of them.
TRUTH_BLOCK = 64
#: The fidelity benchmark's headline columns (sigma = 2 base cells), in its row names.
TRUTH_RATES = {
    "gfnr": "GFNR",
    "gfpr": "GFPR",
    "cfnr": "CFNR",
    "cfpr": "CFPR",
    "mape": "radius MAPE %",
}
#: The graphs of the check against the truth, the single run first.
TRUTH_GRAPHS = ("single", "single, axes 2 1 0", "single, shifted 1 voxel", "chunked")


def _against_truth(workers: int) -> pd.DataFrame:
    """The fidelity benchmark's held-out synthetic cases (every family and noise level at
    its default counts), each run as one volume, with its axes reordered (the fidelity
    benchmark's own spread row), one voxel further into a larger array, and in blocks of
    :data:`TRUTH_BLOCK`³ on ``workers`` worker processes; every graph scored against the
    truth by the fidelity benchmark's ``score``, and against the single run at sigma = 1."""
    # Imported here: the worker processes import this script, and their memory is measured.
    import fidelity as F
    import pandas as pd

    counts = {family: n for family, (_, n) in F.FAMILIES.items()}
    cluster, client = _cluster(workers)
    rows = []
    try:
        for recipe in F.synthetic_recipes(counts, ["heldout"], 0, F.LEVELS):
            case = F.build(recipe)
            one = vesselflow.skeletonize(case.mask, spacing=case.spacing)
            far = vesselflow.skeletonize(np.pad(case.mask, ((1, 0),) * 3), spacing=case.spacing)
            graphs = [
                one,
                F.reordered_run(case, {}),
                vesselflow.VesselGraph(
                    far.positions - case.spacing, far.radii, far.edges, case.spacing
                ),
                vd.skeletonize(case.mask, spacing=case.spacing, chunks=TRUTH_BLOCK, client=client),
            ]
            for name, g in zip(TRUTH_GRAPHS, graphs):
                row = F.score(case, g, F.SIGMAS)
                rows.append(
                    {"case": f"{recipe.name} {recipe.level}".strip(), "graph": name}
                    | {k: row.get(k, np.nan) for k in TRUTH_RATES}
                    | {"from_single": netmets(one, g, 1.0)["gfnr"]}
                )
    finally:
        client.close()
        cluster.close()
    return pd.DataFrame(rows)


def _truth_report(df: pd.DataFrame) -> list[str]:
    """The section on the chunked graph against the truth."""
    import fidelity as F

    wide = df.pivot(index="case", columns="graph")
    n = len(wide)
    lines = [
        "",
        "## Against the truth",
        "",
        f"The fidelity benchmark's held-out synthetic cases ({n}: every family and noise "
        f"level at its default counts), in blocks of {TRUTH_BLOCK}³ (automatic halo), each "
        "scored against its truth by the fidelity benchmark's own scoring, at sigma = 2 "
        "voxels (its headline): is the chunked graph as right as the single run? Beside "
        "it, the single run on the mask with its axes reordered (the fidelity benchmark's "
        "spread row) and on the mask one voxel further into a larger array (another crop "
        "of the same data). Means over the cases; the last column is GFNR at sigma = 1 "
        "against the single run, as in the first table.",
        "",
        "| graph | " + " | ".join(TRUTH_RATES.values()) + " | GFNR from the single run |",
        "|---|" + "---|" * (len(TRUTH_RATES) + 1),
    ]
    for name in TRUTH_GRAPHS:
        means = [float(np.nanmean(wide[(k, name)])) for k in [*TRUTH_RATES, "from_single"]]
        lines.append(f"| {name} | " + " | ".join(f"{m:.4f}" for m in means) + " |")
    lines += [
        "",
        "Paired with the single run, case by case: the mean difference, its 95 % bootstrap "
        "interval and the cases in which the graph scores worse (a positive difference is "
        "worse for every column).",
        "",
        "| graph | " + " | ".join(TRUTH_RATES.values()) + " |",
        "|---|" + "---|" * len(TRUTH_RATES),
    ]
    for name in TRUTH_GRAPHS[1:]:
        cells = []
        for k in TRUTH_RATES:
            d = (wide[(k, name)] - wide[(k, "single")]).dropna().to_numpy()
            lo, hi = F.bootstrap_ci(d)
            cells.append(
                f"{d.mean():+.4f} [{lo:+.4f}, {hi:+.4f}], {int((d > 1e-12).sum())} of {len(d)}"
            )
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


#: The check of vessel ends near seams: (tube radius, block side, volume side), voxels.
ENDS_SETUPS = ((9.0, 32, 96), (6.0, 32, 96), (5.0, 32, 96), (9.0, 64, 160), (5.0, 64, 160))
#: Tubes per set-up, and how far from a seam (voxels) each of their ends lies at most.
ENDS_CASES = 16
ENDS_NEAR = 4.0


def _end_misses(g: Any, ends: tuple[Any, Any]) -> float:
    """The larger of the two true ends' distances to the graph's nearest end (inf when the
    graph has none)."""
    leaves = g.positions[np.bincount(g.edges.ravel(), minlength=g.n_nodes) == 1]
    if not len(leaves):
        return float("inf")
    return max(float(np.min(np.linalg.norm(leaves - e, axis=1))) for e in ends)


def _ends_near_seams(workers: int) -> list[dict[str, Any]]:
    """Straight tubes (capsules) whose two ends each lie within :data:`ENDS_NEAR` voxels of
    a seam, in random directions, in blocks of each set-up of :data:`ENDS_SETUPS`
    (automatic halo): how far the graph's ends lie from the true ones, single run against
    chunked run, and NetMets against the truth at sigma = 2."""
    cluster, client = _cluster(workers)
    rows = []
    try:
        for radius, block, n in ENDS_SETUPS:
            rng = np.random.default_rng(0)
            for _ in range(ENDS_CASES):
                ends = []
                for lo, seam in ((radius + 2, block), (n - radius - 22, n - block)):
                    e = rng.uniform(lo, lo + 20 - 1, 3)
                    e[rng.integers(3)] = seam + rng.uniform(-ENDS_NEAR, ENDS_NEAR)
                    ends.append(e)
                if rng.integers(2):
                    ends[0][1], ends[1][1] = ends[1][1], ends[0][1]
                mask, truth = cylinder((n, n, n), radius=radius, start=ends[0], end=ends[1])
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", UserWarning)  # blocks under BLOCK_RADII
                    graphs = {
                        "single": vesselflow.skeletonize(mask),
                        "chunked": vd.skeletonize(mask, chunks=block, client=client),
                    }
                for name, g in graphs.items():
                    nm = netmets(truth, g, 2.0)
                    rows.append(
                        {"radius": radius, "block": block, "graph": name}
                        | {"miss": _end_misses(g, (ends[0], ends[1])), "cfnr": nm["cfnr"]}
                        | {"gfnr": nm["gfnr"], "gfpr": nm["gfpr"]}
                    )
    finally:
        client.close()
        cluster.close()
    return rows


def _ends_report(rows: list[dict[str, Any]]) -> list[str]:
    """The section on vessel ends near seams."""
    import pandas as pd

    lines = [
        "",
        "## Vessel ends near seams",
        "",
        f"Straight tubes (capsules), {ENDS_CASES} per set-up, in random directions, each end "
        f"within {ENDS_NEAR:g} voxels of a seam, in blocks whose side spans a given number of "
        "the tube's radii (automatic halo): the farther of the two true ends from the "
        "graph's nearest end (per tube; median, mean and largest over the tubes, and the "
        "tubes where it exceeds 2 voxels), and NetMets against the truth at sigma = 2. "
        "`vesselflow.distributed` warns when a block spans fewer than "
        f"{vd.BLOCK_RADII} radii of the thickest vessel along an axis it cuts.",
        "",
        "| radius | block (radii) | graph | end off by: median / mean / largest | "
        "tubes > 2 voxels | GFNR | GFPR | CFNR |",
        "|---|---|---|---|---|---|---|---|",
    ]
    df = pd.DataFrame(rows)
    for (radius, block, name), part in df.groupby(["radius", "block", "graph"], sort=False):
        m = part["miss"].to_numpy()
        lines.append(
            f"| {radius:g} | {block} ({block / radius:.1f}) | {name} | "
            f"{np.median(m):.2f} / {m.mean():.2f} / {m.max():.2f} | "
            f"{int((m > 2).sum())} of {len(m)} | {part['gfnr'].mean():.4f} | "
            f"{part['gfpr'].mean():.4f} | {part['cfnr'].mean():.3f} |"
        )
    return lines


def _mb(x: float) -> str:
    return f"{x / 1e6:.0f} MB"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--block", type=int, default=128)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", default="benches/results/chunked.md")
    parser.add_argument("--size", type=int, default=256, help="bed size (the tiling is 2x2x1 beds)")
    args = parser.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="vf-chunked-"))
    n = args.size
    beds = [vascular_bed(n, seed=s) for s in range(4)]
    tiling = np.concatenate(
        [np.concatenate(beds[0:2], axis=0), np.concatenate(beds[2:4], axis=0)], axis=1
    )
    volumes = {f"bed {n}³": beds[0], f"tiling {2 * n}x{2 * n}x{n}": tiling}
    rows = []
    for name, mask in volumes.items():
        path = str(tmp / f"{len(rows)}.zarr")
        z = zarr.open_array(path, mode="w", shape=mask.shape, dtype=bool, chunks=(args.block,) * 3)
        z[...] = mask
        # The single run at the defaults, which a chunked run at the defaults reproduces.
        single, one = _single(path, tmp / f"{len(rows)}.npz", {})
        # The method's own spread: the single run with its solver's tolerance halved
        # and doubled (the same flow stopped a little earlier or later), on the same
        # mask with its axes reordered (the same flow, its arithmetic in another order)
        # and on the mask one voxel further into a larger array (another crop);
        # and what the sprouts add to a single run.
        npz = tmp / f"{len(rows)}s.npz"
        spread = (
            {
                f"single, cg_tol {tol:g}": _single(path, npz, {"cg_tol": tol})[1]
                for tol in (5e-5, 2e-4)
            }
            | {
                f"single, axes {' '.join(map(str, axes))}": _single(path, npz, {"axes": axes})[1]
                for axes in ([2, 1, 0], [1, 0, 2])
            }
            | {"single, shifted 1 voxel": _single(path, npz, {"shift": 1})[1]}
            | {"single, sprouts off": _single(path, npz, {"sprouts": False})[1]}
        )
        g, wall, peaks = _chunked(path, args.block, args.workers)
        g1, wall1, _ = _chunked(path, args.block, 1)
        killed, did_kill = _killed_run(path, args.block, args.workers, tmp / f"w{len(rows)}")
        parts = sorted((tmp / f"w{len(rows)}" / "blocks").glob("*.npz"))
        for p in parts[:3]:
            p.unlink()
        resumed, _, _ = _chunked(path, args.block, args.workers, workdir=tmp / f"w{len(rows)}")
        gap = _gap(path, mask.shape, one, g, args, npz) if not rows else None
        # Blocks twice as wide, where the volume holds more than one of them.
        bigger = None
        if max(mask.shape) > 2 * args.block:
            x, wall2, peaks2 = _chunked(path, 2 * args.block, args.workers)
            bigger = {"wall": wall2, "peaks": peaks2, "rates": netmets(one, x, 1.0)}
        rows.append(
            {
                "name": name,
                "shape": mask.shape,
                "fg": int(mask.sum()),
                "single": single,
                "g": g,
                "wall": wall,
                "wall1": wall1,
                "peaks": peaks,
                "compare": {"chunked": _compare(one, g)}
                | {k: _compare(one, x) for k, x in spread.items()},
                "deterministic": _same(g, g1),
                "killed": did_kill,
                "killed_same": _same(g, killed),
                "resumed": (resumed.info["blocks_computed"], resumed.info["blocks_reused"]),
                "resumed_same": _same(g, resumed),
                "gap": gap,
                "bigger": bigger,
            }
        )
        print(name, "done", time.strftime("%H:%M:%S"), flush=True)
    truth = _against_truth(args.workers)
    print("truth done", time.strftime("%H:%M:%S"), flush=True)
    ends = _ends_near_seams(args.workers)
    print("ends done", time.strftime("%H:%M:%S"), flush=True)
    Path(args.out).write_text(_report(rows, truth, ends, args))


def _gap_report(rows: list[dict[str, Any]], args: Any) -> list[str]:
    """The section on what the chunked run's distance from the single run is made of."""
    r = rows[0]
    gap = r["gap"]
    s = gap["seams"]
    lines = [
        "",
        "## What the distance from the single run is made of",
        "",
        f"{r['name']}: of the single run's centreline length, {100 * s['band']:.1f} % lies "
        f"within {SEAM_BAND:g} voxels of a seam; there {100 * s['far_in_band']:.1f} % of it is "
        f"farther than 1 voxel from the chunked graph, beyond that band "
        f"{100 * s['far_beyond']:.1f} %. The same chunked run with other halos (NetMets at "
        "sigma = 1 against the single run, as above), and with both runs held to one "
        "contraction schedule (an iteration cap below what any run takes when free, every "
        f"solve tight; the single run then stopped after {gap['iterations']} iterations):",
        "",
        "| chunked run | GFNR | GFPR | CFNR | CFPR | wall |",
        "|---|---|---|---|---|---|",
    ]
    for what, rt, wall in [
        (f"halo {r['g'].info['halo']} (automatic)", r["compare"]["chunked"]["rates"], r["wall"])
    ] + gap["halos"]:
        lines.append(
            f"| {what} | {rt['gfnr']:.4f} | {rt['gfpr']:.4f} | {rt['cfnr']:.4f} | "
            f"{rt['cfpr']:.4f} | {wall:.1f} s |"
        )
    big = [x for x in rows if x["bigger"] is not None]
    if big:
        lines += [
            "",
            f"Blocks of {2 * args.block}³ instead (automatic halo, {args.workers} workers):",
            "",
            "| volume | chunked wall / time ratio | worker peak RSS | GFNR | GFPR | CFNR | CFPR |",
            "|---|---|---|---|---|---|---|",
        ]
        for x in big:
            b, rt = x["bigger"], x["bigger"]["rates"]
            lines.append(
                f"| {x['name']} | {b['wall']:.1f} s / {b['wall'] / x['single']['wall']:.2f}x | "
                f"{', '.join(_mb(p) for p in b['peaks'])} | {rt['gfnr']:.4f} | "
                f"{rt['gfpr']:.4f} | {rt['cfnr']:.4f} | {rt['cfpr']:.4f} |"
            )
    return lines


def _report(
    rows: list[dict[str, Any]], truth: pd.DataFrame, ends: list[dict[str, Any]], args: Any
) -> str:
    lines = [
        "# Chunked runs on Dask against the single run",
        "",
        f"Generated by `python benches/chunked.py --block {args.block} --workers "
        f"{args.workers}` on {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
        f"{os.cpu_count()} cores (shared). Blocks of {args.block}³, halo automatic.",
        "",
        "Each graph against the single run at the default parameters (sprouts on; the "
        "chunked run's blocks grow them and the merge attaches them). NetMets at sigma = 1 "
        "voxel, and its false negative rates at sigma = 2 (the fidelity benchmark's "
        "headline tolerance) beside them. The rows `single, ...` are the method's own "
        "spread: the single run again with its solver's tolerance halved or doubled "
        "(default 1e-4), i.e. the same flow stopped a little earlier or later; and the "
        "single run on the same mask with its axes in another order (positions put back), "
        "i.e. the same flow with its sums in another order: its nodes are numbered, its "
        "rows ordered and its ties broken differently. A chunked run, whose blocks number "
        "and order their nodes their own way, cannot be expected closer to the single run "
        "than the single run is to itself with its axes reordered. The row `single, "
        "shifted 1 voxel` is the single run on the mask one voxel further into a larger "
        "array (a background slab before each axis, positions shifted back): another crop "
        "of the same data. The row `single, sprouts off` is what the sprouts add to a "
        "single run.",
        "",
        "| volume | graph | components 1 / this | cycle rank 1 / this | GFNR | GFPR | CFNR "
        "| CFPR | GFNR / CFNR at sigma = 2 | nodes 1 / this | matched nodes (≤ 1 voxel) | "
        "radius rel. diff. median / mean | matched radii within 2 % |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        for what, c in r["compare"].items():
            (c1, k1), (c2, k2) = c["topology"]
            rt, r2 = c["rates"], c["rates2"]
            lines.append(
                f"| {r['name']} | {what} | {c1} / {c2} | {k1} / {k2} | {rt['gfnr']:.4f} | "
                f"{rt['gfpr']:.4f} | {rt['cfnr']:.4f} | {rt['cfpr']:.4f} | "
                f"{r2['gfnr']:.4f} / {r2['cfnr']:.4f} | "
                f"{c['nodes'][0]} / {c['nodes'][1]} | {c['matched']:.3f} | "
                f"{100 * c['radius_median']:.2f} % / {100 * c['radius_mean']:.2f} % | "
                f"{100 * c['radius_within_2pc']:.1f} % |"
            )
    lines += [
        "",
        "| volume | fg voxels | blocks (empty) | halo | chunked (2 workers): per-chunk pass / "
        "blocks / merge / routing |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        info = r["g"].info
        sec = info["seconds"]
        lines.append(
            f"| {r['name']} | {r['fg']} | {info['blocks']} ({info['blocks_empty']}) | "
            f"{info['halo']} | {sec['chunk_pass']:.1f} s / {sec['blocks']:.1f} s / "
            f"{sec['merge']:.1f} s / {sec['route']:.1f} s |"
        )
    lines += [
        "",
        "| volume | single: wall / peak RSS | chunked: wall (2 workers) / (1 worker) | "
        "worker peak RSS | time ratio (2 workers) |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        s = r["single"]
        lines.append(
            f"| {r['name']} | {s['wall']:.1f} s / {_mb(s['peak'])} | {r['wall']:.1f} s / "
            f"{r['wall1']:.1f} s | {', '.join(_mb(p) for p in r['peaks'])} | "
            f"{r['wall'] / s['wall']:.2f}x |"
        )
    lines += [
        "",
        "| volume | deterministic (2 vs 1 worker) | worker killed: same graph | "
        "resume: blocks computed / reused, same graph |",
        "|---|---|---|---|",
    ]
    for r in rows:
        c, u = r["resumed"]
        lines.append(
            f"| {r['name']} | {r['deterministic']} | {r['killed'] and r['killed_same']} | "
            f"{c} / {u}, {r['resumed_same']} |"
        )
    lines += _gap_report(rows, args)
    lines += _truth_report(truth)
    lines += _ends_report(ends)
    a, b = rows[0], rows[-1]
    blocks = [max(r["g"].info["blocks_computed"], 1) for r in (a, b)]
    per_block = [r["wall1"] / n for r, n in zip((a, b), blocks)]
    density = b["fg"] / np.prod(b["shape"])
    lines += [
        "",
        "## Scaling law and projections",
        "",
        f"Time per {args.block}³ block on one worker: {per_block[0]:.2f} s ({a['name']}) and "
        f"{per_block[1]:.2f} s ({b['name']}); worker peak RSS "
        f"{_mb(max(a['peaks']))} and {_mb(max(b['peaks']))} (4x the volume: "
        f"{max(b['peaks']) / max(a['peaks']):.2f}x); the single run's peak grows "
        f"{b['single']['peak'] / a['single']['peak']:.2f}x.",
        "The block phase is linear in the blocks: time = blocks x t_block / workers; the "
        "merge (one process) is linear in the cells (centreline nodes) and face voxels.",
        "",
        f"| volume | blocks of {args.block}³ (at this density) | 1 worker | 64 workers "
        "| 512 workers |",
        "|---|---|---|---|---|",
    ]
    t_block = per_block[1]
    for n in (2048, 10000):
        nb = (n / args.block) ** 3
        lines.append(
            f"| {n}³ | {nb:.0f} | {nb * t_block / 3600:.1f} h | {nb * t_block / 64 / 3600:.2f} h "
            f"| {nb * t_block / 512 / 3600:.2f} h |"
        )
    lines += [
        "",
        f"At {100 * density:.1f} % foreground. The merge holds every cell and face voxel in one "
        "process: about 120 bytes per centreline node; 2048³ at 5 % (≈ 430 M vessel voxels, "
        "≈ 15 M nodes) needs a few GB there, 10000³ (≈ 2 G nodes) does not fit one process "
        "and needs the merge itself split by region (not done).",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
