//! Stopping a run from outside (Ctrl-C, a Python signal, another thread): a shared
//! flag that the pipeline checks between stages and that the long stages poll
//! inside their loops (every conjugate-gradient iteration, every block of rows of
//! the EDT, the grid build and the cycle searches), so a request lands within a
//! fraction of a second whatever the stage.
//!
//! The stages read the flag of the run they belong to through a thread-local set on
//! every worker thread of the run's own rayon pool ([`crate::Skeletonizer`] builds
//! one per run), so their signatures carry no extra argument and code run outside
//! a pipeline (tests, benches) never sees a request. A stage that sees the request
//! returns early with partial results; the pipeline checks the flag after every
//! stage and returns [`Error::Interrupted`] before anything partial is used. Polling
//! reads an atomic and changes no arithmetic, so the output is the same bit for bit.

use crate::error::{Error, Result};
use std::cell::RefCell;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;

/// A request to stop a run, shared by the run and whoever may stop it; clones
/// share the flag. [`Stop::request`] only stores to an atomic, so it is safe to call
/// from a signal handler or any thread.
#[derive(Debug, Clone, Default)]
pub struct Stop(Arc<Shared>);

#[derive(Debug, Default)]
struct Shared {
    requested: AtomicBool,
    cg_iterations: AtomicU64,
}

impl Stop {
    /// A flag not yet raised.
    pub fn new() -> Stop {
        Stop::default()
    }

    /// Ask every run holding this flag to stop.
    pub fn request(&self) {
        self.0.requested.store(true, Ordering::SeqCst);
    }

    /// Whether a stop was requested.
    pub fn is_requested(&self) -> bool {
        self.0.requested.load(Ordering::Relaxed)
    }

    /// Conjugate-gradient iterations begun so far by runs holding this flag (a
    /// measure of work for tests of how soon a request lands).
    #[doc(hidden)]
    pub fn cg_iterations(&self) -> u64 {
        self.0.cg_iterations.load(Ordering::SeqCst)
    }

    /// [`Error::Interrupted`] if a stop was requested.
    pub(crate) fn check(&self) -> Result<()> {
        if self.is_requested() {
            Err(Error::Interrupted)
        } else {
            Ok(())
        }
    }

    /// Make this the flag that [`requested`] reads on the calling thread (called on
    /// every worker thread of a run's pool as it starts).
    pub(crate) fn install_on_thread(&self) {
        CURRENT.with(|c| *c.borrow_mut() = Some(self.clone()));
    }
}

thread_local! {
    static CURRENT: RefCell<Option<Stop>> = const { RefCell::new(None) };
}

/// Whether the run this thread works for was asked to stop (false outside a run).
/// Cheap enough to call every few thousand rows.
pub fn requested() -> bool {
    CURRENT.with(|c| c.borrow().as_ref().is_some_and(Stop::is_requested))
}

/// [`Error::Interrupted`] if [`requested`], for stages that can return at once.
pub fn checkpoint() -> Result<()> {
    if requested() {
        Err(Error::Interrupted)
    } else {
        Ok(())
    }
}

/// [`requested`], counting one conjugate-gradient iteration: called once before
/// every iteration, it returns `true` when the solve should stop.
pub fn cg_iteration_stops() -> bool {
    CURRENT.with(|c| match c.borrow().as_ref() {
        Some(stop) => {
            stop.0.cg_iterations.fetch_add(1, Ordering::SeqCst);
            stop.is_requested()
        }
        None => false,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requests_reach_threads_of_the_pool_only() {
        let stop = Stop::new();
        let s = stop.clone();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .start_handler(move |_| s.install_on_thread())
            .build()
            .unwrap();
        assert!(!pool.install(requested));
        stop.request();
        assert!(pool.install(requested));
        assert!(pool.install(cg_iteration_stops));
        assert_eq!(stop.cg_iterations(), 1);
        assert!(!requested(), "the test thread is outside the run");
        assert_eq!(stop.check(), Err(Error::Interrupted));
    }
}
