//! Tracing one job's rays in the domains this worker owns.
//!
//! [`JobTracer`] is the worker's compute step, with no I/O: it takes a batch of rays
//! queued for one owned domain (or a range of a tile's camera rays) and puts into an
//! [`Outbox`] everything that comes out: pixel sums in fixed point, credit handed back
//! per tile, and rays bound for other domains. The gRPC side moves batches and outboxes
//! around; this file decides what happens to each ray.
//!
//! Each ray is traced against the domain's BVH clipped to the ray's span inside the
//! domain ([`SpanTrace`]); the span is found by walking the domain layout from the ray's
//! own origin ([`DomainTree::hop`]), so it is the very span the embedded renderer's
//! [`dray_core::trace::DomainSet`] uses, and the image is the same bit for bit. Empty
//! domains are skipped: they can neither hit nor block a ray.
//!
//! A ray bound for another domain that is resident here (and that this worker may trace:
//! see [`Residency`]) is traced in the same step, not queued: only rays for other
//! domains leave the step. The results are the same bits either way (sums are exact in
//! any order and credit is split when a ray is made), and a one-worker render pays no
//! queue round trip per ray.
//!
//! Each domain is traced and shaded over its own [`LoadedDomain`]: the domain's
//! triangles and every emitter, in scene order with scene-wide ids, which shades exactly
//! as the whole scene does (`Integrator::partial`). A step looks each domain up once and
//! holds it until the step ends, so an eviction meanwhile frees it only afterwards.

use std::collections::HashMap;
use std::sync::Arc;

use crate::domain_store::LoadedDomain;

/// A deterministic fast hash for domain keys.
type FastState = foldhash::fast::FixedState;

use dray_core::camera::Camera;
use dray_core::domain::{DomainTree, Hop};
use dray_core::film::to_fixed;
use dray_core::integrator::{Integrator, RayKind, RayState, RenderSettings, Sink};
use dray_core::light_sampler::LightSampler;
use dray_core::ray::RayRecord;
use dray_core::scene::Scene;
use dray_core::trace::SpanTrace;
use glam::Vec3;

use crate::credit::{self, CreditError};

/// Why a batch could not be traced. Each is a reason to fail the job: it means a routing
/// bug, a corrupt ray or an exhausted credit, never a transient condition.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TraceError {
    #[error("received rays for domain {domain}, which this worker does not hold")]
    NotResident { domain: u32 },
    #[error("a ray sent to domain {domain} does not pass through it")]
    Misrouted { domain: u32 },
    #[error("ray for pixel {pixel} is outside the {width}x{height} image")]
    BadPixel { pixel: u32, width: u32, height: u32 },
    #[error(transparent)]
    Credit(#[from] CreditError),
    #[error(
        "tile {tile} ({w}x{h} px, {spp} spp) has credit {credit}, too little for its camera rays"
    )]
    TileCredit {
        tile: u32,
        w: u32,
        h: u32,
        spp: u32,
        credit: u64,
    },
}

/// A rectangle of the image whose camera rays this worker generates.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileRef {
    pub index: u32,
    pub x0: u32,
    pub y0: u32,
    pub width: u32,
    pub height: u32,
    pub credit: u64,
}

impl TileRef {
    /// Camera rays in the tile: pixels times samples.
    pub fn camera_rays(&self, spp: u32) -> u64 {
        self.width as u64 * self.height as u64 * spp as u64
    }
}

/// Everything that comes out of tracing, to be reported or sent on.
#[derive(Debug, Default)]
pub struct Outbox {
    /// Contributions in fixed point, by pixel; a pixel may repeat (the coordinator's sums
    /// are exact in any grouping; the worker merges them per report, see `pixel_sums`).
    pub sums: Vec<(u32, [i64; 3])>,
    /// Credit handed back by rays that terminated, by tile; a tile may repeat, but
    /// consecutive returns to one tile share an entry.
    pub credits: Vec<(u32, u64)>,
    /// Rays to trace next on other workers, by the domain they enter next.
    pub rays: HashMap<u32, Vec<RayRecord>, FastState>,
    /// Rays bound for a domain resident here, traced before the step ends (depth first,
    /// so the stack stays as small as one camera ray's descendants).
    /// A ray made in this step carries the hop found when it was routed, so its
    /// domain walk is not done twice.
    local: Vec<(u32, RayRecord, Option<Hop>)>,
    /// Rays made here (camera rays and children), by kind: each ray is counted once,
    /// where it is made, so the totals equal the single-process renderer's.
    pub traced: [u64; RayKind::COUNT],
    /// Non-finite contributions dropped.
    pub nonfinite: u64,
}

