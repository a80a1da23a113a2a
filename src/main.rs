//! The `nerfjit` command line: parses arguments, calls the library and prints.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

use clap::{Args, CommandFactory, Parser, Subcommand};
use nerfjit::blocks::mesh;
use nerfjit::commands::{
    bake, check, compare, data_check, eval, export, import, ir_dump, point_cloud, render_views, run, sweep,
    transmittance,
};
use nerfjit::observe::TrainingObserver;
use nerfjit::settings::schema;
use nerfjit::{emit, failure, interrupt, script, WORK_STACK_BYTES};
use nerfjit_bench as bench;
use nerfjit_dsl::budget;
use nerfjit_runtime::Layout;
use nerfjit_viewer as viewer;

mod huge_pages;
#[cfg(feature = "mpi")]
mod mpi_cluster;
mod terminal;
use terminal::TerminalBars;

#[global_allocator]
static ALLOCATOR: huge_pages::HugePages = huge_pages::HugePages;

/// Scene scripts with symbolic derivatives, compiled by a Cranelift JIT, rendered on the CPU.
#[derive(Parser)]
#[command(name = "nerfjit", version, about)]
struct Cli {
    /// Worker threads (default: all cores; at most 8 per core).
    #[arg(long, global = true)]
    threads: Option<usize>,
    /// The most memory a run may plan to hold: params, training state (16 bytes per param) and the other
    /// sizes checked before they are allocated (default: 3/4 of physical memory; e.g. 512M, 20G).
    #[arg(long, global = true, value_name = "SIZE", value_parser = budget::parse_size)]
    max_memory: Option<u64>,
    #[command(subcommand)]
    command: Command,
}

/// What the viewer's server gives its clients (`nerfjit view`, `nerfjit run --view`).
#[derive(Args)]
struct ServerLimits {
    /// The viewer's open connections at once; the next is answered 503 and closed.
    #[arg(long, default_value_t = viewer::Limits::default().connections, value_parser = at_least_one())]
    max_connections: usize,
    /// The viewer's open pages at once (each renders on a thread of its own); the next is answered 503.
    #[arg(long, default_value_t = viewer::Limits::default().pages, value_parser = at_least_one())]
    max_pages: usize,
    /// Seconds the viewer waits for a request's head, a silent page (pinged a third of this apart) or a
    /// page that does not read what it is sent, before it closes the connection.
    #[arg(long, default_value_t = viewer::Limits::default().idle.as_secs_f64(), value_parser = positive_seconds)]
    idle_timeout: f64,
}

impl From<ServerLimits> for viewer::Limits {
    fn from(limits: ServerLimits) -> viewer::Limits {
        viewer::Limits {
            connections: limits.max_connections,
            pages: limits.max_pages,
            idle: std::time::Duration::from_secs_f64(limits.idle_timeout),
        }
    }
}

/// A whole number from 1.
fn at_least_one() -> clap::builder::RangedU64ValueParser<usize> {
    clap::builder::RangedU64ValueParser::new().range(1..)
}

/// A number of seconds above 0 and at most a day.
fn positive_seconds(text: &str) -> Result<f64, String> {
    let seconds: f64 = text.parse().map_err(|e| format!("{e}"))?;
    if seconds > 0.0 && seconds <= 86_400.0 {
        Ok(seconds)
    } else {
        Err("seconds above 0 and at most 86400".into())
    }
}

