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
//! - **Rounded caps wider than the end's section.** The contraction can leave an end
//!   node inside its vessel's rounded cap, where the section it measures is narrower
//!   than the vessel (a radius-9 capsule's end node read 5.1): one such radius inside
//!   the tip put the end up to 3.8 voxels past the cap's centre. The depth of the cap
//!   ([`cap_depth`]: how far back from the exit the distance transform keeps up with
//!   the distance to the exit, i.e. the radius of the ball inscribed in the cap) is
//!   about the vessel's radius in a rounded cap and about 0 where the vessel tapers to
//!   its tip. Where it exceeds the end's radius, the end goes to that depth inside the
//!   exit, back along its line if it is past it (never past its neighbour), and
//!   [`follow_ends`] then takes it as the end's radius. A vessel cut flat (a
//!   segmentation's or a field of view's edge inside the array, [`cut_flat`]: its
//!   section a quarter of the depth inside the exit is still nearly the vessel's) keeps
//!   the end's own radius: the centrelines of such truths (the CT aortas' of
//!   `benches/fidelity.py`) end nearer the cut than a radius.
//! - **Lines that run into another vessel.** A spur the contraction leaves at a junction
//!   near a vessel's end can point back along its parent; its line then runs inside the
//!   parent, and moved to where that line leaves the mask the spur grew up to 17 voxels
//!   along the parent, long enough to survive the pruning of short spurs, which then
//!   took the vessel's real end instead. The line stops where it comes nearer another
//!   edge of the graph ([`nearby_edges`]) than both that edge's radius and the distance
//!   travelled, less half a cell; the end then goes one radius inside that point, as
//!   at the mask's edge.
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
use crate::medial::{plane_basis, Field};
use crate::vec3::{base_cell, dot, norm, projection, sub, unit};
use crate::volume::Voxel;
use ndarray::ArrayView3;
use rayon::prelude::*;
use rustc_hash::{FxHashMap, FxHashSet};

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

/// Every degree-1 node inside the mask mapped by `step(i, p, u, r, c, room)`: its
/// index and position, its branch's unit direction pointing out of the end, its radius,
/// the base cell and the distance to its one neighbour, to a position and the radius it
/// was placed by (`None`: the end stays). Other nodes stay.
fn move_ends<T: Voxel>(
    g: &Csr,
    positions: &[[f64; 3]],
    radii: &[f64],
    mask: &ArrayView3<'_, T>,
    spacing: [f64; 3],
    step: impl Fn(usize, [f64; 3], [f64; 3], f64, f64, f64) -> Option<([f64; 3], f64)> + Sync,
) -> (Vec<[f64; 3]>, Vec<f64>) {
    let c = base_cell(spacing);
    (0..g.nodes())
        .into_par_iter()
        .map(|i| {
            let (p, r) = (positions[i], radii[i]);
            if g.neighbours(i).len() != 1 || !inside(mask, p, spacing) {
                return (p, r);
            }
            let Some(u) = direction(g, positions, i, (2.0 * r).max(2.0 * c)) else { return (p, r) };
            let room = dist(&p, &positions[g.neighbours(i)[0] as usize]);
            step(i, p, u, r, c, room).unwrap_or((p, r))
        })
        .unzip()
}

/// How far inside the point `exit` where a vessel's line (unit direction `u`, pointing
/// out) leaves the mask its end's cap has its centre (physical units; `c` the base
/// cell): the points `s` back from `exit`, in steps of `h`, lie in the cap while the
/// distance transform there is at least `s` less [`CAP_SLACK`] base cells; the cap's
/// centre lies that slack before the last of them. In a rounded cap of radius `R` the
/// transform keeps up with `s` up to the cap's centre and stays at `R` beyond it: the
/// answer is about `R`, wherever the end node sits. In a vessel that tapers to its tip
/// the transform falls behind at once: about 0. The scan runs at most `limit` back.
fn cap_depth(field: &Field, exit: [f64; 3], u: [f64; 3], h: f64, limit: f64, c: f64) -> f64 {
    let slack = CAP_SLACK * c;
    let mut depth = 0.0;
    // At most `limit / h` steps.
    for k in 1..=(limit / h).floor() as usize {
        let s = k as f64 * h;
        let x = std::array::from_fn(|d| exit[d] - s * u[d]);
        if field.interpolate(x) * c < s - slack {
            break;
        }
        depth = s;
    }
    (depth - slack).max(0.0)
}

