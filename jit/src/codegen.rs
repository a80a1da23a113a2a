//! Lowering of an IR [`Graph`] to one Cranelift function that evaluates it over a batch of points.
//!
//! The function's signature is
//! `fn(inputs: *const *const f32, outputs: *const *mut f32, params: *const f32, accum: *mut f32, n: i64)`:
//! `inputs` and `outputs` point to arrays of column pointers (structure of arrays), or `inputs` is the base
//! of a tiled kernel's arena whose columns lie at offsets fixed at compile time ([`Columns`]); `accum`
//! holds 4 lanes per reduction. A main loop evaluates whole groups of 4 points; a last partial group masks
//! the reduction lanes at or beyond `n`. Each input is loaded where the graph's input node is and each
//! output stored as soon as it is computed. The caller guarantees that every column holds `n` rounded up to
//! a multiple of 4 points (see [`crate::Kernel`]), so no access leaves the buffers.

use cranelift_codegen::ir::condcodes::{FloatCC, IntCC};
use cranelift_codegen::ir::{types, AbiParam, InstBuilder, MemFlagsData, Signature, Value};
use cranelift_frontend::{FunctionBuilder, Variable};
use nerfjit_dsl::ir::{Graph, Op, V};

use crate::simd::Simd;

/// Where a kernel finds its columns.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Columns {
    /// In the arrays of column pointers that are its first two arguments.
    Pointers,
    /// At fixed byte offsets from the address that is its first argument (the arena of a tiled kernel's
    /// tile): input k at `reads[k]`, output k at `writes[k]`. The second argument is not read.
    Offsets {
        /// The byte offset of each input column.
        reads: Vec<i32>,
        /// The byte offset of each output column.
        writes: Vec<i32>,
    },
}

/// The addresses of the kernel's columns, as the loop reaches them.
enum ColumnAddresses<'a> {
    /// One pointer per column, loaded once in the entry block.
    Pointers { inputs: Vec<Value>, outputs: Vec<Value> },
    /// One base and the columns' constant offsets from it: every access is a single load or store with
    /// an immediate displacement, and no column pointer takes a register or a stack slot.
    Offsets {
        base: Value,
        reads: &'a [i32],
        writes: &'a [i32],
    },
}

/// The column and buffer pointers of the kernel, loaded once in the entry block.
struct Buffers<'a> {
    columns: ColumnAddresses<'a>,
    params: Value,
    accum: Value,
    sums: Sums,
}

/// Where the running sums of the reductions live during the loop.
enum Sums {
    /// In registers (one variable per reduction), loaded before and stored after the loop: no
    /// loop-carried dependency through memory.
    Registers(Vec<Variable>),
    /// In the accumulator buffer, updated every group (for kernels with many reductions, e.g. the param
    /// gradients of a network, which would not fit in registers).
    Memory,
}

/// The most reductions kept in registers.
const MAX_REGISTER_SUMS: usize = 12;

/// The kernel's signature for a target with pointer type `ptr`.
pub fn signature(sig: &mut Signature, ptr: types::Type) {
    for _ in 0..4 {
        sig.params.push(AbiParam::new(ptr));
    }
    sig.params.push(AbiParam::new(types::I64));
}

/// Which multiplications are folded into the add or subtract that is their only user (emitted as FMA).
pub(crate) fn fused_muls(g: &Graph) -> Vec<bool> {
    let live = g.live();
    let mut uses = vec![0u32; g.len()];
    for (i, op) in g.ops().iter().enumerate() {
        if live[i] {
            for a in op.args() {
                uses[a.0 as usize] += 1;
            }
        }
    }
    for v in g.outputs.iter().chain(&g.reductions) {
        uses[v.0 as usize] += 2;
    }
    let is_mul = |v: V| matches!(g.op(v), Op::Mul(..));
    let mut fused = vec![false; g.len()];
    for (i, op) in g.ops().iter().enumerate() {
        if !live[i] {
            continue;
        }
        if let Op::Add(a, b) | Op::Sub(a, b) = *op {
            if a != b {
                for m in [a, b] {
                    if is_mul(m) && uses[m.0 as usize] == 1 {
                        fused[m.0 as usize] = true;
                    }
                }
            }
        }
    }
    // An add of two fusable products fuses only the second. (Dead sums do not count: they are not
    // compiled, and a compacted graph, which has none, must fuse the same products.)
    for (i, op) in g.ops().iter().enumerate() {
        if let (true, Op::Add(a, b) | Op::Sub(a, b)) = (live[i], *op) {
            if fused[a.0 as usize] && fused[b.0 as usize] {
                fused[a.0 as usize] = false;
            }
        }
    }
    fused
}

