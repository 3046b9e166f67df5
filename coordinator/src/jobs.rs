//! The job table: every job the server accepted, its state and progress, and the finished
//! film (fixed-point sums, so GetImage can encode PNG at any exposure and tone curve, or
//! EXR).
//!
//! With workers registered, a job runs on them (`dispatch`, `job`). With none, it runs
//! in this process (`crate::local_render`). Either way its record is here, and the
//! table knows nothing of where jobs run. Each job is a
//! [`JobRecord`](crate::job::record::JobRecord), its one writer, which the table hands
//! to what runs the job, and the read-only [`JobEntry`] it publishes to, which the table
//! hands to readers.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, OnceLock};
use std::time::{Duration, SystemTime};

use dray_core::display::Display;
use dray_core::exposure::Exposure;
use dray_core::film::Film;
use dray_core::tiles::TileGrid;
use dray_core::tonemap::Tonemap;
use dray_proto::v1::{JobEventKind, JobSpec, JobState};

pub use crate::job::entry::JobEntry;
use crate::job::record::JobRecord;
use crate::job::status::{JobStatus, terminal};
use crate::store::{JobStore, Op, StoredJob, to_millis};

/// All jobs the server knows, and the gate that runs them one at a time.
pub struct JobTable {
    /// Every job's record: the table hands out their entries to readers, and the
    /// records themselves to what runs a job or asks it to stop, pause or drop its
    /// image.
    jobs: Mutex<Vec<Arc<JobRecord>>>,
    next_id: AtomicU64,
    /// Makes this coordinator's job ids differ from an earlier run's: a worker that
    /// outlived a coordinator restart must not take a new `job-1` for the old one.
    nonce: u32,
    retention: Retention,
    /// Where jobs are kept across restarts, once set ([`JobTable::keep_in`]).
    store: OnceLock<Arc<JobStore>>,
}

/// How long finished jobs keep their images: the coordinator would otherwise hold every
/// image it ever made.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Retention {
    /// Images of at most this many finished jobs are kept (the newest).
    pub keep_finished: usize,
    /// An image is dropped this long after its job finished (None: never, by age).
    pub ttl: Option<Duration>,
    /// The kept images add up to at most this many bytes (the newest first; None: the
    /// coordinator's `--max-job-bytes`, see [`crate::Coordinator::with_admission`]). A
    /// finished 2048² image holds 96 MiB of exact sums: without a byte budget,
    /// `keep_finished` large images were the only bound.
    pub max_bytes: Option<u64>,
}

impl Retention {
    /// The default [`Retention::keep_finished`] (`dray coordinator --keep-finished`).
    pub const KEEP_FINISHED: usize = 100;
    /// The default [`Retention::ttl`] (`dray coordinator --finished-ttl`).
    pub const TTL: Duration = Duration::from_secs(24 * 3600);
}

impl Default for JobTable {
    fn default() -> JobTable {
        JobTable::new()
    }
}

impl Default for Retention {
    fn default() -> Retention {
        Retention {
            keep_finished: Retention::KEEP_FINISHED,
            ttl: Some(Retention::TTL),
            max_bytes: None,
        }
    }
}

impl JobTable {
    /// An empty table.
    pub fn new() -> JobTable {
        JobTable {
            jobs: Mutex::new(Vec::new()),
            next_id: AtomicU64::new(1),
            nonce: {
                let t = SystemTime::now()
                    .duration_since(SystemTime::UNIX_EPOCH)
                    .unwrap_or_default();
                (t.subsec_nanos() ^ (t.as_secs() as u32).rotate_left(13))
                    ^ std::process::id().rotate_left(7)
            },
            retention: Retention::default(),
            store: OnceLock::new(),
        }
    }

    /// Keep every job accepted from now on in `store`. Once only (later calls are
    /// ignored); before any job is accepted.
    pub fn keep_in(&self, store: Arc<JobStore>) {
        let _ = self.store.set(store);
    }

