//! Opening the job store: the state directory's lock, the database's checks and schema,
//! and the jobs a restarted coordinator reads back.
//!
//! The directory holds `lock` (held with `flock` for the store's life: a second
//! coordinator on the same directory stops with an error naming it), `jobs.sqlite3` (and
//! SQLite's `-wal` file) and `images/`. A database that is not a dray store, is damaged,
//! or comes from a newer dray is an error naming the file, and nothing is changed or
//! deleted: the user decides what to do with it.

use std::fs::{File, TryLockError};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Duration;

use dray_proto::v1::{JobSpec, JobState, JobStats};
use prost::Message;
use rusqlite::{Connection, ErrorCode, OpenFlags};

use dray_core::aov::AOV_WORDS;
use dray_core::film::Film;

use super::op::{Confirm, Op};
use super::writer::{Health, Writer, image_name};
use super::{CommittedTile, StoreError, StoredJob, from_millis};
use super::{image_file, state_dir};

/// The schema this build writes and the newest it reads (`PRAGMA user_version`).
/// 4 added the committed tiles' AOV sums and adaptive-sampling stops.
pub const SCHEMA_VERSION: u32 = 4;

/// `PRAGMA application_id` of a dray job store ("dray"), so another program's SQLite
/// file is never taken for one.
const APPLICATION_ID: i32 = 0x6472_6179;

/// The database's file name in the state directory.
pub const DB_FILE: &str = "jobs.sqlite3";
/// The lock file's name in the state directory.
pub const LOCK_FILE: &str = "lock";
/// The images' folder in the state directory.
pub const IMAGES_DIR: &str = "images";

const SCHEMA: &str = "
CREATE TABLE jobs (
    seq INTEGER PRIMARY KEY,          -- submission order
    id TEXT NOT NULL UNIQUE,
    spec BLOB NOT NULL,               -- dray.v1.JobSpec as accepted
    resolved BLOB,                    -- dray.v1.JobSpec as it ran on workers
    label TEXT NOT NULL,
    state INTEGER NOT NULL,           -- dray.v1.JobState
    error TEXT NOT NULL DEFAULT '',
    submitted_ms INTEGER NOT NULL,
    finished_ms INTEGER,
    elapsed_ms INTEGER,
    stats BLOB,                       -- dray.v1.JobStats
    attempt INTEGER,                  -- newest attempt started on workers
    image TEXT,                       -- file name in images/
    dropped TEXT                      -- why the image was dropped
);
CREATE TABLE tiles (
    job_id TEXT NOT NULL,
    tile INTEGER NOT NULL,
    sums BLOB NOT NULL,               -- 3 x i64 little-endian per pixel, row-major
    passes INTEGER,                   -- progressive passes in the sums; NULL: every pass
    PRIMARY KEY (job_id, tile)
) WITHOUT ROWID;
";

/// From schema 1 (no progressive passes: a stored tile was complete) to 2.
const MIGRATE_1_TO_2: &str = "ALTER TABLE tiles ADD COLUMN passes INTEGER;";

/// From schema 3 to 4 (also run on a new database): a committed tile's AOV sums (8 x
/// i64 little-endian per pixel, row-major; NULL for a job without AOVs) and the samples
/// its pixels stopped at when adaptive sampling stopped it (NULL: it did not). A job of
/// an older store that writes AOVs traces its tiles again (they have none); one with a
/// noise threshold committed no tiles before.
const MIGRATE_3_TO_4: &str = "
ALTER TABLE tiles ADD COLUMN aovs BLOB;
ALTER TABLE tiles ADD COLUMN stopped_at INTEGER;
";

/// An open job store: the lock, and the thread that writes the database.
pub struct JobStore {
    dir: PathBuf,
    writer: Mutex<Option<Writer>>,
    /// Why the writer's last transaction failed, if it did.
    health: Health,
}

impl std::fmt::Debug for JobStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("JobStore").field("dir", &self.dir).finish()
    }
}

