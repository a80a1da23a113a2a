//! Every IR op, compiled by the JIT, against the interpreter on "spicy" inputs (±0, ±1, ±π, huge, tiny,
//! ±∞, NaN) in every pairing, with batch sizes that leave unaligned tails.

use crate::common::{close, interp_eval, jit_eval};
use nerfjit_dsl::ir::{Graph, Op, V};
use nerfjit_jit::Options;

const SPICY: [f64; 14] = [
    0.0,
    -0.0,
    1.0,
    -1.0,
    0.5,
    -2.5,
    std::f64::consts::PI,
    -std::f64::consts::PI,
    1e30,
    -1e-30,
    7.25,
    f64::INFINITY,
    f64::NEG_INFINITY,
    f64::NAN,
];

fn all_ops(a: V, b: V, c: V) -> Vec<Op> {
    use Op::*;
    vec![
        Neg(a),
        Abs(a),
        Sign(a),
        Floor(a),
        Sqrt(a),
        Exp(a),
        Log(a),
        Sin(a),
        Cos(a),
        Tan(a),
        Tanh(a),
        Sigmoid(a),
        Softplus(a),
        TruncExp(a),
        Add(a, b),
        Sub(a, b),
        Mul(a, b),
        Div(a, b),
        Min(a, b),
        Max(a, b),
        Lt(a, b),
        Le(a, b),
        Eq(a, b),
        Select(c, a, b),
    ]
}

#[test]
fn every_op_matches_the_interpreter_on_spicy_inputs() {
    let mut g = Graph::new();
    let (a, b, c) = (g.input(0), g.input(1), g.input(2));
    let ops = all_ops(a, b, c);
    for op in &ops {
        let v = g.push(*op);
        g.outputs.push(v);
    }
    let mut points = Vec::new();
    for &x in &SPICY {
        for &y in &SPICY {
            points.push(vec![x, y, if x > y { 1.0 } else { 0.0 }]);
        }
    }
    for n in [points.len(), points.len() - 1, 3, 1, 0] {
        let pts = &points[..n];
        let (got, _) = jit_eval(&g, pts, &[], Options::default());
        let (want, _) = interp_eval(&g, pts, &[]);
        for (i, (gp, wp)) in got.iter().zip(&want).enumerate() {
            for (k, (&gv, &wv)) in gp.iter().zip(wp).enumerate() {
                let x = pts[i][0];
                // sin/cos/tan of huge arguments are outside the approximation's range.
                let huge_trig = matches!(ops[k], Op::Sin(_) | Op::Cos(_) | Op::Tan(_)) && x.abs() > 1e4;
                let scale = if matches!(ops[k], Op::Tan(_)) { 1e-3 } else { 1.0 };
                assert!(
                    huge_trig || close(gv, wv, 1e-6, scale) || (wv.abs() > 3.4e38 && gv.is_infinite()),
                    "{:?} at {:?}: jit {gv}, interpreter {wv}",
                    ops[k],
                    &pts[i]
                );
            }
        }
    }
}

#[test]
fn reductions_sum_exactly_the_valid_points() {
    for n in 0..=17 {
        let mut g = Graph::new();
        let x = g.input(0);
        let p = g.param(0);
        let y = g.push(Op::Mul(x, p));
        g.outputs.push(y);
        g.reductions.push(x);
        g.reductions.push(y);
        let points: Vec<Vec<f64>> = (0..n).map(|i| vec![i as f64 + 1.0]).collect();
        let (out, red) = jit_eval(&g, &points, &[2.0], Options::default());
        let total = (n * (n + 1) / 2) as f32;
        assert_eq!(red, vec![total, 2.0 * total], "n = {n}");
        assert!(out
            .iter()
            .enumerate()
            .all(|(i, o)| o[0] == 2.0 * (i as f32 + 1.0)));
    }
}

