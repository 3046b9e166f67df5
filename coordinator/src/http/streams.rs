//! Places for the dashboard's event streams: [`MAX_STREAMS`] open at once over every
//! client, and at most [`MAX_STREAMS_PER_CLIENT`] of them for one client
//! ([`super::client`]), so one client cannot take every place (issue 45, item 12: the
//! cap was global only, and one client's 64 streams locked every other page out).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use axum::http::StatusCode;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use super::client::Client;
use super::error::ApiError;

/// Event streams open at once, over every client.
pub const MAX_STREAMS: usize = 64;
/// Event streams one client may have open at once: a quarter of [`MAX_STREAMS`] (a
/// page uses one or two; a few tabs fit), as one source address may take a quarter of
/// the gRPC servers' connections.
pub const MAX_STREAMS_PER_CLIENT: usize = MAX_STREAMS / 4;

/// The places; see the module.
pub struct StreamSlots {
    total: usize,
    share: usize,
    global: Arc<Semaphore>,
    held: Arc<Mutex<HashMap<Client, usize>>>,
}

/// One open stream's place, given back when dropped (the stream ended).
pub struct StreamSlot {
    _global: OwnedSemaphorePermit,
    client: Client,
    held: Arc<Mutex<HashMap<Client, usize>>>,
}

impl StreamSlots {
    /// `total` places, `share` of them at most for one client (both at least 1).
    pub fn new(total: usize, share: usize) -> StreamSlots {
        let total = total.max(1);
        StreamSlots {
            total,
            share: share.clamp(1, total),
            global: Arc::new(Semaphore::new(total)),
            held: Arc::default(),
        }
    }

    /// A place for one more stream of `client`; 503 when it has its share open, or when
    /// every place is taken.
    pub fn take(&self, client: Client) -> Result<StreamSlot, ApiError> {
        let mut held = dray_sync::lock(&self.held);
        let mine = held.get(&client).copied().unwrap_or(0);
        if mine >= self.share {
            return Err(unavailable(format!(
                "this client has {mine} event streams open, its share of the dashboard's \
                 {}: close a tab, or try again later",
                self.total
            )));
        }
        let global = self.global.clone().try_acquire_owned().map_err(|_| {
            unavailable(format!(
                "{} event streams are open already; try again later",
                self.total
            ))
        })?;
        held.insert(client, mine + 1);
        Ok(StreamSlot {
            _global: global,
            client,
            held: self.held.clone(),
        })
    }
}

impl Drop for StreamSlot {
    fn drop(&mut self) {
        let mut held = dray_sync::lock(&self.held);
        if let Some(n) = held.get_mut(&self.client) {
            *n = n.saturating_sub(1);
            if *n == 0 {
                held.remove(&self.client);
            }
        }
    }
}

fn unavailable(message: String) -> ApiError {
    ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "UNAVAILABLE", message)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::http::auth::sessions::SessionId;

    #[test]
    fn one_client_takes_its_share_and_the_total_stays_bounded() {
        let slots = StreamSlots::new(5, 2);
        let (a, b, c) = (
            Client::Session(SessionId([1; 16])),
            Client::Session(SessionId([2; 16])),
            Client::Address([10, 0, 0, 1].into()),
        );
        let mut held = vec![slots.take(a).unwrap(), slots.take(a).unwrap()];
        let e = slots.take(a).err().expect("a's third stream");
        assert_eq!(e.status, StatusCode::SERVICE_UNAVAILABLE);
        assert!(e.message.contains("its share"), "{}", e.message);
        held.push(slots.take(b).unwrap());
        held.push(slots.take(b).unwrap());
        held.push(slots.take(c).unwrap());
        // Five open: c is within its share, but the total is reached.
        let e = slots.take(c).err().expect("beyond the total");
        assert!(e.message.contains("5 event streams"), "{}", e.message);
        // A stream of a's ends: a gets one again, and no more.
        held.remove(0);
        let again = slots.take(a).unwrap();
        assert!(slots.take(a).is_err());
        drop(again);
        drop(held);
        assert!(slots.held.lock().unwrap().is_empty());
    }
}