impl JobStore {
    /// Open (or create) the store in `dir`, and read back every job it holds, in
    /// submission order. Fails, changing nothing, when another coordinator holds the
    /// directory or the database cannot be used.
    pub fn open(dir: &Path) -> Result<(JobStore, Vec<StoredJob>), StoreError> {
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| StoreError::Io { path, source }
        };
        state_dir::prepare(dir, "state directory")?;
        let lock = lock(&dir.join(LOCK_FILE))?;
        let images = dir.join(IMAGES_DIR);
        state_dir::prepare_inner(&images, "images directory")?;
        let path = dir.join(DB_FILE);
        // Made here first (mode 0600, never through a link), so SQLite, which gives its
        // journal the database's mode, makes no file others can read.
        drop(state_dir::open_file(&path)?);
        let conn = open_db(&path)?;
        let jobs = load(&conn, &images).map_err(|e| classify(&path, e))?;
        remove_stale_temporaries(&images);
        let health = Health::default();
        let writer = Writer::spawn(conn, path, images, lock, health.clone()).map_err(io(dir))?;
        Ok((
            JobStore {
                dir: dir.to_path_buf(),
                writer: Mutex::new(Some(writer)),
                health,
            },
            jobs,
        ))
    }

    /// The state directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Post `op` to the writer; dropped once the store is sealed.
    pub fn post(&self, op: Op) {
        if let Some(w) = self.lock().as_ref() {
            w.post(op);
        }
    }

    /// Post `op` and wait (at most `timeout`) until it is in the database: for the rare
    /// writes that must be on disk before the coordinator acts on them (a new attempt,
    /// which workers remember; a new job, before SubmitJob answers). False when it could
    /// not be confirmed: the transaction failed, the store is sealed, or `timeout`
    /// passed. The wait is a oneshot awaited, so the caller's task is suspended and the
    /// runtime's thread stays free for other jobs (it used to block a runtime thread up
    /// to 10 s on a `recv_timeout`).
    pub async fn post_durable(&self, op: Op, timeout: Duration) -> bool {
        let Some(confirmed) = self.post_confirmed(op) else {
            return false;
        };
        matches!(tokio::time::timeout(timeout, confirmed).await, Ok(Ok(true)))
    }

    /// Post `op` and a flush after it: the receiver is answered once `op` is committed.
    /// None once the store is sealed.
    fn post_confirmed(&self, op: Op) -> Option<tokio::sync::oneshot::Receiver<bool>> {
        let (tx, rx) = tokio::sync::oneshot::channel();
        self.post_flushed(op, Confirm::Task(tx)).then_some(rx)
    }

    /// Post `op`, then a flush answered on `confirm`; false once the store is sealed.
    fn post_flushed(&self, op: Op, confirm: Confirm) -> bool {
        let g = self.lock();
        let Some(w) = g.as_ref() else { return false };
        w.post(op);
        w.post(Op::Flush(confirm));
        true
    }

    /// `Err(why)` while the store's last transaction failed (a full or read-only disk):
    /// what it was asked to keep since is not kept. Clears once a transaction succeeds.
    pub fn health(&self) -> Result<(), String> {
        match dray_sync::lock(&self.health).as_ref() {
            Some(why) => Err(why.clone()),
            None => Ok(()),
        }
    }

    /// Write job `id`'s finished image into `images/` (atomically, synced), before the
    /// job is called SUCCEEDED: a job whose image cannot be kept (a full disk) fails
    /// naming why, instead of succeeding with no image (issue 45, item 7). Nothing is
    /// written once the store is sealed (the coordinator is stopping; the job is
    /// resumed from its tiles). Blocks for the write: a caller on the runtime's threads
    /// wraps it in `block_in_place`.
    pub fn keep_image(&self, id: &str, film: &Film) -> Result<(), StoreError> {
        if self.lock().is_none() {
            return Ok(());
        }
        let file = self.dir.join(IMAGES_DIR).join(image_name(id));
        image_file::write_atomic(&file, &image_file::encode(film))
    }

    /// Remove job `id`'s image file, written by [`JobStore::keep_image`] for a job that
    /// then did not succeed after all (a cancel came first).
    pub fn forget_image(&self, id: &str) {
        let file = self.dir.join(IMAGES_DIR).join(image_name(id));
        if let Err(e) = std::fs::remove_file(&file)
            && e.kind() != std::io::ErrorKind::NotFound
        {
            tracing::warn!("cannot remove the unused image {}: {e}", file.display());
        }
    }

    /// Wait (at most 30 s) until everything posted so far is in the database; false when
    /// it could not be confirmed. Blocks the calling thread: for tests and threads
    /// outside the runtime (a task awaits [`JobStore::post_durable`] instead).
    pub fn flush(&self) -> bool {
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        self.post_flushed(Op::Nothing, Confirm::Thread(tx))
            && rx.recv_timeout(Duration::from_secs(30)).unwrap_or(false)
    }

    /// Write what is pending, then stop writing and release the directory's lock: for a
    /// coordinator that is stopping, whose jobs must be resumed as they were rather than
    /// recorded as failed by the shutdown itself.
    pub fn seal(&self) {
        let writer = self.lock().take();
        if let Some(w) = writer {
            w.stop();
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Option<Writer>> {
        dray_sync::lock(&self.writer)
    }
}

impl Drop for JobStore {
    fn drop(&mut self) {
        self.seal();
    }
}

/// Remove the temporary files of image writes a killed or failing coordinator left
/// (`.NAME.tmp`, see `image_file::write_atomic`): nothing names them, and on a full disk
/// they held the space the store needed (issue 45, item 7: 13 were left).
fn remove_stale_temporaries(images: &Path) {
    let Ok(entries) = std::fs::read_dir(images) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name();
        let name = name.to_string_lossy();
        let stale = name.starts_with('.')
            && name.ends_with(".tmp")
            && e.file_type().is_ok_and(|t| t.is_file());
        if stale && let Err(err) = std::fs::remove_file(e.path()) {
            tracing::warn!("cannot remove {}: {err}", e.path().display());
        }
    }
}

