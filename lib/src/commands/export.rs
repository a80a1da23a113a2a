//! `nerfjit export`: a bake (`.bake`) in a file other tools open — the 3D Gaussian splatting `.ply` of its
//! splats, or a textured glTF 2.0 binary of the surface they make ([`nerfjit_runtime::splats::surface`]:
//! their opacity accumulated on a grid, meshed at a level by marching cubes, the texture their colors).

use std::path::Path;
use std::time::Instant;

use nerfjit_runtime::splats::surface::{median_scale, DEFAULT_LEVEL};
use nerfjit_runtime::splats::{splat_surface, write_splat_ply, SplatColors, SurfaceOptions};
use nerfjit_runtime::surfaces::atlas::{bake_atlas, pair_triangles, AtlasLayout, DEFAULT_SIDE, MAX_SIDE};
use nerfjit_runtime::surfaces::glb::write_glb;
use nerfjit_runtime::Up;

use crate::bake_file;
use crate::failure::{Failure, Result};

/// The formats `nerfjit export` writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ExportFormat {
    /// The 3D Gaussian splatting `.ply`.
    SplatPly,
    /// A glTF 2.0 binary of the splats' surface, textured with their colors.
    Glb,
}

/// How `nerfjit export --format glb` meshes and textures the splats.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GlbOptions {
    /// The grid and the level (see [`SurfaceOptions`]).
    pub surface: SurfaceOptions,
    /// Texels along a side of each triangle's patch; `None` for the largest up to 8 within 4096².
    pub texels: Option<usize>,
    /// The scene's up axis (the file's node turns z up to glTF's y).
    pub up: Up,
}

impl Default for GlbOptions {
    fn default() -> GlbOptions {
        GlbOptions {
            surface: SurfaceOptions {
                bounds: None,
                resolution: None,
                level: DEFAULT_LEVEL,
            },
            texels: None,
            up: Up::Y,
        }
    }
}

/// `nerfjit export SCENE.bake --format FORMAT --out FILE`: the bake in a file other tools open; `glb` says
/// how to mesh it (only for [`ExportFormat::Glb`]: `None` otherwise).
pub fn export(bake: &Path, format: ExportFormat, out: &Path, glb: Option<&GlbOptions>) -> Result<String> {
    let wanted = match format {
        ExportFormat::SplatPly => "ply",
        ExportFormat::Glb => "glb",
    };
    if out.extension().and_then(|e| e.to_str()) != Some(wanted) {
        return Err(Failure::Message(format!(
            "cannot write '{}': the format writes a .{wanted} file",
            out.display()
        )));
    }
    if format != ExportFormat::Glb && glb.is_some() {
        return Err(Failure::Message(
            "--res, --level, --bounds, --texels and --up are for --format glb: a splat .ply holds the splats as they are"
                .into(),
        ));
    }
    let scene = bake_file::read(bake)?;
    match format {
        ExportFormat::SplatPly => {
            write_splat_ply(&scene.splats, out)?;
            let bytes = std::fs::metadata(out).map_or(0, |m| m.len());
            Ok(format!(
                "{} splats → {} ({:.1} MB, the 3D Gaussian splatting layout)",
                scene.splats.len(),
                out.display(),
                bytes as f64 / 1e6
            ))
        }
        ExportFormat::Glb => export_glb(&scene.splats, out, glb.copied().unwrap_or_default()),
    }
}

/// Meshes and textures `splats` into a glTF binary at `out`; returns a summary.
fn export_glb(splats: &nerfjit_runtime::splats::Splats, out: &Path, options: GlbOptions) -> Result<String> {
    let start = Instant::now();
    let (grid, mesh) = splat_surface(splats, &options.surface)?;
    let meshed_s = start.elapsed().as_secs_f64();
    let t = Instant::now();
    let patches = pair_triangles(&mesh);
    let layout = match options.texels {
        Some(texels) => AtlasLayout::new(patches.len(), texels)?,
        None => AtlasLayout::fitting(patches.len(), DEFAULT_SIDE).ok_or_else(|| {
            Failure::Message(format!(
                "the texture of {} triangles would be more than {DEFAULT_SIDE} texels a side: lower --res, or \
                 ask for --texels 2 (up to {MAX_SIDE} texels a side)",
                mesh.triangles.len()
            ))
        })?,
    };
    let paired = 2 * patches.iter().filter(|p| p.second.is_some()).count();
    let atlas = bake_atlas(&mesh, patches, &SplatColors(&grid), layout)?;
    write_glb(&mesh, Some(&atlas), options.up, out)?;
    let textured_s = t.elapsed().as_secs_f64();
    let bytes = std::fs::metadata(out).map_or(0, |m| m.len());
    let (min, max) = grid.bounds();
    Ok(format!(
        "{} of {} splats accumulated on {}³ cells of [{:.3}, {:.3}, {:.3}]–[{:.3}, {:.3}, {:.3}] (cells {:.4} wide; the \
         median scale of the splats within them {:.4}; {} blocks of 8³ points stored; opacity peaking at {:.2}), meshed at level {} \
         in {meshed_s:.2} s: {} triangles ({}), textured in {textured_s:.2} s ({}×{} texels: {} patches of {}², \
         {:.1}% of the triangles in pairs) → {} ({:.1} MB)",
        grid.splats,
        splats.len(),
        grid.resolution(),
        min[0],
        min[1],
        min[2],
        max[0],
        max[1],
        max[2],
        (max[0] - min[0]) / grid.resolution() as f32,
        median_scale(splats, (min, max)).unwrap_or(0.0),
        grid.stored,
        grid.peak,
        options.surface.level,
        mesh.triangles.len(),
        if mesh.is_closed() { "closed" } else { "open" },
        atlas.layout.width(),
        atlas.layout.height(),
        atlas.patches.len(),
        atlas.layout.patch,
        100.0 * paired as f64 / mesh.triangles.len() as f64,
        out.display(),
        bytes as f64 / 1e6
    ))
}
