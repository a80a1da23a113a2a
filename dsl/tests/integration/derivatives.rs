//! Every builtin and prelude function: symbolic derivatives (the gradient kernel graph, evaluated by the
//! f64 interpreter) against central finite differences, at random points; plus closed forms.

use nerfjit_dsl::interp::eval_point;
use nerfjit_dsl::{compile, kernel_graphs, Program};
use proptest::prelude::*;

/// Expressions in x, y, z covering every builtin and prelude function.
const CASES: &[&str] = &[
    "neg(x) * y",
    "sin(x) + cos(y) * tan(0.5 * z)",
    "exp(x) * log(y * y + 0.1)",
    "trunc_exp(x) * y + trunc_exp(2.0 * z)",
    "sqrt(x * x + 0.5)",
    "abs(x) * y",
    "sign(x) * y + floor(y) * z + round(z) * x",
    "fract(x) + mod(y, 0.7)",
    "relu(x) + sigmoid(y) + softplus(z) + tanh(x * y)",
    "min(x, y) + max(y, z)",
    "pow(x * x + 0.5, y) + pow(z, 3) + pow(y * y + 1.0, 0.5) + pow(x * x + 1.0, -2)",
    "step(x, y) * z + select(x > y, x * z, y)",
    "clamp(x, -0.5, 0.5) + mix(x, y, z) + smoothstep(-1.0, 1.0, x)",
    "length(vec3(x, y, z)) + dot(vec3(x, y, z), vec3(z, x, y))",
    "cross(vec3(x, y, z), vec3(z, x, 1.0)).y + normalize(vec3(x, y, z)).x",
    "sum(vec3(x, y, z) * vec3(x, y, z)) + concat(vec2(x, y), z)[2] * x",
    "harmonic(vec3(x, y, z), 3)[7] + sum(harmonic(vec2(x, z), 2))",
    "if x < y { x * x } else { y * z } + (if x >= 0.0 && y != 1.0 { z } else { -z }) + (if !(x > 0.0) || y <= 0.0 { 1.0 } else { 2.0 })",
    "dense(w, b, vec3(x, y, z))[1] + dense(w, vec3(z, y, x))[0]",
    "sphere(vec3(x, y, z), 0.5) + box(vec3(x, y, z), vec3(1.0, 0.5, 0.8))",
    "rounded_box(vec3(x, y, z), vec3(1.0), 0.1) + torus(vec3(x, y, z), 1.0, 0.25) + torus_y(vec3(x, y, z), 0.8, 0.2)",
    "capsule(vec3(x, y, z), vec3(0.0), vec3(1.0, 0.5, 0.0), 0.3) + cylinder(vec3(x, y, z), 0.5, 1.0)",
    "plane(vec3(x, y, z), vec3(0.0, 1.0, 0.0), 0.5) + union(x, y) + intersection(y, z) + difference(x, z)",
    "smooth_union(x, y, 0.3) + smooth_intersection(y, z, 0.2) + smooth_difference(x, z, 0.4)",
    "sphere(rotate_x(translate(vec3(x, y, z), vec3(0.1)), 0.3), 0.4) + sphere(rotate_y(vec3(x, y, z), y), 1.0)",
    "box(rotate_z(scale(vec3(x, y, z), 2.0), 0.7), vec3(1.0)) * 2.0 + sphere(repeat(vec3(x, y, z), vec3(3.0)), 0.5)",
    "laplace_cdf(x, 0.5) + volsdf_density(y, 2.0, 0.3) + neus_density(z, 4.0)",
    "sigmoid_density(x, 2.0, 0.5) + step_density(y) + linear_density(z, 2.0, 0.5) + exp_density(x, 1.0, 0.5)",
    "opacity_laplace(x, 1.0, 0.5) + opacity_laplace(y)",
    "contract(vec3(x, y, z)).x + contract(vec3(2.0 * x, y + z, z)).z * y",
    "mlp(net, vec3(x, y, z))[2] * x + sum(mlp(net, vec3(z, x, y)))",
];

const PARAMS: &str = "param w: mat<2, 3> = xavier(seed: 3)\nparam b: vec<2> = [0.1, -0.2]\nparam net: mlp<3, 4, 3, skip: 2> = linear_init(seed: 5)\n";

