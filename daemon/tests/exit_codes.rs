//! Exit codes of the binary, which scripts and the CI rely on. (Having an integration
//! test here also makes `cargo test --workspace` build the `periscope` binary that the
//! end-to-end tests in tests/ drive.)
use std::process::Command;

fn periscope(args: &[&str]) -> (Option<i32>, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_periscope"))
        .args(args)
        .current_dir(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
        .output()
        .expect("periscope runs");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn success_is_zero() {
    assert_eq!(periscope(&["--help"]).0, Some(0));
}

#[test]
fn config_errors_are_two() {
    let (code, stderr) = periscope(&["serve", "--instrument", "Cargo.toml"]);
    assert_eq!(code, Some(2), "{stderr}");
    assert!(stderr.contains("Cargo.toml"), "{stderr}");
}
