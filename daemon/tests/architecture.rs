//! The invariants `ARCHITECTURE.md` states, checked (rust-analyzer's `tidy.rs` in
//! spirit): a sentence there that no test holds decays. Each test names the section
//! of `ARCHITECTURE.md` it holds.
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Every `.rs` file under `dir`, recursively, sorted.
fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_owned()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                out.push(path);
            }
        }
    }
    out.sort();
    out
}

/// A file's code without comments and without its `#[cfg(test)]` module (the tests
/// may name anything).
fn code(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap();
    let text = text.split("#[cfg(test)]\nmod tests").next().unwrap_or("");
    text.lines()
        .filter(|l| !l.trim_start().starts_with("//"))
        .collect::<Vec<_>>()
        .join("\n")
}

/// "The device boundary": past `daemon::devices`, nothing names a driver type, a
/// driver's own error or the simulator. The pipeline, the run service and the API see
/// the device traits, `DeviceError` and `DeviceBackend` only.
#[test]
fn nothing_past_the_device_boundary_names_a_driver_or_the_simulator() {
    const FORBIDDEN: &[&str] = &[
        "periscope_sim",
        "periscope_drivers::galvo",
        "periscope_drivers::tdc",
        "periscope_drivers::picoquant",
        "periscope_drivers::daqmx",
        "SerialGalvo",
        "UsbTdc",
        "PicoQuantTdc",
        "PicoQuantError",
        "DaqGalvo",
        "DaqLaser",
        "DaqError",
        "GalvoError",
        "TdcError",
        "InProcessGalvo",
        "InProcessTdc",
        "Rig",
        "SimBackend",
        "HardwareBackend",
    ];
    let mut found = Vec::new();
    for dir in ["pipeline", "service", "api", "calibrate"] {
        for file in rust_files(&root().join("daemon/src").join(dir)) {
            let code = code(&file);
            for word in FORBIDDEN {
                let named = code.match_indices(word).any(|(i, _)| {
                    let before = code[..i].chars().next_back();
                    let after = code[i + word.len()..].chars().next();
                    let ident = |c: Option<char>| c.is_some_and(|c| c.is_alphanumeric() || c == '_');
                    !ident(before) && !ident(after)
                });
                if named {
                    found.push(format!("{} names `{word}`", file.display()));
                }
            }
        }
    }
    assert!(
        found.is_empty(),
        "past the device boundary:\n{}",
        found.join("\n")
    );
}

/// "One laser guard": every laser driver keeps the one `LaserGuard` (implements
/// `GuardedLaser`), and no other code runs a keepalive of its own.
#[test]
fn every_laser_driver_uses_the_one_guard() {
    let mut drivers = BTreeMap::new();
    for crate_dir in ["drivers/src", "sim/src", "daemon/src"] {
        for file in rust_files(&root().join(crate_dir)) {
            let code = code(&file);
            for line in code.lines() {
                let line = line.trim();
                if let Some(rest) = line.strip_prefix("impl Laser for ") {
                    let ty = rest.split([' ', '{', '<']).next().unwrap_or("").to_owned();
                    drivers.insert(ty, (file.clone(), code.clone()));
                }
            }
            if !file.ends_with("laser_guard.rs") {
                assert!(
                    !code.contains("keepalive\"") && !code.contains("-keepalive"),
                    "{} runs a keepalive thread of its own: use periscope_drivers::LaserGuard",
                    file.display()
                );
            }
        }
    }
    assert!(
        drivers.contains_key("SerialGalvo")
            && drivers.contains_key("InProcessGalvo")
            && drivers.contains_key("DaqLaser"),
        "laser drivers found: {:?}",
        drivers.keys().collect::<Vec<_>>()
    );
    for (ty, (file, code)) in &drivers {
        assert!(
            code.contains(&format!("impl GuardedLaser for {ty}")),
            "{ty} ({}) implements Laser without the LaserGuard (`impl GuardedLaser for {ty}`)",
            file.display()
        );
    }
}

