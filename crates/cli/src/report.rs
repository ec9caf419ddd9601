//! What the program tells the user on stderr while and after it runs: a live
//! spinner on a terminal, one line per finished stage otherwise (logs, pipes),
//! the per-stage timings, and with `--verbose` every contraction iteration.

use crate::args::Verbosity;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::io::IsTerminal;
use std::time::Duration;
use vesselflow::{Progress, RunInfo};

/// Receives the core's [`Progress`] reports and prints what the verbosity asks for.
pub(crate) struct Reporter {
    verbosity: Verbosity,
    /// The live spinner, when stderr is a terminal and not `--quiet`.
    spinner: Option<ProgressBar>,
    /// Latest report, printed as a line when its stage ends (no spinner only).
    last: Option<Progress>,
}

/// One line about where the run is, in the words of the method.
fn describe(p: &Progress) -> String {
    match p.stage {
        "edt" => "edt: distance transform done".to_string(),
        "grid" => format!("grid: {} nodes", p.nodes),
        "contract" => {
            format!("contract: iteration {}, {} nodes, cycle area / stop level {:.3}", p.iteration, p.nodes, p.measure)
        }
        "refine" => {
            let n = p.measure as u64;
            format!(
                "refine: iteration {}, {} nodes, {n} cycle{} collapsed",
                p.iteration,
                p.nodes,
                if n == 1 { "" } else { "s" }
            )
        }
        "output" => format!("output: {} nodes", p.nodes),
        other => format!("{other}: iteration {}, {} nodes, measure {}", p.iteration, p.nodes, p.measure),
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

    /// Per-stage timings, and with `--verbose` the contraction history.
    pub(crate) fn run_details(&self, info: &RunInfo) {
        if self.verbosity == Verbosity::Verbose {
            self.line(&iteration_table(info));
        }
        self.line(&timing_table(info));
    }
}

/// The seconds of every stage and their total.
fn timing_table(info: &RunInfo) -> String {
    let mut out = String::from("stage        seconds\n");
    for t in &info.stage_seconds {
        out.push_str(&format!("{:<10} {:>9.3}\n", t.stage, t.seconds));
    }
    let total: f64 = info.stage_seconds.iter().map(|t| t.seconds).sum();
    out.push_str(&format!("{:<10} {:>9.3}", "total", total));
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
