//! Edges kept inside the mask (output stage, last; not in the paper).
//!
//! [`crate::inside`] puts every node on a vessel voxel, but the straight edge between
//! two nodes can still cut across background: the chord of a thin curved vessel, a
//! junction or an end moved by [`crate::medial`] or [`crate::ends`], a spoke of a knot
//! collapsed by refinement (measured before this stage: 0.6–1.0 % of the edge length
//! of the noisy forests of `benches/fidelity.py` over background voxels). A centreline
//! must run in its vessel, so every edge that leaves the mask is subdivided:
//!
//! - the edge is sampled as `vesselflow.metrics.mask_fidelity` samples it: split into
//!   `ceil(length / (c / 4))` equal pieces (`c` the base cell), each piece's midpoint
//!   in the voxel it rounds to; the edge leaves the mask where a sample is background;
//! - the middle of the run from the first to the last outside sample moves to the
//!   nearest foreground voxel centre ([`crate::inside`]'s search), then climbs, in the
//!   plane through it orthogonal to the edge, to the ridge of the distance transform
//!   (the steepest ascent of [`crate::medial`], which never crosses a saddle into a
//!   neighbouring vessel), with a reach of the larger distance-transform value at the
//!   edge's ends plus one base cell;
//!   or stays at the voxel centre when that leaves less of the two halves outside;
//! - that point becomes a new node of degree 2 between the edge's ends, and the two
//!   halves are checked in turn, to a depth of [`MAX_DEPTH`];
//! - a piece on which a split makes no progress (the point found is one of its ends,
//!   or leaves no less outside, or no foreground voxel lies within
//!   [`crate::inside::SEARCH_LIMIT`] voxels), or that is still outside at that depth,
//!   follows instead a shortest 26-connected path of foreground voxels between its
//!   ends' voxels, searched in their bounding box grown by [`PATH_MARGIN`] voxels of
//!   the coarsest spacing along every axis ([`path_margin`]; voxels joined only around
//!   a corner, which no single point between them joins).
//!
//! Every search is bounded (the depth, the box), so the stage ends on any input.
//!
//! A subdivision replaces an edge by a path through new degree-2 nodes, so the graph's
//! components, cycles, junctions and ends are those it had: no spur, no new loop.
//! One exception keeps two nodes from sharing a position: when routes of two edges of
//! one node leave it through the same point (both routed to the same voxel, as two
//! branches leaving a junction through one vessel do), they share that point's node
//! (and the next while the routes agree), so the branches part there; the count of
//! components and the cycle rank are unchanged (on the 256³ bed: two nodes at
//! (212, 77, 63) before, one now).
//! New nodes are numbered after the old ones, in the order of the edges they split
//! (sorted edge list) and, within an edge, from its smaller end to its larger; each
//! edge is routed on its own (in parallel), so the result does not depend on the
//! thread count. Edges that stay inside, and their nodes, are unchanged bit for bit.

use crate::grid::Csr;
use crate::inside::{nearest_foreground, on_mask, voxel_of};
use crate::medial::{climb, plane_basis, Field};
use crate::radius::output_radii;
use crate::vec3::{base_cell, coarsest, norm, sub};
use crate::volume::Voxel;
use ndarray::ArrayView3;
use rayon::prelude::*;
use std::collections::HashMap;

/// Deepest subdivision of one edge.
pub const MAX_DEPTH: usize = 6;

/// Samples per base cell along an edge (as `vesselflow.metrics.mask_fidelity`).
pub const SAMPLES_PER_CELL: f64 = 4.0;

/// The graph with its edges routed inside the mask.
#[derive(Debug, Clone)]
pub struct Routed {
    pub graph: Csr,
    /// Old nodes' positions first (unchanged), then the new nodes'.
    pub positions: Vec<[f64; 3]>,
    /// For every new node (index `old + k`), its two neighbours on the route that made it
    /// (a node shared by two routes has a third neighbour in the graph).
    pub inserted: Vec<[u32; 2]>,
    /// The distance transform at every new node, physical units (the first guess of
    /// the radius models, like the clusters' EDT radii of the old nodes).
    pub inserted_edt: Vec<f64>,
}

