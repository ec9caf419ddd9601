//! Chunked runs for volumes too large for one process (whole organs): a block phase
//! that runs on every block of the volume independently, and a merge phase that joins
//! the blocks' results into one graph.
//!
//! **Chunk pass** ([`Skeletonizer::largest_radius`]): the run's own EDT on every core
//! alone, before any block runs; empty cores are skipped and the largest radius sizes
//! the halo (the rule is the Python front end's, `vesselflow.distributed`).
//!
//! **Block phase** ([`Skeletonizer::contract_block`]): a block is read with a halo
//! around its *core* (the cores tile the volume, each voxel in exactly one). The whole
//! method runs on block plus halo (EDT, grid, contraction, refinement, output), every
//! foreground voxel followed to its output node ([`crate::fate::VoxelFate`]). Only core voxels are
//! reported, and each one decides, alone, the global cell of its node's position
//! (`round(p / c)`, `c` the base cell): a cell key has exactly one owner per voxel, so
//! float differences between overlapping blocks can never put a voxel in two cells.
//! The block returns per-node records (position, core voxel count, largest radius)
//! keyed by (block-local mask component, cell, block-local node): two output nodes of
//! the block that fall in one cell stay two records. With them go the record pairs
//! joined by its grid edges between core voxels, and its core voxels on the core's faces;
//! with a coarse start, also the split of every edge between two of its records
//! ([`crate::resample::Chain`]: the nodes the split put there, placed and measured on
//! the block's mask, or none), which the merge applies to those edges.
//!
//! **Merge phase** ([`Skeletonizer::merge_blocks`]): the face voxels of neighbouring
//! cores are paired (26-neighbours in different blocks); those pairs join the blocks'
//! mask components into global ones (union–find) and give the record pairs across
//! seams. Records with equal (global component, cell) are one node, the same node seen
//! from both sides of a seam (the flows of overlapping blocks differ by float rounding
//! and by their cuts, so only the cell can say it) — unless a block holds two distinct
//! nodes there: then the cell holds several nodes, the block's own, and a record of
//! another block joins only those it touches across the seam (a face pair). So a
//! volume in one block gives the single run's nodes, none fused. A node sits at its
//! records' mean position weighted by voxel count, added in record order, blocks in
//! order (fixed, so the same bit for bit for any worker count or schedule), as the first
//! record's position plus the mean offset of the others (a node of one record keeps its
//! position exactly), with their radii's mean weighted the same way (the largest of
//! them read the nodes near seams 0.7 % wide). Record pairs become edges, and
//! corner-only contacts bridge what the edges leave apart, as [`crate::grid::build`]
//! does, so every mask component is one graph component. Finally the short cycles that
//! seams made are closed ([`crate::cycles::Move::ShortestEdge`]): only cycles
//! through a seam node are considered (every other cycle is a cycle of one block's
//! graph, nodes and edges unchanged, already judged by its block, which had the mask),
//! and each loses its shortest edge, round by round. Such a cycle is mostly two copies
//! of one vessel, one from each block, joined at a junction and again further along;
//! the copies close where they lie closest and the junction stays. (The single run's
//! refinement, every node halfway to its cycle's centroid, moved such a junction to
//! the middle of the copies, several voxels along the vessel.) A vessel's end that the
//! closing fused goes back to its outermost member, and the one-node spurs seams left
//! go (a junction keeps two neighbours).
//!
//! **Routing phase** ([`crate::blocks_route`]): after the merge, the merged edges that
//! cross background are routed inside the mask, each by the one block that owns it.

