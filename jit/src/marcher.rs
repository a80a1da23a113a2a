//! A fused sphere-tracing kernel: the whole march of 4 rays per f32x4 vector in one native loop, with the
//! SDF's ops inlined, so that no step leaves registers, allocates or hands rays between threads.
//!
//! Per lane, exactly the plain loop: from `t = t0`, up to `max_steps` times, `p = o + t·d`,
//! `dist = sdf(p)`; if `dist < eps` the ray hits (stop); else `t += dist`, and if `t > t1` it misses
//! (stop). Several groups of 4 rays march together (their dependency chains overlap); a group whose 4
//! rays have all stopped stores them and takes the next 4 rays of the batch, so that the rays that take
//! many steps (near silhouettes) keep only their own group's lanes waiting.

use std::time::Instant;

use cranelift_codegen::ir::condcodes::{FloatCC, IntCC};
use cranelift_codegen::ir::{types, AbiParam, BlockArg, InstBuilder, MemFlagsData, Value};
use cranelift_frontend::{FunctionBuilder, FunctionBuilderContext};
use cranelift_module::Module;
use nerfjit_dsl::ir::Graph;
use nerfjit_dsl::march_rays::MarchRays;

use crate::codegen::GraphEmitter;
use crate::kernel::{host_module, CompiledCode, JitError};
use crate::simd::Simd;

type MarchFn = unsafe extern "C" fn(*const *const f32, *const *mut f32, *const f32, i64, f32, i64);

/// When a ray stops: a hit once the distance is below `eps`; a miss after `max_steps` steps (or past t1).
#[derive(Clone, Copy, Debug)]
pub struct Stop {
    /// Hit threshold.
    pub eps: f32,
    /// Most steps per ray.
    pub max_steps: u32,
}

/// A compiled fused sphere tracer for one SDF (a graph of 3 inputs and 1 output).
pub struct Marcher {
    code: CompiledCode,
    func: MarchFn,
    /// The groups of rays it marches together.
    groups: usize,
    /// The smallest param slice the SDF reads.
    pub n_params: usize,
}

impl Marcher {
    /// The groups of 4 rays it marches together (fewer for larger SDFs).
    pub fn groups(&self) -> usize {
        self.groups
    }

    /// Compiles the sphere tracer of `sdf`.
    pub fn compile(sdf: &Graph) -> Result<Marcher, JitError> {
        let start = Instant::now();
        let sdf = sdf.compact();
        sdf.validate().map_err(|e| JitError(format!("invalid IR: {e}")))?;
        crate::kernel::within_budget(&sdf)?;
        if sdf.needs_tiles() {
            return Err(JitError(
                "the fused sphere tracer takes elementwise SDFs; dense layers run tiled".into(),
            ));
        }
        if sdf.n_inputs != 3 || sdf.outputs.len() != 1 {
            return Err(JitError(format!(
                "a sphere tracer needs an SDF of 3 inputs and 1 output, not {} and {}",
                sdf.n_inputs,
                sdf.outputs.len()
            )));
        }
        let groups = groups(sdf.len());
        let module = host_module(groups * sdf.len())?;
        let mut ctx = module.make_context();
        let ptr = module.target_config().pointer_type();
        for ty in [ptr, ptr, ptr, types::I64, types::F32, types::I64] {
            ctx.func.signature.params.push(AbiParam::new(ty));
        }
        let mut fctx = FunctionBuilderContext::new();
        let mut b = FunctionBuilder::new(&mut ctx.func, &mut fctx);
        build(&mut b, &sdf, groups);
        b.finalize(module.target_config());
        let (code, ptr) = CompiledCode::finish(module, ctx, "march", start, sdf.len(), false)?;
        // SAFETY: the function was generated with exactly this signature above.
        let func = unsafe { std::mem::transmute::<*const u8, MarchFn>(ptr) };
        Ok(Marcher {
            code,
            groups,
            func,
            n_params: crate::kernel::params_read(&sdf),
        })
    }

    /// What the compilation did.
    pub fn stats(&self) -> &crate::CompileStats {
        &self.code.stats
    }