/// The background samples of the segment `p`–`q`: the first and last, their count,
/// and the number of samples (see the module); `None` when every sample is foreground.
pub fn outside_run<T: Voxel>(mask: &ArrayView3<'_, T>, p: [f64; 3], q: [f64; 3], spacing: [f64; 3]) -> Option<Outside> {
    let c = base_cell(spacing);
    let d = sub(q, p);
    let pieces = ((norm(d) * SAMPLES_PER_CELL / c).ceil() as usize).max(1);
    let outside = |k: usize| {
        let t = (k as f64 + 0.5) / pieces as f64;
        let x = std::array::from_fn(|a| p[a] + t * d[a]);
        !on_mask(mask, x, spacing)
    };
    let first = (0..pieces).find(|&k| outside(k))?;
    let last = (first..pieces).rev().find(|&k| outside(k)).unwrap_or(first);
    let count = (first..=last).filter(|&k| outside(k)).count();
    Some(Outside { first, last, count, pieces })
}

/// Where a segment leaves the mask, in samples ([`outside_run`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Outside {
    pub first: usize,
    pub last: usize,
    pub count: usize,
    pub pieces: usize,
}

/// The length of `p`–`q` over background, estimated by its samples.
fn outside_length<T: Voxel>(mask: &ArrayView3<'_, T>, p: [f64; 3], q: [f64; 3], spacing: [f64; 3]) -> f64 {
    outside_run(mask, p, q, spacing).map_or(0.0, |o| o.count as f64 / o.pieces as f64 * norm(sub(q, p)))
}

/// The points to insert between `p` and `q`, in order from `p` (see the module).
fn route<T: Voxel>(
    mask: &ArrayView3<'_, T>,
    field: &Field,
    spacing: [f64; 3],
    p: [f64; 3],
    q: [f64; 3],
    depth: usize,
    out: &mut Vec<[f64; 3]>,
) {
    let Some(Outside { first, last, pieces, .. }) = outside_run(mask, p, q, spacing) else { return };
    if depth >= MAX_DEPTH {
        out.extend(voxel_path(mask, p, q, spacing));
        return;
    }
    let c = base_cell(spacing);
    let d = sub(q, p);
    let t = (first + last + 1) as f64 / (2 * pieces) as f64;
    let middle = std::array::from_fn(|a| p[a] + t * d[a]);
    let Some(v) = nearest_foreground(mask, middle, spacing) else {
        out.extend(voxel_path(mask, p, q, spacing));
        return;
    };
    let centre: [f64; 3] = std::array::from_fn(|a| v[a] as f64 * spacing[a]);
    let reach = (field.interpolate(p).max(field.interpolate(q)) + 1.0) * c;
    let n = norm(d);
    let ridge = if n > 0.0 { climb(field, centre, plane_basis(d.map(|x| x / n)), reach, c) } else { None };
    // The ridge point, unless the voxel centre leaves less of the two halves outside.
    let left = |m: [f64; 3]| outside_length(mask, p, m, spacing) + outside_length(mask, m, q, spacing);
    let m = match ridge {
        Some(r) if left(r) <= left(centre) => r,
        _ => centre,
    };
    let tiny = 1e-9 * c;
    if norm(sub(m, p)) <= tiny || norm(sub(m, q)) <= tiny || left(m) >= outside_length(mask, p, q, spacing) {
        out.extend(voxel_path(mask, p, q, spacing));
        return;
    }
    route(mask, field, spacing, p, m, depth + 1, out);
    out.push(m);
    route(mask, field, spacing, m, q, depth + 1, out);
}

