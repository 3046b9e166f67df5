//! The display transform: from the film's linear radiance to the 8-bit sRGB pixels of a
//! PNG (or JPEG): exposure ([`crate::exposure`]), then a tone curve
//! ([`crate::tonemap`]), then the sRGB encoding. The one implementation behind
//! `dray render --output`, `dray submit`, `dray sweep`'s images and the coordinator's
//! GetImage, so each writes the same bytes for the same film. EXR output never passes
//! through here: it stays linear radiance.
//!
//! `Display { exposure: Stops(0), tonemap: Clamp }` is the encoding dray had before
//! automatic exposure and tone curves, byte for byte ([`Film::srgb8`] at scale 1).

use std::path::Path;

use glam::Vec3;

use crate::exposure::Exposure;
use crate::film::{Film, FilmError, linear_to_srgb8, save_srgb8};
use crate::tonemap::Tonemap;

/// How linear radiance becomes 8-bit display values.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Display {
    pub exposure: Exposure,
    pub tonemap: Tonemap,
}

impl Default for Display {
    /// Automatic exposure and [`Tonemap::DEFAULT`]: what 8-bit output gets when no one
    /// says otherwise.
    fn default() -> Display {
        Display {
            exposure: Exposure::Auto,
            tonemap: Tonemap::DEFAULT,
        }
    }
}

/// Pixels as the display transform made them, and the exposure it applied.
#[derive(Clone, Debug, PartialEq)]
pub struct Developed {
    /// 8-bit sRGB, RGB, row-major.
    pub srgb8: Vec<u8>,
    /// The exposure applied, in stops (the one chosen, with [`Exposure::Auto`]).
    pub stops: f32,
}

impl Display {
    /// The transform of today's fixed encoding: `ev` stops, no curve.
    pub fn fixed(ev: f32) -> Display {
        Display {
            exposure: Exposure::Stops(ev),
            tonemap: Tonemap::Clamp,
        }
    }

    /// Develop the film's image at `spp` samples per pixel.
    pub fn develop(&self, film: &Film, spp: u32) -> Developed {
        self.develop_linear(&film.linear(spp))
    }

    /// Develop linear radiance `pixels` (what [`Film::linear`] and an EXR hold).
    pub fn develop_linear(&self, pixels: &[Vec3]) -> Developed {
        let stops = self.exposure.resolve(pixels);
        // 2^EV as the fixed exposure has always computed it, so a fixed exposure with
        // `clamp` gives the bytes it always gave.
        let scale = 2f32.powf(stops);
        let mut srgb8 = Vec::with_capacity(pixels.len() * 3);
        for p in pixels {
            let d = self.tonemap.apply(*p * scale);
            srgb8.extend([d.x, d.y, d.z].map(linear_to_srgb8));
        }
        Developed { srgb8, stops }
    }

    /// The film as a PNG file's bytes.
    pub fn encode_png(&self, film: &Film, spp: u32) -> Result<Vec<u8>, String> {
        use image::ImageEncoder;
        let buf = self.develop(film, spp).srgb8;
        let mut out = Vec::new();
        image::codecs::png::PngEncoder::new(&mut out)
            .write_image(
                &buf,
                film.width,
                film.height,
                image::ExtendedColorType::Rgb8,
            )
            .map_err(|e| format!("cannot encode PNG: {e}"))?;
        Ok(out)
    }

