//! The block kinds a script may hold and the settings each takes, with their values, ranges, defaults
//! and docs: one registry, read by the blocks (which take their settings' ranges and defaults from it and
//! reject any setting not in it), by `nerfjit check` (which checks names, required settings and every
//! value that needs no file without running anything), by `nerfjit settings` (the help text), and by a
//! test that keeps the tables of `docs/LANGUAGE.md` in step with it. Each block kind's plan reads its
//! settings into a typed struct ([`crate::settings::typed`]) with a field per setting here, which a test
//! checks against this schema name by name and form by form.

use nerfjit_dsl::ast::ConfigBlock;
use nerfjit_dsl::config::{Settings, Spanned};
use nerfjit_dsl::{Diagnostic, Span};

use crate::settings::primitives as read;

/// The kinds of block, one per schema.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// `render sphere_trace { }`.
    SphereTrace,
    /// `render volume { }`.
    Volume,
    /// `train { }`.
    Train,
    /// `train sdf { }`.
    TrainSdf,
    /// `mesh { }`.
    Mesh,
    /// `bake { }`.
    Bake,
    /// `viz { }`.
    Viz,
}

/// What values a setting takes, and what it is when absent.
#[derive(Clone, Copy, Debug)]
pub enum Form {
    /// A whole number from `lo` to `hi`; absent, `default` (`None`: off, or decided as the doc says).
    Whole {
        /// The smallest value.
        lo: u64,
        /// The largest value.
        hi: u64,
        /// The value when absent.
        default: Option<u64>,
    },
    /// A number from `lo` to `hi`; absent, `default`.
    Number {
        /// The smallest value.
        lo: f64,
        /// The largest value.
        hi: f64,
        /// The value when absent.
        default: f64,
    },
    /// One of the bare names `choices`; absent, `default` (`None`: decided as the doc says).
    Choice {
        /// The names it takes.
        choices: &'static [&'static str],
        /// The value when absent.
        default: Option<&'static str>,
    },
    /// Three numbers (one is repeated); absent, `default` (`None`: decided as the doc says).
    Triple {
        /// The value when absent.
        default: Option<[f32; 3]>,
    },
    /// An image size, `N` or `[width, height]`, each from 1 to [`MAX_SIDE`].
    Size {
        /// The side when absent.
        default: u32,
    },
    /// The name of one of the script's functions, as a string.
    Function {
        /// The function when absent.
        default: &'static str,
    },
    /// A file the block writes, ending in one of `formats` (any name when empty). With `by_default`, it
    /// is written when absent, as `<script stem>.<by_default>`, and `none` turns it off.
    Output {
        /// The extensions it may have.
        formats: &'static [&'static str],
        /// The suffix of the file written when the setting is absent.
        by_default: Option<&'static str>,
    },
    /// A value with a grammar of its own (a camera, a data source, a schedule), described by `what`;
    /// `check` tests it without reading files, where that is possible.
    Value {
        /// What it is, for help texts.
        what: &'static str,
        /// A check that needs no files.
        check: Option<ValueCheck>,
    },
}

/// A check of a setting's value that needs no files.
pub type ValueCheck = fn(&Spanned) -> Result<(), Diagnostic>;

/// The largest side of an image a block renders.
pub const MAX_SIDE: u64 = 8192;

/// One setting of a block kind.
#[derive(Clone, Copy, Debug)]
pub struct Setting {
    /// Its name.
    pub name: &'static str,
    /// The values it takes.
    pub form: Form,
    /// For a setting that must be given, an example of it.
    pub required: Option<&'static str>,
    /// What it does, in one line (the language reference says more).
    pub doc: &'static str,
}

const fn setting(name: &'static str, form: Form, doc: &'static str) -> Setting {
    Setting {
        name,
        form,
        required: None,
        doc,
    }
}

const fn whole(name: &'static str, lo: u64, hi: u64, default: u64, doc: &'static str) -> Setting {
    let default = Some(default);
    setting(name, Form::Whole { lo, hi, default }, doc)
}

const fn whole_or_none(name: &'static str, lo: u64, hi: u64, doc: &'static str) -> Setting {
    let default = None;
    setting(name, Form::Whole { lo, hi, default }, doc)
}

const fn number(name: &'static str, lo: f64, hi: f64, default: f64, doc: &'static str) -> Setting {
    setting(name, Form::Number { lo, hi, default }, doc)
}

const fn choice(
    name: &'static str,
    choices: &'static [&'static str],
    default: Option<&'static str>,
    doc: &'static str,
) -> Setting {
    setting(name, Form::Choice { choices, default }, doc)
}

const fn flag(name: &'static str, doc: &'static str) -> Setting {
    choice(name, &["true", "false"], Some("false"), doc)
}

const fn triple(name: &'static str, default: Option<[f32; 3]>, doc: &'static str) -> Setting {
    setting(name, Form::Triple { default }, doc)
}

const fn function(name: &'static str, doc: &'static str) -> Setting {
    setting(name, Form::Function { default: "sdf" }, doc)
}

