//! Property tests of the whole method on random small masks (issue 19): every mask a
//! user can pass — any shape down to one voxel thick, any density from empty to all
//! vessel, isotropic or anisotropic spacing — gives `Ok` and a well-formed graph whose
//! components are the mask's 26-connected components.
//!
//! The CI cases are few and small (a few seconds); `cargo test --test properties --
//! --ignored` runs the long campaign.

use ndarray::Array3;
use petgraph::unionfind::UnionFind;
use proptest::prelude::*;
use vesselflow::{Params, Skeleton, Skeletonizer};

/// Spacings tried: isotropic at three scales, and anisotropic along each axis.
const SPACINGS: [[f64; 3]; 6] =
    [[1.0, 1.0, 1.0], [0.25, 0.25, 0.25], [7.5, 7.5, 7.5], [2.0, 1.0, 1.0], [1.0, 0.4, 1.0], [0.5, 0.7, 3.0]];

/// A mask of `shape` with about `density` per cent vessel voxels, from `seed`.
fn mask(shape: [usize; 3], density: u64, seed: u64) -> Array3<u8> {
    let mut state = seed;
    Array3::from_shape_fn(shape, |_| {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        u8::from((state >> 33) % 100 < density)
    })
}

/// 26-connected components of the mask, counted by brute force.
fn mask_components(m: &Array3<u8>) -> usize {
    let (n0, n1, n2) = m.dim();
    let id = |i: usize, j: usize, k: usize| (i * n1 + j) * n2 + k;
    let mut uf = UnionFind::<usize>::new(m.len());
    for ((i, j, k), &v) in m.indexed_iter() {
        if v == 0 {
            continue;
        }
        for (a, b, c) in (0..27).map(|t| (t / 9, t / 3 % 3, t % 3)) {
            let (x, y, z) = (i + a, j + b, k + c);
            if (1..=n0).contains(&x) && (1..=n1).contains(&y) && (1..=n2).contains(&z) && m[[x - 1, y - 1, z - 1]] != 0
            {
                uf.union(id(i, j, k), id(x - 1, y - 1, z - 1));
            }
        }
    }
    m.indexed_iter().filter(|&((i, j, k), &v)| v != 0 && uf.find(id(i, j, k)) == id(i, j, k)).count()
}

fn graph_components(s: &Skeleton) -> usize {
    let mut uf = UnionFind::<usize>::new(s.len());
    for &[a, b] in &s.edges {
        uf.union(a, b);
    }
    (0..s.len()).filter(|&i| uf.find(i) == i).count()
}

/// Whether every node lies within one voxel (Chebyshev) of a vessel voxel.
fn inside_dilated(m: &Array3<u8>, s: &Skeleton) -> Result<(), String> {
    let (n0, n1, n2) = m.dim();
    for p in &s.positions {
        let v = [0, 1, 2].map(|d| (p[d] / s.spacing[d]).round() as isize);
        let near = (0..27).map(|t| [t / 9 - 1, t / 3 % 3 - 1, t % 3 - 1]).any(|o| {
            let [i, j, k] = [v[0] + o[0], v[1] + o[1], v[2] + o[2]];
            i >= 0
                && j >= 0
                && k >= 0
                && (i as usize) < n0
                && (j as usize) < n1
                && (k as usize) < n2
                && m[[i as usize, j as usize, k as usize]] != 0
        });
        if !near {
            return Err(format!("node {p:?} is more than a voxel from the mask"));
        }
    }
    Ok(())
}

/// The invariants; `Err` names the first that fails.
fn check(m: &Array3<u8>, spacing: [f64; 3]) -> Result<(), String> {
    let s = Skeletonizer::new(Params::default())
        .unwrap()
        .run(m.view(), spacing, &mut |_| true)
        .map_err(|e| format!("run failed: {e}"))?;
    let n = s.len();
    if s.radii.len() != n {
        return Err(format!("{} radii for {n} nodes", s.radii.len()));
    }
    if !s.positions.iter().flatten().all(|x| x.is_finite()) {
        return Err("a position is not finite".into());
    }
    if !s.radii.iter().all(|r| r.is_finite() && *r >= 0.0) {
        return Err(format!("a radius is not finite and >= 0: {:?}", s.radii));
    }
    if let Some(e) = s.edges.iter().find(|[a, b]| a >= b || *b >= n) {
        return Err(format!("edge {e:?} is not i < j < {n}"));
    }
    let expected = mask_components(m);
    if s.info.mask_components != expected {
        return Err(format!("RunInfo counts {} mask components, there are {expected}", s.info.mask_components));
    }
    let found = graph_components(&s);
    if found != expected {
        return Err(format!("{found} graph components for {expected} mask components"));
    }
    inside_dilated(m, &s)
}

fn case() -> impl Strategy<Value = ([usize; 3], u64, u64, usize)> {
    ([1usize..=9, 1usize..=9, 1usize..=9], 0u64..=100, any::<u64>(), 0..SPACINGS.len())
}

fn long_case() -> impl Strategy<Value = ([usize; 3], u64, u64, usize)> {
    ([1usize..=18, 1usize..=18, 1usize..=18], 0u64..=100, any::<u64>(), 0..SPACINGS.len())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn random_masks_give_well_formed_graphs((shape, density, seed, sp) in case()) {
        let m = mask(shape, density, seed);
        prop_assert_eq!(check(&m, SPACINGS[sp]), Ok(()), "shape {:?} density {} seed {} spacing {:?}",
            shape, density, seed, SPACINGS[sp]);
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 3000, ..ProptestConfig::default() })]

    /// The long campaign: `cargo test --release --test properties -- --ignored`.
    #[test]
    #[ignore]
    fn random_masks_give_well_formed_graphs_long((shape, density, seed, sp) in long_case()) {
        let m = mask(shape, density, seed);
        prop_assert_eq!(check(&m, SPACINGS[sp]), Ok(()), "shape {:?} density {} seed {} spacing {:?}",
            shape, density, seed, SPACINGS[sp]);
    }
}

/// Edge cases the random search reaches only by luck: all vessel and empty, in
/// every thin shape.
#[test]
fn empty_and_full_masks_of_thin_shapes() {
    for shape in [[1, 1, 1], [1, 1, 7], [2, 1, 5], [1, 6, 2], [2, 2, 2], [3, 2, 9], [9, 9, 1]] {
        for density in [0, 100] {
            for spacing in SPACINGS {
                let m = mask(shape, density, 1);
                assert_eq!(check(&m, spacing), Ok(()), "shape {shape:?} density {density} spacing {spacing:?}");
            }
        }
    }
}
