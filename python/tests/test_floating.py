"""Floating bases and ball joints from Python: nq != nv, q's quaternions, the engines
against Pinocchio's free flyer (its velocity block [v; w] is scandyn's [w; v])."""

import numpy as np
import pytest

import scandyn as sd


def test_floating_dimensions():
    m = sd.load_model("hyq", floating_base=True)
    assert (m.nq, m.nv) == (19, 18) and m.floating_base
    assert m.joint_types[0] == "free" and m.joint_names[0] == "root_joint"
    b = sd.load_model("ballrope:4")
    assert (b.nq, b.nv) == (16, 12) and not b.floating_base
    assert b.joint_types == ["spherical"] * 4
    with pytest.raises(sd.ModelError, match="no mass"):
        sd.load_model("curtain:2:2", floating_base=True)


def random_state(m, batch, rng):
    q = rng.uniform(-1, 1, (batch, m.nq))
    q[:, 3:7] /= np.linalg.norm(q[:, 3:7], axis=1, keepdims=True)
    return q, rng.uniform(-1, 1, (batch, m.nv)), rng.uniform(-1, 1, (batch, m.nv))


def test_floating_engines_are_consistent():
    m = sd.load_model("hyq", floating_base=True)
    rng = np.random.default_rng(1)
    q, qd, tau = random_state(m, 5, rng)
    qdd = sd.forward_dynamics(m, q, qd, tau)
    assert qdd.shape == (5, 18)
    np.testing.assert_allclose(sd.inverse_dynamics(m, q, qd, qdd), tau, rtol=0, atol=1e-10)
    M = sd.mass_matrix(m, q)
    h = sd.bias_forces(m, q, qd)
    np.testing.assert_allclose(np.einsum("bij,bj->bi", M, qdd) + h, tau, rtol=0, atol=1e-9)
    with pytest.raises(sd.ShapeError, match="nq = 19"):
        sd.forward_dynamics(m, q[:, :18], qd, tau)


def test_floating_against_pinocchio():
    pin = pytest.importorskip("pinocchio")
    import scandyn.models

    m = sd.load_model("hyq", floating_base=True)
    pm = pin.buildModelFromUrdf(scandyn.models.path("hyq"), pin.JointModelFreeFlyer())
    pd = pm.createData()
    rng = np.random.default_rng(2)
    q, qd, tau = random_state(m, 3, rng)
    qdd = sd.forward_dynamics(m, q, qd, tau)
    perm = np.r_[3, 4, 5, 0, 1, 2, 6:18]  # pin vector = ours[perm]; the same map back
    for k in range(3):
        ref = pin.aba(pm, pd, q[k], qd[k][perm], tau[k][perm])[perm]
        np.testing.assert_allclose(qdd[k], ref, rtol=0, atol=1e-10 * max(1, np.abs(ref).max()))


def test_floating_kinematics():
    """Frames of a floating base: the root link where q puts it, q with nq columns; the
    Jacobians' free-joint columns against Pinocchio's free flyer (when installed)."""
    m = sd.load_model("hyq", floating_base=True)
    rng = np.random.default_rng(3)
    q, _, _ = random_state(m, 4, rng)
    P = sd.frame_placements(m, q, quaternion=True)
    assert P.shape == (4, len(m.frames), 7)
    np.testing.assert_allclose(P[:, 0, :3], q[:, :3], rtol=0, atol=1e-14)  # frame 0: the root link
    np.testing.assert_allclose(np.abs(np.einsum("bi,bi->b", P[:, 0, 3:], q[:, 3:7])), 1, rtol=0, atol=1e-14)
    J = sd.frame_jacobians(m, q)
    assert J.shape == (4, len(m.frames), 6, m.nv)
    with pytest.raises(sd.ShapeError, match="nq = 19"):
        sd.frame_placements(m, q[:, :18])
    pin = pytest.importorskip("pinocchio")
    import scandyn.models

    pm = pin.buildModelFromUrdf(scandyn.models.path("hyq"), pin.JointModelFreeFlyer())
    pd = pm.createData()
    perm = np.r_[3, 4, 5, 0, 1, 2, 6:18]
    inv = np.argsort(perm)
    swap = np.r_[3:6, 0:3]
    for k in range(4):
        pin.computeJointJacobians(pm, pd, q[k])
        pin.framesForwardKinematics(pm, pd, q[k])
        for f, name in enumerate(m.frames):
            ref = pin.getFrameJacobian(pm, pd, pm.getFrameId(name, pin.BODY), pin.LOCAL_WORLD_ALIGNED)[swap][:, inv]
            np.testing.assert_allclose(J[k, f], ref, rtol=0, atol=1e-12)


def test_multi_dof_refusals():
    """What takes 1-DoF joints only says so, naming the joint."""
    m = sd.load_model("hyq", floating_base=True)
    rng = np.random.default_rng(4)
    q, qd, tau = random_state(m, 2, rng)
    fd = sd.ForwardDynamics(m, max_batch=2, fd_check="on")  # the check takes multi-DoF joints
    np.testing.assert_allclose(fd(q, qd, tau), sd.forward_dynamics(m, q, qd, tau), rtol=0, atol=1e-12)
    # the simulator takes ball joints; prescribed motion (the hybrid dynamics) does not
    with pytest.raises(sd.SceneError, match="prescribed: the model has the multi-DoF joint 'joint_0'"):
        sd.Simulator({"model": "ballrope:3", "dt": 1e-3, "backend": "serial", "instances": 1,
                      "prescribed": {"joints": [0], "trajectory": [{"sine": {"amplitude": 1}}]}})


