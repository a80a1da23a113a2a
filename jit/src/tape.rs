//! A batch interpreter of elementwise graphs, for kernels too short-lived to pay for a compilation.
//!
//! Cranelift compiles about 20 µs per IR node: a field specialized to one region of a mesh (see
//! `nerfjit_dsl::simplify`), evaluated on a few thousand points, would spend a hundred times longer being
//! compiled than running. A [`Tape`] runs such a graph as a list of steps instead, each step one loop over a
//! chunk of points (vectorized by the Rust compiler, with AVX2 and FMA where the CPU has them), its values
//! in slots reused once dead so that a chunk's working set stays in the L1 cache.
//!
//! A tape gives the same bits as the [`crate::Kernel`] of the same graph: it takes only the ops whose
//! results IEEE arithmetic fixes (add, sub, mul, div, sqrt, min, max, abs, neg, sign, floor, comparisons,
//! selects), fuses the same products into FMAs and divides by constants the same way. Graphs with other
//! ops (whose kernels use polynomial approximations), dense layers, grid reads or reductions are refused.

use nerfjit_dsl::ir::{Graph, Op, V};

use crate::codegen::{fused_muls, sum_form, Fused, Negate};

/// Which products of `g` its kernel fuses into FMAs: those whose only reader is an add or a subtract (of
/// two such products, the second).
pub fn fused_products(g: &Graph) -> Vec<bool> {
    fused_muls(g)
}
use crate::kernel::JitError;

/// Points per chunk: 128 slots of 128 points fit in L1 with room to spare (64 KB).
const CHUNK: usize = 128;

/// Where a step reads or writes: a slot index.
type Slot = usize;

/// One step of a tape.
#[derive(Clone, Copy, Debug)]
enum Step {
    /// The slot holds one value for every point.
    Splat(Slot, f32),
    /// Input k.
    Input(Slot, usize),
    Unary(Slot, Unary, Slot),
    Binary(Slot, Binary, Slot, Slot),
    /// a·b + c, rounded once.
    Fma(Slot, Slot, Slot, Slot),
    /// c ≠ 0 ? a : b.
    Select(Slot, Slot, Slot, Slot),
}

#[derive(Clone, Copy, Debug)]
enum Unary {
    Neg,
    Abs,
    Sign,
    Floor,
    Sqrt,
}

#[derive(Clone, Copy, Debug)]
enum Binary {
    Add,
    Sub,
    Mul,
    Div,
    Min,
    Max,
    Lt,
    Le,
    Eq,
}

/// An elementwise graph ready to interpret (params bound at construction).
#[derive(Clone, Debug)]
pub struct Tape {
    steps: Vec<Step>,
    slots: usize,
    outputs: Vec<Slot>,
    /// Per-point inputs.
    pub n_inputs: usize,
}

/// Assigns slots to values, reusing a slot once its value is read for the last time.
struct Slots {
    free: Vec<Slot>,
    count: usize,
}

impl Slots {
    fn take(&mut self) -> Slot {
        self.free.pop().unwrap_or_else(|| {
            self.count += 1;
            self.count - 1
        })
    }
}

impl Tape {
    /// The tape of `g` with its params at `params`, or an error naming the first op a tape does not take.
    pub fn new(g: &Graph, params: &[f32]) -> Result<Tape, JitError> {
        Tape::with_fusion(g, params, &fused_products(g))
    }

