//! Volume rendering of a field: samples along each pixel's ray, one field evaluation per
//! sample, composited by a [`Compositor`].
//!
//! The field maps a point (x, y, z), optionally followed by the unit view direction
//! (dx, dy, dz), to 4 outputs: density σ or opacity a (see [`Mode`]), then r, g, b. Each ray
//! samples `linspace(near, far, samples)`.
//!
//! The image is cut into tiles of about [`TILE_POINTS`] sample points, rendered in parallel
//! with buffers allocated once per worker. A tile lays its points out sample-major (sample j
//! of ray k at `j·rays + k`), evaluates them in one field call and composites across rays,
//! a loop that vectorizes. With early termination, a tile goes [`CHUNK_SAMPLES`] samples at
//! a time and drops the rays that have stopped after each step, so that the field is only
//! evaluated where it still matters.
//!
//! With an [`OccupancyGrid`] ([`render_volume_with`]), a sample whose point lies in an empty
//! cell (or outside the grid's bounds) is not evaluated and gets alpha = 0: it changes
//! neither the transmittance nor the outputs, whatever its color. Rays that miss the grid's
//! box (a slab test) write the background without any work; for the others, the samples
//! between where the ray enters and leaves the box are looked up in the grid, the occupied
//! ones packed ray by ray into one dense field call per tile (or per chunk with early
//! termination), and each ray composites its own evaluated samples in order. As a grid leaves
//! few samples of a ray to evaluate, such a tile takes many more rays (up to
//! [`PACKED_TILE_RAYS`]) so that the field calls stay large, and early termination goes
//! [`PACKED_CHUNK_SAMPLES`] samples at a time, so that few samples past a ray's end are
//! evaluated. Evaluated
//! samples are at exactly the points and depths of the exact render and composited with
//! the same operations, so the result is, bit for bit, the exact render of the field with
//! its first output set to 0 in the empty cells (given finite colors): the two renders
//! differ only by what the skipped samples would have added. Note the course's last δ of
//! 1e10: in [`Mode::Density`] a last sample of tiny σ has alpha ≈ 1 and would take the
//! remaining transmittance; skipped, it contributes nothing.

use std::cell::RefCell;
use std::ops::Range;

use rayon::prelude::*;

use crate::cameras::camera::Camera;
use crate::error::{check_size, Error, Result};
use crate::field::BatchFn;
use crate::volume::composite::{Compositor, Lanes, Mode, RayOutput, LAST_DELTA};
use crate::volume::occupancy::OccupancyGrid;
use crate::volume::sampler::{linspace, DepthSpacing};

/// About this many sample points are evaluated per field call.
pub const TILE_POINTS: usize = 8192;

/// Samples per field call when early termination is on.
pub const CHUNK_SAMPLES: usize = 16;

/// Rays per tile at most when an occupancy grid skips samples (tiles are also kept small
/// enough for eight a thread).
pub const PACKED_TILE_RAYS: usize = 16384;

/// Sample rows per field call when early termination is on and a grid skips samples.
pub const PACKED_CHUNK_SAMPLES: usize = 8;

/// Parameters of volume rendering and training.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VolumeSettings {
    /// Depth of the first sample (>= 0).
    pub near: f32,
    /// Depth of the last sample (> near).
    pub far: f32,
    /// Samples per ray (>= 2).
    pub samples: usize,
    /// Whether the field's first output is a density or an opacity.
    pub mode: Mode,
    /// Color seen through the remaining transmittance; `None` is black.
    pub background: Option<[f32; 3]>,
    /// Stop a ray once its transmittance falls below this (in (0, 1]); `None` is exact.
    pub early_termination: Option<f32>,
    /// How the samples are spread between near and far.
    pub spacing: DepthSpacing,
}

impl VolumeSettings {
    /// Checks the settings.
    pub(crate) fn check(&self) -> Result<()> {
        let ok = self.near.is_finite() && self.far.is_finite() && 0.0 <= self.near && self.near < self.far;
        if !ok || self.samples < 2 {
            return Err(Error::Invalid(format!(
                "volume rendering needs finite 0 <= near < far and at least 2 samples, got near {}, far {}, {} samples",
                self.near, self.far, self.samples
            )));
        }
        self.spacing.check(self.near, self.far)?;
        self.compositor().check()
    }

    /// The fixed sample depths of a ray: `linspace(near, far, out.len())` spread by the spacing.
    pub(crate) fn fixed_depths(&self, out: &mut [f32]) {
        linspace(self.near, self.far, out);
        self.spacing.warp_all(self.near, self.far, out);
    }

    /// The compositor of these settings.
    pub(crate) fn compositor(&self) -> Compositor {
        Compositor {
            mode: self.mode,
            background: self.background,
            early_termination: self.early_termination,
        }
    }

