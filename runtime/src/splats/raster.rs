//! The CPU splat renderer: each splat is projected to a 2D Gaussian on the screen (the ellipsoid's
//! covariance through the projection's Jacobian, widened by a 0.3-pixel low-pass as 3D Gaussian splatting
//! does), the splats are sorted by distance (a radix sort) and binned in that order into the 16×16 tiles
//! they touch, and the tiles are drawn in parallel, each pixel compositing its splats front to back (alpha =
//! opacity · the Gaussian, at most 0.99, below 1/255 skipped) until its transmittance falls under 1e-4.
//! A tile's pixels are composited eight at a time (a row's half, in the vector unit's lanes), each splat
//! over the rows and halves its square covers.
//!
//! The frame is a [`VolumeFrame`], as a field's volume render gives it: composited color over the
//! background, opacity, and the expected distance from the camera Σ wᵢ dᵢ (not normalized).

use std::sync::Mutex;
use std::time::{Duration, Instant};

use glam::{Mat3, Quat, Vec3};
use rayon::prelude::*;

use super::shading::{Seen, ShaderBatch, SplatShader};
use super::Splats;
use crate::cameras::camera::Camera;
use crate::error::{check_size, Result};
use crate::volume::render::VolumeFrame;

/// The side of a tile, in pixels.
pub(super) const TILE: usize = 16;

/// The pixels composited at once: half a tile's row.
const LANES: usize = 8;

/// Splats nearer than this to the camera's plane are not drawn.
const NEAR: f32 = 0.01;

/// The variance (in pixels²) added to every projected splat, so that none is thinner than a pixel.
pub(super) const LOW_PASS: f32 = 0.3;

/// How far beyond the frame's edges (a share of its width and height on each side) the projection's
/// Jacobian follows a splat's center (see [`Viewer::slopes`]).
const BEYOND: f32 = 0.15;

/// Alphas below this are skipped.
const MIN_ALPHA: f32 = 1.0 / 255.0;

/// No splat covers a pixel entirely.
pub(super) const MAX_ALPHA: f32 = 0.99;

/// A pixel whose transmittance falls below this takes no more splats.
const SATURATED: f32 = 1e-4;

/// The sort key of a splat out of sight (no positive distance's bits are these: they are a NaN's).
const OUT_OF_SIGHT: u32 = u32::MAX;

/// How many of its splats a tile composites between looks at which of its half rows are saturated (those
/// take no more splats; a tile whose rows all are, stops), and copies out at once.
const SATURATION_CHECKS: usize = 32;

/// What drawing a frame involved.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SplatFrameStats {
    /// Splats in front of the camera and on the screen.
    pub visible: usize,
    /// Splat-tile pairs drawn.
    pub entries: usize,
    /// The time each phase of the frame took: projecting every splat, sorting the visible ones by
    /// distance (and gathering them in that order), binning them into tiles, compositing the tiles.
    pub phases: [Duration; 4],
}

/// The names of [`SplatFrameStats::phases`].
pub const SPLAT_PHASES: [&str; 4] = ["project", "sort", "bin", "composite"];

/// A splat as the screen sees it.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Projected {
    /// Which splat it is.
    pub index: u32,
    /// The center's continuous pixel coordinates (pixel centers at +0.5).
    pub col: f32,
    pub row: f32,
    /// The inverse of the 2D covariance: (a, b, c) of [[a, b], [b, c]].
    pub conic: [f32; 3],
    /// The half-width (along the columns) and half-height (along the rows) of the box on the screen, in
    /// pixels, that holds its ellipse: every pixel where its alpha reaches [`MIN_ALPHA`] (so that the frame
    /// changes smoothly with the splat, but at that edge).
    pub extent: [f32; 2],
    /// Its distance from the camera.
    pub distance: f32,
    pub opacity: f32,
    /// The Gaussian's exponent below which its alpha is under [`MIN_ALPHA`]: ln(MIN_ALPHA / opacity).
    pub cutoff: f32,
    /// The color it shows this camera.
    pub color: [f32; 3],
}

/// Draws `splats` (colored by `shader`) as `camera` sees them in a `width`×`height` frame over `background`
/// (a [`SplatScene`] made for this one frame; to draw many, make one and keep it).
pub fn render_splats(
    splats: &Splats,
    shader: &dyn SplatShader,
    camera: &Camera,
    width: u32,
    height: u32,
    background: [f32; 3],
) -> Result<(VolumeFrame, SplatFrameStats)> {
    SplatScene::new(splats, shader).render(camera, width, height, background)
}

/// Splats made ready to draw: each splat's 3D covariance and the exponent at which its alpha falls under
/// the smallest drawn are worked out once, so that a frame only projects, sorts and composites.
pub struct SplatScene<'a> {
    splats: &'a Splats,
    /// The color each splat shows a camera (where the splats have spherical harmonics).
    shader: &'a dyn SplatShader,
    /// Each splat's covariance in the world, (xx, xy, xz, yy, yz, zz): R S² Rᵀ.
    covariances: Vec<[f32; 6]>,
    /// Each splat's `Projected::cutoff`.
    cutoffs: Vec<f32>,
    /// The last frame's buffers, kept for the next: the memory of a fresh one costs page faults.
    buffers: Mutex<Buffers>,
}

