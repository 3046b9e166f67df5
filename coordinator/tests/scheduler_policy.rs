//! The schedules as pure functions, without a server: image-plane blocks, round robin,
//! ownership after a loss, and the dynamic round (who is idle, which domains move, budgets,
//! replication, no new version when nothing changes, determinism).

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use dray_coordinator::scheduler::policy::{Change, RoundInput, Schedule, WorkerView, rebalance};
use dray_coordinator::scheduler::state::{JobSchedule, JobWorker, RoundOutcome};
use dray_coordinator::scheduler::table::Ownership;
use dray_proto::v1::{DomainQueue, ReportQueuesRequest, Tile, WorkerEndpoint};

fn ids(names: &[&str]) -> Vec<String> {
    names.iter().map(|s| s.to_string()).collect()
}

/// `(domain, rays_queued, resident, resident_bytes)`.
fn queues(q: &[(u32, u64, bool, u64)]) -> Vec<DomainQueue> {
    q.iter()
        .map(
            |&(domain, rays_queued, resident, resident_bytes)| DomainQueue {
                domain,
                rays_queued,
                resident,
                resident_bytes,
            },
        )
        .collect()
}

fn owners(r: &Ownership) -> Vec<Vec<&str>> {
    r.all_owners()
        .iter()
        .map(|o| o.iter().map(String::as_str).collect())
        .collect()
}

/// One round over `workers` = (id, budget, queues), with nothing loading.
fn round(
    domains: u32,
    routes: &Ownership,
    workers: &[(&str, u64, Vec<DomainQueue>)],
    replicate: bool,
) -> Option<dray_coordinator::scheduler::policy::Decision> {
    let views: Vec<WorkerView<'_>> = workers
        .iter()
        .map(|(id, budget, q)| WorkerView {
            id,
            budget: *budget,
            queues: q,
        })
        .collect();
    rebalance(&RoundInput {
        domains,
        routes,
        workers: &views,
        loading: &BTreeSet::new(),
        replicate,
    })
}

#[test]
fn image_plane_deals_contiguous_blocks_and_routes_nothing() {
    let dealt = Schedule::ImagePlane.deal_tiles(12, 3);
    assert_eq!(
        dealt,
        [vec![0, 1, 2, 3], vec![4, 5, 6, 7], vec![8, 9, 10, 11]]
    );
    // T not a multiple of n: worker i gets [i*T/n, (i+1)*T/n).
    let dealt = Schedule::ImagePlane.deal_tiles(10, 4);
    assert_eq!(
        dealt,
        [vec![0, 1], vec![2, 3, 4], vec![5, 6], vec![7, 8, 9]]
    );
    let r = Schedule::ImagePlane.initial_routes(8, &ids(&["a", "b"]));
    assert!(r.is_local() && r.to_proto().is_empty());
    let after = Schedule::ImagePlane.routes_after_loss(&r, 8, &ids(&["b"]));
    assert!(after.is_local());
}

#[test]
fn domain_schedule_is_round_robin_and_redealt_over_survivors() {
    let r = Schedule::Domain.initial_routes(5, &ids(&["a", "b", "c"]));
    assert_eq!(owners(&r), [["a"], ["b"], ["c"], ["a"], ["b"]]);
    assert_eq!(
        Schedule::Domain.deal_tiles(7, 3),
        [vec![0, 3, 6], vec![1, 4], vec![2, 5]]
    );
    let after = Schedule::Domain.routes_after_loss(&r, 5, &ids(&["a", "c"]));
    assert_eq!(owners(&after), [["a"], ["c"], ["a"], ["c"], ["a"]]);
    // Queue reports never change a static schedule.
    let ws = [("a", 0, queues(&[(0, 100, false, 1)])), ("b", 0, vec![])];
    let mut s = JobSchedule::new("j", Schedule::Domain, 2, &job_workers(&["a", "b"], 0));
    s.record_queues(&report("a", &ws[0].2));
    assert_eq!(
        s.round(Instant::now(), Duration::ZERO),
        RoundOutcome::Waiting
    );
}

#[test]
fn dynamic_keeps_surviving_owners_after_a_loss() {
    let r = Ownership::from_owners(vec![
        ids(&["a"]),
        ids(&["b", "c"]),
        ids(&["b"]),
        ids(&["c"]),
    ]);
    let after = Schedule::Dynamic { replicate: false }.routes_after_loss(&r, 4, &ids(&["a", "c"]));
    // Domain 1 keeps its surviving replica; 2 (b's alone) goes round robin to a.
    assert_eq!(owners(&after), [vec!["a"], vec!["c"], vec!["a"], vec!["c"]]);
}

