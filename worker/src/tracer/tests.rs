//! The tracing step on a scene of two quads in two domains, with no cluster: a tile's
//! credit is conserved, rays cross from one domain to the next, misses see the
//! environment, the step is deterministic, and non-finite values stay out of the sums.
//!
//! The scene: quad A at z = -1 (x in -2..-0.5) and quad B at z = +1 (x in 0.5..2),
//! both y in -1..1, cut by a 2x1x1 grid at x = 0 into domain A (A's quad) and domain B
//! (B's quad). A ray at z = 0 runs between the quads.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use dray_core::camera::Camera;
use dray_core::credit::Credit;
use dray_core::film::to_fixed;
use dray_core::integrator::{IntegratorKind, RayKind, RenderSettings};
use dray_core::kind_set::KindSet;
use dray_core::material::Material;
use dray_core::ray::RayRecord;
use dray_core::scene::{Mesh, Scene};
use dray_core::tiles::TileGrid;
use dray_scene::partition::memory::MemoryPackage;
use dray_scene::partition::{DomainLayout, LayoutSpec, partition_in_memory};
use glam::Vec3;

use super::{JobTracer, NoDomains, Outbox, Residency, TileRef, TraceError};
use crate::domain_sources::memory_domains;
use crate::domain_store::LoadedDomain;
use crate::tickets::Lineage;

const TILE: u32 = 8;
const TILE_CREDIT: Credit = Credit::from_wire(1 << 40);
const RAY_CREDIT: Credit = Credit::from_wire(1 << 20);

/// Two quads, each two triangles, of one white lambert material; no lights, so the
/// renderer's default sky lights them.
fn two_quads() -> Scene {
    let mut mesh = Mesh::default();
    for (x0, x1, z) in [(-2.0, -0.5, -1.0), (0.5, 2.0, 1.0)] {
        let base = mesh.push_vertices(&[
            Vec3::new(x0, -1.0, z),
            Vec3::new(x1, -1.0, z),
            Vec3::new(x1, 1.0, z),
            Vec3::new(x0, 1.0, z),
        ]);
        mesh.indices.push([base, base + 1, base + 2]);
        mesh.indices.push([base, base + 2, base + 3]);
        mesh.material.extend([0, 0]);
    }
    Scene {
        mesh,
        materials: vec![Material::lambert("white", Vec3::splat(0.8))],
        ..Scene::default()
    }
}

/// A job over [`two_quads`] cut by `spec`, with every domain loaded.
struct Fixture {
    settings: RenderSettings,
    camera: Camera,
    /// Triangles per domain.
    counts: Vec<u64>,
    tracer: JobTracer,
    layout: DomainLayout,
    loaded: HashMap<u32, Arc<LoadedDomain>>,
}

impl Fixture {
    fn new(spec: LayoutSpec) -> Fixture {
        let scene = two_quads();
        let environment = dray_scene::effects::default_environment(&scene);
        let settings = RenderSettings {
            width: 16,
            height: 16,
            spp: 2,
            integrator: IntegratorKind::Path,
            max_depth: 4,
            seed: 11,
            environment,
            effects: dray_scene::effects::analyze(&scene, environment),
            ao_samples: 2,
            ao_distance: f32::INFINITY,
            lighting: Default::default(),
            clamp_indirect: None,
            aovs: Default::default(),
        };
        let layout = DomainLayout::for_source(&scene, &spec).expect("layout");
        let mut counts = vec![0u64; layout.domain_count() as usize];
        for p in partition_in_memory(&scene, &layout).expect("partition") {
            counts[p.domain as usize] = p.triangle_count() as u64;
        }
        // A three-quarter view from +x, +y, +z: some camera rays meet quad B first,
        // some cross into domain A, some miss the scene.
        let (lo, hi) = scene.bounds();
        let camera = Camera::framing(lo, hi, 1.0);
        let tracer = JobTracer::new(
            settings.clone(),
            camera.clone(),
            layout.to_domain_tree(),
            layout.epsilon(),
            &counts,
            TILE,
        );
        let package = MemoryPackage::with_layout(scene, layout.clone()).expect("package");
        let source = memory_domains(Arc::new(package), &settings);
        let loaded = (0..layout.domain_count())
            .map(|d| (d, Arc::new(source.load(d).expect("load"))))
            .collect();
        Fixture {
            settings,
            camera,
            counts,
            tracer,
            layout,
            loaded,
        }
    }

    fn two_domains() -> Fixture {
        Fixture::new(LayoutSpec::Grid([2, 1, 1]))
    }

