#!/usr/bin/env python3
"""The roofline numbers of docs/benchmarks.md ("Roofline per kernel family"): for each
kernel family, bytes and instructions per evaluation, the measured evaluations per
second, and from them the achieved DRAM bandwidth, warp-instruction issue rate and
FP32/FP64 rate against the GPU's peaks.

Inputs (committed):
  bench/results/sass-static-sm90.csv   static SASS counts (scripts/sass_static_counts.py)
  bench/results/zaxis-h100.csv, h100.csv, general-path-levels-h200.csv, dfd-cuda-h200.csv
Bytes per evaluation are counted here from each kernel's inputs, outputs and scratch
(the formulas are in ENTRIES, explained in docs/benchmarks.md). Instructions per
evaluation are estimates from STATIC counts: unrolled kernels count every static
instruction once (an upper bound: untaken branches are included), rolled ones count a
loop body once per body (or link) it walks. Nothing here was measured with a profiler.

usage: python3 scripts/roofline_numbers.py     (prints a markdown table)
"""
import csv
import os
import re

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RES = os.path.join(ROOT, "bench", "results")

# Peaks (NVIDIA's H100 SXM5 and H200 SXM datasheets; both 132 SMs at a 1.98 GHz boost clock):
# HBM3 3.35 TB/s (H100), HBM3e 4.8 TB/s (H200); FP32 67 TFLOP/s and FP64 34 TFLOP/s (non-tensor)
# on both; issue: 4 warp schedulers per SM, one warp instruction each per clock.
PEAK = {
    "H100": dict(bw=3.35e12, fp32=67e12, fp64=34e12),
    "H200": dict(bw=4.8e12, fp32=67e12, fp64=34e12),
}
ISSUE = 132 * 4 * 1.98e9  # warp instructions per second, either GPU

LAST_SOURCE = [""]
STATIC = list(csv.DictReader(open(os.path.join(RES, "sass-static-sm90.csv"))))


def kernel(pattern):
    rows = [r for r in STATIC if re.search(pattern, r["kernel"])]
    assert len(rows) == 1, (pattern, len(rows))
    r = rows[0]
    r["loop_sizes"] = [int(x.split(":")[1]) for x in r["loops"].split()] if r["loops"] else []
    return r


def measured(name, **match):
    """seconds_per_call and instances of the one row of results file `name` matching `match`."""
    with open(os.path.join(RES, name)) as f:
        lines = [l for l in f if not l.startswith("#")]
    rows = [r for r in csv.DictReader(lines) if all(r.get(k) == v for k, v in match.items())]
    assert len(rows) == 1, (name, match, len(rows))
    r = rows[0]
    LAST_SOURCE[0] = name
    if "seconds_zaxis" in r:  # zaxis-h100.csv: the z-axis frames' time (the engines' kernels)
        return float(r["seconds_zaxis"]), int(r["instances"])
    return float(r["seconds_per_call"]), int(r["instances"])


class Entries(list):
    """Entries that remember the results file of the last measured() call."""
    def append(self, e):
        e.setdefault("src", LAST_SOURCE[0])
        super().append(e)


