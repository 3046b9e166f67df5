//! The domain store: which domains of which job attempts are resident on this worker,
//! loaded on demand and evicted least-recently-used within a memory budget.
//!
//! A domain is the unit of residency (docs/architecture.md "Words"): its triangles, the scene's
//! emitters (next-event estimation samples them from anywhere) and one BVH, in scene
//! order with scene-wide ids, so that tracing and shading in it give the bits the whole
//! scene gives (see `dray_scene::partition::resident`). Each is loaded alone — read from
//! the package, checked, BVH built — counted and timed, and dropped alone.
//!
//! **Budget.** The store keeps the bytes of resident domains, and of loads under way, at
//! or below its budget: a load first evicts the least recently used domains (of any
//! job) until the newcomer fits together with what its build holds for a moment
//! ([`load_reserve`]: the domain and its build's peak, measured by `tests/load_peak.rs`).
//! A domain that could never fit fails its job with
//! a message saying so, instead of the kernel killing the worker. Tracing steps hold the
//! domains they touch through an `Arc` for the length of one batch, so an evicted
//! domain's memory is freed when the steps using it end: the stated margin over the
//! budget is the domains pinned by steps already running when the eviction happened (at
//! most a few per tracing thread). Freed memory is handed back to the operating system
//! after evictions (glibc keeps freed heap pages otherwise, and the process would look
//! as large as its largest moment).
//!
//! Loads run on the tracing thread that needs the domain (other threads go on with
//! resident work); a domain being loaded by one thread is not loaded twice.
//!
//! **Warm domains.** A slot is keyed by what the domain *is* — the package's content
//! (its manifest checksum, which covers every domain file) and the settings that change
//! a loaded domain — not by the job that loaded it ([`DomainStore::open`]). Jobs of the
//! same package share resident domains, and when a job is released its domains stay
//! resident, idle, until a job of another package opens or the budget needs their room:
//! a sweep, an animation or a second look at the same scene does not load and build
//! its BVHs again. At most one idle package is kept, so a worker between jobs holds no
//! more than the last job's domains.
//!
//! **Per domain.** A job may say what each of its domains is made of instead
//! ([`Contents::per_domain`]: the domain file's checksum and what every domain shares):
//! the frames of an animation are different packages, but a domain that no moving mesh
//! touches is the same domain in each, and a job finds it resident whichever frame
//! loaded it; only the domains a moving mesh touches are loaded and built again
//! (issue 42).

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use dray_core::light_sampler::LightSampler;
use dray_scene::partition::ResidentScene;
use dray_scene::partition::resident::load_reserve;

/// A job attempt, as the store and the queues know it.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct JobKey {
    /// The job id.
    pub id: Arc<str>,
    /// The attempt (`JobSetup.attempt`).
    pub attempt: u32,
}

/// One domain ready to trace: its triangles and the emitters, with a BVH over the
/// domain's triangles, and the light table over that mesh.
pub struct LoadedDomain {
    /// The domain index in the package.
    pub domain: u32,
    /// Exactly one entry in `resident.domains`: this domain.
    pub resident: ResidentScene,
    /// The light table over `resident.scene` (the same table as the whole scene's: every
    /// emitter is in it, in scene order).
    pub lights: Arc<LightSampler>,
    /// What it counts against the budget.
    pub bytes: u64,
}

/// Where a job's domains come from: a package directory or an in-memory package.
pub trait DomainSource: Send + Sync {
    /// Bytes domain `d` will take once loaded, estimated before loading (from the
    /// package manifest), so that room is made first.
    fn estimate_bytes(&self, d: u32) -> u64;
    /// Load domain `d` (blocking: reads files, builds the BVH).
    fn load(&self, d: u32) -> Result<LoadedDomain, String>;
}

/// Why a domain could not be loaded now.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LoadError {
    /// The domain alone is larger than the budget: the job cannot run on this worker.
    #[error(
        "domain {domain} needs about {needed} bytes resident, more than this worker's memory budget leaves for domains ({budget} bytes{note})"
    )]
    TooLarge {
        domain: u32,
        needed: u64,
        budget: u64,
        /// How the budget was split, when it was (see `WorkerConfig::limits`).
        note: String,
    },
    /// Another thread is loading it, or every byte of the budget is held by domains
    /// being loaded: try other work and come back.
    #[error("domain {domain} cannot be loaded right now")]
    Busy { domain: u32 },
    /// Reading or building failed.
    #[error("cannot load domain {domain}: {message}")]
    Failed { domain: u32, message: String },
}

