//! Multi-page greyscale TIFF stacks, with ImageJ spacing.
//!
//! The `tiff` crate decodes one page at a time under explicit [`Limits`] derived
//! from the byte budget: before each page, the mask so far plus that page and its
//! decoded pixels must fit the budget, and the decoder may use only what is left
//! for the page buffer and its compressed strips. A page bomb (many pages, or
//! pages whose strips inflate far beyond their size) therefore fails at the first
//! page that would cross the budget.

use super::{check_budget, corrupt, dims_text, not_a_mask, read_error, spacing_in_range, ReadLimits, VolumeFile};
use crate::{Binariser, IoError, MaskRule, Sample};
use ndarray::Array3;
use std::any::Any;
use std::fs::File;
use std::io::{BufReader, Seek};
use std::path::Path;
use tiff::decoder::{Decoder, DecodingResult, Limits};
use tiff::tags::Tag;
use tiff::ColorType;

const FORMAT: &str = "TIFF";
/// Most bytes one tag's values may take (strip offsets and counts, descriptions):
/// the `tiff` crate's default.
const IFD_VALUE_BYTES: u64 = 1 << 20;

/// Append the mask of one page to `out`, by the rule applied to the whole stack so
/// far: `state` holds the stack's [`Binariser`], of the first page's value type.
/// `Err` says why the stack is not a mask.
fn tiff_page_mask(
    page: DecodingResult,
    rule: MaskRule,
    state: &mut Option<Box<dyn Any>>,
    out: &mut Vec<u8>,
) -> Result<(), String> {
    fn typed<T: Sample + 'static>(
        v: impl IntoIterator<Item = T>,
        rule: MaskRule,
        state: &mut Option<Box<dyn Any>>,
        out: &mut Vec<u8>,
    ) -> Result<(), String> {
        let binariser = state.get_or_insert_with(|| Box::new(Binariser::<T>::new(rule)));
        let Some(binariser) = binariser.downcast_mut::<Binariser<T>>() else {
            return Err(format!("a page holds {} values unlike the first page", T::NAME));
        };
        binariser.extend(v, out);
        binariser.finish()
    }
    match page {
        DecodingResult::U8(v) => typed(v, rule, state, out),
        DecodingResult::U16(v) => typed(v, rule, state, out),
        DecodingResult::U32(v) => typed(v, rule, state, out),
        DecodingResult::U64(v) => typed(v, rule, state, out),
        DecodingResult::I8(v) => typed(v, rule, state, out),
        DecodingResult::I16(v) => typed(v, rule, state, out),
        DecodingResult::I32(v) => typed(v, rule, state, out),
        DecodingResult::I64(v) => typed(v, rule, state, out),
        DecodingResult::F32(v) => typed(v, rule, state, out),
        DecodingResult::F64(v) => typed(v, rule, state, out),
        DecodingResult::F16(v) => typed(v.into_iter().map(f32::from), rule, state, out),
    }
}

/// Pixel size from a TIFF resolution tag (pixels per unit), if present and sane.
fn tiff_pixel_size(decoder: &mut Decoder<BufReader<File>>, tag: Tag) -> Option<f64> {
    match decoder.find_tag(tag).ok()?? {
        tiff::decoder::ifd::Value::Rational(n, d) if n > 0 && d > 0 => Some(d as f64 / n as f64),
        _ => None,
    }
}

/// Decoder limits for a page of `page_bytes` decoded bytes whose largest
/// compressed strip or tile has `segment_bytes`, when `room` bytes of the budget
/// are left after the mask (`room` >= `page_bytes + segment_bytes`). The decoder
/// holds one page buffer and one segment at a time; the page-buffer limit also
/// bounds the tag values of the next directory, parsed once the page is freed.
fn page_limits(page_bytes: u64, segment_bytes: u64, room: u64) -> Limits {
    let to_usize = |n: u64| usize::try_from(n).unwrap_or(usize::MAX);
    let mut limits = Limits::default();
    limits.decoding_buffer_size = to_usize(room - segment_bytes);
    limits.intermediate_buffer_size = to_usize(room - page_bytes);
    limits.ifd_value_size = to_usize(IFD_VALUE_BYTES.min(room - page_bytes));
    limits
}

