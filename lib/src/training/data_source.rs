//! The `data` setting of `train`: which images and cameras a radiance field is fitted to, and how
//! they are loaded.
//!
//! - `views("box_cameras.json")`: the course's cameras with `.npy`/PNG images;
//! - `blender("transforms_train.json", size: 128, background: [0, 0, 0], views: 20)`: NeRF-synthetic
//!   data, area-downscaled to `size`², alpha composited on the background, the first `views` frames;
//! - `nerfstudio("transforms.json", downscale: 2, background: [0, 0, 0], views: 20, normalize: true)`:
//!   a nerfstudio / instant-ngp capture (per-frame intrinsics, distortion, any image size, PNG or JPEG);
//! - `colmap("sparse/0", images: "images", downscale: 2, ...)`: a COLMAP model (text or binary);
//! - `llff("fern", downscale: 8, ...)`: an LLFF forward-facing scene (`poses_bounds.npy`, the images of
//!   `images_8/` or of `images/` divided on load);
//! - `dtu("scan24", masks: true, ...)`: a DTU scan in the IDR / NeuS layout (`cameras_sphere.npz`,
//!   `image/` or `images/`, `mask/`), in the frame where the object is inside the unit sphere.
//!
//! Captures are moved into nerfjit's frame (z up, centered on what the cameras look at, cameras 4 units
//! away on average) unless `normalize: false`, the default of `dtu` (its unit sphere is the frame every
//! surface method works in).

use std::path::{Path, PathBuf};

use nerfjit_dsl::config::{Spanned, Value};
use nerfjit_dsl::{budget, Diagnostic};
use nerfjit_runtime::{
    choose_layout, default_images_folder, layouts_at, load_blender_cameras, load_blender_views,
    load_box_cameras, load_box_views, load_colmap, load_dtu, load_llff, load_nerfstudio, Camera, Capture,
    CaptureRequest, Layout, Normalization, Views,
};

use crate::failure::{at, Failure, Result};
use crate::settings::primitives::{triple, whole, CallArgs};

/// How to load a Blender data set: image size, background, and how many views (the first n; all if None).
#[derive(Clone, Copy, Debug)]
pub struct BlenderData {
    /// Side of the square images after downscaling.
    pub size: u32,
    /// The color under transparent pixels.
    pub background: [f32; 3],
    /// Only the first this many frames, if given.
    pub views: Option<usize>,
}

/// How to load a capture (nerfstudio or COLMAP).
#[derive(Clone, Copy, Debug)]
pub struct CaptureData {
    /// Divide both image sides by this.
    pub downscale: u32,
    /// The color under transparent pixels.
    pub background: [f32; 3],
    /// Only the first this many frames, if given.
    pub views: Option<usize>,
    /// Move the capture into nerfjit's frame.
    pub normalize: bool,
}

/// The kinds of data set.
#[derive(Clone, Debug)]
pub enum DataKind {
    /// The course's `box_cameras.json`.
    Course,
    /// A Blender / NeRF-synthetic `transforms_*.json`.
    Blender(BlenderData),
    /// A nerfstudio / instant-ngp `transforms.json`.
    Nerfstudio(CaptureData),
    /// A COLMAP model folder and the folder of its images.
    Colmap(CaptureData, PathBuf),
    /// An LLFF scene folder (`poses_bounds.npy`).
    Llff(CaptureData),
    /// A DTU scan folder (`cameras_sphere.npz`), and whether its masks are applied.
    Dtu(CaptureData, bool),
}

/// A data set: where it is and how to load it.
#[derive(Clone, Debug)]
pub struct DataSet {
    /// The camera file (or, for COLMAP, LLFF and DTU, the model's or the scene's folder).
    pub path: PathBuf,
    /// Its kind.
    pub kind: DataKind,
}

const HINT: &str = "use views(\"box_cameras.json\"), blender(\"transforms_train.json\", size: 128), \
                    nerfstudio(\"transforms.json\"), colmap(\"sparse/0\", images: \"images\"), \
                    llff(\"scene\", downscale: 8) or dtu(\"scan\", masks: true)";

