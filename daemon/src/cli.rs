//! The `periscope` command line: argument definitions and dispatch.
//!
//! This is the binary's edge, so commands return `anyhow::Result` and attach context;
//! the library modules below it return typed errors. Exit codes: 0 success, 1 failure,
//! 2 invalid usage or configuration, 69 a command whose machinery is not built yet.
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Parser, Subcommand};

use crate::config::{ConfigError, DEFAULT_INSTRUMENT, InstrumentConfig, TomlSource};
use crate::logging::LogFormat;

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
    /// Reconstruct offline from a stored run or a y-tal HDF5 capture (.hdf5/.h5).
    /// Writes volume.npy, volume.json, depth.png, depth.npy, albedo.png and
    /// gaussians.ply to --out.
    Recon {
        /// A run directory or a y-tal capture file.
        capture: PathBuf,
        /// Reconstruction settings (TOML); defaults are derived from the capture.
        #[arg(long, value_name = "RECON.toml")]
        config: Option<PathBuf>,
        /// Directory for the outputs.
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
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
    /// List serial ports and USB devices, and say which ones the instrument config
    /// selects.
    Devices {
        /// The instrument to use.
        #[command(flatten)]
        instrument: InstrumentArg,
    },
}

/// The `--instrument` option shared by the commands that talk to an instrument.
#[derive(Debug, clap::Args)]
pub struct InstrumentArg {
    /// Instrument config (TOML). Default: configs/instrument/sim.toml, the simulated
    /// instrument (a built-in copy is used when that file is not present).
    #[arg(long, value_name = "FILE")]
    pub instrument: Option<PathBuf>,
}

impl InstrumentArg {
    /// Loads and validates the chosen instrument config.
    pub fn load(&self) -> Result<InstrumentConfig, ConfigError> {
        load_instrument(self.instrument.as_deref())
    }
}

/// Loads the instrument config at `path`, or the default simulated instrument.
pub fn load_instrument(path: Option<&Path>) -> Result<InstrumentConfig, ConfigError> {
    match path {
        Some(path) => InstrumentConfig::load(path),
        None if Path::new(DEFAULT_INSTRUMENT).is_file() => {
            InstrumentConfig::load(Path::new(DEFAULT_INSTRUMENT))
        }
        None => InstrumentConfig::from_source(&TomlSource::from_text(
            format!("{DEFAULT_INSTRUMENT} (built in)"),
            include_str!("../../configs/instrument/sim.toml"),
        )),
    }
}

/// A command whose machinery has not been built yet. Reported, never faked.
#[derive(Debug, thiserror::Error)]
#[error("`periscope {command}` is not available yet in this build: {what}")]
pub struct NotAvailable {
    /// The subcommand.
    pub command: &'static str,
    /// What is missing.
    pub what: &'static str,
}

/// Runs a parsed command line.
pub fn execute(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Run {
            plan: _,
            instrument,
            out: _,
        } => {
            let instrument = instrument.load()?;
            tracing::info!("{}", instrument.summary());
            Err(NotAvailable {
                command: "run",
                what: "the capture pipeline has not landed (issue: daemon capture pipeline)",
            }
            .into())
        }
        Command::Check { plan: _, instrument } => {
            let instrument = instrument.load()?;
            tracing::info!("{}", instrument.summary());
            Err(NotAvailable {
                command: "check",
                what: "capture plans have not landed (issue: daemon capture pipeline)",
            }
            .into())
        }
        Command::Resume { run_dir } => {
            anyhow::ensure!(
                run_dir.is_dir(),
                "{} is not a run directory: give the path of a directory under runs/",
                run_dir.display()
            );
            Err(NotAvailable {
                command: "resume",
                what: "run storage has not landed (issue: daemon capture pipeline)",
            }
            .into())
        }
        Command::Recon { capture, .. } => {
            anyhow::ensure!(
                capture.exists(),
                "capture {} does not exist: give a run directory or a y-tal .hdf5/.h5 file",
                capture.display()
            );
            Err(NotAvailable {
                command: "recon",
                what: "offline reconstruction has not landed (issues: recon engine, solvers)",
            }
            .into())
        }
        Command::Serve { instrument, .. } => {
            instrument.load()?;
            Err(NotAvailable {
                command: "serve",
                what: "the HTTP API has not landed (issue: daemon HTTP API)",
            }
            .into())
        }
        Command::Devices { instrument } => devices(&instrument.load()?),
    }
}

/// The exit code for an error returned by [`execute`].
pub fn exit_code(err: &anyhow::Error) -> ExitCode {
    if err.downcast_ref::<NotAvailable>().is_some() {
        ExitCode::from(69)
    } else if err.downcast_ref::<ConfigError>().is_some() {
        ExitCode::from(2)
    } else {
        ExitCode::FAILURE
    }
}

/// `periscope devices`: what this host has plugged in, then the configured
/// instrument's devices opened, identified and queried.
fn devices(config: &InstrumentConfig) -> anyhow::Result<()> {
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
    println!("Instrument: {}", config.summary());
    let mut devices = crate::devices::Devices::open(config)?;
    let r = devices.report()?;
    let deg = |a: periscope_drivers::OpticalAngles| format!("({:.3}°, {:.3}°)", a.x.to_degrees(), a.y.to_degrees());
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
        if r.laser.interlock_closed { "closed" } else { "OPEN" },
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
        "  histogrammer {} {} serial {}  {:?}, sync {:.0} Hz, detector {:.0} Hz, {} histograms since power-up",
        r.tdc.model,
        r.tdc.firmware,
        r.tdc.serial,
        r.tdc_status.state,
        r.tdc_status.rates.sync,
        r.tdc_status.rates.detector,
        r.tdc_status.acquisitions
    );
    Ok(())
}
