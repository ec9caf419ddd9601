//! The coarse start graph (`coarse_cell`, `src/coarse.rs`): cells as wide as the
//! vessel, never across two touching vessels, a node per voxel in thin vessels, the
//! mask's components and loops kept, the same graph for any thread count.

use ndarray::Array3;
use petgraph::unionfind::UnionFind;
use vesselflow::coarse::{cell_side, coarsen, has_cells, MAX_CELL_RADIUS};
use vesselflow::decimate::NodeGraph;
use vesselflow::grid::{self, GridGraph};
use vesselflow::shapes::{self, capsules, segment_distance, Capsule};
use vesselflow::{Params, Skeleton, Skeletonizer};

const CELL: f64 = 0.67;

fn grid_of(mask: &Array3<u8>) -> GridGraph {
    let edt = vesselflow::volume::edt_squared(mask.view(), [1.0; 3]).unwrap();
    grid::build(mask.view(), &edt, [1.0; 3], &Params::default()).unwrap()
}

fn coarse(mask: &Array3<u8>, cell: f64) -> (GridGraph, NodeGraph, Vec<u32>) {
    let g = grid_of(mask);
    let (c, map) = coarsen(g.clone(), [1.0; 3], cell, [0; 3]);
    (g, c, map)
}

/// Components and independent cycles (E - N + components) of a graph.
fn components_and_cycles(nodes: usize, edges: &[(u32, u32)]) -> (usize, usize) {
    let mut uf = UnionFind::<u32>::new(nodes);
    for &(a, b) in edges {
        uf.union(a, b);
    }
    let components = (0..nodes as u32).filter(|&i| uf.find(i) == i).count();
    (components, edges.len() + components - nodes)
}

fn run(mask: &Array3<u8>, params: Params) -> Skeleton {
    Skeletonizer::new(params).unwrap().run(mask.view(), [1.0; 3], &mut |_| true).unwrap()
}

/// Two parallel tubes of radius 5 whose walls overlap along their length.
fn touching_tubes() -> (Array3<u8>, [[f64; 3]; 2], [[f64; 3]; 2]) {
    let a = [[2.0, 12.0, 12.0], [57.0, 12.0, 12.0]];
    let b = [[2.0, 12.0, 21.0], [57.0, 12.0, 21.0]];
    let mask =
        capsules([60, 25, 34], [1.0; 3], &[Capsule { a: a[0], b: a[1], r: 5.0 }, Capsule { a: b[0], b: b[1], r: 5.0 }]);
    (mask, a, b)
}

#[test]
fn no_cell_spans_two_touching_tubes() {
    let (mask, a, b) = touching_tubes();
    let (g, c, map) = coarse(&mask, CELL);
    assert_eq!(g.components, 1, "the tubes touch");
    // The tube of every voxel: the nearer axis (voxels halfway between are left out).
    let mut tube_of_cell = vec![None; c.positions.len()];
    let mut spanning = 0;
    for (v, p) in g.positions.iter().enumerate() {
        let (da, db) = (segment_distance(*p, a[0], a[1]), segment_distance(*p, b[0], b[1]));
        if (da - db).abs() < 1.0 {
            continue;
        }
        let tube = da < db;
        match tube_of_cell[map[v] as usize] {
            None => tube_of_cell[map[v] as usize] = Some(tube),
            Some(t) => spanning += usize::from(t != tube),
        }
    }
    assert_eq!(spanning, 0, "voxels of both tubes share a cell");
    assert!(c.positions.len() * 3 < g.positions.len(), "{} cells for {} voxels", c.positions.len(), g.positions.len());
}

#[test]
fn a_torus_keeps_its_loop() {
    let mask = shapes::torus([24, 64, 64], 20.0, 6.0);
    let (g, c, _) = coarse(&mask, 1.0);
    assert!(c.positions.len() * 4 < g.positions.len(), "{} cells for {} voxels", c.positions.len(), g.positions.len());
    let (components, cycles) = components_and_cycles(c.positions.len(), &c.graph.edge_list());
    assert_eq!(components, 1);
    assert!(cycles >= 1);
    let s = run(&mask, Params { coarse_cell: 1.0, ..Params::default() });
    let edges: Vec<(u32, u32)> = s.edges.iter().map(|e| (e[0] as u32, e[1] as u32)).collect();
    assert_eq!(components_and_cycles(s.len(), &edges), (1, 1));
}

