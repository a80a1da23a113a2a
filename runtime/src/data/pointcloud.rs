//! Point clouds: reading them from `.npz`, `.npy`, `.ply` and XYZ text files, centering them
//! and bounding them.

use std::path::Path;

use glam::Vec3;

use crate::data::npy::parse_points;
use crate::data::ply;
use crate::error::{Error, Result};

/// Reads the points of `path`, by its extension (case-insensitive):
///
/// - `.npz`: the array `key` (e.g. `verts`; the entry `verts.npy`) of a NumPy archive, stored
///   or deflated; without a key, the archive's only array;
/// - `.npy`: a NumPy array;
/// - `.ply`: the `x y z` properties of the `vertex` element (ASCII or binary little-endian);
/// - `.xyz` or `.txt`: one point per line, its first three numbers (separated by spaces, tabs
///   or commas; further columns such as normals are ignored); blank lines and lines starting
///   with `#` are skipped;
/// - `.obj`: the vertices (`v x y z` lines; faces, normals and every other statement are ignored).
///
/// Arrays must have shape (N, 3) and dtype float32 or float64. `key` only applies to `.npz`
/// files. Errors name the file and what is wrong: a missing key (listing the arrays), a wrong
/// dtype or shape, a bad line, a non-finite coordinate, or no points at all.
pub fn read_points(path: &Path, key: Option<&str>) -> Result<Vec<[f32; 3]>> {
    let extension = path
        .extension()
        .map(|e| e.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    if key.is_some() && extension != "npz" {
        return Err(Error::format(
            path,
            format!("an array key ({key:?}) only applies to .npz archives"),
        ));
    }
    let points = match extension.as_str() {
        "npz" => read_npz(path, key)?,
        "npy" => {
            let bytes = crate::input::read_capped(path).map_err(|e| Error::read(path, e))?;
            parse_points(&bytes).map_err(|e| Error::format(path, e))?
        }
        "ply" => read_ply_points(path)?,
        "xyz" | "txt" => read_xyz(path, |line| Some(line))?,
        "obj" => read_xyz(path, |line| {
            line.strip_prefix("v ").or_else(|| line.strip_prefix("v\t"))
        })?,
        _ => {
            return Err(Error::format(
                path,
                format!(
                "unknown point cloud format '.{extension}': expected .npz, .npy, .ply, .obj, .xyz or .txt"
            ),
            ))
        }
    };
    if points.is_empty() {
        return Err(Error::format(path, "the file has no points"));
    }
    Ok(points)
}

fn read_npz(path: &Path, key: Option<&str>) -> Result<Vec<[f32; 3]>> {
    let file = std::fs::File::open(path).map_err(|e| Error::read(path, e))?;
    let mut archive = zip::ZipArchive::new(std::io::BufReader::new(file))
        .map_err(|e| Error::format(path, format!("not a .npz (zip) archive: {e}")))?;
    let arrays: Vec<String> = archive
        .file_names()
        .filter_map(|name| Some(name.ok()?.strip_suffix(".npy")?.to_string()))
        .collect();
    let listing = || {
        if arrays.is_empty() {
            "the archive has no arrays".to_string()
        } else {
            format!("its arrays are: {}", arrays.join(", "))
        }
    };
    let name = match key {
        Some(key) => {
            let key = key.strip_suffix(".npy").unwrap_or(key);
            if !arrays.iter().any(|a| a == key) {
                return Err(Error::format(path, format!("no array '{key}'; {}", listing())));
            }
            key.to_string()
        }
        None => match arrays.as_slice() {
            [only] => only.clone(),
            _ => {
                return Err(Error::format(
                    path,
                    format!("pass the key of the array to read; {}", listing()),
                ))
            }
        },
    };
    let bytes = archive
        .by_name(&format!("{name}.npy"))
        .map_err(std::io::Error::from)
        .and_then(crate::input::read_stream_capped)
        .map_err(|e| Error::format(path, format!("array '{name}': {e}")))?;
    parse_points(&bytes).map_err(|e| Error::format(path, format!("array '{name}': {e}")))
}

fn read_ply_points(path: &Path) -> Result<Vec<[f32; 3]>> {
    let ply = ply::read_ply(path)?;
    let vertex = ply
        .element("vertex")
        .ok_or_else(|| Error::format(path, "there is no 'vertex' element"))?;
    let [Some(x), Some(y), Some(z)] = ["x", "y", "z"].map(|c| vertex.scalar(c)) else {
        return Err(Error::format(
            path,
            "the vertices need scalar properties x, y and z",
        ));
    };
    let points: Vec<[f32; 3]> = (0..vertex.count)
        .map(|k| [x[k] as f32, y[k] as f32, z[k] as f32])
        .collect();
    if let Some(k) = points.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
        return Err(Error::format(
            path,
            format!("vertex {k} {:?} is not finite", points[k]),
        ));
    }
    Ok(points)
}

