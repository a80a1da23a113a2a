//! `nerfjit run`: does what the script's blocks say, as a [`Session`] with progress bars and an optional
//! live viewer.

use std::path::Path;
use std::sync::Arc;

use indicatif::{ProgressBar, ProgressStyle};

use crate::failure::{Failure, Result};
use crate::schema::Kind;
use crate::session::{Observer, Session};
use crate::viewer::{Document, Live, ViewArgs};

fn bar(len: usize, what: &str) -> ProgressBar {
    ProgressBar::new(len as u64).with_style(
        ProgressStyle::with_template(&format!(
            "{{spinner}} {what} [{{bar:30}}] {{pos}}/{{len}} frames {{elapsed}}"
        ))
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    )
}

/// Runs every block of the script in order; all blocks are checked before the first one runs. Training
/// updates the params that later blocks render with. With `view`, a live viewer follows the training
/// (and stays open after the last block until the process is stopped).
pub fn run(
    path: &str,
    overrides: &[String],
    out_dir: Option<&Path>,
    resume: bool,
    view: Option<&ViewArgs>,
) -> Result<()> {
    let mut session = Session::open(path, overrides, out_dir)?;
    if session.is_empty() {
        return Err(Failure::Message(format!(
            "{path} has nothing to run: add a block such as 'render sphere_trace {{ camera: ..., out: \"scene.gif\" }}'"
        )));
    }
    let live = match view {
        Some(args) => {
            let live = Arc::new(Live::new());
            let program = session.program();
            let document = Document::of(program, program.param_values.clone(), false)?;
            crate::viewer::attach(args, document, Arc::clone(&live))?;
            Some(live)
        }
        None => None,
    };
    for i in 0..session.len() {
        // Render blocks show a bar of their frames.
        let bar = match session.kind(i) {
            Kind::SphereTrace => Some(bar(session.frames(i), "rendering")),
            Kind::Volume => Some(bar(session.frames(i), "volume rendering")),
            _ => None,
        };
        let frames = |done: usize| {
            if let Some(bar) = &bar {
                bar.set_position(done as u64)
            }
        };
        let observer = Observer {
            frames: Some(&frames),
            live: live.as_deref(),
            resume,
        };
        let summary = session.run_block(i, &observer)?;
        if let Some(bar) = bar {
            bar.finish_and_clear();
        }
        crate::emit(&format!("{summary}\n"));
    }
    if live.is_some() {
        eprintln!("done: the viewer stays open until Ctrl-C");
        loop {
            std::thread::park();
        }
    }
    Ok(())
}