use crate::blocks_sprouts::{attach_sprouts, SproutRecord};
use crate::cancel::Stop;
use crate::cycles::{refine_step, Cycle, Move};
use crate::decimate::{cell_of, decimate_mapped, NodeGraph};
use crate::error::{Error, Result};
use crate::fate::in_core;
use crate::graph::{RunInfo, Skeleton};
use crate::grid::Csr;
use crate::params::Connectivity;
use crate::pipeline::{check_skeleton, Skeletonizer};
use crate::prune::spurs_that_go;
use crate::resample::{split_long_edges, Chain};
use crate::vec3::{base_cell, dot, norm, sub};
use crate::volume::{edt_squared, Voxel};
use ndarray::ArrayView3;
use petgraph::unionfind::UnionFind;
use std::collections::HashMap;

/// One output node of a block, as seen from its core voxels.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeRecord {
    /// Mask component, numbered within the block.
    pub component: u32,
    /// Global cell, `round(p / c)`.
    pub cell: [i64; 3],
    /// The node, numbered within the block (distinct nodes in one cell stay apart).
    pub node: u32,
    /// The node's position (global, physical units), which all its voxels share.
    pub position: [f64; 3],
    /// Number of core voxels.
    pub count: u64,
    /// Largest output radius of the voxels' nodes.
    pub radius: f64,
    /// Largest radius the voxels' nodes split long edges by, with a coarse start
    /// ([`crate::resample`]; 0 without one or for nodes the split added).
    pub split_radius: f64,
}

/// What the block phase returns for one block.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BlockPart {
    /// Per-node records, sorted by (component, cell, node).
    pub cells: Vec<NodeRecord>,
    /// Pairs of `cells` indices joined by a grid edge between core voxels, sorted.
    pub edges: Vec<[u32; 2]>,
    /// Pairs of `cells` indices of 26-neighbouring core voxels not in `edges`, sorted.
    pub bridges: Vec<[u32; 2]>,
    /// Core voxels on a face of the core shared with another block: global C-order
    /// voxel index and their `cells` index, sorted by voxel.
    pub faces: Vec<(u64, u32)>,
    /// The sprouts whose lobe's farthest voxel lies in the core, in the order grown.
    pub sprouts: Vec<SproutRecord>,
    /// With a coarse start, the split of every edge between two of `cells` (`ends` are
    /// `cells` indices): the nodes it put there, as the block's medial and output stages
    /// left them, or none.
    pub chains: Vec<Chain>,
}

/// The 13 offsets of a 26-neighbourhood that come later in C order.
fn forward_offsets() -> Vec<[i64; 3]> {
    let mut v = vec![];
    for a in -1..=1i64 {
        for b in -1..=1i64 {
            for c in -1..=1i64 {
                if (a, b, c) > (0, 0, 0) {
                    v.push([a, b, c]);
                }
            }
        }
    }
    v
}

/// Whether a neighbour offset is a grid edge of `connectivity` (else a bridge).
fn is_edge_offset(o: [i64; 3], connectivity: Connectivity) -> bool {
    let sq = o.iter().map(|x| x * x).sum::<i64>();
    sq <= match connectivity {
        Connectivity::Six => 1,
        Connectivity::Eighteen => 2,
        Connectivity::TwentySix => 3,
    }
}

/// Refuse a core that does not fit its block of shape `shape` at `origin` in the volume.
pub(crate) fn check_core(shape: [usize; 3], origin: [i64; 3], core: [[usize; 2]; 3], volume: [usize; 3]) -> Result<()> {
    for d in 0..3 {
        let [lo, hi] = core[d];
        let end = origin[d] + hi as i64;
        if lo >= hi || hi > shape[d] || origin[d] < 0 || end > volume[d] as i64 {
            return Err(Error::InvalidMask(format!(
                "block core {core:?} at origin {origin:?} does not fit the block {shape:?} in the volume {volume:?}"
            )));
        }
    }
    Ok(())
}

/// The thread pool of a block-wise phase, on the parameters' `threads`.
pub(crate) fn block_pool(threads: usize) -> Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| Error::ThreadPool { threads, reason: e.to_string() })
}