/// Take the state directory's lock at `path` (creating the file), and write this
/// process's id into it for the message a second coordinator gets.
fn lock(path: &Path) -> Result<File, StoreError> {
    let io = |source| StoreError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut f = state_dir::open_file(path)?;
    match f.try_lock() {
        Ok(()) => {}
        Err(TryLockError::WouldBlock) => {
            let pid = std::fs::read_to_string(path).unwrap_or_default();
            let pid = pid.trim();
            return Err(StoreError::Locked {
                file: path.to_path_buf(),
                holder: if pid.chars().all(|c| c.is_ascii_digit()) && !pid.is_empty() {
                    format!(", pid {pid}")
                } else {
                    String::new()
                },
            });
        }
        Err(TryLockError::Error(e)) => return Err(io(e)),
    }
    f.set_len(0).map_err(io)?;
    writeln!(f, "{}", std::process::id()).map_err(io)?;
    Ok(f)
}

/// Whether `name` is one file name: no separator, not `.` or `..`, not empty.
fn plain_file_name(name: &str) -> bool {
    !name.is_empty() && name != "." && name != ".." && !name.contains(['/', '\\', '\0'])
}

/// A rusqlite error on `file` as the store's error: a file SQLite cannot read as a
/// database is damaged, not an I/O failure.
pub(crate) fn classify(file: &Path, e: rusqlite::Error) -> StoreError {
    match e.sqlite_error_code() {
        Some(ErrorCode::NotADatabase | ErrorCode::DatabaseCorrupt) => StoreError::Corrupt {
            file: file.to_path_buf(),
            why: "it is not a readable SQLite database".into(),
        },
        Some(ErrorCode::DatabaseBusy | ErrorCode::DatabaseLocked) => StoreError::Locked {
            file: file.to_path_buf(),
            holder: String::new(),
        },
        _ => StoreError::Sql {
            file: file.to_path_buf(),
            source: e,
        },
    }
}