    /// Write the film to `path` as PNG or JPEG (by its extension, as
    /// [`Film::write_png`]); the exposure applied, in stops.
    pub fn write(&self, film: &Film, spp: u32, path: &Path) -> Result<f32, FilmError> {
        let d = self.develop(film, spp);
        save_srgb8(path, film.width, film.height, &d.srgb8)?;
        Ok(d.stops)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::exposure::MID_GREY;
    use crate::film::srgb8_to_linear;

    /// A film of `n` pixels whose radiance is `f(i)`, at 1 sample per pixel.
    fn film_of(n: u32, f: impl Fn(u32) -> Vec3) -> Film {
        let mut film = Film::new(n, 1);
        for i in 0..n {
            film.add(i, f(i));
        }
        film
    }

    /// The 8-bit sRGB code of display luminance `y`.
    fn code(y: f32) -> u8 {
        linear_to_srgb8(y)
    }

    /// A photometric-scale film: a sunlit scene of diffuse surfaces (radiance in the
    /// thousands, spread over about 5 stops, coloured), with a few pixels of a visible
    /// emitter far brighter and a black background around it.
    fn photometric(i: u32) -> Vec3 {
        let h = (i.wrapping_mul(2_654_435_761) >> 8) as f32 / (1u32 << 24) as f32;
        let tint = Vec3::new(1.0, 0.8 + 0.2 * h, 0.6 + 0.4 * (1.0 - h));
        match i % 400 {
            0 => Vec3::splat(5.0e6), // 0.25%: the sun's disc, a lamp
            1..=40 => Vec3::ZERO,    // 10%: background
            _ => tint * 6830.0 * 2f32.powf(5.0 * h - 3.5), // the lit scene
        }
    }

    /// The median display luminance code and the share of pixels with a channel at
    /// 255, over pixels with light.
    fn measure(d: &Developed, film: &Film) -> (u8, f64) {
        let lin = film.linear(1);
        let mut lum = Vec::new();
        let mut clipped = 0usize;
        for (p, px) in d.srgb8.chunks(3).zip(&lin) {
            if *px == Vec3::ZERO {
                continue;
            }
            clipped += usize::from(p.contains(&255));
            let y = crate::exposure::luminance(Vec3::from_array(
                [p[0], p[1], p[2]].map(srgb8_to_linear),
            ));
            lum.push(code(y));
        }
        lum.sort_unstable();
        (lum[lum.len() / 2], clipped as f64 / lum.len() as f64)
    }

    #[test]
    fn fixed_exposure_with_clamp_is_the_old_encoding_exactly() {
        // A film where the automatic exposure and every curve would change the bytes:
        // if either leaked into the fixed path, this fails.
        let film = film_of(3000, |i| Vec3::new(i as f32 / 900.0, 0.3, (i % 7) as f32));
        for ev in [0.0, -1.5, 2.0] {
            let want = film.srgb8(1, 2f32.powf(ev));
            let got = Display::fixed(ev).develop(&film, 1);
            assert!(got.srgb8 == want, "{ev} EV, clamp: bytes differ");
            assert_eq!(got.stops, ev);
            assert!(Display::default().develop(&film, 1).srgb8 != want);
            for t in [Tonemap::Reinhard, Tonemap::Aces, Tonemap::Agx] {
                let d = Display {
                    exposure: Exposure::Stops(ev),
                    tonemap: t,
                };
                assert!(d.develop(&film, 1).srgb8 != want, "{t} changes the image");
            }
        }
        let auto = Display {
            exposure: Exposure::Auto,
            tonemap: Tonemap::Clamp,
        };
        assert!(auto.develop(&film, 1).stops.abs() > 0.5);
        assert!(auto.develop(&film, 1).srgb8 != film.srgb8(1, 1.0));
    }

    #[test]
    fn a_photometric_film_is_well_exposed_by_default() {
        let film = film_of(40_000, photometric);
        let d = Display::default().develop(&film, 1);
        let (median, clipped) = measure(&d, &film);
        // Mid-grey: within a stop of 0.18 on the display.
        assert!(
            (code(MID_GREY / 2.0)..=code(MID_GREY * 2.0)).contains(&median),
            "median {median}"
        );
        assert!(clipped < 0.02, "{:.2}% clipped", clipped * 100.0);
        // At a fixed exposure of 0 it is a white sheet: why the default is automatic.
        let (_, white) = measure(&Display::fixed(0.0).develop(&film, 1), &film);
        assert!(white > 0.85, "{white}");
    }

    #[test]
    fn a_few_very_bright_pixels_do_not_darken_the_rest() {
        let base = film_of(20_000, |i| photometric(i * 400 + 50 + i % 300));
        let hot = film_of(20_000, |i| {
            if i % 100 == 7 {
                Vec3::splat(1.0e9) // 1%: fireflies, a specular glint of the sun
            } else {
                photometric(i * 400 + 50 + i % 300)
            }
        });
        let (a, b) = (
            Display::default().develop(&base, 1),
            Display::default().develop(&hot, 1),
        );
        // The hot pixels count as the 95th percentile does, about 2.5 stops above the
        // key, so 1% of them moves it by about 0.025 stops.
        assert!(
            (a.stops - b.stops).abs() < 0.05,
            "{} vs {}",
            a.stops,
            b.stops
        );
        let (ma, mb) = (measure(&a, &base).0, measure(&b, &hot).0);
        assert!(ma.abs_diff(mb) <= 1, "median {ma} vs {mb}");
    }

    #[test]
    fn the_png_is_the_developed_pixels() {
        let film = film_of(64, |i| Vec3::splat(i as f32 * 100.0));
        let png = Display::default().encode_png(&film, 1).unwrap();
        let img = image::load_from_memory(&png).unwrap().to_rgb8();
        assert_eq!(img.into_raw(), Display::default().develop(&film, 1).srgb8);
    }
}
