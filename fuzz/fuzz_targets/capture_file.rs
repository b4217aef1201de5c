//! Capture files of every public format (files downloaded from papers): MAT v5 and
//! v7.3, ZNLOS and y-tal HDF5, told apart by their contents, and the capture each
//! reader builds. Any input: a capture or a named error, never a panic or an
//! allocation beyond the readers' limits.
#![no_main]

// The allocator that refuses what the fuzz limit does not allow (fuzz/src/lib.rs).
use periscope_fuzz as _;

libfuzzer_sys::fuzz_target!(|data: &[u8]| periscope_daemon::fuzz::capture_file(data));
