//! `nerfjit run`: does what the script's blocks say, as a [`Session`], with progress bars and an
//! observer of training (the command line's live viewer) when given.

use std::path::Path;

use crate::failure::{Failure, Result};
use crate::observe::{BarKind, NoBars, ProgressBars, TrainingObserver};
use crate::session::{Observer, Session};
use crate::settings::schema::Kind;

/// Opens the script at `path` for [`run_session`]: all blocks are checked; a script without blocks is an
/// error.
pub fn open(path: &str, overrides: &[String], out_dir: Option<&Path>) -> Result<Session> {
    let session = Session::open(path, overrides, out_dir)?;
    if session.is_empty() {
        return Err(Failure::Message(format!(
            "{path} has nothing to run: add a block such as 'render sphere_trace {{ camera: ..., out: \"scene.gif\" }}'"
        )));
    }
    Ok(session)
}

/// Runs every block of the script in order (see [`run_session`]), without progress bars.
pub fn run(
    path: &str,
    overrides: &[String],
    out_dir: Option<&Path>,
    resume: bool,
    live: Option<&dyn TrainingObserver>,
) -> Result<()> {
    let mut session = open(path, overrides, out_dir)?;
    run_session(&mut session, resume, &NoBars, live)
}

/// Runs every block of `session` in order, printing each one's summary; all blocks were checked before
/// the first one runs. Training updates the params that later blocks render and bake with (`bake` blocks
/// by [`crate::commands::bake::bake_block`]); `live` follows it.
pub fn run_session(
    session: &mut Session,
    resume: bool,
    bars: &dyn ProgressBars,
    live: Option<&dyn TrainingObserver>,
) -> Result<()> {
    for i in 0..session.len() {
        // Render blocks show a bar of their frames.
        let bar = match session.kind(i) {
            Kind::SphereTrace => Some(bars.bar(session.frames(i) as u64, BarKind::Frames("rendering"))),
            Kind::Volume => Some(bars.bar(session.frames(i) as u64, BarKind::Frames("volume rendering"))),
            _ => None,
        };
        let frames = |done: usize| {
            if let Some(bar) = &bar {
                bar.set_position(done as u64)
            }
        };
        let observer = Observer {
            frames: Some(&frames),
            live,
            resume,
            bars: Some(bars),
            baker: Some(&crate::commands::bake::bake_block),
        };
        let summary = session.run_block(i, &observer)?;
        if let Some(bar) = bar {
            bar.finish_and_clear();
        }
        crate::console::emit(&format!("{summary}\n"));
    }
    Ok(())
}
