//! Texture atlases of meshes: each triangle gets a square patch of its own, whose texels hold a color
//! function sampled on the triangle ([`bake_atlas`]); the textured glTF files of `nerfjit mesh` carry them.
//!
//! A patch of n × n texels holds its triangle as a right isosceles triangle whose corners are the centres of
//! the patch's texels (0, 0), (n − 1, 0) and (0, n − 1) (column, row; rows run down the image as glTF's v
//! does), so each corner's UV is a texel centre. A texel centre on or inside the triangle holds the color at
//! its point of the triangle (the barycentric combination of the corners). Bilinear filtering at a point
//! inside the triangle reads the four texels around it: those with i + j ≤ n, all within the patch. The
//! texels with i + j = n, just past the long side, hold the color at the nearest point of that side, so
//! filtering along it blends nothing from elsewhere, and patches need no gutter between them. The texels
//! further out, which filtering never reads, mirror the triangle's across the long side (where a viewer
//! builds mipmaps all the same, they blend colors of the same triangle).

use glam::Vec3;
use image::RgbImage;
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::field::BatchFn;
use crate::output::image_out::Quantize;
use crate::surfaces::mesh::Mesh;

/// The largest side of an atlas, in texels (the largest texture GPUs commonly take).
pub const MAX_SIDE: usize = 16384;

/// The side [`AtlasLayout::fitting`] keeps an atlas within unless asked otherwise.
pub const DEFAULT_SIDE: usize = 4096;

/// The largest patch [`AtlasLayout::fitting`] picks, in texels a side (its triangle's sides 7 texels long).
pub const DEFAULT_MAX_PATCH: usize = 8;

/// The patches' sizes [`AtlasLayout::new`] takes, in texels a side.
pub const PATCHES: std::ops::RangeInclusive<usize> = 2..=64;

/// Where each triangle's patch lies: patches of `patch`² texels in rows of `columns`, triangle t at column
/// t mod `columns` of row t / `columns`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AtlasLayout {
    /// Texels along a side of a patch.
    pub patch: usize,
    /// Patches along a row of the image.
    pub columns: usize,
    /// Rows of patches.
    pub rows: usize,
}

impl AtlasLayout {
    /// The layout of `triangles` patches of `patch`² texels in a near-square image, checked against
    /// [`PATCHES`] and [`MAX_SIDE`].
    pub fn new(triangles: usize, patch: usize) -> Result<AtlasLayout> {
        if !PATCHES.contains(&patch) {
            return Err(Error::Invalid(format!(
                "a texture patch of {patch} texels a side: use {} to {}",
                PATCHES.start(),
                PATCHES.end()
            )));
        }
        if triangles == 0 {
            return Err(Error::Invalid(
                "a texture atlas of a mesh without triangles".into(),
            ));
        }
        let columns = (triangles as f64).sqrt().ceil() as usize;
        let layout = AtlasLayout {
            patch,
            columns,
            rows: triangles.div_ceil(columns),
        };
        if layout.width().max(layout.height()) as usize > MAX_SIDE {
            return Err(Error::Invalid(format!(
                "a texture atlas of {triangles} triangles at {patch}² texels each would be {}×{} texels, more \
                 than {MAX_SIDE} a side: use smaller patches or a coarser mesh",
                layout.width(),
                layout.height()
            )));
        }
        Ok(layout)
    }

    /// The layout with the largest patches (of at most [`DEFAULT_MAX_PATCH`] texels a side) whose image is
    /// at most `side` texels a side, or `None` if even the smallest patches do not fit.
    pub fn fitting(triangles: usize, side: usize) -> Option<AtlasLayout> {
        (*PATCHES.start()..=DEFAULT_MAX_PATCH)
            .rev()
            .filter_map(|patch| AtlasLayout::new(triangles, patch).ok())
            .find(|l| l.width().max(l.height()) as usize <= side)
    }

    /// The image's width in texels.
    pub fn width(&self) -> u32 {
        (self.columns * self.patch) as u32
    }

    /// The image's height in texels.
    pub fn height(&self) -> u32 {
        (self.rows * self.patch) as u32
    }

    /// The UVs of triangle `t`'s three corners (u to the right, v down the image, as glTF has them).
    pub fn uvs(&self, t: usize) -> [[f32; 2]; 3] {
        let (x, y) = ((t % self.columns) * self.patch, (t / self.columns) * self.patch);
        let last = self.patch - 1;
        let uv = |i: usize, j: usize| [(x + i) as f32 + 0.5, (y + j) as f32 + 0.5];
        [uv(0, 0), uv(last, 0), uv(0, last)].map(|[u, v]| [u / self.width() as f32, v / self.height() as f32])
    }
}

/// A mesh's texture: its layout and the image.
pub struct Atlas {
    /// Where each triangle's patch lies.
    pub layout: AtlasLayout,
    /// The texels, RGB with 8 bits a channel.
    pub image: RgbImage,
}

