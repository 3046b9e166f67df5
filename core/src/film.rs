//! The film: per-pixel sums in fixed point, so accumulation is exact and independent of
//! the order contributions arrive in (the same job gives the same bits on 1 thread or 16,
//! on 1 worker or many). Box filter: a sample counts for the pixel it was taken in.
//!
//! A contribution is converted once, deterministically, to an integer with 24 fractional
//! bits; integer addition is associative, so sums never depend on order. Non-finite or
//! negative contributions are counted and dropped: NaN and Inf never reach the image.

use std::path::Path;

use glam::Vec3;

/// Fixed-point scale: 2^24 steps per unit of radiance.
pub const FIXED_SCALE: f64 = (1u64 << 24) as f64;
/// Largest contribution component accepted (radiance units); larger values are clamped
/// so that a pixel sum cannot overflow an i64 over 2^16 samples.
pub const MAX_CONTRIBUTION: f32 = 1.0e7;

/// Convert one contribution to fixed point. Returns `None` for non-finite input.
#[inline]
pub fn to_fixed(v: Vec3) -> Option<[i64; 3]> {
    if !v.is_finite() {
        return None;
    }
    let c = v.clamp(Vec3::ZERO, Vec3::splat(MAX_CONTRIBUTION));
    Some([c.x, c.y, c.z].map(|x| round_non_negative(x as f64 * FIXED_SCALE)))
}

/// `x.round() as i64` for `0 <= x < 2^52`, without the call to libm's `round` that
/// generic x86-64 code makes for it (three per contribution). Below 2^52 the fraction
/// `x - trunc(x)` is exact, so this rounds half away from zero exactly as `round` does.
#[inline]
fn round_non_negative(x: f64) -> i64 {
    let t = x as i64;
    t + i64::from(x - t as f64 >= 0.5)
}

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Film {
    pub width: u32,
    pub height: u32,
    sums: Vec<[i64; 3]>,
    /// Contributions dropped because they were NaN or infinite.
    pub nonfinite: u64,
}

#[derive(Debug, thiserror::Error)]
pub enum FilmError {
    #[error("{path}: cannot write PNG: {message}")]
    Png { path: String, message: String },
    #[error("{path}: cannot write EXR: {message}")]
    Exr { path: String, message: String },
}

impl Film {
    pub fn new(width: u32, height: u32) -> Film {
        Film {
            width,
            height,
            sums: vec![[0; 3]; width as usize * height as usize],
            nonfinite: 0,
        }
    }

    /// Add a contribution to pixel `pixel` (row-major index). Out-of-range pixels are ignored.
    #[inline]
    /// The bytes its sums take in memory (what a coordinator keeping finished images
    /// counts against its budget).
    pub fn heap_bytes(&self) -> u64 {
        (self.sums.len() as u64).saturating_mul(std::mem::size_of::<[i64; 3]>() as u64)
    }

    pub fn add(&mut self, pixel: u32, value: Vec3) {
        match to_fixed(value) {
            Some(f) => {
                if let Some(s) = self.sums.get_mut(pixel as usize) {
                    for c in 0..3 {
                        s[c] = s[c].wrapping_add(f[c]);
                    }
                }
            }
            None => self.nonfinite += 1,
        }
    }

    /// Add an already-converted fixed-point sum (from another film or a remote worker).
    #[inline]
    pub fn add_fixed(&mut self, pixel: u32, value: [i64; 3]) {
        if let Some(s) = self.sums.get_mut(pixel as usize) {
            for c in 0..3 {
                s[c] = s[c].wrapping_add(value[c]);
            }
        }
    }

    /// Merge another film of the same size (exact, order-free).
    pub fn merge(&mut self, other: &Film) {
        for (a, b) in self.sums.iter_mut().zip(&other.sums) {
            for c in 0..3 {
                a[c] = a[c].wrapping_add(b[c]);
            }
        }
        self.nonfinite += other.nonfinite;
    }

    pub fn sum_fixed(&self, pixel: u32) -> [i64; 3] {
        self.sums.get(pixel as usize).copied().unwrap_or([0; 3])
    }

    /// Linear radiance of every pixel: the sum divided by `spp`.
    pub fn linear(&self, spp: u32) -> Vec<Vec3> {
        let k = 1.0 / (FIXED_SCALE * spp.max(1) as f64);
        self.sums
            .iter()
            .map(|s| {
                Vec3::new(
                    (s[0] as f64 * k) as f32,
                    (s[1] as f64 * k) as f32,
                    (s[2] as f64 * k) as f32,
                )
            })
            .collect()
    }

