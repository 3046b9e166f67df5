//! How a coordinator stops: one sequence in the library, which `dray coordinator` (on a
//! signal) and the embedded mode (after its render) both run through
//! [`crate::Coordinator::shutdown`], instead of each assembling its own (the CLI used to
//! seal the store twice, and the embedded mode stopped its server by a channel of its
//! own).
//!
//! The order matters, and is the one the CLI had:
//! 1. new jobs are refused (SubmitJob says UNAVAILABLE), since a job accepted now could
//!    not be kept;
//! 2. the job store is sealed, once: what the running jobs posted (committed tiles, new
//!    attempts) is written, then nothing more, so the jobs the shutdown itself stops are
//!    not recorded as ended and the next coordinator on the directory resumes them;
//! 3. scene loads and package cuts stop at their next look at their cancel flag;
//! 4. every server started by [`crate::serve_with`] for this coordinator begins its
//!    graceful stop (workers' assignment streams are ended), and the shutdown waits a
//!    bounded time for them to end.
//!
//! This file holds the state that sequence needs (whether it began, how many servers
//! still run); the sequence itself is [`crate::Coordinator::shutdown`].

use std::future::Future;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use tokio::sync::watch;

/// A coordinator's stop state, shared by its clones and the servers serving it.
#[derive(Debug)]
pub(crate) struct Shutdown {
    /// Set by the first [`Shutdown::begin`]: from then on no job is accepted.
    begun: AtomicBool,
    /// Turned true once the store is sealed: the servers stop.
    stop: watch::Sender<bool>,
    /// Servers serving this coordinator now.
    servers: watch::Sender<usize>,
}

impl Default for Shutdown {
    fn default() -> Shutdown {
        Shutdown {
            begun: AtomicBool::new(false),
            stop: watch::Sender::new(false),
            servers: watch::Sender::new(0),
        }
    }
}

/// Counts one running server while it lives (see [`Shutdown::serving`]).
pub(crate) struct Serving<'a>(&'a Shutdown);

impl Drop for Serving<'_> {
    fn drop(&mut self) {
        self.0.servers.send_modify(|n| *n = n.saturating_sub(1));
    }
}

impl Shutdown {
    /// Mark the shutdown begun; true for the one call that began it (the others have
    /// nothing to seal or signal).
    pub(crate) fn begin(&self) -> bool {
        !self.begun.swap(true, Ordering::SeqCst)
    }

    /// Whether the shutdown has begun (new jobs are refused).
    pub(crate) fn begun(&self) -> bool {
        self.begun.load(Ordering::SeqCst)
    }

    /// Tell the servers to stop (after the store is sealed).
    pub(crate) fn stop_servers(&self) {
        self.stop.send_replace(true);
    }

    /// Completes once the servers are told to stop.
    pub(crate) fn stopped(&self) -> impl Future<Output = ()> + Send + 'static {
        let mut rx = self.stop.subscribe();
        async move {
            // An error means the sender is gone, with the coordinator: stop as well.
            let _ = rx.wait_for(|s| *s).await;
        }
    }

    /// Count a server as running until the returned guard is dropped.
    pub(crate) fn serving(&self) -> Serving<'_> {
        self.servers.send_modify(|n| *n += 1);
        Serving(self)
    }

    /// Wait until no server runs, at most `grace`; false when some still ran then.
    pub(crate) async fn servers_ended(&self, grace: Duration) -> bool {
        let mut rx = self.servers.subscribe();
        tokio::time::timeout(grace, rx.wait_for(|n| *n == 0))
            .await
            .is_ok_and(|r| r.is_ok())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shutdown begins once, stops the servers only when told, and its wait ends
    /// when the last server has ended (or says some still run after the grace).
    #[tokio::test]
    async fn begins_once_and_waits_for_the_servers() {
        let s = std::sync::Arc::new(Shutdown::default());
        assert!(!s.begun());
        assert!(s.begin());
        assert!(!s.begin(), "a second call begins nothing");
        assert!(s.begun());
        let stopped = tokio::spawn(s.stopped());
        let server = s.serving();
        assert!(
            !s.servers_ended(Duration::from_millis(20)).await,
            "a server still runs"
        );
        assert!(!stopped.is_finished(), "the servers are not told yet");
        s.stop_servers();
        stopped.await.unwrap();
        drop(server);
        assert!(s.servers_ended(Duration::from_secs(10)).await);
    }
}
