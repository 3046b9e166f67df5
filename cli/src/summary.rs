//! The end-of-run summary: a table on the terminal and the `--stats` JSON.

use std::collections::BTreeMap;
use std::time::Duration;

use dray_core::display::Display;
use dray_core::integrator::{RayKind, RenderSettings};
use dray_core::render::{RayCounts, RenderOutput};
use dray_core::scene::Scene;
use dray_net::traffic::TrafficKind;
use dray_proto::v1::{JobStats, PhmStats, RayCacheStats, TrafficStats};
use serde::Serialize;

#[derive(Serialize, Debug)]
pub struct Summary {
    pub scene: String,
    pub triangles: usize,
    pub degenerate_triangles_dropped: u64,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub integrator: &'static str,
    pub max_depth: u32,
    pub seed: u64,
    pub environment: [f32; 3],
    pub effects: Vec<&'static str>,
    pub rays: BTreeMap<&'static str, u64>,
    pub rays_total: u64,
    pub threads: usize,
    /// Spatial domains the scene was cut into (1 = one BVH).
    pub domains: u32,
    pub load_time_s: f64,
    pub build_time_s: f64,
    /// True when `build_time_s` is the workers' domain loads (read plus BVH build) summed
    /// over workers, which may exceed the wall time; false for one process's BVH build.
    pub build_summed_over_workers: bool,
    pub render_time_s: f64,
    pub wall_time_s: f64,
    pub mrays_per_s: f64,
    pub nonfinite_contributions: u64,
    /// Pixels brighter than the film represents, read as its bound (docs/numerics.md
    /// "The film").
    pub saturated_pixels: u64,
    /// Contributions clamped to the film's largest; counted by the tile renderer
    /// (`--workers 0`) only, absent on actors.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub clamped_contributions: Option<u64>,
    /// Contributions of indirect light scaled down by `--clamp-indirect` (0 without it).
    pub clamped_indirect: u64,
    /// Adaptive sampling (`--noise-threshold`): tiles that stopped before the last
    /// pass, and the samples per pixel they did not take, summed over their pixels (0
    /// without it).
    pub tiles_stopped: u32,
    pub samples_saved: u64,
    pub warnings: Vec<String>,
    /// How the job was scheduled on workers, and what that cost.
    #[serde(flatten)]
    pub scheduling: Scheduling,
    /// What the ray caches did; absent when the job had none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ray_cache: Option<RayCacheSummary>,
    /// What the hit maps did; absent when the job had none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub phm: Option<PhmSummary>,
    /// How the 8-bit image was exposed and tone-mapped; absent until it is written.
    #[serde(flatten)]
    pub display: Option<DisplaySummary>,
}

/// The display transform the 8-bit image got, as the `--stats` JSON spells it.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct DisplaySummary {
    /// `--exposure`: "auto" or the stops given.
    pub exposure: String,
    /// The exposure applied, in stops (the one chosen, with `auto`).
    pub exposure_stops: f32,
    /// `--tonemap`.
    pub tonemap: &'static str,
}

impl DisplaySummary {
    pub fn of(d: Display, stops: f32) -> DisplaySummary {
        DisplaySummary {
            exposure: d.exposure.to_string(),
            exposure_stops: stops,
            tonemap: d.tonemap.name(),
        }
    }

    /// "exposure -12.41 EV (auto), tone curve agx".
    pub fn line(&self) -> String {
        let how = if self.exposure == "auto" {
            " (auto)"
        } else {
            ""
        };
        format!(
            "exposure {:.2} EV{how}, tone curve {}",
            self.exposure_stops, self.tonemap
        )
    }
}

