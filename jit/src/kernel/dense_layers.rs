//! Kernels of graphs with dense nodes: elementwise JIT segments and matrix products, run over tiles of
//! points.
//!
//! Every node gets a level: the number of dense products on the longest path from the inputs to it. The
//! scalar nodes of one level form a segment, compiled to an ordinary JIT kernel (so the elementwise work
//! between two products, bias + activation + whatever the script does, stays fused); the dense nodes of
//! level L run, as [`gemm::matmul`], after segment L − 1 and before segment L. Values that cross a
//! boundary live in slots: one column of [`TILE`] floats each, in an arena reused for every tile; the
//! slots' columns are assigned before the segments are compiled, so that a segment addresses them as
//! constant offsets from the arena. The
//! graph's outer products (the gradients of the matrices) run as [`gemm::outer`] after the segment that
//! writes the last of their operands, summed over the whole batch. Constants and params are recomputed in
//! every segment that reads them.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

use nerfjit_dsl::ir::{Graph, Op, V};

use crate::bf16::{self, Bf16Matrix, Bf16Scratch, Precision};
use crate::codegen::Columns;
use crate::gemm::{self, COLUMN, TILE};
use crate::grid_encoding::{GradWindow, GridPlan};
use crate::kernel::{lane_sum, CompileStats, JitError, Kernel, Options};
use crate::profile::{Laps, Phase};

/// One elementwise segment: a JIT kernel reading and writing slots.
struct Segment {
    /// Compiled to find its columns at constant offsets from the tile's arena.
    kernel: Kernel,
    /// The graph reduction each of the kernel's reductions adds to.
    reductions: Vec<usize>,
}

/// A stage's elementwise code before it is compiled: its graph, the slots it reads and writes (its
/// inputs' and outputs', in order) and the graph reduction each of its reductions adds to.
struct SegmentSpec {
    graph: Graph,
    reads: Vec<usize>,
    writes: Vec<usize>,
    reductions: Vec<usize>,
}

/// One dense product: `out = A·x` with A the plan's matrix `matrix`.
struct Product {
    matrix: usize,
    x: Vec<usize>,
    out: Vec<usize>,
}

/// A matrix the products multiply by: the param matrix W (`rows × cols` from param `w` on) or Wᵀ.
#[derive(Clone, Copy, PartialEq)]
struct MatrixOf {
    w: usize,
    rows: usize,
    cols: usize,
    transposed: bool,
}

/// One outer product added to the reductions from `target` on.
struct OuterProduct {
    /// It runs after this stage's segment, the last to write its operands.
    stage: usize,
    target: usize,
    left: Vec<usize>,
    right: Vec<usize>,
}

/// One grid read: its outputs from the point's slots.
struct GridStep {
    plan: GridPlan,
    p: [usize; 3],
    out: Vec<usize>,
}

/// One grid scatter into the table's gradient (in the reductions).
struct ScatterStep {
    plan: GridPlan,
    p: [usize; 3],
    cotangent: Vec<usize>,
}

/// A value filled into a slot once per evaluation.
#[derive(Clone, Copy)]
enum Fill {
    Const(f32),
    Param(usize),
}

/// The executable plan of a graph with dense nodes.
pub(crate) struct Tiled {
    /// Segment `s` runs after the products of `products[s]`.
    segments: Vec<Option<Segment>>,
    products: Vec<Vec<Product>>,
    /// The matrices the products multiply by, each once (a second-order kernel multiplies by most twice).
    matrices: Vec<MatrixOf>,
    /// The grid reads of each stage, run with its products.
    grids: Vec<Vec<GridStep>>,
    outer: Vec<OuterProduct>,
    scatters: Vec<ScatterStep>,
    /// The params of each level of the scatters' grids, sorted (levels of one grid scattered twice
    /// once), if the scatters can be held back and added level by level ([`Passes::hold_scatters`]):
    /// their levels' params are disjoint and nothing else adds to them.
    scatter_parts: Option<Vec<std::ops::Range<usize>>>,
    fills: Vec<(usize, Fill)>,
    input_slots: Vec<Option<usize>>,
    output_slots: Vec<usize>,
    /// Where products and grid reads write the outputs that nothing reads.
    spare: usize,
    n_slots: usize,
    n_reductions: usize,
    /// The arithmetic of the products.
    precision: Precision,
    /// The inputs of the forward pass: all of them, or with [`Options::split`] those before the split (the
    /// rest, the cotangents, are loaded for the backward pass).
    forward_inputs: usize,
    /// Stages `0..forward_stages` are the forward pass; the outputs are read after them.
    forward_stages: usize,
    /// The compilation of all segments.
    pub stats: CompileStats,
}

/// Whether the node is recomputed wherever it is read instead of living in a slot.
fn is_rematerialized(op: &Op) -> bool {
    matches!(op, Op::Const(_) | Op::Param(_))
}

/// Whether the node is computed by a segment.
fn is_elementwise(op: &Op) -> bool {
    !matches!(
        op,
        Op::Const(_) | Op::Param(_) | Op::Input(_) | Op::Dense(_) | Op::Grid(_) | Op::Pick(..)
    )
}

