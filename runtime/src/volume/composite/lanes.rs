//! The compositor across rays: several rays composited together sample by sample, so that the inner
//! loops run across rays and vectorize (forward, and forward with the backward sweep).

use super::depths::RayDepths;
use super::distortion::{distortion_values, Distortion, DistortionScratch};
use super::{backward_row, density_alpha, opacity_alpha, Compositor, Mode, RayOutput, LAST_DELTA};

/// The accumulators of several rays composited together, sample by sample across rays.
///
/// Samples come in sample-major order (sample j of ray k at `j·rays + k`) so that the inner
/// loop runs across rays and vectorizes; the result is that of [`Compositor::forward`].
#[derive(Debug, Default)]
pub(crate) struct Lanes {
    transmittance: Vec<f32>,
    rgb: [Vec<f32>; 3],
    depth: Vec<f32>,
    opacity: Vec<f32>,
    /// The distortion loss's buffers in [`Lanes::forward_backward`], when it has one.
    distortion: DistortionScratch,
}

impl Lanes {
    /// Starts `rays` rays.
    pub(crate) fn reset(&mut self, rays: usize) {
        let fill = |v: &mut Vec<f32>, x: f32| {
            v.clear();
            v.resize(rays, x);
        };
        fill(&mut self.transmittance, 1.0);
        let [r, g, b] = &mut self.rgb;
        for v in [r, g, b, &mut self.depth, &mut self.opacity] {
            fill(v, 0.0);
        }
    }

    /// Adds the next `t.len()` samples of every ray: depths `t`, their δ `delta`, and
    /// sample-major values `raw` and colors `rgb`.
    pub(crate) fn add(&mut self, c: &Compositor, t: &[f32], delta: &[f32], raw: &[f32], rgb: [&[f32]; 3]) {
        // Without early termination the threshold is −∞ and every ray is live (a NaN
        // transmittance stays NaN either way), so the per-sample test is left out.
        let threshold = c.threshold();
        match (c.mode, c.early_termination.is_some()) {
            (Mode::Density, true) => self.add_with::<true>(threshold, density_alpha, t, delta, raw, rgb),
            (Mode::Density, false) => self.add_with::<false>(threshold, density_alpha, t, delta, raw, rgb),
            (Mode::Opacity, true) => self.add_with::<true>(threshold, opacity_alpha, t, delta, raw, rgb),
            (Mode::Opacity, false) => self.add_with::<false>(threshold, opacity_alpha, t, delta, raw, rgb),
        }
    }

    /// [`Lanes::add`] with alphas from `alpha_of(raw, δ)`; `STOP`: whether rays stop below
    /// `threshold`. δ and t are per sample row, shared by all rays.
    #[inline(always)]
    fn add_with<const STOP: bool>(
        &mut self,
        threshold: f32,
        alpha_of: impl Fn(f32, f32) -> (f32, f32),
        t: &[f32],
        delta: &[f32],
        raw: &[f32],
        [r, g, b]: [&[f32]; 3],
    ) {
        let n = self.transmittance.len();
        let Lanes {
            transmittance,
            rgb: [acc_r, acc_g, acc_b],
            depth,
            opacity,
            ..
        } = self;
        // Slices of length n, so that the loop below has no bounds checks and vectorizes.
        let (transmittance, depth, opacity) = (&mut transmittance[..n], &mut depth[..n], &mut opacity[..n]);
        let (acc_r, acc_g, acc_b) = (&mut acc_r[..n], &mut acc_g[..n], &mut acc_b[..n]);
        for (j, (&t, &delta)) in t.iter().zip(delta).enumerate() {
            let row = j * n..(j + 1) * n;
            let (raw, r, g, b) = (&raw[row.clone()], &r[row.clone()], &g[row.clone()], &b[row]);
            for k in 0..n {
                let trans = transmittance[k];
                let (alpha, keep) = alpha_of(raw[k], delta);
                // A stopped ray sees alpha 0: weight 0 and its transmittance unchanged.
                let (alpha, keep) = if !STOP || trans >= threshold {
                    (alpha, keep)
                } else {
                    (0.0, 1.0)
                };
                let w = trans * alpha;
                acc_r[k] += w * r[k];
                acc_g[k] += w * g[k];
                acc_b[k] += w * b[k];
                depth[k] += w * t;
                opacity[k] += w;
                transmittance[k] = trans * keep;
            }
        }
    }

