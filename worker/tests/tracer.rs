//! The worker's tracing step gives the single-process image bit for bit.
//!
//! Several [`JobTracer`]s, each holding only its own domains (and the emitters), trade
//! rays through in-memory queues in a scrambled order, exactly as workers trade them over
//! gRPC; their pixel sums must equal `dray_core::render` over one BVH for every
//! integrator and both layouts, their ray counts must match, and every tile's credit
//! must come back whole.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use dray_core::bvh::Accel;
use dray_core::camera::Camera;
use dray_core::credit::Credit;
use dray_core::film::Film;
use dray_core::integrator::{Integrator, IntegratorKind, RenderSettings};
use dray_core::ray::RayRecord;
use dray_core::render;
use dray_core::scene::Scene;
use dray_core::tiles::TileGrid;
use dray_scene::partition::memory::MemoryPackage;
use dray_scene::partition::resident::resident_in_memory;
use dray_scene::partition::{
    DomainLayout, LayoutSpec, load_resident, open_package, partition_in_memory, write_scene_package,
};
use dray_worker::plan::{memory_domains, package_domains};
use dray_worker::tracer::pass_tag::{PassTags, split_sum_key, tile_key};
use dray_worker::{DomainSource, JobTracer, LoadedDomain, Outbox, TileRef};

const TILE: u32 = 16;
const TILE_CREDIT: Credit = Credit::TILE;

fn settings(scene: &Scene, kind: IntegratorKind, w: u32, h: u32, spp: u32) -> RenderSettings {
    let environment = dray_scene::effects::default_environment(scene);
    RenderSettings {
        width: w,
        height: h,
        spp,
        integrator: kind,
        max_depth: 5,
        seed: 7,
        environment,
        effects: dray_scene::effects::analyze(scene, environment),
        ao_samples: 4,
        ao_distance: f32::INFINITY,
        lighting: Default::default(),
        clamp_indirect: None,
        aovs: Default::default(),
    }
}

fn camera(scene: &Scene, s: &RenderSettings) -> Camera {
    scene.cameras.first().cloned().unwrap_or_else(|| {
        let (lo, hi) = scene.bounds();
        Camera::framing(lo, hi, s.width as f32 / s.height as f32)
    })
}

struct Distributed {
    film: Film,
    rays: [u64; 6],
    /// Traced ahead: each pass's sums alone, as their tags say.
    pass_films: Vec<Film>,
}

/// Trace the job on `workers` tracers, domains dealt round-robin, tiles too.
fn distributed(
    scene: &Scene,
    s: &RenderSettings,
    spec: &LayoutSpec,
    workers: u32,
    scramble: u64,
) -> Distributed {
    let layout = DomainLayout::for_source(scene, spec).unwrap();
    let package = MemoryPackage::with_layout(scene.clone(), layout.clone()).unwrap();
    let source = memory_domains(Arc::new(package), s);
    let all = 0..s.spp;
    distributed_with(
        scene,
        s,
        &layout,
        workers,
        scramble,
        source.as_ref(),
        std::slice::from_ref(&all),
        false,
    )
}

