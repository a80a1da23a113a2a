//! Fused sphere tracing: a native loop that marches whole rays through an SDF, offered by compiled
//! SDFs (see [`crate::BatchFn::as_marcher`]) and used by the sphere tracer in place of its step-by-step loop.

pub use nerfjit_dsl::march_rays::MarchRays;

/// Sphere traces rays in one call, with exactly the per-ray semantics of [`crate::surfaces::sphere_trace`]: from
/// `t = t0`, up to `max_steps` times, `p = o + t·d`, `dist = sdf(p)`; a hit when `dist < eps`, else
/// `t += dist` and a miss once `t > t1`.
pub trait RayMarcher: Sync {
    /// Marches rays `0..n`; writes the final `t` of each ray and 1.0 where it hit, 0.0 where it missed.
    fn march(&self, n: usize, rays: &MarchRays, eps: f32, max_steps: u32, t: &mut [f32], hit: &mut [f32]);
}
