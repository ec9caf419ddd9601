//! Geometric graph decimation by cell hashing (docs/method.md §2.5, paper §III-E and
//! §III-F): nodes that fall in the same cubic cell of side `c` (cells centred on
//! voxel centres) become one node at their mean position with the largest radius
//! of the group; two new nodes are joined if any of their members were.
//!
//! The cell key also carries the mask component, so nodes of different mask
//! components never merge (each component stays one graph component), and nodes
//! asked to keep their identity (skeleton-like nodes) get a cell of their own.
//! New nodes are numbered in key order: component, then cell in C order.

use crate::error::{Error, Result};
use crate::grid::{filled, Csr, ROW_BLOCK};
use rayon::prelude::*;

/// Half-range of a packed cell coordinate: cells must lie in `(-2^20, 2^20)`.
pub const CELL_LIMIT: i64 = 1 << 20;

/// A graph with per-node geometry, as carried between iterations.
#[derive(Debug, Clone, Default)]
pub struct NodeGraph {
    pub graph: Csr,
    pub positions: Vec<[f64; 3]>,
    pub radii: Vec<f64>,
    pub component: Vec<u32>,
}

/// The cell of a position: `round(p / c)` per axis.
pub fn cell_of(p: &[f64; 3], c: f64) -> Result<[i64; 3]> {
    let mut out = [0i64; 3];
    for d in 0..3 {
        let x = (p[d] / c).round();
        if !x.is_finite() || x.abs() >= CELL_LIMIT as f64 {
            return Err(Error::InvalidMask(format!(
                "node position {p:?} is outside the supported extent of ±{CELL_LIMIT} cells (or not finite)"
            )));
        }
        out[d] = x as i64;
    }
    Ok(out)
}

/// Sort key of node `node`: component (32 bits) | cell (3 × 21 bits) | kept (1 bit) |
/// node (32 bits). In key order, nodes of one cell are together, the kept ones after
/// the others, each in node order; one `u128` a node rather than a key and a node
/// index (32 bytes with padding), at the first iteration's decimation, a peak of the
/// run.
fn key(component: u32, cell: [i64; 3], kept: bool, node: u32) -> u128 {
    let packed = cell.iter().fold(0u128, |acc, &x| (acc << 21) | (x + CELL_LIMIT) as u128);
    ((component as u128) << 96) | (packed << 33) | ((kept as u128) << 32) | node as u128
}

/// The node of a [`key`].
fn node_of(key: u128) -> u32 {
    key as u32
}

/// Nodes of keys `a` and `b` share a cell: same component and cell, neither kept.
fn same_cell(a: u128, b: u128) -> bool {
    a >> 32 == b >> 32 && (a >> 32) & 1 == 0
}

/// Edges shorter than this fraction of the cell size join their nodes' clusters.
pub const SHORT_EDGE: f64 = 0.5;

/// Merge nodes per cell. `keep[i]` makes node `i` a cluster of its own.
///
/// Besides sharing a cell, two cells whose nodes (not kept) are joined by an edge
/// shorter than [`SHORT_EDGE`]` * c` may merge: each cell with at most one other,
/// shortest edges first. Fixed cells alone split a centreline that lies on a cell
/// boundary (a tube of even voxel width) into two rails a hair apart that never
/// merge: a "ladder" whose rungs the refinement then collapses along the vessel,
/// eating it from its end. Pairing (rather than chaining) keeps every cluster within
/// two cells, so the decimation stays as fine as the cell grid.
pub fn decimate(g: &NodeGraph, keep: &[bool], c: f64) -> Result<NodeGraph> {
    decimate_mapped(g, keep, c).map(|(next, _)| next)
}

