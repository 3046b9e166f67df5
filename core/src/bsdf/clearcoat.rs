//! The clear coat (`KHR_materials_clearcoat`): a GGX dielectric layer of ior 1.5 over the
//! base, optionally with a normal of its own. It reflects `coat F_c` and passes
//! `1 - coat F_c` down on the way in and on the way out; on a transmissive object it is
//! on the outside only.

use glam::{Vec2, Vec3};

use super::at::BsdfAt;
use super::frame::Frame;
use super::fresnel::schlick_w;
use super::ggx::{ggx_d, ggx_lambda, sample_vndf};
use super::{Bsdf, BsdfParams, BsdfSample, COS_EPS, DELTA_ALPHA, Lobe, MIN_ALPHA, sat, unit};

/// The clear coat's parameters.
#[derive(Clone, Copy, Debug)]
pub(super) struct Coat {
    /// Strength (0: none).
    pub(super) strength: f32,
    /// GGX alpha, clamped to >= [`MIN_ALPHA`].
    pub(super) alpha: f32,
    pub(super) roughness: f32,
    pub(super) delta: bool,
    /// The coat's own shading normal, on `ng`'s side; `None`: the coat uses `n` (and
    /// every function keeps the bits it had before coat normals existed).
    pub(super) n: Option<Vec3>,
}

impl Coat {
    /// `ng`: the BSDF's unit geometric normal as passed.
    pub(super) fn new(params: &BsdfParams, ng: Vec3) -> Coat {
        let strength = sat(params.clearcoat);
        let roughness = sat(params.clearcoat_roughness);
        let a = roughness * roughness;
        // Without a coat its normal is not normalised (no square root and division per hit).
        let n = if strength > 0.0 {
            unit(params.clearcoat_normal).map(|c| if c.dot(ng) < 0.0 { -c } else { c })
        } else {
            None
        };
        Coat {
            strength,
            alpha: a.max(MIN_ALPHA),
            roughness,
            delta: a < DELTA_ALPHA,
            n,
        }
    }
}

impl Bsdf {
    /// Whether the clear coat faces `fr`'s `wo`: always for opaque materials (either side
    /// is their outside), only from the outside for transmissive ones.
    pub(super) fn coat_on(&self, fr: &Frame) -> bool {
        self.coat.strength > 0.0 && (!self.transmission.on || fr.outside)
    }

    /// What the clear coat passes to the layers under it at cosine `c`: `1 - coat F_c(c)`.
    pub(super) fn coat_att(&self, c: f32) -> f32 {
        1.0 - self.coat.strength * coat_fresnel(c)
    }

    /// The coat's reflectance at cosine `c`: `coat F_c(c)`.
    pub(super) fn coat_reflectance(&self, c: f32) -> f32 {
        self.coat.strength * coat_fresnel(c)
    }

    /// The clear coat's own frame for the base frame `fr` and local `wo_l`, and `wo` in
    /// it, when the coat faces `wo` and has a normal of its own: its normal on `wo`'s
    /// side, or the geometric normal when `wo` is below it (as [`Bsdf::frame`] does for
    /// the shading normal). Otherwise `None` and `wo_l`: the coat uses `fr`.
    pub(super) fn coat_frame(&self, fr: &Frame, wo_l: Vec3) -> (Option<Frame>, Vec3) {
        self.layers_read();
        let wo = fr.world(wo_l);
        let cf = self.coat.n.filter(|_| self.coat_on(fr)).and_then(|nc| {
            let nc = if fr.outside { nc } else { -nc };
            let n = if wo.dot(nc) < COS_EPS { fr.ng } else { nc };
            let (t, b) = n.any_orthonormal_pair();
            let cf = Frame { t, b, n, ..*fr };
            (cf.local(wo).z >= COS_EPS).then_some(cf)
        });
        (cf, cf.map_or(wo_l, |cf| cf.local(wo)))
    }

