//! Mask views, spacing checks, and the anisotropic exact Euclidean distance
//! transform (docs/method.md §1).

/// A mask voxel type: `bool` or an integer; non-zero means vessel.
pub trait Voxel: Copy + Send + Sync {
    /// True for a vessel voxel.
    fn is_set(self) -> bool;
}

impl Voxel for bool {
    fn is_set(self) -> bool {
        self
    }
}

macro_rules! int_voxel {
    ($($t:ty),*) => {$(
        impl Voxel for $t {
            fn is_set(self) -> bool {
                self != 0
            }
        }
    )*};
}
int_voxel!(u8, i8, u16, i16, u32, i32, u64, i64);

use crate::error::{Error, Result};
use ndarray::{ArrayView3, Axis};
use rayon::prelude::*;

/// Smallest supported voxel spacing, physical units. See [`MAX_SPACING`].
pub const MIN_SPACING: f64 = 1e-12;

/// Largest supported voxel spacing, physical units.
///
/// The range `[MIN_SPACING, MAX_SPACING]` is where no intermediate quantity overflows
/// or underflows. The tightest is the EDT, which stores squared physical distances in
/// `f32` (normal numbers from 1.2e-38 to 3.4e38): the smallest it stores is
/// `min(spacing)² ≥ 1e-24`, and the largest is bounded because every axis spans fewer
/// than 2²⁰ base cells (`c = min(spacing)`, the cell-key limit checked with the
/// spacing), so a squared distance is below `3 (2²⁰ c)² ≤ 3.3e36`. Everything else is
/// `f64` (positions, areas `∝ c²`, volumes `∝ c³ ≥ 1e-36`) or scale-free (the
/// row-normalised Laplacian weights, hence the normal matrix). Outside this range
/// radii became 0 or infinite, and above 1e154 the EDT's squares overflowed `f64`.
pub const MAX_SPACING: f64 = 1e12;

/// The error for a `spacing` outside the supported range (or not three numbers).
pub fn invalid_spacing(spacing: Vec<f64>) -> Error {
    Error::InvalidSpacing { spacing, range: [MIN_SPACING, MAX_SPACING] }
}

/// Check that `spacing` holds three finite numbers in [`MIN_SPACING`, `MAX_SPACING`].
pub fn check_spacing(spacing: [f64; 3]) -> Result<()> {
    if spacing.iter().all(|s| s.is_finite() && (MIN_SPACING..=MAX_SPACING).contains(s)) {
        Ok(())
    } else {
        Err(invalid_spacing(spacing.to_vec()))
    }
}

/// Where the foreground voxels of `mask` sit, row by row: the foreground voxels of row
/// `r = i * n1 + j` (the voxels `(i, j, ..)`) are nodes `starts[r]..starts[r + 1]`, in C
/// order, so `starts[n0 * n1]` is the foreground count. One cheap pass over the mask
/// (rows in parallel); 8 bytes per row of the box.
pub fn foreground_rows<T: Voxel>(mask: ArrayView3<'_, T>) -> Result<Vec<usize>> {
    let (n0, n1, _) = mask.dim();
    let mut starts = crate::memory::try_with_capacity(n0 * n1 + 1)?;
    starts.push(0);
    starts.par_extend((0..n0 * n1).into_par_iter().map(|r| {
        let row = mask.index_axis(Axis(0), r / n1);
        row.index_axis(Axis(0), r % n1).iter().filter(|v| v.is_set()).count()
    }));
    for r in 1..starts.len() {
        starts[r] += starts[r - 1];
    }
    Ok(starts)
}

/// `values` cut into the parts of consecutive rows, from their `starts` (as in
/// [`foreground_rows`], `starts[0]` being where `values` begins).
fn row_parts<'a, V>(mut values: &'a mut [V], starts: &[usize]) -> Vec<&'a mut [V]> {
    starts
        .windows(2)
        .map(|w| {
            let (head, tail) = std::mem::take(&mut values).split_at_mut(w[1] - w[0]);
            values = tail;
            head
        })
        .collect()
}

