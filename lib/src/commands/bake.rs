//! `nerfjit bake`: a trained volume field baked into Gaussian splats that the CPU draws in milliseconds
//! ([`nerfjit_runtime::splats`]), and what is done with a bake: `nerfjit render` and `nerfjit eval-views`
//! of a `.bake` (see [`eval`]); `nerfjit export` is [`crate::commands::export`].
//!
//! The bake is the field's surface as its training cameras see it, as NeRF-to-splats conversions make it:
//! every training view is volume-rendered in its own aspect ratio with its larger side `--size` (and a
//! [`MARGIN`] on every side, to see a little beyond its frame), each pixel whose opacity reaches `--min-opacity` is placed at
//! its expected depth with its color (the background taken out), and the pixels are merged in cells as
//! wide as their footprints (the width of a pixel at its depth, in levels of detail whose cells double in
//! side from the median footprint's either way, so that a capture's far background is merged into splats
//! as coarse as its pixels and its nearby object into splats as fine as its own): one round splat per cell, at the mean of its pixels, of their mean color and opacity, with a
//! standard deviation of [`SPREAD`] cells so that neighbours overlap. A splat that some view sees in front
//! of what it saw there (a pixel whose expected depth fell between surfaces) is dropped (`seen_through`).
//! The colors are those the field shows from the views that saw each cell, averaged: the splats look alike
//! from every side.
//!
//! By default the views are those the field trained on: the views its training held out are left for
//! scoring, as they are in fine-tuning.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::Path;
use std::time::Instant;

use rayon::prelude::*;

use nerfjit_dsl::Program;
use nerfjit_runtime::splats::{splat_loss_gradients, SplatScene, SplatTuner, Splats, TuneRates};
use nerfjit_runtime::{Camera, ImageF32, Layout, Rng, Views, VolumeFrame};

use crate::bake_file::{self, Bake};
use crate::blocks::bake::BakePlan;
use crate::blocks::train::TrainPlan;
use crate::commands::point_cloud::{view_cameras, PointsArgs, Surfels};
use crate::commands::render_views::{report, CameraSource, ScoredSet, ViewArgs};
use crate::failure::{Failure, Result};
use crate::session::FieldToBake;
use crate::settings::schema::Kind;
use crate::training::validation::score_on_ranks;

/// The learning rates of fine-tuning at its start (the centers' in units of the splats' median scale).
pub const TUNE_RATES: TuneRates = TuneRates {
    position: 0.1,
    color: 0.01,
    opacity: 0.05,
    scale: 0.005,
    rotation: 0.001,
    sh: 0.015,
};

/// The share of fine-tuning's time spent on the views at half their size (four times the steps a second).
pub const COARSE_SHARE: f64 = 0.5;

/// Splats fainter than this after fine-tuning are dropped (they draw nothing: under the renderer's
/// smallest alpha everywhere).
pub const MIN_OPACITY: f32 = 1.0 / 255.0;

/// The default of [`Tuning::min_weight`]: a pixel of the bake's views (on lego, whose 800² views are baked
/// at 400², four of its own: half the splats that one of its own keeps, for a few tenths of a dB; BAKING.md
/// has the measured trade).
pub const MIN_WEIGHT: f32 = 1.0;

/// The side of the views a bake renders from cameras other than its training views' (`--cameras`,
/// `--path`) unless told, in pixels (square views). From its training views it renders views of their own
/// aspect ratio, whose larger side is half theirs ([`baked_side`]): 400² for lego's 800² views.
pub const VIEW_SIZE: u32 = 400;

/// The larger side of the views a bake renders from training views of `width`×`height` unless told: half
/// theirs, so that a splat starts about two of their pixels wide (measured on lego's 800² views and the
/// room capture's 320×240: BAKING.md), at least 16.
pub fn baked_side(width: u32, height: u32) -> u32 {
    (width.max(height) / 2).max(16)
}

