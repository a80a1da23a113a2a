//! Gradients of unions through their nearest primitive of each shape (`nerfjit_dsl::nearest`), against
//! plain reverse mode over the whole `min` (or `max`) tree: random unions of spheres, boxes and tori with
//! random constants (zeros among them, which split a kind into shapes), random trees, random points, in
//! the f64 interpreter.

use nerfjit_dsl::interp::eval_point;
use nerfjit_dsl::ir::{Graph, Op};
use nerfjit_dsl::{compile, kernel_graphs, nearest};
use proptest::prelude::*;

/// A primitive with its constants: kind 0 a sphere, 1 a box, 2 a torus around y; a center component of
/// index 3 or more (in the strategy) is 0.
fn primitive(kind: u8, center: [f64; 3], a: f64, b: f64) -> String {
    let c = format!("[{:?}, {:?}, {:?}]", center[0], center[1], center[2]);
    match kind {
        0 => format!("sphere(p - {c}, {a:?})"),
        1 => format!("box(p - {c}, [{a:?}, {b:?}, 0.4])"),
        _ => format!("torus_y(p - {c}, {a:?}, {:?})", b * 0.3),
    }
}

/// `op` applied over `leaves` as a tree whose shape `splits` picks (each split point taken modulo the
/// length of the range it divides).
fn tree(op: &str, leaves: &[String], splits: &mut impl Iterator<Item = usize>) -> String {
    if leaves.len() == 1 {
        return leaves[0].clone();
    }
    let at = 1 + splits.next().unwrap_or(0) % (leaves.len() - 1);
    format!(
        "{op}({}, {})",
        tree(op, &leaves[..at], splits),
        tree(op, &leaves[at..], splits)
    )
}

fn primitives() -> impl Strategy<Value = Vec<(u8, [f64; 3], f64, f64)>> {
    let component = prop_oneof![Just(0.0), -2.0f64..2.0];
    prop::collection::vec(
        (
            0u8..3,
            [component.clone(), component.clone(), component],
            0.3f64..0.9,
            0.3f64..0.9,
        ),
        2..12,
    )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(96))]

    #[test]
    fn the_nearest_primitives_gradient_is_the_trees(
        prims in primitives(),
        splits in prop::collection::vec(0usize..64, 16),
        use_max in any::<bool>(),
        points in prop::collection::vec([-3.0f64..3.0, -3.0f64..3.0, -3.0f64..3.0], 24),
    ) {
        let leaves: Vec<String> = prims.iter().map(|&(k, c, a, b)| primitive(k, c, a, b)).collect();
        let body = tree(if use_max { "max" } else { "min" }, &leaves, &mut splits.into_iter());
        let program = compile("union.sdf", &format!("fn sdf(p: vec3) -> f32 = {body}\n")).expect("compiles");
        let f = program.lower("sdf").expect("lowers");
        let nearest = kernel_graphs::with_gradient(&f);
        let plain = kernel_graphs::with_plain_gradient(&f);
        for p in &points {
            let want = eval_point(&plain, p, &[]).outputs;
            let got = eval_point(&nearest, p, &[]).outputs;
            prop_assert_eq!(got[0].to_bits(), want[0].to_bits(), "value at {:?} of {}", p, body);
            for axis in 1..4 {
                prop_assert!(
                    got[axis] == want[axis] || (got[axis] - want[axis]).abs() <= 1e-12 * want[axis].abs(),
                    "d/dx{} at {:?}: {} against {} for {}", axis - 1, p, got[axis], want[axis], body
                );
            }
        }
    }
}

/// The number of nodes of `g` doing `name`.
fn count(g: &Graph, name: &str) -> usize {
    g.ops().iter().filter(|op| op.name() == name).count()
}

#[test]
fn a_union_of_eight_spheres_runs_one_backward_pass() {
    let spheres: Vec<String> = (0..8)
        .map(|i| primitive(0, [1.0 + i as f64, 0.5, -0.5], 0.3 + 0.05 * i as f64, 0.0))
        .collect();
    let body = tree("min", &spheres, &mut std::iter::repeat(0));
    let program = compile("spheres.sdf", &format!("fn sdf(p: vec3) -> f32 = {body}\n")).expect("compiles");
    let f = program.lower("sdf").expect("lowers");
    // 8 square roots forward and 1 for the chosen sphere; its derivative 1 division, against 8.
    let nearest = kernel_graphs::with_gradient(&f);
    assert_eq!((count(&nearest, "sqrt"), count(&nearest, "div")), (9, 1));
    let plain = kernel_graphs::with_plain_gradient(&f);
    assert_eq!((count(&plain, "sqrt"), count(&plain, "div")), (8, 8));
}

#[test]
fn other_roots_and_unions_of_distinct_shapes_seed_themselves() {
    for body in [
        "length(p) - 1.0",
        "min(sphere(p, 1.0), box(p, [1.0, 1.0, 1.0]))",
        "max(length(p) - 1.0, 0.0)",
        "min(sphere(p - [1.0, 0.0, 0.0], 0.5), sphere(p - [0.0, 1.0, 0.0], 0.5)) + 0.1",
    ] {
        let program = compile("f.sdf", &format!("fn sdf(p: vec3) -> f32 = {body}\n")).expect("compiles");
        let mut g = program.lower("sdf").expect("lowers").graph;
        let root = g.outputs[0];
        let before = g.len();
        assert_eq!(nearest::gradient_seed(&mut g, root), root, "{body}");
        assert_eq!(g.len(), before, "{body}: nothing added");
    }
    // ReLU's max(x, 0) is not a union: its gradient takes another side at 0.
    let program = compile(
        "f.sdf",
        "fn sdf(p: vec3) -> f32 = max(sphere(p, 1.0) - 2.0, 0.0)\n",
    )
    .expect("compiles");
    let mut g = program.lower("sdf").expect("lowers").graph;
    let root = g.outputs[0];
    assert!(matches!(g.op(root), Op::Max(..)));
    assert_eq!(nearest::gradient_seed(&mut g, root), root);
}

#[test]
fn a_union_of_more_primitives_than_the_limit_seeds_itself() {
    let spheres: Vec<String> = (0..=nearest::MAX_PRIMITIVES)
        .map(|i| primitive(0, [1.0 + i as f64, 0.5, -0.5], 0.3, 0.0))
        .collect();
    let body = tree("min", &spheres, &mut std::iter::repeat(0));
    let program = compile("spheres.sdf", &format!("fn sdf(p: vec3) -> f32 = {body}\n")).expect("compiles");
    let mut g = program.lower("sdf").expect("lowers").graph;
    let root = g.outputs[0];
    assert_eq!(nearest::gradient_seed(&mut g, root), root);
}
