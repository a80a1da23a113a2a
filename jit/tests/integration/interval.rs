//! Property tests of the interval extension ([`nerfjit_dsl::interval::extend`]) on random programs over
//! every elementwise op: over random boxes, the bounds contain the function at random points of the box, in
//! the f64 interpreter and in the JIT (f32, within the rounding margin callers keep). And tape
//! simplification ([`nerfjit_dsl::simplify`]), which rests on those bounds: over random boxes, the simplified
//! graph gives the original's values at random points of the box, in the interpreter and in the JIT.

use crate::common::{close, jit_eval};
use nerfjit_dsl::interp::eval_point;
use nerfjit_dsl::interval::{extend, BOUND};
use nerfjit_dsl::ir::{Graph, Op, V};
use nerfjit_dsl::simplify::Simplifier;
use nerfjit_jit::Options;
use proptest::prelude::*;

const N_INPUTS: u32 = 3;
const N_PARAMS: u32 = 2;

/// One generated node: an op kind and the (relative) indices of its arguments among earlier nodes.
#[derive(Clone, Debug)]
struct Gen {
    kind: u8,
    a: usize,
    b: usize,
    c: usize,
}

/// Builds a graph of every elementwise op from generated nodes (NaN and infinities allowed: the bounds must
/// hold wherever the function is a number).
fn build(nodes: &[Gen]) -> Graph {
    use Op::*;
    let mut g = Graph::new();
    let mut vals: Vec<V> = (0..N_INPUTS).map(|i| g.input(i)).collect();
    vals.extend((0..N_PARAMS).map(|i| g.param(i)));
    vals.push(g.constant(0.5));
    vals.push(g.constant(-2.0));
    for n in nodes {
        let a = vals[n.a % vals.len()];
        let b = vals[n.b % vals.len()];
        let c = vals[n.c % vals.len()];
        let op = match n.kind % 28 {
            0 => Neg(a),
            1 => Abs(a),
            2 => Sign(a),
            3 => Floor(a),
            4 => Sqrt(a),
            5 => Exp(a),
            6 => Log(a),
            7 => Sin(a),
            8 => Cos(a),
            9 => Tan(a),
            10 => Tanh(a),
            11 => Sigmoid(a),
            12 => Softplus(a),
            13 => Add(a, b),
            14 => Sub(a, b),
            15 | 16 => Mul(a, b),
            17 => Mul(a, a),
            18 => Div(a, b),
            19 | 20 => Min(a, b),
            21 | 22 => Max(a, b),
            23 => Lt(a, b),
            24 => Le(a, b),
            25 => Eq(a, b),
            26 => TruncExp(a),
            _ => Select(a, b, c),
        };
        vals.push(g.push(op));
    }
    g.outputs = vec![vals[vals.len() - 1], vals[vals.len() / 2]];
    g.n_inputs = N_INPUTS;
    g
}

fn nodes() -> impl Strategy<Value = Vec<Gen>> {
    prop::collection::vec(
        (any::<u8>(), any::<usize>(), any::<usize>(), any::<usize>()).prop_map(|(kind, a, b, c)| Gen {
            kind,
            a,
            b,
            c,
        }),
        1..16,
    )
}

/// A box (low corner, high corner) and points in it: fractions of the box, with the corners themselves.
fn boxes() -> impl Strategy<Value = (Vec<f64>, Vec<f64>, Vec<Vec<f64>>)> {
    (
        prop::collection::vec(
            (-3.0f64..3.0, prop_oneof![Just(0.0), 0.0f64..0.5, 0.0f64..4.0]),
            N_INPUTS as usize,
        ),
        prop::collection::vec(prop::collection::vec(0.0f64..=1.0, N_INPUTS as usize), 1..24),
    )
        .prop_map(|(sides, fractions)| {
            let lo: Vec<f64> = sides.iter().map(|s| s.0).collect();
            let hi: Vec<f64> = sides.iter().map(|s| s.0 + s.1).collect();
            let inside = |f: &Vec<f64>| (0..lo.len()).map(|k| lo[k] + f[k] * (hi[k] - lo[k])).collect();
            let mut points: Vec<Vec<f64>> = fractions.iter().map(inside).collect();
            points.push(lo.clone());
            points.push(hi.clone());
            (lo, hi, points)
        })
}