/// The memory a frame's projection and binning use.
#[derive(Default)]
pub(super) struct Buffers {
    /// Every splat's projection, in the order of the splats.
    all: Vec<Projected>,
    /// Every splat's sort key: its distance's bits (or [`OUT_OF_SIGHT`]) and its index.
    keys: Vec<(u32, u32)>,
    /// The splats on the screen, nearest first.
    pub projected: Vec<Projected>,
    /// Tile `t`'s splats are `entries[starts[t]..starts[t + 1]]`, nearest first: their places in
    /// `projected`.
    pub starts: Vec<usize>,
    pub entries: Vec<u32>,
}

impl<'a> SplatScene<'a> {
    /// `splats` made ready to draw, their colors given by `shader` where they have spherical harmonics.
    pub fn new(splats: &'a Splats, shader: &'a dyn SplatShader) -> SplatScene<'a> {
        let covariances = (0..splats.len())
            .into_par_iter()
            .map(|i| {
                let [sx, sy, sz] = splats.scales[i];
                let m = if sx == sy && sy == sz {
                    Mat3::from_diagonal(Vec3::splat(sx))
                } else {
                    let [w, x, y, z] = splats.rotations[i];
                    let axes = Mat3::from_quat(Quat::from_xyzw(x, y, z, w).normalize());
                    axes * Mat3::from_diagonal(Vec3::new(sx, sy, sz))
                };
                let (r0, r1, r2) = (m.row(0), m.row(1), m.row(2));
                [
                    r0.dot(r0),
                    r0.dot(r1),
                    r0.dot(r2),
                    r1.dot(r1),
                    r1.dot(r2),
                    r2.dot(r2),
                ]
            })
            .collect();
        let cutoffs = splats
            .opacities
            .par_iter()
            .map(|&o| (MIN_ALPHA / o).ln())
            .collect();
        SplatScene {
            splats,
            shader,
            covariances,
            cutoffs,
            buffers: Mutex::default(),
        }
    }

    /// The frame `camera` sees, `width`×`height`, over `background`.
    pub fn render(
        &self,
        camera: &Camera,
        width: u32,
        height: u32,
        background: [f32; 3],
    ) -> Result<(VolumeFrame, SplatFrameStats)> {
        // Another thread drawing this scene at the same time takes buffers of its own.
        let mut kept = self.buffers.try_lock();
        let buffers = kept.as_deref_mut().map(std::mem::take).unwrap_or_default();
        let screen = self.screen(camera, width, height, buffers)?;
        let start = Instant::now();
        let frame = screen.picture(background);
        let [project, sort, bin] = screen.phases;
        let stats = SplatFrameStats {
            visible: screen.buffers.projected.len(),
            entries: screen.buffers.entries.len(),
            phases: [project, sort, bin, start.elapsed()],
        };
        if let Ok(kept) = kept.as_deref_mut() {
            *kept = screen.buffers;
        }
        Ok((frame, stats))
    }

    /// The splats `viewer` sees, nearest first: each projected into its place (a splat out of sight with
    /// the largest key), the keys (the distance's bits, positive distances sorting as their bits do) sorted
    /// by a radix sort, and the projections gathered in that order. Returns the time projecting took and
    /// the time sorting and gathering took.
    fn project(&self, viewer: &Viewer, buffers: &mut Buffers) -> [Duration; 2] {
        let start = Instant::now();
        const CHUNK: usize = 4096;
        let n = self.splats.len();
        let Buffers {
            all, keys, projected, ..
        } = buffers;
        all.resize(n, Projected::default());
        keys.resize(n, (OUT_OF_SIGHT, 0));
        all.par_chunks_mut(CHUNK)
            .zip(keys.par_chunks_mut(CHUNK))
            .enumerate()
            .for_each(|(chunk, (all, keys))| {
                ShaderBatch::with(|batch| self.project_chunk(viewer, chunk * CHUNK, all, keys, batch));
            });
        let projecting = start.elapsed();
        let start = Instant::now();
        radsort::sort_by_key(keys, |&(key, _)| key);
        let visible = keys.partition_point(|&(key, _)| key != OUT_OF_SIGHT);
        projected.resize(visible, Projected::default());
        projected
            .par_chunks_mut(CHUNK)
            .zip(keys[..visible].par_chunks(CHUNK))
            .for_each(|(projected, keys)| {
                for (p, &(_, i)) in projected.iter_mut().zip(keys) {
                    *p = all[i as usize];
                }
            });
        [projecting, start.elapsed()]
    }

    /// Projects splats `first..first + all.len()` into `all` with their sort keys (see [`SplatScene::project`]),
    /// the visible ones' colors shaded by the scene's shader in one batch.
    fn project_chunk(
        &self,
        viewer: &Viewer,
        first: usize,
        all: &mut [Projected],
        keys: &mut [(u32, u32)],
        batch: &mut ShaderBatch,
    ) {
        let shaded = !self.splats.sh.is_empty();
        for (k, (slot, key)) in all.iter_mut().zip(keys.iter_mut()).enumerate() {
            let i = first + k;
            *key = match viewer.project(self, i) {
                Some(p) => {
                    *slot = p;
                    if shaded {
                        batch.push(&viewer.seen(self.splats, i, self.splats.sh[i]));
                    }
                    (p.distance.to_bits(), i as u32)
                }
                None => (OUT_OF_SIGHT, i as u32),
            };
        }
        if shaded {
            // The batch holds the visible splats, in the chunk's order.
            let visible = keys.iter().zip(all.iter_mut());
            let visible = visible.filter(|(key, _)| key.0 != OUT_OF_SIGHT);
            for ((_, slot), color) in visible.zip(batch.colors(self.shader)) {
                slot.color = color;
            }
        }
    }

    /// The splats projected and binned as `camera` sees them in a `width`×`height` frame, in `buffers`.
    pub(super) fn screen(
        &self,
        camera: &Camera,
        width: u32,
        height: u32,
        mut buffers: Buffers,
    ) -> Result<Screen> {
        check_size(width, height)?;
        let (tiles_x, tiles_y) = ((width as usize).div_ceil(TILE), (height as usize).div_ceil(TILE));
        let viewer = Viewer::of(camera, width, height);
        let [project, sort] = self.project(&viewer, &mut buffers);
        let start = Instant::now();
        bin(&mut buffers, (tiles_x, tiles_y));
        Ok(Screen {
            phases: [project, sort, start.elapsed()],
            viewer,
            buffers,
            width: width as usize,
            height: height as usize,
            tiles_x,
        })
    }
}

