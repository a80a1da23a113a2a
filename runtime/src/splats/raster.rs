//! The CPU splat renderer: each splat is projected to a 2D Gaussian on the screen (the ellipsoid's
//! covariance through the projection's Jacobian, widened by a 0.3-pixel low-pass as 3D Gaussian splatting
//! does), binned into the 16×16 tiles they touch and sorted by distance tile by tile, and the tiles are
//! drawn in parallel, each pixel compositing its splats front to back (alpha = opacity · the Gaussian, at
//! most 0.99, below 1/255 skipped) until its transmittance falls under 1e-4.
//!
//! The frame is a [`VolumeFrame`], as a field's volume render gives it: composited color over the
//! background, opacity, and the expected distance from the camera Σ wᵢ dᵢ (not normalized).

use std::sync::atomic::{AtomicU32, AtomicU64, AtomicUsize, Ordering};

use glam::{Mat3, Quat, Vec3};
use rayon::prelude::*;

use super::Splats;
use crate::cameras::camera::Camera;
use crate::error::{check_size, Result};
use crate::volume::render::VolumeFrame;

/// The side of a tile, in pixels.
pub(super) const TILE: usize = 16;

/// Splats nearer than this to the camera's plane are not drawn.
const NEAR: f32 = 0.01;

/// The variance (in pixels²) added to every projected splat, so that none is thinner than a pixel.
pub(super) const LOW_PASS: f32 = 0.3;

/// Alphas below this are skipped.
const MIN_ALPHA: f32 = 1.0 / 255.0;

/// No splat covers a pixel entirely.
pub(super) const MAX_ALPHA: f32 = 0.99;

/// A pixel whose transmittance falls below this takes no more splats.
const SATURATED: f32 = 1e-4;

/// What drawing a frame involved.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SplatFrameStats {
    /// Splats in front of the camera and on the screen.
    pub visible: usize,
    /// Splat-tile pairs drawn.
    pub entries: usize,
}

/// A splat as the screen sees it.
#[derive(Debug, Clone, Copy)]
pub(super) struct Projected {
    /// Which splat it is.
    pub index: u32,
    /// The center's continuous pixel coordinates (pixel centers at +0.5).
    pub col: f32,
    pub row: f32,
    /// The inverse of the 2D covariance: (a, b, c) of [[a, b], [b, c]].
    pub conic: [f32; 3],
    /// The half-side of its square on the screen, in pixels: it holds every pixel where its alpha reaches
    /// [`MIN_ALPHA`] (so that the frame changes smoothly with the splat, but at that edge).
    pub radius: f32,
    /// Its distance from the camera.
    pub distance: f32,
    pub opacity: f32,
    /// The Gaussian's exponent below which its alpha is under [`MIN_ALPHA`]: ln(MIN_ALPHA / opacity).
    pub cutoff: f32,
    pub color: [f32; 3],
    /// The tiles it touches: columns `tiles[0]..tiles[2]`, rows `tiles[1]..tiles[3]`.
    tiles: [u32; 4],
}

/// Draws `splats` as `camera` sees them in a `width`×`height` frame over `background`.
pub fn render_splats(
    splats: &Splats,
    camera: &Camera,
    width: u32,
    height: u32,
    background: [f32; 3],
) -> Result<(VolumeFrame, SplatFrameStats)> {
    let screen = Screen::of(splats, camera, width, height)?;
    let (frame, _) = screen.draw(background);
    let stats = SplatFrameStats {
        visible: screen.projected.len(),
        entries: screen.entries.len(),
    };
    Ok((frame, stats))
}

/// The splats of a frame projected and binned into its tiles: what drawing it and its gradients share.
pub(super) struct Screen {
    /// The camera as the projection sees it.
    pub viewer: Viewer,
    /// The splats on the screen.
    pub projected: Vec<Projected>,
    /// Tile `t`'s splats are `entries[starts[t]..starts[t + 1]]`, nearest first: each the distance's bits
    /// over the index in `projected` (its low 32 bits).
    pub starts: Vec<usize>,
    pub entries: Vec<u64>,
    pub width: usize,
    pub height: usize,
    pub tiles_x: usize,
}

/// The pixels of a tile: columns `x0..x1`, rows `y0..y1` of the frame.
pub(super) struct Area {
    pub x0: usize,
    pub x1: usize,
    pub y0: usize,
    pub y1: usize,
}

