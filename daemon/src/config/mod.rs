//! Configuration files: loading, two-stage validation and error reporting.
//!
//! Every file goes through the same two stages: a raw serde structure that mirrors the
//! TOML exactly (`deny_unknown_fields`, kebab-case keys), then a validated type that
//! cannot hold an invalid value. Both stages report problems through [`ConfigError`],
//! which names the file, the line and the dotted key, and says what to do.
mod args;
mod daqmx;
mod instrument;
mod scene;
mod source;

pub use args::{InstrumentArg, instrument_source, load_instrument};
pub(crate) use instrument::window_past_period;
pub use instrument::{
    ApiSettings, Backend, BudgetLimits, GalvoArm, GalvoLink, InstrumentConfig, LaserSettings,
    PicoQuantCounter, SYNC_TOLERANCE, SerialLink, SimDevices, SimSettings, SpadSettings, TdcDriver,
    TdcSettings, redact_secrets, whole_ps_offset,
};
pub use scene::{DEFAULT_SCENE, load_scene, scene_from_source, sim_scene};
pub use source::{ConfigError, MAX_TOML_BYTES, TomlSource};

pub(crate) mod exact;

/// The instrument config used when none is given: the simulated instrument.
pub const DEFAULT_INSTRUMENT: &str = "configs/instrument/sim.toml";