/// The splats of a frame projected and binned into its tiles: what drawing it and its gradients share.
pub(super) struct Screen {
    /// The camera as the projection sees it.
    pub viewer: Viewer,
    /// The splats on the screen and the tiles' lists of them.
    pub buffers: Buffers,
    pub width: usize,
    pub height: usize,
    pub tiles_x: usize,
    /// The time projecting, sorting and binning took.
    pub phases: [Duration; 3],
}

/// The pixels of a tile: columns `x0..x1`, rows `y0..y1` of the frame.
pub(super) struct Area {
    pub x0: usize,
    pub x1: usize,
    pub y0: usize,
    pub y1: usize,
}

impl Screen {
    /// Projects and bins `splats` (colored by `shader`) as `camera` sees them in a `width`×`height` frame.
    pub fn of(
        splats: &Splats,
        shader: &dyn SplatShader,
        camera: &Camera,
        width: u32,
        height: u32,
    ) -> Result<Screen> {
        SplatScene::new(splats, shader).screen(camera, width, height, Buffers::default())
    }

    /// Tile `tile`'s splats (nearest first) and pixels.
    pub fn tile(&self, tile: usize) -> (&[u32], Area) {
        let (row, col) = (tile / self.tiles_x, tile % self.tiles_x);
        let area = Area {
            x0: col * TILE,
            x1: ((col + 1) * TILE).min(self.width),
            y0: row * TILE,
            y1: ((row + 1) * TILE).min(self.height),
        };
        let b = &self.buffers;
        (&b.entries[b.starts[tile]..b.starts[tile + 1]], area)
    }

    /// The frame over `background`, and for each pixel how many of its tile's splats it took (the last
    /// one's place in the tile's list, plus one; 0 for none).
    pub fn draw(&self, background: [f32; 3]) -> (VolumeFrame, Vec<u32>) {
        self.composite_frame::<true>(background)
    }

    /// The frame over `background` alone (as [`Screen::draw`] draws it, without counting what each pixel
    /// took).
    pub fn picture(&self, background: [f32; 3]) -> VolumeFrame {
        self.composite_frame::<false>(background).0
    }

    /// The frame over `background`, and with `TAKEN` what [`Screen::draw`] says each pixel took (else an
    /// empty list).
    fn composite_frame<const TAKEN: bool>(&self, background: [f32; 3]) -> (VolumeFrame, Vec<u32>) {
        let pixels = self.width * self.height;
        let mut frame = VolumeFrame {
            width: self.width as u32,
            height: self.height as u32,
            rgb: vec![[0.0; 3]; pixels],
            depth: vec![0.0; pixels],
            opacity: vec![0.0; pixels],
        };
        let band = self.width * TILE;
        let mut taken = vec![0u32; if TAKEN { pixels } else { 0 }];
        let taken_bands: Vec<&mut [u32]> = match TAKEN {
            true => taken.chunks_mut(band).collect(),
            false => (0..self.height.div_ceil(TILE))
                .map(|_| Default::default())
                .collect(),
        };
        frame
            .rgb
            .par_chunks_mut(band)
            .zip(frame.depth.par_chunks_mut(band))
            .zip(frame.opacity.par_chunks_mut(band))
            .zip(taken_bands)
            .enumerate()
            .for_each(|(tile_row, (((rgb, depth), opacity), taken))| {
                for tile_col in 0..self.tiles_x {
                    let (list, area) = self.tile(tile_row * self.tiles_x + tile_col);
                    let band = Band {
                        rgb: &mut *rgb,
                        depth: &mut *depth,
                        opacity: &mut *opacity,
                        taken: &mut *taken,
                    };
                    draw_tile::<TAKEN>(&self.buffers.projected, list, &area, self.width, background, band);
                }
            });
        (frame, taken)
    }
}

/// The camera as the projection needs it.
pub(super) struct Viewer {
    /// World to view.
    pub rotation: Mat3,
    pub position: Vec3,
    pub fx: f32,
    pub fy: f32,
    cx: f32,
    cy: f32,
    width: f32,
    height: f32,
    /// The range of x/z and of y/z where the projection's Jacobian is taken (see [`Viewer::slopes`]).
    slopes_x: (f32, f32),
    slopes_y: (f32, f32),
}

