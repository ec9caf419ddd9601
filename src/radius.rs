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
//!   see `Slab`, `h` rounded up to a whole number of the coarsest spacing: along a grid
//!   axis the voxels sit in slices, and the tent's weights over them sum to its width at
//!   any offset only then): each foreground voxel counts its own volume, so the count
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
//!   vessel add to the area of a few sides of the section, over a short stretch of the
//!   vessel. The model measures the vessel's width along 12 chords through the node,
//!   orthogonal to its direction, in each of five planes (at `-2h, -h, 0, h, 2h` along
//!   the direction, about one radius each way, or `h/2, 3h/2, ..., 9h/2` inside an end):
//!   each chord runs from the plane's centre both ways to where the mask, interpolated
//!   trilinearly (0 outside the array, so a chord stops at the array's face as at
//!   background), falls below one half (a march of a quarter cell finds the step that
//!   holds the crossing, two halvings narrow it to a sixteenth of a cell, and the
//!   mask's value is interpolated linearly across that, to within about 10⁻³ of a cell;
//!   a chord stops at the reach `ρ`). The march keeps the
//!   corners of the cell it is in and steps past the points of a cell whose corners are
//!   all set without reading them (they are inside), and starts past the points that
//!   the distance transform puts deep enough inside that their cells' corners are all
//!   set (see `clear_of`): the same crossings, read faster.
//!   A centre that sits on a background point of the interpolated mask (a thin vessel,
//!   up to half a cell off) starts each chord at the nearest inside point of its line
//!   within half a cell.
//!   **Trim**: of the pooled chords, those longer than their 10 % quantile by more than
//!   the coarsest spacing are left out. The grid moves the half-level crossing of a
//!   round vessel's chord by less than a cell, so on a clean tube every chord is kept;
//!   a bubble (two cells of radius in the benchmark's noise), a branch's mouth or a
//!   touching vessel lengthens the chords through it by more, and since it is short
//!   along the vessel the planes an `h` or two away still hold clean chords that set the
//!   reference. On an anisotropic grid the reference is the 10 % quantile of the
//!   chords of the most finely sampled directions only (those whose voxel width along
//!   them exceeds the finest spacing's by at most a finest cell more than the least
//!   such excess): a chord along a coarse axis is cut short by up to a voxel there, and
//!   a vessel lying in the plane of a stack of thick slices, flattened to a band one
//!   slice thick, lost all its wide chords to its short ones (a band 10.2 µm wide in
//!   5 µm slices: radius 2.92 µm instead of 3.58, below a band 7.8 wide). Isotropic
//!   grids are unaffected. A vessel that widens along its length (an aneurysm, the
//!   carotid bulb) has narrower outer planes, which set the reference, and lost its
//!   middle planes' chords to the trim (a bulge from radius 5 to 10 read 5.7 at its
//!   peak): a plane whose chords agree within the coarsest cell is round, nothing sticks
//!   out of it, and when the vessel is wide (reference at least `WIDE` coarsest cells,
//!   past what a blob of voxel-scale noise engulfs) it keeps its chords whatever their
//!   length; the typical chord is then taken from the middle planes alone.
//!   The radius is the section radius scaled by the kept chords' `quantile`
//!   over the root mean square of all chords of the middle three planes (the slab of
//!   the area): `r = sqrt(A / π) · L_q(kept) / sqrt(mean L²)`. On a round section the
//!   chords are all about equal and the factor is 1, so the area's freedom from bias
//!   carries over whatever the rasterisation; the chords' own bias (the half-level of
//!   the interpolated mask cuts inside a convex surface by up to 13 % on anisotropic
//!   thin vessels, a node off the axis shortens its chords) cancels in the ratio. Where
//!   some chords are lengthened, the area grows like their mean square and the factor
//!   takes it back. The median (0.5) of the kept chords is the default. On the tuning
//!   forests (3 seeds, σ = 2) the trim and the five planes took the radius MAPE at
//!   D0 / D1 / D2 from 9.3 / 17.5 / 34.4 % to 6.4 / 9.4 / 19.5 % (the 10 % reference is
//!   the lowest quantile that leaves analytic tubes unbiased: 0.25 keeps too many
//!   lengthened chords, and a reference from the shortest chord or from the lowest of
//!   the per-plane medians reads thin tubes 3 to 7 % low). Chords are connected to
//!   their centre by construction (each stops at the first background), and the area
//!   counts only the voxels inside their outline (see `Outline`), so a vessel across a
//!   gap does not count. Where most of the wall is covered (bubble noise D2,
//!   whose hole filling also fills the gaps between bubbles) the mask is wider than the
//!   vessel on all sides and no measure of the mask can tell.
//!
//! The section and chord models need a direction: nodes of degree 2 take the chord between
//! their two neighbours, nodes of degree 1 (vessel ends) the direction to their
//! neighbour, with the slab on the inner side only (a full slab at an end would reach
//! into the end cap). Junctions (degree ≥ 3) have no single direction: they take the
//! inscribed radius at the node itself, the distance from the node to the nearest
//! background voxel centre (the raw EDT read at the point; outside the array is
//! background, as for the EDT, so a node near the array's face measures to the centres
//! just past it). The cluster's largest EDT
//! (decimation's transfer) is the widest point of the junction region, where the
//! vessels' walls part: on the tuning forests it read junctions +26 % high at D0 where
//! the point's inscribed radius reads +2 %.
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
//! The section model centres the disc first on the node, then once on the centroid of
//! the foreground it found there (a tube's centroid is its axis). The chord model
//! centres it on the point the kept chords of the middle planes put at the section's
//! centre (see `chord_centre`), which spares the first disc (an eighth of the output
//! stage's time) and, since the trim has left out the chords through bubbles and
//! branch mouths, does not lean toward them as the foreground's centroid does.

use crate::grid::Csr;
use crate::medial::{plane_basis, Field};
use crate::vec3::{base_cell, coarsest, dot, sub, unit};
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
    /// The cross-section area; junctions take the inscribed radius at the node, isolated
    /// nodes the ball of their blob's volume.
    Section,
    /// The cross-section area scaled by the `quantile` of the trimmed chords across the
    /// vessel over their root mean square (see the module); junctions and isolated nodes
    /// as [`RadiusModel::Section`].
    Chords {
        /// Which quantile of the kept chord lengths, clamped to [0, 1]: 0.5 is their median.
        quantile: f64,
    },
}

/// The model of every output node's radius (the routed-in nodes' too, in a single
/// run and in a chunked run's routing phase).
pub const OUTPUT_RADII: RadiusModel = RadiusModel::MEDIAN_CHORDS;

