//! Vessel ends (output stage, with `anchor_ends`; not in the paper).
//!
//! Laplacian flow shortens every free end: before an end becomes a degree-1 node
//! (and is anchored), the rounded cap of its vessel contracts inward. Where a vessel
//! ends in a rounded cap, its centreline ends at the centre of the cap's ball, one
//! radius inside the mask. So each degree-1 node is moved outward, along the
//! direction of the last stretch of its branch, to one radius (its output radius)
//! inside the point where that line leaves the mask; a node already that far out
//! stays. Where the line leaves the array rather than the vessel, the array's face cuts
//! the vessel and its centreline runs on to the face: the end goes to the last point
//! inside (within the box of voxel centres). The search along the line is capped at
//! `3 r + 4 c`.
//!
//! A straight line misses where the vessel curves or where two vessels run side by
//! side into one protrusion of the mask (a leaf and an anastomosis back from it, a
//! hairpin): the line leaves the mask early and the rest of the vessel is lost (on the
//! noisy forests of `benches/fidelity.py`, stretches up to 14 voxels long that
//! thinning found). So each end then follows the
//! mask ([`follow_ends`]): the vessel voxels geodesically nearer to the end than to
//! any other edge of the graph (26-neighbour steps, within the same `3 r + 4 c`) are
//! the part of the mask beyond the end; where the farthest of them lies ahead of the
//! end (on the far side of the plane through it orthogonal to its line) and more than
//! a radius past the end's one-radius-inside point, the end moves along the
//! shortest path towards it to the voxel one radius short of the mask's end. Where
//! the array's faces cut that part of the mask (a vessel leaving the volume, or a
//! block's cut in a chunked run), the mask ends at the cut, not at a cap, and the
//! move must run within 45° of the line (more along it than across). The
//! output's last step routes the edge to the moved end inside the mask
//! ([`crate::edges_inside`]).

use crate::grid::Csr;
use crate::inside::{on_mask as inside, voxel_of};
use crate::vec3::{base_cell, dot, norm, sub, unit};
use crate::volume::Voxel;
use ndarray::ArrayView3;
use rayon::prelude::*;
use rustc_hash::FxHashMap;

/// Steps along the line per base cell.
const STEPS_PER_CELL: f64 = 4.0;

/// The unit direction from the node `reach` back along the branch to end `i`.
fn direction(g: &Csr, positions: &[[f64; 3]], i: usize, reach: f64) -> Option<[f64; 3]> {
    let (mut prev, mut cur) = (i, g.neighbours(i)[0] as usize);
    let mut walked = 0.0;
    // Each step moves one node further from the end: capped by the node count.
    for _ in 0..g.nodes() {
        walked += dist(&positions[prev], &positions[cur]);
        let nb = g.neighbours(cur);
        if walked >= reach || nb.len() != 2 {
            break;
        }
        let next = if nb[0] as usize == prev { nb[1] } else { nb[0] } as usize;
        (prev, cur) = (cur, next);
    }
    unit(sub(positions[i], positions[cur]))
}

fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    norm(sub(*a, *b))
}

/// Every degree-1 node inside the mask mapped by `step(p, u, r, c)`: its position,
/// its branch's unit direction pointing out of the end, its radius and the base cell
/// (`None`: the end stays). Other nodes stay.
fn move_ends<T: Voxel>(
    g: &Csr,
    positions: &[[f64; 3]],
    radii: &[f64],
    mask: &ArrayView3<'_, T>,
    spacing: [f64; 3],
    step: impl Fn([f64; 3], [f64; 3], f64, f64) -> Option<[f64; 3]> + Sync,
) -> Vec<[f64; 3]> {
    let c = base_cell(spacing);
    (0..g.nodes())
        .into_par_iter()
        .map(|i| {
            let p = positions[i];
            if g.neighbours(i).len() != 1 || !inside(mask, p, spacing) {
                return p;
            }
            let r = radii[i];
            let Some(u) = direction(g, positions, i, (2.0 * r).max(2.0 * c)) else { return p };
            step(p, u, r, c).unwrap_or(p)
        })
        .collect()
}

