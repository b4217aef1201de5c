//! The catalogue against run directories made as the pipeline makes them: migrations
//! from an empty and from an older catalogue, rebuilds after deletion and corruption,
//! filters, and concurrent writers.
use super::*;
use crate::run_dir::{RunState, StateChange};

/// A run directory as the pipeline leaves it: run.json with a history, a plan, an
/// instrument config, optionally outputs and annotations.
fn make_run(root: &Path, id: &str, plan: &str, state: RunState, created: f64, tags: &[&str]) {
    let dir = root.join(id);
    std::fs::create_dir_all(&dir).unwrap();
    let mut info = RunInfo {
        id: id.into(),
        plan: plan.into(),
        state,
        stage: "done".into(),
        instrument_path: PathBuf::from("instrument.toml"),
        pairs_total: 64,
        pairs_done: if state == RunState::Completed { 64 } else { 10 },
        error: (state == RunState::Failed).then(|| "the TDC stopped answering".to_owned()),
        timings: vec![("capture".into(), 3.5), ("reconstruct".into(), 1.25)],
        created_unix_s: Some(created),
        submitted_by: Some("alice".into()),
        again_of: None,
        import: None,
        history: vec![
            StateChange {
                at_unix_s: created,
                state: RunState::Queued,
                by: Some("alice".into()),
            },
            StateChange {
                at_unix_s: created + 1.0,
                state: RunState::Running,
                by: None,
            },
        ],
        adaptive_seconds: 0.0,
        adaptive_stopped: None,
        adaptive_batches: 0,
        acting: None,
    };
    info.save(&dir).unwrap();
    std::fs::write(dir.join(file::PLAN), format!("name = \"{plan}\"\n")).unwrap();
    std::fs::write(dir.join(file::INSTRUMENT), "name = \"bench-1\"\n").unwrap();
    if state == RunState::Completed {
        std::fs::write(dir.join(file::VOLUME), vec![0u8; 1000]).unwrap();
        std::fs::write(
            dir.join(file::VOLUME_JSON),
            r#"{"method": "gtr", "timings_s": [["fit", 2.0], ["solve", 0.5]], "final_loss": 0.125}"#,
        )
        .unwrap();
    }
    if !tags.is_empty() {
        Annotations {
            tags: tags.iter().map(|t| (*t).to_owned()).collect(),
            note: format!("note on {id}"),
        }
        .save(&dir)
        .unwrap();
    }
}

fn fixture(root: &Path) {
    make_run(
        root,
        "20261101-100000-wall",
        "wall",
        RunState::Completed,
        1_793_527_200.0,
        &["calib"],
    );
    make_run(
        root,
        "20261102-100000-torso",
        "torso",
        RunState::Failed,
        1_793_613_600.0,
        &[],
    );
    make_run(
        root,
        "20261103-100000-wall",
        "wall",
        RunState::Completed,
        1_793_700_000.0,
        &["calib", "good"],
    );
    make_run(
        root,
        "20261104-100000-wall",
        "wall",
        RunState::Paused,
        1_793_786_400.0,
        &[],
    );
    crate::catalogue::audit::append(
        root,
        &AuditEntry::new("alice", "operator", "submit", Some("20261101-100000-wall"), "ok"),
    )
    .unwrap();
}

fn everything(cat: &Catalogue) -> (Vec<RunRecord>, Vec<AuditEntry>) {
    let runs = cat
        .query(&RunQuery {
            sort: SortKey::Id,
            ..RunQuery::default()
        })
        .unwrap()
        .runs;
    let audit = cat
        .audit(&AuditQuery {
            limit: 1000,
            ..AuditQuery::default()
        })
        .unwrap()
        .entries;
    (runs, audit)
}

#[test]
fn a_new_catalogue_holds_every_run_with_its_history_outputs_and_scores() {
    let dir = tempfile::tempdir().unwrap();
    fixture(dir.path());
    let cat = Catalogue::open(dir.path()).unwrap();
    let (runs, audit) = everything(&cat);
    assert_eq!(runs.len(), 4);
    let r = &runs[0];
    assert_eq!(r.id, "20261101-100000-wall");
    assert_eq!(r.state, RunState::Completed);
    assert_eq!(r.instrument.as_deref(), Some("bench-1"));
    assert_eq!(r.submitted_by.as_deref(), Some("alice"));
    assert_eq!(r.method.as_deref(), Some("gtr"));
    assert_eq!(r.recon_s, Some(2.5));
    assert_eq!(r.final_loss, Some(0.125));
    assert_eq!(r.tags, vec!["calib"]);
    assert_eq!(
        r.history.len(),
        3,
        "queued, running, and the completed save() recorded"
    );
    assert_eq!(r.history[2].state, RunState::Completed);
    assert_eq!(r.timings.len(), 2);
    assert!(
        r.outputs
            .iter()
            .any(|o| o.name == file::VOLUME && o.bytes == 1000)
    );
    assert_eq!(audit.len(), 1);
    let (_, plan) = cat.get("20261102-100000-torso").unwrap().unwrap();
    assert_eq!(plan, "name = \"torso\"\n");
}