/// A job's hit-map statistics (`JobStats.phm`), as the `--stats` JSON spells them.
#[derive(Serialize, Debug, Clone, Copy, PartialEq)]
pub struct PhmSummary {
    /// Rays that asked a map.
    pub lookups: u64,
    /// Rays that skipped a domain (predicted miss), occlusion rays answered as occluded
    /// (predicted hit).
    pub rays_skipped: u64,
    pub rays_occluded: u64,
    /// `shade`: rays answered with a cell's averaged shading (predicted hit), and the
    /// probes whose radiance the cells learned.
    pub rays_shaded: u64,
    pub shading_learned: u64,
    /// Rays traced to learn, and outcomes reported back.
    pub probes: u64,
    pub outcomes: u64,
    /// Sender placement: outcomes applied to other workers' copies of the maps by
    /// merges (one per copy reached).
    pub outcomes_merged: u64,
    /// Cells decided as hits and as misses when the job ended, of all cells (of every
    /// copy, under sender placement).
    pub cells_decided_hit: u64,
    pub cells_decided_miss: u64,
    pub cells: u64,
    /// The maps' memory, every copy: `cells` times the bytes of a dense cell
    /// (`dray_cache::phm::BYTES_PER_CELL`), an upper estimate (a map that never learned
    /// holds none).
    pub map_bytes: u64,
    /// Rays not sent to another worker because a map answered or skipped them.
    pub rays_not_sent: u64,
    pub bytes_not_sent: u64,
    /// `bytes_not_sent` less the traffic of lookups, answers, map outcomes and merges (negative
    /// when the maps cost more bytes than they saved).
    pub bytes_not_sent_net: i64,
}

impl PhmSummary {
    /// The summary of a job's statistics; None when it had no hit maps.
    pub fn of(s: &JobStats) -> Option<PhmSummary> {
        s.phm.as_ref().map(|p: &PhmStats| PhmSummary {
            lookups: p.lookups,
            rays_skipped: p.rays_skipped,
            rays_occluded: p.rays_occluded,
            rays_shaded: p.rays_shaded,
            shading_learned: p.shading_learned,
            probes: p.probes,
            outcomes: p.outcomes,
            outcomes_merged: p.outcomes_merged,
            cells_decided_hit: p.cells_decided_hit,
            cells_decided_miss: p.cells_decided_miss,
            cells: p.cells,
            map_bytes: p.cells.saturating_mul(dray_cache::phm::BYTES_PER_CELL),
            rays_not_sent: p.rays_not_sent,
            bytes_not_sent: p.bytes_not_sent,
            bytes_not_sent_net: p.bytes_not_sent_net,
        })
    }

    /// The line of the human summary, without a label.
    pub fn line(&self) -> String {
        format!(
            "{} lookups: {} skipped, {} occluded, {} probes; cells decided {} hit, {} miss of {}; {} rays not sent",
            self.lookups,
            self.rays_skipped,
            self.rays_occluded,
            self.probes,
            self.cells_decided_hit,
            self.cells_decided_miss,
            self.cells,
            self.rays_not_sent
        )
    }
}

/// A job's ray-cache statistics (`JobStats.ray_cache`), as the `--stats` JSON of
/// `dray render` and `dray submit` spells them, with the hit ratios worked out.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct RayCacheSummary {
    /// Lookups and hits on outer walls (the scene bounds); ratio = hits / lookups (0
    /// without lookups).
    pub outer_lookups: u64,
    pub outer_hits: u64,
    pub outer_hit_ratio: f64,
    /// The same on inner walls (between domains).
    pub inner_lookups: u64,
    pub inner_hits: u64,
    pub inner_hit_ratio: f64,
    /// Hits over lookups on every wall, outer and inner: the total hit ratio Little 2011
    /// reports (0 without lookups).
    pub hit_ratio: f64,
    /// Seconds the coarse pass took (`JobStats.coarse_seconds`; 0 without one).
    pub coarse_seconds: f64,
    /// The most memory the caches' entries took in one process, bytes, estimated
    /// (`JobStats.cache_bytes_per_process`).
    pub bytes_per_process: u64,
    /// Rays a cache answered that would have gone to another worker, and their bytes.
    pub rays_not_sent: u64,
    pub bytes_not_sent: u64,
    /// `bytes_not_sent` less the traffic of lookups, answers, ticket returns and entry
    /// copies (negative when the caches cost more bytes than they saved).
    pub bytes_not_sent_net: i64,
    /// Tickets opened by misses, closed when their credit came back, closed with their
    /// radiance stored, and still open when the job ended.
    pub tickets_opened: u64,
    pub tickets_closed: u64,
    pub tickets_stored: u64,
    pub tickets_open: u64,
    /// Rays of the coarse pass.
    pub coarse_rays: u64,
    /// Rays that went past an unreachable cache host (traced exactly).
    pub rays_bypassed: u64,
    /// Bytes of lookups and ticket returns sent to cache hosts.
    pub cache_bytes: u64,
    /// Cache hosts lost during the job.
    pub lost_hosts: Vec<String>,
    /// Entries in the caches at the end, radiance not stored for a full store, misses
    /// refused a ticket, ticket returns refused (non-zero is a bug), rays whose
    /// crossing could not be placed on their wall.
    pub entries: u64,
    pub entries_dropped: u64,
    pub tickets_refused: u64,
    pub returns_rejected: u64,
    pub lookups_skipped: u64,
}

