//! The output graph (docs/method.md §4): dense centreline nodes with radii, and the
//! record of the run that made them.

/// One stage's wall time.
#[derive(Debug, Clone, PartialEq)]
pub struct StageTime {
    pub stage: &'static str,
    pub seconds: f64,
}

/// What happened during a run.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RunInfo {
    /// Foreground voxels of the mask (initial nodes).
    pub foreground_voxels: usize,
    /// 26-connected components of the mask (= components of the output graph).
    pub mask_components: usize,
    /// Contraction iterations run.
    pub iterations: usize,
    /// Whether the cycle-area test stopped the contraction.
    pub converged: bool,
    /// Whether the stall test stopped it (`Params::stall_ratio`); when neither this nor
    /// `converged` holds, it ran to `max_iterations`.
    pub stalled: bool,
    /// Refinement iterations run.
    pub refine_iterations: usize,
    /// Whether refinement ended with no small cycle left (false: hit its cap).
    pub refine_converged: bool,
    /// Nodes after each contraction iteration (entry 0: the initial grid graph).
    pub nodes_per_iteration: Vec<usize>,
    /// Short-cycle area `A_t`, physical units squared: entry 0 of the initial grid
    /// graph, then after each contraction iteration (indexed like `nodes_per_iteration`).
    pub area_per_iteration: Vec<f64>,
    /// The stop level: `stop_ratio` times the reference area; the contraction stops
    /// at the first `A_t` at or below it.
    pub area_reference: f64,
    /// Conjugate-gradient iterations of each contraction iteration.
    pub cg_iterations: Vec<usize>,
    /// Solves that hit `cg_max_iterations` before reaching `cg_tol`.
    pub cg_unconverged: usize,
    /// Side branches grown back at output (`Params::sprouts`).
    pub sprouts: usize,
    /// Short terminal spurs removed last (`Params::prune_spurs`).
    pub pruned_spurs: usize,
    /// Wall time per stage, in pipeline order.
    pub stage_seconds: Vec<StageTime>,
}

/// A centreline graph: node positions (physical units, array axis order), radii
/// (physical units) and undirected edges `i < j`, sorted, without duplicates.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Skeleton {
    pub positions: Vec<[f64; 3]>,
    pub radii: Vec<f64>,
    pub edges: Vec<[usize; 2]>,
    pub spacing: [f64; 3],
    pub info: RunInfo,
}

impl Skeleton {
    /// Number of nodes.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True when the graph has no node.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Degree of every node.
    pub fn degrees(&self) -> Vec<usize> {
        let mut d = vec![0; self.len()];
        for &[a, b] in &self.edges {
            d[a] += 1;
            d[b] += 1;
        }
        d
    }
}
