//! A coarse, radius-adaptive start graph (`coarse_cell`; not in the paper, which
//! contracts one node per voxel): the voxels of the grid graph are grouped into cells
//! about as wide as the local vessel radius, one node per cell, so that the first
//! contraction iterations, which dominate the run, solve on a few times fewer nodes.
//!
//! The local vessel radius of a voxel is the distance transform at the ridge point it
//! climbs to: every voxel steps to its neighbour of largest EDT while that is larger,
//! and the radius of the voxel where the climb stops (its *centre*) is the vessel's.
//! (The EDT at the voxel itself would be the distance to the nearest wall, small for
//! most voxels of a thick vessel.) A voxel of vessel radius `R` lies in the box of side
//! `coarse_cell * R` (in whole voxels of the coarsest spacing, the same number along
//! every axis, at least one: [`cell_side`]) of a box grid of that side. A cell is a connected set of voxels of one box, joined by grid edges whose
//! two ends climb to centres less than the smaller radius apart: voxels of two
//! vessels that touch climb to their own vessel's ridge, so no cell spans the contact.
//! Vessels of radius under `2 / coarse_cell` voxels, and over [`MAX_CELL_RADIUS`], keep one
//! node per voxel.
//!
//! A cell becomes a node at its voxels' centroid (the member voxel nearest to it when
//! the centroid's voxel is not a member: a bent cell), with the largest EDT of its
//! voxels as radius, as [`crate::decimate`] merges nodes; two cells are joined when
//! any two of their voxels are, so every mask component stays one graph component
//! and the graph is the quotient of the grid graph by connected cells. A cell that
//! touches a single other cell is merged into it ([`absorb_leaves`]).

use crate::decimate::{mean_and_largest, members_by_cluster, quotient, NodeGraph};
use crate::grid::GridGraph;
use crate::vec3::coarsest;
use petgraph::unionfind::UnionFind;
use rayon::prelude::*;

/// Cap on the rounds of pointer doubling that find every voxel's centre: 2⁶⁴ steps of
/// the climb, more than any graph's nodes.
const MAX_DOUBLING: usize = 64;

