//! Vessel radii at the output nodes (output stage; the paper takes the EDT).
//!
//! Two models, so that they can be compared (`tests/radius.rs` prints both):
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
//! - [`RadiusModel::Section`] (the default): the area of the vessel's cross-section,
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
//! The section model needs a direction: nodes of degree 2 take the chord between
//! their two neighbours, nodes of degree 1 (vessel ends) the direction to their
//! neighbour, with the slab on the inner side only (a full slab at an end would reach
//! into the end cap). Junctions (degree ≥ 3) and isolated nodes have no single
//! direction: they keep the raw EDT (offset 0), the better of the EDT models.
//! Isolated nodes (a blob the flow shrank to a point) take the radius of the ball of
//! their blob's volume.
//!
//! No section radius exceeds the raw EDT by more than half a voxel diagonal: a tube's
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
    let c = spacing.iter().cloned().fold(f64::INFINITY, f64::min);
    let h = spacing.iter().cloned().fold(0.0, f64::max).max(0.5 * r0);
    let slab = if end { (h, h) } else { (0.0, h) };
    let reach = 1.5 * r0 + 2.0 * c;
    let (_, centre) = section_area(mask, spacing, p, t, slab, reach);
    let (area, _) = section_area(mask, spacing, centre, t, slab, reach);
    (area / std::f64::consts::PI).sqrt()
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
        .map(|i| match model {
            RadiusModel::Edt { offset } => (edt_radii[i] - offset * c).max(0.0),
            RadiusModel::Section => {
                let (p, r0) = (positions[i], edt_radii[i]);
                let (t, end) = match *g.neighbours(i) {
                    [] => return ball_radius(&mask, spacing, p, r0).min(r0 + cap),
                    [a] => (unit(sub(positions[a as usize], p)), true),
                    [a, b] => (unit(sub(positions[b as usize], positions[a as usize])), false),
                    _ => (None, false),
                };
                t.map_or(r0, |t| section_radius(&mask, spacing, p, t, r0, end).min(r0 + cap))
            }
        })
        .collect()
}
