//! Networks with dense layers: the tiled kernels (JIT segments + matrix products) of every kernel kind
//! against the f64 interpreter, on random layer sizes, random points and batches that do not fill the
//! last tile; and the second-order kernel's param gradient against finite differences of the first-order
//! kernel.

use crate::common::{close, interp_eval, jit_eval};
use nerfjit_dsl::{compile, interp, kernel_graphs, Program};
use nerfjit_jit::{Kernel, Options, Precision};
use proptest::prelude::*;

/// An MLP of the given hidden widths on a harmonic embedding of p, with a skip connection into the last
/// hidden layer and two heads (a scalar and a vec3), in the shape of the course's networks.
fn network(widths: &[usize], activation: &str) -> Program {
    let mut src = String::new();
    let embed = 3 + 3 * 2 * 2;
    let mut fan_in = embed;
    for (l, &w) in widths.iter().enumerate() {
        let skip = if l + 1 == widths.len() && l > 0 { embed } else { 0 };
        src += &format!(
            "param w{l}: mat<{w}, {}> = linear_init(seed: {l})\nparam b{l}: vec<{w}> = uniform(-0.5, 0.5, seed: {})\n",
            fan_in + skip,
            l + 50
        );
        fan_in = w;
    }
    src += &format!("param wd: mat<1, {fan_in}> = linear_init(seed: 90)\nparam wc: mat<3, {fan_in}> = linear_init(seed: 91)\n");
    src += "fn body(p: vec3) -> vec<";
    src += &format!("{fan_in}> {{\n  let e = harmonic(p, 2)\n  let h0 = {activation}(dense(w0, b0, e))\n");
    for l in 1..widths.len() {
        let input = if l + 1 == widths.len() {
            format!("concat(h{}, e)", l - 1)
        } else {
            format!("h{}", l - 1)
        };
        src += &format!("  let h{l} = {activation}(dense(w{l}, b{l}, {input}))\n");
    }
    src += &format!("  h{}\n}}\n", widths.len() - 1);
    src += "fn d(p: vec3) -> f32 = dense(wd, body(p))[0] + 0.1 * length(p)\n";
    src += "fn c(p: vec3) -> vec3 = sigmoid(dense(wc, body(p)))\n";
    compile("net.sdf", &src).unwrap_or_else(|r| panic!("{r}\n{src}"))
}

fn points(seed: u64, n: usize, extra: usize) -> Vec<Vec<f64>> {
    let mut s = seed | 1;
    let mut next = || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s % 10_000) as f64 / 5_000.0 - 1.0
    };
    (0..n).map(|_| (0..3 + extra).map(|_| next()).collect()).collect()
}

fn assert_outputs_match(name: &str, got: &[Vec<f32>], want: &[Vec<f64>]) {
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        for (k, (&a, &b)) in g.iter().zip(w).enumerate() {
            assert!(close(a, b, 2e-4, 1.0), "{name}: point {i} output {k}: {a} vs {b}");
        }
    }
}

