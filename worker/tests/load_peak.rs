//! What a domain load really holds at its peak, against what the domain store reserves
//! for it ([`load_reserve`] of the domain's estimated resident size).
//!
//! The store makes room for the reserve before a load starts, so a worker's resident
//! domains plus the load in progress stay within its memory budget only if the load's
//! peak (the domain file as read, the merged mesh, the BVH builder's arrays and the
//! 8-wide collapse, all live at once for a moment) fits in the reserve. This test counts
//! every byte allocated and freed in the process (a counting global allocator: it is the
//! only test of this binary, so nothing else allocates while it measures) around the
//! worker's own load of each domain of a package on disk, the one `dray cluster` writes,
//! and fails if a load's peak passes the reserve or a loaded domain holds more than the
//! estimate the store counts it at.
//!
//! `DRAY_LOAD_PEAK_SCENE` and `DRAY_LOAD_PEAK_DOMAINS` measure another scene (for
//! example benches/passes.sh's, `grid:iso:gyroid:120:2x2x2` in 32 domains).

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicU64, Ordering};

use dray_core::integrator::{IntegratorKind, RenderSettings};
use dray_scene::partition::resident::{LOAD_PEAK_PERCENT, load_reserve};
use dray_scene::partition::{LayoutSpec, open_package, write_scene_package};
use dray_worker::plan::package_domains;

/// The system allocator, counting live bytes and their peak.
struct Counting;

static LIVE: AtomicU64 = AtomicU64::new(0);
static PEAK: AtomicU64 = AtomicU64::new(0);

fn grew(n: usize) {
    let now = LIVE.fetch_add(n as u64, Ordering::Relaxed) + n as u64;
    PEAK.fetch_max(now, Ordering::Relaxed);
}

fn shrank(n: usize) {
    LIVE.fetch_sub(n as u64, Ordering::Relaxed);
}

// SAFETY: every call is forwarded to the system allocator with its own arguments; the
// counters only observe sizes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's contract is System's.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            grew(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's contract is System's.
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            grew(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: the caller's contract is System's.
        unsafe { System.dealloc(ptr, layout) };
        shrank(layout.size());
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: the caller's contract is System's.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            grew(new_size);
            shrank(layout.size());
        }
        p
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Only the emission effect matters to a load (whether emitters light); the rest is
/// what a path-traced job would send.
fn settings(scene: &dray_core::scene::Scene) -> RenderSettings {
    let environment = dray_scene::effects::default_environment(scene);
    RenderSettings {
        width: 64,
        height: 64,
        spp: 1,
        integrator: IntegratorKind::Path,
        max_depth: 2,
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

#[test]
fn a_domain_load_peaks_within_its_reserve() {
    let spec = std::env::var("DRAY_LOAD_PEAK_SCENE")
        .unwrap_or_else(|_| "grid:iso:gyroid:48:2x2x2".to_string());
    let domains: u32 = std::env::var("DRAY_LOAD_PEAK_DOMAINS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(16);
    let scene = dray_scene::load(&spec).unwrap_or_else(|e| panic!("{spec}: {e}"));
    let s = settings(&scene);
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("package");
    write_scene_package(&dir, &scene, &LayoutSpec::Kd(domains)).unwrap();
    drop(scene);
    let source = package_domains(open_package(&dir).unwrap(), &s).unwrap();
    let count = open_package(&dir).unwrap().domain_count();
    assert_eq!(count, domains);

    let mut worst_peak = 0f64;
    let mut worst_held = 0f64;
    let mut over = Vec::new();
    println!("domain estimate held peak peak/estimate");
    for d in 0..count {
        let estimate = source.estimate_bytes(d);
        let base = LIVE.load(Ordering::Relaxed);
        PEAK.store(base, Ordering::Relaxed);
        let loaded = source.load(d).unwrap();
        let peak = PEAK.load(Ordering::Relaxed) - base;
        let held = LIVE.load(Ordering::Relaxed).saturating_sub(base);
        assert!(estimate > 0, "domain {d} is empty");
        assert_eq!(loaded.bytes, estimate, "domain {d}: counted size");
        let ratio = peak as f64 / estimate as f64;
        println!("{d} {estimate} {held} {peak} {ratio:.3}");
        worst_peak = worst_peak.max(ratio);
        if peak > load_reserve(estimate) {
            over.push(d);
        }
        worst_held = worst_held.max(held as f64 / estimate as f64);
        drop(loaded);
    }
    println!("worst peak/estimate {worst_peak:.3}, held/estimate {worst_held:.3}");
    assert!(
        over.is_empty(),
        "domains {over:?} peaked above their reserve ({LOAD_PEAK_PERCENT}% of the \
         estimate): {worst_peak:.3} times at worst"
    );
    assert!(
        worst_held <= 1.0,
        "a loaded domain holds {worst_held:.3} times the estimate it is counted at"
    );
}
