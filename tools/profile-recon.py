#!/usr/bin/env python3
"""Where a `periscope recon` run spends its CPU time, by inlined function.

The hot loops run inside `recon::simd::dispatch`, so a plain `perf report` puts
nearly every sample in one of a few functions all named
`pulp::x86::v3::V3::vectorize::imp`, and cannot tell the forward pass from the
backward pass. This script builds `periscope` with line tables (into
target/profiling, so the release build is left alone), records the run with
`perf record`, and resolves every sampled address with `addr2line --inlines`, so
each sample counts once towards every function inlined at that address.

    python3 tools/profile-recon.py CAPTURE CONFIG [--threads N] [--top N]

CAPTURE and CONFIG are what `periscope recon` takes (a capture file and a
RECON.toml). Needs `perf` (linux-perf) and `addr2line` (binutils). Prints the
shares of the samples that fell in the periscope binary: inclusive by function,
then by innermost source line, then a few named parts of a 3D-GTR fit.
"""
import argparse
import collections
import os
import re
import shutil
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# Named parts of a fit: a sample counts towards a part when one of its inlined
# frames' function names contains the key (first match wins, in this order).
PARTS = [
    ("virtual confocal synthesis", ["RenderGroup"]),
    ("final FBP", ["GridRows", "fbp::"]),
    ("initial backprojection", ["DensityChunk"]),
    ("backward pass: per-bin sums (series and table)", ["sums<"]),
    ("backward pass: geometry and chain rule", ["backward_group<", "BackwardChunk"]),
    ("forward pass: per-bin adds (series and table)", ["accumulate_with<", "accumulate_keeping<"]),
    ("forward pass: geometry and pulses", ["evaluate_group_into<", "ForwardChunk"]),
    ("parameter maps (refresh)", ["MapRange"]),
    ("rotation chain rule (chain_with)", ["chain_with"]),
    ("AdamW update", ["AdamChunk", "step_averaged"]),
]

# The dispatch's own frames, around every hot loop: left out of the by-function list.
WRAPPERS = ("call<", "with_simd<", "imp<", "imp_fastcall<", "pulp::x86::v3::V3::vectorize")


def die(msg):
    print(f"profile-recon: {msg}", file=sys.stderr)
    sys.exit(2)


def need(tool, package):
    if shutil.which(tool) is None:
        die(f"`{tool}` is not installed; install {package} (apt-get install {package}) and run again")


def build():
    env = dict(os.environ, CARGO_PROFILE_RELEASE_DEBUG="line-tables-only")
    target = os.path.join(ROOT, "target", "profiling")
    subprocess.run(
        ["cargo", "build", "--release", "--locked", "-q", "-p", "periscope-daemon", "--target-dir", target],
        cwd=ROOT,
        env=env,
        check=True,
    )
    return os.path.join(target, "release", "periscope")


def load_segments(binary):
    """(p_offset, p_vaddr, p_filesz) of each LOAD segment."""
    out = subprocess.run(["readelf", "-lW", binary], capture_output=True, text=True, check=True).stdout
    segs = []
    for line in out.splitlines():
        f = line.split()
        if f and f[0] == "LOAD":
            segs.append((int(f[1], 16), int(f[2], 16), int(f[4], 16)))
    return segs


