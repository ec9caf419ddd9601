//! The readers against hostile input (issue 19): NIfTI files that use the header
//! fields the old reader ignored (`vox_offset`, big-endian, scaling), size bombs of
//! every format, corrupt `pixdim`, and property tests on random and mutated files.
//!
//! Every read here is measured by a counting allocator (per thread, so tests
//! running in parallel do not mix): a reader may never hold more than its budget.
//! NIfTI and TIFF files are built byte by byte, so the tests need nothing but
//! Rust; `tests/python/test_io_hostile.py` checks the same files against nibabel.

mod common;

use common::npy_bytes;
use flate2::write::{GzEncoder, ZlibEncoder};
use flate2::Compression;
use proptest::prelude::*;
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::fs;
use std::io::Write;
use std::path::Path;
use tempfile::TempDir;
use vesselflow_io::{read_volume, read_volume_limited, IoError, MaskRule, ReadLimits, VolumeFile};

// ---------------------------------------------------------------------------
// Allocation accounting

struct CountingAllocator;

thread_local! {
    static LIVE: Cell<i64> = const { Cell::new(0) };
    static PEAK: Cell<i64> = const { Cell::new(0) };
}

fn note(delta: i64) {
    let _ = LIVE.try_with(|live| {
        let now = live.get() + delta;
        live.set(now);
        let _ = PEAK.try_with(|peak| peak.set(peak.get().max(now)));
    });
}

// SAFETY: every call is forwarded to the system allocator unchanged; the
// bookkeeping touches only const-initialised thread-locals (no allocation).
unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            note(layout.size() as i64);
        }
        p
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            note(layout.size() as i64);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        note(-(layout.size() as i64));
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            note(new_size as i64 - layout.size() as i64);
        }
        p
    }
}

#[global_allocator]
static ALLOCATOR: CountingAllocator = CountingAllocator;

/// Run `f` and return its result with the most bytes it held at once.
fn peak_bytes<T>(f: impl FnOnce() -> T) -> (T, u64) {
    let base = LIVE.with(Cell::get);
    PEAK.with(|p| p.set(base));
    let out = f();
    let peak = PEAK.with(Cell::get) - base;
    (out, peak.max(0) as u64)
}

const MIB: u64 = 1 << 20;
/// The budget of the property tests.
const FUZZ_BUDGET: u64 = 64 * MIB;
/// Bookkeeping a reader may hold beyond its budget: paths, error messages, a
/// parsed header, `BufReader`s (the budget covers the data-sized buffers).
const SLACK: u64 = 64 << 10;

/// Read `path` within `budget` and check that the reader held no more than that.
fn read_within(path: &Path, budget: u64) -> Result<VolumeFile, IoError> {
    let (result, peak) = peak_bytes(|| read_volume_limited(path, None, MaskRule::Binary, ReadLimits::new(budget)));
    assert!(peak <= budget + SLACK, "{}: held {peak} bytes on a budget of {budget}", path.display());
    result
}

fn error_text(result: Result<VolumeFile, IoError>) -> String {
    match result {
        Ok(v) => panic!("expected an error, got a volume of shape {:?}", v.mask.shape()),
        Err(e) => e.to_string(),
    }
}

// ---------------------------------------------------------------------------
// NIfTI-1 files built by hand

/// NIfTI-1 datatype codes and their sizes.
#[derive(Clone, Copy, Debug)]
enum Dt {
    U8 = 2,
    I16 = 4,
    I32 = 8,
    F32 = 16,
    F64 = 64,
    I8 = 256,
    U16 = 512,
    U64 = 1280,
}

impl Dt {
    fn size(self) -> usize {
        match self {
            Dt::U8 | Dt::I8 => 1,
            Dt::I16 | Dt::U16 => 2,
            Dt::I32 | Dt::F32 => 4,
            Dt::F64 | Dt::U64 => 8,
        }
    }
}

/// What goes into a hand-built header.
#[derive(Clone)]
struct Nii {
    big_endian: bool,
    dim: Vec<i16>,
    datatype: Dt,
    pixdim: [f32; 3],
    vox_offset: f32,
    slope: f32,
    inter: f32,
    magic: [u8; 4],
}

impl Nii {
    fn new(dims: [i16; 3], datatype: Dt) -> Nii {
        Nii {
            big_endian: false,
            dim: dims.to_vec(),
            datatype,
            pixdim: [1.0; 3],
            vox_offset: 352.0,
            slope: 0.0,
            inter: 0.0,
            magic: *b"n+1\0",
        }
    }

