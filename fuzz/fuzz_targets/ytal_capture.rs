//! y-tal HDF5 captures (files downloaded from papers): decoding, the default volume
//! and the rebinned transients. Any input: an answer or a named error, never a panic
//! or an allocation beyond the readers' limits.
#![no_main]

// The allocator that refuses what the fuzz limit does not allow (fuzz/src/lib.rs).
use periscope_fuzz as _;

libfuzzer_sys::fuzz_target!(|data: &[u8]| periscope_daemon::fuzz::ytal_capture(data));
