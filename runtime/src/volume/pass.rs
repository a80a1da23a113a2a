//! The volume pass: the one engine that samples, evaluates and composites a tile of rays for renders
//! ([`crate::volume::render`]), hierarchical renders ([`crate::volume::hierarchical`]) and training
//! steps ([`crate::volume::train`]).
//!
//! A tile is `n` rays (origins and unit directions, loaded into the worker's [`Scratch`]) with
//! `samples` depths each, shared by all rays or each ray's own ([`Depths`]). [`run`] evaluates the
//! field at the samples that can contribute and composites them:
//! - With an [`OccupancyGrid`], rays that miss the grid's box or cross none of its marked blocks of
//!   cells are done without any work; for the others, the samples between where the ray enters its
//!   first marked block and leaves its last ([`OccupancyGrid::occupied_stretch`]) are looked up in the
//!   grid (stepping over those in empty coarse cells of a grid in the scene's space), and the occupied
//!   ones are packed ray by ray into one dense field call (the other samples are empty space: all
//!   outputs 0, alpha 0) and composited ray by ray.
//! - Without a grid, the samples go to the field sample-major (sample j of ray k at `j·n + k`) and are
//!   composited across rays, a loop that vectorizes.
//! - With early termination, the samples go [`CHUNK_SAMPLES`] depths at a time; with a grid, each field
//!   call takes every live ray's next occupied samples, one each while more than
//!   [`PACKED_CALL_POINTS`] rays are live and more (up to [`PACKED_CHUNK_SAMPLES`]) as they stop, so
//!   that few samples past where a ray stops are evaluated. The rays whose transmittance fell below
//!   the threshold (or, with a grid, that have no samples left) are done, and the next field call sees
//!   the live rays only (compaction). Every sample the compositor counts is evaluated.
//!
//! What a pass gives ([`Sink`]) is either each ray's composite (renders) or the field's inputs and
//! outputs at every sample of the tile, sample-major, zero where the field was not evaluated, with the
//! list of samples evaluated (training, whose field gradient [`backward`] takes there, and the coarse
//! pass of hierarchical sampling, from which [`draw_fine_depths`] draws the fine depths). Evaluated
//! samples are at exactly the points and depths of the exact composite and composited with the same
//! operations: a render is, bit for bit, the exact composite of the field with its outputs set to 0
//! where the grid marks empty space (given finite colors).

use std::cell::RefCell;
use std::ops::Range;

use crate::cameras::rays::RayBatch;
use crate::field::{BatchFn, BatchVjp};
use crate::rng::Rng;
use crate::volume::composite::{
    Compositor, DepthColumn, Lanes, RayDepths, RayOutput, SharedDepths, LAST_DELTA,
};
use crate::volume::importance;
use crate::volume::occupancy::OccupancyGrid;
use crate::volume::settings::{VolumeSettings, CHUNK_SAMPLES, PACKED_CALL_POINTS, PACKED_CHUNK_SAMPLES};

/// Per-worker buffers of the volume pass, grown on demand and reused across tiles, frames and steps.
#[derive(Debug, Default)]
pub(crate) struct Scratch {
    /// The tile's field inputs at every sample, sample-major: x, y, z, then the view direction
    /// (training and the coarse pass of hierarchical sampling).
    pub(crate) inputs: [Vec<f32>; 6],
    /// The tile's field outputs at every sample, sample-major: density or opacity, r, g, b.
    pub(crate) outputs: [Vec<f32>; 4],
    /// Cotangents of the field outputs (training).
    pub(crate) cotangents: [Vec<f32>; 4],
    /// Depths of the tile's samples, sample-major (training and hierarchical sampling).
    pub(crate) depths: Vec<f32>,
    /// Accumulators of the rays of the tile.
    pub(crate) lanes: Lanes,
    /// Origin of each live ray of the tile.
    origins: [Vec<f32>; 3],
    /// The origin of every ray of the tile, if they share one.
    shared_origin: Option<[f32; 3]>,
    /// Unit direction of each live ray of the tile.
    directions: [Vec<f32>; 3],
    /// Index in the tile of each live ray.
    ids: Vec<usize>,
    /// Field inputs of one field call.
    call_inputs: [Vec<f32>; 6],
    /// Field outputs of one field call.
    call_outputs: [Vec<f32>; 4],
    /// Depth and δ of each sample of one field call (depths of their own, without a grid).
    call_depths: [Vec<f32>; 2],
    /// Sample index of each packed (occupied) sample (with a grid).
    samples: Vec<u32>,
    /// End of the packed samples of each ray (with a grid).
    ends: Vec<u32>,
    /// Depths where each ray enters and leaves the grid's box (with a grid).
    intervals: [Vec<f32>; 2],
    /// Samples `first..end` of each ray that may be inside the grid and that no field call took yet
    /// (with a grid).
    spans: Vec<[u32; 2]>,
}

/// Grows `v` to at least `n` entries.
fn grow<T: Clone + Default>(v: &mut Vec<T>, n: usize) {
    if v.len() < n {
        v.resize(n, T::default());
    }
}

impl Scratch {
    /// Makes the per-sample buffers of a tile at least `points` and its per-ray buffers at least
    /// `rays` long.
    pub(crate) fn reserve(&mut self, points: usize, rays: usize) {
        for v in self
            .inputs
            .iter_mut()
            .chain(&mut self.outputs)
            .chain(&mut self.cotangents)
        {
            grow(v, points);
        }
        grow(&mut self.depths, points);
        self.reserve_rays(rays);
    }

    /// Makes the per-ray buffers at least `rays` long.
    fn reserve_rays(&mut self, rays: usize) {
        for v in self.origins.iter_mut().chain(&mut self.directions) {
            grow(v, rays);
        }
    }