    /// The file: header, a zero extension flag, `fill` up to `vox_offset`, then `data`.
    fn bytes(&self, data: &[u8], fill: u8) -> Vec<u8> {
        let mut h = vec![0u8; 348];
        let be = self.big_endian;
        let mut put = |at: usize, b: &[u8]| h[at..at + b.len()].copy_from_slice(b);
        let i16b = |v: i16| if be { v.to_be_bytes() } else { v.to_le_bytes() };
        let i32b = |v: i32| if be { v.to_be_bytes() } else { v.to_le_bytes() };
        let f32b = |v: f32| if be { v.to_be_bytes() } else { v.to_le_bytes() };
        put(0, &i32b(348));
        put(38, b"r");
        put(40, &i16b(self.dim.len() as i16));
        for (i, &d) in self.dim.iter().enumerate() {
            put(42 + 2 * i, &i16b(d));
        }
        put(70, &i16b(self.datatype as i16));
        put(72, &i16b(8 * self.datatype.size() as i16));
        put(76, &f32b(1.0));
        for (i, &p) in self.pixdim.iter().enumerate() {
            put(80 + 4 * i, &f32b(p));
        }
        put(108, &f32b(self.vox_offset));
        put(112, &f32b(self.slope));
        put(116, &f32b(self.inter));
        put(344, &self.magic);
        let mut bytes = h;
        bytes.extend_from_slice(&[0; 4]);
        if self.vox_offset.is_finite() && self.vox_offset as usize > 352 {
            bytes.resize(self.vox_offset as usize, fill);
        }
        bytes.extend_from_slice(data);
        bytes
    }
}

fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut enc = GzEncoder::new(Vec::new(), Compression::fast());
    enc.write_all(bytes).unwrap();
    enc.finish().unwrap()
}

/// The 3x4x5 test mask: voxel (i, j, k) is set when (7i + 3j + 5k) mod 6 >= 3, a
/// pattern that changes under any swap or flip of axes.
fn truth() -> ndarray::Array3<u8> {
    ndarray::Array3::from_shape_fn((3, 4, 5), |(i, j, k)| u8::from((i * 7 + j * 3 + k * 5) % 6 >= 3))
}

/// Values in the order NIfTI stores them (first index fastest).
fn fortran_flat(mask: &ndarray::Array3<u8>) -> Vec<u8> {
    mask.t().iter().copied().collect()
}

fn encode(values: &[f64], dt: Dt, big_endian: bool) -> Vec<u8> {
    let mut out = Vec::new();
    for &v in values {
        let mut b: Vec<u8> = match dt {
            Dt::U8 => vec![v as u8],
            Dt::I8 => vec![v as i8 as u8],
            Dt::I16 => (v as i16).to_le_bytes().to_vec(),
            Dt::U16 => (v as u16).to_le_bytes().to_vec(),
            Dt::I32 => (v as i32).to_le_bytes().to_vec(),
            Dt::U64 => (v as u64).to_le_bytes().to_vec(),
            Dt::F32 => (v as f32).to_le_bytes().to_vec(),
            Dt::F64 => v.to_le_bytes().to_vec(),
        };
        if big_endian {
            b.reverse();
        }
        out.extend(b);
    }
    out
}

fn write_both(dir: &TempDir, name: &str, bytes: &[u8]) -> [std::path::PathBuf; 2] {
    let plain = dir.path().join(format!("{name}.nii"));
    let gz = dir.path().join(format!("{name}.nii.gz"));
    fs::write(&plain, bytes).unwrap();
    fs::write(&gz, gzip(bytes)).unwrap();
    [plain, gz]
}

#[test]
fn nifti_data_are_read_from_vox_offset_not_byte_352() {
    let dir = TempDir::new().unwrap();
    let values: Vec<f64> = fortran_flat(&truth()).iter().map(|&v| f64::from(v) * 3.0).collect();
    for big_endian in [false, true] {
        let mut nii = Nii::new([3, 4, 5], Dt::I16);
        nii.big_endian = big_endian;
        nii.vox_offset = 1024.0;
        // Non-zero filler between the header and the data: read from byte 352, the
        // mask would be all ones at the start.
        let bytes = nii.bytes(&encode(&values, Dt::I16, big_endian), 0xAB);
        for path in write_both(&dir, &format!("offset_{big_endian}"), &bytes) {
            let v = read_within(&path, MIB).unwrap();
            assert_eq!(v.mask, truth(), "{}", path.display());
        }
    }
}

