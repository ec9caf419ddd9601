//! Chunked runs (`vesselflow::blocks`): the blocks of a volume, each with a halo, merged
//! into one graph, compared with the single run of the whole volume.

use ndarray::{s, Array3};
use vesselflow::blocks::BlockPart;
use vesselflow::{shapes, Params, Skeleton, Skeletonizer, Stop};

/// Run `mask` in blocks of `core` voxels with `halo` voxels around, merged.
fn chunked(mask: &Array3<u8>, core: usize, halo: usize, spacing: [f64; 3]) -> (Skeleton, Vec<BlockPart>) {
    chunked_with(Params::default(), mask, core, halo, spacing)
}

/// [`chunked`] with `params`.
fn chunked_with(
    params: Params,
    mask: &Array3<u8>,
    core: usize,
    halo: usize,
    spacing: [f64; 3],
) -> (Skeleton, Vec<BlockPart>) {
    let sk = Skeletonizer::new(params).unwrap();
    let volume: [usize; 3] = mask.dim().into();
    let mut parts = vec![];
    for i in (0..volume[0]).step_by(core) {
        for j in (0..volume[1]).step_by(core) {
            for k in (0..volume[2]).step_by(core) {
                let at = [i, j, k];
                let lo: [usize; 3] = std::array::from_fn(|d| at[d].saturating_sub(halo));
                let hi: [usize; 3] = std::array::from_fn(|d| (at[d] + core + halo).min(volume[d]));
                let end: [usize; 3] = std::array::from_fn(|d| (at[d] + core).min(volume[d]));
                let block = mask.slice(s![lo[0]..hi[0], lo[1]..hi[1], lo[2]..hi[2]]);
                let cores = std::array::from_fn(|d| [at[d] - lo[d], end[d] - lo[d]]);
                let origin = lo.map(|x| x as i64);
                parts.push(sk.contract_block(block, origin, cores, volume, spacing, &Stop::new()).unwrap());
            }
        }
    }
    (sk.merge_blocks(&parts, volume, spacing).unwrap(), parts)
}

fn single(mask: &Array3<u8>, spacing: [f64; 3]) -> Skeleton {
    single_with(Params::default(), mask, spacing)
}

fn single_with(params: Params, mask: &Array3<u8>, spacing: [f64; 3]) -> Skeleton {
    Skeletonizer::new(params).unwrap().run(mask.view(), spacing, &mut |_| true).unwrap()
}

/// Connected components and cycle rank (edges - nodes + components).
fn topology(s: &Skeleton) -> (usize, usize) {
    let mut uf = petgraph::unionfind::UnionFind::<usize>::new(s.len());
    for &[a, b] in &s.edges {
        uf.union(a, b);
    }
    let comps = (0..s.len()).filter(|&i| uf.find(i) == i).count();
    (comps, s.edges.len() + comps - s.len())
}

#[test]
fn a_tube_across_blocks_is_one_path_like_the_single_run() {
    let mask = shapes::cylinder([64, 21, 21], 4.0);
    let (g, parts) = chunked(&mask, 16, 16, [1.0; 3]);
    let one = single(&mask, [1.0; 3]);
    assert_eq!(topology(&g), (1, 0));
    assert_eq!(topology(&g), topology(&one));
    assert!(g.degrees().iter().all(|&d| d <= 2));
    // Nodes along the whole axis, as many as the single run's within a few.
    assert!((g.len() as i64 - one.len() as i64).abs() <= 6, "{} vs {}", g.len(), one.len());
    assert_eq!(parts.len(), 4 * 2 * 2);
    // Every foreground voxel is in exactly one core.
    assert_eq!(g.info.foreground_voxels, mask.iter().filter(|&&m| m != 0).count());
}

