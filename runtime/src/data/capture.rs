//! Captures of real scenes — nerfstudio / instant-ngp `transforms.json` files
//! ([`crate::data::nerfstudio`]) and COLMAP models ([`crate::data::colmap`]) — as training [`Views`].
//!
//! A capture is a list of frames, each a camera-to-world pose (OpenGL convention: camera looks
//! down −Z, +Y up, +X right), pixel intrinsics with optional OpenCV lens distortion, its image
//! size and its image file; COLMAP models add a sparse point cloud. Images may be PNG or JPEG,
//! RGB or RGBA, of any aspect ratio; they are undistorted to the pinhole camera of the same
//! intrinsics, composited onto a background and area-downscaled on load.
//!
//! Captures are in the coordinates of whatever made them. [`Capture::normalize`] moves them into
//! the frame nerfjit's scripts expect (the one of the NeRF-synthetic scenes), as instant-ngp's
//! `colmap2nerf` does: +Z along the cameras' mean up vector, the origin at the point nearest to
//! every optical axis (what the cameras look at), and the cameras 4 units from it on average.
//! Forward-facing captures with known depth bounds (LLFF's, or a COLMAP model's from its sparse points:
//! [`Capture::depth_bounds_from_points`]) put the origin on the mean optical axis
//! at the scene's nearest depth instead, turned so that the cameras look along +y (the mean camera
//! near (0, −4, 0)), and their bounds are scaled along.

use std::path::{Path, PathBuf};

use glam::{Mat3, Mat4, Vec3};
use rayon::prelude::*;

use crate::cameras::camera::{Camera, PixelIntrinsics};
use crate::data::blender::{area_resize, composite};
use crate::data::dataset::Views;
use crate::data::decode::decode_checked;
use crate::data::npy::ImageF32;
use crate::error::{Error, Result};

/// The mean distance of the cameras from the scene's center after [`Capture::normalize`], as in
/// the NeRF-synthetic scenes (and instant-ngp's `colmap2nerf`).
pub const NORMALIZED_CAMERA_DISTANCE: f32 = 4.0;

/// OpenCV's radial-tangential lens distortion of normalized image coordinates (`k1`, `k2`,
/// `k3` radial, `p1`, `p2` tangential); all zero for a pinhole camera.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Distortion {
    /// Radial coefficient of r².
    pub k1: f32,
    /// Radial coefficient of r⁴.
    pub k2: f32,
    /// Radial coefficient of r⁶.
    pub k3: f32,
    /// First tangential coefficient.
    pub p1: f32,
    /// Second tangential coefficient.
    pub p2: f32,
}

impl Distortion {
    /// Whether this is no distortion at all.
    pub fn is_none(&self) -> bool {
        *self == Distortion::default()
    }

    /// Where an undistorted normalized point (x, y) = (X/Z, Y/Z) appears in the distorted image.
    pub fn apply(&self, x: f32, y: f32) -> (f32, f32) {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
        (xd, yd)
    }
}

/// One frame's camera: pose, intrinsics, distortion and the size of its image in pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameCamera {
    /// Camera-to-world transform, OpenGL convention (looks down −Z, +Y up, +X right).
    pub c2w: Mat4,
    /// Pinhole intrinsics for an image of `width`×`height`.
    pub intrinsics: PixelIntrinsics,
    /// Lens distortion; images are undistorted on load.
    pub distortion: Distortion,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

impl FrameCamera {
    /// The (undistorted) camera for this frame's image resized to `width`×`height`: intrinsics
    /// scaled per axis, exact for area resampling.
    pub fn camera(&self, width: u32, height: u32) -> Result<Camera> {
        Camera::from_pixels(self.c2w, self.resized(width, height).intrinsics, width, height)
    }

    /// The same camera for its image stored at `width`×`height` (a smaller copy, such as those of
    /// `images_4/`): intrinsics scaled per axis; the distortion, in normalized coordinates, unchanged.
    pub fn resized(&self, width: u32, height: u32) -> FrameCamera {
        let (sx, sy) = (
            width as f32 / self.width as f32,
            height as f32 / self.height as f32,
        );
        let k = self.intrinsics;
        FrameCamera {
            intrinsics: PixelIntrinsics {
                fx: k.fx * sx,
                fy: k.fy * sy,
                cx: k.cx * sx,
                cy: k.cy * sy,
            },
            width,
            height,
            ..*self
        }
    }

    /// The image size after dividing by `downscale` (rounded, at least 1 pixel).
    pub fn downscaled(&self, downscale: u32) -> (u32, u32) {
        let side = |n: u32| ((n as f32 / downscale as f32).round() as u32).max(1);
        (side(self.width), side(self.height))
    }
}

