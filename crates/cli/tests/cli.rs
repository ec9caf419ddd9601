//! The `vesselflow` binary end to end: options generated from the parameters,
//! one-line errors with the documented exit codes, no output file on failure,
//! real runs writing every graph format, the demo summary, and interruption.

use ndarray_npy::{NpzReader, WriteNpyExt};
use std::fs::{self, File};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use tempfile::TempDir;
use vesselflow::{shapes, Params};
use vesselflow_io::serde_json::{self, Value};

fn vesselflow(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vesselflow")).args(args).output().unwrap()
}

fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// The process failed with `code` and said exactly one line, an error naming `needle`.
fn assert_error(out: &Output, code: i32, needle: &str) {
    let err = stderr(out);
    assert_eq!(out.status.code(), Some(code), "stderr: {err}");
    assert_eq!(err.lines().count(), 1, "one line expected: {err}");
    assert!(err.starts_with("vesselflow: error: "), "{err}");
    assert!(err.contains(needle), "{err:?} should name {needle:?}");
}

fn files_in(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> =
        fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    names.sort();
    names
}

/// A cylinder of radius 4 along axis 0 with its axis at (·, 10, 10), as `.npy`.
fn cylinder_npy(dir: &Path) -> PathBuf {
    let path = dir.join("tube.npy");
    shapes::cylinder([40, 21, 21], 4.0).write_npy(File::create(&path).unwrap()).unwrap();
    path
}

fn path_str(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn help_lists_every_parameter_with_its_default() {
    for sub in ["skeletonize", "demo"] {
        let out = vesselflow(&[sub, "--help"]);
        assert_eq!(out.status.code(), Some(0));
        let help = stdout(&out);
        for name in Params::NAMES {
            let option = format!("--{} <VALUE>", name.replace('_', "-"));
            let line = help.lines().find(|l| l.contains(&option)).unwrap_or_else(|| panic!("{option} missing"));
            assert!(line.contains("[default: "), "{line}");
        }
    }
    let help = stdout(&vesselflow(&["skeletonize", "--help"]));
    let line = |opt: &str| help.lines().find(|l| l.contains(opt)).unwrap().to_string();
    assert!(line("--gamma <VALUE>").contains("[default: 0.05]"));
    assert!(line("--medial-weight <VALUE>").contains("[default: radius]"));
    assert!(line("--reconnect-thin <VALUE>").contains("[default: true]"));
    assert!(help.contains("--spacing <A> <B> <C>"));
}

#[test]
fn bare_command_prints_help_and_fails_version_succeeds() {
    let out = vesselflow(&[]);
    assert_eq!(out.status.code(), Some(2));
    assert!(stderr(&out).contains("Usage: vesselflow"));
    let out = vesselflow(&["--version"]);
    assert_eq!(out.status.code(), Some(0));
    assert!(stdout(&out).starts_with("vesselflow "));
}

#[test]
fn unknown_parameter_is_a_usage_error_naming_it() {
    let dir = TempDir::new().unwrap();
    let input = cylinder_npy(dir.path());
    let output = dir.path().join("g.json");
    let out = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&output), "--gama", "0.1"]);
    assert_error(&out, 2, "--gama");
    assert!(stderr(&out).contains("--gamma"), "suggests the near miss");
    assert!(!output.exists());
}

#[test]
fn bad_parameter_value_is_a_usage_error_naming_the_parameter() {
    let dir = TempDir::new().unwrap();
    let input = cylinder_npy(dir.path());
    let output = dir.path().join("g.json");
    for (option, value, name) in [
        ("--gamma", "abc", "`gamma`"),
        ("--gamma", "-1", "`gamma`"),
        ("--connectivity", "7", "`connectivity`"),
        ("--medial-weight", "median", "`medial_weight`"),
        ("--reconnect-thin", "maybe", "`reconnect_thin`"),
        ("--max-iterations", "1.5", "`max_iterations`"),
    ] {
        let out = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&output), option, value]);
        assert_error(&out, 2, name);
    }
    let out = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&output), "--spacing", "1", "0", "1"]);
    assert_error(&out, 2, "spacing");
    let out = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&output), "--spacing", "1", "nan", "1"]);
    assert_error(&out, 2, "spacing");
    assert!(!output.exists());
}

