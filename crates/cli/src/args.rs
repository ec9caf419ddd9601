//! The command line: clap definitions and their translation into a [`Task`].
//!
//! One long option per method parameter is generated from [`Params::NAMES`] and
//! [`Params::default`], so the program can never fall out of step with the core:
//! `max_iterations` becomes `--max-iterations`, its help shows the default, and
//! its value goes through [`Value::parse`] and [`Params::set`], whose errors name
//! the parameter.

use crate::Failure;
use clap::error::{ContextKind, ContextValue, ErrorKind};
use clap::{value_parser, Arg, ArgAction, ArgMatches, Command};
use std::ffi::OsString;
use std::path::PathBuf;
use vesselflow::{Params, Value};
use vesselflow_io::{Coordinates, MaskRule};

/// How much the program says on stderr.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Verbosity {
    /// Errors only.
    Quiet,
    /// Progress and per-stage timings.
    Normal,
    /// Also every contraction iteration.
    Verbose,
}

/// What the command line asks for.
#[derive(Debug)]
pub(crate) enum Task {
    Skeletonize {
        input: PathBuf,
        output: PathBuf,
        spacing: Option<[f64; 3]>,
        rule: MaskRule,
        plot: Option<PathBuf>,
        params: Params,
        key: Option<String>,
        coordinates: Coordinates,
    },
    Demo {
        output: Option<PathBuf>,
        plot: Option<PathBuf>,
        params: Params,
    },
}

/// The parsed command line, or what to do instead of running.
pub(crate) enum Parsed {
    Run(Box<Task>, Verbosity),
    /// `--help`, `--version`, or a bare `vesselflow`: print `text` and exit with `code`.
    Exit {
        text: String,
        to_stderr: bool,
        code: i32,
    },
}

/// A parameter value as typed on the command line (so `'radius'` shows as `radius`).
fn command_line_word(value: &Value) -> String {
    match value {
        Value::Bool(b) => b.to_string(),
        Value::Str(s) => s.clone(),
        other => other.to_string(),
    }
}

/// What a method parameter does, in one sentence for `--help` (the parameter guide,
/// `docs/parameters.md`, says when to change it). `None` for a name the core does not have.
fn parameter_help(name: &str) -> Option<&'static str> {
    Some(match name {
        "connectivity" => {
            "Neighbours joined in the initial voxel graph: 6 (faces), 18 (and edges) or 26 (and corners)."
        }
        "reconnect_thin" => {
            "Also join nodes of degree <= 2 to every vessel voxel within sqrt(2) voxels, so that one-voxel-thin \
             vessels stay connected."
        }
        "radius_correction" => {
            "Voxels (of the finest spacing, 0 to 1) taken off every radius, for a mask known to be wider than its \
             vessels."
        }
        "coarse_cell" => {
            "Start from cells of voxels this many vessel radii wide (0 to 4) instead of one node per voxel, in \
             vessels 2 / coarse_cell to 8 voxels in radius; 0 turns it off (one node per voxel, the paper's start)."
        }
        "medial_weight" => {
            "Weights of the medial Laplacian, which pulls nodes to the vessel axis: 'radius' (the authors' code) or \
             'difference' (the paper's equation 3)."
        }
        "skeletal_angle" => {
            "Degrees (0 to 90) within which a node's neighbours must line up for it to count as already on the \
             centreline and be anchored harder."
        }
        "anchor_ends" => {
            "Count vessel ends (nodes of degree 1) as on the centreline, so that the flow does not shorten vessels."
        }
        "sprouts" => {
            "Grow back side branches the contraction swallowed into their parent (chunked runs too: the merge \
             attaches the blocks' sprouts)."
        }
        "medial" => {
            "After refinement, move nodes onto the ridge of the distance transform and junctions to where their \
             branches meet (at most 0.6 radii)."
        }
        "prune_spurs" => {
            "Last, remove terminal spurs shorter than this many radii (>= 0) of their junction, or lying within \
             this many radii of another branch of it, until none is left (0 keeps them all)."
        }
        "merge_junctions" => {
            "Then join two junctions linked by a branch shorter than this many times (>= 0) the larger of their \
             radii into one node: a meeting of four or more vessels split by the contraction (0 keeps them all)."
        }
        "radius_smoothing" => {
            "Last of all, each node's radius becomes the median of the radii within this many base cells (>= 0) of \
             it along its branch, junctions and vessel ends excluded, an end taking its branch's (0 keeps every \
             node's own measurement)."
        }
        "eps_gamma" => "How many times (>= 1) harder than the others nodes already on the centreline are anchored.",
        "alpha" => {
            "Weight (>= 0) of the smoothing (l2-norm) Laplacian; only the ratios of alpha, beta and gamma matter."
        }
        "beta" => "Weight (>= 0) of the medial Laplacian, which pulls nodes towards the vessel axis.",
        "gamma" => {
            "Anchoring weight (> 0): lower contracts faster and coarser, higher keeps detail and needs more \
             iterations."
        }
        "cg_tol" => "Relative residual (0 to 0.5) at which the conjugate-gradient solves near the stop level end; early iterations solve more loosely (at most 5e-4).",
        "cg_max_iterations" => "Cap (>= 1) on conjugate-gradient iterations per solve.",
        "max_cycle_nodes" => {
            "Cycles of fewer nodes than this (4 to 64) are knots to contract: they make up the convergence measure \
             and are what refinement collapses."
        }
        "stop_ratio" => {
            "The contraction stops when the short-cycle area falls to this fraction (0 to 1) of the reference area."
        }
        "stall_ratio" => {
            "The contraction also stops when an iteration merges fewer than this fraction (0 to 0.5) of the nodes near \
             the stop level; 0 turns this test off."
        }
        "area_reference" => {
            "Reference area of the stop test: 'volume' (the vessel volume, the authors' code) or 'initial_area' (the \
             initial graph's short-cycle area, the paper)."
        }
        "max_iterations" => "Cap on contraction iterations; a run that reaches it ends with a warning.",
        "refine_area" => {
            "Refinement collapses the short cycles smaller than this many squared voxels, except loops around a hole \
             of the mask."
        }
        "max_refine_iterations" => "Cap on refinement iterations.",
        "threads" => "Worker threads, 0 for one per core; the output does not depend on it.",
        "max_memory" => {
            "Refuse a run whose estimated peak memory is larger: bytes, or a size such as 8GB or 512MiB; auto: what \
             this process may use; 0: no limit."
        }
        _ => return None,
    })
}

