//! The operator actions (issue 42) over real gRPC against a real `dray coordinator`
//! process with a state directory and its dashboard: priorities (a higher one is dealt
//! first among queued jobs), PauseJob and ResumeJob, RetryJob and RequeueJob (a new job
//! with the same spec, linked to the old one, whose image is the same bits), each job's
//! event log (kept across a SIGKILL and a restart), and the dashboard's download of the
//! finished PNG and EXR (the bytes GetImage gives, as an attachment).
//!
//! With no worker registered the coordinator renders one job at a time: the queue is
//! real, and the order jobs are dealt in is read from their events. On a `dray cluster`
//! with `--max-running-jobs 1` the same holds for jobs on workers (the cluster's deal
//! queue), and its workers are listed, logged and named in job events under the names
//! `dray cluster` gave them (worker-1, worker-2).

mod common;
mod support;

use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;
use std::process::Stdio;

use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{
    CancelJobRequest, GetImageRequest, GetJobRequest, ImageFormat, Job, JobEvent, JobEventKind,
    JobSpec, JobState, ListWorkersRequest, PauseJobRequest, RetryJobRequest, SubmitJobRequest,
    WorkerStatus,
};
use support::{Proc, WorkerCluster, eventually};
use tonic::transport::Channel;

/// Generous bound that only catches hangs.
const HANG: f64 = 300.0;

/// A coordinator on `state` with its dashboard: the process, its gRPC and HTTP addresses.
fn start(root: &Path, state: &Path) -> (Proc, String, String) {
    start_with(root, state, &[])
}

/// [`start`] with `extra` coordinator flags.
fn start_with(root: &Path, state: &Path, extra: &[&str]) -> (Proc, String, String) {
    let mut cmd = support::dray();
    cmd.args(["coordinator", "--listen", "127.0.0.1:0", "--scene-root"])
        .arg(root)
        .arg("--state-dir")
        .arg(state)
        .args(["--http-listen", "127.0.0.1:0", "--threads", "1"])
        .args(extra)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null());
    let mut p = Proc::spawn(cmd);
    let mut out = BufReader::new(p.child.stdout.take().expect("stdout"));
    let mut addr = |what: &str| {
        let mut line = String::new();
        out.read_line(&mut line).expect("read a line");
        line.trim()
            .rsplit(' ')
            .next()
            .map(|a| a.trim_start_matches("http://").to_string())
            .filter(|a| a.contains(':'))
            .unwrap_or_else(|| panic!("no {what} address in {line:?}"))
    };
    let grpc = addr("gRPC");
    let http = addr("dashboard");
    // The rest of stdout is not read: keep the pipe open without blocking the child.
    std::thread::spawn(move || std::io::copy(&mut out, &mut std::io::sink()));
    (p, grpc, http)
}

fn spec(spp: u32, priority: i32, label: &str) -> JobSpec {
    JobSpec {
        scene: "cornell".into(),
        width: 32,
        height: 24,
        spp,
        seed: 7,
        label: label.into(),
        priority,
        ..Default::default()
    }
}

struct Api {
    rt: tokio::runtime::Runtime,
    c: RenderServiceClient<Channel>,
}

impl Api {
    fn connect(addr: &str) -> Api {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .expect("runtime");
        let c = rt
            .block_on(RenderServiceClient::connect(format!("http://{addr}")))
            .expect("connect");
        Api { rt, c }
    }

    fn submit(&mut self, s: JobSpec) -> String {
        let mut c = self.c.clone();
        self.rt
            .block_on(c.submit_job(SubmitJobRequest { spec: Some(s) }))
            .expect("SubmitJob")
            .into_inner()
            .job_id
    }

    fn job(&mut self, id: &str) -> Job {
        let mut c = self.c.clone();
        self.rt
            .block_on(c.get_job(GetJobRequest { job_id: id.into() }))
            .expect("GetJob")
            .into_inner()
            .job
            .expect("a job")
    }

    fn state(&mut self, id: &str) -> JobState {
        JobState::try_from(self.job(id).progress.unwrap_or_default().state).unwrap()
    }