    /// Loads rays `first..first + n` of `rays` as the tile's rays.
    pub(crate) fn load_rays(&mut self, rays: &RayBatch, first: usize, n: usize) {
        self.reserve_rays(n);
        let tile = first..first + n;
        let sources = [&rays.ox, &rays.oy, &rays.oz, &rays.dx, &rays.dy, &rays.dz];
        let [ox, oy, oz] = &mut self.origins;
        let [dx, dy, dz] = &mut self.directions;
        for (to, from) in [ox, oy, oz, dx, dy, dz].into_iter().zip(sources) {
            to[..n].copy_from_slice(&from[tile.clone()]);
        }
        self.ids.clear();
        self.ids.extend(0..n);
        self.shared_origin = None;
    }

    /// Loads `n` rays from `origin` as the tile's rays, ray k in direction `direction(k)` (called for k
    /// in order).
    pub(crate) fn load_rays_from(
        &mut self,
        origin: [f32; 3],
        n: usize,
        mut direction: impl FnMut(usize) -> [f32; 3],
    ) {
        self.reserve_rays(n);
        for (o, &value) in self.origins.iter_mut().zip(&origin) {
            o[..n].fill(value);
        }
        let [dx, dy, dz] = &mut self.directions;
        for k in 0..n {
            [dx[k], dy[k], dz[k]] = direction(k);
        }
        self.ids.clear();
        self.ids.extend(0..n);
        self.shared_origin = Some(origin);
    }
}

thread_local! {
    /// The buffers of this thread, reused across tiles, frames and steps.
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

/// Runs `f` with this thread's buffers (fresh ones if they are in use, which happens only if
/// a field runs parallel work that makes this thread run another tile).
pub(crate) fn with_scratch<T>(f: impl FnOnce(&mut Scratch) -> T) -> T {
    SCRATCH.with(|cell| match cell.try_borrow_mut() {
        Ok(mut scratch) => f(&mut scratch),
        Err(_) => f(&mut Scratch::default()),
    })
}

/// The sample depths of a tile's rays.
#[derive(Clone, Copy)]
pub(crate) enum Depths<'a> {
    /// The same depths on every ray, with their δ ([`deltas`]).
    Shared(SharedDepths<'a>),
    /// Depths of each ray's own, in the scratch's `depths`, sample-major over the tile's rays (sample j
    /// of ray k at `j·n + k`).
    PerRay,
}

/// Where a running pass reads the depths.
#[derive(Clone, Copy)]
enum Source<'a> {
    /// See [`Depths::Shared`].
    Shared(SharedDepths<'a>),
    /// See [`Depths::PerRay`]: the scratch's depths, taken out while the pass runs.
    PerRay(&'a [f32]),
}

/// A volume pass: what to evaluate and how to composite.
pub(crate) struct Pass<'a> {
    /// The field: a point, maybe a view direction → density or opacity, r, g, b.
    pub(crate) field: &'a dyn BatchFn,
    /// How samples composite.
    pub(crate) compositor: Compositor,
    /// Skip the samples in its empty cells.
    pub(crate) grid: Option<&'a OccupancyGrid>,
    /// Depths per ray.
    pub(crate) samples: usize,
}

impl Pass<'_> {
    /// Sample rows per field call.
    fn chunk(&self) -> usize {
        match (self.compositor.early_termination, self.grid) {
            (Some(_), None) => CHUNK_SAMPLES.min(self.samples),
            (Some(_), Some(_)) => PACKED_CHUNK_SAMPLES.min(self.samples),
            (None, _) => self.samples,
        }
    }
}

/// What a pass gives.
pub(crate) enum Output<'a> {
    /// Each ray's composite, at its index in the tile.
    Rays(RayOutputs<'a>),
    /// The field's inputs and outputs at every sample of the tile, sample-major, into the scratch's
    /// `inputs` and `outputs` (the outputs zero where the field was not evaluated; the inputs only
    /// meaningful where it was).
    Samples,
}

/// Where a running pass puts what it gives.
enum Sink<'a> {
    /// See [`Output::Rays`].
    Rays(RayOutputs<'a>),
    /// See [`Output::Samples`]: the scratch's buffers, taken out while the pass runs.
    Samples {
        /// As many columns as the field has inputs.
        inputs: &'a mut [Vec<f32>],
        outputs: &'a mut [Vec<f32>; 4],
    },
}

/// The composites of a tile's rays, one entry per ray.
pub(crate) struct RayOutputs<'a> {
    /// Colors.
    pub(crate) rgb: &'a mut [[f32; 3]],
    /// Expected depths.
    pub(crate) depth: &'a mut [f32],
    /// Opacities.
    pub(crate) opacity: &'a mut [f32],
}

impl RayOutputs<'_> {
    /// Writes `ray` as the composite of ray `id`.
    #[inline(always)]
    fn write(&mut self, id: usize, ray: RayOutput) {
        (self.rgb[id], self.depth[id], self.opacity[id]) = (ray.rgb, ray.depth, ray.opacity);
    }
}

/// Where the tile's depths are, and the δ of shared ones.
struct TileDepths<'a> {
    depths: Source<'a>,
    /// Rays in the tile.
    n: usize,
    samples: usize,
}

impl TileDepths<'_> {
    /// The depths of the tile's ray `id`.
    #[inline(always)]
    fn column(&self, id: usize) -> DepthColumn<'_> {
        match self.depths {
            Source::Shared(SharedDepths { t, .. }) => DepthColumn {
                t,
                first: 0,
                stride: 1,
                len: self.samples,
            },
            Source::PerRay(t) => DepthColumn {
                t,
                first: id,
                stride: self.n,
                len: self.samples,
            },
        }
    }

    /// The samples of ray `id` whose depths are in [t0, t1], as a range of sample indices.
    fn span(&self, id: usize, t0: f32, t1: f32) -> Range<usize> {
        // A miss: t0 > t1, or NaN.
        if t0.partial_cmp(&t1).is_none_or(|order| order.is_gt()) {
            return 0..0;
        }
        match self.depths {
            Source::Shared(SharedDepths { t, .. }) => {
                samples_before(t, t0, false)..samples_before(t, t1, true)
            }
            Source::PerRay(_) => {
                let column = self.column(id);
                column.count_below(t0, false)..column.count_below(t1, true)
            }
        }
    }
}

