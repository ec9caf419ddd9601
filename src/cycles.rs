//! Short cycles of a fundamental cycle basis: the convergence measure of the
//! contraction (docs/method.md §2.6, paper §III-C) and the refinement that collapses
//! small polygons (docs/method.md §3, paper §III-G, eqs. 10–11).
//!
//! One cycle per edge outside a breadth-first spanning forest (roots: the lowest
//! node of each component; neighbours in CSR order), so there are as many as the
//! graph's cycle rank, as in a fundamental basis. But the cycle of a non-tree edge
//! `(u, v)` is the *shortest* cycle through it (a breadth-first search from `u` to
//! `v` that does not use the edge), not the tree path `u → lca → v`: in an elongated
//! shape the tree paths of two neighbours across a cross-section run back together
//! toward the root, so every cross-section cycle of a long tube is as long as the
//! tube, falls outside the short-cycle window, and the measure stops the contraction
//! of a thick tube after a few iterations (a 1500-voxel tube of radius 8 stopped at
//! 37 202 nodes). The search stops at `max_nodes - 2` edges or [`BALL_LIMIT`] visited
//! nodes, so each edge costs a bounded local search and long cycles are never built.
//! This hot path is written here rather than taken from petgraph/rustworkx, whose
//! cycle bases materialise every cycle.

use crate::grid::{Csr, PerThread};
use rayon::prelude::*;
use std::collections::VecDeque;

/// A breadth-first spanning forest.
struct Forest {
    parent: Vec<u32>,
}

fn forest(g: &Csr) -> Forest {
    let n = g.nodes();
    let mut parent = vec![u32::MAX; n];
    let mut queue = VecDeque::new();
    for root in 0..n {
        if parent[root] != u32::MAX {
            continue;
        }
        parent[root] = root as u32;
        queue.push_back(root);
        while let Some(a) = queue.pop_front() {
            // A run asked to stop ([`crate::cancel`]) gets a partial forest, which it discards.
            if a % 65536 == 0 && crate::cancel::requested() {
                return Forest { parent };
            }
            for &b in g.neighbours(a) {
                if parent[b as usize] == u32::MAX {
                    parent[b as usize] = a as u32;
                    queue.push_back(b as usize);
                }
            }
        }
    }
    Forest { parent }
}

/// A cycle of the fundamental basis: its nodes in order around it, and its
/// vector area `0.5 |sum_(a,b) a × b|` (eq. 10), in physical units squared.
#[derive(Debug, Clone, PartialEq)]
pub struct Cycle {
    pub nodes: Vec<u32>,
    pub area: f64,
}

