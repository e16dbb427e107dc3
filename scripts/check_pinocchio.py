#!/usr/bin/env python3
"""Cross-check scandyn against Pinocchio, an independent dynamics library.

For the robots in the models directory and for random URDF trees (arbitrary
axes, rotated inertial frames, revolute / continuous / prismatic / fixed joints,
shuffled joint names), runs `scandyn eval --algo id,fd,mass,bias,did,dfd` on
random states and compares every column with Pinocchio's rnea, aba, crba,
nonLinearEffects, computeRNEADerivatives and computeABADerivatives (derivatives
with respect to the tangent of q: one column per DoF, continuous joints
included). With a floating base (--base floating or both) the same algorithms
on `--floating-base` models against Pinocchio's JointModelFreeFlyer (its velocity
block [v; w] reordered to scandyn's [w; v], its wrench [f; n] to [n; f], rows and
columns of the derivatives alike; both take q derivatives along the joint's local
increment q (+) d, nv columns), and on
ropes of ball joints (ballrope:N, fixed and free) and free rope:N against models
built here in Python from the generators' geometry (docs/models.md) with
JointModelSpherical. On fixed-base models then `scandyn eval --algo fk,jac` (every
frame: every URDF link, fixed links included) with framesForwardKinematics and
computeFrameJacobian, in world axes (LOCAL_WORLD_ALIGNED) and the frame's own (LOCAL).
Exits non-zero on any mismatch.

Usage: check_pinocchio.py --scandyn build/scandyn [--models DIR] [--random 20] [--tol 1e-9]
                          [--base fixed|floating|both]
Needs: numpy and pinocchio (PyPI package `pin`; scripts/setup_python.sh puts them in
.venv). Without them it exits with 77, which ctest reports as skipped.
"""
import argparse
import csv
import math
import os
import random
import subprocess
import sys
import tempfile

try:
    import numpy as np
    import pinocchio as pin
except ImportError as e:  # the test harness treats 77 as "skipped"
    print('check_pinocchio: skipped: %s (scripts/setup_python.sh installs numpy and pin into .venv)' % e)
    sys.exit(77)


def rpy_to_matrix(r, p, y):
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def random_urdf(n, rng, massive_base=False):
    """A random tree of n links below a base link, as URDF text. The base is a
    massless frame, or (massive_base, for a floating base) a random rigid body."""
    def f(x):
        return repr(float(x))

    def vec(s):
        return [rng.uniform(-s, s) for _ in range(3)]

    def inertial_link(name):
        m = rng.uniform(0.2, 3.0)
        a, b = rng.uniform(0.01, 0.3), rng.uniform(0.01, 0.3)
        c = rng.uniform(abs(a - b) + 1e-3, a + b)
        R = rpy_to_matrix(*vec(3))
        Ic = R @ np.diag([a, b, c]) @ R.T  # written in the inertial frame, itself rotated
        xyz, rpy = vec(0.2), vec(3)
        return ('<link name="%s"><inertial><origin xyz="%s" rpy="%s"/><mass value="%s"/>'
                '<inertia ixx="%s" ixy="%s" ixz="%s" iyy="%s" iyz="%s" izz="%s"/></inertial></link>'
                % (name, ' '.join(map(f, xyz)), ' '.join(map(f, rpy)), f(m), f(Ic[0, 0]), f(Ic[0, 1]),
                   f(Ic[0, 2]), f(Ic[1, 1]), f(Ic[1, 2]), f(Ic[2, 2])))

    links, joints = [inertial_link('base') if massive_base else '<link name="base"/>'], []
    names = ['base']
    for i in range(n):
        name = 'link_%d' % i
        parent = rng.choice(names)
        body = inertial_link(name)
        kind = rng.choices(['revolute', 'continuous', 'prismatic', 'fixed'], [5, 2, 2, 2])[0]
        if kind == 'fixed' and rng.random() < 0.5:
            links.append('<link name="%s"/>' % name)  # massless frame (fixed joints only: no singular M)
        else:
            links.append(body)
        axis = np.array(vec(1.0))
        axis /= np.linalg.norm(axis)
        jname = 'j%03d_%s' % (rng.randrange(1000), name)  # sibling order differs from creation order
        limit = '<limit lower="-3" upper="3" effort="100" velocity="10"/>' if kind in ('revolute', 'prismatic') else ''
        joints.append('<joint name="%s" type="%s"><parent link="%s"/><child link="%s"/>'
                      '<origin xyz="%s" rpy="%s"/><axis xyz="%s"/>%s</joint>'
                      % (jname, kind, parent, name, ' '.join(map(f, vec(0.4))), ' '.join(map(f, vec(3))),
                         ' '.join(map(f, axis)), limit))
        names.append(name)
    return '<?xml version="1.0"?>\n<robot name="random">\n%s\n%s\n</robot>\n' % ('\n'.join(links), '\n'.join(joints))


