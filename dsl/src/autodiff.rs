//! Reverse-mode differentiation as a graph transform.
//!
//! [`vjp`] appends to a graph the nodes that compute a vector-Jacobian product: the adjoints of chosen
//! values (inputs or params) given cotangents of chosen outputs. The new nodes are ordinary ops, so the
//! result can be differentiated again: the gradient of a loss on ∇ₓf with respect to the params (the eikonal
//! loss) is `vjp` applied to a graph that already holds a `vjp`.
//!
//! One convention departs from the textbook: the derivative of `sqrt` at 0 is 0 rather than +∞, so that
//! the gradient of `length(v)` at v = 0 is 0 (a subgradient) and not NaN. At kinks the derivative takes a
//! side: `min` and `max` pass the gradient to their first argument on ties, and ReLU, `max(x, 0)`, passes it
//! where its output is positive (0 at x = 0, as PyTorch and JAX), with a mask read from that output.

use std::collections::HashMap;

use crate::ir::{Dense, Graph, GridRead, Op, Outer, Scatter, V};

/// The gradients of the params that multi-valued nodes read as blocks: dense layers' matrices (outer
/// products) and grid encodings' tables (scatters). They add to the reductions of those params.
#[derive(Clone, Debug, Default)]
pub struct BlockGradients {
    /// The matrices' gradients.
    pub outer: Vec<Outer>,
    /// The tables' gradients.
    pub scatter: Vec<Scatter>,
}

impl BlockGradients {
    /// Makes these the gradients `g` adds to its reductions.
    pub fn install(self, g: &mut Graph) {
        g.outer = self.outer;
        g.scatter = self.scatter;
    }
}

/// Appends to `g` the nodes computing, for each `w` in `wrt`, Σₖ cotₖ · ∂outₖ/∂w, where `seeds` pairs each
/// output value `outₖ` with its cotangent value `cotₖ`. Values of `wrt` that no output depends on get 0.
/// The matrices of dense nodes are not differentiated (see [`vjp_with_dense_params`]).
pub fn vjp(g: &mut Graph, seeds: &[(V, V)], wrt: &[V]) -> Vec<V> {
    vjp_with_dense_params(g, seeds, wrt, false).0
}

/// As [`vjp`]; when `dense_params` is set, also returns the gradients of the matrices of the dense nodes
/// and of the tables of the grid reads (see [`BlockGradients`]).
///
/// A dense node y = W·x passes x̄ = Wᵀ·ȳ to its input (a transposed dense node) and adds ȳ ⊗ x to W's
/// gradient; y = Wᵀ·x passes x̄ = W·ȳ and adds x ⊗ ȳ. Both are again dense nodes and outer products, so
/// second-order kernels keep every product a matrix product. A grid read y = G(θ, p) passes
/// p̄ₐ = ȳ · ∂G/∂pₐ to its point (a read differentiated along axis a) and scatters ȳ into θ; the derivative
/// reads are again grid reads, so second order closes the same way.
pub fn vjp_with_dense_params(
    g: &mut Graph,
    seeds: &[(V, V)],
    wrt: &[V],
    dense_params: bool,
) -> (Vec<V>, BlockGradients) {
    let n = g.len();
    let mut depends = vec![false; n];
    for w in wrt {
        depends[w.0 as usize] = true;
    }
    for i in 0..n {
        let op = g.ops()[i];
        let from_params = dense_params && matches!(op, Op::Dense(_) | Op::Grid(_));
        if !depends[i] && (from_params || g.args(&op).iter().any(|a| depends[a.0 as usize])) {
            depends[i] = true;
        }
    }
    let mut adjoint = Adjoints::new(n);
    let mut dense_adjoint: HashMap<V, Vec<Option<V>>> = HashMap::new();
    let mut blocks = BlockGradients::default();
    for &(out, cot) in seeds {
        adjoint.add(g, &depends, out, cot);
    }
    for i in (0..n).rev() {
        let y = V(i as u32);
        match g.op(y) {
            Op::Dense(d) if depends[i] => {
                let Some(ybar) = dense_adjoint.remove(&y) else {
                    continue;
                };
                let zero = g.constant(0.0);
                let ybar: Vec<V> = ybar.into_iter().map(|a| a.unwrap_or(zero)).collect();
                let x = g.list(d.x).to_vec();
                if x.iter().any(|a| depends[a.0 as usize]) {
                    let xbar = g.dense(d.w, d.rows, d.cols, !d.transposed, &ybar);
                    for (&a, contrib) in x.iter().zip(xbar) {
                        adjoint.add(g, &depends, a, contrib);
                    }
                }
                if dense_params {
                    blocks.outer.push(matrix_gradient(d, x, ybar));
                }
            }
            Op::Grid(r) if depends[i] => {
                let Some(ybar) = dense_adjoint.remove(&y) else {
                    continue;
                };
                let zero = g.constant(0.0);
                let ybar: Vec<V> = ybar.into_iter().map(|a| a.unwrap_or(zero)).collect();
                grid_point_adjoints(g, &mut adjoint, &depends, r, &ybar);
                if dense_params {
                    blocks.scatter.push(Scatter {
                        read: r,
                        cotangent: ybar,
                    });
                }
            }
            Op::Pick(d, k) => {
                let (Some(gy), true) = (adjoint.sum(g, y), depends[i]) else {
                    continue;
                };
                let n_out = match g.op(d) {
                    Op::Dense(dense) => dense.n_out(),
                    Op::Grid(r) => r.spec.n_outputs(),
                    _ => unreachable!("pick of a single-valued node"),
                };
                let slots = dense_adjoint.entry(d).or_insert_with(|| vec![None; n_out]);
                let slot = &mut slots[k as usize];
                *slot = Some(match *slot {
                    Some(prev) => g.push(Op::Add(prev, gy)),
                    None => gy,
                });
            }
            _ => {
                let (Some(gy), true) = (adjoint.sum(g, y), depends[i]) else {
                    continue;
                };
                for (arg, contrib) in local_adjoints(g, y, gy) {
                    adjoint.add(g, &depends, arg, contrib);
                }
            }
        }
    }
    let values = wrt
        .iter()
        .map(|&w| adjoint.sum(g, w).unwrap_or_else(|| g.constant(0.0)))
        .collect();
    (values, blocks)
}

