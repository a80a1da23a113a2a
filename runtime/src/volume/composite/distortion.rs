//! mip-NeRF 360's distortion loss on the compositing weights: its setting, and each sample's ∂L/∂w for
//! the compositor's sweep back.

use crate::volume::sampler::DepthSpacing;

/// mip-NeRF 360's distortion loss on a ray's compositing weights, added to a training step's loss:
/// with each sample's interval [sᵢ, sᵢ₊₁] in normalized ray distance s (0 at `near`, 1 at `far`, as
/// the spacing spreads the samples: [`DepthSpacing::fraction`]; the last sample's interval ends at
/// `far`) and mᵢ its midpoint,
/// L = Σᵢ Σⱼ wᵢwⱼ|mᵢ − mⱼ| + ⅓ Σᵢ wᵢ²(sᵢ₊₁ − sᵢ).
/// It is small when a ray's weight gathers in one short stretch and large when it is spread along the
/// ray (fog, floaters). Its gradient joins the colour loss's in the compositor's one sweep back:
/// ∂L/∂wᵢ = 2 Σⱼ wⱼ|mᵢ − mⱼ| + ⅔ wᵢ(sᵢ₊₁ − sᵢ) is added to the sample's value vᵢ.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Distortion {
    /// What each ray's L is multiplied by in the loss.
    pub weight: f32,
    /// Where s is 0.
    pub near: f32,
    /// Where s is 1.
    pub far: f32,
    /// How the samples are spread between near and far.
    pub spacing: DepthSpacing,
}

/// What [`distortion_values`] works in: per sample (sample-major) the normalized distance s and
/// ∂L/∂w; per ray the weights' sum and their sum times the intervals' midpoints, over the whole ray
/// and over the samples before the current one.
#[derive(Debug, Default)]
pub(super) struct DistortionScratch {
    pub(super) fraction: Vec<f32>,
    pub(super) values: Vec<f32>,
    pub(super) totals: [Vec<f32>; 2],
    pub(super) before: [Vec<f32>; 2],
}

/// Fills `scratch.values` with each sample's ∂L/∂w of the distortion loss `d` (times its weight) of `n`
/// rays whose samples have depths `t` and, from the forward pass, transmittances `trans` (0 past a
/// ray's stop) and alphas `alpha`, all sample-major. Returns the rays' summed loss (times its weight).
pub(super) fn distortion_values(
    d: &Distortion,
    n: usize,
    t: &[f32],
    (trans, alpha): (&[f32], &[f32]),
    scratch: &mut DistortionScratch,
) -> f64 {
    let len = t.len();
    let rows = len / n;
    let DistortionScratch {
        fraction,
        values,
        totals: [total_w, total_wm],
        before: [before_w, before_wm],
    } = scratch;
    fraction.clear();
    fraction.extend(t.iter().map(|&t| d.spacing.fraction(d.near, d.far, t)));
    values.resize(len, 0.0);
    for v in [&mut *total_w, total_wm, before_w, before_wm] {
        v.clear();
        v.resize(n, 0.0);
    }
    // Sample i's weight, interval midpoint and length.
    let sample = |i: usize, j: usize| {
        let (start, end) = (fraction[i], if j + 1 < rows { fraction[i + n] } else { 1.0 });
        (trans[i] * alpha[i], 0.5 * (start + end), end - start)
    };
    for j in 0..rows {
        for k in 0..n {
            let (w, m, _) = sample(j * n + k, j);
            total_w[k] += w;
            total_wm[k] += w * m;
        }
    }
    let mut loss = 0.0f32;
    for j in 0..rows {
        for k in 0..n {
            let i = j * n + k;
            let (w, m, length) = sample(i, j);
            let (w_after, wm_after) = (total_w[k] - before_w[k] - w, total_wm[k] - before_wm[k] - w * m);
            // Σⱼ wⱼ|m − mⱼ| over the ray's other samples, and over the earlier ones only (each pair of
            // samples appears twice in L).
            let earlier = m * before_w[k] - before_wm[k];
            let pull = earlier + wm_after - m * w_after;
            values[i] = d.weight * (2.0 * pull + 2.0 / 3.0 * w * length);
            loss += w * (2.0 * earlier + w * length / 3.0);
            before_w[k] += w;
            before_wm[k] += w * m;
        }
    }
    f64::from(d.weight) * f64::from(loss)
}