/// Squared anisotropic Euclidean distance transform of `mask`, in physical units²,
/// at its foreground voxels only, in C (node) order (`f32`; exact integers up to 2²⁴
/// voxel² on isotropic grids).
///
/// The value of a foreground voxel is the squared distance from its centre to the
/// nearest background voxel centre; voxels outside the array count as background
/// (docs/method.md §1), so every value is finite and ≥ `min(spacing)²`.
///
/// Exact and linear-time: a binary scan along axis 0 (forward, then backward, plane
/// by plane, each plane's rows in parallel), then, plane by plane (planes in
/// parallel), the lower envelope of parabolas (Felzenszwalb & Huttenlocher 2012)
/// along axes 1 and 2 in a plane-sized buffer. Memory follows the vessels: 4 bytes
/// per foreground voxel, plus [`foreground_rows`] and a few planes of scratch, never an
/// array the size of the box. [`Error::OutOfMemory`] if an array cannot be
/// allocated; [`edt_squared_rows`] takes rows already counted.
///
/// ```
/// use vesselflow::volume::edt_squared;
/// let mut m = ndarray::Array3::<u8>::zeros((1, 2, 5));
/// m.slice_mut(ndarray::s![0, 0, ..]).fill(1);
/// let d = edt_squared(m.view(), [1.0, 1.0, 2.0]).unwrap();
/// // Only the 5 foreground voxels; axes 0 and 1 put background 1.0 away.
/// assert_eq!(d, vec![1.0; 5]);
/// ```
pub fn edt_squared<T: Voxel>(mask: ArrayView3<'_, T>, spacing: [f64; 3]) -> Result<Vec<f32>> {
    edt_squared_rows(mask, &foreground_rows(mask)?, spacing)
}

/// [`edt_squared`] given the mask's [`foreground_rows`]; [`Error::OutOfMemory`] if
/// an array cannot be allocated.
pub fn edt_squared_rows<T: Voxel>(mask: ArrayView3<'_, T>, starts: &[usize], spacing: [f64; 3]) -> Result<Vec<f32>> {
    let (n0, n1, n2) = mask.dim();
    assert_eq!(starts.len(), n0 * n1 + 1, "foreground rows of another mask");
    let mut out = crate::memory::try_filled(starts[n0 * n1], 0f32)?;
    if out.is_empty() {
        return Ok(out);
    }
    let plane = n1 * n2;
    let plane_starts = |i: usize| &starts[i * n1..=(i + 1) * n1];
    // Axis 0: run lengths to the previous background plane (forward, kept at the
    // foreground voxels) then to the next one (backward), counting the virtual planes
    // -1 and n0 as background; a plane of counters carries each scan.
    let mut run = crate::memory::try_filled(plane, 0u32)?;
    for i in 0..n0 {
        // A run asked to stop ([`crate::cancel`]) ends here.
        if crate::cancel::requested() {
            return Err(Error::Interrupted);
        }
        let slice = mask.index_axis(Axis(0), i);
        let rows = plane_starts(i);
        let parts = row_parts(&mut out[rows[0]..rows[n1]], rows);
        run.par_chunks_mut(n2).zip(parts).enumerate().for_each(|(j, (f, o))| {
            let mut t = 0;
            for (fk, &v) in f.iter_mut().zip(slice.index_axis(Axis(0), j).iter()) {
                if v.is_set() {
                    *fk += 1;
                    o[t] = *fk as f32;
                    t += 1;
                } else {
                    *fk = 0;
                }
            }
        });
    }
    run.par_iter_mut().for_each(|x| *x = 0);
    let s0 = spacing[0];
    for i in (0..n0).rev() {
        if crate::cancel::requested() {
            return Err(Error::Interrupted);
        }
        let slice = mask.index_axis(Axis(0), i);
        let rows = plane_starts(i);
        let parts = row_parts(&mut out[rows[0]..rows[n1]], rows);
        run.par_chunks_mut(n2).zip(parts).enumerate().for_each(|(j, (nx, o))| {
            let mut t = 0;
            for (nk, &v) in nx.iter_mut().zip(slice.index_axis(Axis(0), j).iter()) {
                if v.is_set() {
                    *nk += 1;
                    let d = (o[t] as u32).min(*nk) as f64 * s0;
                    o[t] = (d * d) as f32;
                    t += 1;
                } else {
                    *nk = 0;
                }
            }
        });
    }
    drop(run);
    // Axes 1 and 2, plane by plane: the plane's values spread into a buffer (zero at
    // background), transformed there, and gathered back. The buffer is zero again
    // after each plane, since only foreground entries are ever written.
    let planes = row_parts(&mut out, &(0..=n0).map(|i| starts[i * n1]).collect::<Vec<_>>());
    planes.into_par_iter().enumerate().filter(|(_, part)| !part.is_empty()).for_each_init(
        || (Envelope::new(n1.max(n2)), vec![0f32; plane]),
        |(env, buffer), (i, part)| {
            // A run asked to stop gets a partial transform, which it discards.
            if crate::cancel::requested() {
                return;
            }
            let slice = mask.index_axis(Axis(0), i);
            let foreground = |j: usize| {
                slice
                    .index_axis(Axis(0), j)
                    .into_iter()
                    .enumerate()
                    .filter(|(_, v)| v.is_set())
                    .map(move |(k, _)| j * n2 + k)
            };
            let mut t = 0;
            for j in 0..n1 {
                for at in foreground(j) {
                    buffer[at] = part[t];
                    t += 1;
                }
            }
            for k in 0..n2 {
                env.line(buffer, k, n2, n1, spacing[1]);
            }
            for j in 0..n1 {
                env.line(buffer, j * n2, 1, n2, spacing[2]);
            }
            let mut t = 0;
            for j in 0..n1 {
                for at in foreground(j) {
                    part[t] = std::mem::take(&mut buffer[at]);
                    t += 1;
                }
            }
        },
    );
    Ok(out)
}