#[test]
fn nifti_big_endian_values_are_decoded_in_their_byte_order() {
    // Scaling makes the byte order matter even for integers: 256 * 1 - 256 is 0
    // only if 256 is decoded as 256 (read little-endian, 0x0100 is 1).
    let dir = TempDir::new().unwrap();
    let flat = fortran_flat(&truth());
    let cases: [(Dt, f64, f32, f32); 5] = [
        (Dt::I16, 256.0, 1.0, -256.0),
        (Dt::U16, 256.0, 1.0, -256.0),
        (Dt::I32, 65536.0, 1.0, -65536.0),
        (Dt::F32, 2.0, 0.5, 0.0),
        (Dt::F64, 4.0, 0.25, 0.0),
    ];
    for (dt, on, slope, inter) in cases {
        // Integers: background `on` (scaled to 0), vessel `on + 1`. Floats: background
        // 0, vessel `on` (scaled to 1).
        let float = matches!(dt, Dt::F32 | Dt::F64);
        let values: Vec<f64> = flat
            .iter()
            .map(|&m| match (float, m) {
                (true, 0) => 0.0,
                (true, _) => on,
                (false, 0) => on,
                (false, _) => on + 1.0,
            })
            .collect();
        for big_endian in [false, true] {
            let mut nii = Nii::new([3, 4, 5], dt);
            (nii.big_endian, nii.slope, nii.inter) = (big_endian, slope, inter);
            let bytes = nii.bytes(&encode(&values, dt, big_endian), 0);
            for path in write_both(&dir, &format!("{dt:?}_{big_endian}"), &bytes) {
                let v = read_within(&path, MIB).unwrap();
                assert_eq!(v.mask, truth(), "{dt:?} big-endian {big_endian}: {}", path.display());
            }
        }
    }
}

#[test]
fn nifti_every_integer_type_in_both_byte_orders() {
    let dir = TempDir::new().unwrap();
    let flat = fortran_flat(&truth());
    for dt in [Dt::U8, Dt::I8, Dt::I16, Dt::U16, Dt::I32, Dt::U64] {
        // Vessel voxels hold a value whose low byte is 0 in little-endian order.
        let on = match dt.size() {
            1 => 128.0,
            _ => 256.0,
        };
        let values: Vec<f64> = flat.iter().map(|&m| f64::from(m) * on).collect();
        for big_endian in [false, true] {
            let mut nii = Nii::new([3, 4, 5], dt);
            nii.big_endian = big_endian;
            nii.pixdim = [0.5, -2.0, 3.0];
            let path = dir.path().join(format!("{dt:?}_{big_endian}.nii"));
            fs::write(&path, nii.bytes(&encode(&values, dt, big_endian), 0)).unwrap();
            let v = read_within(&path, MIB).unwrap();
            assert_eq!(v.mask, truth(), "{dt:?} big-endian {big_endian}");
            assert_eq!(v.spacing, [0.5, 2.0, 3.0]);
        }
    }
}

#[test]
fn nifti_scaling_rules_follow_nibabel() {
    let dir = TempDir::new().unwrap();
    let ones = vec![1u8; 60];
    let read = |slope: f32, inter: f32| {
        let mut nii = Nii::new([3, 4, 5], Dt::U8);
        (nii.slope, nii.inter) = (slope, inter);
        let path = dir.path().join("s.nii");
        fs::write(&path, nii.bytes(&ones, 0)).unwrap();
        read_within(&path, MIB)
    };
    // 1 * 1 - 1 = 0: scaling applied.
    assert!(read(1.0, -1.0).unwrap().mask.iter().all(|&v| v == 0));
    // Slope 0, NaN or infinite: no scaling, whatever the intercept.
    for slope in [0.0, f32::NAN, f32::INFINITY] {
        assert!(read(slope, -1.0).unwrap().mask.iter().all(|&v| v == 1), "slope {slope}");
    }
    // A valid slope with a non-finite intercept is an error (nibabel raises too).
    let msg = error_text(read(1.0, f32::NAN));
    assert!(msg.contains("s.nii") && msg.contains("scl_inter"), "{msg}");
}

#[test]
fn nifti_bad_vox_offset_length_or_magic_is_refused() {
    let dir = TempDir::new().unwrap();
    let data = fortran_flat(&truth());
    let path = dir.path().join("bad.nii");
    let check = |bytes: Vec<u8>, expect: &str| {
        fs::write(&path, &bytes).unwrap();
        let msg = error_text(read_within(&path, MIB));
        assert!(msg.contains("bad.nii") && msg.contains(expect), "{msg}");
        let gz = dir.path().join("bad.nii.gz");
        fs::write(&gz, gzip(&bytes)).unwrap();
        let msg = error_text(read_within(&gz, MIB));
        assert!(msg.contains("bad.nii.gz"), "{msg}");
    };
    for offset in [0.0, 200.0, -1.0, f32::NAN, f32::INFINITY] {
        let mut nii = Nii::new([3, 4, 5], Dt::U8);
        nii.vox_offset = offset;
        check(nii.bytes(&data, 0), "vox_offset");
    }
    let nii = Nii::new([3, 4, 5], Dt::U8);
    let good = nii.bytes(&data, 0);
    check(good[..good.len() - 1].to_vec(), "truncated");
    check([good.as_slice(), &[0]].concat(), "trailing");
    check(good[..300].to_vec(), "header");
    // An offset past the end of the file.
    let mut far = good.clone();
    far[108..112].copy_from_slice(&1e9f32.to_le_bytes());
    check(far, "truncated");
    // Header of a .hdr/.img pair, NIfTI-2, and dimensions that are not sizes.
    let mut pair = nii.clone();
    pair.magic = *b"ni1\0";
    check(pair.bytes(&data, 0), ".hdr/.img");
    let mut two = good.clone();
    two[..4].copy_from_slice(&540i32.to_le_bytes());
    check(two, "NIfTI-2");
    for dims in [[3, 0, 5], [3, -4, 5]] {
        check(Nii::new(dims, Dt::U8).bytes(&data, 0), "dim[2]");
    }
}

