//! l2-norm and medial Laplacians and adaptive anchoring (docs/method.md §2.1–2.3,
//! paper §III-B eqs. 2–4 and §III-D eq. 9), and the normal-equations operator of eq. 8
//! they make ([`NormalOperator`]), which the solver and its preconditioner read.
//!
//! A Laplacian `L = W - I` has row-normalised off-diagonal weights, one per CSR
//! entry, computed when read from one stored total per row, and a diagonal which is
//! `-1` for a row with weights and `0` for a row whose weight sum is 0: such a node
//! gets no pull from that term, rather than a pull toward the origin.

use crate::grid::Csr;
use crate::params::{MedialWeight, Params};
use crate::vec3::{norm, sub};
use rayon::prelude::*;

/// One Laplacian: `(L x)_i = diagonal(i) x_i + sum_j weight(i, j) x_j` over the
/// neighbours `j` of `i`. Its weights are not stored: each is computed when read,
/// `(a(i, j) / total_i) as f32`, from the affinity `a` and one stored row total per
/// node. That keeps 8 bytes a node instead of 4 bytes per CSR entry plus a diagonal
/// (about 28 on a 6-connected grid) while `M` is assembled, the run's peak, and gives
/// `W_ji` (the transpose) as cheaply as `W_ij`. The values are those a stored array
/// would hold, bit for bit.
#[derive(Debug, Clone)]
pub struct Laplacian<'a> {
    affinity: Affinity<'a>,
    /// `sum_k a(i, k)` over the neighbours of `i`, summed in neighbour order.
    total: Vec<f64>,
}

/// The unnormalised affinity `a(i, j) >= 0` of a Laplacian.
#[derive(Debug, Clone, Copy)]
enum Affinity<'a> {
    /// `|p_i - p_j|`.
    Distance(&'a [[f64; 3]]),
    /// `r_j`.
    Radius(&'a [f64]),
    /// `|r_i - r_j|`.
    Difference(&'a [f64]),
}

impl Affinity<'_> {
    #[inline(always)]
    fn at(self, i: usize, j: usize) -> f64 {
        match self {
            Affinity::Distance(p) => distance(&p[i], &p[j]),
            Affinity::Radius(r) => r[j],
            Affinity::Difference(r) => (r[i] - r[j]).abs(),
        }
    }
}

impl<'a> Laplacian<'a> {
    /// Row-normalised weights from an unnormalised affinity.
    fn new(g: &Csr, affinity: Affinity<'a>) -> Laplacian<'a> {
        let total = (0..g.nodes())
            .into_par_iter()
            .with_min_len(4096)
            .map(|i| g.neighbours(i).iter().map(|&j| affinity.at(i, j as usize)).sum())
            .collect();
        Laplacian { affinity, total }
    }

    /// `W_ij` for an edge `i — j`: 0 in a row whose affinities sum to 0 (or NaN).
    #[inline(always)]
    pub fn weight(&self, i: usize, j: usize) -> f32 {
        let total = self.total[i];
        if total > 0.0 {
            (self.affinity.at(i, j) / total) as f32
        } else {
            0.0
        }
    }

    /// `L_ii`: `-1`, or `0` for a row with no weight (a positive total has an affinity
    /// of at least `total / degree`, so some weight of its row is positive).
    #[inline(always)]
    pub fn diagonal(&self, i: usize) -> f32 {
        if self.total[i] > 0.0 {
            -1.0
        } else {
            0.0
        }
    }
}

fn distance(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    norm(sub(*a, *b))
}

/// l2-norm Laplacian: `W_ij = |p_i - p_j| / sum_k |p_i - p_k|` (eq. 2).
pub fn l2_norm<'a>(g: &Csr, positions: &'a [[f64; 3]]) -> Laplacian<'a> {
    Laplacian::new(g, Affinity::Distance(positions))
}

/// Medial Laplacian: `W_ij = r_j / sum_k r_k` (the authors' code, default) or
/// `|r_i - r_j| / sum_k |r_i - r_k|` (eq. 3).
pub fn medial<'a>(g: &Csr, radii: &'a [f64], kind: MedialWeight) -> Laplacian<'a> {
    match kind {
        MedialWeight::Radius => Laplacian::new(g, Affinity::Radius(radii)),
        MedialWeight::Difference => Laplacian::new(g, Affinity::Difference(radii)),
    }
}

