//! Compiled kernels: native code for one IR graph, and the safe entry points that run it on slices.

use std::time::Instant;

use cranelift_codegen::settings::{self, Configurable};
use cranelift_frontend::{FunctionBuilder, FunctionBuilderContext};
use cranelift_jit::{JITBuilder, JITModule};
use cranelift_module::{default_libcall_names, Linkage, Module};
use nerfjit_dsl::ir::{Graph, Op};

use crate::bf16::Precision;
use crate::codegen::{self, Columns};

mod dense_layers;
pub use dense_layers::HeldScatters;
use dense_layers::Tiled;

type KernelFn = unsafe extern "C" fn(*const *const f32, *const *mut f32, *const f32, *mut f32, i64);

/// How to compile a kernel.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Options {
    /// Keep the Cranelift IR text for `nerfjit ir`.
    pub keep_clif: bool,
    /// The arithmetic of dense layers' products: forward, backward and weight gradients.
    pub products: Precision,
    /// For a backward-pass graph whose first `split` inputs are the forward pass's and the rest its
    /// cotangents, and whose outputs read no cotangent: also run as a forward pass that keeps its values
    /// and a backward pass over them ([`Kernel::passes`]).
    pub split: Option<u32>,
}

/// What a compilation did, for reports.
#[derive(Clone, Debug, Default)]
pub struct CompileStats {
    /// Live IR nodes compiled.
    pub nodes: usize,
    /// Machine code bytes.
    pub code_bytes: usize,
    /// Wall time of code generation, in seconds.
    pub seconds: f64,
    /// The Cranelift IR, when [`Options::keep_clif`] asked for it.
    pub clif: Option<String>,
}

/// An error of code generation (a bug or an unsupported host, never a user error).
#[derive(Debug)]
pub struct JitError(pub String);

impl std::fmt::Display for JitError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "JIT compilation failed: {}", self.0)
    }
}

impl std::error::Error for JitError {}

/// Native code and the JIT module that owns its memory (freed on drop).
pub(crate) struct CompiledCode {
    module: Option<JITModule>,
    /// What the compilation did.
    pub stats: CompileStats,
}

// SAFETY: the module is only kept to own the code memory and is never used again after finalization; the
// generated code is immutable and reentrant (it touches only the buffers passed to each call).
unsafe impl Send for CompiledCode {}
// SAFETY: as above; nothing in it is mutated after construction.
unsafe impl Sync for CompiledCode {}

impl Drop for CompiledCode {
    fn drop(&mut self) {
        if let Some(module) = self.module.take() {
            // SAFETY: every function pointer into this memory is owned next to it and dies with it.
            unsafe { module.free_memory() };
        }
    }
}

impl CompiledCode {
    /// Compiles the function built in `ctx` and returns its code and entry point.
    pub(crate) fn finish(
        mut module: JITModule,
        mut ctx: cranelift_codegen::Context,
        name: &str,
        start: Instant,
        nodes: usize,
        keep_clif: bool,
    ) -> Result<(CompiledCode, *const u8), JitError> {
        let clif = keep_clif.then(|| ctx.func.display().to_string());
        let id = module
            .declare_function(name, Linkage::Export, &ctx.func.signature)
            .map_err(|e| JitError(e.to_string()))?;
        module
            .define_function(id, &mut ctx)
            .map_err(|e| JitError(format!("{e:?}")))?;
        let code = ctx
            .compiled_code()
            .map(|c| c.code_buffer().to_vec())
            .unwrap_or_default();
        if let Some(path) = std::env::var_os("NERFJIT_DUMP_CODE") {
            // A debugging aid: the raw machine code, for `objdump -D -b binary -m i386:x86-64`.
            std::fs::write(&path, &code).map_err(|e| JitError(format!("NERFJIT_DUMP_CODE: {e}")))?;
        }
        module.clear_context(&mut ctx);
        module
            .finalize_definitions()
            .map_err(|e| JitError(e.to_string()))?;
        let ptr = module.get_finalized_function(id);
        let stats = CompileStats {
            nodes,
            code_bytes: code.len(),
            seconds: start.elapsed().as_secs_f64(),
            clif,
        };
        Ok((
            CompiledCode {
                module: Some(module),
                stats,
            },
            ptr,
        ))
    }
}

/// 1 + the largest param index `graph` reads (0 if none).
pub(crate) fn params_read(graph: &Graph) -> usize {
    graph
        .ops()
        .iter()
        .filter_map(|op| match op {
            Op::Param(k) => Some(*k as usize + 1),
            Op::Dense(d) => Some(d.params_end()),
            Op::Grid(r) => Some(r.spec.table as usize + r.spec.n_params() as usize),
            _ => None,
        })
        .max()
        .unwrap_or(0)
}

