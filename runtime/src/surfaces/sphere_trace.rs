//! Sphere tracing of signed distance functions, the renderer of surfaces.
//!
//! Per ray, from `t = near`, up to `max_steps` times: `p = o + t·d`, `dist = sdf(p)`; if
//! `dist < eps` the ray hits at `p` (stop); else `t += dist`, and if `t > far` the ray misses
//! (stop). A ray still marching after `max_steps` misses.
//!
//! The image is cut into tiles of [`TILE`] pixels traced in parallel. Each tile keeps its live
//! rays in structure-of-arrays buffers, allocated once per worker, and compacts them after each
//! step, so every SDF call gets a dense batch of live rays only. All of this leaves the
//! per-ray arithmetic, hence the result, exactly that of a plain per-ray loop.
//!
//! An SDF that offers interval bounds ([`BatchFn::interval_bounds`]) has the empty space in front of
//! each group of rays skipped first (`empty_space`): the rays start marching where the bounds stop
//! proving that no ray of the group comes within `eps` of the surface, and the rays of a group proven
//! empty all along miss without any SDF evaluation. Sphere tracing from a later start finds the same
//! hits, at depths that agree up to the tracer's tolerance.

use std::cell::RefCell;

use glam::Vec3;
use rayon::prelude::*;

use crate::cameras::camera::Camera;
use crate::error::{check_size, Error, Result};
use crate::field::{check_arity, BatchFn};
use crate::field::{MarchRays, RayMarcher};
use crate::output::frame::Frame;
use crate::surfaces::empty_space::{self, GroupedRays, GROUP_COLUMNS};

/// Number of pixels (consecutive in row-major order) traced together as one batch.
pub const TILE: usize = 1024;

// Ray slots within a tile are `u16`.
const _: () = assert!(TILE <= 1 << 16);

/// Parameters of [`sphere_trace`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TraceSettings {
    /// Distance along the ray where marching starts (>= 0).
    pub near: f32,
    /// A ray whose `t` exceeds `far` misses (> near; may be infinite).
    pub far: f32,
    /// A point with `sdf < eps` is a hit (> 0).
    pub eps: f32,
    /// Maximum number of SDF evaluations per ray.
    pub max_steps: u32,
    /// Color of pixels whose ray misses.
    pub background: [f32; 3],
    /// Optional bounding sphere (center, radius) promised to contain the whole surface.
    ///
    /// Rays that miss the sphere (inflated by `eps`) are misses without any SDF evaluation;
    /// the others march from `max(near, entry)` and miss once `t > min(far, exit)`. The result
    /// is plain sphere tracing on that interval, which agrees with unbounded tracing up to
    /// rounding of the hit point and rays that graze the surface.
    pub bounds: Option<(Vec3, f32)>,
}

impl Default for TraceSettings {
    fn default() -> Self {
        TraceSettings {
            near: 0.0,
            far: 10.0,
            eps: 1e-5,
            max_steps: 64,
            background: [0.0; 3],
            bounds: None,
        }
    }
}

impl TraceSettings {
    fn check(&self) -> Result<()> {
        let ok = self.near.is_finite()
            && self.near >= 0.0
            && self.far > self.near
            && self.eps.is_finite()
            && self.eps > 0.0;
        if !ok {
            return Err(Error::Invalid(format!(
                "trace settings need 0 <= near < far and eps > 0, got near {}, far {}, eps {}",
                self.near, self.far, self.eps
            )));
        }
        if let Some((center, radius)) = self.bounds {
            if !(center.is_finite() && radius.is_finite() && radius > 0.0) {
                return Err(Error::Invalid(format!(
                    "bounding sphere needs a finite center and a positive radius, got {center} and {radius}"
                )));
            }
        }
        Ok(())
    }

    /// The interval [t0, t1] of the ray (`o`, `d`) to march, or `None` if it is culled: the scalar
    /// reference of [`TraceSettings::intervals`], which the tracer runs.
    #[cfg(test)]
    fn interval(&self, o: Vec3, d: Vec3) -> Option<(f32, f32)> {
        let Some((center, radius)) = self.bounds else {
            return Some((self.near, self.far));
        };
        let radius = radius + self.eps;
        let oc = o - center;
        let b = oc.dot(d);
        let disc = b * b - (oc.dot(oc) - radius * radius);
        if disc.is_nan() || disc < 0.0 {
            return None;
        }
        let s = disc.sqrt();
        let (t0, t1) = (self.near.max(-b - s), self.far.min(-b + s));
        (t0 <= t1).then_some((t0, t1))
    }

