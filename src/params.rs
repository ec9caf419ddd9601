//! Every parameter of the method (`docs/parameters.md`), its default and its validation.
//!
//! One table serves all front ends: [`Params::NAMES`] lists the names,
//! [`Params::set`] assigns a loosely typed [`Value`] with range checks that name
//! the parameter, and [`Params::values`] lists current values (for `repr`,
//! `--help`, and run metadata).

use crate::error::{Error, Result};

/// How close to the stop level (`stop_ratio` times the reference area) the short-cycle
/// area must be before a stalled iteration ends the contraction ([`Params::stall_ratio`]).
/// Far above it, in the first iterations or under strong anchoring, slow progress is
/// still progress. In the benchmark volumes the contraction stalls at 1.2 to 6 times
/// the stop level; a thick vessel bed starts near 1600 times it.
pub const STALL_AREA: f64 = 10.0;

/// Edges of the initial grid graph (docs/method.md §1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Connectivity {
    Six = 6,
    Eighteen = 18,
    TwentySix = 26,
}

/// Medial affinity weighting (docs/method.md §2.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MedialWeight {
    /// `r_j / sum_k r_k`: what the authors' code ran (default).
    Radius,
    /// `|r_i - r_j| / sum_k |r_i - r_k|`: the paper's eq. 3.
    Difference,
}

/// Reference area of the convergence test (docs/method.md §2.6).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AreaReference {
    /// Foreground volume in base cells, in `c^2` units: the number of foreground
    /// voxels times `c^2` on an isotropic grid (the authors' code; default). On an
    /// anisotropic grid it counts the base cells the mask covers, so the stop level
    /// does not shrink with the finest spacing while the cycles keep the size of the
    /// coarse voxels.
    Volume,
    /// Short-cycle area of the initial grid graph (the paper's `A_0`).
    InitialArea,
}

/// A loosely typed parameter value as it arrives from Python or the command line.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
}

impl std::fmt::Display for Value {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Value::Bool(b) => write!(f, "{}", if *b { "True" } else { "False" }),
            Value::Int(i) => write!(f, "{i}"),
            Value::Float(x) => write!(f, "{x:?}"),
            Value::Str(s) => write!(f, "'{s}'"),
        }
    }
}

impl Value {
    /// Parse a command-line word: `true`/`false`, an integer, a float, else a string.
    pub fn parse(word: &str) -> Value {
        match word.to_ascii_lowercase().as_str() {
            "true" => return Value::Bool(true),
            "false" => return Value::Bool(false),
            _ => {}
        }
        if let Ok(i) = word.parse::<i64>() {
            return Value::Int(i);
        }
        if let Ok(x) = word.parse::<f64>() {
            return Value::Float(x);
        }
        Value::Str(word.to_string())
    }
}

