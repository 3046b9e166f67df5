//! Ray caches on domain walls end to end (docs/caches.md), with real cache actors: in-process
//! cache hosts beside `dray render`'s workers, and a stand-alone `dray cache` process in
//! a cluster of processes.
//!
//! - Caches that never answer (`radius=0`) still look every wall-crossing ray up and
//!   ticket it; the image is then the reference renderer's, bit for bit, on 1, 2 and 4
//!   workers, and every ticket opened closes exactly once.
//! - A coarse pass fills the caches before the image's rays look them up; with
//!   `fill=false` the image is then the same bits on every run, worker count and
//!   placement (sender replicas or remote walls), in one process (where a worker
//!   reaches its own cache host through mailboxes) and across processes (gRPC).
//! - Hit maps whose thresholds never decide give the reference bits (shading ones too,
//!   whose probes carry tickets); maps that decide skip domains and occlude shadow
//!   rays, and say so; maps that shade answer camera and diffuse rays at predicted hits
//!   with averaged radiance, finite and near the exact image, for fewer bytes.
//! - Consistent maps come closer to the exact image as the sample count grows.
//! - A cache host killed mid-job: rays go past its walls, the job completes with the
//!   reference bits (nothing was answered) and names the lost host.

mod common;
mod support;

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::Stdio;
use std::sync::{Arc, Mutex};

use serde_json::Value;
use support::{Proc, capture_stderr, dray, eventually};

/// A limit that only catches hangs.
const HANG_SECS: f64 = 240.0;

const SCENE: &str = "cornell:glass";

fn flags(integrator: &str) -> Vec<&str> {
    vec![
        "--width",
        "40",
        "--height",
        "30",
        "--spp",
        "2",
        "--seed",
        "3",
        "--max-depth",
        "5",
        "--domains",
        "8",
        "--integrator",
        integrator,
    ]
}

fn u64_of(v: &Value, key: &str) -> u64 {
    v[key]
        .as_u64()
        .unwrap_or_else(|| panic!("no unsigned {key:?} in {v}"))
}

/// The reference image and stats: `--workers 0`, no actors, no caches.
fn reference(dir: &Path, tag: &str, integrator: &str) -> (Vec<u8>, Value) {
    let r = common::render(
        dir,
        tag,
        SCENE,
        &[&flags(integrator)[..], &["--workers", "0"]].concat(),
    );
    assert!(r.ok, "{tag}: {}", r.stderr);
    (
        std::fs::read(r.png.expect("png")).expect("read png"),
        r.stats.expect("reference stats"),
    )
}

/// Every ticket opened was closed once, none is left open, nothing was refused.
fn check_tickets(rc: &Value, what: &str) {
    let opened = u64_of(rc, "tickets_opened");
    assert!(opened > 0, "{what}: no ticket was opened: {rc}");
    assert_eq!(
        u64_of(rc, "tickets_closed"),
        opened,
        "{what}: tickets opened and closed differ: {rc}"
    );
    assert_eq!(u64_of(rc, "tickets_open"), 0, "{what}: {rc}");
    assert!(
        u64_of(rc, "tickets_stored") <= opened,
        "{what}: more stored than opened: {rc}"
    );
}

