//! The volume compositor: per-sample densities (or opacities) and colors along a ray → the
//! ray's color, depth and opacity, and the backward pass of that.
//!
//! For a ray with samples at depths t₀ < … < tₙ₋₁ with colors cᵢ:
//! - alphaᵢ = 1 − exp(−σᵢδᵢ) with δᵢ = tᵢ₊₁ − tᵢ and the last δ = [`LAST_DELTA`]
//!   ([`Mode::Density`]), or alphaᵢ = aᵢ, the field's per-sample opacity ([`Mode::Opacity`],
//!   the course's box volume, where σ = −ln(1 − a)/δ gives exactly that alpha);
//! - Tᵢ = Πⱼ<ᵢ (1 − alphaⱼ), wᵢ = Tᵢ·alphaᵢ;
//! - color = Σ wᵢcᵢ (+ T_final·background), depth = Σ wᵢtᵢ, opacity = Σ wᵢ.
//!
//! With early termination at threshold θ, a ray stops before the first sample i with
//! Tᵢ < θ: the samples from there on get weight 0 (and gradient 0) and T_final = Tᵢ.
//!
//! Backward, for cotangents (g_color, g_depth, g_opacity) of one ray: with
//! vᵢ = g_color·cᵢ + g_depth·tᵢ + g_opacity and the suffix values S (S = g_color·background
//! after the last live sample, S ← alphaᵢvᵢ + (1 − alphaᵢ)S going backwards), the loss is
//! S₀ and ∂L/∂alphaᵢ = Tᵢ(vᵢ − Sᵢ₊₁), ∂L/∂cᵢ = wᵢ·g_color, ∂L/∂σᵢ = δᵢ(1 − alphaᵢ)·∂L/∂alphaᵢ:
//! one backward sweep per ray, no division by 1 − alpha.
//!
//! The same sweep takes any loss of the weights: with ∂L/∂wᵢ added to vᵢ it back-propagates that
//! loss too, as training does with mip-NeRF 360's distortion loss ([`Distortion`]).
//!
//! This module holds the per-ray maths ([`Compositor`]); `lanes` composites several rays at once across
//! SIMD lanes, `depths` says where their samples lie, and `distortion` computes the distortion loss.

mod depths;
mod distortion;
mod lanes;

pub(crate) use depths::{DepthColumn, RayDepths, SharedDepths};
pub use distortion::Distortion;
pub(crate) use lanes::Lanes;

use crate::error::{Error, Result};

/// δ of the last sample of a ray, as in the course (and NeRF).
pub const LAST_DELTA: f32 = 1e10;

/// What the field's first output is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// A density σ >= 0: alpha = 1 − exp(−σδ).
    Density,
    /// A per-sample opacity a in [0, 1]: alpha = a.
    Opacity,
}

/// How samples are composited. See the module docs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Compositor {
    /// What the per-sample value is.
    pub mode: Mode,
    /// Color seen through the remaining transmittance; `None` is black.
    pub background: Option<[f32; 3]>,
    /// Stop a ray once its transmittance falls below this; `None` composites every sample.
    pub early_termination: Option<f32>,
}

/// A ray's composited color, depth and opacity; also their cotangents in the backward pass.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RayOutput {
    /// Color Σ wᵢcᵢ (+ T_final·background).
    pub rgb: [f32; 3],
    /// Expected depth Σ wᵢtᵢ.
    pub depth: f32,
    /// Opacity Σ wᵢ.
    pub opacity: f32,
}

/// The samples of one ray: depths, the field's first output (density or opacity) and colors.
#[derive(Debug, Clone, Copy)]
pub struct Samples<'a> {
    t: &'a [f32],
    raw: &'a [f32],
    rgb: [&'a [f32]; 3],
}

impl<'a> Samples<'a> {
    /// The samples at increasing depths `t` with values `raw` (σ or a) and colors `rgb`; all
    /// slices must have the same length.
    pub fn new(t: &'a [f32], raw: &'a [f32], rgb: [&'a [f32]; 3]) -> Result<Self> {
        let n = t.len();
        if raw.len() != n || rgb.iter().any(|c| c.len() != n) {
            return Err(Error::Invalid(format!(
                "samples of a ray need as many values and colors as depths ({n}), got {} values and {}/{}/{} colors",
                raw.len(),
                rgb[0].len(),
                rgb[1].len(),
                rgb[2].len()
            )));
        }
        Ok(Samples { t, raw, rgb })
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.t.len()
    }

    /// True if the ray has no sample.
    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }

    /// δᵢ = tᵢ₊₁ − tᵢ, or [`LAST_DELTA`] for the last sample.
    fn delta(&self, i: usize) -> f32 {
        self.t.get(i + 1).map_or(LAST_DELTA, |next| next - self.t[i])
    }
}

