//! Volume readers: `.npy`, NIfTI (`.nii`, `.nii.gz`) and TIFF stack (`.tif`, `.tiff`)
//! files to a binary mask.
//!
//! A mask is "non-zero = vessel". Integer and bool data are binarised as such;
//! floating-point data are refused (they are usually an intensity or probability
//! image) except NIfTI volumes whose every value is exactly 0 or 1, because
//! segmentation tools often store NIfTI masks as float32.

use crate::error::shape_text;
use crate::IoError;
use ndarray::{Array3, ShapeBuilder};
use nifti::{DataElement, NiftiObject, NiftiType, NiftiVolume};
use num_traits::{AsPrimitive, ToPrimitive};
use std::fs::File;
use std::io::{BufReader, Read, Seek};
use std::path::Path;
use tiff::decoder::{Decoder, DecodingResult, Limits};
use tiff::tags::Tag;
use tiff::ColorType;

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
}

/// The volume formats [`read_volume`] understands, by file name.
enum VolumeFormat {
    Npy,
    Nifti,
    Tiff,
}

fn volume_format(path: &Path) -> Option<VolumeFormat> {
    let name = path.file_name()?.to_string_lossy().to_ascii_lowercase();
    if name.ends_with(".npy") {
        Some(VolumeFormat::Npy)
    } else if name.ends_with(".nii") || name.ends_with(".nii.gz") {
        Some(VolumeFormat::Nifti)
    } else if name.ends_with(".tif") || name.ends_with(".tiff") {
        Some(VolumeFormat::Tiff)
    } else {
        None
    }
}

/// Read a binary vessel mask from `.npy`, `.nii` or `.nii.gz`, with the file's
/// spacing (NIfTI `pixdim`, validated finite and non-zero; `.npy`: 1, 1, 1).
///
/// `.npy`: bool or any integer dtype, either byte order, C or Fortran order.
/// NIfTI: integer data, or float data that are all exactly 0 or 1 (after the
/// header's `scl_slope`/`scl_inter`); a 4-D (or higher) volume whose extra
/// dimensions are all 1 is read as 3-D. Any other content is refused with an
/// error naming the file and the problem.
pub fn read_volume(path: &Path) -> Result<VolumeFile, IoError> {
    read(path, None)
}

/// Like [`read_volume`], but with a spacing given by the caller, which replaces
/// (and skips the validation of) whatever the file declares. Validating
/// `spacing` itself is the caller's job (the core's `run` does it).
pub fn read_volume_with_spacing(path: &Path, spacing: [f64; 3]) -> Result<VolumeFile, IoError> {
    read(path, Some(spacing))
}

fn read(path: &Path, spacing: Option<[f64; 3]>) -> Result<VolumeFile, IoError> {
    match volume_format(path) {
        Some(VolumeFormat::Npy) => {
            let mask = read_npy(path)?;
            Ok(VolumeFile { mask, spacing: spacing.unwrap_or([1.0; 3]) })
        }
        Some(VolumeFormat::Nifti) => read_nifti(path, spacing),
        Some(VolumeFormat::Tiff) => read_tiff(path, spacing),
        None => Err(IoError::UnsupportedVolume { path: path.to_path_buf() }),
    }
}

fn read_error(path: &Path) -> impl FnOnce(std::io::Error) -> IoError + '_ {
    move |source| IoError::Read { path: path.to_path_buf(), source }
}

fn corrupt(path: &Path, format: &'static str, reason: impl ToString) -> IoError {
    IoError::Corrupt { path: path.to_path_buf(), format, reason: reason.to_string() }
}

const THRESHOLD_HINT: &str = "a mask must hold bool or integer values (non-zero = vessel): threshold the image first \
     (e.g. `image > t`) and save the result";

/// What an `.npy` header says about the data that follows it.
struct NpyHeader {
    descr: py_literal::Value,
    fortran_order: bool,
    shape: Vec<u64>,
}