#[derive(Subcommand)]
enum Command {
    /// Run a script: its `train` and `render` blocks, in order.
    Run {
        /// The script (a path, or the name of a shipped example such as `torus`).
        script: String,
        /// Write outputs into this folder instead of the paths the script names.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Continue training from the train block's checkpoint, if it exists.
        #[arg(long)]
        resume: bool,
        /// Override a const (`beta=0.1`) or a block setting (`train.steps=100`, `render.size=64`; a block by
        /// kind or name, the first or the i-th from 0: `render[1].size=64`, `volume.size=64`); repeatable.
        #[arg(long = "set", value_name = "NAME=VALUE")]
        set: Vec<String>,
        /// The whole run's training time in minutes: every train block's `minutes` and every bake block's
        /// `tune` scaled by one factor so that they add up to it (each keeps its share; loading data, baking
        /// and validation come on top).
        #[arg(long, value_name = "M")]
        minutes: Option<f64>,
        /// Follow the training in the browser (`nerfjit view`'s page, with progress, a chart and pause);
        /// prints the page's URL and keeps serving after the last block until Ctrl-C.
        #[arg(long)]
        view: bool,
        /// With --view: the address to serve on.
        #[arg(long, default_value = "127.0.0.1", requires = "view")]
        host: std::net::IpAddr,
        /// With --view: the port (0: any free one).
        #[arg(long, default_value_t = 7007, requires = "view")]
        port: u16,
        #[command(flatten)]
        limits: ServerLimits,
    },
    /// Run a script once for every combination of values of its consts and block settings (a grid search),
    /// each run in its own folder; writes a table of every run's final metrics (sweep.json, sweep.md).
    Sweep {
        /// The script (a path, or the name of a shipped example).
        script: String,
        /// A const or block setting and its values, as `--set` names them: `beta=[0.01, 0.05]`,
        /// `train.lr=[1e-3, 1e-2]` (one value without brackets sets it in every run); repeatable.
        #[arg(long = "set", value_name = "NAME=[VALUE, ...]", required = true, value_parser = sweep::parse_axis)]
        set: Vec<sweep::Axis>,
        /// The folder of the runs (run_000/, run_001/, ...) and the table.
        #[arg(long, default_value = "sweep")]
        out: PathBuf,
    },
    /// Transmittance through a piecewise-constant medium along a ray.
    Transmittance {
        /// Segments as length:density, e.g. 2:1,1:0.5,3:10.
        #[arg(long)]
        segments: String,
        /// From this boundary (0 = the start of the first segment); all pairs when omitted.
        #[arg(long, requires = "to")]
        from: Option<usize>,
        /// To this boundary.
        #[arg(long, requires = "from")]
        to: Option<usize>,
    },
    /// Check a script: print diagnostics, or its functions, params and blocks.
    Check {
        /// The script.
        script: String,
    },
    /// Evaluate a function at points given as CSV rows (one column per input scalar).
    Eval {
        /// The script.
        script: String,
        /// The function to evaluate.
        function: String,
        /// A CSV file of points, or `-` for standard input.
        #[arg(long, default_value = "-")]
        points: String,
        /// Append the gradient of each output with respect to the inputs.
        #[arg(long)]
        grad: bool,
        /// Use the f64 reference interpreter instead of the JIT.
        #[arg(long)]
        interp: bool,
    },
    /// Print the IR of a function and the Cranelift IR of its kernel.
    Ir {
        /// The script.
        script: String,
        /// The function.
        function: String,
        /// Which kernel.
        #[arg(long, value_enum, default_value = "value")]
        kind: ir_dump::KernelKind,
        /// Short for `--kind grad`.
        #[arg(long, conflicts_with = "kind")]
        grad: bool,
        /// Only the IR graph and its node counts, without the Cranelift IR and compile time: text that
        /// stays the same from run to run, for diffs.
        #[arg(long)]
        graph_only: bool,
    },
    /// Run a benchmark workload and print its figures (medians).
    Bench {
        /// The workload (w1 … w8, listed by `nerfjit bench --help`).
        workload: bench::Workload,
        /// Repetitions; the median is reported.
        #[arg(long, default_value_t = 9)]
        reps: usize,
        /// The arithmetic of the networks' products in W4, W5, W6 and W8: f32, or bf16 (bfloat16
        /// operands, f32 sums; on AMX or AVX-512 BF16 where the CPU has them).
        #[arg(long, default_value = "f32", value_parser = ["f32", "bf16"])]
        products: String,
        /// W7: the script whose `fn sdf(p: vec3) -> f32` is evaluated at W7's random points, in place of
        /// the 20-primitive scene (`examples/complex_scene.sdf`); large: the model (`.vm`, as `nerfjit
        /// import` reads) in place of the generated city.
        #[arg(long)]
        scene: Option<String>,
        /// quality: minutes of training for each recipe.
        #[arg(long, default_value_t = 5.0)]
        minutes: f64,
    },
    /// Extract the marching-cubes mesh of a script's function (its zero level set by default), or of a
    /// trained field from a checkpoint.
    Mesh {
        /// A script, or a checkpoint written by a training block (it holds its script).
        script: String,
        /// The function to mesh, `fn f(p: vec3) -> f32`.
        #[arg(long, default_value = "sdf")]
        function: String,
        /// Grid cells per axis.
        #[arg(long, default_value_t = 256)]
        res: usize,
        /// The grid: r for [-r, r]³, or x0,y0,z0,x1,y1,z1.
        #[arg(long, default_value = "2", allow_hyphen_values = true)]
        bounds: String,
        /// The level set to extract.
        #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
        level: f32,
        /// The mesh file, .ply, .obj, .stl or .glb (glTF 2.0 binary).
        #[arg(long)]
        out: PathBuf,
        /// Color the mesh with this function (`fn(p: vec3) -> vec3`, or a radiance field's
        /// `fn(p: vec3, d: vec3) -> vec3`, seen from outside along the normal): vertex colors in PLY and
        /// OBJ, a texture in glTF; not STL.
        #[arg(long)]
        color: Option<String>,
        /// With --color into a .glb: texels along a side of each triangle's square patch of the texture
        /// (2 to 64; by default the largest up to 8 that keeps the texture within 4096² texels).
        #[arg(long)]
        texels: Option<usize>,
        /// Also write a turntable GIF of the mesh.
        #[arg(long)]
        gif: Option<PathBuf>,
        /// The scene's up direction (y, or z for Blender scenes such as lego): the turntable's axis, and
        /// a .glb's node turns z up to glTF's y.
        #[arg(long, default_value = "y", value_parser = ["y", "z"])]
        up: String,
        /// Evaluate the function at every grid point instead of only in the blocks of cells whose interval
        /// bounds may cross the level (the mesh is the same; for comparison).
        #[arg(long)]
        no_prune: bool,
    },
    /// Render a script's volume field (or a training checkpoint's) from every camera of a camera file, of a
    /// camera path, or of the script's own render block, as PNGs, a GIF or an MP4.
    Render {
        /// A script, or a checkpoint written by a train block (it holds its script).
        source: String,
        /// Without --cameras or --path: the script's render block's camera.
        #[command(flatten)]
        cameras: CameraChoice,
        #[command(flatten)]
        view: ViewOptions,
        /// A .mp4 (H.264) or .gif file of all views, or an output folder (view_000.png, ...).
        #[arg(long)]
        out: PathBuf,
        /// With a folder: write one GIF of all views (views.gif) instead of PNGs.
        #[arg(long)]
        gif: bool,
    },
    /// Bake a trained volume field (a checkpoint) into Gaussian splats (a .bake file) that `render`,
    /// `eval-views` and `export` take and the CPU draws in milliseconds. Its views are rendered in the
    /// training views' shape with the larger side --size and an eighth more on every side (by default half
    /// the training views' larger side; square views of 400 from --cameras or --path).
    Bake {
        #[command(flatten)]
        seen: SeenPixels,
        /// Seconds of fine-tuning the splats against the field's training views after baking (0: none).
        #[arg(long, default_value_t = 0.0, value_parser = tune_seconds)]
        tune: f64,
        /// The degree of the tuned splats' spherical harmonics: 1, colors that change with the view (the
        /// `.ply`'s `f_rest`); 0, one color a splat (smaller files).
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(0..=1))]
        sh_degree: u8,
        /// Halfway through fine-tuning, drop the splats that weighed under this many pixels (of a view as
        /// wide as those baked) in every training view (their alpha times the transmittance in front of
        /// them, summed over a view), except those near the edges of every frame that holds them: fewer
        /// splats draw faster, too few lose detail.
        #[arg(long, default_value_t = bake::MIN_WEIGHT, value_parser = min_weight)]
        min_weight: f32,
    },
    /// Export a baked scene (.bake) as a file other tools open: `splat-ply`, the 3D Gaussian splatting
    /// .ply that splat viewers read, or `glb`, a glTF 2.0 binary of the surface the splats make, textured
    /// with their colors.
    Export {
        /// The .bake file.
        scene: PathBuf,
        /// The format to write: splat-ply or glb.
        #[arg(long, value_parser = export_format)]
        format: export::ExportFormat,
        /// The file to write (.ply for splat-ply, .glb for glb).
        #[arg(long)]
        out: PathBuf,
        /// glb: grid cells along each axis [default: the longest side over twice the median scale of the
        /// splats within the grid, at most 256].
        #[arg(long)]
        res: Option<usize>,
        /// glb: the level of the splats' accumulated opacity meshed (above 0) [default: 0.5].
        #[arg(long, allow_hyphen_values = true)]
        level: Option<f32>,
        /// glb: the grid, r for [-r, r]³ or x0,y0,z0,x1,y1,z1 [default: a cube around every splat's
        /// reach]; splats outside are left out.
        #[arg(long, allow_hyphen_values = true)]
        bounds: Option<String>,
        /// glb: texels along a side of each triangle's square patch of the texture (2 to 64) [default:
        /// the largest up to 8 that keeps the texture within 4096² texels].
        #[arg(long)]
        texels: Option<usize>,
        /// glb: the scene's up direction (y, or z for Blender scenes such as lego): the file's node turns
        /// z up to glTF's y [default: y].
        #[arg(long, value_parser = ["y", "z"])]
        up: Option<String>,
    },
    /// A colored point cloud (PLY) of a script's volume field (or a checkpoint's): every view rendered,
    /// each pixel of enough opacity placed at its expected depth with its color.
    Points(SeenPixels),
    /// Score a script's volume field (or a checkpoint's) on the views of a camera file: PSNR and SSIM per
    /// view and their means.
    EvalViews {
        /// A script, or a checkpoint written by a train block.
        source: String,
        /// The camera file with the views' images: Blender `transforms_*.json` (at --size²), a nerfstudio
        /// `transforms.json`, a COLMAP model, LLFF scene or DTU scan folder (every frame, read as the
        /// field's training read its data: normalized or not, masked or not; downscaled by the whole
        /// factor nearest to width ÷ --size) [default:
        /// the views the script's train block holds out for validation, loaded as it trains: its `val`
        /// file or `holdout(every: n)` views of its data, at its size].
        #[arg(long)]
        cameras: Option<PathBuf>,
        /// The layout to read a data folder holding several as: dtu, llff, nerfstudio, colmap or blender
        /// [default: the one the field's training read there, else the most specific].
        #[arg(long, value_parser = layout_arg, requires = "cameras")]
        format: Option<Layout>,
        #[command(flatten)]
        view: ViewOptions,
        /// Also write the scores as JSON: per view and mean PSNR and SSIM, the settings and render time.
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// Render several trained fields (checkpoints, scripts or bakes) from one view of a camera file as a labeled
    /// grid beside the target image, with each render's PSNR (the fewer-views comparison).
    Compare {
        /// The camera file with the views' images (any that eval-views reads).
        #[arg(long)]
        cameras: PathBuf,
        /// The layout to read a data folder holding several as: dtu, llff, nerfstudio, colmap or blender
        /// [default: the one the field's training read there, else the most specific].
        #[arg(long, value_parser = layout_arg)]
        format: Option<Layout>,
        #[command(flatten)]
        view: ViewOptions,
        /// Which view of the camera file.
        #[arg(long, default_value_t = 0)]
        index: usize,
        /// Column labels, comma-separated (e.g. "100 views,20 views,10 views,5 views").
        #[arg(long, value_delimiter = ',', required = true)]
        columns: Vec<String>,
        /// A row: LABEL=first.ckpt.json,second.ckpt.json,... (one entry per column); repeatable.
        #[arg(long = "row", required = true, value_parser = compare::parse_row)]
        rows: Vec<compare::Row>,
        /// The PNG to write.
        #[arg(long)]
        out: PathBuf,
    },
    /// Serve a live view of a script (or a checkpoint, or a bake) in the browser: orbit the scene, edit the
    /// script and see it re-compiled and re-rendered, move its consts with sliders. Prints the page's URL.
    View {
        /// A script, a checkpoint written by a train block, or a bake of one (`.bake`: its splats are drawn,
        /// its checkpoint's script is shown read-only).
        source: String,
        /// The address to serve on. Anyone who reaches another address than the loopback default, with
        /// the printed token, runs code compiled from what they type on this machine.
        #[arg(long, default_value = "127.0.0.1")]
        host: std::net::IpAddr,
        /// The port (0: any free one).
        #[arg(long, default_value_t = 7007)]
        port: u16,
        #[command(flatten)]
        limits: ServerLimits,
    },
    /// Convert an f-rep model in the text format of fidget and MPR (`.vm`: one operation per line) into a
    /// script defining `fn sdf(p: vec3) -> f32` and a turntable render.
    Import {
        /// The model file.
        model: PathBuf,
        /// The script to write (default: the model's name with `.sdf`).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Data sets: `nerfjit data check DIR|FILE`.
    Data {
        #[command(subcommand)]
        action: DataCommand,
    },
    /// Describe the settings each kind of block takes — values, ranges, defaults — for every kind, or
    /// for one (`nerfjit settings train`, `nerfjit settings render volume`, `nerfjit settings volume`).
    Settings {
        /// The kind of block.
        kind: Vec<String>,
    },
    /// List the example scripts built into the binary, or print one.
    Examples {
        /// The example to print.
        name: Option<String>,
    },
    /// Print a shell completion script, e.g. `nerfjit completions bash > ~/.local/share/bash-completion/completions/nerfjit`.
    Completions {
        /// The shell.
        shell: clap_complete::Shell,
    },
}

/// What `nerfjit data` does.
#[derive(Subcommand)]
enum DataCommand {
    /// Report what a data set holds — camera files, views, image sizes and formats, intrinsics, where the
    /// cameras are — or name precisely what is wrong with it.
    Check {
        /// A camera file (Blender or nerfstudio transforms, the course's `box_cameras.json`) or a data
        /// folder: Blender camera files, a COLMAP model, an LLFF scene or a DTU scan.
        path: PathBuf,
        /// The layout to read a folder holding several as: dtu, llff, nerfstudio, colmap or blender
        /// [default: the most specific].
        #[arg(long, value_parser = layout_arg)]
        format: Option<Layout>,
    },
}

/// How `render`, `eval-views` and `compare` render views. Settings not given are those the script's
/// train block trains with (a checkpoint holds its script), else near 2, far 6, 128 samples, black.
/// A volume field seen from cameras, pixel by pixel (`points`, `bake`).
#[derive(clap::Args)]
struct SeenPixels {
    /// A checkpoint written by a train block, or a script.
    source: String,
    /// Without --cameras or --path: the cameras of the data the field trains on.
    #[command(flatten)]
    cameras: CameraChoice,
    #[command(flatten)]
    view: ViewOptions,
    /// Pixels below this opacity are left out.
    #[arg(long, default_value_t = 0.5)]
    min_opacity: f32,
    /// The file to write: the cloud's .ply, or the .bake.
    #[arg(long)]
    out: PathBuf,
}

impl SeenPixels {
    /// The library's arguments, the views rendered at `size`² (if given) unless --size says.
    fn args(&self, size: Option<u32>) -> point_cloud::PointsArgs<'_> {
        let view = self.view.args(&self.source);
        point_cloud::PointsArgs {
            view: render_views::ViewArgs {
                size: view.size.or(size),
                ..view
            },
            cameras: self.cameras.source(),
            min_opacity: self.min_opacity,
            out: &self.out,
        }
    }
}