def entries():
    E = Entries()
    # -- thread per instance, iiwa (7 bodies, capacity 8), z-axis frames --------------------
    k = kernel(r"id_instances_kernelIfLi8ENS_10ZJointBodyIfEELb0")
    t, B = measured("zaxis-h100.csv", algo="id", precision="float", model="iiwa")
    E.append(dict(name="id, thread, iiwa float", dev="H100", t=t, evals=B, per="instance",
                  bytes=4 * 7 * 4,  # q, qd, qdd read, tau written: 4 x nv x 4 B
                  instr=int(k["instructions"]), instr_how="static, unrolled (upper bound)",
                  flops32=int(k["flops32"]), flops64=0))
    k = kernel(r"id_instances_kernelIdLi8ENS_10ZJointBodyIdEELb0")
    t, B = measured("zaxis-h100.csv", algo="id", precision="double", model="iiwa")
    E.append(dict(name="id, thread, iiwa double", dev="H100", t=t, evals=B, per="instance",
                  bytes=4 * 7 * 8, instr=int(k["instructions"]), instr_how="static, unrolled (upper bound)",
                  flops32=0, flops64=int(k["flops64"])))
    k = kernel(r"crba_instances_kernelIfLi8ELb0ENS_10ZJointBodyIfEELb0")
    t, B = measured("zaxis-h100.csv", algo="mass", precision="float", model="iiwa")
    E.append(dict(name="mass, crba_thread, iiwa float", dev="H100", t=t, evals=B, per="instance",
                  bytes=(7 + 7 * 7) * 4,  # q read, the full nv x nv M written
                  instr=int(k["instructions"]), instr_how="static, unrolled (upper bound)",
                  flops32=int(k["flops32"]), flops64=0))
    k = kernel(r"fd_instances_kernelIfLi8ELi0ENS_10ZJointBodyIfEELb0")
    L = k["loop_sizes"]  # the three passes' per-body loops
    outside = int(k["instructions"]) - sum(L)
    t, B = measured("zaxis-h100.csv", algo="aba", precision="float", model="iiwa")
    E.append(dict(name="fd, aba_thread (chain), iiwa float", dev="H100", t=t, evals=B, per="instance",
                  bytes=4 * 7 * 4 + 4,  # q, qd, tau read, qdd written, the failed-DoF int
                  instr=outside + 7 * sum(L), instr_how="%d outside + 7 x (%s)" % (outside, " + ".join(map(str, L))),
                  flops32=None, flops64=0))
    k = kernel(r"sim_fused_kernelIfLi8ELj2ELNS0_10IntegratorE0ELi0E")
    L = k["loop_sizes"]
    outside = int(k["instructions"]) - sum(L)
    t, B = measured("h100.csv", backend="cuda", algo="step", strategy="fused-aba:euler:gravity+damping", precision="float",
                    model="iiwa", instances="1000000")
    E.append(dict(name="step, fused-aba euler, iiwa float", dev="H100", t=t, evals=B, per="instance-step",
                  bytes=5 * 7 * 4,  # q, qd, tau read, q, qd written
                  instr=outside + 7 * sum(L), instr_how="%d outside + 7 x (%s)" % (outside, " + ".join(map(str, L))),
                  flops32=None, flops64=0))
    # -- link scans: inverse dynamics of rope:10^6, 10 instances and 1 ------------------------
    vr = kernel(r"velocity_runsIfLb0E")["loop_sizes"][0]
    vw = kernel(r"velocity_walkIfLb0E")["loop_sizes"][0]
    aw = kernel(r"acceleration_walkIfLb0ELb1E")["loop_sizes"]  # inner branch-children loop, outer per-link loop
    fw = kernel(r"force_walkIfLb0E")["loop_sizes"][0]
    per_link = vr + vw + (aw[1] - aw[0]) + fw  # a rope has no branch children: the inner loop never runs
    for B in ("10", "1"):
        t, _ = measured("h100.csv", backend="cuda", algo="id", strategy="scan-local", precision="float", model="rope:1000000",
                        instances=B)
        E.append(dict(name="id, link scans, rope:10^6 x %s float" % B, dev="H100", t=t, evals=int(B) * 10**6,
                      per="link-instance", bytes=(136, 216),
                      instr=per_link, instr_how="%d + %d + (%d - %d) + %d per link" % (vr, vw, aw[1], aw[0], fw),
                      flops32=None, flops64=None))
    # -- parallel chain FD, rope:10^6, one instance -----------------------------------------
    parts = [kernel(p)["loop_sizes"][-1] for p in (r"velocity_aggregate_kernelIfLb0", r"velocity_walk_kernelILb1EfLb0",
                                                   r"inertia_walk_kernelIfLb0", r"bias_walk_kernelIfLb0",
                                                   r"acceleration_walk_kernelIfLb0")]
    t, _ = measured("h100.csv", backend="cuda", algo="fd", strategy="parallel", precision="float", model="rope:1000000")
    E.append(dict(name="fd, parallel chain FD, rope:10^6 float", dev="H100", t=t, evals=10**6, per="link",
                  bytes=44 * 4,  # q, qd, tau, qdd; v, U, D, w, u written and read once: (4 + 2 x 20) x 4 B
                  instr=sum(parts), instr_how=" + ".join(map(str, parts)) + " per link",
                  flops32=None, flops64=None))
    # -- general-path ABA (one thread per instance, interleaved scratch) ----------------------
    k = kernel(r"aba_general_kernelIfLb1")
    big = sorted(k["loop_sizes"])[-4:-1]  # the three per-body loops inside the per-instance loop
    for model, B, links in (("rope:100", "100000", 100), ("tree:1000:1", "10000", 1000), ("rope:100", "10000", 100)):
        t, _ = measured("general-path-levels-h200.csv", variant="thread", precision="float", model=model, instances=B)
        E.append(dict(name="fd, aba_general, %s x %s float" % (model, B), dev="H200", t=t, evals=int(B) * links,
                      per="body-instance",
                      bytes=(2 * 65 + 12) * 4,  # 65 scratch scalars written + read; q, qd, tau, qdd staged
                      instr=sum(big), instr_how=" + ".join(map(str, sorted(big))) + " per body (upper bound)",
                      flops32=None, flops64=None))
    # -- derivatives, iiwa float, 10^6 (the lean chain kernels, the default) -------------------
    k = kernel(r"id_derivatives_lean_kernelIfLi8")
    L = k["loop_sizes"]  # forward, backward, inner pair loop, forward-with-pairs
    outside = int(k["instructions"]) - (L[0] + L[1] + L[3])
    t, B = measured("dfd-cuda-h200.csv", variant="lean", algo="did", strategy="thread", precision="float")
    E.append(dict(name="did (lean), iiwa float", dev="H200", t=t, evals=B, per="instance",
                  bytes=(3 * 49 + 3 * 7) * 4,  # q, qd, qdd read; dtau/dq, dtau/dqd, M written
                  instr=outside + 7 * (L[0] + L[1] + L[3] - L[2]) + 28 * L[2],
                  instr_how="%d outside + 7 x (%d + %d + %d - %d) + 28 pairs x %d" % (
                      outside, L[0], L[1], L[3], L[2], L[2]),
                  flops32=None, flops64=None))
    t, B = measured("dfd-cuda-h200.csv", variant="lean", algo="dfd", strategy="thread", precision="float")
    E.append(dict(name="dfd (lean), iiwa float", dev="H200", t=t, evals=B, per="instance",
                  # kernel 1: q, qd, tau in, qdd + failed out; kernel 2: q, qd, qdd in, 3 nv^2 + failed out
                  bytes=(3 * 7 + 7) * 4 + 4 + (3 * 7 + 3 * 49) * 4 + 4,
                  instr=None, instr_how="not estimated (nested loops of the factor and solves)",
                  flops32=None, flops64=None))
    return E


