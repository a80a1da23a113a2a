//! The volume pass of a tile of rays with depths of their own: the work that training steps
//! ([`crate::volume::train`]) and hierarchical renders ([`crate::volume::hierarchical`]) share.
//!
//! A tile is `n` consecutive rays of a [`RayBatch`] with `m` depths each, laid out sample-major
//! (sample j of ray k at `j·n + k`) in the worker's [`Scratch`]. [`sample_points`] turns the depths into
//! the field's inputs; [`evaluate`] calls the field at the samples that can contribute: with an
//! [`OccupancyGrid`] only those in occupied cells, with early termination only those of rays whose
//! transmittance is still above the threshold, [`CHUNK_SAMPLES`] depths at a time (the other samples are
//! empty space: all outputs 0); [`forward`] does both. The samples are then composited across rays by
//! the compositor's `Lanes`: forward only in hierarchical renders, forward and backward in training,
//! whose field gradient [`backward`] takes at the evaluated samples. [`draw_fine_depths`] draws the fine
//! depths of hierarchical sampling from a coarse pass.

use crate::cameras::rays::RayBatch;
use crate::field::{BatchFn, BatchVjp};
use crate::rng::Rng;
use crate::volume::composite::{Compositor, LAST_DELTA};
use crate::volume::importance;
use crate::volume::occupancy::OccupancyGrid;
use crate::volume::render::{Scratch, VolumeSettings, CHUNK_SAMPLES};

/// Writes the field inputs of the tile's `len` samples (rays `first..first + n`, depths
/// `s.depths[..len]`) into `s.inputs`: the points, then the ray directions when `view_dependent`.
fn sample_points(rays: &RayBatch, first: usize, n: usize, len: usize, view_dependent: bool, s: &mut Scratch) {
    let Scratch {
        inputs: [x, y, z, vx, vy, vz],
        depths,
        ..
    } = s;
    let tile = first..first + n;
    let (ox, oy, oz) = (
        &rays.ox[tile.clone()],
        &rays.oy[tile.clone()],
        &rays.oz[tile.clone()],
    );
    let (dx, dy, dz) = (&rays.dx[tile.clone()], &rays.dy[tile.clone()], &rays.dz[tile]);
    for (j, t) in depths[..len].chunks_exact(n).enumerate() {
        let row = j * n..(j + 1) * n;
        let (x, y, z) = (&mut x[row.clone()], &mut y[row.clone()], &mut z[row.clone()]);
        for k in 0..n {
            x[k] = ox[k] + dx[k] * t[k];
            y[k] = oy[k] + dy[k] * t[k];
            z[k] = oz[k] + dz[k] * t[k];
        }
        if view_dependent {
            vx[row.clone()].copy_from_slice(dx);
            vy[row.clone()].copy_from_slice(dy);
            vz[row].copy_from_slice(dz);
        }
    }
}

/// The forward pass of `field` over the tile's rays `first..first + n` at the `settings.samples` depths
/// each in `s.depths`: the inputs into `s.inputs`, the outputs into `s.outputs` (see [`evaluate`]);
/// returns the samples evaluated (`None`: all).
pub(crate) fn forward(
    field: &dyn BatchFn,
    settings: &VolumeSettings,
    grid: Option<&OccupancyGrid>,
    (rays, first, n): (&RayBatch, usize, usize),
    s: &mut Scratch,
) -> Option<Vec<usize>> {
    let len = n * settings.samples;
    let n_inputs = field.n_inputs();
    sample_points(rays, first, n, len, n_inputs == 6, s);
    let Scratch {
        inputs,
        outputs: [raw, r, g, b],
        depths,
        ..
    } = s;
    let inputs: Vec<&[f32]> = inputs[..n_inputs].iter().map(|c| &c[..len]).collect();
    let outputs = [&mut raw[..len], &mut r[..len], &mut g[..len], &mut b[..len]];
    evaluate(
        field,
        &settings.compositor(),
        grid,
        &inputs,
        &depths[..len],
        n,
        outputs,
    )
}

