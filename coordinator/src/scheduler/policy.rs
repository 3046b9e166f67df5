//! The schedules of Navrátil et al. 2012, as pure functions: inputs in, ownership (or
//! nothing) out. No clocks, no gRPC, no hash-map order: the same inputs give the same
//! table, so every decision is unit-tested and replayable.
//!
//! - **replicated**: no routing ([`Ownership::local`]): every worker holds the whole
//!   scene and traces whole paths for its tiles, dealt round robin (interleaved, so every
//!   worker gets a share of the cheap and the costly parts of the image). What `auto`
//!   ([`super::auto`]) chooses when the scene fits every worker's budget.
//! - **image-plane**: no routing ([`Ownership::local`]); tiles in contiguous blocks, worker
//!   `i` of `n` getting tiles `[i*T/n, (i+1)*T/n)`. Each worker loads whatever domain its
//!   fullest queue needs. The table never changes.
//! - **domain**: static round robin (domain `d` to worker `d % n`), tiles round robin.
//!   Changes only when a worker is lost.
//! - **dynamic** (ray-weighted): starts as domain; then each round ([`rebalance`]) bounds
//!   every worker's domains by what its budget holds (the rest lose their owner and
//!   their rays wait where they are), gives the most-wanted domains that no owner holds
//!   to workers that no ray needs (each letting one of its own go if it is full), and
//!   with `replicate`, adds idle workers as extra owners of hot resident domains.
//! - **dynamic-from-image-plane**: the dynamic schedule started as Navrátil et al. 2012
//!   start theirs, from image-plane: tiles in image-plane blocks and no routing, each
//!   worker loading what its rays need, until every worker has reported its queues once;
//!   then ([`leave_image_plane`]) each domain goes to a worker that holds it (the one
//!   with the most rays waiting for it), the others to the workers owning fewest, and
//!   the rounds go on as under `dynamic`.

use std::collections::{BTreeMap, BTreeSet, HashMap};

use dray_proto::v1::DomainQueue;
use dray_scene::partition::resident::load_reserve;

use crate::ownership::Ownership;

/// The schedule names a job may ask for (JobSpec.schedule; empty means auto).
pub const SCHEDULE_NAMES: [&str; 6] = [
    "auto",
    "replicated",
    "image-plane",
    "domain",
    "dynamic",
    "dynamic-from-image-plane",
];

/// The schedule a job asks for: one by name, or `auto`, which the coordinator resolves
/// when the job starts, from the scene's size and the workers' budgets
/// ([`super::auto::choose`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ScheduleRequest {
    /// Replicate the scene when it fits every worker, else dynamic.
    Auto {
        /// With the dynamic schedule, also replicate hot resident domains.
        replicate: bool,
    },
    /// This schedule, whatever the scene.
    Forced(Schedule),
}

impl ScheduleRequest {
    /// The request JobSpec `schedule` and `replicate` make ("" is auto).
    pub fn parse(name: &str, replicate: bool) -> Result<ScheduleRequest, ScheduleError> {
        match name {
            "" | "auto" => Ok(ScheduleRequest::Auto { replicate }),
            other => Schedule::parse(other, replicate).map(ScheduleRequest::Forced),
        }
    }

    /// The name, as JobSpec spells it.
    pub fn name(self) -> &'static str {
        match self {
            ScheduleRequest::Auto { .. } => "auto",
            ScheduleRequest::Forced(s) => s.name(),
        }
    }
}

/// How a job's domains and rays are placed on its workers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Schedule {
    /// Every worker holds the whole scene and traces its tiles' whole paths; tiles dealt
    /// round robin.
    Replicated,
    /// Each worker traces its own block of tiles and every ray they lead to.
    ImagePlane,
    /// Static round-robin ownership; rays go to owners.
    Domain,
    /// Ray-weighted: domains move to idle workers, driven by queue reports.
    Dynamic {
        /// Also replicate hot resident domains on idle workers.
        replicate: bool,
    },
    /// Dynamic, started from image-plane (Navrátil et al. 2012): image-plane blocks of
    /// tiles and no routing until every worker has reported its queues, then owners by
    /// residency ([`leave_image_plane`]) and dynamic rounds.
    DynamicFromImagePlane {
        /// Also replicate hot resident domains on idle workers.
        replicate: bool,
    },
}

/// A schedule a job cannot have.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ScheduleError {
    /// Not one of [`SCHEDULE_NAMES`].
    #[error(
        "schedule: unknown schedule {0:?} (expected auto, replicated, image-plane, domain, \
         dynamic or dynamic-from-image-plane; empty means auto)"
    )]
    Unknown(String),
    /// `replicate` with a static schedule.
    #[error(
        "replicate: hot-domain replication needs the dynamic schedule, not {0:?} (leave \
         schedule empty, or set it to auto or dynamic)"
    )]
    ReplicateNeedsDynamic(&'static str),
}

