//! Progressive passes: how a job's samples per pixel are cut into passes, so the image
//! of a running job can be shown after each one (docs/architecture.md "Passes").
//!
//! Pass `k` traces samples `ranges()[k]` of every pixel. Each sample's random numbers
//! are keyed by pixel and sample index, and the film adds fixed-point integers, so the
//! final image is the same bits however the samples are cut: passes change when an
//! image can be seen, never what it is.

use std::ops::Range;

/// The default cut: [`Passes::Doubling`].
pub const DEFAULT: &str = "doubling";

/// The most passes a fixed cut may make. Each pass ends at a barrier (its slowest tile)
/// and makes an image: 1 sample per pass of a 65,536-sample job ran 32,628 passes in
/// 300 s where one pass took 16 s (issue 45, item 13). Doubling makes at most 17.
pub const MAX_PASSES: u32 = 256;

/// Bits of a worker's tile key below the pass, when a job traces passes ahead
/// (`JobSetup.passes_ahead`; the worker's `tracer::pass_tag`): such a job has fewer than
/// 2^24 tiles, and its [`MAX_PASSES`] passes fit the 8 bits above.
pub const AHEAD_TILE_BITS: u32 = 24;
const _: () = assert!(MAX_PASSES <= 1 << (32 - AHEAD_TILE_BITS));

/// How the samples are cut.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Passes {
    /// 1, 1, 2, 4, ... samples per pixel: after pass `k` the image has `2^k` samples
    /// (the last pass takes what is left), about log2(spp) + 1 passes. Early previews
    /// come fast, and the waits before pass boundaries (the slowest tile of each pass)
    /// stay few.
    Doubling,
    /// Passes of this many samples (the last one smaller); `Every(spp)` is one pass.
    Every(u32),
}

impl Passes {
    /// Parse the JobSpec/CLI form: "doubling", "one", or a number of samples per pass
    /// (1..=spp, in digits only: `" 1"` or `"+1"` is refused, not read as 1) making at
    /// most [`MAX_PASSES`] passes. Empty means [`DEFAULT`].
    pub fn parse(s: &str, spp: u32) -> Result<Passes, String> {
        let spp = spp.max(1);
        match s {
            "" | "doubling" => Ok(Passes::Doubling),
            "one" => Ok(Passes::Every(spp)),
            n => match n.parse::<u32>() {
                Ok(k) if n.bytes().all(|b| b.is_ascii_digit()) && (1..=spp).contains(&k) => {
                    let least = spp.div_ceil(MAX_PASSES);
                    if k < least {
                        return Err(format!(
                            "{k} samples per pass would make {} passes of {spp} samples, more \
                             than {MAX_PASSES} (every pass is a barrier and an image): give at \
                             least {least} samples per pass, or \"doubling\"",
                            spp.div_ceil(k)
                        ));
                    }
                    Ok(Passes::Every(k))
                }
                _ => Err(format!(
                    "{s:?} is not \"doubling\", \"one\" or a number of samples per pass \
                     1..={spp}"
                )),
            },
        }
    }

    /// The sample ranges of the passes of a `spp`-sample image, in order: contiguous,
    /// non-empty, covering `0..spp` (one pass `0..1` for spp 0, taken as 1).
    pub fn ranges(self, spp: u32) -> Vec<Range<u32>> {
        let spp = spp.max(1);
        let mut out = Vec::new();
        let mut at = 0u32;
        while at < spp {
            let end = match self {
                Passes::Doubling => at.saturating_mul(2).max(1).min(spp),
                Passes::Every(n) => at.saturating_add(n.max(1)).min(spp),
            };
            out.push(at..end);
            at = end;
        }
        out
    }
}

#[cfg(test)]
// One pass is one range: a list of one range is what is meant.
#[allow(clippy::single_range_in_vec_init)]
mod tests {
    use super::*;

    #[test]
    fn doubling_shows_powers_of_two_and_ends_at_spp() {
        assert_eq!(Passes::Doubling.ranges(1), [0..1]);
        assert_eq!(Passes::Doubling.ranges(8), [0..1, 1..2, 2..4, 4..8]);
        assert_eq!(
            Passes::Doubling.ranges(100),
            [0..1, 1..2, 2..4, 4..8, 8..16, 16..32, 32..64, 64..100]
        );
        assert_eq!(Passes::Doubling.ranges(65536).len(), 17);
    }

    #[test]
    fn fixed_passes_and_one_pass() {
        assert_eq!(Passes::Every(3).ranges(8), [0..3, 3..6, 6..8]);
        assert_eq!(Passes::parse("one", 16).unwrap().ranges(16), [0..16]);
        assert_eq!(Passes::parse("", 16).unwrap(), Passes::Doubling);
        assert_eq!(Passes::parse("16", 16).unwrap(), Passes::Every(16));
        for bad in [
            "0", "17", "-1", "half", "1.5", " 1", "1 ", "+1", " one", "Doubling",
        ] {
            let e = Passes::parse(bad, 16).unwrap_err();
            assert!(e.contains("doubling"), "{e}");
        }
    }

    #[test]
    fn fixed_cuts_make_at_most_max_passes() {
        let e = Passes::parse("1", 65536).unwrap_err();
        assert!(
            e.contains("65536 passes") && e.contains("at least 256"),
            "{e}"
        );
        assert_eq!(
            Passes::parse("256", 65536).unwrap().ranges(65536).len(),
            256
        );
        assert_eq!(Passes::parse("1", 256).unwrap().ranges(256).len(), 256);
        assert!(Passes::parse("1", 257).is_err());
    }

    #[test]
    fn every_cut_covers_every_sample_once() {
        for spp in [1u32, 2, 3, 7, 64, 1000] {
            for p in [
                Passes::Doubling,
                Passes::Every(1),
                Passes::Every(5),
                Passes::Every(spp),
            ] {
                let r = p.ranges(spp);
                assert_eq!(r[0].start, 0);
                assert_eq!(r.last().unwrap().end, spp);
                assert!(r.windows(2).all(|w| w[0].end == w[1].start));
                assert!(r.iter().all(|x| !x.is_empty()));
            }
        }
    }
}
