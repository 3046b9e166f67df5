//! A job's traffic as a trace: one JSON line per traced step, per domain load, per
//! forwarded batch and per cache-link message to or from another process on this
//! worker, for replay in a simulator (docs/caches.md "Simulation at scale",
//! `benches/sim/replay.py`).
//!
//! Recorded only for a job that asks (`JobSpec.trace`) on a worker given a directory
//! for traces (`WorkerConfig::trace_dir`, `dray worker --trace-dir`): a job spec names no
//! path, so a client cannot make workers write where it likes. With tracing off a job
//! holds no [`TrafficTrace`] and the tracing threads take no clock: the only cost is
//! the `Option` they test.
//!
//! The file is `<dir>/<job>.<attempt>.<worker>.jsonl` (names reduced to `[A-Za-z0-9_-]`).
//! Times are nanoseconds from the job's setup on this worker (its monotonic clock); CPU
//! is the tracing thread's own clock (`CLOCK_THREAD_CPUTIME_ID`), so a thread that waits
//! for a core counts only what it computed. The schema (version
//! [`TRACE_VERSION`]) is documented in docs/caches.md "The trace's schema"; lines are
//! buffered and written whole, with `O_APPEND`.

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Instant;

use dray_net::traffic::TrafficKind;

/// The trace schema's version, in every line (`"v"`). 2 added the `cache` record; the
/// replay reads 1 and 2.
pub const TRACE_VERSION: u32 = 2;

/// Buffered bytes written out at once.
const FLUSH_AT: usize = 64 * 1024;

/// Why a trace file cannot be opened.
#[derive(Debug, thiserror::Error)]
#[error("cannot open the traffic trace {path}: {source}")]
pub struct TraceOpenError {
    pub path: PathBuf,
    #[source]
    pub source: std::io::Error,
}

/// Rays a step sent on to one domain: how many, and their encoded bytes (records and
/// tickets, as `TrafficStats.rays` counts them).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Sent {
    pub domain: u32,
    pub rays: u64,
    pub bytes: u64,
}

/// One traced step: a batch of rays in one domain, or a chunk of a tile's camera rays
/// (`domain` None).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StepRecord {
    pub domain: Option<u32>,
    pub rays_in: u64,
    pub t0_ns: u64,
    pub t1_ns: u64,
    pub cpu_ns: u64,
    /// Rays traced in the step, every kind (rays traced in resident domains on the way
    /// included).
    pub traced: u64,
    /// Per destination domain, rays that left the step: to a peer or to this worker's
    /// own queue (`remote` says which).
    pub out: Vec<(Sent, bool)>,
    /// Rays handed to wall actors, and rays not sent thanks to caches and hit maps.
    pub lookups: u64,
    pub cache_not_sent: u64,
    pub phm_not_sent: u64,
}

/// One job's trace file on this worker.
pub struct TrafficTrace {
    worker: String,
    start: Instant,
    path: PathBuf,
    out: Mutex<(std::fs::File, Vec<u8>)>,
    /// Whether this worker's own cache host was declared ([`TrafficTrace::cache`]).
    declared: std::sync::atomic::AtomicBool,
}

impl TrafficTrace {
    /// Open (append to) the trace of attempt `attempt` of job `job` by worker `worker`
    /// in `dir`, and write its header line.
    pub fn open(
        dir: &Path,
        job: &str,
        attempt: u32,
        worker: &str,
        threads: usize,
    ) -> Result<TrafficTrace, TraceOpenError> {
        let path = dir.join(format!("{}.{attempt}.{}.jsonl", clean(job), clean(worker)));
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(|source| TraceOpenError {
                path: path.clone(),
                source,
            })?;
        let t = TrafficTrace {
            worker: worker.to_string(),
            start: Instant::now(),
            path,
            out: Mutex::new((file, Vec::new())),
            declared: Default::default(),
        };
        let mut line = String::new();
        let _ = write!(
            line,
            r#"{{"v":{TRACE_VERSION},"rec":"worker","worker":{},"job":{},"attempt":{attempt},"threads":{threads}}}"#,
            json_str(worker),
            json_str(job),
        );
        t.push(line);
        Ok(t)
    }

