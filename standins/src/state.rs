//! The library's global state, as a vendor library keeps it per process: the simulated
//! instrument (its rig, its served galvo ports), the counters plugged into each
//! family's device indices, the faults tests queued, and the record of calls.
//!
//! Everything sits behind one mutex; a call holds it for its duration (a measurement
//! runs on its own thread, so no call waits on a dwell).
use std::path::Path;
use std::sync::{Mutex, MutexGuard};

use periscope_daemon::config::InstrumentConfig;
use periscope_daemon::devices::sim::SimBackend;
use periscope_drivers::picoquant::Family;
use periscope_drivers::picoquant::defin::{MAX_DEV_NUM, error};
use periscope_sim::devices::ServedPort;

use crate::device::{Code, Device};

/// The environment variable naming a simulated instrument config to set the stand-in
/// up from on its first call, for a process that cannot call
/// `PERISCOPE_STANDIN_Setup` (a `periscope` binary under test).
pub const CONFIG_ENV: &str = "PERISCOPE_STANDIN_CONFIG";

/// The simulated instrument behind the library.
pub(crate) struct Bench {
    pub backend: SimBackend,
    pub repetition_rate: f64,
    pub ports: Vec<ServedPort>,
}

/// Everything the library keeps.
#[derive(Default)]
pub(crate) struct State {
    pub bench: Option<Bench>,
    /// Per family, the counters at indices `0..MAX_DEV_NUM`.
    pub devices: [Vec<Option<Device>>; 2],
    /// `(function without prefix, code)`: the next call of that function fails.
    pub fail_next: Vec<(Family, String, Code)>,
    /// Every call, as `MH_Function(args)`.
    pub calls: Vec<String>,
    /// Whether the environment variable was looked at.
    pub env_checked: bool,
    /// The simulated DAQ device, once wired ([`crate::daqmx`]).
    pub daq: Option<crate::daqmx::Daq>,
    /// DAQmx functions whose next call fails with a code.
    pub daq_fail_next: Vec<(String, Code)>,
    /// Whether the DAQ wiring's environment variable was looked at.
    pub daq_env_checked: bool,
}

static STATE: Mutex<Option<State>> = Mutex::new(None);

/// The state, created empty on first use.
pub(crate) fn lock() -> MutexGuard<'static, Option<State>> {
    let mut g = STATE.lock().unwrap_or_else(|p| p.into_inner());
    if g.is_none() {
        *g = Some(State {
            devices: [empty(), empty()],
            ..State::default()
        });
    }
    g
}

fn empty() -> Vec<Option<Device>> {
    (0..MAX_DEV_NUM).map(|_| None).collect()
}

pub(crate) fn family_index(f: Family) -> usize {
    match f {
        Family::MultiHarp => 0,
        Family::HydraHarp => 1,
    }
}

impl State {
    /// Drops the instrument and every counter (stopping their threads).
    pub(crate) fn reset(&mut self) {
        if let Some(daq) = self.daq.as_mut() {
            daq.shut_down();
        }
        for list in &mut self.devices {
            for d in list.iter_mut().flatten() {
                d.close();
            }
        }
        *self = State {
            devices: [empty(), empty()],
            env_checked: true,
            daq_env_checked: self.daq_env_checked,
            ..State::default()
        };
    }

    /// Wires the simulated DAQ device as the hardware config at `path` says, on the
    /// rig set up before.
    pub(crate) fn wire_daq(&mut self, path: &Path) -> Result<(), String> {
        let rig = self
            .bench
            .as_ref()
            .ok_or("set the stand-in up first")?
            .backend
            .rig()
            .clone();
        if let Some(old) = self.daq.as_mut() {
            old.shut_down();
        }
        self.daq = Some(crate::daqmx::Daq::wire(rig, path)?);
        Ok(())
    }