/// Adds ȳ · ∂G/∂pₐ to the adjoint of each coordinate pₐ of a grid read's point. Along an axis the read is
/// already differentiated the second derivative is 0 (trilinear interpolation is linear per axis).
fn grid_point_adjoints(g: &mut Graph, adjoint: &mut Adjoints, depends: &[bool], r: GridRead, ybar: &[V]) {
    for a in 0..3 {
        let bit = 1u8 << a;
        if r.deriv & bit != 0 || !depends[r.p[a].0 as usize] {
            continue;
        }
        let d = g.grid(r.spec, r.p, r.deriv | bit);
        let contrib = g.dot(ybar, &d);
        adjoint.add(g, depends, r.p[a], contrib);
    }
}

/// The gradient of W for a dense node with input `x` and output adjoint `ybar`.
fn matrix_gradient(d: Dense, x: Vec<V>, ybar: Vec<V>) -> Outer {
    let (left, right) = if d.transposed { (x, ybar) } else { (ybar, x) };
    Outer {
        target: d.w,
        left,
        right,
    }
}

/// The contributions to each value's adjoint, summed when the adjoint is first needed: as a balanced tree of
/// adds (pairs of neighbours, then pairs of those sums, …), so that a value read by many others — a point's
/// coordinate in a union of 20 primitives — sums its contributions in a few dependent adds, not a chain.
struct Adjoints {
    pending: Vec<Vec<V>>,
}

impl Adjoints {
    fn new(n: usize) -> Self {
        Adjoints {
            pending: vec![Vec::new(); n],
        }
    }

    /// Adds `contrib` to the adjoint of `at` (nothing where `at` does not depend on the targets, or for a
    /// constant 0).
    fn add(&mut self, g: &Graph, depends: &[bool], at: V, contrib: V) {
        let i = at.0 as usize;
        if depends[i] && g.const_value(contrib) != Some(0.0) {
            self.pending[i].push(contrib);
        }
    }

    /// The adjoint of `at`: the sum of its contributions so far (`None` without any).
    fn sum(&mut self, g: &mut Graph, at: V) -> Option<V> {
        let terms = &mut self.pending[at.0 as usize];
        while terms.len() > 1 {
            *terms = terms
                .chunks(2)
                .map(|pair| match *pair {
                    [a, b] => g.push(Op::Add(a, b)),
                    [a] => a,
                    _ => unreachable!("chunks of at most 2"),
                })
                .collect();
        }
        terms.first().copied()
    }
}