#[test]
fn many_reductions_sum_in_memory_like_few_in_registers() {
    // 20 reductions exceed what the kernel keeps in registers; both paths must agree with the sums.
    for n in [0usize, 1, 3, 4, 5, 17, 64] {
        let mut g = Graph::new();
        let x = g.input(0);
        for k in 0..20 {
            let p = g.param(k);
            let term = g.push(Op::Mul(x, p));
            g.reductions.push(term);
        }
        let points: Vec<Vec<f64>> = (0..n).map(|i| vec![i as f64 + 0.5]).collect();
        let params: Vec<f64> = (0..20).map(|k| k as f64 - 3.0).collect();
        let (_, red) = jit_eval(&g, &points, &params, Options::default());
        let total: f64 = points.iter().map(|p| p[0]).sum();
        for (k, r) in red.iter().enumerate() {
            assert_eq!(f64::from(*r), total * params[k], "n = {n}, reduction {k}");
        }
    }
}

/// A function large enough for single-pass register allocation (more than 12,000 nodes, thousands of values
/// live at once) computes what the interpreter does.
#[test]
fn large_functions_compile_with_the_single_pass_allocator_and_agree() {
    let mut g = Graph::new();
    let (x, y) = (g.input(0), g.input(1));
    // Many terms computed first and summed last: all of them are live across the whole function.
    let mut terms = Vec::new();
    for k in 0..2500 {
        let c = g.constant(0.001 * f64::from(k) + 0.5);
        let xc = g.push(Op::Mul(x, c));
        let s = g.push(Op::Add(xc, y));
        let t = g.push(Op::Mul(s, s));
        let u = g.push(Op::Min(t, c));
        terms.push(g.push(Op::Max(u, xc)));
    }
    let mut sum = terms[0];
    for &t in &terms[1..] {
        sum = g.push(Op::Add(sum, t));
    }
    g.outputs.push(sum);
    g.n_inputs = 2;
    assert!(g.len() > 12_000, "{} nodes", g.len());
    let points: Vec<Vec<f64>> = (0..9)
        .map(|i| vec![0.3 * f64::from(i) - 1.0, 0.7 - 0.1 * f64::from(i)])
        .collect();
    let (got, _) = jit_eval(&g, &points, &[], Options::default());
    let (want, _) = interp_eval(&g, &points, &[]);
    for (gp, wp) in got.iter().zip(&want) {
        assert!(
            close(gp[0], wp[0], 1e-4, 1.0),
            "jit {} vs interpreter {}",
            gp[0],
            wp[0]
        );
    }
}

#[test]
fn selects_with_a_zero_branch_give_the_bits_of_the_branch_taken() {
    // A +0.0 branch compiles to an and with the mask, a −0.0 one to a blend: either way the bits of the
    // branch taken, the sign of a zero included.
    let mut g = Graph::new();
    let (a, b, c) = (g.input(0), g.input(1), g.input(2));
    let (zero, negative_zero) = (g.constant(0.0), g.constant(-0.0));
    let less = g.push(Op::Lt(a, b));
    for condition in [c, less] {
        for (x, y) in [(a, zero), (zero, a), (a, negative_zero), (negative_zero, a)] {
            let v = g.push(Op::Select(condition, x, y));
            g.outputs.push(v);
        }
    }
    let points: Vec<Vec<f64>> = SPICY
        .iter()
        .flat_map(|&x| {
            SPICY
                .iter()
                .map(move |&y| vec![x, y, if x > y { 1.0 } else { 0.0 }])
        })
        .collect();
    let (got, _) = jit_eval(&g, &points, &[], Options::default());
    let (want, _) = interp_eval(&g, &points, &[]);
    for (p, (gp, wp)) in points.iter().zip(got.iter().zip(&want)) {
        for (k, (&gv, &wv)) in gp.iter().zip(wp).enumerate() {
            let same = (gv.is_nan() && wv.is_nan()) || gv.to_bits() == (wv as f32).to_bits();
            assert!(same, "select {k} at {p:?}: jit {gv:e}, interpreter {wv:e}");
        }
    }
}
