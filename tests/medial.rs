//! The medial stage (`medial`, src/medial.rs): nodes on the ridge of the distance
//! transform, not at the mask's local centre of mass; touching vessels keep their own
//! lines; junctions where the centrelines meet.

use ndarray::Array3;
use vesselflow::grid::Csr;
use vesselflow::medial::{recentre, settle, Field, CAP, MIN_CAP, PASSES};
use vesselflow::shapes::{capsules, segment_distance, Capsule};
use vesselflow::{Params, Skeleton, Skeletonizer};

fn run(mask: &Array3<u8>, medial: bool) -> Skeleton {
    let p = Params { medial, ..Params::default() };
    Skeletonizer::new(p).unwrap().run(mask.view(), [1.0; 3], &mut |_| true).unwrap()
}

fn add(a: [f64; 3], b: [f64; 3], s: f64) -> [f64; 3] {
    std::array::from_fn(|d| a[d] + s * b[d])
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn unit(a: [f64; 3]) -> [f64; 3] {
    let n = dot(a, a).sqrt();
    a.map(|x| x / n)
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

/// A right-handed orthonormal frame from an arbitrary (deterministic) direction.
fn frame(seed: [f64; 3]) -> [[f64; 3]; 3] {
    let e0 = unit(seed);
    let e1 = unit(cross(e0, if e0[0].abs() < 0.9 { [1.0, 0.0, 0.0] } else { [0.0, 1.0, 0.0] }));
    [e0, e1, cross(e0, e1)]
}

/// A path graph on `n` nodes.
fn path(n: usize) -> Csr {
    let edges: Vec<(u32, u32)> = (1..n as u32).map(|i| (i - 1, i)).collect();
    Csr::from_sorted_edges(n, &edges)
}

/// A tube of radius 3.5 bent on a circle of radius 18 (centre `o`, plane `e1`, `e2` of
/// a tilted frame), from 20° to 160°, with a bubble of radius 2.5 on its outer side at
/// 90° that reaches 1.5 voxels past the tube's surface. Returns the mask, the distance
/// to the tube's axis, and the point of the axis at an angle.
#[allow(clippy::type_complexity)]
fn bent_tube_with_bubble() -> (Array3<u8>, Box<dyn Fn([f64; 3]) -> f64>, Box<dyn Fn(f64) -> [f64; 3]>) {
    let [_, e1, e2] = frame([0.3, -0.5, 0.8]);
    let (o, big, r) = ([30.0, 30.0, 30.0], 18.0, 3.5);
    let axis = move |deg: f64| {
        let t = deg.to_radians();
        add(add(o, e1, big * t.cos()), e2, big * t.sin())
    };
    let mut parts: Vec<Capsule> =
        (0..28).map(|k| Capsule { a: axis(20.0 + 5.0 * k as f64), b: axis(25.0 + 5.0 * k as f64), r }).collect();
    let bubble = add(o, e2, big + r + 1.5);
    parts.push(Capsule { a: bubble, b: bubble, r: 2.5 });
    let mask = capsules([61, 61, 61], [1.0; 3], &parts);
    let dist = move |q: [f64; 3]| {
        let v = add(q, o, -1.0);
        let (x, y) = (dot(v, e1), dot(v, e2));
        let off = add(add(v, e1, -x), e2, -y);
        (dot(off, off) + ((x * x + y * y).sqrt() - big).powi(2)).sqrt()
    };
    (mask, Box::new(dist), Box::new(axis))
}

/// Nodes pulled 1.5 voxels off the axis toward a bubble, and inward on the rest of a
/// bent tube (where a cluster's mean falls on the chord), go back to within half a
/// voxel of the axis.
#[test]
fn nodes_pulled_off_a_bent_tube_go_back_to_its_axis() {
    let (mask, dist, axis) = bent_tube_with_bubble();
    let [_, e1, e2] = frame([0.3, -0.5, 0.8]);
    let n = 31;
    let positions: Vec<[f64; 3]> = (0..n)
        .map(|k| {
            let deg = 30.0 + 4.0 * k as f64;
            let q = axis(deg);
            // Radially outward toward the bubble near 90°, inward elsewhere.
            let out = unit(add(add([0.0; 3], e1, deg.to_radians().cos()), e2, deg.to_radians().sin()));
            add(q, out, if (deg - 90.0).abs() <= 8.0 { 1.5 } else { -1.2 })
        })
        .collect();
    assert!(positions.iter().all(|&q| dist(q) > 1.1));
    let moved = recentre(&path(n), &positions, &vec![3.5; n], &Field::new(mask.view(), [1.0; 3]).unwrap());
    for (q, m) in positions.iter().zip(&moved) {
        assert!(dist(*m) <= 0.5, "{q:?} (off by {:.2}) moved to {m:?}, still {:.2} off", dist(*q), dist(*m));
    }
}

/// The whole run: with the stage, every curve node of the bent tube lies within half a
/// voxel of its axis; without it, the bubble and the bend pull some further.
#[test]
fn a_bent_tube_with_a_bubble_gets_its_axis() {
    let (mask, dist, _) = bent_tube_with_bubble();
    let worst = |s: &Skeleton| {
        let deg = s.degrees();
        s.positions.iter().zip(&deg).filter(|(_, &d)| d == 2).map(|(&q, _)| dist(q)).fold(0.0, f64::max)
    };
    let (with, without) = (run(&mask, true), run(&mask, false));
    assert!(worst(&with) <= 0.5, "medial: {:.2}", worst(&with));
    assert!(worst(&without) > 0.5, "without: {:.2}", worst(&without));
}

/// A path left 3.5 voxels off the axis of a thick tube (radius 6), its nodes' radii small
/// (2: each pass may move a node `MIN_CAP` = 2 voxels): one pass leaves it on the
/// tube's slope, more than a voxel off; the stage's passes take it to within half a
/// voxel of the axis, each from where the last one left it. Its ends move in the first
/// pass only.
#[test]
fn passes_take_a_path_off_a_thick_tube_s_slope_to_its_axis() {
    assert!(PASSES >= 2 && (CAP * 2.0).max(MIN_CAP) < 3.5 - 1.0);
    let [t, u, _] = frame([1.0, 0.3, -0.2]);
    let o = [30.0, 30.0, 30.0];
    let mask = capsules([61, 61, 61], [1.0; 3], &[Capsule { a: add(o, t, -40.0), b: add(o, t, 40.0), r: 6.0 }]);
    let off = |q: [f64; 3]| segment_distance(q, add(o, t, -100.0), add(o, t, 100.0));
    let n = 11;
    let positions: Vec<[f64; 3]> = (0..n).map(|k| add(add(o, t, 2.0 * k as f64 - 10.0), u, 3.5)).collect();
    let (g, radii, field) = (path(n), vec![2.0; n], Field::new(mask.view(), [1.0; 3]).unwrap());
    let once = recentre(&g, &positions, &radii, &field);
    let settled = settle(&g, &positions, &radii, &field);
    for ((q, a), b) in positions.iter().zip(&once).zip(&settled).take(n - 1).skip(1) {
        assert!(off(*a) > 1.0, "{q:?}: one pass already reached the axis ({:.2} off)", off(*a));
        assert!(off(*b) <= 0.5, "{q:?}: {:.2} off the axis after the passes", off(*b));
    }
    for end in [0, n - 1] {
        assert_ne!(once[end], positions[end]);
        assert_eq!(settled[end], once[end]);
    }
}

/// Two parallel tubes (radii 3 and 4) that touch along their length, at a tilt. A node
/// near the thin one's axis, with a radius large enough that its search reaches the
/// thick one's axis (where the transform is larger), stays on the thin one: the
/// search climbs to the nearest ridge and never crosses the saddle between them.
#[test]
fn touching_tubes_keep_their_own_axes() {
    let [t, u, _] = frame([1.0, 0.35, 0.2]);
    let o = [28.0, 20.0, 20.0];
    let (a0, b0) = (add(o, u, -3.5), add(o, u, 3.5));
    let tube = |c: [f64; 3], r: f64| Capsule { a: add(c, t, -40.0), b: add(c, t, 40.0), r };
    let mask = capsules([57, 41, 41], [1.0; 3], &[tube(a0, 3.0), tube(b0, 4.0)]);
    let line_dist = |q: [f64; 3], c: [f64; 3]| segment_distance(q, add(c, t, -100.0), add(c, t, 100.0));
    let n = 15;
    for (own, other, toward) in [(a0, b0, 1.0), (b0, a0, -1.0)] {
        // One voxel off the axis toward the other tube.
        let positions: Vec<[f64; 3]> = (0..n).map(|k| add(add(own, t, 2.0 * k as f64 - 14.0), u, toward)).collect();
        let moved = recentre(&path(n), &positions, &vec![10.0; n], &Field::new(mask.view(), [1.0; 3]).unwrap());
        for m in &moved {
            assert!(line_dist(*m, own) <= 0.5, "{m:?}: {:.2} from its axis", line_dist(*m, own));
            assert!(line_dist(*m, other) > 6.0);
        }
    }
}

/// A Y whose trunk (radius 4.5) is thicker than its branches (3, at ±35°): the
/// junction lies where the three centrelines meet, not inside the trunk.
#[test]
fn a_junction_sits_where_the_centrelines_meet() {
    let fork = [17.0, 30.0, 24.0];
    let t = 35f64.to_radians();
    let tip = |s: f64| [17.0, 30.0 + 26.0 * t.cos(), 24.0 + s * 26.0 * t.sin()];
    let parts = [
        Capsule { a: [17.0, 3.0, 24.0], b: fork, r: 4.5 },
        Capsule { a: fork, b: tip(1.0), r: 3.0 },
        Capsule { a: fork, b: tip(-1.0), r: 3.0 },
    ];
    let mask = capsules([35, 60, 49], [1.0; 3], &parts);
    let miss = |s: &Skeleton| {
        let deg = s.degrees();
        let junctions: Vec<[f64; 3]> = s.positions.iter().zip(&deg).filter(|(_, &d)| d >= 3).map(|(&q, _)| q).collect();
        assert_eq!(junctions.len(), 1, "{junctions:?}");
        segment_distance(junctions[0], fork, fork)
    };
    let (with, without) = (run(&mask, true), run(&mask, false));
    assert!(miss(&with) <= 1.0, "medial: {:.2}", miss(&with));
    assert!(miss(&without) > 1.0, "without: {:.2}", miss(&without));
}

/// The stage is off with `medial = false` and moves nodes when on; both runs give the
/// same graph (nodes and edges). The positions differ, and so may the radii, which are
/// measured on the mask at the final positions (`radius`).
#[test]
fn the_stage_moves_nodes_but_keeps_the_graph() {
    let (mask, _, _) = bent_tube_with_bubble();
    let (with, without) = (run(&mask, true), run(&mask, false));
    assert_eq!(with.edges, without.edges);
    assert_eq!(with.radii.len(), without.radii.len());
    assert_ne!(with.positions, without.positions);
}

/// On noise (random blobs) and random paths and junctions, a node that moves lands on
/// a vessel voxel and moves at most `CAP` radii (`MIN_CAP` base cells at least), unless it is
/// a path node put back between its junction and its other neighbour (the unfolding):
/// then it sits at their midpoint. A junction moves at most `JUNCTION_CAP` times the
/// larger of its radius and twice its branches' largest (the parent's over the sine of
/// the child's angle, at most doubled).
#[test]
fn moves_stay_on_the_mask_and_within_the_cap() {
    let mut state = 12345u64;
    let mut rnd = |m: u64| {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (state >> 33) % m
    };
    let spacing = [1.0, 0.7, 1.3];
    let blobs: Vec<Capsule> = (0..40)
        .map(|_| {
            let a = [rnd(30) as f64, rnd(40) as f64 * 0.7, rnd(25) as f64 * 1.3];
            let b = [a[0] + rnd(9) as f64 - 4.0, a[1] + rnd(9) as f64 - 4.0, a[2] + rnd(9) as f64 - 4.0];
            Capsule { a, b, r: 0.8 + rnd(30) as f64 / 10.0 }
        })
        .collect();
    let mask = capsules([30, 40, 25], spacing, &blobs);
    let n = 400;
    let positions: Vec<[f64; 3]> =
        (0..n).map(|_| [rnd(300) as f64 / 10.0, rnd(280) as f64 / 10.0, rnd(325) as f64 / 10.0]).collect();
    let radii: Vec<f64> = (0..n).map(|_| 0.5 + rnd(60) as f64 / 10.0).collect();
    // Paths of 8 nodes, every fourth path's first node also joined to two others.
    let mut edges: Vec<(u32, u32)> = vec![];
    for i in 0..n as u32 {
        if i % 8 != 0 {
            edges.push((i - 1, i));
        }
        if i % 32 == 0 && i + 16 < n as u32 {
            edges.extend([(i, i + 9), (i, i + 16)]);
        }
    }
    edges.sort_unstable();
    let g = Csr::from_sorted_edges(n, &edges);
    let moved = recentre(&g, &positions, &radii, &Field::new(mask.view(), spacing).unwrap());
    let on_mask = |q: [f64; 3]| {
        let v: [usize; 3] = std::array::from_fn(|d| (q[d] / spacing[d]).round() as usize);
        v.iter().zip(mask.shape()).all(|(&x, &s)| x < s) && mask[v] != 0
    };
    let unfolded = |i: usize| {
        let nb = g.neighbours(i);
        nb.len() == 2
            && nb.iter().any(|&a| g.neighbours(a as usize).len() >= 3)
            && (0..3).all(|k| moved[i][k] == 0.5 * (moved[nb[0] as usize][k] + moved[nb[1] as usize][k]))
    };
    let (mut count, mut unfolds) = (0, 0);
    for (i, ((p, m), r)) in positions.iter().zip(&moved).zip(&radii).enumerate() {
        if p != m {
            count += 1;
            assert!(on_mask(*m), "{p:?} moved off the mask to {m:?}");
            let d = segment_distance(*p, *m, *m);
            if unfolded(i) {
                unfolds += 1;
            } else if g.neighbours(i).len() >= 3 {
                // Its branches: the paths from it, to the next junction or end.
                let mut widest = 0f64;
                for &first in g.neighbours(i) {
                    let (mut prev, mut cur) = (i, first as usize);
                    for _ in 0..n {
                        widest = widest.max(radii[cur]);
                        let nb = g.neighbours(cur);
                        if nb.len() != 2 {
                            break;
                        }
                        let next = if nb[0] as usize == prev { nb[1] } else { nb[0] } as usize;
                        (prev, cur) = (cur, next);
                    }
                }
                let cap =
                    (vesselflow::medial::JUNCTION_CAP * r.max(2.0 * widest)).max(vesselflow::medial::MIN_CAP * 0.7);
                assert!(d <= cap + 1e-9, "junction {p:?} moved {d} with radius {r}, branches to {widest}");
            } else {
                let cap = (vesselflow::medial::CAP * r).max(vesselflow::medial::MIN_CAP * 0.7);
                assert!(d <= cap + 1e-9, "{p:?} moved {d} with radius {r}");
            }
        }
    }
    assert!(count > 50, "only {count} nodes moved");
    assert!(unfolds < count / 4, "{unfolds} of {count} moves were unfoldings");
}

/// The same positions, bit for bit, whatever the thread count.
#[test]
fn threads_do_not_change_the_positions() {
    let (mask, _, _) = bent_tube_with_bubble();
    let at = |threads: usize| {
        let p = Params { threads, ..Params::default() };
        Skeletonizer::new(p).unwrap().run(mask.view(), [1.0; 3], &mut |_| true).unwrap().positions
    };
    let one = at(1);
    for threads in [2, 3] {
        assert!(at(threads).iter().zip(&one).all(|(a, b)| (0..3).all(|d| a[d].to_bits() == b[d].to_bits())));
    }
}
