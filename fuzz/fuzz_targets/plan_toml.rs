//! Capture plans (TOML from operators and over HTTP) and their budget: any text gives
//! a plan or an error naming the key, and a plan's budget never overflows.
#![no_main]

// The allocator that refuses what the fuzz limit does not allow (fuzz/src/lib.rs).
use periscope_fuzz as _;

libfuzzer_sys::fuzz_target!(|data: &[u8]| periscope_daemon::fuzz::plan_toml(data));
