#!/usr/bin/env python3
"""CPU, one call, double: scandyn's derivatives of inverse and forward dynamics
(`scandyn bench --algo did|dfd --instances 1`) next to Pinocchio's
computeRNEADerivatives / computeABADerivatives (`pin_bench bench --algo did|dfd
--instances 1`, bench/compare/pin_bench), on iiwa and atlas.

The two programs run alternately, `--repeats` times each per (model, algorithm), each
run timing whole calls for `--min-time` seconds; the row reports the fastest run of
each (the least disturbed by other processes on a shared machine), and the note the
median and the ratio scandyn / pinocchio of both. Rows in the format of
bench/results/compare-cpu-*.csv.

With --floating the models are on a free joint (scandyn --floating-base, pin_bench
--root free: JointModelFreeFlyer), --model-names picks the models (default iiwa,atlas).
The CSV starts with '#' lines naming the machine and its load, the commit (--commit, or
HEAD) and the command.

Usage: derivatives_cpu.py --scandyn build/scandyn --pin-bench build-pin/pin_bench
         --models models --out bench/results/derivatives-cpu-<machine>.csv
         [--floating] [--model-names hyq,atlas]
(pin_bench needs LD_LIBRARY_PATH to hold the `pin` wheel's cmeel.prefix/lib).
"""
import argparse
import os
import statistics
import subprocess
import sys

HEADER = ('algo,strategy,backend,precision,model,links,instances,seconds_per_call,evals_per_second,'
          'max_rel_err,library,version,check_max_err,note')


def run(cmd):
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.strip().splitlines()
    return out[-1].split(',')


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--scandyn', required=True)
    ap.add_argument('--pin-bench', required=True)
    ap.add_argument('--models', required=True)
    ap.add_argument('--out', required=True)
    ap.add_argument('--repeats', type=int, default=7)
    ap.add_argument('--min-time', type=float, default=0.3)
    ap.add_argument('--floating', action='store_true', help='the models on a free joint (floating base)')
    ap.add_argument('--model-names', default='iiwa,atlas')
    ap.add_argument('--commit', help="the commit the --scandyn binary was built from, for the CSV's '#' lines "
                    '(default: the working tree\'s HEAD)')
    args = ap.parse_args()
    version = subprocess.run([args.scandyn, '--version'], capture_output=True, text=True).stdout.strip()
    pin_version = subprocess.run([args.pin_bench, 'version'], capture_output=True, text=True).stdout.strip()
    version, pin_version = version.replace(',', ';'), pin_version.replace(',', ';')  # CSV fields
    rows = []
    for model in args.model_names.split(','):
        urdf = os.path.join(args.models, model + '.urdf')
        for algo in ('did', 'dfd'):
            sc, pn = [], []
            for _ in range(args.repeats):
                r = run([args.scandyn, 'bench', '--model', urdf, '--algo', algo, '--instances', '1', '--min-time',
                         str(args.min_time), '--allow-nonphysical-inertia']
                        + (['--floating-base'] if args.floating else []))
                sc.append((float(r[7]), r))
                p = run([args.pin_bench, 'bench', '--urdf', urdf, '--name', model + ('-floating' if args.floating else ''),
                         '--algo', algo, '--instances', '1', '--min-time', str(args.min_time)]
                        + (['--root', 'free'] if args.floating else []))
                pn.append((float(p[7]), p))
            best_s, best_p = min(sc)[0], min(pn)[0]
            med_s, med_p = statistics.median(t for t, _ in sc), statistics.median(t for t, _ in pn)
            note = ('fastest of %d alternating runs; ratio scandyn/pinocchio %.3f (fastest) %.3f (median)'
                    % (args.repeats, best_s / best_p, med_s / med_p))
            r, p = min(sc)[1], min(pn)[1]
            rows.append(','.join(r[:10] + ['scandyn', version, '', note]))
            rows.append(','.join(p[:9] + ['', 'pinocchio', pin_version, '', note]))
            print(rows[-2], rows[-1], sep='\n', flush=True)
    cpu = next((l.split(':', 1)[1].strip() for l in open('/proc/cpuinfo') if l.startswith('model name')), '?')
    with open(args.out, 'w') as fh:
        if True:  # '#' lines: machine, load, commit, command
            commit = args.commit or subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], capture_output=True,
                                                   text=True).stdout.strip()
            fh.write('# machine: %s, %d threads, load average %s at the end of the run\n'
                     % (cpu, os.cpu_count(), ' '.join(open('/proc/loadavg').read().split()[:3])))
            fh.write('# commit: %s (scandyn %s; %s)\n' % (commit, version, pin_version))
            fh.write('# command: %s\n' % ' '.join([os.path.basename(sys.argv[0])] + sys.argv[1:]))
        fh.write(HEADER + '\n' + '\n'.join(rows) + '\n')
    with open(os.path.splitext(args.out)[0] + '.env.txt', 'w') as fh:
        fh.write('date: %s\ncpu: %s, %d threads\nload average: %s\nscandyn: %s\npinocchio: %s\n'
                 % (subprocess.run(['date', '-u', '+%Y-%m-%dT%H:%M:%SZ'], capture_output=True, text=True).stdout.strip(),
                    cpu, os.cpu_count(), ' '.join(open('/proc/loadavg').read().split()[:3]), version, pin_version))
    return 0


if __name__ == '__main__':
    sys.exit(main())
