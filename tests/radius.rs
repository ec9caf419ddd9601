//! Radii on analytic tubes (issue 15, item 3): straight tubes of known radius at
//! random orientations and sub-voxel axis offsets (fixed seed), drawn by both
//! rasterisation conventions (a voxel is set when its centre is inside; when at least
//! half of its volume is), at unit and anisotropic spacing. A node sits near the axis
//! (up to half a voxel off it, as the flow leaves it) with two neighbours two voxels
//! along the tube (each jittered the same way), and its EDT radius is the largest EDT
//! of the voxels around it (decimation's max-radius transfer). The table of bias and
//! mean absolute percentage error per radius band is printed (`--nocapture`).

use ndarray::Array3;
use vesselflow::grid::Csr;
use vesselflow::medial::Field;
use vesselflow::radius::{node_radii, RadiusModel};
use vesselflow::volume::edt_squared;

#[derive(Clone, Copy, Debug, PartialEq)]
enum Raster {
    /// `dist(centre, axis) <= r`.
    Centre,
    /// At least half of 4³ sub-samples inside.
    Partial,
}

fn rng(seed: u64) -> impl FnMut() -> f64 {
    let mut state = seed;
    move || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn line_distance(x: [f64; 3], o: [f64; 3], t: [f64; 3]) -> f64 {
    let d = sub(x, o);
    let along = dot(d, t);
    (dot(d, d) - along * along).max(0.0).sqrt()
}

/// An infinite tube of radius `r` along the unit `t` through `o` (physical units).
fn tube(shape: [usize; 3], spacing: [f64; 3], o: [f64; 3], t: [f64; 3], r: f64, raster: Raster) -> Array3<u8> {
    let half_diag = 0.5 * dot(spacing, spacing).sqrt();
    const SS: usize = 4;
    Array3::from_shape_fn(shape, |(i, j, k)| {
        let x = [i as f64 * spacing[0], j as f64 * spacing[1], k as f64 * spacing[2]];
        let d = line_distance(x, o, t);
        let inside = match raster {
            Raster::Centre => d <= r,
            Raster::Partial if (d - r).abs() > half_diag => d <= r,
            Raster::Partial => {
                let mut hits = 0;
                for a in 0..SS {
                    for b in 0..SS {
                        for c in 0..SS {
                            let s = |n: usize, d: usize| ((n as f64 + 0.5) / SS as f64 - 0.5) * spacing[d];
                            let y = [x[0] + s(a, 0), x[1] + s(b, 1), x[2] + s(c, 2)];
                            hits += usize::from(line_distance(y, o, t) <= r);
                        }
                    }
                }
                2 * hits >= SS * SS * SS
            }
        };
        u8::from(inside)
    })
}

struct Case {
    r: f64,
    /// Radii of the middle node by each model of `MODELS`.
    got: Vec<f64>,
}

const MODELS: [(&str, RadiusModel); 5] = [
    ("edt - 0.5", RadiusModel::Edt { offset: 0.5 }),
    ("edt", RadiusModel::Edt { offset: 0.0 }),
    ("section", RadiusModel::Section),
    ("chords q = 0.35", RadiusModel::Chords { quantile: 0.35 }),
    ("median chords", RadiusModel::MEDIAN_CHORDS),
];

/// A unit vector orthogonal to the unit `t`.
fn across(t: [f64; 3]) -> [f64; 3] {
    let e = if t[0].abs() < 0.9 { [1.0, 0.0, 0.0] } else { [0.0, 1.0, 0.0] };
    let along = dot(e, t);
    let u = sub(e, [along * t[0], along * t[1], along * t[2]]);
    let n = dot(u, u).sqrt();
    u.map(|x| x / n)
}

/// Sets every voxel whose centre lies within `radius` of `c` (physical units).
fn stamp_ball(mask: &mut Array3<u8>, spacing: [f64; 3], c: [f64; 3], radius: f64) {
    for ((i, j, k), v) in mask.indexed_iter_mut() {
        let d = sub([i as f64 * spacing[0], j as f64 * spacing[1], k as f64 * spacing[2]], c);
        if dot(d, d) <= radius * radius {
            *v = 1;
        }
    }
}

/// One tube of radius `r_vox` base cells, the node's radius by every model; with
/// `bubbles` balls of radius 2 cells (the bubble noise of `vesselflow.synth`) centred on
/// its wall at random angles within two cells of the node along the axis.
fn measure(next: &mut impl FnMut() -> f64, r_vox: f64, spacing: [f64; 3], raster: Raster, bubbles: usize) -> Case {
    let c = spacing.iter().cloned().fold(f64::INFINITY, f64::min);
    let r = r_vox * c;
    // A random direction (uniform on the sphere) and a box holding the section's slab
    // and disc around the centre whatever the direction.
    let z = 2.0 * next() - 1.0;
    let phi = std::f64::consts::TAU * next();
    let t = [z, (1.0 - z * z).sqrt() * phi.cos(), (1.0 - z * z).sqrt() * phi.sin()];
    let half = 3.0 * r + 6.0 * c;
    let shape: [usize; 3] = std::array::from_fn(|d| (2.0 * half / spacing[d]).ceil() as usize + 1);
    let o: [f64; 3] = std::array::from_fn(|d| (shape[d] / 2) as f64 * spacing[d] + (next() - 0.5) * spacing[d]);
    let mut mask = tube(shape, spacing, o, t, r, raster);
    let u = across(t);
    let w = [t[1] * u[2] - t[2] * u[1], t[2] * u[0] - t[0] * u[2], t[0] * u[1] - t[1] * u[0]];
    for _ in 0..bubbles {
        let (s, a) = ((4.0 * next() - 2.0) * c, std::f64::consts::TAU * next());
        let centre = std::array::from_fn(|d| o[d] + s * t[d] + r * (a.cos() * u[d] + a.sin() * w[d]));
        stamp_ball(&mut mask, spacing, centre, 2.0 * c);
    }
    // Node 1 near the axis at `o`, nodes 0 and 2 two cells along it, each up to half a
    // cell off the axis in a random direction.
    let jitter = |next: &mut dyn FnMut() -> f64, p: [f64; 3]| -> [f64; 3] {
        let q: [f64; 3] = std::array::from_fn(|_| next() - 0.5);
        let along = dot(q, t);
        let off = sub(q, [along * t[0], along * t[1], along * t[2]]);
        let n = dot(off, off).sqrt().max(1e-12);
        let m = 0.5 * c * next();
        std::array::from_fn(|d| p[d] + off[d] / n * m)
    };
    let positions: Vec<[f64; 3]> =
        [-2.0, 0.0, 2.0].iter().map(|s| jitter(next, std::array::from_fn(|d| o[d] + s * c * t[d]))).collect();
    // The largest EDT among the voxels within one voxel of the node (the cluster).
    let edt = edt_squared(mask.view(), spacing).unwrap();
    let mut it = edt.iter();
    let mut dist = Array3::<f64>::zeros(mask.dim());
    for (v, m) in dist.iter_mut().zip(mask.iter()) {
        if *m != 0 {
            *v = (*it.next().unwrap() as f64).sqrt();
        }
    }
    let p = positions[1];
    let centre: [isize; 3] = std::array::from_fn(|d| (p[d] / spacing[d]).round() as isize);
    let mut r_edt = 0.0f64;
    for a in -1..=1 {
        for b in -1..=1 {
            for e in -1..=1 {
                let v = [centre[0] + a, centre[1] + b, centre[2] + e].map(|x| x as usize);
                r_edt = r_edt.max(dist[v]);
            }
        }
    }
    let g = Csr::from_sorted_edges(3, &[(0, 1), (1, 2)]);
    let field = Field::new(mask.view(), spacing).unwrap();
    let got = MODELS
        .iter()
        .map(|&(_, model)| {
            node_radii(model, &|_| true, &g, &positions, &[r_edt; 3], mask.view(), &field, spacing)[1] / c
        })
        .collect();
    Case { r: r_vox, got }
}

/// `(bias %, MAPE %)` of model `m` over the cases.
fn errors(cases: &[&Case], m: usize) -> (f64, f64) {
    let rel: Vec<f64> = cases.iter().map(|c| (c.got[m] - c.r) / c.r).collect();
    let n = rel.len() as f64;
    (100.0 * rel.iter().sum::<f64>() / n, 100.0 * rel.iter().map(|e| e.abs()).sum::<f64>() / n)
}

const BANDS: [(f64, f64); 4] = [(1.0, 2.0), (2.0, 3.0), (3.0, 5.0), (5.0, 10.0)];

/// Bias and MAPE per band (rows) and model (columns) for one convention and spacing.
fn table(raster: Raster, spacing: [f64; 3], per_band: usize, seed: u64) -> Vec<Vec<(f64, f64)>> {
    let mut next = rng(seed);
    let mut cases = Vec::new();
    for &(lo, hi) in &BANDS {
        for _ in 0..per_band {
            let r = lo + (hi - lo) * next();
            cases.push(measure(&mut next, r, spacing, raster, 0));
        }
    }
    eprintln!("\n{raster:?} rasterisation, spacing {spacing:?}: bias % / MAPE % of the node radius");
    eprintln!("| r (voxels) | {} |", MODELS.map(|m| m.0).join(" | "));
    BANDS
        .iter()
        .map(|&(lo, hi)| {
            let band: Vec<&Case> = cases.iter().filter(|c| c.r >= lo && c.r < hi).collect();
            let row: Vec<(f64, f64)> = (0..MODELS.len()).map(|m| errors(&band, m)).collect();
            let cells: Vec<String> = row.iter().map(|(b, e)| format!("{b:+.1} / {e:.1}")).collect();
            eprintln!("| {lo}–{hi} | {} |", cells.join(" | "));
            row
        })
        .collect()
}

/// The targets of issue 15: |bias| ≤ 3 % and MAPE ≤ 5 % for r = 2…10, both ≤ 10 % for
/// r = 1–2, by the section model and by the median chords (the default), under both
/// conventions and at anisotropic spacing. The EDT model with METHOD.md's half-voxel
/// offset misses them (too low); so does a lower chord quantile (0.35) on thin
/// partial-volume tubes, which is why the default is the median.
#[test]
fn section_and_chord_radii_are_right_across_scales_conventions_and_spacings() {
    let section = MODELS.iter().position(|m| m.0 == "section").unwrap();
    let median = MODELS.iter().position(|m| m.0 == "median chords").unwrap();
    let old = MODELS.iter().position(|m| m.0 == "edt - 0.5").unwrap();
    for (k, spacing) in [[1.0; 3], [1.6, 1.0, 1.2]].into_iter().enumerate() {
        for (j, raster) in [Raster::Centre, Raster::Partial].into_iter().enumerate() {
            let rows = table(raster, spacing, 24, 15 + 2 * k as u64 + j as u64);
            for (band, row) in BANDS.iter().zip(&rows) {
                for m in [section, median] {
                    let (bias, mape) = row[m];
                    let (b_max, m_max) = if band.0 < 2.0 { (10.0, 10.0) } else { (3.0, 5.0) };
                    let name = MODELS[m].0;
                    assert!(
                        bias.abs() <= b_max && mape <= m_max,
                        "{name} {raster:?} {spacing:?} r {band:?}: {bias} / {mape}"
                    );
                }
            }
            // The old model is biased low by more than the target in the thin bands.
            assert!(rows[1][old].0 < -5.0, "{raster:?} {spacing:?}: {:?}", rows[1][old]);
        }
    }
}

/// Bubbles glued to the wall (the noisy forests' radii were 17 % and 37 % high at D1 and
/// D2 by the section model): two balls of radius 2 cells on the wall of tubes of radius
/// 3 to 8 within two cells of the node. The section area counts them (+4.2 %); the median
/// chord takes back most of that (+1.5 %), since a chord through a bubble is long at
/// one end only, a bubble lengthens a minority of them and the trim drops those.
#[test]
fn bubbles_glued_to_the_wall_do_not_widen_the_vessel() {
    let section = MODELS.iter().position(|m| m.0 == "section").unwrap();
    let median = MODELS.iter().position(|m| m.0 == "median chords").unwrap();
    let mut next = rng(7);
    let cases: Vec<Case> = (0..24)
        .map(|k| {
            let raster = if k % 2 == 0 { Raster::Centre } else { Raster::Partial };
            let r = 3.0 + 5.0 * next();
            measure(&mut next, r, [1.0; 3], raster, 2)
        })
        .collect();
    let all: Vec<&Case> = cases.iter().collect();
    let (old_bias, old_mape) = errors(&all, section);
    let (bias, mape) = errors(&all, median);
    eprintln!("bubbles: section {old_bias:+.1} / {old_mape:.1}, median chords {bias:+.1} / {mape:.1}");
    assert!(old_bias > 3.5, "section: {old_bias} / {old_mape}");
    assert!(bias.abs() <= 2.5 && mape <= 2.5, "median chords: {bias} / {mape}");
}

/// A parallel vessel across a gap of background (a dense capillary bed, an artery beside
/// its vein): tubes of radius 2.5 to 4 cells at random orientations, each with a
/// neighbour of the same radius whose wall lies 2 to 3 cells from its own. No chord
/// crosses the gap, but the section's disc reaches into the neighbour, and the area
/// counted its voxels: the section model reads the pair 10 % or more above the lone
/// tube (the median chords did too, +18 % at two background voxels, before the area was
/// bounded by the chords' outline). The median chords read the tube as if it were alone.
#[test]
fn a_parallel_vessel_across_a_gap_does_not_widen_the_vessel() {
    let section = MODELS.iter().position(|m| m.0 == "section").unwrap();
    let median = MODELS.iter().position(|m| m.0 == "median chords").unwrap();
    let spacing = [1.0; 3];
    let mut next = rng(23);
    let (mut worst, mut least_section) = (0.0f64, f64::INFINITY);
    for _ in 0..12 {
        let (r, gap) = (2.5 + 1.5 * next(), 2.0 + next());
        let z = 2.0 * next() - 1.0;
        let phi = std::f64::consts::TAU * next();
        let t = [z, (1.0 - z * z).sqrt() * phi.cos(), (1.0 - z * z).sqrt() * phi.sin()];
        let n = (2.0 * (4.0 * r + gap + 8.0)).ceil() as usize;
        let o: [f64; 3] = std::array::from_fn(|_| (n / 2) as f64 + next() - 0.5);
        let u = across(t);
        let o2: [f64; 3] = std::array::from_fn(|d| o[d] + (2.0 * r + gap) * u[d]);
        let alone = tube([n; 3], spacing, o, t, r, Raster::Partial);
        let other = tube([n; 3], spacing, o2, t, r, Raster::Partial);
        let pair = Array3::from_shape_fn((n, n, n), |v| alone[v] | other[v]);
        let positions: Vec<[f64; 3]> =
            [-2.0, 0.0, 2.0].iter().map(|s| std::array::from_fn(|d| o[d] + s * t[d])).collect();
        let g = Csr::from_sorted_edges(3, &[(0, 1), (1, 2)]);
        let radius = |mask: &Array3<u8>, m: usize| {
            let field = Field::new(mask.view(), spacing).unwrap();
            node_radii(MODELS[m].1, &|_| true, &g, &positions, &[r + 0.5; 3], mask.view(), &field, spacing)[1]
        };
        let excess = |m: usize| radius(&pair, m) / radius(&alone, m) - 1.0;
        worst = worst.max(excess(median).abs());
        least_section = least_section.min(excess(section));
    }
    eprintln!(
        "parallel vessel: median chords within {:.1} % of the lone tube, section +{:.1} % or more",
        100.0 * worst,
        100.0 * least_section
    );
    assert!(least_section > 0.05, "the neighbour lies outside the section's disc: {least_section}");
    assert!(worst <= 0.01, "median chords {worst}");
}

/// A vessel that widens along its length (a fusiform aneurysm, the carotid bulb): the
/// radius rises from 5 to 10 cells and back over 20 cells along an oblique axis
/// (`r(s) = 7.5 + 2.5 cos(π s / 10)`), drawn by voxel centres. The five planes of chords
/// span about one radius each way, so at the peak the outer planes are half as wide as
/// the middle one; the trim took their width as the reference and left the middle
/// planes' chords out: 5.71 at the peak, 5.25 and 4.73 on the flanks (−43, −37, −30 %).
/// A round plane of a vessel this wide keeps its chords: 9.79, 7.83, 6.78 (−2, −5, +1 %;
/// on the flanks the slab, a radius long, averages a steep slope).
#[test]
fn a_vessel_that_widens_along_its_length_keeps_its_width() {
    let spacing = [1.0; 3];
    let t = {
        let t = [0.9, 0.3, 0.2];
        let n = dot(t, t).sqrt();
        t.map(|x| x / n)
    };
    let radius = |s: f64| if s.abs() < 10.0 { 7.5 + 2.5 * (std::f64::consts::PI * s / 10.0).cos() } else { 5.0 };
    let n = 48;
    let o = [24.3, 23.8, 24.1];
    let mask = Array3::from_shape_fn((n, n, n), |(i, j, k)| {
        let x = [i as f64, j as f64, k as f64];
        let along = dot(sub(x, o), t);
        u8::from(line_distance(x, o, t) <= radius(along))
    });
    let field = Field::new(mask.view(), spacing).unwrap();
    for s in [0.0, 4.0, -6.0] {
        let positions: Vec<[f64; 3]> =
            [s - 2.0, s, s + 2.0].iter().map(|a| std::array::from_fn(|d| o[d] + a * t[d])).collect();
        let g = Csr::from_sorted_edges(3, &[(0, 1), (1, 2)]);
        let r0 = radius(s) + 0.5;
        let model = RadiusModel::MEDIAN_CHORDS;
        let got = node_radii(model, &|_| true, &g, &positions, &[r0; 3], mask.view(), &field, spacing)[1];
        let want = radius(s);
        eprintln!("widening vessel at {s:+}: radius {got:.2}, truth {want:.2}");
        assert!((got / want - 1.0).abs() <= 0.06, "at {s}: {got} against {want}");
    }
}

/// Bubbles as large as the vessel (the noisy forests' thin vessels, r = 1.5 to 3 cells,
/// with balls of radius 2 cells): two on the wall within two cells of the node lengthen
/// the chords of every plane near them, and the median of all chords with them. The
/// trim (chords longer than the pool's 10 % quantile by more than a cell are left out)
/// keeps the chords of the planes a radius or two along the vessel, past the bubbles:
/// section +24.5 %, median chords +5.5 % (untrimmed, the median of three planes read
/// about +19 % on the same kind of tubes in a numpy prototype).
#[test]
fn bubbles_as_large_as_a_thin_vessel_are_trimmed() {
    let section = MODELS.iter().position(|m| m.0 == "section").unwrap();
    let median = MODELS.iter().position(|m| m.0 == "median chords").unwrap();
    let mut next = rng(11);
    let cases: Vec<Case> = (0..32)
        .map(|k| {
            let raster = if k % 2 == 0 { Raster::Centre } else { Raster::Partial };
            let r = 1.5 + 1.5 * next();
            measure(&mut next, r, [1.0; 3], raster, 2)
        })
        .collect();
    let all: Vec<&Case> = cases.iter().collect();
    let (old_bias, old_mape) = errors(&all, section);
    let (bias, mape) = errors(&all, median);
    eprintln!("thin bubbles: section {old_bias:+.1} / {old_mape:.1}, median chords {bias:+.1} / {mape:.1}");
    assert!(old_bias > 10.0, "section: {old_bias} / {old_mape}");
    assert!(bias.abs() <= 8.0 && mape <= 9.0, "median chords: {bias} / {mape}");
}

/// A junction takes the inscribed radius at the node, not the largest EDT of its cluster
/// (which decimation hands it, and which lies where the vessels' walls part): at the
/// crossing of two orthogonal tubes of radius 3, given a cluster EDT of 6, the node gets
/// 3 within half a cell (the nearest background centre across the tubes).
#[test]
fn a_junction_takes_its_inscribed_radius() {
    let r = 3.0;
    let n = 25;
    let c = 12.3;
    let mask = Array3::from_shape_fn((n, n, n), |(i, j, k)| {
        let x = [i as f64 - c, j as f64 - c, k as f64 - c];
        let near = |a: usize, b: usize| (x[a] * x[a] + x[b] * x[b]).sqrt() <= r;
        u8::from(near(1, 2) || near(0, 2))
    });
    let positions = vec![[c, c, c], [c - 6.0, c, c], [c + 6.0, c, c], [c, c + 6.0, c]];
    let g = Csr::from_sorted_edges(4, &[(0, 1), (0, 2), (0, 3)]);
    let field = Field::new(mask.view(), [1.0; 3]).unwrap();
    for (name, model) in MODELS.iter().skip(2) {
        let got = node_radii(*model, &|_| true, &g, &positions, &[6.0, r, r, r], mask.view(), &field, [1.0; 3])[0];
        assert!((got - r).abs() <= 0.5, "{name}: junction radius {got}");
    }
}

/// Outside the array is background (the EDT's rule): a junction near the array's face
/// takes the distance to the nearest voxel centre past the face, at any spacing. In a
/// block that is all vessel, the node one voxel in from face 0 of axis 0, 2.3 voxels from
/// face 0 of axis 1 (spacing 2 × 1 × 1.5): the nearest background centres are those at
/// index −1 along axis 1, 3.3 away (axis 0's are 4 away). Counting only the background
/// voxels inside the array there is none, and the node took its reach (EDT + half a
/// voxel diagonal).
#[test]
fn a_junction_near_the_array_face_takes_the_distance_to_the_face() {
    let mask = Array3::<u8>::from_elem((10, 12, 12), 1);
    // (spacing, node, its voxel's EDT, the radius)
    for (spacing, p, edt, want) in [([1.0; 3], [1.0, 6.0, 6.0], 2.0, 2.0), ([2.0, 1.0, 1.5], [2.0, 2.3, 7.5], 3.0, 3.3)]
    {
        let positions = vec![p, [p[0] + 4.0, p[1], p[2]], [p[0], p[1] + 4.0, p[2]], [p[0], p[1], p[2] + 4.0]];
        let g = Csr::from_sorted_edges(4, &[(0, 1), (0, 2), (0, 3)]);
        let edt = [edt; 4];
        let field = Field::new(mask.view(), spacing).unwrap();
        for (name, model) in MODELS.iter().skip(2) {
            let got = node_radii(*model, &|_| true, &g, &positions, &edt, mask.view(), &field, spacing)[0];
            assert!((got - want).abs() < 1e-9, "{name} {spacing:?}: junction radius {got}, want {want}");
        }
    }
}

/// A vessel lying in the plane of a two-photon stack (spacing 5 × 0.6 × 0.6) as wide
/// as a slice is thick or wider shows in one slice only: its section is a band 5 thick
/// and `w` wide (the node's first guess is its EDT, 5). The chord radius stays near the
/// band's area-equivalent radius `sqrt(5 w / π)`. Before the trim took its reference
/// from the most finely sampled directions, the short chords across the slice set it
/// and a band 10.2 wide lost all its wide chords: radius 2.92 (area-equivalent 4.03),
/// below the 3.60 of a band 7.8 wide (3.52).
#[test]
fn a_vessel_flattened_by_thick_slices_keeps_its_width() {
    let spacing = [5.0, 0.6, 0.6];
    let radius = |width: usize| {
        let (n, mid) = (60, 30);
        let mask = Array3::from_shape_fn((5, n, n), |(i, _, k)| u8::from(i == 2 && k.abs_diff(mid) <= width / 2));
        let p = |j: f64| [10.0, j * spacing[1], mid as f64 * spacing[2]];
        let positions = vec![p(30.0), p(26.0), p(34.0)];
        let g = Csr::from_sorted_edges(3, &[(0, 1), (0, 2)]);
        let field = Field::new(mask.view(), spacing).unwrap();
        let model = RadiusModel::MEDIAN_CHORDS;
        node_radii(model, &|_| true, &g, &positions, &[5.0; 3], mask.view(), &field, spacing)[0]
    };
    for width in [13, 17] {
        let r = radius(width);
        let area = (spacing[0] * width as f64 * spacing[2] / std::f64::consts::PI).sqrt();
        eprintln!("flattened band {width} voxels wide: radius {r:.2}, area-equivalent {area:.2}");
        assert!(r >= 0.85 * area && r <= 1.1 * area, "band {width} wide: radius {r}, area-equivalent {area}");
    }
}
