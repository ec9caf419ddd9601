//! Sprouts (output stage, with `sprouts`; not in the paper).
//!
//! Contraction can swallow a short side branch into its parent: the branch's nodes
//! collapse onto the parent's centreline and no end is left to follow it
//! ([`crate::ends`] only moves existing ends). On the noisiest synthetic forests of
//! `benches/fidelity.py` such lost branches are about an eighth of the geometric false
//! negatives. This stage finds them in the mask and grows them back.
//!
//! Every vessel voxel gets its geodesic distance `D` through the mask (26-neighbour
//! steps, [`Reach`]) from the voxels the graph's edges pass through. A voxel inside a
//! vessel the graph covers lies at most about its vessel's radius from an edge, so `D`
//! exceeds its distance transform by little; one in a lost branch lies further away
//! than its own radius by about the branch's length. Voxels with `D - EDT >
//! SPROUT_GAP` cells form the unreached lobes of the mask (26-connected). From each
//! lobe's farthest voxel (the branch's cap) the shortest path runs back to the graph;
//! the sprout ends where the cap's ball is centred (the first voxel back along the path
//! whose transform reaches its distance from the farthest voxel), and starts on the
//! nearest edge of the graph (split there). A sprout shorter than [`BUMP_RADII`] radii
//! of its parent (the radii of the edge's nodes, interpolated where it starts) is a
//! bump of the parent's wall, such as a noise bubble, a flat vessel's rim or the
//! corner of a square end, not a vessel, and is not grown. Sprouts are grown in rounds
//! (a lost branch with a side branch of its own shows that one only once the first is
//! grown), at most [`ROUNDS`]; each round adds the new edges to the sources and updates
//! the distances from them alone. The new nodes are placed on the path every
//! [`NODE_STEP`] cells and then centred like every other node
//! ([`crate::medial::recentre`]).

use crate::edge_grid::{nearest_by_scan, EdgeGrid};
use crate::ends::edge_voxels;
use crate::error::Result;
use crate::grid::Csr;
use crate::medial::{recentre, Field};
use crate::memory::try_filled;
use crate::vec3::{base_cell, coarsest, norm, sub};
use rustc_hash::FxHashSet;

/// How far (base cells) a voxel's geodesic distance from the graph may exceed its own
/// distance transform before it counts as unreached (tuned on the tuning forests).
const SPROUT_GAP: f64 = 8.0;
/// A sprout shorter than this many radii of its parent (from where it starts on the
/// parent's edge to its end) is a bump, not a branch. On the tuning forests the sprouts
/// into noise bubbles were at most about 2.6 parent radii long, true ones mostly over 3;
/// 3.5 also keeps the one false sprout of the tuning trees out.
const BUMP_RADII: f64 = 3.5;
/// Rounds of sprouting.
const ROUNDS: usize = 3;
/// Spacing of a sprout's nodes along its path, in base cells.
const NODE_STEP: f64 = 2.0;
/// Marks a foreground voxel no graph voxel reaches (another mask component) and, in
/// the lobe labels, a voxel of no lobe.
const NONE: u32 = u32::MAX;

/// The graph with its lost branches grown back (see the module): `g` with the new
/// nodes numbered from `g.nodes()`, their positions appended to `positions`. `reach`
/// holds the distances from an earlier state of the graph ([`Reach::of`]), so that it
/// can be computed beside other work; `g`'s own edges are added to its sources first.
/// `radii` are the radii of `g`'s nodes (physical units), which set how long a sprout
/// must be ([`BUMP_RADII`]); the new nodes' are the transform's where they sit. Also
/// returns the sprouts grown, in the order they were grown.
pub fn sprout(
    mut reach: Reach<'_>,
    g: &Csr,
    positions: &[[f64; 3]],
    radii: &[f64],
) -> Result<(Csr, Vec<[f64; 3]>, Vec<Grown>)> {
    let mut graph = g.clone();
    let mut pos = positions.to_vec();
    let mut all = vec![];
    for round in 0..ROUNDS {
        // Each round's sources add to the last round's: distances only shrink.
        reach.extend(&graph, &pos);
        let first = pos.len();
        let (next, grown, sprouts) = sprout_round(&graph, &pos, radii, &reach, round)?;
        if sprouts.is_empty() {
            break;
        }
        all.extend(sprouts);
        pos = grown;
        let centred = centre_new(&next, &pos, first, reach.field, reach.spacing);
        pos[first..].copy_from_slice(&centred);
        graph = next;
    }
    Ok((graph, pos, all))
}