impl Outbox {
    /// Whether nothing is waiting to be reported or sent.
    pub fn is_empty(&self) -> bool {
        self.sums.is_empty()
            && self.credits.is_empty()
            && self.rays.values().all(Vec::is_empty)
            && self.traced.iter().all(|&n| n == 0)
            && self.nonfinite == 0
    }

    /// Rays waiting to be sent.
    pub fn ray_count(&self) -> usize {
        self.rays.values().map(Vec::len).sum()
    }

    fn add(&mut self, pixel: u32, value: Vec3) {
        match to_fixed(value) {
            Some(f) => self.sums.push((pixel, f)),
            None => self.nonfinite += 1,
        }
    }

    fn give_back(&mut self, tile: u32, credit: u64) {
        if credit == 0 {
            return;
        }
        match self.credits.last_mut() {
            Some((t, c)) if *t == tile => *c += credit,
            _ => self.credits.push((tile, credit)),
        }
    }
}

/// Collects what one shading step produces.
#[derive(Default)]
struct StepSink {
    contributions: Vec<(u32, Vec3)>,
    children: Vec<RayState>,
}

impl Sink for StepSink {
    fn contribute(&mut self, pixel: u32, value: Vec3) {
        self.contributions.push((pixel, value));
    }
    fn spawn(&mut self, ray: RayState) {
        self.children.push(ray);
    }
}

/// The sink of a ray's last step (a miss, an unblocked occlusion ray): contributions go
/// straight to the outbox, with no buffer to allocate. Those steps make no rays.
struct ContributionsOnly<'a>(&'a mut Outbox);

impl Sink for ContributionsOnly<'_> {
    fn contribute(&mut self, pixel: u32, value: Vec3) {
        self.0.add(pixel, value);
    }
    fn spawn(&mut self, _ray: RayState) {
        debug_assert!(false, "a miss or an occlusion result made a ray");
    }
}

/// Which domains a step may trace here: resident, and this worker's to trace under the
/// job's current routing table. Asked once per domain per step.
pub trait Residency {
    /// Domain `d`, if this step may trace it here.
    fn domain(&self, d: u32) -> Option<Arc<LoadedDomain>>;
}

/// A fixed set of domains (tests, benchmarks): every one is traced where it is.
impl Residency for HashMap<u32, Arc<LoadedDomain>> {
    fn domain(&self, d: u32) -> Option<Arc<LoadedDomain>> {
        self.get(&d).cloned()
    }
}

/// The domains one step has looked up, held until the step ends.
struct Pins<'r> {
    residency: &'r dyn Residency,
    slots: Vec<Option<Option<Arc<LoadedDomain>>>>,
}

impl<'r> Pins<'r> {
    fn new(residency: &'r dyn Residency, domains: usize) -> Self {
        Pins {
            residency,
            slots: vec![None; domains],
        }
    }

    fn get(&mut self, d: u32) -> Option<&Arc<LoadedDomain>> {
        let slot = self.slots.get_mut(d as usize)?;
        if slot.is_none() {
            *slot = Some(self.residency.domain(d));
        }
        slot.as_ref().and_then(|s| s.as_ref())
    }
}

/// Scratch space reused across the rays of one step.
#[derive(Default)]
struct Step {
    sink: StepSink,
    kinds: Vec<RayKind>,
}

/// One job on one worker: the job's settings and layout. The domains come per step,
/// through a [`Residency`].
pub struct JobTracer {
    /// The job's camera, its name dropped so that the per-domain integrators copy it
    /// without allocating.
    camera: Camera,
    settings: RenderSettings,
    tree: DomainTree,
    pad: f32,
    /// Per domain of the layout, whether it holds any triangle.
    nonempty: Vec<bool>,
    tile_size: u32,
    tiles_x: u32,
    /// A scene with no triangles and its (empty) light table: the integrator of steps
    /// that need no domain (camera rays, rays leaving the scene).
    bare: Scene,
    bare_lights: Arc<LightSampler>,
}

impl JobTracer {
    /// `domain_triangles` has one entry per domain of the layout; `tile_size` is the
    /// edge of the job's row-major tiles.
    pub fn new(
        settings: RenderSettings,
        mut camera: Camera,
        tree: DomainTree,
        pad: f32,
        domain_triangles: &[u64],
        tile_size: u32,
    ) -> JobTracer {
        let tile_size = tile_size.max(1);
        camera.name = String::new();
        let bare = Scene::default();
        let bare_lights = Arc::new(LightSampler::with_bounds(
            &bare,
            false,
            (Vec3::ZERO, Vec3::ONE),
        ));
        JobTracer {
            tiles_x: settings.width.div_ceil(tile_size),
            camera,
            settings,
            tree,
            pad,
            nonempty: domain_triangles.iter().map(|&n| n > 0).collect(),
            tile_size,
            bare,
            bare_lights,
        }
    }