const fn output(name: &'static str, formats: &'static [&'static str], doc: &'static str) -> Setting {
    let by_default = None;
    setting(name, Form::Output { formats, by_default }, doc)
}

const fn written(name: &'static str, suffix: &'static str, doc: &'static str) -> Setting {
    let by_default = Some(suffix);
    setting(
        name,
        Form::Output {
            formats: &[],
            by_default,
        },
        doc,
    )
}

const fn value(
    name: &'static str,
    what: &'static str,
    check: Option<ValueCheck>,
    doc: &'static str,
) -> Setting {
    setting(name, Form::Value { what, check }, doc)
}

impl Setting {
    /// The same setting, which must be given (as in `example`).
    const fn required(self, example: &'static str) -> Setting {
        Setting {
            required: Some(example),
            ..self
        }
    }

    /// The values it takes, for help texts: `a whole number from 2 to 4096`.
    pub fn values(&self) -> String {
        match self.form {
            Form::Whole { lo, hi, .. } => format!("a whole number from {lo} to {hi}"),
            Form::Number { lo, hi, .. } => {
                format!("a number from {} to {}", read::short(lo), read::short(hi))
            }
            Form::Choice { choices, .. } => choices.join(" | "),
            Form::Triple { .. } => "[x, y, z] (or one number for all three)".to_string(),
            Form::Size { .. } => format!("N or [width, height], 1 to {MAX_SIDE}"),
            Form::Function { .. } => "a function's name, as a string".to_string(),
            Form::Output { formats, by_default } => {
                let none = if by_default.is_some() { ", or none" } else { "" };
                if formats.is_empty() {
                    format!("a file name{none}")
                } else {
                    let listed: Vec<String> = formats.iter().map(|f| format!(".{f}")).collect();
                    format!("a {} file{none}", read::one_of(&listed))
                }
            }
            Form::Value { what, .. } => what.to_string(),
        }
    }

    /// The value it has when absent, for help texts (`None` for a required setting, and where the doc
    /// says what happens).
    pub fn default_text(&self) -> Option<String> {
        if self.required.is_some() {
            return None;
        }
        match self.form {
            Form::Whole { default, .. } => default.map(|d| d.to_string()),
            Form::Number { default, .. } => Some(read::short(default)),
            Form::Choice { default, .. } => default.map(str::to_string),
            Form::Triple { default } => default.map(|[x, y, z]| format!("[{x}, {y}, {z}]")),
            Form::Size { default } => Some(default.to_string()),
            Form::Function { default } => Some(format!("\"{default}\"")),
            Form::Output { by_default, .. } => by_default.map(|s| format!("SCRIPT.{s}")),
            Form::Value { .. } => None,
        }
    }
}

/// A block kind and its settings.
#[derive(Debug)]
pub struct BlockSchema {
    /// Which kind it is.
    pub id: Kind,
    /// The keyword that opens the block (`render`).
    pub kind: &'static str,
    /// The word after it, for kinds that have one (`sphere_trace` in `render sphere_trace { }`).
    pub variant: Option<&'static str>,
    /// What the block does, in one line.
    pub doc: &'static str,
    /// The settings it takes.
    pub settings: &'static [Setting],
}

impl BlockSchema {
    /// How the block is written: `render sphere_trace`, `train`.
    pub fn title(&self) -> String {
        match self.variant {
            Some(v) => format!("{} {v}", self.kind),
            None => self.kind.to_string(),
        }
    }

    /// Its setting `name`, if it takes one.
    pub fn setting(&self, name: &str) -> Option<&'static Setting> {
        self.settings.iter().find(|s| s.name == name)
    }

    /// The names of its settings.
    pub fn names(&self) -> Vec<&'static str> {
        self.settings.iter().map(|s| s.name).collect()
    }
}

const IMAGES: &[&str] = &["gif", "mp4", "png"];
const DEPTHS: &[&str] = &["gif", "mp4", "png", "npy"];
const MESHES: &[&str] = &["ply", "obj", "stl", "glb"];
const EVERY: u64 = u32::MAX as u64;
const SEEDS: u64 = u64::MAX >> 1;

const CAMERA: Setting = value(
    "camera",
    "surround(...), orbit(...), look_at(...) or cameras(\"file\")",
    None,
    "the cameras to render from: a path or a camera file",
)
.required("camera: surround(radius: 3, frames: 20, up: z, focal: 1)");
const SIZE: Setting = setting("size", Form::Size { default: 256 }, "the image size in pixels");
const NEAR: Setting = number("near", 0.0, 1e6, 0.0, "where rays start");
const FRAME_MS: Setting = whole("frame_ms", 10, 10_000, 50, "the GIF's frame time in milliseconds");
const SPACING: Setting = value(
    "spacing",
    "linear or lindisp(split: d)",
    Some(check_spacing),
    "where samples lie along a ray: evenly in depth, or in disparity beyond split",
);
const SKIP_EMPTY: Setting = value(
    "skip_empty",
    "grid(bounds, resolution, threshold or thickness, space: scene, contracted or ndc) or none",
    Some(check_skip_empty),
    "an occupancy grid: samples in its empty cells are skipped (space: contracted puts its box in contract(p)'s \
     coordinates, covering all of space; space: ndc in a forward-facing capture's normalized device coordinates)",
);
const EARLY_TERMINATION: Setting = number(
    "early_termination",
    0.0,
    1.0,
    0.0,
    "stop a ray once its transmittance is below this (0: exact)",
);
const IMPORTANCE: Setting = whole(
    "importance",
    0,
    4096,
    0,
    "hierarchical sampling: fine samples per ray drawn from the coarse field's weights (0: off)",
);
const PRODUCTS: Setting = choice(
    "products",
    &["f32", "bf16"],
    Some("f32"),
    "the arithmetic of dense layers' products: f32, or bfloat16 operands with f32 sums (on AMX tiles where the CPU has them)",
);
const SAMPLES: Setting = whole("samples", 2, 4096, 64, "samples per ray");
const BACKGROUND: Setting = triple(
    "background",
    None,
    "the color behind the scene (black, or the data's background)",
);
const STEPS: Setting = whole("steps", 1, 100_000_000, 1000, "optimizer steps");
const BATCH: Setting = whole("batch", 1, 1 << 20, 4096, "rays (or points) per step");
const SCHEDULE: Setting = value(
    "schedule",
    "constant, exponential(gamma, every) or step(factor, every)",
    Some(check_schedule),
    "how the learning rate changes",
);
const OPTIMIZER: Setting = value(
    "optimizer",
    "adam(beta1, beta2, eps, sparse)",
    Some(check_optimizer),
    "Adam's decay rates and epsilon",
);
const SEED: Setting = whole("seed", 0, SEEDS, 0, "the random numbers' seed");
const CHECKPOINT: Setting = written(
    "checkpoint",
    "ckpt.safetensors",
    "params and optimizer state (safetensors; .json for JSON), to resume or render",
);
const CHECKPOINT_EVERY: Setting = whole("checkpoint_every", 1, EVERY, 500, "steps between checkpoints");
const LOG: Setting = written(
    "log",
    "metrics.jsonl",
    "the metrics log, JSON Lines (.csv for CSV)",
);
const TENSORBOARD: Setting = output(
    "tensorboard",
    &[],
    "a folder that also gets the metrics as TensorBoard scalars",
);
const SUMMARY: Setting = output(
    "summary",
    &[],
    "a JSON file with the final params, loss and timings",
);

