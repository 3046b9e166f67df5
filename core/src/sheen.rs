//! The sheen lobe of `KHR_materials_sheen`: the "Charlie" distribution with its own
//! fitted masking term (Estevez and Kulla 2017, "Production Friendly Microfacet Sheen
//! BRDF"), as the extension and the Khronos Sample Viewer use them, and its directional
//! albedo, which scales the layers under the sheen so the sum never gains energy.
//!
//! **Deviation:** the Charlie lobe reflects more than it receives at grazing angles when
//! it is smooth (directional albedo 2.8 at `cos_o` = 0.01 and roughness 0.07; 1.08 at
//! roughness 0.5), and so does the cheaper visibility of Neubelt and Pettineo. dray
//! divides the lobe by `max(1, E(cos_o), E(cos_i))`, with `E` its raw albedo: that is
//! reciprocal, leaves the lobe unchanged wherever it conserves energy, and bounds its
//! albedo by 1 everywhere. [`albedo`] is the albedo of the lobe so divided.
//!
//! The albedo table is computed once, on first use, by a fixed quadrature in a fixed
//! order, so every worker holds the same bits.

use std::f32::consts::PI;
use std::sync::OnceLock;

/// Smallest sheen roughness: below it the distribution is a band too thin for the
/// albedo table to resolve (the Sample Viewer clamps similarly).
pub const MIN_ROUGHNESS: f32 = 0.07;

/// Table resolution in `sqrt(cosine)` (denser at grazing angles, where the albedo
/// changes fastest) and in roughness.
const N_COS: usize = 32;
const N_ROUGH: usize = 32;
/// Quadrature points per table entry (in `cos_i` and in `phi`).
const Q_COS: usize = 80;
const Q_PHI: usize = 80;

/// Charlie distribution for the half vector's cosine `cos_h` with `alpha` = roughness^2:
/// `(2 + 1/alpha) sin(theta_h)^(1/alpha) / (2 pi)`.
pub fn d_charlie(cos_h: f32, alpha: f32) -> f32 {
    let inv = 1.0 / alpha;
    let sin2 = (1.0 - cos_h * cos_h).max(0.0);
    (2.0 + inv) * sin2.powf(0.5 * inv) / (2.0 * PI)
}

/// Estevez and Kulla's fit of the Charlie distribution's `ln Λ` for cosine `x` at sheen
/// roughness `r`, its coefficients interpolated by `(1 - r)^2` as in their paper.
fn l_fit(x: f32, r: f32) -> f32 {
    let t = (1.0 - r) * (1.0 - r);
    let mix = |rough: f32, smooth: f32| rough + (smooth - rough) * t;
    let a = mix(21.5473, 25.3245);
    let b = mix(3.82987, 3.32435);
    let c = mix(0.19823, 0.16801);
    let d = mix(-1.97760, -1.27393);
    let e = mix(-4.32054, -4.85967);
    a / (1.0 + b * x.powf(c)) + d * x + e
}

/// Smith Λ of the Charlie distribution (the fit is made for cosines below 0.5 and
/// mirrored above, as the paper does).
fn lambda(cos: f32, r: f32) -> f32 {
    if cos < 0.5 {
        l_fit(cos, r).exp()
    } else {
        (2.0 * l_fit(0.5, r) - l_fit(1.0 - cos, r)).exp()
    }
}

/// Height-correlated visibility `G2 / (4 cos_o cos_i)` with the Charlie Λ.
pub fn v_charlie(cos_o: f32, cos_i: f32, r: f32) -> f32 {
    1.0 / ((1.0 + lambda(cos_o, r) + lambda(cos_i, r)) * (4.0 * cos_o * cos_i))
}

/// The raw white sheen lobe's value for local directions with cosines `cos_o`, `cos_i`
/// (both > 0) and half-vector cosine `cos_h`.
fn raw_lobe(cos_o: f32, cos_i: f32, cos_h: f32, roughness: f32) -> f32 {
    let r = roughness.clamp(MIN_ROUGHNESS, 1.0);
    let f = d_charlie(cos_h, r * r) * v_charlie(cos_o, cos_i, r);
    if f.is_finite() { f } else { 0.0 }
}

/// The white sheen lobe dray evaluates: the raw lobe divided by
/// `max(1, E(cos_o), E(cos_i))` (see the module's deviation note).
pub fn lobe(cos_o: f32, cos_i: f32, cos_h: f32, roughness: f32) -> f32 {
    let norm = 1.0f32
        .max(lookup(raw_table(), cos_o, roughness))
        .max(lookup(raw_table(), cos_i, roughness));
    raw_lobe(cos_o, cos_i, cos_h, roughness) / norm
}