/// One image of a capture and the camera that took it.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// The camera.
    pub camera: FrameCamera,
    /// The image file.
    pub image: PathBuf,
    /// An object mask for the image (white: object), if the data set has one: pixels where it is below
    /// half are replaced by the background on load, as NeuS and IDR train with masks.
    pub mask: Option<PathBuf>,
}

/// A capture: frames and, from COLMAP, the sparse points of the scene.
#[derive(Debug, Clone, PartialEq)]
pub struct Capture {
    /// The frames, in a stable order (file order, or by image name for COLMAP).
    pub frames: Vec<Frame>,
    /// Sparse 3D points of the scene (COLMAP's `points3D`), in the capture's coordinates.
    pub points: Vec<Vec3>,
    /// instant-ngp's `aabb_scale`, if the file states one.
    pub aabb_scale: Option<f32>,
    /// The nearest and farthest depth of the scene over all views (LLFF's per-view bounds), if known,
    /// in the capture's units: scaled with it by [`Capture::normalize`].
    pub depth_bounds: Option<(f32, f32)>,
}

/// The sparse points a view must see for [`Capture::depth_bounds_from_points`] to use its depths.
pub const MIN_POINTS_PER_VIEW: usize = 10;

/// The 0.1st and 99.9th percentiles of the depths of `points` in front of `camera` that project into
/// its image, if at least [`MIN_POINTS_PER_VIEW`] do.
fn view_depth_bounds(camera: &FrameCamera, points: &[Vec3]) -> Option<(f32, f32)> {
    let to_camera = camera.c2w.inverse();
    let k = camera.intrinsics;
    let (width, height) = (camera.width as f32, camera.height as f32);
    let mut depths: Vec<f32> = points
        .iter()
        .filter_map(|&p| {
            let q = to_camera.transform_point3(p);
            // OpenGL: the camera looks down −z, +y is up and the image's rows go down.
            let depth = -q.z;
            let (u, v) = (k.fx * q.x / depth + k.cx, k.cy - k.fy * q.y / depth);
            let inside = depth > 0.0 && (0.0..width).contains(&u) && (0.0..height).contains(&v);
            (inside && depth.is_finite()).then_some(depth)
        })
        .collect();
    if depths.len() < MIN_POINTS_PER_VIEW {
        return None;
    }
    depths.sort_unstable_by(f32::total_cmp);
    Some((percentile(&depths, 0.1), percentile(&depths, 99.9)))
}

/// The `q`th percentile (0 to 100) of sorted, non-empty `values`, interpolated linearly between the two
/// nearest ranks (NumPy's default, which LLFF's `imgs2poses` uses).
fn percentile(values: &[f32], q: f32) -> f32 {
    let rank = q / 100.0 * (values.len() - 1) as f32;
    let (below, t) = (rank.floor() as usize, rank.fract());
    let above = (below + 1).min(values.len() - 1);
    values[below] + t * (values[above] - values[below])
}

/// −1 or +1: bit `axis` of corner `i` of a cube.
fn sign(i: usize, axis: usize) -> f32 {
    if (i >> axis) & 1 == 1 {
        1.0
    } else {
        -1.0
    }
}

/// The similarity transform [`Capture::normalize`] applied: `x' = scale · (rotation · x − center)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Normalization {
    /// Rotation taking the cameras' mean up vector to +Z.
    pub rotation: Mat3,
    /// The scene's center after the rotation (the point nearest every optical axis).
    pub center: Vec3,
    /// Uniform scale making the mean camera distance [`NORMALIZED_CAMERA_DISTANCE`].
    pub scale: f32,
}

/// Half the side of instant-ngp's scene box per unit of `aabb_scale`, in the file's units: instant-ngp maps
/// the file's coordinates by 0.33 and an offset of 0.5 into its unit cube, which then spans ±1.5 about the
/// file's origin, and `aabb_scale` multiplies that cube.
const AABB_HALF_SIDE: f32 = 1.5;

impl Normalization {
    /// How far the cube of half-side `half` about the original coordinates' origin reaches along any axis
    /// once transformed: the largest coordinate of its corners (a box of ± that much holds it).
    pub fn cube_extent(&self, half: f32) -> f32 {
        let corners = (0..8).map(|i| half * Vec3::new(sign(i, 0), sign(i, 1), sign(i, 2)));
        corners
            .map(|c| self.point(c).abs().max_element())
            .fold(0.0, f32::max)
    }

    /// The transformed point.
    pub fn point(&self, x: Vec3) -> Vec3 {
        self.scale * (self.rotation * x - self.center)
    }