    /// Rays per tile: about [`TILE_POINTS`] points.
    pub(crate) fn rays_per_tile(&self) -> usize {
        (TILE_POINTS / self.samples).clamp(1, 1024)
    }
}

/// Checks that `field` maps a point (and maybe a view direction) to 4 outputs; returns
/// whether it takes the view direction.
pub(crate) fn check_field(field: &dyn BatchFn) -> Result<bool> {
    match (field.n_inputs(), field.n_outputs()) {
        (3, 4) => Ok(false),
        (6, 4) => Ok(true),
        (i, o) => Err(Error::Invalid(format!(
            "the field must map a point (3 inputs) or a point and a view direction (6 inputs) to \
             density-or-opacity and r, g, b (4 outputs), but it maps {i} inputs to {o} outputs"
        ))),
    }
}

/// A volume-rendered image, all in row-major pixel order.
#[derive(Debug, Clone, PartialEq)]
pub struct VolumeFrame {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Composited color.
    pub rgb: Vec<[f32; 3]>,
    /// Expected depth Σ wᵢtᵢ (not normalized by the opacity).
    pub depth: Vec<f32>,
    /// Opacity Σ wᵢ.
    pub opacity: Vec<f32>,
}

/// Per-worker buffers of the volume renderer and trainer, grown on demand and reused. Point
/// buffers are sample-major (sample j of ray k at `j·rays + k`).
#[derive(Debug, Default)]
pub(crate) struct Scratch {
    /// Field inputs: x, y, z, then the view direction.
    pub(crate) inputs: [Vec<f32>; 6],
    /// Field outputs: density or opacity, r, g, b.
    pub(crate) outputs: [Vec<f32>; 4],
    /// Cotangents of the field outputs (training).
    pub(crate) cotangents: [Vec<f32>; 4],
    /// Depth of each sample (training).
    pub(crate) depths: Vec<f32>,
    /// Unit direction of each ray of the tile (rendering).
    pub(crate) directions: [Vec<f32>; 3],
    /// Pixel in the tile of each ray of the tile (rendering).
    pub(crate) pixels: Vec<usize>,
    /// Accumulators of the rays of the tile.
    pub(crate) lanes: Lanes,
    /// Sample index of each packed (occupied) sample (rendering with a grid).
    pub(crate) samples: Vec<u32>,
    /// Grid cells of the samples of one ray (rendering with a grid).
    pub(crate) cells: Vec<u32>,
    /// End of the packed samples of each ray (rendering with a grid).
    pub(crate) ends: Vec<u32>,
    /// Depths where each ray enters and leaves the grid's box (rendering with a grid).
    pub(crate) intervals: [Vec<f32>; 2],
    /// Samples `first..end` of each ray that may be inside the grid (rendering with a grid).
    pub(crate) spans: Vec<[u32; 2]>,
}

impl Scratch {
    /// Makes every point buffer at least `points` and every ray buffer at least `rays` long.
    pub(crate) fn reserve(&mut self, points: usize, rays: usize) {
        let grow = |v: &mut Vec<f32>, n: usize| {
            if v.len() < n {
                v.resize(n, 0.0);
            }
        };
        for v in self
            .inputs
            .iter_mut()
            .chain(&mut self.outputs)
            .chain(&mut self.cotangents)
        {
            grow(v, points);
        }
        grow(&mut self.depths, points);
        for v in &mut self.directions {
            grow(v, rays);
        }
    }

    /// Also makes the buffers of rendering with a grid long enough.
    fn reserve_packed(&mut self, points: usize, rays: usize) {
        for v in [&mut self.samples, &mut self.cells] {
            if v.len() < points {
                v.resize(points, 0);
            }
        }
        if self.spans.len() < rays {
            self.spans.resize(rays, [0, 0]);
        }
        for v in &mut self.intervals {
            if v.len() < rays {
                v.resize(rays, 0.0);
            }
        }
    }
}

thread_local! {
    /// The buffers of this thread, reused across tiles, frames and steps.
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

/// Runs `f` with this thread's buffers (fresh ones if they are in use, which happens only if
/// a field runs parallel work that makes this thread render another tile).
pub(crate) fn with_scratch<T>(f: impl FnOnce(&mut Scratch) -> T) -> T {
    SCRATCH.with(|cell| match cell.try_borrow_mut() {
        Ok(mut scratch) => f(&mut scratch),
        Err(_) => f(&mut Scratch::default()),
    })
}

/// What every tile of a frame needs to know.
struct Job<'a> {
    camera: &'a Camera,
    width: usize,
    /// View-space x of each column's pixel centers.
    xs: Vec<f32>,
    /// View-space y of each row's pixel centers.
    ys: Vec<f32>,
    field: &'a dyn BatchFn,
    view_dependent: bool,
    compositor: Compositor,
    /// Sample depths (shared by all rays) and their δ.
    depths: Vec<f32>,
    deltas: Vec<f32>,
    /// 1 / (mean gap between depths).
    inv_step: f32,
    /// Samples per field call.
    chunk: usize,
    /// Skip the samples in its empty cells.
    grid: Option<&'a OccupancyGrid>,
    /// What a ray without any sample composites to.
    empty: RayOutput,
}

