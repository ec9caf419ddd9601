//! # vesselflow core
//!
//! Turns a 3-D binary vessel mask into a centreline graph with radii by Laplacian
//! flow on geometric graphs (Damseh et al., "Laplacian Flow Dynamics on Geometric
//! Graphs for Anatomical Modeling of Cerebrovascular Networks"), with the departures listed
//! in `docs/method.md`. One stage per module, in pipeline order:
//!
//! | module | stage | paper |
//! |---|---|---|
//! | [`params`] | parameters, defaults, validation | §III, §IV-B |
//! | [`volume`] | mask views, spacing, anisotropic exact EDT | §III-A |
//! | [`grid`] | grid graph (CSR) from the mask, thin-vessel reconnection, components | §III-A |
//! | [`coarse`] | the coarse start graph: voxels grouped into cells as wide as the vessel (`coarse_cell`) | — |
//! | [`laplacian`] | l2-norm and medial weights, adaptive anchoring, the normal-equations operator | §III-B, §III-D, eqs. 2–4, 8, 9 |
//! | [`solver`] | normal equations of eq. 8 by preconditioned conjugate gradients | §III-B, eq. 8 |
//! | [`precondition`] | the assembled normal matrix and its block Gauss–Seidel preconditioner | eq. 8 |
//! | [`decimate`] | cell-hash clustering with max-radius transfer | §III-E, §III-F |
//! | [`cycles`] | short fundamental cycles: convergence area and refinement | §III-C, §III-G, eqs. 10–11 |
//! | [`resample`] | with a coarse start, long edges split back to its cells' spacing (`coarse_cell`) | — |
//! | [`inside`] | nodes on background voxels moved to the nearest vessel voxel | — |
//! | [`medial`] | nodes moved onto the ridge of the distance transform (`medial`) | — |
//! | [`ends`] | free vessel ends moved out to one radius inside the mask (`anchor_ends`) | — |
//! | [`sprouts`] | side branches the contraction swallowed grown back from the mask (`sprouts`) | — |
//! | [`radius`] | node radii: cross-section area scaled by median over RMS chord length (robust to bubbles), or the plain area, or the EDT less a constant | — |
//! | [`edges_inside`] | edges that cross background subdivided by nodes on the mask | — |
//! | [`prune`] | terminal spurs inside their parent's lumen removed: shorter than its radius, or a second rail beside it (`prune_spurs`) | — |
//! | [`junctions`] | junctions linked by a branch shorter than half their radius joined into one node (`merge_junctions`) | — |
//! | [`smooth`] | radii smoothed along the branches, a median over a few voxels (`radius_smoothing`) | — |
//! | [`pipeline`] | the [`Skeletonizer`]: stages glued, statistics, progress | Algorithm 1 |
//! | [`cancel`] | the [`Stop`] flag that long stages poll | — |
//! | [`blocks`] | chunked runs: the block phase and the merge of blocks into one graph | — |
//! | [`fate`] | chunked runs: every voxel followed to its output node through the stages | — |
//! | [`blocks_route`] | chunked runs: the routing phase, edges kept inside the mask per block | — |
//! | [`blocks_sprouts`] | chunked runs: the blocks' sprouts attached to the merged graph | — |
//! | [`graph`] | the output [`Skeleton`] | §IV |
//! | [`memory`] | the run's peak memory estimated from the mask, the `max_memory` guard | — |
//! | [`allocator`] | the programs' heap allocator: large blocks mapped on their own, returned when freed | — |
//! | [`shapes`] | analytic test volumes and the built-in demo volume | — |
//!
//! Every stage is a pure function of (mask block, spacing, parameters) and every
//! parallel reduction uses a fixed chunking, so the output is identical bit for bit
//! whatever the number of threads.
//!
//! ```
//! use vesselflow::{shapes, Params, Skeletonizer};
//! let mask = shapes::cylinder([40, 21, 21], 4.0);
//! let skel = Skeletonizer::new(Params::default()).unwrap()
//!     .run(mask.view(), [1.0, 1.0, 1.0], &mut |_| true).unwrap();
//! assert!(skel.len() > 10);
//! assert!(skel.degrees().iter().all(|&d| d <= 2)); // a path
//! ```

pub mod allocator;
pub mod blocks;
pub mod blocks_route;
pub mod blocks_sprouts;
pub mod cancel;
pub mod coarse;
pub mod cycles;
pub mod decimate;
mod edge_grid;
pub mod edges_inside;
pub mod ends;
pub mod error;
pub mod fate;
pub mod graph;
pub mod grid;
pub mod inside;
pub mod junctions;
pub mod laplacian;
pub mod medial;
pub mod memory;
pub mod packed;
pub mod params;
pub mod pipeline;
pub mod precondition;
pub mod prune;
pub mod radius;
pub mod resample;
pub mod shapes;
pub mod smooth;
pub mod solver;
pub mod sprouts;
mod vec3;
pub mod volume;

pub use cancel::Stop;
pub use error::{Error, Result};
pub use graph::{RunInfo, Skeleton, StageTime};
pub use params::{Params, Value};
pub use pipeline::{Progress, Skeletonizer};
pub use volume::Voxel;

/// Deterministic pseudo-random integers for the unit tests: `next(m)` lies in `0..m`
/// (the high bits of a 64-bit linear congruential generator).
#[cfg(test)]
pub(crate) fn test_rng(seed: u64) -> impl FnMut(u64) -> u64 {
    let mut state = seed;
    move |m| {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (state >> 33) % m
    }
}

/// Deterministic pseudo-random numbers in `[0, 1)` for the unit tests (the top 53 bits
/// of the same generator as [`test_rng`]).
#[cfg(test)]
pub(crate) fn test_unit_rng(seed: u64) -> impl FnMut() -> f64 {
    let mut state = seed;
    move || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// For the unit tests: the simple graph on `n` nodes with the given node pairs (loops
/// dropped, repeats merged), and its sorted edge list.
#[cfg(test)]
pub(crate) fn test_graph(n: usize, pairs: impl Iterator<Item = (u32, u32)>) -> (grid::Csr, Vec<(u32, u32)>) {
    let mut edges: Vec<(u32, u32)> = pairs.filter(|(a, b)| a != b).map(|(a, b)| (a.min(b), a.max(b))).collect();
    edges.sort_unstable();
    edges.dedup();
    (grid::Csr::from_sorted_edges(n, &edges), edges)
}