/// Parse the header of an `.npy` file (format: `numpy.lib.format`, versions 1 to 3):
/// magic string, version, header length, then a Python dict literal with `descr`,
/// `fortran_order` and `shape`. Leaves `reader` at the first data byte.
fn read_npy_header(reader: &mut impl Read) -> Result<NpyHeader, String> {
    let too_short = |_| "the file ends inside the header".to_string();
    let mut preamble = [0u8; 8];
    reader.read_exact(&mut preamble).map_err(too_short)?;
    if &preamble[..6] != b"\x93NUMPY" {
        return Err("it does not start with the .npy magic string".to_string());
    }
    let length_bytes = match preamble[6] {
        1 => 2,
        2 | 3 => 4,
        major => return Err(format!("unknown format version {major}.{}", preamble[7])),
    };
    let mut length = [0u8; 4];
    reader.read_exact(&mut length[..length_bytes]).map_err(too_short)?;
    let mut text = vec![0u8; u32::from_le_bytes(length) as usize];
    reader.read_exact(&mut text).map_err(too_short)?;
    let text = std::str::from_utf8(&text).map_err(|_| "the header is not text".to_string())?;
    let dict: py_literal::Value =
        text.trim_end().parse().map_err(|e| format!("the header is not a Python literal: {e}"))?;

    let entries = dict.as_dict().ok_or("the header is not a dict")?;
    let get = |key: &str| {
        entries
            .iter()
            .find(|(k, _)| k.as_string().is_some_and(|k| k == key))
            .map(|(_, v)| v)
            .ok_or(format!("the header has no '{key}'"))
    };
    let Some(fortran_order) = get("fortran_order")?.as_boolean() else {
        return Err("'fortran_order' is not True or False".to_string());
    };
    let shape = get("shape")?
        .as_tuple()
        .and_then(|dims| dims.iter().map(|d| d.as_integer()?.to_u64()).collect::<Option<Vec<_>>>())
        .ok_or("'shape' is not a tuple of non-negative integers")?;
    Ok(NpyHeader { descr: get("descr")?.clone(), fortran_order, shape })
}

/// Bytes per element of a mask dtype descriptor (`|b1`, `<i4`, `>u2`, ...), or
/// what kind of non-mask data it describes.
fn mask_item_size(descr: &py_literal::Value) -> Result<usize, &'static str> {
    let Some(descr) = descr.as_string() else {
        return Err("a structured dtype");
    };
    let body = descr.trim_start_matches(['<', '>', '|', '=']);
    let (kind, size) = body.split_at(body.chars().next().map_or(0, char::len_utf8));
    match (kind, size) {
        ("b", "1") => Ok(1),
        ("i" | "u", "1" | "2" | "4" | "8") => Ok(size.parse().unwrap_or(1)),
        ("f" | "e" | "d" | "g", _) => Err("floating point"),
        ("c", _) => Err("complex"),
        ("O", _) => Err("Python objects"),
        _ => Err("not a bool or integer type"),
    }
}

fn read_npy(path: &Path) -> Result<Array3<u8>, IoError> {
    let file = File::open(path).map_err(read_error(path))?;
    let file_len = file.metadata().map_err(read_error(path))?.len();
    let mut reader = BufReader::new(file);
    let header = read_npy_header(&mut reader).map_err(|e| corrupt(path, ".npy", e))?;
    let data_start = reader.stream_position().map_err(read_error(path))?;

    let shape = header.shape;
    let [n0, n1, n2] = shape[..] else {
        return Err(IoError::NotThreeD { path: path.to_path_buf(), shape });
    };
    let item_size = mask_item_size(&header.descr).map_err(|kind| IoError::NotAMask {
        path: path.to_path_buf(),
        reason: format!("dtype {} is {kind}, not a mask; {THRESHOLD_HINT}", header.descr),
    })?;

    // Check the data length against the header before allocating anything, so a
    // truncated file or a header claiming a huge shape fails cleanly.
    let count = n0.checked_mul(n1).and_then(|n| n.checked_mul(n2));
    let needed = count
        .and_then(|n| n.checked_mul(item_size as u64))
        .filter(|&n| usize::try_from(n).is_ok())
        .ok_or_else(|| corrupt(path, ".npy", format!("shape {} is too large", shape_text(&shape))))?;
    let available = file_len.saturating_sub(data_start);
    if available < needed {
        return Err(corrupt(
            path,
            ".npy",
            format!(
                "truncated: shape {} of dtype {} needs {needed} bytes of data, \
                 the file holds {available}",
                shape_text(&shape),
                header.descr
            ),
        ));
    }

    let values =
        read_nonzero(&mut reader, (needed / item_size as u64) as usize, item_size).map_err(read_error(path))?;
    let dims = (n0 as usize, n1 as usize, n2 as usize);
    let mask = if header.fortran_order {
        Array3::from_shape_vec(dims.f(), values)
    } else {
        Array3::from_shape_vec(dims, values)
    };
    // The length was checked against the shape above, so this cannot fail; map it anyway.
    mask.map_err(|e| corrupt(path, ".npy", e))
}

