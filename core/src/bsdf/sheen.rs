//! The sheen layer (`KHR_materials_sheen`): a broad, grazing reflection over everything
//! under it (the tables of its lobe and albedo are in [`crate::sheen`]). It faces the
//! same sides as the clear coat, passes down `1 - max(colour) E(cos)` and is sampled
//! by cosine-weighted directions.

use glam::{Vec2, Vec3};
use std::f32::consts::FRAC_1_PI;

use super::at::BsdfAt;
use super::diffuse::cosine_hemisphere;
use super::frame::Frame;
use super::{Bsdf, BsdfParams, BsdfSample, Lobe, lum, sat, sat3};

/// The sheen's colour (black: none), its largest channel and its roughness.
#[derive(Clone, Copy, Debug)]
pub(super) struct Sheen {
    pub(super) color: Vec3,
    pub(super) max: f32,
    pub(super) roughness: f32,
}

impl Sheen {
    pub(super) fn new(params: &BsdfParams) -> Sheen {
        let color = sat3(params.sheen_color);
        Sheen {
            color,
            max: color.max_element(),
            roughness: sat(params.sheen_roughness),
        }
    }
}

impl Bsdf {
    /// Whether the sheen faces `fr`'s `wo` (the same sides as the clear coat).
    pub(super) fn sheen_on(&self, fr: &Frame) -> bool {
        self.sheen.max > 0.0 && (!self.transmission.on || fr.outside)
    }

    /// What the sheen passes to the layers under it at cosine `c`:
    /// `1 - max(sheen colour) E(c)`, with `E` the white sheen lobe's albedo.
    pub(super) fn sheen_att(&self, c: f32) -> f32 {
        1.0 - self.sheen.max * crate::sheen::albedo(c, self.sheen.roughness)
    }

    /// The sheen seen from `wo` (local cosine `cos_o`) under a coat passing `att_o`:
    /// whether it faces `wo`, what it passes down at `wo`, and its selection weight.
    pub(super) fn sheen_at(&self, fr: &Frame, cos_o: f32, att_o: f32) -> (bool, f32, f32) {
        self.layers_read();
        let on = self.sheen_on(fr);
        let (att, w) = if on {
            let e = crate::sheen::albedo(cos_o, self.sheen.roughness);
            (1.0 - self.sheen.max * e, lum(self.sheen.color) * e * att_o)
        } else {
            (1.0, 0.0)
        };
        (on, att, w)
    }
}

impl BsdfAt<'_> {
    /// The attenuation of the lobes under the sheen at `wi` (local cosine `cos_i`), given
    /// the coat's `coat_att`: what the sheen's albedo leaves on the more reflective side
    /// (glTF's min of both, which keeps the sum reciprocal and below 1).
    pub(super) fn under_sheen(&self, coat_att: f32, cos_i: f32) -> f32 {
        if self.sheen_on {
            coat_att * self.sheen_att_o.min(self.bsdf.sheen_att(cos_i))
        } else {
            coat_att
        }
    }

    /// The sheen's value and density at `wi` (half vector `h`), under the coat's
    /// `coat_att`.
    pub(super) fn sheen_eval(&self, cos_o: f32, cos_i: f32, h: Vec3, coat_att: f32) -> (Vec3, f32) {
        let b = self.bsdf;
        let lobe = crate::sheen::lobe(cos_o, cos_i, h.z, b.sheen.roughness);
        (
            b.sheen.color * (lobe * coat_att),
            self.sel.p_sheen * cos_i * FRAC_1_PI,
        )
    }

    /// A cosine-weighted sample for the sheen lobe.
    pub(super) fn sample_sheen(&self, u: Vec2) -> Option<BsdfSample> {
        self.bsdf.layers_read();
        self.finish(self.fr.world(cosine_hemisphere(u)), Lobe::Sheen)
    }
}
