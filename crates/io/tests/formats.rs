//! `.npz` masks, NIfTI affines, the formats of other tools (SWC, CSV, Neuroglancer
//! skeletons) and the all-or-nothing replacement of several outputs.

mod common;

use common::npy_bytes;
use ndarray::{array, Array3};
use ndarray_npy::NpzWriter;
use serde_json::json;
use std::fs::{self, File};
use std::path::{Path, PathBuf};
use tempfile::TempDir;
use vesselflow_io::{
    read_volume, read_volume_key, replace_all, write_graph_arrays, GraphArrays, GraphFormat, IoError, MaskRule,
    ReadLimits,
};

fn tube() -> Array3<u8> {
    Array3::from_shape_fn((4, 5, 6), |(i, j, k)| u8::from((i + 2 * j + 3 * k) % 4 == 0))
}

/// Adds one array to an `.npz` being written.
type AddArray<'a> = &'a dyn Fn(&mut NpzWriter<File>);

/// An `.npz` of the arrays that each closure adds.
fn write_npz(path: &Path, arrays: &[AddArray<'_>]) {
    let mut npz = NpzWriter::new(File::create(path).unwrap());
    for add in arrays {
        add(&mut npz);
    }
    npz.finish().unwrap();
}

#[test]
fn npz_mask_is_the_array_mask_or_the_only_one_with_the_archive_spacing() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("m.npz");
    let mask = tube().mapv(|v| v * 7); // integers 0 and one other value: a mask
    write_npz(
        &path,
        &[
            &|n| n.add_array("mask", &mask).unwrap(),
            &|n| n.add_array("spacing", &array![2.0f32, 0.5, 0.25]).unwrap(),
            &|n| n.add_array("other", &array![1i64, 2]).unwrap(),
        ],
    );
    let volume = read_volume(&path).unwrap();
    assert_eq!(volume.mask, tube());
    assert_eq!(volume.spacing, [2.0, 0.5, 0.25]);
    assert_eq!(volume.affine[0], [2.0, 0.0, 0.0, 0.0]);
    assert_eq!(volume.affine[2], [0.0, 0.0, 0.25, 0.0]);

    let only = dir.path().join("only.npz");
    write_npz(&only, &[&|n| n.add_array("vessels", &tube()).unwrap()]);
    let volume = read_volume(&only).unwrap();
    assert_eq!((volume.mask, volume.spacing), (tube(), [1.0; 3]));
}

#[test]
fn npz_key_picks_an_array_and_ambiguity_is_refused_naming_the_arrays() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("two.npz");
    let other = tube().mapv(|v| 1 - v);
    write_npz(&path, &[&|n| n.add_array("a", &tube()).unwrap(), &|n| n.add_array("b", &other).unwrap()]);
    let msg = read_volume(&path).unwrap_err().to_string();
    assert!(msg.contains("two.npz") && msg.contains("key") && msg.contains("a, b"), "{msg}");
    let read = |key| read_volume_key(&path, Some(key), None, MaskRule::Binary, ReadLimits::new(1 << 30));
    assert_eq!(read("b").unwrap().mask, other);
    let msg = read("c").unwrap_err().to_string();
    assert!(msg.contains("no array \"c\""), "{msg}");
    // A key means nothing to a single-array format.
    let npy = dir.path().join("m.npy");
    fs::write(&npy, npy_bytes("'|u1'", false, "(1, 1, 1)", &[1])).unwrap();
    let msg = read_volume_key(&npy, Some("b"), None, MaskRule::Binary, ReadLimits::new(1 << 30)).unwrap_err();
    assert!(msg.to_string().contains(".npz files only"), "{msg}");
}

