//! `nerfjit points`: a colored point cloud of a radiance field, as nerfstudio's `ns-export pointcloud`
//! makes one. Every view is volume-rendered; each pixel whose opacity reaches a threshold becomes the
//! point at its expected depth, with its rendered color (the background taken out) and a normal facing
//! the camera that saw it. Written as a binary PLY of vertices without faces.

use std::path::Path;
use std::time::Instant;

use nerfjit_dsl::Program;
use nerfjit_jit::KernelCache;
use nerfjit_runtime::{Camera, Mesh, OccupancyGrid};

use crate::commands::render_views::{CameraSource, ViewArgs};
use crate::failure::{Failure, Result};
use nerfjit_field::VolumeFields;

/// The most points a cloud may hold (views × pixels are checked against it before rendering).
pub const MAX_POINTS: u64 = 1 << 26;

/// What `nerfjit points` (and `nerfjit bake`) do.
pub struct PointsArgs<'a> {
    /// The field and how to render it (`size` is the side of each rendered view).
    pub view: ViewArgs<'a>,
    /// Where the cameras come from; by default, the cameras of the data the script trains on.
    pub cameras: CameraSource<'a>,
    /// Pixels below this opacity are left out.
    pub min_opacity: f32,
    /// The file to write.
    pub out: &'a Path,
}

/// Renders the views, back-projects their opaque pixels and writes the cloud; returns a summary line.
pub fn run(args: &PointsArgs) -> Result<String> {
    let start = Instant::now();
    let (program, params) = crate::checkpoint::load_source(args.view.source)?;
    let cameras = view_cameras(args.view.source, &program, &args.cameras)?;
    let field = (&program, params.as_slice());
    let size = args.view.side();
    let Some(surfels) = Surfels::render(&args.view, field, None, &cameras, (size, size), args.min_opacity)?
    else {
        return Ok(String::new());
    };
    let seconds = start.elapsed().as_secs_f64();
    let cloud = Mesh {
        normals: surfels.directions.iter().map(|d| d.map(|x| -x)).collect(),
        vertices: surfels.positions,
        triangles: Vec::new(),
        colors: surfels.colors,
    };
    cloud.write_ply(args.out)?;
    Ok(format!(
        "{} points from {} views of {size}×{size} in {seconds:.2} s (opacity ≥ {}) → {}",
        cloud.vertices.len(),
        cameras.len(),
        args.min_opacity,
        args.out.display()
    ))
}

/// The cameras of `cameras`; by default, those of the data `source`'s script (compiled as `program`)
/// trains on.
pub(crate) fn view_cameras(source: &str, program: &Program, cameras: &CameraSource) -> Result<Vec<Camera>> {
    match cameras.cameras(source, program)? {
        Some((cameras, _)) => Ok(cameras),
        None => {
            let folder = Path::new(source).parent().unwrap_or(Path::new(""));
            crate::blocks::train::data_cameras(program, folder).ok_or_else(|| {
                Failure::Message(format!(
                    "{source} trains on no data whose cameras can be read here: give --cameras FILE or --path 'orbit(...)'"
                ))
            })
        }
    }
}

/// A field's opaque pixels seen from cameras: each at its expected depth, with its color (the background
/// taken out) and opacity, the direction it was seen along and its footprint (the width of its pixel there).
pub(crate) struct Surfels {
    /// Where each lies.
    pub positions: Vec<[f32; 3]>,
    /// Its color.
    pub colors: Vec<[f32; 3]>,
    /// Its pixel's opacity.
    pub opacities: Vec<f32>,
    /// The unit direction it was seen along.
    pub directions: Vec<[f32; 3]>,
    /// The width of its pixel at its depth.
    pub footprints: Vec<f32>,
    /// Each camera's view: the distance along each pixel's ray to what it saw, +∞ where it saw nothing
    /// opaque enough (row-major, `frame.0 × frame.1` pixels).
    pub distances: Vec<Vec<f32>>,
    /// The width and height of every view.
    pub frame: (u32, u32),
}

