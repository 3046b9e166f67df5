//! Tracing rays in the domains traced here: a ray's span in its domain, its hit shaded,
//! and each ray it makes routed on.

use dray_core::aov::FirstHit;
use dray_core::bvh::Hit;
use dray_core::credit::Credit;
use dray_core::domain::{Hop, Span};
use dray_core::integrator::{Integrator, RayKind, RayState, Sink};
use dray_core::ray::RayRecord;
use dray_core::trace::SpanTrace;
use dray_proto::v1::RayTicket;
use glam::Vec3;

use super::outbox::Outbox;
use super::residency::{Pins, Residency, StepCtx};
use super::{JobTracer, TraceError};
use crate::domain_store::LoadedDomain;
use crate::tickets::{Lineage, with_lineage};

/// A ray in flight with what travels with it: its credit, the tile that credit goes
/// back to and its lineage (tickets, coarse and probe flags).
///
/// The lineage is borrowed and cloned only where the ray is kept (a local ray, a
/// lookup): a lineage is 88 bytes, and a bundle holding its own (160 bytes) cost a
/// `memcpy` call at each move along the way, 3% of the instructions of a step.
pub(super) struct InFlight<'l> {
    pub(super) ray: RayState,
    pub(super) credit: Credit,
    /// Its camera ray's tile (checked when the ray came in or its tile was dealt).
    pub(super) tile: u32,
    pub(super) lineage: &'l Lineage,
}

/// A ray entering `domain` to be traced in this step, waiting in [`Outbox`]'s local
/// stack. It stays unpacked (it is never sent), and a ray made in this step carries the
/// hop found when it was routed, so its domain walk is not done twice.
#[derive(Debug)]
pub(super) struct Entering {
    pub(super) domain: u32,
    /// Its span in `domain` and the next domain on its path, when already known.
    pub(super) hop: Option<Hop>,
    pub(super) ray: RayState,
    pub(super) credit: Credit,
    pub(super) tile: u32,
    pub(super) lineage: Lineage,
}

/// The sink of a hit's shading: contributions go straight to the outbox (and the ray's
/// tickets), the rays it makes onto the step's stack, to be given credit and routed.
struct HitSink<'a> {
    out: &'a mut Outbox,
    lineage: &'a Lineage,
    /// The shaded ray's tile key (its pass, for a job tracing passes ahead).
    tile: u32,
    children: &'a mut Vec<RayState>,
    /// The kinds of the rays made, noted as they are made: the credit split reads them,
    /// with no second pass over the rays.
    kinds: &'a mut Vec<RayKind>,
}

impl Sink for HitSink<'_> {
    fn contribute(&mut self, pixel: u32, value: Vec3) {
        self.out.add(pixel, self.tile, value, self.lineage, false);
    }
    fn spawn(&mut self, ray: RayState) {
        self.kinds.push(ray.kind);
        self.children.push(ray);
    }
    fn clamped_indirect(&mut self) {
        self.out.clamped_indirect += 1;
    }
    fn first_hit(&mut self, pixel: u32, hit: &FirstHit) {
        self.out.add_first_hit(pixel, self.tile, hit, self.lineage);
    }
}

/// The sink of a ray's last step (a miss, an unblocked occlusion ray): contributions go
/// straight to the outbox (and the ray's tickets), with no buffer to allocate. Those
/// steps make no rays.
struct ContributionsOnly<'a> {
    out: &'a mut Outbox,
    lineage: &'a Lineage,
    /// The ray's tile key.
    tile: u32,
}

impl Sink for ContributionsOnly<'_> {
    fn contribute(&mut self, pixel: u32, value: Vec3) {
        self.out.add(pixel, self.tile, value, self.lineage, false);
    }
    fn spawn(&mut self, _ray: RayState) {
        debug_assert!(false, "a miss or an occlusion result made a ray");
    }
    fn clamped_indirect(&mut self) {
        self.out.clamped_indirect += 1;
    }
}

/// Scratch space reused across the rays of one step.
#[derive(Default)]
pub(super) struct Step {
    /// The rays a hit made, on top of the rays still waiting: in the routed loop
    /// ([`JobTracer::trace_one`]) it holds one hit's rays at a time; in the one-domain
    /// loop ([`JobTracer::trace_tree`]) it is the stack of the tree's waiting rays, the
    /// hit's rays pushed onto it where the shading makes them (each ray is copied into
    /// the stack once and out of it once, with no second buffer in between).
    children: Vec<RayState>,
    /// The credit of each ray of `children` waiting in [`JobTracer::trace_tree`] (the
    /// tree's tile and lineage are its camera ray's).
    credits: Vec<Credit>,
    /// The kinds of the last hit's rays, in spawn order.
    kinds: Vec<RayKind>,
    /// The last hit's rays' shares of its credit, in spawn order.
    shares: Vec<Credit>,
}

