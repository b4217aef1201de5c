//! The TDC's wire formats: histogram frames and the control replies.
#![no_main]

// The allocator that refuses what the fuzz limit does not allow (fuzz/src/lib.rs).
use periscope_fuzz as _;

libfuzzer_sys::fuzz_target!(|data: &[u8]| periscope_daemon::fuzz::tdc_frame(data));
