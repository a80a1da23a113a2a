//! `nerfjit render` and `nerfjit eval-views`: a script's volume field (or a training checkpoint's)
//! rendered from every camera of a Blender-format camera file, written as PNGs/GIF or scored against the
//! file's images with PSNR and SSIM.

use std::path::{Path, PathBuf};
use std::time::Instant;

use nerfjit_dsl::config::{Settings, Value};
use nerfjit_dsl::{Diagnostic, Program};
use nerfjit_jit::{KernelCache, Precision};
use nerfjit_runtime::splats::SplatScene;
use nerfjit_runtime::volume::composite::Mode;
use nerfjit_runtime::volume::render::VolumeFrame;
use nerfjit_runtime::{
    rgb_image, Camera, DensityEma, DepthSpacing, Layout, OccupancyGrid, Quantize, Views, VolumeSettings,
};

use crate::failure::{at, Failure, Result};
use crate::folder_lock::lock_output_folders;
use crate::frame_files::write_images;
use crate::settings::block::MAX_PIXELS;
use crate::settings::camera::FrameSize;
use crate::settings::primitives::triple;
use crate::settings::values::SkipEmpty;
use crate::training::data_source::{reader_call, scored_views, DataSet, ScoredViews, DEFAULT_WIDTH};
use crate::training::validation::{
    field_renderer, means, score_on_ranks, MeanScores, ViewRenderer, ViewScore,
};
use nerfjit_field::VolumeFields;

/// Where the field comes from and how to render it. Settings not given come from the script's `train`
/// block (a checkpoint's script included): see [`ViewArgs::resolve`].
pub struct ViewArgs<'a> {
    /// A script, or a checkpoint written by `train` (it holds its script).
    pub source: &'a str,
    /// Image side in pixels (with `render --cameras` the width); `None`: [`DEFAULT_WIDTH`], or views scored
    /// from the field's own training data at its training's scale.
    pub size: Option<u32>,
    /// Start of the sampled interval.
    pub near: Option<f32>,
    /// End of the sampled interval.
    pub far: Option<f32>,
    /// Samples per ray.
    pub samples: Option<usize>,
    /// Background color (the data's alpha is composited on it too).
    pub background: Option<[f32; 3]>,
    /// Importance samples per ray (hierarchical sampling with the script's coarse field; 0: none).
    pub importance: Option<usize>,
    /// Evaluate every sample even where the script trains with an occupancy grid or early termination.
    pub exact: bool,
}

/// How a field is rendered, every setting decided.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rendering {
    /// Start of the sampled interval.
    pub near: f32,
    /// End of the sampled interval.
    pub far: f32,
    /// Samples per ray.
    pub samples: usize,
    /// Background color.
    pub background: [f32; 3],
    /// Importance samples per ray (0: none).
    pub importance: usize,
    /// How the samples are spread between near and far.
    pub spacing: DepthSpacing,
    /// The occupancy grid the script trains with (rebuilt from the trained field), if any.
    pub skip_empty: Option<SkipEmpty>,
    /// Whether that grid is a running one (`grid_update: ema`): rebuilt undilated, as its first state.
    pub running_grid: bool,
    /// Transmittance below which a ray stops, as the script trains.
    pub early_termination: Option<f32>,
    /// The arithmetic of the networks' products, as the script trains.
    pub products: Precision,
}

