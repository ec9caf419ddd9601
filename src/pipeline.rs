//! The Skeletonizer: EDT → grid graph → contraction (Algorithm 1) → refinement
//! (§III-G) → output, with per-stage timings and a progress observer.

use crate::cancel::{self, Stop};
use crate::coarse;
use crate::cycles::{refine_step, short_cycle_area, Cycle, Move};
use crate::decimate::{decimate_mapped, NodeGraph, CELL_LIMIT};
use crate::edges_inside::{route_with_radii, Routed};
use crate::ends::{extend_ends, follow_ends};
use crate::error::{Error, Result};
use crate::fate::{core_owners, follow, VoxelFate};
use crate::graph::{RunInfo, Skeleton, StageTime};
use crate::grid::{self, Csr};
use crate::inside::{keep_inside, loop_of_the_mask, undo_moves_off_the_mask, HeldOnMask, LOOP_RADIUS_SHIFT};
use crate::junctions::merge_close_junctions;
use crate::laplacian;
use crate::laplacian::NormalOperator;
use crate::medial;
use crate::memory;
use crate::packed::{PackedCsr, PackedNodes};
use crate::params::{AreaReference, Params, STALL_AREA};
use crate::precondition::{gather_in_place, scatter_in_place, slab_axes, slab_order, Krylov, NormalMatrix};
use crate::prune::prune_skeleton;
use crate::radius::output_radii;
use crate::resample;
use crate::smooth::smooth_skeleton;
use crate::solver::{self, SolveStats};
use crate::sprouts::{sprout, Grown, Reach};
use crate::vec3::base_cell;
use crate::volume::{check_spacing, edt_squared_rows, foreground_rows, Voxel};
use ndarray::ArrayView3;
use rayon::prelude::*;
use std::time::Instant;

/// A progress report, sent after every stage and every iteration.
#[derive(Debug, Clone, PartialEq)]
pub struct Progress {
    /// `"edt"`, `"grid"`, `"contract"`, `"refine"` or `"output"`.
    pub stage: &'static str,
    /// Iteration within the stage (0 for single-step stages).
    pub iteration: usize,
    /// Nodes in the graph now.
    pub nodes: usize,
    /// The convergence measure after a contraction iteration: the short-cycle area
    /// over the stop level, `A_t / (stop_ratio * A_ref)` (the contraction stops when it
    /// reaches 1). NaN in the other stages, which have no such measure.
    pub measure: f64,
}

/// The method with a fixed set of parameters.
#[derive(Debug, Clone)]
pub struct Skeletonizer {
    params: Params,
}

/// Wall time per stage, accumulated in first-use order.
#[derive(Debug, Default)]
pub struct StageClock(Vec<StageTime>);

impl StageClock {
    /// Run `f`, adding its wall time to `stage`.
    pub fn time<R>(&mut self, stage: &'static str, f: impl FnOnce() -> R) -> R {
        let t = Instant::now();
        let r = f();
        let dt = t.elapsed().as_secs_f64();
        match self.0.iter_mut().find(|s| s.stage == stage) {
            Some(s) => s.seconds += dt,
            None => self.0.push(StageTime { stage, seconds: dt }),
        }
        r
    }
}

fn report(
    observer: &mut dyn FnMut(&Progress) -> bool,
    stage: &'static str,
    iteration: usize,
    nodes: usize,
    measure: f64,
) -> Result<()> {
    debug_panic(stage);
    if observer(&Progress { stage, iteration, nodes, measure }) {
        Ok(())
    } else {
        Err(Error::Interrupted)
    }
}

/// Testing hook of the front ends' last line of defence: with the environment
/// variable `VESSELFLOW_DEBUG_PANIC` set to a stage name (`edt`, `grid`, `contract`,
/// ...), the run panics when it reports that stage, as a bug would. The command line
/// and the Python module must turn this into an "internal error" (see
/// [`crate::error::catch_panic`]).
#[doc(hidden)]
pub fn debug_panic(stage: &str) {
    if std::env::var_os("VESSELFLOW_DEBUG_PANIC").is_some_and(|s| s == stage) {
        panic!("VESSELFLOW_DEBUG_PANIC: forced panic at stage `{stage}`");
    }
}

