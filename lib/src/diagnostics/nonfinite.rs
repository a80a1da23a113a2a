//! Naming where a field is not finite. A function that is NaN or infinite somewhere (`sqrt` or `log` of a
//! negative, `0 / 0`) renders those rays as misses or black without a word; after a render, a probe of a
//! few rays of the first camera finds the first such point, so that the user is told which function and
//! where.

use glam::Vec3;
use nerfjit_runtime::{BatchFn, Camera};

/// Pixels probed per image side (a grid of `PROBE_SIDE`² rays).
const PROBE_SIDE: u32 = 16;
/// Points probed along each ray, evenly from near to far.
const PROBE_DEPTHS: u32 = 32;

/// The rays a probe follows and how far.
#[derive(Clone, Copy, Debug)]
pub struct ProbeRays<'a> {
    /// The camera whose pixels are probed.
    pub camera: &'a Camera,
    /// The image's width and height.
    pub size: (u32, u32),
    /// The start of the probed interval along each ray.
    pub near: f32,
    /// Its end.
    pub far: f32,
}

impl ProbeRays<'_> {
    /// Points (and their rays' unit directions) on a grid of pixel rays, evenly from near to far.
    fn points(&self) -> (Vec<Vec3>, Vec<Vec3>) {
        let (w, h) = self.size;
        let mut points = Vec::new();
        let mut dirs = Vec::new();
        for i in 0..PROBE_SIDE {
            for j in 0..PROBE_SIDE {
                let row = (i as f32 + 0.5) / PROBE_SIDE as f32 * h as f32;
                let col = (j as f32 + 0.5) / PROBE_SIDE as f32 * w as f32;
                let (origin, dir) = self.camera.ray_at(row, col, w, h);
                for k in 0..PROBE_DEPTHS {
                    let t = self.near + (self.far - self.near) * (k as f32 + 0.5) / PROBE_DEPTHS as f32;
                    points.push(origin + t * dir);
                    dirs.push(dir);
                }
            }
        }
        (points, dirs)
    }

    /// The probed points, and the inputs of a function of `n_inputs` (3: a position; 6: a position and a
    /// direction) at them as columns: x, y, z, then the ray's unit direction.
    pub(crate) fn columns(&self, n_inputs: usize) -> (Vec<Vec3>, Vec<Vec<f32>>) {
        let (points, dirs) = self.points();
        let columns = (0..n_inputs)
            .map(|c| match c {
                0..3 => points.iter().map(|p| p[c]).collect(),
                _ => dirs.iter().map(|d| d[c - 3]).collect(),
            })
            .collect();
        (points, columns)
    }
}

/// The first probed point where `f` (of a position, or of a position and a direction when it takes six
/// inputs) has an output that is not finite: the point and that output's value.
pub fn first_nonfinite(f: &dyn BatchFn, rays: ProbeRays) -> Option<(Vec3, f32)> {
    if !matches!(f.n_inputs(), 3 | 6) {
        return None;
    }
    let (points, columns) = rays.columns(f.n_inputs());
    let n = points.len();
    let inputs: Vec<&[f32]> = columns.iter().map(Vec::as_slice).collect();
    let outputs = f.eval_columns(&inputs);
    (0..n).find_map(|i| {
        let bad = outputs.iter().map(|o| o[i]).find(|v| !v.is_finite())?;
        Some((points[i], bad))
    })
}

/// A warning naming function `name` if the probe finds it not finite, else `None`.
pub fn warning(name: &str, f: &dyn BatchFn, rays: ProbeRays) -> Option<String> {
    let (p, value) = first_nonfinite(f, rays)?;
    Some(format!(
        "warning: '{name}' is {value} at [{:.4}, {:.4}, {:.4}] (found by probing {} points along the first \
         frame's rays): where a function is not finite, rays render as misses or black",
        p.x,
        p.y,
        p.z,
        (PROBE_SIDE * PROBE_SIDE * PROBE_DEPTHS)
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// f(p) = sqrt(p.x) (NaN where x < 0), or with `direction` also reading the direction's inputs.
    struct SqrtX {
        direction: bool,
    }

    impl BatchFn for SqrtX {
        fn n_inputs(&self) -> usize {
            if self.direction {
                6
            } else {
                3
            }
        }
        fn n_outputs(&self) -> usize {
            1
        }
        fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
            for i in 0..n {
                let shift = if self.direction { inputs[3][i] * 0.0 } else { 0.0 };
                outputs[0][i] = (inputs[0][i] + shift).sqrt();
            }
        }
    }

    fn camera(eye: Vec3) -> Camera {
        Camera::look_at(eye, Vec3::ZERO, Vec3::Z, glam::Vec2::ONE, glam::Vec2::ZERO).unwrap()
    }

    #[test]
    fn the_first_point_where_a_field_is_nan_is_named() {
        for direction in [false, true] {
            let f = SqrtX { direction };
            // Looking along -x from x = 4: the rays reach x < 0 past the origin.
            let from_x = camera(Vec3::new(4.0, 0.0, 0.0));
            let rays = ProbeRays {
                camera: &from_x,
                size: (64, 48),
                near: 1.0,
                far: 7.0,
            };
            let (p, value) = first_nonfinite(&f, rays).expect("NaN beyond the origin");
            assert!(p.x < 0.0 && value.is_nan(), "{p} {value}");
            let text = warning("sdf", &f, rays).unwrap();
            assert!(text.starts_with("warning: 'sdf' is NaN at ["), "{text}");
            // Nearer than the origin, every point has x > 0.
            let short = ProbeRays { far: 3.0, ..rays };
            assert_eq!(first_nonfinite(&f, short), None);
        }
    }
}
