//! Spur pruning (the last output step, with `prune_spurs`; not in the paper).
//!
//! A spur is a junction-endpoint branch: a path of degree-2 nodes from a node of
//! degree 1 to a junction (degree 3 or more). It is short when its length is below
//! `k` times the radius of its junction. A spur shorter than the junction's own radius
//! ends inside the parent vessel's lumen: it is a knot the contraction or the medial
//! stage left beside the centreline (a stub a voxel or two long, or a few nodes of a
//! second rail), not a vessel, and it splits the parent's branch in two at a false
//! junction. The criterion is scale-free: a bump on a thick vessel goes, a thin branch
//! of the same length on a thin vessel stays.
//!
//! A second rail can be longer than the radius and still lie inside the lumen: it runs
//! beside the vessel it left. So a terminal branch also counts as short, whatever its
//! length, when every one of its nodes lies within `k` radii of another branch of its
//! junction (closer to one of that branch's segments than `k` times the radius there,
//! linear along the segment). A real side branch leaves its parent's lumen, so its far
//! nodes fail the test; two vessels that merely touch keep their centrelines the sum of
//! their radii apart. On a tube along the volume's diagonal (radius 3) the contraction
//! left a rail of 12 voxels (4 radii) beside the centreline, joined at one end.
//!
//! Passes repeat until nothing changes, so a spur that becomes short only after its
//! own spurs go is pruned too. Each pass removes at most `degree - 2` spurs per junction,
//! shortest first (ties in the order the branches are traced: from every node of degree
//! other than 2 by id, along its edges in edge order), so a junction never becomes an
//! end: components, loops and endpoint-endpoint branches are never removed, and a
//! junction left with two branches becomes an ordinary path node. The same rule prunes
//! a graph after the fact (`VesselGraph.prune` in Python).

use crate::graph::Skeleton;
use crate::vec3::{norm, projection, sub};
use std::collections::BTreeMap;

/// What a pruning keeps: `nodes[i]` and `edges[e]` for the input's node `i` and edge
/// `e`, and how many spurs it removed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Pruned {
    pub nodes: Vec<bool>,
    pub edges: Vec<bool>,
    pub spurs: usize,
}

/// One spur found in a pass: its length, edges (indices into the pass's live edges)
/// and nodes other than its junction.
type Spur = (f64, Vec<usize>, Vec<usize>);

/// Prune the spurs of the graph of `n` nodes and `edges` (node ids below `n`) shorter
/// than `k` times their junction's radius or inside the lumen of another branch of
/// their junction (see the module); `positions` and `radii`
/// per node, in the same units. `k` of 0 (or less, or NaN) prunes nothing.
pub fn prune_spurs(n: usize, edges: &[[usize; 2]], positions: &[[f64; 3]], radii: &[f64], k: f64) -> Pruned {
    let mut kept = Pruned { nodes: vec![true; n], edges: vec![true; edges.len()], spurs: 0 };
    if k.is_nan() || k <= 0.0 {
        return kept;
    }
    // Every pass but the last removes at least one spur, hence an edge.
    for _ in 0..=edges.len() {
        let live: Vec<usize> = (0..edges.len()).filter(|&e| kept.edges[e]).collect();
        let found = spurs_of(n, &live.iter().map(|&e| edges[e]).collect::<Vec<_>>(), positions, radii, k);
        if found.is_empty() {
            break;
        }
        for spur in found {
            for e in spur.1 {
                kept.edges[live[e]] = false;
            }
            for i in spur.2 {
                kept.nodes[i] = false;
            }
            kept.spurs += 1;
        }
    }
    kept
}

/// `skeleton` without its spurs shorter than `k` radii of their junction
/// ([`prune_spurs`]): the kept nodes renumbered densely in their old order, the kept
/// edges in their old order, and `info.pruned_spurs` set to the count removed.
pub fn prune_skeleton(skeleton: Skeleton, k: f64) -> Skeleton {
    let Skeleton { positions, radii, edges, spacing, mut info } = skeleton;
    let kept = prune_spurs(positions.len(), &edges, &positions, &radii, k);
    info.pruned_spurs = kept.spurs;
    if kept.spurs == 0 {
        return Skeleton { positions, radii, edges, spacing, info };
    }
    let mut id = vec![usize::MAX; positions.len()];
    let mut next = 0;
    for (i, &keep) in kept.nodes.iter().enumerate() {
        if keep {
            id[i] = next;
            next += 1;
        }
    }
    let keep = |i: usize| kept.nodes[i];
    Skeleton {
        positions: positions.into_iter().enumerate().filter(|&(i, _)| keep(i)).map(|(_, p)| p).collect(),
        radii: radii.into_iter().enumerate().filter(|&(i, _)| keep(i)).map(|(_, r)| r).collect(),
        edges: edges.iter().zip(&kept.edges).filter(|(_, &k)| k).map(|(e, _)| e.map(|i| id[i])).collect(),
        spacing,
        info,
    }
}