/// Vector area of a closed polygon, taken about its first vertex (the sum is
/// origin-independent for a closed polygon; this keeps it well conditioned).
pub fn vector_area(nodes: &[u32], positions: &[[f64; 3]]) -> f64 {
    let o = positions[nodes[0] as usize];
    let rel = |i: u32| {
        let p = positions[i as usize];
        [p[0] - o[0], p[1] - o[1], p[2] - o[2]]
    };
    let mut s = [0.0; 3];
    for w in 0..nodes.len() {
        let a = rel(nodes[w]);
        let b = rel(nodes[(w + 1) % nodes.len()]);
        s[0] += a[1] * b[2] - a[2] * b[1];
        s[1] += a[2] * b[0] - a[0] * b[2];
        s[2] += a[0] * b[1] - a[1] * b[0];
    }
    0.5 * (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt()
}

/// Nodes a cycle search may visit before it gives up on an edge.
pub const BALL_LIMIT: usize = 4096;

/// Scratch of the breadth-first cycle searches of one worker, reused from search to
/// search so that a search allocates nothing: a visit stamp and a parent per node
/// (dense, so a visit is one store and no hashing), the frontiers and the path.
struct Search {
    stamp: Vec<u32>,
    parent: Vec<u32>,
    now: u32,
    frontier: Vec<u32>,
    next: Vec<u32>,
    path: Vec<u32>,
}

impl Search {
    fn new() -> Search {
        Search { stamp: vec![], parent: vec![], now: 0, frontier: vec![], next: vec![], path: vec![] }
    }

    /// The search's answer when it is a triangle or a square, found without the
    /// search: the breadth-first search from `u` reaches `v` first through the first
    /// neighbour `a` of `u` (in CSR order) adjacent to `v` (a triangle), or else
    /// through the first node `b` adjacent to `v` in its second level, which it visits
    /// in the order "every `a` in CSR order, then `a`'s neighbours in CSR order"
    /// (a square `v, b, a, u`). Cycles are the dominant case (unit squares of the
    /// voxel grid, triangles after contraction), so most searches end here. Applies
    /// only where the search would reach that level within [`BALL_LIMIT`].
    fn triangle_or_square(&mut self, g: &Csr, u: u32, v: u32, max_nodes: usize) -> bool {
        let (nu, nv) = (g.neighbours(u as usize), g.neighbours(v as usize));
        if max_nodes < 4 || nu.len() > BALL_LIMIT {
            return false;
        }
        let adjacent_to_v = |x: u32| nv.binary_search(&x).is_ok();
        let found = |path: &mut Vec<u32>, nodes: &[u32]| {
            path.clear();
            path.extend_from_slice(nodes);
            true
        };
        if let Some(&a) = nu.iter().find(|&&a| a != v && adjacent_to_v(a)) {
            return found(&mut self.path, &[v, a, u]);
        }
        // The search's second level stays within the ball limit if this bound does.
        let ball = nu.len() + nu.iter().map(|&a| g.neighbours(a as usize).len()).sum::<usize>();
        if max_nodes < 5 || ball > BALL_LIMIT {
            return false;
        }
        for &a in nu.iter().filter(|&&a| a != v) {
            if let Some(&b) = g.neighbours(a as usize).iter().find(|&&b| b != u && adjacent_to_v(b)) {
                return found(&mut self.path, &[v, b, a, u]);
            }
        }
        false
    }

    /// The shortest cycle through the edge `u`–`v` with fewer than `max_nodes` nodes,
    /// left in `self.path` as `v → … → u` (the edge closes it); `false` if none.
    fn shortest_cycle_through(&mut self, g: &Csr, u: u32, v: u32, max_nodes: usize) -> bool {
        self.triangle_or_square(g, u, v, max_nodes) || self.breadth_first(g, u, v, max_nodes)
    }

    /// [`Search::shortest_cycle_through`] by the bounded breadth-first search itself.
    fn breadth_first(&mut self, g: &Csr, u: u32, v: u32, max_nodes: usize) -> bool {
        if self.stamp.len() != g.nodes() {
            // Plain allocations, not the parallel `filled`: this runs inside
            // `PerThread::with`, where a rayon call would let this thread steal
            // another search of the same pass.
            (self.stamp, self.parent, self.now) = (vec![0; g.nodes()], vec![0; g.nodes()], 0);
        }
        self.now = self.now.wrapping_add(1);
        if self.now == 0 {
            self.stamp.fill(0);
            self.now = 1;
        }
        let now = self.now;
        self.stamp[u as usize] = now;
        let mut visited = 1;
        self.frontier.clear();
        self.frontier.push(u);
        for _ in 0..max_nodes.saturating_sub(2) {
            self.next.clear();
            for &a in &self.frontier {
                for &b in g.neighbours(a as usize) {
                    if (a == u && b == v) || self.stamp[b as usize] == now {
                        continue;
                    }
                    self.stamp[b as usize] = now;
                    self.parent[b as usize] = a;
                    visited += 1;
                    if b == v {
                        self.path.clear();
                        self.path.push(v);
                        let mut x = v;
                        while x != u {
                            x = self.parent[x as usize];
                            self.path.push(x);
                        }
                        return true;
                    }
                    self.next.push(b);
                }
            }
            if visited > BALL_LIMIT || self.next.is_empty() {
                return false;
            }
            std::mem::swap(&mut self.frontier, &mut self.next);
        }
        false
    }
}

/// Nodes per parallel task of the cycle searches (fixed, like every split here).
const SEARCH_ROWS: usize = 1024;

/// `step(acc, nodes)` on the shortest cycle through every edge `(u, v)`, `u < v`,
/// outside the breadth-first forest, if that cycle has fewer than `max_nodes` nodes,
/// in order of the edges, folded into one accumulator per fixed block of
/// [`SEARCH_ROWS`] nodes `u`; the accumulators in block order. The closing edges are
/// found as each block is searched, never listed: a list of them and of one result
/// per edge was the run's peak memory on thin-vessel volumes (the first measure of
/// the coarse start graph). One scratch per worker thread.
fn fold_short_cycles<A: Send>(
    g: &Csr,
    max_nodes: usize,
    init: impl Fn() -> A + Sync,
    step: impl Fn(&mut A, &[u32]) + Sync,
) -> Vec<A> {
    let parent = forest(g).parent;
    let scratch = PerThread::new(Search::new);
    let blocks = g.nodes().div_ceil(SEARCH_ROWS);
    (0..blocks)
        .into_par_iter()
        .map(|b| {
            scratch.with(|s| {
                let mut acc = init();
                // A run asked to stop gets a partial result, which it discards.
                if crate::cancel::requested() {
                    return acc;
                }
                for u in b * SEARCH_ROWS..((b + 1) * SEARCH_ROWS).min(g.nodes()) {
                    for &v in g.neighbours(u) {
                        let tree = parent[v as usize] == u as u32 || parent[u] == v;
                        if v as usize > u && !tree && s.shortest_cycle_through(g, u as u32, v, max_nodes) {
                            step(&mut acc, &s.path);
                        }
                    }
                }
                acc
            })
        })
        .collect()
}

/// For every edge `(u, v)`, `u < v`, outside the breadth-first forest, the shortest
/// cycle through it if that has fewer than `max_nodes` nodes; in order of the edges.
pub fn short_cycles(g: &Csr, positions: &[[f64; 3]], max_nodes: usize) -> Vec<Cycle> {
    let parts = fold_short_cycles(g, max_nodes, Vec::new, |out: &mut Vec<Cycle>, nodes| {
        out.push(Cycle { nodes: nodes.to_vec(), area: vector_area(nodes, positions) })
    });
    parts.into_iter().flatten().collect()
}

/// `A_t`: the summed area of the short fundamental cycles (summed in edge order
/// within each block of [`SEARCH_ROWS`] nodes, then the blocks' sums in order).
pub fn short_cycle_area(g: &Csr, positions: &[[f64; 3]], max_nodes: usize) -> f64 {
    let parts = fold_short_cycles(g, max_nodes, || 0.0, |acc: &mut f64, nodes| *acc += vector_area(nodes, positions));
    parts.iter().sum()
}

/// How a refinement move closes a kept cycle.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Move {
    /// Every node of a kept cycle steps halfway to the centroid of one kept cycle
    /// through it — the one with the fewest nodes, then the smallest area, then the
    /// first closing edge (eq. 11; the single run's refinement).
    Centroid,
    /// Every kept cycle's shortest edge is contracted, both ends moved to the edge's
    /// midpoint (edges taken shortest first, each node in at most one; a chunked run's
    /// merge). A thin cycle of two copies of one vessel closes where the copies lie
    /// closest, and its far end (a junction) stays where it is.
    ShortestEdge,
}