#[test]
fn npz_member_is_checked_against_the_budget_and_a_bad_spacing_is_refused() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("big.npz");
    let big = Array3::<u8>::zeros((64, 64, 64));
    write_npz(&path, &[&|n| n.add_array("mask", &big).unwrap()]);
    let err = read_volume_key(&path, None, None, MaskRule::Binary, ReadLimits::new(100_000)).unwrap_err();
    assert!(matches!(err, IoError::TooLarge { .. }), "{err}");

    let bad = dir.path().join("bad.npz");
    write_npz(
        &bad,
        &[&|n| n.add_array("mask", &tube()).unwrap(), &|n| n.add_array("spacing", &array![1.0, 0.0, 1.0]).unwrap()],
    );
    let msg = read_volume(&bad).unwrap_err().to_string();
    assert!(msg.contains("bad.npz") && msg.contains("'spacing'") && msg.contains("finite"), "{msg}");
    // An explicit spacing replaces the file's, as for every format.
    let volume = read_volume_key(&bad, None, Some([1.0; 3]), MaskRule::Binary, ReadLimits::new(1 << 30)).unwrap();
    assert_eq!(volume.spacing, [1.0; 3]);

    let garbage = dir.path().join("garbage.npz");
    fs::write(&garbage, b"not a zip at all").unwrap();
    let msg = read_volume(&garbage).unwrap_err().to_string();
    assert!(msg.contains("garbage.npz") && msg.contains("not a valid .npz"), "{msg}");
}

fn write_nifti(path: &Path, header: &nifti::NiftiHeader) {
    nifti::writer::WriterOptions::new(path).reference_header(header).write_nifti(&tube()).unwrap();
}

#[test]
fn nifti_affine_is_the_sform_else_the_qform_else_pixdim() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("m.nii");
    let pixdim = [1.0, 0.5, 2.0, 4.0, 1.0, 1.0, 1.0, 1.0];
    let base = nifti::NiftiHeader { pixdim, sform_code: 0, qform_code: 0, ..Default::default() };
    write_nifti(&path, &base);
    let a = read_volume(&path).unwrap().affine;
    assert_eq!(a, [[0.5, 0.0, 0.0, 0.0], [0.0, 2.0, 0.0, 0.0], [0.0, 0.0, 4.0, 0.0], [0.0, 0.0, 0.0, 1.0]]);

    // qform: 90 degrees about z (quaternion (cos 45, 0, 0, sin 45)), qfac -1, an offset.
    let s = std::f32::consts::FRAC_1_SQRT_2;
    let mut q = nifti::NiftiHeader {
        qform_code: 1,
        quatern_d: s,
        quatern_x: 10.0,
        quatern_y: -5.0,
        quatern_z: 2.5,
        ..base.clone()
    };
    q.pixdim[0] = -1.0;
    write_nifti(&path, &q);
    let a = read_volume(&path).unwrap().affine;
    let want = [[0.0, -2.0, 0.0, 10.0], [0.5, 0.0, 0.0, -5.0], [0.0, 0.0, -4.0, 2.5], [0.0, 0.0, 0.0, 1.0]];
    for (row, want_row) in a.iter().zip(want) {
        for (x, w) in row.iter().zip(want_row) {
            assert!((x - w).abs() < 1e-6, "{a:?} != {want:?}");
        }
    }

    // sform wins over the qform.
    let sform = nifti::NiftiHeader {
        sform_code: 2,
        srow_x: [0.0, 0.0, 3.0, 1.0],
        srow_y: [0.0, 1.5, 0.0, 2.0],
        srow_z: [-0.5, 0.0, 0.0, 3.0],
        ..q
    };
    write_nifti(&path, &sform);
    let a = read_volume(&path).unwrap().affine;
    assert_eq!(a, [[0.0, 0.0, 3.0, 1.0], [0.0, 1.5, 0.0, 2.0], [-0.5, 0.0, 0.0, 3.0], [0.0, 0.0, 0.0, 1.0]]);
}

fn small_graph<'a>(
    positions: &'a ndarray::Array2<f64>,
    radii: &'a ndarray::Array1<f64>,
    edges: &'a ndarray::Array2<i64>,
    info: &'a serde_json::Value,
) -> GraphArrays<'a> {
    GraphArrays {
        positions: positions.view(),
        radii: radii.view(),
        edges: edges.view(),
        spacing: [1.0, 2.0, 3.0],
        info,
        params: info,
    }
}

