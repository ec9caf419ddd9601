//! The assembled normal matrix of eq. 8 and its block symmetric Gauss–Seidel
//! preconditioner, used by the contraction solve (docs/method.md §2.4).
//!
//! `M = alpha² LnᵀLn + beta² LmᵀLm + Wg²` couples nodes up to two hops apart (about
//! 21 entries per row on a 6-connected grid, of which about 11.4 are stored: each
//! in-block symmetric pair once). Assembled once per contraction iteration, one
//! preconditioned iteration reads each stored entry about twice for the three
//! coordinates, which is less memory traffic than the matrix-free `Lᵀ(L x)` (four
//! passes over the CSR weights and two scratch vectors), and it makes a Gauss–Seidel
//! preconditioner possible: symmetric Gauss–Seidel on `M` cuts the conjugate-gradient
//! iterations of the first contraction iteration about 2.5× against Jacobi, the
//! largest cut per product we measured (smoothed-aggregation multigrid cut iterations
//! further but costs more products per iteration; see the solver's notes).
//!
//! Parallelism without a thread-dependent result: the rows are split into fixed
//! contiguous blocks (their number depends only on the node count), each block is
//! swept sequentially ignoring its coupling to other blocks (block Jacobi with
//! symmetric Gauss–Seidel inside), and every reduction sums fixed chunks in order.
//! The rows are in node order, or in slabs along the volume's axis with the most voxel
//! layers ([`slab_order`]), so that few rows couple to other blocks: on a 23 × 512 ×
//! 512 two-photon stack this cuts the first iteration's 45 conjugate-gradient
//! iterations to 39 and the whole run by ~15 %.

use crate::grid::{filled, Csr, PerThread, ROW_BLOCK};
use crate::laplacian::NormalOperator;
use rayon::prelude::*;
use std::ops::Range;

pub type V3 = [f64; 3];

/// A triple stored in `f32`: the conjugate-gradient vectors other than the solution.
pub type F3 = [f32; 3];

/// A vector entry read and written as `f64` whatever its storage (`V3` or [`F3`]):
/// arithmetic is always `f64`, and an `F3` rounds once when stored.
pub trait Triple: Copy + Send + Sync {
    fn get(&self) -> V3;
    fn set(&mut self, v: V3);
}

impl Triple for V3 {
    #[inline(always)]
    fn get(&self) -> V3 {
        *self
    }
    #[inline(always)]
    fn set(&mut self, v: V3) {
        *self = v;
    }
}

impl Triple for F3 {
    #[inline(always)]
    fn get(&self) -> V3 {
        self.map(f64::from)
    }
    #[inline(always)]
    fn set(&mut self, v: V3) {
        *self = v.map(|t| t as f32);
    }
}

/// Per-block partial sums added in block order, so the total does not depend on the
/// thread count.
pub fn sum_parts(parts: &[V3]) -> V3 {
    parts.iter().fold([0.0; 3], |a, p| [a[0] + p[0], a[1] + p[1], a[2] + p[2]])
}

/// Fewest rows in a Gauss–Seidel block (thin blocks lose coupling and iterations grow).
const MIN_BLOCK: usize = 32_768;
/// Most Gauss–Seidel blocks: enough to balance a few threads.
const MAX_BLOCKS: usize = 16;

/// `M`, stored for the Gauss–Seidel sweeps. Its rows are cut into fixed contiguous
/// blocks; row `j` of block `[lo, hi)` has entries in other blocks (`k < lo` or
/// `k >= hi`), in-block lower entries (`lo <= k < j`), the diagonal and in-block upper
/// entries (`j < k < hi`). `M` is exactly symmetric (see `row`), so only one of each
/// in-block pair is stored: row `j`'s in-block lower entries are the upper entries
/// `M_kj` of the rows `k < j` of its block. The backward sweep reads the upper entries
/// row by row; the forward sweeps read them column by column (once row `k` is solved,
/// it adds its part to the rows after it), which streams the same array in the same
/// order. Entries in other blocks are stored in both their rows. Each kind is stored on
/// its own, row after row in increasing column order: every sweep streams its arrays
/// front to back, skipping nothing. Values are `f32`, like the Laplacian weights they
/// are built from (the diagonal too); arithmetic is `f64`. Entries in other blocks are
/// (column, value) pairs; the in-block upper entries, most of `M`, keep their columns
/// as the distance `k - j` from their row, in `u16` wherever a stripe's rows reach no
/// further (6 bytes an entry instead of 8: on the 256³ bed 20 bytes less per node at
/// the run's peak), else in `u32`.
///
/// The rows are kept in stripes of up to [`ROW_BLOCK`] rows, each built by one parallel
/// task and never copied: no serial concatenation, and the pages of each stripe are
/// first touched by the thread that builds it. A stripe has few enough rows that its
/// entry offsets fit in `u32` (see [`stripe_shift`]).
#[derive(Debug, Clone, Default)]
pub struct NormalMatrix {
    /// The diagonal `D_j = M_jj` (as stored), positive.
    pub diag: Vec<f32>,
    /// Rows per Gauss–Seidel block (the last block may be shorter).
    block: usize,
    /// The largest `k - j` of an in-block upper entry `M_jk` (0 if none).
    reach: usize,
    /// Rows `s << shift..` in stripe `s`.
    stripes: Vec<Stripe>,
    shift: u32,
}

