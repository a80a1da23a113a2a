//! A small software rasterizer for previews of geometry through a [`Camera`]: z-buffered,
//! Lambert-shaded meshes and shaded point splats.
//!
//! The image is cut into bands of rows drawn in parallel, each with its own depth buffer.
//! Depth is the view-space z (distance along the camera's axis); pixel (i, j) is covered by
//! what covers its center (i + 0.5, j + 0.5).

use std::ops::Range;

use glam::{Vec2, Vec3};
use image::RgbImage;
use rayon::prelude::*;

use crate::cameras::camera::Camera;
use crate::error::{check_size, Error, Result};
use crate::output::image_out::{rgb_image, Quantize};
use crate::surfaces::mesh::Mesh;

/// Rows per band drawn as one parallel task.
const BAND: usize = 16;

/// Checks that a color is finite.
fn check_color(what: &str, color: [f32; 3]) -> Result<()> {
    if !Vec3::from(color).is_finite() {
        return Err(Error::Invalid(format!("{what} {color:?} must be finite")));
    }
    Ok(())
}

/// Draws the image band by band in parallel: `draw(rows, colors, depth)` fills the band of
/// `rows`, whose colors start as `background` and depths as infinity.
fn render_bands(
    width: u32,
    height: u32,
    background: [f32; 3],
    draw: impl Fn(Range<usize>, &mut [[f32; 3]], &mut [f32]) + Sync,
) -> Result<RgbImage> {
    let w = width as usize;
    let mut colors = vec![background; w * height as usize];
    colors
        .par_chunks_mut(BAND * w)
        .enumerate()
        .for_each(|(band, colors)| {
            let start = band * BAND;
            let mut depth = vec![f32::INFINITY; colors.len()];
            draw(start..start + colors.len() / w, colors, &mut depth);
        });
    rgb_image(width, height, &colors, Quantize::Round)
}

/// The pixel coordinates (x = column, y = row) and view depth of `p`, if it is in front of the
/// camera.
fn project(camera: &Camera, p: Vec3, width: u32, height: u32) -> Option<(Vec2, f32)> {
    let depth = camera.rotation().z_axis.dot(p - camera.position());
    let (row, col) = camera.project(p, width, height)?;
    Some((Vec2::new(col, row), depth))
}

/// The pixels whose centers lie in [lo, hi] along one image axis, clipped to `0..len`.
fn pixel_range(lo: f32, hi: f32, len: usize) -> Range<usize> {
    let first = (lo - 0.5).ceil().max(0.0);
    let end = ((hi - 0.5).floor() + 1.0).min(len as f32);
    if end > first {
        first as usize..end as usize
    } else {
        0..0
    }
}

/// The pixels along one image axis a splat at `center` covers: those whose centers lie within
/// `radius`, and the one containing `center`; clipped to `0..len`.
fn splat_range(center: f32, radius: f32, len: usize) -> Range<usize> {
    let disc = pixel_range(center - radius, center + radius, len);
    let own = center.floor();
    if !(own >= 0.0 && own < len as f32) {
        return disc;
    }
    let own = own as usize;
    if disc.is_empty() {
        own..own + 1
    } else {
        disc.start.min(own)..disc.end.max(own + 1)
    }
}

/// Twice the signed area of the triangle (a, b, q), computed from the endpoints in a fixed
/// order so that two triangles sharing an edge get exactly opposite values and leave no
/// pixel between them uncovered.
fn edge(a: Vec2, b: Vec2, q: Vec2) -> f32 {
    let raw = |a: Vec2, b: Vec2| (b.x - a.x) * (q.y - a.y) - (b.y - a.y) * (q.x - a.x);
    if (a.x, a.y) <= (b.x, b.y) {
        raw(a, b)
    } else {
        -raw(b, a)
    }
}

/// A mesh triangle in the image.
struct ScreenTriangle {
    /// Pixel coordinates (column, row) of the corners.
    corners: [Vec2; 3],
    /// 1/depth of the corners.
    inv_depth: [f32; 3],
    /// World positions and normals of the corners.
    positions: [Vec3; 3],
    normals: [Vec3; 3],
    /// Twice the signed area in pixels.
    area: f32,
}