/// One contraction iteration (Algorithm 1, lines 3–7): weights and anchoring from the
/// current geometry, the least-squares solve of eq. 8, the moves off `mask` undone
/// ([`undo_moves_off_the_mask`]), and decimation, with the time of each part added to
/// `clock`. The solve's rows are put in slabs along `axes[0]` when given
/// ([`slab_axes`]), which changes its rounding, not its minimiser. Runs on the current
/// rayon pool.
#[allow(clippy::too_many_arguments)]
pub fn contract_step<T: Voxel>(
    g: NodeGraph,
    p: &Params,
    c: f64,
    axes: Option<[usize; 3]>,
    clock: &mut StageClock,
    mask: ArrayView3<'_, T>,
    spacing: [f64; 3],
) -> Result<(NodeGraph, SolveStats)> {
    contract_step_mapped(g, p, p.cg_tol, c, axes, clock, mask, spacing).map(|(next, stats, _)| (next, stats))
}

/// [`contract_step`] that also returns the new node of every old node
/// ([`decimate_mapped`]), with the solve's relative residual `tol` in place of
/// `p.cg_tol` (the run's schedule: [`solver::solve_tolerance`]).
#[allow(clippy::too_many_arguments)]
pub fn contract_step_mapped<T: Voxel>(
    mut g: NodeGraph,
    p: &Params,
    tol: f64,
    c: f64,
    axes: Option<[usize; 3]>,
    clock: &mut StageClock,
    mask: ArrayView3<'_, T>,
    spacing: [f64; 3],
) -> Result<(NodeGraph, SolveStats, Vec<u32>)> {
    let skeletal = clock.time("laplacian", || laplacian::skeletal(&g.graph, &g.positions, p));
    cancel::checkpoint()?;
    let order = axes.map(|axes| clock.time("solve", || slab_order(&g.positions, c, axes)));
    cancel::checkpoint()?;
    // The Laplacians (one row total per node: their weights are computed as `M` reads
    // them) are dropped once `M` is assembled: the right-hand side comes from `M`
    // itself, and the conjugate-gradient vectors are allocated after. The radii and
    // components are not read again until the decimation, nor the graph once `M` is
    // assembled: they wait packed ([`crate::packed`]) while the solve runs.
    let m = {
        let (ln, lm) = clock.time("laplacian", || {
            (laplacian::l2_norm(&g.graph, &g.positions), laplacian::medial(&g.graph, &g.radii, p.medial_weight))
        });
        cancel::checkpoint()?;
        return_free_memory();
        let op = NormalOperator::new(&g.graph, &ln, &lm, &skeletal, p);
        clock.time("solve", || NormalMatrix::assemble(&op, order.as_deref()))
    };
    let nodes =
        clock.time("solve", || PackedNodes::new(std::mem::take(&mut g.radii), std::mem::take(&mut g.component)));
    // The assembly stops early too (a partial matrix).
    cancel::checkpoint()?;
    // The positions in the solve's order, permuted in place.
    let mut start = std::mem::take(&mut g.positions);
    if let Some(order) = &order {
        clock.time("solve", || gather_in_place(&mut start, order));
    }
    // The rule holds the nodes of curves (degree 1 or 2): a loop's ring, a bent vessel.
    // The knots the flow has still to collapse (nodes of degree 3 or more) move freely:
    // held, they stop collapsing where the mask is a voxel thin, and the contraction
    // ran to `max_iterations` on two VascuSynth trees. Their positions before the move,
    // in the solve's order, are kept from here rather than from the start, so that
    // they are not held while `M` is assembled.
    let node = |k: usize| order.as_ref().map_or(k, |o| o[k] as usize);
    let curve = |k: usize| g.graph.neighbours(node(k)).len() <= 2;
    let held = clock.time("solve", || HeldOnMask::new(&start, &curve, mask, spacing));
    let graph = clock.time("solve", || PackedCsr::new(std::mem::take(&mut g.graph)));
    return_free_memory();
    let k = clock.time("solve", || Krylov::displacement(&m, start));
    let (mut moved, stats) = clock.time("solve", || solver::solve(&m, k, tol, p.cg_max_iterations));
    drop(m);
    // The solve stops early when the run is asked to stop: its result is partial.
    cancel::checkpoint()?;
    return_free_memory();
    g.graph = clock.time("solve", || graph.unpack());
    clock.time("solve", || undo_moves_off_the_mask(&mut moved, &held, mask, spacing));
    drop(held);
    (g.radii, g.component) = clock.time("solve", || nodes.unpack());
    if let Some(order) = &order {
        clock.time("solve", || scatter_in_place(&mut moved, order));
    }
    g.positions = moved;
    let (next, map) = clock.time("decimate", || decimate_mapped(&g, &skeletal, c))?;
    // The old graph is freed before the next stage (the cycles' area) allocates.
    drop((g, skeletal));
    return_free_memory();
    Ok((next, stats, map))
}

