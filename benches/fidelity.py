"""Fidelity benchmark: vesselflow and its peers against ground truth, on seeds it was not
tuned on.

One command::

    python benches/fidelity.py                         # the full report (tuning + held-out + real)
    python benches/fidelity.py --quick                 # a ~2 minute guard (prints, writes nothing)
    python benches/fidelity.py --set tuning --no-real  # what defaults may be chosen on

writes ``fidelity.md`` (and ``fidelity_rows.csv``, every number behind it, plus one PNG per
dataset) to ``--out``; ``--sweep`` also runs the sensitivity sweep (tuning set only) into
``sensitivity.md``.

Seeds. Every synthetic family draws its volumes from two fixed, disjoint seed sets:
``tuning`` (seeds 0, 1, 2, ...) and ``heldout`` (seeds 1000, 1001, ...). Defaults may be
chosen on the tuning set only (``--sweep`` runs on it); the report's headline is the held-out
set. ``--set`` picks one or both (default both).

Synthetic families (:data:`FAMILIES`; each noisy one at the paper's bubble-noise levels D0, D1
and D2, ``vesselflow.synth.add_bubble_noise``, noise seed = 10000 + volume seed):
    - ``forest``: ``vesselflow.synth.vascular_forest`` at 128³, the independently written
      family: space-colonisation trees from the faces inward, Murray-like radii 6.5 -> 1.5
      voxels with a 6 % ripple that is part of the truth radius, anastomoses, touching and
      crossing vessels, thick vessels with thin side branches; voxel-centre rasterisation;
    - ``lattice``: ``vesselflow.synth.capillary_network`` at 96³ with radii 1.4-2.4, jitter
      and bend 0.2, voxel-centre rasterisation (``supersample=1``), clean: a loopy, curved,
      jittered capillary lattice whose mask has as many loops as the truth's cycle rank;
    - ``tree``: ``vesselflow.synth.vascular_tree`` (CCO, VascuSynth-like, partial-volume
      rasterisation) at 128³/160³/192³ with 16/32/64 terminals, the paper's own kind of set;
    - ``capillary``: ``vesselflow.synth.capillary_network`` with its defaults (partial
      volume), clean.

Real and third-party volumes in ``../shared/data`` (read in place, never copied: several are
licensed for evaluation only; ``--no-real`` skips them, and the package never needs them):
the vmtk CT aorta at two resolutions, the VascuSynth trees (segments thinner than half a voxel
dropped from the truth, as the data README advises), the vesselsynth volumes (a voxel skeleton
as truth: geometry only), and masks without truth (two-photon, light-sheet, the authors' demo
volumes): topology and time only.

Methods are those of ``vesselflow.compare``; one that is not installed is reported, not run.

Metrics (``vesselflow.metrics``) at ``sigma`` = 2 base cells (the smallest voxel spacing; the
headline) and NetMets at 3 beside it (``--sigmas``): NetMets proper (GFNR, GFPR, CFNR,
CFPR), the authors' VascGraph variant and DIADEM on CCO trees and real trees, radius bias and
MAPE over graph nodes within sigma of the truth (all, and per radius band 1-2, 2-3, 3-5,
5-10 voxels), true junctions with a graph node and with a graph junction (degree >= 3)
within sigma, the graph's cycle rank against
the first Betti number of the noise-free mask, edge length outside the mask, nodes outside
the mask dilated by one voxel, and graph components against 26-connected mask components.

Cases run in ``--jobs`` worker processes, each method single-threaded, so every method's
time is one core's.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import os
import platform
import sys
import time
import traceback
from collections.abc import Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

import vesselflow
from vesselflow import VesselGraph, compare, metrics, synth

sys.path.insert(0, str(Path(__file__).resolve().parent))
from synthetic import write_atomic  # benches/ is not a package: its folder is on the path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DATA = ROOT.parent / "shared" / "data"


def _extension() -> str:
    """Which compiled core this process loaded (workers fork from it, so theirs too)."""
    path = Path(vesselflow._core.__file__ or "")
    try:
        built = datetime.datetime.fromtimestamp(path.stat().st_mtime, datetime.timezone.utc)
    except OSError:
        return f"{path.name} (replaced since it was loaded)"
    return f"{path.name} built {built:%Y-%m-%d %H:%M} UTC"


#: Recorded at import, before any worker starts: a rebuild during a run does not change it.
EXTENSION = _extension()

LEVELS = ("D0", "D1", "D2")
#: First seed of each seed set; a family's i-th volume of a set has seed ``start + i``.
SEED_SETS = {"tuning": 0, "heldout": 1000}
#: Noise seed = NOISE_SEED + volume seed.
NOISE_SEED = 10000
#: Synthetic families: noisy (D0-D2) or clean, and how many volumes per set by default.
FAMILIES = {"forest": (True, 8), "lattice": (False, 3), "tree": (True, 3), "capillary": (False, 2)}
FOREST_SHAPE = (128, 128, 128)
LATTICE_SHAPE = (96, 96, 96)
TREE_SHAPES = (128, 160, 192)
TREE_TERMINALS = (16, 32, 64)
CAPILLARY_SHAPE = (96, 96, 96)
#: Methods too slow for every case (CGAL's mesh skeleton: 2-80 s per volume): they run on
#: the first ``--slow-cases`` volumes of each family, level and set and one volume per real
#: dataset, and the report says so.
SLOW_METHODS = ("mesh", "pointcloud")
#: Tolerances (base cells): the first is the headline.
SIGMAS = (2.0, 3.0)
#: Bootstrap resamples for the spread of the held-out means.
BOOTSTRAP = 2000
#: vesselflow again on every held-out synthetic mask with its axes in this order (the
#: positions put back): the same flow with its arithmetic in another order, whose paired
#: difference is the method's own run-to-run spread (a row of its own in the CSV).
REORDER = (2, 1, 0)
REORDERED = "vesselflow, axes " + " ".join(map(str, REORDER))

#: Real volumes with a centreline graph.
REAL_GRAPH_TRUTH = (
    "aorta_ct_04mm",
    "aorta_ct_03mm",
    "vascusynth_seed1_n200_200",
    "vascusynth_seed2_n250_200",
    "vascusynth_seed1_n100_100",
    "vascusynth_seed1_n200_100",
    "vascusynth_seed2_n250_100",
    "vascusynth_seed3_n500_100",
    "vascusynth_seed4_n1000_100",
)
REAL_SKELETON_TRUTH = ("vesselsynth_0001", "vesselsynth_0004")
REAL_NO_TRUTH = (
    "damseh_synth1",
    "damseh_synth2",
    "lightsheet_vesselexpress_100",
    "tpm_poon2015_mixedSize1",
    "tpm_santos2015_mixedSizelowContrastVessels",
    "tpm_burgess2014_tgMouse",
)
#: VascuSynth segments thinner than this many voxels are not resolved by the masks.
VASCUSYNTH_MIN_RADIUS = 0.5

#: The paper's Table I, (mean, sd) per level: its "Proposed" and "Voxel-based" columns.
PAPER_TABLE_I = {
    "Proposed (paper)": {
        "gfnr": ((0.22, 0.03), (0.20, 0.02), (0.26, 0.03)),
        "gfpr": ((0.12, 0.02), (0.16, 0.03), (0.17, 0.03)),
        "cfnr": ((0.23, 0.06), (0.28, 0.07), (0.26, 0.05)),
        "cfpr": ((0.08, 0.02), (0.11, 0.04), (0.10, 0.03)),
        "diadem": ((74.8, 7.29), (71.7, 6.42), (67.1, 8.15)),
        "mape": ((11.3, 1.67), (12.1, 1.87), (12.7, 1.43)),
    },
    "Voxel-based (paper)": {
        "gfnr": ((0.15, 0.01), (0.27, 0.03), (0.41, 0.09)),
        "gfpr": ((0.11, 0.02), (0.28, 0.05), (0.33, 0.06)),
        "cfnr": ((0.27, 0.05), (0.24, 0.05), (0.17, 0.03)),
        "cfpr": ((0.07, 0.03), (0.27, 0.06), (0.57, 0.11)),
        "diadem": ((65.1, 8.22), (54.1, 13.5), (42.4, 7.06)),
        "mape": ((13.4, 0.84), (14.1, 1.34), (14.8, 1.84)),
    },
}

#: DIADEM's path-length tolerance.
DIADEM_PATH_THRESHOLD = 0.2
DIADEM_NOTE = (
    "DIADEM is computed in 3-D (no z axis: these volumes are isotropic), with node thresholds "
    "= sigma and a path-length threshold of 0.2 (the jar's defaults, 0.08 in xy and 0.2 in z, "
    "are for neurons). It is brittle on dense polylines: the truth itself with 0.3-voxel "
    "Gaussian jitter on its nodes scores only 0.24 (its path lengths grow past the threshold), "
    "so its numbers are not comparable with the paper's and are not used to rank settings."
)

#: Metric columns: name, label, True when higher is better.
GEOMETRY = ("gfnr", "gfpr", "cfnr", "cfpr")
METRIC_LABELS = {
    "gfnr": "GFNR ↓",
    "gfpr": "GFPR ↓",
    "cfnr": "CFNR ↓",
    "cfpr": "CFPR ↓",
    "v_gfnr": "GFNR ↓",
    "v_gfpr": "GFPR ↓",
    "v_cfnr": "CFNR ↓",
    "v_cfpr": "CFPR ↓",
    "diadem": "DIADEM (%) ↑",
    "mape": "MAP (%) ↓",
    "bias": "radius bias (%)",
    "mape_norm": "MAP, normalised (%) ↓",
    "junctions": "junctions found ↑",
    "junction_nodes": "junctions met by a junction ↑",
    "loop_error": "loop error (% of clean-mask loops) ↓",
    "edge_outside": "edge length outside mask (%) ↓",
    "nodes_outside": "nodes outside dilated mask ↓",
    "components_equal": "components 1:1 ↑",
    "seconds": "time (s) ↓",
}
HIGHER_IS_BETTER = {"diadem", "junctions", "junction_nodes", "components_equal"}
#: Radius bands (voxels) of the per-band table.
BANDS = tuple(f"{lo:g}-{hi:g}" for lo, hi in metrics.RADIUS_BANDS)


@dataclass(frozen=True)
class Recipe:
    """How a worker builds one case (volumes are made where they are used)."""

    dataset: str
    name: str
    level: str = ""
    seed: int = 0
    #: ``tuning`` or ``heldout`` for synthetic cases, ``real`` otherwise.
    seed_set: str = "real"
    index: int = 0
    figure: bool = False
    #: Run the slow methods (``SLOW_METHODS``) on this case too.
    slow: bool = False


@dataclass
class Case:
    dataset: str
    name: str
    level: str
    mask: np.ndarray
    spacing: np.ndarray
    truth: VesselGraph | None
    tree: bool
    graph_truth: bool = True
    #: First Betti number of the noise-free mask: the loop target.
    clean_loops: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def synthetic_recipes(
    counts: dict[str, int], seed_sets: Sequence[str], slow_cases: int, levels: Sequence[str]
) -> list[Recipe]:
    """The synthetic cases: ``counts[family]`` volumes of each family per seed set, at every
    noise level for noisy families; figures from the first held-out volume (else tuning)."""
    out = []
    figure_set = "heldout" if "heldout" in seed_sets else seed_sets[0]
    for seed_set in seed_sets:
        for family, (noisy, _) in FAMILIES.items():
            for i in range(counts.get(family, 0)):
                seed = SEED_SETS[seed_set] + i
                for level in levels if noisy else ("",):
                    first = seed_set == figure_set and i == 0 and level in ("", "D1")
                    out.append(
                        Recipe(
                            family,
                            f"{family}{seed:04d}",
                            level,
                            seed,
                            seed_set,
                            i,
                            first,
                            i < slow_cases,
                        )
                    )
    return out


def real_recipes() -> list[Recipe]:
    """Every volume of ``../shared/data`` this report knows, in a fixed order."""
    out = []
    seen: set[str] = set()
    for name in REAL_GRAPH_TRUTH + REAL_SKELETON_TRUTH + REAL_NO_TRUTH:
        if (DATA / f"{name}.npz").exists():
            dataset = real_dataset(name)
            first = dataset not in seen
            # The two-photon stacks are 0.6-1.4 M voxels: too big for the mesh skeleton.
            out.append(Recipe(dataset, name, figure=first, slow=first and dataset != "tpm"))
            seen.add(dataset)
    return out


def real_dataset(name: str) -> str:
    return name.split("_")[0]


def thin_leaves(truth: VesselGraph, min_radius: float) -> VesselGraph:
    """Drop leaf nodes thinner than ``min_radius``, repeatedly (the tree stays connected)."""
    keep = np.ones(truth.n_nodes, bool)
    edges = truth.edges
    while True:
        live = keep[edges[:, 0]] & keep[edges[:, 1]]
        degree = np.bincount(edges[live].ravel(), minlength=truth.n_nodes)
        drop = keep & (degree == 1) & (truth.radii < min_radius)
        if not drop.any() or drop.sum() >= keep.sum() - 1:
            break
        keep &= ~drop
    index = np.cumsum(keep) - 1
    live = keep[edges[:, 0]] & keep[edges[:, 1]]
    return VesselGraph(truth.positions[keep], truth.radii[keep], index[edges[live]], truth.spacing)


def skeleton_graph(skeleton: np.ndarray, spacing: np.ndarray) -> VesselGraph:
    """A voxel skeleton as a graph: one node per voxel, edges to 26-neighbours."""
    ijk = np.argwhere(skeleton)
    index = np.full(skeleton.shape, -1, np.int64)
    index[tuple(ijk.T)] = np.arange(len(ijk))
    padded = np.pad(index, 1, constant_values=-1)
    edges = []
    for off in np.argwhere(np.ones((3, 3, 3), bool)) - 1:
        if tuple(off) <= (0, 0, 0):
            continue
        nb = padded[tuple((ijk + 1 + off).T)]
        hit = nb >= 0
        edges.append(np.stack([np.flatnonzero(hit), nb[hit]], axis=1))
    return VesselGraph(ijk * spacing, np.ones(len(ijk)), np.concatenate(edges), spacing)


def build(recipe: Recipe) -> Case:
    if recipe.dataset in FAMILIES:
        return build_synthetic(recipe)
    with np.load(DATA / f"{recipe.name}.npz") as d:
        mask = d["mask"].astype(bool)
        spacing = np.asarray(d["spacing"], np.float64)
        if "gt_pos" in d.files:
            truth = VesselGraph(d["gt_pos"], d["gt_radius"], d["gt_edges"], spacing)
            if recipe.dataset == "vascusynth":
                truth = thin_leaves(truth, VASCUSYNTH_MIN_RADIUS * spacing.min())
            return Case(recipe.dataset, recipe.name, "", mask, spacing, truth, tree=True)
        if "gt_skeleton" in d.files:
            truth = skeleton_graph(d["gt_skeleton"].astype(bool), spacing)
            return Case(
                recipe.dataset, recipe.name, "", mask, spacing, truth, tree=False, graph_truth=False
            )
    return Case(recipe.dataset, recipe.name, "", mask, spacing, None, tree=False)


def build_synthetic(recipe: Recipe) -> Case:
    """One synthetic volume: the clean mask's loops are measured before the noise."""
    seed = recipe.seed
    if recipe.dataset == "forest":
        clean, truth = synth.vascular_forest(FOREST_SHAPE, seed=seed)
    elif recipe.dataset == "lattice":
        clean, truth = synth.capillary_network(
            LATTICE_SHAPE, seed=seed, radius=(1.4, 2.4), jitter=0.2, bend=0.2, supersample=1
        )
    elif recipe.dataset == "tree":
        shape = (TREE_SHAPES[recipe.index % 3],) * 3
        terminals = TREE_TERMINALS[(recipe.index // 3) % 3]
        clean, truth = synth.vascular_tree(shape, n_terminals=terminals, seed=seed)
    else:
        clean, truth = synth.capillary_network(CAPILLARY_SHAPE, seed=seed)
    loops = int(metrics.topology(clean, truth)["mask_loops"])
    mask = (
        synth.add_bubble_noise(clean, recipe.level, seed=NOISE_SEED + seed)
        if recipe.level
        else clean
    )
    return Case(
        recipe.dataset,
        recipe.name,
        recipe.level,
        mask,
        truth.spacing,
        truth,
        tree=recipe.dataset == "tree",
        clean_loops=loops,
    )


def score(case: Case, graph: VesselGraph, sigmas: Sequence[float]) -> dict[str, Any]:
    """Every metric of one graph against its case; ``sigmas[0]`` is the headline tolerance."""
    row: dict[str, Any] = {}
    topo = metrics.topology(case.mask, graph)
    row.update(
        mask_components=topo["mask_components"],
        graph_components=topo["graph_components"],
        components_equal=topo["components_equal"],
        mask_loops=topo["mask_loops"],
        graph_cycles=topo["graph_cycles"],
    )
    clean = topo["mask_loops"] if case.clean_loops is None else case.clean_loops
    row.update(
        clean_loops=clean,
        loop_diff=abs(topo["graph_cycles"] - clean),
    )
    inside = metrics.mask_fidelity(case.mask, graph)
    row.update(
        nodes_outside=inside["nodes_outside_dilated"],
        edge_outside=100.0 * inside["edge_outside"],
    )
    if case.truth is None:
        return row
    base = float(np.min(case.spacing))
    sigma = sigmas[0] * base
    for k, s in enumerate(sigmas):
        nm = metrics.netmets(case.truth, graph, s * base)
        suffix = "" if k == 0 else f"_s{s:g}"
        row.update({f"gfnr{suffix}": nm["gfnr"], f"gfpr{suffix}": nm["gfpr"]})
        if case.graph_truth:
            row.update({f"cfnr{suffix}": nm["cfnr"], f"cfpr{suffix}": nm["cfpr"]})
    if not case.graph_truth:
        return row
    # Connectivity with the truth's junctions closer than sigma joined (report section
    # "Connectivity at the resolution of sigma"), and how many junctions that joins.
    joined_truth = metrics.join_close_junctions(case.truth, sigma)
    joined = metrics.netmets(joined_truth, graph, sigma)
    row.update(cfnr_joined=joined["cfnr"], cfpr_joined=joined["cfpr"])
    row["close_junctions"] = int(np.count_nonzero(case.truth.degrees() >= 3)) - int(
        np.count_nonzero(joined_truth.degrees() >= 3)
    )
    junctions = metrics.junction_recall(case.truth, graph, sigma)
    row.update(truth_junctions=junctions["n_junctions"], junctions=junctions["recall"])
    row["junction_nodes"] = junctions_met(case.truth, graph, sigma)
    row["truth_cycles"] = case.truth.n_edges - case.truth.n_nodes + components(case.truth)
    if graph.n_nodes:
        err = metrics.radius_error(case.truth, graph, sigma)
        row["mape"] = err["mape"]
        row["bias"] = metrics.radius_bands(case.truth, graph, sigma, ((0.0, np.inf),))["0-inf"][
            "bias"
        ]
        bands = metrics.radius_bands(case.truth, graph, sigma)
        for band, b in bands.items():
            row.update({f"n_{band}": b["n"], f"bias_{band}": b["bias"], f"mape_{band}": b["mape"]})
    if case.dataset in FAMILIES and case.dataset != "tree":
        return row
    vg = metrics.netmets(case.truth, graph, sigma, mode="vascgraph")
    row.update({f"v_{k}": vg[k] for k in GEOMETRY})
    if graph.n_nodes:
        row["mape_norm"] = metrics.radius_error(case.truth, graph, sigma, normalised=True)["mape"]
    if case.tree:
        row["diadem"] = 100.0 * metrics.diadem(
            case.truth,
            graph,
            xy_threshold=sigma,
            z_threshold=sigma,
            xy_path_thresh=DIADEM_PATH_THRESHOLD,
            z_axis=None,
        )
    return row


def junctions_met(truth: VesselGraph, graph: VesselGraph, sigma: float) -> float:
    """Share of true junctions (truth nodes of degree >= 3) with a graph junction (a graph
    node of degree >= 3) within ``sigma``: stricter than ``metrics.junction_recall``, which
    counts any graph node (a junction one node along a branch passes it)."""
    degree = np.bincount(graph.edges.ravel(), minlength=graph.n_nodes)
    nodes = graph.positions[degree >= 3]
    return metrics.junction_recall(
        truth,
        VesselGraph(nodes, graph.radii[degree >= 3], np.empty((0, 2), np.int64), graph.spacing),
        sigma,
    )["recall"]


def components(graph: VesselGraph) -> int:
    import networkx as nx

    return int(nx.number_connected_components(graph.to_networkx())) if graph.n_nodes else 0


_WARM: set[str] = set()


def warm_up(methods: Sequence[str]) -> None:
    """Run each method once on a tiny volume in this process, so one-off costs (skan's
    numba compilation: about 8 s) are not charged to the first case."""
    tiny = np.zeros((9, 9, 9), bool)
    tiny[2:7, 3:6, 3:6] = True
    for method in set(methods) - _WARM - set(SLOW_METHODS) - {REORDERED}:
        compare.run(method, tiny)
        _WARM.add(method)


def evaluate(
    recipe: Recipe,
    methods: Sequence[str],
    sigmas: Sequence[float],
    params: dict[str, Any] | None = None,
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Run ``methods`` on one case and score them; the figure's material when asked for."""
    case = build(recipe)
    warm_up(methods)
    base = {
        "dataset": case.dataset,
        "case": case.name,
        "level": case.level,
        "set": recipe.seed_set,
        "seed": recipe.seed if recipe.dataset in FAMILIES else np.nan,
        "foreground": int(case.mask.sum()),
        "shape": "x".join(map(str, case.mask.shape)),
    }
    rows, figure = [], {}
    for method in methods:
        if method in SLOW_METHODS and not recipe.slow:
            continue
        if method == REORDERED and (recipe.dataset not in FAMILIES or recipe.seed_set != "heldout"):
            continue
        row = dict(base, method=method)
        try:
            options = {"threads": 1, **(params or {})} if method.startswith("vesselflow") else {}
            if method == REORDERED:
                graph = reordered_run(case, options)
            else:
                graph = compare.run(method, case.mask, case.spacing, **options)
            row.update(seconds=graph.info["seconds"], nodes=graph.n_nodes, edges=graph.n_edges)
            if method.startswith("vesselflow"):
                row.update(
                    iterations=graph.info["iterations"],
                    converged=graph.info["converged"],
                    stalled=graph.info["stalled"],
                )
            row.update(score(case, graph, sigmas))
            if recipe.figure and method != REORDERED:
                figure[method] = graph
        except Exception as exc:  # a failing method is a row, not a crash of the report
            row["error"] = f"{type(exc).__name__}: {exc}".splitlines()[0][:200]
            traceback.print_exc()
        rows.append(row)
    if recipe.figure:
        figure["_mask"] = case.mask
        figure["_truth"] = case.truth
    return rows, figure


def reordered_run(case: Case, options: dict[str, Any]) -> VesselGraph:
    """vesselflow on ``case``'s mask with its axes in the order :data:`REORDER`, the
    graph's positions put back in the mask's own axis order, and with the mask's spacing
    (without it an anisotropic case would be scored as if its voxels were cubes)."""
    axes = list(REORDER)
    mask = np.ascontiguousarray(case.mask.transpose(axes))
    graph = compare.run("vesselflow", mask, np.asarray(case.spacing)[axes], **options)
    back = VesselGraph(
        graph.positions[:, np.argsort(axes)], graph.radii, graph.edges, case.spacing, graph.info
    )
    return back


def run_all(
    todo: Sequence[Recipe],
    methods: Sequence[str],
    sigmas: Sequence[float],
    jobs: int,
    params: dict[str, Any] | None = None,
    label: str = "",
) -> tuple[pd.DataFrame, dict[str, dict[str, Any]]]:
    rows, figures = [], {}
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        futures = [pool.submit(evaluate, r, methods, sigmas, params) for r in todo]
        for k, (recipe, fut) in enumerate(zip(todo, futures)):
            case_rows, figure = fut.result()
            rows.extend(case_rows)
            if figure:
                figures[recipe.dataset] = figure
            done = ", ".join(
                f"{r['method']} {r.get('seconds', float('nan')):.1f}s" for r in case_rows
            )
            print(f"[{label}{k + 1}/{len(todo)}] {recipe.name} {recipe.level} {done}", flush=True)
    return pd.DataFrame(rows), figures


# ----------------------------------------------------------------------------- report


def mean_sd(values: pd.Series, digits: int) -> tuple[float, str]:
    v = values.dropna().astype(float)
    if v.empty:
        return np.nan, "-"
    return float(v.mean()), f"{v.mean():.{digits}f} ± {v.std(ddof=0):.{digits}f}"


def digits_for(metric: str) -> int:
    return 1 if metric in ("diadem", "mape", "mape_norm", "bias", "seconds") else 2


def best(means: Sequence[float], metric: str) -> int:
    arr = np.array(means, float)
    if np.all(np.isnan(arr)):
        return -1
    return int(np.nanargmax(arr) if metric in HIGHER_IS_BETTER else np.nanargmin(arr))


def ok_rows(part: pd.DataFrame) -> pd.DataFrame:
    """Rows of methods that ran (no ``error``)."""
    return part[part["error"].isna()] if "error" in part else part


def group_of(df: pd.DataFrame) -> pd.Series:
    """``forest D1``, ``lattice``, ...: a synthetic family and its noise level."""
    return (df.dataset + " " + df.level.fillna("")).str.strip()


def loop_error(part: pd.DataFrame) -> float:
    """Summed ``|graph cycles - clean-mask loops|`` as a percentage of the summed clean-mask
    loops (the issue's loop target)."""
    clean = float(part.clean_loops.sum())
    return 100.0 * float(part.loop_diff.sum()) / clean if clean else np.nan


#: Columns of the headline table: (key, header, how to reduce a group's rows, digits).
HEADLINE = (
    ("gfnr", "GFNR ↓", "mean", 3),
    ("gfpr", "GFPR ↓", "mean", 3),
    ("cfnr", "CFNR ↓", "mean", 3),
    ("cfpr", "CFPR ↓", "mean", 3),
    ("mape", "MAPE % ↓", "mean", 1),
    ("bias", "radius bias %", "mean", 1),
    ("components_equal", "components 1:1 ↑", "count", 0),
    ("loops", "cycles / clean-mask loops", "loops", 0),
    ("loop_error", "loop error % ↓", "loop_error", 0),
    ("junctions", "junctions found % ↑", "percent", 0),
    ("junction_nodes", "met by a junction % ↑", "percent", 0),
    ("edge_outside", "edge length outside % ↓", "mean", 2),
    ("nodes_outside", "cases with a node outside dilated mask ↓", "count_positive", 0),
    ("seconds", "time s", "mean", 2),
)


def reduce_column(part: pd.DataFrame, key: str, how: str, digits: int) -> tuple[float, str]:
    """One cell of a summary table: its value (for picking the best) and its text."""
    if not len(part):
        return np.nan, "-"
    if how == "count":
        n = int(part[key].fillna(False).astype(bool).sum())
        return float(n) / len(part), f"{n}/{len(part)}"
    if how == "count_positive":
        n = int((part[key].fillna(0) > 0).sum())
        return float(n) / len(part), f"{n}/{len(part)}"
    if how == "loops":
        return np.nan, f"{part.graph_cycles.mean():.1f} / {part.clean_loops.mean():.1f}"
    if how == "loop_error":
        v = loop_error(part)
        return v, "-" if np.isnan(v) else f"{v:.0f}"
    if key not in part or part[key].isna().all():
        return np.nan, "-"
    v = float(part[key].mean()) * (100.0 if how == "percent" else 1.0)
    return v, f"{v:.{digits}f}"


def headline_table(df: pd.DataFrame, methods: Sequence[str]) -> str:
    """Rows: family (and level) x method; columns: :data:`HEADLINE`, means over the cases;
    the best method of each family in bold."""
    lines = [
        "| family | method | cases | " + " | ".join(h for _, h, _, _ in HEADLINE) + " |",
        "|---|---|---:|" + "---:|" * len(HEADLINE),
    ]
    for group, part in df.groupby(group_of(df), sort=False):
        cells: dict[str, list[str]] = {}
        for key, _, how, digits in HEADLINE:
            values, texts = [], []
            for method in methods:
                v, text = reduce_column(ok_rows(part[part.method == method]), key, how, digits)
                values.append(v)
                texts.append(text)
            pick = key if key not in ("bias", "seconds", "loops") else ""
            if key == "bias":
                values = [abs(v) for v in values]
                pick = "mape"
            bold = best(values, pick) if pick else -1
            cells[key] = [f"**{t}**" if i == bold and t != "-" else t for i, t in enumerate(texts)]
        for i, method in enumerate(methods):
            n = len(ok_rows(part[part.method == method]))
            if not len(part[part.method == method]):
                continue
            row = " | ".join(cells[key][i] for key, _, _, _ in HEADLINE)
            lines.append(f"| {group} | {method} | {n} | {row} |")
    return "\n".join(lines) + "\n"


def versus_table(df: pd.DataFrame, methods: Sequence[str]) -> str:
    """Held-out against tuning, every level of a family together: ``held-out / tuning``."""
    keys = ("gfnr", "gfpr", "cfnr", "cfpr", "mape", "junctions", "loop_error")
    lines = [
        "| family | method | " + " | ".join(METRIC_LABELS[k] for k in keys) + " |",
        "|---|---|" + "---:|" * len(keys),
    ]
    for family, part in df.groupby("dataset", sort=False):
        for method in methods:
            p = ok_rows(part[part.method == method])
            if not len(p):
                continue
            cells = []
            for key in keys:
                pair = []
                for seed_set in ("heldout", "tuning"):
                    s = p[p.set == seed_set]
                    how = (
                        "percent" if key == "junctions" else key if key == "loop_error" else "mean"
                    )
                    pair.append(
                        reduce_column(
                            s, key, how, 1 if key in ("mape",) else 3 if key in GEOMETRY else 0
                        )[1]
                    )
                cells.append(" / ".join(pair))
            lines.append(f"| {family} | {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def sigma_table(df: pd.DataFrame, methods: Sequence[str], sigmas: Sequence[float]) -> str:
    """NetMets at every tolerance, side by side: ``sigma 2 / sigma 3``."""
    lines = [
        "| family | method | "
        + " | ".join(
            f"{METRIC_LABELS[k]} (sigma {' / '.join(f'{s:g}' for s in sigmas)})" for k in GEOMETRY
        )
        + " |",
        "|---|---|" + "---:|" * len(GEOMETRY),
    ]
    for group, part in df.groupby(group_of(df), sort=False):
        for method in methods:
            p = ok_rows(part[part.method == method])
            if not len(p):
                continue
            cells = []
            for key in GEOMETRY:
                texts = []
                for k, s in enumerate(sigmas):
                    col = key if k == 0 else f"{key}_s{s:g}"
                    texts.append(
                        f"{p[col].mean():.3f}" if col in p and p[col].notna().any() else "-"
                    )
                cells.append(" / ".join(texts))
            lines.append(f"| {group} | {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def joined_table(df: pd.DataFrame, methods: Sequence[str]) -> str:
    """Connectivity rates against the truth as it is and with its junctions closer than
    sigma joined (:func:`vesselflow.metrics.join_close_junctions`): ``as is / joined``."""
    lines = [
        "| family | method | true junctions the joining removes (per case) | "
        "CFNR ↓ as is / joined | CFPR ↓ as is / joined |",
        "|---|---|---:|---:|---:|",
    ]
    for group, part in df.groupby(group_of(df), sort=False):
        for method in methods:
            p = ok_rows(part[part.method == method])
            if not len(p) or "cfnr_joined" not in p or p.cfnr_joined.isna().all():
                continue
            cells = [f"{p.close_junctions.mean():.1f} of {p.truth_junctions.mean():.1f}"]
            for key in ("cfnr", "cfpr"):
                cells.append(f"{p[key].mean():.3f} / {p[f'{key}_joined'].mean():.3f}")
            lines.append(f"| {group} | {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def band_table(df: pd.DataFrame, methods: Sequence[str]) -> str:
    """Radius bias and MAPE per band of truth radius, matches pooled over a family's cases
    (every level): ``bias / MAPE (matched nodes)``."""
    lines = [
        "| family | method | " + " | ".join(f"r {b} vox: bias / MAPE % (n)" for b in BANDS) + " |",
        "|---|---|" + "---:|" * len(BANDS),
    ]
    for family, part in df.groupby("dataset", sort=False):
        for method in methods:
            p = ok_rows(part[part.method == method])
            if not len(p) or f"n_{BANDS[0]}" not in p:
                continue
            cells = []
            for band in BANDS:
                n = p[f"n_{band}"].fillna(0)
                total = float(n.sum())
                if total == 0:
                    cells.append("-")
                    continue
                bias = float((n * p[f"bias_{band}"].fillna(0)).sum()) / total
                mape = float((n * p[f"mape_{band}"].fillna(0)).sum()) / total
                cells.append(f"{bias:+.1f} / {mape:.1f} ({int(total)})")
            lines.append(f"| {family} | {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def bootstrap_ci(values: np.ndarray, seed: int = 0) -> tuple[float, float]:
    """95 % percentile bootstrap interval of the mean (fixed seed: the report is
    reproducible)."""
    rng = np.random.default_rng(seed)
    means = rng.choice(values, size=(BOOTSTRAP, len(values)), replace=True).mean(axis=1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return float(lo), float(hi)


def spread_table(df: pd.DataFrame, method: str) -> str:
    """Mean ± sd over cases and the 95 % bootstrap interval of the mean, per family (levels
    pooled) and per family and level: the noise floor a change must beat."""
    keys = ("gfnr", "gfpr", "cfnr", "cfpr", "mape", "junctions", "junction_nodes", "edge_outside")
    lines = [
        "| family | cases | " + " | ".join(METRIC_LABELS[k] for k in keys) + " |",
        "|---|---:|" + "---:|" * len(keys),
    ]
    ours = ok_rows(df[df.method == method])
    groups = [(f, p) for f, p in ours.groupby("dataset", sort=False)]
    groups += [(g, p) for g, p in ours.groupby(group_of(ours), sort=False) if " " in g]
    for name, part in groups:
        cells = []
        for key in keys:
            v = part[key].dropna().to_numpy(float) if key in part else np.empty(0)
            if not len(v):
                cells.append("-")
                continue
            lo, hi = bootstrap_ci(v)
            d = 1 if key in ("mape",) else 3
            sd = v.std(ddof=1) if len(v) > 1 else 0.0
            cells.append(f"{v.mean():.{d}f} ± {sd:.{d}f} [{lo:.{d}f}, {hi:.{d}f}]")
        lines.append(f"| {name} | {len(part)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def reorder_table(df: pd.DataFrame) -> str:
    """Per family and level, the mean over cases of (score with the axes reordered - score),
    paired by case, and the mean of its absolute value: the method's own spread."""
    keys = ("gfnr", "gfpr", "cfnr", "cfpr", "mape", "junctions", "junction_nodes")
    ours = ok_rows(df[df.method == "vesselflow"])
    other = ok_rows(df[df.method == REORDERED])
    on = ["dataset", "case", "level"]
    both = ours.merge(other, on=on, suffixes=("", "_r"))
    lines = [
        "| family | cases | " + " | ".join(METRIC_LABELS[k] for k in keys) + " |",
        "|---|---:|" + "---:|" * len(keys),
    ]
    groups = [(f, p) for f, p in both.groupby("dataset", sort=False)]
    groups += [(g, p) for g, p in both.groupby(group_of(both), sort=False) if " " in g]
    for name, part in groups:
        cells = []
        for key in keys:
            d = (part[f"{key}_r"] - part[key]).dropna().to_numpy(float)
            digits = 1 if key == "mape" else 3
            cells.append(
                f"{d.mean():+.{digits}f} ({np.abs(d).mean():.{digits}f})" if len(d) else "-"
            )
        lines.append(f"| {name} | {len(part)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def table_by_level(
    df: pd.DataFrame, metric_names: Sequence[str], methods: Sequence[str], paper: bool
) -> str:
    """Rows: level; columns: method, per metric block (the paper's Table I layout)."""
    lines = []
    for metric in metric_names:
        columns = list(methods) + (list(PAPER_TABLE_I) if paper else [])
        lines.append(f"| {METRIC_LABELS[metric]} | " + " | ".join(columns) + " |")
        lines.append("|---" * (len(columns) + 1) + "|")
        for li, level in enumerate(LEVELS):
            cells, means = [], []
            for method in methods:
                m, text = mean_sd(
                    df[(df.method == method) & (df.level == level)].get(metric, pd.Series()),
                    digits_for(metric),
                )
                cells.append(text)
                means.append(m)
            bold = best(means, metric)
            cells = [f"**{c}**" if i == bold else c for i, c in enumerate(cells)]
            key = metric.removeprefix("v_")
            if paper:
                for column in PAPER_TABLE_I.values():
                    mu, sd = column[key][li]
                    cells.append(f"{mu:.{digits_for(metric)}f} ± {sd:.{digits_for(metric)}f}")
            lines.append(f"| {level} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def table_by_case(
    df: pd.DataFrame, metric_names: Sequence[str], methods: Sequence[str], group: str
) -> str:
    """Rows: case (or dataset); columns: metric per method, best in bold."""
    header = (
        "| "
        + group
        + " | "
        + " | ".join(f"{METRIC_LABELS[m]} {meth}" for m in metric_names for meth in methods)
    )
    lines = [header + " |", "|---" * (1 + len(metric_names) * len(methods)) + "|"]
    for key, part in df.groupby(group, sort=False):
        cells = []
        for metric in metric_names:
            means, texts = [], []
            for method in methods:
                m, text = mean_sd(
                    part[part.method == method].get(metric, pd.Series()), digits_for(metric)
                )
                means.append(m)
                texts.append(text if len(part[part.method == method]) > 1 else text.split(" ±")[0])
            bold = best(means, metric)
            cells += [f"**{t}**" if i == bold else t for i, t in enumerate(texts)]
        lines.append(f"| {key} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def topology_table(df: pd.DataFrame, methods: Sequence[str]) -> str:
    lines = [
        "| dataset | volumes | method | components equal | graph - mask components (mean) "
        "| cycles (mean) | truth cycles (mean) | mask loops (mean) | failed |",
        "|---|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for dataset, part in df.groupby("dataset", sort=False):
        for method in methods:
            p = part[part.method == method]
            ok = (
                p[p.get("error", pd.Series(index=p.index, dtype=object)).isna()]
                if "error" in p
                else p
            )
            if not len(p):
                continue
            eq = int(ok.components_equal.sum()) if len(ok) else 0
            diff = (ok.graph_components - ok.mask_components).mean() if len(ok) else np.nan
            truth = (
                ok["truth_cycles"].mean()
                if "truth_cycles" in ok and ok["truth_cycles"].notna().any()
                else np.nan
            )
            lines.append(
                f"| {dataset} | {len(p)} | {method} | {eq}/{len(ok)} | {diff:+.1f} "
                f"| {ok.graph_cycles.mean():.1f} "
                f"| {fmt(truth)} | {ok.mask_loops.mean():.1f} | {len(p) - len(ok)} |"
            )
    return "\n".join(lines) + "\n"


def fmt(x: float) -> str:
    return "-" if x is None or np.isnan(x) else f"{x:.1f}"


def time_table(df: pd.DataFrame, methods: Sequence[str]) -> str:
    lines = ["| dataset | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for dataset, part in df.groupby("dataset", sort=False):
        cells = []
        for method in methods:
            s = part[part.method == method].get("seconds", pd.Series()).dropna()
            cells.append(f"{s.mean():.2f}" if len(s) else "-")
        lines.append(f"| {dataset} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def figure(path: Path, dataset: str, material: dict[str, Any]) -> None:
    """MIP of the mask with each method's graph on top, coloured by radius; truth first."""
    from matplotlib.figure import Figure

    from vesselflow.plot import plot

    mask = material["_mask"]
    panels = [(k, v) for k, v in material.items() if not k.startswith("_")]
    if material.get("_truth") is not None:
        panels.insert(0, ("truth", material["_truth"]))
    axis = int(np.argmin(np.asarray(mask.shape) * np.asarray(panels[0][1].spacing)))
    fig = Figure(figsize=(4.2 * len(panels), 4.4), dpi=90)
    for i, (name, graph) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), i + 1)
        plot(graph, mask, axis=axis, ax=ax)
        ax.set_title(f"{dataset}: {name} ({graph.n_nodes} nodes)", fontsize=9)
    fig.tight_layout()
    write_atomic(path, lambda f: fig.savefig(f, format="png"))


def header(methods: Sequence[str], args: argparse.Namespace) -> str:
    versions = []
    for pkg in (
        "vesselflow",
        "numpy",
        "scipy",
        "scikit-image",
        "skan",
        "kimimaro",
        "compas_cgal",
    ):
        with contextlib.suppress(metadata.PackageNotFoundError):
            versions.append(f"{pkg} {metadata.version(pkg)}")
    missing = {m: why for m, why in compare.available().items() if why}
    out = [
        f"Generated by `python benches/fidelity.py {' '.join(sys.argv[1:])}` on "
        f"{datetime.date.today()} ({platform.machine()}, {os.cpu_count()} cores; "
        f"{', '.join(versions)}; source {source_version()}; extension {EXTENSION}).",
        "",
        f"Methods run: {', '.join(methods)}. "
        + "".join(f"Not run: {m} ({why}). " for m, why in missing.items())
        + "SOAX and VTrails (in the paper's tables) do not install here: SOAX is a Qt desktop "
        "program and VTrails a MATLAB toolbox, with no Python package.",
        "",
        f"Tolerance sigma = {args.sigmas[0]:g} base cells (the smallest voxel spacing) for the "
        "headline NetMets scores, radius matching and junctions; NetMets at "
        f"{', '.join(f'{s:g}' for s in args.sigmas[1:])} beside it. Every method is "
        "single-threaded; comparators get radii from the EDT at their nodes "
        "(`vesselflow.compare.edt_radii`), vesselflow keeps its own.",
        "",
        f"Seed sets: tuning = seeds {SEED_SETS['tuning']}, {SEED_SETS['tuning'] + 1}, ...; "
        f"held-out = seeds {SEED_SETS['heldout']}, {SEED_SETS['heldout'] + 1}, ... (bubble noise "
        f"seed = {NOISE_SEED} + volume seed). Defaults may be chosen on the tuning set only; the "
        "held-out set is the headline.",
        "",
        f"{' and '.join(SLOW_METHODS)} (slow) run only on the first {args.slow_cases} volumes of "
        "each family, level and seed set and the first volume of each real dataset; their means "
        "are over those cases.",
        "",
        f"vesselflow parameters: {vesselflow.Skeletonizer().params}",
        "",
    ]
    return "\n".join(out)


def source_version() -> str:
    """The commit the report was made from, ``+ changes`` when the tree was not clean."""
    import subprocess

    def git(*args: str) -> str:
        done = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True)
        return done.stdout.strip() if done.returncode == 0 else ""

    commit = git("rev-parse", "--short", "HEAD")
    if not commit:
        return "not a git checkout"
    return commit + (" + uncommitted changes" if git("status", "--porcelain") else "")


COLUMN_NOTES = (
    "Columns: NetMets proper (Mayerich et al. 2012) geometric and connectivity false "
    "negative / positive rates; MAPE and bias of the radii of graph nodes within sigma of the "
    "truth centreline (bias < 0: too thin); components 1:1 = volumes whose graph has as many "
    "components as the mask has 26-connected components; cycles = the graph's cycle rank, "
    "against the first Betti number of the noise-free mask (Euler characteristic of the "
    "closed voxel cubes, plus 26-components and enclosed cavities: "
    "`vesselflow.metrics.topology`); loop error = sum of |cycles - clean-mask loops| over "
    "the cases as a percentage of the summed clean-mask loops; junctions found = truth nodes "
    "of degree >= 3 with a graph node within sigma, met by a junction = with a graph node of "
    "degree >= 3 within sigma; edge length outside = share of the "
    "graph's edge length over background voxels of the input mask; the last count = volumes "
    "where a graph node lies outside the input mask dilated by one voxel (the invariant of "
    "`tests/method.rs`). Best of each family in bold."
)


def synthetic_sections(
    df: pd.DataFrame, methods: Sequence[str], args: argparse.Namespace
) -> list[str]:
    syn = df[df.dataset.isin(list(FAMILIES))]
    if not len(syn):
        return []
    held, tune = syn[syn.set == "heldout"], syn[syn.set == "tuning"]
    headline = held if len(held) else tune
    name = "held-out" if len(held) else "tuning"
    parts = [
        f"## Headline: synthetic families, {name} set, sigma = {args.sigmas[0]:g} voxels",
        "",
        COLUMN_NOTES,
        "",
        headline_table(headline, methods),
    ]
    if len(held) and len(tune):
        parts += [
            f"## Held-out / tuning, every level of a family together (sigma = {args.sigmas[0]:g})",
            "",
            "Each cell is `held-out / tuning`. A method tuned to the tuning set would show it "
            "here first.",
            "",
            versus_table(syn, methods),
            f"## Tuning set, sigma = {args.sigmas[0]:g} voxels",
            "",
            headline_table(tune, methods),
        ]
    if len(args.sigmas) > 1:
        parts += [
            f"## NetMets at sigma = {' and '.join(f'{s:g}' for s in args.sigmas)} ({name} set)",
            "",
            sigma_table(headline, methods, args.sigmas),
        ]
    if "cfnr_joined" in headline and headline.cfnr_joined.notna().any():
        parts += [
            f"## Connectivity at the resolution of sigma ({name} set, sigma = {args.sigmas[0]:g})",
            "",
            "NetMets matches core nodes one to one within sigma, so where a vessel gives off "
            "two branches less than sigma apart (the forests' space colonisation grows them "
            "1.5 voxels apart at nearly a third of their junctions), a graph must hold two "
            "junctions there, each within sigma of its own, or lose the branches of one. The "
            "second figure of each cell scores the same graphs against the truth with its "
            "junctions joined by an edge shorter than sigma made one "
            "(`vesselflow.metrics.join_close_junctions`): connectivity at the resolution "
            "sigma stands for. The headline keeps the truth as it is.",
            "",
            joined_table(headline, methods),
        ]
    parts += [
        f"## Radius by band of truth radius ({name} set, sigma = {args.sigmas[0]:g})",
        "",
        "Bias and MAPE (percent) of the radii of graph nodes matched to the truth centreline, by "
        "the truth radius there in voxels, all levels of a family together; n = matched nodes. "
        "The forest and lattice families are rasterised at voxel centres, the tree and "
        "capillary families as partial volume thresholded at 0.5 (see benches/README.md for "
        "how the distance transform relates to the truth radius under each).",
        "",
        band_table(headline, methods),
        f"## Spread of vesselflow's scores across {name} volumes (the guard for changes)",
        "",
        "The method is deterministic, so the spread is across volumes: mean ± sd over the "
        f"cases, then the 95 % percentile bootstrap interval of the mean ({BOOTSTRAP} "
        "resamples of the cases, seed 0). A change whose mean moves by less than the "
        "interval's half-width is within the noise of this benchmark.",
        "",
        spread_table(headline, "vesselflow"),
    ]
    if (headline.method == REORDERED).any():
        parts += [
            "Paired by case: vesselflow on the same masks with their axes in the order "
            f"{' '.join(map(str, REORDER))} (positions put back), mean difference from the run "
            "above, and in brackets the mean absolute difference per case. Only the order of "
            "the arithmetic changes (nodes numbered in another raster order, so every sum, "
            "row order and tie-break differs), so this is the method's own run-to-run spread: "
            "a change of the method whose means move by less is indistinguishable from "
            "reordering the input's axes.",
            "",
            reorder_table(headline),
        ]
    trees = headline[headline.dataset == "tree"]
    if len(trees):
        parts += [
            f"## The paper's Table I layout: CCO trees ({name} set, sigma = "
            f"{args.sigmas[0]:g}, NetMets proper)",
            "",
            "Mean ± sd over the trees at each level; best of our run in bold. The paper's "
            "columns are its own numbers on its own VascuSynth trees (set beside ours for "
            "scale, not measured here). " + DIADEM_NOTE,
            "",
            table_by_level(
                trees, ("gfnr", "gfpr", "cfnr", "cfpr", "diadem", "mape"), methods, paper=True
            ),
            "The authors' NetMets variant (VascGraph: nodes of degree ≠ 2, 99 % trimming):",
            "",
            table_by_level(
                trees, ("v_gfnr", "v_gfpr", "v_cfnr", "v_cfpr", "mape_norm"), methods, paper=False
            ),
        ]
    return parts


def report(df: pd.DataFrame, methods: Sequence[str], args: argparse.Namespace) -> str:
    parts = ["# Fidelity", "", header(methods, args)]
    parts += synthetic_sections(df, methods, args)
    real = df[df.dataset.isin(["aorta", "vascusynth"])]
    if len(real):
        parts += [
            f"## Table II: real and third-party trees with a centreline truth (sigma = "
            f"{args.sigmas[0]:g})",
            "",
            table_by_case(real, ("diadem", "mape"), methods, "case"),
            "NetMets proper on the same volumes:",
            "",
            table_by_case(real, ("gfnr", "gfpr", "cfnr", "cfpr"), methods, "case"),
        ]
    skel = df[df.dataset == "vesselsynth"]
    if len(skel):
        parts += [
            "## vesselsynth (voxel-skeleton truth: geometry only)",
            "",
            table_by_case(skel, ("gfnr", "gfpr"), methods, "case"),
        ]
    parts += [
        "## Topology",
        "",
        "Components: graph components against 26-connected mask components (equal on how many "
        "volumes). Cycles: the graph's cycle rank, against the truth's and the mask's loops "
        "(first Betti number of the mask the method saw).",
        "",
        topology_table(df, methods),
        "## Time (seconds per volume, one core)",
        "",
        time_table(df, methods),
    ]
    ours = df[df.method == "vesselflow"]
    if "iterations" in ours and len(ours):
        converged, stalled = (ours[k].fillna(False).astype(bool) for k in ("converged", "stalled"))
        parts += [
            f"vesselflow contraction iterations: mean {ours.iterations.mean():.1f}, max "
            f"{int(ours.iterations.max())}; converged on {int(converged.sum())}/{len(ours)} "
            f"volumes, stalled near convergence (`stall_ratio`) on {int(stalled.sum())}, "
            f"stopped at `max_iterations` on {int((~converged & ~stalled).sum())}.",
            "",
        ]
    if "error" in df and df.error.notna().any():
        parts += ["## Failures", ""]
        parts += [
            f"- {r.method} on {r.case} {r.level}: {r.error}"
            for r in df[df.error.notna()].itertuples()
        ]
        parts.append("")
    return "\n".join(parts)


# ----------------------------------------------------------------------------- sweep

#: One-at-a-time variations around the defaults.
SWEEP: tuple[tuple[str, dict[str, Any]], ...] = (
    ("defaults", {}),
    ("alpha=0.5 (METHOD.md)", {"alpha": 0.5}),
    ("alpha=0.125", {"alpha": 0.125}),
    ("beta=1.0", {"beta": 1.0}),
    ("beta=0.25", {"beta": 0.25}),
    ("gamma=0.02", {"gamma": 0.02}),
    ("gamma=0.1", {"gamma": 0.1}),
    ("gamma=0.2", {"gamma": 0.2}),
    ("medial_weight=difference", {"medial_weight": "difference"}),
    ("skeletal_angle=0", {"skeletal_angle": 0.0}),
    ("skeletal_angle=5", {"skeletal_angle": 5.0}),
    ("skeletal_angle=25.8", {"skeletal_angle": 25.8}),
    ("anchor_ends=False", {"anchor_ends": False}),
    ("radius_correction=0", {"radius_correction": 0.0}),
    ("radius_correction=0.25", {"radius_correction": 0.25}),
    ("radius_correction=0.75", {"radius_correction": 0.75}),
    ("radius_correction=1.0", {"radius_correction": 1.0}),
    ("cg_tol=1e-6 (METHOD.md)", {"cg_tol": 1e-6}),
    ("cg_tol=1e-3", {"cg_tol": 1e-3}),
    ("cg_tol=1e-2", {"cg_tol": 1e-2}),
    ("stall_ratio=0 (METHOD.md)", {"stall_ratio": 0.0}),
    ("stall_ratio=0.005", {"stall_ratio": 0.005}),
    ("stall_ratio=0.02", {"stall_ratio": 0.02}),
)
SWEEP_COLUMNS = ("gfnr", "gfpr", "cfnr", "cfpr", "mape", "junctions", "iterations", "seconds")


def composite(part: pd.DataFrame) -> float:
    """One number to rank settings: the mean of the four NetMets rates and the MAPE (each a
    fraction, lower is better)."""
    terms = [part[m].mean() for m in GEOMETRY]
    terms += [part.mape.mean() / 100]
    return float(np.mean(terms))


def sweep(args: argparse.Namespace) -> str:
    """One parameter at a time around the defaults, on the tuning set only."""
    counts = {"forest": args.sweep_volumes, "tree": args.sweep_volumes}
    todo = synthetic_recipes(counts, ["tuning"], 0, LEVELS)
    lines = [
        "# Sensitivity of vesselflow's parameters",
        "",
        f"Generated by `python benches/fidelity.py {' '.join(sys.argv[1:])}` on "
        f"{datetime.date.today()}: the first {args.sweep_volumes} forests and CCO trees of the "
        "tuning set x 3 noise levels (never the held-out set), one parameter changed at a time "
        f"from the defaults, sigma = {args.sigmas[0]:g} cells. "
        "Score = mean of GFNR, GFPR, CFNR, CFPR and MAPE (fractions; lower is better).",
        "",
        "| setting | " + " | ".join(METRIC_LABELS.get(c, c) for c in SWEEP_COLUMNS) + " | score |",
        "|---" * (len(SWEEP_COLUMNS) + 2) + "|",
    ]
    for label, params in SWEEP:
        df, _ = run_all(todo, ["vesselflow"], args.sigmas, args.jobs, params, label=f"{label} ")
        cells = [
            mean_sd(df.get(c, pd.Series()), 2 if c not in ("mape", "iterations") else 1)[1]
            for c in SWEEP_COLUMNS
        ]
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {composite(df):.4f} |")
        print(lines[-1], flush=True)
    return "\n".join(lines) + "\n"


def main(argv: Iterable[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--set",
        choices=("tuning", "heldout", "both"),
        default="both",
        help="seed set(s) of the synthetic families (default both; the headline is held-out)",
    )
    for family, (_, n) in FAMILIES.items():
        ap.add_argument(
            f"--{family}s" if family != "capillary" else "--capillaries",
            dest=family,
            type=int,
            default=n,
            help=f"{family} volumes per seed set (default {n})",
        )
    ap.add_argument("--no-real", action="store_true", help="skip ../shared/data")
    ap.add_argument(
        "--quick",
        action="store_true",
        help="a ~1 minute guard: two held-out forests and one CCO tree at D1 and D2 and one "
        "lattice, vesselflow and thinning+skan, no real volume; prints the report, writes "
        "files only with --out",
    )
    ap.add_argument(
        "--methods", nargs="+", default=None, help="subset of vesselflow.compare.METHODS"
    )
    ap.add_argument(
        "--sigmas",
        type=float,
        nargs="+",
        default=list(SIGMAS),
        help="NetMets tolerances in base cells, headline first (default 2 3)",
    )
    ap.add_argument("--jobs", type=int, default=2, help="cases run at once (default 2)")
    ap.add_argument(
        "--slow-cases",
        type=int,
        default=1,
        help=f"volumes per family, level and set that {', '.join(SLOW_METHODS)} run on (default 1)",
    )
    ap.add_argument(
        "--report-only",
        action="store_true",
        help="rewrite fidelity.md from the fidelity_rows.csv and PNGs already in --out (no run)",
    )
    ap.add_argument("--sweep", action="store_true", help="also run the sensitivity sweep")
    ap.add_argument("--sweep-only", action="store_true", help="run only the sensitivity sweep")
    ap.add_argument(
        "--sweep-volumes",
        type=int,
        default=3,
        help="tuning forests and trees per level in the sweep (default 3)",
    )
    ap.add_argument(
        "--out", type=Path, default=None, help="output folder (default benches/results)"
    )
    args = ap.parse_args(argv)
    if args.quick:
        counts = {"forest": 2, "lattice": 1, "tree": 1}
        todo = synthetic_recipes(counts, ["heldout"], 0, ("D1", "D2"))
        wanted = args.methods or ["vesselflow", "voxel"]
    else:
        counts = {family: getattr(args, family) for family in FAMILIES}
        sets = ["tuning", "heldout"] if args.set == "both" else [args.set]
        todo = synthetic_recipes(counts, sets, args.slow_cases, LEVELS)
        todo += [] if args.no_real else real_recipes()
        wanted = args.methods or list(compare.METHODS)
    out = args.out if args.out is not None or args.quick else HERE / "results"
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)

    if args.report_only:
        folder = out or HERE / "results"
        df = pd.read_csv(folder / "fidelity_rows.csv")
        df["level"] = df.level.fillna("")
        methods = [m for m in compare.METHODS if m in set(df.method)]
        text = report(df, methods, args) + "## Figures\n\n"
        text += "".join(
            f"![{png.stem[9:]}]({png.name})\n" for png in sorted(folder.glob("fidelity_*.png"))
        )
        write_atomic(folder / "fidelity.md", lambda f: f.write(text.encode()))
        print(text)
        return
    if not args.sweep_only:
        methods = [m for m in wanted if compare.available().get(m) is None]
        for m in set(wanted) - set(methods):
            print(f"skipping {m}: {compare.available()[m]}", file=sys.stderr)
        t0 = time.time()
        # The method's own spread (held-out synthetic cases only; not in the quick guard).
        extra = [REORDERED] if "vesselflow" in methods and not args.quick else []
        df, figures = run_all(todo, methods + extra, args.sigmas, args.jobs)
        text = report(df, methods, args)
        if out is not None:
            write_atomic(
                out / "fidelity_rows.csv", lambda f: f.write(df.to_csv(index=False).encode())
            )
            figure_lines = ["## Figures", ""]
            for dataset, material in figures.items():
                png = out / f"fidelity_{dataset}.png"
                figure(png, dataset, material)
                figure_lines.append(f"![{dataset}]({png.name})")
            text += "\n".join(figure_lines) + "\n"
        text += f"\nTotal wall time {time.time() - t0:.0f} s.\n"
        if out is not None:
            write_atomic(out / "fidelity.md", lambda f: f.write(text.encode()))
        print(text)
    if args.sweep or args.sweep_only:
        text = sweep(args)
        write_atomic((out or HERE / "results") / "sensitivity.md", lambda f: f.write(text.encode()))
        print(text)


if __name__ == "__main__":
    main()
