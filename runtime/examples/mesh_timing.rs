//! Times marching cubes of a sphere SDF (a `ClosureFn`) at resolution 256 and the distance
//! metrics of 10,000 points against a mesh of about 100,000 triangles, and writes previews
//! of the mesh and of the points.
//!
//! `cargo run -p nerfjit-runtime --release --example mesh_timing -- [out-folder]`

use std::path::PathBuf;
use std::time::Instant;

use glam::{Vec2, Vec3};
use nerfjit_runtime::surfaces::marching::extract;
use nerfjit_runtime::{
    chamfer_report, point_to_mesh_distances, render_mesh, render_points, save_png, Camera, ClosureFn,
};

fn main() -> nerfjit_runtime::Result<()> {
    let out = PathBuf::from(std::env::args().nth(1).unwrap_or_else(|| ".".into()));
    let sphere = ClosureFn::new(3, 1, |p, out| {
        out[0] = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 0.8
    });
    let bounds = ([-1.0; 3], [1.0; 3]);
    for resolution in [256, 128] {
        let start = Instant::now();
        let mesh = extract(&sphere, None, bounds, resolution, 0.0)?;
        println!(
            "marching cubes at {resolution}: {} vertices, {} triangles, closed {}, in {:.0} ms",
            mesh.vertices.len(),
            mesh.triangles.len(),
            mesh.is_closed(),
            start.elapsed().as_secs_f64() * 1e3
        );
    }
    // About 100k triangles.
    let mesh = extract(&sphere, None, bounds, 128, 0.0)?;
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    let points: Vec<[f32; 3]> = (0..10_000)
        .map(|k| {
            let z = 1.0 - 2.0 * (k as f32 + 0.5) / 10_000.0;
            let (r, a) = ((1.0 - z * z).sqrt(), golden * k as f32);
            [0.82 * r * a.cos(), 0.82 * r * a.sin(), 0.82 * z]
        })
        .collect();
    let start = Instant::now();
    let distances = point_to_mesh_distances(&points, &mesh)?;
    let elapsed = start.elapsed().as_secs_f64() * 1e3;
    let mean = distances.iter().sum::<f32>() / distances.len() as f32;
    println!(
        "{} points to {} triangles: mean {mean:.5} (expected 0.02) in {elapsed:.1} ms",
        points.len(),
        mesh.triangles.len()
    );
    let start = Instant::now();
    let report = chamfer_report(&points, &mesh)?;
    println!(
        "chamfer report {report:?} in {:.1} ms",
        start.elapsed().as_secs_f64() * 1e3
    );

    let camera = Camera::look_at(
        Vec3::new(1.5, 1.0, 2.5),
        Vec3::ZERO,
        Vec3::Y,
        Vec2::splat(2.0),
        Vec2::ZERO,
    )?;
    let start = Instant::now();
    let image = render_mesh(
        &camera,
        512,
        512,
        &mesh,
        Vec3::new(1.0, 2.0, 1.5),
        [0.9, 0.8, 0.6],
        [0.1; 3],
    )?;
    println!("mesh preview in {:.1} ms", start.elapsed().as_secs_f64() * 1e3);
    save_png(&out.join("mesh_preview.png"), image)?;
    let image = render_points(&camera, 512, 512, &points, 2.0, [0.3, 0.6, 1.0], [1.0; 3])?;
    save_png(&out.join("points_preview.png"), image)?;
    Ok(())
}
