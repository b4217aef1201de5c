//! One model of a capture, whatever holds it: a run (its directory on disk, or what a
//! run in progress holds in memory) or a y-tal HDF5 file. A reconstruction gets its
//! transients from either through [`Capture::transients`]; a run becomes a y-tal file
//! through [`RunCapture::to_ytal`]. `periscope recon`, `periscope export`, the run's
//! outputs stage and the API's `capture.hdf5` download all go through here.
use std::path::{Path, PathBuf};

use glam::DVec3;
use periscope_recon::io::ytal::{
    FLAG_OVERFLOW, FLAG_SATURATED, Grid, GridFormat, HFormat, MAX_DATASET_BYTES, YtalCapture, YtalError,
    is_hdf5_path, yaml_string,
};
use periscope_recon::transient::rebin_path;
use periscope_recon::{TimeAxis, TransientError, TransientSet, VolumeGrid};

use crate::config::{ConfigError, InstrumentConfig, TomlSource};
use crate::plan::{LaserFalloff, Plan, PlannedPair, ReconSettings, check_recon, default_recon, load_recon};
use crate::record::{push_record, record_axis, record_counts, relay_gains, run_axis};
use crate::run_dir::RunInfo;
use crate::run_dir::{RunDir, RunDirError, file};
use crate::store::Record;
use crate::ytal::ExportError;

/// Why a capture could not be opened or give its transients; every variant names the
/// capture.
#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    /// The path does not exist.
    #[error("capture {} does not exist: give a run directory or a capture file (.hdf5/.h5: y-tal, ZNLOS; .mat: Stanford LCT or f-k, phasor field)", .0.display())]
    Missing(PathBuf),
    /// A directory without `run.json`.
    #[error("{} is not a run directory (no run.json)", .0.display())]
    NotRun(PathBuf),
    /// A file that is not `.hdf5`, `.h5` or `.mat`.
    #[error(
        "{} is a file but not a capture (.hdf5/.h5: y-tal, ZNLOS; .mat: Stanford LCT or f-k, phasor field; docs/formats.md); give a capture file or a run directory",
        .0.display()
    )]
    NotCapture(PathBuf),
    /// The run's state, plan, instrument or pairs could not be read.
    #[error(transparent)]
    Run(#[from] RunDirError),
    /// The run's histogram log could not be read.
    #[error("{}: {source}", path.display())]
    Log {
        /// The log file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The y-tal file could not be read or does not fit the volume.
    #[error(transparent)]
    Ytal(#[from] YtalError),
    /// A run that stored no histogram.
    #[error("{} holds no measured pairs", .0.display())]
    NoPairs(PathBuf),
    /// A run whose `pairs.json` lists none of the pairs its stored histograms are of
    /// (emptied or cut short after the capture).
    #[error(
        "{}: lists {listed} pairs, but every one of the {records} histograms stored is of a pair past them \
         (up to pair {highest}): the file is damaged or was emptied after the capture; restore it from a \
         backup (the histograms are kept)",
        path.display()
    )]
    PairsMissing {
        /// `pairs.json`.
        path: PathBuf,
        /// Pairs it lists.
        listed: usize,
        /// Histograms stored.
        records: usize,
        /// The highest pair index among them.
        highest: usize,
    },
    /// A run whose every histogram overflowed.
    #[error("{}: every stored histogram is flagged overflow; nothing to reconstruct from", .0.display())]
    AllOverflowed(PathBuf),
    /// A y-tal capture with no signal inside the volume's time range.
    #[error(
        "{}: every transient is empty inside the reconstruction volume's time range{}",
        path.display(),
        if *overflowed > 0 { format!(" ({overflowed} more are flagged overflow and left out)") } else { String::new() }
    )]
    NothingInWindow {
        /// The capture.
        path: PathBuf,
        /// Transients left out because they are flagged overflow.
        overflowed: usize,
    },
    /// The transients or their time axis do not fit the volume.
    #[error("{}: {source}", path.display())]
    Transients {
        /// The capture.
        path: PathBuf,
        /// Why.
        source: TransientError,
    },
    /// `laser-falloff = "cos-inverse-square"` on a capture that cannot take it.
    #[error(
        "{}: laser-falloff = \"cos-inverse-square\": {reason}; set laser-falloff = \"none\" for a collimated \
         laser, or \"auto\"",
        path.display()
    )]
    LaserFalloff {
        /// The capture.
        path: PathBuf,
        /// Why.
        reason: String,
    },
}

