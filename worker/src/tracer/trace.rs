//! Tracing rays in the domains traced here: a ray's span in its domain, its hit shaded,
//! and each ray it makes routed on.

use dray_core::domain::{Hop, Span};
use dray_core::integrator::{Integrator, RayKind, RayState, Sink};
use dray_core::ray::RayRecord;
use dray_core::trace::SpanTrace;
use dray_proto::v1::RayTicket;
use glam::Vec3;

use super::outbox::Outbox;
use super::residency::{Pins, Residency, StepCtx};
use super::{JobTracer, TraceError};
use crate::credit;
use crate::domain_store::LoadedDomain;
use crate::tickets::{Lineage, with_lineage};

/// A ray bound for a domain traced in this step. It stays unpacked (it is never
/// sent), and a ray made in this step carries the hop found when it was routed, so its
/// domain walk is not done twice.
#[derive(Debug)]
pub(super) struct LocalRay {
    domain: u32,
    ray: RayState,
    credit: u64,
    hop: Option<Hop>,
    /// The tile its credit goes back to: its camera ray's (checked when the ray came in
    /// or its tile was dealt).
    tile: u32,
    lineage: Lineage,
}

/// The sink of a hit's shading: contributions go straight to the outbox (and the ray's
/// tickets), the rays it makes to the step's buffer, to be given credit and routed.
struct HitSink<'a> {
    out: &'a mut Outbox,
    lineage: &'a Lineage,
    children: &'a mut Vec<RayState>,
}

impl Sink for HitSink<'_> {
    fn contribute(&mut self, pixel: u32, value: Vec3) {
        self.out.add(pixel, value, self.lineage, false);
    }
    fn spawn(&mut self, ray: RayState) {
        self.children.push(ray);
    }
}

/// The sink of a ray's last step (a miss, an unblocked occlusion ray): contributions go
/// straight to the outbox (and the ray's tickets), with no buffer to allocate. Those
/// steps make no rays.
struct ContributionsOnly<'a> {
    out: &'a mut Outbox,
    lineage: &'a Lineage,
}

impl Sink for ContributionsOnly<'_> {
    fn contribute(&mut self, pixel: u32, value: Vec3) {
        self.out.add(pixel, value, self.lineage, false);
    }
    fn spawn(&mut self, _ray: RayState) {
        debug_assert!(false, "a miss or an occlusion result made a ray");
    }
}

/// Scratch space reused across the rays of one step.
#[derive(Default)]
pub(super) struct Step {
    children: Vec<RayState>,
    /// Rays of one tree waiting in [`JobTracer::trace_tree`], with their credit.
    tree: Vec<(RayState, u64)>,
    kinds: Vec<RayKind>,
    shares: Vec<u64>,
}

