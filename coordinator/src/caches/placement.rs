//! Where a job attempt's cache actors live: a pure function of the attempt's hosts and
//! its first routing table, tested without a server.
//!
//! **Rule.** Every face of domain `d` (walls `6d .. 6d + 6`) goes to the cache host
//! beside the worker that owns `d`, so that a ray the cache cannot answer is traced on
//! the machine it already reached: the lookup and the trace that follows a miss cost
//! one network hop, not two. A domain with no such host (image-plane schedules route
//! nothing, a held domain has no owner, stand-alone `dray cache` hosts are beside no
//! worker, an owner may announce no cache endpoint) goes round robin over the hosts by
//! domain (`d % hosts`), which spreads neighbouring domains, as domain ownership does.
//!
//! **Sender placement** ([`Placement::replicated`]; dray's, not Little 2011's, whose
//! caches have no replicas): every host holds a replica of every wall, so a worker
//! looks up a ray in its own process, the one the ray is leaving, and a hit sends
//! nothing; host `i` is replica `i + 1` (tickets carry the number, so returns
//! find the replica that issued them). Each wall still has a *home* by the rule above,
//! where workers without a host of their own look up.
//!
//! **Failures.** A host that cannot open its walls is left out and its walls go round
//! robin by domain over the hosts that are left ([`Placement::without`]); the others keep
//! theirs, so only the lost walls have to be opened again. (Replicated, the others hold
//! every wall already; those whose index moved are opened again with their new replica
//! number, before any ticket exists.)

use std::collections::{BTreeMap, BTreeSet, HashMap};

use dray_core::wall::FACES;
use dray_proto::v1::CacheHost;

use crate::ownership::Ownership;

/// The hosts a job attempt may place cache actors on, and which of them sits beside
/// which worker.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Candidates {
    /// The hosts, in placement order.
    pub hosts: Vec<CacheHost>,
    /// Worker id → index in `hosts` of the host in that worker's process.
    pub beside_worker: HashMap<String, usize>,
}

impl Candidates {
    /// The stand-alone hosts when there are any (they were started to take the caches
    /// off the workers), else the cache hosts the attempt's `workers` (id, announced
    /// endpoint, empty for none) run beside them, in worker order.
    pub fn choose(standalone: Vec<CacheHost>, workers: &[(String, String)]) -> Candidates {
        if !standalone.is_empty() {
            return Candidates {
                hosts: standalone,
                beside_worker: HashMap::new(),
            };
        }
        let mut c = Candidates::default();
        for (id, endpoint) in workers.iter().filter(|(_, e)| !e.is_empty()) {
            c.beside_worker.insert(id.clone(), c.hosts.len());
            c.hosts.push(CacheHost {
                host_id: id.clone(),
                endpoint: endpoint.clone(),
            });
        }
        c
    }

    /// Whether there is no host at all.
    pub fn is_empty(&self) -> bool {
        self.hosts.is_empty()
    }

    /// For each of `domains` domains, the host beside its (first) owner in `routes`, if
    /// that owner runs one.
    pub fn beside(&self, routes: &Ownership, domains: u32) -> Vec<Option<usize>> {
        (0..domains)
            .map(|d| {
                routes
                    .owners(d)
                    .first()
                    .and_then(|w| self.beside_worker.get(w).copied())
            })
            .collect()
    }
}

/// The cache hosts of one job attempt and the host of every wall, as the routing table
/// carries them (`RoutingTable.cache_hosts`, `wall_hosts`). Empty: no caches.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Placement {
    hosts: Vec<CacheHost>,
    /// Index = wall (`6 * domain + face`), value = index in `hosts`.
    wall_hosts: Vec<u32>,
    /// Sender placement: every host holds a replica of every wall.
    replicated: bool,
}

impl Placement {
    /// No caches.
    pub fn none() -> Placement {
        Placement::default()
    }

    /// Place the walls of `domains` domains on `c.hosts`: domain `d` on `beside[d]` when
    /// that is a host, else on host `d % hosts`. Hosts given no wall are left out of the
    /// result. No hosts: no caches.
    pub fn place(domains: u32, c: &Candidates, beside: &[Option<usize>]) -> Placement {
        let n = c.hosts.len();
        if n == 0 {
            return Placement::none();
        }
        let per_domain: Vec<usize> = (0..domains as usize)
            .map(|d| {
                beside
                    .get(d)
                    .copied()
                    .flatten()
                    .filter(|&h| h < n)
                    .unwrap_or(d % n)
            })
            .collect();
        Placement::compact(&c.hosts, &per_domain)
    }