/// Panics unless there are as many input and output columns as expected, each of at least `n` floats.
fn check_columns(n: usize, (inputs, n_in): (&[&[f32]], usize), (outputs, n_out): (&[&mut [f32]], usize)) {
    assert_eq!(inputs.len(), n_in, "kernel takes {n_in} inputs");
    assert_eq!(outputs.len(), n_out, "kernel writes {n_out} outputs");
    assert!(
        inputs.iter().all(|c| c.len() >= n),
        "an input column is shorter than {n}"
    );
    assert!(
        outputs.iter().all(|c| c.len() >= n),
        "an output column is shorter than {n}"
    );
}

/// The sum of a reduction's 4 accumulator lanes (added in f64).
pub(crate) fn lane_sum(lanes: &[f32]) -> f32 {
    lanes.iter().map(|&x| f64::from(x)).sum::<f64>() as f32
}

/// How a kernel runs.
enum Body {
    /// One native function over the whole batch.
    Plain { code: Box<CompiledCode>, func: KernelFn },
    /// Elementwise native functions and matrix products over tiles of points (graphs with dense nodes).
    Tiled(Box<Tiled>),
}

/// A native kernel for one graph: evaluates its outputs per point and sums its reductions over a batch.
///
/// Graphs with dense nodes run over tiles of points: their elementwise parts as native functions, their
/// dense nodes as AVX-512 matrix products (see the `tiled` module).
pub struct Kernel {
    body: Body,
    /// Per-point inputs.
    pub n_inputs: usize,
    /// Per-point outputs.
    pub n_outputs: usize,
    /// Reductions (summed over the batch).
    pub n_reductions: usize,
    /// The smallest param slice the kernel may read (1 + the largest param index used).
    pub n_params: usize,
}

/// Above this many IR nodes, a function's registers are allocated in a single pass. The backtracking
/// allocator's time grows faster than the function: on the 7,866-op model prospero.vm the value kernel
/// (7,600 nodes) takes it 0.4 s, the gradient kernel (22,600 nodes) 20 s and the single pass 0.4 s; single-pass
/// code runs about half as fast.
const SINGLE_PASS_NODES: usize = 12_000;

/// A JIT module for the host CPU, set up for a function of `nodes` IR nodes.
pub(crate) fn host_module(nodes: usize) -> Result<JITModule, JitError> {
    let err = |e: &dyn std::fmt::Display| JitError(e.to_string());
    let mut flags = settings::builder();
    flags.set("opt_level", "speed").map_err(|e| err(&e))?;
    if nodes > SINGLE_PASS_NODES {
        flags
            .set("regalloc_algorithm", "single_pass")
            .map_err(|e| err(&e))?;
    }
    flags
        .set("use_colocated_libcalls", "false")
        .map_err(|e| err(&e))?;
    flags.set("is_pic", "false").map_err(|e| err(&e))?;
    let isa = cranelift_native::builder()
        .map_err(|e| err(&e))?
        .finish(settings::Flags::new(flags))
        .map_err(|e| err(&e))?;
    Ok(JITModule::new(JITBuilder::with_isa(isa, default_libcall_names())))
}

/// The most IR nodes one kernel may have: Cranelift's time and memory grow faster than the code (a
/// million nodes take about 20 s and over 1 GiB), so a larger graph is refused rather than compiled.
pub const MAX_KERNEL_NODES: usize = 1 << 20;

/// Refuses a (compacted) graph beyond [`MAX_KERNEL_NODES`].
pub(crate) fn within_budget(graph: &Graph) -> Result<(), JitError> {
    if graph.len() <= MAX_KERNEL_NODES {
        return Ok(());
    }
    Err(JitError(format!(
        "the kernel has {} IR nodes, more than the {MAX_KERNEL_NODES} one kernel may have: \
         make the function smaller (each call of a function repeats its body)",
        graph.len()
    )))
}

/// `graph` compacted, checked against the IR's rules (a graph that breaks them would make the code read or
/// write outside its buffers) and against the compilation budget.
fn compacted_and_valid(graph: &Graph) -> Result<Graph, JitError> {
    let graph = graph.compact();
    graph
        .validate()
        .map_err(|e| JitError(format!("invalid IR: {e}")))?;
    within_budget(&graph)?;
    Ok(graph)
}