/// The points of a text file, one per line that `coordinates` keeps (returning its coordinates' text).
fn read_xyz(path: &Path, coordinates: impl Fn(&str) -> Option<&str>) -> Result<Vec<[f32; 3]>> {
    let text = crate::input::read_text_capped(path).map_err(|e| Error::read(path, e))?;
    let mut points = Vec::new();
    for (k, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let Some(line) = coordinates(line) else {
            continue;
        };
        let bad = |reason: String| Error::format(path, format!("line {}: {reason}", k + 1));
        let mut point = [0.0f32; 3];
        let mut words = line
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|w| !w.is_empty());
        for (axis, c) in point.iter_mut().enumerate() {
            let word = words
                .next()
                .ok_or_else(|| bad(format!("expected 3 numbers (x y z), found {axis}")))?;
            *c = word
                .parse()
                .map_err(|_| bad(format!("'{word}' is not a number")))?;
            if !c.is_finite() {
                return Err(bad(format!("coordinate '{word}' is not finite")));
            }
        }
        points.push(point);
    }
    Ok(points)
}

/// The points moved so that their mean is at the origin, and that mean (computed in double
/// precision). No points give no points and a zero mean.
pub fn mean_center(points: &[[f32; 3]]) -> (Vec<[f32; 3]>, [f32; 3]) {
    if points.is_empty() {
        return (Vec::new(), [0.0; 3]);
    }
    let mut sum = [0.0f64; 3];
    for p in points {
        for (s, c) in sum.iter_mut().zip(p) {
            *s += f64::from(*c);
        }
    }
    let mean = sum.map(|s| (s / points.len() as f64) as f32);
    let centered = points
        .iter()
        .map(|p| [p[0] - mean[0], p[1] - mean[1], p[2] - mean[2]])
        .collect();
    (centered, mean)
}

/// The frame a fit sees a point cloud in: each point p as (p − center)·scale.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PointFrame {
    /// The input point at the frame's origin.
    pub center: [f32; 3],
    /// How much the frame magnifies the input's units.
    pub scale: f32,
}

impl PointFrame {
    /// The points moved so that their mean is at the origin, unscaled (see [`mean_center`]).
    pub fn mean_centered(points: &[[f32; 3]]) -> PointFrame {
        PointFrame {
            center: mean_center(points).1,
            scale: 1.0,
        }
    }

    /// The center of the points' bounding box at the origin and the farthest point at distance 1: the
    /// cloud inside the unit sphere, whatever its units. An error when the points are all at one place.
    pub fn unit_sphere(points: &[[f32; 3]]) -> Result<PointFrame> {
        let (lo, hi) = bounding_box(points).ok_or_else(|| Error::Invalid("no points to normalize".into()))?;
        let center: [f32; 3] = std::array::from_fn(|k| 0.5 * (lo[k] + hi[k]));
        let radius = points
            .iter()
            .map(|p| (0..3).map(|k| f64::from(p[k] - center[k]).powi(2)).sum::<f64>())
            .fold(0.0f64, f64::max)
            .sqrt();
        let scale = (1.0 / radius) as f32;
        if !(scale.is_finite() && scale > 0.0) {
            return Err(Error::Invalid(format!(
                "the points span {radius:e} about {center:?}: too little to scale into the unit sphere"
            )));
        }
        Ok(PointFrame { center, scale })
    }

