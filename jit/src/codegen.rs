//! Lowering of an IR [`Graph`] to one Cranelift function that evaluates it over a batch of points.
//!
//! The function's signature is
//! `fn(inputs: *const *const f32, outputs: *const *mut f32, params: *const f32, accum: *mut f32, n: i64)`:
//! `inputs` and `outputs` point to arrays of column pointers (structure of arrays), `accum` holds 4 lanes per
//! reduction. A main loop evaluates `unroll` independent groups of 4 points per iteration; a second loop
//! takes single groups, masking reduction lanes at or beyond `n`. The caller guarantees that every column
//! holds `n` rounded up to a multiple of 4 points (see [`crate::Kernel`]), so no access leaves the buffers.

use cranelift_codegen::ir::condcodes::{FloatCC, IntCC};
use cranelift_codegen::ir::{types, AbiParam, InstBuilder, MemFlagsData, Signature, Value};
use cranelift_frontend::FunctionBuilder;
use nerfjit_dsl::ir::{Graph, Op, V};

use crate::simd::Simd;

/// The column and buffer pointers of the kernel, loaded once in the entry block.
struct Buffers {
    inputs: Vec<Value>,
    outputs: Vec<Value>,
    params: Value,
    accum: Value,
}

/// The kernel's signature for a target with pointer type `ptr`.
pub fn signature(sig: &mut Signature, ptr: types::Type) {
    for _ in 0..4 {
        sig.params.push(AbiParam::new(ptr));
    }
    sig.params.push(AbiParam::new(types::I64));
}

/// Which multiplications are folded into the add or subtract that is their only user (emitted as FMA).
fn fused_muls(g: &Graph) -> Vec<bool> {
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
    // An add of two fusable products fuses only the second.
    for op in g.ops() {
        if let Op::Add(a, b) | Op::Sub(a, b) = *op {
            if fused[a.0 as usize] && fused[b.0 as usize] {
                fused[a.0 as usize] = false;
            }
        }
    }
    fused
}

/// Emits the body of the kernel function for `g` into `b` (whose signature is [`signature`]).
pub fn build(b: &mut FunctionBuilder, g: &Graph, unroll: usize) {
    let ptr = types::I64;
    let entry = b.create_block();
    b.append_block_params_for_function_params(entry);
    b.switch_to_block(entry);
    b.seal_block(entry);
    let args = b.block_params(entry).to_vec();
    let (in_arr, out_arr, params, accum, n) = (args[0], args[1], args[2], args[3], args[4]);
    let flags = MemFlagsData::trusted().with_readonly();
    let inputs = (0..g.n_inputs)
        .map(|k| b.ins().load(ptr, flags, in_arr, (k * 8) as i32))
        .collect();
    let outputs = (0..g.outputs.len())
        .map(|k| b.ins().load(ptr, flags, out_arr, (k * 8) as i32))
        .collect();
    let bufs = Buffers {
        inputs,
        outputs,
        params,
        accum,
    };
    let fused = fused_muls(g);
    let live = g.live();

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

    // Main loop: while i + 4·unroll <= n, evaluate `unroll` groups without masks.
    b.switch_to_block(main_head);
    let i = b.block_params(main_head)[0];
    let step = (4 * unroll) as i64;
    let next = b.ins().iadd_imm_s(i, step);
    let more = b.ins().icmp(IntCC::SignedLessThanOrEqual, next, n);
    b.ins().brif(more, main_body, &[], tail_head, &[i.into()]);
    b.switch_to_block(main_body);
    b.seal_block(main_body);
    let offset = b.ins().ishl_imm_s(i, 2);
    emit_groups(b, g, &bufs, &fused, &live, offset, unroll, None);
    b.ins().jump(main_head, &[next.into()]);
    b.seal_block(main_head);

    // Tail loop: single groups while i < n, reductions masked to the lanes below n.
    b.switch_to_block(tail_head);
    let i = b.block_params(tail_head)[0];
    let more = b.ins().icmp(IntCC::SignedLessThan, i, n);
    b.ins().brif(more, tail_body, &[], exit, &[]);
    b.switch_to_block(tail_body);
    b.seal_block(tail_body);
    let offset = b.ins().ishl_imm_s(i, 2);
    let remaining = b.ins().isub(n, i);
    let remaining = b.ins().ireduce(types::I32, remaining);
    let remaining = b.ins().splat(types::I32X4, remaining);
    let lanes = b.func.dfg.constants.insert(
        [0u32, 1, 2, 3]
            .iter()
            .flat_map(|x| x.to_le_bytes())
            .collect::<Vec<u8>>()
            .into(),
    );
    let lanes = b.ins().vconst(types::I32X4, lanes);
    let mask = b.ins().icmp(IntCC::SignedLessThan, lanes, remaining);
    emit_groups(b, g, &bufs, &fused, &live, offset, 1, Some(mask));
    let next = b.ins().iadd_imm_s(i, 4);
    b.ins().jump(tail_head, &[next.into()]);
    b.seal_block(tail_head);

    b.switch_to_block(exit);
    b.seal_block(exit);
    b.ins().return_(&[]);
}

