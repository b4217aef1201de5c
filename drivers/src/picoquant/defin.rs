//! What PicoQuant's headers define (`mhdefin.h`, `hhdefin.h`, `errorcodes.h`), written
//! once: the driver and the test stand-in library both use these numbers, so a value
//! that changes in the vendor's headers changes in one place.
//!
//! Taken from the published headers of MHLib 3.1 (MultiHarp 150/160) and HHLib 3.0
//! (HydraHarp 400). Where the two libraries differ, [`crate::picoquant::Family`] says
//! which value applies.

/// Device indices the libraries accept: `0..MAX_DEV_NUM`.
pub const MAX_DEV_NUM: i32 = 8;
/// `MODE_HIST`: histogramming mode, for `*_Initialize`.
pub const MODE_HIST: i32 = 0;
/// `REFSRC_INTERNAL`: the device's own clock, for `*_Initialize`.
pub const REFSRC_INTERNAL: i32 = 0;
/// `MAXHISTLEN`: the longest histogram, bins (length code 6).
pub const MAX_HIST_LEN: usize = 65_536;
/// `MAXLENCODE`: length codes run `0..=MAX_LEN_CODE`; a code `c` gives `1024 · 2^c` bins.
pub const MAX_LEN_CODE: i32 = 6;
/// `ACQTMIN`..`ACQTMAX`: acquisition time, ms.
pub const ACQ_MS: std::ops::RangeInclusive<i64> = 1..=360_000_000;
/// `CHANOFFSMIN`..`CHANOFFSMAX`: sync and input channel offsets, ps.
pub const CHANNEL_OFFSET_PS: std::ops::RangeInclusive<i32> = -99_999..=99_999;
/// `EDGE_FALLING` and `EDGE_RISING` (MultiHarp edge triggers).
pub const EDGE_FALLING: i32 = 0;
/// See [`EDGE_FALLING`].
pub const EDGE_RISING: i32 = 1;

/// Bits of `*_GetFlags`.
pub mod flag {
    /// A histogram bin overflowed (histogram mode).
    pub const OVERFLOW: i32 = 0x0001;
    /// The FIFO overran (time-tagging modes).
    pub const FIFOFULL: i32 = 0x0002;
    /// The sync signal was lost.
    pub const SYNC_LOST: i32 = 0x0004;
    /// The external reference clock was lost.
    pub const REF_LOST: i32 = 0x0008;
    /// Hardware error: the vendor asks to contact its support.
    pub const SYSERROR: i32 = 0x0010;
    /// A measurement is running.
    pub const ACTIVE: i32 = 0x0020;
    /// Events were dropped (MultiHarp).
    pub const CNTS_DROPPED: i32 = 0x0040;
}

/// Bits of `*_GetWarnings` (valid after the count rates were read).
pub mod warning {
    /// No sync signal.
    pub const SYNC_RATE_ZERO: i32 = 0x0001;
    /// Sync rate very low.
    pub const SYNC_RATE_VERY_LOW: i32 = 0x0002;
    /// Sync rate too high.
    pub const SYNC_RATE_TOO_HIGH: i32 = 0x0004;
    /// No counts on an enabled input.
    pub const INPT_RATE_ZERO: i32 = 0x0010;
    /// An input's rate is too high.
    pub const INPT_RATE_TOO_HIGH: i32 = 0x0040;
    /// An input's rate is above 5 % of the sync rate: pile-up distorts the histogram.
    pub const INPT_RATE_RATIO: i32 = 0x0100;
    /// The sync divider is above 1.
    pub const DIVIDER_GREATER_ONE: i32 = 0x0200;
    /// The histogram spans less than the sync period.
    pub const TIME_SPAN_TOO_SMALL: i32 = 0x0400;
    /// The offset is not needed.
    pub const OFFSET_UNNECESSARY: i32 = 0x0800;
    /// The sync divider is too small (MultiHarp).
    pub const DIVIDER_TOO_SMALL: i32 = 0x1000;
    /// Counts were dropped (MultiHarp).
    pub const COUNTS_DROPPED: i32 = 0x2000;
}

/// Error codes (`MH_ERROR_*`, `HH_ERROR_*`: the same numbers in both libraries).
pub mod error {
    /// No device at this index (or it cannot be opened).
    pub const DEVICE_OPEN_FAIL: i32 = -1;
    /// The device is in use by another program.
    pub const DEVICE_BUSY: i32 = -2;
    /// Library, driver or firmware versions do not match.
    pub const DEVICE_VERSION_MISMATCH: i32 = -9;
    /// The device is not open.
    pub const DEVICE_NOT_OPEN: i32 = -10;
    /// The device is locked by another program.
    pub const DEVICE_LOCKED: i32 = -11;
    /// The kernel driver's version does not match.
    pub const DEVICE_DRIVERVER_MISMATCH: i32 = -12;
    /// Another instance of the library holds the device.
    pub const INSTANCE_RUNNING: i32 = -16;
    /// An argument is out of range.
    pub const INVALID_ARGUMENT: i32 = -17;
    /// The call is not valid in this mode.
    pub const INVALID_MODE: i32 = -18;
    /// An option is not valid.
    pub const INVALID_OPTION: i32 = -19;
    /// Memory could not be allocated.
    pub const INVALID_MEMORY: i32 = -20;
    /// The device is not initialised.
    pub const NOT_INITIALIZED: i32 = -22;
    /// The device is not calibrated.
    pub const NOT_CALIBRATED: i32 = -23;
    /// First of the USB errors (`USB_GETDRIVERVER_FAIL`).
    pub const USB_FIRST: i32 = -32;
    /// The USB driver's version does not match.
    pub const USB_DRIVERVER_MISMATCH: i32 = -33;
    /// A USB vendor command failed.
    pub const USB_VCMD_FAIL: i32 = -36;
    /// A USB bulk read failed.
    pub const USB_BULKRD_FAIL: i32 = -37;
    /// Last of the USB errors (`USB_RESET_FAIL`).
    pub const USB_LAST: i32 = -38;
    /// First of the hardware timeouts (`LANEUP_TIMEOUT`).
    pub const TIMEOUT_FIRST: i32 = -40;
    /// Last of the hardware timeouts (`MACTIVE_TIMEOUT`).
    pub const TIMEOUT_LAST: i32 = -43;
    /// First of the module firmware mismatches (`MODFWPCB_MISMATCH`).
    pub const MODULE_MISMATCH_FIRST: i32 = -52;
    /// Last of the module firmware mismatches (`MODPROPERTY_MISMATCH`).
    pub const MODULE_MISMATCH_LAST: i32 = -54;
    /// Module firmware too old (MultiHarp).
    pub const MODFWVER_TOO_LOW: i32 = -58;
    /// Module firmware too new (MultiHarp).
    pub const MODFWVER_TOO_HIGH: i32 = -59;
}
