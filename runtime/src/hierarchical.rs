//! Volume rendering with hierarchical sampling: a coarse field at `linspace(near, far, samples)`,
//! then a fine field at those depths and `importance` more per ray drawn from the coarse weights
//! (at the centers of equal-probability bins: a deterministic render). The counterpart of
//! [`crate::train::volume_step_with`]. Samples are laid out ray-major here (ray k's samples at
//! `k·samples..`), so that each ray composites from contiguous slices.

use rayon::prelude::*;

use crate::camera::Camera;
use crate::composite::Samples;
use crate::error::{Error, Result};
use crate::field::BatchFn;
use crate::importance;
use crate::rays::RayBatch;
use crate::volume::{check_field, VolumeFrame, VolumeSettings};

/// Rays per parallel tile.
const TILE_RAYS: usize = 64;

/// The field's outputs (value, r, g, b) at depths `depths` (ray-major, `per_ray` each) of rays
/// `first..first + count` of `rays`.
fn evaluate(
    field: &dyn BatchFn,
    rays: &RayBatch,
    first: usize,
    depths: &[f32],
    per_ray: usize,
) -> [Vec<f32>; 4] {
    let len = depths.len();
    let mut inputs: [Vec<f32>; 6] = Default::default();
    for input in &mut inputs {
        input.reserve(len);
    }
    for (i, &t) in depths.iter().enumerate() {
        let r = first + i / per_ray;
        let o = [rays.ox[r], rays.oy[r], rays.oz[r]];
        let d = [rays.dx[r], rays.dy[r], rays.dz[r]];
        for c in 0..3 {
            inputs[c].push(o[c] + t * d[c]);
            inputs[3 + c].push(d[c]);
        }
    }
    let refs: Vec<&[f32]> = inputs[..field.n_inputs()].iter().map(Vec::as_slice).collect();
    let mut outputs: [Vec<f32>; 4] = std::array::from_fn(|_| vec![0.0; len]);
    let mut out_refs: Vec<&mut [f32]> = outputs.iter_mut().map(Vec::as_mut_slice).collect();
    field.eval(len, &refs, &mut out_refs);
    outputs
}

/// Renders a `width`×`height` image with hierarchical sampling (see the module docs).
pub fn render_hierarchical(
    camera: &Camera,
    width: u32,
    height: u32,
    coarse: &dyn BatchFn,
    fine: &dyn BatchFn,
    settings: &VolumeSettings,
    importance: usize,
) -> Result<VolumeFrame> {
    settings.check()?;
    check_field(coarse)?;
    check_field(fine)?;
    if importance == 0 {
        return Err(Error::Invalid(
            "hierarchical sampling needs at least one importance sample".into(),
        ));
    }
    let rays = RayBatch::full_image(camera, width, height)?;
    let m = settings.samples;
    let total = m + importance;
    let mut t = vec![0.0; m];
    settings.fixed_depths(&mut t);
    let mut u = Vec::new();
    importance::quantiles(importance, None, &mut u);
    let compositor = settings.compositor();
    let n = rays.len();
    let mut rgb = vec![[0.0f32; 3]; n];
    let mut depth = vec![0.0f32; n];
    let mut opacity = vec![0.0f32; n];
    rgb.par_chunks_mut(TILE_RAYS)
        .zip(depth.par_chunks_mut(TILE_RAYS))
        .zip(opacity.par_chunks_mut(TILE_RAYS))
        .enumerate()
        .for_each(|(tile, ((rgb, depth), opacity))| {
            let first = tile * TILE_RAYS;
            let count = rgb.len();
            let coarse_depths: Vec<f32> = (0..count).flat_map(|_| t.iter().copied()).collect();
            let [raw, ..] = evaluate(coarse, &rays, first, &coarse_depths, m);
            let mut fine_depths = vec![0.0; count * total];
            let (mut w, mut drawn) = (vec![0.0; m], vec![0.0; importance]);
            for k in 0..count {
                importance::ray_weights(&compositor, &t, &raw[k * m..(k + 1) * m], &mut w);
                importance::inverse_cdf(settings.near, settings.far, &t, &w, &u, &mut drawn);
                importance::merge_sorted(&t, &drawn, &mut fine_depths[k * total..(k + 1) * total]);
            }
            let [raw, r, g, b] = evaluate(fine, &rays, first, &fine_depths, total);
            for k in 0..count {
                let s = k * total..(k + 1) * total;
                let samples = Samples::new(
                    &fine_depths[s.clone()],
                    &raw[s.clone()],
                    [&r[s.clone()], &g[s.clone()], &b[s]],
                )
                .expect("equal lengths by construction");
                let out = compositor.forward(&samples);
                rgb[k] = out.rgb;
                depth[k] = out.depth;
                opacity[k] = out.opacity;
            }
        });
    Ok(VolumeFrame {
        width,
        height,
        rgb,
        depth,
        opacity,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::composite::Mode;
    use crate::field::ClosureFn;
    use crate::volume::render_volume;
    use glam::{Vec2, Vec3};

    /// A thin dense shell (density 400 within 0.005 of radius 0.8) in a faint halo (density 1 within
    /// 0.1), colored by position: uniform samples alias on the shell; the coarse pass sees the halo
    /// and the importance samples concentrate on the shell.
    fn shell() -> impl BatchFn {
        ClosureFn::new(3, 4, |p, out| {
            let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
            out[0] = match (r - 0.8).abs() {
                d if d < 0.005 => 400.0,
                d if d < 0.1 => 1.0,
                _ => 0.0,
            };
            for i in 0..3 {
                out[1 + i] = 0.5 + 0.5 * p[i].clamp(-1.0, 1.0);
            }
        })
    }

    fn mean_abs_difference(a: &VolumeFrame, b: &VolumeFrame) -> f32 {
        let sum: f32 = a
            .rgb
            .iter()
            .zip(&b.rgb)
            .map(|(x, y)| (0..3).map(|c| (x[c] - y[c]).abs()).sum::<f32>())
            .sum();
        sum / (3 * a.rgb.len()) as f32
    }

    #[test]
    fn importance_samples_recover_a_thin_shell_that_coarse_sampling_misses() {
        let camera = Camera::look_at(
            Vec3::new(0.3, 0.2, -3.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::splat(1.5),
            Vec2::ZERO,
        )
        .unwrap();
        let settings = |samples| VolumeSettings {
            spacing: crate::sampler::DepthSpacing::Linear,
            near: 1.0,
            far: 5.0,
            samples,
            mode: Mode::Density,
            background: None,
            early_termination: None,
        };
        let field = shell();
        let exact = render_volume(&camera, 24, 24, &field, &settings(4000)).unwrap();
        let coarse = render_volume(&camera, 24, 24, &field, &settings(96)).unwrap();
        let fine = render_hierarchical(&camera, 24, 24, &field, &field, &settings(32), 64).unwrap();
        let same = render_hierarchical(&camera, 24, 24, &field, &field, &settings(2000), 2000).unwrap();
        // With many samples the hierarchical render is the exact one (same rays, same compositing).
        assert!(
            mean_abs_difference(&same, &exact) < 2e-3,
            "{}",
            mean_abs_difference(&same, &exact)
        );
        let (coarse_error, fine_error) = (
            mean_abs_difference(&coarse, &exact),
            mean_abs_difference(&fine, &exact),
        );
        assert!(
            fine_error < 0.5 * coarse_error,
            "32 + 64 hierarchical samples: error {fine_error}; 96 uniform samples: {coarse_error}"
        );
    }
}
