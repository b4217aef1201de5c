//! The `--instrument` option every instrument command shares, and how it finds the
//! config: the given file, `configs/instrument/sim.toml`, or the built-in copy.
use std::path::{Path, PathBuf};

use super::{ConfigError, DEFAULT_INSTRUMENT, InstrumentConfig, TomlSource};

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
    InstrumentConfig::from_source(&instrument_source(path)?)
}

/// The instrument config's text: the given file, else `configs/instrument/sim.toml`,
/// else the copy built into the binary.
pub fn instrument_source(path: Option<&Path>) -> Result<TomlSource, ConfigError> {
    match path {
        Some(path) => TomlSource::load(path),
        None if Path::new(DEFAULT_INSTRUMENT).is_file() => TomlSource::load(Path::new(DEFAULT_INSTRUMENT)),
        None => Ok(TomlSource::from_text(
            format!("{DEFAULT_INSTRUMENT} (built in)"),
            include_str!("../../../configs/instrument/sim.toml"),
        )),
    }
}
