//! Medial positions (after refinement, with `medial`; not in the paper; see docs/method.md).
//!
//! Contraction and mean-position decimation leave each node at the local centre of
//! mass of the mask, not on its medial axis (the ridge of the distance transform):
//! pulled toward bubbles of segmentation noise, inside the bend of curved vessels,
//! into the thicker vessel at a junction. This stage moves every node to the ridge:
//!
//! - a node of degree 1 or 2 moves within the plane through it orthogonal to its
//!   branch (the line between its two neighbours, or from its one neighbour), to the
//!   maximum of the distance transform in that cross-section;
//! - then a junction (degree ≥ 3) moves to where its branches' centrelines meet, each
//!   branch the least-squares line through its nodes within [`REACH`] radii, from the
//!   first one on, weighted toward the junction (nodes already moved to the ridge; a
//!   line through the stretch beyond the junction's own ball, as before, points where a
//!   curving branch goes, not where it leaves: 32 % of the tuning forests' true
//!   junctions had no graph junction within σ = 2 voxels with it, 26 % then, thinning
//!   19 %): when two branches run nearly straight through
//!   ([`STRAIGHT`]) they are the parent vessel, one line, and the junction is the point
//!   on the parent's axis nearest (least squares) to the other branches' lines (a thin
//!   child's line from its first node outside the parent's tube, [`THIN_CHILD`]);
//!   otherwise (a fork) the point nearest to every branch's line. It moves at most
//!   [`JUNCTION_CAP`] radii (on a parent, of the parent's radius over the sine of the
//!   child's angle when that is larger). The ridge alone would not do: where a thin vessel leaves a
//!   thick one the transform is largest on the thick one's axis, so its maximum (or
//!   plateau) pulls the junction into the parent; and a point fitted to all lines
//!   alike lands up the child where it leaves at an acute angle;
//! - last, a path node that its junction has moved past (its two neighbours, the
//!   junction and the next node, on the same side of it: the branch folds back) goes
//!   to the midpoint of those two (not capped). A fold lengthens every path through the junction by
//!   up to twice the overshoot, which DIADEM's path-length test punishes near a tree's
//!   root (VascuSynth seed2_n250_100: 9.7 → 26.0 %);
//! - isolated nodes stay.
//!
//! The distance transform is the exact one of [`crate::volume`] at voxel centres
//! (distance to the nearest background voxel centre), interpolated trilinearly, with
//! 0 on background. The search samples the disc of radius [`CAP`] times the node's
//! radius (at least [`MIN_CAP`] base cells) on a grid of [`STEP`] base cells (or a
//! multiple, at most [`SAMPLES`] steps from centre to rim), climbs from the node's own sample to the
//! first local maximum by steepest ascent
//! (so a node never crosses a saddle of the distance transform into a neighbouring
//! vessel: two touching vessels keep their own lines), and lands on the weighted
//! centroid of the connected samples within [`PLATEAU`] base cells of that maximum
//! (the discrete transform has flat ridges one or two voxels wide, whose middle is
//! the axis). A move whose target lies on a background voxel is not made.
//!
//! Within a pass ([`recentre`]) every curve node moves from the positions the nodes had
//! before it, every junction from those and the curve nodes' new positions, and the
//! unfolding from all of those (three steps, each in parallel over the nodes), so the
//! result does not depend on the thread count. The stage ([`settle`]) runs [`PASSES`]
//! passes, each from the positions the last one left: a pass moves a node at most its
//! cap, and the flow leaves some nodes further off the ridge than that (a node on the
//! slope of a thick vessel whose cluster's radius is small, a line beside a noise
//! bubble); the next pass also takes each node's plane and each junction's branch lines
//! from nodes already moved (a vessel's end moves in the first pass only, see
//! [`PASSES`]). The
//! transform is the run's first stage's, kept at the foreground voxels (4 bytes per
//! vessel voxel, [`Field::from_squared`]), not computed again.

use crate::error::Result;
use crate::grid::Csr;
use crate::inside::voxel_of;
use crate::vec3::{base_cell, cross, dot, norm, sub, unit};
use crate::volume::{edt_squared_rows, foreground_rows, Voxel};
use ndarray::{ArrayView3, Axis};
use rayon::prelude::*;

/// Largest move, as a fraction of the node's radius.
pub const CAP: f64 = 0.6;

/// Largest move of a junction, as a fraction of its radius (on its parent's axis or
/// not: a cap of [`CAP`] for forks alone was worse on the tuning set): where a thin vessel
/// leaves at an acute angle the junction sits up to a parent's radius or more off
/// the meeting point (chosen on the tuning set: 0.6 and 2.0 were worse). On a parent
/// the radius is the larger of the junction's and the parent's over the sine of the
/// most acute child's angle (at most doubled): the contraction can leave the junction
/// anywhere in the parent's tube, and up a child leaving at θ by the parent's radius
/// over sin θ (a coarse start's junction sits on the child, whose radius held it back).
pub const JUNCTION_CAP: f64 = 1.2;

/// A child branch of a junction on a parent vessel is thin when its nodes' mean radius
/// is at most this fraction of the parent's: its nodes inside the parent's tube sit on
/// the parent's slope of the distance transform, not on its own axis, and its line runs
/// from the first node outside (a radius-2 child leaving a radius-5 parent at 45°: the
/// junction 2.1 voxels from where the centrelines meet with a coarse start, 0.4 so).
pub const THIN_CHILD: f64 = 0.5;

