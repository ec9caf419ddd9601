//! # vesselflow-cli
//!
//! The `vesselflow` command line, as a library so that the same program can be
//! started from the `vesselflow` binary ([`run`]) and from the Python package's
//! console script ([`run_with`]):
//!
//! ```text
//! vesselflow skeletonize INPUT -o OUTPUT [--spacing A B C] [--plot PATH.png] [--PARAM VALUE ...] [-q|-v]
//! vesselflow demo [-o OUTPUT] [--plot PATH.png]
//! ```
//!
//! Exit codes: 0 success; 1 a file could not be read or written, or the run
//! failed; 2 the command line is wrong (unknown option, bad parameter value,
//! unsupported file extension); 130 interrupted. Every error is one line on
//! stderr, `vesselflow: error: <message>`, and no output file is left behind.

mod args;
mod plot;
mod report;
mod summary;

use args::{Parsed, Task, Verbosity};
use ndarray::ArrayView3;
use report::Reporter;
use std::ffi::OsString;
use std::io::Write;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;
use summary::GraphSummary;
use vesselflow::{shapes, Params, Skeleton, Skeletonizer};
use vesselflow_io::IoError;

/// Exit code of a run that failed (I/O or the method).
pub const EXIT_FAILURE: i32 = 1;
/// Exit code of a wrong command line.
pub const EXIT_USAGE: i32 = 2;
/// Exit code of an interrupted run (128 + SIGINT, as shells report it).
pub const EXIT_INTERRUPTED: i32 = 130;

/// Why the program stops without success.
#[derive(Debug)]
pub(crate) enum Failure {
    /// The command line is wrong: exit 2.
    Usage(String),
    /// A file or the run failed: exit 1.
    Run(String),
    /// Stopped on request: exit 130.
    Interrupted,
}

impl Failure {
    fn code(&self) -> i32 {
        match self {
            Failure::Usage(_) => EXIT_USAGE,
            Failure::Run(_) => EXIT_FAILURE,
            Failure::Interrupted => EXIT_INTERRUPTED,
        }
    }

    fn message(&self) -> &str {
        match self {
            Failure::Usage(m) | Failure::Run(m) => m,
            Failure::Interrupted => "interrupted; no output written",
        }
    }
}

impl From<IoError> for Failure {
    fn from(e: IoError) -> Failure {
        match e {
            // Visible from the command line alone, before any file is touched.
            IoError::UnsupportedVolume { .. } | IoError::UnsupportedGraph { .. } => Failure::Usage(e.to_string()),
            _ => Failure::Run(e.to_string()),
        }
    }
}

impl From<vesselflow::Error> for Failure {
    fn from(e: vesselflow::Error) -> Failure {
        use vesselflow::Error;
        match e {
            Error::Interrupted => Failure::Interrupted,
            Error::InvalidParameter { .. } | Error::UnknownParameter(_) | Error::InvalidSpacing(_) => {
                Failure::Usage(e.to_string())
            }
            _ => Failure::Run(e.to_string()),
        }
    }
}

/// Set by the signal handler that [`run`] installs.
static INTERRUPTED: AtomicBool = AtomicBool::new(false);

/// Entry point of the `vesselflow` binary: installs a Ctrl-C (and SIGTERM/SIGHUP)
/// handler, then runs [`run_with`]. The first signal stops the run at the next
/// progress report and exits with 130 without writing; a second one exits at once.
///
/// Call this only from a program's `main`: it takes over the process's signal
/// handling. Embedders (the Python bindings) call [`run_with`] instead.
pub fn run<I, T>(args: I) -> i32
where
    I: IntoIterator<Item = T>,
    T: Into<OsString> + Clone,
{
    // If a handler cannot be installed, signals keep their default action (the
    // process ends, and the atomic writers still leave no partial file).
    let _ = ctrlc::set_handler(|| {
        if INTERRUPTED.swap(true, Ordering::SeqCst) {
            std::process::exit(EXIT_INTERRUPTED);
        }
        eprintln!("\nvesselflow: stopping at the next step (press Ctrl-C again to quit at once)");
    });
    run_with(args, &mut || INTERRUPTED.load(Ordering::SeqCst))
}

/// Run the command line `args` (program name first) and return the exit code.
/// Installs no signal handler: `interrupted` is polled before and after each
/// stage and at every progress report of the run, and a `true` stops it (exit
/// 130, no output). The Python bindings pass a closure that checks Python's
/// pending signals, so Ctrl-C works in the console script too.
pub fn run_with<I, T>(args: I, interrupted: &mut dyn FnMut() -> bool) -> i32
where
    I: IntoIterator<Item = T>,
    T: Into<OsString> + Clone,
{
    let outcome = args::parse(args).and_then(|parsed| match parsed {
        Parsed::Exit { text, to_stderr, code } => {
            if to_stderr {
                eprint!("{text}");
            } else {
                print!("{text}");
            }
            Ok(code)
        }
        Parsed::Run(task, verbosity) => execute(*task, verbosity, interrupted).map(|()| 0),
    });
    match outcome {
        Ok(code) => code,
        Err(failure) => {
            eprintln!("vesselflow: error: {}", failure.message());
            failure.code()
        }
    }
}

