//! The image a surface renderer produces: color, depth, normal and hit per pixel.

/// A rendered image with its per-pixel geometry, all in row-major pixel order.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Shaded color (background where missed).
    pub rgb: Vec<[f32; 3]>,
    /// Ray parameter `t` of the hit, i.e. the distance from the camera along the unit ray
    /// (`f32::INFINITY` where missed).
    pub depth: Vec<f32>,
    /// Unit surface normal (zero where missed or unknown).
    pub normal: Vec<[f32; 3]>,
    /// Whether the ray hit the surface.
    pub hit: Vec<bool>,
}

impl Frame {
    /// A 0×0 frame, to be filled by [`crate::sphere_trace_into`].
    pub fn empty() -> Frame {
        Frame {
            width: 0,
            height: 0,
            rgb: Vec::new(),
            depth: Vec::new(),
            normal: Vec::new(),
            hit: Vec::new(),
        }
    }
}
