//! [`BsdfAt`]: the BSDF seen from one `wo`, where the lobes are composed. The frame, the
//! Fresnel weights at `wo` and the lobe selection are computed once per hit; evaluation
//! sums the lobes' values and densities in a fixed order (diffuse, sheen, coat, reflection;
//! or transmission), and sampling picks one lobe by its selection probability.

use glam::{Vec2, Vec3};

use super::frame::Frame;
use super::fresnel::Weights;
use super::ggx::{ggx_lambda, sample_vndf};
use super::transmission::refract;
use super::{Bsdf, BsdfSample, COS_EPS, Lobe, ONE_MINUS_EPS, SELECT_FLOOR, lum, sanitize_u, unit};

/// Lobe selection probabilities for one `wo`.
#[derive(Clone, Copy, Debug)]
pub(super) struct Selection {
    pub(super) p_diffuse: f32,
    /// Probability of the clear coat's reflection.
    pub(super) p_coat: f32,
    /// Probability of the sheen lobe.
    pub(super) p_sheen: f32,
    /// Probability of the specular group (reflection + transmission).
    pub(super) p_spec: f32,
    /// Reflection-vs-transmission split at the macro normal, used when transmission is delta.
    pub(super) pr_macro: f32,
}

/// A [`Bsdf`] seen from one outgoing direction `wo` ([`Bsdf::at`]). Light sampling and
/// BSDF sampling at a hit share the frame, the Fresnel weights at `wo` and the lobe
/// selection, instead of rebuilding them for every evaluation; the values are those the
/// per-call methods of [`Bsdf`] compute, bit for bit.
#[derive(Clone, Copy, Debug)]
pub struct BsdfAt<'a> {
    pub(super) bsdf: &'a Bsdf,
    pub(super) fr: Frame,
    pub(super) wo_l: Vec3,
    /// Lobe weights at the macro normal (`c = cos_o`).
    pub(super) w_o: Weights,
    pub(super) sel: Selection,
    /// GGX `alpha^2`.
    pub(super) a2: f32,
    /// Smith Λ of `wo`, for the microfacet lobes (0 when there are none).
    pub(super) lambda_o: f32,
    /// The clear coat faces `wo` ([`Bsdf::coat_on`]).
    pub(super) coat_on: bool,
    /// What the coat passes to the lobes under it at `wo` (1 without a coat).
    pub(super) att_o: f32,
    /// The coat's reflectance at `wo`: `coat F_c(cos_o)` (0 without a coat).
    pub(super) coat_w: f32,
    /// Coat GGX `alpha^2`, and Smith Λ of `wo` under it (0 when the coat is delta).
    pub(super) coat_a2: f32,
    pub(super) coat_lambda_o: f32,
    /// The coat's own frame when it has a normal of its own (`None`: it uses `fr`), and
    /// `wo` in it.
    pub(super) coat_fr: Option<Frame>,
    pub(super) coat_wo_l: Vec3,
    /// The sheen faces `wo` ([`Bsdf::sheen_on`]), and what it passes down at `wo`.
    pub(super) sheen_on: bool,
    pub(super) sheen_att_o: f32,
}