impl Job<'_> {
    /// The number of sample depths below `t` (or at most `t` if `inclusive`), that is the
    /// partition point of the sorted depths, found from a guess as they are about evenly
    /// spaced.
    fn samples_before(&self, t: f32, inclusive: bool) -> usize {
        let depths = &self.depths;
        let below = |d: f32| d < t || (inclusive && d == t);
        let n = depths.len();
        // Depth t is about `position` steps from the first: the guess is its ceiling.
        let position = ((t - depths[0]) * self.inv_step).clamp(0.0, n as f32);
        let mut i = (position as usize + 1).min(n);
        while i > 0 && !below(depths[i - 1]) {
            i -= 1;
        }
        while i < n && below(depths[i]) {
            i += 1;
        }
        i
    }
}

/// The part of the frame one tile writes.
struct TileOut<'a> {
    rgb: &'a mut [[f32; 3]],
    depth: &'a mut [f32],
    opacity: &'a mut [f32],
}

impl TileOut<'_> {
    /// Writes `ray` as pixel `pixel` of the tile.
    fn write(&mut self, pixel: usize, ray: RayOutput) {
        (self.rgb[pixel], self.depth[pixel], self.opacity[pixel]) = (ray.rgb, ray.depth, ray.opacity);
    }
}

/// Renders the pixels `start..start + out.rgb.len()` into `out`.
fn render_tile(job: &Job, s: &mut Scratch, start: usize, mut out: TileOut) {
    let mut n = out.rgb.len();
    s.reserve(job.chunk * n, n);
    let [dx, dy, dz] = &mut s.directions;
    let (mut row, mut col) = (start / job.width, start % job.width);
    for ((dx, dy), dz) in dx[..n].iter_mut().zip(&mut dy[..n]).zip(&mut dz[..n]) {
        let d = job.camera.direction(job.xs[col], job.ys[row]);
        (*dx, *dy, *dz) = (d.x, d.y, d.z);
        col += 1;
        if col == job.width {
            (row, col) = (row + 1, 0);
        }
    }
    s.pixels.clear();
    s.pixels.extend(0..n);
    let mut rows = 0..job.depths.len();
    if let Some(grid) = job.grid {
        s.reserve_packed(job.chunk * n, n);
        rows = cull_rays(job, grid, s, &mut out);
        n = s.pixels.len();
    }
    s.lanes.reset(n);
    let n_inputs = if job.view_dependent { 6 } else { 3 };
    for first in rows.clone().step_by(job.chunk) {
        if n == 0 {
            break;
        }
        let m = job.chunk.min(rows.end - first);
        let len = m * n;
        let depths = &job.depths[first..first + m];
        match job.grid {
            None => {
                eval_dense(job, s, depths, n, n_inputs);
                let [raw, r, g, b] = &s.outputs;
                s.lanes.add(
                    &job.compositor,
                    depths,
                    &job.deltas[first..first + m],
                    &raw[..len],
                    [&r[..len], &g[..len], &b[..len]],
                );
            }
            Some(grid) => march_packed(job, grid, s, first..first + m, n, n_inputs),
        }
        if job.compositor.early_termination.is_some() {
            // Compaction: stopped rays are written out; the others move to `live`, which
            // advances only for them, so the next field call sees live rays only.
            let mut live = 0;
            for k in 0..n {
                let pixel = s.pixels[k];
                if s.lanes.is_live(&job.compositor, k) {
                    s.lanes.move_ray(k, live);
                    s.pixels[live] = pixel;
                    for d in &mut s.directions {
                        d[live] = d[k];
                    }
                    if job.grid.is_some() {
                        s.spans[live] = s.spans[k];
                    }
                    live += 1;
                } else {
                    out.write(pixel, s.lanes.output(&job.compositor, k));
                }
            }
            s.lanes.truncate(live);
            n = live;
        }
    }
    for k in 0..n {
        out.write(s.pixels[k], s.lanes.output(&job.compositor, k));
    }
}

