//! Graph writers: each format read back by an independent parser (serde_json,
//! ndarray-npy, quick-xml) must give exactly the graph, spacing and metadata
//! written; bad paths and bad arrays give errors and leave no file.

use ndarray::{array, Array1, Array2, Ix1, Ix2, OwnedRepr};
use ndarray_npy::NpzReader;
use serde_json::Value;
use std::collections::BTreeMap;
use std::fs::{self, File};
use std::path::Path;
use tempfile::TempDir;
use vesselflow::{Params, RunInfo, Skeleton, StageTime};
use vesselflow_io::{
    check_graph_output, params_json, run_info_json, write_graph, write_graph_arrays, GraphArrays, GraphFormat, IoError,
};

/// Four nodes (a triangle and a pendant) with floats that only survive an exact
/// round trip: thirds, tiny and huge magnitudes, negative zero.
fn skeleton() -> Skeleton {
    Skeleton {
        positions: vec![
            [0.1, 1.0 / 3.0, 2.0],
            [1e-300, -2.5e10, 7.0],
            [-0.0, 4.000000000000001, 123456.789],
            [5.5, 6.25, f64::MIN_POSITIVE],
        ],
        radii: vec![0.5, 1.0 / 7.0, 2.0, 3.5],
        edges: vec![[0, 1], [0, 2], [1, 2], [2, 3]],
        spacing: [0.5, 1.0, 2.0],
        info: RunInfo {
            foreground_voxels: 1234,
            mask_components: 1,
            iterations: 3,
            converged: true,
            stalled: false,
            refine_iterations: 2,
            refine_converged: false,
            nodes_per_iteration: vec![1234, 400, 50, 4],
            area_per_iteration: vec![10.5, 0.25, 1e-4],
            area_reference: 1234.0,
            cg_iterations: vec![31, 20, 12],
            cg_unconverged: 0,
            sprouts: 3,
            pruned_spurs: 2,
            stage_seconds: vec![
                StageTime { stage: "edt", seconds: 0.01 },
                StageTime { stage: "grid", seconds: 0.02 },
                StageTime { stage: "contract", seconds: 1.5 },
            ],
        },
    }
}

fn params() -> Params {
    Params::from_pairs([("gamma", vesselflow::Value::Float(0.07)), ("max_iterations", vesselflow::Value::Int(7))])
        .unwrap()
}

/// Files in `dir` (to check that nothing, not even a temporary file, is left).
fn listing(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> =
        fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    names.sort();
    names
}

fn check_info(info: &Value, expected: &RunInfo) {
    assert_eq!(info["foreground_voxels"], 1234);
    assert_eq!(info["mask_components"], 1);
    assert_eq!(info["iterations"], 3);
    assert_eq!(info["converged"], true);
    assert_eq!(info["stalled"], false);
    assert_eq!(info["refine_iterations"], 2);
    assert_eq!(info["refine_converged"], false);
    assert_eq!(info["nodes_per_iteration"], serde_json::json!(expected.nodes_per_iteration));
    assert_eq!(info["area_per_iteration"], serde_json::json!(expected.area_per_iteration));
    assert_eq!(info["area_reference"], 1234.0);
    assert_eq!(info["cg_iterations"], serde_json::json!([31, 20, 12]));
    assert_eq!(info["cg_unconverged"], 0);
    assert_eq!(info["sprouts"], 3);
    assert_eq!(info["pruned_spurs"], 2);
    let stages: Vec<(&String, f64)> =
        info["stage_seconds"].as_object().unwrap().iter().map(|(k, v)| (k, v.as_f64().unwrap())).collect();
    let want: Vec<(String, f64)> = expected.stage_seconds.iter().map(|t| (t.stage.to_string(), t.seconds)).collect();
    assert_eq!(stages.len(), want.len());
    for ((k, v), (wk, wv)) in stages.iter().zip(&want) {
        assert_eq!((k.as_str(), *v), (wk.as_str(), *wv), "stage order and values");
    }
    assert_eq!(info.as_object().unwrap().len(), 15, "every RunInfo field, nothing else");
}

