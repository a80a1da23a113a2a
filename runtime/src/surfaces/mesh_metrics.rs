//! Distances between point clouds and meshes: exact point-to-triangle distances found through
//! a bounding volume hierarchy, and the two-way report of the course's mesh quality figure.

use glam::Vec3;
use rayon::prelude::*;

use crate::data::pointcloud::bounding_box;
use crate::error::{Error, Result};
use crate::surfaces::bvh::Bvh;
use crate::surfaces::mesh::Mesh;

/// Squared distance from `p` to the segment from `a` to `b` (a point if `a == b`).
fn segment_distance2(p: Vec3, a: Vec3, b: Vec3) -> f32 {
    let ab = b - a;
    let len2 = ab.length_squared();
    let t = if len2 > 0.0 {
        ((p - a).dot(ab) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    p.distance_squared(a + t * ab)
}

/// Squared distance from `p` to the triangle `abc` (solid, including its inside): to the
/// plane if `p` projects inside the triangle, else to the nearest of its edges. Degenerate
/// triangles are their edges.
fn triangle_distance2(p: Vec3, [a, b, c]: [Vec3; 3]) -> f32 {
    let n = (b - a).cross(c - a);
    let n2 = n.length_squared();
    if n2 > 0.0 {
        // p projects inside iff it is on the inner side of all three edges.
        let inside = [(a, b), (b, c), (c, a)]
            .iter()
            .all(|&(u, v)| (v - u).cross(p - u).dot(n) >= 0.0);
        if inside {
            let h = (p - a).dot(n);
            return h * h / n2;
        }
    }
    segment_distance2(p, a, b)
        .min(segment_distance2(p, b, c))
        .min(segment_distance2(p, c, a))
}

/// Checks that points are usable for distances.
fn check_points(points: &[[f32; 3]]) -> Result<()> {
    if points.is_empty() {
        return Err(Error::Invalid("distances need at least one point".into()));
    }
    if let Some(k) = points.iter().position(|p| !Vec3::from(*p).is_finite()) {
        return Err(Error::Invalid(format!("point {k} {:?} is not finite", points[k])));
    }
    Ok(())
}

/// The triangles of `mesh` as corner positions, after checking the mesh.
fn triangles_of(mesh: &Mesh) -> Result<Vec<[Vec3; 3]>> {
    mesh.check()?;
    if mesh.triangles.is_empty() {
        return Err(Error::Invalid(
            "the mesh has no triangles to measure distances to".into(),
        ));
    }
    Ok(mesh
        .triangles
        .iter()
        .map(|t| t.map(|i| Vec3::from(mesh.vertices[i as usize])))
        .collect())
}

/// The distance from each point to the nearest point of the mesh's surface (its triangles,
/// inside included), exact up to float rounding. Uses a bounding volume hierarchy and all
/// threads: 10,000 points against 100,000 triangles take tens of milliseconds.
pub fn point_to_mesh_distances(points: &[[f32; 3]], mesh: &Mesh) -> Result<Vec<f32>> {
    check_points(points)?;
    let triangles = triangles_of(mesh)?;
    let boxes: Vec<(Vec3, Vec3)> = triangles
        .iter()
        .map(|&[a, b, c]| (a.min(b).min(c), a.max(b).max(c)))
        .collect();
    let bvh = Bvh::new(&boxes);
    Ok(points
        .par_iter()
        .map(|&p| {
            let p = Vec3::from(p);
            let nearest = bvh.nearest(p, |i| triangle_distance2(p, triangles[i as usize]));
            nearest.map_or(f32::INFINITY, |(_, d2)| d2.sqrt())
        })
        .collect())
}

/// The distance from each of `queries` to the nearest of `points` (not empty).
fn nearest_point_distances(queries: &[[f32; 3]], points: &[[f32; 3]]) -> Vec<f32> {
    PointIndex::new(points).distances(queries)
}

/// A point cloud indexed for nearest-point queries (a bounding volume hierarchy over its points).
pub struct PointIndex {
    points: Vec<Vec3>,
    bvh: Bvh,
}

impl PointIndex {
    /// Indexes `points`.
    pub fn new(points: &[[f32; 3]]) -> PointIndex {
        let points: Vec<Vec3> = points.iter().map(|&p| Vec3::from(p)).collect();
        let boxes: Vec<(Vec3, Vec3)> = points.iter().map(|&p| (p, p)).collect();
        PointIndex {
            bvh: Bvh::new(&boxes),
            points,
        }
    }

    /// The distance from each of `queries` to the nearest point (infinite without points), on all
    /// threads.
    pub fn distances(&self, queries: &[[f32; 3]]) -> Vec<f32> {
        queries
            .par_iter()
            .map(|&q| self.nearest_distance(Vec3::from(q), None))
            .collect()
    }

    /// The median distance from a point of the cloud to its nearest other point, over at most `sample`
    /// points spread evenly through the cloud: how far apart its points lie (0 for fewer than two).
    pub fn spacing(&self, sample: usize) -> f32 {
        if self.points.len() < 2 || sample == 0 {
            return 0.0;
        }
        let stride = self.points.len().div_ceil(sample);
        let mut gaps: Vec<f32> = (0..self.points.len())
            .step_by(stride)
            .collect::<Vec<_>>()
            .par_iter()
            .map(|&i| self.nearest_distance(self.points[i], Some(i)))
            .collect();
        gaps.sort_by(f32::total_cmp);
        gaps[gaps.len() / 2]
    }

    fn nearest_distance(&self, q: Vec3, skip: Option<usize>) -> f32 {
        let nearest = self.bvh.nearest(q, |i| match Some(i as usize) == skip {
            true => f32::INFINITY,
            false => self.points[i as usize].distance_squared(q),
        });
        nearest.map_or(f32::INFINITY, |(_, d2)| d2.sqrt())
    }
}

/// How far a mesh is from a point cloud, both ways.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChamferReport {
    /// Mean distance from the points to the mesh's surface.
    pub mean_points_to_mesh: f32,
    /// Largest distance from a point to the mesh's surface.
    pub max_points_to_mesh: f32,
    /// Mean distance from the mesh's vertices to their nearest point.
    pub mean_mesh_to_points: f32,
    /// Largest distance from a mesh vertex to its nearest point.
    pub max_mesh_to_points: f32,
    /// Diagonal of the points' bounding box, the scale to express the others as fractions of.
    pub bbox_diagonal: f32,
}

fn mean_and_max(distances: &[f32]) -> (f32, f32) {
    let sum: f64 = distances.iter().map(|&d| f64::from(d)).sum();
    let max = distances.iter().copied().fold(0.0, f32::max);
    ((sum / distances.len() as f64) as f32, max)
}

/// The distances between `points` (e.g. the bunny's) and `mesh` both ways: from the points
/// to the mesh's surface ([`point_to_mesh_distances`]) and from the mesh's vertices to the
/// nearest point, with the diagonal of the points' bounding box for scale.
pub fn chamfer_report(points: &[[f32; 3]], mesh: &Mesh) -> Result<ChamferReport> {
    let to_mesh = point_to_mesh_distances(points, mesh)?;
    let to_points = nearest_point_distances(&mesh.vertices, points);
    let (mean_points_to_mesh, max_points_to_mesh) = mean_and_max(&to_mesh);
    let (mean_mesh_to_points, max_mesh_to_points) = mean_and_max(&to_points);
    let bbox_diagonal = bounding_box(points).map_or(0.0, |(lo, hi)| Vec3::from(hi).distance(Vec3::from(lo)));
    Ok(ChamferReport {
        mean_points_to_mesh,
        max_points_to_mesh,
        mean_mesh_to_points,
        max_mesh_to_points,
        bbox_diagonal,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::ClosureFn;
    use crate::rng::Rng;
    use crate::surfaces::marching::extract;

    #[test]
    fn triangle_distance_in_every_region() {
        let t = [Vec3::ZERO, Vec3::X, Vec3::Y];
        let cases = [
            (Vec3::new(0.2, 0.3, 2.0), 4.0),   // above the inside
            (Vec3::new(0.2, 0.3, -0.5), 0.25), // below the inside
            (Vec3::new(-1.0, -1.0, 0.0), 2.0), // beyond vertex a
            (Vec3::new(2.0, 0.0, 1.0), 2.0),   // beyond vertex b
            (Vec3::new(0.5, -2.0, 0.0), 4.0),  // beyond edge ab
            (Vec3::new(1.0, 1.0, 0.0), 0.5),   // beyond edge bc
            (Vec3::new(-0.5, 0.5, 1.0), 1.25), // beyond edge ca, off the plane
        ];
        for (p, expected) in cases {
            let d = triangle_distance2(p, t);
            assert!((d - expected).abs() < 1e-6, "{p}: {d} vs {expected}");
            // Either winding.
            assert!((triangle_distance2(p, [t[0], t[2], t[1]]) - expected).abs() < 1e-6);
        }
        // Degenerate triangles: a segment and a point.
        let segment = [Vec3::ZERO, Vec3::X, Vec3::X * 0.5];
        assert!((triangle_distance2(Vec3::new(0.5, 2.0, 0.0), segment) - 4.0).abs() < 1e-6);
        assert_eq!(triangle_distance2(Vec3::Z, [Vec3::ZERO; 3]), 1.0);
    }

    #[test]
    fn triangle_distance_is_the_minimum_over_the_triangle() {
        let mut rng = Rng::new(3);
        let mut random = || Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0 - Vec3::ONE;
        for _ in 0..100 {
            let t = [random(), random(), random()];
            let p = random() * 1.5;
            let d = triangle_distance2(p, t).sqrt();
            // Dense barycentric samples are never closer, and some come within the spacing.
            let mut sampled = f32::INFINITY;
            let steps = 60;
            for i in 0..=steps {
                for j in 0..=steps - i {
                    let (u, v) = (i as f32 / steps as f32, j as f32 / steps as f32);
                    let q = t[0] + u * (t[1] - t[0]) + v * (t[2] - t[0]);
                    sampled = sampled.min(p.distance(q));
                }
            }
            assert!(d <= sampled + 1e-5, "{d} > {sampled}");
            assert!(sampled - d < 0.1, "{d} vs {sampled}");
        }
    }

    fn unit_sphere_mesh() -> Mesh {
        let sdf = ClosureFn::new(3, 1, |p, out| {
            out[0] = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 1.0
        });
        extract(&sdf, None, ([-1.2; 3], [1.2; 3]), 64, 0.0).unwrap()
    }

    /// `n` points spread evenly over the sphere of `radius` (a Fibonacci spiral).
    fn sphere_points(n: usize, radius: f32) -> Vec<[f32; 3]> {
        let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
        (0..n)
            .map(|k| {
                let z = 1.0 - 2.0 * (k as f32 + 0.5) / n as f32;
                let r = (1.0 - z * z).sqrt();
                let a = golden * k as f32;
                [radius * r * a.cos(), radius * r * a.sin(), radius * z]
            })
            .collect()
    }

    #[test]
    fn distances_to_a_sphere_mesh() {
        let mesh = unit_sphere_mesh();
        // Cell size h = 2.4/64: vertices lie within h²/(8(1 − h)) inside the sphere, and a point
        // of a triangle, a convex combination of vertices at most D = √3·h apart, lies at most
        // about D²/6 = h²/2 further in: 0.0009 in all.
        let on = point_to_mesh_distances(&sphere_points(2000, 1.0), &mesh).unwrap();
        let max = on.iter().copied().fold(0.0, f32::max);
        assert!(max < 0.002, "max {max}");
        for radius in [1.1, 0.9] {
            let off = point_to_mesh_distances(&sphere_points(2000, radius), &mesh).unwrap();
            for d in off {
                assert!((d - 0.1).abs() < 0.002, "radius {radius}: {d}");
            }
        }
        // The hierarchy finds exactly the brute-force minimum, also far from the mesh.
        let triangles = triangles_of(&mesh).unwrap();
        let mut rng = Rng::new(11);
        let queries: Vec<[f32; 3]> = (0..100)
            .map(|_| [0.0; 3].map(|_: f32| 6.0 * rng.next_f32() - 3.0))
            .collect();
        let fast = point_to_mesh_distances(&queries, &mesh).unwrap();
        for (q, d) in queries.iter().zip(fast) {
            let p = Vec3::from(*q);
            let brute = triangles
                .iter()
                .map(|&t| triangle_distance2(p, t))
                .fold(f32::INFINITY, f32::min);
            assert_eq!(d, brute.sqrt());
        }
    }

    #[test]
    fn chamfer_report_both_ways() {
        let mesh = unit_sphere_mesh();
        // The mesh's own vertices: zero both ways.
        let report = chamfer_report(&mesh.vertices, &mesh).unwrap();
        assert!(report.max_points_to_mesh < 1e-6, "{report:?}");
        assert_eq!(
            (report.mean_mesh_to_points, report.max_mesh_to_points),
            (0.0, 0.0)
        );
        // A sphere of radius 1.1 around the unit-sphere mesh.
        let points = sphere_points(5000, 1.1);
        let report = chamfer_report(&points, &mesh).unwrap();
        assert!((report.mean_points_to_mesh - 0.1).abs() < 0.002, "{report:?}");
        assert!((report.max_points_to_mesh - 0.1).abs() < 0.002, "{report:?}");
        // Mesh vertices are 0.1 below the points, plus at most half their spacing (~0.055).
        assert!(
            report.mean_mesh_to_points > 0.1 && report.max_mesh_to_points < 0.13,
            "{report:?}"
        );
        assert!(report.mean_mesh_to_points <= report.max_mesh_to_points);
        assert!(
            (report.bbox_diagonal - 2.2 * 3f32.sqrt()).abs() < 0.01,
            "{report:?}"
        );
    }

    #[test]
    fn bad_inputs_are_errors() {
        let mesh = unit_sphere_mesh();
        assert!(point_to_mesh_distances(&[], &mesh).is_err());
        let e = point_to_mesh_distances(&[[f32::NAN, 0.0, 0.0]], &mesh).unwrap_err();
        assert!(e.to_string().contains("point 0"), "{e}");
        let e = point_to_mesh_distances(&[[0.0; 3]], &Mesh::default()).unwrap_err();
        assert!(e.to_string().contains("no triangles"), "{e}");
        let mut broken = mesh.clone();
        broken.triangles[0][1] = u32::MAX;
        assert!(chamfer_report(&[[0.0; 3]], &broken).is_err());
    }
}