#[test]
fn thin_vessels_keep_one_node_per_voxel() {
    // Radius 1.2: the vessel radius is below 2 / coarse_cell voxels.
    let mask = shapes::cylinder([40, 9, 9], 1.2);
    let (g, c, map) = coarse(&mask, CELL);
    assert_eq!(map, (0..g.positions.len() as u32).collect::<Vec<_>>());
    assert_eq!(c.positions, g.positions);
    assert_eq!(c.graph, g.graph);
    // Off: the grid graph itself, whatever the vessel.
    let thick = shapes::cylinder([30, 21, 21], 7.0);
    let (g, c, _) = coarse(&thick, 0.0);
    assert_eq!((c.positions, c.graph), (g.positions, g.graph));
}

#[test]
fn a_mask_too_thin_for_any_cell_gives_the_graph_of_the_grid_start() {
    // A T of one-voxel lines (radius under 2 / 0.5 voxels) whose three tips are leaf
    // voxels: no leaf is absorbed and no edge split, so the run is that of the grid start.
    let mut mask = Array3::<u8>::zeros((30, 24, 12));
    mask.slice_mut(ndarray::s![3..27, 6, 6]).fill(1);
    mask.slice_mut(ndarray::s![15, 7..21, 6]).fill(1);
    let (g, c, map) = coarse(&mask, 0.5);
    let leaves = (0..g.positions.len()).filter(|&v| g.graph.neighbours(v).len() == 1).count();
    assert!(leaves > 0, "the test needs leaf voxels");
    assert_eq!(map, (0..g.positions.len() as u32).collect::<Vec<_>>());
    assert_eq!((c.positions, c.graph), (g.positions, g.graph));
    let on = run(&mask, Params { coarse_cell: 0.5, ..Params::default() });
    let off = run(&mask, Params { coarse_cell: 0.0, ..Params::default() });
    assert_eq!((on.positions, on.edges, on.radii), (off.positions, off.edges, off.radii));
}

/// Above `MAX_CELL_RADIUS` (8 voxels) a vessel keeps a node per voxel, as a thin one
/// does: cells in vessels that thick went wrong on the real aortas (README, item 13).
#[test]
fn vessels_thicker_than_the_largest_cell_radius_keep_one_node_per_voxel() {
    assert_eq!(MAX_CELL_RADIUS, 8.0);
    assert_eq!(cell_side(CELL, 8.0, 1.0), 5);
    assert_eq!(cell_side(CELL, 8.01, 1.0), 1);
    assert!(!has_cells(CELL, 9.0, 1.0));
    // In voxels of the coarsest spacing: 9 units at spacing 2 are 4.5 voxels.
    assert_eq!(cell_side(CELL, 9.0, 2.0), 3);
    // A tube of radius 10 keeps most of its voxels as nodes (a voxel whose climb stops
    // at a ridge point under 8, as near the tube's flat ends, may share a cell); one of
    // 7.5 is cut into cells.
    let (g, c, _) = coarse(&shapes::cylinder([60, 25, 25], 10.0), CELL);
    assert!(
        c.positions.len() * 10 > 8 * g.positions.len(),
        "{} cells for {} voxels",
        c.positions.len(),
        g.positions.len()
    );
    let (g, c, _) = coarse(&shapes::cylinder([60, 25, 25], 7.5), CELL);
    assert!(c.positions.len() * 10 < g.positions.len(), "{} cells for {} voxels", c.positions.len(), g.positions.len());
}

#[test]
fn a_thick_tube_has_far_fewer_nodes_each_inside_its_cell() {
    let mask = shapes::cylinder([60, 25, 25], 7.0);
    let (g, c, map) = coarse(&mask, CELL);
    let (n, m) = (g.positions.len(), c.positions.len());
    assert!(m * 10 < n, "{m} cells for {n} voxels");
    // The quotient graph: two cells are joined exactly when two of their voxels are.
    let mut want: Vec<(u32, u32)> = g
        .graph
        .edge_list()
        .into_iter()
        .map(|(a, b)| (map[a as usize], map[b as usize]))
        .filter(|(a, b)| a != b)
        .map(|(a, b)| (a.min(b), a.max(b)))
        .collect();
    want.sort_unstable();
    want.dedup();
    assert_eq!(c.graph.edge_list(), want);
    // Every node on a vessel voxel of its own cell, with its cell's largest EDT.
    for k in 0..m {
        let p = c.positions[k];
        let v = g.positions.iter().position(|q| (0..3).all(|d| (q[d] - p[d].round()).abs() < 1e-9));
        let v = v.unwrap_or_else(|| panic!("node {k} at {p:?} is not on a vessel voxel"));
        assert_eq!(map[v] as usize, k, "node {k} lies in another cell's voxel");
        let largest = (0..n).filter(|&i| map[i] as usize == k).map(|i| g.radii[i]).fold(0.0, f64::max);
        assert_eq!(c.radii[k], largest);
    }
    let (components, _) = components_and_cycles(m, &c.graph.edge_list());
    assert_eq!(components, 1);
}