    /// Marches rays `0..n`: writes the final `t` of each ray and 1.0 where it hit, 0.0 where it missed.
    /// Panics if a slice is shorter than `n` or `params` shorter than the SDF reads.
    pub fn march(
        &self,
        n: usize,
        rays: &MarchRays,
        params: &[f32],
        stop: Stop,
        t: &mut [f32],
        hit: &mut [f32],
    ) {
        let Stop { eps, max_steps } = stop;
        let columns = [
            rays.origin[0],
            rays.origin[1],
            rays.origin[2],
            rays.direction[0],
            rays.direction[1],
            rays.direction[2],
            rays.t0,
            rays.t1,
        ];
        assert!(
            columns.iter().all(|c| c.len() >= n) && t.len() >= n && hit.len() >= n,
            "ray columns shorter than {n}"
        );
        assert!(
            params.len() >= self.n_params,
            "the SDF reads {} params",
            self.n_params
        );
        let steps = i64::from(max_steps.max(1));
        let full = n / RAYS_PER_GROUP * RAYS_PER_GROUP;
        if full > 0 {
            let ins: Vec<*const f32> = columns.iter().map(|c| c.as_ptr()).collect();
            let outs = [t.as_mut_ptr(), hit.as_mut_ptr()];
            // SAFETY: every column holds at least `full` rays, a multiple of RAYS_PER_GROUP; the kernel
            // touches exactly rays 0..full of each.
            unsafe {
                (self.func)(
                    ins.as_ptr(),
                    outs.as_ptr(),
                    params.as_ptr(),
                    full as i64,
                    eps,
                    steps,
                )
            };
        }
        let rest = n - full;
        if rest > 0 {
            // The last partial group marches padded copies (the padding repeats the last ray).
            let pad: Vec<[f32; RAYS_PER_GROUP]> = columns
                .iter()
                .map(|c| std::array::from_fn(|k| c[full + k.min(rest - 1)]))
                .collect();
            let (mut pt, mut ph) = ([0.0f32; RAYS_PER_GROUP], [0.0f32; RAYS_PER_GROUP]);
            let ins: Vec<*const f32> = pad.iter().map(|c| c.as_ptr()).collect();
            let outs = [pt.as_mut_ptr(), ph.as_mut_ptr()];
            let len = RAYS_PER_GROUP as i64;
            // SAFETY: each padded column holds RAYS_PER_GROUP rays.
            unsafe { (self.func)(ins.as_ptr(), outs.as_ptr(), params.as_ptr(), len, eps, steps) };
            t[full..n].copy_from_slice(&pt[..rest]);
            hit[full..n].copy_from_slice(&ph[..rest]);
        }
    }
}

/// Rays marched together: independent groups of 4 whose dependency chains (each step waits for the previous
/// one's square roots) overlap in the CPU. Each group takes the next 4 rays as soon as its own are all done,
/// so a slow ray holds back 3 others, not the whole batch.
pub const RAYS_PER_GROUP: usize = 4;

/// The groups marched together: 4 for SDFs of up to [`ONE_GROUP_NODES`] IR nodes, whose steps are short
/// dependency chains; one for larger ones, whose steps overlap by themselves and whose code (inlined once
/// per group) would otherwise take the compiler four times as long.
fn groups(sdf_nodes: usize) -> usize {
    if sdf_nodes > ONE_GROUP_NODES {
        1
    } else {
        4
    }
}

/// The size above which an SDF marches one group of rays at a time ([`groups`]).
const ONE_GROUP_NODES: usize = 2_000;

/// The loop state of one group of rays.
#[derive(Clone, Copy)]
struct Group {
    /// Distance along each ray.
    t: Value,
    /// Lanes still marching (all ones) or stopped.
    active: Value,
    /// Lanes that hit.
    hit: Value,
    /// Index of the group's first ray: always a ray of the batch, so that loads stay in bounds.
    base: Value,
    /// 1 while the group holds rays whose results are not yet stored, 0 once the batch is exhausted.
    live: Value,
    /// Steps the group's rays have taken.
    steps: Value,
}

impl Group {
    const TYPES: [types::Type; 6] = [
        types::F32X4,
        types::I32X4,
        types::I32X4,
        types::I64,
        types::I8,
        types::I64,
    ];

    fn args(&self) -> [BlockArg; 6] {
        [self.t, self.active, self.hit, self.base, self.live, self.steps].map(BlockArg::from)
    }

