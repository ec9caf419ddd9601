//! The one error type of the file layer. Every message names the file and the
//! problem, in a form a command-line user can act on.

use std::path::PathBuf;

/// Why a volume could not be read or a graph could not be written.
#[derive(Debug, thiserror::Error)]
pub enum IoError {
    /// The file could not be opened or read (missing, permissions, I/O).
    #[error("cannot read {path}: {source}", path = .path.display())]
    Read { path: PathBuf, source: std::io::Error },
    /// The file exists but is not a valid file of its format (bad header, truncated).
    #[error("cannot read {path}: not a valid {format} file: {reason}", path = .path.display())]
    Corrupt { path: PathBuf, format: &'static str, reason: String },
    /// The volume's extension is none of the readable ones.
    #[error(
        "cannot read {path}: unsupported volume format (this program reads .npy, .npz, .nii, \
         .nii.gz, .tif and .tiff; the Python package's vesselflow.load_volume reads more formats)",
        path = .path.display()
    )]
    UnsupportedVolume { path: PathBuf },
    /// The volume holds values that are not a mask by the input rule ([`crate::MaskRule`]:
    /// a label or probability image without a threshold or label) or cannot be one (complex, records).
    #[error("cannot read {path}: {reason}", path = .path.display())]
    NotAMask { path: PathBuf, reason: String },
    /// The volume is not three-dimensional.
    #[error(
        "cannot read {path}: expected a 3-D volume, got shape {}",
        shape_text(.shape),
        path = .path.display()
    )]
    NotThreeD { path: PathBuf, shape: Vec<u64> },
    /// The NIfTI header's voxel sizes are not finite numbers whose magnitude lies in
    /// `[1e-12, 1e12]` (the sign is ignored, as NIfTI readers do).
    #[error(
        "cannot read {path}: voxel sizes pixdim[1..4] = {pixdim:?} must be finite numbers of \
         magnitude 1e-12 to 1e12 (pass the spacing explicitly instead)",
        path = .path.display()
    )]
    BadPixdim { path: PathBuf, pixdim: [f32; 3] },
    /// Reading the file would take more memory than the reader may use: the header
    /// declares more data than the budget ([`crate::ReadLimits`]) allows. Nothing
    /// of that size was allocated or inflated.
    #[error(
        "cannot read {path}: {declared} ({needed}) but only {allowed} may be used; \
         free memory, raise the memory budget or crop the volume",
        path = .path.display(),
        needed = needed_text(*.needed),
        allowed = crate::budget::human_bytes(*.allowed)
    )]
    TooLarge {
        path: PathBuf,
        /// What the file declares, e.g. "the header declares 512×512×4096 voxels".
        declared: String,
        /// Bytes the read would allocate (`u64::MAX` when that overflows 64 bits).
        needed: u64,
        /// The budget in bytes.
        allowed: u64,
    },
    /// The graph's extension is none of the writable ones.
    #[error(
        "cannot write {path}: unsupported graph format (use {extensions})",
        path = .path.display(),
        extensions = crate::GraphFormat::extensions_text()
    )]
    UnsupportedGraph { path: PathBuf },
    /// The graph file could not be created or written.
    #[error("cannot write {path}: {source}", path = .path.display())]
    Write { path: PathBuf, source: std::io::Error },
    /// The arrays handed to the writer do not form a valid graph.
    #[error("cannot write {path}: invalid graph: {reason}", path = .path.display())]
    InvalidGraph { path: PathBuf, reason: String },
}

/// Bytes needed, where `u64::MAX` stands for "more than 64 bits can count".
fn needed_text(needed: u64) -> String {
    if needed == u64::MAX {
        "more than 16 EiB".to_string()
    } else {
        crate::budget::human_bytes(needed)
    }
}

/// A shape as NumPy prints it: `(3, 4, 5)`.
pub(crate) fn shape_text(shape: &[u64]) -> String {
    let dims: Vec<String> = shape.iter().map(u64::to_string).collect();
    format!("({})", dims.join(", "))
}