fn with_parameter_options(mut cmd: Command) -> Command {
    for (name, default) in Params::default().values() {
        cmd = cmd.arg(
            Arg::new(name)
                .long(name.replace('_', "-"))
                .value_name("VALUE")
                .allow_negative_numbers(true)
                .help_heading("Method parameters")
                .help(format!("{} [default: {}]", parameter_help(name).unwrap_or(""), command_line_word(&default))),
        );
    }
    cmd.after_help(
        "Method parameters: docs/parameters.md in the source repository says which to change for what. In \
         Python they are the keywords of vesselflow.Skeletonizer, with '_' for '-'.",
    )
}

fn output_arg(required: bool) -> Arg {
    Arg::new("output")
        .short('o')
        .long("output")
        .value_name("OUTPUT")
        .required(required)
        .value_parser(value_parser!(PathBuf))
        .help(format!("Graph file to write: {} (written atomically)", vesselflow_io::GraphFormat::extensions_text()))
}

fn plot_arg() -> Arg {
    Arg::new("plot").long("plot").value_name("PATH.png").value_parser(value_parser!(PathBuf)).help(
        "Also write a picture: the mask projected along axis 0 with the graph's edges coloured by radius \
             (viridis, colour bar at the right; its radius range is printed on stderr)",
    )
}

/// The whole command-line interface.
pub(crate) fn command() -> Command {
    let skeletonize = Command::new("skeletonize")
        .about(
            "Turn a binary vessel mask (.npy, .nii, .nii.gz, .tif) into a centreline graph; other images need \
             --threshold or --label",
        )
        .arg(
            Arg::new("input")
                .value_name("INPUT")
                .required(true)
                .value_parser(value_parser!(PathBuf))
                .help("Mask file (bool, integers 0 and one other value, or floats 0 and 1): .npy, NIfTI .nii/.nii.gz (spacing from its header) or a TIFF stack .tif/.tiff (ImageJ spacing)"),
        )
        .arg(output_arg(true))
        .arg(plot_arg())
        .arg(
            Arg::new("spacing")
                .long("spacing")
                .num_args(3)
                .value_names(["A", "B", "C"])
                .allow_negative_numbers(true)
                .value_parser(value_parser!(f64))
                .help("Voxel size along axes 0, 1, 2, replacing the file's [default: from the file, else 1 1 1]"),
        )
        .arg(
            Arg::new("threshold")
                .long("threshold")
                .value_name("T")
                .allow_negative_numbers(true)
                .value_parser(value_parser!(f64))
                .conflicts_with("label")
                .help("Binarise an image that is not a mask (e.g. a probability map): vessel where value > T"),
        )
        .arg(
            Arg::new("label")
                .long("label")
                .value_name("V")
                .allow_negative_numbers(true)
                .value_parser(value_parser!(f64))
                .help("Take one label of a label image: vessel where value == V"),
        )
        .arg(
            Arg::new("key")
                .long("key")
                .value_name("NAME")
                .help("The array of an .npz file to read [default: 'mask', or its only array besides 'spacing']"),
        )
        .arg(
            Arg::new("coordinates")
                .long("coordinates")
                .value_name("FRAME")
                .value_parser(Coordinates::NAMES)
                .default_value("array")
                .help(
                    "Frame of the graph's positions: array (physical units along array axes 0, 1, 2), xyz (x = the \
                     last axis, as SWC/VTK/Neuroglancer expect) or world (through the file's voxel-to-world affine, \
                     e.g. the NIfTI sform/qform); radii stay in the spacing's units",
                ),
        );
    let demo = Command::new("demo")
        .about("Run on the built-in synthetic volume (branching tubes with a loop) and print a summary")
        .arg(output_arg(false))
        .arg(plot_arg());
    Command::new("vesselflow")
        .version(env!("CARGO_PKG_VERSION"))
        .about("Vessel mask to centreline graph by Laplacian flow (Damseh et al.)")
        .subcommand_required(true)
        .arg_required_else_help(true)
        .arg(
            Arg::new("quiet")
                .short('q')
                .long("quiet")
                .global(true)
                .action(ArgAction::SetTrue)
                .conflicts_with("verbose")
                .help("Print errors only"),
        )
        .arg(
            Arg::new("verbose")
                .short('v')
                .long("verbose")
                .global(true)
                .action(ArgAction::SetTrue)
                .help("Also print every contraction iteration (nodes, CG iterations, area ratio)"),
        )
        .subcommand(with_parameter_options(skeletonize))
        .subcommand(with_parameter_options(demo))
}

