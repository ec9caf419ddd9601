//! Radii smoothed along the vessels (the output's last step, after the pruning;
//! `radius_smoothing`, not in the paper).
//!
//! Each node's radius is measured on the mask around it ([`crate::radius`]) from a few
//! voxels of cross-section, so it carries the voxel grid's noise: on clean synthetic
//! tubes a few per cent from node to node, more where bubble noise touches the wall.
//! Vessels change radius slowly along their length, so the radius of every node of a
//! branch (degree 1 or 2) becomes the median of the radii of the branch's nodes within
//! `w` of it along the branch (arc length; `w` is `radius_smoothing` base cells),
//! itself included. The walk stops at junctions: their radii (the inscribed radius at
//! the node) neither change nor enter a branch's median, so a thick parent and a thin
//! child never mix. A median keeps steps (a vessel that narrows at a branch point)
//! where a mean would blur them, and ignores a single node that a bubble or a touching
//! vessel widened; it removes narrowings and bulges shorter than about `w`.
//!
//! A vessel's end (degree 1) is left where the mask rounds the vessel off, often past the
//! cap's centre, and its section there is the cap's, narrower than the vessel (a capsule
//! of radius 5 read 1.87 at an end 3.6 voxels past its cap's centre, one of radius 3 read
//! 2.36). So ends enter no median, and an end's radius is the median of its window's
//! other nodes, or its neighbour's own radius when the window holds none and the
//! neighbour is on its branch (degree 2). An end next to a junction, or joined only to
//! another end, keeps its own.

use crate::graph::Skeleton;
use crate::vec3::{base_cell, norm, sub};
use rayon::prelude::*;

/// The median of `v` (the mean of the two middle values for an even count); `v` is
/// reordered. Not empty.
fn median(v: &mut [f64]) -> f64 {
    v.sort_unstable_by(f64::total_cmp);
    let m = v.len() / 2;
    if v.len() % 2 == 1 {
        v[m]
    } else {
        0.5 * (v[m - 1] + v[m])
    }
}

/// The radii of the graph of `n` nodes and `edges` smoothed along its branches over
/// `window` (physical units, see the module). `window <= 0` (or NaN) keeps them.
pub fn smooth_radii(n: usize, edges: &[[usize; 2]], positions: &[[f64; 3]], radii: &[f64], window: f64) -> Vec<f64> {
    if window.is_nan() || window <= 0.0 {
        return radii.to_vec();
    }
    let mut adjacency: Vec<Vec<usize>> = vec![Vec::new(); n];
    for &[a, b] in edges {
        adjacency[a].push(b);
        adjacency[b].push(a);
    }
    (0..n)
        .into_par_iter()
        .map(|i| {
            let degree = adjacency[i].len();
            if degree == 0 || degree > 2 {
                return radii[i];
            }
            // Both ways along the branch, through nodes of degree 1 or 2, each node at
            // most once: on a loop without junctions shorter than twice the window the
            // second walk stops where it meets the first one's far end.
            let mut seen = vec![i];
            let mut far = i;
            for &first in &adjacency[i] {
                let (mut prev, mut cur) = (i, first);
                let mut arc = norm(sub(positions[cur], positions[prev]));
                for _ in 0..n {
                    if arc > window || adjacency[cur].len() > 2 || cur == i || cur == far {
                        break;
                    }
                    seen.push(cur);
                    let Some(&next) = adjacency[cur].iter().find(|&&w| w != prev) else { break };
                    arc += norm(sub(positions[next], positions[cur]));
                    (prev, cur) = (cur, next);
                }
                far = seen[seen.len() - 1];
            }
            // A vessel's end measures the cap the mask rounds it off with, not the vessel:
            // ends stay out of every median, and an end takes its window's other nodes'
            // median, or its neighbour's radius when the window holds none.
            let end = |j: usize| adjacency[j].len() == 1;
            let mut values: Vec<f64> = seen.iter().filter(|&&j| !end(j)).map(|&j| radii[j]).collect();
            if values.is_empty() {
                return match adjacency[i][..] {
                    [j] if adjacency[j].len() == 2 => radii[j],
                    _ => radii[i],
                };
            }
            median(&mut values)
        })
        .collect()
}

