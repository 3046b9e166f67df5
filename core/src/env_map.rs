//! An environment map (`--env-map FILE`, read by [`crate::env_map_file`]): an
//! equirectangular image of the radiance arriving from every direction, looked up per
//! pixel (piecewise constant, so the importance sampler's density is exactly
//! proportional to what it samples) and importance-sampled by a [`Distribution2D`]
//! over its pixels weighted by luminance times sin(theta) (a row near a pole covers
//! less solid angle).
//!
//! Mapping (+Y up): a direction at polar angle theta from +Y and azimuth phi =
//! atan2(x, -z) is pixel column (0.5 + phi / 2 pi) * width, row theta / pi * height:
//! the image's centre looks along -Z, its top row is straight up. `rotation` turns the
//! map about +Y, counter-clockwise seen from above (+Z toward +X, as a sun's azimuth).
//! Mitsuba 3's `envmap` puts the image's left edge (u = 0) along -Z, so it shows this
//! map turned by `rotation` with `to_world` rotate(+Y, rotation + 180).

use glam::{Vec2, Vec3};

use crate::distribution::Distribution2D;

/// Why an environment map cannot be made.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EnvMapError {
    #[error(
        "the image is {width}x{height}: an environment map needs at least 1x1 and at most {MAX_ENV_MAP_PIXELS} pixels"
    )]
    Size { width: usize, height: usize },
    #[error("pixel {0} is negative or not finite")]
    Pixel(usize),
    #[error("intensity must be finite and non-negative, got {0}")]
    Intensity(f32),
    #[error("rotation must be a finite number of degrees, got {0}")]
    Rotation(f32),
}

/// The most pixels a map may have (4096 x 2048: 96 MiB of radiance and as much again
/// of sampling tables).
pub const MAX_ENV_MAP_PIXELS: usize = 4096 * 2048;

#[derive(Clone, Debug)]
pub struct EnvMap {
    width: usize,
    height: usize,
    /// Radiance, row-major, times the intensity.
    pixels: Vec<Vec3>,
    /// Sine and cosine of the rotation about +Y.
    rot: (f32, f32),
    dist: Distribution2D,
}

fn luminance(c: Vec3) -> f32 {
    c.x * 0.2126 + c.y * 0.7152 + c.z * 0.0722
}

impl EnvMap {
    /// A map of `width` x `height` radiance `pixels` (row-major, top row first), turned
    /// by `rotation_deg` about +Y and scaled by `intensity`.
    pub fn new(
        width: usize,
        height: usize,
        pixels: Vec<Vec3>,
        rotation_deg: f32,
        intensity: f32,
    ) -> Result<EnvMap, EnvMapError> {
        let n = width.saturating_mul(height);
        if width == 0 || height == 0 || n > MAX_ENV_MAP_PIXELS || pixels.len() != n {
            return Err(EnvMapError::Size { width, height });
        }
        if !intensity.is_finite() || intensity < 0.0 {
            return Err(EnvMapError::Intensity(intensity));
        }
        if !rotation_deg.is_finite() {
            return Err(EnvMapError::Rotation(rotation_deg));
        }
        if let Some(i) = pixels
            .iter()
            .position(|p| !p.is_finite() || p.min_element() < 0.0)
        {
            return Err(EnvMapError::Pixel(i));
        }
        let pixels: Vec<Vec3> = pixels.into_iter().map(|p| p * intensity).collect();
        let weights: Vec<f32> = (0..n)
            .map(|i| {
                let theta = ((i / width) as f32 + 0.5) / height as f32 * std::f32::consts::PI;
                luminance(pixels[i]) * theta.sin()
            })
            .collect();
        let r = rotation_deg.to_radians();
        Ok(EnvMap {
            width,
            height,
            dist: Distribution2D::new(&weights, width, height),
            pixels,
            rot: r.sin_cos(),
        })
    }

    /// `dir` in the map's own frame (the rotation undone: turned by -rotation).
    fn to_map(&self, d: Vec3) -> Vec3 {
        let (s, c) = self.rot;
        Vec3::new(c * d.x - s * d.z, d.y, s * d.x + c * d.z)
    }

    /// A direction of the map's own frame in the world: turned by the rotation about
    /// +Y, right-handed (counter-clockwise seen from above: +Z toward +X, the way a
    /// sun's azimuth grows, and Mitsuba's `to_world` rotate about +Y).
    fn out_of_map(&self, d: Vec3) -> Vec3 {
        let (s, c) = self.rot;
        Vec3::new(c * d.x + s * d.z, d.y, -s * d.x + c * d.z)
    }