/// Every node's stage, and the number of stages of the forward pass. A node's level is the number of
/// dense products and grid reads on the longest path from the inputs to it; with a split, the nodes that
/// depend on the inputs from `split` on (the backward pass's cotangents) come after every node that does
/// not: their stage is their level plus the forward pass's stages. Without a split every node is the
/// forward pass's and its stage is its level.
fn stages(g: &Graph, split: Option<u32>) -> (Vec<usize>, usize) {
    let mut stage = vec![0usize; g.len()];
    let mut backward = vec![false; g.len()];
    for (i, op) in g.ops().iter().enumerate() {
        let args = g.args(op);
        let highest = args.iter().map(|a| stage[a.0 as usize]).max().unwrap_or(0);
        stage[i] = match op {
            Op::Dense(_) | Op::Grid(_) => highest + 1,
            _ => highest,
        };
        backward[i] = match op {
            Op::Input(k) => split.is_some_and(|s| *k >= s),
            _ => args.iter().any(|a| backward[a.0 as usize]),
        };
    }
    let forward_stages = (0..g.len())
        .filter(|&i| !backward[i])
        .map(|i| stage[i] + 1)
        .max()
        .unwrap_or(0);
    for (s, _) in stage.iter_mut().zip(&backward).filter(|(_, &b)| b) {
        *s += forward_stages;
    }
    (stage, forward_stages)
}

struct Slots {
    of: Vec<Option<usize>>,
    count: usize,
}

impl Slots {
    fn get(&mut self, v: V) -> usize {
        let entry = &mut self.of[v.0 as usize];
        *entry.get_or_insert_with(|| {
            self.count += 1;
            self.count - 1
        })
    }
}

impl Tiled {
    /// Plans and compiles `g` (compacted, with dense nodes).
    pub(crate) fn compile(g: &Graph, options: Options) -> Result<Tiled, JitError> {
        let start = Instant::now();
        let (stage, forward_stages) = stages(g, options.split);
        let n_stages = stage.iter().max().map_or(1, |m| m + 1);
        if options.split.is_some() && g.outputs.iter().any(|o| stage[o.0 as usize] >= forward_stages) {
            return Err(JitError("an output of a split kernel reads a cotangent".into()));
        }
        let ops = g.ops();
        let mut slots = Slots {
            of: vec![None; g.len()],
            count: 0,
        };
        // Values read across a boundary: by a later segment, a product, an outer product, or as an output.
        for (i, op) in ops.iter().enumerate() {
            if matches!(op, Op::Input(_) | Op::Pick(..)) {
                slots.get(V(i as u32));
            }
            match op {
                Op::Dense(d) => {
                    for &a in g.list(d.x) {
                        slots.get(a);
                    }
                }
                Op::Grid(r) => {
                    for a in r.p {
                        slots.get(a);
                    }
                }
                _ if is_elementwise(op) => {
                    for a in op.args() {
                        let arg = &ops[a.0 as usize];
                        if is_elementwise(arg) && stage[a.0 as usize] != stage[i] {
                            // A mask is made again from the value it compares (see `compared_value`).
                            let kept = compared_value(ops, a).unwrap_or(a);
                            if !is_rematerialized(&ops[kept.0 as usize]) {
                                slots.get(kept);
                            }
                        }
                    }
                }
                _ => {}
            }
        }
        for o in &g.outer {
            for &v in o.left.iter().chain(&o.right) {
                slots.get(v);
            }
        }
        for sc in &g.scatter {
            for &v in sc.read.p.iter().chain(&sc.cotangent) {
                slots.get(v);
            }
        }
        let output_slots: Vec<usize> = g.outputs.iter().map(|&v| slots.get(v)).collect();
        let spare = slots.count;
        slots.count += 1;

        let mut products: Vec<Vec<Product>> = (0..n_stages).map(|_| Vec::new()).collect();
        let mut picks: HashMap<(u32, u32), usize> = HashMap::new();
        for (i, op) in ops.iter().enumerate() {
            if let Op::Pick(d, k) = op {
                picks.insert((d.0, *k), slots.of[i].expect("picks have slots"));
            }
        }
        let mut matrices: Vec<MatrixOf> = Vec::new();
        for (i, op) in ops.iter().enumerate() {
            if let Op::Dense(d) = op {
                let of = MatrixOf {
                    w: d.w as usize,
                    rows: d.rows as usize,
                    cols: d.cols as usize,
                    transposed: d.transposed,
                };
                let matrix = matrices.iter().position(|&m| m == of).unwrap_or_else(|| {
                    matrices.push(of);
                    matrices.len() - 1
                });
                products[stage[i]].push(Product {
                    matrix,
                    x: g.list(d.x).iter().map(|&a| slots.get(a)).collect(),
                    out: (0..d.n_out() as u32)
                        .map(|k| picks.get(&(i as u32, k)).copied().unwrap_or(spare))
                        .collect(),
                });
            }
        }

        let mut grids: Vec<Vec<GridStep>> = (0..n_stages).map(|_| Vec::new()).collect();
        for (i, op) in ops.iter().enumerate() {
            if let Op::Grid(r) = op {
                grids[stage[i]].push(GridStep {
                    plan: GridPlan::new(r),
                    p: r.p.map(|a| slots.get(a)),
                    out: (0..r.spec.n_outputs() as u32)
                        .map(|k| picks.get(&(i as u32, k)).copied().unwrap_or(spare))
                        .collect(),
                });
            }
        }
        let scatters: Vec<ScatterStep> = g
            .scatter
            .iter()
            .map(|sc| ScatterStep {
                plan: GridPlan::new(&sc.read),
                p: sc.read.p.map(|v| slots.get(v)),
                cotangent: sc.cotangent.iter().map(|&v| slots.get(v)).collect(),
            })
            .collect();
        if scatters
            .iter()
            .any(|sc| sc.plan.params_end() > g.reductions.len())
        {
            return Err(JitError("a scatter writes past the reductions".into()));
        }

        let mut specs: Vec<Option<SegmentSpec>> = (0..n_stages)
            .map(|s| segment_spec(g, &stage, &mut slots, s))
            .collect();

        let mut fills = Vec::new();
        for (i, op) in ops.iter().enumerate() {
            if let (Some(slot), true) = (slots.of[i], is_rematerialized(op)) {
                fills.push((
                    slot,
                    match *op {
                        Op::Const(bits) => Fill::Const(f64::from_bits(bits) as f32),
                        Op::Param(k) => Fill::Param(k as usize),
                        _ => unreachable!(),
                    },
                ));
            }
        }
        let input_slots = (0..g.n_inputs)
            .map(|k| {
                ops.iter()
                    .position(|op| *op == Op::Input(k))
                    .and_then(|i| slots.of[i])
            })
            .collect();
        let outer = g
            .outer
            .iter()
            .map(|o| OuterProduct {
                stage: o
                    .left
                    .iter()
                    .chain(&o.right)
                    .map(|v| stage[v.0 as usize])
                    .max()
                    .unwrap_or(0),
                target: o.target as usize,
                left: o.left.iter().map(|&v| slots.get(v)).collect(),
                right: o.right.iter().map(|&v| slots.get(v)).collect(),
            })
            .collect::<Vec<_>>();
        for o in &outer {
            if o.target + o.left.len() * o.right.len() > g.reductions.len() {
                return Err(JitError("an outer product writes past the reductions".into()));
            }
        }
        let mut plan = Tiled {
            segments: Vec::with_capacity(n_stages),
            products,
            matrices,
            grids,
            outer,
            scatters,
            fills,
            input_slots,
            output_slots,
            spare,
            scatter_parts: None,
            n_slots: slots.count,
            n_reductions: g.reductions.len(),
            precision: options.products,
            forward_inputs: options.split.map_or(g.n_inputs, |k| k.min(g.n_inputs)) as usize,
            forward_stages,
            stats: CompileStats::default(),
        };
        plan.share_slots(&mut specs);
        // The columns' places are now final: each segment addresses them as constant offsets from the arena.
        let offset = |slots: &[usize]| -> Result<Vec<i32>, JitError> {
            slots
                .iter()
                .map(|&s| i32::try_from(s * COLUMN * 4).map_err(|_| JitError("an arena of over 2 GB".into())))
                .collect()
        };
        for spec in specs {
            let segment = match spec {
                Some(spec) => {
                    let columns = Columns::Offsets {
                        reads: offset(&spec.reads)?,
                        writes: offset(&spec.writes)?,
                    };
                    let kernel = Kernel::compile_arena(&spec.graph, options, &columns)?;
                    let st = kernel.stats();
                    plan.stats.nodes += st.nodes;
                    plan.stats.code_bytes += st.code_bytes;
                    if let Some(clif) = &st.clif {
                        plan.stats.clif.get_or_insert_with(String::new).push_str(clif);
                    }
                    Some(Segment {
                        kernel,
                        reductions: spec.reductions,
                    })
                }
                None => None,
            };
            plan.segments.push(segment);
        }
        plan.scatter_parts = plan.find_scatter_parts();
        plan.stats.seconds = start.elapsed().as_secs_f64();
        Ok(plan)
    }