impl Viewer {
    fn of(camera: &Camera, width: u32, height: u32) -> Viewer {
        let k = camera.pixel_intrinsics(width, height);
        // col = cx − fx·x/z lies within the frame widened by BEYOND on each side where x/z is in this range.
        let (w, h) = (width as f32, height as f32);
        let range = |c: f32, f: f32, side: f32| {
            let ends = ((c + BEYOND * side) / f, (c - (1.0 + BEYOND) * side) / f);
            (ends.0.min(ends.1), ends.0.max(ends.1))
        };
        Viewer {
            rotation: camera.rotation().transpose(),
            position: camera.position(),
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            width: w,
            height: h,
            slopes_x: range(k.cx, k.fx, w),
            slopes_y: range(k.cy, k.fy, h),
        }
    }

    /// The slopes x/z and y/z of view-space point `v` at which the projection's Jacobian is taken, and
    /// whether each is its own (not clamped): the Jacobian of a point beside the camera (far off the
    /// frame, barely in front) would stretch its splat across the whole frame, so the slopes are clamped
    /// to the frame widened by [`BEYOND`] on each side, as 3D Gaussian splatting clamps them at 1.3 times
    /// the field of view.
    pub(super) fn slopes(&self, v: Vec3) -> ((f32, bool), (f32, bool)) {
        let clamp = |slope: f32, (lo, hi): (f32, f32)| {
            let clamped = slope.clamp(lo, hi);
            (clamped, clamped == slope)
        };
        (clamp(v.x / v.z, self.slopes_x), clamp(v.y / v.z, self.slopes_y))
    }

    /// Splat `i` of `scene` on the screen; none behind the camera, off the screen or degenerate.
    fn project(&self, scene: &SplatScene, i: usize) -> Option<Projected> {
        let splats = scene.splats;
        let offset = Vec3::from(splats.positions[i]) - self.position;
        let v = self.rotation * offset;
        // (Written so that a z that is not a number fails too.)
        if !(v.z > NEAR && v.z.is_finite()) || splats.opacities[i] < MIN_ALPHA {
            return None;
        }
        let inv_z = 1.0 / v.z;
        let col = self.cx - self.fx * v.x * inv_z;
        let row = self.cy - self.fy * v.y * inv_z;
        // The screen's covariance is J R Σ Rᵀ Jᵀ, J the projection's Jacobian (col = cx − fx·x/z,
        // row = cy − fy·y/z) and R the view's rotation: with u = Rᵀ j for each row j of J, uᵀ Σ u.
        let ((slope_x, _), (slope_y, _)) = self.slopes(v);
        let (x_axis, y_axis, z_axis) = (self.rotation.row(0), self.rotation.row(1), self.rotation.row(2));
        let u_col = x_axis * (-self.fx * inv_z) + z_axis * (self.fx * slope_x * inv_z);
        let u_row = y_axis * (-self.fy * inv_z) + z_axis * (self.fy * slope_y * inv_z);
        let [xx, xy, xz, yy, yz, zz] = scene.covariances[i];
        let times = |u: Vec3| {
            Vec3::new(
                xx * u.x + xy * u.y + xz * u.z,
                xy * u.x + yy * u.y + yz * u.z,
                xz * u.x + yz * u.y + zz * u.z,
            )
        };
        let (s_col, s_row) = (times(u_col), times(u_row));
        let a = u_col.dot(s_col) + LOW_PASS;
        let b = u_col.dot(s_row);
        let c = u_row.dot(s_row) + LOW_PASS;
        let det = a * c - b * b;
        if !(det > 0.0 && det.is_finite()) {
            return None;
        }
        // Its alpha reaches MIN_ALPHA within the ellipse where the exponent is the cutoff (dᵀ Σ⁻¹ d =
        // −2 cutoff), whose half-width along the columns is √(−2 cutoff a) and along the rows √(−2 cutoff c).
        let cutoff = scene.cutoffs[i];
        let extent = [(-2.0 * cutoff * a).sqrt(), (-2.0 * cutoff * c).sqrt()];
        if col + extent[0] < 0.0
            || row + extent[1] < 0.0
            || col - extent[0] > self.width
            || row - extent[1] > self.height
        {
            return None;
        }
        Some(Projected {
            index: i as u32,
            col,
            row,
            conic: [c / det, -b / det, a / det],
            extent,
            distance: v.length(),
            opacity: splats.opacities[i],
            cutoff,
            // The shader's color where the splats have spherical harmonics (see `SplatScene::project`).
            color: splats.colors[i],
        })
    }

    /// What splat `i`, of spherical harmonics `sh`, gives its shader for this camera.
    pub(super) fn seen(&self, splats: &Splats, i: usize, sh: [[f32; 3]; 3]) -> Seen {
        Seen {
            base: splats.colors[i],
            sh,
            offset: Vec3::from(splats.positions[i]) - self.position,
        }
    }
}

/// Calls `f` with each tile (its place, row by row, of `tiles` = (columns, rows)) that `p`'s box
/// touches.
#[inline(always)]
fn each_tile(p: &Projected, (tiles_x, tiles_y): (usize, usize), mut f: impl FnMut(usize)) {
    let tile = |at: f32, n: usize| ((at / TILE as f32).floor().max(0.0) as usize).min(n);
    let [wide, high] = p.extent;
    let (x0, x1) = (tile(p.col - wide, tiles_x), tile(p.col + wide, tiles_x - 1) + 1);
    let (y0, y1) = (tile(p.row - high, tiles_y), tile(p.row + high, tiles_y - 1) + 1);
    for y in y0..y1 {
        for x in x0..x1 {
            f(y * tiles_x + x);
        }
    }
}

