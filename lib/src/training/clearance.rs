//! The clearance of a point-cloud fit (`clearance_weight` in `train sdf`): how far the surface must keep
//! from a uniform point, so that it lies only where the cloud has points. A point's clearance is its
//! distance to the nearest cloud point less a margin of twice the cloud's spacing (the median distance
//! between neighbouring points, within which the true surface passes between them): no surface lies
//! closer to it than that, so |d| ≥ clearance holds for the true signed distance d. Where the point is
//! known to lie outside the surface — in space reached from the edge of the fit's box through cells no
//! cloud point comes near, a flood fill on a coarse grid — the sign is known too: d ≥ clearance. The
//! unsigned form removes surfaces away from the points; the signed one also the solid blobs a fit grows
//! between parts of a scan (its pre-training sphere's inside, never carved away), whose inside satisfies
//! the unsigned form.

use std::collections::VecDeque;

use nerfjit_runtime::PointIndex;

/// Cells per axis of the flood fill's grid.
const OUTSIDE_RESOLUTION: usize = 64;

/// Cloud points whose nearest neighbours measure the cloud's spacing.
const SPACING_SAMPLE: usize = 2000;

/// A cloud indexed for clearances, with the space known to be outside it.
pub struct Clearance {
    index: PointIndex,
    /// Twice the cloud's spacing.
    margin: f32,
    /// The fit's box, [−bound, bound]³.
    bound: f32,
    /// Per cell of the flood fill's grid (x fastest), whether it is known to be outside.
    outside: Vec<bool>,
}

impl Clearance {
    /// Indexes `cloud` (not empty) and floods the cells of [−bound, bound]³ that no point comes near.
    pub fn new(cloud: &[[f32; 3]], bound: f32) -> Clearance {
        let index = PointIndex::new(cloud);
        let margin = 2.0 * index.spacing(SPACING_SAMPLE);
        let n = OUTSIDE_RESOLUTION;
        let cell = 2.0 * bound / n as f32;
        let centers: Vec<[f32; 3]> = (0..n * n * n)
            .map(|i| [i % n, i / n % n, i / (n * n)].map(|k| -bound + (k as f32 + 0.5) * cell))
            .collect();
        // A cell is free when every point of it is farther than the margin from the cloud, and one cell
        // more: the flood then stays out of a scan's holes up to about four cells across (the bunny's
        // base), which the unsigned form still covers.
        let reach = margin + (0.5 * 3f32.sqrt() + 1.0) * cell;
        let free: Vec<bool> = index.distances(&centers).iter().map(|&d| d > reach).collect();
        Clearance {
            outside: flood_from_the_edge(&free, n),
            index,
            margin,
            bound,
        }
    }

    /// The margin: twice the cloud's spacing.
    pub fn margin(&self) -> f32 {
        self.margin
    }

    /// The share of the fit's box known to be outside.
    pub fn outside_share(&self) -> f32 {
        self.outside.iter().filter(|&&o| o).count() as f32 / self.outside.len() as f32
    }

    /// For each point, its clearance and whether it is known to be outside (1) or not (0), as the
    /// clearance kernel's fourth and fifth inputs.
    pub fn targets(&self, points: &[[f32; 3]]) -> (Vec<f32>, Vec<f32>) {
        let clearances = self
            .index
            .distances(points)
            .iter()
            .map(|d| (d - self.margin).max(0.0))
            .collect();
        let outside = points
            .iter()
            .map(|&p| if self.is_outside(p) { 1.0 } else { 0.0 })
            .collect();
        (clearances, outside)
    }

    fn is_outside(&self, p: [f32; 3]) -> bool {
        let n = OUTSIDE_RESOLUTION;
        let cell = p.map(|x| ((x + self.bound) / (2.0 * self.bound) * n as f32).floor());
        if cell.iter().any(|&c| !(0.0..n as f32).contains(&c)) {
            return true; // beyond the box: past every point of the fit
        }
        let [x, y, z] = cell.map(|c| c as usize);
        self.outside[x + n * (y + n * z)]
    }
}