    /// [`TraceSettings::interval`] of the rays from `o` along the directions `d` (component columns) into
    /// `t0` and `t1`, in a loop that vectorizes: the same values, bit for bit, and for a culled ray
    /// `t1 = −∞` (so that a ray is marched exactly where `t0 ≤ t1`).
    fn intervals(&self, o: Vec3, d: [&[f32]; 3], t0: &mut [f32], t1: &mut [f32]) {
        let Some((center, radius)) = self.bounds else {
            t0.fill(self.near);
            t1.fill(self.far);
            return;
        };
        let radius = radius + self.eps;
        let oc = o - center;
        let c = oc.dot(oc) - radius * radius;
        let n = t0.len();
        let (dx, dy, dz, t1) = (&d[0][..n], &d[1][..n], &d[2][..n], &mut t1[..n]);
        for k in 0..n {
            // The order of `Vec3::dot`.
            let b = oc.x * dx[k] + oc.y * dy[k] + oc.z * dz[k];
            let disc = b * b - c;
            let s = disc.sqrt();
            let (lo, hi) = (self.near.max(-b - s), self.far.min(-b + s));
            // `disc >= 0` is false for NaN too.
            let kept = disc >= 0.0 && lo <= hi;
            t0[k] = lo;
            t1[k] = if kept { hi } else { f32::NEG_INFINITY };
        }
    }
}

/// How hit points are colored.
#[derive(Clone, Copy)]
pub enum Shading<'a> {
    /// The script's color: `color` maps a point (3 inputs) to RGB (3 outputs). Normals come
    /// from `gradient` (3 inputs → 4 outputs: d, ∂x, ∂y, ∂z) when given, else are zero.
    Color {
        /// Point → RGB.
        color: &'a dyn BatchFn,
        /// Point → (d, ∇d), for the normal map.
        gradient: Option<&'a dyn BatchFn>,
    },
    /// Diffuse shading `albedo · max(0, n·l)` with n the normalized gradient of the SDF.
    Lambert {
        /// Point → (d, ∂x, ∂y, ∂z).
        gradient: &'a dyn BatchFn,
        /// Direction from the surface towards the light (normalized here).
        light_dir: Vec3,
        /// Surface color.
        albedo: [f32; 3],
    },
}

impl Shading<'_> {
    fn check(&self) -> Result<()> {
        match self {
            Shading::Color { color, gradient } => {
                check_arity(*color, "the color function", 3, 3)?;
                if let Some(g) = gradient {
                    check_arity(*g, "the gradient function", 3, 4)?;
                }
            }
            Shading::Lambert {
                gradient, light_dir, ..
            } => {
                check_arity(*gradient, "the gradient function", 3, 4)?;
                if light_dir.normalize_or_zero() == Vec3::ZERO {
                    return Err(Error::Invalid(format!(
                        "light direction {light_dir} must be finite and non-zero"
                    )));
                }
            }
        }
        Ok(())
    }
}

/// What every tile needs to know about the frame.
struct Job<'a> {
    camera: &'a Camera,
    width: usize,
    /// View-space x of each column's pixel centers.
    xs: Vec<f32>,
    /// View-space y of each row's pixel centers.
    ys: Vec<f32>,
    sdf: &'a dyn BatchFn,
    shading: &'a Shading<'a>,
    settings: &'a TraceSettings,
}

/// The part of the frame one tile writes.
struct TileOut<'a> {
    rgb: &'a mut [[f32; 3]],
    depth: &'a mut [f32],
    normal: &'a mut [[f32; 3]],
    hit: &'a mut [bool],
}

/// The fixed part of a ray of a tile: unit direction, end of its interval, pixel in the tile.
#[derive(Debug, Clone, Copy, Default)]
struct Ray {
    dx: f32,
    dy: f32,
    dz: f32,
    t_end: f32,
    pixel: u32,
}

/// Per-worker buffers, allocated once and reused for every tile.
struct Tile {
    /// Directions of one row segment of pixels, computed together, and their intervals to march.
    dirs: [Vec<f32>; 3],
    seg_t0: Vec<f32>,
    seg_t1: Vec<f32>,
    /// The rays that were not culled, in slots 0..n.
    rays: Vec<Ray>,
    /// Dense state of the live rays: slot, current `t`, current point (the SDF inputs) and
    /// its SDF value. Compaction moves only these.
    slots: Vec<u16>,
    t: Vec<f32>,
    points: [Vec<f32>; 3],
    dist: Vec<f32>,
    /// The hits: pixel in the tile, `t` and point (the shading inputs).
    n_hits: usize,
    hit_pixel: Vec<u32>,
    hit_t: Vec<f32>,
    hit_points: [Vec<f32>; 3],
    /// Shading outputs: color (3) and gradient (4).
    color: [Vec<f32>; 3],
    grad: [Vec<f32>; 4],
    /// Columns of a fused march: origins, ray ends, and the hit flags it returns.
    origin: [Vec<f32>; 3],
    t_end: Vec<f32>,
    hit_flag: Vec<f32>,
    /// Group of each ray for empty space skipping: its block of pixel columns.
    group: Vec<u32>,
    empty_space: empty_space::Scratch,
}

impl Tile {
    fn new() -> Self {
        let v = || vec![0.0f32; TILE];
        Tile {
            dirs: [v(), v(), v()],
            seg_t0: v(),
            seg_t1: v(),
            rays: vec![Ray::default(); TILE],
            slots: vec![0; TILE],
            t: v(),
            points: [v(), v(), v()],
            dist: v(),
            n_hits: 0,
            hit_pixel: vec![0; TILE],
            hit_t: v(),
            hit_points: [v(), v(), v()],
            color: [v(), v(), v()],
            grad: [v(), v(), v(), v()],
            origin: [v(), v(), v()],
            t_end: v(),
            hit_flag: v(),
            group: vec![0; TILE],
            empty_space: empty_space::Scratch::default(),
        }
    }

