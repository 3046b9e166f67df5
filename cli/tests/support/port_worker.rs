//! A `dray worker` on a fixed port, so that a replacement started after a kill takes the
//! same endpoint, as `dray cluster` restarts its members (cli/tests/lost_worker.rs,
//! cli/tests/chaos.rs).

use std::process::Stdio;

use super::{Captured, Proc, capture_stderr, dray};

/// A worker process on `port`, its stderr captured.
pub struct PortWorker {
    pub port: u16,
    pub proc: Proc,
    pub log: Captured,
}

impl PortWorker {
    /// Start a one-thread worker on 127.0.0.1:`port` registering with the coordinator at
    /// `addr` (host:port).
    pub fn start(addr: &str, port: u16) -> PortWorker {
        PortWorker::start_with(addr, port, &[])
    }

    /// [`PortWorker::start`] with `extra` flags.
    pub fn start_with(addr: &str, port: u16, extra: &[&str]) -> PortWorker {
        let mut cmd = dray();
        cmd.args(["worker", "--coordinator", &format!("http://{addr}")])
            .args(["--listen", &format!("127.0.0.1:{port}"), "--threads", "1"])
            .args(extra)
            .env("NO_COLOR", "1")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        let mut proc = Proc::spawn(cmd);
        let log = capture_stderr(&mut proc.child);
        PortWorker { port, proc, log }
    }
}
