//! The gradients of a step: the caller's [`StepWorkspace`], which keeps the tasks' accumulators and the last
//! gradient from step to step, and the sum of the accumulators, element by element in task order, so that a
//! step gives the same bits on any number of threads.

use std::ops::Range;

use rayon::prelude::*;

/// The memory a run's training steps share, passed to each step: the gradient of the last step, and
/// accumulators kept from earlier steps (a hash grid's gradient has millions of entries: fresh memory
/// every step would be faulted in page by page). The sum of a step's accumulators zeroes each one it
/// adds as it reads it, so the next step need not clear them in a pass of its own.
#[derive(Debug, Default)]
pub struct StepWorkspace {
    /// ∂loss/∂θ of the last step (empty before the first).
    pub(super) grads: Vec<f32>,
    /// Accumulators for the next step: all zeros.
    pub(super) zeroed: Vec<Vec<f32>>,
}

impl StepWorkspace {
    /// The last step's gradient of its loss in the field's parameters (empty before the first step).
    pub fn grads(&self) -> &[f32] {
        &self.grads
    }

    /// The last step's gradient, for a caller to add terms of its own loss to (and to lengthen while an
    /// all-reduce carries more values with it).
    pub fn grads_mut(&mut self) -> &mut Vec<f32> {
        &mut self.grads
    }

    /// An accumulator of `n` floats for a step's task: a kept one of that length if there is one, else
    /// the last step's gradient, to be cleared by the task that takes it (beside the other tasks), else
    /// none (the task allocates zeroed memory).
    pub(super) fn accumulator(&mut self, n: usize) -> Accumulator {
        self.zeroed.retain(|a| a.len() == n);
        if let Some(grads) = self.zeroed.pop() {
            return Accumulator::Zeroed(grads);
        }
        match std::mem::take(&mut self.grads) {
            grads if grads.len() == n => Accumulator::ToClear(grads),
            _ => Accumulator::Fresh,
        }
    }
}

/// The memory a step's task sums its gradient into, as the workspace hands it out.
pub(super) enum Accumulator {
    /// All zeros.
    Zeroed(Vec<f32>),
    /// Last step's gradient, to be cleared.
    ToClear(Vec<f32>),
    /// None kept: fresh memory.
    Fresh,
}

impl Accumulator {
    /// The accumulator, all zeros, of `n` floats.
    pub(super) fn cleared(self, n: usize) -> Vec<f32> {
        match self {
            Accumulator::Zeroed(grads) => grads,
            Accumulator::ToClear(mut grads) => {
                grads.fill(0.0);
                grads
            }
            Accumulator::Fresh => vec![0.0; n],
        }
    }
}

/// The stretches of `0..n` outside the sorted, disjoint `ranges`.
pub(super) fn complement(ranges: &[Range<usize>], n: usize) -> Vec<Range<usize>> {
    let mut out = Vec::with_capacity(ranges.len() + 1);
    let mut start = 0;
    for r in ranges {
        if r.start > start {
            out.push(start..r.start);
        }
        start = start.max(r.end);
    }
    if start < n {
        out.push(start..n);
    }
    out
}

/// The stretches `ranges` (sorted, disjoint, within `values`) of `values`, each its own slice.
pub(super) fn windows<'v>(mut values: &'v mut [f32], ranges: &[Range<usize>]) -> Vec<&'v mut [f32]> {
    let mut out = Vec::with_capacity(ranges.len());
    let mut at = 0;
    for r in ranges {
        let (_, rest) = std::mem::take(&mut values).split_at_mut(r.start - at);
        let (window, rest) = rest.split_at_mut(r.len());
        out.push(window);
        values = rest;
        at = r.end;
    }
    out
}

/// Adds `parts` to `total` on the stretches `ranges` (sorted, disjoint), element by element in the
/// parts' order: the same sums on any number of threads. Each part is zeroed as it is added, while it
/// is in cache, so that the next step need not clear it.
pub(super) fn sum_into(total: &mut [f32], parts: &mut [Vec<f32>], ranges: &[Range<usize>]) {
    const BLOCK: usize = 1 << 16;
    let mut parts: Vec<Vec<&mut [f32]>> = parts.iter_mut().map(|g| windows(g, ranges)).collect();
    let mut blocks: Vec<(&mut [f32], Vec<&mut [f32]>)> = Vec::new();
    for (i, total) in windows(total, ranges).into_iter().enumerate() {
        let mut chunks: Vec<_> = parts
            .iter_mut()
            .map(|p| std::mem::take(&mut p[i]).chunks_mut(BLOCK))
            .collect();
        for total in total.chunks_mut(BLOCK) {
            blocks.push((total, chunks.iter_mut().filter_map(Iterator::next).collect()));
        }
    }
    blocks.into_par_iter().for_each(|(total, parts)| {
        for part in parts {
            for (t, g) in total.iter_mut().zip(part) {
                *t += *g;
                *g = 0.0;
            }
        }
    });
}