/// Open the database at `path`: check what it is, make the schema if it is new, and set
/// it up for durable writes.
fn open_db(path: &Path) -> Result<Connection, StoreError> {
    let sql = |e| classify(path, e);
    let conn = Connection::open_with_flags(
        path,
        OpenFlags::SQLITE_OPEN_READ_WRITE
            | OpenFlags::SQLITE_OPEN_CREATE
            | OpenFlags::SQLITE_OPEN_NO_MUTEX
            // A link planted in place of the database (or its journal) is an error.
            | OpenFlags::SQLITE_OPEN_NOFOLLOW,
    )
    .map_err(sql)?;
    let app: i32 = conn
        .pragma_query_value(None, "application_id", |r| r.get(0))
        .map_err(sql)?;
    let version: u32 = conn
        .pragma_query_value(None, "user_version", |r| r.get(0))
        .map_err(sql)?;
    let tables: i64 = conn
        .query_row("SELECT count(*) FROM sqlite_master", [], |r| r.get(0))
        .map_err(sql)?;
    let corrupt = |why: &str| StoreError::Corrupt {
        file: path.to_path_buf(),
        why: why.to_string(),
    };
    if app != APPLICATION_ID && (app != 0 || tables > 0) {
        return Err(corrupt(
            "it is an SQLite database, but not a dray job store",
        ));
    }
    if version > SCHEMA_VERSION {
        return Err(StoreError::Newer {
            file: path.to_path_buf(),
            found: version,
            supported: SCHEMA_VERSION,
        });
    }
    let check: String = conn
        .query_row("PRAGMA quick_check", [], |r| r.get(0))
        .map_err(sql)?;
    if check != "ok" {
        return Err(corrupt(&format!("its integrity check says {check:?}")));
    }
    // Write-ahead log with a sync at every commit: a committed transaction survives a
    // kill or a power cut, and a torn one is rolled back on the next open.
    conn.pragma_update(None, "journal_mode", "WAL")
        .map_err(sql)?;
    conn.pragma_update(None, "synchronous", "FULL")
        .map_err(sql)?;
    if app == 0 {
        let tx = conn.unchecked_transaction().map_err(sql)?;
        tx.execute_batch(SCHEMA).map_err(sql)?;
        tx.execute_batch(super::events::MIGRATE_2_TO_3)
            .map_err(sql)?;
        tx.execute_batch(MIGRATE_3_TO_4).map_err(sql)?;
        tx.pragma_update(None, "application_id", APPLICATION_ID)
            .map_err(sql)?;
        tx.pragma_update(None, "user_version", SCHEMA_VERSION)
            .map_err(sql)?;
        tx.commit().map_err(sql)?;
    } else if (1..SCHEMA_VERSION).contains(&version) {
        let tx = conn.unchecked_transaction().map_err(sql)?;
        if version == 1 {
            tx.execute_batch(MIGRATE_1_TO_2).map_err(sql)?;
        }
        if version <= 2 {
            tx.execute_batch(super::events::MIGRATE_2_TO_3)
                .map_err(sql)?;
        }
        tx.execute_batch(MIGRATE_3_TO_4).map_err(sql)?;
        tx.pragma_update(None, "user_version", SCHEMA_VERSION)
            .map_err(sql)?;
        tx.commit().map_err(sql)?;
    } else if version < SCHEMA_VERSION {
        // Schema 1 is the oldest released: a dray store with a lower version is not one
        // this build wrote.
        return Err(corrupt(&format!("unknown schema version {version}")));
    }
    Ok(conn)
}

