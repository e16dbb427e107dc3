"""scandyn.Simulator: the library's simulator from Python (python/src/simulator.cpp).

Truths: a semi-implicit Euler step written here over sd.forward_dynamics (the engines,
a second path to the same physics; the serial engine is the reference ABA, so double
precision agrees to rounding); the scene format's documented initial-state draws; the
state views' addresses and strides; the library's error messages."""

import json
import os

import numpy as np
import pytest

import scandyn as sd

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def scene(**kw):
    s = {"model": "iiwa", "effects": {"gravity": True, "damping": 0.5}, "dt": 1e-3, "backend": "serial",
         "instances": 5, "initial": {"random": {"seed": 7, "q": 0.5, "qd": 0.2}}}
    s.update(kw)
    return s


def euler_reference(model, q, qd, tau, dt, damping, steps):
    """Semi-implicit Euler over the forward-dynamics engine: qdd = FD(q, qd, tau - d qd),
    qd += dt qdd, q += dt qd (docs/scenes.md, "Integrators")."""
    q, qd = q.copy(), qd.copy()
    for _ in range(steps):
        qdd = sd.forward_dynamics(model, q, qd, tau - damping * qd, backend="serial")
        qd = qd + dt * qdd
        q = q + dt * qd
    return q, qd


@pytest.mark.parametrize("backend", ["serial", "openmp"])
def test_steps_match_forward_dynamics_euler(backend):
    sim = sd.Simulator(scene(backend=backend))
    m = sd.load_model("iiwa")
    rng = np.random.default_rng(1)
    tau = rng.uniform(-5, 5, (5, 7))
    q0, qd0 = sim.q.copy(), sim.qd.copy()
    for _ in range(20):
        sim.step(tau)
    q, qd = euler_reference(m, q0, qd0, tau, 1e-3, 0.5, 20)
    # double: the same ABA; the effects and update in another order of operations
    np.testing.assert_allclose(sim.q, q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sim.qd, qd, rtol=0, atol=1e-10)
    assert sim.steps == 20 and sim.t == pytest.approx(0.02)


def test_serial_and_openmp_bit_identical():
    a, b = sd.Simulator(scene(backend="serial")), sd.Simulator(scene(backend="openmp"))
    tau = np.random.default_rng(2).uniform(-3, 3, (5, 7))
    a.step_many(30, tau)
    b.step_many(30, tau)
    assert a.strategy == "serial-aba" and b.strategy == "openmp-aba"
    assert np.array_equal(a.q, b.q) and np.array_equal(a.qd, b.qd)


def test_step_many_equals_steps_and_none_is_zero_torque():
    a, b, c = (sd.Simulator(scene()) for _ in range(3))
    a.step_many(7)
    for _ in range(7):
        b.step(np.zeros((5, 7)))
    c.step_many(7, np.zeros((5, 7)))
    assert np.array_equal(a.q, b.q) and np.array_equal(a.qd, b.qd)
    assert np.array_equal(a.q, c.q)
    assert a.steps == b.steps == 7


def test_strided_torques():
    a, b = sd.Simulator(scene()), sd.Simulator(scene())
    tau = np.random.default_rng(3).uniform(-2, 2, (5, 7))
    a.step(tau)
    b.step(np.asfortranarray(tau))          # another layout of the same values
    big = np.zeros((10, 14))
    big[::2, ::2] = tau
    c = sd.Simulator(scene())
    c.step(big[::2, ::2])                   # a strided view
    assert np.array_equal(a.q, b.q) and np.array_equal(a.qd, c.qd)


