//! The `periscope` command line: argument definitions and dispatch.
//!
//! Commands return a [`CliError`] that keeps the library's typed error as its source;
//! [`CliError::exit_code`] picks the exit status by its kind: 0 success, 1 failure,
//! 2 invalid usage or configuration. [`report`] writes the error with its causes.
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::{Arc, Mutex};

use clap::{Parser, Subcommand};

use crate::api::ServeError;
use crate::capture::CaptureError;
use crate::config::{ConfigError, InstrumentConfig, TomlSource};
use crate::devices::OpenError;
use crate::logging::LogFormat;
use crate::offline::OfflineError;
use crate::pipeline::{self, Control, PipelineError, Run};
use crate::plan::Plan;
use crate::run_dir::{RunDir, RunDirError};
use crate::service::ServiceError;
use crate::ytal::ExportError;
use crate::{check, offline};
use periscope_drivers::EmergencyPark;
use periscope_drivers::galvo::EmergencyOff;

/// Periscope: non-line-of-sight imaging, from galvo scan to reconstructed volume.
#[derive(Debug, Parser)]
#[command(name = "periscope", version, about, long_about = None, propagate_version = true)]
pub struct Cli {
    /// Log line format on stderr (the level comes from RUST_LOG, default `info`).
    #[arg(long, value_enum, default_value_t = LogFormat::Text, global = true)]
    pub log_format: LogFormat,
    /// Also write every log event as JSON lines to this file.
    #[arg(long, value_name = "FILE", global = true)]
    pub log_file: Option<PathBuf>,
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// The subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run a capture plan end to end: LOS relay scan, pair planning, NLOS capture and
    /// 3D-GTR reconstruction, on the simulated instrument unless --instrument says
    /// otherwise. Results go to --out (default `runs/<id>/`).
    Run {
        /// The capture plan (TOML), e.g. configs/plans/demo.toml.
        plan: PathBuf,
        /// The instrument to use.
        #[command(flatten)]
        instrument: InstrumentArg,
        /// Directory for the run's data and results.
        #[arg(long, value_name = "DIR")]
        out: Option<PathBuf>,
    },
    /// Validate a capture plan against an instrument, print a summary and the
    /// estimated duration, and list targets outside the galvo limits. Moves nothing.
    Check {
        /// The capture plan (TOML).
        plan: PathBuf,
        /// The instrument to use.
        #[command(flatten)]
        instrument: InstrumentArg,
    },
    /// Continue an interrupted run from its last stored pair.
    Resume {
        /// The run directory, e.g. runs/20261121-110000-demo.
        run_dir: PathBuf,
    },
    /// Reconstruct offline from a stored run or a capture file: y-tal or ZNLOS HDF5
    /// (.hdf5/.h5), Stanford LCT or f-k, or phasor-field MATLAB (.mat).
    /// Writes volume.npy, volume.json, depth.png, depth.npy, albedo.png and
    /// gaussians.ply to --out.
    Recon {
        /// A run directory or a capture file (docs/formats.md).
        capture: PathBuf,
        /// Reconstruction settings (TOML); defaults are derived from the capture.
        #[arg(long, value_name = "RECON.toml")]
        config: Option<PathBuf>,
        /// Directory for the outputs.
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
        /// Emulate an adaptive capture on this (dense) capture: reveal its pairs batch by
        /// batch in this order (adaptive: chosen by the running fit; uniform: spread
        /// evenly; random) up to the `[adaptive]` budget, then reconstruct from those
        /// revealed; each batch's choice goes to adaptive.json (docs/adaptive.md).
        #[arg(long, value_name = "ORDER", num_args = 0..=1, default_missing_value = "adaptive")]
        adaptive_replay: Option<crate::adaptive::Order>,
    },
    /// Export a run's measured histograms as a y-tal HDF5 capture (readable by y-tal's
    /// `tal.io.read_capture` and h5py). Works on interrupted runs too.
    Export {
        /// The run directory.
        run_dir: PathBuf,
        /// The capture file to write (default: RUN_DIR/capture.hdf5).
        #[arg(long, value_name = "FILE")]
        out: Option<PathBuf>,
    },
    /// Serve the HTTP API (under /api/v1) for lab operators.
    Serve {
        /// Address to listen on; keep it on loopback unless the network is trusted.
        #[arg(long, value_name = "ADDR", default_value = "127.0.0.1:7878")]
        bind: SocketAddr,
        /// The instrument to use.
        #[command(flatten)]
        instrument: InstrumentArg,
    },
    /// Calibrate the galvo arms: scan a flat target (first-bounce ranges with the
    /// diffuser in, the laser spot with it out), fit each arm's origin, boresight and
    /// up, print fitted against configured values with the residuals, and write the
    /// calibrated instrument config to --out.
    Calibrate {
        /// The instrument to calibrate.
        #[command(flatten)]
        instrument: InstrumentArg,
        /// Write the instrument config with the fitted poses here (the rest of the file
        /// is kept as it is); without it, only the table is printed.
        #[arg(long, value_name = "FILE")]
        out: Option<PathBuf>,
        /// The SPAD range scan's grid: N × N angles over 75 % of the SPAD limits.
        #[arg(long, value_name = "N", default_value_t = 9)]
        grid: usize,
        /// The flat target's distance from the SPAD origin along the configured SPAD
        /// boresight, in metres, facing it. Without it the target's distance and tilt
        /// are fitted and the SPAD pose stays as configured (docs/calibration.md).
        #[arg(long, value_name = "M")]
        target_distance: Option<f64>,
    },
    /// Query the run catalogue (filters: state, dates, plan, tag, text), or tag and
    /// annotate a run.
    Runs(crate::admin::RunsArgs),
    /// Rebuild or sync the run catalogue from the run directories.
    #[command(subcommand)]
    Catalogue(crate::admin::CatalogueCommand),
    /// Make, list and revoke API keys (roles: estop, observer, operator, admin).
    #[command(subcommand)]
    Keys(crate::admin::KeysCommand),
    /// Show the audit trail: who submitted, paused, aborted, e-stopped, made keys.
    Audit(crate::admin::AuditArgs),
    /// List serial ports and USB devices, then open the instrument config's devices
    /// through their drivers and show what each reports (the laser is not switched
    /// on).
    Devices {
        /// The instrument to use.
        #[command(flatten)]
        instrument: InstrumentArg,
    },
}