#[test]
fn nifti_corrupt_pixdim_is_refused_and_the_range_is_inclusive() {
    let dir = TempDir::new().unwrap();
    let data = fortran_flat(&truth());
    let path = dir.path().join("p.nii");
    let read = |pixdim: [f32; 3]| {
        let mut nii = Nii::new([3, 4, 5], Dt::U8);
        nii.pixdim = pixdim;
        fs::write(&path, nii.bytes(&data, 0)).unwrap();
        read_within(&path, MIB)
    };
    for bad in [0.0, -0.0, f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 1e30, -1e30, 1e-30, 1e13, 1e-13] {
        match read([1.0, bad, 1.0]) {
            Err(e @ IoError::BadPixdim { .. }) => {
                let msg = e.to_string();
                assert!(msg.contains("p.nii") && msg.contains("1e-12") && msg.contains("1e12"), "{msg}");
            }
            other => panic!("pixdim {bad}: expected BadPixdim, got {other:?}"),
        }
    }
    assert_eq!(read([1e-12, 1e12, -1e12]).unwrap().spacing, [1e-12, 1e12, 1e12]);
    // A spacing given by the caller replaces a corrupt header's.
    let v = read_volume_limited(&path, Some([1.0, 2.0, 3.0]), MaskRule::Binary, ReadLimits::new(MIB)).unwrap();
    assert_eq!(v.spacing, [1.0, 2.0, 3.0]);
}

#[test]
fn nifti_gz_declaring_a_gibibyte_is_refused_before_inflating() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("x.nii.gz");
    // 512 x 512 x 4096 bytes declared; the stream really holds 1 MiB of them.
    let header = Nii::new([512, 512, 4096], Dt::U8).bytes(&[], 0);
    let bytes = [header.as_slice(), &vec![0u8; MIB as usize]].concat();
    fs::write(&path, gzip(&bytes)).unwrap();
    let budget = 64 * MIB;
    let err = read_within(&path, budget).unwrap_err();
    assert!(
        matches!(err, IoError::TooLarge { needed, allowed, .. } if needed > 1 << 30 && allowed == budget),
        "{err:?}"
    );
    assert_eq!(
        err.to_string(),
        format!(
            "cannot read {}: the header declares 512×512×4096 voxels (1.0 GiB) but only 64.0 MiB may be used; \
             free memory, raise the memory budget or crop the volume",
            path.display()
        )
    );
    // Within a budget that allows it, the short stream is a clean "truncated".
    let msg = error_text(read_within(&path, 2 << 30));
    assert!(msg.contains("x.nii.gz") && msg.contains("truncated"), "{msg}");
}

#[test]
fn nifti_gz_stream_longer_than_declared_is_refused_without_inflating_it_whole() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("bomb.nii.gz");
    let nii = Nii::new([3, 4, 5], Dt::U8);
    // 64 MiB of zeros after the 60 declared bytes: about 64 KiB compressed.
    let bytes = [nii.bytes(&fortran_flat(&truth()), 0), vec![0u8; 64 * MIB as usize]].concat();
    fs::write(&path, gzip(&bytes)).unwrap();
    let msg = error_text(read_within(&path, MIB));
    assert!(msg.contains("bomb.nii.gz") && msg.contains("trailing data"), "{msg}");
}

// ---------------------------------------------------------------------------
// .npy

#[test]
fn npy_header_length_beyond_the_file_is_refused() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("bomb.npy");
    // 20 bytes: magic, version 2.0, a header length of 4 GiB - 1, 8 bytes.
    let mut bytes = b"\x93NUMPY\x02\x00".to_vec();
    bytes.extend_from_slice(&u32::MAX.to_le_bytes());
    bytes.extend_from_slice(b"{'descr'");
    assert_eq!(bytes.len(), 20);
    fs::write(&path, &bytes).unwrap();
    let msg = error_text(read_within(&path, MIB));
    assert!(msg.contains("bomb.npy") && msg.contains("4294967295") && msg.contains("exceeds"), "{msg}");
    // Also under the default budget (the old reader allocated the 4 GiB first).
    let (result, peak) = peak_bytes(|| read_volume(&path));
    assert!(result.is_err() && peak < MIB, "{peak}");
}