/// Positions with every degree-1 node moved to its vessel's end (see the module).
pub fn extend_ends<T: Voxel>(
    g: &Csr,
    positions: &[[f64; 3]],
    radii: &[f64],
    mask: ArrayView3<'_, T>,
    spacing: [f64; 3],
) -> Vec<[f64; 3]> {
    let (n0, n1, n2) = mask.dim();
    let shape = [n0, n1, n2];
    move_ends(g, positions, radii, &mask, spacing, |p, u, r, c| {
        let h = c / STEPS_PER_CELL;
        let steps = ((3.0 * r + 4.0 * c) / h).ceil() as usize;
        let at = |t: f64| [p[0] + t * u[0], p[1] + t * u[1], p[2] + t * u[2]];
        // The last inside sample; the boundary is half a step beyond it.
        let last = (1..=steps).take_while(|&k| inside(&mask, at(k as f64 * h), spacing)).last().unwrap_or(0);
        if last < steps && voxel_of(at((last + 1) as f64 * h), spacing, shape).is_none() {
            // The line leaves the array, not the vessel: the array's face cuts the
            // vessel, whose centreline runs on to the face. The end goes to the last
            // sample inside, kept within the voxel centres' box.
            let face = (0..3)
                .filter(|&d| u[d] != 0.0)
                .map(|d| if u[d] > 0.0 { ((shape[d] - 1) as f64 * spacing[d] - p[d]) / u[d] } else { -p[d] / u[d] })
                .fold(f64::INFINITY, f64::min);
            let t = (last as f64 * h).min(face);
            return (t > 0.0).then(|| at(t));
        }
        let t = (last as f64 + 0.5) * h - r;
        (t > 0.0).then(|| at(t))
    })
}

/// The voxels that the graph's edges pass through (sampled [`STEPS_PER_CELL`] times
/// per base cell, as the ends' lines are), as sorted linear indices into the mask.
pub(crate) fn edge_voxels(g: &Csr, positions: &[[f64; 3]], shape: [usize; 3], spacing: [f64; 3]) -> Vec<usize> {
    let c = base_cell(spacing);
    let mut out: Vec<usize> = g
        .edge_list()
        .par_iter()
        .flat_map_iter(|&(a, b)| {
            let (p, q) = (positions[a as usize], positions[b as usize]);
            let pieces = (dist(&p, &q) * STEPS_PER_CELL / c).ceil() as usize;
            (0..=pieces).filter_map(move |k| {
                let t = if pieces == 0 { 0.0 } else { k as f64 / pieces as f64 };
                let x = std::array::from_fn(|d| p[d] + t * (q[d] - p[d]));
                voxel_of(x, spacing, shape).map(|v| (v[0] * shape[1] + v[1]) * shape[2] + v[2])
            })
        })
        .collect();
    out.par_sort_unstable();
    out.dedup();
    out
}

