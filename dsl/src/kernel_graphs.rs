//! The graphs of each kernel kind, built from a lowered function by the IR transforms.
//!
//! Every kind is one [`Graph`]: per-point inputs and outputs, and reductions summed over a batch.
//! - [`value`]: the function's outputs.
//! - [`with_gradient`]: outputs, then ∂outₖ/∂inputs for each output k (the Jacobian, row by row).
//! - [`vjp`]: inputs followed by one cotangent per output; outputs, then the input gradient Σₖ cₖ ∂outₖ/∂x;
//!   reductions: the param gradient Σₖ cₖ ∂outₖ/∂θ for every param.
//! - [`vjp_backward`]: the backward pass of [`vjp`]'s input gradient g = Σₖ cₖ ∂outₖ/∂x: inputs x, c and a
//!   cotangent w of g; outputs ∂(w·g)/∂x and ∂(w·g)/∂c; reductions ∂(w·g)/∂θ (torch's double backward).
//! - [`forward_backward`]: as [`vjp`] with the function's values as its only outputs, for training (run
//!   whole, or split into a forward pass that keeps its values and a backward pass over them).
//! - [`second_order`]: for a scalar function f, inputs x, then cotangents for f and for each component of
//!   ∇ₓf; outputs f and ∇ₓf; reductions ∂/∂θ (c_f f + c_g·∇ₓf). A loss on ∇ₓf (the eikonal loss) gets its
//!   param gradient from this kernel.
//!
//! - [`interval`]: lower and upper bounds of the outputs over boxes of inputs.
//! - [`loss_gradient`]: for a scalar function f, a per-point loss built from f and ∇ₓf in the IR itself;
//!   outputs the loss terms; reductions their param gradient. One kernel instead of a forward pass, a
//!   loss on the host and a backward pass.
//! - [`sdf_loss`]: the named loss kernels of fitting a signed distance ([`SdfLoss`]: the surface term,
//!   pre-training toward a sphere, the near-surface and eikonal regularizers), built by [`loss_gradient`].
//!
//! In the kinds with param gradients, the gradients of dense layers' matrices are the graph's outer
//! products ([`crate::ir::Outer`]) and those of grid encodings' tables its scatters
//! ([`crate::ir::Scatter`]), added to the reductions of the same params.

use crate::autodiff;
use crate::ir::{Graph, Op, V};
use crate::program::Lowered;

fn inputs(g: &mut Graph, count: u32) -> Vec<V> {
    (0..count).map(|i| g.input(i)).collect()
}

/// The params the graph reads as scalars (matrices and tables are read as blocks and get their
/// gradients from outer products and scatters), so that a table of millions of floats adds no node.
fn scalar_params(g: &Graph, n_params: usize) -> Vec<u32> {
    let mut read = vec![false; n_params];
    for op in g.ops() {
        if let Op::Param(k) = op {
            if let Some(r) = read.get_mut(*k as usize) {
                *r = true;
            }
        }
    }
    (0..n_params as u32).filter(|&k| read[k as usize]).collect()
}

/// Appends the gradient of Σ cot·out over `seeds` with respect to `xs` (returned first) and to every
/// param (returned second: one value per param, the reductions), and installs the block gradients.
fn gradients(g: &mut Graph, seeds: &[(V, V)], xs: &[V], n_params: usize) -> (Vec<V>, Vec<V>) {
    let read = scalar_params(g, n_params);
    let mut wrt = xs.to_vec();
    wrt.extend(read.iter().map(|&k| g.param(k)));
    let (grads, blocks) = autodiff::vjp_with_dense_params(g, seeds, &wrt, true);
    blocks.install(g);
    let zero = g.constant(0.0);
    let mut reductions = vec![zero; n_params];
    for (&k, &v) in read.iter().zip(&grads[xs.len()..]) {
        reductions[k as usize] = v;
    }
    (grads[..xs.len()].to_vec(), reductions)
}

/// The function's values.
pub fn value(f: &Lowered) -> Graph {
    f.graph.compact()
}

/// The interval extension of the function's values (see [`crate::interval`]): inputs the low corners of
/// boxes, then their high corners; outputs lower bounds of every output over the box, then upper bounds.
pub fn interval(f: &Lowered) -> Graph {
    crate::interval::extend(&value(f))
}

/// The values, then the gradient of each output with respect to all inputs. A union of primitives of a
/// few shapes runs one backward pass per shape ([`crate::nearest`]).
pub fn with_gradient(f: &Lowered) -> Graph {
    gradient_graph(f, true)
}

/// As [`with_gradient`], by plain reverse mode over every primitive of a union: the reference the
/// nearest-primitive gradients are tested against.
pub fn with_plain_gradient(f: &Lowered) -> Graph {
    gradient_graph(f, false)
}

