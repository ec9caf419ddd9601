//! Masks no vessel segmentation should produce, but a user may feed: noise, lattices
//! of one-voxel lines, planes, checkerboards, lines along each axis, arrays one or two
//! voxels thick. The run must end (every loop of the method is capped) with a graph
//! that keeps the invariants: every node on a vessel voxel, every mask component one
//! graph component, finite positions and radii, edges in range and no self-loops.

use ndarray::Array3;
use petgraph::unionfind::UnionFind;
use vesselflow::{Params, Skeleton, Skeletonizer, Value};

fn run(mask: &Array3<u8>, spacing: [f64; 3]) -> Skeleton {
    let mut p = Params::default();
    // The cap keeps the test short; the invariants must hold wherever the run stops.
    p.set("max_iterations", &Value::Int(12)).unwrap();
    Skeletonizer::new(p).unwrap().run(mask.view(), spacing, &mut |_| true).unwrap()
}

fn rng(seed: u64) -> impl FnMut() -> u64 {
    let mut state = seed;
    move || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        state >> 33
    }
}

fn check(name: &str, mask: &Array3<u8>, spacing: [f64; 3]) -> Skeleton {
    let s = run(mask, spacing);
    let (n0, n1, n2) = mask.dim();
    for (i, p) in s.positions.iter().enumerate() {
        assert!(p.iter().all(|x| x.is_finite()), "{name}: node {i} at {p:?}");
        let v = [0, 1, 2].map(|d| (p[d] / spacing[d]).round());
        assert!(
            v.iter().zip([n0, n1, n2]).all(|(&x, n)| x >= 0.0 && x < n as f64),
            "{name}: node {i} at {p:?} is outside the array"
        );
        assert_eq!(mask[v.map(|x| x as usize)], 1, "{name}: node {i} at {p:?} is on a background voxel");
    }
    assert!(s.radii.iter().all(|r| r.is_finite() && *r >= 0.0), "{name}: bad radius");
    let mut uf = UnionFind::<usize>::new(s.len());
    for &[a, b] in &s.edges {
        assert!(a < s.len() && b < s.len() && a != b, "{name}: bad edge {a}-{b}");
        uf.union(a, b);
    }
    let components = (0..s.len()).filter(|&i| uf.find(i) == i).count();
    assert_eq!(components, s.info.mask_components, "{name}: graph components vs mask components");
    s
}

#[test]
fn random_noise_keeps_every_node_on_a_vessel_voxel() {
    for (density, seed) in [(10, 1), (30, 2), (50, 3)] {
        let mut r = rng(seed);
        let mask = Array3::from_shape_simple_fn((28, 28, 28), || u8::from(r() % 100 < density));
        check(&format!("noise {density} %"), &mask, [1.0; 3]);
    }
}

#[test]
fn lattice_of_one_voxel_lines() {
    // Lines along all three axes every 4 voxels: holes 3 voxels wide.
    let mask = Array3::from_shape_fn((33, 33, 33), |(i, j, k)| {
        u8::from([i % 4 == 0, j % 4 == 0, k % 4 == 0].iter().filter(|&&b| b).count() >= 2)
    });
    // Its loops are the holes between the lines: 9 lines per axis, 3·9²·8 edges of
    // the lattice graph between 9³ crossings, so 1944 - 729 + 1 = 1216 independent
    // loops, each around a hole three times as wide as its lines, and none made by
    // noise: refinement must keep them (it collapsed every one before).
    for (name, spacing) in [("lattice", [1.0; 3]), ("lattice, anisotropic", [2.0, 1.0, 0.7])] {
        let s = check(name, &mask, spacing);
        let rank = s.edges.len() + 1 - s.len();
        assert!((1216 * 95 / 100..=1216).contains(&rank), "{name}: {rank} of the lattice's 1216 loops");
    }
}

#[test]
fn planes_checkerboards_and_lines() {
    let plane = Array3::from_shape_fn((5, 64, 64), |(i, _, _)| u8::from(i == 2));
    check("plane", &plane, [1.0; 3]);
    let thick = Array3::<u8>::ones((5, 48, 48));
    check("slab", &thick, [1.0; 3]);
    let checker = Array3::from_shape_fn((16, 16, 16), |(i, j, k)| u8::from((i + j + k) % 2 == 0));
    check("checkerboard", &checker, [1.0; 3]);
    for axis in 0..3 {
        let mut shape = [5, 5, 5];
        shape[axis] = 40;
        let line = Array3::from_shape_fn(shape, |(i, j, k)| {
            let idx = [i, j, k];
            u8::from((0..3).all(|d| d == axis || idx[d] == 2))
        });
        check(&format!("line along axis {axis}"), &line, [1.0; 3]);
    }
}

#[test]
fn arrays_one_or_two_voxels_thick() {
    for shape in [(1, 1, 1), (1, 1, 30), (1, 30, 1), (2, 2, 2), (1, 20, 20), (2, 20, 20), (20, 2, 1)] {
        let mut r = rng(shape.0 as u64 * 100 + shape.1 as u64);
        let mask = Array3::from_shape_simple_fn(shape, || u8::from(r() % 100 < 60));
        check(&format!("{shape:?} random"), &mask, [1.0; 3]);
        check(&format!("{shape:?} full"), &Array3::<u8>::ones(shape), [1.0; 3]);
    }
}
