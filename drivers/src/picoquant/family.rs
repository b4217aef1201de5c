//! What differs between PicoQuant's libraries: the MultiHarp's MHLib and the
//! HydraHarp's HHLib export the same histogram-mode calls under their own prefix, with a
//! few differences this type names (edge triggers or constant-fraction discriminators,
//! calibration, `GetHistogram`'s extra argument, ranges). One driver, parameterised by
//! the family, instead of two copies.

use super::defin;
use crate::traits::TdcConfig;

/// Which PicoQuant library, and so which instruments.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Family {
    /// MultiHarp 150/160 through MHLib (`MH_` functions).
    MultiHarp,
    /// HydraHarp 400 through HHLib (`HH_` functions).
    HydraHarp,
}

/// How the instrument's inputs discriminate pulses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Trigger {
    /// An edge trigger at a level (MultiHarp).
    Edge {
        /// Trigger level, mV (-1200 to 1200).
        level_mv: i32,
        /// Rising edge (`true`) or falling edge (`false`).
        rising: bool,
    },
    /// A constant-fraction discriminator (HydraHarp).
    Cfd {
        /// Discriminator level, mV (0 to 1000).
        level_mv: i32,
        /// Zero-cross level, mV (0 to 40).
        zero_cross_mv: i32,
    },
}

impl Family {
    /// The instrument's name: `MultiHarp` or `HydraHarp`.
    pub fn name(self) -> &'static str {
        match self {
            Family::MultiHarp => "MultiHarp",
            Family::HydraHarp => "HydraHarp",
        }
    }

    /// The library's name: `MHLib` or `HHLib`.
    pub fn library_name(self) -> &'static str {
        match self {
            Family::MultiHarp => "MHLib",
            Family::HydraHarp => "HHLib",
        }
    }

    /// The prefix of the library's functions: `MH_` or `HH_`.
    pub fn prefix(self) -> &'static str {
        match self {
            Family::MultiHarp => "MH_",
            Family::HydraHarp => "HH_",
        }
    }

    /// Where PicoQuant's Linux packages and demos put the 64-bit library (the demos of
    /// MHLib and HHLib load it from these paths).
    pub fn default_library(self) -> &'static str {
        match self {
            Family::MultiHarp => "/usr/local/lib64/mh150/mhlib.so",
            Family::HydraHarp => "/usr/local/lib64/hh400/hhlib.so",
        }
    }

    /// Whether the inputs use constant-fraction discriminators (HydraHarp) rather than
    /// edge triggers (MultiHarp).
    pub fn uses_cfd(self) -> bool {
        self == Family::HydraHarp
    }

    /// The trigger the vendor's demos start from: edge at -50 mV, falling, on the
    /// MultiHarp; CFD at 50 mV with a 10 mV zero cross on the HydraHarp.
    pub fn default_trigger(self) -> Trigger {
        match self {
            Family::MultiHarp => Trigger::Edge {
                level_mv: -50,
                rising: false,
            },
            Family::HydraHarp => Trigger::Cfd {
                level_mv: 50,
                zero_cross_mv: 10,
            },
        }
    }

    /// Whether `trigger` is one this family's inputs take, within their ranges
    /// (`TRGLVLMIN..TRGLVLMAX`; `DISCRMIN..DISCRMAX`, `ZCMIN..ZCMAX`).
    pub fn accepts(self, trigger: Trigger) -> bool {
        match (self, trigger) {
            (Family::MultiHarp, Trigger::Edge { level_mv, .. }) => (-1200..=1200).contains(&level_mv),
            (
                Family::HydraHarp,
                Trigger::Cfd {
                    level_mv,
                    zero_cross_mv,
                },
            ) => (0..=1000).contains(&level_mv) && (0..=40).contains(&zero_cross_mv),
            _ => false,
        }
    }

    /// Whether the device must be calibrated after initialising (HydraHarp).
    pub(crate) fn calibrates(self) -> bool {
        self == Family::HydraHarp
    }

    /// The shortest length code `GetHistogram` reads: MHLib's header says codes 0 and
    /// 1 do not work with `MH_GetHistogram`.
    pub fn min_len_code(self) -> i32 {
        match self {
            Family::MultiHarp => 2,
            Family::HydraHarp => 0,
        }
    }

    /// Whether the sync divider `div` is one the device takes: 1 to 16 on the
    /// MultiHarp, a power of two up to 16 on the HydraHarp. (Wrappers of the
    /// libraries disagree on the MultiHarp: QuTech's QMI takes 1 to 16, Ulm's qudi
    /// powers of two; MHLib's header gives only `SYNCDIVMAX` 16.)
    pub fn sync_divider_ok(self, div: u32) -> bool {
        match self {
            Family::MultiHarp => (1..=16).contains(&div),
            Family::HydraHarp => div.is_power_of_two() && div <= 16,
        }
    }

    /// The highest sync rate after the divider the inputs take, Hz: "the sync divider
    /// must be used to keep the effective sync rate at values ≤ 12.5 MHz" (HHLib's
    /// manual, `HH_SetSyncDiv`) and "< 78 MHz" (MHLib's, `MH_SetSyncDiv`).
    pub fn max_sync_rate_hz(self) -> f64 {
        match self {
            Family::MultiHarp => 78e6,
            Family::HydraHarp => 12.5e6,
        }
    }

    /// The largest histogram offset, ns (`OFFSETMAX`).
    pub fn max_offset_ns(self) -> i64 {
        match self {
            Family::MultiHarp => 100_000_000,
            Family::HydraHarp => 500_000,
        }
    }
}

