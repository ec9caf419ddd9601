//! The node graph packed while a contraction iteration's solve runs (not in the paper;
//! a memory measure, see `pipeline::contract_step_mapped`).
//!
//! The solve is the run's peak: the assembled `M` and the four conjugate-gradient
//! vectors are alive, and so is the node graph the decimation needs after it, which the
//! solve itself never reads. Packed losslessly it takes about a third of its size:
//! - the CSR as varints, stretch by stretch of [`ROW_BLOCK`] rows: per row its degree,
//!   then each neighbour as the difference from the one before (the first from the row
//!   itself), zigzag-signed, in LEB128 varints: neighbours on a grid are a row, a
//!   plane's row or a plane apart, one to three bytes, against 4 bytes a target and 8
//!   an offset;
//! - the components as the varint difference from the node before (mostly 0);
//! - the radii as their `f32` squares when every one comes back bit for bit as the
//!   square root (true of the grid's radii, square roots of the `f32` squared
//!   distance transform, and of the decimation's, each one of them), else as they are.
//!
//! Unpacking gives the same arrays, bit for bit. Each kind of varint sits in one
//! allocation ([`pack`]): a peak RSS that varies from run to run otherwise.

use crate::grid::{filled, Csr, ROW_BLOCK};
use rayon::prelude::*;

/// Bytes of `v` as an LEB128 varint.
fn varint_len(v: u64) -> usize {
    (64 - (v | 1).leading_zeros() as usize).div_ceil(7)
}

/// Write `v` as an LEB128 varint at `at`, moving `at` past it.
fn put(out: &mut [u8], at: &mut usize, mut v: u64) {
    while v >= 0x80 {
        out[*at] = v as u8 | 0x80;
        *at += 1;
        v >>= 7;
    }
    out[*at] = v as u8;
    *at += 1;
}

/// Varints of `stretches` stretches in one allocation (many small ones, made on the
/// worker threads, would scatter over the allocator's arenas and keep pages the next
/// large arrays cannot use): `bytes(s)` counts stretch `s`'s bytes, `write(s, out)`
/// writes them. Returns the bytes and where each stretch starts (and the end).
fn pack(
    stretches: usize,
    bytes: impl Fn(usize) -> usize + Sync,
    write: impl Fn(usize, &mut [u8]) + Sync,
) -> (Vec<u8>, Vec<usize>) {
    let sizes: Vec<usize> = (0..stretches).into_par_iter().map(&bytes).collect();
    let mut starts = Vec::with_capacity(stretches + 1);
    starts.push(0);
    for &b in &sizes {
        starts.push(starts[starts.len() - 1] + b);
    }
    let mut out = filled(starts[stretches], 0u8);
    let mut parts = Vec::with_capacity(stretches);
    let mut rest = &mut out[..];
    for &b in &sizes {
        let (here, after) = rest.split_at_mut(b);
        parts.push(here);
        rest = after;
    }
    parts.into_par_iter().enumerate().for_each(|(s, part)| write(s, part));
    (out, starts)
}

/// The varint at `at` (at most 10 bytes), moving `at` past it.
fn get(bytes: &[u8], at: &mut usize) -> u64 {
    let mut v = 0u64;
    for shift in (0..64).step_by(7) {
        let b = bytes[*at];
        *at += 1;
        v |= u64::from(b & 0x7f) << shift;
        if b < 0x80 {
            break;
        }
    }
    v
}

/// `d` as an unsigned varint value: 0, -1, 1, -2, ... → 0, 1, 2, 3, ...
fn zigzag(d: i64) -> u64 {
    ((d << 1) ^ (d >> 63)) as u64
}

fn unzigzag(u: u64) -> i64 {
    (u >> 1) as i64 ^ -((u & 1) as i64)
}

/// A [`Csr`] packed: the varints of each stretch of [`ROW_BLOCK`] rows, and its entry
/// count.
pub struct PackedCsr {
    offsets_len: usize,
    bytes: Vec<u8>,
    starts: Vec<usize>,
    entries: Vec<usize>,
}

impl PackedCsr {
    pub fn new(g: Csr) -> PackedCsr {
        let n = g.nodes();
        let rows = |s: usize| s * ROW_BLOCK..((s + 1) * ROW_BLOCK).min(n);
        // Row `i`'s degree, then each neighbour as the difference from the one before.
        let each = |i: usize, f: &mut dyn FnMut(u64)| {
            let nb = g.neighbours(i);
            f(nb.len() as u64);
            let mut prev = i as i64;
            for &j in nb {
                f(zigzag(j as i64 - prev));
                prev = j as i64;
            }
        };
        let stretches = n.div_ceil(ROW_BLOCK);
        let (bytes, starts) = pack(
            stretches,
            |s| {
                let mut b = 0;
                rows(s).for_each(|i| each(i, &mut |v| b += varint_len(v)));
                b
            },
            |s, out| {
                let mut at = 0;
                rows(s).for_each(|i| each(i, &mut |v| put(out, &mut at, v)));
            },
        );
        let entries = (0..stretches).map(|s| g.offsets[rows(s).end] - g.offsets[rows(s).start]).collect();
        PackedCsr { offsets_len: g.offsets.len(), bytes, starts, entries }
    }