/// What `--cameras` of `eval-views` and `compare` names, and how to read it.
#[derive(Clone, Copy, Debug)]
pub struct ScoredViews<'a> {
    /// A camera file or data folder, or a reader written as in a script (`dtu("scan24", masks: true)`).
    pub cameras: &'a Path,
    /// The layout to read a folder holding several as (`--format`); the most specific by default.
    pub format: Option<Layout>,
    /// The width to read the views at (Blender: the side); `None`: as the field's training read them
    /// when these are its data, else [`DEFAULT_WIDTH`].
    pub width: Option<u32>,
    /// The color the images' alpha is composited on.
    pub background: [f32; 3],
    /// The data the field was trained on, when known.
    pub trained: Option<&'a DataSet>,
}

/// The width views are scored at when neither `--size` nor the field's training says.
pub const DEFAULT_WIDTH: u32 = 128;

/// Views read for scoring, and how they were read.
pub struct ReadViews {
    /// The views.
    pub views: Views,
    /// How they were read, for people: "read as DTU (cameras_sphere.npz) as its training read them".
    pub how: String,
    /// Whether they are the field's own training data read as its training read them.
    pub as_trained: bool,
}

/// The views of `request.cameras` with their images, to score renders against:
/// - a reader written as in a script (`llff("fern", downscale: 8)`): read as it says;
/// - the data the field was trained on (its camera file or folder, or the folder holding it): read as its
///   training read it (the reader and its arguments after `--set` overrides: masks, normalization, views),
///   at its training's scale unless a width is asked;
/// - any other file or folder: read by its layout ([`choose_layout`]: the most specific, or `format`; a
///   folder holding several is noted), every frame, downscaled by the whole factor nearest to the frames'
///   width ÷ the width (Blender transforms at width²). A capture is normalized or kept in its frame as
///   the data the field was trained on was ([`DataSet::normalizes`]; without it, as each kind is by
///   default: captures normalized, DTU scans in the scan's frame, as `render --cameras` places them).
///
/// A DTU scan's masks, where it has them, black out the background as training with `masks: true` does,
/// unless the field was trained on that kind of scan without them: then the images are whole and the
/// masks only choose the pixels of the masked score.
pub fn scored_views(request: &ScoredViews) -> Result<ReadViews> {
    let ScoredViews {
        cameras: file,
        format,
        width,
        background,
        trained,
    } = *request;
    let written = file.to_string_lossy();
    if let Some(set) = reader_call(&written, Path::new("."))? {
        let set = set.on_background(background).at_width(width)?;
        let as_trained = trained.is_some_and(|t| t.same_data_as(&set));
        let views = set.scored()?;
        let how = format!("read as {written}");
        return Ok(ReadViews {
            views,
            how,
            as_trained,
        });
    }
    let own = trained.filter(|t| t.reads(file) && format.is_none_or(|f| t.layout() == Some(f)));
    if let Some(set) = own {
        let set = set.on_background(background).at_width(width)?;
        let how = format!(
            "read as {} as its training read them",
            set.layout().map_or("the course's views", Layout::title)
        );
        let views = set.scored()?;
        return Ok(ReadViews {
            views,
            how,
            as_trained: true,
        });
    }
    let width = width.unwrap_or(DEFAULT_WIDTH);
    let Some(chosen) = choose_layout(file, format)? else {
        if file.is_dir() {
            return Err(Failure::Message(format!(
                "'{}' holds no data set nerfjit reads: no DTU camera archive, poses_bounds.npy, transforms.json, \
                 COLMAP model (here or in sparse/0) or transforms_*.json",
                file.display()
            )));
        }
        // Not a layout of captured views: the course's camera file, its images as they are.
        let set = DataSet {
            path: file.to_path_buf(),
            kind: DataKind::Course,
        };
        let how = "read as the course's cameras".to_string();
        return Ok(ReadViews {
            views: set.views()?,
            how,
            as_trained: false,
        });
    };
    if let Some(note) = chosen.note(file) {
        crate::console::note(&note);
    }
    let how = format!("read as {}", chosen.found.describe());
    let source = chosen.found.source.clone();
    let normalize = trained.and_then(DataSet::normalizes);
    let data = CaptureData {
        downscale: 1,
        background,
        views: None,
        normalize: normalize.unwrap_or(true),
    };
    let kind = match chosen.found.layout {
        Layout::Blender if source.is_dir() => {
            return Err(Failure::Message(format!(
                "'{}' is a Blender data set ({}): name one of its camera files",
                file.display(),
                chosen.found.evidence
            )))
        }
        Layout::Blender => {
            let views = load_blender_views(&source, Some(width), background, None)?;
            return Ok(ReadViews {
                views,
                how,
                as_trained: false,
            });
        }
        Layout::Llff => DataKind::Llff(data),
        Layout::Dtu => {
            let masks = source.join("mask").is_dir();
            let masks_apart = matches!(trained.map(|t| &t.kind), Some(DataKind::Dtu(_, false)));
            let data = CaptureData {
                normalize: normalize.unwrap_or(false),
                ..data
            };
            DataKind::Dtu(data, masks && !masks_apart)
        }
        Layout::Colmap => {
            let images = default_images_folder(&source).unwrap_or_else(|| source.clone());
            DataKind::Colmap(data, images)
        }
        Layout::Nerfstudio => DataKind::Nerfstudio(data),
    };
    let set = DataSet { path: source, kind }.at_width(Some(width))?;
    let views = set.scored()?;
    Ok(ReadViews {
        views,
        how,
        as_trained: false,
    })
}

