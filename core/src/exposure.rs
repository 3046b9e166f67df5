//! Exposure of 8-bit output: a number of stops (radiance times 2^EV), or chosen from the
//! image itself.
//!
//! Scenes come in any units. A procedural Cornell box has radiance near 1; a glTF scene
//! with photometric lights (`KHR_lights_punctual` in lux and candela, emissive strengths
//! of 20 and more) has radiance in the thousands, and at a fixed exposure it is a white
//! sheet. The automatic exposure measures the image's *key* the way Reinhard et al. 2002
//! do (the log-average luminance, a geometric mean, which follows what the eye calls the
//! overall brightness) and maps it to mid-grey (0.18). Two things keep it robust:
//!
//! - pixels with no light at all (luminance 0: background against a black environment)
//!   or a non-finite value are left out, so a small model in a black frame is exposed
//!   for the model, not for the frame;
//! - each log-luminance is clamped to the image's 5th..95th percentile before averaging
//!   (a winsorised mean), so a few very bright pixels (a visible lamp, the sun's disc,
//!   fireflies) or very dark ones cannot pull the exposure: up to 5% of the pixels at
//!   any value change the key only as much as the same pixels at the percentile would.
//!
//! The percentiles come from a histogram of log2 luminance (1/32 stop per bin), and the
//! mean is summed in one order in f64, so the same film gives the same exposure on every
//! run, thread count and worker count: a distributed job, exposed by the coordinator
//! after assembly, has the same bits as `dray render`.

use glam::Vec3;

/// Largest exposure either way, in stops: far beyond any scene's need, small enough
/// that 2^EV is a finite, non-zero f32.
pub const MAX_STOPS: f32 = 64.0;
/// The display value the image's key is mapped to (Reinhard's key value *a*).
pub const MID_GREY: f32 = 0.18;
/// The share of lit pixels each end of the histogram that the key clamps away.
pub const CLAMP_PERCENTILE: f64 = 0.05;

/// Histogram of log2 luminance: bins per stop and the range covered (luminance outside
/// goes to the end bins; the film holds nothing outside 2^-40..2^63 anyway).
const BINS_PER_STOP: f32 = 32.0;
const LOG2_MIN: f32 = -64.0;
const LOG2_MAX: f32 = 64.0;
const BINS: usize = ((LOG2_MAX - LOG2_MIN) * BINS_PER_STOP) as usize;

/// How 8-bit output is exposed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Exposure {
    /// Chosen from the image: its key goes to mid-grey ([`auto_stops`]).
    Auto,
    /// Radiance times 2^EV, EV finite and within ±[`MAX_STOPS`].
    Stops(f32),
}

/// An exposure that is neither `auto` nor a number of stops in range.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ExposureError {
    #[error("{0:?} is neither \"auto\" nor a number of stops")]
    NotANumber(String),
    #[error("{0} is out of range (-{MAX_STOPS}..={MAX_STOPS} stops)")]
    OutOfRange(f32),
}

impl Exposure {
    /// A fixed exposure of `ev` stops, checked.
    pub fn stops(ev: f32) -> Result<Exposure, ExposureError> {
        if ev.is_finite() && ev.abs() <= MAX_STOPS {
            Ok(Exposure::Stops(ev))
        } else {
            Err(ExposureError::OutOfRange(ev))
        }
    }

    /// `auto` or a number of stops (`-12`, `0.5`).
    pub fn parse(s: &str) -> Result<Exposure, ExposureError> {
        let s = s.trim();
        if s.eq_ignore_ascii_case("auto") {
            return Ok(Exposure::Auto);
        }
        let ev: f32 = s
            .parse()
            .map_err(|_| ExposureError::NotANumber(s.to_string()))?;
        Exposure::stops(ev)
    }

    /// The stops to apply to an image of linear radiance `pixels`.
    pub fn resolve(self, pixels: &[Vec3]) -> f32 {
        match self {
            Exposure::Auto => auto_stops(pixels),
            Exposure::Stops(ev) => ev,
        }
    }
}

impl std::fmt::Display for Exposure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Exposure::Auto => f.write_str("auto"),
            Exposure::Stops(ev) => write!(f, "{ev}"),
        }
    }
}

impl std::str::FromStr for Exposure {
    type Err = ExposureError;
    fn from_str(s: &str) -> Result<Exposure, ExposureError> {
        Exposure::parse(s)
    }
}

/// Rec.709 luminance of linear sRGB.
#[inline]
pub fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// log2 luminance of a pixel that has light, `None` for one that has none (or a
/// non-finite value).
#[inline]
fn log_luminance(c: Vec3) -> Option<f32> {
    let y = luminance(c);
    (y.is_finite() && y > 0.0).then(|| y.log2())
}

fn bin_of(l: f32) -> usize {
    (((l - LOG2_MIN) * BINS_PER_STOP).max(0.0) as usize).min(BINS - 1)
}

