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
//! Passes repeat until nothing changes, so a spur that becomes short only after its
//! own spurs go is pruned too. Each pass removes at most `degree - 2` spurs per junction,
//! shortest first (ties in the order the branches are traced: from every node of degree
//! other than 2 by id, along its edges in edge order), so a junction never becomes an
//! end: components, loops and endpoint-endpoint branches are never removed, and a
//! junction left with two branches becomes an ordinary path node. The same rule prunes
//! a graph after the fact (`VesselGraph.prune` in Python).

use crate::graph::Skeleton;
use crate::vec3::{norm, sub};
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
/// than `k` times their junction's radius (see the module); `positions` and `radii`
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

/// One pass: the spurs to remove from the graph of `n` nodes and `edges`.
fn spurs_of(n: usize, edges: &[[usize; 2]], positions: &[[f64; 3]], radii: &[f64], k: f64) -> Vec<Spur> {
    let mut degree = vec![0usize; n];
    let mut adjacency: Vec<Vec<(usize, usize)>> = vec![Vec::new(); n];
    for (e, &[a, b]) in edges.iter().enumerate() {
        degree[a] += 1;
        degree[b] += 1;
        adjacency[a].push((b, e));
        adjacency[b].push((a, e));
    }
    let mut used = vec![false; edges.len()];
    // Per junction, its short spurs in the order they are traced.
    let mut short: BTreeMap<usize, Vec<Spur>> = BTreeMap::new();
    for start in 0..n {
        if degree[start] == 2 {
            continue;
        }
        for &(first, edge) in &adjacency[start] {
            if used[edge] {
                continue;
            }
            // Along degree-2 nodes to the next node of another degree (at most every edge).
            let (mut nodes, mut path) = (vec![start], vec![edge]);
            used[edge] = true;
            let (mut node, mut edge) = (first, edge);
            let mut length = norm(sub(positions[first], positions[start]));
            while degree[node] == 2 && path.len() <= edges.len() {
                nodes.push(node);
                let [(a, ea), (b, eb)] = [adjacency[node][0], adjacency[node][1]];
                let next = if ea == edge { (b, eb) } else { (a, ea) };
                length += norm(sub(positions[next.0], positions[node]));
                (node, edge) = next;
                used[edge] = true;
                path.push(edge);
            }
            nodes.push(node);
            let (head, tail) = (nodes[0], node);
            if (degree[head] > 2) == (degree[tail] > 2) {
                continue;
            }
            let junction = if degree[head] > 2 { head } else { tail };
            if length < k * radii[junction] {
                let others = nodes.into_iter().filter(|&i| i != junction).collect();
                short.entry(junction).or_default().push((length, path, others));
            }
        }
    }
    let mut out = Vec::new();
    for (junction, mut spurs) in short {
        spurs.sort_by(|a, b| a.0.total_cmp(&b.0));
        out.extend(spurs.into_iter().take(degree[junction] - 2));
    }
    out
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