    pub fn settings(&self) -> &RenderSettings {
        &self.settings
    }

    /// Domains in the job's layout.
    pub fn domain_count(&self) -> u32 {
        self.nonempty.len() as u32
    }

    /// Whether domain `d` holds any triangle (rays never enter empty domains).
    pub fn is_nonempty(&self, d: u32) -> bool {
        self.nonempty.get(d as usize).copied().unwrap_or(false)
    }

    /// The integrator over one domain.
    fn integrator<'d>(&self, domain: &'d LoadedDomain) -> Integrator<'d> {
        Integrator::partial(
            &domain.resident.scene,
            self.camera.clone(),
            self.settings.clone(),
            domain.lights.clone(),
            &domain.resident.global_ids,
        )
    }

    /// The integrator of steps that touch no triangle.
    fn bare(&self) -> Integrator<'_> {
        Integrator::partial(
            &self.bare,
            self.camera.clone(),
            self.settings.clone(),
            self.bare_lights.clone(),
            &[],
        )
    }

    /// The tile holding `pixel`.
    pub fn tile_of(&self, pixel: u32) -> u32 {
        let w = self.settings.width.max(1);
        let (x, y) = (pixel % w, pixel / w);
        (y / self.tile_size) * self.tiles_x + x / self.tile_size
    }

    fn wanted(&self) -> impl Fn(u32) -> bool + '_ {
        |d| self.nonempty.get(d as usize).copied().unwrap_or(false)
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
        let spp = self.settings.spp.max(1) as u64;
        let total = tile.camera_rays(spp as u32);
        if credit::camera_share(tile.credit, total, 0).is_none() {
            return Err(TraceError::TileCredit {
                tile: tile.index,
                w: tile.width,
                h: tile.height,
                spp: spp as u32,
                credit: tile.credit,
            });
        }
        let mut pins = Pins::new(residency, self.nonempty.len());
        let bare = self.bare();
        let end = start.saturating_add(count).min(total);
        for i in start..end {
            let (p, sample) = (i / spp, (i % spp) as u32);
            let (lx, ly) = (
                (p % tile.width as u64) as u32,
                (p / tile.width as u64) as u32,
            );
            let pixel = (tile.y0 + ly) * self.settings.width + tile.x0 + lx;
            let share = credit::camera_share(tile.credit, total, i).unwrap_or(0);
            let ray = bare.camera_ray(pixel, sample);
            out.traced[RayKind::Camera as usize] += 1;
            self.route_new(&bare, &mut pins, ray, share, tile.index, out);
        }
        self.trace_local(&mut pins, &mut Step::default(), out)
    }

    /// Send a ray that was just made to the first domain on its path, or finish it at
    /// once when it meets no domain with triangles.
    fn route_new(
        &self,
        bare: &Integrator<'_>,
        pins: &mut Pins<'_>,
        ray: RayState,
        credit: u64,
        tile: u32,
        out: &mut Outbox,
    ) {
        let first =
            self.tree
                .first_hop(ray.origin, ray.dir, 0.0, ray.tmax, self.pad, self.wanted());
        match first {
            Some(h) => self.forward(pins, ray, credit, h.span.domain, Some(h), tile, out),
            None => finish_unblocked(bare, &ray, credit, tile, out),
        }
    }

    /// Send `ray` on to `domain`: traced in this step when the domain may be traced here
    /// (with `hop`, its span there, when already known), else out of the step.
    #[allow(clippy::too_many_arguments)]
    fn forward(
        &self,
        pins: &mut Pins<'_>,
        ray: RayState,
        credit: u64,
        domain: u32,
        hop: Option<Hop>,
        tile: u32,
        out: &mut Outbox,
    ) {
        match RayRecord::from_state(&ray, credit) {
            Ok(r) if pins.get(domain).is_some() => out.local.push((domain, r, hop)),
            Ok(r) => out.rays.entry(domain).or_default().push(r),
            // Depth beyond 16 bits: no valid job gets here (max_depth <= 1024); end the
            // ray rather than lose its credit.
            Err(_) => out.give_back(tile, credit),
        }
    }

    /// A ray leaves domain `from` through a wall into domain `next`. This is the one
    /// place where a ray crossing a wall is seen: the wall is the face of `from` at the
    /// ray's exit `hop.span.t1`, the crossing point `origin + dir * t1` (the cache actors
    /// on walls hook in here).
    #[allow(clippy::too_many_arguments)]
    fn leave(
        &self,
        pins: &mut Pins<'_>,
        ray: RayState,
        credit: u64,
        _from: u32,
        _hop: &Hop,
        next: u32,
        tile: u32,
        out: &mut Outbox,
    ) {
        self.forward(pins, ray, credit, next, None, tile, out);
    }

    /// Trace `rays`, all queued for `domain`, which `residency` must give, and every ray
    /// they lead to in domains it gives.
    pub fn trace_batch(
        &self,
        domain: u32,
        rays: &[RayRecord],
        residency: &dyn Residency,
        out: &mut Outbox,
    ) -> Result<(), TraceError> {
        let mut pins = Pins::new(residency, self.nonempty.len());
        if pins.get(domain).is_none() {
            return Err(TraceError::NotResident { domain });
        }
        let mut step = Step::default();
        for rec in rays {
            self.trace_one(&mut pins, domain, rec, None, &mut step, out)?;
        }
        self.trace_local(&mut pins, &mut step, out)
    }

    /// Trace the rays the step sent to domains traced here, and theirs, until none is
    /// left.
    fn trace_local(
        &self,
        pins: &mut Pins<'_>,
        step: &mut Step,
        out: &mut Outbox,
    ) -> Result<(), TraceError> {
        while let Some((domain, rec, hop)) = out.local.pop() {
            self.trace_one(pins, domain, &rec, hop, step, out)?;
        }
        Ok(())
    }

    /// Trace one ray in `domain` (traced here; `hop` is its span there if known) and
    /// hand on what it makes.
    fn trace_one(
        &self,
        pins: &mut Pins<'_>,
        domain: u32,
        rec: &RayRecord,
        hop: Option<Hop>,
        step: &mut Step,
        out: &mut Outbox,
    ) -> Result<(), TraceError> {
        let loaded = pins
            .get(domain)
            .cloned()
            .ok_or(TraceError::NotResident { domain })?;
        let resident = loaded
            .resident
            .domains
            .first()
            .ok_or(TraceError::NotResident { domain })?;
        let pixels = self.settings.width as u64 * self.settings.height as u64;
        if rec.pixel as u64 >= pixels {
            return Err(TraceError::BadPixel {
                pixel: rec.pixel,
                width: self.settings.width,
                height: self.settings.height,
            });
        }
        let integrator = self.integrator(&loaded);
        let ray = rec.to_state();
        let tile = self.tile_of(ray.pixel);
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
            if integrator.occluded(&geometry, &ray) {
                out.give_back(tile, rec.credit);
            } else if let Some(next) = hop.next {
                self.leave(pins, ray, rec.credit, domain, &hop, next, tile, out);
            } else {
                finish_unblocked(&integrator, &ray, rec.credit, tile, out);
            }
            return Ok(());
        }
        let Some(hit) = integrator.intersect(&geometry, &ray) else {
            match hop.next {
                Some(next) => self.leave(pins, ray, rec.credit, domain, &hop, next, tile, out),
                None => finish_unblocked(&integrator, &ray, rec.credit, tile, out),
            }
            return Ok(());
        };
        let sink = &mut step.sink;
        sink.contributions.clear();
        sink.children.clear();
        integrator.shade_hit(&ray, &hit, sink);
        for &(p, v) in &sink.contributions {
            out.add(p, v);
        }
        step.kinds.clear();
        step.kinds.extend(sink.children.iter().map(|c| c.kind));
        let (shares, back) = credit::split(rec.credit, &step.kinds)?;
        out.give_back(tile, back);
        for (child, share) in sink.children.drain(..).zip(shares) {
            out.traced[child.kind as usize] += 1;
            self.route_new(&integrator, pins, child, share, tile, out);
        }
        Ok(())
    }
}

/// A ray that left the scene without being blocked: occlusion rays add what they carry,
/// others see the environment.
fn finish_unblocked(
    integrator: &Integrator<'_>,
    ray: &RayState,
    credit: u64,
    tile: u32,
    out: &mut Outbox,
) {
    let mut sink = ContributionsOnly(out);
    if ray.kind.is_occlusion() {
        integrator.shadow_result(ray, false, &mut sink);
    } else {
        integrator.shade_miss(ray, &mut sink);
    }
    out.give_back(tile, credit);
}