fn check_params(params: &Value) {
    let map = params.as_object().unwrap();
    assert_eq!(map.keys().map(String::as_str).collect::<Vec<_>>(), Params::NAMES.to_vec());
    assert_eq!(params["gamma"], 0.07);
    assert_eq!(params["max_iterations"], 7);
    assert_eq!(params["medial_weight"], "radius");
    assert_eq!(params["reconnect_thin"], true);
    assert_eq!(params["connectivity"], 6);
}

#[test]
fn json_round_trip_is_exact() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("g.json");
    let skel = skeleton();
    write_graph(&path, &skel, &params()).unwrap();
    let doc: Value = serde_json::from_reader(File::open(&path).unwrap()).unwrap();

    assert_eq!(doc["format"], "vesselflow-graph");
    assert_eq!(doc["version"], 1);
    assert_eq!(doc["spacing"], serde_json::json!([0.5, 1.0, 2.0]));
    let positions: Vec<[f64; 3]> = serde_json::from_value(doc["positions"].clone()).unwrap();
    assert_eq!(positions.len(), 4);
    for (got, want) in positions.iter().zip(&skel.positions) {
        for (g, w) in got.iter().zip(want) {
            assert_eq!(g.to_bits(), w.to_bits(), "bit-exact float round trip");
        }
    }
    let radii: Vec<f64> = serde_json::from_value(doc["radii"].clone()).unwrap();
    assert_eq!(radii, skel.radii);
    let edges: Vec<[usize; 2]> = serde_json::from_value(doc["edges"].clone()).unwrap();
    assert_eq!(edges, skel.edges);
    check_info(&doc["info"], &skel.info);
    check_params(&doc["params"]);
    let keys: Vec<&str> = doc.as_object().unwrap().keys().map(String::as_str).collect();
    assert_eq!(keys, ["format", "version", "spacing", "positions", "radii", "edges", "info", "params"]);
    assert_eq!(listing(dir.path()), ["g.json"]);
}

#[test]
fn npz_round_trip_with_contract_dtypes() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("g.npz");
    let skel = skeleton();
    write_graph(&path, &skel, &params()).unwrap();

    let mut npz = NpzReader::new(File::open(&path).unwrap()).unwrap();
    let mut names = npz.names().unwrap();
    names.sort();
    assert_eq!(names, ["edges", "metadata", "positions", "radii", "spacing"]);
    // Reading with a given element type fails unless the stored dtype is exactly it.
    let positions: Array2<f64> = npz.by_name::<OwnedRepr<f64>, Ix2>("positions").unwrap();
    let want = Array2::from_shape_vec((4, 3), skel.positions.as_flattened().to_vec()).unwrap();
    assert_eq!(positions.mapv(f64::to_bits), want.mapv(f64::to_bits));
    let radii: Array1<f64> = npz.by_name::<OwnedRepr<f64>, Ix1>("radii").unwrap();
    assert_eq!(radii.to_vec(), skel.radii);
    let edges: Array2<i64> = npz.by_name::<OwnedRepr<i64>, Ix2>("edges").unwrap();
    assert_eq!(edges, array![[0i64, 1], [0, 2], [1, 2], [2, 3]]);
    let spacing: Array1<f64> = npz.by_name::<OwnedRepr<f64>, Ix1>("spacing").unwrap();
    assert_eq!(spacing.to_vec(), vec![0.5, 1.0, 2.0]);
    let metadata: Array1<u8> = npz.by_name::<OwnedRepr<u8>, Ix1>("metadata").unwrap();
    let metadata: Value = serde_json::from_slice(metadata.as_slice().unwrap()).unwrap();
    assert_eq!(metadata["format"], "vesselflow-graph");
    assert_eq!(metadata["version"], 1);
    check_info(&metadata["info"], &skel.info);
    check_params(&metadata["params"]);
    assert_eq!(metadata.as_object().unwrap().len(), 4);
}

