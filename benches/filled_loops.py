"""Where the forests' connectivity errors lie: at loops of the truth the mask fills.

    python benches/filled_loops.py [--set heldout] [--levels D0 D2] [--methods ...]
                                   [--out benches/results/filled_loops.md]

The second synthetic family of ``benches/fidelity.py`` (forests) joins about a third of
its leaves to a nearby vessel. Its truth graphs have about 27 cycles per volume; their
clean masks have about 8 loops (tunnels): most joins run alongside a vessel, and the mask
fills the loop they close. No method that reads the mask can draw such a loop, so the
truth's branches there are hard to match. This bench measures how much of the
connectivity error lies there.

Per case: the minimum cycle basis of the truth's core graph (branches as edges, weighted
by length); a basis cycle is *filled* when the fan of triangles from its centroid to its
edges lies on the case's mask at every sample (a disc the mask holds: no tunnel). Every
branch of the truth and of each method's graph is *near a filled loop* when one of its
nodes lies within 3 voxels of a node of a filled cycle. A branch is *found* when both its
end nodes are matched one to one to the other network's core nodes within sigma = 2
voxels (NetMets' matching) and the other network has a branch between the same matched
pair; this count leaves out NetMets' transparent clusters (a branch through unmatched
junctions), so it is stricter than the benchmark's CFNR / CFPR. Reported: the share of
branches near filled loops and the share not found, near them and elsewhere.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import networkx as nx
import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fidelity as F

from vesselflow import VesselGraph, compare
from vesselflow.analysis import trace_branches
from vesselflow.metrics import _match_core_nodes

SIGMA = 2.0
NEAR = 3.0
#: Samples per side of a fan triangle (the fan test's resolution, about a voxel).
FAN_SAMPLES = 9


def _on_mask(mask: np.ndarray, points: np.ndarray) -> bool:
    v = np.rint(points).astype(np.int64)
    inside = np.all((v >= 0) & (v < np.asarray(mask.shape)), axis=1)
    return bool(inside.all() and mask[tuple(v.T)].all())


def _filled(ring: np.ndarray, mask: np.ndarray) -> bool:
    """Whether the fan from the centroid of the closed polyline ``ring`` (voxel units)
    over its edges lies on ``mask`` at every sample."""
    centre = ring.mean(axis=0)
    uv = [
        (u, v) for u in np.linspace(0, 1, FAN_SAMPLES) for v in np.linspace(0, 1 - u, FAN_SAMPLES)
    ]
    w = np.asarray(uv)
    for a, b in zip(ring, np.roll(ring, -1, axis=0)):
        if not _on_mask(mask, centre + w[:, :1] * (a - centre) + w[:, 1:] * (b - centre)):
            return False
    return True


def filled_cycle_nodes(
    truth: VesselGraph, branches: list[Any], mask: np.ndarray
) -> tuple[set[int], int, int]:
    """The truth's nodes on filled basis cycles, the number of filled cycles and of all;
    ``branches`` are the truth's (:func:`vesselflow.analysis.trace_branches`)."""
    core = nx.Graph()
    for k, br in enumerate(branches):
        p = truth.positions[list(br.nodes)]
        half = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) / 2
        # A middle node per branch: parallel branches and loops stay simple cycles.
        core.add_edge(int(br.nodes[0]), ("mid", k), weight=half)
        core.add_edge(("mid", k), int(br.nodes[-1]), weight=half)
    cycles = nx.minimum_cycle_basis(core, weight="weight")
    nodes: set[int] = set()
    filled = 0
    for cycle in cycles:
        walk = [e[0] for e in nx.find_cycle(core.subgraph(cycle))]
        ring: list[int] = []
        for k, x in enumerate(walk):
            if isinstance(x, tuple):
                path = list(branches[x[1]].nodes)
                ring += (path if path[0] == walk[k - 1] else path[::-1])[:-1]
        if len(ring) >= 3 and _filled(truth.positions[ring] / truth.spacing, mask):
            filled += 1
            nodes |= set(ring)
    return nodes, filled, len(cycles)


