//! Ctrl-C and SIGTERM. While a training loop watches ([`Watch`]), the first signal asks it to stop at
//! the end of its step, write its checkpoint and summary, and exit; at any other moment, or on a second
//! signal, the process exits at once (every file it writes is replaced atomically, so none is left
//! half-written).

use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use crate::failure::Failure;

/// The exit status of a run stopped by a signal (128 + SIGINT, as shells report it).
pub const EXIT_STATUS: u8 = 130;

static REQUESTED: AtomicBool = AtomicBool::new(false);
static WATCHERS: AtomicUsize = AtomicUsize::new(0);

/// What the signal handler does (the command line installs it, once, at start; without it a signal ends
/// the process at once): asks the watching training loop to stop, or exits when none watches or when asked
/// a second time.
pub fn on_signal() {
    if WATCHERS.load(Ordering::SeqCst) == 0 || REQUESTED.swap(true, Ordering::SeqCst) {
        std::process::exit(i32::from(EXIT_STATUS));
    }
    crate::console::note("\ninterrupted: stopping after this step (press Ctrl-C again to quit at once)");
}

/// Asks the watching training loop to stop at the end of its step, as a first signal does, without ever
/// exiting the process (for hosts such as Python that catch the signal themselves); whether one watched.
pub fn request_stop() -> bool {
    REQUESTED.store(true, Ordering::SeqCst);
    WATCHERS.load(Ordering::SeqCst) > 0
}

/// A training loop's claim on the signal while it lives.
pub struct Watch(());

impl Watch {
    /// Starts watching for the signal; the first watcher starts with no stop asked (a stop asked of an
    /// earlier run in the same process, as from Python, does not carry over).
    pub fn start() -> Watch {
        if WATCHERS.fetch_add(1, Ordering::SeqCst) == 0 {
            REQUESTED.store(false, Ordering::SeqCst);
        }
        Watch(())
    }

    /// Whether a signal asked the run to stop.
    pub fn requested(&self) -> bool {
        REQUESTED.load(Ordering::SeqCst)
    }
}

impl Drop for Watch {
    fn drop(&mut self) {
        WATCHERS.fetch_sub(1, Ordering::SeqCst);
    }
}

/// The outcome of a training run stopped by a signal after `step` steps, saying where its checkpoint is.
pub fn stopped(step: u32, checkpoint: Option<&Path>) -> Failure {
    let kept = match checkpoint {
        Some(path) => format!(
            "the checkpoint '{}' holds it; run again with --resume to continue",
            path.display()
        ),
        None => "no checkpoint is written (checkpoint: none)".to_string(),
    };
    Failure::Interrupted(format!("training stopped at step {step}: {kept}"))
}