    /// The group of the 4 rays from `first`, starting at their `t0`; past the batch's `n` rays an exhausted
    /// group on the ray `fallback` (so that its loads stay in bounds).
    fn claim(b: &mut FunctionBuilder, batch: &Batch, first: Value, fallback: Value) -> Group {
        let live = b.ins().icmp(IntCC::SignedLessThan, first, batch.n);
        let base = b.ins().select(live, first, fallback);
        let t = batch.load(b, 6, base);
        let active = b.ins().select(live, batch.all, batch.none);
        let steps = b.ins().iconst(types::I64, 0);
        Group {
            t,
            active,
            hit: batch.none,
            base,
            live,
            steps,
        }
    }

    fn from_params(p: &[Value]) -> Group {
        Group {
            t: p[0],
            active: p[1],
            hit: p[2],
            base: p[3],
            live: p[4],
            steps: p[5],
        }
    }
}

/// What every step of the marcher reads: the function's arguments and constants made once in its entry.
struct Batch {
    /// The addresses of the 8 ray columns: origin, direction, t0, t1.
    cols: Vec<Value>,
    /// The addresses of the 2 output columns: final t, hit flag.
    outs: Vec<Value>,
    params: Value,
    /// The number of rays.
    n: Value,
    /// The hit threshold in every lane.
    eps: Value,
    max_steps: Value,
    /// Lane masks with every lane set and none.
    all: Value,
    none: Value,
    flags: MemFlagsData,
}

impl Batch {
    /// Loads the 4 f32 of ray column `column` at ray `index`.
    fn load(&self, b: &mut FunctionBuilder, column: usize, index: Value) -> Value {
        let offset = b.ins().ishl_imm_s(index, 2);
        let addr = b.ins().iadd(self.cols[column], offset);
        b.ins().load(types::F32X4, self.flags.with_readonly(), addr, 0)
    }
}

/// Emits the marcher of `groups` groups: `fn(rays[8], out[2], params, n, eps, max_steps)`, n a positive
/// multiple of [`RAYS_PER_GROUP`].
fn build(b: &mut FunctionBuilder, sdf: &Graph, groups: usize) {
    let (ptr, f4) = (types::I64, types::F32X4);
    let entry = b.create_block();
    b.append_block_params_for_function_params(entry);
    b.switch_to_block(entry);
    b.seal_block(entry);
    let a = b.block_params(entry).to_vec();
    let (ray_arr, out_arr, params, n, eps, max_steps) = (a[0], a[1], a[2], a[3], a[4], a[5]);
    let ro = MemFlagsData::trusted().with_readonly();
    let (all, none) = {
        let mut s = Simd { b };
        (s.i(-1), s.i(0))
    };
    let batch = Batch {
        cols: (0..8).map(|k| b.ins().load(ptr, ro, ray_arr, k * 8)).collect(),
        outs: (0..2).map(|k| b.ins().load(ptr, ro, out_arr, k * 8)).collect(),
        params,
        n,
        eps: b.ins().splat(f4, eps),
        max_steps,
        all,
        none,
        flags: MemFlagsData::new().with_notrap(),
    };
    let emitter = GraphEmitter::new(sdf);
    let zero = b.ins().iconst(ptr, 0);

    // Groups start on the first rays; a group beyond the batch starts exhausted (on ray 0, which exists).
    let mut start: Vec<BlockArg> = Vec::new();
    for g in 0..groups {
        let first = b.ins().iconst(ptr, (g * RAYS_PER_GROUP) as i64);
        let group = Group::claim(b, &batch, first, zero);
        start.extend(group.args());
    }
    start.push(b.ins().iconst(ptr, (groups * RAYS_PER_GROUP) as i64).into());
    let step = b.create_block();
    let exit = b.create_block();
    for _ in 0..groups {
        for ty in Group::TYPES {
            b.append_block_param(step, ty);
        }
    }
    b.append_block_param(step, ptr);
    b.ins().jump(step, &start);

    // One step of every group, then each group that finished stores its rays and takes the next ones.
    b.switch_to_block(step);
    let sp = b.block_params(step).to_vec();
    let mut next = sp[Group::TYPES.len() * groups];
    let current: Vec<Group> = sp
        .chunks(Group::TYPES.len())
        .take(groups)
        .map(Group::from_params)
        .collect();
    let stepped: Vec<Group> = current
        .iter()
        .map(|group| step_group(b, &emitter, &batch, *group))
        .collect();
    let mut any_live = None;
    let mut carried: Vec<BlockArg> = Vec::new();
    for group in stepped {
        let (group, after) = refill(b, &batch, group, next);
        next = after;
        carried.extend(group.args());
        any_live = Some(match any_live {
            None => group.live,
            Some(l) => b.ins().bor(l, group.live),
        });
    }
    carried.push(next.into());
    let go_on = any_live.expect("at least one group");
    b.ins().brif(go_on, step, &carried, exit, &[]);
    b.seal_block(step);

    b.switch_to_block(exit);
    b.seal_block(exit);
    b.ins().return_(&[]);
}

