//! Volume rendering of a field: samples along each pixel's ray, one field evaluation per
//! sample, composited by a [`Compositor`](crate::volume::composite::Compositor).
//!
//! The field maps a point (x, y, z), optionally followed by the unit view direction
//! (dx, dy, dz), to 4 outputs: density σ or opacity a (see [`Mode`](crate::volume::composite::Mode)), then r, g, b. Each ray
//! samples `linspace(near, far, samples)`.
//!
//! The image is cut into tiles of about [`TILE_POINTS`] sample points, rendered in parallel by the
//! volume pass that training runs too (`volume::pass`), with buffers allocated once per worker. A
//! tile evaluates its points sample-major in one field call and composites across rays, a loop that
//! vectorizes. With early termination, a tile goes [`CHUNK_SAMPLES`] samples at a time and drops the
//! rays that have stopped after each step, so that the field is only evaluated where it still matters.
//!
//! With an [`OccupancyGrid`] ([`render_volume_with`]), a sample whose point lies in an empty
//! cell (or outside the grid's bounds) is not evaluated and gets alpha = 0: it changes
//! neither the transmittance nor the outputs, whatever its color. Rays that miss the grid's
//! box (a slab test), or cross none of its marked blocks of 8³ cells, write the background without
//! any work; for the others, the samples between where the ray enters its first marked block and
//! leaves its last are looked up in the grid, the occupied
//! ones packed ray by ray into one dense field call per tile (or per round with early
//! termination), and each ray composites its own evaluated samples in order. As a grid leaves
//! few samples of a ray to evaluate, such a tile takes many more rays (up to
//! [`PACKED_TILE_RAYS`]) so that the field calls stay large, and with early termination each
//! call takes each live ray's next one to [`PACKED_CHUNK_SAMPLES`] occupied samples, so that few
//! samples past a ray's end are evaluated. Evaluated samples are at exactly the points and depths of the exact render and
//! composited with the same operations, so the result is, bit for bit, the exact render of the
//! field with its first output set to 0 in the empty cells (given finite colors): the two renders
//! differ only by what the skipped samples would have added. Note the course's last δ of
//! 1e10: in [`Mode::Density`](crate::volume::composite::Mode::Density) a last sample of tiny σ has alpha ≈ 1 and would take the
//! remaining transmittance; skipped, it contributes nothing.

use rayon::prelude::*;

use crate::cameras::camera::Camera;
use crate::error::{check_size, Error, Result};
use crate::field::BatchFn;
use crate::volume::composite::SharedDepths;
use crate::volume::occupancy::OccupancyGrid;
use crate::volume::pass::{self, with_scratch, Depths, Output, Pass, RayOutputs};
pub use crate::volume::settings::{
    VolumeSettings, CHUNK_SAMPLES, PACKED_CHUNK_SAMPLES, PACKED_TILE_RAYS, TILE_POINTS,
};

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
    check_field(field)?;
    let mut depths = vec![0.0; settings.samples];
    settings.fixed_depths(&mut depths);
    let deltas = pass::deltas(&depths);
    let shared = SharedDepths {
        t: &depths,
        delta: &deltas,
    };
    let pass = Pass {
        field,
        compositor: settings.compositor(),
        grid,
        samples: settings.samples,
    };
    // View-space x of each column's and y of each row's pixel centers.
    let xs: Vec<f32> = (0..width)
        .map(|col| camera.view_x(col as f32 + 0.5, width, height))
        .collect();
    let ys: Vec<f32> = (0..height)
        .map(|row| camera.view_y(row as f32 + 0.5, width, height))
        .collect();
    let origin = camera.position().to_array();
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
        .for_each(|(index, ((rgb, depth), opacity))| {
            let start = index * tile;
            with_scratch(|s| {
                // The tile's pixels in order, from its first one's row and column.
                let (mut row, mut col) = (start / xs.len(), start % xs.len());
                s.load_rays_from(origin, rgb.len(), |_| {
                    let d = camera.direction(xs[col], ys[row]).to_array();
                    col += 1;
                    if col == xs.len() {
                        (row, col) = (row + 1, 0);
                    }
                    d
                });
                let rays = RayOutputs { rgb, depth, opacity };
                pass::run(&pass, Depths::Shared(shared), s, Output::Rays(rays));
            });
        });
    Ok(frame)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::ClosureFn;
    use crate::volume::composite::Mode;
    use crate::volume::composite::Samples;
    use crate::volume::sampler::linspace;
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