/// Consecutive rows of `M` without their diagonal and in-block lower entries.
#[derive(Debug, Clone, Default)]
struct Stripe {
    /// Row `t`'s entries in other blocks: `outer[outer_at[t]..outer_at[t + 1]]`.
    outer: Vec<(u32, f32)>,
    outer_at: Vec<u32>,
    /// Row `t`'s in-block upper entries: columns `j + ahead[e]` and values
    /// `upper[e]` for `e` in `upper_at[t]..upper_at[t + 1]`.
    ahead: Ahead,
    upper: Vec<f32>,
    upper_at: Vec<u32>,
    /// The largest `k - j` of its rows' upper entries.
    reach: usize,
}

/// The columns of a stripe's in-block upper entries as distances `k - j` from their
/// row `j`: `u16` when every one fits.
#[derive(Debug, Clone)]
enum Ahead {
    Near(Vec<u16>),
    Far(Vec<u32>),
}

impl Default for Ahead {
    fn default() -> Ahead {
        Ahead::Far(Vec::new())
    }
}

/// One row's in-block upper entries (see [`Ahead`]).
#[derive(Clone, Copy)]
enum Upper<'a> {
    Near(&'a [u16], &'a [f32]),
    Far(&'a [u32], &'a [f32]),
}

impl Upper<'_> {
    /// `f(k, M_jk)` for the entries of row `j`, in increasing `k`.
    #[inline(always)]
    fn each(self, j: usize, mut f: impl FnMut(usize, f64)) {
        match self {
            Upper::Near(d, v) => d.iter().zip(v).for_each(|(&d, &m)| f(j + d as usize, m as f64)),
            Upper::Far(d, v) => d.iter().zip(v).for_each(|(&d, &m)| f(j + d as usize, m as f64)),
        }
    }
}

impl Stripe {
    fn new() -> Stripe {
        Stripe { outer_at: vec![0], upper_at: vec![0], ..Stripe::default() }
    }

    /// Empty it for the next stripe, keeping its buffers: a worker builds every stripe
    /// in the same scratch without growing it again.
    fn clear(&mut self) {
        let Ahead::Far(ahead) = &mut self.ahead else { unreachable!("a stripe is built with u32 columns") };
        ahead.clear();
        for v in [&mut self.outer_at, &mut self.upper_at] {
            v.clear();
            v.push(0);
        }
        self.outer.clear();
        self.upper.clear();
        self.reach = 0;
    }

    /// Append row `j` (entries in increasing column order) of a matrix in Gauss–Seidel
    /// blocks of `block` rows: its entries in other blocks and its in-block upper ones.
    /// The columns are built as [`Ahead::Far`]; see [`Stripe::compact`].
    fn push_row(&mut self, j: usize, block: usize, row: impl Iterator<Item = (u32, f32)>) {
        let (lo, hi) = (j / block * block, (j / block + 1) * block);
        let Ahead::Far(ahead) = &mut self.ahead else { unreachable!("a stripe is built with u32 columns") };
        for (k, v) in row {
            let col = k as usize;
            if col < lo || col >= hi {
                self.outer.push((k, v));
            } else if col > j {
                // `col - j < block`, and blocks have fewer than 2³² rows.
                ahead.push((col - j) as u32);
                self.upper.push(v);
                self.reach = self.reach.max(col - j);
            }
        }
        // In range: see `stripe_shift`.
        self.outer_at.push(self.outer.len() as u32);
        self.upper_at.push(self.upper.len() as u32);
    }

    /// A copy of exactly its length, with `u16` columns if they fit (a stripe grown in
    /// place would keep up to twice its size).
    fn compact(&self) -> Stripe {
        let ahead = match &self.ahead {
            Ahead::Far(d) if self.reach <= u16::MAX as usize => Ahead::Near(d.iter().map(|&d| d as u16).collect()),
            far => far.clone(),
        };
        Stripe {
            outer: self.outer.clone(),
            outer_at: self.outer_at.clone(),
            ahead,
            upper: self.upper.clone(),
            upper_at: self.upper_at.clone(),
            reach: self.reach,
        }
    }

    /// Row `t`'s in-block upper entries.
    #[inline(always)]
    fn upper(&self, t: usize) -> Upper<'_> {
        let at = self.upper_at[t] as usize..self.upper_at[t + 1] as usize;
        match &self.ahead {
            Ahead::Near(d) => Upper::Near(&d[at.clone()], &self.upper[at]),
            Ahead::Far(d) => Upper::Far(&d[at.clone()], &self.upper[at]),
        }
    }
}