#[test]
fn missing_input_is_an_io_error_naming_the_file() {
    let dir = TempDir::new().unwrap();
    let output = dir.path().join("g.json");
    let missing = dir.path().join("absent.npy");
    let out = vesselflow(&["skeletonize", path_str(&missing), "-o", path_str(&output)]);
    assert_error(&out, 1, "absent.npy");
    assert!(files_in(dir.path()).is_empty(), "no output, no temporary file");
}

#[test]
fn unreadable_input_content_is_an_io_error() {
    let dir = TempDir::new().unwrap();
    let input = dir.path().join("image.npy");
    ndarray::Array3::<f32>::from_elem((4, 4, 4), 0.5).write_npy(File::create(&input).unwrap()).unwrap();
    let output = dir.path().join("g.json");
    let out = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&output)]);
    assert_error(&out, 1, "float32 values other than 0 and 1 (e.g. 0.5)");
    assert!(stderr(&out).contains("--threshold T") && stderr(&out).contains("--label V"));
    assert!(!output.exists());
}

#[test]
fn unwritable_output_fails_before_the_run_and_leaves_no_file() {
    let dir = TempDir::new().unwrap();
    let input = cylinder_npy(dir.path());
    let missing_dir = dir.path().join("nowhere/g.json");
    let out = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&missing_dir)]);
    assert_error(&out, 1, "nowhere/g.json");
    // A regular file where a directory should be (fails for root too).
    fs::write(dir.path().join("plain"), "x").unwrap();
    let under_file = dir.path().join("plain/g.npz");
    let out = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&under_file)]);
    assert_error(&out, 1, "plain/g.npz");
    assert_eq!(files_in(dir.path()), ["plain", "tube.npy"]);
}

#[test]
fn unsupported_extensions_are_usage_errors() {
    let dir = TempDir::new().unwrap();
    let input = cylinder_npy(dir.path());
    let out = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&dir.path().join("g.tsv"))]);
    assert_error(&out, 2, "g.tsv");
    assert!(stderr(&out).contains(".graphml, .json, .npz, .swc, .vtp, .csv or .precomputed"));
    let mha = dir.path().join("mask.mha");
    fs::write(&mha, b"ObjectType = Image\n").unwrap();
    let out = vesselflow(&["skeletonize", path_str(&mha), "-o", path_str(&dir.path().join("g.json"))]);
    assert_error(&out, 2, "mask.mha");
    assert!(stderr(&out).contains("vesselflow.load_volume"));
    assert_eq!(files_in(dir.path()), ["mask.mha", "tube.npy"]);
}

#[test]
fn failed_run_keeps_an_existing_output_untouched() {
    let dir = TempDir::new().unwrap();
    let output = dir.path().join("g.json");
    fs::write(&output, "previous result").unwrap();
    let out = vesselflow(&["skeletonize", path_str(&dir.path().join("absent.npy")), "-o", path_str(&output)]);
    assert_eq!(out.status.code(), Some(1));
    assert_eq!(fs::read_to_string(&output).unwrap(), "previous result");
}

/// Degrees of a graph given as an edge list.
fn degrees(n: usize, edges: &[[usize; 2]]) -> Vec<usize> {
    let mut d = vec![0; n];
    for &[a, b] in edges {
        d[a] += 1;
        d[b] += 1;
    }
    d
}