fn assert_reductions_match(name: &str, got: &[f32], want: &[f64], n: usize) {
    let scale = want.iter().map(|w| w.abs()).fold(0.0, f64::max).max(1.0);
    for (k, (&a, &b)) in got.iter().zip(want).enumerate() {
        assert!(
            (f64::from(a) - b).abs() <= 1e-4 * scale * (n as f64).sqrt().max(1.0),
            "{name}: reduction {k}: {a} vs {b}"
        );
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(12))]

    #[test]
    fn tiled_kernels_match_the_interpreter(
        widths in prop::collection::vec(1usize..40, 1..4),
        n in 0usize..300,
        seed in any::<u64>(),
        relu in any::<bool>(),
    ) {
        let p = network(&widths, if relu { "relu" } else { "tanh" });
        let params = p.param_values_f64();
        let both = p.lower_many(&["d", "c"]).unwrap();
        let d = p.lower("d").unwrap();

        let pts = points(seed, n, 0);
        let g = kernel_graphs::value(&both);
        assert_outputs_match("value", &jit_eval(&g, &pts, &params, Options::default()).0, &interp_eval(&g, &pts, &params).0);
        let g = kernel_graphs::with_gradient(&d);
        assert_outputs_match("gradient", &jit_eval(&g, &pts, &params, Options::default()).0, &interp_eval(&g, &pts, &params).0);

        let pts = points(seed, n, 4);
        let g = kernel_graphs::vjp(&both, p.n_params());
        let (jo, jr) = jit_eval(&g, &pts, &params, Options::default());
        let (io, ir) = interp_eval(&g, &pts, &params);
        assert_outputs_match("vjp", &jo, &io);
        assert_reductions_match("vjp", &jr, &ir, n);
        let g = kernel_graphs::second_order(&d, p.n_params());
        let (jo, jr) = jit_eval(&g, &pts, &params, Options::default());
        let (io, ir) = interp_eval(&g, &pts, &params);
        assert_outputs_match("second order", &jo, &io);
        assert_reductions_match("second order", &jr, &ir, n);
    }

    /// The training kernel split into a forward pass that keeps its values and a backward pass over them,
    /// called on batches of any size, each batch's backward pass after its forward pass or one backward
    /// pass after all the forward passes: the outputs and reductions of the interpreter, and for one batch
    /// the very bits of the unsplit kernel, which recomputes nothing differently.
    #[test]
    fn split_passes_match_the_unsplit_kernel_and_the_interpreter(
        widths in prop::collection::vec(1usize..40, 1..4),
        batches in prop::collection::vec(0usize..300, 1..4),
        seed in any::<u64>(),
        relu in any::<bool>(),
        bf16 in any::<bool>(),
        one_backward in any::<bool>(),
    ) {
        let p = network(&widths, if relu { "relu" } else { "tanh" });
        let params = p.param_values_f64();
        let both = p.lower_many(&["d", "c"]).unwrap();
        let g = kernel_graphs::forward_backward(&both, p.n_params());
        let products = if bf16 { Precision::Bf16 } else { Precision::F32 };
        let split = Kernel::compile(&g, Options { products, split: Some(3), ..Options::default() }).unwrap();
        let params32: Vec<f32> = params.iter().map(|&x| x as f32).collect();
        let mut passes = split.passes(&params32).expect("a split network kernel runs as passes");
        let n: usize = batches.iter().sum();
        let pts = points(seed, n, 4);
        let cols: Vec<Vec<f32>> = (0..7).map(|c| pts.iter().map(|p| p[c] as f32).collect()).collect();
        let mut outs = vec![vec![0.0f32; n]; 4];
        let mut reductions = vec![0.0f32; g.reductions.len()];
        let mut start = 0;
        for &b in &batches {
            let ins: Vec<&[f32]> = cols[..3].iter().map(|c| &c[start..start + b]).collect();
            let cots: Vec<&[f32]> = cols[3..].iter().map(|c| &c[start..start + b]).collect();
            let mut out: Vec<&mut [f32]> = outs.iter_mut().map(|o| &mut o[start..start + b]).collect();
            passes.forward(b, &ins, &mut out);
            if !one_backward {
                passes.backward(b, &cots, &mut reductions);
            }
            start += b;
        }
        if one_backward {
            let cots: Vec<&[f32]> = cols[3..].iter().map(|c| &c[..n]).collect();
            passes.backward(n, &cots, &mut reductions);
        }
        passes.finish(&mut reductions);
        let per_point: Vec<Vec<f32>> = (0..n).map(|i| outs.iter().map(|o| o[i]).collect()).collect();
        let (io, ir) = interp_eval(&g, &pts, &params);
        if bf16 {
            for (got, want) in per_point.iter().flatten().zip(io.iter().flatten()) {
                prop_assert!(close(*got, *want, 0.03, 1.0), "output {} vs {}", got, want);
            }
        } else {
            assert_outputs_match("split passes", &per_point, &io);
            assert_reductions_match("split passes", &reductions, &ir, n);
        }
        if batches.len() == 1 {
            let (wo, wr) = jit_eval(&g, &pts, &params, Options { products, ..Options::default() });
            prop_assert_eq!(&per_point, &wo);
            prop_assert_eq!(&reductions, &wr);
            let (so, sr) = jit_eval(&g, &pts, &params, Options { products, split: Some(3), ..Options::default() });
            prop_assert_eq!(&so, &wo);
            prop_assert_eq!(&sr, &wr);
        }
    }

    #[test]
    fn second_order_param_gradient_matches_finite_differences(
        widths in prop::collection::vec(1usize..12, 1..3),
        seed in any::<u64>(),
    ) {
        // L(θ) = c_f·d(x) + c_g·∇ₓd(x): the second-order kernel's reductions are ∂L/∂θ.
        let p = network(&widths, "tanh");
        let d = p.lower("d").unwrap();
        let first = kernel_graphs::with_gradient(&d);
        let second = kernel_graphs::second_order(&d, p.n_params());
        let pt = &points(seed, 1, 4)[0];
        let loss = |theta: &[f64]| {
            let out = interp::eval_point(&first, &pt[..3], theta).outputs;
            (0..4).map(|k| pt[3 + k] * out[k]).sum::<f64>()
        };
        let params = p.param_values_f64();
        let analytic = interp::eval_point(&second, pt, &params).reductions;
        prop_assert_eq!(analytic.len(), params.len());
        for k in 0..params.len() {
            let mut hi = params.clone();
            let mut lo = params.clone();
            hi[k] += 1e-6;
            lo[k] -= 1e-6;
            let fd = (loss(&hi) - loss(&lo)) / 2e-6;
            prop_assert!((fd - analytic[k]).abs() < 1e-5 * (1.0 + fd.abs()), "param {}: {} vs {}", k, analytic[k], fd);
        }
    }
}

