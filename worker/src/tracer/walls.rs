//! Rays at domain walls: the crossing itself, and the answers of hit maps and ray
//! caches, in place or from the walls' actors (docs/caches.md "Walls").

use dray_cache::{Advice, MapView, StoreView};
use dray_core::domain::Hop;
use dray_core::integrator::RayState;
use dray_core::ray::RayRecord;
use dray_core::wall::{entry_face, wall_index};
use glam::Vec3;

use super::outbox::{Lookup, Outbox};
use super::residency::{Pins, Residency, StepCtx};
use super::trace::{InFlight, Step};
use super::{JobTracer, TraceError};
use crate::tickets::{Lineage, MAX_TICKETS};

/// A ray at a wall answered in place: packed as the wall's actor would see it, and
/// where it goes unless the wall answers it.
struct AtWall<'l> {
    record: RayRecord,
    lineage: &'l Lineage,
    tile: u32,
    /// The domain it enters, and its span there when already known.
    domain: u32,
    hop: Option<Hop>,
}

impl JobTracer {
    /// A ray whose wall's hit map predicts that it misses `domain`: it goes on past the
    /// domain as if it were empty (to the next wall, or out of the scene). Its tickets
    /// are tainted: what it sees now rests on a prediction.
    pub fn skip(
        &self,
        ray: &RayRecord,
        lineage: Lineage,
        domain: u32,
        residency: &dyn Residency,
        out: &mut Outbox,
    ) -> Result<(), TraceError> {
        self.check_pixel(ray.pixel, lineage.coarse)?;
        let pins = Pins::new(residency, self.nonempty.len());
        let ctx = StepCtx::new(self, &pins);
        let state = ray.to_state();
        let tile = self.tile_of(ray.pixel, ray.sample, lineage.coarse);
        let hop = self
            .hop_in(&state, domain)
            .ok_or(TraceError::Misrouted { domain })?;
        let flight = InFlight {
            ray: state,
            credit: ray.credit,
            tile,
            lineage: &lineage,
        };
        self.go_past(&ctx, hop.next, flight, out);
        self.trace_local(&ctx, &mut Step::default(), out)
    }

    /// A ray a hit map predicts to miss the domain it was entering goes on past it, to
    /// `next` (or out of the scene), its probe flag dropped. What it sees from now on
    /// rests on a prediction, so its tickets must not learn from it: they are settled
    /// here, tainted, with the ray's whole credit, and the ray goes on without them.
    ///
    /// Why settle rather than send a taint (zero credit) and let the ray carry them on:
    /// the ray may finish on another worker, whose returns can reach a ticket, and close
    /// it clean, before this worker's taint does (which then finds the ticket closed).
    /// A return that carries credit cannot be overtaken: the ticket cannot close without
    /// it.
    fn go_past(
        &self,
        ctx: &StepCtx<'_>,
        next: Option<u32>,
        flight: InFlight<'_>,
        out: &mut Outbox,
    ) {
        out.settle_tainted(flight.lineage, flight.credit);
        let untied = Lineage {
            tickets: None,
            ..flight.lineage.inherited()
        };
        let flight = InFlight {
            lineage: &untied,
            ..flight
        };
        self.go_on(ctx, &ctx.bare, next, flight, out);
    }

    /// An occlusion ray whose wall's hit map predicts a hit: it is occluded, adding
    /// nothing; its credit goes back (its tickets tainted).
    pub fn answer_occluded(&self, ray: &RayRecord, lineage: &Lineage, out: &mut Outbox) {
        let tile = self.tile_of(ray.pixel, ray.sample, lineage.coarse);
        out.give_back(tile, ray.credit, lineage, true);
    }

    /// A ray answered by a wall's cache with `radiance`, or by its hit map with a
    /// cell's averaged shading (`phm.shade`): its contribution (weight x radiance) and
    /// its credit, both also owed to its tickets, marked as coming from a cache (the
    /// tickets are tainted: what they carry rests on an approximation).
    pub fn answer_hit(&self, ray: &RayRecord, lineage: &Lineage, radiance: Vec3, out: &mut Outbox) {
        let pixels = self.settings.width as u64 * self.settings.height as u64;
        let tile = self.tile_of(ray.pixel, ray.sample, lineage.coarse);
        if lineage.coarse || (ray.pixel as u64) < pixels {
            out.add(ray.pixel, tile, ray.weight * radiance, lineage, true);
        }
        out.give_back(tile, ray.credit, lineage, true);
    }