/// The splats of each tile, nearest first: tile `t`'s are `entries[starts[t]..starts[t + 1]]`, each its
/// place in `projected` (nearest first). Each thread takes a share of the splats and fills its own part of
/// each tile's entries (after the earlier shares' parts), in order.
fn bin(buffers: &mut Buffers, tiles: (usize, usize)) {
    let Buffers {
        projected,
        starts,
        entries,
        ..
    } = buffers;
    let count = tiles.0 * tiles.1;
    let share = projected.len().div_ceil(rayon::current_num_threads()).max(1);
    let counts: Vec<Vec<usize>> = projected
        .par_chunks(share)
        .map(|part| {
            let mut counts = vec![0usize; count];
            for p in part {
                each_tile(p, tiles, |t| counts[t] += 1);
            }
            counts
        })
        .collect();
    // The entries are cut tile by tile, and within a tile share by share.
    starts.clear();
    let mut bounds = Vec::with_capacity(count * counts.len() + 1);
    let mut at = 0usize;
    for t in 0..count {
        starts.push(at);
        for counts in &counts {
            bounds.push(at);
            at += counts[t];
        }
    }
    starts.push(at);
    bounds.push(at);
    entries.resize(at, 0);
    let mut parts: Vec<Vec<&mut [u32]>> = counts.iter().map(|_| Vec::with_capacity(count)).collect();
    for (k, part) in per_tile(entries, &bounds).into_iter().enumerate() {
        parts[k % counts.len()].push(part);
    }
    projected
        .par_chunks(share)
        .zip(parts)
        .enumerate()
        .for_each(|(k, (splats, mut parts))| {
            let mut filled = vec![0usize; count];
            for (i, p) in splats.iter().enumerate() {
                let place = (k * share + i) as u32;
                each_tile(p, tiles, |t| {
                    parts[t][filled[t]] = place;
                    filled[t] += 1;
                });
            }
        });
}

/// `values` cut into each tile's part, tile `t`'s being `values[starts[t]..starts[t + 1]]`.
pub(super) fn per_tile<'a, T>(values: &'a mut [T], starts: &[usize]) -> Vec<&'a mut [T]> {
    let mut rest = values;
    let mut parts = Vec::with_capacity(starts.len().saturating_sub(1));
    for bounds in starts.windows(2) {
        let (part, tail) = rest.split_at_mut(bounds[1] - bounds[0]);
        parts.push(part);
        rest = tail;
    }
    parts
}

/// 2²³ + 2²²: a float whose last bit is worth 1, with room below and above.
const BIASING: f32 = 12_582_912.0;

/// e^x for x in [−30, 0], to a relative error under 2e-4 (2^(x log2 e): the integer part in the exponent's
/// bits, the fraction by a cubic).
#[inline(always)]
fn fast_exp(x: f32) -> f32 {
    let t = x * std::f32::consts::LOG2_E;
    let t = if t < -126.0 { -126.0 } else { t };
    let whole = t.floor();
    let f = t - whole;
    let fraction = fused(f, fused(f, fused(f, 0.079_083_2, 0.224_940_7), 0.695_976_1), 1.0);
    // whole + 127 (in 1..=127) as the low bits of a float of 2²³ + 2²² + whole + 127, whose exponent is
    // 2²³'s: the integer without a conversion (which the vector unit would have to guard against overflow).
    let biased = (whole + (BIASING + 127.0))
        .to_bits()
        .wrapping_sub(BIASING.to_bits());
    f32::from_bits(biased << 23) * fraction
}

/// The pixels `lo..hi` (of a row or a column) within `radius` of `center`.
#[inline(always)]
pub(super) fn span(center: f32, radius: f32, lo: usize, hi: usize) -> std::ops::Range<usize> {
    let first = ((center - radius).floor().max(lo as f32) as usize).max(lo);
    let last = ((center + radius).ceil().max(0.0) as usize).min(hi);
    first..last.max(first)
}

/// a·b + c: one fused multiply-add where this build's CPU has them, else a product and a sum. The frame and
/// its backward pass both compute alphas with it, so that they agree bit for bit.
#[inline(always)]
pub(super) fn fused(a: f32, b: f32, c: f32) -> f32 {
    #[cfg(target_feature = "fma")]
    let sum = a.mul_add(b, c);
    #[cfg(not(target_feature = "fma"))]
    let sum = a * b + c;
    sum
}

/// A splat's Gaussian exponent along a row of pixels `dy` from its center, as a polynomial in dx:
/// −(a dx² + c dy²)/2 − b dx dy = dx (a′ dx + b′) + c′, (a, b, c) its conic.
#[derive(Clone, Copy)]
struct RowPower {
    a: f32,
    b: f32,
    c: f32,
}

impl RowPower {
    /// The row `dy` from `p`'s center.
    #[inline(always)]
    fn of(p: &Projected, dy: f32) -> RowPower {
        RowPower {
            a: -0.5 * p.conic[0],
            b: -p.conic[1] * dy,
            c: -0.5 * p.conic[2] * dy * dy,
        }
    }

    /// The exponent `dx` from the center along the row.
    #[inline(always)]
    fn at(&self, dx: f32) -> f32 {
        fused(dx, fused(self.a, dx, self.b), self.c)
    }
}

/// The Gaussian's exponent at (`dx`, `dy`) from splat `p`'s center.
#[inline(always)]
fn power_at(p: &Projected, dx: f32, dy: f32) -> f32 {
    RowPower::of(p, dy).at(dx)
}