impl<'a> ViewArgs<'a> {
    /// The field of `source` rendered at `size`, every other setting as its script's `train` block trains
    /// (see [`ViewArgs::resolve`]).
    pub fn as_trained(source: &'a str, size: Option<u32>) -> ViewArgs<'a> {
        ViewArgs {
            source,
            size,
            near: None,
            far: None,
            samples: None,
            background: None,
            importance: None,
            exact: false,
        }
    }

    /// The image side (or width) asked, else [`DEFAULT_WIDTH`].
    pub fn side(&self) -> u32 {
        self.size.unwrap_or(DEFAULT_WIDTH)
    }

    /// The settings given, else those `program`'s first `train` block trains with (its `near`, `far`,
    /// `samples`, `importance`, and `background` or its Blender data's background), else near 2, far 6,
    /// 128 samples, black, no importance sampling.
    pub fn resolve(&self, program: &Program) -> Rendering {
        let script = Rendering::of_script(program);
        Rendering {
            near: self.near.unwrap_or(script.near),
            far: self.far.unwrap_or(script.far),
            samples: self.samples.unwrap_or(script.samples),
            background: self.background.unwrap_or(script.background),
            importance: self.importance.unwrap_or(script.importance),
            spacing: script.spacing,
            skip_empty: script.skip_empty.filter(|_| !self.exact),
            running_grid: script.running_grid,
            early_termination: script.early_termination.filter(|_| !self.exact),
            products: script.products,
        }
    }
}

impl Rendering {
    /// The settings `program`'s first `train` block trains with, else near 2, far 6, 128 samples, black,
    /// no importance sampling.
    pub fn of_script(program: &Program) -> Rendering {
        let trained = TrainedWith::of(program);
        Rendering {
            near: trained.near.unwrap_or(2.0),
            far: trained.far.unwrap_or(6.0),
            samples: trained.samples.unwrap_or(128),
            background: trained.background.unwrap_or([0.0; 3]),
            importance: trained.importance.unwrap_or(0),
            spacing: trained.spacing.unwrap_or_default(),
            skip_empty: trained.skip_empty,
            running_grid: trained.running_grid,
            early_termination: trained.early_termination,
            products: trained.products,
        }
    }
}

/// The render settings a script's `train` block gives (those it writes, valid or not checked here: the
/// block was checked when it trained).
#[derive(Default)]
struct TrainedWith {
    near: Option<f32>,
    far: Option<f32>,
    samples: Option<usize>,
    background: Option<[f32; 3]>,
    importance: Option<usize>,
    spacing: Option<DepthSpacing>,
    skip_empty: Option<SkipEmpty>,
    running_grid: bool,
    early_termination: Option<f32>,
    products: Precision,
}

impl TrainedWith {
    fn of(program: &Program) -> TrainedWith {
        let block = program
            .blocks()
            .into_iter()
            .find(|b| crate::settings::schema::kind_of(b) == Some(crate::settings::schema::Kind::Train));
        let Some(mut settings) = block.and_then(|b| Settings::new(program, b).ok()) else {
            return TrainedWith::default();
        };
        let mut number = |key: &str| settings.take(key).and_then(|v| v.number().ok());
        let (near, far) = (number("near"), number("far"));
        let (samples, importance) = (number("samples"), number("importance"));
        let early_termination = number("early_termination")
            .filter(|&t| t > 0.0 && t <= 1.0)
            .map(|t| t as f32);
        let count = |x: Option<f64>| x.filter(|n| *n >= 0.0 && n.fract() == 0.0).map(|n| n as usize);
        let data_background = settings.take("data").and_then(|data| match data.value {
            Value::Call(_, args) => args
                .into_iter()
                .find(|(name, _)| name.as_deref() == Some("background"))
                .and_then(|(_, v)| triple(&v).ok()),
            _ => None,
        });
        let background = settings.take("background").and_then(|v| triple(&v).ok());
        let spacing = settings
            .take("spacing")
            .and_then(|v| crate::settings::values::depth_spacing(&v).ok());
        let skip_empty = settings
            .take("skip_empty")
            .and_then(|v| crate::settings::values::skip_empty(&v).ok().flatten());
        let running_grid = crate::settings::values::grid_update(settings.take("grid_update"))
            .is_ok_and(|u| u != crate::settings::values::GridUpdate::Rebuild);
        let products = match settings.take("products").map(|v| v.value) {
            Some(Value::Name(n)) => Precision::named(&n).unwrap_or_default(),
            _ => Precision::F32,
        };

        TrainedWith {
            near: near.map(|x| x as f32),
            far: far.map(|x| x as f32),
            samples: count(samples),
            background: background.or(data_background),
            importance: count(importance),
            spacing,
            skip_empty,
            running_grid,
            early_termination,
            products,
        }
    }
}

impl Rendering {
    /// The renderer's settings for a field of `mode`.
    pub fn settings(&self, mode: Mode) -> VolumeSettings {
        VolumeSettings {
            near: self.near,
            far: self.far,
            samples: self.samples,
            mode,
            background: Some(self.background),
            early_termination: self.early_termination,
            spacing: self.spacing,
        }
    }

