//! Perspective pinhole cameras with one internal representation and two exact constructors:
//! PyTorch3D NDC cameras ([`Camera::look_at`]), Blender / NeRF-synthetic cameras
//! ([`Camera::from_blender`]) and cameras with pixel intrinsics ([`Camera::from_pixels`]).
//!
//! Internally a camera is a camera-to-world rotation whose columns are the camera axes in
//! PyTorch3D's view convention (+X image left, +Y image up, +Z forward), the camera position,
//! and intrinsics in NDC: `x_ndc = fx·X/Z + px`, `y_ndc = fy·Y/Z + py` for a view-space point
//! (X, Y, Z). NDC relates to pixels by an [`NdcScale`] `S`: a pixel at continuous coordinates
//! (row, col) has `x_ndc = (W − 2·col)/S`, `y_ndc = (H − 2·row)/S`.
//!
//! Continuous pixel coordinates: pixel (i, j) covers rows [i, i+1) and columns [j, j+1), so its
//! center is at (i + 0.5, j + 0.5).

use glam::{Mat3, Mat4, Vec2, Vec3};

use crate::error::{Error, Result};

/// Which image side spans NDC [−1, 1] (between the outer pixel edges).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NdcScale {
    /// PyTorch3D: the shorter side spans [−1, 1], the longer one more.
    ShorterSide,
    /// Blender / NeRF: the width spans [−1, 1] (focal from the horizontal field of view).
    Width,
}

impl NdcScale {
    /// The pixels the side spanning NDC [−1, 1] has in a `width`×`height` image.
    pub fn pixels(self, width: u32, height: u32) -> f32 {
        match self {
            NdcScale::ShorterSide => width.min(height) as f32,
            NdcScale::Width => width as f32,
        }
    }
}

/// Checks a horizontal field of view in radians.
pub(crate) fn check_field_of_view(camera_angle_x: f32) -> Result<()> {
    if !(camera_angle_x > 0.0 && camera_angle_x < std::f32::consts::PI) {
        return Err(Error::Invalid(format!(
            "camera_angle_x {camera_angle_x} must be in (0, π) radians"
        )));
    }
    Ok(())
}

/// Pinhole intrinsics in pixels: focal lengths and principal point (OpenCV's `fx, fy, cx, cy`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelIntrinsics {
    /// Horizontal focal length in pixels.
    pub fx: f32,
    /// Vertical focal length in pixels.
    pub fy: f32,
    /// Principal point's column in pixels (the image center is width / 2).
    pub cx: f32,
    /// Principal point's row in pixels (the image center is height / 2).
    pub cy: f32,
}

/// The rotation part of a camera-to-world matrix, which must be finite, orthonormal and
/// right-handed.
fn checked_rotation(c2w: Mat4) -> Result<Mat3> {
    let rot = Mat3::from_mat4(c2w);
    let orthonormal = (rot.transpose() * rot).abs_diff_eq(Mat3::IDENTITY, 1e-3);
    if !c2w.is_finite() || !orthonormal || rot.determinant() < 0.0 {
        return Err(Error::Invalid(format!(
            "transform_matrix {c2w} must be finite with a rotation (orthonormal, right-handed) 3×3 part"
        )));
    }
    Ok(rot)
}

/// A perspective pinhole camera. See the module docs for the conventions.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// Camera-to-world rotation; columns are the view axes (+X left, +Y up, +Z forward).
    rotation: Mat3,
    position: Vec3,
    focal: Vec2,
    principal: Vec2,
    scale: NdcScale,
}

impl Camera {
    /// PyTorch3D `look_at_view_transform(eye, at, up)` with `PerspectiveCameras(focal,
    /// principal_point)` in NDC: z = normalize(at − eye), x = normalize(up × z),
    /// y = normalize(z × x); R has these axes as columns and a world point X (row vector) maps
    /// to view space by X·R + T with T = −Rᵀ·eye.
    pub fn look_at(eye: Vec3, at: Vec3, up: Vec3, focal: Vec2, principal: Vec2) -> Result<Camera> {
        let all_finite = [eye, at, up].iter().all(|v| v.is_finite());
        if !all_finite || !principal.is_finite() {
            return Err(Error::Invalid(format!(
                "camera eye {eye}, at {at}, up {up} and principal point {principal} must be finite"
            )));
        }
        let z = (at - eye).normalize_or_zero();
        if z == Vec3::ZERO {
            return Err(Error::Invalid(format!(
                "camera eye and target are the same point {eye}"
            )));
        }
        let x = up.cross(z).normalize_or_zero();
        if x == Vec3::ZERO {
            return Err(Error::Invalid(format!(
                "camera up {up} is zero or parallel to the viewing direction {z}"
            )));
        }
        let y = z.cross(x).normalize();
        Camera::new(
            Mat3::from_cols(x, y, z),
            eye,
            focal,
            principal,
            NdcScale::ShorterSide,
        )
    }