#[test]
fn precomputed_skeleton_has_the_documented_binary_layout() {
    let dir = TempDir::new().unwrap();
    let positions = array![[1.0, 2.0, 3.0], [4.0, 5.5, 6.0], [7.0, 8.0, 9.25]];
    let radii = array![0.5, 1.5, 2.5];
    let edges = array![[0i64, 1], [1, 2]];
    let info = json!({});
    let path = dir.path().join("g.precomputed");
    write_graph_arrays(&path, &small_graph(&positions, &radii, &edges, &info)).unwrap();
    let bytes = fs::read(path.join("1")).unwrap();
    let u32_at = |i: usize| u32::from_le_bytes(bytes[i..i + 4].try_into().unwrap());
    let f32_at = |i: usize| f32::from_le_bytes(bytes[i..i + 4].try_into().unwrap());
    assert_eq!((u32_at(0), u32_at(4)), (3, 2));
    assert_eq!(bytes.len(), 8 + 3 * 12 + 2 * 8 + 3 * 4);
    assert_eq!((f32_at(8 + 4 * 4), f32_at(8 + 8 * 4)), (5.5, 9.25));
    assert_eq!((u32_at(44), u32_at(48), u32_at(52), u32_at(56)), (0, 1, 1, 2));
    assert_eq!((f32_at(60), f32_at(68)), (0.5, 2.5));
    let meta: serde_json::Value = serde_json::from_slice(&fs::read(path.join("info")).unwrap()).unwrap();
    assert_eq!(meta["@type"], "neuroglancer_skeletons");
    assert_eq!(meta["transform"], json!([0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]));
}

#[test]
fn swc_and_csv_follow_the_frame_and_the_pair_is_named_by_the_registry() {
    let dir = TempDir::new().unwrap();
    let positions = array![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]];
    let (radii, edges) = (array![0.5, 1.5], array![[0i64, 1]]);
    let info = json!({"coordinates": "xyz"});
    let graph = small_graph(&positions, &radii, &edges, &info);
    write_graph_arrays(&dir.path().join("g.swc"), &graph).unwrap();
    let swc = fs::read_to_string(dir.path().join("g.swc")).unwrap();
    assert!(swc.contains("x y z = array axes 2 1 0"), "{swc}");
    // Rooted at the widest node (1), which comes first.
    assert!(swc.ends_with("1 0 4.0 5.0 6.0 1.5 -1\n2 0 1.0 2.0 3.0 0.5 1\n"), "{swc}");
    let csv = dir.path().join("g.csv");
    assert_eq!(GraphFormat::Csv.outputs(&csv), [csv.clone(), dir.path().join("g.edges.csv")]);
    write_graph_arrays(&csv, &graph).unwrap();
    assert_eq!(fs::read_to_string(&csv).unwrap(), "id,x,y,z,r\r\n0,1.0,2.0,3.0,0.5\r\n1,4.0,5.0,6.0,1.5\r\n");
    assert_eq!(fs::read_to_string(dir.path().join("g.edges.csv")).unwrap(), "source,target\r\n0,1\r\n");
}

#[test]
fn replace_all_puts_everything_back_when_a_move_fails_part_way() {
    let dir = TempDir::new().unwrap();
    let p = |name: &str| -> PathBuf { dir.path().join(name) };
    fs::write(p("new1"), "new").unwrap();
    fs::write(p("t1"), "old").unwrap();
    // The second target is a folder (moved aside first); the second move fails, as
    // its staged file is missing.
    fs::create_dir(p("t2")).unwrap();
    fs::write(p("t2").join("keep"), "x").unwrap();
    let err = replace_all(&[p("new1"), p("new2")], &[p("t1"), p("t2")]).unwrap_err();
    assert!(err.to_string().contains("t2"), "{err}");
    assert_eq!(fs::read_to_string(p("t1")).unwrap(), "old");
    assert_eq!(fs::read_to_string(p("t2").join("keep")).unwrap(), "x");
    assert_eq!(fs::read_to_string(p("new1")).unwrap(), "new", "the staged file goes back to its owner");
    let mut names: Vec<String> =
        fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    names.sort();
    assert_eq!(names, ["new1", "t1", "t2"], "no backup is left behind");

    // And a folder target is replaced whole when everything succeeds.
    fs::create_dir(p("staged")).unwrap();
    fs::write(p("staged").join("info"), "new").unwrap();
    replace_all(&[p("staged")], &[p("t2")]).unwrap();
    assert_eq!(fs::read_to_string(p("t2").join("info")).unwrap(), "new");
    assert!(!p("t2").join("keep").exists() && !p("staged").exists());
}