/// One sphere-tracing step of a group's active lanes: `p = o + t·d`, `dist = sdf(p)`; a lane stops on a
/// hit, past its `t1`, or after `max_steps` steps.
fn step_group(b: &mut FunctionBuilder, emitter: &GraphEmitter, batch: &Batch, group: Group) -> Group {
    let ray: Vec<Value> = [0, 1, 2, 3, 4, 5, 7]
        .iter()
        .map(|&c| batch.load(b, c, group.base))
        .collect();
    let t = group.t;
    let p: Vec<_> = (0..3).map(|c| b.ins().fma(t, ray[3 + c], ray[c])).collect();
    let mut dist = None;
    emitter.emit(
        b,
        &mut |_, k| p[k as usize],
        &mut |_, _, v| dist = Some(v),
        batch.params,
    );
    let dist = dist.expect("the distance is the field's output");
    let mut s = Simd { b };
    let is_hit = s.b.ins().fcmp(FloatCC::LessThan, dist, batch.eps);
    let newly = s.b.ins().band(is_hit, group.active);
    let hit = s.b.ins().bor(group.hit, newly);
    let active = s.b.ins().band_not(group.active, is_hit);
    let advanced = s.b.ins().fadd(t, dist);
    let active_f = s.float(active);
    let t = s.select(active_f, advanced, t);
    let past = s.b.ins().fcmp(FloatCC::GreaterThan, t, ray[6]);
    let active = s.b.ins().band_not(active, past);
    let steps = b.ins().iadd_imm_s(group.steps, 1);
    let steps_left = b.ins().icmp(IntCC::SignedLessThan, steps, batch.max_steps);
    let active = b.ins().select(steps_left, active, batch.none);
    Group {
        t,
        active,
        hit,
        steps,
        ..group
    }
}

/// If `group` holds rays and none is still marching: stores their final `t` and hit flags, and loads the
/// rays from `next` on (or marks the group exhausted past the batch's `n` rays). Returns the group's state
/// and the next unclaimed ray.
fn refill(b: &mut FunctionBuilder, batch: &Batch, group: Group, next: Value) -> (Group, Value) {
    let marching = b.ins().vany_true(group.active);
    let idle = b.ins().icmp_imm_u(IntCC::Equal, marching, 0);
    let done = b.ins().band(idle, group.live);
    let swap = b.create_block();
    let join = b.create_block();
    for ty in Group::TYPES {
        b.append_block_param(join, ty);
    }
    b.append_block_param(join, types::I64);
    let mut kept: Vec<BlockArg> = group.args().to_vec();
    kept.push(next.into());
    b.ins().brif(done, swap, &[], join, &kept);

    b.switch_to_block(swap);
    b.seal_block(swap);
    let offset = b.ins().ishl_imm_s(group.base, 2);
    let mut s = Simd { b };
    let hit_f = s.float(group.hit);
    let hit_one = s.mask_to_one(hit_f);
    for (value, &column) in [group.t, hit_one].into_iter().zip(&batch.outs) {
        let addr = b.ins().iadd(column, offset);
        b.ins().store(batch.flags, value, addr, 0);
    }
    let fresh = Group::claim(b, batch, next, group.base);
    let after = b.ins().iadd_imm_s(next, RAYS_PER_GROUP as i64);
    let mut swapped: Vec<BlockArg> = fresh.args().to_vec();
    swapped.push(after.into());
    b.ins().jump(join, &swapped);

    b.switch_to_block(join);
    b.seal_block(join);
    let p = b.block_params(join).to_vec();
    (Group::from_params(&p), p[Group::TYPES.len()])
}