def main():
    print("| kernel | GPU | per | bytes / eval | instructions / eval | evals/s (file) | DRAM | % peak | warp-instr issue | % peak |")
    print("|---|---|---|---:|---|---:|---:|---:|---:|---:|")
    for e in entries():
        rate = e["evals"] / e["t"]
        pk = PEAK[e["dev"]]
        b = e["bytes"] if isinstance(e["bytes"], tuple) else (e["bytes"], e["bytes"])
        bw = [x * rate for x in b]
        bw_s = "%.2f TB/s" % (bw[0] / 1e12) if b[0] == b[1] else "%.2f-%.2f TB/s" % (bw[0] / 1e12, bw[1] / 1e12)
        pct = "%.0f %%" % (100 * bw[0] / pk["bw"]) if b[0] == b[1] else "%.0f-%.0f %%" % (
            100 * bw[0] / pk["bw"], 100 * bw[1] / pk["bw"])
        b_s = "%d" % b[0] if b[0] == b[1] else "%d-%d" % b
        if e["instr"]:
            issue = e["instr"] * rate / 32
            i_s, ip = "%.2e /s" % issue, "%.0f %%" % (100 * issue / ISSUE)
            instr = "%d (%s)" % (e["instr"], e["instr_how"])
        else:
            i_s, ip, instr = "", "", e["instr_how"]
        print("| %s | %s | %s | %s | %s | %.3g (`%s`) | %s | %s | %s | %s |" % (
            e["name"], e["dev"], e["per"], b_s, instr, rate, e["src"], bw_s, pct, i_s, ip))
        if e.get("flops32"):
            print("|  | | FP32 (static FLOPs %d x rate) | | | | %.1f TFLOP/s | %.0f %% | | |" % (
                e["flops32"], e["flops32"] * rate / 1e12, 100 * e["flops32"] * rate / pk["fp32"]))
        if e.get("flops64"):
            print("|  | | FP64 (static FLOPs %d x rate) | | | | %.1f TFLOP/s | %.0f %% | | |" % (
                e["flops64"], e["flops64"] * rate / 1e12, 100 * e["flops64"] * rate / pk["fp64"]))
    print("\nissue peak: 132 SMs x 4 warp instructions per clock x 1.98 GHz = %.3g warp instructions/s" % ISSUE)


if __name__ == "__main__":
    main()
