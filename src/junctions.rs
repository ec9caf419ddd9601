//! Junctions closer than half a vessel radius are one (output, after the spur pruning;
//! not in the paper).
//!
//! Where four or more vessels meet at a point (a crossing of a capillary bed, a
//! lattice's node), the contraction resolves the meeting as a few junctions of degree 3
//! joined by branches far shorter than the vessels are wide, and the medial stage moves
//! each of those junctions to where its own branches' centrelines meet, the same point:
//! they end up a fraction of a radius apart. A branch shorter than half its vessel's
//! radius is no vessel (the segmentation cannot resolve it), and it splits one meeting
//! into several junctions, of which a comparison with the true network matches one:
//! on the fidelity benchmark's tuning lattices, connectivity false negatives / positives
//! 0.105 / 0.223 with the split meetings, 0.031 / 0.073 with them joined (README, "Where
//! we differ").
//!
//! The rule (`merge_junctions = k`, default 0.5): a branch between two junctions
//! (degree ≥ 3) shorter than `k` times the larger of their radii is contracted, its two
//! junctions becoming one node at their mean position with the larger radius. Chains of
//! such branches join a meeting of many vessels into one node. Where vessels cross at
//! an acute angle the split junctions lie farther apart; a branch up to [`CROSSING`]
//! times that bound is contracted too when the joined node is a crossing: two pairs of
//! its branches run straight through it ([`THROUGH`]). Two bifurcations close together
//! on a parent vessel have one such pair, the parent, and stay two. A contraction that
//! would fold a loop of the graph onto itself (the two junctions joined by another
//! branch of one or two edges, or a common neighbour) is not made, so components and
//! loops are kept: the cycle rank is unchanged. Deterministic: branches are taken shortest first, ties by their ends' ids.

use crate::decimate::mean_and_largest;
use crate::graph::Skeleton;
use crate::prune::{adjacency, trace};
use crate::vec3::{dot, norm, sub, unit};
use std::collections::BTreeSet;

/// How much longer than the bound a branch may be and still be contracted when the
/// joined node is a crossing. Chosen on the fidelity benchmark's tuning set (README,
/// "Where we differ", 19): lattices' connectivity false negatives / positives 0.028 /
/// 0.069 without it, 0.016 / 0.040 at 1.5, 0.012 / 0.032 at 2 where the forests' rose
/// by 0.005.
pub const CROSSING: f64 = 1.5;

/// Two branches of a joined node run straight through it when the cosine between their
/// outward directions is below `-THROUGH` (within about 45° of opposite).
pub const THROUGH: f64 = 0.7;

/// A short branch between two junctions: its length, its ends (`ends[0] < ends[1]`),
/// its inner nodes and its edges; `crossing` when it is contracted only if the joined
/// node is a crossing.
struct Short {
    length: f64,
    crossing: bool,
    ends: [usize; 2],
    inner: Vec<usize>,
    edges: Vec<usize>,
}

