//! The job store's part of the event logs (`crate::job_events`): a table of every job's
//! events and a column naming the job a job runs again, added by schema 3. An event is
//! a row appended as it happens (through the writer, like every change); a restarted
//! coordinator reads each job's events back in the order they were written.

use dray_proto::v1::JobEvent;
use rusqlite::{Connection, Transaction, params};

use super::{StoredJob, from_millis, op::Op};

/// From schema 2 to 3 (also run on a new database, after the schema of version 2): the
/// events table and the lineage column.
pub const MIGRATE_2_TO_3: &str = "
CREATE TABLE events (
    seq INTEGER PRIMARY KEY,          -- the order events were written in
    job_id TEXT NOT NULL,
    at_ms INTEGER NOT NULL,
    kind INTEGER NOT NULL,            -- dray.v1.JobEventKind
    message TEXT NOT NULL
);
CREATE INDEX events_by_job ON events (job_id, seq);
ALTER TABLE jobs ADD COLUMN retried_from TEXT;
";

/// Apply an [`Op::Event`] or [`Op::RetriedFrom`] (other operations are not this file's).
pub(super) fn apply(tx: &Transaction<'_>, op: Op) -> rusqlite::Result<()> {
    match op {
        Op::Event {
            id,
            at_ms,
            kind,
            message,
        } => {
            tx.execute(
                "INSERT INTO events (job_id, at_ms, kind, message) VALUES (?1, ?2, ?3, ?4)",
                params![id, at_ms, kind, message],
            )?;
        }
        Op::RetriedFrom { id, from } => {
            tx.execute(
                "UPDATE jobs SET retried_from = ?2 WHERE id = ?1",
                params![id, from],
            )?;
        }
        _ => {}
    }
    Ok(())
}

/// Read every job's events and lineage into `jobs`.
pub(super) fn load(conn: &Connection, jobs: &mut [StoredJob]) -> rusqlite::Result<()> {
    let mut events =
        conn.prepare("SELECT at_ms, kind, message FROM events WHERE job_id = ?1 ORDER BY seq")?;
    let mut lineage = conn.prepare("SELECT retried_from FROM jobs WHERE id = ?1")?;
    for j in jobs.iter_mut() {
        j.events = events
            .query_map([&j.id], |r| {
                Ok(JobEvent {
                    at: Some(from_millis(r.get(0)?).into()),
                    kind: r.get(1)?,
                    message: r.get(2)?,
                })
            })?
            .collect::<rusqlite::Result<Vec<_>>>()?;
        j.retried_from = lineage.query_row([&j.id], |r| r.get::<_, Option<String>>(0))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use dray_proto::v1::{JobEventKind, JobSpec};

    use crate::store::{JobStore, Op};

    /// Events and lineage come back after the store is opened again, in order.
    #[test]
    fn events_and_lineage_survive_a_reopen() {
        let dir = tempfile::tempdir().unwrap();
        {
            let (store, _) = JobStore::open(dir.path()).unwrap();
            for id in ["a", "b"] {
                let spec = JobSpec::default();
                store.post(Op::Insert {
                    id: id.into(),
                    spec,
                    submitted_ms: 1,
                });
            }
            for (id, kind, msg) in [
                ("a", JobEventKind::Queued, "queued"),
                ("b", JobEventKind::Queued, "queued b"),
                ("a", JobEventKind::Failed, "it broke"),
                ("b", JobEventKind::Retried, "retried from a"),
            ] {
                store.post(Op::Event {
                    id: id.into(),
                    at_ms: 5,
                    kind: kind as i32,
                    message: msg.into(),
                });
            }
            store.post(Op::RetriedFrom {
                id: "b".into(),
                from: "a".into(),
            });
            store.flush();
        }
        let (_store, jobs) = JobStore::open(dir.path()).unwrap();
        let msgs =
            |i: usize| -> Vec<&str> { jobs[i].events.iter().map(|e| e.message.as_str()).collect() };
        assert_eq!(msgs(0), ["queued", "it broke"]);
        assert_eq!(msgs(1), ["queued b", "retried from a"]);
        assert_eq!(jobs[0].events[1].kind, JobEventKind::Failed as i32);
        assert_eq!(jobs[0].retried_from, None);
        assert_eq!(jobs[1].retried_from.as_deref(), Some("a"));
    }
}