    /// Image coordinates in [0, 1)^2 of unit direction `dir`, and sin(theta).
    fn uv(&self, dir: Vec3) -> (Vec2, f32) {
        let d = self.to_map(dir);
        let theta = d.y.clamp(-1.0, 1.0).acos();
        let phi = d.x.atan2(-d.z);
        let u = (0.5 + phi / (2.0 * std::f32::consts::PI)).rem_euclid(1.0);
        let v = (theta / std::f32::consts::PI).clamp(0.0, 1.0);
        (
            Vec2::new(
                u.min(1.0 - f32::EPSILON / 2.0),
                v.min(1.0 - f32::EPSILON / 2.0),
            ),
            theta.sin(),
        )
    }

    /// Radiance arriving along `-dir` (seen looking toward unit direction `dir`).
    pub fn radiance(&self, dir: Vec3) -> Vec3 {
        let (p, _) = self.uv(dir);
        let x = ((p.x * self.width as f32) as usize).min(self.width - 1);
        let y = ((p.y * self.height as f32) as usize).min(self.height - 1);
        self.pixels[y * self.width + x]
    }

    /// The solid-angle density of [`EnvMap::sample`] toward `dir`.
    pub fn pdf(&self, dir: Vec3) -> f32 {
        let (p, sin_t) = self.uv(dir);
        if sin_t <= 0.0 {
            return 0.0;
        }
        self.dist.pdf(p) / (2.0 * std::f32::consts::PI * std::f32::consts::PI * sin_t)
    }

