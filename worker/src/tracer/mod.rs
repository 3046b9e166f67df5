//! Tracing one job's rays in the domains this worker owns.
//!
//! [`JobTracer`] is the worker's compute step, with no I/O: it takes a batch of rays
//! queued for one owned domain (or a range of a tile's camera rays) and puts into an
//! [`Outbox`] everything that comes out: pixel sums in fixed point, credit handed back
//! per tile, and rays bound for other domains. The gRPC side moves batches and outboxes
//! around; this module decides what happens to each ray.
//!
//! Each ray is traced against the domain's BVH clipped to the ray's span inside the
//! domain ([`dray_core::trace::SpanTrace`]); the span is found by walking the domain
//! layout from the ray's own origin ([`DomainTree::hop`]), so it is the very span the
//! embedded renderer's [`dray_core::trace::DomainSet`] uses, and the image is the same
//! bit for bit. Empty domains are skipped: they can neither hit nor block a ray.
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
//!
//! The parts, by concern (docs/architecture.md "Life of a ray"):
//! - [`camera`]: a tile's camera rays, each with its share of the tile's credit;
//! - [`trace`]: a ray in its domain (span, hit, shading) and the routing of the rays
//!   it makes;
//! - [`walls`]: a ray crossing into a domain, and the answers of hit maps and ray
//!   caches at the wall;
//! - [`residency`]: which domains a step may trace here, pinned for the step;
//! - [`outbox`]: what comes out (sums, credit given back, rays and lookups to send).

mod camera;
mod outbox;
pub mod pass_tag;
mod residency;
#[cfg(test)]
mod tests;
mod trace;
mod walls;

use std::sync::Arc;

use dray_core::camera::Camera;
use dray_core::credit::{Credit, CreditError};
use dray_core::domain::{DomainTree, Hop};
use dray_core::integrator::{Integrator, RayState, RenderSettings};
use dray_core::kind_set::KindSet;
use dray_core::light_sampler::LightSampler;
use dray_core::scene::Scene;
use dray_core::tiles::TileGrid;
use dray_core::wall::PhmBins;
use glam::Vec3;

use crate::domain_store::LoadedDomain;
use crate::tickets::Lineage;

pub use camera::TileRef;
pub use outbox::{Lookup, Outbox};
pub use residency::{NoDomains, Residency};

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
    #[error("tile {tile}'s pass, samples {first}..+{count}, is not inside the job's {spp} spp")]
    BadSamples {
        tile: u32,
        first: u32,
        count: u32,
        spp: u32,
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
        credit: Credit,
    },
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
    /// The image's tiles, as the coordinator numbers them.
    tiles: TileGrid,
    /// A scene with no triangles and its (empty) light table: the integrator of steps
    /// that need no domain (camera rays, rays leaving the scene).
    bare: Scene,
    bare_lights: Arc<LightSampler>,
    /// Per domain, its box: where walls are.
    bounds: Vec<(Vec3, Vec3)>,
    /// The ray kinds the job's ray caches look up (empty: caches off).
    cached_kinds: KindSet,
    /// Whether rays of the main pass fill the caches (`ray_cache.fill`); if not, only
    /// the coarse pass's rays take tickets.
    fill: bool,
    /// The ray kinds the job's hit maps serve, and the maps' binning (no kinds: maps
    /// off).
    phm_kinds: KindSet,
    phm_bins: PhmBins,
    /// The coarse pass's image edge N (0: no coarse pass), and its tiles (numbered
    /// after the image's).
    coarse: u32,
    coarse_tiles: TileGrid,
    /// Whether each coarse-pass ray goes through a random point of its coarse pixel
    /// (`JobSpec.coarse_sampling` "random") rather than its centre.
    coarse_random: bool,
    /// The job's passes, when it traces them ahead: results then carry their pass
    /// ([`pass_tag`]).
    tags: Option<pass_tag::PassTags>,
}

impl JobTracer {
    /// `domain_triangles` has one entry per domain of the layout; `tile_size` is the
    /// edge of the job's tiles ([`TileGrid`]).
    pub fn new(
        settings: RenderSettings,
        mut camera: Camera,
        tree: DomainTree,
        pad: f32,
        domain_triangles: &[u64],
        tile_size: u32,
    ) -> JobTracer {
        camera.name = String::new();
        let single = tree
            .single()
            .filter(|&d| domain_triangles.get(d as usize).is_some_and(|&n| n > 0));
        let bare = Scene::default();
        // The layout's bounds are the scene's: camera rays start at them (core's
        // `Frustum::clipped_to`), as in every other configuration.
        let bare_lights = Arc::new(LightSampler::with_bounds(&bare, false, (tree.lo, tree.hi)));
        JobTracer {
            bounds: tree.domain_bounds(),
            cached_kinds: KindSet::default(),
            fill: true,
            phm_kinds: KindSet::default(),
            phm_bins: PhmBins::new(1, 1),
            coarse: 0,
            coarse_tiles: TileGrid::new(0, 0, tile_size),
            coarse_random: false,
            tiles: TileGrid::new(settings.width, settings.height, tile_size),
            tags: None,
            camera,
            settings,
            tree,
            pad,
            single,
            nonempty: domain_triangles.iter().map(|&n| n > 0).collect(),
            bare,
            bare_lights,
        }
    }

    /// Look rays of these kinds up in wall caches (the job's `ray_cache.kinds`).
    pub fn with_cached_kinds(mut self, kinds: KindSet) -> JobTracer {
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
    pub fn with_phm(mut self, kinds: KindSet, bins: PhmBins) -> JobTracer {
        self.phm_kinds = kinds;
        self.phm_bins = bins;
        self
    }

    /// The job's ray-cache coarse pass covers an `n` x `n` image (0: none), one ray
    /// through each coarse pixel: through its centre, or with `random` through a point
    /// of it drawn from the job's seed and the coarse pixel (the same on every worker).
    pub fn with_coarse(mut self, n: u32, random: bool) -> JobTracer {
        self.coarse = n;
        self.coarse_tiles = TileGrid::new(n, n, self.tiles.size());
        self.coarse_random = random;
        self
    }

    /// Tag what rays hand back with their pass (a job tracing passes ahead).
    pub fn with_pass_tags(mut self, tags: pass_tag::PassTags) -> JobTracer {
        self.tags = Some(tags);
        self
    }

    /// The job's passes, when it traces them ahead.
    pub fn pass_tags(&self) -> Option<&pass_tag::PassTags> {
        self.tags.as_ref()
    }

    pub fn settings(&self) -> &RenderSettings {
        &self.settings
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

    fn wanted(&self) -> impl Fn(u32) -> bool + '_ {
        |d| self.nonempty.get(d as usize).copied().unwrap_or(false)
    }

    /// `ray`'s span in `domain`, walking the layout from the ray's origin, and the next
    /// domain with triangles on its path; `None` when the ray does not pass through
    /// `domain`.
    fn hop_in(&self, ray: &RayState, domain: u32) -> Option<Hop> {
        self.tree.hop(
            ray.origin,
            ray.dir,
            0.0,
            ray.tmax,
            self.pad,
            domain,
            self.wanted(),
        )
    }
}