/// Parse `args` (program name first).
pub(crate) fn parse<I, T>(args: I) -> Result<Parsed, Failure>
where
    I: IntoIterator<Item = T>,
    T: Into<OsString> + Clone,
{
    let matches = match command().try_get_matches_from(args) {
        Ok(m) => m,
        Err(e) => return clap_outcome(&e),
    };
    let verbosity = if matches.get_flag("quiet") {
        Verbosity::Quiet
    } else if matches.get_flag("verbose") {
        Verbosity::Verbose
    } else {
        Verbosity::Normal
    };
    let task = match matches.subcommand() {
        Some(("skeletonize", m)) => Task::Skeletonize {
            input: m.get_one::<PathBuf>("input").cloned().unwrap_or_default(),
            output: m.get_one::<PathBuf>("output").cloned().unwrap_or_default(),
            spacing: spacing(m)?,
            rule: MaskRule::new(m.get_one::<f64>("threshold").copied(), m.get_one::<f64>("label").copied())
                .map_err(Failure::Usage)?,
            plot: m.get_one::<PathBuf>("plot").cloned(),
            params: params(m)?,
            key: m.get_one::<String>("key").cloned(),
            coordinates: m
                .get_one::<String>("coordinates")
                .map_or(Ok(Coordinates::Array), |c| c.parse())
                .map_err(Failure::Usage)?,
        },
        Some(("demo", m)) => Task::Demo {
            output: m.get_one::<PathBuf>("output").cloned(),
            plot: m.get_one::<PathBuf>("plot").cloned(),
            params: params(m)?,
        },
        _ => return Err(Failure::Usage("no command given (try --help)".to_string())),
    };
    Ok(Parsed::Run(Box::new(task), verbosity))
}

/// Help and version go to stdout with success; every parse error becomes one line.
fn clap_outcome(e: &clap::Error) -> Result<Parsed, Failure> {
    match e.kind() {
        ErrorKind::DisplayHelp | ErrorKind::DisplayVersion => {
            Ok(Parsed::Exit { text: e.render().to_string(), to_stderr: false, code: 0 })
        }
        ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => {
            Ok(Parsed::Exit { text: e.render().to_string(), to_stderr: true, code: crate::EXIT_USAGE })
        }
        _ => {
            // clap's first paragraph is the error (its continuation lines list e.g. the
            // missing arguments); the rest is usage and tips.
            let rendered = e.render().to_string();
            let paragraph: Vec<&str> = rendered.lines().take_while(|l| !l.trim().is_empty()).map(str::trim).collect();
            let joined = paragraph.join(" ");
            let mut message = joined.strip_prefix("error: ").unwrap_or(&joined).to_string();
            if let Some(ContextValue::String(suggested)) = e.get(ContextKind::SuggestedArg) {
                message.push_str(&format!(" (did you mean {suggested}?)"));
            }
            Err(Failure::Usage(message))
        }
    }
}

fn spacing(m: &ArgMatches) -> Result<Option<[f64; 3]>, Failure> {
    let Some(values) = m.get_many::<f64>("spacing") else {
        return Ok(None);
    };
    let values: Vec<f64> = values.copied().collect();
    match <[f64; 3]>::try_from(values.as_slice()) {
        Ok(s) if s.iter().all(|x| x.is_finite() && *x > 0.0) => Ok(Some(s)),
        _ => Err(Failure::Usage(format!("--spacing: {}", vesselflow::volume::invalid_spacing(values)))),
    }
}

fn params(m: &ArgMatches) -> Result<Params, Failure> {
    let mut params = Params::default();
    for name in Params::NAMES {
        if let Some(word) = m.get_one::<String>(name) {
            params.set(name, &Value::parse(word)).map_err(|e| Failure::Usage(e.to_string()))?;
        }
    }
    Ok(params)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_method_parameter_has_one_sentence_of_help() {
        for name in Params::NAMES {
            let text = parameter_help(name).unwrap_or_else(|| panic!("no help for {name}"));
            assert!(text.ends_with('.') && text.matches(". ").count() == 0, "{name}: one sentence: {text}");
            assert!(!text.contains(".md"), "{name}: the help names no file: {text}");
        }
        assert_eq!(parameter_help("no_such_parameter"), None);
    }
}