def pin_q(model, q):
    """scandyn's q -> Pinocchio's configuration: one angle per 1-DoF joint (cos, sin
    for continuous joints), the quaternions of free and spherical joints as they are
    (both x, y, z, w)."""
    out, i = [], 0
    for j in model.joints[1:]:
        if j.nq == 2 and j.nv == 1:
            out += [math.cos(q[i]), math.sin(q[i])]
            i += 1
        else:
            out += list(q[i:i + j.nq])
            i += j.nq
    return np.array(out)


def free_perm(model):
    """Index map p with pin_vector = ours[p]: a free joint's block (first) is [v; w] in
    Pinocchio and [w; v] in scandyn; every other DoF keeps its place."""
    p = np.arange(model.nv)
    if model.joints[1].nq == 7:
        p[:6] = [3, 4, 5, 0, 1, 2]
    return p


def random_q(model, rng, states):
    """Random scandyn positions (states x nq): angles in [-2, 2], positions of a free
    joint in [-2, 2], uniformly random unit quaternions."""
    rows = []
    for _ in range(states):
        q = []
        for j in model.joints[1:]:
            if j.nq == 7 or (j.nq == 4 and j.nv == 3):
                if j.nq == 7:
                    q += list(rng.uniform(-2, 2, 3))
                u = rng.normal(size=4)
                q += list(u / np.linalg.norm(u))
            else:
                q.append(rng.uniform(-2, 2))
        rows.append(q)
    return np.array(rows)