def mappings(data, binary):
    """(start, end, pgoff) of the binary's executable mappings in the recording."""
    out = subprocess.run(
        ["perf", "script", "-i", data, "--show-mmap-events", "-F", "ip"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    found = []
    pat = re.compile(r"\[(0x[0-9a-f]+)\((0x[0-9a-f]+)\) @ (0x[0-9a-f]+|0)[ \]].*?r-xp (\S+)")
    for line in out.splitlines():
        if "MMAP" not in line:
            continue
        m = pat.search(line)
        if m and os.path.realpath(m.group(4)) == os.path.realpath(binary):
            start, size, pgoff = (int(m.group(i), 16) for i in (1, 2, 3))
            found.append((start, start + size, pgoff))
    return found


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture")
    ap.add_argument("config")
    ap.add_argument("--threads", type=int, default=0, help="RAYON_NUM_THREADS (0: all cores)")
    ap.add_argument("--top", type=int, default=30)
    args = ap.parse_args()
    for path, what in ((args.capture, "capture"), (args.config, "config")):
        if not os.path.isfile(path):
            die(f"{what} file {path!r} does not exist")
    need("perf", "linux-perf")
    need("addr2line", "binutils")
    need("readelf", "binutils")

    binary = build()
    work = tempfile.mkdtemp(prefix="profile-recon-")
    data = os.path.join(work, "perf.data")
    env = dict(os.environ)
    if args.threads:
        env["RAYON_NUM_THREADS"] = str(args.threads)
    with open(os.path.join(work, "recon.log"), "w") as log:
        run = subprocess.run(
            ["perf", "record", "-F", "2000", "-o", data, "--", binary, "recon", args.capture,
             "--config", args.config, "--out", os.path.join(work, "out")],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=env,
        )
    if run.returncode != 0:
        die(f"the recorded run failed (exit {run.returncode}); its output is in {work}/recon.log")

    maps = mappings(data, binary)
    if not maps:
        die(f"no executable mapping of {binary} in the recording ({data})")
    segs = load_segments(binary)

    def to_vaddr(ip):
        for start, end, pgoff in maps:
            if start <= ip < end:
                off = ip - start + pgoff
                for p_off, p_vaddr, p_size in segs:
                    if p_off - 0x1000 <= off < p_off + p_size:
                        return off - p_off + p_vaddr
        return None

    ips = subprocess.run(["perf", "script", "-i", data, "-F", "ip"], capture_output=True, text=True,
                         check=True).stdout.split()
    counts = collections.Counter()
    for ip in ips:
        v = to_vaddr(int(ip, 16))
        if v is not None:
            counts[v] += 1
    total = sum(counts.values())
    if total == 0:
        die("no samples fell in the periscope binary")

    addrs = list(counts)
    frames = {}
    for i in range(0, len(addrs), 5000):
        out = subprocess.run(
            ["addr2line", "-a", "-i", "-f", "-C", "-e", binary] + [hex(a) for a in addrs[i:i + 5000]],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.splitlines()
        cur, j = None, 0
        while j < len(out):
            if out[j].startswith("0x"):
                cur = int(out[j], 16)
                frames[cur] = []
                j += 1
            else:
                frames[cur].append((out[j], out[j + 1] if j + 1 < len(out) else "??"))
                j += 2

    inclusive, innermost, parts = collections.Counter(), collections.Counter(), collections.Counter()
    for a, n in counts.items():
        fr = frames.get(a, [])
        if fr:
            innermost[fr[0][1].split(" ")[0].replace(ROOT + "/", "")] += n
        for name in {f for f, _ in fr}:
            if not name.startswith(WRAPPERS):
                inclusive[name] += n
        names = [f for f, _ in fr]
        for label, keys in PARTS:
            if any(k in f for f in names for k in keys):
                parts[label] += n
                break

    print(f"{total} samples in {binary} ({len(ips)} recorded); shares of those:")
    print("\nby function, inclusive of what is inlined into it (the dispatch's wrappers left out):")
    for name, n in inclusive.most_common(args.top):
        print(f"  {100 * n / total:5.1f} %  {name[:140]}")
    print("\nby innermost source line:")
    for loc, n in innermost.most_common(args.top):
        print(f"  {100 * n / total:5.1f} %  {loc}")
    print("\nparts of a 3D-GTR fit (a sample counts once, towards the first part that names it):")
    for label, _ in PARTS:
        print(f"  {100 * parts[label] / total:5.1f} %  {label}")
    print(f"\nrecording and run output kept in {work}")


if __name__ == "__main__":
    main()