    /// A Blender / NeRF-synthetic camera: `c2w` is the camera-to-world `transform_matrix`
    /// (camera looks down −Z, +Y up, +X right) and `camera_angle_x` the horizontal field of
    /// view in radians, so `focal_px = 0.5·W / tan(0.5·camera_angle_x)`.
    pub fn from_blender(c2w: Mat4, camera_angle_x: f32) -> Result<Camera> {
        check_field_of_view(camera_angle_x)?;
        let rot = checked_rotation(c2w)?;
        // Blender right/up/back axes → view left/up/forward.
        let rotation = Mat3::from_cols(-rot.x_axis, rot.y_axis, -rot.z_axis);
        let focal = Vec2::splat(1.0 / (0.5 * camera_angle_x).tan());
        Camera::new(
            rotation,
            c2w.w_axis.truncate(),
            focal,
            Vec2::ZERO,
            NdcScale::Width,
        )
    }

    /// A camera with pixel intrinsics, as nerfstudio and COLMAP state them: `c2w` is the
    /// camera-to-world transform in the OpenGL / Blender convention (camera looks down −Z, +Y up,
    /// +X right) and a view-space point (x right, y down, z forward) projects to the continuous
    /// pixel `(col, row) = (fx·x/z + cx, fy·y/z + cy)` of a `width`×`height` image (pixel centers
    /// at +0.5). The camera keeps these intrinsics in NDC scaled by the width, so it fits other
    /// images of the same aspect ratio too.
    pub fn from_pixels(c2w: Mat4, pixels: PixelIntrinsics, width: u32, height: u32) -> Result<Camera> {
        let rotation = checked_rotation(c2w)?;
        let PixelIntrinsics { fx, fy, cx, cy } = pixels;
        if !(fx > 0.0 && fy > 0.0 && cx.is_finite() && cy.is_finite() && fx.is_finite() && fy.is_finite()) {
            return Err(Error::Invalid(format!(
                "focal lengths ({fx}, {fy}) px must be positive and the principal point ({cx}, {cy}) finite"
            )));
        }
        crate::error::check_size(width, height)?;
        let (w, h) = (width as f32, height as f32);
        Camera::new(
            Mat3::from_cols(-rotation.x_axis, rotation.y_axis, -rotation.z_axis),
            c2w.w_axis.truncate(),
            Vec2::new(2.0 * fx / w, 2.0 * fy / w),
            Vec2::new((w - 2.0 * cx) / w, (h - 2.0 * cy) / w),
            NdcScale::Width,
        )
    }

    fn new(rotation: Mat3, position: Vec3, focal: Vec2, principal: Vec2, scale: NdcScale) -> Result<Camera> {
        if !focal.is_finite() || focal.x == 0.0 || focal.y == 0.0 {
            return Err(Error::Invalid(format!(
                "camera focal length {focal} must be finite and non-zero"
            )));
        }
        Ok(Camera {
            rotation,
            position,
            focal,
            principal,
            scale,
        })
    }

    /// The camera center in world space.
    pub fn position(&self) -> Vec3 {
        self.position
    }

    /// Focal lengths (x, y) in NDC units of the side chosen by [`Camera::ndc_scale`].
    pub fn focal(&self) -> Vec2 {
        self.focal
    }

    /// Which image side spans NDC [−1, 1]: the shorter side for PyTorch3D cameras, the width
    /// for Blender cameras.
    pub fn ndc_scale(&self) -> NdcScale {
        self.scale
    }

    /// Camera-to-world rotation; its columns are the view axes +X (image left), +Y (image up)
    /// and +Z (forward) in world space.
    pub fn rotation(&self) -> Mat3 {
        self.rotation
    }