impl RadiusModel {
    /// The pipeline's model: the section area scaled by the median chord.
    pub const MEDIAN_CHORDS: RadiusModel = RadiusModel::Chords { quantile: 0.5 };
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
/// voxels whose centres lie within `reach` of the line through `p` along `t` and
/// inside `outline` (when given).
fn section_area<T: Voxel>(
    mask: &ArrayView3<'_, T>,
    spacing: [f64; 3],
    p: [f64; 3],
    t: [f64; 3],
    (middle, half): Slab,
    reach: f64,
    outline: Option<&Outline>,
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
    // Each row along axis 2 is read only where it meets the slab and the ball that holds
    // the slab's disc, both widened by a voxel, far more than any rounding of the tests
    // below: the voxels left out are those the tests turn away, and the sums add the
    // same terms in the same order.
    // The outline's line runs along `t` too: a voxel's offset from it is its offset from
    // the line through `p` plus `p`'s own.
    let shift = outline.map(|o| (o, o.offset(p)));
    let pad = coarsest(spacing);
    let ball = (middle.abs() + half).hypot(reach) + pad;
    let (slab_lo, slab_hi) = (middle - half - pad, middle + half + pad);
    let (mut weight, mut sum) = (0.0, [0.0; 3]);
    for i in r0.0..=r0.1 {
        for j in r1.0..=r1.1 {
            let e = [i as f64 * spacing[0] - p[0], j as f64 * spacing[1] - p[1]];
            let room = ball * ball - e[0] * e[0] - e[1] * e[1];
            if room < 0.0 {
                continue;
            }
            // `z`, the offset along axis 2, within the ball and the slab.
            let (mut z_lo, mut z_hi) = (-room.sqrt(), room.sqrt());
            let b = e[0] * t[0] + e[1] * t[1];
            if t[2].abs() > 1e-12 {
                let (a, c) = ((slab_lo - b) / t[2], (slab_hi - b) / t[2]);
                (z_lo, z_hi) = (z_lo.max(a.min(c)), z_hi.min(a.max(c)));
            } else if !(b > slab_lo && b < slab_hi) {
                continue;
            }
            let k_lo = ((p[2] + z_lo) / spacing[2]).floor().max(r2.0 as f64);
            let k_hi = ((p[2] + z_hi) / spacing[2]).ceil().min(r2.1 as f64);
            if k_lo > k_hi {
                continue;
            }
            let k_lo = k_lo as usize;
            let row = mask.slice(ndarray::s![i, j, k_lo..=k_hi as usize]);
            for (k, _) in row.iter().enumerate().filter(|(_, v)| v.is_set()) {
                let k = k_lo + k;
                let d = sub([i as f64 * spacing[0], j as f64 * spacing[1], k as f64 * spacing[2]], p);
                let along = dot(d, t);
                let w = 1.0 - (along - middle).abs() / half;
                if w <= 0.0 {
                    continue;
                }
                let off = [d[0] - along * t[0], d[1] - along * t[1], d[2] - along * t[2]];
                let admitted = || shift.is_none_or(|(o, s)| o.admits(std::array::from_fn(|a| off[a] + s[a])));
                if dot(off, off) <= reach * reach && admitted() {
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
    let c = base_cell(spacing);
    let h = coarsest(spacing).max(0.5 * r0);
    (c, h, 1.5 * r0 + 2.0 * c)
}

/// The cross-section radius at `p` along the unit direction `t`, with first guess `r0`
/// (see the module); `end` puts the slab on the side `t` points to only; the section
/// holds only the voxels inside `outline` (when given). The disc is centred on
/// `centre` when given, else on the centroid of the foreground a first disc about `p`
/// holds.
#[allow(clippy::too_many_arguments)]
fn section_radius<T: Voxel>(
    mask: &ArrayView3<'_, T>,
    spacing: [f64; 3],
    p: [f64; 3],
    t: [f64; 3],
    r0: f64,
    end: bool,
    outline: Option<&Outline>,
    centre: Option<[f64; 3]>,
) -> f64 {
    let (_, h, reach) = sizes(spacing, r0);
    // A whole number of the coarsest spacing: along a grid axis the tent's weights then
    // sum to the same wherever the node sits between two slices (see the module).
    let coarse = coarsest(spacing);
    let h = (h / coarse).ceil() * coarse;
    let slab = if end { (h, h) } else { (0.0, h) };
    let centre = centre.unwrap_or_else(|| section_area(mask, spacing, p, t, slab, reach, outline).1);
    let (area, _) = section_area(mask, spacing, centre, t, slab, reach, outline);
    (area / std::f64::consts::PI).sqrt()
}

/// The section's outline as the chords found it: about the line through `origin` along
/// `t`, the farthest a chord of the slab's planes reached from its plane's centre in
/// each of the `2 CHORD_DIRECTIONS` half-directions (angle `m π / CHORD_DIRECTIONS` in
/// the plane's basis `u`, `v`), plus a margin of a voxel's width along it. A voxel
/// counts in the section only if its offset from the line is within the larger bound of
/// the two half-directions on either side of it: a vessel across a gap of background,
/// which no chord crosses, stays out of the area (two parallel tubes of radius 3 cells
/// with two background voxels between them read +18 % without it).
struct Outline {
    origin: [f64; 3],
    t: [f64; 3],
    basis: [[f64; 3]; 2],
    /// Per half-direction, physical units (infinite where no chord started: the disc
    /// alone bounds the section there).
    bound: [f64; 2 * CHORD_DIRECTIONS],
    /// The square of the least bound: offsets within it are inside, whatever their angle.
    inner: f64,
}

impl Outline {
    /// The offset of the point `x` (physical units) from the outline's line, orthogonal
    /// to it.
    fn offset(&self, x: [f64; 3]) -> [f64; 3] {
        let d = sub(x, self.origin);
        let along = dot(d, self.t);
        std::array::from_fn(|a| d[a] - along * self.t[a])
    }

    /// Whether a point at the orthogonal offset `off` from the outline's line lies
    /// within the outline.
    fn admits(&self, off: [f64; 3]) -> bool {
        let r2 = dot(off, off);
        if r2 <= self.inner {
            return true;
        }
        let angle = dot(off, self.basis[1]).atan2(dot(off, self.basis[0])).rem_euclid(std::f64::consts::TAU);
        let n = 2 * CHORD_DIRECTIONS;
        let m = (angle / (std::f64::consts::PI / CHORD_DIRECTIONS as f64)) as usize % n;
        let bound = self.bound[m].max(self.bound[(m + 1) % n]);
        r2 <= bound * bound
    }
}

/// The mask interpolated trilinearly (1 on foreground voxel centres, 0 on background
/// and outside the array), read only as "at least one half": whether a point is inside
/// the vessel for the chords. The eight corners of the last cell read are kept, as bits:
/// a chord's march and bisection read the same cell many times in a row (four steps per
/// cell), and a cell whose corners are all set (all clear) is inside (outside) whatever
/// the weights. A mixed cell sums its set corners' weights in the corners' order, so every
/// answer is that of the sum over the eight corners.
struct Interpolated<'a, 'm, T> {
    mask: &'a ArrayView3<'m, T>,
    /// The mask's voxels in memory order when it is laid out in C order (as every front
    /// end passes it): the corners of a cell inside the array are read from it directly.
    flat: Option<&'a [T]>,
    spacing: [f64; 3],
    /// `1 / spacing` where that is exact (a power of two: multiplying by it is dividing),
    /// else 0 (divide).
    inverse: [f64; 3],
    /// Every axis has an exact `inverse`: points are scaled by multiplications alone.
    all_inverse: bool,
    shape: [isize; 3],
    /// The point last read, in cells.
    x: [f64; 3],
    /// The lower corner of the cell whose corners `bits` holds (bit `c` for corner `c`,
    /// whose offset along axis `d` is bit `2 - d` of `c`).
    cell: [isize; 3],
    bits: u8,
}

impl<'a, 'm, T: Voxel> Interpolated<'a, 'm, T> {
    fn new(mask: &'a ArrayView3<'m, T>, spacing: [f64; 3]) -> Self {
        let (n0, n1, n2) = mask.dim();
        let inverse = spacing.map(|s| {
            let power_of_two = s.is_normal() && s.to_bits() & ((1u64 << 52) - 1) == 0;
            if power_of_two && s.recip().is_normal() {
                s.recip()
            } else {
                0.0
            }
        });
        // No cell has a corner at index -2: the first read always loads its corners.
        let shape = [n0 as isize, n1 as isize, n2 as isize];
        let all_inverse = inverse.iter().all(|&i| i > 0.0);
        let flat = mask.as_slice();
        Self { mask, flat, spacing, inverse, all_inverse, shape, x: [0.0; 3], cell: [-2; 3], bits: 0 }
    }

    /// The bits of the corners of `cell` (see `cell`), 0 outside the array.
    fn corners(&self, cell: [isize; 3]) -> u8 {
        let [_, n1, n2] = self.shape;
        let interior = (0..3).all(|d| cell[d] >= 0 && cell[d] + 1 < self.shape[d]);
        if let (Some(flat), true) = (self.flat, interior) {
            // Corner `c`'s offset: bit 2, 1, 0 of `c` steps along axis 0, 1, 2.
            let (s0, s1) = ((n1 * n2) as usize, n2 as usize);
            let base = cell[0] as usize * s0 + cell[1] as usize * s1 + cell[2] as usize;
            let near = &flat[base..base + s1 + 2];
            let far = &flat[base + s0..base + s0 + s1 + 2];
            let set = |v: T, c: u32| u8::from(v.is_set()) << c;
            return set(near[0], 0)
                | set(near[1], 1)
                | set(near[s1], 2)
                | set(near[s1 + 1], 3)
                | set(far[0], 4)
                | set(far[1], 5)
                | set(far[s1], 6)
                | set(far[s1 + 1], 7);
        }
        let mut bits = 0;
        for corner in 0..8 {
            let v: [isize; 3] = std::array::from_fn(|d| cell[d] + ((corner >> (2 - d)) & 1) as isize);
            if (0..3).all(|d| v[d] >= 0 && v[d] < self.shape[d])
                && self.mask[[v[0] as usize, v[1] as usize, v[2] as usize]].is_set()
            {
                bits |= 1 << corner;
            }
        }
        bits
    }

    /// Whether the interpolated mask is at least one half at `p` (physical units).
    fn inside(&mut self, p: [f64; 3]) -> bool {
        self.value(p) >= 0.5
    }

    /// The interpolated mask at `p` (physical units): 0 and 1 exactly in a cell whose
    /// corners are all clear and all set.
    fn value(&mut self, p: [f64; 3]) -> f64 {
        let x: [f64; 3] = if self.all_inverse {
            std::array::from_fn(|d| p[d] * self.inverse[d])
        } else {
            std::array::from_fn(|d| if self.inverse[d] > 0.0 { p[d] * self.inverse[d] } else { p[d] / self.spacing[d] })
        };
        self.x = x;
        if (0..3).any(|d| !(x[d] > -1.0 && x[d] < self.shape[d] as f64)) {
            self.cell = [-2; 3];
            return 0.0;
        }
        // `floor` of a number in (-1, n), inline.
        let lo: [f64; 3] = x.map(|x| {
            let t = x as i64 as f64;
            if t > x {
                t - 1.0
            } else {
                t
            }
        });
        let cell: [isize; 3] = lo.map(|l| l as isize);
        if cell[0] != self.cell[0] || cell[1] != self.cell[1] || cell[2] != self.cell[2] {
            self.cell = cell;
            self.bits = self.corners(cell);
        }
        match self.bits {
            0 => 0.0,
            u8::MAX => 1.0,
            bits => {
                // Corner `c`'s weight is `(w0 · w1) · w2`, `wd` the weight `1 - f` or `f`
                // of its offset along axis `d`, summed in the corners' order.
                let w: [[f64; 2]; 3] = std::array::from_fn(|d| {
                    let f = x[d] - lo[d];
                    [1.0 - f, f]
                });
                // A clear corner adds +0.0, which leaves the (non-negative) sum as it is.
                let mut sum = 0.0;
                for corner in 0..8 {
                    let weight = w[0][corner >> 2] * w[1][(corner >> 1) & 1] * w[2][corner & 1];
                    sum += if bits >> corner & 1 == 1 { weight } else { 0.0 };
                }
                sum
            }
        }
    }

    /// How many more points `x + j · dx` (`j = 1, 2, ...`, `dx` in cells) after the
    /// one last read lie in its cell when all of that cell's corners are set: inside,
    /// so a march need not read them. A margin of 10⁻⁶ of a cell keeps the count clear
    /// of the rounding of the points as the march computes them.
    fn steps_in_full_cell(&self, dx: [f64; 3]) -> usize {
        if self.bits != u8::MAX || self.cell == [-2; 3] {
            return 0;
        }
        const MARGIN: f64 = 1e-6;
        let mut room = f64::INFINITY;
        for d in 0..3 {
            let lo = self.cell[d] as f64;
            let r = if dx[d] > 0.0 {
                (lo + 1.0 - MARGIN - self.x[d]) / dx[d]
            } else if dx[d] < 0.0 {
                (self.x[d] - lo - MARGIN) / -dx[d]
            } else {
                f64::INFINITY
            };
            room = room.min(r);
        }
        // Whole steps only; at most a cell's worth at the march's step unless `dx` is tiny.
        room.clamp(0.0, 1e6) as usize
    }
}

/// Chords per axial plane (directions spread over half a turn) and axial planes. 12
/// directions rather than 16 take a quarter of the chords' cost off the output stage
/// (256³ bed, one thread: 1.97 → 1.54 s) and keep every family's radius MAPE within
/// ±0.13 % of 16's on the fidelity benchmark (tuning and held-out); 8 cost the tuning
/// capillaries and lattices 0.26 and 0.11 % (README, "Where we differ", 10).
const CHORD_DIRECTIONS: usize = 12;
const CHORD_PLANES: usize = 5;
/// March step in base cells, and bisection steps that narrow each crossing to
/// `STEP / 2^BISECTIONS` of a cell before the mask's value is interpolated linearly
/// across what is left (see [`extent`]).
const STEP: f64 = 0.25;
const BISECTIONS: usize = 2;
/// The quantile of the pooled chords that is the reference of the trim: the shortest
/// chords but a few, so that one chord cut short by the grid does not set it.
const TRIM_REFERENCE: f64 = 0.1;

/// The narrowest chord (the trim's reference), in coarsest cells, from which a round
/// plane keeps its chords past the trim: a vessel that wide is not engulfed by a blob of
/// voxel-scale noise.
const WIDE: f64 = 6.0;

/// Distance from `q` along the unit `w` to where the interpolated mask falls below
/// one half, at most `reach` (`q` itself is inside). Every point closer to `q` than
/// `clear` is known to be inside (see [`clear_of`]): the march starts past them.
///
/// The march finds the first of its points outside; `BISECTIONS` halvings narrow the
/// step that holds the crossing to a sixteenth of a cell, and the crossing is where the
/// line through the mask's values at that interval's ends meets one half. Along a line
/// the interpolated mask is a cubic within each cell, all but straight over a sixteenth
/// of a cell: 99 % of the crossings are placed within 10⁻³ of a cell (the midpoint of
/// five halvings, to 1/128, was off by up to 1/256), for two or three fewer reads of the
/// mask.
fn extent<T: Voxel>(
    mask: &mut Interpolated<'_, '_, T>,
    q: [f64; 3],
    w: [f64; 3],
    step: f64,
    reach: f64,
    clear: f64,
) -> f64 {
    let dx: [f64; 3] = std::array::from_fn(|d| step * w[d] / mask.spacing[d]);
    let steps = (reach / step).ceil() as usize;
    // The first point not known to be inside (a huge `clear` saturates: no point to read).
    let mut m = (clear / step).ceil().max(1.0) as usize;
    // The mask's value at the last point read and its index.
    let mut last = (usize::MAX, 0.0);
    // Each turn reads one point and moves past it and the points after it in the same
    // full cell (inside): at most `steps` turns.
    while m <= steps {
        let s = (m as f64 * step).min(reach);
        let mut at = |s: f64| mask.value(std::array::from_fn(|d| q[d] + s * w[d]));
        let here = at(s);
        if here < 0.5 {
            let lo = (m - 1) as f64 * step;
            let (mut inside, mut outside) = ((lo, None), (s, here));
            if last.0 == m - 1 {
                inside.1 = Some(last.1);
            }
            for _ in 0..BISECTIONS {
                let mid = 0.5 * (inside.0 + outside.0);
                let v = at(mid);
                if v >= 0.5 {
                    inside = (mid, Some(v));
                } else {
                    outside = (mid, v);
                }
            }
            let v_in = inside.1.unwrap_or_else(|| at(inside.0));
            // `v_in >= 0.5 > outside.1` (for `q` inside): the fraction lies in [0, 1).
            let f = if v_in > outside.1 { ((v_in - 0.5) / (v_in - outside.1)).clamp(0.0, 1.0) } else { 0.5 };
            return inside.0 + f * (outside.0 - inside.0);
        }
        last = (m, here);
        m += 1 + mask.steps_in_full_cell(dx);
    }
    reach
}

/// How far from `q` every point is inside the interpolated mask, by the distance
/// transform: `depth` is the distance from the centre of voxel `v` to the nearest
/// background voxel centre (voxels outside the array count as background), so every
/// voxel centre nearer than `depth` to `v` is set. A point within `depth - diag - |q - v|`
/// of `q` (`diag` a cell's diagonal) has all eight corners of its cell nearer than that,
/// all set: it is inside, whatever the weights. A margin of 10⁻³ of a cell (and 10⁻⁶
/// of the depth, for the transform's `f32`) keeps the bound clear of rounding. A
/// chord's march starts past these points and finds the same crossing: in a thick
/// vessel most of a chord is this far from the wall, and the march read it cell by cell.
fn clear_of(depth: f64, v: [isize; 3], q: [f64; 3], spacing: [f64; 3], c: f64) -> f64 {
    let centre: [f64; 3] = std::array::from_fn(|d| v[d] as f64 * spacing[d]);
    let off = sub(q, centre);
    depth - dot(spacing, spacing).sqrt() - dot(off, off).sqrt() - 1e-3 * c - 1e-6 * depth
}

/// The chord radius at `p` along the unit direction `t`, first guess `r0`: the section
/// radius times the `quantile` of the kept chord lengths across the vessel over the root
/// mean square of the middle planes' chords (see the module); `end` puts the planes on
/// the side `t` points to only. `None` when no chord starts inside. `field` is the
/// mask's distance transform (it only speeds the chords' march up).
#[allow(clippy::too_many_arguments)]
fn chord_radius<T: Voxel>(
    mask: &ArrayView3<'_, T>,
    field: &Field,
    spacing: [f64; 3],
    p: [f64; 3],
    t: [f64; 3],
    r0: f64,
    end: bool,
    quantile: f64,
) -> Option<f64> {
    let (c, h, reach) = sizes(spacing, r0);
    let coarse = coarsest(spacing);
    let step = STEP * c;
    let [u, v] = plane_basis(t);
    let mut interpolated = Interpolated::new(mask, spacing);
    // The chords' directions, the same in every plane.
    let turns: [(f64, f64); CHORD_DIRECTIONS] = std::array::from_fn(turn);
    let directions: [[f64; 3]; CHORD_DIRECTIONS] =
        turns.map(|(cos, sin)| std::array::from_fn(|d| cos * u[d] + sin * v[d]));
    // How much more coarsely than the finest spacing (the base cell `c`) each direction
    // is sampled: the width of a voxel along it beyond that of a cube of side `c`.
    let excess: [f64; CHORD_DIRECTIONS] =
        std::array::from_fn(|k| (0..3).map(|d| directions[k][d].abs() * (spacing[d] - c)).sum());
    let mut chords: Vec<Chord> = Vec::with_capacity(CHORD_DIRECTIONS * CHORD_PLANES);
    // The outline of the middle planes' chords (see `Outline`): the farthest reach from
    // the plane's centre along each half-direction, `+w` at `k`, `-w` at `k + CHORD_DIRECTIONS`.
    let mut bound = [f64::NEG_INFINITY; 2 * CHORD_DIRECTIONS];
    for j in 0..CHORD_PLANES {
        // Planes at -2h, -h, 0, h, 2h about the node, or h/2, 3h/2, ..., 9h/2 inside an
        // end; the middle three (the first three of an end) span the area's slab.
        let along = if end { (j as f64 + 0.5) * h } else { (j as f64 - 2.0) * h };
        let middle = if end { j < 3 } else { (1..=3).contains(&j) };
        let q0: [f64; 3] = std::array::from_fn(|d| p[d] + along * t[d]);
        // The voxel nearest the plane's centre, and its depth in the mask (physical).
        let v: [isize; 3] = std::array::from_fn(|d| (q0[d] / spacing[d]).round() as isize);
        let depth = field.at(v) * c;
        for (k, &w) in directions.iter().enumerate() {
            // A node up to half a cell off a thin vessel starts from the nearest
            // inside point of the chord's line within half a cell.
            let start = [0.0, 1.0, -1.0, 2.0, -2.0]
                .iter()
                .map(|m| m * 0.25 * c)
                .find(|&s| interpolated.inside(std::array::from_fn(|d| q0[d] + s * w[d])));
            let Some(s) = start else { continue };
            let q: [f64; 3] = std::array::from_fn(|d| q0[d] + s * w[d]);
            let back = w.map(|x| -x);
            let clear = clear_of(depth, v, q, spacing, c);
            let ahead = extent(&mut interpolated, q, w, step, reach, clear);
            let behind = extent(&mut interpolated, q, back, step, reach, clear);
            if middle {
                bound[k] = bound[k].max(s + ahead);
                bound[k + CHORD_DIRECTIONS] = bound[k + CHORD_DIRECTIONS].max(behind - s);
            }
            let (length, midpoint) = (ahead + behind, s + 0.5 * (ahead - behind));
            chords.push(Chord { length, middle, plane: j, direction: k, midpoint });
        }
    }
    let middle: Vec<f64> = chords.iter().filter(|x| x.middle).map(|x| x.length).collect();
    if middle.is_empty() {
        return None;
    }
    let rms = (middle.iter().map(|l| l * l).sum::<f64>() / middle.len() as f64).sqrt();
    // Chords longer than the reference by more than the coarsest cell cross something
    // the vessel does not hold (a bubble, a branch's mouth): they are left out. The
    // reference comes from the chords of the most finely sampled directions (within a
    // finest cell of the least excess; every chord on an isotropic grid): along a
    // coarse axis a chord is cut short by up to a voxel's excess width, and a section
    // that thick slices flatten (a vessel lying in the plane of a two-photon stack) would
    // otherwise lose all its wide chords to its short ones.
    let least = excess.iter().copied().fold(f64::INFINITY, f64::min);
    let mut fine: Vec<f64> = chords.iter().filter(|x| excess[x.direction] <= least + c).map(|x| x.length).collect();
    if fine.is_empty() {
        fine = chords.iter().map(|x| x.length).collect();
    }
    fine.sort_by(f64::total_cmp);
    let reference = quantile_of(&fine, TRIM_REFERENCE);
    let limit = reference + coarse;
    // A plane whose chords all agree within the coarsest cell is round: nothing sticks
    // out of it. When the vessel is wide (its narrowest chords `WIDE` coarsest cells or
    // more, past what a blob of voxel-scale noise engulfs), such a plane's chords are the
    // vessel's width there, however far they exceed the reference: a vessel that widens
    // along its length (an aneurysm, the carotid bulb) keeps them. The planes then differ
    // in width, and the typical chord is taken from the middle planes alone, the
    // population of the root mean square it is set against.
    let mut plane_limit = [limit; CHORD_PLANES];
    let mut widens = false;
    for (j, lim) in plane_limit.iter_mut().enumerate() {
        let (lo, hi) = chords
            .iter()
            .filter(|x| x.plane == j)
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| (lo.min(x.length), hi.max(x.length)));
        if hi > limit && hi - lo <= coarse && reference >= WIDE * coarse {
            *lim = hi;
            widens = true;
        }
    }
    let kept_of = |middle_only: bool| -> Vec<f64> {
        let mut kept: Vec<f64> = chords
            .iter()
            .filter(|x| (x.middle || !middle_only) && x.length <= plane_limit[x.plane])
            .map(|x| x.length)
            .collect();
        kept.sort_by(f64::total_cmp);
        kept
    };
    let mut kept = kept_of(widens);
    if kept.is_empty() {
        kept = kept_of(false);
    }
    let typical = quantile_of(&kept, quantile.clamp(0.0, 1.0));
    // A voxel's width along a half-direction is the margin: a vessel's own voxel centres
    // lie within about a cell of where its chords cross the wall.
    let bound: [f64; 2 * CHORD_DIRECTIONS] = std::array::from_fn(|m| {
        let b = bound[m] + c + excess[m % CHORD_DIRECTIONS];
        if b.is_finite() {
            b
        } else {
            f64::INFINITY
        }
    });
    let inner = bound.iter().copied().fold(f64::INFINITY, f64::min);
    let outline = Outline { origin: p, t, basis: [u, v], bound, inner: inner * inner };
    let kept_middle = chords.iter().filter(|x| x.middle && x.length <= plane_limit[x.plane]);
    let centre = chord_centre(kept_middle, &turns, [u, v], p);
    Some(section_radius(mask, spacing, p, t, r0, end, Some(&outline), Some(centre)) * typical / rms)
}

/// The `k`-th chord direction's coordinates `(cos a, sin a)` in its plane's basis,
/// `a = π k / CHORD_DIRECTIONS`: the directions spread over half a turn.
fn turn(k: usize) -> (f64, f64) {
    let a = std::f64::consts::PI * k as f64 / CHORD_DIRECTIONS as f64;
    (a.cos(), a.sin())
}

/// One chord across the vessel (see [`chord_radius`]).
struct Chord {
    /// Its length (physical units).
    length: f64,
    /// Whether it lies in one of the middle planes (the slab of the area).
    middle: bool,
    /// Its plane and its direction, by index.
    plane: usize,
    direction: usize,
    /// Where its middle lies along its direction from its plane's centre.
    midpoint: f64,
}

/// The section's centre as the `chords` see it, on the plane through `p` orthogonal to
/// the chords' planes: the point whose projections on the chords' lines lie nearest
/// (least squares) to the chords' midpoints. A round section centred at `c` has each
/// chord's midpoint at the projection of `c` on its line, whatever the node's offset.
/// `p` itself when the chords span no plane (fewer than two directions). `turns` are
/// the directions' coordinates in the plane's basis `u`, `v` ([`turn`]).
fn chord_centre<'a>(
    chords: impl Iterator<Item = &'a Chord>,
    turns: &[(f64, f64); CHORD_DIRECTIONS],
    [u, v]: [[f64; 3]; 2],
    p: [f64; 3],
) -> [f64; 3] {
    // The normal equations in the plane's basis.
    let (mut m, mut b) = ([0.0; 3], [0.0; 2]);
    for x in chords {
        let (cos, sin) = turns[x.direction];
        m = [m[0] + cos * cos, m[1] + cos * sin, m[2] + sin * sin];
        b = [b[0] + x.midpoint * cos, b[1] + x.midpoint * sin];
    }
    let det = m[0] * m[2] - m[1] * m[1];
    // Two directions 15° apart give 0.067; one direction (or none) gives 0.
    if det < 1e-3 {
        return p;
    }
    let (along_u, along_v) = ((m[2] * b[0] - m[1] * b[1]) / det, (m[0] * b[1] - m[1] * b[0]) / det);
    std::array::from_fn(|d| p[d] + along_u * u[d] + along_v * v[d])
}

/// The `q` quantile of the sorted, non-empty `x`, interpolated linearly.
fn quantile_of(x: &[f64], q: f64) -> f64 {
    let at = q * (x.len() - 1) as f64;
    let (i, f) = (at.floor() as usize, at - at.floor());
    let j = (i + 1).min(x.len() - 1);
    x[i] * (1.0 - f) + x[j] * f
}

/// The distance from `p` to the nearest background voxel centre within `reach`
/// (physical units), `reach` when there is none: the radius of the largest ball about
/// `p` itself (the EDT read at the point, not at a voxel). Voxels outside the array
/// count as background, as in the EDT: the nearest of them lie at index `-1` or `n`
/// along one axis, each other index the nearest integer to `p`'s.
fn inscribed_radius<T: Voxel>(mask: &ArrayView3<'_, T>, spacing: [f64; 3], p: [f64; 3], reach: f64) -> f64 {
    let (n0, n1, n2) = mask.dim();
    let shape = [n0, n1, n2];
    let mut best = reach * reach;
    let nearest: [f64; 3] = std::array::from_fn(|d| (p[d] / spacing[d]).round());
    for d in 0..3 {
        for face in [nearest[d].min(-1.0), nearest[d].max(shape[d] as f64)] {
            let distance2 = (0..3)
                .map(|a| {
                    let x = (if a == d { face } else { nearest[a] }) * spacing[a] - p[a];
                    x * x
                })
                .sum::<f64>();
            best = best.min(distance2);
        }
    }
    let range = |d: usize| {
        let lo = ((p[d] - reach) / spacing[d]).floor().max(0.0) as usize;
        let hi = ((p[d] + reach) / spacing[d]).ceil().min(shape[d] as f64 - 1.0).max(0.0) as usize;
        lo..=hi
    };
    for i in range(0) {
        for j in range(1) {
            for k in range(2) {
                if mask[[i, j, k]].is_set() {
                    continue;
                }
                let d = sub([i as f64 * spacing[0], j as f64 * spacing[1], k as f64 * spacing[2]], p);
                best = best.min(dot(d, d));
            }
        }
    }
    best.sqrt()
}

/// The radius of the ball of the foreground volume within reach of `p` (first guess
/// `r0`): an isolated node's blob. (A zero direction makes every point's offset
/// from the "line" its offset from `p`, so the disc is a ball.)
fn ball_radius<T: Voxel>(mask: &ArrayView3<'_, T>, spacing: [f64; 3], p: [f64; 3], r0: f64) -> f64 {
    let c = base_cell(spacing);
    // With `t = 0` every voxel is at the tent's middle: weight 1 per unit `half`.
    let (volume, _) = section_area(mask, spacing, p, [0.0; 3], (0.0, 1.0), 1.5 * r0 + 2.0 * c, None);
    (volume * 0.75 / std::f64::consts::PI).cbrt()
}

/// The radii of the output nodes `measure` selects: [`OUTPUT_RADII`] less `shift` (the
/// radius correction in physical units), floored at 0 (0 for the others). The one rule
/// for every output node, in a single run and in a chunked run's routing phase.
#[allow(clippy::too_many_arguments)]
pub fn output_radii<T: Voxel>(
    g: &Csr,
    positions: &[[f64; 3]],
    edt_radii: &[f64],
    measure: &(dyn Fn(usize) -> bool + Sync),
    mask: ArrayView3<'_, T>,
    field: &Field,
    spacing: [f64; 3],
    shift: f64,
) -> Vec<f64> {
    node_radii(OUTPUT_RADII, measure, g, positions, edt_radii, mask, field, spacing)
        .into_iter()
        .map(|r| (r - shift).max(0.0))
        .collect()
}

/// The radius of every node of the output graph `g` that `measure` selects (0 for the
/// others; positions in physical units), given each node's largest EDT value
/// `edt_radii` (physical), by `model`; `field` is the mask's distance transform
/// ([`Field::new`] of `mask` and `spacing`).
#[allow(clippy::too_many_arguments)]
pub fn node_radii<T: Voxel>(
    model: RadiusModel,
    measure: &(dyn Fn(usize) -> bool + Sync),
    g: &Csr,
    positions: &[[f64; 3]],
    edt_radii: &[f64],
    mask: ArrayView3<'_, T>,
    field: &Field,
    spacing: [f64; 3],
) -> Vec<f64> {
    let c = base_cell(spacing);
    let cap = 0.5 * dot(spacing, spacing).sqrt();
    (0..g.nodes())
        .into_par_iter()
        .map(|i| {
            if !measure(i) {
                return 0.0;
            }
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
            let Some(t) = t else { return inscribed_radius(&mask, spacing, p, r0 + cap) };
            let r = match quantile {
                None => section_radius(&mask, spacing, p, t, r0, end, None, None),
                Some(q) => chord_radius(&mask, field, spacing, p, t, r0, end, q).unwrap_or(r0),
            };
            r.min(r0 + cap)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    /// The trilinear interpolation of the mask at `p`, corner by corner (0 outside).
    fn interpolated(mask: &Array3<u8>, spacing: [f64; 3], p: [f64; 3]) -> f64 {
        let x: [f64; 3] = std::array::from_fn(|d| p[d] / spacing[d]);
        let shape = mask.shape();
        if (0..3).any(|d| !(x[d] > -1.0 && x[d] < shape[d] as f64)) {
            return 0.0;
        }
        let mut sum = 0.0;
        for corner in 0..8 {
            let bit = |d: usize| (corner >> (2 - d)) & 1;
            let v: [isize; 3] = std::array::from_fn(|d| x[d].floor() as isize + bit(d) as isize);
            if (0..3).all(|d| v[d] >= 0 && v[d] < shape[d] as isize) && mask[v.map(|i| i as usize)] == 1 {
                sum += (0..3)
                    .map(|d| if bit(d) == 1 { x[d] - x[d].floor() } else { 1.0 - (x[d] - x[d].floor()) })
                    .product::<f64>();
            }
        }
        sum
    }

    /// The section's sums over every voxel of the box about the node, as
    /// `section_area` took them before it read only the rows' stretches that meet the
    /// slab and the ball (the same terms in the same order).
    fn section_area_over_the_box(
        mask: &Array3<u8>,
        spacing: [f64; 3],
        p: [f64; 3],
        t: [f64; 3],
        (middle, half): Slab,
        reach: f64,
    ) -> (f64, [f64; 3]) {
        let shape = mask.shape();
        let extent = reach + middle.abs() + half;
        let range = |d: usize| {
            let lo = ((p[d] - extent) / spacing[d]).floor().max(0.0) as usize;
            let hi = ((p[d] + extent) / spacing[d]).ceil().min(shape[d] as f64 - 1.0).max(0.0) as usize;
            lo..=hi
        };
        let (mut weight, mut sum) = (0.0, [0.0; 3]);
        for i in range(0) {
            for j in range(1) {
                for k in range(2) {
                    if mask[[i, j, k]] == 0 {
                        continue;
                    }
                    let d = sub([i as f64 * spacing[0], j as f64 * spacing[1], k as f64 * spacing[2]], p);
                    let along = dot(d, t);
                    let w = 1.0 - (along - middle).abs() / half;
                    let off = [d[0] - along * t[0], d[1] - along * t[1], d[2] - along * t[2]];
                    if w > 0.0 && dot(off, off) <= reach * reach {
                        weight += w;
                        for a in 0..3 {
                            sum[a] += w * off[a];
                        }
                    }
                }
            }
        }
        let area = weight / half * spacing.iter().product::<f64>();
        (area, if weight > 0.0 { std::array::from_fn(|a| p[a] + sum[a] / weight) } else { p })
    }

    /// The section's area and centroid are those of the sums over the whole box, bit for
    /// bit: random masks (half set), nodes in and near the array, directions random and
    /// along the axes (a row parallel or orthogonal to the slab), the ball of an isolated
    /// node (no direction), full and end slabs, two spacings.
    #[test]
    fn the_section_reads_only_the_rows_that_meet_it_and_sums_as_the_whole_box() {
        let mut next = crate::test_unit_rng(987654321);
        for spacing in [[1.0; 3], [1.6, 1.0, 0.7]] {
            let mask = Array3::from_shape_simple_fn((14, 15, 16), || u8::from(next() < 0.5));
            for case in 0..600 {
                let p: [f64; 3] = std::array::from_fn(|d| (next() * 18.0 - 2.0) * spacing[d]);
                let t = match case % 5 {
                    0 => [0.0; 3],
                    1 => [0.0, 0.0, 1.0],
                    2 => [1.0, 0.0, 0.0],
                    _ => unit(std::array::from_fn(|_| next() - 0.5)).unwrap(),
                };
                let half = 0.5 + 3.0 * next();
                let slab = if case % 2 == 0 { (0.0, half) } else { (half, half) };
                let reach = 0.5 + 6.0 * next();
                let got = section_area(&mask.view(), spacing, p, t, slab, reach, None);
                let want = section_area_over_the_box(&mask, spacing, p, t, slab, reach);
                assert_eq!(got.0.to_bits(), want.0.to_bits(), "{p:?} {t:?} {slab:?} {reach}");
                assert_eq!(got.1.map(f64::to_bits), want.1.map(f64::to_bits), "{p:?} {t:?} {slab:?} {reach}");
            }
        }
    }

    /// The chords of a round section put its centre where it is, wherever the node sits
    /// and whichever directions kept their chords (each chord's midpoint is the
    /// projection of the centre on its line); a single direction spans no plane and
    /// leaves the node where it is.
    #[test]
    fn the_chords_midpoints_put_a_round_sections_centre_where_it_is() {
        let mut next = crate::test_unit_rng(2024);
        for _ in 0..200 {
            let p: [f64; 3] = std::array::from_fn(|_| 10.0 * next());
            let t = unit(std::array::from_fn(|_| next() - 0.5)).unwrap();
            let [u, v] = plane_basis(t);
            // The section's centre, up to two cells off the node in the plane.
            let (du, dv) = (4.0 * next() - 2.0, 4.0 * next() - 2.0);
            let centre: [f64; 3] = std::array::from_fn(|d| p[d] + du * u[d] + dv * v[d]);
            let chords: Vec<Chord> = (0..CHORD_DIRECTIONS)
                .filter(|_| next() < 0.6)
                .map(|k| {
                    let (cos, sin) = turn(k);
                    let w: [f64; 3] = std::array::from_fn(|d| cos * u[d] + sin * v[d]);
                    let midpoint = dot(sub(centre, p), w);
                    Chord { length: 6.0, middle: true, plane: 2, direction: k, midpoint }
                })
                .collect();
            let turns: [(f64, f64); CHORD_DIRECTIONS] = std::array::from_fn(turn);
            let got = chord_centre(chords.iter(), &turns, [u, v], p);
            let spans = chords.first().is_some_and(|f| chords.iter().any(|x| x.direction != f.direction));
            let want = if spans { centre } else { p };
            assert!((0..3).all(|d| (got[d] - want[d]).abs() < 1e-9), "{got:?} against {want:?}");
        }
    }

    /// A vessel along a grid axis has the same slice at every step along it, and its
    /// section reads exactly that slice's voxel area wherever the node sits between two
    /// slices: the slab's half-width is a whole number of the coarsest spacing, over
    /// which the tent's weights sum to the same at any offset. With the half-width of
    /// 1.5 voxels that a first guess of 3 gives, the area read 11 % high with the node
    /// on a slice and 11 % low halfway between two (radius +5.4 and -5.7 %).
    #[test]
    fn an_axis_aligned_vessel_reads_its_slice_at_any_offset_along_it() {
        for spacing in [[1.0; 3], [0.5, 1.0, 1.0]] {
            let (c1, c2) = (10.3, 9.9);
            let mask = Array3::from_shape_fn((40, 21, 21), |(_, j, k)| {
                let (y, x) = (j as f64 - c1, k as f64 - c2);
                u8::from(y * y + x * x <= 9.0)
            });
            let slice = mask.index_axis(ndarray::Axis(0), 0).iter().filter(|&&v| v == 1).count() as f64;
            let want = (slice * spacing[1] * spacing[2] / std::f64::consts::PI).sqrt();
            for delta in [0.0, 0.25, 0.5, 0.75] {
                let p = [(20.0 + delta) * spacing[0], c1, c2];
                for end in [false, true] {
                    let got = section_radius(&mask.view(), spacing, p, [1.0, 0.0, 0.0], 3.0, end, None, None);
                    assert!((got - want).abs() < 1e-9, "{spacing:?} offset {delta} end {end}: {got} against {want}");
                }
            }
        }
    }

    /// The chord reader answers as the interpolation summed corner by corner, in and
    /// out of the array, and a march that skips the points of full cells, and the
    /// points the distance transform puts inside, finds the same crossing as one that
    /// reads every point: random masks (70 % set, so that full, mixed and empty cells all
    /// occur) and noisy balls (deep inside, where the transform skips most of a chord,
    /// some cut by the array's faces), random points and chords, two spacings. The
    /// crossing lies where the interpolated mask meets one half: on the balls' walls,
    /// half of the crossings within 10⁻⁴ of a base cell of the crossing bisected to
    /// 10⁻¹² in the step the march found, 99 % within 10⁻³ (measured: 4 · 10⁻⁶ and
    /// 6 · 10⁻⁴; the midpoint of five halvings is off by up to 1/256, 4 · 10⁻³).
    #[test]
    fn the_chord_reader_and_its_march_answer_as_the_plain_interpolation() {
        let mut next = crate::test_unit_rng(12345);
        let (mut skipped, mut errors) = (0, vec![]);
        for (spacing, ball) in [([1.0; 3], false), ([1.6, 1.0, 0.7], false), ([1.0; 3], true), ([1.6, 1.0, 0.7], true)]
        {
            let c = base_cell(spacing);
            let dims = if ball { (12, 14, 17) } else { (7, 8, 9) };
            // A ball of radius 6 (physical) about a point near a corner of the array.
            let centre = [4.0, 7.0, 6.0].map(|x: f64| x * 1.6);
            let mask = Array3::from_shape_fn(dims, |(i, j, k)| {
                let x = [i as f64 * spacing[0], j as f64 * spacing[1], k as f64 * spacing[2]];
                let d = sub(x, centre);
                u8::from(if ball { dot(d, d).sqrt() < 6.0 + 2.0 * (next() - 0.5) } else { next() < 0.7 })
            });
            let view = mask.view();
            let field = Field::new(view, spacing).unwrap();
            let mut reader = Interpolated::new(&view, spacing);
            for _ in 0..4000 {
                let p: [f64; 3] = std::array::from_fn(|d| (next() * 11.0 - 1.5) * spacing[d]);
                let want = interpolated(&mask, spacing, p);
                assert!((reader.value(p) - want).abs() < 1e-12, "{p:?}");
                assert_eq!(reader.inside(p), want >= 0.5, "{p:?}");
            }
            for _ in 0..400 {
                let q: [f64; 3] = if ball {
                    std::array::from_fn(|d| centre[d] + (next() - 0.5) * 6.0)
                } else {
                    std::array::from_fn(|d| (next() * 8.0) * spacing[d])
                };
                let w = unit(std::array::from_fn(|_| next() - 0.5)).unwrap();
                let (step, reach): (f64, f64) = (0.25 * 0.7, 6.0);
                let v: [isize; 3] = std::array::from_fn(|d| (q[d] / spacing[d] + next() - 0.5).round() as isize);
                let clear = clear_of(field.at(v) * c, v, q, spacing, c);
                skipped += usize::from(clear > step);
                // Every point read, as the march did before it skipped any; then bisected
                // and interpolated, and bisected to the end.
                let value = |s: f64| interpolated(&mask, spacing, std::array::from_fn(|d| q[d] + s * w[d]));
                let first_out =
                    (1..=(reach / step).ceil() as usize).find(|&m| value((m as f64 * step).min(reach)) < 0.5);
                let bisect = |times: usize, m: usize| {
                    let (mut inside, mut outside) = ((m - 1) as f64 * step, (m as f64 * step).min(reach));
                    for _ in 0..times {
                        let mid = 0.5 * (inside + outside);
                        *if value(mid) >= 0.5 { &mut inside } else { &mut outside } = mid;
                    }
                    (inside, outside)
                };
                // A chord starts inside.
                if value(0.0) < 0.5 {
                    continue;
                }
                let plain = first_out.map_or(reach, |m| {
                    let (inside, outside) = bisect(BISECTIONS, m);
                    let (a, b) = (value(inside), value(outside));
                    inside + (a - 0.5) / (a - b) * (outside - inside)
                });
                let got = extent(&mut reader, q, w, step, reach, 0.0);
                assert!((got - plain).abs() < 1e-9 * c, "{q:?} {w:?}: {got} against {plain}");
                let skipping = extent(&mut reader, q, w, step, reach, clear);
                assert!((skipping - plain).abs() < 1e-9 * c, "{q:?} {w:?} {clear}: {skipping} against {plain}");
                if let (true, Some(m)) = (ball, first_out) {
                    let (inside, outside) = bisect(40, m);
                    errors.push((got - 0.5 * (inside + outside)).abs() / c);
                }
            }
        }
        assert!(skipped > 100, "{skipped} chords skipped points");
        assert!(errors.len() > 300, "{} crossings on the balls", errors.len());
        errors.sort_by(f64::total_cmp);
        let (median, p99) = (quantile_of(&errors, 0.5), quantile_of(&errors, 0.99));
        assert!(median < 1e-4 && p99 < 1e-3, "crossings off by {median} (median), {p99} (99 %) of a cell");
    }
}
