"""Fidelity benchmark: vesselflow and its peers against ground truth, shaped like the paper's
Tables I and II.

One command::

    python benches/fidelity.py [--trees 10] [--jobs 2] [--out benches/results]

writes ``fidelity.md`` (and ``fidelity_rows.csv``, every number behind it, plus one PNG per
dataset) to ``--out``; ``--sweep`` also runs the sensitivity sweep into ``sensitivity.md``.

Datasets
    - ``tree``: ``vesselflow.synth.vascular_tree`` at 128³, 160³ and 192³ with 16, 32 and 64
      terminals (cycling, as the paper's three branching levels), each with the paper's
      boundary noise at levels D0, D1 and D2 (``vesselflow.synth.add_bubble_noise``);
    - ``capillary``: ``vesselflow.synth.capillary_network``, loopy meshes with a known cycle
      rank;
    - the real and third-party volumes in ``../shared/data`` (read in place, never copied:
      several are licensed for evaluation only): the vmtk CT aorta at two resolutions
      (centreline and radii from vmtkcenterlines), the VascuSynth trees (generator ground
      truth; segments thinner than half a voxel are dropped from the truth, as the data
      README advises, because the masks cannot resolve them), the vesselsynth volumes
      (a voxel skeleton as truth: geometry only), and masks without truth (two-photon,
      light-sheet, the authors' demo volumes): topology and time only.

Methods are those of ``vesselflow.compare``; one that is not installed is reported, not run.

Metrics (``vesselflow.metrics``), all at the tolerance ``sigma = --sigma`` base cells (the
smallest voxel spacing): NetMets proper and the authors' VascGraph variant (GFNR, GFPR, CFNR,
CFPR), DIADEM on trees, the radius MAPE over graph nodes within ``sigma`` of the truth (and
the authors' normalised variant), and the topology (graph components against 26-connected
mask components; graph cycle rank against the truth's, or the mask's loops).

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
import tempfile
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

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DATA = ROOT.parent / "shared" / "data"

LEVELS = ("D0", "D1", "D2")
TREE_SHAPES = (128, 160, 192)
TREE_TERMINALS = (16, 32, 64)
CAPILLARY_SHAPE = (96, 96, 96)
#: Methods too slow for every case (CGAL's mesh skeleton: 30-60 s per 128^3 volume): they run
#: on the first ``--slow-trees`` trees, the first capillary network and one volume per real
#: dataset, and the report says so.
SLOW_METHODS = ("mesh", "pointcloud")

#: Real volumes with a centreline graph: (file, is a tree).
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
    "mape_norm": "MAP, normalised (%) ↓",
    "seconds": "time (s) ↓",
}
HIGHER_IS_BETTER = {"diadem"}


@dataclass(frozen=True)
class Recipe:
    """How a worker builds one case (volumes are made where they are used)."""

    dataset: str
    name: str
    level: str = ""
    seed: int = 0
    shape: int = 0
    terminals: int = 0
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
    extra: dict[str, Any] = field(default_factory=dict)


def recipes(trees: int, capillaries: int, real: bool, slow_trees: int = 0) -> list[Recipe]:
    """Every case of the report, in a fixed order."""
    out = []
    for i in range(trees):
        shape, terminals = TREE_SHAPES[i % 3], TREE_TERMINALS[(i // 3) % 3]
        for level in LEVELS:
            first = i == 0 and level == "D1"
            out.append(
                Recipe("tree", f"tree{i:02d}", level, i, shape, terminals, first, i < slow_trees)
            )
    for i in range(capillaries):
        out.append(Recipe("capillary", f"capillary{i:02d}", seed=i, figure=i == 0, slow=i == 0))
    if real:
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
    if recipe.dataset == "tree":
        shape = (recipe.shape,) * 3
        mask, truth = synth.vascular_tree(shape, n_terminals=recipe.terminals, seed=recipe.seed)
        mask = synth.add_bubble_noise(mask, recipe.level, seed=1000 + recipe.seed)
        return Case("tree", recipe.name, recipe.level, mask, truth.spacing, truth, tree=True)
    if recipe.dataset == "capillary":
        mask, truth = synth.capillary_network(CAPILLARY_SHAPE, seed=recipe.seed)
        return Case("capillary", recipe.name, "", mask, truth.spacing, truth, tree=False)
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


def score(case: Case, graph: VesselGraph, sigma_cells: float) -> dict[str, Any]:
    """Every metric of one graph against its case."""
    row: dict[str, Any] = {}
    topo = metrics.topology(case.mask, graph)
    row.update(
        mask_components=topo["mask_components"],
        graph_components=topo["graph_components"],
        components_equal=topo["components_equal"],
        mask_loops=topo["mask_loops"],
        graph_cycles=topo["graph_cycles"],
    )
    if case.truth is None:
        return row
    sigma = sigma_cells * float(np.min(case.spacing))
    nm = metrics.netmets(case.truth, graph, sigma)
    row.update(gfnr=nm["gfnr"], gfpr=nm["gfpr"])
    if case.graph_truth:
        row.update(cfnr=nm["cfnr"], cfpr=nm["cfpr"])
        vg = metrics.netmets(case.truth, graph, sigma, mode="vascgraph")
        row.update({f"v_{k}": vg[k] for k in GEOMETRY})
        row["truth_cycles"] = case.truth.n_edges - case.truth.n_nodes + components(case.truth)
        if graph.n_nodes:
            row["mape"] = metrics.radius_error(case.truth, graph, sigma)["mape"]
            row["mape_norm"] = metrics.radius_error(case.truth, graph, sigma, normalised=True)[
                "mape"
            ]
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


def components(graph: VesselGraph) -> int:
    import networkx as nx

    return int(nx.number_connected_components(graph.to_networkx())) if graph.n_nodes else 0


_WARM: set[str] = set()


def warm_up(methods: Sequence[str]) -> None:
    """Run each method once on a tiny volume in this process, so one-off costs (skan's
    numba compilation: about 8 s) are not charged to the first case."""
    tiny = np.zeros((9, 9, 9), bool)
    tiny[2:7, 3:6, 3:6] = True
    for method in set(methods) - _WARM - set(SLOW_METHODS):
        compare.run(method, tiny)
        _WARM.add(method)


def evaluate(
    recipe: Recipe, methods: Sequence[str], sigma_cells: float, params: dict[str, Any] | None = None
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Run ``methods`` on one case and score them; the figure's material when asked for."""
    case = build(recipe)
    warm_up(methods)
    base = {
        "dataset": case.dataset,
        "case": case.name,
        "level": case.level,
        "foreground": int(case.mask.sum()),
        "shape": "x".join(map(str, case.mask.shape)),
    }
    rows, figure = [], {}
    for method in methods:
        if method in SLOW_METHODS and not recipe.slow:
            continue
        row = dict(base, method=method)
        try:
            options = {"threads": 1, **(params or {})} if method == "vesselflow" else {}
            graph = compare.run(method, case.mask, case.spacing, **options)
            row.update(seconds=graph.info["seconds"], nodes=graph.n_nodes, edges=graph.n_edges)
            if method == "vesselflow":
                row.update(
                    iterations=graph.info["iterations"],
                    converged=graph.info["converged"],
                    stalled=graph.info["stalled"],
                )
            row.update(score(case, graph, sigma_cells))
            if recipe.figure:
                figure[method] = graph
        except Exception as exc:  # a failing method is a row, not a crash of the report
            row["error"] = f"{type(exc).__name__}: {exc}".splitlines()[0][:200]
            traceback.print_exc()
        rows.append(row)
    if recipe.figure:
        figure["_mask"] = case.mask
        figure["_truth"] = case.truth
    return rows, figure


