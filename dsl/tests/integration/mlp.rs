//! `mlp<I, W, D, skip: k>` params and the `mlp` builtin: the same function as its layers written out, its
//! initialization per layer, and its errors.

use nerfjit_dsl::interp::eval_point;
use nerfjit_dsl::{compile, kernel_graphs};

const SCRIPT: &str =
    "param net: mlp<3, 5, 3, skip: 2> = linear_init(seed: 4)\nfn f(p: vec3) -> vec<5> = mlp(net, p)\n";

/// relu(W·x + b) for the row-major block of `params` at `at`; returns the output and the next offset.
fn layer(params: &[f64], at: usize, rows: usize, x: &[f64]) -> (Vec<f64>, usize) {
    let cols = x.len();
    let out = (0..rows)
        .map(|r| {
            let z: f64 = (0..cols).map(|c| params[at + r * cols + c] * x[c]).sum::<f64>()
                + params[at + rows * cols + r];
            z.max(0.0)
        })
        .collect();
    (out, at + rows * cols + rows)
}

#[test]
fn mlp_is_its_layers_written_out() {
    let p = compile("mlp.sdf", SCRIPT).unwrap_or_else(|r| panic!("{r}"));
    let params = p.param_values_f64();
    assert_eq!(params.len(), (5 * 3 + 5) + (5 * 5 + 5) + (5 * 8 + 5));
    let g = kernel_graphs::value(&p.lower("f").unwrap());
    for x in [[0.3, -0.2, 0.9], [-1.0, 0.5, 0.1], [2.0, 1.0, -3.0]] {
        let (h0, at) = layer(&params, 0, 5, &x);
        let (h1, at) = layer(&params, at, 5, &h0);
        let joined: Vec<f64> = h1.iter().chain(&x).copied().collect();
        let (h2, end) = layer(&params, at, 5, &joined);
        assert_eq!(end, params.len());
        let got = eval_point(&g, &x, &params).outputs;
        for (a, b) in got.iter().zip(&h2) {
            assert!((a - b).abs() < 1e-12, "{got:?} vs {h2:?}");
        }
    }
}

#[test]
fn linear_init_draws_each_layer_within_its_fan_in() {
    let p = compile("mlp.sdf", SCRIPT).unwrap();
    let params = p.param_values_f64();
    let mut at = 0;
    for cols in [3usize, 5, 8] {
        let bound = 1.0 / (cols as f64).sqrt();
        let block = &params[at..at + 5 * cols + 5];
        assert!(block.iter().all(|v| v.abs() <= bound), "layer with fan-in {cols}");
        // Not all at the bound: drawn, not constant.
        assert!(block.iter().any(|v| v.abs() < 0.5 * bound));
        at += 5 * cols + 5;
    }
}

#[test]
fn bad_mlps_are_diagnosed() {
    let cases = [
        ("param n: mlp<3, 4, 2, skip: 2> = 0.0\n", "skip layer"),
        ("param n: mlp<3, 4, 2, width: 2> = 0.0\n", "unknown mlp option"),
        ("param n: mlp<3, 4, 2> = linear_init(fan_in: 3)\n", "fan_in"),
        (
            "param n: mlp<3, 4, 2> = 0.0\nfn f(p: vec2) -> vec<4> = mlp(n, p)\n",
            "needs vec<3>",
        ),
        (
            "param n: mat<4, 3> = 0.0\nfn f(p: vec3) -> vec<4> = mlp(n, p)\n",
            "needs an mlp param",
        ),
    ];
    for (src, expected) in cases {
        let report = compile("bad.sdf", src)
            .err()
            .unwrap_or_else(|| panic!("accepted: {src}"));
        let text = report.to_string();
        assert!(text.contains(expected), "{src}: {text}");
    }
}