impl Schedule {
    /// The schedule a resolved JobSpec `schedule` and `replicate` name (what JobSetup
    /// carries; "" is dynamic, as it was before `auto`: a job taken back from an older
    /// store). `auto` is not a schedule: see [`ScheduleRequest::parse`].
    pub fn parse(name: &str, replicate: bool) -> Result<Schedule, ScheduleError> {
        let s = match name {
            "" | "dynamic" => return Ok(Schedule::Dynamic { replicate }),
            "dynamic-from-image-plane" => {
                return Ok(Schedule::DynamicFromImagePlane { replicate });
            }
            "replicated" => Schedule::Replicated,
            "image-plane" => Schedule::ImagePlane,
            "domain" => Schedule::Domain,
            other => return Err(ScheduleError::Unknown(other.to_string())),
        };
        if replicate {
            return Err(ScheduleError::ReplicateNeedsDynamic(s.name()));
        }
        Ok(s)
    }

    /// The name, as JobSpec, JobSetup and JobStats spell it.
    pub fn name(self) -> &'static str {
        match self {
            Schedule::Replicated => "replicated",
            Schedule::ImagePlane => "image-plane",
            Schedule::Domain => "domain",
            Schedule::Dynamic { .. } => "dynamic",
            Schedule::DynamicFromImagePlane { .. } => "dynamic-from-image-plane",
        }
    }

    /// Whether rounds of queue reports can change the table.
    pub fn is_dynamic(self) -> bool {
        matches!(
            self,
            Schedule::Dynamic { .. } | Schedule::DynamicFromImagePlane { .. }
        )
    }

    /// Whether the rounds also replicate hot resident domains on idle workers.
    pub fn replicates(self) -> bool {
        matches!(
            self,
            Schedule::Dynamic { replicate: true }
                | Schedule::DynamicFromImagePlane { replicate: true }
        )
    }

    /// The first ownership of `domains` domains over `workers` (in job order).
    pub fn initial_routes(self, domains: u32, workers: &[String]) -> Ownership {
        match self {
            Schedule::Replicated
            | Schedule::ImagePlane
            | Schedule::DynamicFromImagePlane { .. } => Ownership::local(),
            Schedule::Domain | Schedule::Dynamic { .. } => Ownership::round_robin(domains, workers),
        }
    }

    /// Deal `tiles` tiles (positions `0..tiles` of a row-major list) over `workers`
    /// workers: for each worker, the positions it gets, ascending. Image-plane: contiguous
    /// blocks, worker `i` getting `[i*T/n, (i+1)*T/n)` (a worker's rays stay near each
    /// other, so its domain loads serve more of them); otherwise round robin, position
    /// `j` to worker `j % n` (the replicated schedule loads nothing, and interleaved tiles
    /// even out the cost of the image's parts). No workers: nothing dealt.
    pub fn deal_tiles(self, tiles: usize, workers: usize) -> Vec<Vec<usize>> {
        let mut out = vec![Vec::new(); workers];
        if workers == 0 {
            return out;
        }
        match self {
            Schedule::ImagePlane | Schedule::DynamicFromImagePlane { .. } => {
                let (t, n) = (tiles as u64, workers as u64);
                for (i, mine) in out.iter_mut().enumerate() {
                    let i = i as u64;
                    mine.extend((i * t / n) as usize..((i + 1) * t / n) as usize);
                }
            }
            Schedule::Replicated | Schedule::Domain | Schedule::Dynamic { .. } => {
                for j in 0..tiles {
                    out[j % workers].push(j);
                }
            }
        }
        out
    }

    /// The ownership once only `survivors` (non-empty, in job order) are left of the
    /// job's workers. Replicated and image-plane stay local; domain is dealt round robin
    /// again over the survivors; dynamic keeps every surviving owner where it is (its domains may still
    /// be loaded there) and deals the domains left without an owner round robin, in
    /// domain order, over the survivors.
    pub fn routes_after_loss(
        self,
        current: &Ownership,
        domains: u32,
        survivors: &[String],
    ) -> Ownership {
        match self {
            Schedule::Replicated | Schedule::ImagePlane => Ownership::local(),
            Schedule::Domain => Ownership::round_robin(domains, survivors),
            // Still in its image-plane phase: it stays there.
            Schedule::DynamicFromImagePlane { .. } if current.is_local() => Ownership::local(),
            Schedule::Dynamic { .. } | Schedule::DynamicFromImagePlane { .. } => {
                if survivors.is_empty() {
                    return Ownership::from_owners(Vec::new());
                }
                let mut next = 0usize;
                let owners = (0..domains)
                    .map(|d| {
                        let kept: Vec<String> = current
                            .owners(d)
                            .iter()
                            .filter(|o| survivors.contains(o))
                            .cloned()
                            .collect();
                        if kept.is_empty() {
                            let w = survivors[next % survivors.len()].clone();
                            next += 1;
                            vec![w]
                        } else {
                            kept
                        }
                    })
                    .collect();
                Ownership::from_owners(owners)
            }
        }
    }
}

