//! Property tests on randomly generated programs: the JIT (f32) against the interpreter (f64); gradients
//! against central finite differences; second-order kernels against finite differences of first-order
//! ones; batch sizes 0..=17 so that every unaligned tail is exercised.

use crate::common::{close, interp_eval, jit_eval};
use nerfjit_dsl::autodiff::vjp;
use nerfjit_dsl::interp::eval_point;
use nerfjit_dsl::ir::{Graph, Op, V};
use nerfjit_jit::Options;
use proptest::prelude::*;

const N_INPUTS: u32 = 3;
const N_PARAMS: u32 = 2;

/// One generated node: an op kind and the (relative) indices of its arguments among earlier nodes.
#[derive(Clone, Debug)]
struct Gen {
    kind: u8,
    a: usize,
    b: usize,
}

/// Builds a graph from generated nodes, using only smooth, well-conditioned forms (so that f32 and f64
/// agree and finite differences are meaningful), plus min/max/abs when `kinks` is set.
fn build(nodes: &[Gen], kinks: bool) -> Graph {
    let mut g = Graph::new();
    let mut vals: Vec<V> = (0..N_INPUTS).map(|i| g.input(i)).collect();
    vals.extend((0..N_PARAMS).map(|i| g.param(i)));
    for n in nodes {
        let a = vals[n.a % vals.len()];
        let b = vals[n.b % vals.len()];
        let one = g.constant(1.0);
        let kinds = if kinks { 16 } else { 13 };
        let v = match n.kind % kinds {
            0 => g.push(Op::Add(a, b)),
            1 => g.push(Op::Sub(a, b)),
            2 => {
                let t = g.push(Op::Tanh(a));
                g.push(Op::Mul(t, b))
            }
            3 => {
                let b2 = g.push(Op::Mul(b, b));
                let d = g.push(Op::Add(one, b2));
                g.push(Op::Div(a, d))
            }
            4 => g.push(Op::Sin(a)),
            5 => g.push(Op::Cos(a)),
            6 => g.push(Op::Tanh(a)),
            7 => g.push(Op::Sigmoid(a)),
            8 => {
                let t = g.push(Op::Tanh(a));
                g.push(Op::Softplus(t))
            }
            9 => {
                let t = g.push(Op::Tanh(a));
                // trunc_exp is exp where its argument stays inside ±15, as tanh's does.
                g.push(if n.b % 2 == 0 { Op::Exp(t) } else { Op::TruncExp(t) })
            }
            10 => {
                let a2 = g.push(Op::Mul(a, a));
                let s = g.push(Op::Add(one, a2));
                g.push(Op::Log(s))
            }
            11 => {
                let a2 = g.push(Op::Mul(a, a));
                let s = g.push(Op::Add(one, a2));
                g.push(Op::Sqrt(s))
            }
            12 => {
                let t = g.push(Op::Sin(b));
                g.push(Op::Mul(a, t))
            }
            13 => g.push(Op::Min(a, b)),
            14 => g.push(Op::Max(a, b)),
            _ => g.push(Op::Abs(a)),
        };
        vals.push(v);
    }
    let last = *vals.last().expect("values");
    let extra = vals[vals.len() / 2];
    g.outputs = vec![last, extra];
    g.n_inputs = N_INPUTS;
    g
}

fn nodes() -> impl Strategy<Value = Vec<Gen>> {
    prop::collection::vec(
        (any::<u8>(), any::<usize>(), any::<usize>()).prop_map(|(kind, a, b)| Gen { kind, a, b }),
        1..14,
    )
}

fn point() -> impl Strategy<Value = Vec<f64>> {
    prop::collection::vec(-2.0f64..2.0, N_INPUTS as usize)
}

fn params() -> impl Strategy<Value = Vec<f64>> {
    prop::collection::vec(-1.5f64..1.5, N_PARAMS as usize)
}

/// The input values, then the param values, of `g`.
fn inputs_and_params(g: &mut Graph) -> Vec<V> {
    let mut v: Vec<V> = (0..N_INPUTS).map(|i| g.input(i)).collect();
    v.extend((0..N_PARAMS).map(|i| g.param(i)));
    v
}

