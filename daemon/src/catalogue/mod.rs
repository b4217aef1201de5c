//! The run catalogue: every run of a runs directory in one SQLite database
//! (`RUNS_DIR/catalogue.sqlite`), for queries a directory listing cannot answer fast
//! (state, dates, plan, tag, text; paged and sorted), and the audit trail.
//!
//! The run directories stay the source of truth: the catalogue holds what their files
//! say (run.json with its state history, plan.toml, instrument.toml, annotations.json,
//! volume.json, the outputs present) and can always be rebuilt from them and from
//! `audit.jsonl` ([`Catalogue::rebuild`], `periscope catalogue rebuild`). Each row
//! keeps a stamp of the files it was read from; [`Catalogue::sync`] reads again only
//! the runs whose stamp changed (runs written by `periscope run`, by another daemon
//! version, or while the catalogue was away), so opening it after months of runs costs
//! a `stat` per run. A catalogue SQLite cannot read is set aside and rebuilt.
//!
//! | file | what it holds |
//! |---|---|
//! | `mod.rs` | [`Catalogue`]: open, migrate, sync, rebuild, index one run |
//! | `schema.rs` | the versioned migrations |
//! | `query.rs` | [`RunQuery`], [`RunRecord`], [`AuditQuery`]: filtered, sorted, paged reads |
//! | `audit.rs` | [`AuditEntry`] and the append-only `audit.jsonl` |
//!
//! Concurrency: SQLite in WAL mode with a busy timeout, so the daemon, its indexer
//! thread and CLI commands in other processes read and write at once; every write is a
//! transaction keyed by run id or audit id, so nothing is lost or written twice.
use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard};
use std::time::Duration;

use rusqlite::{Connection, OptionalExtension, params};

pub mod audit;
pub mod query;
pub mod schema;

pub use audit::{AUDIT_FILE, AuditEntry};

/// Appends `entry` to the audit trail's log (`audit.jsonl` in `runs_dir`), the record
/// of what was done, without the catalogue: a process that cannot open the catalogue
/// still records, and the catalogue takes the entry from the log at its next sync.
pub fn append_audit(runs_dir: &Path, entry: &AuditEntry) -> Result<(), CatalogueError> {
    audit::append(runs_dir, entry).map_err(|source| CatalogueError::Io {
        path: runs_dir.join(AUDIT_FILE),
        source,
    })
}
pub use query::{AuditPage, AuditQuery, OutputFile, RunPage, RunQuery, RunRecord, SortKey};

use crate::run_dir::{Annotations, DOWNLOADS, RunDir, RunInfo, file};

/// The catalogue's file name in the runs directory.
pub const CATALOGUE_FILE: &str = "catalogue.sqlite";

/// How long a write waits for another writer (another process's sync, say) before it
/// fails.
const BUSY_TIMEOUT: Duration = Duration::from_secs(10);

/// Runs indexed per transaction during a sync.
const SYNC_BATCH: usize = 500;

/// Why the catalogue could not be used.
#[derive(Debug, thiserror::Error)]
pub enum CatalogueError {
    /// SQLite refused an operation.
    #[error("run catalogue {}: {source}", path.display())]
    Sqlite {
        /// The catalogue file.
        path: PathBuf,
        /// What SQLite said.
        #[source]
        source: rusqlite::Error,
    },
    /// A file of the runs directory could not be read or written.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// What failed.
        #[source]
        source: std::io::Error,
    },
    /// The catalogue's schema cannot be brought up to date.
    #[error("run catalogue {}: {message}", path.display())]
    Schema {
        /// The catalogue file.
        path: PathBuf,
        /// Why.
        message: String,
    },
}

/// What a sync or rebuild did.
#[derive(Clone, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct SyncReport {
    /// Run directories found.
    pub runs: usize,
    /// Runs read again (new or changed).
    pub indexed: usize,
    /// Rows dropped because their directory is gone.
    pub removed: usize,
    /// Runs whose run.json could not be read (left out, with a warning).
    pub unreadable: usize,
    /// Audit entries imported from audit.jsonl.
    pub audit_imported: usize,
}