/// A data source written as in a script's `data` setting (`dtu("scan24", masks: true)`, paths relative to
/// `dir`), when `text` is one: the data set it names, or its error with a caret; `None` when `text` is not
/// written as a call (or names an existing file or folder).
pub fn reader_call(text: &str, dir: &Path) -> Result<Option<DataSet>> {
    let text = text.trim();
    let looks_like_call = text.ends_with(')')
        && text
            .split('(')
            .next()
            .is_some_and(|name| !name.is_empty() && name.chars().all(|c| c.is_ascii_lowercase() || c == '_'));
    if !looks_like_call || Path::new(text).exists() {
        return Ok(None);
    }
    let script = format!("train {{ data: {text} }}\n");
    let program = nerfjit_dsl::compile("--cameras", &script).map_err(Failure::Script)?;
    let block = program
        .blocks()
        .into_iter()
        .next()
        .expect("the script holds its block");
    let mut settings = nerfjit_dsl::config::Settings::new(&program, block).map_err(|d| at(&program, d))?;
    let data = settings.take("data").expect("the block sets data");
    Ok(Some(data_set(&data, dir).map_err(|d| at(&program, d))?))
}

/// Reads the `data` setting of a script in `script_dir`, checking that its files exist.
pub fn data_set(v: &Spanned, script_dir: &Path) -> std::result::Result<DataSet, Diagnostic> {
    let Value::Call(kind, _) = &v.value else {
        return Err(
            Diagnostic::new(v.span, format!("expected a data source, found {}", v.describe()))
                .with_hint(HINT),
        );
    };
    let kind_name = kind.as_str();
    let slots: &'static [&'static str] = match kind_name {
        "views" => &["file"],
        "blender" => &["file", "size", "background", "views"],
        "nerfstudio" => &["file", "downscale", "background", "views", "normalize"],
        "colmap" => &["model", "images", "downscale", "background", "views", "normalize"],
        "llff" => &["folder", "downscale", "background", "views", "normalize"],
        "dtu" => &["folder", "masks", "downscale", "background", "views", "normalize"],
        other => {
            return Err(Diagnostic::new(v.span, format!("unknown data source '{other}'")).with_hint(HINT));
        }
    };
    let a = CallArgs::new(v, slots)?;
    let first = match kind_name {
        "colmap" => "model",
        "llff" | "dtu" => "folder",
        _ => "file",
    };
    let path = data_path(&a.string(first)?, script_dir);
    let exists = match kind_name {
        "colmap" => nerfjit_runtime::is_colmap_model(&path),
        "llff" => nerfjit_runtime::is_llff(&path),
        "dtu" => nerfjit_runtime::dtu_cameras_file(&path).is_some(),
        _ => path.is_file(),
    };
    if !exists {
        let what = match kind_name {
            "colmap" => format!(
                "'{}' holds no COLMAP model (cameras.txt or cameras.bin)",
                path.display()
            ),
            "llff" => format!("'{}' holds no LLFF scene (poses_bounds.npy)", path.display()),
            "dtu" => format!(
                "'{}' holds no DTU scan (cameras_sphere.npz or cameras.npz)",
                path.display()
            ),
            _ => format!("data file '{}' not found", path.display()),
        };
        return Err(Diagnostic::new(v.span, what)
            .with_hint("paths are relative to the working folder or to the script"));
    }
    let background = || -> std::result::Result<[f32; 3], Diagnostic> {
        a.raw("background")
            .map(triple)
            .transpose()
            .map(|b| b.unwrap_or([0.0; 3]))
    };
    let views = || -> std::result::Result<Option<usize>, Diagnostic> {
        a.raw("views")
            .map(|n| whole(n, 1, 100_000).map(|n| n as usize))
            .transpose()
    };
    let capture = |normalize: &'static str| -> std::result::Result<CaptureData, Diagnostic> {
        Ok(CaptureData {
            downscale: a
                .raw("downscale")
                .map(|n| whole(n, 1, 64))
                .transpose()?
                .unwrap_or(1) as u32,
            background: background()?,
            views: views()?,
            normalize: a.choice("normalize", &["true", "false"], normalize)? == "true",
        })
    };
    let kind = match kind_name {
        "views" => DataKind::Course,
        "blender" => {
            let size = a.number("size", Some(128.0))?;
            if !(1.0..=4096.0).contains(&size) || size.fract() != 0.0 {
                return Err(Diagnostic::new(v.span, "'size' is a whole number from 1 to 4096"));
            }
            DataKind::Blender(BlenderData {
                size: size as u32,
                background: background()?,
                views: views()?,
            })
        }
        "nerfstudio" => DataKind::Nerfstudio(capture("true")?),
        "llff" => DataKind::Llff(capture("true")?),
        "dtu" => DataKind::Dtu(
            capture("false")?,
            a.choice("masks", &["true", "false"], "false")? == "true",
        ),
        _ => {
            let images = match a.raw("images") {
                Some(_) => data_path(&a.string("images")?, script_dir),
                None => default_images_folder(&path).ok_or_else(|| {
                    Diagnostic::new(
                        v.span,
                        format!("no 'images' folder beside the model '{}'", path.display()),
                    )
                    .with_hint("name it: colmap(\"sparse/0\", images: \"path/to/images\")")
                })?,
            };
            if !images.is_dir() {
                let span = a.raw("images").map_or(v.span, |i| i.span);
                return Err(Diagnostic::new(
                    span,
                    format!("image folder '{}' not found", images.display()),
                ));
            }
            DataKind::Colmap(capture("true")?, images)
        }
    };
    Ok(DataSet { path, kind })
}