/// All parameters of the method, with their defaults (`docs/parameters.md`).
#[derive(Debug, Clone, PartialEq)]
pub struct Params {
    /// Grid-graph connectivity: 6 (default), 18 or 26.
    pub connectivity: Connectivity,
    /// Join nodes of degree <= 2 to all foreground voxels within sqrt(2) voxels.
    pub reconnect_thin: bool,
    /// Subtracted from every output radius, in units of the base cell `c = min(spacing)`.
    /// Radii are measured by cross-section area ([`crate::radius`]), unbiased on drawn
    /// tubes (`tests/radius.rs`), so the default is 0; a positive value removes a known
    /// margin by which a mask is wider than its vessels (the bubble-noise recipe of the
    /// benchmark dilates its masks by one voxel first, which is why 0.75 scored best on
    /// its noisy trees under the EDT radius of `docs/method.md` §1).
    pub radius_correction: f64,
    /// Start the contraction from cells of voxels this many vessel radii wide rather
    /// than from one node per voxel ([`crate::coarse`]): cells never span two vessels,
    /// and vessels of radius under `2 / coarse_cell` voxels or over
    /// [`crate::coarse::MAX_CELL_RADIUS`] keep one node per voxel; long edges are then
    /// split back to the cells' spacing ([`crate::resample`]). 0 turns it off (one node
    /// per voxel everywhere, as in the paper).
    pub coarse_cell: f64,
    /// Medial affinity weighting.
    pub medial_weight: MedialWeight,
    /// Angle (degrees) within which all neighbour directions must be collinear for a
    /// node to count as skeleton-like (adaptive anchoring).
    pub skeletal_angle: f64,
    /// Count degree-1 nodes (vessel ends) as skeleton-like too, so they are anchored
    /// `eps_gamma` times harder and kept through decimation, and at output move each
    /// to one radius inside the mask's end along its vessel, or to the centre of a
    /// rounded cap wider than its section (`ends`). The paper's test needs degree > 1;
    /// without this the flow pulls every free end inward.
    pub anchor_ends: bool,
    /// At output, grow back the side branches the contraction swallowed into their
    /// parent: lobes of the mask the graph does not reach become new branches from the
    /// nearest edge ([`crate::sprouts`]). A chunked run's blocks grow them too, and the
    /// merge attaches them ([`crate::blocks_sprouts`]).
    pub sprouts: bool,
    /// Move every node, after refinement, onto the ridge of the distance transform:
    /// within its cross-section to the nearest local maximum, and every junction to
    /// where its branches' centrelines meet, each at most 0.6 radii away
    /// ([`crate::medial`]). Off: nodes stay where the flow left them, at the local
    /// centre of mass of the mask.
    pub medial: bool,
    /// Last, remove the terminal spurs shorter than this many radii of the junction
    /// they join, or whose nodes all lie within this many radii of another branch of
    /// it, until none is left ([`crate::prune`]): at 1 a spur inside its parent's
    /// lumen, a knot or a second rail beside the centreline rather than a vessel. 0
    /// keeps every spur.
    pub prune_spurs: f64,
    /// Then join the junctions linked by a branch shorter than this many times the
    /// larger of their radii into one node ([`crate::junctions`]): at 0.5 a meeting of
    /// four or more vessels that the contraction split into junctions a fraction of a
    /// radius apart. 0 keeps every junction.
    pub merge_junctions: f64,
    /// Last of all, smooth each node's radius along its branch: the median of the radii
    /// within this many base cells of it along the branch, junctions and vessel ends
    /// excluded, an end taking its branch's ([`crate::smooth`]). 0 keeps every node's own
    /// measurement.
    pub radius_smoothing: f64,
    /// Anchoring factor of skeleton-like nodes (`Wg = eps_gamma * gamma`).
    pub eps_gamma: f64,
    /// Weight of the l2-norm Laplacian. Only the ratios alpha : beta : gamma matter; the
    /// default 0.25 (first 0.5, `docs/method.md`) scored best on the synthetic trees
    /// (`benches/results/sensitivity.md`).
    pub alpha: f64,
    /// Weight of the medial Laplacian.
    pub beta: f64,
    /// Anchoring weight (speed of the flow: lower = faster, coarser).
    pub gamma: f64,
    /// Relative residual at which conjugate gradients stop, measured in the
    /// preconditioner's norm (`sqrt(r · B r)`, B the Gauss–Seidel preconditioner, against
    /// its value at the start). 1e-4, not the first default 1e-6:
    /// the fidelity sweep scores them alike (`benches/results/sensitivity.md`) and 1e-4
    /// needs about 40 % fewer CG iterations. Early contraction iterations, far from
    /// the stop level, solve more loosely, down to `cg_tol` near it
    /// ([`crate::solver::solve_tolerance`]).
    pub cg_tol: f64,
    /// Cap on conjugate-gradient iterations per solve.
    pub cg_max_iterations: usize,
    /// Cycles with fewer than this many nodes count in the convergence measure.
    pub max_cycle_nodes: usize,
    /// Stop when the short-cycle area falls to this fraction of the reference.
    pub stop_ratio: f64,
    /// Also stop when an iteration merges fewer than this fraction of the nodes while
    /// the short-cycle area is within [`STALL_AREA`] times the stop level: the graph has
    /// stopped simplifying, and further flow only wears vessel ends down (refinement
    /// then collapses the few small cycles left). 0 turns it off (as in the paper).
    pub stall_ratio: f64,
    /// Reference area of the convergence test.
    pub area_reference: AreaReference,
    /// Cap on contraction iterations.
    pub max_iterations: usize,
    /// Refinement collapses cycles whose area is below this many `c^2`.
    pub refine_area: f64,
    /// Cap on refinement iterations.
    pub max_refine_iterations: usize,
    /// Worker threads; 0 = one per core. Output does not depend on it.
    pub threads: usize,
    /// Refuse a run whose estimated peak memory ([`crate::memory`]) exceeds this many
    /// bytes ([`crate::Error::OutOfMemory`]), before its heavy stages; `Some(0)` = no
    /// limit. `None` (`"auto"`, the default): the front ends put in what the process
    /// may still use; the core itself then applies no limit. Output does not depend on it.
    pub max_memory: Option<u64>,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            connectivity: Connectivity::Six,
            reconnect_thin: true,
            radius_correction: 0.0,
            coarse_cell: 0.67,
            medial_weight: MedialWeight::Radius,
            skeletal_angle: 10.0,
            anchor_ends: true,
            sprouts: true,
            medial: true,
            prune_spurs: 1.0,
            merge_junctions: 0.5,
            radius_smoothing: 4.0,
            eps_gamma: 10.0,
            alpha: 0.25,
            beta: 0.5,
            gamma: 0.05,
            cg_tol: 1e-4,
            cg_max_iterations: 2000,
            max_cycle_nodes: 10,
            stop_ratio: 1e-3,
            stall_ratio: 0.01,
            area_reference: AreaReference::Volume,
            max_iterations: 100,
            refine_area: 50.0,
            max_refine_iterations: 100,
            threads: 0,
            max_memory: None,
        }
    }
}

