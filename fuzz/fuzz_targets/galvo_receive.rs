//! The galvo driver's receive loop over a controller that sends arbitrary bytes: every
//! request ends in an answer or an error, never a panic or a hang.
#![no_main]

// The allocator that refuses what the fuzz limit does not allow (fuzz/src/lib.rs).
use periscope_fuzz as _;

libfuzzer_sys::fuzz_target!(|data: &[u8]| periscope_daemon::fuzz::galvo_receive(data));
