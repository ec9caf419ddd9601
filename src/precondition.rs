//! The assembled normal matrix of eq. 8 and its block symmetric Gauss–Seidel
//! preconditioner, used by the contraction solve (METHOD.md §2.4).
//!
//! `M = alpha² LnᵀLn + beta² LmᵀLm + Wg²` couples nodes up to two hops apart (about
//! 21 entries per row on a 6-connected grid). Assembled once per contraction
//! iteration, one product `M x` reads those entries once for the three coordinates,
//! which is less memory traffic than the matrix-free `Lᵀ(L x)` (four passes over the
//! CSR weights and two scratch vectors), and it makes a Gauss–Seidel preconditioner
//! possible: symmetric Gauss–Seidel on `M` cuts the conjugate-gradient iterations of
//! the first contraction iteration about 2.5× against Jacobi, the largest
//! cut per product we measured (smoothed-aggregation multigrid cut iterations further
//! but costs more products per iteration; see the solver's notes).
//!
//! Parallelism without a thread-dependent result: the rows are split into fixed
//! contiguous blocks (their number depends only on the node count), each block is
//! swept sequentially ignoring its coupling to other blocks (block Jacobi with
//! symmetric Gauss–Seidel inside), and every reduction sums fixed chunks in order.

use crate::grid::{filled, Csr, PerThread, ROW_BLOCK};
use crate::solver::NormalOperator;
use rayon::prelude::*;

type V3 = [f64; 3];

/// Rows per parallel chunk of the product `M x` and its fused dot product.
const CHUNK: usize = 8192;
/// Fewest rows in a Gauss–Seidel block (thin blocks lose coupling and iterations grow).
const MIN_BLOCK: usize = 32_768;
/// Most Gauss–Seidel blocks: enough to balance a few threads.
const MAX_BLOCKS: usize = 16;

/// `M`, stored for the Gauss–Seidel sweeps. Its rows are cut into fixed contiguous
/// blocks; row `j` of block `[lo, hi)` has entries in earlier blocks (`k < lo`), in-block
/// lower entries (`lo <= k < j`), the diagonal, in-block upper entries (`j < k < hi`)
/// and entries in later blocks (`k >= hi`). The forward sweeps read every off-diagonal
/// entry but the in-block upper ones, the backward sweep only those, so each kind is
/// stored on its own, row after row in increasing column order, as (column, value)
/// pairs: every sweep streams one array front to back, skipping nothing. Values are
/// `f32`, like the Laplacian weights they are built from; arithmetic is `f64`.
///
/// The rows are kept in stripes of [`ROW_BLOCK`] rows, each built by one parallel task
/// and never copied: no serial concatenation, and the pages of each stripe are first
/// touched by the thread that builds it.
#[derive(Debug, Clone, Default)]
pub struct NormalMatrix {
    /// The diagonal `D_j = M_jj` (as stored), positive.
    pub diag: Vec<f64>,
    /// Rows per Gauss–Seidel block (the last block may be shorter): set from the row
    /// count alone by [`NormalMatrix::assemble`], changed by [`NormalMatrix::set_block`].
    block: usize,
    /// Rows `s * ROW_BLOCK..` in stripe `s`.
    stripes: Vec<Stripe>,
}

/// Consecutive rows of `M` without their diagonal, split for the sweeps.
#[derive(Debug, Clone, Default)]
struct Stripe {
    /// Row `t`'s entries outside the in-block upper part: `lower[lower_at[t]..lower_at[t + 1]]`,
    /// cut at `cuts[t] = [b, e]` (from the row's start) into earlier blocks `..b`,
    /// in-block lower `b..e` and later blocks `e..`.
    lower: Vec<(u32, f32)>,
    lower_at: Vec<usize>,
    cuts: Vec<[u32; 2]>,
    /// Row `t`'s in-block upper entries: `upper[upper_at[t]..upper_at[t + 1]]`.
    upper: Vec<(u32, f32)>,
    upper_at: Vec<usize>,
}

impl Stripe {
    fn new() -> Stripe {
        Stripe { lower_at: vec![0], upper_at: vec![0], ..Stripe::default() }
    }

