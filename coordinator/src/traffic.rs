//! Bytes between processes for one job, by kind (`JobStats.traffic`): the workers'
//! report deltas summed, `total` kept as the sum of the kinds; and what the ray caches
//! and hit maps saved net of what consulting them cost.

use dray_proto::v1::TrafficStats;

/// Add the worker's delta `b` into `a` (saturating), and make `a.total` the sum of its
/// kinds (a worker's `total` is ignored: the coordinator sums).
pub fn add(a: &mut TrafficStats, b: &TrafficStats) {
    let sum = |x: &mut u64, y: u64| *x = x.saturating_add(y);
    sum(&mut a.rays, b.rays);
    sum(&mut a.lookups, b.lookups);
    sum(&mut a.answers, b.answers);
    sum(&mut a.ticket_returns, b.ticket_returns);
    sum(&mut a.entry_copies, b.entry_copies);
    sum(&mut a.map_outcomes, b.map_outcomes);
    sum(&mut a.map_merges, b.map_merges);
    sum(&mut a.cache_messages, b.cache_messages);
    a.total = [
        a.rays,
        a.lookups,
        a.answers,
        a.ticket_returns,
        a.entry_copies,
        a.map_outcomes,
        a.map_merges,
    ]
    .iter()
    .fold(0u64, |s, x| s.saturating_add(*x));
}

/// `saved` bytes less the `costs`, as a signed count (clamped to i64's range).
fn net(saved: u64, costs: &[u64]) -> i64 {
    let cost = costs.iter().fold(0u64, |s, x| s.saturating_add(*x));
    let clamp = |x: u64| i64::try_from(x).unwrap_or(i64::MAX);
    clamp(saved).saturating_sub(clamp(cost))
}

/// Ray caches' `bytes_not_sent` less lookups, answers, ticket returns and entry copies.
pub fn cache_net(bytes_not_sent: u64, t: &TrafficStats) -> i64 {
    net(
        bytes_not_sent,
        &[t.lookups, t.answers, t.ticket_returns, t.entry_copies],
    )
}

/// Hit maps' `bytes_not_sent` less lookups, answers, map outcomes and map merges.
pub fn phm_net(bytes_not_sent: u64, t: &TrafficStats) -> i64 {
    net(
        bytes_not_sent,
        &[t.lookups, t.answers, t.map_outcomes, t.map_merges],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deltas_sum_and_total_is_the_sum_of_kinds() {
        let mut a = TrafficStats::default();
        let d = TrafficStats {
            rays: 640,
            lookups: 72,
            answers: 9,
            ticket_returns: 40,
            entry_copies: 72,
            map_outcomes: 9,
            map_merges: 11,
            total: 12345, // ignored
            cache_messages: 5,
        };
        add(&mut a, &d);
        add(&mut a, &d);
        assert_eq!(a.rays, 1280);
        assert_eq!(a.cache_messages, 10);
        assert_eq!(a.total, 2 * (640 + 72 + 9 + 40 + 72 + 9 + 11));
    }

    #[test]
    fn net_savings_may_be_negative() {
        let t = TrafficStats {
            lookups: 100,
            answers: 20,
            ticket_returns: 30,
            entry_copies: 40,
            map_outcomes: 7,
            map_merges: 3,
            ..Default::default()
        };
        assert_eq!(cache_net(1000, &t), 810);
        assert_eq!(cache_net(64, &t), -126);
        assert_eq!(phm_net(64, &t), 64 - 130);
        assert_eq!(cache_net(u64::MAX, &TrafficStats::default()), i64::MAX);
    }
}