/// Renders `mesh` as seen by `camera` in a `width`×`height` image: z-buffered triangles with
/// perspective-correct interpolation of the vertex normals and per-pixel Lambert shading
/// `albedo · max(0, n·l)` for `light_dir` (towards the light, normalized here), where n faces
/// the camera (two-sided lighting). Uncovered pixels are `background`. Triangles with a
/// corner behind the camera are left out (a preview has no near-plane clipping).
pub fn render_mesh(
    camera: &Camera,
    width: u32,
    height: u32,
    mesh: &Mesh,
    light_dir: Vec3,
    albedo: [f32; 3],
    background: [f32; 3],
) -> Result<RgbImage> {
    check_size(width, height)?;
    mesh.check()?;
    check_color("albedo", albedo)?;
    check_color("background", background)?;
    let light = light_dir.normalize_or_zero();
    if !light.is_finite() || light == Vec3::ZERO {
        return Err(Error::Invalid(format!(
            "light direction {light_dir} must be finite and non-zero"
        )));
    }
    let projected: Vec<Option<(Vec2, f32)>> = mesh
        .vertices
        .par_iter()
        .map(|&v| project(camera, Vec3::from(v), width, height))
        .collect();
    let (w, h) = (width as f32, height as f32);
    let triangles: Vec<ScreenTriangle> = mesh
        .triangles
        .par_iter()
        .filter_map(|t| {
            let [a, b, c] = t.map(|i| projected[i as usize]);
            let (a, b, c) = (a?, b?, c?);
            let corners = [a.0, b.0, c.0];
            let area = edge(corners[0], corners[1], corners[2]);
            let lo = corners[0].min(corners[1]).min(corners[2]);
            let hi = corners[0].max(corners[1]).max(corners[2]);
            let visible = area != 0.0 && area.is_finite() && hi.x > 0.0 && hi.y > 0.0 && lo.x < w && lo.y < h;
            visible.then(|| ScreenTriangle {
                corners,
                inv_depth: [a.1, b.1, c.1].map(|d| 1.0 / d),
                positions: t.map(|i| Vec3::from(mesh.vertices[i as usize])),
                normals: t.map(|i| Vec3::from(mesh.normals[i as usize])),
                area,
            })
        })
        .collect();
    let eye = camera.position();
    let width = width as usize;
    render_bands(width as u32, height, background, |rows, colors, depth| {
        for t in &triangles {
            let [p0, p1, p2] = t.corners;
            let lo = p0.min(p1).min(p2);
            let hi = p0.max(p1).max(p2);
            let band_rows = pixel_range(lo.y, hi.y, rows.end);
            for i in band_rows.start.max(rows.start)..band_rows.end {
                for j in pixel_range(lo.x, hi.x, width) {
                    let q = Vec2::new(j as f32 + 0.5, i as f32 + 0.5);
                    let weights = [edge(p1, p2, q), edge(p2, p0, q), edge(p0, p1, q)].map(|e| e / t.area);
                    if weights.iter().any(|&l| l < 0.0) {
                        continue;
                    }
                    // Perspective-correct: interpolate attribute/depth and 1/depth linearly.
                    let w = [0, 1, 2].map(|k| weights[k] * t.inv_depth[k]);
                    let inv = w[0] + w[1] + w[2];
                    let z = 1.0 / inv;
                    let pixel = (i - rows.start) * width + j;
                    if z.is_nan() || z >= depth[pixel] {
                        continue;
                    }
                    depth[pixel] = z;
                    let position =
                        (w[0] * t.positions[0] + w[1] * t.positions[1] + w[2] * t.positions[2]) * z;
                    let mut n =
                        (w[0] * t.normals[0] + w[1] * t.normals[1] + w[2] * t.normals[2]).normalize_or_zero();
                    if n.dot(position - eye) > 0.0 {
                        n = -n;
                    }
                    let shade = n.dot(light).max(0.0);
                    colors[pixel] = albedo.map(|c| c * shade);
                }
            }
        }
    })
}

