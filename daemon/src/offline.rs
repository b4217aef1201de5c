//! `periscope recon CAPTURE`: reconstruct a stored run again, with other settings or
//! another method, without the instrument; or a y-tal HDF5 capture (a public dataset,
//! or another lab's).
use std::path::{Path, PathBuf};

use std::sync::mpsc;

use periscope_recon::TransientSet;
use periscope_recon::gtr::LiveModel;

use crate::adaptive::{Order, Selector};
use crate::capture::{Capture, CaptureError, Transients};
use crate::config::{ConfigError, TomlSource};
use crate::events::{EventSink, RunEvent};
use crate::pipeline::{self, Control, Fit, PipelineError, ReconError, ReconInput};
use crate::plan::{Method, ReconSettings};

/// Why `periscope recon CAPTURE` failed; every variant names the capture or file.
#[derive(Debug, thiserror::Error)]
pub enum OfflineError {
    /// The capture could not be opened or give its transients.
    #[error(transparent)]
    Capture(#[from] CaptureError),
    /// A file could not be read or written.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The RECON.toml is invalid.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The reconstruction or its outputs failed.
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    /// The volume needs more memory than this machine has free.
    #[error(
        "{}: the volume of {shape:?} voxels needs about {:.1} GiB ({per} bytes a voxel {why}), more than the {:.1} GiB free to this process (the machine's available memory, within any address-space limit): a smaller [volume] shape (a RECON.toml given with --config sets it), or coarser voxels over the same bounds",
        config.display(),
        *need as f64 / GIB,
        *available as f64 / GIB
    )]
    Memory {
        /// The RECON.toml, or the capture whose defaults set the volume.
        config: PathBuf,
        /// The volume's shape.
        shape: [usize; 3],
        /// Bytes a voxel.
        per: u64,
        /// What the bytes a voxel hold.
        why: &'static str,
        /// Bytes needed.
        need: u64,
        /// Bytes free.
        available: u64,
    },
    /// The volume fits, but with 3D-GTR's virtual scan and its solver it does not.
    #[error(
        "{}: with the volume ({:.1} GiB), {what} need about {:.1} GiB more, more than the {:.1} GiB free to this process (the machine's available memory, within any address-space limit): a smaller {keys}, or a smaller [volume] shape",
        config.display(),
        *volume as f64 / GIB,
        *need as f64 / GIB,
        *available as f64 / GIB
    )]
    VirtualScan {
        /// The RECON.toml, or the capture whose defaults set the settings.
        config: PathBuf,
        /// What the bytes hold.
        what: String,
        /// The settings that size it.
        keys: &'static str,
        /// Bytes the volume needs.
        volume: u64,
        /// Bytes the virtual scan and its solver need.
        need: u64,
        /// Bytes free.
        available: u64,
    },
    /// An adaptive replay was asked for with a method that has no running fit.
    #[error(
        "--adaptive-replay adaptive chooses pairs from the running 3D-GTR fit, but the settings' method is {method}: use method = \"gtr\", or replay the uniform or random order"
    )]
    AdaptiveNeedsGtr {
        /// The method asked for.
        method: String,
    },
}