def run_all(
    todo: Sequence[Recipe],
    methods: Sequence[str],
    sigma_cells: float,
    jobs: int,
    params: dict[str, Any] | None = None,
    label: str = "",
) -> tuple[pd.DataFrame, dict[str, dict[str, Any]]]:
    rows, figures = [], {}
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        futures = [pool.submit(evaluate, r, methods, sigma_cells, params) for r in todo]
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
    return 1 if metric in ("diadem", "mape", "mape_norm") else 2


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


def best(means: Sequence[float], metric: str) -> int:
    arr = np.array(means, float)
    if np.all(np.isnan(arr)):
        return -1
    return int(np.nanargmax(arr) if metric in HIGHER_IS_BETTER else np.nanargmin(arr))


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


def write_atomic(path: Path, write: Any) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def header(methods: Sequence[str], args: argparse.Namespace) -> str:
    versions = []
    for pkg in (
        "vesselflow",
        "numpy",
        "scipy",
        "scikit-image",
        "skan",
        "kimimaro",
        "skeletor",
        "pc-skeletor",
    ):
        with contextlib.suppress(metadata.PackageNotFoundError):
            versions.append(f"{pkg} {metadata.version(pkg)}")
    missing = {m: why for m, why in compare.available().items() if why}
    out = [
        f"Generated by `python benches/fidelity.py {' '.join(sys.argv[1:])}` on "
        f"{datetime.date.today()} ({platform.machine()}, {os.cpu_count()} cores; "
        f"{', '.join(versions)}).",
        "",
        f"Methods run: {', '.join(methods)}. "
        + "".join(f"Not run: {m} ({why}). " for m, why in missing.items())
        + "SOAX and VTrails (in the paper's tables) do not install here: SOAX is a Qt desktop "
        "program and VTrails a MATLAB toolbox, with no Python package.",
        "",
        f"Tolerance sigma = {args.sigma} base cells (the smallest voxel spacing) for every NetMets "
        "score and for matching radii. Every method is single-threaded; comparators get radii "
        "from the EDT at their nodes, vesselflow keeps its own.",
        "",
        f"{' and '.join(SLOW_METHODS)} (slow) run only on the first {args.slow_trees} trees per "
        "level, the first capillary network and the first volume of each real dataset; their "
        "means are over those cases.",
        "",
        f"vesselflow parameters: {vesselflow.Skeletonizer().params}",
        "",
    ]
    return "\n".join(out)