/// A GraphML file parsed with a real XML parser.
#[derive(Default)]
struct ParsedGraphMl {
    /// key id -> (for, attr.name, attr.type)
    keys: BTreeMap<String, (String, String, String)>,
    edgedefault: String,
    graph_data: BTreeMap<String, String>,
    /// node id -> key -> text
    nodes: Vec<(String, BTreeMap<String, String>)>,
    edges: Vec<(String, String)>,
}

fn parse_graphml(path: &Path) -> ParsedGraphMl {
    use quick_xml::events::Event;
    let text = fs::read_to_string(path).unwrap();
    let mut reader = quick_xml::Reader::from_str(&text);
    let mut out = ParsedGraphMl::default();
    let mut data_key: Option<String> = None;
    let attr = |e: &quick_xml::events::BytesStart, name: &str| -> String {
        e.try_get_attribute(name).unwrap().map(|a| a.unescape_value().unwrap().into_owned()).unwrap_or_default()
    };
    loop {
        match reader.read_event().unwrap() {
            Event::Start(e) | Event::Empty(e) => match e.name().as_ref() {
                b"graphml" => assert_eq!(attr(&e, "xmlns"), "http://graphml.graphdrawing.org/xmlns"),
                b"key" => {
                    let v = (attr(&e, "for"), attr(&e, "attr.name"), attr(&e, "attr.type"));
                    out.keys.insert(attr(&e, "id"), v);
                }
                b"graph" => out.edgedefault = attr(&e, "edgedefault"),
                b"node" => out.nodes.push((attr(&e, "id"), BTreeMap::new())),
                b"edge" => out.edges.push((attr(&e, "source"), attr(&e, "target"))),
                b"data" => data_key = Some(attr(&e, "key")),
                other => panic!("unexpected element {}", String::from_utf8_lossy(other)),
            },
            Event::Text(t) => {
                if let Some(key) = data_key.take() {
                    let value = t.unescape().unwrap().into_owned();
                    match out.nodes.last_mut() {
                        Some((_, data)) => data.insert(key, value),
                        None => out.graph_data.insert(key, value),
                    };
                }
            }
            Event::Eof => break,
            _ => {}
        }
    }
    out
}

#[test]
fn graphml_round_trip_is_exact() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("g.graphml");
    let skel = skeleton();
    write_graph(&path, &skel, &params()).unwrap();
    let g = parse_graphml(&path);

    let double = |scope: &str, name: &str| (scope.to_string(), name.to_string(), "double".to_string());
    for (id, scope) in [
        ("spacing0", "graph"),
        ("spacing1", "graph"),
        ("spacing2", "graph"),
        ("x", "node"),
        ("y", "node"),
        ("z", "node"),
        ("r", "node"),
    ] {
        assert_eq!(g.keys[id], double(scope, id));
    }
    assert_eq!(g.keys.len(), 7);
    assert_eq!(g.edgedefault, "undirected");
    let spacing: Vec<f64> = (0..3).map(|i| g.graph_data[&format!("spacing{i}")].parse().unwrap()).collect();
    assert_eq!(spacing, skel.spacing);

    assert_eq!(g.nodes.len(), 4);
    for (i, (id, data)) in g.nodes.iter().enumerate() {
        assert_eq!(id, &i.to_string());
        let get = |k: &str| data[k].parse::<f64>().unwrap().to_bits();
        let p = skel.positions[i];
        assert_eq!([get("x"), get("y"), get("z")], p.map(f64::to_bits), "x, y, z = axes 0, 1, 2");
        assert_eq!(get("r"), skel.radii[i].to_bits());
    }
    let edges: Vec<[usize; 2]> = g.edges.iter().map(|(s, t)| [s.parse().unwrap(), t.parse().unwrap()]).collect();
    assert_eq!(edges, skel.edges);
}