/// One worker as a dynamic round sees it.
#[derive(Clone, Copy, Debug)]
pub struct WorkerView<'a> {
    /// Its id.
    pub id: &'a str,
    /// Its memory budget for resident domains (0 = unlimited).
    pub budget: u64,
    /// Its latest queue report for this job attempt (empty if none yet).
    pub queues: &'a [DomainQueue],
}

/// Everything a dynamic round decides from.
#[derive(Clone, Copy, Debug)]
pub struct RoundInput<'a> {
    /// Domains in the job.
    pub domains: u32,
    /// The current ownership.
    pub routes: &'a Ownership,
    /// The job's workers, in job order (ties between idle workers go to the first).
    pub workers: &'a [WorkerView<'a>],
    /// `(domain, worker)` pairs given out by earlier rounds whose worker has not yet
    /// reported the domain resident: the load is under way, so the domain counts as
    /// loaded (moving it again would throw the load away) and gets no other replica.
    pub loading: &'a BTreeSet<(u32, String)>,
    /// Replicate hot domains on idle workers that are still idle after the moves.
    pub replicate: bool,
}

/// One change a round made.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Change {
    /// `domain` now belongs to `to` alone (it was with `from`, where it was not loaded).
    Move {
        /// The domain.
        domain: u32,
        /// Its previous owners.
        from: Vec<String>,
        /// The idle worker that now owns it.
        to: String,
    },
    /// `to` became an extra owner of `domain`, which is resident elsewhere.
    Replicate {
        /// The domain.
        domain: u32,
        /// The idle worker added as owner.
        to: String,
    },
    /// `domain` no longer has an owner: `from` owned more wanted domains than it can
    /// hold, and this one was not loaded there. Its rays wait where they are until a
    /// round gives it to a worker with nothing else to do.
    Release {
        /// The domain.
        domain: u32,
        /// Its owner until now.
        from: String,
    },
}

impl Change {
    /// The domain whose owners changed.
    pub fn domain(&self) -> u32 {
        match self {
            Change::Move { domain, .. }
            | Change::Replicate { domain, .. }
            | Change::Release { domain, .. } => *domain,
        }
    }

    /// The domain changed and the worker that received it (None for a release).
    pub fn given(&self) -> Option<(u32, &str)> {
        match self {
            Change::Move { domain, to, .. } | Change::Replicate { domain, to } => {
                Some((*domain, to))
            }
            Change::Release { .. } => None,
        }
    }
}

/// Domains `w` can hold at once, judged from its budget and the largest domain the
/// reports sized: a quarter of a worker's budget is for rays, and its store loads the
/// last of them only with room for that load's peak ([`load_reserve`], the domain
/// itself included) beside the others. So `cap` domains fit when `cap - 1` of them and
/// one load do. At least 1; None when the budget is unlimited or no size is known yet.
fn capacity(w: &WorkerView<'_>, size: u64) -> Option<usize> {
    slots(w.budget, size)
}

/// Domains of `size` bytes a worker with `budget` holds at once (see `capacity`): the
/// one rule for the rounds and for `auto`'s room for copies ([`super::auto`]). At least
/// 1; None when the budget is unlimited (0) or the size unknown (0).
pub fn slots(budget: u64, size: u64) -> Option<usize> {
    if budget == 0 || size == 0 {
        return None;
    }
    let share = budget / 4 * 3;
    let others = share.saturating_sub(load_reserve(size)) / size;
    Some((others as usize).saturating_add(1))
}

/// What a round decided.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Decision {
    /// The new ownership.
    pub routes: Ownership,
    /// What changed, in the order decided.
    pub changes: Vec<Change>,
}

/// What the reports say about one domain.
#[derive(Clone, Debug, Default)]
struct DomainView {
    /// Rays queued for it, over every worker (owners and others alike).
    want: u64,
    /// Workers that hold it.
    resident_at: BTreeSet<String>,
    /// Largest resident size any report gave.
    bytes: u64,
}

