//! Stanford LCT `.mat` captures (files downloaded from papers): bounded inflation, the
//! MAT v5 parse and the capture built from it. Any input: a capture or a named error,
//! never a panic or an allocation beyond the reader's limits.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| periscope_daemon::fuzz::lct_mat(data));
