//! The JIT's gradient of W7's 20-primitive union (`examples/complex_scene.sdf`), taken through the nearest
//! primitive of each shape (`kernel_graphs::with_gradient`), against plain reverse mode over the whole `min`
//! tree: the same values bit for bit, gradients equal to f32 rounding, in fewer nodes and divisions.

use nerfjit_dsl::ir::Graph;
use nerfjit_dsl::{compile, kernel_graphs};
use nerfjit_jit::{Kernel, Options};

fn divisions(g: &Graph) -> usize {
    g.ops().iter().filter(|op| op.name() == "div").count()
}

#[test]
fn the_scenes_gradient_through_its_nearest_primitives_matches_plain_reverse_mode() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../examples/complex_scene.sdf");
    let source = std::fs::read_to_string(path).expect("the example");
    let f = compile("complex_scene.sdf", &source)
        .expect("compiles")
        .lower("sdf")
        .expect("lowers");
    let (nearest, plain) = (
        kernel_graphs::with_gradient(&f),
        kernel_graphs::with_plain_gradient(&f),
    );
    assert!(nearest.len() < plain.len() && divisions(&nearest) < divisions(&plain) / 2);

    const N: usize = 4099;
    let mut state = 0x2545_f491_u32;
    let mut random = || {
        state ^= state << 13;
        state ^= state >> 17;
        state ^= state << 5;
        (state as f32 / u32::MAX as f32) * 8.0 - 4.0
    };
    let cols: Vec<Vec<f32>> = (0..3).map(|_| (0..N).map(|_| random()).collect()).collect();
    let ins: Vec<&[f32]> = cols.iter().map(Vec::as_slice).collect();
    let run = |g: &Graph| {
        let kernel = Kernel::compile(g, Options::default()).expect("compiles");
        let mut outs = vec![vec![0.0f32; N]; 4];
        let mut refs: Vec<&mut [f32]> = outs.iter_mut().map(Vec::as_mut_slice).collect();
        kernel.eval(N, &ins, &mut refs, &[], &mut []);
        outs
    };
    let (got, want) = (run(&nearest), run(&plain));
    for i in 0..N {
        assert_eq!(got[0][i].to_bits(), want[0][i].to_bits(), "value at point {i}");
        for axis in 1..4 {
            let (a, b) = (got[axis][i], want[axis][i]);
            assert!(
                (a - b).abs() <= 1e-5 * b.abs().max(1.0),
                "d/dx{} at point {i}: {a} against {b}",
                axis - 1
            );
        }
    }
}
