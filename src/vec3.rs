//! Small helpers of 3-vector arithmetic on `[f64; 3]` (physical positions and
//! directions), shared by the stages that do geometry on node positions.

/// `a - b`.
pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// The base cell `c`: the smallest voxel spacing, the unit of the stages' lengths.
pub(crate) fn base_cell(spacing: [f64; 3]) -> f64 {
    spacing.iter().cloned().fold(f64::INFINITY, f64::min)
}

/// The coarsest voxel spacing (the largest of the three).
pub(crate) fn coarsest(spacing: [f64; 3]) -> f64 {
    spacing.iter().copied().fold(0.0, f64::max)
}

/// The dot product.
pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The Euclidean length.
pub(crate) fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

/// The cross product.
pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

/// `d` scaled to length 1; `None` for the zero vector.
pub(crate) fn unit(d: [f64; 3]) -> Option<[f64; 3]> {
    let n = norm(d);
    (n > 0.0).then(|| [d[0] / n, d[1] / n, d[2] / n])
}

/// The projection of `p` onto the segment `a`–`b`: its parameter `t` in `[0, 1]` (0 for
/// a segment of length 0) and its distance from `p`.
pub(crate) fn projection(p: [f64; 3], a: [f64; 3], b: [f64; 3]) -> (f64, f64) {
    let ab = sub(b, a);
    let l2 = dot(ab, ab);
    let t = if l2 > 0.0 { (dot(sub(p, a), ab) / l2).clamp(0.0, 1.0) } else { 0.0 };
    let q: [f64; 3] = std::array::from_fn(|d| a[d] + t * ab[d]);
    (t, norm(sub(p, q)))
}