def check(scandyn, urdf_path, label, states, tol, precision='double', lenient=False, floating=False,
          model=None, spec=None):
    """Compares `scandyn eval` on urdf_path (or the generator spec, with the Pinocchio
    model given) with Pinocchio, on random states."""
    if model is None:
        model = pin.buildModelFromUrdf(urdf_path, pin.JointModelFreeFlyer()) if floating \
            else pin.buildModelFromUrdf(urdf_path)
    data = model.createData()
    nv = model.nv
    perm = free_perm(model)
    rng = np.random.default_rng(len(label))
    Q = random_q(model, rng, states)
    nq = Q.shape[1]
    QD = rng.uniform(-2, 2, (states, nv))
    QDD = rng.uniform(-2, 2, (states, nv))
    TAU = rng.uniform(-5, 5, (states, nv))
    with tempfile.TemporaryDirectory() as tmp:
        inp, out = os.path.join(tmp, 'in.csv'), os.path.join(tmp, 'out.csv')
        with open(inp, 'w', newline='') as fh:
            w = csv.writer(fh)
            w.writerow(['q_%d' % i for i in range(nq)] + ['qd_%d' % i for i in range(nv)] +
                       ['qdd_%d' % i for i in range(nv)] + ['tau_%d' % i for i in range(nv)])
            for k in range(states):
                w.writerow(['%.17g' % x for x in np.concatenate([Q[k], QD[k], QDD[k], TAU[k]])])
        algos = 'id,fd,mass,bias,did,dfd'
        subprocess.run([scandyn, 'eval', '--model', spec or urdf_path, '--states', inp, '--out', out,
                        '--algo', algos, '--precision', precision]
                       + (['--allow-nonphysical-inertia'] if lenient else [])
                       + (['--floating-base'] if floating else []), check=True)
        with open(out) as fh:
            rows = list(csv.DictReader(fh))
    worst = {'id': 0.0, 'fd': 0.0, 'mass': 0.0, 'bias': 0.0, 'did': 0.0, 'dfd': 0.0}
    inv = np.argsort(perm)  # ours = pin[inv]
    ours = np.ix_(inv, inv)  # a Pinocchio nv x nv matrix in scandyn's DoF order (rows and columns)
    for k, row in enumerate(rows):
        q = pin_q(model, Q[k])
        v, a, t = QD[k][perm], QDD[k][perm], TAU[k][perm]
        tau = pin.rnea(model, data, q, v, a)[inv]
        qdd = pin.aba(model, data, q, v, t)[inv]
        M = pin.crba(model, data, q)
        M = (np.triu(M) + np.triu(M, 1).T)[np.ix_(inv, inv)]
        h = pin.nonLinearEffects(model, data, q, v)[inv]
        # the derivatives: Pinocchio's q columns are along its local increments q (+) d
        # (a free joint's d = [v; w] in the base frame, a spherical joint's w in the
        # child frame), scandyn's too ([w; v] for the free joint: the permutation)
        dtau_dq, dtau_dqd, dtau_dqdd = (np.array(x) for x in pin.computeRNEADerivatives(model, data, q, v, a))
        dtau_dqdd = np.triu(dtau_dqdd) + np.triu(dtau_dqdd, 1).T
        dtau_dq, dtau_dqd, dtau_dqdd = dtau_dq[ours], dtau_dqd[ours], dtau_dqdd[ours]
        dqdd_dq, dqdd_dqd, dqdd_dtau = (np.array(x) for x in pin.computeABADerivatives(model, data, q, v, t))
        dqdd_dtau = np.triu(dqdd_dtau) + np.triu(dqdd_dtau, 1).T
        dqdd_dq, dqdd_dqd, dqdd_dtau = dqdd_dq[ours], dqdd_dqd[ours], dqdd_dtau[ours]

        def err(name, ref, cols):
            got = np.array([float(row[c]) for c in cols])
            e = np.max(np.abs(got - ref.ravel())) / max(1.0, np.max(np.abs(ref)))
            worst[name] = max(worst[name], e)

        err('id', tau, ['tau_id_%d' % i for i in range(nv)])
        # fd: the difference from Pinocchio's aba, or (ill-conditioned M: long ball-joint
        # ropes reach cond(M) = 1e7 and |qdd| = 1e9, where either answer differs from the
        # exact one by up to cond * 1e-16) scandyn's normwise backward error
        # |M qdd + h - tau| / (|M| |qdd| + |tau - h|), with M and h from Pinocchio
        got = np.array([float(row['qdd_fd_%d' % i]) for i in range(nv)])
        direct = np.max(np.abs(got - qdd)) / max(1.0, np.max(np.abs(qdd)))
        rhs = TAU[k] - h
        backward = np.max(np.abs(M @ got - rhs)) / (np.max(np.abs(M).sum(1)) * np.max(np.abs(got)) + np.max(np.abs(rhs)))
        worst['fd'] = max(worst['fd'], min(direct, backward))
        err('mass', M, ['M_%d_%d' % (i, j) for i in range(nv) for j in range(nv)])
        err('bias', h, ['h_%d' % i for i in range(nv)])

        def matrix(prefix):
            return ['%s_%d_%d' % (prefix, i, j) for i in range(nv) for j in range(nv)]

        err('did', np.concatenate([dtau_dq.ravel(), dtau_dqd.ravel(), dtau_dqdd.ravel()]),
            matrix('dtau_dq') + matrix('dtau_dqd') + matrix('dtau_dqdd'))
        # dfd: the difference from Pinocchio's, or (ill-conditioned M, as for fd: ball-joint
        # ropes) the normwise backward error of the three solves M X = R, with M and R =
        # -dtau/dq, -dtau/dqd, 1 from Pinocchio at scandyn's qdd
        ref = np.concatenate([dqdd_dq.ravel(), dqdd_dqd.ravel(), dqdd_dtau.ravel()])
        cols = matrix('dqdd_dq') + matrix('dqdd_dqd') + matrix('dqdd_dtau')
        got = np.array([float(row[c]) for c in cols])
        direct = np.max(np.abs(got - ref)) / max(1.0, np.max(np.abs(ref)))
        qdd_ours = np.array([float(row['qdd_fd_%d' % i]) for i in range(nv)])
        rq, rqd, _ = (np.array(x) for x in pin.computeRNEADerivatives(model, data, q, v, qdd_ours[perm]))
        backward = 0.0
        for X, R in zip(got.reshape(3, nv, nv), (-rq[ours], -rqd[ours], np.eye(nv))):
            backward = max(backward, np.max(np.abs(M @ X - R)) /
                           (np.max(np.abs(M).sum(1)) * np.max(np.abs(X)) + np.max(np.abs(R))))
        worst['dfd'] = max(worst['dfd'], min(direct, backward))
    if spec is None:  # kinematics: the URDF models, fixed and floating (the frames are the URDF's links)
        worst.update(check_kinematics(scandyn, urdf_path, model, Q, precision, lenient, floating))
    ok = all(v <= tol for v in worst.values())
    print('%-36s nv=%3d  %s  %s' % (label, nv, '  '.join('%s %.1e' % kv for kv in worst.items()),
                                    'ok' if ok else 'MISMATCH'))
    return ok


