//! The color a splat shows from the direction it is seen along: a [`SplatShader`], a batch function that
//! the runtime calls on columns of splats and that a script function compiled by the JIT implements (the
//! runtime never depends on the JIT; `nerfjit-field` supplies it). Splats without spherical harmonics show
//! their base color and need no shader.
//!
//! The shader of baked splats (`nerfjit-field`'s `splat_shader.sdf`) shades them as 3D Gaussian splatting
//! does, truncated to the first degree: color(d) = base + C1 · (−d_y · h₀ + d_z · h₁ − d_x · h₂), d the unit
//! vector from the camera to the splat's center and h₀..₂ its coefficients (each an RGB triple), clamped to
//! [0, 1].

use std::cell::RefCell;

use glam::Vec3;

/// The degree-0 spherical harmonic, 1 / (2 √π): the `.ply` layout's `f_dc` is (color − 0.5) / C0.
pub(crate) const SH_C0: f32 = 0.282_094_8;

/// The columns a [`SplatShader`] reads per splat: its base color (3), its degree-one coefficients h₀, h₁ and
/// h₂ (each RGB, 9), and the offset from the camera to its center (3), in that order.
pub const SHADER_INPUTS: usize = 15;

/// The color of splats seen from a camera, and its derivatives, n splats at a time in columns (one slice per
/// scalar, structure of arrays): [`SHADER_INPUTS`] columns in, the three channels of the color out.
pub trait SplatShader: Sync {
    /// Writes the colors of splats `0..n` (`colors[c][i]`, channel c) from their `inputs` (columns).
    fn shade(&self, n: usize, inputs: &[&[f32]], colors: &mut [&mut [f32]]);

    /// Writes, for splats `0..n`, the derivative of Σ_c `cotangents[c][i]` · color_c with respect to each of
    /// their inputs (`d_inputs[k][i]`, [`SHADER_INPUTS`] columns).
    fn shade_vjp(&self, n: usize, inputs: &[&[f32]], cotangents: &[&[f32]], d_inputs: &mut [&mut [f32]]);
}

/// One splat's shader inputs.
#[derive(Clone, Copy)]
pub(super) struct Seen {
    pub base: [f32; 3],
    pub sh: [[f32; 3]; 3],
    pub offset: Vec3,
}

/// One splat's derivatives through its shader.
pub(super) struct ShadeGradient {
    pub base: [f32; 3],
    pub sh: [[f32; 3]; 3],
    pub offset: Vec3,
}

/// The shader's inputs of a batch of splats (a row each as they are added, then columns), and its output
/// columns.
#[derive(Default)]
pub(super) struct ShaderBatch {
    rows: Vec<[f32; SHADER_INPUTS]>,
    columns: [Vec<f32>; SHADER_INPUTS],
    colors: [Vec<f32>; 3],
}

thread_local! {
    /// Each thread's batch, kept from frame to frame: the memory of fresh columns costs page faults.
    static BATCH: RefCell<ShaderBatch> = RefCell::default();
}

impl ShaderBatch {
    /// Calls `f` with this thread's batch, empty.
    pub fn with<T>(f: impl FnOnce(&mut ShaderBatch) -> T) -> T {
        BATCH.with_borrow_mut(|batch| {
            batch.rows.clear();
            f(batch)
        })
    }

    /// Adds a splat.
    pub fn push(&mut self, seen: &Seen) {
        let [h0, h1, h2] = seen.sh;
        let ([r, g, b], o) = (seen.base, seen.offset);
        self.rows.push([
            r, g, b, h0[0], h0[1], h0[2], h1[0], h1[1], h1[2], h2[0], h2[1], h2[2], o.x, o.y, o.z,
        ]);
    }

    /// Turns the rows into the shader's input columns.
    fn fill_columns(&mut self) {
        let n = self.rows.len();
        for (k, column) in self.columns.iter_mut().enumerate() {
            column.resize(n, 0.0);
            for (x, row) in column.iter_mut().zip(&self.rows) {
                *x = row[k];
            }
        }
    }