    /// [`Tape::new`] with the products that fuse into FMAs given: `fused[i]` for node i, a product whose
    /// only reader is an add or a subtract (as [`fused_products`] decides them for `g` or for a graph `g`
    /// was simplified from, so that the tape rounds as that graph's kernel does).
    pub fn with_fusion(g: &Graph, params: &[f32], fused: &[bool]) -> Result<Tape, JitError> {
        let refuse = |what: &str| Err(JitError(format!("a tape cannot evaluate {what}")));
        if !g.reductions.is_empty() || !g.outer.is_empty() || !g.scatter.is_empty() {
            return refuse("reductions");
        }
        if fused.len() != g.len() {
            return refuse("a graph with fusion flags of another graph");
        }
        let live = g.live();
        let fused = &fusable(g, &live, fused);
        // The last step that reads each value (outputs are read after every step).
        let mut last_use = vec![0usize; g.len()];
        for (i, op) in g.ops().iter().enumerate() {
            if live[i] && !fused[i] {
                for a in Self::reads(g, op, fused) {
                    last_use[a.0 as usize] = i;
                }
            }
        }
        for v in &g.outputs {
            last_use[v.0 as usize] = usize::MAX;
        }
        let mut slots = Slots {
            free: Vec::new(),
            count: 0,
        };
        let mut slot_of: Vec<Slot> = vec![usize::MAX; g.len()];
        let mut steps = Vec::new();
        for (i, op) in g.ops().iter().enumerate() {
            if !live[i] || fused[i] {
                continue;
            }
            let s = |v: V| slot_of[v.0 as usize];
            // The result gets a slot no argument holds, then the arguments read for the last time free theirs.
            let out = slots.take();
            let step = match *op {
                Op::Const(bits) => Step::Splat(out, f64::from_bits(bits) as f32),
                Op::Param(k) => match params.get(k as usize) {
                    Some(&p) => Step::Splat(out, p),
                    None => return refuse("a param beyond those given"),
                },
                Op::Input(k) => Step::Input(out, k as usize),
                Op::Neg(a) => Step::Unary(out, Unary::Neg, s(a)),
                Op::Abs(a) => Step::Unary(out, Unary::Abs, s(a)),
                Op::Sign(a) => Step::Unary(out, Unary::Sign, s(a)),
                Op::Floor(a) => Step::Unary(out, Unary::Floor, s(a)),
                Op::Sqrt(a) => Step::Unary(out, Unary::Sqrt, s(a)),
                Op::Add(a, c) | Op::Sub(a, c) => match sum_form(g, fused, op) {
                    // As the kernel: the negated operand (of a subtract) first, then one FMA.
                    Some(Fused { p, q, addend, negate }) => {
                        let mut operand = |x: V, yes: bool| {
                            if !yes {
                                return s(x);
                            }
                            let neg = slots.take();
                            steps.push(Step::Unary(neg, Unary::Neg, s(x)));
                            slots.free.push(neg);
                            neg
                        };
                        let p = operand(p, negate == Negate::Product);
                        let addend = operand(addend, negate == Negate::Addend);
                        Step::Fma(out, p, s(q), addend)
                    }
                    None if matches!(op, Op::Sub(..)) => Step::Binary(out, Binary::Sub, s(a), s(c)),
                    None => Step::Binary(out, Binary::Add, s(a), s(c)),
                },
                Op::Mul(a, c) => Step::Binary(out, Binary::Mul, s(a), s(c)),
                // As the kernel: a multiplication by the constant's reciprocal.
                Op::Div(a, c) => match g.const_value(c) {
                    Some(k) if k != 0.0 && (1.0 / k).is_finite() => {
                        let r = slots.take();
                        steps.push(Step::Splat(r, (1.0 / k) as f32));
                        slots.free.push(r);
                        Step::Binary(out, Binary::Mul, s(a), r)
                    }
                    _ => Step::Binary(out, Binary::Div, s(a), s(c)),
                },
                Op::Min(a, c) => Step::Binary(out, Binary::Min, s(a), s(c)),
                Op::Max(a, c) => Step::Binary(out, Binary::Max, s(a), s(c)),
                Op::Lt(a, c) => Step::Binary(out, Binary::Lt, s(a), s(c)),
                Op::Le(a, c) => Step::Binary(out, Binary::Le, s(a), s(c)),
                Op::Eq(a, c) => Step::Binary(out, Binary::Eq, s(a), s(c)),
                Op::Select(c, a, b) => Step::Select(out, s(c), s(a), s(b)),
                _ => return refuse(&format!("'{}'", op.name())),
            };
            steps.push(step);
            slot_of[i] = out;
            for a in Self::reads(g, op, fused) {
                let a = a.0 as usize;
                if last_use[a] == i && slot_of[a] != usize::MAX {
                    slots.free.push(slot_of[a]);
                    slot_of[a] = usize::MAX;
                }
            }
        }
        let outputs = g.outputs.iter().map(|v| slot_of[v.0 as usize]).collect();
        Ok(Tape {
            steps,
            slots: slots.count,
            outputs,
            n_inputs: g.n_inputs as usize,
        })
    }

