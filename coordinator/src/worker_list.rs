//! `ListWorkers`: the cluster as a dashboard shows it. Put together from three owners
//! that each know part of it: the membership (address, threads, memory and queue from
//! the last heartbeat), the running jobs' actors (owners, queue reports, rays traced per
//! worker: [`JobView`]) and the rate window here (rays per second between listings).

use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use dray_proto::v1::{DomainOwners, JobDomains, ListWorkersResponse, WorkerDomain, WorkerStatus};

use crate::job::JobView;
use crate::membership::{HeartbeatConfig, WorkerRecord};

/// Shortest window a rate is measured over: listings closer together than this reuse
/// the last rates (a burst of calls would otherwise measure noise).
const MIN_WINDOW: Duration = Duration::from_millis(500);

/// Longest window: an older sample says little about the rate now, so it is replaced and
/// the rate falls back to each job's average.
const MAX_WINDOW: Duration = Duration::from_secs(30);

/// Rays per second per worker, measured between `ListWorkers` calls from the rays each
/// job's actor counted per worker. Nothing is sampled while no one lists the workers.
#[derive(Default)]
pub struct RateWindow {
    inner: Mutex<RateState>,
}

/// Rays traced per (job, worker) at one moment.
type Sample = HashMap<(String, String), u64>;

#[derive(Default)]
struct RateState {
    /// The previous sample, and when it was taken.
    last: Option<(Instant, Sample)>,
    /// Rates measured at the last sample.
    rates: HashMap<String, f64>,
}

impl RateWindow {
    /// Rays per second per worker over the window that ends `now`. A (job, worker) pair
    /// seen in both samples adds its difference; one that is new adds its whole count
    /// only when no earlier sample exists (a first listing then reads as 0 for it).
    pub fn rates(&self, views: &[JobView], now: Instant) -> HashMap<String, f64> {
        let sample: Sample = views
            .iter()
            .flat_map(|v| {
                v.traced
                    .iter()
                    .map(|(w, n)| ((v.job_id.clone(), w.clone()), *n))
            })
            .collect();
        let mut s = dray_sync::lock(&self.inner);
        match &s.last {
            Some((at, _)) if now.saturating_duration_since(*at) < MIN_WINDOW => {
                return s.rates.clone();
            }
            Some((at, prev)) if now.saturating_duration_since(*at) <= MAX_WINDOW => {
                let dt = now.saturating_duration_since(*at).as_secs_f64();
                let mut rates: HashMap<String, f64> = HashMap::new();
                for ((job, w), n) in &sample {
                    let before = prev.get(&(job.clone(), w.clone())).copied().unwrap_or(0);
                    *rates.entry(w.clone()).or_default() += n.saturating_sub(before) as f64 / dt;
                }
                s.rates = rates;
            }
            _ => s.rates.clear(),
        }
        s.last = Some((now, sample));
        s.rates.clone()
    }
}

/// Workers on a ListWorkers page when the request says 0: a cluster of up to this many
/// comes in one page.
pub const DEFAULT_PAGE_SIZE: usize = 100;
/// Most workers on one page, whatever the request asks (ListJobs's largest page too).
pub const MAX_PAGE_SIZE: usize = 1000;

/// Where a ListWorkers page starts and how many workers it holds, from the request.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PageRequest {
    /// List workers whose ids sort after this one; `None` for the first page.
    pub after: Option<String>,
    /// Most workers on the page.
    pub size: usize,
}

impl PageRequest {
    /// `page_size` (0: [`DEFAULT_PAGE_SIZE`], at most [`MAX_PAGE_SIZE`]) and
    /// `page_token` (empty, or a `next_page_token` this server gave: the id of the last
    /// worker of the previous page). Anything else is an error naming the field.
    pub fn parse(page_size: u32, page_token: &str) -> Result<PageRequest, String> {
        let size = match page_size as usize {
            0 => DEFAULT_PAGE_SIZE,
            n => n.min(MAX_PAGE_SIZE),
        };
        if page_token.is_empty() {
            return Ok(PageRequest { after: None, size });
        }
        if !is_worker_id(page_token) {
            return Err(format!(
                "page_token: {} is not a ListWorkers page token; pass the previous page's \
                 next_page_token, or none for the first page",
                crate::text::bounded(page_token)
            ));
        }
        Ok(PageRequest {
            after: Some(page_token.to_string()),
            size,
        })
    }

    /// Whether this is the first page (the one that carries the jobs' tables).
    pub fn first(&self) -> bool {
        self.after.is_none()
    }
}