/// Which operand of a fused multiply-add is negated (for a subtract).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Negate {
    Nothing,
    /// a − p·q = (−p)·q + a.
    Product,
    /// p·q − c = p·q + (−c).
    Addend,
}

/// An add or subtract emitted as one FMA: `±p · q ± addend`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Fused {
    pub p: V,
    pub q: V,
    pub addend: V,
    pub negate: Negate,
}

/// The FMA an add or subtract `op` becomes, given the products that fuse ([`fused_muls`]); `None` for a
/// plain add or subtract.
pub(crate) fn sum_form(g: &Graph, fused: &[bool], op: &Op) -> Option<Fused> {
    let (Op::Add(a, c) | Op::Sub(a, c)) = *op else {
        return None;
    };
    let sub = matches!(op, Op::Sub(..));
    let product = |x: V| match (fused[x.0 as usize], g.op(x)) {
        (true, Op::Mul(p, q)) => Some((p, q)),
        _ => None,
    };
    let pick = |yes: bool, negate: Negate| if yes { negate } else { Negate::Nothing };
    match (product(a), product(c)) {
        // a + p·q  or  a − p·q
        (_, Some((p, q))) => Some(Fused {
            p,
            q,
            addend: a,
            negate: pick(sub, Negate::Product),
        }),
        // p·q + c  or  p·q − c
        (Some((p, q)), None) => Some(Fused {
            p,
            q,
            addend: c,
            negate: pick(sub, Negate::Addend),
        }),
        (None, None) => None,
    }
}

/// Emits the IR ops of one graph as f32x4 instructions.
pub struct GraphEmitter<'g> {
    g: &'g Graph,
    fused: Vec<bool>,
    live: Vec<bool>,
    /// (node, output index) for every output, by node.
    outputs_by_node: Vec<(usize, usize)>,
}

impl<'g> GraphEmitter<'g> {
    /// Prepares `g` for emission (liveness and FMA fusion).
    pub fn new(g: &'g Graph) -> Self {
        let mut outputs_by_node: Vec<(usize, usize)> = g
            .outputs
            .iter()
            .enumerate()
            .map(|(k, v)| (v.0 as usize, k))
            .collect();
        outputs_by_node.sort_unstable();
        GraphEmitter {
            g,
            fused: fused_muls(g),
            live: g.live(),
            outputs_by_node,
        }
    }