pub use crate::config::{InstrumentArg, instrument_source, load_instrument};

/// Runs a parsed command line.
pub fn execute(cli: Cli) -> Result<(), CliError> {
    match cli.command {
        Command::Run {
            plan,
            instrument,
            out,
        } => {
            let instrument_src = instrument_source(instrument.instrument.as_deref())?;
            let plan_src = TomlSource::load(&plan)?;
            // The way to the devices, as `check` makes it (nothing opened), before the
            // run directory is: a simulator's broken scene file is refused naming its
            // key, and leaves no failed run behind.
            crate::devices::backend(&crate::config::InstrumentConfig::from_source(&instrument_src)?)?;
            let (dir, plan, config) = pipeline::prepare(&plan_src, &instrument_src, out.as_deref(), "cli")?;
            crate::logging::notice(&format!(
                "run `{}` on {}\n  run directory: {}",
                plan.name,
                config.summary(),
                dir.display()
            ));
            execute_run(&dir)
        }
        Command::Check { plan, instrument } => {
            let config = instrument.load()?;
            // The way to the devices as a run makes it (nothing opened): the
            // simulator's scene file is read and checked here, not when the run starts.
            crate::devices::backend(&config)?;
            let plan = Plan::load(&plan, &config)?;
            print!("{}", check::report(&plan, &config));
            crate::budget::Budget::of_plan(&plan, &config)
                .check(&config.budget)
                .map_err(|over| CliError::Budget {
                    plan: plan.name.clone(),
                    why: over.message,
                })
        }
        Command::Resume { run_dir } => {
            if !RunDir::holds_run(&run_dir) {
                return Err(CliError::NotRun(run_dir));
            }
            let info = crate::run_dir::RunInfo::load(&run_dir).map_err(|source| CliError::Io {
                path: run_dir.join(crate::run_dir::file::RUN),
                source,
            })?;
            if info.state == crate::run_dir::RunState::Completed {
                return Err(CliError::Completed {
                    id: info.id,
                    dir: run_dir,
                });
            }
            crate::logging::notice(&format!(
                "resuming run {} ({} of {} pairs stored, last stage {})",
                info.id, info.pairs_done, info.pairs_total, info.stage
            ));
            execute_run(&run_dir)
        }
        Command::Recon {
            capture,
            config,
            out,
            adaptive_replay,
        } => {
            // A run directory as the output would have its own results replaced and
            // the reconstruction's events added to its log.
            if RunDir::holds_run(&out) {
                return Err(CliError::OutIsRun(out));
            }
            if out.exists() && !out.is_dir() {
                return Err(CliError::OutNotFolder(out));
            }
            if !out.exists()
                && let Ok(target) = std::fs::read_link(&out)
            {
                return Err(CliError::OutBrokenLink { out, target });
            }
            match adaptive_replay {
                Some(order) => offline::replay(&capture, config.as_deref(), &out, order)?,
                None => offline::recon(&capture, config.as_deref(), &out)?,
            }
            Ok(())
        }
        Command::Export { run_dir, out } => {
            if !RunDir::holds_run(&run_dir) {
                return Err(CliError::NotRun(run_dir));
            }
            let out = out.unwrap_or_else(|| run_dir.join(crate::ytal::CAPTURE_FILE));
            refuse_run_file(&run_dir, &out)?;
            let capture = crate::capture::RunCapture::load(&run_dir)?.to_ytal()?;
            capture.write(&out).map_err(ExportError::from)?;
            println!(
                "wrote {} ({} transients of {} bins, T_Si with first and last legs)",
                out.display(),
                capture.len(),
                capture.bins()
            );
            Ok(())
        }
        Command::Serve { bind, instrument } => {
            let src = instrument_source(instrument.instrument.as_deref())?;
            let config = InstrumentConfig::from_source(&src)?;
            let token = match std::env::var("PERISCOPE_TOKEN") {
                Ok(t) if !t.trim().is_empty() => Some(t.trim().to_owned()),
                _ => config.api.token.clone(),
            };
            let token = token.unwrap_or_else(|| {
                let t = random_token();
                // Plain stderr even with JSON logs: the token is for the operator's eyes,
                // never for a log file.
                eprintln!(
                    "no PERISCOPE_TOKEN or [api] token: this session's token is {t}\n  \
                     (mutating requests need `Authorization: Bearer {t}`)"
                );
                t
            });
            let service = crate::service::Service::open(src, Some(token))?;
            let api = &service.instrument().api;
            // The blocking pool answers the API's slower requests (run directories,
            // exports, plan checks): its size follows the API's own limits, so a flood
            // never puts hundreds of threads beside the instrument's worker.
            let blocking = api.max_concurrent + api.max_checks + api.max_downloads + 4;
            // Compute threads are made now, from this thread, so they keep the
            // instrument's priority rather than inheriting the API's; so is the
            // thread that starts the e-stop's.
            let _ = rayon::ThreadPoolBuilder::new().build_global();
            if let Err(e) = crate::api::start_own_threads() {
                tracing::warn!(error = %e, "the e-stop's threads will be started at the API's priority");
            }
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .enable_all()
                .max_blocking_threads(blocking)
                .on_thread_start(|| {
                    // Ten below the process's own (the instrument's), whatever it started
                    // at: an absolute 10 raised a daemon started at nice 15 where it may.
                    let nice = (crate::priority::current_nice() + crate::priority::API_NICE).min(19);
                    if let Err(e) = crate::priority::lower_current_thread(nice) {
                        tracing::debug!(error = %e, "the API thread keeps the instrument's priority");
                    }
                })
                .thread_name("periscope-api")
                .build()
                .map_err(CliError::Runtime)?;
            Ok(runtime.block_on(crate::api::serve(bind, service))?)
        }
        Command::Devices { instrument } => devices(&instrument.load()?),
        Command::Runs(args) => Ok(crate::admin::runs(args)?),
        Command::Catalogue(cmd) => Ok(crate::admin::catalogue(cmd)?),
        Command::Keys(cmd) => Ok(crate::admin::keys(cmd)?),
        Command::Audit(args) => Ok(crate::admin::audit(args)?),
        Command::Calibrate {
            instrument,
            out,
            grid,
            target_distance,
        } => calibrate(&instrument, out.as_deref(), grid, target_distance),
    }
}