/// Whether `s` has the shape of a worker id (`Membership::register`: `w`, a number, `-`,
/// eight hex digits). A token from an earlier coordinator passes: it is still a place
/// in id order.
fn is_worker_id(s: &str) -> bool {
    let Some((n, nonce)) = s.strip_prefix('w').and_then(|r| r.split_once('-')) else {
        return false;
    };
    !n.is_empty()
        && n.len() <= 20
        && n.bytes().all(|b| b.is_ascii_digit())
        && nonce.len() == 8
        && nonce.bytes().all(|b| b.is_ascii_hexdigit())
}

/// The ListWorkers answer for `workers` (one page of the registered workers, in the
/// order given) and the running jobs' `views`, with `rates` from
/// [`RateWindow::rates`]. A worker is "silent" once it missed two heartbeats, "busy"
/// while some running job lists it, else "idle". Jobs are listed newest first when
/// `with_jobs`. `next_page_token` is left empty for the caller to fill.
pub fn list(
    workers: &[WorkerRecord],
    mut views: Vec<JobView>,
    rates: &HashMap<String, f64>,
    heartbeat: HeartbeatConfig,
    now: Instant,
    with_jobs: bool,
) -> ListWorkersResponse {
    views.sort_by(|a, b| {
        b.submitted_at
            .cmp(&a.submitted_at)
            .then_with(|| a.job_id.cmp(&b.job_id))
    });
    let mut lists = PageLists {
        // Only this page's workers get their lists made.
        on_page: workers.iter().map(|w| w.id.as_str()).collect(),
        jobs_of: BTreeMap::new(),
        domains_of: BTreeMap::new(),
    };
    for v in &views {
        lists.add(v);
    }
    let silent_after = heartbeat.interval.saturating_mul(2);
    let workers = workers
        .iter()
        .map(|w| lists.status(w, rates, silent_after, now))
        .collect();
    let jobs = if !with_jobs {
        Vec::new()
    } else {
        views.iter().map(job_domains).collect()
    };
    ListWorkersResponse {
        workers,
        jobs,
        next_page_token: String::new(),
    }
}

/// The jobs and domains of each worker on a page, gathered from the running jobs'
/// views in one pass, then taken out worker by worker.
///
/// Everything here is linear in the domains and queue entries: with 65,536 domains a
/// scan per domain (which an owned-but-unreported domain and a domain's queue sum each
/// used to make) took ListWorkers to 7 s for one job and 123 s for four.
struct PageLists<'a> {
    /// The page's workers: only they get their lists made.
    on_page: HashSet<&'a str>,
    jobs_of: BTreeMap<&'a str, Vec<String>>,
    domains_of: BTreeMap<&'a str, Vec<WorkerDomain>>,
}

impl<'a> PageLists<'a> {
    /// What `v`, a running job's view, says of the page's workers: the job, the domains
    /// they reported queues for, and the domains they own but have not reported yet.
    fn add(&mut self, v: &'a JobView) {
        // Domains each worker reported a queue for, in this job.
        let mut reported: HashMap<&str, HashSet<u32>> = HashMap::new();
        for w in v
            .workers
            .iter()
            .filter(|w| self.on_page.contains(w.as_str()))
        {
            self.jobs_of
                .entry(w.as_str())
                .or_default()
                .push(v.job_id.clone());
        }
        for (w, queues) in v
            .queues
            .iter()
            .filter(|(w, _)| self.on_page.contains(w.as_str()))
        {
            let mine = self.domains_of.entry(w.as_str()).or_default();
            let seen = reported.entry(w.as_str()).or_default();
            for q in queues {
                seen.insert(q.domain);
                mine.push(WorkerDomain {
                    job_id: v.job_id.clone(),
                    domain: q.domain,
                    resident: q.resident,
                    rays_queued: q.rays_queued,
                    owned: v.owns(w, q.domain),
                    resident_bytes: q.resident_bytes,
                });
            }
        }
        // Owned domains the worker has not reported yet (a new table, or no report).
        for (d, owners) in v.owners.iter().enumerate() {
            for w in owners.iter().filter(|w| self.on_page.contains(w.as_str())) {
                let d = d as u32;
                if !reported.get(w.as_str()).is_some_and(|r| r.contains(&d)) {
                    self.domains_of
                        .entry(w.as_str())
                        .or_default()
                        .push(WorkerDomain {
                            job_id: v.job_id.clone(),
                            domain: d,
                            owned: true,
                            ..Default::default()
                        });
                }
            }
        }
    }