impl Kernel {
    /// Compiles `graph` to native code.
    pub fn compile(graph: &Graph, options: Options) -> Result<Kernel, JitError> {
        let start = Instant::now();
        let graph = compacted_and_valid(graph)?;
        if graph.needs_tiles() {
            return Ok(Kernel {
                body: Body::Tiled(Box::new(Tiled::compile(&graph, options)?)),
                n_inputs: graph.n_inputs as usize,
                n_outputs: graph.outputs.len(),
                n_reductions: graph.reductions.len(),
                n_params: params_read(&graph),
            });
        }
        Kernel::compile_plain(&graph, options, &Columns::Pointers, start)
    }

    /// Compiles `graph` (compacted, without dense nodes) to one native function that finds its columns
    /// where `columns` says; `start` is when the compilation began.
    fn compile_plain(
        graph: &Graph,
        options: Options,
        columns: &Columns,
        start: Instant,
    ) -> Result<Kernel, JitError> {
        let module = host_module(graph.len())?;
        let mut ctx = module.make_context();
        codegen::signature(&mut ctx.func.signature, module.target_config().pointer_type());
        let mut fctx = FunctionBuilderContext::new();
        let mut builder = FunctionBuilder::new(&mut ctx.func, &mut fctx);
        codegen::build(&mut builder, graph, columns);
        builder.finalize(module.target_config());
        let (code, ptr) = CompiledCode::finish(module, ctx, "kernel", start, graph.len(), options.keep_clif)?;
        // SAFETY: the function was generated with exactly this signature by `codegen::signature`.
        let func = unsafe { std::mem::transmute::<*const u8, KernelFn>(ptr) };
        Ok(Kernel {
            body: Body::Plain {
                code: Box::new(code),
                func,
            },
            n_inputs: graph.n_inputs as usize,
            n_outputs: graph.outputs.len(),
            n_reductions: graph.reductions.len(),
            n_params: params_read(graph),
        })
    }

    /// Compiles `graph` (without dense nodes) to a function of one arena whose columns lie at the byte
    /// offsets of `columns` (see [`Kernel::call_arena`]).
    pub(crate) fn compile_arena(
        graph: &Graph,
        options: Options,
        columns: &Columns,
    ) -> Result<Kernel, JitError> {
        let start = Instant::now();
        let graph = compacted_and_valid(graph)?;
        if graph.needs_tiles() {
            return Err(JitError("an arena kernel with dense nodes".into()));
        }
        Kernel::compile_plain(&graph, options, columns, start)
    }

    /// What the compilation did.
    pub fn stats(&self) -> &CompileStats {
        match &self.body {
            Body::Plain { code, .. } => &code.stats,
            Body::Tiled(t) => &t.stats,
        }
    }

    /// Runs the generated code of a kernel without dense nodes on `n` points.
    ///
    /// # Safety
    /// Every column pointer must address at least `n` rounded up to a multiple of 4 floats, `params` at
    /// least [`Kernel::n_params`] and `accum` 4 per reduction; there must be [`Kernel::n_inputs`] input and
    /// [`Kernel::n_outputs`] output pointers.
    pub(crate) unsafe fn call_raw(
        &self,
        ins: &[*const f32],
        outs: &[*mut f32],
        params: &[f32],
        accum: &mut [f32],
        n: usize,
    ) {
        let Body::Plain { func, .. } = &self.body else {
            panic!("call_raw on a tiled kernel");
        };
        debug_assert!(ins.len() == self.n_inputs && outs.len() == self.n_outputs);
        debug_assert!(params.len() >= self.n_params && accum.len() >= 4 * self.n_reductions);
        // SAFETY: as the caller guarantees.
        unsafe {
            func(
                ins.as_ptr(),
                outs.as_ptr(),
                params.as_ptr(),
                accum.as_mut_ptr(),
                n as i64,
            )
        }
    }

    /// Runs a kernel made by [`Kernel::compile_arena`] on `n` points of the arena at `arena`.
    ///
    /// # Safety
    /// Every column offset the kernel was compiled with, plus `n` rounded up to a multiple of 4 floats,
    /// must lie inside the arena; `params` must hold at least [`Kernel::n_params`] floats and `accum` 4
    /// per reduction.
    pub(crate) unsafe fn call_arena(&self, arena: *mut f32, params: &[f32], accum: &mut [f32], n: usize) {
        let Body::Plain { func, .. } = &self.body else {
            panic!("call_arena on a tiled kernel");
        };
        debug_assert!(params.len() >= self.n_params && accum.len() >= 4 * self.n_reductions);
        // SAFETY: as the caller guarantees; the kernel reads its columns at offsets from the first argument
        // and never reads the second.
        unsafe {
            func(
                arena as *const *const f32,
                std::ptr::null(),
                params.as_ptr(),
                accum.as_mut_ptr(),
                n as i64,
            )
        }
    }

