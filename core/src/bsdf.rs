//! The glTF 2.0 BSDF: Lambert diffuse + GGX (Trowbridge-Reitz) specular, metallic/roughness,
//! `KHR_materials_specular`, and dielectric transmission (`KHR_materials_transmission` with
//! `KHR_materials_ior`).
//!
//! # Model
//!
//! Following the glTF 2.0 specification, Appendix B ("BRDF implementation") and the
//! `KHR_materials_specular` / `KHR_materials_transmission` extensions:
//!
//! ```text
//! F_d(c)     = f0 + (1 - f0) (1 - c)^5,  f0 = min(((ior-1)/(ior+1))^2 * specular_color, 1)
//! F_m(c)     = base + (1 - base) (1 - c)^5                         (conductor Fresnel)
//! reflection = ((1-metallic) specular F_d + metallic F_m) * GGX(alpha = roughness^2)
//! diffuse    = (1-metallic) (1-transmission) base/pi
//!              * (1 - specular max(F_d(wo.n))) (1 - specular max(F_d(wi.n)))
//! transmit   = (1-metallic) transmission base * BTDF * (1 - specular max(F_d))
//! ```
//!
//! `c` is `wo . m` for the microfacet normal `m`. Both dielectric and metal reflection
//! share one GGX distribution, so they form one reflection lobe with an RGB Fresnel.
//! `specular = 0` removes the dielectric reflection entirely (F90 = specular in the
//! extension), so a non-metal with `specular = 0` is pure Lambert and its sampler never
//! leaves the diffuse lobe.
//!
//! **Deviation:** Appendix B's `fresnel_mix` attenuates the diffuse base by
//! `1 - F(VdotH)` with `h` the half vector of `wo` and `wi`. Under a smooth (delta) coat
//! that gains energy (albedo ~1.35 at 80 degrees: the mirror reflects `F(wo.n)` while the
//! base loses only `F(VdotH)`), so dray attenuates the base by the layer's Fresnel
//! transmittance on the way in and on the way out, which is reciprocal and keeps the albedo
//! below 1 for every roughness. Transmission keeps the per-microfacet `1 - F(wo.m)`, which
//! pairs exactly with the reflection on the same microfacet.
//!
//! GGX uses the Smith *height-correlated* masking-shadowing `G2 = 1 / (1 + Λ(wo) + Λ(wi))`
//! and is sampled with the distribution of visible normals (Heitz 2018, "Sampling the GGX
//! Distribution of Visible Normals", JCGT 7(4)); with it the reflection throughput is
//! `F G2 / G1(wo)` and never exceeds the Fresnel term.
//!
//! # Transmission
//!
//! Transmission is a *solid* dielectric interface (refraction with Snell's law, total internal
//! reflection), not the thin-walled default of `KHR_materials_transmission` without
//! `KHR_materials_volume`: dray renders glass objects as closed volumes. Which side is the
//! inside is taken from the geometric normal **as passed to [`Bsdf::new`]**: `ng` points to
//! the outside (ior 1), so callers pass the winding normal, not one flipped toward the ray
//! (with [`crate::surface::Surface`]: `if surf.front { surf.ng } else { -surf.ng }`). Rough transmission (alpha >= [`DELTA_ALPHA`]) is GGX microfacet
//! refraction (Walter, Marschner, Li, Torrance 2007, "Microfacet Models for Refraction
//! through Rough Surfaces"), sampled through visible normals. Reflection and refraction on
//! a sampled microfacet are chosen by their Fresnel weights, as in pbrt-v4's dielectric.
//!
//! The Fresnel term of the dielectric stays glTF's Schlick form; when the ray is inside the
//! denser medium Schlick is evaluated with the cosine on the outside of the interface and
//! returns 1 past the critical angle, so total internal reflection is exact and the
//! reflectance is the same from both sides. (With `specular < 1` the part of a totally
//! reflected ray that the weakened coat does not reflect is absorbed, never transmitted.)
//!
//! The BTDF omits the `1/eta^2` radiance compression: it cancels on every closed object
//! whose camera and lights are outside, and without it the throughput of every sample is
//! bounded by 1 (`T G2 / G1` for rough, `T` for smooth refraction). The base colour tints
//! each crossing of the interface (entering and leaving), which keeps the BSDF stateless.
//!
//! # Delta lobes
//!
//! Below `alpha = roughness^2 <` [`DELTA_ALPHA`] reflection and transmission are perfect
//! mirror / perfect refraction. Transmission is also delta when `ior` is within
//! [`IOR_PASS_THROUGH_EPS`] of 1: microfacets do not bend light at an index-matched
//! interface, so the refracted lobe collapses onto `-wo` whatever the roughness.
//! [`Bsdf::eval`] and [`Bsdf::pdf`] cover the non-delta lobes only; a delta sample returns
//! `pdf` = the discrete probability of choosing it and `f = weight / |wi . n|` (with `n` the
//! shading normal passed to [`Bsdf::new`]), so `f |wi . n| / pdf` is the throughput.
//!
//! # Robustness
//!
//! Reflection lobes are zero when `wi` is below the geometric surface on `wo`'s side, and
//! transmission lobes are zero unless `wi` is on the other side of the geometric surface:
//! darkening is preferred over light leaks. When `wo` is below the shading hemisphere (but
//! above the geometric one) the geometric normal is used as the shading normal. Every
//! division is guarded; `eval`/`pdf` return 0 and `sample` returns `None` rather than any
//! NaN or infinity. All functions are pure.

// `!(x > 0.0)` is used on purpose throughout: it also rejects NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use glam::{Vec2, Vec3};
use std::f32::consts::{FRAC_1_PI, PI, TAU};

use crate::material::Material;

/// GGX alpha (`roughness^2`) below which the specular lobes are delta (perfect mirror /
/// perfect refraction). Corresponds to roughness ~0.032.
pub const DELTA_ALPHA: f32 = 1e-3;
/// Smallest GGX alpha used by non-delta evaluation.
pub const MIN_ALPHA: f32 = 1e-4;
/// Roughness below which [`Bsdf::mirror`] treats the reflection lobe as a mirror (Whitted).
pub const WHITTED_MAX_ROUGHNESS: f32 = 0.2;
/// Transmission is delta (straight through) when `|ior - 1|` is below this.
pub const IOR_PASS_THROUGH_EPS: f32 = 1e-3;
/// Largest refraction index used for ray bending (`KHR_materials_ior` allows `inf`).
pub const MAX_IOR: f32 = 10.0;

/// Cosines below this are treated as zero (grazing/tangent directions carry no energy).
const COS_EPS: f32 = 1e-6;
/// Selection-probability floor for a lobe that exists, as a fraction of its maximal weight:
/// lobe weights are estimated at `wo`, and a floor keeps every lobe with a non-zero `eval`
/// samplable (so the one-sample estimator stays unbiased).
const SELECT_FLOOR: f32 = 0.05;
/// The largest `f32` below 1.
const ONE_MINUS_EPS: f32 = 1.0 - f32::EPSILON / 2.0;

/// Shading inputs of the BSDF at one point (factors already multiplied by textures).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BsdfParams {
    /// Linear base colour (albedo for dielectrics, F0 for metals, transmission tint).
    pub base_color: Vec3,
    pub metallic: f32,
    /// Perceptual roughness; GGX alpha is its square.
    pub roughness: f32,
    /// `KHR_materials_specular` factor: scales the dielectric specular lobe (F90).
    pub specular: f32,
    /// `KHR_materials_specular` colour: tints the dielectric F0.
    pub specular_color: Vec3,
    /// `KHR_materials_transmission` factor.
    pub transmission: f32,
    /// `KHR_materials_ior`.
    pub ior: f32,
    /// `KHR_materials_clearcoat` factor (0: no coat) and perceptual roughness.
    pub clearcoat: f32,
    pub clearcoat_roughness: f32,
    /// The coat's own shading normal (`clearcoatNormalTexture`), zero when it has none
    /// (it then uses the shading normal `n`).
    pub clearcoat_normal: Vec3,
    /// `KHR_materials_sheen` colour (black: no sheen) and roughness.
    pub sheen_color: Vec3,
    pub sheen_roughness: f32,
    /// `KHR_materials_anisotropy` strength (0: isotropic) and its direction in world
    /// space (the GGX lobe is stretched along it: `alpha_t = mix(alpha, 1, strength^2)`).
    pub anisotropy: f32,
    pub anisotropy_direction: Vec3,
    /// `KHR_materials_iridescence` strength (0: no film), the film's refraction index
    /// and its thickness in nanometres (0: no film).
    pub iridescence: f32,
    pub iridescence_ior: f32,
    pub iridescence_thickness: f32,
}

impl Default for BsdfParams {
    /// glTF defaults: white, fully metallic, fully rough, specular 1, ior 1.5.
    fn default() -> Self {
        BsdfParams {
            base_color: Vec3::ONE,
            metallic: 1.0,
            roughness: 1.0,
            specular: 1.0,
            specular_color: Vec3::ONE,
            transmission: 0.0,
            ior: 1.5,
            clearcoat: 0.0,
            clearcoat_roughness: 0.0,
            clearcoat_normal: Vec3::ZERO,
            sheen_color: Vec3::ZERO,
            sheen_roughness: 0.0,
            anisotropy: 0.0,
            anisotropy_direction: Vec3::ZERO,
            iridescence: 0.0,
            iridescence_ior: crate::iridescence::DEFAULT_IOR,
            iridescence_thickness: 0.0,
        }
    }
}

impl BsdfParams {
    /// The material's factors, ignoring textures (callers with UVs multiply textures in).
    pub fn from_material(m: &Material) -> BsdfParams {
        BsdfParams {
            base_color: m.base_color.truncate(),
            metallic: m.metallic,
            roughness: m.roughness,
            specular: m.specular,
            specular_color: m.specular_color,
            transmission: m.transmission,
            ior: m.ior,
            clearcoat: m.clearcoat.map_or(0.0, |c| c.factor),
            clearcoat_roughness: m.clearcoat.map_or(0.0, |c| c.roughness),
            // The coat's normal map needs the surface's tangent frame too.
            clearcoat_normal: Vec3::ZERO,
            sheen_color: m.sheen.map_or(Vec3::ZERO, |s| s.color),
            sheen_roughness: m.sheen.map_or(0.0, |s| s.roughness),
            // The direction needs the surface's tangent frame ([`crate::surface`]).
            anisotropy: 0.0,
            anisotropy_direction: Vec3::ZERO,
            iridescence: m.iridescence.map_or(0.0, |i| i.factor),
            iridescence_ior: m
                .iridescence
                .map_or(crate::iridescence::DEFAULT_IOR, |i| i.ior),
            iridescence_thickness: m.iridescence.map_or(0.0, |i| i.thickness_max),
        }
    }
}

/// Which lobe produced a sample.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Lobe {
    Diffuse,
    GlossyReflection,
    /// The clear coat's mirror reflection (its rough reflection is `GlossyReflection`).
    CoatReflection,
    /// The sheen layer's broad, grazing reflection.
    Sheen,
    SpecularReflection,
    SpecularTransmission,
    GlossyTransmission,
}

/// One sampled direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BsdfSample {
    /// Sampled direction (unit, world space), toward the light / next vertex.
    pub wi: Vec3,
    /// For non-delta lobes the full BSDF value `eval(wo, wi)` (no cosine). For delta lobes
    /// the weight such that `f * |wi . n| / pdf` is the throughput factor (`n` the shading
    /// normal given to [`Bsdf::new`]).
    pub f: Vec3,
    /// For non-delta lobes the solid-angle density `pdf(wo, wi)` of [`Bsdf::sample`]
    /// (all non-delta lobes combined); for delta lobes the discrete probability of the lobe.
    pub pdf: f32,
    pub lobe: Lobe,
    pub delta: bool,
}