    /// Append row `j` (entries in increasing column order; its diagonal is skipped),
    /// split at its Gauss–Seidel block of `block` rows.
    fn push_row(&mut self, j: usize, block: usize, row: impl Iterator<Item = (u32, f32)>) {
        let (lo, hi) = ((j / block * block) as u32, ((j / block + 1) * block) as u32);
        let start = self.lower.len();
        let mut cuts = [u32::MAX; 2];
        for (k, v) in row {
            if k == j as u32 {
                continue;
            }
            if k >= lo && cuts[0] == u32::MAX {
                cuts[0] = (self.lower.len() - start) as u32;
            }
            if k > j as u32 && k < hi {
                self.upper.push((k, v));
                continue;
            }
            if k >= hi && cuts[1] == u32::MAX {
                cuts[1] = (self.lower.len() - start) as u32;
            }
            self.lower.push((k, v));
        }
        let len = (self.lower.len() - start) as u32;
        self.cuts.push(cuts.map(|c| c.min(len)));
        self.lower_at.push(self.lower.len());
        self.upper_at.push(self.upper.len());
    }
}

/// `acc + sum_k m_jk x_k` over the given entries of a row.
#[inline]
fn gather(entries: &[(u32, f32)], x: &[V3], mut acc: V3) -> V3 {
    for &(k, m) in entries {
        let (m, xk) = (m as f64, &x[k as usize]);
        for c in 0..3 {
            acc[c] += m * xk[c];
        }
    }
    acc
}

/// Row `j` of `M`: `M_jk = sum_i (a² Ln_ij Ln_ik + b² Lm_ij Lm_ik) + [j = k] Wg_j²`,
/// `i` over `j` and its neighbours (the rows of `L` with an entry in column `j`).
/// `slot` (one per node, all 0 on entry and on return) maps a column to its place in
/// `acc` plus one.
fn row(op: &NormalOperator<'_>, j: usize, acc: &mut Vec<(u32, f64)>, slot: &mut [u32]) {
    let g: &Csr = op.graph;
    let (ln, lm) = (op.ln, op.lm);
    acc.clear();
    let mut add = |k: u32, v: f64| match slot[k as usize] {
        0 => {
            acc.push((k, v));
            slot[k as usize] = acc.len() as u32;
        }
        s => acc[s as usize - 1].1 += v,
    };
    add(j as u32, op.anchor2[j]);
    // `L_ij` for i = j (the diagonal) and for every neighbour i (entry j → i of the
    // transposed weights), in increasing i, then row i of `L`. Every term is
    // `a² (L_ij L_ik)` (a product of two f32 values, exact in f64), so `M_jk` and
    // `M_kj` sum the same terms in the same order: the stored `M` is exactly symmetric.
    let nb = &g.targets[g.offsets[j]..g.offsets[j + 1]];
    let split = nb.partition_point(|&i| (i as usize) < j);
    let entry = |e: usize| (g.targets[e] as usize, ln.weight_t[e], lm.weight_t[e]);
    let below = (g.offsets[j]..g.offsets[j] + split).map(entry);
    let above = (g.offsets[j] + split..g.offsets[j + 1]).map(entry);
    for (i, cn, cm) in below.chain(std::iter::once((j, ln.diagonal[j], lm.diagonal[j]))).chain(above) {
        let (cn, cm) = (cn as f64, cm as f64);
        if cn == 0.0 && cm == 0.0 {
            continue;
        }
        let term = |n: f32, m: f32| op.a2 * (cn * n as f64) + op.b2 * (cm * m as f64);
        add(i as u32, term(ln.diagonal[i], lm.diagonal[i]));
        for f in g.offsets[i]..g.offsets[i + 1] {
            add(g.targets[f], term(ln.weight[f], lm.weight[f]));
        }
    }
    for &(k, _) in acc.iter() {
        slot[k as usize] = 0;
    }
    acc.sort_unstable_by_key(|&(k, _)| k);
}