#[test]
fn npy_over_the_budget_is_too_large_and_names_shape_and_limit() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("big.npy");
    fs::write(&path, npy_bytes("'|u1'", false, "(64, 64, 64)", &[1; 64 * 64 * 64])).unwrap();
    let err = read_within(&path, 100 << 10).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, IoError::TooLarge { allowed: 102400, .. }), "{err:?}");
    assert!(msg.contains("big.npy") && msg.contains("64×64×64 voxels") && msg.contains("100.0 KiB"), "{msg}");
    // Twice that budget reads it.
    assert_eq!(read_within(&path, 600 << 10).unwrap().mask.len(), 64 * 64 * 64);
}

#[test]
fn npy_deeply_nested_header_is_refused() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("deep.npy");
    let deep = format!("{}{}", "[".repeat(5000), "]".repeat(5000));
    fs::write(&path, npy_bytes(&deep, false, "(1, 1, 1)", &[1])).unwrap();
    let msg = error_text(read_within(&path, MIB));
    assert!(msg.contains("deep.npy") && msg.contains("nests"), "{msg}");
}

#[test]
fn npy_bool_and_integers_of_every_byte_order_are_read() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("t.npy");
    // (1, 2, 2) C order: values 0, x, 0, x with x's only non-zero byte the last one
    // in file order (so a reader that decoded the wrong order still sees non-zero:
    // the mask does not depend on byte order, and every form must be accepted).
    for (descr, size) in [
        ("'|b1'", 1),
        ("'?'", 1),
        ("'|i1'", 1),
        ("'|u1'", 1),
        ("'<i2'", 2),
        ("'>i2'", 2),
        ("'<u2'", 2),
        ("'>u2'", 2),
        ("'=i4'", 4),
        ("'>i4'", 4),
        ("'<u4'", 4),
        ("'>i8'", 8),
        ("'<u8'", 8),
    ] {
        let mut data = Vec::new();
        for on in [false, true, false, true] {
            let mut item = vec![0u8; size];
            if on {
                item[size - 1] = 1;
            }
            data.extend(item);
        }
        fs::write(&path, npy_bytes(descr, false, "(1, 2, 2)", &data)).unwrap();
        let v = read_within(&path, MIB).unwrap_or_else(|e| panic!("{descr}: {e}"));
        assert_eq!(v.mask, ndarray::array![[[0u8, 1], [0, 1]]], "{descr}");
    }
}

#[test]
fn npy_object_text_date_and_subarray_dtypes_are_refused_cleanly() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("o.npy");
    for (descr, expect) in [
        // A pickled object array: the pickle after the header is never touched.
        ("'|O'", "Python objects"),
        ("'<U3'", "not a bool, integer or float"),
        ("'|S4'", "not a bool, integer or float"),
        ("'<M8[ns]'", "not a bool, integer or float"),
        ("'<f16'", "floating point"),
        ("'<i3'", "not a bool, integer or float"),
        ("('<i4', (2,))", "structured"),
        ("5", "structured"),
    ] {
        fs::write(&path, npy_bytes(descr, false, "(1, 1, 1)", b"\x80\x04\x95pickle.")).unwrap();
        match read_within(&path, MIB) {
            Err(e @ IoError::NotAMask { .. }) => {
                let msg = e.to_string();
                assert!(msg.contains("o.npy") && msg.contains(expect), "{descr}: {msg}");
            }
            other => panic!("{descr}: expected NotAMask, got {other:?}"),
        }
    }
}

// ---------------------------------------------------------------------------
// TIFF files built by hand

/// A little-endian TIFF whose `pages` directories all describe a `width` x
/// `height` page of `bits`-bit grey pixels stored in one strip, `strip` (shared by
/// every page), compressed with `compression` (1 none, 8 deflate).
fn tiff_bytes(width: u32, height: u32, bits: u16, compression: u16, pages: usize, strip: &[u8]) -> Vec<u8> {
    let mut bytes = b"II*\0".to_vec();
    let strip_at = 8u32;
    let first_ifd = strip_at + strip.len() as u32;
    let first_ifd = first_ifd + first_ifd % 2;
    bytes.extend_from_slice(&first_ifd.to_le_bytes());
    bytes.extend_from_slice(strip);
    bytes.resize(first_ifd as usize, 0);
    const IFD_BYTES: u32 = 2 + 9 * 12 + 4;
    for page in 0..pages {
        let entries: [(u16, u16, u32); 9] = [
            (256, 4, width),
            (257, 4, height),
            (258, 3, u32::from(bits)),
            (259, 3, u32::from(compression)),
            (262, 3, 1),
            (273, 4, strip_at),
            (277, 3, 1),
            (278, 4, height),
            (279, 4, strip.len() as u32),
        ];
        bytes.extend_from_slice(&9u16.to_le_bytes());
        for (tag, kind, value) in entries {
            bytes.extend_from_slice(&tag.to_le_bytes());
            bytes.extend_from_slice(&kind.to_le_bytes());
            bytes.extend_from_slice(&1u32.to_le_bytes());
            bytes.extend_from_slice(&value.to_le_bytes());
        }
        let next = if page + 1 < pages { first_ifd + (page as u32 + 1) * IFD_BYTES } else { 0 };
        bytes.extend_from_slice(&next.to_le_bytes());
    }
    bytes
}