impl Surfels {
    /// Renders every camera's view of the field of `view` (`program` with `params`) as `frame` (width and
    /// height: the cameras' own aspect ratio, or a view's edges are cut off or stretched) and keeps the pixels whose opacity reaches `min_opacity`. With an occupancy grid, the views skip the
    /// cells of `trained_grid` (the grid the training of these params ended with) when it is the one the
    /// script's `train` block makes, else those of the grid
    /// [`Rendering::occupancy`](crate::commands::render_views::Rendering::occupancy) gives. The ranks of an
    /// MPI job share the views; rank 0 gets the surfels, the others `None`.
    pub(crate) fn render(
        view: &ViewArgs,
        (program, params): (&Program, &[f32]),
        trained_grid: Option<&OccupancyGrid>,
        cameras: &[Camera],
        frame: (u32, u32),
        min_opacity: f32,
    ) -> Result<Option<Surfels>> {
        let (width, height) = frame;
        let pixels = cameras.len() as u64 * u64::from(width) * u64::from(height);
        if pixels > MAX_POINTS {
            return Err(Failure::Message(format!(
                "{} views of {width}×{height} could give {pixels} points, more than the {MAX_POINTS} a cloud may \
                 hold: lower --size",
                cameras.len()
            )));
        }
        if !(min_opacity > 0.0 && min_opacity <= 1.0) {
            return Err(Failure::Message(format!(
                "--min-opacity {min_opacity} must be in (0, 1]"
            )));
        }
        let rendering = view.resolve(program);
        let cache = KernelCache::new();
        let fields = VolumeFields::compile(program, &cache, rendering.importance, rendering.products)?;
        let settings = rendering.settings(fields.fine.mode);
        let built;
        let grid = match trained_grid.filter(|g| rendering.skip_empty.is_some_and(|s| s.fits(g))) {
            Some(grid) => Some(grid),
            None => {
                built = rendering.occupancy(view.source, &fields, params)?;
                built.as_ref()
            }
        };
        // Each rank of an MPI job renders its share of the views; rank 0 gathers them.
        let rendered = crate::cluster::split(cameras.len(), |i| -> Result<Vec<u8>> {
            let frame = fields.render_with(&cameras[i], frame, params, &settings, grid)?;
            Ok(crate::blocks::volume::frame_bytes(&frame))
        })
        .map_err(Failure::Message)?;
        let Some(rendered) = rendered else {
            return Ok(None);
        };
        let mut surfels = Surfels {
            positions: Vec::new(),
            colors: Vec::new(),
            opacities: Vec::new(),
            directions: Vec::new(),
            footprints: Vec::new(),
            distances: Vec::new(),
            frame,
        };
        for (camera, bytes) in cameras.iter().zip(&rendered) {
            let rendered = crate::blocks::volume::frame_of(bytes, frame);
            surfels.add(camera, frame, &rendered, rendering.background, min_opacity);
            let seen = rendered.opacity.iter().zip(&rendered.depth);
            surfels.distances.push(
                seen.map(|(&o, &d)| if o >= min_opacity { d / o } else { f32::INFINITY })
                    .collect(),
            );
        }
        if surfels.positions.is_empty() {
            return Err(Failure::Message(format!(
                "no pixel of the {} views reaches opacity {min_opacity}: nothing to write",
                cameras.len()
            )));
        }
        Ok(Some(surfels))
    }

    /// Adds the opaque pixels of `frame` (rendered by `camera` as `width`×`height`).
    fn add(
        &mut self,
        camera: &Camera,
        (width, height): (u32, u32),
        frame: &nerfjit_runtime::VolumeFrame,
        background: [f32; 3],
        min_opacity: f32,
    ) {
        let focal = camera.pixel_intrinsics(width, height).fx.abs();
        for (i, &opacity) in frame.opacity.iter().enumerate() {
            if opacity < min_opacity {
                continue;
            }
            let (row, col) = (i as u32 / width, i as u32 % width);
            let (origin, direction) = camera.ray(row, col, width, height);
            let depth = frame.depth[i] / opacity;
            let rgb = frame.rgb[i];
            let color = std::array::from_fn(|c| {
                ((rgb[c] - background[c] * (1.0 - opacity)) / opacity).clamp(0.0, 1.0)
            });
            self.positions.push((origin + direction * depth).to_array());
            self.colors.push(color);
            self.opacities.push(opacity.min(1.0));
            self.directions.push(direction.to_array());
            self.footprints.push(depth / focal);
        }
    }
}
