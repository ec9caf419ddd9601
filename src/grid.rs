//! The geometric graph in compact CSR form, and the initial grid graph built from
//! the mask (docs/method.md §1, paper §III-A): one node per foreground voxel, edges to
//! face neighbours (or 18/26), thin-vessel reconnection, and a final bridge so that
//! every 26-connected mask component is exactly one graph component.

use crate::error::Result;
use crate::memory::{try_filled, try_with_capacity};
use crate::params::{Connectivity, Params};
use crate::volume::{foreground_rows, Voxel};
use ndarray::{ArrayView3, Axis};
use petgraph::unionfind::UnionFind;
use rayon::prelude::*;
use std::sync::Mutex;

/// Rows per parallel task when a pass walks the graph row by row. Fixed, so every
/// parallel reduction is split the same way whatever the thread count.
pub const ROW_BLOCK: usize = 4096;

/// An undirected simple graph in compressed sparse row form: the neighbours of node
/// `i` are `targets[offsets[i]..offsets[i + 1]]`, sorted, each edge stored both ways.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Csr {
    pub offsets: Vec<usize>,
    pub targets: Vec<u32>,
}

impl Csr {
    /// Number of nodes.
    pub fn nodes(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    /// Number of undirected edges.
    pub fn edges(&self) -> usize {
        self.targets.len() / 2
    }

    /// Neighbours of node `i`, sorted.
    pub fn neighbours(&self, i: usize) -> &[u32] {
        &self.targets[self.offsets[i]..self.offsets[i + 1]]
    }

    /// From undirected edges `(a, b)` with `a < b`, sorted and without duplicates.
    pub fn from_sorted_edges(nodes: usize, edges: &[(u32, u32)]) -> Csr {
        let mut degree = vec![0usize; nodes + 1];
        for &(a, b) in edges {
            degree[a as usize] += 1;
            degree[b as usize] += 1;
        }
        let mut offsets = Vec::with_capacity(nodes + 1);
        let mut acc = 0;
        offsets.push(0);
        for d in &degree[..nodes] {
            acc += d;
            offsets.push(acc);
        }
        // Edges sorted by (a, b): every row receives its smaller neighbours (as `b`)
        // before its larger ones (as `a`), each group in increasing order.
        let mut fill = offsets[..nodes].to_vec();
        let mut targets = vec![0u32; acc];
        for &(a, b) in edges {
            targets[fill[a as usize]] = b;
            fill[a as usize] += 1;
            targets[fill[b as usize]] = a;
            fill[b as usize] += 1;
        }
        Csr { offsets, targets }
    }

    /// Undirected edges `(a, b)`, `a < b`, sorted.
    pub fn edge_list(&self) -> Vec<(u32, u32)> {
        (0..self.nodes())
            .flat_map(|a| self.neighbours(a).iter().filter(move |&&b| b as usize > a).map(move |&b| (a as u32, b)))
            .collect()
    }
}

/// Run `f(rows, entries)` in parallel over blocks of [`ROW_BLOCK`] rows, where
/// `entries` is the part of `data` (one value per CSR entry) that those rows own.
pub fn for_row_blocks<T: Send>(offsets: &[usize], data: &mut [T], f: impl Fn(std::ops::Range<usize>, &mut [T]) + Sync) {
    let n = offsets.len().saturating_sub(1);
    let mut parts = Vec::with_capacity(n.div_ceil(ROW_BLOCK));
    let mut rest = data;
    for start in (0..n).step_by(ROW_BLOCK) {
        let end = (start + ROW_BLOCK).min(n);
        let (head, tail) = rest.split_at_mut(offsets[end] - offsets[start]);
        parts.push((start..end, head));
        rest = tail;
    }
    parts.into_par_iter().for_each(|(rows, part)| f(rows, part));
}

/// `n` copies of `value`, written in parallel. Unlike `vec![0; n]` (calloc: pages
/// mapped to the shared zero page until written), every page is first touched by a
/// write, so an array that is read before it is written costs one page fault per page
/// rather than two, and no TLB shootdown of the other cores running the process
/// (measured at 512³: 10.8 s of system time in 31 s on 2 threads before).
pub fn filled<T: Copy + Send + Sync>(n: usize, value: T) -> Vec<T> {
    (0..n).into_par_iter().map(|_| value).collect()
}

/// One scratch value per worker thread of the current rayon pool, lent by thread
/// index, so a parallel pass can reuse large buffers without allocating per task.
///
/// A slot is never waited for: if the calling thread's slot is taken (the closure
/// of [`PerThread::with`] reached a rayon call, whose work stealing ran another task
/// of the same pass on this thread), that task gets a fresh value from `make`.
/// Waiting there would deadlock: the holder is suspended below us on the same thread.
/// The scratch values must therefore carry nothing from task to task that changes a
/// result, only capacity.
pub struct PerThread<T> {
    slots: Vec<Mutex<T>>,
    make: Box<dyn Fn() -> T + Send + Sync>,
}

impl<T> PerThread<T> {
    /// `make()` once per thread of the current pool.
    pub fn new(make: impl Fn() -> T + Send + Sync + 'static) -> PerThread<T> {
        PerThread {
            slots: (0..rayon::current_num_threads()).map(|_| Mutex::new(make())).collect(),
            make: Box::new(make),
        }
    }