    pub fn unpack(self) -> Csr {
        let total = self.entries.iter().sum();
        let mut targets = filled(total, 0u32);
        let mut offsets = filled(self.offsets_len, 0usize);
        let mut bases = Vec::with_capacity(self.entries.len());
        let mut slices = Vec::with_capacity(self.entries.len());
        let (mut base, mut rest) = (0, &mut targets[..]);
        for &e in &self.entries {
            let (here, after) = rest.split_at_mut(e);
            bases.push(base);
            slices.push(here);
            (base, rest) = (base + e, after);
        }
        let (packed, starts) = (&self.bytes, &self.starts);
        if let Some(ends) = offsets.get_mut(1..) {
            ends.par_chunks_mut(ROW_BLOCK).zip(slices).zip(bases).enumerate().for_each(|(s, ((ends, out), base))| {
                let bytes = &packed[starts[s]..starts[s + 1]];
                let (mut at, mut e) = (0, 0);
                for (t, end) in ends.iter_mut().enumerate() {
                    let degree = get(bytes, &mut at) as usize;
                    let mut prev = (s * ROW_BLOCK + t) as i64;
                    for slot in &mut out[e..e + degree] {
                        prev += unzigzag(get(bytes, &mut at));
                        *slot = prev as u32;
                    }
                    e += degree;
                    *end = base + e;
                }
            });
        }
        Csr { offsets, targets }
    }
}

/// Radii as their `f32` squares, or as they are.
enum Radii {
    Squares(Vec<f32>),
    Plain(Vec<f64>),
}

/// Per-node radii and components, packed.
pub struct PackedNodes {
    radii: Radii,
    /// The components' differences, per stretch of [`ROW_BLOCK`] nodes from
    /// `starts[s]`.
    component: Vec<u8>,
    starts: Vec<usize>,
    nodes: usize,
}

impl PackedNodes {
    pub fn new(radii: Vec<f64>, component: Vec<u32>) -> PackedNodes {
        let square = |r: f64| (r * r) as f32;
        let exact = radii.par_iter().all(|&r| (square(r) as f64).sqrt().to_bits() == r.to_bits());
        let radii =
            if exact { Radii::Squares(radii.par_iter().map(|&r| square(r)).collect()) } else { Radii::Plain(radii) };
        let stretch = |s: usize| &component[s * ROW_BLOCK..((s + 1) * ROW_BLOCK).min(component.len())];
        // Each component as the difference from the one before.
        let each = |s: usize, f: &mut dyn FnMut(u64)| {
            let mut prev = 0i64;
            for &k in stretch(s) {
                f(zigzag(k as i64 - prev));
                prev = k as i64;
            }
        };
        let (packed, starts) = pack(
            component.len().div_ceil(ROW_BLOCK),
            |s| {
                let mut b = 0;
                each(s, &mut |v| b += varint_len(v));
                b
            },
            |s, out| {
                let mut at = 0;
                each(s, &mut |v| put(out, &mut at, v));
            },
        );
        PackedNodes { radii, component: packed, starts, nodes: component.len() }
    }

    /// The radii and components, as given to [`PackedNodes::new`].
    pub fn unpack(self) -> (Vec<f64>, Vec<u32>) {
        let radii = match self.radii {
            Radii::Squares(q) => q.par_iter().map(|&q| (q as f64).sqrt()).collect(),
            Radii::Plain(r) => r,
        };
        let mut component = filled(self.nodes, 0u32);
        let (packed, starts) = (&self.component, &self.starts);
        component.par_chunks_mut(ROW_BLOCK).enumerate().for_each(|(s, out)| {
            let bytes = &packed[starts[s]..starts[s + 1]];
            let (mut at, mut prev) = (0, 0i64);
            for k in out {
                prev += unzigzag(get(bytes, &mut at));
                *k = prev as u32;
            }
        });
        (radii, component)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_graph_comes_back_bit_for_bit() {
        let mut rnd = crate::test_rng(5);
        // Long jumps (multi-byte varints) and more than one stretch.
        let n = 3 * ROW_BLOCK + 17;
        let (g, _) = crate::test_graph(n, (0..5 * n).map(|_| (rnd(n as u64) as u32, rnd(n as u64) as u32)));
        assert_eq!(PackedCsr::new(g.clone()).unpack(), g);
        for empty in [Csr::default(), Csr { offsets: vec![0], targets: vec![] }] {
            assert_eq!(PackedCsr::new(empty.clone()).unpack(), empty);
        }
        // Radii that are square roots of `f32` values pack as squares; others as they are.
        let component: Vec<u32> = (0..n).map(|i| (i / 100) as u32 ^ (rnd(3) as u32 * 1_000_000_007)).collect();
        let roots: Vec<f64> = (0..n).map(|_| (rnd(1 << 20) as f32 * 0.37f32) as f64).map(f64::sqrt).collect();
        let packed = PackedNodes::new(roots.clone(), component.clone());
        assert!(matches!(packed.radii, Radii::Squares(_)));
        assert_eq!(packed.unpack(), (roots, component.clone()));
        let plain: Vec<f64> = (0..n).map(|i| 0.1 + i as f64 / 3.0).collect();
        let packed = PackedNodes::new(plain.clone(), component.clone());
        assert!(matches!(packed.radii, Radii::Plain(_)));
        assert_eq!(packed.unpack(), (plain, component));
    }
}
