//! Adaptive sampling on workers (`JobSpec.noise_threshold`; `dray_core::adaptive`,
//! docs/noise.md): when an image tile finishes a pass, its job's actor decides from the
//! tile's exact sums whether it takes the later passes.
//!
//! The decision is the one `dray render --workers 0` makes (`dray_core::render::
//! render_passes`): the same integer sums before the pass (the pass image it started
//! from) and after it (the film, final for the tile once its credit is back), read in
//! the same order by the same function. A tile that stops is complete in every later
//! pass, as a tile taken back whole from the job store is: it is not dealt again, its
//! pixels go into each later pass image as they are, and a lost worker never clears it.
//! Its pixels keep the samples they stopped at in the film (`Film::set_stop`), which
//! divides them by those.
//!
//! Workers know nothing of it: a stopped tile is simply not dealt. That is why a job
//! with a noise threshold does not trace passes ahead (`super::ahead`): a worker holding
//! a tile's later passes would trace them before the decision.

use dray_core::adaptive;

use super::running::RunningJob;

/// What adaptive sampling saved a job so far (`JobStats.tiles_stopped`,
/// `samples_saved`).
#[derive(Clone, Copy, Debug, Default)]
pub struct Stopped {
    pub tiles: u32,
    pub samples: u64,
}

impl RunningJob {
    /// Image tile `t` has just finished the current pass: with a noise threshold, and a
    /// pass after which the job decides, stop it when its error is below the threshold.
    /// Returns whether it stopped.
    pub(super) fn maybe_stop(&mut self, t: usize) -> bool {
        let Some(threshold) = self.entry.spec.noise_threshold else {
            return false;
        };
        let Some(range) = self.entry.passes.ranges().get(self.pass).cloned() else {
            return false;
        };
        if !adaptive::decides_after(&range, self.last_pass()) {
            return false;
        }
        let _span = tracing::trace_span!("adaptive_decision", tile = t).entered();
        let tile = self.tiles[t];
        let width = self.film.width;
        let (x1, y1) = (
            tile.x0.saturating_add(tile.width).min(width),
            tile.y0.saturating_add(tile.height).min(self.film.height),
        );
        let pixels = (tile.y0..y1).flat_map(|y| (tile.x0..x1).map(move |x| y * width + x));
        let base = self.pass_base.as_deref();
        let error = adaptive::tile_error(
            &range,
            pixels.clone().map(|p| {
                (
                    base.map_or([0; 3], |b| b.sum_fixed(p)),
                    self.film.sum_fixed(p),
                )
            }),
        );
        if !adaptive::stops(error, threshold) {
            return false;
        }
        let mut n = 0u64;
        for p in pixels {
            self.film.set_stop(p, range.end);
            n += 1;
        }
        self.tile_passes[t] = self.passes_total();
        self.stopped.tiles += 1;
        self.stopped.samples += n * u64::from(self.entry.spec.spp.saturating_sub(range.end));
        true
    }
}
