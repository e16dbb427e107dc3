#!/usr/bin/env python3
"""Instructions per call from the callgrind dumps of bench_factor_graph.

bench_factor_graph, run under `valgrind --tool=callgrind --collect-atstart=no`, dumps
one profile per measurement, labelled "<model>,<problem>,<method>,<part> x<calls>".
This prints CSV: model,problem,method,part,instructions_per_call.

Usage: scripts/factor_graph_callgrind.py /tmp/fg_cg.*  [> bench/results/factor_graph_callgrind.csv]
"""
import re
import sys


def main():
    print('model,problem,method,part,instructions_per_call')
    rows = []
    for path in sys.argv[1:]:
        label = total = None
        with open(path, errors='replace') as fh:
            for line in fh:
                m = re.match(r'desc: Trigger: Client Request: (.*) x(\d+)$', line.strip())
                if m:
                    label, calls = m.group(1), int(m.group(2))
                elif line.startswith('summary:'):
                    total = int(line.split()[1])
        if label is not None and total is not None:
            rows.append((label, total / calls))
    for label, ir in sorted(rows):
        print('%s,%.0f' % (label, ir))


if __name__ == '__main__':
    main()
