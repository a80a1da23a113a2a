//! The IR: a typed SSA graph of scalar operations, one value per point.
//!
//! Vectors of the language are lowered to one scalar value per component, so every IR value is one f32 per
//! point and a JIT kernel evaluates each value for 4 points in one SIMD register. Nodes live in an arena in
//! topological order (arguments always precede their users) and are addressed by [`V`]. The builder
//! ([`Graph::push`]) hash-conses every node (common-subexpression elimination) and folds constants and
//! algebraic identities as it goes, so graphs are kept small during lowering and differentiation.
//!
//! A graph has per-point `outputs` and `reductions`: values summed over all points of a batch (the gradient
//! of a loss with respect to params). Kernels of every kind (value, gradient, vector-Jacobian product,
//! second order) are graphs of this one form.
//!
//! ```
//! use nerfjit_dsl::ir::{Graph, Op};
//! let mut g = Graph::new();
//! let x = g.input(0);
//! let y = g.push(Op::Mul(x, x));
//! let two = g.constant(2.0);
//! let z = g.push(Op::Add(y, two));
//! g.outputs.push(z);
//! assert_eq!(nerfjit_dsl::interp::eval_point(&g, &[3.0], &[]).outputs, vec![11.0]);
//! ```

use rustc_hash::FxHashMap;
use std::fmt;

pub(crate) mod semantics;

/// A value in a [`Graph`]: the index of the node that computes it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct V(pub u32);

/// A list of values interned in a [`Graph`] (the vector operand of a [`Dense`] node).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ListId(pub u32);

/// A matrix–vector product with a matrix of params: the multi-valued node of dense layers.
///
/// W is the `rows × cols` row-major block of params starting at param `w`. The node computes `W·x`
/// (`cols` inputs, `rows` outputs) or, when `transposed`, `Wᵀ·x` (`rows` inputs, `cols` outputs; the
/// backward pass of a layer). Its outputs are read through [`Op::Pick`]. Kernels run these nodes as
/// matrix products over tiles of points instead of one scalar op per weight.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Dense {
    /// The first param of W.
    pub w: u32,
    /// Rows of W.
    pub rows: u32,
    /// Columns of W.
    pub cols: u32,
    /// Whether the node computes Wᵀ·x instead of W·x.
    pub transposed: bool,
    /// The input vector.
    pub x: ListId,
}

impl Dense {
    /// The length of the input vector.
    pub fn n_in(&self) -> usize {
        (if self.transposed { self.rows } else { self.cols }) as usize
    }

    /// The number of outputs.
    pub fn n_out(&self) -> usize {
        (if self.transposed { self.cols } else { self.rows }) as usize
    }

    /// One past the last param of W.
    pub fn params_end(&self) -> usize {
        self.w as usize + (self.rows * self.cols) as usize
    }
}

/// A param gradient of outer-product form: `reductions[target + i·cols + j] += Σ_points left[i]·right[j]`
/// for i < rows, j < cols (the gradient of a [`Dense`] node's matrix, summed over a batch).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct Outer {
    /// The first reduction written.
    pub target: u32,
    /// The left vector (length rows).
    pub left: Vec<V>,
    /// The right vector (length cols).
    pub right: Vec<V>,
}

/// A grid encoding's table and layout (see [`crate::grid`]): a `grid` or `hashgrid` param.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct GridSpec {
    /// The first param of the table.
    pub table: u32,
    /// Levels of resolution.
    pub levels: u32,
    /// Floats per entry.
    pub features: u32,
    /// Entries per hashed level: 2^log2_size.
    pub log2_size: u32,
    /// Cells per axis of the coarsest level.
    pub base: u32,
    /// Cells per axis of the finest level.
    pub finest: u32,
    /// The half extent of the cubic bounds (f32 bits, so that the spec can be hashed).
    pub extent: u32,
}

/// A read of a grid encoding at a point (multi-valued: levels × features outputs, read through
/// [`Op::Pick`]), or of its derivative along the axes of `deriv` (bit a: ∂/∂p_a).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct GridRead {
    /// The grid.
    pub spec: GridSpec,
    /// The point.
    pub p: [V; 3],
    /// The axes the read is differentiated along.
    pub deriv: u8,
}

