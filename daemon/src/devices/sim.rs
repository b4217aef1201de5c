//! The simulated backend: a simulated instrument ([`Rig`]) built from the config's
//! `[sim]` table, reached through the lab's own drivers over the simulator's wire
//! (`sim.devices = "wire"`, the default) or through the simulator's devices in
//! process (`sim.devices = "in-process"`). The backend owns the rig: tests reach it
//! with [`SimBackend::rig`] (or [`rig_of`] on a backend they hold only as a
//! [`DeviceBackend`]) to inject faults and to read the simulated laser's own log.
use std::any::Any;

use periscope_drivers::galvo::Connector;
use periscope_drivers::{Erased, GalvoBox, HistogrammerBox};
use periscope_sim::World;
use periscope_sim::devices::{Arm, Rig, RigSettings};
use periscope_sim::transport::samples_needed;

use super::hardware::{Role, laser_arm, serial_galvo, usb_histogrammer};
use super::{DeviceBackend, LaserArm, OpenError};
use crate::config::{ConfigError, InstrumentConfig, SimDevices, SimSettings, TomlSource, sim_scene};

/// Most hidden-surface samples a simulated scene may need (about 1.5 GB of samples).
const MAX_HIDDEN_SAMPLES: f64 = 2e7;

/// The simulated instrument and the way to its devices. It derefs to its [`Rig`], so
/// a test holding the backend injects faults and reads the laser's log through it;
/// clones share the rig.
#[derive(Clone)]
pub struct SimBackend {
    config: InstrumentConfig,
    in_process: bool,
    rig: Rig,
}

impl SimBackend {
    /// A fresh simulated instrument for `config`, whose `[sim]` table is `sim`:
    /// scene physics and devices. Refuses a scene whose third bounce would need more
    /// samples than `MAX_HIDDEN_SAMPLES` (2e7, about 1.5 GB).
    pub fn new(config: &InstrumentConfig, sim: &SimSettings) -> Result<SimBackend, ConfigError> {
        let scene = sim_scene(sim)?;
        // The third bounce samples hidden surfaces every `sample-spacing`: bound the
        // count before anything is allocated (a scene file is a file from someone else).
        // The sampler's own count, not the area over spacing²: every triangle gets at
        // least one sample, so a mesh of many small triangles needs far more.
        let area: f64 = scene.hidden.iter().map(|s| s.mesh.total_area()).sum();
        let samples = samples_needed(&scene, sim.sample_spacing) as f64;
        if !(samples <= MAX_HIDDEN_SAMPLES) {
            let path = sim.scene.clone().unwrap_or_else(|| "<built-in scene>".into());
            return Err(TomlSource::from_text(path, "").invalid(
                "sim.sample-spacing-mm",
                format!(
                    "the hidden surfaces ({area:.3e} m²) need {samples:.3e} samples at {} mm, more than {MAX_HIDDEN_SAMPLES:.0e}: \
                     use a coarser spacing, smaller hidden objects or meshes of fewer triangles",
                    sim.sample_spacing * 1e3
                ),
            ));
        }
        let world = World::new(scene, sim.sample_spacing, sim.seed);
        let rig = Rig::new(
            Some(world),
            RigSettings {
                laser_pose: sim.true_poses[0],
                spad_pose: sim.true_poses[1],
                limits: [config.laser_arm.limits, config.spad_arm.limits],
                settle: [config.laser_arm.settle, config.spad_arm.settle],
                detector: config.sim_detector(sim),
                time_scale: sim.time_scale,
                seed: sim.seed,
                interlock_closed: sim.interlock_closed,
                noise: sim.noise,
            },
        );
        Ok(SimBackend {
            config: config.clone(),
            in_process: sim.devices == SimDevices::InProcess,
            rig,
        })
    }

    /// The simulated backend `config` names, or `None` for another backend.
    pub fn from_config(config: &InstrumentConfig) -> Result<Option<SimBackend>, ConfigError> {
        match &config.backend {
            crate::config::Backend::Sim(sim) => SimBackend::new(config, sim).map(Some),
            crate::config::Backend::Hardware => Ok(None),
        }
    }

    /// The simulated instrument.
    pub fn rig(&self) -> &Rig {
        &self.rig
    }

    /// Whether `role`'s arm is reached in process: `sim.devices = "in-process"` and
    /// no `serial` table of its own (an arm with one talks to that port: a real
    /// controller, or one simulated in another process).
    fn in_process_arm(&self, role: Role) -> bool {
        self.in_process && role.arm(&self.config).link.is_none()
    }
}

impl std::ops::Deref for SimBackend {
    type Target = Rig;

    fn deref(&self) -> &Rig {
        &self.rig
    }
}

/// The simulated instrument behind `backend`, if it is a [`SimBackend`] (for tests
/// that hold the service's backend only as a [`DeviceBackend`]).
pub fn rig_of(backend: &dyn DeviceBackend) -> Option<&Rig> {
    (backend as &dyn Any)
        .downcast_ref::<SimBackend>()
        .map(SimBackend::rig)
}

impl DeviceBackend for SimBackend {
    fn name(&self) -> &'static str {
        if self.in_process {
            "simulated (in process)"
        } else {
            "simulated (wire)"
        }
    }

    fn laser_arm(&self) -> Result<LaserArm, OpenError> {
        if self.in_process_arm(Role::Laser) {
            return Ok(laser_arm(self.rig.in_process_galvo(
                Arm::Laser,
                self.config.laser_arm.limits,
                Some(self.config.laser.watchdog),
            )));
        }
        let connector: Box<dyn Connector> = Box::new(self.rig.galvo_connector(Arm::Laser));
        Ok(laser_arm(serial_galvo(
            &self.config,
            Role::Laser,
            Some(connector),
        )?))
    }

    fn spad_arm(&self) -> Result<GalvoBox, OpenError> {
        if self.in_process_arm(Role::Spad) {
            return Ok(Erased::galvo(self.rig.in_process_galvo(
                Arm::Spad,
                self.config.spad_arm.limits,
                None,
            )));
        }
        let connector: Box<dyn Connector> = Box::new(self.rig.galvo_connector(Arm::Spad));
        Ok(Erased::galvo(serial_galvo(
            &self.config,
            Role::Spad,
            Some(connector),
        )?))
    }

    fn histogrammer(&self) -> Result<HistogrammerBox, OpenError> {
        if self.in_process {
            return Ok(Erased::histogrammer(self.rig.in_process_tdc()));
        }
        usb_histogrammer(Box::new(self.rig.tdc_transport()))
    }
}