/// [`decimate`] that also returns the new node of every old node (for chunked runs,
/// which follow each voxel to its final node: [`crate::blocks`]).
pub fn decimate_mapped(g: &NodeGraph, keep: &[bool], c: f64) -> Result<(NodeGraph, Vec<u32>)> {
    let n = g.positions.len();
    // Positions are checked first, so that the keys are collected straight into one
    // vector of known length (collecting `Result`s goes through pieces that are then
    // copied, twice the keys' 16 bytes a node at once).
    g.positions.par_iter().try_for_each(|p| cell_of(p, c).map(|_| ()))?;
    let mut order: Vec<u128> = (0..n)
        .into_par_iter()
        .map(|i| key(g.component[i], cell_of(&g.positions[i], c).unwrap_or_default(), keep[i], i as u32))
        .collect();
    order.par_sort_unstable();
    // Each pass takes up to a second on the largest graphs.
    crate::cancel::checkpoint()?;
    // Cells, numbered in key order.
    let mut cell = vec![0u32; n];
    let mut cells = 0u32;
    for s in 0..n {
        if s > 0 && !same_cell(order[s - 1], order[s]) {
            cells += 1;
        }
        cell[node_of(order[s]) as usize] = cells;
    }
    let cells = if n > 0 { cells as usize + 1 } else { 0 };
    // Every array is dropped once used: the decimation of the first contraction
    // iteration, which holds the whole grid-sized graph, is among the run's peaks.
    drop(order);
    // Cells paired through their shortest short edge: a greedy matching, shortest
    // first, so a cluster spans at most two cells.
    let limit = (SHORT_EDGE * c).powi(2);
    let mut joins: Vec<(u64, u32, u32)> = (0..n)
        .into_par_iter()
        .flat_map_iter(|i| {
            let (cell, keep) = (&cell, &keep);
            g.graph.neighbours(i).iter().filter_map(move |&j| {
                let j = j as usize;
                let (p, q) = (g.positions[i], g.positions[j]);
                let d2 = (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2);
                let (a, b) = (cell[i].min(cell[j]), cell[i].max(cell[j]));
                (j > i && !keep[i] && !keep[j] && a != b && d2 < limit).then_some((d2.to_bits(), a, b))
            })
        })
        .collect();
    joins.par_sort_unstable();
    crate::cancel::checkpoint()?;
    let mut partner: Vec<u32> = (0..cells as u32).collect();
    for &(_, a, b) in &joins {
        if partner[a as usize] == a && partner[b as usize] == b {
            partner[a as usize] = b;
            partner[b as usize] = a;
        }
    }
    drop(joins);
    // Clusters numbered by their first cell in key order.
    let mut cluster_of_cell = vec![u32::MAX; cells];
    let mut clusters = 0u32;
    for k in 0..cells {
        if cluster_of_cell[k] == u32::MAX {
            cluster_of_cell[k] = clusters;
            cluster_of_cell[partner[k] as usize] = clusters;
            clusters += 1;
        }
    }
    let clusters = clusters as usize;
    drop(partner);
    let map: Vec<u32> = cell.iter().map(|&k| cluster_of_cell[k as usize]).collect();
    drop((cell, cluster_of_cell));
    let (start, members) = members_by_cluster(&map, clusters);
    crate::cancel::checkpoint()?;
    // Each array of the new graph is collected straight into its own vector (no
    // vector of tuples to copy them out of); each cluster's mean is computed once.
    let member = |k: usize| &members[start[k]..start[k + 1]];
    let merge = |k: usize| mean_and_largest(member(k), &g.positions, &g.radii);
    let (positions, radii) = (0..clusters).into_par_iter().map(merge).unzip();
    let component = (0..clusters).into_par_iter().map(|k| g.component[member(k)[0] as usize]).collect();
    let next = NodeGraph { graph: quotient(&g.graph, &map, &start, &members), positions, radii, component };
    Ok((next, map))
}

/// The mean position and the largest radius of the nodes `m` (a cluster's members).
pub(crate) fn mean_and_largest(m: &[u32], positions: &[[f64; 3]], radii: &[f64]) -> ([f64; 3], f64) {
    let mut sum = [0.0; 3];
    let mut r = f64::NEG_INFINITY;
    for &i in m {
        let p = positions[i as usize];
        for d in 0..3 {
            sum[d] += p[d];
        }
        r = r.max(radii[i as usize]);
    }
    let len = m.len() as f64;
    ([sum[0] / len, sum[1] / len, sum[2] / len], r)
}

/// The members of every cluster in increasing node order (a counting sort):
/// cluster `k` holds `members[start[k]..start[k + 1]]`, where `map` gives each node's cluster.
pub(crate) fn members_by_cluster(map: &[u32], clusters: usize) -> (Vec<usize>, Vec<u32>) {
    let mut start = filled(clusters + 1, 0usize);
    for &m in map {
        start[m as usize + 1] += 1;
    }
    for k in 0..clusters {
        start[k + 1] += start[k];
    }
    let mut fill = start.clone();
    let mut members = vec![0u32; map.len()];
    for (i, &m) in map.iter().enumerate() {
        members[fill[m as usize]] = i as u32;
        fill[m as usize] += 1;
    }
    (start, members)
}

