//! The catalogue's schema and its versioned migrations. `PRAGMA user_version` holds
//! the version a catalogue is at; opening one runs every later migration in order,
//! each in its own transaction, so an older catalogue (or an empty file) comes up to
//! date and a half-applied migration never stays.
//!
//! A migration is never edited once released: a change to the schema is a new entry at
//! the end of [`MIGRATIONS`].
use rusqlite::Connection;

/// The migrations, in order: entry `i` takes a catalogue from version `i` to `i + 1`.
pub const MIGRATIONS: &[&str] = &[
    // 1: runs, their state changes, stage timings and output files.
    "CREATE TABLE runs (
        id TEXT PRIMARY KEY,
        plan TEXT NOT NULL,
        state TEXT NOT NULL,
        stage TEXT NOT NULL,
        created REAL,
        updated REAL,
        pairs_total INTEGER NOT NULL,
        pairs_done INTEGER NOT NULL,
        error TEXT,
        stamp TEXT
    );
    CREATE TABLE state_changes (
        run_id TEXT NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
        seq INTEGER NOT NULL,
        at REAL NOT NULL,
        state TEXT NOT NULL,
        by TEXT,
        PRIMARY KEY (run_id, seq)
    );
    CREATE TABLE timings (
        run_id TEXT NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
        seq INTEGER NOT NULL,
        stage TEXT NOT NULL,
        seconds REAL NOT NULL,
        PRIMARY KEY (run_id, seq)
    );
    CREATE TABLE outputs (
        run_id TEXT NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
        name TEXT NOT NULL,
        bytes INTEGER NOT NULL,
        PRIMARY KEY (run_id, name)
    );
    CREATE INDEX runs_state ON runs(state);
    CREATE INDEX runs_created ON runs(created);",
    // 2: provenance (instrument, submitter, run-again), scores, tags and the note, the
    // plan's text, the audit trail, and `meta` (how much of audit.jsonl is imported). Every run is read again from its directory to
    // fill the new columns (its stamp is cleared).
    "ALTER TABLE runs ADD COLUMN instrument TEXT;
    ALTER TABLE runs ADD COLUMN submitted_by TEXT;
    ALTER TABLE runs ADD COLUMN again_of TEXT;
    ALTER TABLE runs ADD COLUMN method TEXT;
    ALTER TABLE runs ADD COLUMN recon_s REAL;
    ALTER TABLE runs ADD COLUMN final_loss REAL;
    ALTER TABLE runs ADD COLUMN note TEXT NOT NULL DEFAULT '';
    ALTER TABLE runs ADD COLUMN plan_text TEXT NOT NULL DEFAULT '';
    CREATE TABLE tags (
        run_id TEXT NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
        tag TEXT NOT NULL,
        PRIMARY KEY (run_id, tag)
    );
    CREATE INDEX tags_tag ON tags(tag);
    CREATE INDEX runs_plan ON runs(plan);
    CREATE TABLE audit (
        id TEXT PRIMARY KEY,
        at REAL NOT NULL,
        actor TEXT NOT NULL,
        role TEXT NOT NULL,
        action TEXT NOT NULL,
        target TEXT,
        outcome TEXT NOT NULL,
        detail TEXT,
        peer TEXT
    );
    CREATE INDEX audit_at ON audit(at);
    CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
    UPDATE runs SET stamp = NULL;",
    // 3: the capture file an imported capture's run reconstructs (`POST /imports`).
    // Every run is read again from its directory to fill it.
    "ALTER TABLE runs ADD COLUMN imported TEXT;
    UPDATE runs SET stamp = NULL;",
];

/// The version a fully migrated catalogue is at.
pub const VERSION: u32 = MIGRATIONS.len() as u32;

/// The catalogue's version (0 for an empty database).
pub fn version(conn: &Connection) -> rusqlite::Result<u32> {
    conn.query_row("PRAGMA user_version", [], |r| r.get(0))
}

/// Runs the migrations after the catalogue's version up to `target`, each in its own
/// transaction with the version bump. A catalogue newer than this build is refused
/// (its columns may mean what this build does not know).
pub fn migrate_to(conn: &mut Connection, target: u32) -> Result<(), String> {
    let at = version(conn).map_err(|e| e.to_string())?;
    if at > VERSION {
        return Err(format!(
            "the catalogue is at schema version {at}, newer than this periscope's {VERSION}: \
             use the newer periscope, or rebuild the catalogue with `periscope catalogue rebuild`"
        ));
    }
    for v in at..target.min(VERSION) {
        // IMMEDIATE: the write lock is taken first, so of two processes migrating at
        // once one waits, then finds the work done.
        let tx = conn
            .transaction_with_behavior(rusqlite::TransactionBehavior::Immediate)
            .map_err(|e| e.to_string())?;
        if version(&tx).map_err(|e| e.to_string())? > v {
            continue;
        }
        tx.execute_batch(MIGRATIONS[v as usize])
            .map_err(|e| format!("migration to schema version {}: {e}", v + 1))?;
        tx.pragma_update(None, "user_version", v + 1)
            .map_err(|e| e.to_string())?;
        tx.commit().map_err(|e| e.to_string())?;
    }
    Ok(())
}
