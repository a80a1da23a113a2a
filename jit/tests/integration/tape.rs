//! Property tests of the tape interpreter ([`nerfjit_jit::Tape`]): on random programs of the ops it takes,
//! it gives the same bits as the compiled kernel of the same graph, fused multiply-adds included; graphs
//! with other ops are refused.

use crate::common::jit_eval;
use nerfjit_dsl::ir::{Graph, Op, V};
use nerfjit_jit::{Options, Tape};
use proptest::prelude::*;

const N_INPUTS: u32 = 3;

/// A random graph of the tape's ops, products often feeding sums (so that some fuse into FMAs and some,
/// used twice, do not).
fn build(nodes: &[(u8, usize, usize, usize)]) -> Graph {
    use Op::*;
    let mut g = Graph::new();
    let mut vals: Vec<V> = (0..N_INPUTS).map(|i| g.input(i)).collect();
    vals.push(g.param(0));
    vals.push(g.constant(0.5));
    vals.push(g.constant(-3.0));
    for &(kind, ia, ib, ic) in nodes {
        let (a, b, c) = (
            vals[ia % vals.len()],
            vals[ib % vals.len()],
            vals[ic % vals.len()],
        );
        let op = match kind % 20 {
            0 => Neg(a),
            1 => Abs(a),
            2 => Sign(a),
            3 => Floor(a),
            4 => Sqrt(a),
            5 | 6 => Add(a, b),
            7 | 8 => Sub(a, b),
            9..=11 => Mul(a, b),
            12 => Div(a, b),
            13 => Min(a, b),
            14 => Max(a, b),
            15 => Lt(a, b),
            16 => Le(a, b),
            17 => Eq(a, b),
            18 => Select(a, b, c),
            // By one of the constants: a product by the reciprocal.
            _ => Div(a, vals[N_INPUTS as usize + 1 + ib % 2]),
        };
        vals.push(g.push(op));
    }
    let last = vals.len() - 1;
    g.outputs = vec![vals[last], vals[last / 2], vals[N_INPUTS as usize]];
    g.n_inputs = N_INPUTS;
    g
}

