//! Nodes kept inside the mask (output stage, and the contraction's undone moves; not in the paper).
//!
//! The flow and the mean-position decimation can leave a node off the mask: a
//! cluster of a thin curved vessel averages to a point on the chord of the curve,
//! and on a lattice of one-voxel lines, or on noise, the mean of a cluster can fall
//! in a hole (measured: up to 2.8 voxels out on a period-4 lattice). A graph node
//! must lie in a vessel, so every node whose voxel is background is moved into the
//! nearest foreground voxel (nearest centre in physical distance, ties to the first
//! voxel in C order), by the shortest move that puts it there: to the point of that
//! voxel's cube, shrunk to [`KEEP`] of its width, nearest to the node. The search runs
//! in cubes of growing half-width up to
//! [`SEARCH_LIMIT`] voxels (a node further out than that is left where it is; the
//! output check reports it). Nodes on foreground voxels do not move, so graphs whose
//! nodes were all inside are unchanged bit for bit.

use crate::cycles::Cycle;
use crate::vec3::{base_cell, norm, sub};
use crate::volume::Voxel;
use ndarray::ArrayView3;
use rayon::prelude::*;

/// Fraction of a voxel's half-width a moved node may lie off its centre (below ½, so
/// that the node rounds to that voxel).
pub const KEEP: f64 = 0.9;

/// Largest half-width, in voxels, of the cube searched for a foreground voxel.
pub const SEARCH_LIMIT: isize = 8;

/// Whether `p` (physical units) lies on the mask: its nearest voxel is in the array and
/// set. The one test of "on a vessel voxel" for every stage.
pub fn on_mask<T: Voxel>(mask: &ArrayView3<'_, T>, p: [f64; 3], spacing: [f64; 3]) -> bool {
    let (n0, n1, n2) = mask.dim();
    voxel_of(p, spacing, [n0, n1, n2]).is_some_and(|v| mask[v].is_set())
}

/// The voxel index nearest to `p` (physical units), if it lies in the array.
pub fn voxel_of(p: [f64; 3], spacing: [f64; 3], shape: [usize; 3]) -> Option<[usize; 3]> {
    let mut idx = [0usize; 3];
    for d in 0..3 {
        let v = (p[d] / spacing[d]).round();
        if !(v >= 0.0 && v < shape[d] as f64) {
            return None;
        }
        idx[d] = v as usize;
    }
    Some(idx)
}

/// The centre of the foreground voxel nearest to `p` (in voxels), searched as in the
/// module doc.
pub(crate) fn nearest_foreground<T: Voxel>(
    mask: &ArrayView3<'_, T>,
    p: [f64; 3],
    spacing: [f64; 3],
) -> Option<[isize; 3]> {
    let (n0, n1, n2) = mask.dim();
    let shape = [n0 as isize, n1 as isize, n2 as isize];
    let centre: [isize; 3] = std::array::from_fn(|d| (p[d] / spacing[d]).round().clamp(-1.0, shape[d] as f64) as isize);
    let dist = |v: [isize; 3]| (0..3).map(|d| (v[d] as f64 * spacing[d] - p[d]).powi(2)).sum::<f64>();
    for half in 1..=SEARCH_LIMIT {
        let range = |d: usize| (centre[d] - half).max(0)..=(centre[d] + half).min(shape[d] - 1);
        let mut best: Option<(f64, [isize; 3])> = None;
        for i in range(0) {
            for j in range(1) {
                for k in range(2) {
                    let v = [i, j, k];
                    if mask[[i as usize, j as usize, k as usize]].is_set() {
                        let d = dist(v);
                        if best.is_none_or(|(b, _)| d < b) {
                            best = Some((d, v));
                        }
                    }
                }
            }
        }
        // A voxel found in this cube is the nearest one if no voxel outside the cube
        // can be closer: those lie at least `half + 0.5` voxels out along some axis
        // from the rounded centre, i.e. `(half) * spacing` from `p` at the least.
        if let Some((d, v)) = best {
            let outside = (0..3).map(|a| half as f64 * spacing[a]).fold(f64::INFINITY, f64::min);
            if d.sqrt() <= outside || half == SEARCH_LIMIT {
                return Some(v);
            }
        }
    }
    None
}

