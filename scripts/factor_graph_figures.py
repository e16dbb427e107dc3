#!/usr/bin/env python3
"""Figures of docs/factor-graph.md: the fill of the factor graph's Cholesky factor per
elimination ordering.

Reads the CSV of bench_factor_graph (--csv, default bench/results/factor_graph.csv)
and the factor patterns it writes with --patterns (--patterns, optional), and writes
into docs/figures/:
  factor-graph-fill.png        nnz(L) per ordering for every system of the tables
  factor-graph-chain.png       chains: elimination-tree height and flops per ordering
                               against the chain length (tree order linear in height,
                               cyclic reduction and nested dissection logarithmic)
  factor-graph-spy-<model>-<problem>.png   spy plots of L per ordering (with --patterns)

Usage:
  build-cpu/bench_factor_graph --reps 1 --inner 1 --cloth 4:4 --patterns /tmp/fg_patterns.csv > /dev/null
  scripts/factor_graph_figures.py --patterns /tmp/fg_patterns.csv
Needs matplotlib.
"""
import argparse
import csv
import os
import sys
from collections import defaultdict

try:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
except ImportError as e:
    print('factor_graph_figures: needs matplotlib (%s)' % e)
    sys.exit(1)

ORDER = ['fg-tree', 'fg-cyclic-reduction', 'fg-amd', 'fg-colamd', 'fg-metis-nd', 'fg-cholmod-nd']
LABEL = {'fg-tree': 'tree (RNEA/ABA)', 'fg-cyclic-reduction': 'cyclic reduction', 'fg-amd': 'AMD',
         'fg-colamd': 'COLAMD', 'fg-metis-nd': 'METIS ND', 'fg-cholmod-nd': 'CHOLMOD ND'}


def main():
    root = os.path.join(os.path.dirname(os.path.abspath(__file__)), '..')
    ap = argparse.ArgumentParser()
    ap.add_argument('--csv', default=os.path.join(root, 'bench', 'results', 'factor_graph.csv'))
    ap.add_argument('--patterns')
    ap.add_argument('--out', default=os.path.join(root, 'docs', 'figures'))
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    rows = list(csv.DictReader(open(args.csv)))

    # 1. fill per ordering, every system of the tables
    systems = []
    for r in rows:
        if r['method'].startswith('fg-') and r['problem'] != 'fd-symbolic':
            key = (r['model'], r['problem'])
            if key not in systems:
                systems.append(key)
    fig, ax = plt.subplots(figsize=(11, 4.5))
    width = 0.8 / len(ORDER)
    for k, m in enumerate(ORDER):
        xs, ys = [], []
        for s, (model, problem) in enumerate(systems):
            for r in rows:
                if r['model'] == model and r['problem'] == problem and r['method'] == m:
                    xs.append(s + (k - len(ORDER) / 2 + 0.5) * width)
                    ys.append(float(r['nnz_L']))
        if xs:
            ax.bar(xs, ys, width, label=LABEL[m])
    ax.set_xticks(range(len(systems)))
    ax.set_xticklabels(['%s\n%s' % s for s in systems], fontsize=8)
    ax.set_yscale('log')
    ax.set_ylabel('nnz(L), entries of the Cholesky factor')
    ax.set_title('Fill of the factor graph\'s normal equations per elimination ordering (CHOLMOD)')
    ax.legend(fontsize=8, ncol=3)
    fig.tight_layout()
    fig.savefig(os.path.join(args.out, 'factor-graph-fill.png'), dpi=120)
    plt.close(fig)

    # 2. chains: etree height and flops against n
    chain = defaultdict(list)
    for r in rows:
        if r['problem'] == 'fd-symbolic':
            n = int(r['model'].split(':')[1])
            chain[r['method']].append((n, int(r['etree_height']), float(r['flops'])))
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    for m in ORDER:
        if m in chain:
            pts = sorted(chain[m])
            a1.plot([p[0] for p in pts], [p[1] for p in pts], 'o-', label=LABEL[m])
            a2.plot([p[0] for p in pts], [p[2] for p in pts], 'o-', label=LABEL[m])
    for a, t in ((a1, 'elimination-tree height (critical path)'), (a2, 'factorisation flops')):
        a.set_xscale('log', base=2)
        a.set_yscale('log')
        a.set_xlabel('chain length n (links)')
        a.set_title(t)
        a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(args.out, 'factor-graph-chain.png'), dpi=120)
    plt.close(fig)

    # 3. spy plots of L
    if args.patterns:
        pat = defaultdict(lambda: ([], []))
        for r in csv.DictReader(open(args.patterns)):
            rr, cc = pat[(r['model'], r['problem'], r['method'])]
            rr.append(int(r['row']))
            cc.append(int(r['col']))
        for model, problem in sorted({(k[0], k[1]) for k in pat}):
            if model not in ('puma560', 'chain:15', 'five-bar', 'cloth:4:4'):
                continue
            methods = [m for m in ORDER if (model, problem, m) in pat]
            fig, axes = plt.subplots(1, len(methods), figsize=(3 * len(methods), 3.3))
            for a, m in zip(axes, methods):
                rr, cc = pat[(model, problem, m)]
                n = max(max(rr), max(cc)) + 1
                img = [[1.0] * n for _ in range(n)]
                for r_, c_ in zip(rr, cc):
                    img[r_][c_] = 0.0
                a.imshow(img, cmap='gray', vmin=0, vmax=1, interpolation='nearest')
                a.set_xticks([])
                a.set_yticks([])
                a.set_title('%s\nnnz(L) = %d' % (LABEL[m], len(rr)), fontsize=9)
            fig.suptitle('%s, %s: the Cholesky factor L per ordering' % (model, problem), fontsize=10)
            fig.tight_layout()
            name = 'factor-graph-spy-%s-%s.png' % (model.replace(':', '-'), problem)
            fig.savefig(os.path.join(args.out, name), dpi=110)
            plt.close(fig)


if __name__ == '__main__':
    main()
