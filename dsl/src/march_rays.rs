//! The rays a fused sphere tracer marches: the one ray layout shared by the JIT, which compiles the
//! tracer of an SDF, and the runtime, which calls it (both build on this crate).

/// The rays to march, in structure-of-arrays layout: origin, unit direction and interval of each ray.
#[derive(Debug, Clone, Copy)]
pub struct MarchRays<'a> {
    /// Origins x, y, z.
    pub origin: [&'a [f32]; 3],
    /// Unit directions x, y, z.
    pub direction: [&'a [f32]; 3],
    /// Where each ray starts marching.
    pub t0: &'a [f32],
    /// Past which each ray misses.
    pub t1: &'a [f32],
}