#[test]
fn skeletonize_a_cylinder_into_every_format() {
    let dir = TempDir::new().unwrap();
    let input = cylinder_npy(dir.path());

    let json = dir.path().join("tube.json");
    let out = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&json), "--gamma", "0.05"]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let doc: Value = serde_json::from_reader(File::open(&json).unwrap()).unwrap();
    assert_eq!(doc["format"], "vesselflow-graph");
    assert_eq!(doc["spacing"], serde_json::json!([1.0, 1.0, 1.0]));
    let positions: Vec<[f64; 3]> = serde_json::from_value(doc["positions"].clone()).unwrap();
    let edges: Vec<[usize; 2]> = serde_json::from_value(doc["edges"].clone()).unwrap();
    let n = positions.len();
    assert!(n >= 5, "a path along the tube, got {n} nodes");
    assert_eq!(edges.len(), n - 1, "a tree with one component: a path");
    assert!(degrees(n, &edges).iter().all(|&d| d == 1 || d == 2), "a path has no junction");
    for p in &positions {
        // Axis 0 runs along the tube; axes 1 and 2 sit on its axis at 10.
        assert!((p[1] - 10.0).abs() < 1.0 && (p[2] - 10.0).abs() < 1.0, "off axis: {p:?}");
    }
    let extent = positions.iter().map(|p| p[0]).fold(f64::NEG_INFINITY, f64::max)
        - positions.iter().map(|p| p[0]).fold(f64::INFINITY, f64::min);
    assert!(extent > 25.0, "spans the tube: {extent}");
    assert_eq!(doc["params"]["gamma"], 0.05);
    assert_eq!(doc["info"]["foreground_voxels"].as_u64().unwrap() as usize, {
        let m = shapes::cylinder([40, 21, 21], 4.0);
        m.iter().filter(|&&v| v != 0).count()
    });

    let npz = dir.path().join("tube.npz");
    let out = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&npz), "-q"]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let mut reader = NpzReader::new(File::open(&npz).unwrap()).unwrap();
    let npz_positions: ndarray::Array2<f64> = reader.by_name("positions").unwrap();
    assert_eq!(npz_positions.nrows(), n, "same run, same graph");

    let graphml = dir.path().join("tube.graphml");
    let out = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&graphml), "-q"]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let text = fs::read_to_string(&graphml).unwrap();
    assert_eq!(text.matches("<node id=").count(), n);
    assert_eq!(text.matches("<edge ").count(), n - 1);
}

#[test]
fn spacing_option_scales_the_physical_graph() {
    let dir = TempDir::new().unwrap();
    let input = cylinder_npy(dir.path());
    let json = dir.path().join("tube.json");
    let out = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&json), "--spacing", "2", "1", "1", "-q"]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let doc: Value = serde_json::from_reader(File::open(&json).unwrap()).unwrap();
    assert_eq!(doc["spacing"], serde_json::json!([2.0, 1.0, 1.0]));
    let positions: Vec<[f64; 3]> = serde_json::from_value(doc["positions"].clone()).unwrap();
    let max0 = positions.iter().map(|p| p[0]).fold(f64::NEG_INFINITY, f64::max);
    assert!(max0 > 45.0, "axis 0 is in physical units (2 per voxel): max {max0}");
    assert!(positions.iter().all(|p| (p[1] - 10.0).abs() < 1.0 && (p[2] - 10.0).abs() < 1.0));
}

#[test]
fn stderr_reports_stages_and_timings_unless_quiet() {
    let dir = TempDir::new().unwrap();
    let input = cylinder_npy(dir.path());
    let json = dir.path().join("tube.json");
    let args = ["skeletonize", path_str(&input), "-o", path_str(&json)];

    let out = vesselflow(&args);
    assert_eq!(out.status.code(), Some(0));
    let err = stderr(&out);
    // Not a terminal: one line per stage, then the timings.
    for stage in ["edt:", "grid:", "contract:", "refine:", "output:"] {
        assert_eq!(err.lines().filter(|l| l.starts_with(stage)).count(), 1, "{stage} in {err}");
    }
    assert!(err.lines().any(|l| l.starts_with("total ")), "{err}");
    assert!(err.contains("wrote") && !err.contains("cg iterations"), "{err}");
    assert!(stdout(&out).is_empty());

    let verbose = stderr(&vesselflow(&[&args[..], &["-v"]].concat()));
    assert!(verbose.contains("cg iterations"), "{verbose}");
    let iterations = serde_json::from_reader::<_, Value>(File::open(&json).unwrap()).unwrap()["info"]["iterations"]
        .as_u64()
        .unwrap();
    let table_rows = verbose
        .lines()
        .skip_while(|l| !l.contains("cg iterations"))
        .skip(1)
        .take_while(|l| l.trim_start().starts_with(|c: char| c.is_ascii_digit()))
        .count();
    assert_eq!(table_rows as u64, iterations + 1, "one row per iteration plus the initial graph");

    let quiet = vesselflow(&[&args[..], &["--quiet"]].concat());
    assert_eq!(quiet.status.code(), Some(0));
    assert!(stderr(&quiet).is_empty(), "{}", stderr(&quiet));
}