/// Skeleton-like nodes (docs/method.md §2.3): degree > 1 and every neighbour direction
/// collinear with the direction to the first neighbour within `skeletal_angle`
/// degrees. Two further conditions make the test mean "a node of a curve":
/// neighbours lie on both sides (some pair is antiparallel, so a fan of neighbours
/// all on one side does not count), and no two neighbours are joined (a node of a
/// triangle is never a curve node). Without them, the three nodes of a flattened
/// triangle pass the paper's `|cos| >= cos(angle)` test, are anchored ten times
/// harder and kept out of decimation, and such triangles never go away: on
/// `damseh_synth2` a thousand of them stall the convergence measure above its
/// threshold for all 100 iterations. A coincident neighbour disqualifies.
///
/// With `anchor_ends`, a node of degree 1 (a vessel's free end) is skeleton-like
/// too: otherwise its single neighbour pulls it inward at every iteration, and on
/// synthetic trees the ends of the graph stop a median 3.6 voxels short of the
/// true ends instead of 1.9.
pub fn skeletal(g: &Csr, positions: &[[f64; 3]], params: &Params) -> Vec<bool> {
    let min_cos = params.skeletal_angle.to_radians().cos();
    (0..g.nodes())
        .into_par_iter()
        .map(|i| {
            let nb = g.neighbours(i);
            if nb.len() == 1 {
                return params.anchor_ends;
            }
            if nb.len() < 2 {
                return false;
            }
            let p = positions[i];
            let dir = |j: u32| {
                let q = positions[j as usize];
                let d = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
                let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                (n > 0.0).then(|| [d[0] / n, d[1] / n, d[2] / n])
            };
            let Some(first) = dir(nb[0]) else { return false };
            let mut both_sides = false;
            for &j in &nb[1..] {
                let Some(u) = dir(j) else { return false };
                let cos = u[0] * first[0] + u[1] * first[1] + u[2] * first[2];
                if cos.abs() < min_cos {
                    return false;
                }
                both_sides |= cos < 0.0;
            }
            both_sides && nb.iter().all(|&j| g.neighbours(j as usize).iter().all(|k| nb.binary_search(k).is_err()))
        })
        .collect()
}

/// Anchoring weights `Wg_i`: `[gamma, eps_gamma * gamma]`, for the other nodes and
/// for the skeleton-like ones.
pub fn anchors(params: &Params) -> [f64; 2] {
    [params.gamma, params.eps_gamma * params.gamma]
}

/// The normal-equations operator of eq. 8.
pub struct NormalOperator<'a> {
    pub graph: &'a Csr,
    pub ln: &'a Laplacian<'a>,
    pub lm: &'a Laplacian<'a>,
    /// `alpha²`, `beta²`.
    pub a2: f64,
    pub b2: f64,
    /// Which nodes are skeleton-like.
    pub skeletal: &'a [bool],
    /// `Wg²` of the other nodes and of the skeleton-like ones (two values, not one per
    /// node: 8 bytes a node less while `M` is assembled, the contraction's peak).
    pub anchor2: [f64; 2],
}

impl<'a> NormalOperator<'a> {
    /// The operator of one contraction iteration: `alpha`, `beta` from `params`, and
    /// anchoring `gamma` (`eps_gamma * gamma` for skeleton-like nodes).
    pub fn new(
        graph: &'a Csr,
        ln: &'a Laplacian<'a>,
        lm: &'a Laplacian<'a>,
        skeletal: &'a [bool],
        params: &Params,
    ) -> Self {
        let anchor2 = anchors(params).map(|w| w * w);
        NormalOperator {
            graph,
            ln,
            lm,
            a2: params.alpha * params.alpha,
            b2: params.beta * params.beta,
            skeletal,
            anchor2,
        }
    }