/// Every job in the database, in submission order, with the committed tiles of those
/// that had not ended.
fn load(conn: &Connection, images: &Path) -> rusqlite::Result<Vec<StoredJob>> {
    let mut q = conn.prepare(
        "SELECT id, spec, resolved, state, error, submitted_ms, finished_ms, elapsed_ms, \
         stats, attempt, image, dropped FROM jobs ORDER BY seq",
    )?;
    let rows = q.query_map([], |r| {
        let blob = |i: usize| -> rusqlite::Result<Option<Vec<u8>>> { r.get(i) };
        let spec = blob(1)?.unwrap_or_default();
        let decode_err = |i: usize, e: prost::DecodeError| {
            rusqlite::Error::FromSqlConversionFailure(i, rusqlite::types::Type::Blob, Box::new(e))
        };
        let state: i32 = r.get(3)?;
        Ok(StoredJob {
            id: r.get(0)?,
            spec: JobSpec::decode(spec.as_slice()).map_err(|e| decode_err(1, e))?,
            resolved: blob(2)?
                .map(|b| JobSpec::decode(b.as_slice()))
                .transpose()
                .map_err(|e| decode_err(2, e))?,
            state: JobState::try_from(state).unwrap_or(JobState::Failed),
            error: r.get(4)?,
            submitted_at: from_millis(r.get(5)?),
            finished_at: r.get::<_, Option<i64>>(6)?.map(from_millis),
            elapsed: r
                .get::<_, Option<i64>>(7)?
                .map(|ms| Duration::from_millis(u64::try_from(ms).unwrap_or(0))),
            stats: blob(8)?
                .map(|b| JobStats::decode(b.as_slice()))
                .transpose()
                .map_err(|e| decode_err(8, e))?
                .unwrap_or_default(),
            attempt: r.get(9)?,
            // Only a plain name in images/: a row naming an absolute path or `..` (a
            // hand-edited or foreign database) names no image.
            image: r
                .get::<_, Option<String>>(10)?
                .filter(|n| plain_file_name(n))
                .map(|n| images.join(n)),
            dropped: r.get(11)?,
            tiles: Vec::new(),
            events: Vec::new(),
            retried_from: None,
        })
    })?;
    // A row whose fields cannot be read (a spec that does not decode, a value of the
    // wrong type: a hand-edited or damaged row) is left out with a warning, and stays in
    // the database untouched; it no longer keeps every other job from coming back (issue
    // 45, item 11). Any other error (the file itself) still fails the open.
    let mut jobs = Vec::new();
    for row in rows {
        match row {
            Ok(job) => jobs.push(job),
            Err(
                e @ (rusqlite::Error::FromSqlConversionFailure(..)
                | rusqlite::Error::InvalidColumnType(..)
                | rusqlite::Error::IntegralValueOutOfRange(..)),
            ) => {
                tracing::warn!("a job in the store cannot be read and is left out: {e}");
            }
            Err(e) => return Err(e),
        }
    }
    let mut tiles = conn.prepare(
        "SELECT tile, sums, passes, aovs, stopped_at FROM tiles WHERE job_id = ?1 ORDER BY tile",
    )?;
    for j in jobs.iter_mut().filter(|j| !ended(j.state)) {
        j.tiles = tiles
            .query_map([&j.id], |r| {
                let sums: Vec<u8> = r.get(1)?;
                let aovs: Option<Vec<u8>> = r.get(3)?;
                Ok(CommittedTile {
                    tile: r.get(0)?,
                    sums: sums
                        .chunks_exact(24)
                        .map(super::image_file::read_words)
                        .collect(),
                    passes: r.get(2)?,
                    aovs: aovs.map(|a| {
                        a.chunks_exact(8 * AOV_WORDS)
                            .map(super::image_file::read_words)
                            .collect()
                    }),
                    stopped_at: r.get(4)?,
                })
            })?
            .collect::<rusqlite::Result<Vec<_>>>()?;
    }
    super::events::load(conn, &mut jobs)?;
    Ok(jobs)
}

/// Whether `s` is a terminal state.
pub(crate) fn ended(s: JobState) -> bool {
    matches!(
        s,
        JobState::Succeeded | JobState::Failed | JobState::Cancelled
    )
}