    /// Worker `w`'s status, with its jobs and domains (taken out of these lists).
    fn status(
        &mut self,
        w: &WorkerRecord,
        rates: &HashMap<String, f64>,
        silent_after: Duration,
        now: Instant,
    ) -> WorkerStatus {
        let since = now.saturating_duration_since(w.last_seen);
        let jobs = self.jobs_of.remove(w.id.as_str()).unwrap_or_default();
        let mut domains = self.domains_of.remove(w.id.as_str()).unwrap_or_default();
        domains.sort_by(|a, b| (&a.job_id, a.domain).cmp(&(&b.job_id, b.domain)));
        let state = if since > silent_after {
            "silent"
        } else if jobs.is_empty() {
            "idle"
        } else {
            "busy"
        };
        WorkerStatus {
            worker_id: w.id.clone(),
            endpoint: w.endpoint.clone(),
            hostname: w.hostname.clone(),
            name: w.name.clone(),
            state: state.into(),
            threads: w.threads,
            memory_used_bytes: w.memory_used_bytes,
            memory_budget_bytes: w.memory_budget_bytes,
            rays_queued: w.rays_queued,
            rays_per_second: rates.get(&w.id).copied().unwrap_or(0.0),
            jobs,
            domains,
            since_heartbeat: Some(prost_types::Duration {
                seconds: since.as_secs() as i64,
                nanos: since.subsec_nanos() as i32,
            }),
            cache_endpoint: w.cache_endpoint.clone().unwrap_or_default(),
        }
    }
}