/// Directional albedo of the white sheen lobe [`lobe`], `E(cos_o) = integral of lobe
/// cos_i`, interpolated from its table. At most 1.
pub fn albedo(cos_o: f32, roughness: f32) -> f32 {
    lookup(table(), cos_o, roughness).min(1.0)
}

/// Bilinear interpolation of a table over (cosine, roughness).
fn lookup(t: &[f32], cos: f32, roughness: f32) -> f32 {
    let x = (cos.clamp(0.0, 1.0).sqrt() * (N_COS - 1) as f32).min((N_COS - 1) as f32);
    let y = ((roughness.clamp(MIN_ROUGHNESS, 1.0) - MIN_ROUGHNESS) / (1.0 - MIN_ROUGHNESS)
        * (N_ROUGH - 1) as f32)
        .min((N_ROUGH - 1) as f32);
    let (x0, y0) = (x as usize, y as usize);
    let (x1, y1) = ((x0 + 1).min(N_COS - 1), (y0 + 1).min(N_ROUGH - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let at = |i: usize, j: usize| t.get(j * N_COS + i).copied().unwrap_or(0.0);
    let a = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
    let b = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
    a * (1.0 - fy) + b * fy
}

/// Albedo of the raw lobe, which normalises it.
fn raw_table() -> &'static [f32] {
    static TABLE: OnceLock<Vec<f32>> = OnceLock::new();
    TABLE.get_or_init(|| tabulate(raw_lobe))
}

/// Albedo of the normalised lobe.
fn table() -> &'static [f32] {
    static TABLE: OnceLock<Vec<f32>> = OnceLock::new();
    TABLE.get_or_init(|| tabulate(lobe))
}

fn tabulate(f: fn(f32, f32, f32, f32) -> f32) -> Vec<f32> {
    let mut t = Vec::with_capacity(N_COS * N_ROUGH);
    for j in 0..N_ROUGH {
        let r = MIN_ROUGHNESS + (1.0 - MIN_ROUGHNESS) * j as f32 / (N_ROUGH - 1) as f32;
        for i in 0..N_COS {
            // The grazing entry uses a cosine just above 0, where the lobe is finite.
            let x = i as f32 / (N_COS - 1) as f32;
            let cos_o = (x * x).max(1e-3);
            t.push(integrate(f, cos_o, r));
        }
    }
    t
}

/// `integral over the hemisphere of f(wo, wi) cos_i`, by the midpoint rule in `cos_i`
/// and `phi` (phi over [0, pi], doubled: the lobe is symmetric about wo's plane).
fn integrate(f: fn(f32, f32, f32, f32) -> f32, cos_o: f32, roughness: f32) -> f32 {
    let sin_o = (1.0 - cos_o * cos_o).max(0.0).sqrt();
    let mut sum = 0.0f64;
    for a in 0..Q_COS {
        let cos_i = (a as f32 + 0.5) / Q_COS as f32;
        let sin_i = (1.0 - cos_i * cos_i).max(0.0).sqrt();
        for b in 0..Q_PHI {
            let phi = PI * (b as f32 + 0.5) / Q_PHI as f32;
            // wo = (sin_o, 0, cos_o), wi = (sin_i cos phi, sin_i sin phi, cos_i).
            let h = [sin_o + sin_i * phi.cos(), sin_i * phi.sin(), cos_o + cos_i];
            let len = (h[0] * h[0] + h[1] * h[1] + h[2] * h[2]).sqrt();
            if len <= 0.0 {
                continue;
            }
            sum += f64::from(f(cos_o, cos_i, h[2] / len, roughness) * cos_i);
        }
    }
    // d omega = d cos_i d phi; phi covers [0, 2 pi] by symmetry.
    (sum * (1.0 / Q_COS as f64) * (2.0 * std::f64::consts::PI / Q_PHI as f64)) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn albedo_is_a_fraction_and_the_table_interpolates_the_integral() {
        for r in [MIN_ROUGHNESS, 0.3, 0.6, 1.0] {
            for c in [0.01f32, 0.05, 0.3, 0.7, 1.0] {
                let e = albedo(c, r);
                assert!(e > 0.0 && e <= 1.0, "r {r} cos {c}: {e}");
                let direct = integrate(lobe, c.max(1e-3), r).min(1.0);
                assert!((e - direct).abs() < 0.02, "r {r} cos {c}: {e} vs {direct}");
            }
        }
    }
}