def test_simulator_state_has_nq_positions():
    """The simulator of a floating ballrope: q is (B, nq) with unit quaternions after
    steps, qd (B, nv); the free fall of gravity moves the base by -g t^2 / 2."""
    s = sd.Simulator({"model": "ballrope:3", "base": "floating", "dt": 1e-3, "backend": "serial",
                      "instances": 4, "integrator": "rk4", "effects": {"gravity": True}})
    assert (s.nq, s.nv) == (15, 12)  # a free base (7, 6) and two ball joints (4, 3)
    assert s.q.shape == (4, s.nq) and s.qd.shape == (4, s.nv)
    z0 = s.q[:, 2].copy()
    for _ in range(100):
        s.step(None)
    np.testing.assert_allclose(np.linalg.norm(s.q[:, 3:7], axis=1), 1.0, atol=1e-12)
    # at rest in the neutral pose the rope falls as one body
    np.testing.assert_allclose(s.q[:, 2] - z0, -0.5 * 9.81 * 0.1 ** 2, rtol=1e-9)
    with pytest.raises(sd.ShapeError, match=r"\(4, %d\)" % s.nv):
        s.step(np.zeros((4, s.nq)))


def test_floating_first_order_derivatives():
    """id_derivatives / fd_derivatives take a floating base and ball joints: q (B, nq),
    (B, nv, nv) results; M against mass_matrix, dqdd/dtau M = 1, dqdd/dq = -M^-1 dtau/dq
    at qdd = FD (1e-9), serial == openmp, and (when installed) Pinocchio's
    computeRNEADerivatives / computeABADerivatives on the free flyer (1e-9 relative)."""
    import scandyn.autograd as ad

    # (spec, floating base, where q's quaternions start)
    for spec, floating, starts in (("hyq", True, [3]), ("ballrope:3", False, [0, 4, 8]),
                                   ("ballrope:3", True, [3, 7, 11])):
        m = sd.load_model(spec, floating_base=floating)
        rng = np.random.default_rng(5)
        q = rng.uniform(-1, 1, (3, m.nq))
        for s in starts:
            q[:, s:s + 4] /= np.linalg.norm(q[:, s:s + 4], axis=1, keepdims=True)
        qd, x = rng.uniform(-1, 1, (3, m.nv)), rng.uniform(-1, 1, (3, m.nv))
        dq, dqd, M = ad.id_derivatives(m, q, qd, x)
        assert dq.shape == (3, m.nv, m.nv)
        np.testing.assert_allclose(M, sd.mass_matrix(m, q), rtol=0, atol=1e-12 * max(1, np.abs(M).max()))
        qdd, fq, fqd, ft = ad.fd_derivatives(m, q, qd, x)
        eye = np.broadcast_to(np.eye(m.nv), M.shape)
        np.testing.assert_allclose(ft @ M, eye, rtol=0, atol=1e-9)
        tq, tqd, _ = ad.id_derivatives(m, q, qd, qdd)
        np.testing.assert_allclose(fq, -ft @ tq, rtol=0, atol=1e-9 * max(1, np.abs(fq).max()))
        np.testing.assert_allclose(fqd, -ft @ tqd, rtol=0, atol=1e-9 * max(1, np.abs(fqd).max()))
        serial = ad.IdDerivatives(m, backend="serial", max_batch=3)(q, qd, x)
        openmp = ad.IdDerivatives(m, backend="openmp", max_batch=3, threads=2)(q, qd, x)
        for a, b in zip(serial, openmp):
            np.testing.assert_array_equal(a, b)
        with pytest.raises(sd.ShapeError, match="nq = %d" % m.nq):
            ad.id_derivatives(m, q[:, :m.nv], qd, x)
    pin = pytest.importorskip("pinocchio")
    import scandyn.models

    m = sd.load_model("hyq", floating_base=True)
    pm = pin.buildModelFromUrdf(scandyn.models.path("hyq"), pin.JointModelFreeFlyer())
    pd = pm.createData()
    rng = np.random.default_rng(6)
    q, qd, tau = random_state(m, 3, rng)
    qdd, fq, fqd, ft = ad.fd_derivatives(m, q, qd, tau)
    dq, dqd, M = ad.id_derivatives(m, q, qd, qdd)
    perm = np.r_[3, 4, 5, 0, 1, 2, 6:18]  # pin vector = ours[perm], its own inverse
    ours = np.ix_(perm, perm)
    for k in range(3):
        for got, ref in zip((dq[k], dqd[k]), pin.computeRNEADerivatives(pm, pd, q[k], qd[k][perm], qdd[k][perm])):
            ref = np.array(ref)[ours]
            np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * max(1, np.abs(ref).max()))
        for got, ref in zip((fq[k], fqd[k]), pin.computeABADerivatives(pm, pd, q[k], qd[k][perm], tau[k][perm])):
            ref = np.array(ref)[ours]
            np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * max(1, np.abs(ref).max()))
