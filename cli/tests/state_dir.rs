//! The state directory is taken only when no other local user can change it (issue 45,
//! item 3; docs/security.md "State directory"). A real `dray coordinator` process, run
//! by root as a service would be, against directories another user (`nobody`, through
//! `setpriv`) prepared: a planted `lock` link must not truncate its target, a directory
//! that user owns or that anyone may write is refused with a message naming it, and an
//! `images` link is refused. Nothing is written through any of them.

mod common;
mod support;

use std::os::unix::fs::PermissionsExt;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use support::Proc;

const NOBODY: u32 = 65534;

/// `dray coordinator --state-dir DIR` on a free port, killed and reaped when dropped
/// (also when an assertion fails).
fn coordinator(dir: &Path, stderr: Stdio) -> Proc {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_dray"));
    cmd.args(["coordinator", "--listen", "127.0.0.1:0"])
        .arg("--state-dir")
        .arg(dir)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(stderr);
    Proc::spawn(cmd)
}

/// Run `dray coordinator --state-dir DIR` and return its stderr once it exits; a
/// coordinator that accepted the directory keeps running, so after 60 s without an exit
/// the test fails (and the process is killed).
fn coordinator_refuses(dir: &Path) -> String {
    let mut p = coordinator(dir, Stdio::piped());
    let status = p.wait_timeout(60.0);
    let mut err = String::new();
    if let Some(mut e) = p.child.stderr.take() {
        use std::io::Read;
        let _ = e.read_to_string(&mut err);
    }
    match status {
        Some(s) => assert!(
            !s.success(),
            "the coordinator accepted {}: {err}",
            dir.display()
        ),
        None => panic!(
            "the coordinator accepted {} and kept running: {err}",
            dir.display()
        ),
    }
    err
}

/// Run `args` as `nobody`.
fn as_nobody(args: &[&str]) {
    let out = Command::new("setpriv")
        .args(["--reuid=65534", "--regid=65534", "--clear-groups"])
        .args(args)
        .output()
        .expect("run setpriv");
    assert!(
        out.status.success(),
        "setpriv {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn root_and_setpriv() -> bool {
    // SAFETY: geteuid has no preconditions.
    if unsafe { libc::geteuid() } != 0 {
        common::dependency_missing(
            "not running as root: these tests play root's coordinator against another \
             user's files (CI runs them as root)",
        );
        return false;
    }
    if Command::new("setpriv").arg("--version").output().is_err() {
        common::dependency_missing("setpriv (util-linux) is not installed");
        return false;
    }
    true
}

#[test]
fn a_state_dir_another_user_prepared_is_refused_and_nothing_is_written_through_it() {
    if !root_and_setpriv() {
        return;
    }
    let base = common::tmp("state-dir-attack");
    std::fs::set_permissions(&base, std::fs::Permissions::from_mode(0o755)).unwrap();
    let victim = base.join("victim");
    std::fs::write(&victim, b"precious\n").unwrap();

    // nobody's own directory, open to all, with `lock` pointing at root's file.
    let planted = base.join("planted");
    std::fs::create_dir(&planted).unwrap();
    std::os::unix::fs::chown(&planted, Some(NOBODY), Some(NOBODY)).unwrap();
    as_nobody(&["chmod", "0777", planted.to_str().unwrap()]);
    as_nobody(&[
        "ln",
        "-s",
        victim.to_str().unwrap(),
        planted.join("lock").to_str().unwrap(),
    ]);
    let err = coordinator_refuses(&planted);
    assert!(
        err.contains("not safe") && err.contains(&planted.display().to_string()),
        "{err}"
    );
    assert!(err.contains("uid 65534"), "{err}");
    assert_eq!(
        std::fs::read(&victim).unwrap(),
        b"precious\n",
        "the lock's target was written"
    );

    // Root's own directory, but writable by everyone: refused too (anyone could plant).
    let open = base.join("open");
    std::fs::create_dir(&open).unwrap();
    std::fs::set_permissions(&open, std::fs::Permissions::from_mode(0o777)).unwrap();
    let err = coordinator_refuses(&open);
    assert!(err.contains("0777") && err.contains("other users"), "{err}");
    assert!(
        !open.join("lock").exists(),
        "a file was made in a refused directory"
    );

    // A link to root's private directory, planted by nobody in a shared place.
    let private = base.join("private");
    std::fs::create_dir(&private).unwrap();
    std::fs::set_permissions(&private, std::fs::Permissions::from_mode(0o700)).unwrap();
    let shared = base.join("shared");
    std::fs::create_dir(&shared).unwrap();
    std::fs::set_permissions(&shared, std::fs::Permissions::from_mode(0o1777)).unwrap();
    let link = shared.join("state");
    as_nobody(&[
        "ln",
        "-s",
        private.to_str().unwrap(),
        link.to_str().unwrap(),
    ]);
    let err = coordinator_refuses(&link);
    assert!(err.contains("symbolic link owned by uid 65534"), "{err}");
    assert!(
        !private.join("lock").exists(),
        "a file was made through the link"
    );

    // An `images` link inside an otherwise private directory.
    let state = base.join("state");
    std::fs::create_dir(&state).unwrap();
    std::fs::set_permissions(&state, std::fs::Permissions::from_mode(0o700)).unwrap();
    let elsewhere = base.join("elsewhere");
    std::fs::create_dir(&elsewhere).unwrap();
    std::os::unix::fs::symlink(&elsewhere, state.join("images")).unwrap();
    let err = coordinator_refuses(&state);
    assert!(
        err.contains("images") && err.contains("symbolic link"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&base);
}

/// A directory the coordinator makes itself is private (0700), and the files in it are
/// readable only by its user (0600).
#[test]
fn a_new_state_dir_and_its_files_are_private() {
    let base = common::tmp("state-dir-new");
    let state = base.join("a").join("state");
    let mut p = coordinator(&state, Stdio::null());
    // Wait for the database, which is made after the lock and the images folder. The
    // coordinator exiting first is the failure; the count of polls only keeps a hung
    // coordinator from hanging the test run (about 10 minutes), it times nothing.
    let db = state.join("jobs.sqlite3");
    let mut polls = 0u32;
    while !db.exists() {
        if let Ok(Some(s)) = p.child.try_wait() {
            panic!("the coordinator exited: {s}");
        }
        polls += 1;
        assert!(polls < 12_000, "the coordinator never made its database");
        std::thread::sleep(Duration::from_millis(50));
    }
    drop(p);
    let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode(&state), 0o700);
    assert_eq!(mode(&state.join("images")), 0o700);
    assert_eq!(mode(&state.join("lock")), 0o600);
    assert_eq!(mode(&db), 0o600);
    let _ = std::fs::remove_dir_all(&base);
}
