//! Volume rendering with hierarchical sampling: a coarse field at `linspace(near, far, samples)`,
//! then a fine field at those depths and `importance` more per ray drawn from the coarse weights
//! (at the centers of equal-probability bins: a deterministic render). Both passes are the volume
//! pass of renders and training (`volume::pass`), tile by tile of rays: with an occupancy grid they
//! evaluate only the samples in its occupied cells (the others are empty space, so no importance
//! sample is drawn there either); with early termination, both evaluate a few depths at a time for
//! the rays whose transmittance is still above the threshold (the coarse samples past a ray's end are
//! empty space to the importance sampling, as in training). The coarse pass keeps its samples (the
//! coarse values at every depth); the fine pass composites each ray. The render of what
//! [`crate::volume::train::volume_step_with`] trains.

use rayon::prelude::*;

use crate::cameras::camera::Camera;
use crate::cameras::rays::RayBatch;
use crate::error::{Error, Result};
use crate::field::BatchFn;
use crate::volume::composite::SharedDepths;
use crate::volume::occupancy::OccupancyGrid;
use crate::volume::pass::{self, with_scratch, Depths, Output, Pass, RayOutputs};
use crate::volume::render::{check_field, VolumeFrame, VolumeSettings};

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
    let mut fixed = vec![0.0; m];
    settings.fixed_depths(&mut fixed);
    let deltas = pass::deltas(&fixed);
    let shared = SharedDepths {
        t: &fixed,
        delta: &deltas,
    };
    let fine_settings = VolumeSettings {
        samples: m + importance,
        ..*settings
    };
    let coarse_pass = Pass {
        field: coarse,
        compositor: settings.compositor(),
        grid,
        samples: m,
    };
    let fine_pass = Pass {
        field: fine,
        samples: fine_settings.samples,
        ..coarse_pass
    };
    let tile = settings.rays_per_tile();
    let pixels = rays.len();
    let mut rgb = vec![[0.0f32; 3]; pixels];
    let mut depth = vec![0.0f32; pixels];
    let mut opacity = vec![0.0f32; pixels];
    rgb.par_chunks_mut(tile)
        .zip(depth.par_chunks_mut(tile))
        .zip(opacity.par_chunks_mut(tile))
        .enumerate()
        .for_each(|(index, ((rgb, depth), opacity))| {
            with_scratch(|s| {
                let (first, n) = (index * tile, rgb.len());
                s.reserve(n * fine_settings.samples, n);
                for (row, &t) in s.depths[..n * m].chunks_exact_mut(n).zip(&fixed) {
                    row.fill(t);
                }
                s.load_rays(&rays, first, n);
                pass::run(&coarse_pass, Depths::Shared(shared), s, Output::Samples);
                pass::draw_fine_depths(settings, importance, s, n, None);
                s.load_rays(&rays, first, n);
                let rays = RayOutputs { rgb, depth, opacity };
                pass::run(&fine_pass, Depths::PerRay, s, Output::Rays(rays));
            })
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
    use crate::field::ClosureFn;
    use crate::volume::composite::Mode;
    use crate::volume::render::render_volume;
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
            spacing: crate::volume::sampler::DepthSpacing::Linear,
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

    #[test]
    fn early_termination_evaluates_fewer_fine_samples_and_stops_rays_where_the_threshold_says() {
        let camera = camera();
        let evaluated = std::sync::atomic::AtomicUsize::new(0);
        // An opaque ball filling most of the view (density 50 inside radius 1.4).
        let counted = ClosureFn::new(3, 4, |p, out| {
            evaluated.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
            out[0] = if r < 1.4 { 50.0 } else { 0.0 };
            for i in 0..3 {
                out[1 + i] = 0.5 + 0.5 * p[i].clamp(-1.0, 1.0);
            }
        });
        let render = |threshold: Option<f32>| {
            let settings = VolumeSettings {
                early_termination: threshold,
                ..settings(32)
            };
            let frame = render_hierarchical(&camera, (24, 24), twice(&counted, 96), &settings, None).unwrap();
            (frame, evaluated.swap(0, std::sync::atomic::Ordering::Relaxed))
        };
        let (exact, all) = render(None);
        // Evaluating run by run changes nothing while no ray stops.
        let (unstopped, _) = render(Some(1e-30));
        assert_eq!(unstopped.rgb, exact.rgb);
        assert_eq!(unstopped.depth, exact.depth);
        let (stopped, some) = render(Some(1e-2));
        // The importance samples crowd where rays end, so few are left behind them: 89.6% evaluated.
        assert!(some * 100 < all * 95, "{some} of {all} samples evaluated");
        let worst = exact
            .rgb
            .iter()
            .zip(&stopped.rgb)
            .flat_map(|(a, b)| (0..3).map(move |c| (a[c] - b[c]).abs()))
            .fold(0.0f32, f32::max);
        // A stopped ray loses at most its remaining transmittance (< 0.01) times a color and the
        // background (each ≤ 1).
        assert!(worst < 0.02, "largest change {worst}");
    }
}
