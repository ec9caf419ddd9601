//! The one place where core errors become Python exceptions.
//!
//! Caller mistakes (bad parameter values, spacing, masks) are `ValueError`, an unknown
//! parameter name is the `TypeError` Python raises for an unexpected keyword, and an
//! interrupted run re-raises whatever stopped it: the exception of the progress
//! callback, or `KeyboardInterrupt` from Ctrl-C. A run over `max_memory` is a
//! `MemoryError` naming what it needs and what is allowed. File errors are `OSError` or
//! `ValueError`.

use std::io::ErrorKind;

use pyo3::exceptions::{
    PyFileExistsError, PyFileNotFoundError, PyIsADirectoryError, PyKeyboardInterrupt, PyMemoryError,
    PyNotADirectoryError, PyOSError, PyPermissionError, PyRuntimeError, PyTypeError, PyValueError,
};
use pyo3::PyErr;
use vesselflow::Error;
use vesselflow_io::IoError;

/// Convert a core error. `pending` is the Python exception that made the observer stop
/// the run, if any; it takes the place of [`Error::Interrupted`].
pub fn to_py(err: Error, pending: Option<PyErr>) -> PyErr {
    match err {
        Error::InvalidParameter { .. } | Error::InvalidSpacing { .. } | Error::InvalidMask(_) => {
            PyValueError::new_err(err.to_string())
        }
        Error::UnknownParameter { ref name, known } => PyTypeError::new_err(format!(
            "Skeletonizer() got an unexpected keyword argument '{name}' (parameters: {})",
            known.join(", ")
        )),
        Error::Interrupted => pending.unwrap_or_else(|| PyKeyboardInterrupt::new_err("interrupted")),
        Error::ThreadPool { .. } | Error::Internal(_) => PyRuntimeError::new_err(err.to_string()),
        Error::OutOfMemory { .. } => PyMemoryError::new_err(err.to_string()),
    }
}

/// [`to_py`] for errors that no Python code caused, for use with `map_err`.
pub fn core(err: Error) -> PyErr {
    to_py(err, None)
}

/// Convert a file-layer error: failures of the file system are `OSError`, as the
/// subclass Python itself would raise (`FileNotFoundError`, `PermissionError`, ...);
/// everything about the content or the extension is `ValueError`.
pub fn io_to_py(err: IoError) -> PyErr {
    let message = err.to_string();
    match &err {
        IoError::Read { source, .. } | IoError::Write { source, .. } => match source.kind() {
            ErrorKind::NotFound => PyFileNotFoundError::new_err(message),
            ErrorKind::PermissionDenied => PyPermissionError::new_err(message),
            ErrorKind::AlreadyExists => PyFileExistsError::new_err(message),
            ErrorKind::IsADirectory => PyIsADirectoryError::new_err(message),
            ErrorKind::NotADirectory => PyNotADirectoryError::new_err(message),
            _ => PyOSError::new_err(message),
        },
        IoError::TooLarge { .. } => PyMemoryError::new_err(message),
        IoError::Corrupt { .. }
        | IoError::UnsupportedVolume { .. }
        | IoError::NotAMask { .. }
        | IoError::NotThreeD { .. }
        | IoError::BadPixdim { .. }
        | IoError::UnsupportedGraph { .. }
        | IoError::InvalidGraph { .. } => PyValueError::new_err(message),
    }
}

/// Run `f` (core or file work, usually with the GIL released), turning a panic into
/// `RuntimeError("internal error, please report: <panic message> (<context>)")`: the
/// last line of defence, so that no panic reaches Python as a `PanicException` and
/// nothing is printed by the panic hook. Must not be called with a Python object
/// borrowed in a state a panic could leave half-changed (none is).
pub fn no_panic<R>(context: impl FnOnce() -> String, f: impl FnOnce() -> R) -> Result<R, PyErr> {
    let _quiet = vesselflow::error::quiet_panics();
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).map_err(|payload| {
        let message = vesselflow::error::panic_message(payload.as_ref());
        PyRuntimeError::new_err(Error::Internal(format!("{message} ({})", context())).to_string())
    })
}