#[test]
fn empty_graph_in_every_format() {
    let dir = TempDir::new().unwrap();
    let skel = Skeleton { spacing: [1.0, 1.0, 1.0], ..Default::default() };
    for name in ["e.json", "e.npz", "e.graphml"] {
        write_graph(&dir.path().join(name), &skel, &Params::default()).unwrap();
    }
    let doc: Value = serde_json::from_reader(File::open(dir.path().join("e.json")).unwrap()).unwrap();
    assert_eq!(doc["positions"], serde_json::json!([]));
    assert_eq!(doc["edges"], serde_json::json!([]));
    let mut npz = NpzReader::new(File::open(dir.path().join("e.npz")).unwrap()).unwrap();
    let positions: Array2<f64> = npz.by_name("positions").unwrap();
    assert_eq!(positions.shape(), [0, 3]);
    let edges: Array2<i64> = npz.by_name("edges").unwrap();
    assert_eq!(edges.shape(), [0, 2]);
    let g = parse_graphml(&dir.path().join("e.graphml"));
    assert!(g.nodes.is_empty() && g.edges.is_empty());
    assert_eq!(g.graph_data.len(), 3);
}

#[test]
fn arrays_entry_accepts_any_layout() {
    let dir = TempDir::new().unwrap();
    // Positions stored transposed (3, N) and viewed as (N, 3): not C-contiguous.
    let stored = array![[0.0, 1.0], [10.0, 11.0], [20.0, 21.0]];
    let edges = array![[0i64, 1]];
    let (info, params) = (run_info_json(&RunInfo::default()), params_json(&Params::default()));
    let graph = GraphArrays {
        positions: stored.t(),
        radii: ndarray::aview1(&[1.5, 2.5]),
        edges: edges.view(),
        spacing: [1.0, 2.0, 3.0],
        info: &info,
        params: &params,
    };
    let want = array![[0.0, 10.0, 20.0], [1.0, 11.0, 21.0]];
    for name in ["a.json", "a.npz", "a.graphml"] {
        write_graph_arrays(&dir.path().join(name), &graph).unwrap();
    }
    let doc: Value = serde_json::from_reader(File::open(dir.path().join("a.json")).unwrap()).unwrap();
    assert_eq!(doc["positions"], serde_json::json!([[0.0, 10.0, 20.0], [1.0, 11.0, 21.0]]));
    let mut npz = NpzReader::new(File::open(dir.path().join("a.npz")).unwrap()).unwrap();
    let positions: Array2<f64> = npz.by_name("positions").unwrap();
    assert_eq!(positions, want);
    let g = parse_graphml(&dir.path().join("a.graphml"));
    assert_eq!(g.nodes[1].1["z"], "21.0");
}

#[test]
fn invalid_arrays_are_refused_and_an_existing_file_is_kept() {
    let dir = TempDir::new().unwrap();
    let path = dir.path().join("keep.json");
    fs::write(&path, "old").unwrap();
    let positions = array![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]];
    let radii = array![1.0, 1.0];
    let (info, params) = (run_info_json(&RunInfo::default()), params_json(&Params::default()));
    let good = GraphArrays {
        positions: positions.view(),
        radii: radii.view(),
        edges: ndarray::aview2(&[[0i64, 1]]),
        spacing: [1.0; 3],
        info: &info,
        params: &params,
    };
    let nan = array![[0.0, f64::NAN, 0.0], [1.0, 0.0, 0.0]];
    let short = array![1.0];
    let flat = array![[0.0, 0.0], [1.0, 0.0]];
    let not_object = Value::from(3);
    let cases: Vec<(GraphArrays, &str)> = vec![
        (GraphArrays { edges: ndarray::aview2(&[[0i64, 2]]), ..good }, "edge endpoint 2"),
        (GraphArrays { edges: ndarray::aview2(&[[-1i64, 0]]), ..good }, "edge endpoint -1"),
        (GraphArrays { edges: ndarray::aview2(&[[0i64, 1, 1]]), ..good }, "(E, 2)"),
        (GraphArrays { radii: short.view(), ..good }, "radii has 1 entries for 2 nodes"),
        (GraphArrays { positions: flat.view(), ..good }, "(N, 3)"),
        (GraphArrays { positions: nan.view(), ..good }, "finite"),
        (GraphArrays { spacing: [1.0, 0.0, 1.0], ..good }, "spacing"),
        (GraphArrays { info: &not_object, ..good }, "info must be a JSON object"),
    ];
    for (graph, needle) in cases {
        let err = write_graph_arrays(&path, &graph).unwrap_err();
        assert!(matches!(err, IoError::InvalidGraph { .. }), "{err}");
        let msg = err.to_string();
        assert!(msg.contains("keep.json") && msg.contains(needle), "{msg} lacks {needle}");
    }
    assert_eq!(fs::read_to_string(&path).unwrap(), "old");
    assert_eq!(listing(dir.path()), ["keep.json"]);
    // And a valid write replaces it.
    write_graph_arrays(&path, &good).unwrap();
    assert!(fs::read_to_string(&path).unwrap().starts_with('{'));
    assert_eq!(listing(dir.path()), ["keep.json"]);
}

