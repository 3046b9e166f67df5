//! The scheduler's event loop, after Apache Ballista's `scheduler_server/event.rs`: RPC
//! handlers and the heartbeat reaper post typed [`SchedulerEvent`]s and return at once;
//! one task takes them in order and hands each to an [`EventAction`], which owns the
//! decisions. Besides events, the action may ask to be woken at an instant (a round
//! that is due later), so pacing needs no polling and no detached timers.
//!
//! Posting never blocks and never fails loudly: the channel is unbounded (events are
//! small and coalesce in the action: many queue reports make at most one round per
//! interval), and an event posted while no loop runs waits for the next loop.

use std::future::Future;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use tokio::sync::mpsc::{UnboundedReceiver, UnboundedSender, unbounded_channel};

use crate::membership::{LostWorker, WorkerRecord};

/// What the scheduler reacts to.
#[derive(Clone, Debug)]
pub enum SchedulerEvent {
    /// A worker stored a queue report for `job_id` (the report itself is already in the
    /// ledger): a round may be due.
    QueueReport {
        /// The job.
        job_id: String,
    },
    /// A worker registered: a running dynamic job takes it on.
    WorkerJoined(WorkerRecord),
    /// A worker stopped heartbeating and was dropped: its jobs start a new attempt on the
    /// survivors, or fail when none is left.
    WorkerLost(LostWorker),
    /// A job completed, failed or was cancelled: forget its pending round.
    JobEnded {
        /// The job.
        job_id: String,
    },
}

/// The handler an [`EventLoop`] drives. Called from one task only, so it may keep plain
/// mutable state.
pub trait EventAction<E>: Send + 'static {
    /// Before the first event.
    fn on_start(&mut self) {}
    /// After the last event, when the channel closed (not when the loop's future is
    /// dropped: an aborted loop just stops).
    fn on_stop(&mut self) {}
    /// One event, received at `now`.
    fn on_receive(&mut self, event: E, now: Instant);
    /// When [`EventAction::on_timer`] should next run, if at all.
    fn next_timer(&self) -> Option<Instant> {
        None
    }
    /// The instant [`EventAction::next_timer`] named has come.
    fn on_timer(&mut self, _now: Instant) {}
}

/// A channel of events and the loop that drains it into an [`EventAction`].
pub struct EventLoop<E> {
    name: &'static str,
    tx: UnboundedSender<E>,
    /// The receiving end, while no loop holds it; a loop puts it back when it ends, so a
    /// server that is stopped and served again keeps its events.
    rx: Arc<Mutex<Option<UnboundedReceiver<E>>>>,
}

/// Returns the receiver to its slot when a running loop ends (returns, or its future is
/// dropped by an abort).
struct Lease<E> {
    rx: Option<UnboundedReceiver<E>>,
    slot: Arc<Mutex<Option<UnboundedReceiver<E>>>>,
}

impl<E> Drop for Lease<E> {
    fn drop(&mut self) {
        if let Some(rx) = self.rx.take() {
            *self.slot.lock().unwrap_or_else(|p| p.into_inner()) = Some(rx);
        }
    }
}

impl<E: Send + 'static> EventLoop<E> {
    /// A loop named `name` (for logs), not yet running.
    pub fn new(name: &'static str) -> EventLoop<E> {
        let (tx, rx) = unbounded_channel();
        EventLoop {
            name,
            tx,
            rx: Arc::new(Mutex::new(Some(rx))),
        }
    }

    /// Queue an event for the loop.
    pub fn post(&self, event: E) {
        // Fails only when the receiver is gone, which this struct prevents while alive.
        let _ = self.tx.send(event);
    }

    /// Run `action` over the events until the future is dropped. Only one loop runs at a
    /// time: a second call while one holds the channel returns at once (with a warning).
    pub fn run<A: EventAction<E>>(
        &self,
        mut action: A,
    ) -> impl Future<Output = ()> + Send + use<E, A> {
        // The lease is made here, not in the future, so that a future dropped before
        // it is first polled still gives the receiver back.
        let lease = self
            .rx
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take()
            .map(|rx| Lease {
                rx: Some(rx),
                slot: self.rx.clone(),
            });
        let name = self.name;
        async move {
            let Some(mut lease) = lease else {
                tracing::warn!(event_loop = name, "already running; not started twice");
                return;
            };
            let Some(rx) = lease.rx.as_mut() else { return };
            action.on_start();
            loop {
                let timer = action.next_timer();
                let sleep = async {
                    match timer {
                        Some(t) => tokio::time::sleep_until(t.into()).await,
                        None => std::future::pending().await,
                    }
                };
                tokio::select! {
                    e = rx.recv() => match e {
                        Some(e) => action.on_receive(e, Instant::now()),
                        None => break,
                    },
                    () = sleep => action.on_timer(Instant::now()),
                }
            }
            action.on_stop();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    struct Recorder {
        seen: tokio::sync::mpsc::UnboundedSender<String>,
        wake: Option<Instant>,
    }

    impl EventAction<u32> for Recorder {
        fn on_receive(&mut self, e: u32, now: Instant) {
            let _ = self.seen.send(format!("event {e}"));
            if e == 2 {
                self.wake = Some(now + Duration::from_millis(20));
            }
        }
        fn next_timer(&self) -> Option<Instant> {
            self.wake
        }
        fn on_timer(&mut self, _now: Instant) {
            self.wake = None;
            let _ = self.seen.send("timer".into());
        }
    }

    async fn next(seen: &mut tokio::sync::mpsc::UnboundedReceiver<String>) -> String {
        tokio::time::timeout(Duration::from_secs(10), seen.recv())
            .await
            .expect("nothing arrived")
            .expect("channel closed")
    }

    #[tokio::test]
    async fn events_in_order_then_the_timer_and_the_receiver_survives_an_abort() {
        let lp = Arc::new(EventLoop::<u32>::new("test"));
        let (tx, mut seen) = unbounded_channel();
        lp.post(1);
        let task = tokio::spawn(lp.run(Recorder {
            seen: tx.clone(),
            wake: None,
        }));
        lp.post(2);
        assert_eq!(next(&mut seen).await, "event 1");
        assert_eq!(next(&mut seen).await, "event 2");
        assert_eq!(next(&mut seen).await, "timer");
        task.abort();
        let _ = task.await;
        // A new loop takes over the same channel.
        lp.post(3);
        let task = tokio::spawn(lp.run(Recorder {
            seen: tx,
            wake: None,
        }));
        assert_eq!(next(&mut seen).await, "event 3");
        task.abort();
    }
}
