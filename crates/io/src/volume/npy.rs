//! `.npy` masks (`numpy.lib.format`, versions 1 to 3): bool or integer dtypes of
//! either byte order, C or Fortran order.

use super::{
    check_budget, checked_product, corrupt, dims_text, read_error, try_vec, ReadLimits, CHUNK_BYTES, THRESHOLD_HINT,
};
use crate::error::shape_text;
use crate::IoError;
use ndarray::{Array3, ShapeBuilder};
use num_traits::ToPrimitive;
use std::fs::File;
use std::io::{BufReader, Read, Seek};
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
/// `fortran_order` and `shape`. Leaves `reader` at the first data byte.
fn read_npy_header(reader: &mut impl Read, file_len: u64) -> Result<NpyHeader, String> {
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
    Ok(NpyHeader { descr: get("descr")?.clone(), fortran_order, shape })
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

/// Bytes per element of a mask dtype descriptor (`|b1`, `<i4`, `>u2`, `?`, ...), or
/// what kind of non-mask data it describes.
fn mask_item_size(descr: &py_literal::Value) -> Result<u64, &'static str> {
    let Some(descr) = descr.as_string() else {
        return Err("a structured dtype");
    };
    let body = descr.strip_prefix(['<', '>', '|', '=']).unwrap_or(descr);
    let (kind, size) = body.split_at(body.chars().next().map_or(0, char::len_utf8));
    match (kind, size) {
        ("b", "1") | ("?", "" | "1") => Ok(1),
        ("i" | "u", "1") => Ok(1),
        ("i" | "u", "2") => Ok(2),
        ("i" | "u", "4") => Ok(4),
        ("i" | "u", "8") => Ok(8),
        ("f" | "e" | "d" | "g", _) => Err("floating point"),
        ("c", _) => Err("complex"),
        ("O", _) => Err("Python objects (a pickled array, which is never read)"),
        _ => Err("not a bool or integer type"),
    }
}

pub(super) fn read_npy(path: &Path, limits: ReadLimits) -> Result<Array3<u8>, IoError> {
    let file = File::open(path).map_err(read_error(path))?;
    let file_len = file.metadata().map_err(read_error(path))?.len();
    let mut reader = BufReader::new(file);
    let header = read_npy_header(&mut reader, file_len).map_err(|e| corrupt(path, ".npy", e))?;
    let data_start = reader.stream_position().map_err(read_error(path))?;

    let shape = header.shape;
    let [n0, n1, n2] = shape[..] else {
        return Err(IoError::NotThreeD { path: path.to_path_buf(), shape });
    };
    let item_size = mask_item_size(&header.descr).map_err(|kind| IoError::NotAMask {
        path: path.to_path_buf(),
        reason: format!("dtype {} is {kind}, not a mask; {THRESHOLD_HINT}", header.descr),
    })?;

    // Check the data length against the file and the budget before allocating
    // anything, so a truncated file or a header claiming a huge shape fails cleanly.
    let count = checked_product(&shape);
    let Some(data_bytes) = count.and_then(|n| n.checked_mul(item_size)) else {
        return Err(corrupt(path, ".npy", format!("shape {} is too large", shape_text(&shape))));
    };
    let available = file_len.saturating_sub(data_start);
    if available < data_bytes {
        return Err(corrupt(
            path,
            ".npy",
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
    read_nonzero(&mut reader, count, item_size as usize, buffer_bytes as usize, &mut values)
        .map_err(read_error(path))?;
    let dims = (n0 as usize, n1 as usize, n2 as usize);
    let mask = if header.fortran_order {
        Array3::from_shape_vec(dims.f(), values)
    } else {
        Array3::from_shape_vec(dims, values)
    };
    // The length was checked against the shape above, so this cannot fail; map it anyway.
    mask.map_err(|e| corrupt(path, ".npy", e))
}

/// Read `count` elements of `item_size` bytes and append "non-zero" (1 byte each)
/// to `out`, through a buffer of `buffer_bytes`. An integer or bool is zero
/// exactly when all its bytes are, whatever the byte order, so no decoding is needed.
fn read_nonzero(
    reader: &mut impl Read,
    count: u64,
    item_size: usize,
    buffer_bytes: usize,
    out: &mut Vec<u8>,
) -> std::io::Result<()> {
    let mut buffer = vec![0u8; buffer_bytes];
    let chunk_items = (buffer_bytes / item_size).max(1);
    let mut left = count as usize;
    while left > 0 {
        let items = chunk_items.min(left);
        let chunk = &mut buffer[..items * item_size];
        reader.read_exact(chunk)?;
        out.extend(chunk.chunks_exact(item_size).map(|item| u8::from(item.iter().any(|&b| b != 0))));
        left -= items;
    }
    Ok(())
}