fn ratio(hits: u64, lookups: u64) -> f64 {
    if lookups == 0 {
        0.0
    } else {
        hits as f64 / lookups as f64
    }
}

impl RayCacheSummary {
    /// The summary of a job's statistics; None when it had no ray caches.
    pub fn of(s: &JobStats) -> Option<RayCacheSummary> {
        s.ray_cache.as_ref().map(|r| RayCacheSummary {
            coarse_seconds: s.coarse_seconds,
            bytes_per_process: s.cache_bytes_per_process,
            ..RayCacheSummary::from_stats(r)
        })
    }

    fn from_stats(r: &RayCacheStats) -> RayCacheSummary {
        RayCacheSummary {
            hit_ratio: ratio(
                r.outer_hits.saturating_add(r.inner_hits),
                r.outer_lookups.saturating_add(r.inner_lookups),
            ),
            coarse_seconds: 0.0,
            bytes_per_process: 0,
            outer_lookups: r.outer_lookups,
            outer_hits: r.outer_hits,
            outer_hit_ratio: ratio(r.outer_hits, r.outer_lookups),
            inner_lookups: r.inner_lookups,
            inner_hits: r.inner_hits,
            inner_hit_ratio: ratio(r.inner_hits, r.inner_lookups),
            rays_not_sent: r.rays_not_sent,
            bytes_not_sent: r.bytes_not_sent,
            bytes_not_sent_net: r.bytes_not_sent_net,
            tickets_opened: r.tickets_opened,
            tickets_closed: r.tickets_closed,
            tickets_stored: r.tickets_stored,
            tickets_open: r.tickets_open,
            coarse_rays: r.coarse_rays,
            rays_bypassed: r.rays_bypassed,
            cache_bytes: r.cache_bytes,
            lost_hosts: r.lost_hosts.clone(),
            entries: r.entries,
            entries_dropped: r.entries_dropped,
            tickets_refused: r.tickets_refused,
            returns_rejected: r.returns_rejected,
            lookups_skipped: r.lookups_skipped,
        }
    }

    /// The lines of the human summary, without a label.
    pub fn lines(&self) -> [String; 3] {
        let lost = if self.lost_hosts.is_empty() {
            "none".to_string()
        } else {
            self.lost_hosts.join(", ")
        };
        [
            format!(
                "outer walls {} hits of {} lookups ({:.1}%), inner walls {} of {} ({:.1}%), \
                 all {:.1}%; coarse pass {:.3} s; {} bytes per process",
                self.outer_hits,
                self.outer_lookups,
                100.0 * self.outer_hit_ratio,
                self.inner_hits,
                self.inner_lookups,
                100.0 * self.inner_hit_ratio,
                100.0 * self.hit_ratio,
                self.coarse_seconds,
                self.bytes_per_process
            ),
            format!(
                "{} rays ({} bytes) not sent; tickets opened {}, closed {}, stored {}, open {}",
                self.rays_not_sent,
                self.bytes_not_sent,
                self.tickets_opened,
                self.tickets_closed,
                self.tickets_stored,
                self.tickets_open
            ),
            format!(
                "{} rays bypassed, {} bytes to cache hosts, lost hosts: {lost}",
                self.rays_bypassed, self.cache_bytes
            ),
        ]
    }
}