/// Every node's neighbours and the edges to them, in edge order.
pub(crate) fn adjacency(n: usize, edges: &[[usize; 2]]) -> Vec<Vec<(usize, usize)>> {
    let mut adjacency: Vec<Vec<(usize, usize)>> = vec![Vec::new(); n];
    for (e, &[a, b]) in edges.iter().enumerate() {
        adjacency[a].push((b, e));
        adjacency[b].push((a, e));
    }
    adjacency
}

/// The branch leaving `start` along `edge`: its nodes from `start` to the first node of
/// degree other than 2 (or back at `start`), its edges and its length.
pub(crate) fn trace(
    start: usize,
    edge: usize,
    adjacency: &[Vec<(usize, usize)>],
    positions: &[[f64; 3]],
) -> (Vec<usize>, Vec<usize>, f64) {
    let first = adjacency[start].iter().find(|&&(_, e)| e == edge).map_or(start, |&(w, _)| w);
    let (mut nodes, mut path) = (vec![start], vec![edge]);
    let (mut node, mut edge) = (first, edge);
    let mut length = norm(sub(positions[first], positions[start]));
    // Along degree-2 nodes, each at most once.
    while adjacency[node].len() == 2 && node != start && path.len() <= positions.len() {
        nodes.push(node);
        let [(a, ea), (b, eb)] = [adjacency[node][0], adjacency[node][1]];
        let next = if ea == edge { (b, eb) } else { (a, ea) };
        length += norm(sub(positions[next.0], positions[node]));
        (node, edge) = next;
        path.push(edge);
    }
    nodes.push(node);
    (nodes, path, length)
}

/// Whether every node of `spur` (checked in the given order) lies within `k` radii of
/// one of the `rails` (the other branches of its junction, as node lists): closer to one
/// of their segments than `k` times the radius there (linear along the segment). Such
/// a spur runs inside the lumen of the vessel beside it, however long it is (a second
/// rail).
fn in_lumen(spur: &[usize], rails: &[&[usize]], positions: &[[f64; 3]], radii: &[f64], k: f64) -> bool {
    spur.iter().all(|&i| {
        let p = positions[i];
        rails.iter().flat_map(|r| r.windows(2)).any(|w| {
            let (t, d) = projection(p, positions[w[0]], positions[w[1]]);
            d < k * (radii[w[0]] + t * (radii[w[1]] - radii[w[0]]))
        })
    })
}

/// One pass: the spurs to remove from the graph of `n` nodes and `edges`.
fn spurs_of(n: usize, edges: &[[usize; 2]], positions: &[[f64; 3]], radii: &[f64], k: f64) -> Vec<Spur> {
    let adjacency = adjacency(n, edges);
    let degree = |i: usize| adjacency[i].len();
    // Every branch once, in tracing order, and the branches at each junction.
    let mut used = vec![false; edges.len()];
    let mut branches = vec![];
    let mut at: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for start in 0..n {
        if degree(start) == 2 {
            continue;
        }
        for &(_, edge) in &adjacency[start] {
            if used[edge] {
                continue;
            }
            let (nodes, path, length) = trace(start, edge, &adjacency, positions);
            for &e in &path {
                used[e] = true;
            }
            let (head, tail) = (nodes[0], nodes[nodes.len() - 1]);
            for end in [head, tail] {
                if degree(end) > 2 {
                    let list = at.entry(end).or_default();
                    // A loop from a junction back to it is one of its branches once.
                    if list.last() != Some(&branches.len()) {
                        list.push(branches.len());
                    }
                }
            }
            branches.push((nodes, path, length));
        }
    }
    // Per junction, its spurs in the lumen in the order they are traced.
    let mut inside: BTreeMap<usize, Vec<Spur>> = BTreeMap::new();
    for (b, (nodes, path, length)) in branches.iter().enumerate() {
        let (head, tail) = (nodes[0], nodes[nodes.len() - 1]);
        if (degree(head) > 2) == (degree(tail) > 2) {
            continue;
        }
        let junction = if degree(head) > 2 { head } else { tail };
        // Its nodes from the free end: a real branch fails the lumen test at the first.
        let mut others: Vec<usize> = nodes.iter().copied().filter(|&i| i != junction).collect();
        if junction == head {
            others.reverse();
        }
        let short = *length < k * radii[junction] || {
            let rails: Vec<&[usize]> =
                at[&junction].iter().filter(|&&r| r != b).map(|&r| branches[r].0.as_slice()).collect();
            in_lumen(&others, &rails, positions, radii, k)
        };
        if short {
            inside.entry(junction).or_default().push((*length, path.clone(), others));
        }
    }
    let mut out = Vec::new();
    for (junction, mut spurs) in inside {
        spurs.sort_by(|a, b| a.0.total_cmp(&b.0));
        let go = spurs_that_go(degree(junction), 0, spurs.len());
        out.extend(spurs.into_iter().take(go));
    }
    out
}