    /// Emits the graph in the current block with input k = `input(b, k)` and params read from `params`,
    /// handing output k's value to `output(b, k, value)` as soon as it is computed; returns the values of
    /// the reductions. Inputs are taken where the graph's input nodes are and outputs given where theirs
    /// are, so that a kernel's loads and stores lie next to their uses: Cranelift keeps loads and stores
    /// in the order they are emitted, and loads all made before stores all made after would keep every
    /// loaded value live (spilled) across the whole group.
    pub fn emit(
        &self,
        b: &mut FunctionBuilder,
        input: &mut dyn FnMut(&mut FunctionBuilder, u32) -> Value,
        output: &mut dyn FnMut(&mut FunctionBuilder, usize, Value),
        params: Value,
    ) -> Vec<Value> {
        let g = self.g;
        let fused = &self.fused;
        let mut vals: Vec<Option<Value>> = vec![None; g.len()];
        // Masks of comparisons, kept so that a select on a comparison needs no conversion.
        let mut masks: Vec<Option<Value>> = vec![None; g.len()];
        let mut next_output = self.outputs_by_node.iter().peekable();
        for (idx, op) in g.ops().iter().enumerate() {
            if !self.live[idx] || fused[idx] {
                continue;
            }
            let mut s = Simd { b };
            let v = |x: V| vals[x.0 as usize].expect("argument emitted before use");
            let value = match *op {
                Op::Const(bits) => s.f(f64::from_bits(bits) as f32),
                Op::Param(k) => {
                    let flags = MemFlagsData::trusted().with_readonly();
                    let p = s.b.ins().load(types::F32, flags, params, (k * 4) as i32);
                    s.b.ins().splat(types::F32X4, p)
                }
                Op::Input(k) => input(s.b, k),
                // The sign bit flipped or cleared by one `xor` or `and` with a constant mask, where
                // Cranelift's vector `fneg` and `fabs` make the mask anew each time (three
                // instructions).
                Op::Neg(a) => {
                    let sign_bit = s.f(-0.0);
                    s.b.ins().bxor(v(a), sign_bit)
                }
                Op::Abs(a) => {
                    let magnitude = s.f(f32::from_bits(0x7fff_ffff));
                    s.b.ins().band(v(a), magnitude)
                }
                Op::Sign(a) => {
                    let zero = s.f(0.0);
                    let pos = s.cmp(FloatCC::GreaterThan, v(a), zero);
                    let neg = s.cmp(FloatCC::LessThan, v(a), zero);
                    let one = s.f(1.0);
                    let mone = s.f(-1.0);
                    let p = s.b.ins().band(pos, one);
                    let m = s.b.ins().band(neg, mone);
                    s.b.ins().bor(p, m)
                }
                Op::Floor(a) => s.b.ins().floor(v(a)),
                Op::Sqrt(a) => s.b.ins().sqrt(v(a)),
                Op::Exp(a) | Op::TruncExp(a) => s.exp(v(a)),
                Op::Log(a) => s.log(v(a)),
                Op::Sin(a) => s.sin_cos(v(a), 0),
                Op::Cos(a) => s.sin_cos(v(a), 1),
                Op::Tan(a) => s.tan(v(a)),
                Op::Tanh(a) => s.tanh(v(a)),
                Op::Sigmoid(a) => s.sigmoid(v(a)),
                Op::Softplus(a) => s.softplus(v(a)),
                Op::Add(a, c) | Op::Sub(a, c) => match sum_form(g, fused, op) {
                    Some(Fused { p, q, addend, negate }) => {
                        let neg =
                            |s: &mut Simd, x: V, yes: bool| if yes { s.b.ins().fneg(v(x)) } else { v(x) };
                        let pv = neg(&mut s, p, negate == Negate::Product);
                        let cv = neg(&mut s, addend, negate == Negate::Addend);
                        s.fma(pv, v(q), cv)
                    }
                    None if matches!(op, Op::Sub(..)) => s.b.ins().fsub(v(a), v(c)),
                    None => s.b.ins().fadd(v(a), v(c)),
                },
                Op::Mul(a, c) => s.b.ins().fmul(v(a), v(c)),
                // Division by a constant is a multiplication by its reciprocal (within 1 ulp; much faster).
                Op::Div(a, c) => match g.const_value(c) {
                    Some(k) if k != 0.0 && (1.0 / k).is_finite() => {
                        let r = s.f((1.0 / k) as f32);
                        s.b.ins().fmul(v(a), r)
                    }
                    _ => s.b.ins().fdiv(v(a), v(c)),
                },
                Op::Min(a, c) => s.min(v(a), v(c)),
                Op::Max(a, c) => s.max(v(a), v(c)),
                Op::Lt(a, c) | Op::Le(a, c) | Op::Eq(a, c) => {
                    let cc = match op {
                        Op::Lt(..) => FloatCC::LessThan,
                        Op::Le(..) => FloatCC::LessThanOrEqual,
                        _ => FloatCC::Equal,
                    };
                    let m = s.cmp(cc, v(a), v(c));
                    masks[idx] = Some(m);
                    s.mask_to_one(m)
                }
                Op::Select(c, a, d) => {
                    let m = match masks[c.0 as usize] {
                        Some(m) => m,
                        None => {
                            let zero = s.f(0.0);
                            s.cmp(FloatCC::NotEqual, v(c), zero)
                        }
                    };
                    // A branch of +0.0 (all bits clear) is a mask: `m ? a : 0` is `m & a`, one
                    // instruction where a blend takes two.
                    let positive_zero = |x: V| g.const_value(x).is_some_and(|c| c.to_bits() == 0);
                    if positive_zero(d) {
                        s.b.ins().band(m, v(a))
                    } else if positive_zero(a) {
                        s.b.ins().band_not(v(d), m)
                    } else {
                        s.select(m, v(a), v(d))
                    }
                }
                Op::Dense(_) | Op::Grid(_) | Op::Pick(..) => {
                    unreachable!("graphs with dense nodes are compiled by the tiled executor")
                }
            };
            vals[idx] = Some(value);
            while let Some(&(_, k)) = next_output.next_if(|&&(node, _)| node == idx) {
                output(b, k, value);
            }
        }
        // (Every output is a node emitted above; should one not be, it is still stored, last.)
        for &(node, k) in next_output {
            output(b, k, vals[node].expect("outputs are live"));
        }
        g.reductions
            .iter()
            .map(|x| vals[x.0 as usize].expect("emitted"))
            .collect()
    }
}

