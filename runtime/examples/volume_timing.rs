//! Times the volume renderer on the course's box volume (workload W2: 256×256, 64 samples at
//! linspace(0, 5, 64), surround(3.0, 20, up y, focal 1.0)) with one thread and with all of
//! them, for fields of different cost, then with an occupancy grid (empty-space skipping) and
//! early termination, and writes the turntable as a GIF.
//!
//! `cargo run -p nerfjit-runtime --release --example volume_timing -- [out.gif]`

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use nerfjit_runtime::{
    render_volume, render_volume_with, rgb_image, save_gif, surround, BatchFn, Camera, ClosureFn, Mode,
    OccupancyGrid, Quantize, Up, VolumeSettings,
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

/// A field that counts the points it evaluates.
struct Counting<'a>(&'a dyn BatchFn, AtomicUsize);

impl BatchFn for Counting<'_> {
    fn n_inputs(&self) -> usize {
        self.0.n_inputs()
    }

    fn n_outputs(&self) -> usize {
        self.0.n_outputs()
    }

    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        self.1.fetch_add(n, Ordering::Relaxed);
        self.0.eval(n, inputs, outputs);
    }
}

/// Median milliseconds per frame over the turntable, after one warm-up frame.
fn time_frames(cameras: &[Camera], field: &dyn BatchFn, settings: &VolumeSettings) -> f64 {
    time_frames_with(cameras, field, settings, None)
}

/// [`time_frames`] with an occupancy grid.
fn time_frames_with(
    cameras: &[Camera],
    field: &dyn BatchFn,
    settings: &VolumeSettings,
    grid: Option<&OccupancyGrid>,
) -> f64 {
    render_volume_with(&cameras[0], 256, 256, field, settings, grid).expect("render");
    let mut times: Vec<f64> = cameras
        .iter()
        .map(|camera| {
            let start = Instant::now();
            render_volume_with(camera, 256, 256, field, settings, grid).expect("render");
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
        spacing: nerfjit_runtime::DepthSpacing::Linear,
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

    // Empty-space skipping with an occupancy grid over the box and its falloff, alone and
    // with early termination: time, samples evaluated and error against the exact render.
    let start = Instant::now();
    let grid = OccupancyGrid::build(&boxed, ([-1.25; 3], [1.25; 3]), 64, Mode::Opacity, 1e-4)?;
    println!(
        "occupancy grid 64³ over [-1.25, 1.25]³, threshold 1e-4: built in {:.1} ms, {:.1}% occupied",
        start.elapsed().as_secs_f64() * 1e3,
        100.0 * grid.occupancy()
    );
    let counting = Counting(&boxed, AtomicUsize::new(0));
    for (name, s, grid) in [
        ("exact", &settings, None),
        ("early termination 1e-3", &early, None),
        ("grid", &settings, Some(&grid)),
        ("grid + early termination 1e-3", &early, Some(&grid)),
    ] {
        let ms = time_frames_with(&cameras, &boxed, s, grid);
        let (mut max, mut sum) = (0u8, 0u64);
        counting.1.store(0, Ordering::Relaxed);
        for camera in &cameras {
            let exact = render_volume(camera, 256, 256, &boxed, &settings)?;
            let frame = render_volume_with(camera, 256, 256, &counting, s, grid)?;
            for (a, b) in exact.rgb.iter().flatten().zip(frame.rgb.iter().flatten()) {
                let err = Quantize::Round.byte(*a).abs_diff(Quantize::Round.byte(*b));
                (max, sum) = (max.max(err), sum + err as u64);
            }
        }
        let frames = cameras.len() as f64;
        let evaluated = counting.1.load(Ordering::Relaxed) as f64 / frames / (256.0 * 256.0 * 64.0);
        println!(
            "box ClosureFn, {name:>29}, {threads} thread(s): {ms:.2} ms per frame, {:.1}% of samples evaluated, max |Δ| {max}/255, mean {:.4}/255",
            100.0 * evaluated,
            sum as f64 / (frames * 256.0 * 256.0 * 3.0)
        );
    }
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