#[test]
fn filters_sort_and_page() {
    let dir = tempfile::tempdir().unwrap();
    fixture(dir.path());
    let cat = Catalogue::open(dir.path()).unwrap();
    let ids =
        |q: RunQuery| -> Vec<String> { cat.query(&q).unwrap().runs.into_iter().map(|r| r.id).collect() };
    assert_eq!(
        ids(RunQuery {
            states: vec![RunState::Completed],
            ..RunQuery::default()
        }),
        vec!["20261101-100000-wall", "20261103-100000-wall"]
    );
    assert_eq!(
        ids(RunQuery {
            tag: Some("good".into()),
            ..RunQuery::default()
        }),
        vec!["20261103-100000-wall"]
    );
    assert_eq!(
        ids(RunQuery {
            plan: Some("torso".into()),
            ..RunQuery::default()
        }),
        vec!["20261102-100000-torso"]
    );
    // Text: in the error, case-insensitive; `%` and `_` are literal.
    assert_eq!(
        ids(RunQuery {
            text: Some("tdc STOPPED".into()),
            ..RunQuery::default()
        }),
        vec!["20261102-100000-torso"]
    );
    assert!(
        ids(RunQuery {
            text: Some("%".into()),
            ..RunQuery::default()
        })
        .is_empty()
    );
    // Date range: [Nov 2, Nov 4).
    assert_eq!(
        ids(RunQuery {
            since: Some(1_793_613_600.0),
            until: Some(1_793_786_400.0),
            ..RunQuery::default()
        }),
        vec!["20261102-100000-torso", "20261103-100000-wall"]
    );
    // Newest first, two per page.
    let page = cat
        .query(&RunQuery {
            descending: true,
            limit: 2,
            offset: 1,
            ..RunQuery::default()
        })
        .unwrap();
    assert_eq!(page.total, 4);
    assert_eq!(
        page.runs.iter().map(|r| r.id.as_str()).collect::<Vec<_>>(),
        vec!["20261103-100000-wall", "20261102-100000-torso"]
    );
}

#[test]
fn rebuild_after_deletion_and_after_corruption_yields_the_same_rows() {
    let dir = tempfile::tempdir().unwrap();
    fixture(dir.path());
    let before = everything(&Catalogue::open(dir.path()).unwrap());
    // Deleted.
    std::fs::remove_file(dir.path().join(CATALOGUE_FILE)).unwrap();
    let _ = std::fs::remove_file(wal(&dir.path().join(CATALOGUE_FILE), "-wal"));
    let _ = std::fs::remove_file(wal(&dir.path().join(CATALOGUE_FILE), "-shm"));
    assert_eq!(everything(&Catalogue::open(dir.path()).unwrap()), before);
    // Rebuilt on request.
    let (cat, report) = Catalogue::rebuild(dir.path()).unwrap();
    assert_eq!((report.runs, report.indexed, report.audit_imported), (4, 4, 1));
    assert_eq!(everything(&cat), before);
    drop(cat);
    // Corrupted: garbage over the whole file (and its WAL gone), then its middle
    // overwritten in a valid file.
    let path = dir.path().join(CATALOGUE_FILE);
    let _ = std::fs::remove_file(wal(&path, "-wal"));
    let _ = std::fs::remove_file(wal(&path, "-shm"));
    std::fs::write(&path, b"this is not a database at all, it is a text file").unwrap();
    assert_eq!(everything(&Catalogue::open(dir.path()).unwrap()), before);
    assert!(
        dir.path().join(format!("{CATALOGUE_FILE}.damaged")).is_file(),
        "the damaged file is kept aside"
    );
    let _ = std::fs::remove_file(wal(&path, "-wal"));
    let _ = std::fs::remove_file(wal(&path, "-shm"));
    let mut bytes = std::fs::read(&path).unwrap();
    let len = bytes.len();
    for b in &mut bytes[len / 2..] {
        *b = 0xA5;
    }
    std::fs::write(&path, &bytes).unwrap();
    assert_eq!(everything(&Catalogue::open(dir.path()).unwrap()), before);
}