    /// The transformed camera-to-world matrix (rotated, its position moved and scaled).
    pub fn pose(&self, c2w: Mat4) -> Mat4 {
        let rotation = self.rotation * Mat3::from_mat4(c2w);
        let position = self.point(c2w.w_axis.truncate());
        Mat4::from_cols(
            rotation.x_axis.extend(0.0),
            rotation.y_axis.extend(0.0),
            rotation.z_axis.extend(0.0),
            position.extend(1.0),
        )
    }
}

/// How to turn a capture's images into views.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CaptureRequest {
    /// Divide both image sides by this (area resampling; 1 keeps the images as they are).
    pub downscale: u32,
    /// The color under transparent pixels of RGBA images.
    pub background: [f32; 3],
    /// Only the first this many frames, if given.
    pub limit: Option<usize>,
}

impl Capture {
    /// How far instant-ngp's scene box (the cube of half-side 1.5 × `aabb_scale` about the
    /// file's origin) reaches along any axis once moved by `normalization` (in the file's units without
    /// one), if the file states an `aabb_scale`.
    pub fn aabb_extent(&self, normalization: Option<&Normalization>) -> Option<f32> {
        let half = AABB_HALF_SIDE * self.aabb_scale?;
        Some(normalization.map_or(half, |n| n.cube_extent(half)))
    }

    /// The scene's nearest and farthest depth as LLFF's `imgs2poses` finds them, from the sparse points:
    /// per view, the 0.1st and 99.9th percentiles of the depths of the points in front of the camera that
    /// project into its image (points occluded in that view count too: COLMAP's tracks are not read;
    /// the lens distortion is left out of the projection); then the least of the views' near depths and
    /// the greatest of their far ones. Views that see fewer than [`MIN_POINTS_PER_VIEW`] points are left
    /// out; `None` when no view is left.
    pub fn depth_bounds_from_points(&self) -> Option<(f32, f32)> {
        let per_view: Vec<(f32, f32)> = self
            .frames
            .par_iter()
            .filter_map(|frame| view_depth_bounds(&frame.camera, &self.points))
            .collect();
        let near = per_view.iter().map(|b| b.0).reduce(f32::min)?;
        let far = per_view.iter().map(|b| b.1).reduce(f32::max)?;
        Some((near, far))
    }

    /// The capture with its images read from `folder` instead: the files of the same names stored smaller
    /// (mip-NeRF 360's `images_4/` beside `images/`), each camera scaled to its file's size.
    pub fn with_images_in(mut self, folder: &Path) -> Result<Capture> {
        for frame in &mut self.frames {
            let name = frame
                .image
                .file_name()
                .ok_or_else(|| Error::format(&frame.image, "the image has no file name"))?;
            let image = folder.join(name);
            let (width, height) = image::image_dimensions(&image)
                .map_err(|e| Error::format(&image, format!("cannot read the image's size: {e}")))?;
            frame.camera = frame.camera.resized(width, height);
            frame.image = image;
        }
        Ok(self)
    }

    /// Moves the capture into nerfjit's frame (see the [module docs](self)) and returns the
    /// transform it applied.
    pub fn normalize(&mut self) -> Result<Normalization> {
        let up: Vec3 = self.frames.iter().map(|f| f.camera.c2w.y_axis.truncate()).sum();
        let mut rotation = if up.length() > 1e-6 {
            rotation_onto_z(up.normalize())
        } else {
            Mat3::IDENTITY
        };
        let rotated = |rotation: Mat3| -> (Vec<Vec3>, Vec<Vec3>) {
            let positions = self
                .frames
                .iter()
                .map(|f| rotation * f.camera.c2w.w_axis.truncate())
                .collect();
            let axes = self
                .frames
                .iter()
                .map(|f| -(rotation * f.camera.c2w.z_axis.truncate()).normalize_or_zero())
                .collect();
            (positions, axes)
        };
        let (mut positions, mut axes) = rotated(rotation);
        let forward = self.forward_facing_near(&axes);
        if forward.is_some() {
            // Turned about z so that the cameras look along +y on average.
            let mean_axis = axes.iter().copied().sum::<Vec3>();
            let heading = mean_axis.x.atan2(mean_axis.y);
            rotation = Mat3::from_rotation_z(heading) * rotation;
            (positions, axes) = rotated(rotation);
        }
        let center = match forward {
            Some(near) => {
                let n = positions.len() as f32;
                let mean_position = positions.iter().copied().sum::<Vec3>() / n;
                let mean_axis = axes.iter().copied().sum::<Vec3>().normalize();
                mean_position + mean_axis * near
            }
            None => nearest_to_axes(&positions, &axes),
        };
        let mean_distance =
            positions.iter().map(|p| (*p - center).length()).sum::<f32>() / positions.len().max(1) as f32;
        if !(mean_distance > 1e-6 && mean_distance.is_finite()) {
            return Err(Error::Invalid(format!(
                "the {} cameras of the capture are all at one point: cannot scale the scene",
                positions.len()
            )));
        }
        let normalization = Normalization {
            rotation,
            center,
            scale: NORMALIZED_CAMERA_DISTANCE / mean_distance,
        };
        for frame in &mut self.frames {
            frame.camera.c2w = normalization.pose(frame.camera.c2w);
        }
        for p in &mut self.points {
            *p = normalization.point(*p);
        }
        if let Some((near, far)) = &mut self.depth_bounds {
            *near *= normalization.scale;
            *far *= normalization.scale;
        }
        Ok(normalization)
    }