/// What one patch's texels hold: the texels sampled on the triangle, and those copied from others.
struct PatchSamples {
    /// Texel (column, row) in the patch and the barycentric weights of the triangle's second and third
    /// corners at its point.
    sampled: Vec<(usize, usize, f32, f32)>,
    /// Texel (column, row) and the sampled texel whose color it takes.
    mirrored: Vec<((usize, usize), (usize, usize))>,
}

impl PatchSamples {
    fn new(patch: usize) -> PatchSamples {
        let last = patch - 1;
        let side = last as f32;
        let mut samples = PatchSamples {
            sampled: Vec::new(),
            mirrored: Vec::new(),
        };
        for j in 0..patch {
            for i in 0..patch {
                if i + j <= last {
                    samples.sampled.push((i, j, i as f32 / side, j as f32 / side));
                } else if i + j == patch {
                    // The nearest point of the long side: half a texel back along the diagonal.
                    let (u, v) = (i as f32 - 0.5, j as f32 - 0.5);
                    samples.sampled.push((i, j, u / side, v / side));
                } else {
                    samples.mirrored.push(((i, j), (last - j, last - i)));
                }
            }
        }
        samples
    }
}

/// Bakes `color` into a texture of `mesh` laid out as `layout`: each texel the color at its point of its
/// triangle, clamped to [0, 1] (NaN as 0). `color` is `fn(p: vec3) -> vec3` or a radiance field's
/// `fn(p: vec3, d: vec3) -> vec3`, then seen along the inward normal (the normal interpolated across the
/// triangle, negated): the mesh's normals must face outwards. The rows of patches are evaluated in
/// parallel, each in one call of `color`.
pub fn bake_atlas(mesh: &Mesh, color: &dyn BatchFn, layout: AtlasLayout) -> Result<Atlas> {
    mesh.check()?;
    if color.n_outputs() != 3 || !matches!(color.n_inputs(), 3 | 6) {
        return Err(Error::Invalid(format!(
            "a texture's color function must map a position (3 inputs) or a position and a direction (6) \
             to a color (3 outputs), but it maps {} inputs to {}",
            color.n_inputs(),
            color.n_outputs()
        )));
    }
    if layout.columns * layout.rows < mesh.triangles.len() {
        return Err(Error::Invalid(format!(
            "an atlas of {} patches for {} triangles",
            layout.columns * layout.rows,
            mesh.triangles.len()
        )));
    }
    let samples = PatchSamples::new(layout.patch);
    let width = layout.width() as usize;
    let mut texels = vec![0u8; width * layout.height() as usize * 3];
    let band = width * layout.patch * 3;
    texels.par_chunks_mut(band).enumerate().for_each(|(row, band)| {
        let first = row * layout.columns;
        let last = (first + layout.columns).min(mesh.triangles.len());
        if first < last {
            bake_row(mesh, color, &samples, layout, first..last, band);
        }
    });
    let image =
        RgbImage::from_raw(layout.width(), layout.height(), texels).expect("the texels fill the image");
    Ok(Atlas { layout, image })
}

