//! Bounds on what a coordinator sends a worker, checked before anything is sized by it.
//!
//! A worker trusts its coordinator to say what to trace, not to say how much memory to
//! take: one `JobSetup` with `domain_count = 0xFFFFFFFF` made a worker allocate a
//! per-domain table of 103 GB and abort (docs/security.md "Hardening, second round", item
//! 5). Every field that sizes
//! something (a table, a loop, an image, a string kept with the job) is held here to
//! the largest value a legitimate coordinator sends: the bounds of a job
//! ([`dray_cache::bounds`], the same definition that caps the coordinator's limits, so
//! nothing the coordinator accepts is refused here), or a generous bound where the
//! coordinator has none. A setup or routing table beyond them is refused with an error
//! naming the field and the bound; the job fails (reported to the coordinator) and the
//! worker goes on serving.
//!
//! The number of jobs a worker holds at once is bounded too ([`MAX_JOBS`], see
//! [`crate::jobs::Jobs::admit`]).

use dray_proto::v1::{JobSetup, RoutingTable};

pub use dray_cache::bounds::{
    MAX_AO_SAMPLES, MAX_COARSE, MAX_DEPTH, MAX_DOMAINS, MAX_PHM_DIRS, MAX_PHM_RES, MAX_SIDE,
    MAX_SPP, MAX_WORKER_JOBS as MAX_JOBS,
};

pub use dray_core::light_samples::MAX_LIGHT_SAMPLES;

/// Largest tile edge: a tile is never larger than the image.
pub const MAX_TILE_SIZE: u32 = MAX_SIDE;
/// Most workers and cache hosts a routing table may list (far beyond any cluster).
pub const MAX_TABLE_MEMBERS: usize = 4096;
/// Most routes in a routing table: every domain on 16 workers.
pub const MAX_ROUTES: usize = 16 * MAX_DOMAINS as usize;
/// Longest job id, package path, checksum, schedule name and trace-context entry the
/// worker keeps, in bytes.
pub const MAX_ID_BYTES: usize = 256;
pub const MAX_PATH_BYTES: usize = 4096;
/// Most effect names and trace-context entries.
pub const MAX_NAMES: usize = 64;

/// A field beyond its bound.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "job setup refused: {field} is {value}, beyond {bound} (a worker's bound on what a coordinator may send)"
)]
pub struct BoundError {
    /// The field, as the proto names it (`domain_count`, `spec.width`, `routing.routes`).
    pub field: &'static str,
    /// Its value (a length for lists and strings).
    pub value: u64,
    /// What it may be, e.g. "1..=65536".
    pub bound: String,
}

fn within(field: &'static str, value: u64, lo: u64, hi: u64) -> Result<(), BoundError> {
    if (lo..=hi).contains(&value) {
        Ok(())
    } else {
        Err(BoundError {
            field,
            value,
            bound: format!("{lo}..={hi}"),
        })
    }
}

fn at_most(field: &'static str, value: usize, hi: usize) -> Result<(), BoundError> {
    within(field, value as u64, 0, hi as u64)
}