    /// A direction drawn in proportion to luminance (per solid angle), its radiance and
    /// its solid-angle density; `None` at a pole, where the density is not finite.
    pub fn sample(&self, u: Vec2) -> Option<(Vec3, Vec3, f32)> {
        let (p, pdf_uv) = self.dist.sample(u);
        let theta = p.y * std::f32::consts::PI;
        let phi = (p.x - 0.5) * 2.0 * std::f32::consts::PI;
        let (st, ct) = theta.sin_cos();
        if st <= 0.0 || pdf_uv <= 0.0 {
            return None;
        }
        let (sp, cp) = phi.sin_cos();
        let dir = self.out_of_map(Vec3::new(st * sp, ct, -st * cp));
        let pdf = pdf_uv / (2.0 * std::f32::consts::PI * std::f32::consts::PI * st);
        Some((dir, self.radiance(dir), pdf))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::uniform_sphere;

    /// A small map with a bright patch, a dim gradient and a black band.
    fn map(rotation: f32) -> EnvMap {
        let (w, h) = (16, 8);
        let pixels = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                if (5..7).contains(&x) && (2..4).contains(&y) {
                    Vec3::new(40.0, 30.0, 20.0)
                } else if y == 6 {
                    Vec3::ZERO
                } else {
                    Vec3::splat(0.1 + 0.05 * x as f32)
                }
            })
            .collect();
        EnvMap::new(w, h, pixels, rotation, 2.0).expect("map")
    }

    #[test]
    fn the_pdf_integrates_to_one_and_follows_the_luminance() {
        for rotation in [0.0, 75.0] {
            let m = map(rotation);
            // Integral of the pdf over the sphere, by uniform sphere samples.
            let n = 512;
            let mut total = 0.0f64;
            for i in 0..n {
                for j in 0..n {
                    let d = uniform_sphere(Vec2::new(
                        (i as f32 + 0.5) / n as f32,
                        (j as f32 + 0.5) / n as f32,
                    ));
                    let w = 4.0 * std::f64::consts::PI / (n * n) as f64;
                    total += f64::from(m.pdf(d)) * w;
                }
            }
            assert!((total - 1.0).abs() < 5e-3, "rotation {rotation}: {total}");
            // Each pixel is drawn with its share of luminance times solid angle (the
            // exact solid angle of its band of rows: the sin(theta) weight at the row's
            // centre is off from it by the same factor in every row, which cancels).
            let band = |y: usize| {
                let t = |y: usize| y as f64 / m.height as f64 * std::f64::consts::PI;
                t(y).cos() - t(y + 1).cos()
            };
            let share: Vec<f64> = (0..m.width * m.height)
                .map(|i| f64::from(luminance(m.pixels[i])) * band(i / m.width))
                .collect();
            let sum: f64 = share.iter().sum();
            for (i, s) in share.iter().enumerate() {
                let centre = Vec2::new(
                    ((i % m.width) as f32 + 0.5) / m.width as f32,
                    ((i / m.width) as f32 + 0.5) / m.height as f32,
                );
                let p = f64::from(m.dist.pdf(centre)) / (m.width * m.height) as f64;
                assert!(
                    (p - s / sum).abs() <= 1e-5 + 1e-4 * p,
                    "pixel {i}: {p} vs {}",
                    s / sum
                );
            }
            // Samples: their pdf is the pdf of their direction, and their radiance the map's.
            for k in 0..500 {
                let u = Vec2::new(
                    (k as f32 * 0.754_877_7).fract(),
                    (k as f32 * 0.569_840_3).fract(),
                );
                let Some((d, l, pdf)) = m.sample(u) else {
                    continue;
                };
                assert!((d.length() - 1.0).abs() < 1e-4);
                assert!(
                    (pdf - m.pdf(d)).abs() <= 1e-3 * pdf,
                    "{d}: {pdf} vs {}",
                    m.pdf(d)
                );
                assert_eq!(l, m.radiance(d));
                assert!(luminance(l) > 0.0, "sampled a black pixel at {d}");
            }
        }
    }

    /// The rotation turns the map counter-clockwise seen from above (+Z toward +X, as
    /// the docs and a sun's azimuth say), and the image's centre column looks along -Z.
    /// Before this test the map turned the other way (clockwise); Mitsuba's `envmap`
    /// with `to_world` rotate(+Y, 180 + rotation) now matches it
    /// (benches/envmap_vs_mitsuba.py).
    #[test]
    fn the_rotation_turns_the_map_counter_clockwise_seen_from_above() {
        // A bright column at the image's centre (u = 0.5), dark elsewhere.
        let (w, h) = (64, 32);
        let pixels = (0..w * h)
            .map(|i| {
                if i % w == w / 2 {
                    Vec3::splat(10.0)
                } else {
                    Vec3::splat(0.01)
                }
            })
            .collect::<Vec<_>>();
        let horizon = |az_deg: f32| {
            let a = az_deg.to_radians();
            // The sun's azimuth convention: from +Z toward +X.
            Vec3::new(a.sin(), 0.0, a.cos())
        };
        for (rotation, bright_at) in [(0.0, 180.0), (90.0, 270.0), (-90.0, 90.0), (180.0, 0.0)] {
            let m = EnvMap::new(w, h, pixels.clone(), rotation, 1.0).expect("map");
            // Just inside the column's pixel (u in [0.5, 0.5 + 1/64]: phi = atan2(x, -z)
            // = 180 - azimuth in [0, 5.6] degrees, so 1 degree less azimuth).
            let on = m.radiance(horizon(bright_at - 1.0));
            let off = m.radiance(horizon(bright_at + 90.0));
            assert_eq!(
                (on.x, off.x),
                (10.0, 0.01),
                "rotation {rotation}: the column should be at azimuth {bright_at}"
            );
            // Samples land on the column, where its radiance is.
            let (d, l, _) = m.sample(Vec2::new(0.37, 0.61)).expect("a sample");
            assert_eq!(l.x, 10.0);
            let az = d.x.atan2(d.z).to_degrees().rem_euclid(360.0);
            let diff = (az - bright_at).rem_euclid(360.0);
            assert!(
                diff.min(360.0 - diff) < 360.0 / w as f32,
                "rotation {rotation}: sample at {az}"
            );
        }
    }

    #[test]
    fn bad_maps_are_refused() {
        assert!(matches!(
            EnvMap::new(0, 1, vec![], 0.0, 1.0),
            Err(EnvMapError::Size { .. })
        ));
        assert!(matches!(
            EnvMap::new(2, 1, vec![Vec3::ONE], 0.0, 1.0),
            Err(EnvMapError::Size { .. })
        ));
        assert!(matches!(
            EnvMap::new(1, 1, vec![Vec3::NAN], 0.0, 1.0),
            Err(EnvMapError::Pixel(0))
        ));
        assert!(matches!(
            EnvMap::new(1, 1, vec![Vec3::ONE], 0.0, -1.0),
            Err(EnvMapError::Intensity(_))
        ));
        assert!(matches!(
            EnvMap::new(1, 1, vec![Vec3::ONE], f32::NAN, 1.0),
            Err(EnvMapError::Rotation(_))
        ));
    }
}
