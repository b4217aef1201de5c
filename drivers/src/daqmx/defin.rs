//! The numbers of NI-DAQmx's C API that the driver uses, as `NIDAQmx.h` defines them
//! (checked against the header NI ships with NI-DAQmx, and against the error table of
//! NI's own Python API, `nidaqmx/error_codes.py`). Kept apart so the stand-in library
//! answers with the very same numbers.

/// `DAQmx_Val_Volts`: units of an analog output voltage channel.
pub const VAL_VOLTS: i32 = 10348;
/// `DAQmx_Val_ChanForAllLines`: one channel for all the lines given.
pub const VAL_CHAN_FOR_ALL_LINES: i32 = 1;
/// `DAQmx_Val_GroupByChannel`: non-interleaved samples (`dataLayout`).
pub const VAL_GROUP_BY_CHANNEL: u32 = 0;
/// `DAQmx_Val_Low`: a digital line's low state (a watchdog expiration state).
pub const VAL_LOW: i32 = 10214;
/// `DAQmx_Val_High`: a digital line's high state.
pub const VAL_HIGH: i32 = 10192;
/// `DAQmx_Val_ResetTimer`: `DAQmxControlWatchdogTask`'s action that feeds the timer.
pub const VAL_RESET_TIMER: i32 = 0;
/// `DAQmx_Val_ClearExpiration`: the action that clears an expired watchdog.
pub const VAL_CLEAR_EXPIRATION: i32 = 1;

/// The largest voltage an NI multifunction card's analog outputs take (±10 V range).
pub const MAX_AO_VOLTS: f64 = 10.0;

/// `DAQmxError…` codes the driver tells apart (negative: errors; positive codes are
/// warnings, which the driver logs and goes on).
pub mod error {
    /// `DAQmxErrorDeviceRemoved`.
    pub const DEVICE_REMOVED: i32 = -200045;
    /// `DAQmxErrorDevAbsentOrUnavailable`.
    pub const DEV_ABSENT_OR_UNAVAILABLE: i32 = -200324;
    /// `DAQmxErrorDevCannotBeAccessed`.
    pub const DEV_CANNOT_BE_ACCESSED: i32 = -201003;
    /// `DAQmxErrorInvalidDeviceID`.
    pub const INVALID_DEVICE_ID: i32 = -200220;
    /// `DAQmxErrorPALUSBTransactionError`.
    pub const PAL_USB_TRANSACTION_ERROR: i32 = -50808;
    /// `DAQmxErrorResourceAlreadyReserved`.
    pub const RESOURCE_ALREADY_RESERVED: i32 = -200022;
    /// `DAQmxErrorPALResourceReserved`.
    pub const PAL_RESOURCE_RESERVED: i32 = -50103;
    /// `DAQmxErrorInvalidAttributeValue`.
    pub const INVALID_ATTRIBUTE_VALUE: i32 = -200077;
    /// `DAQmxErrorMinNotLessThanMax`.
    pub const MIN_NOT_LESS_THAN_MAX: i32 = -200082;
    /// `DAQmxErrorPhysicalChanDoesNotExist`.
    pub const PHYSICAL_CHAN_DOES_NOT_EXIST: i32 = -200170;
    /// `DAQmxErrorInvalidPhysChanName`.
    pub const INVALID_PHYS_CHAN_NAME: i32 = -201237;
    /// `DAQmxErrorSampleValueOutOfRange`.
    pub const SAMPLE_VALUE_OUT_OF_RANGE: i32 = -200490;
    /// `DAQmxErrorInvalidAODataWrite`: an analog output value outside the range its
    /// channel was created with (what `DAQmxWriteAnalogF64` answers).
    pub const INVALID_AO_DATA_WRITE: i32 = -200561;
    /// `DAQmxErrorDuplicateTask`: a task of that name already exists (in this or
    /// another program).
    pub const DUPLICATE_TASK: i32 = -200089;
    /// `DAQmxErrorTimeoutExceeded`.
    pub const TIMEOUT_EXCEEDED: i32 = -200221;
    /// `DAQmxErrorOperationTimedOut`.
    pub const OPERATION_TIMED_OUT: i32 = -200474;
    /// `DAQmxErrorInvalidTask`.
    pub const INVALID_TASK: i32 = -200088;
    /// `DAQmxErrorWatchdogTimerNotSupported`: the device has no hardware watchdog.
    pub const WATCHDOG_TIMER_NOT_SUPPORTED: i32 = -200662;
    /// `DAQmxErrorWriteFailedBecauseWatchdogExpired`: the line holds its expiration
    /// state until the expiration is cleared.
    pub const WRITE_FAILED_BECAUSE_WATCHDOG_EXPIRED: i32 = -200678;
    /// `DAQmxErrorBufferTooSmallForString`.
    pub const BUFFER_TOO_SMALL_FOR_STRING: i32 = -200228;
    /// `DAQmxErrorWriteNumChansMismatch`: the data's channels are not the task's.
    pub const WRITE_NUM_CHANS_MISMATCH: i32 = -200524;
}