fn gradient_graph(f: &Lowered, through_nearest: bool) -> Graph {
    let mut g = f.graph.clone();
    let n_in = g.n_inputs;
    let xs = inputs(&mut g, n_in);
    let one = g.constant(1.0);
    let outs = g.outputs.clone();
    for &o in &outs {
        let seed = if through_nearest {
            crate::nearest::gradient_seed(&mut g, o)
        } else {
            o
        };
        let grad = autodiff::vjp(&mut g, &[(seed, one)], &xs);
        g.outputs.extend(grad);
    }
    g.compact()
}

/// The vector-Jacobian product with respect to inputs (per point) and params (reduced).
pub fn vjp(f: &Lowered, n_params: usize) -> Graph {
    let mut g = f.graph.clone();
    let n_in = g.n_inputs;
    let xs = inputs(&mut g, n_in);
    let outs = g.outputs.clone();
    let seeds: Vec<(V, V)> = outs
        .iter()
        .enumerate()
        .map(|(k, &o)| (o, g.input(n_in + k as u32)))
        .collect();
    let (input_grads, reductions) = gradients(&mut g, &seeds, &xs, n_params);
    g.outputs.extend(input_grads);
    g.reductions = reductions;
    g.compact()
}

/// The backward pass of [`vjp`]'s input gradient (what a host's double backward asks for): inputs x, one
/// cotangent cₖ per output, and one cotangent wⱼ per input gradient gⱼ = Σₖ cₖ ∂outₖ/∂xⱼ; outputs ∂(w·g)/∂x,
/// then ∂(w·g)/∂c; reductions ∂(w·g)/∂θ for every param.
pub fn vjp_backward(f: &Lowered, n_params: usize) -> Graph {
    let mut g = f.graph.clone();
    let n_in = g.n_inputs;
    let xs = inputs(&mut g, n_in);
    let outs = g.outputs.clone();
    let cs: Vec<V> = (0..outs.len() as u32).map(|k| g.input(n_in + k)).collect();
    let seeds: Vec<(V, V)> = outs.iter().copied().zip(cs.iter().copied()).collect();
    let grad_x = autodiff::vjp(&mut g, &seeds, &xs);
    let n_out = cs.len() as u32;
    let seeds: Vec<(V, V)> = grad_x
        .iter()
        .enumerate()
        .map(|(j, &gj)| (gj, g.input(n_in + n_out + j as u32)))
        .collect();
    let wrt: Vec<V> = xs.iter().chain(&cs).copied().collect();
    let (grads, reductions) = gradients(&mut g, &seeds, &wrt, n_params);
    g.outputs = grads;
    g.reductions = reductions;
    g.compact()
}

/// The forward and backward pass of training in one graph: inputs, then one cotangent per output;
/// outputs the function's values (which read no cotangent); reductions Σₖ cₖ ∂outₖ/∂θ for every param.
/// Compiled with a split after the function's inputs, it runs as a forward pass that keeps its values and
/// a backward pass that reads them instead of recomputing them.
pub fn forward_backward(f: &Lowered, n_params: usize) -> Graph {
    let n_out = f.graph.outputs.len();
    let mut g = vjp(f, n_params);
    g.outputs.truncate(n_out);
    g.compact()
}

/// The graph of scalar function `f` extended with ∇ₓf: the graph, f's value and the gradient's values.
fn with_input_gradient(f: &Lowered) -> (Graph, V, Vec<V>) {
    let mut g = f.graph.clone();
    let n_in = g.n_inputs;
    let xs = inputs(&mut g, n_in);
    let out = g.outputs[0];
    let one = g.constant(1.0);
    let grad_x = autodiff::vjp(&mut g, &[(out, one)], &xs);
    (g, out, grad_x)
}

/// The loss kernel of a scalar function f (see the module docs): `terms(g, f, ∇ₓf)` builds the per-point
/// loss terms; the kernel outputs them and reduces ∂(Σ terms)/∂θ for every param. ∇ₓf is only built (and
/// differentiated, second order) when `terms` reads it.
pub fn loss_gradient(
    f: &Lowered,
    n_params: usize,
    terms: impl FnOnce(&mut Graph, V, &[V]) -> Vec<V>,
) -> Graph {
    assert_eq!(f.graph.outputs.len(), 1, "loss kernels are for scalar functions");
    let (mut g, out, grad_x) = with_input_gradient(f);
    let one = g.constant(1.0);
    let terms = terms(&mut g, out, &grad_x);
    let seeds: Vec<(V, V)> = terms.iter().map(|&t| (t, one)).collect();
    g.reductions = gradients(&mut g, &seeds, &[], n_params).1;
    g.outputs = terms;
    g.compact()
}

