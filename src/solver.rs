//! The contraction step: the least-squares solution of eq. 8,
//! `[alpha Ln; beta Lm; Wg] P' = [0; 0; Wg P]`, through its normal equations
//! `M P' = Wg² P` with `M = alpha² LnᵀLn + beta² LmᵀLm + Wg²` (symmetric positive
//! definite), by preconditioned conjugate gradients (docs/method.md §2.4).
//!
//! Choices:
//! - the unknown is the displacement `D = P' - P`, so the right-hand side
//!   `-(alpha² LnᵀLn + beta² LmᵀLm) P` is translation-invariant and the relative
//!   tolerance means the same wherever the volume sits; starting from `D = 0` is the
//!   warm start at `P`. The right-hand side is read off the assembled `M`
//!   ([`NormalMatrix::displacement_rhs`]), so the Laplacians are freed before the
//!   conjugate-gradient vectors are allocated, and it is made one Gauss–Seidel block
//!   at a time straight into the first vector of the iteration
//!   ([`NormalMatrix::displacement_forward`]), so it is never stored whole (24 bytes a
//!   node less at the solve's start);
//! - `M` itself is assembled (two-hop sparsity, ~21 entries per row on a 6-connected
//!   grid, f32 values: [`NormalMatrix`]) and preconditioned by block symmetric
//!   Gauss–Seidel applied in Eisenstat's form, so one iteration reads every entry of
//!   `M` once. On the 256³ synthetic bed this takes the first contraction iteration
//!   from 89 Jacobi iterations to 35 (`cg_tol` 1e-4), each about as costly as a
//!   matrix-free `Lᵀ(L x)`. Tried and not kept: smoothed-aggregation multigrid
//!   (20–25 iterations, but ~8 products of `M` each) and looser stop tests (a rule
//!   for issue 3);
//! - the stop test is the residual in the preconditioner's norm, `r · B r` (which
//!   preconditioned CG computes anyway), not `|r|`: the residual itself then need not
//!   be stored or updated, which saves two vectors (48 B per node) and a sixth of each
//!   iteration's memory traffic; the iteration counts stay within a few per cent of the
//!   `|r|` test at the same tolerance;
//! - the three coordinates share every matrix pass, each with its own CG scalars;
//! - every reduction is summed over fixed chunks (or the fixed Gauss–Seidel blocks) in
//!   a fixed order, so the result does not depend on the thread count.

use crate::laplacian::NormalOperator;
use crate::precondition::{sum_parts, Krylov, NormalMatrix, F3, V3};
use rayon::prelude::*;

/// Entries per parallel chunk of the vector reductions.
const CHUNK: usize = 8192;

/// Per-coordinate `sum_i w_i y_i[c]²`, reduced over fixed chunks.
fn weighted_norms(w: &[f32], y: &[F3]) -> V3 {
    let parts: Vec<V3> = w
        .par_chunks(CHUNK)
        .zip(y.par_chunks(CHUNK))
        .map(|(wc, yc)| {
            let mut s = [0.0; 3];
            for (&wi, yi) in wc.iter().zip(yc) {
                for c in 0..3 {
                    let yi = yi[c] as f64;
                    s[c] += wi as f64 * yi * yi;
                }
            }
            s
        })
        .collect();
    sum_parts(&parts)
}

/// The loosest relative residual of a contraction solve ([`solve_tolerance`]), chosen
/// on the fidelity benchmark's tuning set and checked on the held-out set. Looser
/// starts cut the first solves' conjugate-gradient iterations further (35 → 25 at
/// 1e-3, 16 at 1e-2 on the 256³ bed) but made the lattices' graphs worse: held-out
/// connectivity false negatives 0.142 → 0.160 at 1e-3, tuning 0.139 → 0.161 at 1e-2
/// (even with only the first solve loose); at 5e-4 every family stays within its spread
/// (README, "Where we differ").
pub const EARLY_CG_TOL: f64 = 5e-4;