    /// Where the trace is written.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Nanoseconds since the job was set up here.
    pub fn now_ns(&self) -> u64 {
        self.start.elapsed().as_nanos() as u64
    }

    /// One traced step.
    pub fn step(&self, r: &StepRecord) {
        let mut line = String::with_capacity(160 + 48 * r.out.len());
        let domain = r.domain.map_or("null".to_string(), |d| d.to_string());
        let _ = write!(
            line,
            r#"{{"v":{TRACE_VERSION},"rec":"step","worker":{},"domain":{domain},"rays_in":{},"t0":{},"t1":{},"cpu_ns":{},"traced":{},"lookups":{},"cache_not_sent":{},"phm_not_sent":{},"out":["#,
            json_str(&self.worker),
            r.rays_in,
            r.t0_ns,
            r.t1_ns,
            r.cpu_ns,
            r.traced,
            r.lookups,
            r.cache_not_sent,
            r.phm_not_sent,
        );
        for (i, (s, remote)) in r.out.iter().enumerate() {
            let sep = if i > 0 { "," } else { "" };
            let _ = write!(
                line,
                r#"{sep}{{"domain":{},"rays":{},"bytes":{},"remote":{remote}}}"#,
                s.domain, s.rays, s.bytes
            );
        }
        line.push_str("]}");
        self.push(line);
    }

    /// A domain load: its resident bytes and the time it took (read and build).
    pub fn load(&self, domain: u32, bytes: u64, t0_ns: u64, t1_ns: u64, cpu_ns: u64) {
        self.push(format!(
            r#"{{"v":{TRACE_VERSION},"rec":"load","worker":{},"domain":{domain},"bytes":{bytes},"t0":{t0_ns},"t1":{t1_ns},"cpu_ns":{cpu_ns}}}"#,
            json_str(&self.worker)
        ));
    }

    /// Rays queued here for a domain this worker no longer owns, sent on to an owner.
    pub fn forward(&self, sent: Sent) {
        self.push(format!(
            r#"{{"v":{TRACE_VERSION},"rec":"forward","worker":{},"t":{},"domain":{},"rays":{},"bytes":{}}}"#,
            json_str(&self.worker),
            self.now_ns(),
            sent.domain,
            sent.rays,
            sent.bytes
        ));
    }

    /// One cache-link message of `kind` and `bytes` (encoded, as `TrafficStats` counts
    /// it), to (`sent`) or from the cache host at `endpoint`: one line per message (a
    /// batch of up to 4,096 lookups, of returns or of entries, a merge, an answer, an
    /// ack), not per ray. `mine` is the endpoint of the cache host beside this worker:
    /// the first message declares it in a `cache_host` line, so that the replay can
    /// place a host's messages on the node of the worker it runs beside (a host no
    /// worker declares is a stand-alone one, or beside a worker that sent nothing).
    pub fn cache(
        &self,
        mine: Option<&str>,
        endpoint: &str,
        kind: TrafficKind,
        sent: bool,
        bytes: u64,
    ) {
        if let Some(mine) = mine
            && !self
                .declared
                .swap(true, std::sync::atomic::Ordering::Relaxed)
        {
            self.push(format!(
                r#"{{"v":{TRACE_VERSION},"rec":"cache_host","worker":{},"host":{}}}"#,
                json_str(&self.worker),
                json_str(mine)
            ));
        }
        self.push(format!(
            r#"{{"v":{TRACE_VERSION},"rec":"cache","worker":{},"t":{},"host":{},"dir":"{}","kind":"{}","msgs":1,"bytes":{bytes}}}"#,
            json_str(&self.worker),
            self.now_ns(),
            json_str(endpoint),
            if sent { "sent" } else { "received" },
            kind.name(),
        ));
    }

    fn push(&self, mut line: String) {
        line.push('\n');
        let mut g = dray_sync::lock(&self.out);
        g.1.extend_from_slice(line.as_bytes());
        if g.1.len() >= FLUSH_AT {
            write_out(&mut g);
        }
    }

    /// Write what is buffered (also done when the trace is dropped).
    pub fn flush(&self) {
        write_out(&mut dray_sync::lock(&self.out));
    }
}

impl Drop for TrafficTrace {
    fn drop(&mut self) {
        self.flush();
    }
}