#[test]
fn a_run_stopped_at_the_cap_says_so_even_when_quiet() {
    let dir = TempDir::new().unwrap();
    let input = cylinder_npy(dir.path());
    let json = dir.path().join("tube.json");
    let capped = ["skeletonize", path_str(&input), "-o", path_str(&json), "--max-iterations", "1", "-q"];
    let out = vesselflow(&capped);
    assert_eq!(out.status.code(), Some(0));
    let doc: Value = serde_json::from_reader(File::open(&json).unwrap()).unwrap();
    assert_eq!(doc["info"]["converged"], Value::Bool(false), "one iteration cannot converge this tube");
    let err = stderr(&out);
    assert!(err.contains("warning: the contraction stopped at --max-iterations 1 before converging"), "{err}");
    // A converged run says nothing under --quiet.
    let full = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&json), "-q"]);
    assert!(stderr(&full).is_empty(), "{}", stderr(&full));
}

#[test]
fn max_memory_also_bounds_what_the_reader_may_allocate() {
    let dir = TempDir::new().unwrap();
    let input = cylinder_npy(dir.path()); // 40 x 21 x 21 = 17 640 voxels
    let json = dir.path().join("tube.json");
    let out = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&json), "--max-memory", "10KB", "-q"]);
    assert_error(&out, 1, "may be used");
    assert!(!json.exists());
}

#[test]
fn demo_prints_the_summary() {
    let dir = TempDir::new().unwrap();
    let output = dir.path().join("demo.graphml");
    let out = vesselflow(&["demo", "-o", path_str(&output), "-q"]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let text = stdout(&out);
    let field = |name: &str| -> String {
        let line = text.lines().find(|l| l.starts_with(name)).unwrap_or_else(|| panic!("{name} missing in {text}"));
        line[name.len()..].trim().to_string()
    };
    let count = |name: &str| field(name).parse::<usize>().unwrap();
    let (nodes, edges, components, cycles) =
        (count("nodes"), count("edges"), count("components"), count("independent cycles"));
    assert!(count("foreground voxels") > nodes && nodes > 10);
    assert_eq!(cycles + nodes, edges + components, "cycles = E - N + components");
    // The built-in volume is one tree of tubes with one loop.
    assert_eq!((components, cycles), (1, 1), "{text}");
    assert!(count("junctions") >= 2 && count("endpoints") >= 2, "{text}");
    assert!(field("iterations").contains("converged"));
    assert!(field("seconds").parse::<f64>().unwrap() > 0.0);
    assert_eq!(fs::read_to_string(&output).unwrap().matches("<node id=").count(), nodes);
}

#[test]
fn embedded_entry_stops_when_asked_and_writes_nothing() {
    let dir = TempDir::new().unwrap();
    let input = cylinder_npy(dir.path());
    let output = dir.path().join("g.json");
    let args = ["vesselflow", "skeletonize", path_str(&input), "-o", path_str(&output), "-q"];

    // Asked before anything runs.
    let stop = vesselflow::Stop::new();
    stop.request();
    assert_eq!(vesselflow_cli::run_with(args, &stop), vesselflow_cli::EXIT_INTERRUPTED);
    // Asked from another thread in the middle of the contraction.
    let stop = vesselflow::Stop::new();
    let code = std::thread::scope(|scope| {
        let asker = stop.clone();
        scope.spawn(move || {
            while asker.cg_iterations() < 3 {
                std::thread::yield_now();
            }
            asker.request();
        });
        vesselflow_cli::run_with(args, &stop)
    });
    assert_eq!(code, vesselflow_cli::EXIT_INTERRUPTED);
    assert_eq!(files_in(dir.path()), ["tube.npy"]);
    // Never asked: runs to completion.
    assert_eq!(vesselflow_cli::run_with(args, &vesselflow::Stop::new()), 0);
    assert!(output.exists());
    assert_eq!(files_in(dir.path()), ["g.json", "tube.npy"]);
}

#[cfg(unix)]
#[test]
fn sigint_stops_the_binary_with_130_and_no_output() {
    use std::io::{BufRead, BufReader};
    let dir = TempDir::new().unwrap();
    // Long enough that the contraction is still running when the signal lands, even
    // on a loaded machine where the handler's thread waits to be scheduled (a 600-voxel
    // tube ran to completion, 0.7 s, before it did under CI's parallel tests).
    let input = dir.path().join("long.npy");
    shapes::cylinder([2400, 31, 31], 8.0).write_npy(File::create(&input).unwrap()).unwrap();
    let output = dir.path().join("g.json");
    let mut child = Command::new(env!("CARGO_BIN_EXE_vesselflow"))
        .args(["skeletonize", path_str(&input), "-o", path_str(&output)])
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stderr.take().unwrap()).lines();
    // The "edt:" line is printed when the grid stage reports, i.e. the run is under way.
    for line in lines.by_ref() {
        if line.unwrap().starts_with("edt:") {
            break;
        }
    }
    let kill = Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap();
    assert!(kill.success());
    let rest: Vec<String> = lines.map(Result::unwrap).collect();
    let status = child.wait().unwrap();
    assert_eq!(status.code(), Some(130), "{rest:?}");
    assert!(rest.iter().any(|l| l == "vesselflow: error: interrupted; no output written"), "{rest:?}");
    assert_eq!(files_in(dir.path()), ["long.npy"]);
}

