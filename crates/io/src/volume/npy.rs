//! `.npy` masks (`numpy.lib.format`, versions 1 to 3): bool, integer and
//! float32/float64 dtypes of either byte order, C or Fortran order; and `.npz`
//! archives of them (a zip of `.npy` members), one array picked by name.

use super::{
    check_budget, checked_product, corrupt, dims_text, not_a_mask, read_error, stream_mask, try_vec, ReadLimits,
    CHUNK_BYTES,
};
use crate::error::shape_text;
use crate::{IoError, MaskRule};
use ndarray::{Array3, ShapeBuilder};
use num_traits::ToPrimitive;
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;

/// Headers longer than this are refused: NumPy's own reader stops at 10 000 bytes
/// by default, and a mask's header is about 128.
const MAX_HEADER_BYTES: u64 = 1 << 20;

/// Deepest bracket nesting accepted in the header dict. A mask header nests 2
/// deep (dict, shape tuple); the limit keeps the recursive literal parser far
/// from the end of the stack on a hostile header such as `[[[[...`.
const MAX_HEADER_NESTING: usize = 16;

/// What an `.npy` header says about the data that follows it.
struct NpyHeader {
    descr: py_literal::Value,
    fortran_order: bool,
    shape: Vec<u64>,
}

/// Parse the header of an `.npy` file of `file_len` bytes: magic string,
/// version, header length, then a Python dict literal with `descr`,
/// `fortran_order` and `shape`. Leaves `reader` at the first data byte, whose
/// offset is returned with the header.
fn read_npy_header(reader: &mut impl Read, file_len: u64) -> Result<(NpyHeader, u64), String> {
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
    let length = u64::from(u32::from_le_bytes(length));
    let room = file_len.saturating_sub(8 + length_bytes as u64);
    if length > room {
        return Err(format!("the header length {length} exceeds the {room} bytes left in the file"));
    }
    if length > MAX_HEADER_BYTES {
        return Err(format!("the header length {length} is over the {MAX_HEADER_BYTES} bytes accepted"));
    }
    let mut text = vec![0u8; length as usize];
    reader.read_exact(&mut text).map_err(too_short)?;
    let text = std::str::from_utf8(&text).map_err(|_| "the header is not text".to_string())?;
    if nesting_depth(text) > MAX_HEADER_NESTING {
        return Err(format!("the header nests brackets more than {MAX_HEADER_NESTING} deep"));
    }
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
    let data_start = 8 + length_bytes as u64 + length;
    Ok((NpyHeader { descr: get("descr")?.clone(), fortran_order, shape }, data_start))
}

/// The deepest nesting of `(`, `[` and `{` in `text`, counting brackets inside
/// string literals too (a mask header has none there, so overcounting is harmless).
fn nesting_depth(text: &str) -> usize {
    let (mut depth, mut deepest) = (0usize, 0usize);
    for b in text.bytes() {
        match b {
            b'(' | b'[' | b'{' => {
                depth += 1;
                deepest = deepest.max(depth);
            }
            b')' | b']' | b'}' => depth = depth.saturating_sub(1),
            _ => {}
        }
    }
    deepest
}

/// The value types an `.npy` mask may hold.
#[derive(Clone, Copy)]
enum NpyType {
    Bool,
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    U64,
    I64,
    F16,
    F32,
    F64,
}