    /// The camera-to-world transform in the OpenGL / Blender convention of [`Camera::from_pixels`] (looking
    /// down −z, +y up, +x right).
    pub fn c2w(&self) -> Mat4 {
        let r = self.rotation;
        let axes = Mat3::from_cols(-r.x_axis, r.y_axis, -r.z_axis);
        Mat4::from_cols(
            axes.x_axis.extend(0.0),
            axes.y_axis.extend(0.0),
            axes.z_axis.extend(0.0),
            self.position.extend(1.0),
        )
    }

    /// Its intrinsics in pixels for a `width`×`height` image, as [`Camera::from_pixels`] takes them: with
    /// [`Camera::c2w`] they make the same camera.
    pub fn pixel_intrinsics(&self, width: u32, height: u32) -> PixelIntrinsics {
        let s = self.scale.pixels(width, height);
        PixelIntrinsics {
            fx: 0.5 * self.focal.x * s,
            fy: 0.5 * self.focal.y * s,
            cx: 0.5 * (width as f32 - self.principal.x * s),
            cy: 0.5 * (height as f32 - self.principal.y * s),
        }
    }

    /// The camera whose `(width + 2·margin)`×`(height + 2·margin)` view is this camera's `width`×`height`
    /// view with `margin` more pixels on every side: its pixel (row + margin, col + margin) sees what this
    /// camera's pixel (row, col) sees. (A bake renders its views so, to see a little beyond every frame it
    /// was trained on.)
    pub fn widened(&self, width: u32, height: u32, margin: u32) -> Result<Camera> {
        let PixelIntrinsics { fx, fy, cx, cy } = self.pixel_intrinsics(width, height);
        let m = margin as f32;
        let wider = PixelIntrinsics {
            fx,
            fy,
            cx: cx + m,
            cy: cy + m,
        };
        Camera::from_pixels(self.c2w(), wider, width + 2 * margin, height + 2 * margin)
    }

    /// NDC (x, y) of continuous pixel coordinates (`row`, `col`) in a `width`×`height` image:
    /// +x left, +y up; the side chosen by the camera's [`NdcScale`] spans [−1, 1].
    pub fn pixel_ndc(&self, row: f32, col: f32, width: u32, height: u32) -> Vec2 {
        let s = self.scale.pixels(width, height);
        Vec2::new((width as f32 - 2.0 * col) / s, (height as f32 - 2.0 * row) / s)
    }

    /// View-space X/Z of the ray through continuous column `col` of a `width`×`height` image.
    pub(crate) fn view_x(&self, col: f32, width: u32, height: u32) -> f32 {
        let ndc = self.pixel_ndc(0.0, col, width, height).x;
        (ndc - self.principal.x) / self.focal.x
    }

    /// View-space Y/Z of the ray through continuous row `row` of a `width`×`height` image.
    pub(crate) fn view_y(&self, row: f32, width: u32, height: u32) -> f32 {
        let ndc = self.pixel_ndc(row, 0.0, width, height).y;
        (ndc - self.principal.y) / self.focal.y
    }

    /// Unit world direction of the view-space direction (x, y, 1).
    pub(crate) fn direction(&self, x: f32, y: f32) -> Vec3 {
        (self.rotation.x_axis * x + self.rotation.y_axis * y + self.rotation.z_axis).normalize()
    }

    /// The ray (origin, unit direction) through the center of pixel (`row`, `col`) of a
    /// `width`×`height` image. Width and height must be at least 1.
    pub fn ray(&self, row: u32, col: u32, width: u32, height: u32) -> (Vec3, Vec3) {
        self.ray_at(row as f32 + 0.5, col as f32 + 0.5, width, height)
    }

    /// The ray (origin, unit direction) through continuous pixel coordinates (`row`, `col`);
    /// pixel (i, j) has its center at (i + 0.5, j + 0.5).
    pub fn ray_at(&self, row: f32, col: f32, width: u32, height: u32) -> (Vec3, Vec3) {
        let x = self.view_x(col, width, height);
        let y = self.view_y(row, width, height);
        (self.position, self.direction(x, y))
    }