/// Whole lines only, in one `write` of an `O_APPEND` file, so traces of several workers
/// of one process appended to one file would not interleave within a line.
fn write_out(g: &mut (std::fs::File, Vec<u8>)) {
    if g.1.is_empty() {
        return;
    }
    if let Err(e) = g.0.write_all(&g.1) {
        tracing::warn!("cannot write a traffic trace: {e}");
    }
    g.1.clear();
}

/// `s` reduced to a file-name part.
fn clean(s: &str) -> String {
    s.chars()
        .take(64)
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// `s` as a JSON string.
fn json_str(s: &str) -> String {
    let mut o = String::with_capacity(s.len() + 2);
    o.push('"');
    for c in s.chars() {
        match c {
            '"' => o.push_str("\\\""),
            '\\' => o.push_str("\\\\"),
            c if (c as u32) < 0x20 => {
                let _ = write!(o, "\\u{:04x}", c as u32);
            }
            c => o.push(c),
        }
    }
    o.push('"');
    o
}

/// This thread's CPU time in nanoseconds.
pub fn thread_cpu_ns() -> u64 {
    dray_net::cpu::thread_cpu_nanos()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_are_json_with_the_version_and_written_on_flush() {
        let dir = std::env::temp_dir().join(format!("dray-trace-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let t = TrafficTrace::open(&dir, "job/1", 0, "w\"1", 2).expect("open");
        assert!(t.path().ends_with("job_1.0.w_1.jsonl"), "{:?}", t.path());
        t.step(&StepRecord {
            domain: Some(3),
            rays_in: 10,
            t0_ns: 5,
            t1_ns: 9,
            cpu_ns: 4,
            traced: 12,
            out: vec![
                (
                    Sent {
                        domain: 1,
                        rays: 2,
                        bytes: 80,
                    },
                    true,
                ),
                (
                    Sent {
                        domain: 2,
                        rays: 1,
                        bytes: 40,
                    },
                    false,
                ),
            ],
            ..StepRecord::default()
        });
        t.step(&StepRecord::default());
        t.load(3, 1000, 1, 2, 1);
        t.forward(Sent {
            domain: 1,
            rays: 2,
            bytes: 80,
        });
        let mine = Some("http://127.0.0.1:7000");
        t.cache(
            mine,
            "http://127.0.0.1:7001",
            TrafficKind::Lookups,
            true,
            300,
        );
        t.cache(
            mine,
            "http://127.0.0.1:7001",
            TrafficKind::Answers,
            false,
            20,
        );
        let path = t.path().to_path_buf();
        drop(t);
        let text = std::fs::read_to_string(&path).expect("read");
        let _ = std::fs::remove_dir_all(&dir);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 8);
        assert!(
            lines[0].contains(r#""worker":"w\"1","job":"job/1""#),
            "{}",
            lines[0]
        );
        let head = format!(r#"{{"v":{TRACE_VERSION},"rec":""#);
        assert!(lines.iter().all(|l| l.starts_with(&head)), "{text}");
        assert!(lines[1].ends_with(
            r#""out":[{"domain":1,"rays":2,"bytes":80,"remote":true},{"domain":2,"rays":1,"bytes":40,"remote":false}]}"#
        ));
        assert!(lines[2].contains(r#""domain":null"#) && lines[2].ends_with(r#""out":[]}"#));
        assert_eq!(
            lines
                .iter()
                .map(|l| l.matches('{').count())
                .collect::<Vec<_>>(),
            [1, 3, 1, 1, 1, 1, 1, 1],
            "balanced records"
        );
        assert!(
            lines[5]
                .ends_with(r#""rec":"cache_host","worker":"w\"1","host":"http://127.0.0.1:7000"}"#),
            "the first message declares the worker's own host, once: {}",
            lines[5]
        );
        assert!(
            lines[6].ends_with(r#""host":"http://127.0.0.1:7001","dir":"sent","kind":"lookups","msgs":1,"bytes":300}"#),
            "{}",
            lines[6]
        );
        assert!(
            lines[7].ends_with(r#""host":"http://127.0.0.1:7001","dir":"received","kind":"answers","msgs":1,"bytes":20}"#),
            "{}",
            lines[7]
        );
    }
}
