//! Hierarchical sampling (NeRF's coarse-to-fine scheme): the weights of a coarse pass along each ray
//! define a piecewise-constant density of depths, from which more depths are drawn by inverting its
//! cumulative distribution; the fine pass evaluates the union of both sets, sorted.

use crate::volume::composite::Compositor;

/// Added to every interval's weight so that empty rays still sample the whole interval.
const WEIGHT_FLOOR: f32 = 1e-5;

/// The compositing weights wⱼ = Tⱼ·αⱼ of one ray's samples at sorted depths `t` with field values `raw`
/// (densities or opacities, as `compositor` reads them), written to `weights`. With early termination
/// the weights are those of the truncated composite: 0 from the first sample whose Tⱼ is below the
/// threshold on (so the samples past a ray's end, evaluated or not, place no importance sample).
pub fn ray_weights(compositor: &Compositor, t: &[f32], raw: &[f32], weights: &mut [f32]) {
    let threshold = compositor.threshold();
    let mut transmittance = 1.0f32;
    for j in 0..t.len() {
        if transmittance < threshold {
            weights[j..t.len()].fill(0.0);
            return;
        }
        let delta = t
            .get(j + 1)
            .map_or(crate::volume::composite::LAST_DELTA, |next| next - t[j]);
        let (alpha, keep) = compositor.alpha(raw[j], delta);
        weights[j] = transmittance * alpha;
        transmittance *= keep;
    }
}

/// Draws `out.len()` sorted depths in [near, far] from the density that gives the interval around each
/// coarse depth `t[j]` (from the midpoint with its predecessor, or `near`, to the midpoint with its
/// successor, or `far`) the mass `weights[j]` (+ a small floor), at the quantiles `u` (sorted, in [0, 1)).
pub fn inverse_cdf(near: f32, far: f32, t: &[f32], weights: &[f32], u: &[f32], out: &mut [f32]) {
    let m = t.len();
    let edge = |j: usize| -> f32 {
        if j == 0 {
            near
        } else if j == m {
            far
        } else {
            0.5 * (t[j - 1] + t[j])
        }
    };
    let total: f64 = weights
        .iter()
        .map(|&w| f64::from(w.max(0.0) + WEIGHT_FLOOR))
        .sum();
    let mut j = 0;
    let mut below = 0.0f64;
    let mass = |j: usize| f64::from(weights[j].max(0.0) + WEIGHT_FLOOR) / total;
    for (o, &q) in out.iter_mut().zip(u) {
        let q = f64::from(q.clamp(0.0, 1.0));
        while j + 1 < m && below + mass(j) <= q {
            below += mass(j);
            j += 1;
        }
        let within = ((q - below) / mass(j)).clamp(0.0, 1.0) as f32;
        let (a, b) = (edge(j), edge(j + 1));
        *o = (a + within * (b - a)).clamp(near, far);
    }
}

/// The quantiles for `n` importance samples: stratified (one uniform draw per equal bin, from `draw`) or
/// the bins' centers.
pub fn quantiles(n: usize, draw: Option<&mut dyn FnMut() -> f32>, out: &mut Vec<f32>) {
    out.clear();
    match draw {
        Some(draw) => out.extend((0..n).map(|i| (i as f32 + draw()) / n as f32)),
        None => out.extend((0..n).map(|i| (i as f32 + 0.5) / n as f32)),
    }
}

/// Merges two sorted depth lists into `out` (sorted, length a + b).
pub fn merge_sorted(a: &[f32], b: &[f32], out: &mut [f32]) {
    let (mut i, mut j) = (0, 0);
    for o in out.iter_mut() {
        let take_a = j >= b.len() || (i < a.len() && a[i] <= b[j]);
        if take_a {
            *o = a[i];
            i += 1;
        } else {
            *o = b[j];
            j += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::composite::Mode;
    use proptest::prelude::*;

    fn compositor() -> Compositor {
        Compositor {
            mode: Mode::Density,
            background: None,
            early_termination: None,
        }
    }

    #[test]
    fn weights_are_transmittance_times_alpha() {
        let t = [2.0, 3.0, 4.0];
        let raw = [0.5, 1.0, 2.0];
        let mut w = [0.0; 3];
        ray_weights(&compositor(), &t, &raw, &mut w);
        let a0 = 1.0 - (-0.5f32).exp();
        let a1 = 1.0 - (-1.0f32).exp();
        assert!((w[0] - a0).abs() < 1e-6);
        assert!((w[1] - (1.0 - a0) * a1).abs() < 1e-6);
        // The last sample's δ is "infinite": it takes all the remaining transmittance.
        assert!((w[2] - (1.0 - a0) * (1.0 - a1)).abs() < 1e-6);
    }

    #[test]
    fn samples_concentrate_where_the_weight_is() {
        // All the weight in the interval around t = 4 (from 3.5 to 4.5).
        let t: Vec<f32> = (0..9).map(|j| 2.0 + 0.5 * j as f32).collect();
        let mut weights = vec![0.0; 9];
        weights[4] = 1.0;
        let mut u = Vec::new();
        quantiles(100, None, &mut u);
        let mut out = vec![0.0; 100];
        inverse_cdf(2.0, 6.0, &t, &weights, &u, &mut out);
        let inside = out.iter().filter(|&&x| (3.75..=4.25).contains(&x)).count();
        assert!(inside >= 99, "{inside} of 100 samples near the weight");
    }

    proptest! {
        #[test]
        fn importance_samples_are_sorted_in_range_and_follow_the_cdf(
            weights in prop::collection::vec(0.0f32..1.0, 1..40),
            seed in any::<u64>(),
        ) {
            let m = weights.len();
            let (near, far) = (2.0f32, 6.0f32);
            let t: Vec<f32> = (0..m).map(|j| near + (far - near) * (j as f32 + 0.5) / m as f32).collect();
            let mut rng = crate::rng::Rng::new(seed);
            let mut draw = || rng.next_f32();
            let mut u = Vec::new();
            quantiles(64, Some(&mut draw), &mut u);
            let mut out = vec![0.0; 64];
            inverse_cdf(near, far, &t, &weights, &u, &mut out);
            prop_assert!(out.windows(2).all(|w| w[0] <= w[1]), "not sorted: {out:?}");
            prop_assert!(out.iter().all(|&x| (near..=far).contains(&x)));
            // The fraction of samples below each interval edge matches the CDF there (within one
            // stratum of 1/64 for the stratified quantiles, plus rounding).
            let total: f32 = weights.iter().map(|w| w + WEIGHT_FLOOR).sum();
            let mut cdf = 0.0;
            for j in 0..m {
                cdf += (weights[j] + WEIGHT_FLOOR) / total;
                let edge = if j + 1 == m { far } else { 0.5 * (t[j] + t[j + 1]) };
                let below = out.iter().filter(|&&x| x < edge).count() as f32 / 64.0;
                prop_assert!((below - cdf).abs() <= 1.0 / 64.0 + 1e-3, "edge {j}: {below} vs {cdf}");
            }
            let mut merged = vec![0.0; m + 64];
            merge_sorted(&t, &out, &mut merged);
            prop_assert!(merged.windows(2).all(|w| w[0] <= w[1]));
        }
    }
}
