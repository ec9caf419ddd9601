//! A run stops soon after its [`Stop`] flag is raised from another thread, inside a
//! long stage rather than at its end: measured in conjugate-gradient iterations run
//! after the request, not in wall time.
//!
//! One test per file section; each uses its own flag, so the counts do not mix.

use vesselflow::{shapes, Error, Params, Skeletonizer, Stop, Value};

/// A thick tube and a solve that would take thousands of iterations: a tolerance it
/// cannot reach, and a generous cap.
fn slow_solve() -> (ndarray::Array3<u8>, Skeletonizer) {
    let mask = shapes::cylinder([120, 31, 31], 9.0);
    let params = Params::from_pairs([
        ("cg_tol", Value::Float(1e-300)),
        ("cg_max_iterations", Value::Int(100_000)),
        ("threads", Value::Int(2)),
    ])
    .unwrap();
    (mask, Skeletonizer::new(params).unwrap())
}

#[test]
fn a_request_during_a_solve_stops_it_within_one_iteration() {
    let (mask, sk) = slow_solve();
    let stop = Stop::new();
    let mut before = 0;
    let mut reports_after = 0;
    let done = std::sync::atomic::AtomicBool::new(false);
    let result = std::thread::scope(|scope| {
        let asker = stop.clone();
        let done = &done;
        let setter = scope.spawn(move || {
            // Well inside the first solve (it would run to 100 000 iterations). A run
            // that ends first (no iteration counted) fails the test below.
            while asker.cg_iterations() < 50 && !done.load(std::sync::atomic::Ordering::SeqCst) {
                std::thread::yield_now();
            }
            let before = asker.cg_iterations();
            asker.request();
            before
        });
        let result = sk.run_with_stop(mask.view(), [1.0; 3], &stop, &mut |_| {
            reports_after += usize::from(stop.is_requested());
            true
        });
        done.store(true, std::sync::atomic::Ordering::SeqCst);
        before = setter.join().unwrap();
        result
    });
    assert_eq!(result.unwrap_err(), Error::Interrupted);
    // Iterations begun after the request: the ones each of the two threads may have
    // had in flight, and the check that saw the flag.
    let after = stop.cg_iterations() - before;
    assert!(after <= 2, "{after} conjugate-gradient iterations after the request");
    assert_eq!(reports_after, 0, "no stage reported after the request");
}

#[test]
fn a_request_before_the_run_does_no_work_and_no_request_changes_nothing() {
    let mask = shapes::cylinder([40, 21, 21], 4.0);
    let sk = Skeletonizer::new(Params::default()).unwrap();
    let stop = Stop::new();
    stop.request();
    let mut reports = 0;
    let e = sk.run_with_stop(mask.view(), [1.0; 3], &stop, &mut |_| {
        reports += 1;
        true
    });
    assert_eq!(e.unwrap_err(), Error::Interrupted);
    assert_eq!((reports, stop.cg_iterations()), (0, 0));
    // A flag never raised: the same graph as without one, and the solver's
    // iterations are all counted.
    let stop = Stop::new();
    let a = sk.run_with_stop(mask.view(), [1.0; 3], &stop, &mut |_| true).unwrap();
    let b = sk.run(mask.view(), [1.0; 3], &mut |_| true).unwrap();
    assert_eq!((&a.positions, &a.radii, &a.edges), (&b.positions, &b.radii, &b.edges));
    let solved: usize = a.info.cg_iterations.iter().sum();
    // One check per iteration begun, plus the one that ends each solve when it converges.
    assert!(stop.cg_iterations() as usize >= solved, "{} < {solved}", stop.cg_iterations());
    assert!(stop.cg_iterations() as usize <= solved + a.info.iterations);
}