    /// Put back the jobs a store held (in submission order), as this coordinator's. Ended
    /// jobs come back as they ended, with their images in the store; the others come
    /// back QUEUED and are returned, in order, with what they had stored, for the caller
    /// to run again.
    pub fn restore(&self, stored: Vec<StoredJob>) -> Vec<(Arc<JobRecord>, StoredJob)> {
        let mut resumable = Vec::new();
        for j in stored {
            let ended = terminal(j.state);
            // A held job stays held across the restart.
            let state = match j.state {
                s if ended => s,
                JobState::Paused => JobState::Paused,
                _ => JobState::Queued,
            };
            let tiles_total = TileGrid::image(j.spec.width, j.spec.height).count();
            let status = JobStatus {
                state,
                elapsed_final: ended.then(|| j.elapsed.unwrap_or_default()),
                finished_at: j.finished_at,
                error: j.error.clone(),
                stats: j.stats.clone(),
                dropped: j.dropped.clone(),
                image_file: j.image.clone(),
                resolved: j.resolved.clone(),
                tiles_done: if state == JobState::Succeeded {
                    tiles_total
                } else {
                    0
                },
                ..JobStatus::default()
            };
            let log =
                crate::job_events::EventLog::restored(j.events.clone(), j.retried_from.clone());
            let entry = Arc::new(JobRecord::new(
                j.id.clone(),
                j.spec.clone(),
                j.submitted_at,
                log,
                status,
                self.store.get().cloned(),
            ));
            if !ended {
                entry.note(
                    JobEventKind::Restored,
                    format!(
                        "taken back by a restarted coordinator ({} then); {}",
                        j.state.as_str_name(),
                        if state == JobState::Paused {
                            "paused until resumed"
                        } else {
                            "queued again"
                        }
                    ),
                );
                if j.state != state
                    && let Some(store) = entry.store()
                {
                    store.post(Op::State {
                        id: j.id.clone(),
                        state,
                    });
                }
                resumable.push((entry.clone(), j));
            }
            self.jobs().push(entry);
        }
        resumable
    }

    /// The same table with another retention policy.
    pub fn with_retention(mut self, retention: Retention) -> JobTable {
        // (The budget defaults to --max-job-bytes in `with_admission`.)
        self.retention = retention;
        self
    }

    /// Jobs not yet in a terminal state (queued, preparing or running).
    pub fn active(&self) -> usize {
        self.jobs().iter().filter(|j| !terminal(j.state())).count()
    }

    /// Drop the images the retention policy no longer keeps: those of finished jobs
    /// beyond the newest `keep_finished`, beyond the byte budget, and those older than
    /// the TTL. The jobs stay listed (GetJob), and GetImage says why there is no image.
    /// Runs when a job is submitted and when an image is asked for.
    pub fn sweep(&self) {
        let now = SystemTime::now();
        let mut kept = 0usize;
        let mut kept_bytes = 0u64;
        let budget = self.retention.max_bytes.unwrap_or(u64::MAX);
        for j in self.jobs().iter().rev() {
            if !j.is_terminal() {
                continue;
            }
            let film = j.film();
            if film.is_none() && j.image_file().is_none() {
                continue;
            }
            // A stored image holds exactly the sums the film would.
            let bytes = film.as_ref().map_or_else(
                || u64::from(j.spec.width) * u64::from(j.spec.height) * 24,
                |f| f.heap_bytes(),
            );
            let finished_at = j.finished_at();
            let expired = match (self.retention.ttl, finished_at) {
                (Some(ttl), Some(at)) => now.duration_since(at).is_ok_and(|age| age > ttl),
                _ => false,
            };
            let why = if expired {
                "it finished longer ago than the coordinator's --finished-ttl"
            } else if kept >= self.retention.keep_finished {
                "the coordinator keeps the images of its newest --keep-finished jobs only"
            } else if kept_bytes.saturating_add(bytes) > budget {
                "the newer finished images already take the coordinator's \
                 --keep-finished-bytes (default: --max-job-bytes)"
            } else {
                kept += 1;
                kept_bytes = kept_bytes.saturating_add(bytes);
                continue;
            };
            j.drop_image(why);
        }
    }