def test_state_views_are_the_simulators_memory():
    sim = sd.Simulator(scene(precision="float"))
    q, qd = sim.q, sim.qd
    assert q.shape == (5, 7) and q.dtype == np.float32 and sim.dtype == np.float32
    assert q.strides == (4, 4 * 5)  # (nv x B) SoA seen as (B, nv): strides (1, B) elements
    addr = q.__array_interface__["data"][0]
    sim.step_many(3)
    assert sim.q is q and sim.q.__array_interface__["data"][0] == addr
    assert not np.shares_memory(q, qd)
    # writing through the view changes the simulation: a state set here steps as a fresh one
    q[:] = 0.1
    qd[:] = 0.0
    sim.step(np.zeros((5, 7), np.float32))
    assert np.all(q[0] == q[1]) and not np.all(q == 0.1)
    # the view keeps the simulator alive
    del sim
    import gc

    gc.collect()
    assert np.all(np.isfinite(q))


def test_initial_state_and_reset():
    fixed = scene(initial={"q": [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7], "qd": 0.01})
    sim = sd.Simulator(fixed)
    assert np.array_equal(sim.q, np.tile(np.float64([0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7]), (5, 1)))
    sim.step_many(10)
    moved = sim.q.copy()
    sim.reset([1, 3])
    assert np.array_equal(sim.q[[1, 3]], np.tile(np.float64([0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7]), (2, 1)))
    assert np.all(sim.qd[[1, 3]] == 0.01)
    assert np.array_equal(sim.q[[0, 2, 4]], moved[[0, 2, 4]])
    sim.reset(np.array([True, False, False, False, False]))
    assert np.all(sim.qd[0] == 0.01) and np.array_equal(sim.q[2], moved[2])
    sim.reset()
    assert np.all(sim.qd == 0.01)


def test_random_initial_state_draws():
    """docs/scenes.md: std::mt19937_64(seed), u = (g() >> 11) 2^-53, per instance all q
    then all qd; reset(list) continues the generator."""
    sim = sd.Simulator(scene(instances=3, initial={"random": {"seed": 11, "q": 0.5, "qd": 0.2}}))
    # a second simulator of the same scene draws the same states
    again = sd.Simulator(scene(instances=3, initial={"random": {"seed": 11, "q": 0.5, "qd": 0.2}}))
    assert np.array_equal(sim.q, again.q) and np.array_equal(sim.qd, again.qd)
    assert np.all(np.abs(sim.q) <= 0.5) and np.all(np.abs(sim.qd) <= 0.2)
    assert len(np.unique(sim.q)) == sim.q.size
    first = sim.q.copy()
    sim.reset([0])  # new draws, not a replay
    assert not np.array_equal(sim.q[0], first[0]) and np.array_equal(sim.q[1:], first[1:])
    # instance 1 reset in a 1-instance scene after instance 0 gets the 2nd instance's draws
    one = sd.Simulator(scene(instances=1, initial={"random": {"seed": 11, "q": 0.5, "qd": 0.2}}))
    one.reset([0])
    np.testing.assert_array_equal(one.q[0], first[1])


def test_scene_file_and_properties(tmp_path):
    p = tmp_path / "s.json"
    p.write_text(json.dumps(scene(precision="float", backend="openmp", dt=2e-3, instances=4)))
    sim = sd.Simulator(str(p))
    assert (sim.nv, sim.num_instances, sim.dt, sim.backend, sim.precision) == (7, 4, pytest.approx(2e-3), "openmp", "float")
    assert sim.device == "cpu" and sim.t == 0 and sim.steps == 0
    assert sd.Simulator(str(p), backend="serial").backend == "serial"
    assert "Simulator(" in repr(sim)
    e = sim.energy()
    assert e.shape == (4,) and np.all(np.isfinite(e))


def test_shipped_scene_loads():
    sim = sd.Simulator(os.path.join(ROOT, "scenes", "rope_1e4.json"), backend="serial")
    assert sim.nv == 10000 and sim.num_instances == 1 and sim.precision == "double"
    auto = sd.Simulator(os.path.join(ROOT, "scenes", "rope_1e4.json"))  # "backend": "auto"
    given = sd.Simulator(scene(backend="serial"), backend="auto")
    for s in (auto, given):
        if s.backend == "cuda":
            assert s.backend_note == ""
        else:  # why not cuda, as the command line says it
            assert s.backend in ("openmp", "serial") and s.backend_note.startswith("cuda: ")
    assert given.backend == auto.backend
    assert sd.Simulator(os.path.join(ROOT, "scenes", "rope_1e4.json"), backend="serial").backend_note == ""


