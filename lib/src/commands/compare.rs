//! `nerfjit compare`: renders of several trained fields from one camera as a labeled grid — rows (say
//! NeRF and VolSDF), columns (say trained on 100, 20, 10 and 5 views) — beside the target image, each
//! with its PSNR: the course's fewer-views comparison as one image.

use std::path::Path;

use nerfjit_jit::KernelCache;
use nerfjit_runtime::output::label::{draw_text, text_height, text_width};
use nerfjit_runtime::splats::render_splats;
use nerfjit_runtime::{mse, psnr, rgb_image, save_png, ImageF32, Layout, Quantize};

use crate::commands::render_views::ViewArgs;
use crate::failure::{Failure, Result};
use crate::training::data_source::{scored_views, ScoredViews};
use nerfjit_field::VolumeFields;

/// One row of the grid: its label and one script or checkpoint per column.
#[derive(Clone, Debug)]
pub struct Row {
    /// Drawn left of the row.
    pub label: String,
    /// What each column renders.
    pub sources: Vec<String>,
}

/// Parses `LABEL=a.json,b.json,...`.
pub fn parse_row(text: &str) -> std::result::Result<Row, String> {
    let (label, list) = text
        .split_once('=')
        .ok_or_else(|| format!("'{text}': write a row as LABEL=first.ckpt.json,second.ckpt.json,..."))?;
    Ok(Row {
        label: label.to_string(),
        sources: list.split(',').map(str::to_string).collect(),
    })
}

const PAD: usize = 6;
const SCALE: usize = 2;
const BACKGROUND: [f32; 3] = [0.12, 0.12, 0.14];
const INK: [f32; 3] = [0.95, 0.95, 0.95];

/// The field an entry of the grid shows: a script or checkpoint itself, or the checkpoint a `.bake` was
/// baked from.
fn field_of(source: &str) -> Result<String> {
    Ok(match crate::bake_file::is_bake(Path::new(source)) {
        true => crate::bake_file::read(Path::new(source))?
            .source
            .to_string_lossy()
            .into_owned(),
        false => source.to_string(),
    })
}

/// Renders the grid of `rows` × `columns` (plus the target column) from view `index` of `cameras` (read as
/// `eval-views` reads them, a folder holding several layouts as `format`); settings
/// not given in `args` come from the first entry's script (the target is composited on its background).
pub fn compare(
    args: &ViewArgs,
    cameras: &Path,
    format: Option<Layout>,
    index: usize,
    columns: &[String],
    rows: &[Row],
    out: &Path,
) -> Result<String> {
    if rows.is_empty() {
        return Err(Failure::Message("compare needs at least one --row".into()));
    }
    if let Some(row) = rows.iter().find(|r| r.sources.len() != columns.len()) {
        return Err(Failure::Message(format!(
            "row '{}' has {} entries for {} columns",
            row.label,
            row.sources.len(),
            columns.len()
        )));
    }
    let first_source = field_of(&rows[0].sources[0])?;
    let (first, _) = crate::checkpoint::load_source(&first_source)?;
    let background = args.resolve(&first).background;
    let trained = crate::commands::render_views::trained_data(&first_source, &first);
    let views = scored_views(&ScoredViews {
        cameras,
        format,
        width: args.size,
        background,
        trained: trained.as_ref(),
    })?
    .views;
    let (Some(camera), Some(target)) = (views.cameras.get(index), views.images.get(index)) else {
        return Err(Failure::Message(format!(
            "view {index} does not exist: {} has {} views",
            cameras.display(),
            views.cameras.len()
        )));
    };
    let cache = KernelCache::new();
    let mut cells: Vec<Vec<(ImageF32, f32)>> = Vec::new();
    for row in rows {
        let mut rendered = Vec::new();
        for source in &row.sources {
            let f = match crate::bake_file::is_bake(Path::new(source)) {
                true => {
                    let bake = crate::bake_file::read(Path::new(source))?;
                    let shader = nerfjit_field::splat_shader()?;
                    render_splats(
                        &bake.splats,
                        shader,
                        camera,
                        views.width,
                        views.height,
                        background,
                    )?
                    .0
                }
                false => {
                    let (program, params) = crate::checkpoint::load_source(source)?;
                    let rendering = crate::commands::render_views::Rendering {
                        background,
                        ..args.resolve(&program)
                    };
                    let fields =
                        VolumeFields::compile(&program, &cache, rendering.importance, rendering.products)?;
                    let settings = rendering.settings(fields.fine.mode);
                    let grid = rendering.occupancy(source, &fields, &params)?;
                    let size = (views.width, views.height);
                    fields.render_with(camera, size, &params, &settings, grid.as_ref())?
                }
            };
            let image = ImageF32 {
                width: f.width,
                height: f.height,
                pixels: f.rgb,
            };
            let p = psnr(mse(&image, target)?);
            rendered.push((image, p));
        }
        cells.push(rendered);
    }

    let (cw, ch) = (views.width as usize, views.height as usize);
    let text_h = text_height(SCALE);
    let labels = rows.iter().map(|r| r.label.as_str()).chain(["target"]);
    let left = labels.map(|l| text_width(l, SCALE)).max().unwrap_or(0) + 2 * PAD;
    let top = text_h + 2 * PAD;
    let cell_h = ch + text_h + 2 * PAD;
    // Columns as wide as their image, label and caption ("99.99 dB").
    let col_w = columns
        .iter()
        .map(|c| text_width(c, SCALE))
        .chain([cw, text_width("99.99 dB", SCALE)])
        .max()
        .unwrap_or(cw)
        + 2 * PAD;
    let width = left + (columns.len() + 1) * col_w;
    let height = top + rows.len() * cell_h;
    let mut pixels = vec![BACKGROUND; width * height];
    let blit = |pixels: &mut [[f32; 3]], x0: usize, y0: usize, image: &ImageF32| {
        for y in 0..ch {
            pixels[(y0 + y) * width + x0..(y0 + y) * width + x0 + cw]
                .copy_from_slice(&image.pixels[y * cw..(y + 1) * cw]);
        }
    };
    draw_text(&mut pixels, width, left, PAD, "target", SCALE, INK);
    for (c, name) in columns.iter().enumerate() {
        draw_text(&mut pixels, width, left + (c + 1) * col_w, PAD, name, SCALE, INK);
    }
    for (r, (row, rendered)) in rows.iter().zip(&cells).enumerate() {
        let y0 = top + r * cell_h;
        draw_text(&mut pixels, width, PAD, y0 + ch / 2, &row.label, SCALE, INK);
        blit(&mut pixels, left, y0, target);
        for (c, (image, p)) in rendered.iter().enumerate() {
            let x0 = left + (c + 1) * col_w;
            blit(&mut pixels, x0, y0, image);
            draw_text(
                &mut pixels,
                width,
                x0,
                y0 + ch + PAD,
                &format!("{p:.2} dB"),
                SCALE,
                INK,
            );
        }
    }
    save_png(
        out,
        rgb_image(width as u32, height as u32, &pixels, Quantize::Round)?,
    )?;
    let scores: Vec<String> = rows
        .iter()
        .zip(&cells)
        .map(|(row, rendered)| {
            let ps: Vec<String> = columns
                .iter()
                .zip(rendered)
                .map(|(c, (_, p))| format!("{c}: {p:.2} dB"))
                .collect();
            format!("{}: {}", row.label, ps.join(", "))
        })
        .collect();
    Ok(format!("{}\nwrote {}", scores.join("\n"), out.display()))
}
