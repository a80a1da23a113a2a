//! `nerfjit.run` and `nerfjit.Trainer`: a script's blocks run as `nerfjit run` does, on a thread of their own
//! with the command line's deep stack, the GIL released while they work. A trainer's `steps(every=n)` yields
//! the training's metrics as they come. Ctrl-C asks training to stop at the end of its step (its checkpoint
//! written), then raises `KeyboardInterrupt`.

use std::path::PathBuf;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, Sender};
use std::sync::Mutex;
use std::thread::JoinHandle;
use std::time::Duration;

use nerfjit::failure::Failure;
use nerfjit::interrupt::Watch;
use nerfjit::observe::TrainingObserver;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use serde_json::Value;

use crate::{to_py, NerfjitError};

/// What a run reports to the Python thread.
enum Event {
    /// A training step's metrics, as JSON.
    Step(Value),
    /// The run ended.
    Done(Result<(), Failure>),
}

/// Sends the metrics the training logs (every 10 steps and at the last) at each multiple of `every` steps:
/// the first record at or after it, and the last.
struct Metrics {
    every: u32,
    /// The step the next record is due at.
    due: AtomicU32,
    events: Sender<Event>,
}

impl TrainingObserver for Metrics {
    fn after_step(&self, done: u32, last: bool, _params: &[f32], record: Option<Value>, _watch: &Watch) {
        let Some(Value::Object(mut record)) = record else {
            return;
        };
        if done >= self.due.load(Ordering::Relaxed) || last {
            self.due
                .store((done / self.every + 1) * self.every, Ordering::Relaxed);
            record.insert("step".into(), done.into());
            let _ = self.events.send(Event::Step(Value::Object(record)));
        }
    }
}

/// What a run does: the script, its overrides, its output folder, whether it resumes.
#[derive(Clone)]
struct RunArgs {
    script: String,
    set: Vec<String>,
    out: Option<PathBuf>,
    resume: bool,
}

/// A run on its own thread.
struct Running {
    worker: Option<JoinHandle<()>>,
    events: Option<Receiver<Event>>,
    /// The Ctrl-C that asked it to stop, raised once it has.
    interrupted: Option<PyErr>,
}

impl Running {
    /// Starts `args`, sending the metrics of every `every`-th training step when given.
    fn start(args: RunArgs, every: Option<u32>) -> PyResult<Running> {
        let (events, received) = mpsc::channel();
        let worker = std::thread::Builder::new()
            .stack_size(nerfjit::WORK_STACK_BYTES)
            .spawn(move || {
                let metrics = every.map(|every| Metrics {
                    every,
                    due: AtomicU32::new(every),
                    events: events.clone(),
                });
                let live = metrics.as_ref().map(|m| m as &dyn TrainingObserver);
                let RunArgs {
                    script,
                    set,
                    out,
                    resume,
                } = args;
                let result = nerfjit::commands::run::run(&script, &set, out.as_deref(), resume, live);
                // Said here, so that it is said however the run was stopped (Ctrl-C in the caller's code,
                // a loop left early, the interpreter exiting).
                if let Err(Failure::Interrupted(message)) = &result {
                    nerfjit::note(message);
                }
                let _ = events.send(Event::Done(result));
            })
            .map_err(|e| NerfjitError::new_err(format!("cannot start the run: {e}")))?;
        Ok(Running {
            worker: Some(worker),
            events: Some(received),
            interrupted: None,
        })
    }

    /// The next step's metrics, or `None` once the run has ended well; its error when it failed, and
    /// `KeyboardInterrupt` when Ctrl-C stopped it. Waits with the GIL released, looking for Ctrl-C every
    /// 100 ms.
    fn next(&mut self, py: Python<'_>) -> PyResult<Option<Value>> {
        loop {
            let Some(events) = self.events.take() else {
                return Ok(None);
            };
            let (events, event) = py.detach(move || {
                let event = events.recv_timeout(Duration::from_millis(100));
                (events, event)
            });
            match event {
                Ok(Event::Step(record)) => {
                    self.events = Some(events);
                    if self.interrupted.is_none() {
                        return Ok(Some(record));
                    }
                }
                Ok(Event::Done(result)) => return self.finish(py, Some(result)),
                Err(RecvTimeoutError::Disconnected) => return self.finish(py, None),
                Err(RecvTimeoutError::Timeout) => {
                    self.events = Some(events);
                    if let Err(signal) = py.check_signals() {
                        self.interrupted.get_or_insert(signal);
                    }
                    if self.interrupted.is_some() {
                        nerfjit::interrupt::request_stop();
                    }
                }
            }
        }
    }