/// One dynamic round. First, a worker owning alone more domains than its budget holds
/// (see `capacity`; wanted or not: an unwanted domain it owns is loaded again when its
/// rays come, evicting another) keeps the ones loaded or loading there and the most
/// wanted of the rest, and releases the others (no owner: their rays wait where they
/// are). Then
/// `want(d)` is the sum of the rays queued for `d` at every worker. A
/// worker is idle when no domain it owns is wanted; a domain is unloaded when it is
/// neither resident nor [being loaded](RoundInput::loading) at any of its owners. The
/// most-wanted unloaded domains (want > 0, descending, ties to the lower index) go to
/// idle workers, one per idle worker, each to an idle worker whose budget the domain's
/// resident size fits (0 = unlimited; the budget, not the free memory, since a worker
/// evicts domains nobody wants), preferring one that still holds the domain, else the
/// first in job order. The domain leaves its previous owners. Loaded domains stay.
/// With `replicate`, idle workers left over become extra owners of the most-wanted
/// domains resident somewhere (one new replica per domain per round, never more owners
/// than workers). Last, a worker given domains beyond what it holds lets go of as many
/// of its own (`release_for_gifts`). `None` when nothing changes.
pub fn rebalance(input: &RoundInput<'_>) -> Option<Decision> {
    if input.routes.is_local() || input.workers.is_empty() {
        return None;
    }
    let mut round = Round {
        input,
        view: domain_views(input),
        owners: (0..input.domains)
            .map(|d| input.routes.owners(d).to_vec())
            .collect(),
        changes: Vec::new(),
    };
    let kept = round.bound_owners();
    let mut idle = IdleWorkers::new(input, &round.view, &round.owners);
    if idle.left > 0 {
        round.move_unloaded(&mut idle);
    }
    if input.replicate && idle.left > 0 {
        round.replicate_hot(&mut idle);
    }
    let Round {
        view,
        mut owners,
        mut changes,
        ..
    } = round;
    release_for_gifts(&mut owners, &mut changes, kept, &view, input);
    if changes.is_empty() {
        return None;
    }
    Some(Decision {
        routes: Ownership::from_owners(owners),
        changes,
    })
}

/// A dynamic round in progress: what the reports say about each domain, the owners as
/// decided so far, and the changes in the order decided.
struct Round<'i, 'a> {
    input: &'i RoundInput<'a>,
    view: Vec<DomainView>,
    owners: Vec<Vec<String>>,
    changes: Vec<Change>,
}

impl RoundInput<'_> {
    /// Whether domain `d` was given to worker `w` by an earlier round and is still
    /// loading there.
    fn loading_at(&self, d: usize, w: &str) -> bool {
        self.loading.contains(&(d as u32, w.to_string()))
    }
}

impl DomainView {
    /// Whether any worker has rays queued for the domain.
    fn wanted(&self) -> bool {
        self.want > 0
    }
}

/// What the workers' reports say about each domain of the job: the rays queued for it
/// everywhere, where it is resident, and its largest resident size. A report naming a
/// domain out of range is left out (reports come from the network).
fn domain_views(input: &RoundInput<'_>) -> Vec<DomainView> {
    let mut view = vec![DomainView::default(); input.domains as usize];
    for w in input.workers {
        for q in w.queues {
            // Reports come from the network: a domain out of range is not ours to judge.
            let Some(v) = view.get_mut(q.domain as usize) else {
                continue;
            };
            v.want = v.want.saturating_add(q.rays_queued);
            v.bytes = v.bytes.max(q.resident_bytes);
            if q.resident {
                v.resident_at.insert(w.id.to_string());
            }
        }
    }
    view
}

/// Domains `ds` most wanted first: descending want, then ascending index, a total
/// order, so no tie is left to the sort's stability or to map iteration.
fn by_want(view: &[DomainView], mut ds: Vec<usize>) -> Vec<usize> {
    ds.sort_by(|&a, &b| view[b].want.cmp(&view[a].want).then(a.cmp(&b)));
    ds
}