    /// Traces the pixels `start..start + out.len()` of the frame and writes them to `out`.
    fn render(&mut self, job: &Job, start: usize, out: TileOut) {
        let n = self.start_rays(job, start, out.rgb.len());
        self.march(job, n);
        self.shade(job, out);
    }

    /// Sets up the rays of `len` pixels from `start` that are not culled; returns their number.
    fn start_rays(&mut self, job: &Job, start: usize, len: usize) -> usize {
        let o = job.camera.position();
        let mut n = 0;
        let mut pixel = start;
        while pixel < start + len {
            // One row segment at a time: directions first (a loop that vectorizes), ...
            let (row, col) = (pixel / job.width, pixel % job.width);
            let seg = (job.width - col).min(start + len - pixel);
            let y = job.ys[row];
            let [dx, dy, dz] = &mut self.dirs;
            // d = normalize(x·X + y·Y + Z) for the view axes X, Y, Z, one component array at a time
            // (a loop the compiler vectorizes).
            let r = job.camera.rotation();
            // Summed in the order of `Camera::direction`, so the rays are bit-identical to `Camera::ray`.
            let (ya, z) = (r.y_axis * y, r.z_axis);
            let columns = &job.xs[col..col + seg];
            for (((x, dx), dy), dz) in columns
                .iter()
                .zip(&mut dx[..seg])
                .zip(&mut dy[..seg])
                .zip(&mut dz[..seg])
            {
                let vx = r.x_axis.x * x + ya.x + z.x;
                let vy = r.x_axis.y * x + ya.y + z.y;
                let vz = r.x_axis.z * x + ya.z + z.z;
                let inv = 1.0 / (vx * vx + vy * vy + vz * vz).sqrt();
                (*dx, *dy, *dz) = (vx * inv, vy * inv, vz * inv);
            }
            // ... then their intervals (another loop that vectorizes), then the rays that survive culling.
            let (t0, t1) = (&mut self.seg_t0[..seg], &mut self.seg_t1[..seg]);
            job.settings
                .intervals(o, [&dx[..seg], &dy[..seg], &dz[..seg]], t0, t1);
            for k in 0..seg {
                if t0[k] <= t1[k] {
                    self.rays[n] = Ray {
                        dx: dx[k],
                        dy: dy[k],
                        dz: dz[k],
                        t_end: t1[k],
                        pixel: (pixel - start + k) as u32,
                    };
                    self.slots[n] = n as u16;
                    self.t[n] = t0[k];
                    n += 1;
                }
            }
            pixel += seg;
        }
        if let Some(bounds) = job.sdf.interval_bounds() {
            n = self.skip_empty_space(job, bounds, start, n);
        }
        n
    }

    /// Copies the directions and ends of the first `n` rays into the columns `dirs` and `t_end`.
    fn load_ray_columns(&mut self, n: usize) {
        for (k, ray) in self.rays[..n].iter().enumerate() {
            (self.dirs[0][k], self.dirs[1][k], self.dirs[2][k]) = (ray.dx, ray.dy, ray.dz);
            self.t_end[k] = ray.t_end;
        }
    }

    /// Moves the starts of the first `n` rays past the space `bounds` proves empty ([`empty_space`]) and
    /// drops the rays that miss; returns the number of rays left.
    fn skip_empty_space(&mut self, job: &Job, bounds: &dyn BatchFn, start: usize, n: usize) -> usize {
        self.load_ray_columns(n);
        for (group, ray) in self.group.iter_mut().zip(&self.rays[..n]) {
            let column = (start + ray.pixel as usize) % job.width;
            *group = (column / GROUP_COLUMNS) as u32;
        }
        let rays = GroupedRays {
            origin: job.camera.position(),
            direction: [&self.dirs[0][..n], &self.dirs[1][..n], &self.dirs[2][..n]],
            t_end: &self.t_end[..n],
            group: &self.group[..n],
            groups: job.width.div_ceil(GROUP_COLUMNS),
        };
        empty_space::advance(
            bounds,
            &rays,
            job.settings.eps,
            &mut self.t[..n],
            &mut self.empty_space,
        );
        let mut live = 0;
        for k in 0..n {
            let (ray, t) = (self.rays[k], self.t[k]);
            if t > ray.t_end {
                continue;
            }
            self.rays[live] = ray;
            self.slots[live] = live as u16;
            self.t[live] = t;
            live += 1;
        }
        live
    }