#[test]
fn an_idle_worker_gets_the_most_wanted_unloaded_domain() {
    // a owns 0, 2, 4; b owns 1, 3. Rays wait for 0 (resident at a), 2 and 4 (not loaded).
    let routes = Ownership::round_robin(5, &ids(&["a", "b"]));
    let ws = [
        (
            "a",
            0,
            queues(&[(0, 50, true, 100), (2, 30, false, 100), (4, 70, false, 100)]),
        ),
        // b holds 1 but nobody wants it; rays for 2 wait here too (not forwarded yet).
        ("b", 0, queues(&[(1, 0, true, 100), (2, 50, false, 100)])),
    ];
    let d = round(5, &routes, &ws, false).expect("b is idle");
    // want(2) = 80 > want(4) = 70: b gets 2, which leaves a.
    assert_eq!(
        d.changes,
        [Change::Move {
            domain: 2,
            from: ids(&["a"]),
            to: "b".into()
        }]
    );
    assert_eq!(owners(&d.routes), [["a"], ["b"], ["b"], ["b"], ["a"]]);
    // The same inputs give the same decision.
    assert_eq!(round(5, &routes, &ws, false), Some(d));
}

#[test]
fn loaded_domains_stay_and_busy_workers_get_nothing() {
    let routes = Ownership::round_robin(4, &ids(&["a", "b"]));
    // 0 is wanted and resident at its owner a: it stays even though b is idle.
    let ws = [
        ("a", 0, queues(&[(0, 500, true, 1)])),
        ("b", 0, queues(&[(1, 0, true, 1)])),
    ];
    assert_eq!(round(4, &routes, &ws, false), None);
    // Nobody idle: both own a wanted domain, though 2 is not loaded anywhere.
    let ws = [
        ("a", 0, queues(&[(0, 5, true, 1), (2, 9, false, 1)])),
        ("b", 0, queues(&[(1, 5, false, 1)])),
    ];
    assert_eq!(round(4, &routes, &ws, false), None);
    // No rays anywhere: nothing to do.
    let ws = [("a", 0, vec![]), ("b", 0, vec![])];
    assert_eq!(round(4, &routes, &ws, false), None);
}

#[test]
fn ties_go_to_the_lower_domain_and_each_idle_worker_gets_one() {
    // a owns every domain and has loaded none; b, c, d own nothing.
    let routes = Ownership::from_owners(vec![ids(&["a"]); 4]);
    let ws = [
        (
            "a",
            0,
            queues(&[
                (0, 10, false, 1),
                (1, 20, false, 1),
                (2, 20, false, 1),
                (3, 5, false, 1),
            ]),
        ),
        ("b", 0, vec![]),
        ("c", 0, vec![]),
    ];
    let d = round(4, &routes, &ws, false).unwrap();
    let given: Vec<(u32, &str)> = d.changes.iter().filter_map(Change::given).collect();
    assert_eq!(given, [(1, "b"), (2, "c")]);
}

#[test]
fn budgets_are_respected_and_a_worker_holding_the_domain_is_preferred() {
    let routes = Ownership::from_owners(vec![ids(&["a"]), ids(&["a"])]);
    // Domain 0 takes 1000 bytes, domain 1 takes 100.
    let a = queues(&[(0, 90, false, 1000), (1, 10, false, 100)]);
    // b's budget is too small for 0 but fits 1; c is unlimited.
    let ws = [("a", 0, a.clone()), ("b", 500, vec![]), ("c", 0, vec![])];
    let d = round(2, &routes, &ws, false).unwrap();
    let given: Vec<(u32, &str)> = d.changes.iter().filter_map(Change::given).collect();
    assert_eq!(given, [(0, "c"), (1, "b")]);
    // Only small budgets: the big domain stays where it is.
    let ws = [("a", 0, a.clone()), ("b", 500, vec![]), ("c", 999, vec![])];
    let d = round(2, &routes, &ws, false).unwrap();
    let given: Vec<(u32, &str)> = d.changes.iter().filter_map(Change::given).collect();
    assert_eq!(given, [(1, "b")]);
    // The budget counts, not the free memory: c holds 900 bytes of an unwanted domain
    // but may evict it, and it is preferred for domain 0 because it still holds it.
    let routes = Ownership::from_owners(vec![ids(&["a"]), ids(&["a"]), ids(&["c"])]);
    let ws = [
        ("a", 0, a),
        ("b", 0, vec![]),
        ("c", 1000, queues(&[(0, 0, true, 1000), (2, 0, true, 900)])),
    ];
    let d = round(3, &routes, &ws, false);
    // Domain 0 is resident at c, a non-owner: still unloaded (no owner holds it).
    let given: Vec<(u32, String)> = d
        .unwrap()
        .changes
        .iter()
        .filter_map(Change::given)
        .map(|(d, w)| (d, w.to_string()))
        .collect();
    assert_eq!(given, [(0, "c".to_string()), (1, "b".to_string())]);
}