/// `v` less the items marked in `drop`.
fn without<T>(v: Vec<T>, drop: &[bool]) -> Vec<T> {
    v.into_iter().zip(drop).filter(|(_, &d)| !d).map(|(x, _)| x).collect()
}

fn sorted_pairs(mut v: Vec<[u32; 2]>) -> Vec<[u32; 2]> {
    v.sort_unstable();
    v.dedup();
    v
}

impl Skeletonizer {
    /// The block phase of a chunked run (module doc). `mask` is the block with its halo;
    /// its voxel `(0, 0, 0)` is voxel `origin` of the whole volume of shape `volume`;
    /// `core[d]` is the half-open range of the core along axis `d` in block indices.
    /// A pure function of (block, origin, core, spacing, parameters); `stop` ends it early
    /// with [`Error::Interrupted`].
    pub fn contract_block<T: Voxel>(
        &self,
        mask: ArrayView3<'_, T>,
        origin: [i64; 3],
        core: [[usize; 2]; 3],
        volume: [usize; 3],
        spacing: [f64; 3],
        stop: &Stop,
    ) -> Result<BlockPart> {
        check_core(mask.dim().into(), origin, core, volume)?;
        let in_core = |v: [usize; 3]| in_core(core, v);
        if !mask.indexed_iter().any(|((i, j, k), m)| m.is_set() && in_core([i, j, k])) {
            return Ok(BlockPart::default());
        }
        let (skeleton, fate, grown) = self.run_tracked(mask, origin, spacing, stop, &mut |_| true, Some(core))?;
        let fate = fate.ok_or_else(|| Error::Internal("a tracked run lost its voxels".into()))?;
        let c = base_cell(spacing);

        // Core voxels: (component, cell, voxel id, block index), in C order.
        let mut voxels: Vec<(u32, [i64; 3], usize, [usize; 3])> = vec![];
        let mut node_of_voxel = 0usize;
        for ((i, j, k), m) in mask.indexed_iter() {
            if !m.is_set() {
                continue;
            }
            if in_core([i, j, k]) {
                let node = fate.node[node_of_voxel] as usize;
                let cell = cell_of(&skeleton.positions[node], c)?;
                voxels.push((fate.component[node_of_voxel], cell, node_of_voxel, [i, j, k]));
            }
            node_of_voxel += 1;
        }
        // Records in (component, cell, node) order; the record of every core voxel.
        let mut order: Vec<usize> = (0..voxels.len()).collect();
        order.sort_by_key(|&v| (voxels[v].0, voxels[v].1, fate.node[voxels[v].2], v));
        let mut cells: Vec<NodeRecord> = vec![];
        let mut record = vec![u32::MAX; fate.node.len()];
        for &v in &order {
            let (component, cell, id, _) = voxels[v];
            let node = fate.node[id];
            let p = skeleton.positions[node as usize];
            if cells.last().is_none_or(|s| (s.component, s.cell, s.node) != (component, cell, node)) {
                cells.push(NodeRecord { component, cell, node, position: p, count: 0, radius: 0.0, split_radius: 0.0 });
            }
            let s = cells.last_mut().expect("pushed above");
            s.count += 1;
            s.radius = s.radius.max(skeleton.radii[node as usize]);
            s.split_radius = s.split_radius.max(fate.split_radius.get(node as usize).copied().unwrap_or(0.0));
            record[id] = (cells.len() - 1) as u32;
        }

        // Grid edges between core voxels, as cell pairs.
        let mut edges = vec![];
        for (id, &a) in record.iter().enumerate() {
            if a == u32::MAX {
                continue;
            }
            for &w in fate.grid.neighbours(id) {
                let b = record[w as usize];
                if b != u32::MAX && a != b {
                    edges.push([a.min(b), a.max(b)]);
                }
            }
        }
        let edges = sorted_pairs(edges);

        // 26-neighbours among core voxels (bridge candidates), and the face voxels.
        let local: HashMap<[usize; 3], u32> = voxels.iter().map(|&(_, _, id, v)| (v, record[id])).collect();
        let forward = forward_offsets();
        let mut bridges = vec![];
        let mut faces = vec![];
        for &(_, _, id, v) in &voxels {
            let a = record[id];
            for o in &forward {
                let w: [i64; 3] = std::array::from_fn(|d| v[d] as i64 + o[d]);
                if w.iter().any(|&x| x < 0) {
                    continue;
                }
                if let Some(&b) = local.get(&w.map(|x| x as usize)) {
                    if a != b && edges.binary_search(&[a.min(b), a.max(b)]).is_err() {
                        bridges.push([a.min(b), a.max(b)]);
                    }
                }
            }
            let on_face = (0..3).any(|d| {
                let g = origin[d] + v[d] as i64;
                (v[d] == core[d][0] && g > 0) || (v[d] + 1 == core[d][1] && g + 1 < volume[d] as i64)
            });
            if on_face {
                let g: [u64; 3] = std::array::from_fn(|d| (origin[d] + v[d] as i64) as u64);
                faces.push(((g[0] * volume[1] as u64 + g[1]) * volume[2] as u64 + g[2], a));
            }
        }
        faces.sort_unstable();
        let node = |i: u32| (skeleton.positions[i as usize], skeleton.radii[i as usize]);
        let mut record_of_node = vec![u32::MAX; skeleton.positions.len()];
        for (k, s) in cells.iter().enumerate() {
            record_of_node[s.node as usize] = k as u32;
        }
        let chains = fate
            .chains
            .iter()
            .filter_map(|(ends, nodes)| {
                let ends = ends.map(|e| record_of_node[e as usize]);
                (!ends.contains(&u32::MAX)).then(|| Chain {
                    ends,
                    positions: nodes.iter().map(|&i| node(i).0).collect(),
                    radii: nodes.iter().map(|&i| node(i).1).collect(),
                })
            })
            .collect();
        let sprouts = grown
            .iter()
            .filter(|s| in_core(s.tip))
            .map(|s| SproutRecord {
                round: s.round as u32,
                split: s.split,
                start: node(s.start).0,
                start_radius: node(s.start).1,
                positions: s.nodes.clone().map(|i| node(i).0).collect(),
                radii: s.nodes.clone().map(|i| node(i).1).collect(),
            })
            .collect();
        Ok(BlockPart { cells, edges, bridges: sorted_pairs(bridges), faces, sprouts, chains })
    }