/// The width and height of the views a bake renders from training views of `width`×`height` whose larger
/// side is to be `side`: their aspect ratio kept (a portrait or a wide capture is seen whole, not cut to a
/// square), each side at least a pixel.
pub fn baked_frame(width: u32, height: u32, side: u32) -> (u32, u32) {
    let larger = f64::from(width.max(height).max(1));
    let scaled = |x: u32| ((f64::from(x) * f64::from(side) / larger).round() as u32).max(1);
    (scaled(width), scaled(height))
}

/// How far beyond a training view's frame the bake's view from its camera sees, on every side, as a share
/// of the frame's larger side: held-out views may look a little beyond every training view (the room
/// capture's lower views look higher up its walls), and the splats there stay as the field showed them.
pub const MARGIN: f32 = 0.125;

/// How near the edge of a training view's frame a splat's center lies (as a share of the frame's larger
/// side) for pruning to treat it as beyond the frame (see [`tune`]).
pub const EDGE: f32 = 0.1;

/// A splat's standard deviation, in cells.
pub const SPREAD: f32 = 0.6;

/// How far in front of what a view saw a splat may lie before the view proves it to be in empty space,
/// in cells.
pub const CARVE_CELLS: f32 = 3.0;

/// The finest and the coarsest levels of detail: cells 2⁻²⁴ to 2²⁴ times as wide as the median footprint.
pub const MAX_LEVEL: i32 = 24;

/// How a bake is fine-tuned.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tuning {
    /// Seconds of fine-tuning (0: none).
    pub seconds: f64,
    /// The degree of the spherical harmonics of the splats' colors: 0 (the same from every side) or 1
    /// (colors that change with the view: nine more numbers a splat, learnt while tuning).
    pub sh_degree: u8,
    /// After the coarse half, a splat whose weight (the sum over its pixels of its alpha times the
    /// transmittance in front of it) stayed under this many pixels in every training view, counted in
    /// pixels of the views the field was baked from (one is as wide as a splat was made), is dropped: it
    /// hardly shows, and every splat costs the renderer the same to project, sort and bin.
    pub min_weight: f32,
}

/// Bakes the field of `args.view.source` (seen as `nerfjit points` sees it) into splats, fine-tunes them
/// as `tuning` says against its training views (see [`tune`]) and writes them to `args.out`; returns a
/// summary.
pub fn run(args: &PointsArgs, tuning: Tuning) -> Result<String> {
    bake(args, tuning, None)
}

/// A script's `bake` block, the [`Baker`](crate::session::Baker) of `nerfjit run`: the field as it is at that
/// point of the script baked as [`run`] bakes a checkpoint, with the block's settings as its options, from
/// the views of the script's `train` block's data (less those it holds out). The bake records as what it was
/// baked from the checkpoint the last `train` block wrote (the script as it ran, `--set` overrides included),
/// else the script. In an MPI job the ranks share the views' renders; rank 0 merges and tunes the
/// splats and writes the bake (the other ranks return an empty summary).
pub fn bake_block(plan: &BakePlan, field: &FieldToBake) -> Result<String> {
    let script = field.script.to_string_lossy();
    let args = PointsArgs {
        view: ViewArgs::as_trained(&script, plan.size),
        cameras: CameraSource::Default,
        min_opacity: plan.min_opacity,
        out: &plan.out,
    };
    let tuning = Tuning {
        seconds: plan.tune_seconds,
        sh_degree: plan.sh_degree,
        min_weight: plan.min_weight,
    };
    bake(&args, tuning, Some(field))
}