/// Where a command takes its cameras from.
#[derive(clap::Args)]
struct CameraChoice {
    /// A camera file: Blender or nerfstudio `transforms.json`, a nerfstudio `camera_path.json`, a COLMAP
    /// model, LLFF scene or DTU scan folder (captures placed as the field's training placed its data) or
    /// the course's `box_cameras.json`.
    #[arg(long)]
    cameras: Option<PathBuf>,
    /// A camera path as in a script, e.g. 'orbit(radius: 4, frames: 60, up: z, focal: 2)' or
    /// 'surround(radius: 4, frames: 20, up: z, focal: 2)'.
    #[arg(long, conflicts_with = "cameras")]
    path: Option<String>,
    /// The layout to read a --cameras folder holding several as: dtu, llff, nerfstudio, colmap or blender
    /// [default: the one the field's training read there, else the most specific].
    #[arg(long, value_parser = layout_arg, requires = "cameras")]
    format: Option<Layout>,
}

/// An export `--format`.
fn export_format(text: &str) -> Result<export::ExportFormat, String> {
    match text {
        "splat-ply" => Ok(export::ExportFormat::SplatPly),
        "glb" => Ok(export::ExportFormat::Glb),
        _ => Err(format!("'{text}' is not an export format: splat-ply or glb")),
    }
}

