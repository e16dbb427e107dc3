#!/usr/bin/env python3
"""The rope:N forward-dynamics study of docs/forward-dynamics.md, from bench_cuda_chain_fd.

Reads the rows of bench/results/<device>.csv whose algo is fd and model rope:N with
one instance (strategies parallel, parallel-host, hybrid, jsi on cuda; aba serial on
the GPU machine's host CPU), and writes
  - a Markdown table (time per call and max relative error against the double
    serial ABA, per strategy x precision x N) between the markers
    <!-- rope-fd-table --> and <!-- /rope-fd-table --> of the document;
  - docs/forward-dynamics/rope-fd.png (time and error against N) and the CSV
    behind it, rope-fd.csv;
  - docs/forward-dynamics/hybrid-timeline.png from the hybrid's timeline CSV
    (host groups of the articulated-inertia recursion against the device's walks).
Plots need matplotlib; without it only the table and the CSV are written.

Usage: chain_fd_report.py [--results bench/results/h100.csv]
                          [--timeline bench/results/h100-hybrid-timeline-rope1e6-float.csv]
                          [--doc docs/forward-dynamics.md]
"""
import argparse
import csv
import os
import re
import sys

BEGIN, END = '<!-- rope-fd-table -->', '<!-- /rope-fd-table -->'
STRATEGIES = [('parallel', 'cuda'), ('parallel-host', 'cuda'), ('hybrid', 'cuda'), ('jsi', 'cuda'), ('aba', 'serial')]


def fmt_time(s):
    if s < 1e-3:
        return '%.1f us' % (s * 1e6)
    if s < 1:
        return '%.2f ms' % (s * 1e3)
    return '%.2f s' % s


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    root = os.path.join(os.path.dirname(os.path.abspath(__file__)), '..')
    ap.add_argument('--results', default=os.path.join(root, 'bench/results/h100.csv'))
    ap.add_argument('--timeline', default=os.path.join(root, 'bench/results/h100-hybrid-timeline-rope1e6-float.csv'))
    ap.add_argument('--doc', default=os.path.join(root, 'docs/forward-dynamics.md'))
    a = ap.parse_args()

    rows = {}
    with open(a.results) as fh:
        for r in csv.DictReader(fh):
            m = re.fullmatch(r'rope:(\d+)', r['model'])
            if r['algo'] != 'fd' or not m or r['instances'] != '1':
                continue
            key = (r['strategy'], r['backend'], r['precision'], int(m.group(1)))
            if (r['strategy'], r['backend']) in STRATEGIES:
                rows[key] = (float(r['seconds_per_call']), float(r['max_rel_err']))
    if not rows:
        sys.exit('chain_fd_report.py: no fd rope:N rows in ' + a.results)
    lengths = sorted({k[3] for k in rows})

    # table: one line per N and precision, a (time, error) cell per strategy
    head = '| N | precision | ' + ' | '.join('%s (%s)' % s for s in STRATEGIES) + ' |'
    lines = [head, '|' + '---|' * (2 + len(STRATEGIES))]
    for n in lengths:
        for p in ('float', 'double'):
            cells = []
            for s, b in STRATEGIES:
                v = rows.get((s, b, p, n))
                cells.append('%s, err %.1e' % (fmt_time(v[0]), v[1]) if v else 'not run')
            lines.append('| %d | %s | %s |' % (n, p, ' | '.join(cells)))
    table = '\n'.join(lines)
    with open(a.doc) as fh:
        doc = fh.read()
    if BEGIN not in doc or END not in doc:
        sys.exit('chain_fd_report.py: %s lacks the markers %s %s' % (a.doc, BEGIN, END))
    doc = doc[:doc.index(BEGIN) + len(BEGIN)] + '\n' + table + '\n' + doc[doc.index(END):]
    with open(a.doc, 'w') as fh:
        fh.write(doc)

    outdir = os.path.join(os.path.dirname(a.doc), 'forward-dynamics')
    os.makedirs(outdir, exist_ok=True)
    with open(os.path.join(outdir, 'rope-fd.csv'), 'w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(['strategy', 'backend', 'precision', 'links', 'seconds_per_call', 'max_rel_err'])
        for k in sorted(rows):
            w.writerow(list(k) + list(rows[k]))
    try:
        import matplotlib
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt
    except ImportError:
        print('chain_fd_report.py: matplotlib missing: table and CSV only')
        return
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    for (s, b) in STRATEGIES:
        for p, style in (('float', '-o'), ('double', '--s')):
            pts = [(n, rows[(s, b, p, n)]) for n in lengths if (s, b, p, n) in rows]
            if not pts:
                continue
            label = '%s %s (%s)' % (s, p, b)
            ax[0].loglog([n for n, _ in pts], [v[0] for _, v in pts], style, label=label, ms=4)
            ax[1].loglog([n for n, _ in pts], [max(v[1], 1e-17) for _, v in pts], style, label=label, ms=4)
    ax[0].set_xlabel('rope links N')
    ax[0].set_ylabel('seconds per call (one instance)')
    ax[1].set_xlabel('rope links N')
    ax[1].set_ylabel('max relative error vs double serial ABA')
    ax[0].legend(fontsize=7)
    ax[0].grid(True, which='both', alpha=0.3)
    ax[1].grid(True, which='both', alpha=0.3)
    fig.tight_layout()
    fig.savefig(os.path.join(outdir, 'rope-fd.png'), dpi=110)
    if os.path.exists(a.timeline):
        ev = list(csv.DictReader(open(a.timeline)))
        fig, ax = plt.subplots(figsize=(12, 3))
        for e in ev:
            lane = 1 if e['event'].startswith('cpu') else 0
            ax.barh(lane, float(e['end_ms']) - float(e['start_ms']), left=float(e['start_ms']),
                    color='tab:orange' if lane else 'tab:blue', edgecolor='k', linewidth=0.3)
        ax.set_yticks([0, 1])
        ax.set_yticklabels(['GPU (velocities, group walks, rest)', 'CPU (articulated inertias, per group)'])
        ax.set_xlabel('ms from the start of the call')
        fig.tight_layout()
        fig.savefig(os.path.join(outdir, 'hybrid-timeline.png'), dpi=110)
    print('chain_fd_report.py: wrote', a.doc, 'and', outdir)


if __name__ == '__main__':
    main()
