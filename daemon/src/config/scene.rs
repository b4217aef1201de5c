//! Simulated scenes (`configs/scenes/*.toml`) and the simulated detector, both built
//! from config files with the same file/line/key error reporting as every other config.
use std::path::Path;

use periscope_sim::{Detector, RawScene, Scene};

use super::{ConfigError, InstrumentConfig, SimSettings, TomlSource};

/// The scene used when the instrument config names none: a planar wall and a letter.
pub const DEFAULT_SCENE: &str = include_str!("../../../configs/scenes/wall-letter.toml");

/// Loads and validates a scene file; mesh paths resolve against its folder.
pub fn load_scene(path: &Path) -> Result<Scene, ConfigError> {
    scene_from_source(&TomlSource::load(path)?)
}

/// Validates a scene held in memory.
pub fn scene_from_source(src: &TomlSource) -> Result<Scene, ConfigError> {
    let raw: RawScene = src.parse()?;
    let base = src.path().parent().unwrap_or(Path::new("."));
    Scene::from_raw(&raw, base).map_err(|e| src.invalid(&e.key, e.message))
}

/// The scene a simulated instrument images: its `[sim] scene`, or the built-in one.
pub fn sim_scene(sim: &SimSettings) -> Result<Scene, ConfigError> {
    match &sim.scene {
        Some(path) => load_scene(path),
        None => scene_from_source(&TomlSource::from_text(
            "<built-in scene wall-letter.toml>",
            DEFAULT_SCENE,
        )),
    }
}

impl InstrumentConfig {
    /// The simulated detector: this instrument's laser, SPAD and TDC with the optics of
    /// its `[sim]` section.
    pub fn sim_detector(&self, sim: &SimSettings) -> Detector {
        let half = sim.diffuser_half_angle;
        Detector {
            bin_width: self.tdc.bin_width,
            bins: self.tdc.bins as usize,
            offset: self.tdc.offset,
            system_delay: self.tdc.system_delay,
            jitter_fwhm: self.spad.jitter_fwhm,
            efficiency: self.spad.efficiency,
            dark_count_rate: self.spad.dark_count_rate,
            ambient_rate: sim.ambient_rate,
            dead_time: self.spad.dead_time,
            laser_power: self.laser.power,
            wavelength: self.laser.wavelength,
            // The laser as it really pulses, which a run checks the config against.
            repetition_rate: sim.true_repetition_rate,
            sync_divider: self.tdc.sync_divider.max(1),
            aperture_area: std::f64::consts::PI * (0.5 * sim.aperture).powi(2),
            spot_area: std::f64::consts::PI * (0.5 * sim.spot).powi(2),
            diffuser_solid_angle: 2.0 * std::f64::consts::PI * (1.0 - half.cos()),
            transmission: sim.transmission,
            gate_margin: sim.gate_margin,
            pile_up: sim.pile_up,
        }
    }
}
