#!/usr/bin/env python3
"""IoU against pairs measured, for the adaptive, uniform and random orders.

Replays captures with `periscope recon --adaptive-replay ORDER` at several budgets
(fractions of each capture's pairs), scores each volume with the validation scorer
(Otsu IoU and depth MAE against the scene's truth), and writes a CSV and a plot
(the mean over the seeds, with their range). The default sweep (6 captures, 3
budgets, 3 orders, 6 seeds: 360 runs of 5-15 s) takes about an hour on two cores.
Six seeds, because three misled: at an eighth of a noisy capture the random order's
mean moved by 0.04 with seeds 3-5 (docs/adaptive.md, "Measured").

    python3 tools/adaptive-curve.py                           # the validation captures
    python3 tools/adaptive-curve.py --scenes DIR --filter conf --fractions 0.125 0.25
    python3 tools/adaptive-curve.py --plot-only               # redraw from the CSV

Run it from the project root after `cargo build --release`. Each scene directory holds
`capture*.hdf5`, `truth.json` (its `recommended_volume`) and what `score.py` reads.
The full capture (fraction 1) is reconstructed once, without a replay.
"""
import argparse
import csv
import json
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
VALIDATION = os.path.join(ROOT, "..", "shared", "validation")


def volume_toml(truth, method):
    t = json.load(open(truth))["recommended_volume"]
    n = [t[a].get("n", len(t[a].get("centers", []))) for a in "xyz"]
    b = {a: t[a]["bounds"] for a in "xyz"}
    coords = {}
    for a, k in zip("xyz", n):
        lo, hi = b[a]
        h = (hi - lo) / k / 2
        coords[a] = {"min_center": lo + h, "max_center": hi - h, "n": k}
    text = f'method = "{method}"\n[volume]\nx = {b["x"]}\ny = {b["y"]}\nz = {b["z"]}\nshape = {n}\n'
    return text, coords


def pairs_of(log):
    for line in open(log):
        if line.startswith("reconstructed "):
            return int(line.split()[1])
    raise RuntimeError(f"no 'reconstructed N pairs' line in {log}")


def run(args):
    rows = []
    scenes = sorted(d for d in os.listdir(args.scenes) if os.path.isdir(os.path.join(args.scenes, d)))
    for scene in scenes:
        sd = os.path.join(args.scenes, scene)
        for cap in sorted(f for f in os.listdir(sd) if f.startswith("capture") and f.endswith(".hdf5")):
            name = scene + cap[len("capture"):-len(".hdf5")]
            if (args.filter and args.filter not in name) or name in args.skip:
                continue
            base, coords = volume_toml(os.path.join(sd, "truth.json"), args.method)
            jobs = [(s, "full", 1.0) for s in args.seeds] + [
                (s, o, f) for s in args.seeds for f in args.fractions for o in args.orders]
            total = None
            for seed, order, frac in jobs:
                out = os.path.join(args.out, name, f"{order}-{frac:g}-seed{seed}")
                os.makedirs(out, exist_ok=True)
                # The fit's seed, and the random order's.
                toml = base + f"[gtr]\nseed = {seed}\n" + args.extra
                if order != "full":
                    toml += f"[adaptive]\npairs = {max(1, round(frac * total))}\nseed = {seed}\n{args.adaptive}"
                open(os.path.join(out, "recon.toml"), "w").write(toml)
                json.dump(coords, open(os.path.join(out, "coords.json"), "w"))
                cmd = [args.bin, "recon", os.path.join(sd, cap), "--config", os.path.join(out, "recon.toml"),
                       "--out", out]
                if order != "full":
                    cmd += ["--adaptive-replay", order]
                t = time.time()
                with open(os.path.join(out, "log"), "w") as log:
                    rc = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT)
                secs = time.time() - t
                if rc != 0:
                    print(f"{name} {order} {frac}: recon failed, see {out}/log", file=sys.stderr)
                    continue
                score = subprocess.check_output(
                    [args.python, os.path.join(VALIDATION, "score.py"), os.path.join(out, "volume.npy"), sd,
                     "--axes", "zyx", "--coords", os.path.join(out, "coords.json")], text=True)
                d = json.loads(score.strip().splitlines()[-1])
                pairs = pairs_of(os.path.join(out, "log"))
                if order == "full":
                    total = pairs
                row = dict(capture=name, order=order, fraction=frac, seed=seed, pairs=pairs, of=total,
                           iou=d["iou_otsu"], depth_mae_m=d["depth_mae_m"], seconds=round(secs, 1))
                print(f"| {name:30s} | {order:8s} | {frac:6.4f} | {seed} | {pairs:5d} | {d['iou_otsu']:.3f} | "
                      f"{1000 * d['depth_mae_m']:6.1f} mm | {secs:5.1f} s |", flush=True)
                rows.append(row)
    with open(args.csv, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)
    return rows