    fn check(&self, n: usize, inputs: &[&[f32]], outputs: &[&mut [f32]], params: &[f32], reductions: &[f32]) {
        check_columns(n, (inputs, self.n_inputs), (outputs, self.n_outputs));
        assert!(
            params.len() >= self.n_params,
            "kernel reads {} params",
            self.n_params
        );
        assert_eq!(
            reductions.len(),
            self.n_reductions,
            "kernel sums {} reductions",
            self.n_reductions
        );
    }

    /// Evaluates points `0..n` on this thread: writes `outputs[o][0..n]` and adds the reductions over the
    /// points to `reductions`. Panics if a slice is shorter than the kernel needs.
    pub fn eval(
        &self,
        n: usize,
        inputs: &[&[f32]],
        outputs: &mut [&mut [f32]],
        params: &[f32],
        reductions: &mut [f32],
    ) {
        self.check(n, inputs, outputs, params, reductions);
        if let Body::Tiled(t) = &self.body {
            return t.eval(n, inputs, outputs, params, reductions);
        }
        let mut accum = vec![0.0f32; 4 * self.n_reductions];
        let full = n / 4 * 4;
        if full > 0 {
            let ins: Vec<*const f32> = inputs.iter().map(|c| c.as_ptr()).collect();
            let outs: Vec<*mut f32> = outputs.iter_mut().map(|c| c.as_mut_ptr()).collect();
            // SAFETY: every column holds at least `full` points (checked above), a multiple of 4, and the
            // kernel accesses exactly points 0..full of each column and 4 lanes per reduction of `accum`.
            unsafe { self.call_raw(&ins, &outs, params, &mut accum, full) };
        }
        let rest = n - full;
        if rest > 0 {
            // The last partial group runs on padded copies so that the kernel never reads past a column.
            let pad_in: Vec<[f32; 4]> = inputs
                .iter()
                .map(|c| {
                    let mut a = [0.0; 4];
                    a[..rest].copy_from_slice(&c[full..n]);
                    a
                })
                .collect();
            let mut pad_out = vec![[0.0f32; 4]; self.n_outputs];
            let ins: Vec<*const f32> = pad_in.iter().map(|c| c.as_ptr()).collect();
            let outs: Vec<*mut f32> = pad_out.iter_mut().map(|c| c.as_mut_ptr()).collect();
            // SAFETY: each padded column holds 4 points; the kernel masks the reduction lanes ≥ rest.
            unsafe { self.call_raw(&ins, &outs, params, &mut accum, rest) };
            for (col, pad) in outputs.iter_mut().zip(&pad_out) {
                col[full..n].copy_from_slice(&pad[..rest]);
            }
        }
        for (r, lanes) in reductions.iter_mut().zip(accum.chunks_exact(4)) {
            *r += lane_sum(lanes);
        }
    }

    /// The forward and the backward pass of this kernel run separately (on this thread), the backward
    /// pass going on from the values the forward pass kept instead of recomputing them: for kernels with
    /// dense nodes compiled with [`Options::split`]; `None` for others.
    pub fn passes<'a>(&'a self, params: &'a [f32]) -> Option<Passes<'a>> {
        match &self.body {
            Body::Tiled(t) if t.is_split() => {
                assert!(
                    params.len() >= self.n_params,
                    "kernel reads {} params",
                    self.n_params
                );
                Some(Passes {
                    kernel: self,
                    passes: dense_layers::Passes::new(t, params),
                })
            }
            _ => None,
        }
    }

