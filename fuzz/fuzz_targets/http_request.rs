//! The HTTP API through its router: any request, from this machine or another, with no
//! key or an observer's, is answered in time, never with a 500, and every error as the
//! API's JSON (`periscope_daemon::fuzz::http_request` says how the bytes become a
//! request).
#![no_main]

// The allocator that refuses what the fuzz limit does not allow (fuzz/src/lib.rs).
use periscope_fuzz as _;

libfuzzer_sys::fuzz_target!(
    // The router and its finished run, made before any input is timed.
    init: periscope_daemon::fuzz::http_request_init(),
    |data: &[u8]| periscope_daemon::fuzz::http_request(data)
);
