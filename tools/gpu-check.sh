#!/usr/bin/env bash
# The checks of the GPU path (docs/gpu.md, "How it is checked") on a machine with a
# hardware GPU, with the adapter required: the CPU/GPU agreement tests, every
# independent render's assertions with `device = "auto"`, and the GPU benchmarks.
#
#   tools/gpu-check.sh [OUT]          # build (release) and run here; logs in OUT
#                                     # (default target/gpu-check)
#   tools/gpu-check.sh pack TARBALL   # build and pack the binaries, for a GPU machine
#                                     # without a Rust toolchain
#   tools/gpu-check.sh run TARBALL [OUT]   # there: run the packed binaries
#
# Run it from the repository root. `run` needs the checkout at the path it was
# built in (the tests find their data through it; a symbolic link will do). Each
# section is bounded by `timeout`; SECTIONS (default "tests ytal bench") picks them.
# A headless NVIDIA machine needs the Vulkan loader and GLVND (Debian's libvulkan1,
# libglvnd0, libglx0): docs/gpu.md, "On a hardware GPU".
set -uo pipefail
[ -f Cargo.toml ] || { echo "run this from the repository root" >&2; exit 2; }

# The test and bench executables the checks run, built in release.
build() {
  local json
  json=$(mktemp)
  {
    cargo test --release --locked --no-run -p periscope-recon --lib --test gradient_check --test training \
      --message-format=json
    cargo test --release --locked --no-run -p periscope-tests --test gpu --test ytal --message-format=json
    cargo bench --locked --no-run -p periscope-recon --bench solvers --bench gtr --message-format=json
  } >"$json" || { rm -f "$json"; echo "the build failed" >&2; exit 1; }
  # name<TAB>path for each executable: unit_<crate>, test_<name>, bench_<name>, and
  # the tests' own build of the binary (periscope-e2e).
  python3 - "$json" <<'PY'
import json, sys
for line in open(sys.argv[1]):
    try:
        m = json.loads(line)
    except ValueError:
        continue
    if m.get("reason") != "compiler-artifact" or not m.get("executable"):
        continue
    t = m["target"]
    kind = t["kind"][0]
    if kind == "bin" and not m["profile"]["test"]:
        name = t["name"]
    elif kind == "lib":
        name = "unit_" + t["name"]
    else:
        name = kind + "_" + t["name"]
    print(f"{name}\t{m['executable']}")
PY
  rm -f "$json"
}

# Copies the executables into $1 under their short names.
collect() {
  mkdir -p "$1"
  build | while IFS=$'\t' read -r name path; do cp "$path" "$1/$name"; done
  [ -x "$1/periscope-e2e" ] || { echo "periscope-e2e was not built" >&2; exit 1; }
}

# Runs the sections with the executables in $1, logs into $2.
checks() {
  local bin=$1 out=$2 t0 rc
  mkdir -p "$out"
  out=$(cd "$out" && pwd)
  export PERISCOPE_BIN=$bin/periscope-e2e
  t0=$(date +%s)
  if command -v nvidia-smi >/dev/null; then
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv >"$out/gpu.txt" 2>&1
  fi
  for section in ${SECTIONS:-tests ytal bench}; do
    case $section in
      tests)
        # The adapter is required: a missing one fails instead of skipping.
        (
          export PERISCOPE_REQUIRE_GPU=1
          cd recon &&
            timeout 300 "$bin/unit_periscope_recon" gpu --nocapture --test-threads 1 &&
            timeout 300 "$bin/unit_periscope_recon" solver::fbp --nocapture &&
            timeout 300 "$bin/test_gradient_check" gpu --nocapture --test-threads 1 &&
            timeout 300 "$bin/test_training" gpu --nocapture --test-threads 1 &&
            cd ../tests && timeout 300 "$bin/test_gpu" --nocapture
        ) >"$out/tests.log" 2>&1
        rc=$?
        ;;
      ytal)
        # `device = "auto"`: a hardware adapter takes the fit, the synthesis and FBP.
        (cd tests && timeout 600 "$bin/test_ytal" --nocapture) >"$out/ytal.log" 2>&1
        rc=$?
        ;;
      bench)
        (cd recon && timeout 600 "$bin/bench_solvers" --bench _gpu && timeout 600 "$bin/bench_gtr" --bench gpu) \
          >"$out/bench.log" 2>&1
        rc=$?
        ;;
      *)
        echo "unknown section $section (tests, ytal, bench)" >&2
        exit 2
        ;;
    esac
    echo "$section: exit $rc after $(($(date +%s) - t0)) s; $out/$section.log"
    grep -hE "^test result|FAILED|panicked|SKIPPED|relative L2|time:" "$out/$section.log" | head -40
  done
}

case ${1:-} in
  pack)
    [ -n "${2:-}" ] || { echo "usage: tools/gpu-check.sh pack TARBALL" >&2; exit 2; }
    dir=$(mktemp -d)
    collect "$dir"
    strip "$dir"/* 2>/dev/null
    printf '%s\n' "$(pwd)" >"$dir/built-in"
    tar -cJf "$2" -C "$dir" .
    rm -rf "$dir"
    echo "packed into $2 (built in $(pwd))"
    ;;
  run)
    [ -n "${2:-}" ] || { echo "usage: tools/gpu-check.sh run TARBALL [OUT]" >&2; exit 2; }
    dir=$(mktemp -d)
    tar -xJf "$2" -C "$dir" || exit 1
    built=$(cat "$dir/built-in")
    if [ ! -d "$built/tests/data" ]; then
      echo "the binaries were built in $built, which is not here: the tests read their data from there" \
        "(link this checkout to that path)" >&2
      exit 2
    fi
    checks "$dir" "${3:-target/gpu-check}"
    ;;
  *)
    dir=target/gpu-check-bin
    rm -rf "$dir"
    collect "$dir"
    checks "$(cd "$dir" && pwd)" "${1:-target/gpu-check}"
    ;;
esac