def quat_matrix(x, y, z, w):
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def check_kinematics(scandyn, urdf_path, model, Q, precision, lenient, floating=False):
    """The worst errors of fk (position and rotation) and jac (world, local) over every
    frame of the model, against Pinocchio. scandyn's rows are [angular; linear],
    Pinocchio's [linear; angular]; with a floating base its free joint's columns too."""
    data = model.createData()
    nv = model.nv
    inv = np.argsort(free_perm(model))  # scandyn's columns = Pinocchio's[:, inv]
    worst = {'fk': 0.0, 'jac_world': 0.0, 'jac_local': 0.0}
    with tempfile.TemporaryDirectory() as tmp:
        inp = os.path.join(tmp, 'in.csv')
        with open(inp, 'w', newline='') as fh:
            w = csv.writer(fh)
            w.writerow(['q_%d' % i for i in range(len(Q[0]))])
            for row in Q:
                w.writerow(['%.17g' % x for x in row])
        rows = {}
        for ref in ('world', 'local'):
            out = os.path.join(tmp, 'out_%s.csv' % ref)
            subprocess.run([scandyn, 'eval', '--model', urdf_path, '--states', inp, '--out', out,
                            '--algo', 'fk,jac', '--reference', ref, '--precision', precision]
                           + (['--allow-nonphysical-inertia'] if lenient else [])
                           + (['--floating-base'] if floating else []), check=True)
            with open(out) as fh:
                rows[ref] = list(csv.DictReader(fh))
    # the frames scandyn names: its fk columns, in order
    names = [c[3:-3] for c in rows['world'][0].keys() if c.startswith('fk_') and c.endswith('_px')]
    swap = np.r_[3:6, 0:3]  # Pinocchio's rows in scandyn's order
    for k in range(len(Q)):
        q = pin_q(model, Q[k])
        pin.framesForwardKinematics(model, data, q)
        pin.computeJointJacobians(model, data, q)
        for name in names:
            fid = model.getFrameId(name, pin.BODY)
            assert fid < model.nframes, 'Pinocchio has no body frame %s' % name
            oMf = data.oMf[fid]
            row = rows['world'][k]
            p = np.array([float(row['fk_%s_%s' % (name, e)]) for e in ('px', 'py', 'pz')])
            quat = [float(row['fk_%s_%s' % (name, e)]) for e in ('qx', 'qy', 'qz', 'qw')]
            worst['fk'] = max(worst['fk'], np.max(np.abs(p - oMf.translation)),
                              np.max(np.abs(quat_matrix(*quat) - oMf.rotation)))
            for ref, frame in (('world', pin.LOCAL_WORLD_ALIGNED), ('local', pin.LOCAL)):
                J = np.asarray(pin.getFrameJacobian(model, data, fid, frame)).reshape(6, nv)[swap][:, inv]  # (6,): nv = 1
                got = np.array([[float(rows[ref][k]['J_%s_%d_%d' % (name, r, j)]) for j in range(nv)]
                                for r in range(6)])
                e = np.max(np.abs(got - J)) / max(1.0, np.max(np.abs(J)))
                worst['jac_' + ref] = max(worst['jac_' + ref], e)
    return worst


