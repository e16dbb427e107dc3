#!/usr/bin/env python3
"""Smoke test of bench/compare's shared code (ctest `compare_smoke`, a few seconds).

The equality check of the comparison, on 4 random states, through common.py (states file,
`scandyn eval`, output reading, the error measure), with Pinocchio's Python API as the peer:
- iiwa.urdf: id, bias, mass, fd within 1e-9;
- rope:20: common.rope_urdf (the URDF the peers are given for scandyn's `rope:N`) loaded by
  Pinocchio against scandyn's own generator, so the two ropes are the same model;
- common.read_outputs returns exactly the computations the file holds (rope:20, id and fd);
- mujoco_peer.urdf_depth (which decides MuJoCo's tree-depth probe) is 8 on iiwa (a fixed
  joint to the world, then 7 revolute), 3 on hyq
  (three joints per leg) and N on rope:N.
Exits 77 (skipped) without numpy or Pinocchio (scripts/setup_python.sh installs them).

Usage: smoke.py --scandyn build/scandyn [--models DIR]
"""
import argparse
import os
import sys
import tempfile

try:
    import numpy as np
    import pinocchio as pin
except ImportError as e:
    print('compare smoke: skipped: %s' % e)
    sys.exit(77)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402
import mujoco_peer  # noqa: E402  (MuJoCo itself is imported only when a model is loaded)


def pin_outputs(urdf, S):
    model = pin.buildModelFromUrdf(urdf)
    data = model.createData()
    out = {'id': [], 'bias': [], 'mass': [], 'fd': []}
    for k in range(S['q'].shape[0]):
        q, qd = S['q'][k], S['qd'][k]
        out['id'].append(pin.rnea(model, data, q, qd, S['qdd'][k]).copy())
        out['bias'].append(pin.nonLinearEffects(model, data, q, qd).copy())
        M = pin.crba(model, data, q)
        out['mass'].append(np.triu(M) + np.triu(M, 1).T)
        out['fd'].append(pin.aba(model, data, q, qd, S['tau'][k]).copy())
    return {a: np.array(v) for a, v in out.items()}, [n for n in model.names[1:]]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--scandyn', required=True)
    ap.add_argument('--models')
    args = ap.parse_args()
    if args.models:
        os.environ['SCANDYN_MODELS_DIR'] = args.models
    ok = True
    with tempfile.TemporaryDirectory() as tmp:
        for name in ('iiwa', 'rope:20'):
            model = common.Model(name, tmp)
            names = common.scandyn_joints(args.scandyn, model)
            S = common.random_states(len(names), n=4)
            s_csv = os.path.join(tmp, 'states.csv')
            common.write_states(s_csv, S)
            ref = common.read_outputs(common.scandyn_eval(args.scandyn, model, s_csv, os.path.join(tmp, 'o.csv')),
                                      len(names))
            got, pnames = pin_outputs(model.urdf, S)
            if pnames != names:
                print('%s: DoF order differs: scandyn %s, pinocchio %s' % (name, names[:4], pnames[:4]))
                ok = False
                continue
            errs = {a: common.rel_err(got[a], ref[a]) for a in common.ALGOS}
            good = all(e <= 1e-9 for e in errs.values())
            ok &= good
            print('%-8s nv=%2d  %s  %s' % (name, len(names), '  '.join('%s %.1e' % kv for kv in errs.items()),
                                          'ok' if good else 'MISMATCH'))
        model = common.Model('rope:20', tmp)
        s_csv = os.path.join(tmp, 'states.csv')
        common.write_states(s_csv, common.random_states(20, n=2))
        got = common.read_outputs(common.scandyn_eval(args.scandyn, model, s_csv, os.path.join(tmp, 'p.csv'),
                                                      algos=('id', 'fd')), 20)
        if sorted(got) != ['fd', 'id'] or any(v.shape != (2, 20) for v in got.values()):
            print('read_outputs: %s' % {k: v.shape for k, v in got.items()})
            ok = False
        depths = {name: mujoco_peer.urdf_depth(common.Model(name, tmp).urdf) for name in ('iiwa', 'hyq', 'rope:20')}
        if depths != {'iiwa': 8, 'hyq': 3, 'rope:20': 20}:
            print('urdf_depth: %s' % depths)
            ok = False
    print('compare smoke: %s' % ('ok' if ok else 'FAILED'))
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
