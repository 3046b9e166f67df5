//! Workers that do not share the coordinator's disk: they fetch the job's scene package
//! (manifest, shared files, each domain file when first loaded) from the coordinator's
//! `dray.v1.PackageService`, with real processes over real gRPC.
//!
//! - A coordinator and two workers, each in its own working directory, with the
//!   coordinator's directory (its work dir, where it writes the job's package) *hidden*
//!   from the workers by a private mount namespace (`unshare`): the package path the job
//!   names does not exist for them, so they fetch it, and the image is bit-identical to
//!   `dray render`. Where `unshare` cannot make a namespace, the workers are told
//!   `--fetch-packages always` instead, and the test says so loudly.
//! - The coordinator serves only the files of a running job's package, and only to
//!   holders of the cluster token: path escapes, absolute paths, files the manifest does
//!   not list and symlinks are refused; no token and the API token are refused.
//! - A package file damaged on the coordinator's disk fails the job with a message that
//!   names the file and the checksum mismatch, and nothing damaged is kept by the worker.

mod common;
mod support;

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};

use dray_proto::v1::package_service_client::PackageServiceClient;
use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{FetchFileRequest, FileChunk, GetJobRequest, JobState};
use support::{Proc, capture_stderr, dray, eventually};

const API_TOKEN: &str = "api-token-for-the-package-test-0123456789";
const CLUSTER_TOKEN: &str = "cluster-token-for-the-package-test-0123456789";

/// Upper bound for waits that only catch hangs.
const HANG_SECS: f64 = 180.0;

fn text(log: &Arc<Mutex<String>>) -> String {
    dray_sync::lock(log).clone()
}

/// A token file only this user can read.
fn token_file(dir: &Path, name: &str, token: &str) -> PathBuf {
    use std::os::unix::fs::PermissionsExt;
    let p = dir.join(name);
    std::fs::write(&p, format!("{token}\n")).expect("write token");
    std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o600)).expect("chmod token");
    p
}