/// The relative residual to which a contraction iteration solves, given the user's
/// `cg_tol` and the convergence measure before the iteration, `A_t / (stop_ratio A_ref)`
/// (the contraction stops once it falls to 1): `cg_tol * measure`, clamped to
/// `[cg_tol, max(cg_tol, EARLY_CG_TOL)]`. Far from convergence a step moves the nodes
/// a long way and the next iteration's weights and decimation start again from where
/// it left them, so its solve need not be precise; as the measure falls to the stop
/// level the tolerance tightens to `cg_tol`, which the last iterations use. A NaN
/// measure (no reference area) gives `cg_tol`.
///
/// ```
/// use vesselflow::solver::solve_tolerance;
/// assert_eq!(solve_tolerance(1e-4, 735.0), 5e-4);
/// assert!((solve_tolerance(1e-4, 3.5) - 3.5e-4).abs() < 1e-15);
/// assert_eq!(solve_tolerance(1e-4, 0.9), 1e-4);
/// assert_eq!(solve_tolerance(0.1, 1e6), 0.1);
/// assert_eq!(solve_tolerance(1e-4, f64::NAN), 1e-4);
/// ```
pub fn solve_tolerance(cg_tol: f64, measure: f64) -> f64 {
    let t = cg_tol * measure;
    if t.is_nan() {
        cg_tol
    } else {
        t.clamp(cg_tol, cg_tol.max(EARLY_CG_TOL))
    }
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
/// solved to `|r| <= tol |r_0|` per coordinate, at most `max_iterations` iterations,
/// by conjugate gradients on the assembled `M` preconditioned by block symmetric
/// Gauss–Seidel ([`NormalMatrix::sgs_dot`]).
pub fn contract(op: &NormalOperator<'_>, positions: &[V3], tol: f64, max_iterations: usize) -> (Vec<V3>, SolveStats) {
    let m = NormalMatrix::assemble(op, None);
    let k = Krylov::displacement(&m, positions.to_vec());
    solve(&m, k, tol, max_iterations)
}

/// `x + D` with `M D = r`, for the start `x` and residual `r` that `k` was made from
/// ([`Krylov::displacement`]; the tests' `Krylov::start` takes any `r`; the result solves
/// `M x' = M x + r`): `D` from 0 to `|r_k|_B <= tol |r|_B` per coordinate (the
/// residual in the preconditioner's norm, `|r|_B² = r · B r`), at most
/// `max_iterations` iterations. `D` is added to `x` step by step, so the contraction
/// passes its positions and no displacement vector is stored.
pub fn solve(m: &NormalMatrix, mut k: Krylov, tol: f64, max_iterations: usize) -> (Vec<V3>, SolveStats) {
    assert!(k.y.len() == m.rows() && k.x.len() == m.rows(), "one start and one residual per row of M");
    // Preconditioned CG with block symmetric Gauss–Seidel `B r = (D + U)⁻¹ D (D + L)⁻¹ r`
    // in Eisenstat's form: the search direction `s` is kept with `ŝ = (D + U) s`, so
    // `M s = ŝ + (L + E) s` needs no product of its own: every iteration reads the stored
    // in-block upper entries twice (row by row in `backward`, column by column for `L`
    // in `forward_product`) and the entries in other blocks twice (`s · E s` for the
    // step, then `E s` in `forward_product`). The residual is carried only as
    // `y = (D + L)⁻¹ r`, updated row by row in `forward_product` as
    // `y - step (D + L)⁻¹ M s` once the step is known; `r · B r = y · D y` is both the
    // CG scalar and the stop test, so neither `r` nor `M s` is stored. The update of `x`
    // waits for the next `backward` pass instead of a pass of its own.
    let mut rz = weighted_norms(&m.diag, &k.y);
    let rz0 = rz;
    let mut active = rz0.map(|x| x > 0.0);
    let (mut step, mut beta) = ([0.0; 3], [0.0; 3]);
    let mut iterations = 0;
    // A run asked to stop ends the solve early ([`crate::cancel`]); its caller discards it.
    while active.iter().any(|&a| a) && iterations < max_iterations && !crate::cancel::cg_iteration_stops() {
        iterations += 1;
        let [sh, su] = m.backward(&mut k, step, beta);
        if crate::cancel::requested() {
            break;
        }
        let se = m.outer_product(&k.s);
        let pq: V3 = std::array::from_fn(|c| sh[c] + su[c] + se[c]);
        step = std::array::from_fn(|c| if active[c] && pq[c] > 0.0 { rz[c] / pq[c] } else { 0.0 });
        let rz_new = m.forward_product(&mut k, step);
        for c in 0..3 {
            if active[c] && (rz_new[c] <= tol * tol * rz0[c] || pq[c] <= 0.0) {
                active[c] = false;
            }
        }
        beta = std::array::from_fn(|c| if active[c] && rz[c] > 0.0 { rz_new[c] / rz[c] } else { 0.0 });
        rz = rz_new;
    }
    // The last step's update of `x`.
    k.x.par_iter_mut()
        .zip(k.s.par_iter())
        .for_each(|(x, s)| *x = std::array::from_fn(|c| x[c] + step[c] * s[c] as f64));
    let converged = !active.iter().any(|&a| a);
    (k.x, SolveStats { iterations, converged })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Csr;
    use crate::laplacian::{l2_norm, medial, Laplacian};
    use crate::params::{MedialWeight, Params};

    /// Dense `M = a² LnᵀLn + b² LmᵀLm + diag(w²)`.
    fn dense_normal(g: &Csr, ln: &Laplacian<'_>, lm: &Laplacian<'_>, a: f64, b: f64, w: &[f64]) -> Vec<Vec<f64>> {
        let n = g.nodes();
        let mat = |l: &Laplacian<'_>| {
            let mut m = vec![vec![0.0; n]; n];
            for i in 0..n {
                m[i][i] = l.diagonal(i) as f64;
                for &j in g.neighbours(i) {
                    m[i][j as usize] = l.weight(i, j as usize) as f64;
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
        m
    }

    /// `x` with `m x = rhs` per coordinate, by Gauss–Jordan elimination with pivoting.
    fn gauss(m: &[Vec<f64>], rhs: &[V3]) -> Vec<V3> {
        let n = m.len();
        let mut out = vec![[0.0; 3]; n];
        for c in 0..3 {
            let mut aug: Vec<Vec<f64>> = (0..n)
                .map(|i| {
                    let mut row = m[i].clone();
                    row.push(rhs[i][c]);
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

    /// Dense least squares of eq. 8 by Gaussian elimination on the normal equations.
    fn dense(g: &Csr, ln: &Laplacian<'_>, lm: &Laplacian<'_>, a: f64, b: f64, w: &[f64], p: &[V3]) -> Vec<V3> {
        let m = dense_normal(g, ln, lm, a, b, w);
        let rhs: Vec<V3> = (0..p.len()).map(|i| p[i].map(|x| w[i] * w[i] * x)).collect();
        gauss(&m, &rhs)
    }

    /// A test problem: the Laplacians and anchors of a graph with geometry (leaked, so
    /// that the Laplacians can borrow them for the test's lifetime).
    struct Problem {
        g: Csr,
        p: &'static [V3],
        ln: Laplacian<'static>,
        lm: Laplacian<'static>,
        /// The anchored-harder nodes, and every node's anchoring `Wg` (0.5 or 0.05).
        hard: Vec<bool>,
        w: Vec<f64>,
    }

    impl Problem {
        fn new(g: Csr, p: Vec<V3>, radii: &[f64], hard: Vec<bool>) -> Problem {
            let (p, radii): (&'static [V3], &'static [f64]) = (p.leak(), radii.to_vec().leak());
            let ln = l2_norm(&g, p);
            let lm = medial(&g, radii, MedialWeight::Radius);
            let w = hard.iter().map(|&h| if h { 0.5 } else { 0.05 }).collect();
            Problem { g, p, ln, lm, hard, w }
        }

        fn op(&self) -> NormalOperator<'_> {
            NormalOperator {
                graph: &self.g,
                ln: &self.ln,
                lm: &self.lm,
                a2: 0.25,
                b2: 0.25,
                skeletal: &self.hard,
                anchor2: [0.05 * 0.05, 0.5 * 0.5],
            }
        }

        /// The right-hand side `-(M - Wg²) P` of the displacement system.
        fn rhs(&self) -> Vec<V3> {
            super::reference::rhs(&self.op(), self.p)
        }
    }

    /// A small irregular graph: a 3x3 grid patch plus a diagonal.
    fn patch() -> Problem {
        let edges =
            [(0, 1), (0, 3), (1, 2), (1, 4), (2, 5), (3, 4), (3, 6), (4, 5), (4, 7), (4, 8), (5, 8), (6, 7), (7, 8)];
        let g = Csr::from_sorted_edges(9, &edges);
        let p: Vec<V3> =
            (0..9).map(|i| [(i % 3) as f64 + 0.1 * i as f64, (i / 3) as f64, 0.3 * (i % 2) as f64 + 5.0]).collect();
        let r: Vec<f64> = (0..9).map(|i| 1.0 + (i % 4) as f64).collect();
        Problem::new(g, p, &r, (0..9).map(|i| i == 4).collect())
    }

    /// An `a × b × c` block of voxels with face edges, positions jittered and radii
    /// varied deterministically, one node in seven anchored harder.
    fn block(a: usize, b: usize, c: usize) -> Problem {
        let id = |i: usize, j: usize, k: usize| ((i * b + j) * c + k) as u32;
        let mut edges = vec![];
        for i in 0..a {
            for j in 0..b {
                for k in 0..c {
                    if k + 1 < c {
                        edges.push((id(i, j, k), id(i, j, k + 1)));
                    }
                    if j + 1 < b {
                        edges.push((id(i, j, k), id(i, j + 1, k)));
                    }
                    if i + 1 < a {
                        edges.push((id(i, j, k), id(i + 1, j, k)));
                    }
                }
            }
        }
        edges.sort_unstable();
        let n = a * b * c;
        let g = Csr::from_sorted_edges(n, &edges);
        let p: Vec<V3> = (0..n)
            .map(|t| {
                let (i, j, k) = (t / (b * c), t / c % b, t % c);
                let f = t as f64;
                [i as f64 + 0.2 * (1.3 * f).sin(), j as f64 + 0.2 * (0.7 * f).cos(), k as f64 + 0.1 * (2.1 * f).sin()]
            })
            .collect();
        let radii: Vec<f64> = (0..n).map(|t| 1.0 + 0.5 * (0.37 * t as f64).sin().abs()).collect();
        Problem::new(g, p, &radii, (0..n).map(|t| t % 7 == 0).collect())
    }

    fn max_diff(a: &[V3], b: &[V3]) -> f64 {
        a.iter().zip(b).flat_map(|(x, y)| (0..3).map(move |c| (x[c] - y[c]).abs())).fold(0.0, f64::max)
    }

    #[test]
    fn matches_dense_least_squares() {
        let pb = patch();
        let (fast, stats) = contract(&pb.op(), pb.p, 1e-12, 1000);
        assert!(stats.converged);
        let slow = dense(&pb.g, &pb.ln, &pb.lm, 0.5, 0.5, &pb.w, pb.p);
        // `M` is stored in f32 (like the Laplacian weights it is built from), so the
        // solution carries its relative rounding, ~1e-7.
        assert!(max_diff(&fast, &slow) < 1e-6, "{fast:?} vs {slow:?}");
        // The previous solver (matrix-free, f64 throughout) agrees to 1e-8.
        let (old, _) = super::reference::jacobi_contract(&pb.op(), pb.p, 1e-12, 1000);
        assert!(max_diff(&old, &slow) < 1e-8);
        // The flow moved the nodes: the solution is not the input.
        assert!(fast.iter().zip(pb.p).any(|(a, b)| (a[0] - b[0]).abs() > 1e-3));
    }

    /// The stored `M`, dense, read column by column as `M e_k` (each product adds one
    /// non-zero term per row, so the values come out exactly as stored).
    fn stored(m: &NormalMatrix) -> Vec<Vec<f64>> {
        let n = m.rows();
        let mut out = vec![vec![0.0; n]; n];
        let (mut e, mut col) = (vec![[0.0; 3]; n], vec![[0.0; 3]; n]);
        for k in 0..n {
            e[k] = [1.0; 3];
            m.apply_dot(&e, &mut col);
            e[k] = [0.0; 3];
            for j in 0..n {
                out[j][k] = col[j][0];
            }
        }
        out
    }

    #[test]
    fn assembled_matrix_is_the_normal_matrix_and_exactly_symmetric() {
        for pb in [patch(), block(4, 5, 6)] {
            let n = pb.p.len();
            let want = dense_normal(&pb.g, &pb.ln, &pb.lm, 0.5, 0.5, &pb.w);
            // In blocks of one row every entry is computed and stored by both its rows,
            // so symmetry is the assembly's, not the storage's.
            for bs in [1, 7, n] {
                let m = NormalMatrix::assemble_in_blocks(&pb.op(), bs, None);
                let got = stored(&m);
                for j in 0..n {
                    assert_eq!(m.diag[j] as f64, got[j][j]);
                    for k in 0..n {
                        assert!((got[j][k] - want[j][k]).abs() <= 1e-6 * want[j][j], "M[{j}][{k}]");
                        assert_eq!(got[j][k].to_bits(), got[k][j].to_bits(), "M[{j}][{k}] vs M[{k}][{j}]");
                    }
                }
            }
        }
    }

    #[test]
    fn rows_in_another_order_are_the_same_matrix_permuted() {
        let pb = block(4, 5, 6);
        let n = pb.p.len();
        // A fixed shuffle of the nodes.
        let mut order: Vec<u32> = (0..n as u32).collect();
        for (a, v) in noise(n, 7).iter().enumerate() {
            order.swap(a, ((v[0] + 1.0) / 2.0 * (n - a) as f64) as usize % (n - a) + a);
        }
        assert!(order.iter().enumerate().any(|(a, &j)| a != j as usize));
        for bs in [1, 7, n] {
            let plain = stored(&NormalMatrix::assemble_in_blocks(&pb.op(), bs, None));
            let m = NormalMatrix::assemble_in_blocks(&pb.op(), bs, Some(&order));
            let got = stored(&m);
            for a in 0..n {
                assert_eq!(m.diag[a] as f64, plain[order[a] as usize][order[a] as usize]);
                for b in 0..n {
                    let want = plain[order[a] as usize][order[b] as usize];
                    assert_eq!(got[a][b].to_bits(), want.to_bits(), "block {bs}: M[{a}][{b}]");
                }
            }
        }
    }

    #[test]
    fn right_hand_side_from_the_matrix_is_translation_invariant() {
        for pb in [patch(), block(4, 5, 6)] {
            let n = pb.p.len();
            // The matrix-free `-(a² LnᵀLn + b² LmᵀLm) P`, in f64 from the Laplacians.
            let want = pb.rhs();
            let scale = want.iter().flatten().fold(0.0f64, |a, v| a.max(v.abs()));
            assert!(scale > 1e-3);
            let far: Vec<V3> = pb.p.iter().map(|q| q.map(|v| v + 1e4)).collect();
            for bs in [1, 7, n] {
                let m = NormalMatrix::assemble_in_blocks(&pb.op(), bs, None);
                let got = m.displacement_rhs(pb.p);
                // `M` is stored in f32: its relative rounding, ~1e-7.
                assert!(max_diff(&got, &want) <= 1e-6 * scale, "block {bs}");
                // Positions 1e4 away give the same right-hand side to f64 rounding.
                assert!(max_diff(&m.displacement_rhs(&far), &got) <= 1e-9 * scale, "block {bs}");
            }
        }
    }

    #[test]
    fn the_start_from_positions_is_the_start_from_their_right_hand_side() {
        // `Krylov::displacement` makes and solves each block's right-hand side in a
        // buffer of its own: the same `y`, bit for bit, as the whole `r` then `forward`.
        for pb in [patch(), block(4, 5, 6)] {
            let n = pb.p.len();
            for bs in [1, 7, n] {
                let m = NormalMatrix::assemble_in_blocks(&pb.op(), bs, None);
                let fused = Krylov::displacement(&m, pb.p.to_vec());
                let whole = Krylov::start(&m, pb.p.to_vec(), m.displacement_rhs(pb.p));
                let bits = |k: &Krylov| k.y.iter().flatten().map(|v| v.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&fused), bits(&whole), "block {bs}");
                assert!(fused.y.iter().flatten().any(|&v| v != 0.0));
            }
        }
    }

    /// Deterministic pseudo-random vectors (xorshift64*), entries in [-1, 1).
    fn noise(n: usize, seed: u64) -> Vec<V3> {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let mut next = || {
            s ^= s >> 12;
            s ^= s << 25;
            s ^= s >> 27;
            (s.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 52) as f64 - 1.0
        };
        (0..n).map(|_| [next(), next(), next()]).collect()
    }

    pub(super) fn dot(a: &[V3], b: &[V3]) -> V3 {
        std::array::from_fn(|c| a.iter().zip(b).map(|(x, y)| x[c] * y[c]).sum())
    }

    #[test]
    fn block_gauss_seidel_is_symmetric_positive_definite() {
        let pb = block(5, 6, 7);
        let n = pb.p.len();
        for bs in [n, 50, 17] {
            let m = NormalMatrix::assemble_in_blocks(&pb.op(), bs, None);
            for seed in 0..5 {
                let (u, v) = (noise(n, 2 * seed), noise(n, 2 * seed + 1));
                let (mut bu, mut bv) = (vec![[0.0; 3]; n], vec![[0.0; 3]; n]);
                let uu = m.sgs_dot(&u, &mut bu);
                m.sgs_dot(&v, &mut bv);
                let (ubv, vbu) = (dot(&u, &bv), dot(&v, &bu));
                for c in 0..3 {
                    assert!((ubv[c] - vbu[c]).abs() <= 1e-12 * ubv[c].abs().max(1.0), "block {bs}: {ubv:?} {vbu:?}");
                    assert!(uu[c] > 0.0);
                }
                // The returned dot product is u · B u.
                assert!(max_diff(&[uu], &[dot(&u, &bu)]) <= 1e-12 * uu[0].abs());
            }
        }
    }

    /// Plain preconditioned CG with the explicit products and the same stop test
    /// (`r · B r <= tol² r_0 · B r_0`), as the reference for the Eisenstat form.
    fn explicit_pcg(m: &NormalMatrix, b: &[V3], tol: f64, max_iterations: usize) -> (Vec<V3>, usize) {
        let n = b.len();
        let (mut x, mut r, mut z, mut q) = (vec![[0.0; 3]; n], b.to_vec(), vec![[0.0; 3]; n], vec![[0.0; 3]; n]);
        let mut rz = m.sgs_dot(&r, &mut z);
        let rz0 = rz;
        let mut s = z.clone();
        let mut active = [true; 3];
        let mut k = 0;
        while active.iter().any(|&a| a) && k < max_iterations {
            k += 1;
            let sq = m.apply_dot(&s, &mut q);
            for c in 0..3 {
                let step = if active[c] { rz[c] / sq[c] } else { 0.0 };
                for i in 0..n {
                    x[i][c] += step * s[i][c];
                    r[i][c] -= step * q[i][c];
                }
            }
            let rz_new = m.sgs_dot(&r, &mut z);
            for c in 0..3 {
                active[c] &= rz_new[c] > tol * tol * rz0[c];
                let beta = if active[c] { rz_new[c] / rz[c] } else { 0.0 };
                for i in 0..n {
                    s[i][c] = z[i][c] + beta * s[i][c];
                }
            }
            rz = rz_new;
        }
        (x, k)
    }

    #[test]
    fn eisenstat_form_equals_explicit_preconditioned_cg() {
        // The solver keeps three of its vectors in f32, so it follows the explicit f64
        // iteration to about f32's precision, and reaches a relative residual of 1e-6.
        let pb = block(6, 7, 8);
        let b = pb.rhs();
        for bs in [b.len(), 64, 25] {
            let m = NormalMatrix::assemble_in_blocks(&pb.op(), bs, None);
            let (want, k) = explicit_pcg(&m, &b, 1e-6, 500);
            let (got, stats) = solve(&m, Krylov::start(&m, vec![[0.0; 3]; b.len()], b.clone()), 1e-6, 500);
            assert!(stats.converged);
            assert!(stats.iterations.abs_diff(k) <= 1, "block {bs}: {} vs {k}", stats.iterations);
            assert!(max_diff(&got, &want) < 1e-5, "block {bs}: {}", max_diff(&got, &want));
            // And it solves the assembled system: M x = b to the tolerance.
            let mut mx = vec![[0.0; 3]; b.len()];
            m.apply_dot(&got, &mut mx);
            let res: Vec<V3> = mx.iter().zip(&b).map(|(x, y)| std::array::from_fn(|c| x[c] - y[c])).collect();
            let (rr, bb) = (dot(&res, &res), dot(&b, &b));
            assert!((0..3).all(|c| rr[c].sqrt() <= 2e-6 * bb[c].sqrt()), "{rr:?}");
        }
    }

    #[test]
    fn solve_matches_a_dense_solve_of_the_assembled_matrix() {
        let pb = block(3, 4, 5);
        let m = NormalMatrix::assemble_in_blocks(&pb.op(), 13, None);
        let n = m.rows();
        let dense_m = stored(&m);
        let b = pb.rhs();
        // Three of the solver's vectors are f32: it reaches a relative residual of
        // 1e-6, not f64's.
        let (got, stats) = solve(&m, Krylov::start(&m, vec![[0.0; 3]; n], b.clone()), 1e-6, 1000);
        assert!(stats.converged && stats.iterations < n);
        let exact = gauss(&dense_m, &b);
        let scale = exact.iter().flatten().fold(0f64, |a, v| a.max(v.abs()));
        assert!(max_diff(&got, &exact) < 1e-5 * scale, "{} vs {scale}", max_diff(&got, &exact));
        // Fewer iterations than Jacobi-preconditioned CG on the same system.
        let (_, jacobi) = super::reference::jacobi_contract(&pb.op(), pb.p, 1e-6, 1000);
        assert!(stats.iterations < jacobi.iterations, "{stats:?} vs {jacobi:?}");
    }

    #[test]
    fn the_tolerance_tightens_to_cg_tol_as_the_measure_falls_to_the_stop_level() {
        let tols: Vec<f64> = [1e4, 735.0, 40.0, 5.0, 1.0, 0.5, 0.0].map(|m| solve_tolerance(1e-4, m)).to_vec();
        assert!(tols.windows(2).all(|w| w[0] >= w[1]), "{tols:?}");
        assert_eq!(tols[0], EARLY_CG_TOL);
        assert_eq!(tols[tols.len() - 1], 1e-4);
        // A user's tolerance looser than the early one is used throughout.
        assert!([1e4, 1.0, 0.0].iter().all(|&m| solve_tolerance(0.2, m) == 0.2));
    }

    #[test]
    fn the_first_contraction_solve_runs_to_the_early_tolerance() {
        // The voxel grid of a thick tube starts thousands of times above the stop
        // level, so its first solve runs to `EARLY_CG_TOL` whether the user asks for
        // 1e-4 or for `EARLY_CG_TOL` itself (without the schedule, 1e-4 takes more).
        // One node per voxel (no coarse start), the case the schedule is written for.
        let mask = crate::shapes::cylinder([40, 25, 25], 8.0);
        let run = |cg_tol: f64| {
            let p = Params { cg_tol, coarse_cell: 0.0, ..Params::default() };
            crate::Skeletonizer::new(p).unwrap().run(mask.view(), [1.0; 3], &mut |_| true).unwrap().info
        };
        let (tight, early) = (run(1e-4), run(EARLY_CG_TOL));
        assert!(tight.area_per_iteration[0] > 1e3 * tight.area_reference, "{tight:?}");
        assert_eq!(tight.cg_iterations[0], early.cg_iterations[0]);
    }

    #[test]
    fn result_does_not_depend_on_thread_count() {
        let pb = block(24, 30, 36);
        let run = |threads: usize, block: Option<usize>| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| match block {
                None => contract(&pb.op(), pb.p, 1e-8, 500),
                Some(bs) => {
                    let m = NormalMatrix::assemble_in_blocks(&pb.op(), bs, None);
                    let k = Krylov::start(&m, pb.p.to_vec(), pb.rhs());
                    solve(&m, k, 1e-8, 500)
                }
            })
        };
        let (_, jacobi) = super::reference::jacobi_contract(&pb.op(), pb.p, 1e-8, 500);
        for block in [None, Some(1000)] {
            let (one, s1) = run(1, block);
            assert!(s1.converged);
            // The point of the preconditioner: well under half the Jacobi iterations.
            assert!(2 * s1.iterations < jacobi.iterations, "{s1:?} vs {jacobi:?}");
            for threads in [2, 3] {
                let (many, s) = run(threads, block);
                assert_eq!(s, s1);
                assert!(one.iter().zip(&many).all(|(a, b)| (0..3).all(|c| a[c].to_bits() == b[c].to_bits())));
            }
        }
    }
}

/// The matrix-free operator and the first solver, kept as references for tests.
#[cfg(test)]
mod reference {
    use super::tests::dot;
    use super::*;
    use crate::grid::Csr;
    use crate::laplacian::Laplacian;

    /// `(L x)_i` for one node.
    fn apply_row(g: &Csr, l: &Laplacian<'_>, x: &[V3], i: usize) -> V3 {
        let d = l.diagonal(i) as f64;
        let mut y = [d * x[i][0], d * x[i][1], d * x[i][2]];
        for &j in g.neighbours(i) {
            let wij = l.weight(i, j as usize) as f64;
            let xj = &x[j as usize];
            y[0] += wij * xj[0];
            y[1] += wij * xj[1];
            y[2] += wij * xj[2];
        }
        y
    }

    /// `(Lnᵀ un)_j` and `(Lmᵀ um)_j`, over the weights `W_ij` of `j`'s neighbours `i`.
    fn transposed_row(g: &Csr, ln: &Laplacian<'_>, lm: &Laplacian<'_>, un: &[V3], um: &[V3], j: usize) -> (V3, V3) {
        let (dn, dm) = (ln.diagonal(j) as f64, lm.diagonal(j) as f64);
        let mut a = un[j].map(|v| dn * v);
        let mut b = um[j].map(|v| dm * v);
        for &i in g.neighbours(j) {
            let i = i as usize;
            let (wn, wm) = (ln.weight(i, j) as f64, lm.weight(i, j) as f64);
            for c in 0..3 {
                a[c] += wn * un[i][c];
                b[c] += wm * um[i][c];
            }
        }
        (a, b)
    }

    impl NormalOperator<'_> {
        /// `L x` for both Laplacians.
        fn forward(&self, x: &[V3], un: &mut [V3], um: &mut [V3]) {
            let g = self.graph;
            un.par_iter_mut().zip(um.par_iter_mut()).enumerate().with_min_len(1024).for_each(|(i, (a, b))| {
                *a = apply_row(g, self.ln, x, i);
                *b = apply_row(g, self.lm, x, i);
            });
        }

        /// `y = M x`, using `un`, `um` as scratch.
        pub fn apply(&self, x: &[V3], y: &mut [V3], un: &mut [V3], um: &mut [V3]) {
            self.forward(x, un, um);
            let g = self.graph;
            let (un, um) = (&*un, &*um);
            y.par_iter_mut().enumerate().with_min_len(1024).for_each(|(j, yj)| {
                let (a, b) = transposed_row(g, self.ln, self.lm, un, um, j);
                let w2 = self.anchor2(j);
                for c in 0..3 {
                    yj[c] = self.a2 * a[c] + self.b2 * b[c] + w2 * x[j][c];
                }
            });
        }

        /// The diagonal of `M` (the Jacobi preconditioner).
        pub fn diagonal(&self) -> Vec<f64> {
            let g = self.graph;
            let mut sq = vec![0f64; g.nodes()];
            // diag(LᵀL)_j = sum_i L_ij² = L_jj² + sum over j's neighbours i of W_ij².
            sq.par_iter_mut().enumerate().for_each(|(j, s)| {
                let (dn, dm) = (self.ln.diagonal(j) as f64, self.lm.diagonal(j) as f64);
                let col: f64 = g
                    .neighbours(j)
                    .iter()
                    .map(|&i| {
                        let i = i as usize;
                        let (wn, wm) = (self.ln.weight(i, j) as f64, self.lm.weight(i, j) as f64);
                        self.a2 * wn * wn + self.b2 * wm * wm
                    })
                    .sum();
                *s = col + self.a2 * dn * dn + self.b2 * dm * dm + self.anchor2(j);
            });
            sq
        }
    }

    /// The right-hand side for the displacement, `r0 = b - M·0 = -(a² LnᵀLn + b² LmᵀLm) P
    /// = -(M P - Wg² P)`, matrix-free: the Laplacians' rows sum to zero, so this is
    /// translation-invariant.
    pub(super) fn rhs(op: &NormalOperator<'_>, positions: &[V3]) -> Vec<V3> {
        let n = positions.len();
        let mut r = vec![[0.0; 3]; n];
        {
            let mut un = vec![[0.0; 3]; n];
            let mut um = vec![[0.0; 3]; n];
            op.apply(positions, &mut r, &mut un, &mut um);
        }
        r.par_iter_mut().zip(positions.par_iter()).enumerate().for_each(|(j, (ri, p))| {
            let w2 = op.anchor2(j);
            for c in 0..3 {
                ri[c] = -(ri[c] - w2 * p[c]);
            }
        });
        r
    }

    /// The first solver, kept as the reference for tests: Jacobi-preconditioned
    /// matrix-free CG, stopping on the plain residual.
    /// New positions `P'` of eq. 8: `P + D` with `M D = -(alpha² LnᵀLn + beta² LmᵀLm) P`,
    /// solved to `|r| <= tol |r_0|` per coordinate, at most `max_iterations` iterations.
    pub(super) fn jacobi_contract(
        op: &NormalOperator<'_>,
        positions: &[V3],
        tol: f64,
        max_iterations: usize,
    ) -> (Vec<V3>, SolveStats) {
        let n = positions.len();
        let mut un = vec![[0.0; 3]; n];
        let mut um = vec![[0.0; 3]; n];
        let mut r = rhs(op, positions);
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
        let mut rz = dot(&r, &z);
        let r0 = dot(&r, &r).map(f64::sqrt);
        let mut active = r0.map(|x| x > 0.0);
        let mut q = vec![[0.0; 3]; n];
        let mut iterations = 0;
        while active.iter().any(|&a| a) && iterations < max_iterations {
            iterations += 1;
            op.apply(&search, &mut q, &mut un, &mut um);
            let pq = dot(&search, &q);
            let step: V3 = std::array::from_fn(|c| if active[c] && pq[c] > 0.0 { rz[c] / pq[c] } else { 0.0 });
            d.par_iter_mut().zip(r.par_iter_mut()).zip(search.par_iter().zip(q.par_iter())).for_each(
                |((di, ri), (si, qi))| {
                    for c in 0..3 {
                        di[c] += step[c] * si[c];
                        ri[c] -= step[c] * qi[c];
                    }
                },
            );
            let rr = dot(&r, &r);
            for c in 0..3 {
                if active[c] && (rr[c].sqrt() <= tol * r0[c] || pq[c] <= 0.0) {
                    active[c] = false;
                }
            }
            precondition(&r, &mut z);
            let rz_new = dot(&r, &z);
            let beta: V3 = std::array::from_fn(|c| if active[c] && rz[c] > 0.0 { rz_new[c] / rz[c] } else { 0.0 });
            rz = rz_new;
            search.par_iter_mut().zip(z.par_iter()).for_each(|(si, zi)| {
                for c in 0..3 {
                    si[c] = zi[c] + beta[c] * si[c];
                }
            });
        }
        let converged = !active.iter().any(|&a| a);
        let out =
            positions.par_iter().zip(d.par_iter()).map(|(p, d)| [p[0] + d[0], p[1] + d[1], p[2] + d[2]]).collect();
        (out, SolveStats { iterations, converged })
    }
}

/// Measurement harness on a mask file (not a test of correctness): `VF_BED=/tmp/bed.npy
/// [VF_THREADS=2] [VF_TOL=1e-6] [VF_COMPARE=1] [VF_OUT=/tmp/out.bin] cargo test --release
/// -p vesselflow --lib bed_run -- --ignored --nocapture`. Prints the first contraction
/// iteration's solve (with `VF_COMPARE`: the kernels' times and the new solver against the
/// Jacobi reference), then a whole run's CG iterations, stage times and peak RSS; `VF_OUT`
/// gets the output positions (u64 count, then f64 x, y, z per node).
#[cfg(test)]
mod harness {
    use crate::pipeline::{contract_step, StageClock};
    use crate::{decimate::NodeGraph, grid, volume, Params, Skeletonizer};
    use ndarray::Array3;
    use std::time::Instant;

    /// A C-order `.npy` of `|b1` or `|u1` voxels.
    fn load_npy(path: &str) -> Array3<u8> {
        let bytes = std::fs::read(path).expect("readable mask");
        let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        let header = std::str::from_utf8(&bytes[10..10 + hlen]).expect("ascii header");
        assert!(header.contains("'|b1'") || header.contains("'|u1'"), "{header}");
        assert!(header.contains("'fortran_order': False"));
        let s = &header[header.find("'shape': (").expect("shape") + 10..];
        let dims: Vec<usize> = s[..s.find(')').expect(")")].split(',').filter_map(|x| x.trim().parse().ok()).collect();
        Array3::from_shape_vec((dims[0], dims[1], dims[2]), bytes[10 + hlen..].to_vec()).expect("shape")
    }

    #[test]
    #[ignore]
    fn bed_run() {
        let Ok(path) = std::env::var("VF_BED") else { return };
        let threads: usize = std::env::var("VF_THREADS").ok().and_then(|t| t.parse().ok()).unwrap_or(2);
        let mask = load_npy(&path);
        let mut p = Params { threads, ..Params::default() };
        if let Ok(t) = std::env::var("VF_TOL") {
            p.cg_tol = t.parse().expect("tol");
        }
        // The first contraction iteration alone, solve timed.
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        let edt = volume::edt_squared(mask.view(), [1.0; 3]).unwrap();
        let g = grid::build(mask.view(), &edt, [1.0; 3], &p).unwrap();
        let g = NodeGraph { graph: g.graph, positions: g.positions, radii: g.radii, component: g.component };
        let mut clock = StageClock::default();
        let t = Instant::now();
        let (_, stats) = pool
            .install(|| {
                contract_step(
                    g.clone(),
                    &p,
                    1.0,
                    crate::precondition::slab_axes(mask.dim().into()),
                    &mut clock,
                    mask.view(),
                    [1.0; 3],
                )
            })
            .unwrap();
        let dt = t.elapsed().as_secs_f64();
        if std::env::var("VF_COMPARE").is_ok() {
            let ln = crate::laplacian::l2_norm(&g.graph, &g.positions);
            let lm = crate::laplacian::medial(&g.graph, &g.radii, p.medial_weight);
            let sk = crate::laplacian::skeletal(&g.graph, &g.positions, &p);
            let op = super::NormalOperator::new(&g.graph, &ln, &lm, &sk, &p);
            {
                let n = g.positions.len();
                let t = Instant::now();
                let m = pool.install(|| super::NormalMatrix::assemble(&op, None));
                let t_asm = t.elapsed().as_secs_f64();
                let x: Vec<[f64; 3]> = g.positions.iter().map(|q| [q[0].sin(), q[1].cos(), q[2]]).collect();
                let mut y = vec![[0.0; 3]; n];
                let (mut un, mut um) = (vec![[0.0; 3]; n], vec![[0.0; 3]; n]);
                let t = Instant::now();
                for _ in 0..10 {
                    pool.install(|| m.apply_dot(&x, &mut y));
                }
                let t_apply = t.elapsed().as_secs_f64() / 10.0;
                let t = Instant::now();
                for _ in 0..10 {
                    pool.install(|| m.sgs_dot(&x, &mut y));
                }
                let t_sgs = t.elapsed().as_secs_f64() / 10.0;
                let t = Instant::now();
                for _ in 0..10 {
                    pool.install(|| op.apply(&x, &mut y, &mut un, &mut um));
                }
                let t_mf = t.elapsed().as_secs_f64() / 10.0;
                eprintln!("nnz/row {:.1}: assemble {t_asm:.3} s, M x {t_apply:.4} s, sgs {t_sgs:.4} s, matrix-free M x {t_mf:.4} s", m.stored_entries() as f64 / n as f64);
            }
            for _ in 0..2 {
                let t = Instant::now();
                let (a, sa) = pool.install(|| super::contract(&op, &g.positions, p.cg_tol, p.cg_max_iterations));
                let ta = t.elapsed().as_secs_f64();
                let t = Instant::now();
                let (b, sb) = pool
                    .install(|| super::reference::jacobi_contract(&op, &g.positions, p.cg_tol, p.cg_max_iterations));
                let tb = t.elapsed().as_secs_f64();
                let diff: Vec<f64> =
                    a.iter().zip(&b).map(|(x, y)| (0..3).map(|c| (x[c] - y[c]).powi(2)).sum::<f64>().sqrt()).collect();
                let mean = diff.iter().sum::<f64>() / diff.len() as f64;
                let max = diff.iter().cloned().fold(0.0, f64::max);
                eprintln!("solve new {ta:.3} s {sa:?} | jacobi {tb:.3} s {sb:?} | |new - jacobi| mean {mean:.2e} max {max:.2e}");
            }
        }
        eprintln!("first iteration: {} nodes, {stats:?}, {dt:.3} s, {clock:?}", g.positions.len());
        drop(g);
        let t = Instant::now();
        let sk = Skeletonizer::new(p).unwrap().run(mask.view(), [1.0; 3], &mut |_| true).unwrap();
        let total = t.elapsed().as_secs_f64();
        let info = &sk.info;
        eprintln!("run: {total:.3} s, {} nodes out, {} iterations", sk.len(), info.iterations);
        eprintln!("cg iterations: {:?}", info.cg_iterations);
        eprintln!("nodes: {:?}", info.nodes_per_iteration);
        eprintln!("stages: {:?}", info.stage_seconds);
        let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
        eprintln!("{}", status.lines().find(|l| l.starts_with("VmHWM")).unwrap_or(""));
        if let Ok(out) = std::env::var("VF_OUT") {
            let mut b: Vec<u8> = Vec::new();
            b.extend((sk.len() as u64).to_le_bytes());
            for q in &sk.positions {
                for x in q {
                    b.extend(x.to_le_bytes());
                }
            }
            std::fs::write(out, b).unwrap();
        }
    }
}