/// The param gradient of a grid read: `reductions[entry·features + f] += w(corner)·cotangent[l·features + f]`
/// for the 8 corners of every level (only the table entries the points touch).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct Scatter {
    /// The read whose table gets the gradient.
    pub read: GridRead,
    /// One cotangent per output of the read.
    pub cotangent: Vec<V>,
}

/// The bound of [`Op::TruncExp`]'s derivative: e^a is differentiated as e^clamp(a, −limit, limit).
pub const TRUNC_EXP_LIMIT: f64 = 15.0;

/// One scalar operation. Comparisons give 1.0 or 0.0.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Op {
    /// A constant (stored as f64 bits so that ops can be hashed).
    Const(u64),
    /// The i-th per-point input.
    Input(u32),
    /// The i-th learnable parameter (the same for every point).
    Param(u32),
    /// `-a`
    Neg(V),
    /// `|a|`
    Abs(V),
    /// 1 for a > 0, −1 for a < 0, else 0.
    Sign(V),
    /// Largest integer ≤ a.
    Floor(V),
    /// Square root.
    Sqrt(V),
    /// e^a
    Exp(V),
    /// Natural logarithm.
    Log(V),
    /// Sine.
    Sin(V),
    /// Cosine.
    Cos(V),
    /// Tangent.
    Tan(V),
    /// Hyperbolic tangent.
    Tanh(V),
    /// 1 / (1 + e^−a)
    Sigmoid(V),
    /// ln(1 + e^a)
    Softplus(V),
    /// e^a, whose derivative is taken as e^clamp(a, −15, 15) (instant-ngp's `trunc_exp` for densities: the
    /// gradient stays finite where the value is huge). [`TRUNC_EXP_LIMIT`] is the bound.
    TruncExp(V),
    /// a + b
    Add(V, V),
    /// a − b
    Sub(V, V),
    /// a · b
    Mul(V, V),
    /// a / b
    Div(V, V),
    /// `b < a ? b : a` (a NaN in `a` propagates; the SIMD `minps` semantics).
    Min(V, V),
    /// `a < b ? b : a`.
    Max(V, V),
    /// 1 if a < b else 0.
    Lt(V, V),
    /// 1 if a ≤ b else 0.
    Le(V, V),
    /// 1 if a = b else 0.
    Eq(V, V),
    /// `c != 0 ? a : b`.
    Select(V, V, V),
    /// A matrix–vector product (multi-valued; see [`Dense`]). Its list operand is read with
    /// [`Graph::args`]; [`Op::args`] does not see it.
    Dense(Dense),
    /// A read of a grid encoding (multi-valued; see [`GridRead`]).
    Grid(GridRead),
    /// Output `k` of the multi-valued node `d` ([`Op::Dense`] or [`Op::Grid`]).
    Pick(V, u32),
}

impl Op {
    /// The values this op reads, but for the list operand of [`Op::Dense`] (use [`Graph::args`]).
    pub fn args(&self) -> Args {
        use Op::*;
        let (vals, len) = match *self {
            Const(_) | Input(_) | Param(_) | Dense(_) => ([V(0); 3], 0),
            Pick(d, _) => ([d, V(0), V(0)], 1),
            Grid(r) => (r.p, 3),
            Neg(a) | Abs(a) | Sign(a) | Floor(a) | Sqrt(a) | Exp(a) | Log(a) | Sin(a) | Cos(a) | Tan(a)
            | Tanh(a) | Sigmoid(a) | Softplus(a) | TruncExp(a) => ([a, V(0), V(0)], 1),
            Add(a, b)
            | Sub(a, b)
            | Mul(a, b)
            | Div(a, b)
            | Min(a, b)
            | Max(a, b)
            | Lt(a, b)
            | Le(a, b)
            | Eq(a, b) => ([a, b, V(0)], 2),
            Select(c, a, b) => ([c, a, b], 3),
        };
        Args { vals, len }
    }