/// Whether this machine lets an unprivileged process hide a directory from itself with
/// a private mount namespace (`unshare --user --map-root-user --mount`).
fn can_hide(probe: &Path) -> bool {
    std::fs::create_dir_all(probe).expect("probe dir");
    Command::new("unshare")
        .args(["--user", "--map-root-user", "--mount", "sh", "-c"])
        .arg("mount -t tmpfs none \"$1\" && test ! -e \"$1/x\"")
        .arg("sh")
        .arg(probe)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// A coordinator, its workers and its files.
struct Members {
    coordinator: Proc,
    addr: String,
    log: support::Captured,
    workers: Vec<(Proc, support::Captured)>,
    /// The coordinator's working directory (its --work-dir is `work` inside it).
    coord_dir: PathBuf,
    api: PathBuf,
    cluster: PathBuf,
}

/// How the workers get the package.
#[derive(Clone, Copy, PartialEq)]
enum Isolation {
    /// The coordinator's directory is hidden from the workers (the path does not exist
    /// for them); `--fetch-packages auto`, the default.
    Hidden,
    /// The path exists for them, but `--fetch-packages always`.
    Forced,
}

impl Members {
    /// A coordinator in `dir/coord` with `--work-dir work` and both tokens.
    fn start(dir: &Path, scene_root: &Path) -> Members {
        let coord_dir = dir.join("coord");
        std::fs::create_dir_all(&coord_dir).expect("coordinator dir");
        let secrets = dir.join("secrets");
        std::fs::create_dir_all(&secrets).expect("secrets dir");
        let api = token_file(&secrets, "api.token", API_TOKEN);
        let cluster = token_file(&secrets, "cluster.token", CLUSTER_TOKEN);
        let mut cmd = dray();
        cmd.current_dir(&coord_dir)
            .args([
                "coordinator",
                "--listen",
                "127.0.0.1:0",
                "--work-dir",
                "work",
            ])
            .arg("--scene-root")
            .arg(scene_root)
            .arg("--auth-token-file")
            .arg(&api)
            .arg("--cluster-token-file")
            .arg(&cluster)
            .args(["--heartbeat-timeout-ms", "60000"])
            .env_remove("DRAY_AUTH_TOKEN")
            .env_remove("DRAY_CLUSTER_TOKEN")
            .env("DRAY_LOG", "warn,dray_coordinator::membership=info")
            .env("NO_COLOR", "1")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        let mut coordinator = Proc::spawn(cmd);
        let log = capture_stderr(&mut coordinator.child);
        let addr = support::listening_address(&mut coordinator.child)
            .unwrap_or_else(|line| panic!("no address in {line:?}; log: {}", text(&log)));
        Members {
            coordinator,
            addr,
            log,
            workers: Vec::new(),
            coord_dir,
            api,
            cluster,
        }
    }

    /// A worker running in `dir` (its own working directory) with `extra` flags and a
    /// package cache `cache` relative to it, and wait until it has registered.
    fn add_worker(&mut self, dir: &Path, isolation: Isolation, extra: &[&str]) {
        std::fs::create_dir_all(dir).expect("worker dir");
        let mut args: Vec<String> = [
            "worker",
            "--coordinator",
            &self.addr,
            "--listen",
            "127.0.0.1:0",
            "--no-cache-host",
            "--threads",
            "1",
            "--package-cache",
            "cache",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        args.push("--cluster-token-file".into());
        args.push(self.cluster.display().to_string());
        if isolation == Isolation::Forced {
            args.extend(["--fetch-packages".into(), "always".into()]);
        }
        args.extend(extra.iter().map(|s| s.to_string()));
        let mut cmd = match isolation {
            // The coordinator's directory becomes an empty tmpfs in the worker's own
            // mount namespace: the package path of every job does not exist there.
            Isolation::Hidden => {
                let mut c = Command::new("unshare");
                c.args(["--user", "--map-root-user", "--mount", "sh", "-c"])
                    .arg("mount -t tmpfs none \"$1\" && shift && exec \"$@\"")
                    .arg("sh")
                    .arg(&self.coord_dir)
                    .arg(env!("CARGO_BIN_EXE_dray"));
                c
            }
            Isolation::Forced => dray(),
        };
        cmd.args(&args)
            .current_dir(dir)
            .env_remove("DRAY_CLUSTER_TOKEN")
            .env("DRAY_LOG", "warn,dray_worker::plan=info")
            .env("NO_COLOR", "1")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        let mut p = Proc::spawn(cmd);
        let log = capture_stderr(&mut p.child);
        self.workers.push((p, log));
        let want = self.workers.len();
        assert!(
            eventually(HANG_SECS, || text(&self.log)
                .matches("worker registered")
                .count()
                >= want),
            "worker {want} did not register; coordinator: {}\nworker: {}",
            text(&self.log),
            text(&self.workers[want - 1].1)
        );
    }

    fn worker_logs(&self) -> String {
        self.workers
            .iter()
            .map(|(_, l)| text(l))
            .collect::<Vec<_>>()
            .join("\n")
    }
}

/// `dray submit` to `m` with the API token, as a process (stderr captured).
fn spawn_submit(m: &Members, scene: &str, flags: &[&str], png: &Path) -> (Proc, support::Captured) {
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", &m.addr, scene])
        .args(flags)
        .arg("--output")
        .arg(png)
        .arg("--auth-token-file")
        .arg(&m.api)
        .env_remove("DRAY_AUTH_TOKEN")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let mut p = Proc::spawn(cmd);
    let err = capture_stderr(&mut p.child);
    (p, err)
}

/// `dray submit` to the end: whether it succeeded, and its stderr.
fn submit(m: &Members, scene: &str, flags: &[&str], png: &Path) -> (bool, String) {
    let (mut p, err) = spawn_submit(m, scene, flags, png);
    let status = p.wait_timeout(HANG_SECS);
    let out = err.after(status.is_some());
    let status = status.unwrap_or_else(|| {
        panic!(
            "HANG: dray submit did not finish; its output:\n{out}\nworkers:\n{}",
            m.worker_logs()
        )
    });
    (status.success(), out)
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime")
}

fn bearer<T>(msg: T, token: Option<&str>) -> tonic::Request<T> {
    let mut r = tonic::Request::new(msg);
    if let Some(t) = token {
        r.metadata_mut().insert(
            "authorization",
            format!("Bearer {t}").parse().expect("header value"),
        );
    }
    r
}

/// FetchFile with `token`: the chunks, or the status.
fn fetch(
    addr: &str,
    token: Option<&str>,
    req: FetchFileRequest,
) -> Result<Vec<FileChunk>, tonic::Status> {
    runtime().block_on(async {
        let mut c = PackageServiceClient::connect(format!("http://{addr}"))
            .await
            .expect("connect");
        let mut s = c.fetch_file(bearer(req, token)).await?.into_inner();
        let mut out = Vec::new();
        while let Some(chunk) = s.message().await? {
            out.push(chunk);
        }
        Ok(out)
    })
}

fn job_state(addr: &str, id: &str) -> JobState {
    runtime().block_on(async {
        let mut c = RenderServiceClient::connect(format!("http://{addr}"))
            .await
            .expect("connect");
        c.get_job(bearer(
            GetJobRequest {
                job_id: id.to_string(),
            },
            Some(API_TOKEN),
        ))
        .await
        .expect("GetJob")
        .into_inner()
        .job
        .and_then(|j| j.progress)
        .map_or(JobState::Unspecified, |p| p.state())
    })
}

/// Files under `dir`, recursively, relative to it.
fn files_under(dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if let Ok(r) = p.strip_prefix(dir) {
                out.push(r.display().to_string());
            }
        }
    }
    out.sort();
    out
}

