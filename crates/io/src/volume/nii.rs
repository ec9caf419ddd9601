//! NIfTI-1 masks (`.nii`, or gzip-compressed `.nii.gz`).
//!
//! The `nifti` crate parses the 348-byte header (and detects its byte order); the
//! data are read here, because its reader ignores `vox_offset` when a file has
//! no extensions (it reads from byte 352) and holds the whole data block, decoded,
//! in memory. Here the data start at `vox_offset`, stream through a fixed buffer
//! and become 1 byte per voxel; their length must be exactly what the header
//! declares, which also caps how much of a compressed stream is ever inflated.

use super::{
    check_budget, checked_product, corrupt, dims_text, not_a_mask, read_error, spacing_in_range, stream_mask, try_vec,
    Decode, ReadLimits, VolumeFile, CHUNK_BYTES,
};
use crate::{IoError, MaskRule};
use flate2::read::MultiGzDecoder;
use ndarray::{Array3, ShapeBuilder};
use nifti::{NiftiHeader, NiftiType};
use std::fs::File;
use std::io::{BufRead, BufReader, ErrorKind, Read};
use std::path::Path;

const FORMAT: &str = "NIfTI";
/// Bytes of a NIfTI-1 header, and the first byte a single-file volume's data may start at.
const HEADER_BYTES: u64 = 348;
const SINGLE_FILE_MIN_OFFSET: u64 = 352;

/// NIfTI intensity scaling `y = scl_slope * x + scl_inter`, when the header asks for it
/// (`scl_slope` = 0 or not finite means "no scaling", as in NIfTI-1 and nibabel).
#[derive(Clone, Copy)]
struct Scaling {
    slope: f64,
    inter: f64,
}

impl Scaling {
    fn from_header(path: &Path, header: &NiftiHeader) -> Result<Option<Scaling>, IoError> {
        let (slope, inter) = (f64::from(header.scl_slope), f64::from(header.scl_inter));
        if slope == 0.0 || !slope.is_finite() {
            return Ok(None);
        }
        if !inter.is_finite() {
            return Err(corrupt(path, FORMAT, format!("scl_slope is {slope} but scl_inter is {inter}")));
        }
        Ok((slope != 1.0 || inter != 0.0).then_some(Scaling { slope, inter }))
    }

    fn apply(self, x: f64) -> f64 {
        self.slope * x + self.inter
    }
}

/// A `f32` header value as the decimal number it was written from (`0.3f32` is
/// `0.30000001192092896` as `f64`; its shortest decimal form `0.3` is what the
/// user meant).
fn f32_to_f64_decimal(x: f32) -> f64 {
    x.to_string().parse().unwrap_or(f64::from(x))
}

/// An I/O error while reading: a broken gzip stream or an early end is the
/// file's fault (corrupt), anything else the system's.
fn stream_error(path: &Path, e: std::io::Error) -> IoError {
    match e.kind() {
        ErrorKind::InvalidData | ErrorKind::InvalidInput | ErrorKind::UnexpectedEof => corrupt(path, FORMAT, e),
        _ => IoError::Read { path: path.to_path_buf(), source: e },
    }
}

pub(super) fn read_nifti(
    path: &Path,
    spacing: Option<[f64; 3]>,
    rule: MaskRule,
    limits: ReadLimits,
) -> Result<VolumeFile, IoError> {
    let file = File::open(path).map_err(read_error(path))?;
    let file_len = file.metadata().map_err(read_error(path))?.len();
    let mut reader = BufReader::new(file);
    // Compressed or not by content (gzip magic 1f 8b), whatever the name says.
    let gz = reader.fill_buf().map_err(read_error(path))?.starts_with(&[0x1f, 0x8b]);
    if gz {
        read_stream(path, MultiGzDecoder::new(reader), None, spacing, rule, limits)
    } else {
        read_stream(path, reader, Some(file_len), spacing, rule, limits)
    }
}

/// What the header says about the data block.
struct Layout {
    dims: [u64; 3],
    datatype: NiftiType,
    item_size: u64,
    offset: u64,
    data_bytes: u64,
    big_endian: bool,
    scaling: Option<Scaling>,
}

