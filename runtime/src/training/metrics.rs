//! Image quality: mean squared error, PSNR and SSIM of RGB images with values in [0, 1].

use crate::data::npy::ImageF32;
use crate::error::{Error, Result};

/// Side of the SSIM window.
const WINDOW: usize = 11;
/// Standard deviation of the SSIM window's Gaussian.
const SIGMA: f64 = 1.5;
/// SSIM stabilizers (0.01·L)² and (0.03·L)² for the data range L = 1.
const C1: f64 = 0.01 * 0.01;
const C2: f64 = 0.03 * 0.03;

/// PSNR in dB of a mean squared error of colors in [0, 1]: −10·log10(mse) (infinite for 0).
pub fn psnr(mse: f32) -> f32 {
    -10.0 * mse.log10()
}

/// Checks that `a` and `b` are images of the same size with all their pixels.
fn check_pair(a: &ImageF32, b: &ImageF32) -> Result<()> {
    for img in [a, b] {
        if img.pixels.len() != img.width as usize * img.height as usize {
            return Err(Error::Invalid(format!(
                "{} pixels do not fill a {}×{} image",
                img.pixels.len(),
                img.width,
                img.height
            )));
        }
    }
    if (a.width, a.height) != (b.width, b.height) {
        return Err(Error::Invalid(format!(
            "cannot compare a {}×{} image with a {}×{} image",
            a.width, a.height, b.width, b.height
        )));
    }
    if a.pixels.is_empty() {
        return Err(Error::Invalid("cannot compare empty images".into()));
    }
    Ok(())
}

/// Mean squared error over all pixels and channels of two images of the same size.
pub fn mse(a: &ImageF32, b: &ImageF32) -> Result<f32> {
    check_pair(a, b)?;
    let sum: f64 = a
        .pixels
        .iter()
        .flatten()
        .zip(b.pixels.iter().flatten())
        .map(|(x, y)| f64::from(x - y).powi(2))
        .sum();
    Ok((sum / (3 * a.pixels.len()) as f64) as f32)
}

/// Mean squared error over the pixels of `mask` (one flag per pixel) and all channels, as DTU's
/// protocol scores renders inside the object's mask; `None` when the mask holds no pixel.
pub fn masked_mse(a: &ImageF32, b: &ImageF32, mask: &[bool]) -> Result<Option<f32>> {
    check_pair(a, b)?;
    if mask.len() != a.pixels.len() {
        return Err(Error::Invalid(format!(
            "a mask of {} pixels for an image of {}",
            mask.len(),
            a.pixels.len()
        )));
    }
    let (sum, count) = a
        .pixels
        .iter()
        .zip(&b.pixels)
        .zip(mask)
        .filter(|(_, &inside)| inside)
        .fold((0.0f64, 0usize), |(sum, count), ((x, y), _)| {
            let d: f64 = (0..3).map(|k| f64::from(x[k] - y[k]).powi(2)).sum();
            (sum + d, count + 1)
        });
    Ok((count > 0).then(|| (sum / (3 * count) as f64) as f32))
}

/// The normalized 1-D Gaussian of the SSIM window.
fn gaussian() -> [f64; WINDOW] {
    let half = (WINDOW / 2) as f64;
    let mut g = [0.0; WINDOW];
    for (i, w) in g.iter_mut().enumerate() {
        let x = i as f64 - half;
        *w = (-x * x / (2.0 * SIGMA * SIGMA)).exp();
    }
    let sum: f64 = g.iter().sum();
    g.map(|w| w / sum)
}

/// `image` (`width` wide, row-major) filtered by the separable window `g`, valid part only.
fn filter(image: &[f64], width: usize, g: &[f64; WINDOW]) -> Vec<f64> {
    let height = image.len() / width;
    let (w_out, h_out) = (width + 1 - WINDOW, height + 1 - WINDOW);
    let rows: Vec<f64> = (0..height)
        .flat_map(|y| {
            let row = &image[y * width..(y + 1) * width];
            (0..w_out).map(move |x| row[x..x + WINDOW].iter().zip(g).map(|(v, w)| v * w).sum())
        })
        .collect();
    (0..h_out)
        .flat_map(|y| {
            let rows = &rows;
            (0..w_out).map(move |x| (0..WINDOW).map(|k| rows[(y + k) * w_out + x] * g[k]).sum())
        })
        .collect()
}