ROPE_MASS, ROPE_LENGTH, ROPE_RADIUS = 0.01, 0.01, 0.002  # the rope generators' links (docs/models.md)


def rope_model(n, ball, floating):
    """The Pinocchio model of scandyn's rope:N (revolute joints about x, y, x, ...) or
    ballrope:N (spherical joints), built from the generators' geometry: links 1 cm
    long hanging along -z, each joint 1 cm below the previous one. floating: the
    first link on a free joint instead of its own joint (rope:N --floating-base)."""
    m, L, r = ROPE_MASS, ROPE_LENGTH, ROPE_RADIUS
    side = m * (3 * r * r + L * L) / 12
    inertia = pin.Inertia(m, np.array([0, 0, -L / 2]), np.diag([side, side, m * r * r / 2]))
    model = pin.Model()
    parent = 0
    for i in range(n):
        place = pin.SE3(np.eye(3), np.array([0, 0, 0.0 if i == 0 else -L]))
        if i == 0 and floating:
            joint = pin.JointModelFreeFlyer()
        elif ball:
            joint = pin.JointModelSpherical()
        else:
            joint = pin.JointModelRX() if i % 2 == 0 else pin.JointModelRY()
        parent = model.addJoint(parent, joint, place, 'joint_%d' % i)
        model.appendBodyToJoint(parent, inertia, pin.SE3.Identity())
    return model


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--scandyn', required=True)
    ap.add_argument('--models', default=os.environ.get('SCANDYN_MODELS_DIR',
                                                       os.path.join(os.path.dirname(__file__), '..', 'models')))
    ap.add_argument('--random', type=int, default=20, help='number of random URDF trees')
    ap.add_argument('--states', type=int, default=5)
    ap.add_argument('--tol', type=float, default=1e-9)
    ap.add_argument('--base', choices=['fixed', 'floating', 'both'], default='both',
                    help='fixed-base models, --floating-base ones (and ball-joint ropes), or both')
    args = ap.parse_args()
    ok = True
    bases = [False, True] if args.base == 'both' else [args.base == 'floating']
    for floating in bases:
        tag = ' floating' if floating else ''
        # puma560's base link has no mass: no floating base
        for name in ('iiwa.urdf', 'hyq.urdf', 'atlas.urdf') + (() if floating else ('puma560.urdf',)):
            path = os.path.join(args.models, name)
            if os.path.exists(path):
                # GRiD's atlas.urdf has links whose inertia no rigid body can have
                ok &= check(args.scandyn, path, name + tag, args.states, args.tol, lenient=True, floating=floating)
            else:
                print('%s: not found in %s' % (name, args.models))
                ok = False
        rng = random.Random(2026 + floating)
        with tempfile.TemporaryDirectory() as tmp:
            for t in range(args.random):
                n = rng.choice([1, 2, 3, 5, 8, 13, 21, 40, 80])
                path = os.path.join(tmp, 'random_%d.urdf' % t)
                with open(path, 'w') as fh:
                    fh.write(random_urdf(n, rng, massive_base=floating))
                try:
                    ok &= check(args.scandyn, path, 'random_%d (%d links)%s' % (t, n, tag), args.states, args.tol,
                                floating=floating)
                except subprocess.CalledProcessError as e:
                    print('random_%d: scandyn failed (%s); URDF kept at %s' % (t, e, path))
                    ok = False
        if floating:
            for n in (1, 2, 7, 30):  # a single free body, then free ropes
                ok &= check(args.scandyn, None, 'rope:%d floating' % n, args.states, args.tol, floating=True,
                            model=rope_model(n, False, True), spec='rope:%d' % n)
            for n in (1, 4, 30):
                for free in (False, True):
                    ok &= check(args.scandyn, None, 'ballrope:%d%s' % (n, ' floating' if free else ''), args.states,
                                args.tol, floating=free, model=rope_model(n, True, free), spec='ballrope:%d' % n)
    print('all agree with pinocchio %s' % pin.__version__ if ok else 'MISMATCHES FOUND')
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