/// The run catalogue of one runs directory.
pub struct Catalogue {
    runs_dir: PathBuf,
    path: PathBuf,
    conn: Mutex<Connection>,
}

impl Catalogue {
    /// Opens (creating or migrating it) the catalogue of `runs_dir`, and syncs it with
    /// the run directories. A file SQLite cannot read as a catalogue is moved aside to
    /// `catalogue.sqlite.damaged` and rebuilt, with a warning.
    pub fn open(runs_dir: &Path) -> Result<Catalogue, CatalogueError> {
        let cat = Catalogue::open_unsynced(runs_dir)?;
        cat.sync()?;
        Ok(cat)
    }

    /// Opens and migrates the catalogue without syncing it (the sync reads every run
    /// directory's stamp; the daemon does it on its indexer thread).
    pub fn open_unsynced(runs_dir: &Path) -> Result<Catalogue, CatalogueError> {
        std::fs::create_dir_all(runs_dir).map_err(|source| CatalogueError::Io {
            path: runs_dir.to_owned(),
            source,
        })?;
        let path = runs_dir.join(CATALOGUE_FILE);
        let conn = match open_connection(&path) {
            Ok(c) => c,
            Err(Open::Refused(message)) => {
                return Err(CatalogueError::Schema { path, message });
            }
            Err(Open::Damaged(why)) => {
                let aside = runs_dir.join(format!("{CATALOGUE_FILE}.damaged"));
                tracing::warn!(
                    "run catalogue {} is damaged ({why}); moved to {} and rebuilt from the run directories",
                    path.display(),
                    aside.display()
                );
                set_aside(&path, &aside).map_err(|source| CatalogueError::Io {
                    path: path.clone(),
                    source,
                })?;
                open_connection(&path).map_err(|e| CatalogueError::Schema {
                    path: path.clone(),
                    message: match e {
                        Open::Refused(m) | Open::Damaged(m) => m,
                    },
                })?
            }
        };
        Ok(Catalogue {
            runs_dir: runs_dir.to_owned(),
            path,
            conn: Mutex::new(conn),
        })
    }