    /// Records a DAQmx call; answers with a queued failure for it, if there is one.
    pub(crate) fn enter_daq(&mut self, function: &str, args: String) -> Result<(), Code> {
        self.check_env();
        if !self.daq_env_checked {
            self.daq_env_checked = true;
            if let Some(path) = std::env::var_os(crate::daqmx::DAQ_CONFIG_ENV)
                && let Err(e) = self.wire_daq(Path::new(&path))
            {
                eprintln!("periscope stand-in: {}: {e}", crate::daqmx::DAQ_CONFIG_ENV);
            }
        }
        self.calls.push(format!("{function}({args})"));
        match self.daq_fail_next.iter().position(|(name, _)| name == function) {
            Some(i) => Err(self.daq_fail_next.remove(i).1),
            None => Ok(()),
        }
    }

    /// The DAQ device, or the answer of a library that sees none.
    pub(crate) fn daq(&mut self) -> Result<&mut crate::daqmx::Daq, Code> {
        self.daq
            .as_mut()
            .ok_or(periscope_drivers::daqmx::defin::error::DEV_ABSENT_OR_UNAVAILABLE)
    }

    fn check_env(&mut self) {
        if !self.env_checked {
            self.env_checked = true;
            if let Some(path) = std::env::var_os(CONFIG_ENV)
                && let Err(e) = self.setup(Path::new(&path))
            {
                eprintln!("periscope stand-in: {CONFIG_ENV}: {e}");
            }
        }
    }

    /// Builds the simulated instrument from the config at `path` (`backend = "sim"`)
    /// and plugs one counter of each family into index 0.
    pub(crate) fn setup(&mut self, path: &Path) -> Result<(), String> {
        self.reset();
        let config = InstrumentConfig::load(path).map_err(|e| e.to_string())?;
        let backend = SimBackend::from_config(&config)
            .map_err(|e| e.to_string())?
            .ok_or_else(|| {
                format!(
                    "{}: the stand-in needs a simulated instrument (backend = \"sim\")",
                    path.display()
                )
            })?;
        // The bench's laser pulses as the simulator's does: at `sim.true-rep-rate-mhz`
        // where the config sets it, so a counter can read another rate than the
        // daemon's config expects.
        let repetition_rate = match &config.backend {
            periscope_daemon::config::Backend::Sim(sim) => sim.true_repetition_rate,
            periscope_daemon::config::Backend::Hardware => config.laser.repetition_rate,
        };
        self.bench = Some(Bench {
            backend,
            repetition_rate,
            ports: Vec::new(),
        });
        self.plug(Family::MultiHarp, 0, "1045678", 4, 0)?;
        self.plug(Family::HydraHarp, 0, "1012345", 4, 0)?;
        Ok(())
    }

    /// A counter of `family` with `serial` at `index`, its SPAD on `spad_channel`.
    pub(crate) fn plug(
        &mut self,
        family: Family,
        index: i32,
        serial: &str,
        channels: i32,
        spad_channel: i32,
    ) -> Result<(), String> {
        let bench = self.bench.as_ref().ok_or("set the stand-in up first")?;
        if !(0..MAX_DEV_NUM).contains(&index) || !(1..=64).contains(&channels) {
            return Err(format!("index {index} or {channels} channels out of range"));
        }
        let tdc = bench.backend.rig().in_process_tdc();
        let device = Device::new(family, serial, channels, spad_channel, tdc, bench.repetition_rate);
        let slot = &mut self.devices[family_index(family)][index as usize];
        if let Some(old) = slot.as_mut() {
            old.close();
        }
        *slot = Some(device);
        Ok(())
    }

    /// The counter at `index` of `family`, or the library's answer for an empty index.
    pub(crate) fn device(&mut self, family: Family, index: i32) -> Result<&mut Device, Code> {
        if !(0..MAX_DEV_NUM).contains(&index) {
            return Err(error::INVALID_ARGUMENT);
        }
        self.devices[family_index(family)][index as usize]
            .as_mut()
            .ok_or(error::DEVICE_OPEN_FAIL)
    }

    /// Records a call; answers with a queued failure for it, if there is one.
    pub(crate) fn enter(&mut self, family: Family, function: &str, args: String) -> Result<(), Code> {
        self.check_env();
        self.calls.push(format!("{}{function}({args})", family.prefix()));
        match self
            .fail_next
            .iter()
            .position(|(f, name, _)| *f == family && name == function)
        {
            Some(i) => Err(self.fail_next.remove(i).2),
            None => Ok(()),
        }
    }
}