fn bad(name: &str, reason: impl Into<String>) -> Error {
    Error::InvalidParameter { name: name.to_string(), reason: reason.into() }
}

fn as_f64(name: &str, v: &Value) -> Result<f64> {
    match v {
        Value::Float(x) => Ok(*x),
        Value::Int(i) => Ok(*i as f64),
        _ => Err(bad(name, format!("expected a number, got {v}"))),
    }
}

fn as_usize(name: &str, v: &Value) -> Result<usize> {
    match v {
        Value::Int(i) if *i >= 0 => Ok(*i as usize),
        Value::Int(i) => Err(bad(name, format!("expected an integer >= 0, got {i}"))),
        _ => Err(bad(name, format!("expected an integer, got {v}"))),
    }
}

fn as_bool(name: &str, v: &Value) -> Result<bool> {
    match v {
        Value::Bool(b) => Ok(*b),
        _ => Err(bad(name, format!("expected True or False, got {v}"))),
    }
}

fn as_str<'a>(name: &str, v: &'a Value) -> Result<&'a str> {
    match v {
        Value::Str(s) => Ok(s),
        _ => Err(bad(name, format!("expected a string, got {v}"))),
    }
}

fn in_range(name: &str, x: f64, lo: f64, hi: f64, lo_open: bool) -> Result<f64> {
    let ok = x.is_finite() && (if lo_open { x > lo } else { x >= lo }) && x <= hi;
    if ok {
        Ok(x)
    } else {
        let l = if lo_open { "(" } else { "[" };
        Err(bad(name, format!("must be finite and in {l}{lo}, {hi}], got {x}")))
    }
}

impl Params {
    /// Every parameter name, in documentation order.
    pub const NAMES: [&'static str; 27] = [
        "connectivity",
        "reconnect_thin",
        "radius_correction",
        "coarse_cell",
        "medial_weight",
        "skeletal_angle",
        "anchor_ends",
        "sprouts",
        "medial",
        "prune_spurs",
        "merge_junctions",
        "radius_smoothing",
        "eps_gamma",
        "alpha",
        "beta",
        "gamma",
        "cg_tol",
        "cg_max_iterations",
        "max_cycle_nodes",
        "stop_ratio",
        "stall_ratio",
        "area_reference",
        "max_iterations",
        "refine_area",
        "max_refine_iterations",
        "threads",
        "max_memory",
    ];