/// Two branches of a junction whose outward directions have a dot product below
/// `-STRAIGHT` (within about 26° of opposite) are a parent vessel running through it
/// (chosen on the tuning set: 0.7 was worse).
pub const STRAIGHT: f64 = 0.9;

/// Smallest search radius, in base cells (`c = min(spacing)`): the reach of the nodes
/// of vessels thinner than `MIN_CAP / CAP` (3.3 base cells), which a noise bubble
/// beside them pulls off their axis by more than their own radius. Chosen on the tuning
/// set (forests D0 / D1 / D2 GFNR 0.031 / 0.046 / 0.073 at 1 → 0.026 / 0.041 / 0.066 at
/// 2, lattice 0.017 → 0.011; 1.5 gained half as much; 2.5 and 3 no more on the forests
/// and a higher CFNR; the CCO trees' GFNR rose by 0.001–0.002 from 1.5 on).
pub const MIN_CAP: f64 = 2.0;

/// Finest sampling step of the search, in base cells.
pub const STEP: f64 = 0.25;

/// Most samples of the search from its centre to its rim (coarser steps than
/// [`STEP`] for large radii).
pub const SAMPLES: f64 = 8.0;

/// A junction's branch line is fitted to the branch's nodes within `REACH` radii of
/// the junction (its radius, at least one base cell), from the first one on: chosen
/// on the tuning set (forests D0–D2, junctions met 67.5 → 73.5 %; starting at 0.25,
/// 0.5 or 1 radius, or reaching 2.5 or 3.5 radii, was no better or worse).
pub const REACH: f64 = 3.0;

/// Samples within this many base cells of the local maximum count as its plateau.
pub const PLATEAU: f64 = 0.25;

/// Passes of the stage ([`settle`]): each moves a node at most its cap, from where the
/// last pass left it and its neighbours (so its plane, and a junction's branch lines,
/// are those of the moved nodes). One pass left nodes that the flow had put more than a
/// cap off the ridge (on the slope of a thick vessel, beside a noise bubble) still off
/// it. Chosen on the tuning set (README, "Where we differ", 11: 1, 2, 3 and 5 passes).
/// A vessel's end moves in the first pass only: within a radius of an end cap, or of
/// the array's face, the transform falls toward the cap, so an end's plane, refitted
/// to its moved neighbour, tilted further at every pass and the end slid along it (a
/// flat branch ending at the array's face became a fork after three passes).
pub const PASSES: usize = 3;

/// The distance transform of a mask at its foreground voxels, with random access.
pub struct Field {
    shape: [usize; 3],
    spacing: [f64; 3],
    /// Foreground voxels of row `(i, j)` are entries `starts[i * n1 + j]..starts[.. + 1]`.
    starts: Vec<usize>,
    /// Axis-2 index of every foreground voxel, ascending within each row.
    ks: Vec<u32>,
    /// Distance to the nearest background voxel centre, in base cells (`c =
    /// min(spacing)`), so that scaling the spacing scales nothing but the positions.
    dist: Vec<f32>,
}

impl Field {
    /// The transform of `mask` with voxel `spacing` (rows in parallel).
    pub fn new<T: Voxel>(mask: ArrayView3<'_, T>, spacing: [f64; 3]) -> Result<Field> {
        let starts = foreground_rows(mask)?;
        let squared = edt_squared_rows(mask, &starts, spacing)?;
        Field::from_squared(mask, spacing, starts, squared)
    }

    /// The transform of `mask` from its [`foreground_rows`] and its [`edt_squared_rows`]
    /// with the same `spacing` (physical units²), which a run has from its first stage:
    /// the transform is not computed twice.
    pub fn from_squared<T: Voxel>(
        mask: ArrayView3<'_, T>,
        spacing: [f64; 3],
        starts: Vec<usize>,
        squared: Vec<f32>,
    ) -> Result<Field> {
        let (n0, n1, n2) = mask.dim();
        assert_eq!(starts.len(), n0 * n1 + 1, "foreground rows of another mask");
        assert_eq!(squared.len(), starts[n0 * n1], "a transform of another mask");
        let c2 = base_cell(spacing).powi(2);
        let mut dist = squared;
        dist.par_iter_mut().for_each(|d| *d = (f64::from(*d) / c2).sqrt() as f32);
        let mut ks = crate::memory::try_filled(starts[n0 * n1], 0u32)?;
        let mut rest = ks.as_mut_slice();
        let mut parts = Vec::with_capacity(n0 * n1);
        for w in starts.windows(2) {
            let (head, tail) = std::mem::take(&mut rest).split_at_mut(w[1] - w[0]);
            parts.push(head);
            rest = tail;
        }
        parts.into_par_iter().enumerate().for_each(|(r, part)| {
            let row = mask.index_axis(Axis(0), r / n1);
            let row = row.index_axis(Axis(0), r % n1);
            for (slot, (k, _)) in part.iter_mut().zip(row.iter().enumerate().filter(|(_, v)| v.is_set())) {
                *slot = k as u32;
            }
        });
        Ok(Field { shape: [n0, n1, n2], spacing, starts, ks, dist })
    }

    /// The array's shape.
    pub fn shape(&self) -> [usize; 3] {
        self.shape
    }

    /// The number of foreground voxels: the range of [`Field::index`].
    pub fn count(&self) -> usize {
        self.dist.len()
    }

