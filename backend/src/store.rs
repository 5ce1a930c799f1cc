//! Durable store: embedded SQLite (WAL).
//!
//! Tables:
//! * `runs`: one row per run with its config, status, counters and the latest
//!   checkpoint (serialized tuner + device state, RNG included).
//! * `iterations`: one row per committed iteration (`seq` = 0, 1, 2, … per run)
//!   holding the [`spintune::protocol::IterationRecord`] as JSON.
//!
//! [`Store::commit_iteration`] writes the record and the checkpoint in one
//! transaction; the run task broadcasts only after it returns. With WAL and
//! `synchronous = NORMAL` a committed transaction survives a crash or `kill -9`
//! of the process (not necessarily a power loss).
//!
//! Write transactions are `IMMEDIATE`: they take the write lock before their
//! first read, so a writer in another process (or a schema change) between
//! a transaction's read and its write waits for the busy timeout instead of
//! failing at once with a stale snapshot (`SQLITE_BUSY_SNAPSHOT`).
//!
//! The store is synchronous; async callers use `tokio::task::spawn_blocking`.

use std::path::Path;
use std::sync::Mutex;

use rusqlite::{params, Connection, OptionalExtension, TransactionBehavior};
use spintune::protocol::{RunStatus, RunSummary};

/// Store errors (SQLite or corrupt rows).
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// SQLite failed.
    #[error("database error: {0}")]
    Sqlite(#[from] rusqlite::Error),
    /// A stored JSON value could not be decoded.
    #[error("corrupt stored value: {0}")]
    Json(#[from] serde_json::Error),
    /// No such run.
    #[error("no run with id {0}")]
    NotFound(u64),
    /// The store was written by a newer release (its schema version is
    /// higher than this release reads); nothing was changed.
    #[error(
        "this store has schema version {found}, this release of spintune reads up to {supported}: it was written by a newer spintune; use that release (nothing was changed)"
    )]
    NewerSchema {
        /// The store's `PRAGMA user_version`.
        found: i64,
        /// [`SCHEMA_VERSION`].
        supported: i64,
    },
    /// The writer's task generation is no longer the run's: another task
    /// has taken the run over. Nothing was written; the writer must exit.
    #[error("run {run}: task generation {generation} is stale (the run is now driven by generation {current})")]
    Stale {
        /// Run id.
        run: u64,
        /// The writer's generation.
        generation: u64,
        /// The run's present generation.
        current: u64,
    },
    /// An iteration was committed out of order.
    #[error("run {run}: expected iteration seq {expected}, got {got}")]
    OutOfOrder {
        /// Run id.
        run: u64,
        /// Next expected seq.
        expected: u64,
        /// Seq that was offered.
        got: u64,
    },
}

/// A run row (without its checkpoint).
#[derive(Debug, Clone)]
pub struct StoredRun {
    /// Summary as listed.
    pub summary: RunSummary,
    /// The run config as JSON (a [`crate::config::RunConfig`]).
    pub config_json: String,
    /// Why the row could not be read (`Some`: the run is quarantined, its
    /// summary holds only the id; the other runs are served).
    pub unreadable: Option<String>,
}

impl StoredRun {
    fn quarantined(id: u64, error: String) -> Self {
        Self {
            summary: RunSummary {
                id,
                name: format!("unreadable run {id}"),
                status: RunStatus::Failed {
                    message: format!("quarantined: the stored run is unreadable ({error})"),
                },
                iterations: 0,
                lab_seconds: 0.0,
                tuned: false,
                driver: None,
            },
            config_json: String::new(),
            unreadable: Some(error),
        }
    }
}

/// A page of iteration summaries ([`Store::summary_page`]).
#[derive(Debug, Clone, Default)]
pub struct SummaryPage {
    /// Seq of the first record (`None`: empty page).
    pub first_seq: Option<u64>,
    /// Summary records as JSON, oldest first, contiguous.
    pub records: Vec<String>,
    /// Stored iterations older than the page exist.
    pub more_before: bool,
}

/// Schema version of the store this release writes, kept in SQLite's
/// `PRAGMA user_version` (read by the server and by Python's `open_store`,
/// which refuse a newer one with a clear error). History: 0 — unversioned
/// stores of earlier releases (the `runs.generation` column may be missing);
/// 1 — `runs` with `generation`, `iterations` keyed by (run, seq).
pub const SCHEMA_VERSION: i64 = 1;