    /// The domain holding point `p`.
    fn domain_at(&self, p: Vec3) -> u32 {
        self.layout.locate(p).expect("inside the scene")
    }

    /// Domains A (x < 0) and B (x > 0).
    fn a_and_b(&self) -> (u32, u32) {
        let (a, b) = (
            self.domain_at(Vec3::new(-1.0, 0.0, 0.0)),
            self.domain_at(Vec3::new(1.0, 0.0, 0.0)),
        );
        assert_ne!(a, b, "the grid cuts the scene at x = 0");
        (a, b)
    }

    /// The loaded domains among `ds`.
    fn holding(&self, ds: &[u32]) -> HashMap<u32, Arc<LoadedDomain>> {
        ds.iter().map(|d| (*d, self.loaded[d].clone())).collect()
    }

    fn tiles(&self) -> Vec<TileRef> {
        let grid = TileGrid::new(self.settings.width, self.settings.height, TILE);
        TileRef::all(&grid, TILE_CREDIT)
    }
}

/// A diffuse bounce ray at `origin` going along `dir`, for pixel 0.
fn ray(origin: Vec3, dir: Vec3, weight: Vec3) -> RayRecord {
    RayRecord {
        credit: RAY_CREDIT,
        origin,
        dir: dir.normalize(),
        tmax: f32::INFINITY,
        weight,
        bsdf_pdf: 0.0,
        pixel: 0,
        sample: 0,
        depth: 1,
        kind: RayKind::Diffuse,
        flags: 0,
    }
}

/// From domain A, between the quads, straight across the wall into B and out of the
/// scene without touching either quad.
fn across_between(weight: Vec3) -> RayRecord {
    ray(Vec3::new(-1.0, 0.0, 0.0), Vec3::X, weight)
}

/// From domain A across the wall onto quad B (at (1.25, 0, 1)).
fn across_onto_b() -> RayRecord {
    ray(
        Vec3::new(-1.0, 0.0, 0.0),
        Vec3::new(2.25, 0.0, 1.0),
        Vec3::ONE,
    )
}

/// From domain A straight up, out of the scene through A's top wall.
fn up_and_out(weight: Vec3) -> RayRecord {
    ray(Vec3::new(-1.0, 0.0, 0.0), Vec3::Y, weight)
}

/// Credit handed back plus credit carried by rays sent out, by tile.
fn credit_by_tile(tracer: &JobTracer, out: &Outbox) -> BTreeMap<u32, Credit> {
    let mut by_tile = BTreeMap::new();
    let mut add = |tile: u32, c: Credit| {
        let sum: &mut Credit = by_tile.entry(tile).or_default();
        *sum = sum.checked_add(c).expect("no tile's credit overflows");
    };
    for &(t, c) in &out.credits {
        add(t, c);
    }
    for bundle in out.rays.values() {
        for r in &bundle.rays {
            add(tracer.tile_of(r.pixel, r.sample, false), r.credit);
        }
    }
    for l in &out.lookups {
        add(
            tracer.tile_of(l.ray.pixel, l.ray.sample, false),
            l.ray.credit,
        );
    }
    by_tile
}

/// Sums by pixel (the outbox may list a pixel more than once).
fn sums_by_pixel(out: &Outbox) -> BTreeMap<u32, [i64; 3]> {
    let mut sums = BTreeMap::new();
    for &(k, v) in &out.sums {
        let p = k as u32;
        let s: &mut [i64; 3] = sums.entry(p).or_insert([0; 3]);
        for c in 0..3 {
            s[c] = s[c].wrapping_add(v[c]);
        }
    }
    sums
}

/// Rays sent out, by domain, in order.
fn rays_by_domain(out: &Outbox) -> BTreeMap<u32, Vec<RayRecord>> {
    out.rays
        .iter()
        .filter(|(_, b)| !b.is_empty())
        .map(|(d, b)| (*d, b.rays.clone()))
        .collect()
}

fn camera_rays_of(f: &Fixture, residency: &dyn Residency) -> Outbox {
    let mut out = Outbox::default();
    for t in f.tiles() {
        // In two ranges, as a worker dealing camera rays in chunks would.
        let total = t.camera_rays(f.settings.spp);
        let half = total / 2;
        f.tracer
            .camera_rays(&t, 0, half, residency, &mut out)
            .expect("camera rays");
        f.tracer
            .camera_rays(&t, half, total - half, residency, &mut out)
            .expect("camera rays");
    }
    out
}