/// A running job's table of domains: each domain's owners and the rays queued for it.
fn job_domains(v: &JobView) -> JobDomains {
    let queued = v.queued_by_domain();
    JobDomains {
        job_id: v.job_id.clone(),
        schedule: v.schedule.clone(),
        routing_version: v.version,
        attempt: v.attempt,
        domains: (0..v.domains)
            .map(|d| DomainOwners {
                domain: d,
                worker_ids: v.owners.get(d as usize).cloned().unwrap_or_default(),
                rays_queued: queued.get(d as usize).copied().unwrap_or(0),
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_proto::v1::DomainQueue;

    fn view(job: &str, traced: &[(&str, u64)]) -> JobView {
        JobView {
            job_id: job.into(),
            domains: 2,
            owners: vec![vec!["w1".into()], vec!["w2".into(), "w1".into()]],
            workers: vec!["w1".into(), "w2".into()],
            queues: [(
                "w2".to_string(),
                vec![DomainQueue {
                    domain: 1,
                    rays_queued: 7,
                    resident: true,
                    resident_bytes: 100,
                }],
            )]
            .into_iter()
            .collect(),
            traced: traced.iter().map(|(w, n)| (w.to_string(), *n)).collect(),
            ..Default::default()
        }
    }

    #[test]
    fn rates_are_differences_over_the_window_and_zero_at_first() {
        let r = RateWindow::default();
        let t0 = Instant::now();
        let first = r.rates(&[view("j", &[("w1", 100)])], t0);
        assert_eq!(first.get("w1").copied().unwrap_or(0.0), 0.0);
        // Too soon: the last rates again.
        let soon = r.rates(
            &[view("j", &[("w1", 150)])],
            t0 + Duration::from_millis(100),
        );
        assert_eq!(soon.get("w1").copied().unwrap_or(0.0), 0.0);
        let later = r.rates(&[view("j", &[("w1", 300)])], t0 + Duration::from_secs(2));
        assert_eq!(later["w1"], 100.0);
        // A job that ended no longer counts; a new one counts its whole count.
        let next = r.rates(&[view("k", &[("w1", 40)])], t0 + Duration::from_secs(4));
        assert_eq!(next["w1"], 20.0);
    }

    #[test]
    fn owners_queues_and_states_come_together() {
        let hb = HeartbeatConfig::default();
        let now = Instant::now();
        let rec = |id: &str, ago: Duration| WorkerRecord {
            id: id.into(),
            endpoint: format!("http://{id}"),
            cache_endpoint: None,
            threads: 2,
            memory_budget_bytes: 1000,
            hostname: "h".into(),
            name: format!("n-{id}"),
            last_seen: now - ago,
            memory_used_bytes: 10,
            rays_queued: 7,
            outbox: Default::default(),
            member_token: dray_net::Token::generate().expect("a token"),
        };
        let workers = [
            rec("w1", Duration::ZERO),
            rec("w2", Duration::ZERO),
            rec("w3", Duration::ZERO),
            rec("w4", Duration::from_secs(5)),
        ];
        let rates = HashMap::from([("w1".to_string(), 5.0)]);
        let out = list(&workers, vec![view("j", &[])], &rates, hb, now, true);
        let states: Vec<&str> = out.workers.iter().map(|w| w.state.as_str()).collect();
        assert_eq!(states, ["busy", "busy", "idle", "silent"]);
        assert_eq!(out.workers[0].rays_per_second, 5.0);
        let names: Vec<&str> = out.workers.iter().map(|w| w.name.as_str()).collect();
        assert_eq!(names, ["n-w1", "n-w2", "n-w3", "n-w4"], "WorkerStatus.name");
        let w1: Vec<(u32, bool)> = out.workers[0]
            .domains
            .iter()
            .map(|d| (d.domain, d.owned))
            .collect();
        assert_eq!(w1, [(0, true), (1, true)]);
        let w2 = &out.workers[1].domains;
        assert_eq!(w2.len(), 1);
        assert!(w2[0].resident && w2[0].owned && w2[0].rays_queued == 7);
        assert_eq!(out.jobs.len(), 1);
        assert_eq!(out.jobs[0].domains[1].worker_ids, ["w2", "w1"]);
        assert_eq!(out.jobs[0].domains[1].rays_queued, 7);
        assert!(
            list(&workers, vec![view("j", &[])], &rates, hb, now, false)
                .jobs
                .is_empty()
        );
    }

    #[test]
    fn page_sizes_are_defaulted_and_capped_and_tokens_are_worker_ids() {
        let first = PageRequest::parse(0, "").unwrap();
        assert_eq!((first.size, first.first()), (DEFAULT_PAGE_SIZE, true));
        assert_eq!(PageRequest::parse(5000, "").unwrap().size, MAX_PAGE_SIZE);
        assert_eq!(PageRequest::parse(7, "").unwrap().size, 7);
        let next = PageRequest::parse(7, "w12-0badf00d").unwrap();
        assert_eq!(next.after.as_deref(), Some("w12-0badf00d"));
        assert!(!next.first());
        let long = "w".repeat(10_000);
        for bad in [
            "7",
            " w1-0badf00d",
            "w1-0badf00",
            "w1-0badf00dd",
            "wx-0badf00d",
            &long,
        ] {
            let e = PageRequest::parse(0, bad).unwrap_err();
            assert!(e.starts_with("page_token: "), "{e}");
            assert!(e.len() < 300, "the token is echoed bounded: {e}");
        }
    }

    /// Many domains (issue 45, item 8: 65,536 domains took 7 s a listing, quadratic in
    /// them): every owned domain is listed once for its owner, reported or not, and
    /// each domain's queue sum is right.
    #[test]
    fn many_domains_are_listed_once_each_with_their_queues() {
        let domains = 1u32 << 14;
        let ids = ["w1", "w2", "w3", "w4"];
        let owners: Vec<Vec<String>> = (0..domains)
            .map(|d| vec![ids[d as usize % 4].to_string()])
            .collect();
        // Each worker reports a queue for every other domain it owns, and w1 one for
        // a domain it does not own.
        let mut queues: BTreeMap<String, Vec<DomainQueue>> = BTreeMap::new();
        for d in (0..domains).filter(|d| d % 8 < 4) {
            queues
                .entry(ids[d as usize % 4].to_string())
                .or_default()
                .push(DomainQueue {
                    domain: d,
                    rays_queued: u64::from(d),
                    resident: true,
                    resident_bytes: 1,
                });
        }
        queues.entry("w1".into()).or_default().push(DomainQueue {
            domain: 1,
            rays_queued: 5,
            resident: false,
            resident_bytes: 0,
        });
        let v = JobView {
            job_id: "j".into(),
            domains,
            owners,
            workers: ids.iter().map(|w| w.to_string()).collect(),
            queues,
            ..Default::default()
        };
        let workers: Vec<WorkerRecord> = ids
            .iter()
            .map(|id| WorkerRecord {
                id: id.to_string(),
                endpoint: String::new(),
                cache_endpoint: None,
                threads: 1,
                memory_budget_bytes: 0,
                hostname: String::new(),
                name: String::new(),
                last_seen: Instant::now(),
                memory_used_bytes: 0,
                rays_queued: 0,
                outbox: Default::default(),
                member_token: dray_net::Token::generate().expect("a token"),
            })
            .collect();
        let out = list(
            &workers,
            vec![v],
            &HashMap::new(),
            HeartbeatConfig::default(),
            Instant::now(),
            true,
        );
        for (k, w) in out.workers.iter().enumerate() {
            let owned: Vec<u32> = w
                .domains
                .iter()
                .filter(|d| d.owned)
                .map(|d| d.domain)
                .collect();
            let want: Vec<u32> = (0..domains).filter(|d| *d as usize % 4 == k).collect();
            assert_eq!(owned, want, "{}", w.worker_id);
        }
        let w1_foreign: Vec<&WorkerDomain> =
            out.workers[0].domains.iter().filter(|d| !d.owned).collect();
        assert_eq!(w1_foreign.len(), 1);
        assert_eq!(w1_foreign[0].domain, 1);
        let sums = &out.jobs[0].domains;
        assert_eq!(sums.len(), domains as usize);
        assert_eq!(sums[1].rays_queued, 1 + 5);
        assert_eq!(sums[5].rays_queued, 0);
        assert_eq!(sums[6].rays_queued, 0);
        assert_eq!(sums[8].rays_queued, 8);
    }
}
