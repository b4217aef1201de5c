//! What differs between PicoQuant's libraries: the MultiHarp's MHLib and the
//! HydraHarp's HHLib export the same histogram-mode calls under their own prefix, with a
//! few differences this type names (edge triggers or constant-fraction discriminators,
//! calibration, `GetHistogram`'s extra argument, ranges). One driver, parameterised by
//! the family, instead of two copies.

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
    /// MultiHarp, a power of two up to 16 on the HydraHarp.
    pub fn sync_divider_ok(self, div: u32) -> bool {
        match self {
            Family::MultiHarp => (1..=16).contains(&div),
            Family::HydraHarp => div.is_power_of_two() && div <= 16,
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

impl std::fmt::Display for Family {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}