/// Evaluates `field` at the tile's samples (sample-major, `n` rays) that can contribute, writing zeros
/// (empty space) for the others; returns the indices evaluated, or `None` if all were. With a grid,
/// samples in its empty cells are skipped. With early termination, the depths go in groups of
/// [`CHUNK_SAMPLES`] and a group evaluates only the rays whose transmittance before it is still at the
/// threshold: every sample the compositor counts is evaluated.
pub(crate) fn evaluate(
    field: &dyn BatchFn,
    compositor: &Compositor,
    grid: Option<&OccupancyGrid>,
    inputs: &[&[f32]],
    depths: &[f32],
    n: usize,
    mut outputs: [&mut [f32]; 4],
) -> Option<Vec<usize>> {
    let len = depths.len();
    let occupied = |i: usize| grid.is_none_or(|g| g.occupied([inputs[0][i], inputs[1][i], inputs[2][i]]));
    let Some(threshold) = compositor.early_termination else {
        if grid.is_none() {
            let [raw, r, g, b] = outputs;
            field.eval(len, inputs, &mut [raw, r, g, b]);
            return None;
        }
        let index: Vec<usize> = (0..len).filter(|&i| occupied(i)).collect();
        eval_at(field, inputs, &index, outputs);
        return Some(index);
    };
    let rows = len / n;
    let mut transmittance = vec![1.0f32; n];
    let mut index = Vec::with_capacity(len);
    for group in (0..rows).step_by(CHUNK_SAMPLES) {
        let group = group..(group + CHUNK_SAMPLES).min(rows);
        let start = index.len();
        for j in group.clone() {
            let live = (0..n).filter(|&k| transmittance[k] >= threshold);
            index.extend(live.map(|k| j * n + k).filter(|&i| occupied(i)));
        }
        let span = group.start * n..group.end * n;
        let part = outputs.each_mut().map(|o| &mut o[span.clone()]);
        let local: Vec<usize> = index[start..].iter().map(|&i| i - span.start).collect();
        let inputs_here: Vec<&[f32]> = inputs.iter().map(|c| &c[span.clone()]).collect();
        eval_at(field, &inputs_here, &local, part);
        for j in group {
            for (k, trans) in transmittance.iter_mut().enumerate() {
                let i = j * n + k;
                let delta = if j + 1 < rows {
                    depths[i + n] - depths[i]
                } else {
                    LAST_DELTA
                };
                *trans *= compositor.alpha(outputs[0][i], delta).1;
            }
        }
    }
    Some(index)
}

/// Evaluates `field` at the samples `index` of the columns `inputs` (gathered into one dense call) and
/// scatters the results into `outputs`, which are zero elsewhere.
fn eval_at(field: &dyn BatchFn, inputs: &[&[f32]], index: &[usize], outputs: [&mut [f32]; 4]) {
    let m = index.len();
    let gathered = gather(inputs, index);
    let ins: Vec<&[f32]> = gathered.iter().map(Vec::as_slice).collect();
    let mut packed: [Vec<f32>; 4] = std::array::from_fn(|_| vec![0.0; m]);
    let mut refs: Vec<&mut [f32]> = packed.iter_mut().map(Vec::as_mut_slice).collect();
    if m > 0 {
        field.eval(m, &ins, &mut refs);
    }
    for (out, values) in outputs.into_iter().zip(&packed) {
        out.fill(0.0);
        for (&i, &v) in index.iter().zip(values) {
            out[i] = v;
        }
    }
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
fn gather(columns: &[&[f32]], index: &[usize]) -> Vec<Vec<f32>> {
    columns
        .iter()
        .map(|c| index.iter().map(|&i| c[i]).collect())
        .collect()
}

/// Replaces the coarse depths of the tile's `n` rays in `s.depths` (sample-major) by their fine depths:
/// merged with `importance` depths drawn from the coarse weights (the coarse values in `s.outputs[0]`),
/// stratified with `jitter`, else at the centers of equal-probability bins. Each ray's column is read
/// whole before it is written, so the other rays' coarse depths stay in place.
pub(crate) fn draw_fine_depths(
    coarse: &VolumeSettings,
    importance: usize,
    s: &mut Scratch,
    n: usize,
    mut jitter: Option<&mut Rng>,
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
        if let Some(rng) = jitter.as_deref_mut() {
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
    use crate::volume::model::{TrainableModel, VolumeModel};
    use crate::volume::render::VolumeFrame;
    use crate::volume::sampler::DepthSpacing;
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
                let plain = TrainableModel {
                    field: (&fine, &no_vjp),
                    coarse: None,
                };
                let step = plain.step((&rays, &targets), &settings, grid, None).unwrap();
                assert!(
                    (step.loss - mse(&exact)).abs() <= 1e-6 * mse(&exact),
                    "training, {case}: {} vs {}",
                    step.loss,
                    mse(&exact)
                );
                let hierarchical = TrainableModel {
                    field: (&fine, &no_vjp),
                    coarse: Some((&coarse, &no_vjp, importance)),
                };
                let step = hierarchical
                    .step((&rays, &targets), &settings, grid, None)
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
