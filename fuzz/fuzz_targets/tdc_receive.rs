//! The TDC driver's receive loop over a device that sends arbitrary bytes (chunked as
//! the input's first byte says), optionally followed by the genuine frame: the driver
//! returns a histogram only for the acquisition it asked for, with the configured
//! bin count, and never panics.
#![no_main]

// The allocator that refuses what the fuzz limit does not allow (fuzz/src/lib.rs).
use periscope_fuzz as _;

libfuzzer_sys::fuzz_target!(|data: &[u8]| periscope_daemon::fuzz::tdc_receive(data));
