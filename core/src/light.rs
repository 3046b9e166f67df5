//! Punctual lights (`KHR_lights_punctual`).
//!
//! Units follow the extension: point and spot intensity in candela, directional in lux;
//! dray treats them as radiometric (W/sr and W/m²) with no photometric conversion, which
//! is what a reference path tracer comparing on the same numbers expects.

use glam::Vec3;

/// The most punctual lights a scene may have (loaders refuse more): every hit sends a
/// shadow ray to each, and the credit of the deepest ray trees a job accepts is sized for
/// this many (`Integrator::credit_needed`).
pub const MAX_PUNCTUAL_LIGHTS: u32 = 1 << 16;

#[derive(Clone, Debug, PartialEq)]
pub enum Light {
    Point {
        position: Vec3,
        /// Colour times intensity.
        intensity: Vec3,
    },
    Spot {
        position: Vec3,
        /// Unit direction the spot points to.
        direction: Vec3,
        intensity: Vec3,
        inner_cone: f32,
        outer_cone: f32,
    },
    Directional {
        /// Unit direction the light travels in (glTF: the node's -Z).
        direction: Vec3,
        /// Colour times illuminance.
        irradiance: Vec3,
    },
}

impl Light {
    /// A rough power measure used to pick lights in proportion to their strength.
    pub fn power_weight(&self, scene_radius: f32) -> f32 {
        let lum = |c: Vec3| c.x * 0.2126 + c.y * 0.7152 + c.z * 0.0722;
        match self {
            Light::Point { intensity, .. } => 4.0 * std::f32::consts::PI * lum(*intensity),
            Light::Spot {
                intensity,
                outer_cone,
                ..
            } => 2.0 * std::f32::consts::PI * (1.0 - outer_cone.cos()).max(1e-3) * lum(*intensity),
            Light::Directional { irradiance, .. } => {
                std::f32::consts::PI * scene_radius * scene_radius * lum(*irradiance)
            }
        }
    }
}