    /// Sphere traces the first `n` rays in one call of a fused marcher, recording hits.
    fn march_fused(&mut self, job: &Job, marcher: &dyn RayMarcher, n: usize) {
        let o = job.camera.position();
        for (column, value) in self.origin.iter_mut().zip(o.to_array()) {
            column[..n].fill(value);
        }
        self.load_ray_columns(n);
        let rays = MarchRays {
            origin: [&self.origin[0][..n], &self.origin[1][..n], &self.origin[2][..n]],
            direction: [&self.dirs[0][..n], &self.dirs[1][..n], &self.dirs[2][..n]],
            t0: &self.t[..n],
            t1: &self.t_end[..n],
        };
        let settings = job.settings;
        // The marcher reads t0 from `t` and writes the final t to `dist`.
        marcher.march(
            n,
            &rays,
            settings.eps,
            settings.max_steps,
            &mut self.dist[..n],
            &mut self.hit_flag[..n],
        );
        let mut n_hits = 0;
        for k in 0..n {
            if self.hit_flag[k] == 1.0 {
                let ray = self.rays[k];
                let t = self.dist[k];
                self.hit_pixel[n_hits] = ray.pixel;
                self.hit_t[n_hits] = t;
                // The marcher computes p = o + t·d with a fused multiply-add; so does this.
                self.hit_points[0][n_hits] = t.mul_add(ray.dx, o.x);
                self.hit_points[1][n_hits] = t.mul_add(ray.dy, o.y);
                self.hit_points[2][n_hits] = t.mul_add(ray.dz, o.z);
                n_hits += 1;
            }
        }
        self.n_hits = n_hits;
    }

    /// Sphere traces the first `n` rays, recording hits; rays still live at the end miss.
    fn march(&mut self, job: &Job, mut n: usize) {
        if let Some(marcher) = job.sdf.as_marcher() {
            return self.march_fused(job, marcher, n);
        }
        let settings = job.settings;
        let o = job.camera.position();
        for (k, ray) in self.rays[..n].iter().enumerate() {
            let p = o + Vec3::new(ray.dx, ray.dy, ray.dz) * self.t[k];
            (self.points[0][k], self.points[1][k], self.points[2][k]) = (p.x, p.y, p.z);
        }
        let Tile {
            rays,
            slots,
            t: ts,
            points: [px, py, pz],
            dist,
            hit_pixel,
            hit_t,
            hit_points: [hx, hy, hz],
            ..
        } = self;
        let mut n_hits = 0;
        for _ in 0..settings.max_steps {
            if n == 0 {
                break;
            }
            let (px, py, pz) = (&mut px[..n], &mut py[..n], &mut pz[..n]);
            let dist = &mut dist[..n];
            job.sdf.eval(n, &[px, py, pz], &mut [&mut *dist]);
            // Compaction: every ray is written back at `live`, which advances only for rays
            // that go on marching.
            let mut live = 0;
            for k in 0..n {
                let (slot, dist, t) = (slots[k], dist[k], ts[k]);
                let ray = rays[usize::from(slot)];
                let hit = dist < settings.eps;
                if hit {
                    hit_pixel[n_hits] = ray.pixel;
                    hit_t[n_hits] = t;
                    (hx[n_hits], hy[n_hits], hz[n_hits]) = (px[k], py[k], pz[k]);
                    n_hits += 1;
                }
                let t = t + dist;
                // A NaN distance keeps the ray marching, as in the plain loop.
                let stop = hit || t > ray.t_end;
                slots[live] = slot;
                ts[live] = t;
                px[live] = o.x + ray.dx * t;
                py[live] = o.y + ray.dy * t;
                pz[live] = o.z + ray.dz * t;
                live += usize::from(!stop);
            }
            n = live;
        }
        self.n_hits = n_hits;
    }

    /// Fills `out`: background for every pixel, then the shading of the hits.
    fn shade(&mut self, job: &Job, out: TileOut) {
        fill_rgb(out.rgb, job.settings.background);
        out.depth.fill(f32::INFINITY);
        out.normal.as_flattened_mut().fill(0.0);
        out.hit.fill(false);
        let n = self.n_hits;
        let [hx, hy, hz] = &self.hit_points;
        let points: [&[f32]; 3] = [&hx[..n], &hy[..n], &hz[..n]];
        let [r, g, b] = &mut self.color;
        let [gd, gx, gy, gz] = &mut self.grad;
        let mut grad_out = [&mut gd[..n], &mut gx[..n], &mut gy[..n], &mut gz[..n]];
        let (light, albedo) = match *job.shading {
            Shading::Color { color, gradient } => {
                color.eval(n, &points, &mut [&mut r[..n], &mut g[..n], &mut b[..n]]);
                if let Some(gradient) = gradient {
                    gradient.eval(n, &points, &mut grad_out);
                }
                (None, [0.0; 3])
            }
            Shading::Lambert {
                gradient,
                light_dir,
                albedo,
            } => {
                gradient.eval(n, &points, &mut grad_out);
                (Some(light_dir.normalize()), albedo)
            }
        };
        let has_normals = !matches!(job.shading, Shading::Color { gradient: None, .. });
        for k in 0..n {
            let p = self.hit_pixel[k] as usize;
            out.hit[p] = true;
            out.depth[p] = self.hit_t[k];
            let normal = if has_normals {
                Vec3::new(gx[k], gy[k], gz[k]).normalize_or_zero()
            } else {
                Vec3::ZERO
            };
            out.normal[p] = normal.to_array();
            out.rgb[p] = match light {
                Some(l) => {
                    let lit = normal.dot(l).max(0.0);
                    albedo.map(|a| a * lit)
                }
                None => [r[k], g[k], b[k]],
            };
        }
    }
}

