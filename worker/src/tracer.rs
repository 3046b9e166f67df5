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
//! **Walls and tickets** (ray caches on, docs/caches.md "Walls"): a ray entering a domain
//! through a wall, from another domain or from outside the scene, goes to the wall's
//! cache actor first ([`Outbox::lookups`]) when the job caches its kind, even when the
//! domain is resident here; the actor's answer (a hit, or a miss with a ticket) comes
//! back through `cache_link`. A ray carries the tickets of the walls it (or an
//! ancestor) missed, its children inherit them, and everything they hand back is
//! also owed to those tickets ([`Outbox::tickets`]). With caches off no ray has a
//! ticket and no lookup is made: the step is exactly what it was before caches.
//!
//! Each domain is traced and shaded over its own [`LoadedDomain`]: the domain's
//! triangles and every emitter, in scene order with scene-wide ids, which shades exactly
//! as the whole scene does (`Integrator::partial`). A step looks each domain up once and
//! holds it until the step ends, so an eviction meanwhile frees it only afterwards.

use std::cell::OnceCell;
use std::collections::HashMap;
use std::sync::Arc;

use crate::domain_store::LoadedDomain;

/// A deterministic fast hash for domain keys.
type FastState = foldhash::fast::FixedState;

use dray_cache::{Advice, MapView, StoreView};
use dray_core::camera::Camera;
use dray_core::domain::{DomainTree, Hop, Span};
use dray_core::film::to_fixed;
use dray_core::integrator::{Integrator, RayKind, RayState, RenderSettings, Sink};
use dray_core::light_sampler::LightSampler;
use dray_core::ray::RayRecord;
use dray_core::scene::Scene;
use dray_core::trace::SpanTrace;
use dray_core::wall::{PhmBins, entry_face, wall_index};
use dray_proto::v1::RayTicket;
use glam::Vec3;

use crate::credit::{self, CreditError};
use crate::tickets::{Lineage, MAX_TICKETS, RayBundle, TicketLedger, with_lineage};

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
    #[error("tile {tile} at ({x0}, {y0}), {w}x{h} px, is not inside the {width}x{height} image")]
    BadTile {
        tile: u32,
        x0: u32,
        y0: u32,
        w: u32,
        h: u32,
        width: u32,
        height: u32,
    },
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

/// The sample index of coarse-pass rays: their random numbers are keyed apart from every
/// sample of the image (spp is at most 65536).
const COARSE_SAMPLE: u32 = u32::MAX;

/// A rectangle of the image whose camera rays this worker generates.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileRef {
    pub index: u32,
    pub x0: u32,
    pub y0: u32,
    pub width: u32,
    pub height: u32,
    pub credit: u64,
    /// A tile of the ray-cache coarse pass: its pixels are those of the coarse image,
    /// one regular ray each.
    pub coarse: bool,
}

impl TileRef {
    /// Camera rays in the tile: pixels times samples (one per pixel for a coarse tile).
    pub fn camera_rays(&self, spp: u32) -> u64 {
        let spp = if self.coarse { 1 } else { spp.max(1) };
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
    local: Vec<LocalRay>,
    /// Rays made here (camera rays and children), by kind: each ray is counted once,
    /// where it is made, so the totals equal the single-process renderer's.
    pub traced: [u64; RayKind::COUNT],
    /// Non-finite contributions dropped.
    pub nonfinite: u64,
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
            && self.credits.is_empty()
            && self.rays.values().all(RayBundle::is_empty)
            && self.lookups.is_empty()
            && self.tickets.is_empty()
            && self.outcomes.is_empty()
            && self.traced.iter().all(|&n| n == 0)
            && self.nonfinite == 0
    }

    /// Rays waiting to be sent.
    pub fn ray_count(&self) -> usize {
        self.rays.values().map(RayBundle::len).sum()
    }

    /// A contribution to `pixel` (none for a coarse-pass ray), owed also to the ray's
    /// tickets; `cached` when it is a cache's answer.
    #[inline]
    fn add(&mut self, pixel: u32, value: Vec3, lin: &Lineage, cached: bool) {
        match to_fixed(value) {
            Some(f) => {
                if !lin.coarse {
                    // A pixel's samples are traced one after another, so most
                    // contributions land on the pixel of the one before: add them up
                    // here (wrapping sums, exact in any grouping).
                    match self.sums.last_mut() {
                        Some((p, s)) if *p == pixel => {
                            for c in 0..3 {
                                s[c] = s[c].wrapping_add(f[c]);
                            }
                        }
                        _ => self.sums.push((pixel, f)),
                    }
                }
                if let Some(t) = &lin.tickets {
                    self.tickets.contribute(t, f, cached);
                }
            }
            None => self.nonfinite += 1,
        }
    }