#[test]
fn an_older_catalogue_is_migrated_and_its_runs_read_again() {
    let dir = tempfile::tempdir().unwrap();
    fixture(dir.path());
    // A version-1 catalogue, as an older daemon left it: no tags, scores or audit.
    {
        let mut conn = Connection::open(dir.path().join(CATALOGUE_FILE)).unwrap();
        schema::migrate_to(&mut conn, 1).unwrap();
        assert_eq!(schema::version(&conn).unwrap(), 1);
        conn.execute(
            "INSERT INTO runs (id, plan, state, stage, created, updated, pairs_total, pairs_done, error, stamp)
             VALUES ('20261101-100000-wall', 'wall', 'completed', 'done', 1.0, 2.0, 64, 64, NULL, 'old')",
            [],
        )
        .unwrap();
        conn.execute(
            "INSERT INTO runs (id, plan, state, stage, created, updated, pairs_total, pairs_done, error, stamp)
             VALUES ('20250101-000000-gone', 'gone', 'completed', 'done', 1.0, 2.0, 64, 64, NULL, 'old')",
            [],
        )
        .unwrap();
    }
    let cat = Catalogue::open(dir.path()).unwrap();
    assert_eq!(schema::version(&cat.conn()).unwrap(), schema::VERSION);
    let (runs, audit) = everything(&cat);
    assert_eq!(runs.len(), 4, "the run whose directory is gone is dropped");
    assert_eq!(
        runs[0].tags,
        vec!["calib"],
        "the new columns are filled from the directory"
    );
    assert_eq!(runs[0].created_unix_s, Some(1_793_527_200.0));
    assert_eq!(audit.len(), 1);
    // An empty file migrates from version 0.
    let empty = tempfile::tempdir().unwrap();
    let cat = Catalogue::open(empty.path()).unwrap();
    assert_eq!(schema::version(&cat.conn()).unwrap(), schema::VERSION);
    assert_eq!(everything(&cat).0.len(), 0);
}

#[test]
fn a_catalogue_from_a_newer_periscope_is_refused_not_damaged() {
    let dir = tempfile::tempdir().unwrap();
    {
        let conn = Connection::open(dir.path().join(CATALOGUE_FILE)).unwrap();
        conn.pragma_update(None, "user_version", schema::VERSION + 1)
            .unwrap();
    }
    // Refused as a schema it does not know: neither written with a meaning it does
    // not have, nor set aside under the newer Periscope that may be using it.
    let err = Catalogue::open(dir.path()).err().expect("refused");
    assert!(err.to_string().contains("newer than this periscope"), "{err}");
    assert!(!dir.path().join(format!("{CATALOGUE_FILE}.damaged")).exists());
    assert!(dir.path().join(CATALOGUE_FILE).is_file());
}

#[test]
fn concurrent_writers_lose_and_duplicate_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().to_owned();
    Catalogue::open(&root).unwrap();
    // Four writers with their own connections (as the daemon's indexer, API requests
    // and CLI processes have): each makes runs, indexes them, records audit entries,
    // and syncs.
    let writers: Vec<_> = (0..4)
        .map(|w| {
            let root = root.clone();
            std::thread::spawn(move || {
                let cat = Catalogue::open_unsynced(&root).unwrap();
                for i in 0..25 {
                    let id = format!("20261105-1000{w:02}-w{w}-{i:02}");
                    make_run(
                        &root,
                        &id,
                        "wall",
                        RunState::Completed,
                        1e9 + f64::from(i),
                        &["x"],
                    );
                    cat.index(&id).unwrap();
                    cat.record(&AuditEntry::new(
                        &format!("w{w}"),
                        "operator",
                        "submit",
                        Some(&id),
                        "ok",
                    ))
                    .unwrap();
                    if i % 5 == 0 {
                        cat.sync().unwrap();
                    }
                }
            })
        })
        .collect();
    for w in writers {
        w.join().unwrap();
    }
    let cat = Catalogue::open(&root).unwrap();
    let (runs, audit) = everything(&cat);
    assert_eq!(runs.len(), 100);
    assert_eq!(audit.len(), 100);
    let ids: HashSet<_> = audit.iter().map(|a| a.id.clone()).collect();
    assert_eq!(ids.len(), 100);
    // audit.jsonl has each entry once too.
    assert_eq!(audit::read_all(&root).unwrap().len(), 100);
}

