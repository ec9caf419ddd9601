//! The contraction step: the least-squares solution of eq. 8,
//! `[alpha Ln; beta Lm; Wg] P' = [0; 0; Wg P]`, through its normal equations
//! `M P' = Wg² P` with `M = alpha² LnᵀLn + beta² LmᵀLm + Wg²` (symmetric positive
//! definite), by Jacobi-preconditioned conjugate gradients (METHOD.md §2.4).
//!
//! Choices:
//! - matrix-free: `M x` is applied as `Lᵀ(L x)` from the CSR weights, so `LᵀL`
//!   (two-hop sparsity, about 4× the entries) is never formed;
//! - the unknown is the displacement `D = P' - P`, so the right-hand side
//!   `-(alpha² LnᵀLn + beta² LmᵀLm) P` is translation-invariant and the relative
//!   tolerance means the same wherever the volume sits; starting from `D = 0` is the
//!   warm start at `P`;
//! - the three coordinates share every matrix pass, each with its own CG scalars;
//! - every reduction is summed over fixed chunks in a fixed order, so the result
//!   does not depend on the thread count.

use crate::grid::{for_row_blocks, Csr};
use crate::laplacian::Laplacian;
use crate::params::Params;
use rayon::prelude::*;

type V3 = [f64; 3];

/// Entries per parallel chunk of the vector reductions.
const CHUNK: usize = 8192;

/// The normal-equations operator of eq. 8.
pub struct NormalOperator<'a> {
    pub graph: &'a Csr,
    pub ln: &'a Laplacian,
    pub lm: &'a Laplacian,
    /// `alpha²`, `beta²`.
    pub a2: f64,
    pub b2: f64,
    /// `Wg_i²` per node.
    pub anchor2: Vec<f64>,
}

impl<'a> NormalOperator<'a> {
    /// The operator of one contraction iteration: `alpha`, `beta` from `params`, and
    /// anchoring `gamma` (`eps_gamma * gamma` for skeleton-like nodes).
    pub fn new(graph: &'a Csr, ln: &'a Laplacian, lm: &'a Laplacian, skeletal: &[bool], params: &Params) -> Self {
        let anchor2 = crate::laplacian::anchors(skeletal, params).into_iter().map(|w| w * w).collect();
        NormalOperator { graph, ln, lm, a2: params.alpha * params.alpha, b2: params.beta * params.beta, anchor2 }
    }
}

/// `(L x)_i` for one node.
fn apply_row(g: &Csr, w: &[f32], diag: &[f32], x: &[V3], i: usize) -> V3 {
    let d = diag[i] as f64;
    let mut y = [d * x[i][0], d * x[i][1], d * x[i][2]];
    let (lo, hi) = (g.offsets[i], g.offsets[i + 1]);
    for (e, &j) in (lo..hi).zip(&g.targets[lo..hi]) {
        let wij = w[e] as f64;
        let xj = &x[j as usize];
        y[0] += wij * xj[0];
        y[1] += wij * xj[1];
        y[2] += wij * xj[2];
    }
    y
}

impl NormalOperator<'_> {
    /// `L x` for both Laplacians.
    fn forward(&self, x: &[V3], un: &mut [V3], um: &mut [V3]) {
        let g = self.graph;
        un.par_iter_mut().zip(um.par_iter_mut()).enumerate().with_min_len(1024).for_each(|(i, (a, b))| {
            *a = apply_row(g, &self.ln.weight, &self.ln.diagonal, x, i);
            *b = apply_row(g, &self.lm.weight, &self.lm.diagonal, x, i);
        });
    }

    /// `y = M x`, using `un`, `um` as scratch.
    pub fn apply(&self, x: &[V3], y: &mut [V3], un: &mut [V3], um: &mut [V3]) {
        self.forward(x, un, um);
        let g = self.graph;
        let (un, um) = (&*un, &*um);
        y.par_iter_mut().enumerate().with_min_len(1024).for_each(|(j, yj)| {
            let a = apply_row(g, &self.ln.weight_t, &self.ln.diagonal, un, j);
            let b = apply_row(g, &self.lm.weight_t, &self.lm.diagonal, um, j);
            let w2 = self.anchor2[j];
            for c in 0..3 {
                yj[c] = self.a2 * a[c] + self.b2 * b[c] + w2 * x[j][c];
            }
        });
    }

    /// The diagonal of `M` (the Jacobi preconditioner).
    pub fn diagonal(&self) -> Vec<f64> {
        let g = self.graph;
        let mut sq = vec![0f64; g.nodes()];
        // diag(LᵀL)_j = sum_i L_ij² = L_jj² + sum over j's row of (W_ij)², read from
        // the transposed weights laid out in j's row.
        let mut col = vec![0f64; g.targets.len()];
        for_row_blocks(&g.offsets, &mut col, |rows, out| {
            let mut e = 0;
            for j in rows {
                for k in g.offsets[j]..g.offsets[j + 1] {
                    let (wn, wm) = (self.ln.weight_t[k] as f64, self.lm.weight_t[k] as f64);
                    out[e] = self.a2 * wn * wn + self.b2 * wm * wm;
                    e += 1;
                }
            }
        });
        sq.par_iter_mut().enumerate().for_each(|(j, s)| {
            let (dn, dm) = (self.ln.diagonal[j] as f64, self.lm.diagonal[j] as f64);
            *s = col[g.offsets[j]..g.offsets[j + 1]].iter().sum::<f64>()
                + self.a2 * dn * dn
                + self.b2 * dm * dm
                + self.anchor2[j];
        });
        sq
    }
}