/// Whether `a` and `b` name the same existing file or folder.
fn same_file(a: &Path, b: &Path) -> bool {
    matches!((a.canonicalize(), b.canonicalize()), (Ok(a), Ok(b)) if a == b)
}

/// Resolves a data path: as written (relative to the working folder) if it exists, else relative to the
/// script's folder.
pub fn data_path(written: &str, script_dir: &Path) -> PathBuf {
    let direct = PathBuf::from(written);
    if direct.exists() || direct.is_absolute() {
        direct
    } else {
        let beside = script_dir.join(written);
        if beside.exists() {
            beside
        } else {
            direct
        }
    }
}

impl DataSet {
    /// The layout its reader reads; `None` for the course's views.
    pub fn layout(&self) -> Option<Layout> {
        match self.kind {
            DataKind::Course => None,
            DataKind::Blender(_) => Some(Layout::Blender),
            DataKind::Nerfstudio(_) => Some(Layout::Nerfstudio),
            DataKind::Colmap(..) => Some(Layout::Colmap),
            DataKind::Llff(_) => Some(Layout::Llff),
            DataKind::Dtu(..) => Some(Layout::Dtu),
        }
    }

    /// Whether `path` names this data set's files: its camera file or folder itself, or a folder holding
    /// them in this layout (a COLMAP model in `sparse/0`, a `transforms.json`).
    pub fn reads(&self, path: &Path) -> bool {
        same_file(&self.path, path)
            || layouts_at(path)
                .iter()
                .any(|f| Some(f.layout) == self.layout() && same_file(&f.source, &self.path))
    }

