//! What a job attempt has to report to the coordinator: results and counters gathered
//! since its last report.
//!
//! The parts that produce results (tracing steps, the peer and cache links) never touch
//! the job's report: each posts its own [`Report`] to the job's actor
//! ([`crate::job_actor`]), which adds it to the one it is gathering ([`Report::absorb`]). A
//! tracing step's results travel as one `Report`, so they always land in the same report
//! to the coordinator: no credit arrives there before the contributions of its rays.

use dray_core::aov::AOV_WORDS;
use dray_core::credit::Credit;
use dray_core::integrator::RayKind;

use crate::pixel_sums::PixelSums;
use crate::tickets::TicketLedger;

/// Results of one job attempt: gathered by its actor, or posted to it by one producer.
#[derive(Default)]
pub struct Report {
    pub sums: PixelSums,
    /// AOV sums of first hits (`dray_core::aov`), merged by sum key as `sums`.
    pub aovs: PixelSums<AOV_WORDS>,
    pub credits: Vec<(u32, Credit)>,
    pub traced: [u64; RayKind::COUNT],
    pub nonfinite: u64,
    pub clamped: u64,
    /// Contributions scaled down by `--clamp-indirect`.
    pub clamped_indirect: u64,
    pub bytes: u64,
    pub rays_sent: u64,
    pub rays_forwarded: u64,
    pub idle_seconds: f64,
    /// Peers the job's rays could not be sent to.
    pub unreachable: Vec<String>,
    pub failure: Option<String>,
    /// Contributions and credit owed to ray-cache tickets; returned to their cache
    /// actors (and acknowledged) before the same credit goes to the coordinator.
    pub tickets: TicketLedger,
    /// Rays a cache answered whose domain another worker owns (not sent).
    pub cache_rays_not_sent: u64,
    /// Rays that went past an unreachable cache host.
    pub cache_rays_bypassed: u64,
    /// Rays a hit map skipped past, or answered as occluded at, a domain another worker
    /// owns (not sent).
    pub phm_rays_not_sent: u64,
    /// Bytes of lookups and ticket returns sent to cache hosts.
    pub cache_bytes: u64,
    /// Cache hosts found unreachable.
    pub lost_cache_hosts: Vec<String>,
    /// Bytes exchanged with other processes, by kind.
    pub traffic: crate::traffic::Traffic,
}

impl Report {
    /// Whether there is nothing to report but idle time (which rides along with the
    /// next report, or with the queue report's tick).
    pub fn is_empty(&self) -> bool {
        self.sums.is_empty()
            && self.aovs.is_empty()
            && self.credits.is_empty()
            && self.traced.iter().all(|&n| n == 0)
            && self.nonfinite == 0
            && self.clamped == 0
            && self.clamped_indirect == 0
            && self.bytes == 0
            && self.rays_sent == 0
            && self.rays_forwarded == 0
            && self.unreachable.is_empty()
            && self.failure.is_none()
            && self.tickets.is_empty()
            && self.cache_rays_not_sent == 0
            && self.cache_rays_bypassed == 0
            && self.phm_rays_not_sent == 0
            && self.cache_bytes == 0
            && self.lost_cache_hosts.is_empty()
            && self.traffic.is_empty()
    }

    /// Add `other` to this report: sums, credit, tickets and counters add up, names
    /// (unreachable peers, lost hosts) appear once, and the first failure is kept.
    pub fn absorb(&mut self, other: Report) {
        let Report {
            sums,
            aovs,
            mut credits,
            traced,
            nonfinite,
            clamped,
            clamped_indirect,
            bytes,
            rays_sent,
            rays_forwarded,
            idle_seconds,
            unreachable,
            failure,
            tickets,
            cache_rays_not_sent,
            cache_rays_bypassed,
            phm_rays_not_sent,
            cache_bytes,
            lost_cache_hosts,
            traffic,
        } = other;
        self.sums.absorb(sums);
        self.aovs.absorb(aovs);
        self.credits.append(&mut credits);
        for (k, n) in traced.iter().enumerate() {
            self.traced[k] += n;
        }
        self.nonfinite += nonfinite;
        self.clamped += clamped;
        self.clamped_indirect += clamped_indirect;
        self.bytes += bytes;
        self.rays_sent += rays_sent;
        self.rays_forwarded += rays_forwarded;
        self.idle_seconds += idle_seconds;
        add_names(&mut self.unreachable, unreachable);
        if self.failure.is_none() {
            self.failure = failure;
        }
        self.tickets.merge(tickets);
        self.cache_rays_not_sent += cache_rays_not_sent;
        self.cache_rays_bypassed += cache_rays_bypassed;
        self.phm_rays_not_sent += phm_rays_not_sent;
        self.cache_bytes += cache_bytes;
        add_names(&mut self.lost_cache_hosts, lost_cache_hosts);
        self.traffic.add(&traffic);
    }

    /// What was noted while this report's tickets went back to their cache actors
    /// (their bytes, and hosts found lost), taken from `later`: it rides along with this
    /// report rather than the next one, which may never be sent if this one ends the job.
    pub fn take_link_counters(&mut self, later: &mut Report) {
        self.cache_bytes += std::mem::take(&mut later.cache_bytes);
        self.traffic.add(&std::mem::take(&mut later.traffic));
        add_names(
            &mut self.lost_cache_hosts,
            std::mem::take(&mut later.lost_cache_hosts),
        );
    }
}

/// Add the names of `more` not already in `names`.
fn add_names(names: &mut Vec<String>, more: Vec<String>) {
    for n in more {
        if !names.contains(&n) {
            names.push(n);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn credit(n: u64) -> Credit {
        Credit::from_wire(n)
    }

    #[test]
    fn absorbed_reports_add_up_and_keep_the_first_failure() {
        let mut a = Report::default();
        assert!(a.is_empty());
        a.sums.add(3, [1, 2, 3]);
        a.credits.push((0, credit(5)));
        a.traced[0] = 2;
        a.unreachable.push("w1".into());
        a.failure = Some("first".into());
        let mut b = Report::default();
        b.sums.add(3, [10, 20, 30]);
        b.sums.add(4, [1, 1, 1]);
        b.credits.push((0, credit(7)));
        b.traced[0] = 1;
        b.idle_seconds = 0.5;
        b.unreachable = vec!["w1".into(), "w2".into()];
        b.failure = Some("second".into());
        a.absorb(b);
        let mut sums = a.sums.drain();
        sums.sort_unstable_by_key(|s| s.0);
        assert_eq!(sums, vec![(3, [11, 22, 33]), (4, [1, 1, 1])]);
        assert_eq!(a.credits, vec![(0, credit(5)), (0, credit(7))]);
        assert_eq!(a.traced[0], 3);
        assert_eq!(a.idle_seconds, 0.5);
        assert_eq!(a.unreachable, vec!["w1".to_string(), "w2".to_string()]);
        assert_eq!(a.failure.as_deref(), Some("first"));
    }

    #[test]
    fn link_counters_noted_while_returning_ride_with_the_report() {
        let mut sent = Report::default();
        let mut later = Report {
            cache_bytes: 40,
            lost_cache_hosts: vec!["h".into()],
            rays_sent: 9,
            ..Report::default()
        };
        sent.take_link_counters(&mut later);
        assert_eq!(sent.cache_bytes, 40);
        assert_eq!(sent.lost_cache_hosts, vec!["h".to_string()]);
        assert_eq!(later.cache_bytes, 0);
        assert!(later.lost_cache_hosts.is_empty());
        assert_eq!(later.rays_sent, 9, "other results stay for the next report");
        assert_eq!(sent.rays_sent, 0);
    }
}