/// `periscope calibrate`: scans, fit, table, and the calibrated config.
fn calibrate(
    instrument: &InstrumentArg,
    out: Option<&Path>,
    grid: usize,
    target_distance: Option<f64>,
) -> Result<(), CliError> {
    use crate::calibrate::{self, Calibrator, Settings};
    let settings = Settings {
        grid,
        target_distance,
        ..Settings::default()
    };
    settings.validate()?;
    let src = instrument_source(instrument.instrument.as_deref())?;
    let config = InstrumentConfig::from_source(&src)?;
    if let Some(path) = out {
        // Before the laser is switched on: a calibration is minutes of scanning.
        check_calibrate_out(path, src.path())?;
    }
    crate::logging::notice(&format!("calibrating {}", config.summary()));
    let control = Control::new();
    let signals = RunSignals::new(&control);
    crate::signals::install(signals.clone(), crate::signals::SIGNAL_GRACE);
    let calibrator = Calibrator::open(&config, None, control)?;
    signals.reach(calibrator.emergency_off(), calibrator.emergency_park());
    let measured = calibrator.measure(&settings);
    if let Some(n) = crate::signals::received() {
        crate::logging::notice(&format!(
            "stopped by signal {n}: laser off, arms parked; nothing written"
        ));
        std::process::exit(i32::from(crate::signals::exit_code(n)));
    }
    let calibration = calibrate::fit(&config, &measured?, &settings)?;
    print!("{}", calibration.table());
    // A signal during the fit: nothing written, as a signal during the scans.
    let stopped = || {
        if let Some(n) = crate::signals::received() {
            crate::logging::notice(&format!(
                "stopped by signal {n}: laser off, arms parked; nothing written"
            ));
            std::process::exit(i32::from(crate::signals::exit_code(n)));
        }
    };
    stopped();
    match out {
        Some(path) => {
            let text = calibrate::calibrated_toml(src.text(), &calibration.fitted, src.path(), path)?;
            // What is written must load as the instrument it describes, from where it
            // will be: written beside it and loaded from there before anything at
            // `path` is replaced.
            let io = |source| CliError::Io {
                path: path.to_owned(),
                source,
            };
            let trial = path.with_file_name(format!(
                ".{}.{}.check",
                path.file_name()
                    .map_or("calibrated".into(), |n| n.to_string_lossy()),
                std::process::id()
            ));
            crate::store::write_atomic(&trial, text.as_bytes()).map_err(io)?;
            if let Err(e) = InstrumentConfig::load(&trial) {
                let _ = std::fs::remove_file(&trial);
                return Err(e.into());
            }
            let _ = std::fs::remove_file(&trial);
            stopped();
            crate::store::write_atomic(path, text.as_bytes()).map_err(io)?;
            println!("wrote {}", path.display());
        }
        None => println!("(give --out FILE to write the calibrated instrument config)"),
    }
    Ok(())
}