/// Where end `p` (radius `r`, its branch pointing along the unit `u`) continues
/// along the mask: the vessel voxels reached from `p`'s voxel before any voxel of
/// another edge (26-neighbour steps, geodesic distances within `reach`) form the part
/// of the mask beyond the end; the voxel of that part farthest from `p` is where the
/// vessel ends, and the end moves along the shortest path towards it to the voxel
/// centre one radius (less half a cell) short of it, if that lies more than `r`
/// further on and the farthest voxel lies ahead of `p` (a side branch at the end is no
/// continuation); where that part of the mask reaches the array's faces, the move
/// must also run within 45° of `u` (at a cut, the rim is no continuation). `None`: the
/// end stays.
fn follow_mask<T: Voxel>(
    mask: &ArrayView3<'_, T>,
    edges: &[usize],
    p: [f64; 3],
    u: [f64; 3],
    r: f64,
    reach: f64,
    spacing: [f64; 3],
) -> Option<[f64; 3]> {
    use std::cmp::Reverse;
    use std::collections::BinaryHeap;
    let (n0, n1, n2) = mask.dim();
    let shape = [n0, n1, n2];
    let c = base_cell(spacing);
    let start = voxel_of(p, spacing, shape)?;
    let half: [usize; 3] = std::array::from_fn(|d| (reach / spacing[d]).ceil() as usize + 1);
    let lo: [usize; 3] = std::array::from_fn(|d| start[d].saturating_sub(half[d]));
    let hi: [usize; 3] = std::array::from_fn(|d| (start[d] + half[d]).min(shape[d] - 1));
    let linear = |v: [usize; 3]| (v[0] * shape[1] + v[1]) * shape[2] + v[2];
    let voxel = |i: usize| [i / (shape[1] * shape[2]), (i / shape[2]) % shape[1], i % shape[2]];
    let in_box = |v: [usize; 3]| (0..3).all(|d| lo[d] <= v[d] && v[d] <= hi[d]);
    // Reached vessel voxels: distance, owner (true: the end; false: another edge) and
    // the voxel it was reached from. Only reached voxels are stored.
    // (FxHash: the default SipHash took half of the search's time on the 256³ bed; the map
    // is only read by key, so the hash changes no result.)
    let mut seen: FxHashMap<usize, (f64, bool, usize)> = FxHashMap::default();
    let mut heap = BinaryHeap::new();
    let s = linear(start);
    let (first, last) = (edges.partition_point(|&i| i < linear(lo)), edges.partition_point(|&i| i <= linear(hi)));
    for &i in &edges[first..last] {
        let v = voxel(i);
        if i != s && in_box(v) && mask[v].is_set() {
            seen.insert(i, (0.0, false, i));
            heap.push(Reverse((0u64, i)));
        }
    }
    seen.insert(s, (0.0, true, s));
    heap.push(Reverse((0u64, s)));
    let mut far = (0.0, s);
    // The length of the step to neighbour `o` (offsets `o / 9`, `o / 3 % 3`, `o % 3`
    // less one), the same number whatever the voxel.
    let steps: [f64; 27] = std::array::from_fn(|o| {
        (0..3).map(|k| (([o / 9, (o / 3) % 3, o % 3][k] as f64 - 1.0) * spacing[k]).powi(2)).sum::<f64>().sqrt()
    });
    // Whether the vessel beyond the end reaches the array's faces (it is cut there).
    let mut cut = false;
    // Each vessel voxel of the box is settled once: bounded by the box.
    while let Some(Reverse((bits, i))) = heap.pop() {
        let d = f64::from_bits(bits);
        let (best, own, _) = seen[&i];
        if d > best {
            continue;
        }
        let v = voxel(i);
        if own {
            if d > far.0 {
                far = (d, i);
            }
            cut |= (0..3).any(|k| v[k] == 0 || v[k] + 1 == shape[k]);
        }
        for (o, &step) in steps.iter().enumerate() {
            let w: [isize; 3] = std::array::from_fn(|k| v[k] as isize + [o / 9, (o / 3) % 3, o % 3][k] as isize - 1);
            if o == 13 || (0..3).any(|k| w[k] < lo[k] as isize || w[k] > hi[k] as isize) {
                continue;
            }
            let w = w.map(|x| x as usize);
            if !mask[w].is_set() {
                continue;
            }
            let (j, nd) = (linear(w), d + step);
            if nd <= reach && seen.get(&j).is_none_or(|e| nd < e.0) {
                seen.insert(j, (nd, own, i));
                heap.push(Reverse((nd.to_bits(), j)));
            }
        }
    }
    let target = far.0 + 0.5 * c - r;
    let centre = |v: [usize; 3]| -> [f64; 3] { std::array::from_fn(|d| v[d] as f64 * spacing[d]) };
    if target <= r || dot(sub(centre(voxel(far.1)), p), u) <= 0.0 {
        return None;
    }
    let mut i = far.1;
    // Back along the path (each step lowers the distance): bounded by the reached voxels.
    for _ in 0..seen.len() {
        let (d, _, from) = seen[&i];
        if d <= target || from == i {
            break;
        }
        i = from;
    }
    // Where the array's faces cut the vessel beyond the end, the mask there ends at
    // the face, not at a cap: the move runs more along the branch's line than across
    // it (else it goes to the cut's rim).
    let q = centre(voxel(i));
    let along = dot(sub(q, p), u);
    (!cut || along * std::f64::consts::SQRT_2 >= dist(&q, &p)).then_some(q)
}