    /// Sender placement: every host of `c` holds a replica of every wall of `domains`
    /// domains; each wall's home is as [`Placement::place`] would put it. No hosts: no
    /// caches.
    pub fn replicated(domains: u32, c: &Candidates, beside: &[Option<usize>]) -> Placement {
        let n = c.hosts.len();
        if n == 0 {
            return Placement::none();
        }
        let wall_hosts = (0..domains as usize)
            .flat_map(|d| {
                let h = beside
                    .get(d)
                    .copied()
                    .flatten()
                    .filter(|&h| h < n)
                    .unwrap_or(d % n);
                std::iter::repeat_n(h as u32, FACES as usize)
            })
            .collect();
        Placement {
            hosts: c.hosts.clone(),
            wall_hosts,
            replicated: true,
        }
    }

    /// Whether every host holds a replica of every wall.
    pub fn is_replicated(&self) -> bool {
        self.replicated
    }

    /// The replica number host `h` opens its walls as: `h + 1` under sender placement,
    /// 0 (the only actor) otherwise.
    pub fn replica_of(&self, h: usize) -> u32 {
        if self.replicated {
            u32::try_from(h + 1).unwrap_or(u32::MAX)
        } else {
            0
        }
    }

    /// The placement with every domain `d` on `c.hosts[per_domain[d]]`, listing only
    /// the hosts used, in their order in `hosts`.
    fn compact(hosts: &[CacheHost], per_domain: &[usize]) -> Placement {
        let used: BTreeSet<usize> = per_domain.iter().copied().collect();
        let index: BTreeMap<usize, u32> = used
            .iter()
            .enumerate()
            .map(|(new, &old)| (old, new as u32))
            .collect();
        let wall_hosts = per_domain
            .iter()
            .flat_map(|h| std::iter::repeat_n(index[h], FACES as usize))
            .collect();
        Placement {
            hosts: used.iter().map(|&h| hosts[h].clone()).collect(),
            wall_hosts,
            replicated: false,
        }
    }

    /// Whether the attempt has no caches.
    pub fn is_empty(&self) -> bool {
        self.hosts.is_empty()
    }

    /// The hosts.
    pub fn hosts(&self) -> &[CacheHost] {
        &self.hosts
    }

    /// The host index of every wall.
    pub fn wall_hosts(&self) -> &[u32] {
        &self.wall_hosts
    }

    /// The walls of host `h`, ascending (every wall, under sender placement).
    pub fn walls_of(&self, h: usize) -> Vec<u32> {
        if self.replicated {
            return if h < self.hosts.len() {
                (0..self.wall_hosts.len() as u32).collect()
            } else {
                Vec::new()
            };
        }
        self.wall_hosts
            .iter()
            .enumerate()
            .filter(|(_, x)| **x as usize == h)
            .map(|(w, _)| w as u32)
            .collect()
    }

    /// The placement without the hosts at indices `failed`: their domains go round robin
    /// by domain over the hosts left (domain `d` to the `d % left`-th of them), every
    /// other wall stays where it is. Also returns, per host of the new placement (by its
    /// new index), the walls it gained, which must be opened there. With no host left,
    /// no caches.
    pub fn without(&self, failed: &BTreeSet<usize>) -> (Placement, Vec<(usize, Vec<u32>)>) {
        let left: Vec<usize> = (0..self.hosts.len())
            .filter(|h| !failed.contains(h))
            .collect();
        if left.is_empty() {
            return (Placement::none(), Vec::new());
        }
        let domains = self.wall_hosts.len() / FACES as usize;
        if self.replicated {
            return self.replicas_without(&left);
        }
        let mut moved = BTreeSet::new();
        let per_domain: Vec<usize> = (0..domains)
            .map(|d| {
                let h = self.wall_hosts[d * FACES as usize] as usize;
                if failed.contains(&h) {
                    moved.insert(d);
                    left[d % left.len()]
                } else {
                    h
                }
            })
            .collect();
        let next = Placement::compact(&self.hosts, &per_domain);
        let mut gained: BTreeMap<usize, Vec<u32>> = BTreeMap::new();
        for d in moved {
            let h = next.wall_hosts[d * FACES as usize] as usize;
            gained
                .entry(h)
                .or_default()
                .extend((0..FACES).map(|f| d as u32 * FACES + f));
        }
        (next, gained.into_iter().collect())
    }

