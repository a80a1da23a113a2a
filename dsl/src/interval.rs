//! Interval arithmetic as an IR transform: from a per-point graph, the graph of its natural interval
//! extension.
//!
//! [`extend`] maps every value `v` of a graph to a pair `[lo, hi]` of values computed by ordinary ops
//! (min, max, select, ...), so the interval graph is compiled by the same JIT as any other kernel and checked
//! by the same interpreter. Given a box of inputs (`lo₀ … lo₍ₙ₋₁₎, hi₀ … hi₍ₙ₋₁₎`) it bounds every output over
//! the box (`lo` of each output, then `hi` of each): at any point of the box where every value the graph
//! computes is a number within ±[`BOUND`], each output lies in its interval (up to the rounding of the
//! arithmetic that evaluates both; callers that prune with the bounds, such as octree meshing, keep a margin
//! for it). Where some value inside is NaN nothing is promised: `max(−2, √−1)` is −2 in the IR.
//!
//! Bounds are those of interval arithmetic, exact for one occurrence of each variable and conservative
//! otherwise; a square `x·x` is recognized so that distances stay tight. Every bound is kept inside ±BOUND:
//! an overflow or a NaN bound (the log of a negative range) widens to that limit rather than to a value that
//! a later `min` or `max` could wrongly narrow. Ops without a useful bound (dense layers, grid reads, `tan`,
//! division by a range that contains 0) give the whole range ±BOUND.
//!
//! ```
//! use nerfjit_dsl::interp::eval_point;
//! use nerfjit_dsl::interval::extend;
//! use nerfjit_dsl::ir::{Graph, Op};
//! // f(x) = x² − 1 on the box [0.5, 2]: [−0.75, 3].
//! let mut g = Graph::new();
//! let x = g.input(0);
//! let x2 = g.push(Op::Mul(x, x));
//! let one = g.constant(1.0);
//! let f = g.push(Op::Sub(x2, one));
//! g.outputs.push(f);
//! let bounds = extend(&g);
//! assert_eq!(eval_point(&bounds, &[0.5, 2.0], &[]).outputs, vec![-0.75, 3.0]);
//! ```

use crate::ir::{Graph, Op, V};

/// The largest magnitude of a bound: intervals are clamped to ±`BOUND` so that products of two bounds stay
/// finite in f32.
pub const BOUND: f64 = 1e18;

/// The relative margin by which the arguments of steps (`floor`, `sign`) are widened: far above the f32
/// rounding of the values and of their bounds.
const ROUNDING: f64 = 1e-4;

/// The interval extension of `g`'s per-point outputs (reductions are not carried over): inputs
/// `lo₀ … lo₍ₙ₋₁₎, hi₀ … hi₍ₙ₋₁₎` for n = `g.n_inputs`; outputs `lo` of each output of `g`, then `hi` of each.
pub fn extend(g: &Graph) -> Graph {
    let (mut out, pairs) = extend_pairs(g);
    let los: Vec<V> = g.outputs.iter().map(|v| pairs[v.0 as usize].0).collect();
    let his: Vec<V> = g.outputs.iter().map(|v| pairs[v.0 as usize].1).collect();
    out.outputs = los.into_iter().chain(his).collect();
    out.compact()
}

/// The interval graph of `g` (inputs as in [`extend`], no outputs yet) and the pair of values bounding each
/// node of `g` (for the nodes the outputs do not need: a pair of zeros).
fn extend_pairs(g: &Graph) -> (Graph, Vec<(V, V)>) {
    // About four interval nodes per node.
    let mut out = Graph::with_capacity(4 * g.len());
    let n = g.n_inputs;
    let mut pairs: Vec<(V, V)> = Vec::with_capacity(g.len());
    let live = g.live();
    for (i, op) in g.ops().iter().enumerate() {
        let pair = if live[i] {
            let arg = |v: V| pairs[v.0 as usize];
            Extender { g: &mut out, n }.op(op, arg)
        } else {
            let zero = out.constant(0.0);
            (zero, zero)
        };
        pairs.push(pair);
    }
    out.n_inputs = 2 * n;
    (out, pairs)
}

/// Bounds of every node of a graph over boxes of inputs, evaluated by the reference interpreter in f64
/// (for decisions per box, such as [`crate::simplify`]'s). The interval graph is built once.
pub struct NodeBounds {
    /// The interval graph whose outputs are the bounds of the live nodes: every `lo`, then every `hi`.
    bounds: Graph,
    /// For each node of the original graph, its place among the live nodes.
    place: Vec<Option<usize>>,
}

