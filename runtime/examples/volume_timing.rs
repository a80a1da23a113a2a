//! Times the volume renderer on the course's box volume (workload W2: 256×256, 64 samples at
//! linspace(0, 5, 64), surround(3.0, 20, up y, focal 1.0)) with one thread and with all of
//! them, for fields of different cost, and writes the turntable as a GIF.
//!
//! `cargo run -p nerfjit-runtime --release --example volume_timing -- [out.gif]`

use std::path::Path;
use std::time::Instant;

use nerfjit_runtime::{
    render_volume, rgb_image, save_gif, surround, BatchFn, Camera, ClosureFn, Mode, Quantize, Up,
    VolumeSettings,
};

/// The course's box: center 0, sides 1.75³, opacity from the SDF with α = 1, β = 0.05, color
/// clamp(|p|, 0.02, 0.98).
fn box_point(p: &[f32], out: &mut [f32]) {
    let q = [0, 1, 2].map(|i| p[i].abs() - 0.875);
    let outside = q.iter().map(|q| q.max(0.0).powi(2)).sum::<f32>().sqrt();
    let s = outside + q[0].max(q[1]).max(q[2]).min(0.0);
    out[0] = if s > 0.0 {
        0.5 * (-s / 0.05).exp()
    } else {
        1.0 - 0.5 * (s / 0.05).exp()
    };
    for i in 0..3 {
        out[1 + i] = p[i].abs().clamp(0.02, 0.98);
    }
}

/// The cheapest possible field, to measure the renderer's own cost per sample.
struct Constant;

impl BatchFn for Constant {
    fn n_inputs(&self) -> usize {
        3
    }

    fn n_outputs(&self) -> usize {
        4
    }

    fn eval(&self, n: usize, _inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        for (o, v) in outputs.iter_mut().zip([0.01, 0.2, 0.5, 0.8]) {
            o[..n].fill(v);
        }
    }
}

/// Median milliseconds per frame over the turntable, after one warm-up frame.
fn time_frames(cameras: &[Camera], field: &dyn BatchFn, settings: &VolumeSettings) -> f64 {
    render_volume(&cameras[0], 256, 256, field, settings).expect("render");
    let mut times: Vec<f64> = cameras
        .iter()
        .map(|camera| {
            let start = Instant::now();
            render_volume(camera, 256, 256, field, settings).expect("render");
            start.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[times.len() / 2]
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::args().nth(1).unwrap_or_else(|| "box_volume.gif".into());
    let cameras = surround(3.0, 20, Up::Y, 1.0)?;
    let settings = VolumeSettings {
        near: 0.0,
        far: 5.0,
        samples: 64,
        mode: Mode::Opacity,
        background: None,
        early_termination: None,
    };
    let boxed = ClosureFn::new(3, 4, box_point);
    let cheap = ClosureFn::new(3, 4, |p: &[f32], out: &mut [f32]| {
        out[0] = (0.1 * (p[0] + p[1])).max(0.0);
        out[1..].copy_from_slice(&p[..3]);
    });
    let fields: [(&str, &dyn BatchFn); 3] = [
        ("constant BatchFn", &Constant),
        ("cheap ClosureFn", &cheap),
        ("box ClosureFn", &boxed),
    ];
    let threads = rayon::current_num_threads();
    for (name, field) in fields {
        for n in [1, threads] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(n).build()?;
            let ms = pool.install(|| time_frames(&cameras, field, &settings));
            let ns = ms * 1e6 * n as f64 / (256.0 * 256.0 * 64.0);
            println!("{name:>16}, {n} thread(s): {ms:.2} ms per 256×256×64 frame ({ns:.2} ns per sample per thread)");
        }
    }
    let early = VolumeSettings {
        early_termination: Some(1e-3),
        ..settings
    };
    let ms = time_frames(&cameras, &boxed, &early);
    println!("box ClosureFn, early termination 1e-3, {threads} thread(s): {ms:.2} ms per frame");
    let images = cameras
        .iter()
        .map(|camera| {
            let frame = render_volume(camera, 256, 256, &boxed, &settings)?;
            rgb_image(frame.width, frame.height, &frame.rgb, Quantize::Round)
        })
        .collect::<Result<Vec<_>, _>>()?;
    save_gif(Path::new(&out), &images, 80)?;
    Ok(())
}
