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

use std::ops::Range;

use dray_core::adaptive;
use dray_proto::v1::Tile;

use super::film::JobFilm;

/// What adaptive sampling saved a job so far (`JobStats.tiles_stopped`,
/// `samples_saved`).
#[derive(Clone, Copy, Debug, Default)]
pub struct Stopped {
    pub tiles: u32,
    pub samples: u64,
}

/// Whether image tile `tile`, which has just finished the pass of samples `range`
/// (`last`: the job's last pass), stops under `threshold`: only after a pass the job
/// decides after, when the tile's error, from its exact sums before and after the pass
/// in `film`, is below the threshold. The caller stops it ([`JobFilm::stop_tile`]) and
/// counts it.
pub fn stops(film: &JobFilm, tile: &Tile, range: &Range<u32>, last: bool, threshold: f32) -> bool {
    if !adaptive::decides_after(range, last) {
        return false;
    }
    let _span = tracing::trace_span!("adaptive_decision", tile = tile.index).entered();
    adaptive::stops(adaptive::tile_error(range, film.tile_sums(tile)), threshold)
}
