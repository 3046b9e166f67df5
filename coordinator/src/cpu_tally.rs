//! CPU seconds of the processes that ran one job (`JobStats.cpu_seconds`): each
//! process's clock from the earliest set-up any actor in it reported to the latest
//! reading, summed over processes. Actors of one process (the embedded mode's workers,
//! and the coordinator beside them) report the same clock under the same token, so a
//! process counts once however many actors it holds.

use std::collections::HashMap;

use dray_proto::v1::ProcessCpu;

/// Per process token: (clock at the earliest set-up, latest reading), and the sum of
/// their spans kept as each reading arrives, so reading it costs the same for 10,000
/// processes as for one (a job publishes it with every report).
#[derive(Debug, Default)]
pub struct CpuTally {
    processes: HashMap<u64, (f64, f64)>,
    /// The sum of every process's span, in whole nanoseconds (integers, so the sum does
    /// not depend on the order readings arrived in).
    total_ns: u64,
}

/// A span of a process clock in whole nanoseconds (0 when it runs backwards).
fn span_ns(from: f64, to: f64) -> u64 {
    ((to - from).max(0.0) * 1e9).round() as u64
}

impl CpuTally {
    /// A tally that starts with this (the coordinator's) process, now.
    pub fn here() -> CpuTally {
        let mut t = CpuTally::default();
        let now = dray_net::cpu::process_cpu_seconds();
        t.note(&ProcessCpu {
            process: dray_net::cpu::process_token(),
            at_setup: now,
            now,
        });
        t
    }

    /// One reading of a process's clock.
    pub fn note(&mut self, c: &ProcessCpu) {
        if !(c.at_setup.is_finite() && c.now.is_finite()) {
            return;
        }
        let e = self
            .processes
            .entry(c.process)
            .or_insert((c.at_setup, c.at_setup));
        let before = span_ns(e.0, e.1);
        e.0 = e.0.min(c.at_setup);
        e.1 = e.1.max(c.now);
        let after = span_ns(e.0, e.1);
        self.total_ns = self.total_ns.saturating_sub(before).saturating_add(after);
    }

    /// Read this (the coordinator's) process's clock again.
    pub fn note_here(&mut self) {
        let now = dray_net::cpu::process_cpu_seconds();
        self.note(&ProcessCpu {
            process: dray_net::cpu::process_token(),
            at_setup: now,
            now,
        });
    }

    /// The sum over processes of the clock's advance.
    pub fn seconds(&self) -> f64 {
        self.total_ns as f64 * 1e-9
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_process_counts_once_from_its_earliest_setup() {
        let mut t = CpuTally::default();
        let at = |process, at_setup, now| ProcessCpu {
            process,
            at_setup,
            now,
        };
        // Two workers in one process (same token), one in another.
        t.note(&at(1, 10.0, 11.0));
        t.note(&at(1, 10.5, 12.5));
        t.note(&at(2, 3.0, 4.0));
        t.note(&at(1, 10.5, 12.0)); // an older reading changes nothing
        t.note(&at(2, f64::NAN, 9.0)); // nor does a broken one
        assert_eq!(t.seconds(), 2.5 + 1.0);
        assert_eq!(t.total_ns, 3_500_000_000);
    }
}
