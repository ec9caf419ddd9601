//! Volume readers: `.npy`, `.npz`, NIfTI (`.nii`, `.nii.gz`) and TIFF stack (`.tif`,
//! `.tiff`) files to a binary mask, with its spacing and voxel-to-world affine.
//!
//! Values become a mask by the input rule ([`MaskRule`], see [`crate::binarise`]),
//! applied while the data stream through the reader, so the mask takes 1 byte per
//! voxel whatever the file's data type: bool, integer and floating-point data are
//! accepted if they are binary, and anything else only with a threshold or a label.
//!
//! Every reader treats the file as hostile: what the header declares (shape ×
//! bytes per value, overflow-checked) is checked against the file's real size
//! where the data are uncompressed and against the caller's byte budget
//! ([`ReadLimits`]) before anything of that size is allocated or inflated;
//! buffers sized from the file are reserved fallibly; compressed streams are read
//! only up to what the header declares.

mod nii;
mod npy;
mod tif;

use crate::{IoError, MaskRule};
use ndarray::Array3;
use std::fmt::Write as _;
use std::path::Path;
use vesselflow::volume::{MAX_SPACING, MIN_SPACING};

/// A mask read from a file, with the voxel spacing the file declares.
#[derive(Debug, Clone, PartialEq)]
pub struct VolumeFile {
    /// 1 = vessel, 0 = background, axes as stored in the file. Memory order is
    /// the file's (C for most `.npy`, Fortran for NIfTI and Fortran `.npy`), so
    /// no copy is made; use `as_standard_layout` if C order is needed.
    pub mask: Array3<u8>,
    /// Physical size of a voxel along axes 0, 1, 2: NIfTI `pixdim[1..4]`, or
    /// `[1, 1, 1]` for formats that carry none.
    pub spacing: [f64; 3],
    /// The 4 × 4 voxel-to-world affine (row-major; voxel index `(i, j, k, 1)` to
    /// world `(x, y, z, 1)`): NIfTI's sform, else its qform, else `pixdim`
    /// scaling; for formats without one the diagonal of `spacing`.
    pub affine: [[f64; 4]; 4],
}

/// The affine of a format that has only a spacing: `diag(spacing, 1)`.
pub fn spacing_affine(spacing: [f64; 3]) -> [[f64; 4]; 4] {
    let mut a = [[0.0; 4]; 4];
    for (axis, s) in spacing.iter().enumerate() {
        a[axis][axis] = *s;
    }
    a[3][3] = 1.0;
    a
}

/// How much memory a read may take.
///
/// `max_bytes` bounds everything the reader allocates: the mask (1 byte per
/// voxel), its read buffer (at most a few MiB) and, for TIFF, one decoded page
/// and its compressed strips. A file that declares more is refused with
/// [`IoError::TooLarge`] before that memory is allocated or any data inflated.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReadLimits {
    /// The byte budget.
    pub max_bytes: u64,
}

impl ReadLimits {
    /// A budget of `max_bytes` bytes.
    pub fn new(max_bytes: u64) -> ReadLimits {
        ReadLimits { max_bytes }
    }

    /// The memory this process may still use ([`crate::budget::usable_memory`]:
    /// available memory, cgroup and `RLIMIT_AS` room), at most 64 GiB.
    pub fn for_this_process() -> ReadLimits {
        ReadLimits { max_bytes: crate::budget::default_budget() }
    }
}

impl Default for ReadLimits {
    /// [`ReadLimits::for_this_process`].
    fn default() -> ReadLimits {
        ReadLimits::for_this_process()
    }
}

/// The volume formats [`read_volume`] understands, by file name.
enum VolumeFormat {
    Npy,
    Npz,
    Nifti,
    Tiff,
}

fn volume_format(path: &Path) -> Option<VolumeFormat> {
    let name = path.file_name()?.to_string_lossy().to_ascii_lowercase();
    if name.ends_with(".npy") {
        Some(VolumeFormat::Npy)
    } else if name.ends_with(".npz") {
        Some(VolumeFormat::Npz)
    } else if name.ends_with(".nii") || name.ends_with(".nii.gz") {
        Some(VolumeFormat::Nifti)
    } else if name.ends_with(".tif") || name.ends_with(".tiff") {
        Some(VolumeFormat::Tiff)
    } else {
        None
    }
}

