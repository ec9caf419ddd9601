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
