//! The one error type of the core. Every failure a caller can cause is a variant
//! whose message names the problem; the bindings map these to Python exceptions.

use thiserror::Error;

/// Everything the core can refuse or fail with.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum Error {
    /// A parameter has the wrong type or a value outside its range.
    #[error("invalid parameter `{name}`: {reason}")]
    InvalidParameter { name: String, reason: String },
    /// A parameter name that does not exist.
    #[error("unknown parameter `{0}` (known: {known})", known = crate::params::Params::NAMES.join(", "))]
    UnknownParameter(String),
    /// Spacing must be three finite numbers in
    /// [[`MIN_SPACING`](crate::volume::MIN_SPACING), [`MAX_SPACING`](crate::volume::MAX_SPACING)].
    #[error(
        "invalid spacing {0:?}: need three finite numbers in [{min:e}, {max:e}] (physical units per voxel)",
        min = crate::volume::MIN_SPACING,
        max = crate::volume::MAX_SPACING
    )]
    InvalidSpacing(Vec<f64>),
    /// The mask cannot be processed as given (shape, size).
    #[error("invalid mask: {0}")]
    InvalidMask(String),
    /// The caller's observer asked to stop (e.g. Ctrl-C).
    #[error("interrupted")]
    Interrupted,
    /// A bug: a check of the core's own output failed, or a panic was caught at a
    /// boundary (the bindings, the command line). The message says what and where.
    #[error("internal error, please report: {0}")]
    Internal(String),
    /// The thread pool could not be created.
    #[error("cannot start {threads} worker threads: {reason}")]
    ThreadPool { threads: usize, reason: String },
    /// The run would need more memory than allowed (`max_memory`), or an allocation of
    /// `needed` bytes failed (`allowed` is then 0). Bytes.
    #[error("{}", crate::memory::out_of_memory_message(*needed, *allowed))]
    OutOfMemory { needed: u64, allowed: u64 },
}

/// Result alias of the core.
pub type Result<T> = std::result::Result<T, Error>;

/// Run `f`, turning a panic into [`Error::Internal`] with the panic's message and
/// `context()` (e.g. the input's shape and spacing): the last line of defence of the
/// bindings and the command line, so that no panic reaches a user as a crash or a
/// backtrace. While `f` runs, the panic hook prints nothing (see [`quiet_panics`]).
pub fn catch_panic<R>(context: impl FnOnce() -> String, f: impl FnOnce() -> Result<R>) -> Result<R> {
    let _quiet = quiet_panics();
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(payload) => Err(Error::Internal(format!("{} ({})", panic_message(payload.as_ref()), context()))),
    }
}

/// The text of a panic payload (`panic!` with a literal or a format string).
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        s.to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "panic with a non-text payload".to_string()
    }
}

/// Runs inside [`catch_panic`] in progress; the panic hook is silent while any is.
static QUIET: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// Silence the panic hook until the guard is dropped: the panic is reported as an
/// error instead. The process's previous hook is kept and still runs for panics
/// outside any guarded call. Panics of rayon worker threads count too (their
/// payload reaches the guarded call).
pub fn quiet_panics() -> impl Drop {
    use std::sync::atomic::Ordering;
    static INSTALL: std::sync::Once = std::sync::Once::new();
    INSTALL.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if QUIET.load(Ordering::SeqCst) == 0 {
                previous(info);
            }
        }));
    });
    QUIET.fetch_add(1, Ordering::SeqCst);
    struct Guard;
    impl Drop for Guard {
        fn drop(&mut self) {
            QUIET.fetch_sub(1, Ordering::SeqCst);
        }
    }
    Guard
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_in_a_worker_thread_becomes_an_internal_error() {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
        let r: Result<u32> = catch_panic(
            || "input shape (1, 2, 3)".into(),
            || {
                pool.install(|| {
                    rayon::join(|| (), || -> () { panic!("index {} out of bounds", 7) });
                });
                Ok(1)
            },
        );
        let e = r.unwrap_err();
        assert_eq!(e.to_string(), "internal error, please report: index 7 out of bounds (input shape (1, 2, 3))");
        // No panic: the result and the error pass through untouched.
        assert_eq!(catch_panic(String::new, || Ok(5)), Ok(5));
        assert_eq!(catch_panic(String::new, || Err::<(), _>(Error::Interrupted)), Err(Error::Interrupted));
    }
}