fn program(expr: &str) -> Program {
    let src = format!("{PARAMS}fn f(x: f32, y: f32, z: f32) -> f32 = {expr}\n");
    compile("case.sdf", &src).unwrap_or_else(|r| panic!("{r}"))
}

fn value(p: &Program, g: &nerfjit_dsl::ir::Graph, x: &[f64]) -> f64 {
    eval_point(g, x, &p.param_values_f64()).outputs[0]
}

/// Central difference of f at x along axis k, or None where f is not smooth within the step (a kink or
/// jump: the difference quotients at two step sizes disagree).
fn smooth_difference(f: impl Fn(&[f64]) -> f64, x: &[f64], k: usize) -> Option<f64> {
    let quotient = |h: f64| {
        let (mut xp, mut xm) = (x.to_vec(), x.to_vec());
        xp[k] += h;
        xm[k] -= h;
        (f(&xp) - f(&xm)) / (2.0 * h)
    };
    let (a, b) = (quotient(1e-5), quotient(5e-6));
    ((a - b).abs() <= 1e-5 * (1.0 + a.abs())).then_some(b)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn symbolic_gradients_match_finite_differences(x in prop::collection::vec(-1.9f64..1.9, 3)) {
        let mut checked = 0;
        for expr in CASES {
            let p = program(expr);
            let f = p.lower("f").unwrap();
            let grad = kernel_graphs::with_gradient(&f);
            let analytic = eval_point(&grad, &x, &p.param_values_f64()).outputs;
            for k in 0..3 {
                if let Some(fd) = smooth_difference(|pt| value(&p, &f.graph, pt), &x, k) {
                    checked += 1;
                    prop_assert!((fd - analytic[1 + k]).abs() <= 2e-5 * (1.0 + fd.abs()),
                        "{expr}: d/d{} = {} but finite differences give {fd} at {x:?}", ["x", "y", "z"][k], analytic[1 + k]);
                }
            }
        }
        // Kinks and jumps are skipped, but only rarely: most derivatives are compared.
        prop_assert!(checked * 10 >= CASES.len() * 3 * 8, "only {checked} derivatives compared");
    }

    #[test]
    fn param_gradients_match_finite_differences(x in prop::collection::vec(-1.9f64..1.9, 3), c in -1.0f64..1.0) {
        for expr in CASES.iter().filter(|e| e.contains("dense(") || e.contains("mlp(")) {
        let p = program(expr);
        let f = p.lower("f").unwrap();
        let g = kernel_graphs::vjp(&f, p.n_params());
        let params = p.param_values_f64();
        let mut inputs = x.clone();
        inputs.push(c);
        let analytic = eval_point(&g, &inputs, &params).reductions;
        for k in 0..params.len() {
            let at = |pk: f64| {
                let mut q = params.clone();
                q[k] = pk;
                c * eval_point(&f.graph, &x, &q).outputs[0]
            };
            let fd = (at(params[k] + 1e-6) - at(params[k] - 1e-6)) / 2e-6;
            // A ReLU kink within the step makes the difference quotient meaningless: skip those.
            let smooth = |h: f64| (at(params[k] + h) - at(params[k] - h)) / (2.0 * h);
            if (smooth(1e-6) - smooth(5e-7)).abs() > 1e-6 * (1.0 + fd.abs()) {
                continue;
            }
            prop_assert!((fd - analytic[k]).abs() < 1e-6 * (1.0 + fd.abs()), "{expr} param {k}: {} vs {fd}", analytic[k]);
        }
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(16))]

    /// `vjp_backward` against central differences of what it differentiates, w·g with g the input gradient
    /// that `vjp` computes, in the points, the cotangent and the params (skipping kinks).
    #[test]
    fn vjp_backward_matches_finite_differences_of_the_input_gradient(
        x in prop::collection::vec(-1.9f64..1.9, 3),
        c in -1.0f64..1.0,
        w in prop::collection::vec(-1.0f64..1.0, 3),
    ) {
        let mut checked = 0;
        for expr in CASES {
            let p = program(expr);
            let f = p.lower("f").unwrap();
            let (first, second) = (kernel_graphs::vjp(&f, p.n_params()), kernel_graphs::vjp_backward(&f, p.n_params()));
            let params = p.param_values_f64();
            // w·g at the inputs x, cotangent c, params q.
            let wg = |xc: &[f64], q: &[f64]| {
                let g = eval_point(&first, xc, q).outputs;
                (0..3).map(|j| w[j] * g[1 + j]).sum::<f64>()
            };
            let inputs: Vec<f64> = x.iter().copied().chain([c]).chain(w.iter().copied()).collect();
            let analytic = eval_point(&second, &inputs, &params);
            let xc: Vec<f64> = x.iter().copied().chain([c]).collect();
            for k in 0..4 {
                if let Some(fd) = smooth_difference(|pt| wg(pt, &params), &xc, k) {
                    checked += 1;
                    prop_assert!((fd - analytic.outputs[k]).abs() <= 1e-4 * (1.0 + fd.abs()),
                        "{expr}: d(w·g)/d{} = {} but finite differences give {fd}", ["x", "y", "z", "c"][k], analytic.outputs[k]);
                }
            }
            for k in 0..params.len() {
                if let Some(fd) = smooth_difference(|q| wg(&xc, q), &params, k) {
                    prop_assert!((fd - analytic.reductions[k]).abs() <= 1e-4 * (1.0 + fd.abs()),
                        "{expr} param {k}: {} vs {fd}", analytic.reductions[k]);
                }
            }
        }
        prop_assert!(checked * 10 >= CASES.len() * 4 * 7, "only {checked} derivatives compared");
    }
}