    /// Mark the ray's tickets as met by an approximation (their radiance is not stored).
    fn taint(&mut self, lin: &Lineage) {
        if let Some(t) = &lin.tickets {
            self.tickets.credit(t, 0, true);
        }
    }

    /// Credit handed back to `tile`, and to the ray's tickets.
    #[inline]
    fn give_back(&mut self, tile: u32, credit: u64, lin: &Lineage, cached: bool) {
        if let Some(t) = &lin.tickets {
            self.tickets.credit(t, credit, cached);
        }
        if credit == 0 {
            return;
        }
        match self.credits.last_mut() {
            Some((t, c)) if *t == tile => *c += credit,
            _ => self.credits.push((tile, credit)),
        }
    }
}

/// A ray bound for a domain traced in this step. It stays unpacked (it is never
/// sent), and a ray made in this step carries the hop found when it was routed, so its
/// domain walk is not done twice.
#[derive(Debug)]
struct LocalRay {
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

/// A step with no domain here (answers applied off the tracing threads): rays go out,
/// to walls when `walls`.
pub struct NoDomains {
    pub walls: bool,
}

impl Residency for NoDomains {
    fn domain(&self, _d: u32) -> Option<Arc<LoadedDomain>> {
        None
    }

    fn walls(&self) -> bool {
        self.walls
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

/// Which domains a step may trace here: resident, and this worker's to trace under the
/// job's current routing table. Asked once per domain per step.
pub trait Residency {
    /// Domain `d`, if this step may trace it here.
    fn domain(&self, d: u32) -> Option<Arc<LoadedDomain>>;

    /// Whether rays crossing walls go to cache actors (the job has ray caches and the
    /// routing table places their actors).
    fn walls(&self) -> bool {
        false
    }

    /// A view of `wall`'s hit map to consult in place, when the map lives in this
    /// process (sender placement); rays at other walls ask its actor.
    fn map(&self, _wall: u32) -> Option<&MapView> {
        None
    }

    /// A view of `wall`'s ray cache to answer rays in place, when the cache lives in
    /// this process (sender placement).
    fn cache(&self, _wall: u32) -> Option<&StoreView> {
        None
    }
}

/// A fixed set of domains (tests, benchmarks): every one is traced where it is.
impl Residency for HashMap<u32, Arc<LoadedDomain>> {
    fn domain(&self, d: u32) -> Option<Arc<LoadedDomain>> {
        self.get(&d).cloned()
    }
}

/// The domains one step has looked up, held until the step ends. Each slot is filled
/// at most once, so a domain looked up here stays put (and borrowable) for the step.
struct Pins<'r> {
    residency: &'r dyn Residency,
    slots: Vec<OnceCell<Option<Arc<LoadedDomain>>>>,
    /// [`Residency::walls`], asked once.
    walls: bool,
}

impl<'r> Pins<'r> {
    fn new(residency: &'r dyn Residency, domains: usize) -> Self {
        Pins {
            residency,
            slots: (0..domains).map(|_| OnceCell::new()).collect(),
            walls: residency.walls(),
        }
    }

    fn walls(&self) -> bool {
        self.walls
    }

    fn map(&self, wall: u32) -> Option<&MapView> {
        self.residency.map(wall)
    }

    fn cache(&self, wall: u32) -> Option<&StoreView> {
        self.residency.cache(wall)
    }

    fn get(&self, d: u32) -> Option<&Arc<LoadedDomain>> {
        self.slots
            .get(d as usize)?
            .get_or_init(|| self.residency.domain(d))
            .as_ref()
    }
}

/// One step's view of the job: the pinned domains and, made once per domain per step,
/// an integrator over each. Making an integrator copies the camera and settings and
/// takes a reference on the domain's light table; once per ray, that meant two atomic
/// counters (the domain's and the table's) shared by every tracing thread, touched
/// twice per ray.
struct StepCtx<'p> {
    tracer: &'p JobTracer,
    pins: &'p Pins<'p>,
    integrators: Vec<OnceCell<Integrator<'p>>>,
    /// The integrator of steps that touch no triangle (camera rays, rays leaving the
    /// scene).
    bare: Integrator<'p>,
}

impl<'p> StepCtx<'p> {
    fn new(tracer: &'p JobTracer, pins: &'p Pins<'p>) -> Self {
        StepCtx {
            tracer,
            pins,
            integrators: (0..pins.slots.len()).map(|_| OnceCell::new()).collect(),
            bare: tracer.bare(),
        }
    }

