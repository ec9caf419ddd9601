//! Volume readers against files written by other libraries (ndarray-npy, the
//! nifti crate's writer, hand-built headers): values, axis order, spacing, and
//! a clear refusal of everything that is not a 3-D binary mask.

mod common;

use common::npy_bytes;
use ndarray::{Array, Array2, Array3, Array4, ShapeBuilder};
use ndarray_npy::WriteNpyExt;
use std::fs::{self, File};
use std::path::{Path, PathBuf};
use tempfile::TempDir;
use vesselflow_io::{read_volume, read_volume_with_spacing, IoError};

/// A 3x4x5 volume whose value at (i, j, k) depends on all three indices, so any
/// axis mix-up or transposition changes it; about half the voxels are zero.
fn pattern<T: Copy>(zero: T, values: [T; 3]) -> Array3<T> {
    Array3::from_shape_fn((3, 4, 5), |(i, j, k)| {
        let h = (i * 7 + j * 3 + k * 5) % 6;
        if h < 3 {
            zero
        } else {
            values[h - 3]
        }
    })
}

fn expected_mask() -> Array3<u8> {
    pattern(0u8, [1, 1, 1])
}

fn write_npy<A: WriteNpyExt>(path: &Path, array: &A) {
    array.write_npy(File::create(path).unwrap()).unwrap();
}

fn npy_header_text(path: &Path) -> String {
    String::from_utf8_lossy(&fs::read(path).unwrap()[..128]).into_owned()
}

/// Write `values` in C order and in Fortran order, read both back, compare.
fn npy_round_trip<T>(dir: &TempDir, name: &str, zero: T, values: [T; 3])
where
    T: Copy + ndarray_npy::WritableElement,
{
    let c_order = pattern(zero, values);
    let mut f_order = Array3::from_elem((3, 4, 5).f(), zero);
    f_order.assign(&c_order);

    let c_path = dir.path().join(format!("{name}_c.npy"));
    let f_path = dir.path().join(format!("{name}_f.npy"));
    write_npy(&c_path, &c_order);
    write_npy(&f_path, &f_order);
    assert!(npy_header_text(&c_path).contains("'fortran_order': False"));
    assert!(npy_header_text(&f_path).contains("'fortran_order': True"));

    for path in [c_path, f_path] {
        let volume = read_volume(&path).unwrap();
        assert_eq!(volume.mask, expected_mask(), "{name} from {}", path.display());
        assert_eq!(volume.spacing, [1.0, 1.0, 1.0]);
    }
}

#[test]
fn npy_bool_and_every_integer_dtype_in_c_and_fortran_order() {
    let dir = TempDir::new().unwrap();
    npy_round_trip(&dir, "bool", false, [true, true, true]);
    npy_round_trip(&dir, "u8", 0u8, [1, 7, 255]);
    npy_round_trip(&dir, "i8", 0i8, [-1, 5, i8::MIN]);
    npy_round_trip(&dir, "u16", 0u16, [1, 300, u16::MAX]);
    npy_round_trip(&dir, "i16", 0i16, [-300, 2, i16::MAX]);
    npy_round_trip(&dir, "u32", 0u32, [1, 70_000, u32::MAX]);
    npy_round_trip(&dir, "i32", 0i32, [-70_000, 3, i32::MIN]);
    npy_round_trip(&dir, "u64", 0u64, [1, 1 << 40, u64::MAX]);
    npy_round_trip(&dir, "i64", 0i64, [-(1 << 40), 9, i64::MIN]);
}

#[test]
fn npy_big_endian_integers_are_accepted() {
    // (Byte order cannot change whether an integer is zero; this checks that a
    // `>` descriptor is read at all, as NumPy writes on big-endian machines.)
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("big.npy");
    let data: Vec<u8> = [0i32, 256, 0, -5].iter().flat_map(|v| v.to_be_bytes()).collect();
    fs::write(&path, npy_bytes("'>i4'", false, "(1, 2, 2)", &data)).unwrap();
    let volume = read_volume(&path).unwrap();
    assert_eq!(volume.mask, ndarray::array![[[0u8, 1], [0, 1]]]);
}

