//! `nerfjit points`: a colored point cloud of a radiance field, as nerfstudio's `ns-export pointcloud`
//! makes one. Every view is volume-rendered; each pixel whose opacity reaches a threshold becomes the
//! point at its expected depth, with its rendered color (the background taken out) and a normal facing
//! the camera that saw it. Written as a binary PLY of vertices without faces.

use std::path::Path;
use std::time::Instant;

use nerfjit_jit::KernelCache;
use nerfjit_runtime::{Camera, Mesh};

use crate::commands::render_views::{CameraSource, ViewArgs};
use crate::failure::{Failure, Result};
use nerfjit_field::VolumeFields;

/// The most points a cloud may hold (views × pixels are checked against it before rendering).
pub const MAX_POINTS: u64 = 1 << 26;

/// What `nerfjit points` does.
pub struct PointsArgs<'a> {
    /// The field and how to render it (`size` is the side of each rendered view).
    pub view: ViewArgs<'a>,
    /// Where the cameras come from; by default, the cameras of the data the script trains on.
    pub cameras: CameraSource<'a>,
    /// Pixels below this opacity give no point.
    pub min_opacity: f32,
    /// The PLY file to write.
    pub out: &'a Path,
}

/// Renders the views, back-projects their opaque pixels and writes the cloud; returns a summary line.
pub fn run(args: &PointsArgs) -> Result<String> {
    let (program, params) = crate::checkpoint::load_source(args.view.source)?;
    let cameras = match args.cameras.cameras(args.view.source, &program)? {
        Some((cameras, _)) => cameras,
        None => {
            let folder = Path::new(args.view.source).parent().unwrap_or(Path::new(""));
            crate::blocks::train::data_cameras(&program, folder).ok_or_else(|| {
                Failure::Message(format!(
                    "{} trains on no data whose cameras can be read here: give --cameras FILE or --path 'orbit(...)'",
                    args.view.source
                ))
            })?
        }
    };
    let size = args.view.side();
    let pixels = cameras.len() as u64 * u64::from(size) * u64::from(size);
    if pixels > MAX_POINTS {
        return Err(Failure::Message(format!(
            "{} views of {size}×{size} could give {pixels} points, more than the {MAX_POINTS} a cloud may hold: \
             lower --size",
            cameras.len()
        )));
    }
    if !(args.min_opacity > 0.0 && args.min_opacity <= 1.0) {
        return Err(Failure::Message(format!(
            "--min-opacity {} must be in (0, 1]",
            args.min_opacity
        )));
    }
    let rendering = args.view.resolve(&program);
    let cache = KernelCache::new();
    let fields = VolumeFields::compile(&program, &cache, rendering.importance, rendering.products)?;
    let settings = rendering.settings(fields.fine.mode);
    let start = Instant::now();
    let mut cloud = Mesh {
        vertices: Vec::new(),
        normals: Vec::new(),
        triangles: Vec::new(),
        colors: Vec::new(),
    };
    let grid = rendering.occupancy(args.view.source, &fields, &params)?;
    // Each rank of an MPI job renders its share of the views; rank 0 gathers them and makes the cloud.
    let rendered = crate::cluster::split(cameras.len(), |i| -> Result<Vec<u8>> {
        let frame = fields.render_with(&cameras[i], (size, size), &params, &settings, grid.as_ref())?;
        Ok(crate::blocks::volume::frame_bytes(&frame))
    })
    .map_err(Failure::Message)?;
    let Some(rendered) = rendered else {
        return Ok(String::new());
    };
    for (camera, bytes) in cameras.iter().zip(&rendered) {
        let frame = crate::blocks::volume::frame_of(bytes, (size, size));
        add_points(
            &mut cloud,
            camera,
            size,
            &frame,
            rendering.background,
            args.min_opacity,
        );
    }
    let seconds = start.elapsed().as_secs_f64();
    if cloud.vertices.is_empty() {
        return Err(Failure::Message(format!(
            "no pixel of the {} views reaches opacity {}: nothing to write",
            cameras.len(),
            args.min_opacity
        )));
    }
    cloud.write_ply(args.out)?;
    Ok(format!(
        "{} points from {} views of {size}×{size} in {seconds:.2} s (opacity ≥ {}) → {}",
        cloud.vertices.len(),
        cameras.len(),
        args.min_opacity,
        args.out.display()
    ))
}

/// Adds the opaque pixels of `frame` (rendered by `camera` at `size`²) to `cloud`.
fn add_points(
    cloud: &mut Mesh,
    camera: &Camera,
    size: u32,
    frame: &nerfjit_runtime::VolumeFrame,
    background: [f32; 3],
    min_opacity: f32,
) {
    for (i, &opacity) in frame.opacity.iter().enumerate() {
        if opacity < min_opacity {
            continue;
        }
        let (row, col) = (i as u32 / size, i as u32 % size);
        let (origin, direction) = camera.ray(row, col, size, size);
        let depth = frame.depth[i] / opacity;
        let rgb = frame.rgb[i];
        let color =
            std::array::from_fn(|c| ((rgb[c] - background[c] * (1.0 - opacity)) / opacity).clamp(0.0, 1.0));
        cloud.vertices.push((origin + direction * depth).to_array());
        cloud.normals.push((-direction).to_array());
        cloud.colors.push(color);
    }
}
