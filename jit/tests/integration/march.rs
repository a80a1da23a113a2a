//! The fused sphere tracer against a plain per-ray loop that calls the value kernel of the same SDF at
//! each step (with `o + t·d` fused the same way): hits, final `t`, and every partial group of rays, for a
//! small SDF (4 groups of rays marched together) and a large one (1 group).

use nerfjit_dsl::{compile, kernel_graphs};
use nerfjit_jit::{Kernel, MarchRays, Marcher, Options, Stop};
use proptest::prelude::*;

const SCENE: &str = "param r: f32 = 0.25\n\
    fn sdf(p: vec3) -> f32 = min(torus(p, 1.0, r), sphere(p - [0.0, 0.0, 1.2], 0.3))";

fn plain(
    k: &Kernel,
    o: [f32; 3],
    d: [f32; 3],
    (t0, t1): (f32, f32),
    stop: Stop,
    params: &[f32],
) -> (f32, bool) {
    let Stop {
        eps,
        max_steps: steps,
    } = stop;
    let mut t = t0;
    for _ in 0..steps {
        let p: Vec<f32> = (0..3).map(|c| t.mul_add(d[c], o[c])).collect();
        let mut dist = [0.0f32];
        k.eval(
            1,
            &[&p[0..1], &p[1..2], &p[2..3]],
            &mut [&mut dist],
            params,
            &mut [],
        );
        if dist[0] < eps {
            return (t, true);
        }
        t += dist[0];
        if t > t1 {
            return (t, false);
        }
    }
    (t, false)
}

/// The scene with 250 small spheres far away added to the union: an SDF of more than 2,000 IR nodes (each
/// sphere's center differs in every coordinate, so no subtraction is shared), which the marcher traces one
/// group of rays at a time.
fn large_scene() -> String {
    let mut body = "    let d0 = min(torus(p, 1.0, r), sphere(p - [0.0, 0.0, 1.2], 0.3));\n".to_string();
    for i in 0..250 {
        let (x, y, z) = (10.0 + 0.25 * i as f32, 0.5 * i as f32, 20.0 + 0.125 * i as f32);
        body += &format!(
            "    let d{} = min(d{i}, sphere(p - [{x}, {y}, {z}], 0.1));\n",
            i + 1
        );
    }
    format!("param r: f32 = 0.25\nfn sdf(p: vec3) -> f32 {{\n{body}    d250\n}}")
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn marcher_matches_the_plain_loop(n in 0usize..70, seed in any::<u64>(), steps in 1u32..80, large in any::<bool>()) {
        let source = if large { large_scene() } else { SCENE.to_string() };
        let program = compile("scene.sdf", &source).unwrap();
        let f = program.lower("sdf").unwrap();
        let kernel = Kernel::compile(&kernel_graphs::value(&f), Options::default()).unwrap();
        let marcher = Marcher::compile(&kernel_graphs::value(&f)).unwrap();
        prop_assert_eq!(marcher.groups(), if large { 1 } else { 4 });
        let mut rng = nerfjit_dsl::init::SplitMix64::new(seed);
        let mut u = || rng.uniform() as f32 * 2.0 - 1.0;
        let mut cols: Vec<Vec<f32>> = vec![Vec::new(); 8];
        for i in 0..n {
            let o = [3.0 * u(), 3.0 * u(), 3.0];
            // Every other ray aims inside the torus's tube (it must hit); the others near the center, where
            // they may pass through the hole.
            let target = if i % 2 == 0 {
                let angle = std::f32::consts::PI * u();
                [angle.cos(), angle.sin(), 0.1 * u()]
            } else {
                [0.6 * u(), 0.6 * u(), 0.2 * u()]
            };
            let d: Vec<f32> = (0..3).map(|c| target[c] - o[c]).collect();
            let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            for c in 0..3 {
                cols[c].push(o[c]);
                cols[3 + c].push(d[c] / len);
            }
            cols[6].push(0.5 * u().abs());
            cols[7].push(6.0);
        }
        let rays = MarchRays {
            origin: [&cols[0], &cols[1], &cols[2]],
            direction: [&cols[3], &cols[4], &cols[5]],
            t0: &cols[6],
            t1: &cols[7],
        };
        let (mut t, mut hit) = (vec![0.0; n], vec![0.0; n]);
        marcher.march(n, &rays, &program.param_values, Stop { eps: 1e-4, max_steps: steps }, &mut t, &mut hit);
        let mut hits = 0;
        for i in 0..n {
            let o = [cols[0][i], cols[1][i], cols[2][i]];
            let d = [cols[3][i], cols[4][i], cols[5][i]];
            let (want_t, want_hit) = plain(&kernel, o, d, (cols[6][i], 6.0), Stop { eps: 1e-4, max_steps: steps }, &program.param_values);
            prop_assert_eq!(hit[i] == 1.0, want_hit, "ray {}", i);
            prop_assert!(hit[i] == 0.0 || hit[i] == 1.0);
            // Where the march stopped, hit or miss, to the bit.
            prop_assert_eq!(t[i].to_bits(), want_t.to_bits(), "ray {}", i);
            hits += usize::from(want_hit);
        }
        // Half the rays aim into the torus: the test must see hits when rays march long enough.
        prop_assert!(n < 20 || steps < 40 || hits > 0);
    }
}
