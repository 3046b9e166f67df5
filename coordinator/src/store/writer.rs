//! The store's writer: one OS thread that owns the database connection and applies what
//! the coordinator posts, in the order posted, a batch of everything waiting at a time in
//! one transaction. Posting is a channel send, so a job's actor never waits for the disk
//! while it counts reports; a tile committed in memory reaches the disk a moment later,
//! and a tile lost in that moment is only traced again.
//!
//! An image is written to its file (atomically, by [`super::JobStore::keep_image`])
//! before the job is called SUCCEEDED and before the transaction that names it, so the
//! database never points at a missing or half-written image; a dropped image's file is
//! removed after the transaction that forgets it.

use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::mpsc::{Receiver, Sender};

use dray_proto::v1::JobState;
use prost::Message;
use rusqlite::{Connection, Transaction, params};

use super::op::{Confirm, Op};

/// Most operations in one transaction.
const BATCH: usize = 4096;

/// The writer thread and its mailbox.
pub(crate) struct Writer {
    tx: Sender<Op>,
    thread: std::thread::JoinHandle<()>,
}

/// Why the last transaction failed, until one succeeds again: what SubmitJob tells a
/// client instead of accepting a job the store cannot keep (issue 45, item 7: on a full
/// disk every submit succeeded and the jobs were gone after a restart).
pub(crate) type Health = Arc<std::sync::Mutex<Option<String>>>;

impl Writer {
    /// Start the thread over `conn` (the database at `path`), writing images into
    /// `images`, holding `lock` for as long as it runs.
    pub(crate) fn spawn(
        conn: Connection,
        path: PathBuf,
        images: PathBuf,
        lock: File,
        health: Health,
    ) -> std::io::Result<Writer> {
        let (tx, rx) = std::sync::mpsc::channel();
        let thread = std::thread::Builder::new()
            .name("dray-job-store".into())
            .spawn(move || {
                let _lock = lock;
                run(conn, &path, &images, &rx, &health);
            })?;
        Ok(Writer { tx, thread })
    }

    /// Queue `op`.
    pub(crate) fn post(&self, op: Op) {
        let _ = self.tx.send(op);
    }

    /// Write what is queued, then end the thread (releasing the lock).
    pub(crate) fn stop(self) {
        drop(self.tx);
        if self.thread.join().is_err() {
            tracing::error!("the job store's writer thread panicked");
        }
    }
}

fn run(mut conn: Connection, path: &Path, images: &Path, rx: &Receiver<Op>, health: &Health) {
    let mut failed_since_flush = false;
    while let Ok(first) = rx.recv() {
        let mut batch = vec![first];
        while batch.len() < BATCH {
            match rx.try_recv() {
                Ok(op) => batch.push(op),
                Err(_) => break,
            }
        }
        let (failed, flushes) = write_batch(&mut conn, path, images, batch);
        // A flush confirms every operation posted before it, and those may have been in
        // an earlier batch (the thread takes what is waiting): it answers true only when
        // no batch failed since the last flush was answered.
        failed_since_flush |= failed.is_some();
        if !flushes.is_empty() {
            for f in flushes {
                f.send(!failed_since_flush);
            }
            failed_since_flush = false;
        }
        *dray_sync::lock(health) = failed;
    }
}

/// The image file name of job `id`.
pub(crate) fn image_name(id: &str) -> String {
    format!("{id}.film")
}

/// Write `batch` in one transaction: `Some(why)` when it failed (nothing of it kept),
/// and the flushes it held, to be answered by the caller.
fn write_batch(
    conn: &mut Connection,
    path: &Path,
    images: &Path,
    batch: Vec<Op>,
) -> (Option<String>, Vec<Confirm>) {
    let mut flushes = Vec::new();
    let mut removed = Vec::new();
    let result = (|| -> rusqlite::Result<()> {
        let tx = conn.transaction()?;
        for op in batch {
            match op {
                Op::Flush(reply) => flushes.push(reply),
                Op::Dropped { id, why } => {
                    tx.execute(
                        "UPDATE jobs SET image = NULL, dropped = ?2 WHERE id = ?1",
                        params![id, why],
                    )?;
                    removed.push(images.join(image_name(&id)));
                }
                op => apply(&tx, op)?,
            }
        }
        tx.commit()
    })();
    match result {
        Ok(()) => {
            for f in removed {
                if let Err(e) = std::fs::remove_file(&f)
                    && e.kind() != std::io::ErrorKind::NotFound
                {
                    tracing::warn!("cannot remove the dropped image {}: {e}", f.display());
                }
            }
            (None, flushes)
        }
        Err(e) => {
            tracing::error!(
                "cannot write to the job store {}: {e} (those changes are not kept)",
                path.display()
            );
            (
                Some(format!(
                    "cannot write to the job store {}: {e}",
                    path.display()
                )),
                flushes,
            )
        }
    }
}

fn apply(tx: &Transaction<'_>, op: Op) -> rusqlite::Result<()> {
    match op {
        Op::Nothing | Op::Flush(_) | Op::Dropped { .. } => {}
        op @ (Op::Event { .. } | Op::RetriedFrom { .. }) => super::events::apply(tx, op)?,
        Op::Insert {
            id,
            spec,
            submitted_ms,
        } => {
            tx.execute(
                "INSERT OR IGNORE INTO jobs (id, spec, label, state, submitted_ms) \
                 VALUES (?1, ?2, ?3, ?4, ?5)",
                params![
                    id,
                    spec.encode_to_vec(),
                    spec.label,
                    JobState::Queued as i32,
                    submitted_ms
                ],
            )?;
        }
        Op::Resolved { id, spec } => {
            tx.execute(
                "UPDATE jobs SET resolved = ?2 WHERE id = ?1",
                params![id, spec.encode_to_vec()],
            )?;
        }
        Op::State { id, state } => {
            // An ended job keeps its ending.
            tx.execute(
                "UPDATE jobs SET state = ?2 WHERE id = ?1 AND state NOT IN (?3, ?4, ?5)",
                params![
                    id,
                    state as i32,
                    JobState::Succeeded as i32,
                    JobState::Failed as i32,
                    JobState::Cancelled as i32
                ],
            )?;
        }
        Op::Attempt { id, attempt } => {
            tx.execute(
                "UPDATE jobs SET attempt = max(coalesce(attempt, 0), ?2) WHERE id = ?1",
                params![id, attempt],
            )?;
        }
        Op::Tiles { id, tiles } => {
            let mut q = tx.prepare(
                "INSERT OR REPLACE INTO tiles (job_id, tile, sums, passes, aovs, stopped_at) \
                     VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
            )?;
            for t in tiles {
                let sums = super::image_file::words_le(t.sums.iter().flatten());
                let aovs = t
                    .aovs
                    .as_ref()
                    .map(|a| super::image_file::words_le(a.iter().flatten()));
                q.execute(params![id, t.tile, sums, t.passes, aovs, t.stopped_at])?;
            }
        }
        Op::Finish {
            id,
            state,
            error,
            finished_ms,
            elapsed_ms,
            stats,
            image,
        } => {
            let image = image.then(|| image_name(&id));
            tx.execute(
                "UPDATE jobs SET state = ?2, error = ?3, finished_ms = ?4, elapsed_ms = ?5, \
                 stats = ?6, image = ?7 WHERE id = ?1",
                params![
                    id,
                    state as i32,
                    error,
                    finished_ms,
                    elapsed_ms,
                    stats.encode_to_vec(),
                    image
                ],
            )?;
            tx.execute("DELETE FROM tiles WHERE job_id = ?1", params![id])?;
        }
    }
    Ok(())
}
