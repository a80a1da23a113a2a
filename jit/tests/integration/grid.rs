//! Grid encodings (hash grids and dense grids) and spherical harmonics: derivatives with respect to the
//! point and to the table against finite differences (first order, and the second-order param gradient of a
//! loss on ∇ₓf through the encoding), and the tiled JIT kernels of every kind against the f64 interpreter.

use crate::common::{close, interp_eval, jit_eval};
use nerfjit_dsl::{compile, interp, kernel_graphs, Program};
use nerfjit_jit::Options;
use proptest::prelude::*;

/// A small instant-ngp-shaped field: a hash grid (2 dense levels, the rest hashed into 64 entries) and a
/// dense grid, each read at p, through one tanh layer to a density and a color; the color also reads the
/// spherical harmonics of a direction.
fn field() -> Program {
    let src = "
param g: hashgrid<3, levels: 4, features: 2, log2_size: 6, base: 2, finest: 12, bounds: 1.2> = uniform(-0.5, 0.5, seed: 3)
param v: grid<3, res: 4, features: 3, bounds: 1.0> = uniform(-1.0, 1.0, seed: 4)
param w: mat<4, 11> = xavier(seed: 5)
param b: vec<4> = [0.1, -0.2, 0.05, 0.3]
param wc: mat<3, 13> = xavier(seed: 6)
fn features(p: vec3) -> vec<4> = tanh(dense(w, b, concat(hashgrid(g, p), grid(v, p))))
fn d(p: vec3) -> f32 = features(p)[0] + 0.5 * grid(v, p)[1] + 0.1 * length(p)
fn c(p: vec3, dir: vec3) -> vec3 = sigmoid(dense(wc, concat(features(p)[1], features(p)[2], features(p)[3], sh(normalize(dir), 3), grid(v, p)[0])))
";
    compile("grid.sdf", src).unwrap_or_else(|r| panic!("{r}"))
}

/// Random points in [−spread, spread]. The grid's derivatives jump at cell boundaries, where the JIT (f32)
/// and the interpreter (f64) may round to different sides; irregular spreads keep points off them.
fn points(seed: u64, n: usize, inputs: usize, spread: f64) -> Vec<Vec<f64>> {
    let mut s = seed | 1;
    let mut next = || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        ((s % 100_000) as f64 / 50_000.0 - 1.0) * spread
    };
    (0..n).map(|_| (0..inputs).map(|_| next()).collect()).collect()
}