    /// Deletes the catalogue of `runs_dir` and builds it anew from the run directories
    /// and `audit.jsonl` (`periscope catalogue rebuild`). Tags, notes, state histories
    /// and the audit trail all come back: they live in the runs directory, not only in
    /// the catalogue.
    pub fn rebuild(runs_dir: &Path) -> Result<(Catalogue, SyncReport), CatalogueError> {
        // Not under a running daemon (it holds the catalogue's lock shared for its
        // life): it would keep writing to the deleted file.
        let lock_path = runs_dir.join(LOCK_FILE);
        let io = |source| CatalogueError::Io {
            path: lock_path.clone(),
            source,
        };
        std::fs::create_dir_all(runs_dir).map_err(io)?;
        let lock = lock_file(&lock_path).map_err(io)?;
        match lock.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                return Err(CatalogueError::Schema {
                    path: runs_dir.join(CATALOGUE_FILE),
                    message:
                        "a running `periscope serve` uses this runs directory: stop it before a rebuild \
                              (`periscope catalogue sync` is safe beside it)"
                            .into(),
                });
            }
            Err(std::fs::TryLockError::Error(e)) => return Err(io(e)),
        }
        let path = runs_dir.join(CATALOGUE_FILE);
        for p in [path.clone(), wal(&path, "-wal"), wal(&path, "-shm")] {
            match std::fs::remove_file(&p) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(source) => return Err(CatalogueError::Io { path: p, source }),
            }
        }
        let cat = Catalogue::open_unsynced(runs_dir)?;
        let report = cat.sync()?;
        Ok((cat, report))
    }

    /// The catalogue file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn conn(&self) -> MutexGuard<'_, Connection> {
        self.conn.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn sqlite(&self) -> impl Fn(rusqlite::Error) -> CatalogueError + '_ {
        move |source| CatalogueError::Sqlite {
            path: self.path.clone(),
            source,
        }
    }

    /// Brings the catalogue in line with the run directories: indexes runs that are
    /// new or whose files changed, drops rows whose directory is gone, and imports the
    /// audit entries appended since the last sync.
    pub fn sync(&self) -> Result<SyncReport, CatalogueError> {
        let mut report = SyncReport::default();
        // The rows first, then the directories: a run indexed in between (a submit
        // while this syncs) is in neither list, so it is neither read nor dropped.
        let known: HashMap<String, Option<String>> = {
            let conn = self.conn();
            let mut stmt = conn
                .prepare("SELECT id, stamp FROM runs")
                .map_err(self.sqlite())?;
            let rows = stmt
                .query_map([], |r| {
                    Ok((r.get::<_, String>(0)?, r.get::<_, Option<String>>(1)?))
                })
                .map_err(self.sqlite())?;
            rows.collect::<Result<_, _>>().map_err(self.sqlite())?
        };
        let entries = std::fs::read_dir(&self.runs_dir).map_err(|source| CatalogueError::Io {
            path: self.runs_dir.clone(),
            source,
        })?;
        let mut on_disk: Vec<(String, String)> = entries
            .filter_map(Result::ok)
            .filter(|e| RunDir::holds_run(&e.path()))
            .map(|e| {
                let id = e.file_name().to_string_lossy().into_owned();
                let stamp = stamp(&e.path());
                (id, stamp)
            })
            .collect();
        on_disk.sort();
        report.runs = on_disk.len();
        let changed: Vec<&String> = on_disk
            .iter()
            .filter(|(id, stamp)| known.get(id).is_none_or(|k| k.as_deref() != Some(stamp.as_str())))
            .map(|(id, _)| id)
            .collect();
        for batch in changed.chunks(SYNC_BATCH) {
            // Files are read outside the transaction; the write is quick.
            let records: Vec<Indexed> = batch
                .iter()
                .filter_map(|id| match read_run(&self.runs_dir.join(id.as_str())) {
                    Ok(r) => Some(r),
                    Err(e) => {
                        tracing::warn!("run catalogue: run {id} left out: {e}");
                        report.unreadable += 1;
                        None
                    }
                })
                .collect();
            let mut conn = self.conn();
            let tx = conn.transaction().map_err(self.sqlite())?;
            for r in &records {
                report.indexed +=
                    usize::from(upsert_if_current(&tx, &self.runs_dir, r).map_err(self.sqlite())?);
            }
            tx.commit().map_err(self.sqlite())?;
        }
        let present: HashSet<&str> = on_disk.iter().map(|(id, _)| id.as_str()).collect();
        let gone: Vec<&String> = known
            .keys()
            .filter(|id| !present.contains(id.as_str()))
            // Gone still (not a directory that appeared since the listing).
            .filter(|id| !RunDir::holds_run(&self.runs_dir.join(id.as_str())))
            .collect();
        if !gone.is_empty() {
            let mut conn = self.conn();
            let tx = conn.transaction().map_err(self.sqlite())?;
            for id in &gone {
                tx.execute("DELETE FROM runs WHERE id = ?1", [id])
                    .map_err(self.sqlite())?;
            }
            tx.commit().map_err(self.sqlite())?;
            report.removed = gone.len();
        }
        report.audit_imported = self.import_audit()?;
        Ok(report)
    }

    /// Imports the audit entries appended to audit.jsonl since the last import (all of
    /// them if the file was replaced by a shorter one).
    fn import_audit(&self) -> Result<usize, CatalogueError> {
        let path = self.runs_dir.join(AUDIT_FILE);
        let len = match std::fs::metadata(&path) {
            Ok(m) => m.len(),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(0),
            Err(source) => return Err(CatalogueError::Io { path, source }),
        };
        let done: u64 = self
            .conn()
            .query_row("SELECT value FROM meta WHERE key = 'audit_offset'", [], |r| {
                r.get::<_, String>(0)
            })
            .optional()
            .map_err(self.sqlite())?
            .and_then(|v| v.parse().ok())
            .unwrap_or(0);
        if done == len {
            return Ok(0);
        }
        // The log only grows: what was read before is in the table (entries are
        // inserted by id, so a line read twice counts once). A log shorter than the
        // offset was replaced: read whole.
        let from = if done <= len { done } else { 0 };
        let entries = audit::read_from(&self.runs_dir, from).map_err(|source| CatalogueError::Io {
            path: path.clone(),
            source,
        })?;
        let mut conn = self.conn();
        let tx = conn.transaction().map_err(self.sqlite())?;
        let mut imported = 0;
        for e in &entries {
            imported += insert_audit(&tx, e).map_err(self.sqlite())?;
        }
        tx.execute(
            "INSERT INTO meta (key, value) VALUES ('audit_offset', ?1)
             ON CONFLICT(key) DO UPDATE SET value = excluded.value",
            [len.to_string()],
        )
        .map_err(self.sqlite())?;
        tx.commit().map_err(self.sqlite())?;
        Ok(imported)
    }

    /// Reads run `id`'s directory again and updates its row (after a state change, a
    /// stage, an annotation). A run whose directory is gone loses its row.
    pub fn index(&self, id: &str) -> Result<(), CatalogueError> {
        let dir = self.runs_dir.join(id);
        if !RunDir::holds_run(&dir) {
            self.conn()
                .execute("DELETE FROM runs WHERE id = ?1", [id])
                .map_err(self.sqlite())?;
            return Ok(());
        }
        let r = read_run(&dir).map_err(|source| CatalogueError::Io {
            path: dir.join(file::RUN),
            source,
        })?;
        let mut conn = self.conn();
        let tx = conn.transaction().map_err(self.sqlite())?;
        upsert_if_current(&tx, &self.runs_dir, &r).map_err(self.sqlite())?;
        tx.commit().map_err(self.sqlite())
    }

    /// Records an audit entry: appended to audit.jsonl (the lasting record), then
    /// inserted in the catalogue.
    pub fn record(&self, entry: &AuditEntry) -> Result<(), CatalogueError> {
        append_audit(&self.runs_dir, entry)?;
        self.catalogue_audit(entry)
    }

    /// Puts an entry [`append_audit`] wrote into the catalogue (a sync would too, from
    /// the log).
    pub fn catalogue_audit(&self, entry: &AuditEntry) -> Result<(), CatalogueError> {
        let conn = self.conn();
        insert_audit(&conn, entry).map_err(self.sqlite())?;
        Ok(())
    }

    /// Runs per state, for the metrics.
    pub fn state_counts(&self) -> Result<Vec<(String, u64)>, CatalogueError> {
        let conn = self.conn();
        let mut stmt = conn
            .prepare_cached("SELECT state, COUNT(*) FROM runs GROUP BY state")
            .map_err(self.sqlite())?;
        let rows = stmt
            .query_map([], |r| Ok((r.get(0)?, r.get::<_, i64>(1)?.max(0) as u64)))
            .map_err(self.sqlite())?;
        rows.collect::<Result<_, _>>().map_err(self.sqlite())
    }

    /// The catalogue file's size in bytes (with its write-ahead log).
    pub fn size_bytes(&self) -> u64 {
        [self.path.clone(), wal(&self.path, "-wal")]
            .iter()
            .filter_map(|p| std::fs::metadata(p).ok())
            .map(|m| m.len())
            .sum()
    }
}