/// Hand the pages of freed memory back to the system. glibc keeps freed blocks below
/// its (adaptive, up to 32 MiB) mmap threshold for reuse, so without this the
/// Laplacians freed before the solve, and the matrix freed after it, stay resident
/// while the next arrays are allocated: on the 256³ bed the peak RSS is 281 MB
/// without it and 243 MB with it, for ~1 % more time (the next decimation faults its
/// pages in again). Elsewhere a no-op.
fn return_free_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `malloc_trim` only releases free memory; glibc makes it safe to call
    // from any thread at any time.
    unsafe {
        libc::malloc_trim(0);
    }
}

impl Skeletonizer {
    /// Check the parameters and keep them.
    pub fn new(params: Params) -> Result<Self> {
        // Re-applying every value through the checked setter validates a `Params`
        // built field by field in Rust just as one built from names.
        Params::from_pairs(params.values())?;
        Ok(Skeletonizer { params })
    }

    /// The parameters in force.
    pub fn params(&self) -> &Params {
        &self.params
    }

    /// Skeletonize `mask` (non-zero = vessel) with voxel `spacing` (physical units per
    /// voxel along axes 0, 1, 2). `observer` gets every [`Progress`] report and stops
    /// the run with [`Error::Interrupted`] by returning `false`.
    ///
    /// An empty mask gives an empty graph. A mask that is foreground everywhere is a
    /// solid block (voxels outside the array count as background) and gets its graph.
    ///
    /// `spacing` must lie in [[`MIN_SPACING`](crate::volume::MIN_SPACING), [`MAX_SPACING`](crate::volume::MAX_SPACING)] on every axis, and no
    /// axis may span 2²⁰ or more base cells (`size * spacing / min(spacing)`).
    pub fn run<T: Voxel>(
        &self,
        mask: ArrayView3<'_, T>,
        spacing: [f64; 3],
        observer: &mut dyn FnMut(&Progress) -> bool,
    ) -> Result<Skeleton> {
        self.run_block(mask, [0; 3], spacing, observer)
    }

    /// [`Skeletonizer::run`] that also stops, with [`Error::Interrupted`], soon after
    /// `stop` is requested from another thread or a signal handler: the long stages
    /// poll it inside their loops (every conjugate-gradient iteration, every few
    /// thousand rows), not only between stages.
    pub fn run_with_stop<T: Voxel>(
        &self,
        mask: ArrayView3<'_, T>,
        spacing: [f64; 3],
        stop: &Stop,
        observer: &mut dyn FnMut(&Progress) -> bool,
    ) -> Result<Skeleton> {
        self.run_block_with_stop(mask, [0; 3], spacing, stop, observer)
    }

