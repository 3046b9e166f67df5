//! What a step hands on: contributions and credit given back, rays for other domains
//! and walls, and the tickets they are owed to.

use std::collections::HashMap;

use dray_core::aov::{AOV_WORDS, FirstHit, add_aov_sums};
use dray_core::credit::Credit;
use dray_core::film::{add_sums, to_fixed_clamped};
use dray_core::integrator::RayKind;
use dray_core::ray::RayRecord;
use glam::Vec3;

use super::pass_tag::sum_key;
use super::trace::Entering;
use crate::tickets::{Lineage, RayBundle, TicketLedger};

/// A deterministic fast hash for domain keys.
type FastState = foldhash::fast::FixedState;

/// Everything that comes out of tracing, to be reported or sent on.
#[derive(Debug, Default)]
pub struct Outbox {
    /// Contributions in fixed point, by sum key (the pixel, and the pass of a job that
    /// traces passes ahead: [`super::pass_tag`]); a key may repeat (the coordinator's
    /// sums are exact in any grouping; the worker merges them per report, see
    /// `pixel_sums`).
    pub sums: Vec<(u64, [i64; 3])>,
    /// AOV sums of camera rays' first hits (`dray_core::aov`), by sum key as `sums`;
    /// empty unless the job writes AOVs that need them.
    pub aovs: Vec<(u64, [i64; AOV_WORDS])>,
    /// Credit handed back by rays that terminated, by tile key (the tile, and the pass of
    /// a job that traces passes ahead); a key may repeat, but consecutive returns to one
    /// key share an entry.
    pub credits: Vec<(u32, Credit)>,
    /// Rays to trace next on other workers, by the domain they enter next, with their
    /// tickets.
    pub rays: HashMap<u32, RayBundle, FastState>,
    /// Rays at walls whose cache actors are asked before the rays go on.
    pub lookups: Vec<Lookup>,
    /// Contributions and credit owed to the tickets of the rays that made them.
    pub tickets: TicketLedger,
    /// Outcomes of hit-map probes traced here: (wall, cell, hit inside the domain).
    pub outcomes: Vec<(u32, u32, bool)>,
    /// Rays bound for a domain resident here, traced before the step ends (depth first,
    /// so the stack stays as small as one camera ray's descendants).
    pub(super) local: Vec<Entering>,
    /// Rays made here (camera rays and children), by kind: each ray is counted once,
    /// where it is made, so the totals equal the single-process renderer's.
    pub traced: [u64; RayKind::COUNT],
    /// Non-finite contributions dropped.
    pub nonfinite: u64,
    /// Contributions with a component clamped to the film's largest
    /// (`dray_core::film::MAX_CONTRIBUTION`).
    pub clamped: u64,
    /// Contributions of indirect light scaled down by `--clamp-indirect`
    /// (`dray_core::clamp`).
    pub clamped_indirect: u64,
    /// Rays a hit map consulted in place skipped or occluded on their way to another
    /// worker's domain: rays not sent.
    pub phm_not_sent: u64,
    /// Rays a ray cache answered in place on their way to another worker's domain.
    pub cache_not_sent: u64,
}

impl Outbox {
    /// Whether nothing is waiting to be reported or sent.
    pub fn is_empty(&self) -> bool {
        self.sums.is_empty()
            && self.aovs.is_empty()
            && self.credits.is_empty()
            && self.rays.values().all(RayBundle::is_empty)
            && self.lookups.is_empty()
            && self.tickets.is_empty()
            && self.outcomes.is_empty()
            && self.traced.iter().all(|&n| n == 0)
            && self.nonfinite == 0
            && self.clamped == 0
            && self.clamped_indirect == 0
    }

    /// Rays waiting to be sent.
    pub fn ray_count(&self) -> usize {
        self.rays.values().map(RayBundle::len).sum()
    }

    /// A contribution to `pixel` by a ray of tile key `tile` (none for a coarse-pass
    /// ray), owed also to the ray's tickets; `cached` when it is a cache's answer.
    #[inline]
    pub(super) fn add(&mut self, pixel: u32, tile: u32, value: Vec3, lin: &Lineage, cached: bool) {
        match to_fixed_clamped(value) {
            Some((f, clamped)) => {
                self.clamped += u64::from(clamped);
                if !lin.coarse {
                    // A pixel's samples are traced one after another, so most
                    // contributions land on the pixel of the one before: add them up
                    // here (saturating sums of non-negative values, exact in any grouping).
                    let key = sum_key(pixel, tile);
                    match self.sums.last_mut() {
                        Some((k, s)) if *k == key => add_sums(s, f),
                        _ => self.sums.push((key, f)),
                    }
                }
                if let Some(t) = &lin.tickets {
                    self.tickets.contribute(t, f, cached);
                }
            }
            None => self.nonfinite += 1,
        }
    }

    /// A camera ray's first hit on `pixel`, of tile key `tile`, for the AOVs (none for a
    /// coarse-pass ray, which adds nothing to the image). A non-finite one is dropped,
    /// as a non-finite contribution is.
    #[inline]
    pub(super) fn add_first_hit(&mut self, pixel: u32, tile: u32, hit: &FirstHit, lin: &Lineage) {
        if lin.coarse {
            return;
        }
        let Some(f) = hit.to_fixed() else {
            return;
        };
        let key = sum_key(pixel, tile);
        match self.aovs.last_mut() {
            Some((k, s)) if *k == key => add_aov_sums(s, &f),
            _ => self.aovs.push((key, f)),
        }
    }

    /// Settle the ray's tickets: hand them `credit` (all the ray still holds), marked
    /// as met by an approximation (their radiance is neither stored nor learned).
    pub(super) fn settle_tainted(&mut self, lin: &Lineage, credit: Credit) {
        if let Some(t) = &lin.tickets {
            self.tickets.credit(t, credit, true);
        }
    }

    /// Credit handed back to `tile`, and to the ray's tickets.
    #[inline]
    pub(super) fn give_back(&mut self, tile: u32, credit: Credit, lin: &Lineage, cached: bool) {
        if let Some(t) = &lin.tickets {
            self.tickets.credit(t, credit, cached);
        }
        if credit.is_zero() {
            return;
        }
        match self.credits.last_mut() {
            Some((t, c)) if *t == tile => *c = c.saturating_add(credit),
            _ => self.credits.push((tile, credit)),
        }
    }
}

/// A ray at a wall, waiting for the wall's cache actor (ray caches on).
#[derive(Clone, Debug)]
pub struct Lookup {
    /// The wall (6 * domain + face).
    pub wall: u32,
    /// The domain the ray enters through it: where it goes unless the cache answers.
    pub domain: u32,
    pub ray: RayRecord,
    /// Its tickets (and coarse flag).
    pub lineage: Lineage,
    /// Ask the wall's ray cache (the job caches the ray's kind).
    pub cache: bool,
    /// Ask the wall's hit map (the job's maps serve the ray's kind).
    pub phm: bool,
}