    /// A ray enters `domain` through one of its walls, from another domain or from
    /// outside the scene: the one place where a ray crossing a wall is seen. With ray
    /// caches on for its kind, it goes to the wall's cache actor first (the wall is the
    /// face of `domain` it enters by); otherwise straight on (with `hop`, its span in
    /// `domain`, when already known).
    pub(super) fn cross(
        &self,
        ctx: &StepCtx<'_>,
        domain: u32,
        hop: Option<Hop>,
        flight: InFlight<'_>,
        out: &mut Outbox,
    ) {
        let f = &flight;
        let k = f.ray.kind;
        let (cache, phm) = (
            self.cached_kinds.contains(k),
            self.phm_kinds.contains(k) && !f.lineage.coarse,
        );
        if ctx.pins.walls() && (cache || phm) {
            let face = self
                .bounds
                .get(domain as usize)
                .and_then(|&(lo, hi)| entry_face(lo, hi, f.ray.origin, f.ray.dir));
            if let (Some(face), Ok(r)) = (face, RayRecord::from_state(&f.ray, f.credit)) {
                let InFlight {
                    tile, lineage: lin, ..
                } = flight;
                let wall = wall_index(domain, face);
                // In place when the ray opens no ticket (nothing for the actor to
                // record), its map does not shade its kind (the radiance sums, and the
                // tickets that teach them, are the actor's) and every view it needs is
                // in this process.
                let answer = cache && !lin.coarse;
                let ticket = cache && self.opens_ticket(lin);
                let map = if phm { ctx.pins.map(wall) } else { None };
                let store = if answer { ctx.pins.cache(wall) } else { None };
                let shades = map.is_some_and(|m| m.shades(k));
                if !ticket && !shades && map.is_some() == phm && store.is_some() == answer {
                    let at = AtWall {
                        record: r,
                        lineage: lin,
                        tile,
                        domain,
                        hop,
                    };
                    self.at_wall_in_place(ctx, map, store, at, out);
                    return;
                }
                out.lookups.push(Lookup {
                    wall,
                    domain,
                    ray: r,
                    lineage: lin.clone(),
                    cache,
                    phm,
                });
                return;
            }
        }
        self.forward(ctx, domain, hop, flight, out);
    }

    /// Whether a ray of `lin` crossing a cached wall opens a ticket there: the job
    /// fills its caches (or the ray is of the coarse pass), and the ray carries fewer
    /// than [`MAX_TICKETS`].
    pub fn opens_ticket(&self, lin: &Lineage) -> bool {
        lin.ticket_count() < MAX_TICKETS && self.tickets_for(lin)
    }

    /// A ray entering `domain` is answered at its wall in place, as the wall's actor
    /// would answer it (sender placement; docs/caches.md "An actor is not a network
    /// hop"): the hit map first (a predicted miss skips the domain, a predicted hit
    /// occludes an occlusion ray), then the ray cache (a hit ends the ray with the
    /// stored radiance); otherwise the ray goes on into the domain, as a probe when the
    /// map asks for one. Only for rays that open no ticket: the views read, never write.
    fn at_wall_in_place(
        &self,
        ctx: &StepCtx<'_>,
        map: Option<&MapView>,
        store: Option<&StoreView>,
        at: AtWall<'_>,
        out: &mut Outbox,
    ) {
        let AtWall {
            record: r,
            lineage: lin,
            tile,
            domain,
            hop,
        } = at;
        let elsewhere = || u64::from(ctx.pins.get(domain).is_none());
        let advice = map.map(|m| m.consult(&r));
        match advice {
            Some(Advice::Skip) => {
                let state = r.to_state();
                if let Some(past) = self.hop_in(&state, domain) {
                    out.phm_not_sent += elsewhere();
                    let flight = InFlight {
                        ray: state,
                        credit: r.credit,
                        tile,
                        lineage: lin,
                    };
                    self.go_past(ctx, past.next, flight, out);
                    return;
                }
                // The ray does not cross the domain after all (a routing mismatch that
                // the message path reports as an error): trace it exactly.
            }
            Some(Advice::Occlude) if r.kind.is_occlusion() => {
                out.phm_not_sent += elsewhere();
                self.answer_occluded(&r, lin, out);
                return;
            }
            _ => {}
        }
        if let Some(rgb) = store.and_then(|s| s.answer(&r)) {
            out.cache_not_sent += elsewhere();
            self.answer_hit(&r, lin, Vec3::from_array(rgb), out);
            return;
        }
        let probe = advice == Some(Advice::Probe);
        if probe && let Some(m) = map {
            m.probed();
        }
        let lin = Lineage {
            probe,
            ..lin.clone()
        };
        let flight = InFlight {
            ray: r.to_state(),
            credit: r.credit,
            tile,
            lineage: &lin,
        };
        self.forward(ctx, domain, hop, flight, out);
    }

    /// Note a probe's outcome in `domain` for the map of the wall it entered by.
    pub(super) fn report_probe(&self, domain: u32, ray: &RayState, hit: bool, out: &mut Outbox) {
        let Some(&(lo, hi)) = self.bounds.get(domain as usize) else {
            return;
        };
        let Some(face) = entry_face(lo, hi, ray.origin, ray.dir) else {
            return;
        };
        if let Some(cell) = self.phm_bins.cell(lo, hi, face, ray.origin, ray.dir) {
            out.outcomes.push((wall_index(domain, face), cell, hit));
        }
    }
}