/// With a coarse start the merge splits long edges as the single run does, by the
/// radii the blocks split with (the cells' EDT, 4 here), not by the output radii it
/// carries (3.82 on this tube: no cells at `coarse_cell` 0.5, no split, and 26 nodes
/// against the single run's 46).
#[test]
fn a_coarse_start_splits_a_chunked_tube_like_the_single_run() {
    let mask = shapes::cylinder([64, 21, 21], 4.0);
    let params = || Params { coarse_cell: 0.5, ..Params::default() };
    let (g, _) = chunked_with(params(), &mask, 16, 16, [1.0; 3]);
    let one = single_with(params(), &mask, [1.0; 3]);
    assert_eq!(topology(&g), (1, 0));
    assert!((g.len() as i64 - one.len() as i64).abs() <= 6, "{} vs {}", g.len(), one.len());
}

/// With a coarse start, a volume in one block gives the single run's nodes: the merge
/// splits each edge as the block split it, with the split nodes the block's medial and
/// output stages placed and measured (split on the chords instead, they were up to 3.5
/// voxels off the single run's, and an end the output stage moved out to the vessel's
/// end made its edge long enough to split where the single run had not). The merge is
/// compared before the routing phase and the last steps, so both keep the nodes' own
/// radii (`radius_smoothing` 0: smoothed along the branches, the single run's radii
/// would be medians over its routed graph's branches).
#[test]
fn one_block_with_a_coarse_start_gives_the_single_runs_nodes() {
    let mask = shapes::torus([24, 64, 64], 20.0, 5.0);
    let params = || Params { coarse_cell: 0.5, radius_smoothing: 0.0, ..Params::default() };
    let (g, parts) = chunked_with(params(), &mask, 64, 0, [1.0; 3]);
    let one = single_with(params(), &mask, [1.0; 3]);
    assert!(parts[0].chains.iter().any(|c| !c.positions.is_empty()));
    assert_eq!(topology(&g), (1, 1));
    for (p, r) in g.positions.iter().zip(&g.radii) {
        let same = one
            .positions
            .iter()
            .zip(&one.radii)
            .any(|(q, s)| (0..3).all(|d| (p[d] - q[d]).abs() <= 1e-9) && (r - s).abs() <= 1e-9);
        assert!(same, "merged node at {p:?} (radius {r}) is no node of the single run");
    }
    assert!(g.len() >= 40 && one.len() >= g.len(), "{} merged nodes, {} single", g.len(), one.len());
}

#[test]
fn a_torus_and_a_y_keep_their_cycle_and_their_junction() {
    let torus = shapes::torus([24, 64, 64], 20.0, 4.0);
    let (g, _) = chunked(&torus, 32, 24, [1.0; 3]);
    assert_eq!(topology(&g), (1, 1));
    let (y, _) = shapes::y_bifurcation([64, 48, 48], 3.0);
    let (g, _) = chunked(&y, 24, 24, [1.0; 3]);
    assert_eq!(topology(&g), topology(&single(&y, [1.0; 3])));
    assert!(g.degrees().iter().any(|&d| d >= 3));
}

#[test]
fn the_merge_is_the_same_whatever_the_order_of_the_work() {
    // The parts are pure functions of their block: computing them twice, in another
    // order, gives the same merge bit for bit.
    let mask = shapes::torus([24, 64, 64], 20.0, 4.0);
    let (a, parts) = chunked(&mask, 32, 16, [1.0; 3]);
    let (b, again) = chunked(&mask, 32, 16, [1.0; 3]);
    assert_eq!(parts, again);
    assert_eq!(a.positions, b.positions);
    assert_eq!(a.edges, b.edges);
    assert_eq!(a.radii, b.radii);
}

#[test]
fn separate_vessels_stay_separate_and_an_empty_block_adds_nothing() {
    let mut mask = Array3::<u8>::zeros((48, 48, 48));
    mask.slice_mut(s![.., 10..14, 10..14]).fill(1);
    mask.slice_mut(s![.., 30..34, 30..34]).fill(1);
    let (g, parts) = chunked(&mask, 24, 12, [1.0; 3]);
    assert_eq!(topology(&g).0, 2);
    assert_eq!(g.info.mask_components, 2);
    // The blocks the tubes miss report nothing.
    assert!(parts.iter().any(|p| *p == BlockPart::default()));
}

