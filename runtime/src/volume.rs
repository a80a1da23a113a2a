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

use std::cell::RefCell;

use rayon::prelude::*;

use crate::camera::Camera;
use crate::composite::{Compositor, Lanes, Mode, RayOutput, LAST_DELTA};
use crate::error::{check_size, Error, Result};
use crate::field::BatchFn;
use crate::sampler::linspace;

/// About this many sample points are evaluated per field call.
pub const TILE_POINTS: usize = 8192;

/// Samples per field call when early termination is on.
pub const CHUNK_SAMPLES: usize = 16;

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
        self.compositor().check()
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
    /// Samples per field call.
    chunk: usize,
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
    for (k, ((dx, dy), dz)) in dx[..n].iter_mut().zip(&mut dy[..n]).zip(&mut dz[..n]).enumerate() {
        let pixel = start + k;
        let d = job
            .camera
            .direction(job.xs[pixel % job.width], job.ys[pixel / job.width]);
        (*dx, *dy, *dz) = (d.x, d.y, d.z);
    }
    s.pixels.clear();
    s.pixels.extend(0..n);
    s.lanes.reset(n);
    let o = job.camera.position();
    let n_inputs = if job.view_dependent { 6 } else { 3 };
    let samples = job.depths.len();
    for first in (0..samples).step_by(job.chunk) {
        if n == 0 {
            break;
        }
        let m = job.chunk.min(samples - first);
        let len = m * n;
        let [x, y, z, vx, vy, vz] = &mut s.inputs;
        let [dx, dy, dz] = &s.directions;
        let depths = &job.depths[first..first + m];
        for (j, &t) in depths.iter().enumerate() {
            let row = j * n..(j + 1) * n;
            let (x, y, z) = (&mut x[row.clone()], &mut y[row.clone()], &mut z[row.clone()]);
            for ((((x, y), z), dx), (dy, dz)) in
                x.iter_mut().zip(y).zip(z).zip(&dx[..n]).zip(dy.iter().zip(dz))
            {
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
        let inputs: [&[f32]; 6] = [
            &x[..len],
            &y[..len],
            &z[..len],
            &vx[..len],
            &vy[..len],
            &vz[..len],
        ];
        let [raw, r, g, b] = &mut s.outputs;
        job.field.eval(
            len,
            &inputs[..n_inputs],
            &mut [&mut raw[..len], &mut r[..len], &mut g[..len], &mut b[..len]],
        );
        let deltas = &job.deltas[first..first + m];
        s.lanes.add(
            &job.compositor,
            depths,
            deltas,
            &raw[..len],
            [&r[..len], &g[..len], &b[..len]],
        );
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
    check_size(width, height)?;
    settings.check()?;
    let view_dependent = check_field(field)?;
    let mut depths = vec![0.0; settings.samples];
    linspace(settings.near, settings.far, &mut depths);
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
        chunk: match settings.early_termination {
            Some(_) => CHUNK_SAMPLES.min(settings.samples),
            None => settings.samples,
        },
    };
    let n = width as usize * height as usize;
    let mut frame = VolumeFrame {
        width,
        height,
        rgb: vec![[0.0; 3]; n],
        depth: vec![0.0; n],
        opacity: vec![0.0; n],
    };
    let tile = settings.rays_per_tile();
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
    use crate::composite::Samples;
    use crate::field::ClosureFn;
    use glam::{Vec2, Vec3};

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