impl<'a> Round<'_, 'a> {
    /// The round's first step, ownership bounded by what a worker can hold (Navratil et
    /// al.): a worker that owns alone more domains than it can hold keeps those loaded (or
    /// loading) there and the most wanted of the rest, and lets the others go; their rays
    /// wait where they are until a worker with nothing to do is given them, so one load
    /// serves them all instead of the owner swapping its domains in and out. Returns what
    /// each bounded worker keeps of the domains it owns alone, with its capacity, for the
    /// bound after the moves ([`release_for_gifts`]).
    fn bound_owners(&mut self) -> HashMap<&'a str, (usize, Vec<usize>)> {
        let (input, view) = (self.input, &self.view);
        let (owners, changes) = (&mut self.owners, &mut self.changes);
        let size = view.iter().map(|v| v.bytes).max().unwrap_or(0);
        // Each worker's domains it owns alone, ascending, from one pass over the
        // domains (not one pass per worker: that is N x D at 10,000 workers). A worker's
        // releases below touch only its own domains, so the lists stay true as it goes.
        let mut sole: HashMap<String, Vec<usize>> = HashMap::new();
        for (d, o) in owners.iter().enumerate() {
            if let [only] = o.as_slice() {
                sole.entry(only.clone()).or_default().push(d);
            }
        }
        let mut kept: HashMap<&'a str, (usize, Vec<usize>)> = HashMap::new();
        for w in input.workers {
            let Some(cap) = capacity(w, size) else {
                continue;
            };
            let here = |d: usize| view[d].resident_at.contains(w.id) || input.loading_at(d, w.id);
            let mut mine: Vec<usize> = sole.remove(w.id).unwrap_or_default();
            if mine.len() <= cap {
                kept.insert(w.id, (cap, mine));
                continue;
            }
            mine.sort_by(|&a, &b| {
                here(b)
                    .cmp(&here(a))
                    .then(view[b].want.cmp(&view[a].want))
                    .then(a.cmp(&b))
            });
            for &d in &mine[cap..] {
                if here(d) {
                    continue;
                }
                owners[d].clear();
                changes.push(Change::Release {
                    domain: d as u32,
                    from: w.id.to_string(),
                });
            }
            mine.retain(|&d| !owners[d].is_empty());
            kept.insert(w.id, (cap, mine));
        }
        kept
    }

    /// The round's moves: the most-wanted unloaded domains (wanted, and neither resident
    /// nor loading at any of their owners) each go to one idle worker
    /// ([`IdleWorkers::pick`]) as its only owner, leaving their previous owners.
    fn move_unloaded(&mut self, idle: &mut IdleWorkers<'_>) {
        let (input, view) = (self.input, &self.view);
        let (owners, changes) = (&mut self.owners, &mut self.changes);
        let unloaded: Vec<usize> = (0..view.len())
            .filter(|&d| view[d].wanted())
            .filter(|&d| {
                !owners[d]
                    .iter()
                    .any(|o| view[d].resident_at.contains(o) || input.loading_at(d, o))
            })
            .collect();
        for d in by_want(view, unloaded) {
            if idle.left == 0 {
                break;
            }
            let Some(w) = idle.give(view, d, &[]) else {
                continue;
            };
            let from = std::mem::replace(&mut owners[d], vec![w.id.to_string()]);
            changes.push(Change::Move {
                domain: d as u32,
                from,
                to: w.id.to_string(),
            });
        }
    }

    /// With `replicate`, after the moves: idle workers left over become extra owners of
    /// the most-wanted domains resident somewhere, one new replica per domain per round,
    /// none for a domain moved or loading this round, never more owners than workers.
    fn replicate_hot(&mut self, idle: &mut IdleWorkers<'_>) {
        let (input, view) = (self.input, &self.view);
        let (owners, changes) = (&mut self.owners, &mut self.changes);
        let moved: BTreeSet<u32> = changes
            .iter()
            .filter_map(|c| c.given().map(|g| g.0))
            .collect();
        let hot: Vec<usize> = (0..view.len())
            .filter(|&d| view[d].wanted() && !view[d].resident_at.is_empty())
            .filter(|&d| !moved.contains(&(d as u32)))
            .filter(|&d| !owners[d].iter().any(|o| input.loading_at(d, o)))
            .filter(|&d| owners[d].len() < input.workers.len())
            .collect();
        for d in by_want(view, hot) {
            if idle.left == 0 {
                break;
            }
            let Some(w) = idle.give(view, d, &owners[d]) else {
                continue;
            };
            owners[d].push(w.id.to_string());
            changes.push(Change::Replicate {
                domain: d as u32,
                to: w.id.to_string(),
            });
        }
    }
}

