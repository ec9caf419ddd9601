//! Long edges split back to the coarse start's node spacing (with `coarse_cell`; not in
//! the paper, which starts from one node per voxel).
//!
//! A coarse start ([`crate::coarse`]) puts one node per cell of `coarse_cell` vessel
//! radii, so the contracted centreline has a node about every cell side along the
//! vessel (one node per voxel would give one about every voxel), and the refinement,
//! which collapses the short cycles left between consecutive nodes, merges some of
//! those: a radius-4 cylinder kept 16 nodes over 40 voxels, a radius-4 torus 48 over a
//! circumference of 126. After the refinement every edge longer than the cell side at
//! the smaller radius of its two ends, and than 2 voxels, with either end in a vessel
//! that has cells (a chunked run's merge decides by the radii its blocks split with), is
//! split into
//! equal pieces no longer than that, by new degree-2 nodes on the chord with linearly
//! interpolated radii (which bound their moves in the medial stage). The medial stage
//! then moves them, like every other node, onto the ridge of the distance transform,
//! so the new nodes sample the vessel's own centreline, not the chord; there, once
//! kept on the mask, they take the transform at their position as radius
//! ([`ridge_radii`]), the first guess from which the output stage measures
//! ([`crate::radius`]; it sets the slab and the reach of the section), as the nodes the
//! routing of edges adds do. An old node's radius is its cluster's largest EDT, and a
//! junction's cluster in a thick vessel's blob has a far larger one than its
//! branches: interpolated from it, the new nodes near the junction read the blob.
//!
//! Edges at a junction are split too. The contraction leaves the junction of two thick
//! branches a few cell sides from where they part, and its edges are chords that cut
//! the corner between them (aorta_ct_04mm: a 15 mm chord from the aortic bifurcation
//! down one iliac artery). They were once left whole, for the radii of new nodes in a
//! junction's blob (held-out lattice radius MAP 8.6 → 10.1 % when split); the lattice's
//! vessels, 1.4–2.4 voxels in radius, have no cells and no split edges now. Split, at
//! `coarse_cell` 0.5, GFNR / GFPR aorta_ct_04mm 0.091 / 0.065 → 0.061 / 0.041 and
//! aorta_ct_03mm 0.146 / 0.129 → 0.091 / 0.074 (0.092 / 0.085 once ends followed the
//! mask; without a coarse start 0.063 / 0.138 and 0.092 / 0.162). With interpolated radii the split cost 03mm radius MAP 3.1 → 5.3 %
//! (2.1 % without a coarse start); with [`ridge_radii`] it is 2.8 % (04mm 2.8 → 2.7 %,
//! 2.7 % without; GFNR / GFPR unchanged).

use crate::coarse::{cell_side, has_cells, MIN_SIDE};
use crate::decimate::NodeGraph;
use crate::grid::Csr;
use crate::medial::Field;
use crate::vec3::coarsest;
use std::collections::HashMap;

/// Most pieces one edge is split into (an edge is never longer than the mask, and a
/// piece never shorter than a voxel, so the cap only bounds the loop).
const MAX_PIECES: usize = 1 << 16;

/// The nodes a split put on one edge (none if it kept the edge whole), in order from
/// `ends[0]` to `ends[1]`, with their positions and radii: how a chunked run's block
/// hands the merge its split, with the nodes its medial and output stages placed and
/// measured (the merge has no mask to do so, and its ends may have moved since the
/// split looked at them: a vessel's end node moves out to the vessel's end).
#[derive(Debug, Clone, PartialEq)]
pub struct Chain {
    pub ends: [u32; 2],
    pub positions: Vec<[f64; 3]>,
    pub radii: Vec<f64>,
}

impl Chain {
    /// A radius for each node, positions finite, radii finite and ≥ 0.
    pub fn is_valid(&self) -> bool {
        self.positions.len() == self.radii.len()
            && self.positions.iter().all(|p| p.iter().all(|x| x.is_finite()))
            && self.radii.iter().all(|r| r.is_finite() && *r >= 0.0)
    }
}

