//! Per-view colour transforms (issue 52): a capture whose photos differ in exposure or white balance
//! trains one affine map of colours per view beside the field, as NeRF-W's and nerfacto's per-image
//! appearance codes let each photo have its own look, so that the field need not explain the
//! differences with fog or view-dependent colour.
//!
//! A view's pixel is modelled as `A·c + b` of the radiance `c` the field renders (`A` 3×3, `b` a colour):
//! for a ray of composited foreground colour `f = Σ wᵢcᵢ` and opacity `o = Σ wᵢ` in front of a background
//! `bg`, the prediction is `A·f + o·b + (1 − o)·bg`. The background is the data's (or a training step's
//! random colour), not the photo's, so it is not transformed; an opaque ray gets the whole map. Held-out
//! views, renders and scores use no transform: the field's own colours.

use crate::volume::composite::RayOutput;

/// The values of one view's transform: `A` row-major, then `b`.
pub const TRANSFORM_VALUES: usize = 12;

/// An affine map of a view's colours, `A·c + b`: the values `[A₀₀, A₀₁, A₀₂, A₁₀, …, A₂₂, b₀, b₁, b₂]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColorTransform(pub [f32; TRANSFORM_VALUES]);

impl ColorTransform {
    /// The map that changes nothing: `A = I`, `b = 0`.
    pub const IDENTITY: ColorTransform =
        ColorTransform([1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]);

    /// `A·v` of a colour.
    fn times(&self, v: [f32; 3]) -> [f32; 3] {
        let a = &self.0;
        [0, 1, 2].map(|i| a[3 * i] * v[0] + a[3 * i + 1] * v[1] + a[3 * i + 2] * v[2])
    }

    /// The prediction for a ray that composited to `out` (its colour including `(1 − opacity)·background`)
    /// in front of `background`: `A·f + o·b + (1 − o)·background` with `f` its foreground colour.
    pub fn apply(&self, out: &RayOutput, background: [f32; 3]) -> [f32; 3] {
        let (o, b) = (out.opacity, &self.0[9..]);
        let foreground = [0, 1, 2].map(|c| out.rgb[c] - (1.0 - o) * background[c]);
        let mapped = self.times(foreground);
        [0, 1, 2].map(|c| mapped[c] + o * b[c] + (1.0 - o) * background[c])
    }

    /// The backward pass of [`ColorTransform::apply`] for the cotangent `g` of the prediction: adds ∂L/∂values
    /// to `grads` and returns the ray's cotangents (colour and opacity; its depth has none).
    pub fn backward(
        &self,
        out: &RayOutput,
        background: [f32; 3],
        g: [f32; 3],
        grads: &mut [f64; TRANSFORM_VALUES],
    ) -> RayOutput {
        let (o, a, b) = (out.opacity, &self.0, &self.0[9..]);
        let foreground = [0, 1, 2].map(|c| out.rgb[c] - (1.0 - o) * background[c]);
        for i in 0..3 {
            for j in 0..3 {
                grads[3 * i + j] += f64::from(g[i] * foreground[j]);
            }
            grads[9 + i] += f64::from(g[i] * o);
        }
        // pred = A·(rgb − (1 − o)·bg) + o·b + (1 − o)·bg: ∂/∂rgb = A, ∂/∂o = A·bg + b − bg.
        let rgb = [0, 1, 2].map(|j| (0..3).map(|i| a[3 * i + j] * g[i]).sum());
        let mapped_bg = self.times(background);
        let opacity = (0..3).map(|i| g[i] * (mapped_bg[i] + b[i] - background[i])).sum();
        RayOutput {
            rgb,
            depth: 0.0,
            opacity,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn loss(t: &ColorTransform, out: &RayOutput, bg: [f32; 3], w: [f32; 3]) -> f64 {
        let p = t.apply(out, bg);
        (0..3).map(|c| f64::from(w[c] * p[c])).sum()
    }

    #[test]
    fn the_identity_changes_nothing_and_the_background_stays_untransformed() {
        let out = RayOutput {
            rgb: [0.3, 0.5, 0.9],
            depth: 2.0,
            opacity: 0.6,
        };
        let got = ColorTransform::IDENTITY.apply(&out, [0.5, 0.5, 1.0]);
        for (g, w) in got.iter().zip(out.rgb) {
            assert!((g - w).abs() < 1e-6, "{got:?}");
        }
        // An empty ray shows the background whatever the map.
        let empty = RayOutput {
            rgb: [0.2, 0.4, 0.6],
            depth: 0.0,
            opacity: 0.0,
        };
        let halve = ColorTransform([0.5, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.5, 0.1, 0.1, 0.1]);
        assert_eq!(halve.apply(&empty, [0.2, 0.4, 0.6]), [0.2, 0.4, 0.6]);
    }

    #[test]
    fn gradients_match_finite_differences() {
        let t = ColorTransform([0.9, 0.1, -0.2, 0.05, 1.1, 0.0, 0.3, -0.1, 0.8, 0.02, -0.05, 0.1]);
        let out = RayOutput {
            rgb: [0.4, 0.7, 0.35],
            depth: 1.0,
            opacity: 0.7,
        };
        let (bg, w) = ([0.2, 0.9, 0.5], [0.7, -1.3, 0.4]);
        let mut grads = [0.0f64; TRANSFORM_VALUES];
        let cot = t.backward(&out, bg, w, &mut grads);
        let h = 1e-3f32;
        for (k, got) in grads.iter().enumerate() {
            let (mut up, mut down) = (t, t);
            up.0[k] += h;
            down.0[k] -= h;
            let fd = (loss(&up, &out, bg, w) - loss(&down, &out, bg, w)) / f64::from(2.0 * h);
            assert!((fd - got).abs() < 1e-3, "value {k}: {fd} vs {got}");
        }
        for c in 0..4 {
            let nudged = |d: f32| {
                let mut o = out;
                match c {
                    3 => o.opacity += d,
                    _ => o.rgb[c] += d,
                }
                loss(&t, &o, bg, w)
            };
            let fd = (nudged(h) - nudged(-h)) / f64::from(2.0 * h);
            let got = if c == 3 { cot.opacity } else { cot.rgb[c] };
            assert!((fd - f64::from(got)).abs() < 1e-3, "output {c}: {fd} vs {got}");
        }
    }
}