/// A cylinder of radius 4 along axis 2 (40 voxels) with its axis at (10, 10, ·), as `.npy`:
/// unlike [`cylinder_npy`], it lies in the plane of the `--plot` projection.
fn across_tube_npy(dir: &Path) -> PathBuf {
    across_tube_of_length(dir, 40)
}

/// [`across_tube_npy`] `length` voxels long, as `across.npy` (40) or `across-LENGTH.npy`.
fn across_tube_of_length(dir: &Path, length: usize) -> PathBuf {
    let path = dir.join(if length == 40 { "across.npy".to_string() } else { format!("across-{length}.npy") });
    let tube = shapes::cylinder([length, 21, 21], 4.0).permuted_axes([1, 2, 0]).as_standard_layout().to_owned();
    assert_eq!(tube.shape(), [21, 21, length]);
    tube.write_npy(File::create(&path).unwrap()).unwrap();
    path
}

fn is_grey(p: &image::Rgb<u8>) -> bool {
    p[0] == p[1] && p[1] == p[2]
}

#[test]
fn plot_draws_the_centreline_in_colour_over_the_grey_projection() {
    let dir = TempDir::new().unwrap();
    let input = across_tube_npy(dir.path());
    let (json, png) = (dir.path().join("g.json"), dir.path().join("tube.png"));
    let out = vesselflow(&[
        "skeletonize",
        path_str(&input),
        "-o",
        path_str(&json),
        "--spacing",
        "1",
        "2",
        "1",
        "--plot",
        path_str(&png),
    ]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let err = stderr(&out);
    let line = err.lines().find(|l| l.contains("tube.png")).unwrap_or_else(|| panic!("no plot line in {err}"));
    assert!(line.contains("colour bar: edge radius"), "{line}");
    let image = image::open(&png).unwrap().to_rgb8();

    // Axis 1: 21 voxels of 2 = 42 units, the long side (600 px, the least a picture
    // has); axis 2: 40 voxels of 1 = 40 units, 571 px; the colour bar, its ticks and
    // its label are to the right of the projection.
    let map_width = (40.0_f64 * 600.0 / 42.0).round() as u32;
    assert_eq!(image.height(), 600);
    assert!(image.width() > map_width + 60 && image.width() < map_width + 200, "{:?}", image.dimensions());
    // The tube is 9 voxels (18 units) thick across the 40 units of its length.
    let tube_rows =
        (0..image.height()).filter(|&y| image.get_pixel(map_width / 2, y) != &image::Rgb([0, 0, 0])).count();
    let ratio = tube_rows as f64 / f64::from(map_width);
    assert!((ratio - 18.0 / 40.0).abs() < 0.03, "physical aspect: {tube_rows} rows over {map_width} px = {ratio}");

    // The centreline, voxel row 10 of axis 1, is at pixel row 10.5 * 600 / 21 = 300.
    let doc: Value = serde_json::from_reader(File::open(&json).unwrap()).unwrap();
    let positions: Vec<[f64; 3]> = serde_json::from_value(doc["positions"].clone()).unwrap();
    let min2 = positions.iter().map(|p| p[2]).fold(f64::INFINITY, f64::min);
    let max2 = positions.iter().map(|p| p[2]).fold(f64::NEG_INFINITY, f64::max);
    let px_per_unit = f64::from(map_width) / 40.0;
    let (x0, x1) = (((min2 + 1.0) * px_per_unit) as u32, (max2 * px_per_unit) as u32);
    assert!(x1 > x0 + 300, "the graph spans the tube: {min2}..{max2}");
    for x in x0..x1 {
        // Within 0.2 voxel (6 px) of the axis.
        assert!((294..=306).any(|y| !is_grey(image.get_pixel(x, y))), "no coloured pixel at column {x}");
    }
    for (x, y, p) in image.enumerate_pixels() {
        if x < map_width && !(288..=312).contains(&y) {
            assert!(is_grey(p), "coloured pixel {p:?} off the centreline at ({x}, {y})");
        }
    }
    assert!(image.enumerate_pixels().any(|(x, _, p)| x < map_width && p[0] > 0 && is_grey(p)), "grey foreground");
}

#[test]
fn demo_writes_a_plot_and_says_what_the_colour_bar_spans() {
    let dir = TempDir::new().unwrap();
    let png = dir.path().join("demo.png");
    let out = vesselflow(&["demo", "--plot", path_str(&png)]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    assert!(stderr(&out).contains("colour bar: edge radius"), "{}", stderr(&out));
    // Demo volume 48 x 112 x 96, isotropic: 112 rows are the long side, 4 px per voxel
    // is less than the least a picture has (600 px).
    let image = image::open(&png).unwrap().to_rgb8();
    assert_eq!(image.height(), 600);
    assert!(image.width() > 514 + 60, "{:?}", image.dimensions());
    assert!(image.pixels().filter(|p| !is_grey(p)).count() > 1000, "edges and colour bar");

    let quiet = vesselflow(&["demo", "--plot", path_str(&png), "-q"]);
    assert_eq!(quiet.status.code(), Some(0));
    assert!(stderr(&quiet).is_empty(), "{}", stderr(&quiet));
}

/// The number of coloured (graph) pixels in column `x` of the projection.
fn coloured_rows(image: &image::RgbImage, x: u32) -> usize {
    (0..image.height()).filter(|&y| !is_grey(image.get_pixel(x, y))).count()
}

#[test]
fn plot_size_and_line_width_grow_with_the_volume() {
    let dir = TempDir::new().unwrap();
    let picture = |length: usize| {
        let input = across_tube_of_length(dir.path(), length);
        let png = dir.path().join(format!("tube-{length}.png"));
        let out = vesselflow(&[
            "skeletonize",
            path_str(&input),
            "-o",
            path_str(&dir.path().join("g.json")),
            "--plot",
            path_str(&png),
            "-q",
        ]);
        assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
        image::open(&png).unwrap().to_rgb8()
    };
    // 40 voxels along the picture: 600 px (the least); 300 voxels: 4 px each, 1200 px.
    let (short, long) = (picture(40), picture(300));
    let (short_map, long_map) = (600, 1200);
    assert!(short.width() > short_map && short.width() < short_map + 200, "{:?}", short.dimensions());
    assert!(long.width() > long_map && long.width() < long_map + 300, "{:?}", long.dimensions());
    // Lines are 1/300 of the picture's longer side: 2 px and 4 px wide (plus a pixel of
    // anti-aliasing), across the middle of the tube's centreline.
    let (thin, thick) = (coloured_rows(&short, short_map / 2), coloured_rows(&long, long_map / 2));
    assert!((2..=4).contains(&thin) && thick > thin, "{thin} and {thick} coloured rows");
}

#[test]
fn plot_path_must_be_png_and_writable() {
    let dir = TempDir::new().unwrap();
    let input = cylinder_npy(dir.path());
    let output = dir.path().join("g.json");
    for bad in ["plot.jpg", "plot", "plot.png.txt"] {
        let plot = dir.path().join(bad);
        let out = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&output), "--plot", path_str(&plot)]);
        assert_error(&out, 2, bad);
        assert!(stderr(&out).contains(".png"));
    }
    let out = vesselflow(&["demo", "--plot", path_str(&dir.path().join("demo.svg"))]);
    assert_error(&out, 2, "demo.svg");

    let missing_dir = dir.path().join("nowhere/plot.png");
    let out = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&output), "--plot", path_str(&missing_dir)]);
    assert_error(&out, 1, "nowhere/plot.png");
    fs::write(dir.path().join("plain"), "x").unwrap();
    let under_file = dir.path().join("plain/plot.png");
    let out = vesselflow(&["demo", "--plot", path_str(&under_file)]);
    assert_error(&out, 1, "plain/plot.png");
    fs::create_dir(dir.path().join("taken.png")).unwrap();
    let out = vesselflow(&["demo", "--plot", path_str(&dir.path().join("taken.png")), "-q"]);
    assert_error(&out, 1, "taken.png");
    assert_eq!(files_in(dir.path()), ["plain", "taken.png", "tube.npy"]);
    assert!(files_in(&dir.path().join("taken.png")).is_empty());
}