/// A central difference at two step sizes, or None where they disagree (a cell boundary in the step).
fn smooth_difference(f: impl Fn(f64) -> f64, x: f64, h: f64) -> Option<f64> {
    let quotient = |h: f64| (f(x + h) - f(x - h)) / (2.0 * h);
    let (a, b) = (quotient(h), quotient(h / 2.0));
    ((a - b).abs() <= 1e-5 * (1.0 + a.abs())).then_some(b)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn point_and_table_gradients_match_finite_differences(seed in any::<u64>()) {
        let p = field();
        let params = p.param_values_f64();
        let d = p.lower("d").unwrap();
        let pt = points(seed, 1, 3, 1.1037).remove(0);
        let value = |x: &[f64], theta: &[f64]| interp::eval_point(&d.graph, x, theta).outputs[0];
        // ∂d/∂p
        let grad = interp::eval_point(&kernel_graphs::with_gradient(&d), &pt, &params).outputs;
        let mut compared = 0;
        for a in 0..3 {
            let along = |t: f64| {
                let mut q = pt.clone();
                q[a] = t;
                value(&q, &params)
            };
            if let Some(fd) = smooth_difference(along, pt[a], 1e-6) {
                compared += 1;
                prop_assert!((fd - grad[1 + a]).abs() < 1e-5 * (1.0 + fd.abs()), "d/dp{a}: {} vs {fd}", grad[1 + a]);
            }
        }
        prop_assert!(compared >= 2, "the point sits on cell boundaries along {} axes", 3 - compared);
        // ∂d/∂θ for every param, table entries included (zero where the point does not touch them).
        let vjp = kernel_graphs::vjp(&d, p.n_params());
        let mut inputs = pt.clone();
        inputs.push(0.7);
        let analytic = interp::eval_point(&vjp, &inputs, &params).reductions;
        prop_assert_eq!(analytic.len(), params.len());
        for k in 0..params.len() {
            let at = |t: f64| {
                let mut q = params.clone();
                q[k] = t;
                0.7 * value(&pt, &q)
            };
            let fd = (at(params[k] + 1e-6) - at(params[k] - 1e-6)) / 2e-6;
            prop_assert!((fd - analytic[k]).abs() < 1e-6 * (1.0 + fd.abs()), "param {k}: {} vs {fd}", analytic[k]);
        }
    }

    #[test]
    fn second_order_table_gradient_matches_finite_differences(seed in any::<u64>()) {
        // L(θ) = c_f·d(x) + c_g·∇ₓd(x), the form of the eikonal term: its param gradient goes through the
        // grid's derivative reads (mixed ∂²/∂θ∂p).
        let p = field();
        let d = p.lower("d").unwrap();
        let first = kernel_graphs::with_gradient(&d);
        let second = kernel_graphs::second_order(&d, p.n_params());
        let pt = points(seed, 1, 7, 1.1037).remove(0);
        let loss = |theta: &[f64]| {
            let out = interp::eval_point(&first, &pt[..3], theta).outputs;
            (0..4).map(|k| pt[3 + k] * out[k]).sum::<f64>()
        };
        let params = p.param_values_f64();
        let analytic = interp::eval_point(&second, &pt, &params).reductions;
        prop_assert_eq!(analytic.len(), params.len());
        let tables_end = p.params[2].offset;
        let mut table_terms = 0;
        for k in 0..params.len() {
            let mut hi = params.clone();
            let mut lo = params.clone();
            hi[k] += 1e-6;
            lo[k] -= 1e-6;
            let fd = (loss(&hi) - loss(&lo)) / 2e-6;
            table_terms += usize::from(k < tables_end && fd != 0.0);
            prop_assert!((fd - analytic[k]).abs() < 1e-5 * (1.0 + fd.abs()), "param {}: {} vs {}", k, analytic[k], fd);
        }
        prop_assert!(table_terms > 0, "no table entry was compared");
    }

    #[test]
    fn tiled_kernels_match_the_interpreter(n in 0usize..300, seed in any::<u64>()) {
        // Points range past the bounds (clamped reads) on both sides.
        let p = field();
        let params = p.param_values_f64();
        let both = p.lower_many(&["d", "c"]).unwrap();
        let d = p.lower("d").unwrap();
        let pts = points(seed, n, 6, 1.6171);
        for (name, g) in [("value", kernel_graphs::value(&both)), ("gradient", kernel_graphs::with_gradient(&d))] {
            let (jo, _) = jit_eval(&g, &pts, &params, Options::default());
            let (io, _) = interp_eval(&g, &pts, &params);
            for (i, (a, b)) in jo.iter().zip(&io).enumerate() {
                for (k, (&x, &y)) in a.iter().zip(b).enumerate() {
                    prop_assert!(close(x, y, 1e-3, 1.0), "{name}: point {i} output {k}: {x} vs {y}");
                }
            }
        }
        let pts = points(seed, n, 10, 1.6171);
        for (name, g) in [("vjp", kernel_graphs::vjp(&both, p.n_params())), ("second order", kernel_graphs::second_order(&d, p.n_params()))] {
            let (jo, jr) = jit_eval(&g, &pts, &params, Options::default());
            let (io, ir) = interp_eval(&g, &pts, &params);
            for (i, (a, b)) in jo.iter().zip(&io).enumerate() {
                for (k, (&x, &y)) in a.iter().zip(b).enumerate() {
                    prop_assert!(close(x, y, 1e-3, 1.0), "{name}: point {i} output {k}: {x} vs {y}");
                }
            }
            let scale = ir.iter().map(|w| w.abs()).fold(1.0, f64::max);
            for (k, (&x, &y)) in jr.iter().zip(&ir).enumerate() {
                prop_assert!((f64::from(x) - y).abs() <= 1e-4 * scale * (n as f64).sqrt().max(1.0), "{name}: reduction {k}: {x} vs {y}");
            }
        }
    }
}

