//! The lights a job adds to its scene from the job spec (`JobSpec.lighting`): a sun
//! and an environment map; and how many samples of each light the integrators take
//! (`JobSpec.light_samples`, [`crate::light_samples`]). They live in the render settings
//! rather than the scene, so a worker that holds no triangle (the step that shades rays
//! leaving the scene) sees them too, and a scene package is the same file whatever
//! lights a job puts around it.

use std::sync::Arc;

use crate::env_map::EnvMap;
use crate::light_samples::LightSamples;
use crate::sun::Sun;

/// The spec's lights, ready to sample, and how many samples of each light a hit takes.
/// The default is no lights and one sample: a scene without them pays nothing (the
/// integrators test one `Option`, behind the effect).
#[derive(Clone, Debug, Default)]
pub struct Lighting {
    pub sun: Option<Sun>,
    /// Replaces the constant environment; shared, as a map can be large.
    pub env_map: Option<Arc<EnvMap>>,
    /// Samples per hit of each light that is not a delta light, the scene's emitters
    /// included (`--light-samples`). Here rather than in `RenderSettings` itself because
    /// it travels with the lights: every place that resolves a job's lights from its
    /// spec resolves it too.
    pub samples: LightSamples,
}

impl Lighting {
    /// Whether the spec adds any light (then, as for a scene with lights, the default
    /// environment is black).
    pub fn any(&self) -> bool {
        self.sun.is_some() || self.env_map.is_some()
    }
}