/// One refinement move on the kept cycles (area below `max_area`, and not a
/// `loop_of_the_mask`), closed as `how` says. Returns the new positions and which
/// nodes moved, or `None` if no cycle is kept.
pub fn refine_step(
    g: &Csr,
    positions: &[[f64; 3]],
    max_nodes: usize,
    max_area: f64,
    loop_of_the_mask: &(dyn Fn(&Cycle) -> bool + Sync),
    how: Move,
) -> Option<(Vec<[f64; 3]>, Vec<bool>, usize)> {
    let kept: Vec<Cycle> = short_cycles(g, positions, max_nodes)
        .into_iter()
        .filter(|c| c.area < max_area && !loop_of_the_mask(c))
        .collect();
    if kept.is_empty() {
        return None;
    }
    let (new, moved) = match how {
        Move::Centroid => centroid_move(&kept, positions),
        Move::ShortestEdge => shortest_edge_move(&kept, positions),
    };
    Some((new, moved, kept.len()))
}

/// [`Move::Centroid`] of the `kept` cycles: new positions, and which nodes moved.
fn centroid_move(kept: &[Cycle], positions: &[[f64; 3]]) -> (Vec<[f64; 3]>, Vec<bool>) {
    let mut choice: Vec<Option<usize>> = vec![None; positions.len()];
    let rank = |k: usize| (kept[k].nodes.len(), kept[k].area, k);
    for (k, c) in kept.iter().enumerate() {
        for &i in &c.nodes {
            let slot = &mut choice[i as usize];
            if slot.is_none_or(|old| rank(k).partial_cmp(&rank(old)) == Some(std::cmp::Ordering::Less)) {
                *slot = Some(k);
            }
        }
    }
    let centroids: Vec<[f64; 3]> = kept
        .iter()
        .map(|c| {
            let mut s = [0.0; 3];
            for &i in &c.nodes {
                for d in 0..3 {
                    s[d] += positions[i as usize][d];
                }
            }
            s.map(|x| x / c.nodes.len() as f64)
        })
        .collect();
    let moved: Vec<bool> = choice.iter().map(Option::is_some).collect();
    let new = positions
        .iter()
        .zip(&choice)
        .map(|(p, ch)| match ch {
            Some(k) => std::array::from_fn(|d| 0.5 * (p[d] + centroids[*k][d])),
            None => *p,
        })
        .collect();
    (new, moved)
}