    /// The batch's colors, in the order the splats were added.
    pub fn colors(&mut self, shader: &dyn SplatShader) -> impl Iterator<Item = [f32; 3]> + '_ {
        let n = self.rows.len();
        for column in &mut self.colors {
            column.resize(n, 0.0);
        }
        self.fill_columns();
        let inputs: Vec<&[f32]> = self.columns.iter().map(Vec::as_slice).collect();
        let mut outputs: Vec<&mut [f32]> = self.colors.iter_mut().map(Vec::as_mut_slice).collect();
        shader.shade(n, &inputs, &mut outputs);
        let [r, g, b] = &self.colors;
        (0..n).map(move |i| [r[i], g[i], b[i]])
    }

    /// The derivatives of Σ `cotangents[i]` · color of splat i with respect to each splat's inputs.
    pub fn gradients(&mut self, shader: &dyn SplatShader, cotangents: &[[f32; 3]]) -> Vec<ShadeGradient> {
        let n = self.rows.len();
        assert_eq!(cotangents.len(), n, "one cotangent per splat");
        let cot: [Vec<f32>; 3] = std::array::from_fn(|c| cotangents.iter().map(|g| g[c]).collect());
        let cot: Vec<&[f32]> = cot.iter().map(Vec::as_slice).collect();
        let mut out: [Vec<f32>; SHADER_INPUTS] = std::array::from_fn(|_| vec![0.0; n]);
        let mut d_inputs: Vec<&mut [f32]> = out.iter_mut().map(Vec::as_mut_slice).collect();
        self.fill_columns();
        let inputs: Vec<&[f32]> = self.columns.iter().map(Vec::as_slice).collect();
        shader.shade_vjp(n, &inputs, &cot, &mut d_inputs);
        (0..n)
            .map(|i| ShadeGradient {
                base: std::array::from_fn(|c| out[c][i]),
                sh: std::array::from_fn(|k| std::array::from_fn(|c| out[3 + 3 * k + c][i])),
                offset: Vec3::new(out[12][i], out[13][i], out[14][i]),
            })
            .collect()
    }
}

/// The formula of the baked splats' shader written in Rust, for the runtime's own tests (which cannot
/// reach the JIT); `nerfjit-field`'s tests check the compiled shader against the same formula.
#[cfg(test)]
pub(crate) mod formula {
    use super::*;

    /// The degree-1 spherical harmonics' factor, √3 / (2 √π).
    const SH_C1: f32 = 0.488_602_5;

    /// The shader as a formula.
    pub(crate) struct Formula;

    fn at(inputs: &[&[f32]], i: usize) -> ([f32; 3], [[f32; 3]; 3], Vec3) {
        let x = |k: usize| inputs[k][i];
        let base = [x(0), x(1), x(2)];
        let sh = std::array::from_fn(|k| std::array::from_fn(|c| x(3 + 3 * k + c)));
        (base, sh, Vec3::new(x(12), x(13), x(14)))
    }

    fn raw(base: [f32; 3], sh: &[[f32; 3]; 3], d: Vec3) -> [f32; 3] {
        let b = [-SH_C1 * d.y, SH_C1 * d.z, -SH_C1 * d.x];
        std::array::from_fn(|c| base[c] + b[0] * sh[0][c] + b[1] * sh[1][c] + b[2] * sh[2][c])
    }

    impl SplatShader for Formula {
        fn shade(&self, n: usize, inputs: &[&[f32]], colors: &mut [&mut [f32]]) {
            for i in 0..n {
                let (base, sh, offset) = at(inputs, i);
                for (column, x) in colors.iter_mut().zip(raw(base, &sh, offset.normalize())) {
                    column[i] = x.clamp(0.0, 1.0);
                }
            }
        }

        fn shade_vjp(&self, n: usize, inputs: &[&[f32]], cotangents: &[&[f32]], d_inputs: &mut [&mut [f32]]) {
            for i in 0..n {
                let (base, sh, offset) = at(inputs, i);
                let (distance, d) = (offset.length(), offset.normalize());
                let raw = raw(base, &sh, d);
                // A clamped channel passes nothing back.
                let g: [f32; 3] = std::array::from_fn(|c| {
                    if (0.0..=1.0).contains(&raw[c]) {
                        cotangents[c][i]
                    } else {
                        0.0
                    }
                });
                let b = [-SH_C1 * d.y, SH_C1 * d.z, -SH_C1 * d.x];
                for c in 0..3 {
                    d_inputs[c][i] = g[c];
                    for k in 0..3 {
                        d_inputs[3 + 3 * k + c][i] = b[k] * g[c];
                    }
                }
                // dL/d(basis k) = Σ_c g_c h_k,c; basis = C1 (−d_y, d_z, −d_x); d = offset / |offset|.
                let along = |k: usize| (0..3).map(|c| g[c] * sh[k][c]).sum::<f32>();
                let d_dir = SH_C1 * Vec3::new(-along(2), -along(0), along(1));
                let d_offset = (d_dir - d * d.dot(d_dir)) / distance;
                for (k, x) in d_offset.to_array().into_iter().enumerate() {
                    d_inputs[12 + k][i] = x;
                }
            }
        }
    }
}