fn error_text(result: Result<vesselflow_io::VolumeFile, IoError>) -> String {
    match result {
        Ok(v) => panic!("expected an error, got a volume of shape {:?}", v.mask.shape()),
        Err(e) => e.to_string(),
    }
}

#[test]
fn npy_float_is_refused_with_advice() {
    let dir = TempDir::new().unwrap();
    for (name, descr) in [("f32", "<f4"), ("f64", "<f8")] {
        let path = dir.path().join(format!("{name}.npy"));
        if name == "f32" {
            write_npy(&path, &pattern(0f32, [1.0, 1.0, 1.0]));
        } else {
            write_npy(&path, &pattern(0f64, [0.5, 1.0, 2.0]));
        }
        let msg = error_text(read_volume(&path));
        assert!(msg.contains(&path.display().to_string()), "{msg}");
        assert!(msg.contains(descr), "{msg}");
        assert!(msg.contains("threshold"), "{msg}");
    }
}

#[test]
fn npy_complex_and_structured_dtypes_are_refused() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("c.npy");
    fs::write(&path, npy_bytes("'<c8'", false, "(1, 1, 1)", &[0; 8])).unwrap();
    assert!(error_text(read_volume(&path)).contains("complex"));
    let path = dir.path().join("rec.npy");
    fs::write(&path, npy_bytes("[('a', '<i4'), ('b', '<i4')]", false, "(1, 1, 1)", &[0; 8])).unwrap();
    assert!(error_text(read_volume(&path)).contains("structured"));
}

#[test]
fn npy_wrong_ndim_names_the_shape() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("flat.npy");
    write_npy(&path, &Array2::<u8>::zeros((4, 5)));
    let msg = error_text(read_volume(&path));
    assert!(msg.contains("3-D") && msg.contains("(4, 5)"), "{msg}");

    let path = dir.path().join("four.npy");
    write_npy(&path, &Array4::<u8>::zeros((2, 3, 4, 5)));
    assert!(error_text(read_volume(&path)).contains("(2, 3, 4, 5)"));
}

#[test]
fn npy_truncated_or_corrupt_is_refused_naming_the_file() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("cut.npy");
    write_npy(&path, &pattern(0i32, [1, 2, 3]));
    let bytes = fs::read(&path).unwrap();
    fs::write(&path, &bytes[..bytes.len() - 10]).unwrap();
    let msg = error_text(read_volume(&path));
    assert!(msg.contains("cut.npy") && msg.contains("truncated"), "{msg}");

    // Cut inside the header.
    fs::write(&path, &bytes[..30]).unwrap();
    assert!(error_text(read_volume(&path)).contains("cut.npy"));

    // Not an npy file at all, and an empty file.
    let path = dir.path().join("junk.npy");
    fs::write(&path, b"this is not numpy data at all, just some text").unwrap();
    let msg = error_text(read_volume(&path));
    assert!(msg.contains("junk.npy") && msg.contains("not a valid .npy file"), "{msg}");
    fs::write(&path, b"").unwrap();
    assert!(error_text(read_volume(&path)).contains("junk.npy"));
}

#[test]
fn npy_header_claiming_a_huge_shape_fails_without_allocating() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("huge.npy");
    fs::write(&path, npy_bytes("'|u1'", false, "(100000, 100000, 100000)", &[1; 16])).unwrap();
    assert!(error_text(read_volume(&path)).contains("truncated"));
    fs::write(&path, npy_bytes("'<i8'", false, "(4294967296, 4294967296, 4294967296)", &[1; 16])).unwrap();
    assert!(error_text(read_volume(&path)).contains("too large"));
}

#[test]
fn npy_bool_bytes_other_than_one_are_true_as_in_numpy() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("bool.npy");
    fs::write(&path, npy_bytes("'|b1'", true, "(2, 1, 2)", &[0, 7, 1, 0])).unwrap();
    // Fortran order: flat index = i + 2 * k.
    assert_eq!(read_volume(&path).unwrap().mask, ndarray::array![[[0u8, 1]], [[1, 0]]]);
}

