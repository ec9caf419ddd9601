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
    /// Spacing must be three finite, strictly positive numbers.
    #[error("invalid spacing {0:?}: need three finite numbers > 0")]
    InvalidSpacing(Vec<f64>),
    /// The mask cannot be processed as given (shape, size).
    #[error("invalid mask: {0}")]
    InvalidMask(String),
    /// Every voxel is foreground: almost always an image or an inverted mask.
    #[error(
        "mask is foreground everywhere ({0} voxels): pass a binary vessel segmentation \
         (non-zero = vessel), not an intensity image or an inverted mask"
    )]
    AllForeground(usize),
    /// The caller's observer asked to stop (e.g. Ctrl-C).
    #[error("interrupted")]
    Interrupted,
    /// The thread pool could not be created.
    #[error("cannot start {threads} worker threads: {reason}")]
    ThreadPool { threads: usize, reason: String },
}

/// Result alias of the core.
pub type Result<T> = std::result::Result<T, Error>;
