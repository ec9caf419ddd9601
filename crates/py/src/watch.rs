//! Long calls run on a helper thread while the calling thread watches Python's
//! signals: Python runs signal handlers (Ctrl-C's `KeyboardInterrupt`) only on the
//! main thread, so the thread that called in must stay free to check for them while
//! the core, which polls a [`Stop`] flag, does the work.

use std::sync::mpsc;
use std::time::Duration;

use pyo3::prelude::*;
use vesselflow::Stop;

/// How often the calling thread checks for signals: well under the second a user
/// waits for Ctrl-C to land.
const WATCH_PERIOD: Duration = Duration::from_millis(50);

/// Run `work(stop)` on a helper thread with the GIL released. Meanwhile this thread
/// checks Python's signals every [`WATCH_PERIOD`]; when a signal handler raises,
/// `stop` is requested (the core then stops within a fraction of a second) and the
/// exception is returned beside the result of `work`, to re-raise in its place.
/// `work` must not panic (wrap it in [`crate::errors::no_panic`]).
pub fn watched<R: Send>(py: Python<'_>, work: impl FnOnce(&Stop) -> R + Send) -> (R, Option<PyErr>) {
    let stop = Stop::new();
    py.detach(|| {
        std::thread::scope(|scope| {
            let (done, finished) = mpsc::channel::<()>();
            let stop = &stop;
            let worker = scope.spawn(move || {
                let result = work(stop);
                let _ = done.send(());
                result
            });
            let mut pending = None;
            while let Err(mpsc::RecvTimeoutError::Timeout) = finished.recv_timeout(WATCH_PERIOD) {
                if pending.is_none() {
                    if let Err(e) = Python::attach(|py| py.check_signals()) {
                        stop.request();
                        pending = Some(e);
                    }
                }
            }
            let result = worker.join().unwrap_or_else(|payload| std::panic::resume_unwind(payload));
            (result, pending)
        })
    })
}