    /// The same op reading `f(arg)` for each argument, but for the list operand of [`Op::Dense`], which
    /// is left as it is (lists belong to a graph: see [`Graph::compact`]).
    pub fn map_args(&self, mut f: impl FnMut(V) -> V) -> Op {
        use Op::*;
        match *self {
            Const(_) | Input(_) | Param(_) | Dense(_) => *self,
            Pick(d, k) => Pick(f(d), k),
            Grid(r) => Grid(GridRead { p: r.p.map(f), ..r }),
            Neg(a) => Neg(f(a)),
            Abs(a) => Abs(f(a)),
            Sign(a) => Sign(f(a)),
            Floor(a) => Floor(f(a)),
            Sqrt(a) => Sqrt(f(a)),
            Exp(a) => Exp(f(a)),
            Log(a) => Log(f(a)),
            Sin(a) => Sin(f(a)),
            Cos(a) => Cos(f(a)),
            Tan(a) => Tan(f(a)),
            Tanh(a) => Tanh(f(a)),
            Sigmoid(a) => Sigmoid(f(a)),
            Softplus(a) => Softplus(f(a)),
            TruncExp(a) => TruncExp(f(a)),
            Add(a, b) => Add(f(a), f(b)),
            Sub(a, b) => Sub(f(a), f(b)),
            Mul(a, b) => Mul(f(a), f(b)),
            Div(a, b) => Div(f(a), f(b)),
            Min(a, b) => Min(f(a), f(b)),
            Max(a, b) => Max(f(a), f(b)),
            Lt(a, b) => Lt(f(a), f(b)),
            Le(a, b) => Le(f(a), f(b)),
            Eq(a, b) => Eq(f(a), f(b)),
            Select(c, a, b) => Select(f(c), f(a), f(b)),
        }
    }

    /// The op's name as printed in IR listings.
    pub fn name(&self) -> &'static str {
        use Op::*;
        match self {
            Const(_) => "const",
            Input(_) => "input",
            Param(_) => "param",
            Neg(_) => "neg",
            Abs(_) => "abs",
            Sign(_) => "sign",
            Floor(_) => "floor",
            Sqrt(_) => "sqrt",
            Exp(_) => "exp",
            Log(_) => "log",
            Sin(_) => "sin",
            Cos(_) => "cos",
            Tan(_) => "tan",
            Tanh(_) => "tanh",
            Sigmoid(_) => "sigmoid",
            Softplus(_) => "softplus",
            TruncExp(_) => "trunc_exp",
            Add(..) => "add",
            Sub(..) => "sub",
            Mul(..) => "mul",
            Div(..) => "div",
            Min(..) => "min",
            Max(..) => "max",
            Lt(..) => "lt",
            Le(..) => "le",
            Eq(..) => "eq",
            Select(..) => "select",
            Dense(d) if d.transposed => "dense_t",
            Dense(_) => "dense",
            Grid(r) if r.deriv != 0 => "grid_d",
            Grid(_) => "grid",
            Pick(..) => "pick",
        }
    }
}

/// The arguments of an op ([`Op::args`]), held inline: no op reads more than three values.
#[derive(Clone, Copy, Debug)]
pub struct Args {
    vals: [V; 3],
    len: usize,
}

impl std::ops::Deref for Args {
    type Target = [V];

    fn deref(&self) -> &[V] {
        &self.vals[..self.len]
    }
}

impl IntoIterator for Args {
    type Item = V;
    type IntoIter = std::iter::Take<std::array::IntoIter<V, 3>>;

    fn into_iter(self) -> Self::IntoIter {
        self.vals.into_iter().take(self.len)
    }
}

/// A graph of scalar ops with per-point outputs and per-batch reductions.
#[derive(Clone, Debug, Default)]
pub struct Graph {
    ops: Vec<Op>,
    /// Hash-consing of ops (Fx hashing): the first node of each op among `ops[..memo_covers]`. A rebuilt
    /// graph ([`Graph::rebuild`]: tens of thousands of nodes, rebuilt per box when simplified) starts
    /// without it, and it is made when a node is first added to that graph.
    memo: FxHashMap<Op, V>,
    memo_covers: usize,
    lists: Vec<Vec<V>>,
    list_memo: FxHashMap<Vec<V>, ListId>,
    /// Values written per point, in order.
    pub outputs: Vec<V>,
    /// Values summed over all points of a batch, in order.
    pub reductions: Vec<V>,
    /// Outer-product sums added to the reductions (the gradients of dense layers' matrices).
    pub outer: Vec<Outer>,
    /// Scatters added to the reductions (the gradients of grid encodings' tables).
    pub scatter: Vec<Scatter>,
    /// The number of per-point inputs a kernel of this graph takes (at least 1 + the largest input index).
    pub n_inputs: u32,
}

impl Graph {
    /// An empty graph.
    pub fn new() -> Graph {
        Graph::default()
    }

    /// An empty graph with room for `nodes` nodes.
    pub fn with_capacity(nodes: usize) -> Graph {
        let mut g = Graph::default();
        g.ops.reserve(nodes);
        g
    }

