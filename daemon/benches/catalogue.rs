//! The run catalogue at a lab's scale: 100,000 runs.
//!
//! `cargo bench -p periscope-daemon --bench catalogue` (release). Setup (not timed by
//! criterion, printed): 100,000 run directories as the pipeline leaves them (run.json
//! with a state history, plan.toml, instrument.toml; every tenth run tagged and
//! annotated, every fifth reconstructed with a volume.json) in a temporary directory,
//! then `Catalogue::rebuild` over them (its time and the catalogue's size are
//! printed), and a second sync with nothing changed (the daemon's start).
//!
//! Timed (criterion, group `catalogue`): the queries the dashboard, the API and
//! `periscope runs` make: the newest 50 runs; completed runs in a date range; a tag;
//! a free-text search; a plan name; the audit trail's newest 100; the runs-per-state
//! counts `/metrics` reads at every scrape.
use std::path::Path;
use std::time::Instant;

use criterion::{Criterion, criterion_group, criterion_main};
use periscope_daemon::catalogue::{AuditEntry, AuditQuery, Catalogue, RunQuery, SortKey};
use periscope_daemon::run_dir::{Annotations, RunInfo, RunState, StateChange};

const RUNS: usize = 100_000;
const PLANS: [&str; 5] = ["wall", "torso", "bars", "corner", "survey"];
const START: f64 = 1_767_225_600.0; // 2026-01-01

fn make(root: &Path) {
    let plan_text =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/plans/demo.toml"))
            .unwrap_or_else(|_| "name = \"demo\"\n".into());
    for i in 0..RUNS {
        let created = START + i as f64 * 300.0; // a run every 5 minutes: ~1 year
        let plan = PLANS[i % PLANS.len()];
        let id = format!("run-{i:06}-{plan}");
        let dir = root.join(&id);
        std::fs::create_dir(&dir).unwrap();
        let state = match i % 20 {
            0 => RunState::Failed,
            1 => RunState::Aborted,
            _ => RunState::Completed,
        };
        let mut info = RunInfo {
            id: id.clone(),
            plan: plan.into(),
            state,
            stage: "done".into(),
            instrument_path: "/etc/periscope/lab.toml".into(),
            pairs_total: 4096,
            pairs_done: 4096,
            error: (state == RunState::Failed).then(|| "the TDC stopped answering (USB reset)".into()),
            timings: vec![
                ("los".into(), 12.0),
                ("capture".into(), 600.0),
                ("reconstruct".into(), 9.5),
            ],
            created_unix_s: Some(created),
            submitted_by: Some(format!("user{}", i % 7)),
            again_of: None,
            import: None,
            history: vec![
                StateChange {
                    at_unix_s: created,
                    state: RunState::Queued,
                    by: Some(format!("user{}", i % 7)),
                },
                StateChange {
                    at_unix_s: created + 5.0,
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
        std::fs::write(
            dir.join("plan.toml"),
            plan_text.replace("name = \"demo\"", &format!("name = \"{plan}\"")),
        )
        .unwrap();
        std::fs::write(dir.join("instrument.toml"), "name = \"lab-bench-1\"\n").unwrap();
        if i % 10 == 0 {
            Annotations {
                tags: vec!["calibration".into(), format!("week{}", i / 2016)],
                note: format!("target moved {} cm", i % 13),
            }
            .save(&dir)
            .unwrap();
        }
        if i % 5 == 0 {
            std::fs::write(
                dir.join("volume.json"),
                r#"{"method": "gtr", "timings_s": [["fit", 8.0], ["solve", 1.5]], "final_loss": 0.0123}"#,
            )
            .unwrap();
        }
    }
    for i in 0..10_000 {
        periscope_daemon::catalogue::audit::append(
            root,
            &AuditEntry::new(
                &format!("user{}", i % 7),
                "operator",
                "submit",
                Some(&format!("run-{:06}", i * 10)),
                "ok",
            ),
        )
        .unwrap();
    }
}

fn bench(c: &mut Criterion) {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let t = Instant::now();
    make(root);
    println!(
        "made {RUNS} run directories in {:.1} s",
        t.elapsed().as_secs_f64()
    );
    let t = Instant::now();
    let (cat, report) = Catalogue::rebuild(root).unwrap();
    println!(
        "rebuild: {} runs, {} audit entries in {:.1} s; catalogue {:.1} MB",
        report.indexed,
        report.audit_imported,
        t.elapsed().as_secs_f64(),
        cat.size_bytes() as f64 / 1e6
    );
    let t = Instant::now();
    let again = cat.sync().unwrap();
    println!(
        "sync with nothing changed (the daemon's start): {} runs stat'ed, {} read, {:.2} s",
        again.runs,
        again.indexed,
        t.elapsed().as_secs_f64()
    );
    let mut g = c.benchmark_group("catalogue");
    g.sample_size(20);
    let queries: Vec<(&str, RunQuery)> = vec![
        (
            "newest-50",
            RunQuery {
                descending: true,
                limit: 50,
                ..RunQuery::default()
            },
        ),
        (
            "completed-in-a-month-page-2",
            RunQuery {
                states: vec![RunState::Completed],
                since: Some(START + 90.0 * 86_400.0),
                until: Some(START + 120.0 * 86_400.0),
                limit: 50,
                offset: 50,
                ..RunQuery::default()
            },
        ),
        (
            "tag",
            RunQuery {
                tag: Some("week20".into()),
                limit: 50,
                ..RunQuery::default()
            },
        ),
        (
            "text",
            RunQuery {
                text: Some("usb reset".into()),
                descending: true,
                limit: 50,
                ..RunQuery::default()
            },
        ),
        (
            "plan-sorted-by-pairs",
            RunQuery {
                plan: Some("torso".into()),
                sort: SortKey::Pairs,
                descending: true,
                limit: 50,
                ..RunQuery::default()
            },
        ),
    ];
    for (name, q) in &queries {
        let n = cat.query(q).unwrap().total;
        println!("{name}: {n} match");
        g.bench_function(*name, |b| b.iter(|| cat.query(q).unwrap()));
    }
    g.bench_function("audit-newest-100", |b| {
        b.iter(|| {
            cat.audit(&AuditQuery {
                limit: 100,
                ..AuditQuery::default()
            })
            .unwrap()
        })
    });
    g.bench_function("runs-per-state", |b| b.iter(|| cat.state_counts().unwrap()));
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