/// Where [`Compositor::forward_backward`] writes the gradients of one ray's samples.
#[derive(Debug)]
pub struct SampleGrads<'a> {
    raw: &'a mut [f32],
    rgb: [&'a mut [f32]; 3],
}

impl<'a> SampleGrads<'a> {
    /// Outputs for ∂L/∂σᵢ (or ∂L/∂aᵢ) and ∂L/∂cᵢ, all of the same length.
    pub fn new(raw: &'a mut [f32], rgb: [&'a mut [f32]; 3]) -> Result<Self> {
        let n = raw.len();
        if rgb.iter().any(|c| c.len() != n) {
            return Err(Error::Invalid(format!(
                "gradient outputs of a ray need equal lengths, got {n} and {}/{}/{}",
                rgb[0].len(),
                rgb[1].len(),
                rgb[2].len()
            )));
        }
        Ok(SampleGrads { raw, rgb })
    }
}

/// alpha and 1 − alpha of density `sigma` over `delta`, each computed without cancellation.
#[inline]
fn density_alpha(sigma: f32, delta: f32) -> (f32, f32) {
    let x = sigma * delta;
    if x < 0.5 {
        let alpha = -(-x).exp_m1();
        (alpha, 1.0 - alpha)
    } else {
        let transmitted = (-x).exp();
        (1.0 - transmitted, transmitted)
    }
}

/// alpha and 1 − alpha of a per-sample opacity.
#[inline]
fn opacity_alpha(a: f32, _delta: f32) -> (f32, f32) {
    (a, 1.0 - a)
}

impl Compositor {
    /// Checks that the background is finite and the termination threshold in (0, 1].
    pub(crate) fn check(&self) -> Result<()> {
        if let Some(bg) = self.background {
            if !bg.iter().all(|c| c.is_finite()) {
                return Err(Error::Invalid(format!("background color {bg:?} must be finite")));
            }
        }
        if let Some(t) = self.early_termination {
            if !(t > 0.0 && t <= 1.0) {
                return Err(Error::Invalid(format!(
                    "early termination threshold {t} must be in (0, 1]"
                )));
            }
        }
        Ok(())
    }

    /// A ray stops before a sample whose transmittance is below this.
    pub(crate) fn threshold(&self) -> f32 {
        self.early_termination.unwrap_or(f32::NEG_INFINITY)
    }

    /// (alpha, 1 − alpha) of sample value `raw` over `delta`.
    #[inline]
    pub(crate) fn alpha(&self, raw: f32, delta: f32) -> (f32, f32) {
        match self.mode {
            Mode::Density => density_alpha(raw, delta),
            Mode::Opacity => opacity_alpha(raw, delta),
        }
    }

    /// Composites one ray.
    pub fn forward(&self, samples: &Samples) -> RayOutput {
        let threshold = self.threshold();
        let mut out = RayOutput::default();
        let mut transmittance = 1.0f32;
        for i in 0..samples.len() {
            if transmittance < threshold {
                break;
            }
            let (alpha, keep) = self.alpha(samples.raw[i], samples.delta(i));
            let w = transmittance * alpha;
            for (acc, c) in out.rgb.iter_mut().zip(&samples.rgb) {
                *acc += w * c[i];
            }
            out.depth += w * samples.t[i];
            out.opacity += w;
            transmittance *= keep;
        }
        self.add_background(&mut out, transmittance);
        out
    }

    /// The result of a ray without samples (or whose samples all have alpha 0): the
    /// background (or black), depth 0, opacity 0.
    pub(crate) fn empty_ray(&self) -> RayOutput {
        let mut out = RayOutput::default();
        self.add_background(&mut out, 1.0);
        out
    }

    fn add_background(&self, out: &mut RayOutput, transmittance: f32) {
        if let Some(bg) = self.background {
            for (acc, c) in out.rgb.iter_mut().zip(bg) {
                *acc += transmittance * c;
            }
        }
    }