#[test]
fn unknown_extension_creates_nothing() {
    let dir = TempDir::new().unwrap();
    for name in ["g.txt", "g", "g.json.bak", "g.tsv"] {
        let path = dir.path().join(name);
        let err = write_graph(&path, &skeleton(), &Params::default()).unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains(name) && msg.contains(".graphml, .json, .npz, .swc, .vtp, .csv or .precomputed"), "{msg}");
        assert!(check_graph_output(&path).is_err());
    }
    assert!(listing(dir.path()).is_empty());
}

#[test]
fn unwritable_destination_gives_an_error_naming_the_path() {
    let dir = TempDir::new().unwrap();
    let missing = dir.path().join("no/such/dir/g.json");
    let err = write_graph(&missing, &skeleton(), &Params::default()).unwrap_err();
    let msg = err.to_string();
    assert!(msg.contains("no/such/dir/g.json") && msg.contains("does not exist"), "{msg}");
    assert!(check_graph_output(&missing).unwrap_err().to_string().contains("does not exist"));

    // Parent is a regular file (also fails for root, unlike permission bits).
    fs::write(dir.path().join("plain"), "x").unwrap();
    let under_file = dir.path().join("plain/g.npz");
    let msg = write_graph(&under_file, &skeleton(), &Params::default()).unwrap_err().to_string();
    assert!(msg.contains("plain/g.npz") && msg.contains("not a directory"), "{msg}");

    // Target is a directory.
    fs::create_dir(dir.path().join("d.graphml")).unwrap();
    let msg = write_graph(&dir.path().join("d.graphml"), &skeleton(), &Params::default()).unwrap_err().to_string();
    assert!(msg.contains("d.graphml") && msg.contains("directory"), "{msg}");
    assert_eq!(listing(dir.path()), ["d.graphml", "plain"]);
}

#[test]
fn check_graph_output_leaves_nothing_behind() {
    let dir = TempDir::new().unwrap();
    assert_eq!(check_graph_output(&dir.path().join("g.NPZ")).unwrap(), GraphFormat::Npz);
    assert_eq!(check_graph_output(&dir.path().join("g.graphml")).unwrap(), GraphFormat::GraphMl);
    assert!(listing(dir.path()).is_empty());
}

#[cfg(unix)]
#[test]
fn output_file_gets_ordinary_permissions() {
    use std::os::unix::fs::PermissionsExt;
    let dir = TempDir::new().unwrap();
    let reference = dir.path().join("reference");
    File::create(&reference).unwrap();
    let path = dir.path().join("g.json");
    write_graph(&path, &skeleton(), &Params::default()).unwrap();
    let mode = |p: &Path| fs::metadata(p).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode(&path), mode(&reference), "same as File::create (0o666 less the umask)");
}
