//! Routing phase of a chunked run (after [`Skeletonizer::merge_blocks`]): the merged
//! edges that cross background are routed inside the mask by the single run's own
//! routing ([`crate::edges_inside::route_with_radii`]), block by block.
//!
//! - **Owner**: every merged edge belongs to the block whose core holds its owner
//!   voxel ([`owner_voxel`]: the voxel its midpoint rounds to, clamped to the volume),
//!   so it has exactly one owner, whatever the float differences between blocks.
//! - **Block** ([`Skeletonizer::route_block`]): the worker reads its block with a halo,
//!   keeps the owned edges that cross background in that read (the others are left as
//!   they are, as the single run's routing leaves them; a block with none stops there),
//!   computes the distance transform of block plus halo and routes those edges,
//!   each in a box that must lie in the read: the edge's bounding box grown by the
//!   routing's reach ([`needed_margin`]: the nearest-foreground search, the climb's
//!   reach, counted twice so that the distance transform there is the whole volume's,
//!   and the voxel-path margin). When the read is too small the block returns the halo
//!   it needs, and the caller reads it again with that halo.
//! - **Splice** ([`Skeletonizer::splice_routes`]): the routed parts, in block order, replace their
//!   edges by paths through new nodes, numbered after the merged nodes in block order,
//!   then edge order: the same graph, bit for bit, for any worker count.

use crate::blocks::{block_pool, check_core};
use crate::edges_inside::{outside_run, path_margin, route_with_radii};
use crate::error::{Error, Result};
use crate::graph::Skeleton;
use crate::grid::Csr;
use crate::inside::SEARCH_LIMIT;
use crate::medial::Field;
use crate::pipeline::Skeletonizer;
use crate::vec3::base_cell;
use crate::volume::{check_spacing, Voxel};
use ndarray::ArrayView3;

/// The voxel that owns the edge `p`–`q` (global physical positions): the voxel its
/// midpoint rounds to, clamped to the volume of shape `volume`.
pub fn owner_voxel(p: [f64; 3], q: [f64; 3], spacing: [f64; 3], volume: [usize; 3]) -> [usize; 3] {
    std::array::from_fn(|d| {
        let v = ((p[d] + q[d]) * 0.5 / spacing[d]).round().max(0.0);
        (v as usize).min(volume[d].saturating_sub(1))
    })
}

/// Voxels along axis `d` the routing of an edge may read beyond the edge's bounding box,
/// given `reach`, the larger distance-transform value at its ends in base cells.
pub fn needed_margin(reach: f64, spacing: [f64; 3], d: usize) -> f64 {
    let c = base_cell(spacing);
    (SEARCH_LIMIT + path_margin(spacing)[d] + 1) as f64 + 2.0 * (reach + 1.0) * c / spacing[d]
}

/// What the routing phase returns for one block.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RoutedPart {
    /// Merged edges (global node ids) this block routed, sorted: they leave the graph.
    pub replaced: Vec<[u32; 2]>,
    /// The new nodes: positions (global, physical units) and radii.
    pub positions: Vec<[f64; 3]>,
    pub radii: Vec<f64>,
    /// The edges that replace them: a merged node's global id (`>= 0`), or `-(k + 1)`
    /// for the block's new node `k`.
    pub edges: Vec<[i64; 2]>,
    /// The halo per axis (voxels around the core) the owned edges need, when the read
    /// was smaller; then nothing else is filled.
    pub halo: Option<[usize; 3]>,
}