/// The value type and byte order (`true`: big-endian) of a dtype descriptor (`|b1`,
/// `<i4`, `>f8`, `?`, ...), or what kind of other data it describes.
fn npy_type(descr: &py_literal::Value) -> Result<(NpyType, bool), &'static str> {
    let Some(descr) = descr.as_string() else {
        return Err("a structured dtype");
    };
    let big_endian = descr.starts_with('>');
    let body = descr.strip_prefix(['<', '>', '|', '=']).unwrap_or(descr);
    let (kind, size) = body.split_at(body.chars().next().map_or(0, char::len_utf8));
    let t = match (kind, size) {
        ("b", "1") | ("?", "" | "1") => NpyType::Bool,
        ("u", "1") => NpyType::U8,
        ("i", "1") => NpyType::I8,
        ("u", "2") => NpyType::U16,
        ("i", "2") => NpyType::I16,
        ("u", "4") => NpyType::U32,
        ("i", "4") => NpyType::I32,
        ("u", "8") => NpyType::U64,
        ("i", "8") => NpyType::I64,
        ("f", "2") => NpyType::F16,
        ("f", "4") => NpyType::F32,
        ("f", "8") => NpyType::F64,
        ("f" | "e" | "d" | "g", _) => return Err("floating point of a precision other than 16, 32 or 64 bits"),
        ("c", _) => return Err("complex"),
        ("O", _) => return Err("Python objects (a pickled array, which is never read)"),
        _ => return Err("not a bool, integer or float type"),
    };
    Ok((t, big_endian))
}

impl NpyType {
    fn size(self) -> u64 {
        match self {
            NpyType::Bool | NpyType::U8 | NpyType::I8 => 1,
            NpyType::U16 | NpyType::I16 | NpyType::F16 => 2,
            NpyType::U32 | NpyType::I32 | NpyType::F32 => 4,
            NpyType::U64 | NpyType::I64 | NpyType::F64 => 8,
        }
    }
}

pub(super) fn read_npy(path: &Path, rule: MaskRule, limits: ReadLimits) -> Result<Array3<u8>, IoError> {
    let file = File::open(path).map_err(read_error(path))?;
    let file_len = file.metadata().map_err(read_error(path))?.len();
    read_npy_from(path, ".npy", BufReader::new(file), file_len, rule, limits)
}

/// The mask in the `.npy` data of `file_len` bytes that `reader` yields (a file, or
/// a member of an `.npz`, `format` names which in messages).
fn read_npy_from(
    path: &Path,
    format: &'static str,
    mut reader: impl Read,
    file_len: u64,
    rule: MaskRule,
    limits: ReadLimits,
) -> Result<Array3<u8>, IoError> {
    let (header, data_start) = read_npy_header(&mut reader, file_len).map_err(|e| corrupt(path, format, e))?;

    let shape = header.shape;
    let [n0, n1, n2] = shape[..] else {
        return Err(IoError::NotThreeD { path: path.to_path_buf(), shape });
    };
    let (dtype, big_endian) = npy_type(&header.descr).map_err(|kind| {
        not_a_mask(
            path,
            format!("dtype {} is {kind}, not a mask: save a bool, integer, float32 or float64 mask", header.descr),
        )
    })?;
    let item_size = dtype.size();

    // Check the data length against the file and the budget before allocating
    // anything, so a truncated file or a header claiming a huge shape fails cleanly.
    let count = checked_product(&shape);
    let Some(data_bytes) = count.and_then(|n| n.checked_mul(item_size)) else {
        return Err(corrupt(path, format, format!("shape {} is too large", shape_text(&shape))));
    };
    let available = file_len.saturating_sub(data_start);
    if available < data_bytes {
        return Err(corrupt(
            path,
            format,
            format!(
                "truncated: shape {} of dtype {} needs {data_bytes} bytes of data, \
                 the file holds {available}",
                shape_text(&shape),
                header.descr
            ),
        ));
    }
    let count = data_bytes / item_size;
    let buffer_bytes = data_bytes.min(CHUNK_BYTES.next_multiple_of(item_size));
    check_budget(path, limits, count.checked_add(buffer_bytes), || {
        format!("the header declares {} voxels", dims_text(&shape))
    })?;

    let mut values = try_vec(path, count)?;
    let (reader, buffer) = (&mut reader, buffer_bytes);
    let read = match dtype {
        NpyType::Bool => stream_mask(reader, count, buffer, big_endian, rule, |x: u8| x != 0, &mut values),
        NpyType::U8 => stream_mask(reader, count, buffer, big_endian, rule, |x: u8| x, &mut values),
        NpyType::I8 => stream_mask(reader, count, buffer, big_endian, rule, |x: i8| x, &mut values),
        NpyType::U16 => stream_mask(reader, count, buffer, big_endian, rule, |x: u16| x, &mut values),
        NpyType::I16 => stream_mask(reader, count, buffer, big_endian, rule, |x: i16| x, &mut values),
        NpyType::U32 => stream_mask(reader, count, buffer, big_endian, rule, |x: u32| x, &mut values),
        NpyType::I32 => stream_mask(reader, count, buffer, big_endian, rule, |x: i32| x, &mut values),
        NpyType::U64 => stream_mask(reader, count, buffer, big_endian, rule, |x: u64| x, &mut values),
        NpyType::I64 => stream_mask(reader, count, buffer, big_endian, rule, |x: i64| x, &mut values),
        // Half floats are seen as the float32 they widen to exactly, as in `_core.binarise`.
        NpyType::F16 => stream_mask(reader, count, buffer, big_endian, rule, f16_to_f32, &mut values),
        NpyType::F32 => stream_mask(reader, count, buffer, big_endian, rule, |x: f32| x, &mut values),
        NpyType::F64 => stream_mask(reader, count, buffer, big_endian, rule, |x: f64| x, &mut values),
    };
    read.map_err(read_error(path))?.map_err(|reason| not_a_mask(path, reason))?;
    let dims = (n0 as usize, n1 as usize, n2 as usize);
    let mask = if header.fortran_order {
        Array3::from_shape_vec(dims.f(), values)
    } else {
        Array3::from_shape_vec(dims, values)
    };
    // The length was checked against the shape above, so this cannot fail; map it anyway.
    mask.map_err(|e| corrupt(path, format, e))
}