impl CaptureError {
    /// Whether a configuration is at fault (a stored run's plan or instrument that no
    /// longer loads).
    pub fn is_config(&self) -> bool {
        matches!(self, CaptureError::Run(RunDirError::Config(_)))
    }
}

/// What a reconstruction takes from a capture.
#[derive(Clone, Debug)]
pub struct Transients {
    /// Transients in hidden path length, on the axis the volume needs.
    pub set: TransientSet,
    /// The detection points of the transients kept (the virtual relay is fitted to them).
    pub detection_points: Vec<DVec3>,
    /// A point on the instrument's side (orients the virtual relay).
    pub viewpoint: DVec3,
    /// Transients left out because their counts are only a lower bound (overflow).
    pub overflowed: usize,
    /// The laser falloff divided out of the counts, if any.
    pub falloff: Option<FalloffApplied>,
}

/// A point-source laser's falloff, divided out of a capture's counts
/// ([`TransientSet::compensate_laser_falloff`]).
#[derive(Clone, Debug, PartialEq)]
pub struct FalloffApplied {
    /// The laser's origin, metres.
    pub laser: DVec3,
    /// The smallest and largest multiplier applied to a histogram.
    pub range: (f64, f64),
    /// Why: the setting, or what `auto` saw in the capture.
    pub why: String,
}

/// A run's measurements: its state, plan, instrument, planned pairs and the stored
/// record of each measured pair, in the order they were stored (the order the run's
/// own fit received them, so a reconstruction from here repeats it exactly).
#[derive(Clone, Debug)]
pub struct RunCapture {
    dir: PathBuf,
    info: RunInfo,
    plan: Plan,
    instrument: InstrumentConfig,
    pairs: Vec<PlannedPair>,
    records: Vec<Record>,
}

impl RunCapture {
    /// Reads a run directory: `run.json`, the plan and instrument it was started with,
    /// `pairs.json` and every valid record of `histograms.bin`.
    pub fn load(dir: &Path) -> Result<RunCapture, CaptureError> {
        let run = RunDir::new(dir);
        let (info, plan, instrument) = run.load()?;
        let pairs = run.pairs()?;
        let log = crate::store::read_log(dir).map_err(|source| CaptureError::Log {
            path: run.file(file::HISTOGRAMS),
            source,
        })?;
        if log.discarded_bytes > 0 {
            // What is reconstructed or exported from a damaged log is said, never
            // passed off as the whole capture.
            tracing::warn!(
                run = %dir.display(),
                "the histogram log is damaged ({} bytes in {} places unreadable): using the {} of {} \
                 planned pairs that survive; `periscope resume` measures the rest again",
                log.discarded_bytes,
                log.damaged.len(),
                log.records.len(),
                pairs.len()
            );
        }
        let beyond: Vec<usize> = log
            .records
            .iter()
            .map(|r| r.pair as usize)
            .filter(|&p| p >= pairs.len())
            .collect();
        if !beyond.is_empty() {
            let highest = beyond.iter().copied().max().unwrap_or(0);
            if beyond.len() == log.records.len() {
                return Err(CaptureError::PairsMissing {
                    path: run.file(file::PAIRS),
                    listed: pairs.len(),
                    records: beyond.len(),
                    highest,
                });
            }
            tracing::warn!(
                run = %dir.display(),
                "{} lists {} pairs, but {} of the {} histograms stored are of pairs past them (up to pair {highest}): \
                 those are left out; the file is damaged or was cut short after the capture",
                file::PAIRS,
                pairs.len(),
                beyond.len(),
                log.records.len()
            );
        }
        Ok(RunCapture::new(dir, info, plan, instrument, pairs, log.records))
    }