/// The spherical harmonics are orthonormal over the sphere: Σ YᵢYⱼ·4π/N on a Fibonacci sphere ≈ δᵢⱼ.
#[test]
fn spherical_harmonics_are_orthonormal() {
    let p = compile("sh.sdf", "fn f(d: vec3) -> vec<16> = sh(d, 4)").unwrap();
    let g = kernel_graphs::value(&p.lower("f").unwrap());
    let n = 20_000;
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let mut gram = [[0.0f64; 16]; 16];
    for i in 0..n {
        let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
        let r = (1.0 - z * z).sqrt();
        let phi = golden * i as f64;
        let y = interp::eval_point(&g, &[r * phi.cos(), r * phi.sin(), z], &[]).outputs;
        for a in 0..16 {
            for b in 0..16 {
                gram[a][b] += y[a] * y[b] * 4.0 * std::f64::consts::PI / n as f64;
            }
        }
    }
    for (a, row) in gram.iter().enumerate() {
        for (b, &v) in row.iter().enumerate() {
            let want = if a == b { 1.0 } else { 0.0 };
            assert!((v - want).abs() < 1e-3, "⟨Y{a}, Y{b}⟩ = {v}");
        }
    }
    // Band 0 is the constant 1/(2√π); band 1 is (−y, z, −x)·√(3/4π), instant-ngp's signs.
    let y = interp::eval_point(&g, &[0.0, 0.0, 1.0], &[]).outputs;
    let c1 = (3.0 / (4.0 * std::f64::consts::PI)).sqrt();
    assert!((y[0] - 0.5 / std::f64::consts::PI.sqrt()).abs() < 1e-12);
    assert!((y[2] - c1).abs() < 1e-12 && y[1] == 0.0 && y[3] == 0.0);
}

/// A read touches exactly 8 entries per level (the scatter is sparse) and a table far larger than the
/// batch compiles to a kernel without a node per table float.
#[test]
fn large_tables_stay_out_of_the_graph() {
    let src = "param g: hashgrid<3, levels: 16, features: 2, log2_size: 19> = uniform(-1e-4, 1e-4)
param w: mat<1, 32> = xavier(seed: 1)
fn d(p: vec3) -> f32 = dense(w, hashgrid(g, p))[0]";
    let p = compile("big.sdf", src).unwrap();
    assert!(p.n_params() > 10_000_000, "{} params", p.n_params());
    let d = p.lower("d").unwrap();
    let g = kernel_graphs::vjp(&d, p.n_params());
    assert!(g.len() < 1_000, "the gradient graph has {} nodes", g.len());
    let params: Vec<f64> = p.param_values_f64();
    let pts = points(11, 1, 4, 1.0);
    let (_, reductions) = jit_eval(&g, &pts, &params, Options::default());
    let touched = reductions[..p.n_params() - 32]
        .iter()
        .filter(|&&r| r != 0.0)
        .count();
    assert!(
        (1..=16 * 8 * 2).contains(&touched),
        "{touched} table floats got a gradient"
    );
}

/// Settings out of range and tables beyond the memory limit are diagnostics, not allocations.
#[test]
fn grid_declarations_are_checked() {
    for (src, want) in [
        (
            "param g: hashgrid<3, log2_size: 40> = 0",
            "whole number from 4 to 26",
        ),
        (
            "param g: hashgrid<3, levels: 32, features: 64, log2_size: 26> = 0",
            "the limit is",
        ),
        ("param g: hashgrid<3, level: 4> = 0", "did you mean 'levels'?"),
        ("param g: hashgrid<2> = 0", "3-dimensional"),
        ("param g: hashgrid<3, base: 64, finest: 16> = 0", "below base"),
        ("param v: grid<3, features: 2> = 0", "needs its resolution"),
        ("param v: grid<3, res: 8, bounds: -1> = 0", "half extent"),
        (
            "param v: grid<3, res: 8> = 0\nfn f(p: vec3) -> f32 = hashgrid(v, p)[0]",
            "read a grid<3, res: 8",
        ),
        (
            "param g: hashgrid<3> = 0\nfn f(p: vec2) -> f32 = hashgrid(g, p)[0]",
            "reads a vec3",
        ),
    ] {
        let e = compile("bad.sdf", src)
            .err()
            .unwrap_or_else(|| panic!("{src} compiled"))
            .to_string();
        assert!(e.contains(want), "{src}: {e}");
    }
}