    /// The occupancy grid to render the field of `source` with: the script's `skip_empty` grid as the
    /// checkpoint `source` keeps it (the grid its run last validated with), else built from the field
    /// with `params` as training builds it (a running grid as its first state); with hierarchical
    /// sampling both passes skip its empty cells.
    pub fn occupancy(
        &self,
        source: &str,
        fields: &VolumeFields,
        params: &[f32],
    ) -> Result<Option<OccupancyGrid>> {
        let Some(s) = self.skip_empty else {
            return Ok(None);
        };
        if crate::checkpoint::is_checkpoint(source) {
            let saved = crate::checkpoint::saved_occupancy(Path::new(source))?;
            if let Some(grid) = saved.filter(|g| s.fits(g)) {
                return Ok(Some(grid));
            }
        }
        let mode = fields.fine.mode;
        let grid = s.space.with_grid_field(
            &fields.fine.bind_density(params),
            (s.bounds, s.resolution),
            (mode, s.thickness),
            |density| {
                if self.running_grid {
                    DensityEma::probe(density, s.bounds, s.resolution)?.grid(mode, s.threshold)
                } else {
                    OccupancyGrid::build_for_training(density, s.bounds, s.resolution, mode, s.threshold)
                }
            },
        )?;
        Ok(Some(grid.in_space(s.space)))
    }
}

/// The held-out views the first `train` block of `program` (from `source`) validates on, loaded as in
/// training, and their description.
pub fn held_out_views(source: &str, program: &Program) -> Result<(Views, String)> {
    let folder = Path::new(source).parent().and_then(|p| p.to_str()).unwrap_or("");
    let plan = crate::blocks::train::TrainPlan::new(crate::settings::block::first_block(
        program,
        crate::settings::schema::Kind::Train,
        folder,
    )?)?;
    let (Some(views), Some(described)) = (plan.load_views()?.1, plan.held_out_description()) else {
        return Err(Failure::Message(format!(
            "{source}'s train block holds no views out (no 'val' setting): give --cameras FILE"
        )));
    };
    Ok((views, described))
}

/// Every how many views the train block of `source` (a script or checkpoint, compiled as `program`)
/// holds out of its data for validation (`holdout(every: n)`), and how many of them it scores; `None`
/// when it validates on another file or not at all.
fn held_out_every(source: &str, program: &Program) -> Result<Option<(usize, Option<usize>)>> {
    let folder = Path::new(source).parent().and_then(|p| p.to_str()).unwrap_or("");
    let block = crate::settings::block::first_block(program, crate::settings::schema::Kind::Train, folder)?;
    Ok(crate::blocks::train::TrainPlan::new(block)?.held_out_every())
}

/// The data the field of `source` (a script or checkpoint, compiled as `program`) was trained on, if its
/// `train` block names data found here: camera files given to render or score the field are read as it
/// read its own (a DTU scan trained with `normalize: true` is rendered normalized, not in the scan's frame).
pub fn trained_data(source: &str, program: &Program) -> Option<DataSet> {
    let folder = Path::new(source).parent().unwrap_or(Path::new(""));
    crate::blocks::train::train_data(program, folder)
}

/// Where `nerfjit render` takes its cameras from.
pub enum CameraSource<'a> {
    /// A camera file: Blender or nerfstudio transforms, a nerfstudio `camera_path.json`, a COLMAP model,
    /// LLFF scene or DTU scan folder or the course's `box_cameras.json`; and the layout to read a folder
    /// holding several as (by default the one the field's training read there, else the most specific).
    File(&'a Path, Option<Layout>),
    /// A camera path written as in a script, e.g. `orbit(radius: 4, frames: 60, up: z, focal: 2)`.
    Path(&'a str),
    /// The command's default: for `render`, the first `render` block of the script (a checkpoint's
    /// script included) that sets a camera.
    Default,
}

impl CameraSource<'_> {
    /// The cameras of a file or a path with the file's frame size if it states one; `None` for the default.
    /// A capture's file is normalized as `program`'s training normalized its data (from `source`, a script
    /// or checkpoint: see [`trained_data`]).
    pub(crate) fn cameras(
        &self,
        source: &str,
        program: &Program,
    ) -> Result<Option<(Vec<Camera>, Option<FrameSize>)>> {
        Ok(match self {
            CameraSource::File(file, format) => {
                // A reader written out, or the field's own training data: read as it says or as training
                // read it; any other file or folder by its layout.
                let trained = trained_data(source, program);
                let own = || {
                    let matches = |t: &DataSet| t.reads(file) && format.is_none_or(|f| t.layout() == Some(f));
                    trained.clone().filter(matches)
                };
                match reader_call(&file.to_string_lossy(), Path::new("."))?.or_else(own) {
                    Some(set) => Some((set.cameras()?, set.frame_size()?)),
                    None => Some(crate::settings::camera::camera_file(
                        file,
                        trained.and_then(|d| d.normalizes()),
                        *format,
                    )?),
                }
            }
            CameraSource::Path(text) => Some((path_cameras(text)?, None)),
            CameraSource::Default => None,
        })
    }
}

/// A script's or checkpoint's volume field opened to render single views in memory, as `render` renders
/// them (the train block's near, far, samples, background and occupancy grid unless `args` says): for callers
/// that keep the images, such as the Python package.
pub struct FieldViews {
    /// The program (a checkpoint's holds its script).
    pub program: Program,
    /// The params it renders with.
    pub params: Vec<f32>,
    /// How it renders.
    pub rendering: Rendering,
    fields: VolumeFields,
    grid: Option<OccupancyGrid>,
}

impl FieldViews {
    /// Opens `args.source` and compiles its fields.
    pub fn open(args: &ViewArgs) -> Result<FieldViews> {
        let (program, params) = crate::checkpoint::load_source(args.source)?;
        FieldViews::new(program, params, args)
    }