/// Trace the job in `passes` (sample ranges), each dealt and traded to the end before
/// the next, as the coordinator deals progressive passes; or, `ahead`, every pass's
/// camera rays at once by tracers that tag results with their pass, as workers tracing
/// passes ahead make them.
#[allow(clippy::too_many_arguments)]
fn distributed_with(
    scene: &Scene,
    s: &RenderSettings,
    layout: &DomainLayout,
    workers: u32,
    scramble: u64,
    source: &dyn DomainSource,
    passes: &[std::ops::Range<u32>],
    ahead: bool,
) -> Distributed {
    let tags = ahead.then(|| PassTags::new(passes.to_vec()).expect("passes to trace ahead"));
    let n = layout.domain_count();
    let mut counts = vec![0u64; n as usize];
    for p in partition_in_memory(scene, layout).unwrap() {
        counts[p.domain as usize] = p.triangle_count() as u64;
    }
    let owner = |d: u32| d % workers;
    // Each worker's domains, loaded one by one as its domain store would.
    let held: Vec<HashMap<u32, Arc<LoadedDomain>>> = (0..workers)
        .map(|w| {
            (0..n)
                .filter(|&d| owner(d) == w)
                .map(|d| {
                    let loaded = source.load(d).unwrap();
                    // A domain holds its own triangles and the emitters, never the
                    // whole scene (unless it is the only domain).
                    if n > 1 {
                        assert!(
                            loaded.resident.scene.mesh.indices.len() < scene.mesh.indices.len()
                        );
                    }
                    (d, Arc::new(loaded))
                })
                .collect()
        })
        .collect();
    let tracers: Vec<JobTracer> = (0..workers)
        .map(|_| {
            let t = JobTracer::new(
                s.clone(),
                camera(scene, s),
                layout.to_domain_tree(),
                layout.epsilon(),
                &counts,
                TILE,
            );
            match &tags {
                Some(tags) => t.with_pass_tags(tags.clone()),
                None => t,
            }
        })
        .collect();

    let mut film = Film::new(s.width, s.height);
    let mut rays = [0u64; 6];
    let mut credit: BTreeMap<u32, Credit> = BTreeMap::new();
    let mut queues: HashMap<u32, Vec<RayRecord>> = HashMap::new();
    let mut pass_films: Vec<Film> = passes
        .iter()
        .map(|_| Film::new(s.width, s.height))
        .collect();
    let tile_refs = TileRef::all(&TileGrid::new(s.width, s.height, TILE), TILE_CREDIT);
    assert!(!tile_refs.is_empty());
    // What is dealt before the rays are traded to the end: one pass at a time, or all.
    let rounds: Vec<&[std::ops::Range<u32>]> = if ahead {
        vec![passes]
    } else {
        passes.chunks(1).collect()
    };
    for round in rounds {
        credit.clear();
        let mut absorb = |out: Outbox, queues: &mut HashMap<u32, Vec<RayRecord>>| {
            for (key, v) in out.sums {
                film.add_fixed(key as u32, v);
                if ahead {
                    let (pass, pixel) = split_sum_key(key);
                    pass_films[pass as usize].add_fixed(pixel, v);
                }
            }
            for (t, c) in out.credits {
                let sum = credit.entry(t).or_default();
                *sum = sum.checked_add(c).expect("no tile's credit overflows");
            }
            for (k, n) in out.traced.iter().enumerate() {
                rays[k] += n;
            }
            film.nonfinite += out.nonfinite;
            for (d, mut r) in out.rays {
                assert!(r.tickets.is_empty(), "no tickets without ray caches");
                queues.entry(d).or_default().append(&mut r.rays);
            }
            assert!(out.lookups.is_empty(), "no lookups without ray caches");
        };

        // The tiles as the coordinator deals them (dispatch::image_tiles), at this size.
        for samples in round {
            for (i, t) in tile_refs.iter().enumerate() {
                let t = &t.in_pass(samples.clone());
                let w = &tracers[i % workers as usize];
                let mine = &held[i % workers as usize];
                // Camera rays in two ranges, as a worker generating them lazily would.
                let total = t.camera_rays(s.spp);
                let half = total / 2;
                let mut out = Outbox::default();
                w.camera_rays(t, 0, half, mine, &mut out).unwrap();
                w.camera_rays(t, half, total - half, mine, &mut out)
                    .unwrap();
                absorb(out, &mut queues);
            }
        }
        // Trade rays until none is left, in an order that depends on `scramble`.
        let mut step = scramble;
        loop {
            let mut pending: Vec<u32> = queues
                .iter()
                .filter(|(_, v)| !v.is_empty())
                .map(|(d, _)| *d)
                .collect();
            if pending.is_empty() {
                break;
            }
            pending.sort_unstable();
            step = step
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let d = pending[(step >> 33) as usize % pending.len()];
            let q = queues.get_mut(&d).unwrap();
            let take = q.len().min(1 + (step >> 40) as usize % 300);
            let batch: Vec<RayRecord> = q.drain(q.len() - take..).collect();
            let mut out = Outbox::default();
            let w = owner(d) as usize;
            tracers[w]
                .trace_batch(d, &batch, &[], &held[w], &mut out)
                .unwrap();
            absorb(out, &mut queues);
        }
        // Each tile's credit of each pass comes back whole, under the pass's tag.
        for (k, samples) in round.iter().enumerate() {
            for t in &tile_refs {
                let key = if ahead {
                    tile_key(t.index, k as u32)
                } else {
                    t.index
                };
                assert_eq!(
                    credit.get(&key).copied(),
                    Some(TILE_CREDIT),
                    "tile {} credit, pass {samples:?}",
                    t.index
                );
            }
        }
        assert_eq!(credit.len(), tile_refs.len() * round.len(), "no other key");
    }
    Distributed {
        film,
        rays,
        pass_films,
    }
}