/// The mask in the array `key` of an `.npz` archive (by default the array `mask`,
/// or the only array besides `spacing`), and, if `want_spacing`, the archive's
/// `spacing` array (3 numbers), if it has one. Members are read through the zip crate's streaming
/// decoder, only as far as the member's `.npy` header declares, after the same
/// checks against the budget as an `.npy` file.
pub(super) fn read_npz(
    path: &Path,
    key: Option<&str>,
    want_spacing: bool,
    rule: MaskRule,
    limits: ReadLimits,
) -> Result<(Array3<u8>, Option<[f64; 3]>), IoError> {
    const FORMAT: &str = ".npz";
    let file = File::open(path).map_err(read_error(path))?;
    let mut archive = zip::ZipArchive::new(BufReader::new(file)).map_err(|e| corrupt(path, FORMAT, e))?;
    let names: Vec<String> = archive.file_names().filter_map(|n| n.strip_suffix(".npy")).map(String::from).collect();
    let arrays: Vec<&String> = names.iter().filter(|n| *n != "spacing").collect();
    let key = match key {
        Some(k) => k.to_string(),
        None if arrays.iter().any(|n| *n == "mask") => "mask".to_string(),
        None if arrays.len() == 1 => arrays[0].clone(),
        None => {
            let listed: Vec<&str> = names.iter().map(String::as_str).collect();
            return Err(not_a_mask(
                path,
                format!("choose the array with key= or --key (arrays: {})", listed.join(", ")),
            ));
        }
    };
    if !arrays.iter().any(|n| **n == key) {
        let listed: Vec<&str> = names.iter().map(String::as_str).collect();
        return Err(not_a_mask(path, format!("no array {key:?} (arrays: {})", listed.join(", "))));
    }
    // A spacing given by the caller replaces the archive's, which is then not read.
    let spacing = if want_spacing && names.iter().any(|n| n == "spacing") {
        let member = archive.by_name("spacing.npy").map_err(|e| corrupt(path, FORMAT, e))?;
        let size = member.size();
        Some(read_spacing(member, size).map_err(|e| corrupt(path, FORMAT, format!("the array 'spacing': {e}")))?)
    } else {
        None
    };
    let member = archive.by_name(&format!("{key}.npy")).map_err(|e| corrupt(path, FORMAT, e))?;
    let size = member.size();
    let mask = read_npy_from(path, FORMAT, member, size, rule, limits)?;
    Ok((mask, spacing))
}

