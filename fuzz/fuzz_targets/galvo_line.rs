//! The galvo controllers' line protocol: a line that decodes is exactly the line the
//! encoder writes for its tag and body, and request and reply bodies parse without
//! panicking.
#![no_main]

// The allocator that refuses what the fuzz limit does not allow (fuzz/src/lib.rs).
use periscope_fuzz as _;

libfuzzer_sys::fuzz_target!(|data: &[u8]| periscope_daemon::fuzz::galvo_line(data));