/// The end of `dynamic-from-image-plane`'s image-plane phase: the first ownership, made
/// from the workers' queue reports (the caller waits until every worker has sent one).
/// Domain by domain, in order: a domain resident at some workers goes to the one with
/// the most rays queued for it there (ties to the first in job order), so no load is
/// thrown away and a worker is given only what its memory already holds; a domain
/// resident nowhere goes to the worker owning fewest domains so far whose budget it
/// fits (0 = unlimited; ties to the first in job order; any worker when none fits, as
/// the domain schedule would). Every domain gets one owner. `None` when the routes are
/// not local (the phase is over) or the job has no workers.
pub fn leave_image_plane(input: &RoundInput<'_>) -> Option<Decision> {
    if !input.routes.is_local() || input.workers.is_empty() {
        return None;
    }
    let n = input.domains as usize;
    // Per domain: (rays queued, worker index) of each worker holding it.
    let mut holders: Vec<Vec<(u64, usize)>> = vec![Vec::new(); n];
    let mut bytes = vec![0u64; n];
    for (i, w) in input.workers.iter().enumerate() {
        for q in w.queues {
            let d = q.domain as usize;
            if d >= n {
                continue;
            }
            bytes[d] = bytes[d].max(q.resident_bytes);
            if q.resident {
                holders[d].push((q.rays_queued, i));
            }
        }
    }
    let mut owned = vec![0usize; input.workers.len()];
    let mut owners = Vec::with_capacity(n);
    let mut changes = Vec::with_capacity(n);
    for d in 0..n {
        let held = holders[d]
            .iter()
            .max_by(|a, b| a.0.cmp(&b.0).then(b.1.cmp(&a.1)))
            .map(|&(_, i)| i);
        let fits = |i: usize| {
            let b = input.workers[i].budget;
            b == 0 || bytes[d] <= b
        };
        let fewest = |ok: &dyn Fn(usize) -> bool| {
            (0..input.workers.len())
                .filter(|&i| ok(i))
                .min_by_key(|&i| (owned[i], i))
        };
        let Some(i) = held.or_else(|| fewest(&fits)).or_else(|| fewest(&|_| true)) else {
            continue;
        };
        owned[i] += 1;
        let to = input.workers[i].id.to_string();
        owners.push(vec![to.clone()]);
        changes.push(Change::Move {
            domain: d as u32,
            from: Vec::new(),
            to,
        });
    }
    Some(Decision {
        routes: Ownership::from_owners(owners),
        changes,
    })
}

/// The bound on what a worker holds, after a round's moves and replicas: a worker given
/// domains beyond its capacity lets go of as many of those it owns alone (`kept`:
/// capacity and domains per bounded worker), unwanted ones only (a worker is given
/// domains only when it is idle, so all of its own are), those not loaded there first,
/// then resident ones, never one being loaded. Its store then evicts them when the table
/// arrives. Without this, the store makes room for the new domain by evicting its least
/// recently used one, which it still owns: rays that come for it before the next round
/// releases it load it back, evicting another.
fn release_for_gifts(
    owners: &mut [Vec<String>],
    changes: &mut Vec<Change>,
    mut kept: HashMap<&str, (usize, Vec<usize>)>,
    view: &[DomainView],
    input: &RoundInput<'_>,
) {
    let mut gifts: BTreeMap<String, usize> = BTreeMap::new();
    for c in changes.iter() {
        if let Some((_, to)) = c.given() {
            *gifts.entry(to.to_string()).or_default() += 1;
        }
    }
    for (w, given) in gifts {
        let Some((cap, mut mine)) = kept.remove(w.as_str()) else {
            continue;
        };
        // Still its own alone: a move may have taken one away this round.
        mine.retain(|&d| owners[d].len() == 1 && owners[d][0] == w);
        let excess = (mine.len() + given).saturating_sub(cap);
        if excess == 0 {
            continue;
        }
        let resident = |d: usize| view[d].resident_at.contains(&w);
        let loading = |d: usize| input.loading.contains(&(d as u32, w.clone()));
        mine.retain(|&d| view[d].want == 0 && !loading(d));
        mine.sort_by_key(|&d| (resident(d), d));
        for &d in mine.iter().take(excess) {
            owners[d].clear();
            changes.push(Change::Release {
                domain: d as u32,
                from: w.clone(),
            });
        }
    }
}

/// A round's idle workers (those owning no wanted domain), in job order. A worker given
/// a domain leaves its slot empty, so the order of the others (which decides ties)
/// never changes.
struct IdleWorkers<'r> {
    slots: Vec<Option<&'r WorkerView<'r>>>,
    /// Each idle worker's slot, so a domain's holders are looked up, not searched for.
    slot_of: HashMap<&'r str, usize>,
    /// Every slot before this one is empty.
    first_live: usize,
    /// Slots still holding a worker.
    left: usize,
}

impl<'r> IdleWorkers<'r> {
    /// The workers owning no wanted domain in `owners` (the owners of a wanted domain
    /// are busy; found in one pass over the domains, not one per worker).
    fn new(input: &RoundInput<'r>, view: &[DomainView], owners: &[Vec<String>]) -> Self {
        let busy: BTreeSet<&str> = owners
            .iter()
            .enumerate()
            .filter(|&(d, _)| view[d].wanted())
            .flat_map(|(_, o)| o.iter().map(String::as_str))
            .collect();
        let slots: Vec<Option<&'r WorkerView<'r>>> = input
            .workers
            .iter()
            .filter(|w| !busy.contains(w.id))
            .map(Some)
            .collect();
        let slot_of = slots
            .iter()
            .enumerate()
            .filter_map(|(i, w)| w.map(|w| (w.id, i)))
            .collect();
        IdleWorkers {
            left: slots.len(),
            slots,
            slot_of,
            first_live: 0,
        }
    }

