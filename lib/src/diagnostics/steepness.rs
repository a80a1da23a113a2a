//! Whether an SDF is steeper than its sphere tracer assumes. The tracer steps by `sdf / lipschitz`, which
//! is at most the distance to the surface only where |∇sdf| ≤ `lipschitz`: a steeper field (a scaled SDF, an
//! f-rep model that is not a distance) is stepped through. [`bound_for`] turns gradient norms measured at
//! many points into a bound to use (`nerfjit import` writes it); [`warning`] checks a render's field along
//! the probe rays of [`crate::diagnostics::nonfinite`] and names the setting to raise.

use nerfjit_runtime::BatchFn;

use crate::diagnostics::nonfinite::ProbeRays;

/// The share of measured points whose gradient a bound may leave above it (kinks and singular points,
/// where a few samples see far larger norms than the field has anywhere a ray passes).
const ABOVE: f64 = 0.001;

/// The norm under which all but a thousandth of `norms` lie (NaN left out), or `None` without any.
pub fn typical_largest(norms: &[f32]) -> Option<f32> {
    let mut finite: Vec<f32> = norms.iter().copied().filter(|g| !g.is_nan()).collect();
    finite.sort_by(f32::total_cmp);
    let index = ((finite.len() as f64) * (1.0 - ABOVE)) as usize;
    finite.get(index.min(finite.len().saturating_sub(1))).copied()
}

/// A bound on |∇sdf| to trace with, given the norm most points stay under: 10% more, rounded up to two
/// significant digits (10 → 11, 13.4 → 15).
pub fn bound_for(typical: f32) -> f32 {
    significant(1.1 * typical)
}

/// `x` rounded up to two significant digits (13.41 → 14, 0.2519 → 0.26), but for rounding errors of
/// less than a thousandth of the last digit (11.000001 → 11).
fn significant(x: f32) -> f32 {
    let unit = 10f32.powi(x.log10().floor() as i32 - 1);
    ((x / unit) - 1e-3).ceil() * unit
}

/// The norms of the gradient computed by `gradient` (a function of a position whose outputs are its value
/// and then the gradient's x, y and z) at the points whose x, y and z are the columns of `xyz`.
pub fn gradient_norms(gradient: &dyn BatchFn, xyz: &[&[f32]]) -> Vec<f32> {
    let out = gradient.eval_columns(xyz);
    (0..out[0].len())
        .map(|i| (out[1][i].powi(2) + out[2][i].powi(2) + out[3][i].powi(2)).sqrt())
        .collect()
}

/// A warning if the SDF's gradient (`gradient`, as [`gradient_norms`] takes it) exceeds `lipschitz` by
/// more than 20% at more than 0.1% of the points along the probe rays, naming the bound to trace with.
pub fn warning(gradient: &dyn BatchFn, rays: ProbeRays, lipschitz: f32) -> Option<String> {
    if gradient.n_inputs() != 3 || gradient.n_outputs() != 4 {
        return None;
    }
    let (points, xyz) = rays.columns(3);
    let xyz: Vec<&[f32]> = xyz.iter().map(Vec::as_slice).collect();
    let typical = typical_largest(&gradient_norms(gradient, &xyz))?;
    (typical > 1.2 * lipschitz).then(|| {
        format!(
            "warning: |∇sdf| exceeds {typical:.3} at 0.1% of {} points along the first frame's rays, more than \
             the tracer's lipschitz ({lipschitz}): sphere tracing steps through surfaces where the field is \
             steeper than that; set `lipschitz: {}` (and more `max_steps`) in the render block",
            points.len(),
            bound_for(typical)
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounds_round_up_to_two_significant_digits() {
        assert_eq!(significant(13.41), 14.0);
        assert_eq!(significant(11.0), 11.0);
        assert!((significant(0.2519) - 0.26).abs() < 1e-6);
        assert_eq!(significant(72.8), 73.0);
        assert_eq!(bound_for(10.0), 11.0);
    }

    #[test]
    fn the_typical_largest_norm_leaves_out_a_thousandth_and_nan() {
        let mut norms: Vec<f32> = (0..2000).map(|i| 1.0 + i as f32 / 2000.0).collect();
        norms[1999] = 66.0; // a kink
        norms[0] = f32::NAN;
        let typical = typical_largest(&norms).unwrap();
        assert!((1.99..2.0).contains(&typical), "{typical}");
        assert_eq!(typical_largest(&[f32::NAN]), None);
        assert_eq!(typical_largest(&[3.0]), Some(3.0));
    }
}