/// `g` with every edge longer than the coarse cell side (`cell_side(cell, r, coarsest)`
/// voxels of the coarsest spacing, `r` the smaller radius of its ends, at least
/// [`MIN_SIDE`] voxels), with either end in a vessel that has cells, split into equal
/// pieces (module doc). The radii that decide are `decide` (one per node: in a single
/// run the nodes' own, in a chunked run's merge those the blocks split with); new nodes
/// interpolate `g`'s. An edge with a chain in `given` (ends in `g`'s numbering, either
/// order; valid, [`Chain::is_valid`]) takes the first such chain's nodes instead (none:
/// kept whole), whatever its length. Old nodes keep their numbers; new ones follow, edge by edge in edge order,
/// and take the component of their edge.
pub fn split_long_edges(g: NodeGraph, decide: &[f64], cell: f64, spacing: [f64; 3], given: &[Chain]) -> NodeGraph {
    let coarsest = coarsest(spacing);
    let mut chain_of: HashMap<[u32; 2], &Chain> = HashMap::new();
    for c in given {
        chain_of.entry([c.ends[0].min(c.ends[1]), c.ends[0].max(c.ends[1])]).or_insert(c);
    }
    let NodeGraph { graph, mut positions, mut radii, mut component } = g;
    let old = graph.edge_list();
    let mut edges = Vec::with_capacity(old.len());
    for (a, b) in old {
        let new: Vec<([f64; 3], f64)> = if let Some(chain) = chain_of.get(&[a, b]) {
            let nodes = chain.positions.iter().copied().zip(chain.radii.iter().copied());
            if chain.ends[0] == a {
                nodes.collect()
            } else {
                nodes.rev().collect()
            }
        } else {
            let (p, q) = (positions[a as usize], positions[b as usize]);
            let (ra, rb) = (radii[a as usize], radii[b as usize]);
            let (da, db) = (decide[a as usize], decide[b as usize]);
            let length = (0..3).map(|d| (q[d] - p[d]).powi(2)).sum::<f64>().sqrt();
            let longest = cell_side(cell, da.min(db), coarsest).max(MIN_SIDE) as f64 * coarsest;
            // Neither end in a vessel with cells (too thin or too thick, see `coarse`):
            // left as without a coarse start (splitting such edges changed thin trees'
            // graphs for no gain). With one end in such a vessel, the limit is at least
            // the smallest cell side.
            let thin = !(has_cells(cell, da, coarsest) || has_cells(cell, db, coarsest));
            let pieces = if thin { 1 } else { ((length / longest).ceil() as usize).clamp(1, MAX_PIECES) };
            (1..pieces)
                .map(|k| {
                    let t = k as f64 / pieces as f64;
                    (std::array::from_fn(|d| p[d] + t * (q[d] - p[d])), ra + t * (rb - ra))
                })
                .collect()
        };
        let mut prev = a;
        for (q, r) in new {
            let id = positions.len() as u32;
            positions.push(q);
            radii.push(r);
            component.push(component[a as usize]);
            edges.push((prev, id));
            prev = id;
        }
        edges.push((prev.min(b), prev.max(b)));
    }
    edges.sort_unstable();
    NodeGraph { graph: Csr::from_sorted_edges(positions.len(), &edges), positions, radii, component }
}

/// Every edge of `graph` as [`split_long_edges`] left it, by the old edge it came from:
/// the old edge's ends (`ends[0] < ends[1]`, numbers below `first`) and the nodes the
/// split added on it (numbered from `first`) from `ends[0]` to `ends[1]`, none for an
/// edge it kept whole; sorted by ends.
pub fn split_chains(graph: &Csr, first: usize) -> Vec<([u32; 2], Vec<u32>)> {
    let mut chains = vec![];
    for a in 0..first.min(graph.nodes()) {
        for &w in graph.neighbours(a) {
            // New nodes have degree 2: walk on, away from where we came from, to an old
            // node (at most every new node once).
            let (mut from, mut at, mut nodes) = (a as u32, w, vec![]);
            while at as usize >= first && nodes.len() < graph.nodes() {
                nodes.push(at);
                let next = graph.neighbours(at as usize).iter().copied().find(|&x| x != from);
                let Some(next) = next else { break };
                (from, at) = (at, next);
            }
            if (at as usize) < first && (a as u32) < at {
                chains.push(([a as u32, at], nodes));
            }
        }
    }
    chains.sort_unstable();
    chains
}