    /// The ops, in topological order.
    pub fn ops(&self) -> &[Op] {
        &self.ops
    }

    /// The op that computes `v`.
    pub fn op(&self, v: V) -> Op {
        self.ops[v.0 as usize]
    }

    /// The number of nodes.
    pub fn len(&self) -> usize {
        self.ops.len()
    }

    /// Whether the graph has no nodes.
    pub fn is_empty(&self) -> bool {
        self.ops.is_empty()
    }

    /// The interned lists (the operands of dense nodes).
    pub fn lists(&self) -> &[Vec<V>] {
        &self.lists
    }

    /// The values of list `l`.
    pub fn list(&self, l: ListId) -> &[V] {
        &self.lists[l.0 as usize]
    }

    /// The values `op` reads, including the list operand of [`Op::Dense`].
    pub fn args(&self, op: &Op) -> Vec<V> {
        match op {
            Op::Dense(d) => self.list(d.x).to_vec(),
            _ => op.args().to_vec(),
        }
    }

    /// Whether the graph has multi-valued nodes (dense products or grid reads) or scatters: it runs
    /// over tiles of points, not as one elementwise kernel.
    pub fn needs_tiles(&self) -> bool {
        !self.scatter.is_empty() || self.ops.iter().any(|op| matches!(op, Op::Dense(_) | Op::Grid(_)))
    }

    /// The outputs of a grid read at `p` (differentiated along the axes of `deriv`).
    pub fn grid(&mut self, spec: GridSpec, p: [V; 3], deriv: u8) -> Vec<V> {
        let node = self.insert(Op::Grid(GridRead { spec, p, deriv }));
        (0..spec.n_outputs() as u32)
            .map(|k| self.insert(Op::Pick(node, k)))
            .collect()
    }

    fn intern_list(&mut self, xs: &[V]) -> ListId {
        if let Some(&l) = self.list_memo.get(xs) {
            return l;
        }
        let l = ListId(u32::try_from(self.lists.len()).expect("more than 2^32 lists"));
        self.lists.push(xs.to_vec());
        self.list_memo.insert(xs.to_vec(), l);
        l
    }

    /// The outputs of `W·x` (or `Wᵀ·x` when `transposed`) for the `rows × cols` param block at `w`.
    /// Panics if `x` has the wrong length.
    pub fn dense(&mut self, w: u32, rows: u32, cols: u32, transposed: bool, x: &[V]) -> Vec<V> {
        let list = self.intern_list(x);
        let d = Dense {
            w,
            rows,
            cols,
            transposed,
            x: list,
        };
        assert_eq!(x.len(), d.n_in(), "dense input of the wrong length");
        let node = self.insert(Op::Dense(d));
        (0..d.n_out() as u32)
            .map(|k| self.insert(Op::Pick(node, k)))
            .collect()
    }

    /// Σ aᵢ·bᵢ.
    pub fn dot(&mut self, a: &[V], b: &[V]) -> V {
        let mut acc = self.constant(0.0);
        for (&x, &y) in a.iter().zip(b) {
            let p = self.push(Op::Mul(x, y));
            acc = self.push(Op::Add(acc, p));
        }
        acc
    }

    /// The Euclidean length √(Σ vᵢ²).
    pub fn length(&mut self, v: &[V]) -> V {
        let d = self.dot(v, v);
        self.push(Op::Sqrt(d))
    }

    /// The constant `c`.
    pub fn constant(&mut self, c: f64) -> V {
        // -0.0 and 0.0 are one constant: they behave alike in every op but division by zero.
        let c = if c == 0.0 { 0.0 } else { c };
        self.insert(Op::Const(c.to_bits()))
    }

    /// Per-point input `i`.
    pub fn input(&mut self, i: u32) -> V {
        self.n_inputs = self.n_inputs.max(i + 1);
        self.insert(Op::Input(i))
    }

    /// Learnable parameter `i`.
    pub fn param(&mut self, i: u32) -> V {
        self.insert(Op::Param(i))
    }

    /// The constant value of `v`, if it is a constant.
    pub fn const_value(&self, v: V) -> Option<f64> {
        match self.op(v) {
            Op::Const(bits) => Some(f64::from_bits(bits)),
            _ => None,
        }
    }

    fn is_const(&self, v: V, c: f64) -> bool {
        self.const_value(v) == Some(c)
    }