fn read_header(path: &Path, raw: &[u8; HEADER_BYTES as usize]) -> Result<(NiftiHeader, Layout), IoError> {
    let bad = |reason: String| corrupt(path, FORMAT, reason);
    let sizeof_hdr = [i32::from_le_bytes, i32::from_be_bytes].map(|f| f([raw[0], raw[1], raw[2], raw[3]]));
    if sizeof_hdr.contains(&540) {
        return Err(bad("it is a NIfTI-2 file, which this reader does not read (save it as NIfTI-1)".into()));
    }
    let header = NiftiHeader::from_reader(&raw[..]).map_err(|e| bad(format!("bad header: {e}")))?;
    if header.sizeof_hdr != HEADER_BYTES as i32 {
        return Err(bad(format!("sizeof_hdr is {}, not 348", header.sizeof_hdr)));
    }
    if &header.magic != b"n+1\0" {
        return Err(bad("the header is of a .hdr/.img pair (magic \"ni1\"), not of a single .nii file".into()));
    }

    let ndim = usize::from(header.dim[0]);
    if !(1..=7).contains(&ndim) {
        return Err(bad(format!("dim[0] = {ndim} is not a number of dimensions (1 to 7)")));
    }
    // `dim` is a signed 16-bit field: 0 and "negative" sizes are header damage.
    let shape: Vec<u64> = header.dim[1..=ndim].iter().map(|&d| u64::from(d)).collect();
    if let Some(i) = shape.iter().position(|&d| d == 0 || d > i16::MAX as u64) {
        return Err(bad(format!("dim[{}] = {} is not a size", i + 1, header.dim[i + 1] as i16)));
    }
    if ndim < 3 || shape[3..].iter().any(|&d| d != 1) {
        return Err(IoError::NotThreeD { path: path.to_path_buf(), shape });
    }
    let dims = [shape[0], shape[1], shape[2]];

    let datatype = header.data_type().map_err(|e| bad(format!("bad datatype {}: {e}", header.datatype)))?;
    let item_size = match datatype {
        NiftiType::Uint8 | NiftiType::Int8 => 1,
        NiftiType::Uint16 | NiftiType::Int16 => 2,
        NiftiType::Uint32 | NiftiType::Int32 | NiftiType::Float32 => 4,
        NiftiType::Uint64 | NiftiType::Int64 | NiftiType::Float64 => 8,
        other => {
            return Err(not_a_mask(
                path,
                format!("NIfTI datatype {other:?} is not a mask: save a bool, integer or float mask"),
            ))
        }
    };

    let vox_offset = header.vox_offset;
    // nibabel reads `int(vox_offset)`; a value inside the header is refused as nibabel does.
    if !vox_offset.is_finite() || f64::from(vox_offset) < SINGLE_FILE_MIN_OFFSET as f64 {
        return Err(bad(format!(
            "vox_offset = {vox_offset} (the data of a .nii file start at byte {SINGLE_FILE_MIN_OFFSET} or later)"
        )));
    }
    let offset = vox_offset as u64;
    let data_bytes = checked_product(&dims)
        .and_then(|n| n.checked_mul(item_size))
        .ok_or_else(|| bad(format!("dim {} is too large", dims_text(&dims))))?;
    let scaling = Scaling::from_header(path, &header)?;
    let big_endian = header.endianness == nifti::Endianness::Big;
    Ok((header, Layout { dims, datatype, item_size, offset, data_bytes, big_endian, scaling }))
}

