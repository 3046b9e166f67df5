//! The JSON the dashboard's endpoints speak: small serde types made from (and, for a
//! submission, into) the RenderService's protobuf messages, which have no serde of
//! their own. Field names are snake_case; durations are seconds; times are Unix
//! seconds; states drop their `JOB_STATE_` prefix (`"RUNNING"`).

use dray_proto::v1::camera_spec::Orbit;
use dray_proto::v1::{
    CameraSpec, EnvMapSpec, Job, JobEventKind, JobProgress, JobSpec, JobState, JobStats,
    LightingSpec, ListJobsResponse, ListWorkersResponse, Rgb, SunSpec, Vec3, WorkerJobStats,
    WorkerStatus,
};
use serde::{Deserialize, Serialize};

/// One job as a row of the jobs table: what it renders and how far it is. No
/// statistics: 100 of these go out every second to every open dashboard.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct JobSummary {
    pub id: String,
    pub label: String,
    pub scene: String,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub integrator: String,
    pub schedule: String,
    pub domains: u32,
    #[serde(flatten)]
    pub progress: Progress,
    /// When SubmitJob accepted it.
    pub submitted_at: Option<i64>,
    /// When it reached a terminal state.
    pub finished_at: Option<i64>,
    /// The job group it is a frame of (`Job.group`), and which frame; absent for a lone
    /// job.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub group: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frame: Option<u32>,
    /// The moment of the animation it renders (`JobSpec.time`), in seconds.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub time: Option<f64>,
}

/// A job's progress (WatchJob's JobProgress), with its statistics when the message
/// has them.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct Progress {
    pub state: &'static str,
    pub tiles_done: u32,
    pub tiles_total: u32,
    pub rays_traced: u64,
    pub rays_in_flight: u64,
    pub elapsed_s: Option<f64>,
    pub eta_s: Option<f64>,
    pub error: String,
    /// Samples per pixel of the passes complete so far.
    pub samples_done: u32,
    pub passes_done: u32,
    pub passes_total: u32,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stats: Option<Stats>,
}

/// A page of jobs, newest first.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct JobPage {
    pub jobs: Vec<JobSummary>,
    /// The token of the next page; empty on the last.
    pub next_page_token: String,
}

/// One job with its statistics (GetJob).
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct JobDetail {
    #[serde(flatten)]
    pub job: JobSummary,
    pub stats: Option<Stats>,
    /// Its priority, attempts, lineage and event log (`super::actions`).
    #[serde(flatten)]
    pub operator: OperatorView,
}

/// A job's statistics (JobStats), the fields a person reads.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct Stats {
    pub triangles: u64,
    pub domains: u32,
    pub workers: u32,
    pub effects: Vec<String>,
    /// Rays traced by kind: camera, shadow, reflection, refraction, diffuse,
    /// ambient_occlusion.
    pub rays: [u64; 6],
    pub nonfinite: u64,
    pub domain_loads: u64,
    pub domain_load_seconds: f64,
    pub domains_warm: u64,
    pub evictions: u64,
    pub tiles_retried: u32,
    pub rays_exchanged: u64,
    pub rays_forwarded: u64,
    pub queue_peak: u64,
    pub scheduler_rounds: u32,
    pub routing_version: u64,
    pub schedule: String,
    /// Why the job runs with `schedule` (JobStats.placement).
    pub placement: String,
    pub traffic_bytes: u64,
    pub cpu_seconds: f64,
    pub workers_detail: Vec<WorkerShare>,
}

/// One worker's share of a job (WorkerJobStats).
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct WorkerShare {
    pub worker_id: String,
    pub rays_traced: u64,
    pub domain_loads: u64,
    pub domain_load_seconds: f64,
    pub domains_warm: u64,
    pub evictions: u64,
    pub idle_seconds: f64,
    pub queue_peak: u64,
}

