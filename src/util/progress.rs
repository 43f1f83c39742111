//! Progress as typed events. Library code never prints: long work reports
//! `Event`s to a `Progress` sink it is given. `Console` is the one sink that
//! writes: indicatif bars on a terminal, plain periodic lines otherwise (logs,
//! CI); `Quiet` drops everything (tests, library users with their own UI).

use std::io::IsTerminal;
use std::sync::Mutex;

use indicatif::{ProgressBar, ProgressStyle};

use crate::util::costs::{self, Ledger, Work};

/// The long-running parts of the pipeline.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Photorealistic fitting (steps).
    Fit,
    /// Rendering the test views and comparing them with the photos.
    Evaluate,
    /// Rendering the frames of a camera path.
    Render,
    /// The stylization's colour refit (steps).
    Refit,
    /// Content renders, VGG16 features, TCM matches of every view.
    Guides,
    /// The stylization's image epochs (one step per view).
    ImageEpochs,
    /// Restylizations of `refnpr eval --robustness`.
    Robustness,
    /// The stages of `refnpr capture` (photos, COLMAP's features, matches, mapping, undistortion).
    Capture,
    /// The Gauss-Newton iterations of `refnpr refine-poses`.
    RefinePoses,
}

impl std::fmt::Display for Phase {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Phase::Fit => "fit",
            Phase::Evaluate => "evaluate",
            Phase::Render => "render",
            Phase::Refit => "refit",
            Phase::Guides => "content features",
            Phase::ImageEpochs => "image epochs",
            Phase::Robustness => "robustness",
            Phase::Capture => "capture",
            Phase::RefinePoses => "refine poses",
        })
    }
}

/// What long work reports.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    /// A phase of `total` steps starts, `done` of them already done (a resumed run).
    Start { phase: Phase, done: usize, total: usize },
    /// `done` of `total` steps are done; `message` holds the current figures.
    Step { phase: Phase, done: usize, total: usize, message: String },
    /// The phase ended after `seconds`.
    PhaseDone { phase: Phase, seconds: f64 },
    /// What is being done or was written (a line for the user).
    Info(String),
    /// Something that may give a poor result, though the work goes on.
    Warning(String),
    /// A figure for `--verbose` output (host-device traffic per phase).
    Detail(String),
    /// A long job (`train`, `stylize`) starts: what it will do, for an
    /// estimate of its time and memory (`util::costs`).
    JobStart(Work),
    /// The job of the last `JobStart` finished.
    JobDone,
}

/// Where events go.
pub trait Progress: Sync {
    fn event(&self, event: Event);

    fn info(&self, message: String) {
        self.event(Event::Info(message));
    }

    fn warning(&self, message: String) {
        self.event(Event::Warning(message));
    }
}

/// Drops every event.
pub struct Quiet;

impl Progress for Quiet {
    fn event(&self, _: Event) {}
}

/// Lines printed per phase when stderr is not a terminal.
const PLAIN_LINES_PER_PHASE: usize = 20;

/// Bars on a terminal, plain lines on stderr otherwise.
pub struct Console {
    terminal: bool,
    /// Whether `Event::Detail` lines are printed.
    verbose: bool,
    /// The phase whose bar is shown, and the bar.
    bar: Mutex<Option<(Phase, ProgressBar)>>,
    /// Where finished jobs' costs are kept and estimates come from.
    costs: Option<Ledger>,
    /// The running job and when it started.
    job: Mutex<Option<(Work, std::time::Instant)>>,
}

impl Default for Console {
    fn default() -> Self {
        Self {
            terminal: std::io::stderr().is_terminal(),
            verbose: false,
            bar: Mutex::new(None),
            costs: None,
            job: Mutex::new(None),
        }
    }
}

impl Console {
    /// A console that also prints the `Event::Detail` lines.
    pub fn verbose(verbose: bool) -> Self {
        Self { verbose, ..Self::default() }
    }

    /// Prints an estimate at the start of each long job and records each
    /// finished job's time and memory in `ledger` (the `refnpr` binary's console).
    pub fn with_costs(self, ledger: Option<Ledger>) -> Self {
        Self { costs: ledger, ..self }
    }
}

#[allow(clippy::print_stderr)] // the one sink that prints
impl Console {
    fn with_bar(&self, f: impl FnOnce(&mut Option<(Phase, ProgressBar)>)) {
        let mut slot = self.bar.lock().unwrap_or_else(|e| e.into_inner());
        f(&mut slot);
    }

    /// Prints a line above the bar (or plainly).
    fn line(&self, text: String) {
        self.with_bar(|bar| match bar {
            Some((_, b)) => b.println(text),
            None => eprintln!("{text}"),
        });
    }