fn bits(x: f32) -> u32 {
    // NaNs compare as one value: their payloads are not part of the semantics.
    if x.is_nan() {
        u32::MAX
    } else {
        x.to_bits()
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn tapes_give_the_kernels_bits(
        nodes in prop::collection::vec((any::<u8>(), any::<usize>(), any::<usize>(), any::<usize>()), 1..40),
        points in prop::collection::vec(prop::collection::vec(-4.0f64..4.0, N_INPUTS as usize), 1..300),
        param in -2.0f64..2.0,
    ) {
        let g = build(&nodes);
        let tape = Tape::new(&g, &[param as f32]).expect("only the tape's ops");
        let (want, _) = jit_eval(&g, &points, &[param], Options::default());
        let n = points.len();
        let cols: Vec<Vec<f32>> = (0..N_INPUTS as usize)
            .map(|k| points.iter().map(|p| p[k] as f32).collect())
            .collect();
        let ins: Vec<&[f32]> = cols.iter().map(Vec::as_slice).collect();
        let mut outs = vec![vec![0.0f32; n]; g.outputs.len()];
        let mut refs: Vec<&mut [f32]> = outs.iter_mut().map(Vec::as_mut_slice).collect();
        tape.eval(n, &ins, &mut refs);
        for (i, w) in want.iter().enumerate() {
            for (o, &w) in w.iter().enumerate() {
                prop_assert_eq!(bits(outs[o][i]), bits(w), "output {} of point {}: {} vs {}\n{}",
                    o, i, outs[o][i], w, g);
            }
        }
    }
}

/// A product read by one live sum fuses into it although a dead sum also reads it twice: the kernel
/// compiles the compacted graph (no dead sum), and the tape must round as it does. Random programs found
/// x·(−3) + √x one bit apart at x = 1.8236229577994711 when the dead `m + m` unfused the product.
#[test]
fn dead_sums_do_not_unfuse_a_product() {
    let mut g = Graph::new();
    let x = g.input(0);
    let c = g.constant(-3.0);
    let m = g.push(Op::Mul(x, c));
    let r = g.push(Op::Sqrt(x));
    let _dead = g.push(Op::Add(m, m));
    let sum = g.push(Op::Add(m, r));
    g.outputs = vec![sum];
    g.n_inputs = 1;
    let x = 1.8236229577994711f64;
    let tape = Tape::new(&g, &[]).unwrap();
    let mut out = [0.0f32];
    tape.eval(1, &[&[x as f32]], &mut [&mut out]);
    let (want, _) = jit_eval(&g, &[vec![x]], &[], Options::default());
    let xf = x as f32;
    assert_eq!(
        bits(want[0][0]),
        bits(xf.mul_add(-3.0, xf.sqrt())),
        "the kernel fuses"
    );
    assert_eq!(bits(out[0]), bits(want[0][0]));
}

#[test]
fn ops_with_approximations_and_reductions_are_refused() {
    let mut g = Graph::new();
    let x = g.input(0);
    let e = g.push(Op::Exp(x));
    g.outputs.push(e);
    g.n_inputs = 1;
    let err = Tape::new(&g, &[]).expect_err("exp is approximated by the kernel");
    assert!(err.0.contains("'exp'"), "{}", err.0);
    let mut g = Graph::new();
    let x = g.input(0);
    g.reductions.push(x);
    g.n_inputs = 1;
    assert!(Tape::new(&g, &[]).is_err());
}

/// A product two sums share is not fused by the kernel; restricted to a box where one sum is dropped, the
/// product has one reader left. A tape given the original's fusion flags (through `origin`) still rounds as
/// the original kernel; one that decides afresh fuses it and rounds differently.
#[test]
fn carried_fusion_flags_keep_the_original_kernels_rounding() {
    use nerfjit_dsl::simplify::Simplifier;
    use nerfjit_jit::fused_products;
    let mut g = Graph::new();
    let (x, y, z) = (g.input(0), g.input(1), g.input(2));
    let yy = g.push(Op::Mul(y, y));
    let a = g.push(Op::Add(yy, x));
    let ten = g.constant(10.0);
    let z10 = g.push(Op::Add(z, ten));
    let b = g.push(Op::Add(yy, z10));
    let f = g.push(Op::Min(a, b));
    g.outputs.push(f);
    g.n_inputs = 3;
    let original = fused_products(&g);
    assert!(!original[yy.0 as usize], "read by two sums");
    let (lo, hi) = ([-1.0, 0.1, -1.0], [1.0, 1.0, 1.0]);
    let simplified = Simplifier::new(&g).simplify(&lo, &hi, &[]);
    assert_eq!(simplified.choices, 1);
    let carried: Vec<bool> = simplified.origin.iter().map(|o| original[o.0 as usize]).collect();
    let mut rng = 0x1234_5678_u32;
    let mut next = |l: f64, h: f64| {
        rng ^= rng << 13;
        rng ^= rng >> 17;
        rng ^= rng << 5;
        l + (h - l) * f64::from(rng) / f64::from(u32::MAX)
    };
    let points: Vec<Vec<f64>> = (0..4096)
        .map(|_| (0..3).map(|k| next(lo[k], hi[k])).collect())
        .collect();
    let (want, _) = jit_eval(&g, &points, &[], Options::default());
    let run = |tape: Tape| -> Vec<f32> {
        let cols: Vec<Vec<f32>> = (0..3)
            .map(|k| points.iter().map(|p| p[k] as f32).collect())
            .collect();
        let ins: Vec<&[f32]> = cols.iter().map(Vec::as_slice).collect();
        let mut out = vec![0.0f32; points.len()];
        tape.eval(points.len(), &ins, &mut [&mut out]);
        out
    };
    let kept = run(Tape::with_fusion(&simplified.graph, &[], &carried).unwrap());
    let fresh = run(Tape::new(&simplified.graph, &[]).unwrap());
    let want: Vec<f32> = want.iter().map(|w| w[0]).collect();
    assert_eq!(kept, want);
    assert!(
        fresh.iter().zip(&want).any(|(a, b)| a != b),
        "fusing afresh rounds differently somewhere"
    );
}
