//! A bounding volume hierarchy for nearest-primitive queries (triangles or points), used by
//! the mesh distance metrics.

use glam::Vec3;

/// Primitives per leaf, at most.
const LEAF_SIZE: usize = 4;

/// A node's box, and either its children (`count == 0`: children `first` and `first + 1`) or
/// its primitives (`order[first..first + count]`).
#[derive(Debug, Clone, Copy)]
struct Node {
    min: Vec3,
    max: Vec3,
    first: u32,
    count: u32,
}

impl Node {
    /// Squared distance from `p` to the node's box (0 inside).
    fn distance2(&self, p: Vec3) -> f32 {
        let d = (self.min - p).max(p - self.max).max(Vec3::ZERO);
        d.length_squared()
    }
}

/// A binary tree of boxes over primitives, split at the median along the longest axis.
#[derive(Debug, Clone)]
pub(crate) struct Bvh {
    nodes: Vec<Node>,
    /// Primitive indices in leaf order.
    order: Vec<u32>,
}

/// Splitting halves the primitives, so depth (and the traversal stack) stays below 64.
const MAX_DEPTH: usize = 64;

impl Bvh {
    /// A hierarchy over primitives with boxes `boxes[i] = (min, max)`.
    pub(crate) fn new(boxes: &[(Vec3, Vec3)]) -> Bvh {
        let mut bvh = Bvh {
            nodes: Vec::with_capacity(2 * boxes.len().div_ceil(LEAF_SIZE)),
            order: (0..boxes.len() as u32).collect(),
        };
        let centers: Vec<Vec3> = boxes.iter().map(|(lo, hi)| 0.5 * (*lo + *hi)).collect();
        bvh.nodes.push(Node {
            min: Vec3::ZERO,
            max: Vec3::ZERO,
            first: 0,
            count: 0,
        });
        bvh.build(0, 0, boxes.len(), boxes, &centers);
        bvh
    }

    /// Makes node `index` cover primitives `order[start..end]`.
    fn build(&mut self, index: usize, start: usize, end: usize, boxes: &[(Vec3, Vec3)], centers: &[Vec3]) {
        let items = &mut self.order[start..end];
        let (mut min, mut max) = (Vec3::INFINITY, Vec3::NEG_INFINITY);
        let (mut cmin, mut cmax) = (Vec3::INFINITY, Vec3::NEG_INFINITY);
        for &i in items.iter() {
            let (lo, hi) = boxes[i as usize];
            (min, max) = (min.min(lo), max.max(hi));
            (cmin, cmax) = (cmin.min(centers[i as usize]), cmax.max(centers[i as usize]));
        }
        if items.len() <= LEAF_SIZE {
            self.nodes[index] = Node {
                min,
                max,
                first: start as u32,
                count: items.len() as u32,
            };
            return;
        }
        let extent = cmax - cmin;
        let axis = if extent.x >= extent.y && extent.x >= extent.z {
            0
        } else if extent.y >= extent.z {
            1
        } else {
            2
        };
        let mid = items.len() / 2;
        items.select_nth_unstable_by(mid, |&a, &b| {
            centers[a as usize][axis].total_cmp(&centers[b as usize][axis])
        });
        let left = self.nodes.len();
        let child = Node {
            min: Vec3::ZERO,
            max: Vec3::ZERO,
            first: 0,
            count: 0,
        };
        self.nodes.extend([child, child]);
        self.nodes[index] = Node {
            min,
            max,
            first: left as u32,
            count: 0,
        };
        self.build(left, start, start + mid, boxes, centers);
        self.build(left + 1, start + mid, end, boxes, centers);
    }

    /// The primitive nearest to `p` and its squared distance, given `distance2(i)`, the squared
    /// distance from `p` to primitive `i` (which must be within its box). `None` without
    /// primitives.
    pub(crate) fn nearest(&self, p: Vec3, mut distance2: impl FnMut(u32) -> f32) -> Option<(u32, f32)> {
        let mut best: Option<(u32, f32)> = None;
        let mut stack = [0u32; MAX_DEPTH + 1];
        let mut len = usize::from(!self.order.is_empty());
        while len > 0 {
            len -= 1;
            let node = self.nodes[stack[len] as usize];
            if best.is_some_and(|(_, d)| node.distance2(p) >= d) {
                continue;
            }
            if node.count > 0 {
                let items = &self.order[node.first as usize..(node.first + node.count) as usize];
                for &i in items {
                    let d = distance2(i);
                    if best.is_none_or(|(_, b)| d < b) {
                        best = Some((i, d));
                    }
                }
            } else {
                // Visit the nearer child first: push it last.
                let (a, b) = (node.first, node.first + 1);
                let (da, db) = (
                    self.nodes[a as usize].distance2(p),
                    self.nodes[b as usize].distance2(p),
                );
                let (near, far) = if da <= db { (a, b) } else { (b, a) };
                stack[len] = far;
                stack[len + 1] = near;
                len += 2;
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn nearest_point_matches_brute_force() {
        let mut rng = Rng::new(7);
        let mut random = || Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
        let points: Vec<Vec3> = (0..1000).map(|_| random()).collect();
        let bvh = Bvh::new(&points.iter().map(|&p| (p, p)).collect::<Vec<_>>());
        for _ in 0..200 {
            // Queries inside and far outside the cloud.
            let q = 3.0 * random() - Vec3::ONE;
            let (i, d) = bvh
                .nearest(q, |i| points[i as usize].distance_squared(q))
                .unwrap();
            let brute = points
                .iter()
                .map(|p| p.distance_squared(q))
                .fold(f32::INFINITY, f32::min);
            assert_eq!(d, brute);
            assert_eq!(points[i as usize].distance_squared(q), d);
        }
        // Identical points (no usable split axis) and no points at all.
        let same = vec![(Vec3::ONE, Vec3::ONE); 100];
        let bvh = Bvh::new(&same);
        assert_eq!(bvh.nearest(Vec3::ZERO, |_| 3.0).map(|(_, d)| d), Some(3.0));
        assert!(Bvh::new(&[]).nearest(Vec3::ZERO, |_| 0.0).is_none());
    }
}
