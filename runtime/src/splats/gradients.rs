//! The gradients of a splat frame's error against a target image with respect to every splat's
//! parameters, for fine-tuning a bake against the views it came from ([`splat_loss_gradients`]).
//!
//! The frame is drawn as [`render_splats`](super::render_splats) draws it, remembering how many of its
//! tile's splats each pixel took; each tile then walks its splats back to front, undoing the compositing
//! pixel by pixel (the transmittance before a splat is the one after it over 1 − alpha, and the color
//! behind it is carried along), as 3D Gaussian splatting's backward pass does. The derivatives with respect
//! to each splat's screen-space Gaussian (center, inverse covariance), opacity and color are summed per
//! splat, then carried through the projection to its center, scales and rotation.

use glam::{Mat3, Quat, Vec3};
use rayon::prelude::*;

use super::raster::{alpha_at, per_tile, span, Area, Projected, Screen, Viewer, MAX_ALPHA, TILE};

/// How many of a tile's splats the backward pass copies out at once.
const BATCH: usize = 32;
use super::shading::{ShaderBatch, SplatShader};
use super::Splats;
use crate::cameras::camera::Camera;
use crate::error::{Error, Result};

/// The derivatives of a loss with respect to each splat's parameters, one entry per splat (zero for those
/// the frame does not show).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SplatGradients {
    /// With respect to the centers.
    pub positions: Vec<[f32; 3]>,
    /// With respect to the colors.
    pub colors: Vec<[f32; 3]>,
    /// With respect to the opacities.
    pub opacities: Vec<f32>,
    /// With respect to the standard deviations along the rotated axes.
    pub scales: Vec<[f32; 3]>,
    /// With respect to the quaternions (w, x, y, z) as stored (they are normalized before use).
    pub rotations: Vec<[f32; 4]>,
    /// With respect to the degree-one spherical harmonics (empty when the splats have none).
    pub sh: Vec<[[f32; 3]; 3]>,
    /// Not a derivative: each splat's weight in the frame, the sum over its pixels of its alpha times the
    /// transmittance in front of it (in pixels; 0 for a splat the frame does not show). Fine-tuning drops
    /// splats that weigh next to nothing in every view.
    pub weights: Vec<f32>,
}

impl SplatGradients {
    /// Zero gradients for `n` splats (with spherical harmonics or not).
    fn zeros(n: usize, sh: bool) -> SplatGradients {
        SplatGradients {
            sh: vec![[[0.0; 3]; 3]; if sh { n } else { 0 }],
            positions: vec![[0.0; 3]; n],
            colors: vec![[0.0; 3]; n],
            opacities: vec![0.0; n],
            scales: vec![[0.0; 3]; n],
            rotations: vec![[0.0; 4]; n],
            weights: vec![0.0; n],
        }
    }
}

/// The derivatives of the loss with respect to one projected splat: its center's column and row, its
/// inverse covariance (a, b, c), its opacity and its color.
type ScreenGradient = [f32; 9];

