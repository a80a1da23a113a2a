//! Drawing a bake: its splats as a camera sees them, less those beside the camera ([`in_view`]), for
//! `eval-views`, `render` and `compare` of a `.bake` and for fine-tuning it (`nerfjit bake --tune`).

use rayon::prelude::*;

use nerfjit_runtime::splats::{render_splats, splat_loss_gradients, SplatGradients, Splats};
use nerfjit_runtime::{Camera, VolumeFrame};

use crate::failure::Result;

/// How far beyond the frame's edges a splat's center may lie and still be drawn, as a share of the frame's
/// width and height on each side (3D Gaussian splatting's 1.3 times the field of view's tangent).
pub const DRAWN_BEYOND: f32 = 0.15;

/// Which of `splats` `camera` draws in a `width`×`height` frame: those in front of it whose centers lie
/// within the frame widened by [`DRAWN_BEYOND`] on each side. The renderer linearizes the projection at
/// each splat's center, which stretches a splat beside the camera (far off to the side, barely in front)
/// across the whole frame; 3D Gaussian splatting clamps the linearization at 1.3 times the field of view
/// instead, which keeps such splats off the screen as leaving them out does. A bake of a capture, whose
/// splats surround every camera, needs it; an object's splats all lie in front of its cameras.
pub fn in_view(splats: &Splats, camera: &Camera, (width, height): (u32, u32)) -> Vec<usize> {
    let (w, h) = (width as f32, height as f32);
    let (cols, rows) = (
        -DRAWN_BEYOND * w..=(1.0 + DRAWN_BEYOND) * w,
        -DRAWN_BEYOND * h..=(1.0 + DRAWN_BEYOND) * h,
    );
    (0..splats.len())
        .into_par_iter()
        .with_min_len(4096)
        .filter(|&i| {
            camera
                .project(glam::Vec3::from(splats.positions[i]), width, height)
                .is_some_and(|(row, col)| rows.contains(&row) && cols.contains(&col))
        })
        .collect()
}

/// The splats of `splats` at `indices`.
fn subset(splats: &Splats, indices: &[usize]) -> Splats {
    Splats {
        positions: indices.iter().map(|&i| splats.positions[i]).collect(),
        colors: indices.iter().map(|&i| splats.colors[i]).collect(),
        opacities: indices.iter().map(|&i| splats.opacities[i]).collect(),
        scales: indices.iter().map(|&i| splats.scales[i]).collect(),
        rotations: indices.iter().map(|&i| splats.rotations[i]).collect(),
    }
}

/// The `width`×`height` frame `camera` sees of `splats` over `background`, drawn from the splats
/// [`in_view`].
pub fn draw(splats: &Splats, camera: &Camera, size: (u32, u32), background: [f32; 3]) -> Result<VolumeFrame> {
    let shown = subset(splats, &in_view(splats, camera, size));
    Ok(render_splats(&shown, camera, size.0, size.1, background)?.0)
}

/// [`splat_loss_gradients`] of the frame [`draw`] draws: the splats not [`in_view`] take no part, and their
/// gradients are zero.
pub fn loss_gradients_in_view(
    splats: &Splats,
    camera: &Camera,
    size: (u32, u32),
    background: [f32; 3],
    target: &[[f32; 3]],
) -> Result<(f64, SplatGradients)> {
    let indices = in_view(splats, camera, size);
    let (loss, shown) = splat_loss_gradients(&subset(splats, &indices), camera, size, background, target)?;
    let n = splats.len();
    let mut all = SplatGradients {
        positions: vec![[0.0; 3]; n],
        colors: vec![[0.0; 3]; n],
        opacities: vec![0.0; n],
        scales: vec![[0.0; 3]; n],
        rotations: vec![[0.0; 4]; n],
    };
    for (k, &i) in indices.iter().enumerate() {
        all.positions[i] = shown.positions[k];
        all.colors[i] = shown.colors[k];
        all.opacities[i] = shown.opacities[k];
        all.scales[i] = shown.scales[k];
        all.rotations[i] = shown.rotations[k];
    }
    Ok((loss, all))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{Vec2, Vec3};

    /// A camera at the origin looking along +x, 2 units of focal length (a field of view of 53°).
    fn camera() -> Camera {
        Camera::look_at(Vec3::ZERO, Vec3::X, Vec3::Z, Vec2::splat(2.0), Vec2::ZERO).unwrap()
    }

    fn splats(positions: &[[f32; 3]], scale: f32) -> Splats {
        let n = positions.len();
        Splats {
            positions: positions.to_vec(),
            colors: vec![[1.0, 0.0, 0.0]; n],
            opacities: vec![0.99; n],
            scales: vec![[scale; 3]; n],
            rotations: vec![[1.0, 0.0, 0.0, 0.0]; n],
        }
    }

    #[test]
    fn splats_beside_or_behind_the_camera_are_not_drawn() {
        // Ahead; at the frame's side edge, within the margin; far to the side and barely in front; behind.
        let scene = splats(
            &[
                [3.0, 0.0, 0.0],
                [3.0, 1.65, 0.0],
                [0.02, -50.0, 10.0],
                [-3.0, 0.0, 0.0],
            ],
            0.05,
        );
        assert_eq!(in_view(&scene, &camera(), (40, 30)), vec![0, 1]);
        // Drawn, the splat beside the camera leaves the frame's edges alone: its color is the background's
        // (linearized at its center, its projection would cover the frame).
        let beside = splats(&[[0.02, -50.0, 10.0]], 0.05);
        let frame = draw(&beside, &camera(), (40, 30), [0.0, 0.0, 1.0]).unwrap();
        assert!(frame.rgb.iter().all(|c| *c == [0.0, 0.0, 1.0]));
        assert!(frame.opacity.iter().all(|&o| o == 0.0));
    }

    #[test]
    fn the_gradients_of_a_frame_are_those_of_the_splats_it_draws() {
        let scene = splats(&[[3.0, 0.2, 0.0], [0.02, -50.0, 10.0], [3.0, -0.2, 0.1]], 0.2);
        let target = vec![[0.5, 0.5, 0.5]; 40 * 30];
        let (loss, gradients) =
            loss_gradients_in_view(&scene, &camera(), (40, 30), [0.0; 3], &target).unwrap();
        let drawn = subset(&scene, &[0, 2]);
        let (alone, of_drawn) = splat_loss_gradients(&drawn, &camera(), (40, 30), [0.0; 3], &target).unwrap();
        assert_eq!(loss, alone);
        assert_eq!(gradients.colors.len(), 3);
        assert_eq!(gradients.colors[0], of_drawn.colors[0]);
        assert_eq!(gradients.positions[2], of_drawn.positions[1]);
        assert_eq!(gradients.colors[1], [0.0; 3]);
        assert!(gradients.colors[0].iter().any(|&g| g != 0.0));
    }
}