    fn wait_state(&mut self, id: &str, want: JobState) {
        assert!(
            eventually(HANG, || self.state(id) == want),
            "HANG: job {id} never {want:?}: {:?}",
            self.job(id)
        );
    }

    fn hold(&mut self, id: &str, pause: bool) -> Result<Job, tonic::Status> {
        let mut c = self.c.clone();
        let r = PauseJobRequest { job_id: id.into() };
        self.rt
            .block_on(async {
                if pause {
                    c.pause_job(r).await
                } else {
                    c.resume_job(r).await
                }
            })
            .map(|r| r.into_inner().job.expect("a job"))
    }

    fn retry(
        &mut self,
        id: &str,
        requeue: bool,
        priority: Option<i32>,
    ) -> Result<(Job, Job), tonic::Status> {
        let mut c = self.c.clone();
        let r = RetryJobRequest {
            job_id: id.into(),
            priority,
        };
        self.rt
            .block_on(async {
                if requeue {
                    c.requeue_job(r).await
                } else {
                    c.retry_job(r).await
                }
            })
            .map(|r| {
                let r = r.into_inner();
                (r.job.expect("new job"), r.previous.expect("old job"))
            })
    }

    fn cancel(&mut self, id: &str) {
        let mut c = self.c.clone();
        self.rt
            .block_on(c.cancel_job(CancelJobRequest { job_id: id.into() }))
            .expect("CancelJob");
    }

    fn workers(&mut self) -> Vec<WorkerStatus> {
        let mut c = self.c.clone();
        self.rt
            .block_on(c.list_workers(ListWorkersRequest::default()))
            .expect("ListWorkers")
            .into_inner()
            .workers
    }

    fn image(&mut self, id: &str, format: ImageFormat) -> Vec<u8> {
        let mut c = self.c.clone();
        self.rt
            .block_on(c.get_image(GetImageRequest {
                job_id: id.into(),
                format: format as i32,
                ..Default::default()
            }))
            .expect("GetImage")
            .into_inner()
            .data
            .to_vec()
    }
}

/// The first event of `kind`.
fn event(job: &Job, kind: JobEventKind) -> &JobEvent {
    job.events
        .iter()
        .find(|e| e.kind == kind as i32)
        .unwrap_or_else(|| panic!("no {kind:?} event in {:?}", job.events))
}

fn millis(e: &JobEvent) -> i64 {
    let t = e.at.as_ref().expect("a time");
    t.seconds * 1000 + i64::from(t.nanos / 1_000_000)
}

fn kinds(job: &Job) -> Vec<JobEventKind> {
    job.events
        .iter()
        .map(|e| JobEventKind::try_from(e.kind).unwrap())
        .collect()
}

/// A plain HTTP/1.1 GET: the status line, the headers (lower-case names) and the body.
fn http_get(addr: &str, path: &str) -> (String, Vec<(String, String)>, Vec<u8>) {
    let mut s = std::net::TcpStream::connect(addr).expect("connect to the dashboard");
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).expect("read the answer");
    let end = raw
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("end of headers");
    let head = String::from_utf8_lossy(&raw[..end]).to_string();
    let mut lines = head.split("\r\n");
    let status = lines.next().unwrap_or_default().to_string();
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
        .collect();
    let mut body = raw[end + 4..].to_vec();
    if headers
        .iter()
        .any(|(k, v)| k == "transfer-encoding" && v.contains("chunked"))
    {
        body = dechunk(&body);
    }
    (status, headers, body)
}

fn dechunk(mut b: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let eol = b.windows(2).position(|w| w == b"\r\n").expect("chunk size");
        let size = usize::from_str_radix(std::str::from_utf8(&b[..eol]).unwrap().trim(), 16)
            .expect("hex size");
        if size == 0 {
            return out;
        }
        out.extend_from_slice(&b[eol + 2..eol + 2 + size]);
        b = &b[eol + 2 + size + 2..];
    }
}

fn header<'a>(h: &'a [(String, String)], name: &str) -> &'a str {
    h.iter()
        .find(|(k, _)| k == name)
        .map_or("", |(_, v)| v.as_str())
}

