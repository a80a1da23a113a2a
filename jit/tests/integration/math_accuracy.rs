//! Accuracy of the JIT's vectorized transcendental approximations against f64, over wide ranges and at
//! special values (±0, ±∞, NaN, subnormals, huge arguments).

use nerfjit_dsl::interp;
use nerfjit_dsl::ir::{Graph, Op, V};
use nerfjit_jit::Kernel;

fn unary(op: fn(V) -> Op) -> Graph {
    let mut g = Graph::new();
    let x = g.input(0);
    let y = g.push(op(x));
    g.outputs.push(y);
    g
}

/// Max error of op over `xs`, in units of (|want| + abs_floor).
fn max_error(op: fn(V) -> Op, xs: &[f32], abs_floor: f64) -> (f64, f32) {
    let g = unary(op);
    let k = Kernel::compile(&g, Default::default()).unwrap();
    let mut out = vec![0.0f32; xs.len()];
    k.eval(xs.len(), &[xs], &mut [&mut out], &[], &mut []);
    let mut worst = (0.0, 0.0);
    for (&x, &y) in xs.iter().zip(&out) {
        let want = interp::eval_point(&g, &[f64::from(x)], &[]).outputs[0];
        if !want.is_finite() {
            assert!(
                (want.is_nan() && y.is_nan())
                    || f64::from(y) == want
                    || (want.abs() > 3.4e38 && y.is_infinite()),
                "{:?} at {x}: got {y}, want {want}",
                op(V(0))
            );
            continue;
        }
        if want.abs() > f64::from(f32::MAX) {
            assert!(y.is_infinite(), "{:?} at {x}: got {y}, want overflow", op(V(0)));
            continue;
        }
        let err = (f64::from(y) - want).abs() / (want.abs() + abs_floor);
        if err > worst.0 {
            worst = (err, x);
        }
    }
    worst
}

fn sweep(lo: f32, hi: f32, n: usize) -> Vec<f32> {
    (0..n)
        .map(|i| lo + (hi - lo) * i as f32 / (n - 1) as f32)
        .collect()
}

const SPECIAL: [f32; 9] = [
    0.0,
    -0.0,
    1.0,
    -1.0,
    f32::INFINITY,
    f32::NEG_INFINITY,
    f32::NAN,
    1e-40,
    -1e-40,
];

#[test]
fn exp_is_accurate_everywhere() {
    let mut xs = sweep(-104.0, 89.0, 100_001);
    xs.extend(SPECIAL);
    xs.extend([88.5, 88.72, 88.73, -87.0, -100.0, -103.9]);
    let (err, at) = max_error(Op::Exp, &xs, 1e-38);
    assert!(err < 4e-7, "exp: relative error {err} at {at}");
}

#[test]
fn log_is_accurate_everywhere() {
    let mut xs: Vec<f32> = (0..100_000)
        .map(|i| 10f32.powf(-44.0 + 82.0 * i as f32 / 100_000.0))
        .collect();
    xs.extend(SPECIAL);
    xs.extend([
        f32::MIN_POSITIVE,
        f32::MAX,
        -5.0,
        // Both sides of the reduction's switch at √½.
        std::f32::consts::FRAC_1_SQRT_2,
        f32::from_bits(std::f32::consts::FRAC_1_SQRT_2.to_bits() + 1),
        f32::from_bits(std::f32::consts::FRAC_1_SQRT_2.to_bits() - 1),
        1.0000001,
        0.9999999,
    ]);
    let (err, at) = max_error(Op::Log, &xs, 1e-7);
    assert!(err < 3e-7, "log: error {err} at {at}");
}

#[test]
fn sin_cos_are_accurate_on_a_wide_range() {
    let mut xs = sweep(-8192.0, 8192.0, 200_001);
    xs.extend(SPECIAL);
    xs.extend(sweep(-7.0, 7.0, 10_001));
    for op in [Op::Sin as fn(V) -> Op, Op::Cos] {
        let (err, at) = max_error(op, &xs, 1.0);
        assert!(err < 4e-7, "{:?}: error {err} at {at}", op(V(0)));
    }
}

#[test]
fn tan_is_accurate_away_from_poles() {
    let xs: Vec<f32> = sweep(-1.5, 1.5, 30_001).into_iter().chain(SPECIAL).collect();
    let (err, at) = max_error(Op::Tan, &xs, 1e-3);
    assert!(err < 1e-6, "tan: error {err} at {at}");
}

#[test]
fn activations_are_accurate() {
    let mut xs = sweep(-60.0, 60.0, 60_001);
    xs.extend(SPECIAL);
    for (op, tol) in [
        (Op::Tanh as fn(V) -> Op, 6e-7),
        (Op::Sigmoid, 6e-7),
        (Op::Softplus, 6e-7),
    ] {
        let (err, at) = max_error(op, &xs, 1.0);
        assert!(err < tol, "{:?}: error {err} at {at}", op(V(0)));
    }
}
