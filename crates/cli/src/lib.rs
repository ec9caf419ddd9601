//! # vesselflow-cli
//!
//! The `vesselflow` command line, as a library so that the same program can be
//! started from the `vesselflow` binary ([`run`]) and from the Python package's
//! console script ([`run_with`]):
//!
//! ```text
//! vesselflow skeletonize INPUT -o OUTPUT [--spacing A B C] [--threshold T | --label V] [--plot PATH.png] [--PARAM VALUE ...] [-q|-v]
//! vesselflow demo [-o OUTPUT] [--plot PATH.png]
//! ```
//!
//! Exit codes: 0 success; 1 a file could not be read or written, or the run
//! failed (including an internal error: a caught panic, reported in one line, never
//! a backtrace); 2 the command line is wrong (unknown option, bad parameter value,
//! unsupported file extension); 130 interrupted (SIGINT, SIGTERM or SIGHUP). Every
//! error is one line on stderr, `vesselflow: error: <message>`. The graph and the
//! plot are written to temporary files beside their destinations and renamed there
//! only when both are complete: a failure or an interruption leaves the previous
//! files, or none, and no temporary file.

mod args;
mod plot;
mod report;
mod summary;

use args::{Parsed, Task, Verbosity};
use ndarray::ArrayView3;
use report::Reporter;
use std::cell::RefCell;
use std::ffi::OsString;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{LazyLock, Mutex};
use std::time::Instant;
use summary::GraphSummary;
use tempfile::TempDir;
use vesselflow::{shapes, Params, Skeleton, Skeletonizer, Stop};
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
            Error::InvalidParameter { .. } | Error::UnknownParameter { .. } | Error::InvalidSpacing { .. } => {
                Failure::Usage(e.to_string())
            }
            _ => Failure::Run(e.to_string()),
        }
    }
}

/// Raised by the signal handler that [`run`] installs.
static STOP: LazyLock<Stop> = LazyLock::new(Stop::new);

/// Signals received by the handler that [`run`] installs.
static SIGNALS: AtomicUsize = AtomicUsize::new(0);

/// Staging directories of outputs being written, removed by the third signal before
/// it ends the process (the normal return path removes them itself).
static STAGING: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// Entry point of the `vesselflow` binary: installs a handler of SIGINT, SIGTERM
/// and SIGHUP, then runs [`run_with`]. The first signal stops the run within a
/// fraction of a second (the stages poll the flag it raises) and exits with 130,
/// leaving the previous output files or none; a second one is acknowledged while
/// the temporary files are removed; a third removes them itself and exits at once.
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
    // `ctrlc` runs this on a thread of its own, not in the signal handler itself.
    let _ = ctrlc::set_handler(|| match SIGNALS.fetch_add(1, Ordering::SeqCst) {
        0 => {
            STOP.request();
            eprintln!("\nvesselflow: stopping (press Ctrl-C twice more to quit at once)");
        }
        1 => eprintln!("\nvesselflow: stopping, removing temporary files (press Ctrl-C again to quit at once)"),
        _ => {
            for dir in STAGING.lock().unwrap_or_else(|e| e.into_inner()).iter() {
                let _ = std::fs::remove_dir_all(dir);
            }
            std::process::exit(EXIT_INTERRUPTED);
        }
    });
    run_with(args, &STOP)
}

/// Run the command line `args` (program name first) and return the exit code.
/// Installs no signal handler: the run stops (exit 130, no output) soon after
/// `stop` is requested, from another thread or a signal handler; the stages poll
/// it. The Python bindings raise it when Python sees Ctrl-C, so Ctrl-C works in the
/// console script too.
///
/// A panic is caught here and reported as an internal error (exit 1, one line).
pub fn run_with<I, T>(args: I, stop: &Stop) -> i32
where
    I: IntoIterator<Item = T>,
    T: Into<OsString> + Clone,
{
    let context = RefCell::new(String::from("reading the command line"));
    let outcome = {
        let _quiet = vesselflow::error::quiet_panics();
        std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            args::parse(args).and_then(|parsed| match parsed {
                Parsed::Exit { text, to_stderr, code } => {
                    if to_stderr {
                        eprint!("{text}");
                    } else {
                        print!("{text}");
                    }
                    Ok(code)
                }
                Parsed::Run(task, verbosity) => execute(*task, verbosity, stop, &context).map(|()| 0),
            })
        }))
        .unwrap_or_else(|payload| {
            let message = vesselflow::error::panic_message(payload.as_ref()).replace('\n', " ");
            let e = vesselflow::Error::Internal(format!("{message} ({})", context.borrow()));
            Err(Failure::Run(e.to_string()))
        })
    };
    match outcome {
        Ok(code) => code,
        Err(failure) => {
            eprintln!("vesselflow: error: {}", failure.message());
            failure.code()
        }
    }
}