    /// The nearest depth bound of a forward-facing capture (every camera looking within about 25° of
    /// their mean direction `axes`) whose depth bounds are known; `None` for other captures. Such
    /// captures (LLFF's scenes) are centered on the mean optical axis at that depth, so that after
    /// scaling the nearest content is 4 units from the cameras, and turned so that they look along
    /// +y: their optical axes are too close to parallel for their nearest point to be well defined.
    fn forward_facing_near(&self, axes: &[Vec3]) -> Option<f32> {
        let (near, _) = self.depth_bounds?;
        let mean_axis = axes.iter().copied().sum::<Vec3>() / axes.len().max(1) as f32;
        (mean_axis.length() >= 0.9 && near > 0.0 && near.is_finite()).then_some(near)
    }

    /// The first `limit` frames (all if `None`), or an error if there are fewer.
    fn first_frames(&self, source: &Path, limit: Option<usize>) -> Result<&[Frame]> {
        match limit {
            None => Ok(&self.frames),
            Some(n) if n >= 1 && n <= self.frames.len() => Ok(&self.frames[..n]),
            Some(n) => Err(Error::Invalid(format!(
                "views: {n} must be between 1 and the {} frames of {}",
                self.frames.len(),
                source.display()
            ))),
        }
    }

    /// The size every frame has after `downscale`, or an error naming a frame that differs.
    fn common_size(frames: &[Frame], downscale: u32) -> Result<(u32, u32)> {
        let first = frames
            .first()
            .ok_or_else(|| Error::Invalid("the capture has no frames".into()))?;
        let size = first.camera.downscaled(downscale);
        match frames.iter().find(|f| f.camera.downscaled(downscale) != size) {
            Some(odd) => Err(Error::format(
                &odd.image,
                format!(
                    "image is {}×{} but {} is {}×{}: nerfjit trains on images of one size",
                    odd.camera.width,
                    odd.camera.height,
                    first.image.display(),
                    first.camera.width,
                    first.camera.height
                ),
            )),
            None => Ok(size),
        }
    }

    /// The cameras of the first `limit` frames for their images divided by `downscale`.
    pub fn cameras(&self, source: &Path, downscale: u32, limit: Option<usize>) -> Result<Vec<Camera>> {
        let frames = self.first_frames(source, limit)?;
        let (width, height) = Capture::common_size(frames, downscale.max(1))?;
        frames.iter().map(|f| f.camera.camera(width, height)).collect()
    }

    /// How many views [`Capture::views`] would load with `downscale` and `limit`, and their width and
    /// height: known from the frames' intrinsics before any image is decoded.
    pub fn view_sizes(
        &self,
        source: &Path,
        downscale: u32,
        limit: Option<usize>,
    ) -> Result<(usize, u32, u32)> {
        let frames = self.first_frames(source, limit)?;
        let (width, height) = Capture::common_size(frames, downscale.max(1))?;
        Ok((frames.len(), width, height))
    }

    /// Loads the images of the capture (read from `source`) as views: decoded in parallel,
    /// undistorted, composited onto the background and downscaled. Every image must have the
    /// size its frame states; after downscaling all must have one size.
    pub fn views(&self, source: &Path, request: CaptureRequest) -> Result<Views> {
        if !request.background.iter().all(|c| c.is_finite()) {
            return Err(Error::Invalid(format!(
                "background {:?} must be finite",
                request.background
            )));
        }
        let downscale = request.downscale.max(1);
        let frames = self.first_frames(source, request.limit)?;
        let (width, height) = Capture::common_size(frames, downscale)?;
        let images = frames
            .par_iter()
            .map(|frame| load_frame(frame, (width, height), request.background))
            .collect::<Result<Vec<_>>>()?;
        let cameras = frames
            .iter()
            .map(|f| f.camera.camera(width, height))
            .collect::<Result<Vec<_>>>()?;
        Ok(Views {
            cameras,
            images,
            width,
            height,
            alpha: None,
            masks: None,
        })
    }
}