/// One sprout as grown: its round (from 0), its lobe's farthest voxel (the voxel's
/// index in the mask array), the node it starts from (a node of the graph it grew
/// from, or one the split added when `split`), and its new nodes, start to end.
#[derive(Debug, Clone, PartialEq)]
pub struct Grown {
    pub round: usize,
    pub tip: [usize; 3],
    pub start: u32,
    pub split: bool,
    pub nodes: std::ops::Range<u32>,
}

/// The nodes `first..` of `g` centred like every other node ([`recentre`]), on the
/// graph of them and their neighbours (the rest stay where they are).
fn centre_new(g: &Csr, positions: &[[f64; 3]], first: usize, field: &Field, spacing: [f64; 3]) -> Vec<[f64; 3]> {
    let mut local: Vec<usize> = (first..g.nodes()).flat_map(|i| g.neighbours(i).iter().map(|&j| j as usize)).collect();
    local.extend(first..g.nodes());
    local.sort_unstable();
    local.dedup();
    let at = |i: usize| local.binary_search(&i).ok().map(|k| k as u32);
    let mut edges: Vec<(u32, u32)> = local
        .iter()
        .enumerate()
        .flat_map(|(k, &i)| g.neighbours(i).iter().filter_map(move |&j| at(j as usize).map(|l| (k as u32, l))))
        .filter(|&(k, l)| k < l)
        .collect();
    edges.sort_unstable();
    let c = base_cell(spacing);
    let p: Vec<[f64; 3]> = local.iter().map(|&i| positions[i]).collect();
    let radii: Vec<f64> = p.iter().map(|&q| field.radius_at(q).max(c)).collect();
    let centred = recentre(&Csr::from_sorted_edges(local.len(), &edges), &p, &radii, field);
    centred[local.len() - (g.nodes() - first)..].to_vec()
}

fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    norm(sub(*a, *b))
}

/// Geodesic distances through the mask from the voxels of a graph's edges, and the
/// voxel each was reached from, per foreground voxel ([`Field::index`]); 8 bytes per
/// vessel voxel. Steps go to the 26 neighbours and cost their length in units of
/// `1 / UNITS` base cell, rounded (at most 2 % long), so that a bucket queue orders
/// them: each voxel costs O(1), not the O(log n) of a heap.
pub struct Reach<'a> {
    field: &'a Field,
    spacing: [f64; 3],
    steps: [u32; 27],
    dist: Vec<u32>,
    from: Vec<u32>,
}

/// How far (in the coarsest spacing) the grid searches for the edge nearest a path's
/// root, a voxel the graph's edges pass through: farther, every edge is scanned.
const ROOT_SEARCH: f64 = 2.0;

/// Step costs per base cell (see [`Reach`]).
const UNITS: f64 = 16.0;