    /// Domain `d` if this step may trace it, with its integrator.
    fn domain(&self, d: u32) -> Option<(&'p LoadedDomain, &Integrator<'p>)> {
        let loaded: &'p LoadedDomain = self.pins.get(d)?;
        let integrator = self
            .integrators
            .get(d as usize)?
            .get_or_init(|| self.tracer.integrator(loaded));
        Some((loaded, integrator))
    }
}

/// Scratch space reused across the rays of one step.
#[derive(Default)]
struct Step {
    children: Vec<RayState>,
    /// Rays of one tree waiting in [`JobTracer::trace_tree`], with their credit.
    tree: Vec<(RayState, u64)>,
    kinds: Vec<RayKind>,
    shares: Vec<u64>,
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
    /// The layout's one domain, when it has one and it holds triangles: every ray's
    /// first hop is then its whole interval in that domain, with no walk.
    single: Option<u32>,
    tile_size: u32,
    tiles_x: u32,
    /// A scene with no triangles and its (empty) light table: the integrator of steps
    /// that need no domain (camera rays, rays leaving the scene).
    bare: Scene,
    bare_lights: Arc<LightSampler>,
    /// Per domain, its box: where walls are.
    bounds: Vec<(Vec3, Vec3)>,
    /// Per ray kind, whether the job's ray caches look it up (all false: caches off).
    cached_kinds: [bool; RayKind::COUNT],
    /// Whether rays of the main pass fill the caches (`ray_cache.fill`); if not, only
    /// the coarse pass's rays take tickets.
    fill: bool,
    /// Per ray kind, whether the job's hit maps serve it, and the maps' binning (no
    /// kinds: maps off).
    phm_kinds: [bool; RayKind::COUNT],
    phm_bins: PhmBins,
    /// The coarse pass's image edge N (0: no coarse pass), and the image's tile count
    /// (coarse tiles are numbered after the image's).
    coarse: u32,
    image_tiles: u32,
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
        let single = tree
            .single()
            .filter(|&d| domain_triangles.get(d as usize).is_some_and(|&n| n > 0));
        let bare = Scene::default();
        let bare_lights = Arc::new(LightSampler::with_bounds(
            &bare,
            false,
            (Vec3::ZERO, Vec3::ONE),
        ));
        JobTracer {
            bounds: tree.domain_bounds(),
            cached_kinds: [false; RayKind::COUNT],
            fill: true,
            phm_kinds: [false; RayKind::COUNT],
            phm_bins: PhmBins::new(1, 1),
            coarse: 0,
            image_tiles: settings.width.div_ceil(tile_size) * settings.height.div_ceil(tile_size),
            tiles_x: settings.width.div_ceil(tile_size),
            camera,
            settings,
            tree,
            pad,
            single,
            nonempty: domain_triangles.iter().map(|&n| n > 0).collect(),
            tile_size,
            bare,
            bare_lights,
        }
    }

    /// Look rays of these kinds up in wall caches (the job's `ray_cache.kinds`).
    pub fn with_cached_kinds(mut self, kinds: [bool; RayKind::COUNT]) -> JobTracer {
        self.cached_kinds = kinds;
        self
    }

    /// Whether the main pass's rays fill the caches (`ray_cache.fill`).
    pub fn with_fill(mut self, fill: bool) -> JobTracer {
        self.fill = fill;
        self
    }

    /// Whether a ray of this lineage takes a ticket on a miss: coarse-pass rays always,
    /// others when the main pass fills the caches.
    pub fn tickets_for(&self, lineage: &Lineage) -> bool {
        lineage.coarse || self.fill
    }

