//! The thin-film Fresnel term of `KHR_materials_iridescence`: Belcour and Barla 2017
//! ("A Practical Extension to Microfacet Theory for the Modeling of Varying
//! Iridescence"), in the approximation the extension and the Khronos Sample Viewer use
//! (Schlick reflectances at both interfaces, phase shifts of 0 or pi, the spectral
//! integral evaluated in Fourier space against Gaussian fits of the CIE XYZ curves, then
//! converted to linear Rec. 709 RGB).
//!
//! Two choices follow the Sample Viewer where the extension's text differs from it: the
//! optical path difference uses the cosine *inside* the film (`cos_theta2`; the
//! extension's notes print `cos_theta1`, a typo the viewer does not copy), and the
//! outside medium is always air (the extension asks for the coat's ior 1.5 under a clear
//! coat; the viewer uses 1.0, and dray keeps the coat and the film independent).
//!
//! **Deviation:** the RGB result is clamped to at most 1 per channel (the viewer clamps
//! only below 0). The fitted spectral terms can push a channel slightly above 1, and a
//! reflectance above 1 would make the BSDF gain energy.

use glam::{Mat3, Vec3};
use std::f32::consts::PI;

/// Default `iridescenceIor` of the extension.
pub const DEFAULT_IOR: f32 = 1.3;

/// The Fresnel reflectance (RGB) of a thin film of index `film_ior` and thickness
/// `thickness_nm` nanometres lying on a base whose normal-incidence reflectance is
/// `base_f0`, seen from a medium of index `outside_ior` at cosine `cos1` (to the
/// microfacet normal). Every value is in [0, 1].
pub fn fresnel(
    outside_ior: f32,
    film_ior: f32,
    cos1: f32,
    thickness_nm: f32,
    base_f0: Vec3,
) -> Vec3 {
    let cos1 = cos1.clamp(0.0, 1.0);
    // The film fades into the outside medium as its thickness goes to 0.
    let film = lerp(outside_ior, film_ior, smoothstep(0.0, 0.03, thickness_nm));
    let sin2_sq = sq(outside_ior / film) * (1.0 - cos1 * cos1);
    let cos2_sq = 1.0 - sin2_sq;
    if cos2_sq.is_nan() || cos2_sq < 0.0 {
        // Total internal reflection inside the film.
        return Vec3::ONE;
    }
    let cos2 = cos2_sq.sqrt();

    // First interface: outside to film.
    let r12 = schlick(ior_to_f0(film, outside_ior), cos1);
    let t121 = 1.0 - r12;
    let phi12 = if film < outside_ior { PI } else { 0.0 };
    let phi21 = PI - phi12;

    // Second interface: film to base (the base's ior from its F0, a real index: metals
    // are approximated without their extinction, as the extension says).
    let base_ior = f0_to_ior(base_f0.clamp(Vec3::ZERO, Vec3::splat(0.9999)));
    let r1 = Vec3::from_array(base_ior.to_array().map(|b| ior_to_f0(b, film)));
    let r23 = Vec3::from_array(r1.to_array().map(|r| schlick(r, cos2)));
    let phi23 = Vec3::from_array(base_ior.to_array().map(|b| if b < film { PI } else { 0.0 }));

    let opd = 2.0 * film * thickness_nm * cos2;
    let phi = Vec3::splat(phi21) + phi23;

    // Airy summation, the first two orders of interference spectrally integrated.
    let r123 = (r23 * r12).clamp(Vec3::splat(1e-5), Vec3::splat(0.9999));
    let r123_sqrt = Vec3::new(r123.x.sqrt(), r123.y.sqrt(), r123.z.sqrt());
    let rs = r23 * (t121 * t121) / (Vec3::ONE - r123);
    let mut i = Vec3::splat(r12) + rs;
    let mut cm = rs - Vec3::splat(t121);
    for m in 1..=2 {
        let m = m as f32;
        cm *= r123_sqrt;
        i += cm * (2.0 * sensitivity(m * opd, m * phi));
    }
    let i = i.clamp(Vec3::ZERO, Vec3::ONE);
    if i.is_finite() { i } else { Vec3::ONE }
}