    /// The values step `op` reads: its arguments, a fused product's through it.
    /// (A fused product's only reader is an add or subtract: see [`fusable`].)
    fn reads(g: &Graph, op: &Op, fused: &[bool]) -> Vec<V> {
        let mut reads = Vec::new();
        for a in op.args() {
            match g.op(a) {
                Op::Mul(p, q) if fused[a.0 as usize] => reads.extend([p, q]),
                _ => reads.push(a),
            }
        }
        reads
    }

    /// Per-point outputs.
    pub fn n_outputs(&self) -> usize {
        self.outputs.len()
    }

    /// Evaluates points `0..n`: `inputs[k][i]` is input k of point i; writes `outputs[o][i]`.
    pub fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        assert!(inputs.len() >= self.n_inputs && inputs.iter().all(|x| x.len() >= n));
        assert!(outputs.len() >= self.outputs.len() && outputs.iter().all(|x| x.len() >= n));
        // The slots are kept per thread: a mesher calls a tape hundreds of thousands of times.
        thread_local! {
            static SLOTS: std::cell::RefCell<Vec<Vec<f32>>> = const { std::cell::RefCell::new(Vec::new()) };
        }
        SLOTS.with_borrow_mut(|slots| {
            if slots.len() < self.slots {
                slots.resize(self.slots, vec![0.0f32; CHUNK]);
            }
            let slots = &mut slots[..self.slots];
            #[cfg(target_arch = "x86_64")]
            if crate::gemm::has_avx2_fma() {
                // SAFETY: the CPU has AVX2 and FMA.
                unsafe { self.eval_avx2(n, inputs, outputs, slots) };
                return;
            }
            self.eval_chunks(n, inputs, outputs, slots);
        });
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn eval_avx2(
        &self,
        n: usize,
        inputs: &[&[f32]],
        outputs: &mut [&mut [f32]],
        slots: &mut [Vec<f32>],
    ) {
        self.eval_chunks(n, inputs, outputs, slots);
    }

    #[inline(always)]
    fn eval_chunks(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]], slots: &mut [Vec<f32>]) {
        for start in (0..n).step_by(CHUNK) {
            let m = CHUNK.min(n - start);
            for &step in &self.steps {
                run(step, m, slots, |k| &inputs[k][start..start + m]);
            }
            for (out, &slot) in outputs.iter_mut().zip(&self.outputs) {
                out[start..start + m].copy_from_slice(&slots[slot][..m]);
            }
        }
    }
}

/// The products flagged in `wanted` that can fuse: read once, by an add or subtract of two different values
/// (not both fused: then the second), and not an output.
fn fusable(g: &Graph, live: &[bool], wanted: &[bool]) -> Vec<bool> {
    let mut readers = vec![0u32; g.len()];
    let mut by_sum = vec![false; g.len()];
    for (i, op) in g.ops().iter().enumerate() {
        if !live[i] {
            continue;
        }
        for a in op.args() {
            readers[a.0 as usize] += 1;
        }
        if let Op::Add(a, b) | Op::Sub(a, b) = *op {
            if a != b {
                by_sum[a.0 as usize] = true;
                by_sum[b.0 as usize] = true;
            }
        }
    }
    for v in &g.outputs {
        readers[v.0 as usize] += 2;
    }
    let mut fused: Vec<bool> = (0..g.len())
        .map(|i| wanted[i] && live[i] && matches!(g.ops()[i], Op::Mul(..)) && readers[i] == 1 && by_sum[i])
        .collect();
    for (i, op) in g.ops().iter().enumerate() {
        if let (true, Op::Add(a, b) | Op::Sub(a, b)) = (live[i], *op) {
            if fused[a.0 as usize] && fused[b.0 as usize] {
                fused[a.0 as usize] = false;
            }
        }
    }
    fused
}

