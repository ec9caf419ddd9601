//! What the program tells the user on stderr while and after it runs: a live
//! spinner on a terminal, one line per finished stage otherwise (logs, pipes),
//! the per-stage timings, and with `--verbose` every contraction iteration.

use crate::args::Verbosity;
use crate::summary::GraphSummary;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::io::IsTerminal;
use std::time::Duration;
use vesselflow::{Progress, RunInfo, Skeleton};

/// Receives the core's [`Progress`] reports and prints what the verbosity asks for.
pub(crate) struct Reporter {
    verbosity: Verbosity,
    /// The live spinner, when stderr is a terminal and not `--quiet`.
    spinner: Option<ProgressBar>,
    /// Latest report, printed as a line when its stage ends (no spinner only).
    last: Option<Progress>,
}

/// One line about where the run is, in the words of the method. The core's
/// `measure` is the contraction's convergence measure (NaN in the other stages).
fn describe(p: &Progress) -> String {
    match p.stage {
        "edt" => "edt: distance transform done".to_string(),
        "grid" => format!("grid: {} nodes", p.nodes),
        "contract" => {
            format!("contract: iteration {}, {} nodes, cycle area / stop level {:.3}", p.iteration, p.nodes, p.measure)
        }
        "output" => format!("output: {} nodes", p.nodes),
        other => format!("{other}: iteration {}, {} nodes", p.iteration, p.nodes),
    }
}

/// How the contraction ended: converged, stalled, or stopped at the cap.
pub(crate) fn ending(info: &RunInfo) -> &'static str {
    if info.foreground_voxels == 0 {
        "empty mask"
    } else if info.converged {
        "converged"
    } else if info.stalled {
        "stalled near convergence"
    } else {
        "stopped at --max-iterations"
    }
}

impl Reporter {
    pub(crate) fn new(verbosity: Verbosity) -> Reporter {
        let live = verbosity != Verbosity::Quiet && std::io::stderr().is_terminal();
        let spinner = live.then(|| {
            let bar = ProgressBar::with_draw_target(None, ProgressDrawTarget::stderr());
            bar.set_style(
                ProgressStyle::with_template("{spinner} [{elapsed_precise}] {msg}")
                    .unwrap_or_else(|_| ProgressStyle::default_spinner()),
            );
            bar.enable_steady_tick(Duration::from_millis(120));
            bar.set_message("starting");
            bar
        });
        Reporter { verbosity, spinner, last: None }
    }

    /// Print a line on stderr without tearing the spinner (nothing when quiet).
    pub(crate) fn line(&self, text: &str) {
        if self.verbosity == Verbosity::Quiet {
            return;
        }
        match &self.spinner {
            Some(bar) => bar.suspend(|| eprintln!("{text}")),
            None => eprintln!("{text}"),
        }
    }

    /// Take one report from the core.
    pub(crate) fn observe(&mut self, p: &Progress) {
        if let Some(bar) = &self.spinner {
            bar.set_message(describe(p));
            return;
        }
        if let Some(last) = &self.last {
            if last.stage != p.stage {
                self.line(&describe(last));
            }
        }
        self.last = Some(p.clone());
    }

    /// End of the run (finished or not): clear the spinner or print the last stage.
    pub(crate) fn finish(&mut self) {
        if let Some(bar) = self.spinner.take() {
            bar.finish_and_clear();
        }
        if let Some(last) = self.last.take() {
            self.line(&describe(&last));
        }
    }

    /// The end of a finished run: how the contraction ended and the graph's counts
    /// (unless `--quiet`), after a warning, printed even with `--quiet`, when the mask
    /// is empty or the contraction stopped at `--max-iterations`.
    pub(crate) fn conclude(&self, skel: &Skeleton) {
        let info = &skel.info;
        if info.foreground_voxels == 0 {
            // Not an error (a block of a larger volume may hold no vessel), but an empty
            // file usually means a wrong input.
            eprintln!("vesselflow: warning: the mask is empty: the graph has no nodes");
            return;
        }
        if !(info.converged || info.stalled) {
            // The graph may still hold unreduced knots.
            eprintln!(
                "vesselflow: warning: the contraction stopped at --max-iterations {} before converging \
                 (short-cycle area {:.3} times the stop level); raise --max-iterations or lower --gamma",
                info.iterations,
                info.area_per_iteration.last().copied().unwrap_or(0.0) / info.area_reference.max(f64::MIN_POSITIVE),
            );
        }
        let n = info.iterations;
        let iterations = format!("{n} iteration{}", if n == 1 { "" } else { "s" });
        self.line(&format!("vesselflow: {} after {iterations}: {}", ending(info), GraphSummary::of(skel).line()));
    }

    /// Per-stage timings, and with `--verbose` the contraction history.
    pub(crate) fn run_details(&self, info: &RunInfo) {
        if self.verbosity == Verbosity::Verbose {
            self.line(&iteration_table(info));
        }
        self.line(&timing_table(info));
    }
}