fn isolation(dir: &Path) -> Isolation {
    if can_hide(&dir.join("probe")) {
        Isolation::Hidden
    } else {
        eprintln!(
            "NOTE: `unshare --user --map-root-user --mount` is not available here, so the \
             coordinator's directory cannot be hidden from the workers; they are told \
             --fetch-packages always instead (the transfer is the same, the \"path does not \
             exist\" decision is not exercised)"
        );
        Isolation::Forced
    }
}

#[test]
fn workers_without_the_coordinators_disk_fetch_the_package_and_render_the_same_bits() {
    let dir = common::tmp("package-fetch-bits");
    let how = isolation(&dir);
    let flags = [
        "--width",
        "40",
        "--height",
        "30",
        "--spp",
        "4",
        "--seed",
        "5",
        "--integrator",
        "path",
        "--max-depth",
        "4",
        "--domains",
        "4",
        "--layout",
        "kd",
    ];
    let reference = common::render(&dir, "reference", "cornell", &flags);
    assert!(reference.ok, "dray render: {}", reference.stderr);
    let reference = std::fs::read(reference.png.expect("png")).expect("reference png");

    let mut m = Members::start(&dir, &dir);
    m.add_worker(&dir.join("w1"), how, &[]);
    m.add_worker(&dir.join("w2"), how, &[]);
    for round in 0..2 {
        let png = dir.join(format!("cluster-{round}.png"));
        let (ok, out) = submit(&m, "cornell", &flags, &png);
        assert!(ok, "job failed: {out}\nworkers:\n{}", m.worker_logs());
        let got = std::fs::read(&png).expect("cluster png");
        assert!(
            got == reference,
            "round {round}: the image of workers fetching the package differs from dray render"
        );
    }
    let logs = m.worker_logs();
    assert!(
        logs.matches("fetching the package from the coordinator")
            .count()
            >= 2,
        "the workers did not fetch the package:\n{logs}"
    );
    // Each worker's cache is in its own working directory: a manifest, checked domain
    // files, no partial downloads, nothing of the coordinator's directory.
    let mut domains = 0;
    for w in ["w1", "w2"] {
        let cache = dir.join(w).join("cache");
        let files = files_under(&cache);
        assert!(
            files.iter().any(|f| f.ends_with("/manifest.json")),
            "{w}: no manifest in {}: {files:?}",
            cache.display()
        );
        assert!(
            !files.iter().any(|f| f.ends_with(".part")),
            "{w}: {files:?}"
        );
        domains += files.iter().filter(|f| f.contains("/domain-")).count();
    }
    assert!(domains >= 4, "every domain was fetched by some worker");
    eprintln!(
        "two workers ({}) fetched {domains} domain files; same bits as dray render twice",
        match how {
            Isolation::Hidden => "the coordinator's directory hidden from them",
            Isolation::Forced => "--fetch-packages always",
        }
    );
    assert!(support::alive(m.coordinator.pid()), "{}", text(&m.log));
    drop(m);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_package_service_serves_only_package_files_and_only_to_the_cluster() {
    let dir = common::tmp("package-fetch-service");
    let mut m = Members::start(&dir, &dir);
    // Loads stall, so the job stays running while the service is probed.
    m.add_worker(
        &dir.join("w1"),
        Isolation::Forced,
        &["--load-delay-ms", "3600000"],
    );
    let png = dir.join("never.png");
    let (_submit, err) = spawn_submit(
        &m,
        "cornell",
        &[
            "--width",
            "16",
            "--height",
            "16",
            "--spp",
            "1",
            "--domains",
            "4",
        ],
        &png,
    );
    let mut id = String::new();
    assert!(
        eventually(HANG_SECS, || {
            if let Some(found) = text(&err).lines().find_map(|l| {
                l.strip_prefix("dray submit: job ")?
                    .split_once(" accepted by ")
                    .map(|(id, _)| id.to_string())
            }) {
                id = found;
            }
            !id.is_empty() && job_state(&m.addr, &id) == JobState::Running
        }),
        "the job did not start: {}",
        text(&err)
    );
    let package = m.coord_dir.join("work").join(&id);
    let manifest = std::fs::read(package.join("manifest.json")).expect("the job's manifest");
    // Things beside the package files: a secret outside, a file the manifest does not
    // list, and a domain file replaced by a symlink to the secret.
    std::fs::write(dir.join("secret.txt"), "TOP-SECRET").expect("secret");
    std::fs::write(package.join("extra.bin"), "not listed").expect("extra");
    let domain3 = package.join("domain-00003.bin");
    std::fs::remove_file(&domain3).expect("remove domain 3");
    std::os::unix::fs::symlink(dir.join("secret.txt"), &domain3).expect("symlink");

    let req = |path: &str, offset: u64| FetchFileRequest {
        job_id: id.clone(),
        package_checksum: String::new(),
        path: path.to_string(),
        offset,
    };
    let cluster = Some(CLUSTER_TOKEN);
    let code = |r: Result<Vec<FileChunk>, tonic::Status>| match r {
        Ok(_) => tonic::Code::Ok,
        Err(s) => {
            assert!(
                !s.message().contains("TOP-SECRET"),
                "the secret leaked: {}",
                s.message()
            );
            s.code()
        }
    };

    // The manifest, whole and in order, with the package checksum; and resumed.
    let chunks = fetch(&m.addr, cluster, req("manifest.json", 0)).expect("FetchFile manifest");
    let got: Vec<u8> = chunks.iter().flat_map(|c| c.data.clone()).collect();
    assert_eq!(got, manifest);
    assert!(
        chunks
            .iter()
            .all(|c| c.total_bytes == manifest.len() as u64 && c.data.len() <= 1 << 20)
    );
    let tail = fetch(&m.addr, cluster, req("manifest.json", 10)).expect("resume");
    assert_eq!(tail[0].offset, 10);
    assert_eq!(
        tail.iter()
            .flat_map(|c| c.data.clone())
            .collect::<Vec<u8>>(),
        manifest[10..]
    );
    let checksum = chunks[0].xxh3.clone();
    assert_eq!(checksum.len(), 16, "{checksum}");
    // A domain file the manifest lists is served.
    assert_eq!(
        code(fetch(&m.addr, cluster, req("domain-00000.bin", 0))),
        tonic::Code::Ok
    );

    // Only the cluster token: none, or the API token, is refused.
    for token in [None, Some(API_TOKEN)] {
        assert_eq!(
            code(fetch(&m.addr, token, req("manifest.json", 0))),
            tonic::Code::Unauthenticated,
            "token {token:?}"
        );
    }
    // Nothing outside the package, however spelt.
    for path in [
        "../../secret.txt",
        "../secret.txt",
        "/etc/passwd",
        "..",
        ".",
        "",
        "sub/manifest.json",
        "./manifest.json",
        "manifest.json/../../secret.txt",
    ] {
        assert_eq!(
            code(fetch(&m.addr, cluster, req(path, 0))),
            tonic::Code::InvalidArgument,
            "path {path:?}"
        );
    }
    // Only files the manifest lists; never a symlink, even under a listed name.
    assert_eq!(
        code(fetch(&m.addr, cluster, req("extra.bin", 0))),
        tonic::Code::NotFound
    );
    assert_eq!(
        code(fetch(&m.addr, cluster, req("domain-00003.bin", 0))),
        tonic::Code::DataLoss
    );
    // Only running jobs, only their package, only within the file.
    let mut other = req("manifest.json", 0);
    other.job_id = "no-such-job".into();
    assert_eq!(code(fetch(&m.addr, cluster, other)), tonic::Code::NotFound);
    let mut wrong = req("manifest.json", 0);
    wrong.package_checksum = "0123456789abcdef".into();
    assert_eq!(
        code(fetch(&m.addr, cluster, wrong)),
        tonic::Code::FailedPrecondition
    );
    let mut right = req("manifest.json", 0);
    right.package_checksum = checksum;
    assert_eq!(code(fetch(&m.addr, cluster, right)), tonic::Code::Ok);
    assert_eq!(
        code(fetch(&m.addr, cluster, req("manifest.json", 1 << 40))),
        tonic::Code::OutOfRange
    );
    drop(m);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_package_file_damaged_on_the_coordinator_fails_the_job_naming_it() {
    let dir = common::tmp("package-fetch-damaged");
    let how = isolation(&dir);
    // The scene root is in the coordinator's directory: hidden from the worker too.
    let scenes = dir.join("coord").join("scenes");
    std::fs::create_dir_all(&scenes).expect("scenes");
    let out = dray()
        .args(["partition", "cornell", "--domains", "2", "--out"])
        .arg(scenes.join("pkg"))
        .output()
        .expect("dray partition");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // One bit flipped in the middle of domain 1: same size, another checksum.
    let victim = scenes.join("pkg").join("domain-00001.bin");
    let mut bytes = std::fs::read(&victim).expect("domain file");
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x10;
    std::fs::write(&victim, &bytes).expect("damage");

    let mut m = Members::start(&dir, &scenes);
    m.add_worker(&dir.join("w1"), how, &[]);
    let png = dir.join("damaged.png");
    let (ok, out) = submit(
        &m,
        "pkg",
        &["--width", "24", "--height", "24", "--spp", "2"],
        &png,
    );
    assert!(!ok, "a damaged package rendered: {out}");
    assert!(
        out.contains("CHECKSUM MISMATCH") && out.contains("domain-00001.bin"),
        "the failure does not name the damaged file and the checksum: {out}\nworker: {}",
        m.worker_logs()
    );
    assert!(!png.exists());
    // The damaged download was not kept; the good files were.
    let files = files_under(&dir.join("w1").join("cache"));
    assert!(
        !files.iter().any(|f| f.contains("domain-00001.bin")),
        "{files:?}"
    );
    assert!(
        files.iter().any(|f| f.ends_with("/manifest.json")),
        "{files:?}"
    );
    drop(m);
    let _ = std::fs::remove_dir_all(&dir);
}