    /// Assign one parameter by name, checking its type and range.
    pub fn set(&mut self, name: &str, v: &Value) -> Result<()> {
        match name {
            "connectivity" => {
                self.connectivity = match as_usize(name, v)? {
                    6 => Connectivity::Six,
                    18 => Connectivity::Eighteen,
                    26 => Connectivity::TwentySix,
                    k => return Err(bad(name, format!("must be 6, 18 or 26, got {k}"))),
                }
            }
            "reconnect_thin" => self.reconnect_thin = as_bool(name, v)?,
            "anchor_ends" => self.anchor_ends = as_bool(name, v)?,
            "sprouts" => self.sprouts = as_bool(name, v)?,
            "medial" => self.medial = as_bool(name, v)?,
            "radius_correction" => self.radius_correction = in_range(name, as_f64(name, v)?, 0.0, 1.0, false)?,
            "medial_weight" => {
                self.medial_weight = match as_str(name, v)? {
                    "radius" => MedialWeight::Radius,
                    "difference" => MedialWeight::Difference,
                    s => return Err(bad(name, format!("must be 'radius' or 'difference', got '{s}'"))),
                }
            }
            "skeletal_angle" => self.skeletal_angle = in_range(name, as_f64(name, v)?, 0.0, 90.0, false)?,
            "eps_gamma" => self.eps_gamma = in_range(name, as_f64(name, v)?, 1.0, 1e6, false)?,
            "alpha" => self.alpha = in_range(name, as_f64(name, v)?, 0.0, 1e3, false)?,
            "beta" => self.beta = in_range(name, as_f64(name, v)?, 0.0, 1e3, false)?,
            "gamma" => self.gamma = in_range(name, as_f64(name, v)?, 0.0, 1e3, true)?,
            "cg_tol" => self.cg_tol = in_range(name, as_f64(name, v)?, 0.0, 0.5, true)?,
            "cg_max_iterations" => {
                let k = as_usize(name, v)?;
                if k == 0 {
                    return Err(bad(name, "must be >= 1"));
                }
                self.cg_max_iterations = k;
            }
            "max_cycle_nodes" => {
                let k = as_usize(name, v)?;
                if !(4..=64).contains(&k) {
                    return Err(bad(name, format!("must be in [4, 64], got {k}")));
                }
                self.max_cycle_nodes = k;
            }
            "coarse_cell" => self.coarse_cell = in_range(name, as_f64(name, v)?, 0.0, 4.0, false)?,
            "prune_spurs" => self.prune_spurs = in_range(name, as_f64(name, v)?, 0.0, 100.0, false)?,
            "merge_junctions" => self.merge_junctions = in_range(name, as_f64(name, v)?, 0.0, 10.0, false)?,
            "radius_smoothing" => self.radius_smoothing = in_range(name, as_f64(name, v)?, 0.0, 100.0, false)?,
            "stop_ratio" => self.stop_ratio = in_range(name, as_f64(name, v)?, 0.0, 1.0, true)?,
            "stall_ratio" => self.stall_ratio = in_range(name, as_f64(name, v)?, 0.0, 0.5, false)?,
            "area_reference" => {
                self.area_reference = match as_str(name, v)? {
                    "volume" => AreaReference::Volume,
                    "initial_area" => AreaReference::InitialArea,
                    s => return Err(bad(name, format!("must be 'volume' or 'initial_area', got '{s}'"))),
                }
            }
            "max_iterations" => self.max_iterations = as_usize(name, v)?,
            "refine_area" => self.refine_area = in_range(name, as_f64(name, v)?, 0.0, 1e9, false)?,
            "max_refine_iterations" => self.max_refine_iterations = as_usize(name, v)?,
            "threads" => {
                let t = as_usize(name, v)?;
                if t > 4096 {
                    return Err(bad(name, format!("must be in [0, 4096], got {t}")));
                }
                self.threads = t;
            }
            "max_memory" => {
                self.max_memory = match v {
                    Value::Int(i) if *i >= 0 => Some(*i as u64),
                    Value::Float(x) if x.is_finite() && *x >= 0.0 && *x < u64::MAX as f64 => Some(x.round() as u64),
                    Value::Str(s) if s.eq_ignore_ascii_case("auto") => None,
                    Value::Str(s) if parse_bytes(s).is_some() => parse_bytes(s),
                    _ => {
                        return Err(bad(
                            name,
                            format!("expected bytes >= 0 (e.g. 8000000000, '8GB', '512MiB'), 0 or 'auto', got {v}"),
                        ))
                    }
                }
            }
            _ => return Err(Error::UnknownParameter { name: name.to_string(), known: &Params::NAMES }),
        }
        if self.alpha == 0.0 && self.beta == 0.0 {
            return Err(bad(name, "alpha and beta cannot both be 0 (no flow)"));
        }
        Ok(())
    }