/// `render sphere_trace { }`.
pub const RENDER_SPHERE_TRACE: BlockSchema = BlockSchema {
    id: Kind::SphereTrace,
    kind: "render",
    variant: Some("sphere_trace"),
    doc: "renders the surface sdf = 0 by sphere tracing",
    settings: &[
        CAMERA,
        SIZE,
        NEAR,
        number("far", 0.0, 1e9, 10.0, "where rays that hit nothing stop"),
        number("eps", 1e-12, 1.0, 1e-5, "a hit where sdf < eps"),
        whole(
            "max_steps",
            1,
            1_000_000,
            64,
            "steps before a ray counts as a miss",
        ),
        number(
            "lipschitz",
            1e-3,
            1e6,
            1.0,
            "a bound on |∇sdf|: steps are sdf / lipschitz (1 for distances; fields that are not, such as imported f-rep models, need theirs or rays step through surfaces)",
        ),
        triple("background", Some([0.0; 3]), "the color of missed rays"),
        choice(
            "shading",
            &["color", "lambert"],
            None,
            "the script's color function (the default when it has one) or Lambert shading of the normals",
        ),
        triple(
            "light",
            Some([0.5, 0.8, -0.6]),
            "Lambert shading's light direction",
        ),
        triple("albedo", Some([0.8; 3]), "Lambert shading's surface color"),
        value(
            "bounds",
            "sphere(center: [x, y, z], radius: r)",
            Some(check_bounding_sphere),
            "a bounding sphere: rays missing it are skipped",
        ),
        output("out", IMAGES, "the frames: a GIF or MP4, or PNGs").required("out: \"scene.gif\""),
        output(
            "depth",
            DEPTHS,
            "the depth map: an image, or float depths in .npy",
        ),
        output("normals", IMAGES, "the normal map"),
        FRAME_MS,
    ],
};

/// `render volume { }`.
pub const RENDER_VOLUME: BlockSchema = BlockSchema {
    id: Kind::Volume,
    kind: "render",
    variant: Some("volume"),
    doc: "renders density and color fields by volume rendering",
    settings: &[
        CAMERA,
        SIZE,
        NEAR,
        number("far", 0.0, 1e9, 5.0, "where rays stop"),
        SAMPLES,
        BACKGROUND,
        EARLY_TERMINATION,
        SPACING,
        SKIP_EMPTY,
        IMPORTANCE,
        PRODUCTS,
        output("out", IMAGES, "the frames: a GIF or MP4, or PNGs").required("out: \"volume.gif\""),
        output(
            "depth",
            DEPTHS,
            "the expected depth: an image, or float depths in .npy",
        ),
        FRAME_MS,
    ],
};