/// "Modules point one way": the daemon's top-level modules import one another without
/// circles (a module reaching back into one that imports it is a circle).
#[test]
fn the_daemon_modules_import_one_another_without_circles() {
    let src = root().join("daemon/src");
    let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for file in rust_files(&src) {
        let rel = file.strip_prefix(&src).unwrap();
        let module = rel
            .components()
            .next()
            .unwrap()
            .as_os_str()
            .to_string_lossy()
            .trim_end_matches(".rs")
            .to_owned();
        let code = code(&file);
        let edges = graph.entry(module.clone()).or_default();
        for (i, _) in code.match_indices("crate::") {
            let name: String = code[i + 7..]
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect();
            if !name.is_empty() && name != module {
                edges.insert(name);
            }
        }
        // `use crate::{a, b::c}` groups.
        for (i, _) in code.match_indices("crate::{") {
            let group = &code[i + 8..];
            let group = &group[..group.find('}').unwrap_or(group.len())];
            for part in group.split(',') {
                let name: String = part
                    .trim()
                    .chars()
                    .take_while(|c| c.is_alphanumeric() || *c == '_')
                    .collect();
                if !name.is_empty() && name != module {
                    edges.insert(name);
                }
            }
        }
    }
    // Any cycle, by depth-first search.
    fn visit(
        n: &str,
        graph: &BTreeMap<String, BTreeSet<String>>,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
        cycles: &mut Vec<String>,
    ) {
        if let Some(i) = path.iter().position(|p| p == n) {
            cycles.push(format!("{} -> {n}", path[i..].join(" -> ")));
            return;
        }
        if !done.insert(n.to_owned()) {
            return;
        }
        path.push(n.to_owned());
        for m in graph.get(n).into_iter().flatten() {
            visit(m, graph, path, done, cycles);
        }
        path.pop();
    }
    let mut cycles = Vec::new();
    let mut done = BTreeSet::new();
    for n in graph.keys() {
        visit(n, &graph, &mut Vec::new(), &mut done, &mut cycles);
    }
    assert!(
        cycles.is_empty(),
        "module circles in daemon/src:\n{}",
        cycles.join("\n")
    );
    // The checker sees edges at all.
    assert!(graph["pipeline"].contains("devices"), "{graph:?}");
}

/// "Every file says why it is shaped so": each source file of every crate starts with
/// `//!` module docs.
#[test]
fn every_source_file_starts_with_module_docs() {
    let mut missing = Vec::new();
    for dir in [
        "drivers/src",
        "sim/src",
        "recon/src",
        "daemon/src",
        "tests",
        "standins",
    ] {
        for file in rust_files(&root().join(dir)) {
            let text = std::fs::read_to_string(&file).unwrap();
            if !text.trim_start().starts_with("//!") {
                missing.push(file.display().to_string());
            }
        }
    }
    assert!(
        missing.is_empty(),
        "no `//!` module docs:\n{}",
        missing.join("\n")
    );
}

/// "Test hooks": the release binary is built without the `test-hooks` feature, which
/// alone compiles the fault-injection hooks and the fuzz entry points. Cargo resolves
/// the features of the default members (what `cargo build --release` and
/// `cargo run --release` build) without dev-dependencies; the daemon must have none.
#[test]
fn the_release_binary_has_no_test_hooks() {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let features = |extra: &[&str]| -> String {
        let out = std::process::Command::new(&cargo)
            .current_dir(root())
            .args(["tree", "--locked", "--offline", "--depth", "0", "-f", "{p} [{f}]"])
            .args(extra)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "cargo tree failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let text = String::from_utf8(out.stdout).unwrap();
        text.lines()
            .find(|l| l.starts_with("periscope-daemon "))
            .unwrap_or_else(|| panic!("no periscope-daemon in:\n{text}"))
            .to_owned()
    };
    let release = features(&["-e", "no-dev"]);
    assert!(
        !release.contains("test-hooks"),
        "the release build of the daemon has its test hooks: {release}"
    );
    // And the tests do get them (so the check above can tell the two apart).
    let tests = features(&["-p", "periscope-daemon"]);
    assert!(tests.contains("test-hooks"), "{tests}");
}
