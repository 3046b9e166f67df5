//! Real `dray` processes for the tests of `dray submit`, `dray cluster` and the
//! reflection client: every process is held by a [`Proc`], which kills and reaps it when
//! dropped, so a failing assertion never leaves a server behind.
#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, ChildStdout, Command, Stdio};

/// The `dray` binary under test.
pub fn dray() -> Command {
    Command::new(env!("CARGO_BIN_EXE_dray"))
}

/// A child process, killed (SIGKILL) and reaped on drop.
pub struct Proc {
    pub child: Child,
}

impl Proc {
    pub fn spawn(mut cmd: Command) -> Proc {
        Proc {
            child: cmd.spawn().expect("spawn a dray process"),
        }
    }

    pub fn pid(&self) -> i32 {
        self.child.id() as i32
    }

    /// Send `sig` (libc::SIGTERM, SIGINT, ...).
    pub fn signal(&self, sig: i32) {
        // SAFETY: kill(2) on our own child, not yet reaped.
        unsafe {
            libc::kill(self.pid(), sig);
        }
    }

    /// Wait up to `secs` for the process to exit; its status, or None on timeout.
    pub fn wait_timeout(&mut self, secs: f64) -> Option<std::process::ExitStatus> {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs_f64(secs);
        loop {
            if let Ok(Some(s)) = self.child.try_wait() {
                return Some(s);
            }
            if std::time::Instant::now() >= deadline {
                return None;
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A `dray coordinator` on a free port (port 0; the address is read from its first line).
pub struct Coordinator {
    pub proc: Proc,
    /// host:port
    pub addr: String,
}

pub fn coordinator(scene_root: &Path) -> Coordinator {
    let mut cmd = dray();
    cmd.args(["coordinator", "--listen", "127.0.0.1:0", "--scene-root"])
        .arg(scene_root)
        .stdout(Stdio::piped())
        .stderr(Stdio::null());
    let mut proc = Proc::spawn(cmd);
    let stdout = proc.child.stdout.take().expect("coordinator stdout");
    let line = first_line(stdout);
    let addr = line
        .trim()
        .rsplit(' ')
        .next()
        .filter(|a| a.contains(':'))
        .unwrap_or_else(|| panic!("no address in the coordinator's first line {line:?}"))
        .to_string();
    Coordinator { proc, addr }
}

fn first_line(stdout: ChildStdout) -> String {
    let mut line = String::new();
    BufReader::new(stdout)
        .read_line(&mut line)
        .expect("read the first line");
    line
}

/// A port that was free a moment ago (bind port 0 and let it go).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("bind a free port")
        .port()
}

/// Whether `pid` is still a live (not zombie) process.
pub fn alive(pid: i32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        // The state follows the parenthesised command name.
        Ok(s) => s
            .rsplit(')')
            .next()
            .and_then(|rest| rest.split_whitespace().next())
            .is_some_and(|state| state != "Z" && state != "X"),
        Err(_) => false,
    }
}

/// Poll until `pid` is gone, up to `secs`.
pub fn gone_within(pid: i32, secs: f64) -> bool {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs_f64(secs);
    while std::time::Instant::now() < deadline {
        if !alive(pid) {
            return true;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    !alive(pid)
}