/// Evaluates the field at `depths` on the `n` rays of the tile, sample-major, into the
/// outputs of `s`.
fn eval_dense(job: &Job, s: &mut Scratch, depths: &[f32], n: usize, n_inputs: usize) {
    let o = job.camera.position();
    let len = depths.len() * n;
    let [x, y, z, vx, vy, vz] = &mut s.inputs;
    let [dx, dy, dz] = &s.directions;
    for (j, &t) in depths.iter().enumerate() {
        let row = j * n..(j + 1) * n;
        let (x, y, z) = (&mut x[row.clone()], &mut y[row.clone()], &mut z[row.clone()]);
        for ((((x, y), z), dx), (dy, dz)) in x.iter_mut().zip(y).zip(z).zip(&dx[..n]).zip(dy.iter().zip(dz)) {
            *x = o.x + dx * t;
            *y = o.y + dy * t;
            *z = o.z + dz * t;
        }
        if job.view_dependent {
            vx[row.clone()].copy_from_slice(&dx[..n]);
            vy[row.clone()].copy_from_slice(&dy[..n]);
            vz[row].copy_from_slice(&dz[..n]);
        }
    }
    let inputs: [&[f32]; 6] = [&*x, &*y, &*z, &*vx, &*vy, &*vz].map(|c| &c[..len]);
    let [raw, r, g, b] = &mut s.outputs;
    job.field.eval(
        len,
        &inputs[..n_inputs],
        &mut [&mut raw[..len], &mut r[..len], &mut g[..len], &mut b[..len]],
    );
}

/// Drops the rays of the tile that have no sample inside the grid's box, writing the empty
/// ray for them, and notes the samples each remaining ray may have inside (`s.spans`);
/// returns the samples where some ray of the tile may be inside.
fn cull_rays(job: &Job, grid: &OccupancyGrid, s: &mut Scratch, out: &mut TileOut) -> Range<usize> {
    let n = s.pixels.len();
    let [dx, dy, dz] = &mut s.directions;
    let [t0, t1] = &mut s.intervals;
    let (t0, t1) = (&mut t0[..n], &mut t1[..n]);
    let o = job.camera.position().to_array();
    grid.ray_intervals(o, [&dx[..n], &dy[..n], &dz[..n]], t0, t1);
    let (mut lo, mut hi) = (usize::MAX, 0);
    let mut live = 0;
    for k in 0..n {
        let (first, end) = if t0[k] <= t1[k] {
            (job.samples_before(t0[k], false), job.samples_before(t1[k], true))
        } else {
            (0, 0)
        };
        if first < end {
            (dx[live], dy[live], dz[live]) = (dx[k], dy[k], dz[k]);
            s.pixels[live] = s.pixels[k];
            s.spans[live] = [first as u32, end as u32];
            (lo, hi) = (lo.min(first), hi.max(end));
            live += 1;
        } else {
            out.write(s.pixels[k], job.empty);
        }
    }
    s.pixels.truncate(live);
    lo.min(hi)..hi
}

/// Evaluates the field at the samples `rows` of the `n` rays of the tile where the grid is
/// occupied (only those in the rays' spans can be), packed into one call, and composites
/// them ray by ray: the skipped samples have alpha 0, which changes nothing.
fn march_packed(
    job: &Job,
    grid: &OccupancyGrid,
    s: &mut Scratch,
    rows: Range<usize>,
    n: usize,
    n_inputs: usize,
) {
    let o = job.camera.position();
    let [x, y, z, vx, vy, vz] = &mut s.inputs;
    let [dx, dy, dz] = &s.directions;
    let mut packed = 0;
    s.ends.clear();
    // Ray by ray, the points of the rows in its span, of which the grid keeps the occupied;
    // the packed samples of ray k end at ends[k].
    let rays = s.spans[..n].iter().zip(dx.iter().zip(dy).zip(dz));
    for (&[a, b], ((&dx, &dy), &dz)) in rays {
        let (a, b) = ((a as usize).max(rows.start), (b as usize).min(rows.end));
        if a < b {
            let end = packed + b - a;
            let (x, y, z) = (&mut x[packed..end], &mut y[packed..end], &mut z[packed..end]);
            for (((x, y), z), t) in x
                .iter_mut()
                .zip(y.iter_mut())
                .zip(z.iter_mut())
                .zip(&job.depths[a..b])
            {
                *x = o.x + dx * t;
                *y = o.y + dy * t;
                *z = o.z + dz * t;
            }
            let samples = &mut s.samples[packed..end];
            let here = grid.pack_occupied([x, y, z], samples, a as u32, &mut s.cells[..b - a]);
            if job.view_dependent {
                vx[packed..packed + here].fill(dx);
                vy[packed..packed + here].fill(dy);
                vz[packed..packed + here].fill(dz);
            }
            packed += here;
        }
        s.ends.push(packed as u32);
    }
    if packed == 0 {
        return;
    }
    let inputs: [&[f32]; 6] = [&*x, &*y, &*z, &*vx, &*vy, &*vz].map(|c| &c[..packed]);
    let [raw, r, g, b] = &mut s.outputs;
    job.field.eval(
        packed,
        &inputs[..n_inputs],
        &mut [
            &mut raw[..packed],
            &mut r[..packed],
            &mut g[..packed],
            &mut b[..packed],
        ],
    );
    let mut start = 0;
    for (k, &end) in s.ends.iter().enumerate() {
        let end = end as usize;
        if start < end {
            let samples = start..end;
            s.lanes.add_sparse(
                &job.compositor,
                k,
                &s.samples[samples.clone()],
                (&job.depths, &job.deltas),
                &raw[samples.clone()],
                [&r[samples.clone()], &g[samples.clone()], &b[samples]],
            );
        }
        start = end;
    }
}