#[test]
fn priorities_pause_retry_events_and_downloads() {
    let dir = common::tmp("operator");
    let state = dir.join("state");
    let (mut coordinator, grpc, http) = start(&dir, &state);
    let mut api = Api::connect(&grpc);

    // A long job holds the one render slot while the others queue behind it.
    let long = api.submit(spec(65536, 0, "long"));
    api.wait_state(&long, JobState::Running);
    let low = api.submit(spec(4, 0, "low"));
    let held = api.submit(spec(4, 0, "held"));
    let high = api.submit(spec(4, 5, "high"));
    for id in [&low, &held, &high] {
        api.wait_state(id, JobState::Queued);
    }

    // Pause: only a queued job; a running one is refused, named.
    let paused = api.hold(&held, true).expect("PauseJob");
    assert_eq!(
        paused.progress.clone().unwrap().state,
        JobState::Paused as i32,
        "{paused:?}"
    );
    let refused = api
        .hold(&long, true)
        .expect_err("a running job cannot be paused");
    assert_eq!(refused.code(), tonic::Code::FailedPrecondition);
    assert!(refused.message().contains(&long), "{}", refused.message());
    assert_eq!(
        api.hold(&low, false).expect_err("not paused").code(),
        tonic::Code::FailedPrecondition
    );
    // Retry needs a job that failed or was cancelled.
    assert_eq!(
        api.retry(&long, false, None).expect_err("running").code(),
        tonic::Code::FailedPrecondition
    );

    api.cancel(&long);
    api.wait_state(&low, JobState::Succeeded);
    api.wait_state(&high, JobState::Succeeded);
    // One slot: the higher priority was dealt first, although submitted last.
    let (h, l) = (api.job(&high), api.job(&low));
    assert!(
        millis(event(&h, JobEventKind::Succeeded)) <= millis(event(&l, JobEventKind::Started)),
        "priority 5 must run before priority 0: high {:?}, low {:?}",
        h.events,
        l.events
    );
    // The paused job stayed paused while the others ran, then runs once resumed.
    assert_eq!(api.state(&held), JobState::Paused);
    let resumed = api.hold(&held, false).expect("ResumeJob");
    assert_ne!(resumed.progress.unwrap().state, JobState::Paused as i32);
    api.wait_state(&held, JobState::Succeeded);
    assert_eq!(
        kinds(&api.job(&held)),
        [
            JobEventKind::Queued,
            JobEventKind::Paused,
            JobEventKind::Resumed,
            JobEventKind::Started,
            JobEventKind::PassFinished,
            JobEventKind::PassFinished,
            JobEventKind::Succeeded
        ],
        "{:?}",
        api.job(&held).events
    );

    // Retry the cancelled job at another priority: a new job, same spec, linked.
    let (again, old) = api.retry(&long, false, Some(3)).expect("RetryJob");
    assert_eq!(again.retried_from, long);
    let again_spec = again.spec.clone().unwrap();
    assert_eq!(
        (
            again_spec.spp,
            again_spec.priority,
            again_spec.label.as_str()
        ),
        (65536, 3, "long")
    );
    assert!(
        old.events
            .iter()
            .any(|e| e.kind == JobEventKind::Retried as i32 && e.message.contains(&again.job_id)),
        "{:?}",
        old.events
    );
    assert_eq!(old.attempts, 1);
    // (Its passes may have finished some passes before the cancel.)
    let without_passes: Vec<JobEventKind> = kinds(&old)
        .into_iter()
        .filter(|k| *k != JobEventKind::PassFinished)
        .collect();
    assert_eq!(
        without_passes,
        [
            JobEventKind::Queued,
            JobEventKind::Started,
            JobEventKind::Cancelled,
            JobEventKind::Retried
        ]
    );
    api.cancel(&again.job_id);

    // A succeeded job is requeued (not retried); the new job's image is the same bits.
    assert_eq!(
        api.retry(&low, false, None).expect_err("succeeded").code(),
        tonic::Code::FailedPrecondition
    );
    let (requeued, _) = api.retry(&low, true, None).expect("RequeueJob");
    api.wait_state(&requeued.job_id, JobState::Succeeded);
    assert_eq!(
        api.image(&requeued.job_id, ImageFormat::Png),
        api.image(&low, ImageFormat::Png),
        "a requeued job renders the same bits"
    );
    assert_eq!(api.job(&requeued.job_id).retried_from, low);

    // Downloads from the dashboard: GetImage's bytes, as attachments.
    for (file, format, ctype) in [
        ("image.png", ImageFormat::Png, "image/png"),
        ("image.exr", ImageFormat::Exr, "image/x-exr"),
    ] {
        let (status, headers, body) = http_get(&http, &format!("/api/jobs/{high}/download/{file}"));
        assert!(status.contains(" 200 "), "{status}");
        assert_eq!(header(&headers, "content-type"), ctype);
        let ext = file.rsplit('.').next().unwrap();
        assert_eq!(
            header(&headers, "content-disposition"),
            format!("attachment; filename=\"{high}.{ext}\"")
        );
        assert_eq!(body, api.image(&high, format), "{file}");
    }
    let (status, _, _) = http_get(&http, &format!("/api/jobs/{long}/download/image.png"));
    assert!(
        status.contains(" 409 "),
        "a cancelled job has no download: {status}"
    );
    let (status, _, _) = http_get(&http, &format!("/api/jobs/{high}/download/x.tif"));
    assert!(status.contains(" 404 "), "{status}");

    // The events are in the job store: a coordinator killed and started again on the
    // same state directory still has them, and the lineage.
    let before = api.job(&long);
    let before_new = api.job(&requeued.job_id);
    // SubmitJob answers once the store has every change posted before it: the events
    // above are on disk when it returns.
    api.submit(spec(1, 0, "flush"));
    coordinator.signal(libc::SIGKILL);
    coordinator.wait_timeout(HANG);
    drop(api);
    let (_coordinator, grpc, _) = start(&dir, &state);
    let mut api = Api::connect(&grpc);
    let after = api.job(&long);
    assert_eq!(
        after.events, before.events,
        "the event log survives a restart"
    );
    assert_eq!(after.attempts, 1);
    let after_new = api.job(&requeued.job_id);
    assert_eq!(after_new.retried_from, low);
    assert_eq!(after_new.events, before_new.events);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The priority and pause part of the test above, on a `dray cluster` whose coordinator
/// runs one job on its workers at a time (`--max-running-jobs 1`): the jobs beyond it
/// wait QUEUED in the cluster's deal queue, a priority-5 job submitted last is dealt
/// before a priority-0 one, and a paused job stays PAUSED while the others run.
#[test]
fn a_cluster_limit_deals_by_priority_and_holds_paused_jobs() {
    let dir = common::tmp("operator-cluster");
    let c = WorkerCluster::start(1, 1, &dir, &["--max-running-jobs", "1"]);
    let mut api = Api::connect(&c.addr);
    assert_eq!(api.workers().len(), 1, "the job must run on the worker");

    let long = api.submit(spec(65536, 0, "long"));
    api.wait_state(&long, JobState::Running);
    let low = api.submit(spec(4, 0, "low"));
    let held = api.submit(spec(4, 0, "held"));
    let high = api.submit(spec(4, 5, "high"));
    for id in [&low, &held, &high] {
        api.wait_state(id, JobState::Queued);
    }
    let paused = api.hold(&held, true).expect("PauseJob on a cluster");
    assert_eq!(
        paused.progress.unwrap().state,
        JobState::Paused as i32,
        "{:?}",
        paused.events
    );
    let refused = api
        .hold(&long, true)
        .expect_err("a running job cannot be paused");
    assert_eq!(refused.code(), tonic::Code::FailedPrecondition);
    assert!(
        refused.message().contains("--max-running-jobs"),
        "{}",
        refused.message()
    );

    api.cancel(&long);
    api.wait_state(&low, JobState::Succeeded);
    api.wait_state(&high, JobState::Succeeded);
    let (h, l) = (api.job(&high), api.job(&low));
    assert!(
        millis(event(&h, JobEventKind::Succeeded)) <= millis(event(&l, JobEventKind::Started)),
        "on the cluster too, priority 5 must run before priority 0: high {:?}, low {:?}",
        h.events,
        l.events
    );
    assert_eq!(
        h.stats.as_ref().map(|s| s.workers),
        Some(1),
        "it ran on the worker: {:?}",
        h.stats
    );
    assert_eq!(api.state(&held), JobState::Paused, "{:?}", api.job(&held));
    api.hold(&held, false).expect("ResumeJob");
    api.wait_state(&held, JobState::Succeeded);
    assert_eq!(
        kinds(&api.job(&held))
            .into_iter()
            .filter(|k| *k != JobEventKind::PassFinished)
            .collect::<Vec<_>>(),
        [
            JobEventKind::Queued,
            JobEventKind::Paused,
            JobEventKind::Resumed,
            JobEventKind::Started,
            JobEventKind::Succeeded
        ],
        "{:?}",
        api.job(&held).events
    );
    drop(c);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Pre-emption when asked: a running job is never pre-empted by a higher priority alone,
/// but RequeueJob on it gives up its slot (the running attempt is cancelled, the same spec
/// queued again at its priority), so the higher-priority job waiting is dealt next and
/// the requeued one after it.
#[test]
fn requeueing_a_running_job_lets_a_higher_priority_one_take_its_slot() {
    let dir = common::tmp("operator-preempt");
    let c = WorkerCluster::start(1, 1, &dir, &["--max-running-jobs", "1"]);
    let mut api = Api::connect(&c.addr);
    assert_eq!(api.workers().len(), 1, "the job must run on the worker");

    let long = api.submit(spec(65536, 0, "long"));
    api.wait_state(&long, JobState::Running);
    let high = api.submit(spec(4, 5, "high"));
    api.wait_state(&high, JobState::Queued);
    assert_eq!(
        api.state(&long),
        JobState::Running,
        "a priority alone does not pre-empt"
    );

    let (again, old) = api.retry(&long, true, None).expect("RequeueJob");
    assert_eq!(old.job_id, long);
    api.wait_state(&long, JobState::Cancelled);
    api.wait_state(&high, JobState::Succeeded);
    api.wait_state(&again.job_id, JobState::Running);
    let (h, a) = (api.job(&high), api.job(&again.job_id));
    assert!(
        millis(event(&h, JobEventKind::Succeeded)) <= millis(event(&a, JobEventKind::Started)),
        "the priority-5 job must run before the requeued priority-0 one: high {:?}, requeued {:?}",
        h.events,
        a.events
    );
    assert_eq!(a.retried_from, long, "{:?}", a.events);
    api.cancel(&again.job_id);
    api.wait_state(&again.job_id, JobState::Cancelled);
    drop(c);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A job PAUSED on a coordinator with `--max-running-jobs 1` and workers, which is
/// killed and started again on its state directory without the limit (so jobs on
/// workers start at once): the job comes back PAUSED and stays so while a job queued
/// behind it is taken back and runs to the end, and runs once resumed.
#[test]
fn a_job_restored_paused_on_workers_without_a_limit_waits_for_its_resume() {
    let dir = common::tmp("operator-restore-paused");
    let state = dir.join("state");
    let (mut coordinator, grpc, _) = start_with(&dir, &state, &["--max-running-jobs", "1"]);
    let worker = support::worker(&grpc);
    let mut api = Api::connect(&grpc);
    assert!(
        eventually(HANG, || api.workers().len() == 1),
        "HANG: the worker never registered"
    );
    // The long job holds the one slot; `held` is paused behind it, `after` queued.
    let long = api.submit(spec(65536, 0, "long"));
    api.wait_state(&long, JobState::Running);
    let held = api.submit(spec(4, 0, "held"));
    api.wait_state(&held, JobState::Queued);
    api.hold(&held, true).expect("PauseJob");
    // SubmitJob answers once the store has every change posted before it, the pause
    // included.
    let after = api.submit(spec(4, 0, "after"));
    api.wait_state(&after, JobState::Queued);
    coordinator.signal(libc::SIGKILL);
    coordinator.wait_timeout(HANG);
    drop((api, worker));

    let (_coordinator, grpc, _) = start(&dir, &state);
    let _worker = support::worker(&grpc);
    let mut api = Api::connect(&grpc);
    api.cancel(&long);
    assert_eq!(api.state(&held), JobState::Paused, "{:?}", api.job(&held));
    // `after`, taken back after `held` (submission order), runs on the worker: by its
    // end `held` would have started, had it not been held.
    api.wait_state(&after, JobState::Succeeded);
    assert_eq!(
        api.job(&after).stats.map(|s| s.workers),
        Some(1),
        "it ran on the worker"
    );
    let job = api.job(&held);
    assert_eq!(
        job.progress.clone().unwrap_or_default().state,
        JobState::Paused as i32,
        "a job restored PAUSED started without a resume: {:?}",
        job.events
    );
    api.hold(&held, false).expect("ResumeJob");
    api.wait_state(&held, JobState::Succeeded);
    let kinds: Vec<JobEventKind> = kinds(&api.job(&held))
        .into_iter()
        .filter(|k| *k != JobEventKind::PassFinished)
        .collect();
    assert_eq!(
        kinds,
        [
            JobEventKind::Queued,
            JobEventKind::Paused,
            JobEventKind::Restored,
            JobEventKind::Resumed,
            JobEventKind::Started,
            JobEventKind::Succeeded
        ],
        "{:?}",
        api.job(&held).events
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// `dray cluster` names its workers worker-1 and worker-2, and they are those names
/// everywhere: its own lines, the coordinator's log, ListWorkers (WorkerStatus.name,
/// beside the `w<N>-<nonce>` id) and the WORKER_LOST event of a job that lost one.
#[test]
fn cluster_workers_keep_their_names_in_listings_logs_and_events() {
    let dir = common::tmp("operator-names");
    let c = WorkerCluster::start(
        2,
        2,
        &dir,
        &[
            "--heartbeat-interval-ms",
            "100",
            "--heartbeat-timeout-ms",
            "3000",
            "--restart-limit",
            "0",
        ],
    );
    let mut api = Api::connect(&c.addr);
    let mut listed: Vec<(String, String)> = api
        .workers()
        .into_iter()
        .map(|w| (w.name, w.worker_id))
        .collect();
    listed.sort();
    let names: Vec<&str> = listed.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["worker-1", "worker-2"], "{listed:?}");
    let log = c.log();
    for (name, id) in &listed {
        assert!(id.starts_with('w') && id.contains('-'), "{id}");
        let line = format!("worker registered: {id} ({name})");
        assert!(log.contains(&line), "no {line:?} in:\n{log}");
    }

    // A job on both workers loses worker-2: its event says which, by id and name.
    let job = api.submit(JobSpec {
        width: 64,
        height: 48,
        ..spec(65536, 0, "names")
    });
    api.wait_state(&job, JobState::Running);
    assert!(
        eventually(HANG, || api.workers().iter().all(|w| w.jobs.contains(&job))),
        "HANG: the job never ran on both workers: {:?}",
        api.workers()
    );
    // SAFETY: kill(2) on a worker of the cluster this test started.
    unsafe {
        libc::kill(c.worker_pids[1], libc::SIGKILL);
    }
    let (_, w2) = &listed[1];
    let label = format!("worker {w2} (worker-2)");
    assert!(
        eventually(HANG, || api.job(&job).events.iter().any(|e| {
            e.kind == JobEventKind::WorkerLost as i32 && e.message.contains(&label)
        })),
        "HANG: no WORKER_LOST event naming {label:?}: {:?}",
        api.job(&job).events
    );
    assert!(
        c.log().contains(&format!("worker lost: {w2} (worker-2)")),
        "{}",
        c.log()
    );
    let left: Vec<String> = api.workers().into_iter().map(|w| w.name).collect();
    assert_eq!(left, ["worker-1"]);
    api.cancel(&job);
    drop(c);
    let _ = std::fs::remove_dir_all(&dir);
}
