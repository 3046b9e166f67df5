//! The film: per-pixel sums in fixed point, so accumulation is exact and independent of
//! the order contributions arrive in (the same job gives the same bits on 1 thread or 16,
//! on 1 worker or many). Box filter: a sample counts for the pixel it was taken in.
//!
//! A contribution is converted once, deterministically, to an integer with 24 fractional
//! bits; integer addition is associative, so sums never depend on order. Non-finite
//! contributions are counted and dropped (NaN and Inf never reach the image); negative
//! components count as zero.
//!
//! Sums cannot overflow (docs/numerics.md "The film"): every converted contribution is
//! non-negative and every sum, here, on workers and on the coordinator, is a saturating
//! addition. For non-negative terms `min(a + b, MAX)` is associative and commutative
//! (each partial sum is `min(true sum, MAX)` however the terms are grouped), so the
//! image keeps the same bits in every configuration, and a pixel too bright to represent
//! reads as the largest sum instead of wrapping to a negative one. [`MAX_CONTRIBUTION`] is
//! small enough that a pixel taking one clamped contribution per sample at the most
//! samples a job accepts never reaches that limit.

use std::path::Path;

use glam::Vec3;

use crate::aov::{AovFilm, AovSet};

/// Fixed-point scale: 2^24 steps per unit of radiance.
pub const FIXED_SCALE: f64 = (1u64 << 24) as f64;
/// The most samples per pixel a job accepts (`spp`), which [`MAX_CONTRIBUTION`] is sized for.
pub const MAX_SPP: u32 = 1 << 16;
/// Largest contribution component accepted (radiance units, 2^22); larger values are
/// clamped and counted. With one such contribution per sample at [`MAX_SPP`] samples a
/// pixel sums to 2^22 * 2^24 * 2^16 = 2^62, half of what an i64 holds; pixels taking
/// several clamped contributions per sample saturate (see [`Film::saturated`]).
pub const MAX_CONTRIBUTION: f32 = (1u32 << 22) as f32;
/// The largest sum a pixel component holds; sums saturate here.
pub const MAX_SUM: i64 = i64::MAX;
/// Pixels [`Film::add_fixed_run`] reads ahead before adding: enough cache misses in
/// flight to keep the memory busy, few enough that their lines (at most two a pixel,
/// 32 KiB) are still in the first-level cache when they are added to (128 and 512 were
/// measured alike: docs/scaling.md).
pub const ADD_RUN: usize = 256;

/// A contribution in fixed point, and whether a component was clamped to
/// [`MAX_CONTRIBUTION`]; `None` for non-finite input.
#[inline]
pub fn to_fixed_clamped(v: Vec3) -> Option<([i64; 3], bool)> {
    if !v.is_finite() {
        return None;
    }
    let clamped = v.max_element() > MAX_CONTRIBUTION;
    let c = v.clamp(Vec3::ZERO, Vec3::splat(MAX_CONTRIBUTION));
    Some((
        [c.x, c.y, c.z].map(|x| round_non_negative(x as f64 * FIXED_SCALE)),
        clamped,
    ))
}

/// Convert one contribution to fixed point. Returns `None` for non-finite input.
#[inline]
pub fn to_fixed(v: Vec3) -> Option<[i64; 3]> {
    to_fixed_clamped(v).map(|(f, _)| f)
}

