//! Adaptive sampling (`--noise-threshold X`, `JobSpec.noise_threshold`; docs/noise.md):
//! a tile whose image has converged to below the threshold takes no more samples.
//!
//! **When.** A job cut into progressive passes (`crate::passes`; doubling by default)
//! decides for each tile at the end of every pass but the last, once the tile has at
//! least [`MIN_SAMPLES`] samples. A tile that stops is not dealt in later passes, and
//! its pixels are shown divided by the samples they took (`crate::film::Film`'s
//! per-pixel counts), so its image is unbiased, only noisier than its neighbours by at
//! most the threshold.
//!
//! **The estimate** (Cycles' adaptive-sampling error, with the passes before the last
//! one in the place of Cycles' half buffer, as in Dammertz et al. 2010's hierarchical
//! stopping): for each pixel, with `I` the mean of every sample so far and `A` the mean
//! of the passes before the last one (with doubling passes, the first half of the
//! samples),
//!
//! ```text
//!     e = (|I.r - A.r| + |I.g - A.g| + |I.b - A.b|) / (0.0001 + sqrt(I.r + I.g + I.b))
//! ```
//!
//! the difference relative to the square root of the brightness, so a dark region is
//! allowed the absolute noise the eye sees there (noise is proportional to the square
//! root of the signal for photon counts). The tile's error is the mean of its pixels'
//! errors; it stops when that is below the threshold.
//!
//! **Same bits.** The decision reads only the tile's integer sums (the film's fixed
//! point, which are the same bits everywhere) and computes in `f64` with basic
//! operations and `sqrt` (correctly rounded on every IEEE 754 machine), pixels in
//! row-major order: `dray render --workers 0`, in-process workers and a cluster make the
//! same decisions for every tile, so the same image.

use std::ops::Range;

use crate::film::FIXED_SCALE;

/// The fewest samples a tile takes before it may stop: fewer say too little about a
/// pixel's variance (a light that 4 samples all missed looks converged). With doubling
/// passes the first decisions are at 16 samples, then 32, 64, ...
pub const MIN_SAMPLES: u32 = 16;

/// Cycles' guard against dividing by zero in black pixels.
const EPSILON: f64 = 1e-4;

/// `--noise-threshold X` / `JobSpec.noise_threshold`: a finite number above 0 and at most
/// 1 (the error is relative to the square root of brightness: Cycles' default is 0.01,
/// 0.1 is already coarse; above 1 every tile would stop at its first chance).
pub fn check_threshold(x: f32) -> Result<f32, String> {
    if x.is_finite() && x > 0.0 && x <= 1.0 {
        Ok(x)
    } else {
        Err(format!(
            "must be a number above 0 and at most 1 (the noise left, relative to the \
             square root of brightness; 0.01 is Cycles' default), got {x}"
        ))
    }
}

/// Whether a decision is taken after the pass of samples `pass` (a range of the job's
/// passes), `last` saying whether it is the job's last pass: not after the last pass
/// (nothing follows it) nor before [`MIN_SAMPLES`].
pub fn decides_after(pass: &Range<u32>, last: bool) -> bool {
    !last && pass.start > 0 && pass.end >= MIN_SAMPLES
}

/// The error of one tile after the pass of samples `pass`: `sums` gives, for each of its
/// pixels in row-major order, the sums before the pass (`pass.start` samples) and the
/// sums after it (`pass.end` samples), in the film's fixed point. See the module's
/// comment for the formula.
pub fn tile_error(pass: &Range<u32>, sums: impl Iterator<Item = ([i64; 3], [i64; 3])>) -> f64 {
    let before = 1.0 / (FIXED_SCALE * f64::from(pass.start.max(1)));
    let after = 1.0 / (FIXED_SCALE * f64::from(pass.end.max(1)));
    let (mut total, mut pixels) = (0.0f64, 0u64);
    for (a, i) in sums {
        let mut diff = 0.0;
        let mut bright = 0.0;
        for c in 0..3 {
            let mean_i = i[c] as f64 * after;
            diff += (mean_i - a[c] as f64 * before).abs();
            bright += mean_i;
        }
        total += diff / (EPSILON + bright.max(0.0).sqrt());
        pixels += 1;
    }
    if pixels == 0 {
        0.0
    } else {
        total / pixels as f64
    }
}

/// Whether a tile of error `error` stops at `threshold`.
pub fn stops(error: f64, threshold: f32) -> bool {
    error < f64::from(threshold)
}

/// What adaptive sampling did to a job, read from its film's per-pixel counts (the
/// same for every configuration, since the film is).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Saved {
    /// Tiles that stopped before the job's last pass.
    pub tiles_stopped: u32,
    /// Samples not taken: `spp` minus what each pixel took, summed over the pixels.
    pub samples_saved: u64,
}

impl Saved {
    /// Count what `film` (of a job of `spp` samples per pixel) shows was saved.
    pub fn of(film: &crate::film::Film, spp: u32) -> Saved {
        let Some(stops) = film.stops() else {
            return Saved::default();
        };
        let grid = crate::tiles::TileGrid::image(film.width, film.height);
        let tiles_stopped = grid
            .iter()
            .filter(|t| stops[(t.y0 * film.width + t.x0) as usize] > 0)
            .count() as u32;
        let samples_saved = stops
            .iter()
            .filter(|&&n| n > 0)
            .map(|&n| u64::from(spp.saturating_sub(n)))
            .sum();
        Saved {
            tiles_stopped,
            samples_saved,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixed(v: f64) -> i64 {
        (v * FIXED_SCALE) as i64
    }

    #[test]
    fn a_flat_tile_stops_and_a_noisy_one_does_not() {
        // 16 samples: 8 before the pass, 8 in it.
        let pass = 8..16;
        // Every sample 0.5 in every channel: the means agree exactly.
        let flat = (0..4).map(|_| ([fixed(4.0); 3], [fixed(8.0); 3]));
        assert_eq!(tile_error(&pass, flat), 0.0);
        // The first half saw 0.5 a sample, the second 1.5: I = 1, A = 0.5.
        let noisy = (0..4).map(|_| ([fixed(4.0); 3], [fixed(16.0); 3]));
        let e = tile_error(&pass, noisy);
        let want = 1.5 / (EPSILON + 3f64.sqrt());
        assert!((e - want).abs() < 1e-9, "{e} vs {want}");
        assert!(!stops(e, 0.01) && stops(0.0, 0.01));
    }

    #[test]
    fn decisions_wait_for_min_samples_and_skip_the_last_pass() {
        assert!(!decides_after(&(4..8), false));
        assert!(decides_after(&(8..16), false));
        assert!(!decides_after(&(8..16), true), "the last pass");
        assert!(!decides_after(&(0..64), false), "one pass has no before");
    }

    #[test]
    fn thresholds_and_their_errors() {
        assert_eq!(check_threshold(0.01), Ok(0.01));
        assert_eq!(check_threshold(1.0), Ok(1.0));
        for bad in [0.0, -0.1, 1.5, f32::NAN, f32::INFINITY] {
            let e = check_threshold(bad).expect_err("bad");
            assert!(e.contains("above 0 and at most 1"), "{e}");
        }
    }
}
