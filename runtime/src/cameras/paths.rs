//! Camera paths around the origin for turntable renders.

use glam::{Vec2, Vec3};

use crate::cameras::camera::Camera;
use crate::error::{Error, Result};

/// The world axis that points up in a camera path.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Up {
    /// +Y is up; the path circles in the XZ plane.
    Y,
    /// +Z is up; the path circles in the XY plane.
    Z,
}

impl Up {
    /// The axis a setting names: `y` or `z` (anything else is `None`).
    pub fn named(name: &str) -> Option<Up> {
        match name {
            "y" => Some(Up::Y),
            "z" => Some(Up::Z),
            _ => None,
        }
    }

    /// The up direction: +Y or +Z.
    pub fn vector(self) -> Vec3 {
        match self {
            Up::Y => Vec3::Y,
            Up::Z => Vec3::Z,
        }
    }
}

fn check_path(radius: f32, frames: usize, focal: f32) -> Result<()> {
    if frames == 0 {
        return Err(Error::Invalid("a camera path needs at least 1 frame".into()));
    }
    if !(radius.is_finite() && radius > 0.0) {
        return Err(Error::Invalid(format!(
            "camera path radius {radius} must be positive"
        )));
    }
    if !(focal.is_finite() && focal > 0.0) {
        return Err(Error::Invalid(format!(
            "camera path focal length {focal} must be positive"
        )));
    }
    Ok(())
}

/// The angles θ of `linspace(0, 2π, frames + 1)[:-1]`.
fn angles(frames: usize) -> impl Iterator<Item = f64> {
    (0..frames).map(move |k| std::f64::consts::TAU * k as f64 / frames as f64)
}

fn look_at_origin(eye: [f64; 3], up: Up, focal: f32) -> Result<Camera> {
    let eye = Vec3::new(eye[0] as f32, eye[1] as f32, eye[2] as f32);
    Camera::look_at(eye, Vec3::ZERO, up.vector(), Vec2::splat(focal), Vec2::ZERO)
}

/// The course's `surround(radius, n, up, focal)` path of PyTorch3D cameras looking at the
/// origin: for θ in linspace(0, 2π, n+1)[:-1], with φ = θ + π/2, the eye is
/// (r cos φ, 0, −r sin φ) for [`Up::Y`] and (r cos φ, r sin φ, 2) for [`Up::Z`].
pub fn surround(radius: f32, frames: usize, up: Up, focal: f32) -> Result<Vec<Camera>> {
    check_path(radius, frames, focal)?;
    let r = f64::from(radius);
    angles(frames)
        .map(|theta| {
            let phi = theta + std::f64::consts::FRAC_PI_2;
            let eye = match up {
                Up::Y => [r * phi.cos(), 0.0, -r * phi.sin()],
                Up::Z => [r * phi.cos(), r * phi.sin(), 2.0],
            };
            look_at_origin(eye, up, focal)
        })
        .collect()
}

/// A circular path of PyTorch3D cameras at distance `radius` from the origin, raised by
/// `elevation_deg` above the plane normal to `up`, looking at the origin. With elevation 0
/// and [`Up::Y`] it equals [`surround`].
pub fn orbit(radius: f32, elevation_deg: f32, frames: usize, up: Up, focal: f32) -> Result<Vec<Camera>> {
    check_path(radius, frames, focal)?;
    if elevation_deg.is_nan() || elevation_deg.abs() >= 90.0 {
        return Err(Error::Invalid(format!(
            "orbit elevation {elevation_deg}° must be strictly between −90° and 90°"
        )));
    }
    let r = f64::from(radius);
    let elevation = f64::from(elevation_deg).to_radians();
    let (flat, height) = (r * elevation.cos(), r * elevation.sin());
    angles(frames)
        .map(|theta| {
            let phi = theta + std::f64::consts::FRAC_PI_2;
            let eye = match up {
                Up::Y => [flat * phi.cos(), height, -flat * phi.sin()],
                Up::Z => [flat * phi.cos(), flat * phi.sin(), height],
            };
            look_at_origin(eye, up, focal)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn surround_eyes_follow_the_course_formula() {
        let cams = surround(3.0, 4, Up::Y, 1.5).unwrap();
        assert_eq!(cams.len(), 4);
        let expected = [
            Vec3::new(0.0, 0.0, -3.0),
            Vec3::new(-3.0, 0.0, 0.0),
            Vec3::new(0.0, 0.0, 3.0),
            Vec3::new(3.0, 0.0, 0.0),
        ];
        for (cam, eye) in cams.iter().zip(expected) {
            assert!(cam.position().abs_diff_eq(eye, 1e-5), "{}", cam.position());
            // Every camera looks at the origin.
            let (row, col) = cam.project(Vec3::ZERO, 64, 64).unwrap();
            assert!((row - 32.0).abs() < 1e-3 && (col - 32.0).abs() < 1e-3);
        }
        let cams = surround(3.0, 4, Up::Z, 1.0).unwrap();
        assert!(cams[0].position().abs_diff_eq(Vec3::new(0.0, 3.0, 2.0), 1e-5));
        assert!(cams[1].position().abs_diff_eq(Vec3::new(-3.0, 0.0, 2.0), 1e-5));
    }

    #[test]
    fn orbit_generalizes_surround() {
        let a = surround(2.0, 7, Up::Y, 1.0).unwrap();
        let b = orbit(2.0, 0.0, 7, Up::Y, 1.0).unwrap();
        for (a, b) in a.iter().zip(&b) {
            assert!(a.position().abs_diff_eq(b.position(), 1e-6));
            assert!(a.rotation().abs_diff_eq(b.rotation(), 1e-6));
        }
        for cam in orbit(4.0, 30.0, 5, Up::Z, 1.0).unwrap() {
            let p = cam.position();
            assert!((p.length() - 4.0).abs() < 1e-5);
            assert!((p.z - 2.0).abs() < 1e-5, "height r·sin 30° = 2, got {p}");
        }
    }

    #[test]
    fn bad_paths_are_errors() {
        assert!(surround(2.0, 0, Up::Y, 1.0).is_err());
        assert!(surround(-1.0, 3, Up::Y, 1.0).is_err());
        assert!(surround(1.0, 3, Up::Y, 0.0).is_err());
        assert!(orbit(1.0, 90.0, 3, Up::Y, 1.0).is_err());
        assert!(orbit(1.0, f32::NAN, 3, Up::Y, 1.0).is_err());
    }
}
