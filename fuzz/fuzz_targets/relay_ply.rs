//! `relay.ply`, read back on resume: only the relay layout with finite points and
//! unit normals is accepted.
#![no_main]

// The allocator that refuses what the fuzz limit does not allow (fuzz/src/lib.rs).
use periscope_fuzz as _;

libfuzzer_sys::fuzz_target!(|data: &[u8]| periscope_daemon::fuzz::relay_ply(data));