fn execute(task: Task, verbosity: Verbosity, stop: &Stop, context: &RefCell<String>) -> Result<(), Failure> {
    match task {
        Task::Skeletonize { input, output, spacing, rule, plot, params, key, coordinates } => {
            *context.borrow_mut() = format!("input {}", input.display());
            // Refuse a bad output path before reading or computing anything.
            vesselflow_io::check_graph_output(&output)?;
            if let Some(path) = &plot {
                plot::check_output(path)?;
            }
            let skeletonizer = Skeletonizer::new(params)?;
            // The reader checks what the file declares against the same budget as the run.
            let limits = match skeletonizer.params().max_memory {
                None => vesselflow_io::ReadLimits::for_this_process(),
                Some(0) => vesselflow_io::ReadLimits::new(u64::MAX),
                Some(bytes) => vesselflow_io::ReadLimits::new(bytes),
            };
            let volume = vesselflow_io::read_volume_key(&input, key.as_deref(), spacing, rule, limits)?;
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
            *context.borrow_mut() = format!(
                "input {}, shape {} x {} x {}, spacing {:?}",
                input.display(),
                shape[0],
                shape[1],
                shape[2],
                volume.spacing
            );
            let skel = skeletonize(&skeletonizer, volume.mask.view(), volume.spacing, &mut reporter, stop)?;
            let plot = plot.as_deref().map(|path| (path, volume.mask.view(), volume.spacing));
            // The plot shows the run's own frame (array axes); the graph file the one asked for.
            let mut info = vesselflow_io::run_info_json(&skel.info);
            let framed = match coordinates {
                vesselflow_io::Coordinates::Array => None,
                _ => {
                    let mut framed = skel.clone();
                    let frame =
                        vesselflow_io::to_frame(&mut framed.positions, skel.spacing, coordinates, &volume.affine)
                            .map_err(|e| Failure::Run(format!("--coordinates {coordinates}: {e}")))?;
                    if let Some(warning) = frame.warning {
                        eprintln!("vesselflow: warning: --coordinates {coordinates}: {warning}");
                    }
                    framed.spacing = frame.spacing;
                    vesselflow_io::frame_info(&mut info, coordinates, &volume.affine);
                    Some(framed)
                }
            };
            let graph = (output.as_path(), framed.as_ref().unwrap_or(&skel), &info);
            save(Some(graph), plot, &skel, skeletonizer.params(), &reporter, stop)?;
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
            *context.borrow_mut() = format!("built-in demo volume, shape {:?}, spacing [1.0, 1.0, 1.0]", mask.dim());
            let mut reporter = Reporter::new(verbosity);
            let started = Instant::now();
            let skel = skeletonize(&skeletonizer, mask.view(), [1.0; 3], &mut reporter, stop)?;
            let seconds = started.elapsed().as_secs_f64();
            let plot_of = plot.as_deref().map(|path| (path, mask.view(), [1.0; 3]));
            let info = vesselflow_io::run_info_json(&skel.info);
            let graph = output.as_deref().map(|path| (path, &skel, &info));
            save(graph, plot_of, &skel, skeletonizer.params(), &reporter, stop)?;
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
                report::ending(info),
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
    stop: &Stop,
) -> Result<Skeleton, Failure> {
    if stop.is_requested() {
        return Err(Failure::Interrupted);
    }
    // `max_memory` left at "auto": what this process may still use, mask read.
    let limited;
    let skeletonizer = match skeletonizer.params().max_memory {
        Some(_) => skeletonizer,
        None => {
            let mut params = skeletonizer.params().clone();
            params.max_memory = Some(vesselflow_io::budget::usable_memory().unwrap_or(0));
            limited = Skeletonizer::new(params)?;
            &limited
        }
    };
    let result = skeletonizer.run_with_stop(mask, spacing, stop, &mut |p| {
        reporter.observe(p);
        !stop.is_requested()
    });
    reporter.finish();
    let skel = result?;
    reporter.run_details(&skel.info);
    reporter.conclude(&skel);
    Ok(skel)
}

/// A temporary directory beside an output file, where the file is written before it
/// is renamed into place; removed (with anything left in it) when dropped, and
/// listed in [`STAGING`] meanwhile so that a forced exit can remove it too.
struct Staging {
    dir: Option<TempDir>,
    staged: PathBuf,
    target: PathBuf,
}

impl Staging {
    fn beside(target: &Path) -> Result<Staging, Failure> {
        let parent = match target.parent() {
            Some(p) if !p.as_os_str().is_empty() => p,
            _ => Path::new("."),
        };
        let dir = tempfile::Builder::new()
            .prefix(".vesselflow-")
            .suffix(".tmp")
            .tempdir_in(parent)
            .map_err(|e| Failure::Run(format!("cannot write {}: {e}", target.display())))?;
        STAGING.lock().unwrap_or_else(|e| e.into_inner()).push(dir.path().to_path_buf());
        // The same file name, so that the writer picks the format from its extension.
        let name = target.file_name().map_or_else(|| "output".into(), |n| n.to_owned());
        let staged = dir.path().join(name);
        Ok(Staging { dir: Some(dir), staged, target: target.to_path_buf() })
    }

    /// Move the staged output to its destination: every path a graph format writes
    /// (the `.csv` pair together, a `.precomputed` folder), or the one file.
    fn publish(&self) -> Result<(), Failure> {
        let (staged, targets) = match vesselflow_io::GraphFormat::from_path(&self.target) {
            Some(format) => (format.outputs(&self.staged), format.outputs(&self.target)),
            None => (vec![self.staged.clone()], vec![self.target.clone()]),
        };
        vesselflow_io::replace_all(&staged, &targets).map_err(|e| rename_in_error(e.to_string(), self))
    }
}

impl Drop for Staging {
    fn drop(&mut self) {
        if let Some(dir) = self.dir.take() {
            let path = dir.path().to_path_buf();
            drop(dir);
            STAGING.lock().unwrap_or_else(|e| e.into_inner()).retain(|p| *p != path);
        }
    }
}

/// Write the graph (`(path, graph, run record)`, if given) and the `--plot` picture
/// of `skel` (if asked), each first to a temporary file beside its destination; only
/// when both are complete and no interruption has arrived are they renamed into
/// place. On any failure, panic or interruption the temporary files are removed and
/// the previous files stay.
fn save(
    graph: Option<(&Path, &Skeleton, &vesselflow_io::serde_json::Value)>,
    plot: Option<(&Path, ArrayView3<'_, u8>, [f64; 3])>,
    skel: &Skeleton,
    params: &Params,
    reporter: &Reporter,
    stop: &Stop,
) -> Result<(), Failure> {
    let interrupted = || if stop.is_requested() { Err(Failure::Interrupted) } else { Ok(()) };
    interrupted()?;
    let (graph, out) = match graph {
        Some((path, out, info)) => (Some(Staging::beside(path)?), Some((out, info))),
        None => (None, None),
    };
    let plot = plot.map(|(path, mask, spacing)| Staging::beside(path).map(|s| (s, mask, spacing))).transpose()?;
    if let (Some(g), Some((out, info))) = (&graph, out) {
        vesselflow_io::write_skeleton(&g.staged, out, params, info).map_err(|e| rename_in_error(e.to_string(), g))?;
    }
    interrupted()?;
    let mut bar = None;
    if let Some((p, mask, spacing)) = &plot {
        vesselflow::pipeline::debug_panic("plot");
        let picture = plot::render(*mask, *spacing, skel);
        plot::write_png(&p.staged, &picture.image).map_err(|e| match e {
            Failure::Run(m) => Failure::Run(rename_in_message(m, p)),
            other => other,
        })?;
        bar = Some(match picture.radius_range {
            Some([lo, hi]) => format!("colour bar: edge radius {lo:.4} (bottom) to {hi:.4} (top), viridis"),
            None => "no edges to draw".to_string(),
        });
    }
    interrupted()?;
    if let Some(g) = &graph {
        g.publish()?;
        reporter.line(&format!(
            "vesselflow: wrote {} ({} nodes, {} edges)",
            g.target.display(),
            skel.len(),
            skel.edges.len()
        ));
    }
    if let (Some((p, _, _)), Some(bar)) = (&plot, bar) {
        p.publish()?;
        reporter.line(&format!("vesselflow: wrote {} ({bar})", p.target.display()));
    }
    Ok(())
}

/// An error about a staged file, told about its destination instead.
fn rename_in_message(message: String, s: &Staging) -> String {
    message.replace(&s.staged.display().to_string(), &s.target.display().to_string())
}

fn rename_in_error(message: String, s: &Staging) -> Failure {
    Failure::Run(rename_in_message(message, s))
}