#[test]
fn a_domain_being_loaded_is_not_moved_again() {
    let routes = Ownership::from_owners(vec![ids(&["b"]), ids(&["a"])]);
    let q = [
        ("a", 0u64, queues(&[(0, 80, false, 1), (1, 0, true, 1)])),
        ("b", 0, queues(&[(0, 20, false, 1)])),
        ("c", 0, vec![]),
    ];
    let views: Vec<WorkerView<'_>> = q
        .iter()
        .map(|(id, budget, queues)| WorkerView {
            id,
            budget: *budget,
            queues,
        })
        .collect();
    let input = |loading| RoundInput {
        domains: 2,
        routes: &routes,
        workers: &views,
        loading,
        replicate: false,
    };
    // Without the mark, idle a (its domain 1 is unwanted) takes 0 from b.
    let none = BTreeSet::new();
    let d = rebalance(&input(&none)).unwrap();
    assert_eq!(d.changes[0].given(), Some((0, "a")));
    // b was given 0 by an earlier round and has not reported it resident yet.
    let loading = BTreeSet::from([(0, "b".to_string())]);
    assert_eq!(rebalance(&input(&loading)), None);
}

#[test]
fn replication_only_behind_the_flag_one_replica_per_domain_per_round() {
    // a holds 0 and 1, both hot; b and c own nothing wanted (c owns 2, unwanted).
    let routes = Ownership::from_owners(vec![ids(&["a"]), ids(&["a"]), ids(&["c"])]);
    let ws = [
        ("a", 0, queues(&[(0, 100, true, 10), (1, 300, true, 10)])),
        ("b", 0, vec![]),
        ("c", 0, vec![]),
    ];
    assert_eq!(
        round(3, &routes, &ws, false),
        None,
        "no replicas without the flag"
    );
    let d = round(3, &routes, &ws, true).unwrap();
    assert_eq!(
        d.changes,
        [
            Change::Replicate {
                domain: 1,
                to: "b".into()
            },
            Change::Replicate {
                domain: 0,
                to: "c".into()
            },
        ]
    );
    assert_eq!(
        owners(&d.routes),
        [vec!["a", "c"], vec!["a", "b"], vec!["c"]]
    );
    // One hot domain and two idle workers: one new replica this round, not two.
    let routes = Ownership::from_owners(vec![ids(&["a"]), ids(&["b"]), ids(&["c"])]);
    let ws = [
        ("a", 0, queues(&[(0, 100, true, 10)])),
        ("b", 0, vec![]),
        ("c", 0, vec![]),
    ];
    let d = round(3, &routes, &ws, true).unwrap();
    assert_eq!(d.changes.len(), 1);
    assert_eq!(owners(&d.routes)[0], ["a", "b"]);
    // Never more owners than workers.
    let routes = Ownership::from_owners(vec![ids(&["a", "b"]), ids(&["b"])]);
    let ws = [("a", 0, queues(&[(0, 100, true, 10)])), ("b", 0, vec![])];
    assert_eq!(round(2, &routes, &ws, true), None);
}

#[test]
fn unloaded_domains_come_before_replicas() {
    let routes = Ownership::from_owners(vec![ids(&["a"]), ids(&["a"])]);
    let ws = [
        ("a", 0, queues(&[(0, 1000, true, 10), (1, 5, false, 10)])),
        ("b", 0, vec![]),
        ("c", 0, vec![]),
    ];
    let d = round(2, &routes, &ws, true).unwrap();
    assert_eq!(
        d.changes,
        [
            Change::Move {
                domain: 1,
                from: ids(&["a"]),
                to: "b".into()
            },
            Change::Replicate {
                domain: 0,
                to: "c".into()
            },
        ]
    );
}