/// The submit form: the main knobs of a JobSpec. What is left out takes the same
/// defaults as over gRPC; every check is SubmitJob's.
#[derive(Deserialize, Debug, Default)]
#[serde(deny_unknown_fields)]
pub struct SubmitForm {
    pub scene: String,
    /// JobSpec.priority; absent: 0.
    #[serde(default)]
    pub priority: i32,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    #[serde(default)]
    pub integrator: String,
    pub max_depth: Option<u32>,
    #[serde(default)]
    pub seed: u64,
    #[serde(default)]
    pub domains: u32,
    #[serde(default)]
    pub schedule: String,
    #[serde(default)]
    pub layout: String,
    #[serde(default)]
    pub label: String,
    #[serde(default)]
    pub replicate: bool,
    /// The camera (`JobSpec.view`, docs/cameras.md): points as [x, y, z], the orbit as
    /// [azimuth, elevation] in degrees. None of them set means the scene's camera.
    pub look_from: Option<[f32; 3]>,
    pub look_at: Option<[f32; 3]>,
    pub up: Option<[f32; 3]>,
    pub fov: Option<f32>,
    pub orbit: Option<[f32; 2]>,
    #[serde(default)]
    pub orthographic: bool,
    #[serde(default)]
    pub aperture: String,
    pub focus_distance: Option<f32>,
    pub focus_on: Option<[f32; 3]>,
    /// An environment map (`JobSpec.lighting.env_map`, docs/lights.md): a file under
    /// the scene root; empty means none. Its rotation and intensity as over gRPC.
    #[serde(default)]
    pub env_map: String,
    pub env_rotation: Option<f32>,
    pub env_intensity: Option<f32>,
    /// A sun (`JobSpec.lighting.sun`, docs/lights.md) as [azimuth, elevation] or
    /// [azimuth, elevation, irradiance] in degrees; the page sends only those lengths.
    pub sun: Option<Vec<f32>>,
    /// The sun's angular diameter in degrees (`lighting.sun.angular_diameter_deg`);
    /// None: the real sun's.
    pub sun_size: Option<f32>,
    /// The sun's linear colour as [r, g, b] (`JobSpec.sun_color`); None: white.
    pub sun_color: Option<[f32; 3]>,
    /// The clamp on indirect light (`JobSpec.clamp_indirect`, docs/noise.md); None: no
    /// clamp.
    pub clamp_indirect: Option<f32>,
    /// AOVs for the EXR (`JobSpec.aovs`: "albedo", "normal", "depth", "samples");
    /// absent: none.
    #[serde(default)]
    pub aovs: Vec<String>,
    /// The animation (`JobSpec.time`, `animation`), or a job group of frames
    /// (`JobSpec.frames` "A..B[:STEP]" at `fps`).
    pub time: Option<f64>,
    #[serde(default)]
    pub animation: String,
    #[serde(default)]
    pub frames: String,
    pub fps: Option<f64>,
    /// Adaptive sampling (`JobSpec.noise_threshold`, docs/noise.md); None: every tile
    /// takes `spp`.
    pub noise_threshold: Option<f32>,
}

impl SubmitForm {
    /// The form's camera fields as `JobSpec.view`; None when none is set.
    fn view(&self) -> Option<CameraSpec> {
        let p = |v: Option<[f32; 3]>| v.map(|[x, y, z]| Vec3 { x, y, z });
        let view = CameraSpec {
            look_from: p(self.look_from),
            look_at: p(self.look_at),
            up: p(self.up),
            fov: self.fov,
            orbit: self
                .orbit
                .map(|[azimuth, elevation]| Orbit { azimuth, elevation }),
            orthographic: self.orthographic,
            aperture: self.aperture.trim().to_string(),
            focus_distance: self.focus_distance,
            focus_on: p(self.focus_on),
        };
        (view != CameraSpec::default()).then_some(view)
    }

    /// The form's sun and environment map as `JobSpec.lighting`; None without either.
    fn lighting(&self) -> Option<LightingSpec> {
        let path = self.env_map.trim();
        let env_map = (!path.is_empty()).then(|| EnvMapSpec {
            path: path.to_string(),
            rotation_deg: self.env_rotation,
            intensity: self.env_intensity,
        });
        let sun = match self.sun.as_deref() {
            Some(&[azimuth_deg, elevation_deg, ref rest @ ..]) if rest.len() <= 1 => {
                Some(SunSpec {
                    azimuth_deg,
                    elevation_deg,
                    irradiance: rest.first().copied(),
                    angular_diameter_deg: self.sun_size,
                })
            }
            _ => None,
        };
        (sun.is_some() || env_map.is_some()).then_some(LightingSpec { sun, env_map })
    }
}