/// Renders `points` as seen by `camera` in a `width`×`height` image: z-buffered round splats
/// covering the pixels whose centers lie within `radius_px` of a point's projection (always at
/// least the pixel containing it), shaded like small spheres lit from the camera:
/// `color · (0.4 + 0.6·cos θ)` with cos θ = √(1 − (d/radius_px)²) at distance d from the
/// center. Uncovered pixels are `background`; points behind the camera are left out.
pub fn render_points(
    camera: &Camera,
    width: u32,
    height: u32,
    points: &[[f32; 3]],
    radius_px: f32,
    color: [f32; 3],
    background: [f32; 3],
) -> Result<RgbImage> {
    check_size(width, height)?;
    check_color("color", color)?;
    check_color("background", background)?;
    if !(radius_px.is_finite() && radius_px >= 0.0) {
        return Err(Error::Invalid(format!(
            "splat radius {radius_px} must be finite and >= 0 pixels"
        )));
    }
    let projected: Vec<(Vec2, f32)> = points
        .par_iter()
        .filter_map(|&p| project(camera, Vec3::from(p), width, height))
        .filter(|(c, _)| c.is_finite())
        .collect();
    let width = width as usize;
    let r2 = radius_px * radius_px;
    render_bands(width as u32, height, background, |rows, colors, depth| {
        for &(c, z) in &projected {
            let splat_rows = splat_range(c.y, radius_px, rows.end);
            for i in splat_rows.start.max(rows.start)..splat_rows.end {
                for j in splat_range(c.x, radius_px, width) {
                    let d2 = (Vec2::new(j as f32 + 0.5, i as f32 + 0.5) - c).length_squared();
                    let contains = i as f32 == c.y.floor() && j as f32 == c.x.floor();
                    if d2 > r2 && !contains {
                        continue;
                    }
                    let pixel = (i - rows.start) * width + j;
                    if z < depth[pixel] {
                        depth[pixel] = z;
                        let cos = if r2 > 0.0 {
                            (1.0 - d2 / r2).max(0.0).sqrt()
                        } else {
                            1.0
                        };
                        colors[pixel] = color.map(|k| k * (0.4 + 0.6 * cos));
                    }
                }
            }
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::ClosureFn;
    use crate::surfaces::marching::extract;

    fn camera() -> Camera {
        Camera::look_at(
            Vec3::new(0.3, 0.4, 3.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::splat(2.0),
            Vec2::ZERO,
        )
        .unwrap()
    }

    #[test]
    fn sphere_mesh_covers_the_projected_disc() {
        let r = 0.8;
        let sdf = ClosureFn::new(3, 1, move |p, out| {
            out[0] = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - r
        });
        let mesh = extract(&sdf, None, ([-1.0; 3], [1.0; 3]), 32, 0.0).unwrap();
        let cam = camera();
        let (w, h) = (64, 48);
        let light = cam.position().normalize();
        let img = render_mesh(&cam, w, h, &mesh, light, [1.0, 0.5, 0.25], [0.0, 0.0, 1.0]).unwrap();
        assert_eq!(img.dimensions(), (w, h));
        // The mesh lies between the spheres of radius r − 0.001 and r (see marching.rs): rays
        // passing the center farther than 0.005 from r are clearly in or out.
        let (mut inside, mut checked) = (0, 0);
        for i in 0..h {
            for j in 0..w {
                let (o, d) = cam.ray(i, j, w, h);
                let miss = (o - d * o.dot(d)).length();
                if (miss - r).abs() < 0.005 {
                    continue;
                }
                let covered = img.get_pixel(j, i).0[2] != 255;
                assert_eq!(covered, miss < r, "pixel ({i}, {j}) at {miss}");
                checked += 1;
                inside += usize::from(covered);
            }
        }
        assert!(
            checked > w as usize * h as usize * 9 / 10 && inside > 500,
            "{checked} {inside}"
        );
        // Facing the light, the sphere's front is lit fully: albedo.
        let (row, col) = cam.project(Vec3::ZERO, w, h).unwrap();
        let center = img.get_pixel(col as u32, row as u32).0;
        assert!(center[0] >= 250 && (126..=128).contains(&center[1]), "{center:?}");
    }

    #[test]
    fn nearer_triangles_hide_farther_ones_whatever_the_order() {
        // Seen from +z: a small triangle at z = 0.5 facing the camera, a large one at z = 0
        // whose normal is tilted 60° away from the light.
        let tilted = [3f32.sqrt() / 2.0, 0.0, 0.5];
        let mesh = Mesh {
            vertices: vec![
                [-1.0, -1.0, 0.0],
                [1.0, -1.0, 0.0],
                [0.0, 1.0, 0.0],
                [-0.2, -0.2, 0.5],
                [0.2, -0.2, 0.5],
                [0.0, 0.2, 0.5],
            ],
            normals: vec![
                tilted,
                tilted,
                tilted,
                [0.0, 0.0, 1.0],
                [0.0, 0.0, 1.0],
                [0.0, 0.0, 1.0],
            ],
            triangles: vec![[3, 4, 5], [0, 1, 2]],
            colors: Vec::new(),
        };
        let cam = Camera::look_at(
            Vec3::new(0.0, 0.0, 3.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::ONE,
            Vec2::ZERO,
        )
        .unwrap();
        for order in [[0, 1], [1, 0]] {
            let mut m = mesh.clone();
            m.triangles = order.map(|k| mesh.triangles[k]).to_vec();
            let img = render_mesh(&cam, 32, 32, &m, Vec3::Z, [1.0; 3], [0.0; 3]).unwrap();
            assert_eq!(img.get_pixel(16, 16).0, [255; 3], "{order:?}");
            assert_eq!(img.get_pixel(16, 20).0, [128; 3], "{order:?}");
            assert_eq!(img.get_pixel(2, 2).0, [0; 3], "{order:?}");
        }
    }

    #[test]
    fn point_splats_cover_their_discs_nearest_first() {
        let cam = Camera::look_at(
            Vec3::new(0.0, 0.0, 3.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::ONE,
            Vec2::ZERO,
        )
        .unwrap();
        let (w, h) = (40, 30);
        let near = Vec3::new(0.0, 0.0, 1.0);
        let far = Vec3::new(1.2, 0.0, -1.0);
        for points in [[near, far], [far, near]] {
            let points = points.map(|p| p.to_array());
            let img = render_points(&cam, w, h, &points, 4.0, [1.0, 1.0, 0.0], [0.0; 3]).unwrap();
            let (c, _) = project(&cam, near, w, h).unwrap();
            for i in 0..h {
                for j in 0..w {
                    let d = (Vec2::new(j as f32 + 0.5, i as f32 + 0.5) - c).length();
                    let px = img.get_pixel(j, i).0;
                    if d <= 3.9 {
                        // The near splat, shaded by its own distance from the center.
                        let expected = (255.0 * (0.4 + 0.6 * (1.0 - (d / 4.0).powi(2)).sqrt())).round();
                        assert!((f32::from(px[0]) - expected).abs() <= 1.0, "({i}, {j}): {px:?}");
                        assert_eq!(px[2], 0);
                    }
                }
            }
            // The far splat peeks out on the right.
            let (f, _) = project(&cam, far, w, h).unwrap();
            assert!(f.x > c.x + 1.0);
            let right = img.get_pixel((f.x + 3.0) as u32, f.y as u32).0;
            assert!(right[0] > 0 && right[2] == 0, "{right:?}");
        }
        // Radius 0: exactly the pixel containing the point.
        let img = render_points(&cam, w, h, &[near.to_array()], 0.0, [1.0; 3], [0.0; 3]).unwrap();
        let lit: Vec<(u32, u32)> = img
            .enumerate_pixels()
            .filter(|p| p.2 .0[0] > 0)
            .map(|p| (p.0, p.1))
            .collect();
        let (c, _) = project(&cam, near, w, h).unwrap();
        assert_eq!(lit, vec![(c.x as u32, c.y as u32)]);
        // Points behind the camera or off the image draw nothing.
        let none = [[0.0, 0.0, 5.0], [100.0, 0.0, 0.0]];
        let img = render_points(&cam, w, h, &none, 3.0, [1.0; 3], [0.0; 3]).unwrap();
        assert!(img.pixels().all(|p| p.0 == [0; 3]));
    }

    #[test]
    fn bad_arguments_are_errors() {
        let cam = camera();
        let mesh = Mesh::default();
        let e = |r: Result<RgbImage>| r.unwrap_err().to_string();
        assert!(e(render_mesh(&cam, 0, 4, &mesh, Vec3::Z, [1.0; 3], [0.0; 3])).contains("empty"));
        assert!(e(render_mesh(&cam, 4, 4, &mesh, Vec3::ZERO, [1.0; 3], [0.0; 3])).contains("light"));
        assert!(e(render_mesh(&cam, 4, 4, &mesh, Vec3::Z, [f32::NAN; 3], [0.0; 3])).contains("albedo"));
        let bad = Mesh {
            vertices: vec![[0.0; 3]],
            normals: vec![[0.0; 3]],
            triangles: vec![[0, 0, 1]],
            colors: Vec::new(),
        };
        assert!(e(render_mesh(&cam, 4, 4, &bad, Vec3::Z, [1.0; 3], [0.0; 3])).contains("triangle 0"));
        assert!(e(render_points(&cam, 4, 4, &[], -1.0, [1.0; 3], [0.0; 3])).contains("radius"));
        // An empty mesh or cloud is just the background.
        let img = render_mesh(&cam, 4, 4, &mesh, Vec3::Z, [1.0; 3], [0.5; 3]).unwrap();
        assert!(img.pixels().all(|p| p.0 == [128; 3]));
    }
}
