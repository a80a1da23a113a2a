//! Triangle meshes: [`Mesh`], its PLY, OBJ and STL files, and checks of its shape and topology.

use std::fmt::Write as _;
use std::path::Path;

use glam::Vec3;

use crate::data::ply;
use crate::data::pointcloud::bounding_box;
use crate::error::{check_output_folder, Error, Result};

/// An indexed triangle mesh with one normal per vertex.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Mesh {
    /// Vertex positions.
    pub vertices: Vec<[f32; 3]>,
    /// Unit normals, one per vertex.
    pub normals: Vec<[f32; 3]>,
    /// Triangles as indices into `vertices`, counter-clockwise seen from outside: the normal
    /// `(b − a) × (c − a)` points outwards.
    pub triangles: Vec<[u32; 3]>,
    /// RGB in [0, 1], one per vertex, or none at all (empty).
    pub colors: Vec<[f32; 3]>,
}

/// The vertices of triangle `t`, or `None` if one of its indices is out of range.
fn corners(vertices: &[[f32; 3]], t: [u32; 3]) -> Option<[Vec3; 3]> {
    let v = |i: u32| vertices.get(i as usize).map(|&p| Vec3::from(p));
    Some([v(t[0])?, v(t[1])?, v(t[2])?])
}

impl Mesh {
    /// A mesh with area-weighted vertex normals computed from its triangles (zero for vertices
    /// no triangle uses). Triangles with out-of-range indices are left out of the normals
    /// (and make [`Mesh::check`] fail).
    pub fn from_triangles(vertices: Vec<[f32; 3]>, triangles: Vec<[u32; 3]>) -> Mesh {
        let mut sums = vec![Vec3::ZERO; vertices.len()];
        for &t in &triangles {
            if let Some([a, b, c]) = corners(&vertices, t) {
                // |(b − a) × (c − a)| is twice the area: the weights are proportional to area.
                let n = (b - a).cross(c - a);
                for i in t {
                    sums[i as usize] += n;
                }
            }
        }
        let normals = sums.iter().map(|n| n.normalize_or_zero().into()).collect();
        Mesh {
            vertices,
            normals,
            triangles,
            colors: Vec::new(),
        }
    }

    /// Checks that the mesh is usable: one normal per vertex, no colors or one per vertex (in [0, 1]),
    /// finite coordinates, and triangle indices in range.
    pub fn check(&self) -> Result<()> {
        if self.normals.len() != self.vertices.len() {
            return Err(Error::Invalid(format!(
                "the mesh has {} vertices but {} normals",
                self.vertices.len(),
                self.normals.len()
            )));
        }
        if !self.colors.is_empty() && self.colors.len() != self.vertices.len() {
            return Err(Error::Invalid(format!(
                "the mesh has {} vertices but {} colors",
                self.vertices.len(),
                self.colors.len()
            )));
        }
        if let Some(k) = self
            .colors
            .iter()
            .position(|c| !c.iter().all(|x| (0.0..=1.0).contains(x)))
        {
            return Err(Error::Invalid(format!(
                "mesh vertex {k} has the color {:?}, outside [0, 1]",
                self.colors[k]
            )));
        }
        let not_finite = |list: &[[f32; 3]]| list.iter().position(|p| !Vec3::from(*p).is_finite());
        if let Some(k) = not_finite(&self.vertices).or(not_finite(&self.normals)) {
            return Err(Error::Invalid(format!(
                "mesh vertex {k} has a non-finite position {:?} or normal {:?}",
                self.vertices[k], self.normals[k]
            )));
        }
        let n = self.vertices.len();
        if let Some((k, t)) = self
            .triangles
            .iter()
            .enumerate()
            .find(|(_, t)| t.iter().any(|&i| i as usize >= n))
        {
            return Err(Error::Invalid(format!(
                "mesh triangle {k} {t:?} refers to a vertex past the last one ({n} vertices)"
            )));
        }
        Ok(())
    }