    /// Like [`Kernel::eval`], with the points split over `threads` threads.
    pub fn eval_parallel(
        &self,
        n: usize,
        inputs: &[&[f32]],
        outputs: &mut [&mut [f32]],
        params: &[f32],
        reductions: &mut [f32],
        threads: usize,
    ) {
        self.check(n, inputs, outputs, params, reductions);
        // Below a few thousand points per thread, threads cost more than they save; a tiled kernel does
        // ~100× more work per point, so a few tiles per thread are worth it.
        let per_thread = match self.body {
            Body::Plain { .. } => 4096,
            Body::Tiled(_) => 2 * crate::gemm::TILE,
        };
        let threads = threads.clamp(1, n.div_ceil(per_thread).max(1));
        if threads == 1 {
            return self.eval(n, inputs, outputs, params, reductions);
        }
        let chunk = n.div_ceil(threads).div_ceil(4) * 4;
        // A tiled kernel's matrices are made once for all threads.
        let matrices = match &self.body {
            Body::Tiled(t) => Some(std::sync::Arc::new(t.prepare(params))),
            Body::Plain { .. } => None,
        };
        let mut out_parts: Vec<Vec<&mut [f32]>> = (0..threads).map(|_| Vec::new()).collect();
        for col in outputs.iter_mut() {
            for (t, piece) in col[..n].chunks_mut(chunk).enumerate() {
                out_parts[t].push(piece);
            }
        }
        let sums: Vec<Vec<f32>> = std::thread::scope(|scope| {
            let handles: Vec<_> = out_parts
                .into_iter()
                .enumerate()
                .filter(|(_, outs)| !outs.is_empty() || self.n_outputs == 0)
                .map(|(t, mut outs)| {
                    let start = (t * chunk).min(n);
                    let end = ((t + 1) * chunk).min(n);
                    let ins: Vec<&[f32]> = inputs.iter().map(|c| &c[start..end]).collect();
                    let matrices = matrices.clone();
                    scope.spawn(move || {
                        let mut part = vec![0.0f32; self.n_reductions];
                        match (&self.body, matrices) {
                            (Body::Tiled(t), Some(m)) => {
                                t.eval_with(m, end - start, (&ins, &mut outs), params, &mut part)
                            }
                            _ => self.eval(end - start, &ins, &mut outs, params, &mut part),
                        }
                        part
                    })
                })
                .collect();
            handles
                .into_iter()
                .map(|h| h.join().expect("kernel thread panicked"))
                .collect()
        });
        for part in sums {
            for (r, x) in reductions.iter_mut().zip(part) {
                *r += x;
            }
        }
    }
}

/// A kernel's forward and backward passes over the same points ([`Kernel::passes`]): [`Passes::forward`]
/// over batches of points, then [`Passes::backward`] over all of them in order with the cotangents of the
/// outputs, as often as wanted; [`Passes::finish`] adds what the backward passes summed.
pub struct Passes<'a> {
    kernel: &'a Kernel,
    passes: dense_layers::Passes<'a>,
}

impl<'a> Passes<'a> {
    /// Evaluates the outputs at points `0..n` of the forward pass's `inputs` and keeps what the backward
    /// pass needs after what the forward passes since the last backward pass kept (a tile arena per 128
    /// points or fewer of a call, [`Passes::bytes_per_point`] a point: keep a few hundred points at a
    /// time so that they stay in the cache). Panics if a slice is shorter than the kernel needs.
    pub fn forward(&mut self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        let (n_in, n_out) = (self.passes.forward_inputs(), self.kernel.n_outputs);
        check_columns(n, (inputs, n_in), (outputs, n_out));
        self.passes.forward(n, inputs, outputs);
    }

    /// The backward pass at the points of the [`Passes::forward`] calls since the last backward pass (`n`
    /// of them in all, in the order they were evaluated) with the cotangents: adds their reductions to
    /// `reductions`, some now, the rest at [`Passes::finish`]. Panics if those forward passes were not
    /// over `n` points or a slice is shorter than the kernel needs.
    pub fn backward(&mut self, n: usize, cotangents: &[&[f32]], reductions: &mut [f32]) {
        let k = self.kernel;
        let expected = k.n_inputs - self.passes.forward_inputs();
        assert_eq!(
            cotangents.len(),
            expected,
            "the backward pass takes {expected} cotangents"
        );
        assert!(
            cotangents.iter().all(|c| c.len() >= n),
            "a cotangent column is shorter than {n}"
        );
        assert_eq!(
            reductions.len(),
            k.n_reductions,
            "kernel sums {} reductions",
            k.n_reductions
        );
        self.passes.backward(n, cotangents, reductions);
    }

    /// The memory the forward passes keep per point, in bytes.
    pub fn bytes_per_point(&self) -> usize {
        self.passes.bytes_per_point()
    }

    /// From now on, the backward passes hold their grid scatters back from the reductions, to be taken
    /// by [`Passes::take_scatters`] and added part by part (a level of a grid each, on any number of
    /// threads) where the kernel allows it: its scatters' levels and its other reductions are disjoint.
    /// Returns whether they are held.
    pub fn hold_scatters(&mut self) -> bool {
        self.passes.hold_scatters()
    }

    /// The grid scatters held since [`Passes::hold_scatters`] (which then holds them no more).
    pub fn take_scatters(&mut self) -> Option<HeldScatters<'a>> {
        self.passes.take_scatters()
    }

    /// Adds the sums the backward passes keep until the end to `reductions`.
    pub fn finish(&mut self, reductions: &mut [f32]) {
        assert_eq!(
            reductions.len(),
            self.kernel.n_reductions,
            "kernel sums {} reductions",
            self.kernel.n_reductions
        );
        self.passes.finish(reductions);
    }
}