#[test]
fn camera_rays_carry_exactly_their_tiles_credit() {
    let f = Fixture::two_domains();
    let (a, b) = f.a_and_b();
    let camera_rays: u64 = f
        .tiles()
        .iter()
        .map(|t| t.camera_rays(f.settings.spp))
        .sum();
    for held in [vec![], vec![a], vec![b], vec![a, b]] {
        let residency = f.holding(&held);
        let out = camera_rays_of(&f, &residency);
        let by_tile = credit_by_tile(&f.tracer, &out);
        for t in f.tiles() {
            assert_eq!(
                by_tile.get(&t.index).copied(),
                Some(TILE_CREDIT),
                "tile {} holding {held:?}: credit handed back plus credit sent out",
                t.index
            );
        }
        assert_eq!(by_tile.len(), f.tiles().len(), "credit for unknown tiles");
        assert_eq!(out.traced[RayKind::Camera as usize], camera_rays);
        assert!(out.lookups.is_empty(), "no lookups without ray caches");
        // Rays go out only for domains not traced here.
        for d in rays_by_domain(&out).keys() {
            assert!(
                !held.contains(d),
                "rays sent out for domain {d}, traced here"
            );
        }
        if held.len() == 2 {
            assert_eq!(out.ray_count(), 0, "every ray traced here");
            assert!(!out.sums.is_empty(), "the sky lights the image");
        } else {
            assert!(
                out.ray_count() > 0,
                "holding {held:?}: rays for the other domain"
            );
        }
    }
}

#[test]
fn a_range_past_the_tile_makes_no_rays() {
    let f = Fixture::two_domains();
    let t = f.tiles()[0];
    let total = t.camera_rays(f.settings.spp);
    let mut out = Outbox::default();
    f.tracer
        .camera_rays(&t, total, 10, &f.loaded, &mut out)
        .expect("camera rays");
    assert!(out.is_empty());
}

#[test]
fn a_ray_leaving_a_crosses_to_b_with_its_credit() {
    let f = Fixture::two_domains();
    let (a, b) = f.a_and_b();
    for rec in [across_between(Vec3::ONE), across_onto_b()] {
        let mut out = Outbox::default();
        f.tracer
            .trace_batch(a, &[rec], &[], &f.holding(&[a]), &mut out)
            .expect("trace");
        assert_eq!(
            rays_by_domain(&out),
            BTreeMap::from([(b, vec![rec])]),
            "routed to domain B, unchanged, with its credit"
        );
        assert!(
            out.credits.is_empty(),
            "no credit handed back: the ray goes on"
        );
        assert!(out.sums.is_empty());
        // Rays are counted where they are made, not where they cross.
        assert_eq!(out.traced, [0; RayKind::COUNT]);
    }
}

#[test]
fn a_ray_crossing_into_a_domain_traced_here_is_traced_in_the_same_step() {
    let f = Fixture::two_domains();
    let (a, b) = f.a_and_b();
    let rec = across_onto_b();
    let mut out = Outbox::default();
    f.tracer
        .trace_batch(a, &[rec], &[], &f.holding(&[a, b]), &mut out)
        .expect("trace");
    assert_eq!(out.ray_count(), 0);
    assert_eq!(
        credit_by_tile(&f.tracer, &out),
        BTreeMap::from([(f.tracer.tile_of(0, 0, false), RAY_CREDIT)]),
        "the credit comes back whole, split among the hit's children"
    );
    assert!(
        out.traced.iter().sum::<u64>() > 0,
        "the hit on quad B made rays"
    );
}

#[test]
fn a_ray_that_hits_nothing_sees_the_environment_and_hands_back_its_credit() {
    let f = Fixture::two_domains();
    let (a, b) = f.a_and_b();
    assert!(f.settings.environment.max_element() > 0.0, "a sky to see");
    let weight = Vec3::new(0.5, 0.25, 0.125);
    let expected = to_fixed(weight * f.settings.environment).expect("finite");
    assert!(expected.iter().all(|&c| c > 0));
    // Out of A at once, and out of B after crossing into it.
    for (rec, held) in [
        (up_and_out(weight), vec![a]),
        (across_between(weight), vec![a, b]),
    ] {
        let mut out = Outbox::default();
        f.tracer
            .trace_batch(a, &[rec], &[], &f.holding(&held), &mut out)
            .expect("trace");
        assert_eq!(out.sums, vec![(u64::from(rec.pixel), expected)]);
        assert_eq!(
            out.credits,
            vec![(f.tracer.tile_of(rec.pixel, rec.sample, false), RAY_CREDIT)]
        );
        assert_eq!(out.ray_count(), 0);
        assert_eq!(out.nonfinite, 0);
    }
}