    /// Build from `(name, value)` pairs over the defaults.
    pub fn from_pairs<'a>(pairs: impl IntoIterator<Item = (&'a str, Value)>) -> Result<Params> {
        let mut p = Params::default();
        for (k, v) in pairs {
            p.set(k, &v)?;
        }
        Ok(p)
    }

    /// Current values, in [`Params::NAMES`] order.
    pub fn values(&self) -> Vec<(&'static str, Value)> {
        let mw = match self.medial_weight {
            MedialWeight::Radius => "radius",
            MedialWeight::Difference => "difference",
        };
        let ar = match self.area_reference {
            AreaReference::Volume => "volume",
            AreaReference::InitialArea => "initial_area",
        };
        vec![
            ("connectivity", Value::Int(self.connectivity as i64)),
            ("reconnect_thin", Value::Bool(self.reconnect_thin)),
            ("radius_correction", Value::Float(self.radius_correction)),
            ("coarse_cell", Value::Float(self.coarse_cell)),
            ("medial_weight", Value::Str(mw.into())),
            ("skeletal_angle", Value::Float(self.skeletal_angle)),
            ("anchor_ends", Value::Bool(self.anchor_ends)),
            ("sprouts", Value::Bool(self.sprouts)),
            ("medial", Value::Bool(self.medial)),
            ("prune_spurs", Value::Float(self.prune_spurs)),
            ("merge_junctions", Value::Float(self.merge_junctions)),
            ("radius_smoothing", Value::Float(self.radius_smoothing)),
            ("eps_gamma", Value::Float(self.eps_gamma)),
            ("alpha", Value::Float(self.alpha)),
            ("beta", Value::Float(self.beta)),
            ("gamma", Value::Float(self.gamma)),
            ("cg_tol", Value::Float(self.cg_tol)),
            ("cg_max_iterations", Value::Int(self.cg_max_iterations as i64)),
            ("max_cycle_nodes", Value::Int(self.max_cycle_nodes as i64)),
            ("stop_ratio", Value::Float(self.stop_ratio)),
            ("stall_ratio", Value::Float(self.stall_ratio)),
            ("area_reference", Value::Str(ar.into())),
            ("max_iterations", Value::Int(self.max_iterations as i64)),
            ("refine_area", Value::Float(self.refine_area)),
            ("max_refine_iterations", Value::Int(self.max_refine_iterations as i64)),
            ("threads", Value::Int(self.threads as i64)),
            (
                "max_memory",
                self.max_memory.map_or(Value::Str("auto".into()), |b| Value::Int(b.min(i64::MAX as u64) as i64)),
            ),
        ]
    }
}