    /// Shows `phase`'s bar at `done` of `total`: a phase's first event, or
    /// one that comes back after another phase took the line (the smooth
    /// update's guides inside the image epochs), gets a fresh bar.
    fn show(&self, phase: Phase, done: usize, total: usize, message: Option<String>) {
        self.with_bar(|bar| {
            if bar.as_ref().is_none_or(|(p, _)| *p != phase) {
                let b = ProgressBar::new(total as u64);
                b.set_style(
                    ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} {msg}")
                        .expect("valid template")
                        .progress_chars("=> "),
                );
                if let Some((_, old)) = bar.replace((phase, b)) {
                    old.finish_and_clear();
                }
            }
            let (_, b) = bar.as_ref().expect("a bar was just set");
            b.set_position(done as u64);
            if let Some(m) = message {
                b.set_message(m);
            }
        });
    }
}

#[allow(clippy::print_stderr)] // the one sink that prints
impl Progress for Console {
    fn event(&self, event: Event) {
        match event {
            Event::Start { phase, done, total } if self.terminal => self.show(phase, done, total, None),
            Event::Start { .. } => {}
            Event::Step { phase, done, total, message } if self.terminal => {
                self.show(phase, done, total, Some(message))
            }
            Event::Step { phase, done, total, message } => {
                if done == total || done % (total / PLAIN_LINES_PER_PHASE).max(1) == 0 {
                    eprintln!("{phase} {done}/{total} {message}");
                }
            }
            Event::PhaseDone { phase, seconds } => {
                self.with_bar(|bar| {
                    if let Some((_, b)) = bar.take() {
                        b.finish_and_clear();
                    }
                });
                eprintln!("{phase} done in {seconds:.1} s");
            }
            Event::Info(text) => self.line(text),
            Event::Warning(text) => self.line(format!("warning: {text}")),
            Event::Detail(text) if self.verbose => self.line(text),
            Event::Detail(_) => {}
            Event::JobStart(work) => {
                if let Some(estimate) = self.costs.as_ref().and_then(|l| l.estimate(&work)) {
                    self.line(estimate.to_string());
                }
                *self.job.lock().unwrap_or_else(|e| e.into_inner()) = Some((work, std::time::Instant::now()));
            }
            Event::JobDone => self.record_job(),
        }
    }
}

#[allow(clippy::print_stderr)] // the one sink that prints
impl Console {
    /// Records the finished job's cost (a resumed job did part of the work: not recorded).
    fn record_job(&self) {
        let job = self.job.lock().unwrap_or_else(|e| e.into_inner()).take();
        let (Some(ledger), Some((work, started))) = (&self.costs, job) else { return };
        let Some(peak_mb) = crate::util::memory::peak_rss_mb() else { return };
        if work.resumed {
            return;
        }
        let record = costs::finished(work, started.elapsed().as_secs_f64(), peak_mb);
        if let Err(e) = ledger.record(&record) {
            eprintln!("warning: cannot record this job's cost in {}: {e}", ledger.path().display());
        }
    }
}

/// Warnings of one run: each is reported to the sink as it happens and kept
/// for the run's report file.
pub struct WarningLog<'a> {
    progress: &'a dyn Progress,
    list: Vec<String>,
}

impl<'a> WarningLog<'a> {
    pub fn new(progress: &'a dyn Progress) -> Self {
        Self { progress, list: Vec::new() }
    }

    /// The sink the warnings go to.
    pub fn progress(&self) -> &'a dyn Progress {
        self.progress
    }

    pub fn push(&mut self, message: String) {
        self.progress.warning(message.clone());
        self.list.push(message);
    }

    /// Keeps warnings that were already reported (a stage's report).
    pub fn extend_reported(&mut self, reported: impl IntoIterator<Item = String>) {
        self.list.extend(reported);
    }

    pub fn into_vec(self) -> Vec<String> {
        self.list
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Keeps the events it is given.
    #[derive(Default)]
    struct Collect(Mutex<Vec<Event>>);

    impl Progress for Collect {
        fn event(&self, event: Event) {
            self.0.lock().unwrap().push(event);
        }
    }

    #[test]
    fn a_warning_log_reports_each_warning_once_and_keeps_them_all() {
        let sink = Collect::default();
        let mut log = WarningLog::new(&sink);
        log.push("first".into());
        log.extend_reported(["reported elsewhere".to_string()]);
        log.push("second".into());
        assert_eq!(log.into_vec(), ["first", "reported elsewhere", "second"]);
        let events = sink.0.into_inner().unwrap();
        assert_eq!(events, [Event::Warning("first".into()), Event::Warning("second".into())]);
    }
}