/// The number of the sorted, about evenly spaced `depths` below `t` (at most `t` if `inclusive`),
/// found from a guess.
fn samples_before(depths: &[f32], t: f32, inclusive: bool) -> usize {
    let below = |d: f32| d < t || (inclusive && d == t);
    let n = depths.len();
    let inv_step = (n - 1) as f32 / (depths[n - 1] - depths[0]);
    // Depth t is about `position` steps from the first: the guess is its ceiling.
    let position = ((t - depths[0]) * inv_step).clamp(0.0, n as f32);
    let mut i = (position as usize + 1).min(n);
    while i > 0 && !below(depths[i - 1]) {
        i -= 1;
    }
    while i < n && below(depths[i]) {
        i += 1;
    }
    i
}

/// Runs `pass` over the tile's rays loaded in `s` ([`Scratch::load_rays`]) at `depths`: gives each
/// ray's composite or the samples (see [`Output`]). With [`Output::Samples`], returns the indices
/// (sample-major) of the samples evaluated in the order the field evaluated them, or `None` if all
/// were (in the order of their indices).
pub(crate) fn run(pass: &Pass, depths: Depths, s: &mut Scratch, output: Output) -> Option<Vec<usize>> {
    let own_depths = std::mem::take(&mut s.depths);
    let (mut inputs, mut outputs) = (std::mem::take(&mut s.inputs), std::mem::take(&mut s.outputs));
    let source = match depths {
        Depths::Shared(shared) => Source::Shared(shared),
        Depths::PerRay => Source::PerRay(&own_depths[..s.ids.len() * pass.samples]),
    };
    let sink = match output {
        Output::Rays(rays) => Sink::Rays(rays),
        Output::Samples => Sink::Samples {
            inputs: &mut inputs[..pass.field.n_inputs()],
            outputs: &mut outputs,
        },
    };
    let evaluated = run_tile(pass, source, s, sink);
    (s.depths, s.inputs, s.outputs) = (own_depths, inputs, outputs);
    evaluated
}

/// [`run`] with the depths and the place of what it gives out of the scratch.
fn run_tile(pass: &Pass, depths: Source, s: &mut Scratch, mut output: Sink) -> Option<Vec<usize>> {
    let n_tile = s.ids.len();
    let m = pass.samples;
    let c = &pass.compositor;
    let tile = TileDepths {
        depths,
        n: n_tile,
        samples: m,
    };
    let chunk = pass.chunk();
    for v in s.call_inputs.iter_mut().chain(&mut s.call_outputs) {
        grow(v, chunk * n_tile);
    }
    let keep_samples = matches!(output, Sink::Samples { .. });
    // The samples not evaluated are empty space; without a grid and early termination, all are.
    if let Sink::Samples { outputs, .. } = &mut output {
        if pass.grid.is_some() || c.early_termination.is_some() {
            for o in outputs.iter_mut() {
                o[..n_tile * m].fill(0.0);
            }
        }
    }
    // Without rays to report, the composite only tells which rays stop.
    let composite = !keep_samples || c.early_termination.is_some();
    let mut index = Vec::new();
    let mut n = s.ids.len();
    match pass.grid {
        None => {
            s.lanes.reset(n);
            // Every sample is evaluated unless rays stop before the last depths.
            let mut all_evaluated = true;
            for first in (0..m).step_by(chunk) {
                if n == 0 {
                    break;
                }
                let rows = first..(first + chunk).min(m);
                let direct = n == n_tile;
                dense_call(pass, &tile, rows.clone(), s, &mut output, composite);
                if keep_samples {
                    let ids = &s.ids[..n];
                    if direct {
                        index.extend(rows.start * n_tile..rows.end * n_tile);
                    } else {
                        index.extend(
                            rows.clone()
                                .flat_map(|j| ids.iter().map(move |&id| j * n_tile + id)),
                        );
                    }
                }
                if c.early_termination.is_some() {
                    n = compact(c, s, false, &mut output);
                    all_evaluated &= n == n_tile || rows.end == m;
                }
            }
            if keep_samples && all_evaluated {
                return None;
            }
        }
        Some(grid) => {
            cull_rays(pass, grid, &tile, s, &mut output);
            grow(&mut s.samples, chunk * n_tile);
            n = s.ids.len();
            s.lanes.reset(n);
            // Each round takes the next occupied samples of every live ray, as many as keep the
            // field call near PACKED_CALL_POINTS points (all of them without early termination);
            // rays that stopped or have no samples left are done.
            while n > 0 {
                let per_ray = match c.early_termination {
                    Some(_) => (PACKED_CALL_POINTS / n).clamp(1, chunk),
                    None => chunk,
                };
                packed_call(
                    pass,
                    grid,
                    &tile,
                    per_ray,
                    s,
                    &mut output,
                    (composite, &mut index),
                );
                n = compact(c, s, true, &mut output);
            }
        }
    }
    if let Sink::Rays(rays) = &mut output {
        for k in 0..n {
            rays.write(s.ids[k], s.lanes.output(c, k));
        }
    }
    keep_samples.then_some(index)
}

/// The δ of each of `depths`: the gap to the next one, [`LAST_DELTA`] for the last.
pub(crate) fn deltas(depths: &[f32]) -> Vec<f32> {
    let mut deltas: Vec<f32> = depths.windows(2).map(|w| w[1] - w[0]).collect();
    deltas.push(LAST_DELTA);
    deltas
}