impl Bsdf {
    /// The BSDF seen from `wo`: its frame, lobe weights and lobe selection, computed once
    /// for every evaluation and sample at this hit. `None` when `wo` is degenerate or
    /// tangent to the surface (every evaluation is then zero and every sample absorbed).
    pub fn at(&self, wo: Vec3) -> Option<BsdfAt<'_>> {
        let (fr, wo_l) = self.frame(wo)?;
        if self.lambert {
            return Some(self.at_lambert(fr, wo_l));
        }
        let w_o = self.weights(wo_l.z, fr.etap);
        let coat_on = self.coat_on(&fr);
        let (coat_fr, coat_wo_l) = self.coat_frame(&fr, wo_l);
        let (att_o, coat_w) = if coat_on {
            (
                self.coat_att(coat_wo_l.z),
                self.coat_reflectance(coat_wo_l.z),
            )
        } else {
            (1.0, 0.0)
        };
        let (sheen_on, sheen_att_o, sheen_w) = self.sheen_at(&fr, wo_l.z, att_o);
        let sel = self.selection_from(&w_o, att_o * sheen_att_o, coat_w, sheen_w);
        let a2 = self.ggx.alpha * self.ggx.alpha;
        let coat_a2 = self.coat.alpha * self.coat.alpha;
        let coat_lambda_o = if coat_on && !self.coat.delta {
            ggx_lambda(coat_wo_l, coat_a2)
        } else {
            0.0
        };
        let microfacets = (self.reflection.on && !self.ggx.delta)
            || (self.transmission.on && !self.transmission.delta);
        let lambda_o = if microfacets {
            self.ggx.lambda(wo_l, a2)
        } else {
            0.0
        };
        Some(BsdfAt {
            bsdf: self,
            fr,
            wo_l,
            w_o,
            sel,
            a2,
            lambda_o,
            coat_on,
            att_o,
            coat_w,
            coat_a2,
            coat_lambda_o,
            coat_fr,
            coat_wo_l,
            sheen_on,
            sheen_att_o,
        })
    }

    /// [`Bsdf::at`] of a diffuse-only BSDF: what the general path computes, without
    /// computing it. The layers above the base pass everything (`specular` 0: base
    /// scale `1 - 0 F = 1`; no coat or sheen: attenuations 1), so the diffuse lobe's
    /// selection weight is the luminance of its tint and the total is that weight plus
    /// zeros: its probability is exactly 1 (or 0 for a black or invalid tint).
    fn at_lambert(&self, fr: Frame, wo_l: Vec3) -> BsdfAt<'_> {
        let wd = lum(self.diffuse.tint);
        let p_diffuse = if wd > 0.0 && wd.is_finite() { 1.0 } else { 0.0 };
        BsdfAt {
            bsdf: self,
            fr,
            wo_l,
            w_o: Weights {
                refl: Vec3::ZERO,
                base_scale: 1.0,
                trans: Vec3::ZERO,
            },
            sel: Selection {
                p_diffuse,
                p_coat: 0.0,
                p_sheen: 0.0,
                p_spec: 0.0,
                pr_macro: 1.0,
            },
            // Not read by the diffuse lobe: the inert alphas are not squared.
            a2: 0.0,
            lambda_o: 0.0,
            coat_on: false,
            att_o: 1.0,
            coat_w: 0.0,
            coat_a2: 0.0,
            coat_lambda_o: 0.0,
            coat_fr: None,
            coat_wo_l: wo_l,
            sheen_on: false,
            sheen_att_o: 1.0,
        }
    }

    /// Lobe selection from the lobe weights `w` at the macro normal (luminance), with
    /// floors; `att_o` is what a clear coat passes to the lobes under it and `coat_w` the
    /// coat's own reflectance (1 and 0 without a coat, which leave the values unchanged).
    fn selection_from(&self, w: &Weights, att_o: f32, coat_w: f32, sheen_w: f32) -> Selection {
        self.layers_read();
        let wd = lum(self.diffuse.tint) * w.base_scale.max(SELECT_FLOOR) * att_o;
        let r0 = if self.reflection.on {
            lum(w.refl).max(SELECT_FLOOR * self.reflection.max)
        } else {
            0.0
        };
        let r = r0 * att_o;
        let t0 = lum(w.trans);
        let t = if self.transmission.on && !self.transmission.delta {
            // Rough refraction may succeed on microfacets even past the macro critical angle.
            t0.max(SELECT_FLOOR * lum(self.transmission.tint))
        } else {
            t0
        } * att_o;
        let c = if coat_w > 0.0 || att_o < 1.0 {
            coat_w.max(SELECT_FLOOR * self.coat.strength)
        } else {
            0.0
        };
        let sh = if sheen_w > 0.0 {
            sheen_w.max(SELECT_FLOOR * lum(self.sheen.color))
        } else {
            0.0
        };
        let total = wd + r + t + c + sh;
        if !(total > 0.0) || !total.is_finite() {
            return Selection {
                p_diffuse: 0.0,
                p_coat: 0.0,
                p_sheen: 0.0,
                p_spec: 0.0,
                pr_macro: 1.0,
            };
        }
        let p_diffuse = wd / total;
        let p_coat = c / total;
        let p_sheen = sh / total;
        Selection {
            p_diffuse,
            p_coat,
            p_sheen,
            p_spec: (1.0 - p_diffuse - p_coat - p_sheen).max(0.0),
            pr_macro: if r0 + t0 > 0.0 { r0 / (r0 + t0) } else { 1.0 },
        }
    }
}

