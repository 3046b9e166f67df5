//! Camera rays: a tile's rays, each with its share of the tile's credit.

use dray_core::credit::Credit;
use dray_core::integrator::{RayKind, RayState};
use dray_core::tiles::TileGrid;

use super::outbox::Outbox;
use super::residency::{Pins, Residency, StepCtx};
use super::trace::{InFlight, Step};
use super::{JobTracer, TraceError};
use crate::tickets::Lineage;

/// The sample index of coarse-pass rays: their random numbers are keyed apart from every
/// sample of the image (spp is at most 65536).
const COARSE_SAMPLE: u32 = u32::MAX;

/// Where in coarse pixel `pixel` a randomized coarse-pass ray crosses, in [0, 1)^2: a
/// counter-based random number of the job's seed and the pixel (the film jitter of
/// sample [`COARSE_SAMPLE`], which no image sample uses), so any worker makes the same
/// ray for it.
fn coarse_jitter(seed: u64, pixel: u32) -> glam::Vec2 {
    use dray_core::sampling::{PathKey, Purpose};
    PathKey {
        seed,
        pixel,
        sample: COARSE_SAMPLE,
    }
    .uniform2(0, Purpose::Film, 0)
}

/// A rectangle of the image whose camera rays this worker generates.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileRef {
    pub index: u32,
    pub x0: u32,
    pub y0: u32,
    pub width: u32,
    pub height: u32,
    pub credit: Credit,
    /// A tile of the ray-cache coarse pass: its pixels are those of the coarse image,
    /// one regular ray each.
    pub coarse: bool,
    /// The progressive pass (`dray_core::passes`): samples `first_sample..first_sample
    /// + samples` of every pixel; `samples` 0 means every sample of the job.
    pub first_sample: u32,
    pub samples: u32,
}

impl TileRef {
    /// Every tile of `grid` with `credit`, numbered as the coordinator deals an image's
    /// tiles (`dispatch::image_tiles`): a whole image's work, for tests and benches that
    /// drive a tracer without a coordinator.
    pub fn all(grid: &TileGrid, credit: Credit) -> Vec<TileRef> {
        grid.iter()
            .zip(0..)
            .map(|(t, index)| TileRef {
                index,
                x0: t.x0,
                y0: t.y0,
                width: t.w,
                height: t.h,
                credit,
                coarse: false,
                first_sample: 0,
                samples: 0,
            })
            .collect()
    }

    /// This tile in the pass of samples `samples` (credit as given).
    pub fn in_pass(self, samples: std::ops::Range<u32>) -> TileRef {
        TileRef {
            first_sample: samples.start,
            samples: samples.len() as u32,
            ..self
        }
    }

    /// Samples per pixel this tile traces of a `spp`-sample job: its pass's, or all
    /// (one for a coarse tile).
    pub fn samples_per_pixel(&self, spp: u32) -> u32 {
        match (self.coarse, self.samples) {
            (true, _) => 1,
            (false, 0) => spp.max(1),
            (false, n) => n,
        }
    }

    /// Camera rays in the tile: pixels times samples (one per pixel for a coarse tile).
    pub fn camera_rays(&self, spp: u32) -> u64 {
        self.width as u64 * self.height as u64 * u64::from(self.samples_per_pixel(spp))
    }
}

impl JobTracer {
    /// Tiles the job has: the image's, then the coarse pass's (none without one).
    pub fn tile_count(&self) -> u64 {
        u64::from(self.tiles.count()) + u64::from(self.coarse_tiles.count())
    }

    /// The key credit of a ray of `pixel`, sample `sample` goes back to: the tile
    /// holding the pixel (of the coarse image for a coarse-pass ray), tagged with the
    /// sample's pass when the job traces passes ahead ([`super::pass_tag`]).
    pub fn tile_of(&self, pixel: u32, sample: u32, coarse: bool) -> u32 {
        if coarse {
            return self.tiles.count() + self.coarse_tiles.index_of_pixel(pixel);
        }
        let tile = self.tiles.index_of_pixel(pixel);
        match &self.tags {
            Some(t) => super::pass_tag::tile_key(tile, t.pass_of(sample)),
            None => tile,
        }
    }

    /// The key `tile`'s camera rays give credit back to (see [`JobTracer::tile_of`]).
    pub fn tile_key(&self, tile: &TileRef) -> u32 {
        match &self.tags {
            Some(t) if !tile.coarse => {
                super::pass_tag::tile_key(tile.index, t.pass_of(tile.first_sample))
            }
            _ => tile.index,
        }
    }