/// Every end moved along the mask to where its vessel ends, when the mask goes on
/// past it by more than a radius (see [`follow_mask`]): a vessel that curves or
/// splits beyond the end, which the straight line of [`extend_ends`] leaves.
pub fn follow_ends<T: Voxel>(
    g: &Csr,
    positions: &[[f64; 3]],
    radii: &[f64],
    mask: ArrayView3<'_, T>,
    spacing: [f64; 3],
) -> Vec<[f64; 3]> {
    let (n0, n1, n2) = mask.dim();
    let edges = edge_voxels(g, positions, [n0, n1, n2], spacing);
    move_ends(g, positions, radii, &mask, spacing, |p, u, r, c| {
        follow_mask(&mask, &edges, p, u, r, 3.0 * r + 4.0 * c, spacing)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    #[test]
    fn an_end_moves_to_one_radius_inside_the_mask() {
        // A 1-voxel-thick bar along axis 2 from k = 0 to 16; a path ending at k = 10.
        let mut mask = Array3::<u8>::zeros((3, 3, 30));
        for k in 0..=16 {
            mask[[1, 1, k]] = 1;
        }
        let g = Csr::from_sorted_edges(3, &[(0, 1), (1, 2)]);
        let p = [[1.0, 1.0, 2.0], [1.0, 1.0, 6.0], [1.0, 1.0, 10.0]];
        let out = extend_ends(&g, &p, &[0.5, 0.5, 2.0], mask.view(), [1.0; 3]);
        // Node 2: the mask ends at 16.5, minus its radius 2: 14.5 (to a quarter step).
        assert!((out[2][2] - 14.5).abs() <= 0.25, "{:?}", out[2]);
        assert_eq!(&out[2][..2], &[1.0, 1.0]);
        // Node 0 points the other way: the mask ends at -0.5, its radius 0.5 keeps it at 0.
        assert!((out[0][2] - 0.0).abs() <= 0.25, "{:?}", out[0]);
        // A middle node never moves.
        assert_eq!(out[1], p[1]);
        // An end whose radius reaches past the mask's end stays.
        let out = extend_ends(&g, &p, &[0.5, 0.5, 7.0], mask.view(), [1.0; 3]);
        assert_eq!(out[2], p[2]);
        // The search is capped at 3 r + 4 c: radius 1 moves node 2 by at most 7 - 1.
        let out = extend_ends(&g, &p, &[0.5, 0.5, 1.0], mask.view(), [1.0; 3]);
        assert!(out[2][2] <= 16.0 + 0.25, "{:?}", out[2]);
    }

    #[test]
    fn an_end_whose_vessel_the_array_face_cuts_goes_to_the_face() {
        // A bar of radius 3 along axis 2 from the array's face (k = 0) to k = 16; a path
        // from k = 8 to k = 12 (radius 3 at both ends).
        let mut mask = Array3::<u8>::zeros((9, 9, 30));
        for ((i, j, k), v) in mask.indexed_iter_mut() {
            let (y, x) = (i as f64 - 4.0, j as f64 - 4.0);
            *v = u8::from(k <= 16 && y * y + x * x <= 9.0);
        }
        let g = Csr::from_sorted_edges(3, &[(0, 1), (1, 2)]);
        let p = [[4.0, 4.0, 8.0], [4.0, 4.0, 10.0], [4.0, 4.0, 12.0]];
        let out = extend_ends(&g, &p, &[3.0; 3], mask.view(), [1.0; 3]);
        // Node 0: the vessel runs on past the face, and so does its centreline; the end
        // goes to the face's voxel centres (it stopped about a radius short, at 2.6).
        assert_eq!(out[0], [4.0, 4.0, 0.0]);
        // Node 2: the bar ends inside the array (at 16.5): one radius inside, 13.5.
        assert!((out[2][2] - 13.5).abs() <= 0.25, "{:?}", out[2]);
    }

    #[test]
    fn an_end_follows_its_vessel_where_it_bends() {
        // A one-voxel bar along axis 2 (k = 0..=15) that goes on diagonally from k = 15
        // ((1, 1 + t, 15 + t), t = 0..=10); a path along the bar ends at k = 14, where
        // the straight line of `extend_ends` leaves the mask one voxel on.
        let mut mask = Array3::<u8>::zeros((3, 14, 28));
        for k in 0..=15 {
            mask[[1, 1, k]] = 1;
        }
        for t in 0..=10 {
            mask[[1, 1 + t, 15 + t]] = 1;
        }
        let g = Csr::from_sorted_edges(3, &[(0, 1), (1, 2)]);
        let p = [[1.0, 1.0, 1.0], [1.0, 1.0, 8.0], [1.0, 1.0, 14.0]];
        let straight = extend_ends(&g, &p, &[1.0; 3], mask.view(), [1.0; 3]);
        assert!(straight[2][1] < 1.5 && straight[2][2] < 15.0, "{:?}", straight[2]);
        // Within the reach 3 r + 4 = 7 the farthest voxel of the mask beyond the end is
        // (1, 5, 19), 1 + 4 √2 away: the end moves along the path to the last voxel at
        // most that less r - 1/2 away, (1, 4, 18). Node 0 is one radius inside its cap.
        let out = follow_ends(&g, &p, &[1.0; 3], mask.view(), [1.0; 3]);
        assert_eq!(out[2], [1.0, 4.0, 18.0]);
        assert_eq!(&out[..2], &p[..2]);
        // Another edge along the diagonal owns it: the end has nowhere to go. That
        // edge's far end (node 4) follows the rest of the diagonal, 3 √2 long, to the
        // last voxel at most 3 √2 - 1/2 away.
        let g = Csr::from_sorted_edges(5, &[(0, 1), (1, 2), (3, 4)]);
        let q = [p[0], p[1], p[2], [1.0, 3.0, 17.0], [1.0, 8.0, 22.0]];
        let out = follow_ends(&g, &q, &[1.0; 5], mask.view(), [1.0; 3]);
        assert_eq!(&out[..4], &q[..4]);
        assert_eq!(out[4], [1.0, 10.0, 24.0]);
        // A straight bar whose end is already one radius inside the cap stays, and so
        // does one with a side branch square to it at the end: that is not ahead.
        let mut bar = Array3::<u8>::zeros((3, 14, 28));
        for k in 0..=15 {
            bar[[1, 1, k]] = 1;
        }
        let g = Csr::from_sorted_edges(3, &[(0, 1), (1, 2)]);
        assert_eq!(follow_ends(&g, &p, &[1.0; 3], bar.view(), [1.0; 3]), p);
        for j in 2..=9 {
            bar[[1, j, 14]] = 1;
        }
        assert_eq!(follow_ends(&g, &p, &[1.0; 3], bar.view(), [1.0; 3]), p);
    }

    #[test]
    fn an_end_turns_with_its_vessel_unless_the_array_face_cuts_it() {
        // A one-voxel bar along axis 2 (k = 0..=15) that turns square at k = 15 along
        // axis 1 ((1, 1 + t, 15), t = 0..=8 or to the array's face); a path along the bar ends at k = 14.
        let l_bar = |n1: usize| {
            let mut mask = Array3::<u8>::zeros((3, n1, 28));
            for k in 0..=15 {
                mask[[1, 1, k]] = 1;
            }
            for t in 0..=8.min(n1 - 2) {
                mask[[1, 1 + t, 15]] = 1;
            }
            mask
        };
        let g = Csr::from_sorted_edges(3, &[(0, 1), (1, 2)]);
        let p = [[1.0, 1.0, 1.0], [1.0, 1.0, 8.0], [1.0, 1.0, 14.0]];
        // Inside the array the end follows the turn: the farthest voxel within the reach
        // 3 r + 4 = 7 is (1, 7, 15), sqrt 2 + 5 away; the end stops at the last path voxel
        // within that less r - 1/2, (1, 6, 15).
        let out = follow_ends(&g, &p, &[1.0; 3], l_bar(14).view(), [1.0; 3]);
        assert_eq!(out[2], [1.0, 6.0, 15.0]);
        // With the turn running into the array's face (y = 7 is its last row) the mask
        // ends at a cut, not a cap: a move that far across the line is refused.
        let out = follow_ends(&g, &p, &[1.0; 3], l_bar(8).view(), [1.0; 3]);
        assert_eq!(out, p);
    }
}