/// Read a binary vessel mask from `.npy`, `.npz`, `.nii`, `.nii.gz`, `.tif` or `.tiff`,
/// with the file's spacing, within the default memory budget
/// ([`ReadLimits::for_this_process`]).
///
/// The data must be a binary mask ([`MaskRule::Binary`]: bool, integers with at
/// most one non-zero value, floats all exactly 0 or 1; else [`IoError::NotAMask`]
/// naming the values found); [`read_volume_limited`] takes a threshold or a label
/// instead.
///
/// `.npy`: bool, integer or float32/float64 dtype, either byte order, C or Fortran
/// order; spacing 1, 1, 1. `.npz`: the array `mask`, or the only one besides a
/// `spacing` array, which gives the spacing ([`read_volume_key`] picks another).
/// NIfTI-1: the header's byte order, `vox_offset` and
/// `scl_slope`/`scl_inter` are honoured (scaled data are floating point); a 4-D
/// (or higher) volume whose extra dimensions are all 1 is read as 3-D; spacing is `|pixdim[1..4]|`, which must
/// be finite with magnitude in `[1e-12, 1e12]` (else [`IoError::BadPixdim`]).
/// TIFF: greyscale pages of 8 to 64 bits as axes (page, row, column), ImageJ
/// spacing. Any other content is refused with an error naming the file and the
/// problem.
pub fn read_volume(path: &Path) -> Result<VolumeFile, IoError> {
    read_volume_limited(path, None, MaskRule::Binary, ReadLimits::for_this_process())
}

/// Like [`read_volume`], but with a spacing given by the caller, which replaces
/// (and skips the validation of) whatever the file declares. Validating
/// `spacing` itself is the caller's job (the core's `run` does it).
pub fn read_volume_with_spacing(path: &Path, spacing: [f64; 3]) -> Result<VolumeFile, IoError> {
    read_volume_limited(path, Some(spacing), MaskRule::Binary, ReadLimits::for_this_process())
}

/// [`read_volume`] (`spacing` = `None`) or [`read_volume_with_spacing`], with the
/// values binarised by `rule`, within the caller's memory budget: a file whose declared content would need more than
/// `limits.max_bytes` is refused with [`IoError::TooLarge`] before anything of
/// that size is allocated or inflated.
///
/// ```no_run
/// use std::path::Path;
/// use vesselflow_io::{read_volume_limited, IoError, MaskRule, ReadLimits};
///
/// match read_volume_limited(Path::new("mask.nii.gz"), None, MaskRule::Binary, ReadLimits::new(2 << 30)) {
///     Ok(volume) => println!("{:?}", volume.mask.dim()),
///     Err(IoError::TooLarge { needed, .. }) => println!("needs {needed} bytes"),
///     Err(e) => return Err(e.into()),
/// }
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
pub fn read_volume_limited(
    path: &Path,
    spacing: Option<[f64; 3]>,
    rule: MaskRule,
    limits: ReadLimits,
) -> Result<VolumeFile, IoError> {
    read_volume_key(path, None, spacing, rule, limits)
}

/// [`read_volume_limited`], with the array of an `.npz` named by `key` (other
/// formats hold one volume: a `key` is refused for them).
pub fn read_volume_key(
    path: &Path,
    key: Option<&str>,
    spacing: Option<[f64; 3]>,
    rule: MaskRule,
    limits: ReadLimits,
) -> Result<VolumeFile, IoError> {
    let format = volume_format(path).ok_or_else(|| IoError::UnsupportedVolume { path: path.to_path_buf() })?;
    if key.is_some() && !matches!(format, VolumeFormat::Npz) {
        return Err(not_a_mask(path, "a key (an array name) applies to .npz files only".to_string()));
    }
    match format {
        VolumeFormat::Npy => {
            let mask = npy::read_npy(path, rule, limits)?;
            let spacing = spacing.unwrap_or([1.0; 3]);
            Ok(VolumeFile { mask, spacing, affine: spacing_affine(spacing) })
        }
        VolumeFormat::Npz => {
            let (mask, file_spacing) = npy::read_npz(path, key, spacing.is_none(), rule, limits)?;
            let spacing = spacing.or(file_spacing).unwrap_or([1.0; 3]);
            Ok(VolumeFile { mask, spacing, affine: spacing_affine(spacing) })
        }
        VolumeFormat::Nifti => nii::read_nifti(path, spacing, rule, limits),
        VolumeFormat::Tiff => tif::read_tiff(path, spacing, rule, limits),
    }
}

fn read_error(path: &Path) -> impl FnOnce(std::io::Error) -> IoError + '_ {
    move |source| IoError::Read { path: path.to_path_buf(), source }
}

fn corrupt(path: &Path, format: &'static str, reason: impl ToString) -> IoError {
    IoError::Corrupt { path: path.to_path_buf(), format, reason: reason.to_string() }
}