/// The axis order of [`slab_order`] for a volume of `shape` voxels, unless the node
/// order already runs slowest along the axis with the most voxel layers (axis 0 the
/// longest, ties to the lower axis): that axis first, then the other two in order.
/// The Gauss–Seidel blocks are contiguous rows, so in node order a flat stack (e.g.
/// 23 × 512 × 512) cuts them across its few thick layers and most rows couple to
/// other blocks; in slabs along the longest axis only the rows near a slab's faces
/// do.
pub fn slab_axes(shape: [usize; 3]) -> Option<[usize; 3]> {
    let slow = (0..3).fold(0, |best, d| if shape[d] > shape[best] { d } else { best });
    let mut rest = (0..3).filter(|&d| d != slow);
    (slow != 0).then(|| [slow, rest.next().unwrap_or(0), rest.next().unwrap_or(0)])
}

/// Rows of `M` in slabs along `axes[0]`: the nodes ordered by their cell
/// (`round(p / c)`) along `axes[0]`, then `axes[1]`, `axes[2]`, then node index.
pub fn slab_order(positions: &[V3], c: f64, axes: [usize; 3]) -> Vec<u32> {
    // Cells lie within ±2^20 (the decimation's limit), so `i32` holds them.
    let mut keyed: Vec<([i32; 3], u32)> =
        positions.par_iter().enumerate().map(|(i, p)| (axes.map(|d| (p[d] / c).round() as i32), i as u32)).collect();
    keyed.par_sort_unstable();
    keyed.into_par_iter().map(|(_, i)| i).collect()
}

/// `v[a] = v[order[a]]` for every `a` at once (the rows of [`slab_order`] from node
/// order), in place: a copy would hold the positions twice at the contraction's peak.
/// `order` must be a permutation of `0..v.len()`.
pub fn gather_in_place<T: Copy>(v: &mut [T], order: &[u32]) {
    let mut done = vec![false; v.len()];
    for a in 0..v.len() {
        let (first, mut x) = (v[a], a);
        // Each cycle of the permutation once; a node is written once.
        while !done[x] {
            done[x] = true;
            let next = order[x] as usize;
            v[x] = if next == a { first } else { v[next] };
            x = next;
        }
    }
}

/// `v[order[a]] = v[a]` for every `a` at once (back to node order from
/// [`slab_order`]'s), in place. `order` must be a permutation of `0..v.len()`.
pub fn scatter_in_place<T: Copy>(v: &mut [T], order: &[u32]) {
    let mut done = vec![false; v.len()];
    for a in 0..v.len() {
        let (mut carry, mut x) = (v[a], order[a] as usize);
        while !done[x] {
            done[x] = true;
            carry = std::mem::replace(&mut v[x], carry);
            x = order[x] as usize;
        }
    }
}

/// Rows per stripe of `M` as a power of two `1 << shift`: [`ROW_BLOCK`], or fewer if
/// a stripe's entry count could then pass `u32::MAX` ([`longest_row`] entries a row).
fn stripe_shift(graph: &Csr) -> u32 {
    let rows = (u32::MAX as u64 / longest_row(graph) as u64).clamp(1, ROW_BLOCK as u64);
    rows.ilog2()
}

/// A bound on the entries of a row of `M`: at most `min(n, (d + 1)²)` for the largest
/// degree `d` of `graph` (its columns are its nodes within two hops), at least 1.
fn longest_row(graph: &Csr) -> usize {
    let degree = (0..graph.nodes()).map(|i| graph.neighbours(i).len()).max().unwrap_or(0);
    graph.nodes().min((degree + 1).saturating_mul(degree + 1)).max(1)
}

/// `acc + sum_k m_jk x_k` over the given entries of a row.
#[inline]
fn gather<T: Triple>(entries: &[(u32, f32)], x: &[T], mut acc: V3) -> V3 {
    for &(k, m) in entries {
        let (m, xk) = (m as f64, x[k as usize].get());
        for c in 0..3 {
            acc[c] += m * xk[c];
        }
    }
    acc
}

/// One row of `M` being summed: its entries `(column, value)` in the order of their
/// first term, and an open-addressing table from column to place in `acc` (sized for
/// the longest row, so a worker's scratch does not grow with the node count).
struct RowSum {
    acc: Vec<(u32, f64)>,
    /// Place in `acc` plus one, 0 for free; `1 << bits` long.
    table: Vec<u32>,
    bits: u32,
    /// The table slots in use, freed after each row.
    used: Vec<u32>,
}

impl RowSum {
    /// Scratch for rows of at most `entries` entries.
    fn new(entries: usize) -> RowSum {
        let size = (2 * entries).next_power_of_two().max(16);
        RowSum { acc: Vec::with_capacity(64), table: vec![0; size], bits: size.ilog2(), used: Vec::with_capacity(64) }
    }