/// A reader that read a run before its files changed never writes its older row over
/// the newer one (the CLI syncing while the daemon's indexer records a run's end).
#[test]
fn an_older_read_never_overwrites_a_newer_row() {
    let dir = tempfile::tempdir().unwrap();
    fixture(dir.path());
    let cat = Catalogue::open(dir.path()).unwrap();
    let id = "20261104-100000-wall";
    let run = dir.path().join(id);
    // A slow reader reads the paused run...
    let old = read_run(&run).unwrap();
    // ...the run completes meanwhile (its run.json rewritten) and is indexed...
    std::thread::sleep(std::time::Duration::from_millis(20));
    let mut info = RunInfo::load(&run).unwrap();
    info.state = RunState::Completed;
    info.save(&run).unwrap();
    cat.index(id).unwrap();
    // ...then the slow reader writes: refused, the row stays completed.
    let mut conn = cat.conn();
    let tx = conn.transaction().unwrap();
    assert!(!upsert_if_current(&tx, dir.path(), &old).unwrap());
    tx.commit().unwrap();
    drop(conn);
    assert_eq!(cat.get(id).unwrap().unwrap().0.state, RunState::Completed);
}

/// A run directory copied under another name is its own row, keyed by where it is.
#[test]
fn rows_are_keyed_by_their_directory() {
    let dir = tempfile::tempdir().unwrap();
    fixture(dir.path());
    let from = dir.path().join("20261101-100000-wall");
    let to = dir.path().join("20261101-100000-wall-copy");
    std::fs::create_dir(&to).unwrap();
    for e in std::fs::read_dir(&from).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
    let cat = Catalogue::open(dir.path()).unwrap();
    let ids: Vec<String> = everything(&cat).0.into_iter().map(|r| r.id).collect();
    assert!(
        ids.contains(&"20261101-100000-wall".to_owned())
            && ids.contains(&"20261101-100000-wall-copy".to_owned()),
        "{ids:?}"
    );
    assert_eq!(ids.len(), 5);
}

/// A refused request's target is whatever path the client sent: an entry keeps at
/// most 256 bytes of it (and 2,048 of a detail), cut at a character boundary, so a
/// client cannot fill the trail's disk and its responses with 64 KB paths.
#[test]
fn an_entrys_target_and_detail_are_cut_to_their_bounds() {
    let long = format!("/api/v1/runs/{}", "é".repeat(40_000));
    let e = AuditEntry::new("unknown", "none", "authenticate", Some(&long), "refused").detail(long.clone());
    let target = e.target.as_deref().unwrap();
    assert!(
        target.len() <= 256 + '…'.len_utf8() && target.ends_with('…'),
        "{}",
        target.len()
    );
    assert!(long.starts_with(target.trim_end_matches('…')));
    let detail = e.detail.as_deref().unwrap();
    assert!(detail.len() <= 2048 + '…'.len_utf8(), "{}", detail.len());
    let short = AuditEntry::new("alice", "operator", "pause", Some("20261101-100000-wall"), "ok");
    assert_eq!(short.target.as_deref(), Some("20261101-100000-wall"));
}

/// The audit log read after damage: a line that is not UTF-8 and a line a crash cut
/// short are skipped, not the whole log (reading it as one string refused it all, and
/// with it `periscope runs`, `audit` and `catalogue rebuild`); and an entry appended
/// after the cut line starts a line of its own instead of joining the fragment.
#[test]
fn a_damaged_audit_log_loses_only_its_damaged_lines() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let first = AuditEntry::new("alice", "operator", "submit", Some("run-a"), "ok");
    audit::append(root, &first).unwrap();
    let path = root.join(AUDIT_FILE);
    let mut bytes = std::fs::read(&path).unwrap();
    bytes.extend_from_slice(b"{\"id\": \"\xff\xfe not utf-8\"}\n");
    bytes.extend_from_slice(b"{\"id\": \"cut short by a cra");
    std::fs::write(&path, &bytes).unwrap();
    let second = AuditEntry::new("bob", "operator", "pause", Some("run-b"), "ok");
    audit::append(root, &second).unwrap();
    let ids: Vec<String> = audit::read_all(root).unwrap().into_iter().map(|e| e.id).collect();
    assert_eq!(ids, [first.id.clone(), second.id.clone()]);
    // Read on from an offset inside the second entry's line: that line again.
    let from = std::fs::metadata(&path).unwrap().len() - 10;
    let tail: Vec<String> = audit::read_from(root, from)
        .unwrap()
        .into_iter()
        .map(|e| e.id)
        .collect();
    assert_eq!(tail, [second.id]);
}