/// How many of a junction's `candidates` spurs go (shortest first) when `gone` of its
/// `degree` neighbours already go: no more than leave it two neighbours, so that pruning
/// never turns a vessel's last junction into an end or breaks the vessel there. The
/// single run's pruning and the merge's removal of seam spurs both keep this rule.
pub(crate) fn spurs_that_go(degree: usize, gone: usize, candidates: usize) -> usize {
    candidates.min(degree.saturating_sub(gone + 2))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A vessel along axis 2 (radius 2) through node 1, with a 1-long bump at node 1
    /// (node 3) and a 6-long branch (nodes 4, 5) at node 2's end of the vessel.
    fn bumpy() -> (Vec<[f64; 3]>, Vec<f64>, Vec<[usize; 2]>) {
        let positions = vec![[0.0, 0.0, 0.0], [0.0, 0.0, 5.0], [0.0, 0.0, 10.0], [0.0, 1.0, 5.0], [0.0, 3.0, 5.0]];
        let radii = vec![2.0, 2.0, 2.0, 1.0, 1.0];
        (positions, radii, vec![[0, 1], [1, 2], [1, 3], [3, 4]])
    }

    #[test]
    fn a_spur_shorter_than_k_radii_of_its_junction_goes() {
        let (p, r, e) = bumpy();
        // Nodes 1-3-4 are 3 long: below 2 radii of node 1 (4), not below 1 radius (2).
        let pruned = prune_spurs(5, &e, &p, &r, 2.0);
        assert_eq!(pruned.nodes, [true, true, true, false, false]);
        assert_eq!(pruned.edges, [true, true, false, false]);
        assert_eq!(pruned.spurs, 1);
        assert_eq!(prune_spurs(5, &e, &p, &r, 1.0).spurs, 0);
        assert_eq!(prune_spurs(5, &e, &p, &r, 0.0).spurs, 0);
    }

    #[test]
    fn a_junction_never_becomes_an_end_and_a_spur_of_a_spur_goes_too() {
        // A star of three 1-long arms: at most degree - 2 = 1 goes per pass; then the
        // centre is a path node and nothing is a spur any more.
        let p = vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let star = prune_spurs(4, &[[0, 1], [0, 2], [0, 3]], &p, &[5.0; 4], 1.0);
        assert_eq!(star.spurs, 1);
        assert_eq!(star.edges.iter().filter(|&&k| k).count(), 2);
        // Node 2 carries a short spur (node 3) on a spur (node 2) of the vessel 0-1-4:
        // once 3 goes, 2 is a short spur of 1 and goes in the next pass.
        let p =
            vec![[0.0, 0.0, 0.0], [0.0, 0.0, 5.0], [0.0, 1.0, 5.0], [0.0, 1.0, 5.5], [0.0, 0.0, 10.0], [0.0, 1.5, 5.0]];
        let e = [[0, 1], [1, 2], [2, 3], [1, 4], [2, 5]];
        let pruned = prune_spurs(6, &e, &p, &[3.0, 3.0, 1.0, 1.0, 3.0, 1.0], 1.0);
        assert_eq!(pruned.nodes, [true, true, false, false, true, false]);
        assert_eq!(pruned.spurs, 2);
    }

    /// A vessel along axis 2 (radius 2, nodes 0-1-2-3) with a junction at node 1 and a
    /// second branch from it (nodes 4-5-6) `off` from the axis where it ends, 8 long.
    fn railed(off: f64) -> Pruned {
        let p = vec![
            [0.0, 0.0, 0.0],
            [0.0, 0.0, 5.0],
            [0.0, 0.0, 10.0],
            [0.0, 0.0, 20.0],
            [0.0, 0.6, 7.0],
            [0.0, 0.6 + (off - 0.6) / 2.0, 10.0],
            [0.0, off, 13.0],
        ];
        let e = [[0, 1], [1, 2], [2, 3], [1, 4], [4, 5], [5, 6]];
        prune_spurs(7, &e, &p, &[2.0; 7], 1.0)
    }

    #[test]
    fn a_second_rail_inside_the_lumen_goes_however_long() {
        // Every node of the rail within a radius of the vessel beside it: pruned, though
        // 8 long (4 radii of its junction).
        let rail = railed(1.0);
        assert_eq!(rail.spurs, 1);
        assert_eq!(rail.nodes, [true, true, true, true, false, false, false]);
        // A branch that leaves the lumen (its end 3 from the axis, radius 2) stays.
        assert_eq!(railed(3.0).spurs, 0);
    }

    #[test]
    fn loops_and_lone_branches_stay() {
        // A triangle with a long tail, and a lone 1-long segment.
        let p = vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 9.0], [5.0, 5.0, 5.0], [5.0, 5.0, 6.0]];
        let e = [[0, 1], [1, 2], [0, 2], [0, 3], [4, 5]];
        let pruned = prune_spurs(6, &e, &p, &[1.0; 6], 100.0);
        // The tail is the only spur; the triangle and the segment stay.
        assert_eq!(pruned.nodes, [true, true, true, false, true, true]);
        assert_eq!(pruned.edges, [true, true, true, false, true]);
    }
}
