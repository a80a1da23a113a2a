//! Stratified sampling of depths along rays.
//!
//! Between `near` and `far`, `n` depths per ray, either
//! - [`Spacing::Linspace`]: `linspace(near, far, n)` (both ends included), the course's
//!   renderer, or
//! - [`Spacing::Jittered`]: one uniform depth in each bin
//!   `[near + i·(far−near)/n, near + (i+1)·(far−near)/n)`, for training.
//!
//! Depths of several rays are stored row-major: ray `r`, sample `s` at `r·n + s`.

use crate::cameras::rays::RayBatch;
use crate::error::{Error, Result};
use crate::rng::Rng;

/// How depths are placed between `near` and `far`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Spacing {
    /// `linspace(near, far, n)`: the same depths on every ray, no randomness.
    Linspace,
    /// One uniform random depth in each of `n` equal bins of [near, far).
    Jittered,
}

/// How depths are distributed between `near` and `far` along a ray.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum DepthSpacing {
    /// Evenly in depth.
    #[default]
    Linear,
    /// Half the samples evenly in depth from `near` to `split`, half evenly in disparity (1/depth)
    /// from `split` to `far` (all in disparity when `split` ≤ `near`), as nerfstudio's
    /// piecewise sampler places them for unbounded scenes: dense near the object, sparse out to
    /// a far background.
    LinDisp {
        /// Depth where linear spacing gives way to disparity spacing.
        split: f32,
    },
}

impl DepthSpacing {
    /// Checks the spacing for the interval [near, far]: disparity spacing needs a positive start.
    pub fn check(self, near: f32, far: f32) -> Result<()> {
        match self {
            DepthSpacing::Linear => Ok(()),
            DepthSpacing::LinDisp { split } => {
                let start = split.max(near);
                if split.is_finite() && (start > 0.0 || split >= far) {
                    Ok(())
                } else {
                    Err(Error::Invalid(format!(
                        "disparity spacing from {start} to {far} needs a finite split and a start above 0"
                    )))
                }
            }
        }
    }

    /// The depth that replaces `t`, a depth of linear spacing in [near, far]: the identity for
    /// [`DepthSpacing::Linear`]; monotone and fixing near and far otherwise.
    pub fn warp(self, near: f32, far: f32, t: f32) -> f32 {
        let DepthSpacing::LinDisp { split } = self else {
            return t;
        };
        if split >= far {
            return t;
        }
        let u = ((t - near) / (far - near)).clamp(0.0, 1.0);
        // Disparities interpolated as (1 − v)/from + v/far, exact at both ends. Written as from plus a
        // share of far − from that grows with v, so that the depths stay in order where from and far are
        // a few units in the last place apart (the reciprocal of the sum of reciprocals rounds either way).
        let disparity = |from: f32, v: f32| {
            let share = from * v / ((1.0 - v) * far + v * from);
            from + (far - from) * share
        };
        let depth = if split <= near {
            disparity(near, u)
        } else if u <= 0.5 {
            near + 2.0 * u * (split - near)
        } else {
            disparity(split, 2.0 * u - 1.0)
        };
        depth.clamp(near, far)
    }

    /// Where depth `t` lies in [near, far] as the spacing spreads samples: 0 at near, 1 at far, and
    /// evenly spaced samples at evenly spaced values (the inverse of [`DepthSpacing::warp`], divided
    /// by far − near); mip-NeRF 360's normalized ray distance for the distortion loss.
    pub fn fraction(self, near: f32, far: f32, t: f32) -> f32 {
        let t = t.clamp(near, far);
        let linear = |from: f32, to: f32| (t - from) / (to - from);
        // The inverse of the disparity interpolation (1 − v)/from + v/far: v = (1/from − 1/t)/(1/from − 1/far),
        // written without the reciprocals' cancellation where from and far are close.
        let disparity = |from: f32| (t - from) / (far - from) * (far / t);
        let u = match self {
            DepthSpacing::LinDisp { split } if split < far => {
                if split <= near {
                    disparity(near)
                } else if t <= split {
                    0.5 * linear(near, split)
                } else {
                    0.5 + 0.5 * disparity(split)
                }
            }
            _ => linear(near, far),
        };
        u.clamp(0.0, 1.0)
    }

    /// [`DepthSpacing::warp`] applied to every depth of `depths`.
    pub fn warp_all(self, near: f32, far: f32, depths: &mut [f32]) {
        if self != DepthSpacing::Linear {
            for t in depths {
                *t = self.warp(near, far, *t);
            }
        }
    }
}