/// What the store did for one job attempt since it was last asked ([`DomainStore::take_counters`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StoreCounters {
    pub loads: u64,
    /// Domains the job found resident, loaded by another job of the same content.
    pub warm: u64,
    pub load_seconds: f64,
    pub evictions: u64,
}

enum Slot {
    /// A thread is loading it; `bytes` are reserved (what the load holds at its peak),
    /// `estimate` is what the domain will hold once loaded. `dropped`: the worker let the
    /// domain go while it loaded ([`DomainStore::evict`]), so the load hands the domain
    /// to its caller but does not keep it.
    Loading {
        bytes: u64,
        estimate: u64,
        dropped: bool,
    },
    Ready {
        domain: Arc<LoadedDomain>,
        last_used: u64,
    },
}

impl Slot {
    fn bytes(&self) -> u64 {
        match self {
            Slot::Loading { bytes, .. } => *bytes,
            Slot::Ready { domain, .. } => domain.bytes,
        }
    }

    /// The domain's own size: resident, or once loaded. The scheduler sizes domains by
    /// it; a load's reserve would make a domain look larger than it is while it loads.
    fn domain_bytes(&self) -> u64 {
        match self {
            Slot::Loading { estimate, .. } => *estimate,
            Slot::Ready { domain, .. } => domain.bytes,
        }
    }
}

/// What a loaded domain is made of (see "Warm domains" above): equal keys load
/// equal domains.
pub type Content = Arc<str>;

/// What each domain of a job is made of: one content for every domain of its package,
/// or one per domain (see "Per domain" above).
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct Contents {
    /// Of every domain without one of its own.
    package: Content,
    /// Domain `d`'s own, when given.
    domains: Arc<[Content]>,
}

impl Contents {
    /// Every domain of the job is of `package`'s content.
    pub fn package(package: Content) -> Contents {
        Contents {
            package,
            domains: Arc::from([]),
        }
    }

    /// Domain `d` is of `domains[d]`'s content (others, of `package`'s).
    pub fn per_domain(package: Content, domains: Vec<Content>) -> Contents {
        Contents {
            package,
            domains: domains.into(),
        }
    }

    /// The slot key of domain `d`.
    fn of(&self, d: u32) -> (Content, u32) {
        let c = self.domains.get(d as usize).unwrap_or(&self.package);
        (c.clone(), d)
    }

    /// Whether the slot `key` is one of these domains.
    fn holds(&self, key: &(Content, u32)) -> bool {
        let c = self.domains.get(key.1 as usize).unwrap_or(&self.package);
        *c == key.0
    }
}

impl From<Content> for Contents {
    fn from(package: Content) -> Contents {
        Contents::package(package)
    }
}

#[derive(Default)]
struct Inner {
    slots: HashMap<(Content, u32), Slot>,
    /// The contents of every open job attempt.
    jobs: HashMap<JobKey, Contents>,
    /// The contents whose domains stay resident with no open job (see "Warm domains").
    idle: Option<Contents>,
    /// Domains each open job has used or loaded, so that a warm one counts once.
    used: HashMap<JobKey, std::collections::HashSet<u32>>,
    /// Bytes of all slots, loading ones included.
    bytes: u64,
    clock: u64,
    counters: HashMap<JobKey, StoreCounters>,
}

/// The resident domains of every job attempt on this worker.
pub struct DomainStore {
    /// Bytes resident domains may take together; 0 means unlimited.
    budget: u64,
    /// Said with a domain too large for the budget: where the budget came from.
    note: String,
    /// Added to every load, to emulate slow shared storage in experiments.
    load_delay: Duration,
    inner: Mutex<Inner>,
}

impl DomainStore {
    /// A store holding at most `budget` bytes of domains (0: unlimited), each load
    /// taking at least `load_delay` longer.
    pub fn new(budget: u64, load_delay: Duration) -> DomainStore {
        DomainStore {
            budget,
            note: String::new(),
            load_delay,
            inner: Mutex::new(Inner::default()),
        }
    }

    /// Say `note` (e.g. how a larger budget was split) with every "too large" error.
    pub fn with_note(mut self, note: String) -> DomainStore {
        self.note = note;
        self
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        // Every update below leaves the maps consistent before it can panic.
        dray_sync::lock(&self.inner)
    }