impl OfflineError {
    /// Whether a configuration is at fault: the RECON.toml, the stored run's plan or
    /// instrument, or settings the data cannot support (exit code 2).
    pub fn is_config(&self) -> bool {
        match self {
            OfflineError::Config(_)
            | OfflineError::AdaptiveNeedsGtr { .. }
            | OfflineError::Memory { .. }
            | OfflineError::VirtualScan { .. }
            | OfflineError::Pipeline(PipelineError::Config(_)) => true,
            OfflineError::Capture(e) => e.is_config(),
            OfflineError::Pipeline(PipelineError::Recon(e)) => e.is_settings(),
            OfflineError::Io { .. } | OfflineError::Pipeline(_) => false,
        }
    }
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> OfflineError + '_ {
    move |source| OfflineError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Reconstructs `capture` (a run directory or a y-tal file) into `out`, with the
/// settings of the RECON.toml at `config`, or else the run's plan's (the defaults
/// derived for the capture, for a y-tal file).
pub fn recon(capture: &Path, config: Option<&Path>, out: &Path) -> Result<(), OfflineError> {
    let (settings, t) = load(capture, config)?;
    let input = ReconInput {
        settings,
        set: t.set,
        detection_points: t.detection_points,
        viewpoint: t.viewpoint,
    };
    finish(input, out)
}

/// Opens `capture`, reads its settings and transients, and says what it read.
fn load(capture: &Path, config: Option<&Path>) -> Result<(ReconSettings, Transients), OfflineError> {
    let capture_path = capture;
    let capture = Capture::open(capture)?;
    let settings = match config {
        Some(path) => capture.recon_from::<OfflineError>(&TomlSource::load(path)?)?,
        None => capture.default_recon()?,
    };
    volume_fits(&settings, config.unwrap_or(capture_path))?;
    let t = capture.transients(&settings.volume, settings.laser_falloff)?;
    println!("{}", capture.describe());
    if let Some(f) = &t.falloff {
        println!(
            "  laser falloff accounted for: cos θ / d² from the laser at ({:.3}, {:.3}, {:.3}) m, a gain of \
             {:.2} to {:.2} on each histogram (in 3D-GTR's model; the solvers divide it out) ({}; \
             laser-falloff = \"none\" takes the counts as they are)",
            f.laser.x,
            f.laser.y,
            f.laser.z,
            1.0 / f.range.1,
            1.0 / f.range.0,
            f.why
        );
    }
    if t.overflowed > 0 {
        println!(
            "  {} histograms flagged overflow left out (their counts are only a lower bound)",
            t.overflowed
        );
    }
    Ok((settings, t))
}

/// Bytes in a GiB.
const GIB: f64 = (1u64 << 30) as f64;

/// Refuses a volume this machine cannot hold before anything is computed: a process
/// that asks for more memory than there is gets aborted by its allocator, or killed,
/// minutes into the work. The figures are what `periscope recon` was measured to take
/// (peak resident memory over the volume's voxels, 2026-12-06, at 256³ to 1024³ on
/// the validation captures): about 20 bytes a voxel where FBP with its phasor filter
/// makes the volume (the complex accumulation, the magnitude and the output), whether
/// as the method or after 3D-GTR; 8 with the Laplacian filter, 4 unfiltered; 4 where
/// LCT, f-k or RSD solve on the capture's own grid and resample to the volume.
fn volume_fits(settings: &ReconSettings, config: &Path) -> Result<(), OfflineError> {
    use periscope_recon::solver::SolverKind;
    let Some(available) = periscope_recon::io::memory_available() else {
        return Ok(());
    };
    let fbp = match settings.method {
        Method::Gtr => settings.solver == SolverKind::Fbp,
        Method::Solver(kind) => kind == SolverKind::Fbp,
    };
    use periscope_recon::solver::FbpFilter;
    let (per, why) = match settings.solvers.fbp.filter {
        FbpFilter::Phasor if fbp => (20u64, "where FBP's phasor filter makes it"),
        FbpFilter::Laplacian if fbp => (8, "where FBP's Laplacian filter makes it"),
        _ => (4, "for the volume the solver makes"),
    };
    let shape = settings.volume.shape;
    let need = shape.iter().fold(per, |a, &n| a.saturating_mul(n as u64));
    if need > available {
        return Err(OfflineError::Memory {
            config: config.to_owned(),
            shape,
            per,
            why,
            need,
            available,
        });
    }
    // 3D-GTR's virtual scan, its solver's work arrays and the primitives, as a plan's
    // budget counts them (the first item, the volume's upper estimate, is measured
    // above): a virtual grid of 1024 × 1024 points alone asks 8 GiB.
    if settings.method == Method::Gtr {
        let items: Vec<_> = crate::budget::recon_items(settings, 0, 0, false)
            .into_iter()
            .skip(1)
            .collect();
        let extra = items.iter().fold(0u64, |a, i| a.saturating_add(i.bytes));
        if need.saturating_add(extra) > available
            && let Some(largest) = items.iter().max_by_key(|i| i.bytes)
        {
            return Err(OfflineError::VirtualScan {
                config: config.to_owned(),
                what: items.iter().map(|i| i.what).collect::<Vec<_>>().join(" and "),
                keys: largest.keys,
                volume: need,
                need: extra,
                available,
            });
        }
    }
    Ok(())
}

/// `periscope recon CAPTURE --adaptive-replay ORDER`: emulates an adaptive capture on
/// a recorded one. Its transients are the candidates; batches are revealed to the fit
/// as a capture would measure them (the first spread over the candidates, each next
/// chosen in `order` from the fit after the last one's live training), up to the
/// `[adaptive]` budget; the pairs revealed are then fitted afresh, as a live adaptive
/// capture's are, and the outputs written to `out`, with `adaptive.json` (each batch's
/// choice) beside them. The uniform
/// and random orders run the same streamed fit and differ only in the choice, so the
/// three compare like for like.
pub fn replay(capture: &Path, config: Option<&Path>, out: &Path, order: Order) -> Result<(), OfflineError> {
    let (settings, t) = load(capture, config)?;
    if settings.method != Method::Gtr && order == Order::Adaptive {
        return Err(OfflineError::AdaptiveNeedsGtr {
            method: serde_json::to_string(&settings.method).expect("a name"),
        });
    }
    std::fs::create_dir_all(out).map_err(io(out))?;
    let events = EventSink::open(out).map_err(io(out))?;
    crate::progress::attach(&events);
    let control = Control::new();
    let clock = std::time::Instant::now();
    let axis = *t.set.axis();
    // Each candidate is weighed through the bins its recording covers, as the fit reads them.
    let recorded = (0..t.set.len())
        .map(|i| {
            let r = t.set.recorded(i);
            (axis.edge(r.start as isize), axis.edge(r.end as isize))
        })
        .collect();
    let mut selector =
        Selector::new(t.set.pairs().to_vec(), settings.adaptive.clone(), order).with_recorded(recorded);
    println!(
        "  replaying the {order} order: up to {} of its {} pairs",
        selector.budget(),
        t.set.len()
    );
    let mut batches = vec![selector.first()];
    events.emit(RunEvent::PairsChosen(batches[0].clone()));
    let first = t.set.subset(&batches[0].pairs);
    let empty = TransientSet::new(axis)
        .map_err(ReconError::from)
        .map_err(PipelineError::from)?;
    let input = ReconInput {
        settings: settings.clone(),
        set: empty,
        detection_points: t.detection_points,
        viewpoint: t.viewpoint,
    };
    let result = if settings.method == Method::Gtr {
        let mut fit = Fit::new(input)?;
        let (tx, rx) = mpsc::channel::<TransientSet>();
        let (model_tx, model_rx) = mpsc::channel();
        fit.start_training(
            first,
            rx,
            events.clone(),
            control.clone(),
            Some((model_tx, settings.adaptive.live_steps)),
        )?;
        // The fit sends its model once each batch has had its live training; a fit that
        // ended (an error, which `refit` reports) sends no more.
        while let Ok(model) = model_rx.recv() {
            let Some(b) = selector.next(&model, &axis) else {
                break;
            };
            events.emit(RunEvent::PairsChosen(b.clone()));
            let more = t.set.subset(&b.pairs);
            batches.push(b);
            if tx.send(more).is_err() {
                break;
            }
        }
        drop(tx);
        fit.refit(&events, &control)?
    } else {
        let model = LiveModel {
            kernels: Vec::new(),
            options: settings.train.render,
            pairs: 0,
            step: 0,
        };
        while let Some(b) = selector.next(&model, &axis) {
            events.emit(RunEvent::PairsChosen(b.clone()));
            batches.push(b);
        }
        pipeline::reconstruct(
            ReconInput {
                set: t.set.subset(selector.measured()),
                ..input
            },
            &events,
            &control,
        )?
    };
    if let Some(why) = selector.stopped() {
        println!("  stopped before the budget: {why}");
    }
    let record = serde_json::json!({
        "order": order,
        "candidates": t.set.len(),
        "budget": selector.budget(),
        "measured": selector.measured().len(),
        "stopped": selector.stopped(),
        "settings": settings.adaptive,
        "batches": batches,
    });
    let path = out.join(ADAPTIVE_JSON);
    crate::store::write_atomic(&path, &serde_json::to_vec_pretty(&record).expect("plain data"))
        .map_err(io(&path))?;
    report(&result, out, clock, &events)?;
    println!("  {}", path.display());
    Ok(())
}

/// The replay's record of each batch's choice.
pub const ADAPTIVE_JSON: &str = "adaptive.json";

/// The process's peak resident memory (`VmHWM` of /proc/self/status), bytes; `None`
/// where /proc is not there (not Linux).
fn peak_memory_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let kib = status.lines().find_map(|l| l.strip_prefix("VmHWM:"))?;
    Some(kib.trim().trim_end_matches("kB").trim().parse::<u64>().ok()? * 1024)
}

