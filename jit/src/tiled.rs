//! Kernels of graphs with dense nodes: elementwise JIT segments and matrix products, run over tiles of
//! points.
//!
//! Every node gets a level: the number of dense products on the longest path from the inputs to it. The
//! scalar nodes of one level form a segment, compiled to an ordinary JIT kernel (so the elementwise work
//! between two products, bias + activation + whatever the script does, stays fused); the dense nodes of
//! level L run, as [`gemm::matmul`], after segment L − 1 and before segment L. Values that cross a
//! boundary live in slots: one column of [`TILE`] floats each, in an arena reused for every tile. The
//! graph's outer products (the gradients of the matrices) run last, as [`gemm::outer`], and are summed
//! over the whole batch. Constants and params are recomputed in every segment that reads them.

use std::collections::HashMap;
use std::time::Instant;

use nerfjit_dsl::ir::{Graph, Op, V};

use crate::bf16::{self, Bf16Matrix, Bf16Scratch, Precision};
use crate::encode::GridPlan;
use crate::gemm::{self, COLUMN, TILE};
use crate::kernel::{lane_sum, CompileStats, JitError, Kernel, Options};
use crate::profile::{Laps, Phase};

/// One elementwise segment: a JIT kernel reading and writing slots.
struct Segment {
    kernel: Kernel,
    reads: Vec<usize>,
    writes: Vec<usize>,
    /// The graph reduction each of the kernel's reductions adds to.
    reductions: Vec<usize>,
}

/// One dense product: `out = A·x` with A = W or Wᵀ.
struct Product {
    w: usize,
    rows: usize,
    cols: usize,
    transposed: bool,
    x: Vec<usize>,
    out: Vec<usize>,
}