impl NodeBounds {
    /// Prepares the bounds of `g`'s nodes.
    pub fn new(g: &Graph) -> NodeBounds {
        let (mut bounds, pairs) = extend_pairs(g);
        let live = g.live();
        let mut place = vec![None; g.len()];
        let mut los = Vec::new();
        let mut his = Vec::new();
        for (i, &(lo, hi)) in pairs.iter().enumerate() {
            if live[i] {
                place[i] = Some(los.len());
                los.push(lo);
                his.push(hi);
            }
        }
        bounds.outputs = los.into_iter().chain(his).collect();
        // Not compacted: every pair is an output, and a rebuild would cost more than the few dead nodes.
        NodeBounds { bounds, place }
    }

    /// The bounds `(lo, hi)` of each node over the box `lo ≤ x ≤ hi` of inputs, with the params at `params`
    /// (`None` for the nodes the outputs do not need).
    pub fn eval(&self, lo: &[f64], hi: &[f64], params: &[f64]) -> Vec<Option<(f64, f64)>> {
        let corners: Vec<f64> = lo.iter().chain(hi).copied().collect();
        // The interval graph is elementwise (multi-valued ops bound to constants): a plain loop of the
        // interpreter's semantics, without its general machinery, as this runs once per box.
        let mut vals: Vec<f64> = Vec::with_capacity(self.bounds.len());
        for op in self.bounds.ops() {
            let v = match *op {
                Op::Input(k) => corners.get(k as usize).copied().unwrap_or(f64::NAN),
                Op::Param(k) => params.get(k as usize).copied().unwrap_or(f64::NAN),
                _ => {
                    let args = op.args();
                    let mut a = [0.0; 3];
                    for (slot, v) in a.iter_mut().zip(args.iter()) {
                        *slot = vals[v.0 as usize];
                    }
                    crate::ir::semantics::apply(*op, &a[..args.len()])
                }
            };
            vals.push(v);
        }
        let value = |v: &V| vals[v.0 as usize];
        let live = self.bounds.outputs.len() / 2;
        let (los, his) = self.bounds.outputs.split_at(live);
        self.place
            .iter()
            .map(|p| p.map(|k| (value(&los[k]), value(&his[k]))))
            .collect()
    }
}

/// Builds the interval ops of one node into the interval graph.
struct Extender<'a> {
    g: &'a mut Graph,
    /// The number of inputs of the original graph: input k's `hi` is input `k + n`.
    n: u32,
}