/// The coarse start graph of `grid` with cells `cell` times the local vessel radius
/// wide (module doc), and the cell of every grid node. `cell <= 0` keeps the grid
/// graph (one cell per voxel). `spacing` is the grid's voxel spacing; `origin` the
/// voxel of the whole volume at the grid's voxel `(0, 0, 0)` (a chunked run's block
/// origin, 0 for a single run): the boxes are those of the whole volume's box grid, so
/// a block's cells are the single run's wherever it reads the same radii.
pub fn coarsen(grid: GridGraph, spacing: [f64; 3], cell: f64, origin: [i64; 3]) -> (NodeGraph, Vec<u32>) {
    let n = grid.positions.len();
    if cell <= 0.0 || n == 0 {
        let map = (0..n as u32).collect();
        return (
            NodeGraph { graph: grid.graph, positions: grid.positions, radii: grid.radii, component: grid.component },
            map,
        );
    }
    // The grid's arrays are dropped as soon as they are no longer read: this stage is
    // the run's peak (the grid graph and the cells' arrays at once).
    let GridGraph { graph, positions, radii, component, .. } = grid;
    let g = &graph;
    // The climb: every node to its neighbour of largest EDT (the first in node order
    // among equals) while that is strictly larger; the centre is where it stops.
    let mut centre: Vec<u32> = (0..n)
        .into_par_iter()
        .map(|i| {
            let mut best = i as u32;
            for &j in g.neighbours(i) {
                if radii[j as usize] > radii[best as usize] {
                    best = j;
                }
            }
            best
        })
        .collect();
    // Two buffers, swapped every round (no array allocated per round).
    let mut next = centre.clone();
    for _ in 0..MAX_DOUBLING {
        next.par_iter_mut().zip(&centre).for_each(|(q, &p)| *q = centre[p as usize]);
        std::mem::swap(&mut centre, &mut next);
        if next == centre {
            break;
        }
    }
    drop(next);
    // The box of every voxel, as one key ([`box_key`]), computed once in parallel: the
    // union below only compares the keys of neighbours.
    let coarsest = coarsest(spacing);
    let voxel =
        |i: usize| -> [i64; 3] { std::array::from_fn(|d| (positions[i][d] / spacing[d]).round() as i64 + origin[d]) };
    let boxes: Vec<u64> = (0..n)
        .into_par_iter()
        .map(|i| box_key(cell_side(cell, radii[centre[i] as usize], coarsest), voxel(i)))
        .collect();
    let same_vessel = |i: usize, j: usize| {
        let (a, b) = (positions[centre[i] as usize], positions[centre[j] as usize]);
        let d2: f64 = (0..3).map(|d| (a[d] - b[d]).powi(2)).sum();
        let r = radii[centre[i] as usize].min(radii[centre[j] as usize]);
        d2 < r * r
    };
    // Cells: connected pieces of a box, numbered by their first voxel.
    let mut uf = UnionFind::<u32>::new(n);
    for i in 0..n {
        let bi = boxes[i];
        for &j in g.neighbours(i) {
            let j = j as usize;
            if j > i && bi == boxes[j] && same_vessel(i, j) {
                uf.union(i as u32, j as u32);
            }
        }
    }
    let mut map = vec![u32::MAX; n];
    let mut cells = 0u32;
    for i in 0..n {
        let root = uf.find_mut(i as u32) as usize;
        if map[root] == u32::MAX {
            map[root] = cells;
            cells += 1;
        }
        map[i] = map[root];
    }
    drop(uf);
    // Cells of a box wider than a voxel: only those can be pockets of a box corner.
    let mut wide = vec![false; cells as usize];
    for i in 0..n {
        wide[map[i] as usize] |= side_of(boxes[i]) >= MIN_SIDE;
    }
    drop((centre, boxes));
    let cells = absorb_leaves(g, &mut map, &wide);
    let (start, members) = members_by_cluster(&map, cells);
    let merged: Vec<([f64; 3], f64)> = (0..cells)
        .into_par_iter()
        .map(|k| {
            let m = &members[start[k]..start[k + 1]];
            let (mean, r) = mean_and_largest(m, &positions, &radii);
            let at: [i64; 3] = std::array::from_fn(|d| (mean[d] / spacing[d]).round() as i64 + origin[d]);
            let d2 = |i: u32| -> f64 { (0..3).map(|d| (positions[i as usize][d] - mean[d]).powi(2)).sum() };
            let position = if m.iter().any(|&i| voxel(i as usize) == at) {
                mean
            } else {
                let nearest = m.iter().copied().min_by(|&a, &b| d2(a).total_cmp(&d2(b))).unwrap_or(m[0]);
                positions[nearest as usize]
            };
            (position, r)
        })
        .collect();
    drop((positions, radii));
    let component = (0..cells).map(|k| component[members[start[k]] as usize]).collect();
    let (positions, radii) = merged.into_iter().unzip();
    let next = NodeGraph { graph: quotient(g, &map, &start, &members), positions, radii, component };
    (next, map)
}

/// The thickest vessel that gets cells: its radius in voxels of the coarsest spacing.
/// Thicker vessels keep one node per voxel, as thin ones do. Cells kept the fidelity
/// benchmark's figures within their spread on vessels up to this radius (the synthetic
/// families; the 256³ bed, radii up to 7.9 voxels) and went wrong on thicker ones: on
/// `aorta_ct_03mm` (radii 9-25 voxels) GFNR over four orders of its axes was
/// 0.090-0.236 with cells against 0.078-0.104 without, and smaller cells (sides capped
/// at 3 voxels) did worse, 0.157-0.185 (README, "Where we differ", 13).
pub const MAX_CELL_RADIUS: f64 = 8.0;

