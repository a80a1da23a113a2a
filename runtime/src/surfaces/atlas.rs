//! Texture atlases of meshes: each triangle, or pair of neighbouring triangles, gets a square patch of its
//! own, whose texels hold a color function sampled on the triangles ([`bake_atlas`]); the textured glTF
//! files of `nerfjit mesh` carry them.
//!
//! A patch of n × n texels holds a triangle as a right isosceles triangle whose corners are the centres of
//! the patch's texels (0, 0), (n − 1, 0) and (0, n − 1) (column, row; rows run down the image as glTF's v
//! does), so each corner's UV is a texel centre, and its neighbour, if [`pair_triangles`] found one, across
//! the diagonal, the fourth corner at (n − 1, n − 1). A texel centre on a triangle holds the color at its
//! point of the triangle (the barycentric combination of the corners). Bilinear filtering at a point of a
//! triangle reads the four texels around it, all within the patch: of a pair, on its two triangles, which
//! meet along the diagonal as they do on the surface. A triangle alone reads the texels with i + j ≤ n;
//! those with i + j = n, just past its long side, hold the color at the nearest point of that side, so that
//! filtering along it blends nothing from elsewhere, and the texels further out, which filtering never
//! reads, mirror the triangle's across the long side (where a viewer builds mipmaps all the same, they
//! blend colors of the same triangle). So patches need no gutter between them.

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
    /// The layout of `patches` patches of `patch`² texels in a near-square image, checked against
    /// [`PATCHES`] and [`MAX_SIDE`].
    pub fn new(patches: usize, patch: usize) -> Result<AtlasLayout> {
        if !PATCHES.contains(&patch) {
            return Err(Error::Invalid(format!(
                "a texture patch of {patch} texels a side: use {} to {}",
                PATCHES.start(),
                PATCHES.end()
            )));
        }
        if patches == 0 {
            return Err(Error::Invalid(
                "a texture atlas of a mesh without triangles".into(),
            ));
        }
        let columns = (patches as f64).sqrt().ceil() as usize;
        let layout = AtlasLayout {
            patch,
            columns,
            rows: patches.div_ceil(columns),
        };
        if layout.width().max(layout.height()) as usize > MAX_SIDE {
            return Err(Error::Invalid(format!(
                "a texture atlas of {patches} patches of {patch}² texels would be {}×{} texels, more \
                 than {MAX_SIDE} a side: use smaller patches or a coarser mesh",
                layout.width(),
                layout.height()
            )));
        }
        Ok(layout)
    }

    /// The layout with the largest patches (of at most [`DEFAULT_MAX_PATCH`] texels a side) whose image is
    /// at most `side` texels a side, or `None` if even the smallest patches do not fit.
    pub fn fitting(patches: usize, side: usize) -> Option<AtlasLayout> {
        (*PATCHES.start()..=DEFAULT_MAX_PATCH)
            .rev()
            .filter_map(|patch| AtlasLayout::new(patches, patch).ok())
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

    /// The UVs of patch `p`'s corners (u to the right, v down the image, as glTF has them): the texel
    /// centres (0, 0), (n − 1, 0), (0, n − 1) and (n − 1, n − 1) of the patch (see [`Patch`]).
    pub fn uvs(&self, p: usize) -> [[f32; 2]; 4] {
        let (x, y) = ((p % self.columns) * self.patch, (p / self.columns) * self.patch);
        let last = self.patch - 1;
        let (width, height) = (self.width() as f32, self.height() as f32);
        let uv = |i: usize, j: usize| [((x + i) as f32 + 0.5) / width, ((y + j) as f32 + 0.5) / height];
        [uv(0, 0), uv(last, 0), uv(0, last), uv(last, last)]
    }
}

/// One patch's triangles, each as three vertices of the mesh, in the order both of its corners
/// (counter-clockwise seen from outside, as the mesh has them) and of its texture coordinates: the first at
/// the patch's texel centres (0, 0), (n − 1, 0), (0, n − 1); the second, if any, sharing the first's last two
/// vertices in reverse (their common side), at (n − 1, n − 1), (0, n − 1), (n − 1, 0).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Patch {
    /// The first triangle.
    pub first: [u32; 3],
    /// The second triangle: `[w, first[2], first[1]]` for its own vertex `w`.
    pub second: Option<[u32; 3]>,
}

