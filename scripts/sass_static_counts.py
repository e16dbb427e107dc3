#!/usr/bin/env python3
"""Static SASS counts of CUDA kernels: instructions, FP32/FP64 arithmetic, memory
instructions and the instructions inside each loop (a backward branch's range).

Input: the text of `cuobjdump --dump-sass K.cubin` or `nvdisasm -c K.cubin` (nvdisasm
for cubins cuobjdump does not list), and optionally ptxas' `-Xptxas -v` log for the
registers and stack frame. The cubins come from one translation unit each, e.g.

  nvcc -DSCANDYN_SIM_EFFECT_SETS=0 -Iinclude -Ibuild-dev/include -isystem=/usr/include/eigen3 \
       -O3 -DNDEBUG -arch=sm_90 --expt-relaxed-constexpr -std=c++17 -Xptxas -v \
       -cubin -x cu kernels/inverse_dynamics.cu -o inverse_dynamics.cubin 2> inverse_dynamics.ptxas.txt
  cuobjdump --dump-sass inverse_dynamics.cubin > inverse_dynamics.sass

Counts are STATIC: every instruction of the kernel once, whether a run executes it
never (a branch not taken, the large-argument path of sin/cos) or many times (a loop).
A loop is reported as the instructions between a backward branch's target and the
branch; nested loops appear once each. flops32 = 2 FFMA + FADD + FMUL (likewise FP64).

usage: sass_static_counts.py K.sass [--ptxas K.ptxas.txt] [--match REGEX] [--csv OUT.csv] [--label L]
"""
import argparse
import collections
import csv
import re
import sys

fn_re = re.compile(r'(?:Function : (\S+))|(?:^\.text\.(\S+):)')
label_re = re.compile(r'^(\.L_x_\d+):')
ins_re = re.compile(r'/\*([0-9a-f]{4,})\*/\s+(@!?U?P\w+\s+)?([A-Z][A-Z0-9_.]*)([^;]*);')


def parse(path):
    """{kernel: [(address, opcode, operands)]}; nvdisasm's branch labels become addresses."""
    fns = collections.OrderedDict()
    labels = {}
    cur, pending = None, []
    for line in open(path):
        m = fn_re.search(line)
        if m:
            cur = m.group(1) or m.group(2)
            fns[cur] = []
            pending = []
            continue
        m = label_re.search(line)
        if m:
            pending.append(m.group(1))
            continue
        m = ins_re.search(line)
        if m and cur:
            a = int(m.group(1), 16)
            for l in pending:
                labels[(cur, l)] = a
            pending = []
            fns[cur].append((a, m.group(3), m.group(4)))
    for name, ins in fns.items():
        for k, (a, op, rest) in enumerate(ins):
            m = re.search(r'`\((\.L_x_\d+)\)', rest)
            if m and (name, m.group(1)) in labels:
                ins[k] = (a, op, rest.replace(m.group(0), hex(labels[(name, m.group(1))])))
        # the code ends at the trailing `BRA self` and its NOP padding
        while ins and ins[-1][1] == 'NOP':
            ins.pop()
        if ins and ins[-1][1] == 'BRA':
            ins.pop()
    return fns


def stats(ins, lo=None, hi=None):
    sel = [i for i in ins if (lo is None or lo <= i[0] <= hi) and i[1] != 'NOP']
    c = collections.Counter(i[1].split('.')[0] for i in sel)
    return collections.OrderedDict(
        instructions=len(sel), ffma=c['FFMA'], fp32=c['FFMA'] + c['FADD'] + c['FMUL'],
        dfma=c['DFMA'], fp64=c['DFMA'] + c['DADD'] + c['DMUL'],
        flops32=2 * c['FFMA'] + c['FADD'] + c['FMUL'], flops64=2 * c['DFMA'] + c['DADD'] + c['DMUL'],
        mufu=c['MUFU'], ldg=c['LDG'], stg=c['STG'], ldl=c['LDL'], stl=c['STL'], branches=c['BRA'])


def loops(ins):
    out = []
    for a, op, rest in ins:
        if op.startswith('BRA'):
            m = re.search(r'0x([0-9a-f]+)', rest)
            if m and int(m.group(1), 16) < a:
                out.append((int(m.group(1), 16), a))
    return out


def resources(ptxas_path):
    """{kernel: (registers, stack bytes)} from ptxas -v."""
    res, cur, stack = {}, None, None
    if not ptxas_path:
        return res
    for line in open(ptxas_path):
        m = re.search(r"Compiling entry function '(\S+)'", line)
        if m:
            cur = m.group(1)
            continue
        m = re.search(r'(\d+) bytes stack frame', line)
        if m and cur:
            stack = int(m.group(1))
        m = re.search(r'Used (\d+) registers', line)
        if m and cur:
            res[cur] = (int(m.group(1)), stack)
            cur = None
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('sass')
    ap.add_argument('--ptxas')
    ap.add_argument('--match', help='regex on the mangled kernel name')
    ap.add_argument('--csv', help='append rows to this CSV (written with a header if new)')
    ap.add_argument('--label', default='', help='a label for the CSV rows (e.g. the source file)')
    ap.add_argument('--min-loop', type=int, default=40,
                    help='list loops of at least this many instructions (smaller ones: copy loops, '
                         "sin/cos's large-argument path)")
    a = ap.parse_args()
    fns = parse(a.sass)
    res = resources(a.ptxas)
    pat = re.compile(a.match) if a.match else None
    rows = []
    for name, ins in fns.items():
        if pat and not pat.search(name):
            continue
        s = stats(ins)
        regs, stack = res.get(name, ('', ''))
        big = [(lo, hi, stats(ins, lo, hi)) for lo, hi in loops(ins)]
        big = [(lo, hi, t) for lo, hi, t in big if t['instructions'] >= a.min_loop]
        loop_text = ' '.join('0x%x-0x%x:%d' % (lo, hi, t['instructions']) for lo, hi, t in big)
        print(name)
        print('  registers %s, stack %s B;' % (regs, stack), ', '.join('%s %d' % kv for kv in s.items()))
        for lo, hi, t in big:
            print('  loop 0x%x..0x%x:' % (lo, hi), ', '.join('%s %d' % kv for kv in t.items()))
        rows.append(dict(label=a.label, kernel=name, registers=regs, stack_bytes=stack, **s, loops=loop_text))
    if a.csv and rows:
        import os
        new = not os.path.exists(a.csv)
        with open(a.csv, 'a', newline='') as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
            if new:
                w.writeheader()
            w.writerows(rows)


if __name__ == '__main__':
    main()