/// Refuses a calibration's `--out` that cannot take the calibrated config, before any
/// scan: the instrument config it was read from (it would be replaced, the configured
/// poses gone), a folder that does not exist, or something that is not a regular file.
fn check_calibrate_out(out: &Path, instrument: &Path) -> Result<(), CliError> {
    use std::os::unix::fs::MetadataExt as _;
    let refuse = |why: String| CliError::CalibrateOut {
        path: out.to_owned(),
        why,
    };
    if let (Ok(a), Ok(b)) = (std::fs::metadata(out), std::fs::metadata(instrument))
        && (a.dev(), a.ino()) == (b.dev(), b.ino())
    {
        return Err(refuse(format!(
            "is the instrument config the calibration reads ({}); it would be replaced and its poses lost: \
             write the calibrated config to another file",
            instrument.display()
        )));
    }
    if let Ok(m) = std::fs::symlink_metadata(out)
        && !m.file_type().is_file()
    {
        return Err(refuse(
            "exists and is not a regular file (a folder, device or link): give a file path".into(),
        ));
    }
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    if !parent.is_dir() {
        return Err(refuse(format!(
            "is in {}, which is not a folder: make it first, or write elsewhere",
            parent.display()
        )));
    }
    Ok(())
}

/// Refuses an export's `out` that is one of the run's own files (its histograms,
/// `run.json`, the plan): the export replaces `out` whole, and the run's data would be
/// gone. `capture.hdf5` in the run directory (the default) is the export's own file.
/// Nor anything inside another run's directory or its folders (its histogram
/// log is its only copy of the measurements, `import/` an imported run's only copy of
/// its capture), whether the file is there yet or not: a run that has not finished
/// would take a `capture.hdf5` written there as its own.
fn refuse_run_file(run_dir: &Path, out: &Path) -> Result<(), CliError> {
    let Ok(dir) = run_dir.canonicalize() else {
        return Ok(());
    };
    // Where `out` is, links resolved: itself where it exists, else its folder's.
    let target = match out.canonicalize() {
        Ok(t) => t,
        Err(_) => {
            let parent = match out.parent() {
                Some(p) if !p.as_os_str().is_empty() => p,
                _ => Path::new("."),
            };
            match (parent.canonicalize(), out.file_name()) {
                (Ok(p), Some(name)) => p.join(name),
                // No such folder: the write fails, naming it.
                _ => return Ok(()),
            }
        }
    };
    let export = target.parent() == Some(dir.as_path())
        && target.file_name() == Some(std::ffi::OsStr::new(crate::ytal::CAPTURE_FILE));
    // The folder `out` is in, and the one above (a run's own folders, `import/`): not
    // every ancestor, or a stray run.json in a home or a mount root would refuse every
    // export beneath it.
    if !export && target.ancestors().skip(1).take(2).any(RunDir::holds_run) {
        return Err(CliError::RunFile(out.to_path_buf()));
    }
    // Nor the daemon's own files in a runs directory (its keys, queue, audit trail and
    // catalogue), told by a folder that holds another of them.
    let daemon_files = [
        crate::access::KEYS_FILE,
        crate::service::QUEUE_FILE,
        crate::catalogue::audit::AUDIT_FILE,
        crate::catalogue::CATALOGUE_FILE,
    ];
    if let (Some(folder), Some(name)) = (target.parent(), target.file_name())
        && daemon_files.iter().any(|f| name == *f)
        && daemon_files.iter().any(|f| *f != name && folder.join(f).exists())
    {
        return Err(CliError::RunsDirFile(out.to_path_buf()));
    }
    Ok(())
}

