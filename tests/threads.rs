//! Many threads on a small machine: the run must finish, and give the same graph,
//! whatever the pool size. A 50 % noise mask has many short cycles, so the cycle
//! searches run in many parallel chunks; the search once held a per-thread lock
//! across a rayon call and hung in 1–2 of 10 runs at 8 threads.

use ndarray::Array3;
use std::sync::mpsc;
use std::time::Duration;
use vesselflow::{Params, Skeleton, Skeletonizer, Value};

fn noise(shape: (usize, usize, usize), seed: u64) -> Array3<u8> {
    let mut state = seed;
    Array3::from_shape_simple_fn(shape, || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        u8::from((state >> 33) % 2 == 0)
    })
}

/// Run on another thread; `None` if it did not finish within `limit` (a hang: the
/// limit is many times the run's length, so it never trips on a slow machine).
fn run_or_hang(mask: Array3<u8>, threads: i64, limit: Duration) -> Option<Skeleton> {
    let (done, finished) = mpsc::channel();
    std::thread::spawn(move || {
        let mut p = Params::default();
        p.set("threads", &Value::Int(threads)).unwrap();
        p.set("max_iterations", &Value::Int(2)).unwrap();
        let s = Skeletonizer::new(p).unwrap().run(mask.view(), [1.0; 3], &mut |_| true).unwrap();
        let _ = done.send(s);
    });
    finished.recv_timeout(limit).ok()
}

#[test]
fn noise_at_eight_threads_never_hangs_and_matches_one_thread() {
    let reference = run_or_hang(noise((40, 40, 40), 7), 1, Duration::from_secs(300)).expect("1 thread hung");
    for trial in 0..10 {
        let s = run_or_hang(noise((40, 40, 40), 7), 8, Duration::from_secs(300))
            .unwrap_or_else(|| panic!("run {trial} at 8 threads hung"));
        assert_eq!(s.positions, reference.positions, "run {trial}");
        assert_eq!(s.edges, reference.edges, "run {trial}");
        assert_eq!(s.radii, reference.radii, "run {trial}");
    }
}
