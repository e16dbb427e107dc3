#!/usr/bin/env python3
"""Plots and tables of the side-by-side comparison from bench/results/compare-<device>.csv.

  plot.py bench/results/compare-<device>.csv [...] [--img docs/img] [--doc docs/benchmarks.md]

For each CSV and computation (id, bias, mass, fd): one PNG, docs/img/compare-<device>-<algo>.png,
with evaluations per second against batch size for the robots (one panel per robot) and time
per call against chain length for the ropes (one call, one instance). One line per library,
backend, strategy and precision. With --doc, the markdown tables replace what is between
`<!-- compare-<device> -->` and `<!-- /compare-<device> -->` in that file (appended at the end
if the markers are missing); without, they are printed.

Tables: for each model, computation and batch size, scandyn's time and each peer's, and the
ratio peer time / scandyn time (above 1: scandyn is faster) against the best row of each side
on the same backend kind (CPU: serial against serial, OpenMP against OpenMP; GPU: device-resident
rows only, float32), with the equality check's max error. Rows that record a failure or an
unavailable configuration are listed below the table with their note.
"""
import argparse
import csv
import os
import re
from collections import defaultdict

ALGO_NAMES = {'id': 'inverse dynamics (RNEA)', 'bias': 'bias forces h(q, qd)', 'mass': 'mass matrix (CRBA)',
              'fd': 'forward dynamics'}
ROBOTS = ('iiwa', 'hyq', 'atlas')