fn execute(task: Task, verbosity: Verbosity, interrupted: &mut dyn FnMut() -> bool) -> Result<(), Failure> {
    match task {
        Task::Skeletonize { input, output, spacing, plot, params } => {
            // Refuse a bad output path before reading or computing anything.
            vesselflow_io::check_graph_output(&output)?;
            if let Some(path) = &plot {
                plot::check_output(path)?;
            }
            let skeletonizer = Skeletonizer::new(params)?;
            let volume = match spacing {
                Some(s) => vesselflow_io::read_volume_with_spacing(&input, s)?,
                None => vesselflow_io::read_volume(&input)?,
            };
            let shape = volume.mask.shape();
            let mut reporter = Reporter::new(verbosity);
            reporter.line(&format!(
                "vesselflow: {}: {} x {} x {} voxels, spacing {:?}",
                input.display(),
                shape[0],
                shape[1],
                shape[2],
                volume.spacing
            ));
            let skel = skeletonize(&skeletonizer, volume.mask.view(), volume.spacing, &mut reporter, interrupted)?;
            save(&output, &skel, skeletonizer.params(), interrupted)?;
            reporter.line(&format!(
                "vesselflow: wrote {} ({} nodes, {} edges)",
                output.display(),
                skel.len(),
                skel.edges.len()
            ));
            if let Some(path) = &plot {
                save_plot(path, volume.mask.view(), volume.spacing, &skel, &reporter, interrupted)?;
            }
            Ok(())
        }
        Task::Demo { output, plot, params } => {
            if let Some(path) = &output {
                vesselflow_io::check_graph_output(path)?;
            }
            if let Some(path) = &plot {
                plot::check_output(path)?;
            }
            let skeletonizer = Skeletonizer::new(params)?;
            let mask = shapes::demo_volume();
            let mut reporter = Reporter::new(verbosity);
            let started = Instant::now();
            let skel = skeletonize(&skeletonizer, mask.view(), [1.0; 3], &mut reporter, interrupted)?;
            let seconds = started.elapsed().as_secs_f64();
            if let Some(path) = &output {
                save(path, &skel, skeletonizer.params(), interrupted)?;
                reporter.line(&format!("vesselflow: wrote {}", path.display()));
            }
            if let Some(path) = &plot {
                save_plot(path, mask.view(), [1.0; 3], &skel, &reporter, interrupted)?;
            }
            let (n0, n1, n2) = mask.dim();
            let info = &skel.info;
            let text = format!(
                "vesselflow demo: built-in volume {n0} x {n1} x {n2} (branching tubes with a loop), spacing 1\n\
                 foreground voxels   {}\n{}\n\
                 iterations          {} ({})\n\
                 seconds             {seconds:.3}\n",
                info.foreground_voxels,
                GraphSummary::of(&skel),
                info.iterations,
                match (info.converged, info.stalled) {
                    (true, _) => "converged",
                    (_, true) => "stalled near convergence",
                    _ => "not converged: hit max_iterations",
                },
            );
            std::io::stdout()
                .lock()
                .write_all(text.as_bytes())
                .map_err(|e| Failure::Run(format!("cannot write to standard output: {e}")))
        }
    }
}

/// Run the method with progress reporting and interruption.
fn skeletonize(
    skeletonizer: &Skeletonizer,
    mask: ArrayView3<'_, u8>,
    spacing: [f64; 3],
    reporter: &mut Reporter,
    interrupted: &mut dyn FnMut() -> bool,
) -> Result<Skeleton, Failure> {
    if interrupted() {
        return Err(Failure::Interrupted);
    }
    let result = skeletonizer.run(mask, spacing, &mut |p| {
        reporter.observe(p);
        !interrupted()
    });
    reporter.finish();
    let skel = result?;
    reporter.run_details(&skel.info);
    Ok(skel)
}

/// Write the graph unless an interruption arrived after the run's last report.
fn save(path: &Path, skel: &Skeleton, params: &Params, interrupted: &mut dyn FnMut() -> bool) -> Result<(), Failure> {
    if interrupted() {
        return Err(Failure::Interrupted);
    }
    Ok(vesselflow_io::write_graph(path, skel, params)?)
}

/// Draw and write the `--plot` picture, and say on stderr what its colour bar spans.
fn save_plot(
    path: &Path,
    mask: ArrayView3<'_, u8>,
    spacing: [f64; 3],
    skel: &Skeleton,
    reporter: &Reporter,
    interrupted: &mut dyn FnMut() -> bool,
) -> Result<(), Failure> {
    if interrupted() {
        return Err(Failure::Interrupted);
    }
    let picture = plot::render(mask, spacing, skel);
    plot::write_png(path, &picture.image)?;
    let bar = match picture.radius_range {
        Some([lo, hi]) => format!("colour bar: edge radius {lo:.4} (bottom) to {hi:.4} (top), viridis"),
        None => "no edges to draw".to_string(),
    };
    reporter.line(&format!("vesselflow: wrote {} ({bar})", path.display()));
    Ok(())
}