/// `train { }`: fitting a field to images.
pub const TRAIN: BlockSchema = BlockSchema {
    id: Kind::Train,
    kind: "train",
    variant: None,
    doc: "fits the params of density and color fields to images",
    settings: &[
        value(
            "data",
            "views(...), blender(...), nerfstudio(...) or colmap(...)",
            None,
            "the images and their cameras",
        )
        .required("data: views(\"box_cameras.json\")"),
        NEAR,
        number("far", 0.0, 1e9, 5.0, "where rays stop"),
        SAMPLES,
        BACKGROUND,
        STEPS,
        BATCH,
        whole_or_none(
            "batch_samples",
            256,
            1 << 26,
            "size each step in samples instead of rays, as instant-ngp does: after every step the ray count (from `batch`) is scaled so that the next step evaluates about this many samples, more rays as the occupancy grid and early termination skip more of each",
        ),
        number("lr", 1e-12, 10.0, 5e-4, "Adam's learning rate"),
        SCHEDULE,
        choice(
            "views",
            &["cycle", "random", "all"],
            Some("cycle"),
            "which view each step's rays come from: one in turn, one at random, or each ray from any view",
        ),
        flag("jitter", "stratified jitter of the depths inside their bins"),
        flag(
            "random_background",
            "each step composites its rays and their targets on a random color (images with alpha or masks)",
        ),
        flag(
            "appearance",
            "a colour transform per training view learnt with the field (exposure, white balance); renders use none",
        ),
        number(
            "distortion",
            0.0,
            1e3,
            0.0,
            "the weight of mip-NeRF 360's distortion loss on each ray's weights, against fog and floaters (0: off)",
        ),
        SEED,
        CHECKPOINT,
        CHECKPOINT_EVERY,
        SUMMARY,
        output("preview", &[], "a PNG of view 0 next to its target"),
        whole("preview_every", 1, EVERY, 500, "steps between previews"),
        function("sdf", "the signed distance function of the eikonal term"),
        number(
            "eikonal_weight",
            0.0,
            1e6,
            0.0,
            "the eikonal term's weight (0: off)",
        ),
        whole(
            "eikonal_points",
            1,
            1 << 20,
            1024,
            "the eikonal term's points per step",
        ),
        number(
            "eikonal_bounds",
            1e-3,
            1e6,
            4.0,
            "the eikonal points lie in [-b, b]³",
        ),
        choice(
            "eikonal_sampling",
            &["uniform", "occupied"],
            Some("uniform"),
            "where in [-b, b]³ the eikonal points lie: anywhere, or in the cells skip_empty's grid marks occupied",
        ),
        value(
            "val",
            "holdout(every: n) or a camera file",
            None,
            "held-out views to validate on",
        ),
        whole("val_every", 1, EVERY, 500, "steps between validations"),
        whole_or_none(
            "val_views",
            1,
            100_000,
            "how many held-out views to validate on (all)",
        ),
        value(
            "val_minutes",
            "a number or a list of minutes",
            Some(check_minutes),
            "also validate once training has taken these minutes",
        ),
        IMPORTANCE,
        SKIP_EMPTY,
        PRODUCTS,
        flag(
            "recompute_forward",
            "recompute the networks' forward pass in their backward pass instead of keeping its values (where every sample is evaluated: slower, to compare)",
        ),
        whole(
            "grid_every",
            1,
            EVERY,
            500,
            "steps between occupancy grid updates",
        ),
        whole(
            "grid_warmup",
            0,
            EVERY,
            500,
            "the step of the occupancy grid's first update",
        ),
        value(
            "grid_update",
            "rebuild or ema(decay, fraction)",
            Some(check_grid_update),
            "how the occupancy grid is updated",
        ),
        value(
            "grid_seed",
            "points, points(dilate: n) or none",
            Some(check_grid_seed),
            "before grid_warmup, skip all but the cells near a COLMAP model's sparse points",
        ),
        number(
            "minutes",
            0.0,
            1e6,
            0.0,
            "also stop after this many minutes of training (0: no limit)",
        ),
        EARLY_TERMINATION,
        SPACING,
        OPTIMIZER,
        LOG,
        TENSORBOARD,
    ],
};

/// `train sdf { }`: fitting a function to a point cloud.
pub const TRAIN_SDF: BlockSchema = BlockSchema {
    id: Kind::TrainSdf,
    kind: "train",
    variant: Some("sdf"),
    doc: "fits a signed distance function to a point cloud",
    settings: &[
        value(
            "data",
            "points(\"file\", key: \"name\", normalize: true)",
            None,
            "the point cloud (.npz, .npy, .ply, .obj, .xyz or .txt), mean-centered; with normalize: true, \
             centered on its bounding box and scaled into the unit sphere, and the meshes of the fit written \
             back in its units",
        )
        .required("data: points(\"bunny_pointcloud.npz\", key: \"verts\")"),
        function("function", "the function fitted"),
        PRODUCTS,
        STEPS,
        BATCH,
        whole("random", 1, 1 << 20, 4096, "uniform points per step"),
        number("bounds", 1e-3, 1e6, 4.0, "the uniform points lie in [-b, b]³"),
        number("lr", 1e-12, 10.0, 1e-4, "Adam's learning rate"),
        SCHEDULE,
        OPTIMIZER,
        number(
            "near_weight",
            0.0,
            1e6,
            0.1,
            "the weight of the term keeping uniform points off the surface",
        ),
        number(
            "near_sharpness",
            0.0,
            1e6,
            100.0,
            "how fast that term decays with distance",
        ),
        number("eikonal_weight", 0.0, 1e6, 0.02, "the eikonal term's weight"),
        number(
            "clearance_weight",
            0.0,
            1e6,
            0.0,
            "the weight of the term keeping the surface as far from uniform points as their nearest cloud point, less twice the cloud's spacing (0: off)",
        ),
        number(
            "eikonal_jitter",
            0.0,
            1e3,
            0.0,
            "σ of the noise moving cloud points for an eikonal term about the surface (0: off)",
        ),
        whole("pretrain_steps", 0, 1_000_000, 0, "steps fitting a sphere first"),
        number("pretrain_radius", 1e-3, 1e6, 1.0, "that sphere's radius"),
        SEED,
        CHECKPOINT,
        CHECKPOINT_EVERY,
        LOG,
        TENSORBOARD,
        SUMMARY,
        output("points_gif", IMAGES, "a turning GIF of the point cloud"),
    ],
};