#[test]
fn caches_that_never_answer_give_the_reference_bits_and_close_every_ticket() {
    let dir = common::tmp("caches-radius-zero");
    for integrator in ["whitted", "path"] {
        let (want, want_stats) = reference(&dir, &format!("ref-{integrator}"), integrator);
        for workers in [1, 2, 4] {
            let what = format!("{integrator} on {workers} workers, radius=0");
            let n = workers.to_string();
            let r = common::render(
                &dir,
                "cached",
                SCENE,
                &[
                    &flags(integrator)[..],
                    &["--workers", &n, "--ray-cache", "radius=0"],
                ]
                .concat(),
            );
            assert!(r.ok, "{what}: {}", r.stderr);
            let png = std::fs::read(r.png.expect("png")).expect("read png");
            assert!(png == want, "{what}: the image differs from the reference");
            let stats = r.stats.expect("stats");
            assert_eq!(stats["rays"], want_stats["rays"], "{what}: rays by kind");
            let rc = &stats["ray_cache"];
            let lookups = u64_of(rc, "outer_lookups") + u64_of(rc, "inner_lookups");
            assert!(lookups > 0, "{what}: no lookups: {rc}");
            assert_eq!(
                u64_of(rc, "outer_hits") + u64_of(rc, "inner_hits"),
                0,
                "{what}: {rc}"
            );
            check_tickets(rc, &what);
            // Nothing answered, so every closed ticket could store (8 domains, all walls
            // inside the scene's own light: radiance is finite and positive).
            assert!(
                u64_of(rc, "tickets_stored") > 0,
                "{what}: nothing stored: {rc}"
            );
            assert_eq!(u64_of(rc, "rays_bypassed"), 0, "{what}: {rc}");
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

fn render_ok(dir: &Path, tag: &str, args: &[&str], what: &str) -> (Vec<u8>, Value) {
    let r = common::render(dir, tag, SCENE, args);
    assert!(r.ok, "{what}: {}", r.stderr);
    (
        std::fs::read(r.png.expect("png")).expect("read png"),
        r.stats.expect("stats"),
    )
}

#[test]
fn a_coarse_pass_fills_the_caches_and_without_fill_every_run_gives_the_same_bits() {
    let dir = common::tmp("caches-coarse");
    let (want, _) = reference(&dir, "ref", "whitted");
    // The box is about 555 units wide: coarse crossings are ~20 units apart on the walls.
    let frozen = "radius=15,angle-deg=20,coarse=24,fill=false";
    let remote = format!("{frozen},placement=remote");
    let mut first: Option<Vec<u8>> = None;
    for (run, workers, cache) in [
        (0, "2", frozen),
        (1, "2", frozen),
        (2, "1", frozen),
        (3, "3", frozen),
        (4, "3", remote.as_str()),
        (5, "1", remote.as_str()),
        // A coarse pass freezes the caches by default.
        (6, "2", "radius=15,angle-deg=20,coarse=24"),
    ] {
        let what = format!("run {run} on {workers} workers with --ray-cache {cache}");
        let (png, stats) = render_ok(
            &dir,
            &format!("coarse-{run}"),
            &[
                &flags("whitted")[..],
                &["--workers", workers, "--ray-cache", cache],
            ]
            .concat(),
            &what,
        );
        let rc = &stats["ray_cache"];
        assert_eq!(u64_of(rc, "coarse_rays"), 24 * 24, "{what}: {rc}");
        let hits = u64_of(rc, "outer_hits") + u64_of(rc, "inner_hits");
        assert!(
            hits > 0,
            "{what}: the coarse pass filled nothing that answered: {rc}"
        );
        check_tickets(rc, &what);
        assert!(png != want, "{what}: answers changed nothing in the image");
        match &first {
            None => first = Some(png),
            Some(f) => assert!(*f == png, "{what}: not the same bits as run 0"),
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// `coarse-sampling=random` (Little 2011's randomized coarse positions): each coarse
/// ray crosses its coarse pixel at a point drawn from the job's seed, so the frozen
/// caches, and the image, are the same bits on 1, 2 and 3 workers, and not the image of
/// rays through the centres (other points were sampled). The statistics Little reports
/// are there: the total hit ratio, the coarse pass's time and the caches' memory per
/// process (sender placement: every worker's replica holds every entry).
#[test]
fn randomized_coarse_positions_give_the_same_bits_on_any_worker_count() {
    let dir = common::tmp("caches-coarse-random");
    let centres = "radius=15,angle-deg=20,coarse=24,fill=false";
    let random = format!("{centres},coarse-sampling=random");
    let (at_centres, _) = render_ok(
        &dir,
        "centres",
        &[
            &flags("whitted")[..],
            &["--workers", "2", "--ray-cache", centres],
        ]
        .concat(),
        "centres on 2 workers",
    );
    let mut first: Option<Vec<u8>> = None;
    for workers in ["1", "2", "3"] {
        let what = format!("random coarse positions on {workers} workers");
        let (png, stats) = render_ok(
            &dir,
            &format!("random-{workers}"),
            &[
                &flags("whitted")[..],
                &["--workers", workers, "--ray-cache", &random],
            ]
            .concat(),
            &what,
        );
        let rc = &stats["ray_cache"];
        assert_eq!(u64_of(rc, "coarse_rays"), 24 * 24, "{what}: {rc}");
        check_tickets(rc, &what);
        let hits = u64_of(rc, "outer_hits") + u64_of(rc, "inner_hits");
        let lookups = u64_of(rc, "outer_lookups") + u64_of(rc, "inner_lookups");
        assert!(hits > 0, "{what}: nothing answered: {rc}");
        assert_eq!(
            rc["hit_ratio"].as_f64(),
            Some(hits as f64 / lookups as f64),
            "{what}: {rc}"
        );
        assert!(
            rc["coarse_seconds"].as_f64().is_some_and(|t| t > 0.0),
            "{what}: {rc}"
        );
        let n: u64 = workers.parse().expect("a number");
        assert_eq!(
            u64_of(rc, "bytes_per_process") * n,
            u64_of(rc, "entries") * dray_cache::store::ENTRY_BYTES,
            "{what}: each replica holds every entry: {rc}"
        );
        assert!(u64_of(rc, "entries") > 0, "{what}: {rc}");
        assert!(
            png != at_centres,
            "{what}: the same image as rays through the centres"
        );
        match &first {
            None => first = Some(png),
            Some(f) => assert!(*f == png, "{what}: not the same bits as on 1 worker"),
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn hit_maps_that_never_decide_give_the_reference_bits() {
    let dir = common::tmp("phm-never");
    let (want, want_stats) = reference(&dir, "ref", "path");
    for workers in ["1", "3"] {
        let what = format!("path on {workers} workers with undecided maps");
        let (png, stats) = render_ok(
            &dir,
            "phm",
            &[
                &flags("path")[..],
                &["--workers", workers, "--phm", "miss=0,hit=1"],
            ]
            .concat(),
            &what,
        );
        assert!(png == want, "{what}: the image differs from the reference");
        assert_eq!(stats["rays"], want_stats["rays"], "{what}: rays by kind");
        let p = &stats["phm"];
        assert!(u64_of(p, "lookups") > 0, "{what}: no map was asked: {p}");
        assert_eq!(
            u64_of(p, "rays_skipped") + u64_of(p, "rays_occluded"),
            0,
            "{what}: {p}"
        );
        assert!(u64_of(p, "probes") > 0, "{what}: {p}");
        assert_eq!(
            u64_of(p, "cells_decided_hit") + u64_of(p, "cells_decided_miss"),
            0,
            "{what}: {p}"
        );
        assert!(
            stats.get("ray_cache").is_none(),
            "{what}: no ray caches asked for"
        );
    }
    // Shading maps that never decide answer nothing (only cells that predict a hit
    // shade, or ask for tickets to learn how): the image is the reference's, bit for bit.
    let what = "path on 3 workers with undecided shading maps";
    let (png, stats) = render_ok(
        &dir,
        "phm-shade",
        &[
            &flags("path")[..],
            &[
                "--workers",
                "3",
                "--phm",
                "miss=0,hit=1,kinds=camera+diffuse+shadow,placement=remote,shade=true",
            ],
        ]
        .concat(),
        what,
    );
    assert!(png == want, "{what}: the image differs from the reference");
    assert_eq!(stats["rays"], want_stats["rays"], "{what}: rays by kind");
    let p = &stats["phm"];
    assert_eq!(u64_of(p, "rays_shaded"), 0, "{what}: {p}");
    assert_eq!(u64_of(p, "shading_learned"), 0, "{what}: {p}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Bolstad's averaged shading (`shade=true`): camera and diffuse rays at cells that
/// predict a hit are answered with the mean radiance the cells' probes brought back, so
/// they are neither traced on nor sent; the image stays finite and close to the exact
/// one. (Bytes are printed, not compared: on this scene shading answers a few percent
/// of those rays, and the difference is within the run-to-run spread.)
#[test]
fn shading_hit_maps_answer_predicted_hits_with_the_radiance_their_probes_returned() {
    let dir = common::tmp("phm-shade");
    let job = [
        "--width",
        "64",
        "--height",
        "48",
        "--spp",
        "16",
        "--seed",
        "7",
        "--schedule",
        "domain",
        "--max-depth",
        "4",
        "--domains",
        "8",
        "--integrator",
        "path",
    ];
    let exact = common::render(
        &dir,
        "exact",
        "cornell",
        &[&job[..], &["--workers", "0"]].concat(),
    );
    assert!(exact.ok, "exact: {}", exact.stderr);
    let exact = exact.png.expect("exact png");
    let maps = "kinds=camera+diffuse+shadow,prior=1,miss=0.2,hit=0.8,reprobe=0.05,placement=remote";
    let run = |tag: &str, phm: &str| {
        let exr = dir.join(format!("{tag}.exr"));
        let exr_arg = exr.to_string_lossy().into_owned();
        let r = common::render(
            &dir,
            tag,
            "cornell",
            &[
                &job[..],
                &["--workers", "4", "--phm", phm, "--exr", &exr_arg],
            ]
            .concat(),
        );
        assert!(r.ok, "{tag}: {}", r.stderr);
        let stats = r.stats.expect("stats");
        let exr = std::fs::read(&exr).expect("exr");
        (r.png.expect("png"), exr, stats)
    };
    let (_, _, plain) = run("plain", maps);
    let (png, exr, shaded) = run("shade", &format!("{maps},shade=true"));
    let (p, q) = (&plain["phm"], &shaded["phm"]);
    assert_eq!(u64_of(p, "rays_shaded"), 0, "without shade: {p}");
    assert!(u64_of(q, "rays_shaded") > 0, "nothing was shaded: {q}");
    assert!(u64_of(q, "shading_learned") > 0, "{q}");
    let bytes = |s: &Value| u64_of(&s["traffic"], "total");
    for (name, values) in common::exr_channels(&exr) {
        assert!(
            values.iter().all(|v| v.is_finite()),
            "channel {name} has a value that is not finite"
        );
    }
    let error = rmse(&png, &exact);
    eprintln!(
        "shade: {} rays shaded, {} bytes against {} without, RMSE {error:.4} against exact",
        u64_of(q, "rays_shaded"),
        bytes(&shaded),
        bytes(&plain)
    );
    assert!(error < 0.2, "RMSE against the exact image: {error}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn hit_maps_that_decide_skip_domains_and_occlude_shadow_rays() {
    let dir = common::tmp("phm-decide");
    let job = [
        "--width",
        "64",
        "--height",
        "48",
        "--spp",
        "4",
        "--seed",
        "3",
        "--max-depth",
        "4",
        "--domains",
        "8",
        "--integrator",
        "path",
    ];
    let what = "path on 2 workers with eager maps";
    // Predictions that happen to be right change no pixel, so the image is not
    // compared here: what the maps cost in error is the sweep's to measure.
    let (_png, stats) = render_ok(
        &dir,
        "phm",
        &[
            &job[..],
            &[
                "--workers",
                "2",
                "--phm",
                "prior=1,miss=0.2,hit=0.8,reprobe=0.05",
            ],
        ]
        .concat(),
        what,
    );
    let p = &stats["phm"];
    assert!(
        u64_of(p, "rays_skipped") + u64_of(p, "rays_occluded") > 0,
        "{what}: the maps answered nothing: {p}"
    );
    assert!(
        u64_of(p, "cells_decided_hit") + u64_of(p, "cells_decided_miss") > 0,
        "{what}: no cell decided: {p}"
    );
    assert!(u64_of(p, "outcomes") > 0, "{what}: {p}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Root-mean-square difference of two PNGs' 8-bit values, scaled to [0, 1].
fn rmse(a: &Path, b: &Path) -> f64 {
    let (a, b) = (common::rgb(a), common::rgb(b));
    assert_eq!(a.dimensions(), b.dimensions(), "image sizes differ");
    let n = a.as_raw().len() as f64;
    let sum: f64 = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(&x, &y)| {
            let d = (f64::from(x) - f64::from(y)) / 255.0;
            d * d
        })
        .sum();
    (sum / n).sqrt()
}

/// Consistent maps keep probing decided cells, so as the sample count grows a job's
/// image comes closer to the converged exact one: the error against a many-sample
/// exact render falls. (A cell whose true hit rate lies below `miss` stays decided and
/// keeps its small bias; docs/caches.md says so.)
#[test]
fn consistent_hit_maps_come_closer_to_the_exact_image_as_samples_grow() {
    let dir = common::tmp("phm-converges");
    let job = |spp: &'static str| {
        vec![
            "--width",
            "48",
            "--height",
            "36",
            "--spp",
            spp,
            "--seed",
            "5",
            "--max-depth",
            "4",
            "--domains",
            "8",
            "--integrator",
            "path",
        ]
    };
    let exact = common::render(
        &dir,
        "exact",
        SCENE,
        &[&job("256")[..], &["--workers", "0"]].concat(),
    );
    assert!(exact.ok, "exact: {}", exact.stderr);
    let exact = exact.png.expect("exact png");
    let mut errors = Vec::new();
    for spp in ["2", "32"] {
        let what = format!("consistent maps at {spp} spp");
        let r = common::render(
            &dir,
            &format!("phm-{spp}"),
            SCENE,
            &[
                &job(spp)[..],
                &[
                    "--workers",
                    "2",
                    "--phm",
                    "prior=1,miss=0.2,hit=0.8,reprobe=0.2,mode=consistent",
                ],
            ]
            .concat(),
        );
        assert!(r.ok, "{what}: {}", r.stderr);
        let stats = r.stats.expect("stats");
        let p = &stats["phm"];
        assert!(
            u64_of(p, "rays_skipped") + u64_of(p, "rays_occluded") > 0,
            "{what}: the maps answered nothing, so this test shows nothing: {p}"
        );
        errors.push(rmse(&r.png.expect("png"), &exact));
    }
    eprintln!(
        "RMSE against the 256-spp exact image: 2 spp {:.4}, 32 spp {:.4}",
        errors[0], errors[1]
    );
    assert!(
        errors[1] < errors[0] * 0.75,
        "the error did not fall as samples grew: {errors:?}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// The frozen-cache job of the test above on a cluster of processes, where rays,
/// lookups (remote placement), ticket returns and replicas' entries (sender placement)
/// cross between processes over gRPC: the same bits as one process.
#[test]
fn frozen_caches_give_the_same_bits_across_processes_and_placements() {
    let dir = common::tmp("caches-processes");
    let frozen = "radius=15,angle-deg=20,coarse=24,fill=false";
    let (want, _) = render_ok(
        &dir,
        "embedded",
        &[
            &flags("whitted")[..],
            &["--workers", "2", "--ray-cache", frozen],
        ]
        .concat(),
        "in one process",
    );
    let mut cmd = dray();
    cmd.args(["coordinator", "--listen", "127.0.0.1:0", "--scene-root"])
        .arg(&dir)
        .env("DRAY_LOG", "warn,dray_coordinator=info");
    let (_coordinator, addr, coordinator_log) = spawn_with_address(cmd);
    let url = format!("http://{addr}");
    let workers = start_workers(&url, 3, &[], &coordinator_log);
    for placement in ["sender", "remote"] {
        let what = format!("3 worker processes, placement={placement}");
        let cache = format!("{frozen},placement={placement}");
        let (got, json) = submit(
            &dir,
            &addr,
            placement,
            &[&flags("whitted")[..], &["--ray-cache", &cache]].concat(),
            &what,
        );
        let rc = &json["ray_cache"];
        check_tickets(rc, &what);
        assert!(
            u64_of(rc, "outer_hits") + u64_of(rc, "inner_hits") > 0,
            "{what}: nothing answered: {rc}"
        );
        check_traffic(&json, placement, &what);
        assert!(got == want, "{what}: not the same bits as one process");
    }
    drop(workers);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The job's bytes between processes (`traffic` in `--stats`): every kind present, the
/// total their sum, rays exchanged between the worker processes; under sender
/// placement every lookup is answered in the sender's own process (no lookup or answer
/// bytes) and replicas copy entries, under remote placement lookups cross processes
/// and nothing is copied. The caches' net saving is what they saved less that traffic.
fn check_traffic(json: &Value, placement: &str, what: &str) {
    let t = &json["traffic"];
    let kinds = [
        "rays",
        "lookups",
        "answers",
        "ticket_returns",
        "entry_copies",
        "map_outcomes",
        "map_merges",
    ];
    let sum: u64 = kinds.iter().map(|k| u64_of(t, k)).sum();
    assert_eq!(u64_of(t, "total"), sum, "{what}: total is not the sum: {t}");
    assert!(
        u64_of(t, "rays") > 0,
        "{what}: no rays between processes: {t}"
    );
    assert_eq!(
        u64_of(t, "map_outcomes") + u64_of(t, "map_merges"),
        0,
        "{what}: no hit maps: {t}"
    );
    match placement {
        "sender" => {
            assert_eq!(
                (u64_of(t, "lookups"), u64_of(t, "answers")),
                (0, 0),
                "{what}: lookups left their process: {t}"
            );
            assert!(
                u64_of(t, "entry_copies") > 0,
                "{what}: no replica copies: {t}"
            );
        }
        _ => {
            assert!(u64_of(t, "lookups") > 0, "{what}: no lookup traffic: {t}");
            assert!(u64_of(t, "answers") > 0, "{what}: no answer traffic: {t}");
            assert_eq!(u64_of(t, "entry_copies"), 0, "{what}: copies: {t}");
        }
    }
    let rc = &json["ray_cache"];
    let cost = ["lookups", "answers", "ticket_returns", "entry_copies"]
        .iter()
        .map(|k| u64_of(t, k) as i64)
        .sum::<i64>();
    assert_eq!(
        rc["bytes_not_sent_net"].as_i64(),
        Some(u64_of(rc, "bytes_not_sent") as i64 - cost),
        "{what}: {rc} {t}"
    );
}

/// Hit maps on a cluster of processes, under both placements. Maps that never decide
/// give the reference bits either way. Under sender placement (Bolstad's replicated
/// maps) every worker consults its own copy, so no lookup crosses processes, and the
/// outcomes reach the other copies in merges (`merge=64`, so that there are several);
/// under remote placement the rays cross to the walls' hosts and nothing is merged.
/// Maps that decide skip rays under both placements.
#[test]
fn replicated_hit_maps_are_consulted_locally_and_merged_across_processes() {
    let dir = common::tmp("phm-processes");
    let (want, _) = reference(&dir, "ref", "path");
    let mut cmd = dray();
    cmd.args(["coordinator", "--listen", "127.0.0.1:0", "--scene-root"])
        .arg(&dir)
        .env("DRAY_LOG", "warn,dray_coordinator=info");
    let (_coordinator, addr, coordinator_log) = spawn_with_address(cmd);
    let url = format!("http://{addr}");
    let workers = start_workers(&url, 3, &[], &coordinator_log);
    let path = flags("path");
    let submit = |tag: &str, phm: &str, what: &str| {
        submit(
            &dir,
            &addr,
            tag,
            &[&path[..], &["--phm", phm]].concat(),
            what,
        )
    };
    for placement in ["sender", "remote"] {
        let what = format!("undecided maps on 3 worker processes, placement={placement}");
        let (png, json) = submit(
            &format!("never-{placement}"),
            &format!("miss=0,hit=1,merge=64,placement={placement}"),
            &what,
        );
        assert!(png == want, "{what}: the image differs from the reference");
        let (p, t) = (&json["phm"], &json["traffic"]);
        assert!(u64_of(p, "lookups") > 0, "{what}: no map was asked: {p}");
        assert!(u64_of(p, "probes") > 0, "{what}: {p}");
        let kinds = [
            "rays",
            "lookups",
            "answers",
            "ticket_returns",
            "entry_copies",
        ];
        let sum: u64 = kinds
            .iter()
            .chain(&["map_outcomes", "map_merges"])
            .map(|k| u64_of(t, k))
            .sum();
        assert_eq!(u64_of(t, "total"), sum, "{what}: total is not the sum: {t}");
        if placement == "sender" {
            assert_eq!(
                (u64_of(t, "lookups"), u64_of(t, "answers")),
                (0, 0),
                "{what}: lookups left their process: {t}"
            );
            assert!(u64_of(t, "map_merges") > 0, "{what}: no merges: {t}");
            // Each outcome reaches at most the two other copies (fewer when its
            // batch was still on the way as the job closed).
            let merged = u64_of(p, "outcomes_merged");
            assert!(
                merged > 0 && merged <= 2 * u64_of(p, "outcomes"),
                "{what}: {p}"
            );
        } else {
            assert!(u64_of(t, "lookups") > 0, "{what}: no lookup traffic: {t}");
            assert_eq!(u64_of(t, "map_merges"), 0, "{what}: merges: {t}");
            assert_eq!(u64_of(p, "outcomes_merged"), 0, "{what}: {p}");
        }
        let cost = ["lookups", "answers", "map_outcomes", "map_merges"]
            .iter()
            .map(|k| u64_of(t, k) as i64)
            .sum::<i64>();
        assert_eq!(
            p["bytes_not_sent_net"].as_i64(),
            Some(u64_of(p, "bytes_not_sent") as i64 - cost),
            "{what}: {p} {t}"
        );

        let what = format!("eager maps on 3 worker processes, placement={placement}");
        let (_png, json) = submit(
            &format!("eager-{placement}"),
            &format!("prior=1,miss=0.2,hit=0.8,reprobe=0.05,merge=64,placement={placement}"),
            &what,
        );
        let p = &json["phm"];
        assert!(
            u64_of(p, "rays_skipped") + u64_of(p, "rays_occluded") > 0,
            "{what}: the maps answered nothing: {p}"
        );
    }
    drop(workers);
    let _ = std::fs::remove_dir_all(&dir);
}

/// `dray submit SCENE ARGS` to the coordinator at `addr`, writing `TAG.png` and
/// `TAG.json` in `dir`: the image's bytes and the stats, once it succeeded.
fn submit(dir: &Path, addr: &str, tag: &str, args: &[&str], what: &str) -> (Vec<u8>, Value) {
    let png = dir.join(format!("{tag}.png"));
    let stats = dir.join(format!("{tag}.json"));
    let mut submit = dray();
    submit
        .args(["submit", "--coordinator", addr, SCENE])
        .args(args)
        .arg("--output")
        .arg(&png)
        .arg("--stats")
        .arg(&stats)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let mut submit = Proc::spawn(submit);
    let log = capture_stderr(&mut submit.child);
    let status = submit.wait_timeout(HANG_SECS);
    let out = log.after(status.is_some());
    let status = status.unwrap_or_else(|| panic!("HANG: {what}: {out}"));
    assert!(status.success(), "{what}: {out}");
    let json: Value =
        serde_json::from_slice(&std::fs::read(&stats).expect("read stats")).expect("stats json");
    (std::fs::read(&png).expect("read the job's png"), json)
}

/// `n` one-thread worker processes of the coordinator at `url` (with `extra` flags),
/// once its log says they registered.
fn start_workers(
    url: &str,
    n: usize,
    extra: &[&str],
    coordinator_log: &Arc<Mutex<String>>,
) -> Vec<Proc> {
    let workers: Vec<Proc> = (0..n)
        .map(|_| {
            let mut cmd = dray();
            cmd.args(["worker", "--coordinator", url, "--listen", "127.0.0.1:0"])
                .args(["--threads", "1"])
                .args(extra)
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(Stdio::null());
            Proc::spawn(cmd)
        })
        .collect();
    assert!(
        eventually(60.0, || text(coordinator_log)
            .matches("worker registered")
            .count()
            >= n),
        "the workers did not register: {}",
        text(coordinator_log)
    );
    workers
}

fn text(log: &Arc<Mutex<String>>) -> String {
    dray_sync::lock(log).clone()
}

/// A process whose first stdout line ends with its address.
fn spawn_with_address(mut cmd: std::process::Command) -> (Proc, String, support::Captured) {
    cmd.env("NO_COLOR", "1")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let mut p = Proc::spawn(cmd);
    let log = capture_stderr(&mut p.child);
    let mut first = String::new();
    BufReader::new(p.child.stdout.take().expect("stdout"))
        .read_line(&mut first)
        .expect("read the first line");
    let addr = first
        .trim()
        .rsplit(' ')
        .next()
        .filter(|a| a.contains(':'))
        .unwrap_or_else(|| panic!("no address in {first:?}"))
        .to_string();
    (p, addr, log)
}

#[test]
fn a_cache_host_killed_mid_job_is_bypassed_and_the_image_stays_exact() {
    let dir = common::tmp("caches-killed-host");
    // A job long enough to outlive the kill by far.
    let job: Vec<&str> = vec![
        "--width",
        "160",
        "--height",
        "120",
        "--spp",
        "8",
        "--seed",
        "3",
        "--max-depth",
        "5",
        "--domains",
        "8",
        "--integrator",
        "path",
    ];
    let want = {
        let r = common::render(
            &dir,
            "ref",
            SCENE,
            &[&job[..], &["--workers", "0"]].concat(),
        );
        assert!(r.ok, "reference: {}", r.stderr);
        std::fs::read(r.png.expect("png")).expect("read png")
    };

    let mut cmd = dray();
    cmd.args(["coordinator", "--listen", "127.0.0.1:0", "--scene-root"])
        .arg(&dir)
        .arg("--cache-hosts")
        .env("DRAY_LOG", "warn,dray_coordinator=info");
    let (_coordinator, addr, coordinator_log) = spawn_with_address(cmd);
    let url = format!("http://{addr}");
    let mut cmd = dray();
    cmd.args(["cache", "--coordinator", &url, "--listen", "127.0.0.1:0"])
        .env("DRAY_LOG", "info");
    let (cache, _cache_addr, cache_log) = spawn_with_address(cmd);
    let workers = start_workers(&url, 2, &["--no-cache-host"], &coordinator_log);

    let png = dir.join("job.png");
    let stats = dir.join("job.json");
    let mut submit = dray();
    submit
        .args(["submit", "--coordinator", &addr, SCENE])
        .args(&job)
        .args(["--ray-cache", "radius=0"])
        .arg("--output")
        .arg(&png)
        .arg("--stats")
        .arg(&stats)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let mut submit = Proc::spawn(submit);
    let submit_log = capture_stderr(&mut submit.child);
    // The job's walls are open on the stand-alone host: kill it.
    assert!(
        eventually(HANG_SECS, || text(&cache_log).contains("walls opened")),
        "the cache host never opened the job's walls: {}\n{}",
        text(&cache_log),
        text(&submit_log)
    );
    cache.signal(libc::SIGKILL);
    let status = submit.wait_timeout(HANG_SECS);
    let out = submit_log.after(status.is_some());
    let status = status.unwrap_or_else(|| panic!("HANG: dray submit did not finish: {out}"));
    assert!(
        status.success(),
        "the job failed with its cache host lost: {out}"
    );
    let got = std::fs::read(&png).expect("read the job's png");
    assert!(got == want, "the image differs from the reference");
    let json: Value =
        serde_json::from_slice(&std::fs::read(&stats).expect("read stats")).expect("stats json");
    let rc = &json["ray_cache"];
    assert!(
        rc["lost_hosts"].as_array().is_some_and(|h| !h.is_empty()),
        "the lost cache host is not named: {rc}"
    );
    assert!(
        u64_of(rc, "rays_bypassed") > 0,
        "no ray went past the dead host: {rc}"
    );
    drop(workers);
    let _ = std::fs::remove_dir_all(&dir);
}
