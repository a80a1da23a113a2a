//! The case table of marching cubes, generated rather than written out: for each of a cell's 256 sign
//! cases, the triangles (as cube edges) of the loops its faces' contour segments join into. See the
//! parent module's docs for how the segments are chosen.

use std::sync::OnceLock;

use glam::Vec3;

/// The cube's edges as corner pairs; corner `c` is at offset `(c & 1, c >> 1 & 1, c >> 2 & 1)`.
/// Edges 0–3 run along x, 4–7 along y and 8–11 along z; edge `4·axis + k` starts at the
/// corner whose offsets along the other two axes are the bits of `k`, lower axis first.
pub(super) const EDGES: [[usize; 2]; 12] = [
    [0, 1],
    [2, 3],
    [4, 5],
    [6, 7],
    [0, 2],
    [1, 3],
    [4, 6],
    [5, 7],
    [0, 4],
    [1, 5],
    [2, 6],
    [3, 7],
];

pub(super) fn corner_position(c: usize) -> Vec3 {
    Vec3::new((c & 1) as f32, (c >> 1 & 1) as f32, (c >> 2 & 1) as f32)
}

pub(super) fn edge_midpoint(e: usize) -> Vec3 {
    let [a, b] = EDGES[e];
    0.5 * (corner_position(a) + corner_position(b))
}

/// The edge between neighbouring corners `a` and `b`.
pub(super) fn edge_between(a: usize, b: usize) -> usize {
    let axis = (a ^ b).trailing_zeros() as usize;
    let low = a.min(b);
    let k = match axis {
        0 => low >> 1,
        1 => (low & 1) | (low >> 2) << 1,
        _ => low & 3,
    };
    4 * axis + k
}

/// Whether edges `e1` and `e2` lie on a common face of the cube.
pub(super) fn share_face(e1: usize, e2: usize) -> bool {
    let corners = [EDGES[e1][0], EDGES[e1][1], EDGES[e2][0], EDGES[e2][1]];
    (0..3).any(|axis| corners.iter().all(|c| c >> axis & 1 == corners[0] >> axis & 1))
}

/// The faces of the cube: outward normal and corners in cyclic order.
pub(super) fn faces() -> impl Iterator<Item = (Vec3, [usize; 4])> {
    (0..3).flat_map(|axis| {
        (0..2).map(move |side| {
            let (u, v) = (1 << ((axis + 1) % 3), 1 << ((axis + 2) % 3));
            let base = side << axis;
            let mut normal = Vec3::ZERO;
            normal[axis] = if side == 1 { 1.0 } else { -1.0 };
            (normal, [base, base | u, base | u | v, base | v])
        })
    })
}

/// The directed contour segments on the faces of case `case` (bit `c` set when corner `c` is
/// at or above the level): `next[e]` is the edge the contour goes to from edge `e`.
pub(super) fn contour(case: u8) -> [Option<usize>; 12] {
    let above = |c: usize| case >> c & 1 == 1;
    let mut next = [None; 12];
    for (normal, q) in faces() {
        let face_edge = |k: usize| edge_between(q[k], q[(k + 1) % 4]);
        let crossed: Vec<usize> = (0..4).filter(|&k| above(q[k]) != above(q[(k + 1) % 4])).collect();
        let segments: Vec<(usize, usize)> = if crossed.len() == 2 {
            vec![(face_edge(crossed[0]), face_edge(crossed[1]))]
        } else {
            // Ambiguous (or uncrossed) face: cut off each corner below the level.
            (0..4)
                .filter(|&k| crossed.len() == 4 && !above(q[k]))
                .map(|k| (face_edge((k + 3) % 4), face_edge(k)))
                .collect()
        };
        for (a, b) in segments {
            let (ma, mb) = (edge_midpoint(a), edge_midpoint(b));
            let (left, mid) = (normal.cross(mb - ma), 0.5 * (ma + mb));
            // A corner the segment cuts off (the one its edges share), or any corner if it
            // splits the face in halves, tells which way round it goes.
            let cut = EDGES[a].iter().find(|c| EDGES[b].contains(c)).copied();
            let corner = cut.unwrap_or(q[0]);
            let forward = (left.dot(corner_position(corner) - mid) > 0.0) == above(corner);
            let (from, to) = if forward { (a, b) } else { (b, a) };
            next[from] = Some(to);
        }
    }
    next
}

/// Triangles of the loop `polygon` (in its cyclic order), with no diagonal joining two edges
/// of one face; `None` if there is no such triangulation.
pub(super) fn triangulate(polygon: &[usize]) -> Option<Vec<[usize; 3]>> {
    let k = polygon.len();
    match k {
        0..=2 => return None,
        3 => return Some(vec![[polygon[0], polygon[1], polygon[2]]]),
        _ => {}
    }
    for i in 0..k {
        let (prev, cut, next) = (polygon[(i + k - 1) % k], polygon[i], polygon[(i + 1) % k]);
        if share_face(prev, next) {
            continue;
        }
        let rest: Vec<usize> = polygon.iter().copied().filter(|&e| e != cut).collect();
        if let Some(mut triangles) = triangulate(&rest) {
            triangles.push([prev, cut, next]);
            return Some(triangles);
        }
    }
    None
}

/// The triangles of case `case`, as cube edges.
pub(super) fn case_triangles(case: u8) -> Vec<[usize; 3]> {
    let next = contour(case);
    let mut visited = [false; 12];
    let mut triangles = Vec::new();
    for start in 0..12 {
        let mut polygon = Vec::new();
        let mut e = start;
        while let (false, Some(to)) = (visited[e], next[e]) {
            visited[e] = true;
            polygon.push(e);
            e = to;
        }
        if !polygon.is_empty() {
            // Every loop has a triangulation (checked for all cases by the tests).
            triangles.extend(triangulate(&polygon).unwrap_or_default());
        }
    }
    triangles
}

/// The triangles of all 256 cases.
pub(super) struct Table {
    /// Case `k` has triangles `triangles[start[k]..start[k + 1]]`.
    pub(super) start: [usize; 257],
    /// Triangles as cube edges.
    pub(super) triangles: Vec<[u8; 3]>,
}

pub(super) fn table() -> &'static Table {
    static TABLE: OnceLock<Table> = OnceLock::new();
    TABLE.get_or_init(|| {
        let mut start = [0; 257];
        let mut triangles = Vec::new();
        for case in 0..=255u8 {
            let case_tris = case_triangles(case);
            triangles.extend(case_tris.iter().map(|t| t.map(|e| e as u8)));
            start[case as usize + 1] = triangles.len();
        }
        Table { start, triangles }
    })
}