/// The side of the cells of a vessel of radius `r`, in voxels along every axis:
/// `cell * r` over the coarsest voxel spacing, at least one voxel; one voxel above
/// [`MAX_CELL_RADIUS`]. The same number of voxels per axis keeps the coarse graph a
/// scaled-down grid graph (the Laplacians are row-normalised, so the contraction sees
/// hops, not lengths); cells of equal physical side on an anisotropic grid would make an
/// elongated block look short to it.
pub fn cell_side(cell: f64, r: f64, coarsest: f64) -> i64 {
    if r / coarsest > MAX_CELL_RADIUS {
        return 1;
    }
    ((cell * r / coarsest).floor() as i64).max(1)
}

/// Bits of each axis's box index in a [`box_key`].
const BOX_BITS: u32 = 18;

/// The box of side `side` (voxels along every axis) that holds voxel `v`, as one key:
/// the side in the top bits, then each axis's box index modulo 2¹⁸. Neighbouring
/// voxels are at most one voxel apart along each axis, so their box indices are at most
/// one apart, and their keys are equal exactly when they share a box. The side is at
/// most 32 (`coarse_cell` ≤ 4 times [`MAX_CELL_RADIUS`]), well within the 10 bits left.
fn box_key(side: i64, v: [i64; 3]) -> u64 {
    debug_assert!((1..1 << 10).contains(&side), "a cell side of {side} voxels");
    v.iter().fold(side as u64, |key, &x| (key << BOX_BITS) | (x.div_euclid(side) as u64 & ((1 << BOX_BITS) - 1)))
}

/// The side of the box of a [`box_key`].
fn side_of(key: u64) -> i64 {
    (key >> (3 * BOX_BITS)) as i64
}

/// Whether a vessel of radius `r` is thick enough for cells (a side of two voxels or
/// more): thinner vessels keep one node per voxel, their leaves and edges as in the
/// grid start.
pub fn has_cells(cell: f64, r: f64, coarsest: f64) -> bool {
    cell_side(cell, r, coarsest) >= MIN_SIDE
}

/// The smallest side of a box that groups voxels ([`has_cells`]), in voxels of the
/// coarsest spacing; also the shortest limit on an edge with one end in a vessel thick
/// enough for cells and the other not ([`crate::resample`]).
pub const MIN_SIDE: i64 = 2;

/// Merge every cell that touches only one other cell into that one (when that one
/// touches others too), unless both are cells of a box of one voxel (`wide`: of a
/// wider box), and renumber the cells by first voxel; returns their number. A cell
/// hemmed in by a single neighbour next to a wide cell is a pocket of a box corner or
/// a stray wall voxel of a thick vessel, not a vessel end, but a node of degree 1
/// counts as a vessel end (`anchor_ends`): anchored harder and kept through
/// decimation, it would stay behind as a spur. Between two single voxels (a thin
/// vessel) the leaf is left as in the grid graph: absorbing the tip voxels of thin
/// vessels moved their ends (`vascusynth_seed2_n250_100`, whose vessels are all too
/// thin for a cell: DIADEM 17.2 → 10.3 at `coarse_cell` 0.5, identical to the grid
/// start now).
fn absorb_leaves(g: &crate::grid::Csr, map: &mut [u32], wide: &[bool]) -> usize {
    let cells = wide.len();
    let only = only_neighbour(g, map, cells);
    let target: Vec<u32> = (0..cells)
        .map(|k| match only[k] {
            o if o < MANY && (wide[k] || wide[o as usize]) && only[o as usize] == MANY => o,
            _ => k as u32,
        })
        .collect();
    let mut number = vec![u32::MAX; cells];
    let mut next = 0u32;
    for m in map.iter_mut() {
        let k = target[*m as usize] as usize;
        if number[k] == u32::MAX {
            number[k] = next;
            next += 1;
        }
        *m = number[k];
    }
    next as usize
}