fn params() -> impl Strategy<Value = Vec<f64>> {
    prop::collection::vec(-1.5f64..1.5, N_PARAMS as usize)
}

/// Whether every value `g` computes at `x` (not only its outputs) is a number within ±BOUND: where the
/// bounds are promised (a NaN inside can turn into any number, e.g. `max(−2, √−1) = −2`).
fn defined(g: &Graph, x: &[f64], p: &[f64]) -> bool {
    let mut all = g.clone();
    all.outputs = (0..g.len() as u32).map(V).collect();
    eval_point(&all, x, p).outputs.iter().all(|v| v.abs() <= BOUND)
}

/// Rounds to f32 and back, as the JIT sees its inputs.
fn f32s(v: &[f64]) -> Vec<f64> {
    v.iter().map(|&x| f64::from(x as f32)).collect()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn bounds_contain_the_function_in_the_interpreter(gen in nodes(), (lo, hi, points) in boxes(), p in params()) {
        let g = build(&gen);
        let bounds = extend(&g);
        prop_assert_eq!(bounds.validate(), Ok(()));
        let corners: Vec<f64> = lo.iter().chain(&hi).copied().collect();
        let b = eval_point(&bounds, &corners, &p).outputs;
        let m = g.outputs.len();
        for x in &points {
            let defined = defined(&g, x, &p);
            for (k, &v) in eval_point(&g, x, &p).outputs.iter().enumerate() {
                let (l, h) = (b[k], b[m + k]);
                prop_assert!(l <= h && l >= -BOUND && h <= BOUND, "bounds [{l}, {h}]\n{g}");
                if defined {
                    // Up to f64 rounding.
                    let slack = 1e-9 * (1.0 + v.abs());
                    prop_assert!(l - slack <= v && v <= h + slack,
                        "output {k} = {v} at {x:?} outside [{l}, {h}] on box {lo:?}..{hi:?}\n{g}");
                }
            }
        }
    }

    #[test]
    fn jit_bounds_contain_the_jit_values(gen in nodes(), (lo, hi, points) in boxes(), p in params()) {
        let g = build(&gen);
        let bounds = extend(&g);
        let (lo, hi) = (f32s(&lo), f32s(&hi));
        let points: Vec<Vec<f64>> = points.iter().map(|x| f32s(x).iter().zip(lo.iter().zip(&hi))
            .map(|(&v, (&l, &h))| v.clamp(l, h)).collect()).collect();
        let corners: Vec<f64> = lo.iter().chain(&hi).copied().collect();
        let (b, _) = jit_eval(&bounds, &[corners], &p, Options::default());
        let (values, _) = jit_eval(&g, &points, &p, Options::default());
        let m = g.outputs.len();
        for (x, out) in points.iter().zip(&values) {
            let defined = defined(&g, x, &p);
            for (k, &v) in out.iter().enumerate() {
                let (l, h) = (f64::from(b[0][k]), f64::from(b[0][m + k]));
                prop_assert!(l <= h, "bounds [{l}, {h}]\n{g}");
                let v = f64::from(v);
                if defined {
                    // f32 rounding of both evaluations: the margin octree meshing keeps.
                    let slack = 1e-4 * (1.0 + l.abs().max(h.abs()));
                    prop_assert!(l - slack <= v && v <= h + slack,
                        "output {k} = {v} at {x:?} outside [{l}, {h}]\n{g}");
                }
            }
        }
    }
}

