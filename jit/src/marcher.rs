//! A fused sphere-tracing kernel: the whole march of 4 rays per f32x4 vector in one native loop, with the
//! SDF's ops inlined, so that no step leaves registers, allocates or hands rays between threads.
//!
//! Per lane, exactly the plain loop: from `t = t0`, up to `max_steps` times, `p = o + t·d`,
//! `dist = sdf(p)`; if `dist < eps` the ray hits (stop); else `t += dist`, and if `t > t1` it misses
//! (stop). Several groups of 4 rays march together (their dependency chains overlap) and leave the loop
//! when none of their lanes is still marching.

use std::time::Instant;

use cranelift_codegen::ir::condcodes::{FloatCC, IntCC};
use cranelift_codegen::ir::{types, AbiParam, BlockArg, InstBuilder, MemFlagsData};
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
    /// The smallest param slice the SDF reads.
    pub n_params: usize,
}

impl Marcher {
    /// Compiles the sphere tracer of `sdf`.
    pub fn compile(sdf: &Graph) -> Result<Marcher, JitError> {
        let start = Instant::now();
        let sdf = sdf.compact();
        sdf.validate().map_err(|e| JitError(format!("invalid IR: {e}")))?;
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
        let module = host_module(sdf.len())?;
        let mut ctx = module.make_context();
        let ptr = module.target_config().pointer_type();
        for ty in [ptr, ptr, ptr, types::I64, types::F32, types::I64] {
            ctx.func.signature.params.push(AbiParam::new(ty));
        }
        let mut fctx = FunctionBuilderContext::new();
        let mut b = FunctionBuilder::new(&mut ctx.func, &mut fctx);
        build(&mut b, &sdf);
        b.finalize(module.target_config());
        let (code, ptr) = CompiledCode::finish(module, ctx, "march", start, sdf.len(), false)?;
        // SAFETY: the function was generated with exactly this signature above.
        let func = unsafe { std::mem::transmute::<*const u8, MarchFn>(ptr) };
        Ok(Marcher {
            code,
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
        let full = n / RAYS_PER_ITERATION * RAYS_PER_ITERATION;
        if full > 0 {
            let ins: Vec<*const f32> = columns.iter().map(|c| c.as_ptr()).collect();
            let outs = [t.as_mut_ptr(), hit.as_mut_ptr()];
            // SAFETY: every column holds at least `full` rays, a multiple of RAYS_PER_ITERATION; the kernel
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
            // The last partial iteration marches padded copies (the padding repeats the last ray).
            let pad: Vec<[f32; RAYS_PER_ITERATION]> = columns
                .iter()
                .map(|c| std::array::from_fn(|k| c[full + k.min(rest - 1)]))
                .collect();
            let (mut pt, mut ph) = ([0.0f32; RAYS_PER_ITERATION], [0.0f32; RAYS_PER_ITERATION]);
            let ins: Vec<*const f32> = pad.iter().map(|c| c.as_ptr()).collect();
            let outs = [pt.as_mut_ptr(), ph.as_mut_ptr()];
            let len = RAYS_PER_ITERATION as i64;
            // SAFETY: each padded column holds RAYS_PER_ITERATION rays.
            unsafe { (self.func)(ins.as_ptr(), outs.as_ptr(), params.as_ptr(), len, eps, steps) };
            t[full..n].copy_from_slice(&pt[..rest]);
            hit[full..n].copy_from_slice(&ph[..rest]);
        }
    }
}

/// Rays marched together by one loop: independent groups of 4 whose dependency chains (each step waits for
/// the previous one's square roots) overlap in the CPU.
pub const RAYS_PER_ITERATION: usize = 4 * GROUPS;
const GROUPS: usize = 4;

/// Emits the marcher: `fn(rays[8], out[2], params, n, eps, max_steps)`, n a multiple of
/// [`RAYS_PER_ITERATION`].
fn build(b: &mut FunctionBuilder, sdf: &Graph) {
    let (ptr, f4, i4) = (types::I64, types::F32X4, types::I32X4);
    let entry = b.create_block();
    b.append_block_params_for_function_params(entry);
    b.switch_to_block(entry);
    b.seal_block(entry);
    let a = b.block_params(entry).to_vec();
    let (ray_arr, out_arr, params, n, eps, max_steps) = (a[0], a[1], a[2], a[3], a[4], a[5]);
    let ro = MemFlagsData::trusted().with_readonly();
    let cols: Vec<_> = (0..8).map(|k| b.ins().load(ptr, ro, ray_arr, k * 8)).collect();
    let outs: Vec<_> = (0..2).map(|k| b.ins().load(ptr, ro, out_arr, k * 8)).collect();
    let eps = b.ins().splat(f4, eps);
    let emitter = GraphEmitter::new(sdf);

    let group_head = b.create_block();
    let group_body = b.create_block();
    let step = b.create_block();
    let done = b.create_block();
    let exit = b.create_block();
    b.append_block_param(group_head, ptr);
    for _ in 0..GROUPS {
        for ty in [f4, i4, i4] {
            b.append_block_param(step, ty);
            b.append_block_param(done, ty);
        }
    }
    b.append_block_param(step, ptr);
    let zero = b.ins().iconst(ptr, 0);
    b.ins().jump(group_head, &[zero.into()]);

    b.switch_to_block(group_head);
    let i = b.block_params(group_head)[0];
    let more = b.ins().icmp(IntCC::SignedLessThan, i, n);
    b.ins().brif(more, group_body, &[], exit, &[]);

    // Load the rays of every group; all lanes start marching.
    b.switch_to_block(group_body);
    b.seal_block(group_body);
    let offset = b.ins().ishl_imm_s(i, 2);
    let flags = MemFlagsData::new().with_notrap();
    let addrs: Vec<_> = cols.iter().map(|&c| b.ins().iadd(c, offset)).collect();
    let rays: Vec<Vec<_>> = (0..GROUPS)
        .map(|g| {
            addrs
                .iter()
                .map(|&p| b.ins().load(f4, flags.with_readonly(), p, (16 * g) as i32))
                .collect()
        })
        .collect();
    let all = b.ins().iconst(types::I32, -1);
    let all = b.ins().splat(i4, all);
    let none = b.ins().iconst(types::I32, 0);
    let none = b.ins().splat(i4, none);
    let mut start: Vec<BlockArg> = Vec::new();
    for ray in &rays {
        start.extend([BlockArg::from(ray[6]), all.into(), none.into()]);
    }
    let k0 = b.ins().iconst(ptr, 0);
    start.push(k0.into());
    b.ins().jump(step, &start);

    // One step of every group.
    b.switch_to_block(step);
    let sp = b.block_params(step).to_vec();
    let k = sp[3 * GROUPS];
    let mut next: Vec<BlockArg> = Vec::new();
    let mut any = None;
    for (g, ray) in rays.iter().enumerate() {
        let (t, active, hit) = (sp[3 * g], sp[3 * g + 1], sp[3 * g + 2]);
        let p: Vec<_> = (0..3).map(|c| b.ins().fma(t, ray[3 + c], ray[c])).collect();
        let mut dist = None;
        emitter.emit(
            b,
            &mut |_, k| p[k as usize],
            &mut |_, _, v| dist = Some(v),
            params,
        );
        let dist = dist.expect("the distance is the field's output");
        let mut s = Simd { b };
        let is_hit = s.b.ins().fcmp(FloatCC::LessThan, dist, eps);
        let newly = s.b.ins().band(is_hit, active);
        let hit2 = s.b.ins().bor(hit, newly);
        let active2 = s.b.ins().band_not(active, is_hit);
        let advanced = s.b.ins().fadd(t, dist);
        let active2_f = s.float(active2);
        let t2 = s.select(active2_f, advanced, t);
        let past = s.b.ins().fcmp(FloatCC::GreaterThan, t2, ray[7]);
        let active3 = s.b.ins().band_not(active2, past);
        let lanes_on = b.ins().vany_true(active3);
        any = Some(match any {
            None => lanes_on,
            Some(a) => b.ins().bor(a, lanes_on),
        });
        next.extend([BlockArg::from(t2), active3.into(), hit2.into()]);
    }
    let finished: Vec<_> = next.clone();
    let k2 = b.ins().iadd_imm_s(k, 1);
    next.push(k2.into());
    let steps_left = b.ins().icmp(IntCC::SignedLessThan, k2, max_steps);
    let go_on = b.ins().band(any.expect("at least one group"), steps_left);
    b.ins().brif(go_on, step, &next, done, &finished);
    b.seal_block(step);

    // Store the final t and the hit flags of every group.
    b.switch_to_block(done);
    b.seal_block(done);
    let dp = b.block_params(done).to_vec();
    let out_addrs: Vec<_> = outs.iter().map(|&base| b.ins().iadd(base, offset)).collect();
    for g in 0..GROUPS {
        let (t_final, hit_final) = (dp[3 * g], dp[3 * g + 2]);
        let mut s = Simd { b };
        let hit_f = s.float(hit_final);
        let hit_one = s.mask_to_one(hit_f);
        for (value, &addr) in [t_final, hit_one].into_iter().zip(&out_addrs) {
            b.ins().store(flags, value, addr, (16 * g) as i32);
        }
    }
    let next_i = b.ins().iadd_imm_s(i, RAYS_PER_ITERATION as i64);
    b.ins().jump(group_head, &[next_i.into()]);
    b.seal_block(group_head);

    b.switch_to_block(exit);
    b.seal_block(exit);
    b.ins().return_(&[]);
}
