#!/usr/bin/env python3
"""Closed-loop forward dynamics of `scandyn eval` against Pinocchio's constraint dynamics.

The fivebar and fourbar generators (docs/models.md, docs/loops.md) are described again
here from their documented geometry, as Pinocchio models (revolute z joints, slender
rods of 1 kg/m), with their point loop as a RigidConstraintModel (CONTACT_3D between
the two closing points). Random closed states: the proximal (fourbar: crank) angles
drawn, the rest solved by circle intersection, qd projected onto the loop's
velocity constraint. scandyn's qdd_fd (unique even though the planar loop has a
redundant z row) must match Pinocchio's constraintDynamics (proximal solver, 1e-14)
to 1e-8 relative to max(1, |qdd|). Exit 0 on success, 1 on a mismatch, 77 when
Pinocchio or the scandyn executable is missing.

usage: check_loops_pinocchio.py --scandyn PATH [--states N]
"""
import argparse
import math
import os
import subprocess
import sys
import tempfile

try:
    import numpy as np
    import pinocchio as pin
except ImportError as e:  # pragma: no cover
    print(f"skipped: {e}")
    sys.exit(77)


def rod_inertia(tip):
    tip = np.array(tip, dtype=float)
    L = np.linalg.norm(tip)
    m = L
    u = tip / L
    Ic = m * L * L / 12 * (np.eye(3) - np.outer(u, u)) + 1e-5 * np.eye(3)
    return pin.Inertia(m, tip / 2, Ic)


def build(spec):
    """(model, constraint frames (joint, point) a and b, DoF names) of fivebar / fourbar."""
    model = pin.Model()
    ids = {}

    def add(name, parent, origin, tip):
        jid = model.addJoint(ids.get(parent, 0), pin.JointModelRZ(), pin.SE3(np.eye(3), np.array(origin, float)), name)
        model.appendBodyToJoint(jid, rod_inertia(tip), pin.SE3.Identity())
        ids[name] = jid
    # DoF order as scandyn's: depth-first, siblings by joint name
    if spec == "fivebar":
        add("joint_l0", None, [0, 0, 0], [0, 0.25, 0])
        add("joint_l1", "joint_l0", [0, 0.25, 0], [0.15, 0.15, 0])
        add("joint_r0", None, [0.3, 0, 0], [0, 0.25, 0])
        add("joint_r1", "joint_r0", [0, 0.25, 0], [-0.15, 0.15, 0])
        loop = (ids["joint_l1"], [0.15, 0.15, 0], ids["joint_r1"], [-0.15, 0.15, 0])
    else:
        add("joint_a", None, [0, 0, 0], [0, 0.2, 0])
        add("joint_b", "joint_a", [0, 0.2, 0], [0.4, 0, 0])
        add("joint_d", None, [0.5, 0, 0], [-0.1, 0.2, 0])
        loop = (ids["joint_b"], [0.4, 0, 0], ids["joint_d"], [-0.1, 0.2, 0])
    return model, loop


def point(model, data, jid, p):
    return data.oMi[jid].act(np.array(p, float))


def closed_state(spec, model, loop, rng):
    """A closed configuration near q = 0 and a velocity on the loop."""
    data = model.createData()
    ja, pa, jb, pb = loop
    q = np.zeros(model.nq)
    for _ in range(100):
        q = rng.uniform(-0.15, 0.15, model.nq)
        for _ in range(60):  # Gauss-Newton on the closure (x, y)
            pin.forwardKinematics(model, data, q)
            pin.updateFramePlacements(model, data)
            r = point(model, data, ja, pa) - point(model, data, jb, pb)
            J = loop_jacobian(model, data, q, loop)
            if np.max(np.abs(r)) < 1e-14:
                break
            q = q - np.linalg.pinv(J[:2]) @ r[:2]
        if np.max(np.abs(r)) < 1e-13:
            break
    J = loop_jacobian(model, data, q, loop)
    v = rng.uniform(-1, 1, model.nv)
    v = v - np.linalg.pinv(J[:2]) @ (J[:2] @ v)
    return q, v


def loop_jacobian(model, data, q, loop):
    ja, pa, jb, pb = loop
    pin.computeJointJacobians(model, data, q)
    out = []
    for jid, p in ((ja, pa), (jb, pb)):
        Jw = pin.getJointJacobian(model, data, jid, pin.ReferenceFrame.WORLD)  # [v at world origin; w]
        x = point(model, data, jid, p)
        out.append(Jw[:3] - np.cross(x, Jw[3:].T).T)  # v_p = v_O + w x p = v_O - p x w
    return out[0] - out[1]


def pinocchio_fd(model, loop, q, v, tau):
    ja, pa, jb, pb = loop
    data = model.createData()
    cm = pin.RigidConstraintModel(pin.ContactType.CONTACT_3D, model, ja, pin.SE3(np.eye(3), np.array(pa, float)),
                                  jb, pin.SE3(np.eye(3), np.array(pb, float)), pin.ReferenceFrame.LOCAL)
    models = pin.StdVec_RigidConstraintModel()
    models.append(cm)
    datas = pin.StdVec_RigidConstraintData()
    datas.append(cm.createData())
    try:  # pinocchio 4 takes the constraint datas too; 3 does not
        pin.initConstraintDynamics(model, data, models, datas)
    except Exception:  # Boost.Python.ArgumentError
        pin.initConstraintDynamics(model, data, models)
    prox = pin.ProximalSettings(1e-14, 1e-10, 200)
    return np.array(pin.constraintDynamics(model, data, q, v, tau, models, datas, prox))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scandyn", required=True)
    ap.add_argument("--states", type=int, default=20)
    args = ap.parse_args()
    if not os.access(args.scandyn, os.X_OK):
        print(f"skipped: no scandyn executable at {args.scandyn}")
        return 77
    rng = np.random.default_rng(7)
    worst = 0.0
    for spec in ("fivebar", "fourbar"):
        model, loop = build(spec)
        n = model.nv
        rows, refs = [], []
        for _ in range(args.states):
            q, v = closed_state(spec, model, loop, rng)
            tau = rng.uniform(-1, 1, n)
            rows.append(np.concatenate([q, v, tau]))
            refs.append(pinocchio_fd(model, loop, q, v, tau))
        with tempfile.TemporaryDirectory() as d:
            states, out = os.path.join(d, "s.csv"), os.path.join(d, "o.csv")
            header = [f"{f}_{i}" for f in ("q", "qd", "tau") for i in range(n)]
            with open(states, "w") as f:
                f.write(",".join(header) + "\n")
                for r in rows:
                    f.write(",".join(repr(float(x)) for x in r) + "\n")
            p = subprocess.run([args.scandyn, "eval", "--model", spec, "--states", states, "--out", out],
                               capture_output=True, text=True)
            if p.returncode != 0:
                print(f"{spec}: scandyn eval failed: {p.stderr.strip()}")
                return 1
            got = np.loadtxt(out, delimiter=",", skiprows=1, ndmin=2)[:, :n]
        for k, ref in enumerate(refs):
            e = np.max(np.abs(got[k] - ref)) / max(1.0, np.max(np.abs(ref)))
            worst = max(worst, e)
            if not e <= 1e-8:
                print(f"{spec}: state {k}: qdd differs by {e:.3g} (scandyn {got[k]}, pinocchio {ref})")
                return 1
        print(f"{spec}: {len(refs)} closed states, max rel. difference {max(worst, 0):.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