    /// The params of each level of the scatters' grids, sorted, if they are disjoint (a level scattered
    /// by several scatters counted once) and no segment's reduction or outer product adds to them.
    fn find_scatter_parts(&self) -> Option<Vec<std::ops::Range<usize>>> {
        let mut parts: Vec<std::ops::Range<usize>> = self
            .scatters
            .iter()
            .flat_map(|sc| (0..sc.plan.levels()).map(|l| sc.plan.level_params(l)))
            .collect();
        parts.sort_by_key(|r| (r.start, r.end));
        parts.dedup();
        if parts.is_empty() || parts.windows(2).any(|w| w[0].end > w[1].start) {
            return None;
        }
        let inside = |r: usize| parts.iter().any(|p| p.contains(&r));
        let reductions = self
            .segments
            .iter()
            .flatten()
            .flat_map(|seg| seg.reductions.iter().copied());
        let outer = self
            .outer
            .iter()
            .flat_map(|o| o.target..o.target + o.left.len() * o.right.len());
        if reductions.chain(outer).any(inside) {
            return None;
        }
        Some(parts)
    }

    /// Lets values whose lifetimes do not overlap share a column of the arena, so that a tile's arena
    /// holds what is live at once rather than every value that crosses a boundary (a network's forward
    /// pass then fits in the L2 cache). Time runs over the stages: the forward pass's inputs are loaded at
    /// 0, stage s runs its products at 2s + 1 and its segment and then its outer products at 2s + 2, the
    /// outputs are read and the cotangents loaded after the forward pass (at 2F for F forward stages),
    /// grid scatters read at the end. A column is reused only by a value written strictly after the
    /// column's last read.
    fn share_slots(&mut self, segments: &mut [Option<SegmentSpec>]) {
        const UNSET: usize = usize::MAX;
        let end = 2 * segments.len() + 1;
        let n = self.n_slots;
        let (mut first, mut last) = (vec![UNSET; n], vec![0usize; n]);
        let mut touch = |slot: usize, t: usize| {
            first[slot] = first[slot].min(t);
            last[slot] = last[slot].max(t);
        };
        for &(slot, _) in &self.fills {
            touch(slot, 0);
            touch(slot, end);
        }
        let forward_end = 2 * self.forward_stages;
        for (k, slot) in self.input_slots.iter().enumerate() {
            if let Some(slot) = *slot {
                touch(slot, if k < self.forward_inputs { 0 } else { forward_end });
            }
        }
        for (s, products) in self.products.iter().enumerate() {
            for p in products {
                for &slot in p.x.iter().chain(&p.out) {
                    touch(slot, 2 * s + 1);
                }
            }
        }
        for (s, grids) in self.grids.iter().enumerate() {
            for step in grids {
                for &slot in step.p.iter().chain(&step.out) {
                    touch(slot, 2 * s + 1);
                }
            }
        }
        for (s, segment) in segments.iter().enumerate() {
            if let Some(seg) = segment {
                for &slot in seg.reads.iter().chain(&seg.writes) {
                    touch(slot, 2 * s + 2);
                }
            }
        }
        for sc in &self.scatters {
            for &slot in sc.p.iter().chain(&sc.cotangent) {
                touch(slot, end);
            }
        }
        for o in &self.outer {
            for &slot in o.left.iter().chain(&o.right) {
                touch(slot, 2 * o.stage + 2);
            }
        }
        for &slot in &self.output_slots {
            touch(slot, forward_end);
        }
        // The spare column is written at every stage: it shares with nothing.
        touch(self.spare, 0);
        touch(self.spare, end);
        // Interval colouring: in order of first use, take a column freed strictly before.
        let mut order: Vec<usize> = (0..n).filter(|&s| first[s] != UNSET).collect();
        order.sort_by_key(|&s| first[s]);
        let mut busy: std::collections::BinaryHeap<std::cmp::Reverse<(usize, usize)>> = Default::default();
        let mut free: Vec<usize> = Vec::new();
        let mut column = vec![0usize; n];
        let mut columns = 0;
        for s in order {
            while let Some(&std::cmp::Reverse((until, c))) = busy.peek() {
                if until >= first[s] {
                    break;
                }
                busy.pop();
                free.push(c);
            }
            let c = free.pop().unwrap_or_else(|| {
                columns += 1;
                columns - 1
            });
            column[s] = c;
            busy.push(std::cmp::Reverse((last[s], c)));
        }
        let map = |v: &mut Vec<usize>| v.iter_mut().for_each(|s| *s = column[*s]);
        for products in &mut self.products {
            for p in products {
                map(&mut p.x);
                map(&mut p.out);
            }
        }
        for seg in segments.iter_mut().flatten() {
            map(&mut seg.reads);
            map(&mut seg.writes);
        }
        for step in self.grids.iter_mut().flatten() {
            step.p = step.p.map(|s| column[s]);
            map(&mut step.out);
        }
        for sc in &mut self.scatters {
            sc.p = sc.p.map(|s| column[s]);
            map(&mut sc.cotangent);
        }
        for o in &mut self.outer {
            map(&mut o.left);
            map(&mut o.right);
        }
        map(&mut self.output_slots);
        self.spare = column[self.spare];
        for (slot, _) in &mut self.fills {
            *slot = column[*slot];
        }
        for slot in self.input_slots.iter_mut().flatten() {
            *slot = column[*slot];
        }
        self.n_slots = columns;
    }