fn read_stream<R: Read>(
    path: &Path,
    mut reader: R,
    file_len: Option<u64>,
    spacing: Option<[f64; 3]>,
    rule: MaskRule,
    limits: ReadLimits,
) -> Result<VolumeFile, IoError> {
    let mut raw = [0u8; HEADER_BYTES as usize];
    reader.read_exact(&mut raw).map_err(|e| match e.kind() {
        ErrorKind::UnexpectedEof => corrupt(path, FORMAT, "the file ends inside the 348-byte header"),
        _ => stream_error(path, e),
    })?;
    let (header, layout) = read_header(path, &raw)?;
    let Layout { dims, datatype, item_size, offset, data_bytes, .. } = layout;

    let spacing = match spacing {
        Some(s) => s,
        None => {
            // The sign is ignored (NIfTI readers do: it is the axis direction, which
            // qform/sform carry). The range is checked on the decimal the header
            // was written from, so that 1e-12 written as f32 is accepted.
            let pixdim = [header.pixdim[1], header.pixdim[2], header.pixdim[3]];
            let spacing = pixdim.map(|p| f32_to_f64_decimal(p.abs()));
            if !spacing.iter().all(|&s| spacing_in_range(s)) {
                return Err(IoError::BadPixdim { path: path.to_path_buf(), pixdim });
            }
            spacing
        }
    };

    let declares = || {
        format!(
            "the header declares {} voxels of {datatype:?} ({data_bytes} bytes from byte {offset})",
            dims_text(&dims)
        )
    };
    if let Some(file_len) = file_len {
        // Uncompressed: the data must be exactly the rest of the file.
        let end = offset.checked_add(data_bytes);
        if end != Some(file_len) {
            let holds = file_len.saturating_sub(offset);
            let what = if end.is_none_or(|e| e > file_len) { "truncated" } else { "trailing bytes" };
            return Err(corrupt(path, FORMAT, format!("{what}: {}, the file holds {holds}", declares())));
        }
    }
    let count = data_bytes / item_size;
    let buffer_bytes = data_bytes.min(CHUNK_BYTES.next_multiple_of(item_size));
    check_budget(path, limits, count.checked_add(buffer_bytes), || {
        format!("the header declares {} voxels", dims_text(&dims))
    })?;

    // Skip the extensions (or padding) between the header and vox_offset.
    let skip = offset - HEADER_BYTES;
    let skipped =
        std::io::copy(&mut (&mut reader).take(skip), &mut std::io::sink()).map_err(|e| stream_error(path, e))?;
    if skipped < skip {
        return Err(corrupt(
            path,
            FORMAT,
            format!("the file ends at byte {} before vox_offset = {offset}", 348 + skipped),
        ));
    }

    let mut values = try_vec(path, count)?;
    stream_voxels(&mut reader, &layout, count, buffer_bytes, rule, &mut values)
        .map_err(|e| match e.kind() {
            ErrorKind::UnexpectedEof => {
                corrupt(path, FORMAT, format!("truncated: {}, the data end sooner", declares()))
            }
            _ => stream_error(path, e),
        })?
        .map_err(|reason| not_a_mask(path, reason))?;
    if file_len.is_none() {
        // Compressed: the stream must end here (this also checks the gzip CRC).
        let more = reader.read(&mut [0u8; 1]).map_err(|e| stream_error(path, e))?;
        if more > 0 {
            return Err(corrupt(path, FORMAT, format!("trailing data: {}, the stream holds more", declares())));
        }
    }
    let [n0, n1, n2] = dims.map(|d| d as usize);
    // NIfTI stores voxels with the first index fastest: Fortran order, axes (i, j, k).
    let mask = Array3::from_shape_vec((n0, n1, n2).f(), values).map_err(|e| corrupt(path, FORMAT, e))?;
    let affine = affine(&header).ok_or_else(|| {
        corrupt(path, FORMAT, "the voxel-to-world affine (sform or qform) is not finite numbers".to_string())
    })?;
    Ok(VolumeFile { mask, spacing, affine })
}