impl Extender<'_> {
    fn op(&mut self, op: &Op, arg: impl Fn(V) -> (V, V)) -> (V, V) {
        use Op::*;
        match *op {
            Const(bits) if f64::from_bits(bits).abs() <= BOUND => {
                let c = self.g.constant(f64::from_bits(bits));
                (c, c)
            }
            Const(_) => self.whole(),
            Input(k) => (self.g.input(k), self.g.input(k + self.n)),
            Param(k) => {
                let p = self.g.param(k);
                (p, p)
            }
            Neg(a) => {
                let (lo, hi) = arg(a);
                (self.push(Neg(hi)), self.push(Neg(lo)))
            }
            Abs(a) => self.abs(arg(a)),
            Sign(a) | Floor(a) | Sqrt(a) | Exp(a) | Log(a) | Tanh(a) | Sigmoid(a) | Softplus(a)
            | TruncExp(a) => self.monotone(op, arg(a)),
            Sin(_) | Cos(_) => (self.g.constant(-1.0), self.g.constant(1.0)),
            Tan(_) | Dense(_) | Grid(_) | Pick(..) => self.whole(),
            Add(a, b) => {
                let ((alo, ahi), (blo, bhi)) = (arg(a), arg(b));
                let lo = self.push(Add(alo, blo));
                let hi = self.push(Add(ahi, bhi));
                self.clamp(lo, hi)
            }
            Sub(a, b) => {
                let ((alo, ahi), (blo, bhi)) = (arg(a), arg(b));
                let lo = self.push(Sub(alo, bhi));
                let hi = self.push(Sub(ahi, blo));
                self.clamp(lo, hi)
            }
            Mul(a, b) if a == b => self.square(arg(a)),
            Mul(a, b) => self.mul(arg(a), arg(b)),
            Div(a, b) => self.div(arg(a), arg(b)),
            Min(a, b) => {
                let ((alo, ahi), (blo, bhi)) = (arg(a), arg(b));
                (self.push(Min(alo, blo)), self.push(Min(ahi, bhi)))
            }
            Max(a, b) => {
                let ((alo, ahi), (blo, bhi)) = (arg(a), arg(b));
                (self.push(Max(alo, blo)), self.push(Max(ahi, bhi)))
            }
            // Certainly true where the whole of a lies below the whole of b; possibly true where they overlap.
            Lt(a, b) => {
                let ((alo, ahi), (blo, bhi)) = (arg(a), arg(b));
                (self.push(Lt(ahi, blo)), self.push(Lt(alo, bhi)))
            }
            Le(a, b) => {
                let ((alo, ahi), (blo, bhi)) = (arg(a), arg(b));
                (self.push(Le(ahi, blo)), self.push(Le(alo, bhi)))
            }
            Eq(a, b) => self.eq(arg(a), arg(b)),
            Select(c, a, b) => self.select(arg(c), arg(a), arg(b)),
        }
    }

    fn push(&mut self, op: Op) -> V {
        self.g.push(op)
    }

    fn whole(&mut self) -> (V, V) {
        (self.g.constant(-BOUND), self.g.constant(BOUND))
    }

    /// `[lo, hi]` clamped into ±BOUND, a NaN `lo` becoming −BOUND and a NaN `hi` +BOUND (`max(−B, NaN) = −B`
    /// and `min(B, NaN) = B` in the IR's semantics).
    fn clamp(&mut self, lo: V, hi: V) -> (V, V) {
        let (neg, pos) = (self.g.constant(-BOUND), self.g.constant(BOUND));
        let lo = self.push(Op::Max(neg, lo));
        let hi = self.push(Op::Min(pos, hi));
        (self.push(Op::Min(pos, lo)), self.push(Op::Max(neg, hi)))
    }

    /// An increasing function of one argument.
    fn monotone(&mut self, op: &Op, (lo, hi): (V, V)) -> (V, V) {
        let (lo, hi) = match *op {
            // Bounds of the part of the box where the root is defined.
            Op::Sqrt(_) => {
                let zero = self.g.constant(0.0);
                (self.push(Op::Max(zero, lo)), self.push(Op::Max(zero, hi)))
            }
            // Steps: an argument that f32 rounding moves across an integer (or across 0) jumps by 1, so the
            // argument's bounds are widened by the rounding margin first (p / p is 0.99999994 in f32 when
            // computed as p · (1 / p), as the bounds of a quotient are).
            Op::Floor(_) | Op::Sign(_) => (self.widen(lo, -1.0), self.widen(hi, 1.0)),
            _ => (lo, hi),
        };
        let f = |v: V| op.map_args(|_| v);
        let (lo, hi) = (self.push(f(lo)), self.push(f(hi)));
        match op {
            // Floor too: its widened argument may lie beyond ±BOUND (the whole range of a NaN log).
            Op::Exp(_) | Op::Log(_) | Op::Softplus(_) | Op::TruncExp(_) | Op::Floor(_) => self.clamp(lo, hi),
            _ => (lo, hi),
        }
    }

    /// `v + direction · ROUNDING · (1 + |v|)`: a bound moved outwards by the f32 rounding margin.
    fn widen(&mut self, v: V, direction: f64) -> V {
        let abs = self.push(Op::Abs(v));
        let scale = self.g.constant(direction * ROUNDING);
        let one = self.g.constant(1.0);
        let magnitude = self.push(Op::Add(abs, one));
        let margin = self.push(Op::Mul(magnitude, scale));
        self.push(Op::Add(v, margin))
    }

    /// `|a|`: `[max(lo, −hi, 0), max(−lo, hi)]`.
    fn abs(&mut self, (lo, hi): (V, V)) -> (V, V) {
        let zero = self.g.constant(0.0);
        let (neg_lo, neg_hi) = (self.push(Op::Neg(lo)), self.push(Op::Neg(hi)));
        let low = self.push(Op::Max(lo, neg_hi));
        (self.push(Op::Max(zero, low)), self.push(Op::Max(neg_lo, hi)))
    }

    /// `a·a`: the square of the nearest point to 0 and of the farthest.
    fn square(&mut self, a: (V, V)) -> (V, V) {
        let (near, far) = self.abs(a);
        let lo = self.push(Op::Mul(near, near));
        let hi = self.push(Op::Mul(far, far));
        self.clamp(lo, hi)
    }

    fn mul(&mut self, (alo, ahi): (V, V), (blo, bhi): (V, V)) -> (V, V) {
        // By a constant: scale, ordered by its sign.
        for ((lo, hi), (clo, chi)) in [((alo, ahi), (blo, bhi)), ((blo, bhi), (alo, ahi))] {
            let c = clo;
            if let Some(k) = self.g.const_value(c).filter(|_| clo == chi) {
                let (lo, hi) = (self.push(Op::Mul(lo, c)), self.push(Op::Mul(hi, c)));
                let (lo, hi) = if k < 0.0 { (hi, lo) } else { (lo, hi) };
                return self.clamp(lo, hi);
            }
        }
        let products =
            [(alo, blo), (alo, bhi), (ahi, blo), (ahi, bhi)].map(|(x, y)| self.push(Op::Mul(x, y)));
        let lo = self.fold(Op::Min, &products);
        let hi = self.fold(Op::Max, &products);
        self.clamp(lo, hi)
    }

    fn fold(&mut self, op: fn(V, V) -> Op, values: &[V]) -> V {
        let mut acc = values[0];
        for &v in &values[1..] {
            acc = self.push(op(acc, v));
        }
        acc
    }

    fn div(&mut self, (alo, ahi): (V, V), (blo, bhi): (V, V)) -> (V, V) {
        if let Some(k) = self.g.const_value(blo).filter(|_| blo == bhi) {
            let (lo, hi) = (self.push(Op::Div(alo, blo)), self.push(Op::Div(ahi, blo)));
            let (lo, hi) = if k < 0.0 { (hi, lo) } else { (lo, hi) };
            return self.clamp(lo, hi);
        }
        // The extremes of the four corners' quotients where b keeps one sign; the whole range where it may
        // be 0. The quotients, not a times b's reciprocal: rounded division is monotone in each argument,
        // so every rounded quotient in the box lies between the corners', where a · (1 / b) rounds twice
        // and can miss the quotient itself (x / x is 1, x · (1 / x) may be 1 - 2^-24).
        let zero = self.g.constant(0.0);
        let positive = self.push(Op::Lt(zero, blo));
        let negative = self.push(Op::Lt(bhi, zero));
        let one_sign = self.push(Op::Add(positive, negative));
        let quotients =
            [(alo, blo), (alo, bhi), (ahi, blo), (ahi, bhi)].map(|(x, y)| self.push(Op::Div(x, y)));
        let lo = self.fold(Op::Min, &quotients);
        let hi = self.fold(Op::Max, &quotients);
        let (lo, hi) = self.clamp(lo, hi);
        let (neg, pos) = self.whole();
        (
            self.push(Op::Select(one_sign, lo, neg)),
            self.push(Op::Select(one_sign, hi, pos)),
        )
    }

    /// 1 where both are the same single value; 0 where they cannot meet; else [0, 1].
    fn eq(&mut self, (alo, ahi): (V, V), (blo, bhi): (V, V)) -> (V, V) {
        let a_point = self.push(Op::Eq(alo, ahi));
        let b_point = self.push(Op::Eq(blo, bhi));
        let same = self.push(Op::Eq(alo, blo));
        let points = self.push(Op::Mul(a_point, b_point));
        let lo = self.push(Op::Mul(points, same));
        let a_not_above = self.push(Op::Le(alo, bhi));
        let b_not_above = self.push(Op::Le(blo, ahi));
        (lo, self.push(Op::Mul(a_not_above, b_not_above)))
    }

    /// The chosen branch where the condition is certainly non-zero or certainly zero; the union otherwise.
    fn select(&mut self, (clo, chi): (V, V), (alo, ahi): (V, V), (blo, bhi): (V, V)) -> (V, V) {
        let zero = self.g.constant(0.0);
        let positive = self.push(Op::Lt(zero, clo));
        let negative = self.push(Op::Lt(chi, zero));
        let nonzero = self.push(Op::Add(positive, negative));
        let lo_zero = self.push(Op::Eq(clo, zero));
        let hi_zero = self.push(Op::Eq(chi, zero));
        let is_zero = self.push(Op::Mul(lo_zero, hi_zero));
        let union_lo = self.push(Op::Min(alo, blo));
        let union_hi = self.push(Op::Max(ahi, bhi));
        let lo = self.push(Op::Select(is_zero, blo, union_lo));
        let hi = self.push(Op::Select(is_zero, bhi, union_hi));
        (
            self.push(Op::Select(nonzero, alo, lo)),
            self.push(Op::Select(nonzero, ahi, hi)),
        )
    }
}
