//! The reference interpreter: evaluates any [`Graph`] in f64, point by point. It is the oracle against
//! which the JIT and the derivatives are tested, so it is written for clarity, not speed.

use std::collections::HashMap;

use crate::grid::{corner_vertex, corner_weight};
pub use crate::ir::semantics::apply;
use crate::ir::{Dense, Graph, GridRead, Op};

/// What one evaluation produced.
#[derive(Clone, Debug, PartialEq)]
pub struct Eval {
    /// The per-point outputs.
    pub outputs: Vec<f64>,
    /// The reductions (for one point: that point's terms; for a batch: their sums).
    pub reductions: Vec<f64>,
}

/// `W·x` or `Wᵀ·x` of a dense node (NaN for params out of range).
fn dense(d: &Dense, x: &[f64], params: &[f64]) -> Vec<f64> {
    let w = |i: usize, j: usize| {
        params
            .get(d.w as usize + i * d.cols as usize + j)
            .copied()
            .unwrap_or(f64::NAN)
    };
    (0..d.n_out())
        .map(|o| {
            x.iter()
                .enumerate()
                .map(|(k, xk)| if d.transposed { w(k, o) } else { w(o, k) } * xk)
                .sum()
        })
        .collect()
}

/// Calls `visit(table param, weight, output)` for every table float that a grid read at `p` combines, with
/// its trilinear weight (differentiated as the read asks) and the output it adds to.
fn grid_terms(r: &GridRead, p: [f64; 3], mut visit: impl FnMut(usize, f64, usize)) {
    let spec = r.spec;
    let features = spec.features as usize;
    for (l, level) in spec.layout().iter().enumerate() {
        let cell = spec.cell(l as u32, p);
        for k in 0..8 {
            let w = corner_weight(&cell, k, r.deriv);
            let entry = level.entry(corner_vertex(&cell, k));
            for f in 0..features {
                let param = spec.table as usize + entry as usize * features + f;
                visit(param, w, l * features + f);
            }
        }
    }
}

/// The outputs of a grid read (NaN for params out of range).
fn grid_read(r: &GridRead, p: [f64; 3], params: &[f64]) -> Vec<f64> {
    let mut out = vec![0.0; r.spec.n_outputs()];
    grid_terms(r, p, |param, w, o| {
        out[o] += w * params.get(param).copied().unwrap_or(f64::NAN)
    });
    out
}

/// Evaluates `g` at one point. The outer products and scatters of `g` add to the reductions they target.
pub fn eval_point(g: &Graph, inputs: &[f64], params: &[f64]) -> Eval {
    let mut vals = vec![0.0; g.len()];
    let mut args = Vec::with_capacity(3);
    let mut products: HashMap<usize, Vec<f64>> = HashMap::new();
    for (i, op) in g.ops().iter().enumerate() {
        vals[i] = match *op {
            Op::Input(k) => inputs.get(k as usize).copied().unwrap_or(f64::NAN),
            Op::Param(k) => params.get(k as usize).copied().unwrap_or(f64::NAN),
            Op::Dense(d) => {
                let x: Vec<f64> = g.list(d.x).iter().map(|a| vals[a.0 as usize]).collect();
                products.insert(i, dense(&d, &x, params));
                0.0
            }
            Op::Grid(r) => {
                let p = r.p.map(|a| vals[a.0 as usize]);
                products.insert(i, grid_read(&r, p, params));
                0.0
            }
            Op::Pick(d, k) => products[&(d.0 as usize)][k as usize],
            _ => {
                args.clear();
                args.extend(op.args().iter().map(|a| vals[a.0 as usize]));
                apply(*op, &args)
            }
        };
    }
    let mut reductions: Vec<f64> = g.reductions.iter().map(|v| vals[v.0 as usize]).collect();
    for o in &g.outer {
        let cols = o.right.len();
        for (i, l) in o.left.iter().enumerate() {
            for (j, r) in o.right.iter().enumerate() {
                if let Some(slot) = reductions.get_mut(o.target as usize + i * cols + j) {
                    *slot += vals[l.0 as usize] * vals[r.0 as usize];
                }
            }
        }
    }
    for sc in &g.scatter {
        let p = sc.read.p.map(|a| vals[a.0 as usize]);
        grid_terms(&sc.read, p, |param, w, o| {
            if let Some(slot) = reductions.get_mut(param) {
                *slot += w * vals[sc.cotangent[o].0 as usize];
            }
        });
    }
    Eval {
        outputs: g.outputs.iter().map(|v| vals[v.0 as usize]).collect(),
        reductions,
    }
}

/// Evaluates `g` at every point; `inputs[i]` holds input i of all points. Returns the outputs per point
/// (`outputs[o][point]`) and the reductions summed over the points.
pub fn eval_batch(g: &Graph, inputs: &[Vec<f64>], params: &[f64]) -> (Vec<Vec<f64>>, Vec<f64>) {
    let n = inputs.first().map_or(0, Vec::len);
    let mut outputs = vec![Vec::with_capacity(n); g.outputs.len()];
    let mut sums = vec![0.0; g.reductions.len()];
    let mut point = vec![0.0; inputs.len()];
    for p in 0..n {
        for (slot, column) in point.iter_mut().zip(inputs) {
            *slot = column[p];
        }
        let e = eval_point(g, &point, params);
        for (column, v) in outputs.iter_mut().zip(e.outputs) {
            column.push(v);
        }
        for (s, r) in sums.iter_mut().zip(e.reductions) {
            *s += r;
        }
    }
    (outputs, sums)
}