/// [`Move::ShortestEdge`] of the `kept` cycles: new positions, and which nodes moved.
fn shortest_edge_move(kept: &[Cycle], positions: &[[f64; 3]]) -> (Vec<[f64; 3]>, Vec<bool>) {
    let length = |a: u32, b: u32| {
        let (p, q) = (positions[a as usize], positions[b as usize]);
        ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
    };
    let mut shortest: Vec<(f64, u32, u32)> = kept
        .iter()
        .filter_map(|c| {
            let n = c.nodes.len();
            (0..n)
                .map(|k| {
                    let (a, b) = (c.nodes[k], c.nodes[(k + 1) % n]);
                    (length(a, b), a.min(b), a.max(b))
                })
                .min_by(|x, y| x.0.total_cmp(&y.0).then((x.1, x.2).cmp(&(y.1, y.2))))
        })
        .collect();
    shortest.sort_by(|x, y| x.0.total_cmp(&y.0).then((x.1, x.2).cmp(&(y.1, y.2))));
    let mut new = positions.to_vec();
    let mut moved = vec![false; positions.len()];
    for (_, a, b) in shortest {
        let (a, b) = (a as usize, b as usize);
        if moved[a] || moved[b] {
            continue;
        }
        let mid: [f64; 3] = std::array::from_fn(|d| 0.5 * (positions[a][d] + positions[b][d]));
        new[a] = mid;
        new[b] = mid;
        moved[a] = true;
        moved[b] = true;
    }
    (new, moved)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ring(n: u32, radius: f64) -> (Csr, Vec<[f64; 3]>) {
        let mut e: Vec<_> = (0..n - 1).map(|i| (i, i + 1)).collect();
        e.push((0, n - 1));
        e.sort_unstable();
        let p = (0..n)
            .map(|i| {
                let t = i as f64 / n as f64 * std::f64::consts::TAU;
                [radius * t.cos(), radius * t.sin(), 0.0]
            })
            .collect();
        (Csr::from_sorted_edges(n as usize, &e), p)
    }

    #[test]
    fn a_thin_cycle_closes_at_its_shortest_edge_and_its_far_end_stays() {
        // Two copies of one vessel from a junction J (node 0) that meet 10 cells further
        // along: a triangle J, X, Y with X and Y 0.8 apart.
        let g = Csr::from_sorted_edges(3, &[(0, 1), (0, 2), (1, 2)]);
        let p = vec![[0.0, 10.0, 0.0], [0.4, 0.0, 0.0], [-0.4, 0.0, 0.0]];
        let none = |_: &Cycle| false;
        let (q, moved, kept) = refine_step(&g, &p, 10, 10.0, &none, Move::ShortestEdge).unwrap();
        assert_eq!(kept, 1);
        assert_eq!(moved, vec![false, true, true]);
        assert_eq!(q, vec![p[0], [0.0; 3], [0.0; 3]]);
        // The centroid move takes J a third of the way down the copies.
        let (r, _, _) = refine_step(&g, &p, 10, 10.0, &none, Move::Centroid).unwrap();
        assert!((r[0][1] - 20.0 / 3.0).abs() < 1e-12);
        // A cycle at or above the area bound, or a loop of the mask, is left alone.
        assert!(refine_step(&g, &p, 10, 4.0, &none, Move::ShortestEdge).is_none());
        assert!(refine_step(&g, &p, 10, 10.0, &|_: &Cycle| true, Move::ShortestEdge).is_none());
        // Two cycles sharing their shortest edge's end: the shorter edge goes first,
        // and the node moves once.
        let g = Csr::from_sorted_edges(5, &[(0, 1), (0, 2), (1, 2), (2, 3), (2, 4), (3, 4)]);
        let p = vec![[0.0, 10.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, -0.3, 0.0], [5.0, -5.0, 0.0]];
        let (q, moved, kept) = refine_step(&g, &p, 10, 100.0, &none, Move::ShortestEdge).unwrap();
        assert_eq!(kept, 2);
        assert_eq!(moved, vec![false, false, true, true, false]);
        assert_eq!(q[2], [0.0, -0.15, 0.0]);
        assert_eq!(q[1], p[1]);
    }

    #[test]
    fn square_area_and_length_cut() {
        let (g, p) = ring(4, 1.0);
        let c = short_cycles(&g, &p, 10);
        assert_eq!(c.len(), 1);
        assert_eq!(c[0].nodes.len(), 4);
        assert!((c[0].area - 2.0).abs() < 1e-12); // square inscribed in the unit circle
                                                  // A 12-gon is too long for max_nodes = 10, and counted with 13.
        let (g, p) = ring(12, 5.0);
        assert!(short_cycles(&g, &p, 10).is_empty());
        let a = short_cycle_area(&g, &p, 13);
        assert!((a - 0.5 * 12.0 * 25.0 * (std::f64::consts::TAU / 12.0).sin()).abs() < 1e-9);
    }

    #[test]
    fn every_cross_section_square_of_a_block_is_found() {
        // A 6-connected 10 x 12 x 14 block: one unit square per closing edge, many
        // searches per worker (the reused visit stamps must not leak between them),
        // over more than one block of searched nodes.
        let mask = ndarray::Array3::<u8>::ones((10, 12, 14));
        assert!(mask.len() > SEARCH_ROWS);
        let e = crate::volume::edt_squared(mask.view(), [1.0; 3]).unwrap();
        let g = crate::grid::build(mask.view(), &e, [1.0; 3], &crate::params::Params::default()).unwrap();
        let c = short_cycles(&g.graph, &g.positions, 10);
        assert_eq!(c.len(), g.graph.edges() - g.graph.nodes() + 1);
        assert!(c.iter().all(|c| c.nodes.len() == 4 && (c.area - 1.0).abs() < 1e-12));
        let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
        assert_eq!(pool.install(|| short_cycles(&g.graph, &g.positions, 10)), c);
        let area = short_cycle_area(&g.graph, &g.positions, 10);
        assert_eq!(area, c.len() as f64);
        assert_eq!(pool.install(|| short_cycle_area(&g.graph, &g.positions, 10)).to_bits(), area.to_bits());
    }

    #[test]
    fn triangles_and_squares_are_the_ones_the_search_finds() {
        // Random graphs dense in short cycles; every edge's cycle, by the fast path
        // and by the breadth-first search alone, is the same node sequence.
        let mut rnd = crate::test_rng(3);
        for (n, per_node) in [(12usize, 3usize), (60, 2), (400, 3), (2000, 1)] {
            let (g, edges) = crate::test_graph(
                n,
                (0..per_node * n).map(|_| {
                    let a = rnd(n as u64);
                    (a as u32, ((a + 1 + rnd(6)) % n as u64) as u32)
                }),
            );
            let (mut fast, mut slow) = (Search::new(), Search::new());
            let mut short = 0;
            for &(u, v) in &edges {
                for max_nodes in [3, 4, 5, 10] {
                    let found = fast.shortest_cycle_through(&g, u, v, max_nodes);
                    assert_eq!(found, slow.breadth_first(&g, u, v, max_nodes), "{u}-{v} {max_nodes}");
                    if found {
                        assert_eq!(fast.path, slow.path);
                        short += usize::from(fast.path.len() <= 4);
                    }
                }
            }
            assert!(short > 0);
        }
    }

    #[test]
    fn area_is_translation_invariant() {
        let (g, p) = ring(6, 2.0);
        let q: Vec<_> = p.iter().map(|x| [x[0] + 1e6, x[1] - 3e5, x[2] + 7.0]).collect();
        let (a, b) = (short_cycle_area(&g, &p, 10), short_cycle_area(&g, &q, 10));
        assert!((a - b).abs() < 1e-6 * a);
    }

    #[test]
    fn refinement_moves_small_cycles_only() {
        // Triangle 0-1-2 plus a tail 2-3.
        let g = Csr::from_sorted_edges(4, &[(0, 1), (0, 2), (1, 2), (2, 3)]);
        let p = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 5.0, 0.0]];
        let (q, moved, kept) = refine_step(&g, &p, 10, 50.0, &|_| false, Move::Centroid).unwrap();
        assert_eq!(kept, 1);
        assert_eq!(moved, vec![true, true, true, false]);
        let third = 1.0 / 3.0;
        assert!((q[1][0] - 0.5 * (1.0 + third)).abs() < 1e-12);
        assert_eq!(q[3], p[3]);
        assert!(refine_step(&g, &p, 10, 0.1, &|_| false, Move::Centroid).is_none());
    }
}
