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
  - docs/forward-dynamics/hybrid-timeline.png from the hybrid's timeline CSV:
    busy intervals, one lane per host thread (its walks, reductions, the combine)
    and one for the device (velocities, each group's walks between CUDA events
    recorded right before and after the kernel, passes 2-3), a panel per precision.
    The CSV is what scripts/gpu_check.sh writes (hybrid-timeline-rope1e6.csv, columns
    precision,lane,event,c_lo,c_hi,start_ms,end_ms); the older format (event,start_ms,
    end_ms: one host thread, each device bar from one group's end to the next, so not
    busy intervals) is drawn as it is, and its title says so.
Plots need matplotlib; without it only the table and the CSV are written.

Usage: chain_fd_report.py [--results bench/results/h100.csv]
                          [--timeline bench/results/h100-hybrid-timeline-rope1e6-float.csv]
                          [--doc docs/forward-dynamics.md] [--timeline-only]
  --timeline-only: draw the timeline figure only (no table, no rope-fd plot).
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
    ap.add_argument('--timeline-only', action='store_true')
    a = ap.parse_args()
    outdir = os.path.join(os.path.dirname(a.doc), 'forward-dynamics')
    if a.timeline_only:
        draw_timeline(a.timeline, outdir)
        return

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
        draw_timeline(a.timeline, outdir)
    print('chain_fd_report.py: wrote', a.doc, 'and', outdir)


COLORS = {'gpu velocities': 'tab:gray', 'gpu walk': 'tab:blue', 'gpu finish': 'tab:green',
          'cpu walk': 'tab:orange', 'cpu reduce': 'tab:purple', 'cpu combine': 'tab:red'}


def draw_timeline(path, outdir):
    """docs/forward-dynamics/hybrid-timeline.png from a timeline CSV (either format)."""
    try:
        import matplotlib
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt
        from matplotlib.patches import Patch
    except ImportError:
        print('chain_fd_report.py: matplotlib missing: no timeline figure')
        return
    ev = list(csv.DictReader(open(path)))
    if not ev:
        sys.exit('chain_fd_report.py: no events in ' + path)
    os.makedirs(outdir, exist_ok=True)
    if 'lane' not in ev[0]:  # the older format
        fig, ax = plt.subplots(figsize=(12, 3))
        for e in ev:
            lane = 1 if e['event'].startswith('cpu') else 0
            ax.barh(lane, float(e['end_ms']) - float(e['start_ms']), left=float(e['start_ms']),
                    color='tab:orange' if lane else 'tab:blue', edgecolor='k', linewidth=0.3)
        ax.set_yticks([0, 1])
        ax.set_yticklabels(['GPU (velocities, group walks, rest)', 'CPU (articulated inertias, per group)'])
        ax.set_title('older timeline format: each GPU bar runs from one group\'s end to the next (not busy intervals)',
                     fontsize=9)
    else:
        precisions = sorted({e['precision'] for e in ev}, key=lambda p: p != 'float')
        fig, axes = plt.subplots(len(precisions), 1, figsize=(12, 1.2 + 0.9 * len(precisions) * 4), squeeze=False)
        for ax, p in zip(axes[:, 0], precisions):
            rows = [e for e in ev if e['precision'] == p]
            cpu = sorted({e['lane'] for e in rows if e['lane'] != 'gpu'}, key=lambda l: int(l[3:]))
            lanes = ['gpu'] + cpu
            for e in rows:
                y = lanes.index(e['lane'])
                s0, s1 = float(e['start_ms']), float(e['end_ms'])
                ax.barh(y, s1 - s0, left=s0, height=0.8, color=COLORS.get(e['event'], 'k'), edgecolor='k',
                        linewidth=0.2)
            busy = sum(float(e['end_ms']) - float(e['start_ms']) for e in rows if e['event'] == 'gpu walk')
            end = max(float(e['end_ms']) for e in rows)
            host_end = max([float(e['end_ms']) for e in rows if e['lane'] != 'gpu'] or [0])
            ax.set_yticks(range(len(lanes)))
            ax.set_yticklabels(['GPU'] + ['CPU thread %s' % l[3:] for l in cpu], fontsize=7)
            ax.set_title('%s: host part ends %.2f ms, call %.2f ms; GPU walks busy %.2f ms in total' %
                         (p, host_end, end, busy), fontsize=9)
            ax.set_xlabel('ms (host: from the call\'s start; GPU: from its first event)')
        axes[0, 0].legend(handles=[Patch(color=c, label=k) for k, c in COLORS.items()], fontsize=7, ncol=6,
                          loc='upper right')
    fig.tight_layout()
    fig.savefig(os.path.join(outdir, 'hybrid-timeline.png'), dpi=110)
    print('chain_fd_report.py: wrote', os.path.join(outdir, 'hybrid-timeline.png'))


if __name__ == '__main__':
    main()