/// [`run`] of the field `in_memory` holds (a script's `bake` block, whose script is `args.view.source`),
/// or, without it, of the field `args.view.source` loads.
fn bake(args: &PointsArgs, tuning: Tuning, in_memory: Option<&FieldToBake>) -> Result<String> {
    if !bake_file::is_bake(args.out) {
        return Err(Failure::Message(format!(
            "'{}' must end in .bake (export it afterwards: nerfjit export SCENE.bake --format splat-ply)",
            args.out.display()
        )));
    }
    let start = Instant::now();
    let loaded;
    let (program, params, trained_grid) = match in_memory {
        Some(field) => (field.program, field.params, field.grid),
        None => {
            loaded = crate::checkpoint::load_source(args.view.source)?;
            (&loaded.0, loaded.1.as_slice(), None)
        }
    };
    let background = args.view.resolve(program).background;
    let cameras = bake_cameras(args, program)?;
    // The training views, when tuning needs them or the bake sees the field from their cameras (whose
    // aspect ratio its views keep).
    let from_training = matches!(args.cameras, CameraSource::Default);
    let views = match tuning.seconds > 0.0 || from_training {
        true => Some(training_views(program, args.view.source, background)?),
        false => None,
    };
    // The training views' frames (their aspect ratio, the larger side `--size`) and the views rendered:
    // the same, widened by a margin on every side.
    let (baked, margin, cameras) = match &views {
        Some((views, _)) if from_training => {
            let side = args.view.size.unwrap_or(baked_side(views.width, views.height));
            let (width, height) = baked_frame(views.width, views.height, side);
            let margin = (MARGIN * width.max(height) as f32).round() as u32;
            let widened = cameras
                .iter()
                .map(|camera| camera.widened(width, height, margin))
                .collect::<std::result::Result<Vec<_>, _>>()?;
            ((width, height), margin, widened)
        }
        _ => {
            let side = args.view.size.unwrap_or(VIEW_SIZE);
            ((side, side), 0, cameras)
        }
    };
    let frame = (baked.0 + 2 * margin, baked.1 + 2 * margin);
    let field = (program, params);
    let Some(surfels) = Surfels::render(&args.view, field, trained_grid, &cameras, frame, args.min_opacity)?
    else {
        return Ok(String::new());
    };
    let (splats, cells) = splats_of(&surfels, &cameras);
    // A bake block's field is scored on the data of the script as it ran: its train block's checkpoint holds
    // that script, overrides included.
    let source = match in_memory.and_then(|field| field.checkpoint) {
        Some(checkpoint) => checkpoint,
        None => Path::new(args.view.source),
    };
    let mut bake = Bake {
        splats,
        background,
        source: std::path::absolute(source).unwrap_or_else(|_| source.into()),
    };
    let mut text = format!(
        "baked {} splats ({cells}) from {} pixels of {} views of {}×{}{} in {:.1} s\n",
        bake.splats.len(),
        surfels.positions.len(),
        cameras.len(),
        baked.0,
        baked.1,
        match margin {
            0 => String::new(),
            m => format!(" (and {m} pixels beyond each side)"),
        },
        start.elapsed().as_secs_f64(),
    );
    if let Some((views, loaded)) = views {
        text += &loaded;
        if tuning.seconds > 0.0 {
            text += &tune(&mut bake, &views, tuning, baked.0)?;
        }
    }
    bake_file::write(args.out, &bake)?;
    let bytes = std::fs::metadata(args.out).map_or(0, |m| m.len());
    text += &format!(
        "{} splats → {} ({:.1} MB)",
        bake.splats.len(),
        args.out.display(),
        bytes as f64 / 1e6
    );
    Ok(text)
}

/// The cameras a bake sees the field of `args.view.source` (compiled as `program`) from: those `args`
/// names, else the views of the data its `train` block reads less those the block holds out for scoring
/// (`val: holdout(every: n)`).
fn bake_cameras(args: &PointsArgs, program: &Program) -> Result<Vec<Camera>> {
    let source = args.view.source;
    let cameras = view_cameras(source, program, &args.cameras)?;
    if !matches!(args.cameras, CameraSource::Default) {
        return Ok(cameras);
    }
    let folder = Path::new(source).parent().and_then(|p| p.to_str()).unwrap_or("");
    let block = crate::settings::block::first_block(program, Kind::Train, folder)?;
    let Some((every, _)) = TrainPlan::new(block)?.held_out_every() else {
        return Ok(cameras);
    };
    Ok(cameras
        .into_iter()
        .enumerate()
        .filter(|(i, _)| i % every != 0)
        .map(|(_, camera)| camera)
        .collect())
}