/// `periscope devices`: what this host has plugged in, then the configured
/// instrument's devices opened, identified and queried.
fn devices(config: &InstrumentConfig) -> Result<(), CliError> {
    use periscope_drivers::{ports, tdc};
    println!("Serial ports on this host:");
    match ports::list_serial_ports() {
        Ok(list) if list.is_empty() => println!("  (none)"),
        Ok(list) => {
            for p in list {
                let usb = p.usb.map(|u| format!("  USB {u}")).unwrap_or_default();
                let product = p.product.map(|u| format!("  {u}")).unwrap_or_default();
                println!("  {}{usb}{product}", p.path);
            }
        }
        Err(e) => println!("  (cannot list: {e})"),
    }
    println!("USB devices on this host (select one in the config as tdc.usb = \"VID:PID[:SERIAL]\"):");
    match tdc::list_usb_devices() {
        Ok(list) if list.is_empty() => println!("  (none)"),
        Ok(list) => {
            for d in list {
                let serial = d.serial.map(|s| format!(":{s}")).unwrap_or_default();
                let product = d.product.unwrap_or_default();
                println!(
                    "  {:04x}:{:04x}{serial}  bus {:03} address {:03}  {product}",
                    d.vendor_id, d.product_id, d.bus, d.address
                );
            }
        }
        Err(e) => println!("  (cannot list: {e})"),
    }
    if let crate::config::TdcDriver::PicoQuant(counter) = &config.tdc.driver {
        println!(
            "PicoQuant {}s (select one in the config as tdc.serial = \"SERIAL\"):",
            counter.family
        );
        for line in crate::devices::picoquant::survey(counter) {
            println!("  {line}");
        }
    }
    let daq = crate::devices::daqmx::survey(config);
    if !daq.is_empty() {
        println!("NI-DAQmx (galvo.<arm>.channels and the laser's lines name its devices):");
        for line in daq {
            println!("  {line}");
        }
    }
    println!("Instrument: {}", config.summary());
    let mut devices = crate::devices::Devices::open_config(config)?;
    let r = devices.report()?;
    let deg =
        |a: periscope_drivers::OpticalAngles| format!("({:.3}°, {:.3}°)", a.x.to_degrees(), a.y.to_degrees());
    println!(
        "  laser arm  {} {} serial {} (protocol {})  at {}",
        r.laser_arm.model,
        r.laser_arm.firmware,
        r.laser_arm.serial,
        r.laser_arm.protocol,
        deg(r.laser_position)
    );
    println!(
        "    laser {}  interlock {}  diffuser {}",
        if r.laser.emission { "ON" } else { "off" },
        if r.laser.interlock_closed {
            "closed"
        } else {
            "OPEN"
        },
        if r.laser.diffuser_in { "in" } else { "out" }
    );
    println!(
        "  spad arm   {} {} serial {} (protocol {})  at {}",
        r.spad_arm.model,
        r.spad_arm.firmware,
        r.spad_arm.serial,
        r.spad_arm.protocol,
        deg(r.spad_position)
    );
    println!(
        "  histogrammer {} {} serial {}  {:?}, sync {:.0} Hz (the config expects {:.0} Hz with the laser on: laser.rep-rate-mhz / tdc.sync-divider), detector {:.0} Hz, {} histograms since power-up",
        r.tdc.model,
        r.tdc.firmware,
        r.tdc.serial,
        r.tdc_status.state,
        r.tdc_status.rates.sync,
        config.expected_sync_rate(),
        r.tdc_status.rates.detector,
        r.tdc_status.acquisitions
    );
    Ok(())
}

