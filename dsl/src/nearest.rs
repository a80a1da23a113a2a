//! Gradients of unions through the nearest primitive of each shape.
//!
//! The gradient of `min(d₀, …, dₙ)` is that of the nearest dᵢ, but reverse mode runs the backward pass of
//! every dᵢ, with an adjoint of 0 for all but one of them. Scenes are often unions of primitives that are
//! equal but for their constants (8 spheres, 6 boxes, …). For such a `min` (or `max`) tree,
//! [`gradient_seed`] builds one primitive of each shape whose constants are those of the nearest primitive
//! of that shape — chosen by the same comparisons reverse mode makes at each node of the tree — and a value
//! that selects the nearest shape's primitive. Seeding reverse mode with that value instead of the tree
//! runs one backward pass per shape. Its gradient is the tree's, up to rounding: the chosen primitive
//! computes the nearest primitive's formula with the same constants, and the tree passes its adjoint only
//! to the nearest primitive (the same side on ties), but the two graphs may fuse different products.

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};

use crate::ir::{Graph, Op, V};

/// The most primitives a union may have for [`gradient_seed`] to choose among them. The constants it
/// carries up a tree stay live across the tree's evaluation: on a union of 288 boxes (`nerfjit bench
/// large`) the gradient kernel shrank from 15,851 to 8,468 IR nodes, but Cranelift's register allocator
/// took 0.35 s for it instead of 0.08.
pub const MAX_PRIMITIVES: usize = 64;

/// The most nodes a primitive's graph may have (larger ones are left to plain reverse mode), which also
/// bounds how deep the recursive walks over it go.
const MAX_PRIMITIVE_NODES: usize = 4096;

/// The value to seed reverse mode with for the gradient of `root`: `root` itself unless it is a tree of
/// `min` (or of `max`) nodes over at most [`MAX_PRIMITIVES`] primitives, at least two of the same shape;
/// otherwise a value equal to the nearest primitive's whose gradient runs one backward pass per shape
/// (see the module's documentation).
pub fn gradient_seed(g: &mut Graph, root: V) -> V {
    let uses = use_counts(g);
    let Some(tree) = Tree::collect(g, root, &uses) else {
        return root;
    };
    let mut shapes: Vec<Shape> = Vec::new();
    let mut leaf_shape: HashMap<V, (usize, Vec<f64>)> = HashMap::new();
    for &leaf in &tree.leaves {
        let Some((shape, constants)) = Shape::of(g, leaf) else {
            return root;
        };
        let index = match shapes.iter().position(|s| *s == shape) {
            Some(i) => i,
            None => {
                shapes.push(shape);
                shapes.len() - 1
            }
        };
        leaf_shape.insert(leaf, (index, constants));
    }
    if shapes.len() == tree.leaves.len() {
        return root;
    }
    let nearest = tree.nearest(g, root, &leaf_shape);
    let mut shadows: Vec<(V, V)> = Vec::new();
    for (index, shape) in shapes.iter().enumerate() {
        let Some(chosen) = nearest.get(&index) else {
            continue;
        };
        shadows.push((chosen.flag, shape.build(g, &chosen.constants)));
    }
    let (_, last) = shadows.pop().expect("a tree has leaves");
    shadows
        .into_iter()
        .rev()
        .fold(last, |rest, (flag, value)| g.push(Op::Select(flag, value, rest)))
}

/// How many nodes (and outputs) read each node.
fn use_counts(g: &Graph) -> Vec<u32> {
    let mut uses = vec![0u32; g.len()];
    for op in g.ops() {
        for a in g.args(op) {
            uses[a.0 as usize] += 1;
        }
    }
    for &v in g.outputs.iter().chain(&g.reductions) {
        uses[v.0 as usize] += 1;
    }
    uses
}

/// A tree of `min` nodes, or of `max` nodes, whose inner nodes are read only by the tree.
struct Tree {
    is_min: bool,
    /// The nodes that are not inner nodes, in the order the tree reads them.
    leaves: Vec<V>,
    inner: HashSet<V>,
}

/// For one shape, at a node of the tree: the constants of its nearest primitive of that shape, and a flag
/// (1 or 0) saying whether the node's nearest primitive is of that shape.
struct Chosen {
    constants: Vec<V>,
    flag: V,
}

