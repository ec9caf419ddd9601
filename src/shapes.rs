//! Analytic test volumes and the built-in demo volume, rasterised from capsules
//! (segments with a radius) in physical units, so any spacing can be sampled.
//! A voxel is foreground when its centre lies within the radius of a segment.

use ndarray::Array3;
use rayon::prelude::*;

/// A straight tube from `a` to `b` (physical units, array axis order) with radius `r`
/// and round caps.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Capsule {
    pub a: [f64; 3],
    pub b: [f64; 3],
    pub r: f64,
}

/// Distance from `p` to the segment `a`–`b`.
pub fn segment_distance(p: [f64; 3], a: [f64; 3], b: [f64; 3]) -> f64 {
    let ab = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let ap = [p[0] - a[0], p[1] - a[1], p[2] - a[2]];
    let len2 = ab[0] * ab[0] + ab[1] * ab[1] + ab[2] * ab[2];
    let t = if len2 > 0.0 { ((ap[0] * ab[0] + ap[1] * ab[1] + ap[2] * ab[2]) / len2).clamp(0.0, 1.0) } else { 0.0 };
    let d = [ap[0] - t * ab[0], ap[1] - t * ab[1], ap[2] - t * ab[2]];
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

/// Rasterise capsules into a `shape` volume with voxel `spacing`.
pub fn capsules(shape: [usize; 3], spacing: [f64; 3], parts: &[Capsule]) -> Array3<u8> {
    let mut m = Array3::<u8>::zeros(shape);
    let plane = shape[1] * shape[2];
    if plane == 0 {
        return m;
    }
    let data = m.as_slice_mut().expect("fresh arrays are contiguous");
    data.par_chunks_mut(plane).enumerate().for_each(|(i, slab)| {
        for cap in parts {
            let lo = |d: usize| ((cap.a[d].min(cap.b[d]) - cap.r) / spacing[d]).floor().max(0.0) as usize;
            let hi = |d: usize| (((cap.a[d].max(cap.b[d]) + cap.r) / spacing[d]).ceil() as usize).min(shape[d] - 1);
            if i < lo(0) || i > hi(0) {
                continue;
            }
            for j in lo(1)..=hi(1) {
                for k in lo(2)..=hi(2) {
                    let p = [i as f64 * spacing[0], j as f64 * spacing[1], k as f64 * spacing[2]];
                    if segment_distance(p, cap.a, cap.b) <= cap.r {
                        slab[j * shape[2] + k] = 1;
                    }
                }
            }
        }
    });
    m
}

/// Straight cylinder of `radius` voxels along axis 0 through the centre of axes 1
/// and 2, open at both ends of the array. Its axis is `(*, (n1-1)/2, (n2-1)/2)`.
pub fn cylinder(shape: [usize; 3], radius: f64) -> Array3<u8> {
    let c = [(shape[1] as f64 - 1.0) / 2.0, (shape[2] as f64 - 1.0) / 2.0];
    let len = shape[0] as f64;
    capsules(shape, [1.0; 3], &[Capsule { a: [-radius - 1.0, c[0], c[1]], b: [len + radius, c[0], c[1]], r: radius }])
}

/// Solid torus with centre circle of radius `major` in the plane of axes 1 and 2,
/// centred in the array, tube radius `minor` (voxel units). Exact: a voxel is inside
/// when its distance to the centre circle is at most `minor`.
pub fn torus(shape: [usize; 3], major: f64, minor: f64) -> Array3<u8> {
    let c = shape.map(|n| (n as f64 - 1.0) / 2.0);
    Array3::from_shape_fn(shape, |(i, j, k)| {
        let (x, y, z) = (i as f64 - c[0], j as f64 - c[1], k as f64 - c[2]);
        let ring = (y * y + z * z).sqrt() - major;
        u8::from(ring * ring + x * x <= minor * minor)
    })
}

/// A Y bifurcation in the plane of axes 1 and 2: a trunk from `(c, 4, c)` to the
/// branch point `(c, n1/2, c)`, then two branches at ±35° to the array edge.
/// Returns the mask and the branch point.
pub fn y_bifurcation(shape: [usize; 3], radius: f64) -> (Array3<u8>, [f64; 3]) {
    let c0 = (shape[0] as f64 - 1.0) / 2.0;
    let c2 = (shape[2] as f64 - 1.0) / 2.0;
    let fork = [c0, (shape[1] / 2) as f64, c2];
    let len = shape[1] as f64 / 2.0;
    let t = 35f64.to_radians();
    let parts = [
        Capsule { a: [c0, 4.0, c2], b: fork, r: radius },
        Capsule { a: fork, b: [c0, fork[1] + len * t.cos(), c2 + len * t.sin()], r: radius },
        Capsule { a: fork, b: [c0, fork[1] + len * t.cos(), c2 - len * t.sin()], r: radius },
    ];
    (capsules(shape, [1.0; 3], &parts), fork)
}

/// The demo volume (48 × 112 × 96, isotropic): a trunk of radius 5 that splits into
/// two branches of radius 3.5, joined further on by a bridge of radius 2.5 (one
/// loop), each branch ending in a fork of radius 2.
pub fn demo_volume() -> Array3<u8> {
    let z = 23.5;
    let cap = |a: [f64; 2], b: [f64; 2], r: f64| Capsule { a: [z, a[0], a[1]], b: [z, b[0], b[1]], r };
    let parts = [
        cap([6.0, 48.0], [36.0, 48.0], 5.0),
        cap([36.0, 48.0], [70.0, 24.0], 3.5),
        cap([36.0, 48.0], [70.0, 72.0], 3.5),
        cap([58.0, 32.0], [58.0, 64.0], 2.5),
        cap([70.0, 24.0], [104.0, 12.0], 2.0),
        cap([70.0, 24.0], [100.0, 36.0], 2.0),
        cap([70.0, 72.0], [104.0, 84.0], 2.0),
        cap([70.0, 72.0], [100.0, 60.0], 2.0),
    ];
    capsules([48, 112, 96], [1.0; 3], &parts)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn capsule_rasterisation_matches_the_definition() {
        let cap = Capsule { a: [2.0, 3.0, 3.0], b: [8.0, 5.0, 4.0], r: 2.2 };
        let m = capsules([12, 10, 9], [1.0, 1.0, 1.0], &[cap]);
        for ((i, j, k), &v) in m.indexed_iter() {
            let inside = segment_distance([i as f64, j as f64, k as f64], cap.a, cap.b) <= cap.r;
            assert_eq!(v == 1, inside);
        }
    }

    #[test]
    fn cylinder_cross_section_is_a_disc() {
        let m = cylinder([5, 21, 21], 4.0);
        let slice_count = m.index_axis(ndarray::Axis(0), 2).iter().filter(|&&v| v == 1).count();
        // Lattice points in a disc of radius 4: 49.
        assert_eq!(slice_count, 49);
        assert!(m.iter().all(|&v| v <= 1));
    }
}