    /// [`Skeletonizer::run`] on a block of a larger volume whose voxel `(0, 0, 0)` is
    /// voxel `offset` of the whole. The block is processed in its own coordinates and
    /// its positions are shifted by `offset * spacing` at the end, so the graph is the
    /// same, bit for bit, wherever the block sits; when block origins are whole base
    /// cells apart (`offset * spacing / c` integer, e.g. isotropic grids), the block's
    /// cells are those of the global cell grid, so blocks can be merged by cell.
    pub fn run_block<T: Voxel>(
        &self,
        mask: ArrayView3<'_, T>,
        offset: [i64; 3],
        spacing: [f64; 3],
        observer: &mut dyn FnMut(&Progress) -> bool,
    ) -> Result<Skeleton> {
        self.run_block_with_stop(mask, offset, spacing, &Stop::new(), observer)
    }

    /// [`Skeletonizer::run_block`] with a [`Stop`] flag, as in
    /// [`Skeletonizer::run_with_stop`].
    pub fn run_block_with_stop<T: Voxel>(
        &self,
        mask: ArrayView3<'_, T>,
        offset: [i64; 3],
        spacing: [f64; 3],
        stop: &Stop,
        observer: &mut dyn FnMut(&Progress) -> bool,
    ) -> Result<Skeleton> {
        self.run_tracked(mask, offset, spacing, stop, observer, None).map(|(skeleton, ..)| skeleton)
    }