/// Drops the rays of the tile that have no sample in the stretch where they may meet occupied cells
/// ([`OccupancyGrid::occupied_stretch`]; done: the empty ray) and notes the samples each remaining ray
/// has there (`s.spans`).
fn cull_rays(pass: &Pass, grid: &OccupancyGrid, tile: &TileDepths, s: &mut Scratch, output: &mut Sink) {
    let n = s.ids.len();
    grow(&mut s.spans, n);
    for v in &mut s.intervals {
        grow(v, n);
    }
    let [ox, oy, oz] = &mut s.origins;
    let [dx, dy, dz] = &mut s.directions;
    let [t0, t1] = &mut s.intervals;
    grid.ray_intervals(
        [&ox[..n], &oy[..n], &oz[..n]],
        [&dx[..n], &dy[..n], &dz[..n]],
        t0,
        t1,
    );
    let mut live = 0;
    for k in 0..n {
        let id = s.ids[k];
        let (a, b) = grid.occupied_stretch([ox[k], oy[k], oz[k]], [dx[k], dy[k], dz[k]], (t0[k], t1[k]));
        let span = tile.span(id, a, b);
        if span.start < span.end {
            for v in [&mut *ox, &mut *oy, &mut *oz, &mut *dx, &mut *dy, &mut *dz] {
                v[live] = v[k];
            }
            s.ids[live] = id;
            s.spans[live] = [span.start as u32, span.end as u32];
            live += 1;
        } else if let Sink::Rays(rays) = output {
            rays.write(id, pass.compositor.empty_ray());
        }
    }
    s.ids.truncate(live);
}

/// Evaluates the field at the samples `rows` of the tile's live rays, sample-major, and composites
/// them across rays (if `composite`) or keeps them ([`Sink::Samples`]): straight into the tile's
/// buffers while no ray has stopped, else scattered there.
fn dense_call(
    pass: &Pass,
    tile: &TileDepths,
    rows: Range<usize>,
    s: &mut Scratch,
    output: &mut Sink,
    composite: bool,
) {
    let n = s.ids.len();
    let len = rows.len() * n;
    let n_inputs = pass.field.n_inputs();
    let direct = n == tile.n;
    let Scratch {
        origins: [ox, oy, oz],
        shared_origin,
        directions: [dx, dy, dz],
        ids,
        call_inputs,
        call_outputs,
        call_depths: [call_t, call_delta],
        lanes,
        ..
    } = s;
    if matches!(tile.depths, Source::PerRay(_)) && composite {
        grow(call_t, len);
        grow(call_delta, len);
    }
    {
        let (mut inputs, mut outputs): ([&mut [f32]; 6], [&mut [f32]; 4]) = match output {
            Sink::Samples { inputs, outputs } if direct => {
                let span = rows.start * n..rows.end * n;
                (
                    slices(inputs.iter_mut(), span.clone()),
                    slices(outputs.iter_mut(), span),
                )
            }
            _ => (
                slices(call_inputs[..n_inputs].iter_mut(), 0..len),
                slices(call_outputs.iter_mut(), 0..len),
            ),
        };
        let [x, y, z, vx, vy, vz] = &mut inputs;
        for (jj, j) in rows.clone().enumerate() {
            let row = jj * n..(jj + 1) * n;
            // Slices of length n, so that the loops below have no bounds checks and vectorize.
            let (x, y, z) = (
                &mut x[row.clone()][..n],
                &mut y[row.clone()][..n],
                &mut z[row.clone()][..n],
            );
            let (ox, oy, oz, dx, dy, dz) = (&ox[..n], &oy[..n], &oz[..n], &dx[..n], &dy[..n], &dz[..n]);
            match tile.depths {
                Source::Shared(SharedDepths { t, .. }) => {
                    let t = t[j];
                    if let Some(o) = shared_origin {
                        for k in 0..n {
                            x[k] = o[0] + dx[k] * t;
                            y[k] = o[1] + dy[k] * t;
                            z[k] = o[2] + dz[k] * t;
                        }
                    } else {
                        for k in 0..n {
                            x[k] = ox[k] + dx[k] * t;
                            y[k] = oy[k] + dy[k] * t;
                            z[k] = oz[k] + dz[k] * t;
                        }
                    }
                }
                Source::PerRay(_) => {
                    for k in 0..n {
                        let column = tile.column(ids[k]);
                        let t = column.at(j);
                        x[k] = ox[k] + dx[k] * t;
                        y[k] = oy[k] + dy[k] * t;
                        z[k] = oz[k] + dz[k] * t;
                        if composite {
                            (call_t[jj * n + k], call_delta[jj * n + k]) = (t, column.delta(j));
                        }
                    }
                }
            }
            if n_inputs == 6 {
                vx[row.clone()].copy_from_slice(dx);
                vy[row.clone()].copy_from_slice(dy);
                vz[row].copy_from_slice(dz);
            }
        }
        let ins = inputs.each_ref().map(|c| &**c);
        pass.field.eval(len, &ins[..n_inputs], &mut outputs);
        if composite {
            let (raw, rgb) = (&*outputs[0], [&*outputs[1], &*outputs[2], &*outputs[3]]);
            match tile.depths {
                Source::Shared(SharedDepths { t, delta }) => {
                    lanes.add(&pass.compositor, &t[rows.clone()], &delta[rows.clone()], raw, rgb)
                }
                Source::PerRay(_) => {
                    lanes.add_each(&pass.compositor, &call_t[..len], &call_delta[..len], raw, rgb)
                }
            }
        }
    }
    if let Sink::Samples { inputs, outputs } = output {
        if !direct {
            for (jj, j) in rows.enumerate() {
                for (k, &id) in ids[..n].iter().enumerate() {
                    let (to, from) = (j * tile.n + id, jj * n + k);
                    for (dense, call) in inputs.iter_mut().zip(call_inputs.iter()) {
                        dense[to] = call[from];
                    }
                    for (dense, call) in outputs.iter_mut().zip(call_outputs.iter()) {
                        dense[to] = call[from];
                    }
                }
            }
        }
    }
}

