//! The dashboard's live sessions: which logins have not been logged out.
//!
//! A session cookie is signed (so a forged one is refused without a look-up) but a
//! signature alone cannot be taken back: a cookie copied before logout would work
//! until it expired (issue 45, item 12). So each login gets a random id kept here
//! until it logs out or expires, and a cookie whose id is not here is refused.
//!
//! Only holders of the API token can log in, but the table is bounded all the same
//! ([`MAX_SESSIONS`]): a login beyond it ends the session that expires first (the
//! oldest login), which then has to log in again.

use std::collections::HashMap;
use std::sync::Mutex;

/// Sessions live at once.
pub const MAX_SESSIONS: usize = 1024;

/// A session's id: 128 random bits, as the cookie carries it (hex).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct SessionId(pub [u8; 16]);

impl SessionId {
    /// A new random id.
    pub fn generate() -> Result<SessionId, ring::error::Unspecified> {
        let mut id = [0u8; 16];
        ring::rand::SecureRandom::fill(&ring::rand::SystemRandom::new(), &mut id)?;
        Ok(SessionId(id))
    }

    /// The id as the cookie carries it: 32 hex digits.
    pub fn hex(&self) -> String {
        self.0.iter().map(|b| format!("{b:02x}")).collect()
    }

    /// The id from its 32 hex digits.
    pub fn parse(s: &str) -> Option<SessionId> {
        if s.len() != 32 {
            return None;
        }
        let mut id = [0u8; 16];
        for (k, b) in id.iter_mut().enumerate() {
            *b = u8::from_str_radix(s.get(2 * k..2 * k + 2)?, 16).ok()?;
        }
        Some(SessionId(id))
    }
}

/// The live sessions and when each expires (Unix seconds).
#[derive(Default)]
pub struct Sessions {
    live: Mutex<HashMap<SessionId, u64>>,
}

impl Sessions {
    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<SessionId, u64>> {
        dray_sync::lock(&self.live)
    }

    /// Keep `id` live until `expires`; at `now` the expired ones are forgotten, and the
    /// one that expires first too when [`MAX_SESSIONS`] are live.
    pub fn start(&self, id: SessionId, expires: u64, now: u64) {
        let mut live = self.lock();
        live.retain(|_, e| *e > now);
        while live.len() >= MAX_SESSIONS {
            let Some(first) = live.iter().min_by_key(|(_, e)| **e).map(|(id, _)| *id) else {
                break;
            };
            live.remove(&first);
        }
        live.insert(id, expires);
    }

    /// Whether `id` is live with expiry `expires` at `now`.
    pub fn live(&self, id: &SessionId, expires: u64, now: u64) -> bool {
        expires > now && self.lock().get(id) == Some(&expires)
    }

    /// Whether `id` is still live at `now` (logged out and expired sessions are not).
    pub fn contains(&self, id: &SessionId, now: u64) -> bool {
        self.lock().get(id).is_some_and(|e| *e > now)
    }

    /// End `id`: its cookie, and every copy of it, is refused from now on.
    pub fn end(&self, id: &SessionId) {
        self.lock().remove(id);
    }

    /// Sessions live now (tests).
    pub fn len(&self) -> usize {
        self.lock().len()
    }

    /// Whether none is live.
    pub fn is_empty(&self) -> bool {
        self.lock().is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_round_trip_and_bad_ones_are_refused() {
        let id = SessionId::generate().unwrap();
        assert_eq!(SessionId::parse(&id.hex()), Some(id));
        for bad in ["", "00", &"z".repeat(32), &"0".repeat(31), &"0".repeat(33)] {
            assert_eq!(SessionId::parse(bad), None, "{bad}");
        }
    }

    #[test]
    fn ended_expired_and_evicted_sessions_are_not_live() {
        let s = Sessions::default();
        let a = SessionId([1; 16]);
        s.start(a, 100, 0);
        assert!(s.live(&a, 100, 50));
        assert!(!s.live(&a, 101, 50), "another expiry than the one started");
        assert!(!s.live(&a, 100, 100), "expired");
        s.end(&a);
        assert!(!s.live(&a, 100, 50), "logged out");
        // Full: the session that expires first makes room.
        for k in 0..MAX_SESSIONS {
            let mut id = [0u8; 16];
            id[..8].copy_from_slice(&(k as u64).to_le_bytes());
            s.start(SessionId(id), 1000 + k as u64, 0);
        }
        assert_eq!(s.len(), MAX_SESSIONS);
        let newest = SessionId([9; 16]);
        s.start(newest, 5000, 0);
        assert_eq!(s.len(), MAX_SESSIONS);
        assert!(s.live(&newest, 5000, 0));
        assert!(
            !s.contains(&SessionId([0; 16]), 0),
            "the first to expire was ended"
        );
        assert!(s.contains(&newest, 0));
        // Expired ones are forgotten at the next login.
        s.start(SessionId([8; 16]), 9000, 4000);
        assert_eq!(s.len(), 2);
    }
}
