//! `periscope recon CAPTURE`: reconstruct a stored run again, with other settings or
//! another method, without the instrument; or a y-tal HDF5 capture (a public dataset,
//! or another lab's).
use std::path::Path;

use periscope_recon::{Pair, TransientSet};

use crate::config::TomlSource;
use crate::events::EventSink;
use crate::pipeline::{self, Control, ReconInput};
use crate::plan::{default_recon, load_recon};
use crate::run_dir::RunDir;
use crate::ytal::{YtalCapture, is_hdf5_path};

/// Reconstructs `capture` (a run directory) into `out`.
pub fn recon(capture: &Path, config: Option<&Path>, out: &Path) -> anyhow::Result<()> {
    anyhow::ensure!(
        capture.exists(),
        "capture {} does not exist: give a run directory or a y-tal .hdf5/.h5 file",
        capture.display()
    );
    if capture.is_file() {
        return recon_ytal(capture, config, out);
    }
    anyhow::ensure!(
        RunDir::holds_run(capture),
        "{} is not a run directory (no run.json)",
        capture.display()
    );
    let run = RunDir::new(capture);
    let (_info, plan, inst) = run.load()?;
    let pairs = run.pairs()?;
    let settings = match config {
        Some(path) => load_recon(&TomlSource::load(path)?, Some(plan.recon.volume))?,
        None => plan.recon.clone(),
    };
    let records = crate::store::read_log(capture)?;
    anyhow::ensure!(
        !records.records.is_empty(),
        "{} holds no measured pairs",
        capture.display()
    );
    let (l, s) = (inst.laser_arm.pose.origin, inst.spad_arm.pose.origin);
    let recon_pairs: Vec<Pair> = pairs
        .iter()
        .map(|p| Pair {
            xi: p.xi,
            ni: p.ni,
            xd: p.xd,
            nd: p.nd,
        })
        .collect();
    let axis =
        periscope_recon::transient::hidden_axis(&recon_pairs, &settings.volume, plan.acquisition.bin_width)
            .map_err(|e| anyhow::anyhow!("{}: {e}", capture.display()))?;
    let mut set = TransientSet::new(axis)?;
    let mut used = Vec::new();
    let mut overflowed = 0usize;
    for r in &records.records {
        let Some(p) = pairs.get(r.pair as usize) else {
            continue;
        };
        match pipeline::record_transient(r, p, &inst, &axis) {
            Some(h) => {
                set.push(recon_pairs[r.pair as usize], &h)?;
                used.push(p.xd);
            }
            None => overflowed += 1,
        }
    }
    if overflowed > 0 {
        println!(
            "{}: {overflowed} histograms flagged overflow left out (their counts are only a lower bound)",
            capture.display()
        );
    }
    anyhow::ensure!(
        !set.is_empty(),
        "{}: every stored histogram is flagged overflow; nothing to reconstruct from",
        capture.display()
    );
    let input = ReconInput {
        settings,
        set,
        detection_points: used,
        viewpoint: 0.5 * (l + s),
    };
    finish(input, out)
}

/// Reconstructs a y-tal HDF5 capture.
fn recon_ytal(capture: &Path, config: Option<&Path>, out: &Path) -> anyhow::Result<()> {
    if !is_hdf5_path(capture) {
        anyhow::bail!(
            "{} is a file but not a y-tal capture (.hdf5 or .h5); give a capture file or a run directory",
            capture.display()
        );
    }
    let ytal = YtalCapture::read(capture)?;
    let settings = match config {
        Some(path) => load_recon(&TomlSource::load(path)?, ytal.default_volume().ok())?,
        None => default_recon(ytal.default_volume()?),
    };
    let set = ytal.transients(&settings.volume)?;
    anyhow::ensure!(
        !set.is_empty(),
        "{}: every transient is empty inside the reconstruction volume's time range",
        capture.display()
    );
    println!(
        "{}: {} transients ({}), {} bins of {:.4} m{}",
        capture.display(),
        ytal.len(),
        ytal.h_format.name(),
        ytal.bins(),
        ytal.delta_t,
        if ytal.t_accounts_first_and_last_bounces {
            ", first and last legs removed"
        } else {
            ""
        }
    );
    let input = ReconInput {
        settings,
        set,
        detection_points: ytal.sensor_grid.points.clone(),
        viewpoint: ytal.viewpoint(),
    };
    finish(input, out)
}

/// Runs the reconstruction and writes its outputs to `out`.
fn finish(input: ReconInput, out: &Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(out)?;
    let events = EventSink::open(out)?;
    crate::progress::attach(&events);
    let t = std::time::Instant::now();
    let result = pipeline::reconstruct(input, &events, &Control::new())?;
    let outputs = pipeline::write_outputs(out, &result, &events)?;
    println!(
        "reconstructed {} pairs in {:.1} s",
        result.pairs,
        t.elapsed().as_secs_f64()
    );
    for f in &outputs.files {
        println!("  {}", out.join(f).display());
    }
    Ok(())
}