    /// [`Skeletonizer::run_block_with_stop`] that, with a block's `core` (half-open
    /// ranges per axis), also follows every foreground voxel to its output node
    /// ([`VoxelFate`], for chunked runs) and measures the radii only of the nodes the
    /// merge reads: those that own a core voxel, the nodes a split put between two of
    /// those, and the ends (whose moves bound one another's). Also returns the sprouts grown (their nodes own no voxel: the merge
    /// attaches them).
    pub(crate) fn run_tracked<T: Voxel>(
        &self,
        mask: ArrayView3<'_, T>,
        offset: [i64; 3],
        spacing: [f64; 3],
        stop: &Stop,
        observer: &mut dyn FnMut(&Progress) -> bool,
        core: Option<[[usize; 2]; 3]>,
    ) -> Result<(Skeleton, Option<VoxelFate>, Vec<Grown>)> {
        check_spacing(spacing)?;
        check_shape(mask)?;
        let c = base_cell(spacing);
        let (n0, n1, n2) = mask.dim();
        for (d, n) in [n0, n1, n2].into_iter().enumerate() {
            let far = n as f64 * spacing[d] / c;
            if far >= (CELL_LIMIT - 2) as f64 {
                return Err(Error::InvalidMask(format!(
                    "axis {d} spans {far:.0} base cells (size {n}, spacing {}); at most {} are supported",
                    spacing[d],
                    CELL_LIMIT - 2
                )));
            }
        }
        let axes = slab_axes([n0, n1, n2]);
        let on_start = stop.clone();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(self.params.threads)
            .start_handler(move |_| on_start.install_on_thread())
            .build()
            .map_err(|e| Error::ThreadPool { threads: self.params.threads, reason: e.to_string() })?;
        let p = &self.params;
        let mut clock = StageClock::default();
        let mut info = RunInfo::default();

        // Every stage may return early, with a partial result, once `stop` is
        // requested: `stop.check()` follows each before its result is used.
        stop.check()?;
        // Count the foreground (one cheap pass), and refuse a run that would need more
        // memory than `max_memory` before any heavy stage.
        let (starts, edt) = clock.time("edt", || -> Result<(Vec<usize>, Vec<f32>)> {
            let starts = pool.install(|| foreground_rows(mask))?;
            let shape = [n0, n1, n2];
            let need = memory::estimate(shape, starts[n0 * n1], p.connectivity, pool.current_num_threads());
            memory::check(need.peak(), p.max_memory.unwrap_or(0))?;
            let edt = pool.install(|| edt_squared_rows(mask, &starts, spacing))?;
            Ok((starts, edt))
        })?;
        stop.check()?;
        report(observer, "edt", 0, 0, f64::NAN)?;
        let grid = clock.time("grid", || pool.install(|| grid::build(mask, &edt, spacing, p)))?;
        stop.check()?;
        let n = grid.positions.len();
        info.foreground_voxels = n;
        info.mask_components = grid.components;
        report(observer, "grid", 0, n, f64::NAN)?;
        let mut fate = core.is_some().then(|| VoxelFate::new(&grid));
        // Off, the start graph is the grid graph (no stage in the timings).
        let (mut g, map) = if p.coarse_cell > 0.0 {
            clock.time("coarse", || pool.install(|| coarse::coarsen(grid, spacing, p.coarse_cell, offset)))
        } else {
            coarse::coarsen(grid, spacing, 0.0, offset)
        };
        follow(&mut fate, &map);
        drop(map);
        return_free_memory();
        stop.check()?;

        // Contraction (Algorithm 1).
        let area = |g: &NodeGraph| pool.install(|| short_cycle_area(&g.graph, &g.positions, p.max_cycle_nodes));
        let a0 = clock.time("cycles", || area(&g));
        stop.check()?;
        info.area_reference = p.stop_ratio
            * match p.area_reference {
                // Foreground volume in base cells, times c²: N c² when isotropic.
                AreaReference::Volume => n as f64 * spacing.iter().product::<f64>() / c,
                AreaReference::InitialArea => a0,
            };
        info.nodes_per_iteration.push(g.positions.len());
        info.area_per_iteration.push(a0);
        let mut a_t = a0;
        info.converged = a_t <= info.area_reference;
        while !info.converged && info.iterations < p.max_iterations {
            let tol = solver::solve_tolerance(p.cg_tol, a_t / info.area_reference);
            let (next, stats, map) = pool
                .install(|| contract_step_mapped(std::mem::take(&mut g), p, tol, c, axes, &mut clock, mask, spacing))?;
            follow(&mut fate, &map);
            g = next;
            a_t = clock.time("cycles", || area(&g));
            stop.check()?;
            info.iterations += 1;
            info.cg_iterations.push(stats.iterations);
            info.cg_unconverged += usize::from(!stats.converged);
            info.nodes_per_iteration.push(g.positions.len());
            info.area_per_iteration.push(a_t);
            info.converged = a_t <= info.area_reference;
            let [before, after] = [info.nodes_per_iteration.len() - 2, info.nodes_per_iteration.len() - 1]
                .map(|k| info.nodes_per_iteration[k] as f64);
            info.stalled =
                !info.converged && after > (1.0 - p.stall_ratio) * before && a_t <= STALL_AREA * info.area_reference;
            let measure = if info.area_reference > 0.0 { a_t / info.area_reference } else { 0.0 };
            report(observer, "contract", info.iterations, g.positions.len(), measure)?;
            if info.stalled {
                break;
            }
        }

        // Refinement (§III-G).
        let max_area = p.refine_area * c * c;
        let shift = LOOP_RADIUS_SHIFT * c;
        info.refine_converged = false;
        while info.refine_iterations < p.max_refine_iterations {
            let step = clock.time("refine", || {
                let hole = |c: &Cycle| loop_of_the_mask(c, &g.positions, &g.radii, shift, mask, spacing);
                pool.install(|| refine_step(&g.graph, &g.positions, p.max_cycle_nodes, max_area, &hole, Move::Centroid))
            });
            stop.check()?;
            let Some((positions, moved, _)) = step else {
                info.refine_converged = true;
                break;
            };
            g.positions = positions;
            let keep: Vec<bool> = moved.iter().map(|m| !m).collect();
            let (next, map) = clock.time("refine", || pool.install(|| decimate_mapped(&g, &keep, c)))?;
            follow(&mut fate, &map);
            g = next;
            info.refine_iterations += 1;
            report(observer, "refine", info.refine_iterations, g.positions.len(), f64::NAN)?;
        }
        if info.refine_iterations == 0 {
            report(observer, "refine", 0, g.positions.len(), f64::NAN)?;
        }
        if !info.refine_converged {
            let hole = |c: &Cycle| loop_of_the_mask(c, &g.positions, &g.radii, shift, mask, spacing);
            info.refine_converged = pool
                .install(|| refine_step(&g.graph, &g.positions, p.max_cycle_nodes, max_area, &hole, Move::Centroid))
                .is_none();
            stop.check()?;
        }

        // With a coarse start, edges longer than its cells are split (`resample`); the
        // old nodes keep their numbers, so the voxels' fate needs no update, and the new
        // ones are numbered from `split`.
        let split = g.positions.len();
        if p.coarse_cell > 0.0 {
            let decide = g.radii.clone();
            g = clock.time("resample", || {
                resample::split_long_edges(std::mem::take(&mut g), &decide, p.coarse_cell, spacing, &[])
            });
            if let Some(f) = &mut fate {
                f.split_radius = decide;
                f.chains = resample::split_chains(&g.graph, split);
            }
        }

        // The distance transform, for the medial stage and the routing of edges: the
        // first stage's, kept (4 bytes per vessel voxel) rather than computed again.
        let field =
            clock.time("medial", || pool.install(|| medial::Field::from_squared(mask, spacing, starts, edt)))?;
        stop.check()?;
        if p.medial {
            g.positions =
                clock.time("medial", || pool.install(|| medial::settle(&g.graph, &g.positions, &g.radii, &field)));
        }

        let (out, grown) = clock.time("output", || -> Result<(Skeleton, Vec<Grown>)> {
            g.positions = pool.install(|| keep_inside(&g.positions, mask, spacing));
            // The nodes the split added take the transform where they now sit.
            if p.coarse_cell > 0.0 {
                resample::ridge_radii(&mut g.radii, &g.positions, split, &field);
            }
            let shift = p.radius_correction * c;
            // The graph's geodesic reach through the mask, for the sprouts, runs beside
            // the radii and the ends (one thread of its own; it is a serial search).
            let sprouts = p.sprouts;
            let owners = match (core, &fate) {
                (Some(core), Some(fate)) => Some(core_owners(mask, core, fate, g.positions.len())),
                _ => None,
            };
            let measure = |i: usize| owners.as_ref().is_none_or(|o| o[i] || g.graph.neighbours(i).len() == 1);
            let (reach, (radii, positions)) = pool.install(|| {
                rayon::join(
                    || sprouts.then(|| Reach::of(&g.graph, &g.positions, &field, spacing)).transpose(),
                    || {
                        // One radius rule for every output node, the routed-in ones too.
                        let radii =
                            output_radii(&g.graph, &g.positions, &g.radii, &measure, mask, &field, spacing, shift);
                        if !p.anchor_ends {
                            return (radii, g.positions.clone());
                        }
                        // A moved end can stop past a background voxel the line grazed
                        // between two samples: it is kept inside once more.
                        let (ends, end_radii) = extend_ends(&g.graph, &g.positions, &radii, mask, &field, spacing);
                        let ends = follow_ends(&g.graph, &ends, &end_radii, mask, spacing);
                        (radii, keep_inside(&ends, mask, spacing))
                    },
                )
            });
            let (graph, positions, radii, sprouts) = match reach? {
                Some(reach) => pool.install(|| {
                    with_sprouts(reach, &g.graph, &g.radii, positions, radii, &measure, mask, &field, spacing, shift)
                })?,
                None => (std::mem::take(&mut g.graph), positions, radii, vec![]),
            };
            let (routed, inserted) =
                pool.install(|| route_with_radii(&graph, &positions, &field, mask, spacing, shift));
            let mut radii = radii;
            radii.extend(inserted);
            let Routed { graph, positions, .. } = routed;
            let out = Skeleton {
                radii,
                edges: graph.edge_list().into_iter().map(|(a, b)| [a as usize, b as usize]).collect(),
                positions: positions
                    .iter()
                    .map(|q| std::array::from_fn(|d| q[d] + offset[d] as f64 * spacing[d]))
                    .collect(),
                spacing,
                info: RunInfo::default(),
            };
            // Last, the short spurs and the radii along the branches; a chunked run's
            // blocks leave them to the end of the merge, whose graph their nodes'
            // voxels build.
            let out = if core.is_none() { finish(out, p) } else { out };
            Ok((out, sprouts))
        })?;
        stop.check()?;
        check_skeleton(&out)?;
        report(observer, "output", 0, out.positions.len(), f64::NAN)?;
        info.sprouts = grown.len();
        info.pruned_spurs = out.info.pruned_spurs;
        info.stage_seconds = clock.0;
        Ok((Skeleton { info, ..out }, fate, grown))
    }
}

