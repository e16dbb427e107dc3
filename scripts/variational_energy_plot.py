#!/usr/bin/env python3
"""SVG plots of the energy error against time from bench/variational_cost.cpp's
`energy` CSVs (columns model,integrator,dt,step,t,rel_err,swing_err): one plot per
model, log10 of |E - E0| / (E0 - E_rest) against t, one line per integrator (no
third-party packages). Usage: variational_energy_plot.py OUT.svg CSV..."""
import csv
import math
import sys

COLORS = {"euler": "#d62728", "rk4": "#1f77b4", "variational": "#2ca02c"}
W, H, L, R, T, B = 640, 360, 70, 130, 30, 45


def main(out, files):
    series = {}
    model = dt = ""
    for f in files:
        for r in csv.DictReader(open(f)):
            model, dt = r["model"], r["dt"]
            e = float(r["swing_err"])
            series.setdefault(r["integrator"], []).append((float(r["t"]), e))
    pts = [p for s in series.values() for p in s if math.isfinite(p[1]) and p[1] > 0]
    tmax = max(p[0] for p in pts)
    lo = math.floor(math.log10(min(p[1] for p in pts)))
    hi = math.ceil(math.log10(max(p[1] for p in pts)))
    hi = max(hi, lo + 1)
    x = lambda t: L + (W - L - R) * t / tmax
    y = lambda e: T + (H - T - B) * (hi - math.log10(e)) / (hi - lo)
    s = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" font-family="sans-serif" font-size="11">',
         f'<rect width="{W}" height="{H}" fill="white"/>',
         f'<text x="{L}" y="18" font-size="13">{model}, dt = {dt}: |E - E0| / (E0 - E_rest)</text>',
         f'<rect x="{L}" y="{T}" width="{W - L - R}" height="{H - T - B}" fill="none" stroke="black"/>']
    for d in range(lo, hi + 1):
        s.append(f'<line x1="{L}" x2="{W - R}" y1="{y(10**d):.1f}" y2="{y(10**d):.1f}" stroke="#ddd"/>')
        s.append(f'<text x="{L - 6}" y="{y(10**d) + 4:.1f}" text-anchor="end">1e{d}</text>')
    for k in range(6):
        t = tmax * k / 5
        s.append(f'<text x="{x(t):.1f}" y="{H - B + 16}" text-anchor="middle">{t:g}</text>')
    s.append(f'<text x="{(L + W - R) / 2}" y="{H - 8}" text-anchor="middle">t (s)</text>')
    for n, (name, p) in enumerate(sorted(series.items())):
        c = COLORS.get(name, "black")
        fin = [(t, e) for t, e in p if math.isfinite(e) and e > 0]
        if fin:
            d = " ".join(f"{x(t):.1f},{y(e):.1f}" for t, e in fin)
            s.append(f'<polyline points="{d}" fill="none" stroke="{c}" stroke-width="1.5"/>')
        note = "" if len(fin) == len(p) else " (diverged)"
        s.append(f'<line x1="{W - R + 10}" x2="{W - R + 30}" y1="{T + 14 + 18 * n}" y2="{T + 14 + 18 * n}" stroke="{c}" stroke-width="2"/>')
        s.append(f'<text x="{W - R + 35}" y="{T + 18 + 18 * n}">{name}{note}</text>')
    s.append("</svg>")
    open(out, "w").write("\n".join(s) + "\n")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