/// What a stop signal does to `run`, `resume` and `calibrate`.
struct RunSignals {
    control: Control,
    laser: Mutex<Option<EmergencyOff>>,
    /// The arms' park handles (laser arm, SPAD arm), once the devices are open.
    park: Mutex<Option<[EmergencyPark; 2]>>,
}

impl RunSignals {
    fn new(control: &Control) -> Arc<RunSignals> {
        Arc::new(RunSignals {
            control: control.clone(),
            laser: Mutex::new(None),
            park: Mutex::new(None),
        })
    }

    /// The open devices' direct paths: the laser's off and the arms' park.
    fn reach(&self, off: EmergencyOff, park: [EmergencyPark; 2]) {
        *self.laser.lock().unwrap_or_else(|p| p.into_inner()) = Some(off);
        *self.park.lock().unwrap_or_else(|p| p.into_inner()) = Some(park);
    }
}

impl crate::signals::OnSignal for RunSignals {
    fn laser_off(&self) {
        // A driver already closed switched its laser off on its way out (the run or
        // calibration made the instrument safe before the signal came).
        if let Some(off) = self.laser.lock().unwrap_or_else(|p| p.into_inner()).as_ref()
            && off.is_open()
            && let Err(e) = off.laser_off()
        {
            eprintln!("direct laser off failed: {e}");
        }
    }
    fn park_now(&self) {
        // Cloned out first: the lock is not held through the park's wait.
        let park = self.park.lock().unwrap_or_else(|p| p.into_inner()).clone();
        crate::signals::park_within(park);
    }
    fn stop(&self, signal: &'static str) {
        self.control.pause_by(signal);
    }
}