/// The shortest rotation taking the unit vector `from` onto +Z. (glam's `from_rotation_arc` returns the
/// identity for angles below about 7·10⁻⁴ rad; this keeps them.)
fn rotation_onto_z(from: Vec3) -> Mat3 {
    let axis = from.cross(Vec3::Z);
    let (sin, cos) = (axis.length(), from.z);
    if sin > 1e-12 {
        Mat3::from_axis_angle(axis / sin, sin.atan2(cos))
    } else if cos > 0.0 {
        Mat3::IDENTITY
    } else {
        // Upside down: half a turn about x.
        Mat3::from_axis_angle(Vec3::X, std::f32::consts::PI)
    }
}

/// The point nearest (in least squares) to every line `positions[i] + t·axes[i]`; the mean of the
/// positions when the lines are (nearly) parallel.
fn nearest_to_axes(positions: &[Vec3], axes: &[Vec3]) -> Vec3 {
    let n = positions.len().max(1) as f32;
    let mean = positions.iter().copied().sum::<Vec3>() / n;
    let mut a = Mat3::ZERO;
    let mut b = Vec3::ZERO;
    for (p, d) in positions.iter().zip(axes) {
        // (I − d dᵀ) projects onto the plane perpendicular to the axis.
        let projector = Mat3::IDENTITY - Mat3::from_cols(*d * d.x, *d * d.y, *d * d.z);
        a += projector;
        b += projector * (*p - mean);
    }
    if (a * (1.0 / n)).determinant() < 1e-3 {
        return mean;
    }
    mean + a.inverse() * b
}

/// Decodes, undistorts, composites and resizes one frame's image to `size`.
fn load_frame(frame: &Frame, size: (u32, u32), background: [f32; 3]) -> Result<ImageF32> {
    let mut rgba = decode_checked(&frame.image, None)?.to_rgba32f();
    let camera = &frame.camera;
    if rgba.dimensions() != (camera.width, camera.height) {
        return Err(Error::format(
            &frame.image,
            format!(
                "image is {}×{} but its camera says {}×{}",
                rgba.width(),
                rgba.height(),
                camera.width,
                camera.height
            ),
        ));
    }
    if let Some(mask) = &frame.mask {
        apply_mask(&mut rgba, mask)?;
    }
    let mut image = composite(&rgba, background);
    if !camera.distortion.is_none() {
        image = undistort(&image, camera.intrinsics, camera.distortion);
    }
    if (image.width, image.height) != size {
        image = area_resize(&image, size.0, size.1);
    }
    Ok(image)
}

/// Makes the pixels of `rgba` transparent where the mask image at `mask` (of the same size; gray or
/// color, read as luminance) is below half: masks saved as JPEG or resampled are not strictly binary.
fn apply_mask(rgba: &mut image::Rgba32FImage, mask: &Path) -> Result<()> {
    let luma = decode_checked(mask, None)?.to_luma32f();
    if luma.dimensions() != rgba.dimensions() {
        return Err(Error::format(
            mask,
            format!(
                "the mask is {}×{} but its image is {}×{}",
                luma.width(),
                luma.height(),
                rgba.width(),
                rgba.height()
            ),
        ));
    }
    for (pixel, m) in rgba.pixels_mut().zip(luma.pixels()) {
        if m[0] < 0.5 {
            pixel[3] = 0.0;
        }
    }
    Ok(())
}

/// The pinhole image of the same intrinsics: each pixel samples (bilinearly, clamped to the
/// border) the distorted image where its ray landed.
pub fn undistort(image: &ImageF32, k: PixelIntrinsics, distortion: Distortion) -> ImageF32 {
    let (w, h) = (image.width as usize, image.height as usize);
    let pixels = (0..h)
        .into_par_iter()
        .flat_map_iter(|row| {
            (0..w).map(move |col| {
                let x = (col as f32 + 0.5 - k.cx) / k.fx;
                let y = (row as f32 + 0.5 - k.cy) / k.fy;
                let (xd, yd) = distortion.apply(x, y);
                bilinear(image, k.fy * yd + k.cy - 0.5, k.fx * xd + k.cx - 0.5)
            })
        })
        .collect();
    ImageF32 {
        width: image.width,
        height: image.height,
        pixels,
    }
}