    /// Say what `job`'s domains are made of, before its first load: resident domains of
    /// the same content (another job's, or idle ones of a finished job) are then used
    /// as they are. Idle domains of other content are dropped now. A job never opened
    /// has domains of its own.
    pub fn open(&self, job: &JobKey, content: Contents) {
        let mut g = self.lock();
        g.jobs.insert(job.clone(), content);
        // The idle domains this job (or another open one) holds are its now; the rest go.
        if let Some(old) = g.idle.take() {
            drop_content(&mut g, &old);
        }
    }

    /// The slot key of domain `d` of `job`.
    fn key(g: &Inner, job: &JobKey, d: u32) -> (Content, u32) {
        match g.jobs.get(job) {
            Some(c) => c.of(d),
            None => (private(job), d),
        }
    }

    /// The budget in bytes (0: unlimited).
    pub fn budget(&self) -> u64 {
        self.budget
    }

    /// Domain `d` of `job` if resident (marking it used).
    pub fn get(&self, job: &JobKey, d: u32) -> Option<Arc<LoadedDomain>> {
        let mut g = self.lock();
        g.clock += 1;
        let now = g.clock;
        let key = Self::key(&g, job, d);
        let found = match g.slots.get_mut(&key) {
            Some(Slot::Ready { domain, last_used }) => {
                *last_used = now;
                Some(domain.clone())
            }
            _ => None,
        };
        if found.is_some() {
            note_use(&mut g, job, d, false);
        }
        found
    }

    /// Whether domain `d` of `job` is resident.
    pub fn is_resident(&self, job: &JobKey, d: u32) -> bool {
        let g = self.lock();
        matches!(
            g.slots.get(&Self::key(&g, job, d)),
            Some(Slot::Ready { .. })
        )
    }

    /// Load domain `d` of `job` from `source` unless it is resident, evicting least
    /// recently used domains to make room. Blocking.
    pub fn load(
        &self,
        job: &JobKey,
        d: u32,
        source: &dyn DomainSource,
    ) -> Result<Arc<LoadedDomain>, LoadError> {
        self.load_telling(job, d, source).map(|(domain, _)| domain)
    }

    /// [`Self::load`], and whether this call loaded the domain (false: it was resident),
    /// for a job's traffic trace.
    pub fn load_telling(
        &self,
        job: &JobKey,
        d: u32,
        source: &dyn DomainSource,
    ) -> Result<(Arc<LoadedDomain>, bool), LoadError> {
        let estimate = source.estimate_bytes(d);
        // What the load holds while it runs (see load_reserve), within the budget: a
        // domain that fits only without its build transients still loads, alone.
        let reserve = if self.budget > 0 {
            load_reserve(estimate).min(self.budget)
        } else {
            estimate
        };
        if self.budget > 0 && estimate > self.budget {
            return Err(LoadError::TooLarge {
                domain: d,
                needed: estimate,
                budget: self.budget,
                note: self.note.clone(),
            });
        }
        let key = {
            let mut g = self.lock();
            if !g.jobs.contains_key(job) {
                g.jobs.insert(job.clone(), private(job).into());
            }
            let key = Self::key(&g, job, d);
            match g.slots.get(&key) {
                Some(Slot::Ready { domain, .. }) => {
                    let domain = domain.clone();
                    note_use(&mut g, job, d, false);
                    return Ok((domain, false));
                }
                Some(Slot::Loading { .. }) => return Err(LoadError::Busy { domain: d }),
                None => {}
            }
            if !self.make_room(&mut g, reserve) {
                return Err(LoadError::Busy { domain: d });
            }
            g.slots.insert(
                key.clone(),
                Slot::Loading {
                    bytes: reserve,
                    estimate,
                    dropped: false,
                },
            );
            g.bytes += reserve;
            key
        };
        let start = Instant::now();
        let _span = tracing::debug_span!("load", job = %job.id, domain = d).entered();
        if !self.load_delay.is_zero() {
            std::thread::sleep(self.load_delay);
        }
        // A panic in the load (the BVH build, a reader) fails this load like an error:
        // the slot is freed below, so no thread waits for a load that ended.
        let loaded =
            crate::contain::contained_while("loading a domain", || source.load(d)).and_then(|r| r);
        let seconds = start.elapsed().as_secs_f64();
        let mut g = self.lock();
        g.bytes -= reserve;
        let dropped = matches!(
            g.slots.remove(&key),
            Some(Slot::Loading { dropped: true, .. })
        );
        let loaded = loaded.map_err(|message| LoadError::Failed { domain: d, message })?;
        let domain = Arc::new(loaded);
        if dropped {
            // Let go while it loaded: the caller traces what it loaded it for, but the
            // domain does not stay. Kept, it would be resident at a worker that does not
            // own it, its rays held there, and the tracing threads, which load nothing
            // while a resident domain has rays (`work::next_work`), would never load the
            // domains this worker does own: with every worker in that state, the
            // scheduler has no idle worker to give the held domains to, and the job
            // stops.
            let c = g.counters.entry(job.clone()).or_default();
            c.loads += 1;
            c.load_seconds += seconds;
            c.evictions += 1;
            drop(g);
            release_freed_memory();
            tracing::debug!(job = %job.id, domain = d, seconds, "domain loaded after it was let go; not kept");
            return Ok((domain, true));
        }
        // The reservation made the room; the measured size is what counts from now on.
        g.bytes += domain.bytes;
        g.clock += 1;
        let now = g.clock;
        g.slots.insert(
            key,
            Slot::Ready {
                domain: domain.clone(),
                last_used: now,
            },
        );
        note_use(&mut g, job, d, true);
        let c = g.counters.entry(job.clone()).or_default();
        c.loads += 1;
        c.load_seconds += seconds;
        if self.budget > 0 && g.bytes > self.budget {
            // The estimate was short: evict others until the measured size fits.
            let over = g.bytes - self.budget;
            let keep = Self::key(&g, job, d);
            self.evict_lru(&mut g, over, Some(&keep));
        }
        drop(g);
        // The build's transients are freed now: give them back.
        release_freed_memory();
        tracing::debug!(job = %job.id, domain = d, bytes = domain.bytes, seconds, "domain loaded");
        Ok((domain, true))
    }