/// Sets every pixel of `rgb` to `color`: 16-byte stores of the three patterns four pixels make.
fn fill_rgb(rgb: &mut [[f32; 3]], color: [f32; 3]) {
    let four: [f32; 12] = std::array::from_fn(|i| color[i % 3]);
    let vectors: [[f32; 4]; 3] = std::array::from_fn(|v| std::array::from_fn(|i| four[4 * v + i]));
    let (dozens, rest) = rgb.as_flattened_mut().as_chunks_mut::<12>();
    for dozen in dozens.iter_mut() {
        let (quads, _) = dozen.as_chunks_mut::<4>();
        for (q, v) in quads.iter_mut().zip(&vectors) {
            *q = *v;
        }
    }
    let done = 12 * dozens.len();
    for (i, v) in rest.iter_mut().enumerate() {
        *v = color[(done + i) % 3];
    }
}

thread_local! {
    /// The tile buffers of this thread, reused across tiles and frames.
    static BUFFERS: RefCell<Option<Tile>> = const { RefCell::new(None) };
}

/// Runs `f` with this thread's tile buffers (fresh ones if they are in use, which happens
/// only if an SDF runs parallel work that makes this thread trace another tile).
fn with_tile(f: impl FnOnce(&mut Tile)) {
    BUFFERS.with(|cell| match cell.try_borrow_mut() {
        Ok(mut buffers) => f(buffers.get_or_insert_with(Tile::new)),
        Err(_) => f(&mut Tile::new()),
    })
}

/// Sphere traces a `width`×`height` image of the surface `sdf < 0` (3 inputs → 1 output)
/// seen by `camera`, shaded by `shading`. See the module docs for the exact semantics.
pub fn sphere_trace(
    camera: &Camera,
    width: u32,
    height: u32,
    sdf: &dyn BatchFn,
    shading: &Shading,
    settings: &TraceSettings,
) -> Result<Frame> {
    let mut frame = Frame::empty();
    sphere_trace_into(camera, width, height, sdf, shading, settings, &mut frame)?;
    Ok(frame)
}

/// [`sphere_trace`] into an existing frame, reusing its memory (every pixel is overwritten).
pub fn sphere_trace_into(
    camera: &Camera,
    width: u32,
    height: u32,
    sdf: &dyn BatchFn,
    shading: &Shading,
    settings: &TraceSettings,
    frame: &mut Frame,
) -> Result<()> {
    check_size(width, height)?;
    check_arity(sdf, "the SDF", 3, 1)?;
    if let Some(bounds) = sdf.interval_bounds() {
        check_arity(bounds, "the SDF's interval bounds", 6, 2)?;
    }
    shading.check()?;
    settings.check()?;
    let job = Job {
        camera,
        width: width as usize,
        xs: (0..width)
            .map(|col| camera.view_x(col as f32 + 0.5, width, height))
            .collect(),
        ys: (0..height)
            .map(|row| camera.view_y(row as f32 + 0.5, width, height))
            .collect(),
        sdf,
        shading,
        settings,
    };
    let n = width as usize * height as usize;
    (frame.width, frame.height) = (width, height);
    frame.rgb.resize(n, [0.0; 3]);
    frame.depth.resize(n, 0.0);
    frame.normal.resize(n, [0.0; 3]);
    frame.hit.resize(n, false);
    frame
        .rgb
        .par_chunks_mut(TILE)
        .zip(frame.depth.par_chunks_mut(TILE))
        .zip(frame.normal.par_chunks_mut(TILE))
        .zip(frame.hit.par_chunks_mut(TILE))
        .enumerate()
        .for_each(|(k, (((rgb, depth), normal), hit))| {
            let out = TileOut {
                rgb,
                depth,
                normal,
                hit,
            };
            with_tile(|tile| tile.render(&job, k * TILE, out));
        });
    Ok(())
}

/// Sphere traces one frame per camera (see [`sphere_trace`]); `progress`, when given, is
/// called with the number of frames finished so far after each frame.
///
/// The frames are traced one after the other from a thread of rayon's pool ([`on_pool`]).
pub fn render_frames(
    cameras: &[Camera],
    width: u32,
    height: u32,
    sdf: &dyn BatchFn,
    shading: &Shading,
    settings: &TraceSettings,
    progress: Option<&(dyn Fn(usize) + Sync)>,
) -> Result<Vec<Frame>> {
    on_pool(|| {
        let mut frames = Vec::with_capacity(cameras.len());
        for camera in cameras {
            frames.push(sphere_trace(camera, width, height, sdf, shading, settings)?);
            if let Some(progress) = progress {
                progress(frames.len());
            }
        }
        Ok(frames)
    })
}