    /// Composites one ray, asks `cotangent` for (∂L/∂color, ∂L/∂depth, ∂L/∂opacity) given the
    /// result, and writes ∂L/∂σᵢ (or ∂L/∂aᵢ) and ∂L/∂cᵢ of every sample to `grads` in one
    /// backward sweep. Returns the composited ray.
    pub fn forward_backward(
        &self,
        samples: &Samples,
        grads: &mut SampleGrads,
        cotangent: impl FnOnce(&RayOutput) -> RayOutput,
    ) -> Result<RayOutput> {
        let n = samples.len();
        if grads.raw.len() != n {
            return Err(Error::Invalid(format!(
                "gradient outputs of length {} for a ray of {n} samples",
                grads.raw.len()
            )));
        }
        let SampleGrads {
            raw: g_raw,
            rgb: [g_r, g_g, g_b],
        } = grads;
        // Forward, keeping Tᵢ in g_raw, alphaᵢ in g_r and 1 − alphaᵢ in g_g for the sweep back.
        let threshold = self.threshold();
        let mut out = RayOutput::default();
        let mut transmittance = 1.0f32;
        let mut live = 0;
        while live < n && transmittance >= threshold {
            let i = live;
            let (alpha, keep) = self.alpha(samples.raw[i], samples.delta(i));
            let w = transmittance * alpha;
            for (acc, c) in out.rgb.iter_mut().zip(&samples.rgb) {
                *acc += w * c[i];
            }
            out.depth += w * samples.t[i];
            out.opacity += w;
            (g_raw[i], g_r[i], g_g[i]) = (transmittance, alpha, keep);
            transmittance *= keep;
            live += 1;
        }
        self.add_background(&mut out, transmittance);

        let cot = cotangent(&out);
        let [gc_r, gc_g, gc_b] = cot.rgb;
        let mut suffix = self
            .background
            .map_or(0.0, |[r, g, b]| gc_r * r + gc_g * g + gc_b * b);
        for i in (0..live).rev() {
            let (transmittance, alpha, keep) = (g_raw[i], g_r[i], g_g[i]);
            let w = transmittance * alpha;
            let (r, g, b) = (samples.rgb[0][i], samples.rgb[1][i], samples.rgb[2][i]);
            let value = gc_r * r + gc_g * g + gc_b * b + cot.depth * samples.t[i] + cot.opacity;
            let d_alpha = transmittance * (value - suffix);
            suffix = alpha * value + keep * suffix;
            g_raw[i] = match self.mode {
                Mode::Density => d_alpha * samples.delta(i) * keep,
                Mode::Opacity => d_alpha,
            };
            (g_r[i], g_g[i], g_b[i]) = (w * gc_r, w * gc_g, w * gc_b);
        }
        for g in [&mut **g_raw, &mut **g_r, &mut **g_g, &mut **g_b] {
            g[live..].fill(0.0);
        }
        Ok(out)
    }
}