/// The alpha splat `p` gives the pixel (`dx`, `dy`) from its center (at most [`MAX_ALPHA`]) and its
/// Gaussian there; `None` where its alpha would be under [`MIN_ALPHA`].
#[inline(always)]
pub(super) fn alpha_at(p: &Projected, dx: f32, dy: f32) -> Option<(f32, f32)> {
    let power = power_at(p, dx, dy);
    if power > 0.0 || power < p.cutoff {
        return None;
    }
    let gaussian = fast_exp(power);
    Some(((p.opacity * gaussian).min(MAX_ALPHA), gaussian))
}

/// The rows of the frame that hold a row of tiles (`width` pixels a row).
struct Band<'a> {
    rgb: &'a mut [[f32; 3]],
    depth: &'a mut [f32],
    opacity: &'a mut [f32],
    taken: &'a mut [u32],
}

/// A tile's pixels as they composite, row by row (`TILE` a row, whatever the tile's width).
struct TilePixels {
    transmittance: [f32; TILE * TILE],
    red: [f32; TILE * TILE],
    green: [f32; TILE * TILE],
    blue: [f32; TILE * TILE],
    distance: [f32; TILE * TILE],
    /// How many of the tile's splats each took (the last one's place, plus one).
    taken: [u32; TILE * TILE],
    /// Whether each half row (`LANES` pixels, row by row) may still take splats: whether a pixel of it
    /// in the frame was not saturated when last looked at.
    open: [bool; HALVES],
}

/// The half rows of a tile.
const HALVES: usize = TILE * TILE / LANES;

impl TilePixels {
    /// Composites splat `p`, the tile's `place`th, over the `LANES` pixels from `k` on, which lie at
    /// columns from `x` on and row `y` of the frame. Every lane takes the same steps (a lane the splat
    /// does not reach, or that is saturated, takes alpha 0, which changes nothing), so that the loop runs
    /// in the vector unit. With `TAKEN`, each pixel the splat reaches notes its place.
    #[inline(always)]
    fn composite<const TAKEN: bool>(&mut self, p: &Projected, place: u32, k: usize, x: usize, y: usize) {
        let row = RowPower::of(p, y as f32 + 0.5 - p.row);
        let [cr, cg, cb] = p.color;
        let transmittance: &mut [f32; LANES] = (&mut self.transmittance[k..k + LANES]).try_into().unwrap();
        let red: &mut [f32; LANES] = (&mut self.red[k..k + LANES]).try_into().unwrap();
        let green: &mut [f32; LANES] = (&mut self.green[k..k + LANES]).try_into().unwrap();
        let blue: &mut [f32; LANES] = (&mut self.blue[k..k + LANES]).try_into().unwrap();
        let distance: &mut [f32; LANES] = (&mut self.distance[k..k + LANES]).try_into().unwrap();
        let taken: &mut [u32; LANES] = (&mut self.taken[k..k + LANES]).try_into().unwrap();
        for lane in 0..LANES {
            let dx = (x + lane) as f32 + 0.5 - p.col;
            let power = row.at(dx);
            let t = transmittance[lane];
            let reached = power <= 0.0 && power >= p.cutoff && t >= SATURATED;
            let alpha = (p.opacity * fast_exp(power)).min(MAX_ALPHA);
            let alpha = if reached { alpha } else { 0.0 };
            let weight = alpha * t;
            red[lane] = fused(weight, cr, red[lane]);
            green[lane] = fused(weight, cg, green[lane]);
            blue[lane] = fused(weight, cb, blue[lane]);
            distance[lane] = fused(weight, p.distance, distance[lane]);
            transmittance[lane] = t * (1.0 - alpha);
            if TAKEN {
                taken[lane] = if reached { place + 1 } else { taken[lane] };
            }
        }
    }

    /// Marks the half rows whose pixels are all saturated (those outside the frame count as such) as
    /// closed; returns whether any is still open.
    fn close_saturated(&mut self, area: &Area) -> bool {
        let width = area.x1 - area.x0;
        let mut any = false;
        for (half, open) in self.open.iter_mut().enumerate() {
            let (y, x) = (half * LANES / TILE, half * LANES % TILE);
            if *open {
                let k = y * TILE + x;
                *open = y < area.y1 - area.y0
                    && x < width
                    && self.transmittance[k..k + LANES.min(width - x)]
                        .iter()
                        .any(|&t| t >= SATURATED);
            }
            any |= *open;
        }
        any
    }
}