/// The image at continuous pixel-index coordinates (pixel centers at integers), clamped to the
/// border.
fn bilinear(image: &ImageF32, row: f32, col: f32) -> [f32; 3] {
    let (w, h) = (image.width as usize, image.height as usize);
    let r = row.clamp(0.0, (h - 1) as f32);
    let c = col.clamp(0.0, (w - 1) as f32);
    let (r0, c0) = (r.floor() as usize, c.floor() as usize);
    let (r1, c1) = ((r0 + 1).min(h - 1), (c0 + 1).min(w - 1));
    let (fr, fc) = (r - r0 as f32, c - c0 as f32);
    let at = |r: usize, c: usize| image.pixels[r * w + c];
    let (a, b, c_, d) = (at(r0, c0), at(r0, c1), at(r1, c0), at(r1, c1));
    std::array::from_fn(|i| {
        let top = a[i] + fc * (b[i] - a[i]);
        let bottom = c_[i] + fc * (d[i] - c_[i]);
        top + fr * (bottom - top)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn a_cube_reaches_as_far_as_its_farthest_transformed_corner() {
        let shifted = Normalization {
            rotation: Mat3::IDENTITY,
            center: Vec3::new(1.0, 0.0, 0.0),
            scale: 2.0,
        };
        // x from −1 − 1 to 1 − 1, times 2: −4 to 0.
        assert_eq!(shifted.cube_extent(1.0), 4.0);
        let turned = Normalization {
            rotation: Mat3::from_rotation_z(std::f32::consts::FRAC_PI_4),
            center: Vec3::ZERO,
            scale: 1.0,
        };
        // A corner (1.5, 1.5, ·) turned by 45° lies at x = 0 and y = 1.5·√2.
        assert!((turned.cube_extent(1.5) - 1.5 * 2f32.sqrt()).abs() < 1e-5);
    }

    fn look_at(eye: Vec3, up: Vec3) -> Mat4 {
        // OpenGL: −Z looks at the origin.
        let back = eye.normalize();
        let right = up.cross(back).normalize();
        let up = back.cross(right);
        Mat4::from_cols(
            right.extend(0.0),
            up.extend(0.0),
            back.extend(0.0),
            eye.extend(1.0),
        )
    }

    fn frame(c2w: Mat4) -> Frame {
        Frame {
            camera: FrameCamera {
                c2w,
                intrinsics: PixelIntrinsics {
                    fx: 50.0,
                    fy: 50.0,
                    cx: 24.0,
                    cy: 16.0,
                },
                distortion: Distortion::default(),
                width: 48,
                height: 32,
            },
            image: PathBuf::from("x.png"),
            mask: None,
        }
    }

    /// Eight cameras 4 units from the origin looking at it, z up, symmetric about the z axis.
    fn ring() -> Capture {
        let frames = (0..8)
            .map(|i| {
                let azimuth = i as f32 * std::f32::consts::FRAC_PI_4;
                let elevation: f32 = if i % 2 == 0 { 0.5 } else { -0.2 };
                let eye = 4.0
                    * Vec3::new(
                        elevation.cos() * azimuth.cos(),
                        elevation.cos() * azimuth.sin(),
                        elevation.sin(),
                    );
                frame(look_at(eye, Vec3::Z))
            })
            .collect();
        Capture {
            frames,
            points: vec![Vec3::new(0.1, 0.2, 0.3)],
            aabb_scale: None,
            depth_bounds: None,
        }
    }

    proptest! {
        #[test]
        fn normalization_undoes_a_tilt_a_shift_and_a_scale(
            axis_angle in 0.0f32..std::f32::consts::TAU,
            tilt in -1.2f32..1.2,
            shift in prop::array::uniform3(-20.0f32..20.0),
            scale in 0.05f32..30.0,
        ) {
            // A rotation about a horizontal axis (the arc normalization takes back), then a
            // shift and a scale, applied to the symmetric ring.
            let axis = Vec3::new(axis_angle.cos(), axis_angle.sin(), 0.0);
            let moved = Normalization {
                rotation: Mat3::from_axis_angle(axis, tilt),
                center: Vec3::from(shift),
                scale,
            };
            let original = ring();
            let mut capture = original.clone();
            for f in &mut capture.frames {
                f.camera.c2w = moved.pose(f.camera.c2w);
            }
            capture.points[0] = moved.point(capture.points[0]);
            capture.normalize().unwrap();
            for (got, want) in capture.frames.iter().zip(&original.frames) {
                prop_assert!(got.camera.c2w.abs_diff_eq(want.camera.c2w, 2e-3),
                    "{} vs {}", got.camera.c2w, want.camera.c2w);
            }
            prop_assert!(capture.points[0].abs_diff_eq(original.points[0], 2e-3));
        }
    }

    #[test]
    fn depth_bounds_are_the_views_percentiles_of_the_points_they_see() {
        // Points on the −z axis at depths 1 to 1000 from the origin, and three no view counts: behind the
        // cameras, and in front of the first but outside its image to the right and above.
        let mut points: Vec<Vec3> = (1..=1000).map(|d| Vec3::new(0.0, 0.0, -(d as f32))).collect();
        points.extend([
            Vec3::new(0.0, 0.0, 5.0),
            Vec3::new(10.0, 0.0, -0.5),
            Vec3::new(0.0, 0.2, -0.5),
        ]);
        let mut further = Mat4::IDENTITY;
        further.w_axis = Vec3::new(0.0, 0.0, -500.0).extend(1.0);
        let mut capture = Capture {
            frames: vec![frame(Mat4::IDENTITY), frame(further)],
            points,
            aabb_scale: None,
            depth_bounds: None,
        };
        // The first view sees depths 1 to 1000 (NumPy's percentiles 1.999 and 999.001), the second 1 to
        // 500 (1.499 and 499.501): the least near depth and the greatest far one.
        let (near, far) = capture.depth_bounds_from_points().unwrap();
        assert!(
            (near - 1.499).abs() < 1e-3 && (far - 999.001).abs() < 1e-2,
            "{near} {far}"
        );
        // A view that sees fewer than MIN_POINTS_PER_VIEW points is left out; with none left, no bounds.
        capture.points.truncate(MIN_POINTS_PER_VIEW - 1);
        assert_eq!(capture.depth_bounds_from_points(), None);
        capture.points.clear();
        assert_eq!(capture.depth_bounds_from_points(), None);
    }

    #[test]
    fn tiny_and_upside_down_tilts_are_undone() {
        for tilt in [6.664e-4f32, 1e-5, std::f32::consts::PI] {
            let r = Mat3::from_axis_angle(Vec3::X, tilt);
            let up = r * Vec3::Z;
            assert!((rotation_onto_z(up) * up).abs_diff_eq(Vec3::Z, 1e-6), "{tilt}");
        }
    }

    #[test]
    fn parallel_cameras_are_centered_on_their_mean_position() {
        let frames = (0..3)
            .map(|i| {
                let mut c2w = Mat4::IDENTITY;
                c2w.w_axis = Vec3::new(i as f32, 0.0, 0.0).extend(1.0);
                frame(c2w)
            })
            .collect();
        let mut capture = Capture {
            frames,
            points: Vec::new(),
            aabb_scale: None,
            depth_bounds: None,
        };
        let n = capture.normalize().unwrap();
        assert!(n.point(Vec3::new(1.0, 0.0, 0.0)).length() < 1e-5);
        let one_place = Capture {
            frames: vec![frame(Mat4::IDENTITY); 2],
            points: Vec::new(),
            aabb_scale: None,
            depth_bounds: None,
        };
        let e = one_place.clone().normalize().unwrap_err().to_string();
        assert!(e.contains("all at one point"), "{e}");
    }

    #[test]
    fn forward_facing_cameras_with_depth_bounds_are_centered_at_the_nearest_depth() {
        // Five cameras in a row along x, all looking down −Z (the OpenGL identity pose), slightly
        // turned; the scene from 10 to 50 units in front of them.
        let frames = (0..5)
            .map(|i| {
                let turn = Mat4::from_rotation_y(0.05 * (i as f32 - 2.0));
                let mut c2w = turn;
                c2w.w_axis = Vec3::new(i as f32 - 2.0, 0.0, 0.0).extend(1.0);
                frame(c2w)
            })
            .collect();
        let mut capture = Capture {
            frames,
            points: Vec::new(),
            aabb_scale: None,
            depth_bounds: Some((10.0, 50.0)),
        };
        let n = capture.normalize().unwrap();
        // The origin is 10 units along the mean axis from the mean position, and that distance is 4.
        assert!(n.point(Vec3::new(0.0, 0.0, -10.0)).length() < 1e-3, "{n:?}");
        let (near, far) = capture.depth_bounds.unwrap();
        assert!(
            (near - 4.0).abs() < 0.05 && (far - 20.0).abs() < 0.25,
            "{near} {far}"
        );
        // The cameras look along +y, z up: the middle one from (0, −4, 0) (the mean distance is 4).
        let middle = capture.frames[2].camera.c2w;
        assert!(
            (middle.w_axis.truncate() - Vec3::new(0.0, -4.0, 0.0)).length() < 0.05,
            "{middle}"
        );
        assert!((-middle.z_axis.truncate() - Vec3::Y).length() < 1e-4, "{middle}");
    }

    #[test]
    fn downscaled_cameras_keep_rays_through_the_same_footprints() {
        let f = frame(look_at(Vec3::new(3.0, 1.0, 2.0), Vec3::Z));
        assert_eq!(f.camera.downscaled(2), (24, 16));
        let full = f.camera.camera(48, 32).unwrap();
        let half = f.camera.camera(24, 16).unwrap();
        // Half-resolution pixel (3, 5) covers full-resolution rows 6–7 and columns 10–11.
        let (_, a) = half.ray(3, 5, 24, 16);
        let (_, b) = full.ray_at(7.0, 11.0, 48, 32);
        assert!(a.abs_diff_eq(b, 1e-5), "{a} {b}");
    }

    #[test]
    fn smaller_copies_of_the_images_keep_their_rays() {
        let dir = std::env::temp_dir().join(format!("nerfjit-capture-smaller-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("images_2")).unwrap();
        image::RgbImage::new(24, 16)
            .save(dir.join("images_2/x.png"))
            .unwrap();
        let mut full = frame(look_at(Vec3::new(3.0, 1.0, 2.0), Vec3::Z));
        full.image = dir.join("images/x.png");
        let capture = Capture {
            frames: vec![full.clone()],
            points: Vec::new(),
            aabb_scale: None,
            depth_bounds: None,
        };
        let smaller = capture.with_images_in(&dir.join("images_2")).unwrap();
        let half = &smaller.frames[0];
        assert_eq!(half.image, dir.join("images_2/x.png"));
        assert_eq!((half.camera.width, half.camera.height), (24, 16));
        // The same rays as the full-size camera divided on load.
        let (a, b) = (
            half.camera.camera(24, 16).unwrap(),
            full.camera.camera(24, 16).unwrap(),
        );
        assert!(a.ray(3, 5, 24, 16).1.abs_diff_eq(b.ray(3, 5, 24, 16).1, 1e-6));
        let e = Capture {
            frames: vec![full],
            ..smaller
        }
        .with_images_in(&dir.join("nowhere"))
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("nowhere/x.png") && e.contains("cannot read the image's size"),
            "{e}"
        );
    }

    /// The normalized coordinates whose distortion is (xd, yd), by Newton's method.
    fn undistorted(d: Distortion, xd: f32, yd: f32) -> (f32, f32) {
        let (mut x, mut y) = (xd, yd);
        for _ in 0..50 {
            let (fx, fy) = d.apply(x, y);
            let e = 1e-3;
            let (ax, ay) = d.apply(x + e, y);
            let (bx, by) = d.apply(x, y + e);
            let j = Mat3::from_cols(
                Vec3::new((ax - fx) / e, (ay - fy) / e, 0.0),
                Vec3::new((bx - fx) / e, (by - fy) / e, 0.0),
                Vec3::Z,
            );
            let step = j.inverse() * Vec3::new(fx - xd, fy - yd, 0.0);
            x -= step.x;
            y -= step.y;
        }
        (x, y)
    }

    #[test]
    fn undistortion_recovers_the_pinhole_image_of_a_smooth_scene() {
        let k = PixelIntrinsics {
            fx: 60.0,
            fy: 58.0,
            cx: 41.0,
            cy: 29.0,
        };
        let d = Distortion {
            k1: -0.12,
            k2: 0.03,
            k3: 0.0,
            p1: 0.002,
            p2: -0.001,
        };
        // The scene as a pinhole camera would see it, in normalized coordinates.
        let scene = |x: f32, y: f32| {
            [
                0.5 + 0.4 * (6.0 * x).sin(),
                0.5 + 0.3 * (4.0 * y).cos(),
                0.5 * (x + y).cos(),
            ]
        };
        let (w, h) = (80u32, 60u32);
        let pixel = |row: u32, col: u32| ((col as f32 + 0.5 - k.cx) / k.fx, (row as f32 + 0.5 - k.cy) / k.fy);
        let distorted = ImageF32 {
            width: w,
            height: h,
            pixels: (0..h)
                .flat_map(|r| (0..w).map(move |c| (r, c)))
                .map(|(r, c)| {
                    let (xd, yd) = pixel(r, c);
                    let (x, y) = undistorted(d, xd, yd);
                    scene(x, y)
                })
                .collect(),
        };
        let fixed = undistort(&distorted, k, d);
        let mut worst: f32 = 0.0;
        let mut before: f32 = 0.0;
        // Away from the border, where undistortion samples inside the image.
        for r in 6..h - 6 {
            for c in 6..w - 6 {
                let (x, y) = pixel(r, c);
                let want = scene(x, y);
                let i = (r * w + c) as usize;
                for (ch, want) in want.iter().enumerate() {
                    worst = worst.max((fixed.pixels[i][ch] - want).abs());
                    before = before.max((distorted.pixels[i][ch] - want).abs());
                }
            }
        }
        assert!(worst < 5e-3, "undistorted differs by {worst}");
        assert!(
            before > 0.03,
            "the test's distortion is too weak to matter: {before}"
        );
    }
}
