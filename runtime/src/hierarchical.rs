//! Volume rendering with hierarchical sampling: a coarse field at `linspace(near, far, samples)`,
//! then a fine field at those depths and `importance` more per ray drawn from the coarse weights
//! (at the centers of equal-probability bins: a deterministic render). With an occupancy grid, both
//! passes evaluate only the samples in its occupied cells (the others are empty space, so no
//! importance sample is drawn there either). The counterpart of
//! [`crate::train::volume_step_with`]. Samples are laid out ray-major here (ray k's samples at
//! `k·samples..`), so that each ray composites from contiguous slices.

use rayon::prelude::*;

use crate::camera::Camera;
use crate::composite::Samples;
use crate::error::{Error, Result};
use crate::field::BatchFn;
use crate::importance;
use crate::occupancy::OccupancyGrid;
use crate::rays::RayBatch;
use crate::volume::{check_field, VolumeFrame, VolumeSettings};

/// Rays per parallel tile.
const TILE_RAYS: usize = 64;

/// The field's outputs (value, r, g, b) at depths `depths` (ray-major, `per_ray` each) of rays
/// `first..first + count` of `rays`; with a `grid`, only the points in its occupied cells are
/// evaluated, and the others are empty space (all outputs 0).
fn evaluate(
    field: &dyn BatchFn,
    rays: &RayBatch,
    first: usize,
    depths: &[f32],
    per_ray: usize,
    grid: Option<&OccupancyGrid>,
) -> [Vec<f32>; 4] {
    let len = depths.len();
    let mut inputs: [Vec<f32>; 6] = Default::default();
    for input in &mut inputs {
        input.reserve(len);
    }
    // Which samples are evaluated (all without a grid), in order.
    let mut kept = Vec::with_capacity(len);
    for (i, &t) in depths.iter().enumerate() {
        let r = first + i / per_ray;
        let o = [rays.ox[r], rays.oy[r], rays.oz[r]];
        let d = [rays.dx[r], rays.dy[r], rays.dz[r]];
        let p = [0, 1, 2].map(|c| o[c] + t * d[c]);
        if grid.is_some_and(|g| !g.occupied(p)) {
            continue;
        }
        kept.push(i);
        for c in 0..3 {
            inputs[c].push(p[c]);
            inputs[3 + c].push(d[c]);
        }
    }
    let n = kept.len();
    let refs: Vec<&[f32]> = inputs[..field.n_inputs()].iter().map(Vec::as_slice).collect();
    let mut packed: [Vec<f32>; 4] = std::array::from_fn(|_| vec![0.0; n]);
    let mut out_refs: Vec<&mut [f32]> = packed.iter_mut().map(Vec::as_mut_slice).collect();
    if n > 0 {
        field.eval(n, &refs, &mut out_refs);
    }
    if n == len {
        return packed;
    }
    let mut outputs: [Vec<f32>; 4] = std::array::from_fn(|_| vec![0.0; len]);
    for (output, values) in outputs.iter_mut().zip(&packed) {
        for (&i, &v) in kept.iter().zip(values) {
            output[i] = v;
        }
    }
    outputs
}

/// The two fields of hierarchical sampling and the importance samples drawn per ray.
#[derive(Clone, Copy)]
pub struct CoarseFine<'a> {
    /// Sampled at the fixed depths; its weights place the importance samples.
    pub coarse: &'a dyn BatchFn,
    /// Sampled at the fixed depths and the importance samples; it makes the image.
    pub fine: &'a dyn BatchFn,
    /// Importance samples per ray (at least 1).
    pub importance: usize,
}

/// Renders a `width`×`height` image with hierarchical sampling (see the module docs), skipping the
/// cells `grid` marks empty when given.
pub fn render_hierarchical(
    camera: &Camera,
    (width, height): (u32, u32),
    fields: CoarseFine,
    settings: &VolumeSettings,
    grid: Option<&OccupancyGrid>,
) -> Result<VolumeFrame> {
    let CoarseFine {
        coarse,
        fine,
        importance,
    } = fields;
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
            let [raw, ..] = evaluate(coarse, &rays, first, &coarse_depths, m, grid);
            let mut fine_depths = vec![0.0; count * total];
            let (mut w, mut drawn) = (vec![0.0; m], vec![0.0; importance]);
            for k in 0..count {
                importance::ray_weights(&compositor, &t, &raw[k * m..(k + 1) * m], &mut w);
                importance::inverse_cdf(settings.near, settings.far, &t, &w, &u, &mut drawn);
                importance::merge_sorted(&t, &drawn, &mut fine_depths[k * total..(k + 1) * total]);
            }
            let [raw, r, g, b] = evaluate(fine, &rays, first, &fine_depths, total, grid);
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

    fn camera() -> Camera {
        Camera::look_at(
            Vec3::new(0.3, 0.2, -3.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::splat(1.5),
            Vec2::ZERO,
        )
        .unwrap()
    }

    fn settings(samples: usize) -> VolumeSettings {
        VolumeSettings {
            spacing: crate::sampler::DepthSpacing::Linear,
            near: 1.0,
            far: 5.0,
            samples,
            mode: Mode::Density,
            background: Some([0.2, 0.3, 0.4]),
            early_termination: None,
        }
    }

    /// `field` as both fields of hierarchical sampling.
    fn twice(field: &dyn BatchFn, importance: usize) -> CoarseFine<'_> {
        CoarseFine {
            coarse: field,
            fine: field,
            importance,
        }
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
        let camera = camera();
        let field = shell();
        let exact = render_volume(&camera, 24, 24, &field, &settings(4000)).unwrap();
        let coarse = render_volume(&camera, 24, 24, &field, &settings(96)).unwrap();
        let fine = render_hierarchical(&camera, (24, 24), twice(&field, 64), &settings(32), None).unwrap();
        let same =
            render_hierarchical(&camera, (24, 24), twice(&field, 2000), &settings(2000), None).unwrap();
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

    #[test]
    fn an_occupancy_grid_skips_empty_space_and_changes_nothing() {
        let camera = camera();
        let settings = settings(32);
        let evaluated = std::sync::atomic::AtomicUsize::new(0);
        let inner = shell();
        let counted = ClosureFn::new(3, 4, |p, out| {
            evaluated.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            inner.eval(
                1,
                &[&p[0..1], &p[1..2], &p[2..3]],
                &mut out.iter_mut().map(std::slice::from_mut).collect::<Vec<_>>(),
            );
        });
        let grid = OccupancyGrid::build(&inner, ([-1.2; 3], [1.2; 3]), 48, Mode::Density, 0.0).unwrap();
        assert!(grid.occupancy() < 0.6, "{}", grid.occupancy());
        let exact = render_hierarchical(&camera, (24, 24), twice(&counted, 64), &settings, None).unwrap();
        let all = evaluated.swap(0, std::sync::atomic::Ordering::Relaxed);
        let skipping =
            render_hierarchical(&camera, (24, 24), twice(&counted, 64), &settings, Some(&grid)).unwrap();
        let some = evaluated.load(std::sync::atomic::Ordering::Relaxed);
        assert_eq!(all, 24 * 24 * (32 + 32 + 64));
        assert!(some * 2 < all, "{some} of {all} samples evaluated");
        assert_eq!(skipping.rgb, exact.rgb);
        assert_eq!(skipping.opacity, exact.opacity);
        assert_eq!(skipping.depth, exact.depth);
    }
}