/// The scheduling metrics of a job on workers (GetJob's `JobStats`), as the `--stats`
/// JSON of `dray render` and `dray submit` spells them.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct Scheduling {
    /// "replicated", "image-plane", "domain" or "dynamic"; "none" when no worker took
    /// part (the reference renderer, or a coordinator rendering in its own process).
    pub schedule: String,
    /// Why the job ran with `schedule` (JobStats.placement: what `auto` found, or that
    /// the job forced it); empty when no worker took part.
    pub placement: String,
    /// Domain loads by workers (a domain loaded twice counts twice).
    pub domain_loads: u64,
    /// Domains workers found resident from an earlier or concurrent job of the same
    /// package, instead of loading them.
    pub domains_warm: u64,
    /// Seconds workers spent loading domains, summed over workers.
    pub domain_load_seconds: f64,
    /// Domains evicted to stay within workers' memory budgets.
    pub evictions: u64,
    /// Rays sent from one worker to another (each hop counts).
    pub rays_exchanged: u64,
    /// Rays a worker forwarded because it no longer owned their domain.
    pub rays_forwarded: u64,
    /// Ray batches' payload bytes sent between actors.
    pub ray_bytes_sent: u64,
    /// Bytes between processes by kind, and in total.
    pub traffic: TrafficSummary,
    /// The workers' reports to the coordinator (`JobStats.reports`): messages, bytes,
    /// and the bytes of AOV sums among them.
    pub reports: ReportSummary,
    /// CPU seconds (user + system) of the processes that ran the job, once per process
    /// (render.proto `JobStats.cpu_seconds`); 0 without workers.
    pub cpu_seconds: f64,
    /// Most rays queued at one worker at any moment.
    pub queue_peak: u64,
    /// Rounds of the scheduler.
    pub scheduler_rounds: u32,
    /// The routing table's last version (1: never changed).
    pub routing_version: u64,
    /// Tiles traced again after a worker was lost.
    pub tiles_retraced: u32,
    /// Replicated schedule: tiles dealt after their pass or attempt started, to workers
    /// that had room or joined (JobStats.tiles_dealt_later).
    pub tiles_dealt_later: u64,
    /// Passes the workers could trace ahead of the job's (JobStats.passes_ahead; 0:
    /// each pass waited for the one before).
    pub passes_ahead: u32,
    /// Per worker of the job.
    pub workers: Vec<WorkerSummary>,
    /// Workers that took part (0: no actors).
    #[serde(skip)]
    pub worker_count: u32,
}

/// Bytes between processes by kind (`JobStats.traffic`; docs/caches.md "Statistics"
/// says what each covers), as the `--stats` JSON spells them: each kind under its name
/// ([`TrafficKind::name`]), in the proto's order, then `total` (the sum of the kinds)
/// and `cache_messages` (cache-link messages, both directions; ray batches not counted).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TrafficSummary(TrafficStats);

impl TrafficSummary {
    pub fn of(t: &TrafficStats) -> TrafficSummary {
        TrafficSummary(*t)
    }

    /// The sum of the kinds.
    pub fn total(&self) -> u64 {
        self.0.total
    }
}

impl Serialize for TrafficSummary {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        let mut m = s.serialize_map(Some(TrafficKind::COUNT + 2))?;
        for k in TrafficKind::ALL {
            m.serialize_entry(k.name(), &k.get(&self.0))?;
        }
        m.serialize_entry("total", &self.0.total)?;
        m.serialize_entry("cache_messages", &self.0.cache_messages)?;
        m.end()
    }
}

/// The workers' reports to the coordinator (`JobStats.reports`), as the `--stats`
/// JSON spells them: zero without workers.
#[derive(Serialize, Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReportSummary {
    pub messages: u64,
    pub bytes: u64,
    /// The part of `bytes` that carries AOV sums (`--aov`).
    pub aov_bytes: u64,
}

/// One worker's share of a job.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct WorkerSummary {
    pub worker_id: String,
    pub domain_loads: u64,
    pub domains_warm: u64,
    pub domain_load_seconds: f64,
    pub evictions: u64,
    pub idle_seconds: f64,
    pub queue_peak: u64,
    pub rays_traced: u64,
}

impl Scheduling {
    /// No workers, no scheduling: every count zero.
    pub fn none() -> Scheduling {
        Scheduling {
            schedule: "none".into(),
            placement: String::new(),
            domain_loads: 0,
            domains_warm: 0,
            domain_load_seconds: 0.0,
            evictions: 0,
            rays_exchanged: 0,
            rays_forwarded: 0,
            ray_bytes_sent: 0,
            traffic: TrafficSummary::default(),
            reports: ReportSummary::default(),
            cpu_seconds: 0.0,
            queue_peak: 0,
            scheduler_rounds: 0,
            routing_version: 0,
            tiles_retraced: 0,
            tiles_dealt_later: 0,
            passes_ahead: 0,
            workers: Vec::new(),
            worker_count: 0,
        }
    }