/// The edges met walking the graph from node `i` up to a path length of `reach` (at
/// most 256 nodes), but the edges at `i`; sorted.
fn nearby_edges(g: &Csr, positions: &[[f64; 3]], i: usize, reach: f64) -> Vec<(usize, usize)> {
    let mut queue = vec![(i, 0.0)];
    let mut seen = FxHashSet::from_iter([i]);
    let mut out = vec![];
    let mut k = 0;
    while k < queue.len() && queue.len() < 256 {
        let (a, d) = queue[k];
        k += 1;
        for &b in g.neighbours(a) {
            let b = b as usize;
            if a != i && b != i {
                out.push((a.min(b), a.max(b)));
            }
            let db = d + dist(&positions[a], &positions[b]);
            if db <= reach && seen.insert(b) {
                queue.push((b, db));
            }
        }
    }
    out.sort_unstable();
    out.dedup();
    out
}

/// Whether the mask holds at least half of the ring of radius `rho` about `centre` in
/// the plane orthogonal to the unit `u` ([`RING`] points): called a quarter of the cap's
/// depth `R` inside the exit with `rho = 0.8 R`, true where the vessel is cut flat (its
/// section there is the vessel's) and false in a rounded cap (whose section there has
/// radius `0.66 R`).
fn cut_flat<T: Voxel>(mask: &ArrayView3<'_, T>, centre: [f64; 3], u: [f64; 3], rho: f64, spacing: [f64; 3]) -> bool {
    let [a, b] = plane_basis(u);
    let held = (0..RING)
        .filter(|&k| {
            let (s, c) = (k as f64 * std::f64::consts::TAU / RING as f64).sin_cos();
            inside(mask, std::array::from_fn(|d| centre[d] + rho * (c * a[d] + s * b[d])), spacing)
        })
        .count();
    2 * held >= RING
}

/// Points of the ring of [`cut_flat`].
const RING: usize = 16;

/// Slack (base cells) of the cap test of [`cap_depth`]: the transform on a vessel's
/// axis reads up to 5 % under its radius (voxel centres to background centres) and
/// the line's exit is found to half a step.
const CAP_SLACK: f64 = 0.5;

