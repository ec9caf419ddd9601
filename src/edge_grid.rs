//! Nearest-edge search near known points: a grid of the edges' bounding boxes, kept
//! only around the points searched from (used where sprouts start on a graph:
//! [`crate::sprouts`], [`crate::blocks_sprouts`]).

use crate::vec3::projection;
use rustc_hash::FxHashMap;

/// Edges (indices into an edge list) by the cells of side `side` their bounding boxes
/// touch, kept only for the cells a search may read (those around the points that will
/// be searched from), so that the grid grows with the searches, not with the graph.
pub struct EdgeGrid {
    side: f64,
    cells: FxHashMap<[i64; 3], Vec<u32>>,
}

impl EdgeGrid {
    /// An empty grid over the cells within `side` of the `starts`.
    pub fn around(starts: impl Iterator<Item = [f64; 3]>, side: f64) -> EdgeGrid {
        let mut grid = EdgeGrid { side, cells: FxHashMap::default() };
        for p in starts {
            for key in grid.near(p) {
                grid.cells.entry(key).or_default();
            }
        }
        grid
    }

    fn cell(&self, p: [f64; 3]) -> [i64; 3] {
        p.map(|x| (x / self.side).floor() as i64)
    }

    /// The lowest and highest cell of the box from `a` to `b` (any two corners).
    fn bounds(&self, a: [f64; 3], b: [f64; 3]) -> ([i64; 3], [i64; 3]) {
        (self.cell(std::array::from_fn(|d| a[d].min(b[d]))), self.cell(std::array::from_fn(|d| a[d].max(b[d]))))
    }

    /// The cells of the box from `a` to `b` (any two corners).
    fn boxed(&self, a: [f64; 3], b: [f64; 3]) -> impl Iterator<Item = [i64; 3]> {
        let (lo, hi) = self.bounds(a, b);
        (lo[0]..=hi[0]).flat_map(move |i| (lo[1]..=hi[1]).flat_map(move |j| (lo[2]..=hi[2]).map(move |l| [i, j, l])))
    }

    /// The cells within `side` of `p` (a search's cells).
    fn near(&self, p: [f64; 3]) -> impl Iterator<Item = [i64; 3]> {
        self.boxed(p.map(|x| x - self.side), p.map(|x| x + self.side))
    }

    /// Files edge `k` (`a`–`b`) under every kept cell its bounding box touches: the
    /// box's cells when they are fewer than the kept ones, else the kept cells inside
    /// the box (so a long edge costs no more than the kept cells).
    pub fn insert(&mut self, k: usize, a: [f64; 3], b: [f64; 3]) {
        let (lo, hi) = self.bounds(a, b);
        let span = (0..3).map(|d| (hi[d] as i128 - lo[d] as i128 + 1) as f64).product::<f64>();
        if span <= self.cells.len() as f64 {
            for key in self.boxed(a, b) {
                if let Some(v) = self.cells.get_mut(&key) {
                    v.push(k as u32);
                }
            }
        } else {
            for (key, v) in self.cells.iter_mut() {
                if (0..3).all(|d| lo[d] <= key[d] && key[d] <= hi[d]) {
                    v.push(k as u32);
                }
            }
        }
    }

    /// The edge nearest `p` within `side` (ties to the lower index), with the parameter
    /// of `p`'s projection on it; `segment(k)` gives edge `k`'s two ends. Exact: every
    /// edge within `side` of `p` is filed under one of the cells searched.
    pub fn nearest(&self, p: [f64; 3], segment: impl Fn(usize) -> ([f64; 3], [f64; 3])) -> Option<(usize, f64)> {
        let mut best: Option<(f64, usize, f64)> = None;
        for key in self.near(p) {
            for &k in self.cells.get(&key).map_or(&[][..], |v| v) {
                let k = k as usize;
                let (a, b) = segment(k);
                let (t, d) = projection(p, a, b);
                if d <= self.side && best.is_none_or(|(bd, bk, _)| (d, k) < (bd, bk)) {
                    best = Some((d, k, t));
                }
            }
        }
        best.map(|(_, k, t)| (k, t))
    }
}

/// The edge nearest `p` among edges `0..n` by a scan of every one (ties to the lower
/// index, as [`EdgeGrid::nearest`]), with the parameter of `p`'s projection on it;
/// `segment(k)` gives edge `k`'s two ends. For a point farther than a grid's side from
/// every edge.
pub fn nearest_by_scan(p: [f64; 3], n: usize, segment: impl Fn(usize) -> ([f64; 3], [f64; 3])) -> Option<(usize, f64)> {
    nearest_with_distance(p, n, segment).map(|(_, k, t)| (k, t))
}

/// [`nearest_by_scan`] with the distance first: `(d, k, t)`.
fn nearest_with_distance(
    p: [f64; 3],
    n: usize,
    segment: impl Fn(usize) -> ([f64; 3], [f64; 3]),
) -> Option<(f64, usize, f64)> {
    (0..n)
        .map(|k| {
            let (a, b) = segment(k);
            let (t, d) = projection(p, a, b);
            (d, k, t)
        })
        .min_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small deterministic generator (xorshift), values in [0, 1).
    fn uniform(state: &mut u64) -> f64 {
        *state ^= *state << 13;
        *state ^= *state >> 7;
        *state ^= *state << 17;
        (*state >> 11) as f64 / (1u64 << 53) as f64
    }

    /// On random short and long edges (some sharing ends, some repeated, so that ties
    /// occur), the grid's answer is the scan's whenever the scan's nearest edge lies
    /// within the search side, and none otherwise.
    #[test]
    fn the_grid_finds_what_a_scan_of_every_edge_finds() {
        let mut s = 0x9E37_79B9_7F4A_7C15u64;
        let points: Vec<[f64; 3]> =
            (0..400).map(|_| std::array::from_fn(|_| (uniform(&mut s) * 30.0).round() / 2.0)).collect();
        let mut edges: Vec<[usize; 2]> = (0..600)
            .map(|_| {
                let a = (uniform(&mut s) * 400.0) as usize;
                let b = (uniform(&mut s) * 400.0) as usize;
                [a, b]
            })
            .collect();
        edges.extend_from_within(..50);
        let queries: Vec<[f64; 3]> = (0..300).map(|_| std::array::from_fn(|_| uniform(&mut s) * 16.0 - 0.5)).collect();
        let side = 1.5;
        let mut grid = EdgeGrid::around(queries.iter().copied(), side);
        for (k, &[a, b]) in edges.iter().enumerate() {
            grid.insert(k, points[a], points[b]);
        }
        let (mut found, mut none) = (0, 0);
        for &q in &queries {
            let segment = |k: usize| (points[edges[k][0]], points[edges[k][1]]);
            let scan = nearest_with_distance(q, edges.len(), segment).unwrap();
            let got = grid.nearest(q, segment);
            if scan.0 <= side {
                assert_eq!(got, Some((scan.1, scan.2)), "query {q:?}");
                found += 1;
            } else {
                assert_eq!(got, None, "query {q:?}");
                none += 1;
            }
        }
        assert!(found > 100 && none > 0, "found {found}, none {none}");
    }
}