/// Runs (or resumes) the run in `dir` with a progress display and prints the summary.
fn execute_run(dir: &Path) -> Result<(), CliError> {
    let control = Control::new();
    let signals = RunSignals::new(&control);
    crate::signals::install(signals.clone(), crate::signals::SIGNAL_GRACE);
    let run = Run::open(dir, control, None, None)?;
    signals.reach(run.emergency_off(), run.emergency_park());
    crate::progress::attach(run.events());
    let result = run.execute();
    if let Some(n) = crate::signals::received() {
        let state = match &result {
            Ok(_) => "completed".to_owned(),
            Err(e) => e.to_string(),
        };
        crate::logging::notice(&format!(
            "stopped by signal {n}: {state}; laser off, arms parked. `periscope resume {}` continues the run",
            dir.display()
        ));
        std::process::exit(i32::from(crate::signals::exit_code(n)));
    }
    let summary = result?;
    println!("run complete: {}", summary.dir.display());
    println!("  pairs measured: {}", summary.pairs);
    for (stage, secs) in &summary.timings {
        println!("  {stage:<15} {secs:>8.1} s");
    }
    let o = &summary.outputs;
    for (step, secs) in &o.timings {
        println!("    {step:<20} {secs:>6.1} s");
    }
    if let Some(k) = o.primitives {
        println!(
            "  Gaussians: {k}, final loss {:.4e}",
            o.final_loss.unwrap_or(f64::NAN)
        );
    }
    println!(
        "  depth map: {} of {} pixels with a surface",
        o.depth_pixels, o.pixels
    );
    println!("  outputs:");
    for f in &o.files {
        println!("    {}", summary.dir.join(f).display());
    }
    Ok(())
}

/// Why a command failed: the library's own error, kept whole, or one of the few
/// checks the command line makes itself.
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    /// A config, plan or RECON.toml is invalid.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// A run failed.
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    /// An offline reconstruction failed.
    #[error(transparent)]
    Offline(#[from] OfflineError),
    /// A stored run could not be read.
    #[error(transparent)]
    RunDir(#[from] RunDirError),
    /// A stored run could not be read as a capture.
    #[error(transparent)]
    Capture(#[from] CaptureError),
    /// A y-tal capture could not be built or written.
    #[error(transparent)]
    Export(#[from] ExportError),
    /// The devices could not be opened or queried.
    #[error(transparent)]
    Devices(#[from] OpenError),
    /// The API service could not start.
    #[error(transparent)]
    Service(#[from] ServiceError),
    /// The API server failed.
    #[error(transparent)]
    Serve(#[from] ServeError),
    /// A calibration failed.
    #[error(transparent)]
    Calibrate(#[from] crate::calibrate::CalibrateError),
    /// A catalogue, key or audit command failed.
    #[error(transparent)]
    Admin(#[from] crate::admin::AdminError),
    /// A plan over the instrument's budget.
    #[error("plan `{plan}`: {why}")]
    Budget {
        /// The plan's name.
        plan: String,
        /// Which limit, by how much, and the key that sets it.
        why: String,
    },
    /// A directory that holds no run.
    #[error(
        "{} is not a run directory (no run.json): give the path of a directory under runs/",
        .0.display()
    )]
    NotRun(PathBuf),
    /// `resume` of a run that has finished.
    #[error("run {id} is already complete; its outputs are in {}", dir.display())]
    Completed {
        /// The run's id.
        id: String,
        /// Its directory.
        dir: PathBuf,
    },
    /// A file could not be read.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// `export --out` naming a file in a run directory (not the run's own capture.hdf5).
    #[error(
        "{} is in a run directory, and the export would replace or add to that run's files; give \
         --out a new file outside the run directories (or leave it out: RUN_DIR/capture.hdf5)",
        .0.display()
    )]
    RunFile(PathBuf),
    /// `export --out` naming one of the daemon's files in a runs directory.
    #[error(
        "{} is one of the daemon's files in a runs directory (its keys, queue, audit trail or catalogue), \
         and the export would replace it; give --out a new file outside the run directories",
        .0.display()
    )]
    RunsDirFile(PathBuf),
    /// `recon --out` naming a run directory.
    #[error(
        "{} is a run directory: the reconstruction would replace the run's own results and add to its \
         event log; give --out a new folder",
        .0.display()
    )]
    OutIsRun(PathBuf),
    /// `recon --out` naming something that is not a folder.
    #[error(
        "{} exists and is not a folder: --out names the folder the reconstruction's files go in; give a new or \
         existing folder",
        .0.display()
    )]
    OutNotFolder(PathBuf),
    /// `calibrate --out` naming a file that cannot take the calibrated config.
    #[error("--out {}: {why}", path.display())]
    CalibrateOut {
        /// `--out`.
        path: PathBuf,
        /// Why not.
        why: String,
    },
    /// `recon --out` naming a symbolic link to nothing.
    #[error(
        "{} is a symbolic link to {}, which does not exist: --out names the folder the reconstruction's files go \
         in; make the folder it points to, or give another",
        out.display(),
        target.display()
    )]
    OutBrokenLink {
        /// The link.
        out: PathBuf,
        /// Where it points.
        target: PathBuf,
    },
    /// The async runtime for `serve` could not start.
    #[error("cannot start the API's runtime: {0}")]
    Runtime(std::io::Error),
}