def plot(rows, png):
    try:
        import matplotlib
    except ImportError:
        print("matplotlib is not installed: run this with a Python that has it (the validation "
              "runner's venv, /tmp/periscope-validation-venv/bin/python) to draw the plot; the CSV is written",
              file=sys.stderr)
        return
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    captures = list(dict.fromkeys(r["capture"] for r in rows))
    cols = min(4, len(captures))
    nrows = (len(captures) + cols - 1) // cols
    fig, axes = plt.subplots(nrows, cols, figsize=(3.6 * cols, 3.0 * nrows), squeeze=False)
    style = {"adaptive": ("C3", "o"), "uniform": ("C0", "s"), "random": ("C7", "^")}
    for ax, cap in zip(axes.flat, captures):
        rs = [r for r in rows if r["capture"] == cap]
        fulls = [float(r["iou"]) for r in rs if r["order"] == "full"]
        full = sum(fulls) / len(fulls) if fulls else None
        pairs = next((r["pairs"] for r in rs if r["order"] == "full"), "?")
        lo = 1.0
        for order, (c, m) in style.items():
            by = {}
            for r in rs:
                if r["order"] == order:
                    by.setdefault(float(r["fraction"]), []).append(float(r["iou"]))
            if full is not None and by:
                by[1.0] = fulls
            xs = sorted(by)
            if not xs:
                continue
            mean = [sum(by[x]) / len(by[x]) for x in xs]
            err = [[m_ - min(by[x]) for x, m_ in zip(xs, mean)], [max(by[x]) - m_ for x, m_ in zip(xs, mean)]]
            ax.errorbar(xs, mean, yerr=err, color=c, marker=m, label=order, capsize=3)
            lo = min(lo, min(min(v) for v in by.values()))
        if full is not None:
            ax.axhline(full, color="k", lw=0.6, ls=":")
        ax.set_xscale("log", base=2)
        ax.set_title(f"{cap} ({pairs} pairs)", fontsize=9)
        ax.set_xlabel("fraction of the pairs measured")
        ax.set_ylabel("IoU (Otsu)")
        ax.set_ylim(max(0.0, lo - 0.05), 1.0)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(captures):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    print(f"wrote {png}")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", default=os.path.join(VALIDATION, "scenes"))
    p.add_argument("--filter", default="")
    p.add_argument("--skip", nargs="*", default=["nonplanar_relay_xy3"],
                   help="captures left out (default: the curved relay's X_Y_3 copy, the same pairs as its T_Si file)")
    p.add_argument("--fractions", type=float, nargs="+", default=[0.125, 0.25, 0.5])
    p.add_argument("--orders", nargs="+", default=["adaptive", "uniform", "random"])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5], help="fit (and random order) seeds")
    p.add_argument("--method", default="gtr")
    p.add_argument("--extra", default="", help="more RECON.toml text (before [adaptive])")
    p.add_argument("--adaptive", default="", help="more keys of the [adaptive] table (e.g. 'explore = 0.5')")
    p.add_argument("--bin", default=os.path.join(ROOT, "target", "release", "periscope"))
    p.add_argument("--python", default=os.environ.get("VALIDATION_PYTHON", "/tmp/periscope-validation-venv/bin/python"))
    p.add_argument("--out", default="/tmp/adaptive-curve")
    p.add_argument("--csv", default=os.path.join(ROOT, "target", "adaptive-curve.csv"))
    p.add_argument("--png", default=os.path.join(ROOT, "docs", "img", "adaptive-curve.png"))
    p.add_argument("--plot-only", action="store_true")
    args = p.parse_args()
    for k in ("extra", "adaptive"):
        v = getattr(args, k)
        if v and not v.endswith("\n"):
            setattr(args, k, v + "\n")
    rows = list(csv.DictReader(open(args.csv))) if args.plot_only else run(args)
    plot(rows, args.png)


if __name__ == "__main__":
    main()