def test_scene_errors(tmp_path):
    with pytest.raises(sd.SceneError, match=r"<dict>: effects\.damping: expected a non-negative number") as e:
        sd.Simulator(scene(effects={"damping": -1}))
    assert isinstance(e.value, ValueError)
    with pytest.raises(sd.SceneError, match="<dict>: frobnicate: unknown key"):
        sd.Simulator(dict(scene(), frobnicate=1))
    with pytest.raises(sd.SceneError, match="dt: missing"):
        s = scene()
        del s["dt"]
        sd.Simulator(s)
    with pytest.raises(sd.SceneError, match="model: "):
        sd.Simulator(scene(model="nowhere.urdf"))
    with pytest.raises(sd.SceneError, match="JSON"):
        sd.Simulator(scene(dt=float("nan")))
    bad = tmp_path / "bad.json"
    bad.write_text("{ not json")
    with pytest.raises(sd.SceneError, match="bad.json: not valid JSON"):
        sd.Simulator(str(bad))
    with pytest.raises(sd.SceneError, match="missing.json"):
        sd.Simulator(str(tmp_path / "missing.json"))
    with pytest.raises(sd.BackendError):
        sd.Simulator(scene(), backend="banana")


def test_step_and_reset_errors():
    sim = sd.Simulator(scene())
    with pytest.raises(sd.ShapeError, match=r"tau has shape \(5, 6\), expected \(5, 7\)"):
        sim.step(np.zeros((5, 6)))
    with pytest.raises(sd.ShapeError, match=r"tau has shape \(7,\)"):
        sim.step(np.zeros(7))
    with pytest.raises(sd.DTypeError, match="float64"):
        sim.step(np.zeros((5, 7), np.float32))
    with pytest.raises(IndexError, match=r"instance 5 is outside \[0, 5\)"):
        sim.reset([0, 5])
    with pytest.raises(sd.ShapeError, match="mask"):
        sim.reset(np.array([True, False]))
    assert sim.steps == 0  # nothing stepped


def test_non_finite_state_raises_with_the_library_message():
    sim = sd.Simulator(scene())
    sim.qd[2, 3] = np.nan
    with pytest.raises(sd.SimulationError, match=r"after step 1 .*non-finite in 1 instance-step, first in "
                                                  r"instance 2: the state at DoF \d is not finite") as e:
        sim.step()
    assert isinstance(e.value, RuntimeError)
    assert sim.status() == (0, -1, -1, "")  # cleared after raising
    # without the check the failure stays recorded
    sim.step(check=False)
    failed, first, _, message = sim.status()
    assert failed == 1 and first == 2 and "instance 2" in message  # (q is NaN now: a pivot fails)
    sim.clear_status()
    assert sim.status()[0] == 0
    # a NaN position fails the forward dynamics: that instance keeps its state
    other = sd.Simulator(scene())
    other.q[1, 3] = np.nan
    before = other.qd[1].copy()
    with pytest.raises(sd.SimulationError, match=r"forward dynamics failed in 1 instance-step, first in instance 1: "
                                                  r"articulated inertia pivot at DoF \d is not positive"):
        other.step()
    assert np.array_equal(other.qd[1], before)


def test_torch_and_dlpack_views():
    torch = pytest.importorskip("torch", reason="torch is not installed (not needed in CI)")
    sim = sd.Simulator(scene(), arrays="torch")
    assert isinstance(sim.q, torch.Tensor) and sim.q.stride() == (1, 5) and sim.q.dtype == torch.float64
    raw = sd.Simulator(scene(), arrays="dlpack")
    t = torch.from_dlpack(raw.q)
    assert t.data_ptr() == torch.from_dlpack(raw.q).data_ptr() and torch.equal(t, sim.q)
    sim.q[0, 0] = 2.0  # a write through the tensor is the simulator's state
    assert sim._s.view(False, "numpy")[0, 0] == 2.0
    with pytest.raises(ValueError, match="arrays"):
        sd.Simulator(scene(), arrays="jax")


