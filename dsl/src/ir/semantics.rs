//! The exact semantics of one op on f64 values: the interpreter's (and the interval arithmetic's) step,
//! and the constant folding of [`Graph::push`](super::Graph::push).

use super::Op;

/// The exact semantics of one op applied to argument values (constants carry their value in the op).
pub fn apply(op: Op, a: &[f64]) -> f64 {
    use Op::*;
    let bool01 = |b: bool| if b { 1.0 } else { 0.0 };
    match op {
        Const(bits) => f64::from_bits(bits),
        Input(_) | Param(_) | Dense(_) | Grid(_) | Pick(..) => f64::NAN,
        Neg(_) => -a[0],
        Abs(_) => a[0].abs(),
        Sign(_) => {
            if a[0] > 0.0 {
                1.0
            } else if a[0] < 0.0 {
                -1.0
            } else {
                0.0
            }
        }
        Floor(_) => a[0].floor(),
        Sqrt(_) => a[0].sqrt(),
        Exp(_) | TruncExp(_) => a[0].exp(),
        Log(_) => a[0].ln(),
        Sin(_) => a[0].sin(),
        Cos(_) => a[0].cos(),
        Tan(_) => a[0].tan(),
        Tanh(_) => a[0].tanh(),
        Sigmoid(_) => 1.0 / (1.0 + (-a[0]).exp()),
        Softplus(_) => a[0].max(0.0) + (-a[0].abs()).exp().ln_1p(),
        Add(..) => a[0] + a[1],
        Sub(..) => a[0] - a[1],
        Mul(..) => a[0] * a[1],
        Div(..) => a[0] / a[1],
        Min(..) => {
            if a[1] < a[0] {
                a[1]
            } else {
                a[0]
            }
        }
        Max(..) => {
            if a[0] < a[1] {
                a[1]
            } else {
                a[0]
            }
        }
        Lt(..) => bool01(a[0] < a[1]),
        Le(..) => bool01(a[0] <= a[1]),
        Eq(..) => bool01(a[0] == a[1]),
        Select(..) => {
            if a[0] != 0.0 {
                a[1]
            } else {
                a[2]
            }
        }
    }
}