/// SubmitJob's answer.
#[derive(Serialize, Debug)]
pub struct Submitted {
    pub id: String,
    /// For a range of frames: the job group (`id` is its first frame's job).
    #[serde(skip_serializing_if = "String::is_empty")]
    pub group_id: String,
}

impl From<SubmitForm> for JobSpec {
    fn from(f: SubmitForm) -> JobSpec {
        let view = f.view();
        let lighting = f.lighting();
        JobSpec {
            view,
            lighting,
            scene: f.scene,
            width: f.width,
            height: f.height,
            spp: f.spp,
            integrator: f.integrator,
            max_depth: f.max_depth,
            seed: f.seed,
            domains: f.domains,
            schedule: f.schedule,
            layout: f.layout,
            label: f.label,
            replicate: f.replicate,
            time: f.time,
            animation: f.animation,
            frames: f.frames.trim().to_string(),
            fps: f.fps,
            priority: f.priority,
            noise_threshold: f.noise_threshold,
            sun_color: f.sun_color.map(|[r, g, b]| Rgb { r, g, b }),
            clamp_indirect: f.clamp_indirect,
            aovs: f.aovs,
            ..JobSpec::default()
        }
    }
}

/// `"RUNNING"` for `JOB_STATE_RUNNING`.
pub fn state_name(state: i32) -> &'static str {
    let name = JobState::try_from(state)
        .unwrap_or(JobState::Unspecified)
        .as_str_name();
    name.strip_prefix("JOB_STATE_").unwrap_or(name)
}

fn seconds(d: Option<&prost_types::Duration>) -> Option<f64> {
    d.map(|d| d.seconds as f64 + f64::from(d.nanos) * 1e-9)
}

impl From<&JobProgress> for Progress {
    fn from(p: &JobProgress) -> Progress {
        Progress {
            state: state_name(p.state),
            tiles_done: p.tiles_done,
            tiles_total: p.tiles_total,
            rays_traced: p.rays_traced,
            rays_in_flight: p.rays_in_flight,
            elapsed_s: seconds(p.elapsed.as_ref()),
            eta_s: seconds(p.eta.as_ref()),
            error: p.error.clone(),
            samples_done: p.samples_done,
            passes_done: p.passes_done,
            passes_total: p.passes_total,
            stats: p.stats.as_ref().map(Stats::from),
        }
    }
}

impl From<&Job> for JobSummary {
    fn from(j: &Job) -> JobSummary {
        let spec = j.spec.clone().unwrap_or_default();
        let mut progress = j.progress.as_ref().map(Progress::from).unwrap_or(Progress {
            state: state_name(0),
            tiles_done: 0,
            tiles_total: 0,
            rays_traced: 0,
            rays_in_flight: 0,
            elapsed_s: None,
            eta_s: None,
            error: String::new(),
            samples_done: 0,
            passes_done: 0,
            passes_total: 0,
            stats: None,
        });
        progress.stats = None;
        JobSummary {
            id: j.job_id.clone(),
            label: spec.label,
            scene: spec.scene,
            width: spec.width,
            height: spec.height,
            spp: spec.spp,
            integrator: spec.integrator,
            schedule: spec.schedule,
            domains: spec.domains,
            progress,
            submitted_at: j.submitted_at.as_ref().map(|t| t.seconds),
            finished_at: j.finished_at.as_ref().map(|t| t.seconds),
            group: j.group.as_ref().map(|g| g.group_id.clone()),
            frame: j.group.as_ref().map(|g| g.frame),
            time: spec.time,
        }
    }
}

impl From<&Job> for JobDetail {
    fn from(j: &Job) -> JobDetail {
        JobDetail {
            job: JobSummary::from(j),
            stats: j.stats.as_ref().map(Stats::from),
            operator: OperatorView::from(j),
        }
    }
}