/// Margin, in voxels of the coarsest spacing, of the box searched for a voxel path
/// around its two ends. Counted in voxels of each axis instead, a two-photon stack's
/// box (5 × 0.99 × 0.99 µm) grew by 2 µm across and 10 µm along z, and the routes
/// round a vessel's bends within a plane were not found: edge length outside the mask
/// `tpm_burgess2014` 0.92 → 0.09 %, `tpm_santos2015` 0.18 → 0.08 %, `tpm_poon2015`
/// 0.12 → 0.04 % (the same on isotropic grids).
pub const PATH_MARGIN: isize = 2;

/// Most voxels the box searched for a voxel path grows by along one axis (a stack far
/// finer across than along one axis would otherwise search most of a plane per edge).
pub const MAX_PATH_MARGIN: isize = 32;

/// The margin of the voxel path's box along each axis, in that axis's voxels:
/// [`PATH_MARGIN`] voxels of the coarsest spacing, at most [`MAX_PATH_MARGIN`].
pub fn path_margin(spacing: [f64; 3]) -> [isize; 3] {
    let coarsest = coarsest(spacing);
    spacing.map(|s| ((PATH_MARGIN as f64 * coarsest / s).ceil() as isize).min(MAX_PATH_MARGIN))
}

/// The centres of the voxels of a shortest 26-connected path of foreground voxels
/// from `p`'s voxel to `q`'s (both included, unless a centre is `p` or `q` itself),
/// searched breadth first (neighbours in C order) in their bounding box grown by
/// [`path_margin`]; empty when there is none.
fn voxel_path<T: Voxel>(mask: &ArrayView3<'_, T>, p: [f64; 3], q: [f64; 3], spacing: [f64; 3]) -> Vec<[f64; 3]> {
    let (n0, n1, n2) = mask.dim();
    let shape = [n0, n1, n2];
    let (Some(a), Some(b)) = (voxel_of(p, spacing, shape), voxel_of(q, spacing, shape)) else { return vec![] };
    let margin = path_margin(spacing);
    let lo: [isize; 3] = std::array::from_fn(|d| (a[d].min(b[d]) as isize - margin[d]).max(0));
    let hi: [isize; 3] = std::array::from_fn(|d| (a[d].max(b[d]) as isize + margin[d]).min(shape[d] as isize - 1));
    let side: [usize; 3] = std::array::from_fn(|d| (hi[d] - lo[d] + 1) as usize);
    let index = |v: [isize; 3]| {
        ((v[0] - lo[0]) as usize * side[1] + (v[1] - lo[1]) as usize) * side[2] + (v[2] - lo[2]) as usize
    };
    let mut parent = vec![usize::MAX; side[0] * side[1] * side[2]];
    let start = a.map(|x| x as isize);
    let goal = b.map(|x| x as isize);
    parent[index(start)] = index(start);
    let mut queue = std::collections::VecDeque::from([start]);
    // Each voxel of the box enters the queue once: bounded by the box.
    while let Some(v) = queue.pop_front() {
        if v == goal {
            break;
        }
        for o in 0..27 {
            let w: [isize; 3] = [v[0] + o / 9 - 1, v[1] + (o / 3) % 3 - 1, v[2] + o % 3 - 1];
            if (0..3).any(|d| w[d] < lo[d] || w[d] > hi[d]) || parent[index(w)] != usize::MAX {
                continue;
            }
            if mask[[w[0] as usize, w[1] as usize, w[2] as usize]].is_set() {
                parent[index(w)] = index(v);
                queue.push_back(w);
            }
        }
    }
    if parent[index(goal)] == usize::MAX {
        return vec![];
    }
    let centre = |i: usize| {
        let v = [i / (side[1] * side[2]), (i / side[2]) % side[1], i % side[2]];
        std::array::from_fn(|d| (v[d] as isize + lo[d]) as f64 * spacing[d])
    };
    let mut path = vec![centre(index(goal))];
    let mut i = index(goal);
    while i != index(start) {
        i = parent[i];
        path.push(centre(i));
    }
    path.reverse();
    let c = base_cell(spacing);
    path.retain(|&x| norm(sub(x, p)) > 1e-9 * c && norm(sub(x, q)) > 1e-9 * c);
    path
}