/// The lower edge of bin `b`, in log2 luminance.
fn edge_of(b: usize) -> f32 {
    LOG2_MIN + b as f32 / BINS_PER_STOP
}

/// The image's key: the log-average luminance of its lit pixels, each clamped to the
/// [`CLAMP_PERCENTILE`] percentiles, in log2 units; `None` when no pixel has light.
pub fn log2_key(pixels: &[Vec3]) -> Option<f32> {
    let mut hist = vec![0u64; BINS];
    let mut lit = 0u64;
    for l in pixels.iter().filter_map(|p| log_luminance(*p)) {
        hist[bin_of(l)] += 1;
        lit += 1;
    }
    if lit == 0 {
        return None;
    }
    // The bins holding the pixels of rank CLAMP_PERCENTILE and 1 - CLAMP_PERCENTILE:
    // values are clamped to the low bin's lower edge and the high bin's upper edge, so
    // the clamp never moves a pixel that lies inside the central range.
    let rank = |q: f64| ((lit as f64 * q) as u64).min(lit - 1);
    let bin_at = |r: u64| {
        let mut seen = 0u64;
        hist.iter()
            .position(|&n| {
                seen += n;
                seen > r
            })
            .unwrap_or(BINS - 1)
    };
    let lo = edge_of(bin_at(rank(CLAMP_PERCENTILE)));
    let hi = edge_of(bin_at(rank(1.0 - CLAMP_PERCENTILE)) + 1);
    let sum: f64 = pixels
        .iter()
        .filter_map(|p| log_luminance(*p))
        .map(|l| f64::from(l.clamp(lo, hi)))
        .sum();
    Some((sum / lit as f64) as f32)
}

/// The exposure, in stops, that maps the image's key ([`log2_key`]) to [`MID_GREY`],
/// within ±[`MAX_STOPS`]; 0 for an image with no light (nothing to expose).
pub fn auto_stops(pixels: &[Vec3]) -> f32 {
    match log2_key(pixels) {
        Some(key) => (MID_GREY.log2() - key).clamp(-MAX_STOPS, MAX_STOPS),
        None => 0.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_auto_and_stops() {
        assert_eq!(Exposure::parse("auto"), Ok(Exposure::Auto));
        assert_eq!(Exposure::parse("AUTO"), Ok(Exposure::Auto));
        assert_eq!(Exposure::parse("-12.5"), Ok(Exposure::Stops(-12.5)));
        assert_eq!(Exposure::parse("0"), Ok(Exposure::Stops(0.0)));
        assert_eq!(Exposure::parse("64"), Ok(Exposure::Stops(64.0)));
        assert_eq!(Exposure::parse("65"), Err(ExposureError::OutOfRange(65.0)));
        assert!(matches!(
            Exposure::parse("NaN"),
            Err(ExposureError::OutOfRange(_))
        ));
        assert!(matches!(
            Exposure::parse("inf"),
            Err(ExposureError::OutOfRange(_))
        ));
        let e = Exposure::parse("bright").expect_err("not a number");
        assert_eq!(
            e.to_string(),
            "\"bright\" is neither \"auto\" nor a number of stops"
        );
        assert_eq!(Exposure::Auto.to_string(), "auto");
        assert_eq!(Exposure::Stops(-2.5).to_string(), "-2.5");
    }

    #[test]
    fn a_uniform_image_is_exposed_to_mid_grey() {
        for y in [1e-6f32, 0.18, 1.0, 6830.0, 1e9] {
            let ev = auto_stops(&vec![Vec3::splat(y); 1000]);
            let exposed = y * 2f32.powf(ev);
            assert!(
                (exposed / MID_GREY - 1.0).abs() < 1e-3,
                "{y}: {ev} EV gives {exposed}"
            );
        }
    }

    #[test]
    fn unlit_and_non_finite_pixels_are_left_out() {
        assert_eq!(auto_stops(&[]), 0.0);
        assert_eq!(auto_stops(&vec![Vec3::ZERO; 50]), 0.0);
        // A lit model in a black frame with a few broken pixels: exposed for the model.
        let mut px = vec![Vec3::ZERO; 900];
        px.extend(vec![Vec3::splat(500.0); 100]);
        px.push(Vec3::splat(f32::NAN));
        px.push(Vec3::splat(f32::INFINITY));
        px.push(Vec3::splat(-3.0));
        let ev = auto_stops(&px);
        assert!(
            (500.0 * 2f32.powf(ev) / MID_GREY - 1.0).abs() < 1e-3,
            "{ev}"
        );
    }

    #[test]
    fn the_key_is_the_geometric_mean_of_the_central_range() {
        // Two equal halves a factor 16 apart: the key is their geometric mean.
        let mut px = vec![Vec3::splat(1.0); 500];
        px.extend(vec![Vec3::splat(16.0); 500]);
        assert!((log2_key(&px).unwrap() - 2.0).abs() < 1e-6);
    }
}