impl Tree {
    /// The tree rooted at `root`, if `root` is a `min` or a `max` (not ReLU's `max(x, 0)`, whose gradient
    /// takes another side at 0) over at most [`MAX_PRIMITIVES`] leaves.
    fn collect(g: &Graph, root: V, uses: &[u32]) -> Option<Tree> {
        let is_min = match g.op(root) {
            Op::Min(..) => true,
            Op::Max(_, b) if g.const_value(b).is_none_or(|c| c.to_bits() != 0) => false,
            _ => return None,
        };
        let mut tree = Tree {
            is_min,
            leaves: Vec::new(),
            inner: HashSet::new(),
        };
        // Depth first, the first operand first, without recursion: a chain of `let`s can make a tree as
        // deep as the script is long.
        let mut stack = vec![root];
        while let Some(v) = stack.pop() {
            if v == root || tree.is_inner(g, v, uses) {
                tree.inner.insert(v);
                let (Op::Min(a, b) | Op::Max(a, b)) = g.op(v) else {
                    unreachable!("inner nodes are min or max");
                };
                stack.extend([b, a]);
            } else if tree.leaves.len() == MAX_PRIMITIVES {
                return None;
            } else {
                tree.leaves.push(v);
            }
        }
        Some(tree)
    }

    fn is_inner(&self, g: &Graph, v: V, uses: &[u32]) -> bool {
        match g.op(v) {
            Op::Min(..) => self.is_min && uses[v.0 as usize] == 1,
            Op::Max(_, b) => {
                !self.is_min && uses[v.0 as usize] == 1 && g.const_value(b).is_none_or(|c| c.to_bits() != 0)
            }
            _ => false,
        }
    }

    /// For each shape present under `v`: its nearest primitive's constants and flag.
    fn nearest(
        &self,
        g: &mut Graph,
        v: V,
        leaf_shape: &HashMap<V, (usize, Vec<f64>)>,
    ) -> BTreeMap<usize, Chosen> {
        if !self.inner.contains(&v) {
            let (index, constants) = &leaf_shape[&v];
            let constants = constants.iter().map(|&c| g.constant(c)).collect();
            let flag = g.constant(1.0);
            return BTreeMap::from([(*index, Chosen { constants, flag })]);
        }
        let (Op::Min(a, b) | Op::Max(a, b)) = g.op(v) else {
            unreachable!("inner nodes are min or max");
        };
        let (left, right) = (self.nearest(g, a, leaf_shape), self.nearest(g, b, leaf_shape));
        // The comparison reverse mode makes: min(a, b) takes b where b < a, max(a, b) where a < b.
        let takes_b = if self.is_min {
            g.push(Op::Lt(b, a))
        } else {
            g.push(Op::Lt(a, b))
        };
        let zero = g.constant(0.0);
        let shapes: BTreeSet<usize> = left.keys().chain(right.keys()).copied().collect();
        let mut chosen = BTreeMap::new();
        for index in shapes {
            let pick = |g: &mut Graph, from_b: V, from_a: V| g.push(Op::Select(takes_b, from_b, from_a));
            let here = match (left.get(&index), right.get(&index)) {
                (Some(l), Some(r)) => Chosen {
                    constants: (l.constants.iter().zip(&r.constants))
                        .map(|(&ca, &cb)| pick(g, cb, ca))
                        .collect(),
                    flag: pick(g, r.flag, l.flag),
                },
                (Some(l), None) => Chosen {
                    constants: l.constants.clone(),
                    flag: pick(g, zero, l.flag),
                },
                (None, Some(r)) => Chosen {
                    constants: r.constants.clone(),
                    flag: pick(g, r.flag, zero),
                },
                (None, None) => unreachable!("the index comes from one side"),
            };
            chosen.insert(index, here);
        }
        chosen
    }
}

/// A primitive's graph with its constants taken out: its nodes in order, each op reading earlier nodes by
/// their place in the list; inputs and params as they are, and a `Const(0)` for each use of a constant.
/// The operands of commutative ops are placed in the order of their [`structure`], not of their nodes
/// (the graph orders them by node, which depends on what other primitives share).
#[derive(PartialEq)]
struct Shape {
    ops: Vec<Op>,
}