def test_torch_cpu_torques():
    torch = pytest.importorskip("torch", reason="torch is not installed (not needed in CI)")
    a, b = sd.Simulator(scene()), sd.Simulator(scene())
    tau = np.random.default_rng(4).uniform(-1, 1, (5, 7))
    a.step(tau)
    b.step(torch.from_numpy(tau))
    assert np.array_equal(a.q, b.q)


cuda = pytest.mark.skipif(not sd.has_cuda or sd.backend_unusable("cuda") != "",
                          reason="no usable CUDA device (or the CUDA backend is not built)")


@cuda
@pytest.mark.parametrize("model", ["rope:8", "iiwa"])
def test_cuda_state_is_torch_on_the_device_and_matches_serial(model):
    torch = pytest.importorskip("torch", reason="torch is not installed")
    # the rope's 1 cm links have inertias ~3e-7 kg m^2: explicit damping is stable for
    # dt d / I < 2, so the rope gets d = 1e-4 (iiwa keeps the scene's 0.5)
    effects = {"gravity": True, "damping": 0.5 if model == "iiwa" else 1e-4}
    gpu = sd.Simulator(scene(model=model, backend="cuda", instances=64, dt=1e-4, effects=effects))
    cpu = sd.Simulator(scene(model=model, backend="serial", instances=64, dt=1e-4, effects=effects))
    nv = cpu.nv
    assert isinstance(gpu.q, torch.Tensor) and gpu.q.is_cuda and gpu.q.shape == (64, nv)
    assert gpu.q.stride() == (1, 64) and gpu.device.startswith("cuda") and gpu.strategy == "fused-aba"
    ptr = gpu.q.data_ptr()
    scale = 3.0 if model == "iiwa" else 1e-4
    tau = np.random.default_rng(5).uniform(-scale, scale, (64, nv))
    s = torch.cuda.Stream()  # a stream other than the default
    with torch.cuda.stream(s):
        t = torch.from_numpy(tau).to("cuda", non_blocking=False)
        for _ in range(10):
            gpu.step(t)        # ordered after s's copy; s waits for the step
        q = gpu.q.clone()      # on s, after the steps
    s.synchronize()
    cpu.step_many(10, tau)
    assert gpu.q.data_ptr() == ptr
    # fused CUDA ABA vs the serial reference ABA: rounding, double
    np.testing.assert_allclose(q.cpu().numpy(), cpu.q, rtol=0, atol=1e-11)
    # writes through the tensor on torch's stream are seen by the next step
    gpu.q.fill_(0.0)
    gpu.qd.fill_(0.0)
    cpu.q[:] = 0.0
    cpu.qd[:] = 0.0
    gpu.step(torch.zeros(64, nv, dtype=torch.float64, device="cuda"))
    cpu.step()
    torch.cuda.synchronize()
    np.testing.assert_allclose(gpu.q.cpu().numpy(), cpu.q, rtol=0, atol=1e-12)
    # resets on the device: the scene's draws, as on the CPU
    gpu.reset([3])
    cpu.reset([3])
    np.testing.assert_array_equal(gpu.q[3].cpu().numpy(), cpu.q[3])
    with pytest.raises(sd.DeviceError):
        gpu.step(np.zeros((64, nv)))
    with pytest.raises(sd.DeviceError):
        cpu.step(torch.zeros(64, nv, dtype=torch.float64, device="cuda"))
    with pytest.raises(sd.DTypeError):
        gpu.step(torch.zeros(64, nv, dtype=torch.float32, device="cuda"))