impl Screen {
    /// Projects and bins `splats` as `camera` sees them in a `width`×`height` frame.
    pub fn of(splats: &Splats, camera: &Camera, width: u32, height: u32) -> Result<Screen> {
        check_size(width, height)?;
        let (tiles_x, tiles_y) = ((width as usize).div_ceil(TILE), (height as usize).div_ceil(TILE));
        let viewer = Viewer::of(camera, width, height, (tiles_x as u32, tiles_y as u32));
        let projected: Vec<Projected> = (0..splats.len())
            .into_par_iter()
            .filter_map(|i| viewer.project(splats, i))
            .collect();
        let (starts, entries) = bin(&projected, tiles_x * tiles_y, tiles_x);
        Ok(Screen {
            viewer,
            projected,
            starts,
            entries,
            width: width as usize,
            height: height as usize,
            tiles_x,
        })
    }

    /// Tile `tile`'s splats (nearest first) and pixels.
    pub fn tile(&self, tile: usize) -> (&[u64], Area) {
        let (row, col) = (tile / self.tiles_x, tile % self.tiles_x);
        let area = Area {
            x0: col * TILE,
            x1: ((col + 1) * TILE).min(self.width),
            y0: row * TILE,
            y1: ((row + 1) * TILE).min(self.height),
        };
        (&self.entries[self.starts[tile]..self.starts[tile + 1]], area)
    }

    /// The frame over `background`, and for each pixel how many of its tile's splats it took (the last
    /// one's place in the tile's list, plus one; 0 for none).
    pub fn draw(&self, background: [f32; 3]) -> (VolumeFrame, Vec<u32>) {
        let pixels = self.width * self.height;
        let mut frame = VolumeFrame {
            width: self.width as u32,
            height: self.height as u32,
            rgb: vec![[0.0; 3]; pixels],
            depth: vec![0.0; pixels],
            opacity: vec![0.0; pixels],
        };
        let mut taken = vec![0u32; pixels];
        let band = self.width * TILE;
        frame
            .rgb
            .par_chunks_mut(band)
            .zip(frame.depth.par_chunks_mut(band))
            .zip(frame.opacity.par_chunks_mut(band))
            .zip(taken.par_chunks_mut(band))
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
                    draw_tile(&self.projected, list, &area, self.width, background, band);
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
    tiles: (u32, u32),
}

impl Viewer {
    fn of(camera: &Camera, width: u32, height: u32, tiles: (u32, u32)) -> Viewer {
        let k = camera.pixel_intrinsics(width, height);
        Viewer {
            rotation: camera.rotation().transpose(),
            position: camera.position(),
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            width: width as f32,
            height: height as f32,
            tiles,
        }
    }