#[test]
fn the_same_work_traced_twice_gives_the_same_outbox() {
    let f = Fixture::two_domains();
    let (a, b) = f.a_and_b();
    let batch = [
        across_onto_b(),
        across_between(Vec3::ONE),
        up_and_out(Vec3::splat(0.5)),
    ];
    for held in [vec![a], vec![a, b]] {
        let residency = f.holding(&held);
        let trace = || {
            let mut out = camera_rays_of(&f, &residency);
            f.tracer
                .trace_batch(a, &batch, &[], &residency, &mut out)
                .expect("trace");
            out
        };
        let (first, second) = (trace(), trace());
        assert!(!first.sums.is_empty());
        assert_eq!(first.sums, second.sums, "holding {held:?}");
        assert_eq!(first.credits, second.credits, "holding {held:?}");
        assert_eq!(rays_by_domain(&first), rays_by_domain(&second));
        assert_eq!(first.traced, second.traced);
        assert_eq!(first.nonfinite, second.nonfinite);
    }
}

#[test]
fn non_finite_contributions_never_reach_the_sums() {
    let f = Fixture::two_domains();
    let (a, b) = f.a_and_b();
    // A miss, and a shadow ray that nothing blocks: each adds its weight (times the
    // sky for the miss), not finite, so nothing.
    let shadow = |weight| RayRecord {
        kind: RayKind::Shadow,
        tmax: 5.0,
        ..up_and_out(weight)
    };
    for (rec, weight) in [
        (up_and_out(Vec3::new(f32::INFINITY, 1.0, 1.0)), "inf"),
        (up_and_out(Vec3::new(f32::NAN, 1.0, 1.0)), "NaN"),
        (shadow(Vec3::new(1.0, f32::INFINITY, 1.0)), "inf shadow"),
        (shadow(Vec3::new(1.0, 1.0, f32::NAN)), "NaN shadow"),
    ] {
        let mut out = Outbox::default();
        f.tracer
            .trace_batch(a, &[rec], &[], &f.holding(&[a, b]), &mut out)
            .expect("trace");
        assert!(out.sums.is_empty(), "weight {weight}: {:?}", out.sums);
        assert_eq!(out.nonfinite, 1, "weight {weight}: the miss is counted");
        assert_eq!(
            out.credits,
            vec![(0, RAY_CREDIT)],
            "weight {weight}: the credit still comes back"
        );
    }
    // A hit whose weight is not finite: nothing it leads to reaches the sums, and its
    // credit still comes back whole.
    for weight in [
        Vec3::new(f32::INFINITY, 0.5, 0.5),
        Vec3::new(f32::NAN, 0.5, 0.5),
    ] {
        let mut rec = across_onto_b();
        rec.weight = weight;
        let mut out = Outbox::default();
        f.tracer
            .trace_batch(a, &[rec], &[], &f.holding(&[a, b]), &mut out)
            .expect("trace");
        assert!(out.sums.is_empty(), "{:?}", out.sums);
        assert_eq!(
            credit_by_tile(&f.tracer, &out),
            BTreeMap::from([(0, RAY_CREDIT)])
        );
    }
}

#[test]
fn rays_for_a_domain_not_held_or_not_crossed_are_errors() {
    let f = Fixture::two_domains();
    let (a, b) = f.a_and_b();
    let mut out = Outbox::default();
    assert_eq!(
        f.tracer
            .trace_batch(b, &[across_onto_b()], &[], &f.holding(&[a]), &mut out),
        Err(TraceError::NotResident { domain: b })
    );
    // A ray starting in A, going away from B, sent to B.
    let away = ray(Vec3::new(-1.0, 0.0, 0.0), -Vec3::X, Vec3::ONE);
    assert_eq!(
        f.tracer
            .trace_batch(b, &[away], &[], &f.holding(&[a, b]), &mut out),
        Err(TraceError::Misrouted { domain: b })
    );
    let mut bad = across_onto_b();
    bad.pixel = f.settings.width * f.settings.height;
    assert!(matches!(
        f.tracer
            .trace_batch(a, &[bad], &[], &f.holding(&[a]), &mut out),
        Err(TraceError::BadPixel { .. })
    ));
}

/// Every domain here, and walls placed: rays crossing them go to the walls' actors.
struct WithWalls(HashMap<u32, Arc<LoadedDomain>>);