/// Add `value` to the sum `s`, saturating at [`MAX_SUM`]: the one addition every film
/// sum uses, exact and order-free for the non-negative values [`to_fixed`] makes.
#[inline]
pub fn add_sums(s: &mut [i64; 3], value: [i64; 3]) {
    for c in 0..3 {
        s[c] = s[c].saturating_add(value[c]);
    }
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
    /// Contributions with a component clamped to [`MAX_CONTRIBUTION`] (counted where a
    /// film adds values itself; sums added in fixed point bring no count).
    pub clamped: u64,
    /// Contributions of indirect light scaled down by `--clamp-indirect`
    /// (`crate::clamp`), counted as [`Film::clamped`] is.
    pub clamped_indirect: u64,
    /// The AOVs' sums (`crate::aov`), when the job asks for any.
    pub aovs: Option<AovFilm>,
    /// Adaptive sampling (`crate::adaptive`): per pixel, the samples it stopped at, or 0
    /// for a pixel that did not stop (it has the samples the image is shown with). None
    /// until some tile stops, so a film without adaptive sampling pays nothing.
    stops: Option<Vec<u32>>,
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
            clamped: 0,
            clamped_indirect: 0,
            aovs: None,
            stops: None,
        }
    }

    /// A film that also keeps the sums of `aovs` (none when the set is empty).
    pub fn with_aovs(width: u32, height: u32, aovs: AovSet) -> Film {
        Film {
            aovs: (!aovs.is_empty()).then(|| AovFilm::new(aovs, width as usize * height as usize)),
            ..Film::new(width, height)
        }
    }

    /// The AOVs this film keeps.
    pub fn aov_set(&self) -> AovSet {
        self.aovs.as_ref().map_or(AovSet::NONE, |a| a.set)
    }

    /// The bytes its sums take in memory (what a coordinator keeping finished images
    /// counts against its budget).
    pub fn heap_bytes(&self) -> u64 {
        (self.sums.len() as u64)
            .saturating_mul(std::mem::size_of::<[i64; 3]>() as u64)
            .saturating_add(self.aovs.as_ref().map_or(0, AovFilm::heap_bytes))
            .saturating_add(self.stops.as_ref().map_or(0, |s| 4 * s.len() as u64))
    }

    /// Per pixel, the samples it stopped at under adaptive sampling (0: it did not
    /// stop); None when no pixel stopped.
    pub fn stops(&self) -> Option<&[u32]> {
        self.stops.as_deref()
    }

    /// Pixel `pixel` stopped at `samples` samples (adaptive sampling): it is shown
    /// divided by them, whatever the image's samples per pixel. 0 undoes it.
    pub fn set_stop(&mut self, pixel: u32, samples: u32) {
        let n = self.sums.len();
        if (pixel as usize) < n && (samples > 0 || self.stops.is_some()) {
            self.stops.get_or_insert_with(|| vec![0; n])[pixel as usize] = samples;
        }
    }

    /// The samples pixel `pixel` has in an image of `spp` samples per pixel: `spp`, or
    /// fewer where it stopped early.
    #[inline]
    pub fn samples_of(&self, pixel: usize, spp: u32) -> u32 {
        match self.stops.as_ref().and_then(|s| s.get(pixel)) {
            Some(&n) if n > 0 => n,
            _ => spp,
        }
    }

    /// Add a contribution to pixel `pixel` (row-major index). Out-of-range pixels are ignored.
    #[inline]
    pub fn add(&mut self, pixel: u32, value: Vec3) {
        match to_fixed_clamped(value) {
            Some((f, clamped)) => {
                self.clamped += u64::from(clamped);
                if let Some(s) = self.sums.get_mut(pixel as usize) {
                    add_sums(s, f);
                }
            }
            None => self.nonfinite += 1,
        }
    }

    /// Add an already-converted fixed-point sum (from another film or a remote worker).
    /// Adding a pixel's negated sum sets it to zero exactly.
    #[inline]
    pub fn add_fixed(&mut self, pixel: u32, value: [i64; 3]) {
        if let Some(s) = self.sums.get_mut(pixel as usize) {
            add_sums(s, value);
        }
    }

    /// Add a report's fixed-point sums: `sums[3 * i..3 * i + 3]` to pixel `pixels[i]`,
    /// in order (out-of-range pixels are ignored, as by [`Film::add_fixed`]; `sums` must
    /// hold three values per pixel). The same additions as one `add_fixed` per pixel, so
    /// the same bits, but faster on a film larger than the caches: the pixels of a
    /// report are scattered over the image, and a loop that loads and stores each in
    /// turn waits for one cache miss at a time (every store to a missing line holds a
    /// store-buffer entry until the line arrives). So each run of
    /// [`ADD_RUN`] pixels is first only read, which lets the CPU fetch their lines
    /// together, and then added.
    pub fn add_fixed_run(&mut self, pixels: &[u32], sums: &[i64]) {
        for (px, s) in pixels.chunks(ADD_RUN).zip(sums.chunks(3 * ADD_RUN)) {
            let mut touch = 0i64;
            for &p in px {
                if let Some(v) = self.sums.get(p as usize) {
                    // The first and last word: a pixel's 24 bytes may span two lines.
                    touch ^= v[0] ^ v[2];
                }
            }
            std::hint::black_box(touch);
            for (&p, v) in px.iter().zip(s.chunks_exact(3)) {
                self.add_fixed(p, [v[0], v[1], v[2]]);
            }
        }
    }

    /// Set pixel `pixel`'s sums, beauty and AOVs, to `from`'s (a film of the same size
    /// and AOVs), or to zero without it: the exact copy a pass image is built from and a
    /// retried tile goes back to.
    pub fn set_pixel_from(&mut self, pixel: u32, from: Option<&Film>) {
        if let Some(s) = self.sums.get_mut(pixel as usize) {
            *s = from.map_or([0; 3], |f| f.sum_fixed(pixel));
        }
        if let Some(a) = self.aovs.as_mut() {
            let v = from
                .and_then(|f| f.aovs.as_ref())
                .map_or([0; crate::aov::AOV_WORDS], |b| b.sum_fixed(pixel));
            a.set_fixed(pixel, v);
        }
        let stop = from.map_or(0, |f| f.stops().map_or(0, |s| s[pixel as usize]));
        self.set_stop(pixel, stop);
    }

    /// Merge another film of the same size (exact, order-free).
    pub fn merge(&mut self, other: &Film) {
        for (a, b) in self.sums.iter_mut().zip(&other.sums) {
            add_sums(a, *b);
        }
        self.nonfinite += other.nonfinite;
        self.clamped += other.clamped;
        self.clamped_indirect += other.clamped_indirect;
        if let (Some(a), Some(b)) = (self.aovs.as_mut(), other.aovs.as_ref()) {
            a.merge(b);
        }
        if let Some(b) = other.stops() {
            for (p, &n) in b.iter().enumerate() {
                if n > self.samples_of(p, 0) {
                    self.set_stop(p as u32, n);
                }
            }
        }
    }

    /// Pixels with a component at [`MAX_SUM`]: brighter than the film can represent
    /// (a mean above 2^39 / spp), so their value is a lower bound.
    pub fn saturated(&self) -> u64 {
        self.sums.iter().filter(|s| s.contains(&MAX_SUM)).count() as u64
    }

    pub fn sum_fixed(&self, pixel: u32) -> [i64; 3] {
        self.sums.get(pixel as usize).copied().unwrap_or([0; 3])
    }

    /// Linear radiance of every pixel: the sum divided by `spp`, or by the samples it
    /// stopped at (adaptive sampling).
    pub fn linear(&self, spp: u32) -> Vec<Vec3> {
        let all = 1.0 / (FIXED_SCALE * spp.max(1) as f64);
        self.sums
            .iter()
            .enumerate()
            .map(|(p, s)| {
                let k = match self.samples_of(p, spp) {
                    n if n == spp => all,
                    n => 1.0 / (FIXED_SCALE * n.max(1) as f64),
                };
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

    /// Write an 8-bit sRGB PNG of radiance times `scale` (2^exposure), with no tone
    /// curve (`crate::display::Display` writes the others).
    pub fn write_png(&self, path: &Path, spp: u32, scale: f32) -> Result<(), FilmError> {
        save_srgb8(path, self.width, self.height, &self.srgb8(spp, scale))
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
    /// parallel they land in the file in the order they finish. A film with AOVs gives
    /// one image with their channels too ([`Film::encode_exr_with_aovs`]).
    pub fn encode_exr(&self, spp: u32) -> Result<Vec<u8>, String> {
        if let Some(aovs) = &self.aovs {
            return self.encode_exr_with_aovs(aovs, spp);
        }
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

impl Film {
    /// The beauty (`R`, `G`, `B`) and the AOVs' channels (`albedo.R`, `normal.X`,
    /// `depth.Z`, ...: one part whose channel names carry the layer, as Cycles and Nuke
    /// write multi-layer files and every OpenEXR reader understands), f32.
    fn encode_exr_with_aovs(&self, aovs: &AovFilm, spp: u32) -> Result<Vec<u8>, String> {
        use exr::prelude::{
            AnyChannel, AnyChannels, Encoding, FlatSamples, Image, Layer, LayerAttributes, Vec2,
            WritableImage,
        };
        let lin = self.linear(spp);
        let mut channels: Vec<AnyChannel<FlatSamples>> = ["R", "G", "B"]
            .into_iter()
            .enumerate()
            .map(|(k, name)| {
                AnyChannel::new(name, FlatSamples::F32(lin.iter().map(|p| p[k]).collect()))
            })
            .collect();
        for (name, values) in aovs.channels(spp, self.stops()) {
            channels.push(AnyChannel::new(name, FlatSamples::F32(values)));
        }
        let size = Vec2(self.width as usize, self.height as usize);
        let layer = Layer::new(
            size,
            LayerAttributes::default(),
            Encoding::default(),
            AnyChannels::sort(channels.into()),
        );
        let mut out = std::io::Cursor::new(Vec::new());
        Image::from_layer(layer)
            .write()
            .non_parallel()
            .to_buffered(&mut out)
            .map_err(|e| e.to_string())?;
        Ok(out.into_inner())
    }
}

/// Write 8-bit sRGB pixels (RGB, row-major) as PNG or JPEG, by `path`'s extension.
pub fn save_srgb8(path: &Path, width: u32, height: u32, buf: &[u8]) -> Result<(), FilmError> {
    image::save_buffer(path, buf, width, height, image::ExtendedColorType::Rgb8).map_err(|e| {
        FilmError::Png {
            path: path.display().to_string(),
            message: e.to_string(),
        }
    })
}

/// The inverse of the sRGB transfer function for an 8-bit value (what a viewer shows).
pub fn srgb8_to_linear(c: u8) -> f32 {
    let s = f32::from(c) / 255.0;
    if s <= 0.04045 {
        s / 12.92
    } else {
        ((s + 0.055) / 1.055).powf(2.4)
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
    use super::*;

    /// A run of sums gives what one `add_fixed` per pixel gives, bit for bit: a pixel
    /// named twice (in one read-ahead run and across runs) gets both, pixels outside the
    /// film are ignored.
    #[test]
    fn add_fixed_run_is_add_fixed_per_pixel() {
        let (w, h) = (37u32, 23u32);
        let n = 3 * ADD_RUN + 5;
        let pixels: Vec<u32> = (0..n as u32)
            .map(|i| (i * 7919) % (w * h + 3))
            .chain([5, 5, w * h])
            .collect();
        let sums: Vec<i64> = (0..3 * pixels.len() as i64).map(|v| v * 31 + 1).collect();
        let mut one = Film::new(w, h);
        for (i, &p) in pixels.iter().enumerate() {
            one.add_fixed(p, [sums[3 * i], sums[3 * i + 1], sums[3 * i + 2]]);
        }
        let mut run = Film::new(w, h);
        run.add_fixed_run(&pixels, &sums);
        assert_eq!(run, one);
    }

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
    fn the_brightest_sky_at_the_most_samples_does_not_wrap() {
        // One contribution per sample far above the clamp, at the most samples a job
        // accepts: the pixel reads exactly the clamp, and every clamp is counted.
        let mut f = Film::new(1, 1);
        for _ in 0..MAX_SPP {
            f.add(0, Vec3::splat(1.0e7));
        }
        assert_eq!(f.clamped, u64::from(MAX_SPP));
        assert_eq!(f.saturated(), 0);
        assert_eq!(f.linear(MAX_SPP)[0], Vec3::splat(MAX_CONTRIBUTION));
        // Three more clamped contributions per sample: the sum saturates instead of
        // wrapping, and the pixel is counted as saturated.
        for _ in 0..3 * MAX_SPP {
            f.add(0, Vec3::new(1.0e30, 0.5, 1.0e9));
        }
        assert_eq!(f.sum_fixed(0)[0], MAX_SUM);
        assert_eq!(f.sum_fixed(0)[2], MAX_SUM);
        assert!(f.sum_fixed(0)[1] < MAX_SUM);
        assert_eq!(f.saturated(), 1);
        let v = f.linear(MAX_SPP)[0];
        assert!(v.min_element() > 0.0 && v.is_finite(), "{v}");
        assert!(
            v.x >= MAX_CONTRIBUTION,
            "saturated sums read high, never negative: {v}"
        );
    }

    /// A small deterministic generator for the grouping tests.
    struct Lcg(u64);
    impl Lcg {
        fn next(&mut self) -> u64 {
            self.0 = self
                .0
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            self.0 >> 11
        }
    }

    /// Sum `terms` as a random binary tree of partial films (workers' reports, tiles,
    /// merges), returning the one pixel's sum.
    fn grouped_sum(terms: &[[i64; 3]], rng: &mut Lcg) -> [i64; 3] {
        if terms.len() <= 2 {
            let mut s = [0; 3];
            for t in terms {
                add_sums(&mut s, *t);
            }
            return s;
        }
        let cut = 1 + (rng.next() as usize) % (terms.len() - 1);
        let (a, b) = (
            grouped_sum(&terms[..cut], rng),
            grouped_sum(&terms[cut..], rng),
        );
        let mut f = Film::new(1, 1);
        f.add_fixed(0, b);
        let mut g = Film::new(1, 1);
        g.add_fixed(0, a);
        g.merge(&f);
        g.sum_fixed(0)
    }

    #[test]
    fn saturating_sums_are_the_same_in_any_grouping_and_order() {
        let mut rng = Lcg(7);
        let mut saturated = 0;
        for case in 0..200 {
            // Contributions from tiny to clamped, and in every third case partial sums
            // near the limit (what workers report for very bright pixels).
            let n = 1 + (rng.next() % 400) as usize;
            let mut terms: Vec<[i64; 3]> = (0..n)
                .map(|_| {
                    if case % 3 == 0 {
                        return [0; 3]
                            .map(|_: i64| ((rng.next() << 10) >> (rng.next() % 16)) as i64);
                    }
                    let mut v = Vec3::ZERO;
                    for c in 0..3 {
                        let e = (rng.next() % 64) as i32 - 40;
                        v[c] = (2.0f32).powi(e) * (1.0 + (rng.next() % 1000) as f32 / 1000.0);
                    }
                    to_fixed(v).expect("finite")
                })
                .collect();
            let exact = terms.iter().fold([0i128; 3], |mut s, t| {
                for c in 0..3 {
                    s[c] += i128::from(t[c]);
                }
                s
            });
            let want = exact.map(|c| c.min(i128::from(MAX_SUM)) as i64);
            saturated += usize::from(want.contains(&MAX_SUM));
            for _ in 0..4 {
                // Shuffle, then group at random.
                for i in (1..terms.len()).rev() {
                    terms.swap(i, (rng.next() as usize) % (i + 1));
                }
                assert_eq!(grouped_sum(&terms, &mut rng), want, "case {case}");
            }
        }
        assert!(saturated > 20, "the cases reach the limit: {saturated}");
    }

    #[test]
    fn a_negated_sum_clears_a_pixel_even_when_saturated() {
        let mut f = Film::new(2, 1);
        for _ in 0..5 * MAX_SPP {
            f.add(1, Vec3::splat(1.0e20));
        }
        assert_eq!(f.saturated(), 1);
        let s = f.sum_fixed(1);
        f.add_fixed(1, s.map(i64::wrapping_neg));
        assert_eq!(f.sum_fixed(1), [0; 3]);
        assert_eq!(f.saturated(), 0);
    }

    #[test]
    fn srgb_encoding() {
        assert_eq!(linear_to_srgb8(0.0), 0);
        assert_eq!(linear_to_srgb8(1.0), 255);
        assert_eq!(linear_to_srgb8(f32::NAN), 0);
        assert_eq!(linear_to_srgb8(0.2158605), 128);
        for c in 0..=255u8 {
            assert_eq!(linear_to_srgb8(srgb8_to_linear(c)), c);
        }
    }
}