    /// The metrics of a job from its statistics.
    pub fn of(s: &JobStats) -> Scheduling {
        let schedule = if s.workers == 0 || s.schedule.is_empty() {
            "none".to_string()
        } else {
            s.schedule.clone()
        };
        Scheduling {
            schedule,
            placement: s.placement.clone(),
            domain_loads: s.domain_loads,
            domains_warm: s.domains_warm,
            domain_load_seconds: s.domain_load_seconds,
            evictions: s.evictions,
            rays_exchanged: s.rays_exchanged,
            rays_forwarded: s.rays_forwarded,
            ray_bytes_sent: s.ray_bytes_sent,
            traffic: TrafficSummary::of(&s.traffic.unwrap_or_default()),
            reports: s
                .reports
                .map_or_else(ReportSummary::default, |r| ReportSummary {
                    messages: r.messages,
                    bytes: r.bytes,
                    aov_bytes: r.aov_bytes,
                }),
            cpu_seconds: s.cpu_seconds,
            queue_peak: s.queue_peak,
            scheduler_rounds: s.scheduler_rounds,
            routing_version: s.routing_version,
            tiles_retraced: s.tiles_retried,
            tiles_dealt_later: s.tiles_dealt_later,
            passes_ahead: s.passes_ahead,
            workers: s
                .workers_detail
                .iter()
                .map(|w| WorkerSummary {
                    worker_id: w.worker_id.clone(),
                    domain_loads: w.domain_loads,
                    domains_warm: w.domains_warm,
                    domain_load_seconds: w.domain_load_seconds,
                    evictions: w.evictions,
                    idle_seconds: w.idle_seconds,
                    queue_peak: w.queue_peak,
                    rays_traced: w.rays_traced,
                })
                .collect(),
            worker_count: s.workers,
        }
    }

    /// Why the schedule, for the human summary, when the job ran on workers and the
    /// coordinator said.
    pub fn placement_line(&self) -> Option<&str> {
        (self.worker_count > 0 && !self.placement.is_empty()).then_some(self.placement.as_str())
    }

    /// One line for the human summary, when the job ran on workers.
    pub fn line(&self) -> Option<String> {
        (self.worker_count > 0).then(|| {
            format!(
                "{} on {} worker{}: domain loads {} ({:.3} s){}, evictions {}, rays exchanged {}, \
                 tiles re-traced {}{}; {} bytes between processes, {:.3} CPU s",
                self.schedule,
                self.worker_count,
                if self.worker_count == 1 { "" } else { "s" },
                self.domain_loads,
                self.domain_load_seconds,
                if self.domains_warm > 0 {
                    format!(", {} found resident", self.domains_warm)
                } else {
                    String::new()
                },
                self.evictions,
                self.rays_exchanged,
                self.tiles_retraced,
                if self.passes_ahead > 0 {
                    format!(", passes traced up to {} ahead", self.passes_ahead)
                } else {
                    String::new()
                },
                self.traffic.total(),
                self.cpu_seconds
            )
        })
    }
}

/// Rays by kind from the protocol's counts.
pub fn ray_counts(r: &dray_proto::v1::RayCounts) -> RayCounts {
    RayCounts(r.by_kind())
}

/// Rays by kind under the names the `--stats` JSON uses.
pub fn rays_by_name(rays: &RayCounts) -> BTreeMap<&'static str, u64> {
    RayKind::ALL
        .iter()
        .map(|k| (k.name(), rays.get(*k)))
        .collect()
}

/// What the summary says about the scene, taken before the scene is handed to the
/// in-process coordinator.
#[derive(Clone, Debug)]
pub struct SceneFacts {
    pub triangles: usize,
    pub degenerate_triangles: u64,
    pub warnings: Vec<String>,
}

impl SceneFacts {
    pub fn of(scene: &Scene) -> SceneFacts {
        SceneFacts {
            triangles: scene.mesh.triangle_count(),
            degenerate_triangles: scene.stats.degenerate_triangles,
            warnings: scene.stats.warnings.clone(),
        }
    }
}

