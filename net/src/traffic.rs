//! The kinds of bytes between processes a job's traffic counts (render.proto
//! `TrafficStats`, docs/caches.md "Statistics"), defined once: the workers count by
//! them, the coordinator sums them, and `dray`'s `--stats` JSON and `dray sweep`'s CSV
//! columns are named after them. Adding a kind here (and its field in the proto) is the
//! whole change; nothing else lists them.

use dray_proto::v1::TrafficStats;

/// One kind of traffic, a `u64` field of `TrafficStats`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum TrafficKind {
    /// Ray batches between workers (records and their tickets).
    Rays,
    /// Cache lookups sent.
    Lookups,
    /// Their answers received.
    Answers,
    /// Ticket returns sent and acknowledged.
    TicketReturns,
    /// Sender placement's replica copies, both directions.
    EntryCopies,
    /// Hit-map outcomes sent and acknowledged.
    MapOutcomes,
    /// Sender placement's hit-map merges sent and acknowledged.
    MapMerges,
}

impl TrafficKind {
    /// How many kinds there are.
    pub const COUNT: usize = 7;

    /// Every kind, in the proto's field order (the order reports and columns list them).
    pub const ALL: [TrafficKind; TrafficKind::COUNT] = [
        TrafficKind::Rays,
        TrafficKind::Lookups,
        TrafficKind::Answers,
        TrafficKind::TicketReturns,
        TrafficKind::EntryCopies,
        TrafficKind::MapOutcomes,
        TrafficKind::MapMerges,
    ];

    /// What ray caches cost on the wire, against the bytes they save.
    pub const CACHE_COSTS: [TrafficKind; 4] = [
        TrafficKind::Lookups,
        TrafficKind::Answers,
        TrafficKind::TicketReturns,
        TrafficKind::EntryCopies,
    ];

    /// What hit maps cost on the wire, against the bytes they save.
    pub const PHM_COSTS: [TrafficKind; 4] = [
        TrafficKind::Lookups,
        TrafficKind::Answers,
        TrafficKind::MapOutcomes,
        TrafficKind::MapMerges,
    ];

    /// The kind's name: its `TrafficStats` field, and its key in `--stats`' `traffic`.
    pub const fn name(self) -> &'static str {
        match self {
            TrafficKind::Rays => "rays",
            TrafficKind::Lookups => "lookups",
            TrafficKind::Answers => "answers",
            TrafficKind::TicketReturns => "ticket_returns",
            TrafficKind::EntryCopies => "entry_copies",
            TrafficKind::MapOutcomes => "map_outcomes",
            TrafficKind::MapMerges => "map_merges",
        }
    }

    /// Its index in [`TrafficKind::ALL`].
    pub const fn index(self) -> usize {
        self as usize
    }

    /// The kind's bytes in `t`.
    pub fn get(self, t: &TrafficStats) -> u64 {
        match self {
            TrafficKind::Rays => t.rays,
            TrafficKind::Lookups => t.lookups,
            TrafficKind::Answers => t.answers,
            TrafficKind::TicketReturns => t.ticket_returns,
            TrafficKind::EntryCopies => t.entry_copies,
            TrafficKind::MapOutcomes => t.map_outcomes,
            TrafficKind::MapMerges => t.map_merges,
        }
    }

    /// The kind's field in `t`.
    pub fn get_mut(self, t: &mut TrafficStats) -> &mut u64 {
        match self {
            TrafficKind::Rays => &mut t.rays,
            TrafficKind::Lookups => &mut t.lookups,
            TrafficKind::Answers => &mut t.answers,
            TrafficKind::TicketReturns => &mut t.ticket_returns,
            TrafficKind::EntryCopies => &mut t.entry_copies,
            TrafficKind::MapOutcomes => &mut t.map_outcomes,
            TrafficKind::MapMerges => &mut t.map_merges,
        }
    }

    /// The bytes of `kinds` in `t`, summed (saturating).
    pub fn sum(kinds: &[TrafficKind], t: &TrafficStats) -> u64 {
        kinds.iter().fold(0u64, |s, k| s.saturating_add(k.get(t)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_kind_reads_and_writes_its_own_field() {
        let mut t = TrafficStats::default();
        for (i, k) in TrafficKind::ALL.iter().enumerate() {
            assert_eq!(k.index(), i);
            *k.get_mut(&mut t) = 1 << i;
        }
        assert_eq!(
            (t.rays, t.lookups, t.map_merges, t.total, t.cache_messages),
            (1, 2, 64, 0, 0)
        );
        for (i, k) in TrafficKind::ALL.iter().enumerate() {
            assert_eq!(k.get(&t), 1 << i, "{}", k.name());
        }
        assert_eq!(TrafficKind::sum(&TrafficKind::ALL, &t), 127);
        assert_eq!(
            TrafficKind::sum(&TrafficKind::PHM_COSTS, &t),
            2 + 4 + 32 + 64
        );
    }
}