def branch_counts(
    truth: VesselGraph, branches: list[Any], graph: VesselGraph, near: np.ndarray
) -> Counter[str]:
    """Branches of both networks: all and not found, near filled loops and elsewhere;
    ``branches`` are the truth's, traced once per case."""
    kd = cKDTree(near) if len(near) else None
    sides = {"truth": branches, "graph": trace_branches(graph)}
    ends = {s: [(b.nodes[0], b.nodes[-1]) for b in brs] for s, brs in sides.items()}
    core = {s: sorted({n for e in ends[s] for n in e}) for s in sides}
    lt, lg = _match_core_nodes(
        truth.positions[core["truth"]], graph.positions[core["graph"]], SIGMA
    )
    label = {
        "truth": {core["truth"][i]: x for i, x in lt.items()},
        "graph": {core["graph"][j]: x for j, x in lg.items()},
    }
    pairs = {
        s: Counter(
            tuple(sorted((label[s][u], label[s][v])))
            for u, v in ends[s]
            if u in label[s] and v in label[s]
        )
        for s in sides
    }
    out: Counter[str] = Counter()
    for s, g in (("truth", truth), ("graph", graph)):
        other = pairs["graph" if s == "truth" else "truth"]
        used: Counter[tuple[int, ...]] = Counter()
        for br, (u, v) in zip(sides[s], ends[s]):
            where = "elsewhere"
            if kd is not None and np.any(kd.query(g.positions[list(br.nodes)])[0] <= NEAR):
                where = "near"
            out[f"{s} {where}"] += 1
            key = tuple(sorted((label[s].get(u, -1), label[s].get(v, -1))))
            if -1 not in key and used[key] < other[key]:
                used[key] += 1
            else:
                out[f"{s} {where} not found"] += 1
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", default="heldout", choices=sorted(F.SEED_SETS))
    ap.add_argument("--levels", nargs="+", default=["D0", "D2"], choices=F.LEVELS)
    ap.add_argument("--methods", nargs="+", default=["vesselflow", "voxel", "teasar"])
    ap.add_argument("--out", default="benches/results/filled_loops.md")
    args = ap.parse_args()
    count = F.FAMILIES["forest"][1]
    totals: dict[tuple[str, str], Counter[str]] = {}
    cycles: dict[str, list[int]] = {}
    for level in args.levels:
        cycles[level] = [0, 0]
        for k in range(count):
            seed = F.SEED_SETS[args.set] + k
            recipe = F.Recipe("forest", f"forest{seed:04d}", level, seed, args.set, k)
            case = F.build_synthetic(recipe)
            branches = trace_branches(case.truth)
            nodes, filled, total = filled_cycle_nodes(case.truth, branches, case.mask)
            cycles[level][0] += filled
            cycles[level][1] += total
            near = case.truth.positions[sorted(nodes)]
            for method in args.methods:
                options: dict[str, Any] = {"threads": 1} if method == "vesselflow" else {}
                graph = compare.run(method, case.mask, case.spacing, **options)
                totals.setdefault((level, method), Counter()).update(
                    branch_counts(case.truth, branches, graph, near)
                )
            print(level, recipe.name, "done", time.strftime("%H:%M:%S"), flush=True)
    Path(args.out).write_text(report(totals, cycles, args, count))


def report(
    totals: dict[tuple[str, str], Counter[str]],
    cycles: dict[str, list[int]],
    args: Any,
    count: int,
) -> str:
    levels = " ".join(args.levels)
    lines = [
        "# Connectivity errors at loops of the truth that the mask fills",
        "",
        f"Generated by `python benches/filled_loops.py --set {args.set} --levels {levels}` "
        f"on {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}: the {count} forests of "
        f"the {args.set} set per level (the second family of `benches/fidelity.py`). "
        "How the loops and branches are classified: the bench's docstring.",
        "",
        "| level | truth basis cycles | filled by the mask |",
        "|---|---|---|",
    ]
    for level, (filled, total) in cycles.items():
        lines.append(f"| {level} | {total} | {filled} ({100 * filled / max(total, 1):.0f} %) |")
    lines += [
        "",
        "Branches near a filled loop (within 3 voxels of one of its nodes) and elsewhere, and "
        "the share of each not found (sigma = 2 voxels, both end nodes matched and the "
        "other network joining the same pair).",
        "",
        "| level | method | truth branches near / elsewhere | not found near / elsewhere "
        "| graph branches near / elsewhere | not found near / elsewhere |",
        "|---|---|---|---|---|---|",
    ]
    for (level, method), c in totals.items():
        cells = []
        for s in ("truth", "graph"):
            n, e = c[f"{s} near"], c[f"{s} elsewhere"]
            fn, fe = c[f"{s} near not found"], c[f"{s} elsewhere not found"]
            cells.append(f"{n} / {e}")
            cells.append(f"{100 * fn / max(n, 1):.0f} % / {100 * fe / max(e, 1):.0f} %")
        lines.append(f"| {level} | {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