fn reference(scene: &Scene, s: &RenderSettings) -> (Film, [u64; 6]) {
    let integrator = Integrator::new(scene, camera(scene, s), s.clone());
    let accel = Accel::build(&scene.mesh);
    let out = render::render(&integrator, &accel, 1, &|_, _| {}).unwrap();
    (out.film, out.rays.0)
}

fn check(scene_name: &str, kinds: &[IntegratorKind], spp: u32) {
    let scene = dray_scene::load(scene_name).unwrap();
    for &kind in kinds {
        let s = settings(&scene, kind, 40, 30, spp);
        let (film, rays) = reference(&scene, &s);
        assert!(rays.iter().sum::<u64>() > 0);
        // One domain too: `dray render`'s embedded worker, whose camera rays take the
        // tracer's routing-free path (`trace_tree`).
        for spec in [
            LayoutSpec::Kd(6),
            LayoutSpec::GridCount(8),
            LayoutSpec::Kd(1),
        ] {
            for workers in [1u32, 2, 4] {
                let d = distributed(&scene, &s, &spec, workers, workers as u64 * 31 + 5);
                assert_eq!(
                    d.rays, rays,
                    "{scene_name} {kind:?} {spec:?} {workers} workers: ray counts"
                );
                assert!(
                    d.film == film,
                    "{scene_name} {kind:?} {spec:?} {workers} workers: image differs"
                );
            }
        }
    }
}

/// Progressive passes (each dealt and finished before the next) give the one-pass
/// image bit for bit, and so does the single-process driver's own passes.
#[test]
fn passes_give_the_same_bits_as_one_pass() {
    use dray_core::passes::Passes;
    let scene = dray_scene::load("cornell:glass").unwrap();
    let s = settings(&scene, IntegratorKind::Path, 40, 30, 7);
    let (film, rays) = reference(&scene, &s);
    let layout = DomainLayout::for_source(&scene, &LayoutSpec::Kd(4)).unwrap();
    let package = MemoryPackage::with_layout(scene.clone(), layout.clone()).unwrap();
    let source = memory_domains(Arc::new(package), &s);
    for cut in [Passes::Doubling, Passes::Every(3), Passes::Every(1)] {
        let passes = cut.ranges(s.spp);
        assert!(passes.len() > 1);
        let d = distributed_with(&scene, &s, &layout, 3, 17, source.as_ref(), &passes, false);
        assert_eq!(d.rays, rays, "{cut:?}: ray counts");
        assert!(d.film == film, "{cut:?}: the image differs from one pass");
        // Every pass traced at once, ahead of the ones before it (workers tracing passes
        // ahead): the same image, and each pass's results tagged with their pass.
        let ahead = distributed_with(&scene, &s, &layout, 3, 17, source.as_ref(), &passes, true);
        assert_eq!(ahead.rays, rays, "{cut:?} ahead: ray counts");
        assert!(ahead.film == film, "{cut:?} ahead: the image differs");
        let integrator = Integrator::new(&scene, camera(&scene, &s), s.clone());
        let accel = Accel::build(&scene.mesh);
        let seen = std::sync::Mutex::new(Vec::new());
        let out = render::render_passes(
            &integrator,
            &accel,
            2,
            &passes,
            None,
            &|_, _| {},
            &|f: &Film, k| seen.lock().unwrap().push((k, f.clone())),
            &std::sync::atomic::AtomicBool::new(false),
        )
        .unwrap();
        assert!(
            out.film == film,
            "{cut:?}: render_passes differs from one pass"
        );
        let seen = seen.into_inner().unwrap();
        assert_eq!(seen.len(), passes.len(), "one image per pass");
        assert!(seen.last().unwrap().1 == film);
        // The passes' tagged sums add up to each pass image.
        let mut upto = Film::new(s.width, s.height);
        for (k, pass) in ahead.pass_films.iter().enumerate() {
            for p in 0..s.width * s.height {
                upto.add_fixed(p, pass.sum_fixed(p));
            }
            assert!(upto == seen[k].1, "{cut:?} ahead: pass {k}'s image");
        }
        // Each pass adds light: the first image is not the last.
        assert!(seen[0].1 != film);
    }
}