    /// Evaluates points `0..n` on this thread (see [`Kernel::eval`]; sizes were checked by the caller):
    /// the forward and the backward pass of each tile in turn, in one arena.
    pub(crate) fn eval(
        &self,
        n: usize,
        inputs: &[&[f32]],
        outputs: &mut [&mut [f32]],
        params: &[f32],
        reductions: &mut [f32],
    ) {
        self.eval_with(
            Arc::new(self.prepare(params)),
            n,
            (inputs, outputs),
            params,
            reductions,
        );
    }

    /// The matrices of the products with `params`, in the products' arithmetic.
    pub(crate) fn prepare(&self, params: &[f32]) -> Matrices {
        Matrices(
            self.matrices
                .iter()
                .map(|m| matrix(m, params, self.precision))
                .collect(),
        )
    }

    /// [`Tiled::eval`] with the matrices [`Tiled::prepare`] made of `params`.
    pub(crate) fn eval_with(
        &self,
        matrices: Arc<Matrices>,
        n: usize,
        (inputs, outputs): (&[&[f32]], &mut [&mut [f32]]),
        params: &[f32],
        reductions: &mut [f32],
    ) {
        let mut w = Workspace::new(self, params, matrices);
        w.reserve_arenas(1);
        let mut laps = Laps::start();
        for start in (0..n).step_by(TILE) {
            let count = TILE.min(n - start);
            let arena = w.arena(0);
            let (forward, backward) = inputs.split_at(self.forward_inputs);
            // SAFETY: the arena holds n_slots columns of TILE ≥ count floats; sizes were checked.
            unsafe {
                w.forward_tile(arena, (start, count), forward, outputs, &mut laps);
                w.backward_tile(arena, (start, count), backward, &mut laps);
                w.scatter_tile(arena, count, reductions, &mut laps);
            }
        }
        laps.lap(Phase::Elementwise);
        laps.finish();
        w.finish(reductions);
    }

    /// Whether the plan was compiled with a split into a forward and a backward pass.
    pub(crate) fn is_split(&self) -> bool {
        self.forward_inputs < self.input_slots.len()
    }