    /// What a run holds in memory (the outputs stage exports it without reading the
    /// directory back), records in the order they were stored. Records of pairs the
    /// plan does not have are dropped.
    pub fn new(
        dir: &Path,
        info: RunInfo,
        plan: Plan,
        instrument: InstrumentConfig,
        pairs: Vec<PlannedPair>,
        mut records: Vec<Record>,
    ) -> RunCapture {
        records.retain(|r| (r.pair as usize) < pairs.len());
        RunCapture {
            dir: dir.to_owned(),
            info,
            plan,
            instrument,
            pairs,
            records,
        }
    }

    /// The run's plan.
    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    /// The stored records, in the order they were stored.
    pub fn records(&self) -> &[Record] {
        &self.records
    }

    /// The transients for `volume`, as the run's own fit saw them: on the hidden-path
    /// axis of the planned pairs at the plan's bin width where the plan's TDC window
    /// records them ([`run_axis`]; runs before 2026-12-05 fitted the whole axis live),
    /// pile-up undone when the instrument asks for it, overflowed histograms left out
    /// (and counted).
    pub fn transients(&self, volume: &VolumeGrid) -> Result<Transients, CaptureError> {
        if self.records.is_empty() {
            return Err(CaptureError::NoPairs(self.dir.clone()));
        }
        let fail = |source| CaptureError::Transients {
            path: self.dir.clone(),
            source,
        };
        let axis = run_axis(&self.pairs, volume, &self.plan.acquisition, &self.instrument).map_err(fail)?;
        let mut set = TransientSet::new(axis).map_err(fail)?;
        set.mark_photon_counts();
        // The relay's albedo from its scan, as the run's own fit took it.
        let gains = crate::run_dir::read_relay_ply(&self.dir)?.and_then(|relay| {
            relay_gains(
                &relay,
                &self.pairs,
                &self.instrument,
                self.plan.relay.albedo_from_scan,
            )
        });
        let mut detection_points = Vec::new();
        let mut overflowed = 0;
        for r in &self.records {
            let p = &self.pairs[r.pair as usize];
            let gain = gains.as_ref().map(|g| g[r.pair as usize]);
            if push_record(&mut set, r, p, &self.instrument, gain).map_err(fail)? {
                detection_points.push(p.xd);
            } else {
                overflowed += 1;
            }
        }
        if set.is_empty() {
            return Err(CaptureError::AllOverflowed(self.dir.clone()));
        }
        let (l, s) = (
            self.instrument.laser_arm.pose.origin,
            self.instrument.spad_arm.pose.origin,
        );
        Ok(Transients {
            set,
            detection_points,
            viewpoint: 0.5 * (l + s),
            overflowed,
            falloff: None,
        })
    }