/// What tracing a ray through its span in a domain came to.
pub(super) enum InSpan {
    /// An occlusion ray was blocked: it ends, handing back all of its credit.
    Blocked,
    /// A hit, shaded: its contributions are in the outbox, the rays it made on top of
    /// `Step::children` (their kinds in `Step::kinds`) with their credit in
    /// `Step::shares`, and the ray hands back what the split left.
    Shaded { back: Credit },
    /// Nothing in the span stopped it: it goes on past the span.
    Through,
}

/// Trace `flight`'s ray through `geometry`, its span in one domain, and shade what it
/// hits. The one tracing step of both loops, the routed one
/// ([`JobTracer::trace_one`]) and the one-domain one ([`JobTracer::trace_tree`]), so
/// that they trace, shade and split credit alike.
#[inline(always)]
fn in_span(
    integrator: &Integrator<'_>,
    geometry: &SpanTrace<'_>,
    flight: &InFlight<'_>,
    step: &mut Step,
    out: &mut Outbox,
) -> Result<InSpan, TraceError> {
    let ray = &flight.ray;
    if ray.kind.is_occlusion() {
        return Ok(if integrator.occluded(geometry, ray) {
            InSpan::Blocked
        } else {
            InSpan::Through
        });
    }
    let Some(hit) = integrator.intersect(geometry, ray) else {
        return Ok(InSpan::Through);
    };
    let back = shade(integrator, &hit, flight, step, out)?;
    Ok(InSpan::Shaded { back })
}

/// Shade `hit`: its contributions go to the outbox, the rays it makes onto
/// `step.children` (pushed after what it holds) with their kinds in `step.kinds` and
/// their credit in `step.shares`. Returns the credit the ray hands back itself.
#[inline]
fn shade(
    integrator: &Integrator<'_>,
    hit: &Hit,
    flight: &InFlight<'_>,
    step: &mut Step,
    out: &mut Outbox,
) -> Result<Credit, TraceError> {
    step.kinds.clear();
    integrator.shade_hit(
        &flight.ray,
        hit,
        &mut HitSink {
            out,
            lineage: flight.lineage,
            tile: flight.tile,
            children: &mut step.children,
            kinds: &mut step.kinds,
        },
    );
    Ok(flight.credit.split_into(&step.kinds, &mut step.shares)?)
}

impl JobTracer {
    /// Send a ray that was just made to the first domain on its path, or finish it at
    /// once (with `finisher`) when it meets no domain with triangles. A ray whose first
    /// domain starts ahead of its origin enters it through a wall.
    pub(super) fn route_new(
        &self,
        ctx: &StepCtx<'_>,
        finisher: &Integrator<'_>,
        flight: InFlight<'_>,
        out: &mut Outbox,
    ) {
        let ray = &flight.ray;
        let first = match self.single {
            // What the walk finds in a layout of one domain, without the walk.
            Some(domain) => Some(Hop {
                span: Span {
                    domain,
                    t0: 0.0,
                    t1: ray.tmax,
                },
                next: None,
            }),
            None => {
                self.tree
                    .first_hop(ray.origin, ray.dir, 0.0, ray.tmax, self.pad, self.wanted())
            }
        };
        match first {
            Some(h) if h.span.t0 > 0.0 => self.cross(ctx, h.span.domain, Some(h), flight, out),
            Some(h) => self.forward(ctx, h.span.domain, Some(h), flight, out),
            None => finish_unblocked(finisher, &flight, out),
        }
    }