def read(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def device_of(path):
    return re.sub(r'^compare-|\.csv$', '', os.path.basename(path))


def label(r):
    lib = r['library']
    v = r['version']
    if lib == 'pinocchio' and 'headers' in v:
        lib += ' (headers)'
    s = r['strategy'].replace('-hdr', '')
    return '%s %s %s %s' % (lib, r['backend'], s, r['precision'])


def timed(rows):
    return [r for r in rows if r['seconds_per_call'] and not r['note']]


def plots(rows, device, img_dir):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    os.makedirs(img_dir, exist_ok=True)
    out = []
    for algo in ('id', 'bias', 'mass', 'fd'):
        rs = [r for r in timed(rows) if r['algo'] == algo]
        if not rs:
            continue
        robots = [m for m in ROBOTS if any(r['model'] == m for r in rs)]
        ropes = sorted({r['model'] for r in rs if r['model'].startswith('rope:') and r['instances'] == '1'},
                       key=lambda m: int(m.split(':')[1]))
        n = len(robots) + (1 if ropes else 0)
        all_labels = sorted({label(r) for r in rs})
        cmap = plt.get_cmap('tab10' if len(all_labels) <= 10 else 'tab20')
        color = {k: cmap(i % cmap.N) for i, k in enumerate(all_labels)}
        fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.8), squeeze=False)
        for ax, m in zip(axes[0], robots):
            lines = defaultdict(list)
            for r in rs:
                if r['model'] == m:
                    lines[label(r)].append((int(r['instances']), float(r['evals_per_second'])))
            for k in sorted(lines):
                pts = sorted(lines[k])
                ax.plot([p[0] for p in pts], [p[1] for p in pts], marker='o', ms=3, color=color[k],
                        ls='-' if k.startswith('scandyn') else '--', label=k)
            ax.set_xscale('log')
            ax.set_yscale('log')
            ax.set_xlabel('batch size (instances per call)')
            ax.set_ylabel('evaluations / s')
            ax.set_title('%s: %s' % (m, ALGO_NAMES[algo]), fontsize=9)
            ax.grid(True, which='both', alpha=0.3)
        if ropes:
            ax = axes[0][-1]
            lines = defaultdict(list)
            for r in rs:
                if r['model'] in ropes and r['instances'] == '1':
                    lines[label(r)].append((int(r['links']), float(r['seconds_per_call'])))
            for k in sorted(lines):
                pts = sorted(lines[k])
                ax.plot([p[0] for p in pts], [p[1] for p in pts], marker='o', ms=3, color=color[k],
                        ls='-' if k.startswith('scandyn') else '--', label=k)
            ax.set_xscale('log')
            ax.set_yscale('log')
            ax.set_xlabel('rope length (links), one instance')
            ax.set_ylabel('seconds per call')
            ax.set_title('ropes: %s' % ALGO_NAMES[algo], fontsize=9)
            ax.grid(True, which='both', alpha=0.3)
        handles, labels = [], []
        for ax in axes[0]:
            for h, l in zip(*ax.get_legend_handles_labels()):
                if l not in labels:
                    handles.append(h)
                    labels.append(l)
        fig.legend(handles, labels, loc='lower center', ncol=min(4, len(labels)), fontsize=7, frameon=False)
        fig.suptitle('%s — %s' % (device, ALGO_NAMES[algo]), fontsize=10)
        fig.tight_layout(rect=(0, 0.06 + 0.035 * ((len(labels) + 3) // 4), 1, 0.95))
        path = os.path.join(img_dir, 'compare-%s-%s.png' % (device, algo))
        fig.savefig(path, dpi=110)
        plt.close(fig)
        out.append(path)
    return out


def fmt_t(s):
    s = float(s)
    if s >= 1e-3:
        return '%.2f ms' % (s * 1e3)
    return '%.2f us' % (s * 1e6)


def fmt_e(s):
    return '%.1e' % float(s) if s not in ('', None) else '–'


def kind(r):
    return r['backend'] if r['backend'] in ('serial', 'openmp') else 'gpu'


def host_staged(r):
    return r['strategy'].endswith('-host')


def tables(rows, device):
    lines = []
    t = timed(rows)
    peers = sorted({r['library'] for r in rows if r['library'] != 'scandyn'})
    best = {}
    for r in t:
        if r['backend'] not in ('serial', 'openmp') and r['precision'] != 'float':
            continue
        key = (r['library'], r['model'], r['algo'], r['instances'], kind(r))
        old = best.get(key)
        # a device-resident row wins over a host-staged one (copies included) whatever the times
        if (old is None or (host_staged(old) and not host_staged(r)) or
                (host_staged(old) == host_staged(r) and float(r['seconds_per_call']) < float(old['seconds_per_call']))):
            best[key] = r
    configs = sorted({k[1:] for k in best}, key=lambda k: (
        ROBOTS.index(k[0]) if k[0] in ROBOTS else 10 + int(k[0].split(':')[1]) if k[0].startswith('rope:') else 99,
        ('id', 'bias', 'mass', 'fd').index(k[1]), int(k[2]), k[3]))
    head = '| model | computation | batch | backend | scandyn | ' + ' | '.join(
        '%s | ratio | check' % p for p in peers) + ' |'
    lines += [head, '|' + '---|' * (5 + 3 * len(peers))]
    for (m, a, b, kd) in configs:
        s = best.get(('scandyn', m, a, b, kd))
        cells = ['%s' % m, a, b, kd, (fmt_t(s['seconds_per_call']) + ' (%s)' % s['strategy']) if s else '–']
        any_peer = False
        for p in peers:
            r = best.get((p, m, a, b, kd))
            if r:
                any_peer = True
                ratio = float(r['seconds_per_call']) / float(s['seconds_per_call']) if s else None
                cells += ['%s (%s)' % (fmt_t(r['seconds_per_call']), r['strategy']),
                          '%.2f' % ratio if ratio else '–', fmt_e(r['check_max_err'])]
            else:
                cells += ['–', '–', '–']
        if any_peer or s:
            lines.append('| ' + ' | '.join(cells) + ' |')
    notes = defaultdict(set)
    measured = {(r['library'], r['model']) for r in rows if not r['note']}
    for r in rows:
        if r['note']:
            # a note without an algorithm covers the library on that model, except where a
            # later run of the same library measured some of it (other batch sizes, say)
            whole = '(in one run; the rows of another are in the table)' if (r['library'], r['model']) in measured else '(all)'
            what = '%s %s' % (r['model'], r['algo'] or whole)
            notes[(r['library'], re.sub(r'\d+(\.\d+)? s\b', 'N s', r['note']))].add(what)
    if notes:
        lines += ['', 'Not measured (from the rows\' `note` column):', '']
        for (lib, note), whats in sorted(notes.items()):
            w = sorted(whats)
            lines.append('- **%s**: %s — %s%s' % (lib, note, ', '.join(w[:6]), ' and %d more' % (len(w) - 6)
                                                   if len(w) > 6 else ''))
    versions = sorted({(r['library'], r['version']) for r in rows if r['version']})
    lines += ['', 'Versions: ' + '; '.join('%s' % v for _, v in versions) + '.']
    return '\n'.join(lines) + '\n'


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('csv', nargs='+')
    ap.add_argument('--img', default=os.path.join(os.path.dirname(__file__), '..', '..', 'docs', 'img'))
    ap.add_argument('--doc')
    ap.add_argument('--no-plots', action='store_true')
    args = ap.parse_args()
    for path in args.csv:
        rows = read(path)
        device = device_of(path)
        pngs = [] if args.no_plots else plots(rows, device, args.img)
        md = tables(rows, device)
        if pngs:
            rel = os.path.relpath(args.img, os.path.dirname(args.doc)) if args.doc else args.img
            md += '\n' + '\n'.join('![%s](%s)' % (os.path.basename(p)[:-4], os.path.join(rel, os.path.basename(p)))
                                   for p in pngs) + '\n'
        if args.doc:
            text = open(args.doc).read()
            a, b = '<!-- compare-%s -->' % device, '<!-- /compare-%s -->' % device
            block = '%s\n%s%s' % (a, md, b)
            if a in text and b in text:
                text = text[:text.index(a)] + block + text[text.index(b) + len(b):]
            else:
                text = text.rstrip('\n') + '\n\n' + block + '\n'
            open(args.doc, 'w').write(text)
            print('updated %s (%s)' % (args.doc, device))
        else:
            print(md)


if __name__ == '__main__':
    main()