    /// The stored histograms as a y-tal capture: `T_Si` with paired `N_3` point lists
    /// (illumination point i with detection point i), the TDC counts (with pile-up and
    /// dead time undone when `tdc.pile-up-correction` is on, as every reconstruction of
    /// the run uses them; `histograms.bin` keeps them as counted), each histogram's
    /// flags (in `scene_info`), path lengths that include the legs from the laser and
    /// to the SPAD (`t_accounts_first_and_last_bounces`), and the galvo origins as
    /// `laser_xyz` and `sensor_xyz`. Transients in pair order; pairs never measured
    /// are left out.
    pub fn to_ytal(&self) -> Result<YtalCapture, ExportError> {
        let (plan, inst) = (&self.plan, &self.instrument);
        let mut records: Vec<&Record> = self.records.iter().collect();
        records.sort_by_key(|r| r.pair);
        let refuse = |message: String| ExportError::Refused {
            path: self.dir.clone(),
            message,
        };
        let Some(first) = records.first() else {
            return Err(refuse("holds no measured pairs to export".into()));
        };
        // The time axis: the first record's settings when they are the plan's shape,
        // else the plan's own (a damaged or forged log cannot size the export).
        let acq = &plan.acquisition;
        let (width, offset, bins) = if first.counts.len() == acq.bins as usize {
            (
                f64::from(first.bin_width_ps) * 1e-12,
                f64::from(first.offset_ps) * 1e-12,
                first.counts.len(),
            )
        } else {
            (acq.bin_width, acq.offset, acq.bins as usize)
        };
        let axis = TimeAxis::of_tdc(offset, width, bins, inst.tdc.system_delay);
        let n = records.len();
        if (bins as u64).saturating_mul(n as u64) > MAX_DATASET_BYTES / 4 {
            return Err(refuse(format!(
                "{n} records of {bins} bins are more than an export may hold"
            )));
        }
        let mut h = vec![0.0f32; bins * n];
        for (c, r) in records.iter().enumerate() {
            let same = f64::from(r.bin_width_ps) * 1e-12 == width
                && f64::from(r.offset_ps) * 1e-12 == offset
                && r.counts.len() == bins;
            let counts = record_counts(r, inst);
            let column: Vec<f32> = if same {
                counts
            } else {
                let own = record_axis(r, inst);
                rebin_path(counts, own.start, own.width, &axis)
            };
            for (k, v) in column.into_iter().enumerate() {
                h[k * n + c] = v;
            }
        }
        let grid = |f: &dyn Fn(&PlannedPair) -> (DVec3, DVec3)| {
            let (points, normals) = records.iter().map(|r| f(&self.pairs[r.pair as usize])).unzip();
            Grid {
                points,
                normals,
                format: GridFormat::N3,
                shape: vec![n],
            }
        };
        let dwell_s = records.iter().fold(0u64, |a, r| a.saturating_add(r.dwell_us)) as f64 * 1e-6;
        let scene_info = format!(
            "original_format: periscope\nrun: {}\nplan: {}\npairs_planned: {}\npairs_measured: {n}\n\
             dwell_total_s: {dwell_s}\nbin_width_s: {width}\nacquisition_offset_s: {offset}\n\
             system_delay_s: {}\nrepeats: {}\npile_up_corrected: {}\n",
            yaml_string(&self.info.id),
            yaml_string(&plan.name),
            self.pairs.len(),
            inst.tdc.system_delay,
            plan.acquisition.repeats,
            inst.tdc.pile_up_correction,
        );
        Ok(YtalCapture {
            h,
            h_shape: vec![bins, n],
            h_format: HFormat::TSi,
            sensor_grid: grid(&|p| (p.xd, p.nd)),
            laser_grid: grid(&|p| (p.xi, p.ni)),
            sensor_xyz: Some(inst.spad_arm.pose.origin),
            laser_xyz: Some(inst.laser_arm.pose.origin),
            delta_t: axis.width,
            t_start: axis.start,
            t_accounts_first_and_last_bounces: true,
            scene_info: Some(scene_info),
            flags: Some(
                records
                    .iter()
                    .map(|r| {
                        (if r.flags.overflow { FLAG_OVERFLOW } else { 0 })
                            | (if r.flags.saturated { FLAG_SATURATED } else { 0 })
                    })
                    .collect(),
            ),
        })
    }
}

/// A capture to reconstruct: a run or a y-tal file.
#[derive(Clone, Debug)]
pub enum Capture {
    /// A run's measurements.
    Run(Box<RunCapture>),
    /// A y-tal HDF5 capture, with the path it was read from.
    Ytal {
        /// Where it came from.
        path: PathBuf,
        /// The capture.
        capture: Box<YtalCapture>,
    },
}

impl Capture {
    /// Where the capture was read from: the run directory or the y-tal file.
    pub fn path(&self) -> &Path {
        match self {
            Capture::Run(run) => &run.dir,
            Capture::Ytal { path, .. } => path,
        }
    }