/// The BSDF at one shading point. Cheap to build; holds no references.
#[derive(Clone, Copy, Debug)]
pub struct Bsdf {
    /// Shading normal as passed (unit): the cosine of delta samples refers to it.
    n_in: Vec3,
    /// Shading normal flipped to `ng`'s side.
    n: Vec3,
    /// Geometric normal as passed: its side is the outside of a transmissive object.
    ng: Vec3,
    valid: bool,
    base: Vec3,
    metallic: f32,
    roughness: f32,
    specular: f32,
    /// GGX alpha, clamped to >= [`MIN_ALPHA`]; with anisotropy, along its direction.
    alpha: f32,
    /// GGX alpha across the anisotropy direction (`alpha` when isotropic).
    alpha_b: f32,
    /// Anisotropic: the frame's tangent follows `aniso_t` and the GGX lobe is
    /// `(alpha, alpha_b)`. Isotropic materials keep the functions (and bits) they had.
    aniso: bool,
    aniso_t: Vec3,
    /// Dielectric F0: `min(((ior-1)/(ior+1))^2 * specular_color, 1)`.
    f0: Vec3,
    /// Refraction index used for bending (>= 1).
    eta: f32,
    /// `base (1-metallic) (1-transmission)`.
    diffuse_tint: Vec3,
    /// `base (1-metallic) transmission`.
    trans_tint: Vec3,
    /// Maximal reflectance (at grazing): `(1-metallic) specular + metallic`.
    refl_max: f32,
    has_refl: bool,
    transmissive: bool,
    refl_delta: bool,
    trans_delta: bool,
    /// Clear coat strength (0: none).
    coat: f32,
    /// Coat GGX alpha, clamped to >= [`MIN_ALPHA`].
    coat_alpha: f32,
    coat_roughness: f32,
    coat_delta: bool,
    /// The coat's own shading normal, on `ng`'s side; `None`: the coat uses `n` (and
    /// every function keeps the bits it had before coat normals existed).
    coat_n: Option<Vec3>,
    /// Sheen colour (black: none), its largest channel and its roughness.
    sheen: Vec3,
    sheen_max: f32,
    sheen_roughness: f32,
    /// Thin-film strength (0: none; also 0 when the film has no thickness), the film's
    /// index and thickness (nm).
    irid: f32,
    irid_ior: f32,
    irid_thickness: f32,
    /// Only the diffuse lobe: no dielectric or metal reflection (`specular` and
    /// `metallic` 0), no transmission, coat or sheen. [`Bsdf::at`] and
    /// [`BsdfAt::eval_pdf`] then skip the layers' Fresnel weights and lobe selection,
    /// whose values are known (base scale 1, diffuse probability 1 or 0): the bits are
    /// those of the general path (test `lambert_fast_path_gives_the_general_bits`).
    lambert: bool,
}

/// Local shading frame for one `wo`: `n` is the shading normal on `wo`'s side.
#[derive(Clone, Copy, Debug)]
struct Frame {
    t: Vec3,
    b: Vec3,
    n: Vec3,
    /// Geometric normal on `wo`'s side.
    ng: Vec3,
    /// `eta(wi side) / eta(wo side)` for refraction.
    etap: f32,
    /// `wo` is on the side `ng` (as passed) points to: the outside of a transmissive
    /// object, where its clear coat is.
    outside: bool,
}

impl Frame {
    fn local(&self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.t), v.dot(self.b), v.dot(self.n))
    }

    fn world(&self, v: Vec3) -> Vec3 {
        self.t * v.x + self.b * v.y + self.n * v.z
    }
}

/// Lobe weights for one microfacet cosine `c = wo . m`.
#[derive(Clone, Copy, Debug)]
struct Weights {
    /// Reflection Fresnel (dielectric + metal), RGB.
    refl: Vec3,
    /// `1 - specular max(F_d)`: what the dielectric layer leaves to the base.
    base_scale: f32,
    /// Transmission weight (0 on total internal reflection), RGB.
    trans: Vec3,
}

/// Lobe selection probabilities for one `wo`.
#[derive(Clone, Copy, Debug)]
struct Selection {
    p_diffuse: f32,
    /// Probability of the clear coat's reflection.
    p_coat: f32,
    /// Probability of the sheen lobe.
    p_sheen: f32,
    /// Probability of the specular group (reflection + transmission).
    p_spec: f32,
    /// Reflection-vs-transmission split at the macro normal, used when transmission is delta.
    pr_macro: f32,
}

impl Bsdf {
    /// `n`: shading normal (unit), `ng`: geometric normal (unit), both may face either side;
    /// the BSDF orients itself to `wo`. For transmission the side `ng` points to is the
    /// outside (ior 1): pass the triangle's unflipped (winding) geometric normal, e.g.
    /// `if surf.front { surf.ng } else { -surf.ng }`; a normal flipped toward the ray makes
    /// every hit look like an entry (no exit refraction, no total internal reflection).
    ///
    /// Parameters are sanitised: factors clamped to [0, 1] (NaN becomes 0), `specular_color`
    /// clamped to be non-negative, a NaN `ior` becomes 1.5; `ior` 0 or inf give F0 = 1 (the
    /// spec-gloss conversion of `KHR_materials_specular`) and bend rays with ior 1 resp.
    /// [`MAX_IOR`].
    pub fn new(params: &BsdfParams, n: Vec3, ng: Vec3) -> Bsdf {
        let (n_u, ng_u) = (unit(n), unit(ng));
        let (valid, n_in, ng) = match (n_u, ng_u) {
            (Some(n), Some(ng)) => (true, n, ng),
            (Some(n), None) => (true, n, n),
            (None, Some(ng)) => (true, ng, ng),
            (None, None) => (false, Vec3::Z, Vec3::Z),
        };
        let n = if n_in.dot(ng) < 0.0 { -n_in } else { n_in };

        let base = sat3(params.base_color);
        let metallic = sat(params.metallic);
        let roughness = sat(params.roughness);
        let specular = sat(params.specular);
        let specular_color = params
            .specular_color
            .to_array()
            .map(|c| if c >= 0.0 { c.min(1e6) } else { 0.0 });
        let transmission = sat(params.transmission);
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
        let f0 = (Vec3::from_array(specular_color) * f0_ior).min(Vec3::ONE);
        let eta = if ior.is_nan() {
            1.5
        } else {
            ior.clamp(1.0, MAX_IOR)
        };

        let a_iso = roughness * roughness;
        let strength = sat(params.anisotropy);
        let aniso_t = unit(params.anisotropy_direction).unwrap_or(Vec3::ZERO);
        let aniso = strength > 0.0 && aniso_t != Vec3::ZERO;
        // alpha_t = mix(alpha, 1, strength^2), as the extension gives it.
        let a = if aniso {
            a_iso + (1.0 - a_iso) * strength * strength
        } else {
            a_iso
        };
        let dielectric = (1.0 - metallic) * specular;
        let diffuse_tint = base * ((1.0 - metallic) * (1.0 - transmission));
        let trans_tint = base * ((1.0 - metallic) * transmission);
        let refl_delta = a < DELTA_ALPHA;
        let coat = sat(params.clearcoat);
        let coat_roughness = sat(params.clearcoat_roughness);
        let coat_a = coat_roughness * coat_roughness;
        let coat_n = unit(params.clearcoat_normal)
            .filter(|_| coat > 0.0)
            .map(|c| if c.dot(ng) < 0.0 { -c } else { c });
        let sheen = sat3(params.sheen_color);
        let irid_thickness = if params.iridescence_thickness.is_finite() {
            params.iridescence_thickness.clamp(0.0, 1e6)
        } else {
            0.0
        };
        // A film of no thickness is no film (the Sample Viewer drops it too).
        let irid = if irid_thickness > 0.0 {
            sat(params.iridescence)
        } else {
            0.0
        };
        let irid_ior = if params.iridescence_ior.is_finite() {
            params.iridescence_ior.clamp(1.0, MAX_IOR)
        } else {
            crate::iridescence::DEFAULT_IOR
        };
        Bsdf {
            n_in,
            n,
            ng,
            valid,
            base,
            metallic,
            roughness,
            specular,
            alpha: a.max(MIN_ALPHA),
            alpha_b: if aniso {
                a_iso.max(MIN_ALPHA)
            } else {
                a.max(MIN_ALPHA)
            },
            aniso,
            aniso_t,
            f0,
            eta,
            diffuse_tint,
            trans_tint,
            refl_max: dielectric + metallic,
            has_refl: dielectric > 0.0 || metallic > 0.0,
            transmissive: trans_tint.max_element() > 0.0,
            refl_delta,
            trans_delta: refl_delta || eta - 1.0 < IOR_PASS_THROUGH_EPS,
            coat,
            coat_alpha: coat_a.max(MIN_ALPHA),
            coat_roughness,
            coat_delta: coat_a < DELTA_ALPHA,
            coat_n,
            sheen,
            sheen_max: sheen.max_element(),
            sheen_roughness: sat(params.sheen_roughness),
            irid,
            irid_ior,
            irid_thickness,
            lambert: !(dielectric > 0.0 || metallic > 0.0)
                && trans_tint.max_element() <= 0.0
                && coat <= 0.0
                && sheen.max_element() <= 0.0,
        }
    }

