//! Voxel tracking for chunked runs ([`crate::blocks`]): where every foreground voxel of
//! a run went ([`VoxelFate`]), followed through each decimation, and which output nodes
//! own a voxel of a block's core. The pipeline fills it; the block phase reads it.

use crate::grid::{Csr, GridGraph};
use crate::volume::Voxel;
use ndarray::ArrayView3;

/// Where every foreground voxel of a run went: its node now (voxels in C order), its
/// mask component, and the initial grid graph; with a coarse start, each node's radius
/// as the split of long edges reads it ([`crate::resample`]: its cluster's largest
/// transform value, which a chunked run's merge cannot rebuild from output radii) and
/// the split of every edge ([`crate::resample::split_chains`]).
#[derive(Debug, Clone)]
pub struct VoxelFate {
    pub node: Vec<u32>,
    pub component: Vec<u32>,
    pub grid: Csr,
    pub split_radius: Vec<f64>,
    pub chains: Vec<([u32; 2], Vec<u32>)>,
}

impl VoxelFate {
    pub(crate) fn new(grid: &GridGraph) -> VoxelFate {
        VoxelFate {
            node: (0..grid.positions.len() as u32).collect(),
            component: grid.component.clone(),
            grid: grid.graph.clone(),
            split_radius: vec![],
            chains: vec![],
        }
    }
}

/// Follow a decimation: `map` gives the new node of every old node.
pub(crate) fn follow(fate: &mut Option<VoxelFate>, map: &[u32]) {
    if let Some(f) = fate {
        for n in &mut f.node {
            *n = map[*n as usize];
        }
    }
}

/// True if block voxel `v` lies in `core` (half-open ranges per axis).
pub(crate) fn in_core(core: [[usize; 2]; 3], v: [usize; 3]) -> bool {
    (0..3).all(|d| core[d][0] <= v[d] && v[d] < core[d][1])
}

/// Which of a block's `nodes` output nodes the block hands to the merge, by `fate`:
/// those that own a voxel of its `core`, and the nodes a split put on an edge between
/// two of those (the block hands their chain over).
pub(crate) fn core_owners<T: Voxel>(
    mask: ArrayView3<'_, T>,
    core: [[usize; 2]; 3],
    fate: &VoxelFate,
    nodes: usize,
) -> Vec<bool> {
    let mut owns = vec![false; nodes];
    let voxels = mask.indexed_iter().filter(|(_, m)| m.is_set()).map(|((i, j, k), _)| [i, j, k]);
    for (id, v) in voxels.enumerate() {
        if in_core(core, v) {
            owns[fate.node[id] as usize] = true;
        }
    }
    for (ends, chain) in &fate.chains {
        if owns[ends[0] as usize] && owns[ends[1] as usize] {
            chain.iter().for_each(|&i| owns[i as usize] = true);
        }
    }
    owns
}