    /// `f` on the calling thread's value, or on a fresh one if that is in use.
    pub fn with<R>(&self, f: impl FnOnce(&mut T) -> R) -> R {
        let slot = rayon::current_thread_index().unwrap_or(0) % self.slots.len();
        match self.slots[slot].try_lock() {
            Ok(mut value) => f(&mut value),
            Err(std::sync::TryLockError::Poisoned(e)) => f(&mut e.into_inner()),
            Err(std::sync::TryLockError::WouldBlock) => f(&mut (self.make)()),
        }
    }
}

/// The initial geometric graph: one node per foreground voxel in C order.
#[derive(Debug, Clone, Default)]
pub struct GridGraph {
    pub graph: Csr,
    /// Voxel centre of every node, physical units, `index * spacing`.
    pub positions: Vec<[f64; 3]>,
    /// EDT at every node, physical units (distance to the nearest background centre).
    pub radii: Vec<f64>,
    /// 26-connected mask component of every node, numbered by first voxel in C order.
    pub component: Vec<u32>,
    /// Number of mask components.
    pub components: usize,
}

/// Foreground voxels of the mask, row by row: row `r = i * n1 + j` holds the
/// `k` of its foreground voxels in `ks[rows[r]..rows[r + 1]]`; node ids follow.
struct Rows {
    shape: [usize; 3],
    rows: Vec<usize>,
    ks: Vec<u32>,
}

impl Rows {
    fn new<T: Voxel>(mask: ArrayView3<'_, T>) -> Result<Rows> {
        let (n0, n1, n2) = mask.dim();
        let rows = foreground_rows(mask)?;
        let mut ks = crate::memory::try_filled(rows[n0 * n1], 0u32)?;
        // Blocks of rows in parallel, each filling its own part of `ks`.
        let blocks: Vec<usize> = (0..=n0 * n1).step_by(ROW_BLOCK).chain([n0 * n1]).collect();
        let mut parts = Vec::with_capacity(blocks.len());
        let mut rest = &mut ks[..];
        for w in blocks.windows(2) {
            let (head, tail) = rest.split_at_mut(rows[w[1]] - rows[w[0]]);
            parts.push((w[0]..w[1], head));
            rest = tail;
        }
        parts.into_par_iter().for_each(|(block, part)| {
            let mut t = 0;
            for r in block {
                let row = mask.index_axis(Axis(0), r / n1);
                for (k, v) in row.index_axis(Axis(0), r % n1).iter().enumerate() {
                    if v.is_set() {
                        part[t] = k as u32;
                        t += 1;
                    }
                }
            }
        });
        Ok(Rows { shape: [n0, n1, n2], rows, ks })
    }

    fn len(&self) -> usize {
        self.ks.len()
    }

    /// Node id of voxel `(i, j, k)` if it is foreground.
    fn find(&self, i: isize, j: isize, k: isize) -> Option<u32> {
        let [n0, n1, n2] = self.shape;
        if i < 0 || j < 0 || k < 0 || i >= n0 as isize || j >= n1 as isize || k >= n2 as isize {
            return None;
        }
        let r = i as usize * n1 + j as usize;
        let (lo, hi) = (self.rows[r], self.rows[r + 1]);
        self.ks[lo..hi].binary_search(&(k as u32)).ok().map(|p| (lo + p) as u32)
    }

    /// Voxel index of node `n` lying in row `r`.
    fn voxel(&self, r: usize, n: usize) -> [isize; 3] {
        let n1 = self.shape[1];
        [(r / n1) as isize, (r % n1) as isize, self.ks[n] as isize]
    }

