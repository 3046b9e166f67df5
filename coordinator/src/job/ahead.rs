//! Tracing passes ahead (`JobSetup.passes_ahead`; docs/architecture.md "Passes", "Trace
//! ahead"): when a job's workers may make later passes' camera rays before the pass the
//! job is in is complete, and which tiles the coordinator then deals.
//!
//! With a barrier per pass, a job under a memory budget walks every domain once per pass:
//! doubling passes cost 2.3-2.6x the domain loads of one pass
//! (docs/history/2026-11-29-passes-under-a-budget.md). Tracing ahead lets the passes share
//! one walk. The
//! coordinator's side stays what it was (one pass of a tile counted at a time, pass
//! images, retries, the job store); what changes is the dealing: a worker dealt a tile in
//! this attempt holds it for every later pass, so the tile is not dealt again until the
//! next attempt, and every worker is told when a pass starts (it then reports what it
//! held of that pass).
//!
//! The price is when pass images come: a pass is complete when its slowest tile is, and
//! with the passes sharing a walk that is near the end of the walk. So a job traces
//! ahead only where the walk is what costs: under a memory budget; or where the barrier
//! is all a pass costs beyond its tracing: the replicated schedule (issue 40), whose
//! workers load nothing and exchange nothing, so at each barrier a worker that finished
//! its tiles had nothing to do until the slowest one finished its own (doubling passes
//! took 7.3 s where one pass took 5.0 s on 3 workers). Its workers trace their tiles
//! pass by pass, earliest first, so pass images still come in order.

/// Pixel-passes the workers of a job may hold back at once (their held sums take about
/// 32-48 bytes each, spread over the workers): 8 Mi pixel-passes, 256-400 MB at most.
/// A 192x192 image may trace 227 passes ahead, a 1920x1080 one 4.
pub const HELD_PIXEL_PASSES: u64 = 1 << 23;

/// Passes a job's workers may trace ahead of the job's pass (0: none, each pass waits for
/// the one before): for a job of `passes` passes and `pixels` pixels with `tiles` tiles
/// (image and coarse), when some worker has a memory budget or the schedule is
/// replicated (`worth`) and the job has no ray caches or hit maps (`walled`: their coarse
/// pass and tickets are per pass) and no adaptive sampling (`adaptive`: whether a tile
/// takes its next pass is decided when the pass before it ends, so a worker holding
/// later passes would trace samples the job may not take; docs/noise.md).
pub fn passes_ahead(
    passes: u32,
    pixels: u64,
    tiles: usize,
    worth: bool,
    walled: bool,
    adaptive: bool,
) -> u32 {
    let tagged = (tiles as u64) < 1 << dray_core::passes::AHEAD_TILE_BITS;
    if passes < 2 || !worth || walled || adaptive || !tagged {
        return 0;
    }
    let by_memory = HELD_PIXEL_PASSES / pixels.max(1);
    u64::from(passes - 1).min(by_memory) as u32
}

/// Which image tiles a worker of the current attempt holds (dealt in this attempt: it
/// traces every later pass of them).
#[derive(Debug)]
pub struct Held {
    tiles: Vec<bool>,
}

impl Held {
    pub fn new(image_tiles: usize) -> Held {
        Held {
            tiles: vec![false; image_tiles],
        }
    }

    /// A new attempt: its workers hold nothing yet.
    pub fn clear(&mut self) {
        self.tiles.fill(false);
    }

    /// Tile `t` was dealt in this attempt.
    pub fn deal(&mut self, t: usize) {
        if let Some(h) = self.tiles.get_mut(t) {
            *h = true;
        }
    }

    /// Whether a worker of this attempt holds tile `t`.
    pub fn holds(&self, t: usize) -> bool {
        self.tiles.get(t).copied().unwrap_or(false)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_jobs_under_a_budget_with_passes_trace_ahead_as_far_as_memory_allows() {
        assert_eq!(passes_ahead(3, 192 * 192, 144, true, false, false), 2);
        assert_eq!(
            passes_ahead(3, 192 * 192, 144, false, false, false),
            0,
            "no budget, not replicated"
        );
        assert_eq!(
            passes_ahead(3, 192 * 192, 144, true, true, false),
            0,
            "ray caches"
        );
        assert_eq!(
            passes_ahead(1, 192 * 192, 144, true, false, false),
            0,
            "one pass"
        );
        assert_eq!(
            passes_ahead(3, 192 * 192, 144, true, false, true),
            0,
            "adaptive sampling"
        );
        assert_eq!(passes_ahead(12, 1920 * 1080, 8160, true, false, false), 4);
        assert_eq!(passes_ahead(12, 1 << 30, 1 << 20, true, false, false), 0);
        assert_eq!(
            passes_ahead(3, 64, 1 << 24, true, false, false),
            0,
            "tile keys"
        );
    }
}