    /// Whether `other` reads the same files as this data set in the same layout.
    pub fn same_data_as(&self, other: &DataSet) -> bool {
        self.layout() == other.layout() && same_file(&self.path, &other.path)
    }

    /// The same data set read at about `width` pixels across when given (Blender: `width`²; captures
    /// downscaled by the whole factor nearest to their full-size width ÷ `width`; the course's views as
    /// they are); unchanged when not.
    pub fn at_width(&self, width: Option<u32>) -> Result<DataSet> {
        let Some(width) = width else {
            return Ok(self.clone());
        };
        let mut set = self.clone();
        let downscale = match &mut set.kind {
            DataKind::Course => return Ok(set),
            DataKind::Blender(b) => {
                b.size = width;
                return Ok(set);
            }
            DataKind::Llff(_) => nerfjit_runtime::data::llff::downscale_for_width(&self.path, width)?,
            _ => {
                let (capture, _) = self.downscaled(1).capture()?.expect("a capture's kind");
                let full = capture.frames.first().map_or(width, |f| f.camera.width);
                (full as f32 / width.max(1) as f32).round().max(1.0) as u32
            }
        };
        Ok(set.downscaled(downscale))
    }

    /// The views to score renders against, composited on the data's background: as [`DataSet::load`]
    /// reads them, and a DTU scan read without its masks keeps them apart to choose the pixels of the
    /// masked score (its images stay whole).
    pub fn scored(&self) -> Result<Views> {
        let mut views = self.load(false)?;
        if let DataKind::Dtu(data, false) = self.kind {
            if self.path.join("mask").is_dir() {
                let masked = DataSet {
                    path: self.path.clone(),
                    kind: DataKind::Dtu(data, true),
                };
                views.masks = masked.load(false)?.masks;
            }
        }
        Ok(views)
    }

    /// Whether the data set is a Blender one (which validation views require).
    pub fn blender(&self) -> Option<BlenderData> {
        match self.kind {
            DataKind::Blender(b) => Some(b),
            _ => None,
        }
    }

    /// The capture of a nerfstudio, COLMAP, LLFF or DTU data set, normalized when asked, and how to
    /// load it.
    fn capture(&self) -> Result<Option<(Capture, CaptureData)>> {
        Ok(self
            .normalized_capture()?
            .map(|(capture, data, _)| (capture, data)))
    }