impl Skeletonizer {
    /// The routing phase on one block (module doc). `mask` is the block with a halo, its
    /// voxel `(0, 0, 0)` voxel `origin` of a volume of shape `volume`, `core` the core in
    /// block indices; `nodes` the merged nodes the owned `edges` join (global ids,
    /// ascending) and `positions` theirs (global, physical); `edges` sorted pairs of
    /// global ids `a < b`, each owned by this block ([`owner_voxel`]).
    #[allow(clippy::too_many_arguments)]
    pub fn route_block<T: Voxel>(
        &self,
        mask: ArrayView3<'_, T>,
        origin: [i64; 3],
        core: [[usize; 2]; 3],
        volume: [usize; 3],
        spacing: [f64; 3],
        nodes: &[u32],
        positions: &[[f64; 3]],
        edges: &[[u32; 2]],
    ) -> Result<RoutedPart> {
        check_spacing(spacing)?;
        let shape: [usize; 3] = mask.dim().into();
        check_core(shape, origin, core, volume)?;
        if nodes.len() != positions.len() || nodes.windows(2).any(|w| w[0] >= w[1]) {
            return Err(Error::InvalidMask("route_block: nodes must be ascending, one position each".into()));
        }
        let local = |g: u32| nodes.binary_search(&g).map(|i| i as u32);
        let mut pairs = Vec::with_capacity(edges.len());
        for (i, &[a, b]) in edges.iter().enumerate() {
            let (Ok(la), Ok(lb)) = (local(a), local(b)) else {
                return Err(Error::InvalidMask(format!("route_block: edge {a}-{b} joins a node not given")));
            };
            if a >= b || (i > 0 && edges[i - 1] >= [a, b]) {
                return Err(Error::InvalidMask("route_block: edges must be sorted pairs a < b".into()));
            }
            let o = owner_voxel(positions[la as usize], positions[lb as usize], spacing, volume);
            if (0..3).any(|d| {
                let g = o[d] as i64 - origin[d];
                g < core[d][0] as i64 || g >= core[d][1] as i64
            }) {
                return Err(Error::InvalidMask(format!("route_block: edge {a}-{b} is owned by another block")));
            }
            pairs.push((la, lb));
        }
        let shifted: Vec<[f64; 3]> =
            positions.iter().map(|q| std::array::from_fn(|d| q[d] - origin[d] as f64 * spacing[d])).collect();
        // Only the edges that cross background are routed (the routing's own first test,
        // [`outside_run`]): the others keep their place, need no halo and no distance
        // transform, which a block whose edges all stay inside then never computes.
        pairs.retain(|&(a, b)| outside_run(&mask, shifted[a as usize], shifted[b as usize], spacing).is_some());
        if pairs.is_empty() {
            return Ok(RoutedPart::default());
        }
        let pool = block_pool(self.params().threads)?;
        let field = pool.install(|| Field::new(mask, spacing))?;

        // The halo every owned edge needs; the read must hold it, except at the volume's faces.
        let mut need = [0i64; 3];
        let mut short = false;
        for &(a, b) in &pairs {
            let (p, q) = (shifted[a as usize], shifted[b as usize]);
            let reach = field.interpolate(p).max(field.interpolate(q));
            for d in 0..3 {
                let m = needed_margin(reach, spacing, d);
                let lo = ((p[d].min(q[d]) / spacing[d] - m).floor() as i64).max(-origin[d]);
                let top = volume[d] as i64 - 1 - origin[d];
                let hi = ((p[d].max(q[d]) / spacing[d] + m).ceil() as i64).min(top);
                short |= lo < 0 || hi >= shape[d] as i64;
                need[d] = need[d].max(core[d][0] as i64 - lo).max(hi - (core[d][1] as i64 - 1));
            }
        }
        if short {
            return Ok(RoutedPart { halo: Some(need.map(|x| x.max(0) as usize)), ..RoutedPart::default() });
        }

        let g = Csr::from_sorted_edges(nodes.len(), &pairs);
        let c = base_cell(spacing);
        let shift = self.params().radius_correction * c;
        let (routed, radii) = pool.install(|| route_with_radii(&g, &shifted, &field, mask, spacing, shift));
        let old = nodes.len();
        let id = |i: u32| if (i as usize) < old { nodes[i as usize] as i64 } else { -(i as i64 - old as i64 + 1) };
        let kept = routed.graph.edge_list();
        let replaced = pairs
            .iter()
            .filter(|e| kept.binary_search(e).is_err())
            .map(|&(a, b)| [nodes[a as usize], nodes[b as usize]]);
        Ok(RoutedPart {
            replaced: replaced.collect(),
            positions: routed.positions[old..]
                .iter()
                .map(|q| std::array::from_fn(|d| q[d] + origin[d] as f64 * spacing[d]))
                .collect(),
            radii,
            edges: kept
                .into_iter()
                .filter(|&(a, b)| a as usize >= old || b as usize >= old)
                .map(|(a, b)| [id(a), id(b)])
                .collect(),
            halo: None,
        })
    }
}

impl Skeletonizer {
    /// The merged graph with the routed parts (in block order) spliced in (module
    /// doc), and last its short spurs pruned ([`crate::prune`]).
    pub fn splice_routes(&self, merged: Skeleton, parts: &[RoutedPart]) -> Result<Skeleton> {
        let Skeleton { mut positions, mut radii, edges, spacing, info } = merged;
        let n = positions.len();
        let mut replaced: Vec<[usize; 2]> = vec![];
        let mut added: Vec<[usize; 2]> = vec![];
        for part in parts {
            if part.halo.is_some() {
                return Err(Error::Internal("a routed block was read with too small a halo".into()));
            }
            let base = positions.len();
            let k = part.positions.len();
            let node = |i: i64| -> Result<usize> {
                let v = if i >= 0 { i as usize } else { base + (-i - 1) as usize };
                if (i >= 0 && v >= n) || (i < 0 && v >= base + k) {
                    return Err(Error::InvalidMask(format!("routed block refers to node {i} it does not hold")));
                }
                Ok(v)
            };
            for &[a, b] in &part.edges {
                let (a, b) = (node(a)?, node(b)?);
                added.push([a.min(b), a.max(b)]);
            }
            replaced.extend(part.replaced.iter().map(|e| e.map(|x| x as usize)));
            positions.extend_from_slice(&part.positions);
            radii.extend_from_slice(&part.radii);
        }
        replaced.sort_unstable();
        let mut out: Vec<[usize; 2]> = edges.into_iter().filter(|e| replaced.binary_search(e).is_err()).collect();
        out.extend(added);
        out.sort_unstable();
        // Last, the short spurs and the radii along the branches, as a single run ends.
        let out = crate::pipeline::finish(Skeleton { positions, radii, edges: out, spacing, info }, self.params());
        crate::pipeline::check_skeleton(&out)?;
        Ok(out)
    }
}
