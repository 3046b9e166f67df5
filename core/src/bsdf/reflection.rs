//! The base's reflection: dielectric (`(1-metallic) specular F_d`) and metal
//! (`metallic F_m`) reflection share one GGX distribution, so they form one lobe with an
//! RGB Fresnel. Below [`super::DELTA_ALPHA`] it is a perfect mirror; Whitted asks it for
//! its mirror direction ([`Bsdf::mirror`]).

use glam::Vec3;

use super::at::BsdfAt;
use super::{Bsdf, BsdfSample, Lobe, WHITTED_MAX_ROUGHNESS, unit};

/// Whether the base reflects, and how much at most.
#[derive(Clone, Copy, Debug)]
pub(super) struct Reflection {
    /// Dielectric or metal reflection exists (`specular` or `metallic` > 0).
    pub(super) on: bool,
    /// Maximal reflectance (at grazing): `(1-metallic) specular + metallic`.
    pub(super) max: f32,
}

impl BsdfAt<'_> {
    /// The rough reflection's value and density at `wi` (`wi_l` local, half vector `h`,
    /// `c = wo . h`), under the layers' attenuation `att`.
    pub(super) fn glossy_reflection_eval(
        &self,
        wi_l: Vec3,
        h: Vec3,
        c: f32,
        cos_i: f32,
        att: f32,
    ) -> (Vec3, f32) {
        self.bsdf.layers_read();
        let b = self.bsdf;
        let (cos_o, a2, sel) = (self.wo_l.z, self.a2, &self.sel);
        let w = b.weights(c, self.fr.etap);
        let d = b.ggx.d(h, a2);
        let lo = self.lambda_o;
        let li = b.ggx.lambda(wi_l, a2);
        let g2 = 1.0 / (1.0 + lo + li);
        let g1 = 1.0 / (1.0 + lo);
        let pr = if b.transmission.delta {
            sel.pr_macro
        } else {
            b.pr(&w)
        };
        (
            w.refl * (d * g2 / (4.0 * cos_o * cos_i)) * att,
            // VNDF pdf G1 D (wo.h) / cos_o times the reflection Jacobian 1 / (4 wo.h).
            sel.p_spec * pr * g1 * d / (4.0 * cos_o),
        )
    }

    /// A sample of the smooth reflection: the mirror direction, weighted by the layer's
    /// Fresnel at `wo` and by what the coat and sheen above pass.
    pub(super) fn sample_mirror(&self) -> Option<BsdfSample> {
        self.bsdf.layers_read();
        let b = self.bsdf;
        let (fr, wo_l, sel) = (&self.fr, self.wo_l, &self.sel);
        let wi = fr.world(Vec3::new(-wo_l.x, -wo_l.y, wo_l.z));
        if wi.dot(fr.ng) <= 0.0 {
            return None;
        }
        // Under a coat the mirror is crossed twice at the same angle (to the coat's own
        // normal, the angles in and out may differ).
        let att_i = match self.coat_fr {
            Some(cf) => b.coat_att(cf.local(wi).z.abs()),
            None => self.att_o,
        };
        b.delta_sample(
            wi,
            self.w_o.refl * (self.att_o * att_i * self.sheen_att_o),
            sel.p_spec * sel.pr_macro,
            Lobe::SpecularReflection,
        )
    }
}

impl Bsdf {
    /// For Whitted: the perfect mirror direction and its weight (the Fresnel-weighted
    /// specular reflectance at `wo`, no cosine), if the reflection lobe is smooth enough
    /// (roughness < [`WHITTED_MAX_ROUGHNESS`]; rougher lobes are left to the diffuse/ambient
    /// term) and the mirror direction is above the geometric surface.
    pub fn mirror(&self, wo: Vec3) -> Option<(Vec3, Vec3)> {
        // An anisotropic lobe is as rough as its stretched axis. (The roughness is
        // read only when the lobes exist: a diffuse-only BSDF holds inert values.)
        let base_ok = self.reflection.on && {
            let stretched = if self.ggx.aniso {
                self.ggx.alpha.sqrt()
            } else {
                0.0
            };
            self.ggx.roughness.max(stretched) < WHITTED_MAX_ROUGHNESS
        };
        let coat_ok = self.coat.strength > 0.0 && self.coat.roughness < WHITTED_MAX_ROUGHNESS;
        if !base_ok && !coat_ok {
            return None;
        }
        let (fr, wo_l) = self.frame(wo)?;
        let coat_on = self.coat_on(&fr);
        // One mirror direction: the base's, or the coat's own when only the coat is
        // smooth and it has a normal of its own.
        let (coat_fr, coat_wo_l) = self.coat_frame(&fr, wo_l);
        let (mfr, mwo) = match coat_fr {
            Some(cf) if !base_ok => (cf, coat_wo_l),
            _ => (fr, wo_l),
        };
        let wi = unit(mfr.world(Vec3::new(-mwo.x, -mwo.y, mwo.z)))?;
        if wi.dot(fr.ng) <= 0.0 {
            return None;
        }
        let w = self.weights(wo_l.z, fr.etap);
        // Under a coat the base's mirror is crossed twice at the same angle.
        let (att, coat_w) = if coat_on {
            let a = self.coat_att(coat_wo_l.z);
            (a * a, self.coat_reflectance(coat_wo_l.z))
        } else {
            (1.0, 0.0)
        };
        let att = if self.sheen_on(&fr) {
            att * self.sheen_att(wo_l.z)
        } else {
            att
        };
        let base = if base_ok { w.refl * att } else { Vec3::ZERO };
        let weight = if coat_ok { base + coat_w } else { base };
        (weight.max_element() > 0.0 && weight.is_finite()).then_some((wi, weight))
    }
}