    /// The slot of the idle worker for domain `d`: the first (in job order) whose
    /// budget the domain's resident size fits (0 = unlimited; the budget, not the free
    /// memory, since a worker evicts domains nobody wants), not in `skip`, that still
    /// holds it, else the first that fits. The holders are few: they are looked up, so
    /// a round costs O(moves x holders) plus the scan for a fit.
    fn pick(&self, view: &[DomainView], d: usize, skip: &[String]) -> Option<usize> {
        let fits = |w: &WorkerView<'_>| w.budget == 0 || view[d].bytes <= w.budget;
        let ok = |w: &WorkerView<'_>| fits(w) && !skip.iter().any(|s| s == w.id);
        view[d]
            .resident_at
            .iter()
            .filter_map(|id| self.slot_of.get(id.as_str()).copied())
            .filter(|&i| self.slots[i].is_some_and(ok))
            .min()
            .or_else(|| {
                (self.first_live..self.slots.len()).find(|&i| self.slots[i].is_some_and(ok))
            })
    }

    /// The idle worker for domain `d` ([`IdleWorkers::pick`]), its slot emptied.
    fn give(
        &mut self,
        view: &[DomainView],
        d: usize,
        skip: &[String],
    ) -> Option<&'r WorkerView<'r>> {
        let i = self.pick(view, d, skip)?;
        self.take(i)
    }

    /// Empty slot `i` and return its worker, keeping `first_live` at the first slot
    /// still holding one and `left` at how many do.
    fn take(&mut self, i: usize) -> Option<&'r WorkerView<'r>> {
        let w = self.slots.get_mut(i)?.take();
        if w.is_some() {
            self.left -= 1;
        }
        while self.first_live < self.slots.len() && self.slots[self.first_live].is_none() {
            self.first_live += 1;
        }
        w
    }
}