/// A `--tune` value: seconds, finite and not negative.
fn tune_seconds(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(s) if s.is_finite() && s >= 0.0 => Ok(s),
        _ => Err(format!("'{text}' is not a number of seconds (0 or more)")),
    }
}

/// A `--min-weight` value: a number of pixels, 0 or more.
fn min_weight(text: &str) -> Result<f32, String> {
    match text.parse::<f32>() {
        Ok(w) if w.is_finite() && w >= 0.0 => Ok(w),
        _ => Err(format!("'{text}' is not a number of pixels (0 or more)")),
    }
}

/// A `--format` value: the layout it names.
fn layout_arg(text: &str) -> Result<Layout, String> {
    Layout::parse(text)
        .ok_or_else(|| format!("'{text}' is not a layout: dtu, llff, nerfstudio, colmap or blender"))
}

impl CameraChoice {
    fn source(&self) -> render_views::CameraSource<'_> {
        match (&self.cameras, &self.path) {
            (Some(file), _) => render_views::CameraSource::File(file, self.format),
            (None, Some(text)) => render_views::CameraSource::Path(text),
            (None, None) => render_views::CameraSource::Default,
        }
    }
}

#[derive(clap::Args)]
struct ViewOptions {
    /// Image side in pixels (1 to 4096); with `render --cameras` the width, the height following the
    /// camera file's aspect ratio [default: 128; `eval-views` and `compare` of a field's own training
    /// data: the scale its training read them at].
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=4096))]
    size: Option<u32>,
    /// Start of the sampled interval along each ray [default: the script's, else 2].
    #[arg(long)]
    near: Option<f32>,
    /// End of the sampled interval [default: the script's, else 6].
    #[arg(long)]
    far: Option<f32>,
    /// Samples per ray (1 to 4096) [default: the script's, else 128].
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=4096))]
    samples: Option<u32>,
    /// Background: black or white (the images' alpha is composited on it too) [default: the script's,
    /// else black].
    #[arg(long, value_parser = ["black", "white"])]
    background: Option<String>,
    /// Importance samples per ray drawn from a coarse pass (hierarchical sampling: the script needs
    /// coarse_density and coarse_color; `--samples` is then the coarse count). 0: none [default: the
    /// script's, else 0].
    #[arg(long, value_parser = clap::value_parser!(u32).range(0..=4096))]
    importance: Option<u32>,
    /// Evaluate every sample: no occupancy grid or early ray termination even where the script's train
    /// block uses them (by default renders skip what training skips).
    #[arg(long)]
    exact: bool,
}