/// An output graph, its positions and radii, and the sprouts it grew.
type Sprouted = (Csr, Vec<[f64; 3]>, Vec<f64>, Vec<Grown>);

/// The output graph (`g`, `positions`, `radii`) with its lost side branches grown back
/// ([`sprout`]): the new nodes on vessel voxels, their radii by the one rule from the
/// transform where they sit (`edt`: the old nodes' largest transform values); and the
/// sprouts. A node that `measured` leaves out (a chunked run's block measures only the
/// nodes it owns, the others have radius 0) gives its largest transform value to the
/// test of whether a sprout from its edges is long enough: with 0 every sprout from
/// the halo's edges passed it, and thick vessels grew sprouts to their walls near cuts.
#[allow(clippy::too_many_arguments)]
fn with_sprouts<T: Voxel>(
    reach: Reach<'_>,
    g: &Csr,
    edt: &[f64],
    positions: Vec<[f64; 3]>,
    mut radii: Vec<f64>,
    measured: &dyn Fn(usize) -> bool,
    mask: ArrayView3<'_, T>,
    field: &medial::Field,
    spacing: [f64; 3],
    shift: f64,
) -> Result<Sprouted> {
    let n = positions.len();
    let parents: Vec<f64> = (0..n).map(|i| if measured(i) { radii[i] } else { edt[i] }).collect();
    let (graph, mut positions, grown) = sprout(reach, g, &positions, &parents)?;
    let inside = keep_inside(&positions[n..], mask, spacing);
    positions[n..].copy_from_slice(&inside);
    let edt: Vec<f64> = edt.iter().copied().chain(positions[n..].iter().map(|&q| field.radius_at(q))).collect();
    let all = output_radii(&graph, &positions, &edt, &|i| i >= n, mask, field, spacing, shift);
    radii.extend_from_slice(&all[n..]);
    Ok((graph, positions, radii, grown))
}