/// The 3 numbers of an `.npz`'s `spacing` array (any float or integer dtype, any
/// shape of 3 values), which must be finite and in the range of every spacing.
fn read_spacing(mut reader: impl Read, len: u64) -> Result<[f64; 3], String> {
    let (header, _) = read_npy_header(&mut reader, len)?;
    if checked_product(&header.shape) != Some(3) {
        return Err(format!("shape {} does not hold 3 numbers", shape_text(&header.shape)));
    }
    let (dtype, big_endian) = npy_type(&header.descr).map_err(|kind| format!("dtype {} is {kind}", header.descr))?;
    let mut bytes = vec![0u8; 3 * dtype.size() as usize];
    reader.read_exact(&mut bytes).map_err(|_| "truncated".to_string())?;
    let value = |b: &[u8]| -> f64 {
        use super::Decode;
        use crate::Sample;
        match dtype {
            NpyType::Bool | NpyType::U8 => f64::from(b[0]),
            NpyType::I8 => i8::decode(b, big_endian).to_f64(),
            NpyType::U16 => u16::decode(b, big_endian).to_f64(),
            NpyType::I16 => i16::decode(b, big_endian).to_f64(),
            NpyType::U32 => u32::decode(b, big_endian).to_f64(),
            NpyType::I32 => i32::decode(b, big_endian).to_f64(),
            NpyType::U64 => u64::decode(b, big_endian).to_f64(),
            NpyType::I64 => i64::decode(b, big_endian).to_f64(),
            NpyType::F16 => f64::from(f16_to_f32(u16::decode(b, big_endian))),
            NpyType::F32 => f64::from(f32::decode(b, big_endian)),
            NpyType::F64 => f64::decode(b, big_endian),
        }
    };
    let mut spacing = [0.0; 3];
    for (s, b) in spacing.iter_mut().zip(bytes.chunks_exact(dtype.size() as usize)) {
        *s = value(b).abs();
    }
    if !spacing.iter().all(|&s| super::spacing_in_range(s)) {
        return Err(format!(
            "{spacing:?} must be finite numbers of magnitude 1e-12 to 1e12 (pass the spacing explicitly instead)"
        ));
    }
    Ok(spacing)
}

/// The IEEE 754 half-precision float with bits `h`, widened exactly to `f32`.
fn f16_to_f32(h: u16) -> f32 {
    let sign = if h >> 15 == 1 { -1.0 } else { 1.0 };
    let exponent = i32::from((h >> 10) & 0x1f);
    let fraction = f32::from(h & 0x3ff);
    match exponent {
        0 => sign * fraction * 2f32.powi(-24),
        31 if fraction == 0.0 => sign * f32::INFINITY,
        31 => f32::NAN,
        e => sign * (1.0 + fraction / 1024.0) * 2f32.powi(e - 15),
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn half_floats_widen_exactly() {
        for (bits, value) in [(0x0000, 0.0), (0x3c00, 1.0), (0xbc00, -1.0), (0x3800, 0.5), (0x0001, 2f32.powi(-24))] {
            assert_eq!(super::f16_to_f32(bits), value, "{bits:#06x}");
        }
        assert_eq!(super::f16_to_f32(0x7bff), 65504.0);
        assert_eq!(super::f16_to_f32(0xfc00), f32::NEG_INFINITY);
        assert!(super::f16_to_f32(0x7e00).is_nan());
    }
}
