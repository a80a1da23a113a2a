//! Times the sphere tracer on a torus seen from a turntable path, with hand-written
//! structure-of-arrays kernels standing in for JIT-compiled ones, and writes a looping GIF
//! plus the depth and normal maps of its first frame.
//!
//! `cargo run -p nerfjit-runtime --release --example torus_timing -- [out.gif]`

use std::path::Path;
use std::time::Instant;

use glam::Vec3;
use nerfjit_runtime::{
    depth_image, normal_image, render_frames, rgb_image, save_gif, save_png, surround, BatchFn, Quantize,
    Shading, TraceSettings, Up,
};

/// Distance to the torus of radii (1, 0.35) around the y axis, in a loop that vectorizes.
struct TorusSdf;

impl BatchFn for TorusSdf {
    fn n_inputs(&self) -> usize {
        3
    }

    fn n_outputs(&self) -> usize {
        1
    }

    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        let (x, y, z) = (&inputs[0][..n], &inputs[1][..n], &inputs[2][..n]);
        let points = x.iter().zip(y).zip(z);
        for (((x, y), z), d) in points.zip(&mut outputs[0][..n]) {
            let qx = (x * x + z * z).sqrt() - 1.0;
            *d = (qx * qx + y * y).sqrt() - 0.35;
        }
    }
}

/// The torus distance and its gradient.
struct TorusGradient;

impl BatchFn for TorusGradient {
    fn n_inputs(&self) -> usize {
        3
    }

    fn n_outputs(&self) -> usize {
        4
    }

    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        for k in 0..n {
            let (x, y, z) = (inputs[0][k], inputs[1][k], inputs[2][k]);
            let ring = (x * x + z * z).sqrt();
            let len = ((ring - 1.0) * (ring - 1.0) + y * y).sqrt();
            let s = (ring - 1.0) / (len * ring);
            outputs[0][k] = len - 0.35;
            outputs[1][k] = x * s;
            outputs[2][k] = y / len;
            outputs[3][k] = z * s;
        }
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::args().nth(1).unwrap_or_else(|| "torus.gif".into());
    let cameras = surround(3.0, 60, Up::Y, 1.5)?;
    let shading = Shading::Lambert {
        gradient: &TorusGradient,
        light_dir: Vec3::new(1.0, 1.0, -1.0),
        albedo: [0.9, 0.6, 0.3],
    };
    for bounds in [None, Some((Vec3::ZERO, 1.4))] {
        let settings = TraceSettings {
            max_steps: 64,
            eps: 1e-4,
            bounds,
            ..TraceSettings::default()
        };
        let start = Instant::now();
        let frames = render_frames(&cameras, 256, 256, &TorusSdf, &shading, &settings, None)?;
        let per_frame = start.elapsed().as_secs_f64() * 1e3 / frames.len() as f64;
        println!("bounds {bounds:?}: {per_frame:.3} ms per 256×256 frame");
        if bounds.is_some() {
            let images = frames
                .iter()
                .map(|f| rgb_image(f.width, f.height, &f.rgb, Quantize::Round))
                .collect::<Result<Vec<_>, _>>()?;
            let out = Path::new(&out);
            save_gif(out, &images, 40)?;
            save_png(
                &out.with_extension("depth.png"),
                depth_image(&frames[0], 1.0, 4.5)?,
            )?;
            save_png(&out.with_extension("normal.png"), normal_image(&frames[0])?)?;
        }
    }
    Ok(())
}