/// Read `count` elements of `item_size` bytes and keep "non-zero" (1 byte each).
/// An integer or bool is zero exactly when all its bytes are, whatever the byte
/// order, so no decoding is needed.
fn read_nonzero(reader: &mut impl Read, count: usize, item_size: usize) -> std::io::Result<Vec<u8>> {
    const CHUNK_ITEMS: usize = 1 << 16;
    let mut out = Vec::with_capacity(count);
    let mut buffer = vec![0u8; CHUNK_ITEMS * item_size];
    while out.len() < count {
        let items = CHUNK_ITEMS.min(count - out.len());
        let chunk = &mut buffer[..items * item_size];
        reader.read_exact(chunk)?;
        out.extend(chunk.chunks_exact(item_size).map(|item| u8::from(item.iter().any(|&b| b != 0))));
    }
    Ok(out)
}

/// NIfTI intensity scaling `y = scl_slope * x + scl_inter`, when the header asks for it
/// (`scl_slope` = 0 means "no scaling" in the NIfTI-1 standard).
#[derive(Clone, Copy)]
struct Scaling {
    slope: f64,
    inter: f64,
}

impl Scaling {
    fn from_header(header: &nifti::NiftiHeader) -> Option<Scaling> {
        let (slope, inter) = (f64::from(header.scl_slope), f64::from(header.scl_inter));
        let active = slope != 0.0 && slope.is_finite() && inter.is_finite();
        (active && (slope != 1.0 || inter != 0.0)).then_some(Scaling { slope, inter })
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

fn read_nifti(path: &Path, spacing: Option<[f64; 3]>) -> Result<VolumeFile, IoError> {
    // Open it ourselves first so that a missing or unreadable file (or a directory)
    // gets the same message as for the other formats.
    File::open(path).and_then(|mut f| f.read(&mut [0u8; 1])).map_err(read_error(path))?;
    let object = nifti::ReaderOptions::new().read_file(path).map_err(|e| match e {
        nifti::NiftiError::Io(source) => IoError::Read { path: path.to_path_buf(), source },
        other => corrupt(path, "NIfTI", other),
    })?;
    let header = object.header().clone();

    let ndim = usize::from(header.dim[0]).min(7);
    let shape: Vec<u64> = header.dim[1..=ndim].iter().map(|&d| u64::from(d)).collect();
    if ndim < 3 || shape[3..].iter().any(|&d| d != 1) {
        return Err(IoError::NotThreeD { path: path.to_path_buf(), shape });
    }
    let dims = (shape[0] as usize, shape[1] as usize, shape[2] as usize);

    let spacing = match spacing {
        Some(s) => s,
        None => {
            let pixdim = [header.pixdim[1], header.pixdim[2], header.pixdim[3]];
            if pixdim.iter().any(|p| !p.is_finite() || *p == 0.0) {
                return Err(IoError::BadPixdim { path: path.to_path_buf(), pixdim });
            }
            pixdim.map(|p| f32_to_f64_decimal(p.abs()))
        }
    };

    let volume = object.into_volume();
    let datatype = volume.data_type();
    let data = RawVoxels {
        path,
        raw: volume.into_raw_data(),
        endianness: header.endianness,
        datatype,
        scaling: Scaling::from_header(&header),
        dims,
    };
    let values = match datatype {
        NiftiType::Uint8 => data.nonzero::<u8>()?,
        NiftiType::Int8 => data.nonzero::<i8>()?,
        NiftiType::Uint16 => data.nonzero::<u16>()?,
        NiftiType::Int16 => data.nonzero::<i16>()?,
        NiftiType::Uint32 => data.nonzero::<u32>()?,
        NiftiType::Int32 => data.nonzero::<i32>()?,
        NiftiType::Uint64 => data.nonzero::<u64>()?,
        NiftiType::Int64 => data.nonzero::<i64>()?,
        NiftiType::Float32 => data.zero_one::<f32>()?,
        NiftiType::Float64 => data.zero_one::<f64>()?,
        other => {
            return Err(IoError::NotAMask {
                path: path.to_path_buf(),
                reason: format!("NIfTI datatype {other:?} is not a mask; {THRESHOLD_HINT}"),
            })
        }
    };
    // NIfTI stores voxels with the first index fastest: Fortran order, axes (i, j, k).
    let mask = Array3::from_shape_vec(dims.f(), values).map_err(|e| corrupt(path, "NIfTI", e))?;
    Ok(VolumeFile { mask, spacing })
}

/// The data block of a NIfTI file, with what is needed to decode and binarise it.
struct RawVoxels<'a> {
    path: &'a Path,
    raw: Vec<u8>,
    endianness: nifti::Endianness,
    datatype: NiftiType,
    scaling: Option<Scaling>,
    dims: (usize, usize, usize),
}

impl RawVoxels<'_> {
    fn decode<T: DataElement>(&mut self) -> Result<Vec<T>, IoError> {
        let raw = std::mem::take(&mut self.raw);
        T::from_raw_vec_validated(raw, self.endianness, self.datatype).map_err(|e| corrupt(self.path, "NIfTI", e))
    }