/// Per-coordinate dot products `sum_i a_i[c] * b_i[c]`, reduced over fixed chunks.
fn dot3(a: &[V3], b: &[V3]) -> V3 {
    let parts: Vec<V3> = a
        .par_chunks(CHUNK)
        .zip(b.par_chunks(CHUNK))
        .map(|(x, y)| {
            let mut s = [0.0; 3];
            for (u, v) in x.iter().zip(y) {
                for c in 0..3 {
                    s[c] += u[c] * v[c];
                }
            }
            s
        })
        .collect();
    parts.iter().fold([0.0; 3], |acc, s| [acc[0] + s[0], acc[1] + s[1], acc[2] + s[2]])
}

/// Outcome of one solve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveStats {
    /// CG iterations until the last coordinate converged.
    pub iterations: usize,
    /// Whether every coordinate reached the tolerance within the cap.
    pub converged: bool,
}

/// New positions `P'` of eq. 8: `P + D` with `M D = -(alpha² LnᵀLn + beta² LmᵀLm) P`,
/// solved to `|r| <= tol |r_0|` per coordinate, at most `max_iterations` iterations.
pub fn contract(op: &NormalOperator<'_>, positions: &[V3], tol: f64, max_iterations: usize) -> (Vec<V3>, SolveStats) {
    let n = positions.len();
    let mut un = vec![[0.0; 3]; n];
    let mut um = vec![[0.0; 3]; n];
    // r0 = b - M·0 = -(a² LnᵀLn + b² LmᵀLm) P = -(M P - Wg² P).
    let mut r = vec![[0.0; 3]; n];
    op.apply(positions, &mut r, &mut un, &mut um);
    r.par_iter_mut().zip(positions.par_iter()).zip(op.anchor2.par_iter()).for_each(|((ri, p), w2)| {
        for c in 0..3 {
            ri[c] = -(ri[c] - w2 * p[c]);
        }
    });
    let inv_diag: Vec<f64> = op.diagonal().into_par_iter().map(|d| 1.0 / d).collect();
    let mut d = vec![[0.0; 3]; n];
    let precondition = |r: &[V3], z: &mut [V3]| {
        z.par_iter_mut().zip(r.par_iter()).zip(inv_diag.par_iter()).for_each(|((zi, ri), m)| {
            *zi = [ri[0] * m, ri[1] * m, ri[2] * m];
        })
    };
    let mut z = vec![[0.0; 3]; n];
    precondition(&r, &mut z);
    let mut search = z.clone();
    let mut rz = dot3(&r, &z);
    let r0 = dot3(&r, &r).map(f64::sqrt);
    let mut active = r0.map(|x| x > 0.0);
    let mut q = vec![[0.0; 3]; n];
    let mut iterations = 0;
    while active.iter().any(|&a| a) && iterations < max_iterations {
        iterations += 1;
        op.apply(&search, &mut q, &mut un, &mut um);
        let pq = dot3(&search, &q);
        let step: V3 = std::array::from_fn(|c| if active[c] && pq[c] > 0.0 { rz[c] / pq[c] } else { 0.0 });
        d.par_iter_mut().zip(r.par_iter_mut()).zip(search.par_iter().zip(q.par_iter())).for_each(
            |((di, ri), (si, qi))| {
                for c in 0..3 {
                    di[c] += step[c] * si[c];
                    ri[c] -= step[c] * qi[c];
                }
            },
        );
        let rr = dot3(&r, &r);
        for c in 0..3 {
            if active[c] && (rr[c].sqrt() <= tol * r0[c] || pq[c] <= 0.0) {
                active[c] = false;
            }
        }
        precondition(&r, &mut z);
        let rz_new = dot3(&r, &z);
        let beta: V3 = std::array::from_fn(|c| if active[c] && rz[c] > 0.0 { rz_new[c] / rz[c] } else { 0.0 });
        rz = rz_new;
        search.par_iter_mut().zip(z.par_iter()).for_each(|(si, zi)| {
            for c in 0..3 {
                si[c] = zi[c] + beta[c] * si[c];
            }
        });
    }
    let converged = !active.iter().any(|&a| a);
    let out = positions.par_iter().zip(d.par_iter()).map(|(p, d)| [p[0] + d[0], p[1] + d[1], p[2] + d[2]]).collect();
    (out, SolveStats { iterations, converged })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::laplacian::{l2_norm, medial};
    use crate::params::MedialWeight;

    /// Dense least squares of eq. 8 by Gaussian elimination on the normal equations.
    fn dense(g: &Csr, ln: &Laplacian, lm: &Laplacian, a: f64, b: f64, w: &[f64], p: &[V3]) -> Vec<V3> {
        let n = g.nodes();
        let mat = |l: &Laplacian| {
            let mut m = vec![vec![0.0; n]; n];
            for i in 0..n {
                m[i][i] = l.diagonal[i] as f64;
                for e in g.offsets[i]..g.offsets[i + 1] {
                    m[i][g.targets[e] as usize] = l.weight[e] as f64;
                }
            }
            m
        };
        let (mn, mm) = (mat(ln), mat(lm));
        let mut m = vec![vec![0.0; n]; n];
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    m[i][j] += a * a * mn[k][i] * mn[k][j] + b * b * mm[k][i] * mm[k][j];
                }
            }
            m[i][i] += w[i] * w[i];
        }
        let mut out = vec![[0.0; 3]; n];
        for c in 0..3 {
            let mut aug: Vec<Vec<f64>> = (0..n)
                .map(|i| {
                    let mut row = m[i].clone();
                    row.push(w[i] * w[i] * p[i][c]);
                    row
                })
                .collect();
            for col in 0..n {
                let piv = (col..n).max_by(|&x, &y| aug[x][col].abs().total_cmp(&aug[y][col].abs())).unwrap();
                aug.swap(col, piv);
                for row in 0..n {
                    if row != col {
                        let f = aug[row][col] / aug[col][col];
                        for k in col..=n {
                            aug[row][k] -= f * aug[col][k];
                        }
                    }
                }
            }
            for i in 0..n {
                out[i][c] = aug[i][n] / aug[i][i];
            }
        }
        out
    }

    #[test]
    fn matches_dense_least_squares() {
        // A small irregular graph: a 3x3 grid patch plus a diagonal.
        let edges = vec![
            (0, 1),
            (0, 3),
            (1, 2),
            (1, 4),
            (2, 5),
            (3, 4),
            (3, 6),
            (4, 5),
            (4, 7),
            (4, 8),
            (5, 8),
            (6, 7),
            (7, 8),
        ];
        let g = Csr::from_sorted_edges(9, &edges);
        let p: Vec<V3> =
            (0..9).map(|i| [(i % 3) as f64 + 0.1 * i as f64, (i / 3) as f64, 0.3 * (i % 2) as f64 + 5.0]).collect();
        let r: Vec<f64> = (0..9).map(|i| 1.0 + (i % 4) as f64).collect();
        let tw = g.twins();
        let ln = l2_norm(&g, &tw, &p);
        let lm = medial(&g, &tw, &r, MedialWeight::Radius);
        let w: Vec<f64> = (0..9).map(|i| if i == 4 { 0.5 } else { 0.05 }).collect();
        let op = NormalOperator {
            graph: &g,
            ln: &ln,
            lm: &lm,
            a2: 0.25,
            b2: 0.25,
            anchor2: w.iter().map(|x| x * x).collect(),
        };
        let (fast, stats) = contract(&op, &p, 1e-12, 1000);
        assert!(stats.converged);
        let slow = dense(&g, &ln, &lm, 0.5, 0.5, &w, &p);
        for (a, b) in fast.iter().zip(&slow) {
            for c in 0..3 {
                assert!((a[c] - b[c]).abs() < 1e-8, "{a:?} vs {b:?}");
            }
        }
        // The flow moved the nodes: the solution is not the input.
        assert!(fast.iter().zip(&p).any(|(a, b)| (a[0] - b[0]).abs() > 1e-3));
    }
}