    /// The row of node `n` (a binary search: for a few nodes; passes over all of them
    /// walk the rows with [`Rows::voxels`]).
    fn row_of(&self, n: usize) -> usize {
        self.rows.partition_point(|&s| s <= n) - 1
    }

    /// Voxel index of node `n`.
    fn voxel_of(&self, n: usize) -> [isize; 3] {
        self.voxel(self.row_of(n), n)
    }

    /// Voxel indices of the nodes `first..`, in node order, found by walking the rows
    /// (no per-node row array: it would cost 8 bytes a node at the grid stage's peak).
    fn voxels(&self, first: usize) -> impl Iterator<Item = [isize; 3]> + '_ {
        let mut r = if first < self.len() { self.row_of(first) } else { 0 };
        (first..self.len()).map(move |n| {
            while self.rows[r + 1] <= n {
                r += 1;
            }
            self.voxel(r, n)
        })
    }
}

/// Neighbour offsets within the given squared index distance, sorted so that the
/// neighbours of a node come out in increasing node order (C order).
fn offsets(max_sq: isize) -> Vec<[isize; 3]> {
    let mut v = vec![];
    for a in -1..=1isize {
        for b in -1..=1isize {
            for c in -1..=1isize {
                let sq = a * a + b * b + c * c;
                if sq > 0 && sq <= max_sq {
                    v.push([a, b, c]);
                }
            }
        }
    }
    v
}

/// The graph whose row `a` is the sorted `row(a)` (`count(a)` neighbours) merged with
/// the sorted `extra` pairs `(a, b)`, none of them already in `row(a)`; built in
/// place, with no edge list. [`crate::Error::OutOfMemory`] if it does not fit.
fn with_extra<I: Iterator<Item = u32>>(
    n: usize,
    count: impl Fn(usize) -> usize,
    row: impl Fn(usize) -> I + Sync,
    extra: &[(u32, u32)],
) -> Result<Csr> {
    let mut offsets = try_with_capacity(n + 1)?;
    offsets.push(0);
    let (mut acc, mut x) = (0, 0);
    for a in 0..n {
        let more = row_end(extra, x, a);
        acc += count(a) + more - x;
        offsets.push(acc);
        x = more;
    }
    let mut targets = try_filled(acc, 0u32)?;
    for_row_blocks(&offsets, &mut targets, |block, out| {
        let mut x = extra.partition_point(|&(a, _)| (a as usize) < block.start);
        let mut e = 0;
        for a in block {
            let more = row_end(extra, x, a);
            let mut added = extra[x..more].iter().map(|&(_, b)| b).peekable();
            for b in row(a) {
                while let Some(t) = added.next_if(|&t| t < b) {
                    out[e] = t;
                    e += 1;
                }
                out[e] = b;
                e += 1;
            }
            for t in added {
                out[e] = t;
                e += 1;
            }
            x = more;
        }
    });
    Ok(Csr { offsets, targets })
}

/// The end of row `a`'s pairs in the sorted `extra`, from `x`, the end of the rows
/// before it: a walk, as most rows have none (a binary search over the rest of `extra`
/// for every row took about 0.4 s of the build's 1.2 s on the 512³ bed).
fn row_end(extra: &[(u32, u32)], mut x: usize, a: usize) -> usize {
    while extra.get(x).is_some_and(|&(b, _)| b as usize == a) {
        x += 1;
    }
    x
}