#[cfg(test)]
mod tests {
    /// The `image` column names a file in `images/` only (issue 45, item 6: a row could
    /// hold an absolute path, which `Path::join` takes as is).
    #[test]
    fn only_plain_names_are_image_files() {
        for bad in ["", ".", "..", "/etc/shadow", "../x", "a/b", "a\\b", "a\0b"] {
            assert!(!plain_file_name(bad), "{bad:?}");
        }
        assert!(plain_file_name("0123-abc.film"));
    }

    /// One damaged row (a spec that does not decode) is left out; the other jobs come
    /// back (issue 45, item 11: one bad row stopped the whole store from opening).
    #[test]
    fn one_unreadable_row_does_not_keep_the_others_out() {
        let dir = tempfile::tempdir().unwrap();
        {
            let (store, _) = JobStore::open(dir.path()).unwrap();
            for id in ["good-1", "bad", "good-2"] {
                store.post(Op::Insert {
                    id: id.into(),
                    spec: JobSpec {
                        scene: "cornell".into(),
                        width: 8,
                        height: 8,
                        spp: 1,
                        ..Default::default()
                    },
                    submitted_ms: 1,
                });
            }
            store.flush();
        }
        {
            let conn = Connection::open(dir.path().join(DB_FILE)).unwrap();
            conn.execute("UPDATE jobs SET spec = x'ffffffff' WHERE id = 'bad'", [])
                .unwrap();
        }
        let (_store, jobs) = JobStore::open(dir.path()).unwrap();
        let ids: Vec<&str> = jobs.iter().map(|j| j.id.as_str()).collect();
        assert_eq!(ids, ["good-1", "good-2"]);
    }

    use super::*;
    use rusqlite::OptionalExtension;

    /// Whether the database has a row for job `id`.
    fn has_job(conn: &Connection, id: &str) -> rusqlite::Result<bool> {
        conn.query_row("SELECT 1 FROM jobs WHERE id = ?1", [id], |_| Ok(()))
            .optional()
            .map(|r| r.is_some())
    }

    fn spec() -> JobSpec {
        JobSpec {
            scene: "cornell".into(),
            width: 8,
            height: 8,
            spp: 1,
            label: "a".into(),
            ..Default::default()
        }
    }

    fn files(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn jobs_and_committed_tiles_come_back_in_order() {
        let dir = tempfile::tempdir().unwrap();
        {
            let (store, jobs) = JobStore::open(dir.path()).unwrap();
            assert!(jobs.is_empty());
            for id in ["job-2-x", "job-1-x"] {
                store.post(Op::Insert {
                    id: id.into(),
                    spec: spec(),
                    submitted_ms: 5,
                });
            }
            store.post(Op::State {
                id: "job-2-x".into(),
                state: JobState::Running,
            });
            store.post(Op::Tiles {
                id: "job-2-x".into(),
                tiles: vec![plain_tile(), tile_with_aovs()],
            });
            store.post(Op::Attempt {
                id: "job-2-x".into(),
                attempt: 4,
            });
            assert!(store.flush());
        }
        let (_store, jobs) = JobStore::open(dir.path()).unwrap();
        let ids: Vec<&str> = jobs.iter().map(|j| j.id.as_str()).collect();
        assert_eq!(ids, ["job-2-x", "job-1-x"], "submission order");
        assert_eq!(jobs[0].state, JobState::Running);
        assert_eq!(jobs[0].attempt, Some(4));
        assert_eq!(jobs[0].spec, spec());
        assert_eq!(jobs[0].tiles, [plain_tile(), tile_with_aovs()]);
        assert_eq!(jobs[1].state, JobState::Queued);
    }

    /// A durable write is awaited on the runtime (a oneshot, not a blocked thread): it
    /// confirms what it posted, and a sealed store confirms nothing.
    #[tokio::test]
    async fn a_durable_write_is_awaited_and_a_sealed_store_confirms_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let (store, _) = JobStore::open(dir.path()).unwrap();
        store.post(Op::Insert {
            id: "job-1-x".into(),
            spec: spec(),
            submitted_ms: 5,
        });
        let attempt = |attempt| Op::Attempt {
            id: "job-1-x".into(),
            attempt,
        };
        assert!(
            store
                .post_durable(attempt(2), Duration::from_secs(10))
                .await
        );
        store.seal();
        assert!(
            !store
                .post_durable(attempt(3), Duration::from_secs(10))
                .await,
            "nothing is written once sealed"
        );
        drop(store);
        let (_store, jobs) = JobStore::open(dir.path()).unwrap();
        assert_eq!(jobs[0].attempt, Some(2));
    }