    /// Camera rays `start..start + count` of `tile` (ray i is pixel i / spp of the tile,
    /// row-major, sample i % spp), each sent to the first domain it enters.
    pub fn camera_rays(
        &self,
        tile: &TileRef,
        start: u64,
        count: u64,
        residency: &dyn Residency,
        out: &mut Outbox,
    ) -> Result<(), TraceError> {
        let total = self.check_tile(tile)?;
        let spp = u64::from(tile.samples_per_pixel(self.settings.spp));
        let pins = Pins::new(residency, self.nonempty.len());
        let ctx = StepCtx::new(self, &pins);
        let bare = &ctx.bare;
        let mut step = Step::default();
        // A layout of one domain, traced here: every ray of a camera ray's tree stays in
        // it, and the trees are traced with no routing.
        let whole = self.single.and_then(|d| {
            ctx.domain(d)
                .map(|(loaded, integrator)| (d, loaded, integrator))
        });
        let end = start.saturating_add(count).min(total);
        if start >= end {
            return Ok(());
        }
        // Every ray but the tile's first has the same share.
        let (first_share, share_rest) = (
            tile.credit.camera_share(total, 0).unwrap_or(Credit::ZERO),
            tile.credit.camera_share(total, 1).unwrap_or(Credit::ZERO),
        );
        // Counted once for the run, where each ray was counted as it was made.
        out.traced[RayKind::Camera as usize] += end - start;
        let mut at = TileCursor::new(start, spp, tile.width);
        // One lineage for the tile's rays: a camera ray has no tickets, and is coarse
        // when its tile is.
        let lin = Lineage {
            tickets: None,
            coarse: tile.coarse,
            probe: false,
        };
        // The ray in flight, rewritten in place for each camera ray: a one-domain tree
        // is traced from here without the ray being copied through temporaries (each
        // copy of a just-written ray stalled on store forwarding).
        let key = self.tile_key(tile);
        let mut f = InFlight {
            ray: RayState::default(),
            credit: first_share,
            tile: key,
            lineage: &lin,
        };
        for i in start..end {
            f.credit = if i == 0 { first_share } else { share_rest };
            f.ray = if tile.coarse {
                self.coarse_camera_ray(bare, tile, at.x, at.y)
            } else {
                bare.camera_ray_xy(tile.x0 + at.x, tile.y0 + at.y, tile.first_sample + at.s)
            };
            at.advance();
            if let Some(whole) = whole {
                self.trace_tree(whole, &mut f, &mut step, out)?;
                continue;
            }
            let flight = InFlight {
                ray: f.ray,
                credit: f.credit,
                tile: key,
                lineage: &lin,
            };
            self.route_new(&ctx, bare, flight, out);
            // Depth first, one camera ray's tree at a time: the stack of local rays stays
            // a few entries deep and in cache, where making the whole chunk's camera rays
            // first stacked thousands of them (half a megabyte).
            self.trace_local(&ctx, &mut step, out)?;
        }
        Ok(())
    }

    /// Checks `tile` against the job before any of its rays is made: its pass lies within
    /// the job's samples, its credit gives every camera ray a share, and every pixel is in
    /// the image (or the coarse image), so the rays made from it and their descendants
    /// need no check of their own. Returns the tile's camera-ray count.
    fn check_tile(&self, tile: &TileRef) -> Result<u64, TraceError> {
        let spp = u64::from(tile.samples_per_pixel(self.settings.spp));
        let job_spp = self.settings.spp.max(1);
        if !tile.coarse
            && tile.samples > 0
            && u64::from(tile.first_sample) + u64::from(tile.samples) > u64::from(job_spp)
        {
            return Err(TraceError::BadSamples {
                tile: tile.index,
                first: tile.first_sample,
                count: tile.samples,
                spp: job_spp,
            });
        }
        let total = tile.camera_rays(self.settings.spp);
        if tile.credit.camera_share(total, 0).is_none() {
            return Err(TraceError::TileCredit {
                tile: tile.index,
                w: tile.width,
                h: tile.height,
                spp: spp as u32,
                credit: tile.credit,
            });
        }
        let (width, height) = if tile.coarse {
            (self.coarse, self.coarse)
        } else {
            (self.settings.width, self.settings.height)
        };
        if tile.x0 as u64 + tile.width as u64 > width as u64
            || tile.y0 as u64 + tile.height as u64 > height as u64
        {
            return Err(TraceError::BadTile {
                tile: tile.index,
                x0: tile.x0,
                y0: tile.y0,
                w: tile.width,
                h: tile.height,
                width,
                height,
            });
        }
        Ok(total)
    }

    /// The coarse-pass ray of coarse pixel (`tile.x0 + lx`, `tile.y0 + ly`), its random
    /// numbers keyed apart from every sample of the image: through the pixel's centre,
    /// or through a point drawn from the job's seed and the coarse pixel (Little 2011's
    /// randomized positions; the same point on every worker).
    fn coarse_camera_ray(
        &self,
        bare: &dray_core::integrator::Integrator<'_>,
        tile: &TileRef,
        lx: u32,
        ly: u32,
    ) -> RayState {
        let n = self.coarse.max(1);
        let (cx, cy) = (tile.x0 + lx, tile.y0 + ly);
        let pixel = cy * n + cx;
        let at = if self.coarse_random {
            coarse_jitter(self.settings.seed, pixel)
        } else {
            glam::Vec2::splat(0.5)
        };
        let film = glam::Vec2::new((cx as f32 + at.x) / n as f32, (cy as f32 + at.y) / n as f32);
        bare.camera_ray_through(film, pixel, COARSE_SAMPLE)
    }
}

/// Where a run of a tile's camera rays is: ray `i` is sample `i % spp` of the tile's pixel
/// `i / spp`, row-major. Found by division for the first ray, then stepped, with no
/// division per ray (a 64-bit division costs as much as making the camera ray).
struct TileCursor {
    /// The pixel's column and row within the tile.
    x: u32,
    y: u32,
    /// The sample within the tile's pass.
    s: u32,
    spp: u32,
    width: u32,
}

impl TileCursor {
    fn new(start: u64, spp: u64, width: u32) -> TileCursor {
        let p = start / spp;
        TileCursor {
            x: (p % u64::from(width)) as u32,
            y: (p / u64::from(width)) as u32,
            s: (start % spp) as u32,
            spp: spp as u32,
            width,
        }
    }

    /// Steps to the next ray's sample and pixel.
    fn advance(&mut self) {
        self.s += 1;
        if self.s == self.spp {
            self.s = 0;
            self.x += 1;
            if self.x == self.width {
                self.x = 0;
                self.y += 1;
            }
        }
    }
}