/// Bytes the `tiff` crate holds per value when it parses a tag (its `Value` enum).
const VALUE_COST: u64 = 32;

/// The `tiff` crate parses the first directory before limits can be set (with
/// room for 256 MiB per tag), so its tags are checked here first: each must fit
/// in the file, and its parsed values in the budget. Anything else odd is left
/// to the decoder to report.
fn check_first_directory(path: &Path, file: &mut File, file_len: u64, limits: ReadLimits) -> Result<(), IoError> {
    use std::io::{Read, Seek, SeekFrom};
    let mut reader = BufReader::new(file);
    let mut head = [0u8; 16];
    if file_len < 16 || reader.read_exact(&mut head).is_err() {
        return Ok(());
    }
    let little = match &head[..2] {
        b"II" => true,
        b"MM" => false,
        _ => return Ok(()),
    };
    let uint = |b: &[u8]| {
        let mut v = 0u64;
        for i in 0..b.len() {
            v |= u64::from(b[if little { i } else { b.len() - 1 - i }]) << (8 * i);
        }
        v
    };
    // (offset of the directory, bytes of the entry count, of an entry, of a count)
    let (dir, count_bytes, entry_bytes, value_count_bytes) = match uint(&head[2..4]) {
        42 => (uint(&head[4..8]), 2, 12, 4),
        43 => (uint(&head[8..16]), 8, 20, 8),
        _ => return Ok(()),
    };
    let mut buf = [0u8; 20];
    if reader.seek(SeekFrom::Start(dir)).is_err() || reader.read_exact(&mut buf[..count_bytes]).is_err() {
        return Ok(());
    }
    let entries = uint(&buf[..count_bytes]);
    for _ in 0..entries.min(file_len / entry_bytes as u64) {
        if reader.read_exact(&mut buf[..entry_bytes]).is_err() {
            return Ok(());
        }
        let (tag, kind) = (uint(&buf[..2]), uint(&buf[2..4]));
        let count = uint(&buf[4..4 + value_count_bytes]);
        let size = match kind {
            1 | 2 | 6 | 7 => 1,
            3 | 8 => 2,
            4 | 9 | 11 | 13 => 4,
            5 | 10 | 12 | 16 | 17 | 18 => 8,
            _ => continue,
        };
        if count.checked_mul(size).is_none_or(|bytes| bytes > file_len) {
            return Err(corrupt(
                path,
                FORMAT,
                format!("tag {tag} declares {count} values, more than the file's {file_len} bytes hold"),
            ));
        }
        check_budget(path, limits, count.checked_mul(VALUE_COST), || {
            format!("tag {tag} of the first directory declares {count} values")
        })?;
    }
    Ok(())
}