    /// The cosine of world direction `w` to the coat's normal (`fallback`, the cosine to
    /// the shading normal, when the coat has no normal of its own).
    pub(super) fn coat_cos(&self, w: Vec3, fallback: f32) -> f32 {
        self.coat.n.map_or(fallback, |nc| w.dot(nc).abs())
    }
}

impl BsdfAt<'_> {
    /// What the coat passes to the lobes under it for `wi` (`coat_wi_l`: `wi` in the
    /// coat's frame), in and out. (With a normal of its own, `wi` may lie below the
    /// coat's normal though above the surface: its cosine's magnitude is used, so no
    /// direction the base lobes sample is blacked out.)
    pub(super) fn under_coat(&self, coat_wi_l: Vec3) -> f32 {
        if self.coat_on {
            self.att_o * self.bsdf.coat_att(coat_wi_l.z.abs())
        } else {
            1.0
        }
    }

    /// The coat's rough reflection at `wi` (`coat_wi_l` in the coat's frame, `cos_i` to
    /// the shading normal) with the base's half vector `h` and `c = wo . h`; `None` when
    /// it has none there. With a normal of its own the coat's lobe lives in its frame; its
    /// value is divided by the shading cosine the integrator multiplies by (not the
    /// coat's), so `f cos_i / pdf` stays the coat's `F G2 / G1`.
    pub(super) fn coat_eval(
        &self,
        coat_wi_l: Vec3,
        h: Vec3,
        c: f32,
        cos_i: f32,
    ) -> Option<(Vec3, f32)> {
        let b = self.bsdf;
        let coat_h = match self.coat_fr {
            Some(_) => unit(self.coat_wo_l + coat_wi_l),
            None => Some(h),
        };
        let coat_h = coat_h?;
        if !(self.coat_on && !b.coat.delta && coat_wi_l.z > 0.0) {
            return None;
        }
        let coat_cos_o = self.coat_wo_l.z;
        let d = ggx_d(coat_h, self.coat_a2);
        let lo = self.coat_lambda_o;
        let li = ggx_lambda(coat_wi_l, self.coat_a2);
        let g2 = 1.0 / (1.0 + lo + li);
        let g1 = 1.0 / (1.0 + lo);
        Some((
            Vec3::splat(b.coat.strength * coat_fresnel(c) * d * g2 / (4.0 * coat_cos_o * cos_i)),
            self.sel.p_coat * g1 * d / (4.0 * coat_cos_o),
        ))
    }

    /// A sample of the clear coat: its mirror when smooth, else a GGX reflection through
    /// the coat's visible normals.
    pub(super) fn sample_coat(&self, u: Vec2) -> Option<BsdfSample> {
        self.bsdf.layers_read();
        let b = self.bsdf;
        // In the coat's own frame when it has a normal of its own.
        let (fr, wo_l) = (self.coat_fr.as_ref().unwrap_or(&self.fr), self.coat_wo_l);
        if !self.coat_on {
            return None;
        }
        if b.coat.delta {
            let wi = fr.world(Vec3::new(-wo_l.x, -wo_l.y, wo_l.z));
            if wi.dot(fr.ng) <= 0.0 {
                return None;
            }
            return b.delta_sample(
                wi,
                Vec3::splat(self.coat_w),
                self.sel.p_coat,
                Lobe::CoatReflection,
            );
        }
        let m = sample_vndf(wo_l, b.coat.alpha, b.coat.alpha, u)?;
        let c = wo_l.dot(m);
        if !(c > 0.0) {
            return None;
        }
        self.finish(fr.world(m * (2.0 * c) - wo_l), Lobe::GlossyReflection)
    }
}

/// Fresnel reflectance of the clear coat (ior 1.5, so F0 = 0.04, as
/// `KHR_materials_clearcoat` fixes it) at cosine `c`, in glTF's Schlick form.
pub(super) fn coat_fresnel(c: f32) -> f32 {
    0.04 + 0.96 * schlick_w(c)
}