impl NormalMatrix {
    /// Assemble `M` of `op`.
    pub fn assemble(op: &NormalOperator<'_>) -> NormalMatrix {
        let n = op.graph.nodes();
        let block = n.div_ceil(MAX_BLOCKS).max(MIN_BLOCK);
        // Per worker: the column slots, a row accumulator and a stripe to build in, whose
        // contents are then copied to vectors of exactly their length (a stripe grown
        // in place would keep up to twice its size).
        let scratch = PerThread::new(|| (filled(n, 0u32), Vec::with_capacity(64), Stripe::new()));
        let mut diag = filled(n, 0.0);
        let stripes = diag
            .par_chunks_mut(ROW_BLOCK)
            .enumerate()
            .map(|(b, diag)| {
                scratch.with(|(slot, acc, stripe)| {
                    *stripe = Stripe::new();
                    for (t, d) in diag.iter_mut().enumerate() {
                        let j = b * ROW_BLOCK + t;
                        row(op, j, acc, slot);
                        // `M` is positive semi-definite, so a non-positive diagonal
                        // means an all-zero row and column (or an anchor below f32
                        // range): give it a unit diagonal, which keeps that node in
                        // place and the preconditioner positive definite.
                        let m = acc[acc.partition_point(|e| (e.0 as usize) < j)].1 as f32;
                        *d = if m.is_nan() || m <= 0.0 { 1.0 } else { m as f64 };
                        stripe.push_row(j, block, acc.iter().map(|e| (e.0, e.1 as f32)));
                    }
                    stripe.clone()
                })
            })
            .collect();
        NormalMatrix { diag, block, stripes }
    }

    /// Rows per Gauss–Seidel block.
    pub fn block(&self) -> usize {
        self.block
    }

    /// Use Gauss–Seidel blocks of `rows` rows (at least 1).
    pub fn set_block(&mut self, rows: usize) {
        let (n, block) = (self.rows(), rows.max(1));
        let stripes = (0..n.div_ceil(ROW_BLOCK))
            .into_par_iter()
            .map(|b| {
                let mut stripe = Stripe::new();
                for j in b * ROW_BLOCK..((b + 1) * ROW_BLOCK).min(n) {
                    stripe.push_row(j, block, self.entries(j).into_iter().map(|(k, v)| (k, v as f32)));
                }
                stripe
            })
            .collect();
        (self.block, self.stripes) = (block, stripes);
    }

    /// Number of rows.
    pub fn rows(&self) -> usize {
        self.diag.len()
    }

    /// Row `j`'s entries `(column, M_jk)` in increasing column order, its diagonal included.
    pub fn entries(&self, j: usize) -> Vec<(u32, f64)> {
        let (lower, _, e) = self.forward_row(j);
        let wide = |x: &[(u32, f32)]| x.iter().map(|&(k, v)| (k, v as f64)).collect::<Vec<_>>();
        let mut row = wide(&lower[..e]);
        row.push((j as u32, self.diag[j]));
        row.extend(wide(self.upper_entries(j)));
        row.extend(wide(&lower[e..]));
        debug_assert!(row.windows(2).all(|w| w[0].0 < w[1].0));
        row
    }

    /// Row `j`'s entries but the diagonal and the in-block upper ones, with the ends
    /// `b`, `e` of its earlier-block and in-block lower parts.
    #[inline]
    fn forward_row(&self, j: usize) -> (&[(u32, f32)], usize, usize) {
        let (s, t) = (&self.stripes[j / ROW_BLOCK], j % ROW_BLOCK);
        let [b, e] = s.cuts[t];
        (&s.lower[s.lower_at[t]..s.lower_at[t + 1]], b as usize, e as usize)
    }

    /// Row `j`'s in-block upper entries.
    #[inline]
    fn upper_entries(&self, j: usize) -> &[(u32, f32)] {
        let (s, t) = (&self.stripes[j / ROW_BLOCK], j % ROW_BLOCK);
        &s.upper[s.upper_at[t]..s.upper_at[t + 1]]
    }

    /// Row `j`'s in-block lower entries.
    #[inline]
    fn lower_entries(&self, j: usize) -> &[(u32, f32)] {
        let (lower, b, e) = self.forward_row(j);
        &lower[b..e]
    }