    /// Evict ready domains, least recently used first, until `needed` more bytes fit.
    /// False when they cannot (the rest is being loaded).
    fn make_room(&self, g: &mut Inner, needed: u64) -> bool {
        if self.budget == 0 || g.bytes + needed <= self.budget {
            return true;
        }
        let excess = g.bytes + needed - self.budget;
        self.evict_lru(g, excess, None);
        g.bytes + needed <= self.budget
    }

    /// Evict least recently used ready domains (never `keep`) until `bytes` are freed or
    /// none is left.
    fn evict_lru(&self, g: &mut Inner, bytes: u64, keep: Option<&(Content, u32)>) {
        let mut ready: Vec<(u64, (Content, u32))> = g
            .slots
            .iter()
            .filter_map(|(k, s)| match s {
                Slot::Ready { last_used, .. } => Some((*last_used, k.clone())),
                Slot::Loading { .. } => None,
            })
            .filter(|(_, k)| keep.is_none_or(|keep| k != keep))
            .collect();
        ready.sort_unstable_by_key(|(t, _)| *t);
        let mut freed = 0u64;
        for (_, k) in ready {
            if freed >= bytes {
                break;
            }
            if let Some(slot) = g.slots.remove(&k) {
                let b = slot.bytes();
                freed += b;
                g.bytes -= b;
                // Counted for every open job of that content (idle ones count nowhere).
                let jobs: Vec<JobKey> = g
                    .jobs
                    .iter()
                    .filter(|(_, c)| c.holds(&k))
                    .map(|(j, _)| j.clone())
                    .collect();
                for j in jobs {
                    g.counters.entry(j).or_default().evictions += 1;
                }
                tracing::debug!(content = %k.0, domain = k.1, bytes = b, "domain evicted");
            }
        }
    }

    /// Drop domain `d` of `job` if resident (its owner moved it away); counted as an
    /// eviction. A load of it under way finishes, but does not keep it (see
    /// [`Slot::Loading`]): a routing table can let a domain go while it loads, when the
    /// scheduler decided on a queue report sent just before the load began.
    pub fn evict(&self, job: &JobKey, d: u32) {
        let mut g = self.lock();
        let key = Self::key(&g, job, d);
        match g.slots.get_mut(&key) {
            Some(Slot::Ready { domain, .. }) => {
                let b = domain.bytes;
                g.slots.remove(&key);
                g.bytes -= b;
                g.counters.entry(job.clone()).or_default().evictions += 1;
            }
            Some(Slot::Loading { dropped, .. }) => *dropped = true,
            None => {}
        }
    }

