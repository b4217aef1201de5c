//! The TDC's wire formats: histogram frames and the control replies.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| periscope_daemon::fuzz::tdc_frame(data));
