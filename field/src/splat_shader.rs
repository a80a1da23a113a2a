//! The shader of baked splats: `splat_shader.sdf`'s `shade`, a script function compiled by the JIT into a
//! value kernel and a vector-Jacobian-product kernel, as the runtime's [`SplatShader`] (which the splat
//! renderer and the bake's fine-tuning call on columns of splats).

use std::sync::OnceLock;

use nerfjit_dsl::{kernel_graphs, Type};
use nerfjit_jit::{Kernel, Options};
use nerfjit_runtime::splats::{SplatShader, SHADER_INPUTS};

use crate::{FieldError, Result};

/// The script that defines the shader.
pub const SPLAT_SHADER_SOURCE: &str = include_str!("splat_shader.sdf");

/// The shader's function in [`SPLAT_SHADER_SOURCE`].
const SHADE: &str = "shade";

/// `shade` compiled: its values, and its values with the derivatives of Σ cotangent · color in each input.
pub struct JitSplatShader {
    value: Kernel,
    vjp: Kernel,
}

impl JitSplatShader {
    /// Compiles `shade` of [`SPLAT_SHADER_SOURCE`].
    fn compile() -> Result<JitSplatShader> {
        let program = nerfjit_dsl::compile("splat_shader.sdf", SPLAT_SHADER_SOURCE)?;
        let vec3 = Type::Vec(3);
        let inputs: Vec<Type> = (0..5).map(|_| vec3.clone()).collect();
        crate::check_signature(&program, SHADE, &[&inputs], &vec3)?;
        let lowered = program.lower(SHADE)?;
        Ok(JitSplatShader {
            value: Kernel::compile(&kernel_graphs::value(&lowered), Options::default())?,
            vjp: Kernel::compile(&kernel_graphs::vjp(&lowered, 0), Options::default())?,
        })
    }
}

/// The shader of baked splats, compiled on first use (once per process).
pub fn splat_shader() -> Result<&'static JitSplatShader> {
    static SHADER: OnceLock<std::result::Result<JitSplatShader, String>> = OnceLock::new();
    SHADER
        .get_or_init(|| JitSplatShader::compile().map_err(|e| e.to_string()))
        .as_ref()
        .map_err(|e| FieldError::Message(format!("the splat shader did not compile: {e}")))
}

impl SplatShader for JitSplatShader {
    fn shade(&self, n: usize, inputs: &[&[f32]], colors: &mut [&mut [f32]]) {
        self.value.eval(n, inputs, colors, &[], &mut []);
    }