    /// A store as an older dray wrote it at `db`: `schema`, `version`, job `job-1-x` and
    /// one tile of zero sums inserted by `tile` (which binds the sums as `?1`).
    fn old_store(db: &Path, schema: &str, version: u32, tile: &str) {
        let c = Connection::open(db).unwrap();
        c.execute_batch(schema).unwrap();
        c.pragma_update(None, "application_id", APPLICATION_ID)
            .unwrap();
        c.pragma_update(None, "user_version", version).unwrap();
        c.execute(
            "INSERT INTO jobs (seq, id, spec, label, state, submitted_ms) \
             VALUES (1, 'job-1-x', x'', '', 3, 1)",
            [],
        )
        .unwrap();
        c.execute(tile, [vec![0u8; 24]]).unwrap();
    }

    /// A tile of a job without AOVs, in its second pass, with extreme sums.
    fn plain_tile() -> CommittedTile {
        CommittedTile {
            tile: 3,
            sums: vec![[1, -2, i64::MAX], [i64::MIN, 0, 7]],
            passes: Some(2),
            aovs: None,
            stopped_at: None,
        }
    }

    /// A tile of a job with AOVs that adaptive sampling stopped at 16 samples.
    fn tile_with_aovs() -> CommittedTile {
        CommittedTile {
            tile: 5,
            sums: vec![[4, 5, 6]],
            passes: Some(7),
            aovs: Some(vec![[1, 2, 3, -4, 5, -6, i64::MAX, 9]]),
            stopped_at: Some(16),
        }
    }

    /// A schema-3 store (tiles without AOVs or stops) is migrated: its tiles come back
    /// with neither, and new tiles keep both.
    #[test]
    fn a_schema_3_store_is_migrated_and_keeps_aovs_and_stops_after() {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join(DB_FILE);
        old_store(
            &db,
            &format!("{SCHEMA}{}", super::super::events::MIGRATE_2_TO_3),
            3,
            "INSERT INTO tiles (job_id, tile, sums, passes) VALUES ('job-1-x', 0, ?1, 2)",
        );
        {
            let (store, jobs) = JobStore::open(dir.path()).unwrap();
            assert_eq!(
                jobs[0].tiles,
                [CommittedTile {
                    tile: 0,
                    sums: vec![[0, 0, 0]],
                    passes: Some(2),
                    aovs: None,
                    stopped_at: None,
                }]
            );
            store.post(Op::Tiles {
                id: "job-1-x".into(),
                tiles: vec![tile_with_aovs()],
            });
            store.flush();
        }
        let (_store, jobs) = JobStore::open(dir.path()).unwrap();
        assert_eq!(jobs[0].tiles.len(), 2);
        assert_eq!(jobs[0].tiles[1], tile_with_aovs());
        let c = Connection::open(&db).unwrap();
        let v: u32 = c
            .pragma_query_value(None, "user_version", |r| r.get(0))
            .unwrap();
        assert_eq!(v, SCHEMA_VERSION);
    }

    #[test]
    fn a_second_coordinator_is_refused_naming_the_lock() {
        let dir = tempfile::tempdir().unwrap();
        let (first, _) = JobStore::open(dir.path()).unwrap();
        let err = JobStore::open(dir.path()).unwrap_err();
        let msg = err.to_string();
        assert!(matches!(err, StoreError::Locked { .. }), "{msg}");
        assert!(
            msg.contains(&dir.path().join(LOCK_FILE).display().to_string())
                && msg.contains(&format!("pid {}", std::process::id()))
                && !msg.contains('\n'),
            "{msg}"
        );
        drop(first);
        JobStore::open(dir.path()).expect("free again once the first one is gone");
    }

