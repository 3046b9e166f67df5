//! The Lambert lobe of the base, `(1-metallic) (1-transmission) base / pi`, attenuated by
//! what the layers above it (dielectric, clear coat, sheen) pass down on the way in and
//! out, and sampled by cosine-weighted hemisphere directions.

use glam::{Vec2, Vec3};
use std::f32::consts::{FRAC_1_PI, TAU};

use super::at::BsdfAt;
use super::{BsdfSample, COS_EPS, Lobe};

/// The diffuse lobe's tint, `base (1-metallic) (1-transmission)`.
#[derive(Clone, Copy, Debug)]
pub(super) struct Diffuse {
    pub(super) tint: Vec3,
}

impl BsdfAt<'_> {
    /// The diffuse value and density at `wi` (local cosine `cos_i`), under a base scale
    /// (the dielectric's transmittance in and out) and the layers' attenuation `att`.
    pub(super) fn diffuse_eval(&self, base_scale: f32, att: f32, cos_i: f32) -> (Vec3, f32) {
        (
            self.bsdf.diffuse.tint * (base_scale * FRAC_1_PI) * att,
            self.sel.p_diffuse * cos_i * FRAC_1_PI,
        )
    }

    /// [`BsdfAt::eval_pdf`] of a diffuse-only BSDF: the general path with its known
    /// factors (see `Bsdf::at_lambert`): base scale and attenuation 1, no other lobe; the
    /// half vector it checks always exists here (both cosines are at least `COS_EPS`).
    pub(super) fn lambert_eval_pdf(&self, cos_i: f32, gi: f32) -> (Vec3, f32) {
        let zero = (Vec3::ZERO, 0.0);
        if !(cos_i >= COS_EPS && gi > 0.0) {
            return zero;
        }
        let f = Vec3::ZERO + self.bsdf.diffuse.tint * FRAC_1_PI;
        let pdf = 0.0 + self.sel.p_diffuse * cos_i * FRAC_1_PI;
        if f.is_finite() && pdf.is_finite() && pdf >= 0.0 {
            (f.max(Vec3::ZERO), pdf)
        } else {
            zero
        }
    }

    /// A cosine-weighted sample of the diffuse lobe.
    pub(super) fn sample_diffuse(&self, u: Vec2) -> Option<BsdfSample> {
        self.finish(self.fr.world(cosine_hemisphere(u)), Lobe::Diffuse)
    }
}

/// Cosine-weighted hemisphere direction around +z.
pub(super) fn cosine_hemisphere(u: Vec2) -> Vec3 {
    let r = u.x.sqrt();
    let phi = TAU * u.y;
    Vec3::new(r * phi.cos(), r * phi.sin(), (1.0 - u.x).max(0.0).sqrt())
}
