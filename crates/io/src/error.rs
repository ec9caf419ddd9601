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
        "cannot read {path}: unsupported volume format (this program reads .npy, .nii, \
         .nii.gz, .tif and .tiff; the Python package's vesselflow.load_volume reads more formats)",
        path = .path.display()
    )]
    UnsupportedVolume { path: PathBuf },
    /// The volume holds values that are not a binary mask (floats, complex, records).
    #[error("cannot read {path}: {reason}", path = .path.display())]
    NotAMask { path: PathBuf, reason: String },
    /// The volume is not three-dimensional.
    #[error(
        "cannot read {path}: expected a 3-D volume, got shape {}",
        shape_text(.shape),
        path = .path.display()
    )]
    NotThreeD { path: PathBuf, shape: Vec<u64> },
    /// The NIfTI header's voxel sizes are not finite and positive.
    #[error(
        "cannot read {path}: voxel sizes pixdim[1..4] = {pixdim:?} must be finite and non-zero \
         (pass the spacing explicitly instead)",
        path = .path.display()
    )]
    BadPixdim { path: PathBuf, pixdim: [f32; 3] },
    /// The graph's extension is none of the writable ones.
    #[error(
        "cannot write {path}: unsupported graph format (use .graphml, .json or .npz)",
        path = .path.display()
    )]
    UnsupportedGraph { path: PathBuf },
    /// The graph file could not be created or written.
    #[error("cannot write {path}: {source}", path = .path.display())]
    Write { path: PathBuf, source: std::io::Error },
    /// The arrays handed to the writer do not form a valid graph.
    #[error("cannot write {path}: invalid graph: {reason}", path = .path.display())]
    InvalidGraph { path: PathBuf, reason: String },
}

/// A shape as NumPy prints it: `(3, 4, 5)`.
pub(crate) fn shape_text(shape: &[u64]) -> String {
    let dims: Vec<String> = shape.iter().map(u64::to_string).collect();
    format!("({})", dims.join(", "))
}