    /// 8-bit sRGB pixels of radiance times `scale` (clamped to [0,1] before encoding).
    pub fn srgb8(&self, spp: u32, scale: f32) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.sums.len() * 3);
        for p in self.linear(spp) {
            let p = p * scale;
            for c in [p.x, p.y, p.z] {
                out.push(linear_to_srgb8(c));
            }
        }
        out
    }

    /// Write an 8-bit sRGB PNG of radiance times `scale` (2^exposure).
    pub fn write_png(&self, path: &Path, spp: u32, scale: f32) -> Result<(), FilmError> {
        let buf = self.srgb8(spp, scale);
        image::save_buffer(
            path,
            &buf,
            self.width,
            self.height,
            image::ExtendedColorType::Rgb8,
        )
        .map_err(|e| FilmError::Png {
            path: path.display().to_string(),
            message: e.to_string(),
        })
    }

    /// Write [`Film::encode_exr`]'s bytes to `path`.
    pub fn write_exr(&self, path: &Path, spp: u32) -> Result<(), FilmError> {
        let fail = |message: String| FilmError::Exr {
            path: path.display().to_string(),
            message,
        };
        let bytes = self.encode_exr(spp).map_err(fail)?;
        std::fs::write(path, bytes).map_err(|e| fail(e.to_string()))
    }

    /// The image as linear f32 RGB OpenEXR (`dray render --exr`, GetImage). The same
    /// film gives the same bytes: blocks are compressed on one thread, because in
    /// parallel they land in the file in the order they finish.
    pub fn encode_exr(&self, spp: u32) -> Result<Vec<u8>, String> {
        use exr::prelude::{Image, SpecificChannels, Vec2, WritableImage};
        let lin = self.linear(spp);
        let w = self.width as usize;
        let channels = SpecificChannels::rgb(|Vec2(x, y): Vec2<usize>| {
            let p = lin[y * w + x];
            (p.x, p.y, p.z)
        });
        let mut out = std::io::Cursor::new(Vec::new());
        Image::from_channels((w, self.height as usize), channels)
            .write()
            .non_parallel()
            .to_buffered(&mut out)
            .map_err(|e| e.to_string())?;
        Ok(out.into_inner())
    }
}

/// The sRGB transfer function, clamped, rounded to 8 bits.
pub fn linear_to_srgb8(c: f32) -> u8 {
    let c = if c.is_finite() {
        c.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let s = if c <= 0.003_130_8 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0 + 0.5).clamp(0.0, 255.0) as u8
}

#[cfg(test)]
mod tests {
    #[test]
    fn rounding_without_libm_matches_round() {
        // Halves, the float just below a half, tiny values, the largest contribution,
        // and a sweep of f32 values scaled as contributions are.
        let mut xs = vec![
            0.0,
            0.5,
            1.5,
            2.5,
            0.49999999999999994,
            1.0 - f64::EPSILON / 2.0,
        ];
        xs.push(MAX_CONTRIBUTION as f64 * FIXED_SCALE);
        let mut f = 1.0e-12f32;
        while f < MAX_CONTRIBUTION {
            for g in [f, f.next_up(), f.next_down(), f * 1.37] {
                xs.push(g as f64 * FIXED_SCALE);
            }
            f *= 1.01;
        }
        for x in xs {
            assert_eq!(round_non_negative(x), x.round() as i64, "{x}");
        }
    }

    use super::*;

    #[test]
    fn order_free_and_nan_dropped() {
        let vals = [
            Vec3::new(0.1, 0.2, 0.3),
            Vec3::splat(1e-7),
            Vec3::splat(12345.678),
            Vec3::new(0.3, 0.0, 1.0),
        ];
        let mut a = Film::new(1, 1);
        let mut b = Film::new(1, 1);
        for v in vals {
            a.add(0, v);
        }
        for v in vals.iter().rev() {
            b.add(0, *v);
        }
        b.add(0, Vec3::new(f32::NAN, 0.0, 0.0));
        b.add(0, Vec3::splat(f32::INFINITY));
        assert_eq!(a.sum_fixed(0), b.sum_fixed(0));
        assert_eq!(b.nonfinite, 2);
        assert!(a.linear(1)[0].is_finite());
    }

    #[test]
    fn srgb_encoding() {
        assert_eq!(linear_to_srgb8(0.0), 0);
        assert_eq!(linear_to_srgb8(1.0), 255);
        assert_eq!(linear_to_srgb8(f32::NAN), 0);
        assert_eq!(linear_to_srgb8(0.2158605), 128);
    }
}
