//! Bytes this worker exchanged with other processes for one job, by kind (render.proto
//! `TrafficStats`): what the ray caches and hit maps cost on the wire, beside what they
//! save. Counted where a message is encoded for gRPC or decoded from it (the cache
//! link's gRPC loop, the rays handed to peer streams), never on the mailbox link to the
//! cache host in this process: those bytes never leave it.
//!
//! Sizes are the encoded protobuf messages (`prost::Message::encoded_len`), so they are
//! the bytes the messages take, not estimates; gRPC's 5-byte frame header and HTTP/2
//! and TLS framing are left out.

use dray_net::traffic::TrafficKind;
use dray_proto::v1::{RayTicket, TrafficStats};
use prost::Message;

/// The kind a message's bytes count as (one definition: [`dray_net::traffic`]).
pub(crate) use dray_net::traffic::TrafficKind as Kind;

/// Byte counters by kind, accumulated between reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Traffic {
    /// Bytes by kind, indexed by [`TrafficKind::index`].
    bytes: [u64; TrafficKind::COUNT],
    /// Cache-link messages counted, both directions.
    cache_messages: u64,
}

impl Traffic {
    /// Whether nothing was counted.
    pub fn is_empty(&self) -> bool {
        *self == Traffic::default()
    }

    /// The bytes counted as `kind`.
    pub fn get(&self, kind: TrafficKind) -> u64 {
        self.bytes[kind.index()]
    }

    /// Cache-link messages counted, both directions (ray batches are not).
    pub fn cache_messages(&self) -> u64 {
        self.cache_messages
    }

    /// One cache-link message of `bytes`, as `kind`.
    pub(crate) fn message(&mut self, kind: Kind, bytes: usize) {
        self.bytes[kind.index()] += bytes as u64;
        self.cache_messages += 1;
    }

    /// Ray records of `records` bytes (`dray_core::ray::encoded_len`) and their
    /// `tickets` handed to a peer stream.
    pub(crate) fn rays(&mut self, records: u64, tickets: &[RayTicket]) {
        self.bytes[Kind::Rays.index()] += ray_bytes(records, tickets);
    }

    /// Add `other` into this.
    pub fn add(&mut self, other: &Traffic) {
        for (a, b) in self.bytes.iter_mut().zip(other.bytes) {
            *a += b;
        }
        self.cache_messages += other.cache_messages;
    }

    /// The counters as a report carries them (`total` is the coordinator's to sum).
    pub fn to_proto(self) -> TrafficStats {
        let mut t = TrafficStats {
            cache_messages: self.cache_messages,
            ..TrafficStats::default()
        };
        for k in TrafficKind::ALL {
            *k.get_mut(&mut t) = self.get(k);
        }
        t
    }
}

/// Bytes of records taking `records` bytes with `tickets` in a ray batch: the records
/// (32 to 64 bytes each) and each ticket as the batch's repeated `RayTicket` field
/// encodes it (tag, length, message).
pub(crate) fn ray_bytes(records: u64, tickets: &[RayTicket]) -> u64 {
    let tickets: usize = tickets
        .iter()
        .map(|t| {
            let n = t.encoded_len();
            1 + prost::length_delimiter_len(n) + n
        })
        .sum();
    records + tickets as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kinds_add_up_and_count_messages() {
        let mut t = Traffic::default();
        assert!(t.is_empty());
        t.message(Kind::Lookups, 100);
        t.message(Kind::Answers, 10);
        t.message(Kind::TicketReturns, 7);
        t.message(Kind::EntryCopies, 5);
        t.message(Kind::MapOutcomes, 3);
        t.message(Kind::MapMerges, 4);
        t.message(Kind::Lookups, 1);
        let mut u = Traffic::default();
        u.add(&t);
        u.add(&t);
        assert_eq!(
            [
                Kind::Lookups,
                Kind::Answers,
                Kind::TicketReturns,
                Kind::EntryCopies,
                Kind::MapOutcomes,
            ]
            .map(|k| u.get(k)),
            [202, 20, 14, 10, 6]
        );
        assert_eq!(u.get(Kind::MapMerges), 8);
        assert_eq!(u.cache_messages(), 14);
        let p = u.to_proto();
        assert_eq!(
            (p.lookups, p.map_merges, p.total, p.cache_messages),
            (202, 8, 0, 14)
        );
    }

    #[test]
    fn rays_count_records_and_encoded_tickets() {
        assert_eq!(ray_bytes(3 * 41, &[]), 3 * 41);
        // record 1 (tag + 1-byte varint) and the largest ticket (tag + 10-byte varint):
        // 13 bytes, plus the field's tag and length.
        let t = RayTicket {
            record: 1,
            ticket: u64::MAX,
        };
        assert_eq!(ray_bytes(2 * 64, &[t]), 2 * 64 + 15);
        let mut tr = Traffic::default();
        tr.rays(2 * 50, &[t, t]);
        assert_eq!(tr.get(Kind::Rays), 2 * 50 + 30);
        assert_eq!(tr.cache_messages(), 0, "ray batches are not cache messages");
    }
}