    /// The index of voxel `v` among the foreground voxels (in row order), `None` on
    /// background.
    pub fn index(&self, v: [usize; 3]) -> Option<usize> {
        let r = v[0] * self.shape[1] + v[1];
        let (a, b) = (self.starts[r], self.starts[r + 1]);
        self.ks[a..b].binary_search(&(v[2] as u32)).ok().map(|t| a + t)
    }

    /// The row (`i0 * n1 + i1`) of foreground index `i`.
    pub fn row(&self, i: usize) -> usize {
        self.starts.partition_point(|&s| s <= i) - 1
    }

    /// The voxel of foreground index `i`.
    pub fn voxel(&self, i: usize) -> [usize; 3] {
        let r = self.row(i);
        [r / self.shape[1], r % self.shape[1], self.ks[i] as usize]
    }

    /// The transform at foreground index `i`, in base cells.
    pub fn dist_at(&self, i: usize) -> f64 {
        self.dist[i] as f64
    }

    /// Calls `f(o, j, row)` for every foreground 26-neighbour `j` (in `row`, see
    /// [`Field::row`]) of foreground index `i` in `row`, in index order; `o` is the
    /// offset's number `9 (d0 + 1) + 3 (d1 + 1) + d2 + 1`.
    pub fn for_neighbours(&self, i: usize, row: usize, mut f: impl FnMut(usize, usize, usize)) {
        let (r0, r1) = (row / self.shape[1], row % self.shape[1]);
        let k = self.ks[i];
        for d0 in 0..3 {
            for d1 in 0..3 {
                let (a0, a1) = ((r0 + d0).wrapping_sub(1), (r1 + d1).wrapping_sub(1));
                if a0 >= self.shape[0] || a1 >= self.shape[1] {
                    continue;
                }
                let r = a0 * self.shape[1] + a1;
                let (a, b) = (self.starts[r], self.starts[r + 1]);
                let ks = &self.ks[a..b];
                let from = ks.partition_point(|&x| x + 1 < k);
                for (t, &x) in ks[from..].iter().enumerate().take_while(|(_, &x)| x <= k + 1) {
                    let o = 9 * d0 + 3 * d1 + (x + 1 - k) as usize;
                    if o != 13 {
                        f(o, a + from + t, r);
                    }
                }
            }
        }
    }

    /// The transform at voxel `v`, in base cells (0 on background and outside the array).
    pub fn at(&self, v: [isize; 3]) -> f64 {
        if (0..3).any(|d| v[d] < 0 || v[d] >= self.shape[d] as isize) {
            return 0.0;
        }
        let r = v[0] as usize * self.shape[1] + v[1] as usize;
        let (a, b) = (self.starts[r], self.starts[r + 1]);
        match self.ks[a..b].binary_search(&(v[2] as u32)) {
            Ok(t) => self.dist[a + t] as f64,
            Err(_) => 0.0,
        }
    }

    /// The transform interpolated trilinearly at `p` (physical units), in base cells.
    pub fn interpolate(&self, p: [f64; 3]) -> f64 {
        let x: [f64; 3] = std::array::from_fn(|d| p[d] / self.spacing[d]);
        let lo: [f64; 3] = std::array::from_fn(|d| x[d].floor());
        let f: [f64; 3] = std::array::from_fn(|d| x[d] - lo[d]);
        let base: [isize; 3] = std::array::from_fn(|d| lo[d] as isize);
        let mut sum = 0.0;
        for corner in 0..8 {
            let bit = |d: usize| (corner >> (2 - d)) & 1;
            let w: f64 = (0..3).map(|d| if bit(d) == 1 { f[d] } else { 1.0 - f[d] }).product();
            if w > 0.0 {
                sum += w * self.at(std::array::from_fn(|d| base[d] + bit(d) as isize));
            }
        }
        sum
    }

    /// The transform interpolated at `p`, in physical units: the first-guess radius of a
    /// node placed where no cluster of voxels gives it one (edges split after a coarse
    /// start, [`crate::resample::ridge_radii`]; routed edges, [`crate::edges_inside`]).
    pub fn radius_at(&self, p: [f64; 3]) -> f64 {
        let c = base_cell(self.spacing);
        self.interpolate(p) * c
    }

    /// True if `p` lies on a foreground voxel.
    fn inside(&self, p: [f64; 3]) -> bool {
        voxel_of(p, self.spacing, self.shape).is_some_and(|v| self.at(v.map(|x| x as isize)) > 0.0)
    }
}

/// Two unit vectors orthogonal to the unit vector `t` and to each other.
pub(crate) fn plane_basis(t: [f64; 3]) -> [[f64; 3]; 2] {
    // The axis least aligned with `t` (first on ties) keeps the cross product large.
    let a = (0..3).fold(0, |best, d| if t[d].abs() < t[best].abs() { d } else { best });
    let mut e = [0.0; 3];
    e[a] = 1.0;
    let u = cross(t, e);
    let u = u.map(|x| x / norm(u));
    [u, cross(t, u)]
}

