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

/// The `--set` overrides that give `session`'s training `minutes` in all (`nerfjit run --minutes`): every
/// `train` block's `minutes` and every `bake` block's `tune` scaled by one factor, so that each keeps its share
/// of the time as the script divides it. Loading data, baking, validation and previews come on top. A script
/// none of whose blocks trains for a time is refused.
pub fn minutes_overrides(session: &Session, minutes: f64) -> Result<Vec<String>> {
    if !(minutes.is_finite() && minutes > 0.0 && minutes <= 1e6) {
        return Err(Failure::Message(format!(
            "--minutes {minutes} must be a number of minutes above 0 (at most 1e6)"
        )));
    }
    let timed: Vec<(usize, f64)> = (0..session.len())
        .filter_map(|i| session.timed_seconds(i).map(|s| (i, s)))
        .collect();
    let total: f64 = timed.iter().map(|(_, s)| s).sum();
    if timed.is_empty() || total <= 0.0 {
        return Err(Failure::Message(
            "--minutes shares the time among the train blocks' 'minutes' and the bake blocks' 'tune', and the \
             script sets neither: set them (e.g. minutes: 5 in its train block), or use --set train.steps=N"
                .to_string(),
        ));
    }
    let factor = 60.0 * minutes / total;
    // A block is named as `--set` names it: the i-th block of its kind (`train` and `train sdf` are both
    // `train`).
    let name = |index: usize| {
        let word = match session.kind(index) {
            Kind::Train | Kind::TrainSdf => "train",
            Kind::Bake => "bake",
            _ => unreachable!("only train and bake blocks train for a time"),
        };
        let before = (0..index)
            .filter(|&j| match word {
                "train" => matches!(session.kind(j), Kind::Train | Kind::TrainSdf),
                _ => session.kind(j) == Kind::Bake,
            })
            .count();
        format!("{word}[{before}]")
    };
    Ok(timed
        .into_iter()
        .map(|(i, seconds)| match session.kind(i) {
            Kind::Bake => format!("{}.tune={}", name(i), seconds * factor),
            _ => format!("{}.minutes={}", name(i), seconds * factor / 60.0),
        })
        .collect())
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The session of the script `source` in a scratch folder holding a camera (`cams.json`) and a point cloud
    /// (`points.xyz`), and the folder.
    fn session(name: &str, source: &str) -> (Session, std::path::PathBuf) {
        let out = crate::session::tests::folder_with_one_camera(&format!("minutes-{name}"));
        std::fs::write(out.join("points.xyz"), "0 0 1\n0 1 0\n1 0 0\n").unwrap();
        (Session::from_source("s.sdf", source, &out).unwrap(), out)
    }

    /// Two train blocks of 1 and 3 minutes with a `train sdf` block between them (which takes no time limit)
    /// and a bake tuned 60 s.
    #[test]
    fn minutes_are_shared_among_the_timed_blocks_as_the_script_divides_them() {
        let source = "param r: f32 = 0.5\nfn density(p: vec3) -> f32 = relu(r - length(p))\n\
                      fn color(p: vec3) -> vec3 = [1, 1, 1]\nfn sdf(p: vec3) -> f32 = length(p) - r\n\
                      train { data: views(\"cams.json\"), steps: 10, minutes: 1, checkpoint: none }\n\
                      train sdf { data: points(\"points.xyz\"), steps: 10, checkpoint: none }\n\
                      train { data: views(\"cams.json\"), steps: 10, minutes: 3, checkpoint: none }\n\
                      bake { out: \"ball.bake\", tune: 60 }\n";
        let (s, out) = session("shared", source);
        // 1 + 3 + 1 minutes given 10: twice as long each.
        assert_eq!(
            minutes_overrides(&s, 10.0).unwrap(),
            ["train[0].minutes=2", "train[2].minutes=6", "bake[0].tune=120"]
        );
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let e = minutes_overrides(&s, bad).unwrap_err().to_string();
            assert!(e.contains("must be a number of minutes above 0"), "{e}");
        }
        std::fs::remove_dir_all(&out).unwrap();
    }

    #[test]
    fn a_script_that_trains_for_no_time_is_refused() {
        let source = "param r: f32 = 0.5\nfn density(p: vec3) -> f32 = relu(r - length(p))\n\
                      fn color(p: vec3) -> vec3 = [1, 1, 1]\n\
                      train { data: views(\"cams.json\"), steps: 10, checkpoint: none }\n";
        let (s, out) = session("untimed", source);
        let e = minutes_overrides(&s, 5.0).unwrap_err().to_string();
        assert!(e.contains("the script sets neither"), "{e}");
        std::fs::remove_dir_all(&out).unwrap();
    }
}