    fn jobs(&self) -> MutexGuard<'_, Vec<Arc<JobRecord>>> {
        dray_sync::lock(&self.jobs)
    }

    /// Whether the job store (if any) is writing: `Err(why)` while its last transaction
    /// failed, so a new job would not survive a restart.
    pub fn store_health(&self) -> Result<(), String> {
        self.store.get().map_or(Ok(()), |s| s.health())
    }

    /// Wait until every job record posted so far (a new job's included) is on disk, at
    /// most 10 s, without holding a runtime thread. False when the store could not
    /// write it. True without a store.
    pub async fn confirm_kept(&self) -> bool {
        let Some(store) = self.store.get().cloned() else {
            return true;
        };
        // Everything posted before is confirmed with it, the entry's Insert included.
        store
            .post_durable(Op::Nothing, std::time::Duration::from_secs(10))
            .await
    }

    /// The job store jobs are kept in, if any.
    pub fn store(&self) -> Option<&Arc<JobStore>> {
        self.store.get()
    }

    /// A new job group's id, unique as job ids are (`crate::job_group`).
    pub fn new_group_id(&self) -> String {
        let n = self.next_id.fetch_add(1, Ordering::Relaxed);
        crate::job_group::group_id(n, self.nonce)
    }

    /// Add a job QUEUED, without starting anything: the caller runs it with the record
    /// returned, the job's one writer (in process, or on workers through the
    /// dispatcher).
    pub fn insert(&self, spec: JobSpec) -> Arc<JobRecord> {
        self.insert_as(spec, None)
    }

    /// [`JobTable::insert`] under `id` when given (a frame of a job group, whose id
    /// [`JobTable::new_group_id`] and `crate::job_group::frame_id` made), else a new id.
    pub fn insert_as(&self, spec: JobSpec, id: Option<String>) -> Arc<JobRecord> {
        self.sweep();
        let id = id.unwrap_or_else(|| {
            let n = self.next_id.fetch_add(1, Ordering::Relaxed);
            format!("job-{n}-{:08x}", self.nonce)
        });
        let record = Arc::new(JobRecord::new(
            id,
            spec,
            SystemTime::now(),
            Default::default(),
            JobStatus::queued(),
            self.store.get().cloned(),
        ));
        if let Some(store) = record.store() {
            store.post(Op::Insert {
                id: record.id.clone(),
                spec: record.spec.clone(),
                submitted_ms: to_millis(record.submitted_at),
            });
        }
        self.jobs().push(record.clone());
        record.note(
            JobEventKind::Queued,
            format!("queued at priority {}", record.spec.priority),
        );
        crate::metrics::otel::job_accepted();
        record
    }

    /// The job with id `id`, to read.
    pub fn get(&self, id: &str) -> Option<Arc<JobEntry>> {
        self.record(id).map(|r| r.entry().clone())
    }

    /// The record of job `id`, to change it from outside what runs it: cancel, pause or
    /// resume it, note an operator's action.
    pub(crate) fn record(&self, id: &str) -> Option<Arc<JobRecord>> {
        self.jobs().iter().find(|j| j.id == id).cloned()
    }

    /// Set every job's cancel flag, leaving its state as it is: scene loads and package
    /// cuts stop at their next look at it (a stopping coordinator).
    pub(crate) fn stop_preparations(&self) {
        for r in self.jobs().iter() {
            r.cancel_flag().store(true, Ordering::SeqCst);
        }
    }

    /// All jobs, newest first.
    pub fn list(&self) -> Vec<Arc<JobEntry>> {
        self.jobs()
            .iter()
            .rev()
            .map(|r| r.entry().clone())
            .collect()
    }
}

/// The film as an 8-bit sRGB PNG through `display` (exposure, tone curve): the same
/// bytes `dray render --output` writes with the same `--exposure` and `--tonemap`. Called
/// on the assembled film, so an automatic exposure sees the whole image, whatever the
/// number of workers that traced it.
pub fn encode_png(film: &Film, spp: u32, display: Display) -> Result<Vec<u8>, String> {
    display.encode_png(film, spp)
}

