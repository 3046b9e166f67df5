//! Results tagged with the progressive pass they belong to, for a job that traces passes
//! ahead (`JobSetup.passes_ahead`; docs/architecture.md "Passes", "Trace ahead").
//!
//! The coordinator keeps one pass of a tile in flight (its barrier), so what it receives
//! must be what it would have received had each pass waited for the one before. A worker
//! tracing ahead makes later passes' camera rays while earlier ones are still out, so
//! everything a ray hands back carries its pass, and the job's actor holds a later pass's
//! share until the job is in that pass ([`crate::jobs`]). The pass comes from the ray's
//! sample index (every ray of a camera ray's tree keeps it) and travels in the keys the
//! outbox already uses, so a job that does not trace ahead pays nothing:
//!
//! - a **tile key** (credit) is `pass << 24 | tile`: an untagged key is the tile itself;
//! - a **sum key** (pixel sums) is `(tile key >> 24) << 32 | pixel`: the pass's bits of
//!   the ray's tile key above the pixel, so the low 32 bits are always the pixel.
//!
//! A job traces ahead only when its tiles number fewer than 2^24 and its passes at most
//! 256 ([`dray_core::passes::MAX_PASSES`]), so both keys are exact.

use std::ops::Range;

/// Bits of a tile key below the pass.
pub const TILE_BITS: u32 = dray_core::passes::AHEAD_TILE_BITS;

/// Tiles a job tracing ahead may have (image and coarse).
pub const MAX_TAGGED_TILES: u64 = 1 << TILE_BITS;

/// The tile key of `tile` in pass `pass`.
#[inline]
pub fn tile_key(tile: u32, pass: u32) -> u32 {
    (pass << TILE_BITS) | tile
}

/// (pass, tile) of a tile key.
#[inline]
pub fn split_tile_key(key: u32) -> (u32, u32) {
    (key >> TILE_BITS, key & ((1 << TILE_BITS) - 1))
}

/// The sum key of a contribution to `pixel` by a ray of tile key `tile_key`. For a job
/// that does not trace ahead the high half carries no meaning (the pixel is the low half).
#[inline]
pub fn sum_key(pixel: u32, tile_key: u32) -> u64 {
    (u64::from(tile_key >> TILE_BITS) << 32) | u64::from(pixel)
}

/// (pass, pixel) of a sum key of a job that traces ahead.
#[inline]
pub fn split_sum_key(key: u64) -> (u32, u32) {
    ((key >> 32) as u32, key as u32)
}

/// A job's passes, as sample ranges: which pass a sample is in.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PassTags {
    ranges: Vec<Range<u32>>,
}

impl PassTags {
    /// The passes `ranges` (consecutive, from sample 0, as `dray_core::passes` cuts
    /// them). None for fewer than two passes (nothing to trace ahead) or more than the
    /// 256 a tile key holds.
    pub fn new(ranges: Vec<Range<u32>>) -> Option<PassTags> {
        let ok = ranges.len() >= 2
            && ranges.len() <= 1 << (32 - TILE_BITS)
            && ranges.first().is_some_and(|r| r.start == 0)
            && ranges.windows(2).all(|w| w[0].end == w[1].start)
            && ranges.iter().all(|r| r.start < r.end);
        ok.then_some(PassTags { ranges })
    }

    /// Passes in the job.
    pub fn count(&self) -> u32 {
        self.ranges.len() as u32
    }

    /// The samples of pass `pass`.
    pub fn range(&self, pass: u32) -> Option<Range<u32>> {
        self.ranges.get(pass as usize).cloned()
    }

    /// The pass sample `sample` is in (the last for a sample beyond the job's).
    #[inline]
    pub fn pass_of(&self, sample: u32) -> u32 {
        (self.ranges.partition_point(|r| r.start <= sample) as u32).saturating_sub(1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_round_trip_and_untagged_keys_are_the_plain_values() {
        assert_eq!(tile_key(7, 0), 7);
        assert_eq!(split_tile_key(tile_key(12345, 255)), (255, 12345));
        assert_eq!(sum_key(99, 7) as u32, 99);
        assert_eq!(sum_key(99, 7) >> 32, 0);
        assert_eq!(
            split_sum_key(sum_key(u32::MAX, tile_key(3, 200))),
            (200, u32::MAX)
        );
        // A job that does not trace ahead with more than 2^24 tiles: the pixel is still
        // the low half.
        assert_eq!(sum_key(5, 1 << 25) as u32, 5);
    }

    #[test]
    fn samples_map_to_their_passes() {
        let t = PassTags::new(vec![0..1, 1..2, 2..4, 4..7]).expect("four passes");
        assert_eq!(t.count(), 4);
        let got: Vec<u32> = (0..8).map(|s| t.pass_of(s)).collect();
        assert_eq!(got, vec![0, 1, 2, 2, 3, 3, 3, 3]);
        assert_eq!(t.range(2), Some(2..4));
        let one: Vec<Range<u32>> = std::iter::once(0..4).collect();
        assert!(PassTags::new(one).is_none(), "one pass");
        assert!(PassTags::new(vec![0..1, 2..3]).is_none(), "a gap");
        assert!(PassTags::new((0..257).map(|i| i..i + 1).collect()).is_none());
        assert!(PassTags::new((0..256).map(|i| i..i + 1).collect()).is_some());
    }
}
