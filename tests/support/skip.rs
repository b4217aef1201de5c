//! A test that cannot run here says so where `cargo test` shows it.

/// Writes `SKIPPED …` to the process's stderr. libtest captures `eprintln!` from a test
/// that passes and shows nothing of it, so a skip written that way is silent; a write
/// to `std::io::stderr()` itself is not captured.
pub fn skipped(why: std::fmt::Arguments<'_>) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr(), "SKIPPED {why}");
}