    /// Add `v` to the entry of column `k`. Each entry sums its terms in the order they
    /// come, whatever the table's layout.
    #[inline]
    fn add(&mut self, k: u32, v: f64) {
        let mask = self.table.len() - 1;
        // Fibonacci hashing: the top bits of `k` times 2⁶⁴ over the golden ratio.
        let mut h = ((k as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> (64 - self.bits)) as usize;
        loop {
            match self.table[h] {
                0 => {
                    self.acc.push((k, v));
                    self.table[h] = self.acc.len() as u32;
                    self.used.push(h as u32);
                    return;
                }
                s if self.acc[s as usize - 1].0 == k => {
                    self.acc[s as usize - 1].1 += v;
                    return;
                }
                _ => h = (h + 1) & mask,
            }
        }
    }

    /// Empty the table for the next row, keeping `acc`.
    fn reset(&mut self) {
        for &h in &self.used {
            self.table[h as usize] = 0;
        }
        self.used.clear();
    }
}

/// Row `j` of `M` into `sum.acc`, sorted by column:
/// `M_jk = sum_i (a² Ln_ij Ln_ik + b² Lm_ij Lm_ik) + [j = k] Wg_j²`,
/// `i` over `j` and its neighbours (the rows of `L` with an entry in column `j`).
/// Columns are numbered by `rank` (node `k` is column `rank[k]`; `None`: by node), and
/// columns in `skip` are left out (each entry's value does not depend on which others
/// are computed).
fn row(op: &NormalOperator<'_>, j: usize, rank: Option<&[u32]>, skip: Range<u32>, sum: &mut RowSum) {
    let g: &Csr = op.graph;
    let (ln, lm) = (op.ln, op.lm);
    sum.acc.clear();
    // Node `k`'s column, unless it is skipped (then its term is not computed).
    let column = |k: u32| Some(rank.map_or(k, |r| r[k as usize])).filter(|k| !skip.contains(k));
    if let Some(k) = column(j as u32) {
        sum.add(k, op.anchor2(j));
    }
    // `L_ij` for i = j (the diagonal) and for every neighbour i (row i's weight for
    // j), in increasing i, then row i of `L`. Every term is `a² (L_ij L_ik)` (a
    // product of two f32 values, exact in f64), so `M_jk` and `M_kj` sum the same terms
    // in the same order: the stored `M` is exactly symmetric.
    let nb = g.neighbours(j);
    let split = nb.partition_point(|&i| (i as usize) < j);
    let entry = |&i: &u32| {
        let i = i as usize;
        (i, ln.weight(i, j), lm.weight(i, j))
    };
    let (below, above) = (nb[..split].iter().map(entry), nb[split..].iter().map(entry));
    for (i, cn, cm) in below.chain(std::iter::once((j, ln.diagonal(j), lm.diagonal(j)))).chain(above) {
        let (cn, cm) = (cn as f64, cm as f64);
        if cn == 0.0 && cm == 0.0 {
            continue;
        }
        let term = |n: f32, m: f32| op.a2 * (cn * n as f64) + op.b2 * (cm * m as f64);
        if let Some(k) = column(i as u32) {
            sum.add(k, term(ln.diagonal(i), lm.diagonal(i)));
        }
        for &t in g.neighbours(i) {
            if let Some(k) = column(t) {
                let t = t as usize;
                sum.add(k, term(ln.weight(i, t), lm.weight(i, t)));
            }
        }
    }
    sum.reset();
    sum.acc.sort_unstable_by_key(|&(k, _)| k);
}

impl NormalMatrix {
    /// Assemble `M` of `op` with its rows and columns in `order` (row `a` is node
    /// `order[a]`; `None`: in node order), in Gauss–Seidel blocks whose size depends on
    /// the row count alone.
    pub fn assemble(op: &NormalOperator<'_>, order: Option<&[u32]>) -> NormalMatrix {
        let n = op.graph.nodes();
        NormalMatrix::assemble_in_blocks(op, n.div_ceil(MAX_BLOCKS).max(MIN_BLOCK), order)
    }

    /// [`NormalMatrix::assemble`] in Gauss–Seidel blocks of `block` rows (at least 1).
    pub fn assemble_in_blocks(op: &NormalOperator<'_>, block: usize, order: Option<&[u32]>) -> NormalMatrix {
        let (n, block) = (op.graph.nodes(), block.max(1));
        let rank = order.map(|order| {
            let mut rank = filled(n, 0u32);
            for (a, &j) in order.iter().enumerate() {
                rank[j as usize] = a as u32;
            }
            rank
        });
        // Per worker: a row's sum and a stripe to build in, whose contents are then
        // copied ([`Stripe::compact`]).
        let longest = longest_row(op.graph);
        let scratch = PerThread::new(move || (RowSum::new(longest), Stripe::new()));
        let mut diag = filled(n, 0.0f32);
        let shift = stripe_shift(op.graph);
        let stripes: Vec<Stripe> = diag
            .par_chunks_mut(1 << shift)
            .enumerate()
            .map(|(b, diag)| {
                scratch.with(|(sum, stripe)| {
                    stripe.clear();
                    // A run asked to stop ([`crate::cancel`]) discards the matrix.
                    if crate::cancel::requested() {
                        return Stripe::new();
                    }
                    for (t, d) in diag.iter_mut().enumerate() {
                        let j = (b << shift) + t;
                        let node = order.map_or(j, |o| o[j] as usize);
                        // The in-block lower entries are not stored (the rows before
                        // hold them), so they are not computed either.
                        row(op, node, rank.as_deref(), (j / block * block) as u32..j as u32, sum);
                        let acc = &sum.acc;
                        // `M` is positive semi-definite, so a non-positive diagonal
                        // means an all-zero row and column (or an anchor below f32
                        // range): give it a unit diagonal, which keeps that node in
                        // place and the preconditioner positive definite.
                        let m = acc[acc.partition_point(|e| (e.0 as usize) < j)].1 as f32;
                        *d = if m.is_nan() || m <= 0.0 { 1.0 } else { m };
                        stripe.push_row(j, block, acc.iter().map(|e| (e.0, e.1 as f32)));
                    }
                    stripe.compact()
                })
            })
            .collect();
        let reach = stripes.iter().map(|s| s.reach).max().unwrap_or(0);
        NormalMatrix { diag, block, reach, stripes, shift }
    }