impl JobTracer {
    /// Send a ray that was just made to the first domain on its path, or finish it at
    /// once when it meets no domain with triangles. A ray whose first domain starts
    /// ahead of its origin enters it through a wall.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn route_new(
        &self,
        ctx: &StepCtx<'_>,
        finisher: &Integrator<'_>,
        ray: RayState,
        credit: u64,
        lin: Lineage,
        tile: u32,
        out: &mut Outbox,
    ) {
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
            Some(h) if h.span.t0 > 0.0 => {
                self.cross(ctx, ray, credit, lin, h.span.domain, Some(h), tile, out)
            }
            Some(h) => self.forward(ctx, ray, credit, lin, h.span.domain, Some(h), tile, out),
            None => finish_unblocked(finisher, &ray, credit, &lin, tile, out),
        }
    }

    /// Send `ray` on to `domain`: traced in this step when the domain may be traced here
    /// (with `hop`, its span there, when already known), else out of the step.
    #[allow(clippy::too_many_arguments)]
    #[inline]
    pub(super) fn forward(
        &self,
        ctx: &StepCtx<'_>,
        ray: RayState,
        credit: u64,
        lin: Lineage,
        domain: u32,
        hop: Option<Hop>,
        tile: u32,
        out: &mut Outbox,
    ) {
        // Depth beyond 16 bits (a record's field): no valid job gets here (max_depth
        // <= 1024); end the ray rather than lose its credit.
        if u16::try_from(ray.depth).is_err() {
            out.give_back(tile, credit, &lin, false);
            return;
        }
        if ctx.pins.get(domain).is_some() {
            out.local.push(LocalRay {
                domain,
                ray,
                credit,
                hop,
                tile,
                lineage: lin,
            });
            return;
        }
        match RayRecord::from_state(&ray, credit) {
            Ok(r) => out.rays.entry(domain).or_default().push(r, &lin),
            Err(_) => out.give_back(tile, credit, &lin, false),
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
            let ray = LocalRay {
                domain,
                ray: rec.to_state(),
                credit: rec.credit,
                hop: None,
                tile: self.tile_of(rec.pixel, lin.coarse),
                lineage: lin,
            };
            self.trace_one(&ctx, ray, &mut step, out)?;
        }
        self.trace_local(&ctx, &mut step, out)
    }

    /// Trace `ray` and every ray it leads to in `domain`, the layout's only domain
    /// (`single`), traced here: what [`Self::route_new`], [`Self::forward`] and
    /// [`Self::trace_one`] do for such rays, without the routing. In a layout of one
    /// domain, every span is the ray's whole interval and no ray crosses a wall (so none
    /// takes a ticket or a probe, and the lineage is the camera ray's); the rays are
    /// traced, shaded, counted and given credit exactly as there, so the image, the
    /// counts and the credit are the same. This is the loop of `dray render`'s one
    /// embedded worker, where the routing cost a quarter of the time per ray.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn trace_tree(
        &self,
        (domain, loaded, integrator): (u32, &LoadedDomain, &Integrator<'_>),
        ray: RayState,
        credit: u64,
        lin: &Lineage,
        tile: u32,
        step: &mut Step,
        out: &mut Outbox,
    ) -> Result<(), TraceError> {
        let resident = loaded
            .resident
            .domains
            .first()
            .ok_or(TraceError::NotResident { domain })?;
        step.tree.clear();
        step.tree.push((ray, credit));
        while let Some((ray, credit)) = step.tree.pop() {
            // As in `forward`: a depth a ray record cannot carry ends the ray.
            if u16::try_from(ray.depth).is_err() {
                out.give_back(tile, credit, lin, false);
                continue;
            }
            let geometry = SpanTrace {
                accel: &resident.accel,
                span: Span {
                    domain,
                    t0: 0.0,
                    t1: ray.tmax,
                },
            };
            if ray.kind.is_occlusion() {
                if integrator.occluded(&geometry, &ray) {
                    out.give_back(tile, credit, lin, false);
                } else {
                    finish_unblocked(integrator, &ray, credit, lin, tile, out);
                }
                continue;
            }
            let Some(hit) = integrator.intersect(&geometry, &ray) else {
                finish_unblocked(integrator, &ray, credit, lin, tile, out);
                continue;
            };
            let back = self.shade(integrator, &ray, &hit, credit, lin, step, out)?;
            out.give_back(tile, back, lin, false);
            for (child, &share) in step.children.drain(..).zip(&step.shares) {
                out.traced[child.kind as usize] += 1;
                step.tree.push((child, share));
            }
        }
        Ok(())
    }

    /// Shade `hit`: its contributions go to the outbox, the rays it makes to
    /// `step.children` with their credit in `step.shares`. Returns the credit the ray
    /// hands back itself.
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn shade(
        &self,
        integrator: &Integrator<'_>,
        ray: &RayState,
        hit: &dray_core::bvh::Hit,
        credit: u64,
        lin: &Lineage,
        step: &mut Step,
        out: &mut Outbox,
    ) -> Result<u64, TraceError> {
        step.children.clear();
        integrator.shade_hit(
            ray,
            hit,
            &mut HitSink {
                out,
                lineage: lin,
                children: &mut step.children,
            },
        );
        step.kinds.clear();
        step.kinds.extend(step.children.iter().map(|c| c.kind));
        Ok(credit::split_into(credit, &step.kinds, &mut step.shares)?)
    }

    /// Trace the rays the step sent to domains traced here, and theirs, until none is
    /// left.
    pub(super) fn trace_local(
        &self,
        ctx: &StepCtx<'_>,
        step: &mut Step,
        out: &mut Outbox,
    ) -> Result<(), TraceError> {
        while let Some(ray) = out.local.pop() {
            self.trace_one(ctx, ray, step, out)?;
        }
        Ok(())
    }

    /// Trace one ray in `domain` (traced here; `hop` is its span there if known) and
    /// hand on what it makes; its lineage `lin` is inherited by its children.
    fn trace_one(
        &self,
        ctx: &StepCtx<'_>,
        local: LocalRay,
        step: &mut Step,
        out: &mut Outbox,
    ) -> Result<(), TraceError> {
        let LocalRay {
            domain,
            ray,
            credit,
            hop,
            tile,
            lineage: lin,
        } = local;
        // A probe's outcome is reported for this domain only; its children and its way
        // on are ordinary rays.
        let probe = lin.probe;
        let lin = if probe { lin.inherited() } else { lin };
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
                .tree
                .hop(
                    ray.origin,
                    ray.dir,
                    0.0,
                    ray.tmax,
                    self.pad,
                    domain,
                    self.wanted(),
                )
                .ok_or(TraceError::Misrouted { domain })?,
        };
        let geometry = SpanTrace {
            accel: &resident.accel,
            span: hop.span,
        };
        if ray.kind.is_occlusion() {
            let occluded = integrator.occluded(&geometry, &ray);
            if probe {
                self.report_probe(domain, &ray, occluded, out);
            }
            if occluded {
                out.give_back(tile, credit, &lin, false);
            } else if let Some(next) = hop.next {
                self.cross(ctx, ray, credit, lin, next, None, tile, out);
            } else {
                finish_unblocked(integrator, &ray, credit, &lin, tile, out);
            }
            return Ok(());
        }
        let found = integrator.intersect(&geometry, &ray);
        if probe {
            self.report_probe(domain, &ray, found.is_some(), out);
        }
        let Some(hit) = found else {
            match hop.next {
                Some(next) => self.cross(ctx, ray, credit, lin, next, None, tile, out),
                None => finish_unblocked(integrator, &ray, credit, &lin, tile, out),
            }
            return Ok(());
        };
        let back = self.shade(integrator, &ray, &hit, credit, &lin, step, out)?;
        out.give_back(tile, back, &lin, false);
        for (child, &share) in step.children.drain(..).zip(&step.shares) {
            out.traced[child.kind as usize] += 1;
            self.route_new(ctx, integrator, child, share, lin.clone(), tile, out);
        }
        Ok(())
    }
}

/// A ray that left the scene without being blocked: occlusion rays add what they carry,
/// others see the environment.
pub(super) fn finish_unblocked(
    integrator: &Integrator<'_>,
    ray: &RayState,
    credit: u64,
    lineage: &Lineage,
    tile: u32,
    out: &mut Outbox,
) {
    let mut sink = ContributionsOnly { out, lineage };
    if ray.kind.is_occlusion() {
        integrator.shadow_result(ray, false, &mut sink);
    } else {
        integrator.shade_miss(ray, &mut sink);
    }
    out.give_back(tile, credit, lineage, false);
}