    /// Close every attempt of `job_id` up to `attempt` (released). Their domains stay
    /// resident while another open job shares them; otherwise the last released
    /// content stays as the idle one (see "Warm domains") and the rest is dropped,
    /// without counting evictions.
    pub fn release(&self, job_id: &str, attempt: u32) {
        let mut g = self.lock();
        let closed: Vec<JobKey> = g
            .jobs
            .keys()
            .filter(|j| &*j.id == job_id && j.attempt <= attempt)
            .cloned()
            .collect();
        for j in &closed {
            g.used.remove(j);
        }
        let mut contents: Vec<Contents> = closed.iter().filter_map(|j| g.jobs.remove(j)).collect();
        contents.sort_unstable();
        contents.dedup();
        for c in contents {
            if g.jobs.values().any(|o| *o == c) || g.idle.as_ref() == Some(&c) {
                continue;
            }
            if closed.iter().any(|j| Contents::from(private(j)) == c) {
                // A job never opened had domains of its own: no later job can use them.
                drop_content(&mut g, &c);
                continue;
            }
            if let Some(old) = g.idle.replace(c) {
                drop_content(&mut g, &old);
            }
        }
        g.counters
            .retain(|j, _| !(&*j.id == job_id && j.attempt <= attempt));
    }

    /// Resident domains of `job` with their bytes, in domain order, and those being
    /// loaded now (with their estimated bytes, not the load's reserve): the scheduler
    /// must not move a domain whose load is under way, or the load is thrown away.
    pub fn resident(&self, job: &JobKey) -> Vec<(u32, u64)> {
        let g = self.lock();
        let content = g
            .jobs
            .get(job)
            .cloned()
            .unwrap_or_else(|| private(job).into());
        let mut v: Vec<(u32, u64)> = g
            .slots
            .iter()
            .filter(|(k, _)| content.holds(k))
            .map(|((_, d), s)| (*d, s.domain_bytes()))
            .collect();
        v.sort_unstable();
        v
    }

    /// Bytes held by resident (and loading) domains.
    pub fn used_bytes(&self) -> u64 {
        self.lock().bytes
    }

    /// What the store did for `job` since the previous call.
    pub fn take_counters(&self, job: &JobKey) -> StoreCounters {
        self.lock()
            .counters
            .get_mut(job)
            .map(std::mem::take)
            .unwrap_or_default()
    }
}

/// Mark domain `d` used by `job`; the first use of a domain it did not load itself
/// (`loaded` false) counts as warm.
fn note_use(g: &mut Inner, job: &JobKey, d: u32, loaded: bool) {
    if !g.jobs.contains_key(job) {
        return;
    }
    let first = g.used.entry(job.clone()).or_default().insert(d);
    if first && !loaded {
        g.counters.entry(job.clone()).or_default().warm += 1;
    }
}

/// The content of the domains of a job never [opened](DomainStore::open): its own.
fn private(job: &JobKey) -> Content {
    format!("job {} attempt {}", job.id, job.attempt).into()
}

/// Drop the ready domains of `content` that neither an open job nor the idle contents
/// hold (loads under way finish and are then kept only while their job is open).
fn drop_content(g: &mut Inner, content: &Contents) {
    let mut freed = 0;
    let (jobs, idle) = (&g.jobs, &g.idle);
    g.slots.retain(|k, s| {
        let gone = content.holds(k)
            && matches!(s, Slot::Ready { .. })
            && !jobs.values().any(|c| c.holds(k))
            && !idle.as_ref().is_some_and(|c| c.holds(k));
        if gone {
            freed += s.bytes();
        }
        !gone
    });
    g.bytes -= freed;
}

