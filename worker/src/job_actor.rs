//! The actor of one job attempt on this worker: the one owner of what the job has to
//! report, of its routing table and of the tiles dealt to it.
//!
//! Tracing threads, the peer and cache links and the coordinator link post to it
//! ([`JobEvent`]) and never wait for it. It gathers results into one [`Report`] and
//! sends it ([`crate::reporter`] builds and sends the messages) every
//! [`QUEUE_REPORT_INTERVAL`], with the job's queues, and every [`REPORT_INTERVAL`] when
//! it is in a hurry (see [`JobActor::hurry`]). A report in
//! flight does not stop it: results go on gathering for the next one while it waits for
//! the coordinator (or for cache actors to take back their tickets first), so what it
//! holds stays merged per pixel however long the network takes. Routing tables are
//! applied here, deltas to the whole table the actor keeps. The actor ends when the job
//! is released; the worker holds every actor in one join set ([`crate::jobs::Jobs`]).

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;

use dray_proto::v1::RoutingTable;
use tokio::time::MissedTickBehavior;

use crate::domain_store::StoreCounters;
use crate::jobs::ahead::Ahead;
use crate::jobs::job::{Job, JobEvent, Mailbox, tile_ref};
use crate::jobs::report::Report;
use crate::links::Links;
use crate::member::Member;
use crate::reporter::{self, QUEUE_REPORT_INTERVAL, REPORT_INTERVAL, Sent};
use crate::routing::Routes;
use crate::workload::Workload;

/// A report on its way: first its tickets back to their cache actors, then its
/// messages to the coordinator.
enum Flight {
    /// The report's tickets went back; the report itself is next, with the domain
    /// store's counters taken when it started.
    Returned(Box<Report>, StoreCounters),
    /// The report went out, or could not.
    Sent(Sent),
}

type InFlight = Pin<Box<dyn Future<Output = Flight> + Send>>;

/// One job attempt's actor.
pub(crate) struct JobActor {
    /// Who reports (the job's reports and queues speak for this member).
    member: Arc<Member>,
    /// The queues and domains the job's rays and reports are about.
    workload: Arc<Workload>,
    /// Where the report's tickets go back to their cache hosts.
    links: Arc<Links>,
    job: Arc<Job>,
    mailbox: Mailbox,
    /// Results gathered since the last report left.
    report: Report,
    /// The whole routing table in force: the base the coordinator's deltas apply to.
    table: Option<RoutingTable>,
    /// The last report's sequence number (the coordinator applies each number once).
    sequence: u64,
    /// Most rays queued here for this job at once, so far.
    queue_peak: u64,
    /// Names already warned about (lost peers and cache hosts), so each is logged once.
    warned: std::collections::HashSet<String>,
    /// For a job tracing passes ahead: what it holds back of later passes.
    ahead: Option<Ahead>,
}

impl JobActor {
    pub(crate) fn new(
        member: Arc<Member>,
        workload: Arc<Workload>,
        links: Arc<Links>,
        job: Arc<Job>,
        mailbox: Mailbox,
        table: Option<RoutingTable>,
        ahead: Option<Ahead>,
    ) -> JobActor {
        if let Some(a) = &ahead {
            job.tiles().open_through(a.open_through());
        }
        JobActor {
            member,
            workload,
            links,
            job,
            mailbox,
            report: Report::default(),
            table,
            sequence: 0,
            queue_peak: 0,
            warned: Default::default(),
            ahead,
        }
    }

    /// [`JobActor::run`], and if it panics, the job fails at the coordinator with the
    /// panic's message: a bug met while reporting must not leave the job waiting for
    /// credit that never comes. The failure goes under the largest sequence number, which
    /// no report of the job uses.
    pub(crate) async fn supervised(self) {
        let (member, job) = (self.member.clone(), self.job.clone());
        if let Err(panic) = dray_net::contain::contained(self.run()).await {
            let message = format!(
                "worker {}: internal error (a panic in the job's actor, contained): {panic}",
                member.id()
            );
            tracing::error!(job = %job.key.id, "{message}");
            reporter::report_failure(&member, &job.key.id, job.key.attempt, u64::MAX, message)
                .await;
        }
    }

