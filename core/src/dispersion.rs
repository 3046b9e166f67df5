//! `KHR_materials_dispersion` in an RGB renderer: a path that meets a dispersive
//! transmissive surface follows one colour channel from there on, refracted with that
//! channel's index.
//!
//! The channel is drawn with probability proportional to the path's weight in it,
//! `p_c = w_c / (w_r + w_g + w_b)`, from the path's own counter-based stream
//! ([`crate::sampling::Purpose::Dispersion`]), and the path then carries
//! `w_c / p_c = w_r + w_g + w_b` in that channel and 0 in the others: the expectation is
//! the weight each channel would have had with its own index, so the estimate is
//! unbiased, and a white path carries 3 times its weight in the channel it picked. A
//! path whose weight is already in one channel (it picked at an earlier dispersive
//! surface, or its other channels were absorbed) keeps that channel with probability 1
//! and its weight unchanged, so nothing needs to be remembered in the ray: the weight
//! is the state. The BSDF at the surface is an ordinary one with the channel's index,
//! so its pdfs, and the MIS weights built on them, stay right.
//!
//! Each channel's index is the extension's Cauchy fit through the Abbe number,
//! `n(λ) = max(n_d + (n_d - 1) / V_d (523655 / λ² - 1.5168), 1)` with
//! `1 / V_d = dispersion / 20` and `n_d` the material's `ior`, at the Fraunhofer lines the
//! Abbe number is defined on: C (656.3 nm) for red, d (587.6 nm, the material's own
//! `ior`) for green and F (486.1 nm) for blue. Red to blue then spans `n_F - n_C =
//! (n_d - 1) / V_d`, the spread the extension's notes give its RGB renderers.

use glam::Vec3;

/// Wavelengths (nm) standing for the red, green and blue channels: the Fraunhofer C, d
/// and F lines.
pub const WAVELENGTHS_NM: [f32; 3] = [656.3, 587.6, 486.1];

/// The refraction index of a material of index `ior` (at 587.6 nm) and `dispersion`
/// (20 / Abbe number) for colour channel `channel` (0 red, 1 green, 2 blue). Exactly
/// `ior` without dispersion.
pub fn channel_ior(ior: f32, dispersion: f32, channel: usize) -> f32 {
    let Some(&lambda) = WAVELENGTHS_NM.get(channel) else {
        return ior;
    };
    if !(dispersion > 0.0 && dispersion.is_finite() && ior.is_finite()) {
        return ior;
    }
    let n = ior + (ior - 1.0) * (dispersion / 20.0) * (523_655.0 / (lambda * lambda) - 1.5168);
    n.max(1.0)
}

/// The channel a path of weight `weight` follows through a dispersive surface, given
/// its uniform number `u`, and its weight from there on (all of it in that channel).
/// `None` when the weight carries nothing (or is not finite): the path is left as is.
pub fn pick_channel(weight: Vec3, u: f32) -> Option<(usize, Vec3)> {
    let w = weight.to_array();
    if !weight.is_finite() || w.iter().any(|&c| c < 0.0) {
        return None;
    }
    let live = || (0..3).filter(|&c| w[c] > 0.0);
    let last = live().next_back()?;
    if live().count() == 1 {
        // Already in one channel: it stays there, with its weight.
        return Some((last, weight));
    }
    let target = u * (w[0] + w[1] + w[2]);
    let mut acc = 0.0;
    // Rounding can leave `target` past the last partial sum: then the last live channel.
    let mut channel = last;
    for c in live() {
        acc += w[c];
        if target < acc {
            channel = c;
            break;
        }
    }
    let sum = w[0] + w[1] + w[2];
    let mut out = [0.0; 3];
    out[channel] = sum;
    Some((channel, Vec3::from_array(out)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn channel_indices_follow_the_abbe_number() {
        for ior in [1.33, 1.5, 2.42] {
            assert_eq!(channel_ior(ior, 0.0, 0).to_bits(), ior.to_bits());
            assert_eq!(channel_ior(ior, 0.0, 2).to_bits(), ior.to_bits());
            for dispersion in [0.33, 1.0, 2.04] {
                let n = [0, 1, 2].map(|c| channel_ior(ior, dispersion, c));
                assert!(n[0] < n[1] && n[1] < n[2], "{n:?}");
                // Green is the material's index; red to blue is (n_d - 1) / V_d.
                assert!((n[1] - ior).abs() < 1e-3 * ior, "{n:?}");
                let spread = (ior - 1.0) * dispersion / 20.0;
                assert!(
                    (n[2] - n[0] - spread).abs() < 2e-3 * spread,
                    "{n:?} {spread}"
                );
            }
        }
        // Never below 1, whatever the dispersion.
        assert_eq!(channel_ior(1.01, 1e4, 0), 1.0);
        assert_eq!(channel_ior(1.5, f32::NAN, 0), 1.5);
    }

    #[test]
    fn the_channel_pick_is_unbiased_and_sticks() {
        for w in [
            Vec3::ONE,
            Vec3::new(0.2, 0.5, 0.05),
            Vec3::new(0.0, 0.3, 0.9),
        ] {
            let n = 30_000;
            let mut mean = Vec3::ZERO;
            for i in 0..n {
                let u = (i as f32 + 0.5) / n as f32;
                let (c, out) = pick_channel(w, u).unwrap();
                assert!(w[c] > 0.0);
                assert_eq!(out.to_array().iter().filter(|&&x| x > 0.0).count(), 1);
                mean += out / n as f32;
            }
            assert!(
                (mean - w).abs().max_element() < 1e-3 * w.max_element(),
                "{w}: {mean}"
            );
        }
        // A path in one channel keeps it and its weight, whatever the number.
        for u in [0.0, 0.5, 0.999_999] {
            let w = Vec3::new(0.0, 0.0, 2.5);
            assert_eq!(pick_channel(w, u), Some((2, w)));
        }
        assert_eq!(pick_channel(Vec3::ZERO, 0.3), None);
        assert_eq!(pick_channel(Vec3::new(f32::NAN, 1.0, 1.0), 0.3), None);
        assert_eq!(pick_channel(Vec3::new(-1.0, 1.0, 1.0), 0.3), None);
        // The largest number still picks a live channel.
        let (c, _) = pick_channel(Vec3::new(0.3, 0.3, 0.0), 1.0).unwrap();
        assert!(c < 2);
    }
}