    /// Integer voxels: vessel where the (scaled) value is non-zero.
    fn nonzero<T>(mut self) -> Result<Vec<u8>, IoError>
    where
        T: DataElement + AsPrimitive<f64> + PartialEq + Default,
    {
        let values = self.decode::<T>()?;
        Ok(match self.scaling {
            None => values.into_iter().map(|v| u8::from(v != T::default())).collect(),
            Some(s) => values.into_iter().map(|v| u8::from(s.apply(v.as_()) != 0.0)).collect(),
        })
    }

    /// Float voxels: accepted only if every (scaled) value is exactly 0 or 1.
    fn zero_one<T>(mut self) -> Result<Vec<u8>, IoError>
    where
        T: DataElement + AsPrimitive<f64>,
    {
        let values = self.decode::<T>()?;
        let mut out = Vec::with_capacity(values.len());
        for (index, v) in values.into_iter().enumerate() {
            let x = self.scaling.map_or(v.as_(), |s| s.apply(v.as_()));
            if x == 0.0 || x == 1.0 {
                out.push(x as u8);
                continue;
            }
            let (n0, n1, _) = self.dims;
            let voxel = (index % n0, index / n0 % n1, index / (n0 * n1));
            return Err(IoError::NotAMask {
                path: self.path.to_path_buf(),
                reason: format!(
                    "floating-point image with values other than 0 and 1 (e.g. {x} at voxel \
                     {voxel:?}), not a mask; {THRESHOLD_HINT}"
                ),
            });
        }
        Ok(out)
    }
}