/// The views `source` (a checkpoint or a script, compiled as `program`) trained on, without those its
/// training holds out, on `background`; refused when there are none.
/// Returns them and a line that says so.
fn training_views(program: &Program, source: &str, background: [f32; 3]) -> Result<(Views, String)> {
    let start = Instant::now();
    let folder = Path::new(source).parent().and_then(|p| p.to_str()).unwrap_or("");
    let block = crate::settings::block::first_block(program, Kind::Train, folder)?;
    let views = TrainPlan::new(block)?.load_views()?.0.on_background(background);
    if views.is_empty() {
        return Err(Failure::Message(format!(
            "{source}'s training data holds no views to bake from or tune against"
        )));
    }
    let line = format!(
        "{} training views of {}×{} loaded in {:.1} s\n",
        views.len(),
        views.width,
        views.height,
        start.elapsed().as_secs_f64()
    );
    Ok((views, line))
}

/// Fine-tunes the splats of `bake` for `tuning.seconds` against `views` (the training views of the field it
/// was baked from, without those its training holds out): one view a step, in a shuffled order
/// each pass, Adam on the frame's mean squared error with every rate decaying tenfold over the time
/// ([`TUNE_RATES`], the centers' rate relative to the splats' median scale). The first [`COARSE_SHARE`] of
/// the time takes the views at half size; then the splats that weighed under `tuning.min_weight` pixels of
/// a view `baked_width` wide (the width of the views the splats were baked from) in every view are dropped
/// (unless their centers lie well inside no view's frame: beyond every frame, or within [`EDGE`] of the larger
/// side from the edges of every frame that holds them: no view tunes them, or only parts of them), and at the end those left
/// fainter than [`MIN_OPACITY`]. With `tuning.sh_degree` 1, splats without spherical harmonics get them at
/// that point (zero: the colors unchanged), tuned with the rest in
/// the second half.
/// Returns what it did, a line a pass.
pub fn tune(bake: &mut Bake, views: &Views, tuning: Tuning, baked_width: u32) -> Result<String> {
    let seconds = tuning.seconds;
    let mut text = String::new();
    let start = Instant::now();
    let mut scales: Vec<f32> = bake
        .splats
        .scales
        .iter()
        .map(|s| s[0].max(s[1]).max(s[2]))
        .collect();
    let middle = scales.len() / 2;
    let median_scale = *scales.select_nth_unstable_by(middle, f32::total_cmp).1;
    let rates = TuneRates {
        position: TUNE_RATES.position * median_scale,
        ..TUNE_RATES
    };
    let mut tuner = SplatTuner::new(bake.splats.len(), rates);
    let shader = nerfjit_field::splat_shader()?;
    let mut rng = Rng::new(0x5eed);
    let mut order: Vec<usize> = (0..views.len()).collect();
    let coarse: Vec<Vec<[f32; 3]>> = views.images.iter().map(halved).collect();
    let coarse_size = (views.width / 2, views.height / 2);
    let mut steps = 0usize;
    // Each splat's largest weight in a view of the coarse half, in pixels at full size, and the least it
    // may have.
    let mut heaviest = vec![0.0f32; bake.splats.len()];
    let min_weight = tuning.min_weight * (views.width as f32 / baked_width.max(1) as f32).powi(2);
    let mut light = None;
    'passes: for pass in 1.. {
        for k in (1..order.len()).rev() {
            order.swap(k, rng.below(k as u64 + 1) as usize);
        }
        let mut error = 0.0f64;
        for (done, &v) in order.iter().enumerate() {
            let elapsed = start.elapsed().as_secs_f64();
            if elapsed >= seconds {
                if done > 0 {
                    text += &pass_line(pass, done, error, elapsed);
                }
                break 'passes;
            }
            let fine = elapsed >= COARSE_SHARE * seconds || coarse_size.0 < 16 || coarse_size.1 < 16;
            if fine && light.is_none() {
                // Once every view was seen at half size, the splats that weigh next to nothing in all
                // of them go.
                let seen = steps >= views.len();
                let framed = well_inside_some_frame(&bake.splats.positions, views);
                let keep: Vec<bool> = heaviest
                    .iter()
                    .zip(&framed)
                    .map(|(&h, &framed)| !seen || !framed || h >= min_weight)
                    .collect();
                light = Some(bake.splats.retain(&keep));
                tuner.retain(&keep)?;
                // Colors start to change with the view once the splats have found their places (as 3D
                // Gaussian splatting raises the harmonics' degree as it trains): from the start, they
                // learn to make up for misplaced splats in each view, which the views held out do not
                // share.
                if tuning.sh_degree > 0 && bake.splats.sh.is_empty() {
                    bake.splats.sh = vec![[[0.0; 3]; 3]; bake.splats.len()];
                }
            }
            let (size, target) = match fine {
                true => ((views.width, views.height), &views.images[v].pixels),
                false => (coarse_size, &coarse[v]),
            };
            let (loss, gradients) = splat_loss_gradients(
                &bake.splats,
                shader,
                &views.cameras[v],
                size,
                bake.background,
                target,
            )?;
            error += loss;
            let factor = 0.1f64.powf(elapsed / seconds) as f32;
            tuner.step(&mut bake.splats, &gradients, factor)?;
            if !fine {
                let full = (views.width * views.height) as f32 / (size.0 * size.1) as f32;
                for (h, &w) in heaviest.iter_mut().zip(&gradients.weights) {
                    *h = h.max(w * full);
                }
            }
            steps += 1;
        }
        text += &pass_line(pass, order.len(), error, start.elapsed().as_secs_f64());
    }
    let dropped = bake.splats.prune(MIN_OPACITY);
    text += &format!(
        "tuned {steps} steps ({} views of {}×{}) in {:.1} s; {} splats weighing under {min_weight:.2} pixels \
         of the views in each of them (measured at half size) and {dropped} fainter than {MIN_OPACITY:.4} \
         dropped\n",
        views.len(),
        views.width,
        views.height,
        start.elapsed().as_secs_f64(),
        light.unwrap_or(0),
    );
    Ok(text)
}