    /// Joins the ended run: `result` its outcome (`None`: it ended without one, having panicked).
    fn finish(&mut self, py: Python<'_>, result: Option<Result<(), Failure>>) -> PyResult<Option<Value>> {
        let joined = self.worker.take().map(|w| py.detach(|| w.join()));
        let result = match (result, joined) {
            (Some(result), _) => result,
            (None, Some(Err(panic))) => {
                let why = panic
                    .downcast_ref::<String>()
                    .cloned()
                    .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_default();
                Err(Failure::Message(format!(
                    "the run stopped on an internal error: {why}"
                )))
            }
            (None, _) => Err(Failure::Message("the run ended without saying how".into())),
        };
        match (self.interrupted.take(), result) {
            (Some(signal), _) => Err(signal),
            // Stopped by `stop` or by a signal the caller's code caught: the run ended as asked.
            (None, Err(Failure::Interrupted(_))) => Ok(None),
            (None, result) => result.map(|()| None).map_err(to_py),
        }
    }

    /// Asks the run to stop at the end of its step, then waits for it (its checkpoint written).
    fn close(&mut self, py: Python<'_>) {
        if let Some(worker) = self.worker.take() {
            nerfjit::interrupt::request_stop();
            let _ = py.detach(|| worker.join());
        }
        self.events = None;
    }
}

impl Drop for Running {
    /// A run left behind (a loop over its steps broken off) is asked to stop and joined: nothing trains on
    /// in the background.
    fn drop(&mut self) {
        if let Some(worker) = self.worker.take() {
            nerfjit::interrupt::request_stop();
            let _ = worker.join();
        }
    }
}

/// Runs the blocks of the script at `script` (a path, or an example's name) as `nerfjit run` does, with
/// `set` overrides, writing into `out` (default: the working folder), resuming its checkpoint when
/// `resume`. Ctrl-C stops training at the end of its step with its checkpoint written, then raises
/// `KeyboardInterrupt`.
#[pyfunction]
#[pyo3(signature = (script, *, set = Vec::new(), out = None, resume = false))]
pub(crate) fn run(
    py: Python<'_>,
    script: String,
    set: Vec<String>,
    out: Option<PathBuf>,
    resume: bool,
) -> PyResult<()> {
    let mut running = Running::start(
        RunArgs {
            script,
            set,
            out,
            resume,
        },
        None,
    )?;
    while running.next(py)?.is_some() {}
    Ok(())
}

/// A script's run whose training is followed step by step: `Trainer(script, set=[], out=None,
/// resume=False)`, then `for metrics in trainer.steps(every=100): ...` runs it, yielding a dict of the
/// metrics at every n-th step (the first step logged at or after it: the log holds every 10th; `step`,
/// `loss`, `psnr`, ...) and at the last, as training goes. Ctrl-C
/// stops training at the end of its step, its checkpoint written, and raises `KeyboardInterrupt`; a
/// `Trainer(..., resume=True)` continues from it. Leaving the loop early stops the training the same way.
#[pyclass(module = "nerfjit", name = "Trainer")]
pub(crate) struct Trainer {
    args: RunArgs,
}

#[pymethods]
impl Trainer {
    #[new]
    #[pyo3(signature = (script, *, set = Vec::new(), out = None, resume = false))]
    fn new(script: String, set: Vec<String>, out: Option<PathBuf>, resume: bool) -> Trainer {
        Trainer {
            args: RunArgs {
                script,
                set,
                out,
                resume,
            },
        }
    }

    /// Starts the run: an iterator over the metrics of every `every`-th training step and the last.
    #[pyo3(signature = (every = 100))]
    fn steps(&self, every: u32) -> PyResult<Steps> {
        if every == 0 {
            return Err(pyo3::exceptions::PyValueError::new_err("every is at least 1"));
        }
        Ok(Steps {
            running: Mutex::new(Running::start(self.args.clone(), Some(every))?),
        })
    }
}

/// The metrics of a running training, step by step (see `Trainer.steps`).
#[pyclass(module = "nerfjit", name = "Steps", weakref)]
pub(crate) struct Steps {
    running: Mutex<Running>,
}

#[pymethods]
impl Steps {
    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    /// Asks the training to stop at the end of its step, without waiting (what Ctrl-C does).
    fn stop(&self) {
        nerfjit::interrupt::request_stop();
    }

    /// Stops the training at the end of its step and waits for it to end, its checkpoint written.
    fn close(&self, py: Python<'_>) {
        self.running.lock().expect("the run").close(py);
    }

    fn __next__<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let record = self.running.lock().expect("the run").next(py)?;
        let Some(record) = record else {
            return Ok(None);
        };
        let json = py.import("json")?;
        let value = json.call_method1("loads", (record.to_string(),))?;
        Ok(Some(value.cast_into::<PyDict>()?))
    }
}
