//! Criterion benches of the core's stages on a synthetic vascular forest.
//!
//! - `run/N`: the whole [`Skeletonizer::run`] with default parameters (all cores);
//! - `stages/edt/N`: [`volume::edt_squared`], the anisotropic exact distance transform;
//! - `stages/grid/N`: [`grid::build`], the initial grid graph from mask and EDT;
//! - `stages/contract/N`: one contraction iteration on the initial grid graph
//!   (weights, anchoring, the conjugate-gradient solve, decimation, the cycle-area
//!   measure), and each of those parts alone as `stages/laplacian/N`,
//!   `stages/solve/N`, `stages/decimate/N` and `stages/cycle_area/N`.
//!
//! `N` is the edge of the cube (64 and 96 voxels); throughput is in foreground voxels.
//! The volume is a deterministic forest of binary trees of tapered tubes (radii
//! 1.5–6 voxels) with one anastomosis closing a loop, about 5 % foreground: see
//! [`vascular_forest`].
//!
//! Run with `cargo bench --bench stages` (add `-- --quick` for a short run, or a
//! filter such as `-- contract/96`).

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use ndarray::Array3;
use std::hint::black_box;
use std::time::Duration;
use vesselflow::cycles::short_cycle_area;
use vesselflow::decimate::{decimate, NodeGraph};
use vesselflow::grid;
use vesselflow::laplacian;
use vesselflow::laplacian::NormalOperator;
use vesselflow::pipeline::{contract_step, StageClock};
use vesselflow::solver;
use vesselflow::{volume, Params, Skeletonizer};

/// Edges of the benchmark cubes, voxels.
const SIZES: [usize; 2] = [64, 96];
/// Isotropic unit spacing: positions are in voxels.
const SPACING: [f64; 3] = [1.0; 3];
/// The base cell `c = min(SPACING)` of decimation.
const CELL: f64 = 1.0;

type V3 = [f64; 3];

fn add(a: V3, b: V3, s: f64) -> V3 {
    [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]]
}

fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: V3, b: V3) -> V3 {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

fn unit(a: V3) -> V3 {
    let n = dot(a, a).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}

/// A tapered tube: centreline `a` → `b`, radius `ra` → `rb`, all in voxels.
struct Tube {
    a: V3,
    b: V3,
    ra: f64,
    rb: f64,
}

impl Tube {
    /// The centreline point a fraction `t` of the way from `a` to `b`, and its radius.
    fn at(&self, t: f64) -> (V3, f64) {
        (add(self.a, add(self.b, self.a, -1.0), t), self.ra + t * (self.rb - self.ra))
    }

    /// Set every voxel of `mask` whose centre lies inside the tube, looking only at
    /// the tube's bounding box (clipped to the array).
    fn paint(&self, mask: &mut Array3<u8>) {
        let r = self.ra.max(self.rb);
        let shape = mask.dim();
        let shape = [shape.0, shape.1, shape.2];
        let range = |d: usize| {
            let lo = (self.a[d].min(self.b[d]) - r).floor().max(0.0) as usize;
            let hi = ((self.a[d].max(self.b[d]) + r).ceil() + 1.0).clamp(0.0, shape[d] as f64) as usize;
            lo..hi
        };
        let axis = add(self.b, self.a, -1.0);
        let len2 = dot(axis, axis);
        for i in range(0) {
            for j in range(1) {
                for k in range(2) {
                    let x = add([i as f64, j as f64, k as f64], self.a, -1.0);
                    let t = if len2 > 0.0 { (dot(x, axis) / len2).clamp(0.0, 1.0) } else { 0.0 };
                    let off = add(x, axis, -t);
                    let radius = self.ra + t * (self.rb - self.ra);
                    if dot(off, off) <= radius * radius {
                        mask[[i, j, k]] = 1;
                    }
                }
            }
        }
    }
}

/// Grow a binary tree of tubes from `start` along unit `dir`. Each tube tapers by
/// 5 %; its two children leave its end 35° to either side, in a plane that turns by
/// 90° every generation, 80 % as long and 85 % as thick. Growth stops below a
/// radius of 1.5 voxels (after six generations from a root of radius 6).
fn grow(tubes: &mut Vec<Tube>, start: V3, dir: V3, length: f64, radius: f64, generation: usize) {
    let end = add(start, dir, length);
    let r_end = 0.95 * radius;
    tubes.push(Tube { a: start, b: end, ra: radius, rb: r_end });
    let child_r = 0.85 * r_end;
    if child_r < 1.5 {
        return;
    }
    // A unit vector perpendicular to `dir`, alternating between two orthogonal planes.
    let least = (0..3).min_by(|&x, &y| dir[x].abs().total_cmp(&dir[y].abs())).unwrap_or(0);
    let mut e = [0.0; 3];
    e[least] = 1.0;
    let p1 = unit(cross(dir, e));
    let side = if generation % 2 == 0 { p1 } else { cross(dir, p1) };
    let (c, s) = (35f64.to_radians().cos(), 35f64.to_radians().sin());
    for sign in [-1.0, 1.0] {
        let child = unit(add([c * dir[0], c * dir[1], c * dir[2]], side, sign * s));
        grow(tubes, end, child, 0.8 * length, child_r, generation + 1);
    }
}

/// The benchmark volume: an `n`³ forest of such trees (root radius 6 voxels, root
/// tube 19 voxels long), rooted 8 voxels inside the face `axis 0 = 0` at points of
/// a low-discrepancy sequence over the middle 70 % of that face, each leaning away
/// from the face's centre, added until the foreground reaches 4.5 % (one tree at
/// 64³, three at 96³, which touch: one 26-connected component). In the first tree
/// an anastomosis of 60 % of their radius joins the root's two children near their
/// ends, closing a loop.
fn vascular_forest(n: usize) -> Array3<u8> {
    let nf = n as f64;
    let mut mask = Array3::<u8>::zeros((n, n, n));
    let mut foreground = 0;
    let mut tree = 0;
    while (foreground as f64) < 0.045 * mask.len() as f64 {
        // The R2 sequence (plastic-number based) spreads the roots evenly.
        let u = (0.5 + tree as f64 * 0.754_877_666_246_692_7).fract();
        let v = (0.5 + tree as f64 * 0.569_840_290_998_053_2).fract();
        let start = [8.0, (0.15 + 0.7 * u) * nf, (0.15 + 0.7 * v) * nf];
        let dir = unit([1.0, 0.3 * (0.5 - u), 0.3 * (0.5 - v)]);
        let mut tubes = vec![];
        grow(&mut tubes, start, dir, 19.0, 6.0, 0);
        if tree == 0 {
            // Depth-first order: tubes[1] is the root's first child; the second
            // child is the next tube that starts where it does.
            let first = &tubes[1];
            let second = tubes.iter().skip(2).find(|t| t.a == first.a).expect("the root has two children");
            let ((pa, ra), (pb, rb)) = (first.at(0.9), second.at(0.9));
            tubes.push(Tube { a: pa, b: pb, ra: 0.6 * ra, rb: 0.6 * rb });
        }
        for t in &tubes {
            t.paint(&mut mask);
        }
        foreground = mask.iter().filter(|&&v| v != 0).count();
        tree += 1;
    }
    mask
}

/// One contraction iteration (METHOD.md §2) on `g`, the grid graph of `mask`, as the
/// pipeline runs it on a cube.
fn contract_once(g: &NodeGraph, p: &Params, mask: &Array3<u8>) -> NodeGraph {
    let (next, _) = contract_step(g.clone(), p, CELL, None, &mut StageClock::default(), mask.view(), SPACING)
        .expect("cells in range");
    black_box(short_cycle_area(&next.graph, &next.positions, p.max_cycle_nodes));
    next
}

fn stages(cr: &mut Criterion) {
    let p = Params::default();
    let skeletonizer = Skeletonizer::new(p.clone()).expect("default parameters are valid");
    let volumes: Vec<(usize, Array3<u8>, u64)> = SIZES
        .iter()
        .map(|&n| {
            let mask = vascular_forest(n);
            let fg = mask.iter().filter(|&&v| v != 0).count();
            eprintln!("vascular forest {n}³: {fg} foreground voxels ({:.2} %)", 100.0 * fg as f64 / mask.len() as f64);
            (n, mask, fg as u64)
        })
        .collect();

    let mut group = cr.benchmark_group("run");
    group.sample_size(10).measurement_time(Duration::from_secs(20));
    for (n, mask, fg) in &volumes {
        group.throughput(Throughput::Elements(*fg));
        group.bench_with_input(BenchmarkId::from_parameter(n), mask, |b, m| {
            b.iter(|| skeletonizer.run(m.view(), SPACING, &mut |_| true).expect("run succeeds"))
        });
    }
    group.finish();

    let mut group = cr.benchmark_group("stages");
    group.sample_size(10).measurement_time(Duration::from_secs(10));
    for (n, mask, fg) in &volumes {
        group.throughput(Throughput::Elements(*fg));
        group.bench_with_input(BenchmarkId::new("edt", n), mask, |b, m| {
            b.iter(|| volume::edt_squared(m.view(), SPACING).unwrap())
        });
        let edt = volume::edt_squared(mask.view(), SPACING).unwrap();
        group.bench_with_input(BenchmarkId::new("grid", n), mask, |b, m| {
            b.iter(|| grid::build(m.view(), &edt, SPACING, &p).unwrap())
        });
        let grid = grid::build(mask.view(), &edt, SPACING, &p).unwrap();
        let g =
            NodeGraph { graph: grid.graph, positions: grid.positions, radii: grid.radii, component: grid.component };
        group.bench_with_input(BenchmarkId::new("contract", n), &g, |b, g| b.iter(|| contract_once(g, &p, mask)));

        group.bench_with_input(BenchmarkId::new("laplacian", n), &g, |b, g| {
            b.iter(|| {
                let ln = laplacian::l2_norm(&g.graph, &g.positions);
                let lm = laplacian::medial(&g.graph, &g.radii, p.medial_weight);
                (ln, lm, laplacian::skeletal(&g.graph, &g.positions, &p))
            })
        });
        let ln = laplacian::l2_norm(&g.graph, &g.positions);
        let lm = laplacian::medial(&g.graph, &g.radii, p.medial_weight);
        let skeletal = laplacian::skeletal(&g.graph, &g.positions, &p);
        let op = NormalOperator::new(&g.graph, &ln, &lm, &skeletal, &p);
        group.bench_with_input(BenchmarkId::new("solve", n), &g, |b, g| {
            b.iter(|| solver::contract(&op, &g.positions, p.cg_tol, p.cg_max_iterations))
        });
        let (positions, _) = solver::contract(&op, &g.positions, p.cg_tol, p.cg_max_iterations);
        let moved = NodeGraph { positions, ..g.clone() };
        group.bench_with_input(BenchmarkId::new("decimate", n), &moved, |b, m| {
            b.iter(|| decimate(m, &skeletal, CELL).expect("cells in range"))
        });
        group.bench_with_input(BenchmarkId::new("cycle_area", n), &g, |b, g| {
            b.iter(|| short_cycle_area(&g.graph, &g.positions, p.max_cycle_nodes))
        });
    }
    group.finish();
}

criterion_group!(benches, stages);
criterion_main!(benches);