    /// Continuous pixel coordinates (row, col) of world point `p` in a `width`×`height` image
    /// (pixel (i, j) has its center at (i + 0.5, j + 0.5)); `None` if `p` is not in front of
    /// the camera. The result may lie outside the image.
    pub fn project(&self, p: Vec3, width: u32, height: u32) -> Option<(f32, f32)> {
        let v = self.rotation.transpose() * (p - self.position);
        if !v.is_finite() || v.z <= 0.0 {
            return None;
        }
        let s = self.scale.pixels(width, height);
        let x_ndc = self.focal.x * v.x / v.z + self.principal.x;
        let y_ndc = self.focal.y * v.y / v.z + self.principal.y;
        let col = 0.5 * (width as f32 - x_ndc * s);
        let row = 0.5 * (height as f32 - y_ndc * s);
        Some((row, col))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn course_camera() -> Camera {
        Camera::look_at(
            Vec3::new(-2.5, 0.0, 0.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec2::ONE,
            Vec2::ZERO,
        )
        .unwrap()
    }

    #[test]
    fn pytorch3d_known_point_projects_to_known_pixel() {
        let cam = course_camera();
        // R columns: x = up × z = (0,0,−1), y = (0,1,0), z = (1,0,0); T = (0, 0, 2.5).
        // p = (0, 0.5, 0.5) → view (−0.5, 0.5, 2.5) → NDC (−0.2, 0.2).
        let (row, col) = cam.project(Vec3::new(0.0, 0.5, 0.5), 256, 256).unwrap();
        assert!((col - 0.5 * (256.0 + 0.2 * 256.0)).abs() < 1e-3, "col {col}");
        assert!((row - 0.5 * (256.0 - 0.2 * 256.0)).abs() < 1e-3, "row {row}");
    }

    #[test]
    fn pytorch3d_orientation_matches_course_data() {
        let cam = course_camera();
        let (cr, cc) = cam.project(Vec3::ZERO, 256, 256).unwrap();
        assert!((cr - 128.0).abs() < 1e-4 && (cc - 128.0).abs() < 1e-4);
        // +Y world is up in the image (smaller row), same column.
        let (r, c) = cam.project(Vec3::new(0.0, 0.5, 0.0), 256, 256).unwrap();
        assert!(r < cr - 10.0 && (c - cc).abs() < 1e-4);
        // View +X (image left) is world −z, so world +z lands right of the center.
        let (r, c) = cam.project(Vec3::new(0.0, 0.0, 0.5), 256, 256).unwrap();
        assert!(c > cc + 10.0 && (r - cr).abs() < 1e-4);
        // Points behind the camera do not project.
        assert!(cam.project(Vec3::new(-3.0, 0.0, 0.0), 256, 256).is_none());
    }

    #[test]
    fn pytorch3d_pixel_centers_follow_ndc_convention() {
        let cam = course_camera();
        // Pixel (0, 0) center: NDC (1 − 1/W, 1 − 1/H), i.e. top left is +x (left), +y (up).
        let (o, d) = cam.ray(0, 0, 4, 4);
        assert_eq!(o, Vec3::new(-2.5, 0.0, 0.0));
        let expected = (Vec3::new(1.0, 0.75, -0.75)).normalize();
        assert!(d.abs_diff_eq(expected, 1e-6), "{d}");
        // Non-square: the shorter side (height 2) spans [−1, 1], the width [−2, 2].
        let (_, d) = cam.ray_at(0.0, 0.0, 4, 2);
        assert!(d.abs_diff_eq(Vec3::new(1.0, 1.0, -2.0).normalize(), 1e-6), "{d}");
    }

    #[test]
    fn a_widened_camera_sees_the_same_rays_a_margin_further_in() {
        let pose = Camera::from_blender(lego_pose(), 0.69).unwrap();
        let course = course_camera();
        for (camera, (width, height)) in [(pose, (30, 50)), (course, (40, 24)), (pose, (64, 64))] {
            let margin = 7;
            let wide = camera.widened(width, height, margin).unwrap();
            let (w, h) = (width + 2 * margin, height + 2 * margin);
            for (row, col) in [(0, 0), (height - 1, 3), (5, width - 1), (height / 2, width / 2)] {
                let (o, d) = camera.ray(row, col, width, height);
                let (o2, d2) = wide.ray(row + margin, col + margin, w, h);
                assert!(
                    o.abs_diff_eq(o2, 1e-5) && d.abs_diff_eq(d2, 1e-5),
                    "{d} against {d2}"
                );
            }
            // A point projected by both lands `margin` pixels further in.
            let p = camera.position() + camera.rotation().z_axis * 3.0 + camera.rotation().x_axis * 0.2;
            let (r, c) = camera.project(p, width, height).unwrap();
            let (r2, c2) = wide.project(p, w, h).unwrap();
            assert!((r + margin as f32 - r2).abs() < 1e-3 && (c + margin as f32 - c2).abs() < 1e-3);
        }
    }

    #[test]
    fn blender_known_point_projects_to_known_pixel() {
        // Identity pose, 90° field of view: focal_px = W/2.
        let cam = Camera::from_blender(Mat4::IDENTITY, std::f32::consts::FRAC_PI_2).unwrap();
        let (row, col) = cam.project(Vec3::new(1.0, 0.5, -2.0), 200, 100).unwrap();
        assert!((col - (100.0 + 100.0 * 0.5)).abs() < 1e-3, "col {col}");
        assert!((row - (50.0 - 100.0 * 0.25)).abs() < 1e-3, "row {row}");
        assert!(cam.project(Vec3::new(0.0, 0.0, 1.0), 200, 100).is_none());
        // Ray through pixel (i, j): ((j+0.5 − W/2)/f, −(i+0.5 − H/2)/f, −1).
        let (_, d) = cam.ray(10, 30, 200, 100);
        let expected = Vec3::new((30.5 - 100.0) / 100.0, -(10.5 - 50.0) / 100.0, -1.0);
        assert!(d.abs_diff_eq(expected.normalize(), 1e-6), "{d}");
    }

    /// The camera-to-world matrix of a lego training view.
    fn lego_pose() -> Mat4 {
        let rows = [
            [-0.9305422, 0.11707554, -0.3469646, -1.3986591],
            [-0.36618456, -0.29751042, 0.88170075, 3.5542498],
            [7.450581e-9, 0.947513, 0.31971723, 1.2888215],
            [0.0, 0.0, 0.0, 1.0],
        ];
        Mat4::from_cols_array_2d(&rows).transpose()
    }

    #[test]
    fn blender_matches_nerf_formula_on_a_lego_pose() {
        let c2w = lego_pose();
        let fov = 0.691_111_2_f32;
        let cam = Camera::from_blender(c2w, fov).unwrap();
        let (w, h) = (800, 800);
        let f = 0.5 * w as f32 / (0.5 * fov).tan();
        let p = Vec3::new(0.3, -0.2, 0.4);
        let rot = Mat3::from_mat4(c2w);
        let pc = rot.transpose() * (p - c2w.w_axis.truncate());
        let (u, v) = (400.0 + f * pc.x / -pc.z, 400.0 - f * pc.y / -pc.z);
        let (row, col) = cam.project(p, w, h).unwrap();
        assert!(
            (col - u).abs() < 1e-2 && (row - v).abs() < 1e-2,
            "{row},{col} vs {v},{u}"
        );
    }

    #[test]
    fn pixel_intrinsics_match_the_opencv_formula_on_a_rectangular_image() {
        let c2w = lego_pose();
        let k = PixelIntrinsics {
            fx: 610.0,
            fy: 590.0,
            cx: 331.0,
            cy: 228.5,
        };
        let (w, h) = (640, 480);
        let cam = Camera::from_pixels(c2w, k, w, h).unwrap();
        let p = Vec3::new(0.3, -0.2, 0.4);
        let rot = Mat3::from_mat4(c2w);
        // OpenGL view space (x right, y up, z back) → OpenCV (x right, y down, z forward).
        let gl = rot.transpose() * (p - c2w.w_axis.truncate());
        let cv = Vec3::new(gl.x, -gl.y, -gl.z);
        let (u, v) = (k.fx * cv.x / cv.z + k.cx, k.fy * cv.y / cv.z + k.cy);
        let (row, col) = cam.project(p, w, h).unwrap();
        assert!(
            (col - u).abs() < 1e-2 && (row - v).abs() < 1e-2,
            "{row},{col} vs {v},{u}"
        );
        // The ray of that pixel passes through the point.
        let (origin, dir) = cam.ray_at(v, u, w, h);
        assert!((origin + dir * (p - origin).dot(dir) - p).length() < 1e-4);
        // The Blender camera is the special case of centered intrinsics.
        let fov = 0.691_111_2_f32;
        let f = 0.5 * w as f32 / (0.5 * fov).tan();
        let centered = PixelIntrinsics {
            fx: f,
            fy: f,
            cx: 0.5 * w as f32,
            cy: 0.5 * h as f32,
        };
        let from_pixels = Camera::from_pixels(c2w, centered, w, h).unwrap();
        let blender = Camera::from_blender(c2w, fov).unwrap();
        let (a, b) = (
            from_pixels.project(p, w, h).unwrap(),
            blender.project(p, w, h).unwrap(),
        );
        assert!(
            (a.0 - b.0).abs() < 1e-3 && (a.1 - b.1).abs() < 1e-3,
            "{a:?} {b:?}"
        );
        let bad = PixelIntrinsics { fx: 0.0, ..k };
        assert!(Camera::from_pixels(c2w, bad, w, h).is_err());
    }

    #[test]
    fn degenerate_cameras_are_errors() {
        let e = Camera::look_at(Vec3::ONE, Vec3::ONE, Vec3::Y, Vec2::ONE, Vec2::ZERO);
        assert!(e.is_err());
        let e = Camera::look_at(Vec3::Y, Vec3::ZERO, Vec3::Y, Vec2::ONE, Vec2::ZERO);
        assert!(e.unwrap_err().to_string().contains("parallel"));
        let e = Camera::look_at(Vec3::X, Vec3::ZERO, Vec3::Y, Vec2::ZERO, Vec2::ZERO);
        assert!(e.is_err());
        assert!(Camera::from_blender(Mat4::IDENTITY, 0.0).is_err());
        assert!(Camera::from_blender(Mat4::from_scale(Vec3::splat(2.0)), 1.0).is_err());
    }

    fn check_round_trip(cam: &Camera, p: Vec3, w: u32, h: u32) -> std::result::Result<(), TestCaseError> {
        let Some((row, col)) = cam.project(p, w, h) else {
            return Ok(());
        };
        let (o, d) = cam.ray_at(row, col, w, h);
        let to_p = p - o;
        let miss = (to_p - d * to_p.dot(d)).length();
        prop_assert!(miss <= 1e-4 * (1.0 + to_p.length()), "ray misses p by {}", miss);
        prop_assert!(to_p.dot(d) > 0.0);
        Ok(())
    }

    proptest! {
        #[test]
        fn ray_of_projection_passes_through_point_pytorch3d(
            eye in prop::array::uniform3(-5.0f32..5.0),
            p in prop::array::uniform3(-1.0f32..1.0),
            focal in 0.5f32..3.0,
            w in 1u32..400,
            h in 1u32..400,
        ) {
            let eye = Vec3::from(eye);
            prop_assume!(eye.length() > 2.0 && eye.normalize().y.abs() < 0.95);
            let cam = Camera::look_at(eye, Vec3::ZERO, Vec3::Y, Vec2::splat(focal), Vec2::new(0.1, -0.05)).unwrap();
            check_round_trip(&cam, Vec3::from(p), w, h)?;
        }

        #[test]
        fn c2w_and_pixel_intrinsics_make_the_same_camera(
            eye in prop::array::uniform3(-5.0f32..5.0),
            focal in prop::array::uniform2(0.5f32..3.0),
            principal in prop::array::uniform2(-0.2f32..0.2),
            w in 1u32..400,
            h in 1u32..400,
            row in 0.0f32..1.0,
            col in 0.0f32..1.0,
        ) {
            let eye = Vec3::from(eye);
            prop_assume!(eye.length() > 2.0 && eye.normalize().y.abs() < 0.95);
            let course = Camera::look_at(eye, Vec3::ZERO, Vec3::Y, Vec2::from(focal), Vec2::from(principal)).unwrap();
            let again = Camera::from_pixels(course.c2w(), course.pixel_intrinsics(w, h), w, h).unwrap();
            let (row, col) = (row * h as f32, col * w as f32);
            let ((o1, d1), (o2, d2)) = (course.ray_at(row, col, w, h), again.ray_at(row, col, w, h));
            prop_assert!((o1 - o2).length() < 1e-5 && (d1 - d2).length() < 1e-4, "{d1} against {d2}");
        }

        #[test]
        fn ray_of_projection_passes_through_point_blender(
            angles in prop::array::uniform3(-3.0f32..3.0),
            t in prop::array::uniform3(-4.0f32..4.0),
            p in prop::array::uniform3(-1.0f32..1.0),
            fov in 0.2f32..2.5,
            w in 1u32..400,
            h in 1u32..400,
        ) {
            let q = glam::Quat::from_euler(glam::EulerRot::XYZ, angles[0], angles[1], angles[2]);
            let c2w = Mat4::from_rotation_translation(q, Vec3::from(t));
            let cam = Camera::from_blender(c2w, fov).unwrap();
            check_round_trip(&cam, Vec3::from(p), w, h)?;
        }
    }
}
