//! What a caller follows of running blocks: progress bars (the command line draws them on the terminal; a
//! library user gets none unless it supplies some) and a [`TrainingObserver`] that sees each training step
//! (the live viewer of `nerfjit run --view`).

use serde_json::Value;

use crate::interrupt::Watch;

/// A bar of a long task's progress.
pub trait ProgressBar: Send + Sync {
    /// Sets how far the task is.
    fn set_position(&self, position: u64);
    /// Sets the bar's message.
    fn set_message(&self, _message: String) {}
    /// Prints a line above the bar (or to standard error where no bar is drawn).
    fn println(&self, line: String) {
        crate::console::note(&line);
    }
    /// Removes the bar of a task that is done.
    fn finish_and_clear(&self) {}
    /// Leaves the bar as it is (the task failed).
    fn abandon(&self) {}
}

/// What a progress bar counts.
#[derive(Clone, Copy, Debug)]
pub enum BarKind<'a> {
    /// The steps of a training loop, e.g. "training".
    Steps(&'a str),
    /// The frames of a render, e.g. "rendering".
    Frames(&'a str),
}

/// Makes the progress bars of a run.
pub trait ProgressBars: Sync {
    /// A bar of `len` steps or frames.
    fn bar(&self, len: u64, kind: BarKind) -> Box<dyn ProgressBar>;
}

/// No bars: lines meant to go above a bar go to standard error.
#[derive(Clone, Copy, Debug, Default)]
pub struct NoBars;

struct NoBar;

impl ProgressBar for NoBar {
    fn set_position(&self, _position: u64) {}
}

impl ProgressBars for NoBars {
    fn bar(&self, _len: u64, _kind: BarKind) -> Box<dyn ProgressBar> {
        Box::new(NoBar)
    }
}

/// Follows a training run step by step (the live viewer of `nerfjit run --view`).
pub trait TrainingObserver: Sync {
    /// Called by the training loop after step `done` with the params and the step's progress `record` (if
    /// any; `last` at the run's last step). It may hold the run (a paused viewer) until `watch` sees
    /// Ctrl-C.
    fn after_step(&self, done: u32, last: bool, params: &[f32], record: Option<Value>, watch: &Watch);
}