/// The interval [near, far] sampled on each ray.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DepthRange<'a> {
    /// The same interval for every ray.
    Uniform {
        /// Start of the interval.
        near: f32,
        /// End of the interval.
        far: f32,
    },
    /// One `[near, far]` per ray.
    PerRay(&'a [[f32; 2]]),
}

impl DepthRange<'_> {
    /// [near, far] of ray `i` (which [`DepthRange::check`] has checked to exist).
    fn of(&self, i: usize) -> (f32, f32) {
        match *self {
            DepthRange::Uniform { near, far } => (near, far),
            DepthRange::PerRay(ranges) => (ranges[i][0], ranges[i][1]),
        }
    }

    /// Checks that every interval is finite with near < far (near == far when `samples` is
    /// 1), and that there is one per ray of `n_rays`.
    fn check(&self, n_rays: usize, samples: usize) -> Result<()> {
        if samples == 0 {
            return Err(Error::Invalid("rays need at least 1 sample".into()));
        }
        let ok = |(near, far): (f32, f32)| {
            near.is_finite() && far.is_finite() && (near < far || (samples == 1 && near == far))
        };
        match *self {
            DepthRange::Uniform { near, far } if !ok((near, far)) => Err(Error::Invalid(format!(
                "sampling interval [{near}, {far}] must be finite with near < far"
            ))),
            DepthRange::PerRay(ranges) if ranges.len() != n_rays => Err(Error::Invalid(format!(
                "{} sampling intervals for {n_rays} rays",
                ranges.len()
            ))),
            DepthRange::PerRay(ranges) => match ranges.iter().position(|&[n, f]| !ok((n, f))) {
                Some(i) => Err(Error::Invalid(format!(
                    "sampling interval [{}, {}] of ray {i} must be finite with near < far",
                    ranges[i][0], ranges[i][1]
                ))),
                None => Ok(()),
            },
            DepthRange::Uniform { .. } => Ok(()),
        }
    }
}

/// Writes `linspace(near, far, out.len())` to `out`, computed as `torch.linspace` does
/// (from the start for the first half, from the end for the second).
pub(crate) fn linspace(near: f32, far: f32, out: &mut [f32]) {
    let n = out.len();
    if n == 1 {
        out[0] = near;
        return;
    }
    let step = (far - near) / (n - 1) as f32;
    let half = n / 2;
    for (i, t) in out.iter_mut().enumerate() {
        *t = if i < half {
            near + step * i as f32
        } else {
            far - step * (n - 1 - i) as f32
        };
    }
}

/// The depth at fraction `u` (in [0, 1)) of bin `i` of width `bin` from `near`, kept inside
/// the bin despite rounding.
pub(crate) fn jittered_depth(near: f32, bin: f32, i: usize, u: f32) -> f32 {
    let edge = near + (i + 1) as f32 * bin;
    (near + (i as f32 + u) * bin).min(edge.next_down())
}

/// Writes one uniform depth in each of `out.len()` equal bins of [near, far) to `out`.
fn jittered(near: f32, far: f32, rng: &mut Rng, out: &mut [f32]) {
    let bin = (far - near) / out.len() as f32;
    for (i, t) in out.iter_mut().enumerate() {
        *t = jittered_depth(near, bin, i, rng.next_f32());
    }
}

/// Fills `out` (length `rays·samples`, row-major) with the depths of the rays of `range`.
/// Assumes `range` was checked.
fn fill_depths(range: &DepthRange, samples: usize, spacing: Spacing, rng: &mut Rng, out: &mut [f32]) {
    for (k, ray) in out.chunks_exact_mut(samples).enumerate() {
        let (near, far) = range.of(k);
        match spacing {
            Spacing::Linspace => linspace(near, far, ray),
            Spacing::Jittered => jittered(near, far, rng, ray),
        }
    }
}

/// The depths of `n_rays` rays, `samples` each (row-major rays × samples). `rng` is drawn from
/// only for [`Spacing::Jittered`].
pub fn sample_depths(
    n_rays: usize,
    range: &DepthRange,
    samples: usize,
    spacing: Spacing,
    rng: &mut Rng,
) -> Result<Vec<f32>> {
    range.check(n_rays, samples)?;
    let mut depths = vec![0.0; n_rays * samples];
    fill_depths(range, samples, spacing, rng, &mut depths);
    Ok(depths)
}

