//! A training run as the viewer sees it (`nerfjit run --view`): the latest params, the progress records,
//! and a pause switch. The training loop publishes into it after each step; pages read from it.

use std::sync::{Arc, Condvar, Mutex, MutexGuard, Weak};
use std::time::Duration;

use serde_json::Value;

use super::mailbox::Mailbox;
use nerfjit::interrupt::Watch;
use nerfjit::observe::TrainingObserver;

/// How often (in steps) the training loop hands its params to the viewer at most.
const PARAMS_EVERY: u32 = 10;

#[derive(Default)]
struct State {
    /// The params at `version` (a step count), once published.
    params: Option<(u32, Arc<[f32]>)>,
    /// Every progress record so far, oldest first.
    history: Vec<Value>,
    paused: bool,
    finished: bool,
    /// The renderers to wake when the params change.
    listeners: Vec<Weak<Mailbox>>,
}

/// What a training run shares with the viewer.
pub struct Live {
    state: Mutex<State>,
    resumed: Condvar,
    /// The latest record, for the pages' connections to forward.
    latest: tokio::sync::watch::Sender<Value>,
}

impl Default for Live {
    /// A run with no record yet.
    fn default() -> Live {
        Live {
            state: Mutex::default(),
            resumed: Condvar::new(),
            latest: tokio::sync::watch::channel(Value::Null).0,
        }
    }
}

impl Live {
    /// A run with no record yet.
    pub fn new() -> Live {
        Live::default()
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Called by the training loop after step `done`: keeps `record` (if any) and, every few steps or
    /// at the `last`, a copy of the params; then waits while a page has paused the run (or until `watch`
    /// sees Ctrl-C).
    pub fn after_step(&self, done: u32, last: bool, params: &[f32], record: Option<Value>, watch: &Watch) {
        let mut state = self.lock();
        if let Some(record) = record {
            state.history.push(record.clone());
            self.latest.send_replace(record);
        }
        let stale = state
            .params
            .as_ref()
            .is_none_or(|(v, _)| done >= v + PARAMS_EVERY);
        let watched = state.listeners.iter().any(|l| l.strong_count() > 0);
        if (stale && watched) || last || state.params.is_none() {
            state.params = Some((done, params.into()));
            state.listeners.retain(|l| l.strong_count() > 0);
            for listener in state.listeners.iter().filter_map(Weak::upgrade) {
                listener.post_refresh();
            }
        }
        state.finished = last;
        while state.paused && !last && !watch.requested() {
            // Woken by resume; the timeout lets Ctrl-C end a paused run.
            state = self
                .resumed
                .wait_timeout(state, Duration::from_millis(200))
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
    }

    /// Pauses or resumes the run.
    pub fn set_paused(&self, paused: bool) {
        self.lock().paused = paused;
        self.resumed.notify_all();
    }

    /// Whether the run is paused.
    pub fn paused(&self) -> bool {
        self.lock().paused
    }

    /// Whether the run has taken its last step.
    pub fn finished(&self) -> bool {
        self.lock().finished
    }

    /// Whether the run is still training (not finished, not paused): the viewer then renders sparingly.
    pub fn busy(&self) -> bool {
        let state = self.lock();
        !state.finished && !state.paused
    }

    /// The latest params and their step, once the run has published any.
    pub fn params(&self) -> Option<(u32, Arc<[f32]>)> {
        self.lock().params.clone()
    }

    /// Every record so far.
    pub fn history(&self) -> Vec<Value> {
        self.lock().history.clone()
    }

    /// Wakes `mailbox` whenever new params are published.
    pub fn listen(&self, mailbox: &Arc<Mailbox>) {
        self.lock().listeners.push(Arc::downgrade(mailbox));
    }

    /// A receiver of the latest record.
    pub fn subscribe(&self) -> tokio::sync::watch::Receiver<Value> {
        self.latest.subscribe()
    }
}

impl TrainingObserver for Live {
    fn after_step(&self, done: u32, last: bool, params: &[f32], record: Option<Value>, watch: &Watch) {
        Live::after_step(self, done, last, params, record, watch);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn params_are_published_first_last_and_every_few_steps_while_watched() {
        let (live, watch) = (Live::new(), Watch::start());
        live.after_step(1, false, &[1.0], Some(json!({"step": 1})), &watch);
        assert_eq!(live.params().unwrap().0, 1, "the first step is always published");
        live.after_step(20, false, &[2.0], None, &watch);
        assert_eq!(live.params().unwrap().0, 1, "nobody watches: no copy");
        let mailbox = Arc::new(Mailbox::default());
        live.listen(&mailbox);
        live.after_step(21, false, &[3.0], None, &watch);
        assert_eq!(live.params().unwrap(), (21, Arc::from([3.0f32].as_slice())));
        assert!(mailbox.news_within(Duration::ZERO), "the renderer is woken");
        live.after_step(22, false, &[4.0], None, &watch);
        assert_eq!(
            live.params().unwrap().0,
            21,
            "not again before {PARAMS_EVERY} more steps"
        );
        live.after_step(23, true, &[5.0], Some(json!({"step": 23})), &watch);
        assert_eq!(live.params().unwrap().0, 23, "the last step is always published");
        assert_eq!(live.history(), vec![json!({"step": 1}), json!({"step": 23})]);
        assert!(!live.busy());
    }

    #[test]
    fn a_paused_run_waits_until_resumed() {
        let live = Arc::new(Live::new());
        live.set_paused(true);
        let trainer = {
            let live = Arc::clone(&live);
            std::thread::spawn(move || live.after_step(1, false, &[0.0], None, &Watch::start()))
        };
        std::thread::sleep(Duration::from_millis(50));
        assert!(!trainer.is_finished(), "the step returns only after resume");
        live.set_paused(false);
        trainer.join().unwrap();
    }
}
