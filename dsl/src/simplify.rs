//! Tape simplification, as fidget and libfive do it: the graph of a function restricted to a box of inputs.
//!
//! Over a box, interval bounds ([`crate::interval`]) often decide a choice for every point inside: a `min`
//! whose one argument lies wholly above the other, a `max` the reverse, a `select` whose condition (a
//! comparison, or any value) is decided everywhere. [`Simplifier::simplify`] replaces each such node by the
//! argument it takes and drops what only the other argument needed. A CSG scene of hundreds of primitives
//! joined by `min` keeps, near a point, the few primitives that can be nearest there: the simplified graph
//! evaluates a fraction of the operations.
//!
//! A choice is taken only when the bounds clear each other by a margin of
//! `1e-4 · (1 + |lo| + |hi|)` (as octree meshing keeps for its decisions), far above the f32 rounding of
//! values and bounds, so the simplified graph gives the same values as the original at every point of the
//! box where all the values the original computes are numbers (a NaN inside may take the dropped branch).
//!
//! ```
//! use nerfjit_dsl::ir::{Graph, Op};
//! use nerfjit_dsl::simplify::Simplifier;
//! // f(x) = min(x, 10 − x): on [0, 2] it is x.
//! let mut g = Graph::new();
//! let x = g.input(0);
//! let ten = g.constant(10.0);
//! let other = g.push(Op::Sub(ten, x));
//! let f = g.push(Op::Min(x, other));
//! g.outputs.push(f);
//! g.n_inputs = 1;
//! let simplified = Simplifier::new(&g).simplify(&[0.0], &[2.0], &[]);
//! assert_eq!(simplified.choices, 1);
//! assert_eq!(simplified.graph.len(), 1); // the input alone
//! assert_eq!(simplified.graph.op(simplified.graph.outputs[0]), Op::Input(0));
//! ```

use crate::interval::NodeBounds;
use crate::ir::{Graph, Op, V};

/// The relative margin by which bounds must clear each other for a choice (see the module docs).
pub const MARGIN: f64 = 1e-4;

/// A graph restricted to a box.
#[derive(Clone, Debug)]
pub struct Simplified {
    /// The simplified graph: same inputs, params and outputs as the original, compacted.
    pub graph: Graph,
    /// For each node of `graph`, the node of the simplifier's graph ([`Simplifier::graph`]) it computes:
    /// compilers that decide per node, such as which products fuse into FMAs, can decide as they did for
    /// the original.
    pub origin: Vec<V>,
    /// How many `min`, `max` and `select` nodes the box decided.
    pub choices: usize,
}

/// Simplifies one graph over many boxes (its node bounds are prepared once).
pub struct Simplifier {
    graph: Graph,
    bounds: NodeBounds,
}

/// Whether an interval whose upper bound is `hi` lies below one whose lower bound is `other_lo`, by the margin.
fn clearly_below(hi: f64, other_lo: f64) -> bool {
    hi + MARGIN * (1.0 + hi.abs() + other_lo.abs()) < other_lo
}

impl Simplifier {
    /// Prepares the simplification of `g` (per-point outputs; reductions, outer products and scatters are
    /// kept as they are, so graphs with them gain little). Nodes the outputs do not need are dropped by
    /// every simplification.
    pub fn new(g: &Graph) -> Simplifier {
        Simplifier {
            graph: g.clone(),
            bounds: NodeBounds::new(g),
        }
    }

    /// The graph it simplifies.
    pub fn graph(&self) -> &Graph {
        &self.graph
    }

    /// The graph restricted to the box `lo ≤ x ≤ hi` of inputs, with the params at `params`.
    pub fn simplify(&self, lo: &[f64], hi: &[f64], params: &[f64]) -> Simplified {
        let bounds = self.bounds.eval(lo, hi, params);
        let alias: Vec<Option<V>> = self
            .graph
            .ops()
            .iter()
            .map(|op| self.choice(op, &bounds))
            .collect();
        let (graph, origin) = self.graph.rebuild(&alias);
        Simplified {
            graph,
            origin,
            choices: alias.iter().filter(|a| a.is_some()).count(),
        }
    }

    /// The argument `op` takes at every point of the box, where the bounds decide it.
    fn choice(&self, op: &Op, bounds: &[Option<(f64, f64)>]) -> Option<V> {
        let of = |v: V| bounds[v.0 as usize];
        match *op {
            Op::Min(a, b) | Op::Max(a, b) => {
                let ((alo, ahi), (blo, bhi)) = (of(a)?, of(b)?);
                let (low, high) = if clearly_below(ahi, blo) {
                    (a, b)
                } else if clearly_below(bhi, alo) {
                    (b, a)
                } else {
                    return None;
                };
                Some(if matches!(op, Op::Min(..)) { low } else { high })
            }
            Op::Select(c, a, b) => self.condition(c, bounds).map(|holds| if holds { a } else { b }),
            _ => None,
        }
    }

    /// Whether condition `c` is nonzero (or zero) at every point of the box, where the bounds decide it by
    /// the margin: a comparison from its arguments' bounds, any other value from its own.
    fn condition(&self, c: V, bounds: &[Option<(f64, f64)>]) -> Option<bool> {
        let of = |v: V| bounds[v.0 as usize];
        match self.graph.op(c) {
            Op::Lt(a, b) | Op::Le(a, b) => {
                let ((alo, ahi), (blo, bhi)) = (of(a)?, of(b)?);
                match (clearly_below(ahi, blo), clearly_below(bhi, alo)) {
                    (true, _) => Some(true),
                    (_, true) => Some(false),
                    _ => None,
                }
            }
            Op::Eq(a, b) => {
                let ((alo, ahi), (blo, bhi)) = (of(a)?, of(b)?);
                (clearly_below(ahi, blo) || clearly_below(bhi, alo)).then_some(false)
            }
            _ => {
                let (lo, hi) = of(c)?;
                if clearly_below(0.0, lo) || clearly_below(hi, 0.0) {
                    Some(true)
                } else {
                    None
                }
            }
        }
    }
}