/// `mesh { }`.
pub const MESH: BlockSchema = BlockSchema {
    id: Kind::Mesh,
    kind: "mesh",
    variant: None,
    doc: "extracts a level set of a function as a mesh by marching cubes",
    settings: &[
        function("function", "the function meshed"),
        whole("resolution", 2, 1024, 128, "cells per axis"),
        number("bounds", 1e-3, 1e6, 2.0, "the mesh covers [-r, r]³"),
        number("level", -1e9, 1e9, 0.0, "the level set"),
        output("out", MESHES, "the mesh").required("out: \"mesh.ply\""),
        output("gif", IMAGES, "a turntable of the mesh"),
        choice(
            "up",
            &["y", "z"],
            Some("y"),
            "the turntable's axis: the scene's up direction",
        ),
        value(
            "compare",
            "points(\"file\", key: \"name\")",
            None,
            "a point cloud to measure the mesh's distance to",
        ),
    ],
};

/// `bake { }`: the field baked into Gaussian splats, as `nerfjit bake` bakes a checkpoint (its CLI options as
/// settings; the views are always those of the script's `train` block's data).
pub const BAKE: BlockSchema = BlockSchema {
    id: Kind::Bake,
    kind: "bake",
    variant: None,
    doc: "bakes the volume field into Gaussian splats (a .bake file) and fine-tunes them against the train block's views",
    settings: &[
        output("out", &["bake"], "the baked splats").required("out: \"scene.bake\""),
        number(
            "tune",
            0.0,
            1e6,
            0.0,
            "seconds of fine-tuning the splats against the train block's views, less those it holds out (0: none)",
        ),
        whole(
            "sh_degree",
            0,
            1,
            1,
            "the degree of the tuned splats' spherical harmonics: 1, colors that change with the view; 0, one color a splat",
        ),
        number(
            "min_weight",
            0.0,
            1e6,
            1.0,
            "halfway through tuning, drop the splats that weighed under this many pixels (of a view as wide as those baked) in every view, but for those near the edges of every frame that holds them",
        ),
        whole_or_none(
            "size",
            1,
            4096,
            "the larger side of the views rendered to bake (in the training views' shape), in pixels; by default half theirs",
        ),
        number(
            "min_opacity",
            1e-6,
            1.0,
            0.5,
            "pixels of the views below this opacity are left out",
        ),
    ],
};

/// `viz { }`: the course's teaching images.
pub const VIZ: BlockSchema = BlockSchema {
    id: Kind::Viz,
    kind: "viz",
    variant: None,
    doc: "draws the course's teaching images of rays and samples",
    settings: &[
        CAMERA,
        value("view", "a camera", None, "the camera that sees the sample points"),
        SIZE,
        NEAR,
        number("far", 0.0, 1e9, 5.0, "where rays stop"),
        whole("samples", 1, 100_000, 16, "samples per ray"),
        whole("rays", 1, 100_000, 64, "rays whose samples are drawn"),
        output("grid", IMAGES, "pixel centers in NDC as colors"),
        output("directions", IMAGES, "ray directions as colors"),
        output("points", IMAGES, "sample points seen from the view"),
    ],
};

fn check_spacing(v: &Spanned) -> Result<(), Diagnostic> {
    crate::settings::values::depth_spacing(v).map(drop)
}

fn check_skip_empty(v: &Spanned) -> Result<(), Diagnostic> {
    crate::settings::values::skip_empty(v).map(drop)
}

fn check_schedule(v: &Spanned) -> Result<(), Diagnostic> {
    crate::settings::values::schedule(Some(v.clone()), 1.0).map(drop)
}

fn check_optimizer(v: &Spanned) -> Result<(), Diagnostic> {
    crate::settings::values::optimizer(Some(v.clone())).map(drop)
}

fn check_grid_update(v: &Spanned) -> Result<(), Diagnostic> {
    crate::settings::values::grid_update(Some(v.clone())).map(drop)
}

fn check_grid_seed(v: &Spanned) -> Result<(), Diagnostic> {
    crate::settings::values::grid_seed(v).map(drop)
}

fn check_minutes(v: &Spanned) -> Result<(), Diagnostic> {
    crate::settings::values::minutes_list(v).map(drop)
}

fn check_bounding_sphere(v: &Spanned) -> Result<(), Diagnostic> {
    crate::settings::values::bounding_sphere(v).map(drop)
}

/// Every block kind, in the order of the language reference.
pub const BLOCKS: &[&BlockSchema] = &[
    &RENDER_SPHERE_TRACE,
    &RENDER_VOLUME,
    &TRAIN,
    &TRAIN_SDF,
    &MESH,
    &BAKE,
    &VIZ,
];

/// The schema of the block `settings` were read from, or a diagnostic at the block naming the kinds.
pub fn of(settings: &Settings) -> Result<&'static BlockSchema, Diagnostic> {
    find(&settings.kind, settings.name.as_deref()).ok_or_else(|| {
        let what = match &settings.name {
            Some(n) => format!("{} {n}", settings.kind),
            None => settings.kind.clone(),
        };
        let kinds: Vec<String> = BLOCKS.iter().map(|s| format!("'{} {{ }}'", s.title())).collect();
        Diagnostic::new(settings.span, format!("there are no '{what}' blocks"))
            .with_hint(format!("blocks are {}", kinds.join(", ")))
    })
}

/// The schema of blocks opened by `keyword` and `variant` (`render`, `Some("volume")`), if any.
pub fn find(keyword: &str, variant: Option<&str>) -> Option<&'static BlockSchema> {
    BLOCKS
        .iter()
        .copied()
        .find(|s| s.kind == keyword && s.variant == variant)
}

/// The kind of a script's block, if the schema knows it.
pub fn kind_of(block: &ConfigBlock) -> Option<Kind> {
    let variant = block.name.as_ref().map(|n| n.name.as_str());
    find(&block.kind.name, variant).map(|s| s.id)
}