/// Runs the reconstruction and writes its outputs to `out`.
fn finish(input: ReconInput, out: &Path) -> Result<(), OfflineError> {
    std::fs::create_dir_all(out).map_err(io(out))?;
    let events = EventSink::open(out).map_err(io(out))?;
    crate::progress::attach(&events);
    let t = std::time::Instant::now();
    let result = pipeline::reconstruct(input, &events, &Control::new())?;
    report(&result, out, t, &events)?;
    // An earlier replay's record into the same folder is not this volume's.
    let stale = out.join(ADAPTIVE_JSON);
    match std::fs::remove_file(&stale) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(io(&stale)(e)),
        _ => Ok(()),
    }
}

/// Writes the outputs of `result` to `out` and says what took how long.
fn report(
    result: &pipeline::ReconResult,
    out: &Path,
    t: std::time::Instant,
    events: &EventSink,
) -> Result<(), OfflineError> {
    let outputs = pipeline::write_outputs(out, result, events)?;
    let peak = peak_memory_bytes().map_or(String::new(), |b| {
        format!(", peak memory {:.0} MiB", b as f64 / (1u64 << 20) as f64)
    });
    println!(
        "reconstructed {} pairs in {:.1} s{peak}",
        result.pairs,
        t.elapsed().as_secs_f64()
    );
    for f in &outputs.files {
        println!("  {}", out.join(f).display());
    }
    Ok(())
}