/// Fourier transform of the XYZ sensitivity curves (Gaussian fits) at optical path
/// difference `opd` (nm) with phase `shift`, in linear Rec. 709 RGB.
fn sensitivity(opd: f32, shift: Vec3) -> Vec3 {
    let phase = 2.0 * PI * opd * 1.0e-9;
    let val = Vec3::new(5.4856e-13, 4.4201e-13, 5.2481e-13);
    let pos = Vec3::new(1.6810e+06, 1.7953e+06, 2.2084e+06);
    let var = Vec3::new(4.3278e+09, 9.3046e+09, 6.6121e+09);
    let gauss = |v: f32, p: f32, w: f32, s: f32| {
        v * (2.0 * PI * w).sqrt() * (p * phase + s).cos() * (-phase * phase * w).exp()
    };
    let mut xyz = Vec3::new(
        gauss(val.x, pos.x, var.x, shift.x),
        gauss(val.y, pos.y, var.y, shift.y),
        gauss(val.z, pos.z, var.z, shift.z),
    );
    xyz.x += gauss(9.7470e-14, 2.2399e+06, 4.5282e+09, shift.x);
    xyz /= 1.0685e-7;
    xyz_to_rec709() * xyz
}

/// CIE XYZ to linear Rec. 709 (sRGB primaries, D65), digits as the extension prints them.
#[allow(clippy::excessive_precision)]
fn xyz_to_rec709() -> Mat3 {
    Mat3::from_cols(
        Vec3::new(3.2404542, -0.9692660, 0.0556434),
        Vec3::new(-1.5371385, 1.8760108, -0.2040259),
        Vec3::new(-0.4985314, 0.0415560, 1.0572252),
    )
}

/// Normal-incidence reflectance between media of indices `transmitted` and `incident`.
fn ior_to_f0(transmitted: f32, incident: f32) -> f32 {
    sq((transmitted - incident) / (transmitted + incident))
}

/// The index (against air) whose normal-incidence reflectance is `f0` (< 1).
fn f0_to_ior(f0: Vec3) -> Vec3 {
    let s = Vec3::new(f0.x.sqrt(), f0.y.sqrt(), f0.z.sqrt());
    (Vec3::ONE + s) / (Vec3::ONE - s)
}

fn schlick(f0: f32, c: f32) -> f32 {
    let m = (1.0 - c).clamp(0.0, 1.0);
    let m2 = m * m;
    f0 + (1.0 - f0) * (m2 * m2 * m)
}

fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

fn lerp(a: f32, b: f32, t: f32) -> f32 {
    a + (b - a) * t
}

fn sq(x: f32) -> f32 {
    x * x
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chroma(c: Vec3) -> Vec3 {
        c / c.element_sum()
    }

    #[test]
    fn reflectance_is_a_fraction_and_thickness_shifts_the_hue() {
        let f0 = Vec3::splat(0.04);
        for t in [0.0, 1e-3, 50.0, 250.0, 400.0, 800.0, 1200.0, 1e5] {
            for ior in [1.0, 1.3, 1.8, 2.5] {
                for c in [0.0, 0.01, 0.3, 0.7, 1.0] {
                    for base in [f0, Vec3::ONE, Vec3::ZERO, Vec3::new(0.9, 0.6, 0.2)] {
                        let f = fresnel(1.0, ior, c, t, base);
                        assert!(
                            f.is_finite() && f.min_element() >= 0.0 && f.max_element() <= 1.0,
                            "t {t} ior {ior} c {c} base {base}: {f}"
                        );
                    }
                }
            }
        }
        // Thin films of different thickness reflect different colours, and the colour
        // also changes with the viewing angle.
        let a = chroma(fresnel(1.0, 1.3, 1.0, 250.0, f0));
        let b = chroma(fresnel(1.0, 1.3, 1.0, 400.0, f0));
        assert!((a - b).abs().max_element() > 0.05, "{a} vs {b}");
        let c = chroma(fresnel(1.0, 1.3, 0.4, 250.0, f0));
        assert!((a - c).abs().max_element() > 0.02, "{a} vs {c}");
        // A very thick film averages out to an uncoloured reflectance.
        let thick = chroma(fresnel(1.0, 1.3, 1.0, 1e5, f0));
        assert!(
            (thick - Vec3::splat(1.0 / 3.0)).abs().max_element() < 0.02,
            "{thick}"
        );
        // Grazing light is reflected almost entirely, as by any interface.
        assert!(fresnel(1.0, 1.3, 0.0, 300.0, f0).min_element() > 0.9);
    }
}
