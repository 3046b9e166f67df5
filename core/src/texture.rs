//! Textures and their samplers (glTF semantics).
//!
//! Texels are kept as 8-bit RGBA as decoded from the image; colour textures (base colour,
//! emissive, specular colour) are converted from sRGB to linear at lookup time.

use glam::{Vec2, Vec4};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Wrap {
    Repeat,
    ClampToEdge,
    MirroredRepeat,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Filter {
    Nearest,
    Linear,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Sampler {
    pub wrap_s: Wrap,
    pub wrap_t: Wrap,
    /// Magnification filter; dray uses it for all lookups (no mip maps: one sample per
    /// hit, antialiased by pixel samples).
    pub filter: Filter,
}

impl Default for Sampler {
    /// glTF defaults: repeat, and linear filtering where unspecified.
    fn default() -> Self {
        Sampler {
            wrap_s: Wrap::Repeat,
            wrap_t: Wrap::Repeat,
            filter: Filter::Linear,
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct Texture {
    pub name: String,
    pub width: u32,
    pub height: u32,
    /// Row-major RGBA8, `width * height` entries, first row at v = 0 (glTF convention).
    /// Shared, because every resident domain of a worker carries the scene's textures:
    /// a copy is a pointer, not the image.
    pub texels: std::sync::Arc<[[u8; 4]]>,
    pub sampler: Sampler,
}

fn wrap(coord: i64, size: u32, mode: Wrap) -> usize {
    let n = size as i64;
    let c = match mode {
        Wrap::Repeat => coord.rem_euclid(n),
        Wrap::ClampToEdge => coord.clamp(0, n - 1),
        Wrap::MirroredRepeat => {
            let period = coord.rem_euclid(2 * n);
            if period < n {
                period
            } else {
                2 * n - 1 - period
            }
        }
    };
    c as usize
}

/// sRGB transfer function to linear, by table.
fn srgb_to_linear(v: u8) -> f32 {
    static TABLE: std::sync::OnceLock<[f32; 256]> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        let mut t = [0.0f32; 256];
        for (i, e) in t.iter_mut().enumerate() {
            let c = i as f32 / 255.0;
            *e = if c <= 0.04045 {
                c / 12.92
            } else {
                ((c + 0.055) / 1.055).powf(2.4)
            };
        }
        t
    })[v as usize]
}

impl Texture {
    fn texel(&self, x: i64, y: i64, srgb: bool) -> Vec4 {
        let xi = wrap(x, self.width, self.sampler.wrap_s);
        let yi = wrap(y, self.height, self.sampler.wrap_t);
        let t = self.texels[yi * self.width as usize + xi];
        if srgb {
            Vec4::new(
                srgb_to_linear(t[0]),
                srgb_to_linear(t[1]),
                srgb_to_linear(t[2]),
                t[3] as f32 / 255.0,
            )
        } else {
            Vec4::new(t[0] as f32, t[1] as f32, t[2] as f32, t[3] as f32) / 255.0
        }
    }

    /// Sample at `uv`; `srgb` converts the colour channels to linear. Non-finite UVs read
    /// texel (0, 0) rather than poisoning the image.
    pub fn sample(&self, uv: Vec2, srgb: bool) -> Vec4 {
        if self.width == 0 || self.height == 0 || self.texels.is_empty() {
            return Vec4::ONE;
        }
        let uv = if uv.is_finite() { uv } else { Vec2::ZERO };
        // Keep coordinates in a range where f32 -> i64 is exact enough.
        let uv = uv.clamp(Vec2::splat(-1.0e6), Vec2::splat(1.0e6));
        let x = uv.x * self.width as f32;
        let y = uv.y * self.height as f32;
        match self.sampler.filter {
            Filter::Nearest => self.texel(x.floor() as i64, y.floor() as i64, srgb),
            Filter::Linear => {
                let fx = x - 0.5;
                let fy = y - 0.5;
                let x0 = fx.floor();
                let y0 = fy.floor();
                let tx = fx - x0;
                let ty = fy - y0;
                let (x0, y0) = (x0 as i64, y0 as i64);
                let a = self.texel(x0, y0, srgb);
                let b = self.texel(x0 + 1, y0, srgb);
                let c = self.texel(x0, y0 + 1, srgb);
                let d = self.texel(x0 + 1, y0 + 1, srgb);
                a.lerp(b, tx).lerp(c.lerp(d, tx), ty)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn checker() -> Texture {
        Texture {
            name: "checker".into(),
            width: 2,
            height: 2,
            texels: vec![
                [255, 0, 0, 255],
                [0, 255, 0, 255],
                [0, 0, 255, 255],
                [255, 255, 255, 0],
            ]
            .into(),
            sampler: Sampler {
                filter: Filter::Nearest,
                ..Sampler::default()
            },
        }
    }

    #[test]
    fn nearest_lookup_and_wrap() {
        let t = checker();
        assert_eq!(
            t.sample(Vec2::new(0.25, 0.25), false),
            Vec4::new(1.0, 0.0, 0.0, 1.0)
        );
        assert_eq!(
            t.sample(Vec2::new(0.75, 0.25), false),
            Vec4::new(0.0, 1.0, 0.0, 1.0)
        );
        assert_eq!(
            t.sample(Vec2::new(1.25, 0.25), false),
            Vec4::new(1.0, 0.0, 0.0, 1.0)
        );
        assert_eq!(
            t.sample(Vec2::new(f32::NAN, 0.25), false),
            Vec4::new(1.0, 0.0, 0.0, 1.0)
        );
    }

    #[test]
    fn srgb_endpoints() {
        assert_eq!(srgb_to_linear(0), 0.0);
        assert!((srgb_to_linear(255) - 1.0).abs() < 1e-6);
        assert!((srgb_to_linear(188) - 0.5).abs() < 0.01);
    }
}