impl ViewOptions {
    fn args<'a>(&'a self, source: &'a str) -> render_views::ViewArgs<'a> {
        render_views::ViewArgs {
            source,
            size: self.size,
            near: self.near,
            far: self.far,
            samples: self.samples.map(|n| n as usize),
            background: self
                .background
                .as_ref()
                .map(|b| [if b == "white" { 1.0 } else { 0.0 }; 3]),
            importance: self.importance.map(|n| n as usize),
            exact: self.exact,
        }
    }
}

/// Most `--threads` per core.
const MAX_THREADS_PER_CORE: usize = 8;

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Under mpirun, this process is one rank of the job (MPI is finalized when this is dropped, at the end).
    #[cfg(feature = "mpi")]
    let _mpi = mpi_cluster::install();
    terminal::install_interrupt_handler();
    if let Some(bytes) = cli.max_memory {
        budget::set_max_memory(bytes);
    }
    let mut pool = rayon::ThreadPoolBuilder::new().start_handler(|_| nerfjit_runtime::flush_denormals());
    if let Some(n) = cli.threads {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        if n > MAX_THREADS_PER_CORE * cores {
            eprintln!(
                "error: --threads {n} is more than {MAX_THREADS_PER_CORE} threads per core ({cores} cores here)"
            );
            return ExitCode::FAILURE;
        }
        pool = pool.num_threads(n.max(1));
    }
    // This is the first thing the program does: no pool exists yet.
    if let Err(e) = pool.build_global() {
        eprintln!("error: cannot start the worker threads: {e}");
        return ExitCode::FAILURE;
    }
    let worker = std::thread::Builder::new()
        .name("nerfjit".into())
        .stack_size(WORK_STACK_BYTES)
        .spawn(move || {
            nerfjit_runtime::flush_denormals();
            run_command(cli)
        });
    match worker.map(|w| w.join()) {
        Ok(Ok(code)) => code,
        // A panic has printed its message already.
        Ok(Err(_)) => ExitCode::FAILURE,
        Err(e) => {
            eprintln!(
                "error: cannot start the worker thread with its {} MiB stack: {e}\n  = hint: the stack is \
                 reserved, not used, but must fit in the address space: raise `ulimit -v` to at least 1.5 GB",
                WORK_STACK_BYTES >> 20
            );
            ExitCode::FAILURE
        }
    }
}