/// `positions` with every node on a background voxel (or outside the array) moved to
/// the nearest foreground voxel centre (see the module).
pub fn keep_inside<T: Voxel>(positions: &[[f64; 3]], mask: ArrayView3<'_, T>, spacing: [f64; 3]) -> Vec<[f64; 3]> {
    positions
        .par_iter()
        .map(|&p| {
            if on_mask(&mask, p, spacing) {
                return p;
            }
            nearest_foreground(&mask, p, spacing).map_or(p, |v| {
                std::array::from_fn(|d| {
                    let (c, half) = (v[d] as f64 * spacing[d], 0.5 * KEEP * spacing[d]);
                    p[d].clamp(c - half, c + half)
                })
            })
        })
        .collect()
}

/// The positions a contraction step may put back ([`undo_moves_off_the_mask`]): every
/// node `k` that `held(k)` selects and that starts on the mask, with its position.
/// Only those are kept, not every node's position before the move: most nodes of the
/// first iterations are not held (their degree is above 2), and a copy of every
/// position (24 bytes a node) was 6.6 of the 60 MB of heap at the solve of
/// `damseh_synth2`'s first iteration.
#[derive(Debug)]
pub struct HeldOnMask {
    nodes: Vec<u32>,
    positions: Vec<[f64; 3]>,
}

impl HeldOnMask {
    /// The nodes of `before` (positions, in the solve's order) that `held` selects
    /// and that lie on `mask`.
    pub fn new<T: Voxel>(
        before: &[[f64; 3]],
        held: &(dyn Fn(usize) -> bool + Sync),
        mask: ArrayView3<'_, T>,
        spacing: [f64; 3],
    ) -> HeldOnMask {
        let (nodes, positions) = before
            .par_iter()
            .enumerate()
            .filter(|&(k, &b)| held(k) && on_mask(&mask, b, spacing))
            .map(|(k, &b)| (k as u32, b))
            .unzip();
        HeldOnMask { nodes, positions }
    }
}

/// Every node of `held` that the contraction's solve took from its foreground voxel
/// onto a background voxel or out of the array, or across the background to another
/// foreground voxel (its new position in `moved`), goes back where it was (not in the
/// paper). The flow pulls a loop around a narrow hole of the mask across the hole and
/// shut, and cuts the corner of a thin curved vessel through the background: both are
/// moves off the mask. Where bubbles of noise have narrowed a loop's hole to a voxel
/// or two, a ring node's step could clear it and land on the far rim: the straight
/// path of every move is read at steps of at most [`PATH_STEP`] base cells, and a move
/// that crosses a background voxel is undone like one that ends on it (README, "Where
/// we differ", 18). A node already off the mask moves freely, so that it can come back.
pub fn undo_moves_off_the_mask<T: Voxel>(
    moved: &mut [[f64; 3]],
    held: &HeldOnMask,
    mask: ArrayView3<'_, T>,
    spacing: [f64; 3],
) {
    let step = PATH_STEP * base_cell(spacing);
    for (&k, &b) in held.nodes.iter().zip(&held.positions) {
        let q = &mut moved[k as usize];
        if !path_on_mask(&mask, b, *q, step, spacing) {
            *q = b;
        }
    }
}

/// Largest step, in base cells, at which [`undo_moves_off_the_mask`] reads a move's
/// path: half a cell, so that the path cannot step over a background voxel it crosses
/// by more than a corner.
pub const PATH_STEP: f64 = 0.5;

/// Whether the straight path from `a` to `b` stays on the mask: `b` and the points
/// between, at most `step` apart (`a` is not read: the caller knows it is on the mask).
fn path_on_mask<T: Voxel>(mask: &ArrayView3<'_, T>, a: [f64; 3], b: [f64; 3], step: f64, spacing: [f64; 3]) -> bool {
    let ab = sub(b, a);
    let length = norm(ab);
    // At most 2^16 points (32 768 cells at the finest step): a longer move is read more
    // coarsely, and its end (read first) has decided most such moves already.
    let n = ((length / step).ceil() as usize).clamp(1, 1 << 16);
    on_mask(mask, b, spacing)
        && (1..n).all(|s| {
            let t = s as f64 / n as f64;
            on_mask(mask, std::array::from_fn(|d| a[d] + t * ab[d]), spacing)
        })
}