#[test]
fn bad_cores_are_refused_before_any_work() {
    let sk = Skeletonizer::new(Params::default()).unwrap();
    let mask = Array3::<u8>::ones((8, 8, 8));
    let e = sk.contract_block(mask.view(), [0; 3], [[0, 9], [0, 8], [0, 8]], [8; 3], [1.0; 3], &Stop::new());
    assert!(e.unwrap_err().to_string().contains("does not fit"));
}

#[test]
fn the_chunk_pass_finds_the_largest_radius_with_the_outside_as_background() {
    let sk = Skeletonizer::new(Params::default()).unwrap();
    assert_eq!(sk.largest_radius(Array3::<u8>::zeros((6, 7, 8)).view(), [1.0; 3]), Ok(None));
    // A chunk entirely foreground (inside a thick vessel): the voxels at its middle are
    // 8 voxels from the background outside it.
    assert_eq!(sk.largest_radius(Array3::<u8>::ones((16, 16, 16)).view(), [1.0; 3]), Ok(Some(8.0)));
    // A tube of radius 4 along axis 0: from its axis to the nearest background voxel
    // centre, (4, 1) voxels across, in physical units.
    let tube = shapes::cylinder([40, 21, 21], 4.0);
    assert_eq!(sk.largest_radius(tube.view(), [1.0; 3]), Ok(Some(17f64.sqrt())));
    assert_eq!(sk.largest_radius(tube.view(), [3.0, 0.5, 0.5]), Ok(Some(17f64.sqrt() / 2.0)));
    assert!(sk.largest_radius(tube.view(), [0.0, 1.0, 1.0]).is_err());
}

/// The routing phase (`vesselflow::blocks_route`): a merged chord that cuts a bend is
/// routed through the bend by the block that owns it, which asks for a larger read when
/// its halo cannot hold the routing, and refuses an edge another block owns.
#[test]
fn the_routing_phase_takes_a_chord_back_inside_its_bend() {
    use vesselflow::blocks_route::owner_voxel;
    use vesselflow::edges_inside::outside_run;
    let mut mask = Array3::<u8>::zeros((3, 40, 40));
    for t in 4..=30 {
        mask[[1, t, 4]] = 1;
        mask[[1, 30, t]] = 1;
    }
    let volume = [3, 40, 40];
    let spacing = [1.0; 3];
    let (p, q) = ([1.0, 10.0, 4.0], [1.0, 30.0, 30.0]);
    let merged =
        Skeleton { positions: vec![p, q], radii: vec![0.5; 2], edges: vec![[0, 1]], spacing, info: Default::default() };
    assert!(outside_run(&mask.view(), p, q, spacing).is_some());
    let owner = owner_voxel(p, q, spacing, volume);
    assert_eq!(owner, [1, 20, 17]);
    let sk = Skeletonizer::new(Params::default()).unwrap();
    let route = |lo: [usize; 3], hi: [usize; 3], core: [[usize; 2]; 3]| {
        let block = mask.slice(s![lo[0]..hi[0], lo[1]..hi[1], lo[2]..hi[2]]);
        sk.route_block(block, lo.map(|x| x as i64), core, volume, spacing, &[0, 1], &[p, q], &[[0, 1]])
    };
    // A core of 16 holding the owner voxel with a halo of 2: too small, it says how much.
    let small = route([0, 14, 14], [3, 34, 34], [[0, 3], [2, 18], [2, 18]]).unwrap();
    let halo = small.halo.expect("a halo of 2 cannot hold the edge");
    assert!(halo[1] > 2 && halo[2] > 2 && small.edges.is_empty());
    // Read with that halo: routed, every edge inside, the chord gone.
    let lo = [0, 16 - halo[1].min(16), 16 - halo[2].min(16)];
    let hi = [3, (32 + halo[1]).min(40), (32 + halo[2]).min(40)];
    let core = [[0, 3], [16 - lo[1], 32 - lo[1]], [16 - lo[2], 32 - lo[2]]];
    let part = route(lo, hi, core).unwrap();
    assert_eq!(part.halo, None);
    assert_eq!(part.replaced, vec![[0, 1]]);
    let out = sk.splice_routes(merged.clone(), std::slice::from_ref(&part)).unwrap();
    assert!(out.len() > 2 && out.radii.len() == out.len());
    assert_eq!(out.edges.len(), out.len() - 1);
    for &[a, b] in &out.edges {
        assert_eq!(outside_run(&mask.view(), out.positions[a], out.positions[b], spacing), None);
    }
    // The same whole volume as one block: the same routed graph.
    let whole = route([0; 3], volume, [[0, 3], [0, 40], [0, 40]]).unwrap();
    assert_eq!(sk.splice_routes(merged, &[whole]).unwrap().positions, out.positions);
    // A block whose core does not hold the owner voxel refuses the edge.
    assert!(route([0, 0, 0], [3, 40, 40], [[0, 3], [0, 16], [0, 40]]).is_err());
}

