//! Vessel radii at the output nodes (output stage; the paper takes the EDT).
//!
//! Three models, so that they can be compared (`tests/radius.rs` prints them all):
//!
//! - [`RadiusModel::Edt`]: the largest distance-transform value of the node's
//!   cluster (decimation's max-radius transfer) less a constant, in base cells:
//!   the radius of `docs/method.md` §1, with a half-voxel correction. The EDT measures from a voxel
//!   centre to the nearest *background voxel centre*; the half voxel is the gap between
//!   a face and the next centre along an axis, but on a round tube some background
//!   centre lies only a few hundredths of a voxel beyond the drawn surface, so the raw
//!   EDT near the axis is already close to the radius (measured: 0 to 5 % low, drawn
//!   by voxel centres or by half volume) and the half voxel makes it 10 % (r = 5 to 10)
//!   to 33 % (r = 1 to 2) too low. Raw, its spread grows on thin and anisotropic
//!   vessels (MAPE 7 to 12 % at r = 1 to 2), since the voxels sample the section
//!   coarsely.
//! - [`RadiusModel::Section`]: the area of the vessel's cross-section,
//!   `r = sqrt(A / π)`. `A` is the foreground volume of a slab orthogonal to the local
//!   vessel direction, within a disc of reach `ρ` about the node, per unit of the
//!   slab's thickness (voxels weighted by a tent of half-width `h` along the direction,
//!   see `Slab`): each foreground voxel counts its own volume, so the count
//!   estimates the volume the mask represents, whatever the spacing, and a voxelised
//!   tube's volume is the drawn tube's volume on average over offsets and orientations
//!   (exactly so for voxels set by their centre; a voxel set by half its volume loses a
//!   little where the surface is convex, negligible above one voxel of radius). No
//!   constant is fitted to a data set; the only numbers are the slab and disc sizes,
//!   set by geometry below. It measures the mask: a mask drawn or segmented wider than
//!   its vessels gives wider radii (`radius_correction` subtracts a known margin).
//!
//! - [`RadiusModel::Chords`] (the default, [`RadiusModel::MEDIAN_CHORDS`]): the
//!   section radius made robust to what sticks out of the vessel. Bubbles of
//!   segmentation noise glued to the wall, the mouth of a side branch or a touching
//!   vessel add to the area of a few sides of the section only. The model measures the
//!   vessel's width along 16 chords through the node, orthogonal to its direction, in
//!   each of three planes (at `-h/2, 0, h/2` along the direction, or `h/2, h, 3h/2`
//!   inside an end): each chord runs from the node both ways to where the mask,
//!   interpolated trilinearly, falls below one half (found to 1/1000 of a cell by a march
//!   of a quarter cell and bisection; a chord stops at the reach `ρ`). A node that
//!   sits on a background point of the interpolated mask (a thin vessel, up to half a
//!   cell off) starts each chord at the nearest inside point of its line within half a
//!   cell. The radius is the section radius scaled by the chords' `quantile` over their
//!   root mean square: `r = sqrt(A / π) · L_q / sqrt(mean L²)`. On a round section the
//!   chords are all about equal and the factor is 1, so the area's freedom from bias
//!   carries over whatever the rasterisation; the chords' own bias (the half-level of
//!   the interpolated mask cuts inside a convex surface by up to 13 % on anisotropic
//!   thin vessels, a node off the axis shortens its chords) cancels in the ratio. Where
//!   a minority of the chords is lengthened, the area grows like their mean square and
//!   the factor takes it back. The median (0.5) is the default: it meets the analytic
//!   targets under both rasterisations and at anisotropic spacing; lower quantiles
//!   resist more noise (0.35 takes the noisy forests' bias from +16 to +11 % at D1) but
//!   read thin partial-volume tubes up to 10 % low (`tests/radius.rs`). Chords are
//!   connected to the node by construction (each stops at the first background), so a
//!   vessel across a gap does not count. Where most of the wall is covered (bubble
//!   noise D2, whose hole filling also fills the gaps between bubbles) the mask is wider
//!   than the vessel on all sides and no measure of the mask can tell.
//!
//! The section and chord models need a direction: nodes of degree 2 take the chord between
//! their two neighbours, nodes of degree 1 (vessel ends) the direction to their
//! neighbour, with the slab on the inner side only (a full slab at an end would reach
//! into the end cap). Junctions (degree ≥ 3) and isolated nodes have no single
//! direction: they keep the raw EDT (offset 0), the better of the EDT models.
//! Isolated nodes (a blob the flow shrank to a point) take the radius of the ball of
//! their blob's volume.
//!
//! No section or chord radius exceeds the raw EDT by more than half a voxel diagonal: a tube's
//! axis is no farther from the surface than from the nearest background centre, and
//! the node's voxel is within half a diagonal of the axis. The cap bounds what a
//! touching vessel or a bubble inside the disc can add, and keeps the radius of a
//! section that is not round (a solid block) near its inscribed ball.
//!
//! Sizes, with `c` the base cell and `r₀` the raw EDT radius (a first guess
//! within about half a voxel): tent half-width `h = max(s, r₀ / 2)`, `s` the largest
//! spacing, so that the slab is at least two of the coarsest voxels thick and averages
//! over the grid's phase along oblique vessels, and short enough that a curved vessel
//! (curvature radius ≥ a few `r`) stays straight within it; reach
//! `ρ = 1.5 r₀ + 2 c`, so the whole section lies in the disc although the node may sit
//! up to a voxel off the axis, while a parallel vessel one clearance away stays out.
//! The disc is first centred on the node, then once on the centroid of the foreground
//! it found there (a tube's centroid is its axis).