/// `g` with every edge that leaves the mask subdivided by new nodes on the mask (see
/// the module). `field` is the distance transform of `mask`.
pub fn route_inside<T: Voxel>(
    g: &Csr,
    positions: &[[f64; 3]],
    field: &Field,
    mask: ArrayView3<'_, T>,
    spacing: [f64; 3],
) -> Routed {
    let edges = g.edge_list();
    let paths: Vec<Vec<[f64; 3]>> = edges
        .par_iter()
        .map(|&(a, b)| {
            let mut out = vec![];
            route(&mask, field, spacing, positions[a as usize], positions[b as usize], 0, &mut out);
            out
        })
        .collect();
    let old = positions.len();
    let mut all = positions.to_vec();
    let mut new_edges = Vec::with_capacity(edges.len());
    let mut inserted = vec![];
    // New nodes by (a neighbour, position): a route that leaves a node through a point
    // an earlier route from that node took shares the earlier route's node there.
    let mut beside: HashMap<(u32, [u64; 3]), u32> = HashMap::new();
    let key = |n: u32, m: [f64; 3]| (n, m.map(f64::to_bits));
    for (&(a, b), path) in edges.iter().zip(&paths) {
        // The longest shared start from `a`, then the longest shared end into `b`.
        let (mut lo, mut prev) = (0, a);
        while let Some(&id) = path.get(lo).and_then(|&m| beside.get(&key(prev, m))) {
            (lo, prev) = (lo + 1, id);
        }
        let (mut hi, mut last) = (path.len(), b);
        while let Some(&id) = (hi > lo).then(|| beside.get(&key(last, path[hi - 1]))).flatten() {
            (hi, last) = (hi - 1, id);
        }
        for (k, &m) in path[lo..hi].iter().enumerate() {
            let id = all.len() as u32;
            all.push(m);
            new_edges.push((prev.min(id), prev.max(id)));
            let next = if lo + k + 1 < hi { id + 1 } else { last };
            inserted.push([prev, next]);
            beside.insert(key(prev, m), id);
            beside.insert(key(next, m), id);
            prev = id;
        }
        if prev != last {
            new_edges.push((prev.min(last), prev.max(last)));
        }
    }
    new_edges.sort_unstable();
    new_edges.dedup();
    let inserted_edt = all[old..].iter().map(|&m| field.radius_at(m)).collect();
    Routed { graph: Csr::from_sorted_edges(all.len(), &new_edges), positions: all, inserted, inserted_edt }
}

/// [`route_inside`] and the radii of the new nodes ([`output_radii`], less `shift`), as
/// the output gives every node: the one routing of the single run's output and of a
/// chunked run's routing phase ([`crate::blocks_route`]).
pub fn route_with_radii<T: Voxel>(
    g: &Csr,
    positions: &[[f64; 3]],
    field: &Field,
    mask: ArrayView3<'_, T>,
    spacing: [f64; 3],
    shift: f64,
) -> (Routed, Vec<f64>) {
    let routed = route_inside(g, positions, field, mask, spacing);
    let radii = routed.inserted_radii(|g, q, r| output_radii(g, q, r, &|_| true, mask, field, spacing, shift));
    (routed, radii)
}