proptest! {
    // About a quarter of random graphs and boxes decide a choice.
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn simplified_graphs_give_the_same_values_in_the_interpreter(
        gen in nodes(), (lo, hi, points) in boxes(), p in params()
    ) {
        let g = build(&gen);
        let simplified = Simplifier::new(&g).simplify(&lo, &hi, &p);
        prop_assert_eq!(simplified.graph.validate(), Ok(()));
        prop_assert!(simplified.graph.len() <= g.compact().len());
        for x in points.iter().filter(|x| defined(&g, x, &p)) {
            let want = eval_point(&g, x, &p).outputs;
            let got = eval_point(&simplified.graph, x, &p).outputs;
            prop_assert_eq!(&got, &want, "at {:?} on box {:?}..{:?}\n{}\nsimplified:\n{}", x, lo, hi, g,
                simplified.graph);
        }
    }

    #[test]
    fn simplified_kernels_give_the_same_values_in_the_jit(
        gen in nodes(), (lo, hi, points) in boxes(), p in params()
    ) {
        let g = build(&gen);
        // The box and its points as the JIT sees them: in f32.
        let (lo, hi) = (f32s(&lo), f32s(&hi));
        let points: Vec<Vec<f64>> = points.iter().map(|x| f32s(x).iter().zip(lo.iter().zip(&hi))
            .map(|(&v, (&l, &h))| v.clamp(l, h)).collect()).collect();
        let simplified = Simplifier::new(&g).simplify(&lo, &hi, &p);
        let (want, _) = jit_eval(&g, &points, &p, Options::default());
        let (got, _) = jit_eval(&simplified.graph, &points, &p, Options::default());
        for ((x, got), want) in points.iter().zip(&got).zip(&want) {
            if defined(&g, x, &p) {
                // The same up to the constants simplification folds: in f64, where the JIT's polynomial
                // for, e.g., tanh(−2) may differ in the last bit.
                for (&a, &b) in got.iter().zip(want) {
                    prop_assert!(close(a, f64::from(b), 1e-5, 1.0),
                        "{:?} vs {:?} at {:?}\n{}\nsimplified:\n{}", got, want, x, g, simplified.graph);
                }
            }
        }
    }
}

/// A union of many spheres keeps, over a small box, the spheres that can be nearest there.
#[test]
fn a_union_of_spheres_keeps_the_nearest_ones_over_a_box() {
    let mut g = Graph::new();
    let p: Vec<V> = (0..3).map(|i| g.input(i)).collect();
    let mut union: Option<V> = None;
    for k in 0..20 {
        // A sphere of radius 0.4 at (k, 0, 0).
        let c = g.constant(f64::from(k));
        let dx = g.push(Op::Sub(p[0], c));
        let dx2 = g.push(Op::Mul(dx, dx));
        let y2 = g.push(Op::Mul(p[1], p[1]));
        let z2 = g.push(Op::Mul(p[2], p[2]));
        let r2 = g.push(Op::Add(dx2, y2));
        let r2 = g.push(Op::Add(r2, z2));
        let r = g.push(Op::Sqrt(r2));
        let radius = g.constant(0.4);
        let d = g.push(Op::Sub(r, radius));
        union = Some(union.map_or(d, |u| g.push(Op::Min(u, d))));
    }
    g.outputs.push(union.expect("20 spheres"));
    g.n_inputs = 3;
    let simplifier = Simplifier::new(&g);
    // Around sphere 7 only sphere 7 can be nearest: the others are at least 0.5 away, it at most 0.1.
    let s = simplifier.simplify(&[6.9, -0.1, -0.1], &[7.1, 0.1, 0.1], &[]);
    let count = |g: &Graph| g.ops().iter().filter(|op| matches!(op, Op::Sqrt(_))).count();
    assert_eq!(count(&g.compact()), 20);
    assert_eq!(count(&s.graph), 1, "{}", s.graph);
    assert_eq!(s.choices, 19);
    let at = |g: &Graph| eval_point(g, &[7.05, 0.02, -0.03], &[]).outputs;
    assert_eq!(at(&s.graph), at(&g));
    // Over the whole row nothing is decided.
    let whole = simplifier.simplify(&[-1.0, -1.0, -1.0], &[20.0, 1.0, 1.0], &[]);
    assert_eq!((whole.choices, count(&whole.graph)), (0, 20));
}

/// A point's sphere distance is bounded tightly enough for pruning: the square is recognized.
#[test]
fn sphere_distance_bounds_are_tight() {
    let mut g = Graph::new();
    let p: Vec<V> = (0..3).map(|i| g.input(i)).collect();
    let squares: Vec<V> = p.iter().map(|&x| g.push(Op::Mul(x, x))).collect();
    let xy = g.push(Op::Add(squares[0], squares[1]));
    let r2 = g.push(Op::Add(xy, squares[2]));
    let len = g.push(Op::Sqrt(r2));
    let one = g.constant(1.0);
    let d = g.push(Op::Sub(len, one));
    g.outputs.push(d);
    g.n_inputs = 3;
    let bounds = extend(&g);
    // The box [2, 3] × [−1, 1] × [−1, 1]: distances from √4 − 1 = 1 to √11 − 1.
    let b = eval_point(&bounds, &[2.0, -1.0, -1.0, 3.0, 1.0, 1.0], &[]).outputs;
    assert_eq!(b[0], 1.0);
    assert!((b[1] - (11f64.sqrt() - 1.0)).abs() < 1e-12);
}