/// The binary with extra environment variables.
fn vesselflow_env(args: &[&str], env: &[(&str, &str)]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vesselflow")).args(args).envs(env.iter().copied()).output().unwrap()
}

#[test]
fn a_panic_is_one_line_internal_error_without_backtrace_or_output() {
    let dir = TempDir::new().unwrap();
    let input = cylinder_npy(dir.path());
    let output = dir.path().join("g.json");
    for stage in ["edt", "contract", "output"] {
        let out = vesselflow_env(
            &["skeletonize", path_str(&input), "-o", path_str(&output), "-q"],
            &[("VESSELFLOW_DEBUG_PANIC", stage), ("RUST_BACKTRACE", "1")],
        );
        assert_error(&out, 1, "internal error, please report: VESSELFLOW_DEBUG_PANIC: forced panic");
        let err = stderr(&out);
        assert!(err.contains(&format!("stage `{stage}`")) && err.contains("spacing [1.0, 1.0, 1.0]"), "{err}");
        assert!(err.contains("shape 40 x 21 x 21"), "{err}");
        assert!(!err.contains("panicked") && !err.contains("backtrace"), "{err}");
        assert_eq!(files_in(dir.path()), ["tube.npy"]);
    }
}

#[test]
fn a_failing_plot_leaves_neither_the_graph_nor_temporary_files() {
    let dir = TempDir::new().unwrap();
    let input = across_tube_npy(dir.path());
    let (output, png) = (dir.path().join("g.json"), dir.path().join("p.png"));
    fs::write(&output, "previous graph").unwrap();
    fs::write(&png, "previous plot").unwrap();
    let args = ["skeletonize", path_str(&input), "-o", path_str(&output), "--plot", path_str(&png), "-q"];
    let out = vesselflow_env(&args, &[("VESSELFLOW_DEBUG_PANIC", "plot")]);
    assert_error(&out, 1, "stage `plot`");
    assert_eq!(fs::read_to_string(&output).unwrap(), "previous graph");
    assert_eq!(fs::read_to_string(&png).unwrap(), "previous plot");
    assert_eq!(files_in(dir.path()), ["across.npy", "g.json", "p.png"]);
    // Without the failure both are replaced, and no temporary file is left.
    let out = vesselflow(&args);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    assert!(fs::read_to_string(&output).unwrap().contains("positions"));
    assert!(image::open(&png).is_ok());
    assert_eq!(files_in(dir.path()), ["across.npy", "g.json", "p.png"]);
}

