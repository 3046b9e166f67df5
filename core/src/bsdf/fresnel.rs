//! The base's Fresnel layer: a dielectric (glTF's Schlick form with
//! `KHR_materials_specular`'s F0 and F90, exact total internal reflection from inside)
//! mixed with a metal (Schlick over the base colour) by `metallic`, each optionally under
//! a thin film (`KHR_materials_iridescence`), and what the layer leaves to the diffuse
//! base and to transmission ([`Weights`]).

use glam::Vec3;

use super::{Bsdf, BsdfParams, MAX_IOR, lum, sat};

/// The dielectric and metal Fresnel inputs of the base.
#[derive(Clone, Copy, Debug)]
pub(super) struct Fresnel {
    /// Linear base colour: the metal's F0.
    pub(super) base: Vec3,
    pub(super) metallic: f32,
    /// `KHR_materials_specular` factor: the dielectric's F90.
    pub(super) specular: f32,
    /// Dielectric F0: `min(((ior-1)/(ior+1))^2 * specular_color, 1)`.
    pub(super) f0: Vec3,
    pub(super) film: Film,
}

impl Fresnel {
    /// `base`, `metallic` and `specular` already sanitised by [`Bsdf::new`].
    pub(super) fn new(
        params: &BsdfParams,
        base: Vec3,
        metallic: f32,
        specular: f32,
        film: Film,
    ) -> Fresnel {
        let specular_color = params
            .specular_color
            .to_array()
            .map(|c| if c >= 0.0 { c.min(1e6) } else { 0.0 });
        let ior = params.ior;
        let f0_ior = if ior.is_nan() {
            0.04
        } else if ior.is_infinite() {
            1.0
        } else {
            let i = ior.max(0.0);
            let r = (i - 1.0) / (i + 1.0);
            r * r
        };
        Fresnel {
            base,
            metallic,
            specular,
            f0: (Vec3::from_array(specular_color) * f0_ior).min(Vec3::ONE),
            film,
        }
    }
}

impl Fresnel {
    /// The layer of a diffuse-only BSDF (`specular` and `metallic` 0): it reflects
    /// nothing and passes everything to the base whatever its F0 and film, so none of
    /// them is computed. [`super::Bsdf::new`] uses it only when `lambert` is set, and
    /// then nothing reads it ([`Bsdf::weights`] asserts so in debug builds).
    pub(super) const INERT: Fresnel = Fresnel {
        base: Vec3::ZERO,
        metallic: 0.0,
        specular: 0.0,
        f0: Vec3::ZERO,
        film: Film {
            strength: 0.0,
            ior: 1.0,
            thickness: 0.0,
        },
    };
}

/// The thin film of `KHR_materials_iridescence` over the base.
#[derive(Clone, Copy, Debug)]
pub(super) struct Film {
    /// Strength (0: none; also 0 when the film has no thickness).
    pub(super) strength: f32,
    /// The film's refraction index and its thickness (nm).
    pub(super) ior: f32,
    pub(super) thickness: f32,
}

impl Film {
    pub(super) fn new(params: &BsdfParams) -> Film {
        let thickness = if params.iridescence_thickness.is_finite() {
            params.iridescence_thickness.clamp(0.0, 1e6)
        } else {
            0.0
        };
        // A film of no thickness is no film (the Sample Viewer drops it too).
        let strength = if thickness > 0.0 {
            sat(params.iridescence)
        } else {
            0.0
        };
        let ior = if params.iridescence_ior.is_finite() {
            params.iridescence_ior.clamp(1.0, MAX_IOR)
        } else {
            crate::iridescence::DEFAULT_IOR
        };
        Film {
            strength,
            ior,
            thickness,
        }
    }

    /// The film's Fresnel reflectance at cosine `c` over a base of normal-incidence
    /// reflectance `f0`.
    fn fresnel(&self, c: f32, f0: Vec3) -> Vec3 {
        crate::iridescence::fresnel(1.0, self.ior, c, self.thickness, f0)
    }
}

/// Lobe weights for one microfacet cosine `c = wo . m`.
#[derive(Clone, Copy, Debug)]
pub(super) struct Weights {
    /// Reflection Fresnel (dielectric + metal), RGB.
    pub(super) refl: Vec3,
    /// `1 - specular max(F_d)`: what the dielectric layer leaves to the base.
    pub(super) base_scale: f32,
    /// Transmission weight (0 on total internal reflection), RGB.
    pub(super) trans: Vec3,
}

impl Bsdf {
    /// Cosine on the outer (less dense) side for a wo-side cosine `c`; `None` on total
    /// internal reflection. Opaque materials have no inside: always `c`.
    fn outer_cos(&self, c: f32, etap: f32) -> Option<f32> {
        if !self.transmission.on || etap >= 1.0 {
            return Some(c);
        }
        let sin2_t = (1.0 - c * c).max(0.0) / (etap * etap);
        if sin2_t >= 1.0 {
            None
        } else {
            Some((1.0 - sin2_t).sqrt())
        }
    }

    /// The layer's weights at microfacet cosine `c` (`etap` as in the frame).
    pub(super) fn weights(&self, c: f32, etap: f32) -> Weights {
        debug_assert!(!self.lambert, "a diffuse-only BSDF has no Fresnel layer");
        let fr = &self.fresnel;
        let c = c.clamp(0.0, 1.0);
        let outer = self.outer_cos(c, etap);
        let mut fd = match outer {
            Some(co) => fr.f0 + (Vec3::ONE - fr.f0) * schlick_w(co),
            None => Vec3::ONE,
        };
        let mut fm = fr.base + (Vec3::ONE - fr.base) * schlick_w(c);
        if fr.film.strength > 0.0 {
            // KHR_materials_iridescence: F = mix(F_schlick, F_film, factor), for the
            // dielectric (at the outer cosine, like its Schlick term; total internal
            // reflection stays total) and for the metal. Both stay in [0, 1], so the
            // layering below conserves energy as without the film.
            if let Some(co) = outer {
                fd = fd.lerp(fr.film.fresnel(co, fr.f0), fr.film.strength);
            }
            if fr.metallic > 0.0 {
                fm = fm.lerp(fr.film.fresnel(c, fr.base), fr.film.strength);
            }
        }
        let refl = fd * ((1.0 - fr.metallic) * fr.specular) + fm * fr.metallic;
        let base_scale = (1.0 - fr.specular * fd.max_element()).max(0.0);
        let trans = if outer.is_some() {
            self.transmission.tint * base_scale
        } else {
            Vec3::ZERO
        };
        Weights {
            refl,
            base_scale,
            trans,
        }
    }

    /// Probability of reflecting (vs refracting) on a microfacet with weights `w`.
    pub(super) fn pr(&self, w: &Weights) -> f32 {
        let r = if self.reflection.on { lum(w.refl) } else { 0.0 };
        let t = lum(w.trans);
        if t <= 0.0 {
            1.0
        } else if r <= 0.0 {
            0.0
        } else {
            r / (r + t)
        }
    }
}

/// Schlick's `(1 - c)^5`.
pub(super) fn schlick_w(c: f32) -> f32 {
    let m = (1.0 - c).clamp(0.0, 1.0);
    let m2 = m * m;
    m2 * m2 * m
}