    /// Number of rows.
    pub fn rows(&self) -> usize {
        self.diag.len()
    }

    /// Entries stored, the diagonal included (each in-block pair once).
    #[cfg(test)]
    pub fn stored_entries(&self) -> usize {
        self.rows() + self.stripes.iter().map(|s| s.outer.len() + s.upper.len()).sum::<usize>()
    }

    /// The stripe holding row `j`, and the row's place in it.
    #[inline(always)]
    fn stripe_of(&self, j: usize) -> (&Stripe, usize) {
        (&self.stripes[j >> self.shift], j & ((1 << self.shift) - 1))
    }

    /// Row `j`'s entries in other Gauss–Seidel blocks.
    #[inline]
    fn outer_entries(&self, j: usize) -> &[(u32, f32)] {
        let (s, t) = self.stripe_of(j);
        &s.outer[s.outer_at[t] as usize..s.outer_at[t + 1] as usize]
    }

    /// Row `j`'s in-block upper entries.
    #[inline(always)]
    fn upper_entries(&self, j: usize) -> Upper<'_> {
        let (s, t) = self.stripe_of(j);
        s.upper(t)
    }

    /// `y = M x`, returning the per-coordinate dot products `x · y` (summed per block in
    /// order). The reference product for tests and measurements; the solver needs none.
    pub fn apply_dot(&self, x: &[V3], y: &mut [V3]) -> V3 {
        let bs = self.block;
        let parts: Vec<V3> = y
            .par_chunks_mut(bs)
            .enumerate()
            .map(|(b, ys)| {
                let lo = b * bs;
                ys.fill([0.0; 3]);
                // Row `j`'s in-block lower part has arrived from the rows before it.
                for j in lo..lo + ys.len() {
                    let own = gather_upper(self.upper_entries(j), j, x, 0, x[j].map(|v| self.diag[j] as f64 * v), 1.0);
                    let own = gather(self.outer_entries(j), x, own);
                    let yj = &mut ys[j - lo];
                    *yj = std::array::from_fn(|c| yj[c] + own[c]);
                    scatter(self.upper_entries(j), j, ys, lo, usize::MAX, x[j], 1.0);
                }
                let mut dot = [0.0; 3];
                for (yj, xj) in ys.iter().zip(&x[lo..]) {
                    for c in 0..3 {
                        dot[c] += xj[c] * yj[c];
                    }
                }
                dot
            })
            .collect();
        sum_parts(&parts)
    }

    /// The right-hand side of the displacement system at the positions `p`,
    /// `r = Wg² p - M p`. The rows of `M - Wg² = alpha² LnᵀLn + beta² LmᵀLm` sum to zero
    /// (those of the Laplacians do), so `r_j = sum_(k != j) M_jk (p_j - p_k)`: from the
    /// stored off-diagonal entries alone, translation-invariant (differences of
    /// positions at most two hops apart, never absolute coordinates), and without the
    /// Laplacians, which the caller can free first. Thread-independent, like
    /// [`NormalMatrix::apply_dot`]. The solve never stores it: it starts from
    /// [`NormalMatrix::displacement_forward`], which makes it block by block, and this
    /// whole vector is the reference the tests check that against.
    pub fn displacement_rhs(&self, p: &[V3]) -> Vec<V3> {
        let mut r = filled(self.rows(), [0.0; 3]);
        r.par_chunks_mut(self.block).enumerate().for_each(|(b, rs)| self.displacement_rhs_block(p, b, rs));
        r
    }

