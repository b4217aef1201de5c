//! `periscope recon RUN_DIR` and `periscope export` on a run the simulator just
//! captured, and on copies of it damaged the ways disks and crashes damage files: a
//! record corrupted in the middle of the histogram log, a missing pair plan.
use std::path::Path;

use periscope_daemon::store::{HISTOGRAM_LOG, read_log};
use periscope_recon::io::ytal::YtalCapture;
use periscope_tests::periscope;

const PLAN: &str = include_str!("data/plans/small-fbp.toml");

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_file() {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn recon_and_export_of_a_run_directory_whole_and_damaged() {
    let tmp = tempfile::tempdir().unwrap();
    let plan = tmp.path().join("plan.toml");
    std::fs::write(&plan, PLAN).unwrap();
    let run = tmp.path().join("run");
    let out = periscope(&["run", s(&plan), "--out", s(&run)]);
    assert_eq!(out.code, Some(0), "{out:?}");
    let records = read_log(&run).unwrap().records;
    assert!(records.len() > 20, "{}", records.len());

    // Offline recon of the run reproduces the run's own volume, byte for byte (FBP is
    // deterministic and reads the same stored histograms).
    let again = tmp.path().join("again");
    let out = periscope(&["recon", s(&run), "--out", s(&again)]);
    assert_eq!(out.code, Some(0), "{out:?}");
    assert_eq!(
        std::fs::read(again.join("volume.npy")).unwrap(),
        std::fs::read(run.join("volume.npy")).unwrap(),
        "offline recon differs from the run's own"
    );
    assert!(again.join("depth.png").is_file());

    // Export: one transient per stored record, in pair order, the stored counts with
    // pile-up undone as every reconstruction of the run sees them.
    let (_, _, inst) = periscope_daemon::run_dir::RunDir::new(&run).load().unwrap();
    let cap = tmp.path().join("cap.hdf5");
    let out = periscope(&["export", s(&run), "--out", s(&cap)]);
    assert_eq!(out.code, Some(0), "{out:?}");
    let c = YtalCapture::read(&cap).unwrap();
    assert_eq!(c.len(), records.len());
    let mut sorted = records.clone();
    sorted.sort_by_key(|r| r.pair);
    assert_eq!(c.bins(), sorted[0].counts.len());
    for (k, r) in sorted.iter().enumerate() {
        let h: Vec<f32> = c.transient(k).collect();
        let want = periscope_daemon::pipeline::record_counts(r, &inst);
        assert_eq!(h, want, "transient {k} (pair {})", r.pair);
        let raw: f32 = r.counts.iter().map(|&v| v as f32).sum();
        let total: f32 = h.iter().sum();
        assert!(
            total >= raw && total < 1.1 * raw,
            "pair {}: {total} from {raw} counted",
            r.pair
        );
    }
    // Corrected, the counts are no longer whole numbers, but they are photon counts
    // still: a reconstruction of the export models their noise as the run's own does.
    assert!(
        (0..c.len()).any(|k| c.transient(k).any(|v| v.fract() != 0.0)),
        "pile-up undone leaves fractions"
    );
    let volume = c.default_volume().unwrap();
    assert!(
        c.transients(&volume).unwrap().is_photon_counts(),
        "the export's corrected counts read as noise-free data"
    );

    // An export whose --out is one of the run's own files would replace the run's
    // data with the export: refused, naming the file, and the log left as it was.
    let before = std::fs::read(run.join(HISTOGRAM_LOG)).unwrap();
    for own in [HISTOGRAM_LOG, "run.json"] {
        let out = periscope(&["export", s(&run), "--out", s(&run.join(own))]);
        assert_eq!(out.code, Some(1), "{out:?}");
        assert!(out.stderr.contains("is in a run directory"), "{out:?}");
    }
    assert_eq!(std::fs::read(run.join(HISTOGRAM_LOG)).unwrap(), before);

    // A record damaged in the middle of the log: recon and export use every record
    // but that one, and leave the damaged run as it was.
    let damaged = tmp.path().join("damaged");
    copy_dir(&run, &damaged);
    let log = damaged.join(HISTOGRAM_LOG);
    let mut bytes = std::fs::read(&log).unwrap();
    let record_len = bytes.len() / records.len();
    let middle = records.len() / 2;
    bytes[middle * record_len + 40] ^= 0x10;
    std::fs::write(&log, &bytes).unwrap();
    let out = periscope(&["recon", s(&damaged), "--out", s(&tmp.path().join("d-recon"))]);
    assert_eq!(out.code, Some(0), "{out:?}");
    let dcap = tmp.path().join("d.hdf5");
    let out = periscope(&["export", s(&damaged), "--out", s(&dcap)]);
    assert_eq!(out.code, Some(0), "{out:?}");
    assert_eq!(YtalCapture::read(&dcap).unwrap().len(), records.len() - 1);
    assert_eq!(
        std::fs::read(&log).unwrap(),
        bytes,
        "reading changed the damaged log"
    );
    // Nor another run's files: its log is its only copy of what it measured, and its
    // capture.hdf5 would hold this run's (until 2026-12-06 only the exported run's own
    // files were refused). Nor a file it has not written yet (a run still capturing
    // would take that capture.hdf5 as its own), nor one in its folders (`import/`
    // holds an imported run's only copy of its capture): until 2026-12-07 both were
    // written. The default, the run's own capture.hdf5, is not refused.
    let _ = std::fs::remove_file(damaged.join("capture.hdf5"));
    std::fs::create_dir(damaged.join("import")).unwrap();
    std::fs::write(damaged.join("import/scene.hdf5"), b"the imported capture").unwrap();
    for other in [
        "capture.hdf5",
        HISTOGRAM_LOG,
        "run.json",
        "import/scene.hdf5",
        "import/new.hdf5",
    ] {
        let out = periscope(&["export", s(&run), "--out", s(&damaged.join(other))]);
        assert_eq!(out.code, Some(1), "{other}: {out:?}");
        assert!(out.stderr.contains("is in a run directory"), "{out:?}");
        if other == "capture.hdf5" {
            assert!(!damaged.join(other).exists(), "written before the run had one");
            std::fs::write(damaged.join(other), b"an earlier export").unwrap();
        }
    }
    assert_eq!(std::fs::read(&log).unwrap(), bytes);
    assert_eq!(
        std::fs::read(damaged.join("capture.hdf5")).unwrap(),
        b"an earlier export"
    );
    assert_eq!(
        std::fs::read(damaged.join("import/scene.hdf5")).unwrap(),
        b"the imported capture"
    );
    assert!(!damaged.join("import/new.hdf5").exists());
    // Nor the daemon's own files in a runs directory (told by another of them beside
    // it): until 2026-12-07 an export could replace the keys or the queue.
    let runs = tmp.path().join("runs");
    std::fs::create_dir(&runs).unwrap();
    std::fs::write(runs.join("queue.json"), b"[]").unwrap();
    std::fs::write(runs.join("keys.json"), b"the keys").unwrap();
    let out = periscope(&["export", s(&run), "--out", s(&runs.join("keys.json"))]);
    assert_eq!(out.code, Some(1), "{out:?}");
    assert!(out.stderr.contains("one of the daemon's files"), "{out:?}");
    assert_eq!(std::fs::read(runs.join("keys.json")).unwrap(), b"the keys");
    // A file of that name anywhere else is the user's to write.
    let mine = tmp.path().join("keys.json");
    let out = periscope(&["export", s(&run), "--out", s(&mine)]);
    assert_eq!(out.code, Some(0), "{out:?}");
    let out = periscope(&["export", s(&run), "--out", s(&run.join("capture.hdf5"))]);
    assert_eq!(out.code, Some(0), "{out:?}");

    // No pair plan: a clear error naming the file, no output directory.
    let planless = tmp.path().join("planless");
    copy_dir(&run, &planless);
    std::fs::remove_file(planless.join("pairs.json")).unwrap();
    let nowhere = tmp.path().join("nowhere");
    let out = periscope(&["recon", s(&planless), "--out", s(&nowhere)]);
    assert_eq!(out.code, Some(1), "{out:?}");
    assert!(out.stderr.contains("pairs.json"), "{}", out.stderr);
    assert!(!nowhere.exists(), "an output directory for a refused recon");
    let out = periscope(&["export", s(&planless), "--out", s(&tmp.path().join("p.hdf5"))]);
    assert_eq!(out.code, Some(1), "{out:?}");
    assert!(out.stderr.contains("pairs.json"), "{}", out.stderr);

    // A pair plan emptied after the capture: named as what is wrong (until 2026-12-06
    // the run read as holding no measured pairs), the histograms left as they were.
    let emptied = tmp.path().join("emptied");
    copy_dir(&run, &emptied);
    std::fs::write(emptied.join("pairs.json"), "[]").unwrap();
    for args in [
        ["recon", s(&emptied), "--out", s(&nowhere)],
        ["export", s(&emptied), "--out", s(&tmp.path().join("e.hdf5"))],
    ] {
        let out = periscope(&args);
        assert_eq!(out.code, Some(1), "{out:?}");
        assert!(
            out.stderr.contains("pairs.json: lists 0 pairs") && out.stderr.contains("damaged or was emptied"),
            "{}",
            out.stderr
        );
    }
    assert_eq!(read_log(&emptied).unwrap().records.len(), records.len());
}

/// `periscope recon CAPTURE --adaptive-replay ORDER` on a y-tal capture: the pairs are
/// revealed batch by batch up to the `[adaptive]` budget, the choices go to
/// adaptive.json, and the adaptive order (which needs the running fit) is refused for
/// a solver with a message naming the method and what to do.
#[test]
fn an_adaptive_replay_reveals_its_budget_and_records_each_choice() {
    let tmp = tempfile::tempdir().unwrap();
    let capture = periscope_tests::repo_path("tests/data/ytal/confocal_xy.hdf5");
    let total = YtalCapture::read(&capture).unwrap().len();
    let config = tmp.path().join("recon.toml");
    let gtr = "method = \"gtr\"\n[volume]\nx = [-0.4, 0.4]\ny = [-0.4, 0.4]\nz = [0.2, 0.9]\nshape = [16, 16, 16]\n\
               [gtr]\nprimitives = 200\nepochs = 2\nvirtual-grid = [16, 16]\n\
               [adaptive]\npairs = 40\nfirst = 16\nbatch = 8\nlive-steps = 8\n";
    std::fs::write(&config, gtr).unwrap();
    let record = |out: &Path| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(out.join("adaptive.json")).unwrap()).unwrap()
    };
    // `periscope recon` replaying the capture into `out`, in `order` (`None`: the bare flag).
    let replay = |out: &Path, order: Option<&str>| {
        let mut args = vec![
            "recon",
            s(&capture),
            "--config",
            s(&config),
            "--out",
            s(out),
            "--adaptive-replay",
        ];
        args.extend(order);
        periscope(&args)
    };
    for order in ["adaptive", "uniform", "random"] {
        let out = tmp.path().join(order);
        let done = replay(&out, Some(order));
        assert_eq!(done.code, Some(0), "{order}: {done:?}");
        assert!(
            done.stdout.contains("reconstructed 40 pairs"),
            "{order}: {}",
            done.stdout
        );
        assert!(out.join("volume.npy").is_file());
        let r = record(&out);
        assert_eq!(
            (
                r["order"].as_str(),
                r["candidates"].as_u64(),
                r["measured"].as_u64()
            ),
            (Some(order), Some(total as u64), Some(40))
        );
        let batches = r["batches"].as_array().unwrap();
        let sizes: Vec<usize> = batches
            .iter()
            .map(|b| b["pairs"].as_array().unwrap().len())
            .collect();
        assert_eq!(sizes, vec![16, 8, 8, 8], "{order}");
        let mut all: Vec<u64> = batches
            .iter()
            .flat_map(|b| b["pairs"].as_array().unwrap().iter().map(|p| p.as_u64().unwrap()))
            .collect();
        all.sort_unstable();
        all.dedup();
        assert_eq!(all.len(), 40, "{order}: a pair revealed twice");
        if order == "adaptive" {
            assert!(
                batches[1..]
                    .iter()
                    .all(|b| b["how"] == "adaptive" && b["relative_gain"].is_number())
            );
        }
    }
    // The bare flag means the adaptive order; a solver cannot choose pairs.
    std::fs::write(&config, gtr.replace("method = \"gtr\"", "method = \"fbp\"")).unwrap();
    let out = tmp.path().join("refused");
    let done = replay(&out, None);
    assert_eq!(done.code, Some(2), "{done:?}");
    assert!(
        done.stderr.contains("\"fbp\"") && done.stderr.contains("method = \"gtr\""),
        "{}",
        done.stderr
    );
    assert!(!out.exists(), "an output directory for a refused replay");
    // The uniform order works for a solver too: it needs no fit.
    let out = tmp.path().join("fbp-uniform");
    let done = replay(&out, Some("uniform"));
    assert_eq!(done.code, Some(0), "{done:?}");
    assert_eq!(record(&out)["measured"], 40);
    // A plain recon into the same folder leaves no replay's record beside its volume
    // (until 2026-12-07 the replay's stayed, as if it had chosen the new volume's pairs).
    let done = periscope(&["recon", s(&capture), "--config", s(&config), "--out", s(&out)]);
    assert_eq!(done.code, Some(0), "{done:?}");
    assert!(out.join("volume.npy").is_file() && !out.join("adaptive.json").exists());
}