fn zlib(bytes: &[u8]) -> Vec<u8> {
    let mut enc = ZlibEncoder::new(Vec::new(), Compression::best());
    enc.write_all(bytes).unwrap();
    enc.finish().unwrap()
}

#[test]
fn tiff_built_by_hand_reads_back() {
    // The builder of the bomb tests makes valid files: 3 pages of a 5 x 4 pattern,
    // uncompressed and deflated.
    let dir = TempDir::new().unwrap();
    let page: Vec<u8> = (0..20).map(|i| if i % 3 == 0 { 200 } else { 0 }).collect();
    for (compression, strip) in [(1, page.clone()), (8, zlib(&page))] {
        let path = dir.path().join(format!("hand{compression}.tif"));
        fs::write(&path, tiff_bytes(5, 4, 8, compression, 3, &strip)).unwrap();
        let v = read_within(&path, MIB).unwrap();
        assert_eq!(v.mask.dim(), (3, 4, 5));
        for ((_, r, c), &x) in v.mask.indexed_iter() {
            assert_eq!(x, u8::from((r * 5 + c) % 3 == 0));
        }
    }
}

#[test]
fn tiff_claiming_2_pow_32_squared_pixels_is_too_large_not_a_panic() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("huge.tif");
    let bytes = tiff_bytes(u32::MAX, u32::MAX, 64, 1, 1, &[0; 8]);
    assert!(bytes.len() < 140, "{}", bytes.len());
    fs::write(&path, &bytes).unwrap();
    let msg = error_text(read_within(&path, FUZZ_BUDGET));
    assert!(msg.contains("huge.tif") && msg.contains("4294967295×4294967295"), "{msg}");
    assert!(msg.contains("more than 16 EiB"), "{msg}");
    // Also under the default budget.
    let (result, peak) = peak_bytes(|| read_volume(&path));
    assert!(matches!(result, Err(IoError::TooLarge { .. })) && peak < MIB, "{result:?} {peak}");
}

#[test]
fn tiff_uncompressed_page_larger_than_the_file_is_truncated() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("short.tif");
    fs::write(&path, tiff_bytes(4000, 4000, 8, 1, 1, &[0; 16])).unwrap();
    let msg = error_text(read_within(&path, FUZZ_BUDGET));
    assert!(msg.contains("short.tif") && msg.contains("truncated"), "{msg}");
}

#[test]
fn tiff_page_bomb_stops_at_the_budget() {
    // 2000 pages of 256 x 256 sharing one deflated strip of zeros: 128 MiB of mask
    // from a file of about 230 KB.
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("pages.tif");
    let strip = zlib(&vec![0u8; 256 * 256]);
    fs::write(&path, tiff_bytes(256, 256, 8, 8, 2000, &strip)).unwrap();
    let budget = 8 * MIB;
    let err = read_within(&path, budget).unwrap_err();
    assert!(matches!(err, IoError::TooLarge { allowed, .. } if allowed == budget), "{err:?}");
    let msg = err.to_string();
    assert!(msg.contains("pages.tif") && msg.contains("×256×256 voxels"), "{msg}");
    // The same file with few enough pages reads.
    fs::write(&path, tiff_bytes(256, 256, 8, 8, 20, &strip)).unwrap();
    let v = read_within(&path, budget).unwrap();
    assert_eq!((v.mask.dim(), v.mask.iter().any(|&x| x != 0)), ((20, 256, 256), false));
}

#[test]
fn tiff_deflate_bomb_is_refused_or_cut_at_the_declared_size() {
    let dir = TempDir::new().unwrap();
    // A declared 8192 x 8192 page (64 MiB decoded) of a 64 KiB deflate stream:
    // refused before inflating on a 16 MiB budget.
    let path = dir.path().join("big.tif");
    let strip = zlib(&vec![0u8; 8192 * 8192]);
    fs::write(&path, tiff_bytes(8192, 8192, 8, 8, 1, &strip)).unwrap();
    assert!(matches!(read_within(&path, 16 * MIB), Err(IoError::TooLarge { .. })));
    // A declared 64 x 64 page whose strip inflates to 64 MiB: only the page is
    // inflated (the reader holds well under 1 MiB).
    let path = dir.path().join("liar.tif");
    fs::write(&path, tiff_bytes(64, 64, 8, 8, 1, &strip)).unwrap();
    let (result, peak) = peak_bytes(|| read_volume_limited(&path, None, MaskRule::Binary, ReadLimits::new(16 * MIB)));
    assert!(peak < MIB, "held {peak} bytes");
    if let Ok(v) = result {
        assert_eq!(v.mask, ndarray::Array3::<u8>::zeros((1, 64, 64)));
    }
}

