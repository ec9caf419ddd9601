//! The run's peak memory, estimated from the mask before any heavy stage, and the
//! `max_memory` guard (not in the paper).
//!
//! # The model
//!
//! The estimate is an upper bound of the peak of the memory the run allocates *beyond
//! its input mask* (what `benches/performance.py` reports as "peak RSS over mask"). It
//! is the largest of the stages' own peaks, each a sum of terms that scale with the
//! foreground count `N`, with the box's rows (`n0 * n1`) and planes (`n1 * n2`), or
//! with the threads, plus a fixed [`BASE`]:
//!
//! | stage | what is alive at its peak | bytes |
//! |---|---|---|
//! | count | row offsets of the foreground | `8 n0 n1` |
//! | edt | row offsets; the EDT at the `N` foreground voxels (`f32`); one plane of run lengths (`u32`); per thread a plane buffer (`f32`, resident only where written) and envelope scratch | `8 n0 n1 + 4 N + 4 n1 n2 + T (4 min(n1 n2, N) + 40 max(n1, n2))` |
//! | grid | the EDT; the foreground rows (`8 n0 n1 + 4 N`); per node its base-neighbour slots, degree, CSR, union-find, positions, radii, components | `8 n0 n1 + GRID[c] N` |
//! | contract | the EDT and the foreground rows, kept for the medial stage (`8 n0 n1 + 4 N`); skeletal flags and slab order; while `M` is assembled the node graph (CSR, positions, radii, components) and the l2-norm and medial Laplacians (one `f64` row total per node each: their weights are computed as `M` reads them); during the solve the whole node graph packed ([`crate::packed`], ~15 bytes a node on the 256³ bed), `M` (`f32` values, in-block columns as `u16` distances: ~6 bytes per stored entry) the four conjugate-gradient vectors (one `f64`, three `f32`: 60 bytes) and the held nodes' positions before the move (28 bytes a held node, for the moves off the mask to undo) | `8 n0 n1 + 4 N + CONTRACT[c] N` |
//!
//! `CONTRACT[c]` (bytes per foreground voxel at connectivity `c`) is the largest
//! measured peak, over the mask, 4 MiB and the kept EDT, with a margin of at least
//! 10 %: the peak RSS of a run from Python at 2 threads minus the RSS once the mask is
//! loaded, with the default parameters (the coarse start), on the volumes of
//! `../shared/data` with more than 50 000 foreground voxels and on three thick shapes
//! (an 80³ block of foreground, cylinders of radius 9 and 14 voxels): at 6-connectivity
//! 79–174 B, the most on `aorta_ct_03mm` (the block 167); at 18, 189–502, the most on the
//! block (`aorta_ct_03mm` 441); at 26, 228–677, the most on the block (`aorta_ct_03mm`
//! 577); measured 2026-12-07. Thick vessels cost the most: the coarse start leaves vessels
//! over [`crate::coarse::MAX_CELL_RADIUS`] one node per voxel, their rows of `M` are full
//! (25 entries at 6-connectivity), and after the first iterations the decimated graph
//! has fewer nodes but denser rows. `GRID[c]` is the grid stage's figure (82–96 B at
//! 6-connectivity, of which 4 are the EDT), scaled by the base-neighbour slots at 18
//! and 26; it stays below the contraction. Later stages (refinement, output) work on
//! the contracted graph, a few percent of `N`, and never set the peak. [`BASE`] covers
//! what does not grow with the mask: the allocator's arenas, the worker threads' stacks
//! and the library's code pages, and the later stages' scratch on volumes so small that
//! they set the peak (`vascusynth_seed4_n1000_100`, 17 626 voxels: 7.8 MB in its output
//! stage, against an estimate of 7.9 MB with a base of 4 MiB, 9.9 MB with 6).
//!
//! The bound is measured, not proven: a mask whose vessels are all thicker than these
//! volumes' could need somewhat more; a mask of thin vessels (few interior voxels) needs
//! less than half of it.

use crate::error::{Error, Result};
use crate::params::Connectivity;
use rayon::prelude::*;

/// Fixed bytes of a run beyond its arrays (allocator arenas, the pool's threads, code
/// pages): a run on a one-voxel mask, and the smallest volumes measured, stay below it.
pub const BASE: u64 = 6 << 20;

/// Bytes per foreground voxel of the grid stage's own arrays (after the EDT), by
/// connectivity 6, 18, 26.
pub const GRID: [u64; 3] = [100, 160, 240];

/// Bytes per foreground voxel at the contraction's peak, by connectivity 6, 18, 26: the
/// largest measured, plus at least 10 % (see the module).
pub const CONTRACT: [u64; 3] = [200, 560, 760];

/// The memory a run needs, stage by stage (bytes, beyond the input mask).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Estimate {
    pub edt: u64,
    pub grid: u64,
    pub contract: u64,
}

impl Estimate {
    /// The run's peak: the largest stage, plus [`BASE`].
    pub fn peak(&self) -> u64 {
        BASE + self.edt.max(self.grid).max(self.contract)
    }
}

fn index(connectivity: Connectivity) -> usize {
    match connectivity {
        Connectivity::Six => 0,
        Connectivity::Eighteen => 1,
        Connectivity::TwentySix => 2,
    }
}