/// Check every field of `setup` that sizes something on the worker (see the module
/// docs). Cheap: nothing is allocated.
pub fn check_setup(setup: &JobSetup) -> Result<(), BoundError> {
    at_most("job_id (bytes)", setup.job_id.len(), MAX_ID_BYTES)?;
    at_most(
        "package_path (bytes)",
        setup.package_path.len(),
        MAX_PATH_BYTES,
    )?;
    at_most(
        "package_checksum (bytes)",
        setup.package_checksum.len(),
        MAX_ID_BYTES,
    )?;
    at_most("schedule (bytes)", setup.schedule.len(), MAX_ID_BYTES)?;
    at_most("effects", setup.effects.len(), MAX_NAMES)?;
    for e in &setup.effects {
        at_most("effects[] (bytes)", e.len(), MAX_ID_BYTES)?;
    }
    at_most("trace_context", setup.trace_context.len(), MAX_NAMES)?;
    for (k, v) in &setup.trace_context {
        at_most(
            "trace_context[] (bytes)",
            k.len() + v.len(),
            MAX_ID_BYTES * 4,
        )?;
    }
    within(
        "domain_count",
        setup.domain_count.into(),
        1,
        MAX_DOMAINS.into(),
    )?;
    within("tile_size", setup.tile_size.into(), 1, MAX_TILE_SIZE.into())?;
    if let Some(spec) = &setup.spec {
        within("spec.width", spec.width.into(), 1, MAX_SIDE.into())?;
        within("spec.height", spec.height.into(), 1, MAX_SIDE.into())?;
        within("spec.spp", spec.spp.into(), 1, MAX_SPP.into())?;
        if let Some(d) = spec.max_depth {
            within("spec.max_depth", d.into(), 0, MAX_DEPTH.into())?;
        }
        if let Some(n) = spec.ao_samples {
            within("spec.ao_samples", n.into(), 0, MAX_AO_SAMPLES.into())?;
        }
        // Shadow rays per hit (a loop per light); core's bound, which tiles' credit is
        // sized for and the coordinator holds jobs to.
        if let Some(n) = spec.light_samples {
            within("spec.light_samples", n.into(), 1, MAX_LIGHT_SAMPLES.into())?;
        }
        if let Some(rc) = &spec.ray_cache {
            within(
                "spec.ray_cache.coarse",
                rc.coarse.into(),
                0,
                MAX_COARSE.into(),
            )?;
            at_most("spec.ray_cache.kinds (bytes)", rc.kinds.len(), MAX_ID_BYTES)?;
        }
        at_most(
            "spec.coarse_sampling (bytes)",
            spec.coarse_sampling.len(),
            MAX_ID_BYTES,
        )?;
        if let Some(p) = &spec.phm {
            if let Some(r) = p.res {
                within("spec.phm.res", r.into(), 1, MAX_PHM_RES.into())?;
            }
            if let Some(d) = p.dirs {
                within("spec.phm.dirs", d.into(), 1, MAX_PHM_DIRS.into())?;
            }
            at_most("spec.phm.kinds (bytes)", p.kinds.len(), MAX_ID_BYTES)?;
        }
    }
    if let Some(e) = &setup.env_map {
        at_most("env_map.path (bytes)", e.path.len(), MAX_PATH_BYTES)?;
        at_most("env_map.name (bytes)", e.name.len(), MAX_ID_BYTES)?;
        at_most("env_map.xxh3 (bytes)", e.xxh3.len(), MAX_ID_BYTES)?;
        within(
            "env_map.bytes",
            e.bytes,
            1,
            dray_core::env_map_file::MAX_ENV_MAP_FILE_BYTES,
        )?;
    }
    if let Some(t) = &setup.routing {
        check_routing(t, setup.domain_count)?;
    }
    Ok(())
}