/// Build the initial grid graph of `mask` (docs/method.md §1).
///
/// Edges join face neighbours (`connectivity = 6`; 18 or 26 on request). With
/// `reconnect_thin`, every node of degree ≤ 2 is also joined to all foreground voxels
/// within √2 voxels (the authors' code), so one-voxel vessels are not lost; the rule
/// is applied symmetrically. Finally, voxels that touch only by an edge or a corner
/// still unjoined get one bridging edge per pair of graph pieces, so that each
/// 26-connected mask component is exactly one graph component.
///
/// `edt_sq` is the squared EDT at the foreground voxels in C order
/// ([`crate::volume::edt_squared`]). [`crate::Error::OutOfMemory`] if one of its
/// node-sized arrays cannot be allocated.
pub fn build<T: Voxel>(
    mask: ArrayView3<'_, T>,
    edt_sq: &[f32],
    spacing: [f64; 3],
    params: &Params,
) -> Result<GridGraph> {
    let rows = Rows::new(mask)?;
    let n = rows.len();
    let base_sq = match params.connectivity {
        Connectivity::Six => 1,
        Connectivity::Eighteen => 2,
        Connectivity::TwentySix => 3,
    };
    let base = offsets(base_sq);
    let at = |[i, j, k]: [isize; 3], o: &[isize; 3]| rows.find(i + o[0], j + o[1], k + o[2]);

    // Base neighbours of every node, one slot per offset (in increasing node order),
    // `u32::MAX` where the voxel is background.
    let f = base.len();
    let mut near = try_filled(n * f, u32::MAX)?;
    near.par_chunks_mut(f * ROW_BLOCK).enumerate().for_each(|(c, part)| {
        // A run asked to stop gets a partial graph, which it discards.
        if crate::cancel::requested() {
            return;
        }
        for (slots, v) in part.chunks_mut(f).zip(rows.voxels(c * ROW_BLOCK)) {
            for (slot, o) in slots.iter_mut().zip(&base) {
                *slot = at(v, o).unwrap_or(u32::MAX);
            }
        }
    });
    // A run asked to stop ([`crate::cancel`]) ends at the next of these checks.
    if crate::cancel::requested() {
        return Err(crate::error::Error::Interrupted);
    }
    // Base degrees are at most 26.
    let degree: Vec<u8> = near.par_chunks(f).map(|s| s.iter().filter(|&&b| b != u32::MAX).count() as u8).collect();
    // Thin-vessel reconnection: the edge-diagonal neighbours of every node of degree
    // ≤ 2, both ways (the rule joins a pair when either end is thin), sorted.
    let mut extra: Vec<(u32, u32)> = vec![];
    if params.reconnect_thin && base_sq < 2 {
        let diagonal: Vec<[isize; 3]> =
            offsets(2).into_iter().filter(|o| o.iter().map(|x| x * x).sum::<isize>() == 2).collect();
        extra = (0..n)
            .into_par_iter()
            .filter(|&a| degree[a] <= 2)
            .flat_map_iter(|a| {
                let (diagonal, at, v) = (&diagonal, &at, rows.voxel_of(a));
                diagonal.iter().filter_map(move |o| at(v, o)).flat_map(move |b| [(a as u32, b), (b, a as u32)])
            })
            .collect();
        extra.par_sort_unstable();
        extra.dedup();
    }
    if crate::cancel::requested() {
        return Err(crate::error::Error::Interrupted);
    }
    let mut graph = with_extra(
        n,
        |a| degree[a] as usize,
        |a| near[a * f..(a + 1) * f].iter().copied().filter(|&b| b != u32::MAX),
        &extra,
    )?;
    drop((near, degree, extra));
    if crate::cancel::requested() {
        return Err(crate::error::Error::Interrupted);
    }

    // Bridge graph pieces that touch only diagonally. Candidates: 26-neighbour pairs
    // in different graph pieces, joined in (a, b) order, as a sequential scan of all
    // pairs would (pairs already in one piece never bridge, and pieces only grow).
    // Every candidate has an end outside the largest piece, so only those nodes are
    // searched.
    let mut uf = UnionFind::<u32>::new(n);
    for a in 0..n {
        for &b in graph.neighbours(a) {
            if b as usize > a {
                uf.union(a as u32, b);
            }
        }
    }
    let piece: Vec<u32> = (0..n as u32).map(|a| uf.find_mut(a)).collect();
    let mut size = filled(n, 0u32);
    for &p in &piece {
        size[p as usize] += 1;
    }
    let largest = (0..n).max_by_key(|&p| (size[p], std::cmp::Reverse(p))).unwrap_or(0) as u32;
    drop(size);
    let all = offsets(3);
    let mut candidates: Vec<(u32, u32)> = (0..n)
        .into_par_iter()
        .filter(|&a| piece[a] != largest)
        .flat_map_iter(|a| {
            let (all, piece, at, v) = (&all, &piece, &at, rows.voxel_of(a));
            all.iter().filter_map(move |o| {
                let b = at(v, o)?;
                (piece[a] != piece[b as usize]).then_some(((a as u32).min(b), (a as u32).max(b)))
            })
        })
        .collect();
    drop(piece);
    candidates.par_sort_unstable();
    candidates.dedup();
    let mut bridges: Vec<(u32, u32)> =
        candidates.into_iter().filter(|&(a, b)| uf.union(a, b)).flat_map(|(a, b)| [(a, b), (b, a)]).collect();
    if !bridges.is_empty() {
        // A bridge joins two pieces, so it is never an edge already.
        bridges.sort_unstable();
        graph = with_extra(n, |a| graph.neighbours(a).len(), |a| graph.neighbours(a).iter().copied(), &bridges)?;
    }
    drop(bridges);
    if crate::cancel::requested() {
        return Err(crate::error::Error::Interrupted);
    }
    // Components numbered by their first node.
    let mut label = vec![u32::MAX; n];
    let mut label_of_root = vec![u32::MAX; n];
    let mut components = 0u32;
    for (a, l) in label.iter_mut().enumerate() {
        let root = uf.find_mut(a as u32) as usize;
        if label_of_root[root] == u32::MAX {
            label_of_root[root] = components;
            components += 1;
        }
        *l = label_of_root[root];
    }
    drop((label_of_root, uf));

    let mut positions = try_filled(n, [0.0; 3])?;
    positions.par_chunks_mut(ROW_BLOCK).enumerate().for_each(|(c, part)| {
        for (p, v) in part.iter_mut().zip(rows.voxels(c * ROW_BLOCK)) {
            *p = std::array::from_fn(|d| v[d] as f64 * spacing[d]);
        }
    });
    assert_eq!(edt_sq.len(), n, "the EDT of another mask");
    let mut radii = try_with_capacity(n)?;
    radii.par_extend(edt_sq.par_iter().map(|&d| (d as f64).sqrt()));
    Ok(GridGraph { graph, positions, radii, component: label, components: components as usize })
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    fn grid(mask: &Array3<u8>, params: &Params) -> GridGraph {
        let e = crate::volume::edt_squared(mask.view(), [1.0; 3]).unwrap();
        build(mask.view(), &e, [1.0; 3], params).unwrap()
    }

    /// A rayon call inside `PerThread::with` lets the thread steal another task of
    /// the same pass, which then asks for the same slot. With a waiting lock this
    /// hangs (the short-cycle search did, at 8 threads); the slot must be lent afresh.
    #[test]
    fn per_thread_scratch_never_waits_on_its_own_thread() {
        let (done, finished) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(8).build().unwrap();
            let total: u64 = pool.install(|| {
                let scratch = PerThread::new(Vec::<u64>::new);
                (0..200u64)
                    .into_par_iter()
                    .map(|i| {
                        scratch.with(|s| {
                            s.push(i);
                            let inner: u64 = (0..64u64)
                                .into_par_iter()
                                .map(|k| {
                                    scratch.with(|t| {
                                        t.push(k);
                                        k
                                    })
                                })
                                .sum();
                            inner + i
                        })
                    })
                    .sum()
            });
            done.send(total).unwrap();
        });
        let total = finished.recv_timeout(std::time::Duration::from_secs(60)).expect("PerThread deadlocked");
        assert_eq!(total, 200 * (63 * 64 / 2) + 199 * 200 / 2);
    }

    #[test]
    fn solid_block_has_face_edges_only() {
        let m = Array3::<u8>::ones((3, 4, 5));
        let g = grid(&m, &Params::default());
        assert_eq!(g.graph.nodes(), 60);
        // 6-connected edges of a 3x4x5 block: 2*4*5 + 3*3*5 + 3*4*4.
        assert_eq!(g.graph.edges(), 40 + 45 + 48);
        assert_eq!(g.components, 1);
        assert_eq!(g.positions[59], [2.0, 3.0, 4.0]);
        assert_eq!(g.radii[0], 1.0);
        assert_eq!(g.graph.targets.len(), 2 * 133);
    }

    #[test]
    fn thin_diagonal_line_is_reconnected_and_corners_are_bridged() {
        let mut m = Array3::<u8>::zeros((5, 5, 5));
        for i in 0..5 {
            m[[i, i, 0]] = 1; // edge-diagonal staircase: no face contacts
        }
        m[[4, 0, 4]] = 1;
        m[[3, 1, 3]] = 1; // corner contact only
        let p = Params::default();
        let g = grid(&m, &p);
        assert_eq!(g.components, 2);
        let mut uf = UnionFind::<u32>::new(g.graph.nodes());
        for (a, b) in g.graph.edge_list() {
            uf.union(a, b);
        }
        let roots: std::collections::BTreeSet<_> = (0..g.graph.nodes() as u32).map(|a| uf.find(a)).collect();
        assert_eq!(roots.len(), 2);
        let mut q = p.clone();
        q.reconnect_thin = false;
        // Without reconnection the staircase is still joined, by bridges.
        assert_eq!(grid(&m, &q).components, 2);
    }

    /// The grid graph by its definition, over a dense index: base edges, thin-vessel
    /// edges where either end has base degree ≤ 2, then bridges over all 26-neighbour
    /// pairs in (a, b) order; components numbered by first node.
    fn slow(mask: &Array3<u8>, params: &Params) -> (Vec<(u32, u32)>, Vec<u32>) {
        let (n0, n1, n2) = mask.dim();
        let mut id = Array3::from_elem((n0, n1, n2), u32::MAX);
        let mut vox = vec![];
        for ((i, j, k), &v) in mask.indexed_iter() {
            if v != 0 {
                id[[i, j, k]] = vox.len() as u32;
                vox.push([i as isize, j as isize, k as isize]);
            }
        }
        let at = |v: [isize; 3], o: [isize; 3]| {
            let w = [v[0] + o[0], v[1] + o[1], v[2] + o[2]];
            let inside = (0..3).all(|d| w[d] >= 0 && (w[d] as usize) < [n0, n1, n2][d]);
            if inside {
                let b = id[[w[0] as usize, w[1] as usize, w[2] as usize]];
                (b != u32::MAX).then_some(b)
            } else {
                None
            }
        };
        let base_sq = match params.connectivity {
            Connectivity::Six => 1,
            Connectivity::Eighteen => 2,
            Connectivity::TwentySix => 3,
        };
        let sq = |o: &[isize; 3]| o.iter().map(|x| x * x).sum::<isize>();
        let all = offsets(3);
        let degree: Vec<usize> =
            vox.iter().map(|&v| all.iter().filter(|o| sq(o) <= base_sq && at(v, **o).is_some()).count()).collect();
        let mut edges = vec![];
        for (a, &v) in vox.iter().enumerate() {
            for o in &all {
                if let Some(b) = at(v, *o) {
                    let thin = params.reconnect_thin && base_sq < 2 && sq(o) == 2;
                    if (b as usize) > a && (sq(o) <= base_sq || thin && (degree[a] <= 2 || degree[b as usize] <= 2)) {
                        edges.push((a as u32, b));
                    }
                }
            }
        }
        let mut uf = UnionFind::<u32>::new(vox.len());
        for &(a, b) in &edges {
            uf.union(a, b);
        }
        for (a, &v) in vox.iter().enumerate() {
            for o in &all {
                if let Some(b) = at(v, *o) {
                    if (b as usize) > a && uf.union(a as u32, b) {
                        edges.push((a as u32, b));
                    }
                }
            }
        }
        edges.sort_unstable();
        let mut first = std::collections::BTreeMap::new();
        let label = (0..vox.len() as u32)
            .map(|a| {
                let next = first.len() as u32;
                *first.entry(uf.find(a)).or_insert(next)
            })
            .collect();
        (edges, label)
    }

    #[test]
    fn matches_the_definition_on_random_masks() {
        let mut rnd = crate::test_rng(99);
        for trial in 0..40 {
            let shape = (1 + rnd(9) as usize, 1 + rnd(10) as usize, 1 + rnd(11) as usize);
            // Sparse masks have thin voxels and diagonal-only contacts; dense ones have
            // a large piece and small ones beside it.
            let fill = [8, 20, 35, 60][trial % 4];
            let mask = Array3::from_shape_fn(shape, |_| u8::from(rnd(100) < fill));
            for connectivity in [Connectivity::Six, Connectivity::Eighteen, Connectivity::TwentySix] {
                for reconnect_thin in [true, false] {
                    let p = Params { connectivity, reconnect_thin, ..Params::default() };
                    let g = grid(&mask, &p);
                    let (edges, label) = slow(&mask, &p);
                    assert_eq!(g.graph.edge_list(), edges, "trial {trial} {connectivity:?} {reconnect_thin}");
                    assert_eq!(g.component, label);
                    assert_eq!(g.components, label.iter().map(|&l| l as usize + 1).max().unwrap_or(0));
                }
            }
        }
    }

    #[test]
    fn csr_from_edges_is_symmetric_and_sorted() {
        let edges = vec![(0, 3), (1, 2), (1, 3), (2, 3)];
        let g = Csr::from_sorted_edges(4, &edges);
        assert_eq!(g.neighbours(3), &[0, 1, 2]);
        assert_eq!(g.edge_list(), edges);
        for a in 0..4 {
            assert!(g.neighbours(a).iter().all(|&b| g.neighbours(b as usize).contains(&(a as u32))));
        }
    }
}