/// The mean squared error of the `width`×`height` frame that `camera` sees of `splats` (colored by
/// `shader`) over `background` against `target` (its colors row by row), over every pixel and channel, and
/// its gradients.
pub fn splat_loss_gradients(
    splats: &Splats,
    shader: &dyn SplatShader,
    camera: &Camera,
    (width, height): (u32, u32),
    background: [f32; 3],
    target: &[[f32; 3]],
) -> Result<(f64, SplatGradients)> {
    let screen = Screen::of(splats, shader, camera, width, height)?;
    if target.len() != screen.width * screen.height {
        return Err(Error::Invalid(format!(
            "the target has {} pixels, the {width}×{height} frame {}",
            target.len(),
            screen.width * screen.height
        )));
    }
    let (frame, taken) = screen.draw(background);
    let scale = 2.0 / (3 * target.len()) as f32;
    let mut loss = 0.0f64;
    let d_color: Vec<[f32; 3]> = frame
        .rgb
        .iter()
        .zip(target)
        .map(|(c, t)| {
            std::array::from_fn(|k| {
                let e = c[k] - t[k];
                loss += f64::from(e * e);
                scale * e
            })
        })
        .collect();
    loss /= (3 * target.len()) as f64;

    // Each splat-tile pair's gradient, tile by tile in parallel, then summed per splat.
    let mut per_entry = vec![[0.0f32; 9]; screen.buffers.entries.len()];
    let mut entry_weights = vec![0.0f32; screen.buffers.entries.len()];
    let pixels = Pixels {
        transmittance: frame.opacity.iter().map(|o| 1.0 - o).collect(),
        taken,
        d_color,
        background,
    };
    let starts = &screen.buffers.starts;
    per_tile(&mut per_entry, starts)
        .into_par_iter()
        .zip(per_tile(&mut entry_weights, starts))
        .enumerate()
        .for_each(|(tile, out)| tile_gradients(&screen, tile, &pixels, out));
    let mut per_projected = vec![[0.0f32; 9]; screen.buffers.projected.len()];
    let mut weights = vec![0.0f32; screen.buffers.projected.len()];
    for ((entry, g), w) in screen.buffers.entries.iter().zip(&per_entry).zip(&entry_weights) {
        let sum = &mut per_projected[*entry as usize];
        for (s, x) in sum.iter_mut().zip(g) {
            *s += x;
        }
        weights[*entry as usize] += w;
    }

    let mut gradients = SplatGradients::zeros(splats.len(), !splats.sh.is_empty());
    let mut chained: Vec<(usize, SplatGradient)> = screen
        .buffers
        .projected
        .par_iter()
        .zip(&per_projected)
        .map(|(p, g)| (p.index as usize, chain(&screen.viewer, splats, p, g)))
        .collect();
    if !splats.sh.is_empty() {
        chained
            .par_chunks_mut(4096)
            .for_each(|chunk| shade_backward(&screen.viewer, splats, shader, chunk));
    }
    for (p, w) in screen.buffers.projected.iter().zip(weights) {
        gradients.weights[p.index as usize] = w;
    }
    for (i, g) in chained {
        gradients.positions[i] = g.position.into();
        gradients.colors[i] = g.color;
        if let Some(sh) = gradients.sh.get_mut(i) {
            *sh = g.sh;
        }
        gradients.opacities[i] = g.screen[5];
        gradients.scales[i] = g.scale.into();
        gradients.rotations[i] = g.rotation;
    }
    Ok((loss, gradients))
}

/// What the backward pass needs of each pixel of the drawn frame.
struct Pixels {
    /// The transmittance left after its splats.
    transmittance: Vec<f32>,
    /// How many of its tile's splats it took.
    taken: Vec<u32>,
    /// The loss's derivative with respect to its color.
    d_color: Vec<[f32; 3]>,
    background: [f32; 3],
}

/// The gradient of each of tile `tile`'s splats (`out.0[place]` for the splat at `place` in its list) and
/// its weight in the tile (`out.1[place]`), its pixels walked back to front.
fn tile_gradients(
    screen: &Screen,
    tile: usize,
    pixels: &Pixels,
    (out, weights): (&mut [ScreenGradient], &mut [f32]),
) {
    let (list, area) = screen.tile(tile);
    let mut tile_pixels = TileState {
        transmittance: [0.0; TILE * TILE],
        behind: [[0.0; 3]; TILE * TILE],
        d_color: [[0.0; 3]; TILE * TILE],
        taken: [0; TILE * TILE],
    };
    for y in area.y0..area.y1 {
        for x in area.x0..area.x1 {
            let (k, at) = ((y - area.y0) * TILE + (x - area.x0), y * screen.width + x);
            tile_pixels.transmittance[k] = pixels.transmittance[at];
            tile_pixels.behind[k] = pixels.background;
            tile_pixels.d_color[k] = pixels.d_color[at];
            tile_pixels.taken[k] = pixels.taken[at];
        }
    }
    // The splats after the last one any pixel took touched nothing (their gradients stay zero); the others
    // are copied out a batch at a time, as the frame was drawn, so that their reads overlap.
    let last = tile_pixels
        .taken
        .iter()
        .max()
        .map_or(0, |&t| t as usize)
        .min(list.len());
    let mut batch = [Projected::default(); BATCH];
    for first in (0..last).step_by(BATCH).rev() {
        let entries = &list[first..(first + BATCH).min(last)];
        for (copy, &entry) in batch.iter_mut().zip(entries) {
            *copy = screen.buffers.projected[entry as usize];
        }
        for (place, p) in (first..first + entries.len()).zip(&batch).rev() {
            splat_gradient(
                p,
                place,
                &area,
                &mut tile_pixels,
                (&mut out[place], &mut weights[place]),
            );
        }
    }
}

