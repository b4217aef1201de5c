#!/usr/bin/env python3
"""Draws what `cargo bench -p periscope-daemon --bench scaling` measured.

    python3 tools/plot-scaling.py [target/scaling.csv] [docs/img/scaling.png]

Two panels: `periscope recon`'s time and its peak memory against the capture's pairs,
one line per method and volume edge n (log-log). Needs matplotlib (the validation
venv has it: ../shared/validation/run.sh installs it under /tmp).
"""
import csv
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main():
    src = sys.argv[1] if len(sys.argv) > 1 else "target/scaling.csv"
    dst = sys.argv[2] if len(sys.argv) > 2 else "docs/img/scaling.png"
    rows = list(csv.DictReader(open(src)))
    if not rows:
        sys.exit(f"{src} holds no measurements")
    series = {}
    for r in rows:
        key = (r["method"], int(r["n"]))
        series.setdefault(key, []).append((int(r["pairs"]), float(r["seconds"]), float(r["peak_mib"])))
    fig, (t_ax, m_ax) = plt.subplots(1, 2, figsize=(11, 4.2))
    styles = {"gtr": "-", "fbp": "--"}
    for (method, n), pts in sorted(series.items()):
        pts.sort()
        p = [x[0] for x in pts]
        label = f"{method}, {n}³"
        t_ax.plot(p, [x[1] for x in pts], styles.get(method, ":"), marker="o", label=label)
        m_ax.plot(p, [x[2] for x in pts], styles.get(method, ":"), marker="o", label=label)
    for ax, what in [(t_ax, "time, s (median)"), (m_ax, "peak memory, MiB")]:
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("pairs in the capture")
        ax.set_ylabel(what)
        ax.grid(True, which="both", alpha=0.3)
    t_ax.set_title("periscope recon, end to end")
    m_ax.set_title("peak resident memory")
    m_ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(dst, dpi=110)
    print(f"written: {dst}")


if __name__ == "__main__":
    main()