/// [`only_neighbour`]'s mark of a cell that touches two or more others.
const MANY: u32 = u32::MAX - 1;

/// For every cell (`map`: the cell of each voxel), the one other cell it touches
/// through the grid's edges, [`MANY`] when it touches two or more, `u32::MAX` when
/// none. In parallel over the voxels: each cell's mark only moves from none to one cell
/// to [`MANY`], so the result does not depend on the order the edges are seen in.
fn only_neighbour(g: &crate::grid::Csr, map: &[u32], cells: usize) -> Vec<u32> {
    use std::sync::atomic::{AtomicU32, Ordering::Relaxed};
    debug_assert!(cells < MANY as usize);
    let mark: Vec<AtomicU32> = (0..cells).map(|_| AtomicU32::new(u32::MAX)).collect();
    (0..map.len()).into_par_iter().for_each(|i| {
        let k = map[i];
        for &j in g.neighbours(i) {
            let other = map[j as usize];
            if other != k {
                // At most two changes (none → `other` → MANY), so this ends.
                let _ = mark[k as usize].fetch_update(Relaxed, Relaxed, |m| match m {
                    u32::MAX => Some(other),
                    m if m == other || m == MANY => None,
                    _ => Some(MANY),
                });
            }
        }
    });
    mark.into_iter().map(AtomicU32::into_inner).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decimate::{members_by_cluster, quotient};
    use crate::grid::Csr;

    #[test]
    fn neighbours_box_keys_agree_exactly_when_they_share_a_box() {
        let mut rnd = crate::test_rng(7);
        // Near 0, negative, and where the box index wraps modulo 2¹⁸.
        let around = [0i64, -3, 1 << 18, (1 << 18) * 5 - 1, 40_000];
        for side in 1..=32i64 {
            for &c in &around {
                for _ in 0..50 {
                    let v: [i64; 3] = std::array::from_fn(|_| c * side + rnd(2 * side as u64 + 3) as i64 - side);
                    let w: [i64; 3] = std::array::from_fn(|d| v[d] + rnd(3) as i64 - 1);
                    let same = (0..3).all(|d| v[d].div_euclid(side) == w[d].div_euclid(side));
                    assert_eq!(box_key(side, v) == box_key(side, w), same, "side {side}, {v:?} and {w:?}");
                    assert_eq!(side_of(box_key(side, v)), side);
                    let other = side % 32 + 1;
                    assert_ne!(box_key(side, v), box_key(other, w), "sides {side} and {other}");
                }
            }
        }
    }

    #[test]
    fn the_only_neighbour_is_that_of_the_cell_graph_at_any_thread_count() {
        let mut rnd = crate::test_rng(11);
        for trial in 0..30 {
            let n = 2 + rnd(60) as usize;
            let mut edges: Vec<(u32, u32)> = (0..n * (1 + trial % 3))
                .map(|_| (rnd(n as u64) as u32, rnd(n as u64) as u32))
                .filter(|(a, b)| a != b)
                .map(|(a, b)| (a.min(b), a.max(b)))
                .collect();
            edges.sort_unstable();
            edges.dedup();
            let g = Csr::from_sorted_edges(n, &edges);
            let cells = 1 + rnd(n as u64) as usize;
            let map: Vec<u32> = (0..n).map(|i| if i < cells { i as u32 } else { rnd(cells as u64) as u32 }).collect();
            let (start, members) = members_by_cluster(&map, cells);
            let cell_graph = quotient(&g, &map, &start, &members);
            let expected: Vec<u32> = (0..cells)
                .map(|k| match cell_graph.neighbours(k) {
                    [] => u32::MAX,
                    &[only] => only,
                    _ => MANY,
                })
                .collect();
            for threads in [1, 2] {
                let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
                assert_eq!(pool.install(|| only_neighbour(&g, &map, cells)), expected, "trial {trial}");
            }
        }
    }
}