/// `skeleton` with its radii smoothed along its branches over `cells` base cells
/// ([`smooth_radii`]).
pub fn smooth_skeleton(mut skeleton: Skeleton, cells: f64) -> Skeleton {
    let window = cells * base_cell(skeleton.spacing);
    skeleton.radii =
        smooth_radii(skeleton.positions.len(), &skeleton.edges, &skeleton.positions, &skeleton.radii, window);
    skeleton
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A path of nodes 1 apart along axis 0 with the given radii.
    fn path(radii: &[f64]) -> (Vec<[f64; 3]>, Vec<[usize; 2]>) {
        let p = (0..radii.len()).map(|i| [i as f64, 0.0, 0.0]).collect();
        let e = (1..radii.len()).map(|i| [i - 1, i]).collect();
        (p, e)
    }

    #[test]
    fn a_lone_outlier_goes_and_a_step_stays() {
        // One node widened by a bubble among radius-2 nodes: the median takes it back.
        let r = [2.0, 2.0, 2.0, 2.0, 3.5, 2.0, 2.0, 2.0, 2.0];
        let (p, e) = path(&r);
        let s = smooth_radii(9, &e, &p, &r, 2.0);
        assert_eq!(s, [2.0; 9]);
        // A step from 2 to 4 halfway: every node keeps its side's radius but the two
        // at the step, whose windows hold as many of each (the mean of the middle two).
        let r = [2.0, 2.0, 2.0, 2.0, 4.0, 4.0, 4.0, 4.0];
        let (p, e) = path(&r);
        let s = smooth_radii(8, &e, &p, &r, 1.0);
        assert_eq!(s, [2.0, 2.0, 2.0, 2.0, 4.0, 4.0, 4.0, 4.0]);
        // No window: unchanged.
        assert_eq!(smooth_radii(8, &e, &p, &r, 0.0), r);
    }

    #[test]
    fn junctions_keep_their_radius_and_stop_the_window() {
        // A star: junction 0 (radius 9) with a thick arm 1-2-3, a thin arm 4-5-6 and a
        // one-node arm 7.
        let p = vec![
            [0.0; 3],
            [1.0, 0.0, 0.0],
            [2.0, 0.0, 0.0],
            [3.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 2.0, 0.0],
            [0.0, 3.0, 0.0],
            [0.0, 0.0, 1.0],
        ];
        let r = [9.0, 3.0, 3.2, 3.1, 1.0, 1.2, 1.1, 5.0];
        let e = [[0, 1], [1, 2], [2, 3], [0, 4], [4, 5], [5, 6], [0, 7]];
        let s = smooth_radii(8, &e, &p, &r, 10.0);
        assert_eq!(s[0], 9.0);
        assert_eq!(&s[1..4], &[3.1; 3]);
        assert_eq!(&s[4..7], &[1.1; 3]);
        assert_eq!(s[7], 5.0);
    }

    #[test]
    fn a_loop_without_junctions_is_walked_once() {
        // A square ring of 4 nodes: every window covers the ring, each node once.
        let p = vec![[0.0; 3], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]];
        let r = [1.0, 2.0, 3.0, 10.0];
        let e = [[0, 1], [1, 2], [2, 3], [0, 3]];
        assert_eq!(smooth_radii(4, &e, &p, &r, 100.0), [2.5; 4]);
    }

    #[test]
    fn an_end_takes_its_vessels_radius_not_its_caps() {
        // A radius-5 vessel whose two ends sit in its caps and read narrow: 2.0 near the
        // next node, 1.9 seven units past it (beyond the window of 4).
        let p = vec![[0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0], [4.0, 0.0, 0.0], [11.0, 0.0, 0.0]];
        let r = [2.0, 5.0, 5.2, 4.9, 5.1, 1.9];
        let e = [[0, 1], [1, 2], [2, 3], [3, 4], [4, 5]];
        let s = smooth_radii(6, &e, &p, &r, 4.0);
        // The first end: the median of the others in its window (5.0, 5.2, 4.9, 5.1).
        assert_eq!(s[0], 5.05);
        // The far end: its window holds only itself, so its neighbour's own radius.
        assert_eq!(s[5], 5.1);
        // The narrow ends enter no median: node 1's window (nodes 0 to 4) gives 5.05, not 5.0.
        assert_eq!(s[1], 5.05);
        // An end next to a junction keeps its own radius, and so does a lone edge's.
        let p = vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [5.0, 5.0, 5.0], [6.0, 5.0, 5.0]];
        let r = [6.0, 1.0, 2.0, 3.0, 0.5, 0.7];
        let e = [[0, 1], [0, 2], [0, 3], [4, 5]];
        assert_eq!(smooth_radii(6, &e, &p, &r, 4.0), r);
    }
}
