//! A job's progressive passes as the public API sees them: how its samples are cut
//! (`dray_core::passes`), how many passes are complete, and the image after the last
//! complete one, which GetImage and WatchImage serve while the job runs.
//!
//! The image is a copy of the film as a pass completed (the fixed-point sums, 24 bytes a
//! pixel), built by the job's actor a tile at a time as each tile finishes the pass
//! (`RunningJob::tile_finished`); the actor goes on adding the next pass to its own film
//! meanwhile. The image is dropped when the job ends; a job of one pass ("one") never
//! makes one.

use std::ops::Range;
use std::sync::{Arc, Mutex};

use dray_core::film::Film;
use dray_core::passes::Passes;
use tokio::sync::watch;

/// The image after `passes_done` passes: `samples` samples per pixel.
#[derive(Clone)]
pub struct PassImage {
    pub film: Arc<Film>,
    pub passes_done: u32,
    pub samples: u32,
}

/// One job's passes and its latest pass image.
pub struct PassImages {
    ranges: Vec<Range<u32>>,
    latest: Mutex<Option<PassImage>>,
    /// Passes complete; watchers (WatchImage) wait for it to change.
    done: watch::Sender<u32>,
}

impl PassImages {
    /// The passes of a job with `spp` samples cut as `passes` says (JobSpec.passes,
    /// validated before; an unreadable value is taken as the default).
    pub fn new(passes: &str, spp: u32) -> PassImages {
        let cut = Passes::parse(passes, spp).unwrap_or(Passes::Doubling);
        PassImages {
            ranges: cut.ranges(spp),
            latest: Mutex::new(None),
            done: watch::channel(0).0,
        }
    }

    /// The sample range of every pass, in order.
    pub fn ranges(&self) -> &[Range<u32>] {
        &self.ranges
    }

    /// Passes in all.
    pub fn total(&self) -> u32 {
        self.ranges.len() as u32
    }

    /// Passes complete so far.
    pub fn done(&self) -> u32 {
        *self.done.borrow()
    }

    /// Samples per pixel after `passes` passes.
    pub fn samples_after(&self, passes: u32) -> u32 {
        match passes {
            0 => 0,
            n => self.ranges.get(n as usize - 1).map_or(0, |r| r.end),
        }
    }

    /// Pass `passes_done - 1` is complete and `film` is the image so far (shared with
    /// the job's actor, which keeps it as the base a retried tile returns to).
    pub fn publish(&self, film: Arc<Film>, passes_done: u32) {
        let samples = self.samples_after(passes_done);
        *self.lock() = Some(PassImage {
            film,
            passes_done,
            samples,
        });
        self.done.send_replace(passes_done);
    }

    /// Every pass is complete (the job SUCCEEDED): the final image is the job's own;
    /// the snapshot goes.
    pub fn complete(&self) {
        self.lock().take();
        self.done.send_replace(self.total());
    }

    /// The job ended otherwise: the snapshot goes, watchers wake.
    pub fn drop_image(&self) {
        self.lock().take();
        self.done.send_modify(|_| {});
    }

    /// The image after the last complete pass, while the job runs.
    pub fn latest(&self) -> Option<PassImage> {
        self.lock().clone()
    }

    /// Wakes when a pass completes or the job ends.
    pub fn subscribe(&self) -> watch::Receiver<u32> {
        self.done.subscribe()
    }

    /// The fraction of the job's samples traced when `tiles_done` of `tiles` tiles of
    /// the current pass are complete (for the ETA: passes differ in size).
    pub fn fraction(&self, tiles_done: u32, tiles: u32) -> f64 {
        let spp = self.ranges.last().map_or(1, |r| r.end).max(1);
        let done = self.done();
        let before = self.samples_after(done);
        let this = self.ranges.get(done as usize).map_or(0, |r| r.len() as u32);
        let part = if tiles == 0 {
            0.0
        } else {
            f64::from(this) * f64::from(tiles_done.min(tiles)) / f64::from(tiles)
        };
        ((f64::from(before) + part) / f64::from(spp)).min(1.0)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Option<PassImage>> {
        dray_sync::lock(&self.latest)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn passes_images_and_fractions() {
        let p = PassImages::new("", 8);
        assert_eq!(p.total(), 4);
        assert_eq!(p.fraction(0, 10), 0.0);
        assert_eq!(p.fraction(10, 10), 1.0 / 8.0);
        let mut rx = p.subscribe();
        p.publish(Arc::new(Film::new(2, 2)), 2);
        assert!(rx.has_changed().unwrap());
        assert_eq!(*rx.borrow_and_update(), 2);
        let img = p.latest().expect("an image after two passes");
        assert_eq!((img.passes_done, img.samples), (2, 2));
        // Half of the third pass (samples 2..4): 2 + 1 of 8.
        assert_eq!(p.fraction(5, 10), 3.0 / 8.0);
        p.complete();
        assert!(p.latest().is_none());
        assert_eq!(p.done(), 4);
        assert_eq!(PassImages::new("one", 8).total(), 1);
        assert_eq!(PassImages::new("3", 8).ranges(), [0..3, 3..6, 6..8]);
    }
}