impl<'a> Reach<'a> {
    /// The distances from the edges of `g` (positions in physical units) through the
    /// foreground of `field`, whose voxels have `spacing`.
    pub fn of(g: &Csr, positions: &[[f64; 3]], field: &'a Field, spacing: [f64; 3]) -> Result<Reach<'a>> {
        let mut reach = Reach::new(field, spacing)?;
        reach.extend(g, positions);
        Ok(reach)
    }

    fn new(field: &'a Field, spacing: [f64; 3]) -> Result<Reach<'a>> {
        let c = base_cell(spacing);
        let steps = std::array::from_fn(|o| {
            let d = [o / 9, (o / 3) % 3, o % 3];
            (norm(std::array::from_fn(|k| (d[k] as f64 - 1.0) * spacing[k])) / c * UNITS).round() as u32
        });
        let n = field.count();
        Ok(Reach { field, spacing, steps, dist: try_filled(n, NONE)?, from: try_filled(n, NONE)? })
    }

    /// The distance at foreground voxel `i`, in physical units (infinite if unreached).
    fn at(&self, i: usize) -> f64 {
        match self.dist[i] {
            NONE => f64::INFINITY,
            d => d as f64 / UNITS * base_cell(self.spacing),
        }
    }

    /// Adds the voxels of `g`'s edges to the sources (Dial's algorithm from the new
    /// ones; distances saturate below [`NONE`]).
    fn extend(&mut self, g: &Csr, positions: &[[f64; 3]]) {
        let field = self.field;
        let shape = field.shape();
        let width = *self.steps.iter().max().unwrap_or(&1) as usize + 1;
        // Each entry: the voxel's foreground index and its row.
        let mut buckets: Vec<Vec<(u32, usize)>> = vec![Vec::new(); width];
        let mut pending = 0usize;
        for v in edge_voxels(g, positions, shape, self.spacing) {
            let (row, k) = (v / shape[2], v % shape[2]);
            if let Some(i) = field.index([row / shape[1], row % shape[1], k]).filter(|&i| self.dist[i] > 0) {
                self.dist[i] = 0;
                self.from[i] = i as u32;
                buckets[0].push((i as u32, row));
                pending += 1;
            }
        }
        let (dist, from, steps) = (&mut self.dist, &mut self.from, &self.steps);
        let mut d = 0u32;
        while pending > 0 {
            let bucket = std::mem::take(&mut buckets[d as usize % width]);
            pending -= bucket.len();
            for &(i, row) in &bucket {
                if dist[i as usize] != d {
                    continue;
                }
                field.for_neighbours(i as usize, row, |o, j, row| {
                    let nd = d.saturating_add(steps[o]).min(NONE - 1);
                    if nd < dist[j] {
                        dist[j] = nd;
                        from[j] = i;
                        buckets[nd as usize % width].push((j as u32, row));
                        pending += 1;
                    }
                });
            }
            d += 1;
        }
    }

    /// The centre of foreground voxel `i`.
    fn centre(&self, i: usize) -> [f64; 3] {
        let v = self.field.voxel(i);
        std::array::from_fn(|d| v[d] as f64 * self.spacing[d])
    }
}

/// One round: every lobe's sprout whose path shares no voxel with an earlier one's;
/// the graph, the positions and the sprouts.
fn sprout_round(
    g: &Csr,
    positions: &[[f64; 3]],
    radii: &[f64],
    reach: &Reach<'_>,
    round: usize,
) -> Result<(Csr, Vec<[f64; 3]>, Vec<Grown>)> {
    let field = reach.field;
    let c = base_cell(reach.spacing);
    let edt = |i: usize| field.dist_at(i) * c;
    let d = |i: usize| reach.at(i);
    // The unreached voxels (in a component the graph reaches), labelled by lobe
    // (26-connected), each lobe's farthest voxel its tip; index order throughout.
    let mut lobe = try_filled(field.count(), NONE)?;
    let unreached = |i: usize| d(i).is_finite() && d(i) - edt(i) > SPROUT_GAP * c;
    let mut tips = Vec::new();
    for s in 0..field.count() {
        if lobe[s] != NONE || !unreached(s) {
            continue;
        }
        let id = tips.len() as u32;
        lobe[s] = id;
        let (mut stack, mut far) = (vec![(s, field.row(s))], s);
        while let Some((i, row)) = stack.pop() {
            if d(i) > d(far) {
                far = i;
            }
            field.for_neighbours(i, row, |_, j, row| {
                if lobe[j] == NONE && unreached(j) {
                    lobe[j] = id;
                    stack.push((j, row));
                }
            });
        }
        tips.push(far);
    }
    drop(lobe);
    // Farthest tips first: a long branch claims its path before the lobes along it.
    tips.sort_by(|&a, &b| d(b).total_cmp(&d(a)).then(a.cmp(&b)));
    // Back from each tip: the path to the graph, tip first (distances fall strictly
    // along it, so it ends).
    let paths: Vec<Vec<usize>> = tips
        .iter()
        .map(|&tip| {
            let mut path = vec![tip];
            let mut i = tip;
            while d(i) > 0.0 {
                i = reach.from[i] as usize;
                path.push(i);
            }
            path
        })
        .collect();
    let mut edges = g.edge_list();
    let mut pos = positions.to_vec();
    // The edges near the paths' roots (on the graph's voxels), for the nearest-edge
    // search; kept up to date as edges are split and sprouts added.
    let coarse = coarsest(reach.spacing);
    let roots = paths.iter().map(|path| reach.centre(path[path.len() - 1]));
    let mut grid = EdgeGrid::around(roots, ROOT_SEARCH * coarse);
    for (k, &(a, b)) in edges.iter().enumerate() {
        grid.insert(k, pos[a as usize], pos[b as usize]);
    }
    let mut claimed: FxHashSet<usize> = FxHashSet::default();
    let mut sprouts = vec![];
    for path in paths {
        let tip = path[0];
        if path.iter().any(|i| claimed.contains(i)) {
            continue;
        }
        // The sprout ends at the centre of the cap's ball.
        let far = d(tip);
        let Some(end) = path.iter().position(|&i| edt(i) >= far - d(i)).filter(|&e| e + 1 < path.len()) else {
            continue;
        };
        // The edge nearest the root, split at the root's projection onto it.
        let root = *path.last().unwrap();
        let segment = |k: usize| (pos[edges[k].0 as usize], pos[edges[k].1 as usize]);
        let p = reach.centre(root);
        let near = grid.nearest(p, segment).or_else(|| nearest_by_scan(p, edges.len(), segment));
        let Some((k, t)) = near else { continue };
        let (a, b) = edges[k];
        let split: [f64; 3] =
            std::array::from_fn(|d| pos[a as usize][d] + t * (pos[b as usize][d] - pos[a as usize][d]));
        // The parent's radius there, from its nodes' (a vessel's end cap or a flat
        // cross-section leaves the transform at the split smaller).
        let radius = |i: u32| radii.get(i as usize).copied().unwrap_or_else(|| field.radius_at(pos[i as usize]));
        let parent = radius(a) + t * (radius(b) - radius(a));
        if dist(&split, &reach.centre(path[end])) < BUMP_RADII * parent {
            continue;
        }
        let length = dist(&pos[a as usize], &pos[b as usize]);
        let (split_here, start) = if t * length < c {
            (false, a)
        } else if (1.0 - t) * length < c {
            (false, b)
        } else {
            let j = pos.len() as u32;
            pos.push(split);
            // Edge `k`'s new end lies inside its old box, whose cells it stays filed under.
            edges[k] = (a, j);
            edges.push((b.min(j), b.max(j)));
            grid.insert(edges.len() - 1, pos[b as usize], split);
            (true, j)
        };
        // Nodes every NODE_STEP cells from the root to the end.
        let new = pos.len() as u32;
        let mut prev = start;
        let mut run = 0.0;
        let along: Vec<usize> = path[end..].iter().rev().copied().collect();
        for (n, w) in along.windows(2).enumerate() {
            run += dist(&reach.centre(w[0]), &reach.centre(w[1]));
            if run >= NODE_STEP * c || n + 2 == along.len() {
                let j = pos.len() as u32;
                pos.push(reach.centre(w[1]));
                edges.push((prev.min(j), prev.max(j)));
                grid.insert(edges.len() - 1, pos[prev as usize], pos[j as usize]);
                prev = j;
                run = 0.0;
            }
        }
        claimed.extend(path.iter().copied());
        let nodes = new..pos.len() as u32;
        sprouts.push(Grown { round, tip: field.voxel(tip), start, split: split_here, nodes });
    }
    edges.sort_unstable();
    edges.dedup();
    Ok((Csr::from_sorted_edges(pos.len(), &edges), pos, sprouts))
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    /// A one-voxel bar along axis 2 (k = 0..30) with a side branch along axis 1 at
    /// k = 15 (j = 1..=1 + `side`); the graph follows the bar only.
    fn t_bar(side: usize) -> (Array3<u8>, Csr, Vec<[f64; 3]>) {
        let mut mask = Array3::<u8>::zeros((3, 24, 30));
        for k in 0..30 {
            mask[[1, 1, k]] = 1;
        }
        for t in 0..=side {
            mask[[1, 1 + t, 15]] = 1;
        }
        let g = Csr::from_sorted_edges(3, &[(0, 1), (1, 2)]);
        (mask, g, vec![[1.0, 1.0, 0.0], [1.0, 1.0, 10.0], [1.0, 1.0, 29.0]])
    }

    /// Distances are the geodesic ones, step costs rounded to 1/16 cell: on a random
    /// anisotropic mask, adding a second graph's edges to the sources gives what a search
    /// from both graphs at once gives, and every reached voxel's distance is its
    /// predecessor's plus one step (a shortest-path tree).
    #[test]
    fn extending_the_sources_equals_searching_from_all_of_them() {
        let mut rnd = crate::test_rng(3);
        let mask = Array3::from_shape_fn((9, 10, 12), |_| u8::from(rnd(100) < 60));
        let spacing = [1.0, 1.5, 2.0];
        let field = Field::new(mask.view(), spacing).unwrap();
        let (a, b) = (Csr::from_sorted_edges(2, &[(0, 1)]), Csr::from_sorted_edges(2, &[(0, 1)]));
        let (pa, pb) = (vec![[0.0, 0.0, 0.0], [8.0, 13.5, 22.0]], vec![[8.0, 0.0, 0.0], [0.0, 13.5, 0.0]]);
        let both = Csr::from_sorted_edges(4, &[(0, 1), (2, 3)]);
        let pboth: Vec<[f64; 3]> = pa.iter().chain(&pb).copied().collect();
        let mut step = Reach::of(&a, &pa, &field, spacing).unwrap();
        step.extend(&b, &pb);
        let once = Reach::of(&both, &pboth, &field, spacing).unwrap();
        assert_eq!(step.dist, once.dist);
        let reached = (0..field.count()).filter(|&i| once.dist[i] != NONE).count();
        assert!(reached > field.count() / 2, "{reached} of {}", field.count());
        for i in 0..field.count() {
            let (d, f) = (once.dist[i], once.from[i] as usize);
            if d == NONE || d == 0 {
                continue;
            }
            let (u, v) = (field.voxel(i), field.voxel(f));
            let o = (0..3).fold(0, |o, k| 3 * o + (u[k] + 1 - v[k]));
            assert_eq!(d, once.dist[f] + once.steps[o], "voxel {u:?} from {v:?}");
        }
    }

    #[test]
    fn a_lost_branch_grows_back_and_a_bump_does_not() {
        let (mask, g, p) = t_bar(20);
        let field = Field::new(mask.view(), [1.0; 3]).unwrap();
        let (out, q, grown) = sprout(Reach::of(&g, &p, &field, [1.0; 3]).unwrap(), &g, &p, &[1.0; 3]).unwrap();
        assert_eq!(&q[..3], &p[..]);
        // The bar's edge is split at the branch (node 3), and the sprout reaches the
        // branch's far end (1, 21, 15), one radius (one cell) short of its cap at most.
        assert_eq!(q[3], [1.0, 1.0, 15.0]);
        assert!(q.iter().any(|x| dist(x, &[1.0, 21.0, 15.0]) <= 1.0), "{q:?}");
        assert_eq!(out.edges(), q.len() - 1);
        assert_eq!(out.neighbours(3).len(), 3);
        // One sprout, from the split node 3, its nodes the rest, its tip the branch's cap.
        let [one] = &grown[..] else { panic!("{grown:?}") };
        assert_eq!((one.round, one.start, one.split, one.nodes.clone()), (0, 3, true, 4..q.len() as u32));
        assert_eq!(one.tip, [1, 21, 15]);
        // A side branch shorter than the gap leaves the graph as it was.
        let (mask, g, p) = t_bar(6);
        let field = Field::new(mask.view(), [1.0; 3]).unwrap();
        let (out, q, grown) = sprout(Reach::of(&g, &p, &field, [1.0; 3]).unwrap(), &g, &p, &[1.0; 3]).unwrap();
        assert_eq!((out, q, grown), (g, p, vec![]));
    }
}