/// Positions with every degree-1 node moved to its vessel's end (see the module), and
/// the radii the ends were placed by (the cap's where it is wider than the end's own).
pub fn extend_ends<T: Voxel>(
    g: &Csr,
    positions: &[[f64; 3]],
    radii: &[f64],
    mask: ArrayView3<'_, T>,
    field: &Field,
    spacing: [f64; 3],
) -> (Vec<[f64; 3]>, Vec<f64>) {
    let (n0, n1, n2) = mask.dim();
    let shape = [n0, n1, n2];
    move_ends(g, positions, radii, &mask, spacing, |i, p, u, r, c, room| {
        let h = c / STEPS_PER_CELL;
        let steps = ((3.0 * r + 4.0 * c) / h).ceil() as usize;
        let at = |t: f64| [p[0] + t * u[0], p[1] + t * u[1], p[2] + t * u[2]];
        let near = nearby_edges(g, positions, i, 2.0 * (3.0 * r + 4.0 * c));
        // A point of the line inside another edge's vessel, nearer that edge than the
        // end: the line runs into another vessel, or along the end's own parent (a spur
        // off a junction, pointing back along the vessel it leaves).
        let other = |t: f64| {
            let x = at(t);
            near.iter().any(|&(a, b)| {
                let reach = t.min(radii[a].max(radii[b])) - 0.5 * c;
                reach > 0.0 && projection(x, positions[a], positions[b]).1 < reach
            })
        };
        // The last inside sample; the boundary is half a step beyond it.
        let last = (1..=steps)
            .take_while(|&k| inside(&mask, at(k as f64 * h), spacing) && !other(k as f64 * h))
            .last()
            .unwrap_or(0);
        if last < steps && voxel_of(at((last + 1) as f64 * h), spacing, shape).is_none() {
            // The line leaves the array, not the vessel: the array's face cuts the
            // vessel, whose centreline runs on to the face. The end goes to the last
            // sample inside, kept within the voxel centres' box.
            let face = (0..3)
                .filter(|&d| u[d] != 0.0)
                .map(|d| if u[d] > 0.0 { ((shape[d] - 1) as f64 * spacing[d] - p[d]) / u[d] } else { -p[d] / u[d] })
                .fold(f64::INFINITY, f64::min);
            let t = (last as f64 * h).min(face);
            return (t > 0.0).then(|| (at(t), r));
        }
        let exit = (last as f64 + 0.5) * h;
        let blocked = last < steps && other((last + 1) as f64 * h);
        if blocked {
            let t = exit - r;
            return (t > 0.0).then(|| (at(t), r));
        }
        // One radius inside the exit; where the end's rounded cap is wider than the
        // end's own section (an end node inside its cap reads it narrower), one cap
        // radius, which may move the end back, short of its neighbour.
        let cap = cap_depth(field, at(exit), u, h, exit + room, c);
        if cap > r && !cut_flat(&mask, at(exit - 0.25 * cap), u, 0.8 * cap, spacing) {
            let t = (exit - cap).max(h - room);
            return Some((at(t), cap));
        }
        let t = exit - r;
        (t > 0.0).then(|| (at(t), r))
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
    move_ends(g, positions, radii, &mask, spacing, |_, p, u, r, c, _| {
        follow_mask(&mask, &edges, p, u, r, 3.0 * r + 4.0 * c, spacing).map(|q| (q, r))
    })
    .0
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    /// [`extend_ends`]'s positions at unit spacing.
    fn extend(g: &Csr, p: &[[f64; 3]], radii: &[f64], mask: &Array3<u8>) -> Vec<[f64; 3]> {
        let field = Field::new(mask.view(), [1.0; 3]).expect("a field");
        extend_ends(g, p, radii, mask.view(), &field, [1.0; 3]).0
    }

    /// A mask of the voxels `inside` selects, shape `shape`.
    fn drawn(shape: (usize, usize, usize), inside: impl Fn(f64, f64, f64) -> bool) -> Array3<u8> {
        Array3::from_shape_fn(shape, |(i, j, k)| u8::from(inside(i as f64, j as f64, k as f64)))
    }

    #[test]
    fn an_end_inside_a_wide_rounded_cap_moves_back_to_its_centre() {
        // A capsule of radius 6 about (6, 6, k), its axis from k = 10 to 40: the caps'
        // centres; a path ends at k = 43, inside the cap, where its section reads
        // narrower (radius 4). One such radius inside the tip (46) would keep it 3 voxels
        // past the cap's centre; the cap's inscribed ball puts it back there.
        let mask = drawn((13, 13, 52), |i, j, k| {
            let a = k.clamp(10.0, 40.0);
            (i - 6.0).powi(2) + (j - 6.0).powi(2) + (k - a).powi(2) <= 36.0
        });
        let g = Csr::from_sorted_edges(4, &[(0, 1), (1, 2), (2, 3)]);
        let p = [[6.0, 6.0, 25.0], [6.0, 6.0, 30.0], [6.0, 6.0, 35.0], [6.0, 6.0, 43.0]];
        let out = extend(&g, &p, &[6.0, 6.0, 6.0, 4.0], &mask);
        assert!((out[3][2] - 40.0).abs() <= 1.0, "{:?}", out[3]);
        // The other end, at the full radius, goes to one radius inside its tip (k = 4).
        assert!((out[0][2] - 10.0).abs() <= 1.0, "{:?}", out[0]);
    }

    #[test]
    fn an_end_of_a_vessel_cut_flat_keeps_its_own_radius() {
        // The same vessel cut flat at k = 40 inside the array (a segmentation's edge):
        // its section a quarter radius inside the cut is the vessel's. The end at k = 37
        // (radius 4) is already one radius inside the cut (40.5) and stays; taken for a
        // cap, it would go back to k = 34.5.
        let mask =
            drawn((13, 13, 52), |i, j, k| (10.0..=40.0).contains(&k) && (i - 6.0).powi(2) + (j - 6.0).powi(2) <= 36.0);
        let g = Csr::from_sorted_edges(4, &[(0, 1), (1, 2), (2, 3)]);
        let p = [[6.0, 6.0, 22.0], [6.0, 6.0, 27.0], [6.0, 6.0, 32.0], [6.0, 6.0, 37.0]];
        let out = extend(&g, &p, &[6.0, 6.0, 6.0, 4.0], &mask);
        assert_eq!(out[3], p[3]);
    }

    #[test]
    fn an_end_in_a_tapering_vessel_stays_one_radius_inside_its_tip() {
        // A cone along axis 2, radius 5 at k = 10 narrowing to its tip at k = 40; a path
        // ends at k = 28 (radius 3): its vessel has no rounded cap wider than it, and the
        // end goes to one radius inside the tip, as before there was a cap test.
        let mask = drawn((13, 13, 48), |i, j, k| {
            let r = 5.0 * (40.0 - k) / 30.0;
            (10.0..=40.0).contains(&k) && (i - 6.0).powi(2) + (j - 6.0).powi(2) <= r * r
        });
        let g = Csr::from_sorted_edges(3, &[(0, 1), (1, 2)]);
        let p = [[6.0, 6.0, 14.0], [6.0, 6.0, 20.0], [6.0, 6.0, 28.0]];
        let out = extend(&g, &p, &[5.0, 4.0, 3.0], &mask);
        let tip = (28..48).take_while(|&k| mask[[6, 6, k]] == 1).last().expect("inside") as f64 + 0.5;
        assert!((out[2][2] - (tip - 3.0)).abs() <= 0.25, "{:?} (tip {tip})", out[2]);
    }

    #[test]
    fn a_spur_pointing_back_along_its_parent_is_not_extended_along_it() {
        // A bar of radius 3 along axis 2 (k = 2 to 37), a path along its axis with a
        // one-edge spur from the junction at k = 20 back to (5, 4, 17), beside the path.
        // Its line runs along the parent, inside the vessel, for about 8 voxels: moved
        // one radius short of where it leaves the bar, the spur would grow 5 voxels
        // along the parent, long enough to outlive the pruning of short spurs.
        let mask =
            drawn((9, 9, 40), |i, j, k| (2.0..=37.0).contains(&k) && (i - 4.0).powi(2) + (j - 4.0).powi(2) <= 9.0);
        let g = Csr::from_sorted_edges(5, &[(0, 1), (1, 2), (2, 3), (2, 4)]);
        let p = [[4.0, 4.0, 5.0], [4.0, 4.0, 12.0], [4.0, 4.0, 20.0], [4.0, 4.0, 30.0], [5.0, 4.0, 17.0]];
        let out = extend(&g, &p, &[3.0; 5], &mask);
        assert_eq!(out[4], p[4]);
        // The path's own ends go to one radius inside the bar's ends (1.5 and 37.5).
        assert!((out[0][2] - 4.5).abs() <= 0.25 && (out[3][2] - 34.5).abs() <= 0.25, "{out:?}");
    }

    #[test]
    fn an_end_moves_to_one_radius_inside_the_mask() {
        // A 1-voxel-thick bar along axis 2 from k = 0 to 16; a path ending at k = 10.
        let mut mask = Array3::<u8>::zeros((3, 3, 30));
        for k in 0..=16 {
            mask[[1, 1, k]] = 1;
        }
        let g = Csr::from_sorted_edges(3, &[(0, 1), (1, 2)]);
        let p = [[1.0, 1.0, 2.0], [1.0, 1.0, 6.0], [1.0, 1.0, 10.0]];
        let out = extend(&g, &p, &[0.5, 0.5, 2.0], &mask);
        // Node 2: the mask ends at 16.5, minus its radius 2: 14.5 (to a quarter step).
        assert!((out[2][2] - 14.5).abs() <= 0.25, "{:?}", out[2]);
        assert_eq!(&out[2][..2], &[1.0, 1.0]);
        // Node 0 points the other way: the mask ends at -0.5, its radius 0.5 keeps it at 0.
        assert!((out[0][2] - 0.0).abs() <= 0.25, "{:?}", out[0]);
        // A middle node never moves.
        assert_eq!(out[1], p[1]);
        // An end whose radius reaches past the mask's end stays.
        let out = extend(&g, &p, &[0.5, 0.5, 7.0], &mask);
        assert_eq!(out[2], p[2]);
        // The search is capped at 3 r + 4 c: radius 1 moves node 2 by at most 7 - 1.
        let out = extend(&g, &p, &[0.5, 0.5, 1.0], &mask);
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
        let out = extend(&g, &p, &[3.0; 3], &mask);
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
        let straight = extend(&g, &p, &[1.0; 3], &mask);
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