/// Composites the splats of `list` (nearest first) over the pixels of `area`, into the band of rows
/// (`width` pixels a row) that holds the tile; with `TAKEN`, also how many of them each pixel took.
fn draw_tile<const TAKEN: bool>(
    projected: &[Projected],
    list: &[u32],
    area: &Area,
    width: usize,
    background: [f32; 3],
    band: Band,
) {
    let (w, h) = (area.x1 - area.x0, area.y1 - area.y0);
    let mut pixels = TilePixels {
        transmittance: [1.0; TILE * TILE],
        red: [0.0; TILE * TILE],
        green: [0.0; TILE * TILE],
        blue: [0.0; TILE * TILE],
        distance: [0.0; TILE * TILE],
        taken: [0; TILE * TILE],
        open: [true; HALVES],
    };
    // The splats are copied out a batch at a time before they are drawn: the copies' reads (spread over
    // the frame's splats) overlap one another instead of each stalling a splat's compositing.
    let mut batch = [Projected::default(); SATURATION_CHECKS];
    for (first, entries) in (0..)
        .step_by(SATURATION_CHECKS)
        .zip(list.chunks(SATURATION_CHECKS))
    {
        for (copy, &entry) in batch.iter_mut().zip(entries) {
            *copy = projected[entry as usize];
        }
        for (place, p) in (first..).zip(&batch[..entries.len()]) {
            let columns = span(p.col, p.extent[0], area.x0, area.x1);
            if columns.is_empty() {
                continue;
            }
            let halves = (columns.start - area.x0) / LANES..(columns.end - 1 - area.x0) / LANES + 1;
            for y in span(p.row, p.extent[1], area.y0, area.y1) {
                for half in halves.clone() {
                    let k = (y - area.y0) * TILE + half * LANES;
                    if pixels.open[k / LANES] {
                        pixels.composite::<TAKEN>(p, place, k, area.x0 + half * LANES, y);
                    }
                }
            }
        }
        if !pixels.close_saturated(area) {
            break;
        }
    }
    for y in 0..h {
        for x in 0..w {
            let k = y * TILE + x;
            let at = y * width + area.x0 + x;
            let t = pixels.transmittance[k];
            band.rgb[at] = [
                pixels.red[k] + t * background[0],
                pixels.green[k] + t * background[1],
                pixels.blue[k] + t * background[2],
            ];
            band.depth[at] = pixels.distance[k];
            band.opacity[at] = 1.0 - t;
            if TAKEN {
                band.taken[at] = pixels.taken[k];
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splats::shading::formula::Formula;
    use glam::Vec2;

    fn camera() -> Camera {
        Camera::look_at(
            Vec3::new(0.0, 0.0, -4.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::splat(2.0),
            Vec2::ZERO,
        )
        .unwrap()
    }

    fn one(position: [f32; 3], scale: f32, opacity: f32, color: [f32; 3]) -> Splats {
        Splats {
            positions: vec![position],
            colors: vec![color],
            opacities: vec![opacity],
            scales: vec![[scale; 3]],
            rotations: vec![[1.0, 0.0, 0.0, 0.0]],
            sh: Vec::new(),
        }
    }

    /// A round splat at the center is the Gaussian its projection says: at its center, opacity · 1 (less
    /// the low-pass's widening); one standard deviation out, e^(−1/2) of that.
    #[test]
    fn one_splat_draws_its_projected_gaussian() {
        let (size, scale) = (64u32, 0.1f32);
        let camera = camera();
        let splats = one([0.0; 3], scale, 0.8, [1.0, 0.5, 0.0]);
        let (frame, stats) = render_splats(&splats, &Formula, &camera, size, size, [0.0; 3]).unwrap();
        assert_eq!(stats.visible, 1);
        // The screen's standard deviation: fx · scale / distance, with the low-pass added to its square.
        let fx = camera.pixel_intrinsics(size, size).fx;
        let sigma = ((fx * scale / 4.0).powi(2) + LOW_PASS).sqrt();
        let at = |dx: f32| {
            let (row, col) = (size as usize / 2, (size as f32 / 2.0 + dx).floor() as usize);
            frame.opacity[row * size as usize + col]
        };
        // Pixel centers sit half a pixel off the image's center.
        let expected = |d: f32| 0.8 * (-0.5 * (d * d + 0.25) / (sigma * sigma)).exp();
        assert!(
            (at(0.0) - expected(0.5)).abs() < 2e-4,
            "{} vs {}",
            at(0.0),
            expected(0.5)
        );
        let out = sigma.round();
        assert!((at(out) - expected(out + 0.5)).abs() < 2e-4);
        let center = (size as usize / 2) * size as usize + size as usize / 2;
        let rgb = frame.rgb[center];
        assert!((rgb[0] - frame.opacity[center]).abs() < 1e-6 && rgb[2] == 0.0);
        assert!((frame.depth[center] / frame.opacity[center] - 4.0).abs() < 1e-4);
    }

    /// Two splats on one line of sight: the nearer covers the farther, whatever their order in the list.
    #[test]
    fn the_nearer_splat_is_in_front() {
        let mut splats = one([0.0, 0.0, 1.0], 0.3, 0.99, [0.0, 0.0, 1.0]);
        let near = one([0.0, 0.0, -1.0], 0.3, 0.99, [1.0, 0.0, 0.0]);
        splats.positions.extend(&near.positions);
        splats.colors.extend(&near.colors);
        splats.opacities.extend(&near.opacities);
        splats.scales.extend(&near.scales);
        splats.rotations.extend(&near.rotations);
        let (frame, _) = render_splats(&splats, &Formula, &camera(), 32, 32, [1.0; 3]).unwrap();
        let center = frame.rgb[16 * 32 + 16];
        assert!(center[0] > 0.9 && center[2] < 0.05, "{center:?}");
    }

    #[test]
    fn the_fast_exponential_is_close() {
        for k in 0..=3000 {
            let x = -0.01 * k as f32;
            let (fast, exact) = (fast_exp(x), x.exp());
            assert!((fast - exact).abs() <= 2e-4 * exact, "{x}: {fast} vs {exact}");
        }
    }

    /// Splats behind the camera or off the screen draw nothing; the frame is the background.
    #[test]
    fn splats_out_of_sight_draw_nothing() {
        for position in [[0.0, 0.0, -10.0], [50.0, 0.0, 0.0]] {
            let splats = one(position, 0.1, 1.0, [0.0; 3]);
            let (frame, stats) =
                render_splats(&splats, &Formula, &camera(), 16, 8, [0.25, 0.5, 1.0]).unwrap();
            assert_eq!(stats.visible, 0);
            assert!(frame.rgb.iter().all(|p| *p == [0.25, 0.5, 1.0]));
        }
    }

    /// The tiled compositor (splats binned by tile, eight pixels at a time, rows and halves cut to each
    /// splat's square) draws exactly what compositing every splat over every pixel on its own does, on a
    /// frame whose sides are not whole tiles.
    #[test]
    fn tiles_draw_what_each_pixel_composites_alone() {
        let mut rng = crate::Rng::new(7);
        let mut splats = Splats::default();
        for i in 0..400 {
            let mut r = || 2.0 * rng.next_f32() - 1.0;
            // A hundred of them crowd the middle, where the pixels saturate.
            let spread = if i < 100 { 0.4 } else { 1.5 };
            splats.positions.push([spread * r(), spread * r(), r()]);
            splats
                .colors
                .push([0.5 + 0.5 * r(), 0.5 + 0.5 * r(), 0.5 + 0.5 * r()]);
            splats.opacities.push(0.7 + 0.3 * r());
            splats
                .scales
                .push([0.12 + 0.1 * r(), 0.12 + 0.1 * r(), 0.12 + 0.1 * r()]);
            let q = glam::Vec4::new(r(), r(), r(), r()).normalize();
            splats.rotations.push(q.to_array());
        }
        let (width, height, background) = (53u32, 37u32, [0.2, 0.3, 0.4]);
        let (frame, stats) = render_splats(&splats, &Formula, &camera(), width, height, background).unwrap();
        assert!(stats.entries > stats.visible && stats.visible > 250, "{stats:?}");
        let screen = Screen::of(&splats, &Formula, &camera(), width, height).unwrap();
        // The gradients' frame (which also counts what each pixel took) is the same picture.
        let (drawn, _) = screen.draw(background);
        assert_eq!(
            (&drawn.rgb, &drawn.opacity, &drawn.depth),
            (&frame.rgb, &frame.opacity, &frame.depth)
        );
        // Some half rows saturate and take no more splats.
        let saturated = frame.opacity.iter().filter(|&&o| 1.0 - o < SATURATED).count();
        assert!(saturated > 20, "{saturated} pixels saturated");
        for y in 0..height as usize {
            for x in 0..width as usize {
                let (mut t, mut color, mut distance) = (1.0f32, [0.0f32; 3], 0.0f32);
                for p in &screen.buffers.projected {
                    if t < SATURATED {
                        break;
                    }
                    let Some((alpha, _)) = alpha_at(p, x as f32 + 0.5 - p.col, y as f32 + 0.5 - p.row) else {
                        continue;
                    };
                    let weight = alpha * t;
                    for (sum, c) in color.iter_mut().zip(p.color) {
                        *sum = fused(weight, c, *sum);
                    }
                    distance = fused(weight, p.distance, distance);
                    t *= 1.0 - alpha;
                }
                let at = y * width as usize + x;
                let expected: [f32; 3] = std::array::from_fn(|c| color[c] + t * background[c]);
                assert_eq!(frame.rgb[at], expected, "pixel ({x}, {y})");
                assert_eq!(frame.opacity[at], 1.0 - t);
                assert_eq!(frame.depth[at], distance);
            }
        }
    }

    /// A splat beside the camera (far off the frame, barely in front of it) stays off the frame: the
    /// projection's Jacobian taken at its center would stretch it over all of it.
    #[test]
    fn a_splat_beside_the_camera_stays_off_the_frame() {
        let splats = one([20.0, 0.0, -3.9], 0.05, 1.0, [0.0; 3]);
        let (frame, stats) = render_splats(&splats, &Formula, &camera(), 32, 32, [1.0; 3]).unwrap();
        assert_eq!(stats.visible, 0);
        assert!(frame.rgb.iter().all(|p| *p == [1.0; 3]));
    }

    /// An elongated splat lies along its rotated axis: turned 90° about the view axis, its long side
    /// goes from horizontal to vertical.
    #[test]
    fn a_rotated_splat_turns_on_the_screen() {
        let size = 48usize;
        let spread = |rotation: [f32; 4]| {
            let splats = Splats {
                positions: vec![[0.0; 3]],
                colors: vec![[1.0; 3]],
                opacities: vec![1.0],
                scales: vec![[0.4, 0.05, 0.05]],
                rotations: vec![rotation],
                sh: Vec::new(),
            };
            let (frame, _) =
                render_splats(&splats, &Formula, &camera(), size as u32, size as u32, [0.0; 3]).unwrap();
            let row: f32 = (0..size).map(|x| frame.opacity[size / 2 * size + x]).sum();
            let column: f32 = (0..size).map(|y| frame.opacity[y * size + size / 2]).sum();
            (row, column)
        };
        let (row, column) = spread([1.0, 0.0, 0.0, 0.0]);
        assert!(row > 3.0 * column, "{row} {column}");
        let half = std::f32::consts::FRAC_1_SQRT_2;
        let (row, column) = spread([half, 0.0, 0.0, half]);
        assert!(column > 3.0 * row, "{row} {column}");
    }
}