/// The local maximum of `field` reached from `p` over the samples `p + h (k_0 b_0 +
/// k_1 b_1)` (`b` two orthonormal directions, `h` the step) within `radius` of `p`,
/// placed at the weighted centroid of its plateau; `None` when `p` is already there
/// (to the sample grid) or the target is on background.
pub(crate) fn climb(field: &Field, p: [f64; 3], basis: [[f64; 3]; 2], radius: f64, c: f64) -> Option<[f64; 3]> {
    // The step (a multiple of STEP base cells) and the samples' reach in steps
    // depend on the radius only through integers, so that a radius rounded a hair
    // differently (another spacing scale) gives the same sample grid.
    let r = radius / c;
    let h = STEP * (r / (STEP * SAMPLES) - 1e-6).ceil().max(1.0);
    let m = (r / h + 1e-6).floor() as isize;
    if m < 1 {
        return None;
    }
    let h = h * c;
    let side = (2 * m + 1) as usize;
    let count = side * side;
    let offset = |idx: usize| [(idx / side) as isize - m, (idx % side) as isize - m];
    let index = |k: [isize; 2]| (k[0] + m) as usize * side + (k[1] + m) as usize;
    let point = |k: [isize; 2]| -> [f64; 3] {
        std::array::from_fn(|d| p[d] + (0..2).map(|a| k[a] as f64 * h * basis[a][d]).sum::<f64>())
    };
    let within = |k: [isize; 2]| k[0] * k[0] + k[1] * k[1] <= m * m;
    // The transform at the samples of the disc (NaN outside it), each read the first
    // time the search needs it: the ascent and the plateau read a few dozen of the up
    // to 289 samples, and the same values whichever they read.
    let mut values = vec![f64::NAN; count];
    let mut read = vec![false; count];
    let mut value = |k: [isize; 2]| -> f64 {
        let i = index(k);
        if !read[i] {
            read[i] = true;
            if within(k) {
                values[i] = field.interpolate(point(k));
            }
        }
        values[i]
    };
    let neighbours = |k: [isize; 2]| {
        (0..9).filter_map(move |n| {
            let mut q = k;
            let mut rest = n;
            for x in q.iter_mut() {
                *x += (rest % 3) as isize - 1;
                rest /= 3;
            }
            (q != k && q.iter().all(|&x| x.abs() <= m)).then_some(q)
        })
    };
    // Steepest ascent from the node's own sample (the first neighbour on ties).
    let mut at = [0isize; 2];
    loop {
        let mut best = (value(at), at);
        for q in neighbours(at) {
            let v = value(q);
            if v > best.0 {
                best = (v, q);
            }
        }
        if best.1 == at {
            break;
        }
        at = best.1;
    }
    let peak = value(at);
    if peak.is_nan() || peak <= 0.0 {
        return None;
    }
    // The plateau: samples within PLATEAU of the peak connected to it.
    let floor = peak - PLATEAU;
    let mut member = vec![false; count];
    member[index(at)] = true;
    let mut stack = vec![at];
    while let Some(k) = stack.pop() {
        for q in neighbours(k) {
            let i = index(q);
            if !member[i] && value(q) >= floor {
                member[i] = true;
                stack.push(q);
            }
        }
    }
    // Sums in index order, whatever order the plateau was found in.
    let (mut w, mut sum) = (0.0, [0.0; 2]);
    for i in (0..count).filter(|&i| member[i]) {
        let wi = values[i] - floor;
        w += wi;
        for (s, k) in sum.iter_mut().zip(offset(i)) {
            *s += wi * k as f64;
        }
    }
    if sum.iter().all(|&s| s == 0.0) {
        return None;
    }
    let target: [f64; 3] = std::array::from_fn(|d| p[d] + (0..2).map(|a| sum[a] / w * h * basis[a][d]).sum::<f64>());
    field.inside(target).then_some(target)
}

/// Positions after [`PASSES`] passes of [`recentre`], each from the positions the last
/// one left, a vessel's end (a node of degree 1) moving in the first pass only (fewer
/// passes when one moves no node: the next would move none either). The stage of the
/// pipeline (see the module).
pub fn settle(g: &Csr, positions: &[[f64; 3]], radii: &[f64], field: &Field) -> Vec<[f64; 3]> {
    let mut at = positions.to_vec();
    for k in 0..PASSES {
        let next = pass(g, &at, radii, field, k == 0);
        if next == at {
            break;
        }
        at = next;
    }
    at
}

/// Positions with every node moved once toward the medial axis (one pass of the stage,
/// see the module). `radii` are the nodes' radii (physical units), which bound their
/// moves; `field` is the distance transform of the mask ([`Field::new`]).
pub fn recentre(g: &Csr, positions: &[[f64; 3]], radii: &[f64], field: &Field) -> Vec<[f64; 3]> {
    pass(g, positions, radii, field, true)
}

/// [`recentre`], the ends moving only with `ends`.
fn pass(g: &Csr, positions: &[[f64; 3]], radii: &[f64], field: &Field, ends: bool) -> Vec<[f64; 3]> {
    let c = base_cell(field.spacing);
    let reach = |i: usize| (CAP * radii[i]).max(MIN_CAP * c);
    let curves: Vec<[f64; 3]> = (0..g.nodes())
        .into_par_iter()
        .map(|i| {
            let p = positions[i];
            let nb = g.neighbours(i);
            let t = match nb.len() {
                1 if ends => sub(positions[nb[0] as usize], p),
                2 => sub(positions[nb[1] as usize], positions[nb[0] as usize]),
                _ => return p,
            };
            let n = norm(t);
            (n > 0.0).then(|| climb(field, p, plane_basis(t.map(|x| x / n)), reach(i), c)).flatten().unwrap_or(p)
        })
        .collect();
    let moved: Vec<[f64; 3]> = (0..g.nodes())
        .into_par_iter()
        .map(|i| {
            if g.neighbours(i).len() < 3 {
                return curves[i];
            }
            let p = positions[i];
            let m = meeting_point(g, &curves, radii, radii[i].max(c), i, p);
            let Some((m, wall)) = m else { return p };
            let d = sub(m, p);
            let (n, cap) = (norm(d), (JUNCTION_CAP * radii[i].max(wall)).max(MIN_CAP * c));
            let target = if n > cap { std::array::from_fn(|k| p[k] + d[k] * cap / n) } else { m };
            if field.inside(target) {
                target
            } else {
                p
            }
        })
        .collect();
    unfold(g, &moved, field)
}

