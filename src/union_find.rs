//! A union-find that every thread of a stage updates at once: the grid graph's pieces
//! ([`crate::grid`]) and the coarse start's cells ([`crate::coarse`]) are found by
//! joining the ends of millions of edges, which one thread did serially.
//!
//! Lock-free, one `u32` per element (the stages' peak holds it beside the grid graph;
//! a library's concurrent union-find keeps a `usize` per element, twice as much): each
//! element points to a smaller one or to itself (a representative); a union links the
//! larger of the two representatives under the smaller, by compare-and-swap, so it
//! succeeds only while that one is still a representative; a find halves the path it
//! walks, lowering pointers only to ancestors. Every set's representative is therefore
//! its smallest element, whatever the order in which the threads joined it: the result
//! does not depend on the thread count. A find ends because pointers strictly decrease
//! along a path; a union retries only after another union linked one of its
//! representatives, which happens at most `n - 1` times in all.

use rayon::prelude::*;
use std::sync::atomic::{AtomicU32, Ordering::Relaxed};

/// See the module.
pub struct SharedUnionFind {
    parent: Vec<AtomicU32>,
}

impl SharedUnionFind {
    /// `n` singletons, `0..n` (`n <= u32::MAX`: elements are node ids).
    pub fn new(n: usize) -> Self {
        debug_assert!(n <= u32::MAX as usize);
        Self { parent: (0..n).into_par_iter().map(|i| AtomicU32::new(i as u32)).collect() }
    }

    /// The representative of `x`'s set (its smallest element once no union runs).
    pub fn find(&self, mut x: u32) -> u32 {
        loop {
            let p = self.parent[x as usize].load(Relaxed);
            if p == x {
                return x;
            }
            let g = self.parent[p as usize].load(Relaxed);
            if g != p {
                // `g < p < x`, an ancestor of `x`: pointing `x` at it keeps the sets.
                self.parent[x as usize].fetch_min(g, Relaxed);
            }
            x = g;
        }
    }

    /// Join the sets of `a` and `b`.
    pub fn union(&self, a: u32, b: u32) {
        let (mut a, mut b) = (a, b);
        loop {
            (a, b) = (self.find(a), self.find(b));
            if a == b {
                return;
            }
            let (low, high) = (a.min(b), a.max(b));
            if self.parent[high as usize].compare_exchange(high, low, Relaxed, Relaxed).is_ok() {
                return;
            }
            // `high` was linked meanwhile: start again from the two representatives.
            (a, b) = (high, low);
        }
    }

    /// Every element's representative, the smallest element of its set (in place: no
    /// memory beyond the union-find's own).
    pub fn into_roots(self) -> Vec<u32> {
        self.parent.par_iter().enumerate().for_each(|(i, p)| p.store(self.find(i as u32), Relaxed));
        self.parent.into_iter().map(AtomicU32::into_inner).collect()
    }
}

/// The sets of a union-find numbered 0, 1, ... in the order of their first element:
/// `root[i]` is the representative of `i`'s set (`root[r] == r` for a representative
/// `r`). The numbering depends only on the partition, not on which element represents a
/// set. Returns every element's number and the number of sets.
pub(crate) fn number_by_first(root: &[u32]) -> (Vec<u32>, usize) {
    let mut number = vec![u32::MAX; root.len()];
    let mut sets = 0u32;
    for (i, &r) in root.iter().enumerate() {
        // `number[r]` is written when the set is first met, at or before `i = r`.
        if number[r as usize] == u32::MAX {
            number[r as usize] = sets;
            sets += 1;
        }
        number[i] = number[r as usize];
    }
    (number, sets as usize)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Random unions from several threads give the sets a plain sequential union-find
    /// gives, each represented by its smallest element, at 1 and 4 threads alike.
    #[test]
    fn threads_joining_at_once_find_the_sets_of_a_sequential_union_find() {
        let mut next = crate::test_rng(424242);
        let n = 20_000;
        let pairs: Vec<(u32, u32)> = (0..15_000).map(|_| (next(n as u64) as u32, next(n as u64) as u32)).collect();
        let mut want = petgraph::unionfind::UnionFind::<u32>::new(n);
        for &(a, b) in &pairs {
            want.union(a, b);
        }
        let want = want.into_labeling();
        for threads in [1, 4] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let roots = pool.install(|| {
                let uf = SharedUnionFind::new(n);
                pairs.par_iter().for_each(|&(a, b)| uf.union(a, b));
                uf.into_roots()
            });
            let mut smallest = vec![u32::MAX; n];
            for (i, &w) in want.iter().enumerate() {
                smallest[w as usize] = smallest[w as usize].min(i as u32);
            }
            for i in 0..n {
                assert_eq!(roots[i], smallest[want[i] as usize], "element {i} at {threads} threads");
            }
        }
    }
}