/// Hand freed heap memory back to the operating system. glibc's allocator keeps large
/// freed regions of its main heap for reuse, so without this a worker that loaded and
/// evicted many domains shows the resident size of its busiest moment forever.
fn release_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only walks and trims the allocator's own free lists; it is
    // safe to call from any thread at any time.
    unsafe {
        libc::malloc_trim(0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_core::scene::Scene;
    use std::sync::atomic::{AtomicU64, Ordering};

    /// Domains of a fixed size made from an empty scene, counting loads.
    struct Fake {
        bytes: u64,
        loads: AtomicU64,
    }

    impl DomainSource for Fake {
        fn estimate_bytes(&self, _d: u32) -> u64 {
            self.bytes
        }
        fn load(&self, d: u32) -> Result<LoadedDomain, String> {
            self.loads.fetch_add(1, Ordering::Relaxed);
            let resident = ResidentScene {
                scene: Scene::default(),
                global_ids: Vec::new(),
                bounds: (glam::Vec3::ZERO, glam::Vec3::ONE),
                domains: Vec::new(),
            };
            let lights = Arc::new(LightSampler::with_bounds(
                &resident.scene,
                false,
                resident.bounds,
            ));
            Ok(LoadedDomain {
                domain: d,
                resident,
                lights,
                bytes: self.bytes,
            })
        }
    }

    fn job(a: u32) -> JobKey {
        JobKey {
            id: "j".into(),
            attempt: a,
        }
    }

    /// A source whose load panics the first `panics` times, as the BVH conversion did
    /// on a scene moved to 1e25 (docs/security.md "Hardening, second round", item 3).
    struct Panicking {
        panics: AtomicU64,
        then: Fake,
    }

    impl DomainSource for Panicking {
        fn estimate_bytes(&self, d: u32) -> u64 {
            self.then.estimate_bytes(d)
        }
        fn load(&self, d: u32) -> Result<LoadedDomain, String> {
            if self.panics.load(Ordering::Relaxed) > 0 {
                self.panics.fetch_sub(1, Ordering::Relaxed);
                panic!("index out of bounds: the len is 441 but the index is 444");
            }
            self.then.load(d)
        }
    }

    #[test]
    fn a_load_that_panics_fails_with_the_message_and_frees_its_slot() {
        let src = Panicking {
            panics: AtomicU64::new(1),
            then: Fake {
                bytes: 100,
                loads: AtomicU64::new(0),
            },
        };
        let store = DomainStore::new(450, Duration::ZERO);
        let j = job(0);
        let e = store.load(&j, 2, &src).err().unwrap();
        assert!(matches!(e, LoadError::Failed { domain: 2, .. }), "{e}");
        let text = e.to_string();
        assert!(
            text.contains("the len is 441 but the index is 444"),
            "{text}"
        );
        assert!(text.contains("panic while loading a domain"), "{text}");
        // The slot and its reservation are gone: the next load is not "busy" (before,
        // every thread skipped the domain for ever and the job hung).
        assert_eq!(store.used_bytes(), 0);
        assert!(store.load(&j, 2, &src).is_ok());
        assert_eq!(store.used_bytes(), 100);
    }

    #[test]
    fn loads_once_and_evicts_least_recently_used() {
        let src = Fake {
            bytes: 100,
            loads: AtomicU64::new(0),
        };
        // Room for three resident domains while a fourth is being built (its reserve,
        // 155), but not for four and a fifth's build.
        let store = DomainStore::new(460, Duration::ZERO);
        let j = job(0);
        store.load(&j, 0, &src).unwrap();
        store.load(&j, 1, &src).unwrap();
        store.load(&j, 0, &src).unwrap();
        assert_eq!(
            src.loads.load(Ordering::Relaxed),
            2,
            "a resident domain is not reloaded"
        );
        // Touch 0, so 1 is the least recently used.
        assert!(store.get(&j, 0).is_some());
        store.load(&j, 2, &src).unwrap();
        assert_eq!(store.used_bytes(), 300);
        // 300 resident + 155 for the build fit 460: nothing goes.
        store.load(&j, 3, &src).unwrap();
        assert_eq!(store.used_bytes(), 400);
        assert_eq!(store.take_counters(&j).evictions, 0);
        // Touch 0, 2 and 3, so 1 is the least recently used; 400 + 155 exceed 460.
        for d in [0, 2, 3] {
            assert!(store.get(&j, d).is_some());
        }
        store.load(&j, 4, &src).unwrap();
        assert!([0, 2, 3, 4].iter().all(|&d| store.is_resident(&j, d)));
        assert!(!store.is_resident(&j, 1), "the LRU domain went");
        assert!(store.used_bytes() <= 460);
        let c = store.take_counters(&j);
        assert_eq!((c.loads, c.evictions), (1, 1));
        assert_eq!(store.take_counters(&j).loads, 0, "counters are deltas");
    }

    #[test]
    fn a_domain_that_fits_only_without_its_build_room_still_loads() {
        let src = Fake {
            bytes: 100,
            loads: AtomicU64::new(0),
        };
        // The reserve (155) is more than the budget: the load takes the whole budget.
        let store = DomainStore::new(140, Duration::ZERO);
        store.load(&job(0), 0, &src).unwrap();
        store.load(&job(0), 1, &src).unwrap();
        assert!(!store.is_resident(&job(0), 0), "one at a time");
        assert!(store.is_resident(&job(0), 1));
    }

    #[test]
    fn a_domain_larger_than_the_budget_is_an_error() {
        let src = Fake {
            bytes: 1000,
            loads: AtomicU64::new(0),
        };
        let store = DomainStore::new(999, Duration::ZERO);
        let e = store.load(&job(0), 3, &src).err().unwrap();
        assert!(matches!(e, LoadError::TooLarge { domain: 3, .. }), "{e}");
        assert!(e.to_string().contains("budget"));
        assert_eq!(src.loads.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn release_frees_an_attempt() {
        let src = Fake {
            bytes: 10,
            loads: AtomicU64::new(0),
        };
        let store = DomainStore::new(0, Duration::ZERO);
        store.load(&job(0), 0, &src).unwrap();
        store.load(&job(1), 0, &src).unwrap();
        store.release("j", 0);
        assert!(!store.is_resident(&job(0), 0));
        assert!(store.is_resident(&job(1), 0));
        assert_eq!(store.used_bytes(), 10);
        assert_eq!(store.resident(&job(1)), vec![(0, 10)]);
    }

    fn named(id: &str) -> JobKey {
        JobKey {
            id: id.into(),
            attempt: 0,
        }
    }

    #[test]
    fn jobs_of_the_same_content_share_domains_and_the_last_stays_warm() {
        let src = Fake {
            bytes: 10,
            loads: AtomicU64::new(0),
        };
        let store = DomainStore::new(0, Duration::ZERO);
        let (a, b, c) = (named("a"), named("b"), named("c"));
        store.open(&a, Contents::package("pkg-1".into()));
        store.open(&b, Contents::package("pkg-1".into()));
        store.load(&a, 0, &src).unwrap();
        store.load(&b, 0, &src).unwrap();
        assert_eq!(src.loads.load(Ordering::Relaxed), 1, "b used a's domain");
        let cb = store.take_counters(&b);
        assert_eq!((cb.loads, cb.warm), (0, 1));
        assert!(store.get(&b, 0).is_some());
        assert_eq!(store.take_counters(&b).warm, 0, "a warm domain counts once");
        assert_eq!(store.take_counters(&a).warm, 0, "a loaded it");
        store.release("a", 0);
        store.release("b", 0);
        assert_eq!(store.used_bytes(), 10, "the released package stays warm");
        // A later job of the same package finds it resident.
        store.open(&c, Contents::package("pkg-1".into()));
        assert!(store.is_resident(&c, 0));
        assert!(store.get(&c, 0).is_some());
        assert_eq!(store.take_counters(&c).warm, 1);
        assert_eq!(store.resident(&c), vec![(0, 10)]);
        store.release("c", 0);
        // A job of another package drops the idle one.
        let d = named("d");
        store.open(&d, Contents::package("pkg-2".into()));
        assert_eq!(store.used_bytes(), 0, "idle domains of other content went");
        assert!(!store.is_resident(&d, 0));
        store.load(&d, 0, &src).unwrap();
        assert_eq!(src.loads.load(Ordering::Relaxed), 2);
    }

    /// A [`Fake`] whose load waits for `go` after saying it has started.
    struct Gated {
        started: std::sync::mpsc::SyncSender<()>,
        go: std::sync::Mutex<std::sync::mpsc::Receiver<()>>,
        then: Fake,
    }

    impl DomainSource for Gated {
        fn estimate_bytes(&self, d: u32) -> u64 {
            self.then.estimate_bytes(d)
        }
        fn load(&self, d: u32) -> Result<LoadedDomain, String> {
            self.started.send(()).map_err(|e| e.to_string())?;
            self.go
                .lock()
                .map_err(|e| e.to_string())?
                .recv()
                .map_err(|e| e.to_string())?;
            self.then.load(d)
        }
    }

    /// A routing table that lets a domain go while it loads (the scheduler decided on a
    /// queue report sent just before the load began): the load still gives its caller
    /// the domain, but the domain does not stay resident, where its held rays would stop
    /// the worker from loading the domains it owns.
    #[test]
    fn a_domain_let_go_while_it_loads_is_not_kept() {
        let (started_tx, started) = std::sync::mpsc::sync_channel(1);
        let (go, go_rx) = std::sync::mpsc::sync_channel(1);
        let src = Gated {
            started: started_tx,
            go: std::sync::Mutex::new(go_rx),
            then: Fake {
                bytes: 100,
                loads: AtomicU64::new(0),
            },
        };
        let store = DomainStore::new(1000, Duration::ZERO);
        let j = job(0);
        std::thread::scope(|scope| {
            let loading = scope.spawn(|| store.load(&j, 4, &src));
            started.recv().unwrap();
            assert_eq!(
                store.resident(&j),
                vec![(4, 100)],
                "a loading domain is reported at its size"
            );
            assert_eq!(store.used_bytes(), 155, "the load reserves its room");
            store.evict(&j, 4);
            go.send(()).unwrap();
            let loaded = loading.join().unwrap().unwrap();
            assert_eq!(loaded.domain, 4, "the caller gets what it loaded");
        });
        assert!(!store.is_resident(&j, 4));
        assert!(store.resident(&j).is_empty());
        assert_eq!(store.used_bytes(), 0);
        let c = store.take_counters(&j);
        assert_eq!((c.loads, c.evictions), (1, 1));
        // Given back later, it loads and stays as usual.
        let (started_tx, started) = std::sync::mpsc::sync_channel(1);
        let (go, go_rx) = std::sync::mpsc::sync_channel(1);
        let src = Gated {
            started: started_tx,
            go: std::sync::Mutex::new(go_rx),
            then: src.then,
        };
        go.send(()).unwrap();
        store.load(&j, 4, &src).unwrap();
        started.recv().unwrap();
        assert!(store.is_resident(&j, 4));
        assert_eq!(src.then.loads.load(Ordering::Relaxed), 2);
    }

    /// The frames of an animation: each its own package, domains 0 and 1 the same in
    /// every frame, domain 2 moved. Only domain 2 is loaded again, whether the frames
    /// run one after another or side by side, and the warm ones count as warm.
    #[test]
    fn domains_of_equal_content_stay_warm_across_packages() {
        let src = Fake {
            bytes: 10,
            loads: AtomicU64::new(0),
        };
        let store = DomainStore::new(0, Duration::ZERO);
        let frame = |n: u32| {
            Contents::per_domain(
                format!("frame {n}").into(),
                vec!["ground".into(), "wall".into(), format!("tri at {n}").into()],
            )
        };
        let f0 = named("f0");
        store.open(&f0, frame(0));
        for d in 0..3 {
            store.load(&f0, d, &src).unwrap();
        }
        store.release("f0", 0);
        let f1 = named("f1");
        store.open(&f1, frame(1));
        assert_eq!(store.used_bytes(), 20, "the moved domain of frame 0 went");
        assert!(store.is_resident(&f1, 0) && store.is_resident(&f1, 1));
        assert!(!store.is_resident(&f1, 2));
        for d in 0..3 {
            store.load(&f1, d, &src).unwrap();
        }
        assert_eq!(src.loads.load(Ordering::Relaxed), 4);
        let c = store.take_counters(&f1);
        assert_eq!((c.loads, c.warm), (1, 2));
        assert_eq!(store.resident(&f1), vec![(0, 10), (1, 10), (2, 10)]);
        // Two frames open at once share the static domains; releasing one keeps what
        // the other holds, and the idle frame's shared domains outlive a later release.
        let f2 = named("f2");
        store.open(&f2, frame(2));
        for d in 0..3 {
            store.load(&f2, d, &src).unwrap();
        }
        assert_eq!(src.loads.load(Ordering::Relaxed), 5);
        store.release("f1", 0);
        store.release("f2", 0);
        assert_eq!(store.used_bytes(), 30, "frame 2's domains stay idle");
        let f3 = named("f3");
        store.open(&f3, frame(3));
        assert_eq!(store.used_bytes(), 20);
        assert_eq!(store.resident(&f3), vec![(0, 10), (1, 10)]);
    }

    #[test]
    fn idle_domains_give_way_to_the_budget() {
        let src = Fake {
            bytes: 100,
            loads: AtomicU64::new(0),
        };
        let store = DomainStore::new(440, Duration::ZERO);
        let (a, b) = (named("a"), named("b"));
        store.open(&a, Contents::package("pkg-1".into()));
        for d in 0..3 {
            store.load(&a, d, &src).unwrap();
        }
        store.release("a", 0);
        // Another job of the same package that needs a fourth domain: the least
        // recently used idle one makes room, as any resident domain would.
        store.open(&b, Contents::package("pkg-1".into()));
        store.load(&b, 3, &src).unwrap();
        assert!(store.used_bytes() <= 440);
        assert_eq!(store.resident(&b).len(), 3);
    }
}
