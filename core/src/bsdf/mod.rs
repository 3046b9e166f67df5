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

//!
//! # Files
//!
//! One file per lobe, each holding the lobe's parameters (sanitised by [`Bsdf::new`]) and
//! its share of evaluation and sampling: `diffuse.rs` (Lambert), `reflection.rs`
//! (dielectric and metal reflection on one GGX lobe, and Whitted's mirror),
//! `transmission.rs` (smooth and rough refraction), `clearcoat.rs` and `sheen.rs` (the
//! layers over the base). What the lobes share has a file of its own: `params.rs` (the
//! inputs), `frame.rs` (the local shading frame), `fresnel.rs` (the base's Fresnel
//! weights and thin film), `ggx.rs` (the microfacet distribution). `at.rs` composes the
//! lobes for one `wo` ([`BsdfAt`]): it sums their values and densities in a fixed order
//! and picks one of them to sample, so the bits are those of the single function the
//! module once was.

// `!(x > 0.0)` is used on purpose throughout: it also rejects NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

mod at;
mod clearcoat;
mod diffuse;
mod frame;
mod fresnel;
mod ggx;
mod params;
mod reflection;
mod sheen;
#[cfg(test)]
mod tests;
mod transmission;

use glam::{Vec2, Vec3};

pub use at::BsdfAt;
pub use params::BsdfParams;

use clearcoat::Coat;
use diffuse::Diffuse;
use fresnel::{Film, Fresnel};
use ggx::Ggx;
use reflection::Reflection;
use sheen::Sheen;
use transmission::Transmission;

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