    /// The box spanned by the vertices: (min, max) per axis, `None` for a mesh without
    /// vertices.
    pub fn bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        bounding_box(&self.vertices)
    }

    /// Sorted directed edges `(a << 32) | b` of all triangles.
    fn directed_edges(&self) -> Vec<u64> {
        let mut edges: Vec<u64> = self
            .triangles
            .iter()
            .flat_map(|&[a, b, c]| [(a, b), (b, c), (c, a)])
            .map(|(a, b)| (u64::from(a) << 32) | u64::from(b))
            .collect();
        edges.sort_unstable();
        edges
    }

    /// Whether the surface is closed and consistently oriented: every edge is shared by
    /// exactly two triangles that traverse it in opposite directions. A mesh without
    /// triangles, or with a triangle that repeats a vertex, is not closed.
    pub fn is_closed(&self) -> bool {
        if self.triangles.is_empty() || self.triangles.iter().any(|&[a, b, c]| a == b || b == c || c == a) {
            return false;
        }
        // Each directed edge once (not twice in the same direction) and its reverse present.
        let edges = self.directed_edges();
        let unique = edges.windows(2).all(|w| w[0] != w[1]);
        unique
            && edges
                .iter()
                .all(|&e| edges.binary_search(&e.rotate_right(32)).is_ok())
    }

    /// The Euler characteristic V − E + F, counting the vertices that triangles use and each
    /// undirected edge once: 2 for a closed surface of genus 0, 0 for a torus.
    pub fn euler_characteristic(&self) -> i64 {
        let mut used: Vec<u32> = self.triangles.iter().flatten().copied().collect();
        used.sort_unstable();
        used.dedup();
        let mut edges: Vec<u64> = self
            .directed_edges()
            .into_iter()
            .map(|e| {
                let (a, b) = (e >> 32, e & 0xffff_ffff);
                (a.min(b) << 32) | a.max(b)
            })
            .collect();
        edges.sort_unstable();
        edges.dedup();
        used.len() as i64 - edges.len() as i64 + self.triangles.len() as i64
    }

    /// The signed volume enclosed by the triangles (divergence theorem: Σ a·(b × c) / 6),
    /// positive for a closed mesh whose triangles face outwards. Triangles with out-of-range
    /// indices are skipped.
    pub fn volume(&self) -> f64 {
        let sum: f64 = self
            .triangles
            .iter()
            .filter_map(|&t| corners(&self.vertices, t))
            .map(|[a, b, c]| a.as_dvec3().dot(b.as_dvec3().cross(c.as_dvec3())))
            .sum();
        sum / 6.0
    }

    /// Turns the triangles and normals to face out of the volume they enclose: reverses the triangles'
    /// order of corners and the normals when the signed volume is negative, as it is for the level set of
    /// a density, whose triangles face towards increasing values (inwards).
    pub fn face_outwards(&mut self) {
        if self.volume() < 0.0 {
            for t in &mut self.triangles {
                t.swap(1, 2);
            }
            for n in &mut self.normals {
                *n = n.map(|x| -x);
            }
        }
    }

    /// Writes the mesh as a binary little-endian PLY file: vertices with `x y z nx ny nz`
    /// (float) and faces as `vertex_indices` lists (uchar count, int indices).
    pub fn write_ply(&self, path: &Path) -> Result<()> {
        self.check()?;
        if self.vertices.len() > i32::MAX as usize {
            return Err(Error::write(path, "too many vertices for int PLY indices"));
        }
        let colored = !self.colors.is_empty();
        let header = format!(
            "ply\nformat binary_little_endian 1.0\ncomment written by nerfjit\n\
             element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
             property float nx\nproperty float ny\nproperty float nz\n{}\
             element face {}\nproperty list uchar int vertex_indices\nend_header\n",
            self.vertices.len(),
            if colored {
                "property uchar red\nproperty uchar green\nproperty uchar blue\n"
            } else {
                ""
            },
            self.triangles.len()
        );
        let mut bytes = header.into_bytes();
        bytes.reserve(self.vertices.len() * 27 + self.triangles.len() * 13);
        for (k, (p, n)) in self.vertices.iter().zip(&self.normals).enumerate() {
            for c in p.iter().chain(n) {
                bytes.extend_from_slice(&c.to_le_bytes());
            }
            if colored {
                bytes.extend(self.colors[k].map(|c| (c * 255.0).round() as u8));
            }
        }
        for t in &self.triangles {
            bytes.push(3);
            for &i in t {
                bytes.extend_from_slice(&(i as i32).to_le_bytes());
            }
        }
        check_output_folder(path)?;
        crate::whole_file::write_whole(path, &bytes)
    }

    /// Writes the mesh as a Wavefront OBJ file with `v`, `vn` and `f v//vn` lines; numbers are
    /// written with enough digits to read back exactly.
    pub fn write_obj(&self, path: &Path) -> Result<()> {
        self.check()?;
        let mut text = String::with_capacity(40 * (2 * self.vertices.len() + self.triangles.len()));
        let _ = writeln!(
            text,
            "# nerfjit mesh: {} vertices, {} triangles",
            self.vertices.len(),
            self.triangles.len()
        );
        for (k, [x, y, z]) in self.vertices.iter().enumerate() {
            // Vertex colors as three more numbers after the position (read by trimesh, MeshLab, Blender).
            match self.colors.get(k) {
                Some([r, g, b]) => {
                    let _ = writeln!(text, "v {x} {y} {z} {r} {g} {b}");
                }
                None => {
                    let _ = writeln!(text, "v {x} {y} {z}");
                }
            }
        }
        for [x, y, z] in &self.normals {
            let _ = writeln!(text, "vn {x} {y} {z}");
        }
        for t in &self.triangles {
            let [a, b, c] = t.map(|i| u64::from(i) + 1);
            let _ = writeln!(text, "f {a}//{a} {b}//{b} {c}//{c}");
        }
        check_output_folder(path)?;
        crate::whole_file::write_whole(path, text.as_bytes())
    }

    /// Writes the mesh as binary STL (triangles with their facet normals; STL has no vertex colors).
    pub fn write_stl(&self, path: &Path) -> Result<()> {
        self.check()?;
        let count = u32::try_from(self.triangles.len())
            .map_err(|_| Error::write(path, "too many triangles for STL"))?;
        let mut bytes = Vec::with_capacity(84 + 50 * self.triangles.len());
        // 80 bytes that must not start with "solid" (the text format's first word).
        let mut header = [b' '; 80];
        let title = b"binary STL written by nerfjit";
        header[..title.len()].copy_from_slice(title);
        bytes.extend_from_slice(&header);
        bytes.extend_from_slice(&count.to_le_bytes());
        for &t in &self.triangles {
            let [a, b, c] = corners(&self.vertices, t).expect("checked indices");
            let normal = (b - a).cross(c - a).normalize_or_zero();
            for v in [normal, a, b, c] {
                for x in v.to_array() {
                    bytes.extend_from_slice(&x.to_le_bytes());
                }
            }
            bytes.extend_from_slice(&0u16.to_le_bytes());
        }
        check_output_folder(path)?;
        crate::whole_file::write_whole(path, &bytes)
    }

    /// Reads a PLY mesh (ASCII or binary little-endian): vertex `x y z`, normals from
    /// `nx ny nz` when present (else computed as in [`Mesh::from_triangles`]), and faces from
    /// `vertex_indices` (or `vertex_index`) lists, polygons split into triangle fans. A file
    /// without faces gives a mesh without triangles.
    pub fn read_ply(path: &Path) -> Result<Mesh> {
        let ply = ply::read_ply(path)?;
        let bad = |reason: String| Error::format(path, reason);
        let vertex = ply
            .element("vertex")
            .ok_or_else(|| bad("there is no 'vertex' element".into()))?;
        let columns = |names: [&str; 3]| names.map(|name| vertex.scalar(name));
        let [Some(x), Some(y), Some(z)] = columns(["x", "y", "z"]) else {
            return Err(bad("the vertices need scalar properties x, y and z".into()));
        };
        let vertices: Vec<[f32; 3]> = (0..vertex.count)
            .map(|k| [x[k] as f32, y[k] as f32, z[k] as f32])
            .collect();
        if let Some(k) = vertices.iter().position(|p| !Vec3::from(*p).is_finite()) {
            return Err(bad(format!("vertex {k} {:?} is not finite", vertices[k])));
        }
        let mut triangles = Vec::new();
        if let Some(face) = ply.element("face") {
            let (starts, items) = face
                .list("vertex_indices")
                .or_else(|| face.list("vertex_index"))
                .ok_or_else(|| bad("the faces have no 'vertex_indices' list".into()))?;
            for (k, range) in starts.windows(2).enumerate() {
                let polygon = &items[range[0]..range[1]];
                let index = |i: f64| {
                    let ok = i >= 0.0 && i.fract() == 0.0 && (i as usize) < vertices.len();
                    ok.then_some(i as u32).ok_or_else(|| {
                        bad(format!(
                            "face {k} refers to vertex {i}, but there are {} vertices",
                            vertices.len()
                        ))
                    })
                };
                if polygon.len() < 3 {
                    return Err(bad(format!(
                        "face {k} has {} vertices, fewer than 3",
                        polygon.len()
                    )));
                }
                let first = index(polygon[0])?;
                for pair in polygon[1..].windows(2) {
                    triangles.push([first, index(pair[0])?, index(pair[1])?]);
                }
            }
        }
        let mut mesh = match columns(["nx", "ny", "nz"]) {
            [Some(nx), Some(ny), Some(nz)] => {
                let normals: Vec<[f32; 3]> = (0..vertex.count)
                    .map(|k| [nx[k] as f32, ny[k] as f32, nz[k] as f32])
                    .collect();
                if let Some(k) = normals.iter().position(|n| !Vec3::from(*n).is_finite()) {
                    return Err(bad(format!("normal {k} {:?} is not finite", normals[k])));
                }
                Mesh {
                    vertices,
                    normals,
                    triangles,
                    colors: Vec::new(),
                }
            }
            _ => Mesh::from_triangles(vertices, triangles),
        };
        // Vertex colors as 8-bit channels, the form PLY writers use.
        if let [Some(r), Some(g), Some(b)] = columns(["red", "green", "blue"]) {
            mesh.colors = (0..vertex.count)
                .map(|k| [r[k], g[k], b[k]].map(|c| (c / 255.0).clamp(0.0, 1.0) as f32))
                .collect();
        }
        Ok(mesh)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    fn temp_path(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("nerfjit-mesh-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    /// A unit cube [0, 1]³ as 12 outward triangles.
    fn cube() -> Mesh {
        let vertices = (0..8)
            .map(|c| [(c & 1) as f32, ((c >> 1) & 1) as f32, ((c >> 2) & 1) as f32])
            .collect();
        let quads = [
            [0, 2, 3, 1], // z = 0, normal −z
            [4, 5, 7, 6], // z = 1
            [0, 1, 5, 4], // y = 0
            [2, 6, 7, 3], // y = 1
            [0, 4, 6, 2], // x = 0
            [1, 3, 7, 5], // x = 1
        ];
        let triangles = quads
            .iter()
            .flat_map(|&[a, b, c, d]| [[a, b, c], [a, c, d]])
            .collect();
        Mesh::from_triangles(vertices, triangles)
    }

    #[test]
    fn cube_is_closed_with_unit_volume_and_outward_normals() {
        let mesh = cube();
        mesh.check().unwrap();
        assert!(mesh.is_closed());
        assert_eq!(mesh.euler_characteristic(), 2);
        assert!((mesh.volume() - 1.0).abs() < 1e-12, "{}", mesh.volume());
        assert_eq!(mesh.bounds(), Some(([0.0; 3], [1.0; 3])));
        for (p, n) in mesh.vertices.iter().zip(&mesh.normals) {
            let outward = Vec3::from(*p) - Vec3::splat(0.5);
            assert!(Vec3::from(*n).dot(outward) > 0.0, "{p:?} {n:?}");
            assert!((Vec3::from(*n).length() - 1.0).abs() < 1e-6);
        }
        // Flipping one triangle, or dropping one, opens the surface.
        let mut flipped = mesh.clone();
        flipped.triangles[3].swap(0, 1);
        assert!(!flipped.is_closed());
        let mut open = mesh.clone();
        open.triangles.pop();
        assert!(!open.is_closed());
        assert!(!Mesh::default().is_closed());
        // Turned inside out, it is turned back.
        let mut inside_out = mesh.clone();
        for t in &mut inside_out.triangles {
            t.swap(0, 1);
        }
        inside_out.normals.iter_mut().for_each(|n| *n = n.map(|x| -x));
        assert!(inside_out.volume() < 0.0);
        inside_out.face_outwards();
        assert!((inside_out.volume() - 1.0).abs() < 1e-12 && inside_out.is_closed());
        assert_eq!(inside_out.normals, mesh.normals);
        let mut same = mesh.clone();
        same.face_outwards();
        assert_eq!(same, mesh);
        assert_eq!(Mesh::default().bounds(), None);
    }

    #[test]
    fn ply_and_obj_round_trip() {
        let mut mesh = cube();
        mesh.vertices[3] = [0.1, -1e-7, 123.456];
        let path = temp_path("cube.ply");
        mesh.write_ply(&path).unwrap();
        assert_eq!(Mesh::read_ply(&path).unwrap(), mesh);

        let path = temp_path("cube.obj");
        mesh.write_obj(&path).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let numbers = |prefix: &str| -> Vec<[f32; 3]> {
            text.lines()
                .filter_map(|l| l.strip_prefix(prefix))
                .map(|l| {
                    let v: Vec<f32> = l.split_whitespace().map(|w| w.parse().unwrap()).collect();
                    [v[0], v[1], v[2]]
                })
                .collect()
        };
        assert_eq!(numbers("v "), mesh.vertices);
        assert_eq!(numbers("vn "), mesh.normals);
        let faces: Vec<[u32; 3]> = text
            .lines()
            .filter_map(|l| l.strip_prefix("f "))
            .map(|l| {
                let v: Vec<u32> = l
                    .split_whitespace()
                    .map(|w| {
                        let (a, b) = w.split_once("//").unwrap();
                        assert_eq!(a, b);
                        a.parse::<u32>().unwrap() - 1
                    })
                    .collect();
                [v[0], v[1], v[2]]
            })
            .collect();
        assert_eq!(faces, mesh.triangles);
    }

    #[test]
    fn vertex_colors_round_trip_through_ply_and_reach_obj() {
        let mut mesh = cube();
        mesh.colors = (0..8)
            .map(|k| [k as f32 / 7.0, 0.5, 1.0 - k as f32 / 7.0])
            .collect();
        let path = temp_path("colored.ply");
        mesh.write_ply(&path).unwrap();
        let back = Mesh::read_ply(&path).unwrap();
        assert_eq!(back.vertices, mesh.vertices);
        for (a, b) in back.colors.iter().zip(&mesh.colors) {
            assert!(
                (0..3).all(|c| (a[c] - b[c]).abs() <= 0.5 / 255.0 + 1e-6),
                "{a:?} vs {b:?}"
            );
        }
        let path = temp_path("colored.obj");
        mesh.write_obj(&path).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let first = text.lines().find(|l| l.starts_with("v ")).unwrap();
        assert_eq!(first, "v 0 0 0 0 0.5 1");
        mesh.colors[2] = [1.5, 0.0, 0.0];
        assert!(mesh
            .write_ply(&path)
            .unwrap_err()
            .to_string()
            .contains("outside [0, 1]"));
        mesh.colors.pop();
        assert!(mesh
            .check()
            .unwrap_err()
            .to_string()
            .contains("8 vertices but 7 colors"));
    }

    #[test]
    fn stl_holds_every_triangle_with_its_facet_normal() {
        let mesh = cube();
        let path = temp_path("cube.stl");
        mesh.write_stl(&path).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert!(!bytes.starts_with(b"solid"));
        assert_eq!(u32::from_le_bytes(bytes[80..84].try_into().unwrap()), 12);
        assert_eq!(bytes.len(), 84 + 12 * 50);
        let float = |at: usize| f32::from_le_bytes(bytes[at..at + 4].try_into().unwrap());
        for (k, &t) in mesh.triangles.iter().enumerate() {
            let at = 84 + 50 * k;
            let [a, b, c] = corners(&mesh.vertices, t).unwrap();
            let normal = (b - a).cross(c - a).normalize();
            assert_eq!([float(at), float(at + 4), float(at + 8)], normal.to_array());
            assert_eq!([float(at + 12), float(at + 16), float(at + 20)], a.to_array());
            assert_eq!([float(at + 36), float(at + 40), float(at + 44)], c.to_array());
        }
    }

    #[test]
    fn ascii_ply_with_quads_and_no_normals() {
        let text = "ply\nformat ascii 1.0\nelement vertex 4\nproperty double x\nproperty double y\n\
                    property double z\nelement face 1\nproperty list uchar uint vertex_index\nend_header\n\
                    0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n";
        let path = temp_path("quad.ply");
        std::fs::write(&path, text).unwrap();
        let mesh = Mesh::read_ply(&path).unwrap();
        assert_eq!(mesh.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        assert!(mesh.normals.iter().all(|n| *n == [0.0, 0.0, 1.0]));
        assert_eq!(mesh.bounds(), Some(([0.0; 3], [1.0, 1.0, 0.0])));
    }

    #[test]
    fn bad_meshes_and_files_are_errors() {
        let mut mesh = cube();
        mesh.triangles.push([0, 1, 8]);
        let e = mesh.check().unwrap_err().to_string();
        assert!(e.contains("triangle 12"), "{e}");
        assert!(mesh.write_ply(&temp_path("bad.ply")).is_err());
        let mut mesh = cube();
        mesh.normals.pop();
        assert!(mesh
            .check()
            .unwrap_err()
            .to_string()
            .contains("8 vertices but 7 normals"));
        let e = cube().write_obj(Path::new("no-such-folder/a.obj")).unwrap_err();
        assert!(e.to_string().contains("folder 'no-such-folder' does not exist"));

        let head =
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n";
        let cases = [
            ("noface.ply", format!("{head}element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n"), "face 0 refers to vertex 3, but there are 3 vertices"),
            ("line.ply", format!("{head}element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n2 0 1\n"), "face 0 has 2 vertices"),
            ("noz.ply", "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n0 0\n".to_string(), "need scalar properties x, y and z"),
            ("nan.ply", format!("{head}end_header\n0 0 0\nnan 0 0\n0 1 0\n"), "vertex 1 [NaN, 0.0, 0.0] is not finite"),
        ];
        for (name, text, message) in cases {
            let path = temp_path(name);
            std::fs::write(&path, text).unwrap();
            let e = Mesh::read_ply(&path).unwrap_err().to_string();
            assert!(
                e.starts_with(&path.display().to_string()) && e.contains(message),
                "{name}: {e}"
            );
        }
    }
}