    /// [`DataSet::capture`] with the normalization it applied, if it applied one.
    fn normalized_capture(&self) -> Result<Option<(Capture, CaptureData, Option<Normalization>)>> {
        let (mut capture, data) = match &self.kind {
            DataKind::Nerfstudio(data) => (load_nerfstudio(&self.path)?, *data),
            DataKind::Colmap(data, images) => {
                let capture = load_colmap(&self.path, images)?;
                // mip-NeRF 360's layout: `images_4/` beside `images/` holds them divided by 4.
                let smaller = images.with_file_name(format!("images_{}", data.downscale));
                if data.downscale > 1 && images.file_name().is_some_and(|n| n == "images") && smaller.is_dir()
                {
                    let data = CaptureData {
                        downscale: 1,
                        ..*data
                    };
                    (capture.with_images_in(&smaller)?, data)
                } else {
                    (capture, *data)
                }
            }
            DataKind::Llff(data) => {
                let scene = load_llff(&self.path, data.downscale)?;
                let data = CaptureData {
                    downscale: scene.remaining_downscale,
                    ..*data
                };
                (scene.capture, data)
            }
            DataKind::Dtu(data, masks) => (load_dtu(&self.path, *masks)?, *data),
            _ => return Ok(None),
        };
        let normalization = match data.normalize {
            true => Some(capture.normalize()?),
            false => None,
        };
        Ok(Some((capture, data, normalization)))
    }

    /// How far instant-ngp's scene box reaches along any axis in the frame training uses, when the data set
    /// states an `aabb_scale` (nerfstudio's and instant-ngp's `transforms.json`; see [`Capture::aabb_extent`]).
    pub fn aabb_extent(&self) -> Result<Option<f32>> {
        if !matches!(self.kind, DataKind::Nerfstudio(_)) {
            return Ok(None);
        }
        let captured = self.normalized_capture()?;
        Ok(captured.and_then(|(capture, _, normalization)| capture.aabb_extent(normalization.as_ref())))
    }

    /// The scene's nearest and farthest depth from the cameras in the frame training uses, where the data
    /// set gives them (LLFF's bounds; a COLMAP model's from its sparse points, see
    /// [`Capture::depth_bounds_from_points`]).
    pub fn depth_bounds(&self) -> Result<Option<(f32, f32)>> {
        Ok(self.capture()?.and_then(|(capture, _)| capture.depth_bounds))
    }

    /// The same capture read at `downscale` (other data sets unchanged).
    fn downscaled(&self, downscale: u32) -> DataSet {
        let mut set = self.clone();
        match &mut set.kind {
            DataKind::Course | DataKind::Blender(_) => {}
            DataKind::Nerfstudio(c) | DataKind::Colmap(c, _) | DataKind::Llff(c) | DataKind::Dtu(c, _) => {
                c.downscale = downscale
            }
        }
        set
    }

    /// The same data set composited on `background`.
    pub fn on_background(&self, background: [f32; 3]) -> DataSet {
        let mut set = self.clone();
        match &mut set.kind {
            DataKind::Course => {}
            DataKind::Blender(b) => b.background = background,
            DataKind::Nerfstudio(c) | DataKind::Colmap(c, _) | DataKind::Llff(c) | DataKind::Dtu(c, _) => {
                c.background = background
            }
        }
        set
    }

    /// The background the data set's images are composited on (black for the course's views).
    pub fn background(&self) -> [f32; 3] {
        match &self.kind {
            DataKind::Course => [0.0; 3],
            DataKind::Blender(b) => b.background,
            DataKind::Nerfstudio(c) | DataKind::Colmap(c, _) | DataKind::Llff(c) | DataKind::Dtu(c, _) => {
                c.background
            }
        }
    }

    /// Whether a capture's cameras are moved into nerfjit's frame (its `normalize`); `None` for the
    /// course's and Blender data, which are read as they are.
    pub fn normalizes(&self) -> Option<bool> {
        match &self.kind {
            DataKind::Course | DataKind::Blender(_) => None,
            DataKind::Nerfstudio(c) | DataKind::Colmap(c, _) | DataKind::Llff(c) | DataKind::Dtu(c, _) => {
                Some(c.normalize)
            }
        }
    }

    /// Whether the data set's alpha comes from object masks (a DTU scan read with its masks), inside
    /// which its held-out views are also scored.
    pub fn has_masks(&self) -> bool {
        matches!(self.kind, DataKind::Dtu(_, true))
    }