/// The mesh's triangles in patches: neighbours (triangles that share a side, traversed in opposite
/// directions) paired greedily in the order of the triangles, and the rest alone. A pair's texels all lie on
/// its two triangles, and filtering across their common side blends colors of the surface on both sides of
/// it, as a texture without seams does; a pair also shares two of its four vertices.
pub fn pair_triangles(mesh: &Mesh) -> Vec<Patch> {
    let triangles = &mesh.triangles;
    // Each directed side (a, b) with its triangle and the corner it starts at, sorted to find the reverse.
    let mut sides: Vec<(u32, u32, usize, usize)> = triangles
        .iter()
        .enumerate()
        .flat_map(|(t, c)| (0..3).map(move |k| (c[k], c[(k + 1) % 3], t, k)))
        .collect();
    sides.sort_unstable();
    // The triangles of directed side (a, b), and the corners it starts at.
    let run = |a: u32, b: u32| {
        let at = sides.partition_point(|s| (s.0, s.1) < (a, b));
        let count = sides[at..].iter().take_while(|s| (s.0, s.1) == (a, b)).count();
        &sides[at..at + count]
    };
    // The triangle across side (a, b) and the corner where it starts (b, a): where the side is shared by
    // exactly two triangles, one each way.
    let across = |a: u32, b: u32| match (run(b, a), run(a, b).len()) {
        ([other], 1) => Some((other.2, other.3)),
        _ => None,
    };
    let degenerate = |c: &[u32; 3]| c[0] == c[1] || c[1] == c[2] || c[2] == c[0];
    let mut paired = vec![false; triangles.len()];
    let mut patches = Vec::with_capacity(triangles.len() / 2 + 1);
    for (t, c) in triangles.iter().enumerate() {
        if paired[t] {
            continue;
        }
        paired[t] = true;
        let neighbour = (0..3).filter(|_| !degenerate(c)).find_map(|k| {
            let (u, v) = (c[(k + 1) % 3], c[(k + 2) % 3]);
            across(u, v)
                .filter(|&(other, _)| !paired[other] && !degenerate(&triangles[other]))
                .map(|(other, corner)| (k, other, corner))
        });
        patches.push(match neighbour {
            None => Patch {
                first: *c,
                second: None,
            },
            // The first turned so that its common side runs from corner 1 to 2, the second to start at its
            // own vertex: the corner after the end of its side (v, u).
            Some((k, other, corner)) => {
                paired[other] = true;
                let o = &triangles[other];
                Patch {
                    first: [c[k], c[(k + 1) % 3], c[(k + 2) % 3]],
                    second: Some([o[(corner + 2) % 3], o[corner], o[(corner + 1) % 3]]),
                }
            }
        });
    }
    patches
}

/// A mesh's texture: its patches, where they lie, and the image.
pub struct Atlas {
    /// Where each patch lies.
    pub layout: AtlasLayout,
    /// The triangles of each patch.
    pub patches: Vec<Patch>,
    /// The texels, RGB with 8 bits a channel.
    pub image: RgbImage,
}

/// A texel sampled on a patch's triangle: its column and row in the patch, the triangle (0 or 1) and the
/// barycentric weights of the triangle's second and third corners at its point.
type Sample = (usize, usize, usize, f32, f32);

/// What the texels of a patch hold: those sampled on its triangles, and those copied from others.
struct PatchSamples {
    sampled: Vec<Sample>,
    /// Texel (column, row) and the sampled texel whose color it takes.
    mirrored: Vec<((usize, usize), (usize, usize))>,
}

impl PatchSamples {
    /// The texels of a patch of `patch`² texels with one triangle (`pair` false) or two.
    fn new(patch: usize, pair: bool) -> PatchSamples {
        let last = patch - 1;
        let side = last as f32;
        let mut samples = PatchSamples {
            sampled: Vec::new(),
            mirrored: Vec::new(),
        };
        for j in 0..patch {
            for i in 0..patch {
                let (x, y) = (i as f32, j as f32);
                if i + j <= last {
                    samples.sampled.push((i, j, 0, x / side, y / side));
                } else if pair {
                    // The second triangle: corner 1 at (0, n − 1), corner 2 at (n − 1, 0).
                    samples
                        .sampled
                        .push((i, j, 1, (side - x) / side, (side - y) / side));
                } else if i + j == patch {
                    // The nearest point of the long side: half a texel back along the diagonal.
                    samples
                        .sampled
                        .push((i, j, 0, (x - 0.5) / side, (y - 0.5) / side));
                } else {
                    samples.mirrored.push(((i, j), (last - j, last - i)));
                }
            }
        }
        samples
    }
}