/// Emits the body of the kernel function for `g`, reading and writing its columns where `columns` says,
/// into `b` (whose signature is [`signature`]).
pub fn build(b: &mut FunctionBuilder, g: &Graph, columns: &Columns) {
    let ptr = types::I64;
    let entry = b.create_block();
    b.append_block_params_for_function_params(entry);
    b.switch_to_block(entry);
    b.seal_block(entry);
    let args = b.block_params(entry).to_vec();
    let (in_arr, out_arr, params, accum, n) = (args[0], args[1], args[2], args[3], args[4]);
    let flags = MemFlagsData::trusted().with_readonly();
    let columns = match columns {
        Columns::Pointers => ColumnAddresses::Pointers {
            inputs: (0..g.n_inputs)
                .map(|k| b.ins().load(ptr, flags, in_arr, (k * 8) as i32))
                .collect(),
            outputs: (0..g.outputs.len())
                .map(|k| b.ins().load(ptr, flags, out_arr, (k * 8) as i32))
                .collect(),
        },
        Columns::Offsets { reads, writes } => {
            assert!(
                reads.len() == g.n_inputs as usize && writes.len() == g.outputs.len(),
                "one offset per column"
            );
            ColumnAddresses::Offsets {
                base: in_arr,
                reads,
                writes,
            }
        }
    };
    let sums = if g.reductions.len() <= MAX_REGISTER_SUMS {
        let vars: Vec<Variable> = (0..g.reductions.len())
            .map(|_| b.declare_var(types::F32X4))
            .collect();
        for (k, &var) in vars.iter().enumerate() {
            let start = b.ins().load(
                types::F32X4,
                MemFlagsData::new().with_notrap(),
                accum,
                (k * 16) as i32,
            );
            b.def_var(var, start);
        }
        Sums::Registers(vars)
    } else {
        Sums::Memory
    };
    let bufs = Buffers {
        columns,
        params,
        accum,
        sums,
    };
    let emitter = GraphEmitter::new(g);

    let main_head = b.create_block();
    let main_body = b.create_block();
    let tail_head = b.create_block();
    let tail_body = b.create_block();
    let exit = b.create_block();
    for block in [main_head, tail_head] {
        b.append_block_param(block, ptr);
    }
    let zero = b.ins().iconst(ptr, 0);
    b.ins().jump(main_head, &[zero.into()]);

    // Main loop: whole groups of 4 points (i + 4 <= n), no masks.
    b.switch_to_block(main_head);
    let i = b.block_params(main_head)[0];
    let next = b.ins().iadd_imm_s(i, 4);
    let more = b.ins().icmp(IntCC::SignedLessThanOrEqual, next, n);
    b.ins().brif(more, main_body, &[], tail_head, &[i.into()]);
    b.switch_to_block(main_body);
    b.seal_block(main_body);
    emit_group(b, &emitter, &bufs, i, None);
    b.ins().jump(main_head, &[next.into()]);
    b.seal_block(main_head);

    // Tail: at most one partial group, reductions masked to the lanes below n.
    b.switch_to_block(tail_head);
    let i = b.block_params(tail_head)[0];
    let more = b.ins().icmp(IntCC::SignedLessThan, i, n);
    b.ins().brif(more, tail_body, &[], exit, &[]);
    b.switch_to_block(tail_body);
    b.seal_block(tail_body);
    let remaining = b.ins().isub(n, i);
    let remaining = b.ins().ireduce(types::I32, remaining);
    let remaining = b.ins().splat(types::I32X4, remaining);
    let lanes = lane_indices(b);
    let mask = b.ins().icmp(IntCC::SignedLessThan, lanes, remaining);
    emit_group(b, &emitter, &bufs, i, Some(mask));
    b.ins().jump(exit, &[]);
    b.seal_block(tail_head);

    b.switch_to_block(exit);
    b.seal_block(exit);
    if let Sums::Registers(vars) = &bufs.sums {
        for (k, &var) in vars.iter().enumerate() {
            let sum = b.use_var(var);
            b.ins()
                .store(MemFlagsData::new().with_notrap(), sum, accum, (k * 16) as i32);
        }
    }
    b.ins().return_(&[]);
}