// ---------------------------------------------------------------------------
// Property tests: random and mutated files never panic, never exceed the budget,
// and where a mutation leaves the header alone the result is the right mask.

/// A valid file of each format holding `truth()` (or its pages).
fn valid_npy() -> Vec<u8> {
    let flat: Vec<u8> = truth().iter().copied().collect();
    npy_bytes("'|u1'", false, "(3, 4, 5)", &flat)
}

fn valid_nii() -> Vec<u8> {
    let mut nii = Nii::new([3, 4, 5], Dt::U8);
    nii.vox_offset = 400.0;
    nii.bytes(&fortran_flat(&truth()), 7)
}

fn valid_tif() -> Vec<u8> {
    let page: Vec<u8> = (0..20).map(|i| if i % 3 == 0 { 200 } else { 0 }).collect();
    tiff_bytes(5, 4, 8, 8, 3, &zlib(&page))
}

/// A mutation of a valid file.
#[derive(Clone, Debug)]
enum Mutation {
    /// XOR bytes at (position fraction, mask) pairs.
    Flip(Vec<(f64, u8)>),
    /// Keep this fraction of the file.
    Truncate(f64),
    /// Append these bytes.
    Extend(Vec<u8>),
    /// Overwrite 4 bytes at a position with a "size-like" number.
    Plant(f64, u32),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        prop::collection::vec((0.0..1.0f64, 1..=255u8), 1..8).prop_map(Mutation::Flip),
        (0.0..1.0f64).prop_map(Mutation::Truncate),
        prop::collection::vec(any::<u8>(), 1..64).prop_map(Mutation::Extend),
        (0.0..1.0f64, prop_oneof![Just(0u32), Just(u32::MAX), Just(1 << 31), Just(0x7fff), any::<u32>()])
            .prop_map(|(at, v)| Mutation::Plant(at, v)),
    ]
}