    fn insert(&mut self, op: Op) -> V {
        self.cover_memo();
        if let Some(&v) = self.memo.get(&op) {
            return v;
        }
        let v = self.append(op);
        self.memo.insert(op, v);
        self.memo_covers = self.ops.len();
        v
    }

    /// Adds `op` as a new node, without folding or hash-consing.
    fn append(&mut self, op: Op) -> V {
        let v = V(u32::try_from(self.ops.len()).expect("graph larger than 2^32 nodes"));
        self.ops.push(op);
        v
    }

    /// Adds the nodes appended without hash-consing to the memo (the first of equal ones).
    fn cover_memo(&mut self) {
        if self.memo_covers == self.ops.len() {
            return;
        }
        self.memo.reserve(self.ops.len() - self.memo_covers);
        for (i, &op) in self.ops.iter().enumerate().skip(self.memo_covers) {
            self.memo.entry(op).or_insert(V(i as u32));
        }
        self.memo_covers = self.ops.len();
    }

    /// Adds `op`, or finds an equal node, after folding constants and simple identities
    /// (x+0, x·1, x·0, x−x, −−x, select on a constant condition, ...).
    ///
    /// `x·0 = 0` is applied even though it is not IEEE-exact for infinite x: it keeps gradient graphs
    /// free of terms that are zero by construction, as symbolic-zero autodiff systems do.
    pub fn push(&mut self, op: Op) -> V {
        use Op::*;
        let args = op.args();
        if !args.is_empty() && args.iter().all(|&a| self.const_value(a).is_some()) {
            let vals: Vec<f64> = args.iter().map(|&a| self.const_value(a).unwrap_or(0.0)).collect();
            return self.constant(semantics::apply(op, &vals));
        }
        let op = match op {
            Add(a, b) | Mul(a, b) | Eq(a, b) if a > b => op.map_args(|x| if x == a { b } else { a }),
            _ => op,
        };
        match op {
            Add(a, b) if self.is_const(b, 0.0) => a,
            Add(a, b) if self.is_const(a, 0.0) => b,
            Sub(a, b) if self.is_const(b, 0.0) => a,
            Sub(a, b) if self.is_const(a, 0.0) => self.push(Neg(b)),
            Sub(a, b) if a == b => self.constant(0.0),
            Mul(a, b) if self.is_const(a, 0.0) || self.is_const(b, 0.0) => self.constant(0.0),
            Mul(a, b) if self.is_const(a, 1.0) => b,
            Mul(a, b) if self.is_const(b, 1.0) => a,
            Mul(a, b) if self.is_const(a, -1.0) => self.push(Neg(b)),
            Mul(a, b) if self.is_const(b, -1.0) => self.push(Neg(a)),
            Div(a, b) if self.is_const(b, 1.0) => a,
            Div(a, _) if self.is_const(a, 0.0) => self.constant(0.0),
            Neg(a) => match self.op(a) {
                Neg(x) => x,
                _ => self.insert(op),
            },
            Select(c, a, _) if self.const_value(c).is_some_and(|c| c != 0.0) => a,
            Select(c, _, b) if self.is_const(c, 0.0) => b,
            Select(_, a, b) if a == b => a,
            Min(a, b) | Max(a, b) if a == b => a,
            _ => self.insert(op),
        }
    }

    /// A copy holding only the nodes that outputs and reductions need, in the same order (dead-code
    /// elimination). `n_inputs` is kept.
    pub fn compact(&self) -> Graph {
        self.rebuild(&[]).0
    }