/// Binarise one TIFF page: integers non-zero; floats only if every value is 0 or 1.
fn tiff_page_mask(path: &Path, page: DecodingResult, out: &mut Vec<u8>) -> Result<(), IoError> {
    fn ints<T: Copy + PartialEq + Default>(v: Vec<T>, out: &mut Vec<u8>) {
        out.extend(v.into_iter().map(|x| u8::from(x != T::default())));
    }
    fn floats(path: &Path, v: impl Iterator<Item = f64>, out: &mut Vec<u8>) -> Result<(), IoError> {
        for x in v {
            if x != 0.0 && x != 1.0 {
                return Err(IoError::NotAMask {
                    path: path.to_path_buf(),
                    reason: format!(
                        "floating-point TIFF with value {x}: threshold it first \
                         (vesselflow.load_volume(path, threshold=...))"
                    ),
                });
            }
            out.push(u8::from(x == 1.0));
        }
        Ok(())
    }
    match page {
        DecodingResult::U8(v) => ints(v, out),
        DecodingResult::U16(v) => ints(v, out),
        DecodingResult::U32(v) => ints(v, out),
        DecodingResult::U64(v) => ints(v, out),
        DecodingResult::I8(v) => ints(v, out),
        DecodingResult::I16(v) => ints(v, out),
        DecodingResult::I32(v) => ints(v, out),
        DecodingResult::I64(v) => ints(v, out),
        DecodingResult::F32(v) => floats(path, v.into_iter().map(f64::from), out)?,
        DecodingResult::F64(v) => floats(path, v.into_iter(), out)?,
        DecodingResult::F16(v) => floats(path, v.into_iter().map(f64::from), out)?,
    }
    Ok(())
}

/// Pixel size from a TIFF resolution tag (pixels per unit), if present and sane.
fn tiff_pixel_size(decoder: &mut Decoder<BufReader<File>>, tag: Tag) -> Option<f64> {
    match decoder.find_tag(tag).ok()?? {
        tiff::decoder::ifd::Value::Rational(n, d) if n > 0 && d > 0 => Some(d as f64 / n as f64),
        _ => None,
    }
}

/// A multi-page greyscale TIFF stack as axes (page, row, column). Spacing follows
/// ImageJ's convention: `spacing=` in the image description for axis 0 and the
/// X/Y resolution tags (pixels per unit) for axes 2 and 1, only in ImageJ files;
/// otherwise 1. (OME-TIFF spacing: `vesselflow.load_volume` in Python.)
fn read_tiff(path: &Path, spacing: Option<[f64; 3]>) -> Result<VolumeFile, IoError> {
    let bad = |e: tiff::TiffError| corrupt(path, "TIFF", e);
    let file = File::open(path).map_err(read_error(path))?;
    let mut decoder = Decoder::new(BufReader::new(file)).map_err(bad)?.with_limits(Limits::unlimited());
    let (width, height) = decoder.dimensions().map_err(bad)?;
    let description = decoder.get_tag_ascii_string(Tag::ImageDescription).unwrap_or_default();
    let imagej = description.starts_with("ImageJ=");
    let mut file_spacing = [1.0; 3];
    if imagej {
        let z = description.lines().find_map(|l| l.strip_prefix("spacing=")?.trim().parse::<f64>().ok());
        file_spacing = [
            z.unwrap_or(1.0),
            tiff_pixel_size(&mut decoder, Tag::YResolution).unwrap_or(1.0),
            tiff_pixel_size(&mut decoder, Tag::XResolution).unwrap_or(1.0),
        ];
    }
    let mut data = Vec::new();
    let mut pages = 0usize;
    loop {
        if decoder.dimensions().map_err(bad)? != (width, height) {
            return Err(corrupt(path, "TIFF", format!("page {pages} is not {width} x {height} like page 0")));
        }
        match decoder.colortype().map_err(bad)? {
            ColorType::Gray(_) => {}
            other => {
                return Err(IoError::NotAMask {
                    path: path.to_path_buf(),
                    reason: format!("TIFF page {pages} is {other:?}, not a greyscale mask"),
                })
            }
        }
        tiff_page_mask(path, decoder.read_image().map_err(bad)?, &mut data)?;
        pages += 1;
        if !decoder.more_images() {
            break;
        }
        decoder.next_image().map_err(bad)?;
    }
    let shape = (pages, height as usize, width as usize);
    let mask = Array3::from_shape_vec(shape, data).map_err(|e| corrupt(path, "TIFF", e))?;
    let spacing = match spacing {
        Some(s) => s,
        None if file_spacing.iter().all(|s| s.is_finite() && *s > 0.0) => file_spacing,
        None => return Err(corrupt(path, "TIFF", format!("ImageJ spacing {file_spacing:?} is not positive"))),
    };
    Ok(VolumeFile { mask, spacing })
}