    /// Consult hit maps binned by `bins` for rays of these kinds (the job's `phm`).
    pub fn with_phm(mut self, kinds: [bool; RayKind::COUNT], bins: PhmBins) -> JobTracer {
        self.phm_kinds = kinds;
        self.phm_bins = bins;
        self
    }

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
        let tile = self.tile_of(ray.pixel, lineage.coarse);
        out.taint(&lineage);
        let hop = self
            .tree
            .hop(
                state.origin,
                state.dir,
                0.0,
                state.tmax,
                self.pad,
                domain,
                self.wanted(),
            )
            .ok_or(TraceError::Misrouted { domain })?;
        let lin = lineage.inherited();
        match hop.next {
            Some(next) => self.cross(&ctx, state, ray.credit, lin, next, None, tile, out),
            None => finish_unblocked(&ctx.bare, &state, ray.credit, &lin, tile, out),
        }
        self.trace_local(&ctx, &mut Step::default(), out)
    }

    /// An occlusion ray whose wall's hit map predicts a hit: it is occluded, adding
    /// nothing; its credit goes back (its tickets tainted).
    pub fn answer_occluded(&self, ray: &RayRecord, lineage: &Lineage, out: &mut Outbox) {
        let tile = self.tile_of(ray.pixel, lineage.coarse);
        out.give_back(tile, ray.credit, lineage, true);
    }

    /// The job's ray-cache coarse pass covers an `n` x `n` image (0: none).
    pub fn with_coarse(mut self, n: u32) -> JobTracer {
        self.coarse = n;
        self
    }

    pub fn settings(&self) -> &RenderSettings {
        &self.settings
    }

    /// A ray answered by a wall's cache with `radiance`: its contribution (weight x
    /// radiance) and its credit, both also owed to its tickets, marked as coming from
    /// a cache.
    pub fn answer_hit(&self, ray: &RayRecord, lineage: &Lineage, radiance: Vec3, out: &mut Outbox) {
        let pixels = self.settings.width as u64 * self.settings.height as u64;
        let tile = self.tile_of(ray.pixel, lineage.coarse);
        if lineage.coarse || (ray.pixel as u64) < pixels {
            out.add(ray.pixel, ray.weight * radiance, lineage, true);
        }
        out.give_back(tile, ray.credit, lineage, true);
    }

    /// A ray that came from elsewhere (another worker, a cache actor) must be for a
    /// pixel of the image, or of the coarse image for a coarse-pass ray. Rays made here
    /// are for their camera ray's pixel, which its tile's check covered.
    fn check_pixel(&self, pixel: u32, coarse: bool) -> Result<(), TraceError> {
        let limit = if coarse {
            self.coarse as u64 * self.coarse as u64
        } else {
            self.settings.width as u64 * self.settings.height as u64
        };
        if pixel as u64 >= limit {
            return Err(TraceError::BadPixel {
                pixel,
                width: self.settings.width,
                height: self.settings.height,
            });
        }
        Ok(())
    }

    /// The layout's one domain, when it has one and it holds triangles: every camera
    /// ray of the job is traced in it.
    pub fn single_domain(&self) -> Option<u32> {
        self.single
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

    /// Tiles the job has: the image's, then the coarse pass's (none without one).
    pub fn tile_count(&self) -> u64 {
        let coarse = if self.coarse == 0 {
            0
        } else {
            u64::from(self.coarse.div_ceil(self.tile_size)).pow(2)
        };
        u64::from(self.image_tiles) + coarse
    }

    /// The tile holding `pixel` (of the coarse image for a coarse-pass ray).
    pub fn tile_of(&self, pixel: u32, coarse: bool) -> u32 {
        if coarse {
            let n = self.coarse.max(1);
            let (x, y) = (pixel % n, pixel / n);
            let tiles_x = n.div_ceil(self.tile_size);
            return self.image_tiles + (y / self.tile_size) * tiles_x + x / self.tile_size;
        }
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
        let spp = if tile.coarse {
            1
        } else {
            self.settings.spp.max(1) as u64
        };
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
        // Every pixel of the tile is in the image (or the coarse image), so the rays made
        // here and their descendants need no check of their own.
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
        for i in start..end {
            let (p, sample) = (i / spp, (i % spp) as u32);
            let (lx, ly) = (
                (p % tile.width as u64) as u32,
                (p / tile.width as u64) as u32,
            );
            let share = credit::camera_share(tile.credit, total, i).unwrap_or(0);
            let (ray, lin) = if tile.coarse {
                // One regular ray through the coarse pixel's centre, its random numbers
                // keyed apart from every sample of the image.
                let n = self.coarse.max(1);
                let (cx, cy) = (tile.x0 + lx, tile.y0 + ly);
                let film =
                    glam::Vec2::new((cx as f32 + 0.5) / n as f32, (cy as f32 + 0.5) / n as f32);
                let lin = Lineage {
                    tickets: None,
                    coarse: true,
                    probe: false,
                };
                (
                    bare.camera_ray_through(film, cy * n + cx, COARSE_SAMPLE),
                    lin,
                )
            } else {
                let pixel = (tile.y0 + ly) * self.settings.width + tile.x0 + lx;
                (bare.camera_ray(pixel, sample), Lineage::default())
            };
            out.traced[RayKind::Camera as usize] += 1;
            if let Some((d, loaded, integrator)) = whole {
                let parts = (d, loaded, integrator);
                self.trace_tree(parts, ray, share, &lin, tile.index, &mut step, out)?;
                continue;
            }
            self.route_new(&ctx, bare, ray, share, lin, tile.index, out);
            // Depth first, one camera ray's tree at a time: the stack of local rays stays
            // a few entries deep and in cache, where making the whole chunk's camera rays
            // first stacked thousands of them (half a megabyte).
            self.trace_local(&ctx, &mut step, out)?;
        }
        Ok(())
    }

    /// Send a ray that was just made to the first domain on its path, or finish it at
    /// once when it meets no domain with triangles. A ray whose first domain starts
    /// ahead of its origin enters it through a wall.
    #[allow(clippy::too_many_arguments)]
    fn route_new(
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
    fn forward(
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

    /// A ray enters `domain` through one of its walls, from another domain or from
    /// outside the scene: the one place where a ray crossing a wall is seen. With ray
    /// caches on for its kind, it goes to the wall's cache actor first (the wall is the
    /// face of `domain` it enters by); otherwise straight on.
    #[allow(clippy::too_many_arguments)]
    fn cross(
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
        let k = ray.kind as usize;
        let (cache, phm) = (self.cached_kinds[k], self.phm_kinds[k] && !lin.coarse);
        if ctx.pins.walls() && (cache || phm) {
            let face = self
                .bounds
                .get(domain as usize)
                .and_then(|&(lo, hi)| entry_face(lo, hi, ray.origin, ray.dir));
            if let (Some(face), Ok(r)) = (face, RayRecord::from_state(&ray, credit)) {
                let wall = wall_index(domain, face);
                // In place when the ray opens no ticket (nothing for the actor to
                // record) and every view it needs is in this process.
                let answer = cache && !lin.coarse;
                let ticket = cache && self.opens_ticket(&lin);
                let map = if phm { ctx.pins.map(wall) } else { None };
                let store = if answer { ctx.pins.cache(wall) } else { None };
                if !ticket && map.is_some() == phm && store.is_some() == answer {
                    self.at_wall_in_place(ctx, map, store, r, lin, domain, hop, tile, out);
                    return;
                }
                out.lookups.push(Lookup {
                    wall,
                    domain,
                    ray: r,
                    lineage: lin,
                    cache,
                    phm,
                });
                return;
            }
        }
        self.forward(ctx, ray, credit, lin, domain, hop, tile, out);
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
    #[allow(clippy::too_many_arguments)]
    fn at_wall_in_place(
        &self,
        ctx: &StepCtx<'_>,
        map: Option<&MapView>,
        store: Option<&StoreView>,
        r: RayRecord,
        mut lin: Lineage,
        domain: u32,
        hop: Option<Hop>,
        tile: u32,
        out: &mut Outbox,
    ) {
        let elsewhere = || u64::from(ctx.pins.get(domain).is_none());
        let advice = map.map(|m| m.consult(&r));
        match advice {
            Some(Advice::Skip) => {
                let state = r.to_state();
                let next = self.tree.hop(
                    state.origin,
                    state.dir,
                    0.0,
                    state.tmax,
                    self.pad,
                    domain,
                    self.wanted(),
                );
                if let Some(past) = next {
                    out.phm_not_sent += elsewhere();
                    out.taint(&lin);
                    let lin = lin.inherited();
                    match past.next {
                        Some(d) => self.cross(ctx, state, r.credit, lin, d, None, tile, out),
                        None => finish_unblocked(&ctx.bare, &state, r.credit, &lin, tile, out),
                    }
                    return;
                }
                // The ray does not cross the domain after all (a routing mismatch that
                // the message path reports as an error): trace it exactly.
            }
            Some(Advice::Occlude) if r.kind.is_occlusion() => {
                out.phm_not_sent += elsewhere();
                self.answer_occluded(&r, &lin, out);
                return;
            }
            _ => {}
        }
        if let Some(rgb) = store.and_then(|s| s.answer(&r)) {
            out.cache_not_sent += elsewhere();
            self.answer_hit(&r, &lin, Vec3::from_array(rgb), out);
            return;
        }
        lin.probe = advice == Some(Advice::Probe);
        if lin.probe
            && let Some(m) = map
        {
            m.probed();
        }
        self.forward(ctx, r.to_state(), r.credit, lin, domain, hop, tile, out);
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
    fn trace_tree(
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
    fn trace_local(
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

impl JobTracer {
    /// Note a probe's outcome in `domain` for the map of the wall it entered by.
    fn report_probe(&self, domain: u32, ray: &RayState, hit: bool, out: &mut Outbox) {
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

/// A ray that left the scene without being blocked: occlusion rays add what they carry,
/// others see the environment.
fn finish_unblocked(
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