    /// [`Graph::compact`] where nodes may be replaced by one of their arguments: `alias[i]`, when given, is
    /// the argument (a value of this graph) that stands for node `i`. Only what the outputs then need is
    /// kept, node for node (nothing is folded or merged, but dense layers' and grid reads' equal nodes).
    /// Also gives, for each node of the new graph, the node of this graph it stands for.
    pub fn rebuild(&self, alias: &[Option<V>]) -> (Graph, Vec<V>) {
        // Each node's stand-in, through chains of aliases (arguments come first, so they are resolved).
        let mut resolved: Vec<V> = (0..self.ops.len() as u32).map(V).collect();
        for (i, a) in alias.iter().enumerate() {
            if let Some(a) = a {
                resolved[i] = resolved[a.0 as usize];
            }
        }
        let live = self.live_through(|v| resolved[v.0 as usize]);
        let mut out = Graph::with_capacity(live.iter().filter(|&&l| l).count());
        let mut map = vec![V(0); self.ops.len()];
        for (i, op) in self.ops.iter().enumerate() {
            if !live[i] {
                continue;
            }
            map[i] = match *op {
                Op::Dense(d) => {
                    let xs: Vec<V> = self
                        .list(d.x)
                        .iter()
                        .map(|a| map[resolved[a.0 as usize].0 as usize])
                        .collect();
                    let list = out.intern_list(&xs);
                    out.insert(Op::Dense(Dense { x: list, ..d }))
                }
                // A read at a constant point is not folded: it reads the params.
                Op::Grid(_) => out.insert(op.map_args(|a| map[resolved[a.0 as usize].0 as usize])),
                // The nodes of a hash-consed graph stay distinct and keep their arithmetic (nothing
                // folded: the same values in f32 as the original's).
                _ => out.append(op.map_args(|a| map[resolved[a.0 as usize].0 as usize])),
            };
        }
        let mut origin = vec![V(0); out.len()];
        for (i, &new) in map.iter().enumerate().rev() {
            if live[i] {
                origin[new.0 as usize] = V(i as u32);
            }
        }
        let map: Vec<V> = resolved.iter().map(|r| map[r.0 as usize]).collect();
        let remap = |vs: &[V]| -> Vec<V> { vs.iter().map(|v| map[v.0 as usize]).collect() };
        out.outputs = remap(&self.outputs);
        out.reductions = remap(&self.reductions);
        out.outer = self
            .outer
            .iter()
            .map(|o| Outer {
                target: o.target,
                left: remap(&o.left),
                right: remap(&o.right),
            })
            .collect();
        out.scatter = self
            .scatter
            .iter()
            .map(|sc| Scatter {
                read: GridRead {
                    p: sc.read.p.map(|v| map[v.0 as usize]),
                    ..sc.read
                },
                cotangent: remap(&sc.cotangent),
            })
            .collect();
        out.n_inputs = self.n_inputs;
        (out, origin)
    }

    /// Which nodes the outputs and reductions depend on.
    pub fn live(&self) -> Vec<bool> {
        self.live_through(|v| v)
    }

    /// [`Graph::live`] where every read of a node `v` reads `stand_in(v)` instead.
    fn live_through(&self, stand_in: impl Fn(V) -> V) -> Vec<bool> {
        let mut live = vec![false; self.ops.len()];
        let outer = self.outer.iter().flat_map(|o| o.left.iter().chain(&o.right));
        let scatter = self
            .scatter
            .iter()
            .flat_map(|s| s.read.p.iter().chain(&s.cotangent));
        for v in self
            .outputs
            .iter()
            .chain(&self.reductions)
            .chain(outer)
            .chain(scatter)
        {
            live[stand_in(*v).0 as usize] = true;
        }
        for i in (0..self.ops.len()).rev() {
            if !live[i] {
                continue;
            }
            let mut mark = |a: V| live[stand_in(a).0 as usize] = true;
            match &self.ops[i] {
                Op::Dense(d) => self.list(d.x).iter().for_each(|&a| mark(a)),
                op => op.args().into_iter().for_each(mark),
            }
        }
        live
    }