    /// `y = M x`, returning the per-coordinate dot products `x · y` (summed over
    /// fixed chunks in order).
    pub fn apply_dot(&self, x: &[V3], y: &mut [V3]) -> V3 {
        let parts: Vec<V3> = y
            .par_chunks_mut(CHUNK)
            .enumerate()
            .map(|(c, ys)| {
                let mut dot = [0.0; 3];
                for (t, yj) in ys.iter_mut().enumerate() {
                    let j = c * CHUNK + t;
                    let mut s = [0.0; 3];
                    for (k, m) in self.entries(j) {
                        for d in 0..3 {
                            s[d] += m * x[k as usize][d];
                        }
                    }
                    *yj = s;
                    for d in 0..3 {
                        dot[d] += x[j][d] * s[d];
                    }
                }
                dot
            })
            .collect();
        parts.iter().fold([0.0; 3], |a, s| [a[0] + s[0], a[1] + s[1], a[2] + s[2]])
    }

    /// Block symmetric Gauss–Seidel: `z = (D + U)⁻¹ D (D + L)⁻¹ r` with `L`, `D`,
    /// `U` the strictly lower, diagonal and strictly upper parts of the block-diagonal
    /// part of `M` (blocks of [`NormalMatrix::block`] rows). Symmetric positive
    /// definite (`D > 0`), so plain conjugate gradients stay valid. Returns `r · z` per
    /// coordinate, summed per block in order. The solver applies the same
    /// preconditioner in Eisenstat's form ([`NormalMatrix::forward`],
    /// [`NormalMatrix::backward`], [`NormalMatrix::forward_product`]); this explicit
    /// form is the reference its tests check against.
    pub fn sgs_dot(&self, r: &[V3], z: &mut [V3]) -> V3 {
        let bs = self.block;
        z.copy_from_slice(r);
        self.forward(z);
        let parts: Vec<V3> = z
            .par_chunks_mut(bs)
            .enumerate()
            .map(|(b, zs)| {
                let lo = b * bs;
                let hi = lo + zs.len();
                // Backward: (D + U) z = D y, i.e. z_j = y_j - (U z)_j / D_j.
                let mut dot = [0.0; 3];
                for j in (lo..hi).rev() {
                    let s = gather_local(self.upper_entries(j), zs, lo, [0.0; 3], 1.0);
                    let inv = 1.0 / self.diag[j];
                    let zj = &mut zs[j - lo];
                    for c in 0..3 {
                        zj[c] -= s[c] * inv;
                        dot[c] += r[j][c] * zj[c];
                    }
                }
                dot
            })
            .collect();
        parts.iter().fold([0.0; 3], |a, s| [a[0] + s[0], a[1] + s[1], a[2] + s[2]])
    }

    /// `y ← (D + L)⁻¹ y` (block lower triangular solve, in place: row `j` reads its own
    /// right-hand side before it writes, and earlier rows are solved by then).
    pub fn forward(&self, y: &mut [V3]) {
        let bs = self.block;
        y.par_chunks_mut(bs).enumerate().for_each(|(b, ys)| {
            let lo = b * bs;
            for j in lo..lo + ys.len() {
                let t = gather_local(self.lower_entries(j), ys, lo, ys[j - lo], -1.0);
                let inv = 1.0 / self.diag[j];
                ys[j - lo] = [t[0] * inv, t[1] * inv, t[2] * inv];
            }
        });
    }

    /// Eisenstat's first half, with the previous iteration's update folded in: per row
    /// `x += step s`, `y -= step w` (the new residual's forward solve), `ŝ ← D y + beta ŝ`,
    /// then `s = (D + U)⁻¹ ŝ` (block upper triangular solve), so that `s = z + beta s_old`
    /// for the Gauss–Seidel `z` of the new residual.
    pub fn backward(&self, k: &mut Krylov, step: V3, beta: V3) {
        let bs = self.block;
        let Krylov { x, y, hat, s, w } = k;
        x.par_chunks_mut(bs)
            .zip(y.par_chunks_mut(bs))
            .zip(hat.par_chunks_mut(bs).zip(s.par_chunks_mut(bs)))
            .zip(w.par_chunks(bs))
            .enumerate()
            .for_each(|(b, (((xs, ys), (hs, ss)), ws))| {
                let lo = b * bs;
                for j in (lo..lo + ss.len()).rev() {
                    let t = j - lo;
                    let dj = self.diag[j];
                    for c in 0..3 {
                        xs[t][c] += step[c] * ss[t][c];
                        ys[t][c] -= step[c] * ws[t][c];
                        hs[t][c] = dj * ys[t][c] + beta[c] * hs[t][c];
                    }
                    let u = gather_local(self.upper_entries(j), ss, lo, hs[t], -1.0);
                    let inv = 1.0 / dj;
                    ss[t] = [u[0] * inv, u[1] * inv, u[2] * inv];
                }
            });
    }

