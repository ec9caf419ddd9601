"""Which loops of the mask vesselflow's graph loses, and how wide their holes are.

The fidelity benchmark's loop error counts, per synthetic forest, ``|graph cycles -
clean-mask loops|``; this tool says which loops those are. For each forest of a seed set
(the fidelity benchmark's volumes, made by its own ``build_synthetic``) and each noise
level, it locates the loops of the *clean* mask on its thinning skeleton
(scikit-image ``skeletonize``, skan's branches, a minimum cycle basis of the branch graph
weighted by length), runs vesselflow with its defaults on the mask the benchmark feeds it
(clean or with bubble noise), and calls a loop lost when no cycle of the graph's minimum
cycle basis has its centroid within ``max(3, loop radius / 2)`` voxels of the loop's.
For every lost loop it prints the loop's radius (mean distance of its skeleton voxels
from their centroid), the vessels' radius along it (the clean mask's EDT on its
skeleton voxels), the hole's width in vessel radii, ``(loop radius - r) / r`` (the loop
rule of ``docs/method.md`` keeps a hole at least as wide as its vessels: 1), and the
input mask's distance from the loop's centroid to its nearest vessel voxel (0: the noise
filled the hole there, or the loop does not lie in a plane).

The location is a heuristic: thinning can miss a loop of the mask (the skeleton's loops
are then fewer than the clean mask's first Betti number, which the report shows), and a
graph cycle near a lost loop (a noise loop) hides it. It explains the loop error; the
fidelity benchmark measures it.

    python benches/loops.py                       # held-out forests, clean and D0-D2
    python benches/loops.py --set tuning --levels D2
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import networkx as nx
import numpy as np
from fidelity import SEED_SETS, Recipe, build_synthetic  # this folder: the benchmark's volumes
from scipy import ndimage as ndi
from skan import Skeleton
from skimage.morphology import skeletonize

import vesselflow
from vesselflow.analysis import trace_branches
from vesselflow.graph import VesselGraph

OUT = Path(__file__).resolve().parent / "results" / "loops.md"


def minimum_loops(branches: list[tuple[int, int, float]]) -> list[list[int]]:
    """A minimum cycle basis of a graph given as branches ``(end, end, weight)``, each loop
    as the indices of its branches. Every branch is split in three, so that two branches
    between the same ends, and a branch that closes on itself, make cycles."""
    g = nx.Graph()
    for b, (a, z, weight) in enumerate(branches):
        first, second = ("branch", b, 1), ("branch", b, 2)
        g.add_edge(("end", a), first, weight=weight / 3)
        g.add_edge(first, second, weight=weight / 3)
        g.add_edge(second, ("end", z), weight=weight / 3)
    return [
        sorted({k[1] for k in cycle if k[0] == "branch"})
        for cycle in nx.minimum_cycle_basis(g, weight="weight")
    ]


def skeleton_loops(clean: np.ndarray) -> list[np.ndarray]:
    """The clean mask's loops as arrays of skeleton voxel coordinates: the minimum loops
    of the skeleton's branches (skan), weighted by branch length."""
    skel = Skeleton(skeletonize(clean))
    paths = [skel.path_coordinates(b) for b in range(skel.n_paths)]
    ends = [skel.path(b) for b in range(skel.n_paths)]
    branches = [
        (int(ids[0]), int(ids[-1]), float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()))
        for ids, pts in zip(ends, paths)
    ]
    return [np.concatenate([paths[b] for b in loop]) for loop in minimum_loops(branches)]


def graph_cycle_centroids(graph: VesselGraph) -> np.ndarray:
    """The centroids (in voxels) of the graph's minimum loops, by edge count, over its
    branches (``vesselflow.analysis.trace_branches``): a search over the few hundred
    branches rather than every node."""
    traced = trace_branches(graph)
    branches = [(b.nodes[0], b.nodes[-1], float(len(b.edges))) for b in traced]
    centroids = []
    for loop in minimum_loops(branches):
        nodes = sorted({n for b in loop for n in traced[b].nodes})
        centroids.append(graph.positions[nodes].mean(axis=0) / graph.spacing)
    return np.array(centroids) if centroids else np.zeros((0, 3))