    /// `f(wo, wi)` of the non-delta lobes, without the cosine.
    pub fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        self.eval_pdf(wo, wi).0
    }

    /// Solid-angle density with which [`Bsdf::sample`] produces `wi` through its non-delta
    /// lobes: `sum over lobes of p_lobe * pdf_lobe`.
    pub fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        self.eval_pdf(wo, wi).1
    }

    /// [`Bsdf::eval`] and [`Bsdf::pdf`] in one call.
    pub fn eval_pdf(&self, wo: Vec3, wi: Vec3) -> (Vec3, f32) {
        self.at(wo).map_or((Vec3::ZERO, 0.0), |at| at.eval_pdf(wi))
    }

    /// Samples a direction: `u_lobe` picks the lobe, `u` the direction within it.
    /// Returns `None` for an absorbed/invalid sample (below the surface, total internal
    /// reflection of a sampled refraction, zero pdf or zero value).
    pub fn sample(&self, wo: Vec3, u_lobe: f32, u: Vec2) -> Option<BsdfSample> {
        self.at(wo)?.sample(u_lobe, u)
    }

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
                self.coat * coat_fresnel(coat_wo_l.z),
            )
        } else {
            (1.0, 0.0)
        };
        let sheen_on = self.sheen_on(&fr);
        let (sheen_att_o, sheen_w) = if sheen_on {
            let e = crate::sheen::albedo(wo_l.z, self.sheen_roughness);
            (1.0 - self.sheen_max * e, lum(self.sheen) * e * att_o)
        } else {
            (1.0, 0.0)
        };
        let sel = self.selection_from(&w_o, att_o * sheen_att_o, coat_w, sheen_w);
        let a2 = self.alpha * self.alpha;
        let coat_a2 = self.coat_alpha * self.coat_alpha;
        let coat_lambda_o = if coat_on && !self.coat_delta {
            ggx_lambda(coat_wo_l, coat_a2)
        } else {
            0.0
        };
        let microfacets =
            (self.has_refl && !self.refl_delta) || (self.transmissive && !self.trans_delta);
        let lambda_o = if microfacets {
            self.base_lambda(wo_l, a2)
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
        let wd = lum(self.diffuse_tint);
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
            a2: self.alpha * self.alpha,
            lambda_o: 0.0,
            coat_on: false,
            att_o: 1.0,
            coat_w: 0.0,
            coat_a2: self.coat_alpha * self.coat_alpha,
            coat_lambda_o: 0.0,
            coat_fr: None,
            coat_wo_l: wo_l,
            sheen_on: false,
            sheen_att_o: 1.0,
        }
    }

    /// The base GGX distribution at local microfacet normal `m` (`a2` = alpha^2).
    fn base_d(&self, m: Vec3, a2: f32) -> f32 {
        if self.aniso {
            ggx_d_aniso(m, self.alpha, self.alpha_b)
        } else {
            ggx_d(m, a2)
        }
    }

    /// Smith Λ of the base GGX distribution for local direction `w`.
    fn base_lambda(&self, w: Vec3, a2: f32) -> f32 {
        if self.aniso {
            ggx_lambda_aniso(w, self.alpha, self.alpha_b)
        } else {
            ggx_lambda(w, a2)
        }
    }

    /// Whether the sheen faces `fr`'s `wo` (the same sides as the clear coat).
    fn sheen_on(&self, fr: &Frame) -> bool {
        self.sheen_max > 0.0 && (!self.transmissive || fr.outside)
    }

    /// What the sheen passes to the layers under it at cosine `c`:
    /// `1 - max(sheen colour) E(c)`, with `E` the white sheen lobe's albedo.
    fn sheen_att(&self, c: f32) -> f32 {
        1.0 - self.sheen_max * crate::sheen::albedo(c, self.sheen_roughness)
    }

    /// Whether the clear coat faces `fr`'s `wo`: always for opaque materials (either side
    /// is their outside), only from the outside for transmissive ones.
    fn coat_on(&self, fr: &Frame) -> bool {
        self.coat > 0.0 && (!self.transmissive || fr.outside)
    }

    /// What the clear coat passes to the layers under it at cosine `c`: `1 - coat F_c(c)`.
    fn coat_att(&self, c: f32) -> f32 {
        1.0 - self.coat * coat_fresnel(c)
    }

    /// The clear coat's own frame for the base frame `fr` and local `wo_l`, and `wo` in
    /// it, when the coat faces `wo` and has a normal of its own: its normal on `wo`'s
    /// side, or the geometric normal when `wo` is below it (as [`Bsdf::frame`] does for
    /// the shading normal). Otherwise `None` and `wo_l`: the coat uses `fr`.
    fn coat_frame(&self, fr: &Frame, wo_l: Vec3) -> (Option<Frame>, Vec3) {
        let wo = fr.world(wo_l);
        let cf = self.coat_n.filter(|_| self.coat_on(fr)).and_then(|nc| {
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
    fn coat_cos(&self, w: Vec3, fallback: f32) -> f32 {
        self.coat_n.map_or(fallback, |nc| w.dot(nc).abs())
    }

    /// The coat's attenuation of a transmitted path: the coat is crossed once, on the
    /// outside, at the outside direction's cosine (`cos_out`, the macro cosine of
    /// whichever of `wo` and `wi` is outside; `coat_cos_out` the same to the coat's
    /// normal). 1 without a coat.
    fn coat_att_transmitted(&self, cos_out: f32, coat_cos_out: f32) -> f32 {
        let coat = if self.coat > 0.0 {
            self.coat_att(coat_cos_out.abs())
        } else {
            1.0
        };
        if self.sheen_max > 0.0 {
            coat * self.sheen_att(cos_out.abs())
        } else {
            coat
        }
    }

    /// True when the material has a (non-zero) Lambert lobe.
    pub fn has_diffuse(&self) -> bool {
        self.valid && self.diffuse_tint.max_element() > 0.0
    }

    /// True when the material has a reflection lobe (metal or dielectric specular, or a
    /// clear coat). Unlike [`Material::has_specular`] a black `specular_color` still
    /// counts: glTF keeps F90 = `specular`, so grazing reflection remains.
    pub fn has_specular_lobe(&self) -> bool {
        self.valid && (self.has_refl || self.coat > 0.0)
    }

    /// True when the material transmits (non-zero transmission tint).
    pub fn has_transmission(&self) -> bool {
        self.valid && self.transmissive
    }

    /// Every lobe is delta (perfect mirror/glass): light sampling cannot contribute.
    /// False for a material with no lobe at all (black Lambert).
    pub fn is_delta_only(&self) -> bool {
        let coat = self.coat > 0.0;
        let any = self.has_refl || self.transmissive || coat;
        self.valid
            && any
            && !self.has_diffuse()
            && !(self.sheen_max > 0.0)
            && (!self.has_refl || self.refl_delta)
            && (!self.transmissive || self.trans_delta)
            && (!coat || self.coat_delta)
    }

    /// `base_color (1-metallic) (1-transmission)`, for ambient/AO-style shading.
    pub fn diffuse_albedo(&self) -> Vec3 {
        self.diffuse_tint
    }

    /// For Whitted: the perfect mirror direction and its weight (the Fresnel-weighted
    /// specular reflectance at `wo`, no cosine), if the reflection lobe is smooth enough
    /// (roughness < [`WHITTED_MAX_ROUGHNESS`]; rougher lobes are left to the diffuse/ambient
    /// term) and the mirror direction is above the geometric surface.
    pub fn mirror(&self, wo: Vec3) -> Option<(Vec3, Vec3)> {
        // An anisotropic lobe is as rough as its stretched axis.
        let stretched = if self.aniso { self.alpha.sqrt() } else { 0.0 };
        let base_ok = self.has_refl && self.roughness.max(stretched) < WHITTED_MAX_ROUGHNESS;
        let coat_ok = self.coat > 0.0 && self.coat_roughness < WHITTED_MAX_ROUGHNESS;
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
            (a * a, self.coat * coat_fresnel(coat_wo_l.z))
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

    /// For Whitted: the refracted direction through the macro surface and its weight (the
    /// transmission weight `(1 - specular max F) base (1-metallic) transmission`, no
    /// cosine). Returned for any roughness (rough glass is traced as smooth glass rather
    /// than rendered black); `None` when opaque or on total internal reflection.
    pub fn refraction(&self, wo: Vec3) -> Option<(Vec3, Vec3)> {
        if !self.transmissive {
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
        let trans = w.trans * self.coat_att_transmitted(cos_out, self.coat_cos(out, cos_out));
        (trans.max_element() > 0.0 && trans.is_finite()).then_some((wi, trans))
    }

    /// The local frame for `wo`, or `None` when `wo` is degenerate or tangent to the surface.
    fn frame(&self, wo: Vec3) -> Option<(Frame, Vec3)> {
        if !self.valid {
            return None;
        }
        let wo = unit(wo)?;
        let cg = wo.dot(self.ng);
        if !(cg.abs() >= COS_EPS) {
            return None;
        }
        let outside = cg > 0.0;
        let (ng, mut n) = if outside {
            (self.ng, self.n)
        } else {
            (-self.ng, -self.n)
        };
        if wo.dot(n) < COS_EPS {
            // wo below the shading hemisphere: fall back to the geometric normal.
            n = ng;
        }
        // An anisotropic lobe is stretched along its direction: the frame follows it.
        let along = unit(self.aniso_t - n * n.dot(self.aniso_t)).filter(|_| self.aniso);
        let (t, b) = match along {
            Some(t) => (t, n.cross(t)),
            None => n.any_orthonormal_pair(),
        };
        let etap = if outside { self.eta } else { 1.0 / self.eta };
        let fr = Frame {
            t,
            b,
            n,
            ng,
            etap,
            outside,
        };
        let wo_l = fr.local(wo);
        if !(wo_l.z >= COS_EPS) {
            return None;
        }
        Some((fr, wo_l))
    }

    /// Cosine on the outer (less dense) side for a wo-side cosine `c`; `None` on total
    /// internal reflection. Opaque materials have no inside: always `c`.
    fn outer_cos(&self, c: f32, etap: f32) -> Option<f32> {
        if !self.transmissive || etap >= 1.0 {
            return Some(c);
        }
        let sin2_t = (1.0 - c * c).max(0.0) / (etap * etap);
        if sin2_t >= 1.0 {
            None
        } else {
            Some((1.0 - sin2_t).sqrt())
        }
    }

    fn weights(&self, c: f32, etap: f32) -> Weights {
        let c = c.clamp(0.0, 1.0);
        let outer = self.outer_cos(c, etap);
        let mut fd = match outer {
            Some(co) => self.f0 + (Vec3::ONE - self.f0) * schlick_w(co),
            None => Vec3::ONE,
        };
        let mut fm = self.base + (Vec3::ONE - self.base) * schlick_w(c);
        if self.irid > 0.0 {
            // KHR_materials_iridescence: F = mix(F_schlick, F_film, factor), for the
            // dielectric (at the outer cosine, like its Schlick term; total internal
            // reflection stays total) and for the metal. Both stay in [0, 1], so the
            // layering below conserves energy as without the film.
            if let Some(co) = outer {
                fd = fd.lerp(self.film(co, self.f0), self.irid);
            }
            if self.metallic > 0.0 {
                fm = fm.lerp(self.film(c, self.base), self.irid);
            }
        }
        let refl = fd * ((1.0 - self.metallic) * self.specular) + fm * self.metallic;
        let base_scale = (1.0 - self.specular * fd.max_element()).max(0.0);
        let trans = if outer.is_some() {
            self.trans_tint * base_scale
        } else {
            Vec3::ZERO
        };
        Weights {
            refl,
            base_scale,
            trans,
        }
    }

    /// The thin film's Fresnel reflectance at cosine `c` over a base of normal-incidence
    /// reflectance `f0`.
    fn film(&self, c: f32, f0: Vec3) -> Vec3 {
        crate::iridescence::fresnel(1.0, self.irid_ior, c, self.irid_thickness, f0)
    }

    /// Probability of reflecting (vs refracting) on a microfacet with weights `w`.
    fn pr(&self, w: &Weights) -> f32 {
        let r = if self.has_refl { lum(w.refl) } else { 0.0 };
        let t = lum(w.trans);
        if t <= 0.0 {
            1.0
        } else if r <= 0.0 {
            0.0
        } else {
            r / (r + t)
        }
    }

    /// Lobe selection from the lobe weights `w` at the macro normal (luminance), with
    /// floors; `att_o` is what a clear coat passes to the lobes under it and `coat_w` the
    /// coat's own reflectance (1 and 0 without a coat, which leave the values unchanged).
    fn selection_from(&self, w: &Weights, att_o: f32, coat_w: f32, sheen_w: f32) -> Selection {
        let wd = lum(self.diffuse_tint) * w.base_scale.max(SELECT_FLOOR) * att_o;
        let r0 = if self.has_refl {
            lum(w.refl).max(SELECT_FLOOR * self.refl_max)
        } else {
            0.0
        };
        let r = r0 * att_o;
        let t0 = lum(w.trans);
        let t = if self.transmissive && !self.trans_delta {
            // Rough refraction may succeed on microfacets even past the macro critical angle.
            t0.max(SELECT_FLOOR * lum(self.trans_tint))
        } else {
            t0
        } * att_o;
        let c = if coat_w > 0.0 || att_o < 1.0 {
            coat_w.max(SELECT_FLOOR * self.coat)
        } else {
            0.0
        };
        let sh = if sheen_w > 0.0 {
            sheen_w.max(SELECT_FLOOR * lum(self.sheen))
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

    /// A delta sample with throughput `weight / prob`.
    fn delta_sample(&self, wi: Vec3, weight: Vec3, prob: f32, lobe: Lobe) -> Option<BsdfSample> {
        let wi = unit(wi)?;
        let cos = wi.dot(self.n_in).abs();
        if !(cos >= COS_EPS) || !(prob > 0.0) || !(weight.max_element() > 0.0) {
            return None;
        }
        let f = weight / cos;
        if !f.is_finite() || !prob.is_finite() {
            return None;
        }
        Some(BsdfSample {
            wi,
            f,
            pdf: prob,
            lobe,
            delta: true,
        })
    }
}

/// A [`Bsdf`] seen from one outgoing direction `wo` ([`Bsdf::at`]). Light sampling and
/// BSDF sampling at a hit share the frame, the Fresnel weights at `wo` and the lobe
/// selection, instead of rebuilding them for every evaluation; the values are those the
/// per-call methods of [`Bsdf`] compute, bit for bit.
#[derive(Clone, Copy, Debug)]
pub struct BsdfAt<'a> {
    bsdf: &'a Bsdf,
    fr: Frame,
    wo_l: Vec3,
    /// Lobe weights at the macro normal (`c = cos_o`).
    w_o: Weights,
    sel: Selection,
    /// GGX `alpha^2`.
    a2: f32,
    /// Smith Λ of `wo`, for the microfacet lobes (0 when there are none).
    lambda_o: f32,
    /// The clear coat faces `wo` ([`Bsdf::coat_on`]).
    coat_on: bool,
    /// What the coat passes to the lobes under it at `wo` (1 without a coat).
    att_o: f32,
    /// The coat's reflectance at `wo`: `coat F_c(cos_o)` (0 without a coat).
    coat_w: f32,
    /// Coat GGX `alpha^2`, and Smith Λ of `wo` under it (0 when the coat is delta).
    coat_a2: f32,
    coat_lambda_o: f32,
    /// The coat's own frame when it has a normal of its own (`None`: it uses `fr`), and
    /// `wo` in it.
    coat_fr: Option<Frame>,
    coat_wo_l: Vec3,
    /// The sheen faces `wo` ([`Bsdf::sheen_on`]), and what it passes down at `wo`.
    sheen_on: bool,
    sheen_att_o: f32,
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
        let wi_l = fr.local(wi);
        let gi = wi.dot(fr.ng);
        let sel = &self.sel;
        let a2 = self.a2;
        let (cos_o, cos_i) = (wo_l.z, wi_l.z);
        let mut f = Vec3::ZERO;
        let mut pdf = 0.0;

        if b.lambert {
            // The general path below with its known factors (see `Bsdf::at_lambert`):
            // base scale and attenuation 1, no other lobe; the half vector it checks
            // always exists here (both cosines are at least COS_EPS).
            if !(cos_i >= COS_EPS && gi > 0.0) {
                return zero;
            }
            let f = Vec3::ZERO + b.diffuse_tint * FRAC_1_PI;
            let pdf = 0.0 + sel.p_diffuse * cos_i * FRAC_1_PI;
            return if f.is_finite() && pdf.is_finite() && pdf >= 0.0 {
                (f.max(Vec3::ZERO), pdf)
            } else {
                zero
            };
        }

        if cos_i >= COS_EPS && gi > 0.0 {
            let Some(h) = unit(wo_l + wi_l) else {
                return zero;
            };
            let c = wo_l.dot(h);
            // The base is attenuated by the dielectric layer's Fresnel on the way in and out
            // (not at VdotH as in glTF Appendix B, which gains energy under a smooth layer).
            let base_scale = self.w_o.base_scale * b.weights(cos_i, fr.etap).base_scale;
            // A clear coat attenuates what lies under it the same way, in and out. (With
            // a normal of its own, `wi` may lie below the coat's normal though above the
            // surface: its cosine's magnitude is used, so no direction the base lobes
            // sample is blacked out.)
            let coat_wi_l = self.coat_fr.map_or(wi_l, |cf| cf.local(wi));
            let coat_att = if self.coat_on {
                self.att_o * b.coat_att(coat_wi_l.z.abs())
            } else {
                1.0
            };
            // Under the sheen, what is left by its albedo on the more reflective side
            // (glTF's min of both, which keeps the sum reciprocal and below 1).
            let att = if self.sheen_on {
                coat_att * self.sheen_att_o.min(b.sheen_att(cos_i))
            } else {
                coat_att
            };
            f += b.diffuse_tint * (base_scale * FRAC_1_PI) * att;
            pdf += sel.p_diffuse * cos_i * FRAC_1_PI;
            if self.sheen_on {
                let lobe = crate::sheen::lobe(cos_o, cos_i, h.z, b.sheen_roughness);
                f += b.sheen * (lobe * coat_att);
                pdf += sel.p_sheen * cos_i * FRAC_1_PI;
            }
            // With a normal of its own the coat's lobe lives in its frame; its value is
            // divided by the shading cosine the integrator multiplies by (not the coat's),
            // so `f cos_i / pdf` stays the coat's `F G2 / G1`.
            let coat_h = match self.coat_fr {
                Some(_) => unit(self.coat_wo_l + coat_wi_l),
                None => Some(h),
            };
            if let Some(coat_h) = coat_h
                && self.coat_on
                && !b.coat_delta
                && coat_wi_l.z > 0.0
            {
                let coat_cos_o = self.coat_wo_l.z;
                let d = ggx_d(coat_h, self.coat_a2);
                let lo = self.coat_lambda_o;
                let li = ggx_lambda(coat_wi_l, self.coat_a2);
                let g2 = 1.0 / (1.0 + lo + li);
                let g1 = 1.0 / (1.0 + lo);
                f += Vec3::splat(b.coat * coat_fresnel(c) * d * g2 / (4.0 * coat_cos_o * cos_i));
                pdf += sel.p_coat * g1 * d / (4.0 * coat_cos_o);
            }
            if b.has_refl && !b.refl_delta {
                let w = b.weights(c, fr.etap);
                let d = b.base_d(h, a2);
                let lo = self.lambda_o;
                let li = b.base_lambda(wi_l, a2);
                let g2 = 1.0 / (1.0 + lo + li);
                let g1 = 1.0 / (1.0 + lo);
                f += w.refl * (d * g2 / (4.0 * cos_o * cos_i)) * att;
                let pr = if b.trans_delta {
                    sel.pr_macro
                } else {
                    b.pr(&w)
                };
                // VNDF pdf G1 D (wo.h) / cos_o times the reflection Jacobian 1 / (4 wo.h).
                pdf += sel.p_spec * pr * g1 * d / (4.0 * cos_o);
            }
        } else if cos_i <= -COS_EPS && gi < 0.0 && b.transmissive && !b.trans_delta {
            // Walter et al. 2007: generalized half vector, facing wo's side.
            let etap = fr.etap;
            let Some(mut m) = unit(wi_l * etap + wo_l) else {
                return zero;
            };
            if m.z < 0.0 {
                m = -m;
            }
            let c_o = wo_l.dot(m);
            let c_i = wi_l.dot(m);
            if !(c_o > 0.0 && c_i < 0.0) {
                return zero;
            }
            let w = b.weights(c_o, etap);
            let denom = c_i + c_o / etap;
            let den2 = denom * denom;
            if !(den2 > 1e-12) || w.trans.max_element() <= 0.0 {
                return zero;
            }
            let d = b.base_d(m, a2);
            let lo = self.lambda_o;
            let li = b.base_lambda(wi_l, a2);
            let g2 = 1.0 / (1.0 + lo + li);
            let g1 = 1.0 / (1.0 + lo);
            let cos_out = if fr.outside { cos_o } else { cos_i };
            let out = if fr.outside { fr.world(wo_l) } else { wi };
            f += w.trans
                * (d * g2 * (-c_i) * c_o / (-cos_i * cos_o * den2))
                * b.coat_att_transmitted(cos_out, b.coat_cos(out, cos_out));
            let vndf = g1 * c_o * d / cos_o;
            pdf += sel.p_spec * (1.0 - b.pr(&w)) * vndf * (-c_i) / den2;
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
        let (fr, wo_l) = (&self.fr, self.wo_l);
        let sel = &self.sel;
        let ul = sanitize_u(u_lobe);
        let u = Vec2::new(sanitize_u(u.x), sanitize_u(u.y));
        if !(sel.p_diffuse + sel.p_spec + sel.p_coat + sel.p_sheen > 0.0) {
            return None;
        }
        let layers = sel.p_coat + sel.p_sheen;
        if ul < sel.p_diffuse || (sel.p_spec <= 0.0 && !(layers > 0.0)) {
            let wi_l = cosine_hemisphere(u);
            return self.finish(fr.world(wi_l), Lobe::Diffuse);
        }
        let ul = ul - sel.p_diffuse;
        if ul < sel.p_coat || (sel.p_spec <= 0.0 && sel.p_sheen <= 0.0) {
            return self.sample_coat(u);
        }
        if ul < layers || sel.p_spec <= 0.0 {
            let wi_l = cosine_hemisphere(u);
            return self.finish(fr.world(wi_l), Lobe::Sheen);
        }
        // Reuse the lobe number for the reflection/transmission split.
        let u2 = ((ul - layers) / sel.p_spec).clamp(0.0, ONE_MINUS_EPS);

        if b.refl_delta || (b.trans_delta && u2 >= sel.pr_macro) {
            let w = &self.w_o;
            if b.refl_delta && u2 < sel.pr_macro {
                let wi = fr.world(Vec3::new(-wo_l.x, -wo_l.y, wo_l.z));
                if wi.dot(fr.ng) <= 0.0 {
                    return None;
                }
                // Under a coat the mirror is crossed twice at the same angle (to the
                // coat's own normal, the angles in and out may differ).
                let att_i = match self.coat_fr {
                    Some(cf) => b.coat_att(cf.local(wi).z.abs()),
                    None => self.att_o,
                };
                return b.delta_sample(
                    wi,
                    w.refl * (self.att_o * att_i * self.sheen_att_o),
                    sel.p_spec * sel.pr_macro,
                    Lobe::SpecularReflection,
                );
            }
            let wi_l = refract(wo_l, Vec3::Z, fr.etap)?;
            let wi = fr.world(wi_l);
            if wi.dot(fr.ng) >= 0.0 {
                return None;
            }
            let cos_out = if fr.outside { wo_l.z } else { wi_l.z };
            let out = if fr.outside { fr.world(wo_l) } else { wi };
            return b.delta_sample(
                wi,
                w.trans * b.coat_att_transmitted(cos_out, b.coat_cos(out, cos_out)),
                sel.p_spec * (1.0 - sel.pr_macro),
                Lobe::SpecularTransmission,
            );
        }

        let m = sample_vndf(wo_l, b.alpha, b.alpha_b, u)?;
        let c = wo_l.dot(m);
        if !(c > 0.0) {
            return None;
        }
        let reflect = if b.trans_delta {
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

    /// A sample of the clear coat: its mirror when smooth, else a GGX reflection through
    /// the coat's visible normals.
    fn sample_coat(&self, u: Vec2) -> Option<BsdfSample> {
        let b = self.bsdf;
        // In the coat's own frame when it has a normal of its own.
        let (fr, wo_l) = (self.coat_fr.as_ref().unwrap_or(&self.fr), self.coat_wo_l);
        if !self.coat_on {
            return None;
        }
        if b.coat_delta {
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
        let m = sample_vndf(wo_l, b.coat_alpha, b.coat_alpha, u)?;
        let c = wo_l.dot(m);
        if !(c > 0.0) {
            return None;
        }
        self.finish(fr.world(m * (2.0 * c) - wo_l), Lobe::GlossyReflection)
    }

    /// A non-delta sample: value and pdf are those of `eval`/`pdf`, so MIS is consistent.
    /// A direction that lands on the wrong side for its lobe (a microfacet reflection below
    /// the surface, a rough refraction back above it) is rejected: `pdf` would not count the
    /// technique that produced it, and accepting it would bias the estimate upward.
    fn finish(&self, wi: Vec3, lobe: Lobe) -> Option<BsdfSample> {
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

/// Unit vector or `None` for zero-length / non-finite input.
fn unit(v: Vec3) -> Option<Vec3> {
    let l = v.length();
    if l.is_finite() && l > 1e-20 {
        Some(v / l)
    } else {
        None
    }
}

/// `x` clamped to [0, 1], NaN to 0 (`-0.0` stays `-0.0`, as `clamp` leaves it): one
/// compare and one `min`, where `is_nan` and `clamp` took three branches.
fn sat(x: f32) -> f32 {
    if x >= 0.0 { x.min(1.0) } else { 0.0 }
}

fn sat3(v: Vec3) -> Vec3 {
    Vec3::new(sat(v.x), sat(v.y), sat(v.z))
}

fn sanitize_u(x: f32) -> f32 {
    if x.is_nan() {
        0.0
    } else {
        x.clamp(0.0, ONE_MINUS_EPS)
    }
}

fn lum(c: Vec3) -> f32 {
    c.x * 0.2126 + c.y * 0.7152 + c.z * 0.0722
}

/// Fresnel reflectance of the clear coat (ior 1.5, so F0 = 0.04, as
/// `KHR_materials_clearcoat` fixes it) at cosine `c`, in glTF's Schlick form.
fn coat_fresnel(c: f32) -> f32 {
    0.04 + 0.96 * schlick_w(c)
}

/// Schlick's `(1 - c)^5`.
fn schlick_w(c: f32) -> f32 {
    let m = (1.0 - c).clamp(0.0, 1.0);
    let m2 = m * m;
    m2 * m2 * m
}

/// GGX normal distribution in the local frame, written with `x^2 + y^2 + a^2 z^2`
/// (= `cos^2 (a^2 - 1) + 1`) so it stays accurate for tiny alpha near the normal.
fn ggx_d(m: Vec3, a2: f32) -> f32 {
    if !(m.z > 0.0) {
        return 0.0;
    }
    let x = m.x * m.x + m.y * m.y + a2 * m.z * m.z;
    if !(x > 0.0) {
        return 0.0;
    }
    a2 / (PI * x * x)
}

/// Smith Λ for GGX.
fn ggx_lambda(w: Vec3, a2: f32) -> f32 {
    let z2 = w.z * w.z;
    if !(z2 > 1e-30) {
        return f32::INFINITY;
    }
    let t2 = (w.x * w.x + w.y * w.y) / z2;
    0.5 * ((1.0 + a2 * t2).sqrt() - 1.0)
}

/// Anisotropic GGX distribution with `ax` along the local x axis and `ay` along y.
fn ggx_d_aniso(m: Vec3, ax: f32, ay: f32) -> f32 {
    if !(m.z > 0.0) {
        return 0.0;
    }
    let (x, y) = (m.x / ax, m.y / ay);
    let k = x * x + y * y + m.z * m.z;
    if !(k > 0.0) {
        return 0.0;
    }
    1.0 / (PI * ax * ay * k * k)
}

/// Smith Λ for anisotropic GGX.
fn ggx_lambda_aniso(w: Vec3, ax: f32, ay: f32) -> f32 {
    let z2 = w.z * w.z;
    if !(z2 > 1e-30) {
        return f32::INFINITY;
    }
    let (x, y) = (ax * w.x, ay * w.y);
    0.5 * ((1.0 + (x * x + y * y) / z2).sqrt() - 1.0)
}

/// Heitz 2018, "Sampling the GGX Distribution of Visible Normals": a microfacet normal
/// distributed as `G1(wo) max(0, wo.m) D(m) / wo.z`, for alphas `ax` along local x and
/// `ay` along y (equal when isotropic). `wo.z > 0`.
fn sample_vndf(wo: Vec3, ax: f32, ay: f32, u: Vec2) -> Option<Vec3> {
    let vh = unit(Vec3::new(ax * wo.x, ay * wo.y, wo.z))?;
    let lensq = vh.x * vh.x + vh.y * vh.y;
    let t1 = if lensq > 0.0 {
        Vec3::new(-vh.y, vh.x, 0.0) / lensq.sqrt()
    } else {
        Vec3::X
    };
    let t2 = vh.cross(t1);
    let r = u.x.sqrt();
    let phi = TAU * u.y;
    let p1 = r * phi.cos();
    let s = 0.5 * (1.0 + vh.z);
    let p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * (r * phi.sin());
    let nh = t1 * p1 + t2 * p2 + vh * (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt();
    unit(Vec3::new(ax * nh.x, ay * nh.y, nh.z.max(0.0)))
}

/// Refracts `wo` (pointing away, `wo.m > 0`) through the interface with normal `m`;
/// `etap = eta(transmitted side) / eta(wo side)`. `None` on total internal reflection.
fn refract(wo: Vec3, m: Vec3, etap: f32) -> Option<Vec3> {
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

/// Cosine-weighted hemisphere direction around +z.
fn cosine_hemisphere(u: Vec2) -> Vec3 {
    let r = u.x.sqrt();
    let phi = TAU * u.y;
    Vec3::new(r * phi.cos(), r * phi.sin(), (1.0 - u.x).max(0.0).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// splitmix64: a tiny deterministic generator for the Monte Carlo tests.
    struct Rng(u64);

    impl Rng {
        fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }

        fn f32(&mut self) -> f32 {
            (self.next_u64() >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
        }

        fn vec2(&mut self) -> Vec2 {
            Vec2::new(self.f32(), self.f32())
        }

        fn sphere(&mut self) -> Vec3 {
            uniform_sphere(self.vec2())
        }

        /// The `i`-th of `side^2` jittered-stratified uniform sphere directions.
        fn sphere_strat(&mut self, i: usize, side: usize) -> Vec3 {
            let (a, b) = ((i % side) as f32, (i / side) as f32);
            let u = Vec2::new(
                (a + self.f32()) / side as f32,
                (b + self.f32()) / side as f32,
            );
            uniform_sphere(u.min(Vec2::splat(ONE_MINUS_EPS)))
        }
    }

    /// Bits of an `eval_pdf` answer, for exact comparisons.
    fn bits(fp: (Vec3, f32)) -> [u32; 4] {
        [fp.0.x, fp.0.y, fp.0.z, fp.1].map(f32::to_bits)
    }

    #[test]
    fn sat_is_nan_to_zero_then_clamp() {
        for x in [
            f32::NAN,
            -f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            -0.0,
            0.0,
            1.0,
            1.5,
            -2.0,
            0.25,
            f32::MIN_POSITIVE,
            1.0 - f32::EPSILON,
            -f32::MIN_POSITIVE,
        ] {
            let old = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) };
            assert_eq!(sat(x).to_bits(), old.to_bits(), "{x}");
        }
    }

    #[test]
    fn lambert_fast_path_gives_the_general_bits() {
        let mut rng = Rng(41);
        let bases = [
            Vec3::new(0.8, 0.8, 0.8),
            Vec3::new(0.9, 0.2, 0.05),
            Vec3::ZERO,
            Vec3::new(-0.0, 0.0, -0.0),
            Vec3::new(1e-30, 0.0, 0.0),
            Vec3::new(f32::NAN, 0.5, 2.0),
        ];
        let mut checked = 0;
        for (k, &base) in bases.iter().enumerate() {
            let params = BsdfParams {
                base_color: base,
                metallic: 0.0,
                specular: 0.0,
                roughness: 0.3,
                // Ignored without a reflective layer, but they must not change the bits.
                iridescence: 1.0,
                iridescence_thickness: 400.0,
                anisotropy: if k % 2 == 0 { 0.7 } else { 0.0 },
                anisotropy_direction: Vec3::X,
                ..BsdfParams::default()
            };
            for _ in 0..2000 {
                let n = rng.sphere();
                let ng = (n + rng.sphere() * 0.3).normalize_or(n);
                let fast = Bsdf::new(&params, n, ng);
                assert!(fast.lambert);
                let general = Bsdf {
                    lambert: false,
                    ..fast
                };
                let wo = rng.sphere();
                let (Some(a), Some(b)) = (fast.at(wo), general.at(wo)) else {
                    assert!(fast.at(wo).is_none() && general.at(wo).is_none());
                    continue;
                };
                for _ in 0..4 {
                    let wi = rng.sphere();
                    assert_eq!(
                        bits(a.eval_pdf(wi)),
                        bits(b.eval_pdf(wi)),
                        "base {base} wo {wo} wi {wi}"
                    );
                    let (ul, u) = (rng.f32(), rng.vec2());
                    let (sa, sb) = (a.sample(ul, u), b.sample(ul, u));
                    assert_eq!(sa.is_some(), sb.is_some());
                    if let (Some(sa), Some(sb)) = (sa, sb) {
                        assert_eq!(
                            sa.wi.to_array().map(f32::to_bits),
                            sb.wi.to_array().map(f32::to_bits)
                        );
                        assert_eq!(bits((sa.f, sa.pdf)), bits((sb.f, sb.pdf)));
                        assert_eq!((sa.lobe, sa.delta), (sb.lobe, sb.delta));
                    }
                    checked += 1;
                }
            }
        }
        assert!(checked > 30_000, "only {checked} directions compared");
        // Any reflective, transmissive, coated or sheened layer takes the general path.
        for params in [
            p(0.8, 0.0, 1.0, 1.0, 0.0),
            p(0.8, 0.1, 1.0, 0.0, 0.0),
            p(0.8, 0.0, 1.0, 0.0, 0.5),
            BsdfParams {
                clearcoat: 0.5,
                ..p(0.8, 0.0, 1.0, 0.0, 0.0)
            },
            BsdfParams {
                sheen_color: Vec3::splat(0.5),
                ..p(0.8, 0.0, 1.0, 0.0, 0.0)
            },
        ] {
            assert!(!Bsdf::new(&params, Vec3::Z, Vec3::Z).lambert, "{params:?}");
        }
        assert!(Bsdf::new(&p(0.8, 0.0, 1.0, 0.0, 0.0), Vec3::Z, Vec3::Z).lambert);
    }

    const STRAT_SIDE: usize = 700;

    fn uniform_sphere(u: Vec2) -> Vec3 {
        let z = 1.0 - 2.0 * u.x;
        let r = (1.0 - z * z).max(0.0).sqrt();
        let phi = TAU * u.y;
        Vec3::new(r * phi.cos(), r * phi.sin(), z)
    }

    /// Direction at polar angle `deg` from +z, in the xz plane.
    fn dir(deg: f32) -> Vec3 {
        let t = deg.to_radians();
        Vec3::new(t.sin(), 0.0, t.cos())
    }

    fn p(base: f32, metallic: f32, roughness: f32, specular: f32, transmission: f32) -> BsdfParams {
        BsdfParams {
            base_color: Vec3::splat(base),
            metallic,
            roughness,
            specular,
            specular_color: Vec3::ONE,
            transmission,
            ior: 1.5,
            clearcoat: 0.0,
            clearcoat_roughness: 0.0,
            clearcoat_normal: Vec3::ZERO,
            sheen_color: Vec3::ZERO,
            sheen_roughness: 0.0,
            anisotropy: 0.0,
            anisotropy_direction: Vec3::ZERO,
            iridescence: 0.0,
            iridescence_ior: 1.3,
            iridescence_thickness: 0.0,
        }
    }

    fn flat(params: &BsdfParams) -> Bsdf {
        Bsdf::new(params, Vec3::Z, Vec3::Z)
    }

    /// Albedo estimate `E[f |cos| / pdf]` through `sample()` (None counts as 0).
    fn albedo(b: &Bsdf, wo: Vec3, n: usize, rng: &mut Rng) -> Vec3 {
        let mut sum = Vec3::ZERO;
        for _ in 0..n {
            if let Some(s) = b.sample(wo, rng.f32(), rng.vec2()) {
                sum += s.f * s.wi.z.abs() / s.pdf;
            }
        }
        sum / n as f32
    }

    /// `integral of f |cos|` over the sphere by uniform sphere sampling of `eval`.
    fn albedo_uniform(b: &Bsdf, wo: Vec3, rng: &mut Rng) -> Vec3 {
        let n = STRAT_SIDE * STRAT_SIDE;
        let mut sum = Vec3::ZERO;
        for i in 0..n {
            let wi = rng.sphere_strat(i, STRAT_SIDE);
            sum += b.eval(wo, wi) * wi.z.abs();
        }
        sum * (4.0 * PI / n as f32)
    }

    fn rel_eq(a: f32, b: f32, tol: f32) -> bool {
        (a - b).abs() <= tol * a.abs().max(b.abs()).max(1e-6)
    }

    #[test]
    fn white_furnace_lambert() {
        let b = flat(&p(1.0, 0.0, 1.0, 0.0, 0.0));
        let mut rng = Rng(1);
        for deg in [0.0, 30.0, 60.0, 85.0] {
            let wo = dir(deg);
            let a = albedo(&b, wo, 50_000, &mut rng);
            assert!((a - Vec3::ONE).abs().max_element() < 0.01, "{deg}: {a}");
            // Uniform hemisphere sampling of eval.
            let n = 400_000;
            let mut sum = Vec3::ZERO;
            for _ in 0..n {
                let mut wi = rng.sphere();
                wi.z = wi.z.abs();
                sum += b.eval(wo, wi) * wi.z;
            }
            let a = sum * (2.0 * PI / n as f32);
            assert!((a - Vec3::ONE).abs().max_element() < 0.01, "{deg}: {a}");
        }
    }

    #[test]
    fn energy_bounded() {
        let mut rng = Rng(2);
        for roughness in [0.0, 0.05, 0.2, 0.5, 1.0] {
            for metallic in [0.0, 0.5, 1.0] {
                for specular in [1.0, 0.5] {
                    for (transmission, ior) in [(0.0, 1.5), (0.5, 1.5), (1.0, 1.5), (1.0, 1.0)] {
                        let b = flat(&BsdfParams {
                            ior,
                            ..p(1.0, metallic, roughness, specular, transmission)
                        });
                        for wo in [dir(0.0), dir(45.0), dir(80.0), -dir(30.0), -dir(60.0)] {
                            let a = albedo(&b, wo, 20_000, &mut rng);
                            assert!(
                                a.max_element() <= 1.01 && a.min_element() > 0.0,
                                "r {roughness} m {metallic} s {specular} t {transmission} \
                                 ior {ior} wo {wo}: {a}"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn smooth_glass_conserves_energy() {
        let b = flat(&p(1.0, 0.0, 0.0, 1.0, 1.0));
        let mut rng = Rng(3);
        for wo in [dir(0.0), dir(50.0), dir(85.0), -dir(20.0), -dir(60.0)] {
            let a = albedo(&b, wo, 20_000, &mut rng);
            assert!((a - Vec3::ONE).abs().max_element() < 0.01, "{wo}: {a}");
        }
    }

    /// Sampling and evaluation agree for each material and `wo`: E_sample[f cos / pdf]
    /// over the non-delta samples equals the uniform-sphere estimate of the integral of
    /// f |cos|, and the pdf integrates to the fraction of accepted samples.
    fn assert_sampling_matches_eval(mats: &[BsdfParams], wos: &[Vec3], rng: &mut Rng) {
        for (k, m) in mats.iter().enumerate() {
            let b = flat(m);
            for &wo in wos {
                // Non-delta samples only: eval/pdf cover the non-delta lobes.
                let n = 400_000;
                let mut a_s = Vec3::ZERO;
                let mut ok = 0usize;
                for _ in 0..n {
                    if let Some(s) = b.sample(wo, rng.f32(), rng.vec2()).filter(|s| !s.delta) {
                        a_s += s.f * s.wi.z.abs() / s.pdf;
                        ok += 1;
                    }
                }
                let a_s = a_s / n as f32;
                let a_u = albedo_uniform(&b, wo, rng);
                assert!(
                    (a_s - a_u).abs().max_element() < 0.015,
                    "mat {k} wo {wo}: sampled {a_s} uniform {a_u}"
                );
                let mut pdf_sum = 0.0f64;
                let ns = STRAT_SIDE * STRAT_SIDE;
                for i in 0..ns {
                    pdf_sum += b.pdf(wo, rng.sphere_strat(i, STRAT_SIDE)) as f64;
                }
                let integral = (pdf_sum * 4.0 * std::f64::consts::PI / ns as f64) as f32;
                let frac = ok as f32 / n as f32;
                assert!(integral <= 1.02, "mat {k} wo {wo}: pdf integral {integral}");
                assert!(
                    (integral - frac).abs() < 0.01,
                    "mat {k} wo {wo}: pdf integral {integral} vs accepted {frac}"
                );
            }
        }
    }

    /// Sampling and evaluation agree: E_sample[f cos / pdf] equals the uniform-sphere
    /// estimate of the integral of f |cos|, and the pdf integrates to the fraction of
    /// successful samples.
    #[test]
    fn sampling_matches_eval() {
        let mats = [
            p(0.8, 0.0, 0.5, 1.0, 0.0),
            p(0.9, 1.0, 0.4, 1.0, 0.0),
            p(0.7, 0.3, 0.7, 0.6, 0.0),
            p(1.0, 0.0, 0.5, 1.0, 1.0),
            p(0.9, 0.0, 0.6, 1.0, 0.5),
            // Index-matched: rough reflection, delta pass-through transmission.
            BsdfParams {
                ior: 1.0,
                ..p(0.9, 0.0, 0.4, 1.0, 0.5)
            },
            // Tinted specular colour over a coloured base.
            BsdfParams {
                base_color: Vec3::new(0.9, 0.4, 0.1),
                specular_color: Vec3::new(2.0, 1.0, 0.2),
                ior: 1.8,
                ..p(1.0, 0.2, 0.45, 0.8, 0.0)
            },
        ];
        assert_sampling_matches_eval(&mats, &[dir(10.0), dir(60.0), -dir(40.0)], &mut Rng(4));
    }

    fn coated(base: BsdfParams, coat: f32, roughness: f32) -> BsdfParams {
        BsdfParams {
            clearcoat: coat,
            clearcoat_roughness: roughness,
            ..base
        }
    }

    /// White furnace for the clear coat: a smooth coat over a white Lambert base
    /// reflects `c F(cos_o)` and passes `(1 - c F(cos_o))` down and `(1 - c F(cos_i))`
    /// back up, so its albedo is `c F_o + (1 - c F_o)(1 - c F_hemi)` with
    /// `F_hemi = 2 integral F(mu) mu dmu`: the sampled albedo must match within 1%. Rough
    /// coats, over every base, never gain energy.
    #[test]
    fn clearcoat_white_furnace() {
        let mut rng = Rng(12);
        let n = 100_000;
        let f_hemi: f64 = (0..n)
            .map(|i| {
                let mu = (i as f64 + 0.5) / n as f64;
                2.0 * coat_fresnel(mu as f32) as f64 * mu / n as f64
            })
            .sum();
        let white = p(1.0, 0.0, 1.0, 0.0, 0.0);
        for coat in [0.5f32, 1.0] {
            let b = flat(&coated(white, coat, 0.0));
            assert!(!b.is_delta_only() && b.has_specular_lobe());
            for deg in [0.0f32, 40.0, 75.0, 88.0] {
                let wo = dir(deg);
                let a = albedo(&b, wo, 100_000, &mut rng);
                let fo = coat * coat_fresnel(wo.z);
                let want = fo + (1.0 - fo) * (1.0 - coat * f_hemi as f32);
                assert!(
                    (a - Vec3::splat(want)).abs().max_element() < 0.01 && a.is_finite(),
                    "coat {coat} at {deg}: {a} vs {want}"
                );
            }
        }
        let bases = [
            white,
            p(1.0, 1.0, 0.2, 1.0, 0.0),
            p(1.0, 0.0, 0.4, 1.0, 0.0),
            p(1.0, 0.0, 0.0, 1.0, 1.0),
            p(1.0, 0.0, 0.5, 1.0, 1.0),
        ];
        assert_no_gain(
            "coat",
            &bases,
            &[0.0, 0.05, 0.3, 0.7, 1.0],
            &mut rng,
            |b, r| coated(b, 1.0, r),
        );
    }

    /// `layer` (a base and a roughness to a layered material) over each of `bases` at
    /// each of `roughnesses` reflects no more than it receives (albedo at most 1.01),
    /// something, and nothing non-finite, from above and below.
    fn assert_no_gain(
        name: &str,
        bases: &[BsdfParams],
        roughnesses: &[f32],
        rng: &mut Rng,
        layer: impl Fn(BsdfParams, f32) -> BsdfParams,
    ) {
        for &roughness in roughnesses {
            for &base in bases {
                let b = flat(&layer(base, roughness));
                for wo in [dir(0.0), dir(50.0), dir(85.0), -dir(30.0)] {
                    let a = albedo(&b, wo, 20_000, rng);
                    assert!(
                        a.max_element() <= 1.01 && a.min_element() > 0.0 && a.is_finite(),
                        "{name} roughness {roughness} base {base:?} wo {wo}: {a}"
                    );
                }
            }
        }
    }

    /// The coat's pdf is the density its sampler draws from, so MIS weights are right:
    /// sampled and uniformly integrated albedos agree, and the pdf integrates to the
    /// fraction of accepted samples.
    #[test]
    fn clearcoat_sampling_matches_eval() {
        let mats = [
            coated(p(0.8, 0.0, 0.6, 1.0, 0.0), 1.0, 0.3),
            coated(p(0.9, 1.0, 0.5, 1.0, 0.0), 0.6, 0.15),
            coated(p(0.5, 0.0, 1.0, 0.0, 0.0), 1.0, 0.8),
            coated(p(1.0, 0.0, 0.5, 1.0, 1.0), 1.0, 0.4),
        ];
        assert_sampling_matches_eval(&mats, &[dir(10.0), dir(70.0), -dir(40.0)], &mut Rng(13));
    }

    fn coat_normal(base: BsdfParams, n: Vec3) -> BsdfParams {
        BsdfParams {
            clearcoat_normal: n,
            ..base
        }
    }

    fn reflect(wo: Vec3, n: Vec3) -> Vec3 {
        n * (2.0 * wo.dot(n)) - wo
    }

    /// `clearcoatNormalTexture`: the coat reflects about its own normal and the base
    /// about its own; nothing gains energy, sampling and evaluation agree, and a coat
    /// normal equal to the shading normal changes nothing.
    #[test]
    fn clearcoat_normal_moves_the_coat_not_the_base() {
        let mut rng = Rng(18);
        let tilt = Vec3::new(0.3, 0.1, 1.0).normalize();
        let bases = [
            p(1.0, 0.0, 1.0, 0.0, 0.0),
            p(1.0, 1.0, 0.3, 1.0, 0.0),
            p(1.0, 0.0, 0.4, 1.0, 0.0),
            p(1.0, 0.0, 0.5, 1.0, 1.0),
        ];
        assert_no_gain("coat normal", &bases, &[0.0, 0.1, 0.4], &mut rng, |b, r| {
            coat_normal(coated(b, 1.0, r), tilt)
        });
        let mats = [
            coat_normal(coated(p(0.8, 0.0, 0.6, 1.0, 0.0), 1.0, 0.3), tilt),
            coat_normal(
                coated(p(0.9, 1.0, 0.5, 1.0, 0.0), 0.6, 0.15),
                Vec3::new(-0.4, 0.2, 1.0),
            ),
            coat_normal(coated(p(1.0, 0.0, 0.5, 1.0, 1.0), 1.0, 0.4), tilt),
        ];
        assert_sampling_matches_eval(&mats, &[dir(10.0), dir(60.0), -dir(40.0)], &mut rng);

        let wo = dir(30.0);
        let (m_n, m_c) = (reflect(wo, Vec3::Z), reflect(wo, tilt));
        // A rough coat over a black base: its highlight follows the coat's normal.
        let black = p(0.0, 0.0, 1.0, 0.0, 0.0);
        let b = flat(&coat_normal(coated(black, 1.0, 0.15), tilt));
        let (at_c, at_n) = (b.eval(wo, m_c).x, b.eval(wo, m_n).x);
        assert!(
            at_c > 5.0 * at_n,
            "coat mirror {at_c} vs base mirror {at_n}"
        );
        let plain = flat(&coated(black, 1.0, 0.15));
        assert!(plain.eval(wo, m_n).x > 5.0 * plain.eval(wo, m_c).x);
        // A smooth coat's mirror sample is about its own normal; the rough metal under
        // it still reflects about the shading normal, only attenuated a little
        // differently.
        let metal = p(0.9, 1.0, 0.3, 1.0, 0.0);
        let b = flat(&coat_normal(coated(metal, 1.0, 0.0), tilt));
        let untilted = flat(&coated(metal, 1.0, 0.0));
        let mut coat_samples = 0;
        for _ in 0..2_000 {
            if let Some(s) = b.sample(wo, rng.f32(), rng.vec2())
                && s.lobe == Lobe::CoatReflection
            {
                assert!((s.wi - m_c).length() < 1e-5, "{s:?}");
                coat_samples += 1;
            }
        }
        assert!(coat_samples > 20, "{coat_samples}");
        let (f_t, f_u) = (b.eval(wo, m_n), untilted.eval(wo, m_n));
        assert!(
            (f_t - f_u).abs().max_element() < 0.05 * f_u.max_element(),
            "{f_t} vs {f_u}"
        );
        // A coat normal equal to the shading normal is no change.
        for m in [
            coated(metal, 1.0, 0.3),
            coated(p(0.5, 0.0, 0.4, 1.0, 1.0), 0.7, 0.2),
        ] {
            let same = flat(&coat_normal(m, Vec3::Z));
            let plain = flat(&m);
            for _ in 0..1_000 {
                let (wo, wi) = (rng.sphere(), rng.sphere());
                let (a, c) = (same.eval(wo, wi), plain.eval(wo, wi));
                for k in 0..3 {
                    assert!(rel_eq(a[k], c[k], 1e-4), "{a} vs {c}");
                }
                assert!(rel_eq(same.pdf(wo, wi), plain.pdf(wo, wi), 1e-4));
            }
        }
    }

    fn sheened(base: BsdfParams, color: f32, roughness: f32) -> BsdfParams {
        BsdfParams {
            sheen_color: Vec3::splat(color),
            sheen_roughness: roughness,
            ..base
        }
    }

    /// White furnace for the sheen: a white sheen over a black base reflects exactly its
    /// directional albedo `E(cos_o)` (so sampling, pdf and the albedo table agree); over
    /// any base, under a coat or not, the sum never gains energy.
    #[test]
    fn sheen_white_furnace() {
        let mut rng = Rng(14);
        let black = p(0.0, 0.0, 1.0, 0.0, 0.0);
        for roughness in [0.1f32, 0.4, 1.0] {
            let b = flat(&sheened(black, 1.0, roughness));
            assert!(!b.is_delta_only());
            for deg in [0.0f32, 45.0, 80.0] {
                let wo = dir(deg);
                let a = albedo(&b, wo, 200_000, &mut rng);
                let e = crate::sheen::albedo(wo.z, roughness);
                assert!(
                    (a - Vec3::splat(e)).abs().max_element() < 0.01 && a.is_finite(),
                    "roughness {roughness} at {deg}: {a} vs E {e}"
                );
            }
        }
        let bases = [
            p(1.0, 0.0, 1.0, 0.0, 0.0),
            p(1.0, 0.0, 0.3, 1.0, 0.0),
            p(1.0, 1.0, 0.0, 1.0, 0.0),
            coated(p(1.0, 0.0, 0.5, 1.0, 0.0), 1.0, 0.2),
            p(1.0, 0.0, 0.5, 1.0, 1.0),
        ];
        assert_no_gain("sheen", &bases, &[0.0, 0.3, 1.0], &mut rng, |b, r| {
            sheened(b, 1.0, r)
        });
    }

    /// Sampled and uniformly integrated albedos agree with a sheen, and the pdf
    /// integrates to the accepted fraction: the sheen's pdf is the density its sampler
    /// draws from.
    #[test]
    fn sheen_sampling_matches_eval() {
        let mats = [
            sheened(p(0.8, 0.0, 0.6, 1.0, 0.0), 0.9, 0.5),
            sheened(p(0.3, 0.0, 1.0, 0.0, 0.0), 1.0, 0.2),
            sheened(coated(p(0.9, 1.0, 0.4, 1.0, 0.0), 0.5, 0.3), 0.6, 0.8),
        ];
        assert_sampling_matches_eval(&mats, &[dir(10.0), dir(75.0)], &mut Rng(15));
    }

    fn anisotropic(base: BsdfParams, strength: f32, direction: Vec3) -> BsdfParams {
        BsdfParams {
            anisotropy: strength,
            anisotropy_direction: direction,
            ..base
        }
    }

    /// Anisotropy stretches the lobe along its direction and nothing else: a white
    /// anisotropic metal never gains energy, sampling and evaluation agree, strength 0
    /// is the isotropic lobe to the bit, and the lobe is wider along its direction.
    #[test]
    fn anisotropic_ggx_furnace_and_sampling() {
        let mut rng = Rng(16);
        for roughness in [0.0, 0.3, 0.7] {
            for strength in [0.5, 1.0] {
                for base in [
                    p(1.0, 1.0, roughness, 1.0, 0.0),
                    p(1.0, 0.0, roughness, 1.0, 1.0),
                ] {
                    let b = flat(&anisotropic(base, strength, Vec3::new(1.0, 1.0, 0.3)));
                    for wo in [dir(0.0), dir(50.0), dir(85.0), -dir(30.0)] {
                        let a = albedo(&b, wo, 20_000, &mut rng);
                        assert!(
                            a.max_element() <= 1.01 && a.min_element() > 0.0 && a.is_finite(),
                            "r {roughness} s {strength} {base:?} wo {wo}: {a}"
                        );
                    }
                }
            }
        }
        let mats = [
            anisotropic(p(0.9, 1.0, 0.3, 1.0, 0.0), 0.8, Vec3::X),
            anisotropic(p(0.8, 0.0, 0.2, 1.0, 0.0), 1.0, Vec3::new(1.0, 2.0, 0.0)),
            anisotropic(p(1.0, 0.0, 0.4, 1.0, 1.0), 0.6, Vec3::Y),
        ];
        assert_sampling_matches_eval(&mats, &[dir(10.0), dir(60.0), -dir(40.0)], &mut rng);

        let iso = p(0.9, 1.0, 0.4, 1.0, 0.0);
        let none = flat(&anisotropic(iso, 0.0, Vec3::X));
        let plain = flat(&iso);
        let stretched = flat(&anisotropic(iso, 1.0, Vec3::X));
        for _ in 0..1_000 {
            let (wo, wi) = (rng.sphere(), rng.sphere());
            assert_eq!(none.eval(wo, wi), plain.eval(wo, wi));
            assert_eq!(none.pdf(wo, wi), plain.pdf(wo, wi));
        }
        // Off-specular by 40 degrees along the direction (x) the stretched lobe still
        // reflects much more than across it (y).
        let wo = Vec3::Z;
        let along = Vec3::new(40f32.to_radians().sin(), 0.0, 40f32.to_radians().cos());
        let across = Vec3::new(0.0, along.x, along.z);
        let (fa, fc) = (stretched.eval(wo, along).x, stretched.eval(wo, across).x);
        assert!(fa > 2.0 * fc, "along {fa} across {fc}");
        assert!((plain.eval(wo, along).x - plain.eval(wo, across).x).abs() < 1e-4);
    }

    fn iridescent(base: BsdfParams, factor: f32, thickness: f32) -> BsdfParams {
        BsdfParams {
            iridescence: factor,
            iridescence_ior: 1.3,
            iridescence_thickness: thickness,
            ..base
        }
    }

    /// The thin film changes only the Fresnel term, and keeps it a fraction: over white
    /// bases (dielectric, metal, glass, coated) nothing gains energy; sampling and
    /// evaluation agree; factor 0 (or thickness 0) is the material without the film, to
    /// the bit; and the film's thickness changes the hue of the reflection.
    #[test]
    fn iridescence_furnace_bits_and_colour() {
        let mut rng = Rng(17);
        let bases = [
            p(1.0, 0.0, 1.0, 1.0, 0.0),
            p(1.0, 0.0, 0.3, 1.0, 0.0),
            p(1.0, 1.0, 0.0, 1.0, 0.0),
            p(1.0, 1.0, 0.4, 1.0, 0.0),
            p(1.0, 0.5, 0.2, 1.0, 0.0),
            p(1.0, 0.0, 0.0, 1.0, 1.0),
            p(1.0, 0.0, 0.5, 1.0, 1.0),
            coated(p(1.0, 0.0, 0.4, 1.0, 0.0), 1.0, 0.2),
        ];
        // The "roughness" argument is the film's thickness here.
        assert_no_gain(
            "iridescence",
            &bases,
            &[150.0, 400.0, 900.0],
            &mut rng,
            |b, t| iridescent(b, 1.0, t),
        );
        let mats = [
            iridescent(p(0.8, 0.0, 0.5, 1.0, 0.0), 1.0, 300.0),
            iridescent(p(0.9, 1.0, 0.4, 1.0, 0.0), 0.7, 500.0),
            iridescent(p(1.0, 0.0, 0.5, 1.0, 1.0), 1.0, 250.0),
        ];
        assert_sampling_matches_eval(&mats, &[dir(10.0), dir(60.0), -dir(40.0)], &mut rng);

        for base in [p(0.7, 0.3, 0.4, 1.0, 0.0), p(1.0, 0.0, 0.3, 1.0, 1.0)] {
            let plain = flat(&base);
            for off in [iridescent(base, 0.0, 400.0), iridescent(base, 1.0, 0.0)] {
                let off = flat(&off);
                for _ in 0..1_000 {
                    let (wo, wi) = (rng.sphere(), rng.sphere());
                    assert_eq!(off.eval(wo, wi), plain.eval(wo, wi));
                    assert_eq!(off.pdf(wo, wi), plain.pdf(wo, wi));
                    let (ul, u) = (rng.f32(), rng.vec2());
                    assert_eq!(off.sample(wo, ul, u), plain.sample(wo, ul, u));
                }
            }
        }

        // A smooth black dielectric reflects only its Fresnel term: grey without the film,
        // coloured with it, and differently coloured for another thickness.
        let chroma = |b: &Bsdf| {
            let w = b.mirror(dir(0.0)).unwrap().1;
            w / w.element_sum()
        };
        let black = p(0.0, 0.0, 0.0, 1.0, 0.0);
        let grey = chroma(&flat(&black));
        assert!((grey - Vec3::splat(1.0 / 3.0)).abs().max_element() < 1e-6);
        let thin = chroma(&flat(&iridescent(black, 1.0, 250.0)));
        let thick = chroma(&flat(&iridescent(black, 1.0, 400.0)));
        assert!((thin - grey).abs().max_element() > 0.05, "{thin}");
        assert!(
            (thin - thick).abs().max_element() > 0.05,
            "{thin} vs {thick}"
        );
    }

    #[test]
    fn pdf_integral_lambert_is_one() {
        let b = flat(&p(0.5, 0.0, 1.0, 0.0, 0.0));
        let mut rng = Rng(5);
        let n = 400_000;
        let mut sum = 0.0f64;
        for _ in 0..n {
            sum += b.pdf(dir(35.0), rng.sphere()) as f64;
        }
        let integral = sum * 4.0 * std::f64::consts::PI / n as f64;
        assert!((integral - 1.0).abs() < 0.01, "{integral}");
    }

    #[test]
    fn sample_consistent_with_eval_and_pdf() {
        let mut rng = Rng(6);
        let mut checked = 0;
        for _ in 0..20_000 {
            let m = BsdfParams {
                base_color: Vec3::new(rng.f32(), rng.f32(), rng.f32()),
                metallic: rng.f32(),
                roughness: 0.05 + rng.f32() * 0.95,
                specular: rng.f32(),
                specular_color: Vec3::new(rng.f32(), rng.f32(), rng.f32()) * 2.0,
                transmission: if rng.f32() < 0.5 { 0.0 } else { rng.f32() },
                ior: 1.1 + rng.f32(),
                clearcoat: if rng.f32() < 0.5 { 0.0 } else { rng.f32() },
                clearcoat_roughness: 0.05 + rng.f32() * 0.95,
                clearcoat_normal: if rng.f32() < 0.5 {
                    Vec3::ZERO
                } else {
                    Vec3::Z + rng.sphere() * 0.5
                },
                sheen_color: if rng.f32() < 0.5 {
                    Vec3::ZERO
                } else {
                    Vec3::new(rng.f32(), rng.f32(), rng.f32())
                },
                sheen_roughness: rng.f32(),
                anisotropy: if rng.f32() < 0.5 { 0.0 } else { rng.f32() },
                anisotropy_direction: rng.sphere(),
                iridescence: if rng.f32() < 0.5 { 0.0 } else { rng.f32() },
                iridescence_ior: 1.0 + rng.f32(),
                iridescence_thickness: rng.f32() * 1000.0,
            };
            let b = flat(&m);
            let wo = rng.sphere();
            if let Some(s) = b.sample(wo, rng.f32(), rng.vec2()) {
                if s.delta {
                    continue;
                }
                let f = b.eval(wo, s.wi);
                let pdf = b.pdf(wo, s.wi);
                assert!(rel_eq(s.pdf, pdf, 1e-3), "{m:?} {wo}: {} vs {pdf}", s.pdf);
                for c in 0..3 {
                    assert!(rel_eq(s.f[c], f[c], 1e-3), "{m:?} {wo}: {} vs {f}", s.f);
                }
                checked += 1;
            }
        }
        assert!(checked > 10_000, "{checked}");
    }

    #[test]
    fn reciprocity() {
        let mut rng = Rng(7);
        let mats = [
            p(0.8, 0.0, 0.3, 1.0, 0.0),
            p(0.8, 1.0, 0.1, 1.0, 0.0),
            BsdfParams {
                base_color: Vec3::new(0.9, 0.5, 0.2),
                metallic: 0.4,
                roughness: 0.6,
                specular: 0.7,
                specular_color: Vec3::new(1.0, 0.5, 2.0),
                transmission: 0.0,
                ior: 1.8,
                clearcoat: 0.7,
                clearcoat_roughness: 0.3,
                clearcoat_normal: Vec3::ZERO,
                sheen_color: Vec3::new(0.5, 0.8, 0.2),
                sheen_roughness: 0.5,
                anisotropy: 0.0,
                anisotropy_direction: Vec3::ZERO,
                iridescence: 0.8,
                iridescence_ior: 1.6,
                iridescence_thickness: 300.0,
            },
        ];
        for m in &mats {
            let b = flat(m);
            for _ in 0..2_000 {
                let mut wo = rng.sphere();
                let mut wi = rng.sphere();
                wo.z = wo.z.abs();
                wi.z = wi.z.abs();
                let a = b.eval(wo, wi);
                let c = b.eval(wi, wo);
                for k in 0..3 {
                    assert!(rel_eq(a[k], c[k], 1e-3), "{m:?}: {a} vs {c}");
                }
            }
        }
    }

    #[test]
    fn pure_lambert_never_leaves_diffuse() {
        let b = flat(&p(0.6, 0.0, 0.0, 0.0, 0.0));
        assert!(!b.has_specular_lobe() && b.has_diffuse() && !b.is_delta_only());
        let mut rng = Rng(8);
        for _ in 0..10_000 {
            let mut wo = rng.sphere();
            wo.z = wo.z.abs().max(1e-3);
            if let Some(s) = b.sample(wo, rng.f32(), rng.vec2()) {
                assert_eq!(s.lobe, Lobe::Diffuse);
                assert!(!s.delta);
            }
        }
        assert!(b.mirror(dir(10.0)).is_none() && b.refraction(dir(10.0)).is_none());
    }

    #[test]
    fn smooth_glass_is_delta_and_obeys_snell() {
        let ior = 1.5;
        let b = Bsdf::new(
            &BsdfParams {
                ior,
                ..p(1.0, 0.0, 0.0, 1.0, 1.0)
            },
            Vec3::Z,
            Vec3::Z,
        );
        assert!(b.is_delta_only() && b.has_transmission() && !b.has_diffuse());
        let mut rng = Rng(9);
        for _ in 0..10_000 {
            let wo = rng.sphere();
            if let Some(s) = b.sample(wo, rng.f32(), rng.vec2()) {
                assert!(s.delta);
                assert!(matches!(
                    s.lobe,
                    Lobe::SpecularReflection | Lobe::SpecularTransmission
                ));
            }
            assert_eq!(b.eval(wo, rng.sphere()), Vec3::ZERO);
            assert_eq!(b.pdf(wo, rng.sphere()), 0.0);
        }
        // Entering: sin_i = ior sin_t.
        for deg in [0.0f32, 20.0, 45.0, 70.0, 89.0] {
            let wo = dir(deg);
            let (wi, w) = b.refraction(wo).unwrap();
            let sin_t = (1.0 - wi.z * wi.z).sqrt();
            assert!(wi.z < 0.0 && wi.x <= 1e-6);
            assert!((deg.to_radians().sin() - ior * sin_t).abs() < 1e-4, "{deg}");
            assert!(w.max_element() <= 1.0 && w.min_element() > 0.0);
        }
        // Leaving: ior sin_i = sin_t below the critical angle, TIR above it.
        let critical = (1.0 / ior).asin().to_degrees();
        for deg in [0.0f32, 20.0, 40.0, critical - 0.5] {
            let wo = -dir(deg);
            let (wi, _) = b.refraction(wo).unwrap();
            let sin_t = (1.0 - wi.z * wi.z).sqrt();
            assert!(wi.z > 0.0);
            assert!((ior * deg.to_radians().sin() - sin_t).abs() < 1e-3, "{deg}");
        }
        for deg in [critical + 0.5, 60.0, 85.0] {
            let wo = -dir(deg);
            assert!(b.refraction(wo).is_none(), "{deg}");
            let (wi, w) = b.mirror(wo).unwrap();
            assert!((w - Vec3::ONE).abs().max_element() < 1e-6 && wi.z < 0.0);
            for _ in 0..1_000 {
                let s = b.sample(wo, rng.f32(), rng.vec2()).unwrap();
                assert_eq!(s.lobe, Lobe::SpecularReflection);
                assert!(rel_eq(s.f.x * s.wi.z.abs() / s.pdf, 1.0, 1e-5));
            }
        }
    }

    #[test]
    fn reflection_below_geometric_surface_is_zero() {
        // Shading normal tilted 30 degrees from the geometric normal.
        let n = dir(30.0);
        let mut rng = Rng(10);
        for m in [p(0.8, 0.0, 0.5, 1.0, 0.0), p(0.8, 1.0, 0.3, 1.0, 0.0)] {
            let b = Bsdf::new(&m, n, Vec3::Z);
            let wo = dir(40.0);
            // Above the shading hemisphere, below the geometric one.
            let wi = dir(100.0);
            assert!(wi.dot(n) > 0.0 && wi.z < 0.0);
            assert_eq!(b.eval(wo, wi), Vec3::ZERO);
            assert_eq!(b.pdf(wo, wi), 0.0);
            for _ in 0..5_000 {
                if let Some(s) = b.sample(wo, rng.f32(), rng.vec2()) {
                    assert!(s.wi.z > 0.0, "{s:?}");
                }
            }
        }
    }

    #[test]
    fn mirror_and_orientation() {
        let b = Bsdf::new(&p(0.9, 1.0, 0.0, 1.0, 0.0), -Vec3::Z, Vec3::Z);
        assert!(b.is_delta_only() && b.has_specular_lobe());
        let (wi, w) = b.mirror(dir(30.0)).unwrap();
        assert!((wi - Vec3::new(-0.5, 0.0, 3f32.sqrt() / 2.0)).length() < 1e-5);
        assert!(w.min_element() >= 0.9 - 1e-6 && w.max_element() <= 1.0);
        // Same from the back side.
        let (wi, _) = b.mirror(-dir(30.0)).unwrap();
        assert!((wi - Vec3::new(0.5, 0.0, -(3f32.sqrt()) / 2.0)).length() < 1e-5);
        // Rough metal: no Whitted mirror.
        assert!(
            flat(&p(0.9, 1.0, 0.5, 1.0, 0.0))
                .mirror(dir(30.0))
                .is_none()
        );
        assert!(!flat(&p(0.9, 1.0, 0.5, 1.0, 0.0)).is_delta_only());
    }

    #[test]
    fn stress_no_nan() {
        let mut rng = Rng(11);
        let specials = [0.0, 1e-7, 1e-4, 0.03, 0.5, 1.0];
        let iors = [1.0, 1.0005, 1.5, 0.0, f32::INFINITY, 2.4, 1.0 + 1e-6];
        for i in 0..100_000 {
            let pick = |rng: &mut Rng, xs: &[f32]| xs[(rng.next_u64() % xs.len() as u64) as usize];
            let m = BsdfParams {
                base_color: Vec3::new(rng.f32(), rng.f32(), rng.f32()),
                metallic: pick(&mut rng, &[0.0, 1.0, 0.5, 0.999]),
                roughness: if i % 2 == 0 {
                    pick(&mut rng, &specials)
                } else {
                    rng.f32()
                },
                specular: pick(&mut rng, &[0.0, 1.0, 0.3]),
                specular_color: Vec3::new(rng.f32(), rng.f32(), rng.f32()) * 3.0,
                transmission: pick(&mut rng, &[0.0, 1.0, 0.5]),
                ior: pick(&mut rng, &iors),
                clearcoat: pick(&mut rng, &[0.0, 1.0, 0.5]),
                clearcoat_roughness: if i % 3 == 0 {
                    pick(&mut rng, &specials)
                } else {
                    rng.f32()
                },
                clearcoat_normal: match i % 5 {
                    0 => Vec3::ZERO,
                    1 => Vec3::NAN,
                    _ => rng.sphere(),
                },
                sheen_color: if i % 4 == 1 {
                    Vec3::new(rng.f32(), rng.f32(), rng.f32())
                } else {
                    Vec3::ZERO
                },
                sheen_roughness: pick(&mut rng, &[0.0, 0.5, 1.0]),
                anisotropy: pick(&mut rng, &[0.0, 1.0, 0.5]),
                anisotropy_direction: match i % 6 {
                    0 => Vec3::ZERO,
                    1 => Vec3::NAN,
                    _ => rng.sphere(),
                },
                iridescence: pick(&mut rng, &[0.0, 1.0, 0.5]),
                iridescence_ior: pick(&mut rng, &[1.0, 1.3, 0.0, f32::INFINITY, f32::NAN]),
                iridescence_thickness: pick(&mut rng, &[0.0, 1e-6, 0.01, 400.0, 1e9, f32::NAN]),
            };
            let ng = rng.sphere();
            let n = match i % 4 {
                0 => ng,
                1 => -ng,
                2 => (ng + rng.sphere() * 0.5).normalize_or(ng),
                _ => rng.sphere(),
            };
            let b = Bsdf::new(&m, n, ng);
            let wo = match i % 5 {
                0 => {
                    // Grazing / tangent to the geometric surface.
                    let t = ng.any_orthonormal_pair().0;
                    let eps = pick(&mut rng, &[0.0, 1e-8, 1e-6, 1e-4, -1e-6]);
                    (t + ng * eps).normalize()
                }
                1 => {
                    // Grazing to the shading normal.
                    let t = n.any_orthonormal_pair().0;
                    (t + n * pick(&mut rng, &[0.0, 1e-7, -1e-7])).normalize()
                }
                _ => rng.sphere(),
            };
            let u = match i % 7 {
                0 => Vec2::new(0.0, 0.0),
                1 => Vec2::new(ONE_MINUS_EPS, ONE_MINUS_EPS),
                _ => rng.vec2(),
            };
            let ul = if i % 11 == 0 { 1.0 } else { rng.f32() };
            if let Some(s) = b.sample(wo, ul, u) {
                assert!(
                    s.f.is_finite() && s.pdf.is_finite() && s.pdf > 0.0,
                    "{m:?} {s:?}"
                );
                assert!(s.wi.is_finite() && (s.wi.length() - 1.0).abs() < 1e-3);
                assert!(s.f.min_element() >= 0.0);
                let e = b.eval(wo, s.wi);
                assert!(e.is_finite() && b.pdf(wo, s.wi).is_finite());
            }
            let wi = if i % 3 == 0 { -wo } else { rng.sphere() };
            let e = b.eval(wo, wi);
            let pd = b.pdf(wo, wi);
            assert!(
                e.is_finite() && pd.is_finite() && pd >= 0.0,
                "{m:?} {wo} {wi}"
            );
            assert!(e.min_element() >= 0.0);
            if let Some((d, w)) = b.mirror(wo) {
                assert!(d.is_finite() && w.is_finite());
            }
            if let Some((d, w)) = b.refraction(wo) {
                assert!(d.is_finite() && w.is_finite());
            }
            assert!(b.diffuse_albedo().is_finite());
        }
        // Degenerate inputs.
        let b = Bsdf::new(&BsdfParams::default(), Vec3::ZERO, Vec3::ZERO);
        assert!(b.sample(Vec3::Z, 0.5, Vec2::splat(0.5)).is_none());
        let b = flat(&BsdfParams {
            base_color: Vec3::NAN,
            metallic: f32::NAN,
            roughness: f32::NAN,
            specular: f32::INFINITY,
            specular_color: Vec3::INFINITY,
            transmission: f32::NAN,
            ior: f32::NAN,
            clearcoat: f32::NAN,
            clearcoat_roughness: f32::NAN,
            clearcoat_normal: Vec3::NAN,
            sheen_color: Vec3::NAN,
            sheen_roughness: f32::NAN,
            anisotropy: 0.0,
            anisotropy_direction: Vec3::ZERO,
            iridescence: f32::NAN,
            iridescence_ior: f32::NAN,
            iridescence_thickness: f32::INFINITY,
        });
        for wo in [Vec3::Z, Vec3::X, Vec3::NAN, Vec3::ZERO, dir(89.999)] {
            let _ = b
                .sample(wo, f32::NAN, Vec2::NAN)
                .map(|s| assert!(s.f.is_finite()));
            assert!(b.eval(wo, Vec3::Z).is_finite() && b.pdf(wo, Vec3::NAN).is_finite());
        }
    }
}