/// The display transform a GetImage request asks for: `exposure` absent is automatic,
/// `tonemap` empty the default curve. Errors name the request's field.
pub fn requested_display(exposure: Option<f32>, tonemap: &str) -> Result<Display, String> {
    let exposure = match exposure {
        None => Exposure::Auto,
        Some(ev) => Exposure::stops(ev).map_err(|e| format!("exposure: {e}"))?,
    };
    let tonemap = Tonemap::parse(tonemap).map_err(|e| format!("tonemap: {e}"))?;
    Ok(Display { exposure, tonemap })
}

/// The film as linear f32 RGB OpenEXR, the bytes `dray render --exr` writes.
pub fn encode_exr(film: &Film, spp: u32) -> Result<Vec<u8>, String> {
    film.encode_exr(spp)
        .map_err(|e| format!("cannot encode EXR: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn get_image_display_errors_name_the_field() {
        assert_eq!(requested_display(None, ""), Ok(Display::default()));
        assert_eq!(
            requested_display(Some(0.0), "clamp"),
            Ok(Display::fixed(0.0))
        );
        assert_eq!(
            requested_display(Some(-2.0), "reinhard").map(|d| d.exposure),
            Ok(Exposure::Stops(-2.0))
        );
        for (e, t, want) in [
            (
                Some(f32::NAN),
                "",
                "exposure: NaN is out of range (-64..=64 stops)",
            ),
            (
                Some(65.0),
                "",
                "exposure: 65 is out of range (-64..=64 stops)",
            ),
            (None, "ACES", "tonemap: unknown tone curve \"ACES\""),
        ] {
            let got = requested_display(e, t).expect_err(want);
            assert!(got.starts_with(want), "{got}");
        }
    }

    fn spec(seed: u64) -> JobSpec {
        JobSpec {
            scene: "cornell".into(),
            width: 4,
            height: 2,
            spp: 1,
            seed,
            ..Default::default()
        }
    }

    fn film(v: i64) -> Film {
        let mut f = Film::new(4, 2);
        for p in 0..8 {
            f.add_fixed(p, [v, -v, p as i64]);
        }
        f
    }

    /// Finished jobs come back from the store with their images, and the retention
    /// policy deletes a dropped image's file and records why.
    #[test]
    fn finished_images_are_kept_and_dropped_in_the_store() {
        let dir = tempfile::tempdir().unwrap();
        let (old, new) = {
            let (store, _) = JobStore::open(dir.path()).unwrap();
            let store = Arc::new(store);
            let table = JobTable::new();
            table.keep_in(store.clone());
            let old = table.insert(spec(1));
            old.finish(JobState::Succeeded, String::new(), Some(film(3)));
            let new = table.insert(spec(2));
            new.finish(JobState::Succeeded, String::new(), Some(film(5)));
            store.flush();
            (old.id.clone(), new.id.clone())
        };
        let image = |id: &str| dir.path().join("images").join(format!("{id}.film"));
        assert!(image(&old).is_file() && image(&new).is_file());

        let (store, stored) = JobStore::open(dir.path()).unwrap();
        let store = Arc::new(store);
        let table = JobTable::new().with_retention(Retention {
            keep_finished: 1,
            ..Retention::default()
        });
        table.keep_in(store.clone());
        assert!(table.restore(stored).is_empty(), "nothing to run again");
        let get = |id: &str| table.get(id).unwrap();
        assert_eq!(get(&old).state(), JobState::Succeeded);
        let kept = crate::store::image_file::read(&get(&old).image_file().unwrap()).unwrap();
        assert_eq!(kept, film(3), "the image comes back exactly");

        table.sweep();
        store.flush();
        assert!(
            get(&old)
                .dropped()
                .is_some_and(|w| w.contains("--keep-finished"))
        );
        assert!(get(&old).image_file().is_none());
        assert!(!image(&old).exists(), "the dropped image's file is deleted");
        assert!(image(&new).is_file(), "the newest is kept");
        drop(table);
        store.seal();
        let (_store, stored) = JobStore::open(dir.path()).unwrap();
        let old = stored.iter().find(|j| j.id == old).unwrap();
        assert!(old.image.is_none());
        assert!(
            old.dropped
                .as_deref()
                .is_some_and(|w| w.contains("--keep-finished"))
        );
    }
}