impl CliError {
    /// The process's exit status: 2 when the fault is in a config, plan or RECON.toml
    /// (a stored run's plan or instrument that no longer loads counts, whichever reader
    /// found it, and so does a reconstruction the settings cannot do: a solver that
    /// does not suit the data, a volume no pair sees); 1 for everything else.
    pub fn exit_code(&self) -> ExitCode {
        let config = match self {
            CliError::Config(_) => true,
            CliError::Pipeline(PipelineError::Config(_)) => true,
            CliError::Pipeline(PipelineError::Recon(e)) => e.is_settings(),
            CliError::Offline(e) => e.is_config(),
            CliError::RunDir(RunDirError::Config(_)) => true,
            CliError::Capture(e) => e.is_config(),
            CliError::Service(ServiceError::Config(_)) => true,
            CliError::Calibrate(e) => e.is_config(),
            CliError::Admin(
                crate::admin::AdminError::Config(_)
                | crate::admin::AdminError::Usage(_)
                | crate::admin::AdminError::NoRunsDir { .. }
                | crate::admin::AdminError::Keys(crate::access::KeysError::Invalid(_)),
            ) => true,
            CliError::OutIsRun(_)
            | CliError::OutNotFolder(_)
            | CliError::OutBrokenLink { .. }
            | CliError::CalibrateOut { .. } => true,
            // The plan against the instrument's limits, as `run` refuses it.
            CliError::Budget { .. } => true,
            _ => false,
        };
        if config {
            ExitCode::from(2)
        } else {
            ExitCode::FAILURE
        }
    }
}

/// The error and its causes on one line, `error: cause: deeper cause`; a cause whose
/// text the line already holds (an error that prints its source) is not repeated.
pub fn report(err: &dyn std::error::Error) -> String {
    let mut line = err.to_string();
    let mut source = err.source();
    while let Some(cause) = source {
        let text = cause.to_string();
        if !line.contains(&text) {
            line.push_str(": ");
            line.push_str(&text);
        }
        source = cause.source();
    }
    line
}

/// A random 192-bit token, hex-encoded.
fn random_token() -> String {
    use rand::RngCore;
    let mut bytes = [0u8; 24];
    rand::rng().fill_bytes(&mut bytes);
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_report_names_each_cause_once() {
        let io = std::io::Error::new(std::io::ErrorKind::PermissionDenied, "permission denied");
        // The message already holds its source: printed once.
        let err = CliError::Io {
            path: "runs/a/run.json".into(),
            source: io,
        };
        assert_eq!(report(&err), "runs/a/run.json: permission denied");
        // A transparent wrapper adds nothing of its own.
        let err = CliError::Offline(OfflineError::Capture(CaptureError::NotRun("runs/b".into())));
        assert_eq!(report(&err), "runs/b is not a run directory (no run.json)");
    }

    #[test]
    fn refusals_of_the_command_line_are_failures_and_config_errors_are_two() {
        assert_eq!(CliError::NotRun("x".into()).exit_code(), ExitCode::FAILURE);
        let config = TomlSource::from_text("plan.toml", "").invalid("name", "is empty");
        assert_eq!(CliError::Config(config).exit_code(), ExitCode::from(2));
    }
}
