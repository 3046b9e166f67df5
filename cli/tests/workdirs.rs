//! Where dray processes write on the local disk, against another local user and a stop.
//!
//! - docs/security.md "Hardening, second round", item 1: `dray cluster` used
//!   `/tmp/dray-cluster-<pid>-secrets` for its cluster token, so an unprivileged user who made that directory first (mode 0777)
//!   could swap the token. Here a second user (nobody, through `setpriv`) plants
//!   directories at the old predictable names for the next pids, and the test shows the
//!   cluster's token lives in a new, private directory the other user can neither read
//!   nor write.
//! - docs/security.md "Hardening, second round", item 14: a SIGTERM while a coordinator
//!   cut a large scene into a package left the partial package (hundreds of MB) in its work directory.

mod common;
mod support;

use std::io::{BufRead, BufReader};
use std::os::unix::fs::{MetadataExt, PermissionsExt};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use support::{Proc, dray, eventually, listening_address};

/// Run `script` with `sh -c` as user and group 65534 (nobody), with no supplementary
/// groups; None when that is impossible here (not root, or no setpriv), said loudly, and
/// a failure under CI (`CI=true`), which runs as root.
fn as_other_user(script: &str) -> Option<std::process::Output> {
    // SAFETY: geteuid has no preconditions.
    let root = unsafe { libc::geteuid() } == 0;
    let setpriv = Path::new("/usr/bin/setpriv").exists() || Path::new("/bin/setpriv").exists();
    if !root || !setpriv {
        let why = if root {
            "setpriv is missing"
        } else {
            "not running as root"
        };
        common::dependency_missing(&format!(
            "second-user part: {why}; cannot act as another local user"
        ));
        return None;
    }
    Some(
        Command::new("setpriv")
            .args([
                "--reuid=65534",
                "--regid=65534",
                "--clear-groups",
                "sh",
                "-c",
            ])
            .arg(script)
            .output()
            .expect("run setpriv"),
    )
}

/// The pid the kernel gives next (approximately: other processes may take some).
fn last_pid() -> u32 {
    std::fs::read_to_string("/proc/sys/kernel/ns_last_pid")
        .ok()
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or(0)
}

/// The value after `flag` in process `pid`'s command line.
fn flag_of(pid: u32, flag: &str) -> Option<String> {
    let cmdline = std::fs::read(format!("/proc/{pid}/cmdline")).ok()?;
    let args: Vec<String> = cmdline
        .split(|&b| b == 0)
        .map(|a| String::from_utf8_lossy(a).into_owned())
        .collect();
    let i = args.iter().position(|a| a == flag)?;
    args.get(i + 1).cloned()
}

/// The children of `pid` (from /proc/PID/task/*/children).
fn children(pid: u32) -> Vec<u32> {
    let mut out = Vec::new();
    if let Ok(tasks) = std::fs::read_dir(format!("/proc/{pid}/task")) {
        for t in tasks.flatten() {
            if let Ok(s) = std::fs::read_to_string(t.path().join("children")) {
                out.extend(s.split_whitespace().filter_map(|p| p.parse::<u32>().ok()));
            }
        }
    }
    out
}

#[test]
fn a_cluster_token_lives_in_a_new_private_directory_not_one_another_user_planted() {
    // The other user makes the old predictable directories, world-writable, for the
    // next pids, each holding a token of its choosing.
    let next = last_pid() + 1;
    let planted: Vec<PathBuf> = (next..next + 200)
        .map(|p| std::env::temp_dir().join(format!("dray-cluster-{p}-secrets")))
        .collect();
    let script = planted
        .iter()
        .map(|d| {
            format!(
                "mkdir -m 0777 {0} && printf attacker-token-0123456789abcdef > {0}/cluster.token && chmod 0666 {0}/cluster.token",
                d.display()
            )
        })
        .collect::<Vec<_>>()
        .join("; ");
    let second_user = match as_other_user(&script) {
        Some(out) => {
            assert!(
                planted[0].is_dir(),
                "the other user could not plant {}: {}",
                planted[0].display(),
                String::from_utf8_lossy(&out.stderr)
            );
            true
        }
        None => false,
    };
    struct Cleanup(Vec<PathBuf>);
    impl Drop for Cleanup {
        fn drop(&mut self) {
            for d in &self.0 {
                let _ = std::fs::remove_dir_all(d);
            }
        }
    }
    let _cleanup = Cleanup(planted.clone());

    let root = common::tmp("secrets");
    let mut cmd = dray();
    cmd.args([
        "cluster",
        "--workers",
        "0",
        "--base-port",
        "0",
        "--scene-root",
    ])
    .arg(&root)
    .stdout(Stdio::piped())
    .stderr(Stdio::null());
    let mut proc = Proc::spawn(cmd);
    let cluster_pid = proc.child.id();
    let stdout = proc.child.stdout.take().unwrap();
    let mut lines = Vec::new();
    for line in BufReader::new(stdout).lines() {
        let line = line.unwrap();
        let ready = line.starts_with("dray cluster ready");
        lines.push(line);
        if ready {
            break;
        }
    }
    assert!(
        lines
            .last()
            .is_some_and(|l| l.starts_with("dray cluster ready")),
        "{lines:?}"
    );
    let coordinator = children(cluster_pid)
        .into_iter()
        .find(|&c| flag_of(c, "--cluster-token-file").is_some())
        .expect("the coordinator child, with its --cluster-token-file");
    let token_file = PathBuf::from(flag_of(coordinator, "--cluster-token-file").unwrap());
    let dir = token_file.parent().unwrap().to_path_buf();

    // Not the planted directory, nor any name made from the pid.
    let old = std::env::temp_dir().join(format!("dray-cluster-{cluster_pid}-secrets"));
    assert_ne!(dir, old, "the cluster used the predictable directory");
    assert!(!planted.contains(&dir), "{}", dir.display());
    let name = dir.file_name().unwrap().to_string_lossy().into_owned();
    assert!(
        name.starts_with("dray-cluster-") && !name.contains(&cluster_pid.to_string()),
        "{name}"
    );
    // Made by us, owner-only; the token only we can read, and not the attacker's.
    let m = std::fs::symlink_metadata(&dir).unwrap();
    assert!(m.is_dir() && !m.file_type().is_symlink());
    // SAFETY: geteuid has no preconditions.
    let me = unsafe { libc::geteuid() };
    assert_eq!((m.uid(), m.permissions().mode() & 0o777), (me, 0o700));
    let t = std::fs::symlink_metadata(&token_file).unwrap();
    assert!(t.is_file());
    assert_eq!((t.uid(), t.permissions().mode() & 0o777), (me, 0o600));
    let token = std::fs::read_to_string(&token_file).unwrap();
    assert!(
        !token.contains("attacker"),
        "the cluster runs on the attacker's token"
    );
    if planted.contains(&old) {
        // The directory planted for this very pid was left alone.
        let planted_token = std::fs::read_to_string(old.join("cluster.token")).unwrap();
        assert!(planted_token.starts_with("attacker-token"));
    }

    if second_user {
        // The other user can neither read the token nor put anything beside it.
        let out = as_other_user(&format!(
            "cat {0}; echo x > {1}/planted; ln -s /etc/passwd {1}/cluster.token2; ls {1}",
            token_file.display(),
            dir.display()
        ))
        .unwrap();
        let said = String::from_utf8_lossy(&out.stdout);
        assert!(
            !said.contains(token.trim()),
            "the other user read the token"
        );
        assert!(!dir.join("planted").exists() && !dir.join("cluster.token2").exists());
    }

    proc.signal(libc::SIGTERM);
    assert!(
        proc.wait_timeout(30.0).is_some(),
        "the cluster did not stop"
    );
    assert!(!dir.exists(), "the secrets directory outlived the cluster");
    let _ = std::fs::remove_dir_all(&root);
}