/// `skeleton` with every branch between two junctions shorter than `k` times their
/// larger radius contracted (module doc; `k` of 0, or less, or NaN, joins none): kept
/// nodes renumbered densely in their old order (a joined meeting keeps its smallest
/// junction's id), kept edges in their old order, each with its smaller node first.
pub fn merge_close_junctions(skeleton: Skeleton, k: f64) -> Skeleton {
    let Skeleton { mut positions, mut radii, edges, spacing, info } = skeleton;
    if k.is_nan() || k <= 0.0 {
        return Skeleton { positions, radii, edges, spacing, info };
    }
    let n = positions.len();
    let adjacency = adjacency(n, &edges);
    let degree = |i: usize| adjacency[i].len();
    let mut used = vec![false; edges.len()];
    let mut short = vec![];
    for start in (0..n).filter(|&i| degree(i) >= 3) {
        for &(_, edge) in &adjacency[start] {
            if used[edge] {
                continue;
            }
            let (nodes, path, length) = trace(start, edge, &adjacency, &positions);
            for &e in &path {
                used[e] = true;
            }
            let end = nodes[nodes.len() - 1];
            let bound = k * radii[start].max(radii[end]);
            if end != start && degree(end) >= 3 && length < CROSSING * bound {
                let inner = nodes[1..nodes.len() - 1].to_vec();
                let ends = [start.min(end), start.max(end)];
                short.push(Short { length, crossing: length >= bound, ends, inner, edges: path });
            }
        }
    }
    if short.is_empty() {
        return Skeleton { positions, radii, edges, spacing, info };
    }
    short.sort_by(|a, b| a.length.total_cmp(&b.length).then(a.ends.cmp(&b.ends)));

    // Groups of joined junctions, each led by its smallest member.
    let mut leader: Vec<usize> = (0..n).collect();
    let find = |leader: &[usize], mut i: usize| {
        while leader[i] != i {
            i = leader[i];
        }
        i
    };
    let mut members: Vec<Vec<usize>> = (0..n).map(|i| vec![i]).collect();
    let mut removed_node = vec![false; n];
    let mut removed_edge = vec![false; edges.len()];
    // The groups next to a group, through the edges still kept other than `skip` (a
    // branch's own edges, a handful).
    let neighbours = |group: &[usize], removed_edge: &[bool], leader: &[usize], skip: &[usize]| {
        let mut out = BTreeSet::new();
        for &m in group {
            for &(w, e) in &adjacency[m] {
                if !removed_edge[e] && !skip.contains(&e) {
                    out.insert(find(leader, w));
                }
            }
        }
        out
    };
    for s in &short {
        let (a, b) = (find(&leader, s.ends[0]), find(&leader, s.ends[1]));
        if a == b {
            continue;
        }
        // Safe when the branch is the groups' only link of one or two edges: no other
        // edge between them and no common neighbour (other than the branch's own node).
        let near_a = neighbours(&members[a], &removed_edge, &leader, &s.edges);
        let near_b = neighbours(&members[b], &removed_edge, &leader, &s.edges);
        if near_a.contains(&b) || near_a.intersection(&near_b).next().is_some() {
            continue;
        }
        if s.crossing {
            let joined: Vec<u32> = members[a].iter().chain(&members[b]).map(|&m| m as u32).collect();
            if through_pairs(&joined, &adjacency, &removed_edge, &s.edges, &positions, &radii) < 2 {
                continue;
            }
        }
        for &e in &s.edges {
            removed_edge[e] = true;
        }
        for &i in &s.inner {
            removed_node[i] = true;
        }
        let (keep, gone) = (a.min(b), a.max(b));
        leader[gone] = keep;
        removed_node[gone] = true;
        let moved = std::mem::take(&mut members[gone]);
        members[keep].extend(moved);
    }

    // Each group at its members' mean position (in id order) with their largest radius,
    // as decimation merges a cluster (ids fit in the `u32` the core's graphs use).
    for (first, group) in members.iter_mut().enumerate() {
        if group.len() < 2 || removed_node[first] {
            continue;
        }
        group.sort_unstable();
        let ids: Vec<u32> = group.iter().map(|&m| m as u32).collect();
        (positions[first], radii[first]) = mean_and_largest(&ids, &positions, &radii);
    }
    let mut id = vec![usize::MAX; n];
    let mut next = 0;
    for i in 0..n {
        if !removed_node[i] {
            id[i] = next;
            next += 1;
        }
    }
    let kept_edges = edges
        .iter()
        .zip(&removed_edge)
        .filter(|(_, &gone)| !gone)
        .map(|(e, _)| {
            let [a, b] = e.map(|i| id[find(&leader, i)]);
            [a.min(b), a.max(b)]
        })
        .collect();
    let keep = |i: &usize| !removed_node[*i];
    Skeleton {
        positions: (0..n).filter(keep).map(|i| positions[i]).collect(),
        radii: (0..n).filter(keep).map(|i| radii[i]).collect(),
        edges: kept_edges,
        spacing,
        info,
    }
}