/// Whether the graph under `v` has at most `limit` nodes (counted without recursion).
fn within_nodes(g: &Graph, v: V, limit: usize) -> bool {
    let mut seen = HashSet::from([v]);
    let mut stack = vec![v];
    while let Some(x) = stack.pop() {
        for a in g.op(x).args() {
            if seen.insert(a) {
                if seen.len() > limit {
                    return false;
                }
                stack.push(a);
            }
        }
    }
    true
}

/// A hash of the graph under `v` with its constants taken out, commutative ops' operands in either order.
fn structure(g: &Graph, v: V, memo: &mut HashMap<V, u64>) -> u64 {
    use std::hash::{Hash, Hasher};
    if let Some(&h) = memo.get(&v) {
        return h;
    }
    let op = g.op(v);
    let mut keys: Vec<u64> = op.args().iter().map(|&a| structure(g, a, memo)).collect();
    if matches!(op, Op::Add(..) | Op::Mul(..) | Op::Eq(..)) {
        keys.sort_unstable();
    }
    let mut hasher = std::hash::DefaultHasher::new();
    match op {
        Op::Const(_) => "const".hash(&mut hasher),
        Op::Input(_) | Op::Param(_) => op.hash(&mut hasher),
        _ => op.name().hash(&mut hasher),
    }
    keys.hash(&mut hasher);
    let h = hasher.finish();
    memo.insert(v, h);
    h
}

impl Shape {
    /// The shape of the graph under `leaf` and its constants in order, unless it holds a node that is
    /// not elementwise (dense layers, grid reads) or more than [`MAX_PRIMITIVE_NODES`] nodes.
    fn of(g: &Graph, leaf: V) -> Option<(Shape, Vec<f64>)> {
        if !within_nodes(g, leaf, MAX_PRIMITIVE_NODES) {
            return None;
        }
        let mut shape = Shape { ops: Vec::new() };
        let mut constants = Vec::new();
        let mut placed: HashMap<V, V> = HashMap::new();
        shape.place(g, leaf, &mut placed, &mut constants, &mut HashMap::new())?;
        Some((shape, constants))
    }

    fn place(
        &mut self,
        g: &Graph,
        v: V,
        placed: &mut HashMap<V, V>,
        constants: &mut Vec<f64>,
        keys: &mut HashMap<V, u64>,
    ) -> Option<V> {
        let mut op = g.op(v);
        if let Op::Const(_) = op {
            // Each use of a constant is a slot of its own: two primitives of a shape may differ there.
            constants.push(g.const_value(v).expect("a constant"));
            self.ops.push(Op::Const(0));
            return Some(V(self.ops.len() as u32 - 1));
        }
        if let Some(&at) = placed.get(&v) {
            return Some(at);
        }
        if matches!(op, Op::Dense(_) | Op::Grid(_) | Op::Pick(..)) {
            return None;
        }
        if let Op::Add(a, b) | Op::Mul(a, b) | Op::Eq(a, b) = op {
            if structure(g, b, keys) < structure(g, a, keys) {
                op = op.map_args(|x| if x == a { b } else { a });
            }
        }
        let mut args = Vec::new();
        for a in op.args() {
            args.push(self.place(g, a, placed, constants, keys)?);
        }
        let mut next = args.into_iter();
        let local = op.map_args(|_| next.next().expect("one place per argument"));
        self.ops.push(local);
        let at = V(self.ops.len() as u32 - 1);
        placed.insert(v, at);
        Some(at)
    }

    /// The shape's graph with `constants` in its slots, added to `g`; returns its value.
    fn build(&self, g: &mut Graph, constants: &[V]) -> V {
        let mut slots = constants.iter();
        let mut values: Vec<V> = Vec::with_capacity(self.ops.len());
        for op in &self.ops {
            let v = match op {
                Op::Const(_) => *slots.next().expect("one constant per slot"),
                op => g.push(op.map_args(|local| values[local.0 as usize])),
            };
            values.push(v);
        }
        *values.last().expect("a shape has nodes")
    }
}