impl From<&ListJobsResponse> for JobPage {
    fn from(r: &ListJobsResponse) -> JobPage {
        JobPage {
            jobs: r.jobs.iter().map(JobSummary::from).collect(),
            next_page_token: r.next_page_token.clone(),
        }
    }
}

impl From<&JobStats> for Stats {
    fn from(s: &JobStats) -> Stats {
        Stats {
            triangles: s.triangles,
            domains: s.domains,
            workers: s.workers,
            effects: s.effects.clone(),
            rays: s.rays.as_ref().map(|r| r.by_kind()).unwrap_or_default(),
            nonfinite: s.nonfinite,
            domain_loads: s.domain_loads,
            domain_load_seconds: s.domain_load_seconds,
            domains_warm: s.domains_warm,
            evictions: s.evictions,
            tiles_retried: s.tiles_retried,
            rays_exchanged: s.rays_exchanged,
            rays_forwarded: s.rays_forwarded,
            queue_peak: s.queue_peak,
            scheduler_rounds: s.scheduler_rounds,
            routing_version: s.routing_version,
            schedule: s.schedule.clone(),
            placement: s.placement.clone(),
            traffic_bytes: s.traffic.as_ref().map_or(0, |t| t.total),
            cpu_seconds: s.cpu_seconds,
            workers_detail: s.workers_detail.iter().map(WorkerShare::from).collect(),
        }
    }
}

impl From<&WorkerJobStats> for WorkerShare {
    fn from(w: &WorkerJobStats) -> WorkerShare {
        WorkerShare {
            worker_id: w.worker_id.clone(),
            rays_traced: w.rays_traced,
            domain_loads: w.domain_loads,
            domain_load_seconds: w.domain_load_seconds,
            domains_warm: w.domains_warm,
            evictions: w.evictions,
            idle_seconds: w.idle_seconds,
            queue_peak: w.queue_peak,
        }
    }
}

/// The cluster as ListWorkers tells it: the workers, and who owns which domain of each
/// running job.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct Workers {
    pub workers: Vec<WorkerRow>,
    pub jobs: Vec<JobOwnership>,
}

/// One worker (WorkerStatus).
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct WorkerRow {
    pub id: String,
    /// Its name (`dray worker --name`; empty: none), shown before the id.
    pub name: String,
    pub address: String,
    pub hostname: String,
    pub state: String,
    pub threads: u32,
    pub memory_used_bytes: u64,
    pub memory_budget_bytes: u64,
    pub rays_queued: u64,
    pub rays_per_second: f64,
    pub jobs: Vec<String>,
    pub domains: Vec<DomainAt>,
    pub since_heartbeat_s: Option<f64>,
}

/// One domain of one job at one worker (WorkerDomain).
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct DomainAt {
    pub job_id: String,
    pub domain: u32,
    pub resident: bool,
    pub owned: bool,
    pub rays_queued: u64,
}

/// Who owns each domain of one running job (JobDomains).
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct JobOwnership {
    pub job_id: String,
    pub schedule: String,
    pub routing_version: u64,
    pub attempt: u32,
    pub domains: Vec<DomainOwner>,
}

/// One domain's owners and the rays waiting for it (DomainOwners).
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct DomainOwner {
    pub domain: u32,
    pub worker_ids: Vec<String>,
    pub rays_queued: u64,
}

impl From<&ListWorkersResponse> for Workers {
    fn from(r: &ListWorkersResponse) -> Workers {
        Workers {
            workers: r.workers.iter().map(WorkerRow::from).collect(),
            jobs: r
                .jobs
                .iter()
                .map(|j| JobOwnership {
                    job_id: j.job_id.clone(),
                    schedule: j.schedule.clone(),
                    routing_version: j.routing_version,
                    attempt: j.attempt,
                    domains: j
                        .domains
                        .iter()
                        .map(|d| DomainOwner {
                            domain: d.domain,
                            worker_ids: d.worker_ids.clone(),
                            rays_queued: d.rays_queued,
                        })
                        .collect(),
                })
                .collect(),
        }
    }
}