/// How many disjoint pairs of the branches leaving the junctions `joined` (through kept
/// edges other than `skip`) run straight through their mean position: each branch's
/// direction is from there to its first node two radii away (or its last node), pairs
/// taken most nearly opposite first.
fn through_pairs(
    joined: &[u32],
    adjacency: &[Vec<(usize, usize)>],
    removed_edge: &[bool],
    skip: &[usize],
    positions: &[[f64; 3]],
    radii: &[f64],
) -> usize {
    let (centre, largest) = mean_and_largest(joined, positions, radii);
    let reach = 2.0 * largest;
    let mut directions = vec![];
    for &m in joined {
        let m = m as usize;
        for &(first, e) in &adjacency[m] {
            if removed_edge[e] || skip.contains(&e) || joined.contains(&(first as u32)) {
                continue;
            }
            let (mut prev, mut cur) = (m, first);
            // Along degree-2 nodes, each at most once.
            for _ in 0..positions.len() {
                if adjacency[cur].len() != 2 || norm(sub(positions[cur], centre)) >= reach {
                    break;
                }
                let [(x, _), (y, _)] = [adjacency[cur][0], adjacency[cur][1]];
                (prev, cur) = (cur, if x == prev { y } else { x });
            }
            if let Some(u) = unit(sub(positions[cur], centre)) {
                directions.push(u);
            }
        }
    }
    let mut pairs: Vec<(f64, usize, usize)> = vec![];
    for x in 0..directions.len() {
        for y in x + 1..directions.len() {
            pairs.push((dot(directions[x], directions[y]), x, y));
        }
    }
    pairs.sort_by(|p, q| p.0.total_cmp(&q.0).then((p.1, p.2).cmp(&(q.1, q.2))));
    let mut used = vec![false; directions.len()];
    let mut found = 0;
    for (cos, x, y) in pairs {
        if cos < -THROUGH && !used[x] && !used[y] {
            (used[x], used[y]) = (true, true);
            found += 1;
        }
    }
    found
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::RunInfo;

    fn skeleton(positions: Vec<[f64; 3]>, radii: Vec<f64>, edges: Vec<[usize; 2]>) -> Skeleton {
        Skeleton { positions, radii, edges, spacing: [1.0; 3], info: RunInfo::default() }
    }

    /// Rank of the cycle space: edges - nodes + components.
    fn cycle_rank(s: &Skeleton) -> usize {
        let mut uf = petgraph::unionfind::UnionFind::<usize>::new(s.positions.len());
        for e in &s.edges {
            uf.union(e[0], e[1]);
        }
        let components = (0..s.positions.len()).filter(|&i| uf.find(i) == i).count();
        s.edges.len() + components - s.positions.len()
    }

    /// Two junctions `gap` apart along axis 0 (nodes 0 and 1) joined by an edge, each
    /// with two arms of three nodes 2 apart along the directions `arms[j]` (radius 2).
    fn two_junctions(gap: f64, arms: [[[f64; 3]; 2]; 2]) -> Skeleton {
        let mut positions = vec![[0.0, 0.0, 0.0], [gap, 0.0, 0.0]];
        let mut edges = vec![[0, 1]];
        for (junction, dirs) in arms.into_iter().enumerate() {
            for dir in dirs {
                let mut last = junction;
                for step in 1..=3 {
                    let base = positions[junction];
                    positions.push(std::array::from_fn(|d| base[d] + dir[d] * 2.0 * step as f64));
                    edges.push([last, positions.len() - 1]);
                    last = positions.len() - 1;
                }
            }
        }
        let radii = vec![2.0; positions.len()];
        skeleton(positions, radii, edges)
    }

    /// A crossing of two vessels of radius 2 along axes 1 and 2, resolved as two
    /// junctions `gap` apart along axis 0.
    fn split_crossing(gap: f64) -> Skeleton {
        two_junctions(gap, [[[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]])
    }

    #[test]
    fn a_crossing_split_by_less_than_half_a_radius_becomes_one_node_of_degree_four() {
        let out = merge_close_junctions(split_crossing(0.8), 0.5);
        assert_eq!(out.positions.len(), 13);
        assert_eq!(out.edges.len(), 12);
        let mut degree = vec![0; out.positions.len()];
        for e in &out.edges {
            degree[e[0]] += 1;
            degree[e[1]] += 1;
            assert!(e[0] < e[1], "{e:?}");
        }
        assert_eq!(degree[0], 4);
        assert_eq!(out.positions[0], [0.4, 0.0, 0.0]);
        assert_eq!(cycle_rank(&out), 0);
    }

    #[test]
    fn edges_keep_their_smaller_node_first_when_a_meeting_is_renumbered() {
        // The same crossing with its second junction numbered last: its arms' nodes lie
        // between the two junctions' ids, and their edges to it end at the joined node,
        // which keeps the first junction's smaller id.
        let s = split_crossing(0.8);
        let n = s.positions.len();
        let new_id = |i: usize| match i {
            0 => 0,
            1 => n - 1,
            i => i - 1,
        };
        let mut positions = s.positions.clone();
        for (i, p) in s.positions.iter().enumerate() {
            positions[new_id(i)] = *p;
        }
        let edges = s.edges.iter().map(|e| [new_id(e[0]).min(new_id(e[1])), new_id(e[0]).max(new_id(e[1]))]).collect();
        let out = merge_close_junctions(skeleton(positions, s.radii.clone(), edges), 0.5);
        assert_eq!(out.positions.len(), 13);
        assert!(out.edges.iter().all(|e| e[0] < e[1]), "{:?}", out.edges);
        assert_eq!(out.edges.iter().filter(|e| e[0] == 0).count(), 4);
    }

    #[test]
    fn zero_joins_nothing() {
        let input = split_crossing(0.8);
        let out = merge_close_junctions(input.clone(), 0.0);
        assert_eq!((out.positions, out.edges), (input.positions, input.edges));
    }

    #[test]
    fn a_crossing_split_a_little_farther_apart_is_joined_when_two_lines_run_through() {
        // 1.2 apart at radius 2: past half a radius, within the crossing bound.
        let out = merge_close_junctions(split_crossing(1.2), 0.5);
        assert_eq!(out.positions.len(), 13);
        assert_eq!(out.positions[0], [0.6, 0.0, 0.0]);
    }

    #[test]
    fn two_bifurcations_as_far_apart_on_a_parent_stay_two() {
        // A parent along axis 0 through junctions 0 and 1 (1.2 apart, radius 2), a child
        // leaving each along axes 1 and 2: one pair runs through (the parent), not two.
        let input = two_junctions(1.2, [[[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]]);
        let out = merge_close_junctions(input.clone(), 0.5);
        assert_eq!((out.positions, out.edges), (input.positions, input.edges));
    }

    #[test]
    fn junctions_a_radius_apart_stay_two() {
        let input = split_crossing(2.0);
        let out = merge_close_junctions(input.clone(), 0.5);
        assert_eq!(out.positions, input.positions);
        assert_eq!(out.edges, input.edges);
    }

    #[test]
    fn a_short_branch_with_a_short_twin_is_kept_so_the_loop_stays() {
        // Junctions 0 and 1 joined directly (0.5 long) and through node 2: the triangle
        // is the graph's one loop, which joining them would fold away.
        let mut s = split_crossing(0.5);
        s.positions.push([0.25, 0.4, 0.0]);
        let extra = s.positions.len() - 1;
        s.radii.push(2.0);
        s.edges.push([0, extra]);
        s.edges.push([extra, 1]);
        assert_eq!(cycle_rank(&s), 1);
        let out = merge_close_junctions(s.clone(), 0.5);
        assert_eq!(cycle_rank(&out), 1);
        assert_eq!(out.positions.len(), s.positions.len());
    }

    #[test]
    fn a_chain_of_short_branches_joins_a_meeting_of_three_junctions() {
        // Three junctions 0.6 apart along axis 0 (radius 2), each with two arms.
        let mut positions = vec![[0.0, 0.0, 0.0], [0.6, 0.0, 0.0], [1.2, 0.0, 0.0]];
        let mut edges = vec![[0, 1], [1, 2]];
        for j in 0..3 {
            for sign in [1.0, -1.0] {
                let base = positions[j];
                positions.push([base[0], sign * 2.0 * (j as f64 + 1.0), sign * 2.0]);
                edges.push([j, positions.len() - 1]);
            }
        }
        let radii = vec![2.0; positions.len()];
        let out = merge_close_junctions(skeleton(positions, radii, edges), 0.5);
        assert_eq!(out.positions.len(), 7);
        assert_eq!(out.edges.len(), 6);
        assert!(out.edges.iter().all(|e| e[0] == 0));
        assert!((out.positions[0][0] - 0.6).abs() < 1e-12);
    }
}