/// The core's timed parts of the contraction stage (Algorithm 1): the rest of its
/// timed stages are the stages of the progress reports.
const CONTRACT_PARTS: [&str; 4] = ["laplacian", "solve", "decimate", "cycles"];

/// The seconds of every stage and their total; the contraction's parts are listed,
/// indented, under one `contract` row, so that the stages read as in the progress lines.
fn timing_table(info: &RunInfo) -> String {
    let row = |name: &str, seconds: f64| format!("{name:<12} {seconds:>9.3}\n");
    let parts: Vec<_> = info.stage_seconds.iter().filter(|t| CONTRACT_PARTS.contains(&t.stage)).collect();
    let mut out = String::from("stage          seconds\n");
    let mut contract_done = false;
    for t in &info.stage_seconds {
        if !CONTRACT_PARTS.contains(&t.stage) {
            out.push_str(&row(t.stage, t.seconds));
        } else if !contract_done {
            contract_done = true;
            out.push_str(&row("contract", parts.iter().map(|p| p.seconds).sum()));
            for p in &parts {
                out.push_str(&row(&format!("  {}", p.stage), p.seconds));
            }
        }
    }
    let total: f64 = info.stage_seconds.iter().map(|t| t.seconds).sum();
    out.push_str(&row("total", total));
    out.pop();
    out
}

/// One row per contraction iteration (row 0: the initial grid graph): nodes after
/// it, conjugate-gradient iterations it took, and its short-cycle area over the
/// stop level `info.area_reference` (= `stop_ratio` x reference area; the run
/// stops at the first iteration where this is <= 1).
fn iteration_table(info: &RunInfo) -> String {
    let mut out = format!(
        "contraction: stops when the short-cycle area reaches the stop level {}\n\
         iteration      nodes  cg iterations  area / stop level\n",
        info.area_reference
    );
    let rows = info.nodes_per_iteration.len().max(info.area_per_iteration.len());
    for t in 0..rows {
        let cell = |v: Option<String>| v.unwrap_or_else(|| "-".to_string());
        let nodes = cell(info.nodes_per_iteration.get(t).map(usize::to_string));
        let cg = cell(t.checked_sub(1).and_then(|i| info.cg_iterations.get(i)).map(usize::to_string));
        let ratio = cell(
            info.area_per_iteration
                .get(t)
                .filter(|_| info.area_reference > 0.0)
                .map(|a| format!("{:.3e}", a / info.area_reference)),
        );
        out.push_str(&format!("{t:>9} {nodes:>10} {cg:>14} {ratio:>18}\n"));
    }
    out.pop();
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use vesselflow::StageTime;

    #[test]
    fn the_contraction_parts_are_timed_under_one_contract_row() {
        let stage_seconds = [("edt", 0.5), ("grid", 0.25), ("cycles", 1.0), ("laplacian", 2.0), ("solve", 4.0)]
            .into_iter()
            .chain([("decimate", 8.0), ("refine", 0.125), ("output", 0.0625)])
            .map(|(stage, seconds)| StageTime { stage, seconds })
            .collect();
        let table = timing_table(&RunInfo { stage_seconds, ..Default::default() });
        let rows: Vec<(&str, f64)> = table
            .lines()
            .skip(1)
            .map(|l| {
                let (name, seconds) = l.trim_end().rsplit_once(' ').unwrap();
                (name.trim_end(), seconds.parse().unwrap())
            })
            .collect();
        let expected = [
            ("edt", 0.5),
            ("grid", 0.25),
            ("contract", 15.0),
            ("  cycles", 1.0),
            ("  laplacian", 2.0),
            ("  solve", 4.0),
            ("  decimate", 8.0),
            ("refine", 0.125),
            ("output", 0.0625),
            ("total", 15.9375),
        ];
        assert_eq!(rows.len(), expected.len(), "{table}");
        for ((name, seconds), (want, want_seconds)) in rows.into_iter().zip(expected) {
            assert_eq!(name, want, "{table}");
            assert!((seconds - want_seconds).abs() < 1e-3, "{table}");
        }
    }

    #[test]
    fn the_ending_names_what_stopped_the_contraction() {
        let info = |voxels, converged, stalled| RunInfo {
            foreground_voxels: voxels,
            converged,
            stalled,
            ..Default::default()
        };
        assert_eq!(ending(&info(0, true, false)), "empty mask");
        assert_eq!(ending(&info(9, true, false)), "converged");
        assert_eq!(ending(&info(9, false, true)), "stalled near convergence");
        assert_eq!(ending(&info(9, false, false)), "stopped at --max-iterations");
    }

    #[test]
    fn only_the_contraction_line_shows_the_measure() {
        let line = |stage, measure| describe(&Progress { stage, iteration: 3, nodes: 40, measure });
        assert_eq!(line("contract", 2.5), "contract: iteration 3, 40 nodes, cycle area / stop level 2.500");
        assert_eq!(line("refine", f64::NAN), "refine: iteration 3, 40 nodes");
        assert_eq!(line("grid", f64::NAN), "grid: 40 nodes");
    }
}
