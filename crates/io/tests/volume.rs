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
use vesselflow_io::{read_volume, read_volume_limited, read_volume_with_spacing, IoError, MaskRule, ReadLimits};

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

/// Write the pattern of `zero` and `one` (the vessel value) in C order and in Fortran
/// order, read both back, compare.
fn npy_round_trip<T>(dir: &TempDir, name: &str, zero: T, one: T)
where
    T: Copy + ndarray_npy::WritableElement,
{
    let c_order = pattern(zero, [one; 3]);
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
fn npy_bool_and_every_integer_and_float_dtype_in_c_and_fortran_order() {
    let dir = TempDir::new().unwrap();
    npy_round_trip(&dir, "bool", false, true);
    npy_round_trip(&dir, "u8", 0u8, 255);
    npy_round_trip(&dir, "i8", 0i8, i8::MIN);
    npy_round_trip(&dir, "u16", 0u16, u16::MAX);
    npy_round_trip(&dir, "i16", 0i16, -300);
    npy_round_trip(&dir, "u32", 0u32, u32::MAX);
    npy_round_trip(&dir, "i32", 0i32, i32::MIN);
    npy_round_trip(&dir, "u64", 0u64, u64::MAX);
    npy_round_trip(&dir, "i64", 0i64, i64::MIN);
    npy_round_trip(&dir, "f32", 0f32, 1.0);
    npy_round_trip(&dir, "f64", -0f64, 1.0);
}

fn read_with(path: &Path, rule: MaskRule) -> Result<vesselflow_io::VolumeFile, IoError> {
    read_volume_limited(path, None, rule, ReadLimits::new(1 << 30))
}

#[test]
fn npy_label_images_are_refused_unless_a_label_or_threshold_is_given() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("labels.npy");
    let labels = pattern(0u16, [3, 6, 3]);
    write_npy(&path, &labels);
    let msg = error_text(read_volume(&path));
    assert!(msg.contains("labels.npy") && msg.contains("uint16 values 0, 3 and 6"), "{msg}");
    assert!(msg.contains("threshold=") && msg.contains("--label"), "{msg}");
    let label3 = read_with(&path, MaskRule::Label(3.0)).unwrap();
    assert_eq!(label3.mask, labels.mapv(|v| u8::from(v == 3)));
    let above4 = read_with(&path, MaskRule::Threshold(4.0)).unwrap();
    assert_eq!(above4.mask, labels.mapv(|v| u8::from(v == 6)));
}

#[test]
fn npy_big_endian_values_are_decoded() {
    // A label of 256 read in the wrong byte order would be 65536.
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("big.npy");
    let data: Vec<u8> = [0i32, 256, 0, -5].iter().flat_map(|v| v.to_be_bytes()).collect();
    fs::write(&path, npy_bytes("'>i4'", false, "(1, 2, 2)", &data)).unwrap();
    assert!(error_text(read_volume(&path)).contains("int32 values 0, 256 and -5"));
    let volume = read_with(&path, MaskRule::Label(256.0)).unwrap();
    assert_eq!(volume.mask, ndarray::array![[[0u8, 1], [0, 0]]]);
}

fn error_text(result: Result<vesselflow_io::VolumeFile, IoError>) -> String {
    match result {
        Ok(v) => panic!("expected an error, got a volume of shape {:?}", v.mask.shape()),
        Err(e) => e.to_string(),
    }
}

#[test]
fn npy_probability_map_is_refused_with_advice_and_thresholded_on_request() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("p.npy");
    let map = pattern(0f64, [0.75; 3]);
    write_npy(&path, &map);
    let msg = error_text(read_volume(&path));
    assert!(msg.contains(&path.display().to_string()), "{msg}");
    assert!(msg.contains("float64 values other than 0 and 1 (e.g. 0.75)"), "{msg}");
    assert!(msg.contains("threshold="), "{msg}");
    let mask = read_with(&path, MaskRule::Threshold(0.5)).unwrap().mask;
    assert_eq!(mask, map.mapv(|v| u8::from(v > 0.5)));
    // Half floats (0, 1, 0.5 as IEEE 754 binary16 bits): 0/1 is a mask, 0.5 is not.
    let path = dir.path().join("half.npy");
    let halves = |bits: [u16; 2]| bits.iter().flat_map(|b| b.to_le_bytes()).collect::<Vec<u8>>();
    fs::write(&path, npy_bytes("'<f2'", false, "(1, 1, 2)", &halves([0x0000, 0x3c00]))).unwrap();
    assert_eq!(read_volume(&path).unwrap().mask, ndarray::array![[[0u8, 1]]]);
    fs::write(&path, npy_bytes("'<f2'", false, "(1, 1, 2)", &halves([0x3800, 0x3c00]))).unwrap();
    assert!(error_text(read_volume(&path)).contains("float32 values other than 0 and 1 (e.g. 0.5)"));
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
        write_nifti(&path, [0.3, 0.5, 2.0], &pattern(0i16, [-3; 3]));
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
    assert!(msg.contains("img.nii") && msg.contains("float64 values other than 0 and 1 (e.g. 0.37)"), "{msg}");
    assert!(msg.contains("threshold="), "{msg}");
    let mask = read_with(&path, MaskRule::Threshold(0.5)).unwrap().mask;
    assert_eq!(mask, expected_mask());
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

    // Integer 0/1 with inter -1 holds -1 and 0 (floats, as in nibabel): not a mask,
    // but label -1 is the inverted mask.
    let path = dir.path().join("inverted.nii");
    write_nifti(&path, [1.0, 1.0, 1.0], &pattern(0u8, [1, 1, 1]));
    set_scaling(&path, 1.0, -1.0);
    assert!(error_text(read_volume(&path)).contains("float64 values other than 0 and 1 (e.g. -1)"));
    assert_eq!(read_with(&path, MaskRule::Label(-1.0)).unwrap().mask, expected_mask().mapv(|v| 1 - v));

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
fn tiff_label_stack_is_refused_across_pages_and_read_by_label() {
    // One label per page: only the stack as a whole shows two non-zero values.
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("labels.tif");
    write_tiff::<tiff::encoder::colortype::Gray8>(&path, &[vec![0u8, 3, 3, 0], vec![5u8, 0, 0, 5]], 2, 2, None);
    let msg = error_text(read_volume(&path));
    assert!(msg.contains("labels.tif") && msg.contains("uint8 values 0, 3 and 5"), "{msg}");
    let v = read_with(&path, MaskRule::Label(5.0)).unwrap();
    assert_eq!(v.mask, ndarray::array![[[0u8, 0], [0, 0]], [[1, 0], [0, 1]]]);
    let path = dir.path().join("float.tif");
    write_tiff::<tiff::encoder::colortype::Gray32Float>(&path, &[vec![0.0f32, 1.0, 1.0, 0.0]], 2, 2, None);
    assert_eq!(read_volume(&path).unwrap().mask, ndarray::array![[[0u8, 1], [1, 0]]]);
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
