//! Opt-in accounting of where a kernel's time goes: the tiled kernels time their phases (grid reads and
//! scatters, matrix products, outer products, the compiled elementwise code) when [`enable`]d, and callers
//! add their own phases (the optimizer). For benchmarks: off by default, and then a kernel checks one flag
//! per call.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// A part of the work whose time is accounted.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// Reads of grid encodings (the gathers of hashgrid and grid).
    GridReads,
    /// Scatters of cotangents into grid encodings (their param gradients).
    GridScatters,
    /// Matrix products of dense layers (forward, and the input cotangents backward).
    Products,
    /// Outer products: the weight gradients of dense layers.
    OuterProducts,
    /// The compiled elementwise code between them (activations, losses, copies in and out).
    Elementwise,
    /// The optimizer's update of the params.
    Optimizer,
    /// Whole training steps, as wall time (not summed over threads): what the others are shares of.
    Steps,
}

impl Phase {
    /// Every phase, in the order of [`Times::nanos`].
    pub const ALL: [Phase; 7] = [
        Phase::GridReads,
        Phase::GridScatters,
        Phase::Products,
        Phase::OuterProducts,
        Phase::Elementwise,
        Phase::Optimizer,
        Phase::Steps,
    ];

    /// A short name for tables.
    pub fn name(self) -> &'static str {
        match self {
            Phase::GridReads => "grid reads",
            Phase::GridScatters => "grid scatters",
            Phase::Products => "products",
            Phase::OuterProducts => "weight gradients",
            Phase::Elementwise => "elementwise",
            Phase::Optimizer => "optimizer",
            Phase::Steps => "steps",
        }
    }
}

static ENABLED: AtomicBool = AtomicBool::new(false);
static NANOS: [AtomicU64; 7] = [const { AtomicU64::new(0) }; 7];

/// Turns the accounting on or off (for the whole process).
pub fn enable(on: bool) {
    ENABLED.store(on, Ordering::Relaxed);
}

/// Whether the accounting is on.
pub fn enabled() -> bool {
    ENABLED.load(Ordering::Relaxed)
}

/// Adds `time` to `phase` (summed over threads) if the accounting is on.
pub fn record(phase: Phase, time: Duration) {
    if enabled() {
        NANOS[phase as usize].fetch_add(time.as_nanos() as u64, Ordering::Relaxed);
    }
}

/// The time accounted to each phase, summed over threads (but [`Phase::Steps`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Times {
    /// Nanoseconds per phase, in the order of [`Phase::ALL`].
    pub nanos: [u64; 7],
}

impl Times {
    /// Seconds accounted to `phase`.
    pub fn seconds(&self, phase: Phase) -> f64 {
        self.nanos[phase as usize] as f64 * 1e-9
    }
}

/// The times accounted so far, resetting them to zero.
pub fn take() -> Times {
    Times {
        nanos: std::array::from_fn(|i| NANOS[i].swap(0, Ordering::Relaxed)),
    }
}

/// A stopwatch over consecutive phases of one call: each [`Laps::lap`] gives the time since the last
/// one to a phase; [`Laps::finish`] adds the totals to the process's. Does nothing when the accounting
/// is off.
pub(crate) struct Laps {
    last: Option<Instant>,
    nanos: [u64; 7],
}

impl Laps {
    /// Starts the stopwatch if the accounting is on.
    pub(crate) fn start() -> Laps {
        Laps {
            last: enabled().then(Instant::now),
            nanos: [0; 7],
        }
    }

    /// Gives the time since the last lap (or the start) to `phase`.
    pub(crate) fn lap(&mut self, phase: Phase) {
        if let Some(last) = self.last {
            let now = Instant::now();
            self.nanos[phase as usize] += (now - last).as_nanos() as u64;
            self.last = Some(now);
        }
    }

    /// Adds this call's times to the process's.
    pub(crate) fn finish(self) {
        if self.last.is_some() {
            for (total, &n) in NANOS.iter().zip(&self.nanos) {
                total.fetch_add(n, Ordering::Relaxed);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn laps_count_only_when_enabled() {
        // One test touches the process-wide switch, so no other test races it.
        let _ = take();
        let mut laps = Laps::start();
        laps.lap(Phase::Products);
        laps.finish();
        record(Phase::Optimizer, Duration::from_millis(5));
        assert_eq!(take(), Times::default());
        enable(true);
        let mut laps = Laps::start();
        std::thread::sleep(Duration::from_millis(2));
        laps.lap(Phase::Products);
        laps.finish();
        record(Phase::Optimizer, Duration::from_millis(5));
        enable(false);
        let times = take();
        assert!(times.seconds(Phase::Products) >= 0.002, "{times:?}");
        assert_eq!(times.seconds(Phase::Optimizer), 0.005);
    }
}