    /// Copies points `start..start + count` of `columns` (inputs `first..`) into their slots.
    ///
    /// # Safety
    /// `arena` must hold `n_slots` columns of [`COLUMN`] floats, `count` ≤ [`TILE`], and every column of
    /// `columns` at least `start + count` floats.
    unsafe fn load(&self, arena: *mut f32, columns: &[&[f32]], first: usize, start: usize, count: usize) {
        for (column, slot) in columns.iter().zip(&self.input_slots[first..]) {
            if let Some(slot) = *slot {
                // SAFETY: as the caller guarantees.
                unsafe {
                    std::ptr::copy_nonoverlapping(
                        column[start..start + count].as_ptr(),
                        arena.add(slot * COLUMN),
                        count,
                    )
                };
            }
        }
    }

    /// Copies the outputs' slots into points `start..start + count` of `outputs`.
    ///
    /// # Safety
    /// As [`Tiled::load`].
    unsafe fn store(&self, arena: *const f32, outputs: &mut [&mut [f32]], start: usize, count: usize) {
        for (out, &slot) in outputs.iter_mut().zip(&self.output_slots) {
            // SAFETY: as the caller guarantees.
            unsafe {
                std::ptr::copy_nonoverlapping(
                    arena.add(slot * COLUMN),
                    out[start..start + count].as_mut_ptr(),
                    count,
                )
            };
        }
    }
}

/// The matrices of a plan's products with one set of params ([`Tiled::prepare`]), shared by the threads
/// of an evaluation.
pub(crate) struct Matrices(Vec<Matrix>);

/// What evaluating a plan with one set of params keeps between tiles: the matrices, the partial sums
/// of the reductions and the arenas (one for a whole evaluation; one per tile of points when the forward
/// pass keeps its values for the backward pass, see [`Passes`]).
pub(crate) struct Workspace<'a> {
    plan: &'a Tiled,
    params: &'a [f32],
    matrices: Arc<Matrices>,
    /// Each segment's reductions, 4 lanes each.
    accums: Vec<Vec<f32>>,
    /// Each outer product's sums, rows padded (see [`gemm::padded`]).
    grads: Vec<Vec<f32>>,
    scratch: Vec<f32>,
    bf16_scratch: Bf16Scratch,
    /// The arenas, `n_slots · COLUMN` floats each from the first cache line of their buffer on, each
    /// buffer its own allocation so that arenas stay in place when more are made.
    arenas: Vec<Vec<f32>>,
}