def report(df: pd.DataFrame, methods: Sequence[str], args: argparse.Namespace) -> str:
    trees = df[df.dataset == "tree"]
    parts = ["# Fidelity", "", header(methods, args)]
    if len(trees):
        n = trees.case.nunique()
        parts += [
            f"## Table I: synthetic trees ({n} trees x 3 noise levels, NetMets proper)",
            "",
            "Mean ± sd over the trees at each level; best of our run in bold. The paper's columns "
            "are its own numbers on its own VascuSynth trees (set beside ours for scale, not "
            "measured here). " + DIADEM_NOTE,
            "",
            table_by_level(
                trees, ("gfnr", "gfpr", "cfnr", "cfpr", "diadem", "mape"), methods, paper=True
            ),
            "## Table I, the authors' NetMets variant "
            "(VascGraph: nodes of degree ≠ 2, 99 % trimming)",
            "",
            table_by_level(
                trees, ("v_gfnr", "v_gfpr", "v_cfnr", "v_cfpr", "mape_norm"), methods, paper=False
            ),
        ]
    cap = df[df.dataset == "capillary"]
    if len(cap):
        parts += [
            "## Capillary networks (loopy; NetMets proper)",
            "",
            table_by_case(cap, ("gfnr", "gfpr", "cfnr", "cfpr", "mape"), methods, "dataset"),
        ]
    real = df[df.dataset.isin(["aorta", "vascusynth"])]
    if len(real):
        parts += [
            "## Table II: real and third-party trees with a centreline truth",
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
        "(first Betti number).",
        "",
        topology_table(df, methods),
        "## Time (seconds per volume, one core)",
        "",
        time_table(df, methods),
    ]
    ours = df[df.method == "vesselflow"]
    if "iterations" in ours:
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
SWEEP_COLUMNS = ("gfnr", "gfpr", "cfnr", "cfpr", "diadem", "mape", "iterations", "seconds")