/// Runs one step on the first `m` points of the slots; `input(k)` gives the chunk's input k.
#[inline(always)]
fn run<'a>(step: Step, m: usize, slots: &mut [Vec<f32>], input: impl Fn(usize) -> &'a [f32]) {
    let out = match step {
        Step::Splat(o, _)
        | Step::Input(o, _)
        | Step::Unary(o, ..)
        | Step::Binary(o, ..)
        | Step::Fma(o, ..)
        | Step::Select(o, ..) => o,
    };
    // The result's slot is taken out while the arguments (other slots) are read.
    let mut o = std::mem::take(&mut slots[out]);
    let o_m = &mut o[..m];
    let s = |k: Slot| &slots[k][..m];
    match step {
        Step::Splat(_, c) => o_m.fill(c),
        Step::Input(_, k) => o_m.copy_from_slice(input(k)),
        Step::Unary(_, f, a) => {
            let a = s(a);
            match f {
                Unary::Neg => o_m.iter_mut().zip(a).for_each(|(o, &a)| *o = -a),
                Unary::Abs => o_m.iter_mut().zip(a).for_each(|(o, &a)| *o = a.abs()),
                Unary::Sign => o_m.iter_mut().zip(a).for_each(|(o, &a)| {
                    *o = if a > 0.0 {
                        1.0
                    } else if a < 0.0 {
                        -1.0
                    } else {
                        0.0
                    }
                }),
                Unary::Floor => o_m.iter_mut().zip(a).for_each(|(o, &a)| *o = a.floor()),
                Unary::Sqrt => o_m.iter_mut().zip(a).for_each(|(o, &a)| *o = a.sqrt()),
            }
        }
        Step::Binary(_, f, a, b) => {
            let (a, b) = (s(a), s(b));
            match f {
                Binary::Add => each(o_m, a, b, |a, b| a + b),
                Binary::Sub => each(o_m, a, b, |a, b| a - b),
                Binary::Mul => each(o_m, a, b, |a, b| a * b),
                Binary::Div => each(o_m, a, b, |a, b| a / b),
                // The kernel's minps and maxps: `b < a ? b : a` and `a < b ? b : a`.
                Binary::Min => each(o_m, a, b, |a, b| if b < a { b } else { a }),
                Binary::Max => each(o_m, a, b, |a, b| if a < b { b } else { a }),
                Binary::Lt => each(o_m, a, b, |a, b| one(a < b)),
                Binary::Le => each(o_m, a, b, |a, b| one(a <= b)),
                Binary::Eq => each(o_m, a, b, |a, b| one(a == b)),
            }
        }
        Step::Fma(_, a, b, c) => {
            for (((o, &a), &b), &c) in o_m.iter_mut().zip(s(a)).zip(s(b)).zip(s(c)) {
                *o = a.mul_add(b, c);
            }
        }
        Step::Select(_, c, a, b) => {
            for (((o, &c), &a), &b) in o_m.iter_mut().zip(s(c)).zip(s(a)).zip(s(b)) {
                *o = if c != 0.0 { a } else { b };
            }
        }
    }
    slots[out] = o;
}

/// `o[i] = f(a[i], b[i])`.
#[inline(always)]
fn each(o: &mut [f32], a: &[f32], b: &[f32], f: impl Fn(f32, f32) -> f32) {
    for ((o, &a), &b) in o.iter_mut().zip(a).zip(b) {
        *o = f(a, b);
    }
}

/// 1.0 for true, 0.0 for false (a comparison's value).
#[inline(always)]
fn one(c: bool) -> f32 {
    if c {
        1.0
    } else {
        0.0
    }
}