/// An expression in x and its derivative.
type ClosedForm = (&'static str, fn(f64) -> f64);

#[test]
fn derivatives_match_closed_forms() {
    let cases: &[ClosedForm] = &[
        ("sin(x)", f64::cos),
        ("cos(x)", |x| -x.sin()),
        ("exp(x)", f64::exp),
        ("log(x + 3.0)", |x| 1.0 / (x + 3.0)),
        ("tanh(x)", |x| 1.0 - x.tanh().powi(2)),
        ("sigmoid(x)", |x| {
            let s = 1.0 / (1.0 + (-x).exp());
            s * (1.0 - s)
        }),
        ("softplus(x)", |x| 1.0 / (1.0 + (-x).exp())),
        // trunc_exp's derivative is exp's inside ±15, e^±15 beyond (x·10 reaches ±20).
        ("trunc_exp(10.0 * x) * 0.1", |x| {
            (10.0 * x).clamp(-15.0, 15.0).exp()
        }),
        ("sqrt(x + 3.0)", |x| 0.5 / (x + 3.0).sqrt()),
        ("pow(x + 3.0, 2.5)", |x| 2.5 * (x + 3.0).powf(1.5)),
        // The contraction: the identity inside the unit ball (also at its center), 1/x² beyond.
        ("contract(vec3(x, 0.0, 0.0)).x", |x| {
            if x.abs() <= 1.0 {
                1.0
            } else {
                1.0 / (x * x)
            }
        }),
    ];
    for (expr, df) in cases {
        let p = program(expr);
        let g = kernel_graphs::with_gradient(&p.lower("f").unwrap());
        for i in 0..41 {
            let x = -2.0 + 0.1 * f64::from(i);
            let got = eval_point(&g, &[x, 0.0, 0.0], &[]).outputs[1];
            assert!(
                (got - df(x)).abs() < 1e-12 * (1.0 + df(x).abs()),
                "{expr} at {x}: {got} vs {}",
                df(x)
            );
        }
    }
}

#[test]
fn second_order_kernel_gives_the_eikonal_gradient() {
    // d(p) = |p| * s with param s: ∇ₓd = s p/|p|, so |∇ₓd| = s and the eikonal loss (|∇d| − 1)² has
    // dL/ds = 2 (s − 1). The kernel returns ∂/∂s (c_g · ∇ₓd); with c_g = ∂L/∂∇d = 2(|∇d| − 1) ∇d/|∇d|.
    let p = compile(
        "e.sdf",
        "param s: f32 = 1.5\nfn d(p: vec3) -> f32 = length(p) * s",
    )
    .unwrap();
    let g = kernel_graphs::second_order(&p.lower("d").unwrap(), p.n_params());
    let x = [0.3, -0.4, 1.2];
    let first = eval_point(&g, &[x[0], x[1], x[2], 0.0, 0.0, 0.0, 0.0], &[1.5]).outputs;
    let grad: Vec<f64> = first[1..4].to_vec();
    let norm = grad.iter().map(|v| v * v).sum::<f64>().sqrt();
    assert!((norm - 1.5).abs() < 1e-12);
    let cg: Vec<f64> = grad.iter().map(|v| 2.0 * (norm - 1.0) * v / norm).collect();
    let e = eval_point(&g, &[x[0], x[1], x[2], 0.0, cg[0], cg[1], cg[2]], &[1.5]);
    assert!(
        (e.reductions[0] - 2.0 * (1.5 - 1.0)).abs() < 1e-12,
        "{:?}",
        e.reductions
    );
}

#[test]
fn loss_kernel_gradient_matches_finite_differences_of_its_loss() {
    // ℓ = |d| + (|∇ₓd| − 1)² for a small network d: the loss kernel's reductions vs central differences
    // of ℓ, evaluated through the value-and-gradient kernel.
    use nerfjit_dsl::ir::Op;
    let p = compile(
        "loss.sdf",
        "param net: mlp<3, 6, 2> = linear_init(seed: 2)\nparam w: mat<1, 6> = linear_init(seed: 3)\n\
         fn d(p: vec3) -> f32 = dense(w, mlp(net, p))[0] + 0.3 * length(p) - 0.5\n",
    )
    .unwrap();
    let f = p.lower("d").unwrap();
    let loss = kernel_graphs::loss_gradient(&f, p.n_params(), |g, d, grad| {
        let abs = g.push(Op::Abs(d));
        let squares: Vec<_> = grad.iter().map(|&c| g.push(Op::Mul(c, c))).collect();
        let sum = squares.into_iter().reduce(|a, b| g.push(Op::Add(a, b))).unwrap();
        let norm = g.push(Op::Sqrt(sum));
        let one = g.constant(1.0);
        let off = g.push(Op::Sub(norm, one));
        vec![abs, g.push(Op::Mul(off, off))]
    });
    let value_and_gradient = kernel_graphs::with_gradient(&f);
    let x = [0.4, -0.7, 0.2];
    let params = p.param_values_f64();
    let analytic = eval_point(&loss, &x, &params).reductions;
    let at = |q: &[f64]| {
        let o = eval_point(&value_and_gradient, &x, q).outputs;
        let norm = (o[1] * o[1] + o[2] * o[2] + o[3] * o[3]).sqrt();
        o[0].abs() + (norm - 1.0).powi(2)
    };
    assert_gradient_matches_central_differences(&params, &analytic, at, "loss");
}

/// Asserts that `gradient` is ∂loss/∂params at `params` up to central differences, where those are stable
/// (a ReLU kink within the step makes two step sizes disagree; at least 90% of the params compare).
fn assert_gradient_matches_central_differences(
    params: &[f64],
    gradient: &[f64],
    loss: impl Fn(&[f64]) -> f64,
    what: &str,
) {
    let mut compared = 0;
    for k in 0..params.len() {
        let diff = |h: f64| {
            let (mut hi, mut lo) = (params.to_vec(), params.to_vec());
            hi[k] += h;
            lo[k] -= h;
            (loss(&hi) - loss(&lo)) / (2.0 * h)
        };
        let (a, b) = (diff(1e-6), diff(5e-7));
        if (a - b).abs() > 1e-6 * (1.0 + a.abs()) {
            continue; // a ReLU kink within the step
        }
        compared += 1;
        assert!(
            (a - gradient[k]).abs() < 1e-6 * (1.0 + a.abs()),
            "{what}: param {k}: {} vs {a}",
            gradient[k]
        );
    }
    assert!(
        compared * 10 >= params.len() * 9,
        "{what}: only {compared} of {} compared",
        params.len()
    );
}

#[test]
fn sdf_loss_kernels_compute_their_formulas_and_the_exact_param_gradient() {
    // Each named loss of fitting an SDF, for a small network d: its per-point terms against the formula
    // written here from d and ∇ₓd (the value-and-gradient kernel), and its reductions against central
    // differences of the summed terms.
    use nerfjit_dsl::kernel_graphs::SdfLoss;
    let p = compile(
        "loss.sdf",
        "param net: mlp<3, 5, 2> = linear_init(seed: 4)\nparam w: mat<1, 5> = linear_init(seed: 5)\n\
         fn d(p: vec3) -> f32 = dense(w, mlp(net, p))[0] + 0.4 * length(p) - 0.6\n",
    )
    .unwrap();
    let f = p.lower("d").unwrap();
    let value_and_gradient = kernel_graphs::with_gradient(&f);
    let params = p.param_values_f64();
    let x = [0.5, -0.3, 0.35];
    let d_at_x = eval_point(&value_and_gradient, &x, &params).outputs[0];
    // The clearance term reads a fourth and fifth input, the point's clearance c and whether it is
    // outside: c 0.2 beyond |d| (the hinge active) unsigned and signed (where d < 0 the signed form
    // counts d itself), and 0 (inactive).
    let clearances = [(d_at_x.abs() + 0.2, 0.0), (d_at_x.abs() + 0.2, 1.0), (0.0, 0.0)];
    let losses = [
        SdfLoss::Surface { scale: 0.25 },
        SdfLoss::Clearance { scale: 0.5 },
        SdfLoss::Clearance { scale: 0.75 },
        SdfLoss::Clearance { scale: 1.5 },
        SdfLoss::Sphere {
            radius: 0.7,
            scale: 0.5,
        },
        SdfLoss::Regularizers {
            near: 0.3,
            sharpness: 20.0,
            eikonal: 0.1,
        },
    ];
    for (i, loss) in losses.into_iter().enumerate() {
        let (clearance, outside) = clearances[i % 3];
        // The terms from d and ∇d as the loss's documentation states them.
        let terms = |q: &[f64]| -> Vec<f64> {
            let o = eval_point(&value_and_gradient, &x, q).outputs;
            let (d, norm) = (o[0], (o[1] * o[1] + o[2] * o[2] + o[3] * o[3]).sqrt());
            match loss {
                SdfLoss::Surface { scale } => vec![scale * d.abs()],
                SdfLoss::Clearance { scale } => {
                    let kept = if outside == 1.0 { d } else { d.abs() };
                    vec![scale * (clearance - kept).max(0.0)]
                }
                SdfLoss::Sphere { radius, scale } => {
                    let length = (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt();
                    vec![scale * (d - (length - radius)).powi(2)]
                }
                SdfLoss::Regularizers {
                    near,
                    sharpness,
                    eikonal,
                } => vec![
                    near * (-sharpness * d.abs()).exp(),
                    eikonal * (norm - 1.0).powi(2),
                ],
            }
        };
        let kernel = kernel_graphs::sdf_loss(&f, p.n_params(), loss);
        let got = eval_point(&kernel, &[x[0], x[1], x[2], clearance, outside], &params);
        let want = terms(&params);
        assert_eq!(got.outputs.len(), want.len(), "{loss:?}");
        for (a, b) in got.outputs.iter().zip(&want) {
            assert!(
                (a - b).abs() < 1e-12 * (1.0 + b.abs()),
                "{loss:?}: term {a} vs {b}"
            );
        }
        let sum = |q: &[f64]| terms(q).iter().sum::<f64>();
        assert_gradient_matches_central_differences(&params, &got.reductions, sum, &format!("{loss:?}"));
    }
}

#[test]
fn trunc_exp_is_exp_with_a_gradient_that_stays_finite() {
    let p = program("trunc_exp(x)");
    let lowered = p.lower("f").unwrap();
    let g = kernel_graphs::with_gradient(&lowered);
    for x in [-30.0, -15.0, 0.0, 3.0, 15.0, 80.0, 100.0] {
        let outputs = eval_point(&g, &[x, 0.0, 0.0], &[]).outputs;
        assert_eq!(outputs[0], f64::exp(x), "value at {x}");
        assert_eq!(outputs[1], f64::exp(x.clamp(-15.0, 15.0)), "derivative at {x}");
    }
    // exp's own gradient overflows f32 where trunc_exp's does not.
    let exp = kernel_graphs::with_gradient(&program("exp(x)").lower("f").unwrap());
    assert!(eval_point(&exp, &[100.0, 0.0, 0.0], &[]).outputs[1] as f32 == f32::INFINITY);
    assert!((eval_point(&g, &[100.0, 0.0, 0.0], &[]).outputs[1] as f32).is_finite());
}