/// `moved` with every path node a junction has moved past put back between its two
/// neighbours (see the module): a degree-2 node `q` next to a junction `a`, with its
/// other neighbour `b` on the same side of `q` as `a` (the branch folds back at `q`),
/// moves to the midpoint of `a` and `b` (if that is on the mask). It is not capped like
/// the other moves: a fold is undone wherever it is (capped at [`CAP`] radii, the
/// DIADEM gain on the VascuSynth trees falls from 145 → 176 to 145 → 158, summed).
fn unfold(g: &Csr, moved: &[[f64; 3]], field: &Field) -> Vec<[f64; 3]> {
    (0..g.nodes())
        .into_par_iter()
        .map(|i| {
            let (nb, q) = (g.neighbours(i), moved[i]);
            if nb.len() != 2 {
                return q;
            }
            for (a, b) in [(nb[0] as usize, nb[1] as usize), (nb[1] as usize, nb[0] as usize)] {
                if g.neighbours(a).len() >= 3 && dot(sub(moved[a], q), sub(moved[b], q)) > 0.0 {
                    let mid = std::array::from_fn(|k| 0.5 * (moved[a][k] + moved[b][k]));
                    return if field.inside(mid) { mid } else { q };
                }
            }
            q
        })
        .collect()
}

/// A junction's branch: a point of its line, its outward unit direction, its stretch
/// (node indices).
type Branch = ([f64; 3], [f64; 3], Vec<usize>);

/// Where junction `j`'s branches meet, and the radius that bounds the move there (0 for
/// a fork: the junction's own). `r` is the junction's radius, raised to its neighbours'
/// largest (a junction left on a thin child would otherwise see only a stub of its
/// parent). Each branch's line is fitted to its nodes (at `curves`) within `REACH r` of
/// `p`, from the first one on, walked along nodes of degree 2 ([`fitted_line`] for three
/// or more; through two; from `p` through the first node alone). When two
/// branches are nearly opposite ([`STRAIGHT`]) they are the parent vessel running
/// through: one line through both stretches (its direction from the far end of one
/// to the far end of the other), and the junction is the point on it nearest, in
/// least squares, to the other branches' lines (a [`THIN_CHILD`]'s from its first node
/// outside the parent's tube). Otherwise (a fork with no straight
/// parent) the point nearest, in least squares, to every branch's line. `None` when
/// the lines are (nearly) parallel.
fn meeting_point(
    g: &Csr,
    curves: &[[f64; 3]],
    radii: &[f64],
    r: f64,
    j: usize,
    p: [f64; 3],
) -> Option<([f64; 3], f64)> {
    let mut lines: Vec<Branch> = vec![];
    let r = g.neighbours(j).iter().fold(r, |m, &k| m.max(radii[k as usize]));
    for &first in g.neighbours(j) {
        let (mut prev, mut cur) = (j, first as usize);
        let mut stretch: Vec<usize> = vec![];
        // Each step moves one node along the branch: capped by the node count.
        for _ in 0..g.nodes() {
            let q = curves[cur];
            let d = norm(sub(q, p));
            if d > REACH * r {
                break;
            }
            stretch.push(cur);
            let nb = g.neighbours(cur);
            if nb.len() != 2 {
                break;
            }
            let next = if nb[0] as usize == prev { nb[1] } else { nb[0] } as usize;
            (prev, cur) = (cur, next);
        }
        let line = match stretch[..] {
            [_, _, _, ..] => fitted_line(curves, &stretch),
            [a, b] => two_point_line(curves[a], curves[b]),
            _ => two_point_line(p, curves[first as usize]),
        };
        if let Some((from, t)) = line {
            lines.push((from, t, stretch));
        }
    }
    // The parent: the most nearly opposite pair, the first on ties.
    let mut parent = None;
    let mut best = -STRAIGHT;
    for x in 0..lines.len() {
        for y in x + 1..lines.len() {
            let cos = dot(lines[x].1, lines[y].1);
            if cos < best {
                (best, parent) = (cos, Some((x, y)));
            }
        }
    }
    let on_parent = parent.and_then(|(x, y)| {
        let (sx, sy) = (&lines[x].2, &lines[y].2);
        let ends = |s: &[usize]| s.last().map_or(p, |&i| curves[i]);
        let t = sub(ends(sy), ends(sx));
        let n = norm(t);
        if n == 0.0 {
            return None;
        }
        let t = t.map(|v| v / n);
        // Not empty: with both stretches empty `t` above is 0.
        let on_line: Vec<usize> = sx.iter().chain(sy).copied().collect();
        let count = on_line.len() as f64;
        let centre: [f64; 3] = std::array::from_fn(|d| on_line.iter().map(|&i| curves[i][d]).sum::<f64>() / count);
        let wall = on_line.iter().map(|&i| radii[i]).sum::<f64>() / count;
        // A child's nodes inside the parent's tube sit on the parent's slope, not on
        // the child's axis: its line runs from the first node outside (when two are).
        let outside = |i: &usize| {
            let e = sub(curves[*i], centre);
            let along = dot(e, t);
            dot(e, e) - along * along >= wall * wall
        };
        // x = centre + s t minimising Σ |(I - u uᵀ)(x - from)|² over the other lines.
        let (mut num, mut den, mut sin) = (0.0, 0.0, 1.0f64);
        for (k, (from, u, stretch)) in lines.iter().enumerate() {
            if k != x && k != y {
                // Only a thin child's nodes are trimmed: one as thick as its parent
                // shares the tube it leaves by, and its first nodes show where it turns.
                let thin = stretch.iter().map(|&i| radii[i]).sum::<f64>() <= THIN_CHILD * wall * stretch.len() as f64;
                let beyond: Vec<usize> =
                    if thin { stretch.iter().skip_while(|i| !outside(i)).copied().collect() } else { vec![] };
                let (from, u) = match beyond[..] {
                    [a, .., b] if norm(sub(curves[b], curves[a])) > 0.0 => {
                        let d = sub(curves[b], curves[a]);
                        (curves[a], d.map(|v| v / norm(d)))
                    }
                    _ => (*from, *u),
                };
                let (tu, e) = (dot(t, u), sub(from, centre));
                num += dot(t, e) - tu * dot(u, e);
                den += 1.0 - tu * tu;
                sin = sin.min((1.0 - tu * tu).max(0.0).sqrt());
            }
        }
        // Children (nearly) along the parent meet it nowhere in particular.
        (den > 1e-6).then(|| (std::array::from_fn(|d| centre[d] + num / den * t[d]), wall / sin.max(0.5)))
    });
    if on_parent.is_some() {
        return on_parent;
    }
    let (mut a, mut b) = ([[0.0; 3]; 3], [0.0; 3]);
    for (from, t, _) in &lines {
        // Projector onto the plane orthogonal to the line: I - t tᵀ.
        for (row, (ar, br)) in a.iter_mut().zip(b.iter_mut()).enumerate() {
            for (col, x) in ar.iter_mut().enumerate() {
                let proj = f64::from(u8::from(row == col)) - t[row] * t[col];
                *x += proj;
                *br += proj * from[col];
            }
        }
    }
    solve3(a, b).map(|m| (m, 0.0))
}