use crate::grid::Csr;
use crate::medial::plane_basis;
use crate::volume::Voxel;
use ndarray::ArrayView3;
use rayon::prelude::*;

/// How node radii are measured (see the module).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RadiusModel {
    /// The cluster's largest EDT value less `offset` base cells (at least 0).
    Edt {
        /// Subtracted from the EDT, in base cells.
        offset: f64,
    },
    /// The cross-section area; junctions and isolated nodes keep the EDT (offset 0).
    Section,
    /// The cross-section area scaled by the `quantile` of the chords across the vessel
    /// over their root mean square (see the module); junctions and isolated nodes as
    /// [`RadiusModel::Section`].
    Chords {
        /// Which quantile of the chord lengths, clamped to [0, 1]: 0.5 is their median.
        quantile: f64,
    },
}

impl RadiusModel {
    /// The pipeline's model: the section area scaled by the median chord.
    pub const MEDIAN_CHORDS: RadiusModel = RadiusModel::Chords { quantile: 0.5 };
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn unit(d: [f64; 3]) -> Option<[f64; 3]> {
    let n = dot(d, d).sqrt();
    (n > 0.0).then(|| [d[0] / n, d[1] / n, d[2] / n])
}

/// The slab along the direction `t`: `(middle, half)`, in physical units along `t`
/// from the node. Voxels count with a tent weight, 1 at the middle and 0 at
/// `middle ± half`, of integral 1: its sum over a row of voxel planes is its integral
/// up to second order in the planes' phase, where a flat slab holds a whole number of
/// planes (on a tube along an axis, 5 or 6 planes in a slab 5.5 voxels thick: ±9 % of
/// area).
type Slab = (f64, f64);

/// Tent-weighted foreground volume per unit length along `t` (an area) and its
/// weighted centroid (projected on the plane through `p` orthogonal to `t`), of the
/// voxels whose centres lie within `reach` of the line through `p` along `t`.
fn section_area<T: Voxel>(
    mask: &ArrayView3<'_, T>,
    spacing: [f64; 3],
    p: [f64; 3],
    t: [f64; 3],
    (middle, half): Slab,
    reach: f64,
) -> (f64, [f64; 3]) {
    let (n0, n1, n2) = mask.dim();
    let shape = [n0, n1, n2];
    let extent = reach + middle.abs() + half;
    let range = |d: usize| {
        let lo = ((p[d] - extent) / spacing[d]).floor().max(0.0);
        let hi = ((p[d] + extent) / spacing[d]).ceil().min(shape[d] as f64 - 1.0);
        (lo as usize, hi as usize, hi >= lo)
    };
    let (r0, r1, r2) = (range(0), range(1), range(2));
    if !(r0.2 && r1.2 && r2.2) {
        return (0.0, p);
    }
    let (mut weight, mut sum) = (0.0, [0.0; 3]);
    for i in r0.0..=r0.1 {
        for j in r1.0..=r1.1 {
            for k in r2.0..=r2.1 {
                if !mask[[i, j, k]].is_set() {
                    continue;
                }
                let d = sub([i as f64 * spacing[0], j as f64 * spacing[1], k as f64 * spacing[2]], p);
                let along = dot(d, t);
                let w = 1.0 - (along - middle).abs() / half;
                if w <= 0.0 {
                    continue;
                }
                let off = [d[0] - along * t[0], d[1] - along * t[1], d[2] - along * t[2]];
                if dot(off, off) <= reach * reach {
                    weight += w;
                    for a in 0..3 {
                        sum[a] += w * off[a];
                    }
                }
            }
        }
    }
    let area = weight / half * spacing.iter().product::<f64>();
    let centre = if weight > 0.0 { std::array::from_fn(|a| p[a] + sum[a] / weight) } else { p };
    (area, centre)
}

/// `(c, h, ρ)`: the base cell, the slab's half-width and the disc's reach for the first
/// guess `r0` (see the module).
fn sizes(spacing: [f64; 3], r0: f64) -> (f64, f64, f64) {
    let c = spacing.iter().cloned().fold(f64::INFINITY, f64::min);
    let h = spacing.iter().cloned().fold(0.0, f64::max).max(0.5 * r0);
    (c, h, 1.5 * r0 + 2.0 * c)
}

/// The cross-section radius at `p` along the unit direction `t`, with first guess `r0`
/// (see the module); `end` puts the slab on the side `t` points to only.
fn section_radius<T: Voxel>(
    mask: &ArrayView3<'_, T>,
    spacing: [f64; 3],
    p: [f64; 3],
    t: [f64; 3],
    r0: f64,
    end: bool,
) -> f64 {
    let (_, h, reach) = sizes(spacing, r0);
    let slab = if end { (h, h) } else { (0.0, h) };
    let (_, centre) = section_area(mask, spacing, p, t, slab, reach);
    let (area, _) = section_area(mask, spacing, centre, t, slab, reach);
    (area / std::f64::consts::PI).sqrt()
}

/// The mask interpolated trilinearly at `p` (physical units): 1 on foreground voxel
/// centres, 0 on background and outside the array.
fn mask_at<T: Voxel>(mask: &ArrayView3<'_, T>, spacing: [f64; 3], p: [f64; 3]) -> f64 {
    let (n0, n1, n2) = mask.dim();
    let shape = [n0 as isize, n1 as isize, n2 as isize];
    let x: [f64; 3] = std::array::from_fn(|d| p[d] / spacing[d]);
    if (0..3).any(|d| !(x[d] > -1.0 && x[d] < shape[d] as f64)) {
        return 0.0;
    }
    let lo: [f64; 3] = std::array::from_fn(|d| x[d].floor());
    let f: [f64; 3] = std::array::from_fn(|d| x[d] - lo[d]);
    let mut sum = 0.0;
    for corner in 0..8 {
        let bit = |d: usize| (corner >> (2 - d)) & 1;
        let v: [isize; 3] = std::array::from_fn(|d| lo[d] as isize + bit(d) as isize);
        if (0..3).any(|d| v[d] < 0 || v[d] >= shape[d]) || !mask[[v[0] as usize, v[1] as usize, v[2] as usize]].is_set()
        {
            continue;
        }
        sum += (0..3).map(|d| if bit(d) == 1 { f[d] } else { 1.0 - f[d] }).product::<f64>();
    }
    sum
}

/// Chords per axial plane (directions spread over half a turn) and axial planes.
const CHORD_DIRECTIONS: usize = 16;
const CHORD_PLANES: usize = 3;
/// March step in base cells, and bisection steps that refine each crossing (to
/// `STEP / 2^BISECTIONS` of a cell).
const STEP: f64 = 0.25;
const BISECTIONS: usize = 8;

/// Distance from `q` along the unit `w` to where the interpolated mask falls below
/// one half, at most `reach` (`q` itself is inside).
fn extent<T: Voxel>(
    mask: &ArrayView3<'_, T>,
    spacing: [f64; 3],
    q: [f64; 3],
    w: [f64; 3],
    step: f64,
    reach: f64,
) -> f64 {
    let at = |s: f64| mask_at(mask, spacing, std::array::from_fn(|d| q[d] + s * w[d]));
    let steps = (reach / step).ceil() as usize;
    for m in 1..=steps {
        let s = (m as f64 * step).min(reach);
        if at(s) < 0.5 {
            let (mut inside, mut outside) = ((m - 1) as f64 * step, s);
            for _ in 0..BISECTIONS {
                let mid = 0.5 * (inside + outside);
                if at(mid) >= 0.5 {
                    inside = mid;
                } else {
                    outside = mid;
                }
            }
            return 0.5 * (inside + outside);
        }
    }
    reach
}

/// The chord radius at `p` along the unit direction `t`, first guess `r0`: the section
/// radius times the `quantile` of the chord lengths across the vessel over their root
/// mean square (see the module); `end` puts the planes on the side `t` points to only.
/// `None` when no chord starts inside.
fn chord_radius<T: Voxel>(
    mask: &ArrayView3<'_, T>,
    spacing: [f64; 3],
    p: [f64; 3],
    t: [f64; 3],
    r0: f64,
    end: bool,
    quantile: f64,
) -> Option<f64> {
    let (c, h, reach) = sizes(spacing, r0);
    let step = STEP * c;
    let [u, v] = plane_basis(t);
    let mut chords = Vec::with_capacity(CHORD_DIRECTIONS * CHORD_PLANES);
    for j in 0..CHORD_PLANES {
        // Planes at -h/2, 0, h/2 about the node, or h/2, h, 3h/2 inside an end.
        let along = (j as f64 - 1.0 + if end { 2.0 } else { 0.0 }) * 0.5 * h;
        let q0: [f64; 3] = std::array::from_fn(|d| p[d] + along * t[d]);
        for k in 0..CHORD_DIRECTIONS {
            let a = std::f64::consts::PI * k as f64 / CHORD_DIRECTIONS as f64;
            let w: [f64; 3] = std::array::from_fn(|d| a.cos() * u[d] + a.sin() * v[d]);
            // A node up to half a cell off a thin vessel starts from the nearest
            // inside point of the chord's line within half a cell.
            let start = [0.0, 1.0, -1.0, 2.0, -2.0]
                .iter()
                .map(|m| m * 0.25 * c)
                .find(|&s| mask_at(mask, spacing, std::array::from_fn(|d| q0[d] + s * w[d])) >= 0.5);
            let Some(s) = start else { continue };
            let q: [f64; 3] = std::array::from_fn(|d| q0[d] + s * w[d]);
            let back = w.map(|x| -x);
            chords.push(extent(mask, spacing, q, w, step, reach) + extent(mask, spacing, q, back, step, reach));
        }
    }
    if chords.is_empty() {
        return None;
    }
    let rms = (chords.iter().map(|l| l * l).sum::<f64>() / chords.len() as f64).sqrt();
    chords.sort_by(f64::total_cmp);
    let x = quantile.clamp(0.0, 1.0) * (chords.len() - 1) as f64;
    let (i, f) = (x.floor() as usize, x - x.floor());
    let j = (i + 1).min(chords.len() - 1);
    let typical = chords[i] * (1.0 - f) + chords[j] * f;
    Some(section_radius(mask, spacing, p, t, r0, end) * typical / rms)
}

/// The radius of the ball of the foreground volume within reach of `p` (first guess
/// `r0`): an isolated node's blob. (A zero direction makes every point's offset
/// from the "line" its offset from `p`, so the disc is a ball.)
fn ball_radius<T: Voxel>(mask: &ArrayView3<'_, T>, spacing: [f64; 3], p: [f64; 3], r0: f64) -> f64 {
    let c = spacing.iter().cloned().fold(f64::INFINITY, f64::min);
    // With `t = 0` every voxel is at the tent's middle: weight 1 per unit `half`.
    let (volume, _) = section_area(mask, spacing, p, [0.0; 3], (0.0, 1.0), 1.5 * r0 + 2.0 * c);
    (volume * 0.75 / std::f64::consts::PI).cbrt()
}

/// The radius of every node of the output graph `g` (positions in physical units),
/// given each node's largest EDT value `edt_radii` (physical), by `model`.
pub fn node_radii<T: Voxel>(
    model: RadiusModel,
    g: &Csr,
    positions: &[[f64; 3]],
    edt_radii: &[f64],
    mask: ArrayView3<'_, T>,
    spacing: [f64; 3],
) -> Vec<f64> {
    let c = spacing.iter().cloned().fold(f64::INFINITY, f64::min);
    let cap = 0.5 * dot(spacing, spacing).sqrt();
    (0..g.nodes())
        .into_par_iter()
        .map(|i| {
            let (p, r0) = (positions[i], edt_radii[i]);
            let quantile = match model {
                RadiusModel::Edt { offset } => return (r0 - offset * c).max(0.0),
                RadiusModel::Section => None,
                RadiusModel::Chords { quantile } => Some(quantile),
            };
            let (t, end) = match *g.neighbours(i) {
                [] => return ball_radius(&mask, spacing, p, r0).min(r0 + cap),
                [a] => (unit(sub(positions[a as usize], p)), true),
                [a, b] => (unit(sub(positions[b as usize], positions[a as usize])), false),
                _ => (None, false),
            };
            let Some(t) = t else { return r0 };
            let r = match quantile {
                None => section_radius(&mask, spacing, p, t, r0, end),
                Some(q) => chord_radius(&mask, spacing, p, t, r0, end, q).unwrap_or(r0),
            };
            r.min(r0 + cap)
        })
        .collect()
}