/// Whether each of `positions` lies well inside the frame of some view of `views` (in front of its camera,
/// further than [`EDGE`] of the frame's larger side from its edges). Pruning keeps the splats that lie well
/// inside none: those beyond every frame (the bake's views see a [`MARGIN`] beyond them) no view tunes, and
/// those near the edges of every frame that holds them are tuned by parts of them at most; they stay about
/// as the field showed them to the bake's views, and views held out for scoring, which look a little
/// beyond the training views, see them.
fn well_inside_some_frame(positions: &[[f32; 3]], views: &Views) -> Vec<bool> {
    let inset = EDGE * views.width.max(views.height) as f32;
    let (width, height) = (views.width as f32, views.height as f32);
    positions
        .par_iter()
        .map(|&p| {
            views.cameras.iter().any(|camera| {
                camera
                    .project(glam::Vec3::from(p), views.width, views.height)
                    .is_some_and(|(row, col)| {
                        (inset..height - inset).contains(&row) && (inset..width - inset).contains(&col)
                    })
            })
        })
        .collect()
}

/// An image at half its width and height (each pixel the mean of four; an odd last row or column left out).
fn halved(image: &ImageF32) -> Vec<[f32; 3]> {
    let (w, h) = (image.width as usize / 2, image.height as usize / 2);
    let at = |x: usize, y: usize| image.pixels[y * image.width as usize + x];
    (0..w * h)
        .map(|k| {
            let (x, y) = (2 * (k % w), 2 * (k / w));
            let four = [at(x, y), at(x + 1, y), at(x, y + 1), at(x + 1, y + 1)];
            std::array::from_fn(|c| 0.25 * four.iter().map(|p| p[c]).sum::<f32>())
        })
        .collect()
}