/// The merge keys nodes by cell, one owner per voxel; two distinct nodes of one block in
/// one cell stay two nodes, and another block's record there joins the one it touches
/// across the seam. With one record per block, a cell is one node (as at any seam).
#[test]
fn distinct_nodes_of_a_block_in_one_cell_stay_apart() {
    use vesselflow::blocks::NodeRecord;
    let rec = |node: u32, z: f64| NodeRecord {
        component: 0,
        cell: [0, 0, z.round() as i64],
        node,
        position: [0.0, 0.0, z],
        count: 1,
        radius: 0.5,
        split_radius: 0.0,
    };
    let sk = Skeletonizer::new(Params::default()).unwrap();
    let z = |g: &Skeleton| g.positions.iter().map(|p| p[2]).collect::<Vec<_>>();
    // One block: nodes at z = 0.8 and 1.2 share cell 1.
    let one = BlockPart {
        cells: vec![rec(0, 0.8), rec(1, 1.2), rec(2, 2.0)],
        edges: vec![[0, 1], [1, 2]],
        bridges: vec![],
        faces: vec![],
        ..Default::default()
    };
    let g = sk.merge_blocks(&[one], [1, 1, 3], [1.0; 3]).unwrap();
    assert_eq!(z(&g), [0.8, 1.2, 2.0]);
    assert_eq!(g.edges, [[0, 1], [1, 2]]);
    // Two blocks (cores z < 2 and z >= 2): the first holds two nodes in cell 1, the
    // second one (z = 1.375, from its voxel 2, next to the first's voxel 1 of node 1).
    let a = BlockPart {
        cells: vec![rec(0, 0.8), rec(1, 1.25)],
        edges: vec![[0, 1]],
        faces: vec![(1, 1)],
        ..Default::default()
    };
    let b = BlockPart {
        cells: vec![rec(0, 1.375), rec(1, 3.0)],
        edges: vec![[0, 1]],
        bridges: vec![],
        faces: vec![(2, 0)],
        ..Default::default()
    };
    let g = sk.merge_blocks(&[a, b.clone()], [1, 1, 4], [1.0; 3]).unwrap();
    assert_eq!(z(&g), [0.8, 1.3125, 3.0]);
    assert_eq!(g.edges, [[0, 1], [1, 2]]);
    // One node of the first block in cell 1: the cell is one node, fed by both blocks.
    let a = BlockPart { cells: vec![rec(0, 1.25)], faces: vec![(1, 0)], ..Default::default() };
    let g = sk.merge_blocks(&[a, b], [1, 1, 4], [1.0; 3]).unwrap();
    assert_eq!(z(&g), [1.3125, 3.0]);
    assert_eq!(g.edges, [[0, 1]]);
}