/// The schema of `kind`.
pub fn of_kind(kind: Kind) -> &'static BlockSchema {
    BLOCKS
        .iter()
        .copied()
        .find(|s| s.id == kind)
        .expect("every kind has a schema")
}

/// Checks `settings` against the schema of their kind without reading any file: the kind, the names (a
/// misspelt one gets "did you mean"), the required settings, and each value as far as its form allows.
/// Returns every error found.
pub fn check(settings: &Settings) -> Result<(), Vec<Diagnostic>> {
    let schema = of(settings).map_err(|d| vec![d])?;
    let mut rest = settings.clone();
    let mut errors = Vec::new();
    for setting in schema.settings {
        match rest.take(setting.name) {
            Some(v) => errors.extend(validate(setting, &v).err()),
            None if setting.required.is_some() => errors.push(missing(schema, setting, settings.span)),
            None => {}
        }
    }
    errors.extend(rest.finish(&schema.names()).err());
    errors.sort_by_key(|d| d.span.start);
    if errors.is_empty() {
        Ok(())
    } else {
        Err(errors)
    }
}

/// Checks value `v` of `setting` as far as that needs no files.
pub fn validate(setting: &Setting, v: &Spanned) -> Result<(), Diagnostic> {
    match setting.form {
        Form::Whole { lo, hi, .. } => read::whole(v, lo, hi).map(drop),
        Form::Number { lo, hi, .. } => read::ranged(v, lo, hi).map(drop),
        Form::Choice { choices, .. } => read::name_among(v, choices).map(drop),
        Form::Triple { .. } => read::triple(v).map(drop),
        Form::Size { .. } => read::size(v, MAX_SIDE).map(drop),
        Form::Function { .. } => v.string().map(drop),
        Form::Output { formats, by_default } => read::output_name(v, formats, by_default.is_some()).map(drop),
        Form::Value { check, .. } => check.map_or(Ok(()), |check| check(v)),
    }
}

/// The error for a required `setting` missing from a block of `schema` at `span`.
pub fn missing(schema: &BlockSchema, setting: &Setting, span: Span) -> Diagnostic {
    let example = setting.required.unwrap_or(setting.name);
    Diagnostic::new(
        span,
        format!("the {} block needs '{}'", schema.title(), setting.name),
    )
    .with_hint(format!("add e.g. {example}"))
}

/// The help text of the block kind written `words` (`train sdf`, `render volume` or `volume`), or of
/// every kind when `words` is empty.
pub fn help_for(words: &str) -> Result<String, crate::failure::Failure> {
    if words.trim().is_empty() {
        return Ok(help(None));
    }
    let words = words.split_whitespace().collect::<Vec<_>>().join(" ");
    BLOCKS
        .iter()
        .find(|s| s.title() == words || s.variant == Some(words.as_str()))
        .map(|s| help(Some(s)))
        .ok_or_else(|| {
            let kinds: Vec<String> = BLOCKS.iter().map(|s| s.title()).collect();
            crate::failure::Failure::Message(format!(
                "there are no '{words}' blocks; the kinds are: {}",
                kinds.join(", ")
            ))
        })
}