/// The terminal's progress bars; none on the ranks of an MPI job other than rank 0, which alone prints.
fn bars() -> &'static dyn nerfjit::observe::ProgressBars {
    if nerfjit::cluster::current().rank() == 0 {
        &TerminalBars
    } else {
        &nerfjit::observe::NoBars
    }
}

/// `nerfjit run`: every block of the script in order, with progress bars and, with `view`, a live viewer
/// that follows the training (and stays open after the last block until the process is stopped).
fn run_script(
    path: &str,
    overrides: &[String],
    minutes: Option<f64>,
    out_dir: Option<&std::path::Path>,
    resume: bool,
    view: Option<&viewer::ViewArgs>,
) -> failure::Result<()> {
    let mut overrides = overrides.to_vec();
    if let Some(minutes) = minutes {
        let session = run::open(path, &overrides, out_dir)?;
        overrides.extend(run::minutes_overrides(&session, minutes)?);
    }
    let mut session = run::open(path, &overrides, out_dir)?;
    // In an MPI job rank 0 alone serves the viewer (when it pauses, the other ranks wait at the next step).
    let live = match view.filter(|_| nerfjit::cluster::current().rank() == 0) {
        Some(args) => {
            let live = Arc::new(viewer::Live::new());
            let program = session.program();
            let document = viewer::Document::of(program, program.param_values.clone(), false)?;
            viewer::attach(args, document, Arc::clone(&live))?;
            Some(live)
        }
        None => None,
    };
    let observer = live.as_deref().map(|l| l as &dyn TrainingObserver);
    run::run_session(&mut session, resume, bars(), observer)?;
    if live.is_some() {
        eprintln!("done: the viewer stays open until Ctrl-C");
        loop {
            std::thread::park();
        }
    }
    Ok(())
}