/// A wide layer (the course's 128) and a batch of several tiles, through the JIT with every kind.
#[test]
fn course_width_layers_match_the_interpreter() {
    let p = network(&[128, 128], "relu");
    let params = p.param_values_f64();
    let d = p.lower("d").unwrap();
    let pts = points(7, 300, 4);
    let g = kernel_graphs::second_order(&d, p.n_params());
    let (jo, jr) = jit_eval(&g, &pts, &params, Options::default());
    let (io, ir) = interp_eval(&g, &pts, &params);
    assert_outputs_match("second order", &jo, &io);
    assert_reductions_match("second order", &jr, &ir, 300);
}

/// `products: Bf16`: the value and param-gradient kernels of a course-shaped network stay within
/// bfloat16's accuracy of the interpreter (two roundings of 2⁻⁹ per product operand, through three layers),
/// and differ from the f32 kernels' results (the setting reaches the products, on AMX or not).
#[test]
fn bf16_products_stay_within_bfloat16_accuracy() {
    let bf16 = Options {
        products: Precision::Bf16,
        ..Options::default()
    };
    let p = network(&[128, 64, 48], "relu");
    let params = p.param_values_f64();
    let both = p.lower_many(&["d", "c"]).unwrap();
    let n = 300;
    let pts = points(11, n, 4);
    let g = kernel_graphs::vjp(&both, p.n_params());
    let (bo, br) = jit_eval(&g, &pts, &params, bf16);
    let (fo, fr) = jit_eval(&g, &pts, &params, Options::default());
    let (io, ir) = interp_eval(&g, &pts, &params);
    let mut largest_change = 0.0f64;
    for ((b, f), want) in bo.iter().zip(&fo).zip(&io) {
        for ((&b, &f), &w) in b.iter().zip(f).zip(want) {
            assert!(close(b, w, 0.03, 1.0), "output {b} vs {w}");
            largest_change = largest_change.max(f64::from((b - f).abs()));
        }
    }
    assert!(largest_change > 1e-5, "bf16 products gave the f32 results");
    let scale = ir.iter().fold(0.0f64, |m, w| m.max(w.abs()));
    for (k, (&b, &w)) in br.iter().zip(&ir).enumerate() {
        assert!(
            (f64::from(b) - w).abs() <= 0.03 * scale,
            "param gradient {k}: {b} vs {w} (scale {scale})"
        );
    }
    assert!(br
        .iter()
        .zip(&fr)
        .any(|(b, f)| (b - f).abs() > 1e-6 * scale as f32));
}
