//! Helpers shared by recon's integration tests (each test file is its own crate and
//! takes this module with `mod common;`).

/// `f` run on a pool of `threads` threads: what a result does not depend on, the
/// tests vary.
pub(crate) fn on_threads<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(f)
}