/// Scratch space of the 1-D lower-envelope transform.
struct Envelope {
    f: Vec<f64>,
    site: Vec<isize>,
    bound: Vec<f64>,
}

impl Envelope {
    fn new(n: usize) -> Self {
        Envelope { f: vec![0.0; n], site: vec![0; n + 2], bound: vec![0.0; n + 3] }
    }

    /// In-place 1-D squared distance transform of `data[start + q * stride]`,
    /// `q < n`, with sample spacing `s` and background sites at `q = -1` and `q = n`.
    fn line(&mut self, data: &mut [f32], start: usize, stride: usize, n: usize, s: f64) {
        let f = &mut self.f[..n];
        let mut all_zero = true;
        for (q, fq) in f.iter_mut().enumerate() {
            *fq = data[start + q * stride] as f64;
            all_zero &= *fq == 0.0;
        }
        if all_zero {
            return;
        }
        let value = |q: isize| if q < 0 || q >= n as isize { 0.0 } else { f[q as usize] };
        // Intersection abscissa (physical units) of the parabolas rooted at q and v < q.
        let meet = |q: isize, v: isize| {
            let (xq, xv) = (q as f64 * s, v as f64 * s);
            ((value(q) + xq * xq) - (value(v) + xv * xv)) / (2.0 * (xq - xv))
        };
        let (site, bound) = (&mut self.site, &mut self.bound);
        let mut k = 0usize;
        site[0] = -1;
        bound[0] = f64::NEG_INFINITY;
        bound[1] = f64::INFINITY;
        for q in 0..=n as isize {
            // Background voxels inside the line are sites like the virtual ones;
            // foreground ones only matter through their value.
            let mut x = meet(q, site[k]);
            while x <= bound[k] {
                k -= 1;
                x = meet(q, site[k]);
            }
            k += 1;
            site[k] = q;
            bound[k] = x;
            bound[k + 1] = f64::INFINITY;
        }
        let mut k = 0usize;
        for q in 0..n {
            let x = q as f64 * s;
            while bound[k + 1] < x {
                k += 1;
            }
            let dx = x - site[k] as f64 * s;
            let d = dx * dx + value(site[k]);
            let o = &mut data[start + q * stride];
            if *o != 0.0 {
                *o = d as f32;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    /// Brute force: nearest background centre, including the virtual outside shell.
    fn slow(mask: &Array3<u8>, s: [f64; 3]) -> Vec<f32> {
        let (n0, n1, n2) = mask.dim();
        let mut out = vec![];
        let bg = |i: isize, j: isize, k: isize| {
            i < 0
                || j < 0
                || k < 0
                || i >= n0 as isize
                || j >= n1 as isize
                || k >= n2 as isize
                || mask[[i as usize, j as usize, k as usize]] == 0
        };
        for ((i, j, k), &v) in mask.indexed_iter() {
            if v == 0 {
                out.push(0.0);
                continue;
            }
            let mut best = f64::INFINITY;
            for a in -1..=n0 as isize {
                for b in -1..=n1 as isize {
                    for c in -1..=n2 as isize {
                        if bg(a, b, c) {
                            let d = [
                                (a - i as isize) as f64 * s[0],
                                (b - j as isize) as f64 * s[1],
                                (c - k as isize) as f64 * s[2],
                            ];
                            best = best.min(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
                        }
                    }
                }
            }
            out.push(best as f32);
        }
        out
    }

    #[test]
    fn matches_brute_force_on_random_masks() {
        let mut rnd = crate::test_rng(12345);
        for trial in 0..20 {
            let shape = (1 + rnd(7) as usize, 1 + rnd(8) as usize, 1 + rnd(9) as usize);
            let fill = 50 + rnd(50);
            let m = Array3::from_shape_fn(shape, |_| u8::from(rnd(100) < fill));
            let s = if trial % 2 == 0 { [1.0, 1.0, 1.0] } else { [2.5, 0.7, 1.3] };
            let fast = edt_squared(m.view(), s).unwrap();
            // The sparse transform holds the foreground voxels only, in C order.
            let slow: Vec<f32> =
                slow(&m, s).into_iter().zip(m.iter()).filter(|(_, &v)| v != 0).map(|(d, _)| d).collect();
            assert_eq!(fast.len(), slow.len());
            for (a, b) in fast.iter().zip(&slow) {
                assert!((a - b).abs() <= 1e-4 * b.max(1.0), "{a} vs {b} shape {shape:?}");
            }
        }
    }

    /// The transform's allocation follows the foreground, not the box: a line of 40
    /// voxels in a 40³ box gives 40 values, and the row offsets one per box row.
    #[test]
    fn sparse_volumes_cost_their_foreground() {
        let mut m = Array3::<u8>::zeros((40, 40, 40));
        for k in 0..40 {
            m[[20, 17, k]] = 1;
        }
        let starts = foreground_rows(m.view()).unwrap();
        assert_eq!(starts.len(), 40 * 40 + 1);
        assert_eq!(starts[20 * 40 + 17], 0);
        assert_eq!(starts[20 * 40 + 18], 40);
        let d = edt_squared_rows(m.view(), &starts, [1.0; 3]).unwrap();
        assert_eq!(d.len(), 40);
        assert!(d.capacity() == 40);
        // Every voxel of a 1-voxel line is 1 from background, its ends too.
        assert_eq!(d, vec![1.0; 40]);
    }

    /// The same transform whatever the thread count (planes and rows in parallel).
    #[test]
    fn threads_do_not_change_the_transform() {
        let mut rnd = crate::test_rng(7);
        let m = Array3::from_shape_fn((23, 31, 17), |_| u8::from(rnd(100) < 80));
        let run = |threads| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| edt_squared(m.view(), [1.5, 1.0, 0.5]).unwrap())
        };
        let one = run(1);
        for threads in [2, 3, 8] {
            assert!(run(threads).iter().zip(&one).all(|(a, b)| a.to_bits() == b.to_bits()));
        }
    }

    #[test]
    fn strided_views_give_the_same_transform() {
        let m = Array3::from_shape_fn((6, 7, 8), |(i, j, k)| u8::from((i * 7 + j * 3 + k) % 5 != 0));
        let t = m.t(); // reversed axes, non-contiguous
        let owned = t.to_owned();
        assert_eq!(edt_squared(t, [1.0, 2.0, 3.0]).unwrap(), edt_squared(owned.view(), [1.0, 2.0, 3.0]).unwrap());
    }

    #[test]
    fn spacing_is_checked() {
        assert!(check_spacing([1.0, 1.0, 1.0]).is_ok());
        assert!(check_spacing([MIN_SPACING, 1.0, MAX_SPACING]).is_ok());
        for bad in [
            [0.0, 1.0, 1.0],
            [1.0, -1.0, 1.0],
            [1.0, 1.0, f64::NAN],
            [f64::INFINITY, 1.0, 1.0],
            [1e154, 1.0, 1.0],
            [1.0, 1e18, 1.0],
            [1.0, 1.0, 1e-23],
            [MIN_SPACING * 0.99, 1.0, 1.0],
            [1.0, MAX_SPACING * 1.01, 1.0],
            [-0.0, 1.0, 1.0],
        ] {
            let e = check_spacing(bad).unwrap_err();
            assert!(e.to_string().contains("[1e-12, 1e12]"), "{e}");
        }
    }
}