    /// `(D + L)⁻¹ r` of the displacement system's right-hand side `r` at the positions
    /// `p`, rounded to `f32`: the start of [`Krylov`]. Both factors are block-local, so
    /// each block's `r` is made and solved in a buffer of its own (the same arithmetic
    /// as [`NormalMatrix::displacement_rhs`] then [`NormalMatrix::forward`]) and no
    /// vector of `r` for every row is ever stored.
    pub fn displacement_forward(&self, p: &[V3]) -> Vec<F3> {
        let mut y = filled(self.rows(), [0.0f32; 3]);
        y.par_chunks_mut(self.block).enumerate().for_each_init(Vec::new, |rs, (b, ys)| {
            rs.clear();
            rs.resize(ys.len(), [0.0; 3]);
            self.displacement_rhs_block(p, b, rs);
            self.forward_block(b, rs);
            for (y, r) in ys.iter_mut().zip(rs.iter()) {
                *y = r.map(|t| t as f32);
            }
        });
        y
    }

    /// Block `b`'s rows of [`NormalMatrix::displacement_rhs`], into `rs` (zero).
    fn displacement_rhs_block(&self, p: &[V3], b: usize, rs: &mut [V3]) {
        let lo = b * self.block;
        for j in lo..lo + rs.len() {
            let pj = p[j];
            // Row `j`'s in-block lower part has arrived from the rows before it; each
            // upper entry also sends row `k` its part.
            let mut acc = rs[j - lo];
            self.upper_entries(j).each(j, |k, m| {
                for c in 0..3 {
                    acc[c] += m * (pj[c] - p[k][c]);
                    rs[k - lo][c] += m * (p[k][c] - pj[c]);
                }
            });
            for &(k, m) in self.outer_entries(j) {
                let (m, pk) = (m as f64, &p[k as usize]);
                for c in 0..3 {
                    acc[c] += m * (pj[c] - pk[c]);
                }
            }
            rs[j - lo] = acc;
        }
    }