    /// Take events and report until the job is released (or the worker stops, which
    /// releases every job).
    async fn run(mut self) {
        let job = self.job.clone();
        let mut reports = tokio::time::interval(REPORT_INTERVAL);
        reports.set_missed_tick_behavior(MissedTickBehavior::Delay);
        let mut queues = tokio::time::interval(QUEUE_REPORT_INTERVAL);
        queues.set_missed_tick_behavior(MissedTickBehavior::Delay);
        let mut flight: Option<InFlight> = None;
        let mut queue_flight: Option<Pin<Box<dyn Future<Output = ()> + Send>>> = None;
        let released = job.released();
        tokio::pin!(released);
        loop {
            tokio::select! {
                _ = &mut released => return,
                event = self.mailbox.recv() => match event {
                    Some(event) => self.handle(event).await,
                    None => return,
                },
                landed = wait(&mut flight) => {
                    flight = match landed {
                        Flight::Returned(report, store) => {
                            // What the links posted before the tickets were taken back
                            // (the bytes of the returns) is in the mailbox: into the
                            // report, before it goes.
                            while let Ok(event) = self.mailbox.try_recv() {
                                self.handle(event).await;
                            }
                            Some(self.send(*report, store))
                        }
                        Flight::Sent(Sent::Delivered | Sent::GaveUp) => None,
                        Flight::Sent(Sent::JobOver) => {
                            tracing::info!(job = %job.key.id, attempt = job.key.attempt, "the coordinator says the job is over");
                            if let Some(j) = self.workload.jobs().release(&job.key.id, job.key.attempt) {
                                self.workload.forget(&j.key.id, j.key.attempt);
                            }
                            return;
                        }
                    };
                }
                _ = wait(&mut queue_flight) => queue_flight = None,
                _ = reports.tick(), if flight.is_none() => {
                    if self.hurry() {
                        flight = self.start(false);
                    }
                }
                _ = queues.tick() => {
                    if flight.is_none() {
                        flight = self.start(true);
                    }
                    if queue_flight.is_none() {
                        queue_flight = Some(Box::pin(reporter::report_queues(
                            self.member.clone(),
                            self.workload.clone(),
                            job.clone(),
                        )));
                    }
                }
            }
        }
    }

    async fn handle(&mut self, event: JobEvent) {
        match event {
            JobEvent::Results(mut r) => {
                for name in r.unreachable.iter().chain(&r.lost_cache_hosts) {
                    if self.warned.insert(name.clone()) {
                        tracing::warn!(job = %self.job.key.id, %name, "unreachable: rays for it are dropped or go past its walls");
                    }
                }
                if let Some(a) = self.ahead.as_mut() {
                    a.hold(&mut r);
                }
                self.report.absorb(*r);
            }
            JobEvent::Tiles(t) => self.deal(t),
            JobEvent::Routing(t) => self.route(t).await,
        }
    }

    /// Tiles dealt by the coordinator, queued for the tracing threads. For a job tracing
    /// passes ahead, each tile in its pass and every later one (the coordinator does not
    /// deal it again in this attempt), and the pass the job is in moves on.
    fn deal(&mut self, t: dray_proto::v1::TileAssignment) {
        let job = self.job.clone();
        let tags = job.tracer.pass_tags();
        let mut tiles = Vec::with_capacity(t.tiles.len());
        let mut pass = t.pass;
        for tile in &t.tiles {
            if tile.attempt != job.key.attempt {
                tracing::warn!(job = %t.job_id, attempt = tile.attempt, "tile of another attempt ignored");
                continue;
            }
            let r = tile_ref(tile);
            match tags {
                Some(tags) if self.ahead.is_some() && !r.coarse => {
                    let first = tags.pass_of(r.first_sample);
                    pass = pass.max(first);
                    tiles.extend(
                        (first..tags.count()).filter_map(|p| Some((p, r.in_pass(tags.range(p)?)))),
                    );
                }
                _ => tiles.push((0, r)),
            }
        }
        let limit = job.tracer.tile_count()
            * tags
                .filter(|_| self.ahead.is_some())
                .map_or(1, |t| u64::from(t.count()));
        if let Some(a) = self.ahead.as_mut()
            && a.enter(pass, &mut self.report)
        {
            tracing::debug!(job = %t.job_id, pass, still_held = a.held_sums(), "the job is in a later pass: its held results go out");
            job.tiles().open_through(a.open_through());
        }
        if let Err(e) = job.tiles().deal(tiles, limit) {
            job.fail(format!(
                "worker {}: more tiles dealt than the job's {limit} ({} queued, {} more dealt; \
                 refused)",
                self.member.id(),
                e.queued,
                e.dealt
            ));
            return;
        }
        self.workload.notify();
    }