    /// Send a ray on to `domain`: traced in this step when the domain may be traced here
    /// (with `hop`, its span there, when already known), else out of the step.
    #[inline]
    pub(super) fn forward(
        &self,
        ctx: &StepCtx<'_>,
        domain: u32,
        hop: Option<Hop>,
        flight: InFlight<'_>,
        out: &mut Outbox,
    ) {
        let InFlight {
            ray,
            credit,
            tile,
            lineage,
        } = flight;
        // Depth beyond 16 bits (a record's field): no valid job gets here (max_depth
        // <= 1024); end the ray rather than lose its credit.
        if u16::try_from(ray.depth).is_err() {
            out.give_back(tile, credit, lineage, false);
            return;
        }
        if ctx.pins.get(domain).is_some() {
            out.local.push(Entering {
                domain,
                hop,
                ray,
                credit,
                tile,
                lineage: lineage.clone(),
            });
            return;
        }
        match RayRecord::from_state(&ray, credit) {
            Ok(r) => out.rays.entry(domain).or_default().push(r, lineage),
            Err(_) => out.give_back(tile, credit, lineage, false),
        }
    }

    /// A ray that left a domain unblocked goes on: into `next`, the next domain with
    /// triangles on its path, through its wall; or, with none, out of the scene (finished
    /// with `finisher`).
    pub(super) fn go_on(
        &self,
        ctx: &StepCtx<'_>,
        finisher: &Integrator<'_>,
        next: Option<u32>,
        flight: InFlight<'_>,
        out: &mut Outbox,
    ) {
        match next {
            Some(domain) => self.cross(ctx, domain, None, flight, out),
            None => finish_unblocked(finisher, &flight, out),
        }
    }

    /// Trace `rays`, all queued for `domain`, which `residency` must give, and every ray
    /// they lead to in domains it gives.
    /// `tickets` are the rays' cache tickets, by record index in increasing order (the
    /// wire's sparse form; empty when no ray carries one).
    pub fn trace_batch(
        &self,
        domain: u32,
        rays: &[RayRecord],
        tickets: &[RayTicket],
        residency: &dyn Residency,
        out: &mut Outbox,
    ) -> Result<(), TraceError> {
        let pins = Pins::new(residency, self.nonempty.len());
        if pins.get(domain).is_none() {
            return Err(TraceError::NotResident { domain });
        }
        let ctx = StepCtx::new(self, &pins);
        let mut step = Step::default();
        for (rec, lin) in with_lineage(rays, tickets) {
            self.check_pixel(rec.pixel, lin.coarse)?;
            let entering = Entering {
                domain,
                hop: None,
                ray: rec.to_state(),
                credit: rec.credit,
                tile: self.tile_of(rec.pixel, rec.sample, lin.coarse),
                lineage: lin,
            };
            self.trace_one(&ctx, entering, &mut step, out)?;
        }
        self.trace_local(&ctx, &mut step, out)
    }