def composite(part: pd.DataFrame) -> float:
    """One number to rank settings: the mean of the four NetMets rates and the MAPE (each a
    fraction, lower is better). DIADEM is shown but left out: see ``DIADEM_NOTE``."""
    terms = [part[m].mean() for m in GEOMETRY]
    terms += [part.mape.mean() / 100]
    return float(np.mean(terms))


def sweep(args: argparse.Namespace) -> str:
    todo = [r for r in recipes(args.sweep_trees, 0, False)]
    lines = [
        "# Sensitivity of vesselflow's parameters",
        "",
        f"Generated by `python benches/fidelity.py {' '.join(sys.argv[1:])}` on "
        f"{datetime.date.today()}: {args.sweep_trees} synthetic trees x 3 noise levels (the first "
        "trees of the fidelity run; no real volume), one parameter changed at a time from the "
        f"defaults, sigma = {args.sigma} cells. "
        "Score = mean of GFNR, GFPR, CFNR, CFPR and MAPE (fractions; lower is better). "
        + DIADEM_NOTE,
        "",
        "| setting | " + " | ".join(METRIC_LABELS.get(c, c) for c in SWEEP_COLUMNS) + " | score |",
        "|---" * (len(SWEEP_COLUMNS) + 2) + "|",
    ]
    for label, params in SWEEP:
        df, _ = run_all(todo, ["vesselflow"], args.sigma, args.jobs, params, label=f"{label} ")
        cells = [
            mean_sd(df.get(c, pd.Series()), 2 if c not in ("diadem", "mape", "iterations") else 1)[
                1
            ]
            for c in SWEEP_COLUMNS
        ]
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {composite(df):.4f} |")
        print(lines[-1], flush=True)
    return "\n".join(lines) + "\n"


def main(argv: Iterable[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--trees", type=int, default=10, help="synthetic trees per noise level (default 10)"
    )
    ap.add_argument("--capillaries", type=int, default=3, help="capillary networks (default 3)")
    ap.add_argument("--no-real", action="store_true", help="skip ../shared/data")
    ap.add_argument(
        "--methods", nargs="+", default=None, help="subset of vesselflow.compare.METHODS"
    )
    ap.add_argument(
        "--sigma", type=float, default=3.0, help="NetMets tolerance in base cells (default 3)"
    )
    ap.add_argument("--jobs", type=int, default=2, help="cases run at once (default 2)")
    ap.add_argument(
        "--slow-trees",
        type=int,
        default=2,
        help=f"trees per level that {', '.join(SLOW_METHODS)} run on (default 2)",
    )
    ap.add_argument("--sweep", action="store_true", help="also run the sensitivity sweep")
    ap.add_argument("--sweep-only", action="store_true", help="run only the sensitivity sweep")
    ap.add_argument(
        "--sweep-trees", type=int, default=4, help="trees per level in the sweep (default 4)"
    )
    ap.add_argument("--out", type=Path, default=HERE / "results", help="output folder")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    if not args.sweep_only:
        wanted = args.methods or list(compare.METHODS)
        methods = [m for m in wanted if compare.available().get(m) is None]
        for m in set(wanted) - set(methods):
            print(f"skipping {m}: {compare.available()[m]}", file=sys.stderr)
        t0 = time.time()
        todo = recipes(args.trees, args.capillaries, not args.no_real, args.slow_trees)
        df, figures = run_all(todo, methods, args.sigma, args.jobs)
        write_atomic(
            args.out / "fidelity_rows.csv", lambda f: f.write(df.to_csv(index=False).encode())
        )
        text = report(df, methods, args)
        figure_lines = ["## Figures", ""]
        for dataset, material in figures.items():
            png = args.out / f"fidelity_{dataset}.png"
            figure(png, dataset, material)
            figure_lines.append(f"![{dataset}]({png.name})")
        text += "\n".join(figure_lines) + f"\n\nTotal wall time {time.time() - t0:.0f} s.\n"
        write_atomic(args.out / "fidelity.md", lambda f: f.write(text.encode()))
        print(text)
    if args.sweep or args.sweep_only:
        text = sweep(args)
        write_atomic(args.out / "sensitivity.md", lambda f: f.write(text.encode()))
        print(text)


if __name__ == "__main__":
    main()