/// Evaluates the field at the next `per_ray` occupied samples of each of the tile's live rays (only
/// those in the rays' spans can be; each ray's span starts past what earlier calls took), packed ray
/// by ray into one call, and composites them ray by ray (if `composite`; the skipped samples have
/// alpha 0, which changes nothing) or keeps them ([`Sink::Samples`], their indices added to `index`).
fn packed_call(
    pass: &Pass,
    grid: &OccupancyGrid,
    tile: &TileDepths,
    per_ray: usize,
    s: &mut Scratch,
    output: &mut Sink,
    (composite, index): (bool, &mut Vec<usize>),
) {
    let n = s.ids.len();
    let n_inputs = pass.field.n_inputs();
    let Scratch {
        origins: [ox, oy, oz],
        directions: [dx, dy, dz],
        ids,
        spans,
        call_inputs,
        call_outputs,
        samples,
        ends,
        lanes,
        ..
    } = s;
    let [x, y, z, vx, vy, vz] = call_inputs;
    let mut packed = 0;
    ends.clear();
    // Ray by ray, the next occupied samples from the start of its span, at most `per_ray`; the
    // packed samples of ray k end at ends[k], and its span starts after the last sample looked at.
    for k in 0..n {
        let [a, b] = spans[k].map(|i| i as usize);
        let (o, d) = ([ox[k], oy[k], oz[k]], [dx[k], dy[k], dz[k]]);
        let first_packed = packed;
        let end = packed + per_ray;
        let column = tile.column(ids[k]);
        let (found, next) = grid.next_occupied(
            (o, d),
            a..b,
            |j| column.at(j),
            [&mut x[packed..end], &mut y[packed..end], &mut z[packed..end]],
            &mut samples[packed..end],
        );
        packed += found;
        spans[k][0] = next as u32;
        if n_inputs == 6 {
            vx[first_packed..packed].fill(dx[k]);
            vy[first_packed..packed].fill(dy[k]);
            vz[first_packed..packed].fill(dz[k]);
        }
        ends.push(packed as u32);
    }
    if packed == 0 {
        return;
    }
    let inputs = [&*x, &*y, &*z, &*vx, &*vy, &*vz].map(|c| &c[..packed]);
    let inputs = &inputs[..n_inputs];
    pass.field.eval(
        packed,
        inputs,
        &mut slices::<4>(call_outputs.iter_mut(), 0..packed),
    );
    let [raw, r, g, b] = call_outputs;
    let mut start = 0;
    for (k, &end) in ends.iter().enumerate() {
        let end = end as usize;
        if start < end {
            let at = start..end;
            if composite {
                let (index, raw) = (&samples[at.clone()], &raw[at.clone()]);
                let rgb = [&r[at.clone()], &g[at.clone()], &b[at.clone()]];
                match tile.depths {
                    Source::Shared(t) => lanes.add_sparse(&pass.compositor, k, index, t, raw, rgb),
                    Source::PerRay(_) => {
                        lanes.add_sparse(&pass.compositor, k, index, tile.column(ids[k]), raw, rgb)
                    }
                }
            }
            if let Sink::Samples {
                inputs: dense_inputs,
                outputs: dense_outputs,
            } = output
            {
                for i in at {
                    let to = samples[i] as usize * tile.n + ids[k];
                    index.push(to);
                    for (dense, call) in dense_inputs.iter_mut().zip(inputs) {
                        dense[to] = call[i];
                    }
                    for (dense, call) in dense_outputs.iter_mut().zip([&*raw, &*r, &*g, &*b]) {
                        dense[to] = call[i];
                    }
                }
            }
        }
        start = end;
    }
}

/// The entries `range` of `columns`, then empty slices up to `N`.
fn slices<'a, const N: usize>(
    columns: impl Iterator<Item = &'a mut Vec<f32>>,
    range: Range<usize>,
) -> [&'a mut [f32]; N] {
    let mut out: [&mut [f32]; N] = std::array::from_fn(|_| <&mut [f32]>::default());
    for (slice, column) in out.iter_mut().zip(columns) {
        *slice = &mut column[range.clone()];
    }
    out
}

/// Compaction: the rays that have stopped (or, with `spans`, have no samples left in their span) are
/// done; the others move to the front, so that the next field call sees live rays only. Returns the
/// number of live rays.
fn compact(c: &Compositor, s: &mut Scratch, spans: bool, output: &mut Sink) -> usize {
    let n = s.ids.len();
    let mut live = 0;
    for k in 0..n {
        let id = s.ids[k];
        let samples_left = !spans || s.spans[k][0] < s.spans[k][1];
        if samples_left && s.lanes.is_live(c, k) {
            s.lanes.move_ray(k, live);
            s.ids[live] = id;
            for v in s.origins.iter_mut().chain(&mut s.directions) {
                v[live] = v[k];
            }
            if spans {
                s.spans[live] = s.spans[k];
            }
            live += 1;
        } else if let Sink::Rays(rays) = output {
            rays.write(id, s.lanes.output(c, k));
        }
    }
    s.lanes.truncate(live);
    s.ids.truncate(live);
    live
}

/// The backward pass of `vjp` at the samples `index` only (all of them for `None`), with the samples'
/// cotangents: adds to `grads`.
pub(crate) fn backward(
    vjp: &dyn BatchVjp,
    inputs: &[&[f32]],
    index: Option<&[usize]>,
    cotangents: &[&[f32]; 4],
    grads: &mut [f32],
) {
    let Some(index) = index else {
        vjp.vjp(cotangents[0].len(), inputs, cotangents, grads);
        return;
    };
    let ins = gather(inputs, index);
    let cots = gather(cotangents, index);
    let ins: Vec<&[f32]> = ins.iter().map(Vec::as_slice).collect();
    let cots: Vec<&[f32]> = cots.iter().map(Vec::as_slice).collect();
    vjp.vjp(index.len(), &ins, &cots, grads);
}

/// The entries `index` of each column.
pub(crate) fn gather(columns: &[&[f32]], index: &[usize]) -> Vec<Vec<f32>> {
    columns
        .iter()
        .map(|c| index.iter().map(|&i| c[i]).collect())
        .collect()
}

