//! Opt-in accounting of where a kernel's time goes: the tiled kernels time their phases (grid reads and
//! scatters, matrix products, outer products, the compiled elementwise code) when [`enable`]d, and callers
//! add their own phases (the optimizer). Beside the time, each phase counts its work in its own unit
//! ([`Phase::unit`]), so that a benchmark can set the work against what the machine allows (a roofline).
//! For benchmarks: off by default, and then a kernel checks one flag per call.

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

    /// The unit of the work [`Times::work`] counts for this phase: floating-point operations for the
    /// products (a multiply-add is two), corners read or written for the grids (each `features` floats),
    /// bytes read and written for the optimizer, sample points for whole steps; nothing
    /// (`""`) for the elementwise code, whose work has no single measure.
    pub fn unit(self) -> &'static str {
        match self {
            Phase::GridReads | Phase::GridScatters => "corners",
            Phase::Products | Phase::OuterProducts => "FLOP",
            Phase::Optimizer => "bytes",
            Phase::Steps => "samples",
            Phase::Elementwise => "",
        }
    }
}

static ENABLED: AtomicBool = AtomicBool::new(false);
static NANOS: [AtomicU64; 7] = [const { AtomicU64::new(0) }; 7];
static WORK: [AtomicU64; 7] = [const { AtomicU64::new(0) }; 7];

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

/// Adds `amount` of work (in [`Phase::unit`]) to `phase` if the accounting is on.
pub fn count(phase: Phase, amount: u64) {
    if enabled() {
        WORK[phase as usize].fetch_add(amount, Ordering::Relaxed);
    }
}

/// The time and work accounted to each phase, the time summed over threads (but [`Phase::Steps`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Times {
    /// Nanoseconds per phase, in the order of [`Phase::ALL`].
    pub nanos: [u64; 7],
    /// Work per phase in its [`Phase::unit`], in the same order.
    pub work: [u64; 7],
}

impl Times {
    /// Seconds accounted to `phase`.
    pub fn seconds(&self, phase: Phase) -> f64 {
        self.nanos[phase as usize] as f64 * 1e-9
    }

    /// The work counted for `phase`, in its [`Phase::unit`].
    pub fn work(&self, phase: Phase) -> u64 {
        self.work[phase as usize]
    }
}

/// The times and work accounted so far, resetting them to zero.
pub fn take() -> Times {
    Times {
        nanos: std::array::from_fn(|i| NANOS[i].swap(0, Ordering::Relaxed)),
        work: std::array::from_fn(|i| WORK[i].swap(0, Ordering::Relaxed)),
    }
}

/// A stopwatch over consecutive phases of one call: each [`Laps::lap`] gives the time since the last
/// one to a phase; [`Laps::finish`] adds the totals to the process's. Does nothing when the accounting
/// is off.
pub(crate) struct Laps {
    last: Option<Instant>,
    nanos: [u64; 7],
    work: [u64; 7],
}

impl Laps {
    /// Starts the stopwatch if the accounting is on.
    pub(crate) fn start() -> Laps {
        Laps {
            last: enabled().then(Instant::now),
            nanos: [0; 7],
            work: [0; 7],
        }
    }

    /// Adds `amount` of work (in [`Phase::unit`]) to `phase`.
    pub(crate) fn count(&mut self, phase: Phase, amount: u64) {
        if self.last.is_some() {
            self.work[phase as usize] += amount;
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
            for (total, &n) in WORK.iter().zip(&self.work) {
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
        laps.count(Phase::Products, 10);
        laps.finish();
        record(Phase::Optimizer, Duration::from_millis(5));
        count(Phase::Optimizer, 7);
        assert_eq!(take(), Times::default());
        enable(true);
        let mut laps = Laps::start();
        std::thread::sleep(Duration::from_millis(2));
        laps.lap(Phase::Products);
        laps.count(Phase::Products, 10);
        laps.count(Phase::Products, 5);
        laps.finish();
        record(Phase::Optimizer, Duration::from_millis(5));
        count(Phase::Optimizer, 7);
        enable(false);
        let times = take();
        assert!(times.seconds(Phase::Products) >= 0.002, "{times:?}");
        assert_eq!(times.seconds(Phase::Optimizer), 0.005);
        assert_eq!(
            (times.work(Phase::Products), times.work(Phase::Optimizer)),
            (15, 7)
        );
        assert_eq!(take(), Times::default(), "take resets");
    }
}