/// The δ of each of `depths`: the gap to the next one, [`LAST_DELTA`] for the last.
fn deltas(depths: &[f32]) -> Vec<f32> {
    let mut deltas: Vec<f32> = depths.windows(2).map(|w| w[1] - w[0]).collect();
    deltas.push(LAST_DELTA);
    deltas
}

/// Volume renders a `width`×`height` image of `field` seen by `camera`: `settings.samples`
/// samples at `linspace(near, far, samples)` along each pixel's unit ray. See the module
/// docs for the field's inputs and outputs.
pub fn render_volume(
    camera: &Camera,
    width: u32,
    height: u32,
    field: &dyn BatchFn,
    settings: &VolumeSettings,
) -> Result<VolumeFrame> {
    render_volume_with(camera, width, height, field, settings, None)
}

/// [`render_volume`], skipping the samples in the empty cells of `grid` if there is one
/// (they get alpha = 0 without evaluating the field; see the module docs). The grid is an
/// approximation of the field (see [`crate::volume::occupancy`]); without one the render is exact.
pub fn render_volume_with(
    camera: &Camera,
    width: u32,
    height: u32,
    field: &dyn BatchFn,
    settings: &VolumeSettings,
    grid: Option<&OccupancyGrid>,
) -> Result<VolumeFrame> {
    check_size(width, height)?;
    settings.check()?;
    let view_dependent = check_field(field)?;
    let mut depths = vec![0.0; settings.samples];
    settings.fixed_depths(&mut depths);
    let job = Job {
        camera,
        width: width as usize,
        xs: (0..width)
            .map(|col| camera.view_x(col as f32 + 0.5, width, height))
            .collect(),
        ys: (0..height)
            .map(|row| camera.view_y(row as f32 + 0.5, width, height))
            .collect(),
        field,
        view_dependent,
        compositor: settings.compositor(),
        deltas: deltas(&depths),
        depths,
        chunk: match (settings.early_termination, grid) {
            (Some(_), None) => CHUNK_SAMPLES.min(settings.samples),
            (Some(_), Some(_)) => PACKED_CHUNK_SAMPLES.min(settings.samples),
            (None, _) => settings.samples,
        },
        inv_step: (settings.samples - 1) as f32 / (settings.far - settings.near),
        grid,
        empty: settings.compositor().empty_ray(),
    };
    let n = width as usize * height as usize;
    let mut frame = VolumeFrame {
        width,
        height,
        rgb: vec![[0.0; 3]; n],
        depth: vec![0.0; n],
        opacity: vec![0.0; n],
    };
    let tile = match grid {
        // Eight tiles a thread at least, for the balance between threads.
        Some(_) => (n / (8 * rayon::current_num_threads())).clamp(settings.rays_per_tile(), PACKED_TILE_RAYS),
        None => settings.rays_per_tile(),
    };
    frame
        .rgb
        .par_chunks_mut(tile)
        .zip(frame.depth.par_chunks_mut(tile))
        .zip(frame.opacity.par_chunks_mut(tile))
        .enumerate()
        .for_each(|(k, ((rgb, depth), opacity))| {
            let out = TileOut { rgb, depth, opacity };
            with_scratch(|s| render_tile(&job, s, k * tile, out));
        });
    Ok(frame)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::ClosureFn;
    use crate::volume::composite::Samples;
    use glam::{Vec2, Vec3};
    use std::sync::atomic::{AtomicUsize, Ordering};

    fn camera() -> Camera {
        Camera::look_at(
            Vec3::new(0.4, 0.3, -3.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::splat(2.0),
            Vec2::new(0.05, 0.0),
        )
        .unwrap()
    }

    fn settings(mode: Mode) -> VolumeSettings {
        VolumeSettings {
            spacing: crate::volume::sampler::DepthSpacing::Linear,
            near: 1.0,
            far: 5.0,
            samples: 96,
            mode,
            background: None,
            early_termination: None,
        }
    }

    /// Where the ray (o, d) enters and leaves the sphere of `radius` around `center`.
    fn sphere_hits(o: Vec3, d: Vec3, center: Vec3, radius: f32) -> Option<(f32, f32)> {
        let oc = o - center;
        let b = oc.dot(d);
        let disc = b * b - (oc.dot(oc) - radius * radius);
        (disc >= 0.0).then(|| (-b - disc.sqrt(), -b + disc.sqrt()))
    }

    #[test]
    fn hard_sphere_silhouette_matches_ray_sphere_intersection() {
        let (center, radius) = (Vec3::new(0.2, -0.1, 0.3), 0.8);
        // Dense inside, empty outside, colored by position.
        let field = ClosureFn::new(3, 4, move |p, out| {
            let inside = (Vec3::new(p[0], p[1], p[2]) - center).length() < radius;
            out[0] = if inside { 200.0 } else { 0.0 };
            out[1..4].copy_from_slice(&[0.5 + 0.5 * p[0], 0.5, 0.5 - 0.5 * p[2]]);
        });
        let cam = camera();
        let (w, h) = (48, 40);
        let frame = render_volume(&cam, w, h, &field, &settings(Mode::Density)).unwrap();
        assert_eq!((frame.width, frame.height, frame.rgb.len()), (w, h, 48 * 40));
        let bin = 4.0 / 95.0;
        let (mut hits, mut checked) = (0, 0);
        for row in 0..h {
            for col in 0..w {
                let k = (row * w + col) as usize;
                let (o, d) = cam.ray(row, col, w, h);
                let hit = sphere_hits(o, d, center, radius);
                // Edge pixels: rays that graze the sphere, with a chord shorter than 3 bins.
                if hit.is_some_and(|(t0, t1)| t1 - t0 < 3.0 * bin) {
                    continue;
                }
                checked += 1;
                match hit {
                    Some((t0, _)) => {
                        hits += 1;
                        assert!(
                            frame.opacity[k] > 0.999,
                            "pixel {row},{col}: opacity {}",
                            frame.opacity[k]
                        );
                        // Depth: the first sample inside the sphere, within one bin.
                        assert!(
                            (frame.depth[k] - t0).abs() <= bin + 1e-3,
                            "depth {} vs {t0}",
                            frame.depth[k]
                        );
                        let p = o + d * frame.depth[k];
                        let expected = [0.5 + 0.5 * p.x, 0.5, 0.5 - 0.5 * p.z];
                        for (c, e) in frame.rgb[k].iter().zip(expected) {
                            assert!(
                                (c - e).abs() < 0.5 * bin + 1e-3,
                                "color {:?} vs {expected:?}",
                                frame.rgb[k]
                            );
                        }
                    }
                    None => {
                        assert_eq!(frame.opacity[k], 0.0, "pixel {row},{col}");
                        assert_eq!(frame.rgb[k], [0.0; 3]);
                    }
                }
            }
        }
        assert!(checked > 1700 && hits > 250, "checked {checked}, hits {hits}");
    }

    #[test]
    fn frame_matches_per_ray_compositing_in_both_modes() {
        // A soft blob with a view-dependent color, so every code path carries information.
        let blob = |p: &[f32]| (-(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])).exp();
        for mode in [Mode::Density, Mode::Opacity] {
            let field = ClosureFn::new(6, 4, move |p, out| {
                let b = blob(p);
                out[0] = if mode == Mode::Density { 3.0 * b } else { 0.2 * b };
                out[1] = b;
                out[2] = p[3].abs();
                out[3] = 0.5 + 0.5 * p[4];
            });
            for early_termination in [None, Some(0.3)] {
                let settings = VolumeSettings {
                    background: Some([0.1, 0.2, 0.3]),
                    early_termination,
                    ..settings(mode)
                };
                let cam = camera();
                let frame = render_volume(&cam, 21, 13, &field, &settings).unwrap();
                let mut depths = vec![0.0; settings.samples];
                linspace(settings.near, settings.far, &mut depths);
                for (k, (row, col)) in [(0, 0), (6, 10), (12, 20), (5, 3)].into_iter().enumerate() {
                    let (o, d) = cam.ray(row, col, 21, 13);
                    let mut outputs = vec![[0.0; 4]; depths.len()];
                    for (t, out) in depths.iter().zip(&mut outputs) {
                        let p = o + d * *t;
                        field.eval(
                            1,
                            &[&[p.x], &[p.y], &[p.z], &[d.x], &[d.y], &[d.z]],
                            &mut out.each_mut().map(std::slice::from_mut),
                        );
                    }
                    let column = |c: usize| outputs.iter().map(|o| o[c]).collect::<Vec<_>>();
                    let (raw, r, g, b) = (column(0), column(1), column(2), column(3));
                    let ray = settings
                        .compositor()
                        .forward(&Samples::new(&depths, &raw, [&r, &g, &b]).unwrap());
                    let pixel = (row * 21 + col) as usize;
                    let got = (frame.rgb[pixel], frame.depth[pixel], frame.opacity[pixel]);
                    let close = |a: f32, b: f32| (a - b).abs() < 1e-5;
                    assert!(
                        (0..3).all(|c| close(got.0[c], ray.rgb[c]))
                            && close(got.1, ray.depth)
                            && close(got.2, ray.opacity),
                        "{mode:?} {early_termination:?} case {k}: {got:?} vs {ray:?}"
                    );
                }
            }
        }
    }

    /// The course's box (sides 1.75) as a per-sample opacity (Laplace, β = 0.05), colored by
    /// position; `calls` counts the points evaluated.
    fn box_field(calls: &AtomicUsize) -> impl BatchFn + '_ {
        ClosureFn::new(3, 4, move |p, out| {
            calls.fetch_add(1, Ordering::Relaxed);
            let q = [0, 1, 2].map(|i| p[i].abs() - 0.875);
            let outside = q.iter().map(|q| q.max(0.0).powi(2)).sum::<f32>().sqrt();
            let s = outside + q[0].max(q[1]).max(q[2]).min(0.0);
            out[0] = if s > 0.0 {
                0.5 * (-s / 0.05).exp()
            } else {
                1.0 - 0.5 * (s / 0.05).exp()
            };
            for i in 0..3 {
                out[1 + i] = p[i].abs().clamp(0.02, 0.98);
            }
        })
    }

    fn max_abs_difference(a: &VolumeFrame, b: &VolumeFrame) -> f32 {
        let rgb = a
            .rgb
            .iter()
            .zip(&b.rgb)
            .flat_map(|(a, b)| (0..3).map(|c| (a[c] - b[c]).abs()));
        let opacity = a.opacity.iter().zip(&b.opacity).map(|(a, b)| (a - b).abs());
        rgb.chain(opacity).fold(0.0, f32::max)
    }

    #[test]
    fn grid_renders_are_within_1_255_of_exact_with_far_fewer_samples() {
        let calls = AtomicUsize::new(0);
        let field = box_field(&calls);
        let cam = Camera::look_at(
            Vec3::new(1.5, 1.0, -2.4),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::ONE,
            Vec2::ZERO,
        )
        .unwrap();
        let grid = OccupancyGrid::build(&field, ([-1.5; 3], [1.5; 3]), 64, Mode::Opacity, 1e-4).unwrap();
        let settings = VolumeSettings {
            near: 0.0,
            far: 5.0,
            samples: 64,
            ..settings(Mode::Opacity)
        };
        for background in [None, Some([0.2, 0.9, 0.5])] {
            let settings = VolumeSettings {
                background,
                ..settings
            };
            calls.store(0, Ordering::Relaxed);
            let exact = render_volume(&cam, 64, 64, &field, &settings).unwrap();
            let dense = calls.swap(0, Ordering::Relaxed);
            let fast = render_volume_with(&cam, 64, 64, &field, &settings, Some(&grid)).unwrap();
            let sparse = calls.load(Ordering::Relaxed);
            assert_eq!(dense, 64 * 64 * 64);
            assert!(5 * sparse < dense, "{sparse} of {dense} samples evaluated");
            let error = max_abs_difference(&exact, &fast);
            assert!(error <= 1.0 / 255.0, "max |Δ| {error}");
            // The box covers part of the image only, and both renders see it.
            let covered = exact.opacity.iter().filter(|&&a| a > 0.5).count();
            assert!(covered > 500 && covered < 3500, "{covered}");
        }
    }

    #[test]
    fn grid_renders_are_exact_renders_of_the_field_cut_to_the_grid() {
        // A soft view-dependent blob off center, partly outside the grid's box.
        let blob = |p: &[f32]| (-2.0 * ((p[0] - 0.3).powi(2) + p[1] * p[1] + p[2] * p[2])).exp();
        for mode in [Mode::Density, Mode::Opacity] {
            let value = move |p: &[f32]| {
                if mode == Mode::Density {
                    4.0 * blob(p)
                } else {
                    0.3 * blob(p)
                }
            };
            let field = ClosureFn::new(6, 4, move |p, out| {
                out[0] = value(p);
                out[1] = blob(p);
                out[2] = p[3].abs();
                out[3] = 0.5 + 0.5 * p[4];
            });
            // Thresholds at about 0.8 from the blob's center, so that much of it is cut.
            let threshold = if mode == Mode::Density { 1.0 } else { 0.08 };
            let grid =
                OccupancyGrid::build(&field, ([-1.0, -1.2, -0.9], [1.1, 1.0, 1.3]), 24, mode, threshold)
                    .unwrap();
            assert!(
                grid.occupancy() > 0.1 && grid.occupancy() < 0.9,
                "{}",
                grid.occupancy()
            );
            // The same field, with value 0 where the grid is empty.
            let cut = ClosureFn::new(6, 4, |p, out| {
                let mut o = [0.0f32; 4];
                let inputs = [&p[0..1], &p[1..2], &p[2..3], &p[3..4], &p[4..5], &p[5..6]];
                field.eval(1, &inputs, &mut o.each_mut().map(std::slice::from_mut));
                out.copy_from_slice(&o);
                if !grid.occupied([p[0], p[1], p[2]]) {
                    out[0] = 0.0;
                }
            });
            // The larger frame renders with tiles of more rays than the exact render's.
            let cases = [(33, 27), (200, 150)]
                .into_iter()
                .flat_map(|size| [(size, None), (size, Some(0.3))]);
            for ((width, height), early_termination) in cases {
                let settings = VolumeSettings {
                    background: Some([0.1, 0.2, 0.3]),
                    early_termination,
                    ..settings(mode)
                };
                let fast =
                    render_volume_with(&camera(), width, height, &field, &settings, Some(&grid)).unwrap();
                let reference = render_volume(&camera(), width, height, &cut, &settings).unwrap();
                assert_eq!(fast, reference, "{mode:?} {width}×{height} {early_termination:?}");
            }
        }
    }

    #[test]
    fn sample_spans_are_partition_points_of_the_depths() {
        for (near, far, samples) in [(0.0, 5.0, 64), (1.0, 5.0, 96), (0.3, 0.7, 2), (2.0, 1e4, 1000)] {
            let mut depths = vec![0.0; samples];
            linspace(near, far, &mut depths);
            let job = Job {
                camera: &camera(),
                width: 1,
                xs: vec![],
                ys: vec![],
                field: &ClosureFn::new(3, 4, |_, _| {}),
                view_dependent: false,
                compositor: settings(Mode::Opacity).compositor(),
                deltas: deltas(&depths),
                inv_step: (samples - 1) as f32 / (far - near),
                depths: depths.clone(),
                chunk: samples,
                grid: None,
                empty: RayOutput::default(),
            };
            let mut ts: Vec<f32> = depths
                .iter()
                .flat_map(|&d| [d, d.next_up(), d.next_down()])
                .collect();
            ts.extend([
                -1.0,
                near - 1.0,
                far + 1.0,
                f32::INFINITY,
                f32::NEG_INFINITY,
                0.5 * (near + far),
            ]);
            for t in ts {
                assert_eq!(
                    job.samples_before(t, false),
                    depths.partition_point(|&d| d < t),
                    "{t}"
                );
                assert_eq!(
                    job.samples_before(t, true),
                    depths.partition_point(|&d| d <= t),
                    "{t}"
                );
            }
        }
    }

    #[test]
    fn an_empty_grid_skips_everything() {
        let calls = AtomicUsize::new(0);
        let zero = ClosureFn::new(3, 4, |_, out| out.fill(0.0));
        let grid = OccupancyGrid::build(&zero, ([-1.5; 3], [1.5; 3]), 32, Mode::Opacity, 0.0).unwrap();
        assert_eq!(grid.occupied_cells(), 0);
        let field = box_field(&calls);
        let settings = VolumeSettings {
            background: Some([0.25, 0.5, 1.0]),
            ..settings(Mode::Opacity)
        };
        let frame = render_volume_with(&camera(), 20, 16, &field, &settings, Some(&grid)).unwrap();
        assert_eq!(calls.load(Ordering::Relaxed), 0);
        assert!(frame.rgb.iter().all(|&c| c == [0.25, 0.5, 1.0]));
        assert!(frame.depth.iter().chain(&frame.opacity).all(|&x| x == 0.0));
    }

    #[test]
    fn bad_arguments_are_errors() {
        let cam = camera();
        let field = ClosureFn::new(3, 4, |_, out| out.fill(0.0));
        let good = settings(Mode::Opacity);
        assert!(render_volume(&cam, 4, 4, &field, &good).is_ok());
        assert!(render_volume(&cam, 0, 4, &field, &good).is_err());
        let sdf = ClosureFn::new(3, 1, |_, out| out[0] = 0.0);
        let e = render_volume(&cam, 4, 4, &sdf, &good).unwrap_err().to_string();
        assert!(e.contains("maps 3 inputs to 1 outputs"), "{e}");
        let bad = [
            VolumeSettings { samples: 1, ..good },
            VolumeSettings { far: 1.0, ..good },
            VolumeSettings {
                near: f32::NAN,
                ..good
            },
            VolumeSettings {
                early_termination: Some(2.0),
                ..good
            },
        ];
        for s in bad {
            assert!(render_volume(&cam, 4, 4, &field, &s).is_err(), "{s:?}");
        }
    }
}