#[test]
fn an_empty_mask_warns_and_an_all_vessel_block_gets_its_graph() {
    let dir = TempDir::new().unwrap();
    let empty = dir.path().join("empty.npy");
    ndarray::Array3::<u8>::zeros((6, 7, 8)).write_npy(File::create(&empty).unwrap()).unwrap();
    let output = dir.path().join("g.json");
    let out = vesselflow(&["skeletonize", path_str(&empty), "-o", path_str(&output), "-q"]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    assert_eq!(stderr(&out), "vesselflow: warning: the mask is empty: the graph has no nodes\n");
    let graph: Value = serde_json::from_str(&fs::read_to_string(&output).unwrap()).unwrap();
    assert_eq!(graph["positions"].as_array().map(Vec::len), Some(0), "{graph}");

    let block = dir.path().join("block.npy");
    ndarray::Array3::<u8>::ones((20, 8, 8)).write_npy(File::create(&block).unwrap()).unwrap();
    let out = vesselflow(&["skeletonize", path_str(&block), "-o", path_str(&output), "-q"]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    assert!(stderr(&out).is_empty(), "{}", stderr(&out));
    let graph: Value = serde_json::from_str(&fs::read_to_string(&output).unwrap()).unwrap();
    assert!(graph["positions"].as_array().is_some_and(|p| !p.is_empty()), "{graph}");
}

/// Start the binary on `input` writing `output`, and return it once the run is done
/// and the write is about to begin (the timing table's last line is printed then).
#[cfg(unix)]
fn spawn_until_written(input: &Path, output: &Path, extra: &[&str]) -> std::process::Child {
    use std::io::{BufRead, BufReader};
    let mut child = Command::new(env!("CARGO_BIN_EXE_vesselflow"))
        .args(["skeletonize", path_str(input), "-o", path_str(output)])
        .args(extra)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stderr.take().unwrap()).lines();
    for line in lines.by_ref() {
        if line.unwrap().starts_with("total") {
            break;
        }
    }
    // Keep draining stderr so that the child never blocks on a full pipe.
    std::thread::spawn(move || lines.for_each(drop));
    child
}

#[cfg(unix)]
fn signal(child: &std::process::Child, name: &str) {
    let kill = Command::new("kill").args([name, &child.id().to_string()]).status().unwrap();
    assert!(kill.success());
}

/// A solid block whose grid graph (no contraction) is large: writing it as GraphML
/// takes a good part of a second, so signals land during the write.
#[cfg(unix)]
fn big_graph_input(dir: &Path) -> (PathBuf, [&'static str; 4]) {
    let input = dir.join("block.npy");
    ndarray::Array3::<u8>::ones((64, 64, 64)).write_npy(File::create(&input).unwrap()).unwrap();
    (input, ["--max-iterations", "0", "--max-refine-iterations", "0"])
}

#[cfg(unix)]
#[test]
fn sigterm_during_the_write_exits_130_and_keeps_the_previous_file() {
    let dir = TempDir::new().unwrap();
    let (input, extra) = big_graph_input(dir.path());
    let output = dir.path().join("g.graphml");
    fs::write(&output, "previous result").unwrap();
    let child = spawn_until_written(&input, &output, &extra);
    signal(&child, "-TERM");
    let status = child.wait_with_output().unwrap().status;
    assert_eq!(status.code(), Some(130));
    assert_eq!(fs::read_to_string(&output).unwrap(), "previous result");
    assert_eq!(files_in(dir.path()), ["block.npy", "g.graphml"]);
}

#[cfg(unix)]
#[test]
fn two_sigterms_during_the_write_leave_no_temporary_file() {
    let dir = TempDir::new().unwrap();
    let (input, extra) = big_graph_input(dir.path());
    let output = dir.path().join("g.graphml");
    let child = spawn_until_written(&input, &output, &extra);
    signal(&child, "-TERM");
    signal(&child, "-TERM");
    let status = child.wait_with_output().unwrap().status;
    assert_eq!(status.code(), Some(130));
    assert_eq!(files_in(dir.path()), ["block.npy"]);
}

#[test]
fn a_run_over_max_memory_is_refused_in_one_line_naming_both_numbers() {
    let dir = TempDir::new().unwrap();
    let input = cylinder_npy(dir.path());
    let output = dir.path().join("g.json");
    // Enough to read the 17 640-voxel mask, not to run on it.
    let out = vesselflow(&["-q", "skeletonize", path_str(&input), "-o", path_str(&output), "--max-memory", "100KB"]);
    assert_error(&out, 1, "max_memory allows 97.7 KiB (100000 bytes)");
    assert!(stderr(&out).contains("needs about"), "{}", stderr(&out));
    assert!(!output.exists());
    // A generous limit changes nothing; the file records the limit asked for.
    let out = vesselflow(&["-q", "skeletonize", path_str(&input), "-o", path_str(&output), "--max-memory", "64GiB"]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let bad = vesselflow(&["skeletonize", path_str(&input), "-o", path_str(&output), "--max-memory", "lots"]);
    assert_error(&bad, 2, "max_memory");
}