#[test]
fn npy_version_2_header_is_read() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("v2.npy");
    let dict = "{'descr': '<u2', 'fortran_order': False, 'shape': (1, 1, 2), }\n";
    let mut bytes = b"\x93NUMPY\x02\x00".to_vec();
    bytes.extend_from_slice(&(dict.len() as u32).to_le_bytes());
    bytes.extend_from_slice(dict.as_bytes());
    bytes.extend_from_slice(&[0, 0, 0, 1]);
    fs::write(&path, bytes).unwrap();
    assert_eq!(read_volume(&path).unwrap().mask, ndarray::array![[[0u8, 1]]]);
}

#[test]
fn missing_file_and_unsupported_extension() {
    let dir = TempDir::new().unwrap();
    for name in ["absent.npy", "absent.nii", "absent.nii.gz"] {
        let path = dir.path().join(name);
        let msg = error_text(read_volume(&path));
        assert!(msg.contains(name) && msg.contains("cannot read"), "{msg}");
    }
    let path = dir.path().join("mask.mha");
    fs::write(&path, b"ObjectType = Image\n").unwrap();
    let msg = error_text(read_volume(&path));
    assert!(msg.contains("mask.mha") && msg.contains(".npy") && msg.contains(".nii.gz"), "{msg}");
    assert!(msg.contains("vesselflow.load_volume"), "{msg}");
}

fn nifti_header(pixdim: [f32; 3]) -> nifti::NiftiHeader {
    nifti::NiftiHeader { pixdim: [1.0, pixdim[0], pixdim[1], pixdim[2], 1.0, 1.0, 1.0, 1.0], ..Default::default() }
}

fn write_nifti<A, D>(path: &Path, pixdim: [f32; 3], data: &Array<A, D>)
where
    A: nifti::DataElement + bytemuck::Pod,
    D: ndarray::Dimension + ndarray::RemoveAxis,
{
    let header = nifti_header(pixdim);
    nifti::writer::WriterOptions::new(path).reference_header(&header).write_nifti(data).unwrap();
}

#[test]
fn nifti_integer_mask_with_spacing_from_pixdim() {
    let dir = TempDir::new().unwrap();
    for name in ["m.nii", "m.nii.gz"] {
        let path = dir.path().join(name);
        write_nifti(&path, [0.3, 0.5, 2.0], &pattern(0i16, [1, 2, -3]));
        let volume = read_volume(&path).unwrap();
        assert_eq!(volume.mask, expected_mask(), "{name}");
        // 0.3 as written in f32 is read back as the decimal the user meant.
        assert_eq!(volume.spacing, [0.3, 0.5, 2.0], "{name}");
    }
    let path = dir.path().join("m.nii.gz");
    // gzip really was used (magic bytes 1f 8b).
    assert_eq!(&fs::read(&path).unwrap()[..2], &[0x1f, 0x8b]);
    // Explicit spacing replaces the header's.
    let volume = read_volume_with_spacing(&path, [4.0, 5.0, 6.0]).unwrap();
    assert_eq!(volume.spacing, [4.0, 5.0, 6.0]);
}

#[test]
fn nifti_negative_pixdim_is_taken_as_its_size_and_zero_is_refused() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("neg.nii");
    write_nifti(&path, [-1.5, 1.0, 2.0], &pattern(0u8, [1, 1, 1]));
    assert_eq!(read_volume(&path).unwrap().spacing, [1.5, 1.0, 2.0]);

    let path = dir.path().join("zero.nii");
    write_nifti(&path, [1.0, 0.0, 2.0], &pattern(0u8, [1, 1, 1]));
    let msg = error_text(read_volume(&path));
    assert!(msg.contains("zero.nii") && msg.contains("pixdim"), "{msg}");
    // ... unless the caller gives the spacing.
    assert_eq!(read_volume_with_spacing(&path, [1.0; 3]).unwrap().mask, expected_mask());
}