/// Emits `groups` copies of the graph for the groups of 4 points at byte offsets `offset + 16·k`.
#[allow(clippy::too_many_arguments)]
fn emit_groups(
    b: &mut FunctionBuilder,
    g: &Graph,
    bufs: &Buffers,
    fused: &[bool],
    live: &[bool],
    offset: Value,
    groups: usize,
    lane_mask: Option<Value>,
) {
    let addr_of = |b: &mut FunctionBuilder, base: Value| b.ins().iadd(base, offset);
    let in_addrs: Vec<Value> = bufs.inputs.iter().map(|&p| addr_of(b, p)).collect();
    let out_addrs: Vec<Value> = bufs.outputs.iter().map(|&p| addr_of(b, p)).collect();
    let mut shared: Vec<Option<Value>> = vec![None; g.len()];
    for group in 0..groups {
        let disp = (16 * group) as i32;
        let mut vals: Vec<Option<Value>> = shared.clone();
        // Masks of comparisons, kept so that a select on a comparison needs no conversion.
        let mut masks: Vec<Option<Value>> = vec![None; g.len()];
        for (idx, op) in g.ops().iter().enumerate() {
            if !live[idx] || fused[idx] || vals[idx].is_some() {
                continue;
            }
            let mut s = Simd { b };
            let v = |x: V| vals[x.0 as usize].expect("argument emitted before use");
            let value = match *op {
                Op::Const(bits) => {
                    let c = s.f(f64::from_bits(bits) as f32);
                    shared[idx] = Some(c);
                    c
                }
                Op::Param(k) => {
                    let p = s.b.ins().load(
                        types::F32,
                        MemFlagsData::trusted().with_readonly(),
                        bufs.params,
                        (k * 4) as i32,
                    );
                    let p = s.b.ins().splat(types::F32X4, p);
                    shared[idx] = Some(p);
                    p
                }
                Op::Input(k) => {
                    let flags = MemFlagsData::new().with_notrap().with_readonly();
                    s.b.ins().load(types::F32X4, flags, in_addrs[k as usize], disp)
                }
                Op::Neg(a) => s.b.ins().fneg(v(a)),
                Op::Abs(a) => s.b.ins().fabs(v(a)),
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
                Op::Exp(a) => s.exp(v(a)),
                Op::Log(a) => s.log(v(a)),
                Op::Sin(a) => s.sin_cos(v(a), 0),
                Op::Cos(a) => s.sin_cos(v(a), 1),
                Op::Tan(a) => s.tan(v(a)),
                Op::Tanh(a) => s.tanh(v(a)),
                Op::Sigmoid(a) => s.sigmoid(v(a)),
                Op::Softplus(a) => s.softplus(v(a)),
                Op::Add(a, c) | Op::Sub(a, c) => {
                    let sub = matches!(op, Op::Sub(..));
                    let product = |x: V| match (fused[x.0 as usize], g.op(x)) {
                        (true, Op::Mul(p, q)) => Some((p, q)),
                        _ => None,
                    };
                    match (product(a), product(c)) {
                        // a + p·q  or  a − p·q
                        (_, Some((p, q))) => {
                            let pv = if sub { s.b.ins().fneg(v(p)) } else { v(p) };
                            s.fma(pv, v(q), v(a))
                        }
                        // p·q + c  or  p·q − c
                        (Some((p, q)), None) => {
                            let cv = if sub { s.b.ins().fneg(v(c)) } else { v(c) };
                            s.fma(v(p), v(q), cv)
                        }
                        (None, None) if sub => s.b.ins().fsub(v(a), v(c)),
                        (None, None) => s.b.ins().fadd(v(a), v(c)),
                    }
                }
                Op::Mul(a, c) => s.b.ins().fmul(v(a), v(c)),
                Op::Div(a, c) => s.b.ins().fdiv(v(a), v(c)),
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
                    s.select(m, v(a), v(d))
                }
            };
            vals[idx] = Some(value);
        }
        let get = |x: V| vals[x.0 as usize].expect("output emitted");
        for (k, &o) in g.outputs.iter().enumerate() {
            let flags = MemFlagsData::new().with_notrap();
            b.ins().store(flags, get(o), out_addrs[k], disp);
        }
        for (k, &r) in g.reductions.iter().enumerate() {
            if g.const_value(r) == Some(0.0) {
                continue;
            }
            let mut term = get(r);
            if let Some(mask) = lane_mask {
                let mut s = Simd { b };
                let mask = s.float(mask);
                term = s.b.ins().band(term, mask);
            }
            let flags = MemFlagsData::new().with_notrap();
            let acc = b.ins().load(types::F32X4, flags, bufs.accum, (k * 16) as i32);
            let sum = b.ins().fadd(acc, term);
            b.ins().store(flags, sum, bufs.accum, (k * 16) as i32);
        }
    }
}