/// A tile's pixels as the backward pass walks them back to front: the transmittance before the splats
/// walked so far, the color behind them, the loss's derivative with respect to each pixel's color and how
/// many of the tile's splats it took.
struct TileState {
    transmittance: [f32; TILE * TILE],
    behind: [[f32; 3]; TILE * TILE],
    d_color: [[f32; 3]; TILE * TILE],
    taken: [u32; TILE * TILE],
}

/// Undoes splat `p` (the `place`th of its tile, whose pixels are `area`) over the pixels it reached, and
/// writes its gradient and its weight in the tile.
#[inline(always)]
fn splat_gradient(
    p: &Projected,
    place: usize,
    area: &Area,
    pixels: &mut TileState,
    (out, weight_out): (&mut ScreenGradient, &mut f32),
) {
    let TileState {
        transmittance,
        behind,
        d_color,
        taken,
    } = pixels;
    let mut g = [0.0f32; 9];
    let mut weight_sum = 0.0f32;
    for y in span(p.row, p.extent[1], area.y0, area.y1) {
        let dy = y as f32 + 0.5 - p.row;
        for x in span(p.col, p.extent[0], area.x0, area.x1) {
            let k = (y - area.y0) * TILE + (x - area.x0);
            if place as u32 >= taken[k] {
                continue;
            }
            let dx = x as f32 + 0.5 - p.col;
            let Some((alpha, gaussian)) = alpha_at(p, dx, dy) else {
                continue;
            };
            let before = transmittance[k] / (1.0 - alpha);
            let weight = alpha * before;
            weight_sum += weight;
            let mut d_alpha = 0.0;
            for c in 0..3 {
                g[6 + c] += weight * d_color[k][c];
                d_alpha += d_color[k][c] * (p.color[c] - behind[k][c]);
                behind[k][c] = alpha * p.color[c] + (1.0 - alpha) * behind[k][c];
            }
            d_alpha *= before;
            transmittance[k] = before;
            if p.opacity * gaussian < MAX_ALPHA {
                g[5] += d_alpha * gaussian;
                // power = −(a dx² + c dy²)/2 − b dx dy, dx = x + 0.5 − col, dy = y + 0.5 − row.
                let d_power = d_alpha * alpha;
                let [a, b, c] = p.conic;
                g[0] += d_power * (a * dx + b * dy);
                g[1] += d_power * (c * dy + b * dx);
                g[2] -= d_power * 0.5 * dx * dx;
                g[3] -= d_power * dx * dy;
                g[4] -= d_power * 0.5 * dy * dy;
            }
        }
    }
    *out = g;
    *weight_out = weight_sum;
}

/// One splat's gradient with respect to its own parameters.
struct SplatGradient {
    /// With respect to its screen-space Gaussian, opacity and color (as summed over the pixels).
    screen: ScreenGradient,
    position: Vec3,
    color: [f32; 3],
    sh: [[f32; 3]; 3],
    scale: Vec3,
    rotation: [f32; 4],
}

