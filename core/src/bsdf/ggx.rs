//! The base's GGX (Trowbridge-Reitz) microfacet distribution, isotropic or stretched by
//! `KHR_materials_anisotropy`, with Smith's height-correlated masking and sampling of the
//! visible normals (Heitz 2018). Reflection and rough transmission share it; the clear
//! coat uses the isotropic functions with its own alpha.

use glam::{Vec2, Vec3};
use std::f32::consts::{PI, TAU};

use super::{BsdfParams, DELTA_ALPHA, MIN_ALPHA, sat, unit};

/// The base's GGX distribution at one point.
#[derive(Clone, Copy, Debug)]
pub(super) struct Ggx {
    /// Perceptual roughness (Whitted's mirror test uses it).
    pub(super) roughness: f32,
    /// GGX alpha, clamped to >= [`MIN_ALPHA`]; with anisotropy, along its direction.
    pub(super) alpha: f32,
    /// GGX alpha across the anisotropy direction (`alpha` when isotropic).
    pub(super) alpha_b: f32,
    /// Anisotropic: the frame's tangent follows `aniso_t` and the GGX lobe is
    /// `(alpha, alpha_b)`. Isotropic materials keep the functions (and bits) they had.
    pub(super) aniso: bool,
    pub(super) aniso_t: Vec3,
    /// Alpha below [`DELTA_ALPHA`]: the reflection is a perfect mirror (and the
    /// transmission a perfect refraction).
    pub(super) delta: bool,
}

impl Ggx {
    pub(super) fn new(params: &BsdfParams) -> Ggx {
        let roughness = sat(params.roughness);
        let a_iso = roughness * roughness;
        let (strength, aniso, aniso_t) = Ggx::direction(params);
        // alpha_t = mix(alpha, 1, strength^2), as the extension gives it.
        let a = if aniso {
            a_iso + (1.0 - a_iso) * strength * strength
        } else {
            a_iso
        };
        Ggx {
            roughness,
            alpha: a.max(MIN_ALPHA),
            alpha_b: if aniso {
                a_iso.max(MIN_ALPHA)
            } else {
                a.max(MIN_ALPHA)
            },
            aniso,
            aniso_t,
            delta: a < DELTA_ALPHA,
        }
    }

    /// The anisotropy strength (sanitised), whether the lobe is anisotropic and its
    /// direction (unit; zero when isotropic). A diffuse-only BSDF needs these alone:
    /// its frame's tangent follows the direction ([`super::Bsdf::frame`]).
    pub(super) fn direction(params: &BsdfParams) -> (f32, bool, Vec3) {
        let strength = sat(params.anisotropy);
        // Without anisotropy the direction is not normalised: only `aniso` lobes read it.
        let aniso_t = if strength > 0.0 {
            unit(params.anisotropy_direction).unwrap_or(Vec3::ZERO)
        } else {
            Vec3::ZERO
        };
        (strength, strength > 0.0 && aniso_t != Vec3::ZERO, aniso_t)
    }

    /// The distribution at local microfacet normal `m` (`a2` = alpha^2).
    pub(super) fn d(&self, m: Vec3, a2: f32) -> f32 {
        if self.aniso {
            ggx_d_aniso(m, self.alpha, self.alpha_b)
        } else {
            ggx_d(m, a2)
        }
    }

    /// Smith Λ of the distribution for local direction `w`.
    pub(super) fn lambda(&self, w: Vec3, a2: f32) -> f32 {
        if self.aniso {
            ggx_lambda_aniso(w, self.alpha, self.alpha_b)
        } else {
            ggx_lambda(w, a2)
        }
    }
}

/// GGX normal distribution in the local frame, written with `x^2 + y^2 + a^2 z^2`
/// (= `cos^2 (a^2 - 1) + 1`) so it stays accurate for tiny alpha near the normal.
pub(super) fn ggx_d(m: Vec3, a2: f32) -> f32 {
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
pub(super) fn ggx_lambda(w: Vec3, a2: f32) -> f32 {
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
pub(super) fn sample_vndf(wo: Vec3, ax: f32, ay: f32, u: Vec2) -> Option<Vec3> {
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
