//! Sprouts of a chunked run (with `sprouts`, [`crate::sprouts`]): every block grows the
//! sprouts of its own read, as a single run grows them, and reports those whose lobe's
//! farthest voxel lies in its core ([`SproutRecord`]): a lobe has exactly one owner,
//! and a block that sees a lobe it does not own still grows it, so that it claims its
//! voxels as the single run's would. The merge attaches the reported sprouts to the
//! merged graph ([`attach_sprouts`]), by round, then block, then the order they were
//! grown in: each starts on the merged edge nearest its start (split there by a node
//! at the start's position when the block split its edge, else joined to that edge's
//! nearer end), and its nodes follow as the block placed and measured them. A sprout
//! whose start lies further than [`SEARCH_CELLS`] base cells from every edge is not
//! attached (a block's graph and the merged graph differ there by more than a seam's
//! float rounding).

use crate::edge_grid::EdgeGrid;
use crate::graph::Skeleton;
use crate::vec3::{base_cell, norm, sub};

/// How far (base cells) a sprout's start may lie from the merged edge it starts on.
pub const SEARCH_CELLS: f64 = 4.0;

/// A sprout as a block reports it (global positions, physical units).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SproutRecord {
    /// The round that grew it (from 0).
    pub round: u32,
    /// Whether it starts on a node the block added to split its parent edge.
    pub split: bool,
    /// Where it starts (the split node, or the parent's node it joins) and the radius
    /// there.
    pub start: [f64; 3],
    pub start_radius: f64,
    /// Its nodes after the start, start to end, and their radii.
    pub positions: Vec<[f64; 3]>,
    pub radii: Vec<f64>,
}

impl SproutRecord {
    /// Whether the record can be attached: at least one node, a radius per node, every
    /// position finite and every radius finite and `>= 0`.
    pub fn is_valid(&self) -> bool {
        let radius = |r: &f64| r.is_finite() && *r >= 0.0;
        !self.positions.is_empty()
            && self.positions.len() == self.radii.len()
            && self.positions.iter().chain([&self.start]).all(|p| p.iter().all(|x| x.is_finite()))
            && self.radii.iter().chain([&self.start_radius]).all(radius)
    }
}

/// The merged graph `g` with `sprouts` attached (module doc), given in the order they
/// are attached; and how many were. `g`'s positions must be finite and every sprout
/// valid ([`SproutRecord::is_valid`]).
pub fn attach_sprouts(mut g: Skeleton, sprouts: &[&SproutRecord]) -> (Skeleton, usize) {
    if sprouts.is_empty() {
        return (g, 0);
    }
    let c = base_cell(g.spacing);
    let mut grid = EdgeGrid::around(sprouts.iter().map(|s| s.start), SEARCH_CELLS * c);
    for (k, &[a, b]) in g.edges.iter().enumerate() {
        grid.insert(k, g.positions[a], g.positions[b]);
    }
    let mut attached = 0;
    for s in sprouts {
        let segment = |k: usize| (g.positions[g.edges[k][0]], g.positions[g.edges[k][1]]);
        let Some((k, _)) = grid.nearest(s.start, segment) else { continue };
        let [a, b] = g.edges[k];
        let start = if s.split {
            let j = g.positions.len();
            g.positions.push(s.start);
            g.radii.push(s.start_radius);
            g.edges[k] = [a.min(j), a.max(j)];
            g.edges.push([b.min(j), b.max(j)]);
            grid.insert(k, g.positions[a], s.start);
            grid.insert(g.edges.len() - 1, s.start, g.positions[b]);
            j
        } else if norm(sub(s.start, g.positions[a])) <= norm(sub(s.start, g.positions[b])) {
            a
        } else {
            b
        };
        let mut prev = start;
        for (&p, &r) in s.positions.iter().zip(&s.radii) {
            let j = g.positions.len();
            g.positions.push(p);
            g.radii.push(r);
            g.edges.push([prev.min(j), prev.max(j)]);
            grid.insert(g.edges.len() - 1, g.positions[prev], p);
            prev = j;
        }
        attached += 1;
    }
    g.edges.sort_unstable();
    (g, attached)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::RunInfo;

    fn bar() -> Skeleton {
        Skeleton {
            positions: vec![[0.0, 0.0, 0.0], [0.0, 0.0, 4.0], [0.0, 0.0, 8.0]],
            radii: vec![1.0; 3],
            edges: vec![[0, 1], [1, 2]],
            spacing: [1.0; 3],
            info: RunInfo::default(),
        }
    }

    #[test]
    fn a_sprout_splits_its_edge_or_joins_the_nearer_end_and_a_far_one_is_left_out() {
        let split = SproutRecord {
            round: 0,
            split: true,
            start: [0.5, 0.0, 5.0],
            start_radius: 1.5,
            positions: vec![[3.0, 0.0, 5.0], [6.0, 0.0, 5.0]],
            radii: vec![1.0, 0.8],
        };
        let joined = SproutRecord { split: false, start: [0.0, 0.3, 7.0], ..split.clone() };
        let far = SproutRecord { start: [0.0, 9.0, 4.0], ..split.clone() };
        let (g, n) = attach_sprouts(bar(), &[&split, &joined, &far]);
        assert_eq!(n, 2);
        assert_eq!(g.positions[3..6], [[0.5, 0.0, 5.0], [3.0, 0.0, 5.0], [6.0, 0.0, 5.0]]);
        assert_eq!(g.radii[3..], [1.5, 1.0, 0.8, 1.0, 0.8]);
        // The split edge 1-2 is now 1-3-2; the joined sprout starts on node 2.
        assert_eq!(g.edges, vec![[0, 1], [1, 3], [2, 3], [2, 6], [3, 4], [4, 5], [6, 7]]);
    }

    #[test]
    fn an_edge_longer_than_the_kept_cells_is_still_found() {
        // One edge across 250 000 grid cells: filed under the kept cells inside its box.
        let mut g = bar();
        g.positions[2] = [0.0, 0.0, 1e6];
        let s = SproutRecord {
            split: true,
            start: [1.0, 0.0, 5e5],
            start_radius: 1.0,
            positions: vec![[4.0, 0.0, 5e5]],
            radii: vec![1.0],
            ..SproutRecord::default()
        };
        let (g, n) = attach_sprouts(g, &[&s]);
        assert_eq!(n, 1);
        assert_eq!(g.edges, vec![[0, 1], [1, 3], [2, 3], [3, 4]]);
    }

    #[test]
    fn a_record_with_a_bad_value_is_not_valid() {
        let good = SproutRecord { positions: vec![[1.0; 3]], radii: vec![1.0], ..SproutRecord::default() };
        assert!(good.is_valid());
        assert!(!SproutRecord { radii: vec![], ..good.clone() }.is_valid());
        assert!(!SproutRecord { start: [f64::NAN, 0.0, 0.0], ..good.clone() }.is_valid());
        assert!(!SproutRecord { radii: vec![-1.0], ..good.clone() }.is_valid());
        assert!(!SproutRecord { positions: vec![], radii: vec![], ..good }.is_valid());
    }
}