    /// [`Placement::without`] under sender placement: the hosts `left` (old indices,
    /// ascending) keep every wall; homes on lost hosts go round robin by domain over
    /// them. The hosts whose index (so replica number) moved must open their walls
    /// again with the new number.
    fn replicas_without(&self, left: &[usize]) -> (Placement, Vec<(usize, Vec<u32>)>) {
        let index: BTreeMap<usize, u32> = left
            .iter()
            .enumerate()
            .map(|(new, &old)| (old, new as u32))
            .collect();
        let wall_hosts = self
            .wall_hosts
            .chunks(FACES as usize)
            .enumerate()
            .flat_map(|(d, homes)| {
                let h = homes.first().copied().unwrap_or(0) as usize;
                let new = index
                    .get(&h)
                    .copied()
                    .unwrap_or(index[&left[d % left.len()]]);
                std::iter::repeat_n(new, FACES as usize)
            })
            .collect();
        let next = Placement {
            hosts: left.iter().map(|&h| self.hosts[h].clone()).collect(),
            wall_hosts,
            replicated: true,
        };
        let moved = left
            .iter()
            .enumerate()
            .filter(|(new, old)| new != *old)
            .map(|(new, _)| (new, next.walls_of(new)))
            .collect();
        (next, moved)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replicas_hold_every_wall_and_keep_homes() {
        let c = Candidates::choose(
            Vec::new(),
            &[
                ("a".into(), "http://a:9".into()),
                ("b".into(), "http://b:9".into()),
                ("c".into(), "http://c:9".into()),
            ],
        );
        let p = Placement::replicated(4, &c, &[Some(2), None, Some(0), None]);
        assert!(p.is_replicated());
        assert_eq!(p.hosts().len(), 3);
        assert_eq!(p.walls_of(1), (0..24).collect::<Vec<u32>>());
        assert_eq!(p.walls_of(3), Vec::<u32>::new());
        assert_eq!((p.replica_of(0), p.replica_of(2)), (1, 3));
        assert_eq!(&p.wall_hosts()[..6], &[2; 6]);
        assert_eq!(&p.wall_hosts()[6..12], &[1; 6]);
        // Host 1 fails: 0 keeps its number, 2 becomes 1 and opens again as replica 2.
        let (q, again) = p.without(&BTreeSet::from([1]));
        assert!(q.is_replicated());
        assert_eq!(ids(&q), ["a", "c"]);
        assert_eq!(again, vec![(1, (0..24).collect::<Vec<u32>>())]);
        assert_eq!(q.replica_of(1), 2);
        assert_eq!(&q.wall_hosts()[..6], &[1; 6]);
        assert!(q.wall_hosts().iter().all(|&h| h < 2));
        assert_eq!(Placement::place(4, &c, &[]).replica_of(0), 0);
    }

    fn host(id: &str) -> CacheHost {
        CacheHost {
            host_id: id.into(),
            endpoint: format!("http://{id}:9"),
        }
    }

    fn ids(p: &Placement) -> Vec<&str> {
        p.hosts().iter().map(|h| h.host_id.as_str()).collect()
    }

    /// The host id of each domain (its six walls must agree).
    fn by_domain(p: &Placement) -> Vec<&str> {
        p.wall_hosts()
            .chunks(6)
            .map(|c| {
                assert!(
                    c.iter().all(|h| *h == c[0]),
                    "a domain's walls are split: {c:?}"
                );
                p.hosts()[c[0] as usize].host_id.as_str()
            })
            .collect()
    }

    fn workers(list: &[(&str, &str)]) -> Vec<(String, String)> {
        list.iter()
            .map(|(w, e)| (w.to_string(), e.to_string()))
            .collect()
    }

    #[test]
    fn walls_go_beside_the_owner_of_their_domain() {
        let c = Candidates::choose(
            Vec::new(),
            &workers(&[
                ("a", "http://a:9"),
                ("b", "http://b:9"),
                ("c", "http://c:9"),
            ]),
        );
        assert_eq!(c.hosts.len(), 3);
        // Owners: a, b, c, a, b (round robin) but shuffled to prove the owner rules.
        let routes = Ownership::from_owners(vec![
            vec!["c".into()],
            vec!["a".into()],
            vec!["b".into(), "a".into()],
            vec!["c".into()],
        ]);
        let p = Placement::place(4, &c, &c.beside(&routes, 4));
        assert_eq!(p.wall_hosts().len(), 24);
        assert_eq!(by_domain(&p), ["c", "a", "b", "c"]);
        assert_eq!(ids(&p), ["a", "b", "c"]);
        assert_eq!(p.walls_of(2), [0, 1, 2, 3, 4, 5, 18, 19, 20, 21, 22, 23]);
        assert_eq!(p.hosts()[2].endpoint, "http://c:9");
    }

    #[test]
    fn round_robin_without_an_owner_beside() {
        // b announced no cache host; image-plane routes nothing; domain 1 is held.
        let c = Candidates::choose(
            Vec::new(),
            &workers(&[("a", "http://a:9"), ("b", ""), ("c", "http://c:9")]),
        );
        assert_eq!(ids(&Placement::place(1, &c, &[])), ["a"]);
        let local = Ownership::local();
        let p = Placement::place(5, &c, &c.beside(&local, 5));
        assert_eq!(by_domain(&p), ["a", "c", "a", "c", "a"]);
        let routes = Ownership::from_owners(vec![
            vec!["b".into()],
            vec![],
            vec!["c".into()],
            vec!["a".into()],
        ]);
        let p = Placement::place(4, &c, &c.beside(&routes, 4));
        // 0: owner b has no host, round robin 0 % 2 -> a; 1: held, 1 % 2 -> c.
        assert_eq!(by_domain(&p), ["a", "c", "c", "a"]);
    }

    #[test]
    fn standalone_hosts_take_everything_round_robin() {
        let c = Candidates::choose(
            vec![host("cache-1"), host("cache-2")],
            &workers(&[("a", "http://a:9")]),
        );
        assert!(c.beside_worker.is_empty());
        let routes = Ownership::from_owners(vec![vec!["a".into()]; 3]);
        let p = Placement::place(3, &c, &c.beside(&routes, 3));
        assert_eq!(by_domain(&p), ["cache-1", "cache-2", "cache-1"]);
        // Only the hosts given walls are listed.
        let p = Placement::place(1, &c, &c.beside(&routes, 1));
        assert_eq!(ids(&p), ["cache-1"]);
        assert_eq!(p.wall_hosts(), [0; 6]);
    }

    #[test]
    fn nothing_to_place_on() {
        let c = Candidates::choose(Vec::new(), &workers(&[("a", ""), ("b", "")]));
        assert!(c.is_empty());
        let p = Placement::place(4, &c, &[]);
        assert!(p.is_empty() && p.wall_hosts().is_empty());
    }

    #[test]
    fn a_failed_host_is_replaced_round_robin_over_the_rest() {
        let c = Candidates::choose(vec![host("h0"), host("h1"), host("h2")], &[]);
        let p = Placement::place(6, &c, &[]);
        assert_eq!(by_domain(&p), ["h0", "h1", "h2", "h0", "h1", "h2"]);
        let (q, gained) = p.without(&BTreeSet::from([1]));
        // Domains 1 and 4 were on h1: 1 % 2 -> h2, 4 % 2 -> h0.
        assert_eq!(by_domain(&q), ["h0", "h2", "h2", "h0", "h0", "h2"]);
        assert_eq!(ids(&q), ["h0", "h2"]);
        assert_eq!(
            gained,
            [
                (0, (24..30).collect::<Vec<u32>>()),
                (1, (6..12).collect::<Vec<u32>>())
            ]
        );
        // Losing another re-places on the last one; losing all leaves no caches.
        let (r, gained) = q.without(&BTreeSet::from([0]));
        assert_eq!(by_domain(&r), ["h2"; 6]);
        assert_eq!(gained.len(), 1);
        assert_eq!(gained[0].1.len(), 6 * 3);
        let (none, gained) = r.without(&BTreeSet::from([0]));
        assert!(none.is_empty() && gained.is_empty());
    }
}
