#!/usr/bin/env python3
"""Time per call against links, per CUDA engine and instance count, with the links
at which `Auto` switches engines (docs/benchmarks.md, "Roofline and engine choice").

Reads committed measurements only:
  bench/results/h100.csv                     bench_cuda_id / _fd / _sweep (H100)
  bench/results/compare-h100.csv             scandyn's Auto rows of bench/compare (H100)
  bench/results/general-path-interleave-h200.csv, general-path-levels-h200.csv
                                             the general path, parallel, jsi_dense (H200)
Float32, device-resident rows (no `-host`), one point per (engine, model, instances).
The Auto rule drawn is choose_id_strategy / choose_fd_method (src/engine/engine.cpp):
a rule on the DoF count, not a table of measurements.

usage: .venv/bin/python scripts/engine_crossover_plot.py [--out docs/img/engine-crossover.png]
       [--table]   (also print the points plotted, as a markdown table)
"""
import argparse
import csv
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RES = os.path.join(ROOT, "bench", "results")


def read(name, device):
    """Rows of a results file (comment lines skipped), tagged with the device."""
    rows = []
    with open(os.path.join(RES, name)) as f:
        lines = [l for l in f if not l.startswith("#")]
    for r in csv.DictReader(lines):
        if r.get("library", "scandyn") != "scandyn" or r.get("note"):
            continue
        if r["backend"] != "cuda" or r["precision"] != "float" or not r["seconds_per_call"]:
            continue
        # general-path-levels: only the default variant (thread) and jsi; interleave: the default layout
        if r.get("variant") not in (None, "thread", "jsi"):
            continue
        if r.get("layout") not in (None, "scalars", "-"):
            continue
        r["device"] = device
        r["file"] = name
        rows.append(r)
    return rows


# engine label, colour: strategies as the result files name them
ENGINES = {
    "thread": ("id: thread per instance", "tab:blue"),
    "scan-local": ("id: link scans (IdScanPlan)", "tab:orange"),
    "aba_thread": ("fd: ABA, thread per instance", "tab:blue"),
    "jsi_thread": ("fd: JSI, thread per instance", "tab:cyan"),
    "parallel": ("fd: parallel chain FD (scans)", "tab:orange"),
    "hybrid": ("fd: hybrid (inertias on host)", "tab:brown"),
    "aba_general": ("fd: general-path ABA", "tab:green"),
    "jsi_dense": ("fd: dense JSI (cuSOLVER)", "tab:red"),
}
# instance counts drawn, and their marker
BATCHES = {1: "o", 100: "v", 10000: "s", 100000: "p", 1000000: "D", 10000000: "^"}


def points():
    rows = (read("h100.csv", "H100") + read("compare-h100.csv", "H100")
            + read("general-path-interleave-h200.csv", "H200") + read("general-path-levels-h200.csv", "H200"))
    pts = {}
    for r in rows:
        algo, strat = r["algo"], r["strategy"]
        if algo not in ("id", "fd") or strat not in ENGINES:
            continue
        # models of 1-DoF joints only: Auto sends multi-DoF models elsewhere whatever their size
        if r["model"].startswith("ballrope") or "floating" in r["model"]:
            continue
        B = int(r["instances"])
        links = int(r["links"])
        t = float(r["seconds_per_call"])
        key = (algo, strat, B, r["model"], r["device"])
        # the same configuration in two files (h100.csv and the compare run): keep the later run's
        # (compare-h100.csv is read after h100.csv), as bench/compare/merge.py does
        pts[key] = (links, t, r["file"])
    return pts


def sweep_batch(links, B):
    """True for the shape sweep's 'links x instances ~ 10^7' points (bench_cuda_sweep, h100.csv)."""
    return B > 1 and 0.9e7 <= links * B <= 1.1e7


def plot(pts, out):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    fig, axes = plt.subplots(1, 2, figsize=(15, 6.5), sharey=True)
    for ax, algo in zip(axes, ("id", "fd")):
        series = {}
        for (a, strat, B, model, dev), (links, t, f) in pts.items():
            if a != algo:
                continue
            b = "sweep" if f == "h100.csv" and sweep_batch(links, B) else B
            if b != "sweep" and b not in BATCHES:
                continue
            series.setdefault((strat, b, dev), []).append((links, t, model))
        for (strat, b, dev), p in sorted(series.items(), key=lambda kv: str(kv[0])):
            p.sort()
            label, colour = ENGINES[strat]
            marker = "*" if b == "sweep" else BATCHES[b]
            xs, ys = [x for x, _, _ in p], [y * 1e6 for _, y, _ in p]
            ax.plot(xs, ys, marker=marker, color=colour, linestyle="--" if b == "sweep" else "-",
                    markerfacecolor="none" if dev == "H200" else colour, markersize=8 if b == "sweep" else 6,
                    linewidth=1.2)
        # Auto's switches (src/engine/engine.cpp)
        if algo == "id":
            ax.axvline(64.5, color="k", linewidth=1)
            ax.text(0.98, 0.03, "Auto (choose_id_strategy): thread per instance for nv <= 64,\n"
                    "link scans beyond (solid line at 64)", transform=ax.transAxes, ha="right", va="bottom",
                    fontsize=8, bbox=dict(facecolor="white", edgecolor="none", alpha=0.8))
            ax.set_title("inverse dynamics, float (H100)")
        else:
            ax.axvline(64.5, color="k", linewidth=1)
            ax.axvline(128.5, color="k", linewidth=1, linestyle=":")
            ax.text(0.98, 0.03, "Auto (choose_fd_method): aba_thread for nv <= 64 (solid line);\n"
                    "beyond, general-path ABA for chains up to 128 (dotted line)\nand every tree, "
                    "parallel chain FD for longer chains", transform=ax.transAxes, ha="right", va="bottom",
                    fontsize=8, bbox=dict(facecolor="white", edgecolor="none", alpha=0.8))
            ax.set_title("forward dynamics, float (H100; hollow markers: H200)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("links (DoF)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("time per call (us), device-resident")
    handles = [Line2D([], [], color="tab:blue", label="thread per instance (id: thread; fd: aba_thread)"),
               Line2D([], [], color="tab:orange", label="scans over links (id: IdScanPlan; fd: parallel chain FD)")]
    handles += [Line2D([], [], color=c, label=l) for s, (l, c) in ENGINES.items()
                if s in ("jsi_thread", "aba_general", "jsi_dense", "hybrid")]
    handles += [Line2D([], [], color="gray", marker=m, linestyle="", label="%g instances" % b) for b, m in BATCHES.items()]
    handles.append(Line2D([], [], color="gray", marker="*", linestyle="--", label="links x instances ~ 10^7 (sweep)"))
    fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.13, 1, 1))
    fig.savefig(out, dpi=110)
    print("wrote", out)


def table(pts):
    print("| algo | engine | instances | model | links | time per call | device | file |")
    print("|---|---|---:|---|---:|---:|---|---|")
    for (a, strat, B, model, dev), (links, t, f) in sorted(pts.items(), key=lambda kv: (kv[0][0], kv[0][1], kv[0][2], kv[1][0])):
        if B not in BATCHES and not (f == "h100.csv" and sweep_batch(links, B)):
            continue
        print("| %s | %s | %d | %s | %d | %.4g us | %s | %s |" % (a, strat, B, model, links, t * 1e6, dev, f))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "img", "engine-crossover.png"))
    ap.add_argument("--table", action="store_true")
    a = ap.parse_args()
    p = points()
    if a.table:
        table(p)
    plot(p, a.out)