    /// Trace `root` and every ray it leads to in `domain`, the layout's only domain
    /// (`single`), traced here: what [`Self::route_new`], [`Self::forward`] and
    /// [`Self::trace_one`] do for such rays, without the routing. In a layout of one
    /// domain, every span is the ray's whole interval and no ray crosses a wall (so none
    /// takes a ticket or a probe, and the lineage is the camera ray's); the rays are
    /// traced, shaded, counted and given credit exactly as there (the same
    /// [`in_span`]), so the image, the counts and the credit are the same. This is the
    /// loop of `dray render`'s one embedded worker.
    ///
    /// It is kept apart from the routed loop because the routing costs even here: with
    /// every ray of a one-domain cornell render (96x96, 8 spp, path) sent through
    /// `route_new`, `forward` and `trace_one` instead, `camera_rays` ran 9.7% more
    /// instructions (callgrind: 1,224M against 1,116M) and took 8% longer: the domain
    /// pinned for every ray, and every ray moved through the step's stack with its own
    /// copy of the lineage.
    pub(super) fn trace_tree(
        &self,
        (domain, loaded, integrator): (u32, &LoadedDomain, &Integrator<'_>),
        f: &mut InFlight<'_>,
        step: &mut Step,
        out: &mut Outbox,
    ) -> Result<(), TraceError> {
        let resident = loaded
            .resident
            .domains
            .first()
            .ok_or(TraceError::NotResident { domain })?;
        // One ray of the tree at a time in `f`, the caller's slot, rewritten in place:
        // the tile and lineage are the root's. The root is traced where the caller made
        // it; only its descendants go through the stack `step.children` (a push and a
        // pop per camera ray, or a copy of a ray just made, cost stalls on loads of what
        // was just stored). A hit's rays are shaded straight onto the stack, in spawn
        // order, and popped last first, as they were when they went through a second
        // buffer.
        step.children.clear();
        step.credits.clear();
        let mut first = true;
        loop {
            if !std::mem::take(&mut first) {
                let (Some(ray), Some(credit)) = (step.children.pop(), step.credits.pop()) else {
                    break;
                };
                (f.ray, f.credit) = (ray, credit);
            }
            // As in `forward`: a depth a ray record cannot carry ends the ray.
            if u16::try_from(f.ray.depth).is_err() {
                out.give_back(f.tile, f.credit, f.lineage, false);
                continue;
            }
            let geometry = SpanTrace {
                accel: &resident.accel,
                span: Span {
                    domain,
                    t0: 0.0,
                    t1: f.ray.tmax,
                },
            };
            match in_span(integrator, &geometry, f, step, out)? {
                InSpan::Blocked => out.give_back(f.tile, f.credit, f.lineage, false),
                InSpan::Through => finish_unblocked(integrator, f, out),
                InSpan::Shaded { back } => {
                    out.give_back(f.tile, back, f.lineage, false);
                    // The hit's rays are already on the stack, one share each.
                    for &kind in &step.kinds {
                        out.traced[kind as usize] += 1;
                    }
                    step.credits.extend_from_slice(&step.shares);
                }
            }
        }
        Ok(())
    }

    /// Trace the rays the step sent to domains traced here, and theirs, until none is
    /// left.
    pub(super) fn trace_local(
        &self,
        ctx: &StepCtx<'_>,
        step: &mut Step,
        out: &mut Outbox,
    ) -> Result<(), TraceError> {
        while let Some(entering) = out.local.pop() {
            self.trace_one(ctx, entering, step, out)?;
        }
        Ok(())
    }

    /// Trace one ray entering a domain traced here and hand on what it makes; its
    /// lineage is inherited by its children.
    fn trace_one(
        &self,
        ctx: &StepCtx<'_>,
        entering: Entering,
        step: &mut Step,
        out: &mut Outbox,
    ) -> Result<(), TraceError> {
        let Entering {
            domain,
            hop,
            ray,
            credit,
            tile,
            lineage,
        } = entering;
        // A probe's outcome is reported for this domain only; its children and its way
        // on are ordinary rays.
        let probe = lineage.probe;
        let lineage = if probe { lineage.inherited() } else { lineage };
        let (loaded, integrator) = ctx
            .domain(domain)
            .ok_or(TraceError::NotResident { domain })?;
        let resident = loaded
            .resident
            .domains
            .first()
            .ok_or(TraceError::NotResident { domain })?;
        let hop = match hop {
            Some(h) => h,
            None => self
                .hop_in(&ray, domain)
                .ok_or(TraceError::Misrouted { domain })?,
        };
        let geometry = SpanTrace {
            accel: &resident.accel,
            span: hop.span,
        };
        let f = InFlight {
            ray,
            credit,
            tile,
            lineage: &lineage,
        };
        // This hit's rays alone, when it makes any.
        step.children.clear();
        let outcome = in_span(integrator, &geometry, &f, step, out)?;
        if probe {
            let hit = !matches!(outcome, InSpan::Through);
            self.report_probe(domain, &f.ray, hit, out);
        }
        match outcome {
            InSpan::Blocked => out.give_back(tile, credit, &lineage, false),
            InSpan::Through => self.go_on(ctx, integrator, hop.next, f, out),
            InSpan::Shaded { back } => {
                out.give_back(tile, back, &lineage, false);
                for (child, &share) in step.children.drain(..).zip(&step.shares) {
                    out.traced[child.kind as usize] += 1;
                    let flight = InFlight {
                        ray: child,
                        credit: share,
                        tile,
                        lineage: &lineage,
                    };
                    self.route_new(ctx, integrator, flight, out);
                }
            }
        }
        Ok(())
    }
}

/// A ray that left the scene without being blocked: occlusion rays add what they carry,
/// others see the environment; its credit goes back.
#[inline]
pub(super) fn finish_unblocked(
    integrator: &Integrator<'_>,
    flight: &InFlight<'_>,
    out: &mut Outbox,
) {
    let (ray, lineage) = (&flight.ray, flight.lineage);
    let mut sink = ContributionsOnly {
        out,
        lineage,
        tile: flight.tile,
    };
    if ray.kind.is_occlusion() {
        integrator.shadow_result(ray, false, &mut sink);
    } else {
        integrator.shade_miss(ray, &mut sink);
    }
    out.give_back(flight.tile, flight.credit, lineage, false);
}