/// The lock a daemon holds shared on its runs directory's catalogue for its life, and
/// a rebuild takes exclusively.
pub const LOCK_FILE: &str = "catalogue.lock";

fn lock_file(path: &Path) -> std::io::Result<std::fs::File> {
    std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(path)
}

/// Holds the catalogue of `runs_dir` shared (a daemon, for its life): a rebuild is
/// refused meanwhile.
pub fn hold(runs_dir: &Path) -> std::io::Result<std::fs::File> {
    let path = runs_dir.join(LOCK_FILE);
    let f = lock_file(&path)?;
    match f.try_lock_shared() {
        Ok(()) => {}
        Err(std::fs::TryLockError::WouldBlock) => {
            tracing::warn!(
                "{}: a `periscope catalogue rebuild` is under way; waiting for it to finish",
                path.display()
            );
            f.lock_shared()?;
        }
        Err(std::fs::TryLockError::Error(e)) => return Err(e),
    }
    Ok(f)
}

/// `path` with `suffix` appended (SQLite's `-wal` and `-shm` files).
fn wal(path: &Path, suffix: &str) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(suffix);
    PathBuf::from(s)
}

/// Why a catalogue could not be opened.
enum Open {
    /// The file is not a database or fails its integrity check: it is set aside and
    /// rebuilt (it holds nothing the run directories do not).
    Damaged(String),
    /// Anything else (busy, read-only, a schema from a newer Periscope): refused as it
    /// is, never set aside under another process that may be using it.
    Refused(String),
}