    /// `Wg_j²`.
    #[inline]
    pub fn anchor2(&self, j: usize) -> f64 {
        self.anchor2[usize::from(self.skeletal[j])]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn path(n: u32) -> Csr {
        let e: Vec<_> = (0..n - 1).map(|i| (i, i + 1)).collect();
        Csr::from_sorted_edges(n as usize, &e)
    }

    /// Row `i`'s weights, in neighbour order.
    fn row(l: &Laplacian<'_>, g: &Csr, i: usize) -> Vec<f32> {
        g.neighbours(i).iter().map(|&j| l.weight(i, j as usize)).collect()
    }

    #[test]
    fn l2_weights_are_row_normalised_and_transposed() {
        let g = path(3);
        let p = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [4.0, 0.0, 0.0]];
        let l = l2_norm(&g, &p);
        // Row 1: neighbours at distance 1 and 3.
        assert_eq!(row(&l, &g, 1), [0.25, 0.75]);
        assert_eq!(row(&l, &g, 0), [1.0]);
        // The transpose of entry 1 → 0 is W_01 = 1.
        assert_eq!(l.weight(0, 1), 1.0);
        assert_eq!(l.weight(1, 0), 0.25);
        assert!((0..3).all(|i| l.diagonal(i) == -1.0));
    }

    #[test]
    fn weights_are_what_a_stored_array_would_hold() {
        // A random graph with random positions: every weight is the affinity over its
        // row's sum, summed in neighbour order, rounded to f32 once.
        let mut rnd = crate::test_rng(11);
        let n = 500;
        let (g, _) = crate::test_graph(n, (0..4 * n).map(|_| (rnd(n as u64) as u32, rnd(n as u64) as u32)));
        let p: Vec<[f64; 3]> = (0..n).map(|_| [0, 1, 2].map(|_| rnd(1000) as f64 / 7.0)).collect();
        let l = l2_norm(&g, &p);
        for i in 0..n {
            let nb = g.neighbours(i);
            let total: f64 = nb.iter().map(|&j| distance(&p[i], &p[j as usize])).sum();
            for &j in nb {
                let want = if total > 0.0 { (distance(&p[i], &p[j as usize]) / total) as f32 } else { 0.0 };
                assert_eq!(l.weight(i, j as usize).to_bits(), want.to_bits());
            }
            let any = row(&l, &g, i).iter().any(|&w| w > 0.0);
            assert_eq!(l.diagonal(i), if any { -1.0 } else { 0.0 });
        }
    }

    #[test]
    fn zero_rows_get_no_pull() {
        let g = path(3);
        let r = [2.0, 2.0, 2.0];
        let l = medial(&g, &r, MedialWeight::Difference);
        assert!((0..3).all(|i| row(&l, &g, i).iter().all(|&w| w == 0.0) && l.diagonal(i) == 0.0));
        let l = medial(&g, &[1.0, 3.0, 1.0], MedialWeight::Radius);
        assert_eq!(row(&l, &g, 0), [1.0]);
        assert_eq!(row(&l, &g, 1), [0.5, 0.5]);
    }

    #[test]
    fn collinear_nodes_are_skeletal() {
        let g = path(3);
        let p = Params { anchor_ends: false, ..Params::default() };
        let straight = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.1, 0.0]];
        assert_eq!(skeletal(&g, &straight, &p), vec![false, true, false]);
        // With `anchor_ends` (the default) the path's two ends count too.
        assert_eq!(skeletal(&g, &straight, &Params::default()), vec![true, true, true]);
        let bent = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 1.0, 0.0]];
        assert_eq!(skeletal(&g, &bent, &p), vec![false, false, false]);
        // A flattened triangle: collinear, but no node of it is a curve node.
        let tri = Csr::from_sorted_edges(3, &[(0, 1), (0, 2), (1, 2)]);
        let flat = [[0.0, 0.0, 0.0], [1.0, 0.01, 0.0], [2.0, 0.0, 0.0]];
        assert_eq!(skeletal(&tri, &flat, &p), vec![false, false, false]);
        // A fan: both neighbours on the same side.
        let fan = Csr::from_sorted_edges(3, &[(0, 1), (0, 2)]);
        assert_eq!(skeletal(&fan, &flat, &p), vec![false, false, false]);
        assert_eq!(anchors(&p), [0.05, 0.5]);
    }
}