/// The line from `a` through `b`: `a` and the unit direction; `None` when they coincide.
fn two_point_line(a: [f64; 3], b: [f64; 3]) -> Option<([f64; 3], [f64; 3])> {
    unit(sub(b, a)).map(|t| (a, t))
}

/// The weighted least-squares line through the nodes `stretch` (at `curves`, three or
/// more, from the junction out): their weighted mean and principal axis, oriented from
/// the first node toward the last. The `k`-th of `n` nodes weighs `n - k`, so the nodes
/// where the branch leaves count most (a curving branch's line then still meets the
/// others where it leaves) while every node damps the jitter of the positions, which a
/// line through two nodes takes whole. The axis is found by power iteration on the
/// weighted scatter matrix from the first-to-last direction, which is close to it on a
/// branch (a fixed number of steps).
fn fitted_line(curves: &[[f64; 3]], stretch: &[usize]) -> Option<([f64; 3], [f64; 3])> {
    let (_, start) = two_point_line(curves[stretch[0]], curves[stretch[stretch.len() - 1]])?;
    let n = stretch.len();
    let weight = |k: usize| (n - k) as f64;
    let total: f64 = (0..n).map(weight).sum();
    let centre: [f64; 3] = std::array::from_fn(|d| {
        stretch.iter().enumerate().map(|(k, &i)| weight(k) * curves[i][d]).sum::<f64>() / total
    });
    let mut scatter = [[0.0; 3]; 3];
    for (k, &i) in stretch.iter().enumerate() {
        let e = sub(curves[i], centre);
        for (row, s) in scatter.iter_mut().enumerate() {
            for (col, x) in s.iter_mut().enumerate() {
                *x += weight(k) * e[row] * e[col];
            }
        }
    }
    let mut t = start;
    for _ in 0..AXIS_ITERATIONS {
        let Some(next) = unit(std::array::from_fn(|row| dot(scatter[row], t))) else {
            return Some((centre, start));
        };
        t = next;
    }
    let t = if dot(t, start) < 0.0 { t.map(|x| -x) } else { t };
    Some((centre, t))
}

/// Power-iteration steps of [`fitted_line`].
const AXIS_ITERATIONS: usize = 16;