fn classify(e: &rusqlite::Error) -> Open {
    use rusqlite::ErrorCode::{DatabaseCorrupt, NotADatabase};
    match e.sqlite_error_code() {
        Some(NotADatabase | DatabaseCorrupt) => Open::Damaged(e.to_string()),
        _ => Open::Refused(e.to_string()),
    }
}

/// Opens a catalogue connection, checks the file is a readable database, and migrates
/// it.
fn open_connection(path: &Path) -> Result<Connection, Open> {
    let mut conn = Connection::open(path).map_err(|e| classify(&e))?;
    conn.busy_timeout(BUSY_TIMEOUT).map_err(|e| classify(&e))?;
    let check: String = conn
        .query_row("PRAGMA quick_check", [], |r| r.get(0))
        .map_err(|e| classify(&e))?;
    if check != "ok" {
        return Err(Open::Damaged(format!("integrity check: {check}")));
    }
    conn.pragma_update(None, "journal_mode", "WAL")
        .map_err(|e| classify(&e))?;
    conn.pragma_update(None, "synchronous", "NORMAL")
        .map_err(|e| classify(&e))?;
    conn.pragma_update(None, "foreign_keys", "ON")
        .map_err(|e| classify(&e))?;
    schema::migrate_to(&mut conn, schema::VERSION).map_err(Open::Refused)?;
    Ok(conn)
}

/// Moves a damaged catalogue (and its WAL files) aside.
fn set_aside(path: &Path, aside: &Path) -> std::io::Result<()> {
    std::fs::rename(path, aside)?;
    for suffix in ["-wal", "-shm"] {
        match std::fs::remove_file(wal(path, suffix)) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(e),
        }
    }
    Ok(())
}

/// A stamp of the files a run's row is read from: their modification times and
/// lengths. A row whose stamp differs is read again.
fn stamp(dir: &Path) -> String {
    let mut s = String::new();
    for name in [file::RUN, file::ANNOTATIONS, file::VOLUME_JSON] {
        match std::fs::metadata(dir.join(name)) {
            Ok(m) => {
                let ns = m
                    .modified()
                    .ok()
                    .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                    .map_or(0, |d| d.as_nanos());
                s.push_str(&format!("{ns}:{};", m.len()));
            }
            Err(_) => s.push_str("-;"),
        }
    }
    s
}

/// A run as read from its directory, ready to store.
struct Indexed {
    record: RunRecord,
    plan_text: String,
    stamp: String,
}