/// Check a routing table of a job with `domains` domains (already bounded), in a setup
/// or sent later.
pub fn check_routing(table: &RoutingTable, domains: u32) -> Result<(), BoundError> {
    at_most("routing.workers", table.workers.len(), MAX_TABLE_MEMBERS)?;
    at_most(
        "routing.cache_hosts",
        table.cache_hosts.len(),
        MAX_TABLE_MEMBERS,
    )?;
    at_most("routing.routes", table.routes.len(), MAX_ROUTES)?;
    at_most(
        "routing.wall_hosts",
        table.wall_hosts.len(),
        6 * domains as usize,
    )?;
    for w in &table.workers {
        at_most(
            "routing.workers[] (bytes)",
            w.worker_id.len() + w.endpoint.len(),
            MAX_PATH_BYTES,
        )?;
    }
    for h in &table.cache_hosts {
        at_most(
            "routing.cache_hosts[] (bytes)",
            h.host_id.len() + h.endpoint.len(),
            MAX_PATH_BYTES,
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_proto::v1::{DomainRoute, JobSpec, PhmSettings, RayCacheSettings, WorkerEndpoint};

    fn setup() -> JobSetup {
        JobSetup {
            job_id: "job-1".into(),
            spec: Some(JobSpec {
                width: 640,
                height: 480,
                spp: 16,
                max_depth: Some(5),
                ao_samples: Some(16),
                ..Default::default()
            }),
            domain_count: 4,
            tile_size: 32,
            routing: Some(RoutingTable {
                workers: vec![WorkerEndpoint {
                    worker_id: "w1".into(),
                    endpoint: "http://127.0.0.1:1".into(),
                }],
                routes: (0..4)
                    .map(|d| DomainRoute {
                        domain: d,
                        worker_id: "w1".into(),
                    })
                    .collect(),
                ..Default::default()
            }),
            ..Default::default()
        }
    }

    fn refused(s: JobSetup, field: &str) {
        let e = check_setup(&s).unwrap_err();
        assert_eq!(e.field, field, "{e}");
        assert!(e.to_string().contains(field), "{e}");
    }

    #[test]
    fn a_setup_within_the_coordinators_limits_passes() {
        check_setup(&setup()).unwrap();
        let mut s = setup();
        let spec = s.spec.as_mut().unwrap();
        spec.width = MAX_SIDE;
        spec.height = MAX_SIDE;
        spec.spp = MAX_SPP;
        spec.light_samples = Some(MAX_LIGHT_SAMPLES);
        s.domain_count = MAX_DOMAINS;
        check_setup(&s).unwrap();
    }

    #[test]
    fn every_sizing_field_beyond_its_bound_is_refused_by_name() {
        let with = |f: &dyn Fn(&mut JobSetup)| {
            let mut s = setup();
            f(&mut s);
            s
        };
        // The attack: 0xFFFFFFFF domains made the worker allocate 103 GB and abort.
        let e = check_setup(&with(&|s| s.domain_count = u32::MAX)).unwrap_err();
        assert_eq!(e.value, u64::from(u32::MAX));
        assert!(e.to_string().contains("1..=65536"), "{e}");
        refused(with(&|s| s.domain_count = 0), "domain_count");
        refused(with(&|s| s.tile_size = 0), "tile_size");
        refused(with(&|s| s.tile_size = u32::MAX), "tile_size");
        let spec = |f: &dyn Fn(&mut JobSpec)| with(&|s| f(s.spec.as_mut().unwrap()));
        refused(spec(&|p| p.width = MAX_SIDE + 1), "spec.width");
        refused(spec(&|p| p.height = u32::MAX), "spec.height");
        refused(spec(&|p| p.spp = u32::MAX), "spec.spp");
        refused(spec(&|p| p.max_depth = Some(u32::MAX)), "spec.max_depth");
        refused(spec(&|p| p.ao_samples = Some(u32::MAX)), "spec.ao_samples");
        refused(spec(&|p| p.light_samples = Some(0)), "spec.light_samples");
        refused(
            spec(&|p| p.light_samples = Some(MAX_LIGHT_SAMPLES + 1)),
            "spec.light_samples",
        );
        refused(
            spec(&|p| {
                p.ray_cache = Some(RayCacheSettings {
                    coarse: u32::MAX,
                    ..Default::default()
                })
            }),
            "spec.ray_cache.coarse",
        );
        refused(
            spec(&|p| {
                p.phm = Some(PhmSettings {
                    res: Some(1 << 20),
                    ..Default::default()
                })
            }),
            "spec.phm.res",
        );
        refused(with(&|s| s.job_id = "j".repeat(1 << 20)), "job_id (bytes)");
        refused(
            with(&|s| s.package_path = "p".repeat(1 << 20)),
            "package_path (bytes)",
        );
        refused(
            with(&|s| s.effects = vec!["emission".into(); 1000]),
            "effects",
        );
        refused(
            with(&|s| s.routing.as_mut().unwrap().workers = vec![WorkerEndpoint::default(); 5000]),
            "routing.workers",
        );
        refused(
            with(&|s| s.routing.as_mut().unwrap().wall_hosts = vec![0; 25]),
            "routing.wall_hosts",
        );
    }
}