/// What a pass of tuning reached: its mean error over the views it took, as a PSNR.
fn pass_line(pass: usize, views: usize, error: f64, elapsed: f64) -> String {
    let psnr = -10.0 * (error / views.max(1) as f64).log10();
    format!("tuning pass {pass}: {views} views, {psnr:.2} dB on them as they came, {elapsed:.1} s\n")
}

/// Sums of the surfels that fall in one cell.
#[derive(Default)]
struct Cell {
    position: [f64; 3],
    color: [f64; 3],
    opacity: f64,
    count: u32,
}

/// The level of detail of a pixel whose footprint is `footprint`: that of the cells nearest it in width
/// (within a factor of √2), cells doubling in side from level 0, `middle` wide (levels beyond
/// ±[`MAX_LEVEL`] and footprints that are not finite and positive taken as the nearest that is).
fn level_of(footprint: f32, middle: f32) -> i32 {
    let doublings = (footprint / middle).log2().round();
    if doublings.is_nan() {
        return 0;
    }
    doublings.clamp(-MAX_LEVEL as f32, MAX_LEVEL as f32) as i32
}

/// The side of the cells of `level`, those of level 0 being `middle` wide.
fn cell_side(level: i32, middle: f32) -> f32 {
    middle * 2f32.powi(level)
}

/// One round splat per cell holding surfels, each surfel in the cells of its level of detail ([`level_of`]
/// its footprint, level 0 as wide as the median footprint), less those whose center lies in a finer cell
/// and those some view sees through ([`seen_through`]); the splats and a description of the cells (how many splats of each width, finest
/// first).
fn splats_of(surfels: &Surfels, cameras: &[Camera]) -> (Splats, String) {
    let mut footprints = surfels.footprints.clone();
    let middle = footprints.len() / 2;
    let middle = footprints
        .select_nth_unstable_by(middle, f32::total_cmp)
        .1
        .max(1e-6);
    let mut cells: HashMap<[i32; 4], Cell> = HashMap::new();
    for (i, p) in surfels.positions.iter().enumerate() {
        let level = level_of(surfels.footprints[i], middle);
        let side = cell_side(level, middle);
        let [x, y, z] = p.map(|x| (x / side).floor() as i32);
        let c = cells.entry([level, x, y, z]).or_default();
        for (sum, x) in c.position.iter_mut().zip(p) {
            *sum += f64::from(*x);
        }
        for (sum, x) in c.color.iter_mut().zip(surfels.colors[i]) {
            *sum += f64::from(x);
        }
        c.opacity += f64::from(surfels.opacities[i]);
        c.count += 1;
    }
    let mut cells: Vec<([i32; 4], Cell)> = cells.into_iter().collect();
    cells.sort_unstable_by_key(|(key, _)| *key);
    let centers: Vec<[f32; 3]> = cells
        .iter()
        .map(|(_, c)| c.position.map(|x| (x / f64::from(c.count)) as f32))
        .collect();
    let side = |key: &[i32; 4]| cell_side(key[0], middle);
    let occupied: HashSet<[i32; 4]> = cells.iter().map(|(key, _)| *key).collect();
    let mut levels: Vec<i32> = cells.iter().map(|(key, _)| key[0]).collect();
    levels.dedup();
    // A cell whose center lies in a finer cell: the surface there is drawn as finely as the nearest view saw it.
    let in_finer = |key: &[i32; 4], p: [f32; 3]| {
        levels.iter().take_while(|&&level| level < key[0]).any(|&level| {
            let side = cell_side(level, middle);
            let [x, y, z] = p.map(|x| (x / side).floor() as i32);
            occupied.contains(&[level, x, y, z])
        })
    };
    let kept: Vec<bool> = cells
        .par_iter()
        .zip(&centers)
        .map(|((key, _), &p)| {
            !in_finer(key, p) && !seen_through(glam::Vec3::from(p), surfels, cameras, CARVE_CELLS * side(key))
        })
        .collect();
    let mut splats = Splats::default();
    let mut per_level: BTreeMap<i32, usize> = BTreeMap::new();
    for (((key, c), center), _) in cells.iter().zip(centers).zip(&kept).filter(|(_, &kept)| kept) {
        let n = f64::from(c.count);
        splats.positions.push(center);
        splats
            .colors
            .push(c.color.map(|x| ((x / n) as f32).clamp(0.0, 1.0)));
        splats.opacities.push(((c.opacity / n) as f32).clamp(0.0, 1.0));
        splats.scales.push([SPREAD * side(key); 3]);
        splats.rotations.push([1.0, 0.0, 0.0, 0.0]);
        *per_level.entry(key[0]).or_default() += 1;
    }
    let levels: Vec<String> = per_level
        .iter()
        .map(|(&level, n)| format!("{n} of {:.4}", cell_side(level, middle)))
        .collect();
    (splats, format!("cells: {}", levels.join(", ")))
}