/// Parse a byte count: an integer number of bytes, or a number with a unit (`"8GB"`,
/// `"512MiB"`, `"1.5 G"`; `k`/`M`/`G`/`T` alone and with `B` are powers of 1000, with
/// `iB` powers of 1024; case-insensitive).
fn parse_bytes(text: &str) -> Option<u64> {
    let t = text.trim();
    let split = t.find(|ch: char| !(ch.is_ascii_digit() || ch == '.')).unwrap_or(t.len());
    let (number, unit) = (t[..split].trim(), t[split..].trim().to_ascii_lowercase());
    let x: f64 = number.parse().ok()?;
    let scale: f64 = match unit.as_str() {
        "" | "b" => 1.0,
        "k" | "kb" => 1e3,
        "m" | "mb" => 1e6,
        "g" | "gb" => 1e9,
        "t" | "tb" => 1e12,
        "kib" => 1024.0,
        "mib" => 1024f64.powi(2),
        "gib" => 1024f64.powi(3),
        "tib" => 1024f64.powi(4),
        _ => return None,
    };
    let bytes = (x * scale).round();
    (x.is_finite() && bytes < u64::MAX as f64).then_some(bytes as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_and_values_agree() {
        let names: Vec<_> = Params::default().values().into_iter().map(|(k, _)| k).collect();
        assert_eq!(names, Params::NAMES.to_vec());
    }

    #[test]
    fn round_trip_every_value() {
        let p = Params::default();
        let q = Params::from_pairs(p.values()).unwrap();
        assert_eq!(p, q);
    }

    #[test]
    fn errors_name_the_parameter() {
        let e = Params::from_pairs([("gamma", Value::Float(-1.0))]).unwrap_err();
        assert!(e.to_string().contains("`gamma`"), "{e}");
        let e = Params::from_pairs([("connectivity", Value::Int(7))]).unwrap_err();
        assert!(e.to_string().contains("`connectivity`"), "{e}");
        let e = Params::from_pairs([("nope", Value::Int(7))]).unwrap_err();
        assert!(matches!(e, Error::UnknownParameter { .. }));
        assert!(e.to_string().contains("`nope`") && e.to_string().contains(&Params::NAMES.join(", ")), "{e}");
        let e = Params::from_pairs([("alpha", Value::Float(f64::NAN))]).unwrap_err();
        assert!(e.to_string().contains("`alpha`"), "{e}");
        let e = Params::from_pairs([("medial_weight", Value::Int(1))]).unwrap_err();
        assert!(e.to_string().contains("`medial_weight`"), "{e}");
        for bad in [Value::Int(-1), Value::Str("8 parsecs".into()), Value::Bool(true), Value::Float(-1.0)] {
            let e = Params::from_pairs([("max_memory", bad)]).unwrap_err();
            assert!(e.to_string().contains("`max_memory`"), "{e}");
        }
    }

    #[test]
    fn byte_counts_parse_with_units() {
        assert_eq!(parse_bytes("8GB"), Some(8_000_000_000));
        assert_eq!(parse_bytes("512MiB"), Some(512 << 20));
        assert_eq!(parse_bytes("1KB"), Some(1000));
        assert_eq!(parse_bytes(" 1.5 gib "), Some(3 << 29));
        assert_eq!(parse_bytes("123"), Some(123));
        assert_eq!(parse_bytes("0"), Some(0));
        for bad in ["", "GB", "8 parsecs", "-1GB", "1e3", "nan"] {
            assert_eq!(parse_bytes(bad), None, "{bad}");
        }
    }

    #[test]
    fn max_memory_takes_bytes_with_units() {
        let get = |v: Value| Params::from_pairs([("max_memory", v)]).unwrap().max_memory;
        assert_eq!(get(Value::Str("8GB".into())), Some(8_000_000_000));
        assert_eq!(get(Value::Str("512MiB".into())), Some(512 << 20));
        assert_eq!(get(Value::Int(1000)), Some(1000));
        assert_eq!(get(Value::Int(0)), Some(0));
        assert_eq!(get(Value::Str("auto".into())), None);
        assert_eq!(Params::default().max_memory, None);
    }

    #[test]
    fn parse_words() {
        assert_eq!(Value::parse("true"), Value::Bool(true));
        assert_eq!(Value::parse("12"), Value::Int(12));
        assert_eq!(Value::parse("0.5"), Value::Float(0.5));
        assert_eq!(Value::parse("radius"), Value::Str("radius".into()));
    }
}