/// Replaces the coarse depths of the tile's `n` rays in `s.depths` (sample-major) by their fine depths:
/// merged with `importance` depths drawn from the coarse weights (the coarse values in `s.outputs[0]`),
/// stratified with `jitter` (a generator per ray), else at the centers of equal-probability bins. Each ray's column is read
/// whole before it is written, so the other rays' coarse depths stay in place.
pub(crate) fn draw_fine_depths(
    coarse: &VolumeSettings,
    importance: usize,
    s: &mut Scratch,
    n: usize,
    mut jitter: Option<&mut [Rng]>,
) {
    let m = coarse.samples;
    let compositor = coarse.compositor();
    let total = m + importance;
    s.reserve(n * total, n);
    let (mut t, mut raw, mut w) = (vec![0.0; m], vec![0.0; m], vec![0.0; m]);
    let (mut u, mut drawn, mut merged) = (Vec::new(), vec![0.0; importance], vec![0.0; total]);
    if jitter.is_none() {
        importance::quantiles(importance, None, &mut u);
    }
    for k in 0..n {
        for j in 0..m {
            t[j] = s.depths[j * n + k];
            raw[j] = s.outputs[0][j * n + k];
        }
        importance::ray_weights(&compositor, &t, &raw, &mut w);
        if let Some(rngs) = jitter.as_deref_mut() {
            let rng = &mut rngs[k];
            importance::quantiles(importance, Some(&mut || rng.next_f32()), &mut u);
        }
        importance::inverse_cdf(coarse.near, coarse.far, &t, &w, &u, &mut drawn);
        importance::merge_sorted(&t, &drawn, &mut merged);
        for (j, &d) in merged.iter().enumerate() {
            s.depths[j * n + k] = d;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cameras::camera::Camera;
    use crate::field::{ClosureFn, ClosureVjp};
    use crate::volume::composite::{Mode, RayOutput, Samples};
    use crate::volume::model::{CoarsePass, TrainableModel, VolumeModel};
    use crate::volume::render::VolumeFrame;
    use crate::volume::sampler::DepthSpacing;
    use crate::volume::train::StepWorkspace;
    use glam::{Vec2, Vec3};

    /// A view-dependent field: a dense ball (density 30 within 0.7 of the center) in a faint halo
    /// (density `halo` within 1.1) colored by position and view direction; nothing elsewhere.
    fn ball(p: &[f32], halo: f32) -> [f32; 4] {
        let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        let density = if r < 0.7 {
            30.0
        } else if r < 1.1 {
            halo
        } else {
            0.0
        };
        let shade = |x: f32| 0.5 + 0.4 * x.clamp(-1.0, 1.0);
        [density, shade(p[0]), shade(p[1] * p[4]), shade(p[2] + p[5])]
    }

    /// What the field of `halo` is where the grid (if any) marks empty: empty space.
    fn cut(p: &[f32], halo: f32, grid: Option<&OccupancyGrid>) -> [f32; 4] {
        match grid {
            Some(g) if !g.occupied([p[0], p[1], p[2]]) => [0.0; 4],
            _ => ball(p, halo),
        }
    }

    /// The exact composite of one ray (origin `o`, direction `d`) of the field cut to the grid at
    /// depths `t`.
    fn composite(
        c: &Compositor,
        o: [f32; 3],
        d: [f32; 3],
        t: &[f32],
        halo: f32,
        grid: Option<&OccupancyGrid>,
    ) -> RayOutput {
        let values: Vec<[f32; 4]> = t
            .iter()
            .map(|&t| {
                let p = [o[0] + d[0] * t, o[1] + d[1] * t, o[2] + d[2] * t];
                cut(&[p[0], p[1], p[2], d[0], d[1], d[2]], halo, grid)
            })
            .collect();
        let column = |i: usize| values.iter().map(|v| v[i]).collect::<Vec<f32>>();
        let (raw, r, g, b) = (column(0), column(1), column(2), column(3));
        c.forward(&Samples::new(t, &raw, [&r, &g, &b]).unwrap())
    }

    /// The fine depths of one ray, from the exact coarse composite's weights (see
    /// [`importance::ray_weights`]) at the bin centers.
    fn fine_depths(
        settings: &VolumeSettings,
        importance: usize,
        o: [f32; 3],
        d: [f32; 3],
        grid: Option<&OccupancyGrid>,
    ) -> Vec<f32> {
        let mut t = vec![0.0; settings.samples];
        settings.fixed_depths(&mut t);
        let raw: Vec<f32> = t
            .iter()
            .map(|&t| {
                cut(
                    &[
                        o[0] + d[0] * t,
                        o[1] + d[1] * t,
                        o[2] + d[2] * t,
                        d[0],
                        d[1],
                        d[2],
                    ],
                    0.5,
                    grid,
                )[0]
            })
            .collect();
        let mut w = vec![0.0; t.len()];
        importance::ray_weights(&settings.compositor(), &t, &raw, &mut w);
        let (mut u, mut drawn) = (Vec::new(), vec![0.0; importance]);
        importance::quantiles(importance, None, &mut u);
        importance::inverse_cdf(settings.near, settings.far, &t, &w, &u, &mut drawn);
        let mut merged = vec![0.0; t.len() + importance];
        importance::merge_sorted(&t, &drawn, &mut merged);
        merged
    }

    /// The samples of a ray inside an interval: the partition points of its depths, shared (found
    /// from a guess) or its own (by bisection, in a sample-major tile).
    #[test]
    fn sample_spans_are_partition_points_of_the_depths() {
        for (near, far, samples) in [(0.0, 5.0, 64), (1.0, 5.0, 96), (0.3, 0.7, 2), (2.0, 1e4, 1000)] {
            let mut depths = vec![0.0; samples];
            crate::volume::sampler::linspace(near, far, &mut depths);
            // Ray 1 of a tile of 3 rays: its own depths between two other rays' depths.
            let tile: Vec<f32> = depths.iter().flat_map(|&d| [d - 0.5, d, d + 0.5]).collect();
            let column = DepthColumn {
                t: &tile,
                first: 1,
                stride: 3,
                len: samples,
            };
            let mut ts: Vec<f32> = depths
                .iter()
                .flat_map(|&d| [d, d.next_up(), d.next_down()])
                .collect();
            ts.extend([
                -1.0,
                near - 1.0,
                far + 1.0,
                f32::INFINITY,
                f32::NEG_INFINITY,
                0.5 * (near + far),
            ]);
            for t in ts {
                let below = depths.partition_point(|&d| d < t);
                let at_most = depths.partition_point(|&d| d <= t);
                assert_eq!(samples_before(&depths, t, false), below, "{t}");
                assert_eq!(samples_before(&depths, t, true), at_most, "{t}");
                assert_eq!(column.count_below(t, false), below, "{t}");
                assert_eq!(column.count_below(t, true), at_most, "{t}");
            }
        }
    }

    /// Under early termination, a pass that keeps its samples lists exactly the samples it evaluated:
    /// none past the chunk where every ray stopped, and all of them (`None`) only when nothing stopped
    /// before the last depths.
    #[test]
    fn rounds_of_few_samples_a_ray_give_the_exact_composite() {
        // More rays than PACKED_CALL_POINTS in one tile: the first rounds take one occupied sample a
        // ray, later ones more as rays stop; the composites are the exact ones, bit for bit, and
        // no ray is evaluated past the round in which it stopped.
        let camera = Camera::look_at(
            Vec3::new(0.3, -0.2, -3.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::splat(1.3),
            Vec2::ZERO,
        )
        .unwrap();
        let rays = RayBatch::full_image(&camera, 128, 80).unwrap();
        let n = rays.len();
        assert!(n > 2 * PACKED_CALL_POINTS);
        let evaluated = std::sync::atomic::AtomicUsize::new(0);
        let field = ClosureFn::new(6, 4, |p, out| {
            evaluated.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            out.copy_from_slice(&ball(p, 0.5))
        });
        let grid = OccupancyGrid::build(&field, ([-1.5; 3], [1.5; 3]), 24, Mode::Density, 0.0).unwrap();
        let m = 64;
        let mut depths = vec![0.0; m];
        crate::volume::sampler::linspace(1.5, 4.5, &mut depths);
        let deltas = deltas(&depths);
        let shared = SharedDepths {
            t: &depths,
            delta: &deltas,
        };
        for stop in [1e-1, 1e-4] {
            let c = Compositor {
                mode: Mode::Density,
                background: Some([0.2, 0.3, 0.4]),
                early_termination: Some(stop),
            };
            let pass = Pass {
                field: &field,
                compositor: c,
                grid: Some(&grid),
                samples: m,
            };
            let mut s = Scratch::default();
            s.reserve(n * m, n);
            s.load_rays(&rays, 0, n);
            let (mut rgb, mut depth, mut opacity) = (vec![[0.0; 3]; n], vec![0.0; n], vec![0.0; n]);
            evaluated.store(0, std::sync::atomic::Ordering::Relaxed);
            let out = RayOutputs {
                rgb: &mut rgb,
                depth: &mut depth,
                opacity: &mut opacity,
            };
            run(&pass, Depths::Shared(shared), &mut s, Output::Rays(out));
            let evaluated = evaluated.load(std::sync::atomic::Ordering::Relaxed);
            // The samples the exact composite counts: occupied, and before the ray stopped.
            let mut counted = 0;
            for k in 0..n {
                let (o, d) = (
                    [rays.ox[k], rays.oy[k], rays.oz[k]],
                    [rays.dx[k], rays.dy[k], rays.dz[k]],
                );
                let e = composite(&c, o, d, &depths, 0.5, Some(&grid));
                assert_eq!(
                    (rgb[k], depth[k], opacity[k]),
                    (e.rgb, e.depth, e.opacity),
                    "ray {k}"
                );
                let mut trans = 1.0f32;
                for (j, &t) in depths.iter().enumerate() {
                    let p = [o[0] + d[0] * t, o[1] + d[1] * t, o[2] + d[2] * t];
                    if trans < stop {
                        break;
                    }
                    if grid.occupied(p) {
                        counted += 1;
                        trans *= (-ball(&[p[0], p[1], p[2], d[0], d[1], d[2]], 0.5)[0] * deltas[j]).exp();
                    }
                }
            }
            // A ray evaluates at most PACKED_CHUNK_SAMPLES − 1 samples past where it stops, and only
            // in the rounds with fewer than PACKED_CALL_POINTS / 2 rays live, which take more than one.
            let slack = (PACKED_CHUNK_SAMPLES - 1) * PACKED_CALL_POINTS / 2;
            assert!(
                counted <= evaluated && evaluated <= counted + slack,
                "stop {stop}: {evaluated} evaluated, {counted} counted"
            );
        }
    }

    #[test]
    fn kept_samples_list_what_was_evaluated_when_rays_stop() {
        let camera = Camera::look_at(
            Vec3::new(0.0, 0.0, -3.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::splat(1.0),
            Vec2::ZERO,
        )
        .unwrap();
        let rays = RayBatch::full_image(&camera, 8, 4).unwrap();
        let n = rays.len();
        let (m, stop) = (40, 1e-2);
        let mut depths = vec![0.0; m];
        crate::volume::sampler::linspace(2.0, 4.0, &mut depths);
        let deltas = deltas(&depths);
        let shared = SharedDepths {
            t: &depths,
            delta: &deltas,
        };
        for (density, stopped) in [(1e3, true), (1e-3, false)] {
            let field = ClosureFn::new(3, 4, move |_, out| out.copy_from_slice(&[density, 0.5, 0.5, 0.5]));
            let pass = Pass {
                field: &field,
                compositor: Compositor {
                    mode: Mode::Density,
                    background: None,
                    early_termination: Some(stop),
                },
                grid: None,
                samples: m,
            };
            let mut s = Scratch::default();
            s.reserve(n * m, n);
            s.load_rays(&rays, 0, n);
            let index = run(&pass, Depths::Shared(shared), &mut s, Output::Samples);
            let outputs = &s.outputs;
            if stopped {
                // Every ray is opaque from its first sample: only the first chunk was evaluated.
                let want: Vec<usize> = (0..CHUNK_SAMPLES * n).collect();
                assert_eq!(index.as_deref(), Some(&want[..]));
                assert!(outputs[0][CHUNK_SAMPLES * n..n * m].iter().all(|&v| v == 0.0));
            } else {
                assert_eq!(index, None);
                assert!(outputs[0][..n * m].iter().all(|&v| v == density));
            }
        }
    }

    /// Every caller of the volume pass (render, hierarchical render, training step), with and without an
    /// occupancy grid and early termination, gives the exact composite of the field cut to the grid:
    /// the renders bit for bit, the step's loss to rounding.
    #[test]
    fn every_pass_agrees_with_the_exact_composite_in_every_combination() {
        let camera = Camera::look_at(
            Vec3::new(0.4, 0.3, -3.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::splat(1.2),
            Vec2::ZERO,
        )
        .unwrap();
        let (width, height) = (20u32, 16u32);
        let rays = RayBatch::full_image(&camera, width, height).unwrap();
        // The coarse field's halo is fainter than the fine field's: the two fields differ.
        let coarse = ClosureFn::new(6, 4, |p, out| out.copy_from_slice(&ball(p, 0.5)));
        let fine = ClosureFn::new(6, 4, |p, out| out.copy_from_slice(&ball(p, 2.0)));
        let no_vjp = ClosureVjp::new(6, 4, 1, |_, _, _| {});
        let grid = OccupancyGrid::build(&fine, ([-1.5; 3], [1.5; 3]), 24, Mode::Density, 0.0).unwrap();
        assert!(grid.occupancy() < 0.5, "{}", grid.occupancy());
        let targets: Vec<[f32; 3]> = (0..rays.len())
            .map(|i| [0.1 * (i % 7) as f32, 0.5, 0.3])
            .collect();
        let importance = 24;
        for grid in [None, Some(&grid)] {
            for early_termination in [None, Some(1e-2)] {
                let settings = VolumeSettings {
                    spacing: DepthSpacing::Linear,
                    near: 1.5,
                    far: 4.5,
                    samples: 40,
                    mode: Mode::Density,
                    background: Some([0.2, 0.3, 0.4]),
                    early_termination,
                };
                let c = settings.compositor();
                let mut fixed = vec![0.0; settings.samples];
                settings.fixed_depths(&mut fixed);
                let ray = |k: usize| {
                    (
                        [rays.ox[k], rays.oy[k], rays.oz[k]],
                        [rays.dx[k], rays.dy[k], rays.dz[k]],
                    )
                };
                let exact: Vec<RayOutput> = (0..rays.len())
                    .map(|k| composite(&c, ray(k).0, ray(k).1, &fixed, 2.0, grid))
                    .collect();
                let exact_fine: Vec<RayOutput> = (0..rays.len())
                    .map(|k| {
                        let (o, d) = ray(k);
                        composite(
                            &c,
                            o,
                            d,
                            &fine_depths(&settings, importance, o, d, grid),
                            2.0,
                            grid,
                        )
                    })
                    .collect();
                let case = format!("grid {}, early termination {early_termination:?}", grid.is_some());
                let same = |frame: &VolumeFrame, exact: &[RayOutput], what: &str| {
                    for (k, e) in exact.iter().enumerate() {
                        let got = (frame.rgb[k], frame.depth[k], frame.opacity[k]);
                        assert_eq!(got, (e.rgb, e.depth, e.opacity), "{what}, {case}, ray {k}");
                    }
                };
                let plain = VolumeModel {
                    field: &fine,
                    coarse: None,
                };
                let hierarchical = VolumeModel {
                    field: &fine,
                    coarse: Some((&coarse, importance)),
                };
                let size = (width, height);
                same(
                    &plain.render(&camera, size, &settings, grid).unwrap(),
                    &exact,
                    "render",
                );
                same(
                    &hierarchical.render(&camera, size, &settings, grid).unwrap(),
                    &exact_fine,
                    "hierarchical render",
                );
                // Training's loss is the MSE of the same composites.
                let mse = |exact: &[RayOutput]| {
                    let sum: f64 = exact
                        .iter()
                        .zip(&targets)
                        .map(|(e, t)| (0..3).map(|i| f64::from(e.rgb[i] - t[i]).powi(2)).sum::<f64>())
                        .sum();
                    (sum / (3.0 * rays.len() as f64)) as f32
                };
                let mut workspace = StepWorkspace::default();
                let plain = TrainableModel {
                    field: &fine,
                    vjp: &no_vjp,
                    coarse: None,
                    recompute_forward: false,
                    appearance: None,
                    distortion: 0.0,
                };
                let step = plain
                    .step(&rays, &targets, &settings, grid, None, &mut workspace)
                    .unwrap();
                assert!(
                    (step.loss - mse(&exact)).abs() <= 1e-6 * mse(&exact),
                    "training, {case}: {} vs {}",
                    step.loss,
                    mse(&exact)
                );
                let hierarchical = TrainableModel {
                    field: &fine,
                    vjp: &no_vjp,
                    coarse: Some(CoarsePass {
                        field: &coarse,
                        vjp: &no_vjp,
                        importance,
                    }),
                    recompute_forward: false,
                    appearance: None,
                    distortion: 0.0,
                };
                let step = hierarchical
                    .step(&rays, &targets, &settings, grid, None, &mut workspace)
                    .unwrap();
                let want = mse(&exact_fine);
                assert!(
                    (step.loss - want).abs() <= 1e-6 * want,
                    "hierarchical training, {case}: {} vs {want}",
                    step.loss
                );
            }
        }
    }
}