#[test]
fn reports_from_the_network_cannot_panic_a_round() {
    let routes = Ownership::round_robin(2, &ids(&["a", "b"]));
    let ws = [
        (
            "a",
            0,
            queues(&[
                (7, u64::MAX, true, u64::MAX),
                (0, u64::MAX, false, 1),
                (0, 5, false, 1),
            ]),
        ),
        ("b", 0, vec![]),
    ];
    // Domain 7 does not exist and is ignored; want(0) saturates. b (owning only the
    // unwanted 1) is idle and takes 0, which a has not loaded.
    let d = round(2, &routes, &ws, false).unwrap();
    let given: Vec<(u32, &str)> = d.changes.iter().filter_map(Change::given).collect();
    assert_eq!(given, [(0, "b")]);
}

fn job_workers(names: &[&str], budget: u64) -> Vec<JobWorker> {
    names
        .iter()
        .map(|n| JobWorker {
            endpoint: WorkerEndpoint {
                worker_id: n.to_string(),
                endpoint: format!("http://{n}:1"),
            },
            budget,
        })
        .collect()
}

fn report(worker: &str, q: &[DomainQueue]) -> ReportQueuesRequest {
    ReportQueuesRequest {
        worker_id: worker.into(),
        job_id: "j".into(),
        queues: q.to_vec(),
        ..Default::default()
    }
}

#[test]
fn a_round_without_a_change_makes_no_new_version() {
    let ws = job_workers(&["a", "b"], 0);
    let mut s = JobSchedule::new("j", Schedule::Dynamic { replicate: false }, 4, &ws);
    let t0 = Instant::now();
    let iv = Duration::from_millis(50);
    s.record_queues(&report("a", &queues(&[(0, 10, true, 1)])));
    assert_eq!(s.round(t0, iv), RoundOutcome::Unchanged);
    assert_eq!((s.version(), s.rounds()), (1, 1));
    // A joiner: a new version listing it, owning nothing; the next round gives it the
    // unloaded domain 2 (a's).
    let t = s.add_worker(job_workers(&["c"], 0).remove(0)).unwrap();
    assert_eq!((t.version, t.workers.len()), (2, 3));
    assert!(s.add_worker(job_workers(&["c"], 0).remove(0)).is_none());
    s.record_queues(&report("a", &queues(&[(0, 10, true, 1), (2, 4, false, 1)])));
    let RoundOutcome::Changed(t, _) = s.round(t0 + iv, iv) else {
        panic!("expected a change");
    };
    assert_eq!((t.version, t.attempt), (3, 0));
    let d2: Vec<&str> = t
        .routes
        .iter()
        .filter(|r| r.domain == 2)
        .map(|r| r.worker_id.as_str())
        .collect();
    assert!(d2 == ["b"] || d2 == ["c"], "{d2:?}");
}

#[test]
fn tiles_are_dealt_with_the_attempt() {
    let ws = job_workers(&["a", "b", "c"], 0);
    let mut s = JobSchedule::new("j", Schedule::ImagePlane, 1, &ws);
    let tiles: Vec<Tile> = (0..6)
        .map(|i| Tile {
            index: i * 2,
            ..Default::default()
        })
        .collect();
    let dealt = s.deal(&tiles);
    let idx: Vec<(String, Vec<u32>)> = dealt
        .iter()
        .map(|(w, t)| (w.clone(), t.iter().map(|t| t.index).collect()))
        .collect();
    assert_eq!(
        idx,
        [
            ("a".to_string(), vec![0, 2]),
            ("b".to_string(), vec![4, 6]),
            ("c".to_string(), vec![8, 10])
        ]
    );
    s.restart_without("b").unwrap();
    let dealt = s.deal(&tiles[..3]);
    assert_eq!(dealt.len(), 2);
    assert!(dealt.iter().flat_map(|(_, t)| t).all(|t| t.attempt == 1));
    assert_eq!(dealt[0].1.len() + dealt[1].1.len(), 3);
}