    /// Adds samples `index` (increasing) of ray `k`, whose depths are `t`, with values `raw`
    /// and colors `rgb` (one per index). The samples left out have alpha 0: the result is that
    /// of [`Lanes::add`] with zero values (and finite colors) there, bit for bit, as such
    /// samples leave the ray unchanged.
    pub(crate) fn add_sparse(
        &mut self,
        c: &Compositor,
        k: usize,
        index: &[u32],
        t: impl RayDepths,
        raw: &[f32],
        rgb: [&[f32]; 3],
    ) {
        let threshold = c.threshold();
        let (ray, samples) = ((k, index), (t, raw, rgb));
        match (c.mode, c.early_termination.is_some()) {
            (Mode::Density, true) => self.add_sparse_with::<true>(threshold, density_alpha, ray, samples),
            (Mode::Density, false) => self.add_sparse_with::<false>(threshold, density_alpha, ray, samples),
            (Mode::Opacity, true) => self.add_sparse_with::<true>(threshold, opacity_alpha, ray, samples),
            (Mode::Opacity, false) => self.add_sparse_with::<false>(threshold, opacity_alpha, ray, samples),
        }
    }

    /// [`Lanes::add_sparse`] with alphas from `alpha_of(raw, δ)`, the same operations in the
    /// same order as [`Lanes::add_with`].
    #[inline(always)]
    #[allow(clippy::type_complexity)]
    fn add_sparse_with<const STOP: bool>(
        &mut self,
        threshold: f32,
        alpha_of: impl Fn(f32, f32) -> (f32, f32),
        (k, index): (usize, &[u32]),
        (t, raw, [r, g, b]): (impl RayDepths, &[f32], [&[f32]; 3]),
    ) {
        let mut trans = self.transmittance[k];
        let [mut acc_r, mut acc_g, mut acc_b] = [self.rgb[0][k], self.rgb[1][k], self.rgb[2][k]];
        let (mut depth, mut opacity) = (self.depth[k], self.opacity[k]);
        let n = index.len();
        let (raw, r, g, b) = (&raw[..n], &r[..n], &g[..n], &b[..n]);
        for (i, &j) in index.iter().enumerate() {
            let j = j as usize;
            let (alpha, keep) = alpha_of(raw[i], t.delta(j));
            let (alpha, keep) = if !STOP || trans >= threshold {
                (alpha, keep)
            } else {
                (0.0, 1.0)
            };
            let w = trans * alpha;
            acc_r += w * r[i];
            acc_g += w * g[i];
            acc_b += w * b[i];
            depth += w * t.at(j);
            opacity += w;
            trans *= keep;
        }
        self.transmittance[k] = trans;
        [self.rgb[0][k], self.rgb[1][k], self.rgb[2][k]] = [acc_r, acc_g, acc_b];
        (self.depth[k], self.opacity[k]) = (depth, opacity);
    }

    /// Adds the next samples of every ray when each sample has a depth `t` and δ `delta` of its
    /// own, sample-major like `raw` and `rgb`: the operations of [`Lanes::add`], whose depths and δ
    /// are shared by the rays.
    pub(crate) fn add_each(
        &mut self,
        c: &Compositor,
        t: &[f32],
        delta: &[f32],
        raw: &[f32],
        rgb: [&[f32]; 3],
    ) {
        let threshold = c.threshold();
        let samples = (t, delta, raw, rgb);
        match (c.mode, c.early_termination.is_some()) {
            (Mode::Density, true) => self.add_each_with::<true>(threshold, density_alpha, samples),
            (Mode::Density, false) => self.add_each_with::<false>(threshold, density_alpha, samples),
            (Mode::Opacity, true) => self.add_each_with::<true>(threshold, opacity_alpha, samples),
            (Mode::Opacity, false) => self.add_each_with::<false>(threshold, opacity_alpha, samples),
        }
    }

    /// [`Lanes::add_each`] with alphas from `alpha_of(raw, δ)`.
    #[inline(always)]
    #[allow(clippy::type_complexity)]
    fn add_each_with<const STOP: bool>(
        &mut self,
        threshold: f32,
        alpha_of: impl Fn(f32, f32) -> (f32, f32),
        (t, delta, raw, [r, g, b]): (&[f32], &[f32], &[f32], [&[f32]; 3]),
    ) {
        let n = self.transmittance.len();
        if n == 0 {
            return;
        }
        let Lanes {
            transmittance,
            rgb: [acc_r, acc_g, acc_b],
            depth,
            opacity,
            ..
        } = self;
        let (transmittance, depth, opacity) = (&mut transmittance[..n], &mut depth[..n], &mut opacity[..n]);
        let (acc_r, acc_g, acc_b) = (&mut acc_r[..n], &mut acc_g[..n], &mut acc_b[..n]);
        for j in 0..t.len() / n {
            let row = j * n..(j + 1) * n;
            let (here, delta, raw) = (&t[row.clone()], &delta[row.clone()], &raw[row.clone()]);
            let (r, g, b) = (&r[row.clone()], &g[row.clone()], &b[row]);
            for k in 0..n {
                let trans = transmittance[k];
                let (alpha, keep) = alpha_of(raw[k], delta[k]);
                let (alpha, keep) = if !STOP || trans >= threshold {
                    (alpha, keep)
                } else {
                    (0.0, 1.0)
                };
                let w = trans * alpha;
                acc_r[k] += w * r[k];
                acc_g[k] += w * g[k];
                acc_b[k] += w * b[k];
                depth[k] += w * here[k];
                opacity[k] += w;
                transmittance[k] = trans * keep;
            }
        }
    }