def one_case(seed: int, seed_set: str, level: str) -> dict[str, Any]:
    name = f"forest{seed:04d}"
    clean_case = build_synthetic(Recipe("forest", name, "", seed, seed_set))
    case = (
        clean_case
        if level == "clean"
        else build_synthetic(Recipe("forest", name, level, seed, seed_set))
    )
    clean = clean_case.mask
    loops = skeleton_loops(clean)
    edt = ndi.distance_transform_edt(clean)
    background = ndi.distance_transform_edt(~case.mask.astype(bool))
    graph = vesselflow.skeletonize(case.mask, spacing=case.spacing)
    centroids = graph_cycle_centroids(graph)
    lost = []
    for pts in loops:
        centre = pts.mean(axis=0)
        radius = float(np.linalg.norm(pts - centre, axis=1).mean())
        near = np.linalg.norm(centroids - centre, axis=1).min() if len(centroids) else np.inf
        if near > max(3.0, 0.5 * radius):
            r = float(edt[tuple(np.round(pts).astype(int).T)].mean())
            voxel = tuple(np.round(centre).astype(int))
            lost.append(
                {
                    "at": tuple(int(x) for x in voxel),
                    "loop_radius": radius,
                    "r": r,
                    "hole": (radius - r) / r,
                    "input_gap": float(background[voxel]),
                }
            )
    return {
        "name": name,
        "level": level,
        "clean_loops": clean_case.clean_loops,
        "skeleton_loops": len(loops),
        "graph_cycles": len(centroids),
        "lost": lost,
    }


def report(rows: list[dict[str, Any]], seed_set: str) -> str:
    lines = [
        "# Lost loops",
        "",
        f"Generated by `python benches/loops.py --set {seed_set}` on "
        f"{time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC (see its docstring). "
        "Per forest and level: the clean mask's loops (first Betti number), those thinning "
        "locates, the graph's cycle rank, and every located loop with no graph cycle near it.",
        "",
        "| forest | level | clean-mask loops | located | graph cycles | lost (at voxel: loop "
        "radius, vessel r, hole / r, input's gap at the centre) |",
        "|---|---|---:|---:|---:|---|",
    ]
    for row in rows:
        lost = "; ".join(
            f"{x['at']}: {x['loop_radius']:.1f}, {x['r']:.2f}, {x['hole']:.2f}, "
            f"{x['input_gap']:.2f}"
            for x in row["lost"]
        )
        lines.append(
            f"| {row['name']} | {row['level']} | {row['clean_loops']} | {row['skeleton_loops']} | "
            f"{row['graph_cycles']} | {lost or '-'} |"
        )
    lines += [
        "",
        "| level | loop error (summed, % of clean-mask loops) | lost | of them hole / r < 1.1 | "
        "input's gap ≤ 1.5 voxels |",
        "|---|---:|---:|---:|---:|",
    ]
    for level in dict.fromkeys(r["level"] for r in rows):
        part = [r for r in rows if r["level"] == level]
        clean = sum(r["clean_loops"] for r in part)
        error = sum(abs(r["graph_cycles"] - r["clean_loops"]) for r in part)
        lost = [x for r in part for x in r["lost"]]
        narrow = sum(x["hole"] < 1.1 for x in lost)
        gap = sum(x["input_gap"] <= 1.5 for x in lost)
        lines.append(
            f"| {level} | {error} ({100 * error / clean:.0f} %) | {len(lost)} | {narrow} | {gap} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--set", choices=sorted(SEED_SETS), default="heldout")
    parser.add_argument("--count", type=int, default=8, help="forests (the fidelity benchmark's 8)")
    parser.add_argument("--levels", nargs="+", default=["clean", "D0", "D1", "D2"])
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    rows = []
    for level in args.levels:
        for i in range(args.count):
            row = one_case(SEED_SETS[args.set] + i, args.set, level)
            print(
                row["name"],
                level,
                row["clean_loops"],
                row["graph_cycles"],
                len(row["lost"]),
                flush=True,
            )
            rows.append(row)
    text = report(rows, args.set)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