def ball_scene(**kw):
    """The point mass (models/point_mass.urdf: a 1 kg ball of radius 0.1 on prismatic z, y,
    x) above the plane z = 0, critically damped contact, implicit at 1 ms; 3 instances."""
    m, k = 1 + 2e-6, 1e5
    s = {"model": os.path.join(ROOT, "models", "point_mass.urdf"), "dt": 1e-3, "integrator": "implicit",
         "backend": "serial", "instances": 3,
         "effects": {"gravity": True, "contacts": {
             "planes": [{"normal": [0, 0, 1], "offset": 0}],
             "points": [{"link": "ball", "radius": 0.1}, {"link": "ball", "position": [0, 0, 0.5]}],
             "stiffness": k, "damping": 2 * np.sqrt(k * m), "friction": 0.8}},
         "initial": {"q": [0.1, 0, 0], "qd": [-0.5, 0, 0]}}
    s.update(kw)
    return s


@pytest.mark.parametrize("precision", ["double", "float"])
def test_contact_forces_are_views_of_the_readings(precision):
    """At rest on the plane the ball's contact carries m g (closed form: the z carriages'
    2 mg included), its depth is m g / k; the point 0.5 m above touches nothing. The views
    are the simulator's memory: the same objects show every step's readings."""
    m, k, g = 1 + 2e-6, 1e5, 9.81
    sim = sd.Simulator(ball_scene(precision=precision))
    assert sim.num_contact_points == 2
    f, d, c = sim.contact_forces(), sim.contact_depths(), sim.in_contact()
    assert f.shape == (3, 2, 3) and d.shape == (3, 2) and c.shape == (3, 2)
    assert f.dtype == sim.dtype and d.dtype == sim.dtype and c.dtype == np.int32
    assert not f.any() and not c.any()  # before the first step
    sim.step_many(2000)  # 2 s: at rest
    rtol = 1e-9 if precision == "double" else 1e-4
    assert f is sim.contact_forces()
    np.testing.assert_allclose(f[:, 0, 2], m * g, rtol=rtol)
    np.testing.assert_allclose(f[:, 0, :2], 0, atol=rtol * m * g)
    np.testing.assert_allclose(d[:, 0], m * g / k, rtol=rtol)
    assert (c[:, 0] == 1).all() and (c[:, 1] == 0).all()
    assert not f[:, 1].any() and not d[:, 1].any()
    # the ball lifted clear of the plane: the next step's readings are zeros, in the same views
    sim.q[:, 0] = 1.0
    sim.qd[:, :] = 0
    sim.step()
    assert not f.any() and not d.any() and not c.any()


def test_contact_forces_without_contacts_and_through_torch():
    sim = sd.Simulator(scene())
    assert sim.num_contact_points == 0
    with pytest.raises(sd.ShapeError, match="declares no effects.contacts"):
        sim.contact_forces()
    torch = pytest.importorskip("torch", reason="torch is not installed (not needed in CI)")
    a = sd.Simulator(ball_scene(), arrays="torch")
    a.step_many(50)
    b = sd.Simulator(ball_scene())
    b.step_many(50)
    t = a.contact_forces()
    assert isinstance(t, torch.Tensor) and t.stride() == (10, 5, 1)
    assert np.array_equal(t.numpy(), b.contact_forces())
    assert np.array_equal(a.in_contact().numpy(), b.in_contact())


@cuda
def test_cuda_contact_forces_are_device_views_matching_serial():
    """On cuda the readings are torch tensors over the device memory; after 200 steps of the
    resting ball (double) they equal the serial simulator's to rounding."""
    torch = pytest.importorskip("torch", reason="torch is not installed")
    gpu = sd.Simulator(ball_scene(backend="cuda"))
    cpu = sd.Simulator(ball_scene())
    gpu.step_many(200)
    cpu.step_many(200)
    f = gpu.contact_forces()
    assert isinstance(f, torch.Tensor) and f.device.type == "cuda" and f.shape == (3, 2, 3)
    torch.cuda.current_stream(gpu._s.device).synchronize()
    np.testing.assert_allclose(f.cpu().numpy(), cpu.contact_forces(), rtol=1e-9, atol=1e-9)
    assert torch.equal(gpu.in_contact().cpu(), torch.from_numpy(cpu.in_contact().copy()))
