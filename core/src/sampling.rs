//! Counter-based sampling: every random number is a pure function of
//! (seed, pixel, sample, bounce, purpose, index), so the image does not depend on which
//! thread or worker traced a ray, or when.

use glam::{Vec2, Vec3};

/// What a random number is for. Distinct purposes never share a stream.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u32)]
pub enum Purpose {
    /// Sub-pixel position of the camera ray.
    Film = 1,
    LightSelect = 2,
    LightPoint = 3,
    BsdfLobe = 4,
    BsdfDirection = 5,
    Roulette = 6,
    AmbientOcclusion = 7,
    /// Stochastic alpha for blended materials.
    Alpha = 8,
    /// The colour channel a path follows through a dispersive surface.
    Dispersion = 9,
    /// The point on a thin lens a camera ray starts from (`camera::Lens`).
    Lens = 10,
    /// The direction inside the sun's disk of a light sample.
    SunPoint = 11,
    /// The direction of a light sample of the environment map.
    EnvMapPoint = 12,
}

/// The coordinates of one path: everything but the bounce and purpose.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct PathKey {
    pub seed: u64,
    pub pixel: u32,
    pub sample: u32,
}

#[inline]
fn mix64(mut z: u64) -> u64 {
    // splitmix64 finaliser (Stafford variant 13): a bijection with full avalanche.
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

impl PathKey {
    /// The path's stream: the hash of (seed, pixel, sample), done once for all of the
    /// path's numbers at one vertex.
    #[inline]
    pub fn stream(&self) -> PathStream {
        let a = mix64(self.seed ^ 0x9e37_79b9_7f4a_7c15);
        PathStream {
            path: mix64(a ^ ((self.pixel as u64) << 32 | self.sample as u64)),
        }
    }

    /// 64 random bits for (bounce, purpose, index).
    #[inline]
    pub fn bits(&self, bounce: u32, purpose: Purpose, index: u32) -> u64 {
        self.stream().bits(bounce, purpose, index)
    }

    /// A uniform number in [0, 1).
    #[inline]
    pub fn uniform(&self, bounce: u32, purpose: Purpose, index: u32) -> f32 {
        self.stream().uniform(bounce, purpose, index)
    }

    /// Two uniform numbers in [0, 1).
    #[inline]
    pub fn uniform2(&self, bounce: u32, purpose: Purpose, index: u32) -> Vec2 {
        self.stream().uniform2(bounce, purpose, index)
    }
}

/// One path's random numbers ([`PathKey::stream`]): the same numbers as the key's, for
/// half the hashing (a shaded hit draws five to seven of them).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PathStream {
    path: u64,
}

impl PathStream {
    /// 64 random bits for (bounce, purpose, index).
    #[inline]
    pub fn bits(&self, bounce: u32, purpose: Purpose, index: u32) -> u64 {
        let c = mix64(self.path ^ ((bounce as u64) << 40 | (purpose as u64) << 32 | index as u64));
        mix64(c.wrapping_add(0x632b_e59b_d9b4_e019))
    }

    /// A uniform number in [0, 1).
    #[inline]
    pub fn uniform(&self, bounce: u32, purpose: Purpose, index: u32) -> f32 {
        to_unit(self.bits(bounce, purpose, index))
    }

    /// Two uniform numbers in [0, 1).
    #[inline]
    pub fn uniform2(&self, bounce: u32, purpose: Purpose, index: u32) -> Vec2 {
        let b = self.bits(bounce, purpose, index);
        Vec2::new(to_unit(b), to_unit(b << 24))
    }
}

/// The top 24 bits of `bits` as a float in [0, 1).
#[inline]
pub fn to_unit(bits: u64) -> f32 {
    (bits >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
}

/// Cosine-weighted direction on the hemisphere around unit `n` (Malley's method).
pub fn cosine_hemisphere(n: Vec3, u: Vec2) -> Vec3 {
    let r = u.x.sqrt();
    let phi = 2.0 * std::f32::consts::PI * u.y;
    let (t, b) = n.any_orthonormal_pair();
    let z = (1.0 - u.x).max(0.0).sqrt();
    (t * (r * phi.cos()) + b * (r * phi.sin()) + n * z).normalize_or(n)
}

/// Uniform direction on the unit sphere.
pub fn uniform_sphere(u: Vec2) -> Vec3 {
    let z = 1.0 - 2.0 * u.x;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * std::f32::consts::PI * u.y;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// Uniform barycentrics on a triangle (returns weights for v1 and v2).
pub fn uniform_triangle(u: Vec2) -> (f32, f32) {
    let s = u.x.sqrt();
    (s * (1.0 - u.y), s * u.y)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pure_function_and_distinct_streams() {
        let k = PathKey {
            seed: 7,
            pixel: 12,
            sample: 3,
        };
        assert_eq!(k.bits(1, Purpose::Film, 0), k.bits(1, Purpose::Film, 0));
        assert_ne!(
            k.bits(1, Purpose::Film, 0),
            k.bits(1, Purpose::LightSelect, 0)
        );
        assert_ne!(k.bits(1, Purpose::Film, 0), k.bits(2, Purpose::Film, 0));
        let k2 = PathKey { sample: 4, ..k };
        assert_ne!(k.bits(1, Purpose::Film, 0), k2.bits(1, Purpose::Film, 0));
    }

    #[test]
    fn stream_gives_the_keys_bits() {
        // The formula before streams existed (2026-11-26): images keep their bits.
        fn old_bits(k: &PathKey, bounce: u32, purpose: Purpose, index: u32) -> u64 {
            let a = mix64(k.seed ^ 0x9e37_79b9_7f4a_7c15);
            let b = mix64(a ^ ((k.pixel as u64) << 32 | k.sample as u64));
            let c = mix64(b ^ ((bounce as u64) << 40 | (purpose as u64) << 32 | index as u64));
            mix64(c.wrapping_add(0x632b_e59b_d9b4_e019))
        }
        for i in 0..1000u32 {
            let k = PathKey {
                seed: u64::from(i) * 0x1234_5678_9abc,
                pixel: i * 7919,
                sample: i % 37,
            };
            let s = k.stream();
            for (bounce, purpose) in [(0, Purpose::Film), (i % 64, Purpose::BsdfLobe)] {
                assert_eq!(
                    s.bits(bounce, purpose, i % 3),
                    old_bits(&k, bounce, purpose, i % 3)
                );
                assert_eq!(k.bits(bounce, purpose, 1), old_bits(&k, bounce, purpose, 1));
            }
        }
    }

    #[test]
    fn uniform_mean_is_half() {
        let mut sum = 0.0f64;
        let n = 100_000;
        for i in 0..n {
            let k = PathKey {
                seed: 1,
                pixel: i,
                sample: 0,
            };
            let u = k.uniform(0, Purpose::Film, 0);
            assert!((0.0..1.0).contains(&u));
            sum += u as f64;
        }
        assert!((sum / n as f64 - 0.5).abs() < 0.005);
    }
}