    /// Composites the rays started by [`Lanes::reset`] over all their samples and back-
    /// propagates: `t` holds every sample's depth, sample-major like `raw` and `rgb`;
    /// `cotangent(k, &ray)` gives the cotangents of ray `k` given its result; the gradients
    /// of every sample go to `grads` (∂σ or ∂a, then ∂r, ∂g, ∂b), sample-major. The result
    /// is that of [`Compositor::forward_backward`] on each ray. With `distortion`, the gradients
    /// are those of the loss plus its distortion loss (see [`Distortion`]), and the rays' summed
    /// distortion loss is returned (0 without). Leaves the accumulators undefined.
    ///
    /// `skip`, if given, marks rows (sample indices) whose values are all 0 (samples a grid left
    /// out): they change no ray's composite (alpha 0: the transmittance and the sums stay as they are,
    /// bit for bit) and are not swept, their gradients left undefined. Not with `distortion`, whose
    /// loss reads every row.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn forward_backward(
        &mut self,
        c: &Compositor,
        t: &[f32],
        raw: &[f32],
        rgb: [&[f32]; 3],
        grads: [&mut [f32]; 4],
        (distortion, skip): (Option<&Distortion>, Option<&[bool]>),
        cotangent: impl FnMut(usize, &RayOutput) -> RayOutput,
    ) -> f64 {
        assert!(
            distortion.is_none() || skip.is_none(),
            "the distortion loss reads every row"
        );
        let rows = t.len() / self.transmittance.len().max(1);
        let skip = skip.map(|s| &s[..rows]);
        match c.mode {
            Mode::Density => {
                self.forward_backward_with::<true>(c, t, raw, rgb, grads, (distortion, skip), cotangent)
            }
            Mode::Opacity => {
                self.forward_backward_with::<false>(c, t, raw, rgb, grads, (distortion, skip), cotangent)
            }
        }
    }

    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn forward_backward_with<const DENSITY: bool>(
        &mut self,
        c: &Compositor,
        t: &[f32],
        raw: &[f32],
        [r, g, b]: [&[f32]; 3],
        [g_raw, g_r, g_g, g_b]: [&mut [f32]; 4],
        (distortion, skip): (Option<&Distortion>, Option<&[bool]>),
        mut cotangent: impl FnMut(usize, &RayOutput) -> RayOutput,
    ) -> f64 {
        let alpha_of = if DENSITY { density_alpha } else { opacity_alpha };
        let n = self.transmittance.len();
        if n == 0 {
            return 0.0;
        }
        let rows = t.len() / n;
        let threshold = c.threshold();
        let swept = |j: usize| skip.is_none_or(|s| !s[j]);
        // δ of every sample, kept in g_b until the sweep back.
        for j in (0..rows).filter(|&j| swept(j)) {
            let row = j * n..(j + 1) * n;
            if j + 1 < rows {
                let (here, next) = (&t[row.clone()], &t[(j + 1) * n..(j + 2) * n]);
                for ((delta, t), next) in g_b[row].iter_mut().zip(here).zip(next) {
                    *delta = next - t;
                }
            } else {
                g_b[row].fill(LAST_DELTA);
            }
        }
        // Forward, keeping Tᵢ (0 for stopped rays) in g_raw, alphaᵢ in g_r, 1 − alphaᵢ in g_g.
        let Lanes {
            transmittance,
            rgb: [acc_r, acc_g, acc_b],
            depth,
            opacity,
            distortion: distortion_scratch,
        } = self;
        for j in (0..rows).filter(|&j| swept(j)) {
            let row = j * n..(j + 1) * n;
            let (t, raw, r, g, b) = (
                &t[row.clone()],
                &raw[row.clone()],
                &r[row.clone()],
                &g[row.clone()],
                &b[row.clone()],
            );
            let (s_trans, s_alpha, s_keep) = (
                &mut g_raw[row.clone()],
                &mut g_r[row.clone()],
                &mut g_g[row.clone()],
            );
            let delta = &g_b[row];
            for k in 0..n {
                let trans = transmittance[k];
                let (alpha, keep) = alpha_of(raw[k], delta[k]);
                let live = trans >= threshold;
                let (alpha, keep) = if live { (alpha, keep) } else { (0.0, 1.0) };
                let w = trans * alpha;
                acc_r[k] += w * r[k];
                acc_g[k] += w * g[k];
                acc_b[k] += w * b[k];
                depth[k] += w * t[k];
                opacity[k] += w;
                s_trans[k] = if live { trans } else { 0.0 };
                (s_alpha[k], s_keep[k]) = (alpha, keep);
                transmittance[k] = trans * keep;
            }
        }
        let distortion_loss = match distortion {
            Some(d) => {
                let forward = (&g_raw[..rows * n], &g_r[..rows * n]);
                distortion_values(d, n, &t[..rows * n], forward, distortion_scratch)
            }
            None => 0.0,
        };
        let extra = &distortion_scratch.values;
        // Cotangents replace the accumulators, the suffix values S the transmittances.
        let background = c.background.unwrap_or([0.0; 3]);
        for k in 0..n {
            let mut out = RayOutput {
                rgb: [acc_r[k], acc_g[k], acc_b[k]],
                depth: depth[k],
                opacity: opacity[k],
            };
            c.add_background(&mut out, transmittance[k]);
            let cot = cotangent(k, &out);
            (acc_r[k], acc_g[k], acc_b[k]) = (cot.rgb[0], cot.rgb[1], cot.rgb[2]);
            (depth[k], opacity[k]) = (cot.depth, cot.opacity);
            let [bg_r, bg_g, bg_b] = background;
            transmittance[k] = cot.rgb[0] * bg_r + cot.rgb[1] * bg_g + cot.rgb[2] * bg_b;
        }
        let (gc_r, gc_g, gc_b, gd, go) = (&acc_r[..n], &acc_g[..n], &acc_b[..n], &depth[..n], &opacity[..n]);
        let suffix = &mut transmittance[..n];
        for j in (0..rows).rev().filter(|&j| swept(j)) {
            let row = j * n..(j + 1) * n;
            let (t, r, g, b) = (&t[row.clone()], &r[row.clone()], &g[row.clone()], &b[row.clone()]);
            let (g_raw, g_r) = (&mut g_raw[row.clone()], &mut g_r[row.clone()]);
            let (g_g, g_b) = (&mut g_g[row.clone()], &mut g_b[row.clone()]);
            // The branch is a row's, not a sample's: each arm's loop vectorizes.
            let extra: &[f32] = if distortion.is_some() { &extra[row] } else { &[] };
            let row_sweep = if distortion.is_some() {
                backward_row::<DENSITY, true>
            } else {
                backward_row::<DENSITY, false>
            };
            row_sweep(
                extra, t, r, g, b, gc_r, gc_g, gc_b, gd, go, suffix, g_raw, g_r, g_g, g_b,
            );
        }
        distortion_loss
    }

    /// Whether ray `k` is still live (its transmittance is not below the threshold).
    pub(crate) fn is_live(&self, c: &Compositor, k: usize) -> bool {
        self.transmittance[k] >= c.threshold()
    }

    /// Moves the state of ray `from` to ray `to`.
    pub(crate) fn move_ray(&mut self, from: usize, to: usize) {
        let [r, g, b] = &mut self.rgb;
        for v in [
            &mut self.transmittance,
            r,
            g,
            b,
            &mut self.depth,
            &mut self.opacity,
        ] {
            v[to] = v[from];
        }
    }

    /// Keeps rays 0..n only.
    pub(crate) fn truncate(&mut self, n: usize) {
        let [r, g, b] = &mut self.rgb;
        for v in [
            &mut self.transmittance,
            r,
            g,
            b,
            &mut self.depth,
            &mut self.opacity,
        ] {
            v.truncate(n);
        }
    }

    /// The composited ray `k`.
    pub(crate) fn output(&self, c: &Compositor, k: usize) -> RayOutput {
        let mut out = RayOutput {
            rgb: [self.rgb[0][k], self.rgb[1][k], self.rgb[2][k]],
            depth: self.depth[k],
            opacity: self.opacity[k],
        };
        c.add_background(&mut out, self.transmittance[k]);
        out
    }
}