/// The free cells of an n³ grid (x fastest) reached from its boundary's free cells through the free cells
/// beside them (6-neighbours).
fn flood_from_the_edge(free: &[bool], n: usize) -> Vec<bool> {
    let mut reached = vec![false; free.len()];
    let mut queue = VecDeque::new();
    let on_edge = |k: usize| k == 0 || k == n - 1;
    for (i, &f) in free.iter().enumerate() {
        if f && (on_edge(i % n) || on_edge(i / n % n) || on_edge(i / (n * n))) {
            reached[i] = true;
            queue.push_back(i);
        }
    }
    while let Some(i) = queue.pop_front() {
        let (x, y, z) = (i % n, i / n % n, i / (n * n));
        let neighbours = [
            (x > 0).then(|| i - 1),
            (x + 1 < n).then(|| i + 1),
            (y > 0).then(|| i - n),
            (y + 1 < n).then(|| i + n),
            (z > 0).then(|| i - n * n),
            (z + 1 < n).then(|| i + n * n),
        ];
        for j in neighbours.into_iter().flatten() {
            if free[j] && !reached[j] {
                reached[j] = true;
                queue.push_back(j);
            }
        }
    }
    reached
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `count` random points on the sphere of `radius` about `center` (Gaussian directions).
    fn sphere(center: [f32; 3], radius: f32, count: usize) -> Vec<[f32; 3]> {
        let mut rng = nerfjit_runtime::Rng::new(7);
        (0..count)
            .map(|_| {
                let d = [rng.normal(), rng.normal(), rng.normal()];
                let length = d.iter().map(|x| x * x).sum::<f32>().sqrt();
                [0, 1, 2].map(|k| center[k] + radius * d[k] / length)
            })
            .collect()
    }

    #[test]
    fn the_space_between_two_hollow_balls_is_outside_and_their_insides_are_not() {
        let mut cloud = sphere([-0.5, 0.0, 0.0], 0.3, 4000);
        cloud.extend(sphere([0.5, 0.0, 0.0], 0.3, 4000));
        let c = Clearance::new(&cloud, 1.0);
        assert!(c.margin() > 0.0 && c.margin() < 0.05, "margin {}", c.margin());
        let probes = [
            ([0.0, 0.0, 0.0], true),   // between the balls
            ([0.0, 0.9, 0.0], true),   // above them
            ([-0.5, 0.0, 0.0], false), // the first ball's centre
            ([0.5, 0.05, 0.0], false), // the second's
            ([-0.8, 0.0, 0.0], false), // on the first ball's surface
            ([3.0, 0.0, 0.0], true),   // beyond the box
        ];
        let points: Vec<[f32; 3]> = probes.iter().map(|&(p, _)| p).collect();
        let (clearances, outside) = c.targets(&points);
        for ((p, want), o) in probes.iter().zip(&outside) {
            assert_eq!(*o == 1.0, *want, "{p:?}");
        }
        // The clearance is the distance to the nearest point less the margin: 0.2 less it between the
        // balls, 0.3 less it at a centre, 0 on a surface.
        assert!(
            (clearances[0] - (0.2 - c.margin())).abs() < 0.01,
            "{clearances:?}"
        );
        assert!(
            (clearances[2] - (0.3 - c.margin())).abs() < 0.01,
            "{clearances:?}"
        );
        assert_eq!(clearances[4], 0.0);
        let share = c.outside_share();
        assert!(share > 0.9 && share < 0.99, "outside {share}");
    }

    #[test]
    fn a_closed_grid_boundary_keeps_the_flood_out() {
        // A 4³ grid whose only free cells are the inner 2³: none touches the edge, none is reached.
        let n = 4;
        let free: Vec<bool> = (0..n * n * n)
            .map(|i| [i % n, i / n % n, i / (n * n)].iter().all(|&k| k == 1 || k == 2))
            .collect();
        assert!(flood_from_the_edge(&free, n).iter().all(|&r| !r));
        // Open one edge cell next to them: all 9 are reached.
        let mut open = free.clone();
        open[1 + n] = true; // (1, 1, 0)
        assert_eq!(flood_from_the_edge(&open, n).iter().filter(|&&r| r).count(), 9);
    }
}