/// The header's voxel-to-world affine, chosen as nibabel's `get_best_affine` and
/// the NIfTI-1 standard do: the sform when `sform_code` > 0, else the qform (the
/// quaternion, `qfac` and `pixdim`) when `qform_code` > 0, else the scaling by
/// `|pixdim[1..4]|` (the standard's method 1). `None` if it is not finite.
fn affine(header: &NiftiHeader) -> Option<[[f64; 4]; 4]> {
    let mut a = [[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]];
    let pixdim = [1, 2, 3].map(|i| f64::from(header.pixdim[i]).abs());
    if header.sform_code > 0 {
        for (row, srow) in a.iter_mut().zip([header.srow_x, header.srow_y, header.srow_z]) {
            *row = srow.map(f64::from);
        }
    } else if header.qform_code > 0 {
        let [b, c, d] = [header.quatern_b, header.quatern_c, header.quatern_d].map(f64::from);
        let w = (1.0 - (b * b + c * c + d * d)).max(0.0).sqrt();
        let rotation = quaternion_matrix(w, b, c, d);
        let qfac = if header.pixdim[0] < 0.0 { -1.0 } else { 1.0 };
        let scale = [pixdim[0], pixdim[1], qfac * pixdim[2]];
        let offset = [header.quatern_x, header.quatern_y, header.quatern_z].map(f64::from);
        for row in 0..3 {
            for col in 0..3 {
                a[row][col] = rotation[row][col] * scale[col];
            }
            a[row][3] = offset[row];
        }
    } else {
        for axis in 0..3 {
            a[axis][axis] = pixdim[axis];
        }
    }
    a.iter().flatten().all(|x| x.is_finite()).then_some(a)
}

/// The rotation of the quaternion `(w, x, y, z)`, normalised first.
fn quaternion_matrix(w: f64, x: f64, y: f64, z: f64) -> [[f64; 3]; 3] {
    let norm = w * w + x * x + y * y + z * z;
    if norm < f64::EPSILON {
        return [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    }
    let s = 2.0 / norm;
    let (xs, ys, zs) = (x * s, y * s, z * s);
    let (wx, wy, wz) = (w * xs, w * ys, w * zs);
    let (xx, xy, xz) = (x * xs, x * ys, x * zs);
    let (yy, yz, zz) = (y * ys, y * zs, z * zs);
    [[1.0 - (yy + zz), xy - wz, xz + wy], [xy + wz, 1.0 - (xx + zz), yz - wx], [xz - wy, yz + wx, 1.0 - (xx + yy)]]
}

/// [`stream_mask`] for the header's datatype: scaled data (`scl_slope`, `scl_inter`)
/// are floating point, as in nibabel, so the rule sees the values the user sees.
fn stream_voxels(
    reader: &mut impl Read,
    layout: &Layout,
    count: u64,
    buffer_bytes: u64,
    rule: MaskRule,
    out: &mut Vec<u8>,
) -> std::io::Result<Result<(), String>> {
    fn typed<T: Decode>(
        reader: &mut impl Read,
        layout: &Layout,
        count: u64,
        buffer_bytes: u64,
        rule: MaskRule,
        out: &mut Vec<u8>,
    ) -> std::io::Result<Result<(), String>> {
        let big = layout.big_endian;
        match layout.scaling {
            None => stream_mask(reader, count, buffer_bytes, big, rule, |x: T| x, out),
            Some(s) => stream_mask(reader, count, buffer_bytes, big, rule, |x: T| s.apply(x.to_f64()), out),
        }
    }
    match layout.datatype {
        NiftiType::Uint8 => typed::<u8>(reader, layout, count, buffer_bytes, rule, out),
        NiftiType::Int8 => typed::<i8>(reader, layout, count, buffer_bytes, rule, out),
        NiftiType::Uint16 => typed::<u16>(reader, layout, count, buffer_bytes, rule, out),
        NiftiType::Int16 => typed::<i16>(reader, layout, count, buffer_bytes, rule, out),
        NiftiType::Uint32 => typed::<u32>(reader, layout, count, buffer_bytes, rule, out),
        NiftiType::Int32 => typed::<i32>(reader, layout, count, buffer_bytes, rule, out),
        NiftiType::Uint64 => typed::<u64>(reader, layout, count, buffer_bytes, rule, out),
        NiftiType::Int64 => typed::<i64>(reader, layout, count, buffer_bytes, rule, out),
        NiftiType::Float32 => typed::<f32>(reader, layout, count, buffer_bytes, rule, out),
        // `read_header` admits no other type.
        _ => typed::<f64>(reader, layout, count, buffer_bytes, rule, out),
    }
}
