//! Validation: rendering held-out views and scoring them against their images (PSNR, SSIM, PSNR inside
//! their masks), as `train` validates and `nerfjit eval-views` scores a checkpoint.

use nerfjit_runtime::{psnr, ssim, Camera, ImageF32, OccupancyGrid, Views, VolumeFrame, VolumeSettings};

use crate::failure::{Failure, Result};
use nerfjit_field::VolumeFields;

/// Renders a camera's view at a size: a field's volume render, or a baked scene's.
pub type ViewRenderer<'a> = dyn Fn(&Camera, (u32, u32)) -> Result<VolumeFrame> + 'a;

/// A field's views: `fields` with `params`, rendered with `settings` (and `grid`, the occupancy grid to
/// skip empty space with).
pub fn field_renderer<'a>(
    fields: &'a VolumeFields,
    params: &'a [f32],
    settings: &'a VolumeSettings,
    grid: Option<&'a OccupancyGrid>,
) -> impl Fn(&Camera, (u32, u32)) -> Result<VolumeFrame> + 'a {
    move |camera, size| Ok(fields.render_with(camera, size, params, settings, grid)?)
}

/// One view's scores against its image.
#[derive(Clone, Copy, Debug)]
pub struct ViewScore {
    /// PSNR over the whole image, in dB.
    pub psnr: f32,
    /// SSIM over the whole image.
    pub ssim: f32,
    /// PSNR inside the view's object mask, when the views have masks (DTU's protocol).
    pub masked_psnr: Option<f32>,
}

/// The mean of every view's scores.
#[derive(Clone, Copy, Debug)]
pub struct MeanScores {
    /// Mean PSNR in dB.
    pub psnr: f64,
    /// Mean SSIM.
    pub ssim: f64,
    /// Mean PSNR inside the masks, over the views whose mask holds pixels.
    pub masked_psnr: Option<f64>,
}

/// Renders every view of `views` with `render` and scores it against its image: PSNR, SSIM, and PSNR inside
/// its mask when the views have masks. The views are split over the ranks of the [`crate::cluster`]: every
/// rank scores its share and rank 0 gets every view's scores, in order; the other ranks get `None` (one
/// process gets them all).
pub fn score_on_ranks(views: &Views, render: &ViewRenderer) -> Result<Option<Vec<ViewScore>>> {
    let scored = crate::cluster::split(views.cameras.len(), |i| -> Result<Vec<u8>> {
        let s = score_view(i, views, render)?;
        let masked = s.masked_psnr.unwrap_or(f32::NAN);
        Ok(crate::cluster::f32_bytes(&[s.psnr, s.ssim, masked]))
    })
    .map_err(Failure::Message)?;
    let Some(all) = scored else {
        return Ok(None);
    };
    all.iter()
        .map(|bytes| match crate::cluster::f32s_of(bytes)[..] {
            [psnr, ssim, masked] => Ok(ViewScore {
                psnr,
                ssim,
                masked_psnr: Some(masked).filter(|m| !m.is_nan()),
            }),
            _ => Err(Failure::Message(
                "a rank sent a view's scores that do not read".into(),
            )),
        })
        .collect::<Result<Vec<_>>>()
        .map(Some)
}

/// View `i` rendered and scored against its image.
fn score_view(i: usize, views: &Views, render: &ViewRenderer) -> Result<ViewScore> {
    let camera = &views.cameras[i];
    let target = &views.images[i];
    let f = render(camera, (views.width, views.height))?;
    let rendered = ImageF32 {
        width: f.width,
        height: f.height,
        pixels: f.rgb,
    };
    let mse = nerfjit_runtime::mse(&rendered, target)?;
    let mask = views.masks.as_ref().and_then(|m| m.get(i));
    let masked_mse = match mask {
        Some(mask) => nerfjit_runtime::masked_mse(&rendered, target, mask)?,
        None => None,
    };
    Ok(ViewScore {
        psnr: psnr(mse),
        ssim: ssim(&rendered, target)?,
        masked_psnr: masked_mse.map(psnr),
    })
}

/// The mean of `scores`.
pub fn means(scores: &[ViewScore]) -> MeanScores {
    let mean = |values: Vec<f32>| {
        let n = values.len();
        (n > 0).then(|| values.iter().map(|&v| f64::from(v)).sum::<f64>() / n as f64)
    };
    MeanScores {
        psnr: mean(scores.iter().map(|s| s.psnr).collect()).unwrap_or(0.0),
        ssim: mean(scores.iter().map(|s| s.ssim).collect()).unwrap_or(0.0),
        masked_psnr: mean(scores.iter().filter_map(|s| s.masked_psnr).collect()),
    }
}