/// A multi-page greyscale TIFF stack as axes (page, row, column). Spacing follows
/// ImageJ's convention: `spacing=` in the image description for axis 0 and the
/// X/Y resolution tags (pixels per unit) for axes 2 and 1, only in ImageJ files;
/// otherwise 1. (OME-TIFF spacing: `vesselflow.load_volume` in Python.)
pub(super) fn read_tiff(
    path: &Path,
    spacing: Option<[f64; 3]>,
    rule: MaskRule,
    limits: ReadLimits,
) -> Result<VolumeFile, IoError> {
    let bad = |e: tiff::TiffError| match e {
        tiff::TiffError::IoError(source) if source.kind() != std::io::ErrorKind::UnexpectedEof => {
            IoError::Read { path: path.to_path_buf(), source }
        }
        other => corrupt(path, FORMAT, other),
    };
    let mut file = File::open(path).map_err(read_error(path))?;
    let file_len = file.metadata().map_err(read_error(path))?.len();
    check_first_directory(path, &mut file, file_len, limits)?;
    file.rewind().map_err(read_error(path))?;
    let mut decoder = Decoder::new(BufReader::new(file)).map_err(bad)?;
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
    let spacing = match spacing {
        Some(s) => s,
        None if file_spacing.iter().all(|&s| spacing_in_range(s) && s > 0.0) => file_spacing,
        None => return Err(corrupt(path, FORMAT, format!("ImageJ spacing {file_spacing:?} is not in [1e-12, 1e12]"))),
    };

    let page_pixels = u64::from(width) * u64::from(height);
    let mut data: Vec<u8> = Vec::new();
    let mut pages = 0u64;
    let mut binariser = None;
    loop {
        if decoder.dimensions().map_err(bad)? != (width, height) {
            return Err(corrupt(path, FORMAT, format!("page {pages} is not {width} x {height} like page 0")));
        }
        let bits = match decoder.colortype().map_err(bad)? {
            ColorType::Gray(bits @ (8 | 16 | 32 | 64)) => u64::from(bits),
            other => {
                return Err(IoError::NotAMask {
                    path: path.to_path_buf(),
                    reason: format!(
                        "TIFF page {pages} is {other:?}, not a greyscale mask of 8, 16, 32 or 64 bits per pixel"
                    ),
                })
            }
        };
        // The mask so far and this page, the decoded page, and its largest
        // compressed strip or tile, which the decoder holds besides.
        let page_bytes = page_pixels.checked_mul(bits / 8);
        let mask_bytes = (data.len() as u64).checked_add(page_pixels);
        let segment_bytes = [Tag::StripByteCounts, Tag::TileByteCounts]
            .into_iter()
            .filter_map(|tag| decoder.find_tag_unsigned_vec::<u64>(tag).ok().flatten())
            .flatten()
            .max()
            .unwrap_or(0);
        let needed = page_bytes.and_then(|p| p.checked_add(mask_bytes?)?.checked_add(segment_bytes));
        check_budget(path, limits, needed, || {
            format!(
                "the file declares {} voxels up to page {pages} of {width}×{height} pixels of {bits} bits",
                dims_text(&[pages + 1, u64::from(height), u64::from(width)])
            )
        })?;
        // Within the budget, so neither overflowed.
        let (page_bytes, mask_bytes) = (page_bytes.unwrap_or(u64::MAX), mask_bytes.unwrap_or(u64::MAX));
        let uncompressed = decoder.find_tag_unsigned::<u16>(Tag::Compression).ok().flatten().is_none_or(|c| c == 1);
        if uncompressed && page_bytes > file_len {
            return Err(corrupt(
                path,
                FORMAT,
                format!(
                    "truncated: uncompressed page {pages} of {width}×{height} pixels of {bits} bits needs \
                     {page_bytes} bytes, the file holds {file_len}"
                ),
            ));
        }
        let room = limits.max_bytes - mask_bytes;
        decoder = decoder.with_limits(page_limits(page_bytes, segment_bytes, room));
        data.try_reserve_exact(page_pixels as usize).map_err(|_| IoError::Read {
            path: path.to_path_buf(),
            source: std::io::Error::new(std::io::ErrorKind::OutOfMemory, "cannot allocate the mask"),
        })?;
        let page = decoder.read_image().map_err(|e| match e {
            tiff::TiffError::LimitsExceeded => corrupt(
                path,
                FORMAT,
                format!(
                    "page {pages} would need more memory than the {} left in the budget",
                    crate::budget::human_bytes(room)
                ),
            ),
            other => bad(other),
        })?;
        let before = data.len();
        tiff_page_mask(page, rule, &mut binariser, &mut data).map_err(|reason| not_a_mask(path, reason))?;
        if (data.len() - before) as u64 != page_pixels {
            return Err(corrupt(path, FORMAT, format!("page {pages} does not hold {width}×{height} samples")));
        }
        pages += 1;
        if !decoder.more_images() {
            break;
        }
        decoder.next_image().map_err(bad)?;
    }
    let shape = (pages as usize, height as usize, width as usize);
    let mask = Array3::from_shape_vec(shape, data).map_err(|e| corrupt(path, FORMAT, e))?;
    Ok(VolumeFile { mask, spacing, affine: super::spacing_affine(spacing) })
}