/// One sample of every ray in the sweep back of [`Lanes::forward_backward`]: depths `t` and
/// colors, the rays' cotangents (color, depth, opacity) and suffix values; `g_*` hold T,
/// alpha, 1 − alpha and δ on entry and the gradients on exit; with `EXTRA`, `extra` holds a
/// further ∂L/∂w of each sample (the distortion loss's). Every slice is a parameter of its own,
/// which tells the compiler that they do not overlap, so the loop vectorizes.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn backward_row<const DENSITY: bool, const EXTRA: bool>(
    extra: &[f32],
    t: &[f32],
    r: &[f32],
    g: &[f32],
    b: &[f32],
    gc_r: &[f32],
    gc_g: &[f32],
    gc_b: &[f32],
    gd: &[f32],
    go: &[f32],
    suffix: &mut [f32],
    g_raw: &mut [f32],
    g_r: &mut [f32],
    g_g: &mut [f32],
    g_b: &mut [f32],
) {
    let n = suffix.len();
    for k in 0..n {
        let (trans, alpha, keep, delta) = (g_raw[k], g_r[k], g_g[k], g_b[k]);
        let w = trans * alpha;
        let mut value = gc_r[k] * r[k] + gc_g[k] * g[k] + gc_b[k] * b[k] + gd[k] * t[k] + go[k];
        if EXTRA {
            value += extra[k];
        }
        let d_alpha = trans * (value - suffix[k]);
        suffix[k] = alpha * value + keep * suffix[k];
        g_raw[k] = if DENSITY { d_alpha * delta * keep } else { d_alpha };
        (g_r[k], g_g[k], g_b[k]) = (w * gc_r[k], w * gc_g[k], w * gc_b[k]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::sampler::DepthSpacing;
    use proptest::prelude::*;

    /// One ray in f64: depths, values, colors.
    #[derive(Debug, Clone)]
    struct Ray {
        t: Vec<f64>,
        raw: Vec<f64>,
        rgb: [Vec<f64>; 3],
    }

    impl Ray {
        fn f32s(v: &[f64]) -> Vec<f32> {
            v.iter().map(|&x| x as f32).collect()
        }
    }

    /// Straightforward f64 compositing: Tᵢ as a product over all earlier samples, stopping
    /// after `stop` samples.
    fn reference(c: &Compositor, ray: &Ray, stop: usize) -> [f64; 5] {
        let n = ray.t.len();
        let alpha = |i: usize| match c.mode {
            Mode::Density => {
                let delta = if i + 1 < n {
                    ray.t[i + 1] - ray.t[i]
                } else {
                    LAST_DELTA as f64
                };
                1.0 - (-ray.raw[i] * delta).exp()
            }
            Mode::Opacity => ray.raw[i],
        };
        let trans = |i: usize| (0..i).map(|j| 1.0 - alpha(j)).product::<f64>();
        let mut out = [0.0; 5];
        for i in 0..stop {
            let w = trans(i) * alpha(i);
            for (acc, c) in out.iter_mut().zip(&ray.rgb) {
                *acc += w * c[i];
            }
            out[3] += w * ray.t[i];
            out[4] += w;
        }
        if let Some(bg) = c.background {
            for k in 0..3 {
                out[k] += trans(stop) * bg[k] as f64;
            }
        }
        out
    }

    /// Number of live samples under early termination, in f64.
    fn live_samples(c: &Compositor, ray: &Ray) -> usize {
        let Some(threshold) = c.early_termination else {
            return ray.t.len();
        };
        let n = ray.t.len();
        let mut trans = 1.0;
        for i in 0..n {
            if trans < threshold as f64 {
                return i;
            }
            let a = match c.mode {
                Mode::Density => {
                    let delta = if i + 1 < n {
                        ray.t[i + 1] - ray.t[i]
                    } else {
                        LAST_DELTA as f64
                    };
                    1.0 - (-ray.raw[i] * delta).exp()
                }
                Mode::Opacity => ray.raw[i],
            };
            trans *= 1.0 - a;
        }
        n
    }

    fn rays(mode: Mode) -> impl Strategy<Value = Ray> {
        let value = match mode {
            Mode::Density => 0.0f64..6.0,
            Mode::Opacity => 0.0f64..0.95,
        };
        (1usize..24).prop_flat_map(move |n| {
            (
                0.0f64..2.0,
                prop::collection::vec(0.02f64..0.4, n),
                prop::collection::vec(value.clone(), n),
                prop::array::uniform3(prop::collection::vec(0.0f64..1.0, n)),
            )
                .prop_map(|(t0, gaps, raw, rgb)| {
                    let t = gaps
                        .iter()
                        .scan(t0, |t, gap| {
                            let here = *t;
                            *t += gap;
                            Some(here)
                        })
                        .collect();
                    Ray { t, raw, rgb }
                })
        })
    }

    fn compositors(mode: Mode) -> impl Strategy<Value = Compositor> {
        (
            prop::option::of(prop::array::uniform3(0.0f32..1.0)),
            prop::option::of(0.01f32..0.5),
        )
            .prop_map(move |(background, early_termination)| Compositor {
                mode,
                background,
                early_termination,
            })
    }

    fn run_forward_backward(c: &Compositor, ray: &Ray, cot: RayOutput) -> (RayOutput, [Vec<f32>; 4]) {
        let (t, raw) = (Ray::f32s(&ray.t), Ray::f32s(&ray.raw));
        let rgb = ray.rgb.clone().map(|v| Ray::f32s(&v));
        let samples = Samples::new(&t, &raw, [&rgb[0], &rgb[1], &rgb[2]]).unwrap();
        let n = t.len();
        // Start from garbage: every output must be written.
        let mut g = [vec![7.0; n], vec![7.0; n], vec![7.0; n], vec![7.0; n]];
        let [g0, g1, g2, g3] = &mut g;
        let mut grads = SampleGrads::new(g0, [g1, g2, g3]).unwrap();
        let out = c.forward_backward(&samples, &mut grads, |_| cot).unwrap();
        assert_eq!(out, c.forward(&samples));
        (out, g)
    }

    fn check_forward(c: &Compositor, ray: &Ray) -> std::result::Result<(), TestCaseError> {
        let (t, raw) = (Ray::f32s(&ray.t), Ray::f32s(&ray.raw));
        let rgb = ray.rgb.clone().map(|v| Ray::f32s(&v));
        let samples = Samples::new(&t, &raw, [&rgb[0], &rgb[1], &rgb[2]]).unwrap();
        let out = c.forward(&samples);
        let expected = reference(c, ray, live_samples(c, ray));
        let got = [out.rgb[0], out.rgb[1], out.rgb[2], out.depth, out.opacity];
        for (k, (g, e)) in got.iter().zip(expected).enumerate() {
            prop_assert!(
                (*g as f64 - e).abs() <= 2e-5 * (1.0 + e.abs()),
                "output {}: {} vs {}",
                k,
                g,
                e
            );
        }
        Ok(())
    }

    /// Checks the backward pass against central differences of the f64 reference of
    /// L = g_color·color + g_depth·depth + g_opacity·opacity, with the stop index held fixed.
    fn check_backward(c: &Compositor, ray: &Ray, cot: [f64; 5]) -> std::result::Result<(), TestCaseError> {
        let cot32 = RayOutput {
            rgb: [cot[0] as f32, cot[1] as f32, cot[2] as f32],
            depth: cot[3] as f32,
            opacity: cot[4] as f32,
        };
        let (_, [g_raw, g_r, g_g, g_b]) = run_forward_backward(c, ray, cot32);
        let stop = live_samples(c, ray);
        let loss = |r: &Ray| {
            reference(c, r, stop)
                .iter()
                .zip(cot)
                .map(|(o, g)| o * g)
                .sum::<f64>()
        };
        let h = 1e-6;
        let fd = |edit: &dyn Fn(&mut Ray, f64)| {
            let (mut plus, mut minus) = (ray.clone(), ray.clone());
            edit(&mut plus, h);
            edit(&mut minus, -h);
            (loss(&plus) - loss(&minus)) / (2.0 * h)
        };
        let close = |got: f32, want: f64| (got as f64 - want).abs() <= 1e-3 * (1.0 + want.abs());
        for i in 0..ray.t.len() {
            let want = fd(&|r, h| r.raw[i] += h);
            prop_assert!(
                close(g_raw[i], want),
                "d/d{:?} {}: {} vs {}",
                c.mode,
                i,
                g_raw[i],
                want
            );
            for (k, g) in [&g_r, &g_g, &g_b].iter().enumerate() {
                let want = fd(&|r, h| r.rgb[k][i] += h);
                prop_assert!(close(g[i], want), "d/dc{} {}: {} vs {}", k, i, g[i], want);
            }
        }
        Ok(())
    }

    fn cotangents() -> impl Strategy<Value = [f64; 5]> {
        prop::array::uniform5(-1.0f64..1.0)
    }

    proptest! {
        #[test]
        fn density_forward_matches_f64(c in compositors(Mode::Density), ray in rays(Mode::Density)) {
            check_forward(&c, &ray)?;
        }

        #[test]
        fn opacity_forward_matches_f64(c in compositors(Mode::Opacity), ray in rays(Mode::Opacity)) {
            check_forward(&c, &ray)?;
        }

        #[test]
        fn density_backward_matches_finite_differences(
            c in compositors(Mode::Density), ray in rays(Mode::Density), cot in cotangents()
        ) {
            check_backward(&c, &ray, cot)?;
        }

        #[test]
        fn opacity_backward_matches_finite_differences(
            c in compositors(Mode::Opacity), ray in rays(Mode::Opacity), cot in cotangents()
        ) {
            check_backward(&c, &ray, cot)?;
        }

        #[test]
        fn lanes_match_per_ray_compositing(
            c in compositors(Mode::Density).prop_flat_map(|c| {
                prop_oneof![Just(c), Just(Compositor { mode: Mode::Opacity, ..c })]
            }),
            n in 1usize..12,
            k in 1usize..6,
            chunk in 1usize..8,
            values in prop::collection::vec(0.0f32..0.9, 4 * 12 * 6),
        ) {
            // k rays of n samples at shared depths, fed in chunks.
            let t: Vec<f32> = (0..n).map(|j| 0.5 + 0.3 * j as f32).collect();
            let delta: Vec<f32> = (0..n).map(|j| t.get(j + 1).map_or(LAST_DELTA, |u| u - t[j])).collect();
            let at = |channel: usize, ray: usize, j: usize| values[(channel * 6 + ray) * 12 + j];
            let major = |channel: usize| -> Vec<f32> {
                (0..n).flat_map(|j| (0..k).map(move |ray| (j, ray))).map(|(j, ray)| at(channel, ray, j)).collect()
            };
            let (raw, r, g, b) = (major(0), major(1), major(2), major(3));
            let mut lanes = Lanes::default();
            lanes.reset(k);
            for start in (0..n).step_by(chunk) {
                let end = (start + chunk).min(n);
                let rows = start * k..end * k;
                lanes.add(&c, &t[start..end], &delta[start..end], &raw[rows.clone()],
                    [&r[rows.clone()], &g[rows.clone()], &b[rows]]);
            }
            let (mut live, mut kept) = (0, Vec::new());
            for ray in 0..k {
                let per_ray = |channel| (0..n).map(|j| at(channel, ray, j)).collect::<Vec<_>>();
                let (raw, r, g, b) = (per_ray(0), per_ray(1), per_ray(2), per_ray(3));
                let samples = Samples::new(&t, &raw, [&r, &g, &b]).unwrap();
                prop_assert_eq!(lanes.output(&c, ray), c.forward(&samples));
                let mut trans = 1.0f32;
                for j in 0..n {
                    if trans < c.threshold() {
                        break;
                    }
                    trans *= c.alpha(raw[j], delta[j]).1;
                }
                prop_assert_eq!(lanes.is_live(&c, ray), trans >= c.threshold());
                if lanes.is_live(&c, ray) {
                    kept.push(lanes.output(&c, ray));
                    lanes.move_ray(ray, live);
                    live += 1;
                }
            }
            // Compaction keeps the live rays' state.
            lanes.truncate(live);
            prop_assert_eq!((0..live).map(|k| lanes.output(&c, k)).collect::<Vec<_>>(), kept);
        }
    }

    proptest! {
        #[test]
        fn lanes_backward_matches_per_ray_backward(
            c in compositors(Mode::Density).prop_flat_map(|c| {
                prop_oneof![Just(c), Just(Compositor { mode: Mode::Opacity, ..c })]
            }),
            n in 1usize..12,
            k in 1usize..6,
            gaps in prop::collection::vec(0.02f32..0.3, 12 * 6),
            values in prop::collection::vec(0.0f32..0.9, 4 * 12 * 6),
            empty in prop::collection::vec(prop::bool::weighted(0.3), 12),
            cots in prop::collection::vec(-1.0f32..1.0, 5 * 6),
        ) {
            // k rays of n samples, each at its own depths; the rows marked `empty` all zeros (samples
            // a grid left out).
            let depth = |ray: usize, j: usize| 0.5 + gaps[ray * 12..ray * 12 + j].iter().sum::<f32>();
            let at = |channel: usize, ray: usize, j: usize| {
                if empty[j] {
                    0.0
                } else {
                    values[(channel * 6 + ray) * 12 + j]
                }
            };
            let sample_major = |f: &dyn Fn(usize, usize) -> f32| -> Vec<f32> {
                (0..n).flat_map(|j| (0..k).map(move |ray| (j, ray))).map(|(j, ray)| f(ray, j)).collect()
            };
            let t = sample_major(&depth);
            let [raw, r, g, b] = [0, 1, 2, 3].map(|c| sample_major(&|ray, j| at(c, ray, j)));
            let cot = |ray: usize| RayOutput {
                rgb: [cots[5 * ray], cots[5 * ray + 1], cots[5 * ray + 2]],
                depth: cots[5 * ray + 3],
                opacity: cots[5 * ray + 4],
            };
            let mut lanes = Lanes::default();
            lanes.reset(k);
            let mut grads = [vec![7.0; n * k], vec![7.0; n * k], vec![7.0; n * k], vec![7.0; n * k]];
            let [g0, g1, g2, g3] = &mut grads;
            let mut outputs = vec![RayOutput::default(); k];
            lanes.forward_backward(&c, &t, &raw, [&r, &g, &b], [g0, g1, g2, g3], (None, None), |ray, out| {
                outputs[ray] = *out;
                cot(ray)
            });
            for ray in 0..k {
                let column = |v: &[f32]| (0..n).map(|j| v[j * k + ray]).collect::<Vec<_>>();
                let (t, raw, r, g, b) = (column(&t), column(&raw), column(&r), column(&g), column(&b));
                let samples = Samples::new(&t, &raw, [&r, &g, &b]).unwrap();
                let mut expected = [vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n]];
                let [e0, e1, e2, e3] = &mut expected;
                let mut ray_grads = SampleGrads::new(e0, [e1, e2, e3]).unwrap();
                let out = c.forward_backward(&samples, &mut ray_grads, |_| cot(ray)).unwrap();
                prop_assert_eq!(outputs[ray], out);
                for (got, want) in grads.iter().zip(&expected) {
                    prop_assert_eq!(&column(got), want, "ray {}", ray);
                }
            }
            // Stepping over the empty rows changes neither the composites nor the other rows'
            // gradients, bit for bit.
            lanes.reset(k);
            let mut skipped = [vec![7.0; n * k], vec![7.0; n * k], vec![7.0; n * k], vec![7.0; n * k]];
            let [g0, g1, g2, g3] = &mut skipped;
            let mut skipped_outputs = vec![RayOutput::default(); k];
            lanes.forward_backward(&c, &t, &raw, [&r, &g, &b], [g0, g1, g2, g3], (None, Some(&empty)), |ray, out| {
                skipped_outputs[ray] = *out;
                cot(ray)
            });
            prop_assert_eq!(skipped_outputs, outputs);
            for (got, want) in skipped.iter().zip(&grads) {
                for i in (0..n * k).filter(|i| !empty[i / k]) {
                    prop_assert_eq!(got[i].to_bits(), want[i].to_bits(), "sample {}", i);
                }
            }
        }
    }

    /// mip-NeRF 360's distortion loss of the first `stop` samples of a ray in f64, times `d.weight`.
    fn reference_distortion(c: &Compositor, d: &Distortion, ray: &Ray, stop: usize) -> f64 {
        let n = ray.t.len();
        let mut trans = 1.0;
        let mut w = vec![0.0; n];
        for (i, w) in w.iter_mut().enumerate().take(stop) {
            let a = match c.mode {
                Mode::Density => {
                    let delta = ray.t.get(i + 1).map_or(LAST_DELTA as f64, |next| next - ray.t[i]);
                    1.0 - (-ray.raw[i] * delta).exp()
                }
                Mode::Opacity => ray.raw[i],
            };
            *w = trans * a;
            trans *= 1.0 - a;
        }
        let s: Vec<f64> = (0..=n)
            .map(|i| {
                ray.t
                    .get(i)
                    .map_or(1.0, |&t| f64::from(d.spacing.fraction(d.near, d.far, t as f32)))
            })
            .collect();
        let mid = |i: usize| 0.5 * (s[i] + s[i + 1]);
        let mut loss = 0.0;
        for i in 0..n {
            for j in 0..n {
                loss += w[i] * w[j] * (mid(i) - mid(j)).abs();
            }
            loss += w[i] * w[i] * (s[i + 1] - s[i]) / 3.0;
        }
        f64::from(d.weight) * loss
    }

    fn distortions() -> impl Strategy<Value = Distortion> {
        (0.01f32..2.0, prop::bool::ANY).prop_map(|(weight, disparity)| Distortion {
            weight,
            near: 0.0,
            far: 12.0,
            spacing: if disparity {
                DepthSpacing::LinDisp { split: 1.0 }
            } else {
                DepthSpacing::Linear
            },
        })
    }

    proptest! {
        /// Two rays composited together with a distortion loss: each ray's gradients are those of its
        /// colour loss plus its distortion loss, by central differences of the f64 references.
        #[test]
        fn distortion_gradient_matches_finite_differences(
            c in compositors(Mode::Density).prop_flat_map(|c| {
                prop_oneof![Just(c), Just(Compositor { mode: Mode::Opacity, ..c })]
            }),
            ray in rays(Mode::Opacity),
            d in distortions(),
            cot in cotangents(),
        ) {
            let second = Ray { raw: ray.raw.iter().rev().map(|v| 0.5 * v).collect(), ..ray.clone() };
            let both = [&ray, &second];
            let n = ray.t.len();
            let sample_major = |f: &dyn Fn(&Ray, usize) -> f64| -> Vec<f32> {
                (0..n).flat_map(|j| both.map(|r| f(r, j) as f32)).collect()
            };
            let t = sample_major(&|r, j| r.t[j]);
            let raw = sample_major(&|r, j| r.raw[j]);
            let [red, green, blue] = [0, 1, 2].map(|k| sample_major(&|r, j| r.rgb[k][j]));
            let cot32 = RayOutput {
                rgb: [cot[0] as f32, cot[1] as f32, cot[2] as f32],
                depth: cot[3] as f32,
                opacity: cot[4] as f32,
            };
            let mut lanes = Lanes::default();
            lanes.reset(2);
            let mut grads = [vec![7.0; 2 * n], vec![7.0; 2 * n], vec![7.0; 2 * n], vec![7.0; 2 * n]];
            let [g0, g1, g2, g3] = &mut grads;
            let got_loss =
                lanes.forward_backward(&c, &t, &raw, [&red, &green, &blue], [g0, g1, g2, g3], (Some(&d), None), |_, _| cot32);
            let want_loss: f64 = both.iter().map(|r| reference_distortion(&c, &d, r, live_samples(&c, r))).sum();
            prop_assert!((got_loss - want_loss).abs() <= 1e-4 * (1.0 + want_loss), "loss {got_loss} vs {want_loss}");
            for (k, ray) in both.into_iter().enumerate() {
                let stop = live_samples(&c, ray);
                let loss = |r: &Ray| {
                    let colour: f64 = reference(&c, r, stop).iter().zip(cot).map(|(o, g)| o * g).sum();
                    colour + reference_distortion(&c, &d, r, stop)
                };
                let h = 1e-6;
                for i in 0..n {
                    let (mut plus, mut minus) = (ray.clone(), ray.clone());
                    plus.raw[i] += h;
                    minus.raw[i] -= h;
                    let want = (loss(&plus) - loss(&minus)) / (2.0 * h);
                    let got = f64::from(grads[0][i * 2 + k]);
                    prop_assert!((got - want).abs() <= 2e-3 * (1.0 + want.abs()), "ray {k}, d/draw {i}: {got} vs {want}");
                }
            }
        }
    }

    #[test]
    fn distortion_of_two_samples_by_hand() {
        // Opacities 0.5 and 1 at s = 0 and 0.5 (linear spacing on [0, 1]): weights 0.5 and 0.5, midpoints
        // 0.25 and 0.75, intervals of 0.5. L = 2·0.25·0.5 + ⅓(0.25·0.5 + 0.25·0.5) = 1/4 + 1/12 = 1/3.
        let c = Compositor {
            mode: Mode::Opacity,
            background: None,
            early_termination: None,
        };
        let d = Distortion {
            weight: 1.0,
            near: 0.0,
            far: 1.0,
            spacing: DepthSpacing::Linear,
        };
        let ray = Ray {
            t: vec![0.0, 0.5],
            raw: vec![0.5, 1.0],
            rgb: [vec![0.0; 2], vec![0.0; 2], vec![0.0; 2]],
        };
        assert!((reference_distortion(&c, &d, &ray, 2) - 1.0 / 3.0).abs() < 1e-12);
        // ∂L/∂w = 2·0.5·0.5 + ⅔·0.5·0.5 = 2/3 for both; ∂L/∂a₀ = T₀(v₀ − S₁) with S₁ = a₁v₁ = 2/3: 0;
        // ∂L/∂a₁ = T₁·v₁ = 1/3.
        let mut lanes = Lanes::default();
        lanes.reset(1);
        let zeros = [0.0f32; 2];
        let mut grads = [vec![0.0; 2], vec![0.0; 2], vec![0.0; 2], vec![0.0; 2]];
        let [g0, g1, g2, g3] = &mut grads;
        let loss = lanes.forward_backward(
            &c,
            &[0.0, 0.5],
            &[0.5, 1.0],
            [&zeros, &zeros, &zeros],
            [g0, g1, g2, g3],
            (Some(&d), None),
            |_, _| RayOutput::default(),
        );
        assert!((loss - 1.0 / 3.0).abs() < 1e-6, "{loss}");
        assert!(
            grads[0][0].abs() < 1e-6 && (grads[0][1] - 1.0 / 3.0).abs() < 1e-6,
            "{:?}",
            grads[0]
        );
    }

    #[test]
    fn hand_computed_two_samples() {
        // Opacities 0.5, 0.5 at depths 1, 2: weights 0.5, 0.25, T_final 0.25.
        let c = Compositor {
            mode: Mode::Opacity,
            background: Some([1.0, 0.0, 0.0]),
            early_termination: None,
        };
        let (t, a) = ([1.0, 2.0], [0.5, 0.5]);
        let (r, g, b) = ([0.0, 1.0], [1.0, 0.0], [0.0, 0.0]);
        let out = c.forward(&Samples::new(&t, &a, [&r, &g, &b]).unwrap());
        assert_eq!(out.rgb, [0.25 + 0.25, 0.5, 0.0]);
        assert_eq!((out.depth, out.opacity), (1.0, 0.75));
        // Density: σ = ln 2 over δ = 1 is alpha 1/2 too; the last δ is huge, so alpha 1.
        let c = Compositor {
            mode: Mode::Density,
            ..c
        };
        let sigma = [std::f32::consts::LN_2, 1e-3];
        let out = c.forward(&Samples::new(&t, &sigma, [&r, &g, &b]).unwrap());
        assert!(
            (out.opacity - 1.0).abs() < 1e-6 && (out.depth - 1.5).abs() < 1e-6,
            "{out:?}"
        );
        // Early termination at 0.6 keeps the first sample only and sees the background.
        let c = Compositor {
            mode: Mode::Opacity,
            early_termination: Some(0.6),
            ..c
        };
        let out = c.forward(&Samples::new(&t, &a, [&r, &g, &b]).unwrap());
        assert_eq!(out.rgb, [0.5, 0.5, 0.0]);
        assert_eq!((out.depth, out.opacity), (0.5, 0.5));
    }

    #[test]
    fn mismatched_lengths_and_bad_settings_are_errors() {
        let x = [0.0; 3];
        assert!(Samples::new(&x, &x[..2], [&x, &x, &x]).is_err());
        assert!(Samples::new(&x, &x, [&x, &x[..1], &x]).is_err());
        let samples = Samples::new(&x, &x, [&x, &x, &x]).unwrap();
        assert_eq!((samples.len(), samples.is_empty()), (3, false));
        let (mut a, mut b, mut c, mut d) = ([0.0; 2], [0.0; 2], [0.0; 2], [0.0; 1]);
        assert!(SampleGrads::new(&mut a, [&mut b, &mut c, &mut d]).is_err());
        let mut e = [0.0; 2];
        let mut grads = SampleGrads::new(&mut a, [&mut b, &mut c, &mut e]).unwrap();
        let comp = Compositor {
            mode: Mode::Opacity,
            background: None,
            early_termination: None,
        };
        assert!(comp.forward_backward(&samples, &mut grads, |o| *o).is_err());
        assert!(comp.check().is_ok());
        let bad = [
            Compositor {
                early_termination: Some(0.0),
                ..comp
            },
            Compositor {
                early_termination: Some(f32::NAN),
                ..comp
            },
            Compositor {
                background: Some([0.0, f32::INFINITY, 0.0]),
                ..comp
            },
        ];
        for c in bad {
            assert!(c.check().is_err(), "{c:?}");
        }
    }
}