fn mutate(bytes: &[u8], m: &Mutation) -> Vec<u8> {
    let mut out = bytes.to_vec();
    let at = |f: f64, len: usize| ((f * len as f64) as usize).min(len.saturating_sub(1));
    match m {
        Mutation::Flip(flips) => {
            for &(f, mask) in flips {
                let i = at(f, out.len());
                out[i] ^= mask;
            }
        }
        Mutation::Truncate(f) => out.truncate(at(*f, out.len())),
        Mutation::Extend(tail) => out.extend_from_slice(tail),
        Mutation::Plant(f, v) => {
            let i = at(*f, out.len().saturating_sub(4));
            out[i..i + 4].copy_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// Read `bytes` as `name` within the fuzz budget; an `Ok` must be a 0/1 mask.
fn fuzz_read(dir: &TempDir, name: &str, bytes: &[u8]) -> Result<VolumeFile, IoError> {
    let path = dir.path().join(name);
    fs::write(&path, bytes).unwrap();
    let result = read_within(&path, FUZZ_BUDGET);
    if let Ok(v) = &result {
        assert!(v.mask.iter().all(|&x| x <= 1));
    }
    if let Err(e) = &result {
        assert!(e.to_string().contains(name), "{e}");
    }
    result
}

/// Builds a valid file of one format.
type Seed = fn() -> Vec<u8>;

const FORMATS: [(&str, Seed); 4] =
    [("m.npy", valid_npy), ("m.nii", valid_nii), ("m.nii.gz", valid_nii), ("m.tif", valid_tif)];

fn file_of(name: &str, make: Seed) -> Vec<u8> {
    if name.ends_with(".gz") {
        gzip(&make())
    } else {
        make()
    }
}

fn check_mutated(dir: &TempDir, name: &str, valid: &[u8], m: &Mutation) {
    let bytes = mutate(valid, m);
    let _ = fuzz_read(dir, name, &bytes);
}

/// Flip bits in the data block only (header intact): the result must be the
/// mask of the flipped data, exactly.
fn check_data_flip(dir: &TempDir, name: &str, flips: &[(f64, u8)]) {
    let (valid, data_start, c_order) = match name {
        "m.npy" => (valid_npy(), valid_npy().len() - 60, true),
        _ => (valid_nii(), 400, false),
    };
    let mut bytes = valid.clone();
    for &(f, mask) in flips {
        let i = data_start + ((f * 60.0) as usize).min(59);
        bytes[i] ^= mask;
    }
    let data = &bytes[data_start..];
    let expected = if c_order {
        ndarray::Array3::from_shape_fn((3, 4, 5), |(i, j, k)| u8::from(data[i * 20 + j * 5 + k] != 0))
    } else {
        ndarray::Array3::from_shape_fn((3, 4, 5), |(i, j, k)| u8::from(data[i + 3 * j + 12 * k] != 0))
    };
    // Flips that leave two or more non-zero values make a label image, which the input
    // rule refuses naming them.
    let mut nonzero: Vec<u8> = data.iter().copied().filter(|&x| x != 0).collect();
    nonzero.sort_unstable();
    nonzero.dedup();
    match fuzz_read(dir, name, &bytes) {
        Ok(v) => {
            assert!(nonzero.len() <= 1, "{nonzero:?} read as a mask");
            assert_eq!(v.mask, expected);
        }
        Err(e @ IoError::NotAMask { .. }) => {
            assert!(nonzero.len() >= 2, "{e}");
            assert!(e.to_string().contains("uint8 values 0, "), "{e}");
        }
        Err(e) => panic!("{e}"),
    }
}

fn config(cases: u32) -> ProptestConfig {
    ProptestConfig { cases, failure_persistence: None, ..ProptestConfig::default() }
}

proptest! {
    #![proptest_config(config(300))]

    #[test]
    fn random_bytes_are_refused_cleanly(bytes in prop::collection::vec(any::<u8>(), 0..600), which in 0..4usize) {
        let dir = TempDir::new().unwrap();
        let (name, _) = FORMATS[which];
        // Random bytes behind each format's magic, so the parsers get past it.
        let magic: &[u8] = match name {
            "m.npy" => b"\x93NUMPY\x01\x00",
            "m.tif" => b"II*\0",
            _ => b"",
        };
        let _ = fuzz_read(&dir, name, &[magic, &bytes].concat());
    }

    #[test]
    fn mutated_npy_never_panics_or_overspends(m in mutation()) {
        let dir = TempDir::new().unwrap();
        check_mutated(&dir, "m.npy", &valid_npy(), &m);
    }

    #[test]
    fn mutated_nii_never_panics_or_overspends(m in mutation()) {
        let dir = TempDir::new().unwrap();
        check_mutated(&dir, "m.nii", &valid_nii(), &m);
    }

    #[test]
    fn mutated_nii_gz_never_panics_or_overspends(m in mutation(), inside in any::<bool>()) {
        // Mutate the inflated file (then compress it) or the compressed bytes.
        let dir = TempDir::new().unwrap();
        let bytes = if inside { gzip(&mutate(&valid_nii(), &m)) } else { mutate(&gzip(&valid_nii()), &m) };
        let _ = fuzz_read(&dir, "m.nii.gz", &bytes);
    }

    #[test]
    fn mutated_tif_never_panics_or_overspends(m in mutation()) {
        let dir = TempDir::new().unwrap();
        check_mutated(&dir, "m.tif", &valid_tif(), &m);
    }

    #[test]
    fn flipped_data_bytes_give_exactly_the_flipped_mask(
        flips in prop::collection::vec((0.0..1.0f64, 1..=255u8), 1..6),
        npy in any::<bool>(),
    ) {
        let dir = TempDir::new().unwrap();
        check_data_flip(&dir, if npy { "m.npy" } else { "m.nii" }, &flips);
    }
}

#[test]
fn valid_fuzz_seeds_read_as_the_truth() {
    let dir = TempDir::new().unwrap();
    for (name, make) in FORMATS {
        let v = fuzz_read(&dir, name, &file_of(name, make)).unwrap();
        let expected = if name == "m.tif" {
            ndarray::Array3::from_shape_fn((3, 4, 5), |(_, r, c)| u8::from((r * 5 + c) % 3 == 0))
        } else {
            truth()
        };
        assert_eq!(v.mask, expected, "{name}");
    }
}

/// The long campaign: 50 000 mutations per format (`cargo test -p vesselflow-io
/// --release -- --ignored`, a few minutes). CI runs the 300-case versions above.
#[test]
#[ignore]
fn long_fuzz_campaign() {
    let mut runner = proptest::test_runner::TestRunner::new(config(50_000));
    let dir = TempDir::new().unwrap();
    for (name, make) in FORMATS {
        let valid = file_of(name, make);
        runner
            .run(&mutation(), |m| {
                check_mutated(&dir, name, &valid, &m);
                Ok(())
            })
            .unwrap_or_else(|e| panic!("{name}: {e}"));
    }
    runner
        .run(&(prop::collection::vec(any::<u8>(), 0..2000), 0..4usize), |(bytes, which)| {
            let _ = fuzz_read(&dir, FORMATS[which].0, &bytes);
            Ok(())
        })
        .unwrap();
}