/// Writes the points `o + t·d` of the rays of `rays` at `depths` (row-major, `samples` per
/// ray) to `x`, `y`, `z` (each as long as `depths`). Assumes the lengths were checked.
fn fill_points(rays: &RayBatch, samples: usize, depths: &[f32], [x, y, z]: [&mut [f32]; 3]) {
    let rows = depths.chunks_exact(samples).zip(x.chunks_exact_mut(samples));
    let rows = rows
        .zip(y.chunks_exact_mut(samples))
        .zip(z.chunks_exact_mut(samples));
    for (r, (((t, x), y), z)) in rows.enumerate() {
        let (ox, oy, oz) = (rays.ox[r], rays.oy[r], rays.oz[r]);
        let (dx, dy, dz) = (rays.dx[r], rays.dy[r], rays.dz[r]);
        for (((t, x), y), z) in t.iter().zip(x).zip(y.iter_mut()).zip(z.iter_mut()) {
            *x = ox + dx * t;
            *y = oy + dy * t;
            *z = oz + dz * t;
        }
    }
}

/// The sample points of all rays of `rays` at `depths` (row-major rays × `samples`, e.g. from
/// [`sample_depths`]) in structure-of-arrays layout `[x, y, z]`.
pub fn sample_points(rays: &RayBatch, depths: &[f32], samples: usize) -> Result<[Vec<f32>; 3]> {
    rays.check()?;
    if samples == 0 || depths.len() != rays.len() * samples {
        return Err(Error::Invalid(format!(
            "{} depths are not {samples} per ray for {} rays",
            depths.len(),
            rays.len()
        )));
    }
    let mut points = [
        vec![0.0; depths.len()],
        vec![0.0; depths.len()],
        vec![0.0; depths.len()],
    ];
    let [x, y, z] = &mut points;
    fill_points(rays, samples, depths, [x, y, z]);
    Ok(points)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cameras::camera::Camera;
    use glam::{Vec2, Vec3};

    #[test]
    fn linspace_matches_the_course_sampler() {
        let d = sample_depths(
            2,
            &DepthRange::Uniform { near: 0.0, far: 5.0 },
            64,
            Spacing::Linspace,
            &mut Rng::new(1),
        )
        .unwrap();
        assert_eq!(d.len(), 128);
        assert_eq!((d[0], d[63], d[64], d[127]), (0.0, 5.0, 0.0, 5.0));
        for (i, t) in d[..64].iter().enumerate() {
            assert!((t - 5.0 * i as f32 / 63.0).abs() < 1e-6, "{i}: {t}");
        }
        assert_eq!(d[..64], d[64..]);
        let one = sample_depths(
            1,
            &DepthRange::Uniform { near: 2.0, far: 2.0 },
            1,
            Spacing::Linspace,
            &mut Rng::new(1),
        );
        assert_eq!(one.unwrap(), vec![2.0]);
    }

    #[test]
    fn jitter_puts_one_seeded_depth_in_each_bin() {
        let ranges = [[1.0, 3.0], [0.0, 0.8], [2.0, 6.0]];
        let range = DepthRange::PerRay(&ranges);
        let d = sample_depths(3, &range, 16, Spacing::Jittered, &mut Rng::new(9)).unwrap();
        for (ray, [near, far]) in d.chunks(16).zip(ranges) {
            let bin = (far - near) / 16.0;
            for (i, t) in ray.iter().enumerate() {
                let lo = near + i as f32 * bin;
                assert!(
                    *t >= lo - 1e-6 && *t < lo + bin,
                    "bin {i}: {t} not in [{lo}, {})",
                    lo + bin
                );
            }
        }
        assert_eq!(
            d,
            sample_depths(3, &range, 16, Spacing::Jittered, &mut Rng::new(9)).unwrap()
        );
        assert_ne!(
            d,
            sample_depths(3, &range, 16, Spacing::Jittered, &mut Rng::new(10)).unwrap()
        );
        // Over many rays, jitter covers each bin evenly (mean offset 1/2 of a bin).
        let range = DepthRange::Uniform { near: 0.0, far: 1.0 };
        let d = sample_depths(2000, &range, 4, Spacing::Jittered, &mut Rng::new(3)).unwrap();
        for i in 0..4 {
            let mean: f32 = d
                .iter()
                .skip(i)
                .step_by(4)
                .map(|t| t * 4.0 - i as f32)
                .sum::<f32>()
                / 2000.0;
            assert!((mean - 0.5).abs() < 0.03, "bin {i}: mean offset {mean}");
        }
    }

    proptest::proptest! {
        #[test]
        fn lindisp_spacing_is_monotone_and_keeps_the_ends(
            near in 0.0f32..3.0,
            length in 0.1f32..1000.0,
            split_at in -0.5f32..1.5,
            n in 2usize..200,
        ) {
            let far = near + length;
            let spacing = DepthSpacing::LinDisp { split: near + split_at * length };
            proptest::prop_assume!(spacing.check(near, far).is_ok());
            let mut t = vec![0.0; n];
            linspace(near, far, &mut t);
            spacing.warp_all(near, far, &mut t);
            proptest::prop_assert!((t[0] - near).abs() <= 1e-5 * far && (t[n - 1] - far).abs() <= 1e-4 * far);
            for w in t.windows(2) {
                proptest::prop_assert!(w[0] <= w[1], "{t:?}");
            }
        }

        #[test]
        fn fraction_inverts_the_warp(
            near in 0.01f32..3.0,
            length in 0.1f32..1000.0,
            split_at in -0.5f32..1.5,
            u in 0.0f32..1.0,
        ) {
            let far = near + length;
            for spacing in [DepthSpacing::Linear, DepthSpacing::LinDisp { split: near + split_at * length }] {
                proptest::prop_assume!(spacing.check(near, far).is_ok());
                let t = spacing.warp(near, far, near + u * length);
                let back = spacing.fraction(near, far, t);
                // The warp's f32 rounding of a depth near far is amplified where disparity spacing is coarse,
                // and a half of the samples that spans a few units in the last place (a split next to near or
                // far) holds only that many depths: u comes back to within a half of its width's ulps.
                let halves = match spacing {
                    DepthSpacing::LinDisp { split } if split > near && split < far => (split - near).min(far - split),
                    _ => length,
                };
                let tolerance = 1e-4 + 2e-6 * far / near + 2.0 * f32::EPSILON * far / halves;
                proptest::prop_assert!((back - u).abs() <= tolerance, "{spacing:?}: {u} -> {t} -> {back}");
            }
        }
    }

    #[test]
    fn lindisp_spacing_is_linear_then_even_in_disparity() {
        let spacing = DepthSpacing::LinDisp { split: 4.0 };
        let mut t = vec![0.0; 9];
        linspace(2.0, 100.0, &mut t);
        spacing.warp_all(2.0, 100.0, &mut t);
        for (i, want) in [2.0, 2.5, 3.0, 3.5, 4.0].iter().enumerate() {
            assert!((t[i] - want).abs() < 1e-5, "{t:?}");
        }
        // Disparities from 1/4 to 1/100 in equal steps.
        for (i, t) in t[4..].iter().enumerate() {
            let want = 1.0 / (0.25 + i as f32 / 4.0 * (0.01 - 0.25));
            assert!((t - want).abs() < 1e-3 * want, "{i}: {t} vs {want}");
        }
        assert_eq!(DepthSpacing::Linear.warp(0.0, 5.0, 1.25), 1.25);
        assert!(DepthSpacing::LinDisp { split: 0.0 }.check(0.0, 5.0).is_err());
        assert!(DepthSpacing::LinDisp { split: 0.0 }.check(0.5, 5.0).is_ok());
    }

    #[test]
    fn points_lie_on_their_rays() {
        let cam = Camera::look_at(
            Vec3::new(0.0, 1.0, -3.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::ONE,
            Vec2::ZERO,
        )
        .unwrap();
        let rays = RayBatch::full_image(&cam, 3, 2).unwrap();
        let range = DepthRange::Uniform { near: 1.0, far: 4.0 };
        let depths = sample_depths(rays.len(), &range, 5, Spacing::Jittered, &mut Rng::new(2)).unwrap();
        let [x, y, z] = sample_points(&rays, &depths, 5).unwrap();
        for r in 0..rays.len() {
            let (o, d) = rays.ray(r).unwrap();
            for s in 0..5 {
                let k = r * 5 + s;
                let p = o + d * depths[k];
                assert!(Vec3::new(x[k], y[k], z[k]).abs_diff_eq(p, 1e-6));
            }
        }
        assert!(sample_points(&rays, &depths, 4).is_err());
        assert!(sample_points(&rays, &depths, 0).is_err());
    }

    #[test]
    fn bad_ranges_are_errors() {
        let mut rng = Rng::new(0);
        let bad = [
            (DepthRange::Uniform { near: 2.0, far: 1.0 }, 4, "near < far"),
            (
                DepthRange::Uniform {
                    near: 0.0,
                    far: f32::INFINITY,
                },
                4,
                "finite",
            ),
            (
                DepthRange::Uniform { near: 0.0, far: 1.0 },
                0,
                "at least 1 sample",
            ),
            (
                DepthRange::PerRay(&[[0.0, 1.0]]),
                4,
                "1 sampling intervals for 2 rays",
            ),
            (DepthRange::PerRay(&[[0.0, 1.0], [1.0, 1.0]]), 4, "of ray 1"),
        ];
        for (range, samples, message) in bad {
            let e = sample_depths(2, &range, samples, Spacing::Linspace, &mut rng)
                .unwrap_err()
                .to_string();
            assert!(e.contains(message), "{e}");
        }
    }
}
