//! Dielectric transmission (`KHR_materials_transmission` with `KHR_materials_ior`) as a
//! solid interface: perfect refraction by Snell's law when smooth or index-matched, GGX
//! microfacet refraction (Walter et al. 2007) when rough, and Whitted's refracted ray
//! ([`Bsdf::refraction`]). The coat and sheen are crossed once, on the outside.

use glam::Vec3;

use super::at::BsdfAt;
use super::{Bsdf, BsdfParams, BsdfSample, IOR_PASS_THROUGH_EPS, Lobe, MAX_IOR, unit};

/// The transmission lobe's parameters.
#[derive(Clone, Copy, Debug)]
pub(super) struct Transmission {
    /// `base (1-metallic) transmission`.
    pub(super) tint: Vec3,
    /// The tint is not black: the material transmits (and has an inside).
    pub(super) on: bool,
    /// Perfect refraction: the GGX lobe is a delta, or the index is matched.
    pub(super) delta: bool,
    /// Refraction index used for bending (>= 1).
    pub(super) eta: f32,
}

impl Transmission {
    /// `tint` already sanitised by [`Bsdf::new`]; `ggx_delta`: the base's GGX lobe is a
    /// delta.
    pub(super) fn new(params: &BsdfParams, tint: Vec3, ggx_delta: bool) -> Transmission {
        let eta = if params.ior.is_nan() {
            1.5
        } else {
            params.ior.clamp(1.0, MAX_IOR)
        };
        Transmission {
            tint,
            on: tint.max_element() > 0.0,
            delta: ggx_delta || eta - 1.0 < IOR_PASS_THROUGH_EPS,
            eta,
        }
    }
}

impl Bsdf {
    /// The coat's attenuation of a transmitted path: the coat is crossed once, on the
    /// outside, at the outside direction's cosine (`cos_out`, the macro cosine of
    /// whichever of `wo` and `wi` is outside; `coat_cos_out` the same to the coat's
    /// normal). 1 without a coat.
    fn coat_att_transmitted(&self, cos_out: f32, coat_cos_out: f32) -> f32 {
        let coat = if self.coat.strength > 0.0 {
            self.coat_att(coat_cos_out.abs())
        } else {
            1.0
        };
        if self.sheen.max > 0.0 {
            coat * self.sheen_att(cos_out.abs())
        } else {
            coat
        }
    }

    /// [`Bsdf::coat_att_transmitted`] for the outside direction `out` (world) of cosine
    /// `cos_out`.
    fn layers_transmitted(&self, cos_out: f32, out: Vec3) -> f32 {
        self.coat_att_transmitted(cos_out, self.coat_cos(out, cos_out))
    }

    /// For Whitted: the refracted direction through the macro surface and its weight (the
    /// transmission weight `(1 - specular max F) base (1-metallic) transmission`, no
    /// cosine). Returned for any roughness (rough glass is traced as smooth glass rather
    /// than rendered black); `None` when opaque or on total internal reflection.
    pub fn refraction(&self, wo: Vec3) -> Option<(Vec3, Vec3)> {
        if !self.transmission.on {
            return None;
        }
        let (fr, wo_l) = self.frame(wo)?;
        let wi_l = refract(wo_l, Vec3::Z, fr.etap)?;
        let wi = unit(fr.world(wi_l))?;
        if wi.dot(fr.ng) >= 0.0 {
            return None;
        }
        let w = self.weights(wo_l.z, fr.etap);
        let cos_out = if fr.outside { wo_l.z } else { wi_l.z };
        let out = if fr.outside { fr.world(wo_l) } else { wi };
        let trans = w.trans * self.layers_transmitted(cos_out, out);
        (trans.max_element() > 0.0 && trans.is_finite()).then_some((wi, trans))
    }
}

impl BsdfAt<'_> {
    /// The rough refraction's value and density at `wi` (`wi_l` local, below the
    /// surface); `None` when no microfacet refracts `wo` into `wi`.
    pub(super) fn glossy_transmission_eval(
        &self,
        wi: Vec3,
        wi_l: Vec3,
        cos_i: f32,
    ) -> Option<(Vec3, f32)> {
        self.bsdf.layers_read();
        let b = self.bsdf;
        let (fr, wo_l, a2) = (&self.fr, self.wo_l, self.a2);
        let cos_o = wo_l.z;
        // Walter et al. 2007: generalized half vector, facing wo's side.
        let etap = fr.etap;
        let mut m = unit(wi_l * etap + wo_l)?;
        if m.z < 0.0 {
            m = -m;
        }
        let c_o = wo_l.dot(m);
        let c_i = wi_l.dot(m);
        if !(c_o > 0.0 && c_i < 0.0) {
            return None;
        }
        let w = b.weights(c_o, etap);
        let denom = c_i + c_o / etap;
        let den2 = denom * denom;
        if !(den2 > 1e-12) || w.trans.max_element() <= 0.0 {
            return None;
        }
        let d = b.ggx.d(m, a2);
        let lo = self.lambda_o;
        let li = b.ggx.lambda(wi_l, a2);
        let g2 = 1.0 / (1.0 + lo + li);
        let g1 = 1.0 / (1.0 + lo);
        let cos_out = if fr.outside { cos_o } else { cos_i };
        let out = if fr.outside { fr.world(wo_l) } else { wi };
        let f = w.trans
            * (d * g2 * (-c_i) * c_o / (-cos_i * cos_o * den2))
            * b.layers_transmitted(cos_out, out);
        let vndf = g1 * c_o * d / cos_o;
        let pdf = self.sel.p_spec * (1.0 - b.pr(&w)) * vndf * (-c_i) / den2;
        Some((f, pdf))
    }

    /// A sample of the smooth refraction through the macro surface, weighted by the
    /// layer's transmission at `wo` and what the layers on the outside pass.
    pub(super) fn sample_refraction(&self) -> Option<BsdfSample> {
        self.bsdf.layers_read();
        let b = self.bsdf;
        let (fr, wo_l, sel) = (&self.fr, self.wo_l, &self.sel);
        let wi_l = refract(wo_l, Vec3::Z, fr.etap)?;
        let wi = fr.world(wi_l);
        if wi.dot(fr.ng) >= 0.0 {
            return None;
        }
        let cos_out = if fr.outside { wo_l.z } else { wi_l.z };
        let out = if fr.outside { fr.world(wo_l) } else { wi };
        b.delta_sample(
            wi,
            self.w_o.trans * b.layers_transmitted(cos_out, out),
            sel.p_spec * (1.0 - sel.pr_macro),
            Lobe::SpecularTransmission,
        )
    }
}

/// Refracts `wo` (pointing away, `wo.m > 0`) through the interface with normal `m`;
/// `etap = eta(transmitted side) / eta(wo side)`. `None` on total internal reflection.
pub(super) fn refract(wo: Vec3, m: Vec3, etap: f32) -> Option<Vec3> {
    let c = wo.dot(m);
    if !(c > 0.0) || !(etap > 0.0) {
        return None;
    }
    let sin2_t = (1.0 - c * c).max(0.0) / (etap * etap);
    if sin2_t >= 1.0 {
        return None;
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    unit(-wo / etap + m * (c / etap - cos_t))
}