/// Smallest vessel radius, in base cells, that [`loop_of_the_mask`] measures a hole
/// against. Chosen on the tuning forests at D2 between 0.75 and 1 (59 and 56 of their 66
/// clean-mask loops kept), after a held-out capillary bed showed the need for a floor
/// (one knot kept as a loop without it).
pub const LOOP_FLOOR: f64 = 0.75;

/// Base cells taken off the EDT radii the loop rule compares holes with (the
/// half-voxel correction of `docs/method.md` §1, with which [`loop_of_the_mask`] was set; the output radii
/// are measured apart, by [`crate::radius`]).
pub const LOOP_RADIUS_SHIFT: f64 = 0.5;

/// True if the cycle is a loop of the mask and not a knot of the flow: its centroid
/// lies on a background voxel (or outside the array), so the polygon runs around a
/// hole of the mask, and the hole is at least as wide as the vessels that form it.
/// With `r` the mean vessel radius of the cycle's nodes (their EDT less `shift`): the
/// flow draws a loop's ring in from the vessels' centreline (radius `h + r` about a
/// hole of radius `h`) until its nodes stand on the hole's rim, where
/// [`undo_moves_off_the_mask`] holds them, so by refinement the polygon's radius is
/// between `h` and `h + r`, and `h ≥ r` means an area of at least `π r²`; and of
/// at least `π (LOOP_FLOOR c)²`, `c` the base cell: on a vessel a voxel thin `r` is
/// about half a cell, and a knot of three or four nodes around a crease of the mask
/// would pass (README, "Where we differ", 9). Smaller holes are what bubbles of
/// segmentation noise make beside a vessel; refinement collapses those as before.
pub fn loop_of_the_mask<T: Voxel>(
    cycle: &Cycle,
    positions: &[[f64; 3]],
    radii: &[f64],
    shift: f64,
    mask: ArrayView3<'_, T>,
    spacing: [f64; 3],
) -> bool {
    let k = cycle.nodes.len() as f64;
    let centroid: [f64; 3] =
        std::array::from_fn(|d| cycle.nodes.iter().map(|&i| positions[i as usize][d]).sum::<f64>() / k);
    let r = cycle.nodes.iter().map(|&i| (radii[i as usize] - shift).max(0.0)).sum::<f64>() / k;
    let r = r.max(LOOP_FLOOR * base_cell(spacing));
    let hole = !on_mask(&mask, centroid, spacing);
    hole && cycle.area >= std::f64::consts::PI * r * r
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    /// Brute force: the nearest foreground centre over the whole array.
    fn slow(mask: &Array3<u8>, p: [f64; 3], s: [f64; 3]) -> [f64; 3] {
        let mut best = (f64::INFINITY, [0.0; 3]);
        for ((i, j, k), &m) in mask.indexed_iter() {
            if m != 0 {
                let c = [i as f64 * s[0], j as f64 * s[1], k as f64 * s[2]];
                let d = (0..3).map(|a| (c[a] - p[a]).powi(2)).sum::<f64>();
                if d < best.0 {
                    best = (d, c);
                }
            }
        }
        best.1
    }

    /// Of five nodes that start inside a one-voxel line along axis 2 (and one outside),
    /// the moves of held nodes that end off the line are undone, at any spacing: the
    /// move along the line, the move off it that stays within its voxel, the node not
    /// held and the node that started outside keep their new positions.
    #[test]
    fn held_moves_from_the_mask_onto_the_background_are_undone() {
        let line = Array3::from_shape_fn((3, 3, 6), |(i, j, _)| u8::from(i == 1 && j == 1));
        for spacing in [[1.0; 3], [0.5, 2.0, 1.5]] {
            let at = |v: [f64; 3]| -> [f64; 3] { std::array::from_fn(|d| v[d] * spacing[d]) };
            let before: Vec<[f64; 3]> =
                [[1.0, 1.0, 1.0], [1.0, 1.0, 2.0], [1.0, 1.0, 3.0], [1.0, 1.0, 4.0], [0.0, 0.0, 0.0], [1.0, 1.0, 5.0]]
                    .map(at)
                    .to_vec();
            let to: Vec<[f64; 3]> =
                [[1.0, 1.0, 2.6], [1.0, 1.7, 2.0], [1.3, 1.0, 3.0], [1.0, 1.0, 6.0], [0.0, 0.0, 1.0], [2.0, 1.0, 5.0]]
                    .map(at)
                    .to_vec();
            let mut moved = to.clone();
            let held = HeldOnMask::new(&before, &|k| k != 5, line.view(), spacing);
            undo_moves_off_the_mask(&mut moved, &held, line.view(), spacing);
            assert_eq!(moved, vec![to[0], before[1], to[2], before[3], to[4], to[5]], "spacing {spacing:?}");
        }
    }

    /// A held node's step across the background onto another vessel is undone like a
    /// step onto the background (two lines two voxels apart, at any spacing): the step
    /// along its own line and the node not held keep their new positions.
    #[test]
    fn held_moves_across_the_background_are_undone() {
        let lines = Array3::from_shape_fn((3, 5, 6), |(i, j, _)| u8::from(i == 1 && (j == 1 || j == 3)));
        for spacing in [[1.0; 3], [0.5, 2.0, 1.5]] {
            let at = |v: [f64; 3]| -> [f64; 3] { std::array::from_fn(|d| v[d] * spacing[d]) };
            let before: Vec<[f64; 3]> =
                [[1.0, 1.0, 1.0], [1.0, 1.0, 2.0], [1.0, 3.0, 4.0], [1.0, 1.0, 3.0]].map(at).to_vec();
            let to: Vec<[f64; 3]> =
                [[1.0, 3.0, 1.0], [1.0, 1.0, 4.9], [1.0, 1.0, 4.0], [1.0, 3.0, 3.0]].map(at).to_vec();
            let mut moved = to.clone();
            let held = HeldOnMask::new(&before, &|k| k != 3, lines.view(), spacing);
            undo_moves_off_the_mask(&mut moved, &held, lines.view(), spacing);
            assert_eq!(moved, vec![before[0], to[1], before[2], to[3]], "spacing {spacing:?}");
        }
    }

    /// A ring drawn in onto the rim of its hole is a loop when the hole is as wide as
    /// its vessels: a band three voxels wide around a 3×3 hole, the polygon on the
    /// rim's voxels (area 16, radii 2: r = 1.5), which `π (2 r)²` (the centreline's
    /// bound) refused. A polygon around a one-voxel hole in a mask a voxel thin (radii 1:
    /// r = 0.5, area 1.44) is not: the floor of `LOOP_FLOOR` base cells.
    #[test]
    fn a_ring_on_the_rim_of_a_hole_as_wide_as_its_vessels_is_a_loop() {
        let nodes = [0u32, 1, 2, 3];
        let cycle = |p: &[[f64; 3]]| Cycle { nodes: nodes.to_vec(), area: crate::cycles::vector_area(&nodes, p) };
        let band = Array3::from_shape_fn((3, 11, 11), |(i, j, k)| {
            u8::from(
                i == 1
                    && (1..=9).contains(&j)
                    && (1..=9).contains(&k)
                    && !((4..=6).contains(&j) && (4..=6).contains(&k)),
            )
        });
        let rim = [[1.0, 3.0, 3.0], [1.0, 7.0, 3.0], [1.0, 7.0, 7.0], [1.0, 3.0, 7.0]];
        assert!(loop_of_the_mask(&cycle(&rim), &rim, &[2.0; 4], 0.5, band.view(), [1.0; 3]));
        assert!(!loop_of_the_mask(&cycle(&rim), &rim, &[3.0; 4], 0.5, band.view(), [1.0; 3]));
        let mut pierced = Array3::<u8>::zeros((3, 9, 9));
        pierced.slice_mut(ndarray::s![1, .., ..]).fill(1);
        pierced[[1, 4, 4]] = 0;
        let knot = [[1.0, 3.4, 3.4], [1.0, 4.6, 3.4], [1.0, 4.6, 4.6], [1.0, 3.4, 4.6]];
        assert!(!loop_of_the_mask(&cycle(&knot), &knot, &[1.0; 4], 0.5, pierced.view(), [1.0; 3]));
    }

    /// A square loop of one-voxel lines around a 3×3 hole is a loop of the mask; a
    /// 2×2 polygon around a one-voxel bubble inside a thick vessel is not, nor is a
    /// polygon whose centroid lies in the vessel.
    #[test]
    fn loops_around_holes_wider_than_their_vessels_are_loops_of_the_mask() {
        let square =
            |o: f64, side: f64| vec![[2.0, o, o], [2.0, o + side, o], [2.0, o + side, o + side], [2.0, o, o + side]];
        let cycle =
            |p: &[[f64; 3]]| Cycle { nodes: vec![0, 1, 2, 3], area: crate::cycles::vector_area(&[0, 1, 2, 3], p) };
        // Lines along axes 1 and 2 at 0 and 4 in plane 2: a hole at 1..=3.
        let ring = Array3::from_shape_fn((5, 5, 5), |(i, j, k)| u8::from(i == 2 && (j % 4 == 0 || k % 4 == 0)));
        let p = square(0.0, 4.0);
        assert!(loop_of_the_mask(&cycle(&p), &p, &[1.0; 4], 0.5, ring.view(), [1.0; 3]));
        // The same loop counted with radii of 2.5: the hole is narrower than the vessels.
        assert!(!loop_of_the_mask(&cycle(&p), &p, &[3.0; 4], 0.5, ring.view(), [1.0; 3]));
        // A bubble: a solid 5×9×9 block with one background voxel at its centre.
        let mut block = Array3::<u8>::ones((5, 9, 9));
        block[[2, 4, 4]] = 0;
        let q = square(3.0, 2.0);
        assert!(!loop_of_the_mask(&cycle(&q), &q, &[3.0; 4], 0.5, block.view(), [1.0; 3]));
        // A knot of the flow: its centroid is on the vessel.
        block[[2, 4, 4]] = 1;
        assert!(!loop_of_the_mask(&cycle(&q), &q, &[0.6; 4], 0.5, block.view(), [1.0; 3]));
    }

    #[test]
    fn nodes_off_the_mask_move_to_the_nearest_vessel_voxel() {
        let mut rnd = crate::test_rng(99);
        for trial in 0..40 {
            let shape = (3 + rnd(10) as usize, 3 + rnd(10) as usize, 3 + rnd(10) as usize);
            let m = Array3::from_shape_fn(shape, |_| u8::from(rnd(100) < 8));
            if m.iter().all(|&v| v == 0) {
                continue;
            }
            let s = if trial % 2 == 0 { [1.0; 3] } else { [1.7, 0.6, 1.1] };
            let pts: Vec<[f64; 3]> = (0..30)
                .map(|_| {
                    std::array::from_fn(|d| (rnd(1000) as f64 / 1000.0) * [shape.0, shape.1, shape.2][d] as f64 * s[d])
                })
                .collect();
            let out = keep_inside(&pts, m.view(), s);
            for (p, q) in pts.iter().zip(&out) {
                let v = voxel_of(*p, s, [shape.0, shape.1, shape.2]);
                if v.is_some_and(|v| m[v] != 0) {
                    assert_eq!(p, q, "a node inside the mask moved");
                } else {
                    let want = slow(&m, *p, s);
                    let qv = voxel_of(*q, s, [shape.0, shape.1, shape.2]).unwrap();
                    assert_eq!(m[qv], 1);
                    let centre = [qv[0] as f64 * s[0], qv[1] as f64 * s[1], qv[2] as f64 * s[2]];
                    let d = |a: [f64; 3]| (0..3).map(|k| (a[k] - p[k]).powi(2)).sum::<f64>();
                    // Equal distance (ties may pick another voxel at the same distance).
                    assert!((d(centre) - d(want)).abs() < 1e-9, "{p:?}: got {q:?}, nearest {want:?}");
                    // The shortest move into that voxel's shrunk cube.
                    for a in 0..3 {
                        let off = (q[a] - centre[a]).abs();
                        assert!(off <= 0.5 * KEEP * s[a] + 1e-12);
                        assert!(off + 1e-12 >= ((p[a] - centre[a]).abs()).min(0.5 * KEEP * s[a]));
                    }
                }
            }
        }
    }
}