impl BsdfAt<'_> {
    /// `f(wo, wi)` of the non-delta lobes, without the cosine.
    pub fn eval(&self, wi: Vec3) -> Vec3 {
        self.eval_pdf(wi).0
    }

    /// BSDF value and pdf of the non-delta lobes.
    pub fn eval_pdf(&self, wi: Vec3) -> (Vec3, f32) {
        let b = self.bsdf;
        let zero = (Vec3::ZERO, 0.0);
        let (fr, wo_l) = (&self.fr, self.wo_l);
        let Some(wi) = unit(wi) else {
            return zero;
        };
        if b.lambert {
            // Only the cosine to the shading normal is read: `fr.local(wi).z` is this
            // same product, so the tangent components are not computed.
            return self.lambert_eval_pdf(wi.dot(fr.n), wi.dot(fr.ng));
        }
        let wi_l = fr.local(wi);
        let gi = wi.dot(fr.ng);
        let (cos_o, cos_i) = (wo_l.z, wi_l.z);
        let mut f = Vec3::ZERO;
        let mut pdf = 0.0;
        if cos_i >= COS_EPS && gi > 0.0 {
            let Some(h) = unit(wo_l + wi_l) else {
                return zero;
            };
            let c = wo_l.dot(h);
            // The base is attenuated by the dielectric layer's Fresnel on the way in and out
            // (not at VdotH as in glTF Appendix B, which gains energy under a smooth layer).
            let base_scale = self.w_o.base_scale * b.weights(cos_i, fr.etap).base_scale;
            // A clear coat attenuates what lies under it the same way, in and out, and
            // the sheen what lies under both.
            let coat_wi_l = self.coat_fr.map_or(wi_l, |cf| cf.local(wi));
            let coat_att = self.under_coat(coat_wi_l);
            let att = self.under_sheen(coat_att, cos_i);
            let (df, dp) = self.diffuse_eval(base_scale, att, cos_i);
            f += df;
            pdf += dp;
            if self.sheen_on {
                let (sf, sp) = self.sheen_eval(cos_o, cos_i, h, coat_att);
                f += sf;
                pdf += sp;
            }
            if let Some((cf, cp)) = self.coat_eval(coat_wi_l, h, c, cos_i) {
                f += cf;
                pdf += cp;
            }
            if b.reflection.on && !b.ggx.delta {
                let (rf, rp) = self.glossy_reflection_eval(wi_l, h, c, cos_i, att);
                f += rf;
                pdf += rp;
            }
        } else if cos_i <= -COS_EPS && gi < 0.0 && b.transmission.on && !b.transmission.delta {
            let Some((tf, tp)) = self.glossy_transmission_eval(wi, wi_l, cos_i) else {
                return zero;
            };
            f += tf;
            pdf += tp;
        }

        if f.is_finite() && pdf.is_finite() && pdf >= 0.0 {
            (f.max(Vec3::ZERO), pdf)
        } else {
            zero
        }
    }

    /// Samples a direction: `u_lobe` picks the lobe, `u` the direction within it.
    /// Returns `None` for an absorbed/invalid sample (below the surface, total internal
    /// reflection of a sampled refraction, zero pdf or zero value).
    pub fn sample(&self, u_lobe: f32, u: Vec2) -> Option<BsdfSample> {
        let b = self.bsdf;
        let sel = &self.sel;
        let u = Vec2::new(sanitize_u(u.x), sanitize_u(u.y));
        if b.lambert {
            // The selection of `Bsdf::at_lambert`: only `p_diffuse`, 1 or 0. The general
            // test below is then `p_diffuse + 0 + 0 + 0 > 0`, and every `u_lobe` (below
            // 1 once sanitised) picks the diffuse lobe: the lobe number is not read.
            if !(sel.p_diffuse > 0.0) {
                return None;
            }
            return self.sample_diffuse(u);
        }
        let ul = sanitize_u(u_lobe);
        if !(sel.p_diffuse + sel.p_spec + sel.p_coat + sel.p_sheen > 0.0) {
            return None;
        }
        let layers = sel.p_coat + sel.p_sheen;
        if ul < sel.p_diffuse || (sel.p_spec <= 0.0 && !(layers > 0.0)) {
            return self.sample_diffuse(u);
        }
        let ul = ul - sel.p_diffuse;
        if ul < sel.p_coat || (sel.p_spec <= 0.0 && sel.p_sheen <= 0.0) {
            return self.sample_coat(u);
        }
        if ul < layers || sel.p_spec <= 0.0 {
            return self.sample_sheen(u);
        }
        // Reuse the lobe number for the reflection/transmission split.
        let u2 = ((ul - layers) / sel.p_spec).clamp(0.0, ONE_MINUS_EPS);
        if b.ggx.delta || (b.transmission.delta && u2 >= sel.pr_macro) {
            if b.ggx.delta && u2 < sel.pr_macro {
                return self.sample_mirror();
            }
            return self.sample_refraction();
        }
        self.sample_microfacet(u, u2)
    }

    /// A sample of the rough specular group: a visible GGX normal, then reflection or
    /// refraction on it by their Fresnel weights (`u2` picks).
    fn sample_microfacet(&self, u: Vec2, u2: f32) -> Option<BsdfSample> {
        self.bsdf.layers_read();
        let b = self.bsdf;
        let (fr, wo_l) = (&self.fr, self.wo_l);
        let m = sample_vndf(wo_l, b.ggx.alpha, b.ggx.alpha_b, u)?;
        let c = wo_l.dot(m);
        if !(c > 0.0) {
            return None;
        }
        let reflect = if b.transmission.delta {
            true // u2 < pr_macro here
        } else {
            u2 < b.pr(&b.weights(c, fr.etap))
        };
        if reflect {
            let wi_l = m * (2.0 * c) - wo_l;
            self.finish(fr.world(wi_l), Lobe::GlossyReflection)
        } else {
            let wi_l = refract(wo_l, m, fr.etap)?;
            self.finish(fr.world(wi_l), Lobe::GlossyTransmission)
        }
    }

    /// A non-delta sample: value and pdf are those of `eval`/`pdf`, so MIS is consistent.
    /// A direction that lands on the wrong side for its lobe (a microfacet reflection below
    /// the surface, a rough refraction back above it) is rejected: `pdf` would not count the
    /// technique that produced it, and accepting it would bias the estimate upward.
    pub(super) fn finish(&self, wi: Vec3, lobe: Lobe) -> Option<BsdfSample> {
        let fr = &self.fr;
        let wi = unit(wi)?;
        let (cs, cg) = (wi.dot(fr.n), wi.dot(fr.ng));
        let right_side = match lobe {
            Lobe::GlossyTransmission | Lobe::SpecularTransmission => cs < 0.0 && cg < 0.0,
            _ => cs > 0.0 && cg > 0.0,
        };
        if !right_side {
            return None;
        }
        let (f, pdf) = self.eval_pdf(wi);
        if !(pdf > 0.0) || !pdf.is_finite() || !f.is_finite() || f.max_element() <= 0.0 {
            return None;
        }
        Some(BsdfSample {
            wi,
            f,
            pdf,
            lobe,
            delta: false,
        })
    }
}