/// The sum of the outputs of `g`, weighted by `w`, as a function of inputs and params, in f64.
fn weighted(g: &Graph, w: &[f64], x: &[f64], p: &[f64]) -> f64 {
    eval_point(g, x, p)
        .outputs
        .iter()
        .zip(w)
        .map(|(o, w)| o * w)
        .sum()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(96))]

    #[test]
    fn jit_matches_interpreter(gen in nodes(), pts in prop::collection::vec(point(), 0..=17), p in params()) {
        let g = build(&gen, true);
        prop_assert_eq!(g.validate(), Ok(()));
        prop_assert_eq!(g.compact().validate(), Ok(()));
        let (got, _) = jit_eval(&g, &pts, &p, Options::default());
        let (want, _) = interp_eval(&g, &pts, &p);
        for (gp, wp) in got.iter().zip(&want) {
            for (&gv, &wv) in gp.iter().zip(wp) {
                prop_assert!(close(gv, wv, 2e-4, 1.0), "jit {gv} vs interpreter {wv}\n{g}");
            }
        }
    }

    #[test]
    fn gradients_match_finite_differences(gen in nodes(), x in point(), p in params(),
                                          w in prop::collection::vec(-1.0f64..1.0, 2)) {
        let mut g = build(&gen, false);
        let outs = g.outputs.clone();
        let seeds: Vec<(V, V)> = outs.iter().zip(&w).map(|(&o, &wk)| (o, g.constant(wk))).collect();
        let wrt = inputs_and_params(&mut g);
        let grads = vjp(&mut g, &seeds, &wrt);
        let mut gg = g.clone();
        gg.outputs = grads;
        prop_assert_eq!(gg.validate(), Ok(()));
        let analytic = eval_point(&gg, &x, &p).outputs;
        let h = 1e-6;
        for k in 0..(N_INPUTS + N_PARAMS) as usize {
            let (mut xp, mut xm, mut pp, mut pm) = (x.clone(), x.clone(), p.clone(), p.clone());
            if k < N_INPUTS as usize { xp[k] += h; xm[k] -= h; } else { pp[k - 3] += h; pm[k - 3] -= h; }
            let fd = (weighted(&g, &w, &xp, &pp) - weighted(&g, &w, &xm, &pm)) / (2.0 * h);
            prop_assert!((fd - analytic[k]).abs() <= 1e-5 * (1.0 + fd.abs()),
                "d/d{k}: analytic {} vs finite difference {fd}\n{g}", analytic[k]);
        }
    }

    #[test]
    fn jit_vjp_kernel_matches_interpreter(gen in nodes(), pts in prop::collection::vec(point(), 0..=17),
                                          p in params()) {
        // Inputs x (3) and cotangents (2); outputs: input gradients; reductions: param gradients.
        let mut g = build(&gen, true);
        let outs = g.outputs.clone();
        let seeds: Vec<(V, V)> = outs.iter().enumerate().map(|(k, &o)| (o, g.input(N_INPUTS + k as u32))).collect();
        let wrt = inputs_and_params(&mut g);
        let grads = vjp(&mut g, &seeds, &wrt);
        g.outputs = grads[..3].to_vec();
        g.reductions = grads[3..].to_vec();
        prop_assert_eq!(g.validate(), Ok(()));
        let pts: Vec<Vec<f64>> = pts.iter().map(|x| {
            let mut v = x.clone();
            v.extend([0.7, -0.3]);
            v
        }).collect();
        let (got, got_red) = jit_eval(&g, &pts, &p, Options::default());
        let (want, want_red) = interp_eval(&g, &pts, &p);
        let scale = want.iter().flatten().fold(1.0f64, |m, v| m.max(v.abs()));
        for (gp, wp) in got.iter().zip(&want) {
            for (&gv, &wv) in gp.iter().zip(wp) {
                prop_assert!(close(gv, wv, 1e-3, scale), "jit {gv} vs interpreter {wv}\n{g}");
            }
        }
        let scale = want_red.iter().fold(1.0f64, |m, v| m.max(v.abs()));
        for (&gv, &wv) in got_red.iter().zip(&want_red) {
            prop_assert!(close(gv, wv, 1e-3, scale * pts.len().max(1) as f64), "reduction {gv} vs {wv}");
        }
    }

    #[test]
    fn second_order_matches_finite_differences_of_first_order(gen in nodes(), x in point(), p in params(),
                                                              c in prop::collection::vec(-1.0f64..1.0, 4)) {
        // f = output 0; loss L(θ) = c₀ f + c₁..₃ · ∇ₓf; dL/dθ from the twice-differentiated graph vs
        // central differences of L computed with the once-differentiated graph.
        let mut g = build(&gen, false);
        let f = g.outputs[0];
        let one = g.constant(1.0);
        let xs: Vec<V> = (0..N_INPUTS).map(|i| g.input(i)).collect();
        let grad_x = vjp(&mut g, &[(f, one)], &xs);
        let mut first = g.clone();
        first.outputs = std::iter::once(f).chain(grad_x.iter().copied()).collect();
        let mut seeds = vec![(f, g.constant(c[0]))];
        for (k, &gk) in grad_x.iter().enumerate() {
            seeds.push((gk, g.constant(c[k + 1])));
        }
        let ps: Vec<V> = (0..N_PARAMS).map(|i| g.param(i)).collect();
        let second = vjp(&mut g, &seeds, &ps);
        let mut sg = g.clone();
        sg.outputs = second;
        prop_assert_eq!(sg.validate(), Ok(()));
        let analytic = eval_point(&sg, &x, &p).outputs;
        let h = 1e-5;
        for k in 0..N_PARAMS as usize {
            let (mut pp, mut pm) = (p.clone(), p.clone());
            pp[k] += h;
            pm[k] -= h;
            let fd = (weighted(&first, &c, &x, &pp) - weighted(&first, &c, &x, &pm)) / (2.0 * h);
            prop_assert!((fd - analytic[k]).abs() <= 1e-4 * (1.0 + fd.abs()),
                "d/dθ{k}: second order {} vs finite difference {fd}", analytic[k]);
        }
    }
}