/// Whether some view sees `p` in front of what it saw there by more than `margin`: it proves `p` to be in
/// empty space, and a splat there would hide its surface. Such points come from pixels whose expected depth
/// fell between surfaces (edges, thin parts, the field's haze).
fn seen_through(p: glam::Vec3, surfels: &Surfels, cameras: &[Camera], margin: f32) -> bool {
    let (width, height) = surfels.frame;
    cameras.iter().zip(&surfels.distances).any(|(camera, distances)| {
        let Some((row, col)) = camera.project(p, width, height) else {
            return false;
        };
        let inside = (0.0..height as f32).contains(&row) && (0.0..width as f32).contains(&col);
        inside && {
            let seen = distances[row as usize * width as usize + col as usize];
            seen.is_finite() && (p - camera.position()).length() < seen - margin
        }
    })
}

/// `nerfjit eval-views SCENE.bake`: the bake's views drawn from its splats and scored as `eval-views`
/// scores the field it came from — the same views (by default those its checkpoint's training validates on),
/// at the same size, on the same background — so that the two tables compare.
pub fn eval(
    args: &ViewArgs,
    cameras: Option<&Path>,
    format: Option<Layout>,
    json: Option<&Path>,
) -> Result<String> {
    let bake = bake_file::read(Path::new(args.source))?;
    let source = bake.source.to_string_lossy().into_owned();
    let (program, _) = crate::checkpoint::load_source(&source).map_err(|e| {
        Failure::Message(format!(
            "the checkpoint '{source}' that {} was baked from, whose data it is scored on: {e}",
            args.source
        ))
    })?;
    let set = ScoredSet::read(&source, &program, (args.size, bake.background), cameras, format)?;
    let start = Instant::now();
    let scene = SplatScene::new(&bake.splats, nerfjit_field::splat_shader()?);
    let draw = |camera: &Camera, (w, h): (u32, u32)| -> Result<VolumeFrame> {
        Ok(scene.render(camera, w, h, bake.background)?.0)
    };
    let Some(scores) = score_on_ranks(&set.views, &draw)? else {
        return Ok(String::new());
    };
    let how = serde_json::json!({ "splats": bake.splats.len(), "baked_from": source });
    report(
        args.source,
        &set,
        &scores,
        (bake.background, how, start.elapsed().as_secs_f64()),
        json,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::settings::schema::Form;

    #[test]
    fn a_bake_block_defaults_to_the_command_lines_options() {
        let setting = |name| {
            crate::settings::schema::BAKE
                .setting(name)
                .expect("a setting of bake blocks")
        };
        let Form::Number { default, .. } = setting("min_weight").form else {
            panic!("min_weight is a number")
        };
        assert_eq!(default as f32, MIN_WEIGHT);
        let Form::Whole { default, .. } = setting("size").form else {
            panic!("size is a whole number")
        };
        assert_eq!(
            default, None,
            "the block's size is the training views' unless given"
        );
    }

    #[test]
    fn baked_views_keep_the_training_views_aspect_ratio() {
        assert_eq!(baked_frame(800, 800, 400), (400, 400));
        assert_eq!(baked_frame(320, 240, 160), (160, 120));
        // A portrait phone's 1080×1920 photos read at a quarter, and a wide capture.
        assert_eq!(baked_frame(270, 480, baked_side(270, 480)), (135, 240));
        assert_eq!(baked_frame(400, 160, 200), (200, 80));
        // A view thinner than a pixel at the bake's size still has one.
        assert_eq!(baked_frame(1000, 1, 16), (16, 1));
    }

    #[test]
    fn pruning_tells_splats_well_inside_some_frame_from_those_near_every_edge() {
        use glam::{Vec2, Vec3};
        let camera = |eye: Vec3, at: Vec3| Camera::look_at(eye, at, Vec3::Y, Vec2::ONE, Vec2::ZERO).unwrap();
        let views = |cameras: Vec<Camera>| Views {
            cameras,
            images: Vec::new(),
            width: 40,
            height: 30,
            alpha: None,
            masks: None,
        };
        // In front of the first camera at the frame's center; far above its frame; behind it; beside it;
        // inside its frame 2 pixels from its top edge (less than EDGE of its 40 pixels); 5 pixels from it.
        let positions = [
            [0.0, 0.0, 0.0],
            [0.0, 20.0, 0.0],
            [0.0, 0.0, 6.0],
            [20.0, 0.0, 0.0],
            [0.0, 2.6, 0.0],
            [0.0, 2.0, 0.0],
        ];
        let first = camera(Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO);
        let one = views(vec![first]);
        let well_inside = well_inside_some_frame(&positions, &one);
        assert_eq!(well_inside, [true, false, false, false, false, true]);
        // A second camera, beside the first, frames the point above the first camera's frame.
        let second = camera(Vec3::new(0.0, 20.0, 3.0), Vec3::new(0.0, 20.0, 0.0));
        let two = views(vec![first, second]);
        let well_inside = well_inside_some_frame(&positions, &two);
        assert_eq!(well_inside, [true, true, false, false, false, true]);
    }

    #[test]
    fn pixels_fall_in_cells_as_wide_as_their_footprints() {
        let middle = 0.01;
        assert_eq!(level_of(0.01, middle), 0);
        assert_eq!(level_of(0.0072, middle), 0);
        assert_eq!(level_of(0.014, middle), 0);
        assert_eq!(level_of(0.0145, middle), 1);
        assert_eq!(level_of(0.05, middle), 2);
        assert_eq!(level_of(1.0, middle), 7);
        assert_eq!(level_of(0.001, middle), -3);
        assert_eq!(level_of(f32::INFINITY, middle), MAX_LEVEL);
        assert_eq!(level_of(0.0, middle), -MAX_LEVEL);
        assert_eq!(level_of(f32::NAN, middle), 0);
        for level in -MAX_LEVEL..=MAX_LEVEL {
            let side = cell_side(level, middle);
            assert_eq!(level_of(side, middle), level);
            assert_eq!(level_of(1.4 * side, middle), level);
            assert_eq!(level_of(0.72 * side, middle), level);
        }
    }
}
