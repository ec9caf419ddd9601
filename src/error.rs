//! The one error type of the core. Every failure a caller can cause is a variant
//! whose message names the problem; the bindings map these to Python exceptions.

use thiserror::Error;

/// Everything the core can refuse or fail with.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum Error {
    /// A parameter has the wrong type or a value outside its range.
    #[error("invalid parameter `{name}`: {reason}")]
    InvalidParameter { name: String, reason: String },
    /// A parameter name that does not exist; `known` lists the names that do.
    #[error("unknown parameter `{name}` (known: {})", known.join(", "))]
    UnknownParameter { name: String, known: &'static [&'static str] },
    /// Spacing must be three finite numbers in `range`
    /// ([`crate::volume::invalid_spacing`] gives the supported one).
    #[error(
        "invalid spacing {spacing:?}: need three finite numbers in [{:e}, {:e}] (physical units per voxel)",
        range[0],
        range[1]
    )]
    InvalidSpacing { spacing: Vec<f64>, range: [f64; 2] },
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
    #[error("{}", out_of_memory_message(*needed, *allowed))]
    OutOfMemory { needed: u64, allowed: u64 },
}

/// `bytes` in the largest binary unit that keeps it at or above 1 (`1.5 GiB`).
fn format_bytes(bytes: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut x = bytes as f64;
    let mut u = 0;
    while x >= 1024.0 && u + 1 < UNITS.len() {
        x /= 1024.0;
        u += 1;
    }
    if u == 0 {
        format!("{bytes} B")
    } else {
        format!("{x:.1} {}", UNITS[u])
    }
}

/// `1.5 GiB (1610612736 bytes)`, or `1000 B` below a KiB.
fn exact_bytes(bytes: u64) -> String {
    if bytes < 1024 {
        format_bytes(bytes)
    } else {
        format!("{} ({bytes} bytes)", format_bytes(bytes))
    }
}

/// The message of [`Error::OutOfMemory`].
fn out_of_memory_message(needed: u64, allowed: u64) -> String {
    if allowed == 0 {
        format!(
            "out of memory: an allocation of {} ({needed} bytes) failed; crop the volume to the \
             vessels, split it into blocks or use a machine with more memory",
            format_bytes(needed)
        )
    } else {
        format!(
            "out of memory: this run needs about {} but max_memory allows {}; crop the volume to \
             the vessels, split it into blocks, or raise max_memory= if \
             more is free",
            exact_bytes(needed),
            exact_bytes(allowed)
        )
    }
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