impl<'a> Workspace<'a> {
    fn new(plan: &'a Tiled, params: &'a [f32], matrices: Arc<Matrices>) -> Workspace<'a> {
        Workspace {
            plan,
            params,
            matrices,
            accums: plan
                .segments
                .iter()
                .map(|s| vec![0.0; 4 * s.as_ref().map_or(0, |s| s.reductions.len())])
                .collect(),
            grads: plan
                .outer
                .iter()
                .map(|o| vec![0.0; o.left.len() * gemm::padded(o.right.len())])
                .collect(),
            scratch: Vec::new(),
            bf16_scratch: Bf16Scratch::default(),
            arenas: Vec::new(),
        }
    }

    /// Makes room for `count` arenas, their constants and params filled in (the arenas made before keep
    /// what they hold).
    fn reserve_arenas(&mut self, count: usize) {
        let size = self.plan.n_slots * COLUMN;
        while self.arenas.len() < count {
            let mut buffer = Vec::new();
            let arena = gemm::line_aligned(&mut buffer, size);
            for &(slot, fill) in &self.plan.fills {
                let value = match fill {
                    Fill::Const(c) => c,
                    Fill::Param(k) => self.params[k],
                };
                arena[slot * COLUMN..slot * COLUMN + TILE].fill(value);
            }
            self.arenas.push(buffer);
        }
    }

    /// The start of arena `k` (< the arenas reserved).
    fn arena(&mut self, k: usize) -> *mut f32 {
        let size = self.plan.n_slots * COLUMN;
        gemm::line_aligned(&mut self.arenas[k], size).as_mut_ptr()
    }

    /// The forward pass of the tile of points `start..start + count` in `arena`: loads their `inputs`,
    /// runs the forward stages, stores the `outputs`.
    ///
    /// # Safety
    /// As [`Workspace::run_stages`], and the columns must hold `start + count` points.
    unsafe fn forward_tile(
        &mut self,
        arena: *mut f32,
        (start, count): (usize, usize),
        inputs: &[&[f32]],
        outputs: &mut [&mut [f32]],
        laps: &mut Laps,
    ) {
        let plan = self.plan;
        // SAFETY: as the caller guarantees.
        unsafe {
            plan.load(arena, inputs, 0, start, count);
            self.run_stages(arena, 0..plan.forward_stages, count, laps);
            plan.store(arena, outputs, start, count);
        }
    }

    /// The backward pass of the tile in `arena` (after its forward pass) but its grid scatters
    /// ([`Workspace::scatter_tile`]): loads the points' `cotangents`, runs the other stages.
    ///
    /// # Safety
    /// As [`Workspace::forward_tile`].
    unsafe fn backward_tile(
        &mut self,
        arena: *mut f32,
        (start, count): (usize, usize),
        cotangents: &[&[f32]],
        laps: &mut Laps,
    ) {
        let plan = self.plan;
        // SAFETY: as the caller guarantees.
        unsafe {
            plan.load(arena, cotangents, plan.forward_inputs, start, count);
            self.run_stages(arena, plan.forward_stages..plan.segments.len(), count, laps);
        }
    }

    /// Runs `stages` (products, grid reads, then the segment of each) on the tile in `arena`.
    ///
    /// # Safety
    /// `arena` must be one of this workspace's and `count` ≤ [`TILE`].
    unsafe fn run_stages(
        &mut self,
        arena: *mut f32,
        stages: std::ops::Range<usize>,
        count: usize,
        laps: &mut Laps,
    ) {
        let plan = self.plan;
        // SAFETY: every slot index is < n_slots, so each column lies inside the arena.
        let column = |slot: usize| unsafe { arena.add(slot * COLUMN) };
        let reads =
            |slots: &[usize]| -> Vec<*const f32> { slots.iter().map(|&s| column(s) as *const f32).collect() };
        let writes = |slots: &[usize]| -> Vec<*mut f32> { slots.iter().map(|&s| column(s)).collect() };
        for s in stages {
            for p in &plan.products[s] {
                let m = &self.matrices.0[p.matrix];
                let (x, out) = (reads(&p.x), writes(&p.out));
                // SAFETY: all columns are TILE floats in the arena; a product's outputs are picks, whose
                // slots no input of the same product uses (its inputs precede it).
                unsafe {
                    match m {
                        Matrix::F32(m) => gemm::matmul(m, &x, &out, count),
                        Matrix::Bf16(m) => bf16::matmul(m, &x, &out, count, &mut self.bf16_scratch),
                    }
                };
                laps.count(Phase::Products, 2 * (p.out.len() * p.x.len() * count) as u64);
            }
            laps.lap(Phase::Products);
            for step in &plan.grids[s] {
                let point = step.p.map(|s| column(s) as *const f32);
                // SAFETY: all columns are TILE ≥ count floats in the arena; the outputs are picks,
                // whose slots the point (read before them) does not share.
                unsafe { step.plan.read(point, &writes(&step.out), self.params, count) };
                laps.count(Phase::GridReads, step.plan.corners_per_point() * count as u64);
            }
            laps.lap(Phase::GridReads);
            if let Some(seg) = &plan.segments[s] {
                // SAFETY: the segment's columns are slots of the arena, TILE ≥ count rounded up to 4 floats
                // each.
                unsafe {
                    seg.kernel
                        .call_arena(arena, self.params, &mut self.accums[s], count)
                };
            }
            laps.lap(Phase::Elementwise);
            for (o, g) in plan
                .outer
                .iter()
                .zip(&mut self.grads)
                .filter(|(o, _)| o.stage == s)
            {
                let (left, right) = (reads(&o.left), reads(&o.right));
                // SAFETY: operand columns hold TILE ≥ count floats.
                unsafe {
                    match plan.precision {
                        Precision::F32 => gemm::outer(&left, &right, count, g, &mut self.scratch),
                        Precision::Bf16 => bf16::outer(&left, &right, count, g, &mut self.bf16_scratch),
                    }
                };
                laps.count(
                    Phase::OuterProducts,
                    2 * (left.len() * right.len() * count) as u64,
                );
            }
            laps.lap(Phase::OuterProducts);
        }
    }

    /// Adds the tile's grid scatters to `reductions`.
    ///
    /// # Safety
    /// As [`Workspace::run_stages`].
    unsafe fn scatter_tile(
        &mut self,
        arena: *const f32,
        count: usize,
        reductions: &mut [f32],
        laps: &mut Laps,
    ) {
        // SAFETY: every slot index is < n_slots, so each column lies inside the arena.
        let column = |s: usize| unsafe { arena.add(s * COLUMN) };
        for sc in &self.plan.scatters {
            let cotangent: Vec<*const f32> = sc.cotangent.iter().map(|&s| column(s)).collect();
            // SAFETY: operand columns hold TILE ≥ count floats.
            unsafe { sc.plan.scatter(sc.p.map(column), &cotangent, reductions, count) };
            laps.count(Phase::GridScatters, sc.plan.corners_per_point() * count as u64);
        }
        laps.lap(Phase::GridScatters);
    }

    /// Appends the points and cotangents of the tile's grid scatters (in `arena`) to `held`.
    ///
    /// # Safety
    /// As [`Workspace::run_stages`].
    unsafe fn hold_tile(&self, arena: *const f32, count: usize, held: &mut [HeldStep]) {
        // SAFETY: every slot index is < n_slots, so each column of TILE ≥ count floats lies in the arena.
        let column = |s: usize| unsafe { std::slice::from_raw_parts(arena.add(s * COLUMN), count) };
        for (sc, held) in self.plan.scatters.iter().zip(held) {
            for (to, &slot) in held.p.iter_mut().zip(&sc.p) {
                to.extend_from_slice(column(slot));
            }
            for (to, &slot) in held.cotangent.iter_mut().zip(&sc.cotangent) {
                to.extend_from_slice(column(slot));
            }
        }
    }

    /// Adds the segments' reductions and the outer products' sums to `reductions`, and starts them again.
    fn finish(&mut self, reductions: &mut [f32]) {
        for (seg, acc) in self.plan.segments.iter().zip(&mut self.accums) {
            if let Some(seg) = seg {
                for (&r, lanes) in seg.reductions.iter().zip(acc.chunks_exact(4)) {
                    reductions[r] += lane_sum(lanes);
                }
            }
            acc.fill(0.0);
        }
        for (o, g) in self.plan.outer.iter().zip(&mut self.grads) {
            let (cols, stride) = (o.right.len(), gemm::padded(o.right.len()));
            for i in 0..o.left.len() {
                for j in 0..cols {
                    reductions[o.target + i * cols + j] += g[i * stride + j];
                }
            }
            g.fill(0.0);
        }
        debug_assert_eq!(reductions.len(), self.plan.n_reductions);
    }
}