/// A node seen by two blocks (one record each in its cell) takes their radii's mean,
/// weighted by the core voxels each record holds: the merge cannot measure the radius
/// again, and the larger of two readings of one vessel reads it wide.
#[test]
fn a_node_seen_by_two_blocks_takes_their_radii_mean() {
    use vesselflow::blocks::NodeRecord;
    let rec = |z: f64, count: u64, radius: f64| NodeRecord {
        component: 0,
        cell: [0, 0, z.round() as i64],
        node: 0,
        position: [0.0, 0.0, z],
        count,
        radius,
        split_radius: 0.0,
    };
    let sk = Skeletonizer::new(Params::default()).unwrap();
    // Cores z < 2 and z >= 2 of a 1 x 1 x 4 volume; the node of cell 2 holds three core
    // voxels of the first block (radius 2) and one of the second (radius 4).
    let a = BlockPart { cells: vec![rec(1.75, 3, 2.0)], faces: vec![(1, 0)], ..Default::default() };
    let b = BlockPart { cells: vec![rec(2.25, 1, 4.0)], faces: vec![(2, 0)], ..Default::default() };
    let g = sk.merge_blocks(&[a, b], [1, 1, 4], [1.0; 3]).unwrap();
    assert_eq!(g.positions, [[0.0, 0.0, 1.875]]);
    assert_eq!(g.radii, [2.5]);
}

/// The one-node spurs that seams make go, but not a vessel's end. A 1 x 2 x 12 volume in
/// two blocks (cores z < 6 and z >= 6); both blocks report the leaves, so the leaves are
/// seam nodes. (a) A vessel's last node J with its end seen by the two blocks in two cells
/// of their own (two leaves, both within J's radius): the nearer copy goes, the farther
/// stays the end (both went before, cutting the vessel short by a node). (b) A leaf on J,
/// within J's radius, that points back towards J's other neighbour K (it folds into the
/// vessel): it goes, and J is the end.
#[test]
fn seam_spurs_go_but_a_vessel_keeps_its_end() {
    use vesselflow::blocks::NodeRecord;
    let rec = |node: u32, p: [f64; 3], radius: f64| NodeRecord {
        component: 0,
        cell: p.map(|x| x.round() as i64),
        node,
        position: p,
        count: 1,
        radius,
        split_radius: 0.0,
    };
    let sk = Skeletonizer::new(Params { coarse_cell: 0.0, ..Params::default() }).unwrap();
    let volume = [1, 2, 12];
    // (a) N - J, J - E1, J - E2; E1 is 3.0 from J, E2 3.16.
    let (n, j, e1, e2) = ([0.0, 0.0, 3.0], [0.0, 0.0, 6.0], [0.0, 0.0, 9.0], [0.0, 1.0, 9.0]);
    let a = BlockPart {
        cells: vec![rec(0, n, 2.0), rec(1, j, 4.0), rec(2, e1, 1.0), rec(3, e2, 1.0)],
        edges: vec![[0, 1], [1, 2], [1, 3]],
        faces: vec![(5, 1)],
        ..Default::default()
    };
    let b = BlockPart { cells: vec![rec(0, e1, 1.0), rec(1, e2, 1.0)], faces: vec![(6, 0)], ..Default::default() };
    let g = sk.merge_blocks(&[a, b], volume, [1.0; 3]).unwrap();
    assert_eq!(g.positions, [n, j, e2]);
    assert_eq!(g.edges, [[0, 1], [1, 2]]);
    // (b) P - K - J - L, L 2.24 from J (radius 3), towards K.
    let (p, k, l) = ([0.0, 0.0, 0.0], [0.0, 0.0, 3.0], [0.0, 1.0, 4.0]);
    let a = BlockPart {
        cells: vec![rec(0, p, 2.0), rec(1, k, 2.0), rec(2, j, 3.0), rec(3, l, 1.0)],
        edges: vec![[0, 1], [1, 2], [2, 3]],
        faces: vec![(5, 2)],
        ..Default::default()
    };
    let b = BlockPart { cells: vec![rec(0, l, 1.0)], faces: vec![(6, 0)], ..Default::default() };
    let g = sk.merge_blocks(&[a, b], volume, [1.0; 3]).unwrap();
    assert_eq!(g.positions, [p, k, j]);
    assert_eq!(g.edges, [[0, 1], [1, 2]]);
}