    /// Opens `path`: a run directory, or a capture file of any public format
    /// (`.hdf5`/`.h5`: y-tal, ZNLOS; `.mat`: Stanford LCT and f-k, phasor field), read
    /// into the same in-memory capture ([`periscope_recon::io::formats::read_capture`]
    /// tells the format from the contents).
    pub fn open(path: &Path) -> Result<Capture, CaptureError> {
        if !path.exists() {
            return Err(CaptureError::Missing(path.to_path_buf()));
        }
        if path.is_file() {
            if !is_hdf5_path(path) && !periscope_recon::io::lct::is_mat_path(path) {
                return Err(CaptureError::NotCapture(path.to_path_buf()));
            }
            return Ok(Capture::Ytal {
                path: path.to_path_buf(),
                capture: Box::new(periscope_recon::io::formats::read_capture(path)?),
            });
        }
        if !RunDir::holds_run(path) {
            return Err(CaptureError::NotRun(path.to_path_buf()));
        }
        // An imported capture's run reconstructs the file it holds.
        if let Ok(RunInfo {
            import: Some(source), ..
        }) = RunInfo::load(path)
        {
            return Capture::open(&path.join(file::IMPORT_DIR).join(source.capture));
        }
        Ok(Capture::Run(Box::new(RunCapture::load(path)?)))
    }

    /// The volume to use when the settings give none: the run's plan's, or one over
    /// a y-tal capture's relay and time range.
    pub fn default_volume(&self) -> Result<VolumeGrid, CaptureError> {
        match self {
            Capture::Run(run) => Ok(run.plan.recon.volume),
            Capture::Ytal { path, capture } => Ok(capture.default_volume().map_err(|e| e.at(path))?),
        }
    }

    /// The reconstruction settings RECON.toml `src` gives for this capture, its volume
    /// the capture's own ([`Capture::default_volume`]) where the file gives none. Where
    /// neither does, the capture's reason (naming its file: positions not in metres,
    /// say), not only that the file lacks a `volume`.
    pub fn recon_from<E: From<ConfigError> + From<CaptureError>>(
        &self,
        src: &TomlSource,
    ) -> Result<ReconSettings, E> {
        let default = self.default_volume();
        match load_recon(src, default.as_ref().ok().copied()) {
            Ok(s) => Ok(s),
            // The file is sound but for the volume it leaves to the capture.
            Err(e) => match default {
                Err(why) if check_recon(src).is_ok() => Err(why.into()),
                _ => Err(e.into()),
            },
        }
    }

    /// The reconstruction settings to use without a RECON.toml: the run's plan's, or
    /// the defaults derived for a y-tal capture's volume.
    pub fn default_recon(&self) -> Result<ReconSettings, CaptureError> {
        match self {
            Capture::Run(run) => Ok(run.plan.recon.clone()),
            Capture::Ytal { path, capture } => {
                Ok(default_recon(capture.default_volume().map_err(|e| e.at(path))?))
            }
        }
    }

