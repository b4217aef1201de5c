#!/usr/bin/env python3
"""Where each method stops finding the target as light fails (issue 54, part 4;
docs/recon.md, "Low light").

From a validation scene's noise-free capture (the render's expected counts), draws
Poisson captures at a range of photon levels (the peak bin's expectation: the noisy
validation copy has 50) and ambient backgrounds (a flat rate per bin whose total is
0, 1 or 10 times the signal's; "0" is the noisy copy's 0.05 counts per bin), then
reconstructs each with `periscope recon` (gtr and fbp, the defaults otherwise, the
scene's recommended volume) and with y-tal 0.20's `tal.reconstruct.fbp` (the
baselines' call and wavelength), and scores each with the validation's score.py:
IoU (Otsu), depth MAE and each target's recall.

    python3 tools/low-light.py [SCENE] [OUT]     # y-tal's venv (tal, h5py, numpy)

Run from the project root after `cargo build --release -p periscope-daemon`.
Default SCENE confocal_sparse (a tilted letter and a 10 cm patch at 0.8 m), OUT
/tmp/low-light. Prints a markdown table.
"""
import json
import os
import subprocess
import sys

import h5py
import numpy as np

ROOT = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
VALIDATION = os.path.join(ROOT, "..", "shared", "validation")
SCENE = sys.argv[1] if len(sys.argv) > 1 else "confocal_sparse"
OUT = sys.argv[2] if len(sys.argv) > 2 else "/tmp/low-light"
SD = os.path.join(VALIDATION, "scenes", SCENE)
BIN = os.path.join(ROOT, "target", "release", "periscope")
PEAKS = [50, 15, 5, 1.5, 0.5]
BACKGROUNDS = [0, 1, 10]

truth = json.load(open(os.path.join(SD, "truth.json")))["recommended_volume"]
bounds = {a: truth[a]["bounds"] for a in "xyz"}
shape = [truth[a]["n"] for a in "xyz"]
centres = {}
for a, n in zip("xyz", shape):
    lo, hi = bounds[a]
    h = (hi - lo) / n / 2
    centres[a] = {"min_center": lo + h, "max_center": hi - h, "n": n}
baselines = json.load(open(os.path.join(SD, "baselines.json")))["methods"]
wl = baselines["fbp"]["params"]


def score(volume, axes, coords):
    out = subprocess.run(
        [sys.executable, os.path.join(VALIDATION, "score.py"), volume, SD, "--axes", axes,
         "--coords", coords, "--no-baselines"],
        check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def ytal_fbp(capture, out):
    import tal
    data = tal.io.read_capture(capture)
    axes = [np.linspace(c["min_center"], c["max_center"], c["n"]) for c in centres.values()]
    V = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    vol = tal.reconstruct.fbp.solve(data, wl["wl_mean"], wl["wl_sigma"], volume_xyz=V,
                                    camera_system=tal.enums.CameraSystem.DIRECT_LIGHT, progress=False)
    np.save(out, np.abs(vol).astype(np.float32))


os.makedirs(OUT, exist_ok=True)
coords = os.path.join(OUT, "coords.json")
json.dump(centres, open(coords, "w"))
rng = np.random.default_rng(54)
with h5py.File(os.path.join(SD, "capture.hdf5")) as f:
    H = f["H"][()].astype(np.float64)
    rows = []
    for peak in PEAKS:
        for ratio in BACKGROUNDS:
            name = f"peak{peak}_bg{ratio}"
            d = os.path.join(OUT, name)
            os.makedirs(d, exist_ok=True)
            signal = H * (peak / H.max())
            b = 0.05 if ratio == 0 else ratio * signal.sum() / signal.size
            counts = rng.poisson(signal + b).astype(np.float32)
            cap = os.path.join(d, "capture.hdf5")
            with h5py.File(cap, "w") as o:
                for k in f.keys():
                    if k == "H":
                        o.create_dataset("H", data=counts.reshape(f["H"].shape))
                    else:
                        f.copy(f[k], o, k)
            row = {"name": name, "peak": peak, "bg": ratio, "b": b,
                   "photons": float(signal.sum()), "bg_photons": float(b * signal.size)}
            for method in ["gtr", "fbp"]:
                md = os.path.join(d, method)
                os.makedirs(md, exist_ok=True)
                toml = os.path.join(md, "recon.toml")
                open(toml, "w").write(
                    f'method = "{method}"\n[volume]\nx = {bounds["x"]}\ny = {bounds["y"]}\nz = {bounds["z"]}\n'
                    f'shape = {shape}\n')
                r = subprocess.run([BIN, "recon", cap, "--config", toml, "--out", md],
                                   capture_output=True, text=True)
                row[method] = score(os.path.join(md, "volume.npy"), "zyx", coords) if r.returncode == 0 else None
            ytal = os.path.join(d, "ytal_fbp.npy")
            ytal_fbp(cap, ytal)
            row["ytal_fbp"] = score(ytal, "xyz", coords)
            rows.append(row)
            print(name, {m: (round(row[m]["iou_otsu"], 3) if row[m] else None) for m in ["gtr", "fbp", "ytal_fbp"]},
                  file=sys.stderr, flush=True)
json.dump(rows, open(os.path.join(OUT, "results.json"), "w"), indent=1)


def cell(s):
    if s is None:
        return "failed"
    t = s.get("targets", {})
    recall = "/".join(f'{v["recall_otsu"]:.2f}' for v in t.values())
    return f'{s["iou_otsu"]:.3f} ({s["depth_mae_m"] * 1e3:.0f} mm; {recall})'


print("| peak count | background / signal | photons (signal, background) | gtr | fbp | y-tal fbp |")
print("|---|---|---|---|---|---|")
for r in rows:
    bg = "0.05 per bin" if r["bg"] == 0 else f'{r["bg"]}×'
    print(f'| {r["peak"]} | {bg} | {r["photons"]:.3g}, {r["bg_photons"]:.3g} | {cell(r["gtr"])} | '
          f'{cell(r["fbp"])} | {cell(r["ytal_fbp"])} |')