/// The BSDF at one shading point: its lobes, each sanitised from [`BsdfParams`]. Cheap to
/// build; holds no references.
#[derive(Clone, Copy, Debug)]
pub struct Bsdf {
    /// Shading normal as passed (unit): the cosine of delta samples refers to it.
    n_in: Vec3,
    /// Shading normal flipped to `ng`'s side.
    n: Vec3,
    /// Geometric normal as passed: its side is the outside of a transmissive object.
    ng: Vec3,
    valid: bool,
    /// The base's dielectric-over-metal Fresnel layer (and its thin film).
    fresnel: Fresnel,
    /// The base's GGX distribution, shared by reflection and rough transmission.
    ggx: Ggx,
    diffuse: Diffuse,
    reflection: Reflection,
    transmission: Transmission,
    coat: Coat,
    sheen: Sheen,
    /// Only the diffuse lobe: no dielectric or metal reflection (`specular` and
    /// `metallic` 0), no transmission, coat or sheen. [`Bsdf::at`] and
    /// [`BsdfAt::eval_pdf`] then skip the layers' Fresnel weights and lobe selection,
    /// whose values are known (base scale 1, diffuse probability 1 or 0): the bits are
    /// those of the general path (test `lambert_fast_path_gives_the_general_bits`).
    /// The other lobes then hold inert values ([`Bsdf::lambert`]).
    lambert: bool,
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
        let normals = Normals::new(n, ng);
        let base = BaseLobes::new(params);
        if base.diffuse_only(params) {
            Bsdf::lambert(params, normals, &base)
        } else {
            Bsdf::general(params, normals, &base)
        }
    }

    /// A diffuse-only BSDF (`lambert` set): only what its paths read is built from
    /// `params` (the normals, the diffuse tint and, for the frame's tangent, the
    /// anisotropy direction); the other lobes hold the inert values of
    /// [`Bsdf::LAMBERT_INERT`]. The general construction sanitises every parameter,
    /// builds every lobe and clamps its roughness and index (about 200 instructions
    /// a hit), which a Lambert hit never reads: `Bsdf::at`, `BsdfAt::eval_pdf` and
    /// `BsdfAt::sample` take their `lambert` branches, `mirror` and `refraction` return
    /// before any lobe parameter, and the functions that read them assert (in debug
    /// builds) that the BSDF is not diffuse-only. The test
    /// `lambert_fast_path_gives_the_general_bits` compares every public result against
    /// [`Bsdf::general`].
    fn lambert(params: &BsdfParams, normals: Normals, base: &BaseLobes) -> Bsdf {
        let inert = Bsdf::LAMBERT_INERT;
        Bsdf {
            n_in: normals.n_in,
            n: normals.n,
            ng: normals.ng,
            valid: normals.valid,
            diffuse: base.diffuse,
            // `Bsdf::frame` follows the anisotropy direction whatever the lobes: the
            // diffuse sample's tangent frame, hence its bits, depend on it.
            ggx: {
                let (_, aniso, aniso_t) = Ggx::direction(params);
                Ggx {
                    aniso,
                    aniso_t,
                    ..inert.ggx
                }
            },
            lambert: true,
            ..inert
        }
    }

    /// What a diffuse-only BSDF holds in the lobes it never reads: no reflection,
    /// transmission, coat or sheen (the values its predicates `has_specular_lobe`,
    /// `has_transmission`, `is_delta_only` and `mirror` test, as the general
    /// construction has them for such a material), zero roughness, F0, tints and an
    /// index-matched interface: nearly all zeros, so building it is a few wide stores.
    const LAMBERT_INERT: Bsdf = Bsdf {
        n_in: Vec3::Z,
        n: Vec3::Z,
        ng: Vec3::Z,
        valid: false,
        fresnel: Fresnel::INERT,
        ggx: Ggx {
            roughness: 0.0,
            alpha: 0.0,
            alpha_b: 0.0,
            aniso: false,
            aniso_t: Vec3::ZERO,
            delta: false,
        },
        diffuse: Diffuse { tint: Vec3::ZERO },
        reflection: Reflection {
            on: false,
            max: 0.0,
        },
        transmission: Transmission {
            tint: Vec3::ZERO,
            on: false,
            delta: false,
            eta: 1.0,
        },
        coat: Coat {
            strength: 0.0,
            alpha: 0.0,
            roughness: 0.0,
            delta: false,
            n: None,
        },
        sheen: Sheen {
            color: Vec3::ZERO,
            max: 0.0,
            roughness: 0.0,
        },
        lambert: true,
    };

    /// Every lobe built and sanitised from `params`, and `lambert` unset: the
    /// construction of any material that is not diffuse-only, and the reference the
    /// tests compare the diffuse-only one against.
    fn general(params: &BsdfParams, normals: Normals, base: &BaseLobes) -> Bsdf {
        let ggx = Ggx::new(params);
        let transmission = Transmission::new(params, base.transmission_tint, ggx.delta);
        Bsdf {
            n_in: normals.n_in,
            n: normals.n,
            ng: normals.ng,
            valid: normals.valid,
            fresnel: Fresnel::new(
                params,
                base.base,
                base.metallic,
                base.specular,
                Film::new(params),
            ),
            ggx,
            diffuse: base.diffuse,
            reflection: base.reflection,
            transmission,
            coat: Coat::new(params, normals.ng),
            sheen: Sheen::new(params),
            lambert: false,
        }
    }

    /// [`Bsdf::general`] from the inputs of [`Bsdf::new`], for the tests.
    #[cfg(test)]
    fn new_general(params: &BsdfParams, n: Vec3, ng: Vec3) -> Bsdf {
        Bsdf::general(params, Normals::new(n, ng), &BaseLobes::new(params))
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

    /// True when the material has a (non-zero) Lambert lobe.
    pub fn has_diffuse(&self) -> bool {
        self.valid && self.diffuse.tint.max_element() > 0.0
    }

    /// True when the material has a reflection lobe (metal or dielectric specular, or a
    /// clear coat). Unlike [`crate::material::Material::has_specular`] a black
    /// `specular_color` still counts: glTF keeps F90 = `specular`, so grazing reflection
    /// remains.
    pub fn has_specular_lobe(&self) -> bool {
        self.valid && (self.reflection.on || self.coat.strength > 0.0)
    }

    /// True when the material transmits (non-zero transmission tint).
    pub fn has_transmission(&self) -> bool {
        self.valid && self.transmission.on
    }

    /// Every lobe is delta (perfect mirror/glass): light sampling cannot contribute.
    /// False for a material with no lobe at all (black Lambert).
    pub fn is_delta_only(&self) -> bool {
        let coat = self.coat.strength > 0.0;
        let any = self.reflection.on || self.transmission.on || coat;
        self.valid
            && any
            && !self.has_diffuse()
            && !(self.sheen.max > 0.0)
            && (!self.reflection.on || self.ggx.delta)
            && (!self.transmission.on || self.transmission.delta)
            && (!coat || self.coat.delta)
    }

    /// `base_color (1-metallic) (1-transmission)`, for ambient/AO-style shading.
    pub fn diffuse_albedo(&self) -> Vec3 {
        self.diffuse.tint
    }

    /// The lobes beyond the diffuse one are about to be read. A diffuse-only BSDF holds
    /// inert values there ([`Bsdf::LAMBERT_INERT`]), so reaching such a read with one
    /// would change the image: checked in debug builds (and so in the tests).
    #[inline]
    fn layers_read(&self) {
        debug_assert!(!self.lambert, "a diffuse-only BSDF reached its inert lobes");
    }

    /// A delta sample with throughput `weight / prob`.
    fn delta_sample(&self, wi: Vec3, weight: Vec3, prob: f32, lobe: Lobe) -> Option<BsdfSample> {
        self.layers_read();
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

/// The normals of [`Bsdf::new`], made unit and oriented.
#[derive(Clone, Copy, Debug)]
struct Normals {
    valid: bool,
    /// Shading normal as passed (unit), shading normal on `ng`'s side, geometric normal.
    n_in: Vec3,
    n: Vec3,
    ng: Vec3,
}

impl Normals {
    fn new(n: Vec3, ng: Vec3) -> Normals {
        let (valid, n_in, ng) = match (unit(n), unit(ng)) {
            (Some(n), Some(ng)) => (true, n, ng),
            (Some(n), None) => (true, n, n),
            (None, Some(ng)) => (true, ng, ng),
            (None, None) => (false, Vec3::Z, Vec3::Z),
        };
        let n = if n_in.dot(ng) < 0.0 { -n_in } else { n_in };
        Normals { valid, n_in, n, ng }
    }
}

/// The sanitised parameters both constructions share, from which [`Bsdf::new`] tells a
/// diffuse-only material: the base colour, metallic, specular and transmission factors
/// and the diffuse, transmission and reflection weights made of them.
#[derive(Clone, Copy, Debug)]
struct BaseLobes {
    base: Vec3,
    metallic: f32,
    specular: f32,
    diffuse: Diffuse,
    transmission_tint: Vec3,
    reflection: Reflection,
}

impl BaseLobes {
    fn new(params: &BsdfParams) -> BaseLobes {
        let base = sat3(params.base_color);
        let metallic = sat(params.metallic);
        let specular = sat(params.specular);
        let transmission = sat(params.transmission);
        let dielectric = (1.0 - metallic) * specular;
        BaseLobes {
            base,
            metallic,
            specular,
            diffuse: Diffuse {
                tint: base * ((1.0 - metallic) * (1.0 - transmission)),
            },
            transmission_tint: base * ((1.0 - metallic) * transmission),
            reflection: Reflection {
                on: dielectric > 0.0 || metallic > 0.0,
                max: dielectric + metallic,
            },
        }
    }

    /// Only the diffuse lobe: no dielectric or metal reflection, no transmission (its
    /// tint as [`Transmission`] holds it), no coat or sheen. `sat(x) > 0` exactly when
    /// `x > 0` (NaN and negatives become 0, `-0.0` stays), so the coat's strength and the
    /// sheen's largest channel are tested on the raw parameters without sanitising
    /// them; test `lambert_flag_is_the_general_lobes_test` holds it to the lobes'
    /// own test.
    fn diffuse_only(&self, params: &BsdfParams) -> bool {
        let sheen = params.sheen_color;
        let no_coat = !(params.clearcoat > 0.0);
        let no_sheen = !(sheen.x > 0.0 || sheen.y > 0.0 || sheen.z > 0.0);
        !self.reflection.on && self.transmission_tint.max_element() <= 0.0 && no_coat && no_sheen
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