/// The forward and the backward pass of a kernel compiled with a split ([`Options::split`]) run
/// separately over the same points: the forward passes keep each tile's arena, the backward pass goes on
/// in them after the caller has computed the cotangents from the outputs, so nothing is recomputed.
pub(crate) struct Passes<'a> {
    plan: &'a Tiled,
    params: &'a [f32],
    /// Made by the first forward pass.
    workspace: Option<Workspace<'a>>,
    /// The points in each arena the forward passes since the last backward pass filled, in order.
    kept: Vec<usize>,
    /// The backward passes' grid scatters, held back ([`Passes::hold_scatters`]).
    held: Option<Vec<HeldStep>>,
}

/// One scatter's points and cotangents, as columns, in the order the backward passes ran.
struct HeldStep {
    p: [Vec<f32>; 3],
    cotangent: Vec<Vec<f32>>,
}

/// The grid scatters of a kernel's backward passes, held back from the reductions
/// ([`crate::Passes::hold_scatters`]) to be added part by part: each part is one level of a grid (its params
/// disjoint from the other parts' and from every other reduction), so that the parts can be added on
/// several threads into one gradient.
pub struct HeldScatters<'a> {
    plan: &'a Tiled,
    steps: Vec<HeldStep>,
}

impl HeldScatters<'_> {
    /// The params of each part, sorted and disjoint.
    pub fn parts(&self) -> &[std::ops::Range<usize>] {
        self.plan.scatter_parts.as_deref().unwrap_or(&[])
    }

    /// Adds part `part`'s scatters to `grads`, the gradients of that part's params: the additions of
    /// the backward passes' scatters to those params, in the same order.
    ///
    /// # Panics
    /// If there is no such part or `grads` is not as long as its params.
    pub fn add(&self, part: usize, grads: &mut [f32]) {
        let params = self.parts()[part].clone();
        assert_eq!(
            grads.len(),
            params.len(),
            "the gradients of a part of the scatters"
        );
        let mut laps = Laps::start();
        for (sc, held) in self.plan.scatters.iter().zip(&self.steps) {
            let count = held.p[0].len();
            let p = [0, 1, 2].map(|a| held.p[a].as_ptr());
            let cotangent: Vec<*const f32> = held.cotangent.iter().map(|c| c.as_ptr()).collect();
            for l in (0..sc.plan.levels()).filter(|&l| sc.plan.level_params(l) == params) {
                let window = GradWindow {
                    grads: &mut *grads,
                    origin: params.start,
                };
                // SAFETY: every held column holds `count` floats (each tile appended `count` to all).
                unsafe { sc.plan.scatter_levels(p, &cotangent, window, count, l..l + 1) };
                laps.count(Phase::GridScatters, 8 * count as u64);
            }
        }
        laps.lap(Phase::GridScatters);
        laps.finish();
    }
}

impl<'a> Passes<'a> {
    /// Passes of `plan` with `params` (nothing is prepared before the first forward pass).
    pub(crate) fn new(plan: &'a Tiled, params: &'a [f32]) -> Passes<'a> {
        Passes {
            plan,
            params,
            workspace: None,
            kept: Vec::new(),
            held: None,
        }
    }

    /// Holds the grid scatters of the backward passes from now on back from the reductions, for
    /// [`Passes::take_scatters`], if the plan's scatters allow it (see [`HeldScatters`]); returns whether
    /// they are held.
    pub(crate) fn hold_scatters(&mut self) -> bool {
        if self.plan.scatter_parts.is_some() && self.held.is_none() {
            let steps = self.plan.scatters.iter().map(|sc| HeldStep {
                p: Default::default(),
                cotangent: vec![Vec::new(); sc.cotangent.len()],
            });
            self.held = Some(steps.collect());
        }
        self.held.is_some()
    }

    /// The scatters held since [`Passes::hold_scatters`] (which holds them no more).
    pub(crate) fn take_scatters(&mut self) -> Option<HeldScatters<'a>> {
        let steps = self.held.take()?;
        Some(HeldScatters {
            plan: self.plan,
            steps,
        })
    }

    /// The forward pass over points `0..n` (sizes checked by the caller): writes the outputs, keeps a tile
    /// arena per [`TILE`] points after those of the forward passes before it.
    pub(crate) fn forward(&mut self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        let plan = self.plan;
        let w = self
            .workspace
            .get_or_insert_with(|| Workspace::new(plan, self.params, Arc::new(plan.prepare(self.params))));
        let first = self.kept.len();
        w.reserve_arenas(first + n.div_ceil(TILE));
        let mut laps = Laps::start();
        for (t, start) in (0..n).step_by(TILE).enumerate() {
            let count = TILE.min(n - start);
            let arena = w.arena(first + t);
            // SAFETY: arena first + t exists; sizes were checked by the caller.
            unsafe { w.forward_tile(arena, (start, count), inputs, outputs, &mut laps) };
            self.kept.push(count);
        }
        laps.lap(Phase::Elementwise);
        laps.finish();
    }

    /// The backward pass over the points of the forward passes since the last backward pass, `0..n` in
    /// their order, with their `cotangents`; adds grid scatters to `reductions` now and the rest at
    /// [`Passes::finish`].
    ///
    /// # Panics
    /// If those forward passes were not over `n` points in all.
    pub(crate) fn backward(&mut self, n: usize, cotangents: &[&[f32]], reductions: &mut [f32]) {
        assert_eq!(
            self.kept.iter().sum::<usize>(),
            n,
            "a backward pass runs over the points of the forward passes"
        );
        let Some(w) = self.workspace.as_mut() else {
            return;
        };
        let mut laps = Laps::start();
        let mut start = 0;
        for (t, count) in self.kept.drain(..).enumerate() {
            let arena = w.arena(t);
            // SAFETY: a forward pass filled arena t with `count` points; sizes were checked by the caller.
            unsafe {
                w.backward_tile(arena, (start, count), cotangents, &mut laps);
                match &mut self.held {
                    Some(held) => {
                        w.hold_tile(arena, count, held);
                        laps.lap(Phase::GridScatters);
                    }
                    None => w.scatter_tile(arena, count, reductions, &mut laps),
                }
            }
            start += count;
        }
        laps.lap(Phase::Elementwise);
        laps.finish();
    }

    /// The bytes the forward passes keep per point: a tile arena's over its [`TILE`] points.
    pub(crate) fn bytes_per_point(&self) -> usize {
        self.plan.n_slots * COLUMN * size_of::<f32>() / TILE
    }

    /// Adds what the backward passes summed so far (segment reductions, outer products) to `reductions`.
    pub(crate) fn finish(&mut self, reductions: &mut [f32]) {
        if let Some(w) = &mut self.workspace {
            w.finish(reductions);
        }
    }

    /// The inputs of the forward pass.
    pub(crate) fn forward_inputs(&self) -> usize {
        self.plan.forward_inputs
    }
}

