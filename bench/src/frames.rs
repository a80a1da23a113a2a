//! The `frames` workload: renders of a trained checkpoint at 800² (the published tables' resolution) and
//! 400² (the live viewer's full-size frame), as `nerfjit render` and `eval-views` make them (the
//! checkpoint's occupancy grid, early termination, the settings its script trains with), from the views
//! its training holds out (else its script's camera path). Given a baked scene (`.bake`), its splats drawn
//! by the CPU splat renderer from the views of the checkpoint it was baked from.

use std::path::Path;

use nerfjit::bake_file;
use nerfjit::checkpoint::load_source;
use nerfjit::commands::render_views::{held_out_views, script_cameras, ViewArgs};
use nerfjit::failure::{Failure, Result};
use nerfjit_field::VolumeFields;
use nerfjit_jit::KernelCache;
use nerfjit_runtime::splats::{SplatFrameStats, SplatScene, SPLAT_PHASES};

/// Views rendered per repetition, spread over the cameras.
const VIEWS: usize = 4;

/// Renders up to [`VIEWS`] of the checkpoint's held-out views (else of its `render` block's camera path) at each
/// size, `reps` times, and prints the median time per frame.
pub fn frames(reps: usize, checkpoint: Option<&Path>) -> Result<()> {
    let Some(checkpoint) = checkpoint else {
        return Err(Failure::Message(
            "frames renders a trained checkpoint or its bake: give --scene CKPT (e.g. \
             instant_lego_full.ckpt.safetensors) or --scene SCENE.bake"
                .into(),
        ));
    };
    let bake = match bake_file::is_bake(checkpoint) {
        true => Some(bake_file::read(checkpoint)?),
        false => None,
    };
    let source = bake
        .as_ref()
        .map_or(checkpoint, |b| b.source.as_path())
        .to_string_lossy();
    let (program, params) = load_source(&source)?;
    let (cameras, described) = match held_out_views(&source, &program) {
        Ok((views, described)) => (views.cameras, described),
        Err(_) => {
            let path = script_cameras(&program)?.ok_or_else(|| {
                Failure::Message(format!(
                    "{source}'s script holds no views out and has no render block with a camera"
                ))
            })?;
            (path, "its render path".to_string())
        }
    };
    let count = VIEWS.min(cameras.len());
    let views: Vec<_> = (0..count).map(|i| &cameras[i * cameras.len() / count]).collect();
    if let Some(bake) = &bake {
        nerfjit::emit(&format!(
            "frames: {}, {} splats baked from {source}, {count} of {described}; median of {reps}\n",
            checkpoint.display(),
            bake.splats.len()
        ));
        // Made ready once, as a viewer or a video does (the covariances: ~1 ms a frame if made each time).
        let scene = SplatScene::new(&bake.splats, nerfjit_field::splat_shader()?);
        let phases = std::sync::Mutex::new(Vec::new());
        time_frames(reps, &views, |camera, size| {
            let (_, stats) = scene.render(camera, size, size, bake.background)?;
            phases.lock().unwrap().push((size, stats));
            Ok(())
        })?;
        report_phases(&phases.into_inner().unwrap());
        return Ok(());
    }
    let args = ViewArgs::as_trained(&source, Some(800));
    let rendering = args.resolve(&program);
    let cache = KernelCache::new();
    let fields = VolumeFields::compile(&program, &cache, rendering.importance, rendering.products)?;
    let settings = rendering.settings(fields.fine.mode);
    let grid = rendering.occupancy(&source, &fields, &params)?;
    let occupied = grid.as_ref().map_or("no occupancy grid".to_string(), |g| {
        format!("{:.1}% of the grid's cells occupied", 100.0 * g.occupancy())
    });
    nerfjit::emit(&format!(
        "frames: {source}, {count} of {described}, {} samples a ray, {occupied}; median of {reps}\n",
        rendering.samples
    ));
    time_frames(reps, &views, |camera, size| {
        fields
            .render_with(camera, (size, size), &params, &settings, grid.as_ref())
            .map(|_| ())
            .map_err(Into::into)
    })
}

/// Prints the median time of each phase of the splat renderer's frames at each size, and how many splats
/// and splat-tile pairs they drew.
fn report_phases(frames: &[(u32, SplatFrameStats)]) {
    for size in [800, 400] {
        let of_size: Vec<_> = frames.iter().filter(|(s, _)| *s == size).collect();
        let medians: Vec<String> = SPLAT_PHASES
            .iter()
            .enumerate()
            .map(|(k, name)| {
                let times = of_size.iter().map(|(_, f)| f.phases[k].as_secs_f64()).collect();
                format!("{name} {:.1}", 1e3 * crate::median(times))
            })
            .collect();
        let count = |of: fn(&SplatFrameStats) -> usize| {
            crate::median(of_size.iter().map(|(_, f)| of(f) as f64).collect())
        };
        nerfjit::emit(&format!(
            "  {size}×{size} phases (ms, medians): {}; {:.0} splats on the screen, {:.0} splat-tile pairs\n",
            medians.join(", "),
            count(|f| f.visible),
            count(|f| f.entries)
        ));
    }
}

/// Times `draw` of every view at 800² and 400², `reps` times, and prints the median time a frame.
fn time_frames(
    reps: usize,
    views: &[&nerfjit_runtime::Camera],
    draw: impl Fn(&nerfjit_runtime::Camera, u32) -> Result<()>,
) -> Result<()> {
    for size in [800, 400] {
        let mut failed = None;
        let seconds = crate::time_reps(reps, || {
            for camera in views {
                if let Err(e) = draw(camera, size) {
                    failed = Some(e);
                }
            }
        });
        if let Some(e) = failed {
            return Err(e);
        }
        nerfjit::emit(&format!(
            "  {size}×{size}: {:8.1} ms a frame\n",
            1e3 * seconds / views.len() as f64
        ));
    }
    Ok(())
}
