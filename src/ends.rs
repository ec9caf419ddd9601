//! Vessel ends (output stage, with `anchor_ends`; not in the paper).
//!
//! Laplacian flow shortens every free end: before an end becomes a degree-1 node
//! (and is anchored), the rounded cap of its vessel contracts inward. Where a vessel
//! ends in a rounded cap, its centreline ends at the centre of the cap's ball, one
//! radius inside the mask. So each degree-1 node is moved outward, along the
//! direction of the last stretch of its branch, to one radius (its output radius)
//! inside the point where that line leaves the mask; a node already that far out
//! stays. The search along the line is capped at `3 r + 4 c`.

use crate::grid::Csr;
use crate::inside::voxel_of;
use crate::volume::Voxel;
use ndarray::ArrayView3;
use rayon::prelude::*;

/// Steps along the line per base cell.
const STEPS_PER_CELL: f64 = 4.0;

fn inside<T: Voxel>(mask: &ArrayView3<'_, T>, p: [f64; 3], spacing: [f64; 3]) -> bool {
    let (n0, n1, n2) = mask.dim();
    voxel_of(p, spacing, [n0, n1, n2]).is_some_and(|v| mask[v].is_set())
}

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
    let (p, q) = (positions[i], positions[cur]);
    let d = [p[0] - q[0], p[1] - q[1], p[2] - q[2]];
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    (n > 0.0).then(|| [d[0] / n, d[1] / n, d[2] / n])
}

fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Positions with every degree-1 node moved to its vessel's end (see the module).
pub fn extend_ends<T: Voxel>(
    g: &Csr,
    positions: &[[f64; 3]],
    radii: &[f64],
    mask: ArrayView3<'_, T>,
    spacing: [f64; 3],
) -> Vec<[f64; 3]> {
    let c = spacing.iter().cloned().fold(f64::INFINITY, f64::min);
    let h = c / STEPS_PER_CELL;
    (0..g.nodes())
        .into_par_iter()
        .map(|i| {
            let p = positions[i];
            if g.neighbours(i).len() != 1 || !inside(&mask, p, spacing) {
                return p;
            }
            let r = radii[i];
            let Some(u) = direction(g, positions, i, (2.0 * r).max(2.0 * c)) else { return p };
            let steps = ((3.0 * r + 4.0 * c) / h).ceil() as usize;
            let at = |t: f64| [p[0] + t * u[0], p[1] + t * u[1], p[2] + t * u[2]];
            // The last inside sample; the boundary is half a step beyond it.
            let last = (1..=steps).take_while(|&k| inside(&mask, at(k as f64 * h), spacing)).last().unwrap_or(0);
            let t = (last as f64 + 0.5) * h - r;
            if t > 0.0 {
                at(t)
            } else {
                p
            }
        })
        .collect()
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
}