/// Estimate the memory of a run on a mask of `shape` with `foreground` voxels (see the
/// module for the model). Needs nothing but these counts, so it can run right after
/// the foreground is counted, before the distance transform.
///
/// ```
/// use vesselflow::memory::estimate;
/// use vesselflow::params::Connectivity;
/// let dense = estimate([256; 3], 839_095, Connectivity::Six, 2).peak();
/// let sparse = estimate([256; 3], 256, Connectivity::Six, 2).peak();
/// assert!(dense > 20 * sparse);
/// ```
pub fn estimate(shape: [usize; 3], foreground: usize, connectivity: Connectivity, threads: usize) -> Estimate {
    let [n0, n1, n2] = shape.map(|n| n as u64);
    let n = foreground as u64;
    let threads = threads.max(1) as u64;
    let rows = 8 * (n0 * n1 + 1);
    let plane = n1 * n2;
    // The per-thread plane buffers are zeroed lazily by the system: only the pages
    // holding foreground voxels become resident.
    // The foreground rows and the EDT at the foreground, kept from the first stage to
    // the medial stage.
    let kept = rows + 4 * n;
    let edt = kept + 4 * plane + threads * (4 * plane.min(n + 1024) + 40 * n1.max(n2));
    let c = index(connectivity);
    Estimate { edt, grid: kept + GRID[c] * n, contract: kept + CONTRACT[c] * n }
}

/// Refuse a run whose estimated `peak` exceeds `max_memory` (bytes; 0 = no limit).
pub fn check(peak: u64, max_memory: u64) -> Result<()> {
    if max_memory > 0 && peak > max_memory {
        Err(Error::OutOfMemory { needed: peak, allowed: max_memory })
    } else {
        Ok(())
    }
}

/// `n` copies of `value`, or [`Error::OutOfMemory`] if the allocation fails: for the
/// input-sized arrays, so that a run too large for the machine is refused, not
/// aborted. Written in parallel, so each page is first touched by a write (see
/// [`crate::grid::filled`]).
pub fn try_filled<T: Copy + Send + Sync>(n: usize, value: T) -> Result<Vec<T>> {
    let mut v = try_with_capacity(n)?;
    v.par_extend((0..n).into_par_iter().map(|_| value));
    Ok(v)
}

/// An empty vector with room for `n` values, or [`Error::OutOfMemory`].
pub fn try_with_capacity<T>(n: usize) -> Result<Vec<T>> {
    let mut v = Vec::new();
    v.try_reserve_exact(n).map_err(|_| Error::OutOfMemory {
        needed: (n as u64).saturating_mul(std::mem::size_of::<T>() as u64),
        allowed: 0,
    })?;
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_guard_names_both_numbers() {
        assert!(check(1000, 0).is_ok());
        assert!(check(1000, 1000).is_ok());
        let e = check(5 << 30, 1 << 30).unwrap_err();
        assert_eq!(e, Error::OutOfMemory { needed: 5 << 30, allowed: 1 << 30 });
        let m = e.to_string();
        assert!(m.contains("5.0 GiB") && m.contains("1.0 GiB"), "{m}");
        assert!(m.contains("max_memory=") && m.contains("crop the volume"), "{m}");
    }

    #[test]
    fn the_estimate_follows_the_foreground_not_the_box() {
        // A 300-voxel line in a 300³ box against the same line in a tight box.
        let line = estimate([300; 3], 300, Connectivity::Six, 2).peak() - BASE;
        let tight = estimate([1, 1, 300], 300, Connectivity::Six, 2).peak() - BASE;
        assert!(line < 2 << 20, "{line}");
        assert!(tight < line);
        // Dense: proportional to N, and more at higher connectivity.
        let six = estimate([256; 3], 839_095, Connectivity::Six, 2).peak();
        let big = estimate([512; 3], 8 * 839_095, Connectivity::Six, 2).peak();
        assert!((7.5..8.5).contains(&((big - BASE) as f64 / (six - BASE) as f64)));
        assert!(estimate([256; 3], 839_095, Connectivity::TwentySix, 2).peak() > 2 * six);
    }

    #[test]
    fn a_run_over_max_memory_is_refused_and_a_generous_limit_changes_nothing() {
        use crate::{shapes, Params, Skeletonizer};
        let mask = shapes::cylinder([40, 21, 21], 4.0);
        let run = |max_memory| {
            let p = Params { max_memory, ..Params::default() };
            Skeletonizer::new(p).unwrap().run(mask.view(), [1.0; 3], &mut |_| true)
        };
        let n = mask.iter().filter(|&&v| v != 0).count();
        let need = estimate([40, 21, 21], n, Connectivity::Six, rayon::current_num_threads()).peak();
        match run(Some(1000)) {
            Err(Error::OutOfMemory { needed, allowed: 1000 }) => assert!(needed >= BASE),
            other => panic!("expected OutOfMemory, got {other:?}"),
        }
        // The guard compares the estimate itself: exactly at it the run goes ahead.
        assert!(run(Some(need)).is_ok());
        assert!(matches!(run(Some(need - 1)), Err(Error::OutOfMemory { .. })));
        let free = run(None).unwrap();
        for limited in [run(Some(1 << 40)).unwrap(), run(Some(0)).unwrap()] {
            assert_eq!(limited.positions, free.positions);
            assert_eq!(limited.radii, free.radii);
            assert_eq!(limited.edges, free.edges);
        }
    }

    #[test]
    fn failed_allocations_are_errors() {
        let e = try_with_capacity::<u64>(usize::MAX / 4).unwrap_err();
        assert!(matches!(e, Error::OutOfMemory { allowed: 0, .. }), "{e}");
        assert_eq!(try_filled(5, 7u32).unwrap(), vec![7; 5]);
    }
}