/// Reads a run directory into a catalogue row. Only run.json must be readable; the
/// rest is taken where present.
fn read_run(dir: &Path) -> std::io::Result<Indexed> {
    // The stamp is taken first: a file changed while it is read leaves a stale stamp,
    // so the next sync reads it again.
    let stamp = stamp(dir);
    let mut info = RunInfo::load(dir)?;
    // The row is the directory's: a copied or renamed run is keyed by where it is.
    if let Some(name) = dir.file_name() {
        info.id = name.to_string_lossy().into_owned();
    }
    let plan_text = crate::store::read_text_capped(&dir.join(file::PLAN), 1 << 20).unwrap_or_default();
    let instrument = crate::store::read_text_capped(&dir.join(file::INSTRUMENT), 1 << 20)
        .ok()
        .and_then(|t| t.parse::<toml::Table>().ok())
        .and_then(|t| t.get("name").and_then(|n| n.as_str()).map(str::to_owned));
    let annotations = Annotations::load(dir).unwrap_or_else(|e| {
        tracing::warn!(
            "{}: {e}; the run's tags and note are left out",
            dir.join(file::ANNOTATIONS).display()
        );
        Annotations::default()
    });
    let volume: Option<serde_json::Value> =
        crate::store::read_text_capped(&dir.join(file::VOLUME_JSON), 1 << 20)
            .ok()
            .and_then(|t| serde_json::from_str(&t).ok());
    let method = volume
        .as_ref()
        .and_then(|v| v.get("method"))
        .and_then(|m| m.as_str())
        .map(str::to_owned);
    let final_loss = volume
        .as_ref()
        .and_then(|v| v.get("final_loss"))
        .and_then(serde_json::Value::as_f64);
    let recon_s = volume
        .as_ref()
        .and_then(|v| v.get("timings_s"))
        .and_then(|t| serde_json::from_value::<Vec<(String, f64)>>(t.clone()).ok())
        .map(|t| t.iter().map(|(_, s)| s).sum::<f64>());
    let outputs = DOWNLOADS
        .iter()
        .filter_map(|(name, _)| {
            let m = std::fs::metadata(dir.join(name)).ok()?;
            m.is_file().then(|| OutputFile {
                name: (*name).to_owned(),
                bytes: m.len(),
            })
        })
        .collect();
    let run_json_time = std::fs::metadata(dir.join(file::RUN))
        .and_then(|m| m.modified())
        .ok()
        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
        .map(|d| d.as_secs_f64());
    let created = info
        .created_unix_s
        .or_else(|| time_of_id(&info.id))
        .or(run_json_time);
    let updated = info.history.last().map(|c| c.at_unix_s).or(run_json_time);
    Ok(Indexed {
        record: RunRecord {
            id: info.id.clone(),
            plan: info.plan,
            state: info.state,
            stage: info.stage,
            instrument,
            submitted_by: info.submitted_by,
            again_of: info.again_of,
            imported: info.import.map(|i| i.capture),
            created_unix_s: created,
            updated_unix_s: updated,
            pairs_total: info.pairs_total as u64,
            pairs_done: info.pairs_done as u64,
            error: info.error,
            method,
            recon_s,
            final_loss,
            tags: annotations.tags,
            note: annotations.note,
            timings: info.timings,
            history: info.history,
            outputs,
        },
        plan_text,
        stamp,
    })
}

/// The time a run id starts with (`YYYYMMDD-HHMMSS-…`, UTC), as Unix seconds.
pub fn time_of_id(id: &str) -> Option<f64> {
    let fmt = time::macros::format_description!("[year][month][day]-[hour][minute][second]");
    let head = id.get(..15)?;
    let t = time::PrimitiveDateTime::parse(head, fmt).ok()?;
    Some(t.assume_utc().unix_timestamp() as f64)
}