/// The solution of the symmetric 3 × 3 system `a x = b` by Cramer's rule; `None` when
/// `a` is nearly singular (its determinant below 1e-6 of the product of its diagonal).
fn solve3(a: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |m: [[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(a);
    if d.is_nan() || d.abs() <= 1e-6 * a[0][0] * a[1][1] * a[2][2] {
        return None;
    }
    Some(std::array::from_fn(|k| {
        let mut m = a;
        for (row, &bk) in m.iter_mut().zip(&b) {
            row[k] = bk;
        }
        det(m) / d
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::edt_squared;
    use ndarray::Array3;

    /// Foreground indices run over the foreground voxels in row order, `voxel` and
    /// `row` invert `index`, and `for_neighbours` gives exactly the foreground
    /// 26-neighbours, each with its offset and row, in index order.
    #[test]
    fn foreground_indices_and_neighbours_match_the_mask() {
        let mut rnd = crate::test_rng(9);
        let m = Array3::from_shape_fn((6, 7, 8), |_| u8::from(rnd(100) < 40));
        let f = Field::new(m.view(), [1.0, 2.0, 0.5]).unwrap();
        let fg: Vec<[usize; 3]> = m.indexed_iter().filter(|(_, &x)| x != 0).map(|(v, _)| [v.0, v.1, v.2]).collect();
        assert_eq!(f.count(), fg.len());
        for (i, &v) in fg.iter().enumerate() {
            assert_eq!((f.index(v), f.voxel(i), f.row(i)), (Some(i), v, v[0] * 7 + v[1]));
            let mut got = vec![];
            f.for_neighbours(i, f.row(i), |o, j, row| got.push((o, j, row)));
            let mut want = vec![];
            for (o, w) in (0..27).map(|o| (o, [o / 9, (o / 3) % 3, o % 3])) {
                let u: [isize; 3] = std::array::from_fn(|d| v[d] as isize + w[d] as isize - 1);
                if o == 13 || (0..3).any(|d| u[d] < 0 || u[d] >= [6, 7, 8][d]) {
                    continue;
                }
                let u = u.map(|x| x as usize);
                if m[u] != 0 {
                    want.push((o, f.index(u).unwrap(), u[0] * 7 + u[1]));
                }
            }
            want.sort_by_key(|&(_, j, _)| j);
            assert_eq!(got, want);
        }
        assert_eq!(f.index([0, 0, 0]).is_some(), m[[0, 0, 0]] != 0);
    }

    /// Random access gives the sparse transform's value at every foreground voxel, 0
    /// on background and outside the array; interpolation is exact at voxel centres
    /// and linear between two of them.
    #[test]
    fn the_field_reads_the_transform_at_every_voxel() {
        let mut rnd = crate::test_rng(5);
        let m = Array3::from_shape_fn((7, 9, 11), |_| u8::from(rnd(100) < 70));
        let s = [1.0, 0.8, 1.5];
        let f = Field::new(m.view(), s).unwrap();
        // In base cells: the transform with spacing / min(spacing).
        let mut sparse = edt_squared(m.view(), [1.25, 1.0, 1.875]).unwrap().into_iter();
        for ((i, j, k), &v) in m.indexed_iter() {
            let at = f.at([i as isize, j as isize, k as isize]);
            let want = if v != 0 { (sparse.next().unwrap() as f64).sqrt() } else { 0.0 };
            // Computed in physical units and scaled: equal up to the `f32` rounding.
            assert!((at - want).abs() <= 1e-6 * want, "{:?}: {at} against {want}", (i, j, k));
            let centre = [i as f64 * s[0], j as f64 * s[1], k as f64 * s[2]];
            assert!((f.interpolate(centre) - at).abs() < 1e-12);
        }
        for v in [[-1, 0, 0], [0, 9, 0], [0, 0, 11], [7, 8, 10]] {
            assert_eq!(f.at(v), 0.0);
        }
        let (a, b) = (f.at([3, 4, 5]), f.at([3, 4, 6]));
        assert!((f.interpolate([3.0, 3.2, 5.25 * 1.5]) - (0.75 * a + 0.25 * b)).abs() < 1e-9);
    }

    /// A junction moved past its path neighbour: the branch `b — q — a` folds back at
    /// `q` (a at z 4 below q at z 5, b at z 2), so `q` goes between them; a path node
    /// the junction did not pass, and one next to no junction, stay.
    #[test]
    fn a_path_node_its_junction_passed_goes_between_its_neighbours() {
        let mask = Array3::<u8>::ones((12, 12, 12));
        let f = Field::new(mask.view(), [1.0; 3]).unwrap();
        // 0 junction (neighbours 1, 3, 4); 1 the passed node; 2 beyond it; 3, 4 other
        // branches; 5 — 6 — 7 a path with no junction that folds.
        let g = crate::test_graph(8, [(0, 1), (1, 2), (0, 3), (0, 4), (5, 6), (6, 7)].into_iter()).0;
        let moved = [
            [5.0, 5.0, 4.0],
            [5.0, 5.0, 5.0],
            [5.0, 5.0, 2.0],
            [5.0, 9.0, 5.0],
            [9.0, 5.0, 5.0],
            [2.0, 2.0, 8.0],
            [2.0, 2.0, 9.0],
            [2.0, 2.0, 7.0],
        ];
        let out = unfold(&g, &moved, &f);
        assert_eq!(out[1], [5.0, 5.0, 3.0]);
        for i in [0, 2, 3, 4, 5, 6, 7] {
            assert_eq!(out[i], moved[i], "node {i}");
        }
        // Not folded (the junction stayed above q): q stays.
        let mut straight = moved;
        straight[0] = [5.0, 5.0, 7.0];
        assert_eq!(unfold(&g, &straight, &f)[1], moved[1]);
    }

    /// A thin child (radius 2) leaving a thick straight parent (radius 5) at 90° and
    /// 45°: the graph's junction lies within a voxel of where the centrelines meet
    /// (the least-squares point of all three branch lines, the rule before the parent's
    /// axis, put it 3.8 voxels up the child at 45°).
    #[test]
    fn a_thin_child_meets_a_thick_parent_on_its_axis() {
        use crate::shapes::{capsules, Capsule};
        for degrees in [90f64, 45.0] {
            let meet = [20.0, 30.0, 14.0];
            let (s, c) = degrees.to_radians().sin_cos();
            let parts = [
                Capsule { a: [20.0, 4.0, 14.0], b: [20.0, 68.0, 14.0], r: 5.0 },
                Capsule { a: meet, b: [20.0, 30.0 + 30.0 * c, 14.0 + 30.0 * s], r: 2.0 },
            ];
            let mask = capsules([41, 73, 50], [1.0; 3], &parts);
            let out = crate::Skeletonizer::new(crate::Params::default())
                .unwrap()
                .run(mask.view(), [1.0; 3], &mut |_| true)
                .unwrap();
            let deg = out.degrees();
            let junctions: Vec<[f64; 3]> = (0..out.len()).filter(|&i| deg[i] >= 3).map(|i| out.positions[i]).collect();
            assert_eq!(junctions.len(), 1, "{degrees}°: junctions {junctions:?}");
            let off = norm(sub(junctions[0], meet));
            assert!(off <= 1.0, "{degrees}°: junction {:?} is {off:.2} from {meet:?}", junctions[0]);
        }
    }

    /// A child (from junction 0 up axis 2) that leaves its straight parent (axis 1) at
    /// 90° and curves towards +y beyond one radius: its line runs from where it leaves,
    /// so the junction lands within a voxel of the true meeting point (the origin; 0.6
    /// off). A line through the stretch beyond the junction's ball (r to 3 r, the rule
    /// before) points where the child goes and put it 2.0 voxels off, down the parent.
    #[test]
    fn a_curving_child_meets_its_parent_where_it_leaves() {
        // 0 junction; 1–6 the parent; 7–11 the child.
        let edges = [(0, 1), (1, 2), (2, 3), (0, 4), (4, 5), (5, 6), (0, 7), (7, 8), (8, 9), (9, 10), (10, 11)];
        let g = crate::test_graph(12, edges.into_iter()).0;
        let curves = [
            [0.0, 0.3, 0.4],
            [0.0, 1.0, 0.0],
            [0.0, 2.0, 0.0],
            [0.0, 3.0, 0.0],
            [0.0, -1.0, 0.0],
            [0.0, -2.0, 0.0],
            [0.0, -3.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, 2.0],
            [0.0, 0.0, 3.0],
            [0.0, 1.0, 4.0],
            [0.0, 2.5, 5.0],
        ];
        let m = meeting_point(&g, &curves, &[2.0; 12], 2.0, 0, curves[0]).unwrap().0;
        assert!(norm(m) <= 1.0, "junction at {m:?}");
    }

    /// A fork of three branches at 120° in a plane, meeting at the origin; one
    /// branch's nodes are jittered across it (0.3, -0.7, 0.3, 0.3 from the junction
    /// out: no weighted mean offset and no weighted tilt, with weights 4, 3, 2, 1).
    /// Each branch's line is the weighted least-squares one, so the junction lands on
    /// the origin; the line through the branch's end nodes, both 0.3 to one side, put
    /// it 0.2 away.
    #[test]
    fn a_jittered_branch_still_meets_the_others_on_their_axes() {
        let edges = [(0, 1), (1, 2), (2, 3), (3, 4), (0, 5), (5, 6), (6, 7), (0, 8), (8, 9), (9, 10)];
        let g = crate::test_graph(11, edges.into_iter()).0;
        let along = |angle: f64, s: f64, off: f64| {
            let (sin, cos) = angle.to_radians().sin_cos();
            [s * cos - off * sin, s * sin + off * cos, 0.0]
        };
        let mut curves = vec![[0.2, -0.1, 0.0]];
        curves.extend([0.3, -0.7, 0.3, 0.3].iter().enumerate().map(|(k, &j)| along(0.0, k as f64 + 1.0, j)));
        curves.extend((1..=3).map(|k| along(120.0, k as f64, 0.0)));
        curves.extend((1..=3).map(|k| along(240.0, k as f64, 0.0)));
        let m = meeting_point(&g, &curves, &[2.0; 11], 2.0, 0, curves[0]).unwrap().0;
        assert!(norm(m) < 1e-9, "junction at {m:?}");
        // The fitted line points from the branch's first node toward its last, through
        // the nodes' weighted mean (weights 4, 3, 2, 1 from node 1 out).
        let (centre, t) = fitted_line(&curves, &[1, 2, 3, 4]).unwrap();
        assert!(norm(sub(t, [1.0, 0.0, 0.0])) < 1e-9 && norm(sub(centre, [2.0, 0.0, 0.0])) < 1e-9, "{centre:?} {t:?}");
        let (_, back) = fitted_line(&curves, &[4, 3, 2, 1]).unwrap();
        assert!(back[0] < -0.9, "{back:?}");
    }

    #[test]
    fn three_lines_meet_where_they_cross() {
        // Lines through (1, 2, 3) along the axes and a diagonal: their projectors summed.
        let p = [1.0, 2.0, 3.0];
        let mut a = [[0.0; 3]; 3];
        let mut b = [0.0; 3];
        for t in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.6, 0.0, 0.8]] {
            for r in 0..3 {
                for c in 0..3 {
                    let proj = f64::from(u8::from(r == c)) - t[r] * t[c];
                    a[r][c] += proj;
                    b[r] += proj * p[c];
                }
            }
        }
        let x = solve3(a, b).unwrap();
        assert!((0..3).all(|d| (x[d] - p[d]).abs() < 1e-12), "{x:?}");
        // Parallel lines have no meeting point.
        assert_eq!(solve3([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], [0.0, 1.0, 1.0]), None);
    }
}
