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

    // An export whose --out is one of the run's own files would replace the run's
    // data with the export: refused, naming the file, and the log left as it was.
    let before = std::fs::read(run.join(HISTOGRAM_LOG)).unwrap();
    for own in [HISTOGRAM_LOG, "run.json"] {
        let out = periscope(&["export", s(&run), "--out", s(&run.join(own))]);
        assert_eq!(out.code, Some(1), "{out:?}");
        assert!(out.stderr.contains("is one of the run's own files"), "{out:?}");
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

    // No pair plan: a clear error naming the file, no output directory.
    let planless = tmp.path().join("planless");
    copy_dir(&run, &planless);
    std::fs::remove_file(planless.join("pairs.json")).unwrap();
    let nowhere = tmp.path().join("nowhere");
    let out = periscope(&["recon", s(&planless), "--out", s(&nowhere)]);
    assert_eq!(out.code, Some(1), "{out:?}");
    assert!(out.stderr.contains("pairs.json"), "{}", out.stderr);
    let out = periscope(&["export", s(&planless), "--out", s(&tmp.path().join("p.hdf5"))]);
    assert_eq!(out.code, Some(1), "{out:?}");
    assert!(out.stderr.contains("pairs.json"), "{}", out.stderr);
}
