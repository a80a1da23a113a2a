//! The color a splat shows from a direction: its base color plus, where it has them, degree-one spherical
//! harmonics of the direction it is seen along, as 3D Gaussian splatting shades its splats (truncated to the
//! first degree): color(d) = base + C1 · (−d_y · h₀ + d_z · h₁ − d_x · h₂), d the unit vector from the camera
//! to the splat's center and h₀..₂ its coefficients (each an RGB triple), clamped to [0, 1] (3D Gaussian
//! splatting clamps at 0 only; at 1 too, a frame stays within [0, 1] as the screen shows it, and Spark's
//! picture of a bake is as close to nerfjit's either way).

use glam::Vec3;

/// The degree-0 spherical harmonic, 1 / (2 √π): the `.ply` layout's `f_dc` is (color − 0.5) / C0.
pub(crate) const SH_C0: f32 = 0.282_094_8;

/// The degree-1 spherical harmonics' factor, √3 / (2 √π).
pub(crate) const SH_C1: f32 = 0.488_602_5;

/// The degree-one basis at the unit direction `d`, in the order of the coefficients.
#[inline(always)]
fn basis(d: Vec3) -> [f32; 3] {
    [-SH_C1 * d.y, SH_C1 * d.z, -SH_C1 * d.x]
}

/// The color a splat of base color `base` and degree-one coefficients `sh` shows along the unit direction
/// `d` (from the camera to it), and for each channel whether it is its own (not clamped).
#[inline]
pub(crate) fn seen_color(base: [f32; 3], sh: &[[f32; 3]; 3], d: Vec3) -> ([f32; 3], [bool; 3]) {
    let b = basis(d);
    let raw: [f32; 3] =
        std::array::from_fn(|c| base[c] + b[0] * sh[0][c] + b[1] * sh[1][c] + b[2] * sh[2][c]);
    (
        raw.map(|x| x.clamp(0.0, 1.0)),
        raw.map(|x| (0.0..=1.0).contains(&x)),
    )
}

/// The derivatives of a loss through [`seen_color`], given its derivative `g` with respect to the seen
/// color: with respect to the base color, the coefficients and the splat's center (through the direction
/// `d`, at `distance` from the camera). A clamped channel passes nothing back.
pub(crate) fn seen_color_gradient(
    base: [f32; 3],
    sh: &[[f32; 3]; 3],
    d: Vec3,
    distance: f32,
    g: [f32; 3],
) -> ([f32; 3], [[f32; 3]; 3], Vec3) {
    let (_, inside) = seen_color(base, sh, d);
    let g: [f32; 3] = std::array::from_fn(|c| if inside[c] { g[c] } else { 0.0 });
    let b = basis(d);
    let d_sh = b.map(|bk| g.map(|gc| bk * gc));
    // dL/d(basis k) = Σ_c g_c h_k,c; basis = C1 (−d_y, d_z, −d_x).
    let along = |k: usize| (0..3).map(|c| g[c] * sh[k][c]).sum::<f32>();
    let d_dir = SH_C1 * Vec3::new(-along(2), -along(0), along(1));
    // d = (center − camera) / |center − camera|: dd/dcenter = (I − d dᵀ) / distance.
    let d_center = (d_dir - d * d.dot(d_dir)) / distance;
    (g, d_sh, d_center)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_degree_follows_the_direction() {
        let base = [0.5, 0.4, 0.3];
        let sh = [[0.2, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.2]];
        // Seen along −y, +z and −x, each coefficient adds C1 · 0.2 to its own channel.
        let (up, _) = seen_color(base, &sh, Vec3::NEG_Y);
        assert!((up[0] - (0.5 + SH_C1 * 0.2)).abs() < 1e-6 && up[1] == 0.4 && up[2] == 0.3);
        let (ahead, _) = seen_color(base, &sh, Vec3::Z);
        assert!((ahead[1] - (0.4 + SH_C1 * 0.2)).abs() < 1e-6 && ahead[0] == 0.5);
        let (left, _) = seen_color(base, &sh, Vec3::NEG_X);
        assert!((left[2] - (0.3 + SH_C1 * 0.2)).abs() < 1e-6);
        // Clamped channels say so.
        let (clamped, inside) = seen_color(
            [0.95, 0.5, 0.02],
            &[[1.0, 0.0, -1.0], [0.0; 3], [0.0; 3]],
            Vec3::NEG_Y,
        );
        assert_eq!((clamped[0], clamped[2]), (1.0, 0.0));
        assert_eq!(inside, [false, true, false]);
    }

    /// The gradient with respect to the coefficients and the center matches differences of a loss.
    #[test]
    fn the_gradient_matches_differences() {
        let base = [0.5, 0.45, 0.55];
        let sh = [[0.1, -0.2, 0.05], [0.3, 0.1, -0.1], [-0.15, 0.2, 0.25]];
        let (camera, center) = (Vec3::new(0.2, -0.3, -3.0), Vec3::new(0.4, 0.5, 0.1));
        let weights = [0.7, -1.3, 0.4];
        let loss = |sh: &[[f32; 3]; 3], center: Vec3| {
            let d = (center - camera).normalize();
            let (c, _) = seen_color(base, sh, d);
            (0..3).map(|k| weights[k] * c[k]).sum::<f32>()
        };
        let offset = center - camera;
        let (_, d_sh, d_center) =
            seen_color_gradient(base, &sh, offset.normalize(), offset.length(), weights);
        let h = 1e-3;
        for k in 0..3 {
            for c in 0..3 {
                let (mut up, mut down) = (sh, sh);
                up[k][c] += h;
                down[k][c] -= h;
                let numeric = (loss(&up, center) - loss(&down, center)) / (2.0 * h);
                assert!(
                    (numeric - d_sh[k][c]).abs() < 1e-3,
                    "h[{k}][{c}]: {numeric} vs {}",
                    d_sh[k][c]
                );
            }
            let step = Vec3::AXES[k] * h;
            let numeric = (loss(&sh, center + step) - loss(&sh, center - step)) / (2.0 * h);
            assert!(
                (numeric - d_center[k]).abs() < 1e-3,
                "center {k}: {numeric} vs {}",
                d_center[k]
            );
        }
    }
}