impl Summary {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        spec: &str,
        scene: &SceneFacts,
        s: &RenderSettings,
        out: &RenderOutput,
        threads: usize,
        load: Duration,
        build: Duration,
        wall: Duration,
    ) -> Summary {
        let rays = rays_by_name(&out.rays);
        let secs = out.render_time.as_secs_f64();
        Summary {
            scene: spec.to_string(),
            triangles: scene.triangles,
            degenerate_triangles_dropped: scene.degenerate_triangles,
            width: s.width,
            height: s.height,
            spp: s.spp,
            integrator: s.integrator.name(),
            max_depth: s.max_depth,
            seed: s.seed,
            environment: s.environment.to_array(),
            effects: s.effects.names(),
            rays,
            rays_total: out.rays.total(),
            threads,
            domains: 1,
            load_time_s: load.as_secs_f64(),
            build_time_s: build.as_secs_f64(),
            build_summed_over_workers: false,
            render_time_s: secs,
            wall_time_s: wall.as_secs_f64(),
            mrays_per_s: if secs > 0.0 {
                out.rays.total() as f64 / secs / 1e6
            } else {
                0.0
            },
            nonfinite_contributions: out.film.nonfinite,
            saturated_pixels: out.film.saturated(),
            clamped_contributions: None,
            clamped_indirect: 0,
            tiles_stopped: 0,
            samples_saved: 0,
            warnings: scene.warnings.clone(),
            scheduling: Scheduling::none(),
            ray_cache: None,
            phm: None,
            display: None,
        }
    }
}

