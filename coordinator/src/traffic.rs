//! Bytes between processes for one job, by kind (`JobStats.traffic`): the workers'
//! report deltas summed, `total` kept as the sum of the kinds; what the ray caches
//! and hit maps saved net of what consulting them cost; and the bytes of the workers'
//! reports themselves (`JobStats.reports`), which the coordinator measures as it
//! applies each one, since a report cannot carry its own size.

use dray_net::traffic::TrafficKind;
use dray_proto::v1::{ReportContributionsRequest, ReportStats, TrafficStats};
use prost::Message;

/// `ReportContributionsRequest.aov_pixels` and `aov_sums` (cluster.proto).
const AOV_PIXELS_TAG: u32 = 21;
const AOV_SUMS_TAG: u32 = 22;

/// Count report `r` into `a`: one message, its encoded size, and the part of it the
/// AOV fields take (their tags, lengths and values, as prost encodes them).
pub fn add_report(a: &mut ReportStats, r: &ReportContributionsRequest) {
    let aov = prost::encoding::fixed32::encoded_len_packed(AOV_PIXELS_TAG, &r.aov_pixels)
        + prost::encoding::sfixed64::encoded_len_packed(AOV_SUMS_TAG, &r.aov_sums);
    a.messages = a.messages.saturating_add(1);
    a.bytes = a.bytes.saturating_add(r.encoded_len() as u64);
    a.aov_bytes = a.aov_bytes.saturating_add(aov as u64);
}

/// Add the worker's delta `b` into `a` (saturating), and make `a.total` the sum of its
/// kinds (a worker's `total` is ignored: the coordinator sums).
pub fn add(a: &mut TrafficStats, b: &TrafficStats) {
    for k in TrafficKind::ALL {
        let x = k.get_mut(a);
        *x = x.saturating_add(k.get(b));
    }
    a.cache_messages = a.cache_messages.saturating_add(b.cache_messages);
    a.total = TrafficKind::sum(&TrafficKind::ALL, a);
}

/// `saved` bytes less the `costs` kinds of `t`, as a signed count (clamped to i64's
/// range).
fn net(saved: u64, costs: &[TrafficKind], t: &TrafficStats) -> i64 {
    let clamp = |x: u64| i64::try_from(x).unwrap_or(i64::MAX);
    clamp(saved).saturating_sub(clamp(TrafficKind::sum(costs, t)))
}

/// Ray caches' `bytes_not_sent` less what they cost ([`TrafficKind::CACHE_COSTS`]:
/// lookups, answers, ticket returns and entry copies).
pub fn cache_net(bytes_not_sent: u64, t: &TrafficStats) -> i64 {
    net(bytes_not_sent, &TrafficKind::CACHE_COSTS, t)
}

/// Hit maps' `bytes_not_sent` less what they cost ([`TrafficKind::PHM_COSTS`]: lookups,
/// answers, map outcomes and map merges).
pub fn phm_net(bytes_not_sent: u64, t: &TrafficStats) -> i64 {
    net(bytes_not_sent, &TrafficKind::PHM_COSTS, t)
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

    /// The AOV part is exactly what the two fields add to the message: the same report
    /// without them is `bytes - aov_bytes` long.
    #[test]
    fn reports_count_their_encoded_bytes_and_the_aov_part() {
        let with = ReportContributionsRequest {
            worker_id: "w1".into(),
            job_id: "job-1".into(),
            sequence: 3,
            pixels: vec![1, 2],
            sums: vec![5, 6, 7, 8, 9, 10],
            aov_pixels: vec![1, 2, 3],
            aov_sums: (0..24).collect(),
            ..Default::default()
        };
        let without = ReportContributionsRequest {
            aov_pixels: Vec::new(),
            aov_sums: Vec::new(),
            ..with.clone()
        };
        let mut a = ReportStats::default();
        add_report(&mut a, &with);
        assert_eq!(a.bytes, with.encoded_len() as u64);
        // Three fixed32 and 24 sfixed64; fields 21 and 22 take two-byte tags, and 192
        // bytes a two-byte length.
        assert_eq!(a.aov_bytes, (2 + 1 + 3 * 4) + (2 + 2 + 24 * 8));
        assert_eq!(a.bytes - a.aov_bytes, without.encoded_len() as u64);
        add_report(&mut a, &without);
        assert_eq!(a.messages, 2);
        assert_eq!(a.aov_bytes, 211);
        assert_eq!(a.bytes, (with.encoded_len() + without.encoded_len()) as u64);
    }
}
