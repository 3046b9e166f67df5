//! The deal queue: jobs waiting for a render slot, dealt by priority (issue 42). A job
//! with a higher `JobSpec.priority` is dealt before every waiting job with a lower one;
//! among equal priorities, the one that came to the queue first. A PAUSED job is not
//! dealt (the jobs behind it are) until it is resumed; a job that ended while it waited
//! (cancelled) leaves the queue. A job holding a slot keeps it until it ends: nothing is
//! pre-empted.
//!
//! Two queues use it. The coordinator's own renderer (no worker registered) has one slot
//! (`LocalRenderer::start`, `crate::local_render`), replacing the first-come semaphore it had. Jobs on workers have
//! `--max-running-jobs` slots when that is given (`Cluster::queue`, taken in
//! `Coordinator::launch`); without it they start at once and never wait here, except a
//! job a restarted coordinator took back PAUSED: it waits for ResumeJob
//! ([`DealQueue::resumed`]).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use dray_proto::v1::JobState;
use tokio::sync::Notify;

use crate::job::JobRecord;
use crate::jobs::JobEntry;

/// Jobs waiting for one of `slots` slots.
pub struct DealQueue {
    /// "process" or "cluster": which slots, for logs and the wait histogram.
    name: &'static str,
    state: Mutex<QueueState>,
    /// Woken on every change a waiter may be waiting for: a slot freed, a job paused,
    /// resumed or added.
    changed: Notify,
    next_seq: AtomicU64,
}

struct QueueState {
    free: usize,
    waiting: Vec<Waiter>,
}

struct Waiter {
    job: Arc<JobEntry>,
    seq: u64,
}

/// A slot, held until dropped.
pub struct Slot {
    queue: Arc<DealQueue>,
}

impl Drop for Slot {
    fn drop(&mut self) {
        self.queue.lock().free += 1;
        self.queue.changed.notify_waiters();
    }
}

impl DealQueue {
    /// A queue named `name` ("process", "cluster") with `slots` slots.
    pub fn new(name: &'static str, slots: usize) -> DealQueue {
        DealQueue {
            name,
            state: Mutex::new(QueueState {
                free: slots,
                waiting: Vec::new(),
            }),
            changed: Notify::new(),
            next_seq: AtomicU64::new(0),
        }
    }

    fn lock(&self) -> MutexGuard<'_, QueueState> {
        dray_sync::lock(&self.state)
    }

    /// Whether job `id` is waiting for a slot (so it may be paused).
    pub fn is_waiting(&self, id: &str) -> bool {
        self.lock().waiting.iter().any(|w| w.job.id == id)
    }

    /// Ids of the waiting jobs in the order they would be dealt (paused ones last).
    pub fn order(&self) -> Vec<String> {
        let mut g = self.lock();
        sort(&mut g.waiting);
        g.waiting.iter().map(|w| w.job.id.clone()).collect()
    }

    /// Pause (`paused`) or resume `job` if it waits here: under the queue's lock, so a
    /// job is never paused just as it is dealt. The job's state when it cannot be.
    pub fn hold(&self, job: &JobRecord, paused: bool) -> Result<(), JobState> {
        let g = self.lock();
        if !g.waiting.iter().any(|w| w.job.id == job.id) {
            return Err(job.state());
        }
        let held = job.hold(paused);
        drop(g);
        self.changed.notify_waiters();
        held
    }

    /// Tell the waiters something changed (a job paused or resumed).
    pub fn poke(&self) {
        self.changed.notify_waiters();
    }

    /// Wait while `job` is PAUSED outside any queue (taken back PAUSED by a restarted
    /// coordinator whose jobs on workers start at once, with no slot to wait for):
    /// woken by this queue's pokes, which ResumeJob gives every queue. True once it is
    /// resumed; false when it ends (is cancelled) first.
    pub async fn resumed(&self, job: &JobEntry) -> bool {
        loop {
            let notified = self.changed.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            if job.is_terminal() {
                return false;
            }
            if job.state() != JobState::Paused {
                return true;
            }
            tokio::select! {
                _ = notified => {}
                _ = job.wait_ended() => {}
            }
        }
    }

    /// Put `job` in the queue now (so it can be paused at once); [`Waiting::turn`]
    /// waits for its slot.
    pub fn join(self: &Arc<Self>, job: &Arc<JobEntry>) -> Waiting {
        let seq = self.next_seq.fetch_add(1, Ordering::Relaxed);
        self.lock().waiting.push(Waiter {
            job: job.clone(),
            seq,
        });
        self.changed.notify_waiters();
        Waiting {
            queue: self.clone(),
            job: job.clone(),
            seq,
            since: std::time::Instant::now(),
        }
    }
}

/// A job in the queue ([`DealQueue::join`]).
pub struct Waiting {
    queue: Arc<DealQueue>,
    job: Arc<JobEntry>,
    seq: u64,
    /// When it joined: the wait is logged and measured when it is dealt.
    since: std::time::Instant,
}

