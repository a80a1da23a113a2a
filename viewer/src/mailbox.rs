//! What a page asked for and its renderer has not done yet: only the latest script and the latest camera
//! count (a camera dragged across the screen sends many; the renderer skips to the last one).

use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::Duration;

use super::export::Export;
use super::scene::{Layer, ViewCamera};

/// A frame the page wants: a camera, a size and a layer, numbered by the page.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameRequest {
    /// The page's number for the request (echoed in the frames that answer it).
    pub id: u64,
    /// Where the camera is.
    pub view: ViewCamera,
    /// Canvas width in pixels.
    pub width: u32,
    /// Canvas height in pixels.
    pub height: u32,
    /// What to show.
    pub layer: Layer,
}

/// A file the page wants, made from a view.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExportRequest {
    /// The page's number for the request.
    pub id: u64,
    /// What to make.
    pub what: Export,
    /// The view it starts from.
    pub view: ViewCamera,
}

/// Requests not yet taken by the renderer.
#[derive(Debug, Default)]
pub struct Pending {
    /// A new script text and the page's number for it.
    pub source: Option<(u64, String)>,
    /// A new camera.
    pub frame: Option<FrameRequest>,
    /// New params (of a training run) to render the last camera with.
    pub refresh: bool,
    /// A file to make.
    pub export: Option<ExportRequest>,
}

impl Pending {
    fn is_empty(&self) -> bool {
        self.source.is_none() && self.frame.is_none() && !self.refresh && self.export.is_none()
    }
}

#[derive(Debug, Default)]
struct State {
    pending: Pending,
    closed: bool,
}

/// The latest requests of one page, handed from its connection to its renderer thread.
#[derive(Debug, Default)]
pub struct Mailbox {
    state: Mutex<State>,
    posted: Condvar,
}

impl Mailbox {
    fn lock(&self) -> MutexGuard<'_, State> {
        // A renderer that panicked leaves nothing half-written here: the state is plain data.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Replaces the pending script.
    pub fn post_source(&self, id: u64, text: String) {
        self.lock().pending.source = Some((id, text));
        self.posted.notify_all();
    }

    /// Replaces the pending camera.
    pub fn post_frame(&self, request: FrameRequest) {
        self.lock().pending.frame = Some(request);
        self.posted.notify_all();
    }

    /// Replaces the pending export.
    pub fn post_export(&self, request: ExportRequest) {
        self.lock().pending.export = Some(request);
        self.posted.notify_all();
    }

    /// Asks for the last camera again (the params changed).
    pub fn post_refresh(&self) {
        self.lock().pending.refresh = true;
        self.posted.notify_all();
    }

    /// Ends the mailbox: [`Mailbox::take`] returns `None` from now on.
    pub fn close(&self) {
        self.lock().closed = true;
        self.posted.notify_all();
    }

    /// Waits for requests and takes them all; `None` once closed.
    pub fn take(&self) -> Option<Pending> {
        let mut state = self.lock();
        loop {
            if state.closed {
                return None;
            }
            if !state.pending.is_empty() {
                return Some(std::mem::take(&mut state.pending));
            }
            state = self.posted.wait(state).unwrap_or_else(|e| e.into_inner());
        }
    }

    /// Waits up to `timeout` for a request (or the close); whether one came (work for an older request
    /// is then wasted).
    pub fn news_within(&self, timeout: Duration) -> bool {
        let state = self.lock();
        let (state, _) = self
            .posted
            .wait_timeout_while(state, timeout, |s| !s.closed && s.pending.is_empty())
            .unwrap_or_else(|e| e.into_inner());
        state.closed || !state.pending.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn request(id: u64) -> FrameRequest {
        FrameRequest {
            id,
            view: ViewCamera {
                eye: Vec3::Z,
                target: Vec3::ZERO,
                up: Vec3::Y,
                focal: 1.0,
            },
            width: 8,
            height: 8,
            layer: Layer::Color,
        }
    }

    #[test]
    fn only_the_latest_requests_are_taken() {
        let mailbox = Mailbox::default();
        assert!(!mailbox.news_within(Duration::ZERO));
        mailbox.post_frame(request(1));
        mailbox.post_source(1, "a".into());
        mailbox.post_frame(request(2));
        mailbox.post_source(2, "b".into());
        assert!(
            mailbox.news_within(Duration::from_secs(60)),
            "news that waits is seen at once"
        );
        let pending = mailbox.take().unwrap();
        assert_eq!(pending.frame.map(|f| f.id), Some(2));
        assert_eq!(pending.source, Some((2, "b".to_string())));
        assert!(!mailbox.news_within(Duration::from_millis(1)));
    }

    #[test]
    fn a_waiting_renderer_wakes_for_a_request_and_ends_at_the_close() {
        let mailbox = std::sync::Arc::new(Mailbox::default());
        let renderer = {
            let mailbox = std::sync::Arc::clone(&mailbox);
            std::thread::spawn(move || {
                let mut ids = Vec::new();
                while let Some(p) = mailbox.take() {
                    ids.extend(p.frame.map(|f| f.id));
                }
                ids
            })
        };
        mailbox.post_frame(request(7));
        while mailbox.news_within(Duration::ZERO) {
            std::thread::yield_now();
        }
        mailbox.close();
        assert_eq!(renderer.join().unwrap(), vec![7]);
    }
}