/// One outer product added to the reductions from `target` on.
struct OuterProduct {
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
    /// The grid reads of each stage, run with its products.
    grids: Vec<Vec<GridStep>>,
    outer: Vec<OuterProduct>,
    scatters: Vec<ScatterStep>,
    fills: Vec<(usize, Fill)>,
    input_slots: Vec<Option<usize>>,
    output_slots: Vec<usize>,
    /// Where products and grid reads write the outputs that nothing reads.
    spare: usize,
    n_slots: usize,
    n_reductions: usize,
    /// The arithmetic of the products.
    precision: Precision,
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

fn levels(g: &Graph) -> Vec<usize> {
    let mut level = vec![0usize; g.len()];
    for (i, op) in g.ops().iter().enumerate() {
        let highest = g.args(op).iter().map(|a| level[a.0 as usize]).max().unwrap_or(0);
        level[i] = match op {
            Op::Dense(_) | Op::Grid(_) => highest + 1,
            _ => highest,
        };
    }
    level
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
        let level = levels(g);
        let n_levels = level.iter().max().map_or(1, |m| m + 1);
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
                        if is_elementwise(arg) && level[a.0 as usize] != level[i] {
                            slots.get(a);
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

        let mut products: Vec<Vec<Product>> = (0..n_levels).map(|_| Vec::new()).collect();
        let mut picks: HashMap<(u32, u32), usize> = HashMap::new();
        for (i, op) in ops.iter().enumerate() {
            if let Op::Pick(d, k) = op {
                picks.insert((d.0, *k), slots.of[i].expect("picks have slots"));
            }
        }
        for (i, op) in ops.iter().enumerate() {
            if let Op::Dense(d) = op {
                products[level[i]].push(Product {
                    w: d.w as usize,
                    rows: d.rows as usize,
                    cols: d.cols as usize,
                    transposed: d.transposed,
                    x: g.list(d.x).iter().map(|&a| slots.get(a)).collect(),
                    out: (0..d.n_out() as u32)
                        .map(|k| picks.get(&(i as u32, k)).copied().unwrap_or(spare))
                        .collect(),
                });
            }
        }

        let mut grids: Vec<Vec<GridStep>> = (0..n_levels).map(|_| Vec::new()).collect();
        for (i, op) in ops.iter().enumerate() {
            if let Op::Grid(r) = op {
                grids[level[i]].push(GridStep {
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

        let mut segments = Vec::with_capacity(n_levels);
        let mut stats = CompileStats::default();
        for s in 0..n_levels {
            let segment = build_segment(g, &level, &mut slots, s, options)?;
            if let Some(seg) = &segment {
                let st = seg.kernel.stats();
                stats.nodes += st.nodes;
                stats.code_bytes += st.code_bytes;
                if let Some(clif) = &st.clif {
                    stats.clif.get_or_insert_with(String::new).push_str(clif);
                }
            }
            segments.push(segment);
        }

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
        stats.seconds = start.elapsed().as_secs_f64();
        let mut plan = Tiled {
            segments,
            products,
            grids,
            outer,
            scatters,
            fills,
            input_slots,
            output_slots,
            spare,
            n_slots: slots.count,
            n_reductions: g.reductions.len(),
            precision: options.products,
            stats,
        };
        plan.share_slots();
        Ok(plan)
    }

    /// Lets values whose lifetimes do not overlap share a column of the arena, so that a tile's arena
    /// holds what is live at once rather than every value that crosses a boundary (a network's forward
    /// pass then fits in the L2 cache). Time runs over the stages: inputs are loaded at 0, stage s runs its
    /// products at 2s + 1 and its segment at 2s + 2, outer products and outputs read at the end. A column
    /// is reused only by a value written strictly after the column's last read.
    fn share_slots(&mut self) {
        const UNSET: usize = usize::MAX;
        let end = 2 * self.segments.len() + 1;
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
        for slot in self.input_slots.iter().flatten() {
            touch(*slot, 0);
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
        for (s, segment) in self.segments.iter().enumerate() {
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
                touch(slot, end);
            }
        }
        for &slot in &self.output_slots {
            touch(slot, end);
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
        for seg in self.segments.iter_mut().flatten() {
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

    /// Evaluates points `0..n` on this thread (see [`Kernel::eval`]; sizes were checked by the caller).
    pub(crate) fn eval(
        &self,
        n: usize,
        inputs: &[&[f32]],
        outputs: &mut [&mut [f32]],
        params: &[f32],
        reductions: &mut [f32],
    ) {
        // Columns start on cache lines, COLUMN floats apart.
        let mut buffer = Vec::new();
        let arena = gemm::line_aligned(&mut buffer, self.n_slots * COLUMN);
        let base = arena.as_mut_ptr();
        // SAFETY: every slot index is < n_slots, so each column lies inside the arena.
        let column = |slot: usize| unsafe { base.add(slot * COLUMN) };
        for &(slot, fill) in &self.fills {
            let value = match fill {
                Fill::Const(c) => c,
                Fill::Param(k) => params[k],
            };
            arena[slot * COLUMN..slot * COLUMN + TILE].fill(value);
        }
        let matrices: Vec<Vec<Matrix>> = self
            .products
            .iter()
            .map(|level| level.iter().map(|p| matrix(p, params, self.precision)).collect())
            .collect();
        let mut accums: Vec<Vec<f32>> = self
            .segments
            .iter()
            .map(|s| vec![0.0; 4 * s.as_ref().map_or(0, |s| s.reductions.len())])
            .collect();
        let mut grads: Vec<Vec<f32>> = self
            .outer
            .iter()
            .map(|o| vec![0.0; o.left.len() * gemm::padded(o.right.len())])
            .collect();
        let columns = |slots: &[usize]| -> Vec<*mut f32> { slots.iter().map(|&s| column(s)).collect() };
        let reads =
            |slots: &[usize]| -> Vec<*const f32> { slots.iter().map(|&s| column(s) as *const f32).collect() };
        let segment_io: Vec<Option<(Vec<*const f32>, Vec<*mut f32>)>> = self
            .segments
            .iter()
            .map(|s| s.as_ref().map(|s| (reads(&s.reads), columns(&s.writes))))
            .collect();
        let product_io: Vec<Vec<(Vec<*const f32>, Vec<*mut f32>)>> = self
            .products
            .iter()
            .map(|level| level.iter().map(|p| (reads(&p.x), columns(&p.out))).collect())
            .collect();
        let outer_io: Vec<(Vec<*const f32>, Vec<*const f32>)> = self
            .outer
            .iter()
            .map(|o| (reads(&o.left), reads(&o.right)))
            .collect();
        let grid_io: Vec<Vec<([*const f32; 3], Vec<*mut f32>)>> = self
            .grids
            .iter()
            .map(|level| {
                let point = |p: [usize; 3]| p.map(|s| column(s) as *const f32);
                level
                    .iter()
                    .map(|step| (point(step.p), columns(&step.out)))
                    .collect()
            })
            .collect();
        let scatter_io: Vec<([*const f32; 3], Vec<*const f32>)> = self
            .scatters
            .iter()
            .map(|sc| (sc.p.map(|s| column(s) as *const f32), reads(&sc.cotangent)))
            .collect();
        let mut scratch = Vec::new();
        let mut bf16_scratch = Bf16Scratch::default();
        let mut laps = Laps::start();

        for start in (0..n).step_by(TILE) {
            let count = TILE.min(n - start);
            for (k, slot) in self.input_slots.iter().enumerate() {
                if let Some(slot) = *slot {
                    arena[slot * COLUMN..slot * COLUMN + count]
                        .copy_from_slice(&inputs[k][start..start + count]);
                }
            }
            laps.lap(Phase::Elementwise);
            for s in 0..self.segments.len() {
                for (p, m) in product_io[s].iter().zip(&matrices[s]) {
                    // SAFETY: all columns are TILE floats in the arena; a product's outputs are picks, whose
                    // slots no input of the same product uses (its inputs precede it).
                    unsafe {
                        match m {
                            Matrix::F32(m) => gemm::matmul(m, &p.0, &p.1),
                            Matrix::Bf16(m) => bf16::matmul(m, &p.0, &p.1, &mut bf16_scratch),
                        }
                    };
                }
                laps.lap(Phase::Products);
                for (step, (p, out)) in self.grids[s].iter().zip(&grid_io[s]) {
                    // SAFETY: all columns are TILE ≥ count floats in the arena; the outputs are picks,
                    // whose slots the point (read before them) does not share.
                    unsafe { step.plan.read(*p, out, params, count) };
                }
                laps.lap(Phase::GridReads);
                if let (Some(seg), Some((ins, outs))) = (&self.segments[s], &segment_io[s]) {
                    // SAFETY: the segment's columns are TILE ≥ count rounded up to 4 floats each.
                    unsafe { seg.kernel.call_raw(ins, outs, params, &mut accums[s], count) };
                }
                laps.lap(Phase::Elementwise);
            }
            for ((io, g), _) in outer_io.iter().zip(&mut grads).zip(&self.outer) {
                // SAFETY: operand columns hold TILE ≥ count floats.
                unsafe {
                    match self.precision {
                        Precision::F32 => gemm::outer(&io.0, &io.1, count, g, &mut scratch),
                        Precision::Bf16 => bf16::outer(&io.0, &io.1, count, g, &mut bf16_scratch),
                    }
                };
            }
            laps.lap(Phase::OuterProducts);
            for (sc, (p, cot)) in self.scatters.iter().zip(&scatter_io) {
                // SAFETY: operand columns hold TILE ≥ count floats.
                unsafe { sc.plan.scatter(*p, cot, reductions, count) };
            }
            laps.lap(Phase::GridScatters);
            for (out, &slot) in outputs.iter_mut().zip(&self.output_slots) {
                out[start..start + count].copy_from_slice(&arena[slot * COLUMN..slot * COLUMN + count]);
            }
        }
        laps.lap(Phase::Elementwise);
        laps.finish();

        for (seg, acc) in self.segments.iter().zip(&accums) {
            if let Some(seg) = seg {
                for (&r, lanes) in seg.reductions.iter().zip(acc.chunks_exact(4)) {
                    reductions[r] += lane_sum(lanes);
                }
            }
        }
        for (o, g) in self.outer.iter().zip(&grads) {
            let (cols, stride) = (o.right.len(), gemm::padded(o.right.len()));
            for i in 0..o.left.len() {
                for j in 0..cols {
                    reductions[o.target + i * cols + j] += g[i * stride + j];
                }
            }
        }
        debug_assert_eq!(reductions.len(), self.n_reductions);
    }
}

/// A product's matrix, prepared for its arithmetic.
enum Matrix {
    F32(Vec<f32>),
    Bf16(Bf16Matrix),
}

/// The matrix a product multiplies by (W itself, or a transposed copy), in `precision`.
fn matrix(p: &Product, params: &[f32], precision: Precision) -> Matrix {
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

/// The JIT kernel of level `s`'s elementwise nodes, or None if the level computes nothing.
fn build_segment(
    g: &Graph,
    level: &[usize],
    slots: &mut Slots,
    s: usize,
    options: Options,
) -> Result<Option<Segment>, JitError> {
    let ops = g.ops();
    let mut sg = Graph::new();
    let mut local: HashMap<V, V> = HashMap::new();
    let mut reads: Vec<usize> = Vec::new();
    let mut read = |sg: &mut Graph, local: &HashMap<V, V>, slots: &mut Slots, a: V| -> V {
        match ops[a.0 as usize] {
            Op::Const(bits) => sg.constant(f64::from_bits(bits)),
            Op::Param(k) => sg.param(k),
            _ => match local.get(&a) {
                Some(&v) => v,
                None => {
                    reads.push(slots.get(a));
                    sg.input(reads.len() as u32 - 1)
                }
            },
        }
    };
    let mut writes = Vec::new();
    for (i, op) in ops.iter().enumerate() {
        if level[i] != s || !is_elementwise(op) {
            continue;
        }
        let mapped = op.map_args(|a| read(&mut sg, &local, slots, a));
        let v = sg.push(mapped);
        local.insert(V(i as u32), v);
        if let Some(slot) = slots.of[i] {
            sg.outputs.push(v);
            writes.push(slot);
        }
    }
    let mut reductions = Vec::new();
    for (r, &v) in g.reductions.iter().enumerate() {
        let op = &ops[v.0 as usize];
        if level[v.0 as usize] != s || *op == Op::Const(0f64.to_bits()) {
            continue;
        }
        let value = read(&mut sg, &local, slots, v);
        sg.reductions.push(value);
        reductions.push(r);
    }
    if sg.outputs.is_empty() && sg.reductions.is_empty() {
        return Ok(None);
    }
    Ok(Some(Segment {
        kernel: Kernel::compile(&sg, options)?,
        reads,
        writes,
        reductions,
    }))
}