/// Bakes `color` into a texture of `mesh` with its triangles in `patches` (see [`pair_triangles`]) laid out
/// as `layout`: each texel the color at its point of its triangle, clamped to [0, 1] (NaN as 0). `color` is
/// `fn(p: vec3) -> vec3` or a radiance field's `fn(p: vec3, d: vec3) -> vec3`, then seen along the inward
/// normal (the normal interpolated across the triangle, negated): the mesh's normals must face outwards.
/// The rows of patches are evaluated in parallel, each in one call of `color`.
pub fn bake_atlas(
    mesh: &Mesh,
    patches: Vec<Patch>,
    color: &dyn BatchFn,
    layout: AtlasLayout,
) -> Result<Atlas> {
    mesh.check()?;
    if color.n_outputs() != 3 || !matches!(color.n_inputs(), 3 | 6) {
        return Err(Error::Invalid(format!(
            "a texture's color function must map a position (3 inputs) or a position and a direction (6) \
             to a color (3 outputs), but it maps {} inputs to {}",
            color.n_inputs(),
            color.n_outputs()
        )));
    }
    if layout.columns * layout.rows < patches.len() {
        return Err(Error::Invalid(format!(
            "an atlas of {} patches for {} patches of triangles",
            layout.columns * layout.rows,
            patches.len()
        )));
    }
    let n = mesh.vertices.len();
    let in_range = |c: &[u32; 3]| c.iter().all(|&v| (v as usize) < n);
    let shares = |p: &Patch| {
        p.second
            .is_none_or(|s| in_range(&s) && s[1..] == [p.first[2], p.first[1]])
    };
    if let Some(k) = patches.iter().position(|p| !in_range(&p.first) || !shares(p)) {
        return Err(Error::Invalid(format!(
            "patch {k} {:?} does not fit the mesh",
            patches[k]
        )));
    }
    let samples = [false, true].map(|pair| PatchSamples::new(layout.patch, pair));
    let width = layout.width() as usize;
    let mut texels = vec![0u8; width * layout.height() as usize * 3];
    texels
        .par_chunks_mut(width * layout.patch * 3)
        .zip(patches.par_chunks(layout.columns))
        .for_each(|(band, row)| bake_row(mesh, color, &samples, layout, row, band));
    let image =
        RgbImage::from_raw(layout.width(), layout.height(), texels).expect("the texels fill the image");
    Ok(Atlas {
        layout,
        patches,
        image,
    })
}