/// Structural similarity of two images with values in [0, 1]: the mean SSIM over the valid
/// positions of an 11×11 Gaussian window (σ = 1.5), C1 = 0.01², C2 = 0.03², averaged over
/// the three channels. 1 for identical images. Both sides must be at least 11 pixels.
pub fn ssim(a: &ImageF32, b: &ImageF32) -> Result<f32> {
    check_pair(a, b)?;
    let (width, height) = (a.width as usize, a.height as usize);
    if width < WINDOW || height < WINDOW {
        return Err(Error::Invalid(format!(
            "SSIM needs images of at least {WINDOW}×{WINDOW} pixels, got {width}×{height}"
        )));
    }
    let g = gaussian();
    let mut total = 0.0;
    for c in 0..3 {
        let x: Vec<f64> = a.pixels.iter().map(|p| f64::from(p[c])).collect();
        let y: Vec<f64> = b.pixels.iter().map(|p| f64::from(p[c])).collect();
        let product = |u: &[f64], v: &[f64]| u.iter().zip(v).map(|(p, q)| p * q).collect::<Vec<_>>();
        let (mx, my) = (filter(&x, width, &g), filter(&y, width, &g));
        let (xx, yy, xy) = (
            filter(&product(&x, &x), width, &g),
            filter(&product(&y, &y), width, &g),
            filter(&product(&x, &y), width, &g),
        );
        let sum: f64 = (0..mx.len())
            .map(|i| {
                let (vx, vy, cov) = (
                    xx[i] - mx[i] * mx[i],
                    yy[i] - my[i] * my[i],
                    xy[i] - mx[i] * my[i],
                );
                ((2.0 * mx[i] * my[i] + C1) * (2.0 * cov + C2))
                    / ((mx[i] * mx[i] + my[i] * my[i] + C1) * (vx + vy + C2))
            })
            .sum();
        total += sum / mx.len() as f64;
    }
    Ok((total / 3.0) as f32)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn image(width: u32, height: u32, f: impl Fn(u32, u32) -> [f32; 3]) -> ImageF32 {
        ImageF32 {
            width,
            height,
            pixels: (0..height)
                .flat_map(|y| (0..width).map(move |x| (x, y)))
                .map(|(x, y)| f(x, y))
                .collect(),
        }
    }

    fn pattern(x: u32, y: u32) -> [f32; 3] {
        let s = (x as f32 * 0.3).sin() * (y as f32 * 0.2).cos();
        [
            0.5 + 0.4 * s,
            (x + y) as f32 / 80.0,
            if (x / 5 + y / 5).is_multiple_of(2) {
                0.2
            } else {
                0.8
            },
        ]
    }

    #[test]
    fn psnr_and_mse() {
        assert_eq!(psnr(0.01), 20.0);
        assert_eq!(psnr(1.0), 0.0);
        assert_eq!(psnr(0.0), f32::INFINITY);
        let a = image(4, 3, |_, _| [0.5; 3]);
        let b = image(4, 3, |x, _| if x == 0 { [0.5, 0.5, 0.9] } else { [0.5; 3] });
        // 3 of 36 values differ by 0.4.
        assert!((mse(&a, &b).unwrap() - 0.16 * 3.0 / 36.0).abs() < 1e-7);
        assert_eq!(mse(&a, &a).unwrap(), 0.0);
        // Inside a mask: only its pixels count; an empty mask has no score.
        let first_column: Vec<bool> = (0..12).map(|i| i % 4 == 0).collect();
        assert!((masked_mse(&a, &b, &first_column).unwrap().unwrap() - 0.16 / 3.0).abs() < 1e-7);
        let others: Vec<bool> = first_column.iter().map(|&c| !c).collect();
        assert_eq!(masked_mse(&a, &b, &others).unwrap(), Some(0.0));
        assert_eq!(masked_mse(&a, &b, &[false; 12]).unwrap(), None);
        assert!(masked_mse(&a, &b, &[true; 5]).is_err());
        assert!(mse(&a, &image(3, 4, |_, _| [0.0; 3])).is_err());
    }

    #[test]
    fn ssim_is_one_for_identical_images_and_drops_with_noise() {
        let a = image(40, 32, pattern);
        assert!((ssim(&a, &a).unwrap() - 1.0).abs() < 1e-6);
        let mut rng = Rng::new(4);
        let mut noisy = |amount: f32| {
            let mut b = a.clone();
            for v in b.pixels.iter_mut().flatten() {
                *v = (*v + amount * (rng.next_f32() - 0.5)).clamp(0.0, 1.0);
            }
            ssim(&a, &b).unwrap()
        };
        let (little, more, much) = (noisy(0.05), noisy(0.2), noisy(0.8));
        assert!(
            1.0 > little && little > more && more > much,
            "{little} {more} {much}"
        );
        assert!(little > 0.9 && much < 0.6, "{little} {much}");
        // A brightness shift lowers only the luminance term.
        let shifted = image(40, 32, |x, y| pattern(x, y).map(|v| v + 0.1));
        let s = ssim(&a, &shifted).unwrap();
        assert!(s > 0.9 && s < 1.0, "{s}");
        // Symmetric.
        assert_eq!(ssim(&a, &shifted).unwrap(), ssim(&shifted, &a).unwrap());
    }

    #[test]
    fn ssim_of_a_constant_pair_is_the_luminance_term() {
        // Constant images: SSIM = (2μxμy + C1)/(μx² + μy² + C1).
        let (a, b) = (image(12, 11, |_, _| [0.2; 3]), image(12, 11, |_, _| [0.6; 3]));
        let expected = (2.0 * 0.2 * 0.6 + C1) / (0.04 + 0.36 + C1);
        assert!((ssim(&a, &b).unwrap() as f64 - expected).abs() < 1e-5);
        let e = ssim(&image(10, 20, pattern), &image(10, 20, pattern))
            .unwrap_err()
            .to_string();
        assert!(e.contains("at least 11×11"), "{e}");
        let mut broken = image(12, 12, pattern);
        broken.pixels.pop();
        assert!(ssim(&broken, &image(12, 12, pattern)).is_err());
    }
}