/// Refuse, before any work, a mask whose shape the stages cannot index: a voxel count
/// that overflows, or more foreground voxels than 32-bit node ids can number. (Block
/// offsets need no check: `|offset * spacing| <= 2⁶³ * 1e12` is finite.)
fn check_shape<T: Voxel>(mask: ArrayView3<'_, T>) -> Result<()> {
    let (n0, n1, n2) = mask.dim();
    let voxels = n0.checked_mul(n1).and_then(|v| v.checked_mul(n2)).filter(|&v| v <= isize::MAX as usize);
    let Some(voxels) = voxels else {
        return Err(Error::InvalidMask(format!("shape {n0} x {n1} x {n2} has more voxels than can be addressed")));
    };
    // Node ids are `u32` (`u32::MAX` marks "none"). Counted only when it could matter.
    if voxels >= u32::MAX as usize {
        let foreground = mask.as_slice_memory_order().map_or_else(
            || mask.iter().filter(|v| v.is_set()).count(),
            |s| s.par_iter().filter(|v| v.is_set()).count(),
        );
        if foreground >= u32::MAX as usize {
            return Err(Error::InvalidMask(format!(
                "{foreground} foreground voxels; at most {} are supported",
                u32::MAX - 1
            )));
        }
    }
    Ok(())
}