    #[test]
    fn a_damaged_database_is_an_error_and_nothing_is_deleted() {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join(DB_FILE);
        let junk: Vec<u8> = (0..8192u32).map(|i| (i * 7919 % 251) as u8).collect();
        std::fs::write(&db, &junk).unwrap();
        let err = JobStore::open(dir.path()).unwrap_err();
        let msg = err.to_string();
        assert!(matches!(err, StoreError::Corrupt { .. }), "{msg}");
        assert!(
            msg.contains(&db.display().to_string()) && !msg.contains('\n'),
            "{msg}"
        );
        assert_eq!(std::fs::read(&db).unwrap(), junk, "the file is untouched");
        assert_eq!(files(dir.path()), [IMAGES_DIR, DB_FILE, LOCK_FILE]);
    }

    #[test]
    fn another_programs_database_is_not_taken() {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join(DB_FILE);
        let c = Connection::open(&db).unwrap();
        c.execute_batch("CREATE TABLE t (x); INSERT INTO t VALUES (1);")
            .unwrap();
        drop(c);
        let err = JobStore::open(dir.path()).unwrap_err();
        assert!(err.to_string().contains("not a dray job store"), "{err}");
        let c = Connection::open(&db).unwrap();
        let n: i64 = c
            .query_row("SELECT count(*) FROM t", [], |r| r.get(0))
            .unwrap();
        assert_eq!(n, 1, "its data is untouched");
    }

    #[test]
    fn a_schema_1_store_is_migrated_and_its_tiles_count_as_complete() {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join(DB_FILE);
        old_store(
            &db,
            &SCHEMA.replace(
                "    passes INTEGER,                   -- progressive passes in the sums; NULL: every pass\n",
                "",
            ),
            1,
            "INSERT INTO tiles (job_id, tile, sums) VALUES ('job-1-x', 0, ?1)",
        );
        let (_store, jobs) = JobStore::open(dir.path()).unwrap();
        assert_eq!(jobs.len(), 1);
        assert_eq!(
            jobs[0].tiles,
            [CommittedTile {
                tile: 0,
                sums: vec![[0, 0, 0]],
                passes: None,
                aovs: None,
                stopped_at: None,
            }]
        );
        let c = Connection::open(&db).unwrap();
        let v: u32 = c
            .pragma_query_value(None, "user_version", |r| r.get(0))
            .unwrap();
        assert_eq!(v, SCHEMA_VERSION);
    }

    #[test]
    fn a_store_from_a_newer_dray_is_refused_unchanged() {
        let dir = tempfile::tempdir().unwrap();
        {
            let (store, _) = JobStore::open(dir.path()).unwrap();
            store.post(Op::Insert {
                id: "job-1-x".into(),
                spec: spec(),
                submitted_ms: 1,
            });
        }
        let db = dir.path().join(DB_FILE);
        let c = Connection::open(&db).unwrap();
        c.pragma_update(None, "user_version", SCHEMA_VERSION + 1)
            .unwrap();
        drop(c);
        let err = JobStore::open(dir.path()).unwrap_err();
        let msg = err.to_string();
        assert!(
            matches!(err, StoreError::Newer { found, .. } if found == SCHEMA_VERSION + 1),
            "{msg}"
        );
        assert!(
            msg.contains(&db.display().to_string()) && !msg.contains('\n'),
            "{msg}"
        );
        let c = Connection::open(&db).unwrap();
        assert!(has_job(&c, "job-1-x").unwrap(), "its jobs are still there");
        let v: u32 = c
            .pragma_query_value(None, "user_version", |r| r.get(0))
            .unwrap();
        assert_eq!(v, SCHEMA_VERSION + 1);
    }
}