/// The latest queue report of each worker, as [`WorkerView`]s in `order`, with budgets.
pub fn views<'a>(
    order: &'a [String],
    budgets: &'a BTreeMap<String, u64>,
    reports: &'a BTreeMap<String, Vec<DomainQueue>>,
) -> Vec<WorkerView<'a>> {
    order
        .iter()
        .map(|id| WorkerView {
            id,
            budget: budgets.get(id).copied().unwrap_or(0),
            queues: reports.get(id).map_or(&[], Vec::as_slice),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parse_names_and_replication() {
        assert_eq!(
            Schedule::parse("", false),
            Ok(Schedule::Dynamic { replicate: false })
        );
        assert_eq!(
            Schedule::parse("dynamic", true),
            Ok(Schedule::Dynamic { replicate: true })
        );
        assert_eq!(Schedule::parse("domain", false), Ok(Schedule::Domain));
        assert_eq!(
            Schedule::parse("image-plane", false),
            Ok(Schedule::ImagePlane)
        );
        assert!(matches!(
            Schedule::parse("domain", true),
            Err(ScheduleError::ReplicateNeedsDynamic("domain"))
        ));
        assert!(matches!(
            Schedule::parse("Dynamic", false),
            Err(ScheduleError::Unknown(_))
        ));
        for name in SCHEDULE_NAMES {
            assert_eq!(ScheduleRequest::parse(name, false).unwrap().name(), name);
        }
        // Empty is auto for a job; a resolved schedule is never auto.
        assert_eq!(
            ScheduleRequest::parse("", true),
            Ok(ScheduleRequest::Auto { replicate: true })
        );
        assert_eq!(
            ScheduleRequest::parse("replicated", false),
            Ok(ScheduleRequest::Forced(Schedule::Replicated))
        );
        assert!(matches!(
            ScheduleRequest::parse("replicated", true),
            Err(ScheduleError::ReplicateNeedsDynamic("replicated"))
        ));
        assert!(matches!(
            Schedule::parse("auto", false),
            Err(ScheduleError::Unknown(_))
        ));
    }

    /// The capacity is what the worker's store holds: `cap - 1` domains resident and
    /// the load of one more (its reserve, the domain included) within the three quarters
    /// of the budget left for domains, and not one more.
    #[test]
    fn capacity_is_what_the_store_holds_with_one_load() {
        let view = |budget| WorkerView {
            id: "w",
            budget,
            queues: &[],
        };
        for (budget, size) in [
            (800, 100),
            (700, 100),
            (80_000_000, 9_100_000),
            (80_000_000, 7_930_000),
            (92_000_000, 9_100_000),
            (1 << 40, 12_345_678),
        ] {
            let share = budget / 4 * 3;
            let cap = capacity(&view(budget), size).unwrap() as u64;
            assert!(
                (cap - 1) * size + load_reserve(size) <= share,
                "{cap} x {size} do not fit {share}"
            );
            assert!(
                cap * size + load_reserve(size) > share,
                "{} x {size} would fit {share}",
                cap + 1
            );
        }
        // benches/passes.sh: 9.1 MB domains in 60 MB hold 6 (the rule before counted
        // two domains' room for a build beside all of them: 4).
        assert_eq!(capacity(&view(80_000_000), 9_100_000), Some(6));
        // Too small a budget for even one load still owns one domain; no size, no bound.
        assert_eq!(capacity(&view(100), 1_000), Some(1));
        assert_eq!(capacity(&view(100), 0), None);
        assert_eq!(capacity(&view(0), 1_000), None);
    }

    /// Leaving image-plane: resident domains stay where most of their rays wait, the
    /// rest go to the workers owning fewest (job order on ties), and every domain gets
    /// exactly one owner; a routed table is left alone.
    #[test]
    fn leaving_image_plane_keeps_resident_domains_and_balances_the_rest() {
        let q = |domain, rays_queued, resident| DomainQueue {
            domain,
            rays_queued,
            resident,
            resident_bytes: 100,
        };
        let a = [q(0, 5, true), q(1, 9, true), q(3, 2, false)];
        let b = [q(1, 20, true), q(2, 0, true)];
        let c: [DomainQueue; 0] = [];
        let workers = [
            WorkerView {
                id: "a",
                budget: 0,
                queues: &a,
            },
            WorkerView {
                id: "b",
                budget: 0,
                queues: &b,
            },
            WorkerView {
                id: "c",
                budget: 0,
                queues: &c,
            },
        ];
        let local = Ownership::local();
        let loading = BTreeSet::new();
        let input = RoundInput {
            domains: 6,
            routes: &local,
            workers: &workers,
            loading: &loading,
            replicate: false,
        };
        let d = leave_image_plane(&input).expect("a first ownership");
        let owner = |dom: u32| d.routes.owners(dom).to_vec();
        // 0 held by a; 1 held by both, more rays wait at b; 2 held by b.
        assert_eq!(owner(0), ["a"]);
        assert_eq!(owner(1), ["b"]);
        assert_eq!(owner(2), ["b"]);
        // 3, 4, 5 resident nowhere: c owns none, then a (1) before b (2), then c again.
        assert_eq!(owner(3), ["c"]);
        assert_eq!(owner(4), ["a"]);
        assert_eq!(owner(5), ["c"]);
        assert_eq!(d.changes.len(), 6);
        assert!(!d.routes.is_local());
        // Once routed, nothing more to leave; a routed table is the rounds' to change.
        let input = RoundInput {
            routes: &d.routes,
            ..input
        };
        assert_eq!(leave_image_plane(&input), None);
        // The schedule: image-plane's tiles and first table, dynamic's rounds.
        let s = Schedule::parse("dynamic-from-image-plane", true).expect("a schedule");
        assert_eq!(s, Schedule::DynamicFromImagePlane { replicate: true });
        assert!(s.is_dynamic() && s.replicates());
        assert!(s.initial_routes(6, &["a".into()]).is_local());
        assert_eq!(s.deal_tiles(10, 3), Schedule::ImagePlane.deal_tiles(10, 3));
        assert!(
            s.routes_after_loss(&local, 6, &["a".into()]).is_local(),
            "still in its image-plane phase"
        );
        assert_eq!(
            s.routes_after_loss(&d.routes, 6, &["a".into(), "c".into()])
                .owners(1),
            ["a"]
        );
    }

    #[test]
    fn image_plane_blocks_cover_every_tile_once() {
        for (t, n) in [(10, 3), (3, 5), (0, 2), (262_144, 7)] {
            let dealt = Schedule::ImagePlane.deal_tiles(t, n);
            let flat: Vec<usize> = dealt.concat();
            assert_eq!(flat, (0..t).collect::<Vec<_>>(), "{t} tiles on {n}");
            for (i, mine) in dealt.iter().enumerate() {
                assert_eq!(mine.first().copied().unwrap_or(i * t / n), i * t / n);
            }
        }
        assert!(Schedule::Domain.deal_tiles(5, 0).is_empty());
    }
}