/// Runs `work` on a thread of rayon's global pool, the caller waiting. Parallel calls made one after the
/// other from there, such as the tiles of frame after frame, find the pool's other threads still awake
/// from the call before; each call made from outside the pool hands its work over and waits to be woken,
/// which can cost a good part of a frame that takes 0.15 ms (see the W1 figures in docs/BENCHMARKS.md).
pub fn on_pool<R: Send>(work: impl FnOnce() -> R + Send) -> R {
    rayon::scope(|_| work())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::{ClosureFn, WithBounds};
    use glam::Vec2;
    use std::sync::atomic::{AtomicUsize, Ordering};

    fn sphere_sdf(p: &[f32], out: &mut [f32]) {
        out[0] = Vec3::new(p[0], p[1], p[2]).length() - 1.0;
    }

    fn sphere_gradient(p: &[f32], out: &mut [f32]) {
        let p = Vec3::new(p[0], p[1], p[2]);
        out[0] = p.length() - 1.0;
        let n = p.normalize_or_zero();
        out[1..4].copy_from_slice(&n.to_array());
    }

    fn torus_sdf(p: &[f32], out: &mut [f32]) {
        let q = Vec2::new(Vec2::new(p[0], p[2]).length() - 1.0, p[1]);
        out[0] = q.length() - 0.35;
    }

    fn rainbow(p: &[f32], out: &mut [f32]) {
        for (o, x) in out.iter_mut().zip(p) {
            *o = x.abs().clamp(0.02, 0.98);
        }
    }

    fn camera() -> Camera {
        Camera::look_at(
            Vec3::new(0.3, 0.8, -3.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::splat(1.5),
            Vec2::ZERO,
        )
        .unwrap()
    }

    /// The plain per-ray loop of the reference, for comparison.
    fn naive(
        camera: &Camera,
        width: u32,
        height: u32,
        sdf: &dyn BatchFn,
        color: &dyn BatchFn,
        settings: &TraceSettings,
    ) -> Frame {
        let eval = |f: &dyn BatchFn, p: Vec3, m: usize| {
            let mut out = vec![0.0f32; m];
            let mut cols: Vec<&mut [f32]> = out.chunks_mut(1).collect();
            f.eval(1, &[&[p.x], &[p.y], &[p.z]], &mut cols);
            out
        };
        let n = (width * height) as usize;
        let mut frame = Frame {
            width,
            height,
            rgb: vec![settings.background; n],
            depth: vec![f32::INFINITY; n],
            normal: vec![[0.0; 3]; n],
            hit: vec![false; n],
        };
        for row in 0..height {
            for col in 0..width {
                let (o, d) = camera.ray(row, col, width, height);
                let Some((mut t, far)) = settings.interval(o, d) else {
                    continue;
                };
                for _ in 0..settings.max_steps {
                    let p = o + d * t;
                    let dist = eval(sdf, p, 1)[0];
                    if dist < settings.eps {
                        let i = (row * width + col) as usize;
                        frame.hit[i] = true;
                        frame.depth[i] = t;
                        let c = eval(color, p, 3);
                        frame.rgb[i] = [c[0], c[1], c[2]];
                        break;
                    }
                    t += dist;
                    if t > far {
                        break;
                    }
                }
            }
        }
        frame
    }

    #[test]
    fn tiled_tracer_equals_naive_loop_exactly() {
        let evaluations = AtomicUsize::new(0);
        let sdf = ClosureFn::new(3, 1, |p, out| {
            evaluations.fetch_add(1, Ordering::Relaxed);
            torus_sdf(p, out);
        });
        let color = ClosureFn::new(3, 3, rainbow);
        let shading = Shading::Color {
            color: &color,
            gradient: None,
        };
        let cam = camera();
        let plain = TraceSettings {
            background: [0.1, 0.2, 0.3],
            eps: 1e-4,
            ..TraceSettings::default()
        };
        let bounded = TraceSettings {
            bounds: Some((Vec3::ZERO, 1.4)),
            ..plain
        };
        // The camera is 3.13 from the center: `far` 3 cuts off the back of the torus.
        let short = TraceSettings { far: 3.0, ..plain };
        let mut hits = vec![];
        let mut work = vec![];
        for settings in [plain, bounded, short] {
            // 70×45 is not a multiple of the tile size: the last tile is partial.
            let fast = sphere_trace(&cam, 70, 45, &sdf, &shading, &settings).unwrap();
            let fast_evaluations = evaluations.swap(0, Ordering::Relaxed);
            let slow = naive(&cam, 70, 45, &sdf, &color, &settings);
            // Same pixels, and the SDF saw exactly the points of the plain loop: no dead rays.
            assert_eq!(fast, slow);
            assert_eq!(fast_evaluations, evaluations.swap(0, Ordering::Relaxed));
            hits.push(fast.hit.iter().filter(|&&h| h).count());
            work.push(fast_evaluations);
        }
        assert!(hits[0] > 300 && hits[0] < 70 * 45 - 300, "{hits:?} hits");
        assert_eq!(hits[0], hits[1]);
        assert!(hits[2] + 50 < hits[0], "far cuts hits: {hits:?}");
        assert!(2 * work[1] < work[0], "bounds cull work: {work:?}");
    }

    #[test]
    fn background_fills_every_pixel_of_any_count() {
        for n in 0..13 {
            let mut rgb = vec![[9.0; 3]; n];
            fill_rgb(&mut rgb, [0.25, 0.5, 0.75]);
            assert!(
                rgb.iter().all(|&px| px == [0.25, 0.5, 0.75]),
                "{n} pixels: {rgb:?}"
            );
        }
    }

    #[test]
    fn bounds_clip_rays_to_the_sphere() {
        let s = TraceSettings {
            near: 0.5,
            far: 10.0,
            eps: 0.01,
            bounds: Some((Vec3::new(0.0, 0.0, 5.0), 1.0)),
            ..TraceSettings::default()
        };
        let (t0, t1) = s.interval(Vec3::ZERO, Vec3::Z).unwrap();
        assert!((t0 - 3.99).abs() < 1e-5 && (t1 - 6.01).abs() < 1e-5, "{t0} {t1}");
        assert_eq!(s.interval(Vec3::ZERO, Vec3::X), None);
        assert_eq!(s.interval(Vec3::ZERO, -Vec3::Z), None);
        let inside = s.interval(Vec3::new(0.0, 0.0, 5.0), Vec3::Z).unwrap();
        assert_eq!(inside.0, 0.5);
        let short = TraceSettings { far: 3.0, ..s };
        assert_eq!(short.interval(Vec3::ZERO, Vec3::Z), None);
    }

    #[test]
    fn bounds_agree_with_unbounded_tracing() {
        let sdf = ClosureFn::new(3, 1, torus_sdf);
        let color = ClosureFn::new(3, 3, rainbow);
        let shading = Shading::Color {
            color: &color,
            gradient: None,
        };
        let plain = TraceSettings {
            max_steps: 200,
            eps: 1e-5,
            ..TraceSettings::default()
        };
        let bounded = TraceSettings {
            bounds: Some((Vec3::ZERO, 1.4)),
            ..plain
        };
        let a = sphere_trace(&camera(), 64, 64, &sdf, &shading, &plain).unwrap();
        let b = sphere_trace(&camera(), 64, 64, &sdf, &shading, &bounded).unwrap();
        let differing = a.hit.iter().zip(&b.hit).filter(|(x, y)| x != y).count();
        assert!(differing <= 2, "{differing} pixels differ");
        for i in 0..a.hit.len() {
            if a.hit[i] && b.hit[i] {
                assert!((a.depth[i] - b.depth[i]).abs() < 1e-3);
            }
        }
    }

    /// Bounds of [`torus_sdf`] over a box (6 inputs → 2 outputs).
    fn torus_bounds(b: &[f32], out: &mut [f32]) {
        let (low, high) = (Vec3::new(b[0], b[1], b[2]), Vec3::new(b[3], b[4], b[5]));
        let abs_range = |lo: f32, hi: f32| {
            let nearest = if lo <= 0.0 && hi >= 0.0 {
                0.0
            } else {
                lo.abs().min(hi.abs())
            };
            (nearest, lo.abs().max(hi.abs()))
        };
        let (x, z) = (abs_range(low.x, high.x), abs_range(low.z, high.z));
        let (ring_lo, ring_hi) = (x.0.hypot(z.0) - 1.0, x.1.hypot(z.1) - 1.0);
        let (q, y) = (abs_range(ring_lo, ring_hi), abs_range(low.y, high.y));
        out[0] = q.0.hypot(y.0) - 0.35;
        out[1] = q.1.hypot(y.1) - 0.35;
    }

    #[test]
    fn skipping_the_space_interval_bounds_prove_empty_finds_the_same_hits_with_fewer_evaluations() {
        let evaluations = AtomicUsize::new(0);
        let sdf = ClosureFn::new(3, 1, |p: &[f32], out: &mut [f32]| {
            evaluations.fetch_add(1, Ordering::Relaxed);
            torus_sdf(p, out);
        });
        let bounds = ClosureFn::new(6, 2, torus_bounds);
        let bounded = WithBounds {
            function: &sdf,
            bounds: Some(&bounds),
        };
        let color = ClosureFn::new(3, 3, rainbow);
        let shading = Shading::Color {
            color: &color,
            gradient: None,
        };
        let settings = TraceSettings {
            max_steps: 200,
            eps: 1e-5,
            ..TraceSettings::default()
        };
        let plain = sphere_trace(&camera(), 96, 80, &sdf, &shading, &settings).unwrap();
        let plain_evaluations = evaluations.swap(0, Ordering::Relaxed);
        let skipped = sphere_trace(&camera(), 96, 80, &bounded, &shading, &settings).unwrap();
        let skipped_evaluations = evaluations.load(Ordering::Relaxed);
        let differing = plain.hit.iter().zip(&skipped.hit).filter(|(a, b)| a != b).count();
        assert!(differing <= 2, "{differing} pixels differ");
        let hits = plain.hit.iter().filter(|&&h| h).count();
        assert!(hits > 1000, "{hits} hits");
        for i in 0..plain.hit.len() {
            if plain.hit[i] && skipped.hit[i] {
                assert!((plain.depth[i] - skipped.depth[i]).abs() < 1e-3, "pixel {i}");
                for c in 0..3 {
                    assert!((plain.rgb[i][c] - skipped.rgb[i][c]).abs() < 1e-3, "pixel {i}");
                }
            }
        }
        assert!(
            3 * skipped_evaluations < 2 * plain_evaluations,
            "{skipped_evaluations} evaluations with bounds, {plain_evaluations} without"
        );
    }

    #[test]
    fn sphere_silhouette_depth_and_normals_are_analytic() {
        let sdf = ClosureFn::new(3, 1, sphere_sdf);
        let gradient = ClosureFn::new(3, 4, sphere_gradient);
        let light = Vec3::new(-1.0, 1.0, -1.0);
        let shading = Shading::Lambert {
            gradient: &gradient,
            light_dir: light,
            albedo: [1.0, 0.5, 0.25],
        };
        let settings = TraceSettings {
            max_steps: 200,
            eps: 1e-5,
            background: [0.0, 0.0, 1.0],
            ..TraceSettings::default()
        };
        let cam = camera();
        let (w, h) = (64, 64);
        let frame = sphere_trace(&cam, w, h, &sdf, &shading, &settings).unwrap();
        let mut checked = 0;
        for row in 0..h {
            for col in 0..w {
                let i = (row * w + col) as usize;
                let (o, d) = cam.ray(row, col, w, h);
                let b = o.dot(d);
                let closest = (o - d * b).length();
                if (closest - 1.0).abs() < 0.01 {
                    continue; // grazing
                }
                checked += 1;
                assert_eq!(frame.hit[i], closest < 1.0, "pixel {row},{col}");
                if !frame.hit[i] {
                    assert_eq!(frame.rgb[i], [0.0, 0.0, 1.0]);
                    assert_eq!(frame.depth[i], f32::INFINITY);
                    continue;
                }
                let t = -b - (b * b - (o.length_squared() - 1.0)).sqrt();
                assert!(
                    (frame.depth[i] - t).abs() < 1e-3,
                    "depth {} vs {t}",
                    frame.depth[i]
                );
                let n = (o + d * t).normalize();
                assert!(Vec3::from(frame.normal[i]).abs_diff_eq(n, 1e-3));
                let lit = n.dot(light.normalize()).max(0.0);
                assert!((frame.rgb[i][1] - 0.5 * lit).abs() < 1e-3);
            }
        }
        assert!(checked > 3900, "{checked}");
        let center = (32 * w + 32) as usize;
        let t_axis = cam.position().length() - 1.0;
        assert!((frame.depth[center] - t_axis).abs() < 0.01);
    }

    #[test]
    fn render_frames_reports_progress() {
        let sdf = ClosureFn::new(3, 1, sphere_sdf);
        let color = ClosureFn::new(3, 3, rainbow);
        let shading = Shading::Color {
            color: &color,
            gradient: Some(&ClosureFn::new(3, 4, sphere_gradient)),
        };
        let cams = crate::cameras::paths::surround(3.0, 3, crate::cameras::paths::Up::Y, 1.0).unwrap();
        let seen = std::sync::Mutex::new(0);
        let progress = |k: usize| {
            let mut seen = seen.lock().unwrap();
            *seen = *seen * 10 + k;
        };
        let frames = render_frames(
            &cams,
            16,
            16,
            &sdf,
            &shading,
            &TraceSettings::default(),
            Some(&progress),
        )
        .unwrap();
        assert_eq!(frames.len(), 3);
        assert_eq!(*seen.lock().unwrap(), 123);
        let center = 8 * 16 + 8;
        assert!(frames[0].hit[center]);
        assert!(Vec3::from(frames[0].normal[center]).length() > 0.99);
    }

    #[test]
    fn bad_inputs_are_errors() {
        let sdf = ClosureFn::new(3, 1, sphere_sdf);
        let color = ClosureFn::new(3, 3, rainbow);
        let shading = Shading::Color {
            color: &color,
            gradient: None,
        };
        let s = TraceSettings::default();
        let cam = camera();
        assert!(sphere_trace(&cam, 0, 8, &sdf, &shading, &s).is_err());
        let e = sphere_trace(&cam, 8, 8, &color, &shading, &s).unwrap_err();
        assert!(
            e.to_string().contains("the SDF must map 3 inputs to 1 outputs"),
            "{e}"
        );
        let wrong = Shading::Color {
            color: &sdf,
            gradient: None,
        };
        assert!(sphere_trace(&cam, 8, 8, &sdf, &wrong, &s).is_err());
        let bounded = WithBounds {
            function: &sdf,
            bounds: Some(&sdf),
        };
        let e = sphere_trace(&cam, 8, 8, &bounded, &shading, &s).unwrap_err();
        assert!(
            e.to_string().contains("the SDF's interval bounds must map 6"),
            "{e}"
        );
        for bad in [
            TraceSettings { far: -1.0, ..s },
            TraceSettings { eps: 0.0, ..s },
            TraceSettings {
                bounds: Some((Vec3::ZERO, -1.0)),
                ..s
            },
        ] {
            assert!(sphere_trace(&cam, 8, 8, &sdf, &shading, &bad).is_err());
        }
    }
}