#[test]
fn nifti_float_zero_one_mask_is_accepted_and_float_image_refused() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("f.nii.gz");
    write_nifti(&path, [1.0, 1.0, 1.0], &pattern(0f32, [1.0, 1.0, 1.0]));
    assert_eq!(read_volume(&path).unwrap().mask, expected_mask());

    let path = dir.path().join("img.nii");
    let mut image = pattern(0f64, [1.0, 1.0, 1.0]);
    image[(2, 3, 4)] = 0.37;
    write_nifti(&path, [1.0, 1.0, 1.0], &image);
    let msg = error_text(read_volume(&path));
    assert!(msg.contains("img.nii") && msg.contains("0.37") && msg.contains("(2, 3, 4)"), "{msg}");
    assert!(msg.contains("threshold"), "{msg}");
}

/// Overwrite `scl_slope` and `scl_inter` (bytes 112..120 of a little-endian NIfTI-1 header).
fn set_scaling(path: &Path, slope: f32, inter: f32) {
    let mut bytes = fs::read(path).unwrap();
    bytes[112..116].copy_from_slice(&slope.to_le_bytes());
    bytes[116..120].copy_from_slice(&inter.to_le_bytes());
    fs::write(path, bytes).unwrap();
}

#[test]
fn nifti_scaling_is_applied_before_binarising() {
    let dir = TempDir::new().unwrap();
    // Float 0/2 with slope 0.5 is a 0/1 mask.
    let path = dir.path().join("scaled.nii");
    write_nifti(&path, [1.0, 1.0, 1.0], &pattern(0f32, [2.0, 2.0, 2.0]));
    assert!(read_volume(&path).is_err());
    set_scaling(&path, 0.5, 0.0);
    assert_eq!(read_volume(&path).unwrap().mask, expected_mask());

    // Integer 0/1 with inter -1 is the inverted mask.
    let path = dir.path().join("inverted.nii");
    write_nifti(&path, [1.0, 1.0, 1.0], &pattern(0u8, [1, 1, 1]));
    set_scaling(&path, 1.0, -1.0);
    assert_eq!(read_volume(&path).unwrap().mask, expected_mask().mapv(|v| 1 - v));

    // Slope 0 means "no scaling" (NIfTI-1).
    set_scaling(&path, 0.0, 5.0);
    assert_eq!(read_volume(&path).unwrap().mask, expected_mask());
}

#[test]
fn nifti_four_d_with_trailing_one_is_three_d_otherwise_refused() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("t1.nii");
    let four = expected_mask().insert_axis(ndarray::Axis(3));
    write_nifti(&path, [1.0, 2.0, 3.0], &four);
    let volume = read_volume(&path).unwrap();
    assert_eq!(volume.mask, expected_mask());
    assert_eq!(volume.spacing, [1.0, 2.0, 3.0]);

    let path = dir.path().join("t2.nii");
    write_nifti(&path, [1.0, 1.0, 1.0], &Array4::<u8>::zeros((3, 4, 5, 2)));
    let msg = error_text(read_volume(&path));
    assert!(msg.contains("t2.nii") && msg.contains("(3, 4, 5, 2)"), "{msg}");

    let path = dir.path().join("flat.nii");
    write_nifti(&path, [1.0, 1.0, 1.0], &Array2::<u8>::zeros((3, 4)));
    assert!(error_text(read_volume(&path)).contains("(3, 4)"));
}

#[test]
fn nifti_truncated_or_corrupt_is_refused_naming_the_file() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("cut.nii");
    write_nifti(&path, [1.0, 1.0, 1.0], &pattern(0i32, [1, 1, 1]));
    let bytes = fs::read(&path).unwrap();
    fs::write(&path, &bytes[..bytes.len() - 7]).unwrap();
    let msg = error_text(read_volume(&path));
    assert!(msg.contains("cut.nii") && msg.contains("NIfTI"), "{msg}");

    let path: PathBuf = dir.path().join("junk.nii.gz");
    fs::write(&path, b"definitely not gzip").unwrap();
    assert!(error_text(read_volume(&path)).contains("junk.nii.gz"));
}