/// The graph of the clusters: cluster `k` (members `members[start[k]..start[k + 1]]`)
/// is joined to every other cluster that a member's neighbour belongs to (`map`).
/// Built row by row in parallel blocks of clusters, each block's rows gathered in a
/// worker's scratch and kept in a list of exactly their length (a list grown in place
/// would keep up to twice that), then appended in order, each block's list freed once
/// appended.
pub(crate) fn quotient(g: &Csr, map: &[u32], start: &[usize], members: &[u32]) -> Csr {
    let clusters = start.len() - 1;
    let parts: Vec<(Vec<u32>, Box<[u32]>)> = (0..clusters.div_ceil(ROW_BLOCK))
        .into_par_iter()
        .map_init(
            || (Vec::new(), Vec::new()),
            |(targets, row), b| {
                let rows = b * ROW_BLOCK..((b + 1) * ROW_BLOCK).min(clusters);
                let mut lens = Vec::with_capacity(rows.len());
                targets.clear();
                for k in rows {
                    row.clear();
                    for &i in &members[start[k]..start[k + 1]] {
                        row.extend(
                            g.neighbours(i as usize).iter().map(|&j| map[j as usize]).filter(|&m| m as usize != k),
                        );
                    }
                    row.sort_unstable();
                    row.dedup();
                    lens.push(row.len() as u32);
                    targets.extend_from_slice(row);
                }
                (lens, targets.as_slice().into())
            },
        )
        .collect();
    let mut offsets = Vec::with_capacity(clusters + 1);
    offsets.push(0);
    let mut targets = Vec::with_capacity(parts.iter().map(|p| p.1.len()).sum());
    for (lens, t) in parts {
        for l in lens {
            offsets.push(offsets[offsets.len() - 1] + l as usize);
        }
        targets.extend_from_slice(&t);
    }
    Csr { offsets, targets }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn merges_per_cell_with_mean_position_and_max_radius() {
        // Path 0-1-2-3; nodes 1 and 2 share a cell.
        let g = NodeGraph {
            graph: Csr::from_sorted_edges(4, &[(0, 1), (1, 2), (2, 3)]),
            positions: vec![[0.0; 3], [1.1, 0.0, 0.0], [0.9, 0.2, 0.0], [2.0, 0.0, 0.0]],
            radii: vec![1.0, 2.0, 3.0, 1.0],
            component: vec![0; 4],
        };
        let d = decimate(&g, &[false; 4], 1.0).unwrap();
        assert_eq!(d.positions.len(), 3);
        assert_eq!(d.positions[1], [1.0, 0.1, 0.0]);
        assert_eq!(d.radii, vec![1.0, 3.0, 1.0]);
        assert_eq!(d.graph.edge_list(), vec![(0, 1), (1, 2)]);
        // Kept nodes stay apart even in one cell.
        let k = decimate(&g, &[false, true, false, false], 1.0).unwrap();
        assert_eq!(k.positions.len(), 4);
        assert_eq!(k.graph.edges(), 3);
    }

    #[test]
    fn nodes_straddling_a_cell_face_merge_through_a_short_edge() {
        // A ladder: rails at k = 1.49 and 1.51 (cells 1 and 2), rungs between them.
        let pos = vec![[0.0, 0.0, 1.49], [0.0, 0.0, 1.51], [1.0, 0.0, 1.49], [1.0, 0.0, 1.51]];
        let g = NodeGraph {
            graph: Csr::from_sorted_edges(4, &[(0, 1), (0, 2), (1, 3), (2, 3)]),
            positions: pos,
            radii: vec![1.0; 4],
            component: vec![0; 4],
        };
        let d = decimate(&g, &[false; 4], 1.0).unwrap();
        assert_eq!(d.positions, vec![[0.0, 0.0, 1.5], [1.0, 0.0, 1.5]]);
        assert_eq!(d.graph.edge_list(), vec![(0, 1)]);
        // Kept nodes do not merge.
        assert_eq!(decimate(&g, &[true, false, false, false], 1.0).unwrap().positions.len(), 3);
    }

    #[test]
    fn components_never_merge() {
        let g = NodeGraph {
            graph: Csr::from_sorted_edges(2, &[]),
            positions: vec![[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]],
            radii: vec![1.0, 1.0],
            component: vec![0, 1],
        };
        assert_eq!(decimate(&g, &[false; 2], 1.0).unwrap().positions.len(), 2);
    }

    #[test]
    fn cluster_graph_matches_the_mapped_edge_list() {
        // A random graph and a random clustering: the quotient's rows are the mapped
        // edges without self-loops or repeats, as from the sorted edge list.
        let mut rnd = crate::test_rng(7);
        for n in [1usize, 5, 300, 9000] {
            let (g, edges) = crate::test_graph(n, (0..3 * n).map(|_| (rnd(n as u64) as u32, rnd(n as u64) as u32)));
            let clusters = 1 + n / 3;
            let map: Vec<u32> =
                (0..n).map(|i| if i < clusters { i as u32 } else { rnd(clusters as u64) as u32 }).collect();
            let (start, members) = members_by_cluster(&map, clusters);
            let (want, _) = crate::test_graph(clusters, edges.iter().map(|&(a, b)| (map[a as usize], map[b as usize])));
            assert_eq!(quotient(&g, &map, &start, &members), want, "n = {n}");
        }
    }

    #[test]
    fn far_positions_are_refused() {
        assert!(cell_of(&[1e9, 0.0, 0.0], 1.0).is_err());
        assert!(cell_of(&[f64::NAN, 0.0, 0.0], 1.0).is_err());
        assert_eq!(cell_of(&[-0.4, 0.5, 1.49], 1.0).unwrap(), [0, 1, 1]);
    }
}