    /// Compiles the fields of `program` (`args.source`'s) to render with `params`.
    pub fn new(program: Program, params: Vec<f32>, args: &ViewArgs) -> Result<FieldViews> {
        let rendering = args.resolve(&program);
        let fields = VolumeFields::compile(
            &program,
            &KernelCache::new(),
            rendering.importance,
            rendering.products,
        )?;
        let grid = rendering.occupancy(args.source, &fields, &params)?;
        Ok(FieldViews {
            program,
            params,
            rendering,
            fields,
            grid,
        })
    }

    /// The view of `camera` at `width`×`height`: colour, expected depth and opacity per pixel.
    pub fn render(&self, camera: &Camera, width: u32, height: u32) -> Result<VolumeFrame> {
        let settings = self.rendering.settings(self.fields.fine.mode);
        let frame = (self.fields).render_with(
            camera,
            (width, height),
            &self.params,
            &settings,
            self.grid.as_ref(),
        )?;
        Ok(frame)
    }
}

/// `nerfjit render`: the field (or a baked scene, `.bake`, drawn from its splats) rendered from every camera
/// of `cameras` into `out`: a `.gif` or `.mp4` file of all views, or a folder of PNGs (`view_000.png`, …;
/// one `views.gif` with `gif`). A bake's cameras are read as the checkpoint it was baked from read its data.
pub fn render(args: &ViewArgs, cameras: CameraSource, out: &Path, gif: bool) -> Result<String> {
    let bake = match crate::bake_file::is_bake(Path::new(args.source)) {
        true => Some(crate::bake_file::read(Path::new(args.source))?),
        false => None,
    };
    let source = bake.as_ref().map_or(args.source.to_string(), |b| {
        b.source.to_string_lossy().into_owned()
    });
    let (program, params) = crate::checkpoint::load_source(&source)?;
    let (cameras, frame) = match cameras.cameras(&source, &program)? {
        Some(found) => found,
        None => (
            script_cameras(&program)?.ok_or_else(|| {
                Failure::Message(format!(
                    "{} has no render block with a camera: give --cameras FILE or --path 'orbit(radius: 4, frames: 60, up: z, focal: 2)'",
                    args.source
                ))
            })?,
            None,
        ),
    };
    // --size is the width; the height keeps the aspect ratio of the file's frames.
    let (n, width) = (cameras.len(), args.side());
    let height = frame.map_or(width, |(w, h)| {
        ((f64::from(width) * f64::from(h) / f64::from(w)).round() as u32).clamp(1, 16384)
    });
    let pixels = n as u64 * u64::from(width) * u64::from(height);
    if pixels > MAX_PIXELS {
        return Err(Failure::Message(format!(
            "{n} views of {width}×{height} are {pixels} pixels, more than the {MAX_PIXELS} kept in memory at once"
        )));
    }
    let animation = matches!(out.extension().and_then(|e| e.to_str()), Some("gif" | "mp4"));
    let target: PathBuf = if animation {
        out.to_path_buf()
    } else {
        std::fs::create_dir_all(out)
            .map_err(|e| Failure::Message(format!("cannot create output folder '{}': {e}", out.display())))?;
        out.join(if gif { "views.gif" } else { "view.png" })
    };
    let _locks = lock_output_folders([target.as_path()])?;
    let field_args = ViewArgs {
        source: &source,
        ..*args
    };
    let (draw, how): (Box<ViewRenderer>, String) = match &bake {
        Some(bake) => {
            let scene = SplatScene::new(&bake.splats, nerfjit_field::splat_shader()?);
            (
                Box::new(
                    move |camera: &Camera, (w, h): (u32, u32)| -> Result<VolumeFrame> {
                        Ok(scene.render(camera, w, h, bake.background)?.0)
                    },
                ),
                format!("{} splats", bake.splats.len()),
            )
        }
        None => {
            let view = FieldViews::new(program, params, &field_args)?;
            let r = &view.rendering;
            let how = format!("near {}, far {}, {} samples", r.near, r.far, r.samples);
            (
                Box::new(move |camera: &Camera, (w, h): (u32, u32)| view.render(camera, w, h)),
                how,
            )
        }
    };
    let start = Instant::now();
    // Each rank renders its share of the views; rank 0 gathers and writes them.
    let rendered = crate::cluster::split(n, |i| -> Result<Vec<u8>> {
        let f = draw(&cameras[i], (width, height))?;
        Ok(rgb_image(f.width, f.height, &f.rgb, Quantize::Truncate)?.into_raw())
    })
    .map_err(Failure::Message)?;
    let Some(rendered) = rendered else {
        return Ok(String::new());
    };
    let images = rendered
        .into_iter()
        .map(|raw| image::RgbImage::from_raw(width, height, raw).expect("a frame of the size rendered"))
        .collect();
    let seconds = start.elapsed().as_secs_f64();
    write_images(&target, images, 100)?;
    let per_view = seconds / n.max(1) as f64;
    let written = if animation || gif { &target } else { out };
    Ok(format!(
        "rendered {n} views of {width}×{height} in {seconds:.2} s ({per_view:.2} s/view; {how}) → {}",
        written.display()
    ))
}

/// The cameras of a camera path written as in a script (`--path`).
fn path_cameras(text: &str) -> Result<Vec<Camera>> {
    let script = format!("render volume {{ camera: {text} }}\n");
    let program = nerfjit_dsl::compile("--path", &script).map_err(Failure::Script)?;
    Ok(script_cameras(&program)?.expect("the block sets a camera"))
}

/// The cameras of the first `render` block of `program` that sets `camera`, if any.
pub fn script_cameras(program: &Program) -> Result<Option<Vec<Camera>>> {
    for block in program.blocks().into_iter().filter(|b| b.kind.name == "render") {
        let mut settings = Settings::new(program, block).map_err(|d| at(program, d))?;
        let Some(v) = settings.take("camera") else {
            continue;
        };
        let made = crate::settings::camera::cameras(&v, Path::new(".")).map_err(|d| at(program, d))?;
        let cameras = made.map_err(|e| at(program, Diagnostic::new(v.span, e)))?;
        return Ok(Some(cameras));
    }
    Ok(None)
}

/// The views `nerfjit eval-views` scores, what they are, and (when they are the field's own training data
/// with views held out) every how many it held out and how many it scored.
pub(crate) struct ScoredSet {
    /// The views and their images.
    pub views: Views,
    /// Where they come from, for the report.
    pub described: String,
    /// `holdout(every: n)` and its limit, when the views are the field's own data.
    pub held_out: Option<(usize, Option<usize>)>,
}

impl ScoredSet {
    /// With `cameras` (a file, a folder read by its layout or as `format`, or a reader call; see
    /// [`scored_views`]) every view it holds, at `width` on `background`; without, the views the train
    /// block of `source` (compiled as `program`) validates on.
    pub(crate) fn read(
        source: &str,
        program: &Program,
        (width, background): (Option<u32>, [f32; 3]),
        cameras: Option<&Path>,
        format: Option<Layout>,
    ) -> Result<ScoredSet> {
        let Some(file) = cameras else {
            let (views, described) = held_out_views(source, program)?;
            return Ok(ScoredSet {
                views,
                described,
                held_out: None,
            });
        };
        let trained = trained_data(source, program);
        let read = scored_views(&ScoredViews {
            cameras: file,
            format,
            width,
            background,
            trained: trained.as_ref(),
        })?;
        let held_out = match read.as_trained {
            true => held_out_every(source, program)?,
            false => None,
        };
        Ok(ScoredSet {
            views: read.views,
            described: format!("the views of {} ({})", file.display(), read.how),
            held_out,
        })
    }
}

/// `nerfjit eval-views`: PSNR and SSIM of every view, and their means (also as JSON in `json`). With
/// `cameras` every view of that file; without, the views the field's training validates on (see
/// `ScoredSet::read`); when those are the field's own training data with views held out, the mean over
/// the held-out ones too (which equals its validation at its training's scale). A baked scene is scored
/// the same way by [`crate::commands::bake::eval`].
pub fn eval(
    args: &ViewArgs,
    cameras: Option<&Path>,
    format: Option<Layout>,
    json: Option<&Path>,
) -> Result<String> {
    let (program, params) = crate::checkpoint::load_source(args.source)?;
    let rendering = args.resolve(&program);
    let set = ScoredSet::read(
        args.source,
        &program,
        (args.size, rendering.background),
        cameras,
        format,
    )?;
    let cache = KernelCache::new();
    let fields = VolumeFields::compile(&program, &cache, rendering.importance, rendering.products)?;
    let start = Instant::now();
    let grid = rendering.occupancy(args.source, &fields, &params)?;
    // Each rank scores its share of the views; rank 0 reports them all.
    let settings = rendering.settings(fields.fine.mode);
    let render = field_renderer(&fields, &params, &settings, grid.as_ref());
    let Some(scores) = score_on_ranks(&set.views, &render)? else {
        return Ok(String::new());
    };
    let rendered_with = serde_json::json!({
        "near": rendering.near,
        "far": rendering.far,
        "samples": rendering.samples,
        "importance": rendering.importance,
        "occupancy_grid": grid.is_some(),
        "early_termination": rendering.early_termination,
    });
    let seconds = start.elapsed().as_secs_f64();
    report(
        args.source,
        &set,
        &scores,
        (rendering.background, rendered_with, seconds),
        json,
    )
}

/// The table of `scores` of the views of `set` (and the JSON report in `json`, with what `rendered` says:
/// the background, how they were rendered, in how many seconds).
pub(crate) fn report(
    source: &str,
    set: &ScoredSet,
    scores: &[ViewScore],
    (background, rendered_with, seconds): ([f32; 3], serde_json::Value, f64),
    json: Option<&Path>,
) -> Result<String> {
    let views = &set.views;
    let masked = views.masks.is_some();
    let mut lines = String::from("view  PSNR (dB)  SSIM");
    lines += if masked { "    masked PSNR (dB)\n" } else { "\n" };
    let masked_column = |m: Option<f64>| match (masked, m) {
        (false, _) => String::new(),
        (true, Some(m)) => format!("  {m:>15.2}"),
        (true, None) => format!("  {:>15}", "(empty mask)"),
    };
    for (i, v) in scores.iter().enumerate() {
        let column = masked_column(v.masked_psnr.map(f64::from));
        lines += &format!("{i:>4}  {:>9.2}  {:.4}{column}\n", v.psnr, v.ssim);
    }
    let mean = means(scores);
    let column = masked_column(mean.masked_psnr);
    lines += &format!("mean  {:>9.2}  {:.4}{column}\n", mean.psnr, mean.ssim);
    // The views its training held out of these, as its validation chose them.
    let held: Option<(Vec<usize>, MeanScores)> = set.held_out.map(|(every, limit)| {
        let chosen: Vec<usize> = (0..scores.len())
            .step_by(every)
            .take(limit.unwrap_or(usize::MAX))
            .collect();
        let mean = means(&chosen.iter().map(|&i| scores[i]).collect::<Vec<_>>());
        (chosen, mean)
    });
    if let Some((chosen, mean)) = &held {
        let column = masked_column(mean.masked_psnr);
        let listed: Vec<String> = chosen.iter().map(usize::to_string).collect();
        lines += &format!(
            "held  {:>9.2}  {:.4}{column}   (views {}: those its validation scores)\n",
            mean.psnr,
            mean.ssim,
            listed.join(", ")
        );
    }
    if let Some(path) = json {
        let mut report = serde_json::json!({
            "source": source,
            "protocol": {
                "views": set.described,
                "count": views.len(),
                "width": views.width,
                "height": views.height,
                "background": background,
                "masks": if masked { "PSNR also inside the data's object masks (mask ≥ ½)" } else { "none: whole images" },
            },
            "width": views.width,
            "height": views.height,
            "background": background,
            "views": scores.iter().map(|v| serde_json::json!({
                "psnr": v.psnr, "ssim": v.ssim, "masked_psnr": v.masked_psnr,
            })).collect::<Vec<_>>(),
            "mean_psnr": mean.psnr,
            "mean_ssim": mean.ssim,
            "mean_masked_psnr": mean.masked_psnr,
            "held_out": held.as_ref().map(|(chosen, mean)| serde_json::json!({
                "views": chosen, "mean_psnr": mean.psnr, "mean_ssim": mean.ssim,
                "mean_masked_psnr": mean.masked_psnr,
            })),
            "render_seconds": seconds,
        });
        if let (Some(fields), Some(how)) = (report.as_object_mut(), rendered_with.as_object()) {
            fields.extend(how.clone());
        }
        nerfjit_runtime::write_whole(
            path,
            serde_json::to_string_pretty(&report)
                .unwrap_or_default()
                .as_bytes(),
        )?;
    }
    Ok(lines)
}