/// Fills `band`, the image rows of one row of patches, with the colors of `triangles`.
fn bake_row(
    mesh: &Mesh,
    color: &dyn BatchFn,
    samples: &PatchSamples,
    layout: AtlasLayout,
    triangles: std::ops::Range<usize>,
    band: &mut [u8],
) {
    let count = triangles.len() * samples.sampled.len();
    let mut columns = vec![Vec::with_capacity(count); color.n_inputs()];
    for t in triangles.clone() {
        let corner = |k: usize| mesh.triangles[t][k] as usize;
        let [a, b, c] = [0, 1, 2].map(|k| Vec3::from(mesh.vertices[corner(k)]));
        let [na, nb, nc] = [0, 1, 2].map(|k| Vec3::from(mesh.normals[corner(k)]));
        for &(_, _, u, v) in &samples.sampled {
            let p = a + u * (b - a) + v * (c - a);
            let d = -((1.0 - u - v) * na + u * nb + v * nc).normalize_or_zero();
            for (axis, x) in p.to_array().into_iter().chain(d.to_array()).enumerate() {
                if let Some(column) = columns.get_mut(axis) {
                    column.push(x);
                }
            }
        }
    }
    let inputs: Vec<&[f32]> = columns.iter().map(Vec::as_slice).collect();
    let rgb = color.eval_columns(&inputs);
    let width = layout.width() as usize;
    let at = |column: usize, (i, j): (usize, usize)| 3 * (j * width + column * layout.patch + i);
    for (k, t) in triangles.enumerate() {
        let column = t % layout.columns;
        for (s, &(i, j, _, _)) in samples.sampled.iter().enumerate() {
            let point = k * samples.sampled.len() + s;
            let texel = at(column, (i, j));
            for channel in 0..3 {
                band[texel + channel] = Quantize::Round.byte(rgb[channel][point]);
            }
        }
        for &(to, from) in &samples.mirrored {
            let (to, from) = (at(column, to), at(column, from));
            band.copy_within(from..from + 3, to);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::ClosureFn;

    #[test]
    fn layouts_fit_their_triangles_in_near_square_images() {
        let layout = AtlasLayout::new(10, 4).unwrap();
        assert_eq!((layout.columns, layout.rows), (4, 3));
        assert_eq!((layout.width(), layout.height()), (16, 12));
        // Triangle 5: column 1, row 1; its corners at texel centres (4, 4), (7, 4), (4, 7).
        let [a, b, c] = layout.uvs(5);
        assert_eq!(a, [4.5 / 16.0, 4.5 / 12.0]);
        assert_eq!(b, [7.5 / 16.0, 4.5 / 12.0]);
        assert_eq!(c, [4.5 / 16.0, 7.5 / 12.0]);
        // A million triangles fit 4096² at 4 texels a side, not at 5.
        let fitted = AtlasLayout::fitting(1_000_000, DEFAULT_SIDE).unwrap();
        assert_eq!(fitted.patch, 4);
        assert_eq!(
            AtlasLayout::fitting(100, DEFAULT_SIDE).unwrap().patch,
            DEFAULT_MAX_PATCH
        );
        assert!(AtlasLayout::fitting(5_000_000, DEFAULT_SIDE).is_none());
        for (triangles, patch, message) in [
            (10, 1, "use 2 to 64"),
            (0, 4, "without triangles"),
            (10_000_000, 8, "more than 16384 a side"),
        ] {
            let e = AtlasLayout::new(triangles, patch).unwrap_err().to_string();
            assert!(e.contains(message), "{e}");
        }
    }

    /// Each patch's texels cover what bilinear filtering reads inside its triangle: every texel with
    /// i + j ≤ n is sampled at a point of the triangle, and the rest mirror sampled ones.
    #[test]
    fn patches_sample_every_texel_filtering_reads_on_the_triangle() {
        for patch in [2, 3, 4, 8] {
            let samples = PatchSamples::new(patch);
            assert_eq!(samples.sampled.len() + samples.mirrored.len(), patch * patch);
            for &(i, j, u, v) in &samples.sampled {
                assert!(i + j <= patch);
                assert!(u >= 0.0 && v >= 0.0 && u + v <= 1.0 + 1e-6, "{i} {j}: {u} {v}");
            }
            let sampled = |t: (usize, usize)| samples.sampled.iter().any(|s| (s.0, s.1) == t);
            for &(to, from) in &samples.mirrored {
                assert!(to.0 + to.1 > patch && sampled(from), "{to:?} from {from:?}");
            }
        }
    }

    /// Two triangles, one colored by position and one by direction: each texel inside a triangle holds the
    /// color at its point, the corners those of the vertices, in the patch of its own triangle.
    #[test]
    fn texels_hold_the_color_at_their_points() {
        let mesh = Mesh::from_triangles(
            vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]],
            vec![[0, 1, 2], [1, 3, 2]],
        );
        let layout = AtlasLayout::new(2, 5).unwrap();
        let by_position = ClosureFn::new(3, 3, |x, y| {
            y[0] = x[0];
            y[1] = x[1];
            y[2] = 0.25;
        });
        let atlas = bake_atlas(&mesh, &by_position, layout).unwrap();
        assert_eq!(atlas.image.dimensions(), (10, 5));
        let texel = |uv: [f32; 2]| {
            let (x, y) = (uv[0] * 10.0, uv[1] * 5.0);
            atlas.image.get_pixel(x as u32, y as u32).0
        };
        let byte = |x: f32| (x * 255.0).round() as u8;
        for t in 0..2 {
            for (corner, uv) in layout.uvs(t).into_iter().enumerate() {
                let p = mesh.vertices[mesh.triangles[t][corner] as usize];
                assert_eq!(
                    texel(uv),
                    [byte(p[0]), byte(p[1]), byte(0.25)],
                    "triangle {t} corner {corner}"
                );
            }
        }
        // Texel (1, 2) of triangle 1's patch (5 texels to the right): a quarter of the way from its first
        // corner (1, 0) to its second, half of the way to its third.
        let p = Vec3::new(1.0, 0.0, 0.0) + 0.25 * Vec3::new(0.0, 1.0, 0.0) + 0.5 * Vec3::new(-1.0, 1.0, 0.0);
        assert_eq!(atlas.image.get_pixel(6, 2).0, [byte(p.x), byte(p.y), byte(0.25)]);
        // A radiance field sees the flat square from above: along −z, its normals' negation.
        let by_direction = ClosureFn::new(6, 3, |x, y| {
            y[0] = -x[5];
            y[1] = f32::NAN;
            y[2] = 2.0;
        });
        let atlas = bake_atlas(&mesh, &by_direction, layout).unwrap();
        assert!(atlas.image.pixels().all(|p| p.0 == [255, 0, 255]));
        let scalar = ClosureFn::new(3, 1, |_, y| y[0] = 0.0);
        let e = bake_atlas(&mesh, &scalar, layout).err().unwrap().to_string();
        assert!(e.contains("maps 3 inputs to 1"), "{e}");
    }
}
