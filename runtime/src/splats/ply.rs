//! The `.ply` layout of 3D Gaussian splatting (Kerbl et al. 2023, as its `save_ply` writes it and splat
//! viewers read it): one binary little-endian vertex a splat with float properties `x y z`, `nx ny nz`
//! (zeros), `f_dc_0..2` (the color's degree-0 spherical harmonic, color = 0.5 + C0 · f_dc), `opacity` (its
//! logit), `scale_0..2` (log standard deviations) and `rot_0..3` (the quaternion w, x, y, z); splats whose
//! color changes with the view add `f_rest_0..8` after `f_dc` (the degree-one spherical harmonics, red's
//! three coefficients, then green's, then blue's).

use std::path::Path;

use super::shading::SH_C0;
use super::Splats;
use crate::error::{check_output_folder, Result};

/// The float properties of a vertex, in order, with `f_rest` (the degree-one spherical harmonics) or not.
fn properties(f_rest: bool) -> Vec<String> {
    let mut names: Vec<String> = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        .map(String::from)
        .to_vec();
    if f_rest {
        names.extend((0..9).map(|k| format!("f_rest_{k}")));
    }
    names.extend(
        [
            "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
        ]
        .map(String::from),
    );
    names
}

/// Writes `splats` to `path` in the 3D Gaussian splatting `.ply` layout, whole or not at all.
pub fn write_splat_ply(splats: &Splats, path: &Path) -> Result<()> {
    splats.check()?;
    let properties = properties(!splats.sh.is_empty());
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment 3D Gaussian splats written by nerfjit\nelement vertex {}\n",
        splats.len()
    );
    for name in &properties {
        header.push_str(&format!("property float {name}\n"));
    }
    header.push_str("end_header\n");
    let mut bytes = header.into_bytes();
    bytes.reserve(splats.len() * properties.len() * 4);
    let mut put = |values: &[f32]| {
        for v in values {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    };
    for i in 0..splats.len() {
        let color = splats.colors[i].map(|c| (c - 0.5) / SH_C0);
        let alpha = splats.opacities[i].clamp(1e-6, 1.0 - 1e-6);
        let logit = (alpha / (1.0 - alpha)).ln();
        let [x, y, z] = splats.positions[i];
        let [sx, sy, sz] = splats.scales[i].map(f32::ln);
        let [w, qx, qy, qz] = splats.rotations[i];
        put(&[x, y, z, 0.0, 0.0, 0.0, color[0], color[1], color[2]]);
        if let Some(sh) = splats.sh.get(i) {
            // Channel by channel, as 3D Gaussian splatting flattens its (3, coefficients) features.
            put(&std::array::from_fn::<f32, 9, _>(|k| sh[k % 3][k / 3]));
        }
        put(&[logit, sx, sy, sz, w, qx, qy, qz]);
    }
    check_output_folder(path)?;
    crate::whole_file::write_whole(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_splat_is_written_as_the_3dgs_layout_says() {
        let splats = Splats {
            positions: vec![[1.0, -2.0, 3.0]],
            colors: vec![[0.5, 1.0, 0.0]],
            opacities: vec![0.75],
            scales: vec![[0.01, 0.02, 0.04]],
            rotations: vec![[1.0, 0.0, 0.0, 0.0]],
            sh: Vec::new(),
        };
        let values = written(&splats);
        assert_eq!(values.len(), 17);
        assert_eq!(&values[..3], &[1.0, -2.0, 3.0]);
        let color: Vec<f32> = values[6..9].iter().map(|f| 0.5 + SH_C0 * f).collect();
        for (c, expected) in color.iter().zip([0.5, 1.0, 0.0]) {
            assert!((c - expected).abs() < 1e-6, "{color:?}");
        }
        assert!((1.0 / (1.0 + (-values[9]).exp()) - 0.75).abs() < 1e-6);
        assert!((values[10].exp() - 0.01).abs() < 1e-8 && (values[12].exp() - 0.04).abs() < 1e-8);
        assert_eq!(&values[13..], &[1.0, 0.0, 0.0, 0.0]);
    }

    /// The values of the one splat written in `splats`, after checking the header names the properties.
    fn written(splats: &Splats) -> Vec<f32> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("scene.ply");
        write_splat_ply(splats, &path).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let end = b"end_header\n";
        let at = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
        let header = std::str::from_utf8(&bytes[..at]).unwrap();
        assert!(header.contains("element vertex 1\n"), "{header}");
        let named: Vec<&str> = header
            .lines()
            .filter_map(|l| l.strip_prefix("property float "))
            .collect();
        assert_eq!(named, properties(!splats.sh.is_empty()), "{header}");
        assert_eq!(&named[6..9], ["f_dc_0", "f_dc_1", "f_dc_2"]);
        assert_eq!(named[named.len() - 8], "opacity");
        bytes[at..]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect()
    }

    /// The degree-one harmonics follow `f_dc`, red's three coefficients first, then green's, then blue's.
    #[test]
    fn harmonics_are_written_channel_by_channel() {
        let splats = Splats {
            positions: vec![[0.0; 3]],
            colors: vec![[0.5; 3]],
            opacities: vec![0.5],
            scales: vec![[1.0; 3]],
            rotations: vec![[1.0, 0.0, 0.0, 0.0]],
            // sh[k][c]: coefficient k of channel c, here 10 k + c.
            sh: vec![[[0.0, 1.0, 2.0], [10.0, 11.0, 12.0], [20.0, 21.0, 22.0]]],
        };
        let values = written(&splats);
        assert_eq!(values.len(), 26);
        assert_eq!(
            &values[9..18],
            &[0.0, 10.0, 20.0, 1.0, 11.0, 21.0, 2.0, 12.0, 22.0]
        );
        assert_eq!(&values[22..], &[1.0, 0.0, 0.0, 0.0]);
    }

    #[test]
    fn bad_splats_are_refused_with_what_is_wrong() {
        let mut splats = Splats {
            positions: vec![[0.0; 3]],
            colors: vec![[0.5; 3]],
            opacities: vec![0.5],
            scales: vec![[0.0, 1.0, 1.0]],
            rotations: vec![[1.0, 0.0, 0.0, 0.0]],
            sh: Vec::new(),
        };
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("scene.ply");
        let message = write_splat_ply(&splats, &path).unwrap_err().to_string();
        assert!(message.contains("splat 0: its scales"), "{message}");
        splats.scales[0] = [1.0; 3];
        splats.colors.clear();
        let message = write_splat_ply(&splats, &path).unwrap_err().to_string();
        assert!(message.contains("1 splat positions but 0 colors"), "{message}");
        assert!(!path.exists());
    }
}