impl Waiting {
    /// Wait until the job is the first dealable one and a slot is free, and take the
    /// slot. None when the job ends (is cancelled) while it waits.
    pub async fn turn(self) -> Option<Slot> {
        let (queue, job, seq) = (&self.queue, &self.job, self.seq);
        loop {
            let notified = queue.changed.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            {
                let mut g = queue.lock();
                g.waiting.retain(|w| !w.job.is_terminal());
                if job.is_terminal() {
                    drop(g);
                    queue.changed.notify_waiters();
                    return None;
                }
                sort(&mut g.waiting);
                let first = g.waiting.iter().find(|w| dealable(&w.job));
                if g.free > 0 && first.is_some_and(|w| w.seq == seq) {
                    g.free -= 1;
                    g.waiting.retain(|w| w.seq != seq);
                    let behind = g.waiting.len();
                    drop(g);
                    let waited = self.since.elapsed();
                    tracing::info!(
                        job = %job.id,
                        queue = queue.name,
                        priority = job.spec.priority,
                        waited_ms = waited.as_millis() as u64,
                        behind,
                        "dealt a {} slot",
                        queue.name
                    );
                    crate::metrics::otel::job_dealt(queue.name, waited);
                    // The next in line may have a slot too.
                    queue.changed.notify_waiters();
                    return Some(Slot {
                        queue: queue.clone(),
                    });
                }
            }
            tokio::select! {
                _ = notified => {}
                _ = job.wait_ended() => {}
            }
        }
    }
}

fn dealable(job: &JobEntry) -> bool {
    job.state() != JobState::Paused && !job.is_terminal()
}

/// Dealing order: dealable first, then higher priority, then first come.
fn sort(waiting: &mut [Waiter]) {
    waiting.sort_by_key(|w| {
        (
            !dealable(&w.job),
            std::cmp::Reverse(w.job.spec.priority),
            w.seq,
        )
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::jobs::JobTable;
    use dray_proto::v1::JobSpec;

    fn spec(priority: i32) -> JobSpec {
        JobSpec {
            scene: "cornell".into(),
            width: 4,
            height: 4,
            spp: 1,
            priority,
            ..Default::default()
        }
    }

    fn ids(jobs: &[&Arc<JobRecord>]) -> Vec<String> {
        jobs.iter().map(|j| j.id.clone()).collect()
    }

    /// A queue of two slots (the cluster's under `--max-running-jobs 2`): the highest
    /// priority and then the first come take them, a paused job is passed over, and a
    /// slot given back goes to the next dealable job.
    #[tokio::test]
    async fn slots_go_by_priority_skip_paused_jobs_and_come_back() {
        let table = JobTable::new();
        let q = Arc::new(DealQueue::new("cluster", 2));
        let [a, b, c, d] = [0, 0, 0, 5].map(|p| table.insert(spec(p)));
        let [wa, wb, wc, wd] = [&a, &b, &c, &d].map(|j| q.join(j.entry()));
        assert_eq!(q.order(), ids(&[&d, &a, &b, &c]));
        let sd = wd.turn().await.expect("the priority-5 job is dealt first");
        let sa = wa.turn().await.expect("then the first come");
        assert_eq!(q.order(), ids(&[&b, &c]));
        q.hold(&b, true).expect("b waits: it can be paused");
        assert_eq!(q.order(), ids(&[&c, &b]), "a paused job is dealt last");
        let c_turn = tokio::spawn(wc.turn());
        drop(sa);
        let sc = c_turn
            .await
            .expect("task")
            .expect("the slot given back goes to c, not to the paused b");
        assert!(q.is_waiting(&b.id));
        q.hold(&b, false).expect("resume b");
        let b_turn = tokio::spawn(wb.turn());
        drop(sd);
        let sb = b_turn.await.expect("task").expect("b once resumed");
        assert!(q.order().is_empty());
        drop((sb, sc));
        // A job cancelled while it waits leaves the queue without a slot.
        let e = table.insert(spec(0));
        let f = table.insert(spec(0));
        let (s1, s2) = (
            q.join(e.entry()).turn().await.expect("slot 1"),
            q.join(f.entry()).turn().await.expect("slot 2"),
        );
        let g = table.insert(spec(9));
        let wg = q.join(g.entry());
        g.cancel();
        assert!(wg.turn().await.is_none());
        assert!(!q.is_waiting(&g.id));
        drop((s1, s2));
    }

    /// A job held PAUSED outside any slot queue waits until it is resumed, and a
    /// cancelled one stops waiting.
    #[tokio::test]
    async fn a_paused_job_waits_for_its_resume_or_its_end() {
        let table = JobTable::new();
        let q = Arc::new(DealQueue::new("process", 1));
        let a = table.insert(spec(0));
        a.set_state(JobState::Paused);
        let waiting = tokio::spawn({
            let (q, a) = (q.clone(), a.clone());
            async move { q.resumed(&a).await }
        });
        tokio::task::yield_now().await;
        assert!(!waiting.is_finished(), "a paused job does not go on");
        a.hold(false).expect("resume");
        q.poke();
        assert!(waiting.await.expect("task"), "resumed");
        let b = table.insert(spec(0));
        b.set_state(JobState::Paused);
        let waiting = tokio::spawn({
            let (q, b) = (q.clone(), b.clone());
            async move { q.resumed(&b).await }
        });
        b.cancel();
        assert!(!waiting.await.expect("task"), "cancelled while paused");
    }
}