/// Selects on comparisons pick one branch where the comparison is decided on the whole box.
#[test]
fn decided_comparisons_select_one_branch() {
    let mut g = Graph::new();
    let x = g.input(0);
    let zero = g.constant(0.0);
    let below = g.push(Op::Lt(x, zero));
    let ten = g.constant(10.0);
    let minus = g.constant(-10.0);
    let s = g.push(Op::Select(below, minus, ten));
    g.outputs.push(s);
    g.n_inputs = 1;
    let bounds = extend(&g);
    let at = |lo: f64, hi: f64| eval_point(&bounds, &[lo, hi], &[]).outputs;
    assert_eq!(at(1.0, 2.0), vec![10.0, 10.0]);
    assert_eq!(at(-2.0, -1.0), vec![-10.0, -10.0]);
    assert_eq!(at(-1.0, 1.0), vec![-10.0, 10.0]);
}

/// A step of a quotient that f32 rounds below an integer: floor(p / p) is 1, while the bounds of the
/// quotient, p · (1 / p), are 0.99999994 in f32 for p = 41; the step's bounds still contain 1.
#[test]
fn steps_of_rounded_bounds_still_contain_the_value() {
    let mut g = Graph::new();
    let p = g.param(0);
    let q = g.push(Op::Div(p, p));
    let f = g.push(Op::Floor(q));
    let x = g.input(0);
    let s = g.push(Op::Sub(x, q));
    let sign = g.push(Op::Sign(s));
    g.outputs = vec![f, sign];
    g.n_inputs = 1;
    let (b, _) = jit_eval(&extend(&g), &[vec![1.0, 1.0]], &[41.0], Options::default());
    let (v, _) = jit_eval(&g, &[vec![1.0]], &[41.0], Options::default());
    assert_eq!(v[0], vec![1.0, 0.0]);
    for k in 0..2 {
        assert!(
            b[0][k] <= v[0][k] && v[0][k] <= b[0][2 + k],
            "output {k}: {:?} vs {:?}",
            v[0],
            b[0]
        );
    }
}

/// The floor of the whole range (here the log of a negative param: NaN, so ±BOUND) stays within ±BOUND
/// although its argument is widened by the rounding margin first (random programs found
/// `floor(log(p))` bounded by ±1.0001e18).
#[test]
fn the_floor_of_the_whole_range_stays_in_the_range() {
    let mut g = Graph::new();
    let p = g.param(0);
    let l = g.push(Op::Log(p));
    let f = g.push(Op::Floor(l));
    g.outputs = vec![f];
    g.n_inputs = 1;
    let b = eval_point(&extend(&g), &[0.0, 1.0], &[-1.0]).outputs;
    assert_eq!(b, [-BOUND, BOUND]);
}

/// Division bounds are the corners' quotients, not a times b's reciprocal, which rounds twice: a value
/// divided by itself is exactly 1, and so are its bounds (a · (1 / a) is 1 - 2^-53 for this a in f64).
#[test]
fn a_value_divided_by_itself_is_bounded_by_one() {
    let mut g = Graph::new();
    let x = g.input(0);
    let q = g.push(Op::Div(x, x));
    g.outputs.push(q);
    g.n_inputs = 1;
    let bounds = extend(&g);
    let a = 0.4954064184852829_f64;
    assert_ne!(
        a * (1.0 / a),
        1.0,
        "this value no longer shows the double rounding"
    );
    assert_eq!(eval_point(&bounds, &[a, a], &[]).outputs, vec![1.0, 1.0]);
}

/// Division by an interval that contains 0 is unbounded; by one that does not, it is bounded.
#[test]
fn division_by_a_range_through_zero_is_the_whole_range() {
    let mut g = Graph::new();
    let (x, y) = (g.input(0), g.input(1));
    let q = g.push(Op::Div(x, y));
    g.outputs.push(q);
    g.n_inputs = 2;
    let bounds = extend(&g);
    let at = |c: [f64; 4]| eval_point(&bounds, &c, &[]).outputs;
    assert_eq!(at([1.0, -1.0, 2.0, 1.0]), vec![-BOUND, BOUND]);
    assert_eq!(at([1.0, 2.0, 2.0, 4.0]), vec![0.25, 1.0]);
}