/// A product's matrix, prepared for its arithmetic.
enum Matrix {
    F32(Vec<f32>),
    Bf16(Bf16Matrix),
}

/// The matrix `p` (W itself, or a transposed copy), in `precision`.
fn matrix(p: &MatrixOf, params: &[f32], precision: Precision) -> Matrix {
    let w = &params[p.w..p.w + p.rows * p.cols];
    let (a, rows, cols) = if p.transposed {
        let mut t = vec![0.0; w.len()];
        for i in 0..p.rows {
            for j in 0..p.cols {
                t[j * p.rows + i] = w[i * p.cols + j];
            }
        }
        (t, p.cols, p.rows)
    } else {
        (w.to_vec(), p.rows, p.cols)
    };
    match precision {
        Precision::F32 => Matrix::F32(a),
        Precision::Bf16 => Matrix::Bf16(Bf16Matrix::new(&a, rows, cols)),
    }
}

/// Stage `s`'s elementwise nodes as a graph of their own, or None if the stage computes nothing.
fn segment_spec(g: &Graph, stage: &[usize], slots: &mut Slots, s: usize) -> Option<SegmentSpec> {
    let ops = g.ops();
    let mut segment = SegmentBuilder {
        ops,
        graph: Graph::new(),
        local: HashMap::new(),
        reads: Vec::new(),
    };
    let mut writes = Vec::new();
    for (i, op) in ops.iter().enumerate() {
        if stage[i] != s || !is_elementwise(op) {
            continue;
        }
        let mapped = op.map_args(|a| segment.read(slots, a));
        let v = segment.graph.push(mapped);
        segment.local.insert(V(i as u32), v);
        if let Some(slot) = slots.of[i] {
            segment.graph.outputs.push(v);
            writes.push(slot);
        }
    }
    let mut reductions = Vec::new();
    for (r, &v) in g.reductions.iter().enumerate() {
        let op = &ops[v.0 as usize];
        if stage[v.0 as usize] != s || *op == Op::Const(0f64.to_bits()) {
            continue;
        }
        let value = segment.read(slots, v);
        segment.graph.reductions.push(value);
        reductions.push(r);
    }
    if segment.graph.outputs.is_empty() && segment.graph.reductions.is_empty() {
        return None;
    }
    Some(SegmentSpec {
        graph: segment.graph,
        reads: segment.reads,
        writes,
        reductions,
    })
}

/// A segment's graph as it is built from the whole graph's nodes of one stage.
struct SegmentBuilder<'g> {
    ops: &'g [Op],
    graph: Graph,
    /// The segment's value of each node of the whole graph it has computed or read.
    local: HashMap<V, V>,
    /// The slot each of the segment's inputs reads.
    reads: Vec<usize>,
}

impl SegmentBuilder<'_> {
    /// The segment's value of node `a`: constants and params made again, comparisons with a constant made
    /// again from the value compared ([`compared_value`]), nodes of the stage as computed, the rest read
    /// from their slots (once each).
    fn read(&mut self, slots: &mut Slots, a: V) -> V {
        if let Some(&v) = self.local.get(&a) {
            return v;
        }
        let op = self.ops[a.0 as usize];
        let v = match op {
            Op::Const(bits) => self.graph.constant(f64::from_bits(bits)),
            Op::Param(k) => self.graph.param(k),
            _ if compared_value(self.ops, a).is_some() => {
                let mapped = op.map_args(|x| self.read(slots, x));
                self.graph.push(mapped)
            }
            _ => {
                self.reads.push(slots.get(a));
                self.graph.input(self.reads.len() as u32 - 1)
            }
        };
        self.local.insert(a, v);
        v
    }
}

/// For a comparison of a value with a constant, the value: a segment of a later stage makes such a mask
/// again from the value (a network's activations, which its backward pass keeps anyway for the weight
/// gradients) rather than keeping a column for the mask itself (ReLU's derivative).
fn compared_value(ops: &[Op], v: V) -> Option<V> {
    let is_const = |x: V| matches!(ops[x.0 as usize], Op::Const(_));
    match ops[v.0 as usize] {
        Op::Lt(a, b) | Op::Le(a, b) | Op::Eq(a, b) => match (is_const(a), is_const(b)) {
            (true, false) => Some(b),
            (false, true) => Some(a),
            _ => None,
        },
        _ => None,
    }
}