/// The SQLite store: one connection for writes, one for reads.
pub struct Store {
    writer: Mutex<Connection>,
    reader: Mutex<Connection>,
}

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS runs (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    name        TEXT    NOT NULL,
    config      TEXT    NOT NULL,
    status      TEXT    NOT NULL,
    iterations  INTEGER NOT NULL DEFAULT 0,
    lab_seconds REAL    NOT NULL DEFAULT 0,
    tuned       INTEGER NOT NULL DEFAULT 0,
    checkpoint  TEXT    NOT NULL,
    created_unix_s REAL NOT NULL,
    generation  INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS iterations (
    run_id INTEGER NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
    seq    INTEGER NOT NULL,
    record TEXT    NOT NULL,
    PRIMARY KEY (run_id, seq)
) WITHOUT ROWID;
";

fn open_conn(path: &Path) -> Result<Connection, StoreError> {
    let conn = Connection::open(path)?;
    conn.busy_timeout(std::time::Duration::from_secs(10))?;
    conn.pragma_update(None, "journal_mode", "WAL")?;
    conn.pragma_update(None, "synchronous", "NORMAL")?;
    conn.pragma_update(None, "foreign_keys", "ON")?;
    Ok(conn)
}

fn now_unix_s() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// The driver named by a stored run config (`backend.driver`, default
/// `simulator`); `None` if the config is not readable JSON.
fn stored_driver(config_json: &str) -> Option<String> {
    let v: serde_json::Value = serde_json::from_str(config_json).ok()?;
    let backend = v.get("backend")?;
    Some(
        backend
            .get("driver")
            .and_then(|d| d.as_str())
            .unwrap_or("simulator")
            .to_string(),
    )
}

fn summary_from_row(row: &rusqlite::Row<'_>) -> rusqlite::Result<(RunSummary, String, String)> {
    let id: i64 = row.get(0)?;
    let name: String = row.get(1)?;
    let status: String = row.get(2)?;
    let iterations: i64 = row.get(3)?;
    let lab_seconds: f64 = row.get(4)?;
    let tuned: bool = row.get(5)?;
    let config: String = row.get(6)?;
    Ok((
        RunSummary {
            id: id as u64,
            name,
            status: RunStatus::Running, // replaced by the caller from `status`
            iterations: iterations as u64,
            lab_seconds,
            tuned,
            driver: stored_driver(&config),
        },
        status,
        config,
    ))
}

/// A stored status; an unreadable one becomes `failed` with the reason
/// (resumable from the last checkpoint) instead of an error for every caller.
fn decode_status(text: &str) -> RunStatus {
    serde_json::from_str(text).unwrap_or_else(|e| RunStatus::Failed {
        message: format!(
            "unreadable stored status {text:?} ({e}); resume retries from the last checkpoint"
        ),
    })
}

impl Store {
    /// Open (or create) the database at `path`.
    pub fn open(path: &Path) -> Result<Self, StoreError> {
        let writer = open_conn(path)?;
        let found: i64 = writer.pragma_query_value(None, "user_version", |r| r.get(0))?;
        if found > SCHEMA_VERSION {
            return Err(StoreError::NewerSchema {
                found,
                supported: SCHEMA_VERSION,
            });
        }
        writer.execute_batch(SCHEMA)?;
        if found < 1 {
            // Stores written before task generations existed lack the column.
            let has_generation = writer
                .prepare("SELECT 1 FROM pragma_table_info('runs') WHERE name = 'generation'")?
                .exists([])?;
            if !has_generation {
                writer.execute_batch(
                    "ALTER TABLE runs ADD COLUMN generation INTEGER NOT NULL DEFAULT 0",
                )?;
            }
        }
        if found != SCHEMA_VERSION {
            writer.pragma_update(None, "user_version", SCHEMA_VERSION)?;
        }
        let reader = open_conn(path)?;
        Ok(Self {
            writer: Mutex::new(writer),
            reader: Mutex::new(reader),
        })
    }

    fn w(&self) -> std::sync::MutexGuard<'_, Connection> {
        self.writer.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn r(&self) -> std::sync::MutexGuard<'_, Connection> {
        self.reader.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Create a run with its initial checkpoint; returns its id.
    pub fn create_run(
        &self,
        name: &str,
        config_json: &str,
        status: &RunStatus,
        checkpoint_json: &str,
    ) -> Result<u64, StoreError> {
        let conn = self.w();
        conn.execute(
            "INSERT INTO runs (name, config, status, checkpoint, created_unix_s) VALUES (?1, ?2, ?3, ?4, ?5)",
            params![name, config_json, serde_json::to_string(status)?, checkpoint_json, now_unix_s()],
        )?;
        Ok(conn.last_insert_rowid() as u64)
    }

    /// Take run `id` over for a new task: bump and return its generation.
    /// Every later write of an older generation fails with
    /// [`StoreError::Stale`] (one driver per run, also across processes).
    pub fn claim(&self, id: u64) -> Result<u64, StoreError> {
        let conn = self.w();
        let n = conn.execute(
            "UPDATE runs SET generation = generation + 1 WHERE id = ?1",
            params![id as i64],
        )?;
        if n == 0 {
            return Err(StoreError::NotFound(id));
        }
        let g: i64 = conn.query_row(
            "SELECT generation FROM runs WHERE id = ?1",
            params![id as i64],
            |r| r.get(0),
        )?;
        Ok(g as u64)
    }

    fn check_generation(
        conn: &Connection,
        id: u64,
        generation: Option<u64>,
    ) -> Result<(), StoreError> {
        let current: Option<i64> = conn
            .query_row(
                "SELECT generation FROM runs WHERE id = ?1",
                params![id as i64],
                |r| r.get(0),
            )
            .optional()?;
        let current = current.ok_or(StoreError::NotFound(id))? as u64;
        match generation {
            Some(g) if g != current => Err(StoreError::Stale {
                run: id,
                generation: g,
                current,
            }),
            _ => Ok(()),
        }
    }

    /// Commit iteration `seq` of run `id` and the checkpoint taken right after it,
    /// in one transaction. With `generation`, only if the run is still driven
    /// by that task generation ([`Store::claim`]).
    #[allow(clippy::too_many_arguments)]
    pub fn commit_iteration(
        &self,
        id: u64,
        generation: Option<u64>,
        seq: u64,
        record_json: &str,
        checkpoint_json: &str,
        lab_seconds: f64,
        tuned: bool,
    ) -> Result<(), StoreError> {
        let mut conn = self.w();
        let tx = conn.transaction_with_behavior(TransactionBehavior::Immediate)?;
        Self::check_generation(&tx, id, generation)?;
        let expected: Option<i64> = tx
            .query_row(
                "SELECT iterations FROM runs WHERE id = ?1",
                params![id as i64],
                |r| r.get(0),
            )
            .optional()?;
        let expected = expected.ok_or(StoreError::NotFound(id))? as u64;
        if expected != seq {
            return Err(StoreError::OutOfOrder {
                run: id,
                expected,
                got: seq,
            });
        }
        tx.execute(
            "INSERT INTO iterations (run_id, seq, record) VALUES (?1, ?2, ?3)",
            params![id as i64, seq as i64, record_json],
        )?;
        tx.execute(
            "UPDATE runs SET iterations = ?2, lab_seconds = ?3, tuned = ?4, checkpoint = ?5 WHERE id = ?1",
            params![id as i64, (seq + 1) as i64, lab_seconds, tuned, checkpoint_json],
        )?;
        tx.commit()?;
        Ok(())
    }

    /// Replace the checkpoint of run `id` (e.g. after a target change
    /// between iterations); with `generation`, only for that task generation.
    pub fn save_checkpoint(
        &self,
        id: u64,
        generation: Option<u64>,
        checkpoint_json: &str,
    ) -> Result<(), StoreError> {
        let mut conn = self.w();
        let tx = conn.transaction_with_behavior(TransactionBehavior::Immediate)?;
        Self::check_generation(&tx, id, generation)?;
        tx.execute(
            "UPDATE runs SET checkpoint = ?2 WHERE id = ?1",
            params![id as i64, checkpoint_json],
        )?;
        tx.commit()?;
        Ok(())
    }

    /// Set the status of run `id`; with `generation`, only for that task generation.
    pub fn set_status(
        &self,
        id: u64,
        generation: Option<u64>,
        status: &RunStatus,
    ) -> Result<(), StoreError> {
        let mut conn = self.w();
        let tx = conn.transaction_with_behavior(TransactionBehavior::Immediate)?;
        Self::check_generation(&tx, id, generation)?;
        tx.execute(
            "UPDATE runs SET status = ?2 WHERE id = ?1",
            params![id as i64, serde_json::to_string(status)?],
        )?;
        tx.commit()?;
        Ok(())
    }

    /// The latest checkpoint of run `id`.
    pub fn checkpoint(&self, id: u64) -> Result<String, StoreError> {
        self.r()
            .query_row(
                "SELECT checkpoint FROM runs WHERE id = ?1",
                params![id as i64],
                |r| r.get(0),
            )
            .optional()?
            .ok_or(StoreError::NotFound(id))
    }

    /// All runs, oldest first.
    pub fn list_runs(&self) -> Result<Vec<StoredRun>, StoreError> {
        let conn = self.r();
        let mut stmt = conn.prepare(
            "SELECT id, name, status, iterations, lab_seconds, tuned, config FROM runs ORDER BY id",
        )?;
        // The id is the INTEGER PRIMARY KEY (always readable); the rest may not be.
        let rows = stmt.query_map([], |row| {
            let id: i64 = row.get(0)?;
            Ok((id as u64, summary_from_row(row)))
        })?;
        let mut out = Vec::new();
        for row in rows {
            // One corrupt row must not keep the other runs (or the server)
            // down: it is listed as quarantined with its id and the error.
            let (id, row) = row?;
            out.push(match row {
                Ok((mut summary, status, config_json)) => {
                    summary.status = decode_status(&status);
                    StoredRun {
                        summary,
                        config_json,
                        unreadable: None,
                    }
                }
                Err(e) => StoredRun::quarantined(id, e.to_string()),
            });
        }
        Ok(out)
    }

    /// One run.
    pub fn get_run(&self, id: u64) -> Result<StoredRun, StoreError> {
        let conn = self.r();
        let row = conn
            .query_row(
                "SELECT id, name, status, iterations, lab_seconds, tuned, config FROM runs WHERE id = ?1",
                params![id as i64],
                summary_from_row,
            )
            .optional()?
            .ok_or(StoreError::NotFound(id))?;
        let (mut summary, status, config_json) = row;
        summary.status = decode_status(&status);
        Ok(StoredRun {
            summary,
            config_json,
            unreadable: None,
        })
    }

    /// Stored iteration records (JSON) of run `id` with `seq >= from`, at most `limit`.
    pub fn iterations_json(
        &self,
        id: u64,
        from: u64,
        limit: Option<u64>,
    ) -> Result<Vec<String>, StoreError> {
        let conn = self.r();
        let mut stmt = conn.prepare_cached(
            "SELECT record FROM iterations WHERE run_id = ?1 AND seq >= ?2 ORDER BY seq LIMIT ?3",
        )?;
        let limit = limit.map(|l| l.min(i64::MAX as u64) as i64).unwrap_or(-1);
        let rows = stmt.query_map(
            params![id as i64, from.min(i64::MAX as u64) as i64, limit],
            |r| r.get::<_, String>(0),
        )?;
        Ok(rows.collect::<Result<Vec<_>, _>>()?)
    }

    /// A page of stored iteration *summaries* of run `id` (each record with
    /// `scans` replaced by `[]`, done by SQLite's JSON functions so no record
    /// is parsed here): the newest at most `limit` with `seq < before`
    /// (`None`: the newest overall), oldest first. Seq is contiguous from 0
    /// ([`Store::commit_iteration`] refuses gaps), so `more_before` is
    /// whether the page does not reach seq 0.
    pub fn summary_page(
        &self,
        id: u64,
        before: Option<u64>,
        limit: u64,
    ) -> Result<SummaryPage, StoreError> {
        let conn = self.r();
        let before_i = before.map_or(i64::MAX, |b| b.min(i64::MAX as u64) as i64);
        let mut stmt = conn.prepare_cached(
            "SELECT seq, json_set(record, '$.scans', json('[]')) FROM iterations \
             WHERE run_id = ?1 AND seq < ?2 ORDER BY seq DESC LIMIT ?3",
        )?;
        let rows = stmt.query_map(
            params![id as i64, before_i, limit.min(i64::MAX as u64) as i64],
            |r| Ok((r.get::<_, i64>(0)?, r.get::<_, String>(1)?)),
        )?;
        let mut page = rows.collect::<Result<Vec<_>, _>>()?;
        page.reverse();
        let lowest = page.first().map_or(before_i, |(seq, _)| *seq);
        let more_before: bool = conn
            .prepare_cached(
                "SELECT EXISTS(SELECT 1 FROM iterations WHERE run_id = ?1 AND seq < ?2)",
            )?
            .query_row(params![id as i64, lowest], |r| r.get(0))?;
        Ok(SummaryPage {
            first_seq: page.first().map(|(seq, _)| *seq as u64),
            records: page.into_iter().map(|(_, r)| r).collect(),
            more_before,
        })
    }

    /// Stored iteration summaries (JSON, `scans` = `[]`) of run `id` with
    /// `seq >= from`, at most `limit`, oldest first.
    pub fn summaries_json(
        &self,
        id: u64,
        from: u64,
        limit: u64,
    ) -> Result<Vec<String>, StoreError> {
        let conn = self.r();
        let mut stmt = conn.prepare_cached(
            "SELECT json_set(record, '$.scans', json('[]')) FROM iterations \
             WHERE run_id = ?1 AND seq >= ?2 ORDER BY seq LIMIT ?3",
        )?;
        let rows = stmt.query_map(
            params![
                id as i64,
                from.min(i64::MAX as u64) as i64,
                limit.min(i64::MAX as u64) as i64
            ],
            |r| r.get::<_, String>(0),
        )?;
        Ok(rows.collect::<Result<Vec<_>, _>>()?)
    }

    /// The stored record (JSON) of iteration `seq` of run `id`, if any.
    pub fn iteration_json(&self, id: u64, seq: u64) -> Result<Option<String>, StoreError> {
        Ok(self
            .r()
            .prepare_cached("SELECT record FROM iterations WHERE run_id = ?1 AND seq = ?2")?
            .query_row(params![id as i64, seq.min(i64::MAX as u64) as i64], |r| {
                r.get(0)
            })
            .optional()?)
    }

    /// Delete run `id` and its iterations.
    pub fn delete_run(&self, id: u64) -> Result<(), StoreError> {
        let mut conn = self.w();
        let tx = conn.transaction_with_behavior(TransactionBehavior::Immediate)?;
        tx.execute(
            "DELETE FROM iterations WHERE run_id = ?1",
            params![id as i64],
        )?;
        let n = tx.execute("DELETE FROM runs WHERE id = ?1", params![id as i64])?;
        tx.commit()?;
        if n == 0 {
            return Err(StoreError::NotFound(id));
        }
        Ok(())
    }

    /// Mark every run left `running`, `stepping` or `paused` by a previous
    /// process as `interrupted` (a `stopping` one as `stopped`: its stop was
    /// acknowledged); returns the ids marked interrupted. Faulted runs keep
    /// their fault. Call once at startup.
    pub fn mark_interrupted(&self) -> Result<Vec<u64>, StoreError> {
        let runs = self.list_runs()?;
        let mut ids = Vec::new();
        for r in runs.into_iter().filter(|r| r.unreadable.is_none()) {
            match r.summary.status {
                RunStatus::Running | RunStatus::Stepping | RunStatus::Paused => {
                    self.set_status(r.summary.id, None, &RunStatus::Interrupted)?;
                    ids.push(r.summary.id);
                }
                RunStatus::Stopping => {
                    self.set_status(r.summary.id, None, &RunStatus::Stopped)?;
                }
                _ => {}
            }
        }
        Ok(ids)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_schema_version_is_written_migrated_and_a_newer_one_refused() {
        let dir = std::env::temp_dir().join(format!("spintune-store-v-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("v.db");
        let _ = std::fs::remove_file(&path);
        // an unversioned store of an earlier release, without `generation`
        {
            let c = Connection::open(&path).unwrap();
            c.execute_batch(&SCHEMA.replace(",\n    generation  INTEGER NOT NULL DEFAULT 0", ""))
                .unwrap();
            let cols: i64 = c
                .query_row(
                    "SELECT count(*) FROM pragma_table_info('runs') WHERE name='generation'",
                    [],
                    |r| r.get(0),
                )
                .unwrap();
            assert_eq!(cols, 0, "the fixture must lack the column");
        }
        let s = Store::open(&path).unwrap();
        let id = s.create_run("a", "{}", &RunStatus::Running, "{}").unwrap();
        assert_eq!(s.claim(id).unwrap(), 1, "migrated: generations work");
        drop(s);
        let v: i64 = Connection::open(&path)
            .unwrap()
            .pragma_query_value(None, "user_version", |r| r.get(0))
            .unwrap();
        assert_eq!(v, SCHEMA_VERSION);
        // a store from a newer release is refused, untouched
        Connection::open(&path)
            .unwrap()
            .pragma_update(None, "user_version", SCHEMA_VERSION + 1)
            .unwrap();
        let e = Store::open(&path)
            .err()
            .expect("a newer store must be refused");
        assert!(matches!(e, StoreError::NewerSchema { .. }), "{e}");
        assert!(e.to_string().contains("newer spintune"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn commit_and_read_back() {
        let dir = std::env::temp_dir().join(format!("spintune-store-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("t.db");
        let _ = std::fs::remove_file(&path);
        let s = Store::open(&path).unwrap();
        let id = s
            .create_run("a", "{}", &RunStatus::Running, "{\"c\":0}")
            .unwrap();
        let g = s.claim(id).unwrap();
        s.commit_iteration(id, Some(g), 0, "{\"k\":0}", "{\"c\":1}", 1.5, false)
            .unwrap();
        assert!(matches!(
            s.commit_iteration(id, Some(g), 2, "{}", "{}", 0.0, false),
            Err(StoreError::OutOfOrder { expected: 1, .. })
        ));
        // another task takes the run over: the old one can no longer write
        let g2 = s.claim(id).unwrap();
        assert_eq!(g2, g + 1);
        assert!(matches!(
            s.commit_iteration(id, Some(g), 1, "{}", "{}", 0.0, false),
            Err(StoreError::Stale { generation, current, .. }) if generation == g && current == g2
        ));
        assert!(matches!(
            s.set_status(id, Some(g), &RunStatus::Stopped),
            Err(StoreError::Stale { .. })
        ));
        assert!(matches!(
            s.save_checkpoint(id, Some(g), "{}"),
            Err(StoreError::Stale { .. })
        ));
        s.commit_iteration(id, Some(g2), 1, "{\"k\":1}", "{\"c\":2}", 3.0, true)
            .unwrap();
        assert_eq!(s.iterations_json(id, 1, None).unwrap(), vec!["{\"k\":1}"]);
        assert_eq!(s.checkpoint(id).unwrap(), "{\"c\":2}");
        let r = s.get_run(id).unwrap();
        assert_eq!(r.summary.iterations, 2);
        assert!(r.summary.tuned);
        assert_eq!(s.mark_interrupted().unwrap(), vec![id]);
        assert_eq!(
            s.get_run(id).unwrap().summary.status,
            RunStatus::Interrupted
        );
        // A corrupt status or a corrupt row keeps the others readable.
        let other = s.create_run("b", "{}", &RunStatus::Paused, "{}").unwrap();
        let third = s.create_run("c", "{}", &RunStatus::Paused, "{}").unwrap();
        s.w()
            .execute(
                "UPDATE runs SET status = 'garbage' WHERE id = ?1",
                params![other as i64],
            )
            .unwrap();
        s.w()
            .execute(
                "UPDATE runs SET iterations = 'not a number' WHERE id = ?1",
                params![third as i64],
            )
            .unwrap();
        let listed = s.list_runs().unwrap();
        let b = listed.iter().find(|r| r.summary.id == other).unwrap();
        assert!(
            matches!(&b.summary.status, RunStatus::Failed { message } if message.contains("unreadable")),
            "{:?}",
            b.summary.status
        );
        assert!(b.summary.status.is_resumable());
        let c = listed.iter().find(|r| r.summary.id == third).unwrap();
        assert!(
            c.unreadable.is_some(),
            "a corrupt row is listed as unreadable"
        );
        assert!(listed.iter().any(|r| r.summary.id == id));
        s.delete_run(id).unwrap();
        assert!(s.get_run(id).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