/// The help text of block kinds: every setting of `kind` (all kinds when `None`) with its values,
/// default and doc.
pub fn help(kind: Option<&BlockSchema>) -> String {
    let kinds: Vec<&BlockSchema> = match kind {
        Some(k) => vec![k],
        None => BLOCKS.to_vec(),
    };
    let mut out = String::new();
    for schema in kinds {
        out += &format!("{} {{ ... }}: {}\n", schema.title(), schema.doc);
        for s in schema.settings {
            let default = match (s.required, s.default_text()) {
                (Some(example), _) => format!("; required, e.g. {example}"),
                (None, Some(d)) => format!("; default {d}"),
                (None, None) => String::new(),
            };
            out += &format!("  {:<18} {}{default}\n", s.name, s.doc);
            out += &format!("  {:<18}   {}\n", "", s.values());
        }
        out += "\n";
    }
    out + "(docs/LANGUAGE.md explains every setting; `nerfjit run --set 'KIND.NAME=VALUE'` overrides one)\n"
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings_of(script: &str) -> Settings {
        let program = nerfjit_dsl::compile("s.sdf", script).unwrap();
        Settings::new(&program, program.blocks()[0]).unwrap()
    }

    #[test]
    fn blocks_are_told_apart_by_keyword_and_variant() {
        let script = "fn sdf(p: vec3) -> f32 = length(p) - 1\ntrain sdf { steps: 1 }\ntrain { steps: 1 }\n\
                      render volume { size: 8 }\nrender sphere_trace { size: 8 }\nrender ray_march { size: 8 }";
        let program = nerfjit_dsl::compile("s.sdf", script).unwrap();
        let kinds: Vec<Option<Kind>> = program.blocks().into_iter().map(kind_of).collect();
        let want = [
            Some(Kind::TrainSdf),
            Some(Kind::Train),
            Some(Kind::Volume),
            Some(Kind::SphereTrace),
            None,
        ];
        assert_eq!(kinds, want);
        for schema in BLOCKS {
            assert_eq!(of_kind(schema.id).title(), schema.title());
        }
    }

    #[test]
    fn a_misspelt_setting_is_named_with_the_closest_one() {
        let settings = settings_of(
            "fn sdf(p: vec3) -> f32 = length(p) - 1\ntrain sdf { data: points(\"p.npy\"), stesp: 10 }",
        );
        let error = check(&settings).unwrap_err().remove(0);
        assert!(
            error.message.contains("unknown setting 'stesp'"),
            "{}",
            error.message
        );
        assert_eq!(error.hint.as_deref(), Some("did you mean 'steps'?"));
    }

    #[test]
    fn a_grid_takes_a_threshold_or_a_thickness() {
        let grid = |args: &str| {
            let script =
                format!("fn density(p: vec3) -> f32 = 1\nrender volume {{ skip_empty: grid({args}) }}");
            let value = settings_of(&script).take("skip_empty").unwrap();
            crate::settings::values::skip_empty(&value).map(|s| s.map(|s| (s.threshold, s.thickness)))
        };
        assert_eq!(grid("bounds: 1, thickness: 0.01").unwrap(), Some((0.01, true)));
        assert_eq!(grid("bounds: 1, threshold: 0.3").unwrap(), Some((0.3, false)));
        assert_eq!(grid("bounds: 1").unwrap(), Some((1e-4, false)));
        let both = grid("bounds: 1, threshold: 0.3, thickness: 0.01").unwrap_err();
        assert!(both.message.contains("not both"), "{}", both.message);
        assert!(both.hint.unwrap().contains("thickness: 0.01"));
    }

    #[test]
    fn an_unknown_block_kind_lists_the_kinds() {
        let settings = settings_of("fn sdf(p: vec3) -> f32 = length(p) - 1\nrender ray_march { size: 8 }");
        let error = check(&settings).unwrap_err().remove(0);
        assert!(
            error.message.contains("no 'render ray_march' blocks"),
            "{}",
            error.message
        );
        assert!(error.hint.unwrap().contains("'render sphere_trace { }'"));
    }

    /// The setting names a section of the language reference documents: the first column of its table,
    /// or, for a section without one, every name in backticks.
    fn documented(reference: &str, schema: &BlockSchema) -> (Vec<String>, bool) {
        let heading = format!("### `{} {{ ... }}`", schema.title());
        let start = reference
            .find(&heading)
            .unwrap_or_else(|| panic!("no section '{heading}'"));
        let section = &reference[start + heading.len()..];
        let section = &section[..section.find("\n#").unwrap_or(section.len())];
        let rows: Vec<&str> = section.lines().filter(|l| l.starts_with("| `")).collect();
        let text: Vec<&str> = if rows.is_empty() {
            vec![section]
        } else {
            rows.iter().map(|r| r.split('|').nth(1).unwrap()).collect()
        };
        let names = text
            .iter()
            .flat_map(|t| t.split('`').skip(1).step_by(2))
            .map(|quoted| {
                quoted
                    .split(|c: char| !(c.is_alphanumeric() || c == '_'))
                    .next()
                    .unwrap()
            })
            .map(str::to_string)
            .collect();
        (names, !rows.is_empty())
    }

    #[test]
    fn the_language_reference_documents_every_setting_and_no_other() {
        let reference = include_str!("../../../docs/LANGUAGE.md");
        for schema in BLOCKS {
            let (names, tabled) = documented(reference, schema);
            for setting in schema.names() {
                let title = schema.title();
                assert!(
                    names.iter().any(|n| n == setting),
                    "'{title}' does not document '{setting}'"
                );
            }
            if tabled {
                for name in &names {
                    assert!(
                        schema.setting(name).is_some(),
                        "'{}' documents '{name}', which it does not take",
                        schema.title()
                    );
                }
            }
        }
    }

    #[test]
    fn values_are_checked_against_their_forms_and_every_error_is_reported() {
        let settings = settings_of(
            "fn sdf(p: vec3) -> f32 = length(p) - 1\n\
             mesh { resolution: 100000, level: \"x\", out: \"m.gif\", function: 3, bounds: 0 }",
        );
        let errors = check(&settings).unwrap_err();
        let messages: Vec<&str> = errors.iter().map(|d| d.message.as_str()).collect();
        assert_eq!(errors.len(), 5, "{messages:?}");
        assert!(messages[0].contains("100000 is out of range"), "{messages:?}");
        assert_eq!(
            errors[0].hint.as_deref(),
            Some("expected a whole number from 2 to 1024")
        );
        assert!(
            messages.iter().any(|m| m.contains("cannot write 'm.gif'")),
            "{messages:?}"
        );
    }

    #[test]
    fn a_missing_required_setting_is_named_with_an_example() {
        let settings = settings_of("fn sdf(p: vec3) -> f32 = length(p) - 1\nmesh { resolution: 8 }");
        let errors = check(&settings).unwrap_err();
        assert_eq!(errors.len(), 1);
        assert_eq!(errors[0].message, "the mesh block needs 'out'");
        assert_eq!(errors[0].hint.as_deref(), Some("add e.g. out: \"mesh.ply\""));
    }

    #[test]
    fn a_schedule_decays_every_so_many_steps_or_over_the_run_but_not_both() {
        let block = |schedule: &str| {
            settings_of(&format!(
                "fn sdf(p: vec3) -> f32 = length(p) - 1\ntrain sdf {{ data: points(\"a.npz\"), schedule: {schedule} }}"
            ))
        };
        assert!(check(&block("exponential(gamma: 0.01, over: run)")).is_ok());
        assert!(check(&block("exponential(gamma: 0.1, every: 100)")).is_ok());
        for (bad, says) in [
            ("exponential(gamma: 0.1, every: 100, over: run)", "not both"),
            ("exponential(gamma: 0.1, over: epoch)", "'epoch'"),
            ("exponential(over: run)", "needs the argument 'gamma'"),
        ] {
            let errors = check(&block(bad)).map_or_else(|e| e, |_| panic!("{bad} passed"));
            assert!(errors[0].message.contains(says), "{bad}: {}", errors[0].message);
        }
    }

    #[test]
    fn grammars_are_checked_without_files() {
        let settings = settings_of(
            "fn sdf(p: vec3) -> f32 = length(p) - 1\n\
             train sdf { data: points(\"missing.npz\"), schedule: exponentail(gamma: 0.1, every: 10), \
             optimizer: adam(beta1: 2) }",
        );
        let errors = check(&settings).unwrap_err();
        let messages: Vec<&str> = errors.iter().map(|d| d.message.as_str()).collect();
        assert_eq!(errors.len(), 2, "{messages:?}");
        assert!(
            messages[0].contains("unknown schedule 'exponentail'"),
            "{messages:?}"
        );
        assert!(messages[1].contains("2 is out of range"), "{messages:?}");
    }

    #[test]
    fn every_shipped_example_passes_the_schema() {
        for (name, source) in crate::script::EXAMPLES {
            let program = nerfjit_dsl::compile(name, source).unwrap();
            for block in program.blocks() {
                let settings = Settings::new(&program, block).unwrap();
                if let Err(errors) = check(&settings) {
                    panic!(
                        "{name}: {:?}",
                        errors.iter().map(|d| &d.message).collect::<Vec<_>>()
                    );
                }
            }
        }
    }

    #[test]
    fn defaults_lie_in_their_ranges() {
        for schema in BLOCKS {
            for s in schema.settings {
                match s.form {
                    Form::Whole {
                        lo,
                        hi,
                        default: Some(d),
                    } => assert!((lo..=hi).contains(&d), "{}", s.name),
                    Form::Number { lo, hi, default } => assert!((lo..=hi).contains(&default), "{}", s.name),
                    Form::Choice {
                        choices,
                        default: Some(d),
                    } => assert!(choices.contains(&d), "{}", s.name),
                    Form::Size { default } => assert!((1..=MAX_SIDE).contains(&u64::from(default))),
                    _ => {}
                }
            }
        }
    }

    /// The rows of the table of `schema`'s section of the language reference: (settings, default).
    fn documented_defaults(reference: &str, schema: &BlockSchema) -> Vec<(Vec<String>, String)> {
        let heading = format!("### `{} {{ ... }}`", schema.title());
        let start = reference.find(&heading).expect("a section");
        let section = &reference[start + heading.len()..];
        let section = &section[..section.find("\n#").unwrap_or(section.len())];
        section
            .lines()
            .filter(|l| l.starts_with("| `"))
            .map(|row| {
                let cells: Vec<&str> = row.split(" | ").collect();
                let names = cells[0]
                    .split('`')
                    .skip(1)
                    .step_by(2)
                    .map(str::to_string)
                    .collect();
                let default = cells.last().unwrap().trim_end_matches('|').trim().to_string();
                (names, default)
            })
            .collect()
    }

    /// The numbers and bare words a default cell of the reference gives, one per setting of its row.
    fn cell_values(default: &str, settings: usize) -> Option<Vec<String>> {
        let parts: Vec<String> = default
            .split(", ")
            .map(|p| {
                p.split_whitespace()
                    .next()
                    .unwrap_or("")
                    .trim_matches('`')
                    .to_string()
            })
            .collect();
        (parts.len() == settings).then_some(parts)
    }

    #[test]
    fn the_language_reference_gives_the_schemas_defaults() {
        let reference = include_str!("../../../docs/LANGUAGE.md");
        let mut compared = 0;
        for schema in BLOCKS {
            for (names, default) in documented_defaults(reference, schema) {
                let Some(values) = cell_values(&default, names.len()) else {
                    continue;
                };
                for (name, documented) in names.iter().zip(values) {
                    let setting = schema.setting(name).expect("documented settings exist");
                    let schema_value = match setting.form {
                        Form::Whole { default: Some(d), .. } => d as f64,
                        Form::Number { default, .. } => default,
                        Form::Choice { default: Some(d), .. } => {
                            assert_eq!(
                                documented,
                                d,
                                "'{}' documents {name} = {documented}",
                                schema.title()
                            );
                            compared += 1;
                            continue;
                        }
                        _ => continue,
                    };
                    let x: f64 = documented
                        .parse()
                        .unwrap_or_else(|_| panic!("'{}' documents {name} = '{documented}'", schema.title()));
                    assert!(
                        (x - schema_value).abs() <= 1e-9 * schema_value.abs(),
                        "'{}' documents {name} = {x}, the schema says {schema_value}",
                        schema.title()
                    );
                    compared += 1;
                }
            }
        }
        assert!(compared >= 40, "only {compared} defaults compared");
    }

    #[test]
    fn the_help_lists_every_setting_with_its_values() {
        let text = help(Some(&MESH));
        assert!(text.starts_with("mesh { ... }: extracts"), "{text}");
        assert!(
            text.contains("  resolution         cells per axis; default 128\n"),
            "{text}"
        );
        assert!(text.contains("a whole number from 2 to 1024\n"), "{text}");
        assert!(
            text.contains("the mesh; required, e.g. out: \"mesh.ply\"\n"),
            "{text}"
        );
        assert!(text.contains("a .ply, .obj, .stl or .glb file\n"), "{text}");
    }
}