/// `radii` with the nodes from `first` on (those [`split_long_edges`] added, once the
/// medial stage has moved them and every node is on a foreground voxel) given the
/// distance transform where they sit ([`Field::radius_at`], physical units), in place
/// of their interpolated radii (module doc).
pub fn ridge_radii(radii: &mut [f64], positions: &[[f64; 3]], first: usize, field: &Field) {
    for (r, &p) in radii[first..].iter_mut().zip(&positions[first..]) {
        *r = field.radius_at(p);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn graph(positions: Vec<[f64; 3]>, radii: Vec<f64>, edges: &[(u32, u32)]) -> NodeGraph {
        let n = positions.len();
        NodeGraph { graph: Csr::from_sorted_edges(n, edges), positions, radii, component: vec![0; n] }
    }

    /// A single run's split: the nodes' own radii decide.
    fn split(g: NodeGraph, cell: f64, spacing: [f64; 3]) -> NodeGraph {
        let decide = g.radii.clone();
        split_long_edges(g, &decide, cell, spacing, &[])
    }

    /// A chunked run's merge splits as the blocks did: with the radii they decided by
    /// (a radius-4 tube's EDT, cells of 2 voxels), not the output radii it carries (3.82,
    /// a side of one voxel and no cells), which only the new nodes interpolate.
    #[test]
    fn the_deciding_radii_are_not_the_interpolated_ones() {
        let g = graph(vec![[0.0; 3], [8.0, 0.0, 0.0]], vec![3.82, 3.82], &[(0, 1)]);
        assert_eq!(split(g.clone(), 0.5, [1.0; 3]).positions.len(), 2);
        let s = split_long_edges(g, &[4.0, 4.0], 0.5, [1.0; 3], &[]);
        assert_eq!(s.positions.len(), 5);
        assert!(s.radii.iter().all(|&r| r == 3.82), "{:?}", s.radii);
    }

    #[test]
    fn an_edge_longer_than_the_cell_side_is_split_evenly() {
        // Radius 4, cell 0.5: sides of 2 voxels; the 10-voxel edge becomes 5 pieces.
        let g = graph(vec![[0.0; 3], [10.0, 0.0, 0.0]], vec![4.0, 6.0], &[(0, 1)]);
        let s = split(g, 0.5, [1.0; 3]);
        assert_eq!(s.positions.len(), 6);
        assert_eq!(s.graph.edge_list(), vec![(0, 2), (1, 5), (2, 3), (3, 4), (4, 5)]);
        for (k, p) in s.positions[2..].iter().enumerate() {
            assert!((p[0] - 2.0 * (k + 1) as f64).abs() < 1e-12 && p[1] == 0.0 && p[2] == 0.0, "{p:?}");
        }
        assert!((s.radii[2] - 4.4).abs() < 1e-12 && (s.radii[5] - 5.6).abs() < 1e-12, "{:?}", s.radii);
    }

    #[test]
    fn short_edges_are_kept_and_the_side_follows_the_coarsest_spacing() {
        // A 2-voxel edge at radius 4 is one cell side: kept.
        let g = graph(vec![[0.0; 3], [0.0, 2.0, 0.0], [0.0, 2.0, 2.0]], vec![4.0; 3], &[(0, 1), (1, 2)]);
        let s = split(g.clone(), 0.5, [1.0; 3]);
        assert_eq!((s.positions, s.graph), (g.positions.clone(), g.graph.clone()));
        // Spacing (0.5, 1, 2): a side is floor(0.5 * 8 / 2) = 2 voxels of 2 units.
        let s = split(graph(vec![[0.0; 3], [0.0, 0.0, 9.0]], vec![8.0; 2], &[(0, 1)]), 0.5, [0.5, 1.0, 2.0]);
        assert_eq!(s.positions.len(), 4);
        // Thin vessels (a side of one voxel at both ends): no edge is split, as without a
        // coarse start; with one end thick enough for cells, edges over 2 voxels are.
        let thin = |length: f64, r: f64| graph(vec![[0.0; 3], [length, 0.0, 0.0]], vec![0.9, r], &[(0, 1)]);
        assert_eq!(split(thin(2.0, 0.9), 0.5, [1.0; 3]).positions.len(), 2);
        assert_eq!(split(thin(4.5, 0.9), 0.5, [1.0; 3]).positions.len(), 2);
        assert_eq!(split(thin(4.5, 4.0), 0.5, [1.0; 3]).positions.len(), 4);
        // Edges at a junction are split too: a star of three 10-voxel edges at radius 4
        // (sides of 2 voxels) gains 4 nodes per arm, and the centre stays the junction.
        let arm = |d: usize| -> [f64; 3] { std::array::from_fn(|k| if k == d { 10.0 } else { 0.0 }) };
        let star = graph(vec![[0.0; 3], arm(0), arm(1), arm(2)], vec![4.0; 4], &[(0, 1), (0, 2), (0, 3)]);
        let s = split(star, 0.5, [1.0; 3]);
        assert_eq!(s.positions.len(), 16);
        assert_eq!(s.graph.neighbours(0), &[4, 8, 12]);
        assert!(s.graph.edge_list().iter().all(|&(a, b)| {
            let (p, q) = (s.positions[a as usize], s.positions[b as usize]);
            ((0..3).map(|d| (p[d] - q[d]).powi(2)).sum::<f64>().sqrt() - 2.0).abs() < 1e-12
        }));
    }

    /// A radius-4 tube leaving a ball of radius 9 (a junction in a blob): the edge from
    /// the ball's centre, radius the blob's EDT, down the tube is split, and the new
    /// nodes in the tube take the tube's radius (to half a voxel: 4.12, the axis voxel's
    /// distance to the nearest background centre), where interpolating from the blob's
    /// read them up to 3.5 voxels wide. Only the new nodes change.
    #[test]
    fn split_nodes_take_the_transform_where_they_sit_not_the_blobs_radius() {
        use crate::shapes::{capsules, Capsule};
        let (centre, tip) = ([12.0, 12.0, 12.0], [12.0, 56.0, 12.0]);
        let parts = [Capsule { a: centre, b: centre, r: 9.0 }, Capsule { a: centre, b: [12.0, 62.0, 12.0], r: 4.0 }];
        let mask = capsules([25, 64, 25], [1.0; 3], &parts);
        let field = Field::new(mask.view(), [1.0; 3]).unwrap();
        let ends = vec![centre, tip];
        let radii: Vec<f64> = ends.iter().map(|&p| field.radius_at(p)).collect();
        let s = split(graph(ends, radii.clone(), &[(0, 1)]), 0.5, [1.0; 3]);
        assert!(s.positions.len() > 10, "{} nodes", s.positions.len());
        let mut ridge = s.radii.clone();
        ridge_radii(&mut ridge, &s.positions, 2, &field);
        assert_eq!(ridge[..2], radii[..]);
        let mut worst_interpolated: f64 = 0.0;
        for k in 2..s.positions.len() {
            let p = s.positions[k];
            assert_eq!(ridge[k], field.radius_at(p));
            // In the tube, clear of the ball.
            if p[1] - centre[1] > 9.0 + 4.0 {
                assert!((ridge[k] - 4.0).abs() <= 0.5, "node {k} at {p:?}: radius {}", ridge[k]);
                worst_interpolated = worst_interpolated.max(s.radii[k] - 4.0);
            }
        }
        assert!(worst_interpolated > 3.0, "interpolated radii at most {worst_interpolated} over the tube's");
    }
}