/// The vector [0, 1, 2, 3] of i32 lanes.
pub fn lane_indices(b: &mut FunctionBuilder) -> Value {
    let bytes: Vec<u8> = [0u32, 1, 2, 3].iter().flat_map(|x| x.to_le_bytes()).collect();
    let lanes = b.func.dfg.constants.insert(bytes.into());
    b.ins().vconst(types::I32X4, lanes)
}

/// An address as a value and a displacement from it.
type Address = (Value, i32);

/// Emits the graph for the group of 4 points starting at point `i`: loads, ops, stores, reductions.
fn emit_group(
    b: &mut FunctionBuilder,
    emitter: &GraphEmitter,
    bufs: &Buffers,
    i: Value,
    lane_mask: Option<Value>,
) {
    let offset = b.ins().ishl_imm_s(i, 2);
    let flags = MemFlagsData::new().with_notrap();
    // Each column's address at this group: a pointer plus the group's offset, or the base plus it with
    // the column's own offset as the displacement.
    let (input_at, output_at): (Vec<Address>, Vec<Address>) = match &bufs.columns {
        ColumnAddresses::Pointers { inputs, outputs } => {
            let mut at =
                |ps: &[Value]| -> Vec<Address> { ps.iter().map(|&p| (b.ins().iadd(p, offset), 0)).collect() };
            (at(inputs), at(outputs))
        }
        ColumnAddresses::Offsets { base, reads, writes } => {
            let addr = b.ins().iadd(*base, offset);
            let at = |offsets: &[i32]| offsets.iter().map(|&o| (addr, o)).collect();
            (at(reads), at(writes))
        }
    };
    let mut load = |b: &mut FunctionBuilder, k: u32| {
        let (addr, o) = input_at[k as usize];
        b.ins().load(types::F32X4, flags.with_readonly(), addr, o)
    };
    let mut store = |b: &mut FunctionBuilder, k: usize, value: Value| {
        let (addr, o) = output_at[k];
        b.ins().store(flags, value, addr, o);
    };
    let reductions = emitter.emit(b, &mut load, &mut store, bufs.params);
    for (k, (&term, &r)) in reductions.iter().zip(&emitter.g.reductions).enumerate() {
        if emitter.g.const_value(r) == Some(0.0) {
            continue;
        }
        let term = match lane_mask {
            Some(mask) => {
                let mut s = Simd { b };
                let mask = s.float(mask);
                s.b.ins().band(term, mask)
            }
            None => term,
        };
        match &bufs.sums {
            Sums::Registers(vars) => {
                let acc = b.use_var(vars[k]);
                let sum = b.ins().fadd(acc, term);
                b.def_var(vars[k], sum);
            }
            Sums::Memory => {
                let acc = b.ins().load(types::F32X4, flags, bufs.accum, (k * 16) as i32);
                let sum = b.ins().fadd(acc, term);
                b.ins().store(flags, sum, bufs.accum, (k * 16) as i32);
            }
        }
    }
}