/// A worker owning more wanted domains than its budget holds keeps the loaded ones and
/// the most wanted of the rest, and lets the others go (no owner: their rays wait); an
/// idle worker is then given the most wanted of those.
#[test]
fn ownership_is_bounded_by_what_a_worker_can_hold() {
    // Domains of 100 bytes; a's budget of 700 leaves 525 for domains: 3 of them and the
    // load of a fourth (its reserve, 155 bytes with the domain) fit, so a holds 4.
    let routes = Ownership::from_owners((0..7).map(|_| ids(&["a"])).collect());
    let a = queues(&[
        (0, 5, true, 100),
        (1, 50, false, 100),
        (2, 40, false, 100),
        (3, 30, false, 100),
        (4, 20, false, 100),
        (5, 10, false, 100),
        (6, 0, true, 100),
    ]);
    // Everyone busy: a keeps its loaded domains (6 too, though nothing wants it now: it
    // counts against what a holds) and the two most wanted of the rest, and lets the
    // three least wanted unloaded domains go.
    let d = round(7, &routes, &[("a", 700, a.clone())], false).unwrap();
    let released: Vec<u32> = d
        .changes
        .iter()
        .filter_map(|c| match c {
            Change::Release { domain, from } if from == "a" => Some(*domain),
            _ => None,
        })
        .collect();
    assert_eq!(released, [3, 4, 5]);
    assert!(d.routes.owners(4).is_empty() && d.routes.owners(5).is_empty());
    assert_eq!(d.routes.owners(0), ["a"], "a loaded domain stays");
    assert_eq!(
        d.routes.owners(6),
        ["a"],
        "a loaded domain stays, wanted or not"
    );
    assert_eq!(d.routes.owners(1), ["a"]);
    // With an idle worker, the most wanted domain not loaded anywhere goes to it (a
    // kept it, but has not loaded it); the released ones wait for the next rounds.
    let d = round(
        7,
        &routes,
        &[("a", 700, a.clone()), ("b", 800, vec![])],
        false,
    )
    .unwrap();
    assert_eq!(d.routes.owners(1), ["b"]);
    assert!(d.routes.owners(4).is_empty() && d.routes.owners(5).is_empty());
    // An unlimited budget bounds nothing.
    assert!(round(7, &routes, &[("a", 0, a)], false).is_none());
}

/// An idle worker given a domain when it already owns as many as it holds lets go of one
/// of its own in the same round (one not loaded there first, then the lowest loaded
/// one): its store evicts that one when the table comes, rather than its least recently
/// used domain, which it would still own and load again when rays come for it.
#[test]
fn a_worker_given_a_domain_beyond_what_it_holds_lets_one_of_its_own_go() {
    // Domains of 100 bytes; a budget of 700 holds 4 (see above), 800 holds 5.
    let mut table: Vec<Vec<String>> = (0..4).map(|_| ids(&["a"])).collect();
    table.extend([ids(&["b"]), ids(&["b"])]);
    let routes = Ownership::from_owners(table);
    // a: idle, 0-2 loaded, 3 owned but not loaded. b: busy with 4, and 5 waits unloaded.
    let a = queues(&[(0, 0, true, 100), (1, 0, true, 100), (2, 0, true, 100)]);
    let b = queues(&[(4, 30, true, 100), (5, 50, false, 100)]);
    let d = round(
        6,
        &routes,
        &[("a", 700, a.clone()), ("b", 700, b.clone())],
        false,
    )
    .unwrap();
    assert_eq!(
        d.changes,
        [
            Change::Move {
                domain: 5,
                from: ids(&["b"]),
                to: "a".into(),
            },
            Change::Release {
                domain: 3,
                from: "a".into(),
            },
        ]
    );
    // Every domain of a loaded: the lowest goes.
    let all = queues(&[
        (0, 0, true, 100),
        (1, 0, true, 100),
        (2, 0, true, 100),
        (3, 0, true, 100),
    ]);
    let d = round(
        6,
        &routes,
        &[("a", 700, all.clone()), ("b", 700, b.clone())],
        false,
    )
    .unwrap();
    assert_eq!(d.routes.owners(5), ["a"]);
    assert!(d.routes.owners(0).is_empty());
    assert_eq!(d.routes.owners(3), ["a"]);
    // Room for one more: nothing of a's goes.
    let d = round(6, &routes, &[("a", 800, all), ("b", 700, b)], false).unwrap();
    assert_eq!(d.changes.len(), 1, "{:?}", d.changes);
    assert_eq!(d.routes.owners(5), ["a"]);
    assert!((0..4).all(|x| d.routes.owners(x) == ["a"]));
}
