//! Instrument configs and RECON.toml files: any text gives a config or an error naming
//! the key, never a panic.
#![no_main]

// The allocator that refuses what the fuzz limit does not allow (fuzz/src/lib.rs).
use periscope_fuzz as _;

libfuzzer_sys::fuzz_target!(|data: &[u8]| periscope_daemon::fuzz::config_toml(data));