impl From<&WorkerStatus> for WorkerRow {
    fn from(w: &WorkerStatus) -> WorkerRow {
        WorkerRow {
            id: w.worker_id.clone(),
            name: w.name.clone(),
            address: w.endpoint.clone(),
            hostname: w.hostname.clone(),
            state: w.state.clone(),
            threads: w.threads,
            memory_used_bytes: w.memory_used_bytes,
            memory_budget_bytes: w.memory_budget_bytes,
            rays_queued: w.rays_queued,
            rays_per_second: w.rays_per_second,
            jobs: w.jobs.clone(),
            domains: w
                .domains
                .iter()
                .map(|d| DomainAt {
                    job_id: d.job_id.clone(),
                    domain: d.domain,
                    resident: d.resident,
                    owned: d.owned,
                    rays_queued: d.rays_queued,
                })
                .collect(),
            since_heartbeat_s: seconds(w.since_heartbeat.as_ref()),
        }
    }
}

/// What the page shows of a job's operator side: priority, attempts, lineage, events.
#[derive(Serialize, Debug, Clone, PartialEq, Default)]
pub struct OperatorView {
    pub priority: i32,
    pub attempts: u32,
    /// The job this one runs again; empty for a submitted job.
    pub retried_from: String,
    pub events: Vec<EventRow>,
}

/// One event of a job's log.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct EventRow {
    /// Unix milliseconds.
    pub at_ms: Option<i64>,
    /// `"WORKER_LOST"` for `JOB_EVENT_KIND_WORKER_LOST`.
    pub kind: &'static str,
    pub message: String,
}