impl Residency for WithWalls {
    fn domain(&self, d: u32) -> Option<Arc<LoadedDomain>> {
        self.0.get(&d).cloned()
    }

    fn walls(&self) -> bool {
        true
    }
}

#[test]
fn with_ray_caches_a_crossing_ray_asks_the_wall_first() {
    let f = Fixture::two_domains();
    let (a, b) = f.a_and_b();
    let diffuse = KindSet::of(&[RayKind::Diffuse]);
    let tracer = JobTracer::new(
        f.settings.clone(),
        f.camera.clone(),
        f.layout.to_domain_tree(),
        f.layout.epsilon(),
        &f.counts,
        TILE,
    )
    .with_cached_kinds(diffuse);
    let rec = across_between(Vec3::ONE);
    let mut out = Outbox::default();
    // B is traced here, and still the ray asks the wall it enters B by first.
    tracer
        .trace_batch(a, &[rec], &[], &WithWalls(f.holding(&[a, b])), &mut out)
        .expect("trace");
    assert_eq!(out.lookups.len(), 1);
    let l = &out.lookups[0];
    assert_eq!((l.domain, l.wall / 6, l.ray), (b, b, rec), "a wall of B");
    assert!(l.cache && !l.phm);
    assert!(out.credits.is_empty() && out.sums.is_empty() && out.ray_count() == 0);
    // A kind the job does not cache crosses as without caches.
    let mut reflection = across_between(Vec3::ONE);
    reflection.kind = RayKind::Reflection;
    let mut out = Outbox::default();
    tracer
        .trace_batch(a, &[reflection], &[], &WithWalls(f.holding(&[a])), &mut out)
        .expect("trace");
    assert!(out.lookups.is_empty());
    assert_eq!(
        rays_by_domain(&out),
        BTreeMap::from([(b, vec![reflection])])
    );
}

#[test]
fn a_skipped_domain_is_passed_and_the_rays_tickets_are_tainted() {
    let f = Fixture::two_domains();
    let (a, b) = f.a_and_b();
    let lineage = Lineage::default().with_ticket(42);
    // The map says the ray misses A: it goes on from A's far wall into B.
    let rec = across_onto_b();
    let mut out = Outbox::default();
    f.tracer
        .skip(&rec, lineage, a, &NoDomains { walls: false }, &mut out)
        .expect("skip");
    let bundle = &out.rays[&b];
    assert_eq!(bundle.rays.len(), 1);
    assert_eq!(bundle.rays[0].credit, RAY_CREDIT);
    assert!(
        bundle.tickets.is_empty(),
        "the ray goes on without its ticket"
    );
    // The ticket is settled at once, with all the ray's credit: a taint that carries
    // credit cannot reach the ticket after it closed.
    let owed = out.tickets.drain();
    assert_eq!(owed.len(), 1);
    assert_eq!((owed[0].ticket, owed[0].credit), (42, RAY_CREDIT.to_wire()));
    assert!(owed[0].tainted, "what the ray sees rests on a prediction");
}

/// A one-domain layout's camera rays are traced without routing (`trace_tree`) when
/// the domain is here; sent out and traced as a batch (`trace_one`) otherwise. Both
/// give the same sums, credit and counts.
#[test]
fn the_one_domain_loop_matches_the_routed_one() {
    let f = Fixture::new(LayoutSpec::Grid([1, 1, 1]));
    assert_eq!(f.tracer.single_domain(), Some(0));
    let direct = camera_rays_of(&f, &f.loaded);
    assert_eq!(direct.ray_count(), 0);

    let mut routed = camera_rays_of(&f, &HashMap::new());
    let queued = std::mem::take(&mut routed.rays);
    assert_eq!(queued.keys().copied().collect::<Vec<_>>(), vec![0]);
    let batch = &queued[&0];
    assert!(!batch.is_empty());
    f.tracer
        .trace_batch(0, &batch.rays, &[], &f.loaded, &mut routed)
        .expect("trace");

    assert!(!direct.sums.is_empty());
    assert_eq!(sums_by_pixel(&direct), sums_by_pixel(&routed));
    assert_eq!(
        credit_by_tile(&f.tracer, &direct),
        credit_by_tile(&f.tracer, &routed)
    );
    assert_eq!(direct.traced, routed.traced);
    assert!(
        direct.traced.iter().skip(1).sum::<u64>() > 0,
        "the quads made bounce and shadow rays"
    );
}