#[test]
fn the_same_graph_for_any_thread_count() {
    let mask = shapes::demo_volume();
    let g = grid_of(&mask);
    let on = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| coarsen(g.clone(), [1.0; 3], CELL, [0; 3]))
    };
    let (one, map1) = on(1);
    for threads in [2, 5] {
        let (other, map) = on(threads);
        assert_eq!(map, map1);
        assert_eq!(other.graph, one.graph);
        let bits = |v: &[[f64; 3]]| v.iter().flat_map(|p| p.map(f64::to_bits)).collect::<Vec<_>>();
        assert_eq!(bits(&other.positions), bits(&one.positions));
        assert_eq!(
            other.radii.iter().map(|r| r.to_bits()).collect::<Vec<_>>(),
            one.radii.iter().map(|r| r.to_bits()).collect::<Vec<_>>()
        );
    }
    assert!(one.positions.len() < g.positions.len());
    // No cell is hemmed in by a single other cell: its node would count as a vessel end.
    let leaves = (0..one.positions.len()).filter(|&k| one.graph.neighbours(k).len() == 1).count();
    let grid_leaves = (0..g.positions.len()).filter(|&v| g.graph.neighbours(v).len() == 1).count();
    assert!(leaves <= grid_leaves, "{leaves} cells of degree 1, {grid_leaves} voxels");
    let runs: Vec<Skeleton> =
        [1, 3].iter().map(|&threads| run(&mask, Params { coarse_cell: CELL, threads, ..Params::default() })).collect();
    assert_eq!(runs[0].positions, runs[1].positions);
    assert_eq!(runs[0].edges, runs[1].edges);
    assert_eq!(runs[0].radii, runs[1].radii);
}

/// A block of a chunked run groups its voxels in the whole volume's boxes: cut a radius-5
/// tube (boxes of 2 voxels at 0.5) at voxel 11, an odd offset, and the block's cells away
/// from the cut are the whole volume's, voxel for voxel. Boxes counted from the block's
/// own first voxel would be shifted by one there and share no cell.
#[test]
fn a_block_groups_its_voxels_in_the_volumes_boxes() {
    let whole = shapes::cylinder([64, 15, 15], 5.0);
    let from = 11;
    let block = whole.slice(ndarray::s![from.., .., ..]).to_owned();
    let (_, _, map) = coarse(&whole, 0.5);
    let g = grid_of(&block);
    let (_, block_map) = coarsen(g.clone(), [1.0; 3], 0.5, [from as i64, 0, 0]);
    let (_, local_map) = coarsen(g.clone(), [1.0; 3], 0.5, [0; 3]);
    // Grid nodes are the foreground voxels in C order: the block's are the whole's from
    // the cut on.
    let skipped = whole.slice(ndarray::s![..from, .., ..]).iter().filter(|&&v| v != 0).count();
    let axial = |k: usize| g.positions[k][0] as usize + from;
    let far = (0..g.positions.len()).filter(|&k| (22..50).contains(&axial(k))).collect::<Vec<_>>();
    assert!(far.len() > 1000);
    let (mut same, mut shifted) = (0, 0);
    for &a in &far {
        for &b in &far {
            if a < b && (g.positions[a][0] - g.positions[b][0]).abs() <= 1.0 {
                let together = map[a + skipped] == map[b + skipped];
                assert_eq!(block_map[a] == block_map[b], together, "voxels {a} and {b} of the block");
                same += usize::from(together);
                shifted += usize::from(together != (local_map[a] == local_map[b]));
            }
        }
    }
    assert!(same > 1000 && shifted > 1000, "{same} pairs share a cell, {shifted} differ with local boxes");
}
