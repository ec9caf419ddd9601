//! `cli_main`: the `vesselflow` command line run inside Python, so that the wheel's
//! console script is the same program as the Rust binary.

use std::io::Write;

use pyo3::exceptions::PyKeyboardInterrupt;
use pyo3::prelude::*;

use crate::watch;

/// Run the command line `argv` (program name first) and return its exit code. The run
/// goes on a helper thread with the GIL released while this thread watches for
/// signals; Ctrl-C stops the run like in the binary (exit code 130). Any other
/// exception raised by a Python signal handler propagates. Panics are caught by
/// `run_with` itself (exit code 1, one line).
#[pyfunction]
pub fn cli_main(py: Python<'_>, argv: Vec<String>) -> PyResult<i32> {
    let (code, pending) = watch::watched(py, |stop| {
        let code = vesselflow_cli::run_with(argv, stop);
        // The host is Python, not a Rust `main`: nothing else flushes Rust's stdout.
        let _ = std::io::stdout().flush();
        code
    });
    match pending {
        Some(err) if !err.is_instance_of::<PyKeyboardInterrupt>(py) => Err(err),
        _ => Ok(code),
    }
}