/// `term` where `gy` is not 0, else 0 (not NaN, when `term` is 0·∞).
fn zero_where_zero(g: &mut Graph, gy: V, term: V) -> V {
    let zero = g.constant(0.0);
    let is_zero = g.push(Op::Eq(gy, zero));
    g.push(Op::Select(is_zero, zero, term))
}

/// The contribution `gy · ∂y/∂arg` for each argument of the op computing `y`.
fn local_adjoints(g: &mut Graph, y: V, gy: V) -> Vec<(V, V)> {
    use Op::*;
    let zero = g.constant(0.0);
    let one = g.constant(1.0);
    match g.op(y) {
        Const(_) | Input(_) | Param(_) | Sign(_) | Floor(_) | Lt(..) | Le(..) | Eq(..) => vec![],
        Dense(_) | Grid(_) | Pick(..) => {
            unreachable!("multi-valued nodes are differentiated in vjp_with_dense_params")
        }
        Neg(a) => vec![(a, g.push(Neg(gy)))],
        Abs(a) => {
            let s = g.push(Sign(a));
            vec![(a, g.push(Mul(gy, s)))]
        }
        Sqrt(a) => {
            // d√a = 1/(2√a), taken as 0 where √a = 0 (as PyTorch does for norms): `length` of a zero
            // vector, as in the box SDF's length(max(q, 0)), then has a zero gradient instead of NaN.
            let half = g.constant(0.5);
            let t = g.push(Div(half, y));
            let at_zero = g.push(Eq(y, zero));
            let d = g.push(Select(at_zero, zero, t));
            vec![(a, g.push(Mul(gy, d)))]
        }
        // The contributions of exp, log and division are 0 where gy is: their derivatives can be infinite
        // (an exp that overflows, a log or a quotient at 0), and 0·∞ would be NaN. A zero gy comes from a
        // `min`, `max` or `select` that took the other side, such as a smooth union (−log(e^−ka + e^−kb)/k)
        // whose exponentials underflowed far from its shapes, where another shape is nearer.
        Exp(a) => {
            let d = g.push(Mul(gy, y));
            vec![(a, zero_where_zero(g, gy, d))]
        }
        TruncExp(a) => {
            let limit = g.constant(crate::ir::TRUNC_EXP_LIMIT);
            let low = g.push(Neg(limit));
            let above = g.push(Max(a, low));
            let clamped = g.push(Min(above, limit));
            let d = g.push(Exp(clamped));
            vec![(a, g.push(Mul(gy, d)))]
        }
        Log(a) => {
            let d = g.push(Div(gy, a));
            vec![(a, zero_where_zero(g, gy, d))]
        }
        Sin(a) => {
            let c = g.push(Cos(a));
            vec![(a, g.push(Mul(gy, c)))]
        }
        Cos(a) => {
            let s = g.push(Sin(a));
            let t = g.push(Mul(gy, s));
            vec![(a, g.push(Neg(t)))]
        }
        Tan(a) => {
            let y2 = g.push(Mul(y, y));
            let d = g.push(Add(one, y2));
            vec![(a, g.push(Mul(gy, d)))]
        }
        Tanh(a) => {
            let y2 = g.push(Mul(y, y));
            let d = g.push(Sub(one, y2));
            vec![(a, g.push(Mul(gy, d)))]
        }
        Sigmoid(a) => {
            let c = g.push(Sub(one, y));
            let d = g.push(Mul(y, c));
            vec![(a, g.push(Mul(gy, d)))]
        }
        Softplus(a) => {
            let s = g.push(Sigmoid(a));
            vec![(a, g.push(Mul(gy, s)))]
        }
        Add(a, b) => vec![(a, gy), (b, gy)],
        Sub(a, b) => vec![(a, gy), (b, g.push(Neg(gy)))],
        // a·a: one contribution 2·gy·a (the same value as gy·a + gy·a but for overflow, in two ops
        // instead of three, and one product that can fuse into the adjoint's sum). The squares of a
        // `length` share their adjoint, so they share 2·gy too.
        Mul(a, b) if a == b => {
            let twice = g.push(Add(gy, gy));
            vec![(a, g.push(Mul(twice, a)))]
        }
        Mul(a, b) => vec![(a, g.push(Mul(gy, b))), (b, g.push(Mul(gy, a)))],
        Div(a, b) => {
            let quotient = g.push(Div(gy, b));
            let ga = zero_where_zero(g, gy, quotient);
            let t = g.push(Mul(ga, y));
            let minus_t = g.push(Neg(t));
            vec![(a, ga), (b, zero_where_zero(g, gy, minus_t))]
        }
        Min(a, b) => {
            // min(a, b) = b < a ? b : a
            let takes_b = g.push(Lt(b, a));
            vec![
                (a, g.push(Select(takes_b, zero, gy))),
                (b, g.push(Select(takes_b, gy, zero))),
            ]
        }
        // ReLU, max(a, 0): the gradient flows where the output is positive. The mask reads the output, not
        // a, so that a network's backward pass needs only the activations it already keeps for the weight
        // gradients, not the pre-activations too. (At a = 0 the derivative is then 0, as in PyTorch and JAX,
        // where the general rule below would give 1.)
        Max(a, b) if g.const_value(b).is_some_and(|c| c.to_bits() == 0) => {
            let positive = g.push(Lt(zero, y));
            vec![(a, g.push(Select(positive, gy, zero)))]
        }
        Max(a, b) => {
            // max(a, b) = a < b ? b : a
            let takes_b = g.push(Lt(a, b));
            vec![
                (a, g.push(Select(takes_b, zero, gy))),
                (b, g.push(Select(takes_b, gy, zero))),
            ]
        }
        Select(c, a, b) => vec![(a, g.push(Select(c, gy, zero))), (b, g.push(Select(c, zero, gy)))],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::interp::eval_point;

    #[test]
    fn a_branch_a_min_does_not_take_passes_zero_even_where_its_derivatives_are_infinite() {
        // min(x, smooth union of a and b), the smooth union −log(e^−ka + e^−kb)/k far from both shapes:
        // both exponentials underflow to 0, the log is −∞, the union +∞, and min takes x. The union's
        // adjoint is then 0, and 0 times log's derivative 1/0 (or the quotient's) must stay 0, not NaN.
        let mut g = Graph::new();
        let (x, a, b) = (g.input(0), g.input(1), g.input(2));
        let minus_k = g.constant(-1000.0);
        let (ka, kb) = (g.push(Op::Mul(minus_k, a)), g.push(Op::Mul(minus_k, b)));
        let (ea, eb) = (g.push(Op::Exp(ka)), g.push(Op::Exp(kb)));
        let sum = g.push(Op::Add(ea, eb));
        let log = g.push(Op::Log(sum));
        let union = g.push(Op::Div(log, minus_k));
        let y = g.push(Op::Min(x, union));
        let one = g.constant(1.0);
        let grads = vjp(&mut g, &[(y, one)], &[x, a, b]);
        g.outputs = [vec![y, union], grads].concat();
        let out = eval_point(&g, &[0.5, 2.0, 3.0], &[]).outputs;
        assert_eq!(
            out[..2],
            [0.5, f64::INFINITY],
            "the exponentials underflowed, the union is +∞ and min took x"
        );
        assert_eq!(out[2..], [1.0, 0.0, 0.0], "gradients");
        // Where the union is taken, its gradient blends a's and b's: e^−ka / (e^−ka + e^−kb) for a.
        let out = eval_point(&g, &[0.5, 0.001, 0.002], &[]).outputs;
        let weight_a = 1.0 / (1.0 + (-1.0f64).exp());
        assert_eq!(out[2], 0.0);
        assert!(
            (out[3] - weight_a).abs() < 1e-12 && (out[4] - (1.0 - weight_a)).abs() < 1e-12,
            "{out:?}"
        );
    }

    #[test]
    fn relu_passes_the_gradient_where_its_output_is_positive() {
        // d relu(x)/dx: 1 above 0; 0 below and at 0 (as PyTorch and JAX); the mask reads the output.
        let mut g = Graph::new();
        let x = g.input(0);
        let zero = g.constant(0.0);
        let y = g.push(Op::Max(x, zero));
        let one = g.constant(1.0);
        let grad = vjp(&mut g, &[(y, one)], &[x])[0];
        g.outputs = vec![y, grad];
        for (at, want) in [(2.5, 1.0), (1e-30, 1.0), (0.0, 0.0), (-0.0, 0.0), (-3.0, 0.0)] {
            assert_eq!(eval_point(&g, &[at], &[]).outputs[1], want, "at {at}");
        }
        let Op::Select(mask, ..) = g.op(grad) else {
            panic!("relu's gradient is a select");
        };
        assert_eq!(g.op(mask), Op::Lt(zero, y), "the mask compares the output with 0");
        // max with anything but +0 keeps the general rule: the gradient goes to a unless a < b.
        let b = g.input(1);
        let m = g.push(Op::Max(x, b));
        let grads = vjp(&mut g, &[(m, one)], &[x, b]);
        g.outputs = grads;
        assert_eq!(eval_point(&g, &[1.0, 1.0], &[]).outputs, vec![1.0, 0.0]);
        assert_eq!(eval_point(&g, &[0.5, 1.0], &[]).outputs, vec![0.0, 1.0]);
    }

    #[test]
    fn gradient_of_product_and_second_order() {
        // f(x, y) = x² y;  ∂f/∂x = 2xy, ∂f/∂y = x²;  ∂²f/∂x² = 2y
        let mut g = Graph::new();
        let (x, y) = (g.input(0), g.input(1));
        let x2 = g.push(Op::Mul(x, x));
        let f = g.push(Op::Mul(x2, y));
        let one = g.constant(1.0);
        let grads = vjp(&mut g, &[(f, one)], &[x, y]);
        let second = vjp(&mut g, &[(grads[0], one)], &[x]);
        g.outputs = vec![f, grads[0], grads[1], second[0]];
        let e = eval_point(&g, &[3.0, 5.0], &[]);
        assert_eq!(e.outputs, vec![45.0, 30.0, 9.0, 10.0]);
    }

    /// The longest chain of adds from `v` down to a node that is not an add.
    fn add_depth(g: &Graph, v: V) -> usize {
        match g.op(v) {
            Op::Add(a, b) => 1 + add_depth(g, a).max(add_depth(g, b)),
            _ => 0,
        }
    }

    #[test]
    fn adjoints_sum_their_contributions_as_a_balanced_tree() {
        // x read by 8 products: its adjoint adds 8 contributions in 3 levels of adds, not a chain of 7.
        let mut g = Graph::new();
        let x = g.input(0);
        let mut sum = None;
        for k in 1..=8 {
            let c = g.constant(k as f64);
            let term = g.push(Op::Mul(x, c));
            sum = Some(sum.map_or(term, |s| g.push(Op::Add(s, term))));
        }
        let f = sum.expect("8 terms");
        let cotangent = g.input(1);
        let dx = vjp(&mut g, &[(f, cotangent)], &[x])[0];
        g.outputs = vec![dx];
        assert_eq!(add_depth(&g, dx), 3);
        assert_eq!(eval_point(&g, &[0.7, 0.5], &[]).outputs, vec![18.0]);
    }

    #[test]
    fn a_square_passes_twice_its_adjoint_in_one_product() {
        // d(x²) = (ḡ + ḡ)·x: one add and one product; the squares of a length share ḡ + ḡ.
        let mut g = Graph::new();
        let (x, y) = (g.input(0), g.input(1));
        let (x2, y2) = (g.push(Op::Mul(x, x)), g.push(Op::Mul(y, y)));
        let s = g.push(Op::Add(x2, y2));
        let r = g.push(Op::Sqrt(s));
        let cotangent = g.input(2);
        let before = g.len();
        let grads = vjp(&mut g, &[(r, cotangent)], &[x, y]);
        g.outputs = grads.clone();
        let doubled = |v: V| matches!(g.op(v), Op::Add(a, b) if a == b);
        let factors = |v: V| match g.op(v) {
            Op::Mul(a, b) if doubled(a) => (a, b),
            Op::Mul(a, b) if doubled(b) => (b, a),
            op => panic!("not a product with twice an adjoint: {op:?}"),
        };
        let ((twice_x, by_x), (twice_y, by_y)) = (factors(grads[0]), factors(grads[1]));
        assert_eq!((by_x, by_y), (x, y));
        assert_eq!(twice_x, twice_y, "the squares share twice the sum's adjoint");
        // Besides constants: 0.5 / r, r = 0, the guard, ḡ·that, ḡ + ḡ and the two products.
        let new_ops = (before..g.len()).filter(|&i| !matches!(g.op(V(i as u32)), Op::Const(_)));
        assert_eq!(new_ops.count(), 7);
        let got = eval_point(&g, &[3.0, 4.0, 0.5], &[]).outputs;
        assert!(
            (got[0] - 0.3).abs() < 1e-15 && (got[1] - 0.4).abs() < 1e-15,
            "{got:?}"
        );
    }
}