    /// Eisenstat's second half, one pass over the lower and off-block entries:
    /// `q = M s = ŝ + (L + E) s` (with `(D + U) s = ŝ`, `E` the entries outside the
    /// blocks) and `w = (D + L)⁻¹ q`, without storing `q`. Returns, per coordinate and
    /// summed per block in order, `[s · q, y · D y, w · D y, w · D w]`: the step's
    /// denominator, `r · z` of the current residual, and what `r · z` of the next one
    /// (forward solve `y - step w`) needs.
    pub fn forward_product(&self, k: &mut Krylov) -> [V3; 4] {
        let bs = self.block;
        let Krylov { y, hat, s, w, .. } = k;
        let (y, hat, s) = (&*y, &*hat, &*s);
        let parts: Vec<[V3; 4]> = w
            .par_chunks_mut(bs)
            .enumerate()
            .map(|(b, ws)| {
                let lo = b * bs;
                let mut dots = [[0.0; 3]; 4];
                for j in lo..lo + ws.len() {
                    let (row, b, e) = self.forward_row(j);
                    let mut qj = gather(&row[..b], s, hat[j]);
                    let mut wj = [0.0; 3];
                    for &(k, m) in &row[b..e] {
                        let (k, m) = (k as usize, m as f64);
                        let (sk, wk) = (&s[k], &ws[k - lo]);
                        for c in 0..3 {
                            qj[c] += m * sk[c];
                            wj[c] += m * wk[c];
                        }
                    }
                    let qj = gather(&row[e..], s, qj);
                    let dj = self.diag[j];
                    let inv = 1.0 / dj;
                    for c in 0..3 {
                        wj[c] = (qj[c] - wj[c]) * inv;
                        let (dy, dw) = (dj * y[j][c], dj * wj[c]);
                        dots[0][c] += s[j][c] * qj[c];
                        dots[1][c] += dy * y[j][c];
                        dots[2][c] += dw * y[j][c];
                        dots[3][c] += dw * wj[c];
                    }
                    ws[j - lo] = wj;
                }
                dots
            })
            .collect();
        parts.iter().fold([[0.0; 3]; 4], |a, p| std::array::from_fn(|t| std::array::from_fn(|c| a[t][c] + p[t][c])))
    }
}

/// The vectors of the preconditioned conjugate-gradient iteration in Eisenstat's form,
/// one entry per row of `M`.
pub struct Krylov {
    /// The solution so far.
    pub x: Vec<V3>,
    /// `y = (D + L)⁻¹ r` of the current residual `r` (so `r · z = y · D y`).
    pub y: Vec<V3>,
    /// `ŝ = (D + U) s`.
    pub hat: Vec<V3>,
    /// The search direction `s`.
    pub s: Vec<V3>,
    /// `w = (D + L)⁻¹ M s`.
    pub w: Vec<V3>,
}

impl Krylov {
    /// The state at `x = 0` for the right-hand side `r`: `y = (D + L)⁻¹ r` (in `r`'s
    /// place, so the two never both exist), the rest zero.
    pub fn start(m: &NormalMatrix, r: Vec<V3>) -> Krylov {
        let n = r.len();
        let mut y = r;
        m.forward(&mut y);
        let zero = || filled(n, [0.0; 3]);
        Krylov { x: zero(), y, hat: zero(), s: zero(), w: zero() }
    }
}

/// `acc + sign * sum_k m_jk x_k` over entries in a block whose values `x` start at row `lo`.
#[inline]
fn gather_local(entries: &[(u32, f32)], x: &[V3], lo: usize, mut acc: V3, sign: f64) -> V3 {
    for &(k, m) in entries {
        let (m, xk) = (m as f64, &x[k as usize - lo]);
        for c in 0..3 {
            acc[c] += sign * (m * xk[c]);
        }
    }
    acc
}