impl From<&Job> for OperatorView {
    fn from(j: &Job) -> OperatorView {
        OperatorView {
            priority: j.spec.as_ref().map_or(0, |s| s.priority),
            attempts: j.attempts,
            retried_from: j.retried_from.clone(),
            events: j
                .events
                .iter()
                .map(|e| {
                    let name = JobEventKind::try_from(e.kind)
                        .unwrap_or(JobEventKind::Unspecified)
                        .as_str_name();
                    EventRow {
                        at_ms: e
                            .at
                            .as_ref()
                            .map(|t| t.seconds * 1000 + i64::from(t.nanos / 1_000_000)),
                        kind: name.strip_prefix("JOB_EVENT_KIND_").unwrap_or(name),
                        message: e.message.clone(),
                    }
                })
                .collect(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The dashboard's environment-map fields become `JobSpec.lighting.env_map`; an
    /// empty path is no map.
    #[test]
    fn the_forms_env_map_fields_make_the_lighting() {
        let form: SubmitForm = serde_json::from_str(
            r#"{"scene":"cornell","width":8,"height":8,"spp":1,
                "env_map":" skies/a.hdr ","env_rotation":-45,"env_intensity":2}"#,
        )
        .unwrap();
        let e = JobSpec::from(form)
            .lighting
            .and_then(|l| l.env_map)
            .expect("a map");
        assert_eq!(
            (e.path.as_str(), e.rotation_deg, e.intensity),
            ("skies/a.hdr", Some(-45.0), Some(2.0))
        );
        let plain: SubmitForm = serde_json::from_str(
            r#"{"scene":"cornell","width":8,"height":8,"spp":1,"env_map":""}"#,
        )
        .unwrap();
        assert_eq!(JobSpec::from(plain).lighting, None);
    }

    /// The dashboard's noise threshold becomes `JobSpec.noise_threshold`.
    #[test]
    fn the_forms_noise_threshold_makes_the_specs() {
        let f: SubmitForm = serde_json::from_str(
            r#"{"scene":"cornell","width":8,"height":8,"spp":64,"noise_threshold":0.02}"#,
        )
        .unwrap();
        assert_eq!(JobSpec::from(f).noise_threshold, Some(0.02));
        let f: SubmitForm =
            serde_json::from_str(r#"{"scene":"cornell","width":8,"height":8,"spp":64}"#).unwrap();
        assert_eq!(JobSpec::from(f).noise_threshold, None);
    }

    /// The dashboard's sun field becomes `JobSpec.lighting.sun`, with or without an
    /// irradiance, beside an environment map.
    #[test]
    fn the_forms_sun_field_makes_the_lighting() {
        let form: SubmitForm = serde_json::from_str(
            r#"{"scene":"cornell","width":8,"height":8,"spp":1,"sun":[30,45,3],"env_map":"a.hdr"}"#,
        )
        .unwrap();
        let l = JobSpec::from(form).lighting.expect("lighting");
        let sun = l.sun.expect("a sun");
        assert_eq!(
            (sun.azimuth_deg, sun.elevation_deg, sun.irradiance),
            (30.0, 45.0, Some(3.0))
        );
        assert!(l.env_map.is_some());
        let form: SubmitForm = serde_json::from_str(
            r#"{"scene":"cornell","width":8,"height":8,"spp":1,"sun":[-10,60]}"#,
        )
        .unwrap();
        let l = JobSpec::from(form).lighting.expect("lighting");
        assert_eq!(l.sun.and_then(|s| s.irradiance), None);
        assert_eq!(l.env_map, None);
    }

    /// The sun's size and colour, the clamp and the AOVs of the form become their
    /// JobSpec fields; absent, they stay absent (the coordinator's defaults).
    #[test]
    fn the_forms_sun_size_colour_clamp_and_aovs_make_the_spec() {
        let form: SubmitForm = serde_json::from_str(
            r#"{"scene":"cornell","width":8,"height":8,"spp":1,"sun":[30,45],"sun_size":2.5,
                "sun_color":[1,0.8,0.6],"clamp_indirect":4,"aovs":["albedo","depth"]}"#,
        )
        .unwrap();
        let spec = JobSpec::from(form);
        let sun = spec.lighting.and_then(|l| l.sun).expect("a sun");
        assert_eq!(sun.angular_diameter_deg, Some(2.5));
        assert_eq!(
            spec.sun_color,
            Some(Rgb {
                r: 1.0,
                g: 0.8,
                b: 0.6
            })
        );
        assert_eq!(spec.clamp_indirect, Some(4.0));
        assert_eq!(spec.aovs, ["albedo", "depth"]);
        let plain = JobSpec::from(
            serde_json::from_str::<SubmitForm>(r#"{"scene":"c","width":8,"height":8,"spp":1}"#)
                .unwrap(),
        );
        assert_eq!(
            (plain.sun_color, plain.clamp_indirect, plain.aovs.len()),
            (None, None, 0)
        );
        assert!(
            serde_json::from_str::<SubmitForm>(
                r#"{"scene":"c","width":8,"height":8,"spp":1,"sun_color":[1,1]}"#
            )
            .is_err()
        );
    }

    /// The dashboard's camera fields become `JobSpec.view`; a form without them leaves
    /// the scene's camera.
    #[test]
    fn the_forms_camera_fields_make_the_view() {
        let form: SubmitForm = serde_json::from_str(
            r#"{"scene":"cornell","width":8,"height":8,"spp":1,
                "orbit":[30,-10],"fov":50,"aperture":" f/2.8 ","focus_on":[0,1,2]}"#,
        )
        .unwrap();
        let spec = JobSpec::from(form);
        let v = spec.view.expect("a view");
        assert_eq!(
            v.orbit,
            Some(Orbit {
                azimuth: 30.0,
                elevation: -10.0
            })
        );
        assert_eq!((v.fov, v.aperture.as_str()), (Some(50.0), "f/2.8"));
        assert_eq!(v.focus_on.map(|p| p.z), Some(2.0));
        let plain: SubmitForm =
            serde_json::from_str(r#"{"scene":"cornell","width":8,"height":8,"spp":1}"#).unwrap();
        assert_eq!(JobSpec::from(plain).view, None);
        assert!(
            serde_json::from_str::<SubmitForm>(
                r#"{"scene":"c","width":8,"height":8,"spp":1,"look_at":[1,2]}"#
            )
            .is_err()
        );
    }
}