pub fn print_summary(s: &Summary) {
    let effects = if s.effects.is_empty() {
        "none".to_string()
    } else {
        s.effects.join(", ")
    };
    eprintln!("scene        {}", s.scene);
    eprintln!(
        "triangles    {} ({} degenerate dropped)",
        s.triangles, s.degenerate_triangles_dropped
    );
    eprintln!(
        "image        {}x{}, {} spp, {} (max depth {})",
        s.width, s.height, s.spp, s.integrator, s.max_depth
    );
    eprintln!("effects      {effects}");
    eprintln!("rays         {} total", s.rays_total);
    for (k, n) in &s.rays {
        if *n > 0 {
            eprintln!("  {k:<18} {n}");
        }
    }
    let build = if s.build_summed_over_workers {
        format!(
            "domain loads {:.3}s (read + bvh, summed over workers)",
            s.build_time_s
        )
    } else {
        format!("bvh {:.3}s", s.build_time_s)
    };
    eprintln!(
        "time         load {:.3}s, {build}, render {:.3}s, wall {:.3}s",
        s.load_time_s, s.render_time_s, s.wall_time_s
    );
    eprintln!(
        "throughput   {:.2} Mrays/s on {} threads",
        s.mrays_per_s, s.threads
    );
    if let Some(line) = s.scheduling.line() {
        eprintln!("schedule     {line}");
    }
    if let Some(why) = s.scheduling.placement_line() {
        eprintln!("placement    {why}");
    }
    if let Some(rc) = &s.ray_cache {
        for (i, line) in rc.lines().iter().enumerate() {
            eprintln!(
                "{}{line}",
                if i == 0 {
                    "ray caches   "
                } else {
                    "             "
                }
            );
        }
    }
    if let Some(p) = &s.phm {
        eprintln!("hit maps     {}", p.line());
    }
    if let Some(p) = &s.display {
        eprintln!("display      {}", p.line());
    }
    if s.nonfinite_contributions > 0 {
        eprintln!(
            "non-finite   {} contributions dropped",
            s.nonfinite_contributions
        );
    }
    if let Some(n) = s.clamped_contributions.filter(|&n| n > 0) {
        eprintln!("clamped      {n} contributions above the film's largest");
    }
    if s.clamped_indirect > 0 {
        eprintln!(
            "clamped      {} indirect contributions (--clamp-indirect)",
            s.clamped_indirect
        );
    }
    if s.tiles_stopped > 0 {
        eprintln!(
            "adaptive     {} tiles stopped early, {} samples saved (--noise-threshold)",
            s.tiles_stopped, s.samples_saved
        );
    }
    if s.saturated_pixels > 0 {
        eprintln!(
            "saturated    {} pixels brighter than the film holds",
            s.saturated_pixels
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_proto::v1::WorkerJobStats;

    #[test]
    fn scheduling_from_job_stats() {
        let stats = JobStats {
            workers: 2,
            schedule: "domain".into(),
            placement: "domain: forced by the job (--schedule domain)".into(),
            domain_loads: 9,
            domain_load_seconds: 0.5,
            evictions: 1,
            rays_exchanged: 40,
            tiles_retried: 3,
            routing_version: 2,
            traffic: Some(TrafficStats {
                rays: 2560,
                lookups: 64,
                total: 2624,
                ..TrafficStats::default()
            }),
            cpu_seconds: 1.25,
            reports: Some(dray_proto::v1::ReportStats {
                messages: 3,
                bytes: 900,
                aov_bytes: 600,
            }),
            workers_detail: vec![WorkerJobStats {
                worker_id: "w1".into(),
                domain_loads: 9,
                ..WorkerJobStats::default()
            }],
            ..JobStats::default()
        };
        let s = Scheduling::of(&stats);
        assert_eq!(s.schedule, "domain");
        assert_eq!(
            s.placement_line(),
            Some("domain: forced by the job (--schedule domain)")
        );
        assert_eq!(s.tiles_retraced, 3);
        assert_eq!(s.workers[0].worker_id, "w1");
        let json = serde_json::to_value(&s).expect("json");
        assert_eq!(json["tiles_retraced"], 3);
        assert_eq!(json["traffic"]["total"], 2624);
        assert_eq!(json["traffic"]["lookups"], 64);
        assert_eq!(json["cpu_seconds"], 1.25);
        assert_eq!(
            (
                &json["reports"]["messages"],
                &json["reports"]["bytes"],
                &json["reports"]["aov_bytes"]
            ),
            (&3.into(), &900.into(), &600.into())
        );
        assert_eq!(json["workers"][0]["domain_loads"], 9);
        assert!(json.get("worker_count").is_none());
        assert_eq!(
            s.line().as_deref(),
            Some(
                "domain on 2 workers: domain loads 9 (0.500 s), evictions 1, rays exchanged 40, \
                 tiles re-traced 3; 2624 bytes between processes, 1.250 CPU s"
            )
        );
        // A job the coordinator rendered itself, and the reference renderer.
        let alone = Scheduling::of(&JobStats::default());
        assert_eq!(alone.schedule, "none");
        assert_eq!(alone.line(), None);
        assert_eq!(alone.placement_line(), None);
        assert_eq!(Scheduling::none(), alone);
    }

    #[test]
    fn ray_cache_summary_from_job_stats() {
        assert_eq!(RayCacheSummary::of(&JobStats::default()), None);
        let stats = JobStats {
            ray_cache: Some(RayCacheStats {
                outer_lookups: 1000,
                outer_hits: 920,
                inner_lookups: 1000,
                inner_hits: 80,
                rays_not_sent: 10,
                bytes_not_sent: 640,
                tickets_opened: 80,
                tickets_closed: 79,
                tickets_stored: 70,
                tickets_open: 1,
                rays_bypassed: 3,
                lost_hosts: vec!["http://h:1".into()],
                ..Default::default()
            }),
            coarse_seconds: 1.5,
            cache_bytes_per_process: 2600,
            ..JobStats::default()
        };
        let rc = RayCacheSummary::of(&stats).expect("caches");
        assert_eq!(
            (rc.outer_hit_ratio, rc.inner_hit_ratio, rc.hit_ratio),
            (0.92, 0.08, 0.5)
        );
        assert_eq!((rc.coarse_seconds, rc.bytes_per_process), (1.5, 2600));
        let json = serde_json::to_value(&rc).expect("json");
        for key in [
            "outer_lookups",
            "outer_hits",
            "outer_hit_ratio",
            "inner_lookups",
            "inner_hits",
            "inner_hit_ratio",
            "hit_ratio",
            "coarse_seconds",
            "bytes_per_process",
            "rays_not_sent",
            "bytes_not_sent",
            "tickets_opened",
            "tickets_closed",
            "tickets_stored",
            "tickets_open",
            "rays_bypassed",
            "lost_hosts",
        ] {
            assert!(json.get(key).is_some(), "{key} missing from {json}");
        }
        assert_eq!(json["outer_hit_ratio"], 0.92);
        assert_eq!(json["lost_hosts"][0], "http://h:1");
        let lines = rc.lines();
        assert_eq!(
            lines[0],
            "outer walls 920 hits of 1000 lookups (92.0%), inner walls 80 of 1000 (8.0%), \
             all 50.0%; coarse pass 1.500 s; 2600 bytes per process"
        );
        assert!(lines[1].starts_with("10 rays (640 bytes) not sent; tickets opened 80"));
        assert!(lines[2].ends_with("lost hosts: http://h:1"), "{}", lines[2]);
    }
}