    /// The transients for `volume`, whichever the source, with a point-source laser's
    /// falloff divided out where `falloff` asks for it: `auto` does for a rendered
    /// y-tal capture whose laser visits more than one point
    /// ([`YtalCapture::rendered_by`]), and never for a run (its laser is collimated).
    pub fn transients(&self, volume: &VolumeGrid, falloff: LaserFalloff) -> Result<Transients, CaptureError> {
        let (mut t, laser, auto_why) = match self {
            Capture::Run(run) => (
                run.transients(volume)?,
                Some(run.instrument.laser_arm.pose.origin),
                None,
            ),
            Capture::Ytal { path, capture } => {
                let set = capture.transients(volume).map_err(|e| e.at(path))?;
                let (overflowed, flagged) = capture.overflowed();
                if set.is_empty() {
                    return Err(if overflowed > 0 && overflowed == flagged {
                        CaptureError::AllOverflowed(path.clone())
                    } else {
                        CaptureError::NothingInWindow {
                            path: path.clone(),
                            overflowed,
                        }
                    });
                }
                if set.left_out_empty() > 0 {
                    tracing::info!(
                        file = %path.display(),
                        left_out = set.left_out_empty(),
                        kept = set.len(),
                        "transients that hold no count on the paths through the volume were left out"
                    );
                }
                // The virtual relay spans the relay points: the SPAD's, and the laser's
                // too where the SPAD stays on fewer than three (a phasor-field capture's
                // fixed SPAD and scanned laser: by reciprocity, the scanned side).
                let mut detection_points = capture.sensor_grid.points.clone();
                if detection_points.len() < 3 {
                    detection_points.extend(&capture.laser_grid.points);
                }
                let t = Transients {
                    set,
                    detection_points,
                    viewpoint: capture.viewpoint(),
                    overflowed,
                    falloff: None,
                };
                let why = match capture.rendered_by() {
                    Some(renderer) if capture.laser_grid.points.len() > 1 => Some(format!(
                        "auto: rendered by {renderer}, whose laser is a point source, and scanned over {} points",
                        capture.laser_grid.points.len()
                    )),
                    _ => None,
                };
                (t, capture.laser_xyz, why)
            }
        };
        let why = match falloff {
            LaserFalloff::None => return Ok(t),
            LaserFalloff::Auto => match auto_why {
                Some(why) => why,
                None => return Ok(t),
            },
            LaserFalloff::CosInverseSquare => "laser-falloff = \"cos-inverse-square\"".to_string(),
        };
        let path = self.path().to_path_buf();
        let Some(laser) = laser else {
            if falloff == LaserFalloff::Auto {
                // As for a geometry that does not support it: the counts as they are.
                tracing::warn!(
                    capture = %path.display(),
                    "laser falloff not compensated: the capture gives no laser origin (`laser_xyz` is empty); \
                     set laser-falloff = \"none\" to say so"
                );
                return Ok(t);
            }
            return Err(CaptureError::LaserFalloff {
                path,
                reason: "the capture gives no laser origin (`laser_xyz` is empty)".into(),
            });
        };
        match t.set.compensate_laser_falloff(laser) {
            Ok(range) => t.falloff = Some(FalloffApplied { laser, range, why }),
            Err(e) if falloff == LaserFalloff::Auto => {
                // Counts as they are, rather than a correction the geometry does not support.
                tracing::warn!(capture = %path.display(), "laser falloff not compensated: {e}");
            }
            Err(e) => {
                return Err(CaptureError::LaserFalloff {
                    path,
                    reason: e.to_string(),
                });
            }
        }
        Ok(t)
    }

    /// One line on what the capture holds.
    pub fn describe(&self) -> String {
        match self {
            Capture::Run(run) => format!(
                "{}: run {} (plan `{}`), {} of {} pairs measured",
                run.dir.display(),
                run.info.id,
                run.plan.name,
                run.records.len(),
                run.pairs.len()
            ),
            Capture::Ytal { path, capture } => format!(
                "{}: {} transients ({}), {} bins of {:.4} m{}",
                path.display(),
                capture.len(),
                capture.h_format.name(),
                capture.bins(),
                capture.delta_t,
                if capture.t_accounts_first_and_last_bounces {
                    ", first and last legs removed"
                } else {
                    ""
                }
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    /// Names written into an export's `scene_info` come back as they were from a YAML
    /// reader, whatever they hold (the escapes are YAML's double-quoted ones).
    #[test]
    fn scene_info_strings_are_yaml_double_quoted_scalars() {
        assert_eq!(super::yaml_string("demo"), "\"demo\"");
        assert_eq!(
            super::yaml_string("a'b\"c\\d\u{7}\u{e9}\u{1d11e}"),
            "\"a'b\\\"c\\\\d\\u0007\\u00e9\\U0001d11e\""
        );
    }
}