    /// The largest vessel radius of `mask` (physical units): the largest distance from a
    /// foreground voxel's centre to the nearest background voxel's centre, voxels outside
    /// the array counting as background (the EDT of the run itself), or `None` for an
    /// empty mask. The cheap per-chunk pass of a chunked run, which skips empty blocks
    /// and sizes the halo; on the parameters' `threads`.
    pub fn largest_radius<T: Voxel>(&self, mask: ArrayView3<'_, T>, spacing: [f64; 3]) -> Result<Option<f64>> {
        crate::volume::check_spacing(spacing)?;
        let d = block_pool(self.params().threads)?.install(|| edt_squared(mask, spacing))?;
        Ok(d.into_iter().reduce(f32::max).map(|m| f64::from(m).sqrt()))
    }

    /// The merge phase of a chunked run (module doc): the graph of all blocks' parts,
    /// given in a fixed block order, for a volume of shape `volume`.
    pub fn merge_blocks(&self, parts: &[BlockPart], volume: [usize; 3], spacing: [f64; 3]) -> Result<Skeleton> {
        crate::volume::check_spacing(spacing)?;
        let p = self.params();
        let c = base_cell(spacing);
        // Global record ids: blocks in order, records in order.
        let mut first = vec![0usize];
        for part in parts {
            first.push(first[first.len() - 1] + part.cells.len());
        }
        let records = first[parts.len()];
        let block_of: Vec<usize> =
            (0..parts.len()).flat_map(|b| std::iter::repeat_n(b, parts[b].cells.len())).collect();
        let rec = |b: usize, r: u32| -> Result<usize> {
            let r = r as usize;
            if r >= parts[b].cells.len() {
                return Err(Error::InvalidMask(format!("block {b} refers to cell record {r} it does not hold")));
            }
            Ok(first[b] + r)
        };

        // Seam pairs between face voxels of different blocks.
        let mut face: HashMap<u64, usize> = HashMap::new();
        for (b, part) in parts.iter().enumerate() {
            for &(v, r) in &part.faces {
                if face.insert(v, rec(b, r)?).is_some() {
                    return Err(Error::InvalidMask(format!("voxel {v} lies in the core of two blocks")));
                }
            }
        }
        let [n0, n1, n2] = volume.map(|n| n as i64);
        let mut seam_edges = vec![];
        let mut seam_bridges = vec![];
        for part in parts {
            for &(v, _) in &part.faces {
                let a = face[&v];
                let at = [v as i64 / (n1 * n2), (v as i64 / n2) % n1, v as i64 % n2];
                for o in forward_offsets() {
                    let w: [i64; 3] = std::array::from_fn(|d| at[d] + o[d]);
                    if w.iter().zip([n0, n1, n2]).any(|(&x, n)| x < 0 || x >= n) {
                        continue;
                    }
                    let Some(&b) = face.get(&(((w[0] * n1 + w[1]) * n2 + w[2]) as u64)) else { continue };
                    if block_of[a] != block_of[b] {
                        let pair = [a.min(b), a.max(b)];
                        if is_edge_offset(o, p.connectivity) {
                            seam_edges.push(pair);
                        } else {
                            seam_bridges.push(pair);
                        }
                    }
                }
            }
        }

        // Global mask components: a block's components, joined across seams.
        let mut comp_first = vec![0usize];
        for part in parts {
            let n = part.cells.last().map_or(0, |s| s.component as usize + 1);
            comp_first.push(comp_first[comp_first.len() - 1] + n);
        }
        let local_comp =
            |r: usize| comp_first[block_of[r]] + parts[block_of[r]].cells[r - first[block_of[r]]].component as usize;
        let mut uf = UnionFind::<usize>::new(comp_first[parts.len()]);
        for pair in seam_edges.iter().chain(&seam_bridges) {
            uf.union(local_comp(pair[0]), local_comp(pair[1]));
        }
        // Numbered by first record in block order.
        let mut number: HashMap<usize, u32> = HashMap::new();
        let global: Vec<u32> = (0..records)
            .map(|r| {
                let root = uf.find(local_comp(r));
                let next = number.len() as u32;
                *number.entry(root).or_insert(next)
            })
            .collect();
        let components = number.len();

        // Nodes: records with one (global component, cell) are one node, unless a block
        // holds several there (module doc); summed in record order.
        let cell = |r: usize| parts[block_of[r]].cells[r - first[block_of[r]]].clone();
        let key = |r: usize| (global[r], parts[block_of[r]].cells[r - first[block_of[r]]].cell);
        let mut order: Vec<usize> = (0..records).collect();
        order.sort_by_key(|&r| (key(r), r));
        let mut same = UnionFind::<usize>::new(records);
        let mut shared = vec![false; records];
        for group in order.chunk_by(|&a, &b| key(a) == key(b)) {
            let one_each = group.windows(2).all(|w| block_of[w[0]] != block_of[w[1]]);
            for &r in group {
                shared[r] = !one_each;
                if one_each {
                    same.union(group[0], r);
                }
            }
        }
        for &[a, b] in seam_edges.iter().chain(&seam_bridges) {
            if shared[a] && key(a) == key(b) {
                same.union(a, b);
            }
        }
        // Each node is named by its first record.
        let mut first_of = vec![usize::MAX; records];
        for r in 0..records {
            let root = same.find(r);
            first_of[root] = first_of[root].min(r);
        }
        let first_of: Vec<usize> = (0..records).map(|r| first_of[same.find(r)]).collect();
        order.sort_by_key(|&r| (key(r), first_of[r], r));
        let mut node_of = vec![0u32; records];
        let mut positions: Vec<[f64; 3]> = vec![];
        let mut offsets: Vec<[f64; 3]> = vec![];
        let mut counts: Vec<u64> = vec![];
        let mut radii: Vec<f64> = vec![];
        let mut radius_offsets: Vec<f64> = vec![];
        let mut split_radii: Vec<f64> = vec![];
        let mut component: Vec<u32> = vec![];
        let mut blocks_of_node: Vec<(usize, bool)> = vec![];
        let mut last = None;
        for &r in &order {
            let s = cell(r);
            if last != Some(first_of[r]) {
                last = Some(first_of[r]);
                positions.push(s.position);
                offsets.push([0.0; 3]);
                counts.push(0);
                radii.push(s.radius);
                radius_offsets.push(0.0);
                split_radii.push(0.0);
                component.push(global[r]);
                blocks_of_node.push((block_of[r], false));
            }
            let k = positions.len() - 1;
            for d in 0..3 {
                offsets[k][d] += s.count as f64 * (s.position[d] - positions[k][d]);
            }
            counts[k] += s.count;
            radius_offsets[k] += s.count as f64 * (s.radius - radii[k]);
            split_radii[k] = split_radii[k].max(s.split_radius);
            if blocks_of_node[k].0 != block_of[r] {
                blocks_of_node[k].1 = true;
            }
            node_of[r] = k as u32;
        }
        for ((q, o), &n) in positions.iter_mut().zip(&offsets).zip(&counts) {
            *q = std::array::from_fn(|d| q[d] + o[d] / n as f64);
        }
        for ((r, o), &n) in radii.iter_mut().zip(&radius_offsets).zip(&counts) {
            *r += o / n as f64;
        }
        let nodes = positions.len();

        // Edges: the blocks' and the seams'; then bridges where pieces stay apart.
        let to_nodes = |pairs: &mut dyn Iterator<Item = [usize; 2]>| -> Vec<[u32; 2]> {
            sorted_pairs(
                pairs
                    .map(|[a, b]| [node_of[a], node_of[b]])
                    .filter(|[a, b]| a != b)
                    .map(|[a, b]| [a.min(b), a.max(b)])
                    .collect(),
            )
        };
        let mut block_edges = vec![];
        let mut block_bridges = vec![];
        for (b, part) in parts.iter().enumerate() {
            for e in &part.edges {
                block_edges.push([rec(b, e[0])?, rec(b, e[1])?]);
            }
            for e in &part.bridges {
                block_bridges.push([rec(b, e[0])?, rec(b, e[1])?]);
            }
        }
        let mut seam = vec![false; nodes];
        for (k, &(_, many)) in blocks_of_node.iter().enumerate() {
            seam[k] = many;
        }
        let across = to_nodes(&mut seam_edges.iter().copied().chain(seam_bridges.iter().copied()));
        for &[a, b] in &across {
            seam[a as usize] = true;
            seam[b as usize] = true;
        }
        let mut edges = to_nodes(&mut block_edges.into_iter().chain(seam_edges));
        let mut pieces = UnionFind::<u32>::new(nodes);
        for &[a, b] in &edges {
            pieces.union(a, b);
        }
        for [a, b] in to_nodes(&mut block_bridges.into_iter().chain(seam_bridges)) {
            if pieces.union(a, b) {
                edges.push([a, b]);
            }
        }
        let edges = sorted_pairs(edges);
        let graph = Csr::from_sorted_edges(nodes, &edges.iter().map(|&[a, b]| (a, b)).collect::<Vec<_>>());
        let mut g = NodeGraph { graph, positions, radii, component };

        // The short cycles the merge made: a cycle through a seam node below
        // `refine_area` loses its shortest edge per round; any other cycle is one
        // block's, judged there.
        let max_area = p.refine_area * c * c;
        // Where each merged node went, and which nodes the refinement made by fusing.
        let mut now: Vec<u32> = (0..nodes as u32).collect();
        let mut fused = vec![false; nodes];
        let merged = g.positions.clone();
        for _ in 0..p.max_refine_iterations {
            // Left alone: a cycle of one block (no seam node), judged by that block.
            let one_blocks = |cycle: &Cycle| !cycle.nodes.iter().any(|&i| seam[i as usize]);
            let Some((positions, moved, _)) =
                refine_step(&g.graph, &g.positions, p.max_cycle_nodes, max_area, &one_blocks, Move::ShortestEdge)
            else {
                break;
            };
            g.positions = positions;
            let keep: Vec<bool> = moved.iter().map(|m| !m).collect();
            let (mut next, map) = decimate_mapped(&g, &keep, c)?;
            // A fused node's radius is its members' mean (decimation takes the
            // largest, which a single run measures again at its output; the merge
            // does not, and the largest of two copies reads the vessel wide).
            let mut sums = vec![(0.0f64, 0u32); next.positions.len()];
            for (i, &m) in map.iter().enumerate() {
                sums[m as usize].0 += g.radii[i];
                sums[m as usize].1 += 1;
            }
            for (r, &(sum, n)) in next.radii.iter_mut().zip(&sums) {
                *r = sum / f64::from(n);
            }
            let mut next_seam = vec![false; next.positions.len()];
            let mut next_split = vec![0.0f64; next.positions.len()];
            let mut next_fused = vec![false; next.positions.len()];
            for (i, &m) in map.iter().enumerate() {
                next_seam[m as usize] |= seam[i];
                next_split[m as usize] = next_split[m as usize].max(split_radii[i]);
                next_fused[m as usize] |= fused[i] || moved[i];
            }
            for x in &mut now {
                *x = map[*x as usize];
            }
            seam = next_seam;
            split_radii = next_split;
            fused = next_fused;
            g = next;
        }
        // A vessel's end that the closing fused with its neighbour sits at its outermost
        // member: the member farthest from the end's one neighbour (the midpoint of the
        // fused edge pulled the end in, and the merge has no mask to move it out again).
        let mut outermost: Vec<Option<(f64, usize)>> = vec![None; g.positions.len()];
        for (i, &m) in now.iter().enumerate() {
            let m = m as usize;
            let [q] = *g.graph.neighbours(m) else { continue };
            if !fused[m] {
                continue;
            }
            let d = norm(sub(merged[i], g.positions[q as usize]));
            if outermost[m].is_none_or(|(best, _)| d > best) {
                outermost[m] = Some((d, i));
            }
        }
        for (m, best) in outermost.iter().enumerate() {
            if let Some((_, i)) = best {
                g.positions[m] = merged[*i];
            }
        }

        // With a coarse start, an edge between two records of a block is split as that
        // block split it (the first block's, in block order), with the nodes placed and
        // measured there as in a single run, unless the refinement fused an end. Other
        // edges longer than the cells are split as in a single run, by the radii the
        // blocks split with ([`crate::resample`]; the merge has no mask, so their new nodes
        // stay on the chords).
        if p.coarse_cell > 0.0 {
            let mut given = vec![];
            for (b, part) in parts.iter().enumerate() {
                for (k, chain) in part.chains.iter().enumerate() {
                    if !chain.is_valid() {
                        return Err(Error::InvalidMask(format!(
                            "block {b}'s split chain {k} has a radius count unlike its node count, or a \
                             non-finite or negative value"
                        )));
                    }
                    let ends = [rec(b, chain.ends[0])?, rec(b, chain.ends[1])?].map(|r| now[node_of[r] as usize]);
                    if ends[0] != ends[1] && !fused[ends[0] as usize] && !fused[ends[1] as usize] {
                        given.push(Chain { ends, positions: chain.positions.clone(), radii: chain.radii.clone() });
                    }
                }
            }
            g = split_long_edges(g, &split_radii, p.coarse_cell, spacing, &given);
            seam.resize(g.positions.len(), false);
        }

        // One-node spurs that seams made, among the seam leaves within their node's radius
        // (a vessel end there would reach further). A leaf that points back along its
        // node's vessel (towards another neighbour that is no leaf) folds into it: it goes.
        // Leaves on a junction that point outwards go nearest first, while the junction
        // keeps two neighbours: where two blocks each saw a vessel's end in a cell of their
        // own, the end's two copies are leaves of its last node, and the farther stays
        // (dropping both cut the vessel short).
        let degree: Vec<usize> = (0..g.positions.len()).map(|i| g.graph.neighbours(i).len()).collect();
        let mut spur = vec![false; g.positions.len()];
        let mut folds = vec![0usize; g.positions.len()];
        let mut leaves: Vec<(u32, f64, usize)> = vec![];
        for i in 0..g.positions.len() {
            let [j] = *g.graph.neighbours(i) else { continue };
            let out = sub(g.positions[i], g.positions[j as usize]);
            let d = norm(out);
            if !seam[i] || d > g.radii[j as usize] {
                continue;
            }
            let back = |&k: &u32| {
                k as usize != i
                    && degree[k as usize] >= 2
                    && dot(out, sub(g.positions[k as usize], g.positions[j as usize])) > 0.0
            };
            if g.graph.neighbours(j as usize).iter().any(back) {
                spur[i] = true;
                folds[j as usize] += 1;
            } else if degree[j as usize] >= 3 {
                leaves.push((j, d, i));
            }
        }
        leaves.sort_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)).then(a.2.cmp(&b.2)));
        for on_one in leaves.chunk_by(|a, b| a.0 == b.0) {
            let j = on_one[0].0 as usize;
            let drop = spurs_that_go(degree[j], folds[j], on_one.len());
            for &(_, _, i) in &on_one[..drop] {
                spur[i] = true;
            }
        }
        let mut new_id = vec![u32::MAX; spur.len()];
        let mut kept = 0u32;
        for (i, &s) in spur.iter().enumerate() {
            if !s {
                new_id[i] = kept;
                kept += 1;
            }
        }
        let edges = g
            .graph
            .edge_list()
            .into_iter()
            .filter(|&(a, b)| !spur[a as usize] && !spur[b as usize])
            .map(|(a, b)| [new_id[a as usize] as usize, new_id[b as usize] as usize])
            .collect();
        let out = Skeleton {
            edges,
            positions: without(g.positions, &spur),
            radii: without(g.radii, &spur),
            spacing,
            info: RunInfo {
                foreground_voxels: counts.iter().sum::<u64>() as usize,
                mask_components: components,
                ..RunInfo::default()
            },
        };
        // The blocks' sprouts, by round, then block, then the order grown.
        check_skeleton(&out)?;
        for (b, part) in parts.iter().enumerate() {
            if let Some(k) = part.sprouts.iter().position(|s| !s.is_valid()) {
                return Err(Error::InvalidMask(format!(
                    "block {b}'s sprout {k} has no nodes, a radius count unlike its node count, or a \
                     non-finite or negative value"
                )));
            }
        }
        // Collected in block order, then the order grown; a stable sort keeps it per round.
        let mut sprouts: Vec<&SproutRecord> = parts.iter().flat_map(|part| &part.sprouts).collect();
        sprouts.sort_by_key(|s| s.round);
        let (mut out, attached) = attach_sprouts(out, &sprouts);
        out.info.sprouts = attached;
        check_skeleton(&out)?;
        Ok(out)
    }
}