    /// A new routing table: swap it in, and let go of domains this worker no longer
    /// owns (their queued rays are forwarded by the tracing threads). A delta (a round's
    /// moved domains) is applied to the whole table kept here; when it is not the
    /// delta's base, the whole table is asked of the coordinator.
    async fn route(&mut self, table: RoutingTable) {
        let job = self.job.clone();
        let me = self.member.id();
        if table.attempt != job.key.attempt {
            return;
        }
        let domains = job.tracer.domain_count();
        let table = if table.base_version == 0 {
            table
        } else {
            if let Err(e) = crate::setup_bounds::check_routing(&table, domains) {
                job.fail(format!("worker {me}: {e}"));
                return;
            }
            let patched = self
                .table
                .as_ref()
                .and_then(|kept| crate::routing::patch(kept, &table));
            match patched {
                Some(t) => t,
                None => {
                    match self.member.whole_table(&table.job_id).await {
                        Some(t) if t.attempt == job.key.attempt && t.base_version == 0 => t,
                        // The job ended or moved to another attempt: its release is on the way.
                        _ => return,
                    }
                }
            }
        };
        if let Err(e) = crate::setup_bounds::check_routing(&table, domains) {
            job.fail(format!("worker {me}: {e}"));
            return;
        }
        let routes = match Routes::new(&table, &me, domains) {
            Ok(r) => r,
            Err(e) => {
                job.fail(format!("worker {me}: {e}"));
                return;
            }
        };
        let version = routes.version;
        let Some(old) = job.publish_routes(routes) else {
            return;
        };
        self.table = Some(table);
        let new = job.routes();
        let mut dropped = Vec::new();
        for d in old.owned() {
            if !new.owns(d) {
                self.workload.store().evict(&job.key, d);
                dropped.push(d);
            }
        }
        tracing::debug!(job = %job.key.id, version, owned = ?new.owned(), ?dropped, "routing table changed");
        self.workload.notify();
    }

    /// Whether the report should go on the short tick ([`REPORT_INTERVAL`]) rather than
    /// wait for the queue report's ([`QUEUE_REPORT_INTERVAL`]): when this worker has no
    /// camera ray left to make (the end of its share of a pass, or of the job: the
    /// coordinator waits for the last credit, so it goes at once), or when the report
    /// holds tickets (the cache actors learn their rays' radiance from them).
    ///
    /// While camera rays remain, nothing waits on the credit, and a report every 10 ms
    /// cost the worker's process about 4% of a core in gRPC calls (deep case, one
    /// tracing thread: h2, loopback TCP and wake-ups for 100 reports a second), taken
    /// from tracing where the threads share cores.
    fn hurry(&self) -> bool {
        self.job.tiles().is_empty() || !self.report.tickets.is_empty()
    }

    /// Start sending what was gathered (with `force`, even if that is only idle time),
    /// if there is anything to send. What is owed to ray-cache tickets goes to their
    /// cache actors first, and the report waits until they have applied it: a tile
    /// whose credit is complete at the coordinator has then closed every ticket of its
    /// rays.
    fn start(&mut self, force: bool) -> Option<InFlight> {
        let queued: u64 = self
            .workload
            .queues()
            .job_lengths(&self.job.key.id, self.job.key.attempt)
            .iter()
            .map(|(_, n)| *n as u64)
            .sum();
        self.queue_peak = self.queue_peak.max(queued + self.job.outgoing() as u64);
        let store = self.workload.store().take_counters(&self.job.key);
        let r = &self.report;
        if r.is_empty()
            && store.loads == 0
            && store.warm == 0
            && store.evictions == 0
            && !(force && r.idle_seconds > 0.0)
        {
            return None;
        }
        let mut report = std::mem::take(&mut self.report);
        if report.tickets.is_empty() {
            return Some(self.send(report, store));
        }
        let returns = report.tickets.drain();
        let (links, job) = (self.links.clone(), self.job.clone());
        Some(Box::pin(async move {
            links.return_tickets(&job, returns).await;
            Flight::Returned(Box::new(report), store)
        }))
    }

    /// Send `report` (its tickets returned) with the store's counters `store`,
    /// numbered from the last report's sequence.
    fn send(&mut self, mut report: Report, store: StoreCounters) -> InFlight {
        // Bytes and lost hosts noted while the tickets went back ride along.
        report.take_link_counters(&mut self.report);
        let requests = reporter::requests(
            &self.member,
            &self.job,
            report,
            store,
            self.queue_peak,
            &mut self.sequence,
        );
        let (member, job) = (self.member.clone(), self.job.clone());
        Box::pin(async move { Flight::Sent(reporter::send_all(&member, &job, requests).await) })
    }
}

/// The output of the future in `slot`, once it is ready; never, when there is none.
async fn wait<T>(slot: &mut Option<Pin<Box<dyn Future<Output = T> + Send>>>) -> T {
    match slot.as_mut() {
        Some(f) => f.await,
        None => std::future::pending().await,
    }
}