/// The output's last steps, on a single run's graph and on a chunked run's merged one:
/// the short spurs pruned ([`crate::prune`]), the junctions closer than half a radius
/// joined ([`crate::junctions`]), then the radii smoothed along the branches that are
/// left ([`crate::smooth`]).
pub(crate) fn finish(out: Skeleton, p: &Params) -> Skeleton {
    let pruned = prune_skeleton(out, p.prune_spurs);
    smooth_skeleton(merge_close_junctions(pruned, p.merge_junctions), p.radius_smoothing)
}

/// Check the output graph before it is returned: positions finite, radii finite and
/// ≥ 0, one radius per node, edges between existing nodes and no self-loops. A
/// failure is a bug of the method, reported as [`Error::Internal`] rather than
/// returned as a silently wrong graph.
pub fn check_skeleton(s: &Skeleton) -> Result<()> {
    let n = s.positions.len();
    let bad = |what: String| Err(Error::Internal(format!("the output graph {what}")));
    if s.radii.len() != n {
        return bad(format!("has {} radii for {n} nodes", s.radii.len()));
    }
    if let Some(i) = s.positions.iter().position(|q| !q.iter().all(|x| x.is_finite())) {
        return bad(format!("has a non-finite position at node {i}: {:?}", s.positions[i]));
    }
    if let Some(i) = s.radii.iter().position(|r| !(r.is_finite() && *r >= 0.0)) {
        return bad(format!("has an invalid radius at node {i}: {}", s.radii[i]));
    }
    if let Some(e) = s.edges.iter().find(|e| e[0] >= n || e[1] >= n || e[0] == e[1]) {
        return bad(format!("has an edge {e:?} that is a self-loop or leaves the {n} nodes"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn good() -> Skeleton {
        Skeleton {
            positions: vec![[0.0, 1.0, 2.0], [1.0, 1.0, 2.0], [2.0, 1.0, 2.0]],
            radii: vec![0.5, 0.0, 1.0],
            edges: vec![[0, 1], [1, 2]],
            spacing: [1.0; 3],
            info: RunInfo::default(),
        }
    }

    #[test]
    fn the_output_check_refuses_every_kind_of_broken_graph() {
        assert_eq!(check_skeleton(&good()), Ok(()));
        assert_eq!(check_skeleton(&Skeleton::default()), Ok(()));
        type Break = Box<dyn Fn(&mut Skeleton)>;
        let broken: Vec<(&str, Break)> = vec![
            ("NaN position", Box::new(|s| s.positions[1][2] = f64::NAN)),
            ("infinite position", Box::new(|s| s.positions[0][0] = f64::NEG_INFINITY)),
            ("negative radius", Box::new(|s| s.radii[2] = -0.1)),
            ("infinite radius", Box::new(|s| s.radii[0] = f64::INFINITY)),
            ("NaN radius", Box::new(|s| s.radii[1] = f64::NAN)),
            ("missing radius", Box::new(|s| s.radii.truncate(2))),
            ("edge out of range", Box::new(|s| s.edges.push([1, 3]))),
            ("self-loop", Box::new(|s| s.edges.push([2, 2]))),
        ];
        for (what, breaks) in broken {
            let mut s = good();
            breaks(&mut s);
            let e = check_skeleton(&s).unwrap_err();
            assert!(matches!(e, Error::Internal(_)), "{what}: {e}");
            assert!(e.to_string().starts_with("internal error, please report: the output graph"), "{what}: {e}");
        }
    }
}