/// The values of a file that are not a mask under the rule.
fn not_a_mask(path: &Path, reason: String) -> IoError {
    IoError::NotAMask { path: path.to_path_buf(), reason }
}

/// A value type decoded from its bytes in either byte order.
trait Decode: crate::Sample {
    const SIZE: usize;
    fn decode(bytes: &[u8], big_endian: bool) -> Self;
}

macro_rules! decode {
    ($($t:ty),*) => {$(
        impl Decode for $t {
            const SIZE: usize = std::mem::size_of::<$t>();
            fn decode(bytes: &[u8], big_endian: bool) -> $t {
                let mut b = [0u8; std::mem::size_of::<$t>()];
                b.copy_from_slice(bytes);
                if big_endian { <$t>::from_be_bytes(b) } else { <$t>::from_le_bytes(b) }
            }
        }
    )*};
}
decode!(u8, i8, u16, i16, u32, i32, u64, i64, f32, f64);

/// Spacing values outside the core's `[MIN_SPACING, MAX_SPACING]` (in magnitude) are
/// refused: they are header corruption, and squared or cubed later they would
/// underflow to 0 or overflow to infinity.
fn spacing_in_range(s: f64) -> bool {
    s.is_finite() && (MIN_SPACING..=MAX_SPACING).contains(&s.abs())
}

/// Bytes of the read buffer: data are streamed through it, never held whole.
const CHUNK_BYTES: u64 = 1 << 20;

/// Shape as the product people write: `512×512×4096`.
fn dims_text(dims: &[u64]) -> String {
    let mut text = String::new();
    for (i, d) in dims.iter().enumerate() {
        let _ = write!(text, "{}{d}", if i > 0 { "×" } else { "" });
    }
    text
}

/// Refuse a read whose memory `needed` (`None`: overflows `u64`) exceeds the budget.
fn check_budget(
    path: &Path,
    limits: ReadLimits,
    needed: Option<u64>,
    declared: impl FnOnce() -> String,
) -> Result<u64, IoError> {
    match needed {
        Some(n) if n <= limits.max_bytes => Ok(n),
        _ => Err(IoError::TooLarge {
            path: path.to_path_buf(),
            declared: declared(),
            needed: needed.unwrap_or(u64::MAX),
            allowed: limits.max_bytes,
        }),
    }
}

/// The product of `dims`, `None` on overflow.
fn checked_product(dims: &[u64]) -> Option<u64> {
    dims.iter().try_fold(1u64, |acc, &d| acc.checked_mul(d))
}

/// An empty vector with room for `len` bytes, or a clean error when the
/// allocator refuses (the budget was checked before, but the system may have
/// less than it said).
fn try_vec(path: &Path, len: u64) -> Result<Vec<u8>, IoError> {
    let mut v = Vec::new();
    match usize::try_from(len).ok().map(|n| v.try_reserve_exact(n)) {
        Some(Ok(())) => Ok(v),
        _ => Err(IoError::Read {
            path: path.to_path_buf(),
            source: std::io::Error::new(
                std::io::ErrorKind::OutOfMemory,
                format!("cannot allocate {} for the mask", crate::budget::human_bytes(len)),
            ),
        }),
    }
}

/// Read `count` values of type `T` (in the given byte order) through a buffer of
/// `buffer_bytes`, `convert` each (NIfTI scaling; identity otherwise) and append
/// its mask by `rule` to `out`. The inner `Err` says why the data are not a mask;
/// reading stops at the first chunk that shows it.
fn stream_mask<T: Decode, S: crate::Sample>(
    reader: &mut impl std::io::Read,
    count: u64,
    buffer_bytes: u64,
    big_endian: bool,
    rule: MaskRule,
    convert: impl Fn(T) -> S,
    out: &mut Vec<u8>,
) -> std::io::Result<Result<(), String>> {
    let mut binariser = crate::Binariser::<S>::new(rule);
    let mut buffer = vec![0u8; buffer_bytes as usize];
    let chunk_items = (buffer_bytes / T::SIZE as u64).max(1);
    let mut done = 0u64;
    while done < count {
        let items = chunk_items.min(count - done);
        let chunk = &mut buffer[..items as usize * T::SIZE];
        reader.read_exact(chunk)?;
        binariser.extend(chunk.chunks_exact(T::SIZE).map(|b| convert(T::decode(b, big_endian))), out);
        if binariser.refused() {
            break;
        }
        done += items;
    }
    Ok(binariser.finish())
}