/// Runs the command line's command; prints its error, if any.
fn run_command(cli: Cli) -> ExitCode {
    let result = match cli.command {
        Command::Run {
            script,
            out,
            resume,
            set,
            minutes,
            view,
            host,
            port,
            limits,
        } => {
            let view = view.then_some(viewer::ViewArgs {
                source: &script,
                host,
                port,
                limits: limits.into(),
            });
            run_script(&script, &set, minutes, out.as_deref(), resume, view.as_ref())
        }
        Command::Sweep { script, set, out } => {
            sweep::sweep(&script, &set, &out, bars()).map(|table| emit(&format!("\n{table}")))
        }
        Command::Transmittance { segments, from, to } => {
            transmittance::run(&segments, from.zip(to)).map(|text| emit(&text))
        }
        Command::Check { script } => check::run(&script).map(|text| emit(&text)),
        Command::Eval {
            script,
            function,
            points,
            grad,
            interp,
        } => {
            let args = eval::EvalArgs {
                script: &script,
                function: &function,
                points: &points,
                grad,
                interp,
            };
            eval::run(&args, &mut std::io::stdout().lock())
        }
        Command::Ir {
            script,
            function,
            kind,
            grad,
            graph_only,
        } => {
            let kind = if grad { ir_dump::KernelKind::Grad } else { kind };
            ir_dump::run(&script, &function, kind, graph_only).map(|text| emit(&text))
        }
        Command::Bench {
            workload,
            reps,
            products,
            scene,
            minutes,
        } => bench::run(
            workload,
            reps,
            cli.threads,
            nerfjit_jit::Precision::named(&products).unwrap_or_default(),
            scene.as_deref(),
            minutes,
        ),
        Command::Mesh {
            script,
            function,
            res,
            bounds,
            level,
            out,
            color,
            texels,
            gif,
            up,
            no_prune,
        } => mesh::parse_bounds(&bounds)
            .map_err(failure::Failure::Message)
            .and_then(|bounds| {
                let args = mesh::MeshArgs {
                    function: &function,
                    resolution: res,
                    bounds,
                    level,
                    out: &out,
                    gif: gif.as_deref(),
                    up: nerfjit_runtime::Up::named(&up).unwrap_or(nerfjit_runtime::Up::Y),
                    prune: !no_prune,
                    color: color.as_deref(),
                    texels,
                    frame: None,
                };
                mesh::run(&script, &args)
            })
            .map(|text| emit(&format!("{text}\n"))),
        Command::Render {
            source,
            cameras,
            view,
            out,
            gif,
        } => render_views::render(&view.args(&source), cameras.source(), &out, gif)
            .map(|text| emit(&format!("{text}\n"))),
        Command::Bake {
            seen,
            tune,
            sh_degree,
            min_weight,
        } => {
            let tuning = bake::Tuning {
                seconds: tune,
                sh_degree,
                min_weight,
            };
            bake::run(&seen.args(None), tuning).map(|text| emit(&format!("{text}\n")))
        }
        Command::Export {
            scene,
            format,
            out,
            res,
            level,
            bounds,
            texels,
            up,
        } => {
            let glb =
                (res.is_some() || level.is_some() || bounds.is_some() || texels.is_some() || up.is_some())
                    .then(|| -> Result<export::GlbOptions, failure::Failure> {
                        let defaults = export::GlbOptions::default();
                        Ok(export::GlbOptions {
                            surface: nerfjit_runtime::splats::SurfaceOptions {
                                bounds: bounds
                                    .as_deref()
                                    .map(mesh::parse_bounds)
                                    .transpose()
                                    .map_err(failure::Failure::Message)?,
                                resolution: res,
                                level: level.unwrap_or(defaults.surface.level),
                            },
                            texels,
                            up: up
                                .as_deref()
                                .and_then(nerfjit_runtime::Up::named)
                                .unwrap_or(defaults.up),
                        })
                    })
                    .transpose();
            glb.and_then(|glb| export::export(&scene, format, &out, glb.as_ref()))
                .map(|text| emit(&format!("{text}\n")))
        }
        Command::Points(seen) => point_cloud::run(&seen.args(None)).map(|text| emit(&format!("{text}\n"))),
        Command::EvalViews {
            source,
            cameras,
            format,
            view,
            json,
        } => match nerfjit::bake_file::is_bake(std::path::Path::new(&source)) {
            true => bake::eval(&view.args(&source), cameras.as_deref(), format, json.as_deref()),
            false => render_views::eval(&view.args(&source), cameras.as_deref(), format, json.as_deref()),
        }
        .map(|text| emit(&text)),
        Command::Compare {
            cameras,
            format,
            view,
            index,
            columns,
            rows,
            out,
        } => compare::compare(&view.args(""), &cameras, format, index, &columns, &rows, &out)
            .map(|text| emit(&format!("{text}\n"))),
        Command::View {
            source,
            host,
            port,
            limits,
        } => viewer::run(&viewer::ViewArgs {
            source: &source,
            host,
            port,
            limits: limits.into(),
        }),
        Command::Import { model, out } => {
            import::run(&model, out.as_deref()).map(|text| emit(&format!("{text}\n")))
        }
        Command::Data {
            action: DataCommand::Check { path, format },
        } => data_check::run(&path, format).map(|text| emit(&text)),
        Command::Settings { kind } => schema::help_for(&kind.join(" ")).map(|text| emit(&text)),
        Command::Examples { name } => script::examples(name.as_deref()).map(|text| emit(&text)),
        Command::Completions { shell } => {
            let mut script = Vec::new();
            clap_complete::generate(shell, &mut Cli::command(), "nerfjit", &mut script);
            emit(&String::from_utf8_lossy(&script));
            Ok(())
        }
    };
    // In an MPI job every rank stops together when interrupted (rank 0 says so); any other rank's error is
    // its own, and says which rank it is.
    let rank = nerfjit::cluster::current().rank();
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(failure @ failure::Failure::Interrupted(_)) => {
            if rank == 0 {
                eprint!("{failure}");
            }
            ExitCode::from(interrupt::EXIT_STATUS)
        }
        Err(failure) => {
            match rank {
                0 => eprint!("{failure}"),
                _ => eprint!("rank {rank}: {failure}"),
            }
            ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;

    use clap::CommandFactory;

    use super::Cli;

    /// The command reference's `## `nerfjit …`` sections: the command path and the section's text.
    fn sections() -> Vec<(String, String)> {
        let text = include_str!("../docs/COMMANDS.md");
        let mut out: Vec<(String, String)> = Vec::new();
        for line in text.lines() {
            if let Some(title) = line.strip_prefix("## ") {
                let name = title.strip_prefix("`nerfjit ").and_then(|t| t.strip_suffix('`'));
                out.push((name.unwrap_or(title).to_string(), String::new()));
            } else if let Some((_, body)) = out.last_mut() {
                body.push_str(line);
                body.push('\n');
            }
        }
        out
    }

    /// The long flags a section mentions (`--name`).
    fn flags_in(text: &str) -> BTreeSet<String> {
        let mut flags = BTreeSet::new();
        for (i, _) in text.match_indices("--") {
            let name: String = text[i + 2..]
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '-')
                .collect();
            let starts_word = i == 0 || !text[..i].ends_with(|c: char| c.is_ascii_alphanumeric() || c == '-');
            if starts_word && name.starts_with(|c: char| c.is_ascii_lowercase()) {
                flags.insert(name);
            }
        }
        flags
    }

    /// The long flags of a command and of all its subcommands, without clap's `help` and `version`.
    fn flags_of(cmd: &clap::Command) -> BTreeSet<String> {
        let mut flags: BTreeSet<String> = cmd
            .get_arguments()
            .filter(|a| !a.is_global_set())
            .filter_map(|a| a.get_long().map(str::to_string))
            .filter(|l| l != "help" && l != "version")
            .collect();
        for sub in cmd.get_subcommands() {
            flags.extend(flags_of(sub));
        }
        flags
    }

    /// docs/COMMANDS.md in step with the binary: every command has its section (a command with
    /// subcommands, one section or one per subcommand), every flag of a command is in its section, and a
    /// section names no command or flag the binary does not have; the global flags are in "Options of every
    /// command".
    #[test]
    fn the_command_reference_matches_the_binary() {
        let cli = Cli::command();
        let sections = sections();
        let section = |path: &str| {
            sections
                .iter()
                .find(|(name, _)| name == path)
                .map(|(_, text)| text)
        };
        let mut problems = Vec::new();
        let mut documented = BTreeSet::new();
        for cmd in cli.get_subcommands().filter(|c| c.get_name() != "help") {
            let name = cmd.get_name();
            let pieces: Vec<(String, &clap::Command)> = match section(name) {
                Some(_) => vec![(name.to_string(), cmd)],
                None => cmd
                    .get_subcommands()
                    .map(|s| (format!("{name} {}", s.get_name()), s))
                    .collect(),
            };
            if pieces.is_empty() {
                problems.push(format!("no section `nerfjit {name}`"));
            }
            for (path, cmd) in pieces {
                let Some(text) = section(&path) else {
                    problems.push(format!("no section `nerfjit {path}`"));
                    continue;
                };
                let (want, have) = (flags_of(cmd), flags_in(text));
                for flag in want.difference(&have) {
                    problems.push(format!("`nerfjit {path}` does not mention --{flag}"));
                }
                for flag in have.difference(&want) {
                    problems.push(format!("`nerfjit {path}` names --{flag}, which it does not have"));
                }
                documented.insert(path);
            }
        }
        let global: BTreeSet<String> = cli
            .get_arguments()
            .filter(|a| a.is_global_set())
            .filter_map(|a| a.get_long().map(str::to_string))
            .collect();
        match section("Options of every command") {
            Some(text) if flags_in(text) == global => {}
            Some(text) => problems.push(format!(
                "the global options are {global:?}, documented {:?}",
                flags_in(text)
            )),
            None => problems.push("no section \"Options of every command\"".to_string()),
        }
        for (name, _) in &sections {
            if !["Options of every command", "Diagnostics"].contains(&name.as_str())
                && !documented.contains(name)
            {
                problems.push(format!("a section on `nerfjit {name}`, which does not exist"));
            }
        }
        assert!(
            problems.is_empty(),
            "docs/COMMANDS.md is out of step with the binary:\n{}",
            problems.join("\n")
        );
    }
}
