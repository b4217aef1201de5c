//! Scene meshes (PLY, ASCII or binary, and OBJ): a mesh that loads has faces whose
//! indices are in range and finite vertices.
#![no_main]

// The allocator that refuses what the fuzz limit does not allow (fuzz/src/lib.rs).
use periscope_fuzz as _;

libfuzzer_sys::fuzz_target!(|data: &[u8]| periscope_daemon::fuzz::mesh(data));