    /// Block symmetric Gauss–Seidel: `z = (D + U)⁻¹ D (D + L)⁻¹ r` with `L`, `D`,
    /// `U` the strictly lower, diagonal and strictly upper parts of the block-diagonal
    /// part of `M` (blocks of `block` rows). Symmetric positive definite (`D > 0`), so
    /// plain conjugate gradients stay valid. Returns `r · z` per coordinate, summed per
    /// block in order. The solver applies the same preconditioner in Eisenstat's form
    /// ([`NormalMatrix::forward`], [`NormalMatrix::backward`],
    /// [`NormalMatrix::forward_product`]); this explicit form is the reference its tests
    /// check against.
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
                    let s = gather_upper(self.upper_entries(j), j, zs, lo, [0.0; 3], 1.0);
                    let inv = 1.0 / self.diag[j] as f64;
                    let zj = &mut zs[j - lo];
                    for c in 0..3 {
                        zj[c] -= s[c] * inv;
                        dot[c] += r[j][c] * zj[c];
                    }
                }
                dot
            })
            .collect();
        sum_parts(&parts)
    }

    /// `y ← (D + L)⁻¹ y` (block lower triangular solve, in place, column by column:
    /// once row `j` is solved, its in-block upper entries `M_jk = L_kj` take their part
    /// from the rows `k` after it, so each row has all of its part when its turn comes).
    pub fn forward(&self, y: &mut [V3]) {
        y.par_chunks_mut(self.block).enumerate().for_each(|(b, ys)| self.forward_block(b, ys));
    }

    /// Block `b`'s part of [`NormalMatrix::forward`], in place.
    fn forward_block(&self, b: usize, ys: &mut [V3]) {
        let lo = b * self.block;
        for j in lo..lo + ys.len() {
            let inv = 1.0 / self.diag[j] as f64;
            let yj = ys[j - lo].map(|t| t * inv);
            ys[j - lo] = yj;
            scatter(self.upper_entries(j), j, ys, lo, usize::MAX, yj, -1.0);
        }
    }

    /// Eisenstat's first half, with the previous iteration's update of `x` folded in:
    /// per row `x += step s`, `ŝ ← D y + beta ŝ`, then `s = (D + U)⁻¹ ŝ` (block upper
    /// triangular solve), so that `s = z + beta s_old` for the Gauss–Seidel `z` of the
    /// current residual. Returns, per coordinate and summed per block in order,
    /// `[s · ŝ, s · U s]`.
    pub fn backward(&self, k: &mut Krylov, step: V3, beta: V3) -> [V3; 2] {
        let bs = self.block;
        let Krylov { x, y, hat, s, .. } = k;
        let y = &*y;
        let parts: Vec<[V3; 2]> = x
            .par_chunks_mut(bs)
            .zip(hat.par_chunks_mut(bs).zip(s.par_chunks_mut(bs)))
            .enumerate()
            .map(|(b, (xs, (hs, ss)))| {
                let lo = b * bs;
                let mut dots = [[0.0; 3]; 2];
                for j in (lo..lo + ss.len()).rev() {
                    let t = j - lo;
                    let dj = self.diag[j] as f64;
                    let (s_old, h_old, yj) = (ss[t].get(), hs[t].get(), y[j].get());
                    for c in 0..3 {
                        xs[t][c] += step[c] * s_old[c];
                    }
                    hs[t].set(std::array::from_fn(|c| dj * yj[c] + beta[c] * h_old[c]));
                    let h = hs[t].get();
                    let u = gather_upper(self.upper_entries(j), j, ss, lo, h, -1.0);
                    let inv = 1.0 / dj;
                    ss[t].set([u[0] * inv, u[1] * inv, u[2] * inv]);
                    let sj = ss[t].get();
                    for c in 0..3 {
                        dots[0][c] += sj[c] * h[c];
                        // `(U s)_j = ŝ_j - u_j`.
                        dots[1][c] += sj[c] * (h[c] - u[c]);
                    }
                }
                dots
            })
            .collect();
        parts.iter().fold([[0.0; 3]; 2], |a, p| std::array::from_fn(|t| std::array::from_fn(|c| a[t][c] + p[t][c])))
    }

    /// `s · E s` per coordinate (`E` the entries in other blocks), summed per block in
    /// order: the last term of the step's denominator
    /// `s · M s = s · ŝ + s · U s + s · E s` (`s · L s = s · U s`, `M` being symmetric).
    pub fn outer_product(&self, s: &[F3]) -> V3 {
        let parts: Vec<V3> = s
            .par_chunks(self.block)
            .enumerate()
            .map(|(b, ss)| {
                let lo = b * self.block;
                let mut dot = [0.0; 3];
                for (j, sj) in (lo..).zip(ss) {
                    // Most rows have no entry in another block: nothing to add.
                    let outer = self.outer_entries(j);
                    if outer.is_empty() {
                        continue;
                    }
                    let (e, sj) = (gather(outer, s, [0.0; 3]), sj.get());
                    for c in 0..3 {
                        dot[c] += sj[c] * e[c];
                    }
                }
                dot
            })
            .collect();
        sum_parts(&parts)
    }

    /// Eisenstat's second half, one pass over the entries, with the step known: the
    /// residual's forward solve `y -= step w` for `w = (D + L)⁻¹ M s`, where
    /// `M s = ŝ + (L + E) s` (`(D + U) s = ŝ`), i.e. `D w = ŝ + E s - L (w - s)`,
    /// solved column by column like [`NormalMatrix::forward`]. `w` is never stored:
    /// the parts `M_kj (w_j - s_j)` that row `j` sends to the rows `k` after it wait in
    /// a ring (one per worker thread, zero between blocks: every row takes its part out)
    /// of a power of two above the largest `k - j` of an in-block upper entry. Returns
    /// `r · z = y · D y` of the new residual per coordinate, summed per block in order.
    pub fn forward_product(&self, k: &mut Krylov, step: V3) -> V3 {
        let bs = self.block;
        let Krylov { y, hat, s, rings, .. } = k;
        let (hat, s, rings) = (&*hat, &*s, &*rings);
        let parts: Vec<V3> = y
            .par_chunks_mut(bs)
            .enumerate()
            .map(|(b, ys)| {
                rings.with(|pending| {
                    let lo = b * bs;
                    let mask = pending.len() - 1;
                    let mut dot = [0.0; 3];
                    for j in lo..lo + ys.len() {
                        let e = gather(self.outer_entries(j), s, [0.0; 3]);
                        let dj = self.diag[j] as f64;
                        let inv = 1.0 / dj;
                        let slot = (j - lo) & mask;
                        let acc = std::mem::replace(&mut pending[slot], [0.0; 3]);
                        let (hj, sj) = (hat[j].get(), s[j].get());
                        let wj: V3 = std::array::from_fn(|c| (hj[c] + e[c] - acc[c]) * inv);
                        let old = ys[j - lo].get();
                        ys[j - lo].set(std::array::from_fn(|c| old[c] - step[c] * wj[c]));
                        let yj = ys[j - lo].get();
                        for c in 0..3 {
                            dot[c] += dj * yj[c] * yj[c];
                        }
                        let v: V3 = std::array::from_fn(|c| wj[c] - sj[c]);
                        scatter(self.upper_entries(j), j, pending, lo, mask, v, 1.0);
                    }
                    dot
                })
            })
            .collect();
        sum_parts(&parts)
    }
}

/// The vectors of the preconditioned conjugate-gradient iteration in Eisenstat's form,
/// one entry per row of `M`. The solution is `f64`; the other three are stored in
/// `f32` (every sum and product in `f64`), 36 bytes a node less at the solve: `M` is
/// itself `f32`, so their rounding is of the order of the matrix's, and the iteration
/// counts on the 256³ bed are those of `f64` vectors.
pub struct Krylov {
    /// The solution so far.
    pub x: Vec<V3>,
    /// `y = (D + L)⁻¹ r` of the current residual `r` (so `r · z = y · D y`).
    pub y: Vec<F3>,
    /// `ŝ = (D + U) s`.
    pub hat: Vec<F3>,
    /// The search direction `s`.
    pub s: Vec<F3>,
    /// Per worker thread, the ring of [`NormalMatrix::forward_product`], all zero.
    rings: PerThread<Vec<V3>>,
}