#[test]
fn cornell_every_integrator_matches_one_bvh() {
    check(
        "cornell",
        &[
            IntegratorKind::Path,
            IntegratorKind::Raycast,
            IntegratorKind::Primary,
            IntegratorKind::Ao,
        ],
        4,
    );
}

#[test]
fn glass_and_mirror_match_one_bvh() {
    check(
        "cornell:glass",
        &[IntegratorKind::Whitted, IntegratorKind::Path],
        3,
    );
    check("cornell:mirror", &[IntegratorKind::Whitted], 2);
}

#[test]
fn triangle_soup_and_city_match_one_bvh() {
    check("soup:2000", &[IntegratorKind::Path], 2);
    check("city:3", &[IntegratorKind::Raycast], 2);
}

/// Workers that load their domains and the emitters from a package on disk trace the
/// same image as those holding them in memory, and as one BVH.
#[test]
fn a_package_on_disk_gives_the_same_image() {
    let scene = dray_scene::load("cornell:glass").unwrap();
    let s = settings(&scene, IntegratorKind::Path, 32, 24, 2);
    let (film, _) = reference(&scene, &s);
    let dir = std::env::temp_dir().join(format!("dray-tracer-pkg-{}", std::process::id()));
    let spec = LayoutSpec::Kd(5);
    write_scene_package(&dir, &scene, &spec).unwrap();
    let package = open_package(&dir).unwrap();
    assert!(
        package.manifest().emitters.is_some(),
        "cornell has an area light"
    );
    let layout = package.layout().clone();
    for owned in [vec![0u32, 3], vec![1], vec![0, 1, 2, 3, 4]] {
        let a = load_resident(&package, &owned).unwrap();
        let b = resident_in_memory(&scene, &layout, &owned).unwrap();
        assert_eq!(a.global_ids, b.global_ids, "{owned:?}");
        assert!(a.scene.mesh == b.scene.mesh, "{owned:?}");
    }
    let source = package_domains(open_package(&dir).unwrap(), &s).unwrap();
    let all = 0..s.spp;
    let d = distributed_with(
        &scene,
        &s,
        &layout,
        3,
        11,
        source.as_ref(),
        std::slice::from_ref(&all),
        false,
    );
    let _ = std::fs::remove_dir_all(&dir);
    assert!(d.film == film, "image from the package differs");
}

/// A tile that reaches past the image is an error naming it, not rays for pixels of
/// the next row (or beyond the image): the rays a tile makes are not checked one by one.
#[test]
fn a_tile_past_the_image_is_an_error() {
    let scene = dray_scene::load("cornell").unwrap();
    let s = settings(&scene, IntegratorKind::Path, 40, 30, 1);
    let layout = DomainLayout::for_source(&scene, &LayoutSpec::Kd(1)).unwrap();
    let tracer = JobTracer::new(
        s.clone(),
        camera(&scene, &s),
        layout.to_domain_tree(),
        layout.epsilon(),
        &[scene.mesh.indices.len() as u64],
        TILE,
    );
    let held: HashMap<u32, Arc<LoadedDomain>> = HashMap::new();
    for (x0, y0, width, height) in [(32, 0, 16, 16), (0, 16, 16, 16), (u32::MAX, 0, 2, 2)] {
        let tile = TileRef {
            index: 0,
            x0,
            y0,
            width,
            height,
            credit: TILE_CREDIT,
            coarse: false,
            first_sample: 0,
            samples: 0,
        };
        let mut out = Outbox::default();
        let err = tracer
            .camera_rays(&tile, 0, 4, &held, &mut out)
            .expect_err("a tile past the image was traced");
        let message = err.to_string();
        assert!(
            message.contains("is not inside the 40x30 image"),
            "{message}"
        );
        assert!(out.is_empty(), "rays were made for a bad tile");
    }
}