/// Fills `band`, the image rows of one row of patches, with the colors of the triangles of `row`.
fn bake_row(
    mesh: &Mesh,
    color: &dyn BatchFn,
    samples: &[PatchSamples; 2],
    layout: AtlasLayout,
    row: &[Patch],
    band: &mut [u8],
) {
    let of = |patch: &Patch| &samples[usize::from(patch.second.is_some())];
    let count = row.iter().map(|p| of(p).sampled.len()).sum();
    let mut columns = vec![Vec::with_capacity(count); color.n_inputs()];
    let vertex = |v: u32| {
        (
            Vec3::from(mesh.vertices[v as usize]),
            Vec3::from(mesh.normals[v as usize]),
        )
    };
    for patch in row {
        let corners = [Some(patch.first), patch.second].map(|t| t.map(|c| c.map(vertex)));
        for &(_, _, triangle, u, v) in &of(patch).sampled {
            let [(a, na), (b, nb), (c, nc)] = corners[triangle].expect("a sample of the patch's triangle");
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
    let mut point = 0;
    for (column, patch) in row.iter().enumerate() {
        for &(i, j, ..) in &of(patch).sampled {
            let texel = at(column, (i, j));
            for channel in 0..3 {
                band[texel + channel] = Quantize::Round.byte(rgb[channel][point]);
            }
            point += 1;
        }
        for &(to, from) in &of(patch).mirrored {
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
    fn layouts_fit_their_patches_in_near_square_images() {
        let layout = AtlasLayout::new(10, 4).unwrap();
        assert_eq!((layout.columns, layout.rows), (4, 3));
        assert_eq!((layout.width(), layout.height()), (16, 12));
        // Patch 5: column 1, row 1; its corners at texel centres (4, 4), (7, 4), (4, 7), (7, 7).
        let [a, b, c, d] = layout.uvs(5);
        assert_eq!(a, [4.5 / 16.0, 4.5 / 12.0]);
        assert_eq!(b, [7.5 / 16.0, 4.5 / 12.0]);
        assert_eq!(c, [4.5 / 16.0, 7.5 / 12.0]);
        assert_eq!(d, [7.5 / 16.0, 7.5 / 12.0]);
        // A million patches fit 4096² at 4 texels a side, not at 5.
        let fitted = AtlasLayout::fitting(1_000_000, DEFAULT_SIDE).unwrap();
        assert_eq!(fitted.patch, 4);
        assert_eq!(
            AtlasLayout::fitting(100, DEFAULT_SIDE).unwrap().patch,
            DEFAULT_MAX_PATCH
        );
        assert!(AtlasLayout::fitting(5_000_000, DEFAULT_SIDE).is_none());
        for (patches, patch, message) in [
            (10, 1, "use 2 to 64"),
            (0, 4, "without triangles"),
            (10_000_000, 8, "more than 16384 a side"),
        ] {
            let e = AtlasLayout::new(patches, patch).unwrap_err().to_string();
            assert!(e.contains(message), "{e}");
        }
    }

    /// Each patch's texels cover what bilinear filtering reads on its triangles: a pair's every texel is
    /// sampled on one of them; a lone triangle's every texel with i + j ≤ n, the rest mirroring sampled ones.
    #[test]
    fn patches_sample_every_texel_filtering_reads_on_their_triangles() {
        for patch in [2, 3, 4, 8] {
            let pair = PatchSamples::new(patch, true);
            assert!(pair.mirrored.is_empty() && pair.sampled.len() == patch * patch);
            let single = PatchSamples::new(patch, false);
            assert_eq!(single.sampled.len() + single.mirrored.len(), patch * patch);
            for (samples, pair) in [(&pair, true), (&single, false)] {
                for &(i, j, triangle, u, v) in &samples.sampled {
                    assert!(u >= 0.0 && v >= 0.0 && u + v <= 1.0 + 1e-6, "{i} {j}: {u} {v}");
                    assert_eq!(triangle, usize::from(pair && i + j >= patch));
                }
            }
            let sampled = |t: (usize, usize)| single.sampled.iter().any(|s| (s.0, s.1) == t);
            assert!(single.sampled.iter().all(|s| s.0 + s.1 <= patch));
            for &(to, from) in &single.mirrored {
                assert!(to.0 + to.1 > patch && sampled(from), "{to:?} from {from:?}");
            }
        }
    }

    /// A 4 × 4 grid of squares, each split along a diagonal.
    fn grid() -> Mesh {
        let vertices = (0..25).map(|k| [(k % 5) as f32, (k / 5) as f32, 0.0]).collect();
        let triangles = (0..16)
            .flat_map(|k| {
                let a = (k % 4 + 5 * (k / 4)) as u32;
                [[a, a + 1, a + 6], [a, a + 6, a + 5]]
            })
            .collect();
        Mesh::from_triangles(vertices, triangles)
    }

    /// Pairs share a side, traversed each way; every triangle is in one patch, its corners turned but in
    /// their order; and most triangles of a mesh are paired.
    #[test]
    fn neighbours_pair_across_a_common_side() {
        let mesh = grid();
        let patches = pair_triangles(&mesh);
        let mut seen: Vec<[u32; 3]> = Vec::new();
        let turned = |t: [u32; 3]| {
            (0..3)
                .map(|k| [t[k], t[(k + 1) % 3], t[(k + 2) % 3]])
                .min()
                .unwrap()
        };
        for p in &patches {
            seen.push(turned(p.first));
            if let Some(second) = p.second {
                assert_eq!(second[1..], [p.first[2], p.first[1]], "{p:?}");
                seen.push(turned(second));
            }
        }
        let mut want: Vec<[u32; 3]> = mesh.triangles.iter().map(|&t| turned(t)).collect();
        seen.sort_unstable();
        want.sort_unstable();
        assert_eq!(seen, want);
        assert!(patches.len() <= 20, "{} patches of 32 triangles", patches.len());
        // Triangles that repeat a vertex stay alone.
        let flat = Mesh::from_triangles(mesh.vertices.clone(), vec![[0, 1, 1], [1, 0, 6]]);
        assert!(pair_triangles(&flat).iter().all(|p| p.second.is_none()));
    }

    /// Colored by position, and by direction: each texel holds the color at its point, the corners those of
    /// the vertices, in the patch of its own triangles.
    #[test]
    fn texels_hold_the_color_at_their_points() {
        let mesh = Mesh::from_triangles(
            vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [1.0, 1.0, 0.0],
                [3.0, 0.0, 0.0],
            ],
            vec![[0, 1, 2], [1, 3, 2], [1, 4, 3]],
        );
        let patches = pair_triangles(&mesh);
        assert_eq!(
            patches,
            [
                Patch {
                    first: [0, 1, 2],
                    second: Some([3, 2, 1])
                },
                Patch {
                    first: [1, 4, 3],
                    second: None
                }
            ]
        );
        let layout = AtlasLayout::new(2, 5).unwrap();
        let by_position = ClosureFn::new(3, 3, |x, y| y.copy_from_slice(&[x[0] / 3.0, x[1], 0.25]));
        let atlas = bake_atlas(&mesh, patches.clone(), &by_position, layout).unwrap();
        assert_eq!(atlas.image.dimensions(), (10, 5));
        let byte = |x: f32| (x * 255.0).round() as u8;
        let color = |p: Vec3| [byte(p.x / 3.0), byte(p.y), byte(0.25)];
        let texel = |uv: [f32; 2]| {
            atlas
                .image
                .get_pixel((uv[0] * 10.0) as u32, (uv[1] * 5.0) as u32)
                .0
        };
        for (k, p) in patches.iter().enumerate() {
            let corners = [
                p.first[0],
                p.first[1],
                p.first[2],
                p.second.map_or(p.first[0], |s| s[0]),
            ];
            for (corner, uv) in layout
                .uvs(k)
                .into_iter()
                .enumerate()
                .take(3 + usize::from(p.second.is_some()))
            {
                let vertex = Vec3::from(mesh.vertices[corners[corner] as usize]);
                assert_eq!(texel(uv), color(vertex), "patch {k} corner {corner}");
            }
        }
        // Texel (3, 2) of the pair: on the second triangle, (3, 2, 1) from (4, 4) at the texel centres
        // (4, 4), (0, 4), (4, 0): a quarter of the way to the second corner, half of the way to the third.
        let [a, b, c] = [3, 2, 1].map(|v| Vec3::from(mesh.vertices[v]));
        assert_eq!(
            atlas.image.get_pixel(3, 2).0,
            color(a + 0.25 * (b - a) + 0.5 * (c - a))
        );
        // Texel (1, 2) of the lone triangle's patch (5 texels to the right): a quarter of the way from (1,
        // 0, 0) to (3, 0, 0), half of the way to (1, 1, 0).
        let p = Vec3::new(1.0, 0.0, 0.0) + 0.25 * Vec3::new(2.0, 0.0, 0.0) + 0.5 * Vec3::new(0.0, 1.0, 0.0);
        assert_eq!(atlas.image.get_pixel(6, 2).0, color(p));
        // A radiance field sees the flat mesh from above: along −z, its normals' negation.
        let by_direction = ClosureFn::new(6, 3, |x, y| y.copy_from_slice(&[-x[5], f32::NAN, 2.0]));
        let atlas = bake_atlas(&mesh, patches.clone(), &by_direction, layout).unwrap();
        assert!(atlas.image.pixels().all(|p| p.0 == [255, 0, 255]));
        let scalar = ClosureFn::new(3, 1, |_, y| y[0] = 0.0);
        let e = bake_atlas(&mesh, patches, &scalar, layout)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("maps 3 inputs to 1"), "{e}");
        let stray = vec![Patch {
            first: [0, 1, 2],
            second: Some([4, 1, 2]),
        }];
        let e = bake_atlas(&mesh, stray, &by_position, layout)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("does not fit the mesh"), "{e}");
    }
}