    /// The number of live nodes of each op name, for compile reports.
    pub fn stats(&self) -> Vec<(&'static str, usize)> {
        let mut counts: Vec<(&'static str, usize)> = Vec::new();
        for (op, live) in self.ops.iter().zip(self.live()) {
            if !live {
                continue;
            }
            match counts.iter_mut().find(|(n, _)| *n == op.name()) {
                Some(entry) => entry.1 += 1,
                None => counts.push((op.name(), 1)),
            }
        }
        counts
    }
}

impl fmt::Display for Graph {
    /// Prints the live nodes, one per line: `v3 = mul v1, v2`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let live = self.live();
        for (i, op) in self.ops.iter().enumerate() {
            if !live[i] {
                continue;
            }
            write!(f, "v{i} = {}", op.name())?;
            match *op {
                Op::Const(bits) => write!(f, " {}", f64::from_bits(bits))?,
                Op::Input(k) | Op::Param(k) => write!(f, " {k}")?,
                Op::Pick(d, k) => write!(f, " v{}[{k}]", d.0)?,
                Op::Dense(d) => {
                    let args: Vec<String> = self.list(d.x).iter().map(|a| format!("v{}", a.0)).collect();
                    write!(f, " p{}:{}x{} [{}]", d.w, d.rows, d.cols, args.join(", "))?;
                }
                Op::Grid(r) => {
                    let [x, y, z] = r.p.map(|v| v.0);
                    write!(
                        f,
                        " p{}:{}x{} d{} v{x}, v{y}, v{z}",
                        r.spec.table, r.spec.levels, r.spec.features, r.deriv
                    )?;
                }
                _ => {
                    let args: Vec<String> = op.args().iter().map(|a| format!("v{}", a.0)).collect();
                    write!(f, " {}", args.join(", "))?;
                }
            }
            writeln!(f)?;
        }
        for (k, v) in self.outputs.iter().enumerate() {
            writeln!(f, "output {k} = v{}", v.0)?;
        }
        for (k, v) in self.reductions.iter().enumerate() {
            writeln!(f, "reduce {k} = sum v{}", v.0)?;
        }
        for o in &self.outer {
            let names = |vs: &[V]| {
                vs.iter()
                    .map(|v| format!("v{}", v.0))
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            writeln!(
                f,
                "reduce {}..+{}x{} += outer [{}] [{}]",
                o.target,
                o.left.len(),
                o.right.len(),
                names(&o.left),
                names(&o.right)
            )?;
        }
        for sc in &self.scatter {
            let names: Vec<String> = sc.cotangent.iter().map(|v| format!("v{}", v.0)).collect();
            let [x, y, z] = sc.read.p.map(|v| v.0);
            writeln!(
                f,
                "reduce p{}.. += scatter d{} at v{x}, v{y}, v{z} [{}]",
                sc.read.spec.table,
                sc.read.deriv,
                names.join(", ")
            )?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builder_folds_and_dedupes() {
        let mut g = Graph::new();
        let x = g.input(0);
        let two = g.constant(2.0);
        let three = g.constant(3.0);
        let six = g.push(Op::Mul(two, three));
        assert_eq!(g.const_value(six), Some(6.0));
        let a = g.push(Op::Add(x, six));
        let b = g.push(Op::Add(six, x));
        assert_eq!(a, b, "commutative ops are deduplicated");
        let zero = g.constant(0.0);
        assert_eq!(g.push(Op::Mul(a, zero)), zero);
        assert_eq!(g.push(Op::Add(a, zero)), a);
        let n = g.push(Op::Neg(a));
        assert_eq!(g.push(Op::Neg(n)), a);
    }

    #[test]
    fn compact_drops_dead_nodes() {
        let mut g = Graph::new();
        let x = g.input(0);
        let _dead = g.push(Op::Sin(x));
        let y = g.push(Op::Exp(x));
        g.outputs.push(y);
        let c = g.compact();
        assert_eq!(c.len(), 2);
        assert_eq!(c.n_inputs, 1);
    }

    /// A rebuilt graph keeps its nodes as they are (an alias that makes a node's arguments constants
    /// folds nothing) and gives each new node the node it computes; nodes added to it afterwards are
    /// hash-consed against the rebuilt ones.
    #[test]
    fn rebuilt_graphs_keep_their_nodes_and_dedupe_what_is_added() {
        let mut g = Graph::new();
        let x = g.input(0);
        let one = g.constant(1.0);
        let two = g.constant(2.0);
        let m = g.push(Op::Min(x, one));
        let s = g.push(Op::Add(m, two));
        let y = g.push(Op::Mul(s, x));
        g.outputs.push(y);
        let mut alias = vec![None; g.len()];
        alias[m.0 as usize] = Some(one);
        let (mut r, origin) = g.rebuild(&alias);
        // x, 1, 2, 1 + 2 and (1 + 2)·x: the sum is not folded.
        assert_eq!(r.len(), 5);
        let sum = r.ops().iter().position(|op| matches!(op, Op::Add(..))).unwrap();
        assert_eq!(origin[sum], s);
        assert_eq!(r.op(r.outputs[0]), Op::Mul(V(0), V(sum as u32)));
        // Pushing an op the rebuilt graph has finds its node.
        let again = r.push(Op::Mul(V(sum as u32), V(0)));
        assert_eq!(again, r.outputs[0]);
        assert_eq!(r.len(), 5);
        assert_eq!(r.push(Op::Sin(V(0))), V(5));
    }
}
