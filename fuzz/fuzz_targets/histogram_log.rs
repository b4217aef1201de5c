//! The histogram log (`histograms.bin`), read back on resume and export: the valid
//! prefix and the discarded tail always add up to the input, and every record kept
//! has sane settings.
#![no_main]

// The allocator that refuses what the fuzz limit does not allow (fuzz/src/lib.rs).
use periscope_fuzz as _;

libfuzzer_sys::fuzz_target!(|data: &[u8]| periscope_daemon::fuzz::histogram_log(data));