impl Krylov {
    /// The state at the start `x` whose residual is `r`: `y = (D + L)⁻¹ r` (solved in
    /// `r`'s place, then rounded and `r` freed before the other two are allocated), the
    /// rest zero.
    #[cfg(test)]
    pub fn start(m: &NormalMatrix, x: Vec<V3>, mut r: Vec<V3>) -> Krylov {
        m.forward(&mut r);
        let y = r.par_iter().with_min_len(4096).map(|v| v.map(|t| t as f32)).collect();
        drop(r);
        Krylov::with_y(m, x, y)
    }

    /// The state at the positions `x` of the displacement system
    /// ([`NormalMatrix::displacement_forward`]): the same as [`Krylov::start`] with
    /// `r = m.displacement_rhs(&x)`, without storing `r`.
    pub fn displacement(m: &NormalMatrix, x: Vec<V3>) -> Krylov {
        let y = m.displacement_forward(&x);
        Krylov::with_y(m, x, y)
    }

    fn with_y(m: &NormalMatrix, x: Vec<V3>, y: Vec<F3>) -> Krylov {
        let n = y.len();
        let zero = || filled(n, [0.0f32; 3]);
        let ring = (m.reach + 1).next_power_of_two();
        let rings = PerThread::new(move || vec![[0.0; 3]; ring]);
        Krylov { x, y, hat: zero(), s: zero(), rings }
    }
}

/// `acc + sign * sum_k m_jk x_k` over row `j`'s in-block upper entries, whose values
/// `x` start at row `lo`.
#[inline]
fn gather_upper<T: Triple>(entries: Upper<'_>, j: usize, x: &[T], lo: usize, mut acc: V3, sign: f64) -> V3 {
    entries.each(j, |k, m| {
        let xk = x[k - lo].get();
        for c in 0..3 {
            acc[c] += sign * (m * xk[c]);
        }
    });
    acc
}

/// `x_k += sign * m_jk v` for row `j`'s in-block upper entries, in a block whose values
/// `x` start at row `lo`: row `k` at `(k - lo) & mask` (`usize::MAX`: the block itself;
/// a power of two less one: a ring as wide as the rows' reach).
#[inline]
fn scatter(entries: Upper<'_>, j: usize, x: &mut [V3], lo: usize, mask: usize, v: V3, sign: f64) {
    entries.each(j, |k, m| {
        let xk = &mut x[(k - lo) & mask];
        for c in 0..3 {
            xk[c] += sign * (m * v[c]);
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stripes_are_short_enough_for_u32_offsets() {
        // A path: rows of at most 5 entries, stripes of the full size.
        let path: Vec<(u32, u32)> = (0..99).map(|i| (i, i + 1)).collect();
        assert_eq!(1 << stripe_shift(&Csr::from_sorted_edges(100, &path)), ROW_BLOCK);
        // A star of 2²¹ leaves: a row of `M` may span every node, so a stripe holds
        // as many rows as keep its entries countable in u32, and no more.
        let n = (1 << 21) + 1;
        let star: Vec<(u32, u32)> = (1..n as u32).map(|i| (0, i)).collect();
        let shift = stripe_shift(&Csr::from_sorted_edges(n, &star));
        assert!((1u64 << shift) * n as u64 <= u32::MAX as u64);
        assert!((2u64 << shift) * n as u64 > u32::MAX as u64);
    }

    /// In-place gathers and scatters agree with copies, over permutations with one
    /// cycle, fixed points and several cycles.
    #[test]
    fn permutations_in_place_match_copies() {
        let orders: [&[u32]; 4] = [&[], &[0, 1, 2], &[1, 2, 3, 4, 0], &[3, 0, 2, 5, 1, 4, 7, 6]];
        for order in orders {
            let v: Vec<u64> = (0..order.len() as u64).map(|i| 10 * i + 7).collect();
            let mut g = v.clone();
            gather_in_place(&mut g, order);
            assert_eq!(g, order.iter().map(|&i| v[i as usize]).collect::<Vec<_>>(), "{order:?}");
            let mut back = g.clone();
            scatter_in_place(&mut back, order);
            assert_eq!(back, v, "{order:?}");
        }
    }

    #[test]
    fn slabs_run_along_the_axis_with_the_most_layers() {
        assert_eq!(slab_axes([64, 64, 64]), None);
        assert_eq!(slab_axes([100, 30, 100]), None);
        assert_eq!(slab_axes([23, 512, 512]), Some([1, 0, 2]));
        assert_eq!(slab_axes([20, 30, 60]), Some([2, 0, 1]));
        // Nodes of a 2 × 3 × 2 block in node (C) order; slabs along axis 1.
        let p: Vec<V3> = (0..12).map(|t| [(t / 6) as f64, (t / 2 % 3) as f64, (t % 2) as f64]).collect();
        let order = slab_order(&p, 1.0, [1, 0, 2]);
        assert_eq!(order, [0, 1, 6, 7, 2, 3, 8, 9, 4, 5, 10, 11]);
    }
}