/// The settings a PicoQuant library is given for a [`TdcConfig`], in its own units.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Settings {
    /// Acquisition time, whole milliseconds.
    pub acquisition_ms: i32,
    /// Histogram offset, whole nanoseconds.
    pub offset_ns: i32,
    /// Histogram length code: `1024 · 2^code` bins.
    pub len_code: i32,
}

impl Family {
    /// `config` as this family's library takes it: its sync divider, a whole number of
    /// milliseconds (1 ms to 100 h), an offset of whole nanoseconds within the family's
    /// range and a histogram length code that holds its bins. `Err` says what the device
    /// would refuse and what to set instead. What depends on the device itself (the bin
    /// width, its base resolution times a power of two) is checked once it is open.
    /// Needs no device, so `periscope check` asks it too.
    pub fn settings(self, config: &TdcConfig) -> Result<Settings, String> {
        if !self.sync_divider_ok(config.sync_divider) {
            return Err(format!(
                "the {self} does not take sync divider {} (tdc.sync-divider): {}",
                config.sync_divider,
                match self {
                    Family::MultiHarp => "use 1 to 16",
                    Family::HydraHarp => "use 1, 2, 4, 8 or 16",
                }
            ));
        }
        let acquisition_ms = whole(config.acquisition.as_secs_f64() * 1e3, 1e-3)
            .filter(|ms| defin::ACQ_MS.contains(ms))
            .ok_or_else(|| {
                format!(
                    "the {self} measures whole milliseconds (1 ms to 100 h), not a dwell of {:?}: set the plan's dwell-ms to a whole number",
                    config.acquisition
                )
            })?;
        let offset_ns = whole(config.offset * 1e9, 1e-3)
            .filter(|ns| (0..=self.max_offset_ns()).contains(ns))
            .ok_or_else(|| {
                format!(
                    "the {self} sets its histogram offset in whole nanoseconds (0 to {} ns), not {} ns: set offset-ns to a whole number",
                    self.max_offset_ns(),
                    config.offset * 1e9
                )
            })?;
        let len_code = (self.min_len_code()..=defin::MAX_LEN_CODE)
            .find(|c| 1024usize << c >= config.bins as usize)
            .ok_or_else(|| {
                format!(
                    "the {self} histograms at most {} bins, not {}",
                    defin::MAX_HIST_LEN,
                    config.bins
                )
            })?;
        // Each is within i32: ACQ_MS and the offsets' ranges are.
        Ok(Settings {
            acquisition_ms: acquisition_ms as i32,
            offset_ns: offset_ns as i32,
            len_code,
        })
    }
}

/// `x` as a whole number, if it lies within `tolerance` of one.
fn whole(x: f64, tolerance: f64) -> Option<i64> {
    let r = x.round();
    (x.is_finite() && (x - r).abs() <= tolerance).then_some(r as i64)
}

impl std::fmt::Display for Family {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}
