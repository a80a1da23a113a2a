//! `nerfjit mesh`: the marching-cubes mesh of a script's scalar function, as PLY or OBJ, with an optional
//! turntable GIF of the mesh.

use std::path::Path;
use std::time::Instant;

use glam::{Vec2, Vec3};
use nerfjit_dsl::Type;
use nerfjit_jit::KernelCache;
use nerfjit_runtime::marching::extract;
use nerfjit_runtime::raster::render_mesh;
use nerfjit_runtime::{save_gif, Camera};

use crate::failure::{Failure, Result};
use crate::field::{Compiler, Kind};
use crate::script;

/// What to extract and where to write it.
pub struct MeshArgs<'a> {
    /// The script.
    pub script: &'a str,
    /// The function whose level set is meshed (`fn f(p: vec3) -> f32`).
    pub function: &'a str,
    /// Grid cells per axis.
    pub resolution: usize,
    /// The grid's corners.
    pub bounds: ([f32; 3], [f32; 3]),
    /// The level (0 for an SDF's surface).
    pub level: f32,
    /// `.ply` or `.obj`.
    pub out: &'a Path,
    /// A turntable GIF of the mesh, if wanted.
    pub gif: Option<&'a Path>,
}

/// Parses `--bounds`: `r` for [−r, r]³, or six numbers `x0,y0,z0,x1,y1,z1`.
pub fn parse_bounds(text: &str) -> std::result::Result<([f32; 3], [f32; 3]), String> {
    let numbers: Vec<f32> = text
        .split(',')
        .map(|x| {
            x.trim()
                .parse::<f32>()
                .map_err(|e| format!("bad number '{x}' in --bounds: {e}"))
        })
        .collect::<std::result::Result<_, _>>()?;
    match numbers[..] {
        [r] if r > 0.0 => Ok(([-r; 3], [r; 3])),
        [x0, y0, z0, x1, y1, z1] if x0 < x1 && y0 < y1 && z0 < z1 => Ok(([x0, y0, z0], [x1, y1, z1])),
        _ => Err(
            "--bounds takes r > 0 (for [-r, r]³) or x0,y0,z0,x1,y1,z1 with each low below its high".into(),
        ),
    }
}

/// Extracts and writes the mesh; returns a summary line.
pub fn run(args: &MeshArgs) -> Result<String> {
    let ext = args.out.extension().and_then(|e| e.to_str()).unwrap_or("");
    if !matches!(ext, "ply" | "obj") {
        return Err(Failure::Message(format!(
            "cannot write '{}': use a .ply or .obj file",
            args.out.display()
        )));
    }
    for path in std::iter::once(args.out).chain(args.gif) {
        let folder = path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        if !folder.is_dir() {
            return Err(Failure::Message(format!(
                "cannot write '{}': folder '{}' does not exist",
                path.display(),
                folder.display()
            )));
        }
    }
    let program = script::load(args.script)?;
    let cache = KernelCache::new();
    let compiler = Compiler {
        program: &program,
        params: &program.param_values,
        cache: &cache,
    };
    let vec3 = [Type::Vec(3)];
    let t = Instant::now();
    let value = compiler.function(args.function, &vec3, &Type::F32, Kind::Value)?;
    let gradient = compiler.function(args.function, &vec3, &Type::F32, Kind::Gradient)?;
    let compile_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let mesh = extract(&value, Some(&gradient), args.bounds, args.resolution, args.level)?;
    let extract_s = t.elapsed().as_secs_f64();
    if ext == "ply" {
        mesh.write_ply(args.out)?;
    } else {
        mesh.write_obj(args.out)?;
    }
    if let Some(gif) = args.gif {
        let (lo, hi) = args.bounds;
        let center = Vec3::from_array(lo).lerp(Vec3::from_array(hi), 0.5);
        let radius = 1.6 * (Vec3::from_array(hi) - Vec3::from_array(lo)).length();
        // A turntable around the grid's center, 25° above it.
        let elevation = 25f32.to_radians();
        let frames = (0..36)
            .map(|i| {
                let phi = std::f32::consts::TAU * i as f32 / 36.0 + std::f32::consts::FRAC_PI_2;
                let flat = radius * elevation.cos();
                let eye = center + Vec3::new(flat * phi.cos(), radius * elevation.sin(), -flat * phi.sin());
                let camera = Camera::look_at(eye, center, Vec3::Y, Vec2::splat(1.2), Vec2::ZERO)?;
                render_mesh(
                    &camera,
                    256,
                    256,
                    &mesh,
                    Vec3::new(-0.5, 1.0, -0.8),
                    [0.85, 0.8, 0.7],
                    [0.1, 0.11, 0.14],
                )
            })
            .collect::<nerfjit_runtime::Result<Vec<_>>>()?;
        save_gif(gif, &frames, 50)?;
    }
    Ok(format!(
        "meshed '{}' at level {} on {}³ cells in {extract_s:.3} s (JIT compile {compile_s:.3} s): {} vertices, {} triangles, {} → {}",
        args.function,
        args.level,
        args.resolution,
        mesh.vertices.len(),
        mesh.triangles.len(),
        if mesh.is_closed() { "closed" } else { "open (the surface leaves the grid or is not closed)" },
        args.out.display()
    ))
}