/// Stores a run's row unless its files changed since they were read (then a newer
/// read, by this process or another, writes it): a slow reader never puts an older
/// state over a newer one. Returns whether it was stored.
fn upsert_if_current(tx: &rusqlite::Transaction<'_>, runs_dir: &Path, r: &Indexed) -> rusqlite::Result<bool> {
    if stamp(&runs_dir.join(&r.record.id)) != r.stamp {
        return Ok(false);
    }
    upsert(tx, r)?;
    Ok(true)
}

fn upsert(tx: &rusqlite::Transaction<'_>, r: &Indexed) -> rusqlite::Result<()> {
    let rec = &r.record;
    tx.execute(
        "INSERT INTO runs (id, plan, state, stage, created, updated, pairs_total, pairs_done,
            error, stamp, instrument, submitted_by, again_of, method, recon_s, final_loss, note,
            plan_text, imported)
         VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16, ?17, ?18, ?19)
         ON CONFLICT(id) DO UPDATE SET plan = excluded.plan, state = excluded.state,
            stage = excluded.stage, created = excluded.created, updated = excluded.updated,
            pairs_total = excluded.pairs_total, pairs_done = excluded.pairs_done,
            error = excluded.error, stamp = excluded.stamp, instrument = excluded.instrument,
            submitted_by = excluded.submitted_by, again_of = excluded.again_of,
            method = excluded.method, recon_s = excluded.recon_s,
            final_loss = excluded.final_loss, note = excluded.note,
            plan_text = excluded.plan_text, imported = excluded.imported",
        params![
            rec.id,
            rec.plan,
            query::state_str(rec.state),
            rec.stage,
            rec.created_unix_s,
            rec.updated_unix_s,
            rec.pairs_total as i64,
            rec.pairs_done as i64,
            rec.error,
            r.stamp,
            rec.instrument,
            rec.submitted_by,
            rec.again_of,
            rec.method,
            rec.recon_s,
            rec.final_loss,
            rec.note,
            r.plan_text,
            rec.imported,
        ],
    )?;
    for table in ["state_changes", "timings", "outputs", "tags"] {
        tx.execute(&format!("DELETE FROM {table} WHERE run_id = ?1"), [&rec.id])?;
    }
    let mut ins = tx.prepare_cached(
        "INSERT INTO state_changes (run_id, seq, at, state, by) VALUES (?1, ?2, ?3, ?4, ?5)",
    )?;
    for (i, c) in rec.history.iter().enumerate() {
        ins.execute(params![
            rec.id,
            i as i64,
            c.at_unix_s,
            query::state_str(c.state),
            c.by
        ])?;
    }
    let mut ins =
        tx.prepare_cached("INSERT INTO timings (run_id, seq, stage, seconds) VALUES (?1, ?2, ?3, ?4)")?;
    for (i, (stage, s)) in rec.timings.iter().enumerate() {
        ins.execute(params![rec.id, i as i64, stage, s])?;
    }
    let mut ins = tx.prepare_cached("INSERT INTO outputs (run_id, name, bytes) VALUES (?1, ?2, ?3)")?;
    for o in &rec.outputs {
        ins.execute(params![rec.id, o.name, o.bytes as i64])?;
    }
    let mut ins = tx.prepare_cached("INSERT OR IGNORE INTO tags (run_id, tag) VALUES (?1, ?2)")?;
    for t in &rec.tags {
        ins.execute(params![rec.id, t])?;
    }
    Ok(())
}

/// Inserts an audit entry unless one with its id is there; returns 1 if inserted.
fn insert_audit(conn: &Connection, e: &AuditEntry) -> rusqlite::Result<usize> {
    conn.prepare_cached(
        "INSERT OR IGNORE INTO audit (id, at, actor, role, action, target, outcome, detail, peer)
         VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)",
    )?
    .execute(params![
        e.id,
        e.at_unix_s,
        e.actor,
        e.role,
        e.action,
        e.target,
        e.outcome,
        e.detail,
        e.peer
    ])
}

#[cfg(test)]
mod tests;