    fn shade_vjp(&self, n: usize, inputs: &[&[f32]], cotangents: &[&[f32]], d_inputs: &mut [&mut [f32]]) {
        assert_eq!(d_inputs.len(), SHADER_INPUTS, "one derivative column per input");
        // The kernel reads the inputs, then the cotangents; it writes the colors (not needed here), then
        // the inputs' derivatives.
        let columns: Vec<&[f32]> = inputs.iter().chain(cotangents).copied().collect();
        let mut colors = [vec![0.0f32; n], vec![0.0f32; n], vec![0.0f32; n]];
        let mut outputs: Vec<&mut [f32]> = colors.iter_mut().map(Vec::as_mut_slice).collect();
        outputs.extend(d_inputs.iter_mut().map(|column| &mut **column));
        self.vjp.eval(n, &columns, &mut outputs, &[], &mut []);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The shader's formula (see `splat_shader.sdf`) before the clamp, written out in Rust.
    fn unclamped(x: &[f32; SHADER_INPUTS]) -> [f32; 3] {
        const SH_C1: f32 = 0.488_602_5;
        let length = (x[12] * x[12] + x[13] * x[13] + x[14] * x[14]).sqrt();
        let d = [x[12] / length, x[13] / length, x[14] / length];
        let basis = [-SH_C1 * d[1], SH_C1 * d[2], -SH_C1 * d[0]];
        std::array::from_fn(|c| x[c] + (0..3).map(|k| basis[k] * x[3 + 3 * k + c]).sum::<f32>())
    }

    /// The shader's formula.
    fn formula(x: &[f32; SHADER_INPUTS]) -> [f32; 3] {
        unclamped(x).map(|r| r.clamp(0.0, 1.0))
    }

    fn colors(shader: &JitSplatShader, points: &[[f32; SHADER_INPUTS]]) -> Vec<[f32; 3]> {
        let n = points.len();
        let columns: Vec<Vec<f32>> = (0..SHADER_INPUTS)
            .map(|k| points.iter().map(|p| p[k]).collect())
            .collect();
        let inputs: Vec<&[f32]> = columns.iter().map(Vec::as_slice).collect();
        let mut out = [vec![0.0; n], vec![0.0; n], vec![0.0; n]];
        let mut outputs: Vec<&mut [f32]> = out.iter_mut().map(Vec::as_mut_slice).collect();
        shader.shade(n, &inputs, &mut outputs);
        (0..n).map(|i| [out[0][i], out[1][i], out[2][i]]).collect()
    }

    fn vjp(
        shader: &JitSplatShader,
        point: &[f32; SHADER_INPUTS],
        cotangent: [f32; 3],
    ) -> [f32; SHADER_INPUTS] {
        let inputs: Vec<[f32; 1]> = point.iter().map(|&x| [x]).collect();
        let inputs: Vec<&[f32]> = inputs.iter().map(|c| c.as_slice()).collect();
        let cot: Vec<[f32; 1]> = cotangent.iter().map(|&x| [x]).collect();
        let cot: Vec<&[f32]> = cot.iter().map(|c| c.as_slice()).collect();
        let mut out = [[0.0f32; 1]; SHADER_INPUTS];
        let mut d: Vec<&mut [f32]> = out.iter_mut().map(|c| c.as_mut_slice()).collect();
        shader.shade_vjp(1, &inputs, &cot, &mut d);
        out.map(|c| c[0])
    }

    /// A splat's inputs: a base color, coefficients, and an offset at least 0.5 long.
    fn splat() -> impl Strategy<Value = [f32; SHADER_INPUTS]> {
        (
            prop::array::uniform3(0.0f32..1.0),
            prop::array::uniform9(-0.6f32..0.6),
            prop::array::uniform3(-3.0f32..3.0),
        )
            .prop_filter("an offset away from the camera", |(_, _, o)| {
                o.iter().map(|x| x * x).sum::<f32>() > 0.25
            })
            .prop_map(|(base, sh, offset)| {
                let mut x = [0.0; SHADER_INPUTS];
                x[..3].copy_from_slice(&base);
                x[3..12].copy_from_slice(&sh);
                x[12..].copy_from_slice(&offset);
                x
            })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// The compiled shader gives the formula's colors, within rounding, in batches of any length
        /// (the kernel's last partial group of lanes included).
        #[test]
        fn the_compiled_shader_is_the_formula(points in prop::collection::vec(splat(), 1..11)) {
            let shader = splat_shader().unwrap();
            for (got, point) in colors(shader, &points).iter().zip(&points) {
                let want = formula(point);
                for c in 0..3 {
                    prop_assert!((got[c] - want[c]).abs() < 1e-6, "{got:?} vs {want:?}");
                }
            }
        }

        /// Its derivatives in every input match central differences of the formula (channels near the
        /// clamp's edges, where differences straddle the kink, are left out).
        #[test]
        fn its_derivatives_match_differences(
            point in splat(),
            cotangent in prop::array::uniform3(-1.0f32..1.0),
        ) {
            let shader = splat_shader().unwrap();
            prop_assume!(unclamped(&point).iter().all(|r| r.abs() > 0.01 && (r - 1.0).abs() > 0.01));
            let loss = |x: &[f32; SHADER_INPUTS]| -> f64 {
                let c = formula(x);
                (0..3).map(|k| f64::from(cotangent[k]) * f64::from(c[k])).sum()
            };
            let got = vjp(shader, &point, cotangent);
            let h = 1e-3f32;
            for k in 0..SHADER_INPUTS {
                let (mut up, mut down) = (point, point);
                up[k] += h;
                down[k] -= h;
                let numeric = (loss(&up) - loss(&down)) / f64::from(2.0 * h);
                prop_assert!(
                    (numeric - f64::from(got[k])).abs() < 2e-3,
                    "input {k}: differences {numeric}, the kernel {}", got[k]
                );
            }
        }
    }

    /// The shader's colors follow the direction: seen along −y, +z and −x, each coefficient adds C1 times
    /// itself to the color.
    #[test]
    fn the_first_degree_follows_the_direction() {
        let shader = splat_shader().unwrap();
        let mut x = [0.0f32; SHADER_INPUTS];
        x[..3].copy_from_slice(&[0.5, 0.4, 0.3]);
        x[3] = 0.2; // h₀'s red
        x[7] = 0.2; // h₁'s green
        x[11] = 0.2; // h₂'s blue
        let seen = |x: [f32; SHADER_INPUTS], offset: [f32; 3]| {
            let mut p = x;
            p[12..].copy_from_slice(&offset);
            colors(shader, &[p])[0]
        };
        let c1 = 0.488_602_5 * 0.2;
        let close = |a: [f32; 3], b: [f32; 3]| a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-6);
        assert!(close(seen(x, [0.0, -2.0, 0.0]), [0.5 + c1, 0.4, 0.3]));
        assert!(close(seen(x, [0.0, 0.0, 3.0]), [0.5, 0.4 + c1, 0.3]));
        assert!(close(seen(x, [-0.5, 0.0, 0.0]), [0.5, 0.4, 0.3 + c1]));
        // And clamps to [0, 1].
        x[0] = 0.95;
        x[3] = 1.0;
        assert_eq!(seen(x, [0.0, -1.0, 0.0])[0], 1.0);
    }
}