    /// `p` in this frame.
    pub fn to_frame(&self, p: [f32; 3]) -> [f32; 3] {
        std::array::from_fn(|k| (p[k] - self.center[k]) * self.scale)
    }

    /// `q` (in this frame) in the input's units.
    pub fn to_input(&self, q: [f32; 3]) -> [f32; 3] {
        std::array::from_fn(|k| q[k] / self.scale + self.center[k])
    }
}

/// The axis-aligned box spanned by `points`: (min, max) per axis, `None` if there are none.
pub fn bounding_box(points: &[[f32; 3]]) -> Option<([f32; 3], [f32; 3])> {
    let first = Vec3::from(*points.first()?);
    let (min, max) = points.iter().fold((first, first), |(lo, hi), &p| {
        (lo.min(Vec3::from(p)), hi.max(Vec3::from(p)))
    });
    Some((min.into(), max.into()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::npy::tests::{npy_bytes, npy_f32};
    use std::io::Write;
    use std::path::PathBuf;
    use zip::write::SimpleFileOptions;
    use zip::CompressionMethod;

    fn temp_path(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("nerfjit-points-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    fn points() -> Vec<[f32; 3]> {
        (0..50)
            .map(|k| {
                let t = k as f32 * 0.37;
                [t.cos(), t.sin(), 0.02 * k as f32 - 0.5]
            })
            .collect()
    }

    /// Writes a `.npz` of `(name, npy bytes)` entries with `method`.
    fn write_npz(path: &Path, entries: &[(&str, Vec<u8>)], method: CompressionMethod) {
        let mut zip = zip::ZipWriter::new(std::fs::File::create(path).unwrap());
        for (name, bytes) in entries {
            let options = SimpleFileOptions::default().compression_method(method);
            zip.start_file(format!("{name}.npy"), options).unwrap();
            zip.write_all(bytes).unwrap();
        }
        zip.finish().unwrap();
    }

    #[test]
    fn npz_stored_and_deflated() {
        let points = points();
        let other = npy_f32(&[[9.0; 3]]);
        for (name, method) in [
            ("stored.npz", CompressionMethod::Stored),
            ("deflated.npz", CompressionMethod::Deflated),
        ] {
            let path = temp_path(name);
            write_npz(
                &path,
                &[("verts", npy_f32(&points)), ("extra", other.clone())],
                method,
            );
            assert_eq!(read_points(&path, Some("verts")).unwrap(), points);
            assert_eq!(read_points(&path, Some("extra.npy")).unwrap(), vec![[9.0; 3]]);
            let e = read_points(&path, Some("normals")).unwrap_err().to_string();
            assert!(
                e.contains("no array 'normals'; its arrays are: verts, extra"),
                "{e}"
            );
            let e = read_points(&path, None).unwrap_err().to_string();
            assert!(e.contains("pass the key"), "{e}");
        }
        let path = temp_path("single.npz");
        write_npz(&path, &[("pts", npy_f32(&points))], CompressionMethod::Deflated);
        assert_eq!(read_points(&path, None).unwrap(), points);
        let path = temp_path("ints.npz");
        let ints = npy_bytes(
            "{'descr': '<i8', 'fortran_order': False, 'shape': (1, 3), }",
            &[0; 24],
        );
        write_npz(&path, &[("verts", ints)], CompressionMethod::Stored);
        let e = read_points(&path, Some("verts")).unwrap_err().to_string();
        assert!(e.starts_with(&path.display().to_string()), "{e}");
        assert!(e.contains("array 'verts': dtype is '<i8'"), "{e}");
        let path = temp_path("notzip.npz");
        std::fs::write(&path, b"hello").unwrap();
        assert!(read_points(&path, None)
            .unwrap_err()
            .to_string()
            .contains("not a .npz"));
    }

    #[test]
    fn npy_ply_and_xyz_files() {
        let points = points();
        let path = temp_path("p.npy");
        std::fs::write(&path, npy_f32(&points)).unwrap();
        assert_eq!(read_points(&path, None).unwrap(), points);

        let mesh = crate::surfaces::mesh::Mesh::from_triangles(points.clone(), vec![[0, 1, 2]]);
        let path = temp_path("p.ply");
        mesh.write_ply(&path).unwrap();
        assert_eq!(read_points(&path, None).unwrap(), points);
        let path = temp_path("ascii.PLY");
        std::fs::write(
            &path,
            "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n\
             property float z\nproperty uchar red\nend_header\n1 2 3 255\n4 5 6 0\n",
        )
        .unwrap();
        assert_eq!(
            read_points(&path, None).unwrap(),
            vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
        );

        let path = temp_path("p.xyz");
        let mut text = String::from("# x y z\n\n");
        for p in &points {
            text += &format!("{} {}\t{}  0 0 1\n", p[0], p[1], p[2]);
        }
        std::fs::write(&path, text).unwrap();
        assert_eq!(read_points(&path, None).unwrap(), points);
        let path = temp_path("comma.txt");
        std::fs::write(&path, "1,2,3\n-1e-3, 5, 6.5\n").unwrap();
        assert_eq!(
            read_points(&path, None).unwrap(),
            vec![[1.0, 2.0, 3.0], [-1e-3, 5.0, 6.5]]
        );

        // An OBJ's vertices; its normals, texture coordinates, faces and comments are not points.
        let path = temp_path("mesh.obj");
        std::fs::write(
            &path,
            "# exported\no scan\nv 1 2 3\nvn 0 0 1\nvt 0.5 0.5\nv\t4 5 6 0.2 0.3 0.4\nf 1 2 1\n",
        )
        .unwrap();
        assert_eq!(
            read_points(&path, None).unwrap(),
            vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
        );
    }

    proptest::proptest! {
        /// A cloud in any units and place lies inside the unit sphere in its frame, touching it, and
        /// comes back where it was.
        #[test]
        fn unit_sphere_frames_hold_any_cloud(
            points in proptest::collection::vec(proptest::array::uniform3(-1.0f32..1.0), 2..40),
            units in -3.0f32..4.0,
            offset in proptest::array::uniform3(-1000.0f32..1000.0),
        ) {
            let scale = 10f32.powf(units);
            let cloud: Vec<[f32; 3]> = points
                .iter()
                .map(|p| std::array::from_fn(|k| p[k] * scale + offset[k]))
                .collect();
            proptest::prop_assume!(cloud.iter().any(|p| (0..3).any(|k| p[k] != cloud[0][k])));
            let frame = PointFrame::unit_sphere(&cloud).unwrap();
            let radii: Vec<f32> = cloud
                .iter()
                .map(|&p| frame.to_frame(p).iter().map(|c| c * c).sum::<f32>().sqrt())
                .collect();
            proptest::prop_assert!(radii.iter().all(|&r| r <= 1.0 + 1e-4), "{radii:?}");
            proptest::prop_assert!(radii.iter().any(|&r| r >= 1.0 - 1e-4), "{radii:?}");
            for &p in &cloud {
                let back = frame.to_input(frame.to_frame(p));
                let tolerance = 1e-5 * (scale + offset.iter().map(|c| c.abs()).fold(0.0, f32::max));
                proptest::prop_assert!((0..3).all(|k| (back[k] - p[k]).abs() <= tolerance), "{p:?} {back:?}");
            }
        }
    }

    #[test]
    fn clouds_at_one_place_have_no_unit_sphere_frame() {
        let e = PointFrame::unit_sphere(&[[3.0, 4.0, 5.0]; 4])
            .unwrap_err()
            .to_string();
        assert!(e.contains("too little to scale"), "{e}");
        assert!(PointFrame::unit_sphere(&[]).is_err());
        let mean = PointFrame::mean_centered(&[[1.0, 2.0, 3.0], [3.0, 2.0, -1.0]]);
        assert_eq!(
            mean,
            PointFrame {
                center: [2.0, 2.0, 1.0],
                scale: 1.0
            }
        );
    }

    #[test]
    fn bad_point_files_name_the_file_and_problem() {
        let cases = [
            (
                "short.xyz",
                "1 2 3\n4 5\n",
                "line 2: expected 3 numbers (x y z), found 2",
            ),
            (
                "word.xyz",
                "1 2 3\n\n4 five 6\n",
                "line 3: 'five' is not a number",
            ),
            ("inf.xyz", "1 2 inf\n", "line 1: coordinate 'inf' is not finite"),
            ("empty.xyz", "# nothing\n", "the file has no points"),
            (
                "pts.off",
                "OFF\n1 0 0\n1 2 3\n",
                "unknown point cloud format '.off'",
            ),
            ("faces.obj", "f 1 2 3\n", "the file has no points"),
            (
                "short.obj",
                "v 1 2 3\nv 4 5\n",
                "line 2: expected 3 numbers (x y z), found 2",
            ),
        ];
        for (name, text, message) in cases {
            let path = temp_path(name);
            std::fs::write(&path, text).unwrap();
            let e = read_points(&path, None).unwrap_err().to_string();
            assert!(
                e.starts_with(&path.display().to_string()) && e.contains(message),
                "{name}: {e}"
            );
        }
        let path = temp_path("key.xyz");
        std::fs::write(&path, "1 2 3\n").unwrap();
        let e = read_points(&path, Some("verts")).unwrap_err().to_string();
        assert!(e.contains("only applies to .npz"), "{e}");
        let e = read_points(Path::new("/nonexistent/p.npz"), None)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("cannot read /nonexistent/p.npz"), "{e}");
    }

    #[test]
    fn centering_and_bounds() {
        let (centered, mean) = mean_center(&[[1.0, 2.0, 3.0], [3.0, 2.0, -1.0]]);
        assert_eq!(mean, [2.0, 2.0, 1.0]);
        assert_eq!(centered, vec![[-1.0, 0.0, 2.0], [1.0, 0.0, -2.0]]);
        assert_eq!(mean_center(&[]), (vec![], [0.0; 3]));
        let b = bounding_box(&[[1.0, 2.0, 3.0], [3.0, -2.0, -1.0], [0.0, 0.0, 0.0]]);
        assert_eq!(b, Some(([0.0, -2.0, -1.0], [3.0, 2.0, 3.0])));
        assert_eq!(bounding_box(&[]), None);
    }

    #[test]
    fn course_bunny_reads_when_present() {
        let path = Path::new("/work/shared/data/assignment3/bunny_pointcloud.npz");
        if !path.exists() {
            eprintln!("note: {} not found, skipping", path.display());
            return;
        }
        let points = read_points(path, Some("verts")).unwrap();
        assert_eq!(points.len(), 10_000);
        assert_eq!(read_points(path, None).unwrap(), points);
        let (lo, hi) = bounding_box(&points).unwrap();
        let diagonal = (0..3).map(|a| (hi[a] - lo[a]).powi(2)).sum::<f32>().sqrt();
        assert!(diagonal > 0.1 && diagonal < 100.0, "diagonal {diagonal}");
        let (centered, _) = mean_center(&points);
        let mean: f64 = centered
            .iter()
            .map(|p| f64::from(p[0] + p[1] + p[2]))
            .sum::<f64>()
            / 1e4;
        assert!(mean.abs() < 1e-4, "{mean}");
    }
}