    /// The views as training and scoring read them: premultiplied with their alpha when `with_alpha`
    /// (composited on the data's background otherwise), with the data's object masks when it has them.
    pub fn load(&self, with_alpha: bool) -> Result<Views> {
        if !(with_alpha || self.has_masks()) {
            return self.views();
        }
        let mut views = self.views_with_alpha()?;
        if self.has_masks() {
            views = views.masked_by_alpha();
        }
        Ok(if with_alpha {
            views
        } else {
            views.on_background(self.background())
        })
    }

    /// Loads the training views premultiplied, with their alpha (see [`Views::with_alpha`]), having
    /// checked that both loads fit in the memory limit.
    pub fn views_with_alpha(&self) -> Result<Views> {
        let black = self.on_background([0.0; 3]).views()?;
        let white = self.on_background([1.0; 3]).views()?;
        Ok(Views::with_alpha(black, white)?)
    }

    /// Loads the training views, having checked that they fit in the memory limit.
    pub fn views(&self) -> Result<Views> {
        if let Some((capture, data)) = self.capture()? {
            return self.capture_views(&capture, &data);
        }
        Ok(match self.kind {
            DataKind::Blender(b) => {
                let frames = load_blender_cameras(&self.path)?.images.len();
                self.check_memory(b.views.unwrap_or(frames).min(frames), b.size, b.size)?;
                load_blender_views(&self.path, Some(b.size), b.background, b.views)?
            }
            _ => {
                let cameras = load_box_cameras(&self.path)?;
                if let Some((width, height)) = cameras.image_size {
                    self.check_memory(cameras.images.len(), width, height)?;
                }
                load_box_views(&self.path)?
            }
        })
    }

    /// The views of `capture` (this data set's, loaded) as `data` asks, having checked that they fit in
    /// the memory limit.
    fn capture_views(&self, capture: &Capture, data: &CaptureData) -> Result<Views> {
        let (n, width, height) = capture.view_sizes(&self.path, data.downscale, data.views)?;
        self.check_memory(n, width, height)?;
        let request = CaptureRequest {
            downscale: data.downscale,
            background: data.background,
            limit: data.views,
        };
        Ok(capture.views(&self.path, request)?)
    }

    /// Checks that `n` decoded views of `width`×`height` (RGB, f32) fit in the memory limit.
    fn check_memory(&self, n: usize, width: u32, height: u32) -> Result<()> {
        let pixels = n as u64 * u64::from(width) * u64::from(height);
        let views = if n == 1 { "view" } else { "views" };
        let what = || format!("{n} {views} of {width}×{height} from '{}'", self.path.display());
        Ok(budget::check(what, budget::bytes_of(pixels, 12))?)
    }

    /// The sparse points of a COLMAP model (its `points3D`), moved as its cameras are; none for other
    /// data.
    pub fn sparse_points(&self) -> Result<Vec<[f32; 3]>> {
        let points = match self.capture()? {
            Some((capture, _)) => capture.points.iter().map(|p| p.to_array()).collect(),
            None => Vec::new(),
        };
        Ok(points)
    }

    /// The (width, height) of the views as read, where the cameras state it (captures and the course's
    /// views; Blender views are square at their size).
    pub fn frame_size(&self) -> Result<Option<(u32, u32)>> {
        if let Some((capture, data)) = self.capture()? {
            let (_, width, height) = capture.view_sizes(&self.path, data.downscale, data.views)?;
            return Ok(Some((width, height)));
        }
        Ok(match self.kind {
            DataKind::Blender(b) => Some((b.size, b.size)),
            _ => load_box_cameras(&self.path)?.image_size,
        })
    }

    /// The cameras of the training views, without their images.
    pub fn cameras(&self) -> Result<Vec<Camera>> {
        if let Some((capture, data)) = self.capture()? {
            return Ok(capture.cameras(&self.path, data.downscale, data.views)?);
        }
        Ok(match self.kind {
            DataKind::Blender(_) => load_blender_cameras(&self.path)?.cameras,
            _ => load_box_cameras(&self.path)?.cameras,
        })
    }
}