/// A loss of fitting a signed distance f of a point p: vec3, with its weights (which the kernel holds as
/// constants, so each set of weights is its own kernel).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SdfLoss {
    /// `scale · |f(p)|` at points of the cloud: they lie on the surface.
    Surface {
        /// Usually 1 / the batch size.
        scale: f64,
    },
    /// `scale · (f(p) − (|p| − radius))²`: f as the sphere of `radius` (pre-training).
    Sphere {
        /// The sphere's radius.
        radius: f64,
        /// Usually 1 / the number of points.
        scale: f64,
    },
    /// `scale · max(c − (o·f(p) + (1 − o)·|f(p)|), 0)` with the point's clearance c and whether it is
    /// known to lie outside, o (1) or not (0), as fourth and fifth inputs: the surface keeps at least c
    /// (its distance to the nearest cloud point, less a margin) from p, so it cannot lie where no cloud
    /// point is near, and outside f ≥ c (SAL's unsigned-distance supervision, one-sided, so that a true
    /// distance, never more than the distance to the nearest point, is not penalized).
    Clearance {
        /// Usually the weight / the number of points.
        scale: f64,
    },
    /// Two terms: `near · exp(−sharpness · |f(p)|)` (no surface away from the points) and
    /// `eikonal · (|∇ₓf(p)| − 1)²` (a distance has a unit gradient; its param gradient is second order).
    Regularizers {
        /// The weight of the near-surface term (divided by the number of points).
        near: f64,
        /// How fast the near-surface term falls off with |f|.
        sharpness: f64,
        /// The weight of the eikonal term (divided by the number of points).
        eikonal: f64,
    },
}

/// The loss kernel of `loss` for the scalar function f of a point: outputs the loss's terms per point and
/// reduces their param gradient (see [`loss_gradient`]).
pub fn sdf_loss(f: &Lowered, n_params: usize, loss: SdfLoss) -> Graph {
    loss_gradient(f, n_params, |g, d, grad| match loss {
        SdfLoss::Surface { scale } => {
            let abs = g.push(Op::Abs(d));
            let scale = g.constant(scale);
            vec![g.push(Op::Mul(scale, abs))]
        }
        SdfLoss::Sphere { radius, scale } => {
            let p = inputs(g, 3);
            let length = g.length(&p);
            let radius = g.constant(radius);
            let target = g.push(Op::Sub(length, radius));
            let error = g.push(Op::Sub(d, target));
            let squared = g.push(Op::Mul(error, error));
            let scale = g.constant(scale);
            vec![g.push(Op::Mul(scale, squared))]
        }
        SdfLoss::Clearance { scale } => {
            let (clearance, outside) = (g.input(3), g.input(4));
            // o·f + (1 − o)·|f| = |f| + o·(f − |f|)
            let abs = g.push(Op::Abs(d));
            let below = g.push(Op::Sub(d, abs));
            let signed = g.push(Op::Mul(outside, below));
            let kept = g.push(Op::Add(abs, signed));
            let short = g.push(Op::Sub(clearance, kept));
            let zero = g.constant(0.0);
            let hinge = g.push(Op::Max(short, zero));
            let scale = g.constant(scale);
            vec![g.push(Op::Mul(scale, hinge))]
        }
        SdfLoss::Regularizers {
            near,
            sharpness,
            eikonal,
        } => {
            let sharpness = g.constant(-sharpness);
            let (near, eikonal, one) = (g.constant(near), g.constant(eikonal), g.constant(1.0));
            // near · exp(−sharpness · |d|)
            let abs = g.push(Op::Abs(d));
            let scaled = g.push(Op::Mul(sharpness, abs));
            let falloff = g.push(Op::Exp(scaled));
            let near_term = g.push(Op::Mul(near, falloff));
            // eikonal · (|∇d| − 1)²
            let norm = g.length(grad);
            let off = g.push(Op::Sub(norm, one));
            let off2 = g.push(Op::Mul(off, off));
            vec![near_term, g.push(Op::Mul(eikonal, off2))]
        }
    })
}

/// The second-order kernel of a scalar function (see the module docs).
pub fn second_order(f: &Lowered, n_params: usize) -> Graph {
    assert_eq!(
        f.graph.outputs.len(),
        1,
        "second-order kernels are for scalar functions"
    );
    let (mut g, out, grad_x) = with_input_gradient(f);
    let n_in = g.n_inputs;
    let mut seeds = vec![(out, g.input(n_in))];
    for (k, &gk) in grad_x.iter().enumerate() {
        seeds.push((gk, g.input(n_in + 1 + k as u32)));
    }
    g.reductions = gradients(&mut g, &seeds, &[], n_params).1;
    g.outputs = std::iter::once(out).chain(grad_x).collect();
    g.compact()
}