#[test]
fn nifti_unsupported_datatype_is_refused() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("rgb.nii");
    let rgb = Array3::from_elem((2, 2, 2), [1u8, 2, 3]);
    let header = nifti_header([1.0, 1.0, 1.0]);
    nifti::writer::WriterOptions::new(&path).reference_header(&header).write_rgb_nifti(&rgb).unwrap();
    let msg = error_text(read_volume(&path));
    assert!(msg.contains("rgb.nii") && msg.contains("Rgb24"), "{msg}");
}

/// Write a multi-page greyscale TIFF, optionally with ImageJ metadata.
fn write_tiff<C>(path: &Path, pages: &[Vec<C::Inner>], width: u32, height: u32, imagej: Option<(&str, u32)>)
where
    C: tiff::encoder::colortype::ColorType,
    [C::Inner]: tiff::encoder::TiffValue,
{
    let mut enc = tiff::encoder::TiffEncoder::new(fs::File::create(path).unwrap()).unwrap();
    for page in pages {
        let mut img = enc.new_image::<C>(width, height).unwrap();
        if let Some((description, pixels_per_unit)) = imagej {
            img.encoder().write_tag(tiff::tags::Tag::ImageDescription, description).unwrap();
            img.resolution(tiff::tags::ResolutionUnit::None, tiff::encoder::Rational { n: pixels_per_unit, d: 1 });
        }
        img.write_data(page).unwrap();
    }
}

#[test]
fn tiff_stacks_read_as_page_row_column_with_imagej_spacing() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("stack.tif");
    // 3 pages of 4 rows x 5 columns; voxel (p, r, c) set where (p + r + c) % 3 == 0.
    let page =
        |p: usize| (0..20).map(|i| if (p + i / 5 + i % 5).is_multiple_of(3) { 255u16 } else { 0 }).collect::<Vec<_>>();
    let pages: Vec<Vec<u16>> = (0..3).map(page).collect();
    write_tiff::<tiff::encoder::colortype::Gray16>(
        &path,
        &pages,
        5,
        4,
        Some(("ImageJ=1.53\nimages=3\nslices=3\nspacing=2.5\nunit=micron\n", 4)),
    );
    let v = read_volume(&path).unwrap();
    assert_eq!(v.mask.dim(), (3, 4, 5));
    for ((p, r, c), &x) in v.mask.indexed_iter() {
        assert_eq!(x, u8::from((p + r + c).is_multiple_of(3)), "voxel {p} {r} {c}");
    }
    assert_eq!(v.spacing, [2.5, 0.25, 0.25]);
    // Without ImageJ metadata the spacing is 1.
    let plain = dir.path().join("plain.tiff");
    write_tiff::<tiff::encoder::colortype::Gray8>(&plain, &[vec![0u8, 1, 0, 1]], 2, 2, None);
    let v = read_volume(&plain).unwrap();
    assert_eq!((v.mask.dim(), v.spacing), ((1, 2, 2), [1.0; 3]));
}

#[test]
fn tiff_intensity_and_truncated_files_are_refused() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("float.tif");
    write_tiff::<tiff::encoder::colortype::Gray32Float>(&path, &[vec![0.0f32, 0.4, 1.0, 0.0]], 2, 2, None);
    let msg = error_text(read_volume(&path));
    assert!(msg.contains("float.tif") && msg.contains("threshold"), "{msg}");
    let path = dir.path().join("cut.tif");
    write_tiff::<tiff::encoder::colortype::Gray8>(&path, &[vec![1u8; 64 * 64]], 64, 64, None);
    let bytes = fs::read(&path).unwrap();
    fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    let msg = error_text(read_volume(&path));
    assert!(msg.contains("cut.tif"), "{msg}");
}