impl Routed {
    /// The radii of the new nodes by `radii_of(graph, positions, edt_radii)`, a radius
    /// model applied to a graph of one three-node path (neighbour, new node,
    /// neighbour) per new node: a degree-2 node's radius depends on its own position
    /// and EDT value and on its two neighbours' positions only, so each gets the radius
    /// it has in the routed graph, without measuring every old node again.
    pub fn inserted_radii(&self, radii_of: impl Fn(&Csr, &[[f64; 3]], &[f64]) -> Vec<f64>) -> Vec<f64> {
        let k = self.inserted.len();
        if k == 0 {
            return vec![];
        }
        let edges: Vec<(u32, u32)> = (0..k as u32).flat_map(|i| [(3 * i, 3 * i + 1), (3 * i + 1, 3 * i + 2)]).collect();
        let old = self.positions.len() - k;
        let mut positions = Vec::with_capacity(3 * k);
        let mut edt = Vec::with_capacity(3 * k);
        for (i, &[a, b]) in self.inserted.iter().enumerate() {
            positions.extend([self.positions[a as usize], self.positions[old + i], self.positions[b as usize]]);
            edt.extend([self.inserted_edt[i]; 3]);
        }
        let r = radii_of(&Csr::from_sorted_edges(3 * k, &edges), &positions, &edt);
        (0..k).map(|i| r[3 * i + 1]).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    /// An L-shaped one-voxel-thick bend: the chord between its two arms' ends crosses
    /// background; routing makes it a path of new degree-2 nodes on the bend's voxels,
    /// every edge of which runs inside.
    #[test]
    fn a_chord_across_a_bend_is_routed_through_the_corner() {
        let mut mask = Array3::<u8>::zeros((3, 12, 12));
        for t in 1..=8 {
            mask[[1, t, 1]] = 1;
            mask[[1, 8, t]] = 1;
        }
        let field = Field::new(mask.view(), [1.0; 3]).unwrap();
        let g = Csr::from_sorted_edges(2, &[(0, 1)]);
        let p = vec![[1.0, 1.0, 1.0], [1.0, 8.0, 8.0]];
        assert!(outside_run(&mask.view(), p[0], p[1], [1.0; 3]).is_some());
        let r = route_inside(&g, &p, &field, mask.view(), [1.0; 3]);
        assert_eq!(&r.positions[..2], &p[..]);
        assert!(r.positions.len() > 2, "no node inserted");
        // The path 0 → new nodes → 1, every edge inside.
        for (a, b) in r.graph.edge_list() {
            let (pa, pb) = (r.positions[a as usize], r.positions[b as usize]);
            assert_eq!(outside_run(&mask.view(), pa, pb, [1.0; 3]), None, "{pa:?}-{pb:?}");
        }
        for q in &r.positions[2..] {
            assert_eq!(mask[voxel_of(*q, [1.0; 3], [3, 12, 12]).unwrap()], 1, "{q:?}");
        }
        let deg: Vec<usize> = (0..r.graph.nodes()).map(|i| r.graph.neighbours(i).len()).collect();
        assert_eq!(deg[..2], [1, 1]);
        assert!(deg[2..].iter().all(|&d| d == 2));
        assert_eq!(r.graph.edges(), r.graph.nodes() - 1);
        // Each new node's recorded neighbours are its neighbours in the graph.
        for (k, nb) in r.inserted.iter().enumerate() {
            assert_eq!(r.graph.neighbours(2 + k), &{
                let mut s = *nb;
                s.sort_unstable();
                s
            });
        }
    }

    /// An edge inside the mask is left alone, and an edge whose middle has no
    /// foreground within the search limit is left as it is (bounded, no panic).
    #[test]
    fn inside_edges_and_hopeless_edges_are_left_as_they_are() {
        let mut mask = Array3::<u8>::zeros((3, 40, 3));
        for j in 0..40 {
            if !(10..30).contains(&j) {
                mask[[1, j, 1]] = 1;
            }
        }
        let field = Field::new(mask.view(), [1.0; 3]).unwrap();
        let g = Csr::from_sorted_edges(3, &[(0, 1), (1, 2)]);
        let p = vec![[1.0, 2.0, 1.0], [1.0, 8.0, 1.0], [1.0, 35.0, 1.0]];
        let r = route_inside(&g, &p, &field, mask.view(), [1.0; 3]);
        assert_eq!(r.positions[..3], p[..]);
        // The gap 10..30 is 20 voxels wide: its middle is 10.5 voxels from any vessel,
        // beyond the search.
        assert_eq!(r.positions.len(), 3);
        assert_eq!(r.graph.edge_list(), vec![(0, 1), (1, 2)]);
        assert!(r.inserted.is_empty() && r.inserted_radii(|_, _, _| unreachable!()).is_empty());
    }
    /// A U in one plane of an anisotropic stack (5 × 0.5 × 0.5): the chord between the
    /// ends of its arms crosses background, the voxel nearest its middle is an arm's
    /// end, and the only path round lies 4 voxels (2 units) beyond the ends' box. The
    /// box searched for a voxel path is grown by 2 voxels of the coarsest spacing (20
    /// voxels of 0.5 here), not by 2 voxels of every axis, so the route goes round the U.
    #[test]
    fn the_voxel_path_box_grows_by_the_coarsest_spacing() {
        let mut mask = Array3::<u8>::zeros((3, 20, 11));
        for j in 2..=14 {
            mask[[1, j, 2]] = 1;
            mask[[1, j, 8]] = 1;
        }
        for k in 2..=8 {
            mask[[1, 14, k]] = 1;
        }
        let spacing = [5.0, 0.5, 0.5];
        let field = Field::new(mask.view(), spacing).unwrap();
        let g = Csr::from_sorted_edges(2, &[(0, 1)]);
        let p = vec![[5.0, 5.0, 1.0], [5.0, 5.0, 4.0]];
        assert!(outside_run(&mask.view(), p[0], p[1], spacing).is_some());
        let r = route_inside(&g, &p, &field, mask.view(), spacing);
        assert!(r.positions.len() > 2, "no route found");
        for (a, b) in r.graph.edge_list() {
            let (pa, pb) = (r.positions[a as usize], r.positions[b as usize]);
            assert_eq!(outside_run(&mask.view(), pa, pb, spacing), None, "{pa:?}-{pb:?}");
        }
        // The route reaches the U's bottom (voxel row 14, 7 units down the axis).
        assert!(r.positions.iter().any(|q| (q[1] - 7.0).abs() < 1e-9), "{:?}", r.positions);
    }

    /// Two edges from one node whose chords leave a one-voxel-thick Y at the same
    /// place are routed through the same voxel: that point becomes one node, shared
    /// by both routes (never two nodes at one position), and the graph keeps its
    /// components and cycle rank.
    #[test]
    fn two_routes_through_one_point_share_its_node() {
        let mut mask = Array3::<u8>::zeros((3, 14, 11));
        for j in 1..=8 {
            mask[[1, j, 5]] = 1;
        }
        for t in 1..=4 {
            mask[[1, 8 + t, 5 - t]] = 1;
            mask[[1, 8 + t, 5 + t]] = 1;
        }
        let field = Field::new(mask.view(), [1.0; 3]).unwrap();
        let g = Csr::from_sorted_edges(3, &[(0, 1), (0, 2)]);
        let p = vec![[1.0, 1.0, 5.0], [1.0, 12.0, 1.0], [1.0, 12.0, 9.0]];
        for q in &p[1..] {
            assert!(outside_run(&mask.view(), p[0], *q, [1.0; 3]).is_some());
        }
        let r = route_inside(&g, &p, &field, mask.view(), [1.0; 3]);
        let mut seen: Vec<[u64; 3]> = r.positions.iter().map(|q| q.map(f64::to_bits)).collect();
        seen.sort_unstable();
        let n = seen.len();
        seen.dedup();
        assert_eq!(seen.len(), n, "two nodes at one position: {:?}", r.positions);
        assert_eq!(r.graph.edges(), r.graph.nodes() - 1, "a cycle was made");
    }
}
