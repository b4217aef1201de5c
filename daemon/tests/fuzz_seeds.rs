//! Replays the fuzz targets' committed seeds (`fuzz/corpus/*/seed-*`, past crashes
//! among them as `seed-regression-*`) through the same entry points `cargo fuzz` runs,
//! so every `cargo test` checks them. Fuzzing itself (millions of generated inputs)
//! needs cargo-fuzz and runs in `.ci/fuzz`; this test says so when it runs.
use std::path::Path;

use periscope_daemon::fuzz::TARGETS;

#[test]
fn every_committed_seed_passes_its_target() {
    let corpus = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/corpus");
    let mut total = 0;
    for (name, target) in TARGETS {
        let dir = corpus.join(name);
        let mut seeds: Vec<_> = std::fs::read_dir(&dir)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .map(|e| e.unwrap().path())
            .filter(|p| p.file_name().unwrap().to_string_lossy().starts_with("seed-"))
            .collect();
        seeds.sort();
        assert!(
            !seeds.is_empty(),
            "target {name} has no committed seed in {}",
            dir.display()
        );
        for seed in &seeds {
            let data = std::fs::read(seed).unwrap();
            target(&data);
        }
        total += seeds.len();
    }
    // Not `eprintln!`, which libtest hides from a test that passes.
    use std::io::Write;
    let _ = writeln!(
        std::io::stderr(),
        "replayed {total} committed fuzz seeds over {} targets; fuzzing itself runs in .ci/fuzz \
         (cargo-fuzz), not in cargo test",
        TARGETS.len()
    );
}