/// docs/security.md "Hardening, second round", item 14: a SIGTERM while the coordinator
/// cuts a large scene into a package
/// leaves no package behind (partial or whole).
#[test]
fn a_stop_during_a_large_preparation_leaves_no_partial_package() {
    let root = common::tmp("stop-prep");
    let work = root.join("work");
    let mut cmd = dray();
    cmd.args(["coordinator", "--listen", "127.0.0.1:0", "--scene-root"])
        .arg(&root)
        .arg("--work-dir")
        .arg(&work)
        .env("DRAY_LOG", "warn,dray_coordinator::membership=info")
        .env("NO_COLOR", "1")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let mut coordinator = Proc::spawn(cmd);
    let addr = listening_address(&mut coordinator.child).expect("the coordinator's address");
    let log = support::capture_stderr(&mut coordinator.child);
    // A worker, so that jobs are cut into packages for workers.
    let mut cmd = dray();
    cmd.args(["worker", "--coordinator", &format!("http://{addr}")])
        .args(["--listen", "127.0.0.1:0", "--threads", "1"])
        .stdout(Stdio::null())
        .stderr(Stdio::null());
    let _worker = Proc::spawn(cmd);
    assert!(
        eventually(60.0, || log.lock().unwrap().contains("worker registered")),
        "the worker did not register: {}",
        log.lock().unwrap()
    );

    // Two million triangles: hundreds of MB of package, seconds to cut.
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", &addr, "soup:2000000", "-q"])
        .args(["--width", "8", "--height", "8", "--spp", "1"])
        .arg("--output")
        .arg(root.join("never.png"))
        .stdout(Stdio::null())
        .stderr(Stdio::null());
    let _submit = Proc::spawn(cmd);
    let job_dirs = |work: &Path| -> Vec<PathBuf> {
        // The job store (`state`) is not a job's folder.
        std::fs::read_dir(work)
            .map(|d| {
                d.flatten()
                    .map(|e| e.path())
                    .filter(|p| !p.ends_with("state"))
                    .collect()
            })
            .unwrap_or_default()
    };
    // The cut has begun when the job's folder holds files.
    assert!(
        eventually(120.0, || {
            job_dirs(&work)
                .iter()
                .any(|d| std::fs::read_dir(d).is_ok_and(|mut e| e.next().is_some()))
        }),
        "no package was being written in {}: {}",
        work.display(),
        log.lock().unwrap()
    );
    let written: u64 = job_dirs(&work)
        .iter()
        .flat_map(|d| std::fs::read_dir(d).into_iter().flatten().flatten())
        .filter_map(|e| e.metadata().ok())
        .map(|m| m.len())
        .sum();
    coordinator.signal(libc::SIGTERM);
    let status = coordinator
        .wait_timeout(60.0)
        .expect("the coordinator did not stop within 60 s of SIGTERM");
    assert!(status.success(), "{status:?}: {}", log.lock().unwrap());
    let left = job_dirs(&work);
    assert!(
        left.is_empty(),
        "left in the work directory after the stop ({written} bytes were written when it came): {left:?}"
    );
    let _ = std::fs::remove_dir_all(&root);
}