    /// Splat `i` on the screen; none behind the camera, off the screen or degenerate.
    fn project(&self, splats: &Splats, i: usize) -> Option<Projected> {
        let v = self.rotation * (Vec3::from(splats.positions[i]) - self.position);
        if !v.z.is_finite() || v.z <= NEAR || splats.opacities[i] < MIN_ALPHA {
            return None;
        }
        let inv_z = 1.0 / v.z;
        let col = self.cx - self.fx * v.x * inv_z;
        let row = self.cy - self.fy * v.y * inv_z;
        // Off the screen by more than the splat's widest extent (a bound: 3.4 of its largest deviations, at
        // the steepest the projection gets there; its alpha is under MIN_ALPHA from √(2 ln 255) ≈ 3.33 on)?
        let [sx, sy, sz] = splats.scales[i];
        let widest = sx.max(sy).max(sz);
        let stretch = (1.0 + (v.x * v.x + v.y * v.y) * inv_z * inv_z).sqrt();
        let bound = 3.4 * (widest * self.fx.max(self.fy) * inv_z * stretch + LOW_PASS.sqrt()) + 1.0;
        if col + bound < 0.0 || row + bound < 0.0 || col - bound > self.width || row - bound > self.height {
            return None;
        }
        // The view-space covariance is M Mᵀ; the screen's is J M (J M)ᵀ, J the projection's Jacobian:
        // col = cx − fx·x/z, row = cy − fy·y/z. A round splat's M Mᵀ is s² I whatever its rotation.
        let j_col = Vec3::new(-self.fx * inv_z, 0.0, self.fx * v.x * inv_z * inv_z);
        let j_row = Vec3::new(0.0, -self.fy * inv_z, self.fy * v.y * inv_z * inv_z);
        let (t_col, t_row) = if sx == sy && sy == sz {
            (j_col * sx, j_row * sx)
        } else {
            let [w, x, y, z] = splats.rotations[i];
            let axes = Mat3::from_quat(Quat::from_xyzw(x, y, z, w).normalize());
            let m = self.rotation * axes * Mat3::from_diagonal(Vec3::new(sx, sy, sz));
            (m.transpose() * j_col, m.transpose() * j_row)
        };
        let a = t_col.dot(t_col) + LOW_PASS;
        let b = t_col.dot(t_row);
        let c = t_row.dot(t_row) + LOW_PASS;
        let det = a * c - b * b;
        if !det.is_finite() || det <= 0.0 {
            return None;
        }
        let mid = 0.5 * (a + c);
        let largest = mid + (mid * mid - det).max(0.0).sqrt();
        // Its alpha reaches MIN_ALPHA within the ellipse where the exponent is the cutoff, whose half-width
        // along its widest axis this is.
        let cutoff = (MIN_ALPHA / splats.opacities[i]).ln();
        let radius = (-2.0 * cutoff * largest).sqrt();
        if col + radius < 0.0 || row + radius < 0.0 || col - radius > self.width || row - radius > self.height
        {
            return None;
        }
        let tile = |p: f32, n: u32| ((p / TILE as f32).floor().max(0.0) as u32).min(n);
        let tiles = [
            tile(col - radius, self.tiles.0),
            tile(row - radius, self.tiles.1),
            tile(col + radius, self.tiles.0 - 1) + 1,
            tile(row + radius, self.tiles.1 - 1) + 1,
        ];
        Some(Projected {
            index: i as u32,
            col,
            row,
            conic: [c / det, -b / det, a / det],
            radius,
            distance: v.length(),
            opacity: splats.opacities[i],
            cutoff,
            color: splats.colors[i],
            tiles,
        })
    }
}

/// The splats of each tile, nearest first: tile `t`'s are `entries[starts[t]..starts[t + 1]]`, each the
/// splat's distance (its bits: distances are positive, so their bits sort as they do) over its index.
fn bin(projected: &[Projected], tiles: usize, tiles_x: usize) -> (Vec<usize>, Vec<u64>) {
    let counts: Vec<AtomicU32> = (0..tiles).map(|_| AtomicU32::new(0)).collect();
    let each_tile = |p: &Projected, f: &mut dyn FnMut(usize)| {
        for y in p.tiles[1]..p.tiles[3] {
            for x in p.tiles[0]..p.tiles[2] {
                f(y as usize * tiles_x + x as usize);
            }
        }
    };
    projected.par_iter().for_each(|p| {
        each_tile(p, &mut |t| {
            counts[t].fetch_add(1, Ordering::Relaxed);
        })
    });
    let mut starts = Vec::with_capacity(tiles + 1);
    starts.push(0usize);
    for c in &counts {
        starts.push(starts.last().copied().unwrap_or(0) + c.load(Ordering::Relaxed) as usize);
    }
    let cursors: Vec<AtomicUsize> = starts[..tiles].iter().map(|&s| AtomicUsize::new(s)).collect();
    let entries: Vec<AtomicU64> = (0..starts[tiles]).map(|_| AtomicU64::new(0)).collect();
    projected.par_iter().enumerate().for_each(|(i, p)| {
        let key = (u64::from(p.distance.to_bits()) << 32) | i as u64;
        each_tile(p, &mut |t| {
            let at = cursors[t].fetch_add(1, Ordering::Relaxed);
            entries[at].store(key, Ordering::Relaxed);
        })
    });
    let mut entries: Vec<u64> = entries.into_iter().map(AtomicU64::into_inner).collect();
    per_tile(&mut entries, &starts)
        .into_par_iter()
        .for_each(|list| list.sort_unstable());
    (starts, entries)
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

/// e^x for x in [−30, 0], to a relative error under 2e-4 (2^(x log2 e): the integer part in the exponent's
/// bits, the fraction by a cubic).
fn fast_exp(x: f32) -> f32 {
    let t = (x * std::f32::consts::LOG2_E).max(-126.0);
    let whole = t.floor();
    let f = t - whole;
    let fraction = 1.0 + f * (0.695_976_1 + f * (0.224_940_7 + f * 0.079_083_2));
    f32::from_bits(((whole as i32 + 127) as u32) << 23) * fraction
}

/// The pixels `lo..hi` (of a row or a column) within `radius` of `center`.
#[inline(always)]
pub(super) fn span(center: f32, radius: f32, lo: usize, hi: usize) -> std::ops::Range<usize> {
    let first = ((center - radius).floor().max(lo as f32) as usize).max(lo);
    let last = ((center + radius).ceil().max(0.0) as usize).min(hi);
    first..last.max(first)
}

/// The alpha splat `p` gives the pixel (`dx`, `dy`) from its center (at most [`MAX_ALPHA`]) and its
/// Gaussian there; `None` where its alpha would be under [`MIN_ALPHA`].
#[inline(always)]
pub(super) fn alpha_at(p: &Projected, dx: f32, dy: f32) -> Option<(f32, f32)> {
    let power = -0.5 * (p.conic[0] * dx * dx + p.conic[2] * dy * dy) - p.conic[1] * dx * dy;
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

/// Composites the splats of `list` (nearest first) over the pixels of `area`, into the band of rows
/// (`width` pixels a row) that holds the tile.
fn draw_tile(
    projected: &[Projected],
    list: &[u64],
    area: &Area,
    width: usize,
    background: [f32; 3],
    band: Band,
) {
    let (w, h) = (area.x1 - area.x0, area.y1 - area.y0);
    let mut transmittance = [1.0f32; TILE * TILE];
    let mut color = [[0.0f32; 3]; TILE * TILE];
    let mut distance = [0.0f32; TILE * TILE];
    let mut taken = [0u32; TILE * TILE];
    let mut live = w * h;
    for (place, &entry) in list.iter().enumerate() {
        let p = &projected[entry as u32 as usize];
        for y in span(p.row, p.radius, area.y0, area.y1) {
            let dy = y as f32 + 0.5 - p.row;
            for x in span(p.col, p.radius, area.x0, area.x1) {
                let k = (y - area.y0) * TILE + (x - area.x0);
                let t = transmittance[k];
                if t < SATURATED {
                    continue;
                }
                let Some((alpha, _)) = alpha_at(p, x as f32 + 0.5 - p.col, dy) else {
                    continue;
                };
                let weight = alpha * t;
                for (sum, c) in color[k].iter_mut().zip(p.color) {
                    *sum += weight * c;
                }
                distance[k] += weight * p.distance;
                transmittance[k] = t * (1.0 - alpha);
                taken[k] = place as u32 + 1;
                if transmittance[k] < SATURATED {
                    live -= 1;
                }
            }
        }
        if live == 0 {
            break;
        }
    }
    for y in 0..h {
        for x in 0..w {
            let k = y * TILE + x;
            let at = y * width + area.x0 + x;
            let t = transmittance[k];
            band.rgb[at] = std::array::from_fn(|c| color[k][c] + t * background[c]);
            band.depth[at] = distance[k];
            band.opacity[at] = 1.0 - t;
            band.taken[at] = taken[k];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
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
        }
    }

    /// A round splat at the center is the Gaussian its projection says: at its center, opacity · 1 (less
    /// the low-pass's widening); one standard deviation out, e^(−1/2) of that.
    #[test]
    fn one_splat_draws_its_projected_gaussian() {
        let (size, scale) = (64u32, 0.1f32);
        let camera = camera();
        let splats = one([0.0; 3], scale, 0.8, [1.0, 0.5, 0.0]);
        let (frame, stats) = render_splats(&splats, &camera, size, size, [0.0; 3]).unwrap();
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
        let (frame, _) = render_splats(&splats, &camera(), 32, 32, [1.0; 3]).unwrap();
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
            let (frame, stats) = render_splats(&splats, &camera(), 16, 8, [0.25, 0.5, 1.0]).unwrap();
            assert_eq!(stats.visible, 0);
            assert!(frame.rgb.iter().all(|p| *p == [0.25, 0.5, 1.0]));
        }
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
            };
            let (frame, _) = render_splats(&splats, &camera(), size as u32, size as u32, [0.0; 3]).unwrap();
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