/// Carries the gradient `g` of projected splat `p` through its projection (see `Viewer::project`) to its
/// center, scales and rotation; its color's gradient is the one of the color it showed (which
/// [`shade_backward`] carries on through its shader, where it has one).
fn chain(viewer: &Viewer, splats: &Splats, p: &Projected, g: &ScreenGradient) -> SplatGradient {
    let i = p.index as usize;
    let offset = Vec3::from(splats.positions[i]) - viewer.position;
    let v = viewer.rotation * offset;
    let inv_z = 1.0 / v.z;
    let (fx, fy) = (viewer.fx, viewer.fy);
    let ((slope_x, free_x), (slope_y, free_y)) = viewer.slopes(v);
    let j_col = Vec3::new(-fx * inv_z, 0.0, fx * slope_x * inv_z);
    let j_row = Vec3::new(0.0, -fy * inv_z, fy * slope_y * inv_z);
    let [w, qx, qy, qz] = splats.rotations[i];
    let stored = glam::Vec4::new(w, qx, qy, qz);
    let unit = stored.normalize();
    let turn = Mat3::from_quat(Quat::from_xyzw(unit.y, unit.z, unit.w, unit.x));
    let s = Vec3::from(splats.scales[i]);
    let m = viewer.rotation * turn * Mat3::from_diagonal(s);
    let (t_col, t_row) = (m.transpose() * j_col, m.transpose() * j_row);

    // The inverse covariance Q = Σ⁻¹, Σ = [[a, b], [b, c]]: dL/dΣ = −Q (dL/dQ) Q, with dL/dQ's off-diagonal
    // entries half the derivative with respect to Q's b (which stands in both).
    let [qa, qb, qc] = p.conic;
    let (ga, gb, gc) = (g[2], 0.5 * g[3], g[4]);
    // (Q G) then (Q G Q), all symmetric 2×2.
    let (m00, m01, m10, m11) = (
        qa * ga + qb * gb,
        qa * gb + qb * gc,
        qb * ga + qc * gb,
        qb * gb + qc * gc,
    );
    let d_a = -(m00 * qa + m01 * qb);
    let d_c = -(m10 * qb + m11 * qc);
    let d_b = -2.0 * (m00 * qb + m01 * qc);

    // a = t_col·t_col + low-pass (a constant), b = t_col·t_row, c = t_row·t_row + low-pass.
    let d_t_col = 2.0 * d_a * t_col + d_b * t_row;
    let d_t_row = 2.0 * d_c * t_row + d_b * t_col;
    // t = Mᵀ j: dL/dM = j ⊗ dL/dt, dL/dj = M dL/dt.
    let outer = |j: Vec3, d: Vec3| Mat3::from_cols(j * d.x, j * d.y, j * d.z);
    let d_m = outer(j_col, d_t_col) + outer(j_row, d_t_row);
    let (d_j_col, d_j_row) = (m * d_t_col, m * d_t_row);

    // The view-space center: through the Jacobian's entries and the pixel position
    // (col = cx − fx·x/z, row = cy − fy·y/z, whose derivatives are the unclamped j_col and j_row). The
    // Jacobian's last entries are fx·s/z with the slope s = x/z, or a constant s where it is clamped.
    let mut d_v = Vec3::new(-fx * inv_z, 0.0, fx * v.x * inv_z * inv_z) * g[0]
        + Vec3::new(0.0, -fy * inv_z, fy * v.y * inv_z * inv_z) * g[1];
    let inv_z2 = inv_z * inv_z;
    let (free_x, free_y) = (f32::from(u8::from(free_x)), f32::from(u8::from(free_y)));
    d_v.x += d_j_col.z * fx * inv_z2 * free_x;
    d_v.y += d_j_row.z * fy * inv_z2 * free_y;
    d_v.z += d_j_col.x * fx * inv_z2 - d_j_col.z * fx * slope_x * inv_z2 * (1.0 + free_x);
    d_v.z += d_j_row.y * fy * inv_z2 - d_j_row.z * fy * slope_y * inv_z2 * (1.0 + free_y);
    let position = viewer.rotation.transpose() * d_v;

    // M = R_view · R_q · S.
    let d_n = viewer.rotation.transpose() * d_m;
    let scale = Vec3::new(
        turn.x_axis.dot(d_n.x_axis),
        turn.y_axis.dot(d_n.y_axis),
        turn.z_axis.dot(d_n.z_axis),
    );
    let d_turn = Mat3::from_cols(d_n.x_axis * s.x, d_n.y_axis * s.y, d_n.z_axis * s.z);
    let rotation = quaternion_gradient(unit, stored.length(), d_turn);
    SplatGradient {
        screen: *g,
        position,
        color: [g[6], g[7], g[8]],
        sh: [[0.0; 3]; 3],
        scale,
        rotation,
    }
}

/// Carries the gradients of splats with spherical harmonics from the colors they showed (`color`, as
/// [`chain`] leaves it) through `shader` to their base colors, coefficients and centers.
fn shade_backward(
    viewer: &Viewer,
    splats: &Splats,
    shader: &dyn SplatShader,
    chained: &mut [(usize, SplatGradient)],
) {
    let cotangents: Vec<[f32; 3]> = chained.iter().map(|(_, g)| g.color).collect();
    let shaded = ShaderBatch::with(|batch| {
        for (i, _) in chained.iter() {
            batch.push(&viewer.seen(splats, *i, splats.sh[*i]));
        }
        batch.gradients(shader, &cotangents)
    });
    for ((_, g), d) in chained.iter_mut().zip(shaded) {
        g.color = d.base;
        g.sh = d.sh;
        g.position += d.offset;
    }
}

