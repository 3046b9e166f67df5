//! The lights a job adds to its scene from the job spec (`JobSpec.lighting`): a sun
//! today. They live in the render settings rather than the scene, so a worker that
//! holds no triangle (the step that shades rays leaving the scene) sees them too, and a
//! scene package is the same file whatever lights a job puts around it.

use crate::sun::Sun;

/// The spec's lights, ready to sample. The default is none: a scene without them pays
/// nothing (the integrators test one `Option`, behind the effect).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Lighting {
    pub sun: Option<Sun>,
}

impl Lighting {
    /// Whether the spec adds any light (then, as for a scene with lights, the default
    /// environment is black).
    pub fn any(&self) -> bool {
        self.sun.is_some()
    }
}