/// The gradient with respect to a stored quaternion (w, x, y, z) of length `length`, whose unit quaternion
/// `unit` makes the rotation matrix R, given the gradient `d_r` with respect to R.
fn quaternion_gradient(unit: glam::Vec4, length: f32, d_r: Mat3) -> [f32; 4] {
    let (w, x, y, z) = (unit.x, unit.y, unit.z, unit.w);
    // G(i, k): row i, column k.
    let g = |i: usize, k: usize| d_r.col(k)[i];
    // R = [[1 − 2(y² + z²), 2(xy − wz), 2(xz + wy)],
    //      [2(xy + wz), 1 − 2(x² + z²), 2(yz − wx)],
    //      [2(xz − wy), 2(yz + wx), 1 − 2(x² + y²)]]
    let d_w = 2.0 * (-z * g(0, 1) + y * g(0, 2) + z * g(1, 0) - x * g(1, 2) - y * g(2, 0) + x * g(2, 1));
    let d_x = 2.0
        * (y * g(0, 1) + z * g(0, 2) + y * g(1, 0) - 2.0 * x * g(1, 1) - w * g(1, 2)
            + z * g(2, 0)
            + w * g(2, 1)
            - 2.0 * x * g(2, 2));
    let d_y = 2.0
        * (-2.0 * y * g(0, 0) + x * g(0, 1) + w * g(0, 2) + x * g(1, 0) + z * g(1, 2) - w * g(2, 0)
            + z * g(2, 1)
            - 2.0 * y * g(2, 2));
    let d_z = 2.0
        * (-2.0 * z * g(0, 0) - w * g(0, 1) + x * g(0, 2) + w * g(1, 0) - 2.0 * z * g(1, 1)
            + y * g(1, 2)
            + x * g(2, 0)
            + y * g(2, 1));
    // Through the normalization: (d − u (u·d)) / |q|.
    let d = glam::Vec4::new(d_w, d_x, d_y, d_z);
    ((d - unit * unit.dot(d)) / length).to_array()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splats::shading::formula::Formula;
    use crate::splats::{render_splats, SplatTuner, TuneRates};
    use glam::Vec2;

    const SIZE: u32 = 32;

    fn camera() -> Camera {
        Camera::look_at(
            Vec3::new(0.3, -0.2, -4.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::splat(2.0),
            Vec2::ZERO,
        )
        .unwrap()
    }

    /// Four overlapping splats, each stretched and turned its own way, none opaque enough to be clamped.
    fn scene() -> Splats {
        let turn = |angle: f32, axis: Vec3| {
            let q = Quat::from_axis_angle(axis.normalize(), angle);
            [q.w, q.x, q.y, q.z]
        };
        Splats {
            positions: vec![
                [0.1, 0.0, 0.0],
                [-0.3, 0.2, 0.4],
                [0.35, -0.25, -0.3],
                [0.0, 0.3, 0.8],
            ],
            colors: vec![[0.9, 0.2, 0.1], [0.1, 0.8, 0.3], [0.2, 0.3, 0.9], [0.7, 0.7, 0.2]],
            opacities: vec![0.7, 0.85, 0.5, 0.9],
            scales: vec![
                [0.35, 0.15, 0.2],
                [0.2, 0.4, 0.1],
                [0.25, 0.25, 0.12],
                [0.5, 0.3, 0.3],
            ],
            rotations: vec![
                turn(0.4, Vec3::new(0.0, 0.0, 1.0)),
                turn(-0.9, Vec3::new(1.0, 1.0, 0.0)),
                turn(1.3, Vec3::new(0.2, -1.0, 0.5)),
                turn(0.2, Vec3::new(1.0, 0.0, 0.3)),
            ],
            sh: Vec::new(),
        }
    }

    /// The scene with colors that change with the view (none clamped at this camera).
    fn shaded() -> Splats {
        let mut splats = scene();
        splats.sh = vec![
            [[0.1, -0.2, 0.05], [0.2, 0.1, -0.1], [-0.15, 0.1, 0.2]],
            [[-0.1, 0.05, 0.1], [0.0, -0.2, 0.1], [0.2, 0.1, -0.05]],
            [[0.15, 0.1, -0.1], [0.1, 0.1, 0.1], [-0.1, 0.0, 0.2]],
            [[0.05, -0.1, 0.1], [-0.1, 0.2, 0.1], [0.1, -0.15, 0.05]],
        ];
        splats
    }

    /// The scene and a fifth splat, long and beside the frame: its center lies beyond the frame's widened
    /// edge, where the projection's Jacobian is clamped, and its tail reaches into the frame.
    fn with_one_beside() -> Splats {
        let mut splats = scene();
        splats.positions.push([3.2, 0.1, 0.0]);
        splats.colors.push([0.3, 0.6, 0.9]);
        splats.opacities.push(0.8);
        splats.scales.push([1.2, 0.3, 0.25]);
        let q = Quat::from_axis_angle(Vec3::new(0.1, 0.2, 1.0).normalize(), 0.3);
        splats.rotations.push([q.w, q.x, q.y, q.z]);
        let screen = Screen::of(&splats, &Formula, &camera(), SIZE, SIZE).unwrap();
        let v = screen.viewer.rotation * (Vec3::from(splats.positions[4]) - screen.viewer.position);
        let ((_, free_x), (_, free_y)) = screen.viewer.slopes(v);
        assert!(!free_x && free_y, "the fifth splat's slope is not clamped");
        splats
    }

    /// A target image with some structure: a smooth ramp of colors.
    fn target() -> Vec<[f32; 3]> {
        (0..SIZE * SIZE)
            .map(|k| {
                let (x, y) = ((k % SIZE) as f32 / SIZE as f32, (k / SIZE) as f32 / SIZE as f32);
                [x, y, 1.0 - 0.5 * (x + y)]
            })
            .collect()
    }

    fn loss(splats: &Splats) -> f64 {
        let background = [1.0, 1.0, 1.0];
        splat_loss_gradients(splats, &Formula, &camera(), (SIZE, SIZE), background, &target())
            .unwrap()
            .0
    }

    /// Every parameter's derivative agrees with a difference of the loss (steps of 1e-4), to 1% of the largest
    /// of its kind. The loss is smooth but where a pixel crosses the edge of a splat's cut-off (alpha 1/255),
    /// where it jumps: a step of 1e-3 meets such an edge often enough to move a difference by 20%, and one
    /// splat here has a pixel within 5e-5 of it. So the steps are small, and the derivative must match the
    /// central difference or one of the one-sided ones (an edge lies on one side).
    #[test]
    fn gradients_match_finite_differences() {
        for splats in [scene(), with_one_beside(), shaded()] {
            gradients_match_differences(&splats);
        }
    }

    fn gradients_match_differences(splats: &Splats) {
        let (_, g) =
            splat_loss_gradients(splats, &Formula, &camera(), (SIZE, SIZE), [1.0; 3], &target()).unwrap();
        type Nudge = fn(&mut Splats, usize, usize, f32);
        let mut kinds: Vec<(&str, usize, Nudge, Vec<f32>)> = vec![
            (
                "position",
                3,
                |s, i, k, h| s.positions[i][k] += h,
                g.positions.concat(),
            ),
            ("color", 3, |s, i, k, h| s.colors[i][k] += h, g.colors.concat()),
            (
                "opacity",
                1,
                |s, i, _, h| s.opacities[i] += h,
                g.opacities.clone(),
            ),
            ("scale", 3, |s, i, k, h| s.scales[i][k] += h, g.scales.concat()),
            (
                "rotation",
                4,
                |s, i, k, h| s.rotations[i][k] += h,
                g.rotations.concat(),
            ),
        ];
        if !splats.sh.is_empty() {
            kinds.push((
                "sh",
                9,
                |s, i, k, h| s.sh[i][k / 3][k % 3] += h,
                g.sh.iter().flat_map(|h| h.concat()).collect(),
            ));
        }
        let h = 1e-4;
        for (name, width, nudge, analytic) in kinds {
            let largest = analytic.iter().fold(0.0f32, |m, x| m.max(x.abs()));
            assert!(largest > 1e-5, "{name}: no gradient at all");
            let last = &analytic[(splats.len() - 1) * width..];
            assert!(
                last.iter().any(|x| x.abs() > 0.0),
                "{name}: none for the last splat"
            );
            for i in 0..splats.len() {
                for k in 0..width {
                    let at = |h: f32| {
                        let mut s = splats.clone();
                        nudge(&mut s, i, k, h);
                        loss(&s)
                    };
                    let (below, here, above) = (at(-h), at(0.0), at(h));
                    let differences = [(above - below) / 2.0, above - here, here - below]
                        .map(|d| (d / f64::from(h)) as f32);
                    let exact = analytic[i * width + k];
                    assert!(
                        differences.iter().any(|d| (d - exact).abs() <= 0.01 * largest),
                        "{name} of splat {i}, component {k}: {exact} analytic, {differences:?} numeric (largest {largest})"
                    );
                }
            }
        }
    }

    /// The loss is the frame's mean squared error: the same frame as `render_splats` draws.
    #[test]
    fn the_loss_is_the_rendered_frames_error() {
        let splats = scene();
        let (frame, _) = render_splats(&splats, &Formula, &camera(), SIZE, SIZE, [1.0; 3]).unwrap();
        let error: f64 = frame
            .rgb
            .iter()
            .zip(target())
            .flat_map(|(c, t)| (0..3).map(move |k| f64::from(c[k] - t[k]).powi(2)))
            .sum::<f64>()
            / f64::from(3 * SIZE * SIZE);
        assert!(
            (loss(&splats) - error).abs() < 1e-9,
            "{} vs {error}",
            loss(&splats)
        );
    }

    /// Splats moved, recolored, resized and made fainter find their way back to the picture of where they
    /// were: Adam on these gradients brings the error down a hundredfold.
    /// The splats' weights share out the frame's opacity: their sum is the sum over pixels of 1 − the
    /// transmittance left, and a splat out of sight weighs nothing.
    #[test]
    fn the_weights_add_up_to_the_frames_opacity() {
        let mut splats = scene();
        splats.positions.push([0.0, 0.0, -10.0]);
        splats.colors.push([1.0; 3]);
        splats.opacities.push(0.9);
        splats.scales.push([0.2; 3]);
        splats.rotations.push([1.0, 0.0, 0.0, 0.0]);
        let (_, gradients) =
            splat_loss_gradients(&splats, &Formula, &camera(), (SIZE, SIZE), [1.0; 3], &target()).unwrap();
        let (frame, _) = render_splats(&splats, &Formula, &camera(), SIZE, SIZE, [1.0; 3]).unwrap();
        let opacity: f32 = frame.opacity.iter().sum();
        let weights: f32 = gradients.weights.iter().sum();
        assert!(opacity > 10.0, "{opacity}");
        assert!(
            (weights - opacity).abs() < 1e-4 * opacity,
            "{weights} vs {opacity}"
        );
        assert!(gradients.weights[..4].iter().all(|&w| w > 0.0));
        assert_eq!(gradients.weights[4], 0.0);
    }

    #[test]
    fn tuning_recovers_a_picture() {
        let truth = scene();
        let (picture, _) = render_splats(&truth, &Formula, &camera(), SIZE, SIZE, [1.0; 3]).unwrap();
        let mut splats = truth.clone();
        for i in 0..splats.len() {
            splats.positions[i][0] += 0.08;
            splats.colors[i] = [0.5; 3];
            splats.opacities[i] *= 0.6;
            splats.scales[i] = splats.scales[i].map(|s| s * 1.3);
        }
        let rates = TuneRates {
            position: 0.01,
            color: 0.02,
            opacity: 0.05,
            scale: 0.01,
            rotation: 0.01,
            sh: 0.01,
        };
        let mut tuner = SplatTuner::new(splats.len(), rates);
        let error = |s: &Splats| {
            splat_loss_gradients(s, &Formula, &camera(), (SIZE, SIZE), [1.0; 3], &picture.rgb)
                .unwrap()
                .0
        };
        let before = error(&splats);
        for _ in 0..300 {
            let (_, g) =
                splat_loss_gradients(&splats, &Formula, &camera(), (SIZE, SIZE), [1.0; 3], &picture.rgb)
                    .unwrap();
            tuner.step(&mut splats, &g, 1.0).unwrap();
        }
        splats.check().unwrap();
        let after = error(&splats);
        assert!(after < before / 100.0, "{before} → {after}");
    }

    #[test]
    fn a_target_of_the_wrong_size_is_refused() {
        let e = splat_loss_gradients(
            &scene(),
            &Formula,
            &camera(),
            (SIZE, SIZE),
            [1.0; 3],
            &[[0.0; 3]; 5],
        )
        .unwrap_err();
        assert!(e.to_string().contains("5 pixels"), "{e}");
    }
}
